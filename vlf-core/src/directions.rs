//! # Line directions over the hemisphere
//!
//! The virtual light field discretises the set of all lines through the scene
//! by their *direction*: `l` directions, each carrying a grid of parallel
//! rays (a *parallel subfield*). A line carries light both ways, so a line
//! direction `ω` and its opposite `−ω` are the same line direction and `l`
//! directions over the upper hemisphere suffice; light travelling along `−ω`
//! is the same subfield read backwards. An *oriented* direction ([`Oriented`])
//! is a line direction together with a flag saying whether it is `+ω` or `−ω`,
//! so the `l` line directions give `2l` oriented directions covering the whole
//! sphere.
//!
//! The method needs three things of its directions:
//!
//! 1. A nearly uniform covering of the hemisphere, for `l` from a handful to
//!    several thousand, refined in a nested way so that coarse and fine runs
//!    are comparable.
//! 2. A solid-angle *weight* per direction: the share of the sphere that the
//!    direction stands for, used as the quadrature weight when light is
//!    shot along it.
//! 3. Constant-time look-ups for an arbitrary unit vector `d`: the *nearest*
//!    oriented direction (for rendering), and the *spherical triangle* of
//!    three directions that contains `d` together with barycentric weights
//!    (to split light reflected into `d` over the three surrounding
//!    directions without losing or displacing any of it).
//!
//! ## Construction: subdivided octahedron
//!
//! Take the upper half of the octahedron `|x| + |y| + |z| = 1`, `z ≥ 0`. Its
//! projection onto the `xy` plane is the diamond `|x| + |y| ≤ 1`. At level
//! `k` (`1 ≤ k ≤ 6`) let `n = 2^k` and take the lattice points `(i, j)` with
//! integers `|i| + |j| ≤ n`. A lattice point lifts onto the octahedron as
//!
//! ```text
//!     q(i, j) = (i/n, j/n, 1 − |i|/n − |j|/n),      ω(i, j) = q / |q|.
//! ```
//!
//! Points with `|i| + |j| < n` lie in the open upper hemisphere (`z > 0`).
//! The `4n` points on the rim `|i| + |j| = n` lie on the equator (`z = 0`)
//! and come in antipodal pairs `(i, j)` / `(−i, −j)`: both describe the same
//! line, so only one of each pair becomes a direction, the one with `j > 0`,
//! or `j = 0` and `i > 0`. The other rim point is an *alias*: it refers to the
//! kept direction, reversed. This gives
//!
//! ```text
//!     l = 1 + Σ_{r=1}^{n−1} 4r + 2n = 2n² + 1 = 2·4^k + 1
//! ```
//!
//! directions, i.e. 9, 33, 129, 513, 2049 and 8193 for `k = 1..=6`. They are
//! numbered ring by ring (`r = |i| + |j|` from the pole outwards), each ring
//! counter-clockwise from `(r, 0)`, so index 0 is the pole `(0, 0, 1)`.
//!
//! The lattice cuts each quadrant of the diamond into `n²` unit triangles:
//! with `a = |i|`, `b = |j|`, `(fa, fb)` integers,
//!
//! ```text
//!     lower (fa, fb):  (fa, fb), (fa+1, fb), (fa, fb+1)       fa + fb ≤ n − 1
//!     upper (fa, fb):  (fa+1, fb+1), (fa+1, fb), (fa, fb+1)   fa + fb ≤ n − 2
//! ```
//!
//! so `4n²` triangles tile the diamond. Central (gnomonic) projection from
//! the origin maps the planes through the origin to themselves, so a great
//! circle on the sphere meets a face of the octahedron in a straight line:
//! the spherical triangle bounded by great-circle arcs through `ω` of three
//! lattice points is *exactly* the central projection of the planar lattice
//! triangle. The `4n²` spherical triangles therefore tile the upper
//! hemisphere with no gaps or overlaps, and finding the one containing `d`
//! is a planar problem.
//!
//! ## Look-ups in constant time
//!
//! Given `d ≠ 0`: if `d_z < 0`, work with `−d` and reverse every result
//! (since the oriented set is symmetric under `ω ↦ −ω`). With `d_z ≥ 0`,
//! project centrally onto the octahedron and scale to lattice units:
//!
//! ```text
//!     p = n · (d_x, d_y) / (|d_x| + |d_y| + d_z).
//! ```
//!
//! The signs of `p` choose the quadrant; with `a = |p_x|`, `b = |p_y|`,
//! `fa = ⌊a⌋`, `fb = ⌊b⌋` (clamped so that the triangle stays inside the
//! diamond, which also handles `a = n` or `b = n`), the containing triangle is
//! *lower* `(fa, fb)` if `(a − fa) + (b − fb) ≤ 1`, else *upper* `(fa, fb)`;
//! the quadrant signs map its vertices back to signed `(i, j)`, and a
//! `(2n+1)²` table maps each lattice point to its oriented direction.
//!
//! **Barycentric weights.** With `v₁, v₂, v₃` the three oriented unit
//! directions, solve `d = α v₁ + β v₂ + γ v₃` by Cramer's rule
//! (`α = d·(v₂×v₃) / det`, cyclically, `det = v₁·(v₂×v₃)`) and normalise to
//! `α + β + γ = 1`. Inside the triangle all three are `≥ 0`; tiny negatives
//! from rounding are clamped to zero before normalising. By construction
//! `α v₁ + β v₂ + γ v₃` is parallel to `d`, so radiance split with these
//! weights keeps its mean direction.
//!
//! **Nearest direction.** The oriented direction maximising `d·ω` is found
//! among a constant candidate set: the `4 × 4` block of lattice points
//! around the containing triangle (which holds the three vertices and all
//! their 8 neighbours), and, on the rim, the lower-hemisphere points below
//! them (the lower octahedron's point below lattice point `(i, j)` is
//! `(x, y, −z) = −ω(−i, −j)`). For `d_z ≥ 0` such a point never beats its
//! upper twin `(x, y, z)`; it can only tie it when `d_z = 0`, and is there so
//! that ties resolve as a brute-force search would: to the lowest index, then
//! to `+ω`. The unit tests check the result against brute force over all
//! `2l` oriented directions (there, the nearest was always one of the three
//! vertices of the containing triangle; the larger set is a safety margin
//! that costs a few dot products).
//!
//! ## Solid-angle weights
//!
//! The solid angle of a spherical triangle with unit vertices `a, b, c` is
//! (Van Oosterom and Strackee, 1983)
//!
//! ```text
//!     tan(Ω/2) = |a·(b×c)| / (1 + a·b + b·c + c·a),
//! ```
//!
//! evaluated with `atan2` so that it stays accurate for tiny and for large
//! triangles. Each of the `4n²` triangles gives a third of its solid angle to
//! each of its three vertices (an alias vertex gives it to the direction it
//! aliases). Because the triangles tile the upper hemisphere, the weights of
//! the `l` line directions sum to `2π` up to rounding. Each line direction
//! stands for two oriented directions `±ω`, each with that same weight, so
//! the `2l` oriented weights sum to `4π`, the whole sphere.
//!
//! The cells are not equal: central projection squeezes solid angle near the
//! octahedron's vertices (density `∝ 1/|q|³`, `|q|` from `1/√3` at a face
//! centre to `1` at a vertex), and the pole and the four equatorial vertices
//! touch only 4 triangles instead of 6. The ratio of the largest to the
//! smallest weight tends to `(3/2)·3√3 ≈ 7.8` as `k` grows; see the tests.
//!
//! ## Rotated sets
//!
//! [`DirectionSet::rotated`] returns the same set turned by a rotation `R`
//! (used to perturb the directions between iterations): vectors become
//! `R ω`, weights are unchanged. The set keeps `R`, and every look-up first
//! maps its query back with `Rᵀ = R⁻¹`, so [`DirectionSet::nearest`] and
//! [`DirectionSet::triangle`] stay correct on a rotated set (their results
//! refer to the rotated vectors).

use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

/// One line direction: a unit vector and the solid angle it stands for.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Direction {
    /// Unit vector; `z ≥ 0` in an unrotated set.
    pub vector: DVec3,
    /// Solid angle in steradians; the `l` weights of a set sum to `2π`.
    pub weight: f64,
}

/// An oriented direction: a line direction index and whether it is reversed (−ω).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Oriented {
    /// Index of the line direction in its [`DirectionSet`].
    pub index: u32,
    /// `false` for `+ω`, `true` for `−ω`.
    pub reversed: bool,
}

impl Oriented {
    /// The oriented direction `+ω` of line direction `index`.
    pub fn forward(index: u32) -> Self {
        Oriented { index, reversed: false }
    }

    /// The same line direction, pointing the other way.
    pub fn flipped(self) -> Self {
        Oriented {
            index: self.index,
            reversed: !self.reversed,
        }
    }

    /// The order used to break exact ties: lowest index, then `+ω`.
    fn tie_key(self) -> (u32, bool) {
        (self.index, self.reversed)
    }
}

/// The spherical triangle of three oriented directions containing a query
/// vector `d`, with barycentric weights: `weights ≥ 0`, summing to 1, and
/// `Σ weights[t] · vector(vertices[t])` parallel to `d`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SphericalTriangle {
    pub vertices: [Oriented; 3],
    pub weights: [f64; 3],
}

/// `l = 2·4^k + 1` line directions over the upper hemisphere, from the
/// octahedron subdivided `n = 2^k` times along each edge (see the module
/// documentation).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DirectionSet {
    /// Subdivision level `k`.
    level: u32,
    /// Subdivisions per octahedron edge, `n = 2^k`.
    subdivisions: i32,
    /// The directions as handed out: vectors rotated by `rotation`.
    directions: Vec<Direction>,
    /// The unrotated unit vectors `ω(i, j)`, in the lattice frame used by
    /// the look-ups.
    lattice_vectors: Vec<DVec3>,
    /// The lattice point `(i, j)` each direction was made from.
    lattice_points: Vec<[i32; 2]>,
    /// For every lattice point of the `(2n+1)²` square, row `j`, column `i`
    /// (both offset by `n`), the oriented direction it lifts to; points
    /// outside the diamond hold [`OUTSIDE`] and are never read.
    lattice: Vec<Oriented>,
    /// The rotation from the lattice frame to the frame of `directions`.
    rotation: DMat3,
}

/// Filler for the lattice table entries outside the diamond `|i| + |j| ≤ n`.
const OUTSIDE: Oriented = Oriented {
    index: u32::MAX,
    reversed: false,
};

/// Lower-hemisphere points are candidates for [`DirectionSet::nearest`]
/// below lattice points with `|i| + |j| ≥ n − NEAR_EQUATOR_RINGS`.
const NEAR_EQUATOR_RINGS: i32 = 1;

/// The unit vector `ω(i, j)` of lattice point `(i, j)` at `n` subdivisions.
fn lattice_direction(i: i32, j: i32, n: i32) -> DVec3 {
    let n = f64::from(n);
    let (x, y) = (f64::from(i) / n, f64::from(j) / n);
    DVec3::new(x, y, 1.0 - x.abs() - y.abs()).normalize()
}

/// Whether rim point `(i, j)` (or any interior point) is a direction of its
/// own rather than an alias of its antipode.
fn is_kept(i: i32, j: i32, n: i32) -> bool {
    i.abs() + j.abs() < n || j > 0 || (j == 0 && i > 0)
}

/// The lattice points on ring `|i| + |j| = r`, counter-clockwise from `(r, 0)`.
fn ring(r: i32) -> Vec<[i32; 2]> {
    if r == 0 {
        return vec![[0, 0]];
    }
    let mut points = Vec::with_capacity(4 * r as usize);
    points.extend((0..r).map(|t| [r - t, t]));
    points.extend((0..r).map(|t| [-t, r - t]));
    points.extend((0..r).map(|t| [-r + t, -t]));
    points.extend((0..r).map(|t| [t, -r + t]));
    points
}

/// The signed lattice vertices of the unit triangle `(fa, fb)` (lower or
/// upper) in the quadrant with signs `(sx, sy)`.
fn sub_triangle(fa: i32, fb: i32, upper: bool, sx: i32, sy: i32) -> [[i32; 2]; 3] {
    let unsigned = if upper {
        [[fa + 1, fb + 1], [fa + 1, fb], [fa, fb + 1]]
    } else {
        [[fa, fb], [fa + 1, fb], [fa, fb + 1]]
    };
    unsigned.map(|[a, b]| [sx * a, sy * b])
}

/// Solid angle of the spherical triangle with unit vertices `a, b, c`, by
/// Van Oosterom and Strackee: `tan(Ω/2) = |a·(b×c)| / (1 + a·b + b·c + c·a)`.
pub fn spherical_triangle_solid_angle(a: DVec3, b: DVec3, c: DVec3) -> f64 {
    let numerator = a.dot(b.cross(c)).abs();
    let denominator = 1.0 + a.dot(b) + b.dot(c) + c.dot(a);
    2.0 * numerator.atan2(denominator)
}

impl DirectionSet {
    /// The supported numbers of line directions, `2·4^k + 1` for `k = 1..=6`.
    pub const SUPPORTED: [usize; 6] = [9, 33, 129, 513, 2049, 8193];

    /// The set of `count` line directions; `count` must be one of
    /// [`Self::SUPPORTED`].
    pub fn new(count: usize) -> Result<Self, crate::Error> {
        match Self::SUPPORTED.iter().position(|&c| c == count) {
            Some(p) => Self::from_level(p as u32 + 1),
            None => Err(crate::Error::Parameter(format!(
                "{count} directions are not supported; the number of directions must be one of {:?}",
                Self::SUPPORTED
            ))),
        }
    }

    /// The set at subdivision level `k` (`1..=6`), with `2·4^k + 1` directions.
    pub fn from_level(k: u32) -> Result<Self, crate::Error> {
        if !(1..=6).contains(&k) {
            return Err(crate::Error::Parameter(format!(
                "direction level {k} is not supported; it must be in 1..=6 \
                 (giving {:?} directions)",
                Self::SUPPORTED
            )));
        }
        let n: i32 = 1 << k;
        let side = (2 * n + 1) as usize;
        let mut lattice = vec![OUTSIDE; side * side];
        let mut lattice_points = Vec::with_capacity(2 * (n * n) as usize + 1);
        let mut lattice_vectors = Vec::with_capacity(lattice_points.capacity());

        // Kept points, ring by ring, get the indices.
        for r in 0..=n {
            for [i, j] in ring(r) {
                if is_kept(i, j, n) {
                    lattice[Self::slot_in(n, i, j)] = Oriented::forward(lattice_points.len() as u32);
                    lattice_points.push([i, j]);
                    lattice_vectors.push(lattice_direction(i, j, n));
                }
            }
        }
        // Rim aliases refer to their antipodes, reversed.
        for [i, j] in ring(n) {
            if !is_kept(i, j, n) {
                lattice[Self::slot_in(n, i, j)] = lattice[Self::slot_in(n, -i, -j)].flipped();
            }
        }

        let mut set = DirectionSet {
            level: k,
            subdivisions: n,
            directions: Vec::new(),
            lattice_vectors,
            lattice_points,
            lattice,
            rotation: DMat3::IDENTITY,
        };

        // Each unit triangle gives a third of its solid angle to each vertex.
        let mut weights = vec![0.0; set.lattice_vectors.len()];
        for (sx, sy) in [(1, 1), (-1, 1), (-1, -1), (1, -1)] {
            for fb in 0..n {
                for fa in 0..n - fb {
                    for upper in [false, true] {
                        if upper && fa + fb > n - 2 {
                            continue;
                        }
                        let vertices = sub_triangle(fa, fb, upper, sx, sy).map(|[i, j]| set.at(i, j));
                        let [a, b, c] = vertices.map(|o| set.lattice_vector(o));
                        let third = spherical_triangle_solid_angle(a, b, c) / 3.0;
                        for o in vertices {
                            weights[o.index as usize] += third;
                        }
                    }
                }
            }
        }
        set.directions = set
            .lattice_vectors
            .iter()
            .zip(&weights)
            .map(|(&vector, &weight)| Direction { vector, weight })
            .collect();
        Ok(set)
    }

    /// Number of line directions `l`.
    pub fn len(&self) -> usize {
        self.directions.len()
    }

    /// Always `false`: every supported set has at least 9 directions.
    pub fn is_empty(&self) -> bool {
        self.directions.is_empty()
    }

    /// Subdivision level `k`, with `len() == 2·4^k + 1`.
    pub fn level(&self) -> u32 {
        self.level
    }

    /// Lattice subdivisions per octahedron edge, `n = 2^k`.
    pub fn subdivisions(&self) -> u32 {
        self.subdivisions as u32
    }

    /// The rotation applied to this set (identity unless made by [`Self::rotated`]).
    pub fn rotation(&self) -> DMat3 {
        self.rotation
    }

    /// The line directions, in index order.
    pub fn directions(&self) -> &[Direction] {
        &self.directions
    }

    /// Line direction `i`. Panics if `i >= len()`, like slice indexing.
    pub fn get(&self, i: usize) -> &Direction {
        &self.directions[i]
    }

    /// The frame of line direction `i`'s subfield: its vector, and the phase of its ray
    /// lattice ([`crate::psf::PsfFrame::shift`]) from the 2-D golden-ratio (R2) sequence in
    /// the index, `shift_i = frac(½ + i·(1/g, 1/g²)) − ½` with `g³ = g + 1`. Any phase is
    /// exact for one direction; what matters is that the phases of the `l` directions fill
    /// the cell evenly, so that the rays' errors in a polygon's area cancel over the set
    /// rather than add up. Line direction 0 keeps the paper's grid. A rotated copy of the set
    /// ([`DirectionSet::rotated`]) keeps the phases.
    pub fn frame(&self, i: usize) -> crate::psf::PsfFrame {
        // The plastic number g, the real root of g³ = g + 1.
        const G: f64 = 1.324_717_957_244_746;
        let phase = |a: f64| (0.5 + i as f64 * a).fract() - 0.5;
        crate::psf::PsfFrame::with_shift(
            self.directions[i].vector,
            glam::DVec2::new(phase(1.0 / G), phase(1.0 / (G * G))),
        )
    }

    /// The lattice point `(i, j)` that line direction `index` was made from.
    /// Panics if `index >= len()`.
    pub fn lattice_point(&self, index: usize) -> [i32; 2] {
        self.lattice_points[index]
    }

    /// The unit vector of an oriented direction: `±vector` of its line direction.
    /// Panics if `o.index >= len()`.
    pub fn vector(&self, o: Oriented) -> DVec3 {
        let v = self.directions[o.index as usize].vector;
        if o.reversed { -v } else { v }
    }

    /// The oriented direction nearest to `d` (largest `d·ω` over all `2l`
    /// oriented directions; exact ties go to the lowest index). `d` need not
    /// be normalised but must be non-zero and finite.
    pub fn nearest(&self, d: DVec3) -> Oriented {
        debug_assert!(d.is_finite() && d != DVec3::ZERO, "nearest: bad query {d}");
        let (upper, flip) = self.to_upper_lattice_frame(d);
        let vertices = self.locate(upper);
        let n = self.subdivisions;
        let lo_i = vertices.iter().map(|p| p[0]).min().unwrap_or(0) - 1;
        let hi_i = vertices.iter().map(|p| p[0]).max().unwrap_or(0) + 1;
        let lo_j = vertices.iter().map(|p| p[1]).min().unwrap_or(0) - 1;
        let hi_j = vertices.iter().map(|p| p[1]).max().unwrap_or(0) + 1;

        let first = self.at(vertices[0][0], vertices[0][1]);
        let mut best = (upper.dot(self.lattice_vector(first)), first);
        let mut consider = |o: Oriented| {
            let dot = upper.dot(self.lattice_vector(o));
            if dot > best.0 || (dot == best.0 && o.tie_key() < best.1.tie_key()) {
                best = (dot, o);
            }
        };
        for j in lo_j..=hi_j {
            for i in lo_i..=hi_i {
                let r = i.abs() + j.abs();
                if r > n {
                    continue;
                }
                consider(self.at(i, j));
                if r >= n - NEAR_EQUATOR_RINGS {
                    consider(self.at(-i, -j).flipped());
                }
            }
        }
        if flip { best.1.flipped() } else { best.1 }
    }

    /// The spherical triangle of three oriented directions containing `d`,
    /// with barycentric weights (see the module documentation). `d` need not
    /// be normalised but must be non-zero and finite.
    pub fn triangle(&self, d: DVec3) -> SphericalTriangle {
        debug_assert!(d.is_finite() && d != DVec3::ZERO, "triangle: bad query {d}");
        let (upper, flip) = self.to_upper_lattice_frame(d);
        let vertices = self.locate(upper).map(|[i, j]| self.at(i, j));
        let [v1, v2, v3] = vertices.map(|o| self.lattice_vector(o));
        let (c23, c31, c12) = (v2.cross(v3), v3.cross(v1), v1.cross(v2));
        let det = v1.dot(c23);
        let raw = [upper.dot(c23), upper.dot(c31), upper.dot(c12)].map(|w| (w / det).max(0.0));
        let sum: f64 = raw.iter().sum();
        let weights = if sum > 0.0 {
            raw.map(|w| w / sum)
        } else {
            // Unreachable for a valid query (d lies in the cone of the
            // triangle); fall back to the vertex closest to d.
            let dots = [v1, v2, v3].map(|v| upper.dot(v));
            let closest = (0..3).fold(0, |best, t| if dots[t] > dots[best] { t } else { best });
            let mut w = [0.0; 3];
            w[closest] = 1.0;
            w
        };
        let vertices = if flip {
            vertices.map(Oriented::flipped)
        } else {
            vertices
        };
        SphericalTriangle { vertices, weights }
    }

    /// The same set rotated by `rotation` (a proper rotation matrix), used to
    /// perturb the directions: vectors become `rotation · ω`, weights are
    /// unchanged. Rotations compose: the new set is turned by `rotation`
    /// times this set's rotation. Look-ups on the result map their query back
    /// with the transpose first, so they stay correct.
    pub fn rotated(&self, rotation: DMat3) -> Self {
        debug_assert!(
            (rotation.transpose() * rotation).abs_diff_eq(DMat3::IDENTITY, 1e-9) && rotation.determinant() > 0.0,
            "rotated: not a rotation matrix"
        );
        let total = rotation * self.rotation;
        let directions = self
            .lattice_vectors
            .iter()
            .zip(&self.directions)
            .map(|(&v, d)| Direction {
                vector: total * v,
                weight: d.weight,
            })
            .collect();
        DirectionSet {
            directions,
            rotation: total,
            ..self.clone()
        }
    }

    /// What [`DirectionSet::triangle`] reads, for re-implementing it elsewhere (the GPU viewer's
    /// shader): the subdivisions `n`, the rotation from the lattice frame, the `(2n+1)²` lattice
    /// table (row `j + n`, column `i + n`; points outside the diamond have index `u32::MAX`) and
    /// the unrotated unit vector of every line direction.
    pub fn lookup_tables(&self) -> (i32, DMat3, &[Oriented], &[DVec3]) {
        (self.subdivisions, self.rotation, &self.lattice, &self.lattice_vectors)
    }

    /// Mean solid angle of a direction's cell, `2π/l` (steradians).
    pub fn mean_solid_angle(&self) -> f64 {
        std::f64::consts::TAU / self.len() as f64
    }

    /// The characteristic angular size of a cell, `√(2π/l)` radians (the side
    /// of a square of the mean solid angle), e.g. as a perturbation amplitude.
    pub fn cell_angular_radius(&self) -> f64 {
        self.mean_solid_angle().sqrt()
    }

    /// `d` in the lattice frame, turned into the upper hemisphere, and
    /// whether it was turned (results must then be reversed).
    fn to_upper_lattice_frame(&self, d: DVec3) -> (DVec3, bool) {
        let local = self.rotation.transpose() * d;
        if local.z < 0.0 { (-local, true) } else { (local, false) }
    }

    /// The signed lattice vertices of the unit triangle containing `d`
    /// (lattice frame, `d.z ≥ 0`).
    fn locate(&self, d: DVec3) -> [[i32; 2]; 3] {
        let n = self.subdivisions;
        let scale = f64::from(n) / (d.x.abs() + d.y.abs() + d.z);
        let (px, py) = (d.x * scale, d.y * scale);
        let (sx, a) = if px < 0.0 { (-1, -px) } else { (1, px) };
        let (sy, b) = if py < 0.0 { (-1, -py) } else { (1, py) };
        // `as i32` saturates (and maps NaN to 0), the clamps keep the
        // triangle inside the diamond, including `a = n` or `b = n`.
        let fa = (a.floor() as i32).clamp(0, n - 1);
        let fb = (b.floor() as i32).clamp(0, n - 1 - fa);
        let upper = fa + fb < n - 1 && (a - f64::from(fa)) + (b - f64::from(fb)) > 1.0;
        sub_triangle(fa, fb, upper, sx, sy)
    }

    /// The oriented direction of lattice point `(i, j)`, `|i| + |j| ≤ n`.
    fn at(&self, i: i32, j: i32) -> Oriented {
        debug_assert!(
            i.abs() + j.abs() <= self.subdivisions,
            "lattice point ({i}, {j}) outside"
        );
        self.lattice[Self::slot_in(self.subdivisions, i, j)]
    }

    fn slot_in(n: i32, i: i32, j: i32) -> usize {
        ((j + n) * (2 * n + 1) + (i + n)) as usize
    }

    /// The unrotated unit vector of an oriented direction.
    fn lattice_vector(&self, o: Oriented) -> DVec3 {
        let v = self.lattice_vectors[o.index as usize];
        if o.reversed { -v } else { v }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::{PI, TAU};

    /// splitmix64, for reproducible random queries.
    struct SplitMix(u64);

    impl SplitMix {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        fn next_f64(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        /// Uniform on the unit sphere.
        fn unit(&mut self) -> DVec3 {
            let z = 2.0 * self.next_f64() - 1.0;
            let phi = TAU * self.next_f64();
            let r = (1.0 - z * z).max(0.0).sqrt();
            DVec3::new(r * phi.cos(), r * phi.sin(), z)
        }
    }

    /// Random unit vectors, a share of them close to or on the equator, and
    /// some scaled (queries need not be normalised).
    fn queries(rng: &mut SplitMix, count: usize) -> Vec<DVec3> {
        (0..count)
            .map(|q| {
                let mut d = rng.unit();
                match q % 8 {
                    0 => d.z *= 1e-6,
                    1 => d.z = 0.0,
                    2 => d.z *= 1e-14,
                    _ => {}
                }
                if q % 5 == 0 {
                    d * (0.001 + 1000.0 * rng.next_f64())
                } else {
                    d.normalize()
                }
            })
            .collect()
    }

    /// Special queries: poles, axes, every lattice direction both ways, and
    /// midpoints of lattice neighbours (along both axes and both diagonals,
    /// which covers every edge of the subdivision), exact and jittered by
    /// a small fraction of a cell, where nearest and triangle are decided
    /// by the smallest margins.
    fn special_queries(set: &DirectionSet, rng: &mut SplitMix) -> Vec<DVec3> {
        let mut out = vec![DVec3::Z, -DVec3::Z, DVec3::X, -DVec3::X, DVec3::Y, -DVec3::Y];
        for d in set.directions() {
            out.push(d.vector);
            out.push(-d.vector);
        }
        let n = set.subdivisions() as i32;
        let inside = |i: i32, j: i32| i.abs() + j.abs() <= n;
        for j in -n..=n {
            for i in -n..=n {
                for [di, dj] in [[1, 0], [0, 1], [1, 1], [1, -1]] {
                    if !inside(i, j) || !inside(i + di, j + dj) {
                        continue;
                    }
                    let m = (lattice_direction(i, j, n) + lattice_direction(i + di, j + dj, n)).normalize();
                    out.push(m);
                    out.push(-m);
                    for _ in 0..2 {
                        let jitter = rng.unit() * (0.05 / n as f64);
                        out.push(m + jitter);
                        out.push(-(m + jitter));
                    }
                }
            }
        }
        out
    }

    fn brute_nearest(set: &DirectionSet, d: DVec3) -> (f64, Oriented) {
        let mut best = (f64::NEG_INFINITY, Oriented::forward(0));
        for index in 0..set.len() as u32 {
            for reversed in [false, true] {
                let o = Oriented { index, reversed };
                let dot = d.dot(set.vector(o));
                if dot > best.0 {
                    best = (dot, o);
                }
            }
        }
        best
    }

    #[test]
    fn counts_unit_vectors_upper_hemisphere_distinct_lines() {
        for k in 1..=6u32 {
            let set = DirectionSet::from_level(k).expect("supported level");
            let expected = 2 * 4usize.pow(k) + 1;
            assert_eq!(set.len(), expected, "level {k}");
            assert_eq!(DirectionSet::SUPPORTED[k as usize - 1], expected);
            assert_eq!(DirectionSet::new(expected).expect("supported count").len(), expected);
            assert!(!set.is_empty());
            for d in set.directions() {
                assert!((d.vector.length() - 1.0).abs() < 1e-15, "not unit: {}", d.vector);
                assert!(d.vector.z >= 0.0, "below the equator: {}", d.vector);
            }
            // No two directions are the same line (d vs ±d).
            let v: Vec<DVec3> = set.directions().iter().map(|d| d.vector).collect();
            let mut max_abs_dot = 0.0f64;
            for a in 0..v.len() {
                for b in a + 1..v.len() {
                    max_abs_dot = max_abs_dot.max(v[a].dot(v[b]).abs());
                }
            }
            assert!(max_abs_dot < 1.0 - 1e-6, "level {k}: two directions coincide as lines");
        }
    }

    #[test]
    fn lattice_table_is_consistent() {
        for k in 1..=6u32 {
            let set = DirectionSet::from_level(k).expect("supported level");
            let n = set.subdivisions() as i32;
            let mut aliases = 0;
            for j in -n..=n {
                for i in -n..=n {
                    if i.abs() + j.abs() > n {
                        continue;
                    }
                    let o = set.at(i, j);
                    let q = DVec3::new(i as f64, j as f64, (n - i.abs() - j.abs()) as f64).normalize();
                    assert!((set.vector(o) - q).length() < 1e-15, "({i}, {j}) -> {o:?}");
                    if o.reversed {
                        aliases += 1;
                        assert_eq!(i.abs() + j.abs(), n, "only rim points are aliases");
                    } else {
                        assert_eq!(set.lattice_point(o.index as usize), [i, j]);
                    }
                }
            }
            assert_eq!(aliases, 2 * n);
            assert_eq!(set.get(0).vector, DVec3::Z, "index 0 is the pole");
        }
    }

    type Integrand = fn(DVec3) -> f64;

    #[test]
    fn weights_positive_sum_to_hemisphere_and_integrate() {
        for k in 1..=6u32 {
            let set = DirectionSet::from_level(k).expect("supported level");
            let w: Vec<f64> = set.directions().iter().map(|d| d.weight).collect();
            assert!(w.iter().all(|&x| x > 0.0), "level {k}: non-positive weight");
            let sum: f64 = w.iter().sum();
            assert!((sum - TAU).abs() < 1e-9, "level {k}: weights sum to {sum}, not 2π");
            let max = w.iter().copied().fold(0.0, f64::max);
            let min = w.iter().copied().fold(f64::INFINITY, f64::min);
            println!("level {k}: l = {}, max/min weight = {:.4}", set.len(), max / min);
            // Asymptotically (3/2)·3√3 ≈ 7.79, see the module documentation.
            assert!(max / min < 8.0, "level {k}: max/min weight {}", max / min);
            assert!((set.mean_solid_angle() - TAU / set.len() as f64).abs() < 1e-15);

            // Quadrature of smooth functions over the hemisphere: the error of
            // ∫ z dω = π and ∫ x²y² dω = 2π/15 falls as 1/n² (constants ≈ 0.52
            // and 0.66), which it would not if weights sat on the wrong
            // directions. Quadratics are exact (∫ z² dω = ∫ x² dω = 2π/3)
            // because the set is symmetric under the octahedral group.
            let quad = |f: Integrand| -> f64 { set.directions().iter().map(|d| d.weight * f(d.vector)).sum() };
            let n2 = (set.subdivisions() as f64).powi(2);
            let cases: [(Integrand, f64, f64); 4] = [
                (|v| v.z, PI, 1.0 / n2),
                (|v| v.x * v.x * v.y * v.y, TAU / 15.0, 1.0 / n2),
                (|v| v.z * v.z, TAU / 3.0, 1e-9),
                (|v| v.x * v.x, TAU / 3.0, 1e-9),
            ];
            for (f, exact, tolerance) in cases {
                let error = (quad(f) - exact).abs() / exact;
                assert!(error < tolerance, "level {k}: relative quadrature error {error}");
            }
        }
    }

    #[test]
    fn solid_angle_of_octant_is_half_pi() {
        let omega = spherical_triangle_solid_angle(DVec3::X, DVec3::Y, DVec3::Z);
        assert!((omega - PI / 2.0).abs() < 1e-15);
    }

    #[test]
    fn nearest_matches_brute_force() {
        for count in [9, 129, 2049] {
            let set = DirectionSet::new(count).expect("supported count");
            let mut rng = SplitMix(0x5EED ^ count as u64);
            let mut all = queries(&mut rng, 200_000);
            all.extend(special_queries(&set, &mut rng));
            let mut ties = 0;
            for &d in &all {
                let fast = set.nearest(d);
                let (best_dot, best) = brute_nearest(&set, d);
                let fast_dot = d.dot(set.vector(fast));
                if fast != best {
                    assert_eq!(
                        fast_dot, best_dot,
                        "l = {count}, d = {d}: {fast:?} vs brute force {best:?}"
                    );
                    ties += 1;
                }
            }
            println!("nearest, l = {count}: {} queries, {ties} exact ties", all.len());
        }
    }

    /// The lattice point of an upper-hemisphere (or equator) unit vector.
    fn lattice_of(v: DVec3, n: i32) -> [i32; 2] {
        let s = n as f64 / (v.x.abs() + v.y.abs() + v.z);
        let (x, y) = (v.x * s, v.y * s);
        assert!(
            (x - x.round()).abs() < 1e-9 && (y - y.round()).abs() < 1e-9,
            "{v} is not a lattice direction"
        );
        [x.round() as i32, y.round() as i32]
    }

    /// Whether three signed lattice points form one unit triangle of the
    /// subdivision: one closed quadrant, and |.| equal to a lower or upper
    /// triangle.
    fn is_unit_triangle(points: [[i32; 2]; 3]) -> bool {
        let same_sign = |c: usize| points.iter().all(|p| p[c] >= 0) || points.iter().all(|p| p[c] <= 0);
        if !same_sign(0) || !same_sign(1) {
            return false;
        }
        let mut abs: Vec<[i32; 2]> = points.iter().map(|p| [p[0].abs(), p[1].abs()]).collect();
        abs.sort();
        let a = abs.iter().map(|p| p[0]).min().unwrap_or(0);
        let b = abs.iter().map(|p| p[1]).min().unwrap_or(0);
        let mut lower = vec![[a, b], [a + 1, b], [a, b + 1]];
        let mut upper = vec![[a + 1, b + 1], [a + 1, b], [a, b + 1]];
        lower.sort();
        upper.sort();
        abs == lower || abs == upper
    }

    #[test]
    fn triangle_contains_query_and_reproduces_its_direction() {
        for count in DirectionSet::SUPPORTED {
            let set = DirectionSet::new(count).expect("supported count");
            let n = set.subdivisions() as i32;
            let mut rng = SplitMix(0x7121 ^ count as u64);
            let mut all = queries(&mut rng, 50_000);
            all.extend(special_queries(&set, &mut rng));
            for &d in &all {
                let t = set.triangle(d);
                let u = d.normalize();
                assert!(t.weights.iter().all(|&w| w >= 0.0), "d = {d}: {t:?}");
                assert!((t.weights.iter().sum::<f64>() - 1.0).abs() < 1e-12, "d = {d}: {t:?}");
                let v = t.vertices.map(|o| set.vector(o));
                let mix = v[0] * t.weights[0] + v[1] * t.weights[1] + v[2] * t.weights[2];
                assert!(mix.cross(u).length() < 1e-12 * mix.length(), "d = {d}: Σwv = {mix}");
                assert!(mix.dot(u) > 0.0, "d = {d}: Σwv = {mix} points away");

                // The vertices are a real unit triangle of the subdivision...
                let side = if d.z < 0.0 { -1.0 } else { 1.0 };
                let points = v.map(|w| {
                    assert!(side * w.z >= 0.0, "d = {d}: vertex {w} on the wrong side");
                    lattice_of(side * w, n)
                });
                assert!(is_unit_triangle(points), "d = {d}: {points:?} is not a unit triangle");
                // ...and d lies inside it (triple products agree in sign).
                let det = v[0].dot(v[1].cross(v[2]));
                for (a, b) in [(0, 1), (1, 2), (2, 0)] {
                    let inside = u.dot(v[a].cross(v[b])) / det;
                    assert!(inside > -1e-12, "d = {d} outside {points:?}: {inside}");
                }
            }
        }
    }

    #[test]
    fn triangle_at_lattice_points_and_poles() {
        let set = DirectionSet::new(129).expect("supported count");
        for pole in [DVec3::Z, -DVec3::Z] {
            let t = set.triangle(pole);
            let top = (0..3).fold(0, |b, i| if t.weights[i] > t.weights[b] { i } else { b });
            assert_eq!(t.weights[top], 1.0);
            assert_eq!(
                t.vertices[top],
                Oriented {
                    index: 0,
                    reversed: pole.z < 0.0
                }
            );
        }
        for index in 0..set.len() as u32 {
            for reversed in [false, true] {
                let o = Oriented { index, reversed };
                let t = set.triangle(set.vector(o));
                let top = (0..3).fold(0, |b, i| if t.weights[i] > t.weights[b] { i } else { b });
                assert!(t.weights[top] > 1.0 - 1e-12, "{o:?}: {t:?}");
                assert!(
                    set.vector(t.vertices[top]).dot(set.vector(o)) > 1.0 - 1e-15,
                    "{o:?}: {t:?}"
                );
                assert_eq!(set.nearest(set.vector(o)), o);
            }
        }
    }

    #[test]
    fn unsupported_sizes_are_errors() {
        for count in [0, 1, 8, 10, 32, 8192, 8194, 32769] {
            match DirectionSet::new(count) {
                Err(crate::Error::Parameter(message)) => {
                    assert!(message.contains("8193") && message.contains("129"), "{message}")
                }
                other => panic!("new({count}) gave {other:?}"),
            }
        }
        for k in [0, 7, 100] {
            assert!(matches!(DirectionSet::from_level(k), Err(crate::Error::Parameter(_))));
        }
    }

    #[test]
    fn rotated_set_lookups_follow_the_rotation() {
        let set = DirectionSet::new(513).expect("supported count");
        let mut rng = SplitMix(0xA0A0);
        let rotation = DMat3::from_axis_angle(rng.unit(), 0.3) * DMat3::from_axis_angle(rng.unit(), 1.1);
        let rotated = set.rotated(rotation);
        assert_eq!(rotated.len(), set.len());
        for (a, b) in set.directions().iter().zip(rotated.directions()) {
            assert_eq!(a.weight, b.weight);
            assert!((rotation * a.vector - b.vector).length() < 1e-15);
        }
        let twice = rotated.rotated(rotation);
        for (a, b) in set.directions().iter().zip(twice.directions()) {
            assert!((rotation * rotation * a.vector - b.vector).length() < 1e-14);
        }
        let mut moved = 0;
        // Generic directions: exactly on the equator, Rᵀ R d ≠ d may cross
        // it and pick the mirrored (equally valid) triangle.
        for _ in 0..20_000 {
            let d = rng.unit();
            let o = set.nearest(d);
            assert_eq!(rotated.nearest(rotation * d), o, "d = {d}");
            assert_eq!(twice.nearest(rotation * (rotation * d)), o, "d = {d}");
            let (t, tr) = (set.triangle(d), rotated.triangle(rotation * d));
            assert_eq!(t.vertices, tr.vertices, "d = {d}");
            for (a, b) in t.weights.iter().zip(tr.weights) {
                assert!((a - b).abs() < 1e-12);
            }
            // The rotated set's own answer differs from the unrotated set's.
            if set.nearest(rotation * d) != o {
                moved += 1;
            }
        }
        assert!(
            moved > 10_000,
            "the rotation should change most unrotated look-ups ({moved})"
        );
    }
}
