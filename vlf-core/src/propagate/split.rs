//! An iteration cut the way workers cut it, with nothing between them: every pass's
//! batches split into contiguous **homes**, each home shot left to right on a thread of its
//! own, the batch sums absorbed in batch order afterwards. The bits are those of
//! [`Propagation::step`], whose batch sums are absorbed in the same order (`tests/distributed.rs`).
//!
//! Why it exists: to tell apart the two things a distributed run pays on top of the in-process
//! loop. In [`Propagation::step`] every batch's directions are shared among all the threads,
//! which steal work from one another, so no thread waits while another has directions left.
//! Workers that each take a contiguous run of whole batches (the homes the coordinator cuts,
//! keeping a worker on the directions whose mirror maps it holds) cannot: the iteration waits
//! for the slowest home, however fast the service is, and a batch is the smallest piece that
//! can move. [`Propagation::step_split`] pays that and nothing else, so `vlf bench --split`
//! shows what the cut itself costs, and what the service adds beyond it.

use super::work::{self, BatchSum};
use super::{IterationStats, Propagation};
use crate::scene::Rgb;
use std::ops::Range;
use std::time::Instant;

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
    /// them by what workers report.
    pub fn step_split(
        &mut self,
        homes: &[Range<usize>],
        threads: &mut HomeThreads,
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
        for pass in work.passes() {
            let this = &*self;
            let work_now = &work;
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
                                        (sum, shooting.elapsed().as_secs_f64())
                                    })
                                    .collect()
                            })
                        })
                    })
                    .collect();
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
