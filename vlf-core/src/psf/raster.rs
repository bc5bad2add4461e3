//! Watertight rasterisation of convex polygons, and of outlines of polygon sets, onto a ray grid.
//!
//! A parallel subfield is an `N × N` grid of rays; ray `(i, j)` passes through
//! the cell centre `(i + ½, j + ½)` in *grid units*. A polygon covers a ray
//! when the centre lies inside its projection. Two polygons that share an edge
//! must cover every centre on that edge **exactly once** — otherwise light
//! leaks through the seam or is exchanged twice, and energy balance breaks.
//!
//! Floating-point edge functions are not antisymmetric (evaluating the shared
//! edge from either side may round differently), so vertices are snapped to a
//! fixed-point grid of [`SUBPIXELS`] steps per cell and every edge test is
//! done in exact integer arithmetic with the *top-left rule*: a centre exactly
//! on an edge belongs to the polygon for which that edge is a left edge
//! (`dy < 0` in counter-clockwise order) or a top edge (`dy = 0, dx < 0`).
//! The two polygons sharing an edge traverse it in opposite directions, so
//! exactly one of them owns the centres on it. Snapping moves a vertex by at
//! most 1/512 of a cell — far below the method's own discretisation.
//!
//! Polygons are convex (the importer guarantees it), so each row of the grid
//! meets a polygon in at most one span, found by solving the edge
//! inequalities for `i` rather than testing every cell.

use glam::DVec2;

/// Fixed-point steps per grid cell (a power of two, so snapping is exact).
pub const SUBPIXELS: i64 = 256;
const HALF: i64 = SUBPIXELS / 2;

/// One covered run of a row: rays `start..end` of row `row`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RowSpan {
    pub row: u32,
    pub start: u32,
    pub end: u32,
}

/// Snaps a grid-unit coordinate to fixed point. Coordinates are bounded by the
/// grid (the scene lies in the unit sphere), so `i64` never overflows: with
/// `N ≤ 65536`, products of two coordinate differences stay below 2⁵⁰.
fn snap(x: f64) -> i64 {
    let y = x * SUBPIXELS as f64;
    // `f64::round` is a library call on the baseline x86-64 target, and this runs for every
    // vertex of every polygon in every direction: for y ≥ 0 (grid coordinates of a scene inside
    // the unit sphere are, but within a lattice phase of the grid's low edges) round-half-up by
    // truncation instead, which is the same
    // integer but where y + ½ rounds up in floating point (within 2⁻⁵³ of a half step).
    if y >= 0.0 { (y + 0.5) as i64 } else { y.round() as i64 }
}

/// Whether a cell centre `k·S + S/2` lies in `[lo, hi]` (fixed point).
#[inline]
pub fn spans_a_centre(lo: i64, hi: i64) -> bool {
    first_centre_from(lo) <= last_centre_to(hi)
}

/// Index of the first cell centre at or above `x` (fixed point): `⌈(x − S/2) / S⌉`.
#[inline]
pub fn first_centre_from(x: i64) -> i64 {
    ceil_div(x - HALF, SUBPIXELS)
}

/// Index of the last cell centre at or below `x` (fixed point): `⌊(x − S/2) / S⌋`.
#[inline]
pub fn last_centre_to(x: i64) -> i64 {
    floor_div(x - HALF, SUBPIXELS)
}

#[inline]
fn floor_div(a: i64, b: i64) -> i64 {
    debug_assert!(b > 0);
    a.div_euclid(b)
}

#[inline]
fn ceil_div(a: i64, b: i64) -> i64 {
    -floor_div(-a, b)
}

/// A vertex in fixed point: grid units × [`SUBPIXELS`], rounded.
pub type Fixed = (i64, i64);

/// Snaps a grid-unit point to fixed point (the same for every polygon that has the vertex, so
/// shared edges stay shared).
pub fn snap_point(p: DVec2) -> Fixed {
    (snap(p.x), snap(p.y))
}

/// Calls `emit` for each row span of an `n × n` grid covered by the convex
/// polygon `points` (grid units, either winding). Returns the number of rays
/// covered. A polygon seen edge-on (zero projected area after snapping)
/// covers nothing.
pub fn rasterize_convex(points: &[DVec2], n: u32, emit: impl FnMut(RowSpan)) -> u64 {
    if points.len() < 3 {
        return 0;
    }
    // Most polygons are triangles and quads: snapped onto the stack.
    let mut stack = [(0i64, 0i64); 8];
    let mut heap = Vec::new();
    let p: &mut [Fixed] = if points.len() <= stack.len() {
        for (d, q) in stack.iter_mut().zip(points) {
            *d = snap_point(*q);
        }
        &mut stack[..points.len()]
    } else {
        heap.extend(points.iter().map(|&q| snap_point(q)));
        &mut heap[..]
    };
    rasterize_convex_fixed(p, n, emit)
}

/// [`rasterize_convex`] on snapped vertices (reordered in place to counter-clockwise).
pub fn rasterize_convex_fixed(p: &mut [Fixed], n: u32, mut emit: impl FnMut(RowSpan)) -> u64 {
    if p.len() < 3 {
        return 0;
    }
    // No cell centre inside the bounding box (a polygon smaller than a ray cell, the rule in
    // scanned meshes): nothing to cover.
    let (mut min_x, mut max_x) = (i64::MAX, i64::MIN);
    let (mut min_y, mut max_y) = (i64::MAX, i64::MIN);
    for q in p.iter() {
        min_x = min_x.min(q.0);
        max_x = max_x.max(q.0);
        min_y = min_y.min(q.1);
        max_y = max_y.max(q.1);
    }
    if !spans_a_centre(min_x, max_x) || !spans_a_centre(min_y, max_y) {
        return 0;
    }
    // Twice the signed area, exact.
    let area2 = twice_area(p);
    if area2 == 0 {
        return 0;
    }
    if area2 < 0 {
        p.reverse();
    }
    // A bounding box around one ray centre (the rule in a scan, whose polygons are smaller than
    // a ray cell): the polygon covers that centre or nothing, decided by its edge functions
    // there, with no division. The same centres as the rows' spans below, which solve the same
    // inequalities for the column (tested against them).
    let (col, row) = (ceil_div(min_x - HALF, SUBPIXELS), ceil_div(min_y - HALF, SUBPIXELS));
    if col == floor_div(max_x - HALF, SUBPIXELS) && row == floor_div(max_y - HALF, SUBPIXELS) {
        if !covers_centre(p, col, row, n) {
            return 0;
        }
        emit(RowSpan {
            row: row as u32,
            start: col as u32,
            end: col as u32 + 1,
        });
        return 1;
    }
    covered_rows(p, n, emit)
}

/// Twice the signed area of the snapped polygon `p` (positive counter-clockwise), exact.
fn twice_area(p: &[Fixed]) -> i128 {
    edges(p)
        .map(|(a, b)| a.0 as i128 * b.1 as i128 - b.0 as i128 * a.1 as i128)
        .sum()
}

/// The polygon's edges: the last corner to the first, then each corner to the next. (Not by
/// `p[(k + 1) % len]`: a division per edge, in the loop of every polygon that covers a centre.)
fn edges(p: &[Fixed]) -> impl Iterator<Item = (Fixed, Fixed)> + '_ {
    let mut previous = p.last().copied().unwrap_or_default();
    p.iter().map(move |&b| (std::mem::replace(&mut previous, b), b))
}

/// Whether the counter-clockwise convex polygon `p` covers the centre of ray `(col, row)` of an
/// `n × n` grid, by the top-left rule: inside every edge's half-plane,
/// `dx·(yc − ay) − dy·(xc − ax) − bias ≥ 0` (`bias` 1 where the edge does not own its centres).
fn covers_centre(p: &[Fixed], col: i64, row: i64, n: u32) -> bool {
    let n = n as i64;
    if !(0..n).contains(&col) || !(0..n).contains(&row) {
        return false;
    }
    let (xc, yc) = (col * SUBPIXELS + HALF, row * SUBPIXELS + HALF);
    edges(p).all(|(a, b)| {
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        // An edge of no length (two corners snapped together) bounds nothing.
        let top_left = dy < 0 || (dy == 0 && dx < 0);
        let bias = if top_left { 0 } else { 1 };
        (dx == 0 && dy == 0) || dx * (yc - a.1) - dy * (xc - a.0) - bias >= 0
    })
}

/// The row spans the counter-clockwise convex polygon `p` (of nonzero area, snapped) covers on
/// an `n × n` grid: each row's span solved from the edge inequalities.
fn covered_rows(p: &[Fixed], n: u32, mut emit: impl FnMut(RowSpan)) -> u64 {
    let (mut min_y, mut max_y) = (i64::MAX, i64::MIN);
    for q in p {
        min_y = min_y.min(q.1);
        max_y = max_y.max(q.1);
    }
    let n = n as i64;
    // Rows whose centre j·S + S/2 lies in [min_y, max_y].
    let row_lo = ceil_div(min_y - HALF, SUBPIXELS).max(0);
    let row_hi = floor_div(max_y - HALF, SUBPIXELS).min(n - 1);
    let mut covered = 0u64;
    for row in row_lo..=row_hi {
        let yc = row * SUBPIXELS + HALF;
        let (mut lo, mut hi) = (0i64, n - 1);
        for (a, b) in edges(p) {
            let (dx, dy) = (b.0 - a.0, b.1 - a.1);
            if dx == 0 && dy == 0 {
                // Two corners snapped together: an edge of no length bounds nothing.
                continue;
            }
            let top_left = dy < 0 || (dy == 0 && dx < 0);
            let bias = if top_left { 0 } else { 1 };
            // Inside: dx·(yc − ay) − dy·(x − ax) − bias ≥ 0.
            let c = dx * (yc - a.1);
            if dy == 0 {
                if c - bias < 0 {
                    hi = -1;
                    break;
                }
            } else if dy < 0 {
                let x_min = a.0 + ceil_div(bias - c, -dy);
                lo = lo.max(ceil_div(x_min - HALF, SUBPIXELS));
            } else {
                let x_max = a.0 + floor_div(c - bias, dy);
                hi = hi.min(floor_div(x_max - HALF, SUBPIXELS));
            }
        }
        if lo <= hi {
            covered += (hi - lo + 1) as u64;
            emit(RowSpan {
                row: row as u32,
                start: lo as u32,
                end: (hi + 1) as u32,
            });
        }
    }
    covered
}

/// One edge crossing a row: from column `col` on, the winding number changes by `wind`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Crossing {
    row: u32,
    col: u32,
    wind: i32,
}

/// Calls `emit` for each row span of an `n × n` grid covered by the region that the directed
/// `edges` (pairs of indices into `points`) enclose: the centres of nonzero winding number.
/// `edges` may form any number of closed loops (an outline with holes), in any order.
///
/// **Why it covers exactly what the polygons it outlines cover.** The top-left rule of
/// [`rasterize_convex`] decides a centre `c` on an edge as if it were sampled at
/// `c + (ε, −ε²)` for an infinitesimal ε: for an edge `(dx, dy)` of a counter-clockwise polygon
/// the sign of `dx·(−ε²) − dy·ε` is that of `−dy` when `dy ≠ 0` (left edges own their centres)
/// and of `−dx` when `dy = 0` (top edges do). That point lies on no edge, so it is inside a set
/// of polygons that tile a region exactly when its winding number about their edges is
/// nonzero, and an edge run both ways by two neighbours adds nothing to any winding number.
/// The same sample point decides here: an edge crosses row `yc − ε²` when `y_lo < yc ≤ y_hi`,
/// and lies left of `xc + ε` when its crossing `x(yc) ≤ xc` (exact integer arithmetic, as in
/// [`rasterize_convex`]). So the outline of a chart's polygons covers each ray centre exactly
/// when one of its polygons does, vertices and shared edges included (tested).
pub fn rasterize_outline(
    points: &[Fixed],
    edges: &[(u32, u32)],
    n: u32,
    crossings: &mut Vec<Crossing>,
    emit: impl FnMut(RowSpan),
) -> u64 {
    rasterize_outline_with(edges, |i| points[i as usize], n, crossings, emit)
}

/// [`rasterize_outline`] with the points given by `point(index)`.
pub fn rasterize_outline_with(
    edges: &[(u32, u32)],
    point: impl Fn(u32) -> Fixed,
    n: u32,
    crossings: &mut Vec<Crossing>,
    mut emit: impl FnMut(RowSpan),
) -> u64 {
    crossings.clear();
    let n = n as i64;
    for &(a, b) in edges {
        let (a, b) = (point(a), point(b));
        if a.1 == b.1 {
            continue; // horizontal: crosses no row at y − ε²
        }
        let (wind, lo, hi) = if b.1 > a.1 { (1, a, b) } else { (-1, b, a) };
        // Rows with lo.y < yc ≤ hi.y.
        let first = (floor_div(lo.1 - HALF, SUBPIXELS) + 1).max(0);
        let last = floor_div(hi.1 - HALF, SUBPIXELS).min(n - 1);
        let (ex, ey) = (hi.0 - lo.0, hi.1 - lo.1);
        for row in first..=last {
            let yc = row * SUBPIXELS + HALF;
            // First column whose centre xc satisfies xc ≥ x(yc) = lo.x + ex·(yc − lo.y)/ey.
            let x = lo.0 + ceil_div(ex * (yc - lo.1), ey);
            let col = ceil_div(x - HALF, SUBPIXELS).clamp(0, n);
            crossings.push(Crossing {
                row: row as u32,
                col: col as u32,
                wind,
            });
        }
    }
    crossings.sort_unstable();
    let mut covered = 0u64;
    let mut k = 0;
    while k < crossings.len() {
        let row = crossings[k].row;
        let (mut winding, mut open) = (0i32, None);
        while k < crossings.len() && crossings[k].row == row {
            let col = crossings[k].col;
            while k < crossings.len() && crossings[k].row == row && crossings[k].col == col {
                winding += crossings[k].wind;
                k += 1;
            }
            match open {
                None if winding != 0 => open = Some(col),
                Some(start) if winding == 0 => {
                    open = None;
                    if start < col {
                        covered += (col - start) as u64;
                        emit(RowSpan { row, start, end: col });
                    }
                }
                _ => {}
            }
        }
        // Closed loops leave every row at winding 0; an open outline is cut at the grid's edge.
        if let Some(start) = open
            && start < n as u32
        {
            covered += (n as u32 - start) as u64;
            emit(RowSpan {
                row,
                start,
                end: n as u32,
            });
        }
    }
    covered
}

#[cfg(test)]
mod tests {
    use super::*;

    fn splitmix(state: &mut u64) -> f64 {
        *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = *state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn coverage(polys: &[Vec<DVec2>], n: u32) -> Vec<u32> {
        let mut count = vec![0u32; (n * n) as usize];
        for poly in polys {
            rasterize_convex(poly, n, |s| {
                for i in s.start..s.end {
                    count[(s.row * n + i) as usize] += 1;
                }
            });
        }
        count
    }

    #[test]
    fn axis_aligned_square_covers_the_expected_centres() {
        let sq = vec![
            DVec2::new(2.0, 2.0),
            DVec2::new(6.0, 2.0),
            DVec2::new(6.0, 5.0),
            DVec2::new(2.0, 5.0),
        ];
        let c = coverage(&[sq], 8);
        // Centres 2.5..5.5 in x (4 of them) and 2.5..4.5 in y (3 rows).
        assert_eq!(c.iter().sum::<u32>(), 12);
        assert_eq!(c[(2 * 8 + 2) as usize], 1);
        assert_eq!(c[(5 * 8 + 2) as usize], 0);
    }

    /// Polygons smaller than a ray cell, decided at the one centre their bounding box holds,
    /// cover exactly what the rows' spans give: corners on centres, on cell edges, snapped
    /// together, at and past the grid's edges, both windings, triangles and quads.
    #[test]
    fn one_centre_is_decided_as_the_rows_decide_it() {
        let n = 6u32;
        let mut seed = 3u64;
        let (mut single, mut inside) = (0, 0);
        for trial in 0..40_000 {
            // Corners near a centre, within a cell: on the fixed-point lattice's quarter steps
            // every other trial (edges through centres and cell edges), anywhere otherwise.
            // The centre of cell (−1..8, −1..8): inside the grid and past its edges.
            let centre = DVec2::new((trial % 9) as f64 - 0.5, (trial / 9 % 9) as f64 - 0.5);
            let mut corner = || {
                let (u, v) = (splitmix(&mut seed) - 0.5, splitmix(&mut seed) - 0.5);
                let q = if trial % 2 == 0 {
                    DVec2::new((u * 4.0).round() / 4.0, (v * 4.0).round() / 4.0)
                } else {
                    DVec2::new(u, v) * 0.9
                };
                snap_point(centre + q)
            };
            let len = 3 + (trial / 64) % 2;
            let mut p: Vec<Fixed> = (0..len).map(|_| corner()).collect();
            if len == 4 {
                // A convex quad: its corners in angular order about their mean.
                let (mx, my) = (
                    p.iter().map(|q| q.0).sum::<i64>() as f64 / 4.0,
                    p.iter().map(|q| q.1).sum::<i64>() as f64 / 4.0,
                );
                p.sort_by(|a, b| {
                    ((a.1 as f64 - my).atan2(a.0 as f64 - mx)).total_cmp(&(b.1 as f64 - my).atan2(b.0 as f64 - mx))
                });
                let convex = (0..4).all(|k| {
                    let (a, b, c) = (p[k], p[(k + 1) % 4], p[(k + 2) % 4]);
                    (b.0 - a.0) * (c.1 - b.1) - (b.1 - a.1) * (c.0 - b.0) >= 0
                });
                if !convex {
                    continue;
                }
                if trial % 3 == 0 {
                    p.reverse();
                }
            }
            let mut fast = Vec::new();
            let covered = rasterize_convex_fixed(&mut p.clone(), n, |s| fast.push(s));
            let mut rows = Vec::new();
            let area2 = twice_area(&p);
            let slow = match area2 {
                0 => 0,
                _ => {
                    if area2 < 0 {
                        p.reverse();
                    }
                    covered_rows(&p, n, |s| rows.push(s))
                }
            };
            assert_eq!((covered, &fast), (slow, &rows), "trial {trial}: {p:?}");
            let (lo_x, hi_x) = (
                p.iter().map(|q| q.0).min().unwrap(),
                p.iter().map(|q| q.0).max().unwrap(),
            );
            let (lo_y, hi_y) = (
                p.iter().map(|q| q.1).min().unwrap(),
                p.iter().map(|q| q.1).max().unwrap(),
            );
            let one = |lo: i64, hi: i64| ceil_div(lo - HALF, SUBPIXELS) == floor_div(hi - HALF, SUBPIXELS);
            single += usize::from(one(lo_x, hi_x) && one(lo_y, hi_y));
            inside += covered as usize;
        }
        // The premise: many take the one-centre way, and of those both outcomes are common.
        assert!(
            single > 10_000 && inside > 3_000 && inside < single,
            "{single} single, {inside} covered"
        );
    }

    #[test]
    fn winding_does_not_matter_and_edge_on_covers_nothing() {
        let tri = vec![DVec2::new(0.3, 0.2), DVec2::new(7.1, 1.9), DVec2::new(3.3, 6.8)];
        let mut rev = tri.clone();
        rev.reverse();
        assert_eq!(coverage(&[tri], 8), coverage(&[rev], 8));
        let flat = vec![DVec2::new(0.5, 0.5), DVec2::new(3.5, 3.5), DVec2::new(7.5, 7.5)];
        assert_eq!(coverage(&[flat], 8).iter().sum::<u32>(), 0);
    }

    /// A jittered mesh of quads and triangles tiling a square: every centre
    /// inside the square is covered exactly once, even on shared edges and
    /// vertices that fall exactly on cell centres.
    #[test]
    fn shared_edges_are_watertight() {
        let n = 32u32;
        let mut seed = 7u64;
        for trial in 0..20 {
            let k = 6usize;
            let (x0, x1) = (3.0 + trial as f64 * 0.1, 28.5);
            let step = (x1 - x0) / k as f64;
            let mut grid = vec![vec![DVec2::ZERO; k + 1]; k + 1];
            for (a, row) in grid.iter_mut().enumerate() {
                for (b, p) in row.iter_mut().enumerate() {
                    let mut q = DVec2::new(x0 + a as f64 * step, x0 + b as f64 * step);
                    let interior = a > 0 && a < k && b > 0 && b < k;
                    if interior {
                        if trial % 3 == 0 {
                            // Snap onto cell centres: the hardest case for a fill rule.
                            q = (q - 0.5).round() + 0.5;
                        } else {
                            q += DVec2::new(splitmix(&mut seed) - 0.5, splitmix(&mut seed) - 0.5) * step * 0.3;
                        }
                    }
                    *p = q;
                }
            }
            let mut polys = Vec::new();
            for a in 0..k {
                for b in 0..k {
                    let (p00, p10, p11, p01) = (grid[a][b], grid[a + 1][b], grid[a + 1][b + 1], grid[a][b + 1]);
                    match (a + b + trial) % 3 {
                        0 => polys.push(vec![p00, p10, p11, p01]),
                        1 => {
                            polys.push(vec![p00, p10, p11]);
                            polys.push(vec![p00, p11, p01]);
                        }
                        _ => {
                            polys.push(vec![p10, p11, p01]);
                            polys.push(vec![p00, p10, p01]);
                        }
                    }
                }
            }
            let outer = vec![grid[0][0], grid[k][0], grid[k][k], grid[0][k]];
            let mesh = coverage(&polys, n);
            let whole = coverage(&[outer], n);
            assert!(mesh.iter().all(|&c| c <= 1), "a centre covered twice (trial {trial})");
            assert_eq!(mesh, whole, "mesh coverage differs from its outline (trial {trial})");
        }
    }

    fn outline_coverage(points: &[DVec2], edges: &[(u32, u32)], n: u32) -> Vec<u32> {
        let fixed: Vec<Fixed> = points.iter().map(|&p| snap_point(p)).collect();
        let mut count = vec![0u32; (n * n) as usize];
        let covered = rasterize_outline(&fixed, edges, n, &mut Vec::new(), |s| {
            for i in s.start..s.end {
                count[(s.row * n + i) as usize] += 1;
            }
        });
        assert_eq!(covered, count.iter().map(|&c| c as u64).sum::<u64>());
        count
    }

    /// A jittered triangle mesh over a region with a hole, vertices on cell centres and cell
    /// edges included, its outline running past the grid: the outline (the edges that no
    /// neighbour runs the other way), and equally all edges of all triangles, cover exactly
    /// the centres that the triangles cover one by one.
    #[test]
    fn an_outline_covers_what_its_polygons_cover() {
        let n = 24u32;
        let mut seed = 11u64;
        for trial in 0..40 {
            let k = 7usize;
            let (x0, x1) = (-2.0 + trial as f64 * 0.173, 20.5 + (trial % 5) as f64 * 2.0);
            let step = (x1 - x0) / k as f64;
            let index = |a: usize, b: usize| (a * (k + 1) + b) as u32;
            let mut points = Vec::new();
            for a in 0..=k {
                for b in 0..=k {
                    let mut q = DVec2::new(x0 + a as f64 * step, x0 + b as f64 * step * 0.8 + trial as f64 * 0.01);
                    match trial % 4 {
                        0 => q = (q - 0.5).round() + 0.5, // on centres
                        1 => q = q.round(),               // on cell corners
                        _ => q += DVec2::new(splitmix(&mut seed) - 0.5, splitmix(&mut seed) - 0.5) * step * 0.4,
                    }
                    points.push(q);
                }
            }
            let mut triangles: Vec<[u32; 3]> = Vec::new();
            for a in 0..k {
                for b in 0..k {
                    if (a, b) == (3, 3) || (a, b) == (3, 4) {
                        continue; // a hole
                    }
                    let (p00, p10, p11, p01) = (index(a, b), index(a + 1, b), index(a + 1, b + 1), index(a, b + 1));
                    if (a + b + trial) % 2 == 0 {
                        triangles.extend([[p00, p10, p11], [p00, p11, p01]]);
                    } else {
                        triangles.extend([[p10, p11, p01], [p00, p10, p01]]);
                    }
                }
            }
            let polys: Vec<Vec<DVec2>> = triangles
                .iter()
                .map(|t| t.iter().map(|&i| points[i as usize]).collect())
                .collect();
            let mesh = coverage(&polys, n);
            assert!(mesh.iter().all(|&c| c <= 1));
            let all: Vec<(u32, u32)> = triangles
                .iter()
                .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
                .collect();
            let outline: Vec<(u32, u32)> = all.iter().copied().filter(|&(a, b)| !all.contains(&(b, a))).collect();
            assert!(outline.len() < all.len() / 3);
            let mut scrambled = outline.clone();
            scrambled.reverse();
            for edges in [&all, &outline, &scrambled] {
                let covered = outline_coverage(&points, edges, n);
                assert!(covered.iter().all(|&c| c <= 1));
                assert_eq!(covered, mesh, "trial {trial}");
            }
        }
    }

    /// A convex polygon is its own outline, whichever way round.
    #[test]
    fn a_convex_polygon_is_its_own_outline() {
        let mut seed = 3u64;
        for _ in 0..200 {
            let c = DVec2::new(splitmix(&mut seed) * 16.0, splitmix(&mut seed) * 16.0);
            let r = 0.3 + splitmix(&mut seed) * 9.0;
            let corners = 3 + (splitmix(&mut seed) * 6.0) as usize;
            let mut angles: Vec<f64> = (0..corners)
                .map(|_| splitmix(&mut seed) * std::f64::consts::TAU)
                .collect();
            angles.sort_by(f64::total_cmp);
            let mut poly: Vec<DVec2> = angles.iter().map(|a| c + DVec2::new(a.cos(), a.sin()) * r).collect();
            if splitmix(&mut seed) < 0.5 {
                poly.reverse();
            }
            let edges: Vec<(u32, u32)> = (0..corners as u32).map(|i| (i, (i + 1) % corners as u32)).collect();
            assert_eq!(outline_coverage(&poly, &edges, 16), coverage(&[poly.clone()], 16));
        }
    }

    /// Two corners that snap onto one point leave the polygon whole (an edge of no length
    /// bounds nothing).
    #[test]
    fn corners_snapped_together_do_not_empty_a_polygon() {
        let quad = vec![
            DVec2::new(1.0, 1.0),
            DVec2::new(7.0, 1.0),
            DVec2::new(7.0, 6.0),
            DVec2::new(7.0 + 1e-6, 6.0),
            DVec2::new(1.0, 6.0),
        ];
        assert_eq!(coverage(&[quad], 8).iter().sum::<u32>(), 30);
    }
}
