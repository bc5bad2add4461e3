//! Reading a stage part by part (`vlf_core::parts`): what a viewer streams, and what
//! [`FieldJob::load_parts`] is built on.
//!
//! A stage stores its diffuse maps one blob per chunk (a part). Its mirror radiance is in blobs
//! that hold many tiles: a final field's, one blob per direction; a snapshot's, its checkpoint's
//! mirror totals, one blob per batch of directions (see [`crate::field`]; in jobs of earlier
//! builds, one blob for all). The first tile asked for of a direction (a batch) reads its blob,
//! and its tiles are cut from it from then on. Final fields of earlier builds stored one blob
//! per tile, which are read as such.

use crate::blob::{self, BlobKind};
use crate::error::StoreError;
use crate::field::{FieldJob, Summary};
use crate::layout::{self, MapPart, Stage};
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use vlf_core::field::LightField;
use vlf_core::parts::{Part, PartCatalog};

/// Mirror radiance per direction (one, those of a batch, or all) and slot.
type MirrorTotals = Vec<Vec<[f32; 3]>>;

/// Where a stage keeps its mirror radiance.
#[derive(Clone, Debug, PartialEq)]
enum MirrorSource {
    /// One blob per direction (a final field).
    Directions,
    /// One blob per tile (a final field of an earlier build).
    Tiles,
    /// A snapshot's mirror radiance in the job's encoding, one blob per batch of directions
    /// (`MapPart::Radiance`).
    Radiance,
    /// A snapshot's exact mirror totals, one blob per batch of directions (snapshots of earlier
    /// builds).
    Batches,
    /// A snapshot of an earlier build: all its mirror totals in this one blob (its totals, or
    /// its whole checkpoint).
    Whole(String),
}

/// One committed stage of a job, read part by part.
pub struct StageParts {
    job: FieldJob,
    stage: Stage,
    summary: Summary,
    /// Stored values are radiance in this unit (see [`Summary::radiance_unit`]).
    unit: f32,
    mirrors: MirrorSource,
    /// The blobs of many tiles read so far ([`StageParts::is_shared`]: a direction's, a batch's,
    /// or a snapshot's whole mirror totals), decoded, by key.
    shared: Mutex<HashMap<String, Arc<MirrorTotals>>>,
    /// Bytes of radiance blobs read so far (as stored).
    bytes: AtomicU64,
}

impl StageParts {
    /// Opens `stage` of `job`: reads its summary (the stage must be committed).
    pub fn open(job: FieldJob, stage: Stage) -> Result<StageParts, StoreError> {
        job.job().check_committed(stage)?;
        let summary = job.summary(stage)?;
        let unit = summary.radiance_unit;
        // As [`crate::field::radiance_unit`] writes it: a power of two within 2^±120, which f32
        // holds exactly (a unit beyond f32's range would read every radiance as 0 or ∞).
        if !(unit.is_finite() && unit > 0.0 && unit.log2().fract() == 0.0 && unit.log2().abs() <= 120.0) {
            return Err(job.field_error(vlf_core::Error::Decode(format!(
                "summary of {stage:?}: radiance unit {unit} is not a power of two within 2^±120"
            ))));
        }
        let mirrors = match stage {
            Stage::Iteration(_) if summary.mirror_radiance_by_batch => MirrorSource::Radiance,
            Stage::Iteration(k) => {
                let store = job.job().store();
                let (first, totals, whole) = (
                    layout::map_part(job.id(), k, MapPart::Totals, 0)?,
                    layout::totals(job.id(), k)?,
                    layout::state(job.id(), k)?,
                );
                // A store that holds none yet (a viewer's, filled as parts are fetched) is taken
                // to be of the current layout.
                if store.exists(&first)? {
                    MirrorSource::Batches
                } else if store.exists(&totals)? {
                    MirrorSource::Whole(totals)
                } else if store.exists(&whole)? {
                    MirrorSource::Whole(whole)
                } else {
                    MirrorSource::Batches
                }
            }
            Stage::Field if summary.mirrors_by_direction => MirrorSource::Directions,
            Stage::Field => MirrorSource::Tiles,
        };
        Ok(StageParts {
            job,
            stage,
            summary,
            mirrors,
            unit: unit as f32,
            shared: Mutex::new(HashMap::new()),
            bytes: AtomicU64::new(0),
        })
    }

    pub fn job(&self) -> &FieldJob {
        &self.job
    }

    pub fn stage(&self) -> Stage {
        self.stage
    }

    pub fn summary(&self) -> &Summary {
        &self.summary
    }

    /// Whether `key` holds the radiance of many mirror tiles (a direction's, or a snapshot's
    /// mirror totals), so that a reader keeps it once fetched.
    pub fn is_shared(&self, key: &str) -> bool {
        match (&self.mirrors, self.stage) {
            (MirrorSource::Whole(whole), _) => key == whole,
            (MirrorSource::Directions, stage) => layout::parse_direction(key)
                .is_some_and(|d| layout::direction(self.job.id(), stage, d).is_ok_and(|named| named == key)),
            (MirrorSource::Batches, Stage::Iteration(k)) => {
                layout::map_parts(self.job.id(), k, MapPart::Totals).is_ok_and(|folder| key.starts_with(&folder))
            }
            (MirrorSource::Radiance, Stage::Iteration(k)) => {
                layout::map_parts(self.job.id(), k, MapPart::Radiance).is_ok_and(|folder| key.starts_with(&folder))
            }
            _ => false,
        }
    }

    /// Bytes of radiance blobs read so far, as stored (compressed).
    pub fn bytes_read(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }

    /// The field's geometry with all radiance zero: directions, texel grids and mirror views
    /// rebuilt from the scene and options, no radiance blob read. What a viewer
    /// draws from while the parts arrive, and where [`StageParts::read`] puts them.
    pub fn geometry(&self) -> Result<LightField, StoreError> {
        self.geometry_of(self.job.propagation(None)?)
    }

    /// [`StageParts::geometry`] from the job's propagation `p`, already built.
    fn geometry_of(&self, p: vlf_core::propagate::Propagation) -> Result<LightField, StoreError> {
        let job = &self.job;
        let radiance = vec![[0.0f32; 3]; p.atlas.texels];
        let totals = p
            .specular
            .as_ref()
            .map(|spec| spec.views.iter().map(|v| vec![[0.0; 3]; v.slots()]).collect());
        LightField::from_radiance(p, self.summary.stats.clone(), radiance, totals).map_err(|e| job.field_error(e))
    }

    /// The key of the blob that holds `part` (a snapshot's tiles: its checkpoint's mirror
    /// totals of the direction's batch).
    pub fn key(&self, catalog: &PartCatalog, part: u32) -> Result<String, StoreError> {
        let id = self.job.id();
        match (catalog.part(part), self.stage, &self.mirrors) {
            (Part::Chunk(c), stage, _) => layout::diffuse(id, stage, c),
            (Part::Tile { .. }, Stage::Iteration(_), MirrorSource::Whole(key)) => Ok(key.clone()),
            (Part::Tile { direction, .. }, stage, MirrorSource::Directions) => layout::direction(id, stage, direction),
            (Part::Tile { direction, .. }, Stage::Iteration(k), MirrorSource::Batches) => {
                layout::map_part(id, k, MapPart::Totals, self.batch_of(direction) as u32)
            }
            (Part::Tile { direction, .. }, Stage::Iteration(k), MirrorSource::Radiance) => {
                layout::map_part(id, k, MapPart::Radiance, self.batch_of(direction) as u32)
            }
            (Part::Tile { direction, tile }, stage, _) => {
                let per_side = self.job.options().grid.tiles_per_side();
                layout::tile(id, stage, direction, tile % per_side, tile / per_side)
            }
        }
    }

    /// The batch of a [`MapPart::Radiance`] key of snapshot `k` (`…/mirror-radiance/BBBBB.blob`),
    /// if it is one of the job's batches.
    fn radiance_batch(&self, k: u32, key: &str) -> Option<u32> {
        let folder = layout::map_parts(self.job.id(), k, MapPart::Radiance).ok()?;
        let batch = layout::parse_map_part(&folder, key)?;
        ((batch as usize) < self.job.options().batching().count()).then_some(batch)
    }

    /// The batch of directions `direction` is in.
    fn batch_of(&self, direction: u32) -> usize {
        self.job.options().batching().batch_of(direction as usize)
    }

    /// The distinct keys holding `parts`, in first-needed order.
    pub fn keys(&self, catalog: &PartCatalog, parts: &[u32]) -> Result<Vec<String>, StoreError> {
        let mut keys = Vec::new();
        let mut seen = std::collections::HashSet::new();
        for &p in parts {
            let key = self.key(catalog, p)?;
            if seen.insert(key.clone()) {
                keys.push(key);
            }
        }
        Ok(keys)
    }

    /// Reads `parts` (numbers in `catalog`, the catalog of the stage's geometry): each one's
    /// radiance, in the field's units, checked against the shape the catalog gives it and for finite,
    /// non-negative values. A blob that fails either is an error naming its key. The blobs not
    /// at hand are fetched together, their requests overlapping (see [`vlf_store`'s bulk
    /// calls](crate::store)), and decoded in parallel.
    pub fn read(&self, catalog: &PartCatalog, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>, StoreError> {
        let store = self.job.job().store();
        let missing: Vec<String> = {
            let cached = self.shared.lock().unwrap_or_else(|e| e.into_inner());
            let keys = self.keys(catalog, parts)?;
            keys.into_iter().filter(|k| !cached.contains_key(k)).collect()
        };
        let blobs = store.get_all(&missing)?;
        let read: usize = blobs.iter().map(|b| b.len()).sum();
        self.bytes.fetch_add(read as u64, Ordering::Relaxed);
        let fetched: HashMap<&str, &[u8]> = missing
            .iter()
            .map(String::as_str)
            .zip(blobs.iter().map(|b| &b[..]))
            .collect();
        // A direction's mirror radiance, or a snapshot's mirror totals, hold many tiles: decoded
        // once, before the tiles are cut.
        let slots = self.direction_slots(catalog, &missing);
        missing
            .par_iter()
            .filter(|key| self.is_shared(key))
            .try_for_each(|key| self.cache_shared(key, fetched[key.as_str()], &slots))?;
        let blob = |key: &str| {
            fetched.get(key).copied().ok_or_else(|| StoreError::NotFound {
                url: store.url().to_string(),
                key: key.to_string(),
            })
        };
        parts
            .par_iter()
            .map(|&i| {
                let key = self.key(catalog, i)?;
                let values = match catalog.part(i) {
                    Part::Chunk(_) => {
                        let texels = catalog.values(i) as u32;
                        let (shape, values) = self.values(&key, blob(&key)?, BlobKind::DiffuseMaps)?;
                        self.job.check_shape(&shape, &[texels, 3], || Ok(key.clone()))?;
                        self.scaled(&values)
                    }
                    Part::Tile { direction, tile } => match self.mirrors {
                        MirrorSource::Tiles => {
                            let (shape, values) = self.values(&key, blob(&key)?, BlobKind::TileRadiance)?;
                            self.job
                                .check_shape(&shape, &[catalog.values(i) as u32, 3], || Ok(key.clone()))?;
                            self.scaled(&values)
                        }
                        _ => {
                            let (totals, first) = self.shared_totals(&key, direction)?;
                            let d = totals.get(direction as usize - first).map_or(&[][..], |t| t.as_slice());
                            d.get(catalog.range(i))
                                .ok_or_else(|| {
                                    self.job.field_error(vlf_core::Error::Decode(format!(
                                        "`{key}` has no tile {tile} of direction {direction} ({:?})",
                                        self.stage
                                    )))
                                })?
                                .to_vec()
                        }
                    },
                };
                if !values.iter().flatten().all(|c| c.is_finite() && *c >= 0.0) {
                    return Err(self.job.field_error(vlf_core::Error::Decode(format!(
                        "{key}: negative or non-finite radiance"
                    ))));
                }
                Ok(values)
            })
            .collect()
    }

    /// Decodes the blob of values `bytes` read from `key`.
    fn values(&self, key: &str, bytes: &[u8], kind: BlobKind) -> Result<(Vec<u32>, Vec<f32>), StoreError> {
        self.job
            .job()
            .store()
            .as_async()
            .decode_with(key, bytes, |b| blob::decode_values(b, kind))
    }

    /// Stored values (`[.., 3]`, in the stage's unit) as radiance.
    fn scaled(&self, values: &[f32]) -> Vec<[f32; 3]> {
        let u = self.unit;
        values.chunks_exact(3).map(|v| [v[0] * u, v[1] * u, v[2] * u]).collect()
    }

    /// The mirror radiance held by `key` — of `direction`, of its batch, or of every direction
    /// in a snapshot of an earlier build — as [`StageParts::read`] cached it, and the first
    /// direction it holds.
    fn shared_totals(&self, key: &str, direction: u32) -> Result<(Arc<MirrorTotals>, usize), StoreError> {
        let first = match self.mirrors {
            MirrorSource::Directions => direction as usize,
            MirrorSource::Batches | MirrorSource::Radiance => {
                let batch = self.batch_of(direction);
                self.job.options().batching().range(batch).start
            }
            _ => 0,
        };
        let cached = self.shared.lock().unwrap_or_else(|e| e.into_inner());
        match cached.get(key) {
            Some(totals) => Ok((totals.clone(), first)),
            None => Err(StoreError::NotFound {
                url: self.job.job().store().url().to_string(),
                key: key.to_string(),
            }),
        }
    }

    /// The number of mirror slots of each direction whose blob is among `keys` (a direction's,
    /// or its batch's mirror radiance), from `catalog` (a direction's tiles number its slots one
    /// after the other): what its blob must hold.
    fn direction_slots(&self, catalog: &PartCatalog, keys: &[String]) -> HashMap<u32, usize> {
        let directions: Vec<u32> = match (&self.mirrors, self.stage) {
            (MirrorSource::Directions, _) => keys.iter().filter_map(|k| layout::parse_direction(k)).collect(),
            (MirrorSource::Radiance, Stage::Iteration(k)) => {
                let batching = self.job.options().batching();
                keys.iter()
                    .filter_map(|key| self.radiance_batch(k, key))
                    .flat_map(|b| batching.range(b as usize))
                    .map(|d| d as u32)
                    .collect()
            }
            _ => return HashMap::new(),
        };
        let mut slots: HashMap<u32, usize> = directions.into_iter().map(|d| (d, 0)).collect();
        // A viewer's reads are small and many: the catalog is walked only when a direction's
        // blob is among them.
        if slots.is_empty() {
            return slots;
        }
        for (i, part) in catalog.parts().iter().enumerate().skip(catalog.chunks()) {
            if let Part::Tile { direction, .. } = part
                && let Some(n) = slots.get_mut(direction)
            {
                *n = (*n).max(catalog.range(i as u32).end);
            }
        }
        slots
    }

    /// Decodes `stored`, read from `key`, which holds many tiles (see [`StageParts::is_shared`]),
    /// and keeps it. A direction's blob must hold `slots` of it.
    fn cache_shared(&self, key: &str, stored: &[u8], slots: &HashMap<u32, usize>) -> Result<(), StoreError> {
        let maps = match (self.stage, &self.mirrors) {
            (_, MirrorSource::Directions) => {
                let (shape, values) = self.values(key, stored, BlobKind::DirectionRadiance)?;
                let d = layout::parse_direction(key).and_then(|d| slots.get(&d));
                let Some(&n) = d else {
                    return Err(self.job.field_error(vlf_core::Error::Decode(format!(
                        "`{key}` is not the mirror radiance of a direction with mirror tiles"
                    ))));
                };
                self.job.check_shape(&shape, &[n as u32, 3], || Ok(key.to_string()))?;
                vec![self.scaled(&values)]
            }
            (Stage::Iteration(k), MirrorSource::Batches) => {
                let bytes = self.job.job().decode_snapshot(key, stored)?;
                // `…/mirror-totals/BBBBB.blob`, as `layout::map_part` names batch B's.
                let batch = key
                    .rsplit('/')
                    .next()
                    .and_then(|name| name.strip_suffix(".blob"))
                    .and_then(|b| b.parse::<u32>().ok())
                    .filter(|&b| layout::map_part(self.job.id(), k, MapPart::Totals, b).is_ok_and(|named| named == key))
                    .ok_or_else(|| {
                        self.job.field_error(vlf_core::Error::Decode(format!(
                            "`{key}` is not a batch of mirror totals"
                        )))
                    })?;
                f32_maps(&self.job.decode_map_part(k, batch as usize, &bytes)?.maps)
            }
            (Stage::Iteration(k), MirrorSource::Radiance) => {
                let (shape, values) = self.values(key, stored, BlobKind::BatchRadiance)?;
                let batch = self.radiance_batch(k, key).ok_or_else(|| {
                    self.job.field_error(vlf_core::Error::Decode(format!(
                        "`{key}` is not a batch of mirror radiance"
                    )))
                })?;
                let counts: Vec<usize> = (self.job.options().batching().range(batch as usize))
                    .map(|d| slots.get(&(d as u32)).copied().unwrap_or(0))
                    .collect();
                let held: usize = counts.iter().sum();
                self.job
                    .check_shape(&shape, &[held as u32, 3], || Ok(key.to_string()))?;
                let radiance = self.scaled(&values);
                let mut rest = &radiance[..];
                (counts.iter())
                    .map(|&n| {
                        let (d, after) = rest.split_at(n);
                        rest = after;
                        d.to_vec()
                    })
                    .collect()
            }
            (Stage::Iteration(k), MirrorSource::Whole(_)) => {
                let bytes = self.job.job().decode_snapshot(key, stored)?;
                f32_maps(&self.job.decode_totals(k, &bytes)?.mirrors.unwrap_or_default())
            }
            _ => {
                return Err(self.job.field_error(vlf_core::Error::Decode(format!(
                    "`{key}` holds no tiles of {:?}",
                    self.stage
                ))));
            }
        };
        let mut cached = self.shared.lock().unwrap_or_else(|e| e.into_inner());
        cached.insert(key.to_string(), Arc::new(maps));
        Ok(())
    }
}

/// A checkpoint's `f64` mirror maps as the field's `f32` radiance.
fn f32_maps(maps: &[Vec<vlf_core::scene::Rgb>]) -> MirrorTotals {
    maps.iter()
        .map(|m| m.iter().map(|t| t.map(|c| c as f32)).collect())
        .collect()
}

impl FieldJob {
    /// Reads what a view needs of a committed stage ([`LightField::view_needs`]), or everything
    /// with `None`: the diffuse maps of the needed surfaces and the needed mirror tiles; the rest
    /// of the field stays zero. A field read this way draws that view with the same bits as the
    /// whole field. Also returns how many radiance blobs were read (a final field's mirror
    /// radiance is one blob per direction, a snapshot's one per batch of directions, read when
    /// any of its tiles is needed).
    pub fn load_parts(
        &self,
        stage: Stage,
        needs: Option<&vlf_core::lookup::ViewNeeds>,
    ) -> Result<(LightField, usize), StoreError> {
        self.load_parts_on(stage, needs, None)
    }

    /// Reads several committed stages whole, building the job's geometry (its atlas and every
    /// subfield, most of reading a scanned scene's stage: 2.7 of 3.2 s for the 202 520-triangle
    /// dragon) once for all of them. Each stage's result stands on its own, so a stage that is
    /// missing (snapshot 1 of a job that kept none) does not keep the others from being read.
    pub fn load_each(&self, stages: &[Stage]) -> Result<Vec<Result<LightField, StoreError>>, StoreError> {
        let mut p = Some(self.propagation(None)?);
        Ok((stages.iter().enumerate())
            .map(|(i, &stage)| {
                // The last stage takes the propagation itself; the others a copy.
                let geometry = if i + 1 == stages.len() { p.take() } else { p.clone() };
                Ok(self.load_parts_on(stage, None, geometry)?.0)
            })
            .collect())
    }

    /// [`FieldJob::load_parts`] on the job's propagation `p` where it is built already.
    fn load_parts_on(
        &self,
        stage: Stage,
        needs: Option<&vlf_core::lookup::ViewNeeds>,
        p: Option<vlf_core::propagate::Propagation>,
    ) -> Result<(LightField, usize), StoreError> {
        let reader = StageParts::open(self.clone(), stage)?;
        let mut field = match p {
            Some(p) => reader.geometry_of(p)?,
            None => reader.geometry()?,
        };
        let catalog = PartCatalog::new(&field);
        let parts: Vec<u32> = match needs {
            Some(needs) => catalog.needed(needs),
            None => (0..catalog.len() as u32).collect(),
        };
        let values = reader.read(&catalog, &parts)?;
        for (&i, v) in parts.iter().zip(&values) {
            field.part_values_mut(&catalog, i).copy_from_slice(v);
        }
        Ok((field, reader.keys(&catalog, &parts)?.len()))
    }
}
