//! Light fields in a job: how `vlf-core`'s propagations and fields map onto the keys of
//! [`crate::layout`]. The one module of this crate that knows what a light field is; the rest
//! stores whatever it is given.
//!
//! | what | where | representation |
//! |---|---|---|
//! | the normalised scene | `jobs/J/scene.blob` | `Scene::to_bytes`, exact |
//! | what set-up learns over all directions: the discrete areas `T_t`, the mirrors light reaches | `jobs/J/survey.blob` | `Survey::to_bytes`, exact |
//! | with mirrors: every direction's mirror view and the reflection routes | `jobs/J/mirrors.blob` | `MirrorGeometry` bytes, exact |
//! | the propagation options | the manifest's `parameters` | JSON of `Options` (floats round-trip exactly) |
//! | the checkpoint after K iterations | `jobs/J/iters/KKKKK/state.blob` (the shooting state's head), per batch B of directions `shooting/BBBBB.blob` and `mirror-totals/BBBBB.blob` (its mirror maps), and `totals.blob` (diffuse) | `Propagation::snapshot_bytes`: f64, exact (see below for jobs of earlier builds) |
//! | what a stage is | `S/summary.blob` | JSON [`Summary`] |
//! | outgoing radiance of the charts of diffuse chunk c (`vlf_core::parts`) | `S/diffuse/c.blob` | `[texels, 3]`, the chunk's charts' grids end to end, job encoding |
//! | radiance leaving mirrors along direction d, every tile of it | `field/dirs/d.blob` | `[slots, 3]` in slot order (tile after tile), job encoding |
//!
//! where `S` is a snapshot or the final field.
//!
//! **Snapshots.** Snapshot `K` is the field after `K` iterations; snapshot 0 (emission only) is
//! written when the job is created, so every job can be rendered and resumed from the start. A
//! snapshot holds an exact checkpoint (to resume with the same bits as an uninterrupted run), its
//! summary, and the diffuse radiance in the job's encoding (what a viewer needs, including for
//! ray-traced mirrors). The checkpoint is stored in parts (see
//! `vlf_core::propagate::snapshot`): a worker starting the next iteration reads the shooting
//! state's head and the mirror maps of the batches its lease reads, a viewer the totals. In the
//! distributed service the mirror maps of snapshot K+1 are written by the workers that shot
//! them, the head and diffuse totals by the coordinator. Mirror radiance of a snapshot is read
//! from its checkpoint's mirror totals, by batch of directions: cutting it into tiles after every
//! iteration would write thousands of blobs per iteration (6 000 for the bundled mirror scene at
//! l = 513, N = 64, m = 8) for a state that is superseded by the next one. Those totals are kept
//! twice per batch: exact (`f64`, `mirror-totals/`), for resuming, and as radiance in the job's
//! encoding (`mirror-radiance/`, [`FieldJob::mirror_radiance_put`]), for rendering; compacting a
//! superseded snapshot drops the exact ones, most of a mirror job's store (the mirror scene at
//! l = 2049, N = 128: 53 MB of a 55 MB snapshot). The final field
//! (stage `field`) holds radiance only, mirrors per direction, possibly re-sampled (see
//! `LightField::resample_mirrors`); a viewer fetches the directions whose tiles it needs and
//! cuts the tiles out ([`crate::StageParts`]).
//!
//! **Jobs of earlier builds** still resume and render: their `state.blob` holds the whole
//! checkpoint (the first builds) or a version 2 head whose unshot maps are in `unshot/BBBBB.blob`
//! and whose mirror totals are in `totals.blob` whole; their final fields hold mirror radiance
//! per direction and tile, `field/dirs/d/tile-s-t.blob` (their summaries do not say
//! [`Summary::mirrors_by_direction`]).
//!
//! **Only what is stored is radiance** (and the survey). Directions, subfields, texel grids and
//! mirror views are a deterministic function of the scene and the options, so a reader
//! rebuilds them ([`FieldJob::propagation`], which reads the job's survey rather than passing
//! over every subfield to learn it again) and uses them to put each stored value back in place;
//! a blob whose shape does not match is an error naming its key. A diffuse-only scene has no
//! tile blobs at all.
//!
//! Blobs of a stage are written in parallel; the manifest commit comes last (see [`crate::job`]).

mod finish;

use crate::blob::Encoding;
use crate::error::StoreError;
use crate::id::JobId;
use crate::job::Job;
use crate::layout::MapPart;
use crate::layout::{self, Stage};
use crate::manifest::JobState;
use crate::store::{Put, Store};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use vlf_core::field::LightField;
use vlf_core::maps::TexelAtlas;
use vlf_core::parts::diffuse_chunks;
use vlf_core::propagate::{
    Checkpoint, IterationStats, MapBatch, MapKind, MirrorGeometry, Options, Propagation, ShootingState, StateHead,
    Survey, Totals,
};
use vlf_core::scene::{Rgb, Scene};

/// What a stored stage is: read by renderers and progress reports without the radiance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Iterations the stage's radiance includes.
    pub iterations: u32,
    /// Unshot power left, as a fraction of the emitted power.
    pub unshot_fraction: f64,
    /// Emitted power (VLF-frame units).
    pub emitted: Rgb,
    /// Whether mirror radiance was re-sampled by backward ray tracing.
    pub resampled: bool,
    /// The unit of the stored radiance: a blob value `v` is the radiance `v × radiance_unit`.
    /// The power of two at or above the scene's brightest emitted radiance, so that the compact
    /// encodings (whose range ends at 65 504) hold any scene's radiance and scaling is exact.
    pub radiance_unit: f64,
    /// Statistics of every iteration so far.
    pub stats: Vec<IterationStats>,
    /// The final field's [`LightField::digest`] (SHA-256 of its radiance as propagated, before
    /// the encoding): the same for every run that gives the same field, however it was split.
    /// Only the final field's summary has one; so do only jobs finished by builds that know it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub digest: Option<String>,
    /// Whether the stage's mirror radiance is one blob per direction (`dirs/DDDDD.blob`, a final
    /// field of this build), rather than one per tile (`dirs/DDDDD/tile-SSSS-TTTT.blob`, a
    /// final field of an earlier build) or the snapshot's mirror totals (an iteration's stage).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub mirrors_by_direction: bool,
    /// Whether a snapshot's mirror radiance is read from its [`MapPart::Radiance`] parts, in the
    /// job's encoding (this build's snapshots; a scene without mirrors has none), rather than
    /// from its exact mirror totals (snapshots of earlier builds).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub mirror_radiance_by_batch: bool,
}

impl Summary {
    /// The summary of a committed stage of `job`, without decoding the job's scene (what a
    /// listing of a store's jobs reads).
    pub fn read(job: &Job, stage: Stage) -> Result<Summary, StoreError> {
        let json = job.get_summary(stage)?;
        serde_json::from_slice(&json).map_err(|e| StoreError::Field {
            url: job.store().url().to_string(),
            job: job.id().to_string(),
            source: vlf_core::Error::Decode(format!("summary of {stage:?}: {e}")),
        })
    }
}

/// A light-field job in a store: its [`Job`] plus the scene and options it propagates.
#[derive(Debug, Clone)]
pub struct FieldJob {
    job: Job,
    scene: Scene,
    options: Options,
}

/// Whether a mirror of `scene` is a plane of several polygons, whose mirror slots builds before
/// store format 5 laid out per polygon (see [`crate::manifest::MANIFEST_FORMAT`]).
fn has_tessellated_mirror(scene: &Scene, options: &Options) -> bool {
    let mirrors = (0..scene.surfaces.len())
        .filter(|&s| scene.material(s).is_mirror())
        .count();
    if mirrors < 2 {
        return false;
    }
    let (_, plane_rep) = vlf_core::maps::charts::segment_with_planes(scene, options.texel_size());
    (plane_rep.iter().enumerate()).any(|(s, &rep)| rep as usize != s && scene.material(s).is_mirror())
}

impl FieldJob {
    /// Creates a job for the fresh propagation `p` (no iteration done yet) and writes its
    /// snapshot 0. Radiance blobs use `encoding`.
    pub fn create(store: &Store, p: &Propagation, encoding: Encoding) -> Result<FieldJob, StoreError> {
        let mut job = FieldJob::describe(store, &p.scene, &p.options, encoding)?;
        job.set_up(p)?;
        Ok(job)
    }

    /// Creates a job for `scene` with `options`, not set up yet: its manifest (queued, no
    /// snapshot) and scene only. What a coordinator stores when a job is submitted, so that the
    /// submission is answered at once; setting the job up — its geometry and survey, which take
    /// minutes for a large scan at the big settings — comes after ([`FieldJob::set_up`]), and a
    /// coordinator that stops in between sets it up again when it takes the job up.
    pub fn describe(
        store: &Store,
        scene: &Scene,
        options: &Options,
        encoding: Encoding,
    ) -> Result<FieldJob, StoreError> {
        options.validate().map_err(|e| StoreError::Field {
            url: store.url().to_string(),
            job: String::new(),
            source: e,
        })?;
        let parameters = serde_json::to_value(options).map_err(|e| StoreError::Layout(e.to_string()))?;
        let job = Job::create(store, &scene.to_bytes(), &scene.content_hash(), parameters, encoding)?;
        Ok(FieldJob {
            job,
            scene: scene.clone(),
            options: options.clone(),
        })
    }

    /// Whether the job is set up: its snapshot 0 is written ([`FieldJob::set_up`]).
    pub fn is_set_up(&self) -> bool {
        self.job.manifest().is_finished(0)
    }

    /// Sets up a job [described](FieldJob::describe) but not set up yet from `p`, its fresh
    /// propagation: stores the survey and, with mirrors, their geometry, then writes snapshot 0
    /// (which workers wait for, so they find both).
    pub fn set_up(&mut self, p: &Propagation) -> Result<(), StoreError> {
        if (p.scene.content_hash(), &p.options) != (self.scene.content_hash(), &self.options) {
            return Err(self.job_error("set up from a propagation of another scene or options".into()));
        }
        self.job.put_survey(&p.survey().to_bytes())?;
        let started = std::time::Instant::now();
        if let Some(geometry) = p.mirror_geometry_ref() {
            let len = geometry.serialized_len();
            self.job.put_mirror_geometry_with(len, |w| geometry.write_to(w))?;
            tracing::debug!(
                job = %self.id(),
                mb = format!("{:.1}", len as f64 / 1e6),
                seconds = format!("{:.3}", started.elapsed().as_secs_f64()),
                "mirror geometry stored"
            );
        }
        self.write_snapshot(p)
    }

    /// The job's stored survey, written when the job was created (what set-up learnt over all
    /// its directions, which whoever opens the job later reads rather than learning it again);
    /// `None` for a job stored before surveys were, or with one of an earlier layout
    /// (`Survey::read_stored`), or created by a coordinator that stopped before writing it: its
    /// geometry is then built whole. A survey that is there but unreadable is an error, not a
    /// reason to learn it again.
    pub fn stored_survey(&self) -> Result<Option<Survey>, StoreError> {
        let Some(bytes) = self.job.survey()? else {
            return Ok(None);
        };
        Survey::read_stored(&bytes).map_err(|e| {
            let key = layout::survey(self.id());
            self.field_error(vlf_core::Error::Decode(format!("`{key}`: {e}")))
        })
    }

    /// The job's stored mirror geometry, written when it was set up (every direction's mirror
    /// view and the reflection routes, which whoever opens the job reads rather than computes);
    /// `None` for a job without mirrors, or stored before the geometry was. One that is there
    /// but unreadable is an error, not a reason to compute it again.
    pub fn stored_mirror_geometry(&self) -> Result<Option<MirrorGeometry>, StoreError> {
        // Deserialised as it is decompressed: the payload is never held whole.
        let Some(read) = self
            .job
            .mirror_geometry_with(|r, len| MirrorGeometry::read_from(r, len))?
        else {
            return Ok(None);
        };
        read.map(Some).map_err(|e| {
            let key = layout::mirror_geometry(self.id());
            self.field_error(vlf_core::Error::Decode(format!("`{key}`: {e}")))
        })
    }

    /// The job's propagation at snapshot 0 — its geometry, holding at most `budget` bytes of
    /// subfields when one is given ([`Propagation::with_subfield_budget`]). With the job's
    /// [stored survey](FieldJob::stored_survey) no subfield is built up front
    /// ([`Propagation::with_survey`]): a worker builds those of the directions it shoots; with
    /// its [stored mirror geometry](FieldJob::stored_mirror_geometry) too, no mirror is
    /// rasterised either ([`Propagation::with_stored`]). The geometry is the job's to the bit,
    /// whoever builds it.
    pub fn propagation(&self, budget: Option<usize>) -> Result<Propagation, StoreError> {
        let (scene, options) = (self.scene.clone(), self.options.clone());
        let Some(survey) = self.stored_survey()? else {
            return Propagation::with_subfield_budget(scene, options, budget).map_err(|e| self.field_error(e));
        };
        // A job whose survey maps no mirror has no geometry to ask the store for.
        let stored = if survey.lit_mirrors.is_empty() {
            None
        } else {
            self.stored_mirror_geometry()?
        };
        let p = match stored {
            Some(mirrors) => Propagation::with_stored(scene, options, budget, survey, mirrors),
            None => Propagation::with_survey(scene, options, budget, survey),
        };
        // A misfit names the blob whose check refused it.
        p.map_err(|e| match e {
            vlf_core::Error::Decode(m) => {
                let key = if m.starts_with("the mirror geometry") {
                    layout::mirror_geometry(self.id())
                } else {
                    layout::survey(self.id())
                };
                vlf_core::Error::Decode(format!("`{key}`: {m}"))
            }
            e => e,
        })
        .map_err(|e| self.field_error(e))
    }

    /// Opens job `id`, reading its manifest, scene and options.
    pub fn open(store: &Store, id: &JobId) -> Result<FieldJob, StoreError> {
        let job = Job::open(store, id)?;
        let field_error = |source| StoreError::Field {
            url: store.url().to_string(),
            job: id.to_string(),
            source,
        };
        let scene = Scene::from_bytes(&job.scene()?).map_err(field_error)?;
        // Parameters that fix the bits and were added as options read, where absent, as what
        // jobs were before (see `MANIFEST_FORMAT`): the cut of a pass as 16 batches (format 3),
        // a stint as one direction (formats 3 to 6). From the format that added one, it must be
        // named.
        let named = |format, key: &str, what: &str| match job.manifest().format >= format
            && job.manifest().parameters.get(key).is_none()
        {
            true => Err(field_error(vlf_core::Error::Decode(format!(
                "the job's parameters do not say {what} ({key})"
            )))),
            false => Ok(()),
        };
        named(4, "pass_batches", "how many batches a pass is cut into")?;
        named(7, "stint_directions", "how many directions a stint holds")?;
        let options: Options = serde_json::from_value(job.manifest().parameters.clone()).map_err(|e| {
            field_error(vlf_core::Error::Decode(format!(
                "the job's parameters are not propagation options: {e}"
            )))
        })?;
        options.validate().map_err(field_error)?;
        if scene.content_hash() != job.manifest().scene_hash {
            return Err(field_error(vlf_core::Error::Decode(
                "the stored scene does not match the manifest's scene hash".into(),
            )));
        }
        if job.manifest().format < 5 && has_tessellated_mirror(&scene, &options) {
            return Err(field_error(vlf_core::Error::Decode(format!(
                "the job was made by an older version of vlf (store format {}): its scene has a \
                 mirror of several polygons, whose maps that version laid out per polygon (this \
                 version: per mirror plane); propagate the scene again",
                job.manifest().format
            ))));
        }
        Ok(FieldJob { job, scene, options })
    }

    pub fn id(&self) -> &JobId {
        self.job.id()
    }

    pub fn job(&self) -> &Job {
        &self.job
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn options(&self) -> &Options {
        &self.options
    }

    /// Reads the manifest again (another process may have moved on).
    pub fn reload(&mut self) -> Result<(), StoreError> {
        self.job.reload()
    }

    /// The stage a renderer should show by default: the final field of a finished job, else the
    /// last finished snapshot; `None` while no snapshot is finished (a job queued, or failed
    /// before its set-up was written).
    pub fn latest_stage(&self) -> Option<Stage> {
        match (&self.job.manifest().state, self.job.last_finished()) {
            (JobState::Finished, _) => Some(Stage::Field),
            (_, None) => None,
            (_, Some(k)) => Some(Stage::Iteration(k)),
        }
    }

    /// Writes the snapshot after `p.iterations_done()` iterations and commits it: the shooting
    /// state first, then the totals, the diffuse maps and the summary, then the manifest.
    pub fn write_snapshot(&mut self, p: &Propagation) -> Result<(), StoreError> {
        let committed = self.release_snapshot(p, true)?.commit()?;
        self.adopt_commit(committed);
        Ok(())
    }

    /// Writes the part of the snapshot after `p.iterations_done()` iterations that the next
    /// iteration's workers read — its shooting state's head and, with `maps`, every mirror map —
    /// and returns the rest to write and commit. A coordinator hands out the next iteration's
    /// leases in between (see [`PendingSnapshot`]); its workers wrote the mirror maps already
    /// (`Replica::compute`), unless the iteration left them as they were.
    pub fn release_snapshot(&self, p: &Propagation, maps: bool) -> Result<PendingSnapshot, StoreError> {
        let encoded = self.encode_snapshot(p, maps)?;
        let store = self.job.store();
        store.put_all(encoded.maps)?;
        // The head last: once it is there, the state is complete.
        store.put_all(vec![encoded.head])?;
        Ok(encoded.rest)
    }

    /// The snapshot after `p.iterations_done()` iterations, serialised and encoded on this
    /// thread's pool: what [`FieldJob::release_snapshot`] writes at once and
    /// [`crate::SnapshotWriter`] while the propagation goes on. Holds the whole snapshot as
    /// stored (the mirror scene at l = 2049, N = 128: 78 MB).
    pub(crate) fn encode_snapshot(&self, p: &Propagation, maps: bool) -> Result<EncodedSnapshot, StoreError> {
        let k = p.iterations_done();
        if self.job.manifest().is_finished(k) {
            return Err(self.job_error(format!("snapshot {k} is already finished")));
        }
        // Each batch's maps compressed as they are serialised, not all serialised first.
        let batches = if maps && p.specular.is_some() {
            p.batching().count()
        } else {
            0
        };
        let maps = (0..batches)
            .into_par_iter()
            .flat_map_iter(|b| {
                let put = move |part: MapPart, kind: MapKind| {
                    self.job.map_part_put(k, part, b as u32, &p.map_batch_bytes(b, kind))
                };
                [
                    put(MapPart::Shooting, MapKind::Shooting),
                    put(MapPart::Totals, MapKind::Totals),
                    self.mirror_radiance_put(k, b as u32, &p.mirror_totals_of_batch(b)),
                ]
            })
            .collect::<Result<Vec<_>, _>>()?;
        // The head compressed as it is serialised (`Propagation::write_head_to`), beside the
        // diffuse totals.
        let (head, totals) = rayon::join(
            || self.job.state_put_with(k, p.head_len(), |w| p.write_head_to(w)),
            || p.totals_bytes(),
        );
        let head = head?;
        let unit = radiance_unit(&self.scene);
        let rest = PendingSnapshot {
            job: self.job.clone(),
            k,
            totals,
            atlas: p.atlas.clone(),
            diffuse: p.diffuse_radiance(),
            summary: Summary {
                iterations: k,
                unshot_fraction: p.unshot_fraction(),
                emitted: p.emitted,
                resampled: false,
                radiance_unit: unit,
                stats: p.stats.clone(),
                digest: None,
                mirrors_by_direction: false,
                // Written with the maps by whoever wrote them (none without mirrors), in a job
                // of format 6 on: no build that writes none opens one. A job of an earlier
                // format, resumed by this build, may have blocks from workers of an earlier build.
                mirror_radiance_by_batch: self.job.manifest().format >= 6,
            },
        };
        Ok(EncodedSnapshot { maps, head, rest })
    }

    /// Takes the manifest a [`PendingSnapshot::commit`] of this job wrote. Nothing else may write
    /// this job's manifest while a snapshot is pending (the commit would be forgotten).
    pub fn adopt_commit(&mut self, committed: Job) {
        debug_assert_eq!(committed.id(), self.job.id(), "a commit of another job");
        self.job = committed;
    }

    /// Marks the job failed with `message` (the blobs written so far stay readable).
    pub fn fail(&mut self, message: String) -> Result<(), StoreError> {
        self.set_state(JobState::Failed { message })
    }

    /// Sets whether committing a snapshot deletes what only resuming reads of the one before
    /// (see [`crate::Manifest::compact`]).
    pub fn set_compact(&mut self, compact: bool) -> Result<(), StoreError> {
        self.job.set_compact(compact)
    }

    /// Records whether the final field is to be re-sampled (see [`crate::Manifest::resample`]).
    pub fn set_resample(&mut self, resample: bool) -> Result<(), StoreError> {
        self.job.set_resample(resample)
    }

    /// Sets the job's state (see [`Job::set_state`]).
    pub fn set_state(&mut self, state: JobState) -> Result<(), StoreError> {
        self.job.set_state(state)
    }

    /// The propagation as it stood after the last finished snapshot, ready to step on with the
    /// same bits as a run that never stopped. A finished job cannot be resumed.
    pub fn resume(&mut self) -> Result<Propagation, StoreError> {
        self.resume_within(None)
    }

    /// [`FieldJob::resume`], holding at most `budget` bytes of subfields when one is given
    /// ([`Propagation::with_subfield_budget`]).
    pub fn resume_within(&mut self, budget: Option<usize>) -> Result<Propagation, StoreError> {
        let k = self.snapshot_to_resume()?;
        let checkpoint = self.checkpoint(k)?;
        let mut p = self.propagation(budget)?;
        p.restore(checkpoint).map_err(|e| self.field_error(e))?;
        self.job.set_state(JobState::Propagating { iteration: k + 1 })?;
        Ok(p)
    }

    /// [`FieldJob::resume_within`] for a coordinator, whose workers hold the mirror maps: the
    /// propagation at the last finished snapshot without them
    /// ([`Propagation::restore_without_maps`]: the snapshot's head and diffuse totals, none of
    /// its map parts read). They are zeros until an iteration shoots them, and elsewhere after
    /// ([`vlf_core::propagate::Specular::holds_all`] says which). A snapshot of an earlier
    /// build, whose maps are not stored by batch, is restored whole.
    pub fn resume_without_maps(&mut self, budget: Option<usize>) -> Result<Propagation, StoreError> {
        let k = self.snapshot_to_resume()?;
        self.job.check_committed(Stage::Iteration(k))?;
        self.job.check_resumable(k)?;
        let mut p = self.propagation(budget)?;
        match self.released_state(k)? {
            ReleasedState::Head(head) if head.mirror_totals_by_batch() => {
                self.of_snapshot(k, head.iterations())?;
                let totals = self.decode_totals(k, &self.job.get_released_totals(k)?)?;
                p.restore_without_maps(head, totals.total)
                    .map_err(|e| self.field_error(e))?;
            }
            released => {
                let checkpoint = self.released_checkpoint(k, released)?;
                p.restore(checkpoint).map_err(|e| self.field_error(e))?;
            }
        }
        self.job.set_state(JobState::Propagating { iteration: k + 1 })?;
        Ok(p)
    }

    /// The last finished snapshot, which resuming starts from; an error for a finished job, or
    /// one with no snapshot yet.
    fn snapshot_to_resume(&self) -> Result<u32, StoreError> {
        if self.job.manifest().state == JobState::Finished {
            return Err(self.job_error("the job is finished; nothing to resume".into()));
        }
        self.job
            .last_finished()
            .ok_or_else(|| self.job_error("no finished snapshot to resume from".into()))
    }

    /// The exact checkpoint of finished snapshot `k`: its parts joined (or the whole checkpoint
    /// of a job of the first builds).
    pub fn checkpoint(&self, k: u32) -> Result<Checkpoint, StoreError> {
        self.job.check_committed(Stage::Iteration(k))?;
        self.job.check_resumable(k)?;
        self.released_checkpoint(k, self.released_state(k)?)
    }

    /// The exact checkpoint of snapshot `k` from what [`FieldJob::released_state`] read, once
    /// the iteration after it is released.
    pub fn released_checkpoint(&self, k: u32, released: ReleasedState) -> Result<Checkpoint, StoreError> {
        let checkpoint = match released {
            ReleasedState::Whole(bytes) => Checkpoint::from_bytes(&bytes).map_err(|e| self.field_error(e))?,
            ReleasedState::Head(head) => {
                let by_batch = head.mirror_totals_by_batch();
                let all = self.head_batches(k, &head)?;
                let state = self.assemble(k, head)?;
                let mut totals = self.decode_totals(k, &self.job.get_released_totals(k)?)?;
                if by_batch {
                    let batches = self.released_maps(k, MapPart::Totals, &all)?;
                    totals = totals.with_mirror_batches(batches).map_err(|e| self.field_error(e))?;
                }
                Checkpoint::join(state, totals).map_err(|e| self.field_error(e))?
            }
        };
        self.of_snapshot(k, checkpoint.iterations())?;
        Ok(checkpoint)
    }

    /// What shooting the iteration after finished snapshot `k` reads: half of its checkpoint.
    pub fn shooting_state(&self, k: u32) -> Result<ShootingState, StoreError> {
        self.job.check_committed(Stage::Iteration(k))?;
        self.job.check_resumable(k)?;
        self.released_shooting_state(k)
    }

    /// The whole shooting state of snapshot `k` once the iteration after it is released (see
    /// [`FieldJob::released_state`]).
    pub fn released_shooting_state(&self, k: u32) -> Result<ShootingState, StoreError> {
        let state = match self.released_state(k)? {
            ReleasedState::Whole(bytes) => {
                Checkpoint::from_bytes(&bytes)
                    .map_err(|e| self.field_error(e))?
                    .split()
                    .0
            }
            ReleasedState::Head(head) => self.assemble(k, head)?,
        };
        self.of_snapshot(k, state.iterations())?;
        Ok(state)
    }

    /// The head of snapshot `k`'s shooting state once the iteration after it is released,
    /// whether or not the snapshot is committed yet: what every worker of that iteration reads
    /// (see [`PendingSnapshot`]; any state stored for `k` is the one, as it is a pure function of
    /// the job). A job of the first builds has its whole checkpoint there instead.
    pub fn released_state(&self, k: u32) -> Result<ReleasedState, StoreError> {
        let bytes = self.job.get_released_state(k)?;
        self.state_of(k, bytes)
    }

    /// [`FieldJob::released_state`], and in the same round trip the mirror maps `parts` that
    /// may be wanted next ([`Job::get_released_state_and_parts`]): those that could be read and
    /// decoded, with their part and batch.
    pub fn released_state_and_maps(
        &self,
        k: u32,
        parts: &[(MapPart, usize)],
    ) -> Result<(ReleasedState, Vec<(MapPart, MapBatch)>), StoreError> {
        let (state, stored) = self.job.get_released_state_and_parts(k, parts)?;
        Ok((self.state_of(k, state)?, self.decoded_parts(k, parts, stored)))
    }

    /// The mirror maps `parts` of snapshot `k` written so far, before the iteration after it is
    /// released ([`Job::get_written_map_parts`]): those that could be read and decoded, with
    /// their part and batch. What a worker reads ahead while the coordinator ends the iteration
    /// before (see [`crate::ReadAhead`]).
    pub fn written_maps(&self, k: u32, parts: &[(MapPart, usize)]) -> Result<Vec<(MapPart, MapBatch)>, StoreError> {
        let stored = self.job.get_written_map_parts(k, parts)?;
        Ok(self.decoded_parts(k, parts, stored))
    }

    /// The parts of `stored` (read for `parts` of snapshot `k`) that are there and decode.
    fn decoded_parts(
        &self,
        k: u32,
        parts: &[(MapPart, usize)],
        stored: Vec<Option<Vec<u8>>>,
    ) -> Vec<(MapPart, MapBatch)> {
        (parts.par_iter().zip(stored))
            .filter_map(|(&(part, b), bytes)| Some((part, self.decode_map_part(k, b, &bytes?).ok()?)))
            .collect()
    }

    /// The released state of snapshot `k` from its stored bytes.
    fn state_of(&self, k: u32, bytes: Vec<u8>) -> Result<ReleasedState, StoreError> {
        if !Checkpoint::is_split(&bytes) {
            return Ok(ReleasedState::Whole(bytes));
        }
        let head = StateHead::from_bytes(&bytes).map_err(|e| self.field_error(e))?;
        self.of_snapshot(k, head.iterations())?;
        Ok(ReleasedState::Head(head))
    }

    /// Mirror maps `part` of `batches` of snapshot `k`'s directions, read in parallel, once the
    /// iteration after it is released: what a lease that shoots or gathers from those directions
    /// reads.
    pub fn released_maps(&self, k: u32, part: MapPart, batches: &[usize]) -> Result<Vec<MapBatch>, StoreError> {
        let parts: Vec<(MapPart, usize)> = batches.iter().map(|&b| (part, b)).collect();
        self.released_map_parts(k, &parts)
    }

    /// [`FieldJob::released_maps`] of several parts at once: one bulk read (see
    /// [`Store::get_all`]), in the order of `parts`.
    pub fn released_map_parts(&self, k: u32, parts: &[(MapPart, usize)]) -> Result<Vec<MapBatch>, StoreError> {
        let stored = self.job.get_released_map_parts(k, parts)?;
        (parts.par_iter().zip(&stored))
            .map(|(&(_, b), bytes)| self.decode_map_part(k, b, bytes))
            .collect()
    }

    /// A batch of mirror maps of snapshot `k` from the contents of its blob, checked to be of
    /// that snapshot and batch.
    pub(crate) fn decode_map_part(&self, k: u32, batch: usize, bytes: &[u8]) -> Result<MapBatch, StoreError> {
        let part = MapBatch::from_bytes(bytes).map_err(|e| self.field_error(e))?;
        self.of_snapshot(k, part.iterations)?;
        if part.batch as usize != batch {
            return Err(self.field_error(vlf_core::Error::Decode(format!(
                "mirror maps of batch {} stored as batch {batch} of snapshot {k}",
                part.batch
            ))));
        }
        Ok(part)
    }

    /// The batches of mirror maps that snapshot `k`'s head says were stored: none, or every
    /// batch of the job's passes. Any other count is damage, refused before a batch is listed
    /// (a head claiming 2³² − 1 batches would otherwise allocate and fetch them all).
    fn head_batches(&self, k: u32, head: &StateHead) -> Result<Vec<usize>, StoreError> {
        let count = self.options().batching().count();
        match head.mirror_batches {
            None => Ok(Vec::new()),
            Some(b) if b as usize == count => Ok((0..count).collect()),
            Some(b) => Err(self.field_error(vlf_core::Error::Decode(format!(
                "the head of snapshot {k} names {b} batches of mirror maps, where the job's passes have {count}"
            )))),
        }
    }

    /// A whole shooting state from its head and every batch of shooting (or, in a job of an
    /// earlier build, unshot) maps.
    fn assemble(&self, k: u32, head: StateHead) -> Result<ShootingState, StoreError> {
        let all = self.head_batches(k, &head)?;
        let part = if head.mirror_totals_by_batch() {
            MapPart::Shooting
        } else {
            MapPart::Unshot
        };
        let batches = self.released_maps(k, part, &all)?;
        ShootingState::from_parts(head, batches).map_err(|e| self.field_error(e))
    }

    /// The totals of snapshot `k` from the contents of the blob that holds them (its
    /// `totals.blob`, or the whole checkpoint in `state.blob` of a job of the first builds):
    /// without the mirror totals where they are stored by batch.
    pub(crate) fn decode_totals(&self, k: u32, bytes: &[u8]) -> Result<Totals, StoreError> {
        let totals = Totals::from_bytes(bytes).map_err(|e| self.field_error(e))?;
        self.of_snapshot(k, totals.iterations)?;
        Ok(totals)
    }

    /// Refuses state of snapshot `k` that holds `iterations` iterations.
    fn of_snapshot(&self, k: u32, iterations: u32) -> Result<(), StoreError> {
        if iterations == k {
            Ok(())
        } else {
            Err(self.field_error(vlf_core::Error::Decode(format!(
                "checkpoint of snapshot {k} holds {iterations} iterations"
            ))))
        }
    }

    /// The summary of a committed stage.
    pub fn summary(&self, stage: Stage) -> Result<Summary, StoreError> {
        Summary::read(&self.job, stage)
    }

    /// Reads a committed stage back into a field that renders like the one written (up to the
    /// job's encoding).
    pub fn load(&self, stage: Stage) -> Result<LightField, StoreError> {
        Ok(self.load_parts(stage, None)?.0)
    }

    /// Bytes the store holds for `stage` (its blobs as stored, compressed) and for the whole job.
    pub fn stored_bytes(&self, stage: Stage) -> Result<(u64, u64), StoreError> {
        let store = self.job.store();
        let sum = |prefix: &str| -> Result<u64, StoreError> {
            Ok(store.list_sizes(prefix)?.iter().map(|(_, size)| size).sum())
        };
        Ok((
            sum(&layout::stage_prefix(self.id(), stage)?)?,
            sum(&layout::job_prefix(self.id()))?,
        ))
    }

    fn write_summary(&self, stage: Stage, summary: &Summary) -> Result<(), StoreError> {
        let json = serde_json::to_vec_pretty(summary).map_err(|e| self.job_error(format!("summary: {e}")))?;
        self.job.put_summary(stage, &json)
    }

    /// A blob whose shape does not fit the rebuilt geometry: an error naming its key.
    pub(crate) fn check_shape(
        &self,
        shape: &[u32],
        expected: &[u32],
        key: impl FnOnce() -> Result<String, StoreError>,
    ) -> Result<(), StoreError> {
        if shape == expected {
            return Ok(());
        }
        Err(self.field_error(vlf_core::Error::Decode(format!(
            "`{}` has shape {shape:?}, the field needs {expected:?}",
            key()?
        ))))
    }

    fn job_error(&self, reason: String) -> StoreError {
        StoreError::Job {
            url: self.job.store().url().to_string(),
            job: self.id().to_string(),
            reason,
        }
    }

    pub(crate) fn field_error(&self, source: vlf_core::Error) -> StoreError {
        StoreError::Field {
            url: self.job.store().url().to_string(),
            job: self.id().to_string(),
            source,
        }
    }
}

/// Radiance values divided by the stored unit, flattened.
pub(crate) fn scaled(v: &[[f32; 3]], unit: f64) -> Vec<f32> {
    let scale = (1.0 / unit) as f32;
    v.as_flattened().iter().map(|&x| x * scale).collect()
}

impl FieldJob {
    /// The [`MapPart::Radiance`] blob of batch `batch` of snapshot `k`: the total maps `totals`
    /// of the batch's directions, in order, one after the other, as radiance in the job's
    /// encoding (shape `[slots, 3]`, the batch's slots). Written next to the exact totals by
    /// whoever writes those (a worker, as it shoots the batch; the in-process run with its
    /// snapshot), create-only as they are: a pure function of the job.
    ///
    /// Why a second copy: the exact `f64` totals are what resuming from `k` reads, and only the
    /// last snapshot of a compacting job resumes; a render needs the job's encoding only (a
    /// final field's mirror radiance is stored so). Once `k` is superseded its exact totals are
    /// deleted with the rest of its exact state ([`Job::commit_iteration`]), leaving a seventh of
    /// the bytes in `f16`; and every snapshot renders from these, so it renders the same bits
    /// before and after it is compacted. Rounded to `f32` and scaled as the final field's mirror
    /// radiance is, so that the last snapshot's mirrors are the field's to the bit.
    pub fn mirror_radiance_put(&self, k: u32, batch: u32, totals: &[impl AsRef<[Rgb]>]) -> Result<Put, StoreError> {
        let scale = (1.0 / radiance_unit(&self.scene)) as f32;
        let values: Vec<f32> = (totals.iter().flat_map(|d| d.as_ref().iter()))
            .flat_map(|t| t.map(|c| c as f32 * scale))
            .collect();
        let slots = (values.len() / 3) as u32;
        self.job.mirror_radiance_put(k, batch, &[slots, 3], &values)
    }
}

/// Writes every chunk of diffuse maps of `stage`, in parallel.
pub(crate) fn write_diffuse(
    job: &Job,
    stage: Stage,
    atlas: &TexelAtlas,
    radiance: &[[f32; 3]],
    unit: f64,
) -> Result<(), StoreError> {
    let chunks: Vec<_> = diffuse_chunks(atlas).into_iter().enumerate().collect();
    job.put_encoded(&chunks, |(c, (_, texels))| {
        diffuse_put(job, stage, *c, texels.clone(), radiance, unit)
    })
}

/// The blob of diffuse chunk `c`, whose texels `texels` are in `radiance`.
fn diffuse_put(
    job: &Job,
    stage: Stage,
    c: usize,
    texels: std::ops::Range<usize>,
    radiance: &[[f32; 3]],
    unit: f64,
) -> Result<Put, StoreError> {
    let values = scaled(&radiance[texels.clone()], unit);
    job.diffuse_put(stage, c as u32, &[texels.len() as u32, 3], &values)
}

/// The shooting state of a released snapshot as stored ([`FieldJob::released_state`]).
pub enum ReleasedState {
    /// Its head; the mirror maps are read by batch ([`FieldJob::released_maps`]).
    Head(StateHead),
    /// The whole checkpoint's bytes (a job of the first builds).
    Whole(Vec<u8>),
}

/// A snapshot serialised and encoded, not written yet ([`FieldJob::encode_snapshot`]): its
/// mirror maps, then its head, then the rest, in that order.
pub(crate) struct EncodedSnapshot {
    pub(crate) maps: Vec<Put>,
    pub(crate) head: Put,
    pub(crate) rest: PendingSnapshot,
}

/// A snapshot released to the next iteration but not committed yet
/// ([`FieldJob::release_snapshot`]): its shooting state — all that the next iteration's workers
/// read — is written; its totals, diffuse maps and summary, and the commit, are still to be done.
/// The coordinator of the distributed service hands out the next iteration's leases in between,
/// so workers do not wait for what only resuming and viewing need (nor, on a disk, for the
/// commit's syncs).
///
/// Until it is committed the snapshot is not listed: readers see the previous one, and a
/// coordinator that stops resumes from the previous one and writes the same shooting state again
/// (a pure function of the previous snapshot and the scene), so the blocks workers computed from
/// the released state are the ones it would have them compute.
pub struct PendingSnapshot {
    job: Job,
    k: u32,
    totals: Vec<u8>,
    atlas: TexelAtlas,
    diffuse: Vec<[f32; 3]>,
    summary: Summary,
}

impl PendingSnapshot {
    /// The snapshot's number: iterations done.
    pub fn iteration(&self) -> u32 {
        self.k
    }

    /// Writes the rest of the snapshot and commits it; returns the job with the manifest that
    /// lists it, for [`FieldJob::adopt_commit`].
    /// Its blobs go in one bulk write (their requests overlapping), the manifest that lists
    /// them after.
    pub fn commit(mut self) -> Result<Job, StoreError> {
        let stage = Stage::Iteration(self.k);
        let json = serde_json::to_vec_pretty(&self.summary)
            .map_err(|e| StoreError::Layout(format!("summary of snapshot {}: {e}", self.k)))?;
        // Mirror radiance of a snapshot lives in its checkpoint's totals (see the module docs).
        enum Blob {
            Totals,
            Summary,
            Chunk(usize, std::ops::Range<usize>),
        }
        let blobs: Vec<Blob> = [Blob::Totals, Blob::Summary]
            .into_iter()
            .chain((diffuse_chunks(&self.atlas).into_iter().enumerate()).map(|(c, (_, texels))| Blob::Chunk(c, texels)))
            .collect();
        let unit = self.summary.radiance_unit;
        self.job.put_encoded(&blobs, |blob| match blob {
            Blob::Totals => self.job.totals_put(self.k, &self.totals),
            Blob::Summary => self.job.summary_put(stage, &json),
            Blob::Chunk(c, texels) => diffuse_put(&self.job, stage, *c, texels.clone(), &self.diffuse, unit),
        })?;
        self.job.commit_iteration(self.k)?;
        Ok(self.job)
    }
}

/// The power of two at or above the scene's brightest emitted radiance (see
/// [`Summary::radiance_unit`]); 1 for a scene without emission.
pub fn radiance_unit(scene: &Scene) -> f64 {
    let brightest = scene.materials.iter().flat_map(|m| m.emission).fold(0.0f64, f64::max);
    if brightest > 0.0 && brightest.is_finite() {
        2f64.powi(brightest.log2().ceil().clamp(-120.0, 120.0) as i32)
    } else {
        1.0
    }
}
