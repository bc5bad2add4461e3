//! The dynamic objects' gather on the GPU: `cargo bench -p vlf-viewer --bench gather`.
//!
//! The bundled Cornell box propagated at l = 513, N = 64 (4 iterations), a cube of side 100 in
//! it, and the gather at 10 000 points of the cube over the field's 513 directions (5.1 M rays
//! through the scene and the cube): the unit of gather cost, whose target is 16 ms on
//! a real GPU. Each iteration uploads the points, dispatches and reads the result back, as a
//! viewer's frame would. Skips (with a message) where there is no adapter.

use criterion::{Criterion, criterion_group, criterion_main};
use glam::DVec3;
use vlf_core::directions::DirectionSet;
use vlf_core::dynamic::{DynamicObject, Pose};
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::Material;
use vlf_viewer::{FieldRenderer, Gpu, GpuGather};

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

fn bench(c: &mut Criterion) {
    let gpu = match Gpu::new() {
        Ok(gpu) => gpu,
        Err(e) => {
            eprintln!("skipped: {e}");
            return;
        }
    };
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
    let (scene, _) = vlf_core::scene::load_scene(&path, &Default::default()).expect("the bundled Cornell box");
    let options = Options {
        directions: 513,
        grid: GridSize::new(64, 8).expect("valid grid"),
        stop: Stop::Iterations(4),
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).expect("setup");
    p.run(|_| {});
    let field = p.into_field();
    let n = field.scene.normalisation;
    let at = DVec3::new(420.0, 50.0, 120.0);
    let pose = Pose {
        rotation: glam::DQuat::IDENTITY,
        translation: at,
    };
    let objects = [cube(DVec3::ZERO, 50.0).place(&pose, &n).expect("a valid cube")];
    let renderer = FieldRenderer::with_objects(&gpu, &field, &objects).expect("upload");
    let directions = DirectionSet::new(513).expect("513 directions");
    let gather = GpuGather::new(&gpu, &renderer, &directions, SpecularMode::Rays.into()).expect("pipeline");
    // 10 000 points on the cube's five faces that do not rest on the floor, just off them.
    let faces = [DVec3::X, -DVec3::X, DVec3::Y, DVec3::Z, -DVec3::Z];
    let points: Vec<(DVec3, DVec3)> = (0..10_000)
        .map(|k| {
            let normal = faces[k % 5];
            let (u, v) = normal.any_orthonormal_pair();
            let (s, t) = (((k / 5) % 40) as f64 / 40.0 - 0.5, ((k / 200) % 50) as f64 / 50.0 - 0.5);
            (n.to_vlf(at + normal * 50.01 + (u * s + v * t) * 90.0), normal)
        })
        .collect();
    let mut group = c.benchmark_group(format!("GPU gather on {}", gpu.describe()));
    group.sample_size(20);
    group.bench_function("10 000 points x 513 directions, Cornell box and a cube", |b| {
        b.iter(|| gather.incident(&gpu, &points).expect("gather"))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
