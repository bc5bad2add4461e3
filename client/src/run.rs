//! `vlf run`: the embedded service. The coordinator (`vlf serve`) and `--workers` workers
//! (`vlf worker`) in this process, over a local store, talking gRPC on a loopback port: the
//! distributed service with nothing to set up. Every iteration's batches are leased to the
//! workers, which write their outputs into the store; the coordinator absorbs them in order
//! and commits a snapshot. The result is the same bits as `vlf propagate` and as any number of
//! workers, in this process or others.
//!
//! `--resume JOB` starts the service over the store, which takes up JOB alone (the coordinator's
//! recovery, for one job), and follows it to its end. Other unfinished jobs of the store are left
//! as they are: `vlf serve` over the store takes them all up.

use crate::RunArgs;
use crate::processes::WorkerProcesses;
use crate::propagate::{import, print_summary};
use crate::remote;
use anyhow::{Context, Result, bail};
use std::time::{Duration, Instant};
use vlf_core::scene::Scene;
use vlf_proto::{JobSpec, Target};
use vlf_server::driver::TakeUp;
use vlf_server::{ServeConfig, Server};
use vlf_store::{FieldJob, JobId, Prototypes, Stage, Store};
use vlf_worker::{StoreChoice, WorkerConfig};

pub fn run(args: RunArgs) -> Result<()> {
    let RunArgs {
        propagate: args,
        workers,
    } = args;
    let started = Instant::now();
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let job = match &args.resume {
        Some(id) => {
            if args.job.given_beyond_resample()? {
                bail!(
                    "--resume goes on with the job's own parameters: drop the job's flags (only \
                     --threads, --workers, --subfield-memory and --resample apply)"
                );
            }
            EmbeddedJob::Resume(JobId::parse(id).map_err(anyhow::Error::msg)?)
        }
        None => {
            let spec = args.job.spec()?;
            let path = args
                .scene
                .clone()
                .context("a scene is needed unless --resume is given")?;
            EmbeddedJob::New(import(&path)?, spec)
        }
    };
    // A job to resume must be there: its store is opened as it is, not created at a typo.
    let store = {
        let (url, resample) = (args.store.clone(), args.job.resample);
        let resume = match &job {
            EmbeddedJob::Resume(id) => Some(id.clone()),
            EmbeddedJob::New(..) => None,
        };
        runtime.block_on(vlf_store::blocking(move || -> Result<Store> {
            let Some(id) = resume else {
                return Ok(Store::open(&url)?);
            };
            let store = Store::open_existing(&url)?;
            let mut job = vlf_store::Job::open(&store, &id).with_context(|| format!("no job {id} in {url}"))?;
            // Recorded before the coordinator takes the job up: it finishes a job as recorded.
            // A job that has ended is not rewritten: there is nothing left to re-sample.
            let state = &job.manifest().state;
            if resample && !job.manifest().resample {
                if !matches!(
                    state,
                    vlf_store::JobState::Queued | vlf_store::JobState::Propagating { .. }
                ) {
                    bail!("job {id} is {state}: --resample applies to a job still to finish");
                }
                job.set_resample(true)?;
            }
            Ok(store)
        }))??
    };
    let done = runtime.block_on(embedded(
        store,
        job,
        Workers {
            count: workers,
            threads,
            subfield_budget: args.subfield_budget(),
            processes: false,
        },
        Follow::Progress,
    ))?;
    // The handle the service used: a `memory://` store lives only in it.
    let job = FieldJob::open(&done.store, &done.id)?;
    let summary = job.summary(Stage::Field)?;
    print_summary(&args, &job, &summary, started, f64::NAN, None)
}

/// The job an embedded service runs.
pub enum EmbeddedJob {
    New(Scene, JobSpec),
    /// A job of the store, resumed from its last finished snapshot.
    Resume(JobId),
}

/// The workers of an embedded run, sharing `threads` compute threads: replicas in this process,
/// or processes of their own.
#[derive(Clone, Copy, Debug)]
pub struct Workers {
    pub count: usize,
    pub threads: usize,
    /// Subfield bytes the process holds at most (the coordinator's propagation, which its
    /// workers share), and each worker process when they are processes; `None`: all.
    pub subfield_budget: Option<usize>,
    /// Run each worker as a process of its own (`crate::processes`), `threads / count` threads
    /// each, rather than in this process: each builds the job's geometry and opens the store
    /// itself, as a cluster's workers do.
    pub processes: bool,
}

impl Workers {
    /// `count` workers sharing `threads`, holding every subfield.
    pub fn new(count: usize, threads: usize) -> Workers {
        Workers {
            count,
            threads,
            subfield_budget: None,
            processes: false,
        }
    }

    /// The same workers, each a process of its own when `processes` is set.
    pub fn processes(self, processes: bool) -> Workers {
        Workers { processes, ..self }
    }
}

/// How to wait for the job.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Follow {
    /// Through the API, with progress bars (what `vlf watch` shows).
    Progress,
    /// Silently (benchmarks).
    Quiet,
}

/// What an embedded run did.
pub struct Embedded {
    pub id: JobId,
    pub store: Store,
    /// Per iteration: seconds from its start to its snapshot's commit, and the work it moved
    /// through the store.
    pub iterations: Vec<vlf_server::scheduler::IterationRecord>,
    /// CPU seconds of the worker processes ([`Workers::processes`]), which this process's CPU
    /// clock does not count: 0 when the workers ran in this process, NaN where unknown.
    pub worker_process_cpu_seconds: f64,
}

/// Runs `job` to its end on a coordinator in this process and `workers` (in it, or processes
/// of their own), over `store`, talking gRPC on a loopback port.
pub async fn embedded(store: Store, job: EmbeddedJob, workers: Workers, follow: Follow) -> Result<Embedded> {
    if !(1..=64).contains(&workers.count) {
        bail!("--workers must be between 1 and 64, got {}", workers.count);
    }
    if !(1..=1024).contains(&workers.threads) {
        bail!("--threads must be between 1 and 1024");
    }
    // The cores are shared among the workers; each computes its batches with its share.
    let per_worker = (workers.threads / workers.count).max(1);
    let url = store.url().to_string();
    let loopback = "127.0.0.1:0".parse().context("loopback address")?;
    // The coordinator offers every job's geometry to the workers of this process: built once.
    let prototypes = Prototypes::new(workers.count);
    // The service runs the job it is given, not every unfinished job that shares its store.
    let take_up = match &job {
        EmbeddedJob::Resume(id) => TakeUp::Only(id.clone()),
        EmbeddedJob::New(..) => TakeUp::Nothing,
    };
    let config = ServeConfig {
        prototypes: (!workers.processes).then(|| prototypes.clone()),
        subfield_budget: workers.subfield_budget,
        take_up,
        ..ServeConfig::new(url.clone(), loopback)
    };
    let server = Server::start_with_store(config, store.clone())
        .await
        .context("cannot start the coordinator")?;
    let target = Target::new(format!("http://{}", server.addr()));

    // The workers first: leases are sized to the workers alive when they ask.
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut processes = match workers.processes {
        true => Some(WorkerProcesses::start(
            workers.count,
            per_worker,
            &target.url,
            &url,
            workers.subfield_budget,
        )?),
        false => None,
    };
    // Each worker in this process says when it stops: before the job ends, that is a failure
    // (no other worker may be left to take its leases), not a wait for ever.
    let (stopped_tx, mut stopped_rx) = tokio::sync::mpsc::unbounded_channel::<usize>();
    let handles: Vec<_> = (0..workers.count)
        .filter(|_| processes.is_none())
        .map(|w| {
            let config = WorkerConfig {
                target: target.clone(),
                name: format!("embedded-{w}"),
                threads: Some(per_worker),
                store: StoreChoice::Handle(store.clone()),
                hang_after: None,
                prototypes: Some(prototypes.clone()),
                subfield_budget: workers.subfield_budget,
            };
            let mut stop = stop_rx.clone();
            let stopped = stopped_tx.clone();
            tokio::spawn(async move {
                let ran = vlf_worker::run(config, async move {
                    let _ = stop.wait_for(|s| *s).await;
                })
                .await;
                let _ = stopped.send(w);
                ran
            })
        })
        .collect();
    let registering = Instant::now();
    while server.scheduler().workers_alive() < workers.count as u32 && registering.elapsed() < Duration::from_secs(10) {
        if let Some(exited) = processes.as_mut().and_then(|p| p.exited()) {
            bail!("{exited}");
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    if processes.is_some() && server.scheduler().workers_alive() < workers.count as u32 {
        bail!(
            "only {} of {} worker processes registered within 10 s",
            server.scheduler().workers_alive(),
            workers.count
        );
    }

    let id = match job {
        EmbeddedJob::Resume(id) => {
            let status = server
                .scheduler()
                .status(&id)
                .with_context(|| format!("no job {id} in {url}"))?;
            if follow == Follow::Progress {
                println!(
                    "resuming job {id} in {url} after {} iterations",
                    status.snapshots.len().saturating_sub(1)
                );
            }
            id
        }
        EmbeddedJob::New(scene, spec) => {
            let status = vlf_server::driver::submit(server.scheduler(), scene, spec)
                .await
                .context("cannot create the job")?;
            if follow == Follow::Progress {
                println!("job {} in {url}", status.job_id);
            }
            JobId::parse(&status.job_id).map_err(anyhow::Error::msg)?
        }
    };

    let following = async {
        match follow {
            Follow::Progress => match remote::connect(&target).await {
                Ok(mut clients) => remote::follow(&mut clients, id.as_str()).await.map(|_| ()),
                Err(e) => Err(e),
            },
            Follow::Quiet => wait_quietly(&server, &id).await,
        }
    };
    // A worker that stops (a store it cannot open, a refusal, a crash) would leave the job
    // waiting for its leases to expire, over and over: the run fails instead.
    drop(stopped_tx);
    let followed = match processes.as_mut() {
        None if handles.is_empty() => following.await,
        None => tokio::select! {
            followed = following => followed,
            // `None`: every worker's task is gone, a panicked one's included.
            stopped = stopped_rx.recv() => Err(match stopped {
                Some(w) => anyhow::anyhow!("worker embedded-{w} stopped before job {id} ended (its error is logged)"),
                None => anyhow::anyhow!("every worker stopped before job {id} ended"),
            }),
        },
        Some(running) => tokio::select! {
            followed = following => followed,
            exited = first_exit(running) => Err(anyhow::anyhow!(exited)),
        },
    };
    let worker_process_cpu_seconds = match processes.take() {
        // Read before they are stopped: a killed process's clock is gone with it.
        Some(p) => p.cpu_seconds().unwrap_or(f64::NAN),
        None => 0.0,
    };
    let _ = stop_tx.send(true);
    for handle in handles {
        match handle.await {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => tracing::error!("a worker stopped with an error: {e}"),
            Err(e) => tracing::warn!("a worker panicked: {e}"),
        }
    }
    let iterations = server.scheduler().iterations(&id).unwrap_or_default();
    server.shutdown().await;
    followed?;
    Ok(Embedded {
        id,
        store,
        iterations,
        worker_process_cpu_seconds,
    })
}

/// How the first of `running` to stop stopped, once one has.
async fn first_exit(running: &mut WorkerProcesses) -> String {
    loop {
        if let Some(exited) = running.exited() {
            return exited;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Waits for the job's last status; an error unless it finished.
async fn wait_quietly(server: &Server, id: &JobId) -> Result<()> {
    let mut rx = server.scheduler().subscribe(id)?;
    loop {
        let status = rx.borrow_and_update().clone();
        if vlf_server::scheduler::is_terminal(status.state) {
            if status.state == vlf_proto::v1::State::Finished as i32 {
                return Ok(());
            }
            bail!("job {id} ended {:?}: {}", status.state(), status.message);
        }
        rx.changed().await.context("the coordinator stopped")?;
    }
}
