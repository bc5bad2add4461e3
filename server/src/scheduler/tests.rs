//! The scheduler's state machine, driven by hand: no network, no store traffic.

// Blocks of one range are what these tests mean.
#![allow(clippy::single_range_in_vec_init)]

use super::pass::home;
use super::*;

fn scheduler(lease_ms: u64) -> Arc<Scheduler> {
    Scheduler::new(
        Store::open("memory://").unwrap(),
        Timing {
            lease: Duration::from_millis(lease_ms),
            heartbeat: Duration::from_secs(60),
            max_lease_batches: 1024,
        },
        None,
        None,
    )
}

fn job(s: &Scheduler) -> JobId {
    let id = JobId::generate();
    s.add_job(JobStatus {
        job_id: id.to_string(),
        state: WireState::Propagating as i32,
        ..Default::default()
    })
    .unwrap();
    s.start_iteration(&id, 1, 3, 40);
    id
}

#[tokio::test]
async fn batches_are_leased_once_and_a_pass_completes_when_all_are_reported() {
    let s = scheduler(60_000);
    let id = job(&s);
    s.start_pass(&id, 0, Pass::Shoot, 3, &[1..2], &[]);
    let w = s.register("a", Abilities::ALL);
    let a = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    let b = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((a.batches, b.batches), (0..1, 2..3), "batch 1 was already in the store");
    assert_eq!(s.lease(&w, Duration::from_millis(10)).await.unwrap(), None);
    assert_eq!(s.pass_outcome(&id, Pass::Shoot, 0), PassOutcome::Running);
    assert!(s.report(&w, &a.lease_id, Ok(()), 0.01).unwrap());
    assert!(
        !s.report(&w, &a.lease_id, Ok(()), 0.01).unwrap(),
        "a lease reports once"
    );
    assert_eq!(s.status(&id).unwrap().batches_done, 2);
    assert_eq!(
        s.pass_outcome(&id, Pass::Shoot, 0),
        PassOutcome::Ready(vec![0..1, 1..2]),
        "batches 0 and 1 can be absorbed while 2 is out"
    );
    assert_eq!(s.pass_outcome(&id, Pass::Shoot, 2), PassOutcome::Running);
    assert!(s.report(&w, &b.lease_id, Ok(()), 0.01).unwrap());
    assert_eq!(s.pass_outcome(&id, Pass::Shoot, 2), PassOutcome::Ready(vec![2..3]));
    assert!(matches!(s.heartbeat("nobody"), Err(Unknown::Worker(_))));
}

#[tokio::test]
async fn an_expired_lease_goes_to_another_worker_and_its_late_report_is_ignored() {
    let s = scheduler(20);
    let id = job(&s);
    s.start_pass(&id, 4, Pass::Areas { copy: 1 }, 1, &[], &[]);
    let (w1, w2) = (s.register("slow", Abilities::ALL), s.register("fast", Abilities::ALL));
    let first = s.lease(&w1, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((first.snapshot, first.pass), (4, Pass::Areas { copy: 1 }));
    assert_eq!(s.lease(&w2, Duration::ZERO).await.unwrap(), None);
    tokio::time::sleep(Duration::from_millis(30)).await;
    assert_eq!(s.reap(), 1);
    let second = s.lease(&w2, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(second.batches, first.batches);
    assert!(
        !s.report(&w1, &first.lease_id, Ok(()), 0.01).unwrap(),
        "late report ignored: another worker took its batch"
    );
    let areas = Pass::Areas { copy: 1 };
    assert_eq!(s.pass_outcome(&id, areas, 0), PassOutcome::Running);
    assert!(s.report(&w2, &second.lease_id, Ok(()), 0.01).unwrap());
    assert_eq!(s.pass_outcome(&id, areas, 0), PassOutcome::Ready(vec![0..1]));
}

/// A worker slower than the deadline, which no other worker relieves, has its late report
/// taken: its block is done, and the job learns its speed, so its next lease is cut to fit.
/// Without it, the block expired, went back to the same worker, and was never reported in time.
#[tokio::test]
async fn a_late_report_is_taken_when_no_other_worker_took_its_batches() {
    let s = scheduler(20);
    let id = job(&s);
    s.start_pass(&id, 0, Pass::Shoot, 8, &[], &[]);
    let slow = s.register("slow", Abilities::ALL);
    let first = s.lease(&slow, Duration::ZERO).await.unwrap().unwrap();
    tokio::time::sleep(Duration::from_millis(30)).await;
    assert_eq!(s.reap(), 1);
    // Reported late: nobody took its batches.
    assert!(s.report(&slow, &first.lease_id, Ok(()), 0.03).unwrap(), "taken, late");
    assert!(!s.report(&slow, &first.lease_id, Ok(()), 0.03).unwrap(), "once only");
    let done = first.batches.clone();
    assert_eq!(
        s.pass_outcome(&id, Pass::Shoot, 0),
        PassOutcome::Ready(vlf_core::propagate::reduce::cover(done.clone()))
    );
    // Its worker, reporting from the background, asked for its next lease meanwhile and was
    // given the same batch back: the late report is still its own, and the newer lease goes.
    let again = s.lease(&slow, Duration::ZERO).await.unwrap().unwrap();
    tokio::time::sleep(Duration::from_millis(30)).await;
    assert_eq!(s.reap(), 1);
    let back = s.lease(&slow, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(back.batches, again.batches, "the same batch back");
    assert!(s.report(&slow, &again.lease_id, Ok(()), 0.03).unwrap(), "taken, late");
    assert!(
        !s.report(&slow, &back.lease_id, Ok(()), 0.03).unwrap(),
        "the newer lease went with it"
    );
    assert!(
        matches!(s.pass_outcome(&id, Pass::Shoot, 0), PassOutcome::Ready(blocks) if blocks.last().is_some_and(|b| b.end >= again.batches.end)),
        "its batch is done"
    );
    // A cancelled job's expired lease is not revived.
    let next = s.lease(&slow, Duration::ZERO).await.unwrap().unwrap();
    tokio::time::sleep(Duration::from_millis(30)).await;
    assert_eq!(s.reap(), 1);
    s.cancel(&id).unwrap();
    assert!(!s.report(&slow, &next.lease_id, Ok(()), 0.03).unwrap());
}

#[tokio::test]
async fn several_open_passes_are_leased_in_order_and_closed_as_absorbed() {
    let s = scheduler(60_000);
    let id = job(&s);
    let (a0, a1) = (Pass::Areas { copy: 0 }, Pass::Areas { copy: 1 });
    s.start_pass(&id, 2, a0, 3, &[], &[]);
    s.start_pass(&id, 2, a1, 3, &[1..2], &[]);
    let w = s.register("a", Abilities::ALL);
    let mut grants = Vec::new();
    while let Some(g) = s.lease(&w, Duration::ZERO).await.unwrap() {
        grants.push(g);
    }
    let order: Vec<_> = grants.iter().map(|g| (g.pass, g.batches.start)).collect();
    assert_eq!(order, vec![(a0, 0), (a0, 1), (a0, 2), (a1, 0), (a1, 2)]);
    assert!(grants.iter().all(|g| g.snapshot == 2));
    // A report finds its own pass's batch, whichever pass it is.
    assert!(s.report(&w, &grants[3].lease_id, Ok(()), 0.01).unwrap());
    assert_eq!(s.pass_outcome(&id, a1, 0), PassOutcome::Ready(vec![0..1, 1..2]));
    assert_eq!(s.pass_outcome(&id, a0, 0), PassOutcome::Running);
    for g in &grants[..3] {
        assert!(s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap());
    }
    assert_eq!(s.pass_outcome(&id, a0, 0), PassOutcome::Ready(vec![0..1, 1..2, 2..3]));
    assert_eq!(s.status(&id).unwrap().batches_done, 5);
    s.end_pass(&id, 2, a0);
    assert_eq!(
        s.status(&id).unwrap().batches_done,
        5,
        "a closed pass still counts as done"
    );
    assert_eq!(s.pass_outcome(&id, a0, 0), PassOutcome::Running, "closed");
    assert!(s.report(&w, &grants[4].lease_id, Ok(()), 0.01).unwrap());
    assert_eq!(s.pass_outcome(&id, a1, 2), PassOutcome::Ready(vec![2..3]));
    assert!(grants.iter().all(|g| g.reads.is_empty()), "the areas read nothing");
    // The copy's shooting, opened with the blocks its areas were absorbed as: its leases name
    // them, so that a worker reads those it lacks without listing the store.
    let absorbed = vec![(a0, vec![0..1, 1..2, 2..3])];
    s.start_pass(&id, 2, Pass::ShootCopy { copy: 0 }, 3, &[], &absorbed);
    let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((g.pass, g.reads), (Pass::ShootCopy { copy: 0 }, absorbed));
}

#[test]
fn blocks_grow_with_fewer_workers_and_shrink_for_slow_batches() {
    let minute = Duration::from_secs(60);
    assert_eq!(block_len(16, 16, 1, None, minute), 1, "speed unknown");
    assert_eq!(
        block_len(16, 16, 1, Some(0.01), minute),
        16,
        "one worker: the whole pass"
    );
    assert_eq!(block_len(16, 16, 0, Some(0.01), minute), 16);
    assert_eq!(block_len(16, 16, 2, Some(0.01), minute), 4);
    assert_eq!(block_len(16, 16, 3, Some(0.01), minute), 2);
    assert_eq!(block_len(16, 16, 64, Some(0.01), minute), 1);
    assert_eq!(block_len(8, 8, 1, Some(2.0), minute), 4, "4 × 2 s ≤ 15 s < 8 × 2 s");
    assert_eq!(block_len(8, 8, 1, Some(100.0), minute), 1);
    assert_eq!(block_len(2, 2, 1, Some(0.01), minute), 2);
    // Four passes open (a perturbed iteration's areas): two workers take whole passes, and
    // leases shrink as the open work runs out.
    assert_eq!(block_len(16, 64, 2, Some(0.01), minute), 16);
    assert_eq!(block_len(16, 24, 2, Some(0.01), minute), 8);
    assert_eq!(
        block_len(16, 6, 2, Some(0.01), minute),
        4,
        "never below a quarter of the pass"
    );
    assert_eq!(
        block_len(16, 64, 2, Some(2.0), minute),
        4,
        "the lease's lifetime still bounds it"
    );
}

/// A job whose speed `w` has measured (a one-batch pass reported), so leases are sized by
/// the workers.
async fn job_of_known_speed(s: &Scheduler, w: &str) -> JobId {
    let id = job(s);
    s.start_pass(&id, 0, Pass::Shoot, 1, &[], &[]);
    let g = s.lease(w, Duration::ZERO).await.unwrap().unwrap();
    assert!(s.report(w, &g.lease_id, Ok(()), 0.01).unwrap());
    s.end_pass(&id, 0, Pass::Shoot);
    id
}

#[tokio::test]
async fn stored_blocks_are_kept_and_new_blocks_never_straddle_them() {
    let s = scheduler(60_000);
    let w = s.register("a", Abilities::ALL);
    // The speed is known: one worker leases as much as it can.
    let id = job_of_known_speed(&s, &w).await;
    let areas = Pass::Areas { copy: 0 };
    // In the store: 0..2 and 0..4 (the larger is taken), 1..3 (not a node of the tree:
    // ignored), 4..6 and 12..16.
    s.start_pass(&id, 0, areas, 16, &[0..2, 0..4, 1..3, 4..6, 12..16], &[]);
    assert_eq!(s.pass_outcome(&id, areas, 0), PassOutcome::Ready(vec![0..4, 4..6]));
    // With two workers, each in its home (a: 0..8, old: 8..16), blocks of 4 batches at most:
    // one that does not take runs gets an aligned block, one that does the rest of its home.
    let old = s.register("old", Abilities::BLOCKS);
    let g = s.lease(&old, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.batches, 8..12);
    let mut grants = Vec::new();
    while let Some(g) = s.lease(&w, Duration::ZERO).await.unwrap() {
        grants.push(g.batches);
    }
    assert_eq!(grants, vec![6..8]);
    // Alone, a worker that takes runs gets the gap in one lease.
    let s = scheduler(60_000);
    let w = s.register("a", Abilities::ALL);
    let id = job_of_known_speed(&s, &w).await;
    s.start_pass(&id, 0, areas, 16, &[0..2, 0..4, 1..3, 4..6, 12..16], &[]);
    let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.batches, 6..12, "up to the stored block, not into it");
    assert!(s.lease(&w, Duration::ZERO).await.unwrap().is_none());
    // Its report marks every aligned block of the run written.
    assert!(s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap());
    assert_eq!(
        s.pass_outcome(&id, areas, 0),
        PassOutcome::Ready(vec![0..4, 4..6, 6..8, 8..12, 12..16])
    );
}

#[tokio::test]
async fn after_a_report_a_lone_worker_leases_whole_passes() {
    let s = scheduler(60_000);
    let id = job(&s);
    let w = s.register("a", Abilities::ALL);
    s.start_pass(&id, 0, Pass::Shoot, 16, &[], &[]);
    let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.batches, 0..1, "speed unknown: one batch");
    assert!(s.report(&w, &g.lease_id, Ok(()), 0.05).unwrap());
    s.start_pass(&id, 0, Pass::Areas { copy: 0 }, 16, &[], &[]);
    let mut grants = Vec::new();
    while let Some(g) = s.lease(&w, Duration::ZERO).await.unwrap() {
        grants.push((g.pass, g.batches));
    }
    // The rest of the pass in one lease, then the next pass whole.
    let shoot = Pass::Shoot;
    assert_eq!(grants, [(shoot, 1..16), (Pass::Areas { copy: 0 }, 0..16)]);

    // A worker that does not take runs gets the rest in the largest aligned blocks.
    let s = scheduler(60_000);
    let id = job(&s);
    let w = s.register("old", Abilities::BLOCKS);
    s.start_pass(&id, 0, Pass::Shoot, 16, &[], &[]);
    let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.batches, 0..1, "speed unknown: one batch");
    assert!(s.report(&w, &g.lease_id, Ok(()), 0.05).unwrap());
    let mut grants = Vec::new();
    while let Some(g) = s.lease(&w, Duration::ZERO).await.unwrap() {
        grants.push(g.batches);
    }
    assert_eq!(grants, [1..2, 2..4, 4..8, 8..16]);
}

#[tokio::test]
async fn a_worker_shoots_the_batches_it_shot_last_time() {
    let s = scheduler(60_000);
    let id = job(&s);
    let (a, b) = (s.register("a", Abilities::ALL), s.register("b", Abilities::ALL));
    let shoot = Pass::Shoot;
    // Iteration 1: a takes the first half, b the second.
    s.start_pass(&id, 0, shoot, 4, &[], &[]);
    let mut first = Vec::new();
    for w in [&a, &a, &b, &b] {
        let g = s.lease(w, Duration::ZERO).await.unwrap().unwrap();
        first.push(g.batches.clone());
        assert!(s.report(w, &g.lease_id, Ok(()), 0.0).unwrap());
    }
    assert_eq!(first, [0..1, 1..2, 2..3, 3..4]);
    s.end_pass(&id, 0, shoot);
    // Iteration 2: b asks first and is given its own batches, not batch 0; and so in a rotated
    // copy's areas (a worker's shot of the copy finds the subfields its areas built).
    s.start_pass(&id, 1, shoot, 4, &[], &[]);
    let g = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.batches.start, 2, "b shot batches 2 and 3 last time");
    let h = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(h.batches.start, 0);
    assert!(s.report(&b, &g.lease_id, Ok(()), 0.0).unwrap());
    assert!(s.report(&a, &h.lease_id, Ok(()), 0.0).unwrap());
    let own = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(own.batches, 3..4);
    // What is left of a's batches goes to b rather than nobody: no worker waits.
    let rest = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(rest.batches, 1..2);
    s.start_pass(&id, 1, Pass::Areas { copy: 0 }, 4, &[], &[]);
    let areas = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((areas.pass, areas.batches.start), (Pass::Areas { copy: 0 }, 2));
    let areas = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((areas.pass, areas.batches.start), (Pass::Areas { copy: 0 }, 0));
}

/// A perturbed iteration's passes are leased as one process shoots them (`Pass::shooting_rank`):
/// a rotated copy's shot, once open, before the next copy's areas, and those areas wait while
/// the shot is about to open (its areas all written, not yet absorbed) — a worker keeps the
/// subfields its areas built for the shot, one copy's at most. The two workers' parts of a
/// copy's shot are their parts of its areas.
#[tokio::test]
async fn a_copys_shot_is_leased_before_the_next_copys_areas() {
    let s = scheduler(60_000);
    let id = job(&s);
    let (a0, a1, s0) = (
        Pass::Areas { copy: 0 },
        Pass::Areas { copy: 1 },
        Pass::ShootCopy { copy: 0 },
    );
    s.start_pass(&id, 1, a0, 4, &[], &[]);
    s.start_pass(&id, 1, a1, 4, &[], &[]);
    let (a, b) = (s.register("a", Abilities::ALL), s.register("b", Abilities::ALL));
    let mut parts: HashMap<String, Vec<usize>> = HashMap::new();
    for w in [&a, &b].into_iter().cycle().take(8) {
        if let Some(g) = s.lease(w, Duration::ZERO).await.unwrap() {
            assert_eq!(g.pass, a0, "copy 0's areas first");
            parts.entry(w.clone()).or_default().extend(g.batches.clone());
            assert!(s.report(w, &g.lease_id, Ok(()), 0.01).unwrap());
        }
    }
    assert_eq!(parts.values().map(Vec::len).sum::<usize>(), 4);
    // Copy 0's areas are all written: its shot opens as soon as they are absorbed, and copy 1's
    // areas wait for it.
    assert_eq!(s.lease(&a, Duration::ZERO).await.unwrap(), None);
    let absorbed = vec![(a0, vec![0..4])];
    s.start_pass(&id, 1, s0, 4, &[], &absorbed);
    s.end_pass(&id, 1, a0);
    let mut shot: HashMap<String, Vec<usize>> = HashMap::new();
    for w in [&b, &a] {
        let g = s.lease(w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.pass, s0, "the shot before the next copy's areas, opened earlier");
        shot.entry(w.clone()).or_default().extend(g.batches.clone());
    }
    // Each worker's leases of the shot start in its part of the areas.
    for w in [&a, &b] {
        assert!(
            parts[w].contains(&shot[w][0]),
            "{w}: areas {:?}, shot {:?}",
            parts[w],
            shot[w]
        );
    }
    // Copy 1's areas go on while the shot is out.
    let next = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(next.pass, a1);
}

/// A copy's shot opens once its areas and every earlier copy's are absorbed (the driver absorbs
/// every copy's areas in turn): with copy 0's areas still out and copy 1's all in the store (a
/// job taken up), copy 2's areas do not wait for copy 1's shot. Once copy 0's are written too,
/// they wait.
#[tokio::test]
async fn the_next_areas_wait_only_for_a_shot_that_opens_once_absorbed() {
    let s = scheduler(60_000);
    let id = job(&s);
    let areas = |copy| Pass::Areas { copy };
    s.start_pass(&id, 1, areas(0), 2, &[], &[]);
    s.start_pass(&id, 1, areas(1), 2, &[0..2], &[]);
    s.start_pass(&id, 1, areas(2), 2, &[], &[]);
    let (x, y) = (s.register("x", Abilities::ALL), s.register("y", Abilities::ALL));
    let first = s.lease(&x, Duration::ZERO).await.unwrap().unwrap();
    let second = s.lease(&y, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((first.pass, second.pass), (areas(0), areas(0)));
    let third = s.lease(&x, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(third.pass, areas(2), "copy 0's areas are out: no shot opens yet");
    assert!(s.report(&x, &first.lease_id, Ok(()), 0.01).unwrap());
    assert!(s.report(&y, &second.lease_id, Ok(()), 0.01).unwrap());
    // Copy 0's and copy 1's areas are written: their shots open once absorbed, and copy 2's
    // last areas wait.
    assert_eq!(s.lease(&y, Duration::ZERO).await.unwrap(), None);
}

#[tokio::test]
async fn two_workers_shoot_the_halves_of_the_pass_whatever_order_they_ask_in() {
    let s = scheduler(60_000);
    let id = job(&s);
    let (a, b) = (s.register("a", Abilities::ALL), s.register("b", Abilities::ALL));
    let shoot = Pass::Shoot;
    s.start_pass(&id, 0, shoot, 16, &[], &[]);
    // Speed unknown: one batch each, a at the start of its home, b at the start of its own.
    let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((ga.batches.clone(), gb.batches.clone()), (0..1, 8..9));
    assert!(s.report(&a, &ga.lease_id, Ok(()), 0.01).unwrap());
    assert!(s.report(&b, &gb.lease_id, Ok(()), 0.01).unwrap());
    // Then each the rest of its home in one lease, asked for in turn.
    let mut got: HashMap<String, Vec<Range<usize>>> = HashMap::new();
    for w in [&a, &b, &a, &b] {
        if let Some(g) = s.lease(w, Duration::ZERO).await.unwrap() {
            got.entry(w.clone()).or_default().push(g.batches.clone());
            assert!(s.report(w, &g.lease_id, Ok(()), 0.01 * g.batches.len() as f64).unwrap());
        }
    }
    assert_eq!(got[&a], [1..8]);
    assert_eq!(got[&b], [9..16]);
    s.end_pass(&id, 0, shoot);
    // The next iteration keeps them: b, asking first, gets its half.
    s.start_pass(&id, 1, shoot, 16, &[], &[]);
    let g = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.batches, 8..16);
    // Done with its home, b helps with a's, a quarter of the pass at a time, from the start.
    let g = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.batches, 0..4);
    // a then takes what is left of its home.
    let g = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.batches, 4..8);
}

/// A job whose speed is known, and its shooting pass of 16 batches open, with workers `a`
/// and `b` registered with `abilities`.
async fn two_workers_and_a_pass(s: &Scheduler, abilities: Abilities) -> (JobId, String, String) {
    let (a, b) = (s.register("a", abilities), s.register("b", abilities));
    let id = job_of_known_speed(s, &a).await;
    s.start_pass(&id, 1, Pass::Shoot, 16, &[], &[]);
    (id, a, b)
}

#[tokio::test]
async fn an_idle_worker_is_given_the_tail_a_busy_one_has_not_claimed() {
    let s = scheduler(60_000);
    let (id, a, b) = two_workers_and_a_pass(&s, Abilities::ALL).await;
    // Each worker's home in one lease, its last quarter not committed.
    let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((ga.batches.clone(), ga.committed), (0..8, 6));
    assert_eq!((gb.batches.clone(), gb.committed), (8..16, 14));
    // b is done first (it claimed its tail, then reported); a has not claimed its tail: b
    // is given it, committed whole (too short to share again).
    assert_eq!(s.extend(&b, &gb.lease_id).unwrap(), Some((16, 16)));
    assert!(s.report(&b, &gb.lease_id, Ok(()), 0.08).unwrap());
    let tail = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((tail.batches.clone(), tail.committed), (6..8, 8));
    assert_eq!(s.status(&id).unwrap().leases_out, 2);
    // a learns it when it claims: its run now ends at 6, all of it committed.
    assert_eq!(s.extend(&a, &ga.lease_id).unwrap(), Some((6, 6)));
    // Nothing is left to give: a committed run is never taken.
    assert_eq!(s.lease(&b, Duration::from_millis(5)).await.unwrap(), None);
    // A report past the run's new end is not taken; one at its end is.
    assert!(!s.report_run(&a, &ga.lease_id, Ok(()), 0.06, Some(8), &[]).unwrap());
    assert!(s.report_run(&a, &ga.lease_id, Ok(()), 0.06, Some(6), &[]).unwrap());
    assert!(s.report(&b, &tail.lease_id, Ok(()), 0.02).unwrap());
    assert_eq!(
        s.pass_outcome(&id, Pass::Shoot, 0),
        PassOutcome::Ready(vec![0..4, 4..6, 6..8, 8..16]),
        "the outputs of what each computed: the cover of its run"
    );
    // The tail counts as b's work: b shot it.
    let state = s.lock();
    let shooters = &state.jobs[&id].shooting.shooters;
    assert_eq!(shooters[5].as_deref(), Some(a.as_str()));
    assert_eq!(shooters[6].as_deref(), Some(b.as_str()));
}

#[tokio::test]
async fn a_claimed_run_is_kept_and_a_claim_on_a_lease_that_is_gone_is_refused() {
    let s = scheduler(60_000);
    let (id, a, b) = two_workers_and_a_pass(&s, Abilities::ALL).await;
    let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(s.extend(&a, &ga.lease_id).unwrap(), Some((8, 8)));
    assert_eq!(
        s.extend(&a, &ga.lease_id).unwrap(),
        Some((8, 8)),
        "claiming again changes nothing"
    );
    assert_eq!(s.extend(&b, &ga.lease_id).unwrap(), None, "another worker's lease");
    assert_eq!(s.extend(&a, "l999").unwrap(), None, "no such lease");
    assert!(s.extend("w99-nobody", &ga.lease_id).is_err(), "an unknown worker");
    // b takes its home; with a's run claimed, there is nothing to take from a.
    let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(gb.batches, 8..16);
    assert!(s.report(&b, &gb.lease_id, Ok(()), 0.08).unwrap());
    assert_eq!(s.lease(&b, Duration::from_millis(5)).await.unwrap(), None);
    s.cancel(&id).unwrap();
    assert_eq!(s.extend(&a, &ga.lease_id).unwrap(), None, "the job was cancelled");
}

#[tokio::test]
async fn a_report_of_part_of_a_run_puts_the_rest_back() {
    let s = scheduler(60_000);
    let (id, a, b) = two_workers_and_a_pass(&s, Abilities::ALL).await;
    let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(ga.batches, 0..8);
    // a could not claim its tail (the coordinator did not answer): it reports 0..6.
    assert!(
        !s.report_run(&a, &ga.lease_id, Ok(()), 0.06, Some(0), &[]).unwrap(),
        "an empty run"
    );
    assert!(s.report_run(&a, &ga.lease_id, Ok(()), 0.06, Some(6), &[]).unwrap());
    assert_eq!(
        s.pass_outcome(&id, Pass::Shoot, 0),
        PassOutcome::Ready(vec![0..4, 4..6])
    );
    // The rest is pending again: b's home first, then what a left.
    let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(gb.batches, 8..16);
    let rest = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(rest.batches, 6..8);
}

#[tokio::test]
async fn leases_of_workers_that_do_not_claim_are_committed_and_never_shared() {
    let s = scheduler(60_000);
    let (_, a, b) = two_workers_and_a_pass(&s, Abilities::RUNS).await;
    let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((ga.batches.clone(), ga.committed), (0..8, 8));
    let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert!(s.report(&b, &gb.lease_id, Ok(()), 0.08).unwrap());
    assert_eq!(s.lease(&b, Duration::from_millis(5)).await.unwrap(), None);
    // A worker of an earlier build, leased single blocks, takes no one's tail either.
    let s = scheduler(60_000);
    let (_, a, _) = two_workers_and_a_pass(&s, Abilities::ALL).await;
    let old = s.register("old", Abilities::BLOCKS);
    let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert!(ga.committed < ga.batches.end);
    while let Some(g) = s.lease(&old, Duration::ZERO).await.unwrap() {
        assert!(s.report(&old, &g.lease_id, Ok(()), 0.01).unwrap());
    }
    assert_eq!(
        s.extend(&a, &ga.lease_id).unwrap(),
        Some((ga.batches.end, ga.batches.end))
    );
    // And a lone worker's lease is committed whole: no one could take a part of it.
    let s = scheduler(60_000);
    let w = s.register("a", Abilities::ALL);
    let id = job_of_known_speed(&s, &w).await;
    s.start_pass(&id, 1, Pass::Shoot, 16, &[], &[]);
    let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!((g.batches.clone(), g.committed), (0..16, 16));
}

#[test]
fn homes_split_the_pass_by_what_its_batches_cost() {
    let workers: HashMap<String, WorkerEntry> = ["w2-b", "w1-a", "w3-c"]
        .iter()
        .map(|id| {
            let number = id[1..2].parse().unwrap();
            let entry = WorkerEntry {
                number,
                last_seen: Instant::now(),
                abilities: Abilities::ALL,
            };
            (id.to_string(), entry)
        })
        .collect();
    let two: HashMap<_, _> = workers
        .iter()
        .filter(|(id, _)| *id != "w3-c")
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    // Nothing measured: equal runs, in registration order (not the map's).
    assert_eq!(home("w1-a", &two, 16, &[]), 0..8);
    assert_eq!(home("w2-b", &two, 16, &[]), 8..16);
    assert_eq!(home("w1-a", &workers, 16, &[]), 0..5, "16/3 = 5.33, nearest 5");
    assert_eq!(home("w2-b", &workers, 16, &[]), 5..11);
    assert_eq!(home("w3-c", &workers, 16, &[]), 11..16);
    assert_eq!(home("w9-gone", &two, 16, &[]), 0..16);
    // The first half ten times cheaper: the first worker takes 12 batches.
    let costs: Vec<f64> = (0..16).map(|b| if b < 8 { 0.001 } else { 0.01 }).collect();
    assert_eq!(home("w1-a", &two, 16, &costs), 0..12);
    assert_eq!(home("w2-b", &two, 16, &costs), 12..16);
    // Unmeasured batches cost the mean of the measured ones.
    let partial = [0.0, 0.0, 0.0, 0.0, 3.0, 3.0, 3.0, 3.0];
    assert_eq!(home("w1-a", &two, 8, &partial), 0..4);
}

#[tokio::test]
async fn a_worker_whose_batches_were_cheap_gets_more_of_the_next_pass() {
    let s = scheduler(60_000);
    let id = job(&s);
    let (a, b) = (s.register("a", Abilities::ALL), s.register("b", Abilities::ALL));
    let shoot = Pass::Shoot;
    // Iteration 1: batch by batch (speed unknown until a report, then blocks of 4); a's
    // half takes a tenth of the time of b's.
    s.start_pass(&id, 0, shoot, 16, &[], &[]);
    let cost = |batches: &Range<usize>| batches.len() as f64 * if batches.start < 8 { 0.001 } else { 0.01 };
    while let Some(g) = s.lease(&a, Duration::ZERO).await.unwrap() {
        assert!(s.report(&a, &g.lease_id, Ok(()), cost(&g.batches)).unwrap());
        if let Some(g) = s.lease(&b, Duration::ZERO).await.unwrap() {
            assert!(s.report(&b, &g.lease_id, Ok(()), cost(&g.batches)).unwrap());
        }
    }
    s.end_pass(&id, 0, shoot);
    // Iteration 2: a's home is 0..12 and b's 12..16, each in one lease, b asking first.
    s.start_pass(&id, 1, shoot, 16, &[], &[]);
    let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(gb.batches, 12..16);
    let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(ga.batches, 0..12);
}

/// Within a lease the batches' costs come from the report, batch by batch, rather than an even
/// share of its seconds: where the cost lies inside a worker's half decides where the next split
/// falls.
#[tokio::test]
async fn a_report_gives_each_batch_its_own_cost() {
    // a's half costs 12 ms, b's 20 ms: the next split is where 16 ms are behind. Shared evenly,
    // b's batches cost 2.5 ms each and 16 ms lie between batches 9 and 10 (14.5 and 17 ms,
    // the nearer 10); costed one by one, b's first two cost 4 ms and 16 ms lie at batch 9.
    let costed = [0.004, 0.004, 0.002, 0.002, 0.002, 0.002, 0.002, 0.002];
    for (costs, b_home) in [(&[][..], 10..16), (&costed[..], 9..16)] {
        let s = scheduler(60_000);
        let (id, a, b) = two_workers_and_a_pass(&s, Abilities::ALL).await;
        let ga = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
        let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!((ga.batches.clone(), gb.batches.clone()), (0..8, 8..16));
        assert!(s.report_run(&a, &ga.lease_id, Ok(()), 0.012, None, &[]).unwrap());
        assert!(s.report_run(&b, &gb.lease_id, Ok(()), 0.020, None, costs).unwrap());
        s.end_pass(&id, 1, Pass::Shoot);
        s.start_pass(&id, 2, Pass::Shoot, 16, &[], &[]);
        let gb = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(gb.batches, b_home, "costs {costs:?}");
    }
}

#[tokio::test]
async fn a_waiting_lease_is_served_when_a_pass_opens() {
    let s = scheduler(60_000);
    let id = job(&s);
    let w = s.register("a", Abilities::ALL);
    let waiter = {
        let (s, w) = (s.clone(), w.clone());
        tokio::spawn(async move { s.lease(&w, Duration::from_secs(30)).await })
    };
    tokio::time::sleep(Duration::from_millis(20)).await;
    s.start_pass(&id, 0, Pass::Shoot, 1, &[], &[]);
    let grant = tokio::time::timeout(Duration::from_secs(5), waiter)
        .await
        .expect("woken")
        .unwrap()
        .unwrap();
    assert!(grant.is_some());
}

#[tokio::test]
async fn repeated_failures_fail_the_job_and_cancel_withdraws_work() {
    let s = scheduler(60_000);
    let id = job(&s);
    s.start_pass(&id, 0, Pass::Shoot, 2, &[], &[]);
    let w = s.register("a", Abilities::ALL);
    for attempt in 1..=MAX_BATCH_FAILURES {
        let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 0..1, "a failed block is handed out again first");
        assert!(s.report(&w, &g.lease_id, Err("disk full".into()), 0.01).unwrap());
        let outcome = s.pass_outcome(&id, Pass::Shoot, 0);
        if attempt < MAX_BATCH_FAILURES {
            assert_eq!(outcome, PassOutcome::Running);
        } else {
            assert!(matches!(outcome, PassOutcome::Failed(m) if m.contains("disk full")));
        }
    }
    assert_eq!(
        s.lease(&w, Duration::ZERO).await.unwrap(),
        None,
        "a failed job leases nothing"
    );

    let other = job(&s);
    s.start_pass(&other, 0, Pass::Shoot, 2, &[], &[]);
    let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(g.job, other);
    s.cancel(&other).unwrap();
    assert_eq!(s.pass_outcome(&other, Pass::Shoot, 0), PassOutcome::Cancelled);
    assert!(
        !s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap(),
        "a cancelled job's lease is void"
    );
    assert_eq!(s.lease(&w, Duration::ZERO).await.unwrap(), None);
    assert!(matches!(s.cancel(&JobId::generate()), Err(Unknown::Job(_))));
}

#[tokio::test]
async fn status_sequence_increases_with_every_change() {
    let s = scheduler(60_000);
    let id = job(&s);
    let mut rx = s.subscribe(&id).unwrap();
    let first = rx.borrow_and_update().seq;
    s.start_pass(&id, 0, Pass::Shoot, 1, &[], &[]);
    let w = s.register("a", Abilities::ALL);
    let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap();
    let last = rx.borrow_and_update().clone();
    assert!(last.seq > first + 2, "{} after {first}", last.seq);
    assert_eq!(last.batches_done, 1);
    assert_eq!(last.batches_total, 3);
}

#[tokio::test]
async fn an_iteration_records_what_its_workers_computed_and_publishes_it() {
    let s = scheduler(60_000);
    let id = job(&s);
    assert_eq!(s.status(&id).unwrap().last_iteration, None, "none before the first");
    s.start_pass(&id, 0, Pass::Areas { copy: 0 }, 3, &[], &[]);
    let (a, b) = (s.register("a", Abilities::ALL), s.register("b", Abilities::ALL));
    let first = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    let second = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    let third = s.lease(&a, Duration::ZERO).await.unwrap().unwrap();
    assert!(s.report(&a, &first.lease_id, Ok(()), 0.25).unwrap());
    // A failure is not work done, and a report of a lease that is gone is not taken.
    assert!(s.report(&b, &second.lease_id, Err("disk full".into()), 5.0).unwrap());
    assert!(!s.report(&b, &second.lease_id, Ok(()), 7.0).unwrap());
    let again = s.lease(&b, Duration::ZERO).await.unwrap().unwrap();
    assert!(s.report(&b, &again.lease_id, Ok(()), 0.5).unwrap());
    assert!(s.report(&a, &third.lease_id, Ok(()), 0.125).unwrap());
    s.end_iteration(&id, WorkTraffic::default());
    let records = s.iterations(&id).unwrap();
    assert_eq!(records.len(), 1);
    let used = records[0].workers;
    assert_eq!((used.workers, used.busy_seconds), (2, 0.875));
    assert!(used.span_seconds <= used.seconds && used.seconds == records[0].seconds);
    assert_eq!(s.status(&id).unwrap().last_iteration, Some(used.to_wire()));
    // The next iteration starts counting afresh.
    s.start_iteration(&id, 1, 1, 40);
    s.end_iteration(&id, WorkTraffic::default());
    let next = s.iterations(&id).unwrap()[1].workers;
    assert_eq!((next.workers, next.busy_seconds, next.span_seconds), (0, 0.0, 0.0));
}

/// An iteration's record runs from the end of the one before, so that what the driver does
/// between the two (opening the next passes, starting the commit) is in the records: a pause
/// between `end_iteration` and the next `start_iteration` is counted in the second iteration.
#[tokio::test]
async fn iteration_records_run_from_the_last_release() {
    let s = scheduler(60_000);
    let id = job(&s);
    s.end_iteration(&id, WorkTraffic::default());
    let pause = Duration::from_millis(30);
    std::thread::sleep(pause);
    s.start_iteration(&id, 1, 3, 40);
    s.end_iteration(&id, WorkTraffic::default());
    let records = s.iterations(&id).unwrap();
    assert_eq!(records.len(), 2);
    assert!(records[1].seconds >= pause.as_secs_f64(), "{:?}", records[1].seconds);
}

/// A restarted coordinator (a new scheduler) gives ids its predecessor never gave: a worker
/// of the last one that reports its old lease, or claims its rest, is told the lease is gone,
/// though the new one has handed out as many leases to a worker of the same name.
#[tokio::test]
async fn a_restarted_coordinator_never_gives_an_id_its_predecessor_gave() {
    let (before, after) = (scheduler(60_000), scheduler(60_000));
    let (job_before, job_after) = (job(&before), job(&after));
    before.start_pass(&job_before, 0, Pass::Shoot, 4, &[], &[]);
    after.start_pass(&job_after, 0, Pass::Shoot, 4, &[], &[]);
    let (old, new) = (
        before.register("host", Abilities::ALL),
        after.register("host", Abilities::ALL),
    );
    assert_ne!(old, new, "one host's workers of the two coordinators");
    let stale = before.lease(&old, Duration::ZERO).await.unwrap().unwrap();
    let fresh = after.lease(&new, Duration::ZERO).await.unwrap().unwrap();
    assert_ne!(stale.lease_id, fresh.lease_id);
    // The old worker reports its old lease under its old id: unknown here (without the
    // coordinators' marks both ids were the same, and the report marked the new worker's batch
    // done).
    assert!(matches!(
        after.report(&old, &stale.lease_id, Ok(()), 0.01),
        Err(Unknown::Worker(_))
    ));
    // It re-registers, under another id, and reports again.
    let again = after.register("host", Abilities::ALL);
    assert_eq!(after.extend(&again, &stale.lease_id).unwrap(), None);
    assert!(!after.report(&again, &stale.lease_id, Ok(()), 0.01).unwrap());
    assert_eq!(after.pass_outcome(&job_after, Pass::Shoot, 0), PassOutcome::Running);
}

/// A job that ends through its driver (failed, finished) takes its leases with it: a worker
/// claiming the rest of one is told it is gone, and its report is ignored.
#[tokio::test]
async fn a_job_that_ends_takes_its_leases_with_it() {
    let s = scheduler(60_000);
    let id = job(&s);
    s.start_pass(&id, 0, Pass::Shoot, 4, &[], &[]);
    let w = s.register("a", Abilities::ALL);
    let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
    assert!(s.extend(&w, &g.lease_id).unwrap().is_some());
    s.update(&id, |status| status.state = WireState::Failed as i32);
    assert_eq!(s.extend(&w, &g.lease_id).unwrap(), None, "gone with its job");
    assert!(!s.report(&w, &g.lease_id, Ok(()), 0.01).unwrap());
}

/// A batch whose leases all expire unreported (every worker hangs on it, or dies of it) fails
/// its job after [`MAX_BATCH_EXPIRIES`] leases, with the reason, rather than being leased again
/// for ever; fewer leave it running.
#[tokio::test]
async fn a_batch_that_no_worker_ever_reports_fails_its_job() {
    let s = scheduler(1);
    let id = job(&s);
    s.start_pass(&id, 0, Pass::Shoot, 1, &[], &[]);
    let w = s.register("hangs", Abilities::ALL);
    for lease in 1..=MAX_BATCH_EXPIRIES {
        let g = s.lease(&w, Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(g.batches, 0..1);
        tokio::time::sleep(Duration::from_millis(5)).await;
        assert_eq!(s.reap(), 1);
        let outcome = s.pass_outcome(&id, Pass::Shoot, 0);
        if lease < MAX_BATCH_EXPIRIES {
            assert_eq!(outcome, PassOutcome::Running, "after {lease} expiries");
        } else {
            assert!(
                matches!(&outcome, PassOutcome::Failed(m) if m.contains("never reported")),
                "{outcome:?}"
            );
        }
    }
    assert_eq!(
        s.lease(&w, Duration::ZERO).await.unwrap(),
        None,
        "a failed job leases nothing"
    );
}
