use super::set_up::{DIRECTIONS_AT_ONCE, PARTS_AT_ONCE, SET_UPS, SETTING_UP, read_at_once, set_up_budget};
use super::submit;
use crate::scheduler::{Abilities, Scheduler, Timing};
use std::time::{Duration, Instant};
use vlf_core::propagate::{Batching, Pass, Propagation, SurveyPart, Surveyor, reduce};
use vlf_core::scene::{ImportOptions, Scene, load_obj};
use vlf_proto::JobSpec;
use vlf_proto::v1::{self, State as WireState};
use vlf_store::{FieldJob, JobId, JobState, Store};

fn bundled(name: &str) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name);
    load_obj(&path, &ImportOptions::default()).expect("bundled scene").0
}

#[test]
fn a_standalone_coordinator_of_a_diffuse_scene_keeps_no_subfield() {
    let (cornell, mirrors) = (bundled("cornell.obj"), bundled("mirrors.obj"));
    assert_eq!(set_up_budget(None, false, &cornell), Some(0));
    // Its workers in this process take the propagation whole; learning a mirror scene's
    // survey reads each subfield twice.
    assert_eq!(set_up_budget(None, true, &cornell), None);
    assert_eq!(set_up_budget(None, false, &mirrors), None);
    // A configured budget is the operator's.
    assert_eq!(set_up_budget(Some(1 << 20), false, &cornell), Some(1 << 20));
    assert_eq!(set_up_budget(Some(1 << 20), true, &mirrors), Some(1 << 20));
}

/// A coordinator reads stored survey parts in steps of at most `PARTS_AT_ONCE` parts and
/// `DIRECTIONS_AT_ONCE` directions, at least one part a step, in order.
#[test]
fn survey_parts_are_read_a_few_at_a_time() {
    // l = 8193 in 64 batches of 128 directions.
    let batching = Batching::new(8193, 64, 8);
    assert_eq!(batching.size(), 128);
    let one_each: Vec<_> = (0..64).map(|b| b..b + 1).collect();
    let step = read_at_once(&one_each, &batching);
    assert_eq!(step, &one_each[..DIRECTIONS_AT_ONCE / 128]);
    // A part larger than a step is read alone.
    let whole = vec![0..32, 32..64];
    assert_eq!(read_at_once(&whole, &batching), &whole[..1]);
    // Small parts: at most PARTS_AT_ONCE of them (l = 513, 32 batches of 16 directions:
    // more than PARTS_AT_ONCE of them would still be within DIRECTIONS_AT_ONCE).
    let small = Batching::new(513, 64, 8);
    let ready: Vec<_> = (0..small.count()).map(|b| b..b + 1).collect();
    assert!(ready.len() > PARTS_AT_ONCE && (PARTS_AT_ONCE + 1) * small.size() <= DIRECTIONS_AT_ONCE);
    let step = read_at_once(&ready, &small);
    assert_eq!(step, &ready[..PARTS_AT_ONCE]);
    // Stepping through reads every part once, in order, each step within the bounds.
    let mut next = 0;
    let mut steps = 0;
    while next < one_each.len() {
        let step = read_at_once(&one_each[next..], &batching);
        let directions: usize = step.iter().map(|b| batching.directions_of(b.clone()).len()).sum();
        assert!(!step.is_empty() && step.len() <= PARTS_AT_ONCE && directions <= DIRECTIONS_AT_ONCE);
        assert_eq!(step[0].start, next);
        next = step.last().unwrap().end;
        steps += 1;
    }
    // Two parts a step, but for the last batch's 129 directions (l = 64 · 128 + 1), which
    // would take the last step past 256: it is read alone.
    assert_eq!(DIRECTIONS_AT_ONCE, 256);
    assert_eq!(steps, 31 + 2);
}

/// A job cancelled while it waits for its turn to be set up is recorded cancelled in the
/// store, not set up and not driven: a coordinator taking the store up leaves it be.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_cancelled_before_it_is_set_up_is_recorded_cancelled() {
    let store = Store::open("memory://").unwrap();
    let sched = Scheduler::new(store.clone(), Timing::default(), None, None);
    // Another job is being set up: this one waits its turn.
    let turn = SET_UPS.acquire().await.unwrap();
    let parameters = v1::Parameters {
        directions: Some(33),
        resolution: Some(16),
        iterations: Some(1),
        ..Default::default()
    };
    let spec = JobSpec::from_parameters(&parameters).unwrap();
    let status = submit(&sched, bundled("cornell.obj"), spec).await.unwrap();
    assert_eq!(
        (status.state, status.message.as_str()),
        (WireState::Queued as i32, SETTING_UP)
    );
    let id = JobId::parse(&status.job_id).unwrap();
    sched.cancel(&id).unwrap();
    drop(turn);
    let deadline = Instant::now() + Duration::from_secs(30);
    while sched.status(&id).unwrap().state != WireState::Cancelled as i32 {
        assert!(Instant::now() < deadline, "{:?}", sched.status(&id));
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let job = vlf_store::blocking(move || FieldJob::open(&store, &id).unwrap())
        .await
        .unwrap();
    assert_eq!(job.job().manifest().state, JobState::Cancelled);
    assert!(!job.is_set_up());
}

/// What [`a_job_surveyed_by`] returns: the store, the scheduler, the worker, the job, its
/// spec and the worker's lease.
type SurveyedJob = (
    Store,
    std::sync::Arc<Scheduler>,
    String,
    JobId,
    JobSpec,
    crate::scheduler::Grant,
);

/// A scheduler over a `memory://` store with `timing`, one worker that learns surveys, and
/// a job of `scene` (l = 129: 8 batches) submitted after it registered; returns them with
/// the worker's first lease, a block of the survey.
async fn a_job_surveyed_by(timing: Timing, scene: &str) -> SurveyedJob {
    let store = Store::open("memory://").unwrap();
    let sched = Scheduler::new(store.clone(), timing, None, None);
    let worker = sched.register("surveyor", Abilities::ALL);
    let parameters = v1::Parameters {
        directions: Some(129),
        resolution: Some(16),
        iterations: Some(1),
        ..Default::default()
    };
    let spec = JobSpec::from_parameters(&parameters).unwrap();
    let status = submit(&sched, bundled(scene), spec.clone()).await.unwrap();
    let id = JobId::parse(&status.job_id).unwrap();
    let grant = sched.lease(&worker, Duration::from_secs(30)).await.unwrap().unwrap();
    assert_eq!(grant.pass, Pass::Survey);
    assert!(
        grant.batches.end < spec.options.batching().count(),
        "a part of the survey: {grant:?}"
    );
    (store, sched, worker, id, spec, grant)
}

/// Waits until the job is set up (it then waits for a worker to propagate it), heartbeating
/// for `alive` meanwhile if given, and checks that it was set up with the survey a
/// propagation of `scene` learns whole.
async fn set_up_with_the_whole_survey(
    (store, sched, id): (Store, &Scheduler, JobId),
    scene: &str,
    spec: &JobSpec,
    alive: Option<&str>,
) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while sched.status(&id).unwrap().state != WireState::Propagating as i32 {
        let status = sched.status(&id).unwrap();
        assert!(status.state != WireState::Failed as i32, "{status:?}");
        assert!(Instant::now() < deadline, "{status:?}");
        if let Some(worker) = alive {
            sched.heartbeat(worker).unwrap();
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let whole = Propagation::new(bundled(scene), spec.options.clone()).unwrap();
    let (survey, mirrors) = vlf_store::blocking(move || {
        let job = FieldJob::open(&store, &id).unwrap();
        let mirrors = job.stored_mirror_geometry().unwrap().map(|g| g.to_bytes());
        (job.stored_survey().unwrap(), mirrors)
    })
    .await
    .unwrap();
    assert!(survey == Some(whole.survey()), "the survey stored with the job");
    // With mirrors, the views cut from the planes the parts learnt, and the routes found
    // from them, are those of the whole propagation.
    assert!(
        mirrors == whole.mirror_geometry(),
        "the mirror geometry stored with the job"
    );
}

/// The surveying worker of [`a_job_surveyed_by`] learns the parts of its lease `grant` into
/// the store, each passed through `alter` first, reports the lease done and falls silent;
/// the job is then set up, and checked to be set up with the whole survey.
async fn learnt_then_silent((store, sched, worker, id, spec, grant): SurveyedJob, alter: fn(&mut SurveyPart)) {
    let learnt = {
        let (store, id, run) = (store.clone(), id.clone(), grant.batches.clone());
        vlf_store::blocking(move || {
            let job = FieldJob::open(&store, &id).unwrap();
            let surveyor = Surveyor::new(job.scene(), job.options(), None).unwrap();
            for block in reduce::cover(run) {
                let mut part = surveyor
                    .part(job.options().batching().directions_of(block.clone()))
                    .unwrap();
                alter(&mut part);
                job.put_survey_part(block, &part).unwrap();
            }
        })
    };
    learnt.await.unwrap();
    let reported = sched.report_run(&worker, &grant.lease_id, Ok(()), 0.01, None, &[]);
    assert!(reported.unwrap());
    // The worker is silent from now on: the coordinator learns the rest of the survey.
    set_up_with_the_whole_survey((store, &sched, id), "mirrors.obj", &spec, None).await;
}

/// A timing in which a silent worker is soon given up.
fn short_heartbeat() -> Timing {
    Timing {
        heartbeat: Duration::from_millis(100),
        ..Timing::default()
    }
}

/// A worker learns the first block of a job's survey and dies: the coordinator, with no
/// worker left that learns surveys, learns the rest itself, and the job is set up with the
/// survey a propagation learns whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_survey_whose_worker_dies_is_finished_by_the_coordinator() {
    let surveyed = a_job_surveyed_by(short_heartbeat(), "mirrors.obj").await;
    learnt_then_silent(surveyed, |_| {}).await;
}

/// A worker of another build learns planes that do not fit the job (here, two directions'
/// planes swapped): the coordinator sets them aside and rasterises the mirror views itself,
/// and the job is set up with the survey and mirror geometry a propagation finds whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mirror_planes_that_do_not_fit_are_set_aside() {
    let surveyed = a_job_surveyed_by(short_heartbeat(), "mirrors.obj").await;
    learnt_then_silent(surveyed, |part| {
        assert!(part.mirror_planes.len() >= 2);
        part.mirror_planes.swap(0, 1);
    })
    .await;
}

/// A stored part that cannot be read (here, garbage under its key) does not fail the job:
/// the coordinator learns the rest of the survey itself, and the job is set up with the
/// survey a propagation learns whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_survey_part_that_cannot_be_read_is_learnt_again_by_the_coordinator() {
    let (store, sched, worker, id, spec, grant) = a_job_surveyed_by(Timing::default(), "cornell.obj").await;
    assert_eq!(grant.batches, 0..1);
    let key = vlf_store::layout::work_block(&id, 0, "survey", 0, 1).unwrap();
    let garbage = store.clone();
    vlf_store::blocking(move || garbage.put(&key, b"not a survey part".to_vec()).unwrap())
        .await
        .unwrap();
    let reported = sched.report_run(&worker, &grant.lease_id, Ok(()), 0.01, None, &[]);
    assert!(reported.unwrap());
    // The worker stays alive: the coordinator does not wait for it to die.
    set_up_with_the_whole_survey((store, &sched, id), "cornell.obj", &spec, Some(&worker)).await;
}
