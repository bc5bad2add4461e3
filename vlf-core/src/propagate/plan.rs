//! The plan: what a propagation will simulate, decided before it starts.
//!
//! A scene should pay only for the effects it has. Without mirrors there is
//! no specular state at all: no directional maps, no routes, no exchange, no
//! per-hit mirror bookkeeping. With mirrors, the subfields tell which surface
//! can send light to which (two surfaces facing each other along some ray);
//! a breadth-first search from the emitters over that graph gives, for every
//! mirror, the first iteration in which light can arrive on it. Mirrors light
//! never reaches get no maps (they act as absorbers — they never receive
//! anything anyway), and iterations before the first mirror is lit skip the
//! specular work entirely.

use super::shoot::{Geometry, RayHit, Scratch, walk_tile};
use crate::psf::Subfields;
use crate::scene::Scene;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::fmt;

/// What will be simulated.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    pub surfaces: usize,
    pub emitters: usize,
    pub diffuse: usize,
    pub mirrors: usize,
    /// Mirrors light can reach, as (surface, first iteration it arrives).
    pub lit_mirrors: Vec<(u32, u32)>,
    /// Mirror slots per direction, summed over directions (memory of each map).
    pub mirror_slots: usize,
    /// Whether perturbation is applied (it is not with mirrors: directional
    /// maps exist only for the true directions).
    pub perturbation: bool,
    /// The σ of the Next maps' filter, if it runs ([`super::Options::filter_for`]).
    #[serde(default)]
    pub filter: Option<f64>,
}

impl Plan {
    /// Mirror surfaces that get directional maps.
    pub fn mapped_mirrors(&self) -> Vec<u32> {
        self.lit_mirrors.iter().map(|&(m, _)| m).collect()
    }

    /// The first iteration in which any mirror receives light.
    pub fn first_mirror_iteration(&self) -> Option<u32> {
        self.lit_mirrors.iter().map(|&(_, k)| k).min()
    }

    /// Counts surfaces by kind; finds which mirrors light reaches, and when.
    pub(crate) fn new(scene: &Scene, geometry: Geometry, subfields: &Subfields) -> Plan {
        let mut plan = Plan::counted(scene);
        if plan.mirrors == 0 {
            return plan;
        }
        plan.lit_mirrors = lit_mirrors(scene, &sends_to(geometry, subfields, 0..subfields.len()));
        plan
    }
}

/// The mirrors light reaches, as (surface, first iteration it arrives), by surface, from the
/// pairs of surfaces that face each other along some ray (`edges`, sorted: [`sends_to`] of
/// every direction, in one piece or the union of several).
pub(crate) fn lit_mirrors(scene: &Scene, edges: &[(u32, u32)]) -> Vec<(u32, u32)> {
    // Breadth-first over iterations: `shoots[s]` = first iteration in
    // which s has light to send; a receiver of it relays one later.
    let n = scene.surfaces.len();
    let mut shoots = vec![u32::MAX; n];
    let mut lit = vec![u32::MAX; n];
    let mut frontier: Vec<u32> = (0..n as u32)
        .filter(|&s| scene.material(s as usize).is_emitter())
        .collect();
    for &s in &frontier {
        shoots[s as usize] = 0;
    }
    let mut k = 0;
    while !frontier.is_empty() {
        let mut next = Vec::new();
        for &a in &frontier {
            let from = edges.partition_point(|e| e.0 < a);
            for &(_, b) in edges[from..].iter().take_while(|e| e.0 == a) {
                lit[b as usize] = lit[b as usize].min(k);
                let m = scene.material(b as usize);
                if (m.is_diffuse() || m.is_mirror()) && shoots[b as usize] == u32::MAX {
                    shoots[b as usize] = k + 1;
                    next.push(b);
                }
            }
        }
        next.sort_unstable();
        frontier = next;
        k += 1;
    }
    (0..n as u32)
        .filter(|&s| scene.material(s as usize).is_mirror() && lit[s as usize] != u32::MAX)
        .map(|s| (s, lit[s as usize]))
        .collect()
}

impl Plan {
    /// The plan of `scene` with the mirrors light reaches known (a job's survey,
    /// [`super::survey::Survey::lit_mirrors`]): no pass over the subfields.
    pub(crate) fn surveyed(scene: &Scene, lit_mirrors: Vec<(u32, u32)>) -> Plan {
        Plan {
            lit_mirrors,
            ..Plan::counted(scene)
        }
    }

    /// The surfaces of `scene` counted by kind; nothing decided yet.
    pub(crate) fn counted(scene: &Scene) -> Plan {
        let kinds = |f: fn(&crate::scene::Material) -> bool| {
            (0..scene.surfaces.len()).filter(|&s| f(scene.material(s))).count()
        };
        Plan {
            surfaces: scene.surfaces.len(),
            emitters: kinds(|m| m.is_emitter()),
            diffuse: kinds(|m| m.is_diffuse()),
            mirrors: kinds(|m| m.is_mirror()),
            ..Plan::default()
        }
    }
}

/// All (sender, receiver) surface pairs that face each other along some ray
/// of some subfield, sorted.
///
/// A pair is two consecutive hits of a ray, the front one facing along the direction and the
/// one behind facing back. So the pairs a tile's rays can add are among its surfaces facing
/// forward × those facing back, and once a direction has found all of those, walking the
/// tile's rays (a sort by depth per ray) cannot add one: the tile is passed over. The set is
/// the same as walking every ray's, and it is found much sooner: the same few pairs (floor
/// and ceiling, wall and mirror) recur over most of a direction's tiles.
///
/// Over the directions `range` (all of them for a plan; a part of them for a
/// [`super::survey::SurveyPart`]), sorted and without repeats: parts unite into the whole's set.
pub(crate) fn sends_to(geometry: Geometry, subfields: &Subfields, range: std::ops::Range<usize>) -> Vec<(u32, u32)> {
    /// Tiles with more candidate pairs than this are walked without checking them.
    const CHECKED: usize = 256;
    let mut edges: Vec<(u32, u32)> = range
        .into_par_iter()
        .map_init(Scratch::default, |scratch, d| {
            let sub = &subfields.get(d);
            let w = sub.frame.w;
            let forward = |s: u32| geometry.scene.surfaces[s as usize].normal.dot(w) >= 0.0;
            let mut found: HashSet<(u32, u32)> = HashSet::new();
            let (mut fronts, mut backs) = (Vec::new(), Vec::new());
            scratch.begin_direction();
            for k in 0..sub.tile_count() {
                let entries = sub.tile(k);
                fronts.clear();
                backs.clear();
                for e in entries {
                    match forward(e.surface) {
                        true => fronts.push(e.surface),
                        false => backs.push(e.surface),
                    }
                }
                let candidates = fronts.len() * backs.len();
                if candidates == 0
                    || (candidates <= CHECKED && fronts.iter().all(|&a| backs.iter().all(|&b| found.contains(&(a, b)))))
                {
                    continue;
                }
                walk_tile(geometry, sub, k, None, scratch, &mut |hits: &[RayHit]| {
                    for w in hits.windows(2) {
                        let (a, b) = (w[0].surface, w[1].surface);
                        if w[0].faces_forward() && w[1].faces_backward() {
                            found.insert((a, b));
                            found.insert((b, a));
                        }
                    }
                });
            }
            found.into_iter().collect::<Vec<_>>()
        })
        .flatten()
        .collect();
    edges.sort_unstable();
    edges.dedup();
    edges
}

impl fmt::Display for Plan {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "plan: {} surfaces ({} emitting, {} diffuse, {} mirrors)",
            self.surfaces, self.emitters, self.diffuse, self.mirrors
        )?;
        if self.mirrors == 0 {
            writeln!(f, "  specular: none — no mirror maps, no reflection work")?;
        } else if self.lit_mirrors.is_empty() {
            writeln!(
                f,
                "  specular: no mirror can receive light — mirrors act as absorbers, no maps"
            )?;
        } else {
            let first = self.first_mirror_iteration().unwrap_or(0);
            writeln!(
                f,
                "  specular: {} of {} mirrors reachable, first lit in iteration {}; {} mirror slots over all directions ({:.1} MB per map)",
                self.lit_mirrors.len(),
                self.mirrors,
                first + 1,
                self.mirror_slots,
                self.mirror_slots as f64 * 24.0 / 1e6
            )?;
            if first > 0 {
                writeln!(
                    f,
                    "  specular: iterations 1..={first} skip mirror work (no light has reached one yet)"
                )?;
            }
        }
        if !self.perturbation {
            write!(f, "  perturbation: off")?;
            if self.mirrors > 0 && !self.lit_mirrors.is_empty() {
                write!(f, " (directional mirror maps exist only on the true directions)")?;
            }
            writeln!(f)?;
        }
        match self.filter {
            Some(sigma) => writeln!(f, "  filter: σ = {sigma} texels (Next maps)")?,
            None => writeln!(f, "  filter: off")?,
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::propagate::shoot::for_each_ray;
    use crate::propagate::{Options, Propagation, Stop};
    use crate::psf::GridSize;
    use crate::scene::{ImportOptions, load_obj};

    /// Every ray of every direction walked, every pair kept: what [`sends_to`] must find.
    fn walking_every_ray(geometry: Geometry, subfields: &Subfields) -> Vec<(u32, u32)> {
        let mut scratch = Scratch::default();
        let mut edges = Vec::new();
        for d in 0..subfields.len() {
            for_each_ray(geometry, &subfields.get(d), None, &mut scratch, |hits| {
                for w in hits.windows(2) {
                    if w[0].faces_forward() && w[1].faces_backward() {
                        edges.push((w[0].surface, w[1].surface));
                        edges.push((w[1].surface, w[0].surface));
                    }
                }
            });
        }
        edges.sort_unstable();
        edges.dedup();
        edges
    }

    #[test]
    fn passing_over_tiles_whose_pairs_are_known_finds_every_pair() {
        // The mirror scene (boxes in front of mirrors: pairs that only a few tiles hold) and
        // the Cornell box (a lamp flush with its ceiling: hidden hits), at two resolutions.
        for (name, n) in [("mirrors.obj", 16), ("mirrors.obj", 64), ("cornell.obj", 32)] {
            let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../scenes")
                .join(name);
            let (scene, _) = load_obj(&path, &ImportOptions::default()).unwrap();
            let options = Options {
                directions: 129,
                grid: GridSize::new(n, 8).unwrap(),
                stop: Stop::Iterations(1),
                ..Options::default()
            };
            let p = Propagation::new(scene, options).unwrap();
            let geometry = Geometry {
                scene: &p.scene,
                atlas: &p.atlas,
                stacking: &p.stacking,
            };
            let found = sends_to(geometry, &p.subfields, 0..p.subfields.len());
            assert_eq!(found, walking_every_ray(geometry, &p.subfields), "{name}, N = {n}");
            assert!(
                found.len() > 2 * p.scene.surfaces.len(),
                "{name}: {} pairs",
                found.len()
            );
        }
    }
}
