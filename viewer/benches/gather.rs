//! Dynamic objects on the GPU: `cargo bench -p vlf-viewer --bench gather`.
//!
//! The bundled Cornell box propagated at l = 513, N = 64 (4 iterations), and
//!
//! - a cube of side 100 in it, gathered at 10 000 of its points over the field's 513
//!   directions (5.1 M rays through the scene and the cube): the unit of gather cost,
//!   whose target is 16 ms on a real GPU. Each iteration uploads the points, dispatches and
//!   reads the result back;
//! - whole 1280 × 720 frames (one sample a pixel, read back) with 1 and with 10 cubes of 3 072
//!   triangles each: every object pixel gathered over the 513 directions, and the static scene
//!   shadowed (K = 128 cells per object and the lamp's points) per fragment (`render --gpu`),
//!   or per texel (`vlf view`) with the cubes standing still and with them moving every frame
//!   (placed again, checked clear of the box, uploaded, shadows recomputed).
//!
//! Skips (with a message) where there is no adapter; lavapipe takes minutes a frame.

#[allow(dead_code)]
#[path = "../tests/common/mod.rs"]
mod common;

use criterion::{Criterion, criterion_group, criterion_main};
use glam::DVec3;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::{DynamicObject, Pose};
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::Material;
use vlf_viewer::{FieldRenderer, GpuGather, Placement};

/// A grey cube of half-size `h` around `c`, each face split into `split × split` squares.
fn cube(c: DVec3, h: f64, split: usize) -> DynamicObject {
    let grey = Material::grey("grey", 0.6);
    DynamicObject::cube("cube", c, h, split, grey)
}

fn bench(c: &mut Criterion) {
    let Some(gpu) = common::gpu() else {
        return;
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
    let objects = [cube(DVec3::ZERO, 50.0, 1).place(&pose, &n).expect("a valid cube")];
    let bvh = vlf_core::render::Bvh::build(&field.scene);
    let cpu = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).expect("gatherer");
    let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).expect("upload");
    let gather = GpuGather::new(&gpu, &renderer, SpecularMode::Rays.into()).expect("pipeline");
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
    // Frames with 1 and 10 cubes of 3 072 triangles (side 60, 16 × 16 quads a face).
    let camera = common::readme_camera(1280, 720);
    let mut group = c.benchmark_group(format!("GPU frame 1280x720 on {}", gpu.describe()));
    group.sample_size(10);
    for count in [1usize, 10] {
        let cubes: Vec<(DynamicObject, Pose)> = (0..count)
            .map(|k| {
                let at = DVec3::new(90.0 + 95.0 * (k % 5) as f64, 250.0 + 170.0 * (k / 5) as f64, 150.0);
                let pose = Pose {
                    rotation: glam::DQuat::IDENTITY,
                    translation: at,
                };
                (cube(DVec3::ZERO, 30.0, 16), pose)
            })
            .collect();
        let ends: Vec<Option<DVec3>> = cubes
            .iter()
            .map(|(_, p)| Some(p.translation + DVec3::Z * 40.0))
            .collect();
        let mut placement = Placement::new(cubes, &field, &bvh).expect("clear of the box");
        let (per_fragment, mut per_texel) = {
            let cpu = Gatherer::new(&field, &bvh, placement.placed(), SpecularMode::Rays)
                .expect("gatherer")
                .with_gpu_lighting(true, true);
            let a = FieldRenderer::with_objects(&gpu, &field, &cpu).expect("upload");
            let b = FieldRenderer::with_objects(&gpu, &field, &cpu).expect("upload");
            (a, b)
        };
        per_texel.shadows_per_texel(&gpu, &field).expect("texel shadows");
        let frame = |r: &FieldRenderer| vlf_viewer::render(&gpu, r, &camera, 1, SpecularMode::Rays).expect("frame");
        group.bench_function(format!("{count} cubes of 3 072 triangles, shadows per fragment"), |b| {
            b.iter(|| frame(&per_fragment))
        });
        group.bench_function(format!("{count} cubes, shadows per texel, cubes still"), |b| {
            b.iter(|| frame(&per_texel))
        });
        // As `vlf view --object-to` moves them: placed again, checked clear of the box, uploaded,
        // their shadows recomputed per texel, drawn.
        placement.script(ends, 1 << 40).expect("a script");
        group.bench_function(format!("{count} cubes, shadows per texel, cubes moving"), |b| {
            b.iter(|| {
                placement.advance(1.0 / 60.0, 100.0, DVec3::NEG_Z, &field, &bvh);
                per_texel.move_objects(&gpu, placement.placed()).expect("move");
                frame(&per_texel)
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
