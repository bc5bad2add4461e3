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

use super::batching::Batching;
use super::by_mirror::{PowerByMirror, RoutesBySource};
use super::mirror_geometry::MirrorGeometry;
use super::shoot::NO_SLOT;
use crate::directions::DirectionSet;
use crate::psf::{Footprints, RasterScratch, Subfield, Subfields, SurfaceProjection};
use crate::scene::{Rgb, Scene};
use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, OnceLock};

/// Where one subfield's rays cross mirrors: a compact numbering of its
/// (mirror, ray) crossings, in tile / entry / span / column order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MirrorLayout {
    /// For each entry of [`Subfield::entries`]: its first mirror slot, or
    /// `u32::MAX` for a surface without directional maps.
    pub entry_base: Vec<u32>,
    /// Number of mirror slots.
    pub len: u32,
    /// The mirror entries as (surface, tile, entry index), sorted by surface.
    pub entries: Vec<(u32, u32, u32)>,
}

impl MirrorLayout {
    pub fn new(sub: &Subfield, has_maps: &[bool]) -> Self {
        let mut entry_base = vec![NO_SLOT; sub.entries.len()];
        let mut entries = Vec::new();
        let mut len = 0u32;
        for k in 0..sub.tile_count() {
            let first = sub.tile_start[k] as usize;
            for (local, e) in sub.tile(k).iter().enumerate() {
                if has_maps[e.surface as usize] {
                    entry_base[first + local] = len;
                    entries.push((e.surface, k as u32, (first + local) as u32));
                    len += e.rays;
                }
            }
        }
        entries.sort_by_key(|&(s, k, _)| (s, k));
        MirrorLayout {
            entry_base,
            len,
            entries,
        }
    }

    /// The tiles of `sub` that hold mirror slots, each with its range of
    /// slots: slots are numbered tile by tile, so a tile's are contiguous.
    /// This is how directional radiance is cut into per-tile blobs.
    pub fn tile_slots(&self, sub: &Subfield) -> Vec<(u32, std::ops::Range<usize>)> {
        let mut out = Vec::new();
        for k in 0..sub.tile_count() {
            let first = sub.tile_start[k] as usize;
            let mut range: Option<std::ops::Range<usize>> = None;
            for (local, e) in sub.tile(k).iter().enumerate() {
                let base = self.entry_base[first + local];
                if base != NO_SLOT {
                    let (start, end) = (base as usize, (base + e.rays) as usize);
                    range = Some(range.map_or(start..end, |r| r.start..end));
                }
            }
            if let Some(r) = range.filter(|r| !r.is_empty()) {
                out.push((k as u32, r));
            }
        }
        out
    }

    /// The mirror entries of `surface`.
    pub fn entries_of(&self, surface: u32) -> &[(u32, u32, u32)] {
        let a = self.entries.partition_point(|e| e.0 < surface);
        let b = self.entries.partition_point(|e| e.0 <= surface);
        &self.entries[a..b]
    }

    /// The mirror slot of grid cell `(x, y)` on `surface`, if its ray crosses it.
    pub fn locate(&self, sub: &Subfield, surface: u32, x: u32, y: u32) -> Option<u32> {
        let (entry, offset) = sub.locate_entry(surface, x, y)?;
        self.slot(entry, offset)
    }

    /// The mirror slot of the ray at `offset` within entry `entry` of the subfield
    /// ([`Subfield::entries`]), if the entry's surface has directional maps.
    pub fn slot(&self, entry: usize, offset: u32) -> Option<u32> {
        let base = *self.entry_base.get(entry)?;
        (base != NO_SLOT).then(|| base + offset)
    }

    /// The mirror slot of grid cell `(x, y)` on the plane of `surface`, a polygon of a mirror
    /// that may be tessellated (`plane_rep` per surface,
    /// [`crate::maps::TexelAtlas::plane_rep`]): the polygons of a mirror chart share their
    /// plane's entries, so a look-up on one reads the rays of the whole mirror.
    pub fn locate_on_plane(&self, sub: &Subfield, plane_rep: &[u32], surface: u32, x: u32, y: u32) -> Option<u32> {
        let rep = plane_rep.get(surface as usize).copied().unwrap_or(surface);
        self.locate(sub, rep, x, y)
    }
}

/// The mirror maps owned by one direction (see the module docs). Each is *held* when it has
/// one value per mirror slot of the direction, else empty, its values then as `unheld` says.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DirectionMaps {
    pub unshot: Vec<Rgb>,
    pub total: Vec<Rgb>,
    pub incident: Vec<Rgb>,
    /// What the maps not held are.
    pub unheld: Unheld,
}

impl DirectionMaps {
    /// What the next iteration shoots from, between iterations: the arrivals
    /// when they are `pending` (see [`Pending`]), else the unshot map.
    pub fn shooting(&self, pending: bool) -> &[Rgb] {
        if pending { &self.incident } else { &self.unshot }
    }

    /// Sets what the next iteration shoots from (see [`Self::shooting`]) and lets the other map
    /// go: the next shooting writes it afresh (the gather its unshot map, the shot its incident
    /// map, from zero), so nothing reads what it held.
    pub fn set_shooting(&mut self, pending: bool, map: Vec<Rgb>) {
        let (set, clear) = if pending {
            (&mut self.incident, &mut self.unshot)
        } else {
            (&mut self.unshot, &mut self.incident)
        };
        *set = map;
        *clear = Vec::new();
    }

    /// Bytes of the maps held.
    pub fn bytes(&self) -> usize {
        (self.unshot.capacity() + self.total.capacity() + self.incident.capacity()) * std::mem::size_of::<Rgb>()
    }
}

/// What the values of a mirror map that a process does not hold are ([`DirectionMaps`]).
///
/// A map is held — allocated, one value per slot — where the process reads or writes it, and
/// no more: every direction's in one process running the whole propagation; in the service a
/// worker's, from one snapshot to the next, those of the directions its leases shoot (their
/// shooting and total maps) and of the directions they gather from (their arrivals), and a
/// coordinator's none — at l = 8193, N = 256 the mirror scene's maps are 1.07 GB each for the
/// whole field. A map not held is empty.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Unheld {
    /// Zeros: nothing was shot into them (a new propagation, or a map that a restore cleared).
    /// Allocated when first written ([`Specular::hold_zeros`]); read as zeros.
    #[default]
    Zero,
    /// Elsewhere: in the store, where the workers that computed them wrote them — a worker's
    /// replica between snapshots ([`super::Propagation::restore_head`]), a coordinator whose
    /// workers shoot the maps ([`Specular::release_maps`]) — or in a block that took the
    /// direction's totals along ([`super::Propagation::compute_block`]). Reading one is an
    /// error until its batch is restored.
    Elsewhere,
}

/// One feed of a target direction: light arriving on `mirror` along source
/// line direction `source` reflects into the target with share `weight`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Route {
    pub mirror: u32,
    pub source: u32,
    pub weight: f64,
}

/// Power bookkeeping of one exchange (per channel).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Exchange {
    /// Power that arrived on mirrors (front side).
    pub incident: Rgb,
    /// Power reflected into the next unshot maps: ρs × incident, exactly
    /// (what the routes carry, see [`Specular::settle_batch`]).
    pub reflected: Rgb,
}

/// One direction's subfield restricted to the mirrors with maps, with its slots laid out as the
/// whole subfield's ([`MirrorLayout`] numbers mirror slots tile by tile, entry by entry,
/// counting only mirror entries: the view has them in the same order), so every look-up of a
/// mirror's rays answers as on the whole subfield.
///
/// **All a field's mirror geometry.** The exchange (the gather of a direction's unshot map and
/// of its sources' arrivals, `Φ_in`), the cutting of mirror maps into tiles, the look-ups of a
/// walkthrough and the viewer's ray tables read the views alone; only shooting a direction reads
/// the whole subfield's numbering ([`Specular::entry_base`]), and it has the subfield then.
///
/// **Built from the mirrors alone** ([`Footprints::of`]) where the subfields are not all held:
/// a direction rasterises the mirror planes, not the scene, so no process builds every subfield
/// for its mirrors — a worker builds those of the directions it shoots, a coordinator none. It
/// is the whole subfield's mirror entries and spans, its rays numbered afresh
/// ([`Subfield::only`]), to the bit.
#[derive(Clone, Debug, PartialEq)]
pub struct MirrorView {
    pub sub: Subfield,
    pub layout: MirrorLayout,
}

impl MirrorView {
    /// The view whose subfield `sub` holds the entries of the mirrors `has_maps` marks alone.
    fn new(sub: Subfield, has_maps: &[bool]) -> MirrorView {
        let layout = MirrorLayout::new(&sub, has_maps);
        MirrorView { sub, layout }
    }

    /// Number of mirror slots of the direction.
    pub fn slots(&self) -> usize {
        self.layout.len as usize
    }
}

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

/// Where the gather of one target direction reads ([`Specular::gather`]): per route of the
/// target, in order, every sample of the backward mapping as (the target's mirror slot, the
/// source's slot it reads, or [`NO_SLOT`] where no source ray crosses the mirror there). A
/// function of the geometry alone, the same every iteration.
///
/// Flat: the samples of every route in one array, route `r`'s at `starts[r]..starts[r + 1]`.
/// A curved mirror has millions of routes of one or two samples each (the 47 794-triangle
/// dragon at l = 2049: 4 million), where a list per route cost an allocation and 24 bytes of
/// header each, more than its samples.
#[derive(Clone, Debug)]
struct GatherTable {
    starts: Vec<usize>,
    samples: Vec<(u32, u32)>,
}

impl GatherTable {
    /// The samples of route `r`.
    fn reads(&self, r: usize) -> &[(u32, u32)] {
        &self.samples[self.starts[r]..self.starts[r + 1]]
    }
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
    /// ([`super::Propagation::restore_head`]).
    pub settled: Option<Settled>,
    /// `Φ_in` where it is known here: of the directions whose arrival maps this process holds
    /// (or as an earlier build's blob held it), `None` for the others; empty when none is.
    #[serde(skip)]
    power_in: Vec<Option<MirrorPower>>,
    /// `power_in` by mirror, as a gather's routes ask for it: turned around once, again only
    /// after more of it became known.
    #[serde(skip)]
    by_mirror: OnceLock<Box<PowerByMirror>>,
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
        // crossing[k]: the directions (increasing) whose rays meet mirror k, an entry of its
        // in their layout; listed per mirror, as the routes ask, and only where they meet.
        let mut crossing: Vec<Vec<u32>> = vec![Vec::new(); mirrors.len()];
        for (d, view) in views.iter().enumerate() {
            for &(s, _, _) in &view.layout.entries {
                let list = &mut crossing[ordinal[s as usize] as usize];
                if list.last() != Some(&(d as u32)) {
                    list.push(d as u32);
                }
            }
        }
        let per_mirror: Vec<Vec<(u32, Route)>> = mirrors
            .par_iter()
            .zip(&crossing)
            .map(|(&m, crossing)| mirror_routes(scene, directions, crossing, m))
            .collect();
        drop(crossing);
        let mut routes = vec![Vec::new(); directions.len()];
        for list in per_mirror {
            for (target, route) in list {
                routes[target as usize].push(route);
            }
        }
        routes
            .par_iter_mut()
            .for_each(|r| r.sort_by_key(|r| (r.mirror, r.source)));
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

    /// The backward mapping of target direction `i` ([`GatherTable`]), for the routes `wanted`
    /// (the others' ranges left empty): every slot of the route's mirror in `i` reads the source
    /// ray through the same point of the mirror.
    fn gather_table(&self, scene: &Scene, i: usize, wanted: impl Fn(&Route) -> bool) -> GatherTable {
        let MirrorView { sub, layout } = &self.views[i];
        let n = sub.grid.resolution;
        // The target's rays on the last route's mirror: routes come by mirror, each mirror's
        // several sources read through the same points, so it is found once per mirror.
        let mut on_mirror: Option<(u32, SurfaceProjection)> = None;
        let mut table = GatherTable {
            starts: Vec::with_capacity(self.routes[i].len() + 1),
            samples: Vec::new(),
        };
        table.starts.push(0);
        for route in &self.routes[i] {
            if wanted(route) {
                let proj = match &on_mirror {
                    Some((m, proj)) if *m == route.mirror => proj,
                    _ => {
                        let surface = &scene.surfaces[route.mirror as usize];
                        let proj = SurfaceProjection::new(&sub.frame, n, surface.normal, surface.offset);
                        &on_mirror.insert((route.mirror, proj)).1
                    }
                };
                let MirrorView {
                    sub: source,
                    layout: source_layout,
                } = &self.views[route.source as usize];
                for &(_, k, e) in layout.entries_of(route.mirror) {
                    let base = layout.entry_base[e as usize];
                    let entry = &sub.entries[e as usize];
                    sub.rays_of(k as usize, entry, |slot, x, y| {
                        let p = proj.point_at(x as f64 + 0.5, y as f64 + 0.5);
                        let g = source.frame.to_grid(p, n);
                        let read = if g.x >= 0.0 && g.y >= 0.0 {
                            source_layout.locate(source, route.mirror, g.x as u32, g.y as u32)
                        } else {
                            None
                        };
                        (table.samples).push((base + slot - entry.first_ray, read.unwrap_or(NO_SLOT)));
                    });
                }
            }
            table.starts.push(table.samples.len());
        }
        table
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
    /// arrival maps it shot, as it hands them over ([`super::Propagation::adopt_mirrors`]).
    pub(crate) fn know_power(&mut self, range: std::ops::Range<usize>, power: Vec<MirrorPower>) {
        let l = self.views.len();
        if let Some(pending) = &mut self.pending {
            for (d, power) in range.zip(power) {
                pending.know(l, d, power);
            }
        }
    }

    /// Turns the pending `Φ_in` around by mirror now and keeps it, for the gathers that this
    /// process runs next from the same [`Pending`]: a process running the whole propagation.
    pub(crate) fn prepare_gathers(&self) {
        if let Some(pending) = &self.pending {
            self.by_mirror(pending);
        }
    }

    /// `pending`'s known `Φ_in` by mirror ([`PowerByMirror`]), turned around once per what is
    /// known.
    fn by_mirror<'a>(&self, pending: &'a Pending) -> &'a PowerByMirror {
        (pending.by_mirror).get_or_init(|| Box::new(PowerByMirror::new(&pending.power_in, self.mirrors.len())))
    }

    /// `Φ_in` of `route`'s mirror along its source.
    fn route_power(&self, lit: &PowerByMirror, route: &Route) -> Rgb {
        lit.power(self.ordinal[route.mirror as usize], route.source)
    }

    /// The batches of source directions whose arrivals the gather of `targets` reads (those of
    /// the routes into them that carry power), increasing: what a worker reads from the store
    /// before it gathers a block. As the batches that shot the arrivals settled them
    /// ([`Settled::sources`]); arrivals not settled yet read every batch.
    pub fn source_batches(
        &self,
        targets: std::ops::Range<usize>,
        pending: &Pending,
        batching: &Batching,
    ) -> Vec<usize> {
        let Some(settled) = &pending.settled else {
            return (0..batching.count()).collect();
        };
        let mut found = vec![false; batching.count()];
        if !targets.is_empty() {
            for t in batching.batch_of(targets.start)..=batching.batch_of(targets.end - 1) {
                for &b in settled.sources.get(t).map_or(&[][..], Vec::as_slice) {
                    if let Some(f) = found.get_mut(b as usize) {
                        *f = true;
                    }
                }
            }
        }
        (0..found.len()).filter(|&b| found[b]).collect()
    }

    /// Refuses to gather `targets` unless the `Φ_in` of every source it reads is known here
    /// ([`Specular::know_arrivals`]): a source not known reads as dark, so a replica that did
    /// not restore a batch it gathers from would gather too little, without a word.
    pub fn check_sources_known(
        &self,
        targets: std::ops::Range<usize>,
        pending: &Pending,
        batching: &Batching,
    ) -> crate::Result<()> {
        for b in self.source_batches(targets, pending, batching) {
            if let Some(d) = batching.range(b).find(|&d| pending.power_in(d).is_none()) {
                return Err(crate::Error::Parameter(format!(
                    "the mirror arrival map of direction {d} (batch {b}) is not restored"
                )));
            }
        }
        Ok(())
    }

    /// Reflects the pending arrivals (the incident maps) of every direction
    /// into new unshot maps and clears the incident maps: the exchange, as
    /// one process does it at the start of the iteration that shoots them.
    /// Nothing happens when no arrivals are pending.
    ///
    /// In place: each direction's stale unshot map (while arrivals are pending, nothing reads
    /// it) is cleared and gathered into, and the arrival maps, once every gather has read them,
    /// are cleared to be the next incident maps. Two maps of fresh memory per slot every
    /// iteration were a third of the mirror dragon's gathering on the 2-core VM, most of it the
    /// system zeroing pages.
    pub fn gather_all(&mut self, scene: &Scene, directions: &DirectionSet) {
        if self.pending.is_none() {
            return;
        }
        self.hold_zeros(0..directions.len());
        debug_assert!(
            self.holds_all(),
            "one process gathers only where every arrival map is here"
        );
        // Every arrival map is here: `Φ_in` not known yet (a propagation that finished the
        // iteration from blocks it adopted, say) is found from them, never read as dark.
        let l = directions.len();
        if (self.pending.as_ref()).is_some_and(|p| (0..l).any(|d| p.power_in(d).is_none())) {
            self.know_arrivals(directions, 0..l);
        }
        let Some(pending) = self.pending.take() else {
            return;
        };
        let incident: Vec<Vec<Rgb>> = (self.maps.iter_mut())
            .map(|m| std::mem::take(&mut m.incident))
            .collect();
        let mut unshot: Vec<Vec<Rgb>> = (self.maps.iter_mut()).map(|m| std::mem::take(&mut m.unshot)).collect();
        let read = |d: usize| incident[d].as_slice();
        let this = &*self;
        (unshot.par_iter_mut().enumerate()).for_each(|(i, out)| {
            (this.gather_into(scene, directions, &read, &pending, i, out))
                .expect("one process holds every direction's arrivals")
        });
        let cleared: Vec<Vec<Rgb>> = (incident.into_par_iter())
            .map(|mut map| {
                map.fill([0.0; 3]);
                map
            })
            .collect();
        for ((maps, unshot), incident) in self.maps.iter_mut().zip(unshot).zip(cleared) {
            maps.unshot = unshot;
            maps.incident = incident;
        }
    }

    /// The new unshot map of target direction `i` from the pending arrivals
    /// `incident(source)` of its routes' sources and their `Φ_in` as this process knows it
    /// ([`Specular::know_arrivals`]; see the module docs): what a worker computes for the
    /// directions it shoots. A source whose `Φ_in` is not known here reads as dark: ask
    /// [`Specular::check_sources_known`] first. An arrival map it reads whose `Φ_in` is known
    /// but that is not held is an error, not zeros.
    pub fn gather<'a>(
        &self,
        scene: &Scene,
        directions: &DirectionSet,
        incident: &(dyn Fn(usize) -> &'a [Rgb] + Sync),
        pending: &Pending,
        i: usize,
    ) -> crate::Result<Vec<Rgb>> {
        let mut out = Vec::new();
        self.gather_into(scene, directions, incident, pending, i, &mut out)?;
        Ok(out)
    }

    /// [`Specular::gather`] into `out`, whatever it held: cleared to the direction's zeros
    /// first, its memory kept where it has room.
    pub fn gather_into<'a>(
        &self,
        scene: &Scene,
        directions: &DirectionSet,
        incident: &(dyn Fn(usize) -> &'a [Rgb] + Sync),
        pending: &Pending,
        i: usize,
        out: &mut Vec<Rgb>,
    ) -> crate::Result<()> {
        let power = self.by_mirror(pending);
        let lit = |route: &Route| !self.route_power(power, route).iter().all(|&p| p <= 0.0);
        // Backward mapping: every slot of P in i reads the incident radiance of the source ray
        // through the same point of P. Found once per direction where tables are kept (a
        // fifth of the mirror scene's in-process run went to finding it again every
        // iteration), else for the routes that carry power this time.
        let found;
        let table = if self.keep_gather_tables {
            self.gather_tables[i].get_or_init(|| self.gather_table(scene, i, |_| true))
        } else {
            found = self.gather_table(scene, i, lit);
            &found
        };
        let weight_i = directions.get(i).weight;
        let len = self.views[i].layout.len as usize;
        if out.capacity() >= len {
            out.clear();
            out.resize(len, [0.0; 3]);
        } else {
            // Zeroed by the allocator, which memory fresh from the system is already.
            *out = vec![[0.0; 3]; len];
        }
        let mut samples: Vec<(u32, Rgb)> = Vec::new();
        for (r, route) in self.routes[i].iter().enumerate() {
            let pin = self.route_power(power, route);
            if pin.iter().all(|&p| p <= 0.0) {
                continue;
            }
            let reads = table.reads(r);
            if reads.is_empty() {
                // The mirror has no slot in the target: nothing to fill, nothing to read.
                continue;
            }
            let rho = scene.materials[scene.surfaces[route.mirror as usize].material].specular;
            let source_incident = incident(route.source as usize);
            if !self.holds(route.source as usize, source_incident) {
                return Err(crate::Error::Parameter(format!(
                    "the mirror arrival map of direction {} is not restored",
                    route.source
                )));
            }
            samples.clear();
            samples.extend(reads.iter().map(|&(slot, read)| {
                let v = if read == NO_SLOT {
                    [0.0; 3]
                } else {
                    source_incident[read as usize]
                };
                (slot, v)
            }));
            // Scale so the route carries exactly b·ρs·Φ_in (per channel);
            // where backward mapping found nothing lit (a lit area far smaller
            // than a ray cell), spread the power evenly instead.
            for c in 0..3 {
                let target = route.weight * rho[c] * pin[c];
                if target <= 0.0 {
                    continue;
                }
                let sum: f64 = samples.iter().map(|(_, v)| v[c]).sum();
                if sum > 0.0 {
                    let k = target / (sum * weight_i);
                    for (slot, v) in &samples {
                        out[*slot as usize][c] += v[c] * k;
                    }
                } else {
                    let each = target / (samples.len() as f64 * weight_i);
                    for (slot, _) in &samples {
                        out[*slot as usize][c] += each;
                    }
                }
            }
        }
        Ok(())
    }
}

fn add(acc: &mut Rgb, v: &Rgb) {
    for (a, b) in acc.iter_mut().zip(v) {
        *a += b;
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

/// The routes of mirror `m`: for every source line direction whose rays cross it (`crossing`,
/// increasing), where its reflection goes, as (target, route).
fn mirror_routes(scene: &Scene, directions: &DirectionSet, crossing: &[u32], m: u32) -> Vec<(u32, Route)> {
    let n = scene.surfaces[m as usize].normal;
    let crosses = |d: u32| crossing.binary_search(&d).is_ok();
    // The grazing fallback's candidates, the crossing line directions not parallel to the
    // mirror, gathered once per mirror rather than once per source (a curved mirror's many small
    // planes fall back often, and this scan was most of the routes' time).
    let candidates: Vec<(u32, DVec3)> = (crossing.iter())
        .map(|&t| (t, directions.get(t as usize).vector))
        .filter(|(_, v)| v.dot(n).abs() > 1e-9)
        .collect();
    let mut out = Vec::new();
    for &source in crossing {
        let w = directions.get(source as usize).vector;
        let c = w.dot(n);
        // The orientation of the line that travels towards the front side.
        let incoming = if c < 0.0 { w } else { -w };
        let r = incoming - 2.0 * incoming.dot(n) * n;
        let tri = directions.triangle(r);
        // Keep vertices that leave the front side and whose rays cross the mirror.
        let mut kept: Vec<(u32, f64)> = tri
            .vertices
            .iter()
            .zip(tri.weights)
            .filter(|(o, b)| *b > 0.0 && directions.vector(**o).dot(n) > 1e-9 && crosses(o.index))
            .map(|(o, b)| (o.index, b))
            .collect();
        if kept.is_empty() {
            // Grazing reflection whose triangle lies behind the mirror or misses
            // it: the closest line direction that does leave the front (the largest |t·r|,
            // the lowest index of equals: candidates are in increasing index).
            let mut best: Option<(u32, f64)> = None;
            for &(t, v) in &candidates {
                let f = v.dot(r).abs();
                if best.is_none_or(|(_, b)| f.total_cmp(&b).is_gt()) {
                    best = Some((t, f));
                }
            }
            match best {
                Some((t, _)) => kept.push((t, 1.0)),
                None => continue,
            }
        }
        let total: f64 = kept.iter().map(|(_, b)| b).sum();
        for (target, b) in kept {
            out.push((
                target,
                Route {
                    mirror: m,
                    source,
                    weight: b / total,
                },
            ));
        }
    }
    out
}
