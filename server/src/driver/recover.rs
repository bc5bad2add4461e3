//! A restarted coordinator takes up the jobs of its store, and the status of jobs it does not
//! drive, as the store records them.

use super::set_up::set_up_and_start;
use super::{Origin, start};
use crate::scheduler::Scheduler;
use std::sync::Arc;
use vlf_proto::v1::{JobStatus, State as WireState};
use vlf_store::{Coordinator, FieldJob, Job, JobId, JobState, Store, StoreError};

/// Which jobs of its store a starting coordinator takes up.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum TakeUp {
    /// Every one (`vlf serve`: a restarted coordinator goes on with its jobs).
    #[default]
    Every,
    /// This one alone (`vlf run --resume JOB`: the embedded service runs the job it was asked
    /// for, not every unfinished job that shares its store).
    Only(JobId),
    /// None (`vlf run` of a new job).
    Nothing,
}

/// Takes up the jobs of the store that `which` names: unfinished ones are resumed from their
/// last snapshot and driven; ended ones are listed with their final state. A job that cannot
/// be read is listed as failed with the reason, and the others go on.
pub async fn recover(sched: &Arc<Scheduler>, which: &TakeUp) -> Result<usize, StoreError> {
    let ids = match which {
        TakeUp::Nothing => return Ok(0),
        TakeUp::Only(id) => vec![id.clone()],
        TakeUp::Every => {
            let store = sched.store().clone();
            vlf_store::blocking(move || Job::list(&store))
                .await
                .map_err(|e| StoreError::Layout(e.to_string()))??
        }
    };
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
    let summary = job.latest_stage().and_then(|stage| job.summary(stage).ok());
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

/// What a restarted coordinator makes of a job of its store.
enum Taken {
    Resumed(Box<Coordinator>),
    ToSetUp(FieldJob),
    Ended(JobStatus),
}
