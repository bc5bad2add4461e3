//! Perturbation: the paper's remedy for *holes*.
//!
//! Beams of a discrete direction are cylinders, not cones, so a small sender
//! seen from far away lights a pattern of spots instead of a smooth patch.
//! The paper jitters the whole direction set: an iteration is shot through
//! `count` copies of the set, each rotated by a small random rotation (of the
//! order of one direction cell, `√(2π/l)` radians), each carrying `1/count` of
//! the unshot power. Perturbed shots only feed the diffuse maps; they never
//! create directional totals. Each rotated set gets its own discrete areas
//! `T_t`, so every sub-shot is exactly power-conserving too.
//!
//! The passes that shoot through the copies are in [`super::work`].
//!
//! Rotations come from a fixed-seed splitmix64 sequence keyed by iteration
//! and copy index, so results are reproducible across runs, machines and
//! library versions (a general-purpose RNG crate makes no such promise).

use crate::directions::DirectionSet;
use glam::{DMat3, DVec3};

/// splitmix64: a tiny, well-known generator with a fixed definition.
pub(crate) struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// The rotation of copy `copy` of `count` in iteration `iteration`: about a
/// random axis, by an angle stratified over `[0, α)` with `α = √(2π/l)`.
pub(crate) fn rotation(directions: &DirectionSet, iteration: u32, copy: u32, count: u32) -> DMat3 {
    let mut rng = SplitMix(0x564C_465F_5045_5254 ^ ((iteration as u64) << 32 | copy as u64));
    let z = 2.0 * rng.next_f64() - 1.0;
    let phi = std::f64::consts::TAU * rng.next_f64();
    let r = (1.0 - z * z).max(0.0).sqrt();
    let axis = DVec3::new(r * phi.cos(), r * phi.sin(), z);
    let alpha = directions.mean_solid_angle().sqrt();
    let angle = alpha * (copy as f64 + rng.next_f64()) / count as f64;
    DMat3::from_axis_angle(axis, angle)
}
