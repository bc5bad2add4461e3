//! Charts: which surfaces share one texel grid.
//!
//! A modeller may give a wall as one quad or as 3 200 triangles; a scanner gives a statue as
//! 10⁵ triangles of a few rays each. If every polygon had a texel grid of its own, a small
//! polygon's texels would be crossed by a handful of rays, their discrete areas `T_t` (see
//! [`crate::propagate`]) would be noise, and radiosity `Φ_t / T_t` with them: the field would
//! depend on the tessellation. So texels belong to a **chart**, a connected set of surfaces of
//! one material parameterised by one plane, and a texel's discrete area adds up the rays of
//! every surface of its chart that cross it. Polygon edges inside a chart leave no trace.
//!
//! Two kinds of charts come out of one mechanism:
//!
//! * **planar**: coplanar surfaces of one material that share an edge are merged — a wall
//!   however it is split is one chart, whose grid is laid out from
//!   the outline of the whole wall (its minimum-area bounding rectangle), so the texels do not
//!   depend on how the wall was cut either. An edge that another surface stands on (a
//!   partition on the line where two floor polygons meet) is not crossed: a texel straddling
//!   it would take light on one side and give it back on the other (radiosity's classic leak).
//!   Where a partition stands across the middle of a single polygon that leak remains, as it
//!   did with one grid per polygon;
//! * **curved**: planar groups are then grown into charts across shared edges, breadth first
//!   from the largest, while a group's normal stays within [`CURVED_CHART_ANGLE_DEG`] of the
//!   seed's and its projection onto the seed's plane does not land on texel centres the chart
//!   already covers (no fold-over: one texel never mixes two layers of a surface). Projected
//!   onto the seed's plane, a texel of a surface tilted by θ covers `1/cos θ` more area
//!   (at most 15 % at 30°); its discrete area is measured by the rays it is crossed by, so this
//!   changes its resolution, not the energy balance. A group left alone by the growth with a
//!   few texels' area (a triangle between charts) joins the closest neighbouring chart up to
//!   [`LEFTOVER_ANGLE_DEG`]: a chart of a few texels is crossed by few rays, and noisy.
//!
//! Mirrors only merge with coplanar mirrors: their light is directional and their look-ups
//! are per ray; a texel grid is all they need it for.
//!
//! Everything here is a deterministic function of the scene (and the texel size, for the
//! fold-over test): hashing (`FxHash`, fast on a scan's millions of vertex keys) is used for
//! look-ups only, every order is by surface index or by area with index as tie-break, so charts
//! are bit-identical on every machine and thread count.

use crate::scene::{Scene, vertex_key};
use glam::{DVec2, DVec3};
use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

/// Largest angle between a surface's normal and its curved chart's normal, in degrees.
pub const CURVED_CHART_ANGLE_DEG: f64 = 30.0;

/// A chart left with one group of at most this many texels' area joins a neighbour within
/// [`LEFTOVER_ANGLE_DEG`].
const LEFTOVER_TEXELS: f64 = 32.0;
/// Largest angle between a leftover group's normal and the chart it joins, in degrees.
pub const LEFTOVER_ANGLE_DEG: f64 = 45.0;

/// Coplanarity: `1 − n_a·n_b` below this and plane offsets within [`PLANE_OFFSET_TOLERANCE`]
/// (the VLF frame spans 2; importers flatten faces onto their own Newell planes, so coplanar
/// faces agree to rounding).
const PLANE_NORMAL_TOLERANCE: f64 = 1e-9;
const PLANE_OFFSET_TOLERANCE: f64 = 1e-9;

/// One chart: its surfaces and the normal of the plane it is parameterised on.
#[derive(Clone, Debug, PartialEq)]
pub struct Chart {
    /// Surface indices, ascending.
    pub surfaces: Vec<u32>,
    /// Unit normal of the parameterisation plane (a planar chart's own normal).
    pub normal: DVec3,
    /// A point on that plane.
    pub point: DVec3,
    pub material: usize,
}

/// Cuts the scene's surfaces into charts (see the module docs). `texel` is the texel edge used
/// by the fold-over test. Charts come in order of their smallest surface index.
pub fn segment(scene: &Scene, texel: f64) -> Vec<Chart> {
    segment_with_planes(scene, texel).0
}

/// [`segment`], and for every surface the surface that stands for its plane in the subfields
/// ([`crate::psf::Subfield::build`]): the first surface of its planar group (coplanar
/// neighbours of one material, which share a chart and a plane, so a ray crossing any of them is
/// the same hit). A mirror's too: its slots are per plane, as its exchange is
/// ([`crate::propagate::specular`]).
pub fn segment_with_planes(scene: &Scene, texel: f64) -> (Vec<Chart>, Vec<u32>) {
    let count = scene.surfaces.len();
    let keys: Vec<Vec<[i64; 3]>> = scene
        .surfaces
        .iter()
        .map(|s| s.vertices.iter().map(|&p| vertex_key(p)).collect())
        .collect();

    // Surfaces by vertex, and by edge.
    let mut by_vertex: HashMap<[i64; 3], Vec<u32>> = HashMap::default();
    let mut by_edge: HashMap<([i64; 3], [i64; 3]), Vec<u32>> = HashMap::default();
    for (s, ks) in keys.iter().enumerate() {
        for (i, k) in ks.iter().enumerate() {
            let list = by_vertex.entry(*k).or_default();
            if list.last() != Some(&(s as u32)) {
                list.push(s as u32);
            }
            let next = ks[(i + 1) % ks.len()];
            if *k != next {
                let edge = if *k < next { (*k, next) } else { (next, *k) };
                by_edge.entry(edge).or_default().push(s as u32);
            }
        }
    }
    let coplanar = |a: usize, b: usize| {
        let (sa, sb) = (&scene.surfaces[a], &scene.surfaces[b]);
        sa.material == sb.material
            && 1.0 - sa.normal.dot(sb.normal) <= PLANE_NORMAL_TOLERANCE
            && (sa.offset - sb.offset).abs() <= PLANE_OFFSET_TOLERANCE
    };
    // Neighbours across manifold edges (exactly two surfaces) that no other surface stands on:
    // a partition standing on the line where two floor polygons meet keeps them apart, or a
    // texel straddling the line would take light on one side and give it back on the other.
    let mut pairs: Vec<(u32, u32)> = Vec::new();
    for (&(p, q), list) in &by_edge {
        if let [a, b] = list[..]
            && !stands_on(scene, &keys, &by_vertex, (p, q), a, b)
        {
            pairs.push((a.min(b), a.max(b)));
        }
    }
    pairs.sort_unstable();
    pairs.dedup();

    // 1. Planar groups: union of coplanar, same-material neighbours.
    let mut sets = UnionFind::new(count);
    for &(a, b) in &pairs {
        if coplanar(a as usize, b as usize) {
            sets.union(a as usize, b as usize);
        }
    }
    // Groups numbered by their smallest surface.
    let mut group_of = vec![u32::MAX; count];
    let mut groups: Vec<Vec<u32>> = Vec::new();
    let mut root_group: HashMap<usize, u32> = HashMap::default();
    for (s, group) in group_of.iter_mut().enumerate() {
        let root = sets.find(s);
        let g = *root_group.entry(root).or_insert_with(|| {
            groups.push(Vec::new());
            (groups.len() - 1) as u32
        });
        groups[g as usize].push(s as u32);
        *group = g;
    }

    // 2. Group adjacency across the same edges (curved growth).
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); groups.len()];
    for &(a, b) in &pairs {
        let (ga, gb) = (group_of[a as usize], group_of[b as usize]);
        if ga != gb {
            neighbours[ga as usize].push(gb);
            neighbours[gb as usize].push(ga);
        }
    }
    for n in &mut neighbours {
        n.sort_unstable();
        n.dedup();
    }

    // 3. Grow charts from the largest groups down.
    let area = |g: &Vec<u32>| g.iter().map(|&s| scene.surfaces[s as usize].area).sum::<f64>();
    let areas: Vec<f64> = groups.iter().map(area).collect();
    let mut seeds: Vec<u32> = (0..groups.len() as u32).collect();
    seeds.sort_by(|&a, &b| areas[b as usize].total_cmp(&areas[a as usize]).then(a.cmp(&b)));
    let cos_max = CURVED_CHART_ANGLE_DEG.to_radians().cos();
    let mut chart_of_group = vec![u32::MAX; groups.len()];
    struct Growing {
        seed: u32,
        normal: DVec3,
        material: usize,
        groups: Vec<u32>,
        claimed: HashSet<(i64, i64)>,
    }
    let mut growing: Vec<Growing> = Vec::new();
    for seed in seeds {
        if chart_of_group[seed as usize] != u32::MAX {
            continue;
        }
        let c = growing.len() as u32;
        chart_of_group[seed as usize] = c;
        let first = groups[seed as usize][0] as usize;
        let normal = scene.surfaces[first].normal;
        let material = scene.surfaces[first].material;
        let mut chart = Growing {
            seed,
            normal,
            material,
            groups: vec![seed],
            claimed: HashSet::default(),
        };
        if !scene.materials[material].is_mirror() {
            let frame = crate::psf::PsfFrame::new(normal);
            chart
                .claimed
                .extend(cells_of(scene, &groups[seed as usize], &frame, texel));
            let mut tried: HashSet<u32> = HashSet::default();
            let mut queue = std::collections::VecDeque::from([seed]);
            while let Some(g) = queue.pop_front() {
                for &h in &neighbours[g as usize] {
                    if chart_of_group[h as usize] != u32::MAX || !tried.insert(h) {
                        continue;
                    }
                    let hs = &groups[h as usize];
                    let s0 = &scene.surfaces[hs[0] as usize];
                    if s0.material != material || s0.normal.dot(normal) < cos_max {
                        continue;
                    }
                    let cells = cells_of(scene, hs, &frame, texel);
                    if cells.iter().any(|c| chart.claimed.contains(c)) {
                        continue; // it would fold over the chart
                    }
                    chart.claimed.extend(cells);
                    chart_of_group[h as usize] = c;
                    chart.groups.push(h);
                    queue.push_back(h);
                }
            }
        }
        growing.push(chart);
    }

    // 4. Leftovers: a chart of one small group (a few texels: its texels would be crossed by
    // few rays, and noisy) joins the neighbouring chart whose normal is closest, up to
    // [`LEFTOVER_ANGLE_DEG`], if it does not fold over it.
    let cos_leftover = LEFTOVER_ANGLE_DEG.to_radians().cos();
    for c in 0..growing.len() {
        let chart = &growing[c];
        if chart.groups.len() != 1 || scene.materials[chart.material].is_mirror() {
            continue;
        }
        let g = chart.seed;
        if areas[g as usize] > LEFTOVER_TEXELS * texel * texel {
            continue;
        }
        let normal = scene.surfaces[groups[g as usize][0] as usize].normal;
        let mut best: Option<(f64, u32)> = None;
        for &h in &neighbours[g as usize] {
            let d = chart_of_group[h as usize];
            let other = &growing[d as usize];
            if d as usize == c || other.material != chart.material || other.groups.is_empty() {
                continue;
            }
            let dot = other.normal.dot(normal);
            if dot >= cos_leftover && best.is_none_or(|(b, e)| dot > b || (dot == b && d < e)) {
                best = Some((dot, d));
            }
        }
        let Some((_, d)) = best else { continue };
        let frame = crate::psf::PsfFrame::new(growing[d as usize].normal);
        let cells = cells_of(scene, &groups[g as usize], &frame, texel);
        if cells.iter().any(|x| growing[d as usize].claimed.contains(x)) {
            continue;
        }
        growing[d as usize].claimed.extend(cells);
        growing[d as usize].groups.push(g);
        growing[c].groups.clear();
        chart_of_group[g as usize] = d;
    }

    let mut charts: Vec<Chart> = (growing.into_iter())
        .filter(|c| !c.groups.is_empty())
        .map(|c| {
            let first = groups[c.seed as usize][0] as usize;
            let mut surfaces: Vec<u32> = c
                .groups
                .iter()
                .flat_map(|&g| groups[g as usize].iter().copied())
                .collect();
            surfaces.sort_unstable();
            Chart {
                point: scene.surfaces[first].vertices[0],
                surfaces,
                normal: c.normal,
                material: c.material,
            }
        })
        .collect();
    charts.sort_by_key(|c| c.surfaces[0]);
    let mut plane_rep: Vec<u32> = (0..count as u32).collect();
    for g in &groups {
        for &s in g {
            plane_rep[s as usize] = g[0];
        }
    }
    (charts, plane_rep)
}

/// Whether a surface other than `a` and `b`, and not in their plane, has an edge along the
/// edge `(p, q)` that they share, starting at one of its ends (a wall standing on the line where
/// two floor polygons meet, whether its edge is that line or longer).
fn stands_on(
    scene: &Scene,
    keys: &[Vec<[i64; 3]>],
    by_vertex: &HashMap<[i64; 3], Vec<u32>>,
    (p, q): ([i64; 3], [i64; 3]),
    a: u32,
    b: u32,
) -> bool {
    let sa = &scene.surfaces[a as usize];
    let position = |s: u32, k: [i64; 3]| {
        let i = keys[s as usize].iter().position(|&x| x == k)?;
        Some((i, scene.surfaces[s as usize].vertices[i]))
    };
    let (Some((_, pp)), Some((_, pq))) = (position(a, p), position(a, q)) else {
        return false;
    };
    let along = (pq - pp).normalize_or_zero();
    for (end, out) in [(p, along), (q, -along)] {
        for &c in by_vertex.get(&end).map_or(&[][..], |l| &l[..]) {
            let sc = &scene.surfaces[c as usize];
            if c == a || c == b || (1.0 - sc.normal.dot(sa.normal) <= PLANE_NORMAL_TOLERANCE) {
                continue;
            }
            let Some((i, v)) = position(c, end) else { continue };
            let n = sc.vertices.len();
            for w in [sc.vertices[(i + 1) % n], sc.vertices[(i + n - 1) % n]] {
                if (w - v).normalize_or_zero().dot(out) > 1.0 - 1e-9 {
                    return true;
                }
            }
        }
    }
    false
}

/// The cells of a texel lattice on the plane `(frame.u, frame.v)` whose centres lie strictly
/// inside the projection of one of `surfaces` (convex polygons facing `frame.w`'s side).
fn cells_of(scene: &Scene, surfaces: &[u32], frame: &crate::psf::PsfFrame, texel: f64) -> Vec<(i64, i64)> {
    let mut cells = Vec::new();
    for &s in surfaces {
        let poly: Vec<DVec2> = scene.surfaces[s as usize]
            .vertices
            .iter()
            .map(|&p| DVec2::new(p.dot(frame.u), p.dot(frame.v)) / texel)
            .collect();
        let (mut lo, mut hi) = (poly[0], poly[0]);
        for &p in &poly {
            lo = lo.min(p);
            hi = hi.max(p);
        }
        // Orientation of the projection (the surface may face either side of the plane).
        let mut area2 = 0.0;
        for i in 0..poly.len() {
            area2 += poly[i].perp_dot(poly[(i + 1) % poly.len()]);
        }
        if area2.abs() < 1e-12 {
            continue;
        }
        let sign = area2.signum();
        for y in (lo.y - 0.5).ceil() as i64..=(hi.y - 0.5).floor() as i64 {
            for x in (lo.x - 0.5).ceil() as i64..=(hi.x - 0.5).floor() as i64 {
                let c = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
                let inside = (0..poly.len()).all(|i| {
                    let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
                    sign * (b - a).perp_dot(c - a) > 1e-9 * (b - a).length()
                });
                if inside {
                    cells.push((x, y));
                }
            }
        }
    }
    cells
}

/// The in-plane axis of a chart's texel grid: a side of the minimum-area rectangle around the
/// chart's vertices projected onto its plane, chosen among its four orientations (±side,
/// ±perpendicular) as the one closest to `reference`. Depends on the outline only, not on how
/// the inside is tessellated.
pub(crate) fn grid_axis(points: &[DVec3], normal: DVec3, reference: DVec3) -> DVec3 {
    let frame = crate::psf::PsfFrame::new(normal);
    let pts: Vec<DVec2> = points
        .iter()
        .map(|&p| DVec2::new(p.dot(frame.u), p.dot(frame.v)))
        .collect();
    let hull = convex_hull(pts);
    if hull.len() < 2 {
        return frame.u;
    }
    let mut best: Option<(f64, DVec2)> = None;
    let mut candidates: Vec<(f64, DVec2)> = Vec::new();
    for i in 0..hull.len() {
        let e = hull[(i + 1) % hull.len()] - hull[i];
        if e.length() == 0.0 {
            continue;
        }
        let d = e.normalize();
        let perp = d.perp();
        let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
        for p in &hull {
            let c = DVec2::new(p.dot(d), p.dot(perp));
            lo = lo.min(c);
            hi = hi.max(c);
        }
        let a = (hi - lo).x * (hi - lo).y;
        candidates.push((a, d));
        if best.is_none_or(|(b, _)| a < b) {
            best = Some((a, d));
        }
    }
    let Some((min_area, _)) = best else {
        return frame.u;
    };
    let r = DVec2::new(reference.dot(frame.u), reference.dot(frame.v));
    let mut axis = frame.u;
    let mut best_dot = f64::NEG_INFINITY;
    for (a, d) in candidates {
        if a > min_area * (1.0 + 1e-9) + 1e-300 {
            continue;
        }
        for o in [d, -d, d.perp(), -d.perp()] {
            let dot = o.dot(r);
            if dot > best_dot + 1e-12 {
                best_dot = dot;
                axis = frame.u * o.x + frame.v * o.y;
            }
        }
    }
    axis.normalize()
}

/// Andrew's monotone chain, counter-clockwise, nearly collinear points (relative to the
/// point set's extent) dropped.
fn convex_hull(mut pts: Vec<DVec2>) -> Vec<DVec2> {
    pts.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    pts.dedup();
    if pts.len() < 3 {
        return pts;
    }
    let extent = (pts[pts.len() - 1] - pts[0]).length().max(1e-300);
    let eps = 1e-12 * extent * extent;
    let cross = |o: DVec2, a: DVec2, b: DVec2| (a - o).perp_dot(b - o);
    let chain = |points: &mut dyn Iterator<Item = DVec2>| {
        let mut h: Vec<DVec2> = Vec::new();
        for p in points {
            while h.len() >= 2 && cross(h[h.len() - 2], h[h.len() - 1], p) <= eps {
                h.pop();
            }
            h.push(p);
        }
        h.pop();
        h
    };
    let mut hull = chain(&mut pts.iter().copied());
    hull.extend(chain(&mut pts.iter().rev().copied()));
    hull
}

/// Disjoint sets with path halving and union by index (the smaller root wins: deterministic).
struct UnionFind {
    parent: Vec<usize>,
}

impl UnionFind {
    fn new(n: usize) -> Self {
        UnionFind {
            parent: (0..n).collect(),
        }
    }
    fn find(&mut self, mut x: usize) -> usize {
        while self.parent[x] != x {
            self.parent[x] = self.parent[self.parent[x]];
            x = self.parent[x];
        }
        x
    }
    fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            let (lo, hi) = (ra.min(rb), ra.max(rb));
            self.parent[hi] = lo;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{FaceOrigin, Material, Normalisation, Surface};

    fn polygon(vertices: Vec<DVec3>, material: usize) -> Surface {
        Surface::from_vertices(vertices, material, FaceOrigin { line: 0, face: 0 }).unwrap()
    }

    fn scene(surfaces: Vec<Surface>) -> Scene {
        let m = |name: &str, specular: f64| Material {
            name: name.into(),
            diffuse: [0.5 - specular / 2.0; 3],
            specular: [specular; 3],
            emission: [0.0; 3],
            albedo_texture: None,
        };
        Scene {
            surfaces,
            materials: vec![m("a", 0.0), m("b", 0.0), m("mirror", 0.9)],
            normalisation: Normalisation {
                center: DVec3::ZERO,
                scale: 1.0,
            },
            textures: Vec::new(),
        }
    }

    /// A tilted rectangle `corner + s·a + t·b`, `s, t ∈ [0, 1]`, as one quad or as `k × k`
    /// cells of two triangles.
    fn rectangle(corner: DVec3, a: DVec3, b: DVec3, k: usize, material: usize) -> Vec<Surface> {
        let at = |i: usize, j: usize| corner + a * (i as f64 / k as f64) + b * (j as f64 / k as f64);
        if k == 1 {
            return vec![polygon(vec![at(0, 0), at(1, 0), at(1, 1), at(0, 1)], material)];
        }
        let mut out = Vec::new();
        for i in 0..k {
            for j in 0..k {
                out.push(polygon(vec![at(i, j), at(i + 1, j), at(i + 1, j + 1)], material));
                out.push(polygon(vec![at(i, j), at(i + 1, j + 1), at(i, j + 1)], material));
            }
        }
        out
    }

    #[test]
    fn a_triangulated_wall_is_one_chart_with_the_plain_walls_grid() {
        let (corner, a, b) = (
            DVec3::new(-0.5, -0.3, 0.2),
            DVec3::new(0.8, 0.1, 0.3),
            DVec3::new(-0.1, 0.7, 0.0),
        );
        let b = b - a * (a.dot(b) / a.length_squared()); // a rectangle
        let plain = scene(rectangle(corner, a, b, 1, 0));
        let split = scene(rectangle(corner, a, b, 40, 0));
        let texel = 2.0 / 64.0;
        let charts = segment(&split, texel);
        assert_eq!(charts.len(), 1);
        assert_eq!(charts[0].surfaces.len(), 3200);
        let ga = crate::maps::TexelAtlas::new(&plain, texel, texel).unwrap();
        let gb = crate::maps::TexelAtlas::new(&split, texel, texel).unwrap();
        let (ga, gb) = (&ga.charts[0], &gb.charts[0]);
        assert_eq!((ga.width, ga.height), (gb.width, gb.height));
        assert!((ga.origin - gb.origin).length() < 1e-12 && (ga.axis_u - gb.axis_u).length() < 1e-12);
        // The grid follows the rectangle's sides.
        assert!(ga.axis_u.dot(a.normalize()).abs() > 1.0 - 1e-12 || ga.axis_u.dot(b.normalize()).abs() > 1.0 - 1e-12);
    }

    #[test]
    fn materials_planes_and_mirrors_keep_charts_apart() {
        let x = DVec3::X * 0.4;
        let z = DVec3::Z * 0.4;
        let mut surfaces = rectangle(DVec3::ZERO, x, z, 2, 0);
        // Same plane, next to it, another material.
        surfaces.extend(rectangle(x, x, z, 1, 1));
        // A parallel plane just above: never merged with the first.
        surfaces.extend(rectangle(DVec3::Y * 1e-3, -x, z, 1, 0));
        // A mirror of two coplanar triangles, tilted by 10° from a diffuse neighbour: the
        // mirror is one chart of its own.
        let tilt = DVec3::new(0.0, 10f64.to_radians().sin(), 10f64.to_radians().cos()) * 0.4;
        surfaces.extend(rectangle(DVec3::new(-0.4, 0.0, 0.0), x, -tilt, 1, 2));
        let s = scene(surfaces);
        let charts = segment(&s, 0.05);
        let of = |surface: u32| charts.iter().position(|c| c.surfaces.contains(&surface)).unwrap();
        assert!((0..8).all(|k| of(k) == of(0)), "the split rectangle is one chart");
        assert_ne!(of(8), of(0), "another material");
        assert_ne!(of(9), of(0), "another plane");
        assert_ne!(of(10), of(0), "a mirror");
        assert_eq!(charts.len(), 4);
        // Every surface in exactly one chart, charts ordered by their first surface.
        let mut all: Vec<u32> = charts.iter().flat_map(|c| c.surfaces.clone()).collect();
        all.sort_unstable();
        assert_eq!(all, (0..s.surfaces.len() as u32).collect::<Vec<_>>());
        assert!(charts.windows(2).all(|w| w[0].surfaces[0] < w[1].surfaces[0]));
    }

    /// A closed cylinder's side, 48 facets: curved charts of neighbouring facets, each within
    /// the chart angle of its normal, none folding.
    #[test]
    fn a_curved_mesh_is_cut_into_charts_within_the_angle() {
        let facets = 48;
        let mut surfaces = Vec::new();
        for k in 0..facets {
            let (a0, a1) = (
                k as f64 / facets as f64 * std::f64::consts::TAU,
                (k + 1) as f64 / facets as f64 * std::f64::consts::TAU,
            );
            let p = |a: f64, y: f64| DVec3::new(0.5 * a.cos(), y, 0.5 * a.sin());
            // Outward: counter-clockwise seen from outside.
            surfaces.push(polygon(vec![p(a0, -0.4), p(a0, 0.4), p(a1, 0.4), p(a1, -0.4)], 0));
        }
        let s = scene(surfaces);
        let charts = segment(&s, 0.02);
        let cos_max = CURVED_CHART_ANGLE_DEG.to_radians().cos();
        for c in &charts {
            for &m in &c.surfaces {
                assert!(s.surfaces[m as usize].normal.dot(c.normal) >= cos_max - 1e-12);
            }
        }
        // 360° in charts of at most ±30°: at least 6, and not one a facet.
        println!("cylinder: {} charts", charts.len());
        assert!(charts.len() >= 6 && charts.len() <= 12, "{} charts", charts.len());
        assert!(segment(&s, 0.02) == charts, "deterministic");
    }

    /// A helicoid ramp of nearly horizontal facets winds over itself: no chart may cover a
    /// texel centre twice.
    #[test]
    fn a_surface_winding_over_itself_is_not_folded_into_one_chart() {
        let (steps, turns) = (60, 1.5);
        let mut surfaces = Vec::new();
        let p = |t: f64, r: f64| {
            let a = t * turns * std::f64::consts::TAU;
            DVec3::new(r * a.cos(), -0.3 + 0.1 * t, r * a.sin())
        };
        for k in 0..steps {
            let (t0, t1) = (k as f64 / steps as f64, (k + 1) as f64 / steps as f64);
            // Facing up (+y): counter-clockwise seen from above.
            surfaces.push(polygon(vec![p(t0, 0.2), p(t1, 0.2), p(t1, 0.6)], 0));
            surfaces.push(polygon(vec![p(t0, 0.2), p(t1, 0.6), p(t0, 0.6)], 0));
        }
        let s = scene(surfaces);
        assert!(s.surfaces.iter().all(|f| f.normal.y > 0.9));
        let texel = 0.02;
        let charts = segment(&s, texel);
        assert!(charts.len() >= 2, "a ramp of 1.5 turns cannot be one flat chart");
        for c in &charts {
            let frame = crate::psf::PsfFrame::new(c.normal);
            let mut seen = HashSet::default();
            for &m in &c.surfaces {
                for cell in cells_of(&s, &[m], &frame, texel) {
                    assert!(
                        seen.insert(cell),
                        "chart of {:?} covers cell {cell:?} twice",
                        c.surfaces[0]
                    );
                }
            }
        }
    }
}
