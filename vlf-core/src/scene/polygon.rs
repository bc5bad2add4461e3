//! Planar polygon geometry: Newell normals, planarity, convexity and the
//! decomposition of a non-convex polygon into convex pieces.
//!
//! The VLF propagation rasterises every surface into the ray rows of each
//! parallel subfield and relies on a surface crossing a row in at most one
//! span; that holds for convex polygons only, hence [`convex_pieces`].
//!
//! All tests are done in a 2-D frame of the polygon's plane, translated to the
//! centroid and scaled by the diameter, so that every tolerance below is
//! *relative* (to the diameter for lengths, to the diameter² for areas) and
//! the result does not depend on the scene's units.

use glam::{DVec2, DVec3};

/// Relative tolerance for areas (twice a triangle's area over the polygon's
/// diameter²): a vertex whose removal changes the area by less than this is
/// collinear (or repeated), a polygon with less than this area is degenerate.
/// Well above the rounding of f64 (1e-16) and well below anything a modeller
/// would draw on purpose.
pub(crate) const REL_AREA_EPS: f64 = 1e-10;

/// Why a polygon cannot be split into convex pieces.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PolygonError {
    /// A coordinate is NaN or infinite (or the polygon's extent overflows).
    #[error("the polygon has non-finite coordinates")]
    NonFinite,
    /// Zero area: fewer than three vertices remain once repeated and
    /// collinear vertices are removed, or the remaining area is negligible.
    #[error("the polygon is degenerate: zero area once repeated and collinear vertices are removed")]
    Degenerate,
    /// Two edges that are not neighbours cross or touch: the polygon is not
    /// simple (holes joined by bridge edges are not supported either).
    #[error("the polygon is self-intersecting: two of its edges cross or touch")]
    SelfIntersecting,
    /// Ear clipping found no ear; only possible through rounding on nearly
    /// degenerate input.
    #[error("the polygon could not be split into convex pieces (ear clipping found no ear)")]
    Triangulation,
}

/// Newell's normal of a polygon: perpendicular to its (best-fit) plane,
/// pointing to the side from which the vertices run counter-clockwise, with
/// length twice the polygon's area (for a planar simple polygon).
///
/// Computed as `Σ (vᵢ - v₀) × (vᵢ₊₁ - v₀)`, which equals Newell's sum but
/// keeps full precision far from the origin. Fewer than three vertices give
/// zero.
pub fn newell_normal(v: &[DVec3]) -> DVec3 {
    if v.len() < 3 {
        return DVec3::ZERO;
    }
    let o = v[0];
    v.windows(2)
        .skip(1)
        .map(|w| (w[0] - o).cross(w[1] - o))
        .fold(DVec3::ZERO, |a, b| a + b)
}

/// Largest distance between two vertices (zero for fewer than two).
pub fn diameter(v: &[DVec3]) -> f64 {
    let mut d2: f64 = 0.0;
    for (i, a) in v.iter().enumerate() {
        for b in &v[i + 1..] {
            d2 = d2.max(a.distance_squared(*b));
        }
    }
    d2.sqrt()
}

/// Largest distance of a vertex from the polygon's Newell plane (the plane
/// through the vertex centroid perpendicular to [`newell_normal`]). Zero for
/// a polygon without a defined normal (degenerate).
pub fn planarity_deviation(v: &[DVec3]) -> f64 {
    let n = newell_normal(v).normalize_or_zero();
    if n == DVec3::ZERO {
        return 0.0;
    }
    let c = centroid(v);
    v.iter().map(|p| n.dot(*p - c).abs()).fold(0.0, f64::max)
}

/// Mean of the vertices.
pub(crate) fn centroid(v: &[DVec3]) -> DVec3 {
    if v.is_empty() {
        return DVec3::ZERO;
    }
    v.iter().fold(DVec3::ZERO, |a, b| a + *b) / v.len() as f64
}

/// Whether a planar polygon is strictly convex, counter-clockwise about its
/// Newell normal, and winds once (so a pentagram, all of whose turns are to
/// the left, is not convex). Collinear or repeated vertices make it fail.
/// Not used by the importer itself (which trusts [`convex_pieces`]); kept
/// for callers and tests that check the invariant of
/// [`Surface`](super::Surface).
#[allow(dead_code)] // public once re-exported from `scene`
pub fn is_convex(v: &[DVec3]) -> bool {
    match Plane2d::new(v) {
        Some(plane) => {
            let ring: Vec<usize> = (0..v.len()).collect();
            is_convex_2d(&ring, &plane.points)
        }
        None => false,
    }
}

/// Splits a planar polygon into convex pieces, each counter-clockwise about
/// the polygon's Newell normal and made of the input's own points (no new
/// vertices), whose union is the polygon.
///
/// Repeated consecutive vertices and collinear vertices are removed first.
/// A convex polygon comes back whole; a non-convex one is ear-clipped into
/// triangles that are then merged back greedily across their diagonals while
/// the union stays convex (Hertel–Mehlhorn), which gives few pieces (an
/// L-shape gives two quadrilaterals). The input should be planar (the
/// importer projects it onto its Newell plane first); the decomposition is
/// done in the projection onto that plane.
pub fn convex_pieces(v: &[DVec3]) -> Result<Vec<Vec<DVec3>>, PolygonError> {
    if v.iter().any(|p| !p.is_finite()) {
        return Err(PolygonError::NonFinite);
    }
    if v.len() < 3 {
        return Err(PolygonError::Degenerate);
    }
    let plane = Plane2d::new(v).ok_or(PolygonError::Degenerate)?;
    let p = &plane.points;

    let ring = remove_flat_vertices((0..v.len()).collect(), p);
    if ring.len() < 3 || signed_area2(&ring, p) <= REL_AREA_EPS {
        return Err(PolygonError::Degenerate);
    }
    let to_3d = |r: &[usize]| r.iter().map(|&i| v[i]).collect::<Vec<_>>();
    if is_convex_2d(&ring, p) {
        return Ok(vec![to_3d(&ring)]);
    }
    if self_intersects(&ring, p) {
        return Err(PolygonError::SelfIntersecting);
    }
    let (triangles, diagonals) = ear_clip(ring, p)?;
    let pieces = merge_convex(triangles, &diagonals, p);
    Ok(pieces.iter().map(|r| to_3d(r)).collect())
}

/// The polygon's vertices in an orthonormal frame `(u, w)` of its Newell
/// plane with `u × w = n`, so that counter-clockwise about `n` is
/// counter-clockwise in 2-D; centred on the centroid and scaled by the
/// diameter so that coordinates are of order one.
pub(super) struct Plane2d {
    pub(super) points: Vec<DVec2>,
}

impl Plane2d {
    pub(super) fn new(v: &[DVec3]) -> Option<Self> {
        let d = diameter(v);
        if !(d.is_finite() && d > 0.0) {
            return None;
        }
        let n = newell_normal(v);
        // |n| = 2 × area: relative to d², the same test as for flat vertices.
        if !n.is_finite() || n.length() <= REL_AREA_EPS * d * d {
            return None;
        }
        let n = n.normalize();
        let u = n.any_orthogonal_vector().normalize();
        let w = n.cross(u);
        let c = centroid(v);
        let points = v
            .iter()
            .map(|p| {
                let q = *p - c;
                DVec2::new(q.dot(u), q.dot(w)) / d
            })
            .collect();
        Some(Plane2d { points })
    }
}

/// Twice the signed area of the triangle `a b c` (positive if CCW).
/// Whether `q` lies inside or on the counter-clockwise triangle `a, b, c` (to the area
/// tolerance): what keeps an ear from being clipped over another vertex.
pub(super) fn in_closed_triangle(a: DVec2, b: DVec2, c: DVec2, q: DVec2) -> bool {
    orient(a, b, q) >= -REL_AREA_EPS && orient(b, c, q) >= -REL_AREA_EPS && orient(c, a, q) >= -REL_AREA_EPS
}

pub(super) fn orient(a: DVec2, b: DVec2, c: DVec2) -> f64 {
    (b - a).perp_dot(c - a)
}

/// Twice the signed area of a ring of point indices.
fn signed_area2(ring: &[usize], p: &[DVec2]) -> f64 {
    let n = ring.len();
    (0..n).map(|i| p[ring[i]].perp_dot(p[ring[(i + 1) % n]])).sum()
}

/// Removes, one at a time, vertices that are repeated or collinear with
/// their two current neighbours (including zero-width spikes), until none is
/// left or fewer than three vertices remain.
fn remove_flat_vertices(mut ring: Vec<usize>, p: &[DVec2]) -> Vec<usize> {
    loop {
        let n = ring.len();
        if n < 3 {
            return ring;
        }
        let flat = (0..n).find(|&i| {
            let a = p[ring[(i + n - 1) % n]];
            let b = p[ring[i]];
            let c = p[ring[(i + 1) % n]];
            orient(a, b, c).abs() <= REL_AREA_EPS
        });
        match flat {
            Some(i) => {
                ring.remove(i);
            }
            None => return ring,
        }
    }
}

/// Strictly convex, counter-clockwise, winding once.
fn is_convex_2d(ring: &[usize], p: &[DVec2]) -> bool {
    let n = ring.len();
    if n < 3 {
        return false;
    }
    let mut turning = 0.0;
    for i in 0..n {
        let a = p[ring[(i + n - 1) % n]];
        let b = p[ring[i]];
        let c = p[ring[(i + 1) % n]];
        let (e0, e1) = (b - a, c - b);
        let cross = e0.perp_dot(e1);
        if cross <= REL_AREA_EPS {
            return false;
        }
        turning += cross.atan2(e0.dot(e1));
    }
    // A convex polygon turns by 2π in all; a star polygon by 4π or more.
    (turning - std::f64::consts::TAU).abs() < 1.0
}

/// Whether two edges that are not neighbours in the ring cross or touch.
/// O(n²), run only on non-convex polygons.
pub(super) fn self_intersects(ring: &[usize], p: &[DVec2]) -> bool {
    let n = ring.len();
    for i in 0..n {
        let (a, b) = (p[ring[i]], p[ring[(i + 1) % n]]);
        // Edge j shares no vertex with edge i when j ∉ {i-1, i, i+1}.
        for j in i + 2..n {
            if i == 0 && j == n - 1 {
                continue;
            }
            let (c, d) = (p[ring[j]], p[ring[(j + 1) % n]]);
            if segments_touch(a, b, c, d) {
                return true;
            }
        }
    }
    false
}

/// Whether the closed segments `ab` and `cd` intersect, counting near-touches
/// (within the relative tolerance) as intersections.
fn segments_touch(a: DVec2, b: DVec2, c: DVec2, d: DVec2) -> bool {
    let sign = |x: f64| {
        if x > REL_AREA_EPS {
            1
        } else if x < -REL_AREA_EPS {
            -1
        } else {
            0
        }
    };
    let o1 = sign(orient(a, b, c));
    let o2 = sign(orient(a, b, d));
    let o3 = sign(orient(c, d, a));
    let o4 = sign(orient(c, d, b));
    if o1 * o2 < 0 && o3 * o4 < 0 {
        return true;
    }
    // Collinear cases: a point of one segment lying on the other.
    let on = |s: DVec2, e: DVec2, q: DVec2| {
        let len2 = (e - s).length_squared();
        if len2 == 0.0 {
            return (q - s).length_squared() <= REL_AREA_EPS * REL_AREA_EPS;
        }
        let t = (q - s).dot(e - s) / len2;
        let tol = REL_AREA_EPS / len2.sqrt();
        (-tol..=1.0 + tol).contains(&t)
    };
    (o1 == 0 && on(a, b, c)) || (o2 == 0 && on(a, b, d)) || (o3 == 0 && on(c, d, a)) || (o4 == 0 && on(c, d, b))
}

/// A polygon as indices into the 2-D points, counter-clockwise.
type Ring = Vec<usize>;
/// A directed edge between two point indices.
type Edge = (usize, usize);

/// Ear clipping of a simple counter-clockwise ring without flat vertices.
/// Returns the triangles and the diagonals cut (as directed edges of the
/// ear, `c → a`), in the order they were cut.
fn ear_clip(mut ring: Vec<usize>, p: &[DVec2]) -> Result<(Vec<Ring>, Vec<Edge>), PolygonError> {
    let mut triangles = Vec::with_capacity(ring.len().saturating_sub(2));
    let mut diagonals = Vec::new();
    while ring.len() > 3 {
        let n = ring.len();
        let ear = (0..n).find(|&k| {
            let (a, b, c) = (ring[(k + n - 1) % n], ring[k], ring[(k + 1) % n]);
            let (pa, pb, pc) = (p[a], p[b], p[c]);
            if orient(pa, pb, pc) <= REL_AREA_EPS {
                return false; // reflex (or flat): not an ear tip
            }
            // No other vertex inside or on the (closed) ear.
            !ring
                .iter()
                .any(|&q| q != a && q != b && q != c && in_closed_triangle(pa, pb, pc, p[q]))
        });
        let Some(k) = ear else {
            return Err(PolygonError::Triangulation);
        };
        let (a, b, c) = (ring[(k + n - 1) % n], ring[k], ring[(k + 1) % n]);
        triangles.push(vec![a, b, c]);
        diagonals.push((c, a));
        ring.remove(k);
        // Cutting an ear can leave a neighbour flat; its sliver has no area.
        ring = remove_flat_vertices(ring, p);
        if ring.len() < 3 {
            return Ok((triangles, diagonals));
        }
    }
    triangles.push(ring);
    Ok((triangles, diagonals))
}

/// Hertel–Mehlhorn: removes diagonals, in the order they were cut, whenever
/// the two pieces they separate form a convex polygon together.
fn merge_convex(triangles: Vec<Vec<usize>>, diagonals: &[(usize, usize)], p: &[DVec2]) -> Vec<Vec<usize>> {
    use std::collections::HashMap;
    let mut pieces: Vec<Option<Vec<usize>>> = triangles.into_iter().map(Some).collect();
    // Directed edge → index of the piece that has it.
    let mut owner: HashMap<(usize, usize), usize> = HashMap::new();
    for (id, piece) in pieces.iter().enumerate() {
        if let Some(r) = piece {
            for i in 0..r.len() {
                owner.insert((r[i], r[(i + 1) % r.len()]), id);
            }
        }
    }
    for &(x, y) in diagonals {
        let (Some(&pi), Some(&qi)) = (owner.get(&(x, y)), owner.get(&(y, x))) else {
            continue;
        };
        if pi == qi {
            continue;
        }
        let (Some(pr), Some(qr)) = (&pieces[pi], &pieces[qi]) else {
            continue;
        };
        let Some(merged) = join_rings(pr, qr, x, y) else {
            continue;
        };
        if !is_convex_2d(&merged, p) {
            continue;
        }
        owner.remove(&(x, y));
        owner.remove(&(y, x));
        for i in 0..merged.len() {
            owner.insert((merged[i], merged[(i + 1) % merged.len()]), pi);
        }
        pieces[pi] = Some(merged);
        pieces[qi] = None;
    }
    pieces.into_iter().flatten().collect()
}

/// Joins ring `pr` (which has the edge `x → y`) and ring `qr` (which has
/// `y → x`) along that edge.
fn join_rings(pr: &[usize], qr: &[usize], x: usize, y: usize) -> Option<Vec<usize>> {
    let (np, nq) = (pr.len(), qr.len());
    let i = (0..np).find(|&i| pr[i] == x && pr[(i + 1) % np] == y)?;
    let j = (0..nq).find(|&j| qr[j] == y && qr[(j + 1) % nq] == x)?;
    // pr from y round to x, then qr strictly between x and y.
    let mut merged: Vec<usize> = (0..np).map(|k| pr[(i + 1 + k) % np]).collect();
    merged.extend((1..nq - 1).map(|k| qr[(j + 1 + k) % nq]));
    Some(merged)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn area(v: &[DVec3]) -> f64 {
        newell_normal(v).length() / 2.0
    }

    fn xy(points: &[(f64, f64)]) -> Vec<DVec3> {
        points.iter().map(|&(x, y)| DVec3::new(x, y, 0.0)).collect()
    }

    /// Checks that `pieces` is a convex decomposition of `v`: every piece
    /// convex, same normal, made of input vertices, areas summing up.
    fn check_decomposition(v: &[DVec3], pieces: &[Vec<DVec3>]) {
        let n = newell_normal(v).normalize();
        let total: f64 = pieces.iter().map(|p| area(p)).sum();
        assert!((total - area(v)).abs() < 1e-9 * area(v), "areas {total} vs {}", area(v));
        for piece in pieces {
            assert!(is_convex(piece), "piece not convex: {piece:?}");
            assert!(newell_normal(piece).normalize().dot(n) > 1.0 - 1e-12);
            assert!(piece.iter().all(|q| v.contains(q)));
        }
    }

    #[test]
    fn newell_normal_is_twice_the_area_and_ccw() {
        let sq = xy(&[(0.0, 0.0), (2.0, 0.0), (2.0, 3.0), (0.0, 3.0)]);
        assert_eq!(newell_normal(&sq), DVec3::new(0.0, 0.0, 12.0));
        let rev: Vec<_> = sq.iter().rev().copied().collect();
        assert_eq!(newell_normal(&rev), DVec3::new(0.0, 0.0, -12.0));
        // Far from the origin: no cancellation.
        let far: Vec<_> = sq.iter().map(|p| *p + DVec3::splat(1e9)).collect();
        assert!((newell_normal(&far).z - 12.0).abs() < 1e-6);
        assert_eq!(newell_normal(&sq[..2]), DVec3::ZERO);
    }

    #[test]
    fn convex_polygon_is_kept_whole() {
        let hex: Vec<DVec3> = (0..6)
            .map(|k| {
                let t = k as f64 * std::f64::consts::TAU / 6.0;
                DVec3::new(t.cos(), 0.5, t.sin())
            })
            .collect();
        let pieces = convex_pieces(&hex).unwrap();
        assert_eq!(pieces, vec![hex]);
    }

    #[test]
    fn l_shape_splits_into_convex_pieces() {
        // An L in the plane x + y + z = 1 (tilted), CCW about (1,1,1).
        let flat = [(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (1.0, 1.0), (1.0, 2.0), (0.0, 2.0)];
        let n = DVec3::ONE.normalize();
        let u = DVec3::new(1.0, -1.0, 0.0).normalize();
        let w = n.cross(u);
        let l: Vec<DVec3> = flat
            .iter()
            .map(|&(a, b)| DVec3::splat(1.0 / 3.0) + a * u + b * w)
            .collect();
        assert!((area(&l) - 3.0).abs() < 1e-12);
        assert!(!is_convex(&l));
        let pieces = convex_pieces(&l).unwrap();
        assert_eq!(pieces.len(), 2, "{pieces:?}");
        check_decomposition(&l, &pieces);
    }

    #[test]
    fn comb_splits_into_convex_pieces() {
        // A comb with 5 teeth (many reflex vertices) and a collinear vertex
        // in its base.
        let mut pts = vec![(0.0, 0.0), (5.0, 0.0), (10.0, 0.0)];
        for k in 0..5 {
            let x = 10.0 - 2.0 * k as f64;
            pts.extend([(x, 3.0), (x - 1.0, 3.0), (x - 1.0, 1.0), (x - 2.0, 1.0)]);
        }
        let comb = xy(&pts);
        assert!((area(&comb) - 20.0).abs() < 1e-12);
        let pieces = convex_pieces(&comb).unwrap();
        check_decomposition(&comb, &pieces);
        // At least one piece per tooth plus the base.
        assert!(pieces.len() >= 6, "{}", pieces.len());
        assert!(pieces.iter().all(|p| !p.contains(&DVec3::new(5.0, 0.0, 0.0))));
    }

    #[test]
    fn random_star_shaped_polygons_decompose() {
        // Star-shaped about the origin, hence simple: random radii at sorted
        // random angles, in a random plane, far from the origin.
        let mut seed: u64 = 0x2545_f491_4f6c_dd1d;
        let mut rand = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..300 {
            let n = 3 + (rand() * 40.0) as usize;
            let mut angles: Vec<f64> = (0..n).map(|_| rand() * std::f64::consts::TAU).collect();
            angles.sort_by(f64::total_cmp);
            let normal = DVec3::new(rand() - 0.5, rand() - 0.5, rand() - 0.5).normalize();
            let u = normal.any_orthogonal_vector().normalize();
            let w = normal.cross(u);
            let origin = DVec3::new(rand(), rand(), rand()) * 1e3;
            let v: Vec<DVec3> = angles
                .iter()
                .map(|t| {
                    let r = 0.1 + rand();
                    origin + (u * t.cos() + w * t.sin()) * r * 7.0
                })
                .collect();
            match convex_pieces(&v) {
                Ok(pieces) => check_decomposition(&v, &pieces),
                // Sorted random angles can leave the origin outside (a gap
                // over π): such a polygon may self-intersect; a tiny area is
                // degenerate. Neither may be reported for a simple polygon
                // whose kernel holds the origin with margin.
                Err(e) => {
                    let max_gap = angles
                        .windows(2)
                        .map(|w| w[1] - w[0])
                        .chain([angles[0] + std::f64::consts::TAU - angles[n - 1]])
                        .fold(0.0, f64::max);
                    assert!(max_gap > 3.0, "{e:?} for a star-shaped polygon");
                }
            }
        }
    }

    #[test]
    fn repeated_and_collinear_vertices_are_removed() {
        let sq = xy(&[
            (0.0, 0.0),
            (0.0, 0.0),
            (1.0, 0.0),
            (2.0, 0.0),
            (2.0, 2.0),
            (0.0, 2.0),
            (0.0, 1.0),
            (0.0, 0.0),
        ]);
        let pieces = convex_pieces(&sq).unwrap();
        assert_eq!(pieces.len(), 1);
        assert_eq!(pieces[0].len(), 4);
        assert!((area(&pieces[0]) - 4.0).abs() < 1e-12);
    }

    #[test]
    fn degenerate_polygons_are_refused() {
        let line = xy(&[(0.0, 0.0), (1.0, 1.0), (2.0, 2.0)]);
        assert_eq!(convex_pieces(&line), Err(PolygonError::Degenerate));
        let point = xy(&[(1.0, 1.0), (1.0, 1.0), (1.0, 1.0), (1.0, 1.0)]);
        assert_eq!(convex_pieces(&point), Err(PolygonError::Degenerate));
        let two = xy(&[(0.0, 0.0), (1.0, 0.0)]);
        assert_eq!(convex_pieces(&two), Err(PolygonError::Degenerate));
        assert_eq!(convex_pieces(&[]), Err(PolygonError::Degenerate));
        let nan = xy(&[(0.0, 0.0), (f64::NAN, 0.0), (1.0, 1.0)]);
        assert_eq!(convex_pieces(&nan), Err(PolygonError::NonFinite));
        let inf = xy(&[(0.0, 0.0), (f64::MAX, 0.0), (-f64::MAX, 1.0)]);
        assert!(convex_pieces(&inf).is_err());
    }

    #[test]
    fn self_intersecting_polygons_are_refused() {
        // Bow tie with unequal lobes (non-zero net area).
        let bow = xy(&[(0.0, 0.0), (3.0, 3.0), (3.0, 0.0), (0.0, 1.0)]);
        assert_eq!(convex_pieces(&bow), Err(PolygonError::SelfIntersecting));
        // Pentagram: every turn to the left, but it winds twice.
        let star: Vec<DVec3> = (0..5)
            .map(|k| {
                let t = k as f64 * 2.0 * std::f64::consts::TAU / 5.0;
                DVec3::new(t.cos(), t.sin(), 0.0)
            })
            .collect();
        assert!(!is_convex(&star));
        assert_eq!(convex_pieces(&star), Err(PolygonError::SelfIntersecting));
        // A vertex touching a non-adjacent edge.
        let touch = xy(&[(0.0, 0.0), (4.0, 0.0), (4.0, 4.0), (2.0, 0.0), (0.0, 4.0)]);
        assert_eq!(convex_pieces(&touch), Err(PolygonError::SelfIntersecting));
    }

    #[test]
    fn planarity_and_diameter() {
        let sq = xy(&[(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]);
        assert_eq!(planarity_deviation(&sq), 0.0);
        assert!((diameter(&sq) - 8f64.sqrt()).abs() < 1e-15);
        let mut bent = sq.clone();
        bent[2].z = 0.4;
        // Newell plane through the centroid: deviations ±0.1 on all four.
        assert!((planarity_deviation(&bent) - 0.1).abs() < 1e-3);
    }
}
