//! Setting a job up, between its submission and its first iteration: its survey (a walk over
//! every ray of every subfield, the part of set-up that grows with the field) leased to the
//! workers as the parts of `Pass::Survey` where they can learn it, else learnt here; then its
//! geometry and snapshot 0, on a blocking thread, one job at a time ([`set_up`]). A job that
//! cannot be set up fails with the reason; one cancelled meanwhile is recorded cancelled.

use super::{Origin, drive, stored_status};
use crate::scheduler::{PassOutcome, Scheduler};
use std::sync::Arc;
use tokio::sync::Notify;
use vlf_core::propagate::{Batching, Pass, Propagation, Survey, SurveyPart, SurveyParts};
use vlf_core::psf::Subfield;
use vlf_core::scene::Scene;
use vlf_proto::v1::State as WireState;
use vlf_store::{Coordinator, FieldJob, JobState, StoreError};

/// What a job's status says while it is being set up.
pub(super) const SETTING_UP: &str = "setting up";

/// One job is set up at a time: a set-up takes every thread of the coordinator (and, for a
/// large scan, hundreds of megabytes), and submitting no longer waits for it, so a script that
/// submits many jobs would otherwise start them all at once.
pub(super) static SET_UPS: tokio::sync::Semaphore = tokio::sync::Semaphore::const_new(1);

/// How setting a job up ended.
enum SetUp {
    Done(Box<Coordinator>),
    /// The job cannot be set up (the scene and options make no propagation, a survey block
    /// failed too often, a stored part cannot be read): the job fails, for this reason.
    Failed(String),
    /// The store failed (perhaps for a moment): the job stays queued in the store, and the next
    /// coordinator to take the store up sets it up again.
    Store(String),
    Cancelled,
}

/// Registers `job`, submitted but not set up yet, with the scheduler, and sets it up
/// ([`set_up`]): then drives it. A job that cannot be set up fails, with the reason in its status
/// and in the store; a job cancelled meanwhile is recorded cancelled, set up or not.
pub(super) fn set_up_and_start(sched: &Arc<Scheduler>, job: FieldJob, origin: Origin) {
    let mut status = stored_status(&job);
    status.message = SETTING_UP.into();
    let id = job.id().clone();
    let wake = match sched.add_job(status) {
        Ok(wake) => wake,
        Err(e) => {
            tracing::error!("cannot schedule job {id}: {e}");
            return;
        }
    };
    let sched = sched.clone();
    tokio::spawn(async move {
        let started = std::time::Instant::now();
        let (state, message) = match set_up(&sched, job, &wake, origin).await {
            SetUp::Done(coordinator) => {
                tracing::info!(job = %id, seconds = format!("{:.2}", started.elapsed().as_secs_f64()), "job set up");
                sched.update(&id, |s| s.message.clear());
                drive(&sched, *coordinator, wake, origin);
                return;
            }
            SetUp::Cancelled => (WireState::Cancelled, String::new()),
            SetUp::Failed(message) => (WireState::Failed, message),
            SetUp::Store(message) => (
                WireState::Failed,
                format!(
                    "{message} (the job stays queued in the store: a coordinator taking the store up sets it up again)"
                ),
            ),
        };
        tracing::warn!(job = %id, ?state, "{message}");
        sched.update(&id, |s| {
            s.state = state as i32;
            s.message = message;
        });
    });
}

/// Sets `job` up: learns its survey, then builds its geometry, stores the survey and writes
/// snapshot 0 ([`FieldJob::set_up`]) on a blocking thread, one job at a time. How it ended is
/// recorded in the store where the job ends (failed, cancelled).
///
/// The survey — a walk over every ray of every subfield, the part of set-up that grows with the
/// field — is leased to the workers as the parts of [`Pass::Survey`] ([`learn_survey`]) when
/// one that learns surveys is alive, or when a previous coordinator's workers stored parts of
/// it; it is learnt here, with all the coordinator's threads, when none is (a job submitted
/// before its workers start, workers of an earlier build) or when workers in this process share
/// the coordinator's propagation (they take it whole, survey included). The same bits either way.
async fn set_up(sched: &Arc<Scheduler>, job: FieldJob, wake: &Notify, origin: Origin) -> SetUp {
    let id = job.id().clone();
    let cancelled = {
        let (sched, id) = (sched.clone(), id.clone());
        move || sched.is_cancelled(&id)
    };
    let budget = set_up_budget(sched.subfield_budget(), sched.prototypes().is_some(), job.scene());
    let job = Arc::new(job);
    // Parts a previous coordinator's workers stored.
    let stored = match origin {
        Origin::Recovered if sched.prototypes().is_none() => {
            let job = job.clone();
            match vlf_store::blocking(move || job.stored_blocks(0, Pass::Survey)).await {
                Ok(Ok(stored)) => stored,
                Ok(Err(e)) => return SetUp::Store(format!("cannot list the survey's parts: {e}")),
                Err(e) => return SetUp::Store(format!("internal: {e}")),
            }
        }
        _ => Vec::new(),
    };
    let leased = sched.prototypes().is_none() && (sched.surveyors_alive() > 0 || !stored.is_empty());
    let learnt = match leased {
        true => learn_survey(sched, &job, wake, &stored, budget).await.map(Some),
        false => Ok(None),
    };
    // Every blocking step that held the job is over: this is the only holder left.
    let job = Arc::try_unwrap(job).unwrap_or_else(|shared| (*shared).clone());
    let survey = match learnt {
        Ok(survey) => survey,
        Err(outcome @ (SetUp::Cancelled | SetUp::Failed(_))) => return ended(job, outcome).await,
        Err(outcome) => return outcome,
    };
    let _turn = SET_UPS.acquire().await;
    let mut job = job;
    vlf_store::blocking(move || -> SetUp {
        if cancelled() {
            return record_end(&mut job, SetUp::Cancelled);
        }
        let (scene, options) = (job.scene().clone(), job.options().clone());
        let built = match survey {
            // The mirror views are cut from the planes the workers learnt with the survey; planes
            // that do not fit the job (a worker of another build) are set aside, and the views
            // rasterised here instead, rather than failing the job.
            Some((survey, planes)) => {
                let cut =
                    Propagation::with_survey_and_planes(scene.clone(), options.clone(), budget, survey.clone(), planes);
                match cut {
                    Err(e @ vlf_core::Error::Decode(_)) => {
                        tracing::warn!(job = %job.id(), "rasterising the mirror views here: {e}");
                        Propagation::with_survey(scene, options, budget, survey)
                    }
                    cut => cut,
                }
            }
            None => Propagation::with_subfield_budget(scene, options, budget),
        };
        let prop = match built {
            Ok(prop) => prop,
            Err(e) => return record_end(&mut job, SetUp::Failed(format!("cannot set the job up: {e}"))),
        };
        if let Err(e) = job.set_up(&prop) {
            return SetUp::Store(format!("cannot set the job up: {e}"));
        }
        if cancelled() {
            return record_end(&mut job, SetUp::Cancelled);
        }
        SetUp::Done(Box::new(Coordinator::new(job, prop)))
    })
    .await
    .unwrap_or_else(|e| SetUp::Store(format!("internal: {e}")))
}

/// Records in the store that `job` ended set-up as `outcome` says (it is not taken up again), and
/// returns `outcome`; a store that fails leaves the job queued ([`SetUp::Store`]). Only a
/// cancelled or failed set-up ends the job; any other outcome is returned as it is.
fn record_end(job: &mut FieldJob, outcome: SetUp) -> SetUp {
    let state = match &outcome {
        SetUp::Cancelled => JobState::Cancelled,
        SetUp::Failed(message) => JobState::Failed {
            message: message.clone(),
        },
        SetUp::Done(_) | SetUp::Store(_) => return outcome,
    };
    match job.set_state(state) {
        Ok(()) => outcome,
        Err(e) => SetUp::Store(format!("recording the job's end failed: {e}")),
    }
}

/// [`record_end`] on a blocking thread.
async fn ended(mut job: FieldJob, outcome: SetUp) -> SetUp {
    vlf_store::blocking(move || record_end(&mut job, outcome))
        .await
        .unwrap_or_else(|e| SetUp::Store(format!("internal: {e}")))
}

/// Learns `job`'s survey through its workers: opens [`Pass::Survey`] over the job's batches
/// (the blocks `stored` by a previous coordinator's workers are used as they are) and adds up
/// the parts in order as their blocks are reported ([`SurveyParts`]), while the later ones are
/// still being learnt. The coordinator closes the pass and learns the rest itself, within
/// `budget` and in its turn to set jobs up ([`SET_UPS`]), when no worker that learns surveys
/// is left (none heard from for six heartbeats: three to count one dead, three more of grace —
/// the one that had the pass died, or none came back after a coordinator restart), or when a
/// stored part cannot be read or does not fit (a corrupted blob, one of another build). Returns
/// the survey with every direction's mirror planes ([`SurveyParts::finish_with_planes`]), or why
/// there is none: cancelled, failed ([`SetUp::Failed`]: a block failed too
/// often, the rest cannot be learnt here either), or the store failed.
async fn learn_survey(
    sched: &Arc<Scheduler>,
    job: &Arc<FieldJob>,
    wake: &Notify,
    stored: &[std::ops::Range<usize>],
    budget: Option<usize>,
) -> Result<(Survey, Vec<Subfield>), SetUp> {
    let id = job.id().clone();
    let batching = job.options().batching();
    let batches = batching.count();
    let started = std::time::Instant::now();
    sched.start_iteration(&id, 1, batches, job.options().directions);
    sched.start_pass(&id, 0, Pass::Survey, batches, stored, &[]);
    let grace = sched.timing().heartbeat * 3;
    // Since when no worker that learns surveys is alive.
    let mut unattended: Option<std::time::Instant> = None;
    let mut parts = SurveyParts::new(job.scene(), job.options());
    let mut next = 0;
    let mut by_workers = 0;
    'leased: while next < batches {
        let ready = loop {
            let notified = wake.notified();
            match sched.pass_outcome(&id, Pass::Survey, next) {
                PassOutcome::Running => {
                    if sched.surveyors_alive() > 0 {
                        unattended = None;
                    } else if unattended.get_or_insert_with(std::time::Instant::now).elapsed() >= grace {
                        tracing::warn!(job = %id, from_batch = next, "no worker learns surveys: learning the rest here");
                        break 'leased;
                    }
                    tokio::select! {
                        _ = notified => {}
                        _ = tokio::time::sleep(grace / 4) => {}
                    }
                }
                PassOutcome::Ready(blocks) => break blocks,
                PassOutcome::Cancelled => return Err(SetUp::Cancelled),
                PassOutcome::Failed(m) => return Err(SetUp::Failed(format!("cannot learn the survey: {m}"))),
            }
        };
        let ready = read_at_once(&ready, &batching);
        let read = {
            let (job, ready) = (job.clone(), ready.to_vec());
            vlf_store::blocking(move || job.survey_parts(&ready))
                .await
                .map_err(|e| SetUp::Store(format!("internal: {e}")))?
        };
        let read = match read {
            Ok(read) => read,
            // Not there, or not a part of this job: learnt again, here.
            Err(e @ (StoreError::NotFound { .. } | StoreError::Blob { .. } | StoreError::Field { .. })) => {
                tracing::warn!(job = %id, from_batch = next, "learning the rest of the survey here: {e}");
                break;
            }
            Err(e) => return Err(SetUp::Store(format!("cannot read the survey: {e}"))),
        };
        for (block, part) in ready.iter().zip(read) {
            if let Err(e) = parts.add(part) {
                tracing::warn!(job = %id, from_batch = next, "learning the rest of the survey here: {e}");
                break 'leased;
            }
            (next, by_workers) = (block.end, by_workers + 1);
        }
    }
    sched.end_pass(&id, 0, Pass::Survey);
    if next < batches {
        // No batch is leased any more: the status drops the survey's progress.
        sched.start_iteration(&id, 0, batches, job.options().directions);
        let _turn = SET_UPS.acquire().await;
        let (job, rest) = (job.clone(), batching.directions_of(next..batches));
        let part = vlf_store::blocking(move || SurveyPart::learn(job.scene(), job.options(), rest, budget))
            .await
            .map_err(|e| SetUp::Store(format!("internal: {e}")))?
            .map_err(|e| SetUp::Failed(format!("cannot set the job up: {e}")))?;
        parts
            .add(part)
            .map_err(|e| SetUp::Failed(format!("cannot add up the survey: {e}")))?;
    }
    let learnt = parts
        .finish_with_planes(job.scene())
        .map_err(|e| SetUp::Failed(format!("cannot add up the survey: {e}")))?;
    tracing::info!(
        job = %id,
        seconds = format!("{:.2}", started.elapsed().as_secs_f64()),
        blocks = by_workers,
        stored_before = stored.len(),
        learnt_here = batches - next.min(batches),
        "survey learnt by the workers"
    );
    Ok(learnt)
}

/// The most survey parts, and the most directions of them, that the coordinator reads and holds
/// at once ([`read_at_once`]).
pub(super) const PARTS_AT_ONCE: usize = 8;
pub(super) const DIRECTIONS_AT_ONCE: usize = 256;

/// The first of the parts `ready` (in order) that the coordinator reads at once: at most
/// [`PARTS_AT_ONCE`] parts of at most [`DIRECTIONS_AT_ONCE`] directions, and at least one part.
/// Parts come in as workers finish them, a few at a time; but a coordinator that takes over a
/// job finds every part its predecessor's workers stored ready at once. Each part holds a
/// 16-byte area count per texel of the scene (megabytes for a scan), and with mirror planes
/// tens of kB a direction (the mirror dragon's at l = 2049: about 100 MB of tables in all).
/// Read in one go, every stored blob and every decoded part would be held at once; read in
/// steps, only a step's are, each part's planes moving into the sum as it is added.
pub(super) fn read_at_once<'a>(
    ready: &'a [std::ops::Range<usize>],
    batching: &Batching,
) -> &'a [std::ops::Range<usize>] {
    let mut directions = 0;
    let taken = (ready.iter().take(PARTS_AT_ONCE))
        .take_while(|block| {
            directions += batching.directions_of((*block).clone()).len();
            directions <= DIRECTIONS_AT_ONCE
        })
        .count();
    &ready[..taken.max(1).min(ready.len())]
}

/// The subfield budget a new job is set up within: the configured one; else, for a scene without
/// mirrors whose propagation no worker of this process shares, none kept at all. Such a
/// coordinator builds each subfield once to learn the job's survey and, never shooting, reads
/// none after, so it need never hold them all (at l = 8193, N = 256 the Cornell box's are
/// 696 MB): at most one per thread is alive. The same bits: a subfield is a pure function of
/// the job. With mirrors, learning the survey reads each subfield twice (the discrete areas, the
/// surfaces facing each other), so they are held while it does; the workers of this process
/// take the propagation whole, so those keep them. Either way a coordinator lets them go once
/// the job is set up ([`Propagation::release_subfields`]).
pub(super) fn set_up_budget(configured: Option<usize>, shared: bool, scene: &Scene) -> Option<usize> {
    let mirrors = (0..scene.surfaces.len()).any(|s| scene.material(s).is_mirror());
    match configured {
        None if !shared && !mirrors => Some(0),
        budget => budget,
    }
}
