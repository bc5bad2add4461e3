//! The coordinator's side of an iteration: a [`Coordinator`] absorbs the blocks of each pass in
//! order, releases the next iteration and commits the snapshot ([`SnapshotCommit`]). Apart from
//! the replica because the two meet only through the store's keys; the coordinator holds the one
//! propagation whose snapshots the job lists.

use super::cover::cover;
use crate::error::StoreError;
use crate::field::{FieldJob, PendingSnapshot};
use crate::job::Job;
use crate::layout;
use crate::layout::{MapPart, Stage};
use crate::manifest::JobState;
use std::collections::HashSet;
use std::ops::Range;
use std::time::Instant;
use vlf_core::propagate::{IterationStats, IterationWork, Pass, Propagation};

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
    /// The current iteration's work, built when first needed (its first absorb), and when the
    /// iteration started: when its passes were first asked for, or else when the work was built.
    work: Option<(IterationWork, Instant)>,
    opened: Option<Instant>,
    traffic: Vec<WorkTraffic>,
    /// The batch outputs read back so far in the current iteration.
    absorbed: WorkTraffic,
    /// Where the coordinator's own work of the current iteration went
    /// ([`Coordinator::take_phase_seconds`]).
    phases: CoordinatorPhases,
    /// Whether `prop` holds the mirror maps of its snapshot (zeros, until an iteration shoots
    /// them; then they live in the store, written by the workers): what it was given says
    /// ([`vlf_core::propagate::Specular::holds_all`]), and it stays so until an iteration shoots
    /// them.
    maps_held: bool,
}

impl Coordinator {
    /// Takes over a job from its last finished snapshot.
    pub fn resume(job: FieldJob) -> Result<Coordinator, StoreError> {
        Coordinator::resume_within(job, None)
    }

    /// [`Coordinator::resume`], holding at most `budget` bytes of subfields when one is given
    /// (a coordinator reads them only to set the job up and, with mirrors, to write the field).
    ///
    /// The mirror maps are not read back: its workers read them from the snapshot, and until an
    /// iteration shoots them they are zeros ([`FieldJob::resume_without_maps`]).
    pub fn resume_within(mut job: FieldJob, budget: Option<usize>) -> Result<Coordinator, StoreError> {
        let prop = job.resume_without_maps(budget)?;
        Ok(Coordinator::new(job, prop))
    }

    /// Coordinates `job` from `prop`, which must be the job's propagation at its last finished
    /// snapshot — as [`FieldJob::create`]'s input or [`FieldJob::resume`]'s or
    /// [`FieldJob::resume_without_maps`]'s output is — so the geometry is not built twice. Its
    /// mirror maps may be elsewhere (in the snapshot's parts): the coordinator then never
    /// writes them, and finishes the job from the parts.
    pub fn new(job: FieldJob, prop: Propagation) -> Coordinator {
        let maps_held = prop.specular.as_ref().is_none_or(|s| s.holds_all());
        Coordinator {
            job,
            prop,
            work: None,
            opened: None,
            traffic: Vec::new(),
            absorbed: WorkTraffic::default(),
            phases: CoordinatorPhases::default(),
            maps_held,
        }
    }

    /// Lets go of the subfields, which the coordinator does not read once the job is set up (it
    /// absorbs what workers shoot; mirror tiles are cut along the mirror views):
    /// [`Propagation::release_subfields`]. Once the job's propagation has been handed to
    /// whoever shares this process (`crate::Prototypes`), it needs no more memory for them.
    pub fn release_subfields(&mut self) {
        self.prop.release_subfields();
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

    /// Builds the current iteration's work now, if it is not built yet: what the coordinator
    /// does once the iteration's first leases are out, while the workers compute. Left to the
    /// first absorb, it would be paid at the end of a pass leased whole to one worker, whose
    /// one block is absorbed only when the pass is done (0.1–0.3 ms of the mirror scene's
    /// iterations, on the path to the next leases).
    pub fn prepare_work(&mut self) {
        self.work();
    }

    fn work(&mut self) -> &mut IterationWork {
        let opened = &mut self.opened;
        &mut self
            .work
            .get_or_insert_with(|| {
                let started = opened.take().unwrap_or_else(Instant::now);
                (self.prop.iteration_work(), started)
            })
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
    /// batch count of each. Cheap: the iteration's work (the shooting radiance of every texel,
    /// the rotated copies) is built later, by [`Coordinator::prepare_work`] or the first absorb,
    /// and not between the release and the leases that follow it.
    pub fn passes(&mut self) -> (Vec<(Pass, Vec<Pass>)>, usize) {
        let passes = match &self.work {
            Some((work, _)) => work.passes(),
            None => {
                self.opened.get_or_insert_with(Instant::now);
                self.prop.iteration_passes()
            }
        };
        let passes = passes.into_iter().map(|p| (p, p.prerequisites())).collect();
        (passes, self.prop.batching().count())
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
        // One listing of the next snapshot: every batch's parts, each of the three kinds.
        let id = self.job.id();
        let keys = (self.job.job().store()).list(&layout::stage_prefix(id, Stage::Iteration(k + 1))?)?;
        let held = [MapPart::Shooting, MapPart::Totals, MapPart::Radiance]
            .into_iter()
            .map(|part| {
                let folder = layout::map_parts(id, k + 1, part)?;
                Ok(keys
                    .iter()
                    .filter_map(|key| layout::parse_map_part(&folder, key))
                    .map(|b| b as usize)
                    .collect::<HashSet<usize>>())
            })
            .collect::<Result<Vec<_>, StoreError>>()?;
        Ok(stored
            .into_iter()
            .filter(|block| block.clone().all(|b| held.iter().all(|h| h.contains(&b))))
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
        let reading = Instant::now();
        let (outputs, read) = self.job.read_batches(k, pass, blocks)?;
        self.phases.read += reading.elapsed().as_secs_f64();
        self.absorbed.blobs += read.blobs;
        self.absorbed.bytes += read.bytes;
        let applying = Instant::now();
        for out in outputs {
            let Some((work, _)) = self.work.as_mut() else {
                unreachable!("passes() created it");
            };
            self.prop.apply_batch(work, out).map_err(|e| self.job.field_error(e))?;
        }
        self.phases.apply += applying.elapsed().as_secs_f64();
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
        let finishing = Instant::now();
        let stats = self.prop.finish_iteration(work, started);
        self.phases.finish += finishing.elapsed().as_secs_f64();
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
        let writing = Instant::now();
        let snapshot = self.job.release_snapshot(&self.prop, maps)?;
        self.phases.head += writing.elapsed().as_secs_f64();
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

    /// Where the coordinator's own work went since the last call, phase by phase: what a
    /// coordinator logs with each iteration it releases (`iteration released`, at debug level), to
    /// tell its serial part between iterations apart.
    pub fn take_phase_seconds(&mut self) -> CoordinatorPhases {
        std::mem::take(&mut self.phases)
    }

    /// Takes the manifest a [`SnapshotCommit::commit`] of this job wrote.
    pub fn committed(&mut self, committed: Job) {
        self.job.adopt_commit(committed);
    }

    /// Writes the final field and marks the job finished: the mirror totals come from the last
    /// snapshot's parts, where the workers wrote them — streamed from there a few batches at a
    /// time ([`FieldJob::finish_from_snapshot`]), or, to re-sample them (which reads the whole
    /// field), restored whole first.
    pub fn finish(mut self, resample: bool) -> Result<FieldJob, StoreError> {
        if self.prop.specular.is_some() && !self.maps_held && !resample {
            self.job.finish_from_snapshot(&self.prop)?;
            sweep_work(&self.job);
            return Ok(self.job);
        }
        if self.prop.specular.is_some() && !self.maps_held {
            let k = self.iteration();
            let all: Vec<usize> = (0..self.prop.batching().count()).collect();
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
        sweep_work(&self.job);
        Ok(self.job)
    }
}

/// Deletes whatever is left under the job's work prefix once it is finished: each
/// iteration's outputs go when its snapshot is committed, but a worker wrongly taken for
/// dead may write its lease's output after that (a survey part after snapshot 1, a batch
/// after its iteration's snapshot), and nothing else would ever delete it. A failure here
/// is only logged: the field is written and the job finished; what stays is garbage.
fn sweep_work(job: &FieldJob) {
    let store = job.job().store();
    let root = layout::work_root(job.id());
    let swept = store.list(&root).and_then(|left| {
        store.delete_all(&left)?;
        Ok(left.len())
    });
    match swept {
        Ok(0) => {}
        Ok(n) => tracing::info!(job = %job.id(), blobs = n, "late work outputs swept"),
        Err(e) => tracing::warn!(job = %job.id(), error = %e, "late work outputs left in the store"),
    }
}

/// Where a coordinator's own work of an iteration went, in seconds
/// ([`Coordinator::take_phase_seconds`]). `read` and `apply` add up every absorb of the
/// iteration, most of which overlap the workers' computing; the last absorb, `finish` and `head`
/// (with the wait for the last snapshot's commit) lie between the workers' last report and the
/// next iteration's leases.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CoordinatorPhases {
    /// Reading and decoding the blocks' outputs.
    pub read: f64,
    /// Adding them into the iteration's sums, in order.
    pub apply: f64,
    /// Ending the iteration: the diffuse reflection and the exchange's bookkeeping
    /// ([`Propagation::finish_iteration`]).
    pub finish: f64,
    /// Writing the next snapshot's head, all the next iteration's workers read.
    pub head: f64,
}
