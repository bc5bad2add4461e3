//! The fixed reduction tree of a pass: how the batch sums of a pass are added
//! up, so that the bits never depend on who computed what.
//!
//! A pass has `n` batches (`n` a power of two for every supported `l` and
//! [`super::Options::pass_batches`]: see [`super::Batching`]). Their sums are the leaves of a perfect binary tree, and every
//! inner node is `left + right`, texel by texel (and flow by flow):
//!
//! ```text
//!                 S(0..4) = S(0..2) + S(2..4)
//!               /                            \
//!     S(0..2) = S0 + S1              S(2..4) = S2 + S3
//! ```
//!
//! The pass's result is the root. Any **aligned block** of batches — `len` a
//! power of two, starting at a multiple of `len` — is a node of that tree, so
//! a worker that computes a whole block can send the node's sum alone: one
//! output instead of `len`, and the same bits as the leaves sent one by one.
//! That lets the coordinator size its leases to the workers it has (the whole
//! pass for one worker, quarters for two) without changing the field.
//!
//! [`TreeSum`] takes the blocks in order and merges them like a binary
//! counter: it keeps at most `log2(n) + 1` partial sums. [`Nodes`] takes them
//! in any order, merging each with its sibling once both are in: what a
//! process's threads use, whose batches complete in no fixed order.

use super::FlowRecord;
use super::output::{Arrivals, BatchOutput, BatchSum};
use super::work::add_into;
use crate::scene::Rgb;
use std::ops::Range;

/// Whether `block` is a node of the reduction tree over `batches` leaves.
pub fn is_aligned_block(block: &Range<usize>, batches: usize) -> bool {
    let len = block.len();
    len > 0 && len.is_power_of_two() && block.start.is_multiple_of(len) && block.end <= batches
}

/// The aligned blocks of `len` batches (a power of two, at most `batches`)
/// that cover `0..batches`, in order; the last one is shorter when `len`
/// does not divide `batches`, and cut into aligned pieces.
pub fn blocks(batches: usize, len: usize) -> Vec<Range<usize>> {
    let len = len.clamp(1, batches.max(1)).next_power_of_two();
    let mut out = Vec::new();
    let mut start = 0;
    while start < batches {
        // The largest aligned block from `start` that fits.
        let mut size = len;
        while size > 1 && (!start.is_multiple_of(size) || start + size > batches) {
            size /= 2;
        }
        out.push(start..start + size);
        start += size;
    }
    out
}

/// The fewest aligned blocks that cover the run of batches `run`, in order:
/// from the left, each the largest aligned block that starts there and stays
/// inside the run (`1..8` is `1..2`, `2..4`, `4..8`). A lease may hold such a
/// run, which costs one round trip instead of one per block; its outputs are
/// still these nodes of the tree, so the bits stay the same.
pub fn cover(run: Range<usize>) -> Vec<Range<usize>> {
    let mut out = Vec::new();
    let mut start = run.start;
    while start < run.end {
        let mut size = 1;
        while start.is_multiple_of(2 * size) && start + 2 * size <= run.end {
            size *= 2;
        }
        out.push(start..start + size);
        start += size;
    }
    out
}

/// The outputs of a run of batches computed piece by piece, left to right,
/// merged into those of [`cover`]: two neighbours of the same length that
/// form a node of the tree become that node (`left + right`, as [`TreeSum`]
/// adds them). A worker that computes its lease in steps — to learn between
/// them whether it still holds the rest — writes the same outputs, to the bit,
/// as one that computes the run at once.
#[derive(Debug, Default)]
pub struct RunOutputs {
    /// Nodes not yet merged, left to right (their lengths strictly decrease
    /// wherever a merge could apply).
    nodes: Vec<BatchOutput>,
}

impl RunOutputs {
    pub fn new() -> RunOutputs {
        RunOutputs::default()
    }

    /// One past the last batch taken, if any.
    pub fn end(&self) -> Option<usize> {
        self.nodes.last().map(|n| n.batches.end as usize)
    }

    /// Takes the output of the next aligned block of the run: it must start
    /// where the last one ended, of the same iteration and pass.
    pub fn push(&mut self, output: BatchOutput) -> Result<(), String> {
        let block = output.batches.start as usize..output.batches.end as usize;
        // A node of the tree whatever the pass's length (the run's end bounds it).
        if !is_aligned_block(&block, usize::MAX) {
            return Err(format!("batches {block:?} are not an aligned block"));
        }
        if let Some(last) = self.nodes.last()
            && (last.batches.end != output.batches.start
                || last.iteration != output.iteration
                || last.pass != output.pass
                || !same_kind(&last.arrivals, &output.arrivals))
        {
            return Err(format!(
                "batches {block:?} of {:?} (iteration {}) do not follow {:?} of {:?} (iteration {})",
                output.pass, output.iteration, last.batches, last.pass, last.iteration
            ));
        }
        self.nodes.push(output);
        while let [.., left, right] = &self.nodes[..]
            && left.batches.len() == right.batches.len()
            && left.batches.start.is_multiple_of(2 * left.batches.len() as u32)
        {
            let right = self.nodes.pop().expect("two nodes");
            let left = self.nodes.last_mut().expect("two nodes");
            merge(&mut left.sum, &right.sum);
            left.batches.end = right.batches.end;
            match (left.arrivals.as_mut(), right.arrivals) {
                (Some(Arrivals::Settled(l)), Some(Arrivals::Settled(r))) => l.extend(r),
                (Some(Arrivals::Power(l)), Some(Arrivals::Power(r))) => l.extend(r),
                _ => {}
            }
        }
        Ok(())
    }

    /// The outputs: one per block of [`cover`] of the run taken, in order.
    pub fn finish(self) -> Vec<BatchOutput> {
        self.nodes
    }
}

/// Whether two blocks' arrivals are both absent, both settled or both `Φ_in`: what a merge
/// puts together.
fn same_kind(a: &Option<Arrivals>, b: &Option<Arrivals>) -> bool {
    match (a, b) {
        (Some(a), Some(b)) => std::mem::discriminant(a) == std::mem::discriminant(b),
        (a, b) => a.is_some() == b.is_some(),
    }
}

/// Partial sums of one pass, taken in order as aligned blocks.
#[derive(Debug)]
pub struct TreeSum {
    batches: usize,
    next: usize,
    /// Nodes not yet merged, left to right, with their number of leaves
    /// (strictly decreasing).
    stack: Vec<(usize, BatchSum)>,
}

impl TreeSum {
    pub fn new(batches: usize) -> TreeSum {
        TreeSum {
            batches,
            next: 0,
            stack: Vec::new(),
        }
    }

    /// The first batch not taken yet.
    pub fn next(&self) -> usize {
        self.next
    }

    pub fn is_complete(&self) -> bool {
        self.next == self.batches
    }

    /// Takes the sum of `block`, which must start at [`TreeSum::next`] and
    /// be aligned.
    pub fn push(&mut self, block: Range<usize>, sum: BatchSum) -> Result<(), String> {
        if block.start != self.next || !is_aligned_block(&block, self.batches) {
            return Err(format!(
                "batches {block:?} are not the next aligned block (next is {} of {})",
                self.next, self.batches
            ));
        }
        self.next = block.end;
        self.stack.push((block.len(), sum));
        while let [.., (left, _), (right, _)] = self.stack[..]
            && left == right
        {
            let (len, right) = self.stack.pop().expect("two entries");
            let (_, left) = self.stack.last_mut().expect("two entries");
            merge(left, &right);
            self.stack.last_mut().expect("two entries").0 = 2 * len;
        }
        Ok(())
    }

    /// The root: the pass's sum. For a batch count that is not a power of two
    /// the remaining nodes are added left to right.
    pub fn finish(self) -> Option<BatchSum> {
        if !self.is_complete() {
            return None;
        }
        let mut nodes = self.stack.into_iter().map(|(_, s)| s);
        let mut root = nodes.next()?;
        for node in nodes {
            merge(&mut root, &node);
        }
        Some(root)
    }
}

/// Complete nodes of a run's reduction tree, taken in any order: a node whose sibling is in
/// too is merged with it (`left + right`, as [`TreeSum`] adds them), and so on up. So the
/// root has the bits of the leaves pushed in order into a [`TreeSum`]. What waits is bounded by
/// the leaves still missing, not by the order they come in: a node is held only while its
/// sibling's subtree misses a leaf, so each missing leaf holds at most `log2(n)` nodes (one
/// per level on its way to the root) — `log2(n)` sums when the last leaf is late, where taking
/// the leaves in order would hold the `n − 1` that came before it.
///
/// The merges themselves happen outside: [`Nodes::put`] hands back the pair to merge, so a
/// caller that keeps `Nodes` under a lock adds the texels without holding it.
#[derive(Debug)]
pub struct Nodes {
    leaves: usize,
    /// Complete nodes not yet merged, by first leaf: (leaves, sum).
    done: std::collections::BTreeMap<usize, (usize, BatchSum)>,
}

/// Two sibling nodes, to be added up into their parent ([`Pair::merge`]) and put back.
#[derive(Debug)]
pub struct Pair {
    parent: Range<usize>,
    left: BatchSum,
    right: BatchSum,
}

impl Pair {
    /// The parent node: its leaves and `left + right`.
    pub fn merge(self) -> (Range<usize>, BatchSum) {
        self.merge_keeping().0
    }

    /// [`Pair::merge`], handing back the right node's texels, which the parent no longer needs:
    /// a buffer of the field's size for whoever wants one.
    pub fn merge_keeping(self) -> ((Range<usize>, BatchSum), Vec<Rgb>) {
        let Pair {
            parent,
            mut left,
            right,
        } = self;
        merge(&mut left, &right);
        ((parent, left), right.texels)
    }
}

impl Nodes {
    /// The nodes of a tree over `leaves` leaves (a power of two).
    pub fn new(leaves: usize) -> Nodes {
        Nodes {
            leaves,
            done: Default::default(),
        }
    }

    /// Takes the complete node `block` (an aligned block of the leaves, given once): the pair to
    /// merge when its sibling is in too (merge it and put the parent back), else `None`.
    pub fn put(&mut self, block: Range<usize>, sum: BatchSum) -> Result<Option<Pair>, String> {
        if !is_aligned_block(&block, self.leaves) || self.done.contains_key(&block.start) {
            return Err(format!(
                "batches {block:?} are not a new aligned block of {} batches",
                self.leaves
            ));
        }
        let len = block.len();
        if len == self.leaves {
            self.done.insert(block.start, (len, sum));
            return Ok(None);
        }
        let sibling = match block.start.is_multiple_of(2 * len) {
            true => block.end,
            false => block.start - len,
        };
        if self.done.get(&sibling).is_none_or(|(l, _)| *l != len) {
            self.done.insert(block.start, (len, sum));
            return Ok(None);
        }
        let (_, other) = self.done.remove(&sibling).expect("looked up above");
        let start = block.start.min(sibling);
        let (left, right) = if sibling < block.start {
            (other, sum)
        } else {
            (sum, other)
        };
        Ok(Some(Pair {
            parent: start..start + 2 * len,
            left,
            right,
        }))
    }

    /// Sums held apart, waiting for a sibling (or the root).
    pub fn held(&self) -> usize {
        self.done.len()
    }

    /// The root, once every leaf is in and merged.
    pub fn root(mut self) -> Option<BatchSum> {
        match self.done.remove(&0) {
            Some((len, sum)) if len == self.leaves => Some(sum),
            _ => None,
        }
    }
}

/// `left += right`: texels and flow.
fn merge(left: &mut BatchSum, right: &BatchSum) {
    add_into(&mut left.texels, &right.texels);
    let (a, b) = (&mut left.flow, &right.flow);
    let add = |x: &mut [f64; 3], y: &[f64; 3]| x.iter_mut().zip(y).for_each(|(x, y)| *x += y);
    add(&mut a.shot, &b.shot);
    add(&mut a.received, &b.received);
    add(&mut a.escaped, &b.escaped);
    add(&mut a.blocked, &b.blocked);
}

impl FlowRecord {
    /// Whether every figure is finite.
    pub fn is_finite(&self) -> bool {
        [self.shot, self.received, self.escaped, self.blocked]
            .iter()
            .flatten()
            .all(|v| v.is_finite())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leaf(v: f64) -> BatchSum {
        BatchSum {
            texels: vec![[v, 0.0, 0.0]],
            flow: FlowRecord {
                shot: [v, 0.0, 0.0],
                ..Default::default()
            },
        }
    }

    fn root(batches: usize, blocks: &[Range<usize>], leaves: &[f64]) -> f64 {
        let mut t = TreeSum::new(batches);
        for b in blocks {
            // A block's sum is its own subtree over the leaves.
            let mut sub = TreeSum::new(b.len());
            for i in 0..b.len() {
                sub.push(i..i + 1, leaf(leaves[b.start + i])).unwrap();
            }
            t.push(b.clone(), sub.finish().unwrap()).unwrap();
        }
        let r = t.finish().unwrap();
        assert_eq!(r.texels[0][0].to_bits(), r.flow.shot[0].to_bits());
        r.texels[0][0]
    }

    /// `n` values whose sum depends on the order of additions.
    fn order_sensitive(n: usize) -> Vec<f64> {
        (0..n)
            .map(|i| match i % 4 {
                0 => 1e16,
                2 => -1e16,
                _ => 1.0 + i as f64 * 0.37,
            })
            .collect()
    }

    /// Puts leaf `i` of value `v` into `nodes` and merges what it completes, as
    /// `claim` does.
    fn put_leaf(nodes: &mut Nodes, i: usize, v: f64) {
        let mut pair = nodes.put(i..i + 1, leaf(v)).unwrap();
        while let Some(p) = pair {
            let (block, sum) = p.merge();
            pair = nodes.put(block, sum).unwrap();
        }
    }

    #[test]
    fn any_cover_by_aligned_blocks_gives_the_same_bits() {
        let leaves = order_sensitive(16);
        let ones: Vec<Range<usize>> = (0..16).map(|i| i..i + 1).collect();
        let reference = root(16, &ones, &leaves);
        for len in [2, 4, 8, 16] {
            assert_eq!(
                root(16, &blocks(16, len), &leaves).to_bits(),
                reference.to_bits(),
                "{len}"
            );
        }
        let mixed = [0..8, 8..10, 10..11, 11..12, 12..16];
        assert_eq!(root(16, &mixed, &leaves).to_bits(), reference.to_bits());
        // And it is the tree, not the left fold.
        let fold = leaves.iter().fold(0.0, |a, b| a + b);
        let tree = {
            let mut level = leaves.clone();
            while level.len() > 1 {
                level = level.chunks(2).map(|p| p[0] + p[1]).collect();
            }
            level[0]
        };
        assert_eq!(reference.to_bits(), tree.to_bits());
        assert_ne!(
            tree.to_bits(),
            fold.to_bits(),
            "the test values must tell the orders apart"
        );
    }

    #[test]
    fn nodes_in_any_order_give_the_bits_of_the_tree_and_hold_few_per_missing_leaf() {
        let leaves = order_sensitive(32);
        let ones: Vec<Range<usize>> = (0..32).map(|i| i..i + 1).collect();
        let reference = root(32, &ones, &leaves);
        // Orders: in order, reversed, the first last, and pseudo-random shuffles.
        let mut orders: Vec<Vec<usize>> =
            vec![(0..32).collect(), (0..32).rev().collect(), (1..32).chain([0]).collect()];
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..20 {
            let mut o: Vec<usize> = (0..32).collect();
            for i in (1..o.len()).rev() {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                o.swap(i, (state % (i as u64 + 1)) as usize);
            }
            orders.push(o);
        }
        for order in &orders {
            let mut nodes = Nodes::new(32);
            for (k, &i) in order.iter().enumerate() {
                put_leaf(&mut nodes, i, leaves[i]);
                let missing = 31 - k;
                assert!(
                    nodes.held() <= (5 * missing).max(1),
                    "{} sums held with {missing} leaves missing",
                    nodes.held()
                );
            }
            let r = nodes.root().unwrap();
            assert_eq!(r.texels[0][0].to_bits(), reference.to_bits(), "{order:?}");
            assert_eq!(r.flow.shot[0].to_bits(), reference.to_bits());
        }
        // The first leaf last: everything else merged into one node per level.
        let mut nodes = Nodes::new(32);
        for (i, &v) in leaves.iter().enumerate().skip(1) {
            put_leaf(&mut nodes, i, v);
        }
        assert_eq!(nodes.held(), 5, "1, 2..4, 4..8, 8..16, 16..32");
        // Blocks that are not new aligned blocks are refused; an incomplete tree has no root.
        assert!(nodes.put(1..2, leaf(0.0)).is_err());
        assert!(nodes.put(0..3, leaf(0.0)).is_err());
        assert!(Nodes::new(4).put(4..5, leaf(0.0)).is_err());
        assert!(nodes.root().is_none());
    }

    /// The output of `block`, summed over its own subtree of `leaves`, with
    /// one part of its arrivals per batch holding the batch number.
    fn block_output(block: Range<usize>, leaves: &[f64]) -> BatchOutput {
        let mut sub = TreeSum::new(block.len());
        for i in 0..block.len() {
            sub.push(i..i + 1, leaf(leaves[block.start + i])).unwrap();
        }
        BatchOutput {
            iteration: 3,
            pass: super::super::Pass::Shoot,
            batches: block.start as u32..block.end as u32,
            sum: sub.finish().unwrap(),
            arrivals: Some(Arrivals::Settled(block.clone().map(part_of).collect())),
        }
    }

    /// The arrivals of batch `b`: its number as power and as the batch it feeds.
    fn part_of(b: usize) -> crate::propagate::specular::BatchArrivals {
        crate::propagate::specular::BatchArrivals {
            exchange: crate::propagate::Exchange {
                incident: [b as f64, 0.0, 0.0],
                reflected: [0.0; 3],
            },
            feeds: vec![b as u32],
        }
    }

    /// Outputs whose arrivals are of different kinds (settled, `Φ_in`, none) are not merged.
    #[test]
    fn a_run_takes_arrivals_of_one_kind() {
        let leaves = [1.0; 4];
        let mut run = RunOutputs::new();
        run.push(block_output(0..1, &leaves)).unwrap();
        let mut power = block_output(1..2, &leaves);
        power.arrivals = Some(Arrivals::Power(vec![vec![(0, [1.0; 3])]]));
        assert!(run.push(power.clone()).is_err());
        power.arrivals = None;
        assert!(run.push(power).is_err());
        run.push(block_output(1..2, &leaves)).unwrap();
        let merged = run.finish();
        assert_eq!(merged.len(), 1);
        assert_eq!(
            merged[0].arrivals,
            Some(Arrivals::Settled(vec![part_of(0), part_of(1)]))
        );
    }

    #[test]
    fn a_run_computed_in_steps_gives_the_outputs_of_its_cover() {
        let leaves: Vec<f64> = (0..16)
            .map(|i| match i % 3 {
                0 => 1e16,
                1 => -1e16,
                _ => 1.0 + i as f64 * 0.37,
            })
            .collect();
        // Every run, cut at every set of points (steps), each step computed as
        // its own cover: what a worker claiming its lease piece by piece does.
        for start in 0..16usize {
            for end in start + 1..=16usize {
                let inner = end - start - 1;
                for cuts in 0u32..(1 << inner.min(6)) {
                    let mut steps = Vec::new();
                    let mut at = start;
                    for i in 0..inner.min(6) {
                        if cuts & (1 << i) != 0 {
                            steps.push(at..start + i + 1);
                            at = start + i + 1;
                        }
                    }
                    steps.push(at..end);
                    let mut run = RunOutputs::new();
                    for step in &steps {
                        for block in cover(step.clone()) {
                            run.push(block_output(block, &leaves)).unwrap();
                        }
                    }
                    assert_eq!(run.end(), Some(end));
                    let got = run.finish();
                    let want: Vec<BatchOutput> = cover(start..end)
                        .into_iter()
                        .map(|b| block_output(b, &leaves))
                        .collect();
                    let bits = |o: &[BatchOutput]| -> Vec<(Range<u32>, u64, u64)> {
                        o.iter()
                            .map(|o| {
                                (
                                    o.batches.clone(),
                                    o.sum.texels[0][0].to_bits(),
                                    o.sum.flow.shot[0].to_bits(),
                                )
                            })
                            .collect()
                    };
                    assert_eq!(bits(&got), bits(&want), "{start}..{end} in steps {steps:?}");
                    assert_eq!(got, want, "arrivals in order");
                }
            }
        }
    }

    #[test]
    fn a_run_refuses_a_piece_out_of_place() {
        let leaves = vec![1.0; 16];
        let mut run = RunOutputs::new();
        assert!(run.push(block_output(1..3, &leaves)).is_err(), "not aligned");
        run.push(block_output(2..4, &leaves)).unwrap();
        assert!(run.push(block_output(5..6, &leaves)).is_err(), "a gap");
        assert!(run.push(block_output(2..3, &leaves)).is_err(), "overlaps");
        let mut other = block_output(4..5, &leaves);
        other.iteration = 4;
        assert!(run.push(other).is_err(), "another iteration");
        run.push(block_output(4..8, &leaves)).unwrap();
        assert_eq!(
            run.finish().iter().map(|o| o.batches.clone()).collect::<Vec<_>>(),
            vec![2..4, 4..8]
        );
    }

    #[test]
    fn misaligned_or_out_of_order_blocks_are_refused() {
        let mut t = TreeSum::new(8);
        assert!(t.push(1..2, leaf(1.0)).is_err(), "not next");
        assert!(t.push(0..3, leaf(1.0)).is_err(), "not a power of two");
        t.push(0..1, leaf(1.0)).unwrap();
        assert!(t.push(1..3, leaf(1.0)).is_err(), "not aligned");
        t.push(1..2, leaf(1.0)).unwrap();
        assert!(t.push(2..10, leaf(1.0)).is_err(), "past the end");
        t.push(2..4, leaf(1.0)).unwrap();
        assert!(!t.is_complete());
        t.push(4..8, leaf(1.0)).unwrap();
        assert_eq!(t.finish().unwrap().texels[0][0], 4.0);
        assert!(TreeSum::new(2).finish().is_none(), "incomplete");
    }

    #[test]
    fn blocks_cover_the_batches_with_aligned_pieces() {
        assert_eq!(blocks(16, 4), vec![0..4, 4..8, 8..12, 12..16]);
        assert_eq!(blocks(16, 16), vec![0..16]);
        assert_eq!(blocks(16, 3), vec![0..4, 4..8, 8..12, 12..16], "rounded up to 4");
        assert_eq!(blocks(8, 100), vec![0..8]);
        assert_eq!(blocks(6, 4), vec![0..4, 4..6]);
        assert_eq!(blocks(1, 0), vec![0..1]);
        for b in blocks(6, 4) {
            assert!(is_aligned_block(&b, 6));
        }
    }

    #[test]
    fn a_run_is_cut_into_the_fewest_aligned_blocks() {
        assert_eq!(cover(1..16), vec![1..2, 2..4, 4..8, 8..16]);
        assert_eq!(cover(0..16), vec![0..16]);
        assert_eq!(cover(3..9), vec![3..4, 4..8, 8..9]);
        assert_eq!(cover(5..6), vec![5..6]);
        assert_eq!(cover(4..4), Vec::<Range<usize>>::new());
        // Every run of a 16-batch pass: aligned pieces, in order, covering
        // it exactly, never two that could merge into one node.
        for start in 0..16 {
            for end in start + 1..=16 {
                let pieces = cover(start..end);
                assert_eq!(pieces.first().unwrap().start, start);
                assert_eq!(pieces.last().unwrap().end, end);
                for w in pieces.windows(2) {
                    assert_eq!(w[0].end, w[1].start);
                    let merged = w[0].start..w[1].end;
                    assert!(
                        w[0].len() != w[1].len() || !is_aligned_block(&merged, 16),
                        "{:?} and {:?} are one node",
                        w[0],
                        w[1]
                    );
                }
                assert!(pieces.iter().all(|b| is_aligned_block(b, 16)));
            }
        }
    }
}
