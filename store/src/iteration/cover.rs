//! Which aligned blocks make up a pass: among those held and those stored, the nodes of the pass's
//! reduction tree that cover it. Pure functions of batch ranges, kept apart from the I/O so that
//! they are tested on ranges alone; the replica uses one to learn a pass it reads with the fewest
//! reads, the coordinator the other to absorb a pass from what is stored.

use std::ops::Range;
use vlf_core::propagate::reduce::is_aligned_block;

/// The aligned blocks of a pass of `n` batches that cover it with the fewest reads from the
/// store, in order, each with whether it is held here: blocks in `held` cost nothing, those in
/// `stored` one read each. `None` when together they leave a gap. Any cover gives the same sum:
/// its blocks are nodes of the pass's reduction tree (`vlf_core::propagate::reduce`).
pub(super) fn cheapest_cover(
    held: &[Range<usize>],
    stored: &[Range<usize>],
    n: usize,
) -> Option<Vec<(Range<usize>, bool)>> {
    // reads[i]: the fewest reads that cover batches i..n; take[i]: the block to take at i.
    let mut reads: Vec<Option<usize>> = vec![None; n + 1];
    let mut take: Vec<Option<(Range<usize>, bool)>> = vec![None; n + 1];
    reads[n] = Some(0);
    for i in (0..n).rev() {
        let candidates = (held.iter().map(|b| (b, true))).chain(stored.iter().map(|b| (b, false)));
        for (block, from_here) in candidates {
            if block.start != i || !is_aligned_block(block, n) {
                continue;
            }
            let Some(after) = reads[block.end] else {
                continue;
            };
            let total = after + usize::from(!from_here);
            if reads[i].is_none_or(|r| total < r) {
                reads[i] = Some(total);
                take[i] = Some((block.clone(), from_here));
            }
        }
    }
    let mut plan = Vec::new();
    let mut i = 0;
    while i < n {
        let (block, from_here) = take[i].clone()?;
        i = block.end;
        plan.push((block, from_here));
    }
    Some(plan)
}

/// Aligned blocks among `stored` (sorted as [`FieldJob::stored_blocks`](crate::field::FieldJob::stored_blocks) sorts them) that cover
/// the batches `span` of a pass one after another, the largest at each step; the first batch
/// no stored block starts at, if there is a gap.
pub(super) fn cover(stored: &[Range<usize>], span: Range<usize>) -> Result<Vec<Range<usize>>, usize> {
    let mut out = Vec::new();
    let mut next = span.start;
    while next < span.end {
        let block = stored
            .iter()
            .find(|b| b.start == next && is_aligned_block(b, span.end))
            .ok_or(next)?;
        next = block.end;
        out.push(block.clone());
    }
    Ok(out)
}

#[cfg(test)]
// Single blocks are what these tests mean.
#[allow(clippy::single_range_in_vec_init)]
mod tests {
    use super::cheapest_cover;

    #[test]
    fn a_cover_takes_what_is_held_and_reads_the_fewest_blocks() {
        // What is held covers the pass: nothing to read.
        let held = [0..4, 4..6, 6..8];
        let plan = cheapest_cover(&held, &[0..8], 8).unwrap();
        assert_eq!(plan, vec![(0..4, true), (4..6, true), (6..8, true)]);
        // Held blocks fill what they can, stored ones the rest.
        let plan = cheapest_cover(&[0..4], &[0..8, 4..8], 8).unwrap();
        assert_eq!(plan, vec![(0..4, true), (4..8, false)]);
        // The fewest reads, not the most held: one stored block over two.
        let plan = cheapest_cover(&[0..4, 4..6], &[0..8, 6..7, 7..8], 8).unwrap();
        assert_eq!(plan, vec![(0..8, false)]);
        // A held block that leads to a gap is not taken.
        let plan = cheapest_cover(&[0..2], &[0..4, 4..8], 8).unwrap();
        assert_eq!(plan, vec![(0..4, false), (4..8, false)]);
        // Blocks that are not nodes of the reduction tree are never taken.
        assert_eq!(cheapest_cover(&[0..2, 2..6, 6..8], &[], 8), None);
        assert_eq!(cheapest_cover(&[0..4], &[4..6], 8), None, "a gap");
        assert_eq!(cheapest_cover(&[], &[], 0), Some(Vec::new()));
    }
}
