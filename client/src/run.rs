//! `vlf run`: the embedded service. A coordinator and `--workers` worker
//! replicas in this process, over a store: every iteration's batches of
//! directions are handed out to the workers, whose outputs go through the
//! store, and the coordinator absorbs them in order and commits a snapshot —
//! the distributed service's data path (`vlf_store::iteration`), on one
//! machine and with no set-up. The result is the same bits as
//! `vlf propagate` and as any number of workers.

use crate::RunArgs;
use crate::propagate::{print_summary, start, thread_pool};
use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;
use vlf_store::{Coordinator, FieldJob, Replica, Stage, Store};

pub fn run(args: RunArgs) -> Result<()> {
    let RunArgs {
        propagate: args,
        workers,
    } = args;
    if !(1..=64).contains(&workers) {
        bail!("--workers must be between 1 and 64, got {workers}");
    }
    let pool = thread_pool(&args)?;
    let started = Instant::now();
    let (job, prop) = start(&args, &pool)?;
    print!("{}", prop.plan);
    let id = job.id().clone();
    let mut coordinator = Coordinator::new(job, prop);
    // Each worker has its own store handle and its own copy of the geometry, as a worker process
    // would.
    let mut replicas: Vec<Replica> = pool
        .install(|| -> Result<Vec<Replica>, vlf_store::StoreError> {
            (0..workers)
                .map(|_| Replica::new(FieldJob::open(&Store::open(&args.store)?, &id)?))
                .collect()
        })
        .context("cannot start the workers")?;

    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("{prefix:>14} [{bar:40}] {pos}/{len} batches {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    while !coordinator.finished() {
        let k = coordinator.iteration();
        bar.set_prefix(format!("iteration {}", k + 1));
        bar.set_message(format!(
            "unshot {:.2e}, {workers} workers",
            coordinator.propagation().unshot_fraction()
        ));
        while let Some((pass, batches)) = coordinator.pending_pass() {
            bar.set_length(batches as u64);
            bar.set_position(0);
            let next = AtomicUsize::new(0);
            let failure = Mutex::new(None);
            pool.install(|| {
                rayon::scope(|s| {
                    for replica in replicas.iter_mut() {
                        let (next, failure, bar) = (&next, &failure, &bar);
                        s.spawn(move |_| {
                            loop {
                                let b = next.fetch_add(1, Ordering::Relaxed);
                                if b >= batches {
                                    break;
                                }
                                if let Err(e) = replica.compute(k, pass, b..b + 1) {
                                    // Stop handing out work; the first error is reported.
                                    next.store(batches, Ordering::Relaxed);
                                    let mut slot = failure.lock().unwrap_or_else(|p| p.into_inner());
                                    slot.get_or_insert(e);
                                    break;
                                }
                                bar.inc(1);
                            }
                        });
                    }
                })
            });
            if let Some(e) = failure.into_inner().unwrap_or_else(|p| p.into_inner()) {
                bar.finish_and_clear();
                return Err(e).with_context(|| format!("a worker failed in iteration {}", k + 1));
            }
            pool.install(|| coordinator.absorb_pass())
                .with_context(|| format!("cannot absorb {pass:?} of iteration {}", k + 1))?;
        }
        pool.install(|| coordinator.finish_iteration())
            .with_context(|| format!("cannot finish iteration {}", k + 1))?;
    }
    bar.finish_and_clear();
    let job = pool
        .install(|| coordinator.finish(args.resample))
        .context("cannot write the final field")?;
    let summary = job.summary(Stage::Field)?;
    print_summary(&args, &job, &summary, started, f64::NAN, None)
}
