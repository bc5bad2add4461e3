//! How the directions of a pass are cut into batches: the unit of work a worker leases and of
//! the reduction. Apart from the work of an iteration because everything that walks batches
//! reads it — the iteration's passes, the mirror exchange's look-ups, the store's layout of
//! mirror-map parts — and none of them need the rest of each other.

use std::ops::Range;

/// The unit batch sizes are multiples of, and the most a stint holds; the plain loop
/// ([`super::Propagation::run_batch`]) shoots this many of a batch's stints at once, in
/// parallel, each into a texel-sized buffer, so it bounds that loop's memory, not a batch's
/// size.
pub const CHUNK: usize = 16;

/// How the directions of a pass are cut into batches, the unit of work and of reduction.
///
/// A batch holds `size = max(CHUNK, ⌊(l − 1) / B / CHUNK⌋ · CHUNK)` consecutive directions,
/// `B` being the job's [`super::Options::pass_batches`] (a power of two), and the last batch
/// also takes the remainder: `count = l / size` batches, so `B` of them wherever `l` allows
/// (64 for l ≥ 2049 at the default B = 64; 32 for l = 513, 8 for 129, 2 for 33). Sizes are
/// multiples of [`CHUNK`], so every chunk of a batch keeps all threads busy, and the count is
/// a power of two for every supported `l` and `B` (as the reduction tree wants: `l − 1` is
/// `2·4^k`). A function of the job's options alone, never of a thread or worker count, so the
/// summation order, and therefore the bits, never depend on how the work is spread.
///
/// What `B` trades: each batch's output is a dense texel-sized sum, so more batches cost more
/// node sums through the store and more leases; fewer leave workers unbalanced. With 16 a
/// pass, 8 workers got 2 batches each, and a run of fewer than 4 batches has no last quarter to
/// hand to an idle worker (`server::scheduler`), so the slowest batch set the pace (a balance
/// of 0.77 at 8 workers, docs/scaling.md). In one process the count costs nothing: a pass's
/// batch sums fold into its reduction tree as they complete ([`super::claim`]).
///
/// A batch is in turn cut into **stints**: `s` consecutive directions from the batch's first
/// (the last stint takes what is left), `s` being the job's [`super::Options::stint_directions`]
/// (a power of two up to [`CHUNK`], so that every chunk holds whole stints). One thread shoots a
/// stint's directions in order into one texel buffer, each adding onto what the ones before it
/// left, and the batch's sum is `Σ_k stint_k`, in stint order from zero. Why: the buffer is as
/// large as the field, and adding it to the sum (and clearing it) was a pass over a few hundred
/// kB per direction: 17 % of one thread's time on the Cornell box at l = 2049, N = 128, and a
/// stream through the shared caches that 16 threads contend for. A stint pays it once for `s`
/// directions. Stints of one direction are the sums of earlier builds, to the bit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Batching {
    directions: usize,
    size: usize,
    count: usize,
    stint: usize,
}

impl Batching {
    /// The batches of `directions` directions for a target of `per_pass` batches, each cut into
    /// stints of `stint` directions. Both are powers of two, as [`super::Options::validate`]
    /// requires; any other is taken as the power of two below it (and a stint as [`CHUNK`] at
    /// most), so that the cut stays one.
    pub fn new(directions: usize, per_pass: u32, stint: u32) -> Batching {
        let per_pass = 1usize << (per_pass.max(1).ilog2());
        let size = (directions.saturating_sub(1) / per_pass / CHUNK * CHUNK).max(CHUNK);
        Batching {
            directions,
            size,
            count: (directions / size).max(1),
            stint: (1usize << stint.max(1).ilog2()).min(CHUNK),
        }
    }

    /// Directions per stint (the last stint of a batch may hold fewer).
    pub fn stint(&self) -> usize {
        self.stint
    }

    /// The stints of batch `batch`, in order: `stint` directions each from its first, the last
    /// one running to the batch's end (none past the last batch).
    pub fn stints(&self, batch: usize) -> impl Iterator<Item = Range<usize>> + use<> {
        let range = self.range(batch);
        let stint = self.stint;
        range.clone().step_by(stint).map(move |s| s..(s + stint).min(range.end))
    }

    /// Directions per batch (the last one takes the remainder as well).
    pub fn size(&self) -> usize {
        self.size
    }

    /// Batches per pass.
    pub fn count(&self) -> usize {
        self.count
    }

    /// The directions of batch `batch`: `size` of them from `batch · size`, the last batch
    /// running to `l` (empty past the last).
    pub fn range(&self, batch: usize) -> Range<usize> {
        let start = (batch * self.size).min(self.directions);
        match batch + 1 {
            n if n < self.count => start..start + self.size,
            n if n == self.count => start..self.directions,
            _ => self.directions..self.directions,
        }
    }

    /// The directions of the run of batches `batches` (empty for an empty run).
    pub fn directions_of(&self, batches: Range<usize>) -> Range<usize> {
        match batches.is_empty() {
            true => 0..0,
            false => self.range(batches.start).start..self.range(batches.end - 1).end,
        }
    }

    /// The batch direction `d` is in.
    pub fn batch_of(&self, d: usize) -> usize {
        (d / self.size).min(self.count - 1)
    }
}
