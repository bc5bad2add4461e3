//! The scene: planar, one-sided polygons with ideal diffuse / ideal mirror
//! materials and isotropic emission, normalised into the VLF frame.
//!
//! Everything in [`Scene`] lives in the **VLF frame**: the scene's bounding
//! sphere is mapped onto the unit sphere, so that every parallel subfield
//! (an `N × N` ray grid over the square `[-1, 1]²` perpendicular to its
//! direction) covers the whole scene whatever the direction. Cameras and
//! images stay in the scene's own units; [`Normalisation`] converts between
//! the two. Radiance and radiosity are invariant under this similarity (only
//! powers scale, by `scale²`), so no photometric quantity is rescaled.
//!
//! Files are read by one module per format (`obj.rs`: Wavefront OBJ + MTL;
//! `gltf/`: glTF 2.0, `.gltf` and `.glb`), chosen by [`load_scene`]; each
//! turns its file into polygons and materials, and `build.rs` validates,
//! splits (non-convex faces into convex pieces, non-planar ones into
//! triangles: `bent.rs`, geometry in `polygon.rs`) and normalises them,
//! the same for every format and for [`Scene::from_polygons`].

mod bent;
mod build;
mod gltf;
mod obj;
mod polygon;
pub mod texture;
mod weld;

pub use self::gltf::{gltf_external_files, load_gltf};
pub use build::{ImportOptions, MAX_FACES, MAX_LISTED_WARNINGS, MAX_MIRROR_REFLECTANCE};
pub use obj::load_obj;
pub use polygon::{PolygonError, convex_pieces, newell_normal};
pub use texture::{Texture, UvMap, Wrap};

use std::path::Path;

use glam::DVec3;
use serde::{Deserialize, Serialize};

/// The scene file formats, by extension (case-insensitive): what
/// [`load_scene`] reads.
pub const SCENE_EXTENSIONS: &[&str] = &["obj", "gltf", "glb"];

/// Reads a scene file of any supported format, chosen by its extension:
/// `.obj` ([`load_obj`], with its MTL libraries), `.gltf` or `.glb`
/// ([`load_gltf`]). Every format goes through the same validation and
/// normalisation, so the result and its warnings mean the same whatever the
/// source. Another extension is an error that names the supported ones.
pub fn load_scene(path: &Path, options: &ImportOptions) -> Result<(Scene, Vec<String>), crate::Error> {
    let extension = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match extension.as_str() {
        "obj" => load_obj(path, options),
        "gltf" | "glb" => load_gltf(path, options),
        _ => Err(crate::Error::scene(
            &path.display().to_string(),
            None,
            format!(
                "unknown scene format {}: supported are {}",
                if extension.is_empty() {
                    "(no extension)".to_string()
                } else {
                    format!("'.{extension}'")
                },
                SCENE_EXTENSIONS
                    .iter()
                    .map(|e| format!(".{e}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        )),
    }
}

/// RGB triple used for reflectances and radiances (linear, per channel).
pub type Rgb = [f64; 3];

/// A material, following the conventions of `docs/scenes.md`:
/// `Kd` = ρd, `Ke` = emitted radiance, `illum 3` = ideal mirror with ρs = `Ks`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Material {
    pub name: String,
    /// Ideal diffuse reflectance ρd per channel, in `[0, 1]`.
    pub diffuse: Rgb,
    /// Ideal mirror reflectance ρs per channel (zero unless `illum 3`).
    pub specular: Rgb,
    /// Emitted radiance `Le` (W·sr⁻¹·m⁻²) from the front side, isotropic.
    pub emission: Rgb,
    /// An albedo texture ([`Scene::textures`]) that multiplies `diffuse` where the surface's
    /// [`Surface::uv`] places it (see [`texture`]).
    pub albedo_texture: Option<u32>,
}

impl Material {
    /// A grey diffuse material of reflectance `rho`: no mirror, no emission, no texture (the
    /// objects of tests and benchmarks).
    pub fn grey(name: &str, rho: f64) -> Material {
        Material {
            name: name.into(),
            diffuse: [rho; 3],
            specular: [0.0; 3],
            emission: [0.0; 3],
            albedo_texture: None,
        }
    }

    pub fn is_emitter(&self) -> bool {
        self.emission.iter().any(|&e| e > 0.0)
    }
    pub fn is_mirror(&self) -> bool {
        self.specular.iter().any(|&s| s > 0.0)
    }
    pub fn is_diffuse(&self) -> bool {
        self.diffuse.iter().any(|&d| d > 0.0)
    }
}

/// Where a surface came from in the input, for error messages and tooling.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FaceOrigin {
    /// 1-based line of the `f` statement in the OBJ file (0 if generated,
    /// or for formats without lines, such as glTF).
    pub line: usize,
    /// 0-based index of the face among all faces of the file (for glTF, of
    /// the triangle among all triangles read).
    pub face: usize,
}

/// Vertices closer than this (VLF frame) are one vertex wherever polygons are matched up by
/// their corners (T-junctions, charts, subfield outlines). Importers keep shared corners
/// bit-identical up to the rounding of flattening a face onto its plane (≈1e-16), far below it,
/// and the frame spans 2, so distinct vertices of any real scene are far above it.
pub const VERTEX_QUANTUM: f64 = 1.0 / (1u64 << 32) as f64;

/// The key under which nearly coincident vertices (within [`VERTEX_QUANTUM`]) are one vertex.
pub fn vertex_key(p: DVec3) -> [i64; 3] {
    let q = |x: f64| (x / VERTEX_QUANTUM).round() as i64;
    [q(p.x), q(p.y), q(p.z)]
}

/// One planar **convex** polygon, counter-clockwise about its front normal.
///
/// Non-convex input polygons are split into convex pieces by the importer, so
/// that every surface crosses each ray row of a subfield in at most one span.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Surface {
    /// Vertices in the VLF frame, counter-clockwise seen from the front.
    pub vertices: Vec<DVec3>,
    /// Unit front normal (right-hand rule over `vertices`).
    pub normal: DVec3,
    /// Plane offset: `normal · x = offset` for every point `x` of the polygon.
    pub offset: f64,
    /// Area in the VLF frame.
    pub area: f64,
    /// Index into [`Scene::materials`].
    pub material: usize,
    pub origin: FaceOrigin,
    /// Texture coordinates over the surface, where its material has an albedo texture.
    pub uv: Option<UvMap>,
}

/// The similarity that maps scene units into the VLF frame:
/// `x_vlf = (x_scene - center) * scale`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Normalisation {
    pub center: DVec3,
    pub scale: f64,
}

impl Normalisation {
    pub fn to_vlf(&self, p: DVec3) -> DVec3 {
        (p - self.center) * self.scale
    }
    pub fn to_scene(&self, p: DVec3) -> DVec3 {
        p / self.scale + self.center
    }
}

/// A validated scene in the VLF frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    pub surfaces: Vec<Surface>,
    pub materials: Vec<Material>,
    pub normalisation: Normalisation,
    /// Albedo textures, named by [`Material::albedo_texture`].
    pub textures: Vec<Texture>,
}

impl Surface {
    /// A planar convex polygon in the VLF frame, its normal, offset and area taken from its
    /// Newell normal; `None` if it has no area. (The importers build their surfaces through
    /// their own validation; this is for surfaces made in code, such as a placed object's.)
    pub fn from_vertices(vertices: Vec<DVec3>, material: usize, origin: FaceOrigin) -> Option<Surface> {
        let n = newell_normal(&vertices);
        (n.length() > 0.0).then(|| {
            let normal = n.normalize();
            Surface {
                offset: normal.dot(vertices[0]),
                area: n.length() / 2.0,
                normal,
                vertices,
                material,
                origin,
                uv: None,
            }
        })
    }
}

impl Scene {
    pub fn material(&self, surface: usize) -> &Material {
        &self.materials[self.surfaces[surface].material]
    }

    /// Diffuse reflectance ρd of `surface` at its point `p`: the material's, times its albedo
    /// texture where the surface's texture coordinates place `p` (the texture's mean where the
    /// surface has none).
    pub fn albedo_at(&self, surface: usize, p: DVec3) -> Rgb {
        let m = self.material(surface);
        let Some(t) = m.albedo_texture.and_then(|t| self.textures.get(t as usize)) else {
            return m.diffuse;
        };
        let c = match &self.surfaces[surface].uv {
            Some(map) => t.sample(map.at(p)),
            None => t.mean(),
        };
        [m.diffuse[0] * c[0], m.diffuse[1] * c[1], m.diffuse[2] * c[2]]
    }

    /// Radius of the bounding sphere in the VLF frame: every vertex lies
    /// within it. The importer makes it slightly below 1 so that rays at the
    /// border of a subfield still cover the scene.
    pub const FRAME_RADIUS: f64 = 0.999;

    /// Builds a scene from polygons given in scene units (each a list of
    /// vertices, counter-clockwise about the front normal), normalising it
    /// into the VLF frame. This is the mechanism behind the importers and
    /// the programmatic test scenes alike: it validates, splits non-convex
    /// polygons into convex pieces and bent ones into triangles, and skips
    /// degenerate ones (both returned as warnings).
    pub fn from_polygons(
        polygons: &[(Vec<DVec3>, usize, FaceOrigin)],
        materials: Vec<Material>,
        options: &ImportOptions,
    ) -> Result<(Scene, Vec<String>), crate::Error> {
        build::build_scene(polygons, materials, options, "<generated>")
    }

    /// The scene as bytes (bincode), for storage: the exact normalised
    /// scene, so a propagation resumed or rebuilt from it has the same bits.
    pub fn to_bytes(&self) -> Vec<u8> {
        bincode::serialize(self).expect("bincode into memory cannot fail for plain data")
    }

    /// Decodes [`Scene::to_bytes`], checking what propagation relies on:
    /// materials exist and are physical, coordinates are finite and within the unit ball (every
    /// subfield's grid spans it, and the texel grids are sized by it), normals are unit, at
    /// least one surface.
    pub fn from_bytes(bytes: &[u8]) -> crate::Result<Scene> {
        let bad = |m: String| crate::Error::Decode(format!("stored scene: {m}"));
        let scene: Scene = bincode::deserialize(bytes).map_err(|e| bad(e.to_string()))?;
        if scene.surfaces.is_empty() {
            return Err(bad("no surface".into()));
        }
        let unit = |c: f64| c.is_finite() && (0.0..=1.0).contains(&c);
        for (i, m) in scene.materials.iter().enumerate() {
            if !m.diffuse.iter().chain(&m.specular).all(|&c| unit(c))
                || !m.emission.iter().all(|&c| c.is_finite() && c >= 0.0)
            {
                return Err(bad(format!("material {i} (`{}`) is not physical", m.name)));
            }
            if m.albedo_texture.is_some_and(|t| t as usize >= scene.textures.len()) {
                return Err(bad(format!("material {i} (`{}`) names a missing texture", m.name)));
            }
        }
        for t in &scene.textures {
            t.validate().map_err(bad)?;
        }
        for (i, s) in scene.surfaces.iter().enumerate() {
            let finite = s.vertices.iter().all(|v| v.is_finite())
                && s.offset.is_finite()
                && s.area.is_finite()
                && s.uv.is_none_or(|m| m.is_finite());
            if s.material >= scene.materials.len()
                || s.vertices.len() < 3
                || !finite
                || (s.normal.length() - 1.0).abs() > 1e-6
            {
                return Err(bad(format!("surface {i} is malformed")));
            }
            // Normalised within `FRAME_RADIUS`; the unit ball leaves room for rounding (a
            // T-junction's split puts vertices on edges, convex combinations of the corners).
            if let Some(v) = s.vertices.iter().find(|v| v.length() > 1.0) {
                return Err(bad(format!(
                    "surface {i} has a vertex {v} outside the scene's frame (the unit ball)"
                )));
            }
        }
        let n = &scene.normalisation;
        if !(n.scale.is_finite() && n.scale > 0.0 && n.center.is_finite()) {
            return Err(bad("bad normalisation".into()));
        }
        Ok(scene)
    }

    /// SHA-256 of [`Scene::to_bytes`], lower-case hex: identifies a scene in
    /// a store (two jobs of the same scene have the same hash).
    pub fn content_hash(&self) -> String {
        use sha2::Digest;
        let digest = sha2::Sha256::digest(self.to_bytes());
        digest.iter().map(|b| format!("{b:02x}")).collect()
    }
}
