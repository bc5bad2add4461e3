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
//! that surface's stored radiance ([`LightField::shade_from_maps`]: its diffuse map, a mirror's
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
//! bounce, below the error of the first for the objects a walkthrough moves). The static
//! surfaces a gather ray meets are read as the field holds them, without the shadows the
//! objects cast on them ([`super::shadow`]): that would cost a shadow cone per gather ray.
//!
//! **Direct light.** By default direct light comes from the field like all light. When the
//! field shades with exact direct light ([`LightField::use_exact_direct`]), so does the
//! gather: the static surfaces' own emission is left out of the sum, and the irradiance `E(p)`
//! straight from the emitters, with shadow rays that the objects stop too, is added:
//!
//! ```text
//! L_out = ρd · ( Σ_d (L_in − Le)(±ω_d) |n·ω_d| Δω_d / Σ_d |n·ω_d| Δω_d  +  E(p)/π ).
//! ```
//!
//! **Cost** is one ray through the static BVH and the objects' per direction and point
//! (`L × P` rays for `P` points), counted by [`rays_traced`].

use super::PlacedObject;
use crate::direct::Emitters;
use crate::directions::DirectionSet;
use crate::field::LightField;
use crate::lookup::SpecularMode;
use crate::render::{Bvh, Hit};
use crate::scene::Rgb;
use glam::DVec3;

/// How far a gather ray starts off the surface, against self-intersection (the VLF frame
/// spans 2).
pub(super) const RAY_OFFSET: f64 = 1e-7;

/// Shadow cone cells per object and static point, unless set ([`Gatherer::with_shadow_samples`]).
pub const DEFAULT_SHADOW_SAMPLES: u32 = 128;

/// Points per emitter for the direct part of shadows, unless set
/// ([`Gatherer::with_direct_samples`]); as many as `render --direct-samples` takes by default.
pub const DEFAULT_DIRECT_SAMPLES: u32 = crate::direct::DEFAULT_SAMPLES;

thread_local! {
    static RAYS: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

/// Gather and shadow rays traced on this thread so far: what the cost of gathering is
/// counted in (a thread-local count, so counting costs no contention).
pub fn rays_traced() -> u64 {
    RAYS.with(|r| r.get())
}

/// Gathers light from `field` at points of placed objects.
pub struct Gatherer<'a> {
    field: &'a LightField,
    bvh: &'a Bvh,
    objects: &'a [PlacedObject],
    directions: DirectionSet,
    mode: SpecularMode,
    shadow_samples: u32,
    emitters: Emitters,
    /// Whether gather rays see the objects' shadows, and those shadows per texel
    /// ([`Gatherer::with_gather_shadows`]).
    sees_shadows: bool,
    gather_shadows: Option<Vec<[f32; 3]>>,
    /// Whether the objects' shadows give back the light the objects reflect, and that light
    /// per object and surface ([`Gatherer::with_bounce_light`]).
    bounces: bool,
    pub(super) object_light: Option<Vec<Vec<Rgb>>>,
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
            shadow_samples: DEFAULT_SHADOW_SAMPLES,
            emitters: Emitters::new(&field.scene, DEFAULT_DIRECT_SAMPLES)?,
            sees_shadows: false,
            gather_shadows: None,
            bounces: false,
            object_light: None,
        })
    }

    /// Cuts each emitter into about `k` points for the direct part of the objects' shadows
    /// ([`super::shadow`]; exact direct light uses its own).
    pub fn with_direct_samples(mut self, k: u32) -> crate::Result<Self> {
        self.emitters = Emitters::new(&self.field.scene, k)?;
        Ok(self.prepared())
    }

    /// Takes `emitters` (the field's own, built for it) as the points of the objects' shadows:
    /// where exact direct light's points serve both, as on the GPU.
    pub fn with_emitters(mut self, emitters: Emitters) -> Self {
        self.emitters = emitters;
        self.prepared()
    }

    pub fn emitters(&self) -> &Emitters {
        &self.emitters
    }

    /// Cuts each object's shadow cone into `k` cells ([`super::shadow`]); 0 casts no shadows.
    pub fn with_shadow_samples(mut self, k: u32) -> Self {
        self.shadow_samples = k;
        self.prepared()
    }

    /// Lets the gather see the objects' shadows on the static scene: a gather ray that meets a
    /// static surface reads its radiance less what the objects take from it there, from
    /// [`Gatherer::texel_shadows`] (computed here, and again when the shadow or direct samples
    /// change: in a builder, not inside the gather's parallel loops). Without it, the cube
    /// on a floor under a lamp gathers from the floor as if the cube cast no shadow on it,
    /// and its faces toward its own shadow come out too bright (+50 % on the side facing away
    /// from the lamp in the Cornell box, `docs/dynamic.md`). Off by default: the gather's
    /// analytic tests (a furnace, one-sided light) are about the gather alone.
    pub fn with_gather_shadows(mut self, on: bool) -> Self {
        self.sees_shadows = on;
        self.prepared()
    }

    /// Whether gather rays see the objects' shadows ([`Gatherer::with_gather_shadows`]).
    pub fn gather_shadows(&self) -> bool {
        self.sees_shadows
    }

    /// Lets the objects' shadows give back the light the objects reflect onto the static
    /// scene: where a shadow cone's cell meets an object, the point loses the radiance behind
    /// the object but receives the object's own, `ΔL = ρ/π ∫_{Ω_obj} (L_in − L_obj)(n·ω)⁺ dω`
    /// ([`super::shadow`]). `L_obj` is the object's diffuse radiance, gathered once per pose
    /// at the centroid of each of its surfaces ([`Gatherer::object_light`], seeing the
    /// objects' shadows where the gather does): flat per triangle, and without an object
    /// mirror's reflection. A white object can then brighten what is near it. Without it, the
    /// shadow of a white cube in the Cornell box is twice as deep as a path tracer's
    /// (`docs/dynamic.md`). Off by default, for the shadow's analytic tests (a black disc).
    pub fn with_bounce_light(mut self, on: bool) -> Self {
        self.bounces = on;
        self.prepared()
    }

    /// Sets what [`Gatherer::with_gather_shadows`] and [`Gatherer::with_bounce_light`] set,
    /// without computing what the CPU needs for them (the shadows per texel and the objects'
    /// light cost `texels × objects × K` rays): for a gatherer that only lays the objects out
    /// for the GPU, which computes its own (`vlf_viewer::FieldRenderer::with_objects`). Its own
    /// CPU gather then reads the field as if both were off. Call it last: the other builders
    /// compute what the settings ask for.
    pub fn with_gpu_lighting(mut self, gather_shadows: bool, bounce_light: bool) -> Self {
        (self.sees_shadows, self.bounces) = (gather_shadows, bounce_light);
        (self.gather_shadows, self.object_light) = (None, None);
        self
    }

    /// Whether the objects' shadows give back their reflected light
    /// ([`Gatherer::with_bounce_light`]).
    pub fn bounce_light(&self) -> bool {
        self.bounces
    }

    /// The light each object sends back, per surface ([`Gatherer::with_bounce_light`]).
    pub fn object_light_cache(&self) -> Option<&[Vec<Rgb>]> {
        self.object_light.as_deref()
    }

    /// Computes what the settings ask for, in order: the shadows per texel (without the
    /// objects' light), the objects' light (its gather seeing those shadows), then the shadows
    /// again with the objects' light given back. In a builder, not inside the gather's
    /// parallel loops.
    fn prepared(mut self) -> Self {
        self.gather_shadows = None;
        self.object_light = None;
        if self.sees_shadows {
            self.gather_shadows = Some(self.texel_shadows());
        }
        if self.bounces {
            self.object_light = Some(self.object_light());
            if self.sees_shadows {
                self.gather_shadows = Some(self.texel_shadows());
            }
        }
        self
    }

    /// The diffuse radiance each object sends from the centroid of each of its surfaces
    /// (`ρd` times the gather there), per object and surface: what a shadow gives back with
    /// [`Gatherer::with_bounce_light`].
    pub fn object_light(&self) -> Vec<Vec<Rgb>> {
        use rayon::prelude::*;
        self.objects
            .iter()
            .map(|o| {
                (o.scene.surfaces.par_iter())
                    .map(|s| {
                        let centroid = s.vertices.iter().sum::<DVec3>() / s.vertices.len() as f64;
                        self.diffuse(centroid, s.normal, o.scene.materials[s.material].diffuse)
                    })
                    .collect()
            })
            .collect()
    }

    /// The direction set gathered over.
    pub fn directions(&self) -> &DirectionSet {
        &self.directions
    }

    pub fn shadow_samples(&self) -> u32 {
        self.shadow_samples
    }

    pub fn field(&self) -> &'a LightField {
        self.field
    }

    pub fn bvh(&self) -> &'a Bvh {
        self.bvh
    }

    pub(super) fn count_ray(&self) {
        RAYS.with(|r| r.set(r.get() + 1));
    }

    /// Whether an object meets the ray from `origin` along `dir` before `t_max`.
    pub fn occluded(&self, origin: DVec3, dir: DVec3, t_max: f64) -> bool {
        (self.objects.iter()).any(|o| o.intersect(origin, dir, t_max).is_some())
    }

    /// The nearest object the ray from `origin` along `dir` meets before `t_max`: its index and
    /// the hit.
    pub fn nearest_object(&self, origin: DVec3, dir: DVec3, t_max: f64) -> Option<(usize, Hit)> {
        let mut best: Option<(usize, Hit)> = None;
        for (k, o) in self.objects.iter().enumerate() {
            let limit = best.map_or(t_max, |(_, h)| h.t);
            if let Some(h) = o.intersect(origin, dir, limit) {
                best = Some((k, h));
            }
        }
        best
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
        let exact = self.field.exact_direct.as_ref();
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
            let l = self.arriving_past(origin, dir, exact.is_some());
            for k in 0..3 {
                sum[k] += l[k] * w;
            }
        }
        if weights > 0.0 {
            sum = sum.map(|s| s / weights);
        }
        if let Some(exact) = exact {
            let e = exact.irradiance_past(&self.field.scene, self.bvh, p, n, |o, d, t| self.occluded(o, d, t));
            for k in 0..3 {
                sum[k] += e[k] * std::f64::consts::FRAC_1_PI;
            }
        }
        sum
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
        self.arriving_past(origin, dir, false)
    }

    /// [`Gatherer::arriving`], less the static surface's own emission when `no_emission`
    /// (direct light is then counted by shadow rays).
    fn arriving_past(&self, origin: DVec3, dir: DVec3, no_emission: bool) -> Rgb {
        let scene = &self.field.scene;
        self.count_ray();
        let hit = self.bvh.intersect(scene, origin, dir, 0.0, f64::INFINITY);
        let t_static = hit.map_or(f64::INFINITY, |h| h.t);
        match hit {
            Some(hit) if !self.occluded(origin, dir, t_static) => {
                self.sent_back_shadowed(&hit, dir, no_emission, self.gather_shadows.as_deref())
            }
            _ => [0.0; 3],
        }
    }

    /// The radiance the static surface at `hit` sends back along `−dir`, as the field's maps
    /// hold it ([`LightField::shade_from_maps`]: exact direct light is for the points a camera
    /// sees, not for every gather ray), less the surface's own emission when `no_emission`.
    pub(super) fn sent_back(&self, hit: &Hit, dir: DVec3, no_emission: bool) -> Rgb {
        self.sent_back_shadowed(hit, dir, no_emission, None)
    }

    /// [`Gatherer::sent_back`], the diffuse radiance less `shadows` (per texel, as
    /// [`Gatherer::texel_shadows`] lays them out) where given.
    fn sent_back_shadowed(&self, hit: &Hit, dir: DVec3, no_emission: bool, shadows: Option<&[[f32; 3]]>) -> Rgb {
        let field = self.field;
        let mut l = match shadows {
            None => field.shade_from_maps(self.bvh, hit, dir, self.mode),
            Some(shadows) => field.shade_by(
                self.bvh,
                hit,
                dir,
                self.mode,
                &|surface, p| {
                    let (l, loss) = (field.radiance_at(surface, p), field.bilinear(shadows, surface, p));
                    [0, 1, 2].map(|c| (l[c] - loss[c]).max(0.0))
                },
                &|surface, p| field.radiance_at(surface, p),
            ),
        };
        if no_emission && hit.front {
            let le = self.field.scene.material(hit.surface).emission;
            for c in 0..3 {
                l[c] = (l[c] - le[c]).max(0.0);
            }
        }
        l
    }
}
