//! Walking the rays of one subfield: the inner loop of propagation.
//!
//! For each tile, the hits of every ray are gathered from the tile's edge
//! tables (depth and texel recomputed from [`SurfaceProjection`]), sorted by
//! depth along `+w`, and handed to a visitor. Shooting then looks at
//! consecutive hits: two surfaces exchange light along the segment between
//! them only if they face each other; a back face blocks (absorbs) the light.

use crate::maps::TexelAtlas;
use crate::psf::{Subfield, SurfaceProjection};
use crate::scene::{Rgb, Scene};
use glam::DVec2;

/// One ray–surface intersection.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RayHit {
    pub depth: f64,
    pub surface: u32,
    pub texel: u32,
}

/// The static inputs of a walk: the scene and where its texels are.
#[derive(Clone, Copy)]
pub(crate) struct Geometry<'a> {
    pub scene: &'a Scene,
    pub atlas: &'a TexelAtlas,
}

/// Reusable buffers of one worker thread.
#[derive(Default)]
pub(crate) struct Scratch {
    offsets: Vec<u32>,
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
pub(crate) fn for_each_ray(
    Geometry { scene, atlas }: Geometry,
    sub: &Subfield,
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
            },
        );
        let mut fill: Vec<u32> = scratch.offsets[..m * m].to_vec();
        for e in entries {
            let surface = &scene.surfaces[e.surface as usize];
            let grid = &atlas.grids[e.surface as usize];
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
                    };
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
                while j > 0 && before(&hits[j], &hits[j - 1]) {
                    hits.swap(j, j - 1);
                    j -= 1;
                }
            }
            visit(hits);
        }
    }
}

#[inline]
fn before(a: &RayHit, b: &RayHit) -> bool {
    a.depth < b.depth || (a.depth == b.depth && a.surface < b.surface)
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

/// Shoots along one direction of solid-angle weight `weight`.
///
/// `radiance[t]` is the power a texel sends per unit of `Δω · (ray count)`,
/// i.e. `Φ_t / T_t` (see the module docs of [`crate::propagate`]); each ray
/// leaving texel `t` carries `radiance[t] · weight`. `facing[s] = n_s · w`.
/// Power arriving at a texel is added to `received[t]`.
pub(crate) fn shoot(
    geometry: Geometry,
    sub: &Subfield,
    weight: f64,
    facing: &[f64],
    radiance: &[Rgb],
    received: &mut [Rgb],
    scratch: &mut Scratch,
) -> Flow {
    let mut flow = Flow::default();
    for_each_ray(geometry, sub, scratch, |hits| {
        // Along −w, the first surface sends into the void if it faces −w.
        let first = hits[0];
        if facing[first.surface as usize] < 0.0 {
            add_scaled(&mut flow.shot, &radiance[first.texel as usize], weight);
            add_scaled(&mut flow.escaped, &radiance[first.texel as usize], weight);
        }
        for pair in hits.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            let a_forward = facing[a.surface as usize] > 0.0; // a's front looks along +w
            let b_backward = facing[b.surface as usize] < 0.0; // b's front looks along −w
            if a_forward {
                let l = &radiance[a.texel as usize];
                add_scaled(&mut flow.shot, l, weight);
                if b_backward {
                    add_scaled(&mut flow.received, l, weight);
                    add_scaled(&mut received[b.texel as usize], l, weight);
                } else {
                    add_scaled(&mut flow.blocked, l, weight);
                }
            }
            if b_backward {
                let l = &radiance[b.texel as usize];
                add_scaled(&mut flow.shot, l, weight);
                if a_forward {
                    add_scaled(&mut flow.received, l, weight);
                    add_scaled(&mut received[a.texel as usize], l, weight);
                } else {
                    add_scaled(&mut flow.blocked, l, weight);
                }
            }
        }
        let last = hits[hits.len() - 1];
        if facing[last.surface as usize] > 0.0 {
            add_scaled(&mut flow.shot, &radiance[last.texel as usize], weight);
            add_scaled(&mut flow.escaped, &radiance[last.texel as usize], weight);
        }
    });
    flow
}

/// Adds `weight` to `area[t]` for every ray crossing texel `t`: one direction's
/// share of the texels' discrete areas `T_t`.
pub(crate) fn count(geometry: Geometry, sub: &Subfield, weight: f64, area: &mut [Rgb], scratch: &mut Scratch) {
    for_each_ray(geometry, sub, scratch, |hits| {
        for h in hits {
            area[h.texel as usize][0] += weight;
        }
    });
}
