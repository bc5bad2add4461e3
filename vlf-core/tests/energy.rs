//! Energy balance and analytic enclosures.

mod common;

use common::*;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;

fn options(l: usize, n: u32, m: u32, iterations: u32) -> Options {
    Options {
        directions: l,
        grid: GridSize::new(n, m).unwrap(),
        stop: Stop::Iterations(iterations),
        ..Options::default()
    }
}

fn lum(c: &[f64; 3]) -> f64 {
    c.iter().sum::<f64>() / 3.0
}

/// In a closed box every ray that leaves a wall lands on another wall: each
/// iteration's shot power equals its received power.
#[test]
fn closed_box_conserves_energy_every_iteration() {
    let scene = closed_box(
        0.55,
        3,
        &[3],
        vec![material("wall", 0.6, 0.0), material("lamp", 0.5, 2.0)],
    );
    let mut p = Propagation::new(scene, options(129, 48, 8, 5)).unwrap();
    p.run(|_| {});
    for s in &p.stats {
        let f = &s.flow;
        for c in 0..3 {
            assert!(f.shot[c] > 0.0);
            let rel = (f.shot[c] - f.received[c]).abs() / f.shot[c];
            assert!(
                rel < 1e-9,
                "iteration {}: shot {} received {} (rel {rel})",
                s.index,
                f.shot[c],
                f.received[c]
            );
            assert_eq!(f.escaped[c], 0.0, "light escaped a closed box");
            assert_eq!(f.blocked[c], 0.0, "a back face was hit inside a closed box");
        }
    }
    // What was shot in iteration 0 is exactly the emitted power.
    let rel = (lum(&p.stats[0].flow.shot) - lum(&p.emitted)).abs() / lum(&p.emitted);
    assert!(rel < 1e-12, "emitted power not shot exactly: {rel}");
}

/// Uniform reflectance ρ everywhere: received power in iteration k is Φ·ρ^k,
/// so after K iterations the total received is Φ·(1 − ρ^K)/(1 − ρ).
#[test]
fn enclosure_follows_the_geometric_series() {
    let rho = 0.7;
    let scene = closed_box(
        0.55,
        2,
        &[0],
        vec![material("wall", rho, 0.0), material("lamp", rho, 1.0)],
    );
    let k = 8;
    let mut p = Propagation::new(scene, options(33, 32, 8, k)).unwrap();
    p.run(|_| {});
    let phi = lum(&p.emitted);
    let received: f64 = p.stats.iter().map(|s| lum(&s.flow.received)).sum();
    let expected = phi * (1.0 - rho.powi(k as i32)) / (1.0 - rho);
    assert!(
        ((received - expected) / expected).abs() < 1e-9,
        "received {received}, expected {expected}"
    );
    for (i, s) in p.stats.iter().enumerate() {
        let want = phi * rho.powi(i as i32);
        assert!((lum(&s.flow.received) - want).abs() / want < 1e-9, "iteration {i}");
    }
    // Unshot fraction after K iterations is ρ^K.
    assert!((p.unshot_fraction() - rho.powi(k as i32)).abs() < 1e-9);
}

/// The furnace: all walls emit Le and reflect ρ. The exact solution is uniform radiance
/// Le/(1 − ρ), Le·(1 + ρ + … + ρ^K) = Le·(1 − ρ^(K+1))/(1 − ρ) after K iterations. Each wall
/// emits its true power, so its rays carry `k_c·Le` where its rays over- or under-count its
/// area by `1/k_c`; every texel then shows Le plus reflected light scaled by a mixture of the
/// walls' factors, `Le + (want − Le)·k` with `k` between the smallest and the largest `k_c`,
/// to rounding. (The factors are within the cosine quadrature's error of 1: 2–4 % with 33
/// directions, a fraction of a per cent from 513 on.)
#[test]
fn furnace_is_uniform_texel_by_texel() {
    let (rho, le) = (0.5, 1.0);
    let scene = closed_box(
        0.55,
        2,
        &[0, 1, 2, 3, 4, 5],
        vec![material("unused", rho, 0.0), material("glow", rho, le)],
    );
    let k = 12;
    let mut p = Propagation::new(scene, options(33, 32, 8, k)).unwrap();
    p.run(|_| {});
    let band = emission_band(&p);
    println!("the walls' emission factors: {band:?}");
    // 33 directions integrate a wall's cosine, Σ Δω·|cos θ| = π, to a few per cent.
    assert!(band.0 > 0.95 && band.1 < 1.05, "{band:?}");
    let field = p.into_field();
    let want = le * (1.0 - rho.powi(k as i32 + 1)) / (1.0 - rho);
    let (checked, worst) = assert_furnace(&field, le, want, band, 1e-5);
    println!("{checked} texels, reflected light within {worst:.1e} of the furnace's");
    assert!(checked > 1000, "too few texels checked: {checked}");
}

/// The same bits whatever the number of threads.
#[test]
fn same_bits_with_one_and_several_threads() {
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let scene = closed_box(
                0.55,
                2,
                &[3],
                vec![material("wall", 0.6, 0.0), material("lamp", 0.5, 3.0)],
            );
            let mut p = Propagation::new(scene, options(129, 32, 8, 3)).unwrap();
            p.run(|_| {});
            (p.total.clone(), p.current.clone())
        })
    };
    let one = run(1);
    for t in [2, 3, 5] {
        let other = run(t);
        assert!(one == other, "results differ between 1 and {t} threads");
    }
}
