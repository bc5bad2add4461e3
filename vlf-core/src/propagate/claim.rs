//! How one process's threads shoot a run of batches: every thread **claims** the next stint (a
//! few consecutive directions of a batch, [`super::Batching`]) the moment it is done with one,
//! and each batch adds its stints up **in order** as they arrive.
//!
//! Why: the bits of an iteration are fixed by its batch sums, each `Σ_k stint_k` over the
//! batch's stints in order from zero (see [`super::Batching`]). The first schedules kept that
//! order by meeting: the threads shared a batch CHUNK directions at a time and waited at the end
//! of every chunk for its slowest direction (with 16 threads, one direction each: every chunk
//! waited for the slowest of 16), or each thread took a home of whole batches cut by what they
//! cost the iteration before (too few batches for more than four threads, and wrong after a
//! pass of another shape). Here nothing waits for a stint but the sum of its own batch:
//!
//! - **Claiming.** The stints are dealt in a fixed order ([`claim_order`]) through one atomic
//!   counter; a thread computes its stint into a buffer of its own
//!   (`Propagation::shoot_stint`, the kernel every schedule shares).
//! - **Adding in order.** A finished stint is handed to its batch. Whichever thread hands over
//!   the batch's next stint in order adds it, and any that were waiting behind it, into the
//!   batch's sum (one thread at a time per batch; the others leave theirs and go on claiming).
//!   So each texel's additions happen in stint order, and the sums are the bits of every other
//!   schedule, on any number of threads.
//! - **Several batches at once.** One batch takes one addition at a time, so the threads claim
//!   round-robin across a group of up to `threads` batches: with as many batches as threads,
//!   each batch receives about one stint per stint's time, and its additions (a pass over the
//!   texels, a fraction of a stint's shooting) keep up.
//! - **Bounded memory.** A stint that finished ahead of an earlier one of its batch waits
//!   with its buffer; at most `2 · threads` buffers are out at once (a thread that would take
//!   another waits for one to come back). A batch's sum folds into the run's reduction tree as
//!   soon as it is complete, merged with its sibling node once that is complete too
//!   ([`Nodes`]: the bits of absorbing the batches one by one, in any order of completion). So
//!   a run holds the sums of the batches being added (about one per thread), the complete
//!   nodes whose siblings still miss a batch (at most `log2(batches)` per incomplete batch;
//!   the batches are claimed group by group, so few are incomplete at once), and the buffers:
//!   not one sum per batch, however many batches a pass is cut into.
//! - **Why it cannot stall.** A thread borrows its buffer before it claims, and within a batch
//!   the stints are claimed in order: so whenever a stint waits, the oldest unadded stint of
//!   its batch is already claimed, and the thread shooting it holds its buffer and is not
//!   waiting. That holds as long as shooting a stint never blocks nor yields to other rayon
//!   work (no `join`, `scope` or parallel iterator inside `Propagation::shoot_stint`): a thread
//!   that did could pick up another claiming loop and wait for a buffer while its own stint
//!   stays unfinished. The factor 2 is for
//!   throughput; any cap of at least one buffer a thread is live. A thread that fails or panics
//!   wakes the waiting ones, which then stop.

use super::Propagation;
use super::output::BatchSum;
use super::reduce::{Nodes, is_aligned_block};
use super::shoot::Flow;
use super::work::{DirectionScratch, IterationWork, MirrorIo, Pass, add_and_clear, cleared, split_by_stint};
use crate::scene::Rgb;
use std::collections::BTreeMap;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::Instant;

/// A stint to claim: its batch (index within the run of batches), its index among the run's
/// stints, and its directions.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Claim {
    pub batch: usize,
    pub stint: usize,
    pub directions: Range<usize>,
}

/// The order in which threads claim the stints of consecutive batches (`stints`, per batch its
/// stints in order, none empty): the batches in groups of `width`, and within a group
/// round-robin, the first stint of each batch, then the second of each, and so on.
pub(crate) fn claim_order(stints: &[Vec<Range<usize>>], width: usize) -> Vec<Claim> {
    let width = width.max(1);
    let mut first = Vec::with_capacity(stints.len());
    let mut count = 0;
    for batch in stints {
        first.push(count);
        count += batch.len();
    }
    let mut order = Vec::with_capacity(count);
    for (g, group) in stints.chunks(width).enumerate() {
        let longest = group.iter().map(Vec::len).max().unwrap_or(0);
        for k in 0..longest {
            for (i, batch) in group.iter().enumerate() {
                if let Some(directions) = batch.get(k) {
                    let b = g * width + i;
                    order.push(Claim {
                        batch: b,
                        stint: first[b] + k,
                        directions: directions.clone(),
                    });
                }
            }
        }
    }
    order
}

/// A stint shot, waiting to be added to its batch's sum.
struct Shot {
    buf: Vec<Rgb>,
    /// Its directions' flows, in order.
    flows: Vec<Flow>,
    /// One past its last direction: where the batch's next stint starts.
    end: usize,
    seconds: f64,
}

/// One batch's sum as it grows.
struct Sum {
    /// The first direction of the stint to add next.
    next: usize,
    /// Stints shot ahead of `next`, by first direction.
    waiting: BTreeMap<usize, Shot>,
    /// Σ of the stints before `next`, from zero (`None` before the first, and while the
    /// adding thread adds to it outside the lock).
    texels: Option<Vec<Rgb>>,
    flow: Flow,
    /// Seconds the batch's directions took to shoot, added up over the threads.
    seconds: f64,
    /// A thread is adding to `texels`.
    adding: bool,
    /// One past the batch's last direction.
    end: usize,
}

/// The run's complete batch sums, folded into its reduction tree as they complete.
struct Fold {
    /// The tree's complete nodes over the run's batches (indices within the run).
    nodes: Nodes,
    /// Per batch of the run, the seconds its directions took to shoot, over the threads.
    seconds: Vec<f64>,
}

/// The texel-sized buffers lent to the threads: at most `cap` out at once. Every buffer in
/// `free` holds the field's texels, all zero: a stint's buffer is cleared as it is added to its
/// batch's sum ([`add_and_clear`]), so the next stint need not clear it again.
struct Buffers {
    free: Vec<Vec<Rgb>>,
    out: usize,
}

/// What the threads share while they shoot a run of batches.
struct Claims<'m, 'x> {
    order: Vec<Claim>,
    next: AtomicUsize,
    /// Directions added to their sums so far (what progress reports).
    added: AtomicUsize,
    sums: Vec<Mutex<Sum>>,
    fold: Mutex<Fold>,
    buffers: Mutex<Buffers>,
    returned: Condvar,
    cap: usize,
    texels: usize,
    /// Per stint of the run, its directions' mirror maps until claimed (none where the pass
    /// shoots none).
    maps: Vec<Mutex<Option<&'m mut [MirrorIo<'x>]>>>,
    failed: AtomicBool,
    error: Mutex<Option<crate::Error>>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Claims<'_, '_> {
    /// A buffer for the next stint, waiting while `cap` are out; `None` once a thread failed.
    fn borrow(&self) -> Option<Vec<Rgb>> {
        let mut b = lock(&self.buffers);
        while b.out >= self.cap && !self.failed.load(Ordering::Acquire) {
            b = self.returned.wait(b).unwrap_or_else(|p| p.into_inner());
        }
        if self.failed.load(Ordering::Acquire) {
            return None;
        }
        b.out += 1;
        let free = b.free.pop();
        drop(b);
        Some(free.unwrap_or_else(|| vec![[0.0; 3]; self.texels]))
    }

    /// Returns a buffer to the pool; it must be clear (see [`Buffers`]).
    fn give_back(&self, buf: Vec<Rgb>) {
        let mut b = lock(&self.buffers);
        b.out -= 1;
        b.free.push(buf);
        self.returned.notify_one();
    }

    /// Counts a lent buffer as back though it stays out: it became a batch's sum.
    fn retire(&self) {
        let mut b = lock(&self.buffers);
        b.out -= 1;
        self.returned.notify_one();
    }

    /// Takes `buf`, the texels of a sum merged into its parent, into the pool, cleared, where
    /// the pool is short of its cap: the buffer a batch's first stint took along is replaced
    /// without asking the allocator (whose fresh pages the kernel faults in and clears).
    fn recycle(&self, mut buf: Vec<Rgb>) {
        let room = |b: &Buffers| b.free.len() + b.out < self.cap;
        if buf.len() != self.texels || !room(&lock(&self.buffers)) {
            return;
        }
        buf.fill([0.0; 3]);
        let mut b = lock(&self.buffers);
        if room(&b) {
            b.free.push(buf);
        }
    }

    fn fail(&self, e: crate::Error) {
        lock(&self.error).get_or_insert(e);
        self.stop();
    }

    /// Stops every thread: none claims again, and those waiting for a buffer wake.
    fn stop(&self) {
        self.failed.store(true, Ordering::Release);
        let _guard = lock(&self.buffers);
        self.returned.notify_all();
    }

    /// Hands the shot of the stint that starts at direction `d` to batch `batch`, and adds
    /// whatever is next in order.
    fn deliver(&self, batch: usize, d: usize, shot: Shot) {
        let mut sum = lock(&self.sums[batch]);
        sum.waiting.insert(d, shot);
        if sum.adding {
            return; // the thread adding will find it
        }
        sum.adding = true;
        loop {
            let next = sum.next;
            let Some(shot) = sum.waiting.remove(&next) else {
                sum.adding = false;
                return;
            };
            sum.next = shot.end;
            let texels = match sum.texels.take() {
                // The batch's first stint: its buffer becomes the sum, `0 + x = x` bit for bit
                // (an addition gives −0 only from two −0, so a buffer cleared to +0 holds none).
                None => {
                    drop(sum);
                    self.retire();
                    shot.buf
                }
                Some(mut texels) => {
                    drop(sum);
                    let mut buf = shot.buf;
                    add_and_clear(&mut texels, &mut buf);
                    self.give_back(buf);
                    texels
                }
            };
            self.added.fetch_add(shot.flows.len(), Ordering::Relaxed);
            sum = lock(&self.sums[batch]);
            sum.texels = Some(texels);
            for flow in &shot.flows {
                sum.flow.add(flow);
            }
            sum.seconds += shot.seconds;
            if sum.next == sum.end {
                // Complete: no stint of the batch is left to wait, nor to add.
                let done = BatchSum {
                    texels: sum.texels.take().unwrap_or_else(|| vec![[0.0; 3]; self.texels]),
                    flow: sum.flow.into(),
                };
                let seconds = sum.seconds;
                sum.adding = false;
                drop(sum);
                self.complete(batch, done, seconds);
                return;
            }
        }
    }

    /// Folds batch `batch`'s complete sum into the run's tree: merged with its sibling if that
    /// is complete, and so on up ([`Nodes`]). The additions happen outside the lock, so the
    /// threads whose batches complete together do not queue behind one another's.
    fn complete(&self, batch: usize, sum: BatchSum, seconds: f64) {
        let mut fold = lock(&self.fold);
        fold.seconds[batch] = seconds;
        let mut next = fold.nodes.put(batch..batch + 1, sum);
        loop {
            match next {
                Ok(None) => return,
                Ok(Some(pair)) => {
                    drop(fold);
                    let ((block, sum), spare) = pair.merge_keeping();
                    self.recycle(spare);
                    fold = lock(&self.fold);
                    next = fold.nodes.put(block, sum);
                }
                Err(e) => {
                    drop(fold);
                    self.fail(crate::Error::Parameter(e));
                    return;
                }
            }
        }
    }

    /// Claims, shoots and delivers stints until none is left (or a thread failed).
    fn work(&self, prop: &Propagation, work: &IterationWork, pass: Pass, mut heard: impl FnMut(usize)) {
        // A panic here must not leave the others waiting for the buffer it held: they stop,
        // and the scope passes the panic on.
        let _unwinding = StopOnPanic(self);
        let mut scratch = DirectionScratch::default();
        loop {
            if self.failed.load(Ordering::Acquire) {
                return;
            }
            let Some(mut buf) = self.borrow() else { return };
            let k = self.next.fetch_add(1, Ordering::Relaxed);
            let Some(claim) = self.order.get(k) else {
                self.give_back(buf);
                return;
            };
            let maps = match self.maps.get(claim.stint) {
                Some(slot) => lock(slot).take(),
                None => None,
            };
            let started = Instant::now();
            let directions = claim.directions.clone();
            match prop.shoot_stint(work, pass, directions.clone(), maps, &mut buf, &mut scratch) {
                Ok(flows) => {
                    let seconds = started.elapsed().as_secs_f64();
                    let shot = Shot {
                        buf,
                        flows,
                        end: directions.end,
                        seconds,
                    };
                    self.deliver(claim.batch, directions.start, shot);
                    heard(self.added.load(Ordering::Relaxed));
                }
                Err(e) => {
                    cleared(&mut buf, self.texels);
                    self.give_back(buf);
                    self.fail(e);
                    return;
                }
            }
        }
    }
}

/// Stops the claims when dropped by a panic.
struct StopOnPanic<'c, 'm, 'x>(&'c Claims<'m, 'x>);

impl Drop for StopOnPanic<'_, '_, '_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.stop();
        }
    }
}

impl Propagation {
    /// Shoots the aligned block `batches` of `pass` on the current rayon pool's threads,
    /// stints claimed one at a time (see the module docs): the block's node sum (the bits of
    /// absorbing each batch's [`Propagation::run_batch`] in order) and per batch the seconds its
    /// directions took to shoot, added up over the threads. `maps` are the mirror maps of the
    /// batches' directions, in order, when the pass shoots them. `progress` hears, on the
    /// calling thread, how many directions are added to their sums so far: between the stints
    /// that thread shoots, and once more at the end with all of them.
    pub(crate) fn shoot_claimed(
        &self,
        work: &IterationWork,
        pass: Pass,
        batches: Range<usize>,
        maps: Option<&mut [MirrorIo]>,
        mut progress: impl FnMut(usize),
    ) -> crate::Result<(BatchSum, Vec<f64>)> {
        if !is_aligned_block(&batches, work.batches()) {
            return Err(crate::Error::Parameter(format!(
                "batches {batches:?} are not an aligned block of the {} batches",
                work.batches()
            )));
        }
        let ranges: Vec<Range<usize>> = batches.clone().map(|b| work.batch_range(b)).collect();
        if let Some(b) = ranges.iter().position(|r| r.is_empty()) {
            return Err(crate::Error::Parameter(format!(
                "batch {} out of range ({} batches)",
                batches.start + b,
                work.batches()
            )));
        }
        let count = match (ranges.first(), ranges.last()) {
            (Some(a), Some(b)) => b.end - a.start,
            _ => unreachable!("an aligned block holds a batch"),
        };
        if let (Pass::Shoot, true) = (pass, work.uses_mirror_maps())
            && maps.as_ref().is_none_or(|m| m.len() != count)
        {
            return Err(crate::Error::Parameter(format!(
                "batches {batches:?} need the mirror maps of their {count} directions"
            )));
        }
        let threads = rayon::current_num_threads().max(1);
        let stints: Vec<Vec<Range<usize>>> = batches.clone().map(|b| work.batching().stints(b).collect()).collect();
        // Each stint's mirror maps, its own slice of `maps`.
        let maps = maps
            .and_then(|maps| split_by_stint(maps, stints.iter().flatten()))
            .map(|own| own.into_iter().map(|m| Mutex::new(Some(m))).collect());
        let claims = Claims {
            order: claim_order(&stints, threads),
            next: AtomicUsize::new(0),
            added: AtomicUsize::new(0),
            sums: ranges
                .iter()
                .map(|r| {
                    Mutex::new(Sum {
                        next: r.start,
                        waiting: BTreeMap::new(),
                        texels: None,
                        flow: Flow::default(),
                        seconds: 0.0,
                        adding: false,
                        end: r.end,
                    })
                })
                .collect(),
            fold: Mutex::new(Fold {
                nodes: Nodes::new(ranges.len()),
                seconds: vec![0.0; ranges.len()],
            }),
            buffers: Mutex::new(Buffers {
                free: self.buffers.take_cleared(self.atlas.texels),
                out: 0,
            }),
            returned: Condvar::new(),
            cap: 2 * threads,
            texels: self.atlas.texels,
            maps: maps.unwrap_or_default(),
            failed: AtomicBool::new(false),
            error: Mutex::new(None),
        };
        let mut reported = 0;
        rayon::in_place_scope(|scope| {
            for _ in 1..threads {
                scope.spawn(|_| claims.work(self, work, pass, |_| {}));
            }
            // The calling thread claims too, and passes the progress on.
            claims.work(self, work, pass, |added| {
                if added > reported {
                    reported = added;
                    progress(added);
                }
            });
        });
        let error = lock(&claims.error).take();
        let Claims { fold, buffers, cap, .. } = claims;
        // Kept for the next pass, no more than it may lend (a pool of fewer threads next time
        // leaves the rest to be freed).
        let Buffers { mut free, out } = buffers.into_inner().unwrap_or_else(|p| p.into_inner());
        debug_assert!(out == 0 || error.is_some(), "{out} buffers lent and never returned");
        free.truncate(cap);
        self.buffers.keep_clean(free);
        if let Some(e) = error {
            return Err(e);
        }
        let Fold { nodes, seconds } = fold.into_inner().unwrap_or_else(|p| p.into_inner());
        let Some(root) = nodes.root() else {
            return Err(crate::Error::Parameter(format!(
                "batches {batches:?} of {pass:?}: not every batch was shot"
            )));
        };
        if count > reported {
            progress(count);
        }
        Ok((root, seconds))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn claims_go_round_robin_within_groups_of_batches() {
        // Three batches: stints of one direction, then of two (the last ones short).
        let stints = [vec![0..1, 1..2, 2..3], vec![3..5, 5..6], vec![6..8, 8..10, 10..11]];
        let got = |width| -> Vec<(usize, usize, usize)> {
            claim_order(&stints, width)
                .into_iter()
                .map(|c| (c.batch, c.stint, c.directions.start))
                .collect()
        };
        assert_eq!(
            got(2),
            [
                (0, 0, 0),
                (1, 3, 3),
                (0, 1, 1),
                (1, 4, 5),
                (0, 2, 2),
                (2, 5, 6),
                (2, 6, 8),
                (2, 7, 10)
            ]
        );
        // One thread: plain direction order.
        let one: Vec<usize> = got(1).into_iter().map(|(_, _, d)| d).collect();
        assert_eq!(one, [0, 1, 2, 3, 5, 6, 8, 10]);
        // Every stint exactly once, with its own index and directions, whatever the width.
        let all: Vec<Range<usize>> = stints.iter().flatten().cloned().collect();
        for width in 1..6 {
            let mut claims = claim_order(&stints, width);
            claims.sort_by_key(|c| c.stint);
            let directions: Vec<Range<usize>> = claims.iter().map(|c| c.directions.clone()).collect();
            assert_eq!(directions, all, "width {width}");
            assert!(claims.iter().enumerate().all(|(k, c)| c.stint == k), "width {width}");
        }
    }
}
