//! Which parts of a field are resident in the renderer's pool, and where: a bounded LRU cache.
//!
//! The pool holds `capacity` RGB values. A part is placed in the smallest free run that fits it
//! (best fit, which leaves the large runs for the large diffuse maps; free runs are kept sorted
//! and merged with their neighbours when freed). When none
//! fits, resident parts are evicted least recently used first — but never one the current view
//! uses (touched in the current round, see [`Residency::touch`]): a view that needs more than the
//! pool gets as much of what it needs as fits, and the rest is reported, not thrashed. A part
//! that would not fit even then evicts nothing.

use std::collections::BTreeMap;

/// The resident parts of a pool of `capacity` values.
#[derive(Clone, Debug)]
pub struct Residency {
    sizes: Vec<usize>,
    /// Where each resident part starts in the pool.
    base: Vec<Option<usize>>,
    /// The round in which each part was last used.
    used: Vec<u64>,
    /// The current round: parts used in it are pinned.
    round: u64,
    /// Free runs of the pool: start → length, merged with their neighbours.
    free: BTreeMap<usize, usize>,
    capacity: usize,
    resident_values: usize,
    resident_parts: usize,
}

impl Residency {
    /// A pool of `capacity` values for parts of `sizes` values each, nothing resident.
    pub fn new(sizes: Vec<usize>, capacity: usize) -> Residency {
        let n = sizes.len();
        let mut free = BTreeMap::new();
        if capacity > 0 {
            free.insert(0, capacity);
        }
        Residency {
            sizes,
            base: vec![None; n],
            used: vec![0; n],
            round: 0,
            free,
            capacity,
            resident_values: 0,
            resident_parts: 0,
        }
    }

    /// Where part `part` lies in the pool, if resident.
    pub fn base(&self, part: u32) -> Option<usize> {
        self.base[part as usize]
    }

    pub fn is_resident(&self, part: u32) -> bool {
        self.base[part as usize].is_some()
    }

    /// Parts resident, and the values they take.
    pub fn resident(&self) -> (usize, usize) {
        (self.resident_parts, self.resident_values)
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Starts a new round in which `parts` are used: they become the most recently used, and
    /// [`Residency::place`] will not evict them during this round.
    pub fn touch(&mut self, parts: &[u32]) {
        self.round += 1;
        for &p in parts {
            self.used[p as usize] = self.round;
        }
    }

    /// Places part `part` (not resident) in the pool, evicting least recently used parts not
    /// used in this round as needed; the evicted parts are appended to `evicted`. `None` when it
    /// cannot fit without evicting a part the current view uses (or is larger than the pool):
    /// then nothing is evicted, since evicting would only lose parts for nothing.
    /// A placed part counts as used in this round.
    pub fn place(&mut self, part: u32, evicted: &mut Vec<u32>) -> Option<usize> {
        debug_assert!(!self.is_resident(part));
        let size = self.sizes[part as usize];
        let base = match self.best_fit(size) {
            Some(base) => base,
            None if !self.fits_after_evicting(size) => return None,
            None => {
                // Victims, least recently used first.
                let mut victims: Vec<u32> = (0..self.sizes.len() as u32)
                    .filter(|&p| self.is_resident(p) && self.used[p as usize] < self.round)
                    .collect();
                victims.sort_by_key(|&p| (self.used[p as usize], p));
                let mut found = None;
                for v in victims {
                    self.evict(v);
                    evicted.push(v);
                    if let Some(base) = self.best_fit(size) {
                        found = Some(base);
                        break;
                    }
                }
                found?
            }
        };
        self.take(base, size);
        self.base[part as usize] = Some(base);
        self.used[part as usize] = self.round;
        self.resident_values += size;
        self.resident_parts += 1;
        Some(base)
    }

    /// Frees part `part`'s place (nothing if it is not resident).
    pub fn evict(&mut self, part: u32) {
        let Some(base) = self.base[part as usize].take() else {
            return;
        };
        let size = self.sizes[part as usize];
        self.resident_values -= size;
        self.resident_parts -= 1;
        if size == 0 {
            return;
        }
        let (mut start, mut len) = (base, size);
        if let Some((&s, &l)) = self.free.range(..base).next_back()
            && s + l == base
        {
            self.free.remove(&s);
            start = s;
            len += l;
        }
        if let Some(&l) = self.free.get(&(base + size)) {
            self.free.remove(&(base + size));
            len += l;
        }
        self.free.insert(start, len);
    }

    /// Evicts everything.
    pub fn clear(&mut self) {
        *self = Residency::new(std::mem::take(&mut self.sizes), self.capacity);
    }

    /// Whether evicting every part not used in this round would leave a free run of `size`
    /// values: the free runs and those parts' places, merged where they touch, between the
    /// pinned parts.
    fn fits_after_evicting(&self, size: usize) -> bool {
        let mut runs: Vec<(usize, usize)> = self.free.iter().map(|(&s, &l)| (s, l)).collect();
        runs.extend((0..self.sizes.len()).filter_map(|p| {
            let base = self.base[p]?;
            (self.used[p] < self.round && self.sizes[p] > 0).then_some((base, self.sizes[p]))
        }));
        runs.sort_unstable();
        let (mut start, mut end) = (0, 0);
        for (s, l) in runs {
            if s != end {
                start = s;
            }
            end = s + l;
            if end - start >= size {
                return true;
            }
        }
        false
    }

    /// The start of the smallest free run of at least `size` values (the lowest of equals).
    fn best_fit(&self, size: usize) -> Option<usize> {
        if size == 0 {
            return Some(0);
        }
        self.free
            .iter()
            .filter(|&(_, &len)| len >= size)
            .min_by_key(|&(&start, &len)| (len, start))
            .map(|(&s, _)| s)
    }

    /// Marks `size` values from `base` (the start of a free run) as used.
    fn take(&mut self, base: usize, size: usize) {
        if size == 0 {
            return;
        }
        let len = self.free.remove(&base).unwrap_or(0);
        if len > size {
            self.free.insert(base + size, len - size);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// No two resident parts overlap, all lie in the pool, and free runs cover the rest exactly.
    fn check(r: &Residency) {
        let mut used = vec![0u8; r.capacity];
        for (p, base) in r.base.iter().enumerate() {
            if let Some(b) = base {
                for u in &mut used[*b..*b + r.sizes[p]] {
                    *u += 1;
                }
            }
        }
        for (&s, &l) in &r.free {
            for u in &mut used[s..s + l] {
                *u += 1;
            }
        }
        assert!(used.iter().all(|&u| u == 1), "pool covered exactly once: {used:?}");
        let runs: Vec<_> = r.free.iter().collect();
        for w in runs.windows(2) {
            assert!(w[0].0 + w[0].1 < *w[1].0, "free runs are merged: {runs:?}");
        }
    }

    #[test]
    fn evicts_the_least_recently_used_first() {
        let mut r = Residency::new(vec![4; 5], 12);
        let mut evicted = Vec::new();
        for p in 0..3 {
            r.touch(&[p]);
            assert!(r.place(p, &mut evicted).is_some());
        }
        assert!(evicted.is_empty());
        // Part 0 used again: part 1 is now the least recently used.
        r.touch(&[0]);
        r.touch(&[3]);
        assert_eq!(r.place(3, &mut evicted), Some(4), "where part 1 was");
        assert_eq!(evicted, vec![1]);
        check(&r);
        assert_eq!(r.resident(), (3, 12));
    }

    #[test]
    fn never_evicts_what_the_current_view_uses() {
        let mut r = Residency::new(vec![4; 4], 8);
        let mut evicted = Vec::new();
        r.touch(&[0, 1, 2]);
        assert!(r.place(0, &mut evicted).is_some());
        assert!(r.place(1, &mut evicted).is_some());
        assert_eq!(r.place(2, &mut evicted), None, "the view needs more than the pool");
        assert!(evicted.is_empty());
        assert!(r.is_resident(0) && r.is_resident(1));
        // The next view needs 2 and 3 only: 0 and 1 make room.
        r.touch(&[2, 3]);
        assert!(r.place(2, &mut evicted).is_some());
        assert!(r.place(3, &mut evicted).is_some());
        evicted.sort();
        assert_eq!(evicted, vec![0, 1]);
        check(&r);
    }

    #[test]
    fn freed_runs_merge_so_large_parts_fit_again() {
        // Sizes 3, 2, 3, then a part of 8 needs the whole pool.
        let mut r = Residency::new(vec![3, 2, 3, 8, 0], 8);
        let mut evicted = Vec::new();
        r.touch(&[0, 1, 2]);
        for p in 0..3 {
            r.place(p, &mut evicted).unwrap();
        }
        check(&r);
        r.evict(1);
        check(&r);
        r.touch(&[3, 4]);
        assert_eq!(r.place(3, &mut evicted), Some(0));
        assert_eq!(r.place(4, &mut evicted), Some(0), "an empty part takes no room");
        check(&r);
        assert_eq!(r.resident(), (2, 8));
        r.clear();
        assert_eq!(r.resident(), (0, 0));
        check(&r);
    }

    #[test]
    fn a_part_goes_to_the_smallest_run_that_fits_it() {
        let mut r = Residency::new(vec![3, 2, 3, 2, 1, 3], 10);
        let mut evicted = Vec::new();
        r.touch(&[0, 1, 2, 3]);
        for p in 0..4 {
            r.place(p, &mut evicted).unwrap();
        }
        r.evict(0);
        r.evict(3);
        // Free: [0, 3) and [8, 10). The small part takes the small run …
        r.touch(&[1, 2, 4, 5]);
        assert_eq!(r.place(4, &mut evicted), Some(8));
        // … so the large one still fits.
        assert_eq!(r.place(5, &mut evicted), Some(0));
        assert!(evicted.is_empty());
        check(&r);
    }

    /// A part larger than the pool, or than what evicting every other view's parts frees, is
    /// refused without evicting anything: the parts it could not use survive.
    #[test]
    fn a_part_larger_than_the_pool_is_refused() {
        let mut r = Residency::new(vec![10, 1, 1], 4);
        let mut evicted = Vec::new();
        r.touch(&[1, 2]);
        r.place(1, &mut evicted).unwrap();
        r.place(2, &mut evicted).unwrap();
        r.touch(&[0]);
        assert_eq!(r.place(0, &mut evicted), None);
        assert!(evicted.is_empty(), "evicted {evicted:?} for nothing");
        assert!(r.is_resident(1) && r.is_resident(2));
        check(&r);
        // Sizes 2, 2, 2 in a pool of 6, the middle one pinned: the free runs around it, each of
        // 2 after evicting the others, never make 4.
        let mut r = Residency::new(vec![2, 2, 2, 4], 6);
        r.touch(&[0, 1, 2]);
        for p in 0..3 {
            r.place(p, &mut evicted).unwrap();
        }
        r.touch(&[1, 3]);
        assert_eq!(r.place(3, &mut evicted), None);
        assert!(evicted.is_empty(), "evicted {evicted:?} for nothing");
        assert!((0..3).all(|p| r.is_resident(p)));
        check(&r);
        // With the middle one free to go too, it fits.
        r.touch(&[3]);
        assert!(r.place(3, &mut evicted).is_some());
        check(&r);
    }
}
