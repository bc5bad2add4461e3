//! Light-field jobs through the store, on every backend: a crash between
//! writing a snapshot's blobs and committing it, then a resume, gives the
//! same bits as a run that never stopped; every stage reads back within its
//! encoding's error; damaged or mismatched blobs are errors naming their key.

#[allow(dead_code)]
#[macro_use]
mod suite;

use suite::Opener;
use vlf_core::field::LightField;
use vlf_core::propagate::snapshot::earlier;
use vlf_core::propagate::{Checkpoint, Options, Propagation, StateHead, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::{ImportOptions, Scene, load_obj};
use vlf_store::blob::{self, BlobKind, Encoding};
use vlf_store::{FieldJob, JobId, MapPart, SnapshotWriter, Stage, Store, StoreError, layout};

fn bundled(name: &str) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name);
    load_obj(&path, &ImportOptions::default()).expect("bundled scene").0
}

fn options(iterations: u32) -> Options {
    Options {
        directions: 33,
        grid: GridSize::new(16, 4).unwrap(),
        stop: Stop::Iterations(iterations),
        ..Options::default()
    }
}

/// Propagates `scene` to the end in a new job, writing every snapshot and the field.
fn run(store: &Store, scene: &Scene, encoding: Encoding) -> (FieldJob, LightField) {
    let mut p = Propagation::new(scene.clone(), options(4)).unwrap();
    let mut job = FieldJob::create(store, &p, encoding).unwrap();
    while !p.finished() {
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
    }
    let field = p.into_field();
    job.finish(&field, false).unwrap();
    (job, field)
}

fn without_times(mut c: Checkpoint) -> Checkpoint {
    for s in &mut c.stats {
        s.seconds = 0.0;
    }
    c
}

fn crash_and_resume(o: &Opener) {
    let scene = bundled("mirrors.obj");
    let (straight, _) = run(&o.open(), &scene, Encoding::F32);

    // A run that dies after committing snapshot 2, half-way through writing snapshot 3.
    let store = o.open();
    let mut p = Propagation::new(scene.clone(), options(4)).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    for _ in 0..2 {
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
    }
    p.step(|_| {});
    let id = job.id().clone();
    job.job()
        .put_diffuse(Stage::Iteration(3), 0, &[1, 1, 3], &[9.0; 3])
        .unwrap();
    job.job().put_state(3, b"half-written state").unwrap();
    drop((job, p, store));

    // A new process opens the job: snapshot 2 is the last; resuming reaches the same bits.
    let store = o.open();
    let mut job = FieldJob::open(&store, &id).unwrap();
    assert_eq!(job.job().last_finished(), Some(2));
    assert!(
        job.load(Stage::Iteration(3)).is_err(),
        "an uncommitted snapshot was readable"
    );
    let mut p = job.resume().unwrap();
    assert_eq!(p.iterations_done(), 2);
    while !p.finished() {
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
    }
    job.finish(&p.into_field(), false).unwrap();

    assert_eq!(job.job().manifest().finished_iterations, vec![0, 1, 2, 3, 4]);
    assert!(
        without_times(job.checkpoint(4).unwrap()) == without_times(straight.checkpoint(4).unwrap()),
        "resumed state differs"
    );
    // The stored radiance of the final field is the same, byte for byte.
    let keys = |j: &FieldJob| -> Vec<(String, Vec<u8>)> {
        let prefix = layout::stage_prefix(j.id(), Stage::Field).unwrap();
        let store = j.job().store();
        store
            .list(&prefix)
            .unwrap()
            .into_iter()
            .filter(|k| !k.ends_with("summary.blob"))
            .map(|k| (k[prefix.len()..].to_string(), store.get(&k).unwrap().to_vec()))
            .collect()
    };
    let (a, b) = (keys(&job), keys(&straight));
    assert!(a.iter().any(|(k, _)| k.starts_with("dirs/")), "no mirror tile stored");
    assert!(a == b, "final field blobs differ after a resume");
    assert!(matches!(job.resume(), Err(StoreError::Job { reason, .. }) if reason.contains("finished")));
}

/// `|a − b| ≤ rel·|a| + abs` for every value.
fn assert_close(a: &[[f32; 3]], b: &[[f32; 3]], rel: f32, abs: f32, what: &str) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        let peak = x.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for c in 0..3 {
            let err = (x[c] - y[c]).abs();
            assert!(err <= rel * peak + abs, "{what}: {x:?} read back as {y:?}");
        }
    }
}

fn encodings_and_snapshots(o: &Opener) {
    let mut scene = bundled("mirrors.obj");
    // Emission far beyond f16's range (65 504): the stored unit keeps it representable.
    for m in &mut scene.materials {
        m.emission = m.emission.map(|e| e * 1e6);
    }
    let store = o.open();
    for (encoding, rel) in [
        (Encoding::F32, 0.0),
        (Encoding::F16, 2f32.powi(-11)),
        (Encoding::Rgb9e5, 2f32.powi(-9)),
    ] {
        let (job, field) = run(&store, &scene, encoding);
        let unit = job.summary(Stage::Field).unwrap().radiance_unit as f32;
        assert!(unit >= 1e6, "{unit}");
        let back = job.load(Stage::Field).unwrap();
        let abs = if rel == 0.0 { 0.0 } else { unit * 2f32.powi(-24) };
        assert_close(
            &field.radiance,
            &back.radiance,
            rel,
            abs,
            &format!("{encoding:?} diffuse"),
        );
        let (a, b) = (field.specular.as_ref().unwrap(), back.specular.as_ref().unwrap());
        for (ta, tb) in a.totals.iter().zip(&b.totals) {
            assert_close(ta, tb, rel, abs, &format!("{encoding:?} mirrors"));
        }
        // Snapshot 0 is emission only; the last snapshot is the field (nothing was re-sampled).
        let zero = job.load(Stage::Iteration(0)).unwrap();
        for (t, material) in zero.atlas.texel_materials().iter().enumerate() {
            let emits = zero.scene.materials[*material as usize].is_emitter();
            if !emits {
                assert_eq!(zero.radiance[t], [0.0; 3], "texel {t} of a non-emitter");
            } else if zero.covered[t] {
                assert!(zero.radiance[t][0] > 0.0, "texel {t} of an emitter");
            }
        }
        assert!(
            zero.specular
                .as_ref()
                .unwrap()
                .totals
                .iter()
                .flatten()
                .all(|v| *v == [0.0; 3])
        );
        let last = job.load(Stage::Iteration(4)).unwrap();
        assert_close(&back.radiance, &last.radiance, 0.0, 0.0, "last snapshot");
        // Its mirror radiance is stored in the job's encoding as the field's is: the same bits.
        assert_close(
            &back.specular.as_ref().unwrap().totals.concat(),
            &last.specular.as_ref().unwrap().totals.concat(),
            0.0,
            0.0,
            "last snapshot mirrors",
        );
        // Stages read on one geometry are what each reads alone; a stage the job does not have
        // is an error of its own, which leaves the others read.
        let each = job
            .load_each(&[Stage::Field, Stage::Iteration(1), Stage::Iteration(9)])
            .unwrap();
        assert_eq!(each.len(), 3);
        assert!(
            each[0].as_ref().unwrap() == &back,
            "{encoding:?}: the field read with others"
        );
        assert!(
            each[1].as_ref().unwrap() == &job.load(Stage::Iteration(1)).unwrap(),
            "{encoding:?}: snapshot 1"
        );
        assert!(each[2].is_err(), "snapshot 9 of a job of 4 iterations");
    }
}

fn damage_names_the_key(o: &Opener) {
    let store = o.open();
    let (job, _) = run(&store, &bundled("mirrors.obj"), Encoding::F16);
    let id = job.id().clone();
    let expect = |r: Result<LightField, StoreError>, key: &str, needle: &str| match r {
        Ok(_) => panic!("damaged `{key}` was accepted"),
        Err(e) => {
            let m = e.to_string();
            assert!(m.contains(key) && m.contains(needle), "{m}");
        }
    };
    // A flipped byte in a direction's mirror radiance.
    let tile = layout::direction(&id, Stage::Field, 5).unwrap();
    let good = store.get(&tile).unwrap().to_vec();
    let mut bad = good.clone();
    let last = bad.len() - 1;
    bad[last] ^= 0x10;
    store.put(&tile, bad).unwrap();
    expect(job.load(Stage::Field), &tile, "checksum");
    // Truncated.
    store.put(&tile, good[..good.len() / 2].to_vec()).unwrap();
    expect(job.load(Stage::Field), &tile, "");
    // A valid blob of the wrong shape: one slot short, one slot over.
    let (shape, values) = blob::decode_values(&good, BlobKind::DirectionRadiance).unwrap();
    for slots in [shape[0] - 1, shape[0] + 1] {
        let mut values = values.clone();
        values.resize(3 * slots as usize, 0.5);
        let wrong = blob::encode_values(BlobKind::DirectionRadiance, Encoding::F16, &[slots, 3], &values).unwrap();
        store.put(&tile, wrong).unwrap();
        expect(job.load(Stage::Field), &tile, "shape");
    }
    // A tile's blob where a direction's belongs.
    let tile_kind = blob::encode_values(BlobKind::TileRadiance, Encoding::F16, &shape, &values).unwrap();
    store.put(&tile, tile_kind).unwrap();
    expect(job.load(Stage::Field), &tile, "kind");
    store.put(&tile, good).unwrap();
    assert!(job.load(Stage::Field).is_ok());
    // A summary whose radiance unit is not a power of two, or one that f32 cannot hold (every
    // radiance would read as 0, a black picture, or as ∞).
    let key = layout::summary(&id, Stage::Field).unwrap();
    let good = store.get(&key).unwrap().to_vec();
    for unit in [2f64.powi(-200), 2f64.powi(200), 3.0] {
        let json = blob::decode_bytes(&good, BlobKind::Summary).unwrap();
        let mut summary: serde_json::Value = serde_json::from_slice(&json).unwrap();
        summary["radiance_unit"] = serde_json::json!(unit);
        let json = serde_json::to_vec(&summary).unwrap();
        store
            .put(&key, blob::encode_bytes(BlobKind::Summary, &json).unwrap())
            .unwrap();
        match job.load(Stage::Field) {
            Ok(_) => panic!("a radiance unit of {unit:e} was accepted"),
            Err(e) => assert!(e.to_string().contains("radiance unit"), "{e}"),
        }
    }
    store.put(&key, good).unwrap();
    assert!(job.load(Stage::Field).is_ok());
    // A diffuse map of the wrong kind.
    let map = layout::diffuse(&id, Stage::Iteration(2), 0).unwrap();
    let tile_kind = blob::encode_values(BlobKind::TileRadiance, Encoding::F16, &[1, 3], &[0.5; 3]).unwrap();
    store.put(&map, tile_kind).unwrap();
    expect(job.load(Stage::Iteration(2)), &map, "kind");
    // A checkpoint whose blob is sound but whose content is not a checkpoint.
    let state = layout::state(&id, 3).unwrap();
    store
        .put(&state, blob::encode_bytes(BlobKind::Snapshot, b"not bincode").unwrap())
        .unwrap();
    let err = job.checkpoint(3).unwrap_err();
    assert!(matches!(err, StoreError::Field { .. }), "{err}");
    // Unknown jobs, and snapshots that do not exist.
    let missing = FieldJob::open(&store, &JobId::parse("no-such-job").unwrap()).unwrap_err();
    assert!(matches!(missing, StoreError::NotFound { .. }), "{missing}");
    let err = job.load(Stage::Iteration(9)).unwrap_err();
    assert!(err.to_string().contains("iteration 9 is not finished"), "{err}");
    // The rest of the job is untouched.
    assert!(job.load(Stage::Iteration(1)).is_ok());
}

/// Takes `flag` (true) out of the summary of `stage`, as earlier builds wrote it.
fn summary_without(store: &Store, id: &JobId, stage: Stage, flag: &str) {
    let key = layout::summary(id, stage).unwrap();
    let json = blob::decode_bytes(&store.get(&key).unwrap(), BlobKind::Summary).unwrap();
    let mut summary: serde_json::Value = serde_json::from_slice(&json).unwrap();
    assert_eq!(summary[flag], serde_json::Value::Bool(true), "{flag} of {stage:?}");
    summary.as_object_mut().unwrap().remove(flag);
    let json = serde_json::to_vec(&summary).unwrap();
    store
        .put(&key, blob::encode_bytes(BlobKind::Summary, &json).unwrap())
        .unwrap();
}

/// A final field as earlier builds stored it — mirror radiance one blob per direction and tile,
/// a summary that does not say `mirrors_by_direction` — reads back as this build's does.
fn earlier_final_fields(o: &Opener) {
    let store = o.open();
    let (job, _) = run(&store, &bundled("mirrors.obj"), Encoding::F16);
    let id = job.id().clone();
    let now = job.load(Stage::Field).unwrap();
    let spec = now.specular.as_ref().unwrap();
    let per_side = job.options().grid.tiles_per_side();
    let mut tiles = 0;
    for (d, view) in spec.views.iter().enumerate() {
        let l = &view.layout;
        let key = layout::direction(&id, Stage::Field, d as u32).unwrap();
        if l.len == 0 {
            assert!(
                !store.exists(&key).unwrap(),
                "a blob for direction {d}, which has no mirror slot"
            );
            continue;
        }
        let (_, values) = blob::decode_values(&store.get(&key).unwrap(), BlobKind::DirectionRadiance).unwrap();
        for (k, range) in l.tile_slots(&view.sub) {
            let (s, t) = (k % per_side, k / per_side);
            let tile = &values[3 * range.start..3 * range.end];
            job.job()
                .put_tile(Stage::Field, d as u32, s, t, &[range.len() as u32, 3], tile)
                .unwrap();
            tiles += 1;
        }
        store.delete(&key).unwrap();
    }
    assert!(
        tiles > spec.views.iter().filter(|v| v.slots() > 0).count(),
        "several tiles a direction"
    );
    summary_without(&store, &id, Stage::Field, "mirrors_by_direction");

    let job = FieldJob::open(&store, &id).unwrap();
    assert!(!job.summary(Stage::Field).unwrap().mirrors_by_direction);
    let then = job.load(Stage::Field).unwrap();
    assert_eq!(then.radiance, now.radiance);
    assert_eq!(then.specular.as_ref().unwrap().totals, spec.totals);
}

/// Snapshots written while the next iteration runs ([`SnapshotWriter`]) are the snapshots
/// written in place, committed in order; one whose write fails is reported, is not listed, and
/// leaves the ones before it as they were.
fn snapshots_written_behind(o: &Opener) {
    let scene = bundled("mirrors.obj");
    let (in_place, field) = run(&o.open(), &scene, Encoding::F32);

    let store = o.open();
    let mut p = Propagation::new(scene.clone(), options(4)).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    let mut writer = SnapshotWriter::new();
    while !p.finished() {
        p.step(|_| {});
        writer.write(&mut job, &p).unwrap();
        assert_eq!(writer.writing(), Some(p.iterations_done()));
        // The one before is committed by now; this one is not yet listed.
        assert_eq!(job.job().last_finished(), Some(p.iterations_done() - 1));
    }
    writer.finish(&mut job).unwrap();
    assert_eq!(writer.writing(), None);
    let reopened = FieldJob::open(&store, job.id()).unwrap();
    assert_eq!(reopened.job().manifest().finished_iterations, vec![0, 1, 2, 3, 4]);
    for k in 0..=4 {
        assert_eq!(
            without_times(reopened.checkpoint(k).unwrap()),
            without_times(in_place.checkpoint(k).unwrap()),
            "checkpoint {k}"
        );
        let (a, b) = (
            reopened.load(Stage::Iteration(k)).unwrap(),
            in_place.load(Stage::Iteration(k)).unwrap(),
        );
        assert_eq!(a.radiance, b.radiance, "snapshot {k}");
        assert_eq!(
            a.specular.unwrap().totals,
            b.specular.unwrap().totals,
            "snapshot {k}'s mirrors"
        );
    }
    job.finish(&field, false).unwrap();

    // A blob of snapshot 2 already there with other bytes: its write fails behind the
    // propagation, and the failure comes out at the next call.
    let store = o.open();
    let mut p = Propagation::new(scene.clone(), options(4)).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    let squatter = layout::map_part(job.id(), 2, MapPart::Shooting, 0).unwrap();
    store
        .put(
            &squatter,
            blob::encode_bytes(BlobKind::Snapshot, b"other bytes").unwrap(),
        )
        .unwrap();
    let mut writer = SnapshotWriter::new();
    p.step(|_| {});
    writer.write(&mut job, &p).unwrap();
    p.step(|_| {});
    writer.write(&mut job, &p).unwrap();
    let err = writer.finish(&mut job).unwrap_err();
    assert!(err.to_string().contains(&squatter), "{err}");
    let reopened = FieldJob::open(&store, job.id()).unwrap();
    assert_eq!(reopened.job().manifest().finished_iterations, vec![0, 1]);
    assert!(reopened.load(Stage::Iteration(1)).is_ok());
    assert_eq!(
        without_times(reopened.checkpoint(1).unwrap()),
        without_times(in_place.checkpoint(1).unwrap())
    );
}

per_backend! {
    crash_then_resume_gives_the_same_bits => crate::crash_and_resume,
    snapshots_written_behind_are_those_written_in_place => crate::snapshots_written_behind,
    earlier_final_fields_read_back => crate::earlier_final_fields,
    encodings_and_snapshots_read_back => crate::encodings_and_snapshots,
    damaged_blobs_name_their_key => crate::damage_names_the_key,
}

/// Rewrites snapshot `k` of job `id` as an earlier build left it — the whole checkpoint in
/// `state.blob` (`whole`), or a version 2 head with unshot maps by batch and all the totals in
/// `totals.blob` — and returns the checkpoint it holds: this build's, with the pending arrivals
/// reflected (earlier builds reflected them at the end of an iteration).
fn as_earlier_build(store: &Store, id: &JobId, k: u32, whole: bool) -> Checkpoint {
    let job = FieldJob::open(store, id).unwrap();
    let current = job.checkpoint(k).unwrap();
    let mut p = Propagation::resume(job.scene().clone(), job.options().clone(), current).unwrap();
    p.specular.as_mut().unwrap().gather_all(&p.scene, &p.directions);
    let gathered = p.checkpoint();
    let (shooting, totals) = gathered.clone().split();
    let (head, unshot) = shooting.into_parts(job.options().batching());
    let put = |key: &str, bytes: &[u8]| {
        store
            .put(key, blob::encode_bytes(BlobKind::Snapshot, bytes).unwrap())
            .unwrap()
    };
    let (state_key, totals_key) = (layout::state(id, k).unwrap(), layout::totals(id, k).unwrap());
    for b in 0..unshot.len() as u32 {
        for part in [MapPart::Shooting, MapPart::Totals, MapPart::Radiance, MapPart::Unshot] {
            store.delete(&layout::map_part(id, k, part, b).unwrap()).unwrap();
        }
    }
    if whole {
        put(&state_key, &earlier::whole_v1(&gathered).unwrap());
        store.delete(&totals_key).unwrap();
    } else {
        put(&state_key, &earlier::head_v2(&head).unwrap());
        put(&totals_key, &totals.to_bytes());
        for part in &unshot {
            put(
                &layout::map_part(id, k, MapPart::Unshot, part.batch).unwrap(),
                &part.to_bytes(),
            );
        }
    }
    gathered
}

/// A job that an earlier build stopped after snapshot 2 is taken up by this build's coordinator
/// and a worker, which write this build's snapshots from there on, and ends with the bits of a
/// run that never stopped.
#[test]
fn jobs_stopped_by_earlier_builds_resume_with_the_same_bits() {
    let store = Store::open("memory://").unwrap();
    let scene = bundled("mirrors.obj");
    let (reference, _) = run(&store, &scene, Encoding::F32);
    for whole in [false, true] {
        let mut p = Propagation::new(scene.clone(), options(4)).unwrap();
        let mut job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
        for _ in 0..2 {
            p.step(|_| {});
            job.write_snapshot(&p).unwrap();
        }
        let id = job.id().clone();
        as_earlier_build(&store, &id, 2, whole);
        let mut coordinator = vlf_store::Coordinator::resume(FieldJob::open(&store, &id).unwrap()).unwrap();
        let mut replica = vlf_store::Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
        while !coordinator.finished() {
            let k = coordinator.iteration();
            while let Some((pass, batches)) = coordinator.pending_pass() {
                replica.compute(k, pass, 0..batches).unwrap();
                coordinator.absorb_pass().unwrap();
            }
            coordinator.finish_iteration().unwrap();
        }
        let done = coordinator.finish(false).unwrap();
        assert!(
            without_times(done.checkpoint(4).unwrap()) == without_times(reference.checkpoint(4).unwrap()),
            "resumed from an earlier build's {} snapshot",
            if whole { "whole" } else { "version 2" }
        );
        assert!(
            done.load(Stage::Field).unwrap().specular.unwrap().totals
                == reference.load(Stage::Field).unwrap().specular.unwrap().totals
        );
    }
}

/// A job stored before passes were cut by `pass_batches` and batches into stints (manifest
/// format 3, parameters without either) was cut into 16 batches of directions summed one by
/// one: it reads as such, its snapshots' mirror maps by the batches it wrote, and it resumes to
/// the bits of a run that never stopped — where this build's default cut (64 a pass, fewer at
/// this l, stints of 8) gives other bits.
#[test]
fn jobs_of_format_3_read_and_resume_as_they_ran() {
    use vlf_core::propagate::defaults::{LEGACY_PASS_BATCHES, LEGACY_STINT_DIRECTIONS, PASS_BATCHES, STINT_DIRECTIONS};
    let store = Store::open("memory://").unwrap();
    let scene = bundled("mirrors.obj");
    let legacy = Options {
        directions: 513,
        pass_batches: LEGACY_PASS_BATCHES,
        stint_directions: LEGACY_STINT_DIRECTIONS,
        ..options(4)
    };
    let now = Options {
        pass_batches: PASS_BATCHES,
        stint_directions: STINT_DIRECTIONS,
        ..legacy.clone()
    };
    assert!(
        legacy.batching().count() != now.batching().count() && legacy.batching().stint() != now.batching().stint(),
        "the test needs an l whose cut the options change"
    );
    let mut straight = Propagation::new(scene.clone(), legacy.clone()).unwrap();
    straight.run(|_| {});

    // Two snapshots written by the legacy cut, then the manifest made what format 3 wrote.
    let mut p = Propagation::new(scene.clone(), legacy.clone()).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    for _ in 0..2 {
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
    }
    let id = job.id().clone();
    let viewed = job.load(Stage::Iteration(2)).unwrap();
    let written = job.job().manifest().clone();
    let mut manifest = written.clone();
    manifest.format = 3;
    for key in ["pass_batches", "stint_directions"] {
        manifest.parameters.as_object_mut().unwrap().remove(key).unwrap();
    }
    store.put(&layout::manifest(&id), manifest.to_blob().unwrap()).unwrap();

    // From the format that added it, each must be named: without it, the job is refused rather
    // than read as it was before.
    for (format, key) in [(4, "pass_batches"), (7, "stint_directions")] {
        let mut unnamed = written.clone();
        unnamed.format = format;
        unnamed.parameters.as_object_mut().unwrap().remove(key).unwrap();
        if format < 7 {
            unnamed.parameters.as_object_mut().unwrap().remove("stint_directions");
        }
        store.put(&layout::manifest(&id), unnamed.to_blob().unwrap()).unwrap();
        let refused = match FieldJob::open(&store, &id) {
            Ok(_) => panic!("format {format} without {key} was read"),
            Err(e) => e.to_string(),
        };
        assert!(refused.contains(key), "{refused}");
    }
    // Format 6 names the cut but not the stint: one direction, as it ran.
    let mut six = written.clone();
    six.format = 6;
    six.parameters
        .as_object_mut()
        .unwrap()
        .remove("stint_directions")
        .unwrap();
    store.put(&layout::manifest(&id), six.to_blob().unwrap()).unwrap();
    assert_eq!(FieldJob::open(&store, &id).unwrap().options(), &legacy);
    store.put(&layout::manifest(&id), manifest.to_blob().unwrap()).unwrap();

    let old = FieldJob::open(&store, &id).unwrap();
    assert_eq!(old.job().manifest().format, 3);
    assert_eq!(
        old.options(),
        &legacy,
        "format 3 parameters read as 16 batches a pass of single directions"
    );
    let back = old.load(Stage::Iteration(2)).unwrap();
    assert_eq!(back.radiance, viewed.radiance);
    assert_eq!(back.specular.unwrap().totals, viewed.specular.unwrap().totals);

    // A coordinator and a worker take it up and end where the straight run did.
    let mut coordinator = vlf_store::Coordinator::resume(FieldJob::open(&store, &id).unwrap()).unwrap();
    let mut replica = vlf_store::Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
    while !coordinator.finished() {
        let k = coordinator.iteration();
        while let Some((pass, batches)) = coordinator.pending_pass() {
            assert_eq!(batches, 16, "l = 513 cut into 16 batches, not the 32 of the default");
            replica.compute(k, pass, 0..batches).unwrap();
            coordinator.absorb_pass().unwrap();
        }
        coordinator.finish_iteration().unwrap();
    }
    let done = coordinator.finish(false).unwrap();
    assert!(without_times(done.checkpoint(4).unwrap()) == without_times(straight.checkpoint()));
}

/// Jobs of earlier builds hold a snapshot's checkpoint whole in `state.blob` (the first builds)
/// or as a version 2 head whose unshot maps are in `unshot/BBBBB.blob` and whose mirror totals
/// are in `totals.blob` whole; both hold the arrivals already reflected (unshot maps), none
/// pending. They stay readable: checkpointed, shot from with the same bits, and viewed.
#[test]
fn snapshots_of_earlier_builds_still_read() {
    let store = Store::open("memory://").unwrap();
    let scene = bundled("mirrors.obj");
    let (job, _) = run(&store, &scene, Encoding::F32);
    let id = job.id().clone();
    let current = job.checkpoint(2).unwrap();
    assert!(current.pending.is_some(), "arrivals wait to be reflected");
    let viewed = job.load(Stage::Iteration(2)).unwrap();
    let open_parts = || vlf_store::StageParts::open(FieldJob::open(&store, &id).unwrap(), Stage::Iteration(2)).unwrap();
    let parts = open_parts();
    let geometry = parts.geometry().unwrap();
    let catalog = vlf_core::parts::PartCatalog::new(&geometry);
    let tile = (0..catalog.len() as u32)
        .find(|&i| matches!(catalog.part(i), vlf_core::parts::Part::Tile { .. }))
        .expect("the mirror scene has mirror tiles");
    let radiance_key = parts.key(&catalog, tile).unwrap();
    assert!(
        radiance_key.contains("/mirror-radiance/") && parts.is_shared(&radiance_key),
        "{radiance_key}"
    );
    // As the builds of store format 5 wrote it: exact totals by batch and no radiance parts (a
    // summary that does not name them). It renders from the totals, with the same bits in
    // `f32`.
    summary_without(&store, &id, Stage::Iteration(2), "mirror_radiance_by_batch");
    for b in 0..job.options().batching().count() as u32 {
        store
            .delete(&layout::map_part(&id, 2, MapPart::Radiance, b).unwrap())
            .unwrap();
    }
    let parts = open_parts();
    let batch_key = parts.key(&catalog, tile).unwrap();
    assert!(
        batch_key.contains("/mirror-totals/") && parts.is_shared(&batch_key) && !parts.is_shared(&radiance_key),
        "{batch_key}"
    );
    let back = FieldJob::open(&store, &id).unwrap().load(Stage::Iteration(2)).unwrap();
    assert_eq!(back.radiance, viewed.radiance);
    assert_eq!(back.specular.unwrap().totals, viewed.specular.as_ref().unwrap().totals);

    // A worker shoots the iteration after snapshot 2 from this build's parts.
    let pass = vlf_core::propagate::Pass::Shoot;
    let batches = job.options().batching().count();
    let shoot = || {
        let mut replica = vlf_store::Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
        replica.compute(2, pass, 0..batches).unwrap();
        let key = layout::work_block(&id, 2, "shoot", 0, batches as u32).unwrap();
        let out = job.get_batch(2, pass, 0..batches).unwrap();
        store.delete(&key).unwrap();
        out
    };
    let from_parts = shoot();
    assert!(from_parts.arrivals.is_some(), "the shot reports its mirror arrivals");

    let (state_key, totals_key) = (layout::state(&id, 2).unwrap(), layout::totals(&id, 2).unwrap());
    for (layout_name, whole) in [("version 2 head", false), ("whole checkpoint", true)] {
        let gathered = as_earlier_build(&store, &id, 2, whole);
        let old = FieldJob::open(&store, &id).unwrap();
        assert!(old.checkpoint(2).unwrap() == gathered, "{layout_name}");
        let parts = open_parts();
        let key = parts.key(&catalog, tile).unwrap();
        assert_eq!(&key, if whole { &state_key } else { &totals_key }, "{layout_name}");
        assert!(parts.is_shared(&key) && !parts.is_shared(&batch_key), "{layout_name}");
        // A worker shoots the same block with the same bits, and writes the same maps for
        // snapshot 3 (they are create-only: other bytes would be refused).
        assert!(shoot() == from_parts, "{layout_name}");
        let back = old.load(Stage::Iteration(2)).unwrap();
        assert_eq!(back.radiance, viewed.radiance, "{layout_name}");
        assert_eq!(
            back.specular.as_ref().unwrap().totals,
            viewed.specular.as_ref().unwrap().totals,
            "mirror radiance of a {layout_name}"
        );
    }
}

/// A split checkpoint whose totals are missing, damaged or of another snapshot is an error
/// naming the job; shooting from it, which does not read the totals, still works.
#[test]
fn damaged_checkpoint_totals_are_errors() {
    let store = Store::open("memory://").unwrap();
    let (job, _) = run(&store, &bundled("mirrors.obj"), Encoding::F32);
    let id = job.id().clone();
    let totals = |k| layout::totals(&id, k).unwrap();
    let good = store.get(&totals(3)).unwrap().to_vec();
    // Another snapshot's totals.
    store.put(&totals(3), store.get(&totals(2)).unwrap().to_vec()).unwrap();
    let err = job.checkpoint(3).unwrap_err();
    assert!(
        matches!(err, StoreError::Field { .. }) && err.to_string().contains("iterations"),
        "{err}"
    );
    // Sound blob, wrong content.
    store
        .put(
            &totals(3),
            blob::encode_bytes(BlobKind::Snapshot, b"not bincode").unwrap(),
        )
        .unwrap();
    let err = job.checkpoint(3).unwrap_err();
    assert!(matches!(err, StoreError::Field { .. }), "{err}");
    // Flipped bits.
    let mut flipped = good.clone();
    flipped[good.len() / 2] ^= 0x40;
    store.put(&totals(3), flipped).unwrap();
    let err = job.checkpoint(3).unwrap_err();
    assert!(err.to_string().contains(&totals(3)), "{err}");
    // Missing.
    store.delete(&totals(3)).unwrap();
    let err = job.checkpoint(3).unwrap_err();
    assert!(matches!(err, StoreError::NotFound { .. }), "{err}");
    assert!(job.shooting_state(3).is_ok());
    store.put(&totals(3), good).unwrap();
    assert!(job.checkpoint(3).is_ok());
    // A head that names other than the job's batches of mirror maps (sound blob, checksums
    // right): refused before any batch is listed or fetched.
    let state = layout::state(&id, 3).unwrap();
    let good_head = store.get(&state).unwrap().to_vec();
    let mut head = StateHead::from_bytes(&blob::decode_bytes(&good_head, BlobKind::Snapshot).unwrap()).unwrap();
    let batches = head.mirror_batches.expect("a mirror job's head counts its batches");
    for wrong in [u32::MAX, batches + 1, batches - 1] {
        head.mirror_batches = Some(wrong);
        store
            .put(
                &state,
                blob::encode_bytes(BlobKind::Snapshot, &head.to_bytes()).unwrap(),
            )
            .unwrap();
        for err in [job.checkpoint(3).unwrap_err(), job.shooting_state(3).unwrap_err()] {
            assert!(
                err.to_string()
                    .contains(&format!("names {wrong} batches of mirror maps")),
                "{err}"
            );
        }
    }
    store.put(&state, good_head).unwrap();
    assert!(job.checkpoint(3).is_ok());
}

#[test]
fn snapshots_and_fields_are_written_with_their_requests_overlapping() {
    // Over a store 10 ms away, a job's blobs go out many at a time, not one per compute thread,
    // and read back the same as over a store without latency.
    let scene = bundled("mirrors.obj");
    let far = Store::open("memory://?latency=10ms").unwrap();
    let near = Store::open("memory://").unwrap();
    let (far_job, _) = run(&far, &scene, Encoding::F32);
    let (near_job, _) = run(&near, &scene, Encoding::F32);
    let traffic = far.traffic();
    let surfaces = scene.surfaces.len() as u64;
    assert!(
        traffic.most_in_flight >= surfaces.min(64),
        "{traffic:?} for {surfaces} surfaces"
    );
    assert_eq!(traffic.writes, near.traffic().writes);
    let (a, b) = (far_job.checkpoint(4).unwrap(), near_job.checkpoint(4).unwrap());
    assert_eq!(without_times(a), without_times(b));
    let chunks = vlf_core::parts::diffuse_chunks(&far_job.load(Stage::Field).unwrap().atlas).len() as u32;
    for c in 0..chunks {
        let stage = Stage::Field;
        {
            assert_eq!(
                far_job.job().get_diffuse(stage, c).unwrap(),
                near_job.job().get_diffuse(stage, c).unwrap()
            );
        }
    }
}

/// A scene of 30 000 polygons (every wall of a closed room a grid of triangles, fine texels so
/// the maps span several chunks): a snapshot is a bounded number of blobs — the diffuse maps
/// by chunk of charts, not by polygon — and a damaged chunk is named by its key.
#[test]
fn a_snapshot_of_thousands_of_polygons_is_a_few_blobs() {
    use glam::DVec3;
    use vlf_core::scene::{FaceOrigin, Material};
    let (h, k) = (1.0, 50);
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    let mut polygons = Vec::new();
    for face in 0..6 {
        let axis = axes[face / 2];
        let sign = if face % 2 == 0 { -1.0 } else { 1.0 };
        let (ta, tb) = (axes[(face / 2 + 1) % 3], axes[(face / 2 + 2) % 3]);
        let at = |i: usize, j: usize| {
            axis * sign * h + ta * h * (2.0 * i as f64 / k as f64 - 1.0) + tb * h * (2.0 * j as f64 / k as f64 - 1.0)
        };
        for i in 0..k {
            for j in 0..k {
                for t in [
                    [at(i, j), at(i + 1, j), at(i + 1, j + 1)],
                    [at(i, j), at(i + 1, j + 1), at(i, j + 1)],
                ] {
                    // Inward: ta × tb = axis, so flip on the + faces.
                    let t = if sign > 0.0 {
                        vec![t[0], t[1], t[2]]
                    } else {
                        vec![t[0], t[2], t[1]]
                    };
                    let material = usize::from(
                        face == 3 && (k / 2 - 4..k / 2 + 4).contains(&i) && (k / 2 - 4..k / 2 + 4).contains(&j),
                    );
                    polygons.push((
                        t,
                        material,
                        FaceOrigin {
                            line: 0,
                            face: polygons.len(),
                        },
                    ));
                }
            }
        }
    }
    let m = |name: &str, d: f64, e: f64| Material {
        name: name.into(),
        diffuse: [d; 3],
        specular: [0.0; 3],
        emission: [e; 3],
        albedo_texture: None,
    };
    let (scene, _) = Scene::from_polygons(
        &polygons,
        vec![m("wall", 0.5, 0.0), m("lamp", 0.5, 10.0)],
        &ImportOptions::default(),
    )
    .unwrap();
    assert_eq!(scene.surfaces.len(), 30_000);
    let store = Store::open("memory://").unwrap();
    let options = Options {
        directions: 9,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(1),
        texel_cells: 0.1,
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F16).unwrap();
    p.step(|_| {});
    job.write_snapshot(&p).unwrap();
    let id = job.id().clone();
    let snapshot = store
        .list(&layout::stage_prefix(&id, Stage::Iteration(1)).unwrap())
        .unwrap();
    let chunks = vlf_core::parts::diffuse_chunks(&p.atlas).len();
    println!(
        "{} polygons, {} charts, {} texels: {} chunks, snapshot of {} blobs",
        p.scene.surfaces.len(),
        p.atlas.charts.len(),
        p.atlas.texels,
        chunks,
        snapshot.len()
    );
    assert!(chunks >= 2, "the maps should span several chunks here");
    assert!(snapshot.len() <= chunks + 8, "{snapshot:?}");
    // A damaged chunk is named by its key, and the snapshot before it still reads.
    let key = layout::diffuse(&id, Stage::Iteration(1), 1).unwrap();
    let mut bad = store.get(&key).unwrap().to_vec();
    let last = bad.len() - 1;
    bad[last] ^= 0x01;
    store.put(&key, bad).unwrap();
    let e = job.load(Stage::Iteration(1)).unwrap_err().to_string();
    assert!(e.contains(&key), "{e}");
    assert!(job.load(Stage::Iteration(0)).is_ok());
}

/// Builds before store format 5 laid out a mirror's slots per polygon, this one per mirror
/// plane: an earlier job whose scene has a mirror of several polygons is refused with a
/// message that says to propagate again (its maps would be read into other rays), while one
/// whose mirrors are single polygons (the bundled mirror scene) still reads as it was.
#[test]
fn earlier_jobs_with_a_mirror_of_several_polygons_are_refused() {
    let scenes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(scenes.join("mirrors.mtl"), dir.path().join("mirrors.mtl")).unwrap();
    // The first mirror quad `f a b c d` as two triangles of one plane.
    let text = std::fs::read_to_string(scenes.join("mirrors.obj")).unwrap();
    let at = text.find("usemtl mirror").unwrap();
    let face = at + text[at..].find("\nf ").unwrap() + 1;
    let end = face + text[face..].find('\n').unwrap();
    let v: Vec<&str> = text[face + 2..end].split_whitespace().collect();
    assert_eq!(v.len(), 4, "the mirror is a quad");
    let split = format!("f {} {} {}\nf {} {} {}", v[0], v[1], v[2], v[0], v[2], v[3]);
    std::fs::write(
        dir.path().join("mirrors.obj"),
        format!("{}{split}{}", &text[..face], &text[end..]),
    )
    .unwrap();
    let tessellated = load_obj(&dir.path().join("mirrors.obj"), &ImportOptions::default())
        .unwrap()
        .0;
    assert_eq!(tessellated.surfaces.len(), bundled("mirrors.obj").surfaces.len() + 1);

    let store = Store::open("memory://").unwrap();
    for (scene, refused) in [(bundled("mirrors.obj"), false), (tessellated, true)] {
        let (job, field) = run(&store, &scene, Encoding::F32);
        let id = job.id().clone();
        assert!(FieldJob::open(&store, &id).is_ok(), "this build reads what it wrote");
        let mut manifest = job.job().manifest().clone();
        manifest.format = 4;
        store.put(&layout::manifest(&id), manifest.to_blob().unwrap()).unwrap();
        match FieldJob::open(&store, &id) {
            Ok(old) => {
                assert!(!refused, "a format 4 job with a mirror of two triangles was read");
                assert!(old.load(Stage::Field).unwrap().radiance == field.radiance);
            }
            Err(e) => {
                let e = e.to_string();
                assert!(refused, "a format 4 job of single-polygon mirrors was refused: {e}");
                assert!(
                    e.contains("mirror of several polygons") && e.contains("propagate the scene again"),
                    "{e}"
                );
            }
        }
    }
}

/// What a client fetches to render a stage ([`vlf_store::Job::read_by_renders`]) draws it with
/// the same bits as the whole store: of a job's last snapshot, not its exact state (a fraction of
/// its bytes, with mirrors and without); of a mirror snapshot of store format 5 (no mirror
/// radiance parts), its exact totals.
#[test]
fn a_stage_renders_from_what_renders_read() {
    let store = Store::open("memory://").unwrap();
    let (diffuse, _) = run(&store, &bundled("cornell.obj"), Encoding::F16);
    let (job, _) = run(&store, &bundled("mirrors.obj"), Encoding::F16);
    let fetched = |job: &FieldJob, stage: Stage| -> (LightField, usize, usize) {
        let id = job.id().clone();
        let opened = vlf_store::Job::open(&store, &id).unwrap();
        let all = store.list(&layout::stage_prefix(&id, stage).unwrap()).unwrap();
        // As the service lists them: under the job's prefix.
        let under = layout::job_prefix(&id);
        let names = all.iter().map(|k| k[under.len()..].to_string()).collect();
        let kept: Vec<String> = (opened.read_by_renders(stage, names).unwrap().into_iter())
            .map(|n| under.clone() + &n)
            .collect();
        let bytes = |keys: &[String]| keys.iter().map(|k| store.get(k).unwrap().len()).sum::<usize>();
        let partial = Store::open("memory://").unwrap();
        for key in [layout::manifest(&id), layout::scene(&id)].iter().chain(&kept) {
            partial.put(key, store.get(key).unwrap()).unwrap();
        }
        let field = FieldJob::open(&partial, &id).unwrap().load(stage).unwrap();
        (field, bytes(&kept), bytes(&all))
    };
    for job in [&diffuse, &job] {
        for stage in [Stage::Field, Stage::Iteration(4)] {
            let (field, kept, all) = fetched(job, stage);
            assert!(field == job.load(stage).unwrap(), "{stage:?}");
            if stage == Stage::Field {
                assert_eq!(kept, all, "a final field is all radiance");
            } else {
                assert!(4 * kept < all, "{stage:?}: {kept} of {all} bytes");
            }
        }
    }
    // The mirror job as store format 5 wrote it.
    let id = job.id().clone();
    let mut manifest = job.job().manifest().clone();
    manifest.format = 5;
    store.put(&layout::manifest(&id), manifest.to_blob().unwrap()).unwrap();
    summary_without(&store, &id, Stage::Iteration(4), "mirror_radiance_by_batch");
    for b in 0..job.options().batching().count() as u32 {
        store
            .delete(&layout::map_part(&id, 4, MapPart::Radiance, b).unwrap())
            .unwrap();
    }
    let (field, kept, all) = fetched(&job, Stage::Iteration(4));
    assert!(field == job.load(Stage::Iteration(4)).unwrap());
    assert!(kept < all && 2 * kept > all, "format 5: {kept} of {all} bytes");
}

/// A job of store format 5 that this build goes on with (its coordinator and workers of this
/// build, or of the one before, alike) compacts as format 5 did: its superseded snapshots keep
/// their exact mirror totals, which renders read, as their summaries do not name radiance parts.
#[test]
fn a_format_5_job_compacts_as_it_did() {
    let store = Store::open("memory://").unwrap();
    let mut p = Propagation::new(bundled("mirrors.obj"), options(4)).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    job.set_compact(true).unwrap();
    let id = job.id().clone();
    let mut manifest = job.job().manifest().clone();
    manifest.format = 5;
    store.put(&layout::manifest(&id), manifest.to_blob().unwrap()).unwrap();
    let mut job = FieldJob::open(&store, &id).unwrap();
    while !p.finished() {
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
    }
    assert_eq!(job.job().manifest().compacted, vec![0, 1, 2, 3]);
    let batches = job.options().batching().count();
    for k in 1..=4 {
        assert!(!job.summary(Stage::Iteration(k)).unwrap().mirror_radiance_by_batch);
        let parts = |part| store.list(&layout::map_parts(&id, k, part).unwrap()).unwrap().len();
        assert_eq!(parts(MapPart::Totals), batches, "snapshot {k}");
        assert_eq!(parts(MapPart::Shooting) > 0, k == 4, "snapshot {k}");
        assert!(store.exists(&layout::state(&id, k).unwrap()).unwrap(), "snapshot {k}");
        let parts = vlf_store::StageParts::open(job.clone(), Stage::Iteration(k)).unwrap();
        let geometry = parts.geometry().unwrap();
        let catalog = vlf_core::parts::PartCatalog::new(&geometry);
        let tile = (0..catalog.len() as u32)
            .find(|&i| matches!(catalog.part(i), vlf_core::parts::Part::Tile { .. }))
            .unwrap();
        assert!(parts.key(&catalog, tile).unwrap().contains("/mirror-totals/"));
        assert!(job.load(Stage::Iteration(k)).is_ok());
    }
}

/// A diffuse job that compacts keeps of a superseded snapshot what renders read, its summary and
/// diffuse maps, and deletes its exact state (the head and the diffuse totals, `f64` per texel,
/// most of the snapshot): each snapshot renders as it did while it was the last, only the last
/// resumes, and it resumes exactly.
#[test]
fn compacted_diffuse_snapshots_keep_what_renders_read() {
    let store = Store::open("memory://").unwrap();
    let mut p = Propagation::new(bundled("cornell.obj"), options(4)).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F16).unwrap();
    job.set_compact(true).unwrap();
    let mut fresh = Vec::new();
    while !p.finished() {
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
        fresh.push(job.load(Stage::Iteration(p.iterations_done())).unwrap());
    }
    let id = job.id().clone();
    let views: Vec<LightField> = (1..=4).map(|k| job.load(Stage::Iteration(k)).unwrap()).collect();
    assert!(views == fresh, "a snapshot renders otherwise once superseded");
    assert_eq!(job.job().manifest().compacted, vec![0, 1, 2, 3]);
    for k in 0..=4 {
        for exact in [layout::state(&id, k).unwrap(), layout::totals(&id, k).unwrap()] {
            assert_eq!(store.exists(&exact).unwrap(), k == 4, "{exact}");
        }
        let kept = store
            .list(&layout::stage_prefix(&id, Stage::Iteration(k)).unwrap())
            .unwrap();
        assert!(
            kept.iter().any(|key| key.contains("/diffuse/")),
            "snapshot {k}: {kept:?}"
        );
        if k < 4 {
            let rendered = |key: &String| key.ends_with("/summary.blob") || key.contains("/diffuse/");
            assert!(kept.iter().all(rendered), "snapshot {k}: {kept:?}");
            assert!(job.checkpoint(k).unwrap_err().to_string().contains("compacted"));
        }
    }
    assert!(without_times(job.checkpoint(4).unwrap()) == without_times(p.checkpoint()));
}

/// A job that compacts (what `vlf propagate` and the service do unless told to keep
/// checkpoints): committing a snapshot deletes the mirror shooting maps and the exact mirror
/// totals of the one before. Every snapshot still renders as it did before it was compacted (its
/// mirror radiance in the job's encoding stays), the last resumes to the field of a job that
/// kept them all, the earlier ones are refused as checkpoints with a message that says why, and
/// the store holds the shooting maps and exact totals of the last snapshot only: the compacted
/// snapshots are less than half their size before (`f16`).
#[test]
fn compacted_snapshots_render_as_before_and_only_the_last_resumes() {
    let scene = bundled("mirrors.obj");
    let mut runs = Vec::new();
    for compact in [false, true] {
        let store = Store::open("memory://").unwrap();
        let mut p = Propagation::new(scene.clone(), options(4)).unwrap();
        let mut job = FieldJob::create(&store, &p, Encoding::F16).unwrap();
        job.set_compact(compact).unwrap();
        // Each snapshot as it renders while it is the last.
        let mut fresh = Vec::new();
        while !p.finished() {
            p.step(|_| {});
            job.write_snapshot(&p).unwrap();
            fresh.push(job.load(Stage::Iteration(p.iterations_done())).unwrap());
        }
        let views: Vec<LightField> = (1..=4).map(|k| job.load(Stage::Iteration(k)).unwrap()).collect();
        assert!(
            views == fresh,
            "a snapshot renders otherwise once superseded (compact: {compact})"
        );
        runs.push((store, job.id().clone(), views));
    }
    let parts = |part| {
        move |store: &Store, id: &JobId, k: u32| store.list(&layout::map_parts(id, k, part).unwrap()).unwrap().len()
    };
    let (shooting_parts, exact_totals, radiance_parts) = (
        parts(MapPart::Shooting),
        parts(MapPart::Totals),
        parts(MapPart::Radiance),
    );
    let bytes_of = |part| {
        move |store: &Store, id: &JobId, k: u32| -> usize {
            let prefix = layout::map_parts(id, k, part).unwrap();
            store
                .list(&prefix)
                .unwrap()
                .iter()
                .map(|key| store.get(key).unwrap().len())
                .sum()
        }
    };
    let (exact_bytes, radiance_bytes) = (bytes_of(MapPart::Totals), bytes_of(MapPart::Radiance));
    let [(kept_store, kept_id, kept_views), (store, id, views)] = &runs[..] else {
        unreachable!()
    };
    let kept = FieldJob::open(kept_store, kept_id).unwrap();
    let job = FieldJob::open(store, id).unwrap();
    assert_eq!(job.job().manifest().compacted, vec![0, 1, 2, 3]);
    assert!(kept.job().manifest().compacted.is_empty());
    let batches = job.options().batching().count();
    for k in 0..4 {
        assert!(shooting_parts(kept_store, kept_id, k) > 0, "snapshot {k} kept its maps");
        assert_eq!(
            exact_totals(kept_store, kept_id, k),
            batches,
            "snapshot {k} kept its totals"
        );
        assert_eq!(shooting_parts(store, id, k), 0, "snapshot {k} compacted");
        assert_eq!(exact_totals(store, id, k), 0, "snapshot {k} compacted");
        assert_eq!(radiance_parts(store, id, k), batches, "snapshot {k} still renders");
        if k > 0 {
            let (now, then) = (radiance_bytes(store, id, k), exact_bytes(kept_store, kept_id, k));
            assert!(
                2 * now < then,
                "snapshot {k}: mirror radiance {now} bytes, exact totals {then}"
            );
        }
        let refused = job.checkpoint(k).unwrap_err().to_string();
        assert!(refused.contains("compacted") && refused.contains("4"), "{refused}");
        assert!(job.shooting_state(k).is_err());
    }
    assert!(shooting_parts(store, id, 4) > 0);
    assert_eq!(exact_totals(store, id, 4), batches);
    for (k, (a, b)) in views.iter().zip(kept_views).enumerate() {
        assert!(a.radiance == b.radiance, "snapshot {} renders otherwise", k + 1);
        assert!(a.specular.as_ref().unwrap().totals == b.specular.as_ref().unwrap().totals);
    }
    assert!(without_times(job.checkpoint(4).unwrap()) == without_times(kept.checkpoint(4).unwrap()));
    // Both finish from their last snapshot to the same field.
    let mut digests = Vec::new();
    for mut done in [kept, job] {
        let mut p = done.resume().unwrap();
        while !p.finished() {
            p.step(|_| {});
        }
        let field = p.into_field();
        done.finish(&field, false).unwrap();
        digests.push(field.digest());
    }
    assert_eq!(digests[0], digests[1]);
}
