//! Look-ups: the radiance leaving a surface point towards a viewer, read from
//! a propagated [`LightField`], and the CPU renderer built on them.
//!
//! * Diffuse surfaces (and emitters): their radiance maps, bilinear
//!   ([`LightField::radiance_at`]).
//! * Mirrors, two ways ([`SpecularMode`]):
//!   - **from the rays** (the light field proper): the outgoing direction `v`
//!     lies in a spherical triangle of three directions with barycentric
//!     weights `b_k`; in each direction's subfield the point falls between
//!     four rays, whose mirror radiance is interpolated bilinearly; the three
//!     are blended by `b_k`. No searching but finding the mirror in a tile's
//!     short list. Blurry where directions are sparse, but constant time;
//!   - **ray traced**: reflect the eye ray until it meets a diffuse surface
//!     and read its map (sharp reflections; cost grows with depth).

use crate::field::LightField;
use crate::render::{Bvh, Camera, Hit, Image, render};
use crate::scene::Rgb;
use glam::DVec3;
use serde::{Deserialize, Serialize};

/// How mirrors are shaded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum SpecularMode {
    /// From the field's directional radiance maps (the paper's section 6.1).
    Rays,
    /// Recursive reflection through the scene, at most `depth` mirrors deep
    /// (the paper's section 6.3).
    Trace { depth: u32 },
}

/// Offset along the normal for secondary rays (VLF frame: the scene spans 2).
const RAY_EPSILON: f64 = 1e-7;

impl LightField {
    /// Radiance leaving mirror `surface` at `p` (VLF frame) along unit
    /// direction `outgoing`, from the directional maps. Zero if the field has
    /// no mirror maps or no ray of the three directions meets `p`.
    pub fn mirror_radiance_from_rays(&self, surface: usize, p: DVec3, outgoing: DVec3) -> Rgb {
        let Some(spec) = &self.specular else {
            return [0.0; 3];
        };
        let tri = spec.directions.triangle(outgoing);
        let mut out = [0.0; 3];
        let mut weight = 0.0;
        for (o, b) in tri.vertices.iter().zip(tri.weights) {
            if b <= 0.0 {
                continue;
            }
            let d = o.index as usize;
            let sub = &spec.subfields[d];
            let layout = &spec.layouts[d];
            let n = sub.grid.resolution;
            // Bilinear between the four rays around p's projection.
            let g = sub.frame.to_grid(p, n) - 0.5;
            let (x0, y0) = (g.x.floor(), g.y.floor());
            let (fx, fy) = (g.x - x0, g.y - y0);
            let mut value = [0.0; 3];
            let mut w_sum = 0.0;
            for (dx, dy, w) in [
                (0.0, 0.0, (1.0 - fx) * (1.0 - fy)),
                (1.0, 0.0, fx * (1.0 - fy)),
                (0.0, 1.0, (1.0 - fx) * fy),
                (1.0, 1.0, fx * fy),
            ] {
                let (x, y) = (x0 + dx, y0 + dy);
                if w <= 0.0 || x < 0.0 || y < 0.0 {
                    continue;
                }
                if let Some(slot) = layout.locate(sub, surface as u32, x as u32, y as u32) {
                    let t = spec.totals[d][slot as usize];
                    for c in 0..3 {
                        value[c] += t[c] as f64 * w;
                    }
                    w_sum += w;
                }
            }
            if w_sum > 0.0 {
                for c in 0..3 {
                    out[c] += value[c] / w_sum * b;
                }
                weight += b;
            }
        }
        if weight > 0.0 {
            for v in &mut out {
                *v /= weight;
            }
        }
        out
    }

    /// Radiance arriving at `origin` from direction `-dir` (i.e. seen looking
    /// along `dir`), by tracing through mirrors at most `depth` deep.
    pub fn traced_radiance(&self, bvh: &Bvh, origin: DVec3, dir: DVec3, depth: u32) -> Rgb {
        match bvh.intersect(&self.scene, origin, dir, RAY_EPSILON, f64::INFINITY) {
            Some(hit) => self.shade(bvh, &hit, dir, SpecularMode::Trace { depth }),
            None => [0.0; 3],
        }
    }

    /// Radiance leaving `hit` towards the viewer looking along `dir`.
    pub fn shade(&self, bvh: &Bvh, hit: &Hit, dir: DVec3, mode: SpecularMode) -> Rgb {
        if !hit.front {
            return [0.0; 3];
        }
        let mut out = self.diffuse_radiance_at(bvh, hit.surface, hit.point);
        let material = self.scene.material(hit.surface);
        if !material.is_mirror() {
            return out;
        }
        let n = self.scene.surfaces[hit.surface].normal;
        let reflected = dir - 2.0 * dir.dot(n) * n;
        let mirrored = match mode {
            SpecularMode::Rays => self.mirror_radiance_from_rays(hit.surface, hit.point, -dir),
            SpecularMode::Trace { depth: 0 } => [0.0; 3],
            SpecularMode::Trace { depth } => {
                let l = self.traced_radiance(bvh, hit.point + n * RAY_EPSILON, reflected, depth - 1);
                [
                    l[0] * material.specular[0],
                    l[1] * material.specular[1],
                    l[2] * material.specular[2],
                ]
            }
        };
        for c in 0..3 {
            out[c] += mirrored[c];
        }
        out
    }

    /// Renders the field for a pinhole camera: primary visibility by ray
    /// casting, then [`LightField::shade`]. `samples` per pixel axis (box
    /// filter).
    pub fn render(&self, camera: &Camera, samples: u32, mode: SpecularMode) -> Image {
        let bvh = Bvh::build(&self.scene);
        render(&self.scene, &bvh, camera, samples, |hit: &Hit, dir| {
            self.shade(&bvh, hit, dir, mode)
        })
    }

    /// The paper's backward ray-traced re-sampling of mirror totals: every
    /// mirror slot's radiance is replaced by what a ray traced back along its
    /// reflection finds (`ρs` × the radiance arriving from the mirror image
    /// direction), following real ray paths through further mirrors up to
    /// `depth`. Sharpens reflections seen "from the rays"; done once, after
    /// the last iteration.
    pub fn resample_mirrors(&mut self, depth: u32) {
        use rayon::prelude::*;
        let Some(spec) = &self.specular else {
            return;
        };
        let bvh = Bvh::build(&self.scene);
        let scene = &self.scene;
        let field = &*self;
        let totals: Vec<Vec<[f32; 3]>> = (0..spec.directions.len())
            .into_par_iter()
            .map(|d| {
                let sub = &spec.subfields[d];
                let layout = &spec.layouts[d];
                let mut out = spec.totals[d].clone();
                let w = spec.directions.get(d).vector;
                for &(surface, k, e) in &layout.entries {
                    let s = &scene.surfaces[surface as usize];
                    let rho = scene.materials[s.material].specular;
                    let outgoing = if w.dot(s.normal) > 0.0 { w } else { -w };
                    // Light leaving along `outgoing` arrived from its mirror image.
                    let towards_source = -(outgoing - 2.0 * outgoing.dot(s.normal) * s.normal);
                    let proj = crate::psf::SurfaceProjection::new(&sub.frame, sub.grid.resolution, s.normal, s.offset);
                    let entry = &sub.entries[e as usize];
                    let base = layout.entry_base[e as usize];
                    sub.rays_of(k as usize, entry, |slot, x, y| {
                        let p = proj.point_at(x as f64 + 0.5, y as f64 + 0.5);
                        let l = field.traced_radiance(&bvh, p + s.normal * RAY_EPSILON, towards_source, depth);
                        out[(base + slot - entry.first_ray) as usize] =
                            [(l[0] * rho[0]) as f32, (l[1] * rho[1]) as f32, (l[2] * rho[2]) as f32];
                    });
                }
                out
            })
            .collect();
        if let Some(spec) = &mut self.specular {
            spec.totals = totals;
        }
    }
}
