//! Exact direct light: the field's own direct part converges to it, and
//! swapping it in keeps the rest of the field (indirect light) intact.

mod common;

use common::*;
use glam::DVec3;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::{Bvh, Camera, compare};

/// A lamp over a floor with a box-like blocker casting a shadow, and a wall.
fn shadow_scene() -> vlf_core::scene::Scene {
    let lamp = rect(
        DVec3::new(0.0, 0.6, 0.0),
        DVec3::X * 0.15,
        DVec3::Z * 0.15,
        -DVec3::Y,
        1,
    );
    let floor = rect(DVec3::new(0.0, -0.4, 0.0), DVec3::X * 0.6, DVec3::Z * 0.6, DVec3::Y, 0);
    let wall = rect(DVec3::new(0.0, 0.0, -0.6), DVec3::X * 0.6, DVec3::Y * 0.4, DVec3::Z, 0);
    let blocker = rect(
        DVec3::new(0.2, -0.1, 0.1),
        DVec3::X * 0.12,
        DVec3::Z * 0.12,
        DVec3::Y,
        0,
    );
    let blocker_under = rect(
        DVec3::new(0.2, -0.1001, 0.1),
        DVec3::X * 0.12,
        DVec3::Z * 0.12,
        -DVec3::Y,
        0,
    );
    scene(
        vec![lamp, floor, wall, blocker, blocker_under],
        vec![material("white", 0.6, 0.0), material("lamp", 0.0, 1.0)],
    )
}

fn options(l: usize, n: u32, iterations: u32) -> Options {
    Options {
        directions: l,
        grid: GridSize::new(n, 8).unwrap(),
        stop: Stop::Iterations(iterations),
        texel_cells: 2.0,
        ..Options::default()
    }
}

/// The field after one iteration and after `iterations`.
fn fields(l: usize, n: u32, iterations: u32) -> (LightField, LightField) {
    let mut p = Propagation::new(shadow_scene(), options(l, n, iterations)).unwrap();
    p.step(|_| {});
    let first = p.field_now();
    p.run(|_| {});
    (first, p.into_field())
}

/// Mean over the covered texels of the floor and wall of |D_t − ρ/π·E(centre)|,
/// relative to the mean exact value.
fn direct_part_error(l: usize, n: u32) -> f64 {
    let (first, mut last) = fields(l, n, 1);
    last.use_exact_direct(&first, 1024).unwrap();
    let bvh = Bvh::build(&last.scene);
    let (mut diff, mut sum) = (0.0, 0.0);
    for surface in [1, 2] {
        let g = first.atlas.grid(surface);
        for y in 0..g.height {
            for x in 0..g.width {
                let t = g.first + (y * g.width + x) as usize;
                if !first.covered[t] {
                    continue;
                }
                let p = g.origin + g.axis_u * ((x as f64 + 0.5) * g.texel) + g.axis_v * ((y as f64 + 0.5) * g.texel);
                let field = first.radiance_at(surface, p)[0];
                let exact = last.diffuse_radiance_at(&bvh, surface, p)[0];
                diff += (field - exact).abs();
                sum += exact;
            }
        }
    }
    diff / sum
}

#[test]
fn the_fields_direct_light_converges_to_the_exact_one() {
    let coarse = direct_part_error(33, 32);
    let fine = direct_part_error(513, 64);
    // Measured: 1.29 at l = 33, N = 32; 0.156 at 513, 64; 0.061 at 2049, 128.
    assert!(fine < 0.3 * coarse, "coarse {coarse}, fine {fine}");
    assert!(fine < 0.2, "fine {fine}");
}

#[test]
fn exact_direct_keeps_the_indirect_light_of_the_field() {
    // After one iteration the field is direct light only: with it exchanged
    // for the exact one, a surface the lamp cannot see (the blocker's
    // underside) stays black, as in the field.
    let (first, mut last) = fields(129, 32, 1);
    last.use_exact_direct(&first, 64).unwrap();
    let bvh = Bvh::build(&last.scene);
    let under = DVec3::new(0.2, -0.1001, 0.1);
    assert_eq!(last.diffuse_radiance_at(&bvh, 4, under), [0.0; 3]);
    // After more iterations it has indirect light (from the floor), which the
    // exchange keeps: L − D + exact is the field's value where D = 0.
    let (first, mut last) = fields(129, 32, 4);
    let field_value = last.radiance_at(4, under);
    assert!(field_value[0] > 0.0);
    last.use_exact_direct(&first, 64).unwrap();
    let exact = last.diffuse_radiance_at(&bvh, 4, under);
    assert!(
        (exact[0] - field_value[0]).abs() < 1e-12 * field_value[0].max(1.0),
        "{exact:?} vs {field_value:?}"
    );
}

#[test]
fn exact_direct_renders_closer_to_the_fine_field_than_the_coarse_field_does() {
    // A coarse field with exact direct light against a coarse field without,
    // both measured against a fine field with exact direct light: exact
    // direct light removes most of the coarse field's error (sharp shadow).
    let camera = Camera::new(
        DVec3::new(0.0, 0.3, 0.9),
        DVec3::new(0.0, -0.3, 0.0),
        DVec3::Y,
        60.0,
        64,
        48,
    )
    .unwrap();
    let mode = SpecularMode::Rays;
    let (first, mut fine) = fields(513, 128, 3);
    fine.use_exact_direct(&first, 256).unwrap();
    let reference = fine.render(&camera, 2, mode);
    let (first, mut coarse) = fields(33, 32, 3);
    let plain = coarse.render(&camera, 2, mode);
    coarse.use_exact_direct(&first, 256).unwrap();
    let exact = coarse.render(&camera, 2, mode);
    let e_plain = compare::compare(&plain, &reference, 8, compare::Pixels::default()).unwrap();
    let e_exact = compare::compare(&exact, &reference, 8, compare::Pixels::default()).unwrap();
    assert!(
        e_exact.relative_rmse < 0.6 * e_plain.relative_rmse,
        "exact {e_exact:?}, plain {e_plain:?}"
    );
}

#[test]
fn a_mismatched_first_iteration_is_refused() {
    let (first, _) = fields(33, 32, 1);
    let (_, mut other) = fields(129, 32, 1);
    assert!(other.use_exact_direct(&first, 16).is_err());
    let (first, mut last) = fields(33, 32, 1);
    assert!(last.use_exact_direct(&first, 0).is_err());
}
