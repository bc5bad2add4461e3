//! A bounding volume hierarchy over the scene's convex polygons, for primary
//! visibility when rendering a view of the light field.
//!
//! The light field itself never casts rays one by one (propagation works on
//! whole parallel subfields), but rendering a pinhole view needs "which
//! surface does this camera ray see first", once or a few times per pixel.
//! Scenes have up to a few hundred thousand polygons, so a brute-force loop
//! is out of the question; a BVH built with a binned surface-area heuristic
//! makes each query logarithmic.
//!
//! # Layout
//!
//! The tree is kept **flat** so that the same arrays can later be uploaded
//! as storage buffers and traversed by a compute shader:
//!
//! * [`Bvh::nodes`] is a `Vec<Node>` in depth-first order; the root is node
//!   0. Each [`Node`] is 32 bytes (`#[repr(C)]`): `min`/`max` as `[f32; 3]`,
//!   then `index: u32` and `count: u32`.
//!   * **Interior** node (`count == 0`): its left child is the *next* node
//!     (`self + 1`), its right child is node `index`.
//!   * **Leaf** node (`count > 0`): it holds the `count` primitives
//!     `primitives[index .. index + count]`.
//! * [`Bvh::primitives`] is a `Vec<u32>` of surface indices into
//!   [`Scene::surfaces`], permuted so that every leaf's primitives are
//!   contiguous. Surfaces with fewer than three vertices or non-finite
//!   coordinates are left out (they can never be hit).
//!
//! The `f32` bounds are rounded outwards from the `f64` ones (and padded by
//! [`BOX_PADDING`]), so they are conservative: a box never misses a point
//! that the exact `f64` polygon test accepts. The tree depth is at most
//! [`MAX_DEPTH`], so a traversal stack of [`STACK_SIZE`] entries always
//! suffices (a shader can use a fixed-size array).
//!
//! # Intersection
//!
//! Polygons are intersected directly (plane hit, then an inclusive
//! inside-all-edges test with a tolerance of [`EDGE_EPSILON`] in VLF units),
//! not as triangle fans, so a polygon has no internal seams; a ray through an
//! edge shared by two polygons hits at least one of them. Both faces are hit;
//! [`Hit::front`] tells which one. Ties in `t` go to the lowest surface index,
//! which makes the result independent of the tree's shape.
//!
//! The build is sequential and deterministic: the same scene always gives
//! the same arrays.

use glam::DVec3;

use crate::scene::{Scene, Surface};

/// Number of bins per axis of the SAH sweep.
const BINS: usize = 16;
/// A node with at most this many primitives may become a leaf when the SAH
/// says splitting does not pay.
const MAX_LEAF: usize = 4;
/// Cost of a box test relative to a polygon test, for the SAH.
const TRAVERSAL_COST: f64 = 0.5;
/// Maximum depth of the tree (the root has depth 0); deeper nodes are
/// forced to be leaves.
pub const MAX_DEPTH: usize = 48;
/// Size of a traversal stack that always suffices (`>= MAX_DEPTH + 1`).
pub const STACK_SIZE: usize = 64;
/// Padding added to every box on every side, in VLF units (the scene lies
/// in the unit sphere), well above [`EDGE_EPSILON`].
pub const BOX_PADDING: f64 = 1e-7;
/// Tolerance of the inside-edge test: a point at most this far outside an
/// edge (in VLF units, measured in the polygon's plane) still counts as a hit.
pub const EDGE_EPSILON: f64 = 1e-9;

/// One node of the flattened tree (see the module documentation).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Node {
    /// Lower corner of the conservative bounding box.
    pub min: [f32; 3],
    /// Upper corner of the conservative bounding box.
    pub max: [f32; 3],
    /// Interior: index of the right child (the left one is the next node).
    /// Leaf: index of the first primitive in [`Bvh::primitives`].
    pub index: u32,
    /// Number of primitives of a leaf; 0 marks an interior node.
    pub count: u32,
}

impl Node {
    /// Whether this node is a leaf (holds primitives).
    pub fn is_leaf(&self) -> bool {
        self.count > 0
    }
}

/// The nearest intersection of a ray with the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Index into [`Scene::surfaces`].
    pub surface: usize,
    /// Ray parameter: `point = origin + t * dir`.
    pub t: f64,
    /// The hit point (in the frame of the ray, i.e. the VLF frame).
    pub point: DVec3,
    /// Whether the front face was hit (`dir · normal < 0`).
    pub front: bool,
}

/// A bounding volume hierarchy over a scene's surfaces. It stores indices
/// only: pass the same [`Scene`] to [`Bvh::intersect`].
#[derive(Clone, Debug, PartialEq)]
pub struct Bvh {
    nodes: Vec<Node>,
    primitives: Vec<u32>,
}

#[derive(Clone, Copy, Debug)]
struct Aabb {
    min: DVec3,
    max: DVec3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        min: DVec3::INFINITY,
        max: DVec3::NEG_INFINITY,
    };

    fn grow(&mut self, p: DVec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }

    fn union(&mut self, other: &Aabb) {
        self.min = self.min.min(other.min);
        self.max = self.max.max(other.max);
    }

    /// Half the surface area (the SAH only needs ratios); 0 when empty.
    fn half_area(&self) -> f64 {
        let d = (self.max - self.min).max(DVec3::ZERO);
        d.x * d.y + d.y * d.z + d.z * d.x
    }

    fn center(&self) -> DVec3 {
        0.5 * (self.min + self.max)
    }
}

/// The largest `f32` that is `<= v`.
fn f32_down(v: f64) -> f32 {
    let f = v as f32;
    if f as f64 <= v { f } else { f32_step(f, false) }
}

/// The smallest `f32` that is `>= v`.
fn f32_up(v: f64) -> f32 {
    let f = v as f32;
    if f as f64 >= v { f } else { f32_step(f, true) }
}

/// The next representable `f32` above (`up`) or below `f` (finite `f`).
fn f32_step(f: f32, up: bool) -> f32 {
    if f == 0.0 {
        let tiny = f32::from_bits(1);
        return if up { tiny } else { -tiny };
    }
    let bits = f.to_bits();
    // Away from zero means a larger magnitude, i.e. bits + 1.
    let away = (f > 0.0) == up;
    f32::from_bits(if away { bits + 1 } else { bits - 1 })
}

/// Intersects one convex polygon with the ray `origin + t * dir`,
/// `t_min <= t <= t_max` (both inclusive). Returns `t`, the point and
/// whether the front face was hit. Both faces are hit; a ray parallel to
/// the plane misses. The inside test is inclusive with a tolerance of
/// [`EDGE_EPSILON`], so points on an edge hit.
pub fn intersect_surface(
    surface: &Surface,
    origin: DVec3,
    dir: DVec3,
    t_min: f64,
    t_max: f64,
) -> Option<(f64, DVec3, bool)> {
    let vertices = &surface.vertices;
    if vertices.len() < 3 {
        return None;
    }
    let n = surface.normal;
    let denom = n.dot(dir);
    if denom == 0.0 {
        return None;
    }
    let t = (surface.offset - n.dot(origin)) / denom;
    // Written so that NaN fails.
    if !(t >= t_min && t <= t_max) {
        return None;
    }
    let point = origin + t * dir;
    let eps2 = EDGE_EPSILON * EDGE_EPSILON;
    let mut previous = vertices[vertices.len() - 1];
    for &vertex in vertices {
        let edge = vertex - previous;
        // |edge| × signed in-plane distance of `point` to the edge line,
        // positive on the inner side of a counter-clockwise polygon.
        let c = edge.cross(point - previous).dot(n);
        if c < 0.0 && c * c > eps2 * edge.length_squared() {
            return None;
        }
        previous = vertex;
    }
    Some((t, point, denom < 0.0))
}

/// The nearest hit among all surfaces, by brute force (reference for tests
/// and tiny scenes). Same conventions as [`Bvh::intersect`].
pub fn intersect_brute_force(scene: &Scene, origin: DVec3, dir: DVec3, t_min: f64, t_max: f64) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    let mut best_t = t_max;
    for (i, surface) in scene.surfaces.iter().enumerate() {
        match intersect_surface(surface, origin, dir, t_min, best_t) {
            // Strictly nearer only: ties keep the lowest index.
            Some((t, point, front)) if best.is_none() || t < best_t => {
                best_t = t;
                best = Some(Hit {
                    surface: i,
                    t,
                    point,
                    front,
                });
            }
            _ => {}
        }
    }
    best
}

/// Entry parameter of the ray into a node's box within `[t_min, t_max]`
/// (inclusive), or `None` when it misses.
fn slab(node: &Node, origin: DVec3, inv: DVec3, dir: DVec3, t_min: f64, t_max: f64) -> Option<f64> {
    let mut t0 = t_min;
    let mut t1 = t_max;
    for axis in 0..3 {
        let lo = node.min[axis] as f64;
        let hi = node.max[axis] as f64;
        let o = origin[axis];
        if dir[axis] == 0.0 {
            if o < lo || o > hi {
                return None;
            }
            continue;
        }
        let ta = (lo - o) * inv[axis];
        let tb = (hi - o) * inv[axis];
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t0 <= t1).then_some(t0)
}

struct Builder<'a> {
    boxes: &'a [Aabb],
    centers: &'a [DVec3],
    nodes: Vec<Node>,
}

impl Builder<'_> {
    fn bounds(&self, prims: &[u32]) -> (Aabb, Aabb) {
        let mut bounds = Aabb::EMPTY;
        let mut centroids = Aabb::EMPTY;
        for &p in prims {
            bounds.union(&self.boxes[p as usize]);
            centroids.grow(self.centers[p as usize]);
        }
        (bounds, centroids)
    }

    /// Builds the subtree over `prims` (which starts at `first` in the
    /// global primitive array) and returns its node index.
    fn build(&mut self, prims: &mut [u32], first: usize, depth: usize) -> u32 {
        let index = self.nodes.len();
        let (bounds, centroids) = self.bounds(prims);
        let padded_min = bounds.min - DVec3::splat(BOX_PADDING);
        let padded_max = bounds.max + DVec3::splat(BOX_PADDING);
        self.nodes.push(Node {
            min: padded_min.to_array().map(f32_down),
            max: padded_max.to_array().map(f32_up),
            index: first as u32,
            count: prims.len() as u32,
        });
        let count = prims.len();
        if count <= 1 || depth >= MAX_DEPTH {
            return index as u32;
        }

        let split = self.best_split(prims, &bounds, &centroids);
        let mid = match split {
            Some((axis, bin, cost)) => {
                let leaf_cost = count as f64 * bounds.half_area();
                if count <= MAX_LEAF && leaf_cost <= cost {
                    return index as u32;
                }
                // Partition: primitives in bins <= `bin` first.
                let mut i = 0;
                let mut j = count;
                while i < j {
                    if bin_of(self.centers[prims[i] as usize], &centroids, axis) <= bin {
                        i += 1;
                    } else {
                        j -= 1;
                        prims.swap(i, j);
                    }
                }
                if i == 0 || i == count { count / 2 } else { i }
            }
            None => {
                // All centroids coincide: no spatial split helps.
                if count <= MAX_LEAF {
                    return index as u32;
                }
                count / 2
            }
        };

        let (left, right) = prims.split_at_mut(mid);
        self.build(left, first, depth + 1);
        let right_index = self.build(right, first + mid, depth + 1);
        let node = &mut self.nodes[index];
        node.index = right_index;
        node.count = 0;
        index as u32
    }

    /// The binned SAH split of least cost: `(axis, last bin of the left
    /// side, cost)` with cost in the units of `count × half_area`.
    fn best_split(&self, prims: &[u32], bounds: &Aabb, centroids: &Aabb) -> Option<(usize, usize, f64)> {
        let mut best: Option<(usize, usize, f64)> = None;
        for axis in 0..3 {
            // Centroids are finite (unusable surfaces are left out).
            if centroids.max[axis] <= centroids.min[axis] {
                continue;
            }
            let mut bin_boxes = [Aabb::EMPTY; BINS];
            let mut bin_counts = [0usize; BINS];
            for &p in prims {
                let b = bin_of(self.centers[p as usize], centroids, axis);
                bin_boxes[b].union(&self.boxes[p as usize]);
                bin_counts[b] += 1;
            }
            // Right-to-left sweep: area × count of bins `b+1 ..`.
            let mut right_cost = [0.0; BINS];
            let mut acc = Aabb::EMPTY;
            let mut n = 0;
            for b in (1..BINS).rev() {
                acc.union(&bin_boxes[b]);
                n += bin_counts[b];
                right_cost[b - 1] = if n > 0 { acc.half_area() * n as f64 } else { f64::NAN };
            }
            let mut acc = Aabb::EMPTY;
            let mut n = 0;
            for b in 0..BINS - 1 {
                acc.union(&bin_boxes[b]);
                n += bin_counts[b];
                if n == 0 || right_cost[b].is_nan() {
                    continue;
                }
                let cost = TRAVERSAL_COST * bounds.half_area() + acc.half_area() * n as f64 + right_cost[b];
                if best.is_none_or(|(_, _, c)| cost < c) {
                    best = Some((axis, b, cost));
                }
            }
        }
        best
    }
}

fn bin_of(center: DVec3, centroids: &Aabb, axis: usize) -> usize {
    let extent = centroids.max[axis] - centroids.min[axis];
    let x = (center[axis] - centroids.min[axis]) / extent * BINS as f64;
    (x as usize).min(BINS - 1)
}

impl Bvh {
    /// Builds the hierarchy over all of the scene's surfaces (binned SAH,
    /// deterministic).
    pub fn build(scene: &Scene) -> Bvh {
        let mut boxes = Vec::with_capacity(scene.surfaces.len());
        let mut primitives = Vec::with_capacity(scene.surfaces.len());
        for (i, surface) in scene.surfaces.iter().enumerate() {
            let mut b = Aabb::EMPTY;
            for &v in &surface.vertices {
                b.grow(v);
            }
            let usable = surface.vertices.len() >= 3
                && b.min.is_finite()
                && b.max.is_finite()
                && surface.normal.is_finite()
                && surface.offset.is_finite();
            if usable {
                primitives.push(i as u32);
            }
            boxes.push(b);
        }
        if primitives.is_empty() {
            return Bvh {
                nodes: Vec::new(),
                primitives,
            };
        }
        let centers: Vec<DVec3> = boxes.iter().map(Aabb::center).collect();
        let mut builder = Builder {
            boxes: &boxes,
            centers: &centers,
            nodes: Vec::with_capacity(2 * primitives.len()),
        };
        builder.build(&mut primitives, 0, 0);
        let nodes = builder.nodes;
        tracing::debug!(
            surfaces = scene.surfaces.len(),
            primitives = primitives.len(),
            nodes = nodes.len(),
            "built BVH"
        );
        Bvh { nodes, primitives }
    }

    /// The flattened nodes, root first (see the module documentation).
    pub fn nodes(&self) -> &[Node] {
        &self.nodes
    }

    /// Surface indices referenced by the leaves.
    pub fn primitives(&self) -> &[u32] {
        &self.primitives
    }

    /// The nearest surface hit by `origin + t * dir` with
    /// `t_min <= t <= t_max`, either face. `dir` need not be unit length
    /// (`t` is in its units) but must be non-zero. Ties in `t` go to the
    /// lowest surface index, exactly as [`intersect_brute_force`].
    pub fn intersect(&self, scene: &Scene, origin: DVec3, dir: DVec3, t_min: f64, t_max: f64) -> Option<Hit> {
        self.traverse(scene, origin, dir, t_min, t_max, false)
    }

    /// Whether any surface meets `origin + t * dir` with `t_min <= t <= t_max`: a shadow ray's
    /// question. The traversal stops at the first hit it finds instead of looking on for the
    /// nearest, so the answer is [`Bvh::intersect`]'s `is_some()` at less cost wherever the
    /// segment is blocked. (The shader's `blocked` does the same.)
    pub fn occluded(&self, scene: &Scene, origin: DVec3, dir: DVec3, t_min: f64, t_max: f64) -> bool {
        self.traverse(scene, origin, dir, t_min, t_max, true).is_some()
    }

    /// The nearest hit, or with `any_hit` the first one found.
    fn traverse(&self, scene: &Scene, origin: DVec3, dir: DVec3, t_min: f64, t_max: f64, any_hit: bool) -> Option<Hit> {
        if self.nodes.is_empty() || t_min.is_nan() || t_max.is_nan() || t_min > t_max {
            return None;
        }
        let inv = dir.recip();
        let mut best: Option<Hit> = None;
        let mut best_t = t_max;
        let mut stack = [0u32; STACK_SIZE];
        let mut top = 0usize;
        slab(&self.nodes[0], origin, inv, dir, t_min, best_t)?;
        let mut current = 0usize;
        loop {
            let node = &self.nodes[current];
            if node.is_leaf() {
                let start = node.index as usize;
                for &p in &self.primitives[start..start + node.count as usize] {
                    let s = p as usize;
                    if let Some((t, point, front)) = intersect_surface(&scene.surfaces[s], origin, dir, t_min, best_t) {
                        let better = match &best {
                            None => true,
                            Some(b) => t < b.t || (t == b.t && s < b.surface),
                        };
                        if better {
                            best_t = t;
                            best = Some(Hit {
                                surface: s,
                                t,
                                point,
                                front,
                            });
                            if any_hit {
                                return best;
                            }
                        }
                    }
                }
            } else {
                let left = current + 1;
                let right = node.index as usize;
                let tl = slab(&self.nodes[left], origin, inv, dir, t_min, best_t);
                let tr = slab(&self.nodes[right], origin, inv, dir, t_min, best_t);
                match (tl, tr) {
                    (Some(a), Some(b)) => {
                        let (near, far) = if a <= b { (left, right) } else { (right, left) };
                        stack[top] = far as u32;
                        top += 1;
                        current = near;
                        continue;
                    }
                    (Some(_), None) => {
                        current = left;
                        continue;
                    }
                    (None, Some(_)) => {
                        current = right;
                        continue;
                    }
                    (None, None) => {}
                }
            }
            // Pop the next node still worth visiting.
            loop {
                if top == 0 {
                    return best;
                }
                top -= 1;
                let candidate = stack[top] as usize;
                if slab(&self.nodes[candidate], origin, inv, dir, t_min, best_t).is_some() {
                    current = candidate;
                    break;
                }
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::scene::{FaceOrigin, Material, Normalisation};

    /// A small deterministic generator (xorshift64*), to avoid a dependency.
    pub(crate) struct Rng(u64);
    impl Rng {
        pub(crate) fn new(seed: u64) -> Rng {
            Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
        }
        pub(crate) fn next_u64(&mut self) -> u64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
        }
        /// Uniform in [0, 1).
        pub(crate) fn f64(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        pub(crate) fn range(&mut self, a: f64, b: f64) -> f64 {
            a + (b - a) * self.f64()
        }
        pub(crate) fn unit(&mut self) -> DVec3 {
            loop {
                let v = DVec3::new(self.range(-1.0, 1.0), self.range(-1.0, 1.0), self.range(-1.0, 1.0));
                let l = v.length_squared();
                if l > 1e-6 && l <= 1.0 {
                    return v / l.sqrt();
                }
            }
        }
    }

    pub(crate) fn surface(vertices: Vec<DVec3>) -> Surface {
        // Newell normal; the polygons here are planar and convex.
        let mut n = DVec3::ZERO;
        for i in 0..vertices.len() {
            let a = vertices[i];
            let b = vertices[(i + 1) % vertices.len()];
            n += a.cross(b);
        }
        let area = 0.5 * n.length();
        let normal = n.normalize();
        Surface {
            offset: normal.dot(vertices[0]),
            vertices,
            normal,
            area,
            material: 0,
            origin: FaceOrigin { line: 0, face: 0 },
            uv: None,
        }
    }

    pub(crate) fn scene_of(surfaces: Vec<Surface>) -> Scene {
        Scene {
            surfaces,
            materials: vec![Material {
                name: "grey".into(),
                diffuse: [0.5; 3],
                specular: [0.0; 3],
                emission: [0.0; 3],
                albedo_texture: None,
            }],
            normalisation: Normalisation {
                center: DVec3::ZERO,
                scale: 1.0,
            },
            textures: Vec::new(),
        }
    }

    /// A random convex polygon: `k` points on a circle at increasing angles,
    /// counter-clockwise about a random normal.
    fn random_polygon(rng: &mut Rng) -> Surface {
        let normal = rng.unit();
        let u = normal.any_orthonormal_vector();
        let v = normal.cross(u);
        let center = rng.unit() * rng.range(0.0, 0.7);
        let radius = rng.range(0.02, 0.25);
        let k = 3 + (rng.next_u64() % 6) as usize;
        let mut angles: Vec<f64> = (0..k).map(|_| rng.range(0.0, std::f64::consts::TAU)).collect();
        angles.sort_by(f64::total_cmp);
        let vertices = angles
            .iter()
            .map(|a| center + radius * (a.cos() * u + a.sin() * v))
            .collect();
        let s = surface(vertices);
        assert!(s.normal.dot(normal) > 0.999);
        s
    }

    pub(crate) fn random_scene(seed: u64, n: usize) -> Scene {
        let mut rng = Rng::new(seed);
        scene_of((0..n).map(|_| random_polygon(&mut rng)).collect())
    }

    #[test]
    fn f32_rounding_is_conservative() {
        for v in [0.1f64, -0.1, 1.0 / 3.0, -1.0 / 3.0, 0.0, 1e-40, -1e-40, 0.999_999_999_9] {
            let d = f32_down(v);
            let u = f32_up(v);
            assert!((d as f64) <= v && (u as f64) >= v, "{v}: {d} {u}");
            assert!(f32_step(d, true) as f64 > v || d as f64 == v);
            assert!((f32_step(u, false) as f64) < v || u as f64 == v);
        }
    }

    #[test]
    fn single_polygon_hits_both_faces_and_respects_range() {
        // Unit square in z = 0, front normal +z.
        let s = surface(vec![
            DVec3::new(-0.5, -0.5, 0.0),
            DVec3::new(0.5, -0.5, 0.0),
            DVec3::new(0.5, 0.5, 0.0),
            DVec3::new(-0.5, 0.5, 0.0),
        ]);
        assert!((s.normal - DVec3::Z).length() < 1e-15);
        let from_front = intersect_surface(&s, DVec3::new(0.1, 0.2, 2.0), -DVec3::Z, 0.0, f64::INFINITY);
        let (t, p, front) = from_front.expect("front hit");
        assert_eq!(t, 2.0);
        assert!(front);
        assert_eq!(p, DVec3::new(0.1, 0.2, 0.0));
        let (t, _, front) = intersect_surface(&s, DVec3::new(0.1, 0.2, -3.0), DVec3::Z, 0.0, f64::INFINITY).unwrap();
        assert_eq!(t, 3.0);
        assert!(!front);
        // Range limits are inclusive; outside them it misses.
        assert!(intersect_surface(&s, DVec3::new(0.1, 0.2, 2.0), -DVec3::Z, 0.0, 2.0).is_some());
        assert!(intersect_surface(&s, DVec3::new(0.1, 0.2, 2.0), -DVec3::Z, 0.0, 1.999).is_none());
        assert!(intersect_surface(&s, DVec3::new(0.1, 0.2, 2.0), -DVec3::Z, 2.001, 9.0).is_none());
        // Behind the origin, beside the polygon, parallel to it: misses.
        assert!(intersect_surface(&s, DVec3::new(0.1, 0.2, 2.0), DVec3::Z, 0.0, f64::INFINITY).is_none());
        assert!(intersect_surface(&s, DVec3::new(0.6, 0.2, 2.0), -DVec3::Z, 0.0, f64::INFINITY).is_none());
        assert!(intersect_surface(&s, DVec3::new(0.1, 0.2, 0.0), DVec3::X, 0.0, f64::INFINITY).is_none());
        // Exactly on an edge and a vertex: hits (inclusive).
        assert!(intersect_surface(&s, DVec3::new(0.5, 0.2, 1.0), -DVec3::Z, 0.0, f64::INFINITY).is_some());
        assert!(intersect_surface(&s, DVec3::new(-0.5, -0.5, 1.0), -DVec3::Z, 0.0, f64::INFINITY).is_some());
        // Just outside the tolerance: misses.
        assert!(intersect_surface(&s, DVec3::new(0.5 + 1e-8, 0.2, 1.0), -DVec3::Z, 0.0, f64::INFINITY).is_none());
    }

    #[test]
    fn bvh_matches_brute_force_on_random_rays() {
        let scene = random_scene(7, 200);
        let bvh = Bvh::build(&scene);
        let mut rng = Rng::new(99);
        let mut hits = 0;
        let mut back = 0;
        for i in 0..20_000 {
            // Origins inside and outside the unit sphere; some finite ranges.
            let origin = rng.unit() * rng.range(0.0, 2.0);
            let dir = if i % 2 == 0 {
                rng.unit()
            } else {
                // Aim at a random point in the scene for more hits, with a
                // non-unit direction.
                (rng.unit() * rng.range(0.0, 0.7) - origin) * rng.range(0.5, 3.0)
            };
            let (t_min, t_max) = if i % 5 == 0 {
                (rng.range(0.0, 0.5), rng.range(0.5, 2.0))
            } else {
                (0.0, f64::INFINITY)
            };
            let expected = intersect_brute_force(&scene, origin, dir, t_min, t_max);
            let got = bvh.intersect(&scene, origin, dir, t_min, t_max);
            assert_eq!(got, expected, "ray {i}: origin {origin}, dir {dir}");
            // The shadow ray's question, answered at the first hit found.
            let segment_end = t_max.min(rng.range(0.2, 3.0));
            assert_eq!(
                bvh.occluded(&scene, origin, dir, t_min, segment_end),
                intersect_brute_force(&scene, origin, dir, t_min, segment_end).is_some(),
                "segment {i}: origin {origin}, dir {dir}, t ≤ {segment_end}"
            );
            if let Some(h) = got {
                hits += 1;
                back += usize::from(!h.front);
                assert_eq!(h.front, dir.dot(scene.surfaces[h.surface].normal) < 0.0);
            }
        }
        // The comparison is not vacuous: many hits, of both faces.
        assert!(hits > 5_000, "{hits} hits");
        assert!(back > 1_000 && hits - back > 1_000, "{back} back faces of {hits}");
    }

    #[test]
    fn axis_parallel_rays_and_axis_aligned_polygons() {
        // Axis-aligned polygons give flat boxes; axis-parallel rays have
        // zero direction components. Grid origins land exactly on planes.
        let mut surfaces = Vec::new();
        for k in 0..5 {
            let z = -0.4 + 0.2 * k as f64;
            let x0 = -0.5 + 0.1 * k as f64;
            surfaces.push(surface(vec![
                DVec3::new(x0, -0.5, z),
                DVec3::new(x0 + 0.5, -0.5, z),
                DVec3::new(x0 + 0.5, 0.5, z),
                DVec3::new(x0, 0.5, z),
            ]));
            surfaces.push(surface(vec![
                DVec3::new(z, -0.3, x0),
                DVec3::new(z, 0.3, x0),
                DVec3::new(z, 0.3, x0 + 0.4),
            ]));
        }
        let scene = scene_of(surfaces);
        let bvh = Bvh::build(&scene);
        let mut hits = 0;
        for ix in -10..=10 {
            for iy in -10..=10 {
                let (x, y) = (ix as f64 * 0.1, iy as f64 * 0.1);
                for (origin, dir) in [
                    (DVec3::new(x, y, 2.0), -DVec3::Z),
                    (DVec3::new(x, y, -2.0), DVec3::Z),
                    (DVec3::new(-2.0, x, y), DVec3::X),
                    (DVec3::new(x, 2.0, y), -DVec3::Y),
                ] {
                    let expected = intersect_brute_force(&scene, origin, dir, 0.0, f64::INFINITY);
                    assert_eq!(bvh.intersect(&scene, origin, dir, 0.0, f64::INFINITY), expected);
                    hits += usize::from(expected.is_some());
                }
            }
        }
        assert!(hits > 250, "{hits}");
    }

    #[test]
    fn shared_edges_are_watertight() {
        // A rotated 8 × 8 grid of quads, each split into two triangles along
        // its diagonal; rays aimed at points on the shared edges and
        // vertices must never slip through.
        let rotation = glam::DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.7, 1.1);
        let grid = |i: usize, j: usize| rotation * DVec3::new(-0.6 + 0.15 * i as f64, -0.6 + 0.15 * j as f64, 0.05);
        let mut surfaces = Vec::new();
        for i in 0..8 {
            for j in 0..8 {
                surfaces.push(surface(vec![grid(i, j), grid(i + 1, j), grid(i + 1, j + 1)]));
                surfaces.push(surface(vec![grid(i, j), grid(i + 1, j + 1), grid(i, j + 1)]));
            }
        }
        let scene = scene_of(surfaces);
        let bvh = Bvh::build(&scene);
        let mut rng = Rng::new(3);
        for _ in 0..20_000 {
            let (i, j) = ((rng.next_u64() % 8) as usize, (rng.next_u64() % 8) as usize);
            let s = rng.f64();
            // A point on the diagonal, on a grid line, or a vertex.
            let target = match rng.next_u64() % 3 {
                0 => grid(i, j).lerp(grid(i + 1, j + 1), s),
                1 => grid(i, j).lerp(grid(i + 1, j), s),
                _ => grid(i, j),
            };
            let origin = rng.unit() * 1.5;
            let dir = target - origin;
            if dir.normalize().dot(scene.surfaces[0].normal).abs() < 0.05 {
                continue; // grazing: the grid edge itself may be missed legitimately
            }
            let hit = bvh.intersect(&scene, origin, dir, 0.0, f64::INFINITY);
            let hit = hit.unwrap_or_else(|| panic!("ray to {target} from {origin} slipped through"));
            assert!((hit.t - 1.0).abs() < 1e-9, "t = {}", hit.t);
        }
    }

    #[test]
    fn tree_invariants() {
        let scene = random_scene(11, 500);
        let bvh = Bvh::build(&scene);
        assert_eq!(bvh, Bvh::build(&scene), "deterministic");
        let mut seen = bvh.primitives().to_vec();
        seen.sort_unstable();
        assert_eq!(seen, (0..500).collect::<Vec<u32>>());
        // Every node's box contains its children's and its primitives'.
        fn check(bvh: &Bvh, scene: &Scene, index: usize, depth: usize, leaves: &mut usize) {
            assert!(depth <= MAX_DEPTH);
            let node = bvh.nodes()[index];
            let inside = |p: DVec3| (0..3).all(|a| p[a] >= node.min[a] as f64 && p[a] <= node.max[a] as f64);
            if node.is_leaf() {
                *leaves += node.count as usize;
                for &p in &bvh.primitives()[node.index as usize..(node.index + node.count) as usize] {
                    assert!(scene.surfaces[p as usize].vertices.iter().all(|&v| inside(v)));
                }
            } else {
                for child in [index + 1, node.index as usize] {
                    let c = bvh.nodes()[child];
                    assert!((0..3).all(|a| c.min[a] >= node.min[a] && c.max[a] <= node.max[a]));
                    check(bvh, scene, child, depth + 1, leaves);
                }
            }
        }
        let mut leaves = 0;
        check(&bvh, &scene, 0, 0, &mut leaves);
        assert_eq!(leaves, 500);
        assert!(bvh.nodes().len() < 2 * 500);
    }

    #[test]
    fn empty_and_degenerate_scenes() {
        let empty = scene_of(Vec::new());
        let bvh = Bvh::build(&empty);
        assert!(bvh.nodes().is_empty());
        assert_eq!(bvh.intersect(&empty, DVec3::ZERO, DVec3::X, 0.0, f64::INFINITY), None);
        let mut degenerate = surface(vec![DVec3::X, DVec3::Y, DVec3::Z]);
        degenerate.vertices.truncate(2);
        let scene = scene_of(vec![degenerate]);
        let bvh = Bvh::build(&scene);
        assert!(bvh.primitives().is_empty());
        assert_eq!(bvh.intersect(&scene, DVec3::ZERO, DVec3::ONE, 0.0, f64::INFINITY), None);
    }
}
