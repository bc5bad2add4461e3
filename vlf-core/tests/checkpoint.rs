//! Checkpoints: stopping after any iteration and resuming from the stored
//! state gives the same bits as a run that never stopped, with and without
//! mirrors and perturbation; damaged state is refused, never used.

mod common;

use common::*;
use vlf_core::Error;
use vlf_core::propagate::{Checkpoint, Options, Perturbation, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::Scene;

fn options(iterations: u32, perturb: u32) -> Options {
    Options {
        directions: 33,
        grid: GridSize::new(16, 8).unwrap(),
        stop: Stop::Iterations(iterations),
        perturbation: Perturbation {
            iterations: perturb,
            count: 2,
        },
        deferral: Some(0.01),
        filter_sigma: Some(1.0),
        ..Options::default()
    }
}

fn diffuse_box() -> Scene {
    closed_box(
        0.6,
        2,
        &[3],
        vec![material("wall", 0.6, 0.0), material("lamp", 0.2, 1.0)],
    )
}

/// Everything of a propagation's state except the wall-clock times.
fn state(p: &Propagation) -> Checkpoint {
    let mut c = p.checkpoint();
    for s in &mut c.stats {
        s.seconds = 0.0;
    }
    c
}

fn resumes_bit_identically(scene: Scene, perturb: u32) {
    let total = 5;
    let mut straight = Propagation::new(scene.clone(), options(total, perturb)).unwrap();
    straight.run(|_| {});
    for stop_after in [0, 1, 3] {
        let mut first = Propagation::new(scene.clone(), options(total, perturb)).unwrap();
        for _ in 0..stop_after {
            first.step(|_| {});
        }
        let bytes = first.checkpoint().to_bytes();
        drop(first);
        let restored = Checkpoint::from_bytes(&bytes).unwrap();
        assert_eq!(restored.iterations(), stop_after);
        let mut resumed = Propagation::resume(scene.clone(), options(total, perturb), restored).unwrap();
        resumed.run(|_| {});
        assert!(
            state(&resumed) == state(&straight),
            "resuming after {stop_after} iterations changed the bits"
        );
        assert_eq!(resumed.diffuse_radiance(), straight.diffuse_radiance());
        assert_eq!(resumed.mirror_totals(), straight.mirror_totals());
    }
}

#[test]
fn resume_with_mirrors_gives_the_same_bits() {
    resumes_bit_identically(mirror_room(), 0);
}

#[test]
fn resume_with_perturbation_and_deferral_gives_the_same_bits() {
    resumes_bit_identically(diffuse_box(), 2);
}

#[test]
fn damaged_checkpoints_are_refused() {
    let scene = mirror_room();
    let mut p = Propagation::new(scene.clone(), options(3, 0)).unwrap();
    p.step(|_| {});
    let good = p.checkpoint();
    let bytes = good.to_bytes();
    // Truncated or garbage bytes.
    for bad in [
        &bytes[..bytes.len() / 2],
        &bytes[..3],
        b"not a checkpoint at all".as_slice(),
    ] {
        assert!(matches!(Checkpoint::from_bytes(bad), Err(Error::Decode(_))));
    }
    let resume = |c: Checkpoint| Propagation::resume(scene.clone(), options(3, 0), c);
    let expect_refused = |c: Checkpoint, needle: &str| match resume(c) {
        Err(Error::Decode(m)) => assert!(m.contains(needle), "{m}"),
        Err(e) => panic!("wrong error {e}"),
        Ok(_) => panic!("accepted a damaged checkpoint ({needle})"),
    };
    let mut c = good.clone();
    c.current.pop();
    expect_refused(c, "texel");
    let mut c = good.clone();
    c.total[7][1] = f64::NAN;
    expect_refused(c, "non-finite");
    let mut c = good.clone();
    c.current[0][0] = -1.0;
    expect_refused(c, "negative");
    let mut c = good.clone();
    c.mirrors.as_mut().unwrap()[4].unshot.push([0.0; 3]);
    expect_refused(c, "direction 4");
    let mut c = good.clone();
    c.mirrors = None;
    expect_refused(c, "mirrors");
    let mut c = good.clone();
    c.stats[0].index = 5;
    expect_refused(c, "order");
    // A checkpoint of another scene (no mirrors there).
    let other = Propagation::new(diffuse_box(), options(3, 0)).unwrap().checkpoint();
    assert!(resume(other).is_err());
    // The good one is accepted.
    assert!(resume(good).is_ok());
}

#[test]
fn scene_bytes_round_trip_and_refuse_damage() {
    let scene = mirror_room();
    let bytes = scene.to_bytes();
    assert_eq!(Scene::from_bytes(&bytes).unwrap(), scene);
    assert_eq!(scene.content_hash().len(), 64);
    assert_ne!(scene.content_hash(), diffuse_box().content_hash());
    assert!(matches!(
        Scene::from_bytes(&bytes[..bytes.len() - 9]),
        Err(Error::Decode(_))
    ));
    let mut broken = scene.clone();
    broken.surfaces[2].material = 99;
    assert!(matches!(Scene::from_bytes(&broken.to_bytes()), Err(Error::Decode(_))));
    let mut broken = scene.clone();
    broken.surfaces[1].vertices[0].x = f64::INFINITY;
    assert!(matches!(Scene::from_bytes(&broken.to_bytes()), Err(Error::Decode(_))));
    let mut broken = scene;
    broken.materials[0].diffuse[0] = 1.5;
    assert!(matches!(Scene::from_bytes(&broken.to_bytes()), Err(Error::Decode(_))));
}
