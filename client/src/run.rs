//! `vlf run`: the embedded service. The coordinator (`vlf serve`) and `--workers` workers
//! (`vlf worker`) in this process, over a local store, talking gRPC on a loopback port: the
//! distributed service with nothing to set up. Every iteration's batches are leased to the
//! workers, which write their outputs into the store; the coordinator absorbs them in batch order
//! and commits a snapshot. The result is the same bits as `vlf propagate` and as any number of
//! workers, in this process or others.
//!
//! `--resume JOB` starts the service over the store, which takes up every unfinished job of it
//! (the coordinator's recovery), and follows JOB to its end.

use crate::RunArgs;
use crate::propagate::print_summary;
use crate::remote;
use anyhow::{Context, Result, bail};
use std::time::Instant;
use vlf_core::scene::{ImportOptions, load_obj};
use vlf_proto::Target;
use vlf_server::{ServeConfig, Server};
use vlf_store::{FieldJob, JobId, Stage, Store};
use vlf_worker::{StoreChoice, WorkerConfig};

pub fn run(args: RunArgs) -> Result<()> {
    let RunArgs {
        propagate: args,
        workers,
    } = args;
    if !(1..=64).contains(&workers) {
        bail!("--workers must be between 1 and 64, got {workers}");
    }
    if args.threads == Some(0) || args.threads.is_some_and(|t| t > 1024) {
        bail!("--threads must be between 1 and 1024");
    }
    let started = Instant::now();
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    // The cores are shared among the workers; each computes its batches with its share.
    let per_worker = (threads / workers).max(1);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let (id, store) = runtime.block_on(async {
        let store = {
            let url = args.store.clone();
            vlf_store::blocking(move || Store::open(&url)).await??
        };
        let loopback = "127.0.0.1:0".parse().context("loopback address")?;
        let server = Server::start_with_store(ServeConfig::new(args.store.clone(), loopback), store.clone())
            .await
            .context("cannot start the coordinator")?;
        let target = Target::new(format!("http://{}", server.addr()));

        // The workers first: leases are sized to the workers alive when a pass opens.
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        let handles: Vec<_> = (0..workers)
            .map(|w| {
                let config = WorkerConfig {
                    target: target.clone(),
                    name: format!("embedded-{w}"),
                    threads: Some(per_worker),
                    store: StoreChoice::Handle(store.clone()),
                    hang_after: None,
                };
                let mut stop = stop_rx.clone();
                tokio::spawn(vlf_worker::run(config, async move {
                    let _ = stop.wait_for(|s| *s).await;
                }))
            })
            .collect();
        let registered = Instant::now();
        while server.scheduler().workers_alive() < workers as u32 && registered.elapsed().as_secs() < 10 {
            tokio::time::sleep(std::time::Duration::from_millis(2)).await;
        }

        let id = match &args.resume {
            Some(id) => {
                let id = JobId::parse(id).map_err(anyhow::Error::msg)?;
                let status = server
                    .scheduler()
                    .status(&id)
                    .with_context(|| format!("no job {id} in {}", args.store))?;
                println!(
                    "resuming job {id} in {} after {} iterations",
                    args.store,
                    status.snapshots.len().saturating_sub(1)
                );
                id
            }
            None => {
                let spec = args.job.spec()?;
                let path = args
                    .scene
                    .clone()
                    .context("a scene is needed unless --resume is given")?;
                let (scene, warnings) = vlf_store::blocking(move || {
                    load_obj(&path, &ImportOptions::default())
                        .with_context(|| format!("cannot import {}", path.display()))
                })
                .await??;
                for w in &warnings {
                    tracing::warn!("{w}");
                }
                let status = vlf_server::driver::submit(server.scheduler(), scene, spec)
                    .await
                    .context("cannot create the job")?;
                println!("job {} in {}", status.job_id, args.store);
                JobId::parse(&status.job_id).map_err(anyhow::Error::msg)?
            }
        };

        let mut clients = remote::connect(&target).await?;
        let followed = remote::follow(&mut clients, id.as_str()).await;
        let _ = stop_tx.send(true);
        for handle in handles {
            match handle.await {
                Ok(Ok(_)) => {}
                Ok(Err(e)) => tracing::warn!("a worker stopped with an error: {e}"),
                Err(e) => tracing::warn!("a worker panicked: {e}"),
            }
        }
        server.shutdown().await;
        followed?;
        anyhow::Ok((id, store))
    })?;

    // The handle the service used: a `memory://` store lives only in it.
    let job = FieldJob::open(&store, &id)?;
    let summary = job.summary(Stage::Field)?;
    print_summary(&args, &job, &summary, started, f64::NAN, None)
}
