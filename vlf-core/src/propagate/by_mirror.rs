//! The exchange turned around: `Φ_in` and the routes, by mirror.
//!
//! The exchange asks one question of `Φ_in` per [`Route`]: how much power arrived on the
//! route's mirror along its source direction. `Φ_in` is stored by source ([`MirrorPower`]: per
//! direction, the mirrors it lit) and a target's routes come by mirror (sorted by (mirror,
//! source)), so each question was a binary search in another direction's list: a cache miss per
//! step, four million routes an iteration for the mirror dragon (47 794 triangles, l = 2049,
//! N = 128), 61 % of its coordinator's CPU, all of it between iterations, where the workers
//! wait.
//!
//! * [`PowerByMirror`]: `Φ_in` by mirror, then source, turned around once per
//!   [`Pending`](super::specular::Pending). A worker's gather looks its routes up in it.
//! * [`RoutesByMirror`]: the routes by mirror, then source, then target, once per propagation
//!   (a function of the geometry), for [`Specular::settle`](super::specular::Specular::settle):
//!   it walks each lit mirror's routes beside its sources, one merge, no search, and adds each
//!   route into its target's sum. Mirror after mirror, a target's sum takes its routes in their
//!   (mirror, source) order, the order of the definition, so the sums are its bits.

use super::specular::{MirrorPower, Route};
use crate::scene::Rgb;

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
    /// The index of `power_in` (per source direction, as [`MirrorPower`]) over `mirrors`
    /// mirrors: a counting sort by mirror, stable in the source. `power_in` is as a restore
    /// checks it (`check_pending`: each list by strictly increasing mirror, every mirror below
    /// `mirrors`); an entry for a mirror number out of range is left out all the same, as no
    /// route could ask for it.
    pub fn new(power_in: &[MirrorPower], mirrors: usize) -> PowerByMirror {
        let known = |k: u32| (k as usize) < mirrors;
        let mut start = vec![0u32; mirrors + 1];
        for &(k, _) in power_in.iter().flatten().filter(|(k, _)| known(*k)) {
            start[k as usize + 1] += 1;
        }
        for k in 0..mirrors {
            start[k + 1] += start[k];
        }
        let mut next = start.clone();
        let mut sources = vec![0; start[mirrors] as usize];
        let mut powers = vec![[0.0; 3]; start[mirrors] as usize];
        for (source, list) in power_in.iter().enumerate() {
            for &(k, power) in list.iter().filter(|(k, _)| known(*k)) {
                let at = &mut next[k as usize];
                sources[*at as usize] = source as u32;
                powers[*at as usize] = power;
                *at += 1;
            }
        }
        PowerByMirror { start, sources, powers }
    }

    /// Number of (mirror, source) pairs that carry power.
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

/// The routes of every target direction, by mirror (its ordinal), then by source, then by
/// target: the exchange's table read mirror by mirror ([`RoutesByMirror::reflected`]). Only the
/// routes that can carry power are kept: those whose mirror has slots in their target (the
/// others have nothing to fill).
#[derive(Clone, Debug)]
pub struct RoutesByMirror {
    /// `start[k]..start[k + 1]`: mirror `k`'s run of `routes`.
    start: Vec<u32>,
    /// (source, target, weight `b`).
    routes: Vec<(u32, u32, f64)>,
}

impl RoutesByMirror {
    /// Turns `routes` (per target, by (mirror, source)) around: `ordinal` numbers the mirrors
    /// (a surface's ordinal among `mirrors`), `slotted[i]` lists the mirrors with slots in target
    /// `i` (increasing).
    pub fn new(routes: &[Vec<Route>], ordinal: &[u32], slotted: &[Vec<u32>], mirrors: usize) -> RoutesByMirror {
        // Each target's runs of one mirror, with the mirror's ordinal, where it has slots.
        let kept = || {
            routes.iter().enumerate().flat_map(move |(i, routes)| {
                (routes.chunk_by(|a, b| a.mirror == b.mirror))
                    .map(move |run| (i, ordinal[run[0].mirror as usize], run))
                    .filter(move |&(_, k, _)| slotted[i].binary_search(&k).is_ok())
            })
        };
        let mut start = vec![0u32; mirrors + 1];
        for (_, k, run) in kept() {
            start[k as usize + 1] += run.len() as u32;
        }
        for k in 0..mirrors {
            start[k + 1] += start[k];
        }
        let mut next = start.clone();
        let mut by_mirror = vec![(0, 0, 0.0); start[mirrors] as usize];
        for (i, k, run) in kept() {
            for route in run {
                let at = &mut next[k as usize];
                by_mirror[*at as usize] = (route.source, i as u32, route.weight);
                *at += 1;
            }
        }
        // Filled target by target: each mirror's run is by target, and by source within one;
        // by (source, target) now. A stable sort: were a (source, target) pair there twice, its
        // routes would stay in the target's order.
        let mut rest = &mut by_mirror[..];
        for k in 0..mirrors {
            let (run, after) = rest.split_at_mut((start[k + 1] - start[k]) as usize);
            run.sort_by_key(|&(source, target, _)| (source, target));
            rest = after;
        }
        RoutesByMirror {
            start,
            routes: by_mirror,
        }
    }

    /// Number of routes kept.
    pub fn len(&self) -> usize {
        self.routes.len()
    }

    /// What each of `targets` target directions' gather reflects into its unshot map:
    /// `Σ b·ρs·Φ_in` over its routes that carry power, per channel where positive, added in the
    /// target's route order. `rho(k)`: mirror `k`'s specular reflectance.
    pub fn reflected(&self, lit: &PowerByMirror, rho: impl Fn(u32) -> Rgb, targets: usize) -> Vec<Rgb> {
        let mut reflected = vec![[0.0; 3]; targets];
        for k in 0..self.start.len().saturating_sub(1) {
            let (sources, powers) = lit.of(k as u32);
            if sources.is_empty() {
                continue;
            }
            let rho = rho(k as u32);
            let mut j = 0;
            for &(source, target, weight) in &self.routes[self.start[k] as usize..self.start[k + 1] as usize] {
                // Both by increasing source: the merge's next match.
                while j < sources.len() && sources[j] < source {
                    j += 1;
                }
                if j == sources.len() {
                    break;
                }
                let pin = powers[j];
                if sources[j] != source || pin.iter().all(|&p| p <= 0.0) {
                    continue;
                }
                let sum = &mut reflected[target as usize];
                for c in 0..3 {
                    let carried = weight * rho[c] * pin[c];
                    if carried > 0.0 {
                        sum[c] += carried;
                    }
                }
            }
        }
        reflected
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
        let index = PowerByMirror::new(&power_in, 5);
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

    /// Routes read mirror by mirror give each target the sum of its own routes taken in order:
    /// a mirror without a slot in the target is left out, sources interleave between targets,
    /// a source that lit nothing and a route past the mirror's last lit source carry nothing.
    #[test]
    fn routes_by_mirror_sum_each_targets_routes_in_order() {
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
        let lit = PowerByMirror::new(&power_in, 3);
        let by_mirror = RoutesByMirror::new(&routes, &ordinal, &slotted, 3);
        assert_eq!(by_mirror.len(), 10, "target 1's route on mirror 1 is left out");
        let got = by_mirror.reflected(&lit, rho, 3);
        for (i, routes) in routes.iter().enumerate() {
            let mut want = [0.0; 3];
            for r in routes {
                let k = ordinal[r.mirror as usize];
                if !slotted[i].contains(&k) {
                    continue;
                }
                let pin = lit.power(k, r.source);
                for c in 0..3 {
                    let carried = r.weight * rho(k)[c] * pin[c];
                    if carried > 0.0 {
                        want[c] += carried;
                    }
                }
            }
            assert_eq!(got[i], want, "target {i}");
        }
        assert_eq!(got[2], [0.3 * 0.9 * 3.0 + 0.7 * 0.9, 0.7 * 0.8, 0.7 * 0.6]);
    }
}
