//! Albedo textures: a diffuse reflectance that varies over a surface.
//!
//! Scanned and modelled scenes carry their colour in images (glTF's `baseColorTexture`), not in
//! one value per material. Light transport needs the reflectance where light lands, and the
//! field stores radiosity per texel of a chart ([`crate::maps`]), so the image is averaged over
//! each texel's footprint ([`crate::maps::albedo`]) and a texel reflects `ρ_t` times what it
//! receives. Two things are needed for that, kept here:
//!
//! * [`Texture`]: the image, decoded to **linear** RGB (sRGB-encoded images are decoded by the
//!   importer: reflectance is linear), with its wrap modes;
//! * [`UvMap`]: where a surface's points fall in the image. Texture coordinates are given per
//!   vertex and interpolated linearly over a triangle, so on a planar polygon they are an affine
//!   function of the position, `uv(p) = uv₀ + (g_u·(p − p₀), g_v·(p − p₀))`. Stored that way,
//!   a triangle split at a T-junction or into convex pieces hands the same map to its pieces.

use super::Rgb;
use glam::{DVec2, DVec3};
use serde::{Deserialize, Serialize};

/// Largest texture edge kept in a scene: beyond it an image only adds detail far below a texel
/// (a texel is ~1/64 of the scene) and bytes to every stored job. Larger images are box-filtered
/// down by the importer.
pub const MAX_TEXTURE_SIZE: u32 = 1024;

/// How texture coordinates outside `[0, 1]` read the image (glTF's sampler wrap modes).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Wrap {
    Repeat,
    Clamp,
    Mirror,
}

impl Wrap {
    /// The texel index along an axis of `size` texels for integer texel coordinate `i`.
    fn index(self, i: i64, size: u32) -> usize {
        let n = size as i64;
        let j = match self {
            Wrap::Repeat => i.rem_euclid(n),
            Wrap::Clamp => i.clamp(0, n - 1),
            Wrap::Mirror => {
                let k = i.rem_euclid(2 * n);
                if k < n { k } else { 2 * n - 1 - k }
            }
        };
        j as usize
    }
}

/// A linear-RGB image with its wrap modes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Texture {
    /// Where it came from, for messages.
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Row-major from the image's top row (glTF's `v = 0`), linear RGB in `[0, 1]`.
    pub texels: Vec<[f32; 3]>,
    /// Wrap along u and along v.
    pub wrap: [Wrap; 2],
}

impl Texture {
    /// Checks what sampling relies on: a non-empty image of the stated size, values in `[0, 1]`.
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 || self.width > MAX_TEXTURE_SIZE || self.height > MAX_TEXTURE_SIZE {
            return Err(format!(
                "texture '{}' is {} × {} (1 to {MAX_TEXTURE_SIZE} per side)",
                self.name, self.width, self.height
            ));
        }
        if self.texels.len() != self.width as usize * self.height as usize {
            return Err(format!(
                "texture '{}' holds {} texels for {} × {}",
                self.name,
                self.texels.len(),
                self.width,
                self.height
            ));
        }
        if let Some(bad) = self.texels.iter().flatten().find(|c| !(0.0..=1.0).contains(*c)) {
            return Err(format!("texture '{}' holds {bad}, outside [0, 1]", self.name));
        }
        Ok(())
    }

    /// Bilinear sample at texture coordinates `uv` (`u` right, `v` down, texel centres at
    /// `(i + ½)/width`), as glTF samples a linear-filtered texture.
    pub fn sample(&self, uv: DVec2) -> Rgb {
        // Within ±2⁵², where every f64 is a whole number (so the weights below are 0 there): a
        // coordinate far beyond the image, or one whose product with the size overflows to ∞,
        // reads a texel of the image, never NaN or an index that overflows.
        const FAR: f64 = (1u64 << 52) as f64;
        let x = (uv.x * self.width as f64 - 0.5).clamp(-FAR, FAR);
        let y = (uv.y * self.height as f64 - 0.5).clamp(-FAR, FAR);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let at = |i: i64, j: i64| {
            let c = self.texels
                [self.wrap[1].index(j, self.height) * self.width as usize + self.wrap[0].index(i, self.width)];
            [c[0] as f64, c[1] as f64, c[2] as f64]
        };
        let (a, b, c, d) = (at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1));
        std::array::from_fn(|k| (a[k] * (1.0 - fx) + b[k] * fx) * (1.0 - fy) + (c[k] * (1.0 - fx) + d[k] * fx) * fy)
    }

    /// The mean over the whole image.
    pub fn mean(&self) -> Rgb {
        let mut sum = [0.0f64; 3];
        for c in &self.texels {
            for k in 0..3 {
                sum[k] += c[k] as f64;
            }
        }
        sum.map(|s| s / self.texels.len() as f64)
    }
}

/// Texture coordinates over a planar surface: `uv(p) = uv₀ + (g_u·(p − p₀), g_v·(p − p₀))`
/// (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct UvMap {
    pub p0: DVec3,
    pub uv0: DVec2,
    /// Gradients of u and of v, in the surface's plane.
    pub grad_u: DVec3,
    pub grad_v: DVec3,
}

impl UvMap {
    /// The affine map that takes triangle `p`'s corners to `uv`. `None` for a degenerate
    /// triangle or non-finite coordinates.
    pub fn from_triangle(p: [DVec3; 3], uv: [DVec2; 3]) -> Option<UvMap> {
        // With e1 = p1 − p0, e2 = p2 − p0 and the Gram matrix G of (e1, e2), the gradient of a
        // function f that is linear over the triangle is g = [e1 e2] G⁻¹ (f1 − f0, f2 − f0).
        let (e1, e2) = (p[1] - p[0], p[2] - p[0]);
        let (a, b, c) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
        let det = a * c - b * b;
        if !(det.is_finite() && det > 1e-300 && uv.iter().all(|t| t.is_finite())) {
            return None;
        }
        let gradient = |f1: f64, f2: f64| {
            let x = (c * f1 - b * f2) / det;
            let y = (a * f2 - b * f1) / det;
            e1 * x + e2 * y
        };
        let (du, dv) = (uv[1] - uv[0], uv[2] - uv[0]);
        Some(UvMap {
            p0: p[0],
            uv0: uv[0],
            grad_u: gradient(du.x, dv.x),
            grad_v: gradient(du.y, dv.y),
        })
    }

    /// Texture coordinates of point `p` of the surface.
    pub fn at(&self, p: DVec3) -> DVec2 {
        let d = p - self.p0;
        self.uv0 + DVec2::new(self.grad_u.dot(d), self.grad_v.dot(d))
    }

    /// The same map for positions moved into the VLF frame by `x ↦ (x − center)·scale`.
    pub fn scaled(&self, center: DVec3, scale: f64) -> UvMap {
        UvMap {
            p0: (self.p0 - center) * scale,
            uv0: self.uv0,
            grad_u: self.grad_u / scale,
            grad_v: self.grad_v / scale,
        }
    }

    pub fn is_finite(&self) -> bool {
        self.p0.is_finite() && self.uv0.is_finite() && self.grad_u.is_finite() && self.grad_v.is_finite()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_map_interpolates_the_corners_and_survives_scaling() {
        let p = [
            DVec3::new(0.3, -1.0, 2.0),
            DVec3::new(2.0, 0.5, 1.0),
            DVec3::new(-0.5, 1.5, 0.2),
        ];
        let uv = [DVec2::new(0.1, 0.9), DVec2::new(0.8, 0.7), DVec2::new(0.4, -0.3)];
        let map = UvMap::from_triangle(p, uv).unwrap();
        for k in 0..3 {
            assert!((map.at(p[k]) - uv[k]).length() < 1e-12);
        }
        let centroid = (p[0] + p[1] + p[2]) / 3.0;
        assert!((map.at(centroid) - (uv[0] + uv[1] + uv[2]) / 3.0).length() < 1e-12);
        let (center, scale) = (DVec3::new(1.0, 2.0, -3.0), 0.37);
        let moved = map.scaled(center, scale);
        assert!((moved.at((centroid - center) * scale) - map.at(centroid)).length() < 1e-12);
        assert!(UvMap::from_triangle([p[0], p[1], p[0]], uv).is_none());
    }

    #[test]
    fn bilinear_sampling_and_wrap_modes() {
        let t = Texture {
            name: "t".into(),
            width: 2,
            height: 1,
            texels: vec![[0.0; 3], [1.0; 3]],
            wrap: [Wrap::Repeat, Wrap::Clamp],
        };
        t.validate().unwrap();
        // Texel centres read their texel; halfway between reads the mean.
        assert_eq!(t.sample(DVec2::new(0.25, 0.5))[0], 0.0);
        assert_eq!(t.sample(DVec2::new(0.75, 0.5))[0], 1.0);
        assert!((t.sample(DVec2::new(0.5, 0.5))[0] - 0.5).abs() < 1e-12);
        // Repeat: u = 1.25 is u = 0.25; clamp in v reads the only row.
        assert_eq!(t.sample(DVec2::new(1.25, 7.0))[0], 0.0);
        let mirror = Texture {
            wrap: [Wrap::Mirror, Wrap::Clamp],
            ..t.clone()
        };
        assert_eq!(mirror.sample(DVec2::new(1.25, 0.5))[0], 1.0);
        assert!((t.mean()[0] - 0.5).abs() < 1e-12);
        // Coordinates far beyond any texel (finite, so a file may hold them; times the width,
        // some overflow to ∞) sample a texel of the image in every wrap mode: no NaN, no
        // overflowing index.
        for wrap in [Wrap::Repeat, Wrap::Clamp, Wrap::Mirror] {
            let t = Texture {
                wrap: [wrap, wrap],
                ..t.clone()
            };
            let far = [
                DVec2::new(1e30, 0.5),
                DVec2::new(-1e30, -1e30),
                DVec2::new(0.5, f64::MAX),
                DVec2::new(f64::MAX, 0.5),
                DVec2::new(-f64::MAX, f64::MAX),
            ];
            for uv in far {
                let c = t.sample(uv)[0];
                assert!((0.0..=1.0).contains(&c), "{wrap:?} at {uv}: {c}");
            }
        }
        let bad = Texture {
            texels: vec![[0.0; 3], [1.5; 3]],
            ..t
        };
        assert!(bad.validate().is_err());
    }
}
