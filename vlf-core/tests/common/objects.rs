//! Moving objects and fields to put them in, for the dynamic-object tests.

use super::{closed_box, material};
use glam::DVec3;
use vlf_core::dynamic::DynamicObject;
use vlf_core::field::LightField;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::Material;

/// A furnace (every wall emits Le = 1 and reflects ρ = 0.5) after `k` iterations: uniform
/// radiance `Le·(1 − ρ^(k+1))/(1 − ρ)` in every texel, to 1e-5.
pub fn furnace(k: u32) -> (LightField, f64) {
    let (_, field, l) = furnace_with_first(k);
    (field, l)
}

/// [`furnace`], with the field after its first iteration before it (what exact direct light
/// needs).
pub fn furnace_with_first(k: u32) -> (LightField, LightField, f64) {
    let (rho, le) = (0.5, 1.0);
    let scene = closed_box(
        0.55,
        2,
        &[0, 1, 2, 3, 4, 5],
        vec![material("unused", rho, 0.0), material("glow", rho, le)],
    );
    let options = Options {
        directions: 129,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(k),
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    p.step(|_| {});
    let mut first = p.field_now();
    p.run(|_| {});
    let mut field = p.into_field();
    // The propagated furnace is uniform to its walls' counting error (each wall emits its true
    // power, `Propagation::emission_scale`: a few 0.1 % here, see tests/energy.rs); what these
    // tests measure is the gather, so they read the furnace's exact radiance, everywhere.
    let after = |iterations: i32| le * (1.0 - rho.powi(iterations + 1)) / (1.0 - rho);
    let uniform = |field: &mut LightField, l: f64| field.radiance.iter_mut().for_each(|t| *t = [l as f32; 3]);
    uniform(&mut first, after(1));
    uniform(&mut field, after(k as i32));
    (first, field, after(k as i32))
}

/// The two triangles of the quad `c ± a ± b`, facing `a × b`.
pub fn quad(c: DVec3, a: DVec3, b: DVec3) -> [[DVec3; 3]; 2] {
    let (p0, p1, p2, p3) = (c - a - b, c + a - b, c + a + b, c - a + b);
    [[p0, p1, p2], [p0, p2, p3]]
}

/// A cube of half-size `h` around `c`, facing out.
pub fn cube(name: &str, c: DVec3, h: f64, rho: f64) -> DynamicObject {
    let mut triangles = Vec::new();
    for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
        let u = if axis == DVec3::X {
            DVec3::Y
        } else if axis == DVec3::Y {
            DVec3::Z
        } else {
            DVec3::X
        };
        let v = axis.cross(u);
        triangles.extend(quad(c + axis * h, u * h, v * h));
        triangles.extend(quad(c - axis * h, v * h, u * h));
    }
    DynamicObject::uniform(name, triangles, Material::grey(name, rho))
}
