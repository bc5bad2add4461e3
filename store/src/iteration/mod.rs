//! An iteration through the store: workers compute blocks of batches of directions and write
//! their outputs into the job; the coordinator absorbs them in order and commits the next
//! snapshot. This is the data path of the distributed service — the coordinator moves no
//! radiance over the network, only which blocks to compute (leases) — and it is usable
//! in-process as well, with threads for workers.
//!
//! The protocol for the iteration that starts from snapshot `k` (see `vlf_core::propagate::work`
//! for passes and batches, `vlf_core::propagate::reduce` for blocks):
//!
//! 1. Every batch of a pass is computed by some [`Replica`] (a worker's copy of the
//!    propagation, restored from snapshot `k`'s head and the mirror maps the block reads) once
//!    the pass's prerequisites are absorbed, as part of an aligned block. A shooting block
//!    with mirrors first writes its directions' mirror maps as parts of snapshot `k + 1`
//!    (`iters/K+1/{shooting,mirror-totals}/BBBBB.blob`: the arrivals to reflect next, the
//!    totals); then its node sum and its arrivals settled by batch (a few numbers) go to
//!    `jobs/J/work/KKKKK/PASS/SSSSS-EEEEE.blob`. Writes are create-only; a block computed
//!    twice (a lease that expired and was handed out again, a late result) writes the same
//!    bytes, which the store accepts as unchanged — and different bytes would be an error,
//!    never a silent replacement.
//! 2. The [`Coordinator`] reads the blocks in pass and batch order and absorbs each as soon as
//!    it is written (the next ones are still being computed meanwhile); replicas read the
//!    blocks of a pass's prerequisites to learn what it needs (a rotated copy's areas).
//! 3. After the last pass the coordinator finishes the iteration (diffuse reflection; the
//!    batches' settled arrivals added up) and writes snapshot `k + 1`'s head, which releases
//!    the next iteration ([`Coordinator::release_iteration`]); it then writes the rest of the
//!    snapshot (diffuse totals and maps, summary), commits it and deletes the iteration's
//!    outputs ([`SnapshotCommit::commit`]) — in the service, while workers compute the next
//!    iteration; [`Coordinator::finish_iteration`] does both at once.
//!
//! So mirror maps go from worker to worker through the store and never through the
//! coordinator, and a replica keeps the maps it wrote: one that shoots the same directions in
//! the next iteration, and gathers from directions it shot, reads none back (a single worker
//! reads no mirror map at all).
//!
//! The bits do not depend on which replica computed which block, how large the blocks were, or
//! when: tested with several replicas in threads, blocks of 1, 2 and 4 batches assigned in a
//! shuffled order and some computed twice.
//!
//! The code, read top-down: this module names the iteration's work blobs and reads and writes
//! them ([`FieldJob::put_batch`], [`FieldJob::get_batches`], [`FieldJob::stored_blocks`]); then
//! - `replica`: the worker's side, [`Replica`], which computes leased blocks and writes their
//!   outputs and mirror maps;
//! - `coordinator`: the coordinator's side, [`Coordinator`], which absorbs the blocks in order and
//!   commits the snapshot ([`SnapshotCommit`]), and what an iteration moved ([`WorkTraffic`]);
//! - `cover`: which aligned blocks make up a pass, for both sides;
//! - `prototypes`: [`Prototypes`], propagations a process's coordinator hands its workers.
//! - `survey`: the survey learnt by the workers before the job is set up, as the parts of a pass
//!   leased like the iterations' ([`vlf_core::propagate::Pass::Survey`]).

mod coordinator;
mod cover;
mod prototypes;
mod replica;
mod survey;

pub use coordinator::{Coordinator, CoordinatorPhases, SnapshotCommit, WorkTraffic};
pub use prototypes::Prototypes;
pub use replica::{HeldMaps, ReadAhead, Replica, ReplicaPhases};

use crate::blob::{self, BlobError, BlobKind};
use crate::error::StoreError;
use crate::field::FieldJob;
use crate::layout;
use crate::store::{Put, PutOutcome};
use rayon::prelude::*;
use std::ops::Range;
use vlf_core::propagate::{BatchOutput, Pass};

/// The key segment of a pass.
fn pass_name(pass: Pass) -> String {
    match pass {
        Pass::Shoot => "shoot".into(),
        Pass::Areas { copy } => format!("areas-{copy:02}"),
        Pass::ShootCopy { copy } => format!("copy-{copy:02}"),
        Pass::Survey => "survey".into(),
    }
}

impl FieldJob {
    /// Writes a block output of the iteration starting from snapshot `output.iteration`
    /// (create-only: the same content again is accepted, other content refused).
    pub fn put_batch(&self, output: &BatchOutput) -> Result<PutOutcome, StoreError> {
        let put = self.batch_put(output)?;
        self.job().store().put_new(&put.key, put.bytes)
    }

    /// [`FieldJob::put_batch`]'s blob, encoded, for [`crate::Store::put_all`].
    pub fn batch_put(&self, output: &BatchOutput) -> Result<Put, StoreError> {
        let key = layout::work_block(
            self.id(),
            output.iteration,
            &pass_name(output.pass),
            output.batches.start,
            output.batches.end,
        )?;
        // Serialised into the compressor as it goes, not into memory first (see
        // `blob::encode_bytes_with`).
        self.work_put(key, || {
            blob::encode_bytes_with(BlobKind::BatchOutput, output.serialized_len(), |w| output.write_to(w))
        })
    }

    /// The work blob `encode` makes, under `key`, for [`crate::Store::put_all`]: create-only, as
    /// every block output is.
    fn work_put(&self, key: String, encode: impl FnOnce() -> Result<Vec<u8>, BlobError>) -> Result<Put, StoreError> {
        let bytes = encode().map_err(|source| StoreError::Blob {
            url: self.job().store().url().to_string(),
            key: key.clone(),
            source,
        })?;
        Ok(Put {
            key,
            bytes: bytes.into(),
            create_only: true,
        })
    }

    /// Reads the output of batches `batches` of `pass` of the iteration starting from snapshot
    /// `k`.
    pub fn get_batch(&self, k: u32, pass: Pass, batches: Range<usize>) -> Result<BatchOutput, StoreError> {
        let mut outputs = self.get_batches(k, pass, std::slice::from_ref(&batches))?;
        Ok(outputs.remove(0))
    }

    /// [`FieldJob::get_batch`] of several blocks, their requests overlapping (see
    /// [`crate::Store::get_all`]), decoded in parallel, in the order of `blocks`.
    pub fn get_batches(&self, k: u32, pass: Pass, blocks: &[Range<usize>]) -> Result<Vec<BatchOutput>, StoreError> {
        Ok(self.read_batches(k, pass, blocks)?.0)
    }

    /// [`FieldJob::get_batches`], and what the blobs read weigh as stored.
    fn read_batches(
        &self,
        k: u32,
        pass: Pass,
        blocks: &[Range<usize>],
    ) -> Result<(Vec<BatchOutput>, WorkTraffic), StoreError> {
        let keys = blocks
            .iter()
            .map(|b| layout::work_block(self.id(), k, &pass_name(pass), b.start as u32, b.end as u32))
            .collect::<Result<Vec<_>, _>>()?;
        let blobs = self.job().store().get_all(&keys)?;
        let read = WorkTraffic {
            blobs: blobs.len() as u64,
            bytes: blobs.iter().map(|b| b.len() as u64).sum(),
        };
        let outputs = (keys.par_iter().zip(&blobs).zip(blocks))
            .map(|((key, blob), batches)| {
                // Deserialised as it is decompressed: the payload is never held whole.
                let output = self
                    .job()
                    .store()
                    .as_async()
                    .decode_with(key, blob, |b| {
                        blob::decode_bytes_with(b, BlobKind::BatchOutput, |r| BatchOutput::read_from(r))
                    })?
                    .map_err(|e| self.decode_error(key, e.to_string()))?;
                let held = output.batches.start as usize..output.batches.end as usize;
                if (output.iteration, output.pass, &held) != (k, pass, batches) {
                    return Err(self.decode_error(
                        key,
                        format!(
                            "holds batches {held:?} of {:?} of iteration {}",
                            output.pass, output.iteration
                        ),
                    ));
                }
                Ok(output)
            })
            .collect::<Result<_, _>>()?;
        Ok((outputs, read))
    }

    /// The blocks of `pass` of the iteration starting from snapshot `k` whose outputs are in the
    /// store, in order of their first batch (larger first where two start together).
    pub fn stored_blocks(&self, k: u32, pass: Pass) -> Result<Vec<Range<usize>>, StoreError> {
        let prefix = layout::work_pass(self.id(), k, &pass_name(pass))?;
        let mut blocks: Vec<Range<usize>> = self
            .job()
            .store()
            .list(&prefix)?
            .iter()
            .filter_map(|key| layout::parse_work_block(&prefix, key))
            .map(|r| r.start as usize..r.end as usize)
            .collect();
        blocks.sort_by_key(|r| (r.start, std::cmp::Reverse(r.end)));
        Ok(blocks)
    }

    fn decode_error(&self, key: &str, reason: String) -> StoreError {
        StoreError::Field {
            url: self.job().store().url().to_string(),
            job: self.id().to_string(),
            source: vlf_core::Error::Decode(format!("`{key}`: {reason}")),
        }
    }
}
