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

use super::shoot::{Geometry, Scratch, for_each_ray};
use crate::psf::Subfields;
use crate::scene::Scene;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
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
        let edges = sends_to(geometry, subfields);
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
        plan.lit_mirrors = (0..n as u32)
            .filter(|&s| scene.material(s as usize).is_mirror() && lit[s as usize] != u32::MAX)
            .map(|s| (s, lit[s as usize]))
            .collect();
        plan
    }
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
    fn counted(scene: &Scene) -> Plan {
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
fn sends_to(geometry: Geometry, subfields: &Subfields) -> Vec<(u32, u32)> {
    let mut edges: Vec<(u32, u32)> = (0..subfields.len())
        .into_par_iter()
        .map_init(Scratch::default, |scratch, d| {
            let sub = &subfields.get(d);
            let mut pairs = Vec::new();
            for_each_ray(geometry, sub, None, scratch, |hits| {
                for w in hits.windows(2) {
                    let (a, b) = (w[0].surface, w[1].surface);
                    if w[0].faces_forward() && w[1].faces_backward() {
                        pairs.push((a, b));
                        pairs.push((b, a));
                    }
                }
            });
            pairs.sort_unstable();
            pairs.dedup();
            pairs
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
