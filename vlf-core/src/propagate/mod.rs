//! Propagation: Jacobi-style shooting of light along every ray of every
//! direction, iteration after iteration.
//!
//! ## Energy normalisation (the paper's section 4.4, made exact)
//!
//! Diffuse texels hold **power** (Current / Next / Total maps, RGB, f64). A
//! texel must send its unshot power `Φ_t` out over the hemisphere in
//! proportion to its projected area and the directions' solid angles. In the
//! discretised field, the projected area of texel `t` in direction `ω` is the
//! number of rays `n_t(ω)` that cross it times the ray cell area, so the
//! texel's *total projected area* is
//!
//! ```text
//!     T_t = Σ_ω Δω · n_t(ω)          (in units of the cell area)
//! ```
//!
//! and every ray of direction `ω` leaving `t` carries the power
//! `Φ_t · Δω / T_t`. Summed over all rays and directions this is exactly
//! `Φ_t`: **each texel sends out exactly its power**, to rounding, whatever the
//! sampling pattern of the texel by the rays (the paper's precomputed *total
//! projected unit area* only holds on average). Since `Σ_ω Δω·cos θ_ω ≈ π`,
//! `T_t ≈ π·A_t/cell`, so `A_t = T_t/π` (cells) is the texel's *discrete
//! area*, and a ray's `Φ_t/T_t` is the radiance `B_t/π` in matching units:
//! radiance look-ups at render time are simply `Total_t / T_t`. A furnace
//! (closed enclosure, uniform emission and reflectance) is then uniform to
//! rounding, texel by texel (tested).
//!
//! ## An iteration
//! 1. every texel with unshot power is a sender: `radiance_t = Φ_t / T_t`;
//! 2. for every direction (claimed a stint of a few at a time by whichever
//!    thread is free, `claim`), walk each ray's sorted hits: two consecutive
//!    surfaces facing each other exchange `radiance·Δω`; a back face blocks;
//!    nothing beyond the first/last surface means escape;
//! 3. the received power is reduced over directions **in direction order**
//!    (fixed batches and stints, each summed in direction order, so the bits
//!    do not depend on the thread or worker count), times `ρd` it becomes
//!    Next and is added to Total.
//!
//! Options: deferred propagation (charts with negligible unshot power wait),
//! perturbation (the paper's remedy for holes: shoot the first iterations
//! through randomly rotated copies of the direction set) and power-preserving
//! Gaussian filtering of the Next maps.

mod areas;
mod batching;
mod block;
pub mod checkpoint;
mod claim;
mod filter;
pub mod mirror_geometry;
mod options;
mod output;
mod perturb;
pub mod plan;
pub mod reduce;
mod rotated;
pub(crate) mod shoot;
pub mod snapshot;
pub mod specular;
mod split;
pub mod survey;
pub mod work;

pub use batching::{Batching, CHUNK};
pub use checkpoint::{Checkpoint, ShootingState, Totals};
pub use mirror_geometry::{MirrorGeometry, MirrorGeometryRef};
pub use options::{Options, Perturbation, Stop, defaults};
pub use output::{Arrivals, BatchOutput, BatchSum, MirrorBlock};
pub use plan::Plan;
pub use shoot::Flow;
pub use snapshot::{MapBatch, MapKind, SnapshotBytes, StateHead};
pub use specular::{Exchange, Specular};
pub use split::{HomeThreads, split_by_cost};
pub use survey::{Survey, SurveyPart, SurveyParts, Surveyor};
pub use work::{IterationWork, Pass};

use crate::directions::DirectionSet;
use crate::maps::TexelAtlas;
use crate::psf::{Footprints, Subfield, Subfields};
use crate::scene::{Rgb, Scene};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, OnceLock};
use std::time::Instant;

/// What happened in one iteration (powers per channel, VLF-frame units).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct IterationStats {
    pub index: u32,
    pub flow: FlowRecord,
    /// Unshot power left after the iteration (Next + deferred).
    pub unshot: Rgb,
    /// Charts (surfaces sharing texels, [`crate::maps::charts`]) deferred this iteration.
    pub deferred_surfaces: usize,
    /// Mirror exchange after the iteration (zero without mirrors).
    pub exchange: Exchange,
    /// Of `unshot`, the part in mirror maps.
    pub specular_unshot: Rgb,
    pub seconds: f64,
}

/// Where one iteration's time went in this process, phase by phase (seconds): what the
/// `plan`, `shoot`, `reduce` and `finish` tracing spans (debug level, target
/// `vlf_core::propagate`) time, and what `vlf bench` breaks an iteration down into. Not part
/// of a checkpoint or of [`IterationStats`]: timings are not the field's bits.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PhaseTimes {
    /// The iteration's work laid out ([`Propagation::iteration_work`]) and the mirror maps'
    /// arrivals of the last iteration gathered.
    pub plan: f64,
    /// The directions' batches shot, every thread at work, less the reduction.
    pub shoot: f64,
    /// The pass's sum added into the iteration's totals. (The batches' sums fold into the
    /// pass's reduction tree as they complete, while the threads shoot: that is in `shoot`.)
    pub reduce: f64,
    /// The end: mirror totals and power in, then [`Propagation::finish_iteration`] (the Next
    /// maps filtered and swapped, convergence, statistics).
    pub finish: f64,
}

impl PhaseTimes {
    pub fn total(&self) -> f64 {
        self.plan + self.shoot + self.reduce + self.finish
    }
}

/// Serializable copy of [`Flow`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FlowRecord {
    pub shot: Rgb,
    pub received: Rgb,
    pub escaped: Rgb,
    pub blocked: Rgb,
}

impl From<Flow> for FlowRecord {
    fn from(f: Flow) -> Self {
        FlowRecord {
            shot: f.shot,
            received: f.received,
            escaped: f.escaped,
            blocked: f.blocked,
        }
    }
}

/// Progress of the running iteration, for progress bars.
#[derive(Clone, Copy, Debug)]
pub struct Progress {
    pub iteration: u32,
    pub directions_done: usize,
    pub directions_total: usize,
}

/// A propagation in progress: the field's geometry plus the radiosity maps.
#[derive(Clone)]
pub struct Propagation {
    pub scene: Scene,
    pub options: Options,
    pub directions: DirectionSet,
    pub atlas: TexelAtlas,
    /// Held whole, or built on demand within a budget ([`Subfields`]). Shared: a clone of the
    /// propagation (a worker's replica) does not copy them.
    pub subfields: Arc<Subfields>,
    /// What the subfields rasterise, for the rotated copies built on the fly.
    footprints: Arc<Footprints>,
    /// Diffuse reflectance `ρ_t` of every texel ([`crate::maps::albedo`]).
    pub(crate) albedo: Arc<[Rgb]>,
    /// Discrete projected area `T_t` of every texel (see module docs).
    pub projected_area: Vec<f64>,
    /// Per chart, `k_c` of [`emission_scales`] (1 for a chart that does not emit).
    pub emission_scale: Vec<f64>,
    /// Unshot power per texel (the paper's Current map).
    pub current: Vec<Rgb>,
    /// Power leaving each texel over all iterations so far (emitted + reflected).
    pub total: Vec<Rgb>,
    pub emitted: Rgb,
    pub stats: Vec<IterationStats>,
    /// Per iteration stepped in this process ([`Propagation::step`]), where its time went.
    pub phase_times: Vec<PhaseTimes>,
    /// Mirror maps and reflection routes; `None` when the scene has no
    /// mirror light can reach (no specular machinery at all).
    pub specular: Option<Specular>,
    /// What this propagation simulates (see [`Plan`]).
    pub plan: Plan,
    stacking: shoot::Stacking,
    /// The chart of every texel.
    pub(crate) owners: Vec<u32>,
    /// The per-stint texel buffers, kept from one block or step to the next.
    buffers: work::KeptBuffers,
    /// Rotated copies' subfields, kept from a copy's areas to its shot ([`rotated`]).
    rotated: Arc<rotated::RotatedSubfields>,
    /// Where the charts no ray crosses take their light from ([`crate::maps::fill`]): a
    /// function of the geometry and of `projected_area` as set up, found by the first
    /// [`Propagation::diffuse_radiance`] and shared by clones.
    pub(crate) hole_fill: Arc<OnceLock<crate::maps::fill::AcrossCharts>>,
}

fn sum_rgb(v: &[Rgb]) -> Rgb {
    v.iter().fold([0.0; 3], |a, b| [a[0] + b[0], a[1] + b[1], a[2] + b[2]])
}

pub(crate) fn luminance(c: &Rgb) -> f64 {
    (c[0] + c[1] + c[2]) / 3.0
}

/// Where set-up takes the mirrors' views and routes from.
enum Mirrors {
    /// Rasterising the mirror planes in every direction, and finding the routes.
    Computed,
    /// Every direction's subfield restricted to the mirror planes, learnt with the survey: the
    /// routes found from them.
    FromPlanes(Vec<Subfield>),
    /// The job's stored geometry, read back.
    Stored(MirrorGeometry),
}

impl Propagation {
    /// Builds the field's geometry (directions, subfields, texel grids,
    /// discrete areas) and loads the emitters' power as unshot.
    pub fn new(scene: Scene, options: Options) -> crate::Result<Self> {
        Propagation::with_subfield_budget(scene, options, None)
    }

    /// [`Propagation::new`], holding at most `budget` bytes of subfields when one is given
    /// (built on demand, least recently used dropped first: [`Subfields::within`]): the same
    /// bits, in the memory a worker needs for the directions it shoots rather than for the
    /// whole field. Set-up still reads every subfield once (two or three passes over the
    /// directions, each rebuilding what the budget did not keep).
    pub fn with_subfield_budget(scene: Scene, options: Options, budget: Option<usize>) -> crate::Result<Self> {
        Propagation::set_up(scene, options, budget, None, Mirrors::Computed)
    }

    /// [`Propagation::with_subfield_budget`] where the [`Survey`] is known — what set-up
    /// otherwise learns by passing over every direction (the discrete areas `T_t`, the mirrors
    /// light reaches), learnt by whoever created the job and stored with it
    /// ([`Propagation::survey`]). No subfield is then built up front: each is built when first
    /// asked for — by a worker, when it shoots the direction — and kept within `budget` (all
    /// kept without one). A worker of a cluster so spends on set-up what its share of the
    /// directions costs rather than what the whole field does, and holds only its share's
    /// subfields; its mirrors rasterise their own planes alone ([`specular::MirrorView`]). The
    /// same bits as learning the survey again: it is the same numbers.
    ///
    /// Refuses a survey that does not fit the scene and options ([`Survey::check`]), with an
    /// [`Error::Decode`](crate::Error::Decode) that says why (the caller adds where it was read).
    pub fn with_survey(scene: Scene, options: Options, budget: Option<usize>, survey: Survey) -> crate::Result<Self> {
        Propagation::set_up(scene, options, budget, Some(survey), Mirrors::Computed)
    }

    /// [`Propagation::with_survey`] where every direction's subfield restricted to the scene's
    /// mirror planes is known too, learnt with the survey's parts
    /// ([`SurveyParts::finish_with_planes`]): the mirror views are cut from them rather than
    /// rasterised again — what a coordinator whose workers learnt the survey sets the job up
    /// with. The same bits. Planes that are not those of the directions (another count, frame or
    /// grid, a surface that is not a mirror, tables out of bounds) are refused.
    pub fn with_survey_and_planes(
        scene: Scene,
        options: Options,
        budget: Option<usize>,
        survey: Survey,
        planes: Vec<Subfield>,
    ) -> crate::Result<Self> {
        Propagation::set_up(scene, options, budget, Some(survey), Mirrors::FromPlanes(planes))
    }

    /// [`Propagation::with_survey`] where the mirror geometry is known too — every direction's
    /// mirror view and the reflection routes, computed by whoever set the job up and stored with
    /// it ([`Propagation::mirror_geometry`]): no mirror plane is rasterised, no route found. The
    /// same bits: it is the same tables. A geometry that does not fit the scene, the options or
    /// the mirrors the survey maps is refused ([`MirrorGeometry::check`]).
    pub fn with_stored(
        scene: Scene,
        options: Options,
        budget: Option<usize>,
        survey: Survey,
        mirrors: MirrorGeometry,
    ) -> crate::Result<Self> {
        Propagation::set_up(scene, options, budget, Some(survey), Mirrors::Stored(mirrors))
    }

    /// This propagation's mirror geometry, borrowed, to be written where it goes
    /// ([`MirrorGeometryRef::write_to`]); `None` without mirrors. What a job stores beside its
    /// survey, so that nobody computes it again.
    pub fn mirror_geometry_ref(&self) -> Option<MirrorGeometryRef<'_>> {
        (self.specular.as_ref()).map(|s| MirrorGeometry::borrowed(&self.scene, &self.options, s))
    }

    /// This propagation's mirror geometry, as bytes for [`MirrorGeometry::from_bytes`]; `None`
    /// without mirrors.
    pub fn mirror_geometry(&self) -> Option<Vec<u8>> {
        self.mirror_geometry_ref().map(|g| g.to_bytes())
    }

    /// Lets go of the subfields, when nothing this propagation will still do reads them: the
    /// coordinator of a diffuse job absorbs what workers shoot and never shoots itself, so it
    /// holds none once the job is set up (at l = 8193, N = 256 the Cornell box's are 696 MB). One
    /// asked for later is built again (the same spans), so no bit changes; clones made before
    /// (a prototype handed to a worker) keep theirs. Mirrors need none: their tiles are cut
    /// along their views ([`specular::MirrorView`]).
    pub fn release_subfields(&mut self) {
        self.subfields = Arc::new(self.subfields.released());
    }

    /// What this propagation's set-up learnt over all directions, for whoever builds the same
    /// propagation next ([`Propagation::with_survey`]).
    pub fn survey(&self) -> Survey {
        Survey::new(
            survey::Surveyed::of(&self.scene, &self.options),
            self.projected_area.clone(),
            self.plan.lit_mirrors.clone(),
        )
    }

    /// Builds the geometry, and learns the survey unless it is `known`; the mirrors' views and
    /// routes as `given` says.
    fn set_up(
        scene: Scene,
        options: Options,
        budget: Option<usize>,
        known: Option<Survey>,
        given: Mirrors,
    ) -> crate::Result<Self> {
        options.validate()?;
        // Seconds since the last lap: where set-up's time goes, logged at the end.
        let mut last = Instant::now();
        let mut lap = move || {
            let now = Instant::now();
            let seconds = now.duration_since(last).as_secs_f64();
            last = now;
            seconds
        };
        let directions = DirectionSet::new(options.directions)?;
        let atlas = TexelAtlas::new(&scene, options.texel_size(), options.grid.ray_spacing())?;
        if let Some(survey) = &known {
            survey.check(&scene, &options, atlas.texels)?;
        }
        let grid = options.grid;
        let footprints = Arc::new(Footprints::new(&scene, &atlas.plane_rep));
        let albedo: Arc<[Rgb]> = crate::maps::albedo::texel_albedo(&scene, &atlas).into();
        let frames = (0..directions.len()).map(|d| directions.frame(d)).collect();
        let atlas_s = lap();
        let subfields = match (budget, &known) {
            (Some(bytes), _) => Subfields::within(footprints.clone(), frames, grid, bytes),
            // Known, the survey spares the pass over every direction: each is built when shot.
            (None, Some(_)) => Subfields::on_demand(footprints.clone(), frames, grid),
            // Learning it passes over them all, reading each two or three times.
            (None, None) => Subfields::build_all(footprints.clone(), frames, grid),
        };
        let stacking = shoot::Stacking::new(&scene, &atlas);
        let geometry = shoot::Geometry {
            scene: &scene,
            atlas: &atlas,
            stacking: &stacking,
        };
        let subfields_s = lap();
        let (projected_area, mut plan) = match known {
            Some(survey) => (survey.projected_area, Plan::surveyed(&scene, survey.lit_mirrors)),
            None => (
                areas::discrete_areas(geometry, &directions, |d| subfields.get(d)),
                Plan::new(&scene, geometry, &subfields),
            ),
        };
        let survey_s = lap();
        let owners = atlas.owners();
        let emission_scale = emission_scales(&scene, &atlas, &projected_area, grid.cell_area());
        // Emission: Φ_t = Le·T_t·k_c (in cell-area units), each emitter's true power π·Le·A.
        let current: Vec<Rgb> = projected_area
            .iter()
            .zip(&owners)
            .map(|(&t, &c)| {
                let le = scene.materials[atlas.chart_material[c as usize] as usize].emission;
                let t = t * emission_scale[c as usize];
                [le[0] * t, le[1] * t, le[2] * t]
            })
            .collect();
        let emitted = sum_rgb(&current);
        if luminance(&emitted) <= 0.0 {
            return Err(crate::Error::Parameter(
                "no emitter is hit by any ray: the emitters are too small for this resolution (raise N)".into(),
            ));
        }
        let mirrors = plan.mapped_mirrors();
        let mut specular = match given {
            Mirrors::Stored(geometry) => Some(geometry.into_specular(&scene, &options, &subfields, &mirrors)?),
            _ if mirrors.is_empty() => None,
            Mirrors::FromPlanes(planes) => Some(mirror_geometry::specular_from_planes(
                &scene,
                &directions,
                &subfields,
                planes,
                mirrors,
            )?),
            Mirrors::Computed => Some(Specular::new(
                &scene,
                &directions,
                &subfields,
                &atlas.plane_rep,
                mirrors,
            )),
        };
        if let Some(spec) = &mut specular {
            // Within a budget, memory is what the process is short of.
            spec.keep_gather_tables = budget.is_none();
        }
        plan.mirror_slots = specular
            .as_ref()
            .map_or(0, |s| s.views.iter().map(specular::MirrorView::slots).sum());
        plan.perturbation = options.perturbation.iterations > 0 && options.perturbation.count > 0 && specular.is_none();
        plan.filter = options.filter_for(specular.is_some());
        tracing::debug!(
            atlas_s = format!("{atlas_s:.3}"),
            subfields_s = format!("{subfields_s:.3}"),
            survey_s = format!("{survey_s:.3}"),
            mirrors_s = format!("{:.3}", lap()),
            subfields_built = subfields.memory().builds,
            "propagation set up"
        );
        Ok(Propagation {
            specular,
            plan,
            stacking,
            total: current.clone(),
            scene,
            options,
            directions,
            atlas,
            subfields: Arc::new(subfields),
            footprints,
            albedo,
            projected_area,
            emission_scale,
            current,
            emitted,
            stats: Vec::new(),
            owners,
            buffers: work::KeptBuffers::default(),
            rotated: Arc::default(),
            phase_times: Vec::new(),
            hole_fill: Arc::default(),
        })
    }

    /// How many subfields of rotated copies this propagation (and its clones) built so far:
    /// twice a copy's directions per copy where they are not kept from its areas to its shot,
    /// once where they are ([`rotated`]).
    pub fn rotated_subfields_built(&self) -> usize {
        self.rotated.built()
    }

    /// Rotated subfields kept now, from a copy's areas for its shot ([`rotated`]).
    pub fn rotated_subfields_kept(&self) -> usize {
        self.rotated.kept()
    }

    /// Drops the rotated subfields kept for iterations before `index` ([`rotated`]): what one
    /// that moves on to iteration `index` without finishing the last (a worker) kept there
    /// and another shot, or no one.
    pub fn drop_rotated_subfields_before(&self, index: u32) {
        if let Some(last) = index.checked_sub(1) {
            self.rotated.clear(last);
        }
    }

    /// How this propagation's passes are cut into batches ([`Options::pass_batches`]).
    pub fn batching(&self) -> Batching {
        self.options.batching()
    }

    /// Unshot power as a fraction of the emitted power.
    pub fn unshot_fraction(&self) -> f64 {
        luminance(&self.unshot_power()) / luminance(&self.emitted)
    }

    /// Unshot power: diffuse (Current maps) plus specular (mirror maps).
    pub fn unshot_power(&self) -> Rgb {
        let mut p = sum_rgb(&self.current);
        if let Some(s) = &self.specular {
            let q = s.unshot_power(&self.directions);
            for c in 0..3 {
                p[c] += q[c];
            }
        }
        p
    }

    pub fn iterations_done(&self) -> u32 {
        self.stats.len() as u32
    }

    /// Whether the stop rule says to stop now.
    pub fn finished(&self) -> bool {
        let k = self.iterations_done();
        match self.options.stop {
            Stop::Iterations(n) => k >= n,
            Stop::Converge {
                epsilon,
                max_iterations,
            } => k >= max_iterations || self.unshot_fraction() < epsilon,
        }
    }

    /// Runs iterations until the stop rule holds.
    pub fn run(&mut self, mut progress: impl FnMut(Progress)) -> &[IterationStats] {
        while !self.finished() {
            self.step(&mut progress);
        }
        &self.stats
    }

    /// Performs one iteration in this process with the threads of the current rayon pool: every
    /// pass's stints claimed one at a time by whichever thread is free, each batch summed in
    /// stint order as its stints come in (`claim`), the batch sums absorbed in order.
    /// The same bits on any number of threads, and as any split across workers.
    ///
    /// Where no budget bounds the subfields, a perturbed iteration's passes are shot in
    /// [`IterationWork::shooting_order`] (each copy's shot right after its areas, its rotated
    /// subfields built once: [`rotated`]) and absorbed in [`IterationWork::passes`]'s, a shot's
    /// whole-pass sum held until its turn (at most `copies − 1` texel-sized sums). Within a
    /// subfield budget nothing is kept, so the passes are shot in the order they are absorbed.
    pub fn step(&mut self, mut progress: impl FnMut(Progress)) -> IterationStats {
        let mut held: Vec<(Pass, BatchSum)> = Vec::new();
        let order = if self.subfields.has_budget() {
            IterationWork::passes
        } else {
            IterationWork::shooting_order
        };
        self.step_by(order, |prop, work, pass, maps, clock, heard| {
            let mut io = maps.map(|m| work::mirror_io(m));
            let all = 0..work.batches();
            let (sum, _) = prop
                .shoot_claimed(work, pass, all.clone(), io.as_deref_mut(), |done| progress(heard(done)))
                .expect("batches of this process's own work are well-formed");
            drop(io);
            clock.reducing();
            held.push((pass, sum));
            while let Some(k) = (work.next_expected()).and_then(|(next, _)| held.iter().position(|(p, _)| *p == next)) {
                let (pass, sum) = held.remove(k);
                work.absorb(pass, all.clone(), sum)
                    .expect("the whole pass is the root of its tree");
            }
            clock.reduced();
        })
    }

    /// Performs one iteration in this process, each batch in turn, its stints shared among the
    /// current pool's threads CHUNK at a time (they meet at the end of every chunk): the
    /// plainest schedule, which the others are held to (`tests/distributed.rs`).
    pub fn step_shared(&mut self, mut progress: impl FnMut(Progress)) -> IterationStats {
        let mut buffers = self.buffers.take();
        let stats = self.step_by(IterationWork::passes, |prop, work, pass, mut maps, clock, heard| {
            for batch in 0..work.batches() {
                let range = work.batch_range(batch);
                let mut own = maps.as_mut().map(|m| work::mirror_io(&mut m[range.clone()]));
                let sum = prop
                    .run_batch_with(work, pass, batch, own.as_deref_mut(), &mut buffers)
                    .expect("batches of this process's own work are well-formed");
                clock.reducing();
                work.absorb(pass, batch..batch + 1, sum)
                    .expect("this process absorbs its batches in order");
                clock.reduced();
                progress(heard(range.end));
            }
        });
        self.buffers.keep(buffers);
        stats
    }

    /// One iteration in this process around `shoot`, which shoots and absorbs one pass: the
    /// iteration's work and mirror maps set up, every pass in the order `order` gives, then the
    /// end of the iteration and its phase times. `shoot` gets the pass's work, the mirror maps,
    /// the phase clock and a function that turns the directions done in the pass into the
    /// iteration's progress.
    #[allow(clippy::type_complexity)]
    fn step_by(
        &mut self,
        order: fn(&IterationWork) -> Vec<Pass>,
        mut shoot: impl FnMut(
            &Propagation,
            &mut IterationWork,
            Pass,
            Option<&mut Vec<specular::DirectionMaps>>,
            &mut PhaseClock,
            &dyn Fn(usize) -> Progress,
        ),
    ) -> IterationStats {
        let started = Instant::now();
        let mut clock = PhaseClock::start(started);
        let mut work = self.iteration_work();
        let passes = order(&work);
        let l = self.directions.len();
        let mut maps = self.gathered_maps(&work);
        clock.planned();
        for (p, &pass) in passes.iter().enumerate() {
            let iteration = work.index;
            let heard = |done: usize| Progress {
                iteration,
                directions_done: p * l + done,
                directions_total: passes.len() * l,
            };
            shoot(self, &mut work, pass, maps.as_mut(), &mut clock, &heard);
        }
        clock.shot();
        let stats = self.end_step(work, maps, started);
        self.phase_times.push(clock.finished());
        stats
    }

    /// The mirror maps an iteration's shooting reads and writes, taken out of the propagation,
    /// when `work` uses them: the last iteration's arrivals gathered first (the exchange, see
    /// `specular::Pending`).
    ///
    /// One process shooting every direction holds every direction's maps: those it never wrote
    /// are zeros, allocated now ([`Specular::hold_zeros`]). A propagation whose maps are
    /// elsewhere (a coordinator's, a worker's replica) computes blocks instead, and never steps.
    fn gathered_maps(&mut self, work: &IterationWork) -> Option<Vec<specular::DirectionMaps>> {
        match (&mut self.specular, work.uses_mirror_maps()) {
            (Some(spec), true) => {
                assert!(
                    spec.holds_all(),
                    "a propagation whose mirror maps are elsewhere cannot step"
                );
                spec.hold_zeros(0..self.directions.len());
                spec.gather_all(&self.scene, &self.directions);
                Some(std::mem::take(&mut spec.maps))
            }
            _ => None,
        }
    }

    /// Ends an iteration of this process whose passes are all absorbed: the mirror maps back
    /// in, then [`Propagation::finish_iteration`].
    fn end_step(
        &mut self,
        mut work: IterationWork,
        maps: Option<Vec<specular::DirectionMaps>>,
        started: Instant,
    ) -> IterationStats {
        let l = self.directions.len();
        if let (Some(spec), Some(maps)) = (&mut self.specular, maps) {
            spec.maps = maps;
            // What a worker does for the directions it shoots (`compute_block`):
            // every mirror slot sent its unshot radiance once along its direction
            // (see `shoot::leaving`), so Total += Unshot; and Φ_in of the arrivals, settled.
            spec.maps
                .par_iter_mut()
                .for_each(|m| work::add_into(&mut m.total, &m.unshot));
            let directions = &self.directions;
            work.power_in = (0..l)
                .into_par_iter()
                .map(|d| spec.power_in_of(directions, d, &spec.maps[d].incident))
                .collect();
            // Settled batch by batch, as the service's workers settle what they shot.
            let batching = work.batching();
            let parts = spec.settle_batches(&self.scene, &batching, 0..batching.count(), &work.power_in);
            work.arrivals = parts.into_iter().map(Some).collect();
        }
        // This process gathers the arrivals next (`Specular::gather_all`).
        self.finish(work, started, true)
    }

    /// Ends an iteration whose passes are all absorbed: what arrived on
    /// mirrors waits to be reflected ([`specular::Pending`]: the exchange runs
    /// when the next iteration shoots it, here only its power is settled),
    /// diffuse surfaces reflect what they received (`Next = ρd · received`,
    /// filtered), `Total += Next`, and the held-back power joins the new
    /// unshot power. Reads no mirror map: a coordinator whose workers keep
    /// them finishes iterations with this too.
    pub fn finish_iteration(&mut self, work: IterationWork, started: Instant) -> IterationStats {
        self.finish(work, started, false)
    }

    /// [`Propagation::finish_iteration`]; `gathers_next` when this process gathers the arrivals
    /// it leaves pending (it runs the whole propagation), which then keeps every direction's
    /// `Φ_in`, turned around for its gathers ([`specular::Specular::prepare_gathers`]).
    fn finish(&mut self, mut work: IterationWork, started: Instant, gathers_next: bool) -> IterationStats {
        debug_assert!(
            work.next_expected().is_none(),
            "an iteration finished before its passes"
        );
        let index = work.index;
        // A copy shot elsewhere (another worker of this process) left its subfields here.
        self.rotated.clear(index);
        let l = self.directions.len();
        let first_lit = self.plan.first_mirror_iteration().unwrap_or(u32::MAX);
        // Settled where they were shot, batch by batch, and added up here in batch order: the
        // arrivals' reflected power is also what the mirrors hold unshot (see
        // `Specular::unshot_power`).
        let (exchange, settled) = match self.specular.as_mut() {
            Some(spec) if index >= first_lit && work.uses_mirror_maps() => {
                // Every batch's part, absorbed with its output (`apply_batch`) or settled here
                // (`end_step`). A pass absorbed without them (`IterationWork::absorb` alone, a
                // misuse) leaves those batches' arrivals unsettled: the exchange's power and the
                // batches gathered from then leave them out, which a debug build refuses.
                let none = specular::BatchArrivals::default();
                let missing = work.arrivals.iter().filter(|part| part.is_none()).count();
                debug_assert_eq!(missing, 0, "batches absorbed without their mirror arrivals");
                if missing > 0 {
                    tracing::warn!(
                        missing,
                        "batches absorbed without their mirror arrivals: left out of the exchange"
                    );
                }
                let parts = (work.arrivals.iter()).map(|part| part.as_ref().unwrap_or(&none));
                let settled = specular::Settled::of_parts(parts, work.batches());
                let exchange = settled.exchange;
                let mut pending = specular::Pending::new(settled);
                if gathers_next {
                    // This process shot every direction: every `Φ_in` is known here.
                    for (d, power) in std::mem::take(&mut work.power_in).into_iter().enumerate() {
                        pending.know(l, d, power);
                    }
                }
                spec.pending = Some(pending);
                if gathers_next {
                    spec.prepare_gathers();
                }
                (exchange, true)
            }
            _ => (Exchange::default(), false),
        };
        let mut next: Vec<Rgb> = (work.received.iter().zip(self.albedo.iter()))
            .map(|(r, rho)| [r[0] * rho[0], r[1] * rho[1], r[2] * rho[2]])
            .collect();
        if let Some(sigma) = self.plan.filter {
            filter::gaussian(&self.atlas, &self.projected_area, &mut next, sigma);
        }
        for ((n, total), carried) in next.iter_mut().zip(&mut self.total).zip(&work.carried) {
            for c in 0..3 {
                total[c] += n[c];
                n[c] += carried[c];
            }
        }
        self.current = next;
        let specular_unshot = match &self.specular {
            Some(_) if settled => exchange.reflected,
            Some(s) => s.unshot_power(&self.directions),
            None => [0.0; 3],
        };
        let stats = IterationStats {
            index,
            flow: work.flow.into(),
            unshot: self.unshot_power(),
            deferred_surfaces: work.deferred_surfaces,
            exchange,
            specular_unshot,
            seconds: started.elapsed().as_secs_f64(),
        };
        self.stats.push(stats.clone());
        stats
    }

    /// Bytes held by the field: subfield tables (those held, within a budget), the radiance maps of the
    /// texels and, with mirrors, their views and directional totals (f32).
    pub fn field_bytes(&self) -> usize {
        let layout = |l: &specular::MirrorLayout| l.entry_base.len() * 4 + l.entries.len() * 12;
        let specular = self.specular.as_ref().map_or(0, |s| {
            (s.views.iter())
                .map(|v| v.sub.memory_bytes() + layout(&v.layout) + v.slots() * 12)
                .sum::<usize>()
        });
        self.subfields.memory().live
            + self.atlas.texels * (std::mem::size_of::<[f32; 3]>() + std::mem::size_of::<f32>())
            + specular
    }

    /// The finished light field (radiance per texel), ready to render or save.
    pub fn into_field(self) -> crate::field::LightField {
        crate::field::LightField::from_propagation(self)
    }
}

/// `Φ_t / T_t` per texel (zero where no ray crosses the texel).
pub(crate) fn radiance_of(power: &[Rgb], area: &[f64]) -> Vec<Rgb> {
    power
        .iter()
        .zip(area)
        .map(|(p, &a)| {
            if a > 0.0 {
                [p[0] / a, p[1] / a, p[2] / a]
            } else {
                [0.0; 3]
            }
        })
        .collect()
}

/// The factor `k_c = π·A_c / T_c` by which each emitting chart's rays carry more (or less)
/// than its radiance `Le`, so that it emits its true power `π·Le·A_c` (`A_c` its area in ray
/// cells, `T_c = Σ_t T_t` over its texels); 1 for a chart that does not emit.
///
/// Why: the power an emitter puts into the field is `Le·T_c`, the rays that cross it. The
/// lattice phases ([`crate::psf::PsfFrame::shift`]) make `T_c` an unbiased estimate of
/// `π·A_c`, but for a lamp a few rays across it is still a noisy one (±1.5 % for a lamp of
/// 6.4 ray spacings over 129 directions), and every watt of that error is carried into
/// every wall's brightness. The receivers need no such factor: a texel's radiance is what
/// its own rays bring, divided by its own rays `T_t`, so its counting errors cancel. Nor
/// does the emitter's look: it shows `Le` ([`Propagation::diffuse_radiance`]).
pub(crate) fn emission_scales(scene: &Scene, atlas: &TexelAtlas, projected_area: &[f64], cell_area: f64) -> Vec<f64> {
    let mut rays = vec![0.0; atlas.charts.len()];
    for (c, g) in atlas.charts.iter().enumerate() {
        rays[c] = projected_area[g.first..g.first + g.len()].iter().sum::<f64>();
    }
    let mut area = vec![0.0; atlas.charts.len()];
    for (s, &c) in atlas.chart_of.iter().enumerate() {
        area[c as usize] += scene.surfaces[s].area;
    }
    (0..atlas.charts.len())
        .map(|c| {
            let emits = scene.materials[atlas.chart_material[c] as usize].is_emitter();
            if emits && rays[c] > 0.0 {
                std::f64::consts::PI * area[c] / cell_area / rays[c]
            } else {
                1.0
            }
        })
        .collect()
}

/// Times an iteration's phases ([`PhaseTimes`]) as they follow each other, each inside a
/// tracing span of its name: plan, then shooting interleaved with reductions, then the end.
struct PhaseClock {
    times: PhaseTimes,
    /// When the current phase began, and its span.
    since: Instant,
    span: Option<tracing::span::EnteredSpan>,
}

impl PhaseClock {
    fn start(started: Instant) -> PhaseClock {
        PhaseClock {
            times: PhaseTimes::default(),
            since: started,
            span: Some(tracing::debug_span!("plan").entered()),
        }
    }

    /// Seconds since the last mark, and a new span `name` from now.
    fn lap(&mut self, name: &'static str) -> f64 {
        self.span = None;
        let now = Instant::now();
        let seconds = now.duration_since(self.since).as_secs_f64();
        self.since = now;
        self.span = Some(match name {
            "shoot" => tracing::debug_span!("shoot").entered(),
            "reduce" => tracing::debug_span!("reduce").entered(),
            _ => tracing::debug_span!("finish").entered(),
        });
        seconds
    }

    fn planned(&mut self) {
        self.times.plan += self.lap("shoot");
    }

    fn reducing(&mut self) {
        self.times.shoot += self.lap("reduce");
    }

    fn reduced(&mut self) {
        self.times.reduce += self.lap("shoot");
    }

    /// Shooting (and reducing) is over; the end begins.
    fn shot(&mut self) {
        self.times.shoot += self.lap("finish");
    }

    fn finished(mut self) -> PhaseTimes {
        self.span = None;
        self.times.finish += self.since.elapsed().as_secs_f64();
        self.times
    }
}
