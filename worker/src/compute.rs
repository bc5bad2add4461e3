//! Computing a lease: its run of batches, one aligned block at a time, on every core, from the
//! store (or a survey's parts, before the job's first iteration).

use super::*;

/// A lease computed: its run, the writes of its outputs, what each batch cost, what to read
/// ahead of the next iteration, and where the replica spent the wall time.
pub(crate) type Computed = (Range<usize>, Writing, Vec<f64>, Option<ReadAhead>, ReplicaPhases);

/// Computes a lease's batches into the store, left to right, one aligned block at a time; the
/// outputs are those of the fewest aligned blocks that cover what was computed. Batches past the
/// lease's committed part are claimed first (`Claim`). Returns the run computed: the lease's,
/// ending earlier when the coordinator gave its tail to another worker.
pub(crate) async fn compute(
    store: &Store,
    pool: &Arc<rayon::ThreadPool>,
    replicas: &Arc<Mutex<Replicas>>,
    lease: &v1::Lease,
    ahead: Option<ReadAhead>,
    workers: &v1::workers_client::WorkersClient<vlf_proto::Authed>,
    worker_id: &str,
) -> Result<Computed, String> {
    let job = JobId::parse(&lease.job_id).map_err(|e| format!("lease names job `{}`: {e}", lease.job_id))?;
    let pass = pass_from_wire(lease.pass_kind, lease.pass_copy)
        .ok_or_else(|| format!("lease names pass ({}, {})", lease.pass_kind, lease.pass_copy))?;
    let reads = (lease.reads.iter())
        .map(pass_blocks_from_wire)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("lease names {e}"))?;
    let (store, pool, replicas) = (store.clone(), pool.clone(), replicas.clone());
    let (k, start) = (lease.snapshot, lease.batch as usize);
    let end = start + (lease.batch_count as usize).max(1);
    let committed = match lease.committed_count {
        0 => end,
        n => (start + n as usize).min(end),
    };
    if pass == Pass::Survey {
        return compute_survey(store, pool, replicas, job, start..committed).await;
    }
    let claim = Arc::new(Claim::new(committed, end));
    // The computing thread holds the only sender: the claimer stops when it is done.
    let (asks, asked) = tokio::sync::mpsc::unbounded_channel();
    let claimer = claimer(
        workers.clone(),
        worker_id.to_string(),
        lease.lease_id.clone(),
        claim.clone(),
        asked,
    );
    let computing = vlf_store::blocking(move || {
        pool.install(|| -> Result<Computed, StoreError> {
            let mut replicas = lock(&replicas);
            let replica = replicas.replica(&store, &job)?;
            for (earlier, blocks) in reads {
                replica.absorbed(k, earlier, blocks);
            }
            if let Some(ahead) = ahead {
                replica.adopt_ahead(ahead);
            }
            let (run, writes) = replica.compute_run_behind(k, pass, start, |done| claim.next_block(done, &asks))?;
            let costs = replica.batch_costs().to_vec();
            Ok((run, writes, costs, replica.read_ahead(k, pass), replica.phase_seconds()))
        })
    });
    let (computed, ()) = tokio::join!(computing, claimer);
    computed
        .map_err(|e| format!("internal: {e}"))?
        .map_err(|e| e.to_string())
}

/// Learns the survey parts of the batches `run` of `job` (not set up yet: no [`Replica`] can be
/// opened) into the store, one per aligned block of the run (`reduce::cover`), with the
/// [`Surveyor`] the worker keeps for the job (its atlas built at the first survey lease), the
/// subfields held within the worker's budget. A survey lease is committed whole; were it not, the
/// run computed is the committed part, and the report says so (the rest goes back to the pool).
pub(crate) async fn compute_survey(
    store: Store,
    pool: Arc<rayon::ThreadPool>,
    replicas: Arc<Mutex<Replicas>>,
    job: JobId,
    run: Range<usize>,
) -> Result<Computed, String> {
    let computing = vlf_store::blocking(move || {
        pool.install(|| -> Result<Computed, StoreError> {
            let mut replicas = lock(&replicas);
            let (opened, surveyor) = replicas.surveyor(&store, &job)?;
            let batching = opened.options().batching();
            let (mut writes, mut costs) = (Vec::new(), Vec::new());
            for block in reduce::cover(run.clone()) {
                let started = Instant::now();
                let part =
                    (surveyor.part(batching.directions_of(block.clone()))).map_err(|source| StoreError::Field {
                        url: store.url().to_string(),
                        job: job.to_string(),
                        source,
                    })?;
                // Written while the next block is learnt, its bytes dropped once written, rather
                // than every part of the lease held until its end (with mirror planes, a curved
                // mirror's parts are tens of kB a direction); a store slower than the learning
                // still holds them meanwhile. Should a later block fail, the parts already on
                // their way land unreported: harmless, as a part is a pure function of the job
                // and its block, written create-only, and one the coordinator finds stored is
                // one it need not lease again.
                let put = opened.survey_part_put(block.clone(), &part)?;
                drop(part);
                writes.push(store.put_all_behind(vec![put])?);
                let each = started.elapsed().as_secs_f64() / block.len() as f64;
                costs.extend(std::iter::repeat_n(each, block.len()));
            }
            tracing::debug!(job = %job, batches = ?run, "survey parts learnt");
            Ok((
                run,
                Writing::all(&store, writes)?,
                costs,
                None,
                ReplicaPhases::default(),
            ))
        })
    });
    computing
        .await
        .map_err(|e| format!("internal: {e}"))?
        .map_err(|e| e.to_string())
}
