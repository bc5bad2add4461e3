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

pub mod cli;

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

/// The geometry of the jobs seen last, most recent first.
struct Replicas {
    store: Option<(String, Store)>,
    jobs: Vec<(JobId, Replica)>,
    /// The job whose survey this worker was leased last, and what learns its parts: kept from
    /// one survey lease to the next (its atlas built once), dropped once the job's iterations
    /// come (a replica of the job is opened).
    surveying: Option<(JobId, FieldJob, Surveyor)>,
    prototypes: Option<vlf_store::Prototypes>,
    subfield_budget: Option<usize>,
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
        self.surveying = None;
        Ok(store)
    }

    /// The job `job`, not set up yet, and what learns its survey's parts within the worker's
    /// budget: the ones kept from the last survey lease if they are this job's.
    fn surveyor(&mut self, store: &Store, job: &JobId) -> Result<(&FieldJob, &Surveyor), StoreError> {
        if self.surveying.as_ref().is_none_or(|(id, _, _)| id != job) {
            self.surveying = None;
            let started = Instant::now();
            let opened = FieldJob::open(store, job)?;
            // It keeps the atlas from lease to lease, and a part's subfields (within the budget)
            // until the part is learnt: none without mirrors, where a part reads each once.
            let surveyor = Surveyor::new(opened.scene(), opened.options(), self.subfield_budget).map_err(|source| {
                StoreError::Field {
                    url: store.url().to_string(),
                    job: job.to_string(),
                    source,
                }
            })?;
            tracing::info!(
                job = %job,
                setup_s = format!("{:.2}", started.elapsed().as_secs_f64()),
                "survey geometry built"
            );
            self.surveying = Some((job.clone(), opened, surveyor));
        }
        match &self.surveying {
            Some((_, job, surveyor)) => Ok((job, surveyor)),
            None => unreachable!("set above"),
        }
    }

    fn replica(&mut self, store: &Store, job: &JobId) -> Result<&mut Replica, StoreError> {
        match self.jobs.iter().position(|(id, _)| id == job) {
            Some(i) => {
                let entry = self.jobs.remove(i);
                self.jobs.insert(0, entry);
            }
            None => {
                // The job's iterations have come: its survey is over.
                if self.surveying.as_ref().is_some_and(|(id, _, _)| id == job) {
                    self.surveying = None;
                }
                let opened = FieldJob::open(store, job)?;
                let taking = Instant::now();
                let replica = match self.prototypes.as_ref().and_then(|p| p.take(job)) {
                    Some(prop) => {
                        // A copy of the coordinator's propagation (or the original, for the
                        // last worker to take it), with its routes turned around: logged too.
                        let replica = Replica::at_snapshot(opened, prop);
                        tracing::info!(
                            job = %job,
                            setup_s = format!("{:.2}", taking.elapsed().as_secs_f64()),
                            "job geometry taken from this process's coordinator"
                        );
                        replica
                    }
                    None => {
                        // Every worker process builds the job's geometry for itself: the texel
                        // grids and directions; the subfields of what it shoots, as it shoots
                        // them (the discrete areas are the job's, stored with it); with mirrors,
                        // the mirror planes rasterised alone in every direction (their views) and
                        // the reflection routes. Time that more workers do not shorten
                        // (docs/scaling.md), so it is logged.
                        let started = Instant::now();
                        let replica = Replica::within(opened, self.subfield_budget)?;
                        tracing::info!(
                            job = %job,
                            setup_s = format!("{:.2}", started.elapsed().as_secs_f64()),
                            "job geometry built"
                        );
                        replica
                    }
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
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads.unwrap_or(0))
            .build()
            .map_err(|e| WorkerError::Threads(e.to_string()))?,
    );
    let replicas = Arc::new(Mutex::new(Replicas {
        store: None,
        jobs: Vec::new(),
        surveying: None,
        prototypes: config.prototypes.clone(),
        subfield_budget: config.subfield_budget,
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

/// The report of a lease: computed up to the end of the run at `costs` per batch, or failed;
/// asking for the next lease with a wait of `next_wait_ms` (0: not asking).
fn report_request(
    worker_id: &str,
    lease_id: &str,
    outcome: Result<Range<usize>, String>,
    costs: Vec<f64>,
    next_wait_ms: u32,
) -> v1::ReportRequest {
    let seconds = costs.iter().sum();
    let (batch_end, error, batch_seconds) = match outcome {
        Ok(run) => (run.end as u32, String::new(), costs),
        Err(e) => (0, e, Vec::new()),
    };
    v1::ReportRequest {
        worker_id: worker_id.to_string(),
        lease_id: lease_id.to_string(),
        error,
        seconds,
        next_wait_ms,
        batch_end,
        batch_seconds,
    }
}

/// What writing a lease's outputs came to, as a report's error.
fn written_or_error(written: Result<Result<(), StoreError>, tokio::task::JoinError>) -> Result<(), String> {
    match written {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(e.to_string()),
        Err(e) => Err(format!("internal: {e}")),
    }
}

/// Reports `lease`, computed up to the end of `run` at `costs` per batch, once `writes` are done (an
/// error if they failed), without asking for the next lease: the worker has asked for it already.
/// A report that does not arrive only lets the lease expire.
fn report_when_written(
    reports: &mut tokio::task::JoinSet<()>,
    mut workers: v1::workers_client::WorkersClient<vlf_proto::Authed>,
    worker_id: &str,
    lease: &v1::Lease,
    run: Range<usize>,
    costs: Vec<f64>,
    writes: tokio::task::JoinHandle<Result<(), StoreError>>,
) {
    let (worker_id, lease_id) = (worker_id.to_string(), lease.lease_id.clone());
    reports.spawn(async move {
        let written = written_or_error(writes.await).map(|()| run);
        if let Err(e) = &written {
            tracing::error!(lease = lease_id, "writing the outputs failed: {e}");
        }
        let report = report_request(&worker_id, &lease_id, written, costs, 0);
        match workers.report(report).await {
            Ok(reply) if !reply.get_ref().accepted => {
                tracing::debug!(lease = lease_id, "report ignored (lease expired or job ended)")
            }
            Ok(_) => {}
            Err(status) => tracing::debug!(lease = lease_id, "report failed: {}", status.message()),
        }
    });
}

/// A lease computed: its run, the writes of its outputs, what each batch cost, what to read
/// ahead of the next iteration, and where the replica spent the wall time.
type Computed = (Range<usize>, Writing, Vec<f64>, Option<ReadAhead>, ReplicaPhases);

/// Computes a lease's batches into the store, left to right, one aligned block at a time; the
/// outputs are those of the fewest aligned blocks that cover what was computed. Batches past the
/// lease's committed part are claimed first (`Claim`). Returns the run computed: the lease's,
/// ending earlier when the coordinator gave its tail to another worker.
async fn compute(
    store: &Store,
    pool: &Arc<rayon::ThreadPool>,
    replicas: &Arc<Mutex<Replicas>>,
    lease: &v1::Lease,
    ahead: Option<ReadAhead>,
    workers: &v1::workers_client::WorkersClient<vlf_proto::Authed>,
    worker_id: &str,
) -> Result<Computed, String> {
    let job = JobId::parse(&lease.job_id).map_err(|e| format!("lease names job `{}`: {e}", lease.job_id))?;
    let pass = pass_from_wire(lease.pass_kind, lease.pass_copy)
        .ok_or_else(|| format!("lease names pass ({}, {})", lease.pass_kind, lease.pass_copy))?;
    let reads = (lease.reads.iter())
        .map(pass_blocks_from_wire)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("lease names {e}"))?;
    let (store, pool, replicas) = (store.clone(), pool.clone(), replicas.clone());
    let (k, start) = (lease.snapshot, lease.batch as usize);
    let end = start + (lease.batch_count as usize).max(1);
    let committed = match lease.committed_count {
        0 => end,
        n => (start + n as usize).min(end),
    };
    if pass == Pass::Survey {
        return compute_survey(store, pool, replicas, job, start..committed).await;
    }
    let claim = Arc::new(Claim::new(committed, end));
    // The computing thread holds the only sender: the claimer stops when it is done.
    let (asks, asked) = tokio::sync::mpsc::unbounded_channel();
    let claimer = claimer(
        workers.clone(),
        worker_id.to_string(),
        lease.lease_id.clone(),
        claim.clone(),
        asked,
    );
    let computing = vlf_store::blocking(move || {
        pool.install(|| -> Result<Computed, StoreError> {
            let mut replicas = lock(&replicas);
            let replica = replicas.replica(&store, &job)?;
            for (earlier, blocks) in reads {
                replica.absorbed(k, earlier, blocks);
            }
            if let Some(ahead) = ahead {
                replica.adopt_ahead(ahead);
            }
            let (run, writes) = replica.compute_run_behind(k, pass, start, |done| claim.next_block(done, &asks))?;
            let costs = replica.batch_costs().to_vec();
            Ok((run, writes, costs, replica.read_ahead(k, pass), replica.phase_seconds()))
        })
    });
    let (computed, ()) = tokio::join!(computing, claimer);
    computed
        .map_err(|e| format!("internal: {e}"))?
        .map_err(|e| e.to_string())
}

/// Learns the survey parts of the batches `run` of `job` (not set up yet: no [`Replica`] can be
/// opened) into the store, one per aligned block of the run (`reduce::cover`), with the
/// [`Surveyor`] the worker keeps for the job (its atlas built at the first survey lease), the
/// subfields held within the worker's budget. A survey lease is committed whole; were it not, the
/// run computed is the committed part, and the report says so (the rest goes back to the pool).
async fn compute_survey(
    store: Store,
    pool: Arc<rayon::ThreadPool>,
    replicas: Arc<Mutex<Replicas>>,
    job: JobId,
    run: Range<usize>,
) -> Result<Computed, String> {
    let computing = vlf_store::blocking(move || {
        pool.install(|| -> Result<Computed, StoreError> {
            let mut replicas = lock(&replicas);
            let (opened, surveyor) = replicas.surveyor(&store, &job)?;
            let batching = opened.options().batching();
            let (mut writes, mut costs) = (Vec::new(), Vec::new());
            for block in reduce::cover(run.clone()) {
                let started = Instant::now();
                let part =
                    (surveyor.part(batching.directions_of(block.clone()))).map_err(|source| StoreError::Field {
                        url: store.url().to_string(),
                        job: job.to_string(),
                        source,
                    })?;
                // Written while the next block is learnt, its bytes dropped once written, rather
                // than every part of the lease held until its end (with mirror planes, a curved
                // mirror's parts are tens of kB a direction); a store slower than the learning
                // still holds them meanwhile. Should a later block fail, the parts already on
                // their way land unreported: harmless, as a part is a pure function of the job
                // and its block, written create-only, and one the coordinator finds stored is
                // one it need not lease again.
                let put = opened.survey_part_put(block.clone(), &part)?;
                drop(part);
                writes.push(store.put_all_behind(vec![put])?);
                let each = started.elapsed().as_secs_f64() / block.len() as f64;
                costs.extend(std::iter::repeat_n(each, block.len()));
            }
            tracing::debug!(job = %job, batches = ?run, "survey parts learnt");
            Ok((
                run,
                Writing::all(&store, writes)?,
                costs,
                None,
                ReplicaPhases::default(),
            ))
        })
    });
    computing
        .await
        .map_err(|e| format!("internal: {e}"))?
        .map_err(|e| e.to_string())
}

/// What a worker may compute of its lease: the batches before `committed` are its own; those
/// from there to `end` it claims with `Extend` as it goes, and meanwhile the coordinator may
/// give them to a worker with nothing to do (the reply then says where the run ends). The
/// computing thread asks for more as it starts the last committed batch, so the answer comes
/// while it computes: a claim costs no waiting.
struct Claim {
    state: Mutex<ClaimState>,
    changed: Condvar,
}

struct ClaimState {
    committed: usize,
    end: usize,
    /// An `Extend` is on its way.
    asking: bool,
}

impl Claim {
    fn new(committed: usize, end: usize) -> Claim {
        let state = ClaimState {
            committed,
            end,
            asking: false,
        };
        Claim {
            state: Mutex::new(state),
            changed: Condvar::new(),
        }
    }

    /// The block to compute from batch `done` on, waiting for a claim if need be; `None` when
    /// the run ends there. Blocks are the aligned pieces of the committed part, its last batch
    /// alone while more is to be claimed (the claim is asked as it starts).
    fn next_block(&self, done: usize, asks: &Asks) -> Option<Range<usize>> {
        let mut state = lock(&self.state);
        loop {
            if state.end <= done {
                return None;
            }
            if state.committed > done {
                break;
            }
            ask(&mut state, asks);
            state = self.changed.wait(state).unwrap_or_else(|p| p.into_inner());
        }
        let (committed, end) = (state.committed, state.end);
        let upto = if committed < end && committed - done > 1 {
            committed - 1
        } else {
            committed
        };
        let block = reduce::cover(done..upto).first()?.clone();
        if block.end == committed {
            ask(&mut state, asks);
        }
        Some(block)
    }
}

/// Where the computing thread asks the claimer for more of the lease.
type Asks = tokio::sync::mpsc::UnboundedSender<()>;

fn ask(state: &mut ClaimState, asks: &Asks) {
    if state.asking || state.committed >= state.end {
        return;
    }
    state.asking = true;
    if asks.send(()).is_err() {
        // No one to ask: keep what is committed.
        state.end = state.committed;
        state.asking = false;
    }
}

/// Answers the computing thread's asks with `Extend` calls until it is done. A lease that is
/// gone, or a coordinator that does not answer (after a few tries), ends the run at what is
/// committed: the report then says so, and the rest goes back to the pool.
async fn claimer(
    mut workers: v1::workers_client::WorkersClient<vlf_proto::Authed>,
    worker_id: String,
    lease_id: String,
    claim: Arc<Claim>,
    mut asks: tokio::sync::mpsc::UnboundedReceiver<()>,
) {
    while asks.recv().await.is_some() {
        let mut reply = None;
        for attempt in 0..3 {
            let request = v1::ExtendRequest {
                worker_id: worker_id.clone(),
                lease_id: lease_id.clone(),
            };
            match workers.extend(request).await {
                Ok(r) => {
                    reply = Some(r.into_inner());
                    break;
                }
                Err(status) if transient(&status) && attempt < 2 => {
                    tokio::time::sleep(Duration::from_millis(50 << attempt)).await;
                }
                Err(status) => {
                    tracing::debug!(lease = lease_id, "cannot claim more of the lease: {}", status.message());
                    break;
                }
            }
        }
        let mut state = lock(&claim.state);
        let (committed, end) = (state.committed, state.end);
        match reply.map(|r| (r.committed_end as usize, r.end as usize)) {
            // The coordinator never takes back what is committed, nor lengthens a run.
            Some((c, e)) if committed <= c && c <= e && e <= end => {
                state.committed = c;
                state.end = e;
            }
            Some((c, e)) => {
                tracing::warn!(
                    lease = lease_id,
                    "Extend answered {c}..{e} for a lease committed to {committed} of {end}; stopping there"
                );
                state.end = committed;
            }
            None => state.end = committed,
        }
        state.asking = false;
        claim.changed.notify_all();
    }
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

#[cfg(test)]
// Blocks of one range are what these tests mean.
#[allow(clippy::single_range_in_vec_init)]
mod tests {
    use super::*;

    /// The blocks `claim` hands out from `start` until it says stop (or `limit` blocks).
    fn blocks(claim: &Claim, start: usize, asks: &Asks, limit: usize) -> Vec<Range<usize>> {
        let mut out = Vec::new();
        let mut done = start;
        while let Some(block) = claim.next_block(done, asks) {
            done = block.end;
            out.push(block);
            if out.len() == limit {
                break;
            }
        }
        out
    }

    fn answer(claim: &Claim, committed: usize, end: usize) {
        let mut state = lock(&claim.state);
        (state.committed, state.end, state.asking) = (committed, end, false);
        claim.changed.notify_all();
    }

    #[test]
    fn a_committed_run_is_its_cover_and_asks_nothing() {
        let claim = Claim::new(16, 16);
        let (asks, mut asked) = tokio::sync::mpsc::unbounded_channel();
        assert_eq!(blocks(&claim, 1, &asks, 99), [1..2, 2..4, 4..8, 8..16]);
        assert!(asked.try_recv().is_err());
    }

    #[test]
    fn the_tail_is_claimed_while_the_last_committed_batch_is_computed() {
        let claim = Claim::new(6, 8);
        let (asks, mut asked) = tokio::sync::mpsc::unbounded_channel();
        // The committed part, its last batch alone: the claim goes out as it is handed out.
        assert_eq!(blocks(&claim, 0, &asks, 2), [0..4, 4..5]);
        assert!(asked.try_recv().is_err(), "not yet");
        assert_eq!(blocks(&claim, 5, &asks, 1), [5..6]);
        assert!(asked.try_recv().is_ok());
        // Granted: the rest in one block, and the run ends there.
        answer(&claim, 8, 8);
        assert_eq!(blocks(&claim, 6, &asks, 99), [6..8]);
        assert!(asked.try_recv().is_err(), "one claim");
    }

    #[test]
    fn a_tail_given_to_another_worker_ends_the_run() {
        let claim = Claim::new(6, 8);
        let (asks, _asked) = tokio::sync::mpsc::unbounded_channel();
        assert_eq!(blocks(&claim, 0, &asks, 3), [0..4, 4..5, 5..6]);
        answer(&claim, 6, 6);
        assert_eq!(claim.next_block(6, &asks), None);
    }

    #[test]
    fn a_worker_that_reaches_its_claim_waits_for_the_answer() {
        let claim = Arc::new(Claim::new(2, 4));
        let (asks, mut asked) = tokio::sync::mpsc::unbounded_channel();
        let claimer = {
            let claim = claim.clone();
            std::thread::spawn(move || {
                asked.blocking_recv().expect("an ask");
                answer(&claim, 4, 4);
            })
        };
        assert_eq!(blocks(&claim, 2, &asks, 99), [2..4]);
        claimer.join().unwrap();
    }

    #[test]
    fn with_no_one_to_ask_the_run_ends_at_what_is_committed() {
        let claim = Claim::new(3, 8);
        let (asks, asked) = tokio::sync::mpsc::unbounded_channel();
        drop(asked);
        assert_eq!(blocks(&claim, 0, &asks, 99), [0..2, 2..3]);
    }
}
