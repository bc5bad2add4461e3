//! An iteration cut the way workers cut it, with nothing between them: every pass's
//! batches split into contiguous **homes**, each home shot left to right on a thread of its
//! own, the batch sums absorbed in batch order afterwards. The bits are those of
//! [`Propagation::step`], whose batch sums are absorbed in the same order (`tests/distributed.rs`).
//!
//! Why it exists: it is the distributed run's cut without the service. The coordinator cuts a
//! pass into the workers' homes by what each batch cost the last time ([`split_by_cost`]), and
//! a worker's threads cannot help another worker: `vlf bench` runs this to tell what the cut
//! costs from what the service adds. Within one process, [`Propagation::step`] does better
//! (stints claimed one at a time, `super::claim`): a home is a whole batch at least, so a
//! thread that ends its home early waits for the others.

use super::output::BatchSum;
use super::work::{self, IterationWork, MirrorIo, Pass};
use super::{IterationStats, Progress, Propagation};
use crate::scene::Rgb;
use std::ops::Range;
use std::time::Instant;

/// A pass of `batches` batches split into `parts` runs of consecutive batches of equal cost, in
/// order (some empty when there are more parts than batches). A batch costs the `seconds` last
/// measured for it, or the mean of those measured (all alike before any): batches differ — the
/// mirror scene's first quarter shoots in half the time of its last — and equal runs had one of
/// two workers wait for the other every iteration. Part `r` starts at the batch boundary nearest
/// to `r / parts` of the total cost. The coordinator cuts a shooting pass into the workers'
/// homes by this rule.
pub fn split_by_cost(seconds: &[f64], batches: usize, parts: usize) -> Vec<Range<usize>> {
    let measured: Vec<f64> = seconds.iter().copied().filter(|s| *s > 0.0).collect();
    let mean = match measured.len() {
        0 => 1.0,
        n => measured.iter().sum::<f64>() / n as f64,
    };
    // Cost before each batch boundary: before[b] is the cost of batches 0..b.
    let mut before = vec![0.0; batches + 1];
    for b in 0..batches {
        let cost = seconds.get(b).copied().filter(|s| *s > 0.0).unwrap_or(mean);
        before[b + 1] = before[b] + cost;
    }
    let parts = parts.max(1);
    let start = |r: usize| -> usize {
        let target = before[batches] * r as f64 / parts as f64;
        (0..=batches)
            .min_by(|&a, &b| (before[a] - target).abs().total_cmp(&(before[b] - target).abs()))
            .unwrap_or(0)
    };
    (0..parts).map(|r| start(r)..start(r + 1)).collect()
}

/// The compute threads of each home (a rayon pool per home, as each worker has its own), and the
/// chunk buffers each keeps from one batch to the next (see `work::KeptBuffers`: allocating them
/// afresh would fault their pages in every time).
pub struct HomeThreads {
    pools: Vec<rayon::ThreadPool>,
    buffers: Vec<Vec<Vec<Rgb>>>,
}

impl HomeThreads {
    /// `count` homes of `threads` threads each.
    pub fn new(count: usize, threads: usize) -> crate::Result<HomeThreads> {
        if !(1..=1024).contains(&count) || !(1..=1024).contains(&threads) {
            return Err(crate::Error::Parameter(format!(
                "{count} homes of {threads} threads: each must be between 1 and 1024"
            )));
        }
        let pools = (0..count)
            .map(|_| rayon::ThreadPoolBuilder::new().num_threads(threads).build())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| crate::Error::Parameter(format!("cannot start the home threads: {e}")))?;
        Ok(HomeThreads {
            pools,
            buffers: vec![Vec::new(); count],
        })
    }

    /// How many homes these threads compute at once.
    pub fn count(&self) -> usize {
        self.pools.len()
    }

    /// The threads of each home.
    pub fn per_home(&self) -> usize {
        self.pools.first().map_or(0, |p| p.current_num_threads())
    }
}

impl Propagation {
    /// Performs one iteration with every pass's batches split into `homes` (contiguous, in
    /// order, covering all the batches; at most one per home of `threads`, and an empty home leaves
    /// its threads idle): each home's batches are shot left to right on its threads, and the batch sums
    /// are absorbed in batch order once every home is done. The same bits as
    /// [`Propagation::step`].
    ///
    /// Returns the iteration's statistics and, per batch, the seconds its last pass took to shoot
    /// it on its home's threads: what the next iteration's homes are cut by, as the coordinator cuts
    /// them by what workers report. `progress` hears of every batch as its home finishes it.
    pub fn step_split(
        &mut self,
        homes: &[Range<usize>],
        threads: &mut HomeThreads,
        mut progress: impl FnMut(Progress),
    ) -> crate::Result<(IterationStats, Vec<f64>)> {
        let started = Instant::now();
        let mut clock = super::PhaseClock::start(started);
        let mut work = self.iteration_work();
        let batches = work.batches();
        check_homes(homes, batches, threads.count())?;
        let l = self.directions.len();
        let mut maps = self.gathered_maps(&work);
        clock.planned();
        let mut costs = vec![0.0; batches];
        let passes = work.passes();
        let (iteration, total) = (work.index, passes.len() * l);
        for (p, &pass) in passes.iter().enumerate() {
            let mut io = maps.as_mut().map(|m| work::mirror_io(m));
            let mut done = p * l;
            let shot = self
                .shoot_homes(&work, pass, homes, io.as_deref_mut(), threads, |directions| {
                    done += directions;
                    progress(Progress {
                        iteration,
                        directions_done: done,
                        directions_total: total,
                    });
                })
                .expect("batches of this process's own work are well-formed");
            drop(io);
            clock.reducing();
            for (home, sums) in homes.iter().zip(shot) {
                for (batch, (sum, cost)) in home.clone().zip(sums) {
                    work.absorb(pass, batch..batch + 1, sum)
                        .expect("this process absorbs its batches in order");
                    costs[batch] = cost;
                }
            }
            clock.reduced();
        }
        clock.shot();
        let stats = self.end_step(work, maps, started);
        self.phase_times.push(clock.finished());
        Ok((stats, costs))
    }
}

/// Refuses homes that are not `threads` (homes) or fewer contiguous runs covering `0..batches` in order.
fn check_homes(homes: &[Range<usize>], batches: usize, threads: usize) -> crate::Result<()> {
    let refuse = |why: String| Err(crate::Error::Parameter(format!("homes {homes:?}: {why}")));
    if homes.len() > threads {
        return refuse(format!("{} homes for {threads} threads", homes.len()));
    }
    let mut next = 0;
    for home in homes {
        if home.start != next || home.end < home.start {
            return refuse(format!("batch {next} is not where a home starts"));
        }
        next = home.end;
    }
    match next == batches {
        true => Ok(()),
        false => refuse(format!("they end at batch {next} of {batches}")),
    }
}

impl Propagation {
    /// Shoots the batches of `pass` in `homes` (consecutive runs, in order), each home on a pool
    /// of `threads` (one per home), its batches left to right into the home's own chunk
    /// buffers. `maps` are the mirror maps of the homes' directions, from the first home's first
    /// direction on (when the pass shoots them): each home gets its part. Returns per home each
    /// batch's sum and the seconds it took to shoot; `finished` hears, on the calling thread, the
    /// directions of every batch as a home finishes it.
    fn shoot_homes(
        &self,
        work: &IterationWork,
        pass: Pass,
        homes: &[Range<usize>],
        maps: Option<&mut [MirrorIo]>,
        threads: &mut HomeThreads,
        mut finished: impl FnMut(usize),
    ) -> crate::Result<Vec<Vec<(BatchSum, f64)>>> {
        let span = |home: &Range<usize>| work.batching().directions_of(home.clone());
        let (done, hear) = std::sync::mpsc::channel::<usize>();
        let shot: Vec<crate::Result<Vec<(BatchSum, f64)>>> = std::thread::scope(|scope| {
            // Each home's mirror maps, apart: the homes' directions are consecutive.
            let mut rest = maps;
            let running: Vec<_> = (homes.iter())
                .zip(threads.pools.iter().zip(threads.buffers.iter_mut()))
                .map(|(home, (pool, buffers))| {
                    let span = span(home);
                    let mut own = rest.take().map(|r| {
                        let (own, after) = r.split_at_mut(span.len());
                        rest = Some(after);
                        own
                    });
                    let done = done.clone();
                    scope.spawn(move || {
                        pool.install(|| {
                            home.clone()
                                .map(|batch| {
                                    let range = work.batch_range(batch);
                                    let at = range.start - span.start..range.end - span.start;
                                    let io = own.as_deref_mut().map(|m| &mut m[at]);
                                    let shooting = Instant::now();
                                    let sum = self.run_batch_with(work, pass, batch, io, buffers)?;
                                    let _ = done.send(range.len());
                                    Ok((sum, shooting.elapsed().as_secs_f64()))
                                })
                                .collect()
                        })
                    })
                })
                .collect();
            drop(done);
            hear.into_iter().for_each(&mut finished);
            running
                .into_iter()
                .map(|home| home.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)))
                .collect()
        });
        shot.into_iter().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_split_by_cost_covers_the_pass_in_order() {
        let costs: Vec<f64> = (0..16).map(|b| 0.001 * (1 + b % 5) as f64).collect();
        for parts in 1..=20 {
            let split = split_by_cost(&costs, 16, parts);
            assert_eq!(split.len(), parts);
            assert_eq!(split[0].start, 0);
            assert_eq!(split[parts - 1].end, 16);
            assert!(split.windows(2).all(|w| w[0].end == w[1].start), "{parts}: {split:?}");
        }
        // Three cheap batches and an expensive one: the expensive one alone.
        assert_eq!(split_by_cost(&[1.0, 1.0, 1.0, 3.0], 4, 2), [0..3, 3..4]);
        // More parts than batches: some are empty.
        assert_eq!(split_by_cost(&[], 2, 4), [0..0, 0..1, 1..1, 1..2]);
        assert_eq!(split_by_cost(&[], 0, 2), [0..0, 0..0]);
    }
}
