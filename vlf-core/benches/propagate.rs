//! Propagation benchmarks on the bundled office scene (139 polygons).
//!
//! `cargo bench -p vlf-core --bench propagate` — the paper's reference point is
//! the office at l = 513, N = 64, m = 8, 4 iterations: 34 minutes on one
//! 1.7 GHz core. Setup (rasterising every subfield, discrete areas) and the
//! iterations are measured separately.

use criterion::{Criterion, criterion_group, criterion_main};
use std::path::Path;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::{ImportOptions, load_obj};

fn office() -> vlf_core::scene::Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/office.obj");
    load_obj(&path, &ImportOptions::default())
        .expect("bundled office scene")
        .0
}

fn options(l: usize) -> Options {
    Options {
        directions: l,
        grid: GridSize::new(64, 8).expect("valid grid"),
        stop: Stop::Iterations(4),
        ..Options::default()
    }
}

fn bench(c: &mut Criterion) {
    let scene = office();
    let mut group = c.benchmark_group("office N=64 m=8");
    group.sample_size(10);
    for l in [129, 513] {
        group.bench_function(format!("setup l={l}"), |b| {
            b.iter(|| Propagation::new(scene.clone(), options(l)).expect("setup"))
        });
        group.bench_function(format!("4 iterations l={l}"), |b| {
            b.iter_batched(
                || Propagation::new(scene.clone(), options(l)).expect("setup"),
                |mut p| {
                    p.run(|_| {});
                    p
                },
                criterion::BatchSize::LargeInput,
            )
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
