//! What rasterising a direction's subfield costs for a scanned mesh.
//!
//! `cargo bench -p vlf-core --bench subfields`: a closed room with a ball of 20 480 or 81 920
//! triangles (an icosphere, its vertices jittered as a scan's are), N = 128, m = 8: the
//! subfields of 64 of l = 2049 directions, built one after another on one thread. Every
//! set-up builds each direction's subfield once, the survey once more where no subfield is
//! kept, and a perturbed iteration twice per rotated copy (its areas, then its shot): for a
//! mesh of tens of thousands of triangles, most of a perturbed iteration.

use criterion::{Criterion, criterion_group, criterion_main};
use glam::DVec3;
use vlf_core::directions::DirectionSet;
use vlf_core::maps::TexelAtlas;
use vlf_core::propagate::Options;
use vlf_core::psf::{Footprints, GridSize, RasterScratch, Subfield};
use vlf_core::scene::{FaceOrigin, ImportOptions, Material, Scene};

#[path = "../tests/common/mod.rs"]
mod common;

/// [`common::icosphere`] about `c`, each vertex moved along the radius by up to `jitter · r` as a
/// scan's are: by a hash of its position, so that the triangles meeting there move it alike.
fn ball(c: DVec3, r: f64, levels: u32, jitter: f64) -> Vec<Vec<DVec3>> {
    let moved = |p: DVec3| {
        let key = (p.x.to_bits() ^ p.y.to_bits().rotate_left(21) ^ p.z.to_bits().rotate_left(42))
            .wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let u = (key >> 11) as f64 / (1u64 << 53) as f64;
        c + (p - c) * (1.0 + jitter * (u - 0.5))
    };
    (common::icosphere(c, r, levels).into_iter())
        .map(|tri| tri.iter().map(|&p| moved(p)).collect())
        .collect()
}

fn room_with_ball(levels: u32) -> Scene {
    let m = |name: &str, e: f64| Material {
        name: name.into(),
        diffuse: [0.6; 3],
        specular: [0.0; 3],
        emission: [e; 3],
        albedo_texture: None,
    };
    let origin = FaceOrigin { line: 0, face: 0 };
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    let mut polygons = Vec::new();
    for face in 0..6 {
        let (axis, sign) = (axes[face / 2], if face % 2 == 0 { -1.0 } else { 1.0 });
        let (a, b) = (axes[(face / 2 + 1) % 3] * 2.0, axes[(face / 2 + 2) % 3] * 2.0);
        let c = axis * sign * 2.0;
        let mut v = vec![c - a - b, c + a - b, c + a + b, c - a + b];
        if (v[1] - v[0]).cross(v[2] - v[0]).dot(-axis * sign) < 0.0 {
            v.reverse();
        }
        polygons.push((v, (face == 3) as usize, origin.clone()));
    }
    for tri in ball(DVec3::new(0.0, -1.0, 0.0), 0.8, levels, 0.01) {
        polygons.push((tri, 0, origin.clone()));
    }
    Scene::from_polygons(
        &polygons,
        vec![m("wall", 0.0), m("lamp", 5.0)],
        &ImportOptions::default(),
    )
    .expect("valid room")
    .0
}

fn bench(c: &mut Criterion) {
    let options = Options {
        directions: 2049,
        grid: GridSize::new(128, 8).expect("valid grid"),
        ..Options::default()
    };
    let directions = DirectionSet::new(options.directions).expect("valid l");
    let mut group = c.benchmark_group("subfields of a ball in a room, N=128 m=8");
    group.sample_size(10);
    for levels in [5, 6] {
        let scene = room_with_ball(levels);
        let atlas = TexelAtlas::new(&scene, options.texel_size(), options.grid.ray_spacing()).expect("atlas");
        let footprints = Footprints::new(&scene, &atlas.plane_rep);
        let triangles = 20 << (2 * levels);
        group.bench_function(format!("{triangles} triangles, 64 directions"), |b| {
            let mut scratch = RasterScratch::default();
            b.iter(|| {
                (0..64)
                    .map(|k| {
                        let sub =
                            Subfield::build_with(&footprints, directions.frame(k * 32), options.grid, &mut scratch);
                        sub.entries.len()
                    })
                    .sum::<usize>()
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
