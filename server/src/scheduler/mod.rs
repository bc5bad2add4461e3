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
//! workers alive and the speed as they change. A pass of an iteration with several workers is
//! split into their homes, runs of equal measured cost (`home`), and a worker takes what is left
//! of its home in one lease (within the same lifetime bound), then helps the others a quarter at
//! a time.
//! A home lease commits all but its last quarter to a worker that claims ([`Abilities::claims`]);
//! the worker claims the tail when it gets there ([`Scheduler::extend`]), and a worker with nothing
//! left to do is given it meanwhile (`Scheduler::steal`): the workers even out at the end of
//! the pass what the cost split did not foresee.
//! The worker computes the run as the fewest aligned blocks that cover it (`reduce::cover`); a
//! worker that does not take runs (an earlier build) is leased single aligned blocks.
//! [`Scheduler::lease`] hands a run from the batch `PassRun::first_pending` picks (its home's
//! first, then the batches it shot last time) in
//! the first open pass of the oldest job, in shooting order (a rotated copy's shot before the
//! next copy's areas, which wait while it is about to open: `Pass::shooting_rank`), to a worker
//! for [`Timing::lease`]; the worker computes it, writes the outputs into the store and [`Scheduler::report`]s, which may take its next
//! lease along. A lease that is not reported in time (a dead or stalled worker) expires and its
//! batches are pending again; a worker that misses three heartbeats loses its leases at once. A
//! late report is still taken when its worker was heard from meanwhile and no other worker took
//! any of its batches since (`leases::revive_late`): a worker slower than the deadline gets its
//! blocks done, and the job learns its speed. Any other report on a lease that is gone (expired
//! and taken, job cancelled) is ignored: a block's output is a pure
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
//!
//! **Modules.** `mod.rs` holds the types and the state behind the lock, and the helpers every
//! part uses (who is alive, publishing a status); the `impl Scheduler` is split by who calls it:
//! - `jobs`: a job's life, as its driver and the job service drive it — adding it, its
//!   iterations and passes, what the driver finds when it wakes, its status, cancelling it;
//! - `workers`: workers registering and being heard from;
//! - `leases`: the workers' side of the work — leases cut, stolen, claimed, reported, expired;
//! - `pass`: an open pass's batches and how a lease is cut from them (plain data, pure functions);
//! - `usage`: how an iteration used its workers.

use std::collections::HashMap;
use std::ops::Range;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::{Notify, watch};
use vlf_core::propagate::Pass;
use vlf_proto::v1::{JobStatus, State as WireState};
use vlf_store::{JobId, Prototypes, Store, WorkTraffic};

mod jobs;
mod leases;
mod pass;
mod usage;
mod workers;

pub use pass::block_len;
use pass::{BatchState, PassRun, Shooting};
pub use usage::IterationUse;
use usage::UseClock;

/// A finished iteration, as the scheduler saw it ([`Scheduler::iterations`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct IterationRecord {
    /// From its start — the release of the one before, or for the first one driven here, its
    /// start — to the next one's, its snapshot's release (the commit overlaps the next
    /// iteration): the records of a job add up to its iterations' time.
    pub seconds: f64,
    /// What it moved through the store.
    pub traffic: WorkTraffic,
    /// How it used the workers.
    pub workers: IterationUse,
}

/// How long leases last and how often workers must be heard from.
#[derive(Clone, Copy, Debug)]
pub struct Timing {
    /// A lease's lifetime: a batch not reported by then goes to another worker (a late report is
    /// still taken if none took it meanwhile).
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
    /// It learns parts of a job's survey ([`Pass::Survey`]); a job is set up with the survey
    /// its workers learn only while one that can is alive.
    pub surveys: bool,
}

impl Abilities {
    /// This build's.
    pub const ALL: Abilities = Abilities {
        runs: true,
        claims: true,
        surveys: true,
    };
    /// A worker that computes runs but claims nothing (nor learns surveys).
    pub const RUNS: Abilities = Abilities {
        runs: true,
        claims: false,
        surveys: false,
    };
    /// A worker that computes single aligned blocks (of an iteration's passes only).
    pub const BLOCKS: Abilities = Abilities {
        runs: false,
        claims: false,
        surveys: false,
    };

    /// Whether a worker with these abilities may be leased `pass`.
    fn takes(self, pass: Pass) -> bool {
        pass != Pass::Survey || self.surveys
    }
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
    /// At most this many bytes of a job's subfields held by its coordinator (see
    /// [`vlf_core::psf::Subfields`]); `None`: all.
    subfield_budget: Option<usize>,
    state: Mutex<State>,
    /// Woken when batches become pending (a pass starts, a lease expires or fails).
    work_ready: Notify,
    /// This coordinator's mark in the lease and worker ids it gives (`w7.3fa0c1-host`,
    /// `l9.3fa0c1`): random, so that a restarted coordinator, whose counter starts again, never
    /// gives an id that a worker of the last one still holds (a lease id of the last one would
    /// otherwise name another worker's lease, and a report on it mark that worker's batches
    /// done before they are written).
    epoch: String,
}

struct State {
    jobs: HashMap<JobId, JobEntry>,
    workers: HashMap<String, WorkerEntry>,
    leases: HashMap<String, LeaseEntry>,
    /// Leases expired while their workers were still heard from, for a late report on one
    /// (`leases::revive_late`).
    expired: HashMap<String, LeaseEntry>,
    /// Source of job order, lease and worker ids.
    counter: u64,
}

/// A random mark for a new coordinator's ids (`Scheduler::epoch`): 24 bits of the process's hasher
/// seed and the clock.
fn new_epoch() -> String {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    format!("{:06x}", h.finish() & 0xff_ffff)
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
    /// When the last iteration ended (its snapshot released): the next one starts then, so
    /// that the iterations' durations add up to the run, what the driver does between the two
    /// included.
    released: Option<Instant>,
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
    /// The same of the job's survey ([`Pass::Survey`]), which costs another thing a batch.
    survey_batch_seconds: Option<f64>,
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

/// A batch whose leases expired unreported this many times fails its job: every worker that
/// takes it hangs on it or dies of it (runs out of memory, say), or one batch takes longer than
/// the lease, and without a limit it would be leased again for ever. Far more than a worker
/// slower than the lease meets: its late report is still taken when no other worker took its
/// batches meanwhile (`leases::revive_late`), and an idle worker relieves it at the first
/// expiry.
pub const MAX_BATCH_EXPIRIES: u32 = 10;

/// Expired leases kept for their workers' late reports ([`Scheduler::reap`]), the oldest let go
/// first: a few per worker of a large cluster.
pub const MAX_EXPIRED_KEPT: usize = 1024;

impl Scheduler {
    /// A scheduler over `store`; with `prototypes`, every job's propagation is offered there to
    /// workers of this process (see [`Prototypes`]); with `subfield_budget`, a job's
    /// propagation holds at most that many bytes of subfields.
    pub fn new(
        store: Store,
        timing: Timing,
        prototypes: Option<Prototypes>,
        subfield_budget: Option<usize>,
    ) -> Arc<Scheduler> {
        Arc::new(Scheduler {
            store,
            timing,
            prototypes,
            subfield_budget,
            state: Mutex::new(State {
                jobs: HashMap::new(),
                workers: HashMap::new(),
                leases: HashMap::new(),
                expired: HashMap::new(),
                counter: 0,
            }),
            work_ready: Notify::new(),
            epoch: new_epoch(),
        })
    }

    pub fn store(&self) -> &Store {
        &self.store
    }

    pub fn prototypes(&self) -> Option<&Prototypes> {
        self.prototypes.as_ref()
    }

    /// The subfield budget of the jobs' propagations held here, if any.
    pub fn subfield_budget(&self) -> Option<usize> {
        self.subfield_budget
    }

    pub fn timing(&self) -> Timing {
        self.timing
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock leaves plain data that every operation re-checks.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
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

/// Workers heard from within three heartbeats that learn survey parts.
fn alive_surveyors(state: &State, timing: Timing) -> u32 {
    let now = Instant::now();
    (state.workers.values())
        .filter(|w| w.abilities.surveys && now.duration_since(w.last_seen) <= timing.heartbeat * 3)
        .count() as u32
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
        // While the job is set up (iteration 0, its survey leased) no iteration's time is known.
        if status.iterations_planned > 0 && status.iteration > 0 && status.eta_iteration_seconds >= 0.0 {
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

#[cfg(test)]
mod tests;
