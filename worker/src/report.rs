//! Reporting a lease: at once when its outputs are written within a moment, else from the
//! background once they are, so the next lease is computed while the writes finish.

use super::*;

/// The report of a lease: computed up to the end of the run at `costs` per batch, or failed;
/// asking for the next lease with a wait of `next_wait_ms` (0: not asking).
pub(crate) fn report_request(
    worker_id: &str,
    lease_id: &str,
    outcome: Result<Range<usize>, String>,
    costs: Vec<f64>,
    next_wait_ms: u32,
) -> v1::ReportRequest {
    let seconds = costs.iter().sum();
    let (batch_end, error, batch_seconds) = match outcome {
        Ok(run) => (run.end as u32, String::new(), costs),
        Err(e) => (0, e, Vec::new()),
    };
    v1::ReportRequest {
        worker_id: worker_id.to_string(),
        lease_id: lease_id.to_string(),
        error,
        seconds,
        next_wait_ms,
        batch_end,
        batch_seconds,
    }
}

/// What writing a lease's outputs came to, as a report's error.
pub(crate) fn written_or_error(written: Result<Result<(), StoreError>, tokio::task::JoinError>) -> Result<(), String> {
    match written {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(e.to_string()),
        Err(e) => Err(format!("internal: {e}")),
    }
}

/// Reports `lease`, computed up to the end of `run` at `costs` per batch, once `writes` are done (an
/// error if they failed), without asking for the next lease: the worker has asked for it already.
/// A report that does not arrive only lets the lease expire.
pub(crate) fn report_when_written(
    reports: &mut tokio::task::JoinSet<()>,
    mut workers: v1::workers_client::WorkersClient<vlf_proto::Authed>,
    worker_id: &str,
    lease: &v1::Lease,
    run: Range<usize>,
    costs: Vec<f64>,
    writes: tokio::task::JoinHandle<Result<(), StoreError>>,
) {
    let (worker_id, lease_id) = (worker_id.to_string(), lease.lease_id.clone());
    reports.spawn(async move {
        let written = written_or_error(writes.await).map(|()| run);
        if let Err(e) = &written {
            tracing::error!(lease = lease_id, "writing the outputs failed: {e}");
        }
        let report = report_request(&worker_id, &lease_id, written, costs, 0);
        match workers.report(report).await {
            Ok(reply) if !reply.get_ref().accepted => {
                tracing::debug!(lease = lease_id, "report ignored (lease expired or job ended)")
            }
            Ok(_) => {}
            Err(status) => tracing::debug!(lease = lease_id, "report failed: {}", status.message()),
        }
    });
}
