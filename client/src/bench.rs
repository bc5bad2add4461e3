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
//! With two workers or more, a third way runs too: the in-process loop cut the way the workers
//! cut it (`Propagation::step_split`: the batches split into contiguous homes by what they cost
//! in the iteration before, as the coordinator splits them, each home on its own share of the
//! threads, nothing between them). Where a worker's threads cannot help another worker, the
//! iteration waits for the slowest home whatever the service does: that way's ratio is what the
//! cut costs, and the service's ratio to it what the service adds.
//!
//! Reported per way: the median and fastest wall time, the median over rounds of each round's
//! ratio to its in-process run (with the smallest and largest: a noisy machine's slow spells hit
//! both runs of a round alike), the CPU time the process spent on the run (every thread: so the
//! service's extra work shows apart from its waiting, `cores busy` = CPU / wall), the median time
//! of every iteration, and the work each iteration moved through the store (blobs and MB). Every
//! service run's last checkpoint is checked bit for bit against the in-process one.

mod scaling;

use crate::JobFlags;
use crate::run::{Embedded, EmbeddedJob, Follow, Workers, embedded};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;
use vlf_core::propagate::{Checkpoint, HomeThreads, PhaseTimes, Propagation, split_by_cost};
use vlf_core::scene::Scene;
use vlf_proto::JobSpec;
use vlf_server::scheduler::{IterationRecord, IterationUse};
use vlf_store::{FieldJob, JobId, SnapshotWriter, Store, Traffic};

#[derive(Args)]
pub struct BenchArgs {
    /// Scene file: Wavefront OBJ (with its MTL) or glTF 2.0 (.gltf, .glb).
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
    /// Make every call to the store wait this many milliseconds first (`memory://?latency=`), as
    /// a round trip to a remote object store would, both ways alike: what the service's store
    /// calls cost on a cluster's S3-compatible store, without one.
    #[arg(long, value_name = "MS", conflicts_with = "store")]
    latency: Option<f64>,
    /// Store every run writes into, in place of a fresh `memory://` one: a directory (on tmpfs,
    /// such as `/dev/shm/vlf-bench`, a local store without a disk's latency, whose blobs live
    /// in the kernel's page cache rather than the process's heap) or any store URL. Each run's
    /// job is deleted once it is measured.
    #[arg(long, value_name = "URL")]
    store: Option<String>,
    /// Print the scaling tables instead (`bench/scaling.rs`): the in-process loop on 1, 2, 4, …
    /// threads up to all cores, and the service with each `--workers` count of
    /// `--worker-threads` threads each; speed-up, efficiency and Amdahl's serial fraction.
    #[arg(long)]
    scaling: bool,
    /// Thread counts of `--scaling`'s in-process runs, comma-separated (default: 1, 2, 4, … and
    /// all cores).
    #[arg(long, value_delimiter = ',', requires = "scaling")]
    scale_threads: Vec<usize>,
    /// Threads of each worker in `--scaling`'s service runs.
    #[arg(long, default_value_t = 2, requires = "scaling")]
    worker_threads: usize,
    /// Run the service's workers as processes of their own (`vlf worker`, this program), as a
    /// cluster's are, rather than in this process: each builds the job's geometry and opens the
    /// store itself. Needs a `--store` they can open (a directory: `/dev/shm/vlf-bench` keeps
    /// it in memory). CPU times then add the worker processes'.
    #[arg(long)]
    worker_processes: bool,
}

/// The store every run of the bench writes into: `--store`, else `memory://` with `--latency`'s
/// wait.
fn store_url(args: &BenchArgs) -> String {
    match (&args.store, args.latency) {
        (Some(url), _) => url.clone(),
        (None, Some(ms)) => format!("memory://?latency={ms}ms"),
        (None, None) => "memory://".into(),
    }
}

/// Deletes a measured run's job, so that every run starts from the same store.
fn forget(store: &Store, id: &JobId) -> Result<()> {
    let keys = store.list(&vlf_store::layout::job_prefix(id))?;
    store
        .delete_all(&keys)
        .with_context(|| format!("cannot delete the bench's job {id} from {}", store.url()))
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
    /// CPU time of the whole process over the run: user and system, every thread (the
    /// coordinator's, the workers', the store's, a co-tenant's).
    cpu_seconds: f64,
    iterations: Vec<IterationRecord>,
    /// Everything the run read and wrote through the store (snapshots, work, the final field).
    traffic: Traffic,
    /// In one process: per iteration, where its time went, and the seconds its snapshot took
    /// to write (empty for the service).
    phases: Vec<(PhaseTimes, f64)>,
    /// In one process: whether the job's first iterations were perturbed (they are not where
    /// light reaches a mirror, whatever the options say); `None` for the service.
    perturbed: Option<bool>,
}

/// When a run started, on the wall clock and on the process's CPU clock.
#[derive(Clone, Copy)]
struct Started {
    wall: Instant,
    cpu: f64,
}

impl Started {
    fn now() -> Started {
        Started {
            wall: Instant::now(),
            cpu: process_cpu_seconds(),
        }
    }
}

/// The CPU time this process has used so far, all threads, user and system
/// (`CLOCK_PROCESS_CPUTIME_ID`).
fn process_cpu_seconds() -> f64 {
    cpu_clock_seconds(rustix::time::ClockId::ProcessCPUTime)
}

/// A CPU-time clock's reading, in seconds.
fn cpu_clock_seconds(clock: rustix::time::ClockId) -> f64 {
    let t = rustix::time::clock_gettime(clock);
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

impl Sample {
    /// A run that started at `started` and has just ended over `store`.
    fn ended(started: Started, iterations: Vec<IterationRecord>, store: &Store) -> Sample {
        Sample {
            seconds: started.wall.elapsed().as_secs_f64(),
            cpu_seconds: process_cpu_seconds() - started.cpu,
            iterations,
            traffic: store.traffic(),
            phases: Vec::new(),
            perturbed: None,
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
    if args.worker_processes && store_url(&args).starts_with("memory://") {
        bail!(
            "--worker-processes needs a --store that the worker processes can open: a directory \
             (/dev/shm/vlf-bench keeps it in memory) or an object store"
        );
    }
    let spec = args.job.spec()?;
    let scene = crate::propagate::import(&args.scene)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;

    if args.scaling {
        if args.cotenant {
            bail!("--cotenant measures the phase breakdown beside a busy neighbour: not with --scaling");
        }
        let report = scaling::run(&args, &store_url(&args), &scene, &spec, &runtime, threads)?;
        print!("{report}");
        if let Some(path) = &args.out {
            std::fs::write(path, &report).with_context(|| format!("cannot write {}", path.display()))?;
        }
        return Ok(());
    }
    let ways: Vec<Way> = std::iter::once(Way::InProcess)
        .chain(args.workers.iter().filter(|&&w| w > 1).map(|&w| Way::Split(w)))
        .chain(args.workers.iter().map(|&w| Way::Service(w)))
        .collect();
    let mut samples: Vec<Vec<Sample>> = ways.iter().map(|_| Vec::new()).collect();
    let mut reference: Option<Checkpoint> = None;
    let url = store_url(&args);
    Store::open(&url).context("--latency or --store")?;
    let cotenant = if args.cotenant { Some(Cotenant::start()?) } else { None };
    let bar = indicatif::ProgressBar::new((args.repeat * ways.len()) as u64);
    for _ in 0..args.repeat {
        for (way, kind) in ways.iter().enumerate() {
            // Threads of its own each run, as `vlf propagate` starts them, and as the service's
            // workers start theirs: threads kept from the last round would have their
            // allocator's memory at hand, where fresh ones fault their pages in.
            let (sample, last) = match *kind {
                Way::InProcess => rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .context("cannot start the compute threads")?
                    .install(|| in_process(&url, &scene, &spec))?,
                Way::Split(count) => in_process_split(&url, &scene, &spec, Workers::new(count, threads))?,
                Way::Service(count) => {
                    let workers = Workers::new(count, threads).processes(args.worker_processes);
                    service(&runtime, &url, &scene, &spec, workers)?
                }
            };
            let last = without_times(last);
            match &reference {
                None => reference = Some(last),
                Some(r) if *r != last => {
                    bail!("the run `{}` changed the bits of the field", kind.name())
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
    // The first way is the in-process run, which knows whether the scene let them be perturbed.
    let perturbed = samples[0].first().and_then(|s| s.perturbed).unwrap_or(true);
    let plain = match perturbed {
        true => spec.options.perturbation.iterations.max(1) as usize,
        false => 1,
    };
    let report = report(&args, threads, &ways, &samples, plain);
    print!("{report}");
    if let Some(path) = &args.out {
        std::fs::write(path, &report).with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}

/// `vlf propagate`'s loop into a `memory://` store.
fn in_process(url: &str, scene: &Scene, spec: &JobSpec) -> Result<(Sample, Checkpoint)> {
    in_process_with(url, scene, spec, |prop| {
        prop.step(|_| {});
        Ok(())
    })
}

/// The in-process loop cut into `workers.count` homes of `workers.count`-th of the threads, as
/// the service's workers split a pass (`Propagation::step_split`): the homes of an iteration
/// are cut by what the batches cost in the one before, as the coordinator cuts them
/// (`split_by_cost`); the first iteration's are even.
fn in_process_split(url: &str, scene: &Scene, spec: &JobSpec, workers: Workers) -> Result<(Sample, Checkpoint)> {
    let per_home = (workers.threads / workers.count).max(1);
    let mut threads = HomeThreads::new(workers.count, per_home)?;
    let mut costs = Vec::new();
    in_process_with(url, scene, spec, |prop| {
        let homes = split_by_cost(&costs, prop.iteration_work().batches(), workers.count);
        costs = prop.step_split(&homes, &mut threads, |_| {})?.1;
        Ok(())
    })
}

/// `vlf propagate`'s loop into the bench's store, each iteration done by `step`.
fn in_process_with(
    url: &str,
    scene: &Scene,
    spec: &JobSpec,
    mut step: impl FnMut(&mut Propagation) -> Result<()>,
) -> Result<(Sample, Checkpoint)> {
    let started = Started::now();
    let store = Store::open(url)?;
    let mut prop = Propagation::new(scene.clone(), spec.options.clone())?;
    let mut job = FieldJob::create(&store, &prop, spec.encoding)?;
    // As `vlf propagate` and the service do (the service's jobs of this bench compact too).
    if !spec.keep_checkpoints {
        job.set_compact(true)?;
    }
    let mut iterations = Vec::new();
    let mut phases = Vec::new();
    let mut snapshots = SnapshotWriter::new();
    while !prop.finished() {
        let t = Instant::now();
        step(&mut prop)?;
        // What the loop waits for: this snapshot encoded, the one before committed.
        let writing = Instant::now();
        snapshots.write(&mut job, &prop)?;
        if prop.finished() {
            snapshots.finish(&mut job)?;
        }
        let written = writing.elapsed().as_secs_f64();
        iterations.push(IterationRecord {
            seconds: t.elapsed().as_secs_f64(),
            ..IterationRecord::default()
        });
        phases.push((prop.phase_times.last().copied().unwrap_or_default(), written));
    }
    let last = prop.checkpoint();
    let perturbed = Some(prop.plan.perturbation);
    job.finish(&prop.into_field(), false)?;
    let sample = Sample {
        phases,
        perturbed,
        ..Sample::ended(started, iterations, &store)
    };
    forget(&store, job.id())?;
    Ok((sample, last))
}

/// The embedded service over the bench's store.
fn service(
    runtime: &tokio::runtime::Runtime,
    url: &str,
    scene: &Scene,
    spec: &JobSpec,
    workers: Workers,
) -> Result<(Sample, Checkpoint)> {
    let started = Started::now();
    let store = Store::open(url)?;
    let job = EmbeddedJob::New(scene.clone(), spec.clone());
    let Embedded {
        id,
        store,
        iterations,
        worker_process_cpu_seconds,
    } = runtime.block_on(embedded(store, job, workers, Follow::Quiet))?;
    let count = iterations.len() as u32;
    // Taken before the check below reads the store.
    let mut sample = Sample::ended(started, iterations, &store);
    sample.cpu_seconds += worker_process_cpu_seconds;
    let last = FieldJob::open(&store, &id)?.checkpoint(count)?;
    forget(&store, &id)?;
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

/// How `way` compares with `base` over the rounds: the ratios `way[i] / base[i]`, one per round.
struct Ratios {
    median: f64,
    /// A 95 % confidence interval of the median ratio ([`median_interval`]); `None` with fewer
    /// than 6 rounds, which cannot give one.
    interval: Option<(f64, f64)>,
    smallest: f64,
    largest: f64,
}

impl Ratios {
    fn paired(base: &[f64], way: &[f64]) -> Ratios {
        let mut ratios: Vec<f64> = base.iter().zip(way).map(|(b, w)| w / b).collect();
        ratios.sort_by(f64::total_cmp);
        Ratios {
            median: median(ratios.clone()),
            interval: median_interval(ratios.len()).map(|(lo, hi)| (ratios[lo], ratios[hi])),
            smallest: ratios.first().copied().unwrap_or(f64::NAN),
            largest: ratios.last().copied().unwrap_or(f64::NAN),
        }
    }

    /// The table cells: median, interval, smallest–largest.
    fn cells(&self) -> String {
        let interval = match self.interval {
            Some((lo, hi)) => format!("{lo:.2}–{hi:.2}"),
            None => "–".into(),
        };
        format!(
            "{:.2} | {interval} | {:.2}–{:.2}",
            self.median, self.smallest, self.largest
        )
    }
}

/// The order statistics (0-based, of `n` sorted samples) that bound a distribution-free 95 %
/// confidence interval of the median: `[x(i), x(n−1−i)]` misses the median only when `i + 1` or
/// more samples fall on one side of it, which happens with probability `2·P(B ≤ i)` for `B ~
/// Binomial(n, ½)`, whatever the distribution, if the rounds are independent (the pairing takes
/// out the machine's slow spells, which rounds would otherwise share).
/// The largest `i` with `2·P(B ≤ i) ≤ 5 %`: the narrowest such interval. `None` for `n < 6`,
/// where even the whole range misses with more than 5 % (`2 / 2⁵ = 6.25 %` for `n = 5`).
fn median_interval(n: usize) -> Option<(usize, usize)> {
    // P(B = k) for k = 0, 1, …: C(n, k) / 2ⁿ, by the ratio of successive terms.
    let mut term = 0.5f64.powi(n as i32);
    let mut below = 0.0;
    let mut found = None;
    for i in 0..n / 2 {
        below += term;
        if 2.0 * below > 0.05 {
            break;
        }
        found = Some((i, n - 1 - i));
        term *= (n - i) as f64 / (i + 1) as f64;
    }
    found
}

/// One way of running the bench's job.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Way {
    /// `vlf propagate`'s loop (`Propagation::step`: a home of batches per thread, or every batch
    /// shared among the threads where homes would be too small).
    InProcess,
    /// The same loop cut into this many homes, as that many workers cut it.
    Split(usize),
    /// The embedded service with this many workers.
    Service(usize),
}

impl Way {
    fn name(self) -> String {
        match self {
            Way::InProcess => "in-process".into(),
            Way::Split(w) => format!("in-process, cut in {w} homes"),
            Way::Service(1) => "service, 1 worker".into(),
            Way::Service(w) => format!("service, {w} workers"),
        }
    }
}

/// A report's title: the command, the scene and the job's shape, with the batches a pass is
/// cut into (what the workers' balance depends on) and the directions of a stint (what each
/// direction streams through memory).
fn heading(args: &BenchArgs, command: &str) -> String {
    let job = &args.job;
    let batching = vlf_core::propagate::Batching::new(job.directions, job.pass_batches, job.stint_directions);
    format!(
        "# {command}: {} (l = {}, N = {}, m = {}, {} batches a pass, stints of {})\n\n",
        args.scene.display(),
        job.directions,
        job.resolution,
        job.tile,
        batching.count(),
        batching.stint()
    )
}

/// The Markdown report.
fn report(args: &BenchArgs, threads: usize, ways: &[Way], samples: &[Vec<Sample>], plain_after: usize) -> String {
    let mut out = heading(args, "vlf bench");
    let cpu = cpu_name().unwrap_or_else(|| "unknown CPU".into());
    let _ = writeln!(
        out,
        "{threads} threads on {cpu}; `{}` store; median of {} runs each, interleaved. \
         Every run gave the in-process bits.{}{}\n",
        store_url(args),
        args.repeat,
        if args.cotenant {
            " With a co-tenant: a thread computing 30 ms of every 60 throughout (`--cotenant`)."
        } else {
            ""
        },
        if args.worker_processes {
            " The service's workers are processes of their own (`--worker-processes`), each \
             building the job's geometry; a run's times include starting them and their set-up, \
             and their CPU time is added to the runs'."
        } else {
            ""
        }
    );
    let _ = writeln!(
        out,
        "`×` is the median over rounds of each round's ratio to its in-process run (a slow \
         spell of the machine slows both runs of a round); `95 %` is a confidence interval of \
         that median (distribution-free: order statistics of the rounds' ratios; none below 6 \
         rounds), `range` the smallest and largest ratio.\n"
    );
    let base: Vec<f64> = samples[0].iter().map(|s| s.seconds).collect();
    let _ = writeln!(out, "| run | median s | fastest s | × in-process | × 95 % | × range |");
    let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|");
    for (way, runs) in ways.iter().zip(samples) {
        let times: Vec<f64> = runs.iter().map(|s| s.seconds).collect();
        let fastest = times.iter().copied().fold(f64::INFINITY, f64::min);
        let ratios = Ratios::paired(&base, &times);
        let m = median(times);
        let _ = writeln!(out, "| {} | {m:.3} | {fastest:.3} | {} |", way.name(), ratios.cells());
    }
    cpu_table(&mut out, ways, samples, threads, args.cotenant);
    phase_table(&mut out, ways, samples);

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
        let _ = writeln!(out, "| run | median s | × in-process | × 95 % | × range |");
        let _ = writeln!(out, "|---|---:|---:|---:|---:|");
        let base: Vec<f64> = samples[0].iter().map(plain).collect();
        for (way, runs) in ways.iter().zip(samples) {
            let times: Vec<f64> = runs.iter().map(plain).collect();
            let ratios = Ratios::paired(&base, &times);
            let m = median(times);
            let _ = writeln!(out, "| {} | {m:.3} | {} |", way.name(), ratios.cells());
        }
        cut_table(&mut out, ways, samples, &plain);
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
            way.name(),
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
        let _ = write!(header, " {} s |", way.name());
        rule.push_str("---:|");
    }
    let services = || (ways.iter().zip(samples)).filter(|(w, _)| matches!(w, Way::Service(_)));
    for (way, _) in services() {
        let _ = write!(header, " {} blobs / MB |", way.name());
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
        for (_, runs) in services() {
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

/// Where the iterations of the runs in one process spent their time, phase by phase
/// (`vlf_core::propagate::PhaseTimes`, and the snapshot's write): the median over runs of each
/// run's sum over its iterations, and its share of the iterations' time. `other` is what no
/// phase accounts for (progress reports, the loop itself).
fn phase_table(out: &mut String, ways: &[Way], samples: &[Vec<Sample>]) {
    let rows: Vec<(String, [f64; 7])> = (ways.iter().zip(samples))
        .filter(|(_, runs)| runs.iter().all(|s| !s.phases.is_empty()))
        .map(|(way, runs)| {
            let per_run = |f: &dyn Fn(&Sample) -> f64| median(runs.iter().map(f).collect());
            let sum = |f: fn(&(PhaseTimes, f64)) -> f64| move |s: &Sample| s.phases.iter().map(f).sum::<f64>();
            let total = per_run(&|s: &Sample| s.iterations.iter().map(|i| i.seconds).sum());
            let parts = [
                per_run(&sum(|p| p.0.plan)),
                per_run(&sum(|p| p.0.shoot)),
                per_run(&sum(|p| p.0.reduce)),
                per_run(&sum(|p| p.0.finish)),
                per_run(&sum(|p| p.1)),
            ];
            let other = (total - parts.iter().sum::<f64>()).max(0.0);
            let cells = [parts[0], parts[1], parts[2], parts[3], parts[4], other, total];
            (way.name(), cells)
        })
        .collect();
    if rows.is_empty() {
        return;
    }
    let _ = writeln!(
        out,
        "\nWhere the iterations' time goes in one process (median over runs of each run's sum, \
         seconds and share; tracing spans `plan`, `shoot`, `reduce`, `finish` at debug level):\n"
    );
    let _ = writeln!(
        out,
        "| run | plan | shoot | reduce | finish | snapshot write | other | iterations |"
    );
    let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|---:|---:|");
    for (name, cells) in rows {
        let total = cells[6].max(1e-12);
        let mut row = format!("| {name} |");
        for &c in &cells[..6] {
            let _ = write!(row, " {c:.3} ({:.0} %) |", 100.0 * c / total);
        }
        let _ = writeln!(out, "{row} {:.3} |", cells[6]);
    }
}

/// What each run cost in CPU, every thread of the process: the service's extra work shows apart
/// from its waiting, which leaves cores idle (`cores busy` = CPU / wall).
fn cpu_table(out: &mut String, ways: &[Way], samples: &[Vec<Sample>], threads: usize, cotenant: bool) {
    let _ = writeln!(
        out,
        "\nCPU per run: user and system time of every thread of the process (the coordinator's, \
         the workers', the store's{}), paired by round like the wall times; `cores busy` is CPU / \
         wall, out of the {threads} threads' cores:\n",
        if cotenant { ", the co-tenant's" } else { "" }
    );
    let _ = writeln!(
        out,
        "| run | median CPU s | × in-process | × 95 % | × range | cores busy |"
    );
    let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|");
    let base: Vec<f64> = samples[0].iter().map(|s| s.cpu_seconds).collect();
    for (way, runs) in ways.iter().zip(samples) {
        let cpu: Vec<f64> = runs.iter().map(|s| s.cpu_seconds).collect();
        let busy = median(runs.iter().map(|s| s.cpu_seconds / s.seconds.max(1e-9)).collect());
        let ratios = Ratios::paired(&base, &cpu);
        let _ = writeln!(
            out,
            "| {} | {:.3} | {} | {busy:.2} |",
            way.name(),
            median(cpu),
            ratios.cells()
        );
    }
}

/// What the service adds to the cut: each service run of two workers or more over its round's
/// in-process run cut into as many homes, whole and over the plain iterations (`plain`).
fn cut_table(out: &mut String, ways: &[Way], samples: &[Vec<Sample>], plain: &dyn Fn(&Sample) -> f64) {
    let cut_of = |w: usize| ways.iter().position(|&way| way == Way::Split(w));
    let pairs: Vec<(Way, usize, usize)> = (ways.iter().enumerate())
        .filter_map(|(i, &way)| match way {
            Way::Service(w) => cut_of(w).map(|c| (way, c, i)),
            _ => None,
        })
        .collect();
    if pairs.is_empty() {
        return;
    }
    let _ = writeln!(
        out,
        "\nWhat the service adds to the cut: each service run over its round's in-process run cut \
         into as many homes (`in-process, cut in w homes`: the same split of the batches, nothing \
         between the homes), whole runs and the iterations above:\n"
    );
    let _ = writeln!(
        out,
        "| run | whole × cut | × 95 % | × range | iterations × cut | × 95 % | × range |"
    );
    let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|---:|");
    for (way, cut, service) in pairs {
        let whole = |i: usize| samples[i].iter().map(|s| s.seconds).collect::<Vec<f64>>();
        let iterations = |i: usize| samples[i].iter().map(plain).collect::<Vec<f64>>();
        let _ = writeln!(
            out,
            "| {} | {} | {} |",
            way.name(),
            Ratios::paired(&whole(cut), &whole(service)).cells(),
            Ratios::paired(&iterations(cut), &iterations(service)).cells(),
        );
    }
}

/// How the service's workers spent the plain iterations (see `IterationUse`): medians over
/// every plain iteration of every run of a way.
fn workers_table(out: &mut String, ways: &[Way], samples: &[Vec<Sample>], plain_after: usize) {
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
    for (way, runs) in ways.iter().zip(samples).filter(|(w, _)| matches!(w, Way::Service(_))) {
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
            way.name(),
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
    fn the_cpu_clock_is_the_whole_process() {
        // A thread of its own computes until its own CPU clock says 20 ms: the process's clock,
        // read on this thread (which only waits), must have counted them.
        let before = process_cpu_seconds();
        let spun = std::thread::spawn(|| {
            let thread_seconds = || cpu_clock_seconds(rustix::time::ClockId::ThreadCPUTime);
            let start = thread_seconds();
            let mut x = 1u64;
            while thread_seconds() - start < 0.02 {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            }
            thread_seconds() - start
        })
        .join()
        .expect("the spinning thread");
        let counted = process_cpu_seconds() - before;
        assert!(
            spun >= 0.02 && counted >= spun,
            "the thread used {spun} s, the process clock counted {counted} s"
        );
    }

    #[test]
    fn paired_ratios_cancel_a_machine_that_slows_down_between_rounds() {
        // The machine is 3× slower in the last round: each round's ratio is still 1.2.
        let r = Ratios::paired(&[1.0, 1.0, 3.0], &[1.2, 1.2, 3.6]);
        for v in [r.median, r.smallest, r.largest] {
            assert!((v - 1.2).abs() < 1e-12, "{v}");
        }
        assert!(r.interval.is_none(), "three rounds give no interval");
        let r = Ratios::paired(&[1.0, 2.0, 4.0], &[1.1, 2.6, 4.0]);
        assert_eq!((r.median, r.smallest, r.largest), (1.1, 1.0, 1.3));
        assert_eq!(r.cells(), "1.10 | – | 1.00–1.30");
        assert_eq!(median(vec![3.0, 1.0, 2.0, 10.0]), 2.5);
    }

    /// P(B ≤ i) for B ~ Binomial(n, ½), from binomial coefficients built by Pascal's rule (not
    /// the ratio of terms the code uses).
    fn binomial_cdf(n: usize, i: usize) -> f64 {
        let mut row = vec![1.0f64];
        for _ in 0..n {
            let mut next = vec![1.0; row.len() + 1];
            for k in 1..row.len() {
                next[k] = row[k - 1] + row[k];
            }
            row = next;
        }
        row[..=i].iter().sum::<f64>() / 2f64.powi(n as i32)
    }

    #[test]
    fn the_median_interval_covers_95_percent_and_is_the_narrowest_that_does() {
        // The textbook values: 6th to 16th of 21 (97.3 %), 14th to 28th of 41.
        assert_eq!(median_interval(21), Some((5, 15)));
        assert_eq!(median_interval(41), Some((13, 27)));
        assert_eq!(median_interval(5), None);
        assert_eq!(median_interval(6), Some((0, 5)));
        for n in 6..=100 {
            let (lo, hi) = median_interval(n).unwrap_or_else(|| panic!("n = {n}"));
            assert_eq!(hi, n - 1 - lo, "symmetric, n = {n}");
            let coverage = |i: usize| 1.0 - 2.0 * binomial_cdf(n, i);
            assert!(coverage(lo) >= 0.95, "n = {n}: {}", coverage(lo));
            assert!(coverage(lo + 1) < 0.95, "n = {n}: a narrower one covers too");
            assert!(lo < hi && lo <= (n - 1) / 2 && hi >= n / 2, "holds the median, n = {n}");
        }
        for n in 0..6 {
            assert_eq!(median_interval(n), None, "n = {n}");
        }
    }

    #[test]
    fn the_interval_is_read_from_the_sorted_ratios() {
        // Rounds in any order; ratios 1.00, 1.01, …, 1.20 shuffled by a fixed permutation.
        let n = 21;
        let base = vec![2.0; n];
        let way: Vec<f64> = (0..n).map(|i| 2.0 * (1.0 + ((i * 8) % n) as f64 / 100.0)).collect();
        let r = Ratios::paired(&base, &way);
        let (lo, hi) = r.interval.expect("21 rounds");
        assert!((lo - 1.05).abs() < 1e-12 && (hi - 1.15).abs() < 1e-12, "{lo} {hi}");
        assert!((r.median - 1.10).abs() < 1e-12);
        assert_eq!(r.cells(), "1.10 | 1.05–1.15 | 1.00–1.20");
    }
}
