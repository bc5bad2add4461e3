//! Dynamic objects on the GPU against the CPU reference (`vlf_core::dynamic`), on the bundled
//! scenes with cubes in them: the gather at points of a cube and around it (mirrors read
//! either way, objects blocking the gather), and whole views with objects, their shadows and
//! their images in mirrors. Lavapipe in CI.

mod common;

use common::{bundled_field, gpu};
use glam::DVec3;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::{DynamicObject, PlacedObject, Pose};
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::render::Bvh;
use vlf_core::scene::Material;
use vlf_viewer::{FieldRenderer, GpuGather};

/// A grey cube of half-size `h` (scene units) around `c`.
fn cube(c: DVec3, h: f64) -> DynamicObject {
    let grey = Material::grey("grey", 0.6);
    DynamicObject::cube("cube", c, h, 1, grey)
}

/// Two cubes in a bundled scene: one on the floor, one in the air.
fn two_cubes(field: &LightField) -> Vec<PlacedObject> {
    let n = field.scene.normalisation;
    [
        (DVec3::new(400.0, 51.0, 150.0), 50.0),
        (DVec3::new(170.0, 380.0, 260.0), 40.0),
    ]
    .map(|(c, h)| cube(c, h).place(&Pose::IDENTITY, &n).unwrap())
    .to_vec()
}

/// Points just off the cube's faces (normals out) and points around it, in the VLF frame.
fn points(field: &LightField, c: DVec3, h: f64) -> Vec<(DVec3, DVec3)> {
    let n = field.scene.normalisation;
    let mut out = Vec::new();
    for (k, normal) in [DVec3::X, -DVec3::X, DVec3::Y, DVec3::Z, -DVec3::Z]
        .into_iter()
        .enumerate()
    {
        let (u, v) = normal.any_orthonormal_pair();
        for j in 0..4 {
            let s = (j as f64 - 1.37) * 0.31 + 0.07 * k as f64;
            out.push((
                n.to_vlf(c + normal * (h * 1.001) + (u * s + v * (0.5 - s)) * h * 0.8),
                normal,
            ));
        }
    }
    for j in 0..12 {
        let a = 0.5 + j as f64;
        let at = c + DVec3::new(a.cos(), 0.3 * (j % 3) as f64 - 0.4, a.sin()) * (2.5 * h);
        out.push((n.to_vlf(at), DVec3::new(a.sin(), 0.8, -a.cos()).normalize()));
    }
    out
}

fn compare(scene: &str, c: DVec3, h: f64, modes: &[SpecularMode]) {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field(scene, 129, 3);
    let bvh = Bvh::build(&field.scene);
    let placed: Vec<PlacedObject> = vec![cube(c, h).place(&Pose::IDENTITY, &field.scene.normalisation).unwrap()];
    let points = points(&field, c, h);
    for &mode in modes {
        let cpu = Gatherer::with_directions(&field, &bvh, &placed, mode, 129).unwrap();
        let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
        let want: Vec<[f64; 3]> = points.iter().map(|&(p, n)| cpu.incident(p, n)).collect();
        let got = GpuGather::new(&gpu, &renderer, mode.into())
            .unwrap()
            .incident(&gpu, &points)
            .unwrap();
        let scale = want.iter().flatten().copied().fold(0.0, f64::max);
        assert!(scale > 0.0);
        let mut worst = 0.0f64;
        let mut total = 0.0;
        for (k, (g, w)) in got.iter().zip(&want).enumerate() {
            for c in 0..3 {
                let e = (g[c] - w[c]).abs() / scale;
                worst = worst.max(e);
                total += e;
                assert!(e < 1e-3, "{scene} {mode:?} point {k}: GPU {g:?}, CPU {w:?}");
            }
        }
        let mean = total / (3 * got.len()) as f64;
        println!("{scene} {mode:?}: GPU vs CPU gather, mean {mean:.2e}, worst {worst:.2e} of the brightest point");
        assert!(mean < 1e-4, "{mean}");
    }
}

#[test]
fn the_gpu_gathers_what_the_cpu_gathers() {
    compare(
        "cornell.obj",
        DVec3::new(420.0, 60.0, 120.0),
        50.0,
        &[SpecularMode::Rays],
    );
}

#[test]
fn the_gpu_gathers_mirrors_as_the_cpu_does() {
    compare(
        "mirrors.obj",
        DVec3::new(300.0, 250.0, 300.0),
        60.0,
        &[SpecularMode::Trace { depth: 3 }, SpecularMode::Rays],
    );
}

/// Without objects nothing blocks: a point inside where the cube would be gathers light.
#[test]
fn objects_block_the_gpu_gather() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field("cornell.obj", 33, 2);
    let c = DVec3::new(420.0, 60.0, 120.0);
    let placed = vec![
        cube(c, 50.0)
            .place(&Pose::IDENTITY, &field.scene.normalisation)
            .unwrap(),
    ];
    let inside = [(field.scene.normalisation.to_vlf(c), DVec3::Y)];
    let bvh = Bvh::build(&field.scene);
    let gather = |objects: &[PlacedObject]| {
        let cpu = Gatherer::new(&field, &bvh, objects, SpecularMode::Rays).unwrap();
        let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
        GpuGather::new(&gpu, &renderer, SpecularMode::Rays.into())
            .unwrap()
            .incident(&gpu, &inside)
            .unwrap()[0]
    };
    assert_eq!(
        gather(&placed),
        [0.0; 3],
        "inside the cube, the cube blocks every direction"
    );
    assert!(gather(&[])[1] > 0.0);
}

/// Pixels whose channels differ by more than `rel` of the larger value (and 10⁻⁶ absolute).
fn differing(a: &vlf_core::render::Image, b: &vlf_core::render::Image, rel: f32) -> usize {
    a.pixels
        .iter()
        .zip(&b.pixels)
        .filter(|(p, q)| (0..3).any(|c| (p[c] - q[c]).abs() > rel * p[c].abs().max(q[c].abs()) + 1e-6))
        .count()
}

/// A view with two cubes (one on the floor, one in the air) drawn by `render --gpu` and by the
/// CPU's `render_with_objects`: the same pixels but for a few at polygon edges, in the cubes,
/// their shadows and the mirrors; and the cubes change the view (their shadows darken it).
fn view_matches(scene: &str, modes: &[SpecularMode]) {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field(scene, 33, 3);
    let bvh = Bvh::build(&field.scene);
    let placed = two_cubes(&field);
    let camera = vlf_core::render::Camera::new(
        DVec3::new(278.0, 273.0, -800.0),
        DVec3::new(278.0, 273.0, 0.0),
        DVec3::Y,
        39.0,
        32,
        32,
    )
    .unwrap();
    for &mode in modes {
        let cpu = Gatherer::with_directions(&field, &bvh, &placed, mode, 33)
            .unwrap()
            .with_shadow_samples(32);
        let want = vlf_core::dynamic::view::render_with_objects(&cpu, &bvh, &camera, 1);
        let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
        let got = vlf_viewer::render(&gpu, &renderer, &camera, 1, mode).unwrap();
        let plain = field.render(&camera, 1, mode);
        let pixels = want.pixels.len();
        let changed = differing(&want, &plain, 1e-3);
        let off = differing(&want, &got, 1e-2);
        let way_off = differing(&want, &got, 0.5);
        let (m, g) = (want.mean(), got.mean());
        println!(
            "{scene} {mode:?}: the cubes change {changed} of {pixels} pixels; GPU vs CPU: {off} differ by 1 %, \
             {way_off} by half; means {m:?} vs {g:?}"
        );
        assert!(changed > pixels / 10, "{changed}");
        assert!(off * 20 <= pixels, "{off} of {pixels} pixels differ by more than 1 %");
        assert!(
            way_off * 100 <= pixels,
            "{way_off} of {pixels} pixels differ by more than half"
        );
        for c in 0..3 {
            assert!(
                (m[c] - g[c]).abs() <= 5e-3 * m[c].abs(),
                "image means differ: CPU {m:?}, GPU {g:?}"
            );
        }
    }
}

#[test]
fn the_gpu_draws_objects_and_their_shadows_as_the_cpu_does() {
    view_matches("cornell.obj", &[SpecularMode::Rays]);
}

#[test]
fn the_gpu_draws_objects_in_mirrors_as_the_cpu_does() {
    view_matches("mirrors.obj", &[SpecularMode::Trace { depth: 4 }, SpecularMode::Rays]);
}

/// Shadows at 64 points of the floor around two cubes (one on it, one in the air), GPU against
/// CPU: the same loss, direct part (the lamp's points) and indirect part (the cones' cells).
#[test]
fn the_gpu_casts_the_shadows_the_cpu_casts() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field("cornell.obj", 33, 3);
    let bvh = Bvh::build(&field.scene);
    let placed = two_cubes(&field);
    let cpu = Gatherer::with_directions(&field, &bvh, &placed, SpecularMode::Rays, 33)
        .unwrap()
        .with_shadow_samples(32);
    let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
    let gather = GpuGather::new(&gpu, &renderer, SpecularMode::Rays.into()).unwrap();
    let mut points = Vec::new();
    for i in 0..8 {
        for j in 0..8 {
            let (x, z) = (30.0 + 70.0 * i as f64, 20.0 + 70.0 * j as f64);
            points.push((
                field.scene.normalisation.to_vlf(DVec3::new(x, 0.0, z)),
                DVec3::Y,
                [0.7; 3],
            ));
        }
    }
    let want: Vec<Option<[f64; 3]>> = points
        .iter()
        .map(|&(p, normal, rho)| cpu.shadow_loss(p, normal, rho))
        .collect();
    let got = gather.shadow_loss(&gpu, &points).unwrap();
    let scale = want.iter().flatten().flatten().copied().fold(0.0, f64::max);
    for (k, (g, w)) in got.iter().zip(&want).enumerate() {
        let (g, w) = (g.unwrap_or([0.0; 3]), w.unwrap_or([0.0; 3]));
        for c in 0..3 {
            assert!((g[c] - w[c]).abs() < 1e-3 * scale, "point {k}: GPU {g:?}, CPU {w:?}");
        }
    }
}
