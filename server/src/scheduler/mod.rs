//! Jobs, leases and workers: the coordinator's state machine, with no networking.
//!
//! **Leases.** Each pass a job has open is a row of batches, each `Pending`, `Leased` or `Done`;
//! several passes of an iteration can be open at once (a perturbed iteration opens every rotated
//! copy's areas together). Outputs are written per **block**, an aligned run of batches (a node
//! of the pass's reduction tree, `vlf_core::propagate::reduce`), so how the batches are grouped
//! changes nothing in the result, only the cost: one output and one absorb per block, one round
//! trip per lease. A lease is cut when a worker asks: a run of pending batches, up to the end of
//! the aligned block of at most [`block_len`] batches that holds its first — the whole pass for
//! one worker, a quarter of a pass per worker beyond, and never so large that it would take more
//! than a quarter of the lease's lifetime at the job's measured speed — so the sizes follow the
//! workers alive and the speed as they change. A shooting pass with several workers is split into
//! their homes, runs of equal measured cost (`home`), and a worker takes what is left of its
//! home in one lease (within the same lifetime bound), then helps the others a quarter at a time.
//! A home lease commits all but its last quarter to a worker that claims ([`Abilities::claims`]);
//! the worker claims the tail when it gets there ([`Scheduler::extend`]), and a worker with nothing
//! left to do is given it meanwhile (`Scheduler::steal`): the workers even out at the end of
//! the pass what the cost split did not foresee.
//! The worker computes the run as the fewest aligned blocks that cover it (`reduce::cover`); a
//! worker that does not take runs (an earlier build) is leased single aligned blocks.
//! [`Scheduler::lease`] hands a run from the batch `PassRun::first_pending` picks (its home's
//! first, then the batches it shot last time) in
//! the first open pass of the oldest job to a worker for [`Timing::lease`]; the worker computes
//! it, writes the outputs into the store and [`Scheduler::report`]s, which may take its next
//! lease along. A lease that is not reported in time (a dead or stalled worker) expires and its
//! batches are pending again; a worker that misses three heartbeats loses its leases at once. A
//! report on a lease that is gone (expired, job cancelled) is ignored: a block's output is a pure
//! function of the job and the block, written create-only, so a late or duplicated result can
//! only write the bytes that are already there.
//!
//! **Absorbing.** Every block reported done wakes the job's driver (see [`crate::driver`]), which
//! absorbs the batches from the store in order as they come, opens the passes whose
//! prerequisites are then absorbed, and ends the iteration after the last one. A worker's failed
//! batch goes back to the pool; the third failure of the same batch fails the job (a
//! deterministic failure would otherwise loop for ever).
//!
//! **Status.** Every change publishes the job's [`JobStatus`] on a watch channel with a
//! sequence number one higher; watchers see changes in order (possibly coalesced) and the last
//! one they see is terminal.

use std::collections::HashMap;
use std::ops::Range;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::{Notify, watch};
use vlf_core::propagate::Pass;
use vlf_core::propagate::reduce::{self, is_aligned_block};
use vlf_proto::v1::{JobStatus, State as WireState};
use vlf_store::{JobId, Prototypes, Store, WorkTraffic};

mod pass;
mod usage;

pub use pass::block_len;
pub use usage::IterationUse;
use usage::UseClock;

/// A finished iteration, as the scheduler saw it ([`Scheduler::iterations`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct IterationRecord {
    /// From its start to the next one's (its snapshot released: the commit overlaps the next
    /// iteration).
    pub seconds: f64,
    /// What it moved through the store.
    pub traffic: WorkTraffic,
    /// How it used the workers.
    pub workers: IterationUse,
}
use pass::{Batch, BatchState, PassRun, Shooting, find_run, first_claim};

/// How long leases last and how often workers must be heard from.
#[derive(Clone, Copy, Debug)]
pub struct Timing {
    /// A lease's lifetime: a batch not reported by then goes to another worker.
    pub lease: Duration,
    /// The heartbeat interval asked of workers; silent for three, a worker is dead.
    pub heartbeat: Duration,
    /// Most batches a lease may hold (see [`block_len`]).
    pub max_lease_batches: usize,
}

impl Default for Timing {
    fn default() -> Self {
        Timing {
            lease: Duration::from_secs(60),
            heartbeat: Duration::from_secs(2),
            max_lease_batches: 1024,
        }
    }
}

/// A lease handed to a worker: a run of batches of one pass of the iteration after `snapshot`,
/// which the worker computes as the aligned blocks that cover it (`reduce::cover`; a single
/// block for a worker that does not take runs).
#[derive(Clone, Debug, PartialEq)]
pub struct Grant {
    pub lease_id: String,
    pub job: JobId,
    pub snapshot: u32,
    pub pass: Pass,
    pub batches: Range<usize>,
    /// The batches before this one are the worker's; the rest of the run it claims with
    /// [`Scheduler::extend`] (all of them for a worker that does not claim).
    pub committed: usize,
    pub deadline: Duration,
    /// The blocks of the earlier passes this pass reads, as the coordinator absorbed them (see
    /// [`Scheduler::start_pass`]).
    pub reads: Vec<(Pass, Vec<Range<usize>>)>,
}

/// What a worker's build can do; earlier builds lack the later abilities and are served as
/// they expect.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Abilities {
    /// It computes a lease that is a run of aligned blocks (see [`Grant`]).
    pub runs: bool,
    /// It computes only a lease's committed batches unasked and claims the others with
    /// [`Scheduler::extend`], so another worker can be given them meanwhile.
    pub claims: bool,
}

impl Abilities {
    /// This build's.
    pub const ALL: Abilities = Abilities {
        runs: true,
        claims: true,
    };
    /// A worker that computes runs but claims nothing.
    pub const RUNS: Abilities = Abilities {
        runs: true,
        claims: false,
    };
    /// A worker that computes single aligned blocks.
    pub const BLOCKS: Abilities = Abilities {
        runs: false,
        claims: false,
    };
}

/// What a driver finds when it wakes, waiting for a batch.
#[derive(Clone, Debug, PartialEq)]
pub enum PassOutcome {
    /// The block waited for is still out.
    Running,
    /// These blocks, from the one waited for on, are written (in order, contiguous).
    Ready(Vec<Range<usize>>),
    /// Cancelled by a client.
    Cancelled,
    /// A batch failed too often.
    Failed(String),
}

/// A request that names something the scheduler does not know.
#[derive(Debug, thiserror::Error)]
pub enum Unknown {
    #[error("no job `{0}`")]
    Job(String),
    #[error("worker `{0}` is not registered (the coordinator may have restarted): register again")]
    Worker(String),
}

/// The coordinator's state, shared by the gRPC services and the job drivers.
pub struct Scheduler {
    store: Store,
    timing: Timing,
    /// Where jobs' propagations are offered to workers in this process, if any share it.
    prototypes: Option<Prototypes>,
    state: Mutex<State>,
    /// Woken when batches become pending (a pass starts, a lease expires or fails).
    work_ready: Notify,
}

struct State {
    jobs: HashMap<JobId, JobEntry>,
    workers: HashMap<String, WorkerEntry>,
    leases: HashMap<String, LeaseEntry>,
    /// Source of job order, lease and worker ids.
    counter: u64,
}

struct JobEntry {
    /// Submission order: the oldest job with pending batches is served first.
    order: u64,
    /// The published status; `seq` is bumped on every change.
    status: watch::Sender<JobStatus>,
    /// The passes open for leasing, in absorbing order.
    passes: Vec<PassRun>,
    cancel_requested: bool,
    failure: Option<String>,
    /// Woken when the pass completes, fails or the job is cancelled (a stored permit: no
    /// wake-up is lost while the driver is busy).
    driver: Arc<Notify>,
    clock: Clock,
    /// Who shot each batch last, and what it cost.
    shooting: Shooting,
}

impl JobEntry {
    /// Whether its work may be leased: neither cancelled nor failed.
    fn is_open(&self) -> bool {
        !self.cancel_requested && self.failure.is_none()
    }
}

/// Timing of a job's current iteration, for throughput and ETA.
struct Clock {
    created: Instant,
    iteration_started: Instant,
    /// Batches of the iteration's passes already absorbed and closed.
    batches_before_pass: usize,
    /// Batches of all the iteration's passes.
    batches_total: usize,
    /// Directions per pass (l).
    directions: usize,
    /// Batches per pass.
    batches_per_pass: usize,
    /// The iterations this coordinator finished: their durations, work traffic and how they
    /// used the workers.
    finished: Vec<IterationRecord>,
    /// The current iteration's leases and reports so far.
    use_clock: UseClock,
    /// Compute seconds per batch of the last block reported (sizes the next passes' blocks).
    batch_seconds: Option<f64>,
}

#[derive(Clone)]
struct WorkerEntry {
    /// Registration order (the number in its id).
    number: u64,
    last_seen: Instant,
    abilities: Abilities,
}

/// A lease about to be handed out (see [`Scheduler::hand_out`]).
struct Lease<'a> {
    number: u64,
    worker: &'a str,
    batches: Range<usize>,
    committed: usize,
}

struct LeaseEntry {
    /// The number in the lease's id, which its batch's state records.
    number: u64,
    job: JobId,
    snapshot: u32,
    pass: Pass,
    worker: String,
    /// The run as it stands: its end moves earlier when another worker is given its tail.
    batches: Range<usize>,
    /// The batches before this one are the worker's (see [`Grant::committed`]).
    committed: usize,
    deadline: Instant,
}

/// A batch that failed this many times fails its job.
const MAX_BATCH_FAILURES: u32 = 3;

impl Scheduler {
    /// A scheduler over `store`; with `prototypes`, every job's propagation is offered there to
    /// workers of this process (see [`Prototypes`]).
    pub fn new(store: Store, timing: Timing, prototypes: Option<Prototypes>) -> Arc<Scheduler> {
        Arc::new(Scheduler {
            store,
            timing,
            prototypes,
            state: Mutex::new(State {
                jobs: HashMap::new(),
                workers: HashMap::new(),
                leases: HashMap::new(),
                counter: 0,
            }),
            work_ready: Notify::new(),
        })
    }

    pub fn store(&self) -> &Store {
        &self.store
    }

    pub fn prototypes(&self) -> Option<&Prototypes> {
        self.prototypes.as_ref()
    }

    pub fn timing(&self) -> Timing {
        self.timing
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock leaves plain data that every operation re-checks.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    // ------------------------------------------------------------ jobs

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
                    batches_before_pass: 0,
                    batches_total: 0,
                    directions: 0,
                    batches_per_pass: 0,
                    finished: Vec::new(),
                    use_clock: UseClock::default(),
                    batch_seconds: None,
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
        Ok(entry.status.borrow().clone())
    }

    /// Every job's status, oldest first.
    pub fn list(&self) -> Vec<JobStatus> {
        let state = self.lock();
        let mut jobs: Vec<_> = state.jobs.values().collect();
        jobs.sort_by_key(|j| j.order);
        jobs.iter().map(|j| j.status.borrow().clone()).collect()
    }

    /// A receiver of the job's status changes.
    pub fn subscribe(&self, job: &JobId) -> Result<watch::Receiver<JobStatus>, Unknown> {
        let state = self.lock();
        let entry = state.jobs.get(job).ok_or_else(|| Unknown::Job(job.to_string()))?;
        Ok(entry.status.subscribe())
    }

    /// Changes the job's status with `change` and publishes it (the driver's milestones).
    pub fn update(&self, job: &JobId, change: impl FnOnce(&mut JobStatus)) {
        let mut state = self.lock();
        let alive = alive_workers(&state, self.timing);
        if let Some(entry) = state.jobs.get_mut(job) {
            let mut status = entry.status.borrow().clone();
            change(&mut status);
            publish(entry, status, alive);
        }
    }

    /// Starts iteration `snapshot + 1` of `job`: `passes` passes of `batches` batches over
    /// `directions` directions.
    pub fn start_iteration(&self, job: &JobId, passes: usize, batches: usize, directions: usize) {
        let mut state = self.lock();
        if let Some(entry) = state.jobs.get_mut(job) {
            let clock = &mut entry.clock;
            clock.iteration_started = Instant::now();
            clock.use_clock = UseClock::default();
            clock.batches_before_pass = 0;
            clock.batches_total = passes * batches;
            clock.directions = directions;
            clock.batches_per_pass = batches;
        }
    }

    /// Records that the current iteration ended (for the job's ETA and its status's
    /// [`IterationUse`]). `traffic` is what the iteration moved through the store.
    pub fn end_iteration(&self, job: &JobId, traffic: WorkTraffic) {
        let mut state = self.lock();
        let alive = alive_workers(&state, self.timing);
        if let Some(entry) = state.jobs.get_mut(job) {
            let clock = &mut entry.clock;
            let seconds = clock.iteration_started.elapsed().as_secs_f64();
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
    /// of the earlier passes it reads, as absorbed: its leases name them ([`Grant::reads`]).
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
        }
        let entry = state.jobs.get(job).ok_or_else(|| Unknown::Job(job.to_string()))?;
        Ok(entry.status.borrow().clone())
    }

    // ------------------------------------------------------------ workers

    /// Registers a worker with what its build can do and returns its id.
    pub fn register(&self, name: &str, abilities: Abilities) -> String {
        let mut state = self.lock();
        state.counter += 1;
        let number = state.counter;
        let id = format!("w{number}-{}", sanitize(name));
        state.workers.insert(
            id.clone(),
            WorkerEntry {
                number,
                last_seen: Instant::now(),
                abilities,
            },
        );
        tracing::info!(worker = id, "worker registered");
        id
    }

    /// Workers heard from within three heartbeats.
    pub fn workers_alive(&self) -> u32 {
        alive_workers(&self.lock(), self.timing)
    }

    /// Notes that `worker` is alive.
    pub fn heartbeat(&self, worker: &str) -> Result<(), Unknown> {
        let mut state = self.lock();
        touch(&mut state, worker)
    }

    /// Leases the first pending batch of the oldest job to `worker`, waiting up to `wait` for
    /// one.
    pub async fn lease(&self, worker: &str, wait: Duration) -> Result<Option<Grant>, Unknown> {
        let until = Instant::now() + wait;
        loop {
            let notified = self.work_ready.notified();
            tokio::pin!(notified);
            // Register interest before looking, so a pass opened in between is not missed.
            notified.as_mut().enable();
            if let Some(grant) = self.try_lease(worker)? {
                return Ok(Some(grant));
            }
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            tokio::select! {
                _ = &mut notified => {}
                _ = tokio::time::sleep(left) => {}
            }
        }
    }

    fn try_lease(&self, worker: &str) -> Result<Option<Grant>, Unknown> {
        let mut guard = self.lock();
        let state = &mut *guard;
        touch(state, worker)?;
        let alive = alive_workers(state, self.timing);
        let mut jobs: Vec<(&JobId, &JobEntry)> = state.jobs.iter().collect();
        jobs.sort_by_key(|(_, j)| j.order);
        let found = jobs.iter().find_map(|(id, entry)| {
            if !entry.is_open() {
                return None;
            }
            entry.passes.iter().enumerate().find_map(|(p, run)| {
                let (b, home) = run.first_pending(worker, &entry.shooting, &state.workers)?;
                Some(((*id).clone(), p, b, home))
            })
        });
        let Some((job, p, first, home)) = found else {
            return Ok(self.steal(state, worker, alive));
        };
        state.counter += 1;
        let number = state.counter;
        let abilities = state.workers.get(worker).map(|w| w.abilities).unwrap_or_default();
        let takes_runs = abilities.runs;
        let home = home.filter(|home| alive > 1 && home.contains(&first));
        let Some(entry) = state.jobs.get_mut(&job) else {
            unreachable!("found above");
        };
        let most = self.timing.max_lease_batches.max(1);
        let speed = entry.clock.batch_seconds;
        let open: usize = entry.passes.iter().map(|r| r.batches.len() - r.done).sum();
        let run = &mut entry.passes[p];
        let n = run.batches.len();
        let (batches, committed) = match home {
            // What is left of its home in one lease, as far as the lease's lifetime allows:
            // homes are split by what the batches cost on the workers that shot them, so they
            // balance the workers, and follow one that slows down, without a lease per quarter.
            // What the cost split mispredicts, the workers even out at the end of the pass: the
            // worker claims the last quarter of its run when it gets there, and one with
            // nothing left to do can be given it meanwhile (`Scheduler::steal`).
            Some(home) if takes_runs => {
                let len = block_len(n, n, 1, speed, self.timing.lease).min(most);
                let batches = run.pending_run_within(first, home.end.min(first + len));
                let committed = first_claim(&batches, abilities.claims);
                (batches, committed)
            }
            _ => {
                let len = block_len(n, open, alive, speed, self.timing.lease).min(most);
                let batches = if takes_runs {
                    run.pending_run(first, len)
                } else {
                    run.pending_block(first, len)
                };
                (batches.clone(), batches.end)
            }
        };
        let lease = Lease {
            number,
            worker,
            batches,
            committed,
        };
        Ok(Some(self.hand_out(&mut state.leases, entry, p, job, lease, alive)))
    }

    /// Marks `lease`'s batches of the open pass `p` of `entry` (the job `job`) leased, records the
    /// lease and publishes the job's status.
    fn hand_out(
        &self,
        leases: &mut HashMap<String, LeaseEntry>,
        entry: &mut JobEntry,
        p: usize,
        job: JobId,
        lease: Lease,
        alive: u32,
    ) -> Grant {
        entry.clock.use_clock.leased();
        let run = &mut entry.passes[p];
        for b in &mut run.batches[lease.batches.clone()] {
            b.state = BatchState::Leased(lease.number);
        }
        let grant = Grant {
            lease_id: format!("l{}", lease.number),
            job: job.clone(),
            snapshot: run.snapshot,
            pass: run.pass,
            batches: lease.batches.clone(),
            committed: lease.committed,
            deadline: self.timing.lease,
            reads: run.reads.clone(),
        };
        let status = entry.status.borrow().clone();
        publish(entry, status, alive);
        leases.insert(
            grant.lease_id.clone(),
            LeaseEntry {
                number: lease.number,
                job,
                snapshot: grant.snapshot,
                pass: grant.pass,
                worker: lease.worker.to_string(),
                batches: lease.batches,
                committed: lease.committed,
                deadline: Instant::now() + self.timing.lease,
            },
        );
        grant
    }

    /// With nothing pending, gives `worker` the tail of another worker's lease that this one has
    /// not claimed yet. Of the leases of open passes with unclaimed batches, the one with the
    /// most (the oldest among equals). This is how the
    /// workers share the end of a pass as threads steal work from one another: the cost split
    /// of the homes (`home`) predicts what a worker's batches cost from the last iteration, and
    /// a worker that shares its machine, or meets other arrivals, takes longer than predicted.
    fn steal(&self, state: &mut State, worker: &str, alive: u32) -> Option<Grant> {
        let abilities = state.workers.get(worker)?.abilities;
        if !abilities.runs {
            return None;
        }
        let open = |job: &JobId| state.jobs.get(job).is_some_and(JobEntry::is_open);
        let (victim, _) = state
            .leases
            .iter()
            .filter(|(_, l)| l.worker != worker && l.committed < l.batches.end && open(&l.job))
            .map(|(id, l)| (id.clone(), (l.batches.end - l.committed, std::cmp::Reverse(l.number))))
            .max_by_key(|(_, key)| *key)?;
        state.counter += 1;
        let number = state.counter;
        let lease = state.leases.get_mut(&victim)?;
        let batches = lease.committed..lease.batches.end;
        lease.batches.end = batches.start;
        let (job, snapshot, pass) = (lease.job.clone(), lease.snapshot, lease.pass);
        let entry = state.jobs.get_mut(&job)?;
        let p = entry
            .passes
            .iter()
            .position(|r| (r.snapshot, r.pass) == (snapshot, pass))?;
        let committed = first_claim(&batches, abilities.claims);
        tracing::debug!(job = %job, ?batches, from = victim, worker, "tail of a lease given to an idle worker");
        let lease = Lease {
            number,
            worker,
            batches,
            committed,
        };
        Some(self.hand_out(&mut state.leases, entry, p, job, lease, alive))
    }

    /// `worker` claims the rest of its lease. Returns the lease as it stands, `(committed, end)`
    /// — `end` earlier than granted when its tail went to another worker — or `None` when the
    /// lease is gone (expired, its job ended).
    pub fn extend(&self, worker: &str, lease_id: &str) -> Result<Option<(usize, usize)>, Unknown> {
        let mut state = self.lock();
        touch(&mut state, worker)?;
        let Some(lease) = state.leases.get_mut(lease_id).filter(|l| l.worker == worker) else {
            return Ok(None);
        };
        lease.committed = lease.batches.end;
        Ok(Some((lease.committed, lease.batches.end)))
    }

    /// Records a worker's result for a lease: `Ok(())` when the block's output is in the store,
    /// `Err(message)` when it could not be computed; `seconds` is what computing it took. Returns
    /// whether the report was taken (`false`: the lease had expired or its job ended; nothing
    /// changes).
    pub fn report(
        &self,
        worker: &str,
        lease_id: &str,
        result: Result<(), String>,
        seconds: f64,
    ) -> Result<bool, Unknown> {
        self.report_run(worker, lease_id, result, seconds, None, &[])
    }

    /// [`Scheduler::report`] of a lease computed up to `end` (`None`: to its end): a worker
    /// that could not claim the rest (the coordinator did not answer) reports what it has, and
    /// the batches after `end` are pending again. An `end` outside the lease is not taken.
    /// `costs` are what each batch computed cost, in order (empty: `seconds` shared evenly).
    pub fn report_run(
        &self,
        worker: &str,
        lease_id: &str,
        result: Result<(), String>,
        seconds: f64,
        end: Option<usize>,
        costs: &[f64],
    ) -> Result<bool, Unknown> {
        let mut state = self.lock();
        touch(&mut state, worker)?;
        let alive = alive_workers(&state, self.timing);
        let Some(lease) = state.leases.get(lease_id) else {
            return Ok(false);
        };
        if lease.worker != worker || end.is_some_and(|e| e <= lease.batches.start || e > lease.batches.end) {
            return Ok(false);
        }
        let Some(lease) = state.leases.remove(lease_id) else {
            return Ok(false);
        };
        let number = lease.number;
        let Some(entry) = state.jobs.get_mut(&lease.job) else {
            return Ok(false);
        };
        let Some(run) = find_run(&mut entry.passes, &lease) else {
            return Ok(false);
        };
        let pass = run.pass;
        let full = lease.batches.clone();
        if !run.batches[full.clone()]
            .iter()
            .all(|b| b.state == BatchState::Leased(number))
        {
            return Ok(false);
        }
        let batches = full.start..end.unwrap_or(full.end);
        let mut requeued = false;
        if batches.end < full.end {
            for b in &mut run.batches[batches.end..full.end] {
                b.state = BatchState::Pending;
            }
            requeued = true;
        }
        match result {
            Ok(()) => {
                for block in reduce::cover(batches.clone()) {
                    run.mark_done(block);
                }
                if pass == Pass::Shoot {
                    entry
                        .shooting
                        .record(worker, batches.clone(), run.batches.len(), seconds, costs);
                }
                if seconds.is_finite() && seconds > 0.0 {
                    entry.clock.batch_seconds = Some(seconds / batches.len() as f64);
                }
                entry.clock.use_clock.reported(worker, seconds);
                entry.driver.notify_one();
            }
            Err(message) => {
                tracing::warn!(job = %lease.job, ?batches, worker, "block failed: {message}");
                let mut failures = 0;
                for b in &mut run.batches[batches.clone()] {
                    b.failures += 1;
                    b.state = BatchState::Pending;
                    failures = failures.max(b.failures);
                }
                if failures >= MAX_BATCH_FAILURES {
                    entry.failure = Some(format!(
                        "batches {batches:?} of {pass:?} failed {failures} times; last: {message}"
                    ));
                    entry.driver.notify_one();
                } else {
                    requeued = true;
                }
            }
        }
        let status = entry.status.borrow().clone();
        publish(entry, status, alive);
        drop(state);
        if requeued {
            self.work_ready.notify_waiters();
        }
        Ok(true)
    }

    /// Expires leases past their deadline and forgets workers silent for three heartbeats
    /// (their leases expire with them). Returns how many leases expired.
    pub fn reap(&self) -> usize {
        let now = Instant::now();
        let mut state = self.lock();
        let dead_after = self.timing.heartbeat * 3;
        let dead: Vec<String> = state
            .workers
            .iter()
            .filter(|(_, w)| now.duration_since(w.last_seen) > dead_after)
            .map(|(id, _)| id.clone())
            .collect();
        for id in &dead {
            tracing::warn!(
                worker = id,
                "worker silent for 3 heartbeats: its leases go back to the pool"
            );
            state.workers.remove(id);
        }
        let expired: Vec<String> = state
            .leases
            .iter()
            .filter(|(_, l)| l.deadline <= now || dead.contains(&l.worker))
            .map(|(id, _)| id.clone())
            .collect();
        let alive = alive_workers(&state, self.timing);
        for id in &expired {
            let Some(lease) = state.leases.remove(id) else {
                continue;
            };
            let number = lease.number;
            if let Some(entry) = state.jobs.get_mut(&lease.job) {
                if let Some(run) = find_run(&mut entry.passes, &lease) {
                    let batches = lease.batches.clone();
                    let mut any = false;
                    for b in &mut run.batches[batches.clone()] {
                        if b.state == BatchState::Leased(number) {
                            b.state = BatchState::Pending;
                            any = true;
                        }
                    }
                    if any {
                        tracing::warn!(job = %lease.job, ?batches, worker = lease.worker, "lease expired");
                    }
                }
                let status = entry.status.borrow().clone();
                publish(entry, status, alive);
            }
        }
        drop(state);
        if !expired.is_empty() {
            self.work_ready.notify_waiters();
        }
        expired.len()
    }
}

/// Whether a wire state is one a job does not leave.
pub fn is_terminal(state: i32) -> bool {
    matches!(
        WireState::try_from(state),
        Ok(WireState::Finished | WireState::Failed | WireState::Cancelled)
    )
}

fn touch(state: &mut State, worker: &str) -> Result<(), Unknown> {
    let entry = state
        .workers
        .get_mut(worker)
        .ok_or_else(|| Unknown::Worker(worker.to_string()))?;
    entry.last_seen = Instant::now();
    Ok(())
}

fn alive_workers(state: &State, timing: Timing) -> u32 {
    let now = Instant::now();
    state
        .workers
        .values()
        .filter(|w| now.duration_since(w.last_seen) <= timing.heartbeat * 3)
        .count() as u32
}

/// Publishes `status` with the progress figures of `entry` and the next sequence number.
fn publish(entry: &mut JobEntry, mut status: JobStatus, workers_alive: u32) {
    let clock = &entry.clock;
    let done: usize = entry.passes.iter().map(|r| r.done).sum();
    let mut leases: Vec<u64> = entry
        .passes
        .iter()
        .flat_map(|r| &r.batches)
        .filter_map(|b| match b.state {
            BatchState::Leased(n) => Some(n),
            _ => None,
        })
        .collect();
    leases.dedup();
    let leased = leases.len();
    let batches_done = clock.batches_before_pass + done;
    let elapsed = clock.iteration_started.elapsed().as_secs_f64();
    status.seq += 1;
    status.workers_alive = workers_alive;
    status.leases_out = leased as u32;
    status.elapsed_seconds = clock.created.elapsed().as_secs_f64();
    if is_terminal(status.state) {
        status.batches_done = 0;
        status.batches_total = 0;
        status.directions_per_second = 0.0;
        status.eta_iteration_seconds = -1.0;
        status.eta_job_seconds = if status.state == WireState::Finished as i32 {
            0.0
        } else {
            -1.0
        };
    } else {
        status.batches_done = batches_done as u32;
        status.batches_total = clock.batches_total as u32;
        let per_batch = if clock.batches_per_pass > 0 {
            clock.directions as f64 / clock.batches_per_pass as f64
        } else {
            0.0
        };
        let rate = if elapsed > 0.0 && batches_done > 0 {
            batches_done as f64 / elapsed
        } else {
            0.0
        };
        status.directions_per_second = rate * per_batch;
        let left = clock.batches_total.saturating_sub(batches_done) as f64;
        status.eta_iteration_seconds = if rate > 0.0 { left / rate } else { -1.0 };
        status.eta_job_seconds = -1.0;
        if status.iterations_planned > 0 && status.eta_iteration_seconds >= 0.0 {
            let per_iteration = if clock.finished.is_empty() {
                elapsed + status.eta_iteration_seconds
            } else {
                clock.finished.iter().map(|r| r.seconds).sum::<f64>() / clock.finished.len() as f64
            };
            let after = status.iterations_planned.saturating_sub(status.iteration.max(1)) as f64;
            status.eta_job_seconds = status.eta_iteration_seconds + after * per_iteration;
        }
    }
    entry.status.send_replace(status);
}

/// A worker's name as it may appear in its id.
fn sanitize(name: &str) -> String {
    name.chars()
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        .take(48)
        .collect()
}

#[cfg(test)]
mod tests;
