//! Specular transport: ideal mirrors in the light field.
//!
//! A diffuse surface's outgoing radiance is the same in every direction and
//! lives in its texel maps; a mirror's is directional, so it lives **per
//! direction**, on the rays of each subfield that cross the mirror: one
//! value per *mirror slot* (a (mirror, ray) crossing, see [`MirrorLayout`]).
//! Each direction owns three maps over its mirror slots ([`DirectionMaps`]):
//!
//! * `unshot` — radiance still to be sent from the mirror along this
//!   direction (leaving its front side). Shot like a diffuse sender's, but
//!   only along this one direction: this is how caustics (L S D) and mirrors
//!   in mirrors (L S S D) arise.
//! * `total` — every radiance that ever left the mirror along the ray: after
//!   the last iteration, the tile radiance maps the walkthrough reads.
//! * `incident` — radiance that arrived on the mirror along this direction
//!   during the last shot, waiting to be reflected.
//!
//! **Held where they are read.** A process allocates a direction's maps only when it reads or
//! writes them ([`Unheld`]): one process running the whole propagation holds every direction's,
//! a worker of the service those of the directions its leases shoot and of the directions they
//! gather from, a coordinator none. Allocated for every direction in every process, the maps
//! were the largest part of a mirror job's memory, everywhere: three maps of 1.07 GB each for
//! the mirror scene at l = 8193, N = 256.
//!
//! ## Reflection between iterations (the exchange)
//!
//! Light arriving on mirror `P` along oriented direction `ω` leaves along the
//! mirror image `r = ω − 2(ω·n)n`. `r` falls in a spherical triangle of three
//! directions `i₁, i₂, i₃` with barycentric weights `b_k`; the reflected
//! power `ρs·Φ_in(P, ω)` is split over them by `b_k`. That is a fixed table,
//! the [`Route`]s: for each target direction `i`, the (mirror, source
//! direction, weight) triples that feed it. Each target gathers its new
//! unshot map **backwards**, as the paper does: every ray of `i` that crosses
//! `P` finds the point where it leaves `P`, projects it into the source
//! subfield `ω` and reads the incident radiance of the ray there, so no slot
//! of `i` is left empty however the two grids are sampled. The gathered
//! radiance is then scaled so that the power of route `(P, ω → i)` is
//! exactly `b·ρs·Φ_in(P, ω)`: power is conserved to rounding despite the
//! nearest-direction approximation and the resampling between grids.
//!
//! Targets are computed independently (in parallel) from read-only incident
//! maps, in a fixed route order, so the result does not depend on threads.
//!
//! **A mirror is a plane.** The polygons of a mirror chart (coplanar, one
//! material: [`crate::maps::charts`]) are one entry per tile in the subfields,
//! under their first polygon ([`crate::maps::TexelAtlas::plane_rep`]), as a
//! diffuse plane's are. So "mirror" here — a slot's, a route's, `Φ_in`'s — is
//! the plane: a wall cut into 3 200 triangles has the slots, routes and
//! power of its quad, and a look-up on any of its polygons reads the plane's
//! rays ([`MirrorLayout::locate_on_plane`]). Per polygon, routes and `Φ_in`
//! grew with the tessellation (19 200 mirror triangles at l = 513: 30 M
//! routes, 236 MB of `Φ_in` a snapshot) and a polygon narrower than a ray
//! cell lost the power routed to it.
//!
//! **When.** An iteration ends with its arrivals *pending* ([`Pending`]):
//! what they come to is settled batch by batch of sources where they were shot
//! ([`Specular::settle_batch`]: what arrived, what will be reflected — as the
//! routes carry it — and which batches gather from which), and the gather runs when the next iteration shoots
//! the target: [`Specular::gather_all`] in one process, or, in the
//! distributed service, the worker that leases the target's batch, for its
//! directions only ([`Specular::gather`]), reading the arrivals of the
//! sources ([`Specular::source_batches`]) from the snapshot or from its own memory.
//! The field's bits are the same either way.
//!
//! ## Where each part lives
//!
//! * [`layout`]: a direction's mirror slots ([`MirrorLayout`], [`MirrorView`]) and the maps
//!   over them ([`DirectionMaps`], held or not: [`Unheld`]);
//! * [`routes`]: the exchange's fixed table ([`Route`]), found from the views;
//! * [`pending`]: arrivals waiting to be reflected ([`Pending`]), settled batch by batch of
//!   sources ([`Specular::settle_batch`], [`Settled`]);
//! * [`gather`]: a target's new unshot map, read backwards from its sources' arrivals
//!   ([`Specular::gather`]);
//! * [`by_mirror`]: `Φ_in` and the routes turned around, so that settling and gathering walk
//!   them in order rather than search;
//! * this module: the state itself ([`Specular`]), built from the views, and the maps'
//!   bookkeeping (what is held, what is unshot).

mod by_mirror;
mod gather;
mod layout;
mod pending;
mod routes;

use by_mirror::{PowerByMirror, RoutesBySource};
pub use layout::{DirectionMaps, MirrorLayout, MirrorView, Unheld};
pub use pending::{BatchArrivals, Exchange, MirrorPower, Pending, Settled};
pub use routes::Route;

use super::mirror_geometry::MirrorGeometry;
use super::shoot::NO_SLOT;
use crate::directions::DirectionSet;
use crate::psf::{Footprints, RasterScratch, Subfield, Subfields};
use crate::scene::{Rgb, Scene};
use gather::GatherTable;
use rayon::prelude::*;
use std::sync::{Arc, OnceLock};

/// The specular state of a propagation.
#[derive(Clone, Debug)]
pub struct Specular {
    /// Surfaces with directional maps (mirrors that light can reach): each the first polygon
    /// of its mirror plane (see the module docs), by increasing surface number — so a mirror's
    /// ordinal here orders the routes as its surface does.
    pub mirrors: Vec<u32>,
    /// Per direction, its mirror entries alone: the mirror geometry of everything but shooting.
    /// Shared by the copies of a propagation (the workers of one process take copies of their
    /// coordinator's), as the routes and `slotted` are: a function of the geometry, never
    /// changed once found.
    pub views: Arc<[MirrorView]>,
    /// Per direction, its maps: those held, the others empty (their values: [`Unheld`]).
    pub maps: Vec<DirectionMaps>,
    /// `routes[i]`: what feeds target direction `i`, sorted by (mirror, source).
    pub routes: Arc<[Vec<Route>]>,
    /// Arrivals of the last iteration not reflected yet: then the incident
    /// maps hold them and the unshot maps are stale (see [`Pending`]).
    pub pending: Option<Pending>,
    ordinal: Vec<u32>,
    /// `slotted[d]`: the mirrors (by ordinal, increasing) that some ray of direction `d`
    /// crosses. What the exchange's bookkeeping asks of every route, known without the
    /// subfields (which a coordinator need not hold). Sparse: a direction's rays meet few of a
    /// curved mirror's triangles, and a table of every (direction, mirror) was 830 MB for the
    /// 202 520-triangle mirror dragon at l = 2049.
    slotted: Arc<[Vec<u32>]>,
    /// Per target direction, its [`GatherTable`] once its first gather found it, when
    /// [`Specular::keep_gather_tables`].
    gather_tables: Vec<OnceLock<GatherTable>>,
    /// The routes by source, for settling, once the first settle asks ([`RoutesBySource`]):
    /// shared by the copies of a propagation made after it was built (the workers of one
    /// process, `vlf run`), as it is a function of the geometry.
    routes_by_source: OnceLock<Arc<RoutesBySource>>,
    /// Whether a gather keeps the table it finds, for the next iterations' gathers of the same
    /// direction: on unless the process holds its subfields within a memory budget. The tables
    /// take 8 bytes a sample, a few samples a mirror slot (one per route), and 8 bytes a route:
    /// about 85 MB for the mirror scene at l = 2049, N = 128, whose three maps a direction hold
    /// 200 MB. Keeping them halved what its iterations spent before shooting (1.59 → 0.76 s
    /// over 11 iterations on the 2-core VM) and made the whole run 15–18 % faster.
    pub keep_gather_tables: bool,
}

impl Specular {
    /// Lays out the mirror maps of `mirrors` over the subfields of every direction and builds
    /// the reflection routes. Where `subfields` are all held, each view is cut from its
    /// subfield ([`Subfield::only`]); else the mirror planes alone are rasterised
    /// ([`Footprints::of`]), no subfield of the scene built — the same views either way.
    pub fn new(
        scene: &Scene,
        directions: &DirectionSet,
        subfields: &Subfields,
        plane_rep: &[u32],
        mirrors: Vec<u32>,
    ) -> Self {
        let (mirrors, has_maps, ordinal) = mirror_tables(scene, mirrors);
        let views: Vec<MirrorView> = if subfields.all_held() {
            subfields.map(|_, sub| MirrorView::new(sub.only(|s| has_maps[s as usize]), &has_maps))
        } else {
            let footprints = Footprints::of(scene, plane_rep, |rep| has_maps[rep as usize]);
            (0..subfields.len())
                .into_par_iter()
                .map_init(RasterScratch::default, |scratch, d| {
                    let sub = Subfield::build_with(&footprints, subfields.frame(d), subfields.grid(), scratch);
                    MirrorView::new(sub, &has_maps)
                })
                .collect()
        };
        Specular::with_views(scene, directions, mirrors, ordinal, views)
    }

    /// [`Specular::new`] where each direction's subfield restricted to the scene's mirror planes
    /// is known (`planes`, learnt with the survey's parts: [`super::SurveyPart::mirror_planes`],
    /// checked by the caller): the views are cut from them, no plane rasterised — the same views,
    /// restricted to the mirrors light reaches.
    pub(crate) fn from_mirror_planes(
        scene: &Scene,
        directions: &DirectionSet,
        planes: Vec<Subfield>,
        mirrors: Vec<u32>,
    ) -> Self {
        let (mirrors, has_maps, ordinal) = mirror_tables(scene, mirrors);
        let views = (planes.into_par_iter())
            .map(|plane| MirrorView::new(plane.only(|s| has_maps[s as usize]), &has_maps))
            .collect();
        Specular::with_views(scene, directions, mirrors, ordinal, views)
    }

    /// The state of `mirrors` (sorted, by ordinal) with these views, its routes found from them.
    fn with_views(
        scene: &Scene,
        directions: &DirectionSet,
        mirrors: Vec<u32>,
        ordinal: Vec<u32>,
        views: Vec<MirrorView>,
    ) -> Self {
        let routes = routes::find(scene, directions, &mirrors, &ordinal, &views);
        Specular::assemble(mirrors, ordinal, views, routes)
    }

    /// The specular state whose views and routes were computed elsewhere — a job's stored
    /// [`MirrorGeometry`], which [`MirrorGeometry::check`] found to be this scene's: the same
    /// state as [`Specular::new`] builds, without rasterising a mirror or finding a route.
    pub(crate) fn from_geometry(scene: &Scene, geometry: MirrorGeometry) -> Self {
        let (mirrors, has_maps, ordinal) = mirror_tables(scene, geometry.mirrors);
        let views = (geometry.views.into_par_iter())
            .map(|sub| MirrorView::new(sub, &has_maps))
            .collect();
        Specular::assemble(mirrors, ordinal, views, geometry.routes)
    }

    /// What [`Specular::from_geometry`] reads back, borrowed from this state: its views'
    /// subfields and its routes.
    pub(crate) fn geometry(&self) -> (&[u32], Vec<&Subfield>, &[Vec<Route>]) {
        (&self.mirrors, self.views.iter().map(|v| &v.sub).collect(), &self.routes)
    }

    /// The state of `mirrors` (sorted, by ordinal) with these views and routes, nothing held.
    fn assemble(mirrors: Vec<u32>, ordinal: Vec<u32>, views: Vec<MirrorView>, routes: Vec<Vec<Route>>) -> Self {
        let slotted: Vec<Vec<u32>> = views
            .iter()
            .map(|view| {
                let mut slotted: Vec<u32> = (view.layout.entries.iter())
                    .filter(|&&(_, _, e)| view.sub.entries[e as usize].rays > 0)
                    .map(|&(s, _, _)| ordinal[s as usize])
                    .collect();
                slotted.sort_unstable();
                slotted.dedup();
                slotted
            })
            .collect();
        // Zeros, allocated where first written (`hold_zeros`).
        let maps = vec![DirectionMaps::default(); views.len()];
        Specular {
            gather_tables: (0..views.len()).map(|_| OnceLock::new()).collect(),
            mirrors,
            views: views.into(),
            maps,
            routes: routes.into(),
            pending: None,
            ordinal,
            slotted: slotted.into(),
            routes_by_source: OnceLock::new(),
            keep_gather_tables: true,
        }
    }

    /// The first mirror slot of every entry of `sub`, direction `d`'s whole subfield
    /// ([`MirrorLayout::entry_base`]): what shooting the direction reads, found from the subfield
    /// it shoots (one pass over its entries) rather than held for every direction. A subfield
    /// whose mirror rays are not the view's (which would put radiance in the wrong slots) is an
    /// error, never shot.
    pub fn entry_base(&self, d: usize, sub: &Subfield) -> crate::Result<Vec<u32>> {
        // Entries are stored tile by tile, so index order is the layout's slot order.
        let mut len = 0u32;
        let base: Vec<u32> = (sub.entries.iter())
            .map(|e| match self.ordinal.get(e.surface as usize) {
                Some(&k) if k != NO_SLOT => {
                    len += e.rays;
                    len - e.rays
                }
                _ => NO_SLOT,
            })
            .collect();
        let slots = self.views.get(d).map_or(0, MirrorView::slots);
        if len as usize != slots {
            return Err(crate::Error::Parameter(format!(
                "direction {d}: its subfield crosses the mirrors with {len} rays, its mirror view with {slots}"
            )));
        }
        Ok(base)
    }

    /// Number of mirror slots of direction `d`.
    pub fn slots(&self, d: usize) -> usize {
        self.views[d].slots()
    }

    /// Whether `map`, one of direction `d`'s maps, is held: one value per slot.
    pub fn holds(&self, d: usize, map: &[Rgb]) -> bool {
        map.len() == self.slots(d)
    }

    /// Allocates the zeros of every map of `directions` not held, when the maps not held are
    /// zeros ([`Unheld::Zero`]): what whoever writes them first (shooting a direction) does.
    /// Maps elsewhere stay as they are: they are restored, never made up.
    pub fn hold_zeros(&mut self, directions: impl IntoIterator<Item = usize>) {
        for d in directions {
            let slots = self.views[d].slots();
            let m = &mut self.maps[d];
            if m.unheld != Unheld::Zero {
                continue;
            }
            for map in [&mut m.unshot, &mut m.total, &mut m.incident] {
                if map.len() != slots {
                    *map = vec![[0.0; 3]; slots];
                }
            }
        }
    }

    /// The map of direction `d` that `which` picks, as held, or else its zeros. Zeros are what
    /// a map not held is unless it is [`Unheld::Elsewhere`]: what reads maps that may be
    /// elsewhere (a coordinator's, a replica's) asks [`Specular::holds`] or
    /// [`Specular::holds_all`] first — a coordinator writes maps and finishes from them only
    /// while it holds them all, a block restores what it reads.
    pub fn map_or_zeros(&self, d: usize, which: impl Fn(&DirectionMaps) -> &[Rgb]) -> std::borrow::Cow<'_, [Rgb]> {
        let map = which(&self.maps[d]);
        if self.holds(d, map) {
            std::borrow::Cow::Borrowed(map)
        } else {
            std::borrow::Cow::Owned(vec![[0.0; 3]; self.slots(d)])
        }
    }

    /// Whether every map is here: held, or zeros not allocated yet ([`Unheld::Zero`]) — none
    /// elsewhere.
    pub fn holds_all(&self) -> bool {
        (self.maps.iter().enumerate()).all(|(d, m)| {
            m.unheld == Unheld::Zero || [&m.unshot, &m.total, &m.incident].iter().all(|v| self.holds(d, v))
        })
    }

    /// Bytes of the mirror maps held ([`DirectionMaps::bytes`]).
    pub fn held_bytes(&self) -> usize {
        self.maps.iter().map(DirectionMaps::bytes).sum()
    }

    /// The directions some of whose maps are held (allocated), in increasing order.
    pub fn held_directions(&self) -> impl Iterator<Item = usize> + '_ {
        (self.maps.iter().enumerate())
            .filter(|(_, m)| m.bytes() > 0)
            .map(|(d, _)| d)
    }

    /// Power still unshot in the mirror maps: `Σ_i Σ_slots U · Δω_i`, or,
    /// while arrivals are [`Pending`], the power the exchange reflects into
    /// them ([`Specular::settle_batch`]: the gather scales each route to carry
    /// exactly its share of that).
    pub fn unshot_power(&self, directions: &DirectionSet) -> Rgb {
        if let Some(exchange) = self.settled() {
            return exchange.reflected;
        }
        let mut p = [0.0; 3];
        for (d, maps) in self.maps.iter().enumerate() {
            let w = directions.get(d).weight;
            for u in &maps.unshot {
                for c in 0..3 {
                    p[c] += u[c] * w;
                }
            }
        }
        p
    }

    /// Frees every direction's maps, keeping the views and routes: their values are elsewhere
    /// ([`Unheld::Elsewhere`]) — for a coordinator whose workers hold the maps (see
    /// [`Pending`]), which then needs only what the arrivals come to ([`Settled`]), and for
    /// a worker's replica moving on to the next snapshot. Restoring a batch brings its maps back
    /// ([`super::Propagation::restore_shooting_batch`], [`super::Propagation::restore_totals_batch`]),
    /// as adopting a block does ([`super::Propagation::adopt_mirrors`]).
    pub fn release_maps(&mut self) {
        for m in &mut self.maps {
            *m = DirectionMaps {
                unheld: Unheld::Elsewhere,
                ..DirectionMaps::default()
            };
        }
    }

    /// Whether any mirror slot holds unshot radiance, or arrivals wait to be
    /// reflected.
    pub fn has_unshot(&self) -> bool {
        match &self.pending {
            Some(p) => match &p.settled {
                Some(settled) => settled.exchange.incident.iter().any(|&c| c > 0.0),
                None => (p.power_in.iter().flatten().flatten()).any(|(_, v)| v.iter().any(|&c| c > 0.0)),
            },
            None => self
                .maps
                .iter()
                .any(|m| m.unshot.iter().any(|u| u.iter().any(|&c| c > 0.0))),
        }
    }

    /// `Φ_in(P, ω)` of direction `d` for every mirror `P` that received power
    /// ([`MirrorPower`]): what its incident map `incident` holds,
    /// `Σ_slots I · Δω`.
    pub fn power_in_of(&self, directions: &DirectionSet, d: usize, incident: &[Rgb]) -> MirrorPower {
        // Sized to the mirrors the direction's rays cross: allocated once, not grown (the unlit
        // ones are dropped below).
        let mut p: MirrorPower = Vec::with_capacity(self.slotted[d].len());
        let w = directions.get(d).weight;
        let MirrorView { sub, layout } = &self.views[d];
        // The entries are sorted by surface: each mirror's are adjacent.
        for &(s, _, e) in &layout.entries {
            let base = layout.entry_base[e as usize] as usize;
            let k = self.ordinal[s as usize];
            if p.last().is_none_or(|&(last, _)| last != k) {
                p.push((k, [0.0; 3]));
            }
            let acc = &mut p.last_mut().expect("pushed").1;
            for v in &incident[base..base + sub.entries[e as usize].rays as usize] {
                for c in 0..3 {
                    acc[c] += v[c] * w;
                }
            }
        }
        p.retain(|(_, v)| v.iter().any(|&c| c != 0.0));
        p.sort_unstable_by_key(|&(k, _)| k);
        p
    }

    /// Whether this and `other` share their geometry rather than each holding its own: the
    /// views, the routes, the mirrors each direction crosses and the table of routes by source
    /// (false while either has not built that table). Copies of a propagation share the first
    /// three, and the table once it was built before the copy ([`Specular::prepare_settle`]).
    pub fn shares_geometry(&self, other: &Specular) -> bool {
        let table = match (self.routes_by_source.get(), other.routes_by_source.get()) {
            (Some(a), Some(b)) => Arc::ptr_eq(a, b),
            _ => false,
        };
        table
            && Arc::ptr_eq(&self.views, &other.views)
            && Arc::ptr_eq(&self.routes, &other.routes)
            && Arc::ptr_eq(&self.slotted, &other.slotted)
    }
}

/// `mirrors` sorted, each once, with which surfaces they are (`has_maps`, by surface) and each
/// one's ordinal among them (`ordinal`, by surface; [`NO_SLOT`] for the other surfaces).
fn mirror_tables(scene: &Scene, mut mirrors: Vec<u32>) -> (Vec<u32>, Vec<bool>, Vec<u32>) {
    mirrors.sort_unstable();
    mirrors.dedup();
    let mut has_maps = vec![false; scene.surfaces.len()];
    let mut ordinal = vec![NO_SLOT; scene.surfaces.len()];
    for (k, &m) in mirrors.iter().enumerate() {
        has_maps[m as usize] = true;
        ordinal[m as usize] = k as u32;
    }
    (mirrors, has_maps, ordinal)
}
