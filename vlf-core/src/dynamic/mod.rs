//! Dynamic objects: meshes that move through a propagated field, lit by it.
//!
//! The field was propagated for the static scene; an object that moves in a walkthrough is
//! not part of it. What the object looks like is light the field already holds: every point of
//! the object receives, along each direction, the radiance the static scene sends toward it,
//! and reflects a fraction ρd of what arrives ([`gather`]). Objects are rigid ([`Pose`]: a
//! rotation then a translation, in the scene's own coordinates, as the user placed the scene),
//! need no emitter, and block their own gather and each other's.
//!
//! This module holds the library side, each piece readable as its formula: placing objects
//! (this file), gathering light at their points ([`gather`]), the shadows they cast on the
//! static scene ([`shadow`]), what they read of the field ([`needs`]), and drawing a view with
//! them on the CPU ([`view`]), the reference the viewer's GPU version is held to.

pub mod gather;
pub mod needs;
pub mod shadow;
pub mod view;

use crate::render::Bvh;
use crate::scene::{FaceOrigin, Material, Normalisation, Scene, Surface};
use glam::{DQuat, DVec3};

/// A rigid motion in scene coordinates: `x ↦ rotation · x + translation`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub rotation: DQuat,
    pub translation: DVec3,
}

impl Pose {
    pub const IDENTITY: Pose = Pose {
        rotation: DQuat::IDENTITY,
        translation: DVec3::ZERO,
    };

    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.rotation * p + self.translation
    }
}

/// A moving object: triangles in its own coordinates (scene units), each with its material.
#[derive(Clone, Debug, PartialEq)]
pub struct DynamicObject {
    pub name: String,
    pub triangles: Vec<[DVec3; 3]>,
    /// Index into `materials` of every triangle.
    pub material_of: Vec<u32>,
    pub materials: Vec<Material>,
}

/// Why an object cannot be placed.
#[derive(Debug, thiserror::Error)]
pub enum ObjectError {
    #[error("object '{name}': {message}")]
    Invalid { name: String, message: String },
    #[error(transparent)]
    Import(#[from] crate::Error),
}

impl DynamicObject {
    /// An object of one material.
    pub fn uniform(name: &str, triangles: Vec<[DVec3; 3]>, material: Material) -> Self {
        DynamicObject {
            name: name.to_string(),
            material_of: vec![0; triangles.len()],
            triangles,
            materials: vec![material],
        }
    }

    /// A cube of half-size `half` around `center` (scene units), each face split into
    /// `split × split` squares of two triangles, facing out, of one material: the test and
    /// benchmark object.
    pub fn cube(name: &str, center: DVec3, half: f64, split: usize, material: Material) -> Self {
        let split = split.max(1);
        let step = 2.0 * half / split as f64;
        let mut triangles = Vec::with_capacity(12 * split * split);
        for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
            let u = axis.any_orthonormal_vector();
            let v = axis.cross(u);
            // (u, v) and (v, u) are both right-handed about their face's outward normal.
            for (n, a, b) in [(axis, u, v), (-axis, v, u)] {
                let at =
                    |x: usize, y: usize| center + (n - a - b) * half + a * (x as f64 * step) + b * (y as f64 * step);
                for i in 0..split {
                    for j in 0..split {
                        let (p0, p1, p2, p3) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
                        triangles.push([p0, p1, p2]);
                        triangles.push([p0, p2, p3]);
                    }
                }
            }
        }
        DynamicObject::uniform(name, triangles, material)
    }

    /// Reads an object from a scene file (OBJ with its MTL, or glTF), in the file's own
    /// coordinates, which are the scene's: place it with the static scene's normalisation
    /// ([`DynamicObject::place`]), not one of its own. It needs no emitter. Faces are split into
    /// triangles as the importer splits them (convex pieces, bent faces). Returns the object
    /// and the importer's warnings.
    ///
    /// An object's material has one ρd (its gather is shaded per point without texture
    /// coordinates), so an albedo texture is averaged into it, with a warning: a glTF base colour
    /// factor of 1 with a texture would otherwise gather as a white object.
    pub fn load(path: &std::path::Path) -> Result<(DynamicObject, Vec<String>), ObjectError> {
        let options = crate::scene::ImportOptions {
            object: true,
            ..Default::default()
        };
        let (mut scene, mut warnings) = crate::scene::load_scene(path, &options)?;
        for m in &mut scene.materials {
            let Some(t) = m.albedo_texture.take() else {
                continue;
            };
            let Some(texture) = scene.textures.get(t as usize) else {
                return Err(ObjectError::Invalid {
                    name: path.display().to_string(),
                    message: format!("material '{}' names texture {t}, which the file does not have", m.name),
                });
            };
            let mean = texture.mean();
            m.diffuse = [0, 1, 2].map(|c| m.diffuse[c] * mean[c]);
            warnings.push(format!(
                "material '{}': its albedo texture is averaged over the object (ρd = {:.3} {:.3} {:.3}): a \
                 dynamic object has one reflectance per material",
                m.name, m.diffuse[0], m.diffuse[1], m.diffuse[2]
            ));
        }
        let n = scene.normalisation;
        let (mut triangles, mut material_of) = (Vec::new(), Vec::new());
        for s in &scene.surfaces {
            let v: Vec<DVec3> = s.vertices.iter().map(|&p| n.to_scene(p)).collect();
            for k in 1..v.len() - 1 {
                triangles.push([v[0], v[k], v[k + 1]]);
                material_of.push(s.material as u32);
            }
        }
        let name = path
            .file_name()
            .map_or_else(|| path.display().to_string(), |f| f.to_string_lossy().into_owned());
        let object = DynamicObject {
            name,
            triangles,
            material_of,
            materials: scene.materials,
        };
        object.validate()?;
        Ok((object, warnings))
    }

    /// Checks what the gather relies on: finite vertices, at least one triangle with area, a
    /// physical, non-emitting material (an object is lit by the field; its own light would
    /// not be in it).
    pub fn validate(&self) -> Result<(), ObjectError> {
        let bad = |message: String| ObjectError::Invalid {
            name: self.name.clone(),
            message,
        };
        if let Some(k) = self.triangles.iter().position(|t| !t.iter().all(|p| p.is_finite())) {
            return Err(bad(format!("triangle {k} has a non-finite vertex")));
        }
        if !self
            .triangles
            .iter()
            .any(|t| (t[1] - t[0]).cross(t[2] - t[0]).length() > 0.0)
        {
            return Err(bad("no triangle has an area".into()));
        }
        if self.material_of.len() != self.triangles.len() {
            return Err(bad(format!(
                "{} material indices for {} triangles",
                self.material_of.len(),
                self.triangles.len()
            )));
        }
        if let Some(k) = self
            .material_of
            .iter()
            .position(|&m| m as usize >= self.materials.len())
        {
            return Err(bad(format!("triangle {k} names a missing material")));
        }
        let unit = |c: f64| c.is_finite() && (0.0..=1.0).contains(&c);
        for m in &self.materials {
            if !m.diffuse.iter().chain(&m.specular).all(|&c| unit(c))
                || (0..3).any(|c| m.diffuse[c] + m.specular[c] > 1.0)
            {
                return Err(bad(format!(
                    "material '{}' is not physical (ρd + ρs ≤ 1 per channel)",
                    m.name
                )));
            }
            if m.is_emitter() {
                return Err(bad(format!(
                    "material '{}' emits: a dynamic object is lit by the field and cannot add light to it",
                    m.name
                )));
            }
        }
        Ok(())
    }

    /// The object at `pose`, in the field's frame (`normalisation` is the static scene's):
    /// its triangles as surfaces (degenerate ones dropped) and a BVH over them.
    pub fn place(&self, pose: &Pose, normalisation: &Normalisation) -> Result<PlacedObject, ObjectError> {
        self.validate()?;
        let surfaces: Vec<Surface> = (self.triangles.iter().enumerate())
            .filter_map(|(k, t)| {
                let vertices: Vec<DVec3> = t.iter().map(|&p| normalisation.to_vlf(pose.apply(p))).collect();
                Surface::from_vertices(vertices, self.material_of[k] as usize, FaceOrigin { line: 0, face: k })
            })
            .collect();
        let scene = Scene {
            surfaces,
            materials: self.materials.clone(),
            normalisation: *normalisation,
            textures: Vec::new(),
        };
        let bvh = Bvh::build(&scene);
        let (lo, hi) = (scene.surfaces.iter().flat_map(|s| &s.vertices))
            .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let center = (lo + hi) * 0.5;
        let radius = (scene.surfaces.iter().flat_map(|s| &s.vertices))
            .map(|v| v.distance(center))
            .fold(0.0, f64::max);
        Ok(PlacedObject {
            name: self.name.clone(),
            scene,
            bvh,
            center,
            radius,
        })
    }
}

/// An object at one pose, in the field's frame: its surfaces (as a scene of their own, with
/// the object's materials), a BVH over them and a sphere that bounds them.
#[derive(Clone, Debug)]
pub struct PlacedObject {
    pub name: String,
    pub scene: Scene,
    pub bvh: Bvh,
    /// Centre and radius of a sphere holding every vertex (VLF frame): the cone a static
    /// point sees the object in ([`shadow`]).
    pub center: DVec3,
    pub radius: f64,
}

/// How far (VLF frame) an object may cross a static surface before it is said to intersect
/// it: an object resting on a floor touches it without crossing.
const CONTACT_TOLERANCE: f64 = 1e-6;

impl PlacedObject {
    /// The object's nearest hit along the ray from `origin` along unit `dir` before `t_max`,
    /// skipping its BVH where the ray misses the bounding sphere (most rays of a view).
    pub fn intersect(&self, origin: DVec3, dir: DVec3, t_max: f64) -> Option<crate::render::Hit> {
        let to = self.center - origin;
        let along = to.dot(dir);
        let r2 = self.radius * self.radius * (1.0 + 1e-9) + 1e-18;
        if to.length_squared() - along * along > r2 || (along < 0.0 && to.length_squared() > r2) {
            return None;
        }
        self.bvh.intersect(&self.scene, origin, dir, 0.0, t_max)
    }

    /// Checks that the object lies inside the field (the VLF frame's cube `[−1, 1]³`, where
    /// the static scene is) and crosses no static surface: light the field carries through the
    /// object's volume, and surfaces inside it, would be wrong on both sides. Touching is
    /// allowed. An edge of one triangle crossing the other (either way round) finds every
    /// crossing of two triangles.
    pub fn check_clear(&self, scene: &Scene, bvh: &Bvh) -> Result<(), ObjectError> {
        let bad = |message: String| ObjectError::Invalid {
            name: self.name.clone(),
            message,
        };
        let inside = |v: &DVec3| v.abs().max_element() <= 1.0 + CONTACT_TOLERANCE;
        if !self.scene.surfaces.iter().flat_map(|s| &s.vertices).all(inside) {
            return Err(bad(
                "lies outside the scene's bounds, where the field holds no light (move it inside)".into(),
            ));
        }
        let crossing = |a: DVec3, b: DVec3, scene: &Scene, bvh: &Bvh| {
            let length = a.distance(b);
            length > 2.0 * CONTACT_TOLERANCE
                && bvh
                    .intersect(
                        scene,
                        a,
                        (b - a) / length,
                        CONTACT_TOLERANCE,
                        length - CONTACT_TOLERANCE,
                    )
                    .is_some_and(|h| {
                        // A crossing, not an edge that ends on the surface within the tolerance.
                        let n = scene.surfaces[h.surface].normal;
                        let (da, db) = ((a - h.point).dot(n), (b - h.point).dot(n));
                        da.abs() > CONTACT_TOLERANCE && db.abs() > CONTACT_TOLERANCE && da * db < 0.0
                    })
        };
        let edges = |s: &Surface| {
            let v = s.vertices.clone();
            (0..v.len()).map(move |k| (v[k], v[(k + 1) % v.len()]))
        };
        let (lo, hi) = (
            self.center - DVec3::splat(self.radius),
            self.center + DVec3::splat(self.radius),
        );
        for s in &self.scene.surfaces {
            for (a, b) in edges(s) {
                if crossing(a, b, scene, bvh) {
                    return Err(bad("crosses a surface of the static scene (move it clear)".into()));
                }
            }
        }
        for s in &scene.surfaces {
            let near = s
                .vertices
                .iter()
                .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(l, h), &v| {
                    (l.min(v), h.max(v))
                });
            if near.0.cmple(hi).all() && near.1.cmpge(lo).all() {
                for (a, b) in edges(s) {
                    if crossing(a, b, &self.scene, &self.bvh) {
                        return Err(bad("crosses a surface of the static scene (move it clear)".into()));
                    }
                }
            }
        }
        Ok(())
    }
}
