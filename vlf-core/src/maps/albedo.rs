//! Diffuse reflectance per texel, `ρ_t`.
//!
//! A texel reflects `ρ_t` times the power it receives ([`crate::propagate`]). Without an
//! albedo texture that is its material's ρd. With one ([`crate::scene::texture`]), the texel
//! covers many texture pixels, and what it reflects is the sum over its area of `ρ(x)·E(x)`:
//! with the irradiance `E` taken as constant over the texel (the field's own resolution), that
//! is `E·∫ρ/A`, so `ρ_t` is the **mean of ρ over the texel's part of the surface**. It is
//! estimated on a `K × K` lattice of points per texel ([`SAMPLES_PER_SIDE`]): each point that
//! lies on a surface of the chart is lifted onto that surface along the chart's normal, and the
//! texture is read where the surface's coordinates place it. A texel that no lattice point of a
//! textured surface falls on (a sliver at a chart's edge) takes the material's ρd times the
//! texture's mean.

use super::TexelAtlas;
use crate::scene::{Rgb, Scene};
use glam::DVec2;

/// Lattice points per texel side.
pub const SAMPLES_PER_SIDE: u32 = 4;

/// `ρ_t` for every texel of `atlas` (see the module docs). Deterministic: surfaces in order.
pub fn texel_albedo(scene: &Scene, atlas: &TexelAtlas) -> Vec<Rgb> {
    let mut albedo = vec![[0.0; 3]; atlas.texels];
    for (grid, &material) in atlas.charts.iter().zip(&atlas.chart_material) {
        let m = &scene.materials[material as usize];
        let fallback = match m.albedo_texture.and_then(|t| scene.textures.get(t as usize)) {
            Some(t) => {
                let mean = t.mean();
                std::array::from_fn(|c| m.diffuse[c] * mean[c])
            }
            None => m.diffuse,
        };
        albedo[grid.first..grid.first + grid.len()].fill(fallback);
    }
    if scene.textures.is_empty() {
        return albedo;
    }
    let mut sum = vec![[0.0f64; 3]; atlas.texels];
    let mut count = vec![0u32; atlas.texels];
    let k = SAMPLES_PER_SIDE as f64;
    let mut corners: Vec<DVec2> = Vec::new();
    for (s, surface) in scene.surfaces.iter().enumerate() {
        if surface.uv.is_none() || scene.material(s).albedo_texture.is_none() {
            continue;
        }
        let grid = atlas.grid(s);
        let normal = grid.axis_u.cross(grid.axis_v);
        let along = surface.normal.dot(normal);
        if along.abs() < 1e-9 {
            continue; // seen edge-on from its chart's plane: no area there
        }
        // The surface in lattice coordinates (texel coordinates × K).
        corners.clear();
        corners.extend(surface.vertices.iter().map(|&p| grid.coords(p) * k));
        let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
        for c in &corners {
            lo = lo.min(*c);
            hi = hi.max(*c);
        }
        let limit = DVec2::new(grid.width as f64, grid.height as f64) * k;
        let (x0, y0) = ((lo.x - 0.5).ceil().max(0.0) as u32, (lo.y - 0.5).ceil().max(0.0) as u32);
        let (x1, y1) = (
            (hi.x - 0.5).floor().min(limit.x - 1.0),
            (hi.y - 0.5).floor().min(limit.y - 1.0),
        );
        if x1 < 0.0 || y1 < 0.0 {
            continue;
        }
        for y in y0..=y1 as u32 {
            for x in x0..=x1 as u32 {
                let q = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
                if !inside_convex(&corners, q) {
                    continue;
                }
                // The lattice point on the chart's plane, lifted onto the surface's plane.
                let on_plane = grid.origin + (grid.axis_u * q.x + grid.axis_v * q.y) * (grid.texel / k);
                let p = on_plane + normal * ((surface.offset - surface.normal.dot(on_plane)) / along);
                let rho = scene.albedo_at(s, p);
                let t = grid.first + ((y / SAMPLES_PER_SIDE) * grid.width + x / SAMPLES_PER_SIDE) as usize;
                for c in 0..3 {
                    sum[t][c] += rho[c];
                }
                count[t] += 1;
            }
        }
    }
    for ((a, s), &n) in albedo.iter_mut().zip(&sum).zip(&count) {
        if n > 0 {
            *a = s.map(|v| v / n as f64);
        }
    }
    albedo
}

/// Whether `q` lies inside (or on) the convex polygon `corners`, of either winding.
fn inside_convex(corners: &[DVec2], q: DVec2) -> bool {
    let (mut pos, mut neg) = (false, false);
    for (i, &a) in corners.iter().enumerate() {
        let b = corners[(i + 1) % corners.len()];
        let cross = (b - a).perp_dot(q - a);
        pos |= cross > 0.0;
        neg |= cross < 0.0;
    }
    !(pos && neg)
}
