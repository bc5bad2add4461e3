//! The worker's side of an iteration: a [`Replica`] computes leased blocks and writes their
//! outputs and mirror maps into the store. Apart from the coordinator because the two meet only
//! through the store's keys: a worker holds maps and state of its own that the coordinator never
//! sees, and the reverse.

use super::cover::cheapest_cover;
use crate::error::StoreError;
use crate::field::{FieldJob, ReleasedState};
use crate::layout::MapPart;
use crate::store::{Put, Writing};
use rayon::prelude::*;
use std::collections::HashSet;
use std::ops::Range;
use std::time::Instant;
use vlf_core::propagate::reduce::RunOutputs;
use vlf_core::propagate::{BatchOutput, IterationWork, MapBatch, MapKind, MirrorBlock, Pass, Propagation};

/// A worker's copy of a job's propagation: the geometry is built once; each iteration restores
/// the state from the store — except the mirror maps this replica computed itself, which it
/// keeps (see [`Replica::compute`]).
pub struct Replica {
    job: FieldJob,
    prop: Propagation,
    /// The iteration being worked on, its work (with the prerequisites learnt so far) and which
    /// batches' mirror maps of its snapshot are restored.
    current: Option<Current>,
    /// Mirror maps this replica computed: parts of the snapshot after the current iteration.
    held: Vec<MirrorBlock>,
    /// Their blobs, encoded: the last block's, not started yet (they go out when the next block
    /// starts computing, or with the run's outputs); and those on their way into the store while
    /// a later block computes, waited for with the outputs.
    unwritten: Vec<Put>,
    writing: Vec<Writing>,
    /// The snapshot whose whole state `prop` holds, if any (a prototype's): nothing of it is
    /// read from the store.
    holds_snapshot: Option<u32>,
    /// Blocks of passes of an iteration that the coordinator absorbed, as a lease names them
    /// ([`Replica::absorbed`]): `(k, pass, blocks)`.
    absorbed: Vec<(u32, Pass, Vec<Range<usize>>)>,
    /// What each batch of the last computation cost (see [`Replica::batch_costs`]).
    costs: Vec<f64>,
    /// Where the last computation's wall time went ([`Replica::phase_seconds`]).
    phases: ReplicaPhases,
    /// Mirror-map parts of a later snapshot read ahead ([`Replica::adopt_ahead`]).
    ahead: Option<ReadAhead>,
}

/// Mirror-map parts of the next snapshot that a worker reads while the coordinator ends the
/// iteration ([`Replica::read_ahead`]), rather than after it releases the next one.
///
/// A worker's home stays put from one iteration to the next, so the arrivals that cross into it
/// from the other workers' homes are the same parts each time: those its leases read this
/// iteration. The other workers write them as they compute, block by block; once this worker
/// is done with the iteration it waits — for the slowest worker, then for the coordinator to
/// absorb the last outputs, reflect the diffuse light and write the next head — and reads the
/// parts written by then. The next iteration's start then reads only the head and the parts
/// that were not there yet, and decodes nothing more: with two workers on the mirror scene,
/// about a megabyte of maps a worker decoded on the iteration's critical path.
///
/// Safe to read before the release: a part is written create-only, once, as a pure function of
/// the job (a block computed twice writes the same bytes), so a part that is there is the one
/// the next iteration reads. A part that is missing or fails to decode is simply left to the
/// start, which reads it with the head and reports what is wrong with it.
pub struct ReadAhead {
    job: FieldJob,
    snapshot: u32,
    parts: Vec<(MapPart, usize)>,
    maps: Vec<(MapPart, MapBatch)>,
}

impl ReadAhead {
    /// The snapshot whose parts it reads.
    pub fn snapshot(&self) -> u32 {
        self.snapshot
    }

    /// Reads the parts written so far, in one bulk read, and decodes them (on the caller's
    /// rayon pool). What cannot be read is left to the iteration's start.
    pub fn fetch(mut self) -> ReadAhead {
        if let Ok(maps) = self.job.written_maps(self.snapshot, &self.parts) {
            self.maps = maps;
        }
        self
    }

    /// How many of its parts were read.
    pub fn fetched(&self) -> usize {
        self.maps.len()
    }
}

/// The mirror maps a replica holds ([`Replica::held_maps`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct HeldMaps {
    /// Bytes of their values.
    pub bytes: usize,
    /// The directions whose maps they are.
    pub directions: std::collections::BTreeSet<usize>,
}

struct Current {
    k: u32,
    work: IterationWork,
    /// Per batch: its shooting maps restored, its totals restored.
    shooting: Vec<bool>,
    totals: Vec<bool>,
    /// The mirror-map parts its leases read from the store so far, and those fetched with the
    /// head (a guess) that no lease asked for yet.
    read: Vec<(MapPart, usize)>,
    prefetched: HashSet<(MapPart, usize)>,
    /// The outputs this replica computed of passes that later passes of the iteration read (a
    /// rotated copy's areas, which its shooting needs whole): those learn them from here, and
    /// read from the store only what other workers computed.
    own: Vec<BatchOutput>,
}

impl Replica {
    /// Opens `job` and builds its geometry.
    pub fn new(job: FieldJob) -> Result<Replica, StoreError> {
        Replica::within(job, None)
    }

    /// Opens `job` and builds its geometry ([`FieldJob::propagation`]), holding at most `budget`
    /// bytes of subfields when one is given: a worker then holds the subfields of the directions
    /// its leases shoot (its home, which stays put from one iteration to the next), not the
    /// whole field's, and computes the same bits. With the job's stored survey it also builds
    /// only those, as it shoots them: its set-up is its share of the field's, not all of it.
    pub fn within(job: FieldJob, budget: Option<usize>) -> Result<Replica, StoreError> {
        let prop = job.propagation(budget)?;
        Ok(Replica::with_propagation(job, prop))
    }

    /// The propagation this replica computes blocks on.
    pub fn propagation(&self) -> &Propagation {
        &self.prop
    }

    /// What this replica's subfields hold and held ([`vlf_core::psf::SubfieldMemory`]).
    pub fn subfield_memory(&self) -> vlf_core::psf::SubfieldMemory {
        self.prop.subfields.memory()
    }

    /// How many subfields of rotated copies this replica built so far: once each where no budget
    /// bounds its subfields and each copy is shot after its areas, as the service leases them
    /// ([`Propagation::rotated_subfields_built`]).
    pub fn rotated_subfields_built(&self) -> usize {
        self.prop.rotated_subfields_built()
    }

    /// Rotated subfields it keeps now, from a copy's areas for its shot.
    pub fn rotated_subfields_kept(&self) -> usize {
        self.prop.rotated_subfields_kept()
    }

    /// The mirror maps this replica holds now: those restored into its propagation, those of
    /// the blocks it computed for the next snapshot, and the parts it read ahead. Those of the
    /// directions its leases shoot and gather from, not of the whole field
    /// ([`vlf_core::propagate::specular::Unheld`]).
    pub fn held_maps(&self) -> HeldMaps {
        let mut held = HeldMaps::default();
        if let Some(spec) = &self.prop.specular {
            held.bytes += spec.held_bytes();
            held.directions.extend(spec.held_directions());
        }
        let batching = self.prop.batching();
        for block in &self.held {
            held.bytes += block.bytes();
            let (first, end) = (block.batches.start as usize, block.batches.end as usize);
            held.directions.extend(batching.directions_of(first..end));
        }
        for (_, part) in self.ahead.iter().flat_map(|a| &a.maps) {
            held.bytes += part.bytes();
            held.directions.extend(batching.range(part.batch as usize));
        }
        held
    }

    /// A replica of `job` over `prop`, a propagation of the same scene and options (built by
    /// someone else in this process: the geometry is not built twice). Its state is restored
    /// from the store before every iteration, so what it holds now does not matter. With
    /// mirrors, the routes are turned around for settling what its blocks shoot now, as part
    /// of its set-up ([`vlf_core::propagate::Specular::prepare_settle`]).
    pub fn with_propagation(job: FieldJob, prop: Propagation) -> Replica {
        if let Some(spec) = &prop.specular {
            spec.prepare_settle();
        }
        Replica {
            job,
            prop,
            current: None,
            held: Vec::new(),
            unwritten: Vec::new(),
            writing: Vec::new(),
            holds_snapshot: None,
            absorbed: Vec::new(),
            costs: Vec::new(),
            phases: ReplicaPhases::default(),
            ahead: None,
        }
    }

    /// A replica of `job` over `prop`, the job's whole state at its snapshot
    /// `prop.iterations_done()` — as a coordinator in this process holds it when it takes the job
    /// up ([`Prototypes`](super::Prototypes)): the iteration from that snapshot reads nothing of it from the store
    /// (the same bits: the snapshot was written from that state).
    ///
    /// A propagation whose mirror maps are elsewhere (a coordinator whose workers shot them)
    /// holds only part of the snapshot: the replica then reads the maps from the store as any
    /// other does.
    pub fn at_snapshot(job: FieldJob, prop: Propagation) -> Replica {
        let k = prop.iterations_done();
        let whole = prop.specular.as_ref().is_none_or(|s| s.holds_all());
        Replica {
            holds_snapshot: whole.then_some(k),
            ..Replica::with_propagation(job, prop)
        }
    }

    /// Computes the aligned block `batches` of `pass` of the iteration starting from snapshot `k`
    /// and writes its output into the store: the mirror maps of its directions (the next
    /// snapshot's parts, create-only), then the block output that the coordinator absorbs. The
    /// pass's prerequisites must be complete in the store.
    ///
    /// What it reads: the snapshot's head, and for a shooting pass with mirrors the maps
    /// [`Propagation::mirror_batches_read`] names — but not those it computed itself in the
    /// iteration before (kept in memory: the same bits as the store's). So a worker that shoots
    /// the same directions every iteration, and gathers from directions it shoots, reads no
    /// mirror map back; with one worker, none at all.
    pub fn compute(&mut self, k: u32, pass: Pass, batches: Range<usize>) -> Result<(), StoreError> {
        self.settle_failed();
        self.costs.clear();
        self.phases = ReplicaPhases::default();
        let out = self.shoot(k, pass, batches)?;
        let outputs = [out];
        let writing = Instant::now();
        self.write_outputs(&outputs)?;
        self.phases.outputs += writing.elapsed().as_secs_f64();
        self.keep_for_later_passes(outputs);
        Ok(())
    }

    /// Seconds the last [`Replica::compute`] or run spent computing its blocks — shooting,
    /// gathering and all else a block does, encoding their mirror maps, and for a run
    /// serialising its outputs — without the waits for the store (the head, the maps and areas
    /// read, the outputs written) or decoding what it read. What a lease reports: the
    /// coordinator splits the next pass among workers by what their batches cost, and a wait of
    /// a round trip per lease, spread over its batches, would make the batches of a worker with
    /// fewer of them look dearer, and its next share smaller still.
    pub fn compute_seconds(&self) -> f64 {
        self.costs.iter().sum()
    }

    /// What each batch of the last [`Replica::compute`] or run cost to compute, in order, in
    /// seconds (see [`Replica::compute_seconds`]): a block's batches are timed one by one as they
    /// shoot, its gathering shared evenly among them, and the whole then scaled to all the block
    /// took ([`Propagation::compute_block_costed`]); encoding the block's mirror maps and a
    /// run's outputs is shared evenly on top.
    pub fn batch_costs(&self) -> &[f64] {
        &self.costs
    }

    /// Where the last [`Replica::compute`] or run spent its wall time, phase by phase: what a
    /// worker logs with each lease (`lease run`), to tell computing from the rest.
    pub fn phase_seconds(&self) -> ReplicaPhases {
        self.phases
    }

    /// Tells the replica which blocks of `pass` of the iteration from snapshot `k` the
    /// coordinator absorbed (a lease names those of the passes it reads): a pass that needs them
    /// then reads the ones it did not compute itself without listing the store first.
    pub fn absorbed(&mut self, k: u32, pass: Pass, blocks: Vec<Range<usize>>) {
        self.absorbed.retain(|(at, p, _)| *at == k && *p != pass);
        self.absorbed.push((k, pass, blocks));
    }

    /// What to read ahead of the iteration after the one from snapshot `k`, once this replica
    /// computed a run of `pass` of it ([`ReadAhead`]): the mirror-map parts of snapshot `k + 1`
    /// its leases will read again — those they read of snapshot `k`. `None` unless `pass` is the
    /// iteration's last (before that, more leases of the iteration may come) and some part was
    /// read.
    pub fn read_ahead(&self, k: u32, pass: Pass) -> Option<ReadAhead> {
        let current = self.current.as_ref().filter(|c| c.k == k)?;
        if current.work.passes().last() != Some(&pass) || current.read.is_empty() {
            return None;
        }
        Some(ReadAhead {
            job: self.job.clone(),
            snapshot: k + 1,
            parts: current.read.clone(),
            maps: Vec::new(),
        })
    }

    /// Hands the replica parts read ahead ([`Replica::read_ahead`], then [`ReadAhead::fetch`]):
    /// the start of the iteration from their snapshot restores them instead of reading them.
    /// Those of another job or snapshot are dropped there.
    pub fn adopt_ahead(&mut self, ahead: ReadAhead) {
        self.ahead = (ahead.job.id() == self.job.id()).then_some(ahead);
    }

    /// Computes a run of `pass` from batch `start`, one aligned block at a time, as `next` hands
    /// them out — `next(done)` is the block that starts at `done`, or `None` to stop there — and
    /// writes the run's outputs, merged into the blocks of
    /// [`vlf_core::propagate::reduce::cover`] (the same outputs as
    /// [`Replica::compute`] of those blocks). Returns the run computed. A worker computes a lease
    /// so when it must claim the lease's batches as it goes (see `vlf_worker`).
    pub fn compute_run(
        &mut self,
        k: u32,
        pass: Pass,
        start: usize,
        next: impl FnMut(usize) -> Option<Range<usize>>,
    ) -> Result<Range<usize>, StoreError> {
        let (run, writes) = self.compute_run_behind(k, pass, start, next)?;
        writes.wait()?;
        Ok(run)
    }

    /// [`Replica::compute_run`], returning as soon as the run is computed: its outputs and
    /// mirror maps are still on their way into the store, until the [`Writing`] returned is
    /// done. A worker whose store is a round trip away computes its next lease meanwhile, and
    /// reports this one once the writes are done (the report says the outputs are there).
    pub fn compute_run_behind(
        &mut self,
        k: u32,
        pass: Pass,
        start: usize,
        mut next: impl FnMut(usize) -> Option<Range<usize>>,
    ) -> Result<(Range<usize>, Writing), StoreError> {
        self.settle_failed();
        self.costs.clear();
        self.phases = ReplicaPhases::default();
        let mut outputs = RunOutputs::new();
        let mut done = start;
        while let Some(block) = next(done) {
            if block.start != done || block.is_empty() {
                return Err(self.job.field_error(vlf_core::Error::Parameter(format!(
                    "block {block:?} does not continue the run at batch {done}"
                ))));
            }
            done = block.end;
            let out = self.shoot(k, pass, block)?;
            outputs
                .push(out)
                .map_err(|e| self.job.field_error(vlf_core::Error::Parameter(e)))?;
        }
        let outputs = outputs.finish();
        let writing = Instant::now();
        let writes = self.write_outputs_behind(&outputs)?;
        let serialised = writing.elapsed().as_secs_f64();
        self.phases.outputs += serialised;
        // Serialising and compressing the outputs (the writes go on behind) is the batches' work,
        // as encoding their maps is: shared evenly among them.
        share_evenly(&mut self.costs, serialised);
        self.keep_for_later_passes(outputs);
        Ok((start..done, writes))
    }

    /// Writes `outputs` along with the mirror maps still on their way, and waits for both: one
    /// round trip. An output in the store does not say its maps are (a worker may stop between
    /// the two); the report that follows does, and a coordinator that finds outputs no report
    /// told it of checks their maps first ([`Coordinator::blocks_in_store`](super::Coordinator::blocks_in_store)).
    fn write_outputs(&mut self, outputs: &[BatchOutput]) -> Result<(), StoreError> {
        self.write_outputs_behind(outputs)?.wait()
    }

    /// [`Replica::write_outputs`] without the wait: the writes of `outputs` and of every mirror
    /// map still on its way, as one [`Writing`].
    fn write_outputs_behind(&mut self, outputs: &[BatchOutput]) -> Result<Writing, StoreError> {
        let mut puts = outputs
            .par_iter()
            .map(|out| self.job.batch_put(out))
            .collect::<Result<Vec<_>, _>>()?;
        puts.append(&mut self.unwritten);
        let store = self.job.job().store();
        let mut writes = std::mem::take(&mut self.writing);
        writes.push(store.put_all_behind(puts)?);
        Writing::all(store, writes)
    }

    /// Keeps the outputs just written that a later pass of the iteration reads (see
    /// [`Current::own`]).
    fn keep_for_later_passes(&mut self, outputs: impl IntoIterator<Item = BatchOutput>) {
        let Some(current) = self.current.as_mut() else {
            return;
        };
        let passes = current.work.passes();
        let read_later = |pass: Pass| passes.iter().any(|&p| current.work.prerequisites(p).contains(&pass));
        let kept: Vec<BatchOutput> = outputs
            .into_iter()
            .filter(|out| out.iteration == current.k && read_later(out.pass))
            .collect();
        current.own.extend(kept);
    }

    /// Starts writing the last block's mirror maps, to go on while the next block computes.
    fn write_behind(&mut self) -> Result<(), StoreError> {
        if !self.unwritten.is_empty() {
            let puts = std::mem::take(&mut self.unwritten);
            self.writing.push(self.job.job().store().put_all_behind(puts)?);
        }
        Ok(())
    }

    /// Forgets what a lease that failed before its outputs left unwritten, and lets what it
    /// started finish: its error was reported with it.
    fn settle_failed(&mut self) {
        self.unwritten.clear();
        let _ = Writing::wait_all(std::mem::take(&mut self.writing));
    }

    /// [`Replica::compute`] but for writing the block's output: returns it.
    fn shoot(&mut self, k: u32, pass: Pass, batches: Range<usize>) -> Result<BatchOutput, StoreError> {
        self.write_behind()?;
        if self.current.as_ref().map(|c| c.k) != Some(k) {
            let starting = Instant::now();
            self.start(k)?;
            self.phases.start += starting.elapsed().as_secs_f64();
        }
        let reading = Instant::now();
        let Some(current) = self.current.as_mut() else {
            unreachable!("started just above");
        };
        let work = &mut current.work;
        let passes = work.passes();
        if !passes.contains(&pass) {
            return Err(self.job.field_error(vlf_core::Error::Parameter(format!(
                "{pass:?} is not a pass of iteration {k} (its passes: {passes:?})"
            ))));
        }
        // The mirror maps the block reads that this replica does not hold yet.
        let (shooting, totals) = self
            .prop
            .mirror_batches_read(work, pass, batches.clone())
            .map_err(|e| self.job.field_error(e))?;
        let missing = |wanted: Vec<usize>, have: &[bool]| -> Vec<usize> {
            wanted.into_iter().filter(|&b| have.get(b) == Some(&false)).collect()
        };
        // Parts fetched with the head that this block wanted: the guess was right, keep it.
        let guessed =
            (shooting.iter().map(|&b| (MapPart::Shooting, b))).chain(totals.iter().map(|&b| (MapPart::Totals, b)));
        for part in guessed {
            if current.prefetched.remove(&part) {
                current.read.push(part);
            }
        }
        let (shooting, totals) = (missing(shooting, &current.shooting), missing(totals, &current.totals));
        // One bulk read for both kinds: their round trips overlap, however few threads compute.
        let wanted: Vec<(MapPart, usize)> = (shooting.iter().map(|&b| (MapPart::Shooting, b)))
            .chain(totals.iter().map(|&b| (MapPart::Totals, b)))
            .collect();
        let read = self.job.released_map_parts(k, &wanted)?;
        current.read.extend(&wanted);
        for ((part, _), maps) in wanted.iter().zip(read) {
            let restored = match part {
                MapPart::Totals => self.prop.restore_totals_batch(maps),
                _ => self.prop.restore_shooting_batch(maps),
            };
            restored.map_err(|e| self.job.field_error(e))?;
        }
        shooting.into_iter().for_each(|b| current.shooting[b] = true);
        totals.into_iter().for_each(|b| current.totals[b] = true);
        self.phases.map_reads += reading.elapsed().as_secs_f64();
        let learning = Instant::now();
        // Learn what the pass reads (a rotated copy's areas): the blocks this replica computed
        // from memory, the others from the store — those the lease named, or else those listed.
        if !work.is_ready(pass) {
            for earlier in work.prerequisites(pass) {
                let n = work.batches();
                let own: Vec<Range<usize>> = (current.own.iter())
                    .filter(|o| o.pass == earlier)
                    .map(|o| o.batches.start as usize..o.batches.end as usize)
                    .collect();
                let plan = match cheapest_cover(&own, &[], n) {
                    Some(plan) => plan,
                    None => {
                        let named = (self.absorbed.iter()).find(|(at, p, _)| (*at, *p) == (k, earlier));
                        let stored = match named {
                            Some((_, _, blocks)) => blocks.clone(),
                            None => self.job.stored_blocks(k, earlier)?,
                        };
                        cheapest_cover(&own, &stored, n).ok_or_else(|| {
                            self.job.field_error(vlf_core::Error::Parameter(format!(
                                "{pass:?} of iteration {k} needs {earlier:?}, whose blocks in the store ({stored:?}) \
                                 and here ({own:?}) do not cover its {n} batches"
                            )))
                        })?
                    }
                };
                let to_read: Vec<Range<usize>> = (plan.iter())
                    .filter(|(_, held)| !held)
                    .map(|(b, _)| b.clone())
                    .collect();
                let mut read = self.job.get_batches(k, earlier, &to_read)?.into_iter();
                // Learnt once: the pass needs them no more.
                let (mut held, others): (Vec<BatchOutput>, Vec<BatchOutput>) = std::mem::take(&mut current.own)
                    .into_iter()
                    .partition(|o| o.pass == earlier);
                current.own = others;
                let mut sums = Vec::with_capacity(plan.len());
                for (block, from_here) in plan {
                    let out = if from_here {
                        let at = held
                            .iter()
                            .position(|o| o.batches == (block.start as u32..block.end as u32));
                        at.map(|i| held.swap_remove(i))
                    } else {
                        read.next()
                    };
                    let Some(out) = out else {
                        unreachable!("the plan takes its blocks from those held and read");
                    };
                    sums.push((block, out.sum));
                }
                work.learn(earlier, sums).map_err(|e| self.job.field_error(e))?;
            }
        }
        self.phases.prerequisites += learning.elapsed().as_secs_f64();
        let computing = Instant::now();
        let (out, block, mut costs) = self
            .prop
            .compute_block_costed(work, pass, batches.clone())
            .map_err(|e| self.job.field_error(e))?;
        self.phases.compute += computing.elapsed().as_secs_f64();
        let encoding = Instant::now();
        if let Some(block) = block {
            // The block took its directions' totals with it: computing it again reads them.
            batches.for_each(|b| current.totals[b] = false);
            let (job, batching) = (self.job.job(), self.prop.batching());
            // Each batch's parts compressed as they are serialised, not all serialised first.
            let puts = (block.batches.clone().into_par_iter())
                .flat_map_iter(|b| {
                    let put = |part: MapPart, kind: MapKind| {
                        job.map_part_put(k + 1, part, b, &block.batch_bytes(batching, b, kind))
                    };
                    [
                        put(MapPart::Shooting, MapKind::Shooting),
                        put(MapPart::Totals, MapKind::Totals),
                        self.job.mirror_radiance_put(k + 1, b, &block.batch_totals(batching, b)),
                    ]
                })
                .collect::<Result<Vec<_>, _>>()?;
            self.unwritten = puts;
            self.held.push(block);
        }
        let encoded = encoding.elapsed().as_secs_f64();
        self.phases.encode += encoded;
        share_evenly(&mut costs, encoded);
        self.costs.extend(costs);
        Ok(out)
    }

    /// Moves on to the iteration that starts from snapshot `k`. Every lease reads the head of
    /// the shooting state (statistics, Current, what the pending arrivals come to): written before the iteration is
    /// released, perhaps not committed yet (see `PendingSnapshot`). The mirror maps this
    /// replica computed for `k` are taken from memory; the others come by batch, as leases need
    /// them. A snapshot of an earlier build is restored whole.
    ///
    /// A worker's homes stay put from one iteration to the next, so its leases read the same
    /// parts of the other workers' maps each time (the arrivals that cross the edges of its
    /// home): what the last iteration read comes along with the head, in the same round trip,
    /// instead of one more when the first block that gathers them starts — or before the head,
    /// those read ahead ([`ReadAhead`]).
    fn start(&mut self, k: u32) -> Result<(), StoreError> {
        // Rotated subfields kept in the last iteration that another worker shot.
        self.prop.drop_rotated_subfields_before(k);
        let guess = self.current.take().map(|c| c.read).unwrap_or_default();
        let held = std::mem::take(&mut self.held);
        // Parts read ahead need not come with the head.
        let ahead = (self.ahead.take())
            .filter(|a| a.snapshot == k)
            .map_or_else(Vec::new, |a| a.maps);
        let guess: Vec<(MapPart, usize)> = (guess.into_iter())
            .filter(|&(part, b)| !ahead.iter().any(|(p, m)| (*p, m.batch as usize) == (part, b)))
            .collect();
        if self.holds_snapshot.take() == Some(k) {
            let all = vec![true; self.prop.batching().count()];
            self.current = Some(Current {
                k,
                work: self.prop.iteration_work(),
                shooting: all.clone(),
                totals: all,
                read: Vec::new(),
                prefetched: HashSet::new(),
                own: Vec::new(),
            });
            return Ok(());
        }
        let (state, prefetched) = self.job.released_state_and_maps(k, &guess)?;
        let mut fetched = HashSet::new();
        let (shooting, totals) = match state {
            ReleasedState::Head(head) if head.mirror_totals_by_batch() => {
                let batches = head.mirror_batches.unwrap_or(0) as usize;
                self.prop.restore_head(head).map_err(|e| self.job.field_error(e))?;
                let mut loaded = vec![false; batches];
                for block in held.into_iter().filter(|b| b.iterations == k) {
                    let range = block.batches.start as usize..block.batches.end as usize;
                    self.prop.adopt_mirrors(block).map_err(|e| self.job.field_error(e))?;
                    loaded.get_mut(range).into_iter().flatten().for_each(|b| *b = true);
                }
                let (mut shooting, mut totals) = (loaded.clone(), loaded);
                for (part, maps) in ahead.into_iter().chain(prefetched) {
                    let b = maps.batch as usize;
                    let have = match part {
                        MapPart::Totals => &mut totals,
                        _ => &mut shooting,
                    };
                    // Not over maps of its own, which it holds already.
                    if have.get(b) != Some(&false) {
                        continue;
                    }
                    let restored = match part {
                        MapPart::Totals => self.prop.restore_totals_batch(maps),
                        _ => self.prop.restore_shooting_batch(maps),
                    };
                    restored.map_err(|e| self.job.field_error(e))?;
                    have[b] = true;
                    fetched.insert((part, b));
                }
                (shooting, totals)
            }
            earlier => {
                let checkpoint = self.job.released_checkpoint(k, earlier)?;
                self.prop.restore(checkpoint).map_err(|e| self.job.field_error(e))?;
                let all = vec![true; self.prop.batching().count()];
                (all.clone(), all)
            }
        };
        self.current = Some(Current {
            k,
            work: self.prop.iteration_work(),
            shooting,
            totals,
            read: Vec::new(),
            prefetched: fetched,
            own: Vec::new(),
        });
        self.absorbed.retain(|(at, _, _)| *at == k);
        Ok(())
    }
}

/// Adds `seconds` to `costs`, shared evenly among them.
fn share_evenly(costs: &mut [f64], seconds: f64) {
    let share = seconds / costs.len().max(1) as f64;
    costs.iter_mut().for_each(|c| *c += share);
}

/// Where a replica's computation spent its wall time, in seconds ([`Replica::phase_seconds`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ReplicaPhases {
    /// Moving on to a new iteration: reading its head and the mirror maps guessed with it.
    pub start: f64,
    /// Reading and restoring the mirror maps the blocks shoot from that were not here yet.
    pub map_reads: f64,
    /// Learning what the pass reads of earlier passes (a rotated copy's areas).
    pub prerequisites: f64,
    /// Computing the blocks (gathering their mirror maps included).
    pub compute: f64,
    /// Encoding the blocks' mirror maps for the store.
    pub encode: f64,
    /// Serialising the outputs and starting their writes (and, for [`Replica::compute`], waiting
    /// for them).
    pub outputs: f64,
}
