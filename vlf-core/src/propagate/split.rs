//! An iteration cut the way workers cut it, with nothing between them: every pass's
//! batches split into contiguous **homes**, each home shot left to right on a thread of its
//! own, the batch sums absorbed in batch order afterwards. The bits are those of
//! [`Propagation::step`], whose batch sums are absorbed in the same order (`tests/distributed.rs`).
//!
//! Why it exists: in [`Propagation::step_shared`] every batch's directions are shared among all
//! the threads, CHUNK at a time, and the threads meet at the end of every chunk (its buffers
//! are then added up in direction order): each meeting waits for the slowest direction of the
//! chunk. A thread that owns whole batches never waits within a pass; what it risks instead is
//! ending the pass before the others, as a batch is the smallest piece that can move. The
//! homes are cut by what each batch cost the last time ([`split_by_cost`]), which batches
//! repeat closely from one iteration to the next. On two threads the cut is the faster
//! (×0.97 of the shared loop's time per iteration for the mirror scene, ×0.92 for the office,
//! `docs/bench`), so [`Propagation::step`] cuts when every thread gets a home of a few
//! batches ([`cut_homes`]).
//!
//! It is also the distributed run's cut without the service: workers take homes by the same
//! rule, so `vlf bench` runs this to tell what the cut costs from what the service adds.

use super::work::{self, BatchSum};
use super::{IterationStats, Progress, Propagation};
use crate::scene::Rgb;
use std::ops::Range;
use std::time::Instant;

/// Batches a home must have, at least, for [`Propagation::step`] to cut a pass into homes:
/// enough that the split by cost can even out batches whose costs differ twofold (the mirror
/// scene's first quarter shoots in half the time of its last).
pub const HOME_BATCHES: usize = 4;

/// How many homes [`Propagation::step`] cuts a pass of `batches` batches into on `threads`
/// threads: one per thread when each then holds at least [`HOME_BATCHES`] batches, else 1 (the
/// threads share every batch).
pub fn cut_homes(threads: usize, batches: usize) -> usize {
    match threads > 1 && batches >= HOME_BATCHES * threads {
        true => threads,
        false => 1,
    }
}

/// A pass of `batches` batches split into `parts` runs of consecutive batches of equal cost, in
/// order (some empty when there are more parts than batches). A batch costs the `seconds` last
/// measured for it, or the mean of those measured (all alike before any): batches differ — the
/// mirror scene's first quarter shoots in half the time of its last — and equal runs had one of
/// two workers wait for the other every iteration. Part `r` starts at the batch boundary nearest
/// to `r / parts` of the total cost. The coordinator cuts a shooting pass into the workers'
/// homes by this rule, and [`Propagation::step`] into its threads'.
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

/// What [`Propagation::step`] keeps from one cut iteration to the next: its home threads and
/// what each batch cost. A clone of the propagation starts without (threads are not copied).
#[derive(Default)]
pub(crate) struct KeptCut {
    threads: Option<HomeThreads>,
    costs: Vec<f64>,
}

impl Clone for KeptCut {
    fn clone(&self) -> Self {
        KeptCut::default()
    }
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
        let mut work = self.iteration_work();
        let batches = work.batches();
        check_homes(homes, batches, threads.count())?;
        let l = self.directions.len();
        let directions = |home: &Range<usize>| match home.is_empty() {
            true => 0..0,
            false => work.batch_range(home.start, l).start..work.batch_range(home.end - 1, l).end,
        };
        let spans: Vec<Range<usize>> = homes.iter().map(directions).collect();
        let mut maps = self.gathered_maps(&work);
        let mut costs = vec![0.0; batches];
        let passes = work.passes();
        let (iteration, total) = (work.index, passes.len() * l);
        for (p, &pass) in passes.iter().enumerate() {
            let this = &*self;
            let work_now = &work;
            // The homes say what they finished; this thread passes it on as it comes.
            let (finished, hear) = std::sync::mpsc::channel::<usize>();
            let shot: Vec<Vec<(BatchSum, f64)>> = std::thread::scope(|scope| {
                // Each home's mirror maps, apart: the homes' directions are consecutive.
                let mut rest = maps.as_deref_mut();
                let running: Vec<_> = (homes.iter().zip(&spans))
                    .zip(threads.pools.iter().zip(threads.buffers.iter_mut()))
                    .map(|((home, span), (pool, buffers))| {
                        let mut own = rest.take().map(|r| {
                            let (own, after) = r.split_at_mut(span.len());
                            rest = Some(after);
                            own
                        });
                        let finished = finished.clone();
                        scope.spawn(move || {
                            pool.install(|| {
                                home.clone()
                                    .map(|batch| {
                                        let range = work_now.batch_range(batch, l);
                                        let at = range.start - span.start..range.end - span.start;
                                        let mut io = own.as_mut().map(|m| work::mirror_io(&mut m[at]));
                                        let shooting = Instant::now();
                                        let sum = this
                                            .run_batch_with(work_now, pass, batch, io.as_deref_mut(), buffers)
                                            .expect("batches of this process's own work are well-formed");
                                        let _ = finished.send(range.len());
                                        (sum, shooting.elapsed().as_secs_f64())
                                    })
                                    .collect()
                            })
                        })
                    })
                    .collect();
                drop(finished);
                let mut done = p * l;
                for directions in hear {
                    done += directions;
                    progress(Progress {
                        iteration,
                        directions_done: done,
                        directions_total: total,
                    });
                }
                running
                    .into_iter()
                    .map(|home| home.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)))
                    .collect()
            });
            for (home, sums) in homes.iter().zip(shot) {
                for (batch, (sum, cost)) in home.clone().zip(sums) {
                    work.absorb(pass, batch..batch + 1, sum)
                        .expect("this process absorbs its batches in order");
                    costs[batch] = cost;
                }
            }
        }
        Ok((self.end_step(work, maps, started), costs))
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
    /// [`Propagation::step`] cut into `homes` homes of `per_home` threads each, by what the
    /// batches cost in the last cut iteration (evenly the first time).
    pub(super) fn step_cut(&mut self, homes: usize, per_home: usize, progress: impl FnMut(Progress)) -> IterationStats {
        let mut threads = match self.cut.threads.take() {
            Some(t) if t.count() == homes && t.per_home() == per_home => t,
            _ => HomeThreads::new(homes, per_home).expect("the current pool's threads, at most 1024"),
        };
        let batches = work::batch_count(self.directions.len());
        let cut = split_by_cost(&self.cut.costs, batches, homes);
        let (stats, costs) = self
            .step_split(&cut, &mut threads, progress)
            .expect("homes cut by split_by_cost cover the pass in order");
        self.cut = KeptCut {
            threads: Some(threads),
            costs,
        };
        stats
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

    #[test]
    fn a_pass_is_cut_only_when_every_thread_gets_a_few_batches() {
        assert_eq!(cut_homes(1, 16), 1, "one thread: nothing to cut");
        assert_eq!(cut_homes(2, 16), 2);
        assert_eq!(cut_homes(4, 16), 4);
        assert_eq!(cut_homes(5, 16), 1, "homes of 3 batches could not even out their costs");
        assert_eq!(cut_homes(16, 16), 1);
        assert_eq!(cut_homes(16, 64), 16);
        assert_eq!(cut_homes(2, 4), 1);
        assert_eq!(cut_homes(0, 16), 1);
    }
}
