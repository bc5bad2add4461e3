//! Texel grids on charts: where diffuse radiosity lives.
//!
//! Diffuse light is view-independent, so a diffuse surface's outgoing radiance
//! is stored once, as a map of texels on a plane (the paper's Current / Next
//! / Total texture maps), not per direction. A texel grid belongs to a
//! **chart** ([`charts`]): a connected set of surfaces of one material that
//! share one parameterisation, so that how a surface was tessellated leaves no
//! trace. Each chart gets a rectangular grid of square texels covering its
//! bounding rectangle on its plane; all grids are laid end to end in one global
//! texel array (an *atlas*), so per-texel quantities are plain `Vec`s indexed by
//! [`TexelGrid::first`] + local index.
//!
//! Texels are *discrete areas*: a texel's area as the light field sees it is
//! `A_t = T_t / π`, where `T_t = Σ_ω Δω · n_t(ω)` sums, over all directions,
//! the solid-angle weight times the number of rays that cross the texel (in
//! units of the ray cell area), whichever surface of the chart they cross.
//! See [`crate::propagate`] for why this makes shooting exactly
//! power-conserving.

pub mod albedo;
pub mod charts;
pub mod fill;

use crate::scene::Scene;
use glam::{DVec2, DVec3};
use serde::{Deserialize, Serialize};

/// The texel grid of one surface.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TexelGrid {
    /// Corner of the grid (texel (0,0)'s outer corner), on the surface plane.
    pub origin: DVec3,
    /// Unit in-plane axes; `axis_u × axis_v` = the surface's front normal.
    pub axis_u: DVec3,
    pub axis_v: DVec3,
    /// Texel edge length in the VLF frame.
    pub texel: f64,
    pub width: u32,
    pub height: u32,
    /// Index of texel (0,0) in the atlas.
    pub first: usize,
}

impl TexelGrid {
    /// Continuous texel coordinates of a point on the plane (texel `(s, t)`
    /// spans `[s, s+1) × [t, t+1)`).
    #[inline]
    pub fn coords(&self, p: DVec3) -> DVec2 {
        let d = p - self.origin;
        DVec2::new(d.dot(self.axis_u), d.dot(self.axis_v)) / self.texel
    }

    /// Atlas index of the texel containing continuous coordinates `c`
    /// (clamped onto the grid: points of the polygon are always inside it,
    /// up to rounding).
    ///
    /// `x as u32` is `⌊x⌋` clamped to `[0, u32::MAX]` for every `x` (Rust's float-to-integer
    /// casts truncate toward zero and saturate, NaN to 0), so no call to `floor` is needed:
    /// without SSE4.1 that is a library call, a tenth of the propagation's time.
    #[inline]
    pub fn index(&self, c: DVec2) -> usize {
        let s = (c.x as u32).min(self.width - 1);
        let t = (c.y as u32).min(self.height - 1);
        self.first + (t * self.width + s) as usize
    }

    pub fn len(&self) -> usize {
        (self.width * self.height) as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// All texel grids of a scene, one per chart.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TexelAtlas {
    /// One grid per chart, in chart order (charts numbered by their smallest surface).
    pub charts: Vec<TexelGrid>,
    /// The chart of every surface.
    pub chart_of: Vec<u32>,
    /// The material of every chart (all its surfaces share it).
    pub chart_material: Vec<u32>,
    /// For every surface, the surface that stands for its plane in the subfields
    /// ([`charts::segment_with_planes`]): a wall cut into 3 200 triangles is one entry per tile.
    pub plane_rep: Vec<u32>,
    pub texels: usize,
}

impl TexelAtlas {
    /// Upper bound on the atlas size: 2²⁸ texels is already several GiB of maps.
    pub const MAX_TEXELS: usize = 1 << 28;

    /// Cuts the scene into charts ([`charts::segment`]) and lays out a grid of texel edge
    /// `texel` (VLF units) on every chart of a field whose rays are `ray_spacing` apart.
    ///
    /// The grid's axes follow the chart's outline ([`charts::grid_axis`]). Texel boundaries
    /// are placed on the lattice `−1 + (m + φ)·ray_spacing` (φ = 1/π) along each grid axis.
    /// Ray centres of axis-aligned directions lie at `−1 + (j + ½)·ray_spacing`, and
    /// axis-aligned walls are the rule in real scenes: were a texel boundary to fall exactly
    /// on a ray centre, which texel the ray lands in would depend on the last bit of rounding
    /// (so scaling or moving the scene would change the result). With the irrational offset no
    /// boundary coincides with a centre for any simple texel size.
    pub fn new(scene: &Scene, texel: f64, ray_spacing: f64) -> crate::Result<Self> {
        const PHI: f64 = std::f64::consts::FRAC_1_PI;
        if !(texel.is_finite() && texel > 0.0 && ray_spacing.is_finite() && ray_spacing > 0.0) {
            return Err(crate::Error::Parameter(format!(
                "texel size must be positive and finite, got {texel}"
            )));
        }
        // A texel too small for the scene is refused here, before segmenting lists every texel
        // cell of every polygon (for a texel of 1e-5, billions of cells). A chart's grid covers
        // its polygons laid onto its plane, tilted by up to 45° (`charts`), so the grids hold at
        // least `Σ area · cos 45°` in texels; twice the limit in area is then more than the
        // limit in texels (short of polygons that overlap one another). The area is found from
        // the vertices, not read from the surface (which a stored scene could misstate).
        let area: f64 = (scene.surfaces.iter())
            .map(|s| crate::scene::newell_normal(&s.vertices).length() / 2.0)
            .sum();
        let cells = area / (texel * texel);
        if cells > 2.0 * Self::MAX_TEXELS as f64 {
            return Err(crate::Error::Parameter(format!(
                "texel size {texel:.3e} gives more than {} texels (the surfaces' area alone is {cells:.3e} texels); choose a larger texel",
                Self::MAX_TEXELS
            )));
        }
        let snap = |world: f64| -1.0 + (((world + 1.0) / ray_spacing - PHI).floor() + PHI) * ray_spacing;
        let (charts, plane_rep) = charts::segment_with_planes(scene, texel);
        let mut grids = Vec::with_capacity(charts.len());
        let mut chart_of = vec![0u32; scene.surfaces.len()];
        let mut chart_material = Vec::with_capacity(charts.len());
        let mut first = 0usize;
        let mut points = Vec::new();
        for (c, chart) in charts.iter().enumerate() {
            points.clear();
            for &s in &chart.surfaces {
                chart_of[s as usize] = c as u32;
                points.extend_from_slice(&scene.surfaces[s as usize].vertices);
            }
            chart_material.push(chart.material as u32);
            let normal = chart.normal;
            // A fixed reference for the axis' orientation: the world axis least aligned with
            // the normal (as a subfield's frame picks it).
            let reference = crate::psf::PsfFrame::new(normal).u;
            let axis_u = charts::grid_axis(&points, normal, reference);
            let axis_v = normal.cross(axis_u);
            let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
            for &p in &points {
                let c = DVec2::new(p.dot(axis_u), p.dot(axis_v));
                lo = lo.min(c);
                hi = hi.max(c);
            }
            // Snap the grid's corner (in world coordinates along each axis).
            let corner = DVec2::new(snap(lo.x), snap(lo.y));
            let extent = hi - corner;
            // A chart whose extent is a whole number of texels up to rounding does not get an
            // extra, empty row.
            let width = ((extent.x / texel - 1e-9).ceil() as u64).max(1);
            let height = ((extent.y / texel - 1e-9).ceil() as u64).max(1);
            let count = width.saturating_mul(height) as usize;
            if count > Self::MAX_TEXELS || first + count > Self::MAX_TEXELS {
                return Err(crate::Error::Parameter(format!(
                    "texel size {texel:.3e} gives more than {} texels; choose a larger texel",
                    Self::MAX_TEXELS
                )));
            }
            grids.push(TexelGrid {
                origin: axis_u * corner.x + axis_v * corner.y + normal * normal.dot(chart.point),
                axis_u,
                axis_v,
                texel,
                width: width as u32,
                height: height as u32,
                first,
            });
            first += count;
        }
        Ok(TexelAtlas {
            charts: grids,
            chart_of,
            chart_material,
            plane_rep,
            texels: first,
        })
    }

    /// The texel grid of `surface` (its chart's).
    #[inline]
    pub fn grid(&self, surface: usize) -> &TexelGrid {
        &self.charts[self.chart_of[surface] as usize]
    }

    /// The chart owning each texel.
    pub fn owners(&self) -> Vec<u32> {
        let mut owner = vec![0u32; self.texels];
        for (c, g) in self.charts.iter().enumerate() {
            owner[g.first..g.first + g.len()].fill(c as u32);
        }
        owner
    }

    /// Area of every surface's chart (the sum of its surfaces' areas).
    pub fn chart_areas(&self, scene: &Scene) -> Vec<f64> {
        let mut area = vec![0.0; self.charts.len()];
        for (s, &c) in self.chart_of.iter().enumerate() {
            area[c as usize] += scene.surfaces[s].area;
        }
        self.chart_of.iter().map(|&c| area[c as usize]).collect()
    }

    /// The material of each texel (its chart's).
    pub fn texel_materials(&self) -> Vec<u32> {
        let mut material = vec![0u32; self.texels];
        for (g, &m) in self.charts.iter().zip(&self.chart_material) {
            material[g.first..g.first + g.len()].fill(m);
        }
        material
    }

    /// Consecutive runs of charts holding at most `max_texels` texels each (a chart larger
    /// than that is a run of its own): the units in which diffuse maps are stored and
    /// streamed, so that their number follows the texels, not the polygon count. Each run's
    /// texels are one contiguous range of the atlas.
    pub fn chunks(&self, max_texels: usize) -> Vec<std::ops::Range<u32>> {
        let mut chunks = Vec::new();
        let (mut start, mut texels) = (0usize, 0usize);
        for (c, g) in self.charts.iter().enumerate() {
            if c > start && texels + g.len() > max_texels {
                chunks.push(start as u32..c as u32);
                start = c;
                texels = 0;
            }
            texels += g.len();
        }
        if start < self.charts.len() {
            chunks.push(start as u32..self.charts.len() as u32);
        }
        chunks
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `index` is the texel whose cell `[s, s+1) × [t, t+1)` holds the coordinates, clamped
    /// onto the grid: the same as flooring first, for every float, edge cases included.
    #[test]
    fn a_texel_index_is_the_floored_coordinates_clamped() {
        let grid = TexelGrid {
            origin: DVec3::ZERO,
            axis_u: DVec3::X,
            axis_v: DVec3::Y,
            texel: 0.5,
            width: 7,
            height: 5,
            first: 100,
        };
        let floored = |c: DVec2| {
            let s = (c.x.floor().max(0.0) as u32).min(grid.width - 1);
            let t = (c.y.floor().max(0.0) as u32).min(grid.height - 1);
            grid.first + (t * grid.width + s) as usize
        };
        let mut values = vec![
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            -0.0,
            0.0,
            -1e-300,
            1e-300,
            f64::MAX,
            -f64::MAX,
            4.0e9,
            -4.0e9,
        ];
        values.extend((-40..=120).map(|k| k as f64 * 0.0625));
        values.extend((0..=8).flat_map(|k| [k as f64, (k as f64).next_down(), (k as f64).next_up()]));
        for &x in &values {
            for &y in &values {
                let c = DVec2::new(x, y);
                assert_eq!(grid.index(c), floored(c), "{c:?}");
            }
        }
        assert_eq!(grid.index(DVec2::new(2.99, 1.0)), 100 + 7 + 2);
    }
}
