//! The batches of an open pass and how a lease is cut from them: which batch a worker starts
//! at (its home, the batches it shot last time), how far a lease runs, how much of it is
//! committed, and how long a block may be. Plain data and pure functions; the [`super::Scheduler`]
//! holds them under its lock.

use super::{LeaseEntry, WorkerEntry};
use std::collections::HashMap;
use std::ops::Range;
use std::time::Duration;
use vlf_core::propagate::{Pass, split_by_cost};

/// What the scheduler remembers of a job's shooting passes, per batch.
#[derive(Default)]
pub(super) struct Shooting {
    /// The worker that computed it last: it keeps the batch's mirror maps (`vlf_store::Replica`),
    /// so leasing it the same batches again saves reading them back.
    pub(super) shooters: Vec<Option<String>>,
    /// Compute seconds of its last lease, shared equally among that lease's batches: what
    /// [`home`] splits the pass by.
    pub(super) seconds: Vec<f64>,
}

impl Shooting {
    /// Records that `worker` shot `batches` of a pass of `len` batches in `seconds`, each batch
    /// what `costs` says (when it has one cost per batch), else an even share.
    pub(super) fn record(&mut self, worker: &str, batches: Range<usize>, len: usize, seconds: f64, costs: &[f64]) {
        if self.shooters.len() < len {
            self.shooters.resize(len, None);
            self.seconds.resize(len, 0.0);
        }
        let share = seconds / batches.len().max(1) as f64;
        let per_batch = costs.len() == batches.len();
        for (i, b) in batches.enumerate() {
            self.shooters[b] = Some(worker.to_string());
            let cost = if per_batch { costs[i] } else { share };
            if cost.is_finite() && cost > 0.0 {
                self.seconds[b] = cost;
            }
        }
    }
}

pub(super) struct PassRun {
    pub(super) snapshot: u32,
    pub(super) pass: Pass,
    pub(super) batches: Vec<Batch>,
    /// The blocks whose outputs are written, in order (they never overlap).
    pub(super) done_blocks: Vec<Range<usize>>,
    /// How many batches are done.
    pub(super) done: usize,
    /// The blocks of the earlier passes it reads, as absorbed (see [`super::Grant::reads`]).
    pub(super) reads: Vec<(Pass, Vec<Range<usize>>)>,
}

#[derive(Clone, Copy, PartialEq)]
pub(super) enum BatchState {
    Pending,
    Leased(u64),
    Done,
}

pub(super) struct Batch {
    pub(super) state: BatchState,
    /// Failed leases that held this batch.
    pub(super) failures: u32,
    /// Leases that held this batch and expired unreported ([`super::MAX_BATCH_EXPIRIES`]).
    pub(super) expiries: u32,
}

/// The part of a home run committed to a worker when it is leased: all of it for a worker that
/// does not claim (`claims`), else all but its last quarter (rounded down: a run of fewer than 4
/// batches is committed whole). The worker claims
/// that tail as it starts the batch before it ([`super::Scheduler::extend`]); until then the tail can
/// go to an idle worker. One claim per lease, and the batches computed in single steps are
/// the few around it: each claim costs a round trip, each step some setup, and a quarter of a
/// worker's home is more than the cost split mispredicts in the iterations measured.
pub(super) fn first_claim(run: &Range<usize>, claims: bool) -> usize {
    match claims {
        true => run.end - run.len() / 4,
        false => run.end,
    }
}

/// Batches per block for a pass of `batches` batches while `open` batches of the job's open
/// passes are not done yet (the pass's own among them): all of the pass for one worker (a lease
/// per pass), and beyond, a quarter of the open work per worker (`open / 2·workers`, rounded to
/// a power of two, so that a slow worker holds back little) up to the whole pass; and small
/// enough that a block takes at most a quarter of the lease's lifetime at `batch_seconds` per
/// batch. Before the job's first report nothing is known of its speed: blocks of one batch.
///
/// With one pass open, that is a quarter of a pass per worker. A perturbed iteration opens
/// every rotated copy's areas at once, then each copy's shooting as its areas are in: with
/// that much work open, the blocks are large — but several workers each take their home of a
/// pass (`home`), so that a worker shoots the part of a copy whose areas it computed and keeps
/// their subfields, and reads none of them back — and the leases shrink as the open work runs
/// out.
pub fn block_len(batches: usize, open: usize, workers: u32, batch_seconds: Option<f64>, lease: Duration) -> usize {
    let Some(per_batch) = batch_seconds else {
        return 1;
    };
    let by_workers = match workers {
        0 | 1 => batches,
        w => open.max(batches) / (2 * w as usize).next_power_of_two(),
    };
    let budget = lease.as_secs_f64() / 4.0;
    let mut len = by_workers.max(1).next_power_of_two();
    while len > 1 && (len > batches || len as f64 * per_batch > budget) {
        len /= 2;
    }
    len
}

impl PassRun {
    /// The pending batch `worker` should start a lease at, and for a pass of an iteration its
    /// [`home`]. Of such a pass: the first of its home; else the first it shot last time (it keeps
    /// their mirror maps); else the first that no other registered worker shot. Else — rather
    /// than wait — the first pending batch. The survey has no homes.
    ///
    /// Homes matter for mirrors: a direction gathers what arrived from the directions that
    /// reflect into it, which are near it in direction order (cut into 16 batches, the bundled
    /// mirror scene's read from at most their neighbours' neighbours). Two workers that shoot the halves
    /// of the pass read 4 batches of each other's arrivals; leased blocks in the order asked,
    /// they interleave and read nearly everything. As homes stay put while the workers do, a
    /// worker shoots the same batches from iteration to iteration and keeps their maps.
    ///
    /// And for a perturbed iteration's rotated copies: a worker keeps the rotated subfields its
    /// areas of a copy built for the copy's shot (`vlf_core::propagate::rotated`), so the shot
    /// of its home finds the subfields its areas of the same home built.
    pub(super) fn first_pending(
        &self,
        worker: &str,
        shooting: &Shooting,
        workers: &HashMap<String, WorkerEntry>,
    ) -> Option<(usize, Option<Range<usize>>)> {
        let pending = || (0..self.batches.len()).filter(|&b| self.batches[b].state == BatchState::Pending);
        if self.pass == Pass::Survey {
            return pending().next().map(|b| (b, None));
        }
        let shooter = |b: usize| shooting.shooters.get(b).and_then(Option::as_deref);
        let home = home(worker, workers, self.batches.len(), &shooting.seconds);
        let at_home = pending().find(|&b| home.contains(&b));
        let own = || pending().find(|&b| shooter(b) == Some(worker));
        let free = || pending().find(|&b| shooter(b).is_none_or(|w| !workers.contains_key(w)));
        let first = at_home.or_else(own).or_else(free).or_else(|| pending().next())?;
        Some((first, Some(home)))
    }

    /// The largest aligned block of at most `len` batches from `first` (a pending batch) whose
    /// batches are all pending.
    pub(super) fn pending_block(&self, first: usize, len: usize) -> Range<usize> {
        let n = self.batches.len();
        let mut size = len.max(1).next_power_of_two();
        while size > 1
            && (!first.is_multiple_of(size)
                || first + size > n
                || self.batches[first..first + size]
                    .iter()
                    .any(|b| b.state != BatchState::Pending))
        {
            size /= 2;
        }
        first..first + size
    }

    /// The run of pending batches from `first` (a pending batch) to the end of the aligned block
    /// of `len` batches (rounded up to a power of two) that holds it, or to the first batch that
    /// is not pending: what a worker that takes runs is leased. From an aligned `first` it is
    /// [`PassRun::pending_block`]'s block or more; past one (after the first lease of a job, one
    /// batch to learn its speed) it takes the rest of that block in one lease instead of one
    /// lease per aligned piece.
    pub(super) fn pending_run(&self, first: usize, len: usize) -> Range<usize> {
        let size = len.max(1).next_power_of_two();
        let end = ((first / size + 1) * size).min(self.batches.len());
        let pending = self.batches[first..end]
            .iter()
            .take_while(|b| b.state == BatchState::Pending)
            .count();
        first..first + pending.max(1)
    }

    /// The run of pending batches from `first` (a pending batch) up to `end` or to the first batch
    /// that is not pending.
    pub(super) fn pending_run_within(&self, first: usize, end: usize) -> Range<usize> {
        let end = end.clamp(first + 1, self.batches.len());
        let pending = self.batches[first..end]
            .iter()
            .take_while(|b| b.state == BatchState::Pending)
            .count();
        first..first + pending.max(1)
    }

    /// Records that the output of `block` is written.
    pub(super) fn mark_done(&mut self, block: Range<usize>) {
        for b in &mut self.batches[block.clone()] {
            b.state = BatchState::Done;
        }
        self.done += block.len();
        let at = self.done_blocks.partition_point(|b| b.start < block.start);
        self.done_blocks.insert(at, block);
    }
}

/// `worker`'s home in a pass of `batches` batches: the registered workers, in registration
/// order, split the pass by [`split_by_cost`] (all of it for a lone worker): by what its
/// batches cost when last shot, as workers reported it.
pub(super) fn home(
    worker: &str,
    workers: &HashMap<String, WorkerEntry>,
    batches: usize,
    seconds: &[f64],
) -> Range<usize> {
    let mut order: Vec<(u64, &str)> = workers.iter().map(|(id, w)| (w.number, id.as_str())).collect();
    order.sort_unstable();
    let Some(rank) = order.iter().position(|(_, id)| *id == worker) else {
        return 0..batches;
    };
    split_by_cost(seconds, batches, order.len()).swap_remove(rank)
}

/// The open pass a lease belongs to.
pub(super) fn find_run<'a>(passes: &'a mut [PassRun], lease: &LeaseEntry) -> Option<&'a mut PassRun> {
    passes
        .iter_mut()
        .find(|r| (r.snapshot, r.pass) == (lease.snapshot, lease.pass))
}
