//! A pinhole camera, given in the scene's own units.
//!
//! Users place the camera where they modelled the scene (the OBJ's units),
//! not in the normalised VLF frame, so [`Camera`] stays in scene units and
//! the renderer converts its rays with [`crate::scene::Normalisation`].
//! Since that conversion is a similarity, directions and angles are the same
//! in both frames.
//!
//! Pixel coordinates are continuous: `px` grows to the right and `py`
//! **downwards** from the top-left corner of the image, so pixel `(i, j)`
//! covers `[i, i + 1) × [j, j + 1)` and its centre is `(i + 0.5, j + 0.5)`.
//! The field of view `fovy_degrees` is the full vertical angle, from the top
//! edge of the image to the bottom one; the horizontal one follows from the
//! aspect ratio `width / height` (square pixels).

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Largest accepted image side, in pixels.
pub const MAX_SIZE: u32 = 16384;

/// A pinhole camera in scene units. Build it with [`Camera::new`], which
/// validates it; the fields are public for reading and serialisation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Position of the pinhole.
    pub eye: DVec3,
    /// A point the camera looks at: it appears at the centre of the image.
    pub target: DVec3,
    /// Approximate up direction; only its component orthogonal to the view
    /// direction matters.
    pub up: DVec3,
    /// Full vertical field of view, in degrees, in `(0, 180)`.
    pub fovy_degrees: f64,
    /// Image width in pixels, `1..=16384`.
    pub width: u32,
    /// Image height in pixels, `1..=16384`.
    pub height: u32,
}

/// The camera's orthonormal frame and image-plane scale.
struct Frame {
    forward: DVec3,
    right: DVec3,
    up: DVec3,
    /// `tan(fovy / 2)`: half the image height at unit distance.
    tan_half: f64,
    aspect: f64,
}

impl Camera {
    /// A validated camera: all values finite, `eye != target`, `up` not
    /// parallel to the view direction, `0 < fovy_degrees < 180` and
    /// `1 <= width, height <= 16384`. Violations give [`Error::Parameter`].
    pub fn new(eye: DVec3, target: DVec3, up: DVec3, fovy_degrees: f64, width: u32, height: u32) -> Result<Camera> {
        for (name, v) in [("eye", eye), ("target", target), ("up", up)] {
            if !v.is_finite() {
                return Err(Error::Parameter(format!("camera {name} must be finite, got {v}")));
            }
        }
        if !fovy_degrees.is_finite() || fovy_degrees <= 0.0 || fovy_degrees >= 180.0 {
            return Err(Error::Parameter(format!(
                "camera vertical field of view must be strictly between 0 and 180 degrees, got {fovy_degrees}"
            )));
        }
        for (name, v) in [("width", width), ("height", height)] {
            if !(1..=MAX_SIZE).contains(&v) {
                return Err(Error::Parameter(format!(
                    "image {name} must be between 1 and {MAX_SIZE} pixels, got {v}"
                )));
            }
        }
        let view = target - eye;
        // `normalize_or_zero` also catches a difference that overflows.
        let forward = view.normalize_or_zero();
        if forward == DVec3::ZERO || !forward.is_finite() {
            return Err(Error::Parameter(format!(
                "camera eye and target must differ, both are {eye}"
            )));
        }
        let up_unit = up.normalize_or_zero();
        if up_unit == DVec3::ZERO || forward.cross(up_unit).length() < 1e-6 {
            return Err(Error::Parameter(format!(
                "camera up vector {up} must be non-zero and not parallel to the view direction {forward}"
            )));
        }
        Ok(Camera {
            eye,
            target,
            up,
            fovy_degrees,
            width,
            height,
        })
    }

    fn frame(&self) -> Frame {
        let forward = (self.target - self.eye).normalize();
        let right = forward.cross(self.up).normalize();
        let up = right.cross(forward);
        Frame {
            forward,
            right,
            up,
            tan_half: (0.5 * self.fovy_degrees.to_radians()).tan(),
            aspect: self.width as f64 / self.height as f64,
        }
    }

    /// The ray through the continuous pixel position `(px, py)` (see the
    /// module documentation): `(origin, unit direction)` in scene units.
    pub fn ray(&self, px: f64, py: f64) -> (DVec3, DVec3) {
        let f = self.frame();
        let x = (2.0 * px / self.width as f64 - 1.0) * f.tan_half * f.aspect;
        let y = (1.0 - 2.0 * py / self.height as f64) * f.tan_half;
        let dir = (f.forward + x * f.right + y * f.up).normalize();
        (self.eye, dir)
    }

    /// The continuous pixel position where the point `p` (scene units)
    /// appears, or `None` when it is not in front of the camera. The
    /// position may lie outside the image. Inverse of [`Camera::ray`].
    pub fn project(&self, p: DVec3) -> Option<(f64, f64)> {
        let f = self.frame();
        let d = p - self.eye;
        let z = d.dot(f.forward);
        if z.is_nan() || z <= 0.0 {
            return None;
        }
        let x = d.dot(f.right) / z;
        let y = d.dot(f.up) / z;
        let px = (x / (f.tan_half * f.aspect) + 1.0) * 0.5 * self.width as f64;
        let py = (1.0 - y / f.tan_half) * 0.5 * self.height as f64;
        Some((px, py))
    }
}

/// Parses `"X,Y,Z"` (three finite numbers, spaces around them allowed).
pub fn parse_vec3(s: &str) -> Result<DVec3> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(Error::Parameter(format!(
            "expected a vector as X,Y,Z (three comma-separated numbers), got '{s}'"
        )));
    }
    let mut v = [0.0; 3];
    for (slot, (part, axis)) in v.iter_mut().zip(parts.iter().zip(["X", "Y", "Z"])) {
        let x: f64 = part
            .parse()
            .map_err(|_| Error::Parameter(format!("{axis} component '{part}' of '{s}' is not a number")))?;
        if !x.is_finite() {
            return Err(Error::Parameter(format!(
                "{axis} component '{part}' of '{s}' must be finite"
            )));
        }
        *slot = x;
    }
    Ok(DVec3::from_array(v))
}

/// Parses an image size `"WxH"` (e.g. `640x480`; `X` also accepted), each
/// side in `1..=16384`.
pub fn parse_size(s: &str) -> Result<(u32, u32)> {
    let t = s.trim();
    let Some((w, h)) = t.split_once(['x', 'X']) else {
        return Err(Error::Parameter(format!(
            "expected an image size as WxH (e.g. 640x480), got '{s}'"
        )));
    };
    let side = |part: &str, name: &str| -> Result<u32> {
        let v: u32 = part
            .trim()
            .parse()
            .map_err(|_| Error::Parameter(format!("image {name} '{part}' in '{s}' is not a positive integer")))?;
        if !(1..=MAX_SIZE).contains(&v) {
            return Err(Error::Parameter(format!(
                "image {name} must be between 1 and {MAX_SIZE} pixels, got {v} in '{s}'"
            )));
        }
        Ok(v)
    };
    Ok((side(w, "width")?, side(h, "height")?))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(width: u32, height: u32) -> Camera {
        Camera::new(
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(-2.0, 0.5, -1.0),
            DVec3::new(0.1, 1.0, 0.2),
            50.0,
            width,
            height,
        )
        .expect("valid camera")
    }

    fn angle(a: DVec3, b: DVec3) -> f64 {
        a.normalize().dot(b.normalize()).clamp(-1.0, 1.0).acos().to_degrees()
    }

    #[test]
    fn centre_ray_points_at_target() {
        for (w, h) in [(64, 48), (65, 33), (1, 1)] {
            let c = camera(w, h);
            let (o, d) = c.ray(w as f64 / 2.0, h as f64 / 2.0);
            assert_eq!(o, c.eye);
            assert!((d.length() - 1.0).abs() < 1e-12);
            assert!((d - (c.target - c.eye).normalize()).length() < 1e-12, "{d}");
        }
    }

    #[test]
    fn vertical_fov_and_aspect() {
        let c = camera(200, 100);
        let forward = c.target - c.eye;
        // Top and bottom edges (at the horizontal centre): half the fovy.
        let (_, top) = c.ray(100.0, 0.0);
        let (_, bottom) = c.ray(100.0, 100.0);
        assert!((angle(top, forward) - 25.0).abs() < 1e-9);
        assert!((angle(bottom, forward) - 25.0).abs() < 1e-9);
        assert!((angle(top, bottom) - 50.0).abs() < 1e-9);
        // py grows downwards: the top edge ray leans towards `up`.
        assert!(top.dot(c.up) > bottom.dot(c.up));
        // Left/right edges: atan(aspect × tan(fovy / 2)).
        let expected = (2.0 * 25f64.to_radians().tan()).atan().to_degrees();
        let (_, left) = c.ray(0.0, 50.0);
        let (_, right) = c.ray(200.0, 50.0);
        assert!((angle(left, forward) - expected).abs() < 1e-9);
        assert!((angle(right, forward) - expected).abs() < 1e-9);
        // px grows to the right: right = forward × up.
        let r = forward.cross(c.up);
        assert!(right.dot(r) > 0.0 && left.dot(r) < 0.0);
        // Square pixels: one pixel step spans the same angle both ways
        // near the centre.
        let (_, c0) = c.ray(100.0, 50.0);
        let (_, cx) = c.ray(101.0, 50.0);
        let (_, cy) = c.ray(100.0, 51.0);
        assert!((angle(c0, cx) - angle(c0, cy)).abs() < 1e-9);
    }

    #[test]
    fn project_inverts_ray() {
        let c = camera(320, 200);
        for (px, py) in [(0.5, 0.5), (160.0, 100.0), (319.5, 12.25), (3.0, 199.0), (-20.0, 250.0)] {
            let (o, d) = c.ray(px, py);
            for t in [0.1, 1.0, 37.0] {
                let (qx, qy) = c.project(o + t * d).expect("in front");
                assert!(
                    (qx - px).abs() < 1e-9 && (qy - py).abs() < 1e-9,
                    "({px}, {py}) → ({qx}, {qy})"
                );
            }
            assert_eq!(c.project(o - d), None);
        }
        assert_eq!(c.project(c.eye), None);
    }

    #[test]
    fn invalid_cameras_are_refused() {
        let ok = |e, t, u, f, w, h| Camera::new(e, t, u, f, w, h);
        let (e, t, u) = (DVec3::ZERO, DVec3::NEG_Z, DVec3::Y);
        assert!(ok(e, t, u, 60.0, 16384, 1).is_ok());
        let cases: Vec<(Result<Camera>, &str)> = vec![
            (
                ok(DVec3::new(f64::NAN, 0.0, 0.0), t, u, 60.0, 8, 8),
                "eye must be finite",
            ),
            (
                ok(e, DVec3::splat(f64::INFINITY), u, 60.0, 8, 8),
                "target must be finite",
            ),
            (
                ok(e, t, DVec3::new(0.0, f64::NAN, 0.0), 60.0, 8, 8),
                "up must be finite",
            ),
            (ok(e, e, u, 60.0, 8, 8), "eye and target must differ"),
            (ok(e, t, DVec3::Z, 60.0, 8, 8), "not parallel"),
            (ok(e, t, DVec3::ZERO, 60.0, 8, 8), "non-zero"),
            (ok(e, t, u, 0.0, 8, 8), "field of view"),
            (ok(e, t, u, 180.0, 8, 8), "field of view"),
            (ok(e, t, u, f64::NAN, 8, 8), "field of view"),
            (ok(e, t, u, 60.0, 0, 8), "width must be between 1 and 16384"),
            (ok(e, t, u, 60.0, 8, 16385), "height must be between 1 and 16384"),
        ];
        for (result, needle) in cases {
            match result {
                Err(Error::Parameter(m)) => assert!(m.contains(needle), "'{m}' lacks '{needle}'"),
                other => panic!("expected a parameter error with '{needle}', got {other:?}"),
            }
        }
    }

    #[test]
    fn parse_helpers() {
        assert_eq!(parse_vec3("1,2.5,-3").unwrap(), DVec3::new(1.0, 2.5, -3.0));
        assert_eq!(parse_vec3(" 0 , 1e2 ,-0.5 ").unwrap(), DVec3::new(0.0, 100.0, -0.5));
        assert_eq!(parse_size("640x480").unwrap(), (640, 480));
        assert_eq!(parse_size("1X16384").unwrap(), (1, 16384));
        let bad = [
            (parse_vec3("1,2").map(|_| ()), "X,Y,Z"),
            (parse_vec3("1,2,3,4").map(|_| ()), "X,Y,Z"),
            (parse_vec3("1,a,3").map(|_| ()), "Y component 'a'"),
            (parse_vec3("1,2,inf").map(|_| ()), "must be finite"),
            (parse_size("640").map(|_| ()), "WxH"),
            (parse_size("0x480").map(|_| ()), "width must be between 1 and 16384"),
            (parse_size("640x-1").map(|_| ()), "height '-1'"),
            (parse_size("640x20000").map(|_| ()), "height must be between"),
        ];
        for (result, needle) in bad {
            match result {
                Err(Error::Parameter(m)) => assert!(m.contains(needle), "'{m}' lacks '{needle}'"),
                other => panic!("expected a parameter error with '{needle}', got {other:?}"),
            }
        }
    }
}
