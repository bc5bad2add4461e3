//! Checkpoints: stopping after any iteration and resuming from the stored
//! state gives the same bits as a run that never stopped, with and without
//! mirrors and perturbation; damaged state is refused, never used.

mod common;

use common::*;
use vlf_core::Error;
use vlf_core::propagate::specular::{MirrorPower, Pending, Settled};
use vlf_core::propagate::{
    Checkpoint, MapBatch, Options, Perturbation, Propagation, ShootingState, SnapshotBytes, StateHead, Stop, Totals,
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

fn map_batches(bytes: &[Vec<u8>]) -> Vec<MapBatch> {
    bytes.iter().map(|b| MapBatch::from_bytes(b).unwrap()).collect()
}

/// The shooting state from its stored parts.
fn shooting(parts: &SnapshotBytes) -> ShootingState {
    ShootingState::from_parts(
        StateHead::from_bytes(&parts.head).unwrap(),
        map_batches(&parts.shooting),
    )
    .unwrap()
}

/// The totals from their stored parts.
fn totals(parts: &SnapshotBytes) -> Totals {
    Totals::from_bytes(&parts.totals)
        .unwrap()
        .with_mirror_batches(map_batches(&parts.mirror_totals))
        .unwrap()
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
        let halves = first.snapshot_bytes(true);
        drop(first);
        let restored = Checkpoint::from_bytes(&bytes).unwrap();
        assert_eq!(restored.iterations(), stop_after);
        // The same state from its parts, as a store keeps them.
        let joined = Checkpoint::join(shooting(&halves), totals(&halves)).unwrap();
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
    c.mirrors.as_mut().unwrap()[4].shooting.push([0.0; 3]);
    expect_refused(c, "direction 4");
    // The arrivals of the first iteration wait to be reflected: their power
    // must fit every direction and mirror, and be power.
    assert!(
        good.pending.is_some(),
        "the lamp lights a mirror in the first iteration"
    );
    // Settled: finite power, per batch of targets the batches of sources, increasing, that exist.
    let settled = |c: &mut Checkpoint| c.pending.as_mut().unwrap().settled.as_mut().unwrap().clone();
    let with = |change: &dyn Fn(&mut Settled)| {
        let mut c = good.clone();
        let mut s = settled(&mut c);
        change(&mut s);
        c.pending.as_mut().unwrap().settled = Some(s);
        c
    };
    expect_refused(with(&|s| s.exchange.reflected[1] = f64::NAN), "pending");
    expect_refused(with(&|s| s.exchange.incident[0] = -1.0), "pending");
    expect_refused(with(&|s| drop(s.sources.pop())), "pending");
    expect_refused(with(&|s| s.sources[0].push(u32::MAX)), "pending");
    expect_refused(with(&|s| s.sources[0].extend([0, 0])), "pending");
    // As an earlier build stored them, every direction's `Φ_in` (sparse: per direction, the
    // mirrors that received power, by increasing number): it must fit every direction and
    // mirror, and be power.
    let l = good.mirrors.as_ref().unwrap().len();
    let pending = good.pending.as_ref().unwrap();
    let power: Vec<MirrorPower> = (0..l).map(|d| pending.power_in(d).unwrap().clone()).collect();
    let lit = power
        .iter()
        .position(|p| p.len() >= 2)
        .expect("a direction lights both mirrors");
    let with_power = |change: &dyn Fn(&mut Vec<MirrorPower>)| {
        let mut c = good.clone();
        let mut power = power.clone();
        change(&mut power);
        c.pending = Some(Pending::of_power_in(power));
        c
    };
    assert!(resume(with_power(&|_| {})).is_ok());
    expect_refused(with_power(&|p| p[lit].swap(0, 1)), "pending");
    expect_refused(with_power(&|p| p[lit].push((99, [1.0; 3]))), "pending");
    expect_refused(with_power(&|p| drop(p.pop())), "pending");
    expect_refused(with_power(&|p| p.push(Vec::new())), "pending");
    expect_refused(with_power(&|p| p[lit][0].1[0] = f64::NAN), "pending");
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
fn halves_are_the_whole_split_into_parts() {
    let scene = mirror_room();
    let mut p = Propagation::new(scene, options(3, 0)).unwrap();
    p.step(|_| {});
    p.step(|_| {});
    let whole = p.checkpoint();
    assert!(whole.pending.is_some(), "arrivals wait to be reflected");
    let (state, totals) = whole.clone().split();
    assert_eq!(state.iterations(), 2);
    assert_eq!(totals.iterations, 2);
    // Serialised straight from the propagation: the same bytes as the parts.
    let bytes = p.snapshot_bytes(true);
    let (head, batches) = state.clone().into_parts(options(3, 0).batching());
    let (diffuse_totals, total_batches) = totals.clone().into_parts(options(3, 0).batching());
    assert!(batches.len() > 1, "{} batches", batches.len());
    assert_eq!(total_batches.len(), batches.len());
    assert!(diffuse_totals.mirrors.is_none());
    assert_eq!(bytes.head, head.to_bytes());
    assert_eq!(
        bytes.shooting,
        batches.iter().map(MapBatch::to_bytes).collect::<Vec<_>>()
    );
    assert_eq!(bytes.totals, diffuse_totals.to_bytes());
    assert_eq!(
        bytes.mirror_totals,
        total_batches.iter().map(MapBatch::to_bytes).collect::<Vec<_>>()
    );
    // Without the maps (the service's coordinator, whose workers write
    // them): the same head and totals, no map.
    let lean = p.snapshot_bytes(false);
    assert_eq!(lean.head, bytes.head);
    assert_eq!(lean.totals, bytes.totals);
    assert!(lean.shooting.is_empty() && lean.mirror_totals.is_empty());
    assert!(Checkpoint::is_split(&bytes.head));
    assert!(ShootingState::from_parts(head, batches).unwrap() == state);
    assert!(diffuse_totals.with_mirror_batches(total_batches).unwrap() == totals);
    // The whole checkpoint round-trips, and gives its totals.
    let whole_bytes = whole.to_bytes();
    assert!(!Checkpoint::is_split(&whole_bytes));
    assert!(Checkpoint::from_bytes(&whole_bytes).unwrap() == whole);
    assert_eq!(Totals::from_bytes(&whole_bytes).unwrap(), totals);
    // A head is not a whole checkpoint.
    match Checkpoint::from_bytes(&bytes.head) {
        Err(Error::Decode(m)) => assert!(m.contains("split"), "{m}"),
        other => panic!("read a shooting state's head as a whole checkpoint: {other:?}"),
    }
    assert!(Checkpoint::join(state.clone(), totals.clone()).unwrap() == whole);
    // A replica restores the head, then only the batches it needs.
    let mut r = Propagation::new(mirror_room(), options(3, 0)).unwrap();
    r.restore_head(StateHead::from_bytes(&bytes.head).unwrap()).unwrap();
    assert_eq!(r.iterations_done(), 2);
    r.restore_shooting_batch(MapBatch::from_bytes(&bytes.shooting[1]).unwrap())
        .unwrap();
    r.restore_totals_batch(MapBatch::from_bytes(&bytes.mirror_totals[1]).unwrap())
        .unwrap();
    let restored = r.checkpoint();
    assert_eq!(restored.pending, whole.pending);
    let (got, want) = (restored.mirrors.unwrap(), whole.mirrors.unwrap());
    let batch1 = options(3, 0).batching().range(1);
    let mut lit = false;
    for (d, (got, want)) in got.iter().zip(&want).enumerate() {
        if batch1.contains(&d) {
            assert_eq!(got, want, "direction {d} of batch 1");
            lit |= want.shooting.iter().any(|v| v[0] > 0.0);
        } else {
            let zero = |m: &[[f64; 3]]| m.iter().all(|v| *v == [0.0; 3]);
            assert!(zero(&got.shooting) && zero(&got.total), "direction {d} outside batch 1");
        }
    }
    assert!(lit, "batch 1 holds no arrival: the test shows nothing");
}

/// A direction's maps in a version 1 checkpoint: unshot, total.
type MapsV1<'a> = (&'a [[f64; 3]], &'a [[f64; 3]]);

/// A whole checkpoint as builds before pending arrivals wrote it (version 1).
#[derive(serde::Serialize)]
struct WholeV1<'a> {
    version: u32,
    stats: &'a [vlf_core::propagate::IterationStats],
    current: &'a [[f64; 3]],
    total: &'a [[f64; 3]],
    mirrors: Option<Vec<MapsV1<'a>>>,
}

/// A shooting state's head as those builds wrote it (version 2).
#[derive(serde::Serialize)]
struct HeadV2<'a> {
    version: u32,
    stats: &'a [vlf_core::propagate::IterationStats],
    current: &'a [[f64; 3]],
    unshot_batches: Option<u32>,
}

#[test]
fn checkpoints_of_earlier_builds_still_read_and_resume_with_the_same_bits() {
    let scene = mirror_room();
    let mut straight = Propagation::new(scene.clone(), options(5, 0)).unwrap();
    straight.run(|_| {});
    // Earlier builds reflected the arrivals at the end of an iteration: their
    // checkpoints hold the gathered unshot maps and nothing pending.
    let mut p = Propagation::new(scene.clone(), options(5, 0)).unwrap();
    p.step(|_| {});
    p.step(|_| {});
    p.specular.as_mut().unwrap().gather_all(&p.scene, &p.directions);
    let gathered = p.checkpoint();
    assert!(gathered.pending.is_none());
    let mirrors = gathered.mirrors.as_ref().unwrap();
    assert!(mirrors.iter().any(|m| m.shooting.iter().any(|v| v[0] > 0.0)));
    let v1 = bincode::serialize(&WholeV1 {
        version: 1,
        stats: &gathered.stats,
        current: &gathered.current,
        total: &gathered.total,
        mirrors: Some(mirrors.iter().map(|m| (&m.shooting[..], &m.total[..])).collect()),
    })
    .unwrap();
    assert_eq!(
        vlf_core::propagate::snapshot::earlier::whole_v1(&gathered),
        Some(v1.clone()),
        "the helper other tests use writes the same layout"
    );
    let read = Checkpoint::from_bytes(&v1).unwrap();
    assert!(read == gathered);
    assert_eq!(Totals::from_bytes(&v1).unwrap(), gathered.clone().split().1);
    let mut resumed = Propagation::resume(scene, options(5, 0), read).unwrap();
    resumed.run(|_| {});
    assert!(
        state(&resumed) == state(&straight),
        "an earlier build's checkpoint resumed to other bits"
    );
    // Its head in parts (version 2), with the unshot maps by batch.
    let (shooting, _) = gathered.split();
    let (head, batches) = shooting.clone().into_parts(options(3, 0).batching());
    let v2 = bincode::serialize(&HeadV2 {
        version: 2,
        stats: &head.stats,
        current: &head.current,
        unshot_batches: head.mirror_batches,
    })
    .unwrap();
    assert_eq!(vlf_core::propagate::snapshot::earlier::head_v2(&head), Some(v2.clone()));
    assert!(Checkpoint::is_split(&v2));
    let old_head = StateHead::from_bytes(&v2).unwrap();
    assert!(!old_head.mirror_totals_by_batch());
    assert!(
        StateHead::from_bytes(&head.to_bytes())
            .unwrap()
            .mirror_totals_by_batch()
    );
    assert!(ShootingState::from_parts(old_head, batches).unwrap() == shooting);
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
    let (head2, batches2) = state2.clone().into_parts(options(3, 0).batching());
    let (head_bytes, batch_bytes) = (head2.to_bytes(), batches2[0].to_bytes());
    let totals_bytes = totals2.to_bytes();
    assert!(StateHead::from_bytes(&head_bytes[..head_bytes.len() / 2]).is_err());
    assert!(MapBatch::from_bytes(&batch_bytes[..batch_bytes.len() - 1]).is_err());
    assert!(Totals::from_bytes(&totals_bytes[..totals_bytes.len() - 1]).is_err());
    assert!(Totals::from_bytes(&totals_bytes[..2]).is_err());
    // Parts missing, out of order, or of another snapshot.
    let parts_refused = |batches: Vec<MapBatch>, needle: &str| match ShootingState::from_parts(head2.clone(), batches) {
        Err(Error::Decode(m)) => assert!(m.contains(needle), "{m}"),
        other => panic!("assembled mismatched parts ({needle}): {other:?}"),
    };
    parts_refused(batches2[1..].to_vec(), "head says");
    let mut swapped = batches2.clone();
    swapped.swap(0, 1);
    parts_refused(swapped, "belongs");
    let mut foreign = batches2.clone();
    foreign[0] = state1.clone().into_parts(options(3, 0).batching()).1[0].clone();
    parts_refused(foreign, "belongs");
    // A batch that does not fit is refused by the replica, which stays as it was.
    let mut r = Propagation::new(scene.clone(), options(3, 0)).unwrap();
    r.restore_head(head2.clone()).unwrap();
    let before = r.checkpoint();
    let mut bad = batches2[1].clone();
    bad.maps[0].push([0.0; 3]);
    assert!(r.restore_shooting_batch(bad.clone()).is_err());
    assert!(r.restore_totals_batch(bad).is_err());
    let mut bad = batches2[1].clone();
    bad.maps[0][0][2] = -1.0;
    assert!(r.restore_shooting_batch(bad.clone()).is_err());
    assert!(r.restore_totals_batch(bad).is_err());
    assert!(
        r.restore_shooting_batch(state1.clone().into_parts(options(3, 0).batching()).1[1].clone())
            .is_err()
    );
    assert!(r.checkpoint() == before);
    let mut bad_head = head2.clone();
    bad_head.mirror_batches = bad_head.mirror_batches.map(|n| n + 1);
    assert!(r.restore_head(bad_head).is_err());
    let mut bad_head = head2.clone();
    (bad_head.pending.as_mut().unwrap().settled.as_mut().unwrap()).sources[0].push(u32::MAX);
    assert!(r.restore_head(bad_head).is_err());
    assert!(r.checkpoint() == before);
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
    // A vertex outside the unit ball, where no ray of any subfield goes (a texel walk over it
    // would never end): finite, and still refused.
    let mut broken = scene.clone();
    broken.surfaces[1].vertices[0].x = 1e6;
    match Scene::from_bytes(&broken.to_bytes()) {
        Err(Error::Decode(m)) => assert!(m.contains("outside the scene's frame"), "{m}"),
        other => panic!("a vertex at 1e6 was accepted: {other:?}"),
    }
    let mut broken = scene;
    broken.materials[0].diffuse[0] = 1.5;
    assert!(matches!(Scene::from_bytes(&broken.to_bytes()), Err(Error::Decode(_))));
}

/// Earlier builds stored every direction's pending `Φ_in`, dense (a value for every mirror, zeros
/// included: whole checkpoints of version 3, heads of version 4), then sparse (versions 5 and
/// 6): they read as the same arrivals, settle as this build settles them, and resume to the
/// bits of a run that never stopped.
#[test]
fn pending_power_of_earlier_builds_is_settled_as_it_is_restored() {
    use vlf_core::propagate::snapshot::earlier;
    let scene = mirror_room();
    let mut straight = Propagation::new(scene.clone(), options(5, 0)).unwrap();
    straight.run(|_| {});
    let mut p = Propagation::new(scene.clone(), options(5, 0)).unwrap();
    p.step(|_| {});
    p.step(|_| {});
    let c = p.checkpoint();
    let l = p.directions.len();
    let mirrors = p.specular.as_ref().unwrap().mirrors.len();
    let pending = c.pending.as_ref().expect("arrivals wait to be reflected");
    let known = |p: &Pending| -> Vec<MirrorPower> { (0..l).map(|d| p.power_in(d).unwrap().clone()).collect() };
    assert!(
        known(pending).iter().any(|v| !v.is_empty() && v.len() < mirrors),
        "some lit direction misses a mirror: the dense table holds zeros the sparse one leaves out"
    );
    let (head, _) = c.clone().split().0.into_parts(options(5, 0).batching());
    for sparse in [false, true] {
        let read = Checkpoint::from_bytes(&earlier::whole_of_power(&c, mirrors, sparse)).unwrap();
        let old = read.pending.as_ref().unwrap();
        assert!(old.settled.is_none(), "an earlier build's arrivals are not settled");
        assert_eq!(known(old), known(pending), "Φ_in read otherwise (sparse: {sparse})");
        let old_head = StateHead::from_bytes(&earlier::head_of_power(&head, l, mirrors, sparse)).unwrap();
        assert!(old_head.mirror_totals_by_batch());
        assert_eq!(known(old_head.pending.as_ref().unwrap()), known(pending));
        // Restored, they settle to this build's bits.
        let mut replica = Propagation::new(scene.clone(), options(5, 0)).unwrap();
        replica.restore_head(old_head).unwrap();
        assert_eq!(
            replica.specular.as_ref().unwrap().pending.as_ref().unwrap().settled,
            pending.settled
        );
        let mut resumed = Propagation::resume(scene.clone(), options(5, 0), read).unwrap();
        assert!(resumed.checkpoint() == c, "resumed otherwise (sparse: {sparse})");
        resumed.run(|_| {});
        assert!(state(&resumed) == state(&straight), "resumed to other bits");
    }
}
