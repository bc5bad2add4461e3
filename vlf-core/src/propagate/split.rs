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
//! batches ([`cut_homes`]), and so does a worker's replica with a long block of its lease
//! (`Propagation::compute_block`).
//!
//! It is also the distributed run's cut without the service: workers take homes by the same
//! rule, so `vlf bench` runs this to tell what the cut costs from what the service adds.

use super::work::{self, BatchSum, IterationWork, MirrorIo, Pass};
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

/// What a propagation keeps from one cut to the next: its home threads and what each batch of
/// a pass cost when last shot (by [`Propagation::step`] or in a worker's block). Behind a lock,
/// as a worker's block is shot through `&self`. A clone of the propagation starts without
/// (threads are not copied).
#[derive(Default)]
pub(crate) struct KeptCut(std::sync::Mutex<CutState>);

#[derive(Default)]
struct CutState {
    threads: Option<HomeThreads>,
    costs: Vec<f64>,
}

impl Clone for KeptCut {
    fn clone(&self) -> Self {
        KeptCut::default()
    }
}

impl KeptCut {
    fn lock(&self) -> std::sync::MutexGuard<'_, CutState> {
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Threads for `homes` homes of `per_home` threads (those kept, if they are that many), and
    /// the costs kept, per batch (0 where none is known).
    fn take(&self, homes: usize, per_home: usize) -> crate::Result<(HomeThreads, Vec<f64>)> {
        let mut state = self.lock();
        let threads = match state.threads.take() {
            Some(t) if t.count() == homes && t.per_home() == per_home => t,
            _ => HomeThreads::new(homes, per_home)?,
        };
        Ok((threads, state.costs.clone()))
    }

    /// Keeps `threads` for the next cut, and what the batches just shot cost.
    fn keep(&self, threads: HomeThreads, costs: impl IntoIterator<Item = (usize, f64)>) {
        let mut state = self.lock();
        state.threads = Some(threads);
        for (batch, cost) in costs {
            if state.costs.len() <= batch {
                state.costs.resize(batch + 1, 0.0);
            }
            state.costs[batch] = cost;
        }
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
    /// [`Propagation::step`] cut into `homes` homes of `per_home` threads each, by what the
    /// batches cost when last shot (evenly the first time).
    pub(super) fn step_cut(&mut self, homes: usize, per_home: usize, progress: impl FnMut(Progress)) -> IterationStats {
        let (mut threads, known) = (self.cut.take(homes, per_home)).expect("the current pool's threads, at most 1024");
        let cut = split_by_cost(&known, work::batch_count(self.directions.len()), homes);
        let (stats, costs) = self
            .step_split(&cut, &mut threads, progress)
            .expect("homes cut by split_by_cost cover the pass in order");
        self.cut.keep(threads, costs.into_iter().enumerate());
        stats
    }

    /// Shoots the aligned block `batches` of `pass` cut into a home per thread of the current
    /// pool, when each gets a few batches ([`cut_homes`]), by what they cost when last shot:
    /// each batch's sum and its share of the block's time, in batch order. `None` when the block is not worth cutting (the
    /// caller shoots it with the threads sharing every batch). What a worker with several threads
    /// does with a block of its lease, as [`Propagation::step`] does with a pass.
    pub(super) fn shoot_block_cut(
        &self,
        work: &IterationWork,
        pass: Pass,
        batches: Range<usize>,
        maps: Option<&mut [MirrorIo]>,
    ) -> crate::Result<Option<Vec<(BatchSum, f64)>>> {
        let threads = rayon::current_num_threads();
        let homes = cut_homes(threads, batches.len());
        if homes < 2 {
            return Ok(None);
        }
        let (mut pools, known) = self.cut.take(homes, threads / homes)?;
        let block_costs: Vec<f64> = batches.clone().map(|b| known.get(b).copied().unwrap_or(0.0)).collect();
        let cut: Vec<Range<usize>> = split_by_cost(&block_costs, batches.len(), homes)
            .into_iter()
            .map(|h| h.start + batches.start..h.end + batches.start)
            .collect();
        let started = Instant::now();
        let shot = self.shoot_homes(work, pass, &cut, maps, &mut pools, |_| {});
        let wall = started.elapsed().as_secs_f64();
        let shot: Vec<(BatchSum, f64)> = match shot {
            Ok(shot) => shot.into_iter().flatten().collect(),
            Err(e) => {
                self.cut.keep(pools, []);
                return Err(e);
            }
        };
        self.cut.keep(pools, batches.zip(shot.iter().map(|(_, cost)| *cost)));
        // The homes ran at once, so their batches' times add up to more than the block took:
        // each batch is given its share of the block's time instead, which keeps the costs'
        // proportions (what homes are cut by) and makes them add up to the worker's time, as a
        // report's seconds must.
        let threads_time: f64 = shot.iter().map(|(_, cost)| cost).sum();
        let share = if threads_time > 0.0 { wall / threads_time } else { 0.0 };
        Ok(Some(shot.into_iter().map(|(sum, cost)| (sum, cost * share)).collect()))
    }

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
        let l = self.directions.len();
        let span = |home: &Range<usize>| match home.is_empty() {
            true => 0..0,
            false => work.batch_range(home.start, l).start..work.batch_range(home.end - 1, l).end,
        };
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
                                    let range = work.batch_range(batch, l);
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
