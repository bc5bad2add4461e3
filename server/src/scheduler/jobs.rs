//! A job's life, as its driver and the job service see it: adding it, opening and closing its
//! iterations and passes, what the driver finds when it wakes, its status, cancelling it. The
//! workers never call these; apart from the blocks already stored when a pass opens, the
//! batches' states change on the workers' side (`leases`), so this half reads as the driver's
//! protocol with the scheduler.

use super::pass::{Batch, BatchState, PassRun, Shooting};
use super::usage::UseClock;
use super::{Clock, IterationRecord, JobEntry, PassOutcome, Scheduler, Unknown, alive_workers, is_terminal, publish};
use std::ops::Range;
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::{Notify, watch};
use vlf_core::propagate::Pass;
use vlf_core::propagate::reduce::is_aligned_block;
use vlf_proto::v1::JobStatus;
use vlf_store::{JobId, WorkTraffic};

impl Scheduler {
    /// Adds a job with its initial status (`seq` is set here); returns the driver's wake-up.
    /// `directions` and `batches_per_pass` size the progress figures.
    pub fn add_job(&self, mut status: JobStatus) -> Result<Arc<Notify>, String> {
        let id = JobId::parse(&status.job_id)?;
        let mut state = self.lock();
        state.counter += 1;
        let order = state.counter;
        status.seq = 1;
        status.store_url = self.store.url().to_string();
        let driver = Arc::new(Notify::new());
        let now = Instant::now();
        let (tx, _) = watch::channel(status);
        state.jobs.insert(
            id,
            JobEntry {
                order,
                status: tx,
                passes: Vec::new(),
                cancel_requested: false,
                failure: None,
                driver: driver.clone(),
                clock: Clock {
                    created: now,
                    iteration_started: now,
                    released: None,
                    batches_before_pass: 0,
                    batches_total: 0,
                    directions: 0,
                    batches_per_pass: 0,
                    finished: Vec::new(),
                    use_clock: UseClock::default(),
                    batch_seconds: None,
                    survey_batch_seconds: None,
                },
                shooting: Shooting::default(),
            },
        );
        Ok(driver)
    }

    /// Whether the scheduler knows `job`.
    pub fn has_job(&self, job: &JobId) -> bool {
        self.lock().jobs.contains_key(job)
    }

    /// The job's status now.
    pub fn status(&self, job: &JobId) -> Result<JobStatus, Unknown> {
        let state = self.lock();
        let entry = state.jobs.get(job).ok_or_else(|| Unknown::Job(job.to_string()))?;
        let mut status = entry.status.borrow().clone();
        // The workers alive now, not at the job's last event: a worker that joins a job waiting
        // on another's lease causes no event, and would not be counted until the next one.
        status.workers_alive = alive_workers(&state, self.timing);
        Ok(status)
    }

    /// Every job's status, oldest first (workers alive counted now, as [`Self::status`] does).
    pub fn list(&self) -> Vec<JobStatus> {
        let state = self.lock();
        let alive = alive_workers(&state, self.timing);
        let mut jobs: Vec<_> = state.jobs.values().collect();
        jobs.sort_by_key(|j| j.order);
        (jobs.iter())
            .map(|j| JobStatus {
                workers_alive: alive,
                ..j.status.borrow().clone()
            })
            .collect()
    }

    /// A receiver of the job's status changes.
    pub fn subscribe(&self, job: &JobId) -> Result<watch::Receiver<JobStatus>, Unknown> {
        let state = self.lock();
        let entry = state.jobs.get(job).ok_or_else(|| Unknown::Job(job.to_string()))?;
        Ok(entry.status.subscribe())
    }

    /// Changes the job's status with `change` and publishes it (the driver's milestones). A job
    /// that ends has nothing left to lease: its open passes close and its leases go, as a
    /// cancelled job's do (a worker claiming the rest of one is told it is gone, a report on one
    /// is ignored, and no idle worker is given its tail).
    pub fn update(&self, job: &JobId, change: impl FnOnce(&mut JobStatus)) {
        let mut state = self.lock();
        let alive = alive_workers(&state, self.timing);
        let mut ended = false;
        if let Some(entry) = state.jobs.get_mut(job) {
            let mut status = entry.status.borrow().clone();
            change(&mut status);
            if is_terminal(status.state) {
                entry.passes.clear();
                ended = true;
            }
            publish(entry, status, alive);
        }
        if ended {
            state.leases.retain(|_, lease| lease.job != *job);
            state.expired.retain(|_, lease| lease.job != *job);
        }
    }

    /// Starts iteration `snapshot + 1` of `job`: `passes` passes of `batches` batches over
    /// `directions` directions. Its clock started when the one before ended, if it did here.
    pub fn start_iteration(&self, job: &JobId, passes: usize, batches: usize, directions: usize) {
        let mut state = self.lock();
        if let Some(entry) = state.jobs.get_mut(job) {
            let clock = &mut entry.clock;
            clock.iteration_started = clock.released.take().unwrap_or_else(Instant::now);
            clock.use_clock = UseClock::default();
            clock.batches_before_pass = 0;
            clock.batches_total = passes * batches;
            clock.directions = directions;
            clock.batches_per_pass = batches;
        }
    }

    /// Records that the current iteration ended (for the job's ETA and its status's
    /// [`IterationUse`](super::IterationUse)). `traffic` is what the iteration moved through the store.
    pub fn end_iteration(&self, job: &JobId, traffic: WorkTraffic) {
        let mut state = self.lock();
        let alive = alive_workers(&state, self.timing);
        if let Some(entry) = state.jobs.get_mut(job) {
            let clock = &mut entry.clock;
            let ended = Instant::now();
            let seconds = ended.duration_since(clock.iteration_started).as_secs_f64();
            clock.released = Some(ended);
            let used = clock.use_clock.end(seconds);
            clock.finished.push(IterationRecord {
                seconds,
                traffic,
                workers: used,
            });
            entry.passes.clear();
            let mut status = entry.status.borrow().clone();
            status.last_iteration = Some(used.to_wire());
            publish(entry, status, alive);
        }
    }

    /// The iterations this coordinator finished for `job`: how long each took, from its start to
    /// the start of the next (its snapshot released: the commit overlaps the next iteration),
    /// what it moved through the store and how it used the workers.
    pub fn iterations(&self, job: &JobId) -> Result<Vec<IterationRecord>, Unknown> {
        let state = self.lock();
        let entry = state.jobs.get(job).ok_or_else(|| Unknown::Job(job.to_string()))?;
        let clock = &entry.clock;
        Ok(clock.finished.clone())
    }

    /// Opens `pass` of the iteration after `snapshot`, `batches` batches, for leasing after the
    /// passes already open. Blocks whose output is already in the store (`stored`, such as
    /// [`vlf_store::FieldJob::stored_blocks`] lists) are used as they are. `reads` are the blocks
    /// of the earlier passes it reads, as absorbed: its leases name them ([`Grant::reads`](super::Grant::reads)).
    pub fn start_pass(
        &self,
        job: &JobId,
        snapshot: u32,
        pass: Pass,
        batches: usize,
        stored: &[Range<usize>],
        reads: &[(Pass, Vec<Range<usize>>)],
    ) {
        let mut state = self.lock();
        let alive = alive_workers(&state, self.timing);
        let Some(entry) = state.jobs.get_mut(job) else {
            return;
        };
        let mut run = PassRun {
            snapshot,
            pass,
            batches: (0..batches)
                .map(|_| Batch {
                    state: BatchState::Pending,
                    failures: 0,
                    expiries: 0,
                })
                .collect(),
            done_blocks: Vec::new(),
            done: 0,
            reads: reads.to_vec(),
        };
        // Where two stored blocks start together, the larger.
        let mut stored = stored.to_vec();
        stored.sort_by_key(|b| (b.start, std::cmp::Reverse(b.end)));
        for block in &stored {
            let free = run.batches[block.start.min(batches)..block.end.min(batches)]
                .iter()
                .all(|b| b.state == BatchState::Pending);
            if is_aligned_block(block, batches) && free {
                run.mark_done(block.clone());
            }
        }
        let any_done = run.done > 0;
        entry.passes.push(run);
        let status = entry.status.borrow().clone();
        publish(entry, status, alive);
        if any_done {
            entry.driver.notify_one();
        }
        drop(state);
        self.work_ready.notify_waiters();
    }

    /// Closes `pass` of the iteration after `snapshot`, whose batches are all absorbed.
    pub fn end_pass(&self, job: &JobId, snapshot: u32, pass: Pass) {
        let mut state = self.lock();
        if let Some(entry) = state.jobs.get_mut(job)
            && let Some(i) = entry
                .passes
                .iter()
                .position(|r| (r.snapshot, r.pass) == (snapshot, pass))
        {
            let run = entry.passes.remove(i);
            entry.clock.batches_before_pass += run.batches.len();
        }
    }

    /// Whether the block of the open `pass` that starts at batch `from` is written, and which
    /// blocks after it are too.
    pub fn pass_outcome(&self, job: &JobId, pass: Pass, from: usize) -> PassOutcome {
        let state = self.lock();
        let Some(entry) = state.jobs.get(job) else {
            return PassOutcome::Cancelled;
        };
        if entry.cancel_requested {
            return PassOutcome::Cancelled;
        }
        if let Some(message) = &entry.failure {
            return PassOutcome::Failed(message.clone());
        }
        let Some(run) = entry.passes.iter().find(|r| r.pass == pass) else {
            return PassOutcome::Running;
        };
        let mut ready: Vec<Range<usize>> = Vec::new();
        let mut at = from;
        while let Some(b) = run.done_blocks.iter().find(|b| b.start == at) {
            at = b.end;
            ready.push(b.clone());
        }
        if ready.is_empty() {
            PassOutcome::Running
        } else {
            PassOutcome::Ready(ready)
        }
    }

    /// Whether the job was cancelled.
    pub fn is_cancelled(&self, job: &JobId) -> bool {
        self.lock().jobs.get(job).is_none_or(|e| e.cancel_requested)
    }

    /// Asks for the job to stop: its pending batches are withdrawn and its leases dropped; the
    /// driver records the cancellation in the store. Returns the status as it stands.
    pub fn cancel(&self, job: &JobId) -> Result<JobStatus, Unknown> {
        let mut state = self.lock();
        let entry = state.jobs.get_mut(job).ok_or_else(|| Unknown::Job(job.to_string()))?;
        if !is_terminal(entry.status.borrow().state) {
            entry.cancel_requested = true;
            entry.passes.clear();
            entry.driver.notify_one();
            state.leases.retain(|_, lease| lease.job != *job);
            state.expired.retain(|_, lease| lease.job != *job);
        }
        let entry = state.jobs.get(job).ok_or_else(|| Unknown::Job(job.to_string()))?;
        Ok(entry.status.borrow().clone())
    }
}
