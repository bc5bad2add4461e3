//! Checkpoints: the state of a propagation between two iterations, enough
//! to resume it with **the same bits** as if it had never stopped.
//!
//! Everything else a [`Propagation`] holds — directions, subfields, texel
//! grids, discrete areas, mirror layouts and reflection routes — is a
//! deterministic function of the scene and the [`Options`], so it is rebuilt
//! rather than stored. What remains is small and exact (f64, never a lossy
//! encoding):
//!
//! * the diffuse Current (unshot) and Total maps, per texel;
//! * with mirrors, every direction's unshot and total maps over its mirror
//!   slots (the incident maps are always empty between iterations: the
//!   exchange consumes them);
//! * the statistics of the iterations done, whose count is the next
//!   iteration's index (which seeds the perturbation and the mirror plan).
//!
//! Serialised with bincode behind a version number; [`Checkpoint::from_bytes`]
//! and [`Propagation::resume`] refuse anything that does not fit the rebuilt
//! geometry, or that is not finite and non-negative, with an [`Error::Decode`].

use super::{IterationStats, Options, Propagation};
use crate::error::Error;
use crate::scene::{Rgb, Scene};
use serde::{Deserialize, Serialize};

/// Version of the checkpoint's serialisation.
const CHECKPOINT_VERSION: u32 = 1;

/// The specular maps of one direction in a checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DirectionCheckpoint {
    pub unshot: Vec<Rgb>,
    pub total: Vec<Rgb>,
}

/// The state of a propagation after `stats.len()` iterations.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    version: u32,
    pub stats: Vec<IterationStats>,
    /// Unshot power per texel.
    pub current: Vec<Rgb>,
    /// Power that left each texel so far.
    pub total: Vec<Rgb>,
    /// Per direction, `None` without specular machinery.
    pub mirrors: Option<Vec<DirectionCheckpoint>>,
}

impl Checkpoint {
    /// Iterations done when the checkpoint was taken.
    pub fn iterations(&self) -> u32 {
        self.stats.len() as u32
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        bincode::serialize(self).expect("bincode into memory cannot fail for plain numbers")
    }

    pub fn from_bytes(bytes: &[u8]) -> crate::Result<Checkpoint> {
        let checkpoint: Checkpoint =
            bincode::deserialize(bytes).map_err(|e| Error::Decode(format!("checkpoint: {e}")))?;
        if checkpoint.version != CHECKPOINT_VERSION {
            return Err(Error::Decode(format!(
                "checkpoint version {} (this build reads {CHECKPOINT_VERSION})",
                checkpoint.version
            )));
        }
        Ok(checkpoint)
    }
}

impl Propagation {
    /// The state to resume from after the iterations done so far.
    pub fn checkpoint(&self) -> Checkpoint {
        Checkpoint {
            version: CHECKPOINT_VERSION,
            stats: self.stats.clone(),
            current: self.current.clone(),
            total: self.total.clone(),
            mirrors: self.specular.as_ref().map(|s| {
                s.maps
                    .iter()
                    .map(|m| DirectionCheckpoint {
                        unshot: m.unshot.clone(),
                        total: m.total.clone(),
                    })
                    .collect()
            }),
        }
    }

    /// Rebuilds the propagation of `scene` with `options` and restores
    /// `checkpoint` into it: stepping on gives the same bits as the run the
    /// checkpoint was taken from.
    pub fn resume(scene: Scene, options: Options, checkpoint: Checkpoint) -> crate::Result<Propagation> {
        let mut p = Propagation::new(scene, options)?;
        p.restore(checkpoint)?;
        Ok(p)
    }

    /// Replaces this propagation's state by `checkpoint` (of the same scene
    /// and options), keeping the geometry: how a worker moves on to the next
    /// iteration without rebuilding its subfields. On error the state is
    /// unchanged.
    pub fn restore(&mut self, checkpoint: Checkpoint) -> crate::Result<()> {
        let p = self;
        let bad = |m: String| {
            Err(Error::Decode(format!(
                "checkpoint does not fit the scene and options: {m}"
            )))
        };
        let texels = p.atlas.texels;
        if checkpoint.current.len() != texels || checkpoint.total.len() != texels {
            return bad(format!(
                "{} / {} texel values for {texels} texels",
                checkpoint.current.len(),
                checkpoint.total.len()
            ));
        }
        if let Some(i) = checkpoint
            .stats
            .iter()
            .enumerate()
            .position(|(i, s)| s.index != i as u32)
        {
            return bad(format!("iteration statistics out of order at {i}"));
        }
        let valid = |v: &[Rgb]| v.iter().flatten().all(|&c| c.is_finite() && c >= 0.0);
        if !valid(&checkpoint.current) || !valid(&checkpoint.total) {
            return bad("negative or non-finite power".into());
        }
        match (&mut p.specular, checkpoint.mirrors) {
            (None, None) => {}
            (Some(spec), Some(maps)) => {
                if maps.len() != spec.maps.len() {
                    return bad(format!(
                        "mirror maps for {} directions, expected {}",
                        maps.len(),
                        spec.maps.len()
                    ));
                }
                for (d, (own, saved)) in spec.maps.iter().zip(&maps).enumerate() {
                    let slots = own.total.len();
                    if saved.unshot.len() != slots || saved.total.len() != slots {
                        return bad(format!(
                            "direction {d}: mirror maps do not match its {slots} mirror slots"
                        ));
                    }
                    if !valid(&saved.unshot) || !valid(&saved.total) {
                        return bad(format!("direction {d}: negative or non-finite mirror radiance"));
                    }
                }
                for (own, saved) in spec.maps.iter_mut().zip(maps) {
                    own.unshot = saved.unshot;
                    own.total = saved.total;
                    own.incident.iter_mut().for_each(|v| *v = [0.0; 3]);
                }
            }
            (Some(_), None) => return bad("the scene has mirrors, the checkpoint none".into()),
            (None, Some(_)) => return bad("the checkpoint has mirror maps, the scene no mirror".into()),
        }
        p.current = checkpoint.current;
        p.total = checkpoint.total;
        p.stats = checkpoint.stats;
        Ok(())
    }
}
