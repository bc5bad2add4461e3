//! The iteration split into passes and batches (`propagate::work`): batches
//! computed by separate replicas of the propagation, in any order, absorbed
//! in batch order by a coordinator, give the same bits as the in-process
//! step — with mirrors (maps travel with their directions) and with
//! perturbation (the areas pass feeds the copy's shooting pass).

mod common;

use common::*;
use std::collections::HashMap;
use vlf_core::propagate::specular::{BatchArrivals, MirrorPower};
use vlf_core::propagate::{
    Arrivals, BatchOutput, Checkpoint, HomeThreads, MapBatch, MapKind, Options, Pass, Propagation, ShootingState,
    StateHead, Stop, Totals, reduce,
};
use vlf_core::psf::GridSize;
use vlf_core::scene::Scene;

fn options(perturb: u32) -> Options {
    split_options(perturb)
}

/// A fixed permutation of `0..n` that is far from the identity.
fn shuffled(n: usize, seed: usize) -> Vec<usize> {
    let mut v: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        let j = (i * 7919 + seed * 104_729) % (i + 1);
        v.swap(i, j);
    }
    v
}

/// The mirror maps of a snapshot as a store holds them: per batch, its
/// shooting maps and its totals, serialised.
#[derive(Default)]
struct MapStore(HashMap<(u32, usize), (Vec<u8>, Vec<u8>)>);

impl MapStore {
    fn put(&mut self, k: u32, b: usize, shooting: Vec<u8>, total: Vec<u8>) {
        // Written again (a block computed twice) they are the same bytes.
        if let Some(old) = self.0.insert((k, b), (shooting.clone(), total.clone())) {
            assert!(
                old == (shooting, total),
                "batch {b} of snapshot {k} written with other bytes"
            );
        }
    }

    fn get(&self, k: u32, b: usize) -> (MapBatch, MapBatch) {
        let (s, t) = &self.0[&(k, b)];
        (MapBatch::from_bytes(s).unwrap(), MapBatch::from_bytes(t).unwrap())
    }
}

/// Runs the propagation with `workers` replicas computing the batches of
/// every pass in a shuffled order, their outputs serialised as they would
/// travel, the coordinator applying them in batch order. The coordinator
/// never sees a mirror map: workers write their directions' maps as the next
/// snapshot's parts and read those they need. Returns the coordinator's
/// propagation and its last snapshot assembled from the parts; with `adopt`,
/// the coordinator also takes the maps in (`adopt_mirrors`).
fn run_distributed(scene: &Scene, options: &Options, workers: usize, adopt: bool) -> (Propagation, Checkpoint) {
    run_distributed_in_blocks(scene, options, workers, adopt, 1 << (workers - 1))
}

/// [`run_distributed`] with blocks of `block` batches.
fn run_distributed_in_blocks(
    scene: &Scene,
    options: &Options,
    workers: usize,
    adopt: bool,
    block: usize,
) -> (Propagation, Checkpoint) {
    let mut main = Propagation::new(scene.clone(), options.clone()).unwrap();
    // Replicas start every iteration blank (a clone of a fresh propagation),
    // so they hold only what they read of this iteration's snapshot: a map
    // they should have read and did not would give other bits.
    let blank = Propagation::new(scene.clone(), options.clone()).unwrap();
    let mut maps = MapStore::default();
    let first = main.snapshot_bytes(true);
    for (b, (s, t)) in first.shooting.into_iter().zip(first.mirror_totals).enumerate() {
        maps.put(0, b, s, t);
    }
    loop {
        let k = main.iterations_done();
        let parts = main.snapshot_bytes(false);
        if main.finished() {
            let head = StateHead::from_bytes(&parts.head).unwrap();
            let batches = head.mirror_batches.unwrap_or(0) as usize;
            let (shooting, totals): (Vec<_>, Vec<_>) = (0..batches).map(|b| maps.get(k, b)).unzip();
            let state = ShootingState::from_parts(head, shooting).unwrap();
            let totals = Totals::from_bytes(&parts.totals)
                .unwrap()
                .with_mirror_batches(totals)
                .unwrap();
            return (main, Checkpoint::join(state, totals).unwrap());
        }
        let started = std::time::Instant::now();
        let mut replicas: Vec<Propagation> = (0..workers).map(|_| blank.clone()).collect();
        for r in &mut replicas {
            r.restore_head(StateHead::from_bytes(&parts.head).unwrap()).unwrap();
        }
        let mut works: Vec<_> = replicas.iter().map(|r| r.iteration_work()).collect();
        let mut read: Vec<(Vec<bool>, Vec<bool>)> = vec![(vec![false; 64], vec![false; 64]); workers];
        let mut work = main.iteration_work();
        // Every output of the iteration, as stored: workers read a pass's
        // prerequisites from here, never from the coordinator. Leases hold
        // blocks of 1, 2 or 4 batches with 1, 2 or 3 workers (`run_distributed`).
        let blocks = reduce::blocks(work.batches(), block);
        let mut stored: HashMap<(Pass, usize), Vec<u8>> = HashMap::new();
        let mut blocks_of_maps = Vec::new();
        for pass in work.passes() {
            for (i, b) in shuffled(blocks.len(), k as usize).into_iter().enumerate() {
                let w = i % workers;
                for earlier in works[w].prerequisites(pass) {
                    let sums: Vec<_> = blocks
                        .iter()
                        .map(|b| {
                            (
                                b.clone(),
                                BatchOutput::from_bytes(&stored[&(earlier, b.start)]).unwrap().sum,
                            )
                        })
                        .collect();
                    works[w].learn(earlier, sums).unwrap();
                }
                assert!(works[w].is_ready(pass));
                let (shooting, totals) = replicas[w]
                    .mirror_batches_read(&works[w], pass, blocks[b].clone())
                    .unwrap();
                for b in shooting {
                    if !std::mem::replace(&mut read[w].0[b], true) {
                        replicas[w].restore_shooting_batch(maps.get(k, b).0).unwrap();
                    }
                }
                for b in totals {
                    if !std::mem::replace(&mut read[w].1[b], true) {
                        replicas[w].restore_totals_batch(maps.get(k, b).1).unwrap();
                    }
                }
                let (out, block) = replicas[w].compute_block(&works[w], pass, blocks[b].clone()).unwrap();
                if let Some(block) = block {
                    blocks_of_maps.push(block.clone());
                    for b in block.batches.clone() {
                        let bytes = |kind| block.batch_bytes(main.batching(), b, kind);
                        maps.put(k + 1, b as usize, bytes(MapKind::Shooting), bytes(MapKind::Totals));
                    }
                }
                stored.insert((pass, blocks[b].start), out.to_bytes());
            }
            for b in &blocks {
                let out = BatchOutput::from_bytes(&stored[&(pass, b.start)]).unwrap();
                main.apply_batch(&mut work, out).unwrap();
            }
        }
        main.finish_iteration(work, started);
        if adopt {
            for block in blocks_of_maps {
                main.adopt_mirrors(block).unwrap();
            }
        }
    }
}

fn same_bits_as_in_process(scene: Scene, options: Options) {
    let mut straight = Propagation::new(scene.clone(), options.clone()).unwrap();
    straight.run(|_| {});
    let want = without_times(straight.checkpoint());
    for workers in [1, 2, 3] {
        let (_, stored) = run_distributed(&scene, &options, workers, false);
        assert!(without_times(stored) == want, "{workers} workers changed the bits");
    }
    // A coordinator that takes the workers' maps in holds the same state.
    let (main, stored) = run_distributed(&scene, &options, 2, true);
    assert!(without_times(main.checkpoint()) == want);
    assert!(without_times(stored) == want);
}

#[test]
fn batches_from_several_workers_in_any_order_give_the_same_bits_with_mirrors() {
    let p = Propagation::new(mirror_room(), options(0)).unwrap();
    assert!(p.specular.is_some());
    same_bits_as_in_process(mirror_room(), options(0));
}

#[test]
fn batches_of_several_chunks_keep_each_directions_mirror_maps() {
    // l = 513 cut into 16 batches: batches of 32 directions (the last 33) in stints of one,
    // computed 16 at a time, so a batch's mirror maps are split between chunks (between stints
    // of several directions: `every_stint_gives_one_field_on_every_schedule…`).
    let options = Options {
        directions: 513,
        stint_directions: 1,
        stop: Stop::Iterations(3),
        pass_batches: 16,
        ..options(0)
    };
    assert_eq!(options.batching().size(), 32);
    let p = Propagation::new(mirror_room(), options.clone()).unwrap();
    assert_eq!(p.iteration_work().batches(), 16);
    // (That each chunk gets its own directions' maps is checked by physics:
    // mirror_render.rs compares mirrors from the rays with ray tracing at
    // l = 513.)
    same_bits_as_in_process(mirror_room(), options);
}

#[test]
fn perturbed_passes_split_across_workers_give_the_same_bits() {
    let scene = lit_box();
    same_bits_as_in_process(scene, options(2));
}

/// The in-process run with every pass's batches cut into homes (at the batches `cuts` name, each
/// home on `threads` threads of its own) gives the same bits as the step, whatever the cut.
fn homes_give_the_same_bits(scene: Scene, options: Options, threads: usize, cuts: &[&[usize]]) {
    // The loop that shares every batch among the threads (`step` may cut on its own).
    let mut straight = Propagation::new(scene.clone(), options.clone()).unwrap();
    while !straight.finished() {
        straight.step_shared(|_| {});
    }
    let want = without_times(straight.checkpoint());
    for cut in cuts {
        let mut split = Propagation::new(scene.clone(), options.clone()).unwrap();
        let n = split.iteration_work().batches();
        assert!(n >= 4, "a cut needs batches to move: {n}");
        let mut bounds = vec![0];
        bounds.extend(cut.iter().map(|&c| c.min(n)));
        bounds.push(n);
        let homes: Vec<_> = bounds.windows(2).map(|w| w[0]..w[1]).collect();
        let mut threads = HomeThreads::new(homes.len(), threads).unwrap();
        while !split.finished() {
            let passes = split.iteration_work().passes().len();
            let mut heard = Vec::new();
            let (_, costs) = split.step_split(&homes, &mut threads, |p| heard.push(p)).unwrap();
            assert_eq!(costs.len(), n);
            assert!(
                costs.iter().all(|&c| c > 0.0),
                "every batch was shot and timed: {costs:?}"
            );
            // Every batch of every pass, as it is finished, up to all of the iteration.
            assert_eq!(heard.len(), n * passes);
            assert!(heard.windows(2).all(|w| w[0].directions_done < w[1].directions_done));
            let last = heard.last().unwrap();
            assert_eq!(last.directions_done, last.directions_total);
        }
        assert!(
            without_times(split.checkpoint()) == want,
            "homes {homes:?} changed the bits"
        );
    }
    // `step` on pools of 1 to 7 threads (stints claimed one at a time, each batch summed in
    // stint order as they come in, whichever thread shot them): the same bits.
    for threads in [1, 2, 3, 4, 7] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let mut auto = Propagation::new(scene.clone(), options.clone()).unwrap();
        let mut heard = Vec::new();
        pool.install(|| auto.run(|p| heard.push(p)));
        assert!(
            without_times(auto.checkpoint()) == want,
            "step on {threads} threads changed the bits"
        );
        // Progress only grows within an iteration, up to all of it.
        for it in heard.chunk_by(|a, b| a.iteration == b.iteration) {
            assert!(it.windows(2).all(|w| w[0].directions_done < w[1].directions_done));
            let last = it.last().unwrap();
            assert_eq!(last.directions_done, last.directions_total);
        }
    }
}

/// A stint only regroups a batch's additions (`Batching`): every length gives its own bits on
/// every schedule (the plain loop, homes, stints claimed on 1 to 7 threads, workers), and a field
/// that agrees to rounding with stints of one direction (earlier builds' sums), though not to
/// the bit, or the option would do nothing.
#[test]
fn every_stint_gives_one_field_on_every_schedule_and_regroups_only_the_rounding() {
    let field = |stint| {
        let options = Options {
            stint_directions: stint,
            ..options(1)
        };
        assert_eq!(options.batching().stint(), stint as usize);
        homes_give_the_same_bits(lit_box(), options.clone(), 2, &[&[3]]);
        same_bits_as_in_process(lit_box(), options.clone());
        let mut p = Propagation::new(lit_box(), options).unwrap();
        p.run(|_| {});
        p.checkpoint().total
    };
    let one = field(1);
    let lit = one.iter().flatten().filter(|&&v| v > 0.0).count();
    assert!(lit > one.len(), "the box is lit");
    for stint in [2, 16] {
        let other = field(stint);
        assert_eq!(other.len(), one.len());
        let worst = one
            .iter()
            .flatten()
            .zip(other.iter().flatten())
            .map(|(a, b)| (a - b).abs() / a.abs().max(1e-300))
            .fold(0.0f64, f64::max);
        assert!(worst < 1e-12, "stints of {stint}: relative difference {worst:e}");
        assert!(other != one, "stints of {stint} summed exactly as single directions");
    }
    // With mirrors, each stint shoots its own directions' maps, on every schedule: stints of 2
    // and of 16 (l = 513 is cut into batches of 16 directions, so a batch is one stint, and
    // the last batch, of 17, a stint of 16 and one of 1).
    for stint in [2, 16] {
        let options = Options {
            directions: 513,
            stint_directions: stint,
            stop: Stop::Iterations(3),
            ..options(0)
        };
        homes_give_the_same_bits(mirror_room(), options.clone(), 2, &[&[5, 9]]);
        same_bits_as_in_process(mirror_room(), options);
    }
}

#[test]
fn a_block_cut_among_a_replicas_threads_gives_the_same_bits() {
    // Whole-pass blocks of 32 batches on pools of 1 to 4 threads: a replica's threads claim the
    // block's stints one at a time.
    let options = Options {
        directions: 513,
        stop: Stop::Iterations(3),
        ..options(0)
    };
    let mut straight = Propagation::new(mirror_room(), options.clone()).unwrap();
    while !straight.finished() {
        straight.step_shared(|_| {});
    }
    let want = without_times(straight.checkpoint());
    let batches = options.batching().count();
    assert_eq!(batches, 32);
    for threads in 1..=4 {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let (main, stored) = pool.install(|| run_distributed_in_blocks(&mirror_room(), &options, 1, true, batches));
        assert!(without_times(stored) == want, "{threads} threads changed the bits");
        assert!(without_times(main.checkpoint()) == want);
    }
}

#[test]
fn a_cut_blocks_batch_costs_add_up_to_no_more_than_the_block_took() {
    // A whole-pass block on 2 threads, its directions shot two at a time: each batch's cost is
    // its share of the block's time, so that a worker's report does not count its threads'
    // time twice (before that, they added up to about twice the block's time).
    let options = Options {
        directions: 513,
        stop: Stop::Iterations(2),
        ..options(0)
    };
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    pool.install(|| {
        let mut p = Propagation::new(mirror_room(), options).unwrap();
        let work = p.iteration_work();
        let n = work.batches();
        let started = std::time::Instant::now();
        let (_, _, costs) = p.compute_block_costed(&work, Pass::Shoot, 0..n).unwrap();
        let took = started.elapsed().as_secs_f64();
        assert_eq!(costs.len(), n);
        assert!(costs.iter().all(|&c| c > 0.0), "{costs:?}");
        let sum: f64 = costs.iter().sum();
        assert!(sum <= took, "batch costs add up to {sum} s, the block took {took} s");
    });
}

#[test]
fn homes_on_threads_of_their_own_give_the_same_bits_with_mirrors() {
    let options = Options {
        directions: 513,
        stop: Stop::Iterations(3),
        ..options(0)
    };
    // Uneven halves, a lone batch, three homes one of which is empty.
    homes_give_the_same_bits(mirror_room(), options, 1, &[&[7], &[1], &[15], &[5, 5, 11]]);
}

#[test]
fn homes_on_threads_of_their_own_give_the_same_bits_with_perturbation() {
    let scene = lit_box();
    homes_give_the_same_bits(scene, options(2), 2, &[&[1], &[2, 3]]);
}

/// Where every subfield is held, a rotated copy's subfields are built once, by its areas, and
/// taken by its shot (`step` shoots each copy right after its areas); within a subfield budget
/// they are built by both passes. The same bits either way, and as the plain loop's.
#[test]
fn rotated_subfields_are_built_once_where_every_subfield_is_held() {
    let options = options(2);
    let (l, copies) = (options.directions, options.perturbation.count as usize);
    let mut straight = Propagation::new(lit_box(), options.clone()).unwrap();
    while !straight.finished() {
        straight.step_shared(|_| {});
    }
    let want = without_times(straight.checkpoint());
    // The plain loop shoots the copies after all their areas: the first copy's are kept.
    assert_eq!(straight.rotated_subfields_built(), 2 * (2 * copies - 1) * l);

    let mut held = Propagation::new(lit_box(), options.clone()).unwrap();
    held.run(|_| {});
    assert_eq!(
        held.rotated_subfields_built(),
        2 * copies * l,
        "once per copy and direction"
    );
    assert!(
        without_times(held.checkpoint()) == want,
        "kept subfields changed the bits"
    );

    let budget = 64 << 10;
    let mut bounded = Propagation::with_subfield_budget(lit_box(), options, Some(budget)).unwrap();
    assert!(!bounded.subfields.all_held());
    bounded.run(|_| {});
    assert_eq!(
        bounded.rotated_subfields_built(),
        2 * 2 * copies * l,
        "twice within a budget"
    );
    assert!(without_times(bounded.checkpoint()) == want);
}

#[test]
// Homes of one range are what some of these cases mean.
#[allow(clippy::single_range_in_vec_init)]
fn homes_that_do_not_cover_the_pass_in_order_are_refused() {
    let mut p = Propagation::new(mirror_room(), options(0)).unwrap();
    let n = p.iteration_work().batches();
    let before = without_times(p.checkpoint());
    let mut two = HomeThreads::new(2, 1).unwrap();
    for homes in [
        vec![0..1, 2..n],
        vec![0..2, 1..n],
        vec![0..n - 1],
        vec![1..n],
        vec![0..1, 1..2, 2..n],
    ] {
        let e = p.step_split(&homes, &mut two, |_| {}).unwrap_err().to_string();
        assert!(e.contains("homes"), "{homes:?}: {e}");
    }
    assert!(HomeThreads::new(0, 1).is_err() && HomeThreads::new(2, 0).is_err());
    // Nothing was computed: the propagation is where it was.
    assert!(without_times(p.checkpoint()) == before);
}

#[test]
fn batches_partition_the_directions_into_whole_chunks() {
    use vlf_core::propagate::Batching;
    use vlf_core::propagate::CHUNK;
    for per_pass in (0..=10).map(|k| 1u32 << k) {
        for l in [9, 33, 129, 513, 2049, 8193] {
            let batching = Batching::new(l, per_pass, 8);
            let count = batching.count();
            // A power of two (the reduction tree's leaves), the target wherever `l` has
            // CHUNK directions for each, never more.
            assert!(
                count.is_power_of_two() && count <= per_pass as usize,
                "l = {l}: {count} of {per_pass}"
            );
            if (l - 1) / per_pass as usize >= CHUNK {
                assert_eq!(count, per_pass as usize, "l = {l}");
            }
            let mut next = 0;
            for b in 0..count {
                let r = batching.range(b);
                assert_eq!(r.start, next, "l = {l}, batch {b}");
                assert!(!r.is_empty());
                if b + 1 < count {
                    assert_eq!(r.len() % CHUNK, 0, "l = {l}, batch {b} of {} directions", r.len());
                }
                assert!(r.clone().all(|d| batching.batch_of(d) == b), "l = {l}, batch {b}");
                // Stints of 8 from the batch's first direction, the last one to its end.
                let stints: Vec<_> = batching.stints(b).collect();
                assert_eq!(stints.first().map(|s| s.start), Some(r.start));
                assert_eq!(stints.last().map(|s| s.end), Some(r.end));
                assert!(stints.windows(2).all(|w| w[0].end == w[1].start && w[0].len() == 8));
                assert!(stints.last().is_some_and(|s| (1..=8).contains(&s.len())));
                next = r.end;
            }
            assert_eq!(next, l, "l = {l}: batches end at {next}");
            assert!(batching.range(count).is_empty());
            assert_eq!(batching.directions_of(0..count), 0..l);
        }
    }
    // The legacy cut (jobs stored before the options) and the default.
    let legacy = Batching::new(513, 16, 1);
    assert_eq!((legacy.count(), legacy.range(15)), (16, 480..513));
    assert_eq!(legacy.stints(15).count(), 33, "a legacy stint is one direction");
    assert_eq!(Batching::new(33, 16, 1).range(1), 16..33);
    let default = Options::default().batching();
    assert_eq!(
        (default.count(), default.size(), default.stint()),
        (32, 16, 8),
        "l = 513 at the default"
    );
    use vlf_core::propagate::defaults::{PASS_BATCHES, STINT_DIRECTIONS};
    let big = Batching::new(2049, PASS_BATCHES, STINT_DIRECTIONS);
    assert_eq!((big.count(), big.range(63)), (64, 2016..2049));
    assert_eq!(
        big.stints(63).collect::<Vec<_>>(),
        [2016..2024, 2024..2032, 2032..2040, 2040..2048, 2048..2049]
    );
    // A target that is not a power of two (refused by the options) is the one below it; a
    // stint is CHUNK directions at most.
    assert_eq!(Batching::new(2049, 48, 8), Batching::new(2049, 32, 8));
    assert_eq!(Batching::new(2049, 0, 8), Batching::new(2049, 1, 8));
    assert_eq!(Batching::new(2049, 64, 6), Batching::new(2049, 64, 4));
    assert_eq!(Batching::new(2049, 64, 0), Batching::new(2049, 64, 1));
    assert_eq!(Batching::new(2049, 64, 64).stint(), CHUNK);
}

/// A coordinator opens an iteration's passes before it builds the iteration's work
/// (`iteration_passes`): they are the work's passes, with the same prerequisites, through the
/// perturbed iterations and after them, and in a scene with mirrors (never perturbed).
#[test]
fn the_next_passes_are_named_without_building_the_work() {
    for (scene, copies) in [(lit_box(), [3, 3, 0, 0]), (mirror_room(), [0; 4])] {
        let mut p = Propagation::new(scene, options(2)).unwrap();
        let mut seen = Vec::new();
        while !p.finished() {
            let (passes, work) = (p.iteration_passes(), p.iteration_work());
            assert_eq!(passes, work.passes());
            for &pass in &passes {
                assert_eq!(pass.prerequisites(), work.prerequisites(pass));
            }
            seen.push(passes.len());
            p.step(|_| {});
        }
        let expected: Vec<usize> = copies.iter().map(|&c| if c == 0 { 1 } else { 2 * c }).collect();
        assert_eq!(seen, expected);
    }
}

#[test]
fn a_perturbed_iteration_lists_every_copys_areas_first_and_learns_only_areas() {
    let scene = lit_box();
    let mut p = Propagation::new(scene, options(1)).unwrap();
    let mut work = p.iteration_work();
    let areas = |copy| Pass::Areas { copy };
    let shoot = |copy| Pass::ShootCopy { copy };
    assert_eq!(
        work.passes(),
        vec![areas(0), areas(1), areas(2), shoot(0), shoot(1), shoot(2)]
    );
    assert_eq!(work.prerequisites(shoot(1)), vec![areas(1)]);
    assert!(work.prerequisites(areas(2)).is_empty());
    assert!(!work.is_ready(shoot(1)));
    assert!(p.compute_block(&work, shoot(1), 0..1).is_err(), "areas unknown");
    let sums: Vec<_> = (0..work.batches())
        .map(|b| (b..b + 1, p.run_batch(&work, areas(1), b, None).unwrap()))
        .collect();
    assert!(work.learn(shoot(1), sums.clone()).is_err(), "not a prerequisite");
    assert!(work.learn(areas(1), sums[1..].to_vec()).is_err(), "a batch missing");
    assert!(work.learn(areas(7), sums.clone()).is_err(), "no such copy");
    // The areas learnt from single batches equal those from one block of all.
    let mut whole = p.iteration_work();
    let (all, _) = p.compute_block(&whole, areas(1), 0..work.batches()).unwrap();
    whole.learn(areas(1), [(0..work.batches(), all.sum)]).unwrap();
    work.learn(areas(1), sums).unwrap();
    assert!(work.is_ready(shoot(1)) && !work.is_ready(shoot(0)));
    let a = p.compute_block(&work, shoot(1), 0..2).unwrap();
    let b = p.compute_block(&whole, shoot(1), 0..2).unwrap();
    assert!(a == b, "a copy's areas depend on how they were leased");
    assert!(p.compute_block(&work, shoot(1), 1..3).is_err(), "not aligned");
}

#[test]
fn out_of_order_and_foreign_batches_are_refused() {
    let mut p = Propagation::new(mirror_room(), options(0)).unwrap();
    let mut work = p.iteration_work();
    assert_eq!(work.passes(), vec![Pass::Shoot]);
    // Maps never written are not held (their zeros are allocated when first written): refused.
    let mut maps = p.specular.as_ref().unwrap().maps[16..32].to_vec();
    let err = p.run_batch(&work, Pass::Shoot, 1, Some(&mut maps)).unwrap_err();
    assert!(err.to_string().contains("not held"), "{err}");
    p.specular.as_mut().unwrap().hold_zeros(16..32);
    let mut maps = p.specular.as_ref().unwrap().maps[16..32].to_vec();
    let sum = p.run_batch(&work, Pass::Shoot, 1, Some(&mut maps)).unwrap();
    // Batch 1 before batch 0; a block that is not a node of the tree.
    assert!(work.absorb(Pass::Shoot, 1..2, sum.clone()).is_err());
    assert!(work.absorb(Pass::Shoot, 0..3, sum.clone()).is_err());
    // A pass this iteration does not have; a batch past the end; maps missing.
    assert!(p.run_batch(&work, Pass::Areas { copy: 0 }, 0, None).is_err());
    assert!(p.run_batch(&work, Pass::Shoot, work.batches(), None).is_err());
    if work.uses_mirror_maps() {
        assert!(p.run_batch(&work, Pass::Shoot, 0, None).is_err());
    }
    // A sum of the wrong size, or with NaN.
    let mut short = sum.clone();
    short.texels.pop();
    assert!(work.absorb(Pass::Shoot, 0..1, short).is_err());
    let mut nan = sum.clone();
    nan.texels[0][1] = f64::NAN;
    assert!(work.absorb(Pass::Shoot, 0..1, nan).is_err());
    let mut nan = sum;
    nan.flow.escaped[2] = f64::INFINITY;
    assert!(work.absorb(Pass::Shoot, 0..1, nan).is_err());
    // Outputs of another iteration, or with maps that do not fit, are refused by the coordinator.
    let mut main = Propagation::new(mirror_room(), options(0)).unwrap();
    let mut work = main.iteration_work();
    let (mut out, block) = main.compute_block(&work, Pass::Shoot, 0..2).unwrap();
    out.iteration = 3;
    assert!(main.apply_batch(&mut work, out.clone()).is_err());
    out.iteration = 0;
    assert!(work.uses_mirror_maps());
    // Arrivals settled by batch: one part per batch of the block, finite power, feeding batches
    // that exist, each once, in order; none where the pass uses mirror maps is refused.
    let parts = match out.arrivals.clone() {
        Some(Arrivals::Settled(parts)) => parts,
        other => panic!("arrivals not settled: {other:?}"),
    };
    assert_eq!(parts.len(), 2);
    assert!(
        parts.iter().any(|p| !p.feeds.is_empty()),
        "light on a mirror in the first iteration"
    );
    let with = |change: &dyn Fn(&mut Vec<BatchArrivals>)| {
        let mut bad = out.clone();
        let mut parts = parts.clone();
        change(&mut parts);
        bad.arrivals = Some(Arrivals::Settled(parts));
        bad
    };
    let count = work.batches() as u32;
    for bad in [
        with(&|p| drop(p.pop())),
        with(&|p| p[0].exchange.incident[1] = f64::NAN),
        with(&|p| p[1].exchange.reflected[0] = -1.0),
        with(&|p| p[0].feeds.push(count)),
        with(&|p| p[0].feeds = vec![1, 0]),
        with(&|p| p[0].feeds = vec![0, 0]),
    ] {
        assert!(main.apply_batch(&mut work, bad).is_err());
    }
    let mut missing = out.clone();
    missing.arrivals = None;
    assert!(main.apply_batch(&mut work, missing).is_err());
    // As an earlier build reported them, `Φ_in` per direction (sparse, by increasing mirror),
    // they settle to the worker's bits; a NaN, a mirror beyond the scene's, one twice or a
    // direction short is refused.
    let block = block.unwrap();
    let spec = main.specular.as_ref().unwrap();
    let power: Vec<MirrorPower> = (block.shooting.iter().enumerate())
        .map(|(d, incident)| spec.power_in_of(&main.directions, d, incident))
        .collect();
    let batching = work.batching();
    for (b, part) in parts.iter().enumerate() {
        let of_batch: Vec<&MirrorPower> = power[batching.range(b)].iter().collect();
        assert_eq!(spec.settle_batch(&main.scene, &batching, b, &of_batch), *part);
    }
    let mirrors = spec.mirrors.len();
    let lit = power.iter().position(|p| !p.is_empty()).expect("light on a mirror");
    let with_power = |change: &dyn Fn(&mut Vec<MirrorPower>)| {
        let mut old = out.clone();
        let mut power = power.clone();
        change(&mut power);
        old.arrivals = Some(Arrivals::Power(power));
        old
    };
    for bad in [
        with_power(&|p| p[lit][0].1[1] = f64::NAN),
        with_power(&|p| p[lit].push((u32::MAX, [1.0; 3]))),
        with_power(&|p| {
            let first = p[lit][0];
            p[lit].push(first)
        }),
        with_power(&|p| drop(p.pop())),
    ] {
        assert!(main.apply_batch(&mut work, bad).is_err());
    }
    // Stored, it reads back; as earlier builds wrote it (`Φ_in`, dense or sparse), as `Φ_in`.
    assert_eq!(BatchOutput::from_bytes(&out.to_bytes()).unwrap(), out);
    for sparse in [false, true] {
        let old = vlf_core::propagate::snapshot::earlier::batch_output_of_power(&out, &power, mirrors, sparse);
        assert_eq!(BatchOutput::from_bytes(&old).unwrap(), with_power(&|_| {}));
    }
    // An earlier build's output is absorbed as this build's is.
    let mut old_work = main.iteration_work();
    main.apply_batch(&mut old_work, with_power(&|_| {})).unwrap();
    // Mirror maps of another snapshot, or that do not fit, are not adopted.
    assert!(
        main.adopt_mirrors(block.clone()).is_err(),
        "adopted before the iteration ended"
    );
    let mut short = block.clone();
    short.total.pop();
    assert!(main.adopt_mirrors(short).is_err());
    assert!(BatchOutput::from_bytes(b"garbage").is_err());
}

#[test]
fn a_block_takes_its_totals_along_and_is_computed_again_only_once_they_are_restored() {
    let mut p = Propagation::new(mirror_room(), options(0)).unwrap();
    // Past the first iterations: light reaches the mirrors, arrivals are pending.
    for _ in 0..3 {
        p.step(|_| {});
    }
    assert!(p.specular.as_ref().unwrap().pending.is_some());
    let saved = p.snapshot_bytes(true);
    let mut again = p.clone();
    let work = p.iteration_work();
    let (out, block) = p.compute_block(&work, Pass::Shoot, 0..1).unwrap();
    let block = block.unwrap();
    let spec = p.specular.as_ref().unwrap();
    let first = work.batch_range(0);
    let slots: usize = first.clone().map(|d| spec.slots(d)).sum();
    assert!(slots > 0, "the batch has mirror slots");
    assert!(
        first.clone().all(|d| spec.maps[d].total.is_empty()),
        "the totals moved into the block"
    );
    // Its other directions keep theirs.
    let next = work.batch_range(1);
    assert!(next.clone().all(|d| spec.maps[d].total.len() == spec.slots(d)));
    // The block's totals are the old ones plus what the directions sent
    // (gathered from the pending arrivals).
    let before = again.specular.as_ref().unwrap();
    let pending = before.pending.as_ref().unwrap();
    let read = |d: usize| before.maps[d].incident.as_slice();
    for (i, d) in first.clone().enumerate() {
        let sent = before
            .gather(&again.scene, &again.directions, &read, pending, d)
            .unwrap();
        let want: Vec<[f64; 3]> = before.maps[d]
            .total
            .iter()
            .zip(&sent)
            .map(|(t, s)| [t[0] + s[0], t[1] + s[1], t[2] + s[2]])
            .collect();
        assert_eq!(block.total[i], want, "direction {d}");
    }
    let (_, copied) = again.compute_block(&work, Pass::Shoot, 0..1).unwrap();
    assert_eq!(copied.unwrap(), block);

    // Again without the totals: refused, naming them.
    let err = p.compute_block(&work, Pass::Shoot, 0..1).unwrap_err().to_string();
    assert!(err.contains("totals"), "{err}");
    // Restored from the snapshot: the same output and maps, bit for bit.
    p.restore_totals_batch(MapBatch::from_bytes(&saved.mirror_totals[0]).unwrap())
        .unwrap();
    let (out2, block2) = p.compute_block(&work, Pass::Shoot, 0..1).unwrap();
    assert_eq!(out2.to_bytes(), out.to_bytes());
    assert_eq!(block2.unwrap(), block);
}

/// The big configurations' shape (l = 8193, the largest direction set: 64 batches of 128
/// directions) at a size CI affords (N = 8): the same bits from the in-process step on 1 and 2
/// threads, from 1, 2 and 3 workers, with mirrors and with perturbation.
#[test]
fn the_largest_direction_set_gives_the_same_bits_on_any_split() {
    for (scene, perturb) in [(mirror_room(), 0), (lit_box(), 1)] {
        let options = Options {
            directions: 8193,
            grid: GridSize::new(8, 4).unwrap(),
            stop: Stop::Iterations(2),
            ..options(perturb)
        };
        assert_eq!(options.batching().count(), 64);
        let mut want = None;
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut p = Propagation::new(scene.clone(), options.clone()).unwrap();
            pool.install(|| p.run(|_| {}));
            let got = without_times(p.checkpoint());
            match &want {
                None => want = Some(got),
                Some(w) => assert!(got == *w, "{threads} threads changed the bits"),
            }
        }
        let want = want.unwrap();
        for workers in [1, 2, 3] {
            let (_, stored) = run_distributed(&scene, &options, workers, false);
            assert!(without_times(stored) == want, "{workers} workers changed the bits");
        }
    }
}

/// A propagation that finished an iteration from a worker's block steps on by itself once it
/// has adopted the block's maps: the `Φ_in` of the arrivals it adopted is found from them, and
/// the next iterations have the bits of a run that never left the process.
#[test]
fn a_coordinator_that_adopted_every_block_steps_on_to_the_same_bits() {
    let scene = mirror_room();
    let mut straight = Propagation::new(scene.clone(), options(0)).unwrap();
    for _ in 0..5 {
        straight.step(|_| {});
    }
    let mut p = Propagation::new(scene, options(0)).unwrap();
    p.step(|_| {});
    p.step(|_| {});
    assert!(p.specular.as_ref().unwrap().pending.is_some(), "arrivals pending");
    let mut worker = p.clone();
    let mut work = p.iteration_work();
    let batches = work.batches();
    let (out, block) = worker.compute_block(&work, Pass::Shoot, 0..batches).unwrap();
    p.apply_batch(&mut work, out).unwrap();
    p.finish_iteration(work, std::time::Instant::now());
    let pending = p.specular.as_ref().unwrap().pending.as_ref().unwrap();
    assert!(pending.power_in(0).is_none(), "a coordinator knows no Φ_in");
    // The block hands its arrivals' `Φ_in` over with them: one short is refused.
    let block = block.unwrap();
    assert!(block.pending && block.power_in.len() == p.directions.len());
    let mut short = block.clone();
    short.power_in.pop();
    assert!(p.adopt_mirrors(short).is_err());
    p.adopt_mirrors(block).unwrap();
    let pending = p.specular.as_ref().unwrap().pending.as_ref().unwrap();
    assert!(
        (0..p.directions.len()).all(|d| pending.power_in(d).is_some()),
        "adopted, known"
    );
    p.step(|_| {});
    p.step(|_| {});
    assert!(without_times(p.checkpoint()) == without_times(straight.checkpoint()));
}
