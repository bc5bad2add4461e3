//! Arrivals waiting to be reflected, and what they come to, settled batch by batch of sources.

use super::by_mirror::RoutesBySource;
use super::{PowerByMirror, Specular};
use crate::directions::DirectionSet;
use crate::propagate::batching::Batching;
use crate::scene::{Rgb, Scene};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, OnceLock};

/// Power bookkeeping of one exchange (per channel).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Exchange {
    /// Power that arrived on mirrors (front side).
    pub incident: Rgb,
    /// Power reflected into the next unshot maps: ρs × incident, exactly
    /// (what the routes carry, see [`Specular::settle_batch`]).
    pub reflected: Rgb,
}

/// The last iteration's arrivals on mirrors, waiting to be reflected.
///
/// The exchange runs at the start of the iteration that shoots its result, not at the end of
/// the one that produced the arrivals: a snapshot holds the arrivals (the incident maps), and
/// whoever shoots a direction gathers its unshot map then. In the distributed service that is
/// the worker with the direction's lease, so the maps go from worker to worker (a worker that
/// keeps its directions reads nothing back).
///
/// **What travels is settled where the arrivals were made.** A gather reads the power `Φ_in`
/// that each route's source brought to its mirror, a function of the source's incident map
/// ([`Specular::power_in_of`]): whoever gathers finds it from the maps it restores, the same
/// bits as where they were shot. So `Φ_in` itself goes nowhere. What the rest of the run asks
/// of the arrivals is settled by whoever shot them, batch by batch of sources
/// ([`BatchArrivals`]): the exchange's power, which the stop rule and a job's status read, and
/// which batches of sources each batch of targets gathers from, which tells a worker what to
/// read. A coordinator adds those up in batch order ([`Settled`]); it used to carry every
/// direction's `Φ_in` from the workers' outputs into the next head, where every worker read it
/// again: for the 47 794-triangle mirror dragon at l = 2049, N = 128, 93 MB and about a second
/// of every iteration, half of it serial on the coordinator.
#[derive(Debug, Serialize, Deserialize)]
pub struct Pending {
    /// What the arrivals come to ([`Settled`]). `None` only as read from an earlier build's
    /// blob, which held every direction's `Φ_in` instead: restoring it settles them
    /// ([`crate::propagate::Propagation::restore_head`]).
    pub settled: Option<Settled>,
    /// `Φ_in` where it is known here: of the directions whose arrival maps this process holds
    /// (or as an earlier build's blob held it), `None` for the others; empty when none is.
    #[serde(skip)]
    pub(super) power_in: Vec<Option<MirrorPower>>,
    /// `power_in` by mirror, as a gather's routes ask for it: turned around once, again only
    /// after more of it became known.
    #[serde(skip)]
    pub(super) by_mirror: OnceLock<Box<PowerByMirror>>,
}

/// What a [`Pending`]'s arrivals come to, added up over every batch of sources in order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Settled {
    /// The exchange's power bookkeeping: the sum of the batches' [`BatchArrivals::exchange`].
    pub exchange: Exchange,
    /// Per batch of target directions, the batches of source directions whose arrivals its
    /// gathers read (increasing): what a worker reads before it gathers
    /// ([`Specular::source_batches`]).
    pub sources: Vec<Vec<u32>>,
}

impl Settled {
    /// The arrivals of every batch of sources, in order, added up: `parts[b]` of batch `b` of
    /// `batches`.
    pub fn of_parts<'a>(parts: impl IntoIterator<Item = &'a BatchArrivals>, batches: usize) -> Settled {
        let mut settled = Settled {
            exchange: Exchange::default(),
            sources: vec![Vec::new(); batches],
        };
        for (b, part) in parts.into_iter().enumerate() {
            add(&mut settled.exchange.incident, &part.exchange.incident);
            add(&mut settled.exchange.reflected, &part.exchange.reflected);
            for &t in &part.feeds {
                if let Some(sources) = settled.sources.get_mut(t as usize) {
                    sources.push(b as u32);
                }
            }
        }
        settled
    }
}

/// What one batch of source directions brought to the mirrors, settled by whoever shot it
/// ([`Specular::settle_batch`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BatchArrivals {
    /// The power its directions brought to the mirrors (`Σ Φ_in`), and what their routes reflect
    /// (`Σ b·ρs·Φ_in`).
    pub exchange: Exchange,
    /// The batches of target directions that a route of its carrying power feeds (increasing).
    pub feeds: Vec<u32>,
}

impl Pending {
    /// Arrivals whose settling `settled` tells, their `Φ_in` known nowhere yet: each direction's
    /// becomes known as its arrival maps are restored here ([`Specular::know_arrivals`]).
    pub fn new(settled: Settled) -> Pending {
        Pending {
            settled: Some(settled),
            power_in: Vec::new(),
            by_mirror: OnceLock::new(),
        }
    }

    /// Arrivals as earlier builds stored them: every direction's `Φ_in`, not settled yet.
    pub fn of_power_in(power_in: Vec<MirrorPower>) -> Pending {
        Pending {
            settled: None,
            power_in: power_in.into_iter().map(Some).collect(),
            by_mirror: OnceLock::new(),
        }
    }

    /// What the arrivals come to, once settled.
    pub fn settled(&self) -> Option<&Settled> {
        self.settled.as_ref()
    }

    /// `Φ_in` of direction `d`, where it is known here.
    pub fn power_in(&self, d: usize) -> Option<&MirrorPower> {
        self.power_in.get(d).and_then(Option::as_ref)
    }

    /// `Φ_in` of every direction, when it is known here for all `directions`.
    pub(crate) fn all_power_in(&self, directions: usize) -> Option<Vec<&MirrorPower>> {
        (0..directions).map(|d| self.power_in(d)).collect()
    }

    /// Takes `power` as direction `d`'s `Φ_in`, of `directions`.
    pub(crate) fn know(&mut self, directions: usize, d: usize, power: MirrorPower) {
        if self.power_in.len() != directions {
            self.power_in.resize(directions, None);
        }
        self.power_in[d] = Some(power);
        self.by_mirror = OnceLock::new();
    }
}

/// A clone turns its known `Φ_in` around afresh if it needs it.
impl Clone for Pending {
    fn clone(&self) -> Pending {
        Pending {
            settled: self.settled.clone(),
            power_in: self.power_in.clone(),
            by_mirror: OnceLock::new(),
        }
    }
}

/// Two [`Pending`]s are equal when they settle alike: the `Φ_in` a process knows is a function of
/// the arrival maps it holds, which a checkpoint compares apart. Not settled yet (as an earlier
/// build stored them), they are equal when they hold the same `Φ_in`.
impl PartialEq for Pending {
    fn eq(&self, other: &Pending) -> bool {
        let n = self.power_in.len().max(other.power_in.len());
        let same_power = || (0..n).all(|d| self.power_in(d) == other.power_in(d));
        self.settled == other.settled && (self.settled.is_some() || same_power())
    }
}

/// `Φ_in` of one direction: `(k, Φ)` for every mirror `k` (by its ordinal in
/// [`Specular::mirrors`]) that received power `Φ` ≠ 0, by increasing `k`.
///
/// Sparse because a direction's rays meet few of a scan's mirror polygons:
/// at N = 64 a triangle of the 47 794-triangle dragon is far smaller than a
/// ray cell, so a direction crosses about one in a hundred. Dense, `Φ_in`
/// was `l × mirrors` triples — 588 MB in every snapshot of that dragon as a
/// mirror at l = 513, 9.4 GB at l = 8193 — nearly all zeros. Omitted entries
/// are zeros: every use skips a mirror without power, so the sums are those
/// of the dense table, to the bit.
pub type MirrorPower = Vec<(u32, Rgb)>;

impl Specular {
    /// What the sources of batch `batch` of `batching` brought to the mirrors, `power_in` being
    /// their `Φ_in` in order ([`Specular::power_in_of`]): the exchange's power and the batches
    /// of targets they feed ([`BatchArrivals`]), what whoever shot the batch reports. The
    /// power is the sum the gathers scale their routes to (`b·ρs·Φ_in` per route with slots to
    /// fill), so whoever never sees a map knows the exchange's power, within rounding of what
    /// the gathered maps add up to.
    ///
    /// One pass over the batch's routes, by source ([`RoutesBySource`]) beside each source's
    /// `Φ_in`: every batch is settled apart, and [`Settled::of_parts`] adds them in batch
    /// order, so the bits do not depend on who settled which.
    pub fn settle_batch(
        &self,
        scene: &Scene,
        batching: &Batching,
        batch: usize,
        power_in: &[&MirrorPower],
    ) -> BatchArrivals {
        let first = batching.range(batch).start;
        let rho = |k: u32| scene.materials[scene.surfaces[self.mirrors[k as usize] as usize].material].specular;
        (self.routes_by_source()).settle(first, power_in, rho, |target| batching.batch_of(target as usize))
    }

    /// [`Specular::settle_batch`] of each of `batches`, in parallel, in order: `power_in` is the
    /// `Φ_in` of their directions, in order (those of a block, or of every batch). What a worker
    /// reports of a block, what a coordinator finds of an earlier build's output, and what one
    /// process settles of a whole pass, alike.
    pub fn settle_batches(
        &self,
        scene: &Scene,
        batching: &Batching,
        batches: std::ops::Range<usize>,
        power_in: &[impl std::borrow::Borrow<MirrorPower> + Sync],
    ) -> Vec<BatchArrivals> {
        let first = batching.directions_of(batches.clone()).start;
        (batches.into_par_iter())
            .map(|b| {
                let range = batching.range(b);
                let power: Vec<&MirrorPower> = (power_in[range.start - first..range.end - first].iter())
                    .map(|p| p.borrow())
                    .collect();
                self.settle_batch(scene, batching, b, &power)
            })
            .collect()
    }

    /// [`Specular::settle_batches`] of every batch, `power_in` being every direction's `Φ_in`,
    /// added up in order: what one process that shot them all leaves pending.
    pub fn settle_all(&self, scene: &Scene, batching: &Batching, power_in: &[&MirrorPower]) -> Settled {
        let parts = self.settle_batches(scene, batching, 0..batching.count(), power_in);
        Settled::of_parts(&parts, batching.count())
    }

    /// The routes by source, turned around once ([`RoutesBySource`]).
    fn routes_by_source(&self) -> &RoutesBySource {
        self.routes_by_source.get_or_init(|| {
            let started = std::time::Instant::now();
            let by_source = RoutesBySource::new(&self.routes, &self.ordinal, &self.slotted, self.views.len());
            tracing::debug!(
                routes = by_source.len(),
                seconds = started.elapsed().as_secs_f64(),
                "routes turned around by source"
            );
            Arc::new(by_source)
        })
    }

    /// Turns the routes around by source now ([`RoutesBySource`]), if no settle did yet: what a
    /// worker does as it sets up. Left to its first block's settle, it was that block's cost
    /// (0.7–0.9 s on one thread for the 4 million routes of the 47 794-triangle mirror dragon
    /// at l = 2049, N = 128, against 0.1–0.2 s of shooting a batch), and the scheduler took the
    /// batches of each worker's first lease for dear ones.
    pub fn prepare_settle(&self) {
        if self.routes.iter().any(|r| !r.is_empty()) {
            self.routes_by_source();
        }
    }

    /// Whether the routes are turned around by source already ([`Specular::prepare_settle`]).
    pub fn settle_prepared(&self) -> bool {
        self.routes_by_source.get().is_some()
    }

    /// The exchange's power of the pending arrivals, once settled.
    pub fn settled(&self) -> Option<Exchange> {
        Some(self.pending.as_ref()?.settled.as_ref()?.exchange)
    }

    /// Settles pending arrivals that an earlier build stored as every direction's `Φ_in`
    /// ([`Pending::of_power_in`]), batch by batch as this build's workers do. Arrivals settled
    /// already, or none, are left as they are.
    pub(crate) fn settle_pending(&mut self, scene: &Scene, batching: &Batching) {
        let l = self.views.len();
        let Some(pending) = &self.pending else {
            return;
        };
        if pending.settled.is_some() {
            return;
        }
        let power_in = pending
            .all_power_in(l)
            .expect("an earlier build's pending arrivals know every Φ_in");
        let settled = self.settle_all(scene, batching, &power_in);
        if let Some(pending) = &mut self.pending {
            pending.settled = Some(settled);
        }
    }

    /// Takes `Φ_in` of the directions `range` from their arrival maps, where held: what a
    /// process does as it restores or adopts them while arrivals are pending, so that its
    /// gathers read the same `Φ_in` as where the maps were shot.
    pub fn know_arrivals(&mut self, directions: &DirectionSet, range: std::ops::Range<usize>) {
        if self.pending.is_none() {
            return;
        }
        let known: Vec<(usize, MirrorPower)> = range
            .into_par_iter()
            .filter(|&d| self.holds(d, &self.maps[d].incident))
            .map(|d| (d, self.power_in_of(directions, d, &self.maps[d].incident)))
            .collect();
        let l = self.views.len();
        if let Some(pending) = &mut self.pending {
            for (d, power) in known {
                pending.know(l, d, power);
            }
        }
    }

    /// Takes `power`, per direction of `range`, as their `Φ_in`: what a block found of the
    /// arrival maps it shot, as it hands them over ([`crate::propagate::Propagation::adopt_mirrors`]).
    pub(crate) fn know_power(&mut self, range: std::ops::Range<usize>, power: Vec<MirrorPower>) {
        let l = self.views.len();
        if let Some(pending) = &mut self.pending {
            for (d, power) in range.zip(power) {
                pending.know(l, d, power);
            }
        }
    }
}

/// Adds `v` to `acc`, channel by channel.
pub(super) fn add(acc: &mut Rgb, v: &Rgb) {
    for (a, b) in acc.iter_mut().zip(v) {
        *a += b;
    }
}
