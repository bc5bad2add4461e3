//! Non-planar ("bent") faces: triangulation on the face's own vertices.
//!
//! A face bent beyond the planarity tolerance has no single plane, and
//! flattening it would move its vertices off the edges it shares with its
//! neighbours. Split into triangles that use exactly its vertices instead,
//! each triangle is planar by construction and every shared edge stays
//! shared. The split is chosen in the projection onto the face's Newell
//! plane, where the face is a simple polygon (if it is not, the face is
//! refused): a quad along its shorter valid diagonal, which gives the
//! better-conditioned pair of triangles, anything larger by ear clipping.

use glam::{DVec2, DVec3};

use super::polygon::{Plane2d, PolygonError, REL_AREA_EPS, in_closed_triangle, orient, self_intersects};

/// Splits a (non-planar) polygon into triangles, as index triples into `v`,
/// each counter-clockwise about the polygon's Newell normal in projection
/// onto the Newell plane, together covering that projection.
///
/// Consecutive repeated vertices are dropped (that moves nothing); collinear
/// vertices in projection are kept (in 3-D they are not collinear), so a
/// triangle of the result may be degenerate in projection but not in 3-D;
/// one that is degenerate in 3-D is left for the caller to skip.
pub(crate) fn triangulate(v: &[DVec3]) -> Result<Vec<[usize; 3]>, PolygonError> {
    if v.iter().any(|p| !p.is_finite()) {
        return Err(PolygonError::NonFinite);
    }
    let plane = Plane2d::new(v).ok_or(PolygonError::Degenerate)?;
    let p = &plane.points;
    let mut ring: Vec<usize> = Vec::with_capacity(v.len());
    for i in 0..v.len() {
        if ring.last().is_none_or(|&j| v[j] != v[i]) {
            ring.push(i);
        }
    }
    while ring.len() > 1 && v[ring[0]] == v[ring[ring.len() - 1]] {
        ring.pop();
    }
    match ring.len() {
        0..3 => return Err(PolygonError::Degenerate),
        3 => return Ok(vec![[ring[0], ring[1], ring[2]]]),
        _ => {}
    }
    if self_intersects(&ring, p) {
        return Err(PolygonError::SelfIntersecting);
    }
    if ring.len() == 4
        && let Some(triangles) = split_quad([ring[0], ring[1], ring[2], ring[3]], v, p)
    {
        return Ok(triangles);
    }
    ear_clip(ring, p)
}

/// A quad `a b c d` split along `a c` or `b d`: the diagonal must leave two
/// triangles that are counter-clockwise in projection (a non-convex quad has
/// one such diagonal, through its reflex vertex); of two, the shorter one in
/// 3-D. `None` if neither does (flat vertices in projection).
fn split_quad([a, b, c, d]: [usize; 4], v: &[DVec3], p: &[DVec2]) -> Option<Vec<[usize; 3]>> {
    let ccw = |t: &[usize; 3]| orient(p[t[0]], p[t[1]], p[t[2]]) > REL_AREA_EPS;
    let ac = vec![[a, b, c], [a, c, d]];
    let bd = vec![[b, c, d], [b, d, a]];
    match (ac.iter().all(ccw), bd.iter().all(ccw)) {
        (true, true) if v[b].distance_squared(v[d]) < v[a].distance_squared(v[c]) => Some(bd),
        (true, _) => Some(ac),
        (false, true) => Some(bd),
        (false, false) => None,
    }
}

/// Ear clipping of a simple counter-clockwise ring that keeps every vertex:
/// a strictly convex ear with no other vertex in it if there is one, else
/// an ear that is flat in projection.
fn ear_clip(mut ring: Vec<usize>, p: &[DVec2]) -> Result<Vec<[usize; 3]>, PolygonError> {
    let mut triangles = Vec::with_capacity(ring.len() - 2);
    while ring.len() > 3 {
        let n = ring.len();
        let corners = |k: usize| (ring[(k + n - 1) % n], ring[k], ring[(k + 1) % n]);
        let is_ear = |k: usize, least: f64| {
            let (a, b, c) = corners(k);
            let (pa, pb, pc) = (p[a], p[b], p[c]);
            orient(pa, pb, pc) > least
                && !ring
                    .iter()
                    .any(|&q| q != a && q != b && q != c && in_closed_triangle(pa, pb, pc, p[q]))
        };
        let k = (0..n)
            .find(|&k| is_ear(k, REL_AREA_EPS))
            .or_else(|| (0..n).find(|&k| is_ear(k, -REL_AREA_EPS)))
            .ok_or(PolygonError::Triangulation)?;
        let (a, b, c) = corners(k);
        triangles.push([a, b, c]);
        ring.remove(k);
    }
    triangles.push([ring[0], ring[1], ring[2]]);
    Ok(triangles)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::newell_normal;

    fn corners(v: &[DVec3], triangles: &[[usize; 3]]) -> Vec<[DVec3; 3]> {
        triangles.iter().map(|t| t.map(|i| v[i])).collect()
    }

    /// Every triangle faces the polygon's front, and in projection they add
    /// up to the polygon's area.
    fn check_cover(v: &[DVec3], triangles: &[[usize; 3]]) {
        let n = newell_normal(v).normalize();
        let projected: f64 = corners(v, triangles)
            .iter()
            .map(|t| newell_normal(t).dot(n) / 2.0)
            .sum();
        let area = newell_normal(v).length() / 2.0;
        assert!(
            (projected - area).abs() < 1e-12 * area.max(1.0),
            "{projected} vs {area}"
        );
        for t in corners(v, triangles) {
            assert!(newell_normal(&t).dot(n) > 0.0, "{t:?} faces away from {n}");
        }
    }

    #[test]
    fn a_bent_quad_splits_along_its_shorter_diagonal() {
        // A rhombus, bent at its short diagonal (b d).
        let mut v = vec![
            DVec3::new(-2.0, 0.0, 0.0),
            DVec3::new(0.0, -1.0, 0.0),
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        ];
        v[0].z = 0.3;
        let t = triangulate(&v).unwrap();
        assert_eq!(t, vec![[1, 2, 3], [1, 3, 0]]);
        check_cover(&v, &t);
        // Rotated by one vertex, the same diagonal (now a c).
        let w: Vec<DVec3> = (0..4).map(|i| v[(i + 1) % 4]).collect();
        assert_eq!(triangulate(&w).unwrap(), vec![[0, 1, 2], [0, 2, 3]]);
    }

    #[test]
    fn a_non_convex_bent_quad_splits_at_its_reflex_vertex() {
        // A dart: vertex 2 is reflex, so only the diagonal 0 2 lies inside,
        // although 1 3 is shorter.
        let v = vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(4.0, -1.0, 0.2),
            DVec3::new(3.0, 0.0, 0.0),
            DVec3::new(4.0, 1.0, 0.2),
        ];
        assert!(v[1].distance(v[3]) < v[0].distance(v[2]));
        let t = triangulate(&v).unwrap();
        assert_eq!(t, vec![[0, 1, 2], [0, 2, 3]]);
        check_cover(&v, &t);
    }

    #[test]
    fn a_bent_l_shape_is_ear_clipped_on_its_own_vertices() {
        let flat = [(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (1.0, 1.0), (1.0, 2.0), (0.0, 2.0)];
        let v: Vec<DVec3> = flat
            .iter()
            .enumerate()
            .map(|(i, &(x, y))| DVec3::new(x, y, 0.1 * (i % 2) as f64))
            .collect();
        let t = triangulate(&v).unwrap();
        assert_eq!(t.len(), 4);
        check_cover(&v, &t);
        // A flat vertex in projection is kept, not dropped.
        let mut w = v.clone();
        w.insert(1, DVec3::new(1.0, 0.0, 0.3));
        let t = triangulate(&w).unwrap();
        assert_eq!(t.len(), 5);
        assert!(t.iter().flatten().any(|&i| i == 1));
        check_cover(&w, &t);
        // Repeated vertices are dropped.
        let mut r = v.clone();
        r.insert(3, v[2]);
        r.push(v[0]);
        let t = triangulate(&r).unwrap();
        assert_eq!(t.len(), 4);
        assert!(!t.iter().flatten().any(|&i| i == 3 || i == 7));
    }

    #[test]
    fn self_intersecting_and_degenerate_bent_polygons_are_refused() {
        let bow = vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(3.0, 3.0, 0.5),
            DVec3::new(3.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.5),
        ];
        assert_eq!(triangulate(&bow), Err(PolygonError::SelfIntersecting));
        let line = vec![DVec3::ZERO, DVec3::X, DVec3::X * 2.0, DVec3::X * 3.0];
        assert_eq!(triangulate(&line), Err(PolygonError::Degenerate));
        let nan = vec![DVec3::ZERO, DVec3::X, DVec3::NAN, DVec3::Y];
        assert_eq!(triangulate(&nan), Err(PolygonError::NonFinite));
    }
}
