//! What the GPU benches share.

use glam::DVec3;
use vlf_core::render::Camera;

/// The README's view of the bundled scenes (from the open side of the box, 39° vertically), at
/// `width × height`.
pub fn readme_camera(width: u32, height: u32) -> Camera {
    Camera::new(
        DVec3::new(278.0, 273.0, -800.0),
        DVec3::new(278.0, 273.0, 0.0),
        DVec3::Y,
        39.0,
        width,
        height,
    )
    .expect("a valid camera")
}
