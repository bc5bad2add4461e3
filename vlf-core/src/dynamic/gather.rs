//! The gather: shading a point of a moving object from the field.
//!
//! A diffuse point `p` with normal `n` and reflectance ρd sends
//!
//! ```text
//! L_out = ρd/π · ∫_{n·ω > 0} L_in(p, ω) (n·ω) dω
//! ```
//!
//! where `L_in(p, ω)` is the radiance arriving from direction `ω`: the radiance that the
//! static surface seen from `p` along `ω` sends back toward `p`. The field already holds it:
//! that surface's stored radiance ([`LightField::shade`]: its diffuse map, a mirror's
//! directional maps or a traced reflection, a back face 0), found with a ray through the
//! scene's BVH. (The field's own tiles are no constant-time shortcut here: a diffuse-only
//! field keeps no subfields, and the nearest field ray can pass half a ray spacing from `p`.)
//!
//! The integral is taken over the field's own direction set: each line direction `ω_d`
//! (weight `Δω_d`, the hemisphere's cells) stands for the two directions `±ω_d`, and the one on
//! `n`'s side is used. The continuous form divides by π = `∫ (n·ω)⁺ dω`; the discrete sum
//! `W = Σ_d |n·ω_d| Δω_d` is close to π but not equal, so dividing by `W` instead,
//!
//! ```text
//! L_out = ρd · Σ_d L_in(±ω_d) |n·ω_d| Δω_d / Σ_d |n·ω_d| Δω_d,
//! ```
//!
//! makes a field of uniform radiance `L` give exactly `ρd·L` whatever the normal (a furnace
//! stays a furnace; tested), and the error of the quadrature is left in how `L_in` varies, not
//! in its mean. (The thesis stored per-cell areas and projected-area constants to the same end;
//! none is needed with this normalisation.)
//!
//! A direction blocked by an object (the point's own object, a concave mesh, or another)
//! brings no light: light the objects reflect onto each other is not gathered (a second
//! bounce, below the error of the first for the objects a walkthrough moves).

use super::PlacedObject;
use crate::directions::DirectionSet;
use crate::field::LightField;
use crate::lookup::SpecularMode;
use crate::render::Bvh;
use crate::scene::Rgb;
use glam::DVec3;

/// How far a gather ray starts off the surface, against self-intersection (the VLF frame
/// spans 2).
const RAY_OFFSET: f64 = 1e-7;

/// Gathers light from `field` at points of placed objects.
pub struct Gatherer<'a> {
    field: &'a LightField,
    bvh: &'a Bvh,
    objects: &'a [PlacedObject],
    directions: DirectionSet,
    mode: SpecularMode,
}

impl<'a> Gatherer<'a> {
    /// A gatherer over the field's own direction set. `bvh` is the static scene's;
    /// `objects` are the placed objects that block gather rays; `mode` is how mirrors are read
    /// (as when rendering the static scene).
    pub fn new(
        field: &'a LightField,
        bvh: &'a Bvh,
        objects: &'a [PlacedObject],
        mode: SpecularMode,
    ) -> crate::Result<Self> {
        Self::with_directions(field, bvh, objects, mode, field.options.directions)
    }

    /// [`Gatherer::new`] with a direction set of `directions` lines (one of
    /// [`DirectionSet::SUPPORTED`]): fewer for speed, more for a smoother gather.
    pub fn with_directions(
        field: &'a LightField,
        bvh: &'a Bvh,
        objects: &'a [PlacedObject],
        mode: SpecularMode,
        directions: usize,
    ) -> crate::Result<Self> {
        Ok(Gatherer {
            field,
            bvh,
            objects,
            directions: DirectionSet::new(directions)?,
            mode,
        })
    }

    pub fn field(&self) -> &'a LightField {
        self.field
    }

    pub fn objects(&self) -> &'a [PlacedObject] {
        self.objects
    }

    pub fn mode(&self) -> SpecularMode {
        self.mode
    }

    /// The cosine-weighted mean radiance arriving at `p` over the hemisphere of `n`:
    /// `Σ L_in |n·ω| Δω / Σ |n·ω| Δω` (see the module docs). A diffuse point reflects ρd times
    /// it.
    pub fn incident(&self, p: DVec3, n: DVec3) -> Rgb {
        let n = n.normalize();
        let origin = p + n * RAY_OFFSET;
        let (mut sum, mut weights) = ([0.0f64; 3], 0.0f64);
        for d in 0..self.directions.len() {
            let direction = self.directions.get(d);
            let c = n.dot(direction.vector);
            if c == 0.0 {
                continue;
            }
            let (dir, w) = if c > 0.0 {
                (direction.vector, c * direction.weight)
            } else {
                (-direction.vector, -c * direction.weight)
            };
            weights += w;
            let l = self.arriving(origin, dir);
            for k in 0..3 {
                sum[k] += l[k] * w;
            }
        }
        if weights > 0.0 {
            sum.map(|s| s / weights)
        } else {
            [0.0; 3]
        }
    }

    /// Radiance a diffuse point of reflectance `rho` at `p` (normal `n`) sends in every
    /// direction.
    pub fn diffuse(&self, p: DVec3, n: DVec3, rho: Rgb) -> Rgb {
        let e = self.incident(p, n);
        [rho[0] * e[0], rho[1] * e[1], rho[2] * e[2]]
    }

    /// Radiance arriving at `origin` from `−dir` (looking along `dir`): the static surface's,
    /// or nothing where an object is closer or nothing is hit.
    pub fn arriving(&self, origin: DVec3, dir: DVec3) -> Rgb {
        let scene = &self.field.scene;
        let hit = self.bvh.intersect(scene, origin, dir, 0.0, f64::INFINITY);
        let t_static = hit.map_or(f64::INFINITY, |h| h.t);
        let blocked = self
            .objects
            .iter()
            .any(|o| o.bvh.intersect(&o.scene, origin, dir, 0.0, t_static).is_some());
        match hit {
            Some(hit) if !blocked => self.field.shade(self.bvh, &hit, dir, self.mode),
            _ => [0.0; 3],
        }
    }
}
