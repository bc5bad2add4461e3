//! Footprints: the shapes a subfield rasterises, prepared once per scene.
//!
//! For every direction, [`super::Subfield::build`] finds the rays that cross each surface. Done
//! polygon by polygon, that work grows with how finely a modeller cut the scene, not with its
//! rays: a wall given as 3 200 triangles is rasterised 3 200 times per direction, and every
//! triangle of a scan projects its own copy of its three corners (a closed mesh has half as
//! many vertices as triangles). So the scene is prepared once, here:
//!
//! * **Shared vertices.** Corners that coincide (within [`crate::scene::VERTEX_QUANTUM`]) are
//!   one point, projected and snapped once per direction however many polygons meet there.
//!   Snapping the same point once also keeps shared edges shared exactly.
//! * **Planar charts by their outline.** The polygons of a planar group (coplanar neighbours
//!   of one diffuse material, one entry per tile, see [`crate::maps::charts`]) are one plane
//!   to a ray: what matters is which centres the group covers, not which of its polygons
//!   covers them. Each polygon's edges are run counter-clockwise; an edge that a neighbour runs
//!   the other way adds nothing to any winding number and is dropped, and what is left is the
//!   group's outline (outer loop and holes). [`super::raster::rasterize_outline`] covers
//!   exactly the centres that the polygons' own rasterisations cover (proved there, and
//!   tested), so the subfields do not change, only their cost: the 40 × 40 grid room costs
//!   what the plain room does.
//!
//! Curved charts keep one shape per polygon: their polygons are different planes, and a ray
//! may cross the chart twice.

use super::PsfFrame;
use super::raster::{self, Crossing, Fixed, RowSpan};
use crate::scene::{Scene, vertex_key};
use glam::DVec3;
use std::collections::HashMap;

/// One shape of [`Footprints`]: a convex polygon (its corners, in order) or an outline (its
/// directed edges), standing for surface `surface` in the tiles.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Shape {
    surface: u32,
    kind: ShapeKind,
    /// Range of [`Footprints::corners`] (a polygon) or [`Footprints::edges`] (an outline).
    first: u32,
    len: u32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ShapeKind {
    Polygon,
    Outline,
}

/// What a subfield rasterises (see the module docs): the scene's distinct vertices, and one
/// shape per surface or per planar group.
#[derive(Clone, Debug, PartialEq)]
pub struct Footprints {
    points: Vec<DVec3>,
    /// Small, as they are walked for every direction: a scan's triangles are 10⁵ shapes.
    shapes: Vec<Shape>,
    /// Each shape's bounding-box corners, four indices into the points' [`CentreKey`]s: a
    /// triangle's or a quad's own corners (a triangle's last repeated), or the wide key's
    /// (index `points.len()`) for a shape that is always rasterised (an outline, a polygon of
    /// other than three or four corners). Fixed-size, so that the test every shape takes in every direction is a
    /// branch-free pass ([`Footprints::rasterize`]).
    boxes: Vec<[u32; 4]>,
    /// Each shape's plane normal (a shape seen edge-on is crossed by no ray), read only for
    /// the shapes that cover a ray centre.
    normals: Vec<DVec3>,
    corners: Vec<u32>,
    edges: Vec<(u32, u32)>,
}

/// Per-direction working memory of [`Footprints::rasterize`], kept by the caller.
#[derive(Default)]
pub struct RasterScratch {
    /// The points in fixed point, in `i32` (grid coordinates below 2¹²·[`raster::SUBPIXELS`]):
    /// half the cache a scan's 10⁵ vertices take in `i64`.
    fixed: Vec<[i32; 2]>,
    polygon: Vec<Fixed>,
    crossings: Vec<Crossing>,
    /// Each point's [`CentreKey`], and the wide key last.
    keys: Vec<CentreKey>,
    /// The shapes whose bounding box holds a ray centre, in shape order.
    candidates: Vec<u32>,
    /// What a subfield's tiles are built from ([`super::Subfield::build_with`]).
    pub(super) tiles: super::TileScratch,
}

/// Where a point lies among the ray centres, for the bounding-box test of every shape in every
/// direction: the lanes `[⌈x⌉, ⌈y⌉, −⌊x⌋, −⌊y⌋]`, the first centre index at or above the
/// point and minus the last at or below it, per axis ([`raster::first_centre_from`],
/// [`raster::last_centre_to`]). The lane-wise least of a box's corners' keys holds its lowest
/// corner's first centres and its highest corner's last ones, and the box holds a centre when
/// the first is at most the last on both axes: `⌈x⌉ − ⌊x⌋ ≤ 0`, the sums of opposite lanes.
///
/// Four `i16` lanes in a `u64` (lane `k` in bits `16k..16k + 16`), so that a box's four
/// corners are three lane-wise minima of one SSE2 register each. Clamped to
/// ±[`CentreKey::LIMIT`], far past any grid (`N ≤ 4096`), which can only pass a box lying
/// wholly past the grid, and that the rasteriser then drops: no box that holds a centre fails.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct CentreKey(u64);

impl CentreKey {
    const LIMIT: i64 = 16_000;
    /// Below every point's lanes: a box with it holds every centre.
    const WIDE: CentreKey = CentreKey::from_lanes([-Self::LIMIT as i16; 4]);

    /// The key of the point `(x, y)` in fixed point.
    #[inline]
    fn of(x: i64, y: i64) -> Self {
        let lane = |c: i64| c.clamp(-Self::LIMIT, Self::LIMIT) as i16;
        CentreKey::from_lanes([
            lane(raster::first_centre_from(x)),
            lane(raster::first_centre_from(y)),
            lane(-raster::last_centre_to(x)),
            lane(-raster::last_centre_to(y)),
        ])
    }

    const fn from_lanes(lanes: [i16; 4]) -> Self {
        let mut bits = 0;
        let mut k = 0;
        while k < 4 {
            bits |= (lanes[k] as u16 as u64) << (16 * k);
            k += 1;
        }
        CentreKey(bits)
    }

    #[cfg_attr(all(target_arch = "x86_64", target_feature = "sse2"), allow(dead_code))]
    fn lanes(self) -> [i16; 4] {
        std::array::from_fn(|k| (self.0 >> (16 * k)) as u16 as i16)
    }

    /// Whether the box of four corners holds a ray centre.
    #[cfg(all(target_arch = "x86_64", target_feature = "sse2"))]
    #[inline]
    fn box_spans_a_centre([a, b, c, d]: [CentreKey; 4]) -> bool {
        use std::arch::x86_64::{
            _mm_add_epi16, _mm_cmpgt_epi16, _mm_cvtsi64_si128, _mm_min_epi16, _mm_movemask_epi8, _mm_setzero_si128,
            _mm_shufflelo_epi16,
        };
        // SAFETY: these intrinsics are unsafe only in that they need SSE2, and this function
        // is compiled only where the target enables SSE2 (`cfg` above; every x86-64 target
        // does). They take no pointers.
        unsafe {
            let lanes = |k: CentreKey| _mm_cvtsi64_si128(k.0 as i64);
            let least = _mm_min_epi16(_mm_min_epi16(lanes(a), lanes(b)), _mm_min_epi16(lanes(c), lanes(d)));
            // Lanes 2 and 3 moved onto 0 and 1 and added: |sums| ≤ 2·LIMIT, no overflow.
            let sums = _mm_add_epi16(least, _mm_shufflelo_epi16::<0b00_00_11_10>(least));
            _mm_movemask_epi8(_mm_cmpgt_epi16(sums, _mm_setzero_si128())) & 0b1111 == 0
        }
    }

    /// Whether the box of four corners holds a ray centre.
    #[cfg(not(all(target_arch = "x86_64", target_feature = "sse2")))]
    #[inline]
    fn box_spans_a_centre(corners: [CentreKey; 4]) -> bool {
        CentreKey::box_spans_a_centre_by_lanes(corners)
    }

    /// [`CentreKey::box_spans_a_centre`] lane by lane: where SSE2 is not, and the tests'
    /// reference where it is.
    #[cfg_attr(all(target_arch = "x86_64", target_feature = "sse2"), allow(dead_code))]
    fn box_spans_a_centre_by_lanes(corners: [CentreKey; 4]) -> bool {
        let lanes = corners.map(CentreKey::lanes);
        let [x, y, minus_x, minus_y]: [i32; 4] =
            std::array::from_fn(|k| lanes.iter().map(|l| i32::from(l[k])).min().unwrap_or(i32::MAX));
        (x + minus_x <= 0) & (y + minus_y <= 0)
    }
}

impl Footprints {
    /// Prepares `scene`'s shapes. `plane_rep[s]` is the surface that stands for `s` in the
    /// tiles ([`crate::maps::TexelAtlas::plane_rep`]): surfaces sharing one are a planar group,
    /// rasterised by its outline. Deterministic: shapes in order of their surface, edges sorted.
    pub fn new(scene: &Scene, plane_rep: &[u32]) -> Self {
        Footprints::of(scene, plane_rep, |_| true)
    }

    /// [`Footprints::new`] for the shapes whose standing surface is kept (`keep(rep)`), and
    /// only the points they use: what a subfield of those surfaces alone rasterises. Its tiles
    /// hold the same entries, with the same spans, as the whole scene's hold for those surfaces
    /// (a tile's entries are sorted by surface, and a shape is rasterised on its own); only the
    /// slot numbering (`first_ray`) counts their rays alone. The mirror views are built so
    /// ([`crate::propagate::specular::MirrorView`]): a few mirror planes cost a direction a few
    /// shapes, not the scene's.
    pub fn of(scene: &Scene, plane_rep: &[u32], keep: impl Fn(u32) -> bool) -> Self {
        let rep_of = |s: usize| plane_rep.get(s).copied().unwrap_or(s as u32) as usize;
        let mut members: Vec<Vec<u32>> = vec![Vec::new(); scene.surfaces.len()];
        for s in 0..scene.surfaces.len() {
            members[rep_of(s)].push(s as u32);
        }
        // Corners shared by several surfaces are equal only up to rounding (`vertex_key` merges
        // them); the point stands at the first one met in the whole scene, shapes kept or not,
        // so that a subset's corners snap to the grid exactly as the whole scene's do.
        let mut canonical: HashMap<[i64; 3], DVec3> = HashMap::new();
        for &s in members.iter().flatten() {
            for &p in &scene.surfaces[s as usize].vertices {
                canonical.entry(vertex_key(p)).or_insert(p);
            }
        }
        let mut points = Vec::new();
        let mut index_of: HashMap<[i64; 3], u32> = HashMap::new();
        let mut point = |p: DVec3| {
            let key = vertex_key(p);
            *index_of.entry(key).or_insert_with(|| {
                points.push(canonical.get(&key).copied().unwrap_or(p));
                points.len() as u32 - 1
            })
        };
        let (mut shapes, mut normals, mut corners, mut edges) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (rep, group) in members.iter().enumerate() {
            if !keep(rep as u32) {
                continue;
            }
            let normal = scene.surfaces[rep].normal;
            if let [only] = group[..] {
                let first = corners.len() as u32;
                corners.extend(scene.surfaces[only as usize].vertices.iter().map(|&p| point(p)));
                normals.push(normal);
                shapes.push(Shape {
                    surface: rep as u32,
                    kind: ShapeKind::Polygon,
                    first,
                    len: corners.len() as u32 - first,
                });
            } else if !group.is_empty() {
                // Net count of every undirected edge, + for the direction low → high index.
                let mut net: HashMap<(u32, u32), i32> = HashMap::new();
                for &s in group {
                    let ring: Vec<u32> = scene.surfaces[s as usize].vertices.iter().map(|&p| point(p)).collect();
                    for (k, &a) in ring.iter().enumerate() {
                        let b = ring[(k + 1) % ring.len()];
                        if a != b {
                            *net.entry((a.min(b), a.max(b))).or_default() += if a < b { 1 } else { -1 };
                        }
                    }
                }
                let mut kept: Vec<((u32, u32), i32)> = net.into_iter().filter(|&(_, c)| c != 0).collect();
                kept.sort_unstable();
                let first = edges.len() as u32;
                for ((lo, hi), c) in kept {
                    let edge = if c > 0 { (lo, hi) } else { (hi, lo) };
                    edges.extend(std::iter::repeat_n(edge, c.unsigned_abs() as usize));
                }
                normals.push(normal);
                shapes.push(Shape {
                    surface: rep as u32,
                    kind: ShapeKind::Outline,
                    first,
                    len: edges.len() as u32 - first,
                });
            }
        }
        let wide = [points.len() as u32; 4];
        let boxes = (shapes.iter())
            .map(|shape| match shape.kind {
                ShapeKind::Polygon => match corners[shape.first as usize..(shape.first + shape.len) as usize] {
                    [a, b, c] => [a, b, c, c],
                    [a, b, c, d] => [a, b, c, d],
                    _ => wide,
                },
                ShapeKind::Outline => wide,
            })
            .collect();
        Footprints {
            points,
            shapes,
            boxes,
            normals,
            corners,
            edges,
        }
    }

    /// Number of shapes rasterised per direction (surfaces, with a planar group counted once).
    pub fn shape_count(&self) -> usize {
        self.shapes.len()
    }

    /// Rasterises every shape not seen edge-on onto the `n × n` grid of `frame`: `emit` gets the
    /// surface that stands for it and each covered row span.
    pub fn rasterize(&self, frame: &PsfFrame, n: u32, scratch: &mut RasterScratch, mut emit: impl FnMut(u32, RowSpan)) {
        let RasterScratch {
            fixed,
            polygon,
            crossings,
            keys,
            candidates,
            ..
        } = scratch;
        fixed.resize(self.points.len(), [0; 2]);
        keys.resize(self.points.len() + 1, CentreKey::WIDE);
        for ((&p, fixed), key) in self.points.iter().zip(fixed.iter_mut()).zip(keys.iter_mut()) {
            let g = frame.to_grid(p, n);
            let (x, y) = raster::snap_point(g);
            // The key from the coordinates the rasteriser reads, so that both see one point.
            let (x, y) = (x as i32, y as i32);
            *fixed = [x, y];
            *key = CentreKey::of(x.into(), y.into());
        }
        keys[self.points.len()] = CentreKey::WIDE;
        // Most polygons of a scan cover no ray centre, and their bounding box says so before
        // anything else is looked at. Asked of every shape in one pass without a branch, whose
        // outcome (a scan's polygons are near the size of a ray cell) is a coin's toss; the
        // shapes that pass are listed in order for the pass below.
        candidates.clear();
        candidates.resize(self.boxes.len(), 0);
        let mut count = 0;
        for (shape, corners) in self.boxes.iter().enumerate() {
            candidates[count] = shape as u32;
            count += CentreKey::box_spans_a_centre(corners.map(|i| keys[i as usize])) as usize;
        }
        candidates.truncate(count);
        let at = |i: u32| {
            let [x, y] = fixed[i as usize];
            (x as i64, y as i64)
        };
        for &index in candidates.iter() {
            let (shape, normal) = (&self.shapes[index as usize], &self.normals[index as usize]);
            let range = shape.first as usize..(shape.first + shape.len) as usize;
            let surface = shape.surface;
            match shape.kind {
                ShapeKind::Polygon => {
                    polygon.clear();
                    polygon.extend(self.corners[range].iter().map(|&i| at(i)));
                    // Seen edge-on, it covers nothing: asked only of the polygons that cover a
                    // centre (most of a scan's whose box holds one do not), as its normal is
                    // one more cache line.
                    let mut edge_on = None;
                    raster::rasterize_convex_fixed(polygon, n, |s| {
                        if !*edge_on.get_or_insert_with(|| normal.dot(frame.w).abs() < 1e-12) {
                            emit(surface, s);
                        }
                    });
                }
                ShapeKind::Outline => {
                    if normal.dot(frame.w).abs() < 1e-12 {
                        continue; // edge-on: no ray crosses it
                    }
                    raster::rasterize_outline_with(&self.edges[range], at, n, crossings, |s| emit(surface, s));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::maps::TexelAtlas;
    use crate::scene::{FaceOrigin, ImportOptions, Material};
    use glam::DVec2;

    /// A floor cut into a jittered grid of triangles and quads, a box standing on it and a
    /// second floor piece of another material: every direction's rays are covered by the
    /// same surfaces' footprints, group by group, whether the groups are rasterised by their
    /// outline or polygon by polygon.
    #[test]
    fn outlines_cover_what_the_polygons_cover() {
        let k = 12;
        let mut seed = 5u64;
        let mut jitter = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.3
        };
        let mut grid = vec![vec![DVec3::ZERO; k + 1]; k + 1];
        for (a, row) in grid.iter_mut().enumerate() {
            for (b, p) in row.iter_mut().enumerate() {
                let inside = a > 0 && a < k && b > 0 && b < k;
                let (ja, jb) = if inside { (jitter(), jitter()) } else { (0.0, 0.0) };
                *p = DVec3::new((a as f64 + ja) / k as f64, (b as f64 + jb) / k as f64, 0.0);
            }
        }
        let origin = FaceOrigin { line: 0, face: 0 };
        let mut polygons = Vec::new();
        for a in 0..k {
            for b in 0..k {
                let (p00, p10, p11, p01) = (grid[a][b], grid[a + 1][b], grid[a + 1][b + 1], grid[a][b + 1]);
                match (a * 7 + b) % 3 {
                    0 => polygons.push((vec![p00, p10, p11, p01], 0, origin.clone())),
                    _ => {
                        polygons.push((vec![p00, p10, p11], 0, origin.clone()));
                        polygons.push((vec![p00, p11, p01], 0, origin.clone()));
                    }
                }
            }
        }
        // Another material beside it, sharing its edge.
        polygons.push((
            vec![
                DVec3::new(1.0, 0.0, 0.0),
                DVec3::new(1.5, 0.0, 0.0),
                DVec3::new(1.5, 1.0, 0.0),
                DVec3::new(1.0, 1.0, 0.0),
            ],
            1,
            origin.clone(),
        ));
        // A lamp facing down above it.
        polygons.push((
            vec![
                DVec3::new(0.2, 0.2, 0.8),
                DVec3::new(0.2, 0.6, 0.8),
                DVec3::new(0.6, 0.6, 0.8),
                DVec3::new(0.6, 0.2, 0.8),
            ],
            2,
            origin,
        ));
        let material = |name: &str, emission: f64| Material {
            emission: [emission; 3],
            ..Material::grey(name, 0.5)
        };
        let (scene, _) = Scene::from_polygons(
            &polygons,
            vec![material("a", 0.0), material("b", 0.0), material("lamp", 1.0)],
            &ImportOptions::default(),
        )
        .unwrap();
        let atlas = TexelAtlas::new(&scene, 0.05, 2.0 / 64.0).unwrap();
        let outlines = Footprints::new(&scene, &atlas.plane_rep);
        let identity: Vec<u32> = (0..scene.surfaces.len() as u32).collect();
        let one_by_one = Footprints::new(&scene, &identity);
        assert_eq!(one_by_one.shape_count(), scene.surfaces.len());
        assert_eq!(outlines.shape_count(), 3, "the floor is one group");
        let n = 64;
        let mut scratch = RasterScratch::default();
        for w in [
            DVec3::new(0.0, 0.0, 1.0),
            DVec3::new(0.3, -0.2, 0.9),
            DVec3::new(-0.7, 0.1, 0.2),
            DVec3::new(0.01, 0.95, 0.2),
        ] {
            let frame = PsfFrame::new(w);
            let mut by_group = vec![vec![0u32; (n * n) as usize]; scene.surfaces.len()];
            outlines.rasterize(&frame, n, &mut scratch, |s, span| {
                for x in span.start..span.end {
                    by_group[s as usize][(span.row * n + x) as usize] += 1;
                }
            });
            let mut by_polygon = vec![vec![0u32; (n * n) as usize]; scene.surfaces.len()];
            one_by_one.rasterize(&frame, n, &mut scratch, |s, span| {
                for x in span.start..span.end {
                    by_polygon[atlas.plane_rep[s as usize] as usize][(span.row * n + x) as usize] += 1;
                }
            });
            assert_eq!(by_group, by_polygon, "direction {w}");
            assert!(by_group.iter().flatten().all(|&c| c <= 1));
            // The plain polygons' own rasteriser agrees too.
            let floor: u32 = by_group[0].iter().sum();
            let direct: u64 = (scene.surfaces.iter().enumerate())
                .filter(|(s, _)| atlas.plane_rep[*s] == 0)
                .map(|(_, s)| {
                    let pts: Vec<DVec2> = s.vertices.iter().map(|&p| frame.to_grid(p, n)).collect();
                    raster::rasterize_convex(&pts, n, |_| {})
                })
                .sum();
            assert_eq!(floor as u64, direct);
            assert!(floor > 0);
        }
    }

    /// The bounding-box test by centre keys, lane-parallel and lane by lane, says what
    /// `raster::spans_a_centre` says of the box's extent on both axes, for boxes of four corners
    /// (repeats included) lying on centres, on cell edges and one step beside either, inside
    /// and past the grid; past the keys' clamp it may only pass boxes the exact test fails
    /// that lie wholly beyond it. A box with the wide key passes.
    #[test]
    fn a_box_holds_a_centre_by_its_keys_as_by_its_corners() {
        let s = raster::SUBPIXELS;
        let mut seed = 11u64;
        let mut next = |bound: i64| {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 33) % bound as u64) as i64
        };
        // Near the cell `base`, on or one step beside a centre or a cell edge, or anywhere.
        let coordinate = |base: i64, next: &mut dyn FnMut(i64) -> i64| {
            let offset = [0, s / 2, s / 2 - 1, s / 2 + 1, 1, s - 1, next(s)][next(7) as usize];
            (base + next(2)) * s + offset
        };
        let (mut passed, mut failed) = (0, 0);
        for round in 0..200_000 {
            // Mostly boxes a cell or two wide near the origin; some anywhere up to past the
            // clamp, some at its edges.
            let reach = if round % 10 == 0 { CentreKey::LIMIT + 40 } else { 3 };
            let edges = [
                -CentreKey::LIMIT - 2,
                -CentreKey::LIMIT - 1,
                CentreKey::LIMIT - 1,
                CentreKey::LIMIT,
            ];
            let base = match round % 10 {
                5 => (edges[next(4) as usize], edges[next(4) as usize]),
                _ => (next(2 * reach + 1) - reach, next(2 * reach + 1) - reach),
            };
            let points: Vec<(i64, i64)> = (0..4)
                .map(|_| (coordinate(base.0, &mut next), coordinate(base.1, &mut next)))
                .collect();
            let mut corners = [0usize, 1, 2, 3];
            if round % 3 == 0 {
                corners[3] = 2; // a triangle
            }
            let keys = corners.map(|k| CentreKey::of(points[k].0, points[k].1));
            let xs = corners.map(|k| points[k].0);
            let ys = corners.map(|k| points[k].1);
            let (lo_x, hi_x) = (*xs.iter().min().unwrap(), *xs.iter().max().unwrap());
            let (lo_y, hi_y) = (*ys.iter().min().unwrap(), *ys.iter().max().unwrap());
            let exact = raster::spans_a_centre(lo_x, hi_x) && raster::spans_a_centre(lo_y, hi_y);
            let (fast, by_lanes) = (
                CentreKey::box_spans_a_centre(keys),
                CentreKey::box_spans_a_centre_by_lanes(keys),
            );
            assert_eq!(fast, by_lanes, "{points:?}");
            // Wholly past the clamp, in centre indices: the first centre above the box past
            // +LIMIT, or the last below it past −LIMIT.
            let beyond = |lo: i64, hi: i64| {
                raster::first_centre_from(lo) > CentreKey::LIMIT || raster::last_centre_to(hi) < -CentreKey::LIMIT
            };
            if fast != exact {
                assert!(
                    fast && (beyond(lo_x, hi_x) || beyond(lo_y, hi_y)),
                    "{points:?}: {exact} exactly"
                );
            }
            if exact {
                passed += 1;
            } else {
                failed += 1;
            }
            let mut wide = keys;
            wide[round % 4] = CentreKey::WIDE;
            assert!(CentreKey::box_spans_a_centre(wide) && CentreKey::box_spans_a_centre_by_lanes(wide));
        }
        assert!(passed > 20_000 && failed > 20_000, "{passed} boxes pass, {failed} fail");
    }

    /// A subset's footprints (`Footprints::of`, what the mirror views rasterise) place a corner
    /// shared with a surface left out where the whole scene's do: at the first of its nearly
    /// equal copies met in the whole scene, so the subset's shapes snap to the grid to the bit
    /// as they do among all the others.
    #[test]
    fn a_subset_places_shared_corners_as_the_whole_scene() {
        let origin = FaceOrigin { line: 0, face: 0 };
        // The second quad's copies of the shared edge's corners are off by far less than the
        // vertex quantum: one vertex, whose place is the first quad's.
        let off = 1e-12;
        let polygons = vec![
            (
                vec![
                    DVec3::new(0.0, 0.0, 0.0),
                    DVec3::new(0.3, 0.0, 0.0),
                    DVec3::new(0.3, 1.0, 0.0),
                    DVec3::new(0.0, 1.0, 0.0),
                ],
                0,
                origin.clone(),
            ),
            (
                vec![
                    DVec3::new(0.3 + off, 0.0, 0.0),
                    DVec3::new(1.0, 0.0, 0.0),
                    DVec3::new(1.0, 1.0, 0.0),
                    DVec3::new(0.3 - off, 1.0, 0.0),
                ],
                1,
                origin,
            ),
        ];
        let lamp = Material {
            emission: [1.0; 3],
            ..Material::grey("lamp", 0.5)
        };
        let materials = vec![Material::grey("wall", 0.5), lamp];
        let (scene, _) = Scene::from_polygons(&polygons, materials, &ImportOptions::default()).unwrap();
        let atlas = TexelAtlas::new(&scene, 0.05, 2.0 / 64.0).unwrap();
        let whole = Footprints::new(&scene, &atlas.plane_rep);
        let rep = atlas.plane_rep[1];
        let subset = Footprints::of(&scene, &atlas.plane_rep, |s| s == rep);
        assert_eq!(subset.shape_count(), 1);
        let corners = |f: &Footprints| -> Vec<DVec3> {
            let shape = f.shapes.iter().find(|s| s.surface == rep).expect("the kept shape");
            assert_eq!(shape.kind, ShapeKind::Polygon);
            let range = shape.first as usize..(shape.first + shape.len) as usize;
            f.corners[range].iter().map(|&c| f.points[c as usize]).collect()
        };
        let bits = |p: &DVec3| p.to_array().map(f64::to_bits);
        // The premise: the second quad has its own copies of two corners of the first.
        let (first, second) = (&scene.surfaces[0].vertices, &scene.surfaces[1].vertices);
        let copies: Vec<&DVec3> = (second.iter())
            .filter(|q| {
                first
                    .iter()
                    .any(|p| vertex_key(*p) == vertex_key(**q) && bits(p) != bits(q))
            })
            .collect();
        assert_eq!(copies.len(), 2, "{first:?} and {second:?}");
        let (a, b) = (corners(&whole), corners(&subset));
        assert!(a.iter().zip(&b).all(|(p, q)| bits(p) == bits(q)), "{a:?} against {b:?}");
        // Placed at the first quad's copies.
        for q in copies {
            assert!(
                a.iter()
                    .any(|p| first.iter().any(|f| bits(f) == bits(p)) && vertex_key(*p) == vertex_key(*q))
            );
        }
        // And they rasterise the same spans.
        let (n, frame) = (64, PsfFrame::new(DVec3::new(0.2, -0.3, 0.9)));
        let spans = |f: &Footprints| {
            let mut out = Vec::new();
            f.rasterize(&frame, n, &mut RasterScratch::default(), |s, span| {
                if s == rep {
                    out.push((span.row, span.start, span.end));
                }
            });
            out
        };
        assert_eq!(spans(&whole), spans(&subset));
    }
}
