//! Reading a stage part by part (`vlf_core::parts`): what a viewer streams, and what
//! [`FieldJob::load_parts`] is built on.
//!
//! A final field stores one blob per part. A snapshot stores its diffuse maps the same way but
//! its mirror radiance in its checkpoint's totals (see [`crate::field`]): the first tile asked
//! for reads them, and the tiles are cut from them from then on.

use crate::blob::{self, BlobKind};
use crate::error::StoreError;
use crate::field::{FieldJob, Summary};
use crate::layout::{self, Stage};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use vlf_core::field::LightField;
use vlf_core::parts::{Part, PartCatalog};
use vlf_core::propagate::Propagation;

/// Mirror radiance per direction and slot.
type MirrorTotals = Vec<Vec<[f32; 3]>>;

/// One committed stage of a job, read part by part.
pub struct StageParts {
    job: FieldJob,
    stage: Stage,
    summary: Summary,
    /// Stored values are radiance in this unit (see [`Summary::radiance_unit`]).
    unit: f32,
    /// A snapshot's blob that holds its mirror totals: its checkpoint's totals half, or the
    /// whole checkpoint of a job written before the split. `None` for the final field.
    totals_key: Option<String>,
    /// A snapshot's mirror totals per direction, once read.
    snapshot_totals: Mutex<Option<Arc<MirrorTotals>>>,
    /// Bytes of radiance blobs read so far (as stored).
    bytes: AtomicU64,
}

impl StageParts {
    /// Opens `stage` of `job`: reads its summary (the stage must be committed).
    pub fn open(job: FieldJob, stage: Stage) -> Result<StageParts, StoreError> {
        job.job().check_committed(stage)?;
        let summary = job.summary(stage)?;
        let unit = summary.radiance_unit;
        if !(unit.is_finite() && unit > 0.0 && unit.log2().fract() == 0.0) {
            return Err(job.field_error(vlf_core::Error::Decode(format!(
                "summary of {stage:?}: radiance unit {unit} is not a power of two"
            ))));
        }
        let totals_key = match stage {
            Stage::Iteration(k) => {
                let (totals, whole) = (layout::totals(job.id(), k)?, layout::state(job.id(), k)?);
                let store = job.job().store();
                // A store that holds neither yet (a viewer's, filled as parts are fetched) is
                // taken to be of the current layout.
                Some(if !store.exists(&totals)? && store.exists(&whole)? {
                    whole
                } else {
                    totals
                })
            }
            Stage::Field => None,
        };
        Ok(StageParts {
            job,
            stage,
            summary,
            totals_key,
            unit: unit as f32,
            snapshot_totals: Mutex::new(None),
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

    /// A snapshot's blob that holds the radiance of all its mirror tiles (`None` for the final
    /// field).
    pub fn totals_key(&self) -> Option<&str> {
        self.totals_key.as_deref()
    }

    /// Bytes of radiance blobs read so far, as stored (compressed).
    pub fn bytes_read(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }

    /// The field's geometry with all radiance zero: directions, subfields, texel grids and
    /// mirror layouts rebuilt from the scene and options, no radiance blob read. What a viewer
    /// draws from while the parts arrive, and where [`StageParts::read`] puts them.
    pub fn geometry(&self) -> Result<LightField, StoreError> {
        let job = &self.job;
        let p = Propagation::new(job.scene().clone(), job.options().clone()).map_err(|e| job.field_error(e))?;
        let radiance = vec![[0.0f32; 3]; p.atlas.texels];
        let totals = p
            .specular
            .as_ref()
            .map(|spec| spec.layouts.iter().map(|l| vec![[0.0; 3]; l.len as usize]).collect());
        LightField::from_radiance(p, self.summary.stats.clone(), radiance, totals).map_err(|e| job.field_error(e))
    }

    /// The key of the blob that holds `part` (a snapshot's tiles: its checkpoint's totals).
    pub fn key(&self, catalog: &PartCatalog, part: u32) -> Result<String, StoreError> {
        let id = self.job.id();
        match (catalog.part(part), self.stage, &self.totals_key) {
            (Part::Surface(s), stage, _) => layout::diffuse(id, stage, s),
            (Part::Tile { .. }, Stage::Iteration(_), Some(key)) => Ok(key.clone()),
            (Part::Tile { direction, tile }, stage, _) => {
                let per_side = self.job.options().grid.tiles_per_side();
                layout::tile(id, stage, direction, tile % per_side, tile / per_side)
            }
        }
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

    /// Reads `parts` (numbers in `catalog`, the catalog of `geometry`), in parallel: each one's
    /// radiance, in the field's units, checked against the shape the geometry gives it and for
    /// finite, non-negative values. A blob that fails either is an error naming its key.
    pub fn read(
        &self,
        geometry: &LightField,
        catalog: &PartCatalog,
        parts: &[u32],
    ) -> Result<Vec<Vec<[f32; 3]>>, StoreError> {
        parts
            .par_iter()
            .map(|&i| {
                let key = || self.key(catalog, i);
                let values = match catalog.part(i) {
                    Part::Surface(s) => {
                        let g = &geometry.atlas.grids[s as usize];
                        let (shape, values) = self.values(&key()?, BlobKind::DiffuseMaps)?;
                        self.job.check_shape(&shape, &[g.height, g.width, 3], key)?;
                        self.scaled(&values)
                    }
                    Part::Tile { direction, tile } => match self.stage {
                        Stage::Iteration(_) => {
                            let totals = self.snapshot_totals()?;
                            let d = totals.get(direction as usize).map_or(&[][..], |t| t.as_slice());
                            d.get(catalog.range(i))
                                .ok_or_else(|| {
                                    self.job.field_error(vlf_core::Error::Decode(format!(
                                        "the checkpoint of {:?} has no tile {tile} of direction {direction}",
                                        self.stage
                                    )))
                                })?
                                .to_vec()
                        }
                        Stage::Field => {
                            let (shape, values) = self.values(&key()?, BlobKind::TileRadiance)?;
                            self.job.check_shape(&shape, &[catalog.values(i) as u32, 3], key)?;
                            self.scaled(&values)
                        }
                    },
                };
                if !values.iter().flatten().all(|c| c.is_finite() && *c >= 0.0) {
                    return Err(self.job.field_error(vlf_core::Error::Decode(format!(
                        "{}: negative or non-finite radiance",
                        key()?
                    ))));
                }
                Ok(values)
            })
            .collect()
    }

    /// Reads and decodes the blob of values at `key`, counting its bytes.
    fn values(&self, key: &str, kind: BlobKind) -> Result<(Vec<u32>, Vec<f32>), StoreError> {
        let store = self.job.job().store();
        let bytes = store.get(key)?;
        self.bytes.fetch_add(bytes.len() as u64, Ordering::Relaxed);
        store
            .as_async()
            .decode_with(key, &bytes, |b| blob::decode_values(b, kind))
    }

    /// Stored values (`[.., 3]`, in the stage's unit) as radiance.
    fn scaled(&self, values: &[f32]) -> Vec<[f32; 3]> {
        let u = self.unit;
        values.chunks_exact(3).map(|v| [v[0] * u, v[1] * u, v[2] * u]).collect()
    }

    /// A snapshot's mirror totals, read from its checkpoint the first time.
    fn snapshot_totals(&self) -> Result<Arc<MirrorTotals>, StoreError> {
        let (Stage::Iteration(k), Some(key)) = (self.stage, &self.totals_key) else {
            return Err(self.job.field_error(vlf_core::Error::Decode(
                "a final field keeps its mirror radiance in tiles".into(),
            )));
        };
        let mut cached = self.snapshot_totals.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(totals) = &*cached {
            return Ok(totals.clone());
        }
        let store = self.job.job().store();
        let stored = store.get(key)?;
        self.bytes.fetch_add(stored.len() as u64, Ordering::Relaxed);
        let bytes = store
            .as_async()
            .decode_with(key, &stored, |b| blob::decode_bytes(b, BlobKind::Snapshot))?;
        let maps = self.job.decode_totals(k, &bytes)?.mirrors.unwrap_or_default();
        let totals: Arc<MirrorTotals> = Arc::new(
            maps.iter()
                .map(|m| m.iter().map(|t| t.map(|c| c as f32)).collect())
                .collect(),
        );
        *cached = Some(totals.clone());
        Ok(totals)
    }
}

impl FieldJob {
    /// Reads what a view needs of a committed stage ([`LightField::view_needs`]), or everything
    /// with `None`: the diffuse maps of the needed surfaces and the needed mirror tiles; the rest
    /// of the field stays zero. A field read this way draws that view with the same bits as the
    /// whole field. Also returns how many radiance blobs were read (a snapshot's mirror radiance
    /// is one blob, its checkpoint, read when any mirror tile is needed).
    pub fn load_parts(
        &self,
        stage: Stage,
        needs: Option<&vlf_core::lookup::ViewNeeds>,
    ) -> Result<(LightField, usize), StoreError> {
        let reader = StageParts::open(self.clone(), stage)?;
        let mut field = reader.geometry()?;
        let catalog = PartCatalog::new(&field);
        let parts: Vec<u32> = match needs {
            Some(needs) => catalog.needed(needs),
            None => (0..catalog.len() as u32).collect(),
        };
        let values = reader.read(&field, &catalog, &parts)?;
        for (&i, v) in parts.iter().zip(&values) {
            field.part_values_mut(&catalog, i).copy_from_slice(v);
        }
        Ok((field, reader.keys(&catalog, &parts)?.len()))
    }
}
