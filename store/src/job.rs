//! A job in a store, and its commit protocol.
//!
//! **Blobs first, manifest last.** The blobs of an iteration's snapshot (resume state, diffuse
//! and mirror maps, tiles) are written first; then [`Job::commit_iteration`] rewrites the manifest
//! with the iteration added to `finished_iterations`. Every write is atomic on its own, and
//! readers trust only what the manifest lists, so a crash anywhere leaves a consistent job: the
//! blobs of an unlisted iteration are invisible (reads refuse them) and are simply written again
//! when propagation resumes from the last listed iteration.
//!
//! **Finished snapshots are immutable.** A write to a listed iteration (or to the final field
//! once the job is finished) is create-only: the same content again is a no-op, different content
//! is [`StoreError::AlreadyExists`]. A write to an unlisted stage replaces what a crashed run may
//! have left there.
//!
//! One process writes a job at a time (the one that created or resumed it); any number may read.

use crate::blob::{self, BlobKind, Encoding};
use crate::error::StoreError;
use crate::id::JobId;
use crate::layout::{self, MapPart, Stage};
use crate::manifest::{JobState, Manifest};
use crate::store::{IN_FLIGHT, Put, Store};
use bytes::Bytes;
use rayon::prelude::*;

/// A released state's bytes and, for each part asked along, its bytes if they could be read
/// ([`Job::get_released_state_and_parts`]).
pub type StateAndParts = (Vec<u8>, Vec<Option<Vec<u8>>>);

/// A job: its store and the manifest as last read or written.
#[derive(Debug, Clone)]
pub struct Job {
    store: Store,
    manifest: Manifest,
}

impl Job {
    /// Creates a job with a new id: writes the scene, then the manifest (queued, nothing
    /// finished). `scene` is the caller's serialisation of the normalised scene, `scene_hash`
    /// its hash in hex, `parameters` the propagation options, `encoding` that of all radiance.
    pub fn create(
        store: &Store,
        scene: &[u8],
        scene_hash: &str,
        parameters: serde_json::Value,
        encoding: Encoding,
    ) -> Result<Job, StoreError> {
        Job::create_with_id(store, JobId::generate(), scene, scene_hash, parameters, encoding)
    }

    /// As [`Job::create`] with a given id; fails with [`StoreError::AlreadyExists`] if a job (or
    /// another scene) already has it.
    pub fn create_with_id(
        store: &Store,
        id: JobId,
        scene: &[u8],
        scene_hash: &str,
        parameters: serde_json::Value,
        encoding: Encoding,
    ) -> Result<Job, StoreError> {
        let manifest = Manifest::new(id, scene_hash, parameters, encoding);
        let job = Job {
            store: store.clone(),
            manifest,
        };
        job.manifest.validate().map_err(|reason| job.error(reason))?;
        let id = job.id();
        let scene = blob::encode_bytes(BlobKind::Scene, scene).map_err(|e| job.error(e.to_string()))?;
        store.put_new(&layout::scene(id), scene)?;
        let manifest = job.manifest.to_blob().map_err(|reason| job.error(reason))?;
        store.flush()?;
        store.put_new(&layout::manifest(id), manifest)?;
        store.flush()?;
        Ok(job)
    }

    /// Opens an existing job by reading its manifest.
    pub fn open(store: &Store, id: &JobId) -> Result<Job, StoreError> {
        let manifest = read_manifest(store, id)?;
        Ok(Job {
            store: store.clone(),
            manifest,
        })
    }

    /// The ids of the jobs in `store` that have a manifest, sorted (by creation time for
    /// generated ids). One delimiter listing, then the existence checks of every job's manifest,
    /// their requests overlapping (see [`Store::exist_all`]).
    pub fn list(store: &Store) -> Result<Vec<JobId>, StoreError> {
        let ids: Vec<JobId> = store
            .list_children(layout::JOBS_PREFIX)?
            .iter()
            .filter_map(|name| JobId::parse(name).ok())
            .collect();
        let manifests = ids.iter().map(layout::manifest).collect::<Vec<_>>();
        let present = store.exist_all(&manifests)?;
        Ok(ids
            .into_iter()
            .zip(present)
            .filter_map(|(id, there)| there.then_some(id))
            .collect())
    }

    /// Reads the manifest again (to see another process's progress).
    pub fn reload(&mut self) -> Result<(), StoreError> {
        self.manifest = read_manifest(&self.store, self.id())?;
        Ok(())
    }

    /// The job's id.
    pub fn id(&self) -> &JobId {
        &self.manifest.job_id
    }

    /// The manifest as last read or written.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The store the job is in.
    pub fn store(&self) -> &Store {
        &self.store
    }

    /// The last finished iteration, if any: where to resume.
    pub fn last_finished(&self) -> Option<u32> {
        self.manifest.last_finished()
    }

    /// Whether `stage` is committed: a listed iteration, or the field of a finished job.
    pub fn is_committed(&self, stage: Stage) -> bool {
        match stage {
            Stage::Iteration(k) => self.manifest.is_finished(k),
            Stage::Field => self.manifest.state == JobState::Finished,
        }
    }

    /// Encodes `items` into blobs with `encode` on the compute threads (rayon) and writes them
    /// with [`Store::put_all`], whose requests overlap their round trips: the way to write many
    /// blobs (see [`crate::store`]). A slice of `4 · IN_FLIGHT` items at a time, so that only a
    /// slice's encoded blobs are held at once.
    pub fn put_encoded<T: Sync>(
        &self,
        items: &[T],
        encode: impl Fn(&T) -> Result<Put, StoreError> + Sync,
    ) -> Result<(), StoreError> {
        for slice in items.chunks(4 * IN_FLIGHT) {
            let puts = slice.par_iter().map(&encode).collect::<Result<Vec<_>, _>>()?;
            self.store.put_all(puts)?;
        }
        Ok(())
    }

    /// Writes what setting the job up learnt over all its directions (caller's serialisation):
    /// once, create-only — it is a pure function of the job.
    pub fn put_survey(&self, survey: &[u8]) -> Result<(), StoreError> {
        self.put_once(&layout::survey(self.id()), BlobKind::Survey, survey)
    }

    /// The job's survey (caller's serialisation); `None` if it has none.
    pub fn survey(&self) -> Result<Option<Vec<u8>>, StoreError> {
        self.get_if_any(&layout::survey(self.id()), BlobKind::Survey)
    }

    /// Writes the mirror views and routes computed when the job was set up: the `raw_len` bytes
    /// `write` writes (caller's serialisation), compressed as they are written
    /// ([`blob::encode_bytes_with`]; a curved mirror's are a hundred megabytes). Once,
    /// create-only — like the survey, a pure function of the job.
    ///
    /// Where the job has a geometry already (a coordinator setting up again a job whose set-up
    /// stopped midway), what is compared is the payload, not the compressed bytes: a build before
    /// this one compressed a large geometry from memory, into another frame of the same payload.
    /// Another payload is [`StoreError::AlreadyExists`], and the stored blob stays as it was.
    pub fn put_mirror_geometry_with(
        &self,
        raw_len: u64,
        write: impl FnOnce(&mut dyn std::io::Write) -> std::io::Result<()>,
    ) -> Result<(), StoreError> {
        let (key, kind) = (layout::mirror_geometry(self.id()), BlobKind::MirrorGeometry);
        let encoded = blob::encode_bytes_with(kind, raw_len, write).map_err(|e| self.blob_error(&key, e))?;
        let bytes = Bytes::from(encoded);
        match self.store.put_new(&key, bytes.clone()) {
            Err(conflict @ StoreError::AlreadyExists { .. }) => {
                let there = self.store.get(&key)?;
                let same = matches!(
                    (blob::decode_bytes(&there, kind), blob::decode_bytes(&bytes, kind)),
                    (Ok(a), Ok(b)) if a == b
                );
                if same { Ok(()) } else { Err(conflict) }
            }
            outcome => outcome.map(|_| ()),
        }
    }

    /// The job's mirror views and routes, as `read` makes them of the blob's payload while it is
    /// decompressed ([`blob::decode_bytes_with`]: the blob's checks, and `read` must take all of
    /// the payload), given the payload's length as its header says; `None` if the job has none.
    /// The outer error is the store's or the blob's, the inner one `read`'s.
    pub fn mirror_geometry_with<T, E>(
        &self,
        read: impl FnOnce(&mut dyn std::io::Read, u64) -> Result<T, E>,
    ) -> Result<Option<Result<T, E>>, StoreError> {
        let key = layout::mirror_geometry(self.id());
        let bytes = match self.store.get(&key) {
            Ok(bytes) => bytes,
            Err(StoreError::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(e),
        };
        // A header that cannot be read is refused by the decoding, before `read` is called.
        let len = blob::read_header(&bytes).map_or(0, |h| h.raw_len);
        let decoded = blob::decode_bytes_with(&bytes, BlobKind::MirrorGeometry, |r| read(r, len));
        decoded.map(Some).map_err(|e| self.blob_error(&key, e))
    }

    /// Writes `data` as the `kind` blob at `key`, create-only: what is a pure function of the
    /// job may be written again, with the same bytes, by a coordinator that sets it up again.
    fn put_once(&self, key: &str, kind: BlobKind, data: &[u8]) -> Result<(), StoreError> {
        let bytes = blob::encode_bytes(kind, data).map_err(|e| self.blob_error(key, e))?;
        self.store.put_new(key, bytes)?;
        Ok(())
    }

    /// The `kind` blob at `key`, decoded; `None` if there is none.
    fn get_if_any(&self, key: &str, kind: BlobKind) -> Result<Option<Vec<u8>>, StoreError> {
        match self.store.get_bytes_blob(key, kind) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(StoreError::NotFound { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Writes the resume state of iteration `k` (caller's serialisation).
    pub fn put_state(&self, k: u32, state: &[u8]) -> Result<(), StoreError> {
        self.store.put_all(vec![self.state_put(k, state)?])
    }

    /// [`Job::put_state`]'s blob, encoded, for [`Store::put_all`].
    pub fn state_put(&self, k: u32, state: &[u8]) -> Result<Put, StoreError> {
        let key = layout::state(self.id(), k)?;
        let bytes = blob::encode_bytes(BlobKind::Snapshot, state).map_err(|e| self.blob_error(&key, e))?;
        Ok(self.put_into(Stage::Iteration(k), key, bytes))
    }

    /// [`Job::state_put`] of the `raw_len` bytes `write` writes, compressed as they are written
    /// ([`blob::encode_bytes_with`]): the same payload, no buffer of the whole state.
    pub fn state_put_with(
        &self,
        k: u32,
        raw_len: u64,
        write: impl FnOnce(&mut dyn std::io::Write) -> std::io::Result<()>,
    ) -> Result<Put, StoreError> {
        let key = layout::state(self.id(), k)?;
        let bytes =
            blob::encode_bytes_with(BlobKind::Snapshot, raw_len, write).map_err(|e| self.blob_error(&key, e))?;
        Ok(self.put_into(Stage::Iteration(k), key, bytes))
    }

    /// Mirror maps `part` of batch `batch` of the resume state of iteration `k` (caller's
    /// serialisation), encoded, for [`Store::put_all`]. Create-only: they are a pure function of
    /// the job, so the same bytes again (a block computed twice, a run resumed) are accepted and
    /// different bytes refused.
    pub fn map_part_put(&self, k: u32, part: MapPart, batch: u32, bytes: &[u8]) -> Result<Put, StoreError> {
        let key = layout::map_part(self.id(), k, part, batch)?;
        let bytes = blob::encode_bytes(BlobKind::Snapshot, bytes).map_err(|e| self.blob_error(&key, e))?;
        Ok(Put {
            key,
            bytes: bytes.into(),
            create_only: true,
        })
    }

    /// The [`MapPart::Radiance`] values blob of batch `batch` of snapshot `k` (`shape`
    /// `[slots, 3]`, in the stage's radiance unit), in the job's encoding, for
    /// [`Store::put_all`]; create-only, as [`Job::map_part_put`]'s.
    pub fn mirror_radiance_put(&self, k: u32, batch: u32, shape: &[u32], values: &[f32]) -> Result<Put, StoreError> {
        let key = layout::map_part(self.id(), k, MapPart::Radiance, batch)?;
        let bytes = blob::encode_values(BlobKind::BatchRadiance, self.manifest.encoding, shape, values)
            .map_err(|e| self.blob_error(&key, e))?;
        Ok(Put {
            key,
            bytes: bytes.into(),
            create_only: true,
        })
    }

    /// Mirror maps `part` of batch `b` of the resume state of iteration `k` as written,
    /// committed or not (see [`Job::get_released_state`]), for every `(part, b)` of `parts`,
    /// their requests overlapping (see [`Store::get_all`]), in the order of `parts`.
    pub fn get_released_map_parts(&self, k: u32, parts: &[(MapPart, usize)]) -> Result<Vec<Vec<u8>>, StoreError> {
        let keys = parts
            .iter()
            .map(|&(part, b)| layout::map_part(self.id(), k, part, b as u32))
            .collect::<Result<Vec<_>, _>>()?;
        let blobs = self.store.get_all(&keys)?;
        (keys.par_iter().zip(&blobs))
            .map(|(key, bytes)| self.decode_snapshot(key, bytes))
            .collect()
    }

    /// The caller's serialisation in a snapshot blob read from `key`, checked.
    pub(crate) fn decode_snapshot(&self, key: &str, bytes: &[u8]) -> Result<Vec<u8>, StoreError> {
        self.store
            .as_async()
            .decode_with(key, bytes, |b| blob::decode_bytes(b, BlobKind::Snapshot))
    }

    /// The totals half of the resume state of iteration `k` (caller's serialisation; optional: a
    /// job's resume state may be one blob), encoded, for [`Store::put_all`].
    pub fn totals_put(&self, k: u32, totals: &[u8]) -> Result<Put, StoreError> {
        let key = layout::totals(self.id(), k)?;
        let bytes = blob::encode_bytes(BlobKind::Snapshot, totals).map_err(|e| self.blob_error(&key, e))?;
        Ok(self.put_into(Stage::Iteration(k), key, bytes))
    }

    /// Writes the summary of `stage` (caller's JSON).
    pub fn put_summary(&self, stage: Stage, json: &[u8]) -> Result<(), StoreError> {
        self.store.put_all(vec![self.summary_put(stage, json)?])
    }

    /// [`Job::put_summary`]'s blob, encoded, for [`Store::put_all`].
    pub fn summary_put(&self, stage: Stage, json: &[u8]) -> Result<Put, StoreError> {
        let key = layout::summary(self.id(), stage)?;
        let bytes = blob::encode_bytes(BlobKind::Summary, json).map_err(|e| self.blob_error(&key, e))?;
        Ok(self.put_into(stage, key, bytes))
    }

    /// Writes the diffuse maps of chunk `chunk` (`values` in row-major `shape`, e.g.
    /// `[texels, 3]`), in the job's encoding.
    pub fn put_diffuse(&self, stage: Stage, chunk: u32, shape: &[u32], values: &[f32]) -> Result<(), StoreError> {
        self.store.put_all(vec![self.diffuse_put(stage, chunk, shape, values)?])
    }

    /// [`Job::put_diffuse`]'s blob, encoded, for [`Store::put_all`].
    pub fn diffuse_put(&self, stage: Stage, chunk: u32, shape: &[u32], values: &[f32]) -> Result<Put, StoreError> {
        let key = layout::diffuse(self.id(), stage, chunk)?;
        self.values_put(stage, key, BlobKind::DiffuseMaps, shape, values)
    }

    /// Writes the directional maps of mirror `surface`, in the job's encoding.
    pub fn put_mirror(&self, stage: Stage, surface: u32, shape: &[u32], values: &[f32]) -> Result<(), StoreError> {
        let key = layout::mirror(self.id(), stage, surface)?;
        self.store.put_all(vec![self.values_put(
            stage,
            key,
            BlobKind::MirrorMaps,
            shape,
            values,
        )?])
    }

    /// Writes tile (`s`, `t`) of direction `dir`, in the job's encoding.
    pub fn put_tile(
        &self,
        stage: Stage,
        dir: u32,
        s: u32,
        t: u32,
        shape: &[u32],
        values: &[f32],
    ) -> Result<(), StoreError> {
        self.store
            .put_all(vec![self.tile_put(stage, dir, s, t, shape, values)?])
    }

    /// [`Job::put_tile`]'s blob, encoded, for [`Store::put_all`].
    pub fn tile_put(
        &self,
        stage: Stage,
        dir: u32,
        s: u32,
        t: u32,
        shape: &[u32],
        values: &[f32],
    ) -> Result<Put, StoreError> {
        let key = layout::tile(self.id(), stage, dir, s, t)?;
        self.values_put(stage, key, BlobKind::TileRadiance, shape, values)
    }

    /// The blob of every mirror slot of direction `dir` (`shape` `[slots, 3]`), in the job's
    /// encoding, for [`Store::put_all`].
    pub fn direction_put(&self, stage: Stage, dir: u32, shape: &[u32], values: &[f32]) -> Result<Put, StoreError> {
        let key = layout::direction(self.id(), stage, dir)?;
        self.values_put(stage, key, BlobKind::DirectionRadiance, shape, values)
    }

    /// Marks iteration `k` finished: its snapshot blobs (at least the resume state) must be
    /// written. Iterations are committed in increasing order; committing a listed one again is a
    /// no-op. Sets the state to propagating iteration `k + 1`.
    pub fn commit_iteration(&mut self, k: u32) -> Result<(), StoreError> {
        if self.manifest.is_finished(k) {
            return Ok(());
        }
        if !matches!(self.manifest.state, JobState::Queued | JobState::Propagating { .. }) {
            return Err(self.error(format!("cannot commit iteration {k}: job is {:?}", self.manifest.state)));
        }
        if let Some(last) = self.last_finished()
            && k < last
        {
            return Err(self.error(format!(
                "cannot commit iteration {k}: iteration {last} is already finished"
            )));
        }
        if !self.store.exists(&layout::state(self.id(), k)?)? {
            return Err(self.error(format!("cannot commit iteration {k}: its resume state is not written")));
        }
        // The snapshot this one supersedes loses what only resuming from it reads if the job
        // compacts ([`Job::resume_only_parts`]). Listed as compacted in the same manifest
        // write, deleted after it (a reader never finds a resumable snapshot without its
        // parts; a crash in between leaves garbage).
        let superseded = match self.last_finished() {
            Some(p) if self.manifest.compact && !self.manifest.compacted.contains(&p) => {
                let parts = self.resume_only_parts(p)?;
                (!parts.is_empty()).then_some((p, parts))
            }
            _ => None,
        };
        let mut manifest = self.manifest.clone();
        manifest.finished_iterations.push(k);
        manifest.state = JobState::Propagating {
            iteration: k.saturating_add(1),
        };
        if let Some((p, _)) = &superseded {
            manifest.compacted.push(*p);
        }
        self.write_manifest(manifest)?;
        if let Some((p, parts)) = superseded
            && let Err(e) = self.store.delete_all(&parts)
        {
            tracing::warn!(job = %self.id(), snapshot = p, error = %e, "compacted snapshot's exact state not all deleted");
        }
        Ok(())
    }

    /// The keys of snapshot `p`'s blobs that only resuming from it reads, which compacting it
    /// deletes ([`Job::commit_iteration`]): what a render reads stays (the summary, the diffuse
    /// maps and the mirror radiance, in the job's encoding).
    ///
    /// - Its mirror shooting maps.
    /// - From store format 6 on, its exact state: the shooting state's head, the diffuse totals
    ///   and, where its mirror radiance is stored as [`MapPart::Radiance`] parts (as many as
    ///   there are batches of exact totals), the exact mirror totals. Most of a mirror job's
    ///   store; most of a diffuse job's snapshots (`f64` per texel, where the diffuse maps a
    ///   render reads are `f16`).
    ///
    /// One listing of the snapshot.
    fn resume_only_parts(&self, p: u32) -> Result<Vec<String>, StoreError> {
        let folder = |part| layout::map_parts(self.id(), p, part);
        let (shooting, totals, radiance) = (
            folder(MapPart::Shooting)?,
            folder(MapPart::Totals)?,
            folder(MapPart::Radiance)?,
        );
        let keys = self
            .store
            .list(&layout::stage_prefix(self.id(), Stage::Iteration(p))?)?;
        let under = |prefix: &str| -> Vec<String> { keys.iter().filter(|k| k.starts_with(prefix)).cloned().collect() };
        let mut parts = under(&shooting);
        if self.manifest.format < 6 {
            return Ok(parts);
        }
        let exact = [layout::state(self.id(), p)?, layout::totals(self.id(), p)?];
        parts.extend(keys.iter().filter(|k| exact.contains(k)).cloned());
        let (totals, radiance) = (under(&totals), under(&radiance));
        if radiance.len() == totals.len() {
            parts.extend(totals);
        }
        Ok(parts)
    }

    /// Of the blobs of `stage` (`names`: keys, or names under the job's prefix as the service
    /// lists them), those a render of it reads. A snapshot's mirror shooting maps (and the
    /// unshot maps of earlier builds) are for resuming only; from store format 6 on, so is its
    /// whole exact state — the head, the diffuse and the exact mirror totals — as a render reads
    /// the mirror radiance in the job's encoding ([`Job::resume_only_parts`]). What a client
    /// fetches to render a running job's last snapshot: a tenth of it for the mirror scene at
    /// l = 2049, N = 128, a twelfth for the Cornell box; and none of what compacting the
    /// snapshot may delete meanwhile.
    pub fn read_by_renders(&self, stage: Stage, mut names: Vec<String>) -> Result<Vec<String>, StoreError> {
        let Stage::Iteration(k) = stage else {
            return Ok(names);
        };
        let job = layout::job_prefix(self.id());
        let under_job = |key: String| key.strip_prefix(&job).map(str::to_string).unwrap_or(key);
        let mut folders = vec![MapPart::Shooting, MapPart::Unshot];
        let mut exact = Vec::new();
        if self.manifest.format >= 6 {
            folders.push(MapPart::Totals);
            exact = vec![
                under_job(layout::state(self.id(), k)?),
                under_job(layout::totals(self.id(), k)?),
            ];
        }
        let folders = (folders.into_iter())
            .map(|part| Ok(under_job(layout::map_parts(self.id(), k, part)?)))
            .collect::<Result<Vec<_>, StoreError>>()?;
        names.retain(|name| {
            let name = name.strip_prefix(&job).unwrap_or(name);
            !(folders.iter().any(|f| name.starts_with(f.as_str())) || exact.iter().any(|e| e == name))
        });
        Ok(names)
    }

    /// Sets whether committing a snapshot compacts the one before ([`Manifest::compact`]).
    pub fn set_compact(&mut self, compact: bool) -> Result<(), StoreError> {
        let mut manifest = self.manifest.clone();
        manifest.compact = compact;
        self.write_manifest(manifest)
    }

    /// Refuses snapshot `k` if it was compacted ([`Manifest::compacted`]): it renders, but does
    /// not resume.
    pub fn check_resumable(&self, k: u32) -> Result<(), StoreError> {
        if self.manifest.compacted.contains(&k) {
            let last = self.last_finished().map_or("none".into(), |l| l.to_string());
            return Err(self.error(format!(
                "snapshot {k} was compacted once a later one was committed: it renders, but only \
                 its radiance is kept, not the state to resume from (the last snapshot, {last}, resumes)"
            )));
        }
        Ok(())
    }

    /// Sets the job's state (e.g. failed, cancelled, or propagating again to resume).
    /// [`JobState::Finished`] commits the final field: write it first.
    pub fn set_state(&mut self, state: JobState) -> Result<(), StoreError> {
        let mut manifest = self.manifest.clone();
        manifest.state = state;
        self.write_manifest(manifest)
    }

    /// Records whether the final field is to be re-sampled (see [`Manifest::resample`]).
    pub fn set_resample(&mut self, resample: bool) -> Result<(), StoreError> {
        let mut manifest = self.manifest.clone();
        manifest.resample = resample;
        self.write_manifest(manifest)
    }

    /// Marks the job finished, committing the final field.
    pub fn finish(&mut self) -> Result<(), StoreError> {
        self.set_state(JobState::Finished)
    }

    /// The scene (caller's serialisation).
    pub fn scene(&self) -> Result<Vec<u8>, StoreError> {
        self.store.get_bytes_blob(&layout::scene(self.id()), BlobKind::Scene)
    }

    /// The resume state of finished iteration `k`.
    pub fn get_state(&self, k: u32) -> Result<Vec<u8>, StoreError> {
        self.check_committed(Stage::Iteration(k))?;
        self.store
            .get_bytes_blob(&layout::state(self.id(), k)?, BlobKind::Snapshot)
    }

    /// The resume state of iteration `k` as written, committed or not (see
    /// `FieldJob::released_shooting_state` for when that is safe).
    pub fn get_released_state(&self, k: u32) -> Result<Vec<u8>, StoreError> {
        self.store
            .get_bytes_blob(&layout::state(self.id(), k)?, BlobKind::Snapshot)
    }

    /// [`Job::get_released_state`], and along with it, in the same round trip, the mirror-map
    /// `parts` that may be wanted next: each one's bytes, or `None` where it cannot be read (it
    /// is then read again when it is wanted, and fails there if it must).
    pub fn get_released_state_and_parts(
        &self,
        k: u32,
        parts: &[(MapPart, usize)],
    ) -> Result<StateAndParts, StoreError> {
        let mut keys = vec![layout::state(self.id(), k)?];
        for &(part, b) in parts {
            keys.push(layout::map_part(self.id(), k, part, b as u32)?);
        }
        let mut read = self.store.get_each(&keys)?.into_iter();
        let state = match read.next() {
            Some(state) => self.decode_snapshot(&keys[0], &state?)?,
            None => unreachable!("the state's key is the first"),
        };
        Ok((state, self.decode_each(&keys[1..], read.collect())))
    }

    /// The mirror-map `parts` of the resume state of iteration `k` written so far, whether or
    /// not the iteration is released: each one's bytes, or `None` where it is not there yet or
    /// cannot be read (see [`Job::get_released_state_and_parts`]). One bulk read.
    pub fn get_written_map_parts(
        &self,
        k: u32,
        parts: &[(MapPart, usize)],
    ) -> Result<Vec<Option<Vec<u8>>>, StoreError> {
        let keys = (parts.iter())
            .map(|&(part, b)| layout::map_part(self.id(), k, part, b as u32))
            .collect::<Result<Vec<_>, _>>()?;
        let read = self.store.get_each(&keys)?;
        Ok(self.decode_each(&keys, read))
    }

    /// The caller's serialisation in each snapshot blob read from `keys`, `None` where it could
    /// not be read or is damaged.
    fn decode_each(&self, keys: &[String], read: Vec<Result<Bytes, StoreError>>) -> Vec<Option<Vec<u8>>> {
        (keys.par_iter().zip(read))
            .map(|(key, bytes)| bytes.ok().and_then(|b| self.decode_snapshot(key, &b).ok()))
            .collect()
    }

    /// The totals half of the resume state of iteration `k` as written, committed or not.
    pub fn get_released_totals(&self, k: u32) -> Result<Vec<u8>, StoreError> {
        self.store
            .get_bytes_blob(&layout::totals(self.id(), k)?, BlobKind::Snapshot)
    }

    /// The totals half of the resume state of finished iteration `k`.
    pub fn get_totals(&self, k: u32) -> Result<Vec<u8>, StoreError> {
        self.check_committed(Stage::Iteration(k))?;
        self.store
            .get_bytes_blob(&layout::totals(self.id(), k)?, BlobKind::Snapshot)
    }

    /// The summary of a committed stage.
    pub fn get_summary(&self, stage: Stage) -> Result<Vec<u8>, StoreError> {
        self.check_committed(stage)?;
        self.store
            .get_bytes_blob(&layout::summary(self.id(), stage)?, BlobKind::Summary)
    }

    /// The diffuse maps of chunk `chunk` of a committed stage: shape and values.
    pub fn get_diffuse(&self, stage: Stage, chunk: u32) -> Result<(Vec<u32>, Vec<f32>), StoreError> {
        self.check_committed(stage)?;
        self.store
            .get_values(&layout::diffuse(self.id(), stage, chunk)?, BlobKind::DiffuseMaps)
    }

    /// The directional maps of mirror `surface` of a committed stage: shape and values.
    pub fn get_mirror(&self, stage: Stage, surface: u32) -> Result<(Vec<u32>, Vec<f32>), StoreError> {
        self.check_committed(stage)?;
        self.store
            .get_values(&layout::mirror(self.id(), stage, surface)?, BlobKind::MirrorMaps)
    }

    /// Tile (`s`, `t`) of direction `dir` of a committed stage: shape and values.
    pub fn get_tile(&self, stage: Stage, dir: u32, s: u32, t: u32) -> Result<(Vec<u32>, Vec<f32>), StoreError> {
        self.check_committed(stage)?;
        self.store
            .get_values(&layout::tile(self.id(), stage, dir, s, t)?, BlobKind::TileRadiance)
    }

    /// The tiles `(s, t)` stored for direction `dir` of a committed stage: one prefix listing.
    pub fn list_tiles(&self, stage: Stage, dir: u32) -> Result<Vec<(u32, u32)>, StoreError> {
        self.check_committed(stage)?;
        let keys = self.store.list(&layout::direction_prefix(self.id(), stage, dir)?)?;
        Ok(keys.iter().filter_map(|k| layout::parse_tile(k)).collect())
    }

    /// `values` (row-major `shape`) encoded in the job's encoding as a blob of `kind` for `key`.
    fn values_put(
        &self,
        stage: Stage,
        key: String,
        kind: BlobKind,
        shape: &[u32],
        values: &[f32],
    ) -> Result<Put, StoreError> {
        let bytes =
            blob::encode_values(kind, self.manifest.encoding, shape, values).map_err(|e| self.blob_error(&key, e))?;
        Ok(self.put_into(stage, key, bytes))
    }

    /// A write into `stage`: create-only into a committed stage, replacing into an uncommitted
    /// one.
    fn put_into(&self, stage: Stage, key: String, bytes: Vec<u8>) -> Put {
        Put {
            key,
            bytes: bytes.into(),
            create_only: self.is_committed(stage),
        }
    }

    fn write_manifest(&mut self, mut manifest: Manifest) -> Result<(), StoreError> {
        manifest.touch();
        manifest.validate().map_err(|reason| self.error(reason))?;
        let bytes = manifest.to_blob().map_err(|reason| self.error(reason))?;
        // The blobs the manifest lists must be durable before it is; then the commit itself.
        self.store.flush()?;
        self.store.put(&layout::manifest(self.id()), bytes)?;
        self.store.flush()?;
        self.manifest = manifest;
        Ok(())
    }

    pub(crate) fn check_committed(&self, stage: Stage) -> Result<(), StoreError> {
        if self.is_committed(stage) {
            return Ok(());
        }
        Err(self.error(match stage {
            Stage::Iteration(k) => {
                format!(
                    "iteration {k} is not finished (finished: {:?})",
                    self.manifest.finished_iterations
                )
            }
            Stage::Field => format!("the final field is not committed (job is {:?})", self.manifest.state),
        }))
    }

    fn error(&self, reason: String) -> StoreError {
        StoreError::Job {
            url: self.store.url().to_string(),
            job: self.id().to_string(),
            reason,
        }
    }

    fn blob_error(&self, key: &str, source: blob::BlobError) -> StoreError {
        StoreError::Blob {
            url: self.store.url().to_string(),
            key: key.to_string(),
            source,
        }
    }
}

/// Reads and validates the manifest of job `id`.
fn read_manifest(store: &Store, id: &JobId) -> Result<Manifest, StoreError> {
    let key = layout::manifest(id);
    let json = store.get_bytes_blob(&key, BlobKind::Manifest)?;
    let invalid = |reason: String| StoreError::Manifest {
        url: store.url().to_string(),
        key: key.clone(),
        reason,
    };
    let manifest = Manifest::from_json(&json).map_err(invalid)?;
    if &manifest.job_id != id {
        return Err(invalid(format!("it belongs to job `{}`", manifest.job_id)));
    }
    Ok(manifest)
}
