//! The exchange turned around: `Φ_in` by mirror, the routes by source.
//!
//! The exchange asks one question of `Φ_in` per [`Route`]: how much power arrived on the
//! route's mirror along its source direction. `Φ_in` is found by source ([`MirrorPower`]: per
//! direction, the mirrors it lit) and a target's routes come by mirror (sorted by (mirror,
//! source)), so each question was a binary search in another direction's list: a cache miss per
//! step, four million routes an iteration for the mirror dragon (47 794 triangles, l = 2049,
//! N = 128).
//!
//! * [`PowerByMirror`]: `Φ_in` by mirror, then source, turned around once per what a
//!   [`Pending`](super::Pending) knows of it. A gather looks its routes up in it.
//! * [`RoutesBySource`]: the routes by source, then mirror, then target, once per propagation
//!   (a function of the geometry), for
//!   [`Specular::settle_batch`](super::Specular::settle_batch): a batch of sources is
//!   one run of it, walked beside each source's `Φ_in`, one merge, no search.

use super::pending::add;
use super::{BatchArrivals, Exchange, MirrorPower, Route};
use crate::scene::Rgb;
use rayon::prelude::*;

/// `Φ_in(P, ω)` indexed by mirror `P` (its ordinal), then by source direction `ω`.
///
/// The sources and their powers lie apart: a route's look-up searches a mirror's sources (four
/// bytes each, a run a few cache lines long) and reads one power. Side by side, each step of the
/// search was a line of its own, a cache miss each, as the routes of one target jump from
/// mirror to mirror.
#[derive(Debug)]
pub struct PowerByMirror {
    /// `start[k]..start[k + 1]`: mirror `k`'s run of `sources` and `powers`; `mirrors + 1`
    /// values.
    start: Vec<u32>,
    /// The source directions, by mirror, then increasing.
    sources: Vec<u32>,
    /// `Φ_in` of each of `sources`.
    powers: Vec<Rgb>,
}

impl PowerByMirror {
    /// The index of `power_in` (per source direction, as [`MirrorPower`], where known) over
    /// `mirrors` mirrors: a counting sort by mirror, stable in the source. `power_in` is as a restore
    /// checks it (`check_pending`: each list by strictly increasing mirror, every mirror below
    /// `mirrors`); an entry for a mirror number out of range is left out all the same, as no
    /// route could ask for it.
    pub fn new(power_in: &[Option<MirrorPower>], mirrors: usize) -> PowerByMirror {
        let known = |k: u32| (k as usize) < mirrors;
        let mut start = vec![0u32; mirrors + 1];
        for &(k, _) in power_in.iter().flatten().flatten().filter(|(k, _)| known(*k)) {
            start[k as usize + 1] += 1;
        }
        for k in 0..mirrors {
            start[k + 1] += start[k];
        }
        let mut next = start.clone();
        let mut sources = vec![0; start[mirrors] as usize];
        let mut powers = vec![[0.0; 3]; start[mirrors] as usize];
        for (source, list) in power_in.iter().enumerate() {
            for &(k, power) in list.iter().flatten().filter(|(k, _)| known(*k)) {
                let at = &mut next[k as usize];
                sources[*at as usize] = source as u32;
                powers[*at as usize] = power;
                *at += 1;
            }
        }
        PowerByMirror { start, sources, powers }
    }

    /// Number of (mirror, source) pairs that carry power.
    #[cfg(test)]
    pub fn len(&self) -> usize {
        self.sources.len()
    }

    /// Where mirror `k`'s run lies (empty for a mirror number out of range).
    fn run(&self, k: u32) -> std::ops::Range<usize> {
        match (self.start.get(k as usize), self.start.get(k as usize + 1)) {
            (Some(&from), Some(&to)) => from as usize..to as usize,
            _ => 0..0,
        }
    }

    /// The sources that lit mirror `k` (increasing) and their powers.
    #[cfg(test)]
    pub fn of(&self, k: u32) -> (&[u32], &[Rgb]) {
        let run = self.run(k);
        (&self.sources[run.clone()], &self.powers[run])
    }

    /// `Φ_in` of mirror `k` along `source` (zero where none arrived).
    pub fn power(&self, k: u32, source: u32) -> Rgb {
        let run = self.run(k);
        match self.sources[run.clone()].binary_search(&source) {
            Ok(i) => self.powers[run.start + i],
            Err(_) => [0.0; 3],
        }
    }
}

/// The routes of every target direction, by source, then by mirror (its ordinal), then by
/// target: the exchange's table read source by source ([`RoutesBySource::settle`]). A batch of
/// sources is one run of it, so whoever shoots a batch settles the exchange of what its
/// directions brought to the mirrors, walking that batch's routes alone. Only the routes that
/// can carry power are kept: those whose mirror has slots in their target (the others have
/// nothing to fill).
#[derive(Clone, Debug)]
pub struct RoutesBySource {
    /// `start[s]..start[s + 1]`: source `s`'s run of `routes`.
    start: Vec<usize>,
    /// (mirror ordinal, target, weight `b`).
    routes: Vec<(u32, u32, f64)>,
}

impl RoutesBySource {
    /// Turns `routes` (per target, by (mirror, source)) around over `directions` sources:
    /// `ordinal` numbers the mirrors (a surface's ordinal among the mirrors), `slotted[i]` lists
    /// the mirrors with slots in target `i` (increasing).
    pub fn new(routes: &[Vec<Route>], ordinal: &[u32], slotted: &[Vec<u32>], directions: usize) -> RoutesBySource {
        // Each target's runs of one mirror, with the mirror's ordinal, where it has slots: one
        // look-up of the target's slotted mirrors per run, not per route.
        let kept = || {
            routes.iter().enumerate().flat_map(move |(i, routes)| {
                (routes.chunk_by(|a, b| a.mirror == b.mirror))
                    .map(move |run| (i, ordinal[run[0].mirror as usize], run))
                    .filter(move |&(_, k, _)| slotted[i].binary_search(&k).is_ok())
                    .flat_map(|(i, k, run)| run.iter().map(move |route| (i, k, route)))
                    .filter(move |&(_, _, route)| (route.source as usize) < directions)
            })
        };
        let mut start = vec![0usize; directions + 1];
        for (_, _, route) in kept() {
            start[route.source as usize + 1] += 1;
        }
        for s in 0..directions {
            start[s + 1] += start[s];
        }
        let mut next = start.clone();
        let mut by_source = vec![(0, 0, 0.0); start[directions]];
        for (i, k, route) in kept() {
            let at = &mut next[route.source as usize];
            by_source[*at] = (k, i as u32, route.weight);
            *at += 1;
        }
        // Filled target by target: each source's run is by target; by (mirror, target) now, to
        // walk beside the source's `Φ_in` (by mirror), each source's run on its own thread. A
        // stable sort: were a (mirror, target) pair there twice, its routes would stay in the
        // target's order.
        let mut runs = Vec::with_capacity(directions);
        let mut rest = &mut by_source[..];
        for s in 0..directions {
            let (run, after) = rest.split_at_mut(start[s + 1] - start[s]);
            runs.push(run);
            rest = after;
        }
        runs.into_par_iter()
            .for_each(|run| run.sort_by_key(|&(k, target, _)| (k, target)));
        RoutesBySource {
            start,
            routes: by_source,
        }
    }

    /// Number of routes kept.
    pub fn len(&self) -> usize {
        self.routes.len()
    }

    /// Source `s`'s routes: (mirror ordinal, target, weight), by mirror, then target.
    fn of(&self, s: usize) -> &[(u32, u32, f64)] {
        match (self.start.get(s), self.start.get(s + 1)) {
            (Some(&from), Some(&to)) => &self.routes[from..to],
            _ => &[],
        }
    }

    /// The exchange of what the sources `first..first + power_in.len()` (a batch) brought to the
    /// mirrors, `power_in` being their `Φ_in`: the power that arrived, `Σ Φ_in` (source by
    /// source, mirror by mirror), what their routes reflect, `Σ b·ρs·Φ_in` per channel where
    /// positive (source by source, then by (mirror, target)), and the batches of the targets that
    /// a route carrying power feeds (`batch_of`: a target's batch), increasing. `rho(k)`: mirror
    /// `k`'s specular reflectance.
    pub fn settle(
        &self,
        first: usize,
        power_in: &[&MirrorPower],
        rho: impl Fn(u32) -> Rgb,
        batch_of: impl Fn(u32) -> usize,
    ) -> BatchArrivals {
        let mut exchange = Exchange::default();
        let mut feeds: Vec<u32> = Vec::new();
        for (s, &lit) in (first..).zip(power_in) {
            for (_, v) in lit {
                add(&mut exchange.incident, v);
            }
            let mut j = 0;
            for &(k, target, weight) in self.of(s) {
                // Both by increasing mirror: the merge's next match.
                while j < lit.len() && lit[j].0 < k {
                    j += 1;
                }
                if j == lit.len() {
                    break;
                }
                let (lit_k, pin) = lit[j];
                if lit_k != k || pin.iter().all(|&p| p <= 0.0) {
                    continue;
                }
                // A gather of the target reads this source (`Specular::gather_into`).
                let b = batch_of(target) as u32;
                if let Err(at) = feeds.binary_search(&b) {
                    feeds.insert(at, b);
                }
                let rho = rho(k);
                for c in 0..3 {
                    let carried = weight * rho[c] * pin[c];
                    if carried > 0.0 {
                        exchange.reflected[c] += carried;
                    }
                }
            }
        }
        BatchArrivals { exchange, feeds }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every (source, mirror) pair reads what the per-source lists hold, zero elsewhere, and the
    /// runs are by increasing source.
    #[test]
    fn turned_around_it_answers_as_the_lists() {
        let power_in: Vec<MirrorPower> = vec![
            vec![(0, [1.0, 0.0, 0.0]), (3, [2.0, 0.0, 0.0])],
            vec![],
            vec![(3, [0.0, 5.0, 0.0]), (4, [0.0, 0.0, 6.0]), (9, [7.0, 7.0, 7.0])],
            vec![(0, [8.0, 0.0, 0.0])],
        ];
        let known: Vec<Option<MirrorPower>> = power_in.iter().cloned().map(Some).collect();
        let index = PowerByMirror::new(&known, 5);
        for (s, list) in power_in.iter().enumerate() {
            for k in 0..6u32 {
                let want = match list.iter().find(|(m, _)| *m == k) {
                    Some(&(_, p)) if k < 5 => p,
                    _ => [0.0; 3],
                };
                assert_eq!(index.power(k, s as u32), want, "mirror {k}, source {s}");
            }
        }
        assert_eq!(index.of(0).0, [0, 3]);
        assert_eq!(index.of(3), (&[0, 2][..], &[[2.0, 0.0, 0.0], [0.0, 5.0, 0.0]][..]));
        assert!(index.of(1).0.is_empty() && index.of(9).0.is_empty() && index.of(u32::MAX).0.is_empty());
        assert_eq!(index.len(), 5);
    }

    /// Turned around over many sources, each source's run is what it would be straight from the
    /// lists: its kept routes, in the order the targets list them, then sorted
    /// stably by (mirror, target) — a (mirror, target) pair twice keeps its weights' order.
    #[test]
    fn each_source_gets_its_runs_as_the_definition() {
        let directions = 3 * 32 + 7;
        let mut seed = 12345u64;
        let mut next = |n: u64| {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 33) % n
        };
        // Surfaces 0..8 are mirrors 7..0 (ordinals run against surface numbers).
        let ordinal: Vec<u32> = (0..8).rev().collect();
        let mut routes = Vec::new();
        let mut slotted = Vec::new();
        for _ in 0..9 {
            let mut list: Vec<Route> = (0..400)
                .map(|_| Route {
                    mirror: next(8) as u32,
                    // A few past the last source, which are left out.
                    source: next(directions as u64 + 3) as u32,
                    weight: next(1000) as f64 / 7.0,
                })
                .collect();
            list.sort_by_key(|r| (r.mirror, r.source));
            routes.push(list);
            let mut slots: Vec<u32> = (0..8).filter(|_| next(4) > 0).collect();
            slots.sort_unstable();
            slotted.push(slots);
        }
        let by_source = RoutesBySource::new(&routes, &ordinal, &slotted, directions);
        let mut want: Vec<Vec<(u32, u32, f64)>> = vec![Vec::new(); directions];
        for (i, list) in routes.iter().enumerate() {
            for r in list {
                let k = ordinal[r.mirror as usize];
                if (r.source as usize) < directions && slotted[i].contains(&k) {
                    want[r.source as usize].push((k, i as u32, r.weight));
                }
            }
        }
        let mut twice = 0;
        for (s, run) in want.iter_mut().enumerate() {
            run.sort_by_key(|&(k, target, _)| (k, target));
            twice += run.windows(2).filter(|w| (w[0].0, w[0].1) == (w[1].0, w[1].1)).count();
            assert_eq!(by_source.of(s), &run[..], "source {s}");
        }
        assert!(
            twice > 0,
            "the lists hold a (mirror, target) pair twice for some source"
        );
        assert_eq!(by_source.len(), want.iter().map(Vec::len).sum::<usize>());
        assert!(by_source.of(directions).is_empty());
    }

    /// A batch of sources settles what its own routes carry, walked source by source, then by
    /// (mirror, target): a mirror without a slot in the target is left out, a source that lit
    /// nothing and a route past a source's last lit mirror carry nothing, and the batches of the
    /// targets that a carrying route feeds are listed once each.
    #[test]
    fn routes_by_source_settle_a_batch_of_sources() {
        let route = |mirror, source, weight| Route { mirror, source, weight };
        // Surfaces 10, 20, 30 are mirrors 0, 1, 2.
        let mut ordinal = vec![u32::MAX; 31];
        (ordinal[10], ordinal[20], ordinal[30]) = (0, 1, 2);
        let routes = vec![
            vec![
                route(10, 0, 0.5),
                route(10, 2, 0.25),
                route(20, 1, 1.0),
                route(20, 3, 0.5),
                route(30, 3, 0.125),
            ],
            vec![
                route(10, 1, 0.75),
                route(10, 2, 0.5),
                route(20, 3, 0.5),
                route(30, 0, 1.0),
            ],
            vec![route(20, 0, 0.3), route(20, 2, 0.7)],
        ];
        // Target 1 has no slot on mirror 1 (surface 20).
        let slotted = vec![vec![0, 1, 2], vec![0, 2], vec![1]];
        let power_in: Vec<MirrorPower> = vec![
            vec![(0, [1.0, 2.0, 0.0]), (1, [3.0, 0.0, 0.0])],
            vec![(0, [0.5, 0.5, 0.5])],
            vec![(0, [0.0, 0.0, 4.0]), (1, [1.0, 1.0, 1.0])],
            vec![],
        ];
        let rho = |k: u32| [0.9, 0.8, if k == 1 { 0.6 } else { 0.7 }];
        // Targets 0 and 1 are batch 0, target 2 batch 1.
        let batch_of = |t: u32| t as usize / 2;
        let by_source = RoutesBySource::new(&routes, &ordinal, &slotted, 4);
        assert_eq!(by_source.len(), 10, "target 1's route on mirror 1 is left out");
        for sources in [0..2, 2..4, 0..4, 3..4] {
            let power: Vec<&MirrorPower> = power_in[sources.clone()].iter().collect();
            let got = by_source.settle(sources.start, &power, rho, batch_of);
            // By definition: the routes of the sources, by (source, mirror, target).
            let mut kept: Vec<(u32, u32, usize, f64)> = (routes.iter().enumerate())
                .flat_map(|(i, routes)| routes.iter().map(move |r| (i, r)))
                .filter(|(i, r)| {
                    sources.contains(&(r.source as usize)) && slotted[*i].contains(&ordinal[r.mirror as usize])
                })
                .map(|(i, r)| (r.source, ordinal[r.mirror as usize], i, r.weight))
                .collect();
            kept.sort_by_key(|&(s, k, i, _)| (s, k, i));
            let mut want = BatchArrivals::default();
            for s in sources.clone() {
                for (_, v) in &power_in[s] {
                    add(&mut want.exchange.incident, v);
                }
            }
            for (s, k, i, weight) in kept {
                let pin = (power_in[s as usize].iter())
                    .find(|(m, _)| *m == k)
                    .map_or([0.0; 3], |p| p.1);
                if pin.iter().all(|&p| p <= 0.0) {
                    continue;
                }
                let b = batch_of(i as u32) as u32;
                if !want.feeds.contains(&b) {
                    want.feeds.push(b);
                }
                for (c, sum) in want.exchange.reflected.iter_mut().enumerate() {
                    let carried = weight * rho(k)[c] * pin[c];
                    if carried > 0.0 {
                        *sum += carried;
                    }
                }
            }
            want.feeds.sort_unstable();
            assert_eq!(got, want, "sources {sources:?}");
        }
        // Sources 2 and 3: source 2 feeds targets 0, 1 (mirror 0) and 2 (mirror 1); source 3
        // lit nothing.
        let power: Vec<&MirrorPower> = power_in[2..4].iter().collect();
        let got = by_source.settle(2, &power, rho, batch_of);
        assert_eq!(got.feeds, [0, 1]);
        assert_eq!(got.exchange.incident, [1.0, 1.0, 5.0]);
        assert_eq!(
            got.exchange.reflected,
            [0.7 * 0.9, 0.7 * 0.8, 0.25 * 0.7 * 4.0 + 0.5 * 0.7 * 4.0 + 0.7 * 0.6]
        );
    }
}
