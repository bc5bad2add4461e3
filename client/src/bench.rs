//! `vlf bench`: what the distributed service costs over an in-process propagation.
//!
//! The same job (scene and parameters) runs `--repeat` times each way, interleaved so that a
//! noisy machine spreads its noise evenly: `vlf propagate`'s loop in this process (setup, every
//! iteration, every snapshot written into a `memory://` store) and the embedded service (`vlf
//! run`: a coordinator and `--workers` workers in this process talking gRPC on loopback, every
//! batch output going through a `memory://` store). The `memory://` store keeps the disk's latency
//! out of the comparison; what is left is the service's own cost: leases, encoding and moving
//! the batch outputs, the coordinator's absorbing, and each worker building its geometry.
//!
//! Reported per way: the median and fastest wall time, the median over rounds of each round's
//! ratio to its in-process run (with the smallest and largest: a noisy machine's slow spells hit
//! both runs of a round alike), the median time of every iteration, and the work each iteration
//! moved through the store (blobs and MB). Every service run's last checkpoint is checked bit for bit against
//! the in-process one.

use crate::JobFlags;
use crate::run::{Embedded, EmbeddedJob, Follow, Workers, embedded};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;
use vlf_core::propagate::{Checkpoint, Propagation};
use vlf_core::scene::Scene;
use vlf_proto::JobSpec;
use vlf_server::scheduler::{IterationRecord, IterationUse};
use vlf_store::{FieldJob, Store, Traffic};

#[derive(Args)]
pub struct BenchArgs {
    /// Wavefront OBJ scene.
    scene: PathBuf,
    #[command(flatten)]
    job: JobFlags,
    /// Worker counts of the service runs, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    workers: Vec<usize>,
    /// Runs of each way (the median is reported).
    #[arg(long, default_value_t = 5)]
    repeat: usize,
    /// Compute threads (default: all cores), shared by a service run's workers.
    #[arg(long)]
    threads: Option<usize>,
    /// Also write the report (Markdown) to this file.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Share the machine with another program, as a cluster's workers often do: a thread that
    /// computes for 30 ms of every 60 while every run goes, both ways alike. What the service
    /// then costs shows how its workers cope with cores that are not their own.
    #[arg(long)]
    cotenant: bool,
}

/// A thread that computes for 30 ms of every 60 until dropped (`--cotenant`).
struct Cotenant {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Cotenant {
    fn start() -> Result<Cotenant> {
        use std::sync::atomic::Ordering;
        use std::time::Duration;
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::Builder::new()
            .name("cotenant".into())
            .spawn(move || {
                let mut x = 1u64;
                while !flag.load(Ordering::Relaxed) {
                    let busy = Instant::now();
                    while busy.elapsed() < Duration::from_millis(30) {
                        x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
                    }
                    std::thread::sleep(Duration::from_millis(30));
                }
            })
            .context("cannot start the co-tenant thread")?;
        Ok(Cotenant {
            stop,
            thread: Some(thread),
        })
    }
}

impl Drop for Cotenant {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// One run of one way.
struct Sample {
    seconds: f64,
    iterations: Vec<IterationRecord>,
    /// Everything the run read and wrote through the store (snapshots, work, the final field).
    traffic: Traffic,
}

impl Sample {
    /// A run that started at `started` and has just ended over `store`.
    fn ended(started: Instant, iterations: Vec<IterationRecord>, store: &Store) -> Sample {
        Sample {
            seconds: started.elapsed().as_secs_f64(),
            iterations,
            traffic: store.traffic(),
        }
    }
}

pub fn run(args: BenchArgs) -> Result<()> {
    if !(1..=100).contains(&args.repeat) {
        bail!("--repeat must be between 1 and 100, got {}", args.repeat);
    }
    if args.workers.is_empty() || args.workers.iter().any(|w| !(1..=64).contains(w)) {
        bail!("--workers must list counts between 1 and 64");
    }
    let threads = match args.threads {
        Some(t) if (1..=1024).contains(&t) => t,
        Some(t) => bail!("--threads must be between 1 and 1024, got {t}"),
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    let spec = args.job.spec()?;
    let scene = crate::propagate::import(&args.scene)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;

    let ways: Vec<Option<usize>> = std::iter::once(None)
        .chain(args.workers.iter().copied().map(Some))
        .collect();
    let mut samples: Vec<Vec<Sample>> = ways.iter().map(|_| Vec::new()).collect();
    let mut reference: Option<Checkpoint> = None;
    let cotenant = if args.cotenant { Some(Cotenant::start()?) } else { None };
    let bar = indicatif::ProgressBar::new((args.repeat * ways.len()) as u64);
    for _ in 0..args.repeat {
        for (way, workers) in ways.iter().enumerate() {
            let (sample, last) = match workers {
                // Threads of its own, as `vlf propagate` starts them, and as the service's
                // workers start theirs: threads kept from the last round would have their
                // allocator's memory at hand, where fresh ones fault their pages in.
                None => rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .context("cannot start the compute threads")?
                    .install(|| in_process(&scene, &spec))?,
                Some(count) => service(&runtime, &scene, &spec, Workers { count: *count, threads })?,
            };
            let last = without_times(last);
            match &reference {
                None => reference = Some(last),
                Some(r) if *r != last => {
                    bail!("the service with {workers:?} workers changed the bits of the field")
                }
                Some(_) => {}
            }
            samples[way].push(sample);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    drop(cotenant);

    // The first iteration learns the job's speed (a one-batch lease), perturbed ones shoot
    // rotated copies: the plain iterations after them are the propagation's throughput.
    let plain = spec.options.perturbation.iterations.max(1) as usize;
    let report = report(&args, threads, &ways, &samples, plain);
    print!("{report}");
    if let Some(path) = &args.out {
        std::fs::write(path, &report).with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}

/// `vlf propagate`'s loop into a `memory://` store.
fn in_process(scene: &Scene, spec: &JobSpec) -> Result<(Sample, Checkpoint)> {
    let started = Instant::now();
    let store = Store::open("memory://")?;
    let mut prop = Propagation::new(scene.clone(), spec.options.clone())?;
    let mut job = FieldJob::create(&store, &prop, spec.encoding)?;
    let mut iterations = Vec::new();
    while !prop.finished() {
        let t = Instant::now();
        prop.step(|_| {});
        job.write_snapshot(&prop)?;
        iterations.push(IterationRecord {
            seconds: t.elapsed().as_secs_f64(),
            ..IterationRecord::default()
        });
    }
    let last = prop.checkpoint();
    job.finish(&prop.into_field(), false)?;
    Ok((Sample::ended(started, iterations, &store), last))
}

/// The embedded service over a `memory://` store.
fn service(
    runtime: &tokio::runtime::Runtime,
    scene: &Scene,
    spec: &JobSpec,
    workers: Workers,
) -> Result<(Sample, Checkpoint)> {
    let started = Instant::now();
    let store = Store::open("memory://")?;
    let job = EmbeddedJob::New(scene.clone(), spec.clone());
    let Embedded { id, store, iterations } = runtime.block_on(embedded(store, job, workers, Follow::Quiet))?;
    let count = iterations.len() as u32;
    // Taken before the check below reads the store.
    let sample = Sample::ended(started, iterations, &store);
    let last = FieldJob::open(&store, &id)?.checkpoint(count)?;
    Ok((sample, last))
}

fn without_times(mut c: Checkpoint) -> Checkpoint {
    for s in &mut c.stats {
        s.seconds = 0.0;
    }
    c
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => (v[n / 2 - 1] + v[n / 2]) / 2.0,
    }
}

/// The median, smallest and largest of `way[i] / base[i]` over the rounds `i`.
fn paired_ratio(base: &[f64], way: &[f64]) -> (f64, f64, f64) {
    let ratios: Vec<f64> = base.iter().zip(way).map(|(b, w)| w / b).collect();
    let low = ratios.iter().copied().fold(f64::INFINITY, f64::min);
    let high = ratios.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    (median(ratios), low, high)
}

fn name(workers: Option<usize>) -> String {
    match workers {
        None => "in-process".into(),
        Some(1) => "service, 1 worker".into(),
        Some(w) => format!("service, {w} workers"),
    }
}

/// The Markdown report.
fn report(
    args: &BenchArgs,
    threads: usize,
    ways: &[Option<usize>],
    samples: &[Vec<Sample>],
    plain_after: usize,
) -> String {
    let mut out = String::new();
    let cpu = cpu_name().unwrap_or_else(|| "unknown CPU".into());
    let _ = writeln!(
        out,
        "# vlf bench: {} (l = {}, N = {}, m = {})\n",
        args.scene.display(),
        args.job.directions,
        args.job.resolution,
        args.job.tile
    );
    let _ = writeln!(
        out,
        "{threads} threads on {cpu}; `memory://` store; median of {} runs each, interleaved. \
         Every service run gave the in-process bits.{}\n",
        args.repeat,
        if args.cotenant {
            " With a co-tenant: a thread computing 30 ms of every 60 throughout (`--cotenant`)."
        } else {
            ""
        }
    );
    let _ = writeln!(
        out,
        "`×` is the median over rounds of each round's ratio to its in-process run (a slow \
         spell of the machine slows both runs of a round), with the smallest and largest.\n"
    );
    let base: Vec<f64> = samples[0].iter().map(|s| s.seconds).collect();
    let _ = writeln!(out, "| run | median s | fastest s | × in-process | × range |");
    let _ = writeln!(out, "|---|---:|---:|---:|---:|");
    for (way, runs) in ways.iter().zip(samples) {
        let times: Vec<f64> = runs.iter().map(|s| s.seconds).collect();
        let fastest = times.iter().copied().fold(f64::INFINITY, f64::min);
        let (ratio, low, high) = paired_ratio(&base, &times);
        let m = median(times);
        let _ = writeln!(
            out,
            "| {} | {m:.3} | {fastest:.3} | {ratio:.2} | {low:.2}–{high:.2} |",
            name(*way)
        );
    }

    // The plain iterations, summed per run and paired by round like the whole runs.
    let count = samples[0].first().map_or(0, |s| s.iterations.len());
    if count > plain_after {
        let plain = |s: &Sample| -> f64 { s.iterations.iter().skip(plain_after).map(|i| i.seconds).sum() };
        let which = match plain_after + 1 {
            k if k == count => format!("Iteration {k}"),
            k => format!("Iterations {k}–{count}"),
        };
        let _ = writeln!(
            out,
            "\n{which} (the propagation's throughput: the first{} left out), summed per run:\n",
            if plain_after > 1 { " and the perturbed ones" } else { "" }
        );
        let _ = writeln!(out, "| run | median s | × in-process | × range |");
        let _ = writeln!(out, "|---|---:|---:|---:|");
        let base: Vec<f64> = samples[0].iter().map(plain).collect();
        for (way, runs) in ways.iter().zip(samples) {
            let times: Vec<f64> = runs.iter().map(plain).collect();
            let (ratio, low, high) = paired_ratio(&base, &times);
            let m = median(times);
            let _ = writeln!(out, "| {} | {m:.3} | {ratio:.2} | {low:.2}–{high:.2} |", name(*way));
        }
        workers_table(&mut out, ways, samples, plain_after);
    }

    // What each way moved through the store in its first run (the same every run), and what the
    // service moves on top of the in-process run, per iteration.
    let _ = writeln!(
        out,
        "\nThrough the store, per run (every object read and written, as stored: snapshots, work, \
         the final field); `+ per iteration` is what the service moves on top of the in-process \
         run, divided by the iterations:\n"
    );
    let _ = writeln!(
        out,
        "| run | written: objects / MB | read: objects / MB | + per iteration: written / read MB |"
    );
    let _ = writeln!(out, "|---|---:|---:|---:|");
    let first = |runs: &[Sample]| runs.first().map_or(Traffic::default(), |s| s.traffic);
    let base_traffic = first(&samples[0]);
    let iterations = samples[0].first().map_or(0, |s| s.iterations.len()).max(1) as f64;
    for (way, runs) in ways.iter().zip(samples) {
        let t = first(runs);
        let extra = |a: u64, b: u64| (a as f64 - b as f64) / 1e6 / iterations;
        let _ = writeln!(
            out,
            "| {} | {} / {:.1} | {} / {:.1} | {:.2} / {:.2} |",
            name(*way),
            t.writes,
            t.written_bytes as f64 / 1e6,
            t.reads,
            t.read_bytes as f64 / 1e6,
            extra(t.written_bytes, base_traffic.written_bytes),
            extra(t.read_bytes, base_traffic.read_bytes),
        );
    }

    let _ = writeln!(
        out,
        "\nPer iteration (median seconds; work through the store, per service run):\n"
    );
    let mut header = "| iteration |".to_string();
    let mut rule = "|---:|".to_string();
    for way in ways {
        let _ = write!(header, " {} s |", name(*way));
        rule.push_str("---:|");
    }
    for way in &ways[1..] {
        let _ = write!(header, " {} blobs / MB |", name(*way));
        rule.push_str("---:|");
    }
    let _ = writeln!(out, "{header}\n{rule}");
    for k in 0..count {
        let mut row = format!("| {} |", k + 1);
        for runs in samples {
            let t = median(
                runs.iter()
                    .filter_map(|s| s.iterations.get(k).map(|i| i.seconds))
                    .collect(),
            );
            let _ = write!(row, " {t:.3} |");
        }
        for runs in &samples[1..] {
            let traffic = runs
                .first()
                .and_then(|s| s.iterations.get(k))
                .map(|i| i.traffic)
                .unwrap_or_default();
            let _ = write!(row, " {} / {:.2} |", traffic.blobs, traffic.bytes as f64 / 1e6);
        }
        let _ = writeln!(out, "{row}");
    }
    out
}

/// How the service's workers spent the plain iterations (see `IterationUse`): medians over
/// every plain iteration of every run of a way.
fn workers_table(out: &mut String, ways: &[Option<usize>], samples: &[Vec<Sample>], plain_after: usize) {
    let _ = writeln!(
        out,
        "\nHow the service spent those iterations (medians per iteration): the workers computed \
         in a `span` from its first lease to its last report, `busy` of it all in all (`balance` \
         = busy / (workers × span): 1 when no worker waited for another; `waiting` = workers × \
         span − busy); `between` is the rest, the serial part between iterations (the last \
         block's absorb, the diffuse reflection, the next head, the next leases):\n"
    );
    let _ = writeln!(
        out,
        "| run | iteration ms | between ms | span ms | balance | waiting ms |"
    );
    let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|");
    for (way, runs) in ways.iter().zip(samples).skip(1) {
        let used: Vec<IterationUse> = runs
            .iter()
            .flat_map(|s| s.iterations.iter().skip(plain_after).map(|i| i.workers))
            .filter(|u| u.workers > 0)
            .collect();
        if used.is_empty() {
            continue;
        }
        let ms = |f: &dyn Fn(&IterationUse) -> f64| median(used.iter().map(f).collect()) * 1e3;
        let balance = median(used.iter().filter_map(IterationUse::balance).collect());
        let _ = writeln!(
            out,
            "| {} | {:.1} | {:.1} | {:.1} | {balance:.2} | {:.1} |",
            name(*way),
            ms(&|u| u.seconds),
            ms(&|u| u.between_seconds()),
            ms(&|u| u.span_seconds),
            ms(&|u| u.waiting_seconds()),
        );
    }
}

/// The CPU's model name (Linux).
fn cpu_name() -> Option<String> {
    let info = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("model name"))?;
    Some(line.split_once(':')?.1.trim().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paired_ratios_cancel_a_machine_that_slows_down_between_rounds() {
        // The machine is 3× slower in the last round: each round's ratio is still 1.2.
        let base = [1.0, 1.0, 3.0];
        let service = [1.2, 1.2, 3.6];
        let (ratio, low, high) = paired_ratio(&base, &service);
        assert!((ratio - 1.2).abs() < 1e-12 && (low - 1.2).abs() < 1e-12 && (high - 1.2).abs() < 1e-12);
        let (ratio, low, high) = paired_ratio(&[1.0, 2.0, 4.0], &[1.1, 2.6, 4.0]);
        assert_eq!((ratio, low, high), (1.1, 1.0, 1.3));
        assert_eq!(median(vec![3.0, 1.0, 2.0, 10.0]), 2.5);
    }
}
