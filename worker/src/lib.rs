//! A VLF worker: registers with a coordinator, heartbeats, and loops over leases — each one
//! aligned block of batches of directions of one pass of one iteration of one job — computing the
//! block from the store with all its cores (rayon) and writing its output back into the store
//! before it reports.
//!
//! Stateless: everything a lease needs is in the store (the job's scene, options and the
//! checkpoint its iteration starts from); the geometry of the last jobs seen, and the mirror
//! maps this worker wrote into the next snapshot, are kept only as a cache (`vlf_store::Replica`:
//! a worker that shoots the same directions again reads them from memory, not the store). Any worker can take any lease, and scaling out is starting more of them, on any machine
//! that reaches the coordinator and the store. A worker outlives its coordinator: when calls fail
//! it retries with back-off and registers again with whoever answers.

pub mod cli;

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tonic::Code;
use vlf_core::propagate::reduce;
use vlf_proto::v1;
use vlf_proto::{ConnectError, Target, pass_from_wire};
use vlf_store::{FieldJob, JobId, Replica, Store, StoreError};

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

/// The geometry of the jobs seen last, most recent first.
struct Replicas {
    store: Option<(String, Store)>,
    jobs: Vec<(JobId, Replica)>,
    prototypes: Option<vlf_store::Prototypes>,
}

const CACHED_JOBS: usize = 2;

impl Replicas {
    fn store(&mut self, choice: &StoreChoice, server_url: &str) -> Result<Store, StoreError> {
        let url = match choice {
            StoreChoice::Handle(store) => return Ok(store.clone()),
            StoreChoice::Url(url) => url.as_str(),
            StoreChoice::FromServer => server_url,
        };
        if let Some((open, store)) = &self.store
            && open == url
        {
            return Ok(store.clone());
        }
        let store = Store::open_existing(url)?;
        self.store = Some((url.to_string(), store.clone()));
        self.jobs.clear();
        Ok(store)
    }

    fn replica(&mut self, store: &Store, job: &JobId) -> Result<&mut Replica, StoreError> {
        match self.jobs.iter().position(|(id, _)| id == job) {
            Some(i) => {
                let entry = self.jobs.remove(i);
                self.jobs.insert(0, entry);
            }
            None => {
                let opened = FieldJob::open(store, job)?;
                let replica = match self.prototypes.as_ref().and_then(|p| p.take(job)) {
                    Some(prop) => Replica::at_snapshot(opened, prop),
                    None => Replica::new(opened)?,
                };
                self.jobs.insert(0, (job.clone(), replica));
                self.jobs.truncate(CACHED_JOBS);
            }
        }
        Ok(&mut self.jobs[0].1)
    }
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
    let threads = config.threads.unwrap_or(0);
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| WorkerError::Threads(e.to_string()))?,
    );
    let replicas = Arc::new(Mutex::new(Replicas {
        store: None,
        jobs: Vec::new(),
        prototypes: config.prototypes.clone(),
    }));
    let mut stats = WorkerStats::default();
    let mut backoff = Duration::from_millis(50);
    'register: loop {
        let registered = tokio::select! {
            _ = &mut stop => return Ok(stats),
            r = workers.register(v1::RegisterRequest {
                name: config.name.clone(),
                threads: pool.current_num_threads() as u32,
                takes_runs: true,
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
        let outcome = lease_loop(
            &config,
            &mut workers,
            &id,
            &store,
            &pool,
            &replicas,
            &mut stats,
            &mut stop,
        )
        .await;
        heartbeat.abort();
        match outcome {
            Loop::Stop => return Ok(stats),
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
) -> Loop {
    // The next lease, when the last report brought it.
    let mut next: Option<v1::Lease> = None;
    loop {
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
        let result = compute(store, pool, replicas, &lease).await;
        let seconds = started.elapsed().as_secs_f64();
        tracing::debug!(
            lease = lease.lease_id,
            snapshot = lease.snapshot,
            pass = lease.pass_kind,
            copy = lease.pass_copy,
            batch = lease.batch,
            count = lease.batch_count,
            ms = format!("{:.1}", seconds * 1e3),
            "lease computed"
        );
        match &result {
            Ok(()) => {
                stats.batches += 1;
                stats.compute_seconds += seconds;
            }
            Err(e) => {
                stats.failed += 1;
                tracing::error!(job = lease.job_id, batch = lease.batch, "batch failed: {e}");
            }
        }
        let report = v1::ReportRequest {
            worker_id: id.to_string(),
            lease_id: lease.lease_id.clone(),
            error: result.err().unwrap_or_default(),
            seconds,
            next_wait_ms: LEASE_WAIT_MS,
        };
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

/// How long a lease request waits for work at the coordinator (a long poll).
const LEASE_WAIT_MS: u32 = 2000;

/// Computes a lease's batches into the store: the aligned blocks that cover them, in order.
async fn compute(
    store: &Store,
    pool: &Arc<rayon::ThreadPool>,
    replicas: &Arc<Mutex<Replicas>>,
    lease: &v1::Lease,
) -> Result<(), String> {
    let job = JobId::parse(&lease.job_id).map_err(|e| format!("lease names job `{}`: {e}", lease.job_id))?;
    let pass = pass_from_wire(lease.pass_kind, lease.pass_copy)
        .ok_or_else(|| format!("lease names pass ({}, {})", lease.pass_kind, lease.pass_copy))?;
    let (store, pool, replicas) = (store.clone(), pool.clone(), replicas.clone());
    let (k, b) = (lease.snapshot, lease.batch as usize);
    let run = b..b + (lease.batch_count as usize).max(1);
    vlf_store::blocking(move || {
        pool.install(|| -> Result<(), StoreError> {
            let mut replicas = lock(&replicas);
            let replica = replicas.replica(&store, &job)?;
            reduce::cover(run)
                .into_iter()
                .try_for_each(|block| replica.compute(k, pass, block))
        })
    })
    .await
    .map_err(|e| format!("internal: {e}"))?
    .map_err(|e| e.to_string())
}

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
