//! The dynamic-object flags `render` and `view` share, and reading the objects they name.

use crate::parse_vec3_arg;
use anyhow::{Context, Result, bail};
use clap::Args;
use glam::{DQuat, DVec3};
use std::path::PathBuf;
use vlf_core::dynamic::{DynamicObject, PlacedObject, Pose};
use vlf_core::field::LightField;
use vlf_core::render::Bvh;
use vlf_core::scene::Scene;

/// Most shadow cone cells per object and point: beyond, a view takes hours for no visible gain.
const MAX_SHADOW_SAMPLES: u32 = 1 << 16;

#[derive(Args, Clone, Debug)]
pub struct ObjectFlags {
    /// A dynamic object to draw in the view, lit by the field, casting shadows on the scene
    /// (OBJ or glTF, in the scene's coordinates, no emitter needed); repeat for more objects.
    #[arg(long, value_name = "FILE")]
    pub object: Vec<PathBuf>,
    /// Where to move each --object, in order: a translation in scene units (default: none).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3_arg, allow_hyphen_values = true, requires = "object")]
    pub object_at: Vec<DVec3>,
    /// How far to turn each --object about the up direction, in order, in degrees (before
    /// moving it).
    #[arg(long, value_name = "DEG", allow_hyphen_values = true, requires = "object")]
    pub object_turn: Vec<f64>,
    /// Cells of each object's shadow cone per shaded point (0: no shadows on the scene).
    #[arg(long, value_name = "K", default_value_t = vlf_core::dynamic::gather::DEFAULT_SHADOW_SAMPLES, requires = "object")]
    pub object_shadow_samples: u32,
    /// Directions of the object's gather (one of 9, 33, 129, 513, 2049, 8193; default: the
    /// field's).
    #[arg(long, value_name = "L", requires = "object")]
    pub object_directions: Option<usize>,
}

impl ObjectFlags {
    pub fn is_empty(&self) -> bool {
        self.object.is_empty()
    }

    /// Checks the numbers given: at most one --object-at and --object-turn per object, finite
    /// turns, a bounded shadow sample count.
    pub fn check(&self) -> Result<()> {
        if self.object_at.len() > self.object.len() || self.object_turn.len() > self.object.len() {
            bail!(
                "{} --object-at and {} --object-turn for {} --object: at most one each per object",
                self.object_at.len(),
                self.object_turn.len(),
                self.object.len()
            );
        }
        if let Some(turn) = self.object_turn.iter().find(|t| !t.is_finite()) {
            bail!("--object-turn must be finite, got {turn}");
        }
        if let Some(l) = self.object_directions
            && !vlf_core::directions::DirectionSet::SUPPORTED.contains(&l)
        {
            bail!(
                "--object-directions must be one of {:?}, got {l}",
                vlf_core::directions::DirectionSet::SUPPORTED
            );
        }
        if self.object_shadow_samples > MAX_SHADOW_SAMPLES {
            bail!(
                "--object-shadow-samples must be 0..={MAX_SHADOW_SAMPLES}, got {}",
                self.object_shadow_samples
            );
        }
        Ok(())
    }

    /// Reads every --object, each with its pose from --object-at and --object-turn (in order;
    /// missing ones leave the object as its file has it), turns about `up`.
    pub fn load(&self, up: DVec3) -> Result<Vec<(DynamicObject, Pose)>> {
        self.check()?;
        let mut objects = Vec::new();
        for (k, path) in self.object.iter().enumerate() {
            let (object, warnings) =
                DynamicObject::load(path).with_context(|| format!("cannot read the object {}", path.display()))?;
            for w in &warnings {
                tracing::warn!("{w}");
            }
            let turn = self.object_turn.get(k).copied().unwrap_or(0.0);
            let pose = Pose {
                rotation: DQuat::from_axis_angle(up.normalize(), turn.to_radians()),
                translation: self.object_at.get(k).copied().unwrap_or(DVec3::ZERO),
            };
            objects.push((object, pose));
        }
        Ok(objects)
    }

    /// [`ObjectFlags::load`], each object placed in the static `scene` (whose BVH `bvh` is),
    /// refusing one that lies outside the scene or crosses a static surface.
    pub fn place(&self, up: DVec3, scene: &Scene, bvh: &Bvh) -> Result<Vec<PlacedObject>> {
        let mut placed = Vec::new();
        for ((object, pose), path) in self.load(up)?.into_iter().zip(&self.object) {
            let object = object.place(&pose, &scene.normalisation)?;
            object
                .check_clear(scene, bvh)
                .with_context(|| format!("cannot place {} there", path.display()))?;
            placed.push(object);
        }
        Ok(placed)
    }

    /// The gather's direction count: --object-directions, or the field's own.
    pub fn directions(&self, field: &LightField) -> usize {
        self.object_directions.unwrap_or(field.options.directions)
    }
}
