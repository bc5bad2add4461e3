//! Walking the rays of one subfield: the inner loop of propagation.
//!
//! For each tile, the hits of every ray are gathered from the tile's edge
//! tables (depth and texel recomputed from [`SurfaceProjection`]), sorted by
//! depth along `+w`, and handed to a visitor. Shooting then looks at
//! consecutive hits: two surfaces exchange light along the segment between
//! them only if they face each other; a back face blocks (absorbs) the light.

use crate::maps::TexelAtlas;
use crate::psf::raster::SUBPIXELS;
use crate::psf::{Subfield, SurfaceProjection};
use crate::scene::{Rgb, Scene};
use glam::{DVec2, DVec3};
use std::collections::HashMap;

/// One ray–surface intersection.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RayHit {
    pub depth: f64,
    pub surface: u32,
    pub texel: u32,
    /// The hit's slot in the subfield's mirror maps, or [`NO_SLOT`].
    pub mirror: u32,
    /// Order among hits at the same depth (see [`before`]).
    pub tie: u32,
}

impl RayHit {
    /// Whether the surface's front looks along `−w` (a ray travelling along `+w` meets its
    /// front). [`for_each_ray`] ranks those hits first among equals, so `tie` says it: at most
    /// `u32::MAX / 2` for them, above for the others. No subfield holds a surface seen
    /// edge-on, so every hit faces one way or the other.
    pub fn faces_backward(&self) -> bool {
        self.tie <= u32::MAX / 2
    }

    /// Whether the surface's front looks along `+w`.
    pub fn faces_forward(&self) -> bool {
        !self.faces_backward()
    }
}

/// Marks a hit on a surface without directional (mirror) maps.
pub(crate) const NO_SLOT: u32 = u32::MAX;

/// The static inputs of a walk: the scene, where its texels are, and how
/// coplanar surfaces stack ([`Stacking`]).
#[derive(Clone, Copy)]
pub(crate) struct Geometry<'a> {
    pub scene: &'a Scene,
    pub atlas: &'a TexelAtlas,
    pub stacking: &'a Stacking,
}

/// Depths closer than this (VLF frame, where the scene spans 2) are a tie:
/// surfaces that coincide up to rounding, such as a lamp modelled flush with
/// its ceiling.
const DEPTH_TIE: f64 = 1e-9;

/// How surfaces that share a plane lie on each other: which one a ray meets
/// first, and which surfaces can be hidden at all.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Stacking {
    /// Per surface, its rank among coplanar ones: a higher rank lies on top
    /// (is seen first from the front). Emitters lie on top of what they are
    /// flush with, then smaller charts on top of larger ones (a decal on a
    /// wall, however the wall is cut), then later surfaces.
    pub rank: Vec<u32>,
    /// Per surface, whether another surface lies in (nearly) its plane, facing
    /// either way: only such a pair can tie in depth along a ray and hide one
    /// another ([`drop_hidden`]). A ray whose hits are all on other
    /// surfaces needs no such check, and a direction's discrete areas over
    /// them need no walk at all ([`count`]).
    pub shares_plane: Vec<bool>,
}

impl Stacking {
    pub(crate) fn new(scene: &Scene, atlas: &TexelAtlas) -> Stacking {
        let chart_area = atlas.chart_areas(scene);
        let n = scene.surfaces.len();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| {
            let ea = scene.material(a).is_emitter();
            let eb = scene.material(b).is_emitter();
            ea.cmp(&eb)
                .then(chart_area[b].total_cmp(&chart_area[a]))
                .then(a.cmp(&b))
        });
        let mut rank = vec![0u32; n];
        for (r, s) in order.into_iter().enumerate() {
            rank[s] = r as u32;
        }
        Stacking {
            rank,
            shares_plane: shares_plane(scene, &atlas.plane_rep),
        }
    }
}

/// [`Stacking::shares_plane`]. Subfields hold a planar group (a wall however it is cut) as
/// its representative surface `plane_rep[s]`, so only representatives meet along a ray:
/// each is compared with the others, either facing (two hits [`parallel`] and facing the
/// same way can tie), and the other surfaces take their representative's answer.
///
/// Two planes whose normals are [`parallel`] are at most 4.5·10⁻⁵ rad apart, so where
/// their offsets differ by `Δ` (as oriented alike) they are at least `Δ − 4.5·10⁻⁵·R`
/// apart at every point within `R` of the origin, and a ray's depths on them differ by at
/// least that: above `gap = 10⁻⁴ + 5·10⁻⁵·R` they can never tie (to [`DEPTH_TIE`]). `R`
/// bounds the scene's vertices; a hit lies on its polygon up to half a rasteriser sub-pixel
/// (about 10⁻⁴ at N = 4096), which the first term covers.
///
/// Candidates are found in a grid over (normal, offset) with cells wider than both
/// tolerances, each surface filed under its plane both ways (`(n, o)` and `(−n, −o)`), so a
/// surface looks at the 27 cells around its normal and, in each, at the offsets within
/// `gap` of its own: linear in the surfaces, however many share an offset (a sphere
/// about the origin) or a normal (a floor of separate tiles).
fn shares_plane(scene: &Scene, plane_rep: &[u32]) -> Vec<bool> {
    const NORMAL_CELL: f64 = 1e-4;
    let radius = scene
        .surfaces
        .iter()
        .flat_map(|s| s.vertices.iter())
        .map(|v| v.length())
        .fold(0.0, f64::max);
    let gap = 1e-4 + 5e-5 * radius;
    let cell = |n: DVec3| (n / NORMAL_CELL).floor().as_i64vec3().to_array();
    let reps: Vec<usize> = (0..scene.surfaces.len())
        .filter(|&s| plane_rep.get(s).is_none_or(|&r| r as usize == s))
        .collect();
    let mut cells: HashMap<[i64; 3], Vec<(f64, u32)>> = HashMap::new();
    for &r in &reps {
        let s = &scene.surfaces[r];
        for sign in [1.0, -1.0] {
            cells
                .entry(cell(s.normal * sign))
                .or_default()
                .push((s.offset * sign, r as u32));
        }
    }
    for filed in cells.values_mut() {
        filed.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    }
    let shares_with_another = |a: usize| {
        let sa = &scene.surfaces[a];
        let [x, y, z] = cell(sa.normal);
        (-1..=1)
            .flat_map(|i| (-1..=1).flat_map(move |j| (-1..=1).map(move |k| [x + i, y + j, z + k])))
            .any(|c| {
                let Some(filed) = cells.get(&c) else {
                    return false;
                };
                let from = filed.partition_point(|(o, _)| *o < sa.offset - gap);
                filed[from..]
                    .iter()
                    .take_while(|(o, _)| *o <= sa.offset + gap)
                    .any(|&(_, b)| {
                        let sb = &scene.surfaces[b as usize];
                        let dot = sa.normal.dot(sb.normal);
                        let apart = if dot > 0.0 {
                            sa.offset - sb.offset
                        } else {
                            sa.offset + sb.offset
                        };
                        b as usize != a && dot.abs() >= 1.0 - 1e-9 && apart.abs() <= gap
                    })
            })
    };
    let mut shares = vec![false; scene.surfaces.len()];
    for &r in &reps {
        shares[r] = shares_with_another(r);
    }
    (0..scene.surfaces.len())
        .map(|s| shares[plane_rep.get(s).map_or(s, |&r| r as usize)])
        .collect()
}

/// Reusable buffers of one worker thread.
#[derive(Default)]
pub(crate) struct Scratch {
    offsets: Vec<u32>,
    fill: Vec<u32>,
    hits: Vec<RayHit>,
    projections: Projections,
}

impl Scratch {
    /// Starts a new direction's walk, tile by tile ([`walk_tile`]): forgets the surfaces'
    /// projections into the last one's subfield.
    pub(crate) fn begin_direction(&mut self) {
        self.projections.begin();
    }
}

/// Surfaces' [`TexelProjection`]s in the subfield being walked, each computed the first time
/// one of its tile entries comes up: a surface crosses many tiles (a wall, a few hundred),
/// and a projection costs a few dozen multiplications and a division. A small direct-mapped
/// cache (surface `s` in slot `s` mod 1024), so that its memory does not grow with the
/// scene: a surface pushed out by another is computed again, to the same bits.
struct Projections {
    /// The walk being made: slots stamped with another one are stale.
    walk: u64,
    /// Per slot: the walk it was filled in, its surface, and that surface's projection.
    slots: Vec<(u64, u32, TexelProjection)>,
}

impl Default for Projections {
    fn default() -> Self {
        Projections::with_slots(1024)
    }
}

impl Projections {
    /// A cache of `slots` rounded up to a power of two, so that a surface's slot is a mask of
    /// its number, not a division.
    fn with_slots(slots: usize) -> Projections {
        Projections {
            walk: 0,
            slots: vec![(0, 0, TexelProjection::default()); slots.max(1).next_power_of_two()],
        }
    }

    /// The slot of `surface`: its number modulo the (power-of-two) slot count.
    #[inline]
    fn slot_of(&self, surface: u32) -> usize {
        surface as usize & (self.slots.len() - 1)
    }

    /// Starts the walk of another subfield.
    fn begin(&mut self) {
        self.walk += 1;
    }

    /// `surface`'s projection in this walk's subfield `sub`, kept for the next time.
    #[inline]
    fn get(&mut self, geometry: Geometry, sub: &Subfield, surface: u32) -> TexelProjection {
        let index = self.slot_of(surface);
        let slot = &mut self.slots[index];
        if (slot.0, slot.1) != (self.walk, surface) {
            *slot = (self.walk, surface, TexelProjection::new(geometry, sub, surface));
        }
        slot.2
    }

    /// `surface`'s projection in this walk's subfield `sub`, from the cache or computed.
    #[inline]
    fn read(&self, geometry: Geometry, sub: &Subfield, surface: u32) -> TexelProjection {
        match self.slots[self.slot_of(surface)] {
            (walk, s, projection) if (walk, s) == (self.walk, surface) => projection,
            _ => TexelProjection::new(geometry, sub, surface),
        }
    }
}

/// Texel lookup as an affine function of grid coordinates: the texel
/// coordinates of the hit of ray `(x, y)` are `c0 + cx·x + cy·y`; its depth is
/// `depth[0] + depth[1]·x + depth[2]·y`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct TexelProjection {
    depth: [f64; 3],
    c0: DVec2,
    cx: DVec2,
    cy: DVec2,
}

impl TexelProjection {
    /// Where the rays of `sub` meet surface `surface`'s plane: depth and texel coordinates.
    fn new(geometry: Geometry, sub: &Subfield, surface: u32) -> TexelProjection {
        let s = &geometry.scene.surfaces[surface as usize];
        let grid = geometry.atlas.grid(surface as usize);
        let proj = SurfaceProjection::new(&sub.frame, sub.grid.resolution, s.normal, s.offset);
        TexelProjection {
            depth: proj.depth,
            c0: grid.coords(proj.p0),
            cx: grid.coords(proj.p0 + proj.px) - grid.coords(proj.p0),
            cy: grid.coords(proj.p0 + proj.py) - grid.coords(proj.p0),
        }
    }

    /// The atlas index of the texel hit by the ray at grid coordinates `(gx, gy)` (the ray's
    /// centre): the one formula of every walk, so that they agree to the bit.
    #[inline]
    fn texel(&self, grid: &crate::maps::TexelGrid, gx: f64, gy: f64) -> u32 {
        grid.index(self.c0 + self.cx * gx + self.cy * gy) as u32
    }
}

/// Calls `visit` for every ray of `sub` that crosses at least one surface,
/// with its hits sorted by increasing depth along `+w` (ties broken by
/// surface id, so the order is deterministic even for coplanar surfaces).
/// `mirror_base[e]` is the first mirror slot of tile entry `e` (or
/// [`NO_SLOT`]); without it no hit has a mirror slot.
pub(crate) fn for_each_ray(
    geometry: Geometry,
    sub: &Subfield,
    mirror_base: Option<&[u32]>,
    scratch: &mut Scratch,
    mut visit: impl FnMut(&[RayHit]),
) {
    scratch.projections.begin();
    for k in 0..sub.tile_count() {
        walk_tile(geometry, sub, k, mirror_base, scratch, &mut visit);
    }
}

/// [`for_each_ray`] over the rays of tile `k` (`scratch`'s projections begun for `sub`).
pub(crate) fn walk_tile(
    geometry: Geometry,
    sub: &Subfield,
    k: usize,
    mirror_base: Option<&[u32]>,
    scratch: &mut Scratch,
    visit: &mut impl FnMut(&[RayHit]),
) {
    let Geometry { scene, atlas, stacking } = geometry;
    let entries = sub.tile(k);
    if entries.is_empty() {
        return;
    }
    let m = sub.grid.tile as usize;
    let per_side = sub.grid.tiles_per_side() as usize;
    let (tile_x, tile_y) = ((k % per_side * m) as f64, (k / per_side * m) as f64);
    // Counting sort of hits by ray: count, prefix-sum, fill.
    scratch.offsets.clear();
    scratch.offsets.resize(m * m + 1, 0);
    for e in entries {
        for s in sub.spans_of(e) {
            for x in s.start..s.end {
                scratch.offsets[s.row as usize * m + x as usize + 1] += 1;
            }
        }
    }
    for r in 0..m * m {
        scratch.offsets[r + 1] += scratch.offsets[r];
    }
    let total = scratch.offsets[m * m] as usize;
    scratch.hits.clear();
    scratch.hits.resize(
        total,
        RayHit {
            depth: 0.0,
            surface: 0,
            texel: 0,
            mirror: NO_SLOT,
            tie: 0,
        },
    );
    scratch.fill.clear();
    scratch.fill.extend_from_slice(&scratch.offsets[..m * m]);
    let fill = &mut scratch.fill;
    let first_entry = sub.tile_start[k] as usize;
    for (local, e) in entries.iter().enumerate() {
        let mut mirror = mirror_base.map_or(NO_SLOT, |b| b[first_entry + local]);
        // At equal depth, surfaces facing −w (met from their front when
        // travelling along +w) come first; among same-facing ones the top
        // of the stack is met first from its front side.
        let rank = stacking.rank[e.surface as usize];
        let tie = if scene.surfaces[e.surface as usize].normal.dot(sub.frame.w) < 0.0 {
            u32::MAX / 2 - rank
        } else {
            u32::MAX / 2 + 1 + rank
        };
        let grid = atlas.grid(e.surface as usize);
        let tp = scratch.projections.get(geometry, sub, e.surface);
        for s in sub.spans_of(e) {
            let y = tile_y + s.row as f64 + 0.5;
            for x in s.start..s.end {
                let gx = tile_x + x as f64 + 0.5;
                let ray = s.row as usize * m + x as usize;
                let slot = fill[ray] as usize;
                fill[ray] += 1;
                scratch.hits[slot] = RayHit {
                    depth: tp.depth[0] + tp.depth[1] * gx + tp.depth[2] * y,
                    surface: e.surface,
                    texel: tp.texel(grid, gx, y),
                    mirror,
                    tie,
                };
                if mirror != NO_SLOT {
                    mirror += 1;
                }
            }
        }
    }
    // Only surfaces that share a plane can hide one another (`Stacking::shares_plane`).
    let may_hide = entries.iter().any(|e| stacking.shares_plane[e.surface as usize]);
    let order = Order {
        geometry,
        sub,
        projections: &scratch.projections,
    };
    for r in 0..m * m {
        let (a, b) = (scratch.offsets[r] as usize, scratch.offsets[r + 1] as usize);
        if a == b {
            continue;
        }
        let hits = &mut scratch.hits[a..b];
        // Few hits per ray: insertion sort beats a general sort here.
        for i in 1..hits.len() {
            let mut j = i;
            while j > 0 && order.before(&hits[j], &hits[j - 1]) {
                hits.swap(j, j - 1);
                j -= 1;
            }
        }
        let seen = if may_hide { drop_hidden(scene, hits) } else { hits.len() };
        if seen > 0 {
            visit(&hits[..seen]);
        }
    }
}

/// Moves the hits that a ray can meet to the front of the sorted `hits`, keeping their order,
/// and returns how many there are. A hit is *hidden* where a parallel surface facing the same
/// way lies on it at the same depth and on top of it (met first from the front: a flush lamp
/// over its ceiling, a decal over its wall): no light reaches it or leaves it along this ray,
/// so the ray is not part of its discrete area either — [`count`] leaves it out, and the
/// shot goes from the top surface straight to the next surface, whose back the top surface's
/// back blocks as it would.
fn drop_hidden(scene: &Scene, hits: &mut [RayHit]) -> usize {
    // The first hit hidden is tied with a neighbour in `hits` as sorted (the last kept is the
    // one before it until then): without two neighbours at one depth, none is.
    if hits.windows(2).all(|w| (w[0].depth - w[1].depth).abs() > DEPTH_TIE) {
        return hits.len();
    }
    drop_tied(scene, hits)
}

/// [`drop_hidden`] without its shortcut.
fn drop_tied(scene: &Scene, hits: &mut [RayHit]) -> usize {
    let tied = |a: &RayHit, b: &RayHit| {
        (a.depth - b.depth).abs() <= DEPTH_TIE
            && a.faces_backward() == b.faces_backward()
            && parallel(scene, a.surface, b.surface)
    };
    let mut kept = 0;
    for i in 0..hits.len() {
        let h = hits[i];
        // Facing −w, the surface on top comes first; facing +w, it comes last.
        let hidden = if h.faces_backward() {
            kept > 0 && tied(&hits[kept - 1], &h)
        } else {
            i + 1 < hits.len() && tied(&h, &hits[i + 1])
        };
        if !hidden {
            hits[kept] = h;
            kept += 1;
        }
    }
    kept
}

/// What ordering a ray's hits reads: the scene, the subfield walked and its surfaces'
/// projections so far.
struct Order<'a> {
    geometry: Geometry<'a>,
    sub: &'a Subfield,
    projections: &'a Projections,
}

impl Order<'_> {
    #[inline]
    fn before(&self, a: &RayHit, b: &RayHit) -> bool {
        before(self, a, b)
    }

    fn projection(&self, surface: u32) -> TexelProjection {
        self.projections.read(self.geometry, self.sub, surface)
    }
}

/// Hit order along `+w`: by depth, and for (near-)coincident *parallel*
/// surfaces by their tie key, so that a flush lamp is met before its ceiling
/// from below and two back-to-back polygons never exchange light through
/// each other. Surfaces that are not parallel and meet the ray at (almost)
/// the same depth cross there — a ray grazing the edge where a tessellated
/// sphere's silhouette folds — and keep their depth order: the tie key would
/// put the facet facing `−w` first and let the ray escape through the fold;
/// near a silhouette edge, see [`silhouette_order`].
#[inline]
fn before(order: &Order, a: &RayHit, b: &RayHit) -> bool {
    let scene = order.geometry.scene;
    let gap = (a.depth - b.depth).abs();
    if gap <= DEPTH_TIE && parallel(scene, a.surface, b.surface) {
        return a.tie < b.tie;
    }
    if gap <= SILHOUETTE_GAP
        && a.faces_backward() != b.faces_backward()
        && let Some(a_first) = silhouette_order(order, a, b)
    {
        return a_first;
    }
    a.depth < b.depth
}

/// Depth gaps below this (VLF frame) are checked against [`silhouette_order`]'s bound;
/// larger ones are beyond any surface's coverage error but a grazing one's.
const SILHOUETTE_GAP: f64 = 0.05;

/// The order of two hits, one facing each way, that lie closer in depth than the rays'
/// coverage can tell apart: `Some(true)` if `a` comes first.
///
/// Why: a ray is "on" a surface where the rasteriser says so, and the rasteriser works on
/// vertices snapped to 1/[`SUBPIXELS`] of a ray spacing (so that neighbours share edges
/// exactly, [`crate::psf::raster`]). A ray that passes a silhouette edge — a box's corner
/// seen from outside, where one wall faces `+w` and the other `−w` and both project to the
/// same side of the edge — up to half a sub-pixel outside it is covered by both walls, but
/// the planes' depths, extended past the edge, come in the reverse order, and the ray lets
/// the light of both escape (a closed box lost 1e-5 of its power this way, per iteration).
/// Within the depth the snapping can account for, `|∇(d_b − d_a)|·(1/SUBPIXELS)`, the order
/// is the one of the rays inside the edge: the surface facing `+w` first where the two form
/// a concave corner (each in front of the other: a room's corner), the one facing `−w`
/// first where they form a convex one (a solid's edge).
#[cold]
fn silhouette_order(order: &Order, a: &RayHit, b: &RayHit) -> Option<bool> {
    let scene = order.geometry.scene;
    if parallel(scene, a.surface, b.surface) {
        return None;
    }
    let (sa, sb) = (&scene.surfaces[a.surface as usize], &scene.surfaces[b.surface as usize]);
    let (pa, pb) = (order.projection(a.surface), order.projection(b.surface));
    let slope = DVec2::new(pb.depth[1] - pa.depth[1], pb.depth[2] - pa.depth[2]).length();
    if (a.depth - b.depth).abs() > slope / SUBPIXELS as f64 + DEPTH_TIE {
        return None;
    }
    let centroid =
        |s: &crate::scene::Surface| s.vertices.iter().copied().sum::<glam::DVec3>() / s.vertices.len() as f64;
    let (forward, backward) = if a.faces_forward() { (sa, sb) } else { (sb, sa) };
    let concave = forward.normal.dot(centroid(backward) - centroid(forward)) > 0.0;
    // Concave: the surface facing +w (a) first; convex: the one facing −w first.
    Some(concave == a.faces_forward())
}

/// Whether two surfaces are parallel (either facing) to rounding.
#[inline]
fn parallel(scene: &Scene, a: u32, b: u32) -> bool {
    let (na, nb) = (scene.surfaces[a as usize].normal, scene.surfaces[b as usize].normal);
    na.dot(nb).abs() >= 1.0 - 1e-9
}

/// Where the power shot along one direction went (per channel).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Flow {
    /// Power that left senders along this direction (both orientations).
    pub shot: Rgb,
    /// Power that arrived on a surface facing the sender.
    pub received: Rgb,
    /// Power that left the scene (no surface behind the sender).
    pub escaped: Rgb,
    /// Power stopped by the back of a one-sided surface.
    pub blocked: Rgb,
}

impl Flow {
    pub fn add(&mut self, other: &Flow) {
        for c in 0..3 {
            self.shot[c] += other.shot[c];
            self.received[c] += other.received[c];
            self.escaped[c] += other.escaped[c];
            self.blocked[c] += other.blocked[c];
        }
    }
}

#[inline]
fn add_scaled(dst: &mut Rgb, src: &Rgb, k: f64) {
    for c in 0..3 {
        dst[c] += src[c] * k;
    }
}

/// One direction's subfield and its solid-angle weight.
#[derive(Clone, Copy)]
pub(crate) struct Beam<'a> {
    pub sub: &'a Subfield,
    pub weight: f64,
}

/// What a hit sends along its ray: its diffuse radiance, plus its unshot
/// mirror radiance. Every hit leaves exactly once per shot (forward if its
/// front faces +w, backward if −w), so every mirror slot sends its unshot
/// radiance once: the iteration's end adds it to the slot's total
/// ([`super::Propagation::finish_iteration`]), and a shot changes only the
/// incident maps.
fn leaving(h: &RayHit, radiance: &[Rgb], spec: &mut Option<SpecularIo>) -> Rgb {
    let mut l = radiance[h.texel as usize];
    if h.mirror != NO_SLOT
        && let Some(s) = spec.as_mut()
    {
        add_scaled(&mut l, &s.unshot[h.mirror as usize], 1.0);
    }
    l
}

/// The directional (mirror) side of one direction's shot, all indexed by the
/// subfield's mirror slots.
pub(crate) struct SpecularIo<'a> {
    pub mirror_base: &'a [u32],
    /// Unshot radiance leaving each mirror slot along this direction.
    pub unshot: &'a [Rgb],
    /// Radiance arriving on each mirror slot (either orientation), added to.
    pub incident: &'a mut [Rgb],
}

/// Shoots along one direction of solid-angle weight `weight`.
///
/// `radiance[t]` is the power a texel sends per unit of `Δω · (ray count)`,
/// i.e. `Φ_t / T_t` (see the module docs of [`crate::propagate`]); each ray
/// leaving texel `t` carries `radiance[t] · weight`, plus, for a mirror, its
/// unshot radiance along this direction. Power
/// arriving at a texel is added to `received[t]`; radiance arriving at a
/// mirror slot to `specular.incident`.
pub(crate) fn shoot(
    geometry: Geometry,
    beam: Beam,
    radiance: &[Rgb],
    received: &mut [Rgb],
    mut specular: Option<SpecularIo>,
    scratch: &mut Scratch,
) -> Flow {
    let Beam { sub, weight } = beam;
    let mut flow = Flow::default();
    let base = specular.as_ref().map(|s| s.mirror_base);
    let spec = &mut specular;
    for_each_ray(geometry, sub, base, scratch, |hits| {
        let leaving = |h: &RayHit, spec: &mut Option<SpecularIo>| leaving(h, radiance, spec);
        let arrive = |h: &RayHit, l: &Rgb, flow: &mut Flow, received: &mut [Rgb], spec: &mut Option<SpecularIo>| {
            add_scaled(&mut flow.received, l, weight);
            add_scaled(&mut received[h.texel as usize], l, weight);
            if h.mirror != NO_SLOT
                && let Some(s) = spec.as_mut()
            {
                add_scaled(&mut s.incident[h.mirror as usize], l, 1.0);
            }
        };
        // Along −w, the first surface sends into the void if it faces −w.
        let first = hits[0];
        if first.faces_backward() {
            let l = leaving(&first, spec);
            add_scaled(&mut flow.shot, &l, weight);
            add_scaled(&mut flow.escaped, &l, weight);
        }
        for pair in hits.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            let a_forward = a.faces_forward();
            let b_backward = b.faces_backward();
            if a_forward {
                let l = leaving(&a, spec);
                add_scaled(&mut flow.shot, &l, weight);
                if b_backward {
                    arrive(&b, &l, &mut flow, received, spec);
                } else {
                    add_scaled(&mut flow.blocked, &l, weight);
                }
            }
            if b_backward {
                let l = leaving(&b, spec);
                add_scaled(&mut flow.shot, &l, weight);
                if a_forward {
                    arrive(&a, &l, &mut flow, received, spec);
                } else {
                    add_scaled(&mut flow.blocked, &l, weight);
                }
            }
        }
        let last = hits[hits.len() - 1];
        if last.faces_forward() {
            let l = leaving(&last, spec);
            add_scaled(&mut flow.shot, &l, weight);
            add_scaled(&mut flow.escaped, &l, weight);
        }
    });
    flow
}

/// Calls `crossed(t)` once for every ray of `sub` crossing texel `t`: one direction's share of
/// the texels' discrete areas `T_t` is its weight added at each call (see [`super::areas`]).
///
/// Every ray that crosses a surface counts, whatever lies in front of it, unless a surface
/// sharing its plane hides it ([`drop_hidden`]). So a tile without such surfaces needs no
/// walk along its rays (no sort by depth): each surface's spans add up on their own. The
/// bits are the walk's, since every term a caller adds is the same weight, and from zero such
/// sums do not depend on their order.
pub(crate) fn count(geometry: Geometry, sub: &Subfield, scratch: &mut Scratch, mut crossed: impl FnMut(usize)) {
    scratch.projections.begin();
    for k in 0..sub.tile_count() {
        let entries = sub.tile(k);
        if entries
            .iter()
            .any(|e| geometry.stacking.shares_plane[e.surface as usize])
        {
            walk_tile(geometry, sub, k, None, scratch, &mut |hits: &[RayHit]| {
                for h in hits {
                    crossed(h.texel as usize);
                }
            });
            continue;
        }
        for e in entries {
            let grid = geometry.atlas.grid(e.surface as usize);
            let tp = scratch.projections.get(geometry, sub, e.surface);
            // Grid coordinates are whole numbers, so `x + ½` is the walk's `tile_x + col + ½`.
            sub.rays_of(k, e, |_, x, y| {
                crossed(tp.texel(grid, x as f64 + 0.5, y as f64 + 0.5) as usize);
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::directions::DirectionSet;
    use crate::psf::{Footprints, GridSize};
    use crate::scene::{FaceOrigin, Material, Normalisation, Surface};
    use glam::DVec3;

    /// The rectangle `c ± a ± b` facing `normal`.
    fn rect(c: DVec3, a: DVec3, b: DVec3, normal: DVec3, material: usize) -> Surface {
        let mut vertices = vec![c - a - b, c + a - b, c + a + b, c - a + b];
        if (a.cross(b)).dot(normal) < 0.0 {
            vertices.reverse();
        }
        let n = normal.normalize();
        Surface {
            offset: n.dot(c),
            normal: n,
            area: 4.0 * a.cross(b).length(),
            vertices,
            material,
            origin: FaceOrigin { line: 0, face: 0 },
            uv: None,
        }
    }

    /// A room facing in, its walls each cut into 2 × 2 quads (one plane each: not hideable),
    /// with a lamp flush on its ceiling and a poster on its back wall (each sharing a plane
    /// with what it lies on), a panel of two back-to-back faces in one plane, and a block
    /// standing free. Returns the scene and which surfaces share a plane.
    fn room() -> (Scene, Vec<bool>) {
        let h = 0.8;
        let mut surfaces = Vec::new();
        let mut shared = Vec::new();
        let axes = [DVec3::X, DVec3::Y, DVec3::Z];
        for face in 0..6 {
            let axis = axes[face / 2];
            let sign = if face % 2 == 0 { -1.0 } else { 1.0 };
            let (ta, tb) = (
                axes[(face / 2 + 1) % 3] * (h / 2.0),
                axes[(face / 2 + 2) % 3] * (h / 2.0),
            );
            for (i, j) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                let c = axis * sign * h + ta * i + tb * j;
                surfaces.push(rect(c, ta, tb, -axis * sign, 0));
                // The ceiling (+y) and the back wall (−z) carry the lamp and the poster.
                shared.push(face == 3 || face == 4);
            }
        }
        surfaces.push(rect(DVec3::Y * h, DVec3::X * 0.15, DVec3::Z * 0.15, -DVec3::Y, 1));
        shared.push(true);
        let poster = DVec3::new(0.3, 0.1, -h);
        surfaces.push(rect(poster, DVec3::X * 0.2, DVec3::Y * 0.25, DVec3::Z, 2));
        shared.push(true);
        let panel = DVec3::new(-0.3, -0.2, 0.1);
        let (pa, pb) = (DVec3::new(0.2, 0.0, 0.1), DVec3::Y * 0.3);
        let n = pa.cross(pb).normalize();
        surfaces.push(rect(panel, pa, pb, n, 0));
        surfaces.push(rect(panel, pa, pb, -n, 0));
        shared.extend([true, true]);
        // A block: a parallel face 0.05 from the floor does not share its plane.
        let block = DVec3::new(0.35, -h + 0.05, 0.3);
        surfaces.push(rect(block, DVec3::X * 0.1, DVec3::Z * 0.1, DVec3::Y, 0));
        surfaces.push(rect(
            block + DVec3::X * 0.1 - DVec3::Y * 0.025,
            DVec3::Z * 0.1,
            DVec3::Y * 0.025,
            DVec3::X,
            0,
        ));
        shared.extend([false, false]);
        let scene = Scene {
            surfaces,
            materials: vec![
                Material::grey("wall", 0.7),
                Material {
                    emission: [1.0; 3],
                    ..Material::grey("lamp", 0.7)
                },
                Material::grey("poster", 0.3),
            ],
            normalisation: Normalisation {
                center: DVec3::ZERO,
                scale: 1.0,
            },
            textures: Vec::new(),
        };
        (scene, shared)
    }

    struct Setup {
        scene: Scene,
        atlas: TexelAtlas,
        stacking: Stacking,
        subfields: Vec<Subfield>,
        weights: Vec<f64>,
    }

    fn setup() -> (Setup, Vec<bool>) {
        let (scene, shared) = room();
        let grid = GridSize::new(32, 8).unwrap();
        let atlas = TexelAtlas::new(&scene, grid.ray_spacing(), grid.ray_spacing()).unwrap();
        let footprints = Footprints::new(&scene, &atlas.plane_rep);
        let directions = DirectionSet::new(33).unwrap();
        let subfields = (0..directions.len())
            .map(|d| Subfield::build(&footprints, directions.frame(d), grid))
            .collect();
        let weights = (0..directions.len()).map(|d| directions.get(d).weight).collect();
        let stacking = Stacking::new(&scene, &atlas);
        let setup = Setup {
            scene,
            atlas,
            stacking,
            subfields,
            weights,
        };
        (setup, shared)
    }

    impl Setup {
        fn geometry<'a>(&'a self, stacking: &'a Stacking) -> Geometry<'a> {
            Geometry {
                scene: &self.scene,
                atlas: &self.atlas,
                stacking,
            }
        }
    }

    /// What every surface would be if any could hide another: the walk and its check on
    /// every ray.
    fn all_shared(stacking: &Stacking) -> Stacking {
        Stacking {
            rank: stacking.rank.clone(),
            shares_plane: vec![true; stacking.rank.len()],
        }
    }

    #[test]
    fn only_surfaces_that_share_a_plane_with_another_are_marked() {
        let (setup, shared) = setup();
        // A wall cut in four is one plane in the subfields: its quads are marked only where
        // something else lies in that plane.
        assert_eq!(setup.stacking.shares_plane, shared);
    }

    /// Many surfaces about the origin at one offset (a sphere's facets: none shares a plane),
    /// and many in one plane (tiles of a floor, each its own plane representative, with
    /// their opposite faces: all share it), against every pair compared.
    #[test]
    fn planes_are_found_shared_as_by_comparing_every_pair() {
        let mut surfaces = Vec::new();
        for i in 0..40 {
            for j in 0..20 {
                let (theta, phi) = (
                    (j as f64 + 0.5) / 20.0 * std::f64::consts::PI,
                    i as f64 / 40.0 * std::f64::consts::TAU,
                );
                let n = DVec3::new(theta.sin() * phi.cos(), theta.cos(), theta.sin() * phi.sin());
                let (a, b) = (
                    n.any_orthonormal_vector() * 0.02,
                    n.cross(n.any_orthonormal_vector()) * 0.02,
                );
                surfaces.push(rect(n * 0.7, a, b, n, 0));
            }
        }
        for i in 0..12 {
            for j in 0..12 {
                let c = DVec3::new(i as f64 * 0.1 - 0.6, -0.5, j as f64 * 0.1 - 0.6);
                let up = (i + j) % 3 != 0;
                surfaces.push(rect(
                    c,
                    DVec3::X * 0.04,
                    DVec3::Z * 0.04,
                    if up { DVec3::Y } else { -DVec3::Y },
                    0,
                ));
            }
        }
        // One tile alone in a plane a hair above the others' (still the same plane) and one
        // clearly above (not).
        surfaces.push(rect(
            DVec3::new(0.9, -0.5 + 1e-7, 0.0),
            DVec3::X * 0.04,
            DVec3::Z * 0.04,
            DVec3::Y,
            0,
        ));
        surfaces.push(rect(
            DVec3::new(0.9, -0.45, 0.3),
            DVec3::X * 0.04,
            DVec3::Z * 0.04,
            DVec3::Y,
            0,
        ));
        let scene = Scene {
            surfaces,
            materials: vec![Material::grey("m", 0.5)],
            normalisation: Normalisation {
                center: DVec3::ZERO,
                scale: 1.0,
            },
            textures: Vec::new(),
        };
        let n = scene.surfaces.len();
        let identity: Vec<u32> = (0..n as u32).collect();
        let gap = 1e-4
            + 5e-5
                * scene
                    .surfaces
                    .iter()
                    .flat_map(|s| &s.vertices)
                    .map(|v| v.length())
                    .fold(0.0, f64::max);
        let every_pair: Vec<bool> = (0..n)
            .map(|a| {
                let sa = &scene.surfaces[a];
                (0..n).any(|b| {
                    let sb = &scene.surfaces[b];
                    let dot = sa.normal.dot(sb.normal);
                    let apart = if dot > 0.0 {
                        sa.offset - sb.offset
                    } else {
                        sa.offset + sb.offset
                    };
                    a != b && dot.abs() >= 1.0 - 1e-9 && apart.abs() <= gap
                })
            })
            .collect();
        let found = shares_plane(&scene, &identity);
        assert_eq!(found, every_pair);
        assert_eq!(
            found.iter().filter(|&&s| s).count(),
            144 + 1,
            "the floor's tiles and the one a hair above"
        );
    }

    #[test]
    fn areas_counted_over_spans_are_the_walks_bits() {
        let (setup, _) = setup();
        let walked = all_shared(&setup.stacking);
        let texels = setup.atlas.texels;
        let mut scratch = Scratch::default();
        let (mut fast_tiles, mut walked_tiles) = (0, 0);
        for (sub, &w) in setup.subfields.iter().zip(&setup.weights) {
            let mut fast = vec![[0.0; 3]; texels];
            let mut slow = vec![[0.0; 3]; texels];
            count(setup.geometry(&setup.stacking), sub, &mut scratch, |t| fast[t][0] += w);
            count(setup.geometry(&walked), sub, &mut Scratch::default(), |t| {
                slow[t][0] += w
            });
            let bits = |v: &[Rgb]| v.iter().map(|t| t[0].to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&slow), "direction {:?}", sub.frame.w);
            assert!(slow.iter().any(|t| t[0] > 0.0));
            for k in 0..sub.tile_count() {
                let entries = sub.tile(k);
                match entries.iter().any(|e| setup.stacking.shares_plane[e.surface as usize]) {
                    true => walked_tiles += 1,
                    false if !entries.is_empty() => fast_tiles += 1,
                    false => {}
                }
            }
        }
        // The scene takes both paths.
        assert!(fast_tiles > 0 && walked_tiles > 0, "{fast_tiles} / {walked_tiles}");
        // And the hidden ceiling under the lamp takes no rays: the check still runs there.
        let ceiling_under_lamp = {
            let lamp = &setup.scene.surfaces[24];
            let ceiling = setup.atlas.grid(12);
            let centre = lamp.vertices.iter().copied().sum::<DVec3>() / 4.0;
            ceiling.index(ceiling.coords(centre))
        };
        let mut area = vec![[0.0; 3]; texels];
        for (sub, &w) in setup.subfields.iter().zip(&setup.weights) {
            count(setup.geometry(&setup.stacking), sub, &mut scratch, |t| area[t][0] += w);
        }
        assert_eq!(area[ceiling_under_lamp][0], 0.0);
    }

    #[test]
    fn shooting_checks_hidden_hits_only_where_they_can_be() {
        let (setup, _) = setup();
        let walked = all_shared(&setup.stacking);
        let texels = setup.atlas.texels;
        let radiance: Vec<Rgb> = (0..texels)
            .map(|t| {
                let x = (t as f64 * 0.618_033_988_7).fract();
                [x, 0.5 * x + 0.1, 1.0 - x]
            })
            .collect();
        // One scratch kept from direction to direction, and one whose projection cache of 4
        // slots keeps almost nothing, against a fresh one each time.
        let mut scratch = Scratch::default();
        let mut tiny = Scratch {
            projections: Projections::with_slots(4),
            ..Scratch::default()
        };
        let bits = |v: &[Rgb]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
        for (sub, &weight) in setup.subfields.iter().zip(&setup.weights) {
            let beam = Beam { sub, weight };
            let mut slow = vec![[0.0; 3]; texels];
            let s = shoot(
                setup.geometry(&walked),
                beam,
                &radiance,
                &mut slow,
                None,
                &mut Scratch::default(),
            );
            for scratch in [&mut scratch, &mut tiny] {
                let mut fast = vec![[0.0; 3]; texels];
                let f = shoot(
                    setup.geometry(&setup.stacking),
                    beam,
                    &radiance,
                    &mut fast,
                    None,
                    scratch,
                );
                assert_eq!(f, s);
                assert_eq!(bits(&fast), bits(&slow));
            }
        }
    }

    /// Hits at given depths along one ray, on surfaces `(depth, surface)`.
    fn hits(scene: &Scene, list: &[(f64, u32)]) -> Vec<RayHit> {
        let w = DVec3::new(0.3, 0.4, 0.866).normalize();
        list.iter()
            .map(|&(depth, surface)| {
                let backward = scene.surfaces[surface as usize].normal.dot(w) < 0.0;
                RayHit {
                    depth,
                    surface,
                    texel: 0,
                    mirror: NO_SLOT,
                    tie: if backward {
                        u32::MAX / 2 - surface
                    } else {
                        u32::MAX / 2 + 1 + surface
                    },
                }
            })
            .collect()
    }

    #[test]
    fn a_ray_without_two_hits_at_one_depth_hides_none() {
        let (setup, _) = setup();
        let scene = &setup.scene;
        // The lamp (24) on the ceiling (12), the poster (25) on the back wall (16), the two
        // faces of the panel (26, 27), a floor quad (8) and the block (28): every pair at
        // every pair of depths, ties included, gives what the full loop gives.
        let surfaces = [24, 12, 25, 16, 26, 27, 8, 28];
        let depths = [0.1, 0.1 + 1e-10, 0.1 + 5e-10, 0.3, 0.3 + 2e-9, 0.7];
        let kept = |h: &[RayHit]| h.iter().map(|h| (h.depth.to_bits(), h.surface)).collect::<Vec<_>>();
        let mut hidden = 0;
        for &a in &surfaces {
            for &b in &surfaces {
                for (i, &da) in depths.iter().enumerate() {
                    for &db in &depths[i..] {
                        let list = [(da, a), (db, b), (0.9, 8)];
                        let mut short = hits(scene, &list);
                        let mut full = short.clone();
                        let (n, m) = (drop_hidden(scene, &mut short), drop_tied(scene, &mut full));
                        assert_eq!(kept(&short[..n]), kept(&full[..m]), "{list:?}");
                        hidden += 3 - n;
                    }
                }
            }
        }
        assert!(hidden > 0, "some hits are hidden");
    }
}
