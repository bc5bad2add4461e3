//! What dynamic objects cost on the CPU.
//!
//! `cargo bench -p vlf-core --bench dynamic`: the bundled Cornell box propagated at l = 513,
//! N = 64 (4 iterations), a cube of side 100 placed in it, and
//!
//! - the gather at 10 000 points of the cube (513 directions each: 5.1 M rays), the issue's
//!   unit of gather cost;
//! - the shadow the cube casts at 10 000 points of the floor around it (K = 128 cone cells
//!   each, and the lamp's points).
//!
//! Points are spread over rayon's threads as a view's pixels are.

use criterion::{Criterion, criterion_group, criterion_main};
use glam::DVec3;
use rayon::prelude::*;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::{DynamicObject, Pose};
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::Bvh;
use vlf_core::scene::Material;

/// A grey cube of half-size `h` around the origin.
fn cube(h: f64) -> DynamicObject {
    let grey = Material::grey("grey", 0.6);
    DynamicObject::cube("cube", DVec3::ZERO, h, 1, grey)
}

fn bench(c: &mut Criterion) {
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
    let bvh = Bvh::build(&field.scene);
    let n = field.scene.normalisation;
    let at = DVec3::new(420.0, 50.0, 120.0);
    let pose = Pose {
        rotation: glam::DQuat::IDENTITY,
        translation: at,
    };
    let objects = [cube(50.0).place(&pose, &n).expect("a valid cube")];
    let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).expect("gatherer");
    // 10 000 points on the cube's five faces that do not rest on the floor, just off them.
    let faces = [DVec3::X, -DVec3::X, DVec3::Y, DVec3::Z, -DVec3::Z];
    let on_cube: Vec<(DVec3, DVec3)> = (0..10_000)
        .map(|k| {
            let normal = faces[k % 5];
            let (u, v) = normal.any_orthonormal_pair();
            let (s, t) = (((k / 5) % 40) as f64 / 40.0 - 0.5, ((k / 200) % 50) as f64 / 50.0 - 0.5);
            (n.to_vlf(at + normal * 50.01 + (u * s + v * t) * 90.0), normal)
        })
        .collect();
    // 10 000 points of the floor (y = 0) in a 300 × 300 square around the cube.
    let on_floor: Vec<DVec3> = (0..10_000)
        .map(|k| {
            n.to_vlf(DVec3::new(
                420.0 - 150.0 + (k % 100) as f64 * 3.0,
                0.0,
                120.0 - 150.0 + (k / 100) as f64 * 3.0,
            ))
        })
        .collect();
    let mut group = c.benchmark_group("Cornell box l=513 N=64, a cube of side 100");
    group.sample_size(10);
    group.bench_function("gather, 10 000 points x 513 directions", |b| {
        b.iter(|| {
            on_cube
                .par_iter()
                .map(|&(p, normal)| gather.incident(p, normal)[1])
                .sum::<f64>()
        })
    });
    group.bench_function("shadow, 10 000 floor points", |b| {
        b.iter(|| {
            on_floor
                .par_iter()
                .filter_map(|&p| gather.shadow_loss(p, DVec3::Y, [0.7; 3]).map(|l| l[1]))
                .sum::<f64>()
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
