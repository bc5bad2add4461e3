//! How the cost of propagation grows with the number of mirrors.
//!
//! `cargo bench -p vlf-core --bench mirrors`: a closed room (l = 513, N = 64,
//! m = 8, 4 iterations) with 0, 1, 2, 4 and 8 mirror panels hung on its
//! walls. With 0 mirrors the specular machinery is absent altogether, so that
//! point is the diffuse cost.

use criterion::{Criterion, criterion_group, criterion_main};
use glam::DVec3;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::{FaceOrigin, ImportOptions, Material, Scene};

fn quad(c: DVec3, a: DVec3, b: DVec3, normal: DVec3) -> Vec<DVec3> {
    let mut v = vec![c - a - b, c + a - b, c + a + b, c - a + b];
    if (v[1] - v[0]).cross(v[2] - v[0]).dot(normal) < 0.0 {
        v.reverse();
    }
    v
}

fn room(mirrors: usize) -> Scene {
    let m = |name: &str, d: f64, s: f64, e: f64| Material {
        name: name.into(),
        diffuse: [d; 3],
        specular: [s; 3],
        emission: [e; 3],
        albedo_texture: None,
    };
    let materials = vec![
        m("wall", 0.6, 0.0, 0.0),
        m("lamp", 0.5, 0.0, 10.0),
        m("mirror", 0.0, 0.9, 0.0),
    ];
    let origin = FaceOrigin { line: 0, face: 0 };
    let mut polygons = Vec::new();
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    for face in 0..6 {
        let (axis, sign) = (axes[face / 2], if face % 2 == 0 { -1.0 } else { 1.0 });
        let (a, b) = (axes[(face / 2 + 1) % 3], axes[(face / 2 + 2) % 3]);
        polygons.push((
            quad(axis * sign * 2.0, a * 2.0, b * 2.0, -axis * sign),
            0,
            origin.clone(),
        ));
    }
    polygons.push((
        quad(DVec3::new(0.0, 1.99, 0.0), DVec3::X * 0.4, DVec3::Z * 0.4, -DVec3::Y),
        1,
        origin.clone(),
    ));
    // Mirror panels just in front of the walls, two per wall at most.
    for k in 0..mirrors {
        let face = [0, 1, 4, 5][k % 4];
        let (axis, sign) = (axes[face / 2], if face % 2 == 0 { -1.0 } else { 1.0 });
        let (a, b) = (axes[(face / 2 + 1) % 3], axes[(face / 2 + 2) % 3]);
        let shift = if k < 4 { -0.8 } else { 0.8 };
        let c = axis * sign * 1.99 + b * shift;
        polygons.push((quad(c, a * 0.6, b * 0.5, -axis * sign), 2, origin.clone()));
    }
    Scene::from_polygons(&polygons, materials, &ImportOptions::default())
        .expect("valid room")
        .0
}

fn bench(c: &mut Criterion) {
    let options = Options {
        directions: 513,
        grid: GridSize::new(64, 8).expect("valid grid"),
        stop: Stop::Iterations(4),
        ..Options::default()
    };
    let mut group = c.benchmark_group("room l=513 N=64 m=8, 4 iterations");
    group.sample_size(10);
    for mirrors in [0, 1, 2, 4, 8] {
        let scene = room(mirrors);
        group.bench_function(format!("{mirrors} mirrors"), |b| {
            b.iter(|| {
                let mut p = Propagation::new(scene.clone(), options.clone()).expect("setup");
                p.run(|_| {});
                p
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
