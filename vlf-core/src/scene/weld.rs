//! T-junctions: a vertex of one polygon lying inside an edge of another.
//!
//! CAD exports are full of them: a wall given as one quad meets two quads of the next wall
//! whose shared corner lies halfway along the first wall's edge. Mathematically the two sides
//! cover the same line, but the rasteriser ([`crate::psf::raster`]) is watertight only across
//! edges whose endpoints are the *same* vertices: it snaps every vertex to a fixed-point grid,
//! and the snapped T vertex falls a fraction of a sub-pixel off the snapped long edge, leaving
//! a sliver that some rays pass through — light leaking out of a closed room.
//!
//! The fix is to make every edge shared exactly: a polygon with T vertices on its edges is
//! replaced by a fan of triangles from its centroid to its boundary with the T vertices
//! inserted in order. Every triangle is convex whatever the snapping does (unlike the polygon
//! with collinear vertices inserted, which snapping can make reflex), its boundary edges are
//! exactly the neighbours' edges, and its inner edges are shared within the fan. The texels do
//! not care: the fan is in the polygon's chart ([`crate::maps::charts`]).

use super::{Surface, VERTEX_QUANTUM, vertex_key};
use glam::DVec3;
use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

/// A vertex lies on an edge when its distance to the edge's line is below this fraction of the
/// edge's length, and strictly between its endpoints (by more than it).
const ON_EDGE: f64 = 1e-7;

/// Splits every surface that has T vertices on its edges (see the module docs). Returns the
/// surfaces (in order, a split surface's fan in its place) and how many were split.
pub fn split_t_junctions(surfaces: Vec<Surface>) -> (Vec<Surface>, usize) {
    if surfaces.is_empty() {
        return (surfaces, 0);
    }
    // A uniform grid of cells holding the distinct vertices, cell edge ~ the median edge length.
    let mut lengths: Vec<f64> = surfaces
        .iter()
        .flat_map(|s| (0..s.vertices.len()).map(|i| (s.vertices[(i + 1) % s.vertices.len()] - s.vertices[i]).length()))
        .filter(|l| *l > 0.0)
        .collect();
    if lengths.is_empty() {
        return (surfaces, 0);
    }
    let mid = lengths.len() / 2;
    let cell = lengths.select_nth_unstable_by(mid, f64::total_cmp).1.max(1e-9);
    let key = |p: DVec3| {
        let q = (p / cell).floor();
        (q.x as i64, q.y as i64, q.z as i64)
    };
    // Vertices closer than a quantum are one vertex (the same corner computed twice rounds a
    // few ulps apart): the first one met stands for them.
    let mut seen = HashSet::default();
    let mut grid: HashMap<(i64, i64, i64), Vec<DVec3>> = HashMap::default();
    for s in &surfaces {
        for &p in &s.vertices {
            if seen.insert(vertex_key(p)) {
                grid.entry(key(p)).or_default().push(p);
            }
        }
    }

    let mut out = Vec::with_capacity(surfaces.len());
    let mut split = 0;
    for s in surfaces {
        let n = s.vertices.len();
        let mut ring: Vec<DVec3> = Vec::with_capacity(n);
        let mut found = false;
        for i in 0..n {
            let (a, b) = (s.vertices[i], s.vertices[(i + 1) % n]);
            ring.push(a);
            let on_edge = vertices_on_edge(&grid, cell, a, b);
            found |= !on_edge.is_empty();
            ring.extend(on_edge);
        }
        if !found {
            out.push(s);
            continue;
        }
        split += 1;
        let centre = s.vertices.iter().fold(DVec3::ZERO, |acc, p| acc + *p) / n as f64;
        for i in 0..ring.len() {
            let vertices = vec![centre, ring[i], ring[(i + 1) % ring.len()]];
            let area = (vertices[1] - vertices[0]).cross(vertices[2] - vertices[0]).length() / 2.0;
            out.push(Surface {
                vertices,
                area,
                ..s.clone()
            });
        }
    }
    (out, split)
}

/// The vertices of `grid` strictly inside segment `a → b`, in order from `a`.
fn vertices_on_edge(grid: &HashMap<(i64, i64, i64), Vec<DVec3>>, cell: f64, a: DVec3, b: DVec3) -> Vec<DVec3> {
    let d = b - a;
    let len2 = d.length_squared();
    if len2 == 0.0 {
        return Vec::new();
    }
    let len = len2.sqrt();
    let tol = ON_EDGE * len;
    let lo = (a.min(b) - DVec3::splat(tol)) / cell;
    let hi = (a.max(b) + DVec3::splat(tol)) / cell;
    let (lo, hi) = (lo.floor(), hi.floor());
    // Walk the cells of the edge's bounding box (edges are about a cell long, so a few).
    let volume = (hi - lo + DVec3::ONE).element_product();
    let mut hits: Vec<(f64, DVec3)> = Vec::new();
    let mut test = |p: DVec3| {
        let t = (p - a).dot(d) / len2;
        if t * len <= tol.max(4.0 * VERTEX_QUANTUM) || (1.0 - t) * len <= tol.max(4.0 * VERTEX_QUANTUM) {
            return;
        }
        if (a + d * t - p).length() <= tol {
            hits.push((t, p));
        }
    };
    if volume <= 4096.0 {
        for x in lo.x as i64..=hi.x as i64 {
            for y in lo.y as i64..=hi.y as i64 {
                for z in lo.z as i64..=hi.z as i64 {
                    if let Some(list) = grid.get(&(x, y, z)) {
                        list.iter().for_each(|&p| test(p));
                    }
                }
            }
        }
    } else {
        // A long diagonal edge: step along it instead, a cell at a time.
        let steps = (len / cell).ceil() as i64 + 1;
        let mut seen = HashSet::default();
        for k in 0..=steps {
            let c = a + d * (k as f64 / steps as f64);
            let q = (c / cell).floor();
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let cell_key = (q.x as i64 + dx, q.y as i64 + dy, q.z as i64 + dz);
                        if seen.insert(cell_key)
                            && let Some(list) = grid.get(&cell_key)
                        {
                            list.iter().for_each(|&p| test(p));
                        }
                    }
                }
            }
        }
    }
    hits.sort_by(|x, y| x.0.total_cmp(&y.0));
    hits.dedup_by(|x, y| x.1 == y.1);
    hits.into_iter().map(|(_, p)| p).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::FaceOrigin;

    fn quad(v: [DVec3; 4]) -> Surface {
        let n = (v[1] - v[0]).cross(v[2] - v[0]).normalize();
        Surface {
            vertices: v.to_vec(),
            normal: n,
            offset: n.dot(v[0]),
            area: (v[1] - v[0]).cross(v[3] - v[0]).length(),
            material: 0,
            origin: FaceOrigin { line: 0, face: 0 },
            uv: None,
        }
    }

    #[test]
    fn a_t_vertex_splits_the_long_edge_and_nothing_else() {
        let p = |x: f64, y: f64| DVec3::new(x, y, 0.0);
        // A below y = 0 spans x ∈ [0, 2]; B and C above, meeting at (1, 0).
        let a = quad([p(0.0, -1.0), p(2.0, -1.0), p(2.0, 0.0), p(0.0, 0.0)]);
        let b = quad([p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)]);
        let c = quad([p(1.0, 0.0), p(2.0, 0.0), p(2.0, 1.0), p(1.0, 1.0)]);
        let area: f64 = [&a, &b, &c].iter().map(|s| s.area).sum();
        let (out, split) = split_t_junctions(vec![a, b.clone(), c.clone()]);
        assert_eq!(split, 1);
        // A became a fan of 5 triangles (4 corners + the T vertex); B and C are untouched.
        assert_eq!(out.len(), 7);
        assert_eq!(out[5], b);
        assert_eq!(out[6], c);
        let fan_area: f64 = out[..5].iter().map(|s| s.area).sum();
        assert!((fan_area + 2.0 - area).abs() < 1e-12);
        // The edge (1,0)–(0,0) and (2,0)–(1,0) are edges of the fan now, exactly.
        let has_edge = |x: DVec3, y: DVec3| {
            out[..5]
                .iter()
                .any(|s| (0..3).any(|i| s.vertices[i] == x && s.vertices[(i + 1) % 3] == y))
        };
        assert!(has_edge(p(2.0, 0.0), p(1.0, 0.0)));
        assert!(has_edge(p(1.0, 0.0), p(0.0, 0.0)));
        for s in &out[..5] {
            assert!(s.area > 0.0);
            assert_eq!(s.normal, out[0].normal);
        }
    }

    #[test]
    fn a_mesh_without_t_junctions_is_left_alone() {
        let p = |x: f64, y: f64| DVec3::new(x, y, 0.3);
        let a = quad([p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)]);
        let b = quad([p(1.0, 0.0), p(2.0, 0.0), p(2.0, 1.0), p(1.0, 1.0)]);
        let (out, split) = split_t_junctions(vec![a.clone(), b.clone()]);
        assert_eq!(split, 0);
        assert_eq!(out, vec![a, b]);
    }
}
