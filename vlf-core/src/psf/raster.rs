//! Watertight rasterisation of convex polygons onto a ray grid.
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
    // the unit sphere always are) round-half-up by truncation instead, which is the same
    // integer but where y + ½ rounds up in floating point (within 2⁻⁵³ of a half step).
    if y >= 0.0 { (y + 0.5) as i64 } else { y.round() as i64 }
}

fn floor_div(a: i64, b: i64) -> i64 {
    debug_assert!(b > 0);
    a.div_euclid(b)
}

fn ceil_div(a: i64, b: i64) -> i64 {
    -floor_div(-a, b)
}

/// Calls `emit` for each row span of an `n × n` grid covered by the convex
/// polygon `points` (grid units, either winding). Returns the number of rays
/// covered. A polygon seen edge-on (zero projected area after snapping)
/// covers nothing.
pub fn rasterize_convex(points: &[DVec2], n: u32, mut emit: impl FnMut(RowSpan)) -> u64 {
    if points.len() < 3 {
        return 0;
    }
    // Most polygons are triangles and quads: snapped onto the stack.
    let mut stack = [(0i64, 0i64); 8];
    let mut heap = Vec::new();
    let p: &mut [(i64, i64)] = if points.len() <= stack.len() {
        for (d, q) in stack.iter_mut().zip(points) {
            *d = (snap(q.x), snap(q.y));
        }
        &mut stack[..points.len()]
    } else {
        heap.extend(points.iter().map(|q| (snap(q.x), snap(q.y))));
        &mut heap[..]
    };
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
    if ceil_div(min_x - HALF, SUBPIXELS) > floor_div(max_x - HALF, SUBPIXELS)
        || ceil_div(min_y - HALF, SUBPIXELS) > floor_div(max_y - HALF, SUBPIXELS)
    {
        return 0;
    }
    // Twice the signed area, exact.
    let area2: i128 = (0..p.len())
        .map(|k| {
            let (a, b) = (p[k], p[(k + 1) % p.len()]);
            a.0 as i128 * b.1 as i128 - b.0 as i128 * a.1 as i128
        })
        .sum();
    if area2 == 0 {
        return 0;
    }
    if area2 < 0 {
        p.reverse();
    }
    let n = n as i64;
    // Rows whose centre j·S + S/2 lies in [min_y, max_y].
    let row_lo = ceil_div(min_y - HALF, SUBPIXELS).max(0);
    let row_hi = floor_div(max_y - HALF, SUBPIXELS).min(n - 1);
    let mut covered = 0u64;
    for row in row_lo..=row_hi {
        let yc = row * SUBPIXELS + HALF;
        let (mut lo, mut hi) = (0i64, n - 1);
        for k in 0..p.len() {
            let (a, b) = (p[k], p[(k + 1) % p.len()]);
            let (dx, dy) = (b.0 - a.0, b.1 - a.1);
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
}
