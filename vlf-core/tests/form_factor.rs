//! Analytic case: irradiance under a uniformly emitting square.

mod common;

use common::*;
use glam::DVec3;
use std::f64::consts::PI;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;

/// Point-to-rectangle form factor for a point below one corner of an `a × b`
/// rectangle parallel to its plane at distance `c` (Howell's catalogue, B-3).
fn corner_form_factor(a: f64, b: f64, c: f64) -> f64 {
    let (x, y) = (a / c, b / c);
    let (sx, sy) = ((1.0 + x * x).sqrt(), (1.0 + y * y).sqrt());
    (x / sx * (y / sx).atan() + y / sy * (x / sy).atan()) / (2.0 * PI)
}

/// Relative errors (of the mean, and RMS pointwise) of the radiance about the
/// receiver's centre after one bounce.
fn centre_error(l: usize, n: u32, m: u32) -> (f64, f64) {
    let (side, gap, le, rho) = (0.9, 0.5, 1.0, 0.5);
    let h = side / 2.0;
    let emitter = rect(
        DVec3::new(0.0, gap / 2.0, 0.0),
        DVec3::X * h,
        DVec3::Z * h,
        -DVec3::Y,
        1,
    );
    let receiver = rect(
        DVec3::new(0.0, -gap / 2.0, 0.0),
        DVec3::X * h,
        DVec3::Z * h,
        DVec3::Y,
        0,
    );
    let scene = scene(
        vec![emitter, receiver],
        vec![material("floor", rho, 0.0), material("lamp", 0.0, le)],
    );
    let options = Options {
        directions: l,
        grid: GridSize::new(n, m).unwrap(),
        stop: Stop::Iterations(1),
        texel_cells: 2.0,
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    p.run(|_| {});
    let field = p.into_field();
    // Irradiance at a point under the square: π·L·F, with F the sum of the
    // four corner factors of the sub-rectangles meeting above the point;
    // reflected radiance ρ·E/π. Compare means over a disc of sample points
    // about the centre (look-ups bilinear), which averages out the
    // point-sampling noise of single texels.
    let centre = DVec3::new(0.0, -gap / 2.0, 0.0);
    let (mut measured, mut expected, mut square_error) = (0.0, 0.0, 0.0);
    let count = 256;
    for k in 0..count {
        let a = k as f64 * 2.399963; // golden-angle spiral
        let r = 0.2 * ((k as f64 + 0.5) / count as f64).sqrt();
        let (x, z) = (r * a.cos(), r * a.sin());
        let got = field.radiance_at(1, centre + DVec3::new(x, 0.0, z))[0];
        let f = corner_form_factor(h - x, h - z, gap)
            + corner_form_factor(h + x, h - z, gap)
            + corner_form_factor(h - x, h + z, gap)
            + corner_form_factor(h + x, h + z, gap);
        let want = rho * le * f;
        measured += got / count as f64;
        expected += want / count as f64;
        square_error += ((got - want) / want).powi(2) / count as f64;
    }
    ((measured - expected).abs() / expected, square_error.sqrt())
}

#[test]
fn irradiance_under_a_square_matches_the_form_factor() {
    let errors: Vec<(f64, f64)> = [(129, 32, 8), (513, 64, 8), (2049, 128, 16)]
        .iter()
        .map(|&(l, n, m)| centre_error(l, n, m))
        .collect();
    println!("(mean, rms) relative error at l/N = 129/32, 513/64, 2049/128: {errors:.4?}");
    for (mean, rms) in &errors {
        assert!(*mean < 0.03, "mean error {mean}");
        assert!(*rms < 0.1, "pointwise error {rms}");
    }
    assert!(errors[2].0 < 0.005, "fine mean error {}", errors[2].0);
    assert!(errors[2].1 < 0.02, "fine pointwise error {}", errors[2].1);
    assert!(
        errors[2].1 < errors[0].1,
        "pointwise error did not fall as l and N grew: {errors:?}"
    );
}
