//! The distributed data path without the network: replicas in threads
//! compute batches into the store in a shuffled order (some twice, as a
//! retried lease would), a coordinator absorbs them in order and commits
//! snapshots; the job ends bit-identical to a single-process run.

#[allow(dead_code)]
#[macro_use]
mod suite;

use std::collections::BTreeSet;
use suite::Opener;
use vlf_core::propagate::{Checkpoint, Options, Pass, Perturbation, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::{ImportOptions, Scene, load_obj};
use vlf_store::blob::{BlobKind, Encoding};
use vlf_store::{
    Coordinator, CoordinatorPhases, FieldJob, JobId, MapPart, ReadAhead, Replica, Stage, Store, StoreError, layout,
};

fn bundled(name: &str) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name);
    load_obj(&path, &ImportOptions::default()).expect("bundled scene").0
}

/// l = 33 gives 2 batches per pass, l = 129 gives 8 (blocks of 1, 2 and 4 for 1, 2 and 4 workers).
fn options(perturb: u32, directions: usize) -> Options {
    Options {
        directions,
        grid: GridSize::new(16, 4).unwrap(),
        stop: Stop::Iterations(3),
        perturbation: Perturbation {
            iterations: perturb,
            count: 2,
        },
        filter_sigma: Some(1.0),
        ..Options::default()
    }
}

fn shuffled(n: usize, seed: u32) -> Vec<usize> {
    let mut v: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        v.swap(i, (i * 7919 + seed as usize * 104_729) % (i + 1));
    }
    v
}

fn in_process(store: &Store, scene: &Scene, options: &Options) -> FieldJob {
    let mut p = Propagation::new(scene.clone(), options.clone()).unwrap();
    let mut job = FieldJob::create(store, &p, Encoding::F32).unwrap();
    while !p.finished() {
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
    }
    job.finish(&p.into_field(), false).unwrap();
    job
}

fn with_replicas(o: &Opener, scene: &Scene, options: &Options, workers: usize) -> FieldJob {
    let p = Propagation::new(scene.clone(), options.clone()).unwrap();
    let job = FieldJob::create(&o.open(), &p, Encoding::F32).unwrap();
    let id = job.id().clone();
    let mut coordinator = Coordinator::resume(job).unwrap();
    // Each replica has its own store handle, as a worker process would.
    let mut replicas: Vec<Replica> = (0..workers)
        .map(|_| Replica::new(FieldJob::open(&o.open(), &id).unwrap()).unwrap())
        .collect();
    while !coordinator.finished() {
        let k = coordinator.iteration();
        let mut expected_blobs = 0;
        while let Some((pass, batches)) = coordinator.pending_pass() {
            // Leases of `workers` batches (8 per pass: blocks of 1, 2 or 4).
            let blocks = vlf_core::propagate::reduce::blocks(batches, workers);
            expected_blobs += blocks.len() as u64;
            let order = shuffled(blocks.len(), k);
            std::thread::scope(|s| {
                for (w, replica) in replicas.iter_mut().enumerate() {
                    let mine: Vec<_> = order
                        .iter()
                        .skip(w)
                        .step_by(workers)
                        .map(|&b| blocks[b].clone())
                        .collect();
                    s.spawn(move || {
                        for b in mine {
                            replica.compute(k, pass, b).unwrap();
                        }
                    });
                }
            });
            // A lease that expired and was handed out again: the same bytes, accepted.
            replicas[workers - 1].compute(k, pass, blocks[0].clone()).unwrap();
            coordinator.absorb_pass().unwrap();
        }
        let store = coordinator.job().job().store();
        let written: u64 = store
            .list_sizes(&layout::work_prefix(&id, k).unwrap())
            .unwrap()
            .iter()
            .map(|(_, size)| size)
            .sum();
        coordinator.finish_iteration().unwrap();
        // What went through the store is accounted for: one blob per batch of every pass.
        let traffic = *coordinator.traffic().last().unwrap();
        assert_eq!(traffic.blobs, expected_blobs);
        assert_eq!(traffic.bytes, written);
        assert!(written > 0);
        let store = coordinator.job().job().store();
        assert!(store.list(&layout::work_prefix(&id, k).unwrap()).unwrap().is_empty());
    }
    // Outputs of leases that expired, written after their snapshots were committed (a survey
    // part, a batch): the finished job leaves none behind.
    let store = coordinator.job().job().store().clone();
    let late = [
        format!("{}survey/00000-00001.blob", layout::work_prefix(&id, 0).unwrap()),
        format!("{}shoot/00000-00001.blob", layout::work_prefix(&id, 1).unwrap()),
    ];
    for key in &late {
        store.put(key, vec![7u8; 16]).unwrap();
    }
    let job = coordinator.finish(false).unwrap();
    assert!(store.list(&layout::work_root(&id)).unwrap().is_empty());
    job
}

fn without_times(mut c: Checkpoint) -> Checkpoint {
    for s in &mut c.stats {
        s.seconds = 0.0;
    }
    c
}

fn field_blobs(job: &FieldJob) -> Vec<(String, Vec<u8>)> {
    let prefix = layout::stage_prefix(job.id(), Stage::Field).unwrap();
    let store = job.job().store();
    store
        .list(&prefix)
        .unwrap()
        .into_iter()
        .filter(|k| !k.ends_with("summary.blob"))
        .map(|k| (k[prefix.len()..].to_string(), store.get(&k).unwrap().to_vec()))
        .collect()
}

fn same_bits(o: &Opener, scene: Scene, options: Options) {
    let reference = in_process(&o.open(), &scene, &options);
    for workers in [1, 2, 4] {
        let job = with_replicas(o, &scene, &options, workers);
        assert_eq!(job.job().manifest().finished_iterations, vec![0, 1, 2, 3]);
        assert!(
            without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()),
            "{workers} replicas: state differs"
        );
        assert!(
            field_blobs(&job) == field_blobs(&reference),
            "{workers} replicas: stored field differs"
        );
        // The snapshots' mirror radiance, written by the workers as they shoot, is the bytes
        // the in-process run writes with its snapshots.
        for k in 0..=3 {
            let radiance = radiance_blobs(&job, k);
            assert_eq!(!radiance.is_empty(), scene_has_mirrors(&scene), "snapshot {k}");
            assert!(
                radiance == radiance_blobs(&reference, k),
                "{workers} replicas: mirror radiance of snapshot {k} differs"
            );
        }
    }
}

/// Every [`MapPart::Radiance`] blob of snapshot `k`, by key under the job.
fn radiance_blobs(job: &FieldJob, k: u32) -> Vec<(String, Vec<u8>)> {
    let prefix = layout::map_parts(job.id(), k, MapPart::Radiance).unwrap();
    let store = job.job().store();
    (store.list(&prefix).unwrap().into_iter())
        .map(|key| (key[prefix.len()..].to_string(), store.get(&key).unwrap().to_vec()))
        .collect()
}

fn scene_has_mirrors(scene: &Scene) -> bool {
    (0..scene.surfaces.len()).any(|s| scene.material(s).is_mirror())
}

fn mirrors(o: &Opener) {
    same_bits(o, bundled("mirrors.obj"), options(0, 33));
}

fn perturbed(o: &Opener) {
    same_bits(o, bundled("cornell.obj"), options(2, 129));
}

/// A new job of `scene`, its coordinator, and a replica with a store handle of its own.
fn start(o: &Opener, scene: Scene, options: Options, encoding: Encoding) -> (JobId, Coordinator, Replica) {
    let p = Propagation::new(scene, options).unwrap();
    let job = FieldJob::create(&o.open(), &p, encoding).unwrap();
    let id = job.id().clone();
    let coordinator = Coordinator::resume(job).unwrap();
    let replica = Replica::new(FieldJob::open(&o.open(), &id).unwrap()).unwrap();
    (id, coordinator, replica)
}

fn conflicting_or_missing_batches(o: &Opener) {
    let (id, mut coordinator, mut replica) = start(o, bundled("cornell.obj"), options(0, 129), Encoding::F16);
    let (pass, batches) = coordinator.pending_pass().unwrap();
    assert_eq!((pass, batches), (Pass::Shoot, 8));
    replica.compute(0, pass, 0..4).unwrap();
    replica.compute(0, pass, 4..6).unwrap();
    // Not a node of the reduction tree.
    assert!(replica.compute(0, pass, 5..7).is_err());
    // The last batches are missing: the coordinator cannot absorb the pass.
    let err = coordinator.absorb_pass().unwrap_err();
    assert!(matches!(err, StoreError::NotFound { .. }), "{err}");
    // A block whose content differs from what is stored is refused, never replaced.
    let reader = FieldJob::open(&o.open(), &id).unwrap();
    let mut forged = reader.get_batch(0, pass, 0..4).unwrap();
    forged.sum.texels[0][0] += 1.0;
    assert!(matches!(
        reader.put_batch(&forged),
        Err(StoreError::AlreadyExists { .. })
    ));
    // A pass the iteration does not have.
    assert!(replica.compute(0, Pass::ShootCopy { copy: 0 }, 0..1).is_err());
}

/// Computes and absorbs every pending pass of the coordinator's iteration with one replica, one
/// lease per pass.
fn compute_iteration(coordinator: &mut Coordinator, replica: &mut Replica) {
    let k = coordinator.iteration();
    while let Some((pass, batches)) = coordinator.pending_pass() {
        replica.compute(k, pass, 0..batches).unwrap();
        coordinator.absorb_pass().unwrap();
    }
}

/// The service's order: an iteration is released (its shooting state written) and computed while
/// the previous snapshot is committed. A released snapshot stays invisible until committed; a
/// coordinator that stops in between resumes from the snapshot before, reuses what workers
/// computed from the released state, and ends with the bits of an uninterrupted run.
fn released_before_committed(o: &Opener) {
    let (scene, options) = (bundled("mirrors.obj"), options(0, 33));
    let reference = in_process(&o.open(), &scene, &options);
    let (id, mut coordinator, mut replica) = start(o, scene.clone(), options.clone(), Encoding::F32);
    compute_iteration(&mut coordinator, &mut replica);
    let (_, commit) = coordinator.release_iteration().unwrap();
    assert_eq!(commit.iteration(), 1);
    // Released, not committed: readers see nothing of snapshot 1; its workers read its state.
    let reader = FieldJob::open(&o.open(), &id).unwrap();
    assert!(reader.checkpoint(1).is_err());
    assert!(reader.shooting_state(1).is_err());
    assert!(reader.load(Stage::Iteration(1)).is_err());
    assert_eq!(reader.released_shooting_state(1).unwrap().iterations(), 1);
    // The next iteration is computed from it before the commit...
    compute_iteration(&mut coordinator, &mut replica);
    // ...and the coordinator stops: snapshot 1 is never committed, iteration 1's outputs stay.
    drop((commit, coordinator));
    let stopped = FieldJob::open(&o.open(), &id).unwrap();
    assert_eq!(stopped.job().manifest().finished_iterations, vec![0]);
    assert!(!stopped.stored_blocks(1, Pass::Shoot).unwrap().is_empty());

    // A new coordinator resumes from snapshot 0 and commits each snapshot while the next
    // iteration is computed; what the first one's workers wrote is used as it is.
    let mut coordinator = Coordinator::resume(stopped).unwrap();
    assert_eq!(coordinator.iteration(), 0);
    let mut replica = Replica::new(FieldJob::open(&o.open(), &id).unwrap()).unwrap();
    let mut pending = None;
    while !coordinator.finished() {
        let k = coordinator.iteration();
        let reused = coordinator.blocks_in_store().unwrap();
        assert_eq!(
            reused.iter().all(Vec::is_empty),
            k > 1,
            "iteration {}: {reused:?}",
            k + 1
        );
        compute_iteration(&mut coordinator, &mut replica);
        if let Some(commit) = pending.take() {
            let committed = vlf_store::SnapshotCommit::commit(commit).unwrap();
            coordinator.committed(committed);
        }
        pending = Some(coordinator.release_iteration().unwrap().1);
    }
    let last = pending.unwrap().commit().unwrap();
    coordinator.committed(last);
    let job = coordinator.finish(false).unwrap();
    assert_eq!(job.job().manifest().finished_iterations, vec![0, 1, 2, 3]);
    assert!(without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()));
    assert!(field_blobs(&job) == field_blobs(&reference), "stored field differs");
    assert!(
        job.job().store().list(&format!("jobs/{id}/work/")).unwrap().is_empty(),
        "every iteration's outputs are deleted once its snapshot is committed"
    );
}

/// A lease reads the head of the shooting state, the shooting maps of the directions it gathers
/// from and the mirror totals of its own directions — and nothing it computed itself: a replica
/// that shot every direction in the iteration before computes the next with all the snapshot's
/// mirror maps gone from the store, where a fresh one fails naming a missing blob. With another
/// batch's totals gone, a fresh lease still computes, and the one that needs them fails naming
/// the blob.
fn a_lease_reads_only_what_it_needs(o: &Opener) {
    let (id, mut coordinator, mut replica) = start(o, bundled("mirrors.obj"), options(0, 33), Encoding::F32);
    for _ in 0..2 {
        compute_iteration(&mut coordinator, &mut replica);
        coordinator.finish_iteration().unwrap();
    }
    let (pass, batches) = coordinator.pending_pass().unwrap();
    assert_eq!((pass, batches), (Pass::Shoot, 2));
    // The coordinator holds no mirror map: the workers do.
    let spec = coordinator.propagation().specular.as_ref().unwrap();
    assert!(spec.pending.is_some());
    assert!(
        spec.maps
            .iter()
            .all(|m| m.total.is_empty() && m.unshot.is_empty() && m.incident.is_empty())
    );
    let store = o.open();
    let maps: Vec<(String, Vec<u8>)> = [MapPart::Shooting, MapPart::Totals]
        .into_iter()
        .flat_map(|part| (0..2).map(move |b| (part, b)))
        .map(|(part, b)| {
            let key = layout::map_part(&id, 2, part, b).unwrap();
            let bytes = store.get(&key).unwrap().to_vec();
            store.delete(&key).unwrap();
            (key, bytes)
        })
        .collect();
    replica.compute(2, pass, 0..2).unwrap();
    let mut fresh = Replica::new(FieldJob::open(&o.open(), &id).unwrap()).unwrap();
    let err = fresh.compute(2, pass, 0..2).unwrap_err();
    assert!(maps.iter().any(|(key, _)| err.to_string().contains(key)), "{err}");
    for (key, bytes) in maps {
        store.put(&key, bytes).unwrap();
    }
    let second = layout::map_part(&id, 2, MapPart::Totals, 1).unwrap();
    let kept = store.get(&second).unwrap().to_vec();
    store.delete(&second).unwrap();
    let mut fresh = Replica::new(FieldJob::open(&o.open(), &id).unwrap()).unwrap();
    fresh.compute(2, pass, 0..1).unwrap();
    let err = fresh.compute(2, pass, 1..2).unwrap_err();
    assert!(err.to_string().contains(&second), "{err}");
    // With the blob back, the lease computes, and the iteration ends as it would have.
    store.put(&second, kept).unwrap();
    fresh.compute(2, pass, 1..2).unwrap();
    coordinator.absorb_pass().unwrap();
    coordinator.finish_iteration().unwrap();
}

/// A replica of job `id` with a store handle of its own, whose traffic counts its calls alone.
fn counted_replica(o: &Opener, id: &JobId) -> (Replica, Store) {
    let store = o.open();
    (Replica::new(FieldJob::open(&store, id).unwrap()).unwrap(), store)
}

/// How much `count` of the replica's store traffic grew while it computed `block` of the shot
/// of the iteration from snapshot `k`.
fn count_computing(
    (replica, store): &mut (Replica, Store),
    k: u32,
    block: std::ops::Range<usize>,
    count: impl Fn(vlf_store::Traffic) -> u64,
) -> u64 {
    let before = count(store.traffic());
    replica.compute(k, Pass::Shoot, block).unwrap();
    count(store.traffic()) - before
}

/// Two workers, each on its own half of the pass: from the second time a worker computes its
/// half, the arrivals it reads from the other's half come with the head, in one round trip,
/// where a worker new to the half waits for two — and the bits are the same (the new worker's
/// output and maps, written create-only over the first's, must be the same bytes).
fn arrivals_come_with_the_head(o: &Opener) {
    let (id, mut coordinator, _) = start(o, bundled("mirrors.obj"), options(0, 33), Encoding::F32);
    // Each replica with a store handle of its own, whose round trips it counts (handles of the
    // memory backend share one store, and its count: the replicas take turns).
    let replica = || counted_replica(o, &id);
    let round_trips = |replica: &mut (Replica, Store), k: u32, block: std::ops::Range<usize>| {
        count_computing(replica, k, block, |t| t.round_trips)
    };
    let (mut a, mut b) = (replica(), replica());
    let mut trips = Vec::new();
    for k in 0..4 {
        assert_eq!(coordinator.pending_pass(), Some((Pass::Shoot, 2)));
        trips.push(round_trips(&mut a, k, 0..1));
        round_trips(&mut b, k, 1..2);
        if k == 3 {
            // A worker new to the first half (a store handle of its own, nothing held).
            let fresh = round_trips(&mut replica(), k, 0..1);
            assert_eq!(fresh, trips[3] + 1, "{trips:?} against {fresh}");
        }
        coordinator.absorb_pass().unwrap();
        coordinator.finish_iteration().unwrap();
    }
    // Once arrivals cross between the halves, a worker's iteration takes two round trips: the
    // head with the arrivals, then the output with the maps.
    assert_eq!(trips[3], 2, "{trips:?}");
}

/// Two workers, each on its own half of the pass, the first reading ahead the arrivals that
/// cross into its half once it is done with an iteration, before the coordinator releases the
/// next: its next start reads the head alone where it read the head and the arrivals. Parts not
/// written yet when it reads ahead come with the head, as before; parts read ahead of another
/// snapshot are ignored; the job ends with the in-process bits.
fn arrivals_read_ahead(o: &Opener) {
    let (scene, options) = (
        bundled("mirrors.obj"),
        Options {
            stop: Stop::Iterations(9),
            ..options(0, 33)
        },
    );
    let reference = in_process(&o.open(), &scene, &options);
    let (id, mut coordinator, _) = start(o, scene, options, Encoding::F32);
    // Each replica with a store handle of its own, whose reads it counts.
    let replica = || counted_replica(o, &id);
    let reads = |replica: &mut (Replica, Store), k: u32, block: std::ops::Range<usize>| {
        count_computing(replica, k, block, |t| t.reads)
    };
    let (mut a, mut b) = (replica(), replica());
    let (mut read, mut fetched) = (Vec::new(), Vec::new());
    let mut stale = None;
    for k in 0..9 {
        assert_eq!(coordinator.pending_pass(), Some((Pass::Shoot, 2)));
        read.push(reads(&mut a, k, 0..1));
        // In iteration 5, the first worker is done before the second started: nothing of its
        // half is written yet.
        let early = (k == 5).then(|| a.0.read_ahead(k, Pass::Shoot).map(ReadAhead::fetch));
        reads(&mut b, k, 1..2);
        // Not in the first iterations, where the arrivals that cross settle.
        let ahead = match early {
            Some(ahead) => ahead,
            None if k >= 3 => a.0.read_ahead(k, Pass::Shoot).map(ReadAhead::fetch),
            None => None,
        };
        fetched.push(ahead.as_ref().map_or(0, ReadAhead::fetched));
        if k == 6 {
            // Kept for iteration 8, where it is of the wrong snapshot.
            stale = a.0.read_ahead(k, Pass::Shoot).map(ReadAhead::fetch);
        }
        match (k, ahead) {
            (7, _) => a.0.adopt_ahead(stale.take().unwrap()),
            (_, Some(ahead)) => a.0.adopt_ahead(ahead),
            (_, None) => {}
        }
        coordinator.absorb_pass().unwrap();
        coordinator.finish_iteration().unwrap();
    }
    let arrivals = fetched[3];
    assert!(arrivals > 0, "{fetched:?}");
    assert_eq!(fetched[3..], [arrivals, arrivals, 0, arrivals, arrivals, arrivals]);
    // An iteration reads the head, and the arrivals that were not read ahead: those of
    // iteration 3 (none read ahead), 6 (none written yet) and 8 (read ahead of snapshot 7).
    let (head_only, with_arrivals) = (1, 1 + arrivals as u64);
    assert_eq!(
        read[3..],
        [
            with_arrivals,
            head_only,
            head_only,
            with_arrivals,
            head_only,
            with_arrivals
        ],
        "{read:?}"
    );
    let job = coordinator.finish(false).unwrap();
    assert!(without_times(job.checkpoint(9).unwrap()) == without_times(reference.checkpoint(9).unwrap()));
    assert!(field_blobs(&job) == field_blobs(&reference), "stored field differs");
}

/// A rotated copy's shooting needs the copy's areas whole: a replica learns the blocks it
/// computed itself from memory and reads only the others' from the store — those the lease
/// names without listing the store first. The job ends with the bits of the in-process run.
fn a_copys_shooting_reads_only_the_areas_others_computed(o: &Opener) {
    let (scene, options) = (bundled("cornell.obj"), options(2, 129));
    let reference = in_process(&o.open(), &scene, &options);
    let (id, mut coordinator, _) = start(o, scene, options, Encoding::F32);
    // Each replica with a store handle of its own, whose round trips it counts.
    let replica = || {
        let store = o.open();
        (Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap(), store)
    };
    let round_trips = |(replica, store): &mut (Replica, Store), pass: Pass, block: std::ops::Range<usize>| {
        let before = store.traffic().round_trips;
        replica.compute(0, pass, block).unwrap();
        store.traffic().round_trips - before
    };
    let (areas, shoot) = (|copy| Pass::Areas { copy }, |copy| Pass::ShootCopy { copy });
    let (mut a, mut b) = (replica(), replica());
    // a computes copy 0's areas whole and the first half of copy 1's; b the second half.
    round_trips(&mut a, areas(0), 0..8);
    round_trips(&mut a, areas(1), 0..4);
    round_trips(&mut b, areas(1), 4..8);
    assert_eq!(coordinator.absorb_pass().unwrap(), areas(0));
    assert_eq!(coordinator.absorb_pass().unwrap(), areas(1));
    // Copy 0's shooting reads none of the areas: one round trip, its output.
    assert_eq!(round_trips(&mut a, shoot(0), 0..8), 1);
    // Copy 1's reads the other worker's half: named by the lease, two round trips (the read,
    // the output)...
    a.0.absorbed(0, areas(1), vec![0..4, 4..8]);
    assert_eq!(round_trips(&mut a, shoot(1), 0..4), 2);
    // ...and without the names, a listing first: three.
    assert_eq!(round_trips(&mut b, shoot(1), 4..8), 3);
    assert_eq!(coordinator.absorb_pass().unwrap(), shoot(0));
    assert_eq!(coordinator.absorb_pass().unwrap(), shoot(1));
    coordinator.finish_iteration().unwrap();
    // Named blocks that are not in the store are an error that names the blob.
    let k = coordinator.iteration();
    compute_iteration_but(&mut coordinator, &mut a.0, shoot(0));
    let mut c = replica();
    c.0.absorbed(k, areas(0), vec![0..2, 2..4, 4..8]);
    let err = c.0.compute(k, shoot(0), 0..8).unwrap_err();
    assert!(err.to_string().contains("00000-00002"), "{err}");
    a.0.compute(k, shoot(0), 0..8).unwrap();
    coordinator.absorb_pass().unwrap();
    coordinator.absorb_pass().unwrap();
    coordinator.finish_iteration().unwrap();
    while !coordinator.finished() {
        compute_iteration(&mut coordinator, &mut a.0);
        coordinator.finish_iteration().unwrap();
    }
    let job = coordinator.finish(false).unwrap();
    assert!(without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()));
    assert!(field_blobs(&job) == field_blobs(&reference), "stored field differs");
}

/// [`compute_iteration`] of every pass but `skip`, which is left for the caller to compute; only
/// the passes before it are absorbed.
fn compute_iteration_but(coordinator: &mut Coordinator, replica: &mut Replica, skip: Pass) {
    let k = coordinator.iteration();
    let passes: Vec<Pass> = coordinator.passes().0.into_iter().map(|(p, _)| p).collect();
    let batches = coordinator.passes().1;
    for pass in passes.iter().filter(|&&p| p != skip) {
        replica.compute(k, *pass, 0..batches).unwrap();
    }
    while coordinator.pending_pass().is_some_and(|(p, _)| p != skip) {
        coordinator.absorb_pass().unwrap();
    }
}

/// A run computed "behind" returns with its outputs and mirror maps still on their way: one
/// round trip fewer than a run that waits for them, which a worker over a store a round trip
/// away spends computing its next lease. Once the writes are done, the outputs are there for
/// the coordinator, the same bytes as a waiting run's.
fn a_run_computed_behind_returns_before_its_writes(o: &Opener) {
    let (id, mut coordinator, _) = start(o, bundled("mirrors.obj"), options(0, 33), Encoding::F32);
    let replica = || {
        let store = o.open();
        (Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap(), store)
    };
    let (mut a, mut b) = (replica(), replica());
    let one = |stop: usize| move |done: usize| (done < stop).then_some(done..done + 1);
    let before = a.1.traffic().round_trips;
    let (run, writes) = a.0.compute_run_behind(0, Pass::Shoot, 0, one(1)).unwrap();
    let behind = a.1.traffic().round_trips - before;
    assert_eq!(run, 0..1);
    let before = b.1.traffic().round_trips;
    assert_eq!(b.0.compute_run(0, Pass::Shoot, 1, one(2)).unwrap(), 1..2);
    let waiting = b.1.traffic().round_trips - before;
    assert_eq!(behind + 1, waiting, "the same reads, and no wait for the writes");
    let runtime = tokio::runtime::Builder::new_current_thread().build().unwrap();
    runtime.block_on(writes.finished()).unwrap();
    coordinator.absorb_pass().unwrap();
    coordinator.finish_iteration().unwrap();
}

/// A worker writes a block's output and its mirror maps together; one that stops in between can
/// leave the output alone. A coordinator that finds the output without a report of it takes it
/// only with its maps, and computed again, the block gives the same bytes and its maps back.
fn an_output_without_its_maps_is_computed_again(o: &Opener) {
    for part in [MapPart::Totals, MapPart::Radiance] {
        an_output_without_its_part_is_computed_again(o, part);
    }
}

fn an_output_without_its_part_is_computed_again(o: &Opener, part: MapPart) {
    let (id, mut coordinator, mut replica) = start(o, bundled("mirrors.obj"), options(0, 33), Encoding::F32);
    for _ in 0..2 {
        compute_iteration(&mut coordinator, &mut replica);
        coordinator.finish_iteration().unwrap();
    }
    replica.compute(2, Pass::Shoot, 0..1).unwrap();
    replica.compute(2, Pass::Shoot, 1..2).unwrap();
    let store = o.open();
    let lost = layout::map_part(&id, 3, part, 1).unwrap();
    store.delete(&lost).unwrap();
    let mut restarted = Coordinator::resume(FieldJob::open(&store, &id).unwrap()).unwrap();
    assert_eq!(restarted.blocks_in_store().unwrap(), vec![vec![0..1]]);
    let mut again = Replica::new(FieldJob::open(&o.open(), &id).unwrap()).unwrap();
    again.compute(2, Pass::Shoot, 1..2).unwrap();
    assert!(store.exists(&lost).unwrap());
    assert_eq!(restarted.blocks_in_store().unwrap(), vec![vec![0..1, 1..2]]);
    restarted.absorb_pass().unwrap();
    restarted.finish_iteration().unwrap();
}

/// A replica made from the coordinator's own propagation (what `vlf run`'s workers clone) reads
/// nothing of the snapshot it starts from, and writes the bytes a replica built from the store
/// writes (outputs are create-only: other bytes would be refused).
fn a_prototype_replica_reads_nothing_of_its_snapshot(o: &Opener) {
    let (id, mut coordinator, mut replica) = start(o, bundled("mirrors.obj"), options(0, 33), Encoding::F32);
    let (pass, batches) = coordinator.pending_pass().unwrap();
    let prototype = coordinator.propagation().clone();
    let store = o.open();
    let snapshot = layout::stage_prefix(&id, Stage::Iteration(0)).unwrap();
    let state: Vec<(String, Vec<u8>)> = store
        .list(&snapshot)
        .unwrap()
        .into_iter()
        .filter(|k| k.ends_with("state.blob") || k.contains("/shooting/") || k.contains("/mirror-totals/"))
        .map(|k| {
            let bytes = store.get(&k).unwrap().to_vec();
            store.delete(&k).unwrap();
            (k, bytes)
        })
        .collect();
    assert!(state.len() > 2, "{state:?}");
    let mut from_prototype = Replica::at_snapshot(FieldJob::open(&o.open(), &id).unwrap(), prototype);
    from_prototype.compute(0, pass, 0..batches).unwrap();
    assert!(
        replica.compute(0, pass, 0..batches).is_err(),
        "the snapshot's state is gone"
    );
    for (key, bytes) in state {
        store.put(&key, bytes).unwrap();
    }
    let mut replica = Replica::new(FieldJob::open(&o.open(), &id).unwrap()).unwrap();
    replica.compute(0, pass, 0..batches).unwrap();
    coordinator.absorb_pass().unwrap();
    coordinator.finish_iteration().unwrap();
}

/// Leases computed as workers that claim as they go compute them: in single batches and small
/// blocks, some runs cut short (their tail given to another worker), each written as the
/// outputs of its cover. The job ends with the bits of the in-process run.
fn runs_computed_in_steps(o: &Opener) {
    let (scene, options) = (bundled("mirrors.obj"), options(0, 129));
    let reference = in_process(&o.open(), &scene, &options);
    let (_, mut coordinator, mut replica) = start(o, scene, options, Encoding::F32);
    let mut other = Replica::new(FieldJob::open(&o.open(), coordinator.job().id()).unwrap()).unwrap();
    let id = coordinator.job().id().clone();
    while !coordinator.finished() {
        let k = coordinator.iteration();
        while let Some((pass, batches)) = coordinator.pending_pass() {
            assert_eq!(batches, 8);
            // One worker: batches 0..3 one at a time, then 3..4, and it stops at 6 (4..6 one
            // block); the other takes 6..8 in single batches.
            let steps = |stop: usize| {
                move |done: usize| match done {
                    d if d >= stop => None,
                    d if d < 4 => Some(d..d + 1),
                    d => Some(vlf_core::propagate::reduce::cover(d..stop)[0].clone()),
                }
            };
            let ones = |stop: usize| move |done: usize| (done < stop).then_some(done..done + 1);
            assert_eq!(replica.compute_run(k, pass, 0, steps(6)).unwrap(), 0..6);
            assert_eq!(other.compute_run(k, pass, 6, ones(8)).unwrap(), 6..8);
            // The outputs are those of the runs' covers, nothing else.
            let work = coordinator
                .job()
                .job()
                .store()
                .list(&layout::work_prefix(&id, k).unwrap())
                .unwrap();
            assert_eq!(work.len(), 3, "0..4, 4..6 and 6..8: {work:?}");
            // A run that does not continue where it stands is refused.
            assert!(replica.compute_run(k, pass, 0, |_| Some(2..3)).is_err());
            coordinator.absorb_pass().unwrap();
        }
        coordinator.finish_iteration().unwrap();
    }
    let job = coordinator.finish(false).unwrap();
    assert!(without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()));
    assert!(field_blobs(&job) == field_blobs(&reference), "stored field differs");
}

/// A job whose subfields do not fit one worker's budget completes across three workers, each
/// holding at most its budget (plus what its threads read: `budget + threads · largest`
/// bytes alive), with the bits of the in-process run. Each worker keeps a home of batches, as
/// the scheduler keeps them: once its home's subfields are built (the first iteration), later
/// iterations build none, with mirrors too (their gathers read the sources' mirror views, not
/// their subfields). The job's survey is stored, so no one passes over the whole field at
/// set-up, with mirrors neither (their views rasterise the mirror planes alone), and the
/// coordinator, which never shoots, builds no subfield at all.
fn across_workers_within_budgets(scene: Scene, options: Options, steady: bool) {
    let store = Store::open("memory://").unwrap();
    let reference = in_process(&store, &scene, &options);
    let p = Propagation::new(scene, options).unwrap();
    let (l, mirrors) = (p.directions.len() as u64, p.specular.is_some());
    let all = p.subfields.memory().live;
    let largest = p.subfields.map(|_, s| s.memory_bytes()).into_iter().max().unwrap();
    // Bytes of one mirror map of each direction.
    let map_bytes: Vec<usize> = (0..l as usize)
        .map(|d| p.specular.as_ref().map_or(0, |s| s.slots(d) * 24))
        .collect();
    let job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    let id = job.id().clone();
    drop(p);
    let budget = all * 45 / 100;
    // The coordinator within the same budget.
    let mut coordinator = Coordinator::resume_within(job, Some(budget)).unwrap();
    let coordinator_subfields = coordinator.propagation().subfields.clone();
    let mut workers: Vec<Replica> = (0..3)
        .map(|_| Replica::within(FieldJob::open(&store, &id).unwrap(), Some(budget)).unwrap())
        .collect();
    // The job's survey is stored: set-up passes over no subfield, with mirrors neither.
    for worker in &workers {
        let built = worker.subfield_memory().builds;
        assert_eq!(built, 0, "set-up built {built} subfields (mirrors: {mirrors})");
    }
    let mut builds_after_first = Vec::new();
    let mut most_maps = vec![0usize; workers.len()];
    let coordinator_maps = |c: &Coordinator| c.propagation().specular.as_ref().map_or(0, |s| s.held_bytes());
    while !coordinator.finished() {
        let k = coordinator.iteration();
        assert_eq!(coordinator_maps(&coordinator), 0, "the coordinator holds mirror maps");
        while let Some((pass, batches)) = coordinator.pending_pass() {
            // Homes of contiguous batches: 3, 3 and 2 of 8.
            let homes: Vec<Vec<usize>> = (0..workers.len())
                .map(|w| (0..batches).filter(|b| b * 3 / batches == w).collect())
                .collect();
            // The directions a worker's leases shoot, and those they gather from: found from the
            // coordinator's state, not from what the workers did.
            let prop = coordinator.propagation();
            let (work, batching) = (prop.iteration_work(), prop.batching());
            let reads: Vec<(BTreeSet<usize>, BTreeSet<usize>)> = (homes.iter())
                .map(|home| {
                    let own: BTreeSet<usize> = home.iter().flat_map(|&b| batching.range(b)).collect();
                    let read = (home.iter())
                        .flat_map(|&b| prop.mirror_batches_read(&work, pass, b..b + 1).unwrap().0)
                        .flat_map(|b| batching.range(b))
                        .filter(|d| !own.contains(d))
                        .collect();
                    (own, read)
                })
                .collect();
            std::thread::scope(|s| {
                for (worker, home) in workers.iter_mut().zip(&homes) {
                    s.spawn(move || {
                        for &b in home {
                            worker.compute(k, pass, b..b + 1).unwrap();
                        }
                    });
                }
            });
            // A worker holds the maps of the directions it shoots (its shooting and total maps
            // restored, those it computed for the next snapshot), and the arrivals of those it
            // gathers from; none of any other direction.
            for (w, (worker, (own, read))) in workers.iter().zip(&reads).enumerate() {
                let held = worker.held_maps();
                let others: Vec<&usize> = (held.directions.iter())
                    .filter(|d| !own.contains(d) && !read.contains(d))
                    .collect();
                assert!(others.is_empty(), "worker {w} holds the maps of directions {others:?}");
                let bound: usize = own.iter().map(|&d| 3 * map_bytes[d]).sum::<usize>()
                    + read.iter().map(|&d| map_bytes[d]).sum::<usize>();
                assert!(
                    held.bytes <= bound,
                    "worker {w}: {} bytes of maps, over {bound}",
                    held.bytes
                );
                most_maps[w] = most_maps[w].max(held.bytes);
            }
            coordinator.absorb_pass().unwrap();
        }
        coordinator.finish_iteration().unwrap();
        if k == 0 {
            builds_after_first = workers.iter().map(|w| w.subfield_memory().builds).collect();
        }
    }
    assert_eq!(coordinator_maps(&coordinator), 0, "the coordinator holds mirror maps");
    let whole: usize = map_bytes.iter().sum();
    for (w, &most) in most_maps.iter().enumerate() {
        assert_eq!(most > 0, mirrors, "worker {w} held {most} bytes of maps");
        assert!(
            !mirrors || most < 3 * whole,
            "worker {w} held every direction's maps: {most} bytes"
        );
    }
    let job = coordinator.finish(false).unwrap();
    assert!(without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()));
    assert!(field_blobs(&job) == field_blobs(&reference), "stored field differs");
    // Each worker built its home's subfields, once, and together they built the field's once.
    assert_eq!(
        builds_after_first.iter().sum::<u64>(),
        l,
        "mirrors: {mirrors}, {builds_after_first:?}"
    );
    let held = coordinator_subfields.memory();
    assert_eq!(
        held.builds, 0,
        "the coordinator built subfields (mirrors: {mirrors}): {held:?}"
    );
    let threads = rayon::current_num_threads();
    for (w, worker) in workers.iter().enumerate() {
        let held = worker.subfield_memory();
        assert!(
            held.peak <= budget + threads * largest,
            "worker {w}: {} bytes alive, over {budget} + {threads}·{largest}",
            held.peak
        );
        assert!(
            held.peak < all,
            "worker {w} held the whole field ({all} bytes): {held:?}"
        );
        if steady {
            assert_eq!(
                held.builds, builds_after_first[w],
                "worker {w} rebuilt its home: {held:?}"
            );
        }
    }
}

/// Runs the job to its end with one replica, and compares it with `reference`, a run of the same.
fn finishes_as(mut coordinator: Coordinator, mut replica: Replica, reference: &FieldJob) {
    while !coordinator.finished() {
        compute_iteration(&mut coordinator, &mut replica);
        coordinator.finish_iteration().unwrap();
    }
    let job = coordinator.finish(false).unwrap();
    assert!(without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()));
    assert!(field_blobs(&job) == field_blobs(reference), "stored field differs");
}

/// A worker's subfields are built on demand and kept (no budget), and it keeps each rotated
/// subfield its areas of a copy build for the copy's shot: computing each copy's shot right after
/// its areas, as the service leases them, it builds each rotated subfield once (`copies·l` per
/// perturbed iteration); within a budget it keeps none and builds each twice. The same bits
/// either way, absorbed in the iteration's order.
#[test]
fn a_worker_without_a_budget_builds_each_rotated_subfield_once() {
    let (scene, options) = (bundled("cornell.obj"), options(2, 129));
    let store = Store::open("memory://").unwrap();
    let reference = in_process(&store, &scene, &options);
    for (budget, builds_per_subfield) in [(None, 1), (Some(1), 2)] {
        let p = Propagation::new(scene.clone(), options.clone()).unwrap();
        let l = p.directions.len();
        let job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
        let id = job.id().clone();
        let mut coordinator = Coordinator::resume(job).unwrap();
        let mut replica = Replica::within(FieldJob::open(&store, &id).unwrap(), budget).unwrap();
        // Another worker computes the first iteration's areas too, and not the shots: it keeps
        // one copy's subfields (none within a budget), and drops them when it moves on (to the
        // plain iteration, which keeps none of its own).
        let mut other = Replica::within(FieldJob::open(&store, &id).unwrap(), budget).unwrap();
        let mut perturbed = 0;
        while !coordinator.finished() {
            let k = coordinator.iteration();
            let (passes, batches) = coordinator.passes();
            let mut shooting: Vec<Pass> = passes.iter().map(|(pass, _)| *pass).collect();
            shooting.sort_by_key(|pass| pass.shooting_rank());
            let copies = shooting.iter().filter(|p| matches!(p, Pass::Areas { .. })).count();
            perturbed += usize::from(copies > 0);
            if k == 0 {
                for &pass in shooting.iter().filter(|p| matches!(p, Pass::Areas { .. })) {
                    other.compute(k, pass, 0..batches).unwrap();
                }
                assert_eq!(other.rotated_subfields_kept(), if budget.is_none() { l } else { 0 });
            } else if copies == 0 {
                // A plain iteration keeps nothing new: what is kept is what was not dropped.
                other.compute(k, Pass::Shoot, 0..1).unwrap();
                assert_eq!(other.rotated_subfields_kept(), 0, "the first iteration's are dropped");
            }
            let before = replica.rotated_subfields_built();
            for pass in shooting {
                replica.compute(k, pass, 0..batches).unwrap();
            }
            assert_eq!(
                replica.rotated_subfields_built() - before,
                builds_per_subfield * copies * l,
                "iteration {k}, budget {budget:?}"
            );
            while coordinator.pending_pass().is_some() {
                coordinator.absorb_pass().unwrap();
            }
            coordinator.finish_iteration().unwrap();
        }
        assert_eq!(perturbed, 2, "the premise: two perturbed iterations");
        let job = coordinator.finish(false).unwrap();
        assert!(without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()));
        assert!(field_blobs(&job) == field_blobs(&reference), "stored field differs");
    }
}

/// A replica of job `id` cannot be made, with an error that `says` why.
fn refused(store: &Store, id: &JobId, says: &str) {
    let error = Replica::new(FieldJob::open(store, id).unwrap())
        .err()
        .unwrap()
        .to_string();
    assert!(error.contains(says), "{error}");
}

/// A job's survey is stored with it (`FieldJob::propagation`): a replica of a diffuse job builds
/// no subfield until it shoots, then only those of its lease. A job stored before surveys were
/// (no survey blob) computes as before, its replicas building the whole geometry, to the same
/// bits; a survey blob that is damaged or does not fit is an error naming it, not a reason to
/// learn it again.
#[test]
fn replicas_read_the_jobs_survey() {
    let (scene, options) = (bundled("cornell.obj"), options(0, 129));
    let store = Store::open("memory://").unwrap();
    let reference = in_process(&store, &scene, &options);
    let p = Propagation::new(scene, options).unwrap();
    let l = p.directions.len() as u64;
    let job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    let id = job.id().clone();
    assert!(job.stored_survey().unwrap() == Some(p.survey()));

    let mut replica = Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
    assert_eq!(replica.subfield_memory().builds, 0, "set-up built subfields");
    replica.compute(0, Pass::Shoot, 2..4).unwrap();
    let shot = p.batching().directions_of(2..4).len() as u64;
    assert_eq!(replica.subfield_memory().builds, shot);

    // As a job of an earlier build: its replicas pass over the whole field, and write the
    // block computed above again with the same bytes (create-only: different ones are refused).
    let key = layout::survey(&id);
    store.delete(&key).unwrap();
    let job = FieldJob::open(&store, &id).unwrap();
    assert!(job.stored_survey().unwrap().is_none());
    let coordinator = Coordinator::resume(job).unwrap();
    let replica = Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
    assert_eq!(replica.subfield_memory().builds, l);
    finishes_as(coordinator, replica, &reference);

    let blob = |kind, bytes: &[u8]| vlf_store::blob::encode_bytes(kind, bytes).unwrap();
    let valid = blob(BlobKind::Survey, &p.survey().to_bytes());
    let mut flipped = valid.clone();
    flipped[60] ^= 4;
    let mut other = p.survey();
    other.projected_area.truncate(3);
    for (bytes, says) in [
        (flipped, "checksum"),
        (valid[..40].to_vec(), "survey.blob"),
        (blob(BlobKind::Survey, &[2, 0, 0, 0, 7]), "survey.blob"),
        (blob(BlobKind::Survey, &other.to_bytes()), "3 areas"),
        (blob(BlobKind::Scene, &p.survey().to_bytes()), "survey.blob"),
    ] {
        store.put(&key, bytes).unwrap();
        refused(&store, &id, says);
    }
}

/// A mirror job stores its mirror geometry when it is set up, and whoever opens the job reads it
/// rather than computing it: the routes it stores are the routes a replica has (altered in the
/// store, altered in the replica), and replicas that read it give the in-process field. A job
/// stored without it computes it, the same; one that is there but unreadable or of another job
/// is an error naming it.
#[test]
fn replicas_read_the_jobs_mirror_geometry() {
    let (scene, options) = (bundled("mirrors.obj"), options(0, 129));
    let store = Store::open("memory://").unwrap();
    let reference = in_process(&store, &scene, &options);
    let p = Propagation::new(scene.clone(), options.clone()).unwrap();
    let job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    let id = job.id().clone();
    let stored = job
        .stored_mirror_geometry()
        .unwrap()
        .expect("a mirror job stores its geometry");
    assert_eq!(Some(stored.to_bytes()), p.mirror_geometry());
    let key = layout::mirror_geometry(&id);
    let blob = |kind, bytes: &[u8]| vlf_store::blob::encode_bytes(kind, bytes).unwrap();
    let valid = store.get(&key).unwrap();

    let mut altered = stored.clone();
    let t = (0..altered.routes.len())
        .find(|&t| !altered.routes[t].is_empty())
        .unwrap();
    altered.routes[t][0].weight *= 0.5;
    store
        .put(&key, blob(BlobKind::MirrorGeometry, &altered.to_bytes()))
        .unwrap();
    let read = FieldJob::open(&store, &id).unwrap().propagation(None).unwrap();
    assert_eq!(*read.specular.as_ref().unwrap().routes, *altered.routes);
    store.put(&key, valid.clone()).unwrap();

    let coordinator = Coordinator::resume(FieldJob::open(&store, &id).unwrap()).unwrap();
    let replica = Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
    assert_eq!(replica.subfield_memory().builds, 0, "set-up built subfields");
    finishes_as(coordinator, replica, &reference);

    // As a job of an earlier build: computed, the same.
    store.delete(&key).unwrap();
    let job = FieldJob::open(&store, &id).unwrap();
    assert!(job.stored_mirror_geometry().unwrap().is_none());
    let computed = job.propagation(None).unwrap();
    assert_eq!(computed.mirror_geometry(), Some(stored.to_bytes()));

    let mut flipped = valid.to_vec();
    flipped[60] ^= 4;
    let other = Propagation::new(
        scene,
        Options {
            directions: 33,
            ..options
        },
    )
    .unwrap()
    .mirror_geometry()
    .unwrap();
    for (bytes, says) in [
        (flipped, "checksum"),
        (valid[..40].to_vec(), "mirrors.blob"),
        (blob(BlobKind::MirrorGeometry, &[1, 0, 0, 0, 7]), "mirrors.blob"),
        (
            blob(BlobKind::MirrorGeometry, &other),
            "mirrors.blob`: the mirror geometry was computed for l = 33",
        ),
        (blob(BlobKind::Survey, &stored.to_bytes()), "mirrors.blob"),
        // A length in the payload past the payload's end: refused, not allocated.
        (
            blob(
                BlobKind::MirrorGeometry,
                &[1, 0, 0, 0, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f],
            ),
            "mirrors.blob`: mirror geometry",
        ),
        // Read as it is decompressed: a byte after the geometry is still found.
        (
            blob(BlobKind::MirrorGeometry, &[stored.to_bytes(), vec![0]].concat()),
            "of which its reader took",
        ),
    ] {
        store.put(&key, bytes).unwrap();
        refused(&store, &id, says);
    }
}

/// A job's geometry written again (a set-up repeated) is accepted when its payload is the one
/// stored, however that was compressed — an earlier build compressed large geometries from
/// memory, into another frame than this build's stream — and refused, the stored one kept, when
/// the payload differs.
#[test]
fn a_geometry_written_again_is_compared_by_its_payload() {
    let (scene, options) = (bundled("mirrors.obj"), options(0, 33));
    let store = Store::open("memory://").unwrap();
    let p = Propagation::new(scene, options).unwrap();
    let field = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    let (job, key) = (field.job(), layout::mirror_geometry(field.id()));
    // A payload large enough to be streamed (8 MiB and up; one whose frames differ), in a frame
    // from memory.
    let payload: Vec<u8> = (0..24u32 << 20)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 29) as u8 ^ (i >> 13) as u8)
        .collect();
    let from_memory = vlf_store::blob::encode_bytes(BlobKind::MirrorGeometry, &payload).unwrap();
    store.put(&key, from_memory.clone()).unwrap();
    let write = |payload: &[u8]| {
        let payload = payload.to_vec();
        move |w: &mut dyn std::io::Write| payload.chunks(4097).try_for_each(|piece| w.write_all(piece))
    };
    let streamed = vlf_store::blob::encode_bytes_with(BlobKind::MirrorGeometry, payload.len() as u64, write(&payload));
    assert!(
        streamed.unwrap() != from_memory,
        "the frames differ, or this tests nothing"
    );
    job.put_mirror_geometry_with(payload.len() as u64, write(&payload))
        .unwrap();
    let mut other = payload.clone();
    other[5_000_000] ^= 1;
    let error = job
        .put_mirror_geometry_with(other.len() as u64, write(&other))
        .unwrap_err();
    assert!(matches!(error, StoreError::AlreadyExists { .. }), "{error}");
    assert!(store.get(&key).unwrap() == from_memory);
}

/// A coordinator reads no subfield (it absorbs what workers shoot, perturbed copies' areas
/// included, and cuts mirror tiles along the mirror views): once it lets them go it builds none
/// to the job's end, with mirrors too, and the field is the in-process run's.
#[test]
fn a_coordinator_lets_its_subfields_go() {
    for (scene, perturbations) in [("cornell.obj", 2), ("mirrors.obj", 0)] {
        let (scene, options) = (bundled(scene), options(perturbations, 129));
        let store = Store::open("memory://").unwrap();
        let reference = in_process(&store, &scene, &options);
        let p = Propagation::new(scene, options.clone()).unwrap();
        let job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
        let id = job.id().clone();
        let mut coordinator = Coordinator::new(job, p);
        assert!(coordinator.propagation().subfields.memory().live > 0);
        coordinator.release_subfields();
        let mut replica = Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
        while !coordinator.finished() {
            compute_iteration(&mut coordinator, &mut replica);
            coordinator.finish_iteration().unwrap();
        }
        let held = coordinator.propagation().subfields.memory();
        let job = coordinator.finish(false).unwrap();
        assert!(without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()));
        assert!(field_blobs(&job) == field_blobs(&reference), "stored field differs");
        assert_eq!(digest(&job), digest(&reference));
        assert_eq!((held.live, held.builds), (0, 0), "{held:?}");
    }
}

/// A coordinator that takes a mirror job up reads no mirror map back: before light can reach a
/// mirror they are zeros, which it holds without allocating them (and writes into the
/// snapshots); after, they are in the snapshot's parts, where the workers read them and the
/// coordinator finishes the field from. Stopped after any iteration, it ends with the bits of an
/// uninterrupted run.
#[test]
fn a_coordinator_takes_a_mirror_job_up_without_its_maps() {
    let (scene, options) = (bundled("mirrors.obj"), options(0, 129));
    let store = Store::open("memory://").unwrap();
    let reference = in_process(&store, &scene, &options);
    let p = Propagation::new(scene.clone(), options.clone()).unwrap();
    let first_lit = p.plan.first_mirror_iteration().unwrap();
    for stop in 0..3 {
        let p = Propagation::new(scene.clone(), options.clone()).unwrap();
        let id = FieldJob::create(&store, &p, Encoding::F32).unwrap().id().clone();
        let mut coordinator = Coordinator::new(FieldJob::open(&store, &id).unwrap(), p);
        let mut replica = Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
        for _ in 0..stop {
            compute_iteration(&mut coordinator, &mut replica);
            coordinator.finish_iteration().unwrap();
        }
        drop(coordinator);
        let mut coordinator = Coordinator::resume(FieldJob::open(&store, &id).unwrap()).unwrap();
        let spec = coordinator.propagation().specular.as_ref().unwrap();
        assert_eq!(spec.held_bytes(), 0, "resumed after {stop} iterations");
        assert_eq!(spec.holds_all(), stop <= first_lit, "resumed after {stop} iterations");
        while !coordinator.finished() {
            compute_iteration(&mut coordinator, &mut replica);
            coordinator.finish_iteration().unwrap();
        }
        let job = coordinator.finish(false).unwrap();
        assert!(without_times(job.checkpoint(3).unwrap()) == without_times(reference.checkpoint(3).unwrap()));
        assert!(
            field_blobs(&job) == field_blobs(&reference),
            "stored field differs, stopped after {stop}"
        );
        // Written from the snapshot's parts, the field's digest is the one of the whole field.
        assert_eq!(digest(&job), digest(&reference));
    }
}

fn digest(job: &FieldJob) -> String {
    let summary = vlf_store::Summary::read(job.job(), Stage::Field).unwrap();
    summary.digest.expect("a final field's summary gives its digest")
}

#[test]
fn a_diffuse_job_larger_than_a_workers_budget_completes_across_three() {
    across_workers_within_budgets(bundled("cornell.obj"), options(0, 129), true);
}

#[test]
fn a_mirror_job_larger_than_a_workers_budget_completes_across_three() {
    across_workers_within_budgets(bundled("mirrors.obj"), options(0, 129), true);
}

per_backend! {
    runs_computed_in_steps_give_the_same_bits => crate::runs_computed_in_steps,
    a_lease_reads_only_what_it_needs => crate::a_lease_reads_only_what_it_needs,
    a_prototype_replica_reads_nothing_of_its_snapshot => crate::a_prototype_replica_reads_nothing_of_its_snapshot,
    released_iterations_resume_with_the_same_bits => crate::released_before_committed,
    replicas_give_the_same_bits_with_mirrors => crate::mirrors,
    replicas_give_the_same_bits_with_perturbation => crate::perturbed,
    conflicting_or_missing_batches_are_errors => crate::conflicting_or_missing_batches,
    arrivals_come_with_the_head => crate::arrivals_come_with_the_head,
    arrivals_read_ahead => crate::arrivals_read_ahead,
    an_output_without_its_maps_is_computed_again => crate::an_output_without_its_maps_is_computed_again,
    a_copys_shooting_reads_only_the_areas_others_computed => crate::a_copys_shooting_reads_only_the_areas_others_computed,
    a_run_computed_behind_returns_before_its_writes => crate::a_run_computed_behind_returns_before_its_writes,
}

/// What a replica says it spent computing leaves out its waits for the store: over a store 300 ms
/// away, a block of the smallest mirror job reads the head and maps and writes its output (three
/// round trips, 0.9 s), and computes its two batches in a few milliseconds.
#[test]
fn compute_seconds_leave_out_the_waits_for_the_store() {
    let store = Store::open("memory://?latency=300ms").unwrap();
    let p = Propagation::new(bundled("mirrors.obj"), options(0, 33)).unwrap();
    let id = FieldJob::create(&store, &p, Encoding::F32).unwrap().id().clone();
    let mut replica = Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
    let before = store.traffic().round_trips;
    replica.compute(0, Pass::Shoot, 0..2).unwrap();
    assert!(store.traffic().round_trips - before >= 3);
    let seconds = replica.compute_seconds();
    assert!(seconds > 0.0 && seconds < 0.3, "{seconds} s");
    // Batch by batch, adding up to it.
    let costs = replica.batch_costs();
    assert_eq!(costs.len(), 2);
    assert!(costs.iter().all(|&c| c > 0.0) && (costs.iter().sum::<f64>() - seconds).abs() < 1e-12);
    // Where the wall time went, phase by phase: the head's round trip in moving on to the
    // iteration, the computing apart from it.
    let phases = replica.phase_seconds();
    assert!(phases.start >= 0.3, "{phases:?}");
    assert!(phases.compute > 0.0 && phases.compute < phases.start, "{phases:?}");
}

/// Where a coordinator's own work went, phase by phase, over a store 300 ms away: each absorb
/// reads its block (a round trip) and the release writes the next head (another); ending the
/// iteration and adding the outputs up are computing, apart from them. Taking the phases resets
/// them.
#[test]
fn coordinator_phases_tell_its_store_waits_from_its_computing() {
    let store = Store::open("memory://?latency=300ms").unwrap();
    let p = Propagation::new(bundled("mirrors.obj"), options(0, 33)).unwrap();
    let job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    let id = job.id().clone();
    let mut coordinator = Coordinator::new(job, p);
    let mut replica = Replica::new(FieldJob::open(&store, &id).unwrap()).unwrap();
    // A replica turns the routes around as it sets up, not in its first block; a coordinator,
    // which settles only what an earlier build's workers left, does not.
    let prepared = |p: &Propagation| p.specular.as_ref().unwrap().settle_prepared();
    assert!(prepared(replica.propagation()));
    // Its work prepared while the workers compute.
    coordinator.prepare_work();
    compute_iteration(&mut coordinator, &mut replica);
    let (_, commit) = coordinator.release_iteration().unwrap();
    let phases = coordinator.take_phase_seconds();
    assert!(phases.read >= 0.3 && phases.head >= 0.3, "{phases:?}");
    assert!(phases.finish > 0.0 && phases.finish < 0.3, "{phases:?}");
    assert!(phases.apply < 0.3, "{phases:?}");
    assert_eq!(coordinator.take_phase_seconds(), CoordinatorPhases::default());
    assert!(!prepared(coordinator.propagation()));
    coordinator.committed(commit.commit().unwrap());
}

#[test]
fn each_worker_takes_a_prototype_once_and_the_last_takes_the_original() {
    let prop = Propagation::new(bundled("mirrors.obj"), options(0, 33)).unwrap();
    let bits = without_times(prop.checkpoint());
    let maps = |p: &Propagation| p.specular.as_ref().unwrap().maps.as_ptr();
    let original = maps(&prop);
    let id = JobId::generate();
    let prototypes = vlf_store::Prototypes::new(2);
    prototypes.insert(id.clone(), prop);
    let first = prototypes.take(&id).expect("offered");
    let second = prototypes.take(&id).expect("one left");
    assert!(prototypes.take(&id).is_none(), "both workers took theirs");
    // The first is a copy, the second the original, both with the same state.
    assert_ne!(maps(&first), original);
    assert_eq!(maps(&second), original);
    assert!(without_times(first.checkpoint()) == bits);
    assert!(without_times(second.checkpoint()) == bits);
    // They share their mirror geometry, the table of routes by source built once, rather
    // than each holding a copy.
    fn spec(p: &Propagation) -> &vlf_core::propagate::Specular {
        p.specular.as_ref().unwrap()
    }
    assert!(spec(&first).shares_geometry(spec(&second)));
    // A lone worker takes the original at once; a withdrawn offer is gone.
    let alone = vlf_store::Prototypes::new(1);
    alone.insert(id.clone(), second);
    assert_eq!(alone.take(&id).map(|p| maps(&p)), Some(original));
    assert!(alone.take(&id).is_none());
    alone.insert(id.clone(), first);
    alone.remove(&id);
    assert!(alone.take(&id).is_none());
}

/// Survey parts through the store: workers' blocks, stored and read back in any grouping, add up
/// to the survey the propagation learns whole; a part that does not fit its key (other
/// directions, corrupted bytes) is an error that names the key, and is refused when written
/// under the wrong batches.
#[test]
fn survey_parts_through_the_store_make_the_survey() {
    use vlf_core::propagate::{SurveyParts, Surveyor, reduce};
    let store = Store::open("memory://").unwrap();
    let (scene, options) = (bundled("mirrors.obj"), options(0, 129));
    let job = FieldJob::describe(&store, &scene, &options, Encoding::F32).unwrap();
    let batching = options.batching();
    let batches = batching.count();
    assert_eq!(batches, 8);
    // Two workers' leases, each the blocks that cover its run.
    let surveyor = Surveyor::new(&scene, &options, Some(0)).unwrap();
    let mut blocks = Vec::new();
    for run in [0..3, 3..8] {
        for block in reduce::cover(run) {
            let part = surveyor.part(batching.directions_of(block.clone())).unwrap();
            job.put_survey_part(block.clone(), &part).unwrap();
            blocks.push(block);
        }
    }
    assert_eq!(job.stored_blocks(0, Pass::Survey).unwrap(), blocks);
    let mut sum = SurveyParts::new(&scene, &options);
    for part in job.survey_parts(&blocks).unwrap() {
        sum.add(part).unwrap();
    }
    let whole = Propagation::new(scene.clone(), options.clone()).unwrap().survey();
    assert!(sum.finish(&scene).unwrap() == whole);
    // Written under the wrong batches: refused.
    let part = surveyor.part(batching.directions_of(0..1)).unwrap();
    let error = job.survey_part_put(1..2, &part).unwrap_err().to_string();
    assert!(error.contains("is not that of batches 1..2"), "{error}");
    // Stored under the wrong key (another block's bytes), or corrupted: the key is named.
    let key =
        |b: &std::ops::Range<usize>| layout::work_block(job.id(), 0, "survey", b.start as u32, b.end as u32).unwrap();
    let (first, second) = (key(&blocks[0]), key(&blocks[1]));
    let good = store.get(&first).unwrap().to_vec();
    store.put(&first, store.get(&second).unwrap().to_vec()).unwrap();
    let error = job.survey_parts(&blocks[..1]).unwrap_err().to_string();
    assert!(error.contains(&first) && error.contains("holds directions"), "{error}");
    let mut bytes = good.clone();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x55;
    store.put(&first, bytes).unwrap();
    let error = job.survey_parts(&blocks[..1]).unwrap_err().to_string();
    assert!(error.contains(&first), "{error}");
    store.put(&first, good).unwrap();
    assert!(job.survey_parts(&blocks).is_ok());
}
