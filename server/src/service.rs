//! The gRPC services of `vlf.v1`, a thin layer over the [`Scheduler`]: requests are checked and
//! turned into scheduler calls, scheduler answers into messages, and errors into status codes —
//! `NOT_FOUND` for unknown jobs, workers and blobs, `INVALID_ARGUMENT` for bad ids, scenes and
//! parameters (with the importer's message), `RESOURCE_EXHAUSTED` for uploads over the limit.

use crate::driver::{self, SubmitError};
use crate::scheduler::{Abilities, Scheduler, Unknown, is_terminal};
use crate::upload::{self, UploadError};
use futures::{Stream, StreamExt};
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tonic::{Request, Response, Status};
use vlf_proto::v1::{self, jobs_server, tiles_server, workers_server};
use vlf_proto::{JobSpec, pass_blocks_to_wire, pass_to_wire};
use vlf_store::{JobId, StoreError, layout};

/// The three services over one scheduler.
#[derive(Clone)]
pub struct Api {
    sched: Arc<Scheduler>,
    max_upload: u64,
    /// Turns true when the server shuts down: open `Watch` streams end then, or a graceful
    /// shutdown would wait for them as long as their jobs run (or forever, for a job that waits
    /// for workers).
    closing: Option<tokio::sync::watch::Receiver<bool>>,
}

impl Api {
    pub fn new(sched: Arc<Scheduler>, max_upload: u64) -> Api {
        Api {
            sched,
            max_upload,
            closing: None,
        }
    }

    /// Ends the open `Watch` streams, with `UNAVAILABLE`, once `closing` turns true.
    pub fn closing_with(mut self, closing: tokio::sync::watch::Receiver<bool>) -> Api {
        self.closing = Some(closing);
        self
    }

    /// The status of `id`: the scheduler's, or, for a job it does not drive (written into the
    /// store by another process), the store's.
    async fn status_of(&self, id: &JobId) -> Result<v1::JobStatus, Status> {
        match self.sched.status(id) {
            Ok(status) => Ok(status),
            Err(_) => {
                let (store, id) = (self.sched.store().clone(), id.clone());
                vlf_store::blocking(move || driver::read_stored_status(&store, &id))
                    .await
                    .map_err(|e| Status::internal(e.to_string()))?
                    .map_err(store_status)
            }
        }
    }

    /// Leases `worker` its next run of batches, waiting up to `wait_ms` for one: a long poll, bounded so
    /// that a connection is never held for long.
    async fn next_lease(&self, worker: &str, wait_ms: u32) -> Result<Option<v1::Lease>, Status> {
        let wait = Duration::from_millis(u64::from(wait_ms.min(10_000)));
        let grant = self.sched.lease(worker, wait).await.map_err(unknown)?;
        Ok(grant.map(|g| {
            let (pass_kind, pass_copy) = pass_to_wire(g.pass);
            v1::Lease {
                lease_id: g.lease_id,
                job_id: g.job.to_string(),
                snapshot: g.snapshot,
                pass_kind,
                pass_copy,
                batch: g.batches.start as u32,
                batch_count: g.batches.len() as u32,
                committed_count: (g.committed - g.batches.start) as u32,
                deadline_ms: g.deadline.as_millis() as u32,
                reads: g
                    .reads
                    .iter()
                    .map(|(pass, blocks)| pass_blocks_to_wire(*pass, blocks))
                    .collect(),
            }
        }))
    }
}

fn job_id(id: &str) -> Result<JobId, Status> {
    JobId::parse(id).map_err(|e| Status::invalid_argument(format!("job id `{id}`: {e}")))
}

fn unknown(e: Unknown) -> Status {
    Status::not_found(e.to_string())
}

/// A store error as a status: a missing job or blob is `NOT_FOUND`.
fn store_status(e: StoreError) -> Status {
    match e {
        StoreError::NotFound { .. } => Status::not_found(e.to_string()),
        StoreError::InvalidKey { .. } | StoreError::Layout(_) => Status::invalid_argument(e.to_string()),
        e => Status::internal(e.to_string()),
    }
}

type StatusStream = Pin<Box<dyn Stream<Item = Result<v1::JobStatus, Status>> + Send>>;
type BlobStream = Pin<Box<dyn Stream<Item = Result<v1::StoredBlob, Status>> + Send>>;

#[tonic::async_trait]
impl jobs_server::Jobs for Api {
    async fn submit(&self, request: Request<v1::SubmitRequest>) -> Result<Response<v1::JobStatus>, Status> {
        let request = request.into_inner();
        let parameters = request.parameters.unwrap_or_default();
        let spec = JobSpec::from_parameters(&parameters).map_err(|e| Status::invalid_argument(e.to_string()))?;
        let scene = match request.scene {
            Some(v1::submit_request::Scene::Upload(upload)) => {
                let limit = self.max_upload;
                let (scene, warnings) = vlf_store::blocking(move || upload::import(&upload, limit))
                    .await
                    .map_err(|e| Status::internal(e.to_string()))?
                    .map_err(|e| match e {
                        UploadError::TooLarge { .. } => Status::resource_exhausted(e.to_string()),
                        UploadError::Io(_) => Status::internal(e.to_string()),
                        _ => Status::invalid_argument(e.to_string()),
                    })?;
                for w in warnings {
                    tracing::warn!("uploaded scene: {w}");
                }
                scene
            }
            Some(v1::submit_request::Scene::SceneOfJob(id)) => {
                let id = job_id(&id)?;
                let store = self.sched.store().clone();
                vlf_store::blocking(move || vlf_store::FieldJob::open(&store, &id).map(|j| j.scene().clone()))
                    .await
                    .map_err(|e| Status::internal(e.to_string()))?
                    .map_err(store_status)?
            }
            None => return Err(Status::invalid_argument("no scene: upload one or name a job's")),
        };
        let status = driver::submit(&self.sched, scene, spec).await.map_err(|e| match e {
            SubmitError::Invalid(e) => Status::invalid_argument(e.to_string()),
            e => Status::internal(e.to_string()),
        })?;
        Ok(Response::new(status))
    }

    async fn get(&self, request: Request<v1::JobRequest>) -> Result<Response<v1::JobStatus>, Status> {
        let id = job_id(&request.into_inner().job_id)?;
        Ok(Response::new(self.status_of(&id).await?))
    }

    async fn list(&self, _: Request<v1::ListJobsRequest>) -> Result<Response<v1::ListJobsReply>, Status> {
        Ok(Response::new(v1::ListJobsReply {
            jobs: self.sched.list(),
        }))
    }

    type WatchStream = StatusStream;

    async fn watch(&self, request: Request<v1::JobRequest>) -> Result<Response<Self::WatchStream>, Status> {
        let id = job_id(&request.into_inner().job_id)?;
        let mut rx = match self.sched.subscribe(&id) {
            Ok(rx) => rx,
            Err(_) => {
                // Not driven here: the store's status is final as far as this server knows.
                let status = self.status_of(&id).await?;
                return Ok(Response::new(Box::pin(futures::stream::iter([Ok(status)]))));
            }
        };
        let mut closing = self.closing.clone();
        let stream = async_stream(move |tx| async move {
            loop {
                let status = rx.borrow_and_update().clone();
                let terminal = is_terminal(status.state);
                if tx.send(Ok(status)).await.is_err() || terminal {
                    return;
                }
                tokio::select! {
                    changed = rx.changed() => {
                        if changed.is_err() {
                            return;
                        }
                    }
                    () = shut_down(&mut closing) => {
                        let _ = tx
                            .send(Err(Status::unavailable(
                                "the coordinator is shutting down; watch the job again once it is back \
                                 (a restarted coordinator takes its jobs up from the store)",
                            )))
                            .await;
                        return;
                    }
                }
            }
        });
        Ok(Response::new(stream))
    }

    async fn cancel(&self, request: Request<v1::JobRequest>) -> Result<Response<v1::JobStatus>, Status> {
        let id = job_id(&request.into_inner().job_id)?;
        match self.sched.cancel(&id) {
            Ok(status) => {
                tracing::info!(job = %id, "cancel requested");
                Ok(Response::new(status))
            }
            // A job of the store that is not driven here cannot be running here.
            Err(_) => Ok(Response::new(self.status_of(&id).await?)),
        }
    }

    async fn list_snapshots(
        &self,
        request: Request<v1::JobRequest>,
    ) -> Result<Response<v1::ListSnapshotsReply>, Status> {
        let id = job_id(&request.into_inner().job_id)?;
        let status = self.status_of(&id).await?;
        Ok(Response::new(v1::ListSnapshotsReply {
            job_id: status.job_id,
            iterations: status.snapshots,
            field: status.state == v1::State::Finished as i32,
        }))
    }
}

#[tonic::async_trait]
impl workers_server::Workers for Api {
    async fn register(&self, request: Request<v1::RegisterRequest>) -> Result<Response<v1::RegisterReply>, Status> {
        let request = request.into_inner();
        let abilities = Abilities {
            runs: request.takes_runs,
            claims: request.takes_claims,
            surveys: request.takes_surveys,
        };
        let worker_id = self.sched.register(&request.name, abilities);
        Ok(Response::new(v1::RegisterReply {
            worker_id,
            store_url: self.sched.store().url().to_string(),
            heartbeat_ms: self.sched.timing().heartbeat.as_millis() as u32,
        }))
    }

    async fn heartbeat(&self, request: Request<v1::HeartbeatRequest>) -> Result<Response<v1::HeartbeatReply>, Status> {
        self.sched.heartbeat(&request.into_inner().worker_id).map_err(unknown)?;
        Ok(Response::new(v1::HeartbeatReply {}))
    }

    async fn lease(&self, request: Request<v1::LeaseRequest>) -> Result<Response<v1::LeaseReply>, Status> {
        let request = request.into_inner();
        let lease = self.next_lease(&request.worker_id, request.wait_ms).await?;
        Ok(Response::new(v1::LeaseReply { lease }))
    }

    async fn report(&self, request: Request<v1::ReportRequest>) -> Result<Response<v1::ReportReply>, Status> {
        let request = request.into_inner();
        let result = if request.error.is_empty() {
            Ok(())
        } else {
            Err(request.error)
        };
        let end = (request.batch_end > 0).then_some(request.batch_end as usize);
        let accepted = self
            .sched
            .report_run(
                &request.worker_id,
                &request.lease_id,
                result,
                request.seconds,
                end,
                &request.batch_seconds,
            )
            .map_err(unknown)?;
        // The next lease in the same round trip, if asked for.
        let next = match request.next_wait_ms {
            0 => None,
            wait => self.next_lease(&request.worker_id, wait).await?,
        };
        Ok(Response::new(v1::ReportReply { accepted, next }))
    }

    async fn extend(&self, request: Request<v1::ExtendRequest>) -> Result<Response<v1::ExtendReply>, Status> {
        let request = request.into_inner();
        match self
            .sched
            .extend(&request.worker_id, &request.lease_id)
            .map_err(unknown)?
        {
            Some((committed, end)) => Ok(Response::new(v1::ExtendReply {
                committed_end: committed as u32,
                end: end as u32,
            })),
            None => Err(Status::not_found(format!(
                "lease `{}` is gone (expired, or its job ended)",
                request.lease_id
            ))),
        }
    }
}

/// A blob name relative to a job: plain segments only.
fn blob_key(id: &JobId, name: &str) -> Result<String, Status> {
    let ok = !name.is_empty()
        && name.len() <= 512
        && name
            .split('/')
            .all(|s| !s.is_empty() && s != "." && s != ".." && !s.contains('\\'));
    if ok {
        Ok(format!("{}{name}", layout::job_prefix(id)))
    } else {
        Err(Status::invalid_argument(format!(
            "`{name}` is not a blob name of a job"
        )))
    }
}

#[tonic::async_trait]
impl tiles_server::Tiles for Api {
    type FetchStream = BlobStream;

    async fn fetch(&self, request: Request<v1::FetchRequest>) -> Result<Response<Self::FetchStream>, Status> {
        let request = request.into_inner();
        let id = job_id(&request.job_id)?;
        let keys = request
            .names
            .iter()
            .map(|n| blob_key(&id, n).map(|k| (n.clone(), k)))
            .collect::<Result<Vec<_>, _>>()?;
        let store = self.sched.store().as_async().clone();
        let in_flight = store.in_flight();
        let stream = async_stream(move |tx| async move {
            // In the order asked, the reads overlapping their round trips to the store.
            let mut blobs = futures::stream::iter(keys)
                .map(|(name, key)| {
                    let store = store.clone();
                    async move {
                        match store.get(&key).await {
                            Ok(bytes) => Ok(v1::StoredBlob {
                                name,
                                data: bytes.to_vec(),
                            }),
                            Err(e) => Err(store_status(e)),
                        }
                    }
                })
                .buffered(in_flight);
            while let Some(item) = blobs.next().await {
                let failed = item.is_err();
                if tx.send(item).await.is_err() || failed {
                    return;
                }
            }
        });
        Ok(Response::new(stream))
    }

    async fn list_blobs(&self, request: Request<v1::ListBlobsRequest>) -> Result<Response<v1::ListBlobsReply>, Status> {
        let request = request.into_inner();
        let id = job_id(&request.job_id)?;
        let job_prefix = layout::job_prefix(&id);
        let prefix = if request.prefix.is_empty() {
            job_prefix.clone()
        } else {
            blob_key(&id, request.prefix.trim_end_matches('/'))? + "/"
        };
        let listed = self
            .sched
            .store()
            .as_async()
            .list_sizes(&prefix)
            .await
            .map_err(store_status)?;
        let (names, sizes): (Vec<String>, Vec<u64>) = listed
            .into_iter()
            .filter_map(|(key, size)| Some((key.strip_prefix(&job_prefix)?.to_string(), size)))
            .unzip();
        // Nothing listed: a job that exists, with nothing under the prefix, or no such job.
        if names.is_empty() && !self.sched.has_job(&id) {
            let manifest = layout::manifest(&id);
            let store = self.sched.store().as_async();
            if !store.exists(&manifest).await.map_err(store_status)? {
                return Err(Status::not_found(format!("job `{id}` does not exist")));
            }
        }
        Ok(Response::new(v1::ListBlobsReply { names, sizes }))
    }
}

/// A stream fed by `produce` through a small channel (backpressure: a slow client slows the
/// producer, nothing piles up).
/// Resolves once `closing` turns true or its server is dropped (which stops it too); never
/// without one.
async fn shut_down(closing: &mut Option<tokio::sync::watch::Receiver<bool>>) {
    match closing {
        Some(rx) => {
            let _ = rx.wait_for(|closing| *closing).await;
        }
        None => std::future::pending().await,
    }
}

fn async_stream<T, F, Fut>(produce: F) -> Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>
where
    T: Send + 'static,
    F: FnOnce(tokio::sync::mpsc::Sender<Result<T, Status>>) -> Fut,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tokio::spawn(produce(tx));
    Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scheduler::Timing;
    use vlf_core::propagate::Pass;
    use vlf_proto::v1::workers_server::Workers;

    fn report(worker: &str, lease: &v1::Lease, next_wait_ms: u32) -> Request<v1::ReportRequest> {
        Request::new(v1::ReportRequest {
            worker_id: worker.into(),
            lease_id: lease.lease_id.clone(),
            error: String::new(),
            seconds: 0.01,
            next_wait_ms,
            batch_end: 0,
            batch_seconds: Vec::new(),
        })
    }

    /// Registers a worker of one thread that takes runs, with the other abilities as given;
    /// returns its id.
    async fn register(api: &Api, name: &str, takes_claims: bool, takes_surveys: bool) -> String {
        let request = v1::RegisterRequest {
            name: name.into(),
            threads: 1,
            takes_runs: true,
            takes_claims,
            takes_surveys,
        };
        api.register(Request::new(request))
            .await
            .unwrap()
            .into_inner()
            .worker_id
    }

    /// Listing the blobs of a job that does not exist is NOT_FOUND, not an empty list; a job that
    /// exists lists what it has, nothing included.
    #[tokio::test]
    async fn listing_the_blobs_of_no_job_is_not_found() {
        use vlf_proto::v1::tiles_server::Tiles;
        let (sched, id) = scheduler_with_a_job();
        let api = Api::new(sched, 0);
        let list = |job: String| {
            let request = Request::new(v1::ListBlobsRequest {
                job_id: job,
                prefix: String::new(),
            });
            api.list_blobs(request)
        };
        let reply = list(id.to_string()).await.unwrap().into_inner();
        assert!(reply.names.is_empty(), "the scheduler's job, nothing stored yet");
        let err = list(JobId::generate().to_string()).await.unwrap_err();
        assert_eq!(err.code(), tonic::Code::NotFound, "{err:?}");
        assert!(err.message().contains("does not exist"), "{}", err.message());
    }

    /// A scheduler over a `memory://` store with one propagating job, its iteration started.
    fn scheduler_with_a_job() -> (Arc<Scheduler>, JobId) {
        let store = vlf_store::Store::open("memory://").unwrap();
        let sched = Scheduler::new(store, Timing::default(), None, None);
        let id = JobId::generate();
        sched
            .add_job(v1::JobStatus {
                job_id: id.to_string(),
                state: v1::State::Propagating as i32,
                ..Default::default()
            })
            .unwrap();
        sched.start_iteration(&id, 1, 16, 513);
        (sched, id)
    }

    #[tokio::test]
    async fn a_report_brings_the_next_lease_when_asked_for() {
        let (sched, id) = scheduler_with_a_job();
        sched.start_pass(&id, 0, Pass::Shoot, 16, &[], &[]);
        let api = Api::new(sched.clone(), 0);
        let worker = api
            .register(Request::new(v1::RegisterRequest {
                name: "w".into(),
                threads: 2,
                takes_runs: true,
                takes_claims: true,
                takes_surveys: true,
            }))
            .await
            .unwrap()
            .into_inner()
            .worker_id;
        let lease = |wait_ms| {
            api.lease(Request::new(v1::LeaseRequest {
                worker_id: worker.clone(),
                wait_ms,
            }))
        };
        let first = lease(0).await.unwrap().into_inner().lease.unwrap();
        assert_eq!((first.batch, first.batch_count), (0, 1), "speed unknown: one batch");
        // The report takes the next lease along: the rest of the pass, one run.
        let reply = api.report(report(&worker, &first, 50)).await.unwrap().into_inner();
        assert!(reply.accepted);
        let next = reply.next.expect("a next lease");
        assert_eq!((next.batch, next.batch_count), (1, 15));
        // Nothing is left to lease: the wait runs out and the reply has none; a report that does
        // not ask gets none either.
        let reply = api.report(report(&worker, &next, 20)).await.unwrap().into_inner();
        assert!(reply.accepted && reply.next.is_none());
        assert!(lease(0).await.unwrap().into_inner().lease.is_none());
        let stale = api.report(report(&worker, &next, 0)).await.unwrap().into_inner();
        assert!(!stale.accepted && stale.next.is_none(), "reported twice");
        // An unknown worker is told so.
        let err = api.report(report("w99-nobody", &first, 10)).await.unwrap_err();
        assert_eq!(err.code(), tonic::Code::NotFound);
        assert!(
            first.reads.is_empty() && next.reads.is_empty(),
            "a shooting pass reads no pass"
        );
        // A rotated copy's shooting: its lease names the blocks of the copy's areas.
        let areas = Pass::Areas { copy: 1 };
        sched.start_pass(
            &id,
            0,
            Pass::ShootCopy { copy: 1 },
            16,
            &[],
            &[(areas, vec![0..8, 8..16])],
        );
        let copy = lease(0).await.unwrap().into_inner().lease.unwrap();
        assert_eq!((copy.pass_kind, copy.pass_copy), (2, 1));
        assert_eq!(copy.reads, vec![pass_blocks_to_wire(areas, &[0..8, 8..16])]);
    }

    /// A survey is leased only to workers that learn surveys (an earlier build's would fail
    /// it), and what its batches took does not size the iterations' leases.
    #[tokio::test]
    async fn a_survey_goes_only_to_workers_that_learn_surveys() {
        let (sched, id) = scheduler_with_a_job();
        let api = Api::new(sched.clone(), 0);
        let mut workers = Vec::new();
        for (name, takes_surveys) in [("old", false), ("new", true)] {
            workers.push(register(&api, name, true, takes_surveys).await);
        }
        assert_eq!((sched.workers_alive(), sched.surveyors_alive()), (2, 1));
        let lease = |w: &String| {
            api.lease(Request::new(v1::LeaseRequest {
                worker_id: w.clone(),
                wait_ms: 0,
            }))
        };
        sched.start_pass(&id, 0, Pass::Survey, 16, &[], &[]);
        assert!(
            lease(&workers[0]).await.unwrap().into_inner().lease.is_none(),
            "not to an old worker"
        );
        let first = lease(&workers[1]).await.unwrap().into_inner().lease.unwrap();
        assert_eq!((first.pass_kind, first.pass_copy, first.snapshot), (3, 0, 0));
        assert_eq!((first.batch, first.batch_count), (0, 1), "speed unknown: one batch");
        // Reported, it sizes the survey's next leases: a quarter of what is open per worker, here
        // blocks of 4 (the lease runs to the end of the block that holds its first batch).
        let reply = api.report(report(&workers[1], &first, 20)).await.unwrap().into_inner();
        assert!(reply.accepted);
        let second = reply.next.expect("the next lease");
        assert_eq!((second.pass_kind, second.batch, second.batch_count), (3, 1, 3));
        let mut rest = vec![first, second];
        while let Some(next) = lease(&workers[1]).await.unwrap().into_inner().lease {
            rest.push(next);
        }
        for l in &rest[1..] {
            assert!(
                api.report(report(&workers[1], l, 0))
                    .await
                    .unwrap()
                    .into_inner()
                    .accepted
            );
        }
        let covered: u32 = rest.iter().map(|l| l.batch_count.max(1)).sum();
        assert_eq!(covered, 16);
        let blocks: Vec<_> = rest
            .iter()
            .flat_map(|l| {
                vlf_core::propagate::reduce::cover(l.batch as usize..(l.batch + l.batch_count.max(1)) as usize)
            })
            .collect();
        assert_eq!(
            sched.pass_outcome(&id, Pass::Survey, 0),
            crate::scheduler::PassOutcome::Ready(blocks)
        );
        sched.end_pass(&id, 0, Pass::Survey);
        // The old worker shoots; the speed is still unknown: one batch.
        sched.start_pass(&id, 0, Pass::Shoot, 16, &[], &[]);
        let shoot = lease(&workers[0]).await.unwrap().into_inner().lease.unwrap();
        assert_eq!((shoot.pass_kind, shoot.batch, shoot.batch_count), (0, 0, 1));
    }

    #[tokio::test]
    async fn a_lease_says_what_is_committed_and_extend_claims_the_rest() {
        let (sched, id) = scheduler_with_a_job();
        let api = Api::new(sched.clone(), 0);
        let mut workers = Vec::new();
        for (name, takes_claims) in [("a", true), ("b", true), ("old", false)] {
            workers.push(register(&api, name, takes_claims, true).await);
        }
        let lease = |w: &String| {
            api.lease(Request::new(v1::LeaseRequest {
                worker_id: w.clone(),
                wait_ms: 0,
            }))
        };
        // The speed is learnt from one batch; then each worker's home (a third of the pass).
        sched.start_pass(&id, 0, Pass::Shoot, 1, &[], &[]);
        let first = lease(&workers[0]).await.unwrap().into_inner().lease.unwrap();
        assert!(
            api.report(report(&workers[0], &first, 0))
                .await
                .unwrap()
                .into_inner()
                .accepted
        );
        sched.end_pass(&id, 0, Pass::Shoot);
        sched.start_pass(&id, 1, Pass::Shoot, 16, &[], &[]);
        let a = lease(&workers[0]).await.unwrap().into_inner().lease.unwrap();
        assert_eq!((a.batch, a.batch_count, a.committed_count), (0, 5, 4));
        let old = lease(&workers[2]).await.unwrap().into_inner().lease.unwrap();
        assert_eq!(
            (old.batch_count, old.committed_count),
            (5, 5),
            "a worker that does not claim"
        );
        let extend = |w: &String, lease: &str| {
            api.extend(Request::new(v1::ExtendRequest {
                worker_id: w.clone(),
                lease_id: lease.into(),
            }))
        };
        let claimed = extend(&workers[0], &a.lease_id).await.unwrap().into_inner();
        assert_eq!((claimed.committed_end, claimed.end), (5, 5));
        let gone = extend(&workers[1], &a.lease_id).await.unwrap_err();
        assert_eq!(gone.code(), tonic::Code::NotFound, "not b's lease");
        // A report names where the run ended.
        let mut done = report(&workers[0], &a, 0).into_inner();
        done.batch_end = 6;
        assert!(
            !api.report(Request::new(done.clone()))
                .await
                .unwrap()
                .into_inner()
                .accepted,
            "past its end"
        );
        done.batch_end = 5;
        assert!(api.report(Request::new(done)).await.unwrap().into_inner().accepted);
    }
}
