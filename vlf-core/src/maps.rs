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

    /// Lays out grids of texel edge `texel` (VLF units) on every surface.
    pub fn new(scene: &Scene, texel: f64) -> crate::Result<Self> {
        if !(texel.is_finite() && texel > 0.0) {
            return Err(crate::Error::Parameter(format!(
                "texel size must be positive and finite, got {texel}"
            )));
        }
        let mut grids = Vec::with_capacity(scene.surfaces.len());
        let mut first = 0usize;
        for surface in &scene.surfaces {
            let v0 = surface.vertices[0];
            // The longest edge as u axis keeps slivers' grids tight.
            let (a, b) = (0..surface.vertices.len())
                .map(|k| (surface.vertices[k], surface.vertices[(k + 1) % surface.vertices.len()]))
                .max_by(|x, y| (x.1 - x.0).length_squared().total_cmp(&(y.1 - y.0).length_squared()))
                .unwrap_or((v0, v0));
            let axis_u = (b - a).normalize();
            let axis_v = surface.normal.cross(axis_u);
            let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
            for &p in &surface.vertices {
                let c = DVec2::new((p - v0).dot(axis_u), (p - v0).dot(axis_v));
                lo = lo.min(c);
                hi = hi.max(c);
            }
            let extent = hi - lo;
            let width = ((extent.x / texel).ceil() as u64).max(1);
            let height = ((extent.y / texel).ceil() as u64).max(1);
            let count = width.saturating_mul(height) as usize;
            if count > Self::MAX_TEXELS || first + count > Self::MAX_TEXELS {
                return Err(crate::Error::Parameter(format!(
                    "texel size {texel:.3e} gives more than {} texels; choose a larger texel",
                    Self::MAX_TEXELS
                )));
            }
            // Centre the grid on the polygon's bounding rectangle.
            let pad = DVec2::new(width as f64 * texel - extent.x, height as f64 * texel - extent.y) * 0.5;
            let corner = lo - pad;
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
