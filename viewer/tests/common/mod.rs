//! What the viewer's GPU tests and benches share: an adapter (or a skip), a bundled scene's
//! field and the README's viewpoint.

use glam::DVec3;
use std::path::Path;
use vlf_core::field::LightField;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::Camera;
use vlf_core::scene::{ImportOptions, load_obj};
use vlf_viewer::Gpu;

/// The adapter, or `None` (the test skips) where there is none and `VLF_REQUIRE_GPU` is unset;
/// CI installs lavapipe and sets it, so there a missing adapter fails the test.
pub fn gpu() -> Option<Gpu> {
    match Gpu::new() {
        Ok(gpu) => {
            eprintln!("GPU: {}", gpu.describe());
            Some(gpu)
        }
        Err(e) if std::env::var_os("VLF_REQUIRE_GPU").is_none() => {
            eprintln!("skipped: {e}");
            None
        }
        Err(e) => panic!("VLF_REQUIRE_GPU is set but {e}"),
    }
}

/// A bundled scene propagated with `directions` on a 32 × 32 grid (tiles of 8) for
/// `iterations`.
#[allow(dead_code)] // not every test binary uses both
pub fn bundled_field(scene: &str, directions: usize, iterations: u32) -> LightField {
    bundled_field_with_texel(scene, directions, iterations, 1.0)
}

/// [`bundled_field`] with texels of `texel_cells` ray spacings.
#[allow(dead_code)] // not every test binary uses both
pub fn bundled_field_with_texel(scene: &str, directions: usize, iterations: u32, texel_cells: f64) -> LightField {
    let mut p = bundled_propagation(scene, directions, iterations, texel_cells);
    p.run(|_| {});
    p.into_field()
}

/// [`bundled_field`] after one iteration and after `iterations`, with the final field shading
/// with exact direct light (`samples` points per emitter).
#[allow(dead_code)] // not every test binary uses both
pub fn bundled_field_exact(scene: &str, directions: usize, iterations: u32, samples: u32) -> LightField {
    let (first, mut field) = bundled_first_and_last(scene, directions, iterations, 1.0);
    field.use_exact_direct(&first, samples).expect("exact direct light");
    field
}

/// [`bundled_field_with_texel`] after one iteration (snapshot 1) and after `iterations`.
#[allow(dead_code)] // not every test binary uses both
pub fn bundled_first_and_last(
    scene: &str,
    directions: usize,
    iterations: u32,
    texel_cells: f64,
) -> (LightField, LightField) {
    let mut p = bundled_propagation(scene, directions, iterations, texel_cells);
    p.step(|_| {});
    let first = p.field_now();
    p.run(|_| {});
    (first, p.into_field())
}

fn bundled_propagation(scene: &str, directions: usize, iterations: u32, texel_cells: f64) -> Propagation {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(scene);
    let (scene, _) = load_obj(&path, &ImportOptions::default()).expect("bundled scene");
    let options = Options {
        directions,
        grid: GridSize::new(32, 8).expect("grid"),
        stop: Stop::Iterations(iterations),
        texel_cells,
        ..Options::default()
    };
    Propagation::new(scene, options).expect("propagation")
}

/// The README's view of the bundled scenes (from the open side of the box, 39° vertically), at
/// `width × height`.
#[allow(dead_code)] // not every test binary uses it
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
