//! The fixed reduction tree of a pass: how the batch sums of a pass are added
//! up, so that the bits never depend on who computed what.
//!
//! A pass has `n` batches (`n` a power of two for every supported `l`: 1, 2,
//! 8 or 16). Their sums are the leaves of a perfect binary tree, and every
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
//! counter: it keeps at most `log2(n) + 1` partial sums.

use super::FlowRecord;
use super::work::{BatchSum, add_into};
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

    #[test]
    fn any_cover_by_aligned_blocks_gives_the_same_bits() {
        // Values whose sum depends on the order of additions.
        let leaves: Vec<f64> = (0..16)
            .map(|i| match i % 4 {
                0 => 1e16,
                2 => -1e16,
                _ => 1.0 + i as f64 * 0.37,
            })
            .collect();
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
