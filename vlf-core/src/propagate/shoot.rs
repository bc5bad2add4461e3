//! Walking the rays of one subfield: the inner loop of propagation.
//!
//! For each tile, the hits of every ray are gathered from the tile's edge
//! tables (depth and texel recomputed from [`SurfaceProjection`]), sorted by
//! depth along `+w`, and handed to a visitor. Shooting then looks at
//! consecutive hits: two surfaces exchange light along the segment between
//! them only if they face each other; a back face blocks (absorbs) the light.

use crate::maps::TexelAtlas;
use crate::psf::raster::SUBPIXELS;
use crate::psf::{PsfFrame, Subfield, SurfaceProjection};
use crate::scene::{Rgb, Scene};
use glam::DVec2;

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

/// The static inputs of a walk: the scene, where its texels are, and which
/// of two coplanar surfaces lies on top ([`stacking`]).
#[derive(Clone, Copy)]
pub(crate) struct Geometry<'a> {
    pub scene: &'a Scene,
    pub atlas: &'a TexelAtlas,
    pub stacking: &'a [u32],
}

/// Depths closer than this (VLF frame, where the scene spans 2) are a tie:
/// surfaces that coincide up to rounding, such as a lamp modelled flush with
/// its ceiling.
const DEPTH_TIE: f64 = 1e-9;

/// The stacking order of coplanar surfaces: a higher rank lies on top
/// (is seen first from the front). Emitters lie on top of what they are
/// flush with, then smaller charts on top of larger ones (a decal on a wall,
/// however the wall is cut: `chart_area` is each surface's chart's area),
/// then later surfaces.
pub(crate) fn stacking(scene: &Scene, chart_area: &[f64]) -> Vec<u32> {
    let mut order: Vec<usize> = (0..scene.surfaces.len()).collect();
    order.sort_by(|&a, &b| {
        let ea = scene.material(a).is_emitter();
        let eb = scene.material(b).is_emitter();
        ea.cmp(&eb)
            .then(chart_area[b].total_cmp(&chart_area[a]))
            .then(a.cmp(&b))
    });
    let mut rank = vec![0u32; order.len()];
    for (r, s) in order.into_iter().enumerate() {
        rank[s] = r as u32;
    }
    rank
}

/// Reusable buffers of one worker thread.
#[derive(Default)]
pub(crate) struct Scratch {
    offsets: Vec<u32>,
    fill: Vec<u32>,
    hits: Vec<RayHit>,
}

/// Texel lookup as an affine function of grid coordinates: the texel
/// coordinates of the hit of ray `(x, y)` are `c0 + cx·x + cy·y`.
#[derive(Clone, Copy)]
struct TexelProjection {
    depth: [f64; 3],
    c0: DVec2,
    cx: DVec2,
    cy: DVec2,
}

/// Calls `visit` for every ray of `sub` that crosses at least one surface,
/// with its hits sorted by increasing depth along `+w` (ties broken by
/// surface id, so the order is deterministic even for coplanar surfaces).
/// `mirror_base[e]` is the first mirror slot of tile entry `e` (or
/// [`NO_SLOT`]); without it no hit has a mirror slot.
pub(crate) fn for_each_ray(
    Geometry { scene, atlas, stacking }: Geometry,
    sub: &Subfield,
    mirror_base: Option<&[u32]>,
    scratch: &mut Scratch,
    mut visit: impl FnMut(&[RayHit]),
) {
    let m = sub.grid.tile as usize;
    let per_side = sub.grid.tiles_per_side() as usize;
    let n = sub.grid.resolution;
    for k in 0..sub.tile_count() {
        let entries = sub.tile(k);
        if entries.is_empty() {
            continue;
        }
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
            let rank = stacking[e.surface as usize];
            let tie = if scene.surfaces[e.surface as usize].normal.dot(sub.frame.w) < 0.0 {
                u32::MAX / 2 - rank
            } else {
                u32::MAX / 2 + 1 + rank
            };
            let surface = &scene.surfaces[e.surface as usize];
            let grid = atlas.grid(e.surface as usize);
            let proj = SurfaceProjection::new(&sub.frame, n, surface.normal, surface.offset);
            let tp = TexelProjection {
                depth: proj.depth,
                c0: grid.coords(proj.p0),
                cx: grid.coords(proj.p0 + proj.px) - grid.coords(proj.p0),
                cy: grid.coords(proj.p0 + proj.py) - grid.coords(proj.p0),
            };
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
                        texel: grid.index(tp.c0 + tp.cx * gx + tp.cy * y) as u32,
                        mirror,
                        tie,
                    };
                    if mirror != NO_SLOT {
                        mirror += 1;
                    }
                }
            }
        }
        for r in 0..m * m {
            let (a, b) = (scratch.offsets[r] as usize, scratch.offsets[r + 1] as usize);
            if a == b {
                continue;
            }
            let hits = &mut scratch.hits[a..b];
            // Few hits per ray: insertion sort beats a general sort here.
            for i in 1..hits.len() {
                let mut j = i;
                while j > 0 && before(scene, &sub.frame, n, &hits[j], &hits[j - 1]) {
                    hits.swap(j, j - 1);
                    j -= 1;
                }
            }
            let seen = drop_hidden(scene, hits);
            if seen > 0 {
                visit(&hits[..seen]);
            }
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

/// Hit order along `+w`: by depth, and for (near-)coincident *parallel*
/// surfaces by their tie key, so that a flush lamp is met before its ceiling
/// from below and two back-to-back polygons never exchange light through
/// each other. Surfaces that are not parallel and meet the ray at (almost)
/// the same depth cross there — a ray grazing the edge where a tessellated
/// sphere's silhouette folds — and keep their depth order: the tie key would
/// put the facet facing `−w` first and let the ray escape through the fold;
/// near a silhouette edge, see [`silhouette_order`].
#[inline]
fn before(scene: &Scene, frame: &PsfFrame, n: u32, a: &RayHit, b: &RayHit) -> bool {
    let gap = (a.depth - b.depth).abs();
    if gap <= DEPTH_TIE && parallel(scene, a.surface, b.surface) {
        return a.tie < b.tie;
    }
    if gap <= SILHOUETTE_GAP
        && a.faces_backward() != b.faces_backward()
        && let Some(a_first) = silhouette_order(scene, frame, n, a, b)
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
fn silhouette_order(scene: &Scene, frame: &PsfFrame, n: u32, a: &RayHit, b: &RayHit) -> Option<bool> {
    if parallel(scene, a.surface, b.surface) {
        return None;
    }
    let (sa, sb) = (&scene.surfaces[a.surface as usize], &scene.surfaces[b.surface as usize]);
    let (pa, pb) = (
        SurfaceProjection::new(frame, n, sa.normal, sa.offset),
        SurfaceProjection::new(frame, n, sb.normal, sb.offset),
    );
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

/// Adds `weight` to `area[t]` for every ray crossing texel `t`: one direction's
/// share of the texels' discrete areas `T_t`.
pub(crate) fn count(geometry: Geometry, sub: &Subfield, weight: f64, area: &mut [Rgb], scratch: &mut Scratch) {
    for_each_ray(geometry, sub, None, scratch, |hits| {
        for h in hits {
            area[h.texel as usize][0] += weight;
        }
    });
}
