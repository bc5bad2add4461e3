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

mod recover;
mod set_up;
#[cfg(test)]
mod tests;

pub use recover::{TakeUp, read_stored_status, recover, stored_status};
use set_up::set_up_and_start;

use crate::scheduler::{PassOutcome, Scheduler};
use std::sync::Arc;
use tokio::sync::Notify;
use vlf_core::propagate::Pass;
use vlf_core::scene::Scene;
use vlf_proto::JobSpec;
use vlf_proto::v1::{JobStatus, State as WireState};
use vlf_store::{Coordinator, FieldJob, Job, JobId, JobState, Stage, StoreError, WorkTraffic};

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

/// Where a driver's job comes from.
#[derive(Clone, Copy, PartialEq)]
enum Origin {
    /// Submitted to this coordinator: nothing of its iterations is in the store yet.
    Submitted,
    /// Taken up from the store (a restarted coordinator): workers of the previous one may have
    /// written batches of the iterations after its last snapshot.
    Recovered,
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
            Ok(()) => self.finish(resample).await.err(),
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
    async fn finish(&mut self, resample: bool) -> Result<(), Stop> {
        // Cancelled while the last snapshot was committed: recorded cancelled, as earlier.
        self.check_cancelled()?;
        let coordinator = self
            .coordinator
            .take()
            .ok_or_else(|| Stop::Failed("internal: coordinator lost".to_string()))?;
        let unshot = coordinator.propagation().unshot_fraction();
        // The digest is in the summary it just wrote (a small blob, read back).
        let digest = vlf_store::blocking(move || {
            let job = coordinator.finish(resample)?;
            Ok::<_, StoreError>(job.summary(Stage::Field)?.digest.unwrap_or_default())
        })
        .await
        .map_err(|e| Stop::Failed(format!("internal: {e}")))?
        .map_err(|e| Stop::Failed(format!("cannot write the final field: {e}")))?;
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
