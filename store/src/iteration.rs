//! An iteration through the store: workers compute blocks of batches of directions and write
//! their outputs into the job; the coordinator absorbs them in order and commits the next
//! snapshot. This is the data path of the distributed service — the coordinator moves no
//! radiance over the network, only which blocks to compute (leases) — and it is usable
//! in-process as well, with threads for workers.
//!
//! The protocol for the iteration that starts from snapshot `k` (see `vlf_core::propagate::work`
//! for passes and batches, `vlf_core::propagate::reduce` for blocks):
//!
//! 1. Every batch of a pass is computed by some [`Replica`] (a worker's copy of the
//!    propagation, restored from snapshot `k`'s head and the mirror maps the block reads) once
//!    the pass's prerequisites are absorbed, as part of an aligned block. A shooting block
//!    with mirrors first writes its directions' mirror maps as parts of snapshot `k + 1`
//!    (`iters/K+1/{shooting,mirror-totals}/BBBBB.blob`: the arrivals to reflect next, the
//!    totals); then its node sum and each direction's `Φ_in` (a few numbers) go to
//!    `jobs/J/work/KKKKK/PASS/SSSSS-EEEEE.blob`. Writes are create-only; a block computed
//!    twice (a lease that expired and was handed out again, a late result) writes the same
//!    bytes, which the store accepts as unchanged — and different bytes would be an error,
//!    never a silent replacement.
//! 2. The [`Coordinator`] reads the blocks in pass and batch order and absorbs each as soon as
//!    it is written (the next ones are still being computed meanwhile); replicas read the
//!    blocks of a pass's prerequisites to learn what it needs (a rotated copy's areas).
//! 3. After the last pass the coordinator finishes the iteration (diffuse reflection; the
//!    mirrors' power settled from `Φ_in`) and writes snapshot `k + 1`'s head, which releases
//!    the next iteration ([`Coordinator::release_iteration`]); it then writes the rest of the
//!    snapshot (diffuse totals and maps, summary), commits it and deletes the iteration's
//!    outputs ([`SnapshotCommit::commit`]) — in the service, while workers compute the next
//!    iteration; [`Coordinator::finish_iteration`] does both at once.
//!
//! So mirror maps go from worker to worker through the store and never through the
//! coordinator, and a replica keeps the maps it wrote: one that shoots the same directions in
//! the next iteration, and gathers from directions it shot, reads none back (a single worker
//! reads no mirror map at all).
//!
//! The bits do not depend on which replica computed which block, how large the blocks were, or
//! when: tested with several replicas in threads, blocks of 1, 2 and 4 batches assigned in a
//! shuffled order and some computed twice.

use crate::blob::{self, BlobKind};
use crate::error::StoreError;
use crate::field::{FieldJob, PendingSnapshot, ReleasedState};
use crate::id::JobId;
use crate::job::Job;
use crate::layout;
use crate::layout::MapPart;
use crate::manifest::JobState;
use crate::store::{Put, PutOutcome, Writing};
use rayon::prelude::*;
use std::collections::{HashMap, HashSet};
use std::ops::Range;
use std::sync::{Arc, Mutex};
use std::time::Instant;
use vlf_core::propagate::reduce::{RunOutputs, is_aligned_block};
use vlf_core::propagate::work::batch_count;
use vlf_core::propagate::{BatchOutput, IterationStats, IterationWork, MirrorBlock, Pass, Propagation};

/// The key segment of a pass.
fn pass_name(pass: Pass) -> String {
    match pass {
        Pass::Shoot => "shoot".into(),
        Pass::Areas { copy } => format!("areas-{copy:02}"),
        Pass::ShootCopy { copy } => format!("copy-{copy:02}"),
    }
}

impl FieldJob {
    /// Writes a block output of the iteration starting from snapshot `output.iteration`
    /// (create-only: the same bytes again are accepted, different bytes refused).
    pub fn put_batch(&self, output: &BatchOutput) -> Result<PutOutcome, StoreError> {
        let put = self.batch_put(output)?;
        self.job().store().put_new(&put.key, put.bytes)
    }

    /// [`FieldJob::put_batch`]'s blob, encoded, for [`crate::Store::put_all`].
    pub fn batch_put(&self, output: &BatchOutput) -> Result<Put, StoreError> {
        let key = layout::work_block(
            self.id(),
            output.iteration,
            &pass_name(output.pass),
            output.batches.start,
            output.batches.end,
        )?;
        let bytes =
            blob::encode_bytes(BlobKind::BatchOutput, &output.to_bytes()).map_err(|source| StoreError::Blob {
                url: self.job().store().url().to_string(),
                key: key.clone(),
                source,
            })?;
        Ok(Put {
            key,
            bytes: bytes.into(),
            create_only: true,
        })
    }

    /// Reads the output of batches `batches` of `pass` of the iteration starting from snapshot
    /// `k`.
    pub fn get_batch(&self, k: u32, pass: Pass, batches: Range<usize>) -> Result<BatchOutput, StoreError> {
        let mut outputs = self.get_batches(k, pass, std::slice::from_ref(&batches))?;
        Ok(outputs.remove(0))
    }

    /// [`FieldJob::get_batch`] of several blocks, their requests overlapping (see
    /// [`crate::Store::get_all`]), decoded in parallel, in the order of `blocks`.
    pub fn get_batches(&self, k: u32, pass: Pass, blocks: &[Range<usize>]) -> Result<Vec<BatchOutput>, StoreError> {
        Ok(self.read_batches(k, pass, blocks)?.0)
    }

    /// [`FieldJob::get_batches`], and what the blobs read weigh as stored.
    fn read_batches(
        &self,
        k: u32,
        pass: Pass,
        blocks: &[Range<usize>],
    ) -> Result<(Vec<BatchOutput>, WorkTraffic), StoreError> {
        let keys = blocks
            .iter()
            .map(|b| layout::work_block(self.id(), k, &pass_name(pass), b.start as u32, b.end as u32))
            .collect::<Result<Vec<_>, _>>()?;
        let blobs = self.job().store().get_all(&keys)?;
        let read = WorkTraffic {
            blobs: blobs.len() as u64,
            bytes: blobs.iter().map(|b| b.len() as u64).sum(),
        };
        let outputs = (keys.par_iter().zip(&blobs).zip(blocks))
            .map(|((key, blob), batches)| {
                let bytes = self
                    .job()
                    .store()
                    .as_async()
                    .decode_with(key, blob, |b| blob::decode_bytes(b, BlobKind::BatchOutput))?;
                let output = BatchOutput::from_bytes(&bytes).map_err(|e| self.decode_error(key, e.to_string()))?;
                let held = output.batches.start as usize..output.batches.end as usize;
                if (output.iteration, output.pass, &held) != (k, pass, batches) {
                    return Err(self.decode_error(
                        key,
                        format!(
                            "holds batches {held:?} of {:?} of iteration {}",
                            output.pass, output.iteration
                        ),
                    ));
                }
                Ok(output)
            })
            .collect::<Result<_, _>>()?;
        Ok((outputs, read))
    }

    /// The blocks of `pass` of the iteration starting from snapshot `k` whose outputs are in the
    /// store, in order of their first batch (larger first where two start together).
    pub fn stored_blocks(&self, k: u32, pass: Pass) -> Result<Vec<Range<usize>>, StoreError> {
        let prefix = layout::work_pass(self.id(), k, &pass_name(pass))?;
        let mut blocks: Vec<Range<usize>> = self
            .job()
            .store()
            .list(&prefix)?
            .iter()
            .filter_map(|key| layout::parse_work_block(&prefix, key))
            .map(|r| r.start as usize..r.end as usize)
            .collect();
        blocks.sort_by_key(|r| (r.start, std::cmp::Reverse(r.end)));
        Ok(blocks)
    }

    fn decode_error(&self, key: &str, reason: String) -> StoreError {
        StoreError::Field {
            url: self.job().store().url().to_string(),
            job: self.id().to_string(),
            source: vlf_core::Error::Decode(format!("`{key}`: {reason}")),
        }
    }
}

/// Propagations of jobs built in this process, for replicas to start from instead of building
/// the geometry again — a coordinator and workers sharing a process (`vlf run`). Each is the
/// job's whole state at the snapshot its coordinator took it up from ([`Replica::at_snapshot`]).
/// The geometry is a pure function of the job's scene and options, and the state is that
/// snapshot's, so it gives the same bits as a replica built from the store.
///
/// Each of the process's workers takes a job's propagation once: all but the last get a copy,
/// the last the one offered (a copy of the mirror scene's is 13 MB of maps, which cost its first
/// iteration 2–4 ms of fresh memory). A worker that asks again (its replica was dropped) finds
/// none and builds one from the store.
#[derive(Clone)]
pub struct Prototypes {
    offers: Arc<Mutex<HashMap<JobId, Offer>>>,
    workers: usize,
}

struct Offer {
    prop: Propagation,
    /// Workers that have not taken it yet.
    left: usize,
}

impl Prototypes {
    /// Prototypes for the `workers` workers of this process.
    pub fn new(workers: usize) -> Prototypes {
        Prototypes {
            offers: Arc::default(),
            workers: workers.max(1),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<JobId, Offer>> {
        // Plain data: a panic elsewhere cannot leave it half-changed.
        self.offers.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Offers `prop`, job `id`'s propagation at its last snapshot, to the workers of this
    /// process.
    pub fn insert(&self, id: JobId, prop: Propagation) {
        let left = self.workers;
        self.lock().insert(id, Offer { prop, left });
    }

    /// Job `id`'s propagation for one worker, if one is offered: a copy, or for the last worker
    /// the one offered.
    pub fn take(&self, id: &JobId) -> Option<Propagation> {
        let mut offers = self.lock();
        let offer = offers.get_mut(id)?;
        offer.left -= 1;
        if offer.left == 0 {
            offers.remove(id).map(|o| o.prop)
        } else {
            Some(offer.prop.clone())
        }
    }

    /// Withdraws job `id`'s propagation (the job ended).
    pub fn remove(&self, id: &JobId) {
        self.lock().remove(id);
    }
}

impl std::fmt::Debug for Prototypes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let jobs: Vec<String> = self.lock().keys().map(|id| id.to_string()).collect();
        f.debug_struct("Prototypes")
            .field("jobs", &jobs)
            .field("workers", &self.workers)
            .finish()
    }
}

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
        let prop = Propagation::new(job.scene().clone(), job.options().clone()).map_err(|e| job.field_error(e))?;
        Ok(Replica::with_propagation(job, prop))
    }

    /// A replica of `job` over `prop`, a propagation of the same scene and options (built by
    /// someone else in this process: the geometry is not built twice). Its state is restored
    /// from the store before every iteration, so what it holds now does not matter.
    pub fn with_propagation(job: FieldJob, prop: Propagation) -> Replica {
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
        }
    }

    /// A replica of `job` over `prop`, the job's whole state at its snapshot
    /// `prop.iterations_done()` — as a coordinator in this process holds it when it takes the job
    /// up ([`Prototypes`]): the iteration from that snapshot reads nothing of it from the store
    /// (the same bits: the snapshot was written from that state).
    pub fn at_snapshot(job: FieldJob, prop: Propagation) -> Replica {
        let k = prop.iterations_done();
        Replica {
            holds_snapshot: Some(k),
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
        let out = self.shoot(k, pass, batches)?;
        let outputs = [out];
        self.write_outputs(&outputs)?;
        self.keep_for_later_passes(outputs);
        Ok(())
    }

    /// Seconds the last [`Replica::compute`] or run spent computing its blocks — shooting and
    /// encoding their mirror maps — without the waits for the store (the head, the maps and
    /// areas read, the outputs written) or decoding what it read. What a lease reports: the
    /// coordinator splits the next pass among workers by what their batches cost, and a wait of
    /// a round trip per lease, spread over its batches, would make the batches of a worker with
    /// fewer of them look dearer, and its next share smaller still.
    pub fn compute_seconds(&self) -> f64 {
        self.costs.iter().sum()
    }

    /// What each batch of the last [`Replica::compute`] or run cost to compute, in order, in
    /// seconds (see [`Replica::compute_seconds`]): a block's batches are timed one by one, and
    /// what the block does besides (gathering its arrivals, encoding its mirror maps) is shared
    /// evenly among them.
    pub fn batch_costs(&self) -> &[f64] {
        &self.costs
    }

    /// Tells the replica which blocks of `pass` of the iteration from snapshot `k` the
    /// coordinator absorbed (a lease names those of the passes it reads): a pass that needs them
    /// then reads the ones it did not compute itself without listing the store first.
    pub fn absorbed(&mut self, k: u32, pass: Pass, blocks: Vec<Range<usize>>) {
        self.absorbed.retain(|(at, p, _)| *at == k && *p != pass);
        self.absorbed.push((k, pass, blocks));
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
        let writes = self.write_outputs_behind(&outputs)?;
        self.keep_for_later_passes(outputs);
        Ok((start..done, writes))
    }

    /// Writes `outputs` along with the mirror maps still on their way, and waits for both: one
    /// round trip. An output in the store does not say its maps are (a worker may stop between
    /// the two); the report that follows does, and a coordinator that finds outputs no report
    /// told it of checks their maps first ([`Coordinator::blocks_in_store`]).
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
            self.start(k)?;
        }
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
        let (out, block, mut costs) = self
            .prop
            .compute_block_costed(work, pass, batches.clone())
            .map_err(|e| self.job.field_error(e))?;
        let encoding = Instant::now();
        if let Some(block) = block {
            // The block took its directions' totals with it: computing it again reads them.
            batches.for_each(|b| current.totals[b] = false);
            let l = self.prop.directions.len();
            let job = self.job.job();
            let puts = block
                .batch_bytes(l)
                .par_iter()
                .flat_map_iter(|(b, shooting, totals)| {
                    [
                        job.map_part_put(k + 1, MapPart::Shooting, *b, shooting),
                        job.map_part_put(k + 1, MapPart::Totals, *b, totals),
                    ]
                })
                .collect::<Result<Vec<_>, _>>()?;
            self.unwritten = puts;
            self.held.push(block);
        }
        let share = encoding.elapsed().as_secs_f64() / costs.len().max(1) as f64;
        costs.iter_mut().for_each(|c| *c += share);
        self.costs.extend(costs);
        Ok(out)
    }

    /// Moves on to the iteration that starts from snapshot `k`. Every lease reads the head of
    /// the shooting state (statistics, Current, pending `Φ_in`): written before the iteration is
    /// released, perhaps not committed yet (see `PendingSnapshot`). The mirror maps this
    /// replica computed for `k` are taken from memory; the others come by batch, as leases need
    /// them. A snapshot of an earlier build is restored whole.
    ///
    /// A worker's homes stay put from one iteration to the next, so its leases read the same
    /// parts of the other workers' maps each time (the arrivals that cross the edges of its
    /// home): what the last iteration read comes along with the head, in the same round trip,
    /// instead of one more when the first block that gathers them starts.
    fn start(&mut self, k: u32) -> Result<(), StoreError> {
        let guess = self.current.take().map(|c| c.read).unwrap_or_default();
        let held = std::mem::take(&mut self.held);
        if self.holds_snapshot.take() == Some(k) {
            let all = vec![true; batch_count(self.prop.directions.len())];
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
                for (part, maps) in prefetched {
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
                let all = vec![true; batch_count(self.prop.directions.len())];
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

/// The aligned blocks of a pass of `n` batches that cover it with the fewest reads from the
/// store, in order, each with whether it is held here: blocks in `held` cost nothing, those in
/// `stored` one read each. `None` when together they leave a gap. Any cover gives the same sum:
/// its blocks are nodes of the pass's reduction tree (`vlf_core::propagate::reduce`).
fn cheapest_cover(held: &[Range<usize>], stored: &[Range<usize>], n: usize) -> Option<Vec<(Range<usize>, bool)>> {
    // reads[i]: the fewest reads that cover batches i..n; take[i]: the block to take at i.
    let mut reads: Vec<Option<usize>> = vec![None; n + 1];
    let mut take: Vec<Option<(Range<usize>, bool)>> = vec![None; n + 1];
    reads[n] = Some(0);
    for i in (0..n).rev() {
        let candidates = (held.iter().map(|b| (b, true))).chain(stored.iter().map(|b| (b, false)));
        for (block, from_here) in candidates {
            if block.start != i || !is_aligned_block(block, n) {
                continue;
            }
            let Some(after) = reads[block.end] else {
                continue;
            };
            let total = after + usize::from(!from_here);
            if reads[i].is_none_or(|r| total < r) {
                reads[i] = Some(total);
                take[i] = Some((block.clone(), from_here));
            }
        }
    }
    let mut plan = Vec::new();
    let mut i = 0;
    while i < n {
        let (block, from_here) = take[i].clone()?;
        i = block.end;
        plan.push((block, from_here));
    }
    Some(plan)
}

/// Aligned blocks among `stored` (sorted as [`FieldJob::stored_blocks`] sorts them) that cover
/// the batches `span` of a pass one after another, the largest at each step; the first batch
/// no stored block starts at, if there is a gap.
fn cover(stored: &[Range<usize>], span: Range<usize>) -> Result<Vec<Range<usize>>, usize> {
    let mut out = Vec::new();
    let mut next = span.start;
    while next < span.end {
        let block = stored
            .iter()
            .find(|b| b.start == next && is_aligned_block(b, span.end))
            .ok_or(next)?;
        next = block.end;
        out.push(block.clone());
    }
    Ok(out)
}

/// What an iteration moved through the store: the batch outputs workers wrote and the
/// coordinator read back (compressed, as stored). Snapshots come on top.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WorkTraffic {
    pub blobs: u64,
    pub bytes: u64,
}

/// The rest of an iteration's end once the next iteration is released
/// ([`Coordinator::release_iteration`]): the snapshot's commit, then the deletion of the
/// iteration's batch outputs (only after the commit: a coordinator that stops before it resumes
/// from the previous snapshot and uses them again).
pub struct SnapshotCommit {
    snapshot: PendingSnapshot,
    /// Where the iteration's batch outputs are (`layout::work_prefix`).
    work: String,
}

impl SnapshotCommit {
    /// The snapshot it commits.
    pub fn iteration(&self) -> u32 {
        self.snapshot.iteration()
    }

    /// Commits the snapshot and deletes the iteration's batch outputs — every one under its
    /// prefix, those of leases that expired after writing theirs too; returns the job with the
    /// manifest that lists the snapshot, for [`Coordinator::committed`].
    pub fn commit(self) -> Result<Job, StoreError> {
        let job = self.snapshot.commit()?;
        let work = job.store().list(&self.work)?;
        job.store().delete_all(&work)?;
        Ok(job)
    }
}

/// The coordinator's side: absorbs the batches of each pass in order and commits snapshots.
pub struct Coordinator {
    job: FieldJob,
    prop: Propagation,
    work: Option<(IterationWork, Instant)>,
    traffic: Vec<WorkTraffic>,
    /// The batch outputs read back so far in the current iteration.
    absorbed: WorkTraffic,
    /// Whether `prop` holds the mirror maps of its snapshot: true from its restore until an
    /// iteration shoots them (then they live in the store, written by the workers).
    maps_held: bool,
}

impl Coordinator {
    /// Takes over a job from its last finished snapshot.
    pub fn resume(mut job: FieldJob) -> Result<Coordinator, StoreError> {
        let prop = job.resume()?;
        Ok(Coordinator::new(job, prop))
    }

    /// Coordinates `job` from `prop`, which must be the job's propagation at its last finished
    /// snapshot — as [`FieldJob::create`]'s input or [`FieldJob::resume`]'s output is — so the
    /// geometry is not built twice.
    pub fn new(job: FieldJob, prop: Propagation) -> Coordinator {
        Coordinator {
            job,
            prop,
            work: None,
            traffic: Vec::new(),
            absorbed: WorkTraffic::default(),
            maps_held: true,
        }
    }

    /// Work blobs and bytes of every iteration this coordinator finished, in order.
    pub fn traffic(&self) -> &[WorkTraffic] {
        &self.traffic
    }

    pub fn job(&self) -> &FieldJob {
        &self.job
    }

    pub fn propagation(&self) -> &Propagation {
        &self.prop
    }

    /// The snapshot the current iteration starts from.
    pub fn iteration(&self) -> u32 {
        self.prop.iterations_done()
    }

    /// Whether the stop rule says the job is done.
    pub fn finished(&self) -> bool {
        self.prop.finished()
    }

    fn work(&mut self) -> &mut IterationWork {
        &mut self
            .work
            .get_or_insert_with(|| (self.prop.iteration_work(), Instant::now()))
            .0
    }

    /// The next pass whose batches are needed, with its batch count, or `None` when the
    /// iteration's passes are all absorbed.
    pub fn pending_pass(&mut self) -> Option<(Pass, usize)> {
        self.next_batch().map(|(pass, _)| (pass, self.work().batches()))
    }

    /// The batch the iteration absorbs next, or `None` when its passes are all absorbed.
    pub fn next_batch(&mut self) -> Option<(Pass, usize)> {
        self.work().next_expected()
    }

    /// Every pass of the current iteration, in absorbing order, with its prerequisites, and the
    /// batch count of each.
    pub fn passes(&mut self) -> (Vec<(Pass, Vec<Pass>)>, usize) {
        let work = self.work();
        let passes = work.passes().into_iter().map(|p| (p, work.prerequisites(p))).collect();
        (passes, work.batches())
    }

    /// The blocks of every pass of the current iteration already in the store, in
    /// [`Coordinator::passes`] order (a restarted coordinator reuses what workers wrote before it
    /// stopped: the bytes are the same).
    pub fn blocks_in_store(&mut self) -> Result<Vec<Vec<Range<usize>>>, StoreError> {
        let (passes, _) = self.passes();
        passes.iter().map(|(pass, _)| self.complete_blocks(*pass)).collect()
    }

    /// The blocks of `pass` of the current iteration whose outputs are in the store, and whose
    /// mirror maps are too when the pass shoots them: a worker writes a block's output and its
    /// maps together and reports once both are there, so a block found in the store without a
    /// report may lack its maps (its worker stopped in between). Such a block is computed again.
    fn complete_blocks(&mut self, pass: Pass) -> Result<Vec<Range<usize>>, StoreError> {
        let k = self.iteration();
        let stored = self.job.stored_blocks(k, pass)?;
        if pass != Pass::Shoot || !self.work().uses_mirror_maps() || stored.is_empty() {
            return Ok(stored);
        }
        let store = self.job.job().store();
        let held = |part| -> Result<HashSet<usize>, StoreError> {
            let prefix = layout::map_parts(self.job.id(), k + 1, part)?;
            Ok(store
                .list(&prefix)?
                .iter()
                .filter_map(|key| layout::parse_map_part(&prefix, key))
                .map(|b| b as usize)
                .collect())
        };
        let (shooting, totals) = (held(MapPart::Shooting)?, held(MapPart::Totals)?);
        Ok(stored
            .into_iter()
            .filter(|block| block.clone().all(|b| shooting.contains(&b) && totals.contains(&b)))
            .collect())
    }

    /// Ends the job in `state` (failed or cancelled): the snapshots written so far stay
    /// readable, and the job is not resumed.
    pub fn end(&mut self, state: JobState) -> Result<(), StoreError> {
        self.job.set_state(state)
    }

    /// Absorbs the rest of the pending pass from the store: the blocks written that cover it, in
    /// order (the largest where several start at the same batch).
    pub fn absorb_pass(&mut self) -> Result<Pass, StoreError> {
        let Some((pass, next)) = self.next_batch() else {
            return Err(self.job.field_error(vlf_core::Error::Parameter(
                "no pass is pending: finish the iteration".into(),
            )));
        };
        let batches = self.work().batches();
        let stored = self.complete_blocks(pass)?;
        let blocks = cover(&stored, next..batches).map_err(|at| StoreError::NotFound {
            url: self.job.job().store().url().to_string(),
            key: format!("batch {at} of {pass:?} of iteration {}", self.iteration() + 1),
        })?;
        self.absorb_blocks(pass, &blocks)?;
        Ok(pass)
    }

    /// Absorbs the outputs of `blocks` of `pass` (the next ones expected, in order) from the
    /// store: the coordinator takes each block in as soon as it is written. They are read
    /// together (their requests overlap), then absorbed in order; if one cannot be read, none is
    /// absorbed.
    pub fn absorb_blocks(&mut self, pass: Pass, blocks: &[Range<usize>]) -> Result<(), StoreError> {
        let k = self.iteration();
        self.work();
        let (outputs, read) = self.job.read_batches(k, pass, blocks)?;
        self.absorbed.blobs += read.blobs;
        self.absorbed.bytes += read.bytes;
        for out in outputs {
            let Some((work, _)) = self.work.as_mut() else {
                unreachable!("passes() created it");
            };
            self.prop.apply_batch(work, out).map_err(|e| self.job.field_error(e))?;
        }
        Ok(())
    }

    /// Finishes the iteration once every pass is absorbed: commits the next snapshot and
    /// deletes the iteration's batch outputs.
    pub fn finish_iteration(&mut self) -> Result<IterationStats, StoreError> {
        let (stats, commit) = self.release_iteration()?;
        let committed = commit.commit()?;
        self.committed(committed);
        Ok(stats)
    }

    /// Finishes the iteration once every pass is absorbed and releases the next one: writes the
    /// next snapshot's shooting state, which is all its workers read, and returns the rest of the
    /// snapshot to commit ([`SnapshotCommit::commit`], then [`Coordinator::committed`]) while
    /// they compute. Nothing may write the job's manifest in between.
    pub fn release_iteration(&mut self) -> Result<(IterationStats, SnapshotCommit), StoreError> {
        let k = self.iteration();
        if self.pending_pass().is_some() {
            return Err(self.job.field_error(vlf_core::Error::Parameter(format!(
                "iteration {k} has passes left to absorb"
            ))));
        }
        let Some((work, started)) = self.work.take() else {
            unreachable!("pending_pass created it");
        };
        // The workers wrote the next snapshot's mirror maps if the iteration shot them; else they
        // are those of the snapshot it started from, written here.
        let shot = work.uses_mirror_maps();
        let stats = self.prop.finish_iteration(work, started);
        self.maps_held &= !shot;
        if !self.maps_held
            && let Some(spec) = self.prop.specular.as_mut()
        {
            // The workers hold them: the coordinator's memory does not grow with the mirror
            // slots.
            spec.release_maps();
        }
        let maps = self.prop.specular.is_some() && !shot;
        if maps && !self.maps_held {
            return Err(self.job.field_error(vlf_core::Error::Parameter(format!(
                "iteration {k} left the mirror maps as they were, and this coordinator no longer holds them"
            ))));
        }
        let snapshot = self.job.release_snapshot(&self.prop, maps)?;
        // What the outputs weighed is known from reading them: no listing (a round trip to an
        // object store) before the next iteration starts.
        self.traffic.push(std::mem::take(&mut self.absorbed));
        Ok((
            stats,
            SnapshotCommit {
                snapshot,
                work: layout::work_prefix(self.job.id(), k)?,
            },
        ))
    }

    /// Takes the manifest a [`SnapshotCommit::commit`] of this job wrote.
    pub fn committed(&mut self, committed: Job) {
        self.job.adopt_commit(committed);
    }

    /// Writes the final field and marks the job finished: the mirror totals come from the last
    /// snapshot's parts, where the workers wrote them.
    pub fn finish(mut self, resample: bool) -> Result<FieldJob, StoreError> {
        if self.prop.specular.is_some() && !self.maps_held {
            let k = self.iteration();
            let all: Vec<usize> = (0..batch_count(self.prop.directions.len())).collect();
            for part in self.job.released_maps(k, MapPart::Totals, &all)? {
                self.prop
                    .restore_totals_batch(part)
                    .map_err(|e| self.job.field_error(e))?;
            }
        }
        let mut field = self.prop.into_field();
        if resample {
            field.resample_mirrors(8);
        }
        self.job.finish(&field, resample)?;
        Ok(self.job)
    }
}

#[cfg(test)]
// Single blocks are what these tests mean.
#[allow(clippy::single_range_in_vec_init)]
mod tests {
    use super::cheapest_cover;

    #[test]
    fn a_cover_takes_what_is_held_and_reads_the_fewest_blocks() {
        // What is held covers the pass: nothing to read.
        let held = [0..4, 4..6, 6..8];
        let plan = cheapest_cover(&held, &[0..8], 8).unwrap();
        assert_eq!(plan, vec![(0..4, true), (4..6, true), (6..8, true)]);
        // Held blocks fill what they can, stored ones the rest.
        let plan = cheapest_cover(&[0..4], &[0..8, 4..8], 8).unwrap();
        assert_eq!(plan, vec![(0..4, true), (4..8, false)]);
        // The fewest reads, not the most held: one stored block over two.
        let plan = cheapest_cover(&[0..4, 4..6], &[0..8, 6..7, 7..8], 8).unwrap();
        assert_eq!(plan, vec![(0..8, false)]);
        // A held block that leads to a gap is not taken.
        let plan = cheapest_cover(&[0..2], &[0..4, 4..8], 8).unwrap();
        assert_eq!(plan, vec![(0..4, false), (4..8, false)]);
        // Blocks that are not nodes of the reduction tree are never taken.
        assert_eq!(cheapest_cover(&[0..2, 2..6, 6..8], &[], 8), None);
        assert_eq!(cheapest_cover(&[0..4], &[4..6], 8), None, "a gap");
        assert_eq!(cheapest_cover(&[], &[], 0), Some(Vec::new()));
    }
}
