//! Writing a job's final field: its diffuse radiance by chunk, its mirror radiance by direction
//! (`field/dirs/d.blob`), then its summary, whose digest covers every value
//! ([`LightField::digest`]).
//!
//! Two ways in, the same blobs and digest. Whoever holds the whole field (one process that
//! propagated it, or a coordinator asked to re-sample its mirrors) writes it from memory
//! ([`FieldJob::finish`]). A coordinator whose workers shot the mirror maps holds none of them,
//! and reads the last snapshot's exact totals back a few batches of directions at a time,
//! writing each direction's radiance as it goes ([`FieldJob::finish_from_snapshot`]): its memory
//! is the diffuse field's and a few batches', not the mirror totals of every direction (0.5 GB
//! as `f32` for the mirror scene at l = 8193, N = 256, after 1.07 GB of `f64` read back).

use super::{FieldJob, Summary, radiance_unit, scaled, write_diffuse};
use crate::error::StoreError;
use crate::layout::{MapPart, Stage};
use crate::store::Put;
use rayon::prelude::*;
use vlf_core::field::{LightField, digest_of, mirror_digest};
use vlf_core::propagate::Propagation;

impl FieldJob {
    /// Writes `field` as the job's final field and marks the job finished.
    ///
    /// A direction's mirror radiance is one blob, its slots tile after tile, although a viewer
    /// needs only the tiles it sees of it: the 2 781 492 mirror slots of the mirror scene at
    /// l = 2049, N = 128 lie in 69 467 tiles, a few hundred bytes each once encoded, and writing
    /// that many objects (a PUT each on an object store, a file each on disk) cost more than
    /// the field's propagation; one per direction is 2 049 blobs of 6.6 kB on average, which a
    /// viewer fetches as quickly as one tile, and keeps.
    pub fn finish(&mut self, field: &LightField, resampled: bool) -> Result<(), StoreError> {
        let unit = radiance_unit(&self.scene);
        write_diffuse(&self.job, Stage::Field, &field.atlas, &field.radiance, unit)?;
        if let Some(spec) = &field.specular {
            let lit: Vec<usize> = (0..spec.views.len()).filter(|&d| spec.views[d].slots() > 0).collect();
            self.job
                .put_encoded(&lit, |&d| self.direction_put(d, &spec.totals[d], unit))?;
        }
        let summary = FieldSummary {
            iterations: field.stats.len(),
            unshot_fraction: field.unshot_fraction,
            emitted: field.emitted,
            stats: field.stats.clone(),
            digest: field.digest(),
        };
        self.write_field_summary(summary, resampled, unit)
    }

    /// Writes the final field of `p`, the propagation after its last iteration, whose mirror
    /// totals are not held but in the parts of its last snapshot (written by the workers that
    /// shot them), and marks the job finished: the same blobs and digest as [`FieldJob::finish`]
    /// of `p` with its totals restored, not re-sampled.
    ///
    /// The totals are read back a few batches at a time (one bulk read each), checked against
    /// the directions' slots ([`Propagation::check_map_batch`]), rounded to `f32` as the field
    /// rounds them, hashed and written direction by direction, and dropped: memory is a few
    /// batches of maps, not the whole field's.
    pub fn finish_from_snapshot(&mut self, p: &Propagation) -> Result<(), StoreError> {
        let k = p.iterations_done();
        let unit = radiance_unit(&self.scene);
        let radiance = p.diffuse_radiance();
        write_diffuse(&self.job, Stage::Field, &p.atlas, &radiance, unit)?;
        let mirrors = match &p.specular {
            None => None,
            Some(spec) => {
                let batching = p.batching();
                let mut digests = vec![[0u8; 32]; spec.views.len()];
                let all: Vec<usize> = (0..batching.count()).collect();
                // As many batches at once as threads write them (at least a few, for the bulk
                // read's round trip).
                for chunk in all.chunks(rayon::current_num_threads().max(4)) {
                    let parts = self.released_maps(k, MapPart::Totals, chunk)?;
                    let written: Vec<(usize, [u8; 32], Option<Put>)> = (parts.into_par_iter())
                        .map(|part| {
                            let range = p.check_map_batch(&part).map_err(|e| self.field_error(e))?;
                            range
                                .zip(part.maps)
                                .map(|(d, exact)| {
                                    // As `LightField`'s totals are: each channel rounded to `f32`.
                                    let totals: Vec<[f32; 3]> = exact.iter().map(|t| t.map(|c| c as f32)).collect();
                                    let put = (!totals.is_empty())
                                        .then(|| self.direction_put(d, &totals, unit))
                                        .transpose()?;
                                    Ok((d, mirror_digest(&totals), put))
                                })
                                .collect::<Result<Vec<_>, StoreError>>()
                        })
                        .collect::<Result<Vec<_>, _>>()?
                        .into_iter()
                        .flatten()
                        .collect();
                    let mut puts = Vec::new();
                    for (d, digest, put) in written {
                        digests[d] = digest;
                        puts.extend(put);
                    }
                    self.job.store().put_all(puts)?;
                }
                Some(digests)
            }
        };
        let summary = FieldSummary {
            iterations: p.stats.len(),
            unshot_fraction: p.unshot_fraction(),
            emitted: p.emitted,
            stats: p.stats.clone(),
            digest: digest_of(p.stats.len(), &radiance, mirrors.as_deref()),
        };
        self.write_field_summary(summary, false, unit)
    }

    /// The blob of direction `d`'s mirror radiance in the final field.
    fn direction_put(&self, d: usize, totals: &[[f32; 3]], unit: f64) -> Result<Put, StoreError> {
        let values = scaled(totals, unit);
        self.job
            .direction_put(Stage::Field, d as u32, &[totals.len() as u32, 3], &values)
    }

    /// Writes the final field's summary and marks the job finished.
    fn write_field_summary(&mut self, field: FieldSummary, resampled: bool, unit: f64) -> Result<(), StoreError> {
        self.write_summary(
            Stage::Field,
            &Summary {
                iterations: field.iterations as u32,
                unshot_fraction: field.unshot_fraction,
                emitted: field.emitted,
                resampled,
                radiance_unit: unit,
                stats: field.stats,
                digest: Some(field.digest),
                mirrors_by_direction: true,
                mirror_radiance_by_batch: false,
            },
        )?;
        self.job.finish()
    }
}

/// What a final field's summary says of it, however it was written.
struct FieldSummary {
    iterations: usize,
    unshot_fraction: f64,
    emitted: vlf_core::scene::Rgb,
    stats: Vec<vlf_core::propagate::IterationStats>,
    digest: String,
}
