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

/// What the scheduler remembers of a job's shooting passes, per batch.
#[derive(Default)]
struct Shooting {
    /// The worker that computed it last: it keeps the batch's mirror maps (`vlf_store::Replica`),
    /// so leasing it the same batches again saves reading them back.
    shooters: Vec<Option<String>>,
    /// Compute seconds of its last lease, shared equally among that lease's batches: what
    /// [`home`] splits the pass by.
    seconds: Vec<f64>,
}

impl Shooting {
    /// Records that `worker` shot `batches` of a pass of `len` batches in `seconds`.
    fn record(&mut self, worker: &str, batches: Range<usize>, len: usize, seconds: f64) {
        if self.shooters.len() < len {
            self.shooters.resize(len, None);
            self.seconds.resize(len, 0.0);
        }
        let share = seconds / batches.len().max(1) as f64;
        for b in batches {
            self.shooters[b] = Some(worker.to_string());
            if share.is_finite() && share > 0.0 {
                self.seconds[b] = share;
            }
        }
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
    /// Durations of the iterations this coordinator finished, and their work traffic.
    iteration_seconds: Vec<f64>,
    traffic: Vec<WorkTraffic>,
    /// Compute seconds per batch of the last block reported (sizes the next passes' blocks).
    batch_seconds: Option<f64>,
}

struct PassRun {
    snapshot: u32,
    pass: Pass,
    batches: Vec<Batch>,
    /// The blocks whose outputs are written, in order (they never overlap).
    done_blocks: Vec<Range<usize>>,
    /// How many batches are done.
    done: usize,
}

#[derive(Clone, Copy, PartialEq)]
enum BatchState {
    Pending,
    Leased(u64),
    Done,
}

struct Batch {
    state: BatchState,
    /// Failed leases that held this batch.
    failures: u32,
}

#[derive(Clone)]
struct WorkerEntry {
    /// Registration order (the number in its id).
    number: u64,
    last_seen: Instant,
    abilities: Abilities,
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
                    iteration_seconds: Vec::new(),
                    traffic: Vec::new(),
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
            clock.batches_before_pass = 0;
            clock.batches_total = passes * batches;
            clock.directions = directions;
            clock.batches_per_pass = batches;
        }
    }

    /// Records that the current iteration ended (for the job's ETA).
    /// `traffic` is what the iteration moved through the store.
    pub fn end_iteration(&self, job: &JobId, traffic: WorkTraffic) {
        let mut state = self.lock();
        if let Some(entry) = state.jobs.get_mut(job) {
            let seconds = entry.clock.iteration_started.elapsed().as_secs_f64();
            entry.clock.iteration_seconds.push(seconds);
            entry.clock.traffic.push(traffic);
            entry.passes.clear();
        }
    }

    /// The iterations this coordinator finished for `job`: how long each took, from its start to
    /// the start of the next (its snapshot released: the commit overlaps the next iteration), and
    /// what it moved through the store.
    pub fn iterations(&self, job: &JobId) -> Result<Vec<(f64, WorkTraffic)>, Unknown> {
        let state = self.lock();
        let entry = state.jobs.get(job).ok_or_else(|| Unknown::Job(job.to_string()))?;
        let clock = &entry.clock;
        Ok(clock
            .iteration_seconds
            .iter()
            .copied()
            .zip(clock.traffic.iter().copied())
            .collect())
    }

    /// Opens `pass` of the iteration after `snapshot`, `batches` batches, for leasing after the
    /// passes already open. Blocks whose output is already in the store (`stored`, such as
    /// [`vlf_store::FieldJob::stored_blocks`] lists) are used as they are.
    pub fn start_pass(&self, job: &JobId, snapshot: u32, pass: Pass, batches: usize, stored: &[Range<usize>]) {
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
        let mut state = self.lock();
        touch(&mut state, worker)?;
        let alive = alive_workers(&state, self.timing);
        let mut jobs: Vec<(&JobId, &JobEntry)> = state.jobs.iter().collect();
        jobs.sort_by_key(|(_, j)| j.order);
        let found = jobs.iter().find_map(|(id, entry)| {
            if entry.cancel_requested || entry.failure.is_some() {
                return None;
            }
            entry.passes.iter().enumerate().find_map(|(p, run)| {
                let (b, home) = run.first_pending(worker, &entry.shooting, &state.workers)?;
                Some(((*id).clone(), p, b, home))
            })
        });
        let Some((job, p, first, home)) = found else {
            return Ok(self.steal(&mut state, worker, alive));
        };
        state.counter += 1;
        let number = state.counter;
        let lease_id = format!("l{number}");
        let deadline = Instant::now() + self.timing.lease;
        let abilities = state.workers.get(worker).map(|w| w.abilities).unwrap_or_default();
        let takes_runs = abilities.runs;
        let home = home.filter(|home| alive > 1 && home.contains(&first));
        let Some(entry) = state.jobs.get_mut(&job) else {
            unreachable!("found above");
        };
        let most = self.timing.max_lease_batches.max(1);
        let speed = entry.clock.batch_seconds;
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
                let len = block_len(n, 1, speed, self.timing.lease).min(most);
                let batches = run.pending_run_within(first, home.end.min(first + len));
                let committed = match abilities.claims {
                    true => first_claim(&batches),
                    false => batches.end,
                };
                (batches, committed)
            }
            _ => {
                let len = block_len(n, alive, speed, self.timing.lease).min(most);
                let batches = if takes_runs {
                    run.pending_run(first, len)
                } else {
                    run.pending_block(first, len)
                };
                (batches.clone(), batches.end)
            }
        };
        for b in &mut run.batches[batches.clone()] {
            b.state = BatchState::Leased(number);
        }
        let grant = Grant {
            lease_id: lease_id.clone(),
            job: job.clone(),
            snapshot: run.snapshot,
            pass: run.pass,
            batches,
            committed,
            deadline: self.timing.lease,
        };
        let status = entry.status.borrow().clone();
        publish(entry, status, alive);
        state.leases.insert(
            lease_id,
            LeaseEntry {
                number,
                job,
                snapshot: grant.snapshot,
                pass: grant.pass,
                worker: worker.to_string(),
                batches: grant.batches.clone(),
                committed,
                deadline,
            },
        );
        Ok(Some(grant))
    }

    /// With nothing pending, gives `worker` the tail of another worker's lease that this one has
    /// not claimed yet: half of it (rounded up), from its end. Of the leases of open passes with
    /// unclaimed batches, the one with the most (the oldest among equals). This is how the
    /// workers share the end of a pass as threads steal work from one another: the cost split
    /// of the homes (`home`) predicts what a worker's batches cost from the last iteration, and
    /// a worker that shares its machine, or meets other arrivals, takes longer than predicted.
    fn steal(&self, state: &mut State, worker: &str, alive: u32) -> Option<Grant> {
        let abilities = state.workers.get(worker)?.abilities;
        if !abilities.runs {
            return None;
        }
        let open = |job: &JobId| {
            state
                .jobs
                .get(job)
                .is_some_and(|e| !e.cancel_requested && e.failure.is_none())
        };
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
        let run = entry
            .passes
            .iter_mut()
            .find(|r| (r.snapshot, r.pass) == (snapshot, pass))?;
        for b in &mut run.batches[batches.clone()] {
            b.state = BatchState::Leased(number);
        }
        let committed = match abilities.claims {
            true => first_claim(&batches),
            false => batches.end,
        };
        tracing::debug!(job = %job, ?batches, from = victim, worker, "tail of a lease given to an idle worker");
        let grant = Grant {
            lease_id: format!("l{number}"),
            job: job.clone(),
            snapshot,
            pass,
            batches,
            committed,
            deadline: self.timing.lease,
        };
        let status = entry.status.borrow().clone();
        publish(entry, status, alive);
        state.leases.insert(
            grant.lease_id.clone(),
            LeaseEntry {
                number,
                job,
                snapshot,
                pass,
                worker: worker.to_string(),
                batches: grant.batches.clone(),
                committed,
                deadline: Instant::now() + self.timing.lease,
            },
        );
        Some(grant)
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
        self.report_run(worker, lease_id, result, seconds, None)
    }

    /// [`Scheduler::report`] of a lease computed up to `end` (`None`: to its end): a worker
    /// that could not claim the rest (the coordinator did not answer) reports what it has, and
    /// the batches after `end` are pending again. An `end` outside the lease is not taken.
    pub fn report_run(
        &self,
        worker: &str,
        lease_id: &str,
        result: Result<(), String>,
        seconds: f64,
        end: Option<usize>,
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
                        .record(worker, batches.clone(), run.batches.len(), seconds);
                }
                if seconds.is_finite() && seconds > 0.0 {
                    entry.clock.batch_seconds = Some(seconds / batches.len() as f64);
                }
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

/// The part of a run a worker that claims is committed when it is leased: all but its last
/// quarter (rounded down: a run of fewer than 4 batches is committed whole). The worker claims
/// that tail as it starts the batch before it ([`Scheduler::extend`]); until then the tail can
/// go to an idle worker. One claim per lease, and the batches computed in single steps are
/// the few around it: each claim costs a round trip, each step some setup, and a quarter of a
/// worker's home is more than the cost split mispredicts in the iterations measured.
fn first_claim(run: &Range<usize>) -> usize {
    run.end - run.len() / 4
}

/// Batches per block for a pass of `batches` batches: all of them for one worker (a lease per
/// pass), a quarter of a pass per worker beyond (`batches / 2·workers`, rounded to a power of
/// two, so that a slow worker holds back little), and small enough that a block takes at most a
/// quarter of the lease's lifetime at `batch_seconds` per batch. Before the job's first report
/// nothing is known of its speed: blocks of one batch.
pub fn block_len(batches: usize, workers: u32, batch_seconds: Option<f64>, lease: Duration) -> usize {
    let Some(per_batch) = batch_seconds else {
        return 1;
    };
    let by_workers = match workers {
        0 | 1 => batches,
        w => batches / (2 * w as usize).next_power_of_two(),
    };
    let budget = lease.as_secs_f64() / 4.0;
    let mut len = by_workers.max(1).next_power_of_two();
    while len > 1 && (len > batches || len as f64 * per_batch > budget) {
        len /= 2;
    }
    len
}

impl PassRun {
    /// The pending batch `worker` should start a lease at, and for a shooting pass its [`home`].
    /// Of a shooting pass: the first of its home; else the first it shot last time (it keeps their mirror maps); else the first
    /// that no other registered worker shot. Else — rather than wait — the first pending batch.
    ///
    /// Homes matter for mirrors: a direction gathers what arrived from the directions that
    /// reflect into it, which are near it in direction order (the bundled mirror scene's 16
    /// batches read from at most their neighbours' neighbours). Two workers that shoot the halves
    /// of the pass read 4 batches of each other's arrivals; leased blocks in the order asked,
    /// they interleave and read nearly everything. As homes stay put while the workers do, a
    /// worker shoots the same batches from iteration to iteration and keeps their maps.
    fn first_pending(
        &self,
        worker: &str,
        shooting: &Shooting,
        workers: &HashMap<String, WorkerEntry>,
    ) -> Option<(usize, Option<Range<usize>>)> {
        let pending = || (0..self.batches.len()).filter(|&b| self.batches[b].state == BatchState::Pending);
        if self.pass != Pass::Shoot {
            return pending().next().map(|b| (b, None));
        }
        let shooter = |b: usize| shooting.shooters.get(b).and_then(Option::as_deref);
        let home = home(worker, workers, self.batches.len(), &shooting.seconds);
        let at_home = pending().find(|&b| home.contains(&b));
        let own = || pending().find(|&b| shooter(b) == Some(worker));
        let free = || pending().find(|&b| shooter(b).is_none_or(|w| !workers.contains_key(w)));
        let first = at_home.or_else(own).or_else(free).or_else(|| pending().next())?;
        Some((first, Some(home)))
    }

    /// The largest aligned block of at most `len` batches from `first` (a pending batch) whose
    /// batches are all pending.
    fn pending_block(&self, first: usize, len: usize) -> Range<usize> {
        let n = self.batches.len();
        let mut size = len.max(1).next_power_of_two();
        while size > 1
            && (!first.is_multiple_of(size)
                || first + size > n
                || self.batches[first..first + size]
                    .iter()
                    .any(|b| b.state != BatchState::Pending))
        {
            size /= 2;
        }
        first..first + size
    }

    /// The run of pending batches from `first` (a pending batch) to the end of the aligned block
    /// of `len` batches (rounded up to a power of two) that holds it, or to the first batch that
    /// is not pending: what a worker that takes runs is leased. From an aligned `first` it is
    /// [`PassRun::pending_block`]'s block or more; past one (after the first lease of a job, one
    /// batch to learn its speed) it takes the rest of that block in one lease instead of one
    /// lease per aligned piece.
    fn pending_run(&self, first: usize, len: usize) -> Range<usize> {
        let size = len.max(1).next_power_of_two();
        let end = ((first / size + 1) * size).min(self.batches.len());
        let pending = self.batches[first..end]
            .iter()
            .take_while(|b| b.state == BatchState::Pending)
            .count();
        first..first + pending.max(1)
    }

    /// The run of pending batches from `first` (a pending batch) up to `end` or to the first batch
    /// that is not pending.
    fn pending_run_within(&self, first: usize, end: usize) -> Range<usize> {
        let end = end.clamp(first + 1, self.batches.len());
        let pending = self.batches[first..end]
            .iter()
            .take_while(|b| b.state == BatchState::Pending)
            .count();
        first..first + pending.max(1)
    }

    /// Records that the output of `block` is written.
    fn mark_done(&mut self, block: Range<usize>) {
        for b in &mut self.batches[block.clone()] {
            b.state = BatchState::Done;
        }
        self.done += block.len();
        let at = self.done_blocks.partition_point(|b| b.start < block.start);
        self.done_blocks.insert(at, block);
    }
}

/// The open pass a lease belongs to.
/// `worker`'s home in a pass of `batches` batches: the registered workers, in registration
/// order, split the pass into runs of consecutive batches of equal cost (all of it for a lone
/// worker). A batch costs the `seconds` its last lease measured, or the mean of those measured
/// (all alike before any): batches differ — the mirror scene's first quarter shoots in half the
/// time of its last — and equal runs had one of two workers wait for the other every iteration.
fn home(worker: &str, workers: &HashMap<String, WorkerEntry>, batches: usize, seconds: &[f64]) -> Range<usize> {
    let mut order: Vec<(u64, &str)> = workers.iter().map(|(id, w)| (w.number, id.as_str())).collect();
    order.sort_unstable();
    let Some(rank) = order.iter().position(|(_, id)| *id == worker) else {
        return 0..batches;
    };
    let measured: Vec<f64> = seconds.iter().copied().filter(|s| *s > 0.0).collect();
    let mean = match measured.len() {
        0 => 1.0,
        n => measured.iter().sum::<f64>() / n as f64,
    };
    // Cost before each batch boundary: before[b] is the cost of batches 0..b.
    let mut before = vec![0.0; batches + 1];
    for b in 0..batches {
        let cost = seconds.get(b).copied().filter(|s| *s > 0.0).unwrap_or(mean);
        before[b + 1] = before[b] + cost;
    }
    // Worker r's home starts at the boundary nearest to r/w of the total.
    let start = |r: usize| -> usize {
        let target = before[batches] * r as f64 / order.len() as f64;
        (0..=batches)
            .min_by(|&a, &b| (before[a] - target).abs().total_cmp(&(before[b] - target).abs()))
            .unwrap_or(0)
    };
    start(rank)..start(rank + 1)
}

fn find_run<'a>(passes: &'a mut [PassRun], lease: &LeaseEntry) -> Option<&'a mut PassRun> {
    passes
        .iter_mut()
        .find(|r| (r.snapshot, r.pass) == (lease.snapshot, lease.pass))
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
            let per_iteration = if clock.iteration_seconds.is_empty() {
                elapsed + status.eta_iteration_seconds
            } else {
                clock.iteration_seconds.iter().sum::<f64>() / clock.iteration_seconds.len() as f64
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
// Blocks of one range are what these tests mean.
#[allow(clippy::single_range_in_vec_init)]
mod tests {
    use super::*;

    fn scheduler(lease_ms: u64) -> Arc<Scheduler> {
        Scheduler::new(
            Store::open("memory://").unwrap(),
            Timing {
                lease: Duration::from_millis(lease_ms),
                heartbeat: Duration::from_secs(60),
                max_lease_batches: 1024,
            },
            None,
        )
    }

    fn job(s: &Scheduler) -> JobId {
        let id = JobId::generate();
        s.add_job(JobStatus {
            job_id: id.to_string(),
            state: WireState::Propagating as i32,
            ..Default::default()
        })
        .unwrap();
        s.start_iteration(&id, 1, 3, 40);
        id
    }

    #[tokio::test]
    async fn batches_are_leased_once_and_a_pass_completes_when_all_are_reported() {
        let s = scheduler(60_000);
        let id = job(&s);
        s.start_pass(&id, 0, Pass::Shoot, 3, &[1..2]);
        let w = s.register("a", Abilities::ALL);
        let a = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        let b = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((a.batches, b.batches), (0..1, 2..3), "batch 1 was already in the store");
        assert_eq!(s.lease(&w, Duration::from_millis(10)).await.unwrap(), None);
        assert_eq!(s.pass_outcome(&id, Pass::Shoot, 0), PassOutcome::Running);
        assert!(s.report(&w, &a.lease_id, Ok(()), 0.01).unwrap());
        assert!(
            !s.report(&w, &a.lease_id, Ok(()), 0.01).unwrap(),
            "a lease reports once"
        );
        assert_eq!(s.status(&id).unwrap().batches_done, 2);
        assert_eq!(
            s.pass_outcome(&id, Pass::Shoot, 0),
            PassOutcome::Ready(vec![0..1, 1..2]),
            "batches 0 and 1 can be absorbed while 2 is out"
        );
        assert_eq!(s.pass_outcome(&id, Pass::Shoot, 2), PassOutcome::Running);
        assert!(s.report(&w, &b.lease_id, Ok(()), 0.01).unwrap());
        assert_eq!(s.pass_outcome(&id, Pass::Shoot, 2), PassOutcome::Ready(vec![2..3]));
        assert!(matches!(s.heartbeat("nobody"), Err(Unknown::Worker(_))));
    }

    #[tokio::test]
    async fn an_expired_lease_goes_to_another_worker_and_its_late_report_is_ignored() {
        let s = scheduler(20);
        let id = job(&s);
        s.start_pass(&id, 4, Pass::Areas { copy: 1 }, 1, &[]);
        let (w1, w2) = (s.register("slow", Abilities::ALL), s.register("fast", Abilities::ALL));
        let first = s.lease(&w1, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((first.snapshot, first.pass), (4, Pass::Areas { copy: 1 }));
        assert_eq!(s.lease(&w2, Duration::ZERO).await.unwrap(), None);
        tokio::time::sleep(Duration::from_millis(30)).await;
        assert_eq!(s.reap(), 1);
        let second = s.lease(&w2, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(second.batches, first.batches);
        assert!(
            !s.report(&w1, &first.lease_id, Ok(()), 0.01).unwrap(),
            "late report ignored"
        );
        let areas = Pass::Areas { copy: 1 };
        assert_eq!(s.pass_outcome(&id, areas, 0), PassOutcome::Running);
        assert!(s.report(&w2, &second.lease_id, Ok(()), 0.01).unwrap());
        assert_eq!(s.pass_outcome(&id, areas, 0), PassOutcome::Ready(vec![0..1]));
    }

    #[tokio::test]
    async fn several_open_passes_are_leased_in_order_and_closed_as_absorbed() {
        let s = scheduler(60_000);
        let id = job(&s);
        let (a0, a1) = (Pass::Areas { copy: 0 }, Pass::Areas { copy: 1 });
        s.start_pass(&id, 2, a0, 3, &[]);
        s.start_pass(&id, 2, a1, 3, &[1..2]);
        let w = s.register("a", Abilities::ALL);
        let mut grants = Vec::new();
        while let Some(g) = s.lease(&w, Duration::ZERO).await.unwrap() {
            grants.push(g);
        }
        let order: Vec<_> = grants.iter().map(|g| (g.pass, g.batches.start)).collect();
        assert_eq!(order, vec![(a0, 0), (a0, 1), (a0, 2), (a1, 0), (a1, 2)]);
        assert!(grants.iter().all(|g| g.snapshot == 2));
        // A report finds its own pass's batch, whichever pass it is.
        assert!(s.report(&w, &grants[3].lease_id, Ok(()), 0.01).unwrap());
        assert_eq!(s.pass_outcome(&id, a1, 0), PassOutcome::Ready(vec![0..1, 1..2]));
        assert_eq!(s.pass_outcome(&id, a0, 0), PassOutcome::Running);
        for g in &grants[..3] {
            assert!(s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap());
        }
        assert_eq!(s.pass_outcome(&id, a0, 0), PassOutcome::Ready(vec![0..1, 1..2, 2..3]));
        assert_eq!(s.status(&id).unwrap().batches_done, 5);
        s.end_pass(&id, 2, a0);
        assert_eq!(
            s.status(&id).unwrap().batches_done,
            5,
            "a closed pass still counts as done"
        );
        assert_eq!(s.pass_outcome(&id, a0, 0), PassOutcome::Running, "closed");
        assert!(s.report(&w, &grants[4].lease_id, Ok(()), 0.01).unwrap());
        assert_eq!(s.pass_outcome(&id, a1, 2), PassOutcome::Ready(vec![2..3]));
    }

    #[test]
    fn blocks_grow_with_fewer_workers_and_shrink_for_slow_batches() {
        let minute = Duration::from_secs(60);
        assert_eq!(block_len(16, 1, None, minute), 1, "speed unknown");
        assert_eq!(block_len(16, 1, Some(0.01), minute), 16, "one worker: the whole pass");
        assert_eq!(block_len(16, 0, Some(0.01), minute), 16);
        assert_eq!(block_len(16, 2, Some(0.01), minute), 4);
        assert_eq!(block_len(16, 3, Some(0.01), minute), 2);
        assert_eq!(block_len(16, 64, Some(0.01), minute), 1);
        assert_eq!(block_len(8, 1, Some(2.0), minute), 4, "4 × 2 s ≤ 15 s < 8 × 2 s");
        assert_eq!(block_len(8, 1, Some(100.0), minute), 1);
        assert_eq!(block_len(2, 1, Some(0.01), minute), 2);
    }

    /// A job whose speed `w` has measured (a one-batch pass reported), so leases are sized by
    /// the workers.
    async fn job_of_known_speed(s: &Scheduler, w: &str) -> JobId {
        let id = job(s);
        s.start_pass(&id, 0, Pass::Shoot, 1, &[]);
        let g = s.lease(w, Duration::ZERO).await.unwrap().unwrap();
        assert!(s.report(w, &g.lease_id, Ok(()), 0.01).unwrap());
        s.end_pass(&id, 0, Pass::Shoot);
        id
    }

    #[tokio::test]
    async fn stored_blocks_are_kept_and_new_blocks_never_straddle_them() {
        let s = scheduler(60_000);
        let w = s.register("a", Abilities::ALL);
        // The speed is known: one worker leases as much as it can.
        let id = job_of_known_speed(&s, &w).await;
        let areas = Pass::Areas { copy: 0 };
        // In the store: 0..2 and 0..4 (the larger is taken), 1..3 (not a node of the tree:
        // ignored), 4..6 and 12..16.
        s.start_pass(&id, 0, areas, 16, &[0..2, 0..4, 1..3, 4..6, 12..16]);
        assert_eq!(s.pass_outcome(&id, areas, 0), PassOutcome::Ready(vec![0..4, 4..6]));
        // With two workers, blocks of 4 batches at most: one that does not take runs gets an
        // aligned block, one that does the rest of the next block.
        let old = s.register("old", Abilities::BLOCKS);
        let g = s.lease(&old, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 6..8);
        let mut grants = Vec::new();
        while let Some(g) = s.lease(&w, Duration::ZERO).await.unwrap() {
            grants.push(g.batches);
        }
        assert_eq!(grants, vec![8..12]);
        // Alone, a worker that takes runs gets the gap in one lease.
        let s = scheduler(60_000);
        let w = s.register("a", Abilities::ALL);
        let id = job_of_known_speed(&s, &w).await;
        s.start_pass(&id, 0, areas, 16, &[0..2, 0..4, 1..3, 4..6, 12..16]);
        let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 6..12, "up to the stored block, not into it");
        assert!(s.lease(&w, Duration::ZERO).await.unwrap().is_none());
        // Its report marks every aligned block of the run written.
        assert!(s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap());
        assert_eq!(
            s.pass_outcome(&id, areas, 0),
            PassOutcome::Ready(vec![0..4, 4..6, 6..8, 8..12, 12..16])
        );
    }

    #[tokio::test]
    async fn after_a_report_a_lone_worker_leases_whole_passes() {
        let s = scheduler(60_000);
        let id = job(&s);
        let w = s.register("a", Abilities::ALL);
        s.start_pass(&id, 0, Pass::Shoot, 16, &[]);
        let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 0..1, "speed unknown: one batch");
        assert!(s.report(&w, &g.lease_id, Ok(()), 0.05).unwrap());
        s.start_pass(&id, 0, Pass::Areas { copy: 0 }, 16, &[]);
        let mut grants = Vec::new();
        while let Some(g) = s.lease(&w, Duration::ZERO).await.unwrap() {
            grants.push((g.pass, g.batches));
        }
        // The rest of the pass in one lease, then the next pass whole.
        let shoot = Pass::Shoot;
        assert_eq!(grants, [(shoot, 1..16), (Pass::Areas { copy: 0 }, 0..16)]);

        // A worker that does not take runs gets the rest in the largest aligned blocks.
        let s = scheduler(60_000);
        let id = job(&s);
        let w = s.register("old", Abilities::BLOCKS);
        s.start_pass(&id, 0, Pass::Shoot, 16, &[]);
        let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 0..1, "speed unknown: one batch");
        assert!(s.report(&w, &g.lease_id, Ok(()), 0.05).unwrap());
        let mut grants = Vec::new();
        while let Some(g) = s.lease(&w, Duration::ZERO).await.unwrap() {
            grants.push(g.batches);
        }
        assert_eq!(grants, [1..2, 2..4, 4..8, 8..16]);
    }

    #[tokio::test]
    async fn a_worker_shoots_the_batches_it_shot_last_time() {
        let s = scheduler(60_000);
        let id = job(&s);
        let (a, b) = (s.register("a", Abilities::ALL), s.register("b", Abilities::ALL));
        let shoot = Pass::Shoot;
        // Iteration 1: a takes the first half, b the second.
        s.start_pass(&id, 0, shoot, 4, &[]);
        let mut first = Vec::new();
        for w in [&a, &a, &b, &b] {
            let g = s.lease(w, Duration::ZERO).await.unwrap().unwrap();
            first.push(g.batches.clone());
            assert!(s.report(w, &g.lease_id, Ok(()), 0.0).unwrap());
        }
        assert_eq!(first, [0..1, 1..2, 2..3, 3..4]);
        s.end_pass(&id, 0, shoot);
        // Iteration 2: b asks first and is given its own batches, not batch 0; a pass of another
        // kind keeps the plain order.
        s.start_pass(&id, 1, shoot, 4, &[]);
        let g = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches.start, 2, "b shot batches 2 and 3 last time");
        let h = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(h.batches.start, 0);
        assert!(s.report(&b, &g.lease_id, Ok(()), 0.0).unwrap());
        assert!(s.report(&a, &h.lease_id, Ok(()), 0.0).unwrap());
        let own = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(own.batches, 3..4);
        // What is left of a's batches goes to b rather than nobody: no worker waits.
        let rest = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(rest.batches, 1..2);
        s.start_pass(&id, 1, Pass::Areas { copy: 0 }, 4, &[]);
        let areas = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((areas.pass, areas.batches.start), (Pass::Areas { copy: 0 }, 0));
    }

    #[tokio::test]
    async fn two_workers_shoot_the_halves_of_the_pass_whatever_order_they_ask_in() {
        let s = scheduler(60_000);
        let id = job(&s);
        let (a, b) = (s.register("a", Abilities::ALL), s.register("b", Abilities::ALL));
        let shoot = Pass::Shoot;
        s.start_pass(&id, 0, shoot, 16, &[]);
        // Speed unknown: one batch each, a at the start of its home, b at the start of its own.
        let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((ga.batches.clone(), gb.batches.clone()), (0..1, 8..9));
        assert!(s.report(&a, &ga.lease_id, Ok(()), 0.01).unwrap());
        assert!(s.report(&b, &gb.lease_id, Ok(()), 0.01).unwrap());
        // Then each the rest of its home in one lease, asked for in turn.
        let mut got: HashMap<String, Vec<Range<usize>>> = HashMap::new();
        for w in [&a, &b, &a, &b] {
            if let Some(g) = s.lease(w, Duration::ZERO).await.unwrap() {
                got.entry(w.clone()).or_default().push(g.batches.clone());
                assert!(s.report(w, &g.lease_id, Ok(()), 0.01 * g.batches.len() as f64).unwrap());
            }
        }
        assert_eq!(got[&a], [1..8]);
        assert_eq!(got[&b], [9..16]);
        s.end_pass(&id, 0, shoot);
        // The next iteration keeps them: b, asking first, gets its half.
        s.start_pass(&id, 1, shoot, 16, &[]);
        let g = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 8..16);
        // Done with its home, b helps with a's, a quarter of the pass at a time, from the start.
        let g = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 0..4);
        // a then takes what is left of its home.
        let g = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 4..8);
    }

    /// A job whose speed is known, and its shooting pass of 16 batches open, with workers `a`
    /// and `b` registered with `abilities`.
    async fn two_workers_and_a_pass(s: &Scheduler, abilities: Abilities) -> (JobId, String, String) {
        let (a, b) = (s.register("a", abilities), s.register("b", abilities));
        let id = job_of_known_speed(s, &a).await;
        s.start_pass(&id, 1, Pass::Shoot, 16, &[]);
        (id, a, b)
    }

    #[tokio::test]
    async fn an_idle_worker_is_given_the_tail_a_busy_one_has_not_claimed() {
        let s = scheduler(60_000);
        let (id, a, b) = two_workers_and_a_pass(&s, Abilities::ALL).await;
        // Each worker's home in one lease, its last quarter not committed.
        let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((ga.batches.clone(), ga.committed), (0..8, 6));
        assert_eq!((gb.batches.clone(), gb.committed), (8..16, 14));
        // b is done first (it claimed its tail, then reported); a has not claimed its tail: b
        // is given it, committed whole (too short to share again).
        assert_eq!(s.extend(&b, &gb.lease_id).unwrap(), Some((16, 16)));
        assert!(s.report(&b, &gb.lease_id, Ok(()), 0.08).unwrap());
        let tail = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((tail.batches.clone(), tail.committed), (6..8, 8));
        assert_eq!(s.status(&id).unwrap().leases_out, 2);
        // a learns it when it claims: its run now ends at 6, all of it committed.
        assert_eq!(s.extend(&a, &ga.lease_id).unwrap(), Some((6, 6)));
        // Nothing is left to give: a committed run is never taken.
        assert_eq!(s.lease(&b, Duration::from_millis(5)).await.unwrap(), None);
        // A report past the run's new end is not taken; one at its end is.
        assert!(!s.report_run(&a, &ga.lease_id, Ok(()), 0.06, Some(8)).unwrap());
        assert!(s.report_run(&a, &ga.lease_id, Ok(()), 0.06, Some(6)).unwrap());
        assert!(s.report(&b, &tail.lease_id, Ok(()), 0.02).unwrap());
        assert_eq!(
            s.pass_outcome(&id, Pass::Shoot, 0),
            PassOutcome::Ready(vec![0..4, 4..6, 6..8, 8..16]),
            "the outputs of what each computed: the cover of its run"
        );
        // The tail counts as b's work: b shot it.
        let state = s.lock();
        let shooters = &state.jobs[&id].shooting.shooters;
        assert_eq!(shooters[5].as_deref(), Some(a.as_str()));
        assert_eq!(shooters[6].as_deref(), Some(b.as_str()));
    }

    #[tokio::test]
    async fn a_claimed_run_is_kept_and_a_claim_on_a_lease_that_is_gone_is_refused() {
        let s = scheduler(60_000);
        let (id, a, b) = two_workers_and_a_pass(&s, Abilities::ALL).await;
        let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(s.extend(&a, &ga.lease_id).unwrap(), Some((8, 8)));
        assert_eq!(
            s.extend(&a, &ga.lease_id).unwrap(),
            Some((8, 8)),
            "claiming again changes nothing"
        );
        assert_eq!(s.extend(&b, &ga.lease_id).unwrap(), None, "another worker's lease");
        assert_eq!(s.extend(&a, "l999").unwrap(), None, "no such lease");
        assert!(s.extend("w99-nobody", &ga.lease_id).is_err(), "an unknown worker");
        // b takes its home; with a's run claimed, there is nothing to take from a.
        let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(gb.batches, 8..16);
        assert!(s.report(&b, &gb.lease_id, Ok(()), 0.08).unwrap());
        assert_eq!(s.lease(&b, Duration::from_millis(5)).await.unwrap(), None);
        s.cancel(&id).unwrap();
        assert_eq!(s.extend(&a, &ga.lease_id).unwrap(), None, "the job was cancelled");
    }

    #[tokio::test]
    async fn a_report_of_part_of_a_run_puts_the_rest_back() {
        let s = scheduler(60_000);
        let (id, a, b) = two_workers_and_a_pass(&s, Abilities::ALL).await;
        let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(ga.batches, 0..8);
        // a could not claim its tail (the coordinator did not answer): it reports 0..6.
        assert!(
            !s.report_run(&a, &ga.lease_id, Ok(()), 0.06, Some(0)).unwrap(),
            "an empty run"
        );
        assert!(s.report_run(&a, &ga.lease_id, Ok(()), 0.06, Some(6)).unwrap());
        assert_eq!(
            s.pass_outcome(&id, Pass::Shoot, 0),
            PassOutcome::Ready(vec![0..4, 4..6])
        );
        // The rest is pending again: b's home first, then what a left.
        let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(gb.batches, 8..16);
        let rest = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(rest.batches, 6..8);
    }

    #[tokio::test]
    async fn leases_of_workers_that_do_not_claim_are_committed_and_never_shared() {
        let s = scheduler(60_000);
        let (_, a, b) = two_workers_and_a_pass(&s, Abilities::RUNS).await;
        let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((ga.batches.clone(), ga.committed), (0..8, 8));
        let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert!(s.report(&b, &gb.lease_id, Ok(()), 0.08).unwrap());
        assert_eq!(s.lease(&b, Duration::from_millis(5)).await.unwrap(), None);
        // A worker of an earlier build, leased single blocks, takes no one's tail either.
        let s = scheduler(60_000);
        let (_, a, _) = two_workers_and_a_pass(&s, Abilities::ALL).await;
        let old = s.register("old", Abilities::BLOCKS);
        let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        assert!(ga.committed < ga.batches.end);
        while let Some(g) = s.lease(&old, Duration::ZERO).await.unwrap() {
            assert!(s.report(&old, &g.lease_id, Ok(()), 0.01).unwrap());
        }
        assert_eq!(
            s.extend(&a, &ga.lease_id).unwrap(),
            Some((ga.batches.end, ga.batches.end))
        );
        // And a lone worker's lease is committed whole: no one could take a part of it.
        let s = scheduler(60_000);
        let w = s.register("a", Abilities::ALL);
        let id = job_of_known_speed(&s, &w).await;
        s.start_pass(&id, 1, Pass::Shoot, 16, &[]);
        let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((g.batches.clone(), g.committed), (0..16, 16));
    }

    #[test]
    fn homes_split_the_pass_by_what_its_batches_cost() {
        let workers: HashMap<String, WorkerEntry> = ["w2-b", "w1-a", "w3-c"]
            .iter()
            .map(|id| {
                let number = id[1..2].parse().unwrap();
                let entry = WorkerEntry {
                    number,
                    last_seen: Instant::now(),
                    abilities: Abilities::ALL,
                };
                (id.to_string(), entry)
            })
            .collect();
        let two: HashMap<_, _> = workers
            .iter()
            .filter(|(id, _)| *id != "w3-c")
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        // Nothing measured: equal runs, in registration order (not the map's).
        assert_eq!(home("w1-a", &two, 16, &[]), 0..8);
        assert_eq!(home("w2-b", &two, 16, &[]), 8..16);
        assert_eq!(home("w1-a", &workers, 16, &[]), 0..5, "16/3 = 5.33, nearest 5");
        assert_eq!(home("w2-b", &workers, 16, &[]), 5..11);
        assert_eq!(home("w3-c", &workers, 16, &[]), 11..16);
        assert_eq!(home("w9-gone", &two, 16, &[]), 0..16);
        // The first half ten times cheaper: the first worker takes 12 batches.
        let costs: Vec<f64> = (0..16).map(|b| if b < 8 { 0.001 } else { 0.01 }).collect();
        assert_eq!(home("w1-a", &two, 16, &costs), 0..12);
        assert_eq!(home("w2-b", &two, 16, &costs), 12..16);
        // Unmeasured batches cost the mean of the measured ones.
        let partial = [0.0, 0.0, 0.0, 0.0, 3.0, 3.0, 3.0, 3.0];
        assert_eq!(home("w1-a", &two, 8, &partial), 0..4);
    }

    #[tokio::test]
    async fn a_worker_whose_batches_were_cheap_gets_more_of_the_next_pass() {
        let s = scheduler(60_000);
        let id = job(&s);
        let (a, b) = (s.register("a", Abilities::ALL), s.register("b", Abilities::ALL));
        let shoot = Pass::Shoot;
        // Iteration 1: batch by batch (speed unknown until a report, then blocks of 4); a's
        // half takes a tenth of the time of b's.
        s.start_pass(&id, 0, shoot, 16, &[]);
        let cost = |batches: &Range<usize>| batches.len() as f64 * if batches.start < 8 { 0.001 } else { 0.01 };
        while let Some(g) = s.lease(&a, Duration::ZERO).await.unwrap() {
            assert!(s.report(&a, &g.lease_id, Ok(()), cost(&g.batches)).unwrap());
            if let Some(g) = s.lease(&b, Duration::ZERO).await.unwrap() {
                assert!(s.report(&b, &g.lease_id, Ok(()), cost(&g.batches)).unwrap());
            }
        }
        s.end_pass(&id, 0, shoot);
        // Iteration 2: a's home is 0..12 and b's 12..16, each in one lease, b asking first.
        s.start_pass(&id, 1, shoot, 16, &[]);
        let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(gb.batches, 12..16);
        let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(ga.batches, 0..12);
    }

    #[tokio::test]
    async fn a_waiting_lease_is_served_when_a_pass_opens() {
        let s = scheduler(60_000);
        let id = job(&s);
        let w = s.register("a", Abilities::ALL);
        let waiter = {
            let (s, w) = (s.clone(), w.clone());
            tokio::spawn(async move { s.lease(&w, Duration::from_secs(30)).await })
        };
        tokio::time::sleep(Duration::from_millis(20)).await;
        s.start_pass(&id, 0, Pass::Shoot, 1, &[]);
        let grant = tokio::time::timeout(Duration::from_secs(5), waiter)
            .await
            .expect("woken")
            .unwrap()
            .unwrap();
        assert!(grant.is_some());
    }

    #[tokio::test]
    async fn repeated_failures_fail_the_job_and_cancel_withdraws_work() {
        let s = scheduler(60_000);
        let id = job(&s);
        s.start_pass(&id, 0, Pass::Shoot, 2, &[]);
        let w = s.register("a", Abilities::ALL);
        for attempt in 1..=MAX_BATCH_FAILURES {
            let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
            assert_eq!(g.batches, 0..1, "a failed block is handed out again first");
            assert!(s.report(&w, &g.lease_id, Err("disk full".into()), 0.01).unwrap());
            let outcome = s.pass_outcome(&id, Pass::Shoot, 0);
            if attempt < MAX_BATCH_FAILURES {
                assert_eq!(outcome, PassOutcome::Running);
            } else {
                assert!(matches!(outcome, PassOutcome::Failed(m) if m.contains("disk full")));
            }
        }
        assert_eq!(
            s.lease(&w, Duration::ZERO).await.unwrap(),
            None,
            "a failed job leases nothing"
        );

        let other = job(&s);
        s.start_pass(&other, 0, Pass::Shoot, 2, &[]);
        let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.job, other);
        s.cancel(&other).unwrap();
        assert_eq!(s.pass_outcome(&other, Pass::Shoot, 0), PassOutcome::Cancelled);
        assert!(
            !s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap(),
            "a cancelled job's lease is void"
        );
        assert_eq!(s.lease(&w, Duration::ZERO).await.unwrap(), None);
        assert!(matches!(s.cancel(&JobId::generate()), Err(Unknown::Job(_))));
    }

    #[tokio::test]
    async fn status_sequence_increases_with_every_change() {
        let s = scheduler(60_000);
        let id = job(&s);
        let mut rx = s.subscribe(&id).unwrap();
        let first = rx.borrow_and_update().seq;
        s.start_pass(&id, 0, Pass::Shoot, 1, &[]);
        let w = s.register("a", Abilities::ALL);
        let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap();
        let last = rx.borrow_and_update().clone();
        assert!(last.seq > first + 2, "{} after {first}", last.seq);
        assert_eq!(last.batches_done, 1);
        assert_eq!(last.batches_total, 3);
    }
}
