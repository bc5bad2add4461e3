//! Dynamic objects: meshes that move through a propagated field, lit by it.
//!
//! The field was propagated for the static scene; an object that moves in a walkthrough is
//! not part of it. What the object looks like is light the field already holds: every point of
//! the object receives, along each direction, the radiance the static scene sends toward it,
//! and reflects a fraction ρd of what arrives ([`gather`]). Objects are rigid ([`Pose`]: a
//! rotation then a translation, in the scene's own coordinates, as the user placed the scene),
//! need no emitter, and block their own gather and each other's.
//!
//! This module holds the library side: placing objects, gathering light at their points,
//! and drawing a view with them on the CPU ([`view`]).
//! What is left for the client (drawing objects in the viewer, shadows that objects cast on
//! the static scene, objects seen in mirrors, streaming what the gather needs) is listed in
//! the issue that asks for them.

pub mod gather;
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

    /// Reads an object from a scene file (OBJ with its MTL, or glTF), in the file's own
    /// coordinates, which are the scene's: place it with the static scene's normalisation
    /// ([`DynamicObject::place`]), not one of its own. It needs no emitter. Faces are split into
    /// triangles as the importer splits them (convex pieces, bent faces). Returns the object
    /// and the importer's warnings.
    pub fn load(path: &std::path::Path) -> Result<(DynamicObject, Vec<String>), ObjectError> {
        let options = crate::scene::ImportOptions {
            object: true,
            ..Default::default()
        };
        let (scene, warnings) = crate::scene::load_scene(path, &options)?;
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
        Ok(PlacedObject { scene, bvh })
    }
}

/// An object at one pose, in the field's frame: its surfaces (as a scene of their own, with
/// the object's materials) and a BVH over them.
#[derive(Clone, Debug)]
pub struct PlacedObject {
    pub scene: Scene,
    pub bvh: Bvh,
}
