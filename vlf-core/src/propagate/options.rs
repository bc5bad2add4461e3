//! What a propagation is asked to do: [`Options`], everything that determines its bits, with
//! their defaults and the checks that refuse absurd values before any work starts.

use super::batching::{self, CHUNK};
use crate::directions::DirectionSet;
use crate::psf::GridSize;
use crate::scene::Scene;
use serde::{Deserialize, Serialize};

/// When to stop iterating.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Stop {
    /// Exactly this many iterations.
    Iterations(u32),
    /// Until the unshot power is below `epsilon` × the emitted power, or
    /// `max_iterations` have run.
    Converge { epsilon: f64, max_iterations: u32 },
}

/// The paper's perturbation: the first `iterations` iterations are each shot
/// through `count` randomly rotated copies of the direction set, each carrying
/// `1/count` of the unshot power.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Perturbation {
    pub iterations: u32,
    pub count: u32,
}

/// Everything that determines a propagation (and so its bits).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Options {
    /// Number of line directions `l` (one of [`DirectionSet::SUPPORTED`]).
    pub directions: usize,
    pub grid: GridSize,
    pub stop: Stop,
    /// Texel edge as a multiple of the ray spacing `2/N`.
    pub texel_cells: f64,
    /// Deferred propagation: a surface whose unshot power is below this
    /// fraction of the total unshot power waits (keeps accumulating).
    pub deferral: Option<f64>,
    pub perturbation: Perturbation,
    /// σ (in texels) of the Gaussian filter applied to Next maps.
    pub filter_sigma: Option<f64>,
    /// Filter only where mirrors receive light (the plan decides, as it does for perturbation):
    /// the filter's smoothing pays where the field's own light is what a view shows —
    /// reflections and caustics — and costs accuracy where renders compute direct light
    /// exactly, as they do by default (`docs/accuracy.md`, *Choosing the defaults*). Off: the
    /// filter runs wherever `filter_sigma` is set.
    #[serde(default)]
    pub filter_only_with_mirrors: bool,
    /// Batches a pass is cut into where `l` allows ([`batching::Batching`]): the unit of leases
    /// and of the reduction, so part of the bits. A power of two. Jobs stored before it was an
    /// option were cut into [`defaults::LEGACY_PASS_BATCHES`], which is what their parameters
    /// read as, so that they render and resume as they ran.
    #[serde(default = "defaults::legacy_pass_batches")]
    pub pass_batches: u32,
    /// Consecutive directions of a batch that one thread shoots into one texel buffer before
    /// that buffer is added to the batch's sum (a *stint*, [`batching::Batching`]): what sets
    /// how often a field-sized buffer is streamed through memory, and part of the bits. A
    /// power of two up to [`CHUNK`]. Jobs stored before it was an option added every direction
    /// on its own, [`defaults::LEGACY_STINT_DIRECTIONS`], which is what their parameters read
    /// as, so that they render and resume as they ran.
    #[serde(default = "defaults::legacy_stint_directions")]
    pub stint_directions: u32,
}

/// The settings a job gets where its user names none: the one table that the command line
/// (`propagate`, `run`, `submit`, `bench`, `study`'s base point), the service's messages
/// (`vlf_proto::convert::JobSpec`) and [`Options::recommended`] read.
pub mod defaults {
    /// Line directions `l`.
    pub const DIRECTIONS: usize = 513;
    /// Rays per subfield side `N`, and tile side `m`.
    pub const RESOLUTION: u32 = 64;
    pub const TILE: u32 = 8;
    /// Stop when the unshot power is below this fraction of the emitted power, or after
    /// [`MAX_ITERATIONS`].
    pub const CONVERGE: f64 = 1e-3;
    pub const MAX_ITERATIONS: u32 = 1000;
    /// Texel edge in ray spacings.
    pub const TEXEL_CELLS: f64 = 1.0;
    /// The paper's remedies for holes: perturbed iterations and copies (the plan drops them
    /// where mirrors are), and the Next maps' filter σ in texels (applied only where mirrors
    /// are: [`super::Options::filter_only_with_mirrors`]); issue 30 measured what each costs.
    pub const PERTURB_ITERATIONS: u32 = 2;
    pub const PERTURB_COUNT: u32 = 4;
    pub const FILTER_SIGMA: f64 = 1.0;
    /// Batches per pass ([`super::batching::Batching`]): 64, so that 8 workers get 8 each and the
    /// last quarter of each one's run can go to whichever worker is idle (issue 31).
    pub const PASS_BATCHES: u32 = 64;
    /// What passes were cut into before [`super::Options::pass_batches`] existed.
    pub const LEGACY_PASS_BATCHES: u32 = 16;

    /// [`LEGACY_PASS_BATCHES`], for options stored without `pass_batches`.
    pub fn legacy_pass_batches() -> u32 {
        LEGACY_PASS_BATCHES
    }
    /// Directions per stint ([`super::batching::Batching`]): 8, which pays a buffer's pass over
    /// the field once for 8 directions while a pass at l = 2049 still has 257 stints to share
    /// out (16 a thread at 16 threads, so a tail of one stint is a few per cent of a pass).
    /// One thread on the Cornell box at l = 2049, N = 128 took 13.3–13.6 s with stints of 1,
    /// 11.3–11.6 s with 4, 10.3–10.5 s with 8 and 10.8 s with 16 (docs/scaling.md, *Stints*).
    pub const STINT_DIRECTIONS: u32 = 8;
    /// What a stint was before [`super::Options::stint_directions`] existed: one direction.
    pub const LEGACY_STINT_DIRECTIONS: u32 = 1;

    /// [`LEGACY_STINT_DIRECTIONS`], for options stored without `stint_directions`.
    pub fn legacy_stint_directions() -> u32 {
        LEGACY_STINT_DIRECTIONS
    }
}

impl Default for Options {
    /// The pure method at the default resolution ([`defaults`]): no perturbation, no filter.
    /// The library's neutral point, which tests and benchmarks vary from; a user's job gets
    /// [`Options::recommended`].
    fn default() -> Self {
        Options {
            directions: defaults::DIRECTIONS,
            grid: GridSize {
                resolution: defaults::RESOLUTION,
                tile: defaults::TILE,
            },
            stop: Stop::Converge {
                epsilon: defaults::CONVERGE,
                max_iterations: defaults::MAX_ITERATIONS,
            },
            texel_cells: defaults::TEXEL_CELLS,
            deferral: None,
            perturbation: Perturbation::default(),
            filter_sigma: None,
            filter_only_with_mirrors: false,
            pass_batches: defaults::PASS_BATCHES,
            stint_directions: defaults::STINT_DIRECTIONS,
        }
    }
}

impl Options {
    /// What a job gets where its user names nothing: every setting of [`defaults`], remedies
    /// included.
    pub fn recommended() -> Options {
        Options {
            perturbation: Perturbation {
                iterations: defaults::PERTURB_ITERATIONS,
                count: defaults::PERTURB_COUNT,
            },
            filter_sigma: Some(defaults::FILTER_SIGMA),
            filter_only_with_mirrors: true,
            ..Options::default()
        }
    }

    /// The filter σ a scene gets: `filter_sigma`, unless it applies only with mirrors and
    /// `mirrors` (mirrors that receive light) is false.
    pub fn filter_for(&self, mirrors: bool) -> Option<f64> {
        self.filter_sigma.filter(|_| mirrors || !self.filter_only_with_mirrors)
    }

    /// These options with what the plan would decide for `scene` made explicit (the filter, by
    /// whether the scene has mirrors): a starting point to vary one setting from, as a study
    /// does, where "the filter toggled" must mean the filter the scene actually gets.
    pub fn resolved_for(&self, scene: &Scene) -> Options {
        let mirrors = scene.materials.iter().any(|m| m.is_mirror());
        Options {
            filter_sigma: self.filter_for(mirrors),
            filter_only_with_mirrors: false,
            ..self.clone()
        }
    }
}

impl Options {
    /// Refuses absurd values with a message naming the parameter.
    pub fn validate(&self) -> crate::Result<()> {
        let bad = |m: String| Err(crate::Error::Parameter(m));
        GridSize::new(self.grid.resolution, self.grid.tile)?;
        if !DirectionSet::SUPPORTED.contains(&self.directions) {
            return bad(format!(
                "directions = {} is not one of {:?} (l = 2·4^k + 1)",
                self.directions,
                DirectionSet::SUPPORTED
            ));
        }
        match self.stop {
            Stop::Iterations(0) => return bad("iterations must be at least 1".into()),
            Stop::Iterations(k) if k > 100_000 => return bad(format!("iterations = {k} is absurd (max 100000)")),
            Stop::Converge {
                epsilon,
                max_iterations,
            } => {
                if !(epsilon > 0.0 && epsilon < 1.0) {
                    return bad(format!("convergence threshold must be in (0, 1), got {epsilon}"));
                }
                if max_iterations == 0 {
                    return bad("max iterations must be at least 1".into());
                }
            }
            _ => {}
        }
        if !(self.texel_cells.is_finite() && (0.05..=1024.0).contains(&self.texel_cells)) {
            return bad(format!(
                "texel size must be 0.05..1024 ray spacings, got {}",
                self.texel_cells
            ));
        }
        if let Some(d) = self.deferral
            && !(0.0..1.0).contains(&d)
        {
            return bad(format!("deferral threshold must be in [0, 1), got {d}"));
        }
        if self.perturbation.iterations > 0 && !(1..=64).contains(&self.perturbation.count) {
            return bad(format!(
                "perturbation count must be 1..=64, got {}",
                self.perturbation.count
            ));
        }
        if let Some(s) = self.filter_sigma
            && !(s.is_finite() && s > 0.0 && s <= 16.0)
        {
            return bad(format!("filter sigma must be in (0, 16] texels, got {s}"));
        }
        if !(self.pass_batches.is_power_of_two() && self.pass_batches <= 1024) {
            return bad(format!(
                "batches per pass must be a power of two up to 1024, got {}",
                self.pass_batches
            ));
        }
        if !(self.stint_directions.is_power_of_two() && self.stint_directions as usize <= CHUNK) {
            return bad(format!(
                "directions per stint must be a power of two up to {CHUNK}, got {}",
                self.stint_directions
            ));
        }
        Ok(())
    }

    /// How this job's passes are cut into batches.
    pub fn batching(&self) -> batching::Batching {
        batching::Batching::new(self.directions, self.pass_batches, self.stint_directions)
    }

    /// Texel edge length in the VLF frame.
    pub fn texel_size(&self) -> f64 {
        self.texel_cells * self.grid.ray_spacing()
    }
}
