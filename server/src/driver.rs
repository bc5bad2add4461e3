//! One task per job: it walks the job's iterations and passes, opening each pass for leasing as
//! soon as its prerequisites are absorbed, absorbing every block from the store in order as soon
//! as it is reported, and committing a snapshot after every iteration —
//! [`vlf_store::Coordinator`]'s protocol, with the blocks computed by remote workers instead of
//! local threads.
//!
//! A coordinator that restarts calls [`recover`]: every job of the store that was queued or
//! propagating is resumed from its last finished snapshot (`Coordinator::resume`), and blocks
//! of the interrupted iteration that workers had already written are used as they are (a block's
//! output is a pure function of the job and the block, so they are the same bytes a new
//! computation would write).

use crate::scheduler::{PassOutcome, Scheduler};
use std::sync::Arc;
use tokio::sync::Notify;
use vlf_core::propagate::{Batching, Pass, Propagation, Survey, SurveyPart, SurveyParts};
use vlf_core::psf::Subfield;
use vlf_core::scene::Scene;
use vlf_proto::JobSpec;
use vlf_proto::v1::{JobStatus, State as WireState};
use vlf_store::{Coordinator, FieldJob, Job, JobId, JobState, Stage, Store, StoreError, WorkTraffic};

/// Why a job could not be created.
#[derive(Debug, thiserror::Error)]
pub enum SubmitError {
    /// The scene and parameters do not make a propagation (the library's message).
    #[error("{0}")]
    Invalid(vlf_core::Error),
    /// The store refused the job.
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("internal error: {0}")]
    Internal(String),
}

/// Creates a job for `scene` with `spec` in the scheduler's store and starts setting it up and
/// driving it. Returns its first status at once: queued, "setting up". Setting a job up (its
/// geometry, its survey, snapshot 0: [`set_up_and_start`]) takes minutes for a large scan at the
/// big settings, longer than a client, or a proxy between, should wait for an answer; what can
/// be checked at once (the scene as parsed, the parameters) is refused here, what only setting
/// up finds (emitters no ray hits) fails the job, with the library's message.
pub async fn submit(sched: &Arc<Scheduler>, scene: Scene, spec: JobSpec) -> Result<JobStatus, SubmitError> {
    spec.options.validate().map_err(SubmitError::Invalid)?;
    let store = sched.store().clone();
    let job = vlf_store::blocking(move || -> Result<_, SubmitError> {
        let mut job = FieldJob::describe(&store, &scene, &spec.options, spec.encoding)?;
        if spec.resample {
            job.set_resample(true)?;
        }
        if !spec.keep_checkpoints {
            job.set_compact(true)?;
        }
        Ok(job)
    })
    .await
    .map_err(|e| SubmitError::Internal(e.to_string()))??;
    let id = job.id().clone();
    tracing::info!(job = %id, "job submitted");
    set_up_and_start(sched, job, Origin::Submitted);
    sched.status(&id).map_err(|e| SubmitError::Internal(e.to_string()))
}

/// What a job's status says while it is being set up.
const SETTING_UP: &str = "setting up";

/// One job is set up at a time: a set-up takes every thread of the coordinator (and, for a
/// large scan, hundreds of megabytes), and submitting no longer waits for it, so a script that
/// submits many jobs would otherwise start them all at once.
static SET_UPS: tokio::sync::Semaphore = tokio::sync::Semaphore::const_new(1);

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
fn set_up_and_start(sched: &Arc<Scheduler>, job: FieldJob, origin: Origin) {
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
const PARTS_AT_ONCE: usize = 8;
const DIRECTIONS_AT_ONCE: usize = 256;

/// The first of the parts `ready` (in order) that the coordinator reads at once: at most
/// [`PARTS_AT_ONCE`] parts of at most [`DIRECTIONS_AT_ONCE`] directions, and at least one part.
/// Parts come in as workers finish them, a few at a time; but a coordinator that takes over a
/// job finds every part its predecessor's workers stored ready at once. Each part holds a
/// 16-byte area count per texel of the scene (megabytes for a scan), and with mirror planes
/// tens of kB a direction (the mirror dragon's at l = 2049: about 100 MB of tables in all).
/// Read in one go, every stored blob and every decoded part would be held at once; read in
/// steps, only a step's are, each part's planes moving into the sum as it is added.
fn read_at_once<'a>(ready: &'a [std::ops::Range<usize>], batching: &Batching) -> &'a [std::ops::Range<usize>] {
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
fn set_up_budget(configured: Option<usize>, shared: bool, scene: &Scene) -> Option<usize> {
    let mirrors = (0..scene.surfaces.len()).any(|s| scene.material(s).is_mirror());
    match configured {
        None if !shared && !mirrors => Some(0),
        budget => budget,
    }
}

/// Takes up every job of the store: unfinished ones are resumed from their last snapshot and
/// driven; ended ones are listed with their final state. A job that cannot be read is listed as
/// failed with the reason, and the others go on.
pub async fn recover(sched: &Arc<Scheduler>) -> Result<usize, StoreError> {
    let store = sched.store().clone();
    let ids = vlf_store::blocking(move || Job::list(&store))
        .await
        .map_err(|e| StoreError::Layout(e.to_string()))??;
    let mut resumed = 0;
    for id in ids {
        if sched.has_job(&id) {
            continue;
        }
        let (store, budget) = (sched.store().clone(), sched.subfield_budget());
        let opened = {
            let id = id.clone();
            vlf_store::blocking(move || -> Result<Taken, StoreError> {
                let job = FieldJob::open(&store, &id)?;
                match job.job().manifest().state {
                    // Submitted to a coordinator that stopped before it was set up.
                    JobState::Queued if !job.is_set_up() => Ok(Taken::ToSetUp(job)),
                    JobState::Queued | JobState::Propagating { .. } => {
                        Ok(Taken::Resumed(Box::new(Coordinator::resume_within(job, budget)?)))
                    }
                    _ => Ok(Taken::Ended(stored_status(&job))),
                }
            })
            .await
            .map_err(|e| StoreError::Layout(e.to_string()))?
        };
        match opened {
            Ok(Taken::Resumed(coordinator)) => {
                tracing::info!(job = %id, snapshot = coordinator.iteration(), "resuming job");
                start(sched, *coordinator, Origin::Recovered);
                resumed += 1;
            }
            Ok(Taken::ToSetUp(job)) => {
                tracing::info!(job = %id, "setting up job");
                set_up_and_start(sched, job, Origin::Recovered);
                resumed += 1;
            }
            Ok(Taken::Ended(status)) => {
                let _ = sched.add_job(status);
            }
            Err(e) => {
                tracing::error!(job = %id, "cannot take up job: {e}");
                let _ = sched.add_job(JobStatus {
                    job_id: id.to_string(),
                    state: WireState::Failed as i32,
                    message: format!("the coordinator cannot read this job: {e}"),
                    ..Default::default()
                });
            }
        }
    }
    Ok(resumed)
}

/// The status of a job as its store records it (for jobs this coordinator does not drive).
pub fn stored_status(job: &FieldJob) -> JobStatus {
    let manifest = job.job().manifest();
    let (state, message, iteration) = match &manifest.state {
        JobState::Queued => (WireState::Queued, String::new(), 0),
        JobState::Propagating { iteration } => (WireState::Propagating, String::new(), *iteration),
        JobState::Finished => (WireState::Finished, String::new(), 0),
        JobState::Failed { message } => (WireState::Failed, message.clone(), 0),
        JobState::Cancelled => (WireState::Cancelled, String::new(), 0),
    };
    let summary = job.summary(job.latest_stage()).ok();
    let unshot = summary.as_ref().map_or(f64::NAN, |s| s.unshot_fraction);
    let digest = match manifest.state {
        JobState::Finished => summary.and_then(|s| s.digest).unwrap_or_default(),
        _ => String::new(),
    };
    JobStatus {
        job_id: job.id().to_string(),
        state: state as i32,
        message,
        iteration,
        iterations_planned: planned(job),
        unshot_fraction: unshot,
        snapshots: manifest.finished_iterations.clone(),
        store_url: job.job().store().url().to_string(),
        eta_iteration_seconds: -1.0,
        eta_job_seconds: -1.0,
        digest,
        ..Default::default()
    }
}

/// Opens a job of `store` that the scheduler does not drive and reads its status.
pub fn read_stored_status(store: &Store, id: &JobId) -> Result<JobStatus, StoreError> {
    Ok(stored_status(&FieldJob::open(store, id)?))
}

fn planned(job: &FieldJob) -> u32 {
    match job.options().stop {
        vlf_core::propagate::Stop::Iterations(k) => k,
        vlf_core::propagate::Stop::Converge { .. } => 0,
    }
}

/// Where a driver's job comes from.
#[derive(Clone, Copy, PartialEq)]
enum Origin {
    /// Submitted to this coordinator: nothing of its iterations is in the store yet.
    Submitted,
    /// Taken up from the store (a restarted coordinator): workers of the previous one may have
    /// written batches of the iterations after its last snapshot.
    Recovered,
}

/// What a restarted coordinator makes of a job of its store.
enum Taken {
    Resumed(Box<Coordinator>),
    ToSetUp(FieldJob),
    Ended(JobStatus),
}

/// Registers the job with the scheduler and spawns its driver.
fn start(sched: &Arc<Scheduler>, coordinator: Coordinator, origin: Origin) {
    let mut status = stored_status(coordinator.job());
    status.unshot_fraction = coordinator.propagation().unshot_fraction();
    let wake = match sched.add_job(status) {
        Ok(wake) => wake,
        Err(e) => {
            tracing::error!("cannot schedule job {}: {e}", coordinator.job().id());
            return;
        }
    };
    drive(sched, coordinator, wake, origin);
}

/// Spawns the driver of a job the scheduler knows (woken by `wake`).
fn drive(sched: &Arc<Scheduler>, coordinator: Coordinator, wake: Arc<Notify>, origin: Origin) {
    sched.update(coordinator.job().id(), |s| {
        s.unshot_fraction = coordinator.propagation().unshot_fraction();
        s.snapshots = coordinator.job().job().manifest().finished_iterations.clone();
    });
    if let Some(prototypes) = sched.prototypes() {
        prototypes.insert(coordinator.job().id().clone(), coordinator.propagation().clone());
    }
    // The prototype keeps the subfields for the workers of this process; the coordinator reads
    // none (mirror tiles are cut along the mirror views).
    let mut coordinator = coordinator;
    coordinator.release_subfields();
    let resample = coordinator.job().job().manifest().resample;
    let driver = Driver {
        sched: sched.clone(),
        wake,
        id: coordinator.job().id().clone(),
        coordinator: Some(coordinator),
        committing: None,
        origin,
    };
    tokio::spawn(driver.run(resample));
}

struct Driver {
    sched: Arc<Scheduler>,
    wake: Arc<Notify>,
    id: JobId,
    /// Out while a blocking step has it.
    coordinator: Option<Coordinator>,
    /// The last snapshot, being committed while the next iteration is computed.
    committing: Option<Committing>,
    origin: Origin,
}

/// A snapshot's commit running on a blocking thread ([`vlf_store::SnapshotCommit::commit`]).
struct Committing {
    snapshot: u32,
    task: tokio::task::JoinHandle<Result<Result<Job, StoreError>, vlf_store::Panicked>>,
}

/// How a job's drive ended early.
enum Stop {
    Cancelled,
    Failed(String),
}

impl Driver {
    async fn run(mut self, resample: bool) {
        let ended = match self.propagate().await {
            Ok(()) => self.finish(resample).await.err().map(Stop::Failed),
            Err(stop) => Some(stop),
        };
        if let Some(prototypes) = self.sched.prototypes() {
            prototypes.remove(&self.id);
        }
        let Some(stop) = ended else {
            let iterations = self.sched.iterations(&self.id).unwrap_or_default();
            let (blobs, bytes) = iterations
                .iter()
                .fold((0, 0), |(n, b), r| (n + r.traffic.blobs, b + r.traffic.bytes));
            // How the workers were used over the job (see `IterationUse`).
            let (busy, capacity, between) = iterations.iter().fold((0.0, 0.0, 0.0), |(b, c, s), r| {
                let w = &r.workers;
                (
                    b + w.busy_seconds,
                    c + f64::from(w.workers) * w.span_seconds,
                    s + w.between_seconds(),
                )
            });
            tracing::info!(
                job = %self.id,
                work_blobs = blobs,
                work_mb = format!("{:.2}", bytes as f64 / 1e6),
                workers_busy = format!("{:.0}%", 100.0 * busy / capacity.max(f64::MIN_POSITIVE)),
                between_iterations_s = format!("{between:.3}"),
                "job finished"
            );
            return;
        };
        let (state, wire, message) = match stop {
            Stop::Cancelled => (JobState::Cancelled, WireState::Cancelled, String::new()),
            Stop::Failed(message) => (
                JobState::Failed {
                    message: message.clone(),
                },
                WireState::Failed,
                message,
            ),
        };
        tracing::warn!(job = %self.id, ?state, "job ended");
        // A snapshot being committed is committed first (or has failed): the end is the last
        // manifest write.
        let settled = self.settle().await.err().map(|stop| match stop {
            Stop::Failed(m) => format!(" ({m})"),
            Stop::Cancelled => String::new(),
        });
        // Record the end in the store, so a restarted coordinator does not take the job up again.
        let recorded = self.blocking(move |c| c.end(state)).await;
        let message = match recorded {
            Ok(Ok(())) => message,
            Ok(Err(e)) => format!("{message} (and recording it in the store failed: {e})"),
            Err(e) => format!("{message} ({e})"),
        } + settled.as_deref().unwrap_or("");
        self.sched.update(&self.id, |s| {
            s.state = wire as i32;
            s.message = message;
        });
    }

    /// Iterates until the job's stop rule is met.
    async fn propagate(&mut self) -> Result<(), Stop> {
        let mut driven = 0u32;
        loop {
            let c = self.coordinator.as_mut().ok_or_else(lost)?;
            if c.finished() {
                return self.settle().await;
            }
            let k = c.iteration();
            let (passes, batches) = c.passes();
            let directions = c.propagation().directions.len();
            self.sched.start_iteration(&self.id, passes.len(), batches, directions);
            self.sched.update(&self.id, |s| {
                s.state = WireState::Propagating as i32;
                s.iteration = k + 1;
            });
            // Batches a previous coordinator's workers already wrote are not computed again. It
            // can have released at most one iteration past its last commit, so only the first two
            // iterations driven here can find any, and only in a job taken up from the store (a
            // listing is a round trip to an object store).
            let stored = if driven < 2 && self.origin == Origin::Recovered {
                self.blocking(|c| c.blocks_in_store())
                    .await
                    .map_err(Stop::Failed)?
                    .map_err(|e| Stop::Failed(e.to_string()))?
            } else {
                vec![Vec::new(); passes.len()]
            };
            let mut opened = vec![false; passes.len()];
            // The passes absorbed so far, with the blocks they were absorbed as.
            let mut absorbed: Vec<(Pass, Vec<std::ops::Range<usize>>)> = Vec::new();
            // How long the last absorb took: the first thing between the workers' last report
            // and the next iteration.
            let mut last_absorb = std::time::Duration::ZERO;
            self.open_ready(k, &passes, batches, &stored, &absorbed, &mut opened);
            // The leases are out: the work the absorbs need is built while the workers compute.
            self.blocking(|c| c.prepare_work()).await.map_err(Stop::Failed)?;
            for (pass, _) in &passes {
                let pass = *pass;
                // Take each block in as soon as it is written, in order, while the rest are
                // computed.
                let mut next = 0;
                let mut blocks = Vec::new();
                while next < batches {
                    let ready = loop {
                        let notified = self.wake.notified();
                        match self.sched.pass_outcome(&self.id, pass, next) {
                            PassOutcome::Running => notified.await,
                            PassOutcome::Ready(blocks) => break blocks,
                            PassOutcome::Cancelled => return Err(Stop::Cancelled),
                            PassOutcome::Failed(m) => return Err(Stop::Failed(m)),
                        }
                    };
                    next = ready.last().map_or(next, |b| b.end);
                    blocks.extend(ready.iter().cloned());
                    let absorbing = std::time::Instant::now();
                    self.blocking(move |c| c.absorb_blocks(pass, &ready))
                        .await
                        .map_err(Stop::Failed)?
                        .map_err(|e| Stop::Failed(format!("cannot absorb {pass:?} of iteration {}: {e}", k + 1)))?;
                    last_absorb = absorbing.elapsed();
                }
                // What it opens is open before it closes: a pass waiting for them (the
                // scheduler's `opening_once_absorbed`) never finds neither.
                absorbed.push((pass, blocks));
                self.open_ready(k, &passes, batches, &stored, &absorbed, &mut opened);
                self.sched.end_pass(&self.id, k, pass);
            }
            self.check_cancelled()?;
            // Snapshots are committed in order: the last one before this one is released.
            let settling = std::time::Instant::now();
            self.settle().await?;
            let settled = settling.elapsed();
            let (_, commit, phases) = self
                .blocking(|c| {
                    c.release_iteration()
                        .map(|(stats, commit)| (stats, commit, c.take_phase_seconds()))
                })
                .await
                .map_err(Stop::Failed)?
                .map_err(|e| Stop::Failed(format!("cannot write snapshot {}: {e}", k + 1)))?;
            // The coordinator's own work, phase by phase: the last absorb, the commit's wait,
            // `finish` and `head` lie between the workers' last report and the next leases (part
            // of what `vlf bench` reports as `between`); `read` and `apply` add up every absorb.
            let ms = |seconds: f64| format!("{:.1}", seconds * 1e3);
            tracing::debug!(
                job = %self.id,
                snapshot = k + 1,
                last_absorb_ms = ms(last_absorb.as_secs_f64()),
                read_ms = ms(phases.read),
                apply_ms = ms(phases.apply),
                commit_wait_ms = ms(settled.as_secs_f64()),
                finish_ms = ms(phases.finish),
                head_ms = ms(phases.head),
                "iteration released"
            );
            let (traffic, unshot) = self
                .coordinator
                .as_ref()
                .map(|c| {
                    (
                        c.traffic().last().copied().unwrap_or_default(),
                        c.propagation().unshot_fraction(),
                    )
                })
                .unwrap_or((WorkTraffic::default(), f64::NAN));
            self.sched.end_iteration(&self.id, traffic);
            self.sched.update(&self.id, |s| s.unshot_fraction = unshot);
            // The next iteration's workers read only the shooting state, written by now: the
            // rest of the snapshot and its commit go on while they compute.
            // The snapshot is announced as soon as it is committed.
            let snapshot = commit.iteration();
            let (sched, id) = (self.sched.clone(), self.id.clone());
            self.committing = Some(Committing {
                snapshot,
                task: tokio::spawn(async move {
                    let committed = vlf_store::blocking(move || commit.commit()).await;
                    if let Ok(Ok(_)) = &committed {
                        sched.update(&id, |s| s.snapshots.push(snapshot));
                        tracing::info!(
                            job = %id,
                            snapshot,
                            work_blobs = traffic.blobs,
                            work_mb = format!("{:.2}", traffic.bytes as f64 / 1e6),
                            "iteration committed"
                        );
                    }
                    committed
                }),
            });
            driven = driven.saturating_add(1);
        }
    }

    /// Waits for the snapshot being committed, if any, and takes its manifest.
    async fn settle(&mut self) -> Result<(), Stop> {
        let Some(Committing { snapshot, task }) = self.committing.take() else {
            return Ok(());
        };
        let committed = task
            .await
            .map_err(|e| Stop::Failed(format!("internal: {e}")))?
            .map_err(|e| Stop::Failed(format!("internal: {e}")))?
            .map_err(|e| Stop::Failed(format!("cannot commit snapshot {snapshot}: {e}")))?;
        self.coordinator.as_mut().ok_or_else(lost)?.committed(committed);
        Ok(())
    }

    /// Writes the final field and marks the job finished.
    async fn finish(&mut self, resample: bool) -> Result<(), String> {
        self.check_cancelled().map_err(|_| "cancelled".to_string())?;
        let coordinator = self
            .coordinator
            .take()
            .ok_or_else(|| "internal: coordinator lost".to_string())?;
        let unshot = coordinator.propagation().unshot_fraction();
        // The digest is in the summary it just wrote (a small blob, read back).
        let digest = vlf_store::blocking(move || {
            let job = coordinator.finish(resample)?;
            Ok::<_, StoreError>(job.summary(Stage::Field)?.digest.unwrap_or_default())
        })
        .await
        .map_err(|e| format!("internal: {e}"))?
        .map_err(|e| format!("cannot write the final field: {e}"))?;
        self.sched.update(&self.id, |s| {
            s.state = WireState::Finished as i32;
            s.unshot_fraction = unshot;
            s.digest = digest;
        });
        Ok(())
    }

    /// Opens for leasing every pass of the iteration after snapshot `k` that is not open yet and
    /// whose prerequisites are all absorbed; its leases name the blocks they were absorbed as.
    fn open_ready(
        &self,
        k: u32,
        passes: &[(Pass, Vec<Pass>)],
        batches: usize,
        stored: &[Vec<std::ops::Range<usize>>],
        absorbed: &[(Pass, Vec<std::ops::Range<usize>>)],
        opened: &mut [bool],
    ) {
        for (i, (pass, needs)) in passes.iter().enumerate() {
            let reads: Option<Vec<_>> = (needs.iter())
                .map(|p| absorbed.iter().find(|(done, _)| done == p).cloned())
                .collect();
            if let Some(reads) = reads.filter(|_| !opened[i]) {
                self.sched.start_pass(&self.id, k, *pass, batches, &stored[i], &reads);
                opened[i] = true;
            }
        }
    }

    fn check_cancelled(&self) -> Result<(), Stop> {
        if self.sched.is_cancelled(&self.id) {
            Err(Stop::Cancelled)
        } else {
            Ok(())
        }
    }

    /// Runs `step` on the coordinator on a blocking thread (store I/O, absorbing).
    async fn blocking<T: Send + 'static>(
        &mut self,
        step: impl FnOnce(&mut Coordinator) -> T + Send + 'static,
    ) -> Result<T, String> {
        let mut c = self
            .coordinator
            .take()
            .ok_or_else(|| "internal: coordinator lost".to_string())?;
        let (c, out) = vlf_store::blocking(move || {
            let out = step(&mut c);
            (c, out)
        })
        .await
        .map_err(|e| format!("internal: {e}"))?;
        self.coordinator = Some(c);
        Ok(out)
    }
}

fn lost() -> Stop {
    Stop::Failed("internal: coordinator lost".into())
}

#[cfg(test)]
mod tests {
    use super::{DIRECTIONS_AT_ONCE, PARTS_AT_ONCE, SET_UPS, SETTING_UP, read_at_once, set_up_budget, submit};
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
}
