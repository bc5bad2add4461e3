//! A VLF worker: registers with a coordinator, heartbeats, and loops over leases — each a run of
//! batches of directions of one pass of one iteration of one job, or of the job's survey before
//! its first iteration (`compute_survey`) — computing the run from the
//! store with all its cores (rayon), one aligned block at a time, and writing its outputs back
//! into the store before it reports. A lease may leave its last batches uncommitted: the worker
//! claims them when it gets there (`Claim`), and if the coordinator has given them to an idle
//! worker meanwhile, its run ends where the claim's answer says.
//!
//! Stateless: everything a lease needs is in the store (the job's scene, options and the
//! checkpoint its iteration starts from); the geometry of the last jobs seen, and the mirror
//! maps this worker wrote into the next snapshot, are kept only as a cache (`vlf_store::Replica`:
//! a worker that shoots the same directions again reads them from memory, not the store). Any worker can take any lease, and scaling out is starting more of them, on any machine
//! that reaches the coordinator and the store. A worker outlives its coordinator: when calls fail
//! it retries with back-off and registers again with whoever answers.

mod claim;
pub mod cli;
mod compute;
mod replicas;
mod report;

use claim::{Claim, claimer};
use compute::compute;
use replicas::Replicas;
use report::{report_request, report_when_written, written_or_error};

use std::ops::Range;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use tonic::Code;
use vlf_core::propagate::{Pass, Surveyor, reduce};
use vlf_proto::v1;
use vlf_proto::{ConnectError, Target, pass_blocks_from_wire, pass_from_wire};
use vlf_store::{FieldJob, JobId, ReadAhead, Replica, ReplicaPhases, Store, StoreError, Writing};

/// Where the worker finds the store.
#[derive(Clone, Debug)]
pub enum StoreChoice {
    /// The URL the coordinator gives at registration.
    FromServer,
    /// Another URL for the same store (the worker reaches it by another path).
    Url(String),
    /// An open store (in-process workers sharing a `memory://` store).
    Handle(Store),
}

/// A worker's settings.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    pub target: Target,
    /// For the coordinator's logs.
    pub name: String,
    /// Compute threads (default: all cores).
    pub threads: Option<usize>,
    pub store: StoreChoice,
    /// Test hook: after this many leases, take one more and stall for ever (never report), as a
    /// hung machine would.
    pub hang_after: Option<u64>,
    /// Propagations offered by a coordinator in this process: cloned instead of built.
    pub prototypes: Option<vlf_store::Prototypes>,
    /// At most this many bytes of a job's subfields held ([`Replica::within`]): the worker
    /// keeps those of its home's directions rather than the whole field's. `None`: no bound (all
    /// held, or with the job's survey stored those of the directions it shoots, built on demand);
    /// it then also keeps a rotated copy's subfields from its areas to its shot, at most `l`.
    /// (A prototype from a coordinator in this process comes with the coordinator's.)
    pub subfield_budget: Option<usize>,
}

/// Why a worker stopped.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    #[error(transparent)]
    Connect(#[from] ConnectError),
    #[error("the coordinator refused this worker: {0}")]
    Refused(tonic::Status),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("cannot start the compute threads: {0}")]
    Threads(String),
}

/// What a worker did.
#[derive(Clone, Copy, Debug, Default)]
pub struct WorkerStats {
    /// Leases computed.
    pub batches: u64,
    pub failed: u64,
    pub compute_seconds: f64,
}

/// Whether a failed call is worth retrying (the coordinator is restarting, the network blinked).
fn transient(status: &tonic::Status) -> bool {
    matches!(
        status.code(),
        Code::Unavailable | Code::Unknown | Code::Cancelled | Code::DeadlineExceeded | Code::Internal | Code::Aborted
    )
}

/// Runs until `stop` resolves or the coordinator refuses the worker.
pub async fn run(
    config: WorkerConfig,
    stop: impl std::future::Future<Output = ()>,
) -> Result<WorkerStats, WorkerError> {
    tokio::pin!(stop);
    let clients = config.target.connect_lazy()?;
    let mut workers = clients.workers;
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads.unwrap_or(0))
            .build()
            .map_err(|e| WorkerError::Threads(e.to_string()))?,
    );
    let replicas = Arc::new(Mutex::new(Replicas::new(
        config.prototypes.clone(),
        config.subfield_budget,
    )));
    let mut stats = WorkerStats::default();
    let mut backoff = Duration::from_millis(50);
    'register: loop {
        let registered = tokio::select! {
            _ = &mut stop => return Ok(stats),
            r = workers.register(v1::RegisterRequest {
                name: config.name.clone(),
                threads: pool.current_num_threads() as u32,
                takes_runs: true,
                takes_claims: true,
                takes_surveys: true,
            }) => r,
        };
        let reply = match registered {
            Ok(r) => r.into_inner(),
            Err(status) if transient(&status) => {
                tracing::debug!("coordinator not reachable ({}); retrying", status.message());
                tokio::select! {
                    _ = &mut stop => return Ok(stats),
                    _ = tokio::time::sleep(backoff) => {}
                }
                backoff = (backoff * 2).min(Duration::from_secs(2));
                continue;
            }
            Err(status) => return Err(WorkerError::Refused(status)),
        };
        backoff = Duration::from_millis(50);
        let id = reply.worker_id;
        tracing::info!(worker = id, store = reply.store_url, "registered");
        let store = {
            let (replicas, choice, url) = (replicas.clone(), config.store.clone(), reply.store_url.clone());
            vlf_store::blocking(move || lock(&replicas).store(&choice, &url))
                .await
                .map_err(|e| WorkerError::Threads(e.to_string()))??
        };
        let heartbeat = spawn_heartbeat(
            workers.clone(),
            id.clone(),
            Duration::from_millis(u64::from(reply.heartbeat_ms.max(10))),
        );
        let mut reports = tokio::task::JoinSet::new();
        let outcome = lease_loop(
            &config,
            &mut workers,
            &id,
            &store,
            &pool,
            &replicas,
            &mut stats,
            &mut stop,
            &mut reports,
        )
        .await;
        heartbeat.abort();
        match outcome {
            Loop::Stop => {
                // Reports still waiting for their outputs' writes go out first, rather than
                // leave the leases computed to expire.
                let sent = async { while reports.join_next().await.is_some() {} };
                if tokio::time::timeout(REPORTS_AT_STOP, sent).await.is_err() {
                    tracing::warn!("stopping with reports unsent: their leases will expire");
                }
                return Ok(stats);
            }
            Loop::Refused(status) => return Err(WorkerError::Refused(status)),
            Loop::Register => continue 'register,
        }
    }
}

enum Loop {
    Stop,
    Register,
    Refused(tonic::Status),
}

/// How long a stopping worker waits for its reports still on their way.
const REPORTS_AT_STOP: Duration = Duration::from_secs(5);

/// Leases, computes and reports until told to stop or the coordinator is lost; reports sent in
/// the background go into `reports`.
#[allow(clippy::too_many_arguments)]
async fn lease_loop(
    config: &WorkerConfig,
    workers: &mut v1::workers_client::WorkersClient<vlf_proto::Authed>,
    id: &str,
    store: &Store,
    pool: &Arc<rayon::ThreadPool>,
    replicas: &Arc<Mutex<Replicas>>,
    stats: &mut WorkerStats,
    stop: &mut std::pin::Pin<&mut impl std::future::Future<Output = ()>>,
    reports: &mut tokio::task::JoinSet<()>,
) -> Loop {
    // The next lease, when the last report brought it.
    let mut next: Option<v1::Lease> = None;
    // Mirror-map parts being read ahead of the next iteration.
    let mut ahead: Option<Ahead> = None;
    loop {
        // Reports sent in the background since: forget them.
        while reports.try_join_next().is_some() {}
        let lease = match next.take() {
            Some(lease) => lease,
            None => {
                let leased = tokio::select! {
                    _ = stop.as_mut() => return Loop::Stop,
                    r = workers.lease(v1::LeaseRequest { worker_id: id.to_string(), wait_ms: LEASE_WAIT_MS }) => r,
                };
                match leased {
                    Ok(reply) => match reply.into_inner().lease {
                        Some(lease) => lease,
                        None => continue,
                    },
                    Err(status) if status.code() == Code::NotFound || transient(&status) => {
                        tracing::info!("lost the coordinator ({}); registering again", status.message());
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        return Loop::Register;
                    }
                    Err(status) => return Loop::Refused(status),
                }
            }
        };
        if config.hang_after.is_some_and(|n| stats.batches >= n) {
            tracing::warn!(lease = lease.lease_id, "test hook: stalling with a lease");
            println!("stalled holding lease {}", lease.lease_id);
            stop.as_mut().await;
            return Loop::Stop;
        }
        let started = Instant::now();
        let read_ahead = Ahead::for_lease(&mut ahead, &lease).await;
        let computed = compute(store, pool, replicas, &lease, read_ahead, workers, id).await;
        if let Ok((_, _, costs, _, phases)) = &computed {
            // The lease's wall time against its batches' computing, and the replica's phases:
            // what the lease spent outside its batches (moving on to the iteration, reading
            // maps, serialising outputs) shows as the difference.
            tracing::debug!(
                lease = lease.lease_id,
                snapshot = lease.snapshot,
                pass = lease.pass_kind,
                copy = lease.pass_copy,
                batch = lease.batch,
                count = lease.batch_count,
                wall_ms = format!("{:.1}", started.elapsed().as_secs_f64() * 1e3),
                batches_ms = format!("{:.1}", costs.iter().sum::<f64>() * 1e3),
                start_ms = format!("{:.1}", phases.start * 1e3),
                map_reads_ms = format!("{:.1}", phases.map_reads * 1e3),
                prerequisites_ms = format!("{:.1}", phases.prerequisites * 1e3),
                compute_ms = format!("{:.1}", phases.compute * 1e3),
                encode_ms = format!("{:.1}", phases.encode * 1e3),
                outputs_ms = format!("{:.1}", phases.outputs * 1e3),
                "lease run"
            );
        }
        // The outputs are on their way into the store. A local store has them in at once: the
        // report goes now and brings the next lease. One a round trip away is still writing:
        // the report goes once they are in, in the background, and the next lease is computed
        // meanwhile (a perturbed iteration's eight passes each paid a round trip otherwise).
        // What the report says the lease took is its computing alone, batch by batch, without
        // the waits for the store (`Replica::batch_costs`); a failed lease reports the time
        // until it failed.
        let (result, costs) = match computed {
            Ok((run, writes, costs, next_ahead, _)) => {
                if let Some(next_ahead) = next_ahead {
                    ahead = Some(Ahead::start(&lease.job_id, next_ahead, pool));
                }
                let mut writes = tokio::spawn(writes.finished());
                match tokio::time::timeout(WRITE_OVERLAP, &mut writes).await {
                    Ok(written) => (written_or_error(written).map(|()| run), costs),
                    Err(_) => {
                        stats.batches += 1;
                        stats.compute_seconds += costs.iter().sum::<f64>();
                        report_when_written(reports, workers.clone(), id, &lease, run, costs, writes);
                        continue;
                    }
                }
            }
            Err(e) => (Err(e), vec![started.elapsed().as_secs_f64()]),
        };
        let seconds: f64 = costs.iter().sum();
        match &result {
            Ok(_) => {
                stats.batches += 1;
                stats.compute_seconds += seconds;
            }
            Err(e) => {
                stats.failed += 1;
                let ms = format!("{:.1}", seconds * 1e3);
                tracing::error!(job = lease.job_id, batch = lease.batch, ms, "batch failed: {e}");
            }
        }
        let report = report_request(id, &lease.lease_id, result, costs, LEASE_WAIT_MS);
        // The report also asks for the next lease (one round trip instead of two); stopping
        // meanwhile is fine: an unanswered report only lets the lease expire.
        let reported = tokio::select! {
            _ = stop.as_mut() => return Loop::Stop,
            r = workers.report(report) => r,
        };
        match reported {
            Ok(reply) => {
                let reply = reply.into_inner();
                if !reply.accepted {
                    tracing::debug!(lease = lease.lease_id, "report ignored (lease expired or job ended)");
                }
                next = reply.next;
            }
            Err(status) if status.code() == Code::NotFound || transient(&status) => return Loop::Register,
            Err(status) => return Loop::Refused(status),
        }
    }
}

/// Mirror-map parts of the next snapshot being read while the worker waits for the iteration to
/// be released (see [`ReadAhead`]): on the worker's own threads, idle by then.
struct Ahead {
    job: String,
    snapshot: u32,
    reading: tokio::task::JoinHandle<Result<ReadAhead, vlf_store::Panicked>>,
}

impl Ahead {
    /// Starts reading `ahead`, of job `job`.
    fn start(job: &str, ahead: ReadAhead, pool: &Arc<rayon::ThreadPool>) -> Ahead {
        let pool = pool.clone();
        Ahead {
            job: job.to_string(),
            snapshot: ahead.snapshot(),
            reading: tokio::spawn(vlf_store::blocking(move || pool.install(|| ahead.fetch()))),
        }
    }

    /// What was read ahead of `lease`'s iteration, once read; `None` if nothing was. Parts of a
    /// later iteration of the same job are kept for it; any other are dropped.
    async fn for_lease(ahead: &mut Option<Ahead>, lease: &v1::Lease) -> Option<ReadAhead> {
        let reading = ahead.take()?;
        if reading.job != lease.job_id || reading.snapshot < lease.snapshot {
            return None;
        }
        if reading.snapshot > lease.snapshot {
            *ahead = Some(reading);
            return None;
        }
        let read = reading.reading.await.ok()?.ok()?;
        tracing::debug!(
            snapshot = read.snapshot(),
            parts = read.fetched(),
            "mirror maps read ahead"
        );
        Some(read)
    }
}

/// How long a lease request waits for work at the coordinator (a long poll).
const LEASE_WAIT_MS: u32 = 2000;

/// How long a worker waits for a lease's outputs to be in the store before it reports the lease
/// in the background and goes on: longer than a local store takes, shorter than a round trip to
/// an object store.
const WRITE_OVERLAP: Duration = Duration::from_millis(2);

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Heartbeats every `interval` until aborted.
fn spawn_heartbeat(
    mut workers: v1::workers_client::WorkersClient<vlf_proto::Authed>,
    id: String,
    interval: Duration,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(interval);
        loop {
            tick.tick().await;
            if let Err(status) = workers.heartbeat(v1::HeartbeatRequest { worker_id: id.clone() }).await {
                tracing::debug!("heartbeat failed: {}", status.message());
            }
        }
    })
}
