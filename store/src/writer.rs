//! Writing a propagation's snapshots while it goes on.
//!
//! A process that propagates a job itself (`vlf propagate`, the bench's in-process runs) writes
//! a snapshot after every iteration. Written in place, the iteration waits for the store: for
//! the mirror scene at l = 2049, N = 128 a snapshot is 78 MB in about 150 blobs, a third of
//! the run with an object store's round trips. [`SnapshotWriter`] takes the snapshot's bytes at
//! once (serialised and compressed on the propagation's own threads, so the next iteration
//! cannot change them) and writes them on a thread of its own while the next iteration runs;
//! that thread commits the snapshot once its blobs are in, in the order of
//! [`crate::FieldJob::write_snapshot`] (mirror maps, head, the rest, then the manifest).
//!
//! One snapshot is written at a time: the next waits for the one before to be committed, so
//! the manifest lists snapshots in order, a crash leaves the last committed one to resume from
//! exactly as before, and the memory held is one snapshot's bytes. The field's bits do not
//! depend on when a snapshot is written (it is a copy of the state).

use crate::error::StoreError;
use crate::field::FieldJob;
use crate::job::Job;
use std::thread::JoinHandle;
use vlf_core::propagate::Propagation;

/// Writes the snapshots of one job, each while the next iteration runs (see the module docs).
#[derive(Default)]
pub struct SnapshotWriter {
    /// The snapshot being written: its number and the thread that writes and commits it.
    writing: Option<(u32, JoinHandle<Result<Job, StoreError>>)>,
}

impl SnapshotWriter {
    pub fn new() -> SnapshotWriter {
        SnapshotWriter::default()
    }

    /// Waits until the snapshot being written (if any) is committed, and records the commit in
    /// `job`; then takes the snapshot after `p.iterations_done()` iterations and starts writing
    /// it. An error is the earlier snapshot's, or this one's refusal (a snapshot already
    /// finished); an error writing this one comes from the next call, or from
    /// [`SnapshotWriter::finish`].
    pub fn write(&mut self, job: &mut FieldJob, p: &Propagation) -> Result<(), StoreError> {
        self.finish(job)?;
        let encoded = job.encode_snapshot(p, true)?;
        let store = job.job().store().clone();
        let k = encoded.rest.iteration();
        let thread = std::thread::Builder::new()
            .name(format!("vlf-snapshot-{k}"))
            .spawn(move || {
                store.put_all(encoded.maps)?;
                // The head last: once it is there, the state is complete.
                store.put_all(vec![encoded.head])?;
                encoded.rest.commit()
            })
            .map_err(|e| StoreError::Runtime {
                url: job.job().store().url().to_string(),
                reason: format!("cannot start a thread to write snapshot {k}: {e}"),
            })?;
        self.writing = Some((k, thread));
        Ok(())
    }

    /// Waits until the snapshot being written (if any) is committed, and records the commit in
    /// `job`: after it, `job` lists every snapshot given to [`SnapshotWriter::write`].
    pub fn finish(&mut self, job: &mut FieldJob) -> Result<(), StoreError> {
        let Some((k, thread)) = self.writing.take() else {
            return Ok(());
        };
        let committed = thread.join().map_err(|_| StoreError::Runtime {
            url: job.job().store().url().to_string(),
            reason: format!("the thread writing snapshot {k} panicked"),
        })??;
        job.adopt_commit(committed);
        Ok(())
    }

    /// The snapshot being written, if one is.
    pub fn writing(&self) -> Option<u32> {
        self.writing.as_ref().map(|(k, _)| *k)
    }
}

impl Drop for SnapshotWriter {
    /// A writer dropped with a snapshot in flight (its caller failed) lets the write finish: a
    /// process that exits at once may leave its blobs without a commit, which is safe (readers
    /// trust only the manifest) but wasted.
    fn drop(&mut self) {
        if let Some((_, thread)) = self.writing.take() {
            let _ = thread.join();
        }
    }
}
