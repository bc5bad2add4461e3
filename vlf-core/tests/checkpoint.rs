//! Checkpoints: stopping after any iteration and resuming from the stored
//! state gives the same bits as a run that never stopped, with and without
//! mirrors and perturbation; damaged state is refused, never used.

mod common;

use common::*;
use vlf_core::Error;
use vlf_core::propagate::{
    Checkpoint, Options, Perturbation, Propagation, ShootingState, SnapshotBytes, StateHead, Stop, Totals, UnshotBatch,
};
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

/// The shooting state from its stored parts.
fn shooting(parts: &SnapshotBytes) -> ShootingState {
    let batches = parts
        .unshot
        .iter()
        .map(|b| UnshotBatch::from_bytes(b).unwrap())
        .collect();
    ShootingState::from_parts(StateHead::from_bytes(&parts.head).unwrap(), batches).unwrap()
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
        let halves = first.snapshot_bytes();
        drop(first);
        let restored = Checkpoint::from_bytes(&bytes).unwrap();
        assert_eq!(restored.iterations(), stop_after);
        // The same state from its parts, as a store keeps them.
        let joined = Checkpoint::join(shooting(&halves), Totals::from_bytes(&halves.totals).unwrap()).unwrap();
        assert!(joined == restored, "the parts of a checkpoint are not the whole");
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
fn halves_are_the_whole_split_and_old_whole_blobs_still_read() {
    let scene = mirror_room();
    let mut p = Propagation::new(scene, options(3, 0)).unwrap();
    p.step(|_| {});
    p.step(|_| {});
    let whole = p.checkpoint();
    let (state, totals) = whole.clone().split();
    assert_eq!(state.iterations(), 2);
    assert_eq!(totals.iterations, 2);
    // Serialised straight from the propagation: the same bytes as the parts.
    let bytes = p.snapshot_bytes();
    let (head, batches) = state.clone().into_parts();
    assert!(batches.len() > 1, "{} batches", batches.len());
    assert_eq!(bytes.head, head.to_bytes());
    assert_eq!(
        bytes.unshot,
        batches.iter().map(UnshotBatch::to_bytes).collect::<Vec<_>>()
    );
    assert_eq!(bytes.totals, totals.to_bytes());
    assert!(Checkpoint::is_split(&bytes.head));
    assert!(ShootingState::from_parts(head, batches).unwrap() == state);
    // The shooting half carries no totals: well under the whole.
    let whole_bytes = whole.to_bytes();
    assert!(!Checkpoint::is_split(&whole_bytes));
    let shooting_len = bytes.head.len() + bytes.unshot.iter().map(Vec::len).sum::<usize>();
    assert!(
        shooting_len < whole_bytes.len() * 6 / 10,
        "{shooting_len} of {}",
        whole_bytes.len()
    );
    // A whole (version 1) checkpoint, as older stores hold, gives the totals.
    assert_eq!(Totals::from_bytes(&whole_bytes).unwrap(), totals);
    // A head is not a whole checkpoint.
    match Checkpoint::from_bytes(&bytes.head) {
        Err(Error::Decode(m)) => assert!(m.contains("split"), "{m}"),
        other => panic!("read a shooting state's head as a whole checkpoint: {other:?}"),
    }
    assert!(Checkpoint::join(state.clone(), totals.clone()).unwrap() == whole);
    // A replica restores the head, then only the batches it shoots.
    let mut r = Propagation::new(mirror_room(), options(3, 0)).unwrap();
    r.restore_head(StateHead::from_bytes(&bytes.head).unwrap()).unwrap();
    assert_eq!(r.iterations_done(), 2);
    r.restore_unshot(UnshotBatch::from_bytes(&bytes.unshot[1]).unwrap())
        .unwrap();
    let restored = r.checkpoint().mirrors.unwrap();
    let expected = whole.mirrors.as_ref().unwrap();
    let batch1 = vlf_core::propagate::work::batch_range(1, expected.len());
    for (d, (got, want)) in restored.iter().zip(expected).enumerate() {
        if batch1.contains(&d) {
            assert_eq!(got.unshot, want.unshot, "direction {d} of batch 1");
        } else {
            assert!(
                got.unshot.iter().all(|v| *v == [0.0; 3]),
                "direction {d} outside batch 1"
            );
        }
    }
}

#[test]
fn mismatched_or_damaged_halves_are_refused() {
    let scene = mirror_room();
    let mut p = Propagation::new(scene.clone(), options(3, 0)).unwrap();
    p.step(|_| {});
    let (state1, _) = p.checkpoint().split();
    p.step(|_| {});
    let (state2, totals2) = p.checkpoint().split();
    let refused = |joined: vlf_core::Result<Checkpoint>, needle: &str| match joined {
        Err(Error::Decode(m)) => assert!(m.contains(needle), "{m}"),
        other => panic!("joined mismatched halves ({needle}): {other:?}"),
    };
    // Halves of two snapshots.
    refused(Checkpoint::join(state1.clone(), totals2.clone()), "iterations");
    // One with mirror maps, one without; maps of different sizes.
    let mut t = totals2.clone();
    t.mirrors = None;
    refused(Checkpoint::join(state2.clone(), t), "mirror");
    let mut t = totals2.clone();
    t.mirrors.as_mut().unwrap()[3].push([0.0; 3]);
    refused(Checkpoint::join(state2.clone(), t), "direction 3");
    let mut t = totals2.clone();
    t.total.pop();
    refused(Checkpoint::join(state2.clone(), t), "texel");
    // Truncated parts.
    let (head2, batches2) = state2.clone().into_parts();
    let (head_bytes, batch_bytes) = (head2.to_bytes(), batches2[0].to_bytes());
    let totals_bytes = totals2.to_bytes();
    assert!(StateHead::from_bytes(&head_bytes[..head_bytes.len() / 2]).is_err());
    assert!(UnshotBatch::from_bytes(&batch_bytes[..batch_bytes.len() - 1]).is_err());
    assert!(Totals::from_bytes(&totals_bytes[..totals_bytes.len() - 1]).is_err());
    assert!(Totals::from_bytes(&totals_bytes[..2]).is_err());
    // Parts missing, out of order, or of another snapshot.
    let parts_refused =
        |batches: Vec<UnshotBatch>, needle: &str| match ShootingState::from_parts(head2.clone(), batches) {
            Err(Error::Decode(m)) => assert!(m.contains(needle), "{m}"),
            other => panic!("assembled mismatched parts ({needle}): {other:?}"),
        };
    parts_refused(batches2[1..].to_vec(), "head says");
    let mut swapped = batches2.clone();
    swapped.swap(0, 1);
    parts_refused(swapped, "belongs");
    let mut foreign = batches2.clone();
    foreign[0] = state1.clone().into_parts().1[0].clone();
    parts_refused(foreign, "belongs");
    // A batch that does not fit is refused by the replica, which stays as it was.
    let mut r = Propagation::new(scene.clone(), options(3, 0)).unwrap();
    r.restore_head(head2.clone()).unwrap();
    let before = r.checkpoint();
    let mut bad = batches2[1].clone();
    bad.maps[0].push([0.0; 3]);
    assert!(r.restore_unshot(bad).is_err());
    let mut bad = batches2[1].clone();
    bad.maps[0][0][2] = -1.0;
    assert!(r.restore_unshot(bad).is_err());
    assert!(r.restore_unshot(state1.clone().into_parts().1[1].clone()).is_err());
    assert!(r.checkpoint() == before);
    let mut bad_head = head2.clone();
    bad_head.unshot_batches = bad_head.unshot_batches.map(|n| n + 1);
    assert!(r.restore_head(bad_head).is_err());
    // A shooting state that does not fit the scene is refused, and leaves the
    // propagation as it was.
    let mut r = Propagation::new(scene, options(3, 0)).unwrap();
    let before = r.checkpoint();
    let mut s = state2.clone();
    s.mirrors.as_mut().unwrap()[2][0][1] = f64::INFINITY;
    match r.restore_shooting(s) {
        Err(Error::Decode(m)) => assert!(m.contains("direction 2"), "{m}"),
        other => panic!("restored a non-finite mirror map: {other:?}"),
    }
    assert!(r.checkpoint() == before);
    let mut s = state2.clone();
    s.current.push([0.0; 3]);
    assert!(r.restore_shooting(s).is_err());
    r.restore_shooting(state2.clone()).unwrap();
    assert_eq!(r.iterations_done(), 2);
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
