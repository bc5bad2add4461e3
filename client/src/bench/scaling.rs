//! `vlf bench --scaling`: what more cores and more workers buy.
//!
//! The bench's job runs `--repeat` times at every thread count in one process (`vlf
//! propagate`'s loop on a pool of its own: 1, 2, 4, … threads and all the cores, or
//! `--scale-threads`) and on every `--workers` count of the embedded service, each worker with
//! `--worker-threads` threads of its own; rounds interleave every setting so that a noisy
//! machine spreads its noise evenly. Every run's field is checked bit for bit against the first.
//!
//! Each table gives the median time, the speed-up `S = p₀ · T₀ / T_p` over the first setting
//! (`p₀` its threads or workers: one thread, one worker, unless the list starts higher, when
//! that first row is taken as perfectly parallel), the efficiency `S / p` and the **serial fraction** that
//! Amdahl's law `T_p = T₁ · (f + (1 − f) / p)` gives for it, solved for `f` (the Karp–Flatt
//! metric): `f = (p / S − 1) / (p − 1)`. A constant `f` across `p` is a serial part; an `f`
//! that grows with `p` is contention or imbalance. Both the whole run (set-up and snapshots
//! included) and the iterations alone are given: the iterations are what the propagation
//! scales, the set-up is what every run pays once.

use super::{Sample, Workers, in_process, median, service, without_times};
use anyhow::{Context, Result, bail};
use std::fmt::Write as _;
use vlf_core::propagate::Checkpoint;
use vlf_core::scene::Scene;
use vlf_proto::JobSpec;

/// The settings one scaling table compares: thread counts in one process, or worker counts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Setting {
    Threads(usize),
    Workers { count: usize, threads_each: usize },
}

impl Setting {
    /// What the setting multiplies: threads, or workers.
    fn units(self) -> usize {
        match self {
            Setting::Threads(t) => t,
            Setting::Workers { count, .. } => count,
        }
    }
}

/// The thread counts of the in-process table: `asked`, or 1, 2, 4, … below `cores` and `cores`.
pub(super) fn thread_counts(asked: &[usize], cores: usize) -> Vec<usize> {
    if !asked.is_empty() {
        return asked.to_vec();
    }
    let mut counts: Vec<usize> = std::iter::successors(Some(1), |t| Some(t * 2))
        .take_while(|&t| t < cores)
        .collect();
    counts.push(cores.max(1));
    counts
}

/// Amdahl's serial fraction for a speed-up `speedup` on `p` units (Karp–Flatt); `None` for
/// `p = 1`, where it is undefined.
pub(super) fn serial_fraction(speedup: f64, p: usize) -> Option<f64> {
    (p > 1).then(|| (p as f64 / speedup - 1.0) / (p as f64 - 1.0))
}

/// Runs the scaling cases and returns the report.
pub(super) fn run(
    args: &super::BenchArgs,
    url: &str,
    scene: &Scene,
    spec: &JobSpec,
    runtime: &tokio::runtime::Runtime,
    cores: usize,
) -> Result<String> {
    let threads = thread_counts(&args.scale_threads, cores);
    if threads.iter().any(|t| !(1..=1024).contains(t)) {
        bail!("--scale-threads must list counts between 1 and 1024");
    }
    if !(1..=256).contains(&args.worker_threads) {
        bail!(
            "--worker-threads must be between 1 and 256, got {}",
            args.worker_threads
        );
    }
    let settings: Vec<Setting> = (threads.iter().map(|&t| Setting::Threads(t)))
        .chain(args.workers.iter().map(|&count| Setting::Workers {
            count,
            threads_each: args.worker_threads,
        }))
        .collect();
    let mut samples: Vec<Vec<Sample>> = settings.iter().map(|_| Vec::new()).collect();
    let mut reference: Option<Checkpoint> = None;
    let bar = indicatif::ProgressBar::new((args.repeat * settings.len()) as u64);
    for _ in 0..args.repeat {
        for (i, &setting) in settings.iter().enumerate() {
            let (sample, last) = match setting {
                Setting::Threads(t) => rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .context("cannot start the compute threads")?
                    .install(|| in_process(url, scene, spec))?,
                Setting::Workers { count, threads_each } => {
                    let workers = Workers::new(count, count * threads_each).processes(args.worker_processes);
                    service(runtime, url, scene, spec, workers)?
                }
            };
            let last = without_times(last);
            match &reference {
                None => reference = Some(last),
                Some(r) if *r != last => bail!("{setting:?} changed the bits of the field"),
                Some(_) => {}
            }
            samples[i].push(sample);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    Ok(report(args, cores, &settings, &samples))
}

/// The Markdown report: one table per kind of setting.
fn report(args: &super::BenchArgs, cores: usize, settings: &[Setting], samples: &[Vec<Sample>]) -> String {
    let mut out = super::heading(args, "vlf bench --scaling");
    let cpu = super::cpu_name().unwrap_or_else(|| "unknown CPU".into());
    let _ = writeln!(
        out,
        "{cores} cores on {cpu}; `{}` store; median of {} runs each, interleaved. Every run gave \
         the same bits. Speed-up `S = p₀ · t₀ / t` over the first row (`p₀` its threads or \
         workers: a first row of more than one is taken as perfectly parallel, so list 1 first \
         for a measured base), efficiency `S / p`, and Amdahl's serial fraction `f = (p / S − 1) / (p − 1)`; `iterations` leaves the set-up (scene, subfields, \
         the job's creation) out.\n",
        super::store_url(args),
        args.repeat
    );
    let threads: Vec<usize> = (0..settings.len())
        .filter(|&i| matches!(settings[i], Setting::Threads(_)))
        .collect();
    let workers: Vec<usize> = (0..settings.len())
        .filter(|&i| matches!(settings[i], Setting::Workers { .. }))
        .collect();
    if !threads.is_empty() {
        let _ = writeln!(out, "## Threads in one process (`vlf propagate`)\n");
        table(&mut out, "threads", settings, samples, &threads);
    }
    if let Some(&first) = workers.first() {
        let each = match settings[first] {
            Setting::Workers { threads_each: 1, .. } => "1 thread".to_string(),
            Setting::Workers { threads_each, .. } => format!("{threads_each} threads"),
            Setting::Threads(_) => String::new(),
        };
        let _ = match args.worker_processes {
            false => writeln!(
                out,
                "\n## Workers of the embedded service (`vlf run`), {each} each\n\n\
                 A coordinator and the workers in one process, gRPC on loopback, every batch \
                 output through the store.\n"
            ),
            true => writeln!(
                out,
                "\n## Worker processes (`vlf worker`), {each} each\n\n\
                 A coordinator in this process and every worker a process of its own, as a \
                 cluster's: each builds the job's geometry and opens the store itself; gRPC on \
                 loopback, every batch output through the store. `whole s` includes starting \
                 them and their set-up; CPU s adds the workers' processes.\n"
            ),
        };
        table(&mut out, "workers", settings, samples, &workers);
    }
    out
}

/// One scaling table over the settings `rows` (the first is the base). `CPU s` is the process's
/// CPU time over the run (every thread): where it grows with `p`, the threads work slower
/// (memory, caches, contention); where it stays and the speed-up falls short, they wait (serial
/// parts, imbalance) — `cores busy` = CPU / wall tells the two apart.
fn table(out: &mut String, unit: &str, settings: &[Setting], samples: &[Vec<Sample>], rows: &[usize]) {
    let whole = |i: usize| median(samples[i].iter().map(|s| s.seconds).collect());
    let iterations = |i: usize| {
        median(
            samples[i]
                .iter()
                .map(|s| s.iterations.iter().map(|r| r.seconds).sum())
                .collect(),
        )
    };
    let cpu = |i: usize| median(samples[i].iter().map(|s| s.cpu_seconds).collect());
    let busy = |i: usize| median(samples[i].iter().map(|s| s.cpu_seconds / s.seconds.max(1e-9)).collect());
    let _ = writeln!(
        out,
        "| {unit} | whole s | speed-up | efficiency | serial f | iterations s | speed-up | efficiency | serial f | CPU s | cores busy |"
    );
    let _ = writeln!(out, "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let base = rows[0];
    let p0 = settings[base].units() as f64;
    for &i in rows {
        let p = settings[i].units();
        let mut row = format!("| {p} |");
        for time in [&whole as &dyn Fn(usize) -> f64, &iterations] {
            let t = time(i);
            // Speed-up over the base row, counted from the base's own units (1 when it is 1).
            let speedup = time(base) / t * p0;
            let f = serial_fraction(speedup, p).map_or("–".into(), |f| format!("{f:.3}"));
            let _ = write!(
                row,
                " {t:.3} | {speedup:.2}× | {:.0} % | {f} |",
                100.0 * speedup / p as f64
            );
        }
        let _ = writeln!(out, "{row} {:.2} | {:.2} |", cpu(i), busy(i));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thread_counts_double_up_to_the_cores() {
        assert_eq!(thread_counts(&[], 16), [1, 2, 4, 8, 16]);
        assert_eq!(thread_counts(&[], 6), [1, 2, 4, 6]);
        assert_eq!(thread_counts(&[], 1), [1]);
        assert_eq!(thread_counts(&[3, 5], 16), [3, 5]);
    }

    #[test]
    fn the_serial_fraction_inverts_amdahls_law() {
        // T_p = T_1 (f + (1 − f)/p) for f = 0.1: S = 1 / (0.1 + 0.9/p).
        for p in [2usize, 4, 16] {
            let s = 1.0 / (0.1 + 0.9 / p as f64);
            assert!((serial_fraction(s, p).unwrap() - 0.1).abs() < 1e-12);
        }
        assert!(
            serial_fraction(16.0, 16).unwrap().abs() < 1e-12,
            "perfect scaling: f = 0"
        );
        assert_eq!(serial_fraction(1.0, 1), None);
    }
}
