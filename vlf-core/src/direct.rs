//! Exact direct light at render time, in place of the field's.
//!
//! The field's diffuse maps hold all light, direct included, at the
//! resolution of its rays and texels: a shadow edge is as sharp as a texel
//! and as well placed as the nearest ray direction. Direct light is the one
//! part that is cheap to compute exactly per pixel, so a renderer may swap
//! it: with `D_t` the direct part of texel `t`'s radiance in the field and
//! `E(p)` the irradiance at `p` straight from the emitters (with shadows),
//!
//! ```text
//! L(p) = L_field(p) − D(p) + ρd / π · E(p)
//! ```
//!
//! `D` is the radiance the first iteration gave the texels beyond their own
//! emission: in the first iteration only the emitters shoot and nothing
//! received is shot again, so that is exactly the field's direct light
//! (light reaching a diffuse surface by way of a mirror first is not direct:
//! it stays the field's, caustics included).
//!
//! `E(p) = Σ_e Le_e ∫_{A_e} V(p, s) cos θ_p cos θ_s / |p − s|² ds` is
//! integrated by a fixed quadrature: each emitter polygon is fanned into
//! triangles, each triangle cut into `k²` equal sub-triangles, and every
//! sub-triangle contributes its area at its centroid with one shadow ray.
//! The rule is exact for a constant integrand and converges as `k` grows; it
//! is deterministic (no noise, the same bits every time), and it only errs
//! near an emitter's edge seen from close by, where `1/r²` varies within one
//! sub-triangle.

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::field::LightField;
use crate::render::Bvh;
use crate::scene::{Rgb, Scene};

/// Quadrature points per emitter where nothing else is asked: `vlf render`, `vlf study`, and
/// the dynamic objects' shadows (`dynamic::gather::DEFAULT_DIRECT_SAMPLES`).
pub const DEFAULT_SAMPLES: u32 = 64;

/// Quadrature points per emitter in a walkthrough (`vlf view`): a quarter of the shadow rays,
/// so a quarter of the frame's cost on a GPU (an NVIDIA H100 at 1280 × 720: 15.6 against
/// 58.8 ms a frame for the Cornell box, 12.7 against 47.9 ms for the mirror scene), at an
/// accuracy the study cannot tell apart on the bundled scenes (against Mitsuba, 320 × 240:
/// block error 1.11 against 1.10 % for the Cornell box, 3.55 against 3.55 % for the mirror
/// scene; `docs/gpu.md`). Sixteen points still resolve a lamp's penumbra at the distances of
/// a room; a large emitter close to a surface wants more (`--direct-samples`).
pub const WALK_SAMPLES: u32 = 16;

/// Relative shortening of a shadow ray so it does not hit the emitter it
/// aims at (the sample lies on it).
const SHADOW_SHORTEN: f64 = 1e-6;
/// Offset of a shadow ray's origin along the normal (VLF frame: the scene spans 2).
const RAY_EPSILON: f64 = 1e-7;
/// Where along a shadow ray (unit direction, VLF frame) occluders start to count. The origin
/// lies within the padded bounds of the surface it leaves ([`crate::render::bvh::BOX_PADDING`]),
/// so from `t = 0` a traversal descends that surface's branch of the BVH to a leaf: about ten
/// levels on a wall of 3 200 triangles. One millionth of the scene's size further on, the
/// segment has left those flat boxes unless it grazes the surface. (With the first-hit
/// traversal, [`crate::render::Bvh::occluded`], a room of such walls renders with exact direct
/// light in 0.72 of the time, to the same bits: `docs/bench/meshes.md`.) (The shader offsets its origins by 10⁻⁵, past the padding, already.)
pub const SHADOW_START: f64 = 1e-6;

/// One quadrature point on an emitter.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
struct Sample {
    point: DVec3,
    normal: DVec3,
    /// `Le · area` of the sub-triangle (VLF units; `E` is scale-free since
    /// area / r² is).
    power: Rgb,
    /// The emitting surface it lies on.
    #[serde(default)]
    surface: u32,
}

/// The scene's emitters cut into quadrature points (see the module docs): the irradiance
/// straight from them at any point, past whatever blocks the way.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Emitters {
    /// Grouped by surface, in the scene's order.
    samples: Vec<Sample>,
}

impl Emitters {
    /// Every emitter of `scene` in about `per_emitter` points (at least 1 per fan triangle).
    pub fn new(scene: &Scene, per_emitter: u32) -> crate::Result<Emitters> {
        if per_emitter == 0 || per_emitter > 1 << 16 {
            return Err(crate::Error::Parameter(format!(
                "direct light samples per emitter must be 1..=65536, got {per_emitter}"
            )));
        }
        Ok(Emitters {
            samples: emitter_samples(scene, per_emitter),
        })
    }

    /// Number of quadrature points: shadow rays per shaded point.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// `Σ_s Le_s A_s cos θ_p cos θ_s / r²` over the points `s` in front of `p` (VLF frame,
    /// front normal `normal`) whose shadow ray is not `blocked(origin, dir, t_max)`: the
    /// irradiance `E(p)` when `blocked` is the scene, and other sums when it is something else
    /// (the direct light an object takes away).
    pub fn irradiance(&self, p: DVec3, normal: DVec3, blocked: impl Fn(DVec3, DVec3, f64) -> bool) -> Rgb {
        Self::sum(&self.samples, p, normal, blocked)
    }

    /// Every quadrature point: where it is, the emitting surface's front normal, its power
    /// `Le·A` and the surface's index; grouped by surface, in the scene's order.
    pub fn points(&self) -> impl Iterator<Item = (DVec3, DVec3, Rgb, usize)> + '_ {
        self.samples
            .iter()
            .map(|s| (s.point, s.normal, s.power, s.surface as usize))
    }

    /// The emitting surfaces, each with its number of points.
    pub fn surfaces(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.samples
            .chunk_by(|a, b| a.surface == b.surface)
            .map(|g| (g[0].surface as usize, g.len()))
    }

    /// [`Emitters::irradiance`] from the points of the emitting surfaces that `which` selects.
    pub fn irradiance_from(
        &self,
        which: impl Fn(usize) -> bool,
        p: DVec3,
        normal: DVec3,
        blocked: impl Fn(DVec3, DVec3, f64) -> bool,
    ) -> Rgb {
        let mut e = [0.0; 3];
        for g in self.samples.chunk_by(|a, b| a.surface == b.surface) {
            if which(g[0].surface as usize) {
                let part = Self::sum(g, p, normal, &blocked);
                for c in 0..3 {
                    e[c] += part[c];
                }
            }
        }
        e
    }

    fn sum(samples: &[Sample], p: DVec3, normal: DVec3, blocked: impl Fn(DVec3, DVec3, f64) -> bool) -> Rgb {
        let origin = p + normal * RAY_EPSILON;
        let mut e = [0.0; 3];
        for s in samples {
            let to = s.point - p;
            let r2 = to.length_squared();
            if r2 <= 0.0 {
                continue;
            }
            let r = r2.sqrt();
            let w = to / r;
            let (cos_p, cos_s) = (normal.dot(w), -s.normal.dot(w));
            if cos_p <= 0.0 || cos_s <= 0.0 || blocked(origin, w, r * (1.0 - SHADOW_SHORTEN)) {
                continue;
            }
            let g = cos_p * cos_s / r2;
            for (e, power) in e.iter_mut().zip(s.power) {
                *e += power * g;
            }
        }
        e
    }
}

/// What exact direct light needs: the field's direct part per texel and the
/// emitters' quadrature points.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExactDirect {
    /// `D_t`: the field's direct radiance per texel (holes filled).
    direct: Vec<[f32; 3]>,
    samples: Emitters,
}

impl ExactDirect {
    /// Builds the direct part from `first`, the same field after its first
    /// iteration (its radiance minus the surfaces' own emission), and cuts
    /// every emitter into about `samples_per_emitter` quadrature points (at
    /// least 1 per fan triangle).
    pub fn new(first: &LightField, samples_per_emitter: u32) -> crate::Result<ExactDirect> {
        let samples = Emitters::new(&first.scene, samples_per_emitter)?;
        let mut direct = first.radiance.clone();
        first.remove_emission(0, &mut direct);
        Ok(ExactDirect { direct, samples })
    }

    /// `D_t` for every texel, laid out like the field's radiance: what a renderer elsewhere
    /// (the GPU) subtracts.
    pub fn direct(&self) -> &[[f32; 3]] {
        &self.direct
    }

    /// The emitters' quadrature points.
    pub fn emitters(&self) -> &Emitters {
        &self.samples
    }

    /// Number of shadow rays per shaded point.
    pub fn samples(&self) -> usize {
        self.samples.len()
    }

    /// Irradiance `E(p)` straight from the emitters at `p` (VLF frame) on a
    /// surface of front normal `normal`, with shadows.
    pub fn irradiance(&self, scene: &Scene, bvh: &Bvh, p: DVec3, normal: DVec3) -> Rgb {
        self.irradiance_past(scene, bvh, p, normal, |_, _, _| false)
    }

    /// [`ExactDirect::irradiance`] with more in the way than the static scene:
    /// `occluded(origin, dir, t_max)` says whether something else (a moving
    /// object) meets the shadow ray before `t_max`. Where it never does, the
    /// result has the same bits as without it.
    pub fn irradiance_past(
        &self,
        scene: &Scene,
        bvh: &Bvh,
        p: DVec3,
        normal: DVec3,
        occluded: impl Fn(DVec3, DVec3, f64) -> bool,
    ) -> Rgb {
        self.samples.irradiance(p, normal, |origin, w, t_max| {
            bvh.occluded(scene, origin, w, SHADOW_START, t_max) || occluded(origin, w, t_max)
        })
    }
}

/// Quadrature points of every emitter (see the module docs).
fn emitter_samples(scene: &Scene, per_emitter: u32) -> Vec<Sample> {
    let mut out = Vec::new();
    for (surface, s) in scene.surfaces.iter().enumerate() {
        let le = scene.materials[s.material].emission;
        if !le.iter().any(|&c| c > 0.0) {
            continue;
        }
        let triangles = s.vertices.len() - 2;
        // k² sub-triangles per fan triangle: k = ⌈√(per_emitter / triangles)⌉.
        let k = ((per_emitter as f64 / triangles as f64).sqrt().ceil() as usize).max(1);
        for i in 1..s.vertices.len() - 1 {
            let (a, b, c) = (s.vertices[0], s.vertices[i], s.vertices[i + 1]);
            let area = 0.5 * (b - a).cross(c - a).length() / (k * k) as f64;
            let power = le.map(|l| l * area);
            let at = |u: f64, v: f64| a + (b - a) * (u / k as f64) + (c - a) * (v / k as f64);
            for u in 0..k {
                for v in 0..k - u {
                    // Upward sub-triangle (u, v), (u+1, v), (u, v+1).
                    out.push(Sample {
                        point: at(u as f64 + 1.0 / 3.0, v as f64 + 1.0 / 3.0),
                        normal: s.normal,
                        power,
                        surface: surface as u32,
                    });
                    // Downward sub-triangle (u+1, v), (u, v+1), (u+1, v+1).
                    if u + v + 2 <= k {
                        out.push(Sample {
                            point: at(u as f64 + 2.0 / 3.0, v as f64 + 2.0 / 3.0),
                            normal: s.normal,
                            power,
                            surface: surface as u32,
                        });
                    }
                }
            }
        }
    }
    out
}

impl LightField {
    /// Turns `values`, the radiance of this field's texels from `first` on after the first
    /// iteration, into their direct part `D_t`: each texel loses its chart's own emission
    /// (clamped at zero). Works on any run of texels, so a viewer can turn one part of
    /// snapshot 1 at a time.
    pub fn remove_emission(&self, first: usize, values: &mut [[f32; 3]]) {
        let end = first + values.len();
        for (grid, &material) in self.atlas.charts.iter().zip(&self.atlas.chart_material) {
            let (from, to) = (grid.first.max(first), (grid.first + grid.len()).min(end));
            if from >= to {
                continue;
            }
            let le = self.scene.materials[material as usize].emission;
            for t in &mut values[from - first..to - first] {
                for c in 0..3 {
                    t[c] = (t[c] - le[c] as f32).max(0.0);
                }
            }
        }
    }

    /// Shades this field's diffuse surfaces with exact direct light from now
    /// on (see the module docs). `first` is the same job's field after its
    /// first iteration: the same scene and options, else a
    /// [`crate::Error::Parameter`].
    pub fn use_exact_direct(&mut self, first: &LightField, samples_per_emitter: u32) -> crate::Result<()> {
        if first.scene != self.scene || first.options != self.options || first.radiance.len() != self.radiance.len() {
            return Err(crate::Error::Parameter(
                "exact direct light needs the first iteration of the same scene and options".into(),
            ));
        }
        self.exact_direct = Some(ExactDirect::new(first, samples_per_emitter)?);
        Ok(())
    }

    /// Radiance the field's maps give `surface` at `p`, with the direct part
    /// exchanged for the exact one when [`LightField::use_exact_direct`] was
    /// called.
    pub fn diffuse_radiance_at(&self, bvh: &Bvh, surface: usize, p: DVec3) -> Rgb {
        self.diffuse_radiance_past(bvh, surface, p, |_, _, _| false)
    }

    /// [`LightField::diffuse_radiance_at`] with the shadow rays of exact
    /// direct light also stopped where `occluded(origin, dir, t_max)` (see
    /// [`ExactDirect::irradiance_past`]): moving objects cast sharp direct
    /// shadows.
    pub fn diffuse_radiance_past(
        &self,
        bvh: &Bvh,
        surface: usize,
        p: DVec3,
        occluded: impl Fn(DVec3, DVec3, f64) -> bool,
    ) -> Rgb {
        let mut l = self.radiance_at(surface, p);
        let Some(exact) = &self.exact_direct else {
            return l;
        };
        let rho = self.scene.albedo_at(surface, p);
        if !rho.iter().any(|&c| c > 0.0) {
            return l;
        }
        let d = self.bilinear(&exact.direct, surface, p);
        let e = exact.irradiance_past(&self.scene, bvh, p, self.scene.surfaces[surface].normal, occluded);
        for c in 0..3 {
            l[c] = (l[c] - d[c] + rho[c] * std::f64::consts::FRAC_1_PI * e[c]).max(0.0);
        }
        l
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{FaceOrigin, ImportOptions, Material};

    fn square(z: f64, size: f64, up: bool) -> Vec<DVec3> {
        let h = size / 2.0;
        let v = vec![
            DVec3::new(-h, -h, z),
            DVec3::new(h, -h, z),
            DVec3::new(h, h, z),
            DVec3::new(-h, h, z),
        ];
        if up { v } else { v.into_iter().rev().collect() }
    }

    fn material(name: &str, diffuse: f64, emission: f64) -> Material {
        Material {
            name: name.into(),
            diffuse: [diffuse; 3],
            specular: [0.0; 3],
            emission: [emission; 3],
            albedo_texture: None,
        }
    }

    /// Two parallel coaxial squares, the emitter above facing down.
    fn facing_squares(size: f64, gap: f64) -> Scene {
        let polygons = vec![
            (square(0.0, size, true), 0, FaceOrigin { line: 0, face: 0 }),
            (square(gap, size, false), 1, FaceOrigin { line: 0, face: 1 }),
        ];
        let materials = vec![material("floor", 0.5, 0.0), material("light", 0.0, 1.0)];
        Scene::from_polygons(&polygons, materials, &ImportOptions::default())
            .unwrap()
            .0
    }

    #[test]
    fn quadrature_matches_the_analytic_irradiance_under_a_square_light() {
        // Below the centre of a parallel square of side a at height h, of
        // radiance 1: four a/2 × a/2 rectangles with a corner overhead, each
        // of form factor [X/√(1+X²)·atan(X/√(1+X²))]/π with X = (a/2)/h, so
        // E = π·4·that = 4·X/√(1+X²)·atan(X/√(1+X²)).
        let (size, gap) = (1.0, 1.0);
        let scene = facing_squares(size, gap);
        let bvh = Bvh::build(&scene);
        let x = size / 2.0 / gap;
        let s = (1.0 + x * x).sqrt();
        let analytic = 4.0 * (x / s * (x / s).atan());
        let p = scene.normalisation.to_vlf(DVec3::ZERO);
        let n = scene.surfaces[0].normal;
        let mut last = f64::INFINITY;
        for per_emitter in [8, 128, 2048] {
            let e = ExactDirect {
                direct: Vec::new(),
                samples: Emitters::new(&scene, per_emitter).unwrap(),
            }
            .irradiance(&scene, &bvh, p, n);
            let err = (e[0] - analytic).abs() / analytic;
            assert!(err < last, "{per_emitter}: {err} after {last}");
            last = err;
        }
        assert!(last < 1e-3, "relative error {last}");
    }

    #[test]
    fn occluders_cast_shadows_and_back_faces_see_nothing() {
        let (size, gap) = (1.0, 1.0);
        let scene = facing_squares(size, gap);
        let bvh = Bvh::build(&scene);
        let exact = ExactDirect {
            direct: Vec::new(),
            samples: Emitters::new(&scene, 64).unwrap(),
        };
        let n = scene.surfaces[0].normal;
        let p = scene.normalisation.to_vlf(DVec3::ZERO);
        assert!(exact.irradiance(&scene, &bvh, p, n)[0] > 0.0);
        // Facing away from the light: nothing.
        assert_eq!(exact.irradiance(&scene, &bvh, p, -n), [0.0; 3]);
        // Above the light (behind its back face): nothing.
        let above = scene.normalisation.to_vlf(DVec3::new(0.0, 0.0, 2.0 * gap));
        assert_eq!(exact.irradiance(&scene, &bvh, above, -n), [0.0; 3]);
        // Under the floor, looking up through it: the floor occludes.
        let below = scene.normalisation.to_vlf(DVec3::new(0.0, 0.0, -0.1));
        assert_eq!(exact.irradiance(&scene, &bvh, below, n), [0.0; 3]);
    }

    #[test]
    fn samples_cover_each_emitter_with_its_area() {
        let scene = facing_squares(1.0, 1.0);
        for per_emitter in [1, 5, 64, 100] {
            let samples = emitter_samples(&scene, per_emitter);
            assert!(
                samples.len() >= per_emitter as usize,
                "{per_emitter}: {}",
                samples.len()
            );
            let total: f64 = samples.iter().map(|s| s.power[0]).sum();
            assert!((total - scene.surfaces[1].area).abs() < 1e-12);
        }
    }
}
