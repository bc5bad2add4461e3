//! Texel grids on surfaces: where diffuse radiosity lives.
//!
//! Diffuse light is view-independent, so a diffuse surface's outgoing radiance
//! is stored once, as a map of texels on its plane (the paper's Current / Next
//! / Total texture maps), not per direction. Each surface gets a rectangular
//! grid of square texels covering its bounding rectangle in a frame of its
//! plane; all grids are laid end to end in one global texel array (an
//! *atlas*), so per-texel quantities are plain `Vec`s indexed by
//! [`TexelGrid::first`] + local index.
//!
//! Texels are *discrete areas*: a texel's area as the light field sees it is
//! `A_t = T_t / π`, where `T_t = Σ_ω Δω · n_t(ω)` sums, over all directions,
//! the solid-angle weight times the number of rays that cross the texel (in
//! units of the ray cell area). See [`crate::propagate`] for why this makes
//! shooting exactly power-conserving.

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
    #[inline]
    pub fn index(&self, c: DVec2) -> usize {
        let s = (c.x.floor().max(0.0) as u32).min(self.width - 1);
        let t = (c.y.floor().max(0.0) as u32).min(self.height - 1);
        self.first + (t * self.width + s) as usize
    }

    pub fn len(&self) -> usize {
        (self.width * self.height) as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// All texel grids of a scene, one per surface, in surface order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TexelAtlas {
    pub grids: Vec<TexelGrid>,
    pub texels: usize,
}

impl TexelAtlas {
    /// Upper bound on the atlas size: 2²⁸ texels is already several GiB of maps.
    pub const MAX_TEXELS: usize = 1 << 28;

    /// Lays out grids of texel edge `texel` (VLF units) on every surface of
    /// a field whose rays are `ray_spacing` apart.
    ///
    /// Texel boundaries are placed on the lattice `−1 + (m + φ)·ray_spacing`
    /// (φ = 1/π) along each grid axis. Ray centres of axis-aligned directions
    /// lie at `−1 + (j + ½)·ray_spacing`, and axis-aligned walls are the rule
    /// in real scenes: were a texel boundary to fall exactly on a ray centre,
    /// which texel the ray lands in would depend on the last bit of rounding
    /// (so scaling or moving the scene would change the result). With the
    /// irrational offset no boundary coincides with a centre for any simple
    /// texel size.
    pub fn new(scene: &Scene, texel: f64, ray_spacing: f64) -> crate::Result<Self> {
        const PHI: f64 = std::f64::consts::FRAC_1_PI;
        if !(texel.is_finite() && texel > 0.0 && ray_spacing.is_finite() && ray_spacing > 0.0) {
            return Err(crate::Error::Parameter(format!(
                "texel size must be positive and finite, got {texel}"
            )));
        }
        let snap = |world: f64| -1.0 + (((world + 1.0) / ray_spacing - PHI).floor() + PHI) * ray_spacing;
        let mut grids = Vec::with_capacity(scene.surfaces.len());
        let mut first = 0usize;
        for surface in &scene.surfaces {
            let v0 = surface.vertices[0];
            let count = surface.vertices.len();
            let edges: Vec<DVec3> = (0..count)
                .map(|k| surface.vertices[(k + 1) % count] - surface.vertices[k])
                .collect();
            // The longest edge as u axis keeps slivers' grids tight; among
            // edges equal to rounding (a square) the first, so the choice
            // does not depend on the scene's scale.
            let longest = edges.iter().map(|e| e.length()).fold(0.0, f64::max);
            let axis_u = edges
                .iter()
                .find(|e| e.length() >= longest * (1.0 - 1e-9))
                .map_or(DVec3::X, |e| e.normalize());
            let axis_v = surface.normal.cross(axis_u);
            let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
            for &p in &surface.vertices {
                let c = DVec2::new((p - v0).dot(axis_u), (p - v0).dot(axis_v));
                lo = lo.min(c);
                hi = hi.max(c);
            }
            // Snap the grid's corner (in world coordinates along each axis).
            let base = DVec2::new(v0.dot(axis_u), v0.dot(axis_v));
            let corner = DVec2::new(snap(base.x + lo.x), snap(base.y + lo.y)) - base;
            let extent = hi - corner;
            // A polygon whose extent is a whole number of texels up to
            // rounding does not get an extra, empty row.
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
                origin: v0 + axis_u * corner.x + axis_v * corner.y,
                axis_u,
                axis_v,
                texel,
                width: width as u32,
                height: height as u32,
                first,
            });
            first += count;
        }
        Ok(TexelAtlas { grids, texels: first })
    }

    /// The surface owning each texel.
    pub fn owners(&self) -> Vec<u32> {
        let mut owner = vec![0u32; self.texels];
        for (s, g) in self.grids.iter().enumerate() {
            owner[g.first..g.first + g.len()].fill(s as u32);
        }
        owner
    }
}
