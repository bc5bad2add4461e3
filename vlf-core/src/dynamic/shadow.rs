//! Shadows that moving objects cast on the static scene.
//!
//! The field was propagated without the objects, so a static diffuse point `p` (normal `n`,
//! reflectance ρ) holds the light of every direction, including the ones an object now stands
//! in. It must lose exactly that light:
//!
//! ```text
//! ΔL(p) = ρ/π · ∫_{Ω_obj} L_in(p, ω) (n·ω)⁺ dω
//! ```
//!
//! where `Ω_obj` is the set of directions in which an object is nearer than the static scene,
//! and `L_in(p, ω)` is the radiance the static surface behind the object sends toward `p`
//! (the field's, as the gather reads it: [`Gatherer::arriving`] without the objects). This is
//! the i-Field's visibility ratio without its per-ray storage: light arriving indirectly is
//! lost as well as direct light, a large source gives a soft shadow (only part of it is
//! covered), and a wall between `p` and the object blocks the object's shadow with it (the
//! static surface is then nearer), so shadows never pierce walls.
//!
//! **Coverage as a solid angle.** The field's own directions are far too coarse for a small or
//! distant object: it would fall between them and pop in and out as it moves. Instead the
//! integral is taken over the cone that holds the object's bounding sphere (centre `c`,
//! radius `r` at distance `d`: half-angle `α = asin(r/d)`, the whole sphere of directions
//! when `p` is inside it). The cone's spherical cap, of solid angle `Ω = 2π(1 − cos α)`, is cut
//! into `K` cells of equal area along a Fibonacci spiral (cell `i` at `cos θ = 1 − (1 − cos α)
//! (i + ½)/K`, turned by the golden angle each step) around the axis `p → c`, and each cell's
//! centre ray stands for its `Ω/K`. The pattern moves and shrinks with the object, so however
//! small or far away the object is, `K` rays sample it, and its shadow changes smoothly as it
//! moves. Several objects' cones are integrated once: a cell of one cone inside an earlier
//! object's cone is left to that one.
//!
//! **Direct light** is sampled where it is finest. A small lamp behind a large object is hit
//! by a few of the cone's cells or by none, depending on where `p` is (a speckled shadow);
//! a small object in front of a large lamp hides a few of the lamp's quadrature points or none
//! (a shadow that pops). So each emitter's direct light is counted on whichever is finer, seen
//! from `p`: the cone's cells (solid angle `Ω/K` each), or the emitter's own points
//! ([`crate::direct::Emitters`], its solid angle over their number): there the direct part of
//! `ΔL` is `ρ/π · Σ Le A cos θ_p cos θ_s / r²` over the points that an object hides from `p`
//! and the static scene does not, and the cone's cells leave that emitter's emission out. When
//! the field shades with exact direct light ([`crate::direct`]), direct light needs no
//! subtracting: the shadow rays toward the emitters see the objects
//! ([`crate::direct::ExactDirect::irradiance_past`]), and the cells leave every emission out.

//! **Bits.** A point that no cell ray of any object reaches (behind a wall, below the object's
//! horizon, or outside every cone) loses nothing and keeps the very bits it has without the
//! objects: the loss is applied only where it is not zero.
//!
//! **The object's own light.** Where it lost `L_in`, the shadowed point sees the object's own
//! radiance `L_obj`. With [`Gatherer::with_bounce_light`] it is given back,
//! `ΔL = ρ/π ∫_{Ω_obj} (L_in − L_obj)(n·ω)⁺ dω`, `L_obj` gathered once per pose at each object
//! surface's centroid (flat per triangle; an object mirror's reflection left out), so a white
//! object can brighten what is near it; without, the shadow is too dark by
//! `ρ/π ∫_{Ω_obj} L_obj (n·ω)⁺ dω` (measured in `docs/dynamic.md`).
//!
//! **Per texel.** [`Gatherer::texel_shadows`] evaluates `ΔL` at the centre of every texel of
//! the static charts: what gather rays read with [`Gatherer::with_gather_shadows`], and the
//! viewer's shadows per texel.

use super::gather::{Gatherer, RAY_OFFSET};
use crate::render::Hit;
use crate::scene::Rgb;
use glam::DVec3;

/// The golden angle, `π (3 − √5)`: consecutive spiral points turn by it.
const GOLDEN_ANGLE: f64 = 2.399_963_229_728_653;

/// The cone from a point toward an object's bounding sphere.
#[derive(Clone, Copy, Debug)]
struct Cone {
    axis: DVec3,
    /// `cos α`; −1 when the point is inside the sphere (every direction).
    cos_alpha: f64,
}

impl Cone {
    fn toward(p: DVec3, center: DVec3, radius: f64) -> Cone {
        let to = center - p;
        let d = to.length();
        if d <= radius || d == 0.0 {
            return Cone {
                axis: if d > 0.0 { to / d } else { DVec3::Z },
                cos_alpha: -1.0,
            };
        }
        let sin = radius / d;
        Cone {
            axis: to / d,
            cos_alpha: (1.0 - sin * sin).sqrt(),
        }
    }

    fn contains(&self, w: DVec3) -> bool {
        w.dot(self.axis) >= self.cos_alpha
    }

    /// Whether any of the cone lies above the plane of normal `n` (the cone's axis is within
    /// `90° + α` of `n`).
    fn reaches_above(&self, n: DVec3) -> bool {
        if self.cos_alpha <= 0.0 {
            return true;
        }
        let sin_alpha = (1.0 - self.cos_alpha * self.cos_alpha).sqrt();
        n.dot(self.axis) > -sin_alpha
    }

    /// Solid angle of the cap.
    fn solid_angle(&self) -> f64 {
        2.0 * std::f64::consts::PI * (1.0 - self.cos_alpha)
    }

    /// The centre of cell `i` of `k` (see the module docs).
    fn cell(&self, i: u32, k: u32, (u, v): (DVec3, DVec3)) -> DVec3 {
        let cos_theta = 1.0 - (1.0 - self.cos_alpha) * (i as f64 + 0.5) / k as f64;
        let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
        let (s, c) = (i as f64 * GOLDEN_ANGLE).sin_cos();
        (u * (c * sin_theta) + v * (s * sin_theta) + self.axis * cos_theta).normalize()
    }
}

impl Gatherer<'_> {
    /// The radiance a static diffuse point at `p` (normal `n`, reflectance `rho`) loses to the
    /// objects standing between it and the static scene: `ΔL` of the module docs, direct light
    /// included, for radiance read from the field's maps. `None` where no object takes any
    /// light from it (the point keeps its bits).
    pub fn shadow_loss(&self, p: DVec3, n: DVec3, rho: Rgb) -> Option<Rgb> {
        self.loss(p, n, rho, true)
    }

    /// `ΔL` as a point the camera sees loses it: [`Gatherer::shadow_loss`], less its direct
    /// part where the field shades with exact direct light (whose shadow rays see the objects).
    pub fn shadow_loss_seen(&self, p: DVec3, n: DVec3, rho: Rgb) -> Option<Rgb> {
        self.loss(p, n, rho, self.field().exact_direct.is_none())
    }

    /// `ΔL`: the indirect part over the objects' cones, and the direct part when `direct`
    /// (without it when exact direct light's shadow rays already see the objects), each
    /// emitter's over the cone's cells or its own points, whichever are finer.
    fn loss(&self, p: DVec3, n: DVec3, rho: Rgb, direct: bool) -> Option<Rgb> {
        let k = self.shadow_samples();
        if k == 0 || self.objects().is_empty() || !rho.iter().any(|&c| c > 0.0) {
            return None;
        }
        let origin = p + n * RAY_OFFSET;
        let cones: Vec<Cone> = (self.objects().iter())
            .map(|o| Cone::toward(origin, o.center, o.radius))
            .collect();
        if !cones.iter().any(|c| c.reaches_above(n)) {
            return None;
        }
        let scene = &self.field().scene;
        // Emitters whose direct light is counted on the cone's cells: those whose own points
        // are farther apart, seen from `p`, than the cells (a cell's solid angle against an
        // emitter's solid angle over its points).
        let cell = cones.iter().map(Cone::solid_angle).fold(0.0, f64::max) / k as f64;
        let on_cells: Vec<usize> = if direct {
            (self.emitters().surfaces())
                .filter(|&(e, points)| {
                    let s = &scene.surfaces[e];
                    let to = p - s.vertices.iter().sum::<DVec3>() / s.vertices.len() as f64;
                    let solid_angle =
                        (s.area * s.normal.dot(to).max(0.0) / to.length().powi(3)).min(std::f64::consts::TAU);
                    solid_angle / points as f64 > cell
                })
                .map(|(e, _)| e)
                .collect()
        } else {
            Vec::new()
        };
        let mut lost = [0.0f64; 3];
        let mut any = false;
        for (j, cone) in cones.iter().enumerate() {
            if !cone.reaches_above(n) {
                continue;
            }
            let frame = cone.axis.any_orthonormal_pair();
            let cell = cone.solid_angle() / k as f64;
            for i in 0..k {
                let w = cone.cell(i, k, frame);
                let cos = n.dot(w);
                if cos <= 0.0 || cones[..j].iter().any(|c| c.contains(w)) {
                    continue;
                }
                let Some((behind, (object, front))) = self.behind_object(origin, w) else {
                    continue;
                };
                any = true;
                // The object's own light, given back.
                if let Some(light) = &self.object_light
                    && front.front
                {
                    let l = light[object][front.surface];
                    for c in 0..3 {
                        lost[c] -= l[c] * cos * cell;
                    }
                }
                if let Some(hit) = behind {
                    let l = self.sent_back(&hit, w, !on_cells.contains(&hit.surface));
                    for c in 0..3 {
                        lost[c] += l[c] * cos * cell;
                    }
                }
            }
        }
        if direct {
            // The points of the other emitters that an object hides and the static scene does not.
            let e = self.emitters().irradiance_from(
                |e| !on_cells.contains(&e),
                p,
                n,
                |o, w, t| !self.occluded(o, w, t) || self.bvh().occluded(scene, o, w, crate::direct::SHADOW_START, t),
            );
            if e.iter().any(|&c| c > 0.0) {
                any = true;
                for c in 0..3 {
                    lost[c] += e[c];
                }
            }
        }
        any.then(|| std::array::from_fn(|c| rho[c] * std::f64::consts::FRAC_1_PI * lost[c]))
    }

    /// Whether an object is nearer than the static scene along `dir` from `origin`, and if so
    /// the static surface behind it (`None` inside: nothing) and the object and its surface
    /// met.
    fn behind_object(&self, origin: DVec3, dir: DVec3) -> Option<(Option<Hit>, (usize, Hit))> {
        self.count_ray();
        let (object, front) = self.nearest_object(origin, dir, f64::INFINITY)?;
        match self
            .bvh()
            .intersect(&self.field().scene, origin, dir, 0.0, f64::INFINITY)
        {
            Some(hit) if hit.t < front.t => None,
            hit => Some((hit, (object, front))),
        }
    }
}

impl Gatherer<'_> {
    /// The diffuse radiance the static `surface` sends from `p` with the objects in the scene:
    /// the field's (with exact direct light, shadow rays that the objects stop too) less the
    /// light the objects take from it (`ΔL`). The same bits as without objects where none
    /// takes any.
    pub fn diffuse_with_shadows(&self, surface: usize, p: DVec3) -> Rgb {
        let field = self.field();
        let mut l = field.diffuse_radiance_past(self.bvh(), surface, p, |o, d, t| self.occluded(o, d, t));
        let n = field.scene.surfaces[surface].normal;
        if let Some(loss) = self.shadow_loss_seen(p, n, field.scene.albedo_at(surface, p)) {
            for c in 0..3 {
                l[c] = (l[c] - loss[c]).max(0.0);
            }
        }
        l
    }
}

impl Gatherer<'_> {
    /// What every texel of the static charts loses to the objects: `ΔL` at the texel's centre
    /// on its chart's plane, with the normal and reflectance of the chart's first surface,
    /// laid out like the field's radiance (zero where nothing is lost). What gather rays read
    /// when they see the objects' shadows ([`Gatherer::with_gather_shadows`]), and what the
    /// viewer draws as shadows per texel. Texels are independent: computed in parallel, the
    /// same bits whatever the thread count.
    pub fn texel_shadows(&self) -> Vec<[f32; 3]> {
        use rayon::prelude::*;
        let field = self.field();
        let atlas = &field.atlas;
        let mut first = vec![usize::MAX; atlas.charts.len()];
        for (surface, &chart) in atlas.chart_of.iter().enumerate().rev() {
            first[chart as usize] = surface;
        }
        let charts: Vec<(usize, Vec<[f32; 3]>)> = (0..atlas.charts.len())
            .into_par_iter()
            .filter(|&c| first[c] != usize::MAX)
            .map(|c| {
                let (g, surface) = (&atlas.charts[c], first[c]);
                let n = field.scene.surfaces[surface].normal;
                let values = (0..g.height)
                    .flat_map(|y| (0..g.width).map(move |x| (x, y)))
                    .map(|(x, y)| {
                        let p = g.origin + (g.axis_u * (x as f64 + 0.5) + g.axis_v * (y as f64 + 0.5)) * g.texel;
                        let rho = field.scene.albedo_at(surface, p);
                        self.shadow_loss(p, n, rho).map_or([0.0; 3], |l| l.map(|v| v as f32))
                    })
                    .collect();
                (g.first, values)
            })
            .collect();
        let mut out = vec![[0.0f32; 3]; atlas.texels];
        for (start, values) in charts {
            out[start..start + values.len()].copy_from_slice(&values);
        }
        out
    }
}
