//! Rotated copies' subfields, kept from a copy's areas to its shot.
//!
//! A perturbed iteration shoots through rotated copies of the direction set ([`super::perturb`]),
//! and every copy takes two passes over its directions: [`Pass::Areas`](super::Pass::Areas)
//! counts each texel's discrete area `T_t` in the copy, and
//! [`Pass::ShootCopy`](super::Pass::ShootCopy), which needs every direction's areas first, shoots
//! the copy's rays. Both walk the same subfield of each rotated direction, which nothing else
//! reads. Built afresh by each pass, a mesh of tens of thousands of triangles paid for its
//! rasterisation twice, and rasterising was most of the iteration: the 47 794-triangle dragon
//! at l = 2049, N = 128 spends 24–26 s on each perturbed iteration (2-core VM) against 1.1 s on
//! a plain one, which walks subfields held since set-up.
//!
//! So a propagation whose subfields no budget bounds (held whole, or built on demand and kept,
//! as a service worker's are) keeps each rotated subfield its `Areas` pass built, until the
//! copy's shot takes it: at most one copy's worth, `l` subfields — about what the held subfields
//! take, and only during the perturbed iterations (those left by a worker whose shot another
//! took go when it moves on: `Propagation::drop_rotated_subfields_before`). The bound is per
//! propagation: a worker keeping two jobs' replicas may keep two jobs' worth. A propagation
//! within a subfield budget keeps none: its bound is the budget's. A subfield taken from here is
//! the one the pass would have built, so the bits are the same.
//!
//! One copy's are enough when each copy is shot right after its areas
//! ([`Pass::shooting_rank`](super::Pass::shooting_rank)): [`super::Propagation::step`] shoots in that order (`IterationWork::shooting_order`), and the
//! service leases in it — a copy's shot before the next copy's areas, which wait for it while
//! it is about to open, and each worker's part of a copy's shot is the part of its areas it
//! computed (its home). The 47 794-triangle dragon's embedded run (`vlf run`, one worker,
//! 2 threads, 2 perturbed iterations of 4 copies): 12 293 rotated builds per perturbed
//! iteration before (the next copy's areas leased while the shot waited for its areas to be
//! absorbed), 8 196 = `copies·l` since.

use crate::psf::Subfield;
use std::collections::HashMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

/// The rotated subfields built by an iteration's `Areas` passes and not yet shot: see the module
/// docs. Shared by a propagation's clones (a worker of this process shooting a copy finds what
/// another counted).
#[derive(Debug, Default)]
pub(crate) struct RotatedSubfields {
    held: Mutex<Held>,
    /// Rotated subfields built so far, kept or not.
    built: AtomicUsize,
}

#[derive(Debug, Default)]
struct Held {
    /// The iteration whose subfields these are.
    iteration: u32,
    /// Per (copy, direction).
    subfields: HashMap<(u32, usize), Subfield>,
}

impl RotatedSubfields {
    /// Counts a rotated subfield built.
    pub(crate) fn count_build(&self) {
        self.built.fetch_add(1, Ordering::Relaxed);
    }

    /// Rotated subfields built so far.
    pub(crate) fn built(&self) -> usize {
        self.built.load(Ordering::Relaxed)
    }

    /// Keeps the subfield of direction `d` of copy `copy` of iteration `iteration` for the copy's
    /// shot, unless `limit` are kept already. Those of an earlier iteration are dropped; one of
    /// an earlier iteration than those kept (a late duplicate of a lease) is not kept.
    pub(crate) fn keep(&self, iteration: u32, copy: u32, d: usize, sub: Subfield, limit: usize) {
        let mut held = self.lock();
        if iteration < held.iteration {
            return;
        }
        // Freed once the lock is let go: up to `limit` subfields, which no other thread need
        // wait for.
        let mut stale = HashMap::new();
        if iteration > held.iteration {
            stale = std::mem::take(&mut held.subfields);
            held.iteration = iteration;
        }
        if held.subfields.len() < limit {
            held.subfields.insert((copy, d), sub);
        }
        drop(held);
        drop(stale);
    }

    /// The kept subfield of direction `d` of copy `copy` of iteration `iteration`, given up.
    pub(crate) fn take(&self, iteration: u32, copy: u32, d: usize) -> Option<Subfield> {
        let mut held = self.lock();
        match held.iteration == iteration {
            true => held.subfields.remove(&(copy, d)),
            false => None,
        }
    }

    /// How many are kept.
    pub(crate) fn kept(&self) -> usize {
        self.lock().subfields.len()
    }

    /// Drops every kept subfield of iteration `iteration` or before (it is over).
    pub(crate) fn clear(&self, iteration: u32) {
        let mut held = self.lock();
        if held.iteration <= iteration {
            let stale = std::mem::take(&mut held.subfields);
            drop(held);
            drop(stale);
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Held> {
        // A thread that panicked holding the lock left at worst a subfield kept or not: either
        // is a correct state (a missing one is built again).
        self.held.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::psf::{GridSize, PsfFrame};
    use glam::{DVec2, DVec3};

    fn subfield(tag: u32) -> Subfield {
        Subfield {
            frame: PsfFrame {
                w: DVec3::Z,
                u: DVec3::X,
                v: DVec3::Y,
                shift: DVec2::new(tag as f64, 0.0),
            },
            grid: GridSize::new(8, 8).unwrap(),
            tile_start: vec![0, 0],
            entries: Vec::new(),
            spans: Vec::new(),
        }
    }

    /// A kept subfield is taken once, by its copy and direction in its iteration; no more than
    /// the limit are kept; a new iteration drops the last one's.
    #[test]
    fn kept_until_taken_within_the_limit_and_the_iteration() {
        let rotated = RotatedSubfields::default();
        rotated.keep(3, 0, 5, subfield(5), 2);
        rotated.keep(3, 1, 5, subfield(15), 2);
        rotated.keep(3, 0, 6, subfield(6), 2);
        assert_eq!(rotated.kept(), 2, "the limit");
        assert_eq!(rotated.take(3, 0, 6), None, "not kept past the limit");
        assert_eq!(rotated.take(4, 0, 5), None, "another iteration's");
        assert_eq!(rotated.take(3, 1, 5), Some(subfield(15)));
        assert_eq!(rotated.take(3, 1, 5), None, "taken once");
        rotated.keep(4, 0, 7, subfield(7), 2);
        assert_eq!(rotated.kept(), 1, "the last iteration's dropped");
        assert_eq!(rotated.take(3, 0, 5), None);
        assert_eq!(rotated.take(4, 0, 7), Some(subfield(7)));
        // A late one of iteration 3 neither is kept nor drops iteration 4's.
        rotated.keep(3, 0, 9, subfield(9), 2);
        assert_eq!(rotated.kept(), 0);
        rotated.keep(4, 0, 8, subfield(8), 2);
        assert_eq!(rotated.kept(), 1);
        assert_eq!(rotated.take(3, 0, 9), None);
        // The end of iteration 3 leaves iteration 4's; the end of 4 drops them.
        rotated.clear(3);
        assert_eq!(rotated.kept(), 1);
        rotated.clear(4);
        assert_eq!(rotated.kept(), 0);
    }
}
