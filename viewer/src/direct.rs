//! Exact direct light on the GPU: the twin of `vlf_core::direct`.
//!
//! A diffuse point seen by the camera sends `L − D + ρd/π·E(p)` (see `vlf_core::direct`): `L`
//! the field's radiance, `D` its direct part (snapshot 1's radiance less the surfaces' own
//! emission, per texel), `E(p)` the irradiance straight from the emitters, summed per fragment
//! over their quadrature points with one shadow ray each through the scene's BVH
//! (`direct_irradiance` in `shaders/field.wgsl`). The quadrature points are the CPU's, so
//! the two renderers differ by f32 rounding only.
//!
//! **`D` is more parts.** The direct map of diffuse chunk `c` is part `catalog.len() + c` of the
//! renderer's part table ([`DirectParts`]): it lives in the same pool as the radiance, is
//! fetched, kept resident and evicted like any other part (a streaming viewer fetches it from
//! snapshot 1 next to the chunk itself), and a surface whose direct part is not resident yet
//! shows the field's own direct light, as a mirror whose tiles are missing is traced. One
//! mechanism, no second pool: the cache's size covers both.

use crate::{PartSource, ViewerError};
use glam::DVec3;
use std::sync::Arc;
use vlf_core::direct::Emitters;
use vlf_core::field::LightField;
use vlf_core::parts::PartCatalog;
use vlf_core::scene::Scene;

/// Where the direct parts sit in a renderer's part table: after the field's own parts, one per
/// diffuse chunk, in chunk order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DirectParts {
    /// The part number of chunk 0's direct part (the field's part count).
    pub first: u32,
    /// Diffuse chunks, hence direct parts.
    pub chunks: u32,
}

impl DirectParts {
    pub fn new(catalog: &PartCatalog) -> DirectParts {
        DirectParts {
            first: catalog.len() as u32,
            chunks: catalog.chunks() as u32,
        }
    }

    /// The direct part of chunk `chunk`.
    pub fn of_chunk(&self, chunk: u32) -> u32 {
        self.first + chunk
    }

    /// The chunk whose direct part `part` is, `None` for the field's own parts.
    pub fn chunk(&self, part: u32) -> Option<u32> {
        part.checked_sub(self.first).filter(|&c| c < self.chunks)
    }

    /// Parts of the table: the field's and the direct ones.
    pub fn table_len(&self) -> usize {
        (self.first + self.chunks) as usize
    }
}

/// The emitters' quadrature points as `shaders/field.wgsl` reads them (`emitter_points`,
/// `emitter_groups`): per point its position and power; per emitting surface its centroid and
/// area, normal and index, emission and point count, and first point.
#[derive(Default)]
pub(crate) struct EmitterBuffers {
    pub points: Vec<[f32; 4]>,
    pub groups: Vec<[u32; 4]>,
}

impl EmitterBuffers {
    pub fn new(scene: &Scene, emitters: &Emitters) -> EmitterBuffers {
        let mut out = EmitterBuffers::default();
        let points: Vec<_> = emitters.points().collect();
        for group in points.chunk_by(|a, b| a.3 == b.3) {
            let (surface, first) = (group[0].3, out.points.len() / 2);
            let s = &scene.surfaces[surface];
            let centroid = s.vertices.iter().sum::<DVec3>() / s.vertices.len() as f64;
            let emission = scene.material(surface).emission.map(|c| c as f32);
            let bits = |v: glam::Vec3| v.to_array().map(f32::to_bits);
            let [cx, cy, cz] = bits(centroid.as_vec3());
            let [nx, ny, nz] = bits(s.normal.as_vec3());
            let [ex, ey, ez] = emission.map(f32::to_bits);
            out.groups.extend([
                [cx, cy, cz, (s.area as f32).to_bits()],
                [nx, ny, nz, surface as u32],
                [ex, ey, ez, group.len() as u32],
                [first as u32, 0, 0, 0],
            ]);
            for &(point, _, power, _) in group {
                out.points.push(point.as_vec3().extend(0.0).to_array());
                out.points
                    .push([power[0] as f32, power[1] as f32, power[2] as f32, 0.0]);
            }
        }
        out
    }

    /// Emitting surfaces.
    pub fn group_count(&self) -> u32 {
        (self.groups.len() / 4) as u32
    }
}

/// Why `scene` cannot be drawn with exact direct light on the GPU, if it cannot: the shader's
/// `ρd` is the material's, so albedo textures (which the CPU reads per point) are refused
/// rather than drawn wrong.
pub fn check_scene(scene: &Scene) -> Result<(), ViewerError> {
    match textured_material(scene) {
        Some(name) => Err(ViewerError::Unsupported(format!(
            "exact direct light on the GPU reads each material's ρd, and material {name:?} has an albedo \
             texture: render on the CPU (drop --gpu) or take the field's direct light (--direct field)"
        ))),
        None => Ok(()),
    }
}

/// Why dynamic objects cannot be drawn in `scene` on the GPU, if they cannot: the shadows they
/// cast scale with the static surface's `ρd`, which the shaders take per material, where the
/// CPU reads an albedo texture per point (`Scene::albedo_at`). A textured scene is refused
/// rather than shadowed wrong (a mean per material would be wrong wherever the texture is not
/// flat, and the CPU renders it right).
pub fn check_scene_for_objects(scene: &Scene) -> Result<(), ViewerError> {
    match textured_material(scene) {
        Some(name) => Err(ViewerError::Unsupported(format!(
            "dynamic objects' shadows on the GPU read each material's ρd, and material {name:?} of the \
             static scene has an albedo texture: render the objects on the CPU (drop --gpu)"
        ))),
        None => Ok(()),
    }
}

/// The name of the first material with an albedo texture that a surface of `scene` uses.
fn textured_material(scene: &Scene) -> Option<&str> {
    (0..scene.surfaces.len())
        .map(|s| scene.material(s))
        .find(|m| m.albedo_texture.is_some())
        .map(|m| m.name.as_str())
}

/// A [`PartSource`] that serves the direct parts too: the field's own parts from `field`, and
/// the direct part of chunk `c` from `first` (the same job's snapshot 1) as its chunk `c` less
/// the surfaces' own emission ([`LightField::remove_emission`]). What a streaming viewer with
/// exact direct light reads from.
pub struct DirectSource {
    field: Box<dyn PartSource>,
    first: Box<dyn PartSource>,
    geometry: Arc<LightField>,
    catalog: PartCatalog,
    direct: DirectParts,
}

impl DirectSource {
    /// `geometry` is the job's field without radiance (any stage's).
    pub fn new(field: Box<dyn PartSource>, first: Box<dyn PartSource>, geometry: Arc<LightField>) -> DirectSource {
        let catalog = PartCatalog::new(&geometry);
        DirectSource {
            direct: DirectParts::new(&catalog),
            field,
            first,
            geometry,
            catalog,
        }
    }
}

impl PartSource for DirectSource {
    fn fetch(&mut self, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>, String> {
        let chunks: Vec<u32> = parts.iter().filter_map(|&p| self.direct.chunk(p)).collect();
        let own: Vec<u32> = parts
            .iter()
            .copied()
            .filter(|&p| self.direct.chunk(p).is_none())
            .collect();
        let mut own = self.field.fetch(&own)?.into_iter();
        let mut direct = self.first.fetch(&chunks)?.into_iter().zip(&chunks);
        parts
            .iter()
            .map(|&p| {
                let values = match self.direct.chunk(p) {
                    None => own.next(),
                    Some(_) => direct.next().map(|(mut values, &c)| {
                        let start = self.catalog.range(c).start;
                        if values.len() == self.catalog.values(c) {
                            self.geometry.remove_emission(start, &mut values);
                        }
                        values
                    }),
                };
                values.ok_or_else(|| format!("the source gave fewer parts than the {} asked for", parts.len()))
            })
            .collect()
    }

    fn bytes(&self) -> u64 {
        self.field.bytes() + self.first.bytes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn direct_parts_follow_the_fields_and_map_back_to_their_chunks() {
        let parts = DirectParts { first: 7, chunks: 3 };
        assert_eq!(parts.of_chunk(0), 7);
        assert_eq!(parts.chunk(9), Some(2));
        assert_eq!(parts.chunk(6), None);
        assert_eq!(parts.chunk(10), None);
        assert_eq!(parts.table_len(), 10);
    }

    #[test]
    fn albedo_textures_are_refused_by_name() {
        use vlf_core::scene::{FaceOrigin, ImportOptions, Material};
        let square = |z: f64| {
            let v = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)].map(|(x, y)| DVec3::new(x, y, z));
            if z > 0.0 {
                v.into_iter().rev().collect()
            } else {
                v.to_vec()
            }
        };
        let material = |name: &str, emission: f64| Material {
            emission: [emission; 3],
            ..Material::grey(name, 0.5)
        };
        let polygons = [
            (square(0.0), 0, FaceOrigin { line: 0, face: 0 }),
            (square(1.0), 1, FaceOrigin { line: 0, face: 1 }),
        ];
        let materials = vec![material("brick", 0.0), material("lamp", 1.0)];
        let (mut scene, _) = Scene::from_polygons(&polygons, materials, &ImportOptions::default()).unwrap();
        assert!(check_scene(&scene).is_ok());
        scene.materials[0].albedo_texture = Some(0);
        let e = check_scene(&scene).unwrap_err().to_string();
        assert!(e.contains("\"brick\"") && e.contains("albedo texture"), "{e}");
    }
}
