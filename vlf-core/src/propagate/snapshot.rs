//! How a snapshot's checkpoint is stored: in parts sized to who reads them.
//!
//! A checkpoint has two halves (see [`super::checkpoint`]): the shooting state,
//! which the next iteration's workers read, and the totals, which only the
//! coordinator (to resume) and viewers (a snapshot's mirror radiance) read.
//! The shooting state is cut further, because a worker shoots only the
//! directions of its lease:
//!
//! * a [`StateHead`]: the iteration statistics and Current — what every lease
//!   reads (a texel map, small);
//! * one [`UnshotBatch`] per batch of directions (`work::batch_range`): the
//!   unshot mirror maps of the batch's directions — read by the leases that
//!   shoot those directions, and only when mirrors take part.
//!
//! So w workers read the unshot maps once between them rather than w times,
//! and the parts are written and read in parallel. [`Propagation::snapshot_bytes`]
//! serialises every part straight from the propagation's maps;
//! [`ShootingState::from_parts`] puts a shooting state back together, and
//! [`Propagation::restore_head`] and [`Propagation::restore_unshot`] restore
//! one part at a time on a worker's replica.

use super::checkpoint::{SPLIT_VERSION, ShootingState, encode, misfit, version_of};
use super::work::{batch_count, batch_range};
use super::{IterationStats, Propagation};
use crate::error::Error;
use crate::scene::Rgb;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// What every lease of the next iteration reads of a snapshot.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StateHead {
    version: u32,
    pub stats: Vec<IterationStats>,
    /// Unshot power per texel.
    pub current: Vec<Rgb>,
    /// The number of [`UnshotBatch`]es, `None` without specular machinery.
    pub unshot_batches: Option<u32>,
}

/// The unshot mirror maps of one batch of directions.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UnshotBatch {
    version: u32,
    /// Iterations done when the checkpoint was taken.
    pub iterations: u32,
    pub batch: u32,
    /// Per direction of the batch, in order, its unshot mirror map.
    pub maps: Vec<Vec<Rgb>>,
}

fn decode<T: serde::de::DeserializeOwned>(bytes: &[u8], what: &str) -> crate::Result<T> {
    match version_of(bytes) {
        Some(SPLIT_VERSION) => bincode::deserialize(bytes).map_err(|e| Error::Decode(format!("{what}: {e}"))),
        Some(v) => Err(Error::Decode(format!(
            "{what}: version {v} (this build reads {SPLIT_VERSION})"
        ))),
        None => Err(Error::Decode(format!("{what}: truncated"))),
    }
}

impl StateHead {
    /// Iterations done when the checkpoint was taken.
    pub fn iterations(&self) -> u32 {
        self.stats.len() as u32
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    pub fn from_bytes(bytes: &[u8]) -> crate::Result<StateHead> {
        decode(bytes, "shooting state head")
    }
}

impl UnshotBatch {
    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    pub fn from_bytes(bytes: &[u8]) -> crate::Result<UnshotBatch> {
        decode(bytes, "unshot mirror maps")
    }
}

impl ShootingState {
    /// Cuts the state into its head and one part per batch of its
    /// directions.
    pub fn into_parts(self) -> (StateHead, Vec<UnshotBatch>) {
        let iterations = self.iterations();
        let batches = self.mirrors.map(|mut maps| {
            let l = maps.len();
            let mut parts: Vec<UnshotBatch> = (0..batch_count(l))
                .rev()
                .map(|b| UnshotBatch {
                    version: SPLIT_VERSION,
                    iterations,
                    batch: b as u32,
                    maps: maps.split_off(batch_range(b, l).start),
                })
                .collect();
            parts.reverse();
            parts
        });
        let head = StateHead {
            version: SPLIT_VERSION,
            stats: self.stats,
            current: self.current,
            unshot_batches: batches.as_ref().map(|b| b.len() as u32),
        };
        (head, batches.unwrap_or_default())
    }

    /// Puts a shooting state back together from its head and all its
    /// batches, in order; parts of another snapshot, missing or out of order
    /// are refused.
    pub fn from_parts(head: StateHead, batches: Vec<UnshotBatch>) -> crate::Result<ShootingState> {
        let bad = |m: String| Err(Error::Decode(format!("shooting state parts do not match: {m}")));
        let iterations = head.iterations();
        let mirrors = match head.unshot_batches {
            None if batches.is_empty() => None,
            None => return bad(format!("{} unshot batches for a state without mirrors", batches.len())),
            Some(n) if n as usize != batches.len() => {
                return bad(format!("{} unshot batches, the head says {n}", batches.len()));
            }
            Some(_) => {
                let mut maps = Vec::new();
                for (b, part) in batches.into_iter().enumerate() {
                    if part.batch as usize != b || part.iterations != iterations {
                        return bad(format!(
                            "batch {} after {} iterations where batch {b} after {iterations} belongs",
                            part.batch, part.iterations
                        ));
                    }
                    maps.extend(part.maps);
                }
                Some(maps)
            }
        };
        Ok(ShootingState {
            stats: head.stats,
            current: head.current,
            mirrors,
        })
    }
}

/// A checkpoint's parts, serialised ([`Propagation::snapshot_bytes`]).
pub struct SnapshotBytes {
    /// [`StateHead::to_bytes`].
    pub head: Vec<u8>,
    /// [`UnshotBatch::to_bytes`] of every batch, in order (none without
    /// mirrors).
    pub unshot: Vec<Vec<u8>>,
    /// [`super::Totals::to_bytes`].
    pub totals: Vec<u8>,
}

/// The parts over borrowed maps: the same bincode bytes (a slice serialises
/// as a vector does), without copying megabytes of maps first.
#[derive(Serialize)]
struct StateHeadRef<'a> {
    version: u32,
    stats: &'a [IterationStats],
    current: &'a [Rgb],
    unshot_batches: Option<u32>,
}

#[derive(Serialize)]
struct UnshotBatchRef<'a> {
    version: u32,
    iterations: u32,
    batch: u32,
    maps: Vec<&'a [Rgb]>,
}

#[derive(Serialize)]
struct TotalsRef<'a> {
    version: u32,
    iterations: u32,
    total: &'a [Rgb],
    mirrors: Option<Vec<&'a [Rgb]>>,
}

impl Propagation {
    /// The parts of [`Propagation::checkpoint`], serialised in parallel:
    /// equal to `checkpoint().split()` with the shooting half
    /// [`ShootingState::into_parts`], each `to_bytes`, without the copy.
    pub fn snapshot_bytes(&self) -> SnapshotBytes {
        let maps = self.specular.as_ref().map(|s| &s.maps);
        let iterations = self.iterations_done();
        let l = self.directions.len();
        let head = StateHeadRef {
            version: SPLIT_VERSION,
            stats: &self.stats,
            current: &self.current,
            unshot_batches: maps.map(|_| batch_count(l) as u32),
        };
        let totals = TotalsRef {
            version: SPLIT_VERSION,
            iterations,
            total: &self.total,
            mirrors: maps.map(|m| m.iter().map(|m| m.total.as_slice()).collect()),
        };
        let unshot = |b: usize| {
            let maps = maps.map_or(Vec::new(), |m| {
                m[batch_range(b, l)].iter().map(|m| m.unshot.as_slice()).collect()
            });
            encode(&UnshotBatchRef {
                version: SPLIT_VERSION,
                iterations,
                batch: b as u32,
                maps,
            })
        };
        let batches = if maps.is_some() { batch_count(l) } else { 0 };
        let ((head, totals), unshot) = rayon::join(
            || rayon::join(|| encode(&head), || encode(&totals)),
            || (0..batches).into_par_iter().map(unshot).collect(),
        );
        SnapshotBytes { head, unshot, totals }
    }

    /// Restores the head of a shooting state: the statistics and Current. The
    /// unshot mirror maps are left as they were until their batches are
    /// restored ([`Propagation::restore_unshot`]); like
    /// [`Propagation::restore_shooting`], for a replica that computes blocks
    /// only. On error the state is unchanged.
    pub fn restore_head(&mut self, head: StateHead) -> crate::Result<()> {
        self.check_unshot_texels(&head.current, &head.stats)?;
        let expected = self
            .specular
            .as_ref()
            .map(|_| batch_count(self.directions.len()) as u32);
        if head.unshot_batches != expected {
            return misfit(format!(
                "{:?} batches of unshot mirror maps, the scene has {expected:?}",
                head.unshot_batches
            ));
        }
        self.current = head.current;
        self.stats = head.stats;
        Ok(())
    }

    /// Restores the unshot mirror maps of one batch of directions, of the
    /// snapshot whose head was restored last. On error the state is
    /// unchanged.
    pub fn restore_unshot(&mut self, part: UnshotBatch) -> crate::Result<()> {
        let l = self.directions.len();
        let iterations = self.iterations_done();
        if self.specular.is_none() {
            return misfit("unshot mirror maps for a scene without mirrors".into());
        }
        let b = part.batch as usize;
        if b >= batch_count(l) || part.iterations != iterations {
            return misfit(format!(
                "unshot maps of batch {b} after {} iterations, for a state after {iterations} with {} batches",
                part.iterations,
                batch_count(l)
            ));
        }
        let range = batch_range(b, l);
        if part.maps.len() != range.len() {
            return misfit(format!(
                "batch {b}: {} unshot maps for {} directions",
                part.maps.len(),
                range.len()
            ));
        }
        self.check_mirror_maps(range.start, &part.maps)?;
        if let Some(spec) = self.specular.as_mut() {
            for (own, saved) in spec.maps[range].iter_mut().zip(part.maps) {
                own.unshot = saved;
            }
        }
        Ok(())
    }
}
