//! The GPU gather against the CPU's (`vlf_core::dynamic::gather`), on the bundled scenes with
//! a cube in them: the same radiance at points of the cube and around it, with mirrors read
//! either way, and objects blocking the gather. Lavapipe in CI.

mod common;

use common::{bundled_field, gpu};
use glam::DVec3;
use vlf_core::directions::DirectionSet;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::{DynamicObject, PlacedObject, Pose};
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::render::Bvh;
use vlf_core::scene::Material;
use vlf_viewer::{FieldRenderer, GpuGather};

/// A grey cube of half-size `h` (scene units) around `c`, facing out.
fn cube(c: DVec3, h: f64) -> DynamicObject {
    let mut triangles = Vec::new();
    for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
        let u = axis.any_orthogonal_vector().normalize();
        let v = axis.cross(u);
        for (n, a, b) in [(axis, u, v), (-axis, v, u)] {
            let f = c + n * h;
            let (p0, p1, p2, p3) = (f - (a + b) * h, f + (a - b) * h, f + (a + b) * h, f - (a - b) * h);
            triangles.push([p0, p1, p2]);
            triangles.push([p0, p2, p3]);
        }
    }
    let grey = Material {
        name: "grey".into(),
        diffuse: [0.6; 3],
        specular: [0.0; 3],
        emission: [0.0; 3],
        albedo_texture: None,
    };
    DynamicObject::uniform("cube", triangles, grey)
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
    let renderer = FieldRenderer::with_objects(&gpu, &field, &placed).unwrap();
    let points = points(&field, c, h);
    let directions = DirectionSet::new(129).unwrap();
    for &mode in modes {
        let cpu = Gatherer::with_directions(&field, &bvh, &placed, mode, 129).unwrap();
        let want: Vec<[f64; 3]> = points.iter().map(|&(p, n)| cpu.incident(p, n)).collect();
        let got = GpuGather::new(&gpu, &renderer, &directions, mode.into())
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
    let directions = DirectionSet::new(33).unwrap();
    let gather = |objects: &[PlacedObject]| {
        let renderer = FieldRenderer::with_objects(&gpu, &field, objects).unwrap();
        GpuGather::new(&gpu, &renderer, &directions, SpecularMode::Rays.into())
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
