//! The subfields of a direction set, held whole or within a memory budget.
//!
//! A subfield is a pure function of the scene's footprints, its direction's frame and the grid
//! ([`Subfield::build_with`]): building it twice gives the same spans, so whoever shoots a
//! direction may rebuild its subfield rather than keep it, and the field's bits cannot tell.
//! That is what bounds a worker's memory by the directions it shoots rather than by the field:
//! at l = 8193 and N = 256 the subfields of the Cornell box are 696 MB, every one of which a
//! worker would otherwise build and keep, though it shoots only its share.
//!
//! [`Subfields`] holds them one of three ways:
//!
//! - **whole** ([`Subfields::build_all`]): every subfield built at once and kept, the fastest
//!   when they fit (a single process, a small job);
//! - **within a budget** ([`Subfields::within`]): a cache of at most `budget` bytes of
//!   subfields, built when first asked for and dropped least recently used first. A worker
//!   whose leases stay on the same directions from one iteration to the next (the scheduler
//!   keeps each worker's home) builds its home's subfields once and keeps them, as long as the
//!   home fits the budget; a smaller budget still gives the same field, at the cost of
//!   rebuilding (nothing measurable at N = 128, 15 % more propagation time at N = 256 when
//!   every subfield is rebuilt every time: `docs/scaling.md`);
//! - **on demand** ([`Subfields::on_demand`]): built when first asked for and kept, a budget
//!   without a bound — a worker that need not pass over the whole field at set-up (the job's
//!   survey is stored with the job) builds only the subfields of the directions it shoots.
//!
//! **The bound.** Besides the cache's `budget`, a subfield is alive while someone reads it:
//! a thread shooting a direction (or passing over it at set-up) holds one; gathering a direction's mirror maps reads the mirror entries alone, which the
//! specular state keeps (`crate::propagate::specular::MirrorView`), and holds none. So the
//! subfield bytes alive never exceed `budget + threads · largest subfield` — what
//! [`SubfieldMemory::peak`] counts, every subfield built being counted until it is dropped.

use super::{Footprints, GridSize, PsfFrame, RasterScratch, Subfield};
use rayon::prelude::*;
use std::ops::Deref;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// The subfields of every direction of a field, whole or built on demand within a budget.
pub struct Subfields {
    footprints: Arc<Footprints>,
    frames: Vec<PsfFrame>,
    grid: GridSize,
    held: Held,
    counter: Arc<Counter>,
}

enum Held {
    All(Arc<[Subfield]>),
    Budget { bytes: usize, cache: Mutex<Cache> },
}

/// The cached subfields of a budgeted [`Subfields`], with when each was last asked for.
struct Cache {
    slots: Vec<Option<Arc<Counted>>>,
    last_used: Vec<u64>,
    clock: u64,
    bytes: usize,
}

/// A subfield built on demand, counted alive until dropped.
struct Counted {
    subfield: Subfield,
    bytes: usize,
    counter: Arc<Counter>,
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.counter.live.fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

#[derive(Default)]
struct Counter {
    live: AtomicUsize,
    peak: AtomicUsize,
    builds: AtomicU64,
}

/// What a [`Subfields`] holds and has held, in bytes of [`Subfield::memory_bytes`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SubfieldMemory {
    /// The budget, if any (`None`: all held, or built on demand and kept).
    pub budget: Option<usize>,
    /// Subfield bytes alive now: cached, or read by someone.
    pub live: usize,
    /// The most that were ever alive at once.
    pub peak: usize,
    /// Subfields built so far (l once when held whole; more when a budget makes some rebuilt).
    pub builds: u64,
}

/// A subfield being read: borrowed from a whole set, or shared with a budget's cache (which
/// may drop it meanwhile; it lives until this reference goes).
pub struct SubfieldRef<'a>(Reading<'a>);

enum Reading<'a> {
    Borrowed(&'a Subfield),
    Shared(Arc<Counted>),
}

impl Deref for SubfieldRef<'_> {
    type Target = Subfield;
    fn deref(&self) -> &Subfield {
        match &self.0 {
            Reading::Borrowed(s) => s,
            Reading::Shared(c) => &c.subfield,
        }
    }
}

impl Subfields {
    /// Every subfield of `frames` built now (in parallel) and kept.
    pub fn build_all(footprints: Arc<Footprints>, frames: Vec<PsfFrame>, grid: GridSize) -> Subfields {
        let all: Vec<Subfield> = frames
            .par_iter()
            .map_init(RasterScratch::default, |scratch, &frame| {
                Subfield::build_with(&footprints, frame, grid, scratch)
            })
            .collect();
        let counter = Counter::default();
        let bytes = all.iter().map(Subfield::memory_bytes).sum();
        counter.live.store(bytes, Ordering::Relaxed);
        counter.peak.store(bytes, Ordering::Relaxed);
        counter.builds.store(all.len() as u64, Ordering::Relaxed);
        Subfields {
            footprints,
            frames,
            grid,
            held: Held::All(all.into()),
            counter: Arc::new(counter),
        }
    }

    /// No subfield built yet: each is built when first asked for, and at most `budget` bytes of
    /// them are kept (see the module docs for the bound on what is alive).
    pub fn within(footprints: Arc<Footprints>, frames: Vec<PsfFrame>, grid: GridSize, budget: usize) -> Subfields {
        let l = frames.len();
        Subfields {
            footprints,
            frames,
            grid,
            held: Held::Budget {
                bytes: budget,
                cache: Mutex::new(Cache {
                    slots: vec![None; l],
                    last_used: vec![0; l],
                    clock: 0,
                    bytes: 0,
                }),
            },
            counter: Arc::new(Counter::default()),
        }
    }

    /// No subfield built yet: each is built when first asked for and kept — a budget with no
    /// bound. What a worker of a diffuse job holds when the job's survey is stored
    /// (`Propagation::with_survey`): the subfields of the directions it shoots, not the field's.
    pub fn on_demand(footprints: Arc<Footprints>, frames: Vec<PsfFrame>, grid: GridSize) -> Subfields {
        Subfields::within(footprints, frames, grid, usize::MAX)
    }

    /// The same directions with none held: each built again when asked for and kept, within
    /// this set's budget if it has one. What one that no longer reads them swaps its set for
    /// (`Propagation::release_subfields`); whoever shares this set keeps it.
    pub fn released(&self) -> Subfields {
        let (footprints, frames) = (self.footprints.clone(), self.frames.clone());
        match &self.held {
            Held::Budget { bytes, .. } => Subfields::within(footprints, frames, self.grid, *bytes),
            Held::All(_) => Subfields::on_demand(footprints, frames, self.grid),
        }
    }

    /// Whether every subfield is held (built up front, [`Subfields::build_all`]): reading any
    /// costs nothing then.
    pub fn all_held(&self) -> bool {
        matches!(self.held, Held::All(_))
    }

    /// Whether a memory budget bounds what is held: not when every subfield is held, nor when
    /// they are built on demand and kept ([`Subfields::on_demand`]). A set without one may keep
    /// more beside it (the rotated copies' subfields, `crate::propagate::rotated`).
    pub fn has_budget(&self) -> bool {
        self.budget().is_some()
    }

    fn budget(&self) -> Option<usize> {
        match &self.held {
            Held::All(_) => None,
            Held::Budget { bytes, .. } => Some(*bytes).filter(|&b| b != usize::MAX),
        }
    }

    /// Number of directions.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// The subfield of direction `d`: held, or built now (and cached within the budget).
    pub fn get(&self, d: usize) -> SubfieldRef<'_> {
        let (budget, cache) = match &self.held {
            Held::All(all) => return SubfieldRef(Reading::Borrowed(&all[d])),
            Held::Budget { bytes, cache } => (*bytes, cache),
        };
        if let Some(hit) = lock(cache).touch(d) {
            return SubfieldRef(Reading::Shared(hit));
        }
        // Built outside the lock: other threads go on reading the cache meanwhile. Two threads
        // that miss the same direction both build it (the same spans); the first cached wins.
        let subfield = Subfield::build_with(
            &self.footprints,
            self.frames[d],
            self.grid,
            &mut RasterScratch::default(),
        );
        let bytes = subfield.memory_bytes();
        let live = self.counter.live.fetch_add(bytes, Ordering::Relaxed) + bytes;
        self.counter.peak.fetch_max(live, Ordering::Relaxed);
        self.counter.builds.fetch_add(1, Ordering::Relaxed);
        let built = Arc::new(Counted {
            subfield,
            bytes,
            counter: self.counter.clone(),
        });
        SubfieldRef(Reading::Shared(lock(cache).insert(d, built, budget)))
    }

    /// The frame of direction `d`'s subfield (known without building it).
    pub fn frame(&self, d: usize) -> PsfFrame {
        self.frames[d]
    }

    /// The ray grid every subfield shares.
    pub fn grid(&self) -> GridSize {
        self.grid
    }

    /// `f(d, subfield of d)` for every direction, in parallel, in direction order: the set-up
    /// passes over the whole field (discrete areas, which surfaces see each other), which
    /// within a budget build each subfield they are not holding.
    pub fn map<T: Send>(&self, f: impl Fn(usize, &Subfield) -> T + Sync + Send) -> Vec<T> {
        (0..self.len()).into_par_iter().map(|d| f(d, &self.get(d))).collect()
    }

    /// What is held and was held (see [`SubfieldMemory`]).
    pub fn memory(&self) -> SubfieldMemory {
        SubfieldMemory {
            budget: self.budget(),
            live: self.counter.live.load(Ordering::Relaxed),
            peak: self.counter.peak.load(Ordering::Relaxed),
            builds: self.counter.builds.load(Ordering::Relaxed),
        }
    }
}

/// Two sets are equal when they build the same subfields: the same footprints, frames and grid
/// (whatever each holds now).
impl PartialEq for Subfields {
    fn eq(&self, other: &Subfields) -> bool {
        self.grid == other.grid && self.frames == other.frames && *self.footprints == *other.footprints
    }
}

impl std::fmt::Debug for Subfields {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Subfields")
            .field("directions", &self.len())
            .field("grid", &self.grid)
            .field("memory", &self.memory())
            .finish()
    }
}

fn lock(cache: &Mutex<Cache>) -> std::sync::MutexGuard<'_, Cache> {
    // The cache is consistent between statements: a panic elsewhere leaves nothing half done.
    cache.lock().unwrap_or_else(|p| p.into_inner())
}

impl Cache {
    fn touch(&mut self, d: usize) -> Option<Arc<Counted>> {
        let hit = self.slots[d].clone()?;
        self.clock += 1;
        self.last_used[d] = self.clock;
        Some(hit)
    }

    /// Caches `built` as direction `d`'s (unless a racing build got there first: that one is
    /// returned), then drops the least recently used others until the cache is within
    /// `budget` (the one just asked for stays, even alone over it: its reader holds it anyway).
    fn insert(&mut self, d: usize, built: Arc<Counted>, budget: usize) -> Arc<Counted> {
        if let Some(first) = self.touch(d) {
            return first;
        }
        self.clock += 1;
        self.last_used[d] = self.clock;
        self.bytes += built.bytes;
        self.slots[d] = Some(built.clone());
        while self.bytes > budget {
            let oldest = (0..self.slots.len())
                .filter(|&e| e != d && self.slots[e].is_some())
                .min_by_key(|&e| self.last_used[e]);
            let Some(e) = oldest else { break };
            if let Some(gone) = self.slots[e].take() {
                self.bytes -= gone.bytes;
            }
        }
        built
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::directions::DirectionSet;
    use crate::maps::TexelAtlas;
    use crate::scene::{ImportOptions, load_obj};

    fn cornell_like() -> (Arc<Footprints>, Vec<PsfFrame>, GridSize) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
        let (scene, _) = load_obj(&path, &ImportOptions::default()).unwrap();
        let grid = GridSize::new(32, 8).unwrap();
        let atlas = TexelAtlas::new(&scene, grid.ray_spacing(), grid.ray_spacing()).unwrap();
        let footprints = Arc::new(Footprints::new(&scene, &atlas.plane_rep));
        let dirs = DirectionSet::new(129).unwrap();
        let frames = (0..dirs.len()).map(|d| dirs.frame(d)).collect();
        (footprints, frames, grid)
    }

    #[test]
    fn a_budget_builds_the_same_subfields_and_keeps_within_it() {
        let (footprints, frames, grid) = cornell_like();
        let whole = Subfields::build_all(footprints.clone(), frames.clone(), grid);
        let total = whole.memory().live;
        let largest = whole.map(|_, s| s.memory_bytes()).into_iter().max().unwrap();
        let budget = total / 5;
        let bounded = Subfields::within(footprints, frames, grid, budget);
        assert_eq!(bounded.memory().live, 0, "nothing built before it is asked for");
        // Twice over every direction, on 2 threads: the second pass must rebuild most.
        let threads = 2;
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        for _ in 0..2 {
            let same = pool.install(|| bounded.map(|d, s| *s == *whole.get(d)));
            assert!(same.iter().all(|&s| s), "a subfield built on demand differs");
        }
        let m = bounded.memory();
        assert!(
            m.builds > 2 * bounded.len() as u64 * 3 / 4,
            "a budget of a fifth keeps few: {m:?}"
        );
        assert!(
            m.peak <= budget + threads * largest,
            "alive {} > budget {budget} + {threads}·{largest}",
            m.peak
        );
        assert!(m.live <= budget + largest, "at rest only the cache holds them: {m:?}");
        assert!(
            total > 2 * m.peak,
            "the whole set {total} is not what a budget holds ({m:?})"
        );
    }

    #[test]
    fn what_fits_the_budget_is_built_once() {
        let (footprints, frames, grid) = cornell_like();
        let bounded = Subfields::within(footprints, frames, grid, usize::MAX);
        let home = 10..40;
        for _ in 0..3 {
            for d in home.clone() {
                let _ = bounded.get(d);
            }
        }
        assert_eq!(bounded.memory().builds, home.len() as u64);
    }

    #[test]
    fn the_least_recently_used_goes_first() {
        let (footprints, frames, grid) = cornell_like();
        let one = Subfields::build_all(footprints.clone(), frames.clone(), grid);
        let size = |d: usize| one.get(d).memory_bytes();
        // Room for 0 and 1, or 0 and 2, not for all three.
        let bounded = Subfields::within(footprints, frames, grid, size(0) + size(1).max(size(2)));
        let _ = bounded.get(0);
        let _ = bounded.get(1);
        let _ = bounded.get(0); // 1 is now the least recently used
        let _ = bounded.get(2);
        let builds = bounded.memory().builds;
        let _ = bounded.get(0);
        assert_eq!(bounded.memory().builds, builds, "0 was used last: kept");
        let _ = bounded.get(1);
        assert_eq!(bounded.memory().builds, builds + 1, "1 was dropped for 2");
    }
}
