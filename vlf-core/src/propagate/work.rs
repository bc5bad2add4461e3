//! An iteration as work that can be split across threads, processes and
//! machines: **passes** over **batches** of directions, reduced in order.
//!
//! Every iteration is a short list of [`Pass`]es. A plain iteration has one,
//! [`Pass::Shoot`]: every true direction shoots the unshot radiance (and the
//! mirrors' directional unshot radiance) along its rays. A perturbed
//! iteration has two per rotated copy of the direction set: [`Pass::Areas`]
//! (the copy's discrete areas `T_t`, which the copy's radiance `Φ_t / T_t`
//! needs) and [`Pass::ShootCopy`]. They are listed every `Areas` first, then
//! every `ShootCopy`, and a pass needs only its
//! [`IterationWork::prerequisites`] (a copy's shooting needs that copy's
//! areas; the areas need nothing), so a distributed run can compute every
//! copy's areas at once and start shooting copy 0 while the others' areas
//! are still out: no barrier between passes that do not depend on each other.
//!
//! A pass is cut into batches of consecutive directions ([`Batching`]). A batch is
//! a pure function of the iteration's inputs ([`IterationWork`], derived
//! deterministically from the propagation's state), the pass results already
//! absorbed, and — for [`Pass::Shoot`] — the mirror maps of its own
//! directions and the arrivals of those it gathers from. Its output is a [`BatchSum`]: per-texel
//! power summed over the batch's directions **in direction order, starting
//! from zero** (a stint of consecutive directions into one buffer, then the
//! stints' buffers in order: [`Batching`]), and the batch's flow. The batch sums of a pass are added up
//! along a fixed binary tree ([`super::reduce`]), so a worker may compute a
//! whole aligned block of batches and send the block's node sum alone, and
//! [`IterationWork::absorb`] takes the blocks in order. So the bits of an
//! iteration do not depend on who computed which batch, how many batches a
//! lease held, or when it finished: a single process running the batches in
//! a loop ([`super::Propagation::step`]) and a coordinator collecting blocks
//! from any number of workers get the same field.
//!
//! Between iterations, what stays global is small: the texel maps (reduced
//! here) and, with mirrors, what each batch brought to the mirrors, settled
//! where it was shot ([`super::specular::BatchArrivals`]). The mirror
//! maps stay with their directions: a shooting batch first gathers its
//! directions' unshot maps from the last iteration's arrivals (the exchange,
//! see [`super::specular::Pending`]), and its output carries its directions'
//! new maps apart from what the coordinator absorbs ([`MirrorBlock`](super::MirrorBlock),
//! [`BatchOutput`](super::BatchOutput), `output.rs`).

use super::batching::{Batching, CHUNK};
use super::output::BatchSum;
use super::reduce::TreeSum;
use super::shoot::{self, Flow, Scratch};
use super::specular::{BatchArrivals, DirectionMaps, MirrorPower};
use super::{Propagation, perturb, radiance_of};
use crate::directions::DirectionSet;
use crate::psf::{RasterScratch, Subfield};
use crate::scene::Rgb;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// One map-reduce over the directions of an iteration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Pass {
    /// Shoot along the true directions; mirrors' maps take part.
    Shoot,
    /// Discrete areas of rotated copy `copy` of the direction set.
    Areas { copy: u32 },
    /// Shoot through rotated copy `copy`, carrying `1/count` of the power.
    ShootCopy { copy: u32 },
    /// Learn what the job's set-up learns over the true directions ([`super::SurveyPart`]):
    /// never a pass of an iteration, but the service leases it like one before the first, so
    /// that the workers rather than the coordinator walk every subfield's rays once.
    Survey,
}

/// The per-stint texel buffers (one colour per texel each: a chunk's
/// [`CHUNK`] in the plain loop, up to two per thread when stints are
/// claimed, `super::claim`), kept by a [`Propagation`] from one block or step
/// to the next. Allocated afresh each
/// time, their pages are zeroed by the kernel each time: a worker computing
/// its lease in single-batch blocks paid about 0.5 ms per block for it. Taken
/// by one block at a time (a second one meanwhile gets fresh buffers); a clone
/// of the propagation starts without. Kept `clean` when every buffer holds only zeros (as the
/// claimed schedule leaves them), so the next one need not clear them again.
#[derive(Default)]
pub(crate) struct KeptBuffers(std::sync::Mutex<Kept>);

#[derive(Default)]
struct Kept {
    buffers: Vec<Vec<Rgb>>,
    clean: bool,
}

impl KeptBuffers {
    fn take_kept(&self) -> Kept {
        std::mem::take(&mut *self.0.lock().unwrap_or_else(|p| p.into_inner()))
    }

    /// The buffers kept, as they were left.
    pub(crate) fn take(&self) -> Vec<Vec<Rgb>> {
        self.take_kept().buffers
    }

    /// The buffers kept, each [`cleared`] to `texels` zeros (unless they were kept clean).
    pub(crate) fn take_cleared(&self, texels: usize) -> Vec<Vec<Rgb>> {
        let Kept { mut buffers, clean } = self.take_kept();
        for b in &mut buffers {
            if !clean || b.len() != texels {
                cleared(b, texels);
            }
        }
        buffers
    }

    /// Keeps `buffers`, whatever they hold.
    pub(crate) fn keep(&self, buffers: Vec<Vec<Rgb>>) {
        *self.0.lock().unwrap_or_else(|p| p.into_inner()) = Kept { buffers, clean: false };
    }

    /// Keeps `buffers`, which hold only zeros.
    pub(crate) fn keep_clean(&self, buffers: Vec<Vec<Rgb>>) {
        *self.0.lock().unwrap_or_else(|p| p.into_inner()) = Kept { buffers, clean: true };
    }
}

impl Clone for KeptBuffers {
    fn clone(&self) -> Self {
        KeptBuffers::default()
    }
}

/// What one thread keeps from one direction to the next: the ray walk's scratch and, for
/// rotated copies, the subfield raster's.
#[derive(Default)]
pub(crate) struct DirectionScratch {
    shoot: Scratch,
    raster: RasterScratch,
}

/// What the passes of one iteration read, and what they have produced so far.
pub struct IterationWork {
    pub index: u32,
    /// Unshot power held back this iteration (deferred surfaces, and texels
    /// no ray of a rotated copy crosses).
    pub(crate) carried: Vec<Rgb>,
    pub(crate) deferred_surfaces: usize,
    mode: Mode,
    /// Received power, over the passes absorbed so far.
    pub(crate) received: Vec<Rgb>,
    pub(crate) flow: Flow,
    /// With mirror maps: per batch, what its directions brought to the mirrors, once absorbed.
    pub(crate) arrivals: Vec<Option<BatchArrivals>>,
    /// Every direction's `Φ_in`, where one process shot them all (empty elsewhere): its
    /// gathers read it next ([`super::specular::Pending`]).
    pub(crate) power_in: Vec<MirrorPower>,
    /// The pass being absorbed (its index) and its partial sums.
    cursor: usize,
    tree: TreeSum,
    batching: Batching,
}

enum Mode {
    /// Shoot the true directions with this radiance per texel; the mirror
    /// maps take part when `mirrors`.
    Direct { radiance: Vec<Rgb>, mirrors: bool },
    /// Shoot through rotated copies, each with `part` = 1/count of the power.
    Perturbed {
        part: Vec<Rgb>,
        copies: Vec<DirectionSet>,
        /// Radiance of each copy, once its areas are absorbed.
        radiance: Vec<Option<Vec<Rgb>>>,
    },
}

/// The passes of an iteration that shoots through `copies` rotated copies of
/// the directions (0: through the true directions), in the order they must
/// be absorbed: every pass comes after its [`Pass::prerequisites`].
fn passes_of(copies: u32) -> Vec<Pass> {
    if copies == 0 {
        return vec![Pass::Shoot];
    }
    let mut passes: Vec<Pass> = (0..copies)
        .flat_map(|copy| [Pass::Areas { copy }, Pass::ShootCopy { copy }])
        .collect();
    passes.sort_by_key(|pass| pass.absorbing_rank());
    passes
}

impl Pass {
    /// The passes whose results this one reads: its batches can be computed
    /// as soon as these are absorbed (or [`IterationWork::learn`]ed),
    /// whatever else is still running.
    pub fn prerequisites(self) -> Vec<Pass> {
        match self {
            Pass::ShootCopy { copy } => vec![Pass::Areas { copy }],
            Pass::Shoot | Pass::Areas { .. } | Pass::Survey => Vec::new(),
        }
    }

    /// The passes of an iteration that read this one's results: those that can open once it is
    /// absorbed (the inverse of [`Pass::prerequisites`]).
    pub fn dependents(self) -> Vec<Pass> {
        match self {
            Pass::Areas { copy } => vec![Pass::ShootCopy { copy }],
            Pass::Shoot | Pass::ShootCopy { .. } | Pass::Survey => Vec::new(),
        }
    }

    /// Where this pass comes in the order an iteration's passes are absorbed, lowest first: every
    /// copy's areas, then every copy's shot (`A0 A1 … S0 S1 …`), each after its
    /// [`Pass::prerequisites`]. [`IterationWork::passes`] is in this order.
    pub fn absorbing_rank(self) -> (u32, u32) {
        match self {
            Pass::Shoot | Pass::Survey => (0, 0),
            Pass::Areas { copy } => (0, copy),
            Pass::ShootCopy { copy } => (1, copy),
        }
    }

    /// Where this pass comes when one process shoots an iteration's passes, lowest first: a
    /// rotated copy's shot right after its areas, before the next copy's areas (`A0 S0 A1 S1 …`),
    /// so that the rotated subfields kept from the one to the other ([`super::rotated`]) are
    /// one copy's. [`IterationWork::shooting_order`] sorts by it, and the service leases the
    /// open passes in its order.
    pub fn shooting_rank(self) -> (u32, u32) {
        match self {
            Pass::Shoot | Pass::Survey => (0, 0),
            Pass::Areas { copy } => (copy, 0),
            Pass::ShootCopy { copy } => (copy, 1),
        }
    }
}

impl IterationWork {
    /// The passes of this iteration in the order one process shoots them: each rotated copy's
    /// shot right after its areas (`A0 S0 A1 S1 …`), so that the rotated subfields kept from the
    /// one to the other ([`super::rotated`]) are never more than one copy's. They are still
    /// absorbed in [`IterationWork::passes`]'s order (a shot's sum waits for the last areas):
    /// the same bits.
    pub fn shooting_order(&self) -> Vec<Pass> {
        let mut order = self.passes();
        order.sort_by_key(|pass| pass.shooting_rank());
        order
    }

    /// The passes of this iteration, in the order they must be absorbed:
    /// every pass comes after its [`prerequisites`](Self::prerequisites).
    pub fn passes(&self) -> Vec<Pass> {
        match &self.mode {
            Mode::Direct { .. } => passes_of(0),
            Mode::Perturbed { copies, .. } => passes_of(copies.len() as u32),
        }
    }

    /// The passes whose results `pass` reads ([`Pass::prerequisites`]).
    pub fn prerequisites(&self, pass: Pass) -> Vec<Pass> {
        pass.prerequisites()
    }

    /// Whether the results `pass` reads are known here.
    pub fn is_ready(&self, pass: Pass) -> bool {
        match (pass, &self.mode) {
            (Pass::ShootCopy { copy }, Mode::Perturbed { radiance, .. }) => {
                radiance.get(copy as usize).is_some_and(Option::is_some)
            }
            _ => true,
        }
    }

    /// Takes in the result of a prerequisite pass from the node sums of
    /// aligned blocks covering it, in order, reduced exactly as
    /// [`absorb`](Self::absorb) reduces them: how a worker learns a rotated
    /// copy's areas before shooting it. Only the coordinator's `absorb` moves
    /// the iteration forward; this touches nothing a later absorb reads twice.
    pub fn learn(
        &mut self,
        pass: Pass,
        blocks: impl IntoIterator<Item = (Range<usize>, BatchSum)>,
    ) -> crate::Result<()> {
        let Pass::Areas { copy } = pass else {
            return Err(crate::Error::Parameter(format!(
                "{pass:?} is no other pass's prerequisite"
            )));
        };
        if !self.passes().contains(&pass) {
            return Err(crate::Error::Parameter(format!(
                "{pass:?} is not a pass of iteration {}",
                self.index
            )));
        }
        if self.is_ready(Pass::ShootCopy { copy }) {
            return Ok(());
        }
        let texels = self.received.len();
        let mut tree = TreeSum::new(self.batching.count());
        for (batches, sum) in blocks {
            check_sum(pass, &batches, &sum, texels)?;
            tree.push(batches, sum)
                .map_err(|e| crate::Error::Decode(format!("{pass:?}: {e}")))?;
        }
        let Some(root) = tree.finish() else {
            return Err(crate::Error::Decode(format!(
                "{pass:?}: the blocks given do not cover its {} batches",
                self.batching.count()
            )));
        };
        self.finish_pass(pass, root.texels);
        Ok(())
    }

    /// Batches per pass.
    pub fn batches(&self) -> usize {
        self.batching.count()
    }

    /// How the passes are cut into batches (the job's [`Batching`]).
    pub fn batching(&self) -> Batching {
        self.batching
    }

    /// Whether the true directions' mirror maps take part (then batches of
    /// [`Pass::Shoot`] need the maps of their directions).
    pub fn uses_mirror_maps(&self) -> bool {
        matches!(self.mode, Mode::Direct { mirrors: true, .. })
    }

    /// The pass and first batch [`IterationWork::absorb`] expects next, or
    /// `None` when every pass is absorbed.
    pub fn next_expected(&self) -> Option<(Pass, usize)> {
        let passes = self.passes();
        passes.get(self.cursor).map(|&p| (p, self.tree.next()))
    }

    /// Adds the node sum of the aligned block `batches` of `pass`. Blocks
    /// must come in order, pass by pass (see the module docs); anything else
    /// is refused.
    pub fn absorb(&mut self, pass: Pass, batches: Range<usize>, sum: BatchSum) -> crate::Result<()> {
        let expected = self.next_expected();
        if expected.map(|(p, _)| p) != Some(pass) {
            return Err(crate::Error::Parameter(format!(
                "batches {batches:?} of {pass:?} out of order (expected {expected:?})"
            )));
        }
        check_sum(pass, &batches, &sum, self.received.len())?;
        self.tree
            .push(batches, sum)
            .map_err(|e| crate::Error::Parameter(format!("{pass:?}: {e}")))?;
        if self.tree.is_complete() {
            let tree = std::mem::replace(&mut self.tree, TreeSum::new(self.batching.count()));
            let root = tree.finish().expect("a complete tree has a root");
            if !matches!(pass, Pass::Areas { .. }) {
                let f = &root.flow;
                self.flow.add(&Flow {
                    shot: f.shot,
                    received: f.received,
                    escaped: f.escaped,
                    blocked: f.blocked,
                });
            }
            self.finish_pass(pass, root.texels);
            self.cursor += 1;
        }
        Ok(())
    }

    fn finish_pass(&mut self, pass: Pass, sum: Vec<Rgb>) {
        match (pass, &mut self.mode) {
            (Pass::Areas { copy }, Mode::Perturbed { part, radiance, .. }) => {
                let area: Vec<f64> = sum.iter().map(|a| a[0]).collect();
                for (t, a) in area.iter().enumerate() {
                    if *a <= 0.0 {
                        add_into(&mut self.carried[t..t + 1], &part[t..t + 1]);
                    }
                }
                radiance[copy as usize] = Some(radiance_of(part, &area));
            }
            _ => add_into(&mut self.received, &sum),
        }
    }

    /// The directions of batch `batch` (see [`Batching::range`]).
    pub fn batch_range(&self, batch: usize) -> Range<usize> {
        self.batching.range(batch)
    }
}

/// Refuses a block sum of the wrong size or with non-finite values.
fn check_sum(pass: Pass, batches: &Range<usize>, sum: &BatchSum, texels: usize) -> crate::Result<()> {
    if sum.texels.len() != texels {
        return Err(crate::Error::Decode(format!(
            "batches {batches:?} of {pass:?} have {} texels, the field {texels}",
            sum.texels.len()
        )));
    }
    if sum.texels.iter().flatten().any(|v| !v.is_finite()) || !sum.flow.is_finite() {
        return Err(crate::Error::Decode(format!(
            "batches {batches:?} of {pass:?} hold non-finite power"
        )));
    }
    Ok(())
}

impl Propagation {
    /// The passes of the next iteration, in absorbing order: those of
    /// [`Propagation::iteration_work`]'s, without computing what it shoots. A
    /// coordinator opens them for leasing before it builds its own work.
    pub fn iteration_passes(&self) -> Vec<Pass> {
        passes_of(self.perturbed_copies())
    }

    /// How many rotated copies the next iteration shoots through: 0 but in
    /// the perturbed first iterations. Perturbed copies only carry diffuse
    /// transport; with mirrors in the scene every iteration goes through the
    /// true directions (their maps exist only there).
    fn perturbed_copies(&self) -> u32 {
        let p = self.options.perturbation;
        let perturbed = self.iterations_done() < p.iterations && p.count > 0 && self.specular.is_none();
        if perturbed { p.count } else { 0 }
    }

    /// The inputs of the next iteration, fixed from the current state:
    /// deferral, the shooting radiance, perturbation and mirror plan.
    pub fn iteration_work(&self) -> IterationWork {
        let index = self.iterations_done();
        let texels = self.atlas.texels;

        // Deferred propagation: quiet charts keep their unshot power.
        let mut per_surface = vec![0.0f64; self.atlas.charts.len()];
        for (t, c) in self.current.iter().enumerate() {
            per_surface[self.owners[t] as usize] += super::luminance(c);
        }
        let unshot_total: f64 = per_surface.iter().sum();
        let deferred: Vec<bool> = match self.options.deferral {
            Some(threshold) if threshold > 0.0 => {
                let d: Vec<bool> = per_surface
                    .iter()
                    .map(|&p| p > 0.0 && p < threshold * unshot_total)
                    .collect();
                // Never defer everything: that would stall the iteration.
                if per_surface.iter().zip(&d).any(|(&p, &x)| p > 0.0 && !x) {
                    d
                } else {
                    vec![false; d.len()]
                }
            }
            _ => vec![false; per_surface.len()],
        };
        let mut carried = vec![[0.0; 3]; texels];
        let mut shooting = self.current.clone();
        for (t, c) in shooting.iter_mut().enumerate() {
            if deferred[self.owners[t] as usize] {
                carried[t] = *c;
                *c = [0.0; 3];
            }
        }

        let p = self.options.perturbation;
        let mode = if self.perturbed_copies() > 0 {
            let share = 1.0 / p.count as f64;
            Mode::Perturbed {
                part: shooting.iter().map(|v| v.map(|c| c * share)).collect(),
                copies: (0..p.count)
                    .map(|copy| {
                        self.directions
                            .rotated(perturb::rotation(&self.directions, index, copy, p.count))
                    })
                    .collect(),
                radiance: vec![None; p.count as usize],
            }
        } else {
            // Mirror work only once light can have reached a mirror.
            let first_lit = self.plan.first_mirror_iteration().unwrap_or(u32::MAX);
            let mirrors = self
                .specular
                .as_ref()
                .is_some_and(|s| index >= first_lit || s.has_unshot());
            Mode::Direct {
                radiance: radiance_of(&shooting, &self.projected_area),
                mirrors,
            }
        };
        IterationWork {
            index,
            carried,
            deferred_surfaces: deferred.iter().filter(|&&d| d).count(),
            received: vec![[0.0; 3]; texels],
            flow: Flow::default(),
            arrivals: match &mode {
                Mode::Direct { mirrors: true, .. } => vec![None; self.batching().count()],
                _ => Vec::new(),
            },
            power_in: Vec::new(),
            mode,
            cursor: 0,
            tree: TreeSum::new(self.batching().count()),
            batching: self.batching(),
        }
    }

    /// Shoots direction `d` of `pass` into `buf`, a value per texel of the field: adds what the
    /// direction delivers to each texel (received power, or its discrete area for
    /// [`Pass::Areas`]) onto what `buf` holds (zeros, or its stint's earlier directions:
    /// [`Propagation::shoot_stint`]), and returns where its power went. The caller clears it
    /// before a stint, so that one who has just read the buffer through (to add it to a sum)
    /// clears it in the same pass ([`add_and_clear`]) rather than in one more pass over a few
    /// hundred kB here. `maps` are its mirror maps when the pass shoots them
    /// ([`IterationWork::uses_mirror_maps`]): the incident radiance is added to them. A rotated
    /// copy's subfield is built here, in `scratch`, by its `Areas` pass, and kept for its
    /// `ShootCopy` pass where every subfield is held ([`super::rotated`]).
    pub(crate) fn shoot_direction(
        &self,
        work: &IterationWork,
        pass: Pass,
        d: usize,
        maps: Option<&mut MirrorIo>,
        buf: &mut [Rgb],
        scratch: &mut DirectionScratch,
    ) -> crate::Result<Flow> {
        let geometry = shoot::Geometry {
            scene: &self.scene,
            atlas: &self.atlas,
            stacking: &self.stacking,
        };
        debug_assert_eq!(buf.len(), self.atlas.texels, "a cleared buffer of the field's texels");
        let DirectionScratch { shoot: walk, raster } = scratch;
        match (pass, &work.mode) {
            (Pass::Shoot, Mode::Direct { radiance, mirrors }) => {
                let sub = self.subfields.get(d);
                let beam = shoot::Beam {
                    sub: &sub,
                    weight: self.directions.get(d).weight,
                };
                // Where each mirror entry's slots start in this subfield's numbering.
                let mirror_base = match (mirrors, self.specular.as_ref()) {
                    (true, Some(spec)) => spec.entry_base(d, &sub)?,
                    _ => Vec::new(),
                };
                let io = match (mirrors, maps, self.specular.as_ref()) {
                    (false, _, _) => None,
                    (true, Some(m), Some(_)) => Some(shoot::SpecularIo {
                        mirror_base: &mirror_base,
                        unshot: m.unshot,
                        incident: &mut *m.incident,
                    }),
                    (true, _, _) => {
                        return Err(crate::Error::Parameter(format!("direction {d} needs its mirror maps")));
                    }
                };
                Ok(shoot::shoot(geometry, beam, radiance, buf, io, walk))
            }
            (Pass::Areas { copy }, Mode::Perturbed { copies, .. }) if (copy as usize) < copies.len() => {
                let set = &copies[copy as usize];
                let sub = Subfield::build_with(&self.footprints, set.frame(d), self.options.grid, raster);
                self.rotated.count_build();
                let weight = set.get(d).weight;
                shoot::count(geometry, &sub, walk, |t| buf[t][0] += weight);
                // Kept for the copy's shot where no budget bounds the subfields (`super::rotated`).
                if !self.subfields.has_budget() {
                    self.rotated.keep(work.index, copy, d, sub, self.directions.len());
                }
                Ok(Flow::default())
            }
            (Pass::ShootCopy { copy }, Mode::Perturbed { copies, radiance, .. }) if (copy as usize) < copies.len() => {
                let Some(radiance) = &radiance[copy as usize] else {
                    return Err(crate::Error::Parameter(format!(
                        "{pass:?} before the areas of copy {copy} are absorbed"
                    )));
                };
                let set = &copies[copy as usize];
                let sub = self.rotated.take(work.index, copy, d).unwrap_or_else(|| {
                    self.rotated.count_build();
                    Subfield::build_with(&self.footprints, set.frame(d), self.options.grid, raster)
                });
                let beam = shoot::Beam {
                    sub: &sub,
                    weight: set.get(d).weight,
                };
                Ok(shoot::shoot(geometry, beam, radiance, buf, None, walk))
            }
            _ => Err(crate::Error::Parameter(format!(
                "{pass:?} is not a pass of iteration {}",
                work.index
            ))),
        }
    }

    /// Shoots the directions of stint `stint` of `pass` in order into `buf`, each adding onto
    /// what the ones before it left ([`Propagation::shoot_direction`]): the stint's term of its
    /// batch's sum ([`Batching`]). `maps` are the stint's directions' mirror maps, in order,
    /// when the pass shoots them. Returns each direction's flow, in order. The one kernel of
    /// every schedule: a batch shot CHUNK stints at a time ([`Propagation::run_batch`]) and
    /// stints claimed one by one (`super::claim`) compute exactly this, so they get the same
    /// bits.
    pub(crate) fn shoot_stint(
        &self,
        work: &IterationWork,
        pass: Pass,
        stint: Range<usize>,
        mut maps: Option<&mut [MirrorIo]>,
        buf: &mut [Rgb],
        scratch: &mut DirectionScratch,
    ) -> crate::Result<Vec<Flow>> {
        stint
            .enumerate()
            .map(|(i, d)| {
                let own = maps.as_deref_mut().and_then(|m| m.get_mut(i));
                self.shoot_direction(work, pass, d, own, buf, scratch)
            })
            .collect()
    }

    /// Computes batch `batch` of `pass` of `work`. `maps` are the mirror maps
    /// of the batch's directions, in order, when [`Pass::Shoot`] uses them
    /// ([`IterationWork::uses_mirror_maps`]); they receive the incident
    /// radiance and the totals. Stints run in parallel; the sum is in
    /// stint order.
    pub fn run_batch(
        &self,
        work: &IterationWork,
        pass: Pass,
        batch: usize,
        maps: Option<&mut [DirectionMaps]>,
    ) -> crate::Result<BatchSum> {
        let mut io = maps.map(mirror_io);
        self.run_batch_with(work, pass, batch, io.as_deref_mut(), &mut Vec::new())
    }

    /// [`Propagation::run_batch`] with `buffers`, the per-stint texel
    /// buffers of a chunk, kept by the caller from batch to batch: allocating
    /// them afresh for every direction (a few hundred kB each) made the
    /// kernel map and fault in pages faster than the propagation used them.
    pub(crate) fn run_batch_with(
        &self,
        work: &IterationWork,
        pass: Pass,
        batch: usize,
        maps: Option<&mut [MirrorIo]>,
        buffers: &mut Vec<Vec<Rgb>>,
    ) -> crate::Result<BatchSum> {
        let range = work.batch_range(batch);
        if range.is_empty() {
            return Err(crate::Error::Parameter(format!(
                "batch {batch} out of range ({} batches)",
                work.batches()
            )));
        }
        if let (Pass::Shoot, Mode::Direct { mirrors: true, .. }) = (pass, &work.mode)
            && maps.as_ref().is_none_or(|m| m.len() != range.len())
        {
            return Err(crate::Error::Parameter(format!(
                "batch {batch} needs the mirror maps of its {} directions",
                range.len()
            )));
        }
        if let (Some(maps), Some(spec)) = (maps.as_ref(), &self.specular) {
            let unfit =
                |(d, m): &(usize, &MirrorIo)| m.unshot.len() != spec.slots(*d) || m.incident.len() != spec.slots(*d);
            if let Some((d, _)) = range.clone().zip(maps.iter()).find(unfit) {
                return Err(crate::Error::Parameter(format!(
                    "direction {d}: its mirror maps are not held (one value per mirror slot)"
                )));
            }
        }
        // The batch's stints, CHUNK at a time: each chunk's stints in parallel, each into its
        // own buffer, then added to the sum in stint order (how many at a time changes nothing
        // but the memory: CHUNK buffers, as when a stint was one direction).
        let stints: Vec<Range<usize>> = work.batching.stints(batch).collect();
        if buffers.len() < CHUNK {
            buffers.resize_with(CHUNK, Vec::new);
        }
        // The stints' mirror maps, each its own slice.
        let mut maps_of: Vec<Option<&mut [MirrorIo]>> = match maps.and_then(|m| split_by_stint(m, &stints)) {
            Some(own) => own.into_iter().map(Some).collect(),
            None => stints.iter().map(|_| None).collect(),
        };
        // Σ over the batch's stints in order, from zero; texel blocks in
        // parallel (each texel's additions stay in order).
        let mut sum = vec![[0.0; 3]; self.atlas.texels];
        let mut flow = Flow::default();
        for (group, maps) in stints.chunks(CHUNK).zip(maps_of.chunks_mut(CHUNK)) {
            let bufs = &mut buffers[..group.len()];
            let flows: Vec<Vec<Flow>> = group
                .par_iter()
                .zip(maps.par_iter_mut())
                .zip(bufs.par_iter_mut())
                .map_init(DirectionScratch::default, |scratch, ((stint, maps), buf)| {
                    cleared(buf, self.atlas.texels);
                    self.shoot_stint(work, pass, stint.clone(), maps.as_deref_mut(), buf, scratch)
                })
                .collect::<crate::Result<_>>()?;
            let bufs = &*bufs;
            sum.par_chunks_mut(4096).enumerate().for_each(|(c, block)| {
                let base = c * 4096;
                for buf in bufs {
                    add_into(block, &buf[base..base + block.len()]);
                }
            });
            for f in flows.iter().flatten() {
                flow.add(f);
            }
        }
        Ok(BatchSum {
            texels: sum,
            flow: flow.into(),
        })
    }
}

/// What shooting one direction reads and writes of its mirror maps: the
/// unshot radiance its mirror slots send, and the incident radiance they
/// receive (added to). Borrowed separately so that a worker shoots from its
/// unshot maps in place into fresh incident maps.
pub(crate) struct MirrorIo<'a> {
    pub unshot: &'a [Rgb],
    pub incident: &'a mut [Rgb],
}

/// `items`, one per direction of consecutive `stints`, cut into one slice per stint; `None`
/// unless they are exactly the stints' directions' (a pass that shoots no mirror maps may be
/// handed some anyway).
pub(crate) fn split_by_stint<'a, 's, T>(
    items: &'a mut [T],
    stints: impl IntoIterator<Item = &'s Range<usize>>,
) -> Option<Vec<&'a mut [T]>> {
    let mut rest = items;
    let mut own = Vec::new();
    for stint in stints {
        if stint.len() > rest.len() {
            return None;
        }
        let (head, tail) = std::mem::take(&mut rest).split_at_mut(stint.len());
        own.push(head);
        rest = tail;
    }
    rest.is_empty().then_some(own)
}

/// The shooting view of whole mirror maps (the in-process step's own).
pub(crate) fn mirror_io(maps: &mut [DirectionMaps]) -> Vec<MirrorIo<'_>> {
    maps.iter_mut()
        .map(|m| MirrorIo {
            unshot: &m.unshot,
            incident: &mut m.incident,
        })
        .collect()
}

/// `acc += v`, texel by texel.
pub(crate) fn add_into(acc: &mut [Rgb], v: &[Rgb]) {
    for (a, b) in acc.iter_mut().zip(v) {
        a[0] += b[0];
        a[1] += b[1];
        a[2] += b[2];
    }
}

/// `acc += v`, then `v = 0`, texel by texel: a shot stint's buffer added to its batch's sum
/// and left [`cleared`] for the next stint in the one pass that reads it (the same additions
/// as [`add_into`]).
pub(crate) fn add_and_clear(acc: &mut [Rgb], v: &mut [Rgb]) {
    for (a, b) in acc.iter_mut().zip(v) {
        a[0] += b[0];
        a[1] += b[1];
        a[2] += b[2];
        *b = [0.0; 3];
    }
}

/// Makes `buf` `texels` zeros, as [`Propagation::shoot_direction`] takes it.
pub(crate) fn cleared(buf: &mut Vec<Rgb>, texels: usize) {
    buf.clear();
    buf.resize(texels, [0.0; 3]);
}
