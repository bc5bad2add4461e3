//! How a snapshot's checkpoint is stored: in parts sized to who reads them.
//!
//! A checkpoint has two halves (see [`super::checkpoint`]): the shooting
//! state, which the next iteration's workers read, and the totals. Both are
//! cut further, because a worker shoots only the directions of its lease:
//!
//! * a [`StateHead`]: the iteration statistics, Current and what the pending
//!   arrivals come to ([`super::specular::Settled`]) — what every lease reads
//!   (small);
//! * per batch of directions ([`super::Batching`]), two [`MapBatch`]es: the
//!   directions' shooting maps (the arrivals to gather, or the unshot maps)
//!   and their total maps — read by the leases that shoot those directions,
//!   and the shooting maps also by leases that gather from them;
//! * the diffuse [`Totals`] (the texels' Total), read by the coordinator and
//!   by viewers, who read the mirror totals by batch as well.
//!
//! The map batches are what a worker writes after shooting its directions
//! ([`super::MirrorBlock::batch_bytes`]), so in the distributed service the
//! mirror maps go from worker to worker and never through the coordinator,
//! and a worker that shoots the same directions again reads nothing back.
//! [`Propagation::snapshot_bytes`] serialises every part straight from the
//! propagation's maps; [`ShootingState::from_parts`] and
//! [`Totals::with_mirror_batches`] put the halves back together, and
//! [`Propagation::restore_head`], [`Propagation::restore_shooting_batch`] and
//! [`Propagation::restore_totals_batch`] restore one part at a time on a
//! worker's replica.
//!
//! Earlier builds wrote version 2 heads, without pending arrivals, whose
//! batches held unshot maps and whose totals blob held the mirror totals
//! whole: [`StateHead::from_bytes`] still reads them, and
//! [`StateHead::mirror_totals_by_batch`] tells the two apart. Versions 4 and 6
//! held every direction's pending `Φ_in` (dense, then sparse): read too, and
//! settled as they are restored.

use super::batching::Batching;
use super::checkpoint::{
    CheckpointOfPower, DensePending, HEAD_DENSE, HEAD_SPARSE, HEAD_VERSION, SPLIT_VERSION, ShootingState,
    SparsePending, Totals, encode, encode_into, misfit, version_of,
};
use super::output::MirrorBlock;
use super::specular::Pending;
use super::{IterationStats, Propagation};
use crate::error::Error;
use crate::scene::Rgb;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;

/// What every lease of the next iteration reads of a snapshot.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StateHead {
    version: u32,
    pub stats: Vec<IterationStats>,
    /// Unshot power per texel.
    pub current: Vec<Rgb>,
    /// The number of batches of mirror maps, `None` without specular
    /// machinery.
    pub mirror_batches: Option<u32>,
    /// What the arrivals the shooting maps hold come to, when they wait to be reflected.
    pub pending: Option<Pending>,
}

/// A head with pending `Φ_in`, as earlier builds wrote it: dense (version 4, `P` =
/// [`DensePending`]) or sparse (version 6, [`SparsePending`]).
#[derive(Serialize, Deserialize)]
struct StateHeadOfPower<P> {
    version: u32,
    stats: Vec<IterationStats>,
    current: Vec<Rgb>,
    mirror_batches: Option<u32>,
    pending: Option<P>,
}

/// A head as earlier builds wrote it (version 2).
#[derive(Deserialize)]
struct StateHeadV2 {
    version: u32,
    stats: Vec<IterationStats>,
    current: Vec<Rgb>,
    unshot_batches: Option<u32>,
}

/// Mirror maps of one batch of directions: their shooting maps or their
/// totals, as the key that holds it says.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MapBatch {
    version: u32,
    /// Iterations done when the checkpoint was taken.
    pub iterations: u32,
    pub batch: u32,
    /// Per direction of the batch, in order, its map.
    pub maps: Vec<Vec<Rgb>>,
}

impl MapBatch {
    /// Bytes of the maps it holds.
    pub fn bytes(&self) -> usize {
        self.maps.iter().map(Vec::capacity).sum::<usize>() * std::mem::size_of::<Rgb>()
    }
}

impl StateHead {
    /// Iterations done when the checkpoint was taken.
    pub fn iterations(&self) -> u32 {
        self.stats.len() as u32
    }

    /// Whether the snapshot's mirror totals are stored by batch (this
    /// build, and heads with `Φ_in`) rather than whole in its totals
    /// blob, and its map batches stored where this build puts them (earlier
    /// builds: version 2).
    pub fn mirror_totals_by_batch(&self) -> bool {
        self.version == HEAD_VERSION
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    pub fn from_bytes(bytes: &[u8]) -> crate::Result<StateHead> {
        let bad = |e: bincode::Error| Error::Decode(format!("shooting state head: {e}"));
        match version_of(bytes) {
            Some(HEAD_VERSION) => bincode::deserialize(bytes).map_err(bad),
            Some(HEAD_DENSE) => {
                let old: StateHeadOfPower<DensePending> = bincode::deserialize(bytes).map_err(bad)?;
                Ok(old.into_head(|p| p.sparse()))
            }
            Some(HEAD_SPARSE) => {
                let old: StateHeadOfPower<SparsePending> = bincode::deserialize(bytes).map_err(bad)?;
                Ok(old.into_head(|p| p.power_in))
            }
            Some(SPLIT_VERSION) => {
                let old: StateHeadV2 = bincode::deserialize(bytes).map_err(bad)?;
                Ok(StateHead {
                    version: old.version,
                    stats: old.stats,
                    current: old.current,
                    mirror_batches: old.unshot_batches,
                    pending: None,
                })
            }
            Some(v) => Err(Error::Decode(format!(
                "shooting state head: version {v} (this build reads {SPLIT_VERSION}, {HEAD_DENSE}, {HEAD_SPARSE} and {HEAD_VERSION})"
            ))),
            None => Err(Error::Decode("shooting state head: truncated".into())),
        }
    }
}

impl<P> StateHeadOfPower<P> {
    /// This build's head of the same snapshot, its arrivals not settled yet: `power_in` gives
    /// every direction's `Φ_in` of the pending arrivals.
    fn into_head(self, power_in: impl FnOnce(P) -> Vec<super::specular::MirrorPower>) -> StateHead {
        StateHead {
            version: HEAD_VERSION,
            stats: self.stats,
            current: self.current,
            mirror_batches: self.mirror_batches,
            pending: self.pending.map(|p| Pending::of_power_in(power_in(p))),
        }
    }
}

impl MapBatch {
    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    pub fn from_bytes(bytes: &[u8]) -> crate::Result<MapBatch> {
        match version_of(bytes) {
            Some(SPLIT_VERSION) => bincode::deserialize(bytes).map_err(|e| Error::Decode(format!("mirror maps: {e}"))),
            Some(v) => Err(Error::Decode(format!(
                "mirror maps: version {v} (this build reads {SPLIT_VERSION})"
            ))),
            None => Err(Error::Decode("mirror maps: truncated".into())),
        }
    }
}

/// Cuts per-direction maps into one [`MapBatch`] per batch of directions.
fn cut(iterations: u32, mut maps: Vec<Vec<Rgb>>, batching: Batching) -> Vec<MapBatch> {
    let mut parts: Vec<MapBatch> = (0..batching.count())
        .rev()
        .map(|b| MapBatch {
            version: SPLIT_VERSION,
            iterations,
            batch: b as u32,
            maps: maps.split_off(batching.range(b).start),
        })
        .collect();
    parts.reverse();
    parts
}

/// Puts per-direction maps back together from all their batches, in order.
fn uncut(iterations: u32, batches: Vec<MapBatch>, what: &str) -> crate::Result<Vec<Vec<Rgb>>> {
    let mut maps = Vec::new();
    for (b, part) in batches.into_iter().enumerate() {
        if part.batch as usize != b || part.iterations != iterations {
            return Err(Error::Decode(format!(
                "{what} do not match: batch {} after {} iterations where batch {b} after {iterations} belongs",
                part.batch, part.iterations
            )));
        }
        maps.extend(part.maps);
    }
    Ok(maps)
}

impl ShootingState {
    /// Cuts the state into its head and one part per batch of its
    /// directions (cut by the job's `batching`).
    pub fn into_parts(self, batching: Batching) -> (StateHead, Vec<MapBatch>) {
        let iterations = self.iterations();
        let batches = self.mirrors.map(|maps| cut(iterations, maps, batching));
        let head = StateHead {
            version: HEAD_VERSION,
            stats: self.stats,
            current: self.current,
            mirror_batches: batches.as_ref().map(|b| b.len() as u32),
            pending: self.pending,
        };
        (head, batches.unwrap_or_default())
    }

    /// Puts a shooting state back together from its head and all its
    /// batches, in order; parts of another snapshot, missing or out of order
    /// are refused.
    pub fn from_parts(head: StateHead, batches: Vec<MapBatch>) -> crate::Result<ShootingState> {
        let bad = |m: String| Err(Error::Decode(format!("shooting state parts do not match: {m}")));
        let iterations = head.iterations();
        let mirrors = match head.mirror_batches {
            None if batches.is_empty() => None,
            None => return bad(format!("{} map batches for a state without mirrors", batches.len())),
            Some(n) if n as usize != batches.len() => {
                return bad(format!("{} map batches, the head says {n}", batches.len()));
            }
            Some(_) => Some(uncut(iterations, batches, "shooting state parts")?),
        };
        Ok(ShootingState {
            stats: head.stats,
            current: head.current,
            mirrors,
            pending: head.pending,
        })
    }
}

impl Totals {
    /// Cuts the mirror totals out, one part per batch of directions (cut by the job's
    /// `batching`; none without mirrors).
    pub fn into_parts(mut self, batching: Batching) -> (Totals, Vec<MapBatch>) {
        let batches = self
            .mirrors
            .take()
            .map_or(Vec::new(), |maps| cut(self.iterations, maps, batching));
        (self, batches)
    }

    /// Puts the mirror totals back from all their batches, in order (none:
    /// as they are).
    pub fn with_mirror_batches(mut self, batches: Vec<MapBatch>) -> crate::Result<Totals> {
        if batches.is_empty() {
            return Ok(self);
        }
        if self.mirrors.is_some() {
            return Err(Error::Decode("totals hold mirror maps twice".into()));
        }
        self.mirrors = Some(uncut(self.iterations, batches, "mirror totals")?);
        Ok(self)
    }
}

impl MirrorBlock {
    /// The total maps of batch `b`, one of the block's: its directions' maps, in order (what the
    /// batch's mirror radiance is made of).
    pub fn batch_totals(&self, batching: Batching, b: u32) -> Vec<&[Rgb]> {
        self.total[self.local(batching, b)].iter().map(Vec::as_slice).collect()
    }

    /// The block's part of the next snapshot for batch `b`, one of the block's: the
    /// [`MapBatch::to_bytes`] of its maps of `kind`, from the block's maps without copying them.
    /// A batch at a time, so that whoever stores them compresses each as it is serialised: a
    /// block may be a worker's whole home, and all its batches serialised at once were 1.07 GB
    /// for each of two workers of the mirror scene at l = 8193, N = 256.
    pub fn batch_bytes(&self, batching: Batching, b: u32, kind: MapKind) -> Vec<u8> {
        let maps = match kind {
            MapKind::Shooting => &self.shooting,
            MapKind::Totals => &self.total,
        };
        encode(&MapBatchRef {
            version: SPLIT_VERSION,
            iterations: self.iterations,
            batch: b,
            maps: maps[self.local(batching, b)].iter().map(Vec::as_slice).collect(),
        })
    }

    /// Where batch `b`'s directions are among the block's.
    fn local(&self, batching: Batching, b: u32) -> std::ops::Range<usize> {
        let first = batching.range(self.batches.start as usize).start;
        let range = batching.range(b as usize);
        range.start - first..range.end - first
    }
}

/// Which of a batch's mirror maps a snapshot part holds ([`Propagation::map_batch_bytes`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MapKind {
    /// What the next iteration shoots from: the arrivals while they are pending, else the
    /// unshot maps ([`super::specular::DirectionMaps::shooting`]).
    Shooting,
    /// The total maps.
    Totals,
}

/// A checkpoint's parts, serialised ([`Propagation::snapshot_bytes`]).
pub struct SnapshotBytes {
    /// [`StateHead::to_bytes`].
    pub head: Vec<u8>,
    /// [`MapBatch::to_bytes`] of every batch's shooting maps, in order (none
    /// without mirrors, or when left out).
    pub shooting: Vec<Vec<u8>>,
    /// [`Totals::to_bytes`], without the mirror totals.
    pub totals: Vec<u8>,
    /// [`MapBatch::to_bytes`] of every batch's mirror totals, in order (none
    /// without mirrors, or when left out).
    pub mirror_totals: Vec<Vec<u8>>,
}

/// The parts over borrowed maps: the same bincode bytes (a slice serialises
/// as a vector does), without copying megabytes of maps first.
#[derive(Serialize)]
struct StateHeadRef<'a> {
    version: u32,
    stats: &'a [IterationStats],
    current: &'a [Rgb],
    mirror_batches: Option<u32>,
    pending: Option<&'a Pending>,
}

#[derive(Serialize)]
struct MapBatchRef<'a> {
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
    /// The total mirror maps of batch `b` of the directions, direction after direction, as
    /// held now: what a snapshot's mirror radiance is made of (none without mirrors).
    pub fn mirror_totals_of_batch(&self, b: usize) -> Vec<Cow<'_, [Rgb]>> {
        let range = self.batching().range(b);
        self.specular
            .as_ref()
            .map_or(Vec::new(), |s| range.map(|d| s.map_or_zeros(d, |m| &m.total)).collect())
    }

    /// The parts of [`Propagation::checkpoint`], serialised in parallel:
    /// equal to `checkpoint().split()` with the shooting half
    /// [`ShootingState::into_parts`] and the totals [`Totals::into_parts`],
    /// each `to_bytes`, without the copy. Without `maps`, the mirror maps
    /// are left out: the service's coordinator, whose workers write them.
    pub fn snapshot_bytes(&self, maps: bool) -> SnapshotBytes {
        let spec = self.specular.as_ref();
        let batching = self.batching();
        let batches = if maps && spec.is_some() { batching.count() } else { 0 };
        let ((head, totals), (shooting, mirror_totals)) = rayon::join(
            || rayon::join(|| encode(&self.head_ref()), || self.totals_bytes()),
            || {
                rayon::join(
                    || {
                        (0..batches)
                            .into_par_iter()
                            .map(|b| self.map_batch_bytes(b, MapKind::Shooting))
                            .collect()
                    },
                    || {
                        (0..batches)
                            .into_par_iter()
                            .map(|b| self.map_batch_bytes(b, MapKind::Totals))
                            .collect()
                    },
                )
            },
        );
        SnapshotBytes {
            head,
            shooting,
            totals,
            mirror_totals,
        }
    }

    /// The snapshot's head over this propagation's state: [`SnapshotBytes::head`] serialised.
    fn head_ref(&self) -> StateHeadRef<'_> {
        let spec = self.specular.as_ref();
        StateHeadRef {
            version: HEAD_VERSION,
            stats: &self.stats,
            current: &self.current,
            mirror_batches: spec.map(|_| self.batching().count() as u32),
            pending: spec.and_then(|s| s.pending.as_ref()),
        }
    }

    /// The snapshot's diffuse totals over this propagation's state: [`SnapshotBytes::totals`]
    /// serialised.
    fn totals_ref(&self) -> TotalsRef<'_> {
        TotalsRef {
            version: SPLIT_VERSION,
            iterations: self.iterations_done(),
            total: &self.total,
            mirrors: None,
        }
    }

    /// [`SnapshotBytes::totals`] alone.
    pub fn totals_bytes(&self) -> Vec<u8> {
        encode(&self.totals_ref())
    }

    /// How many bytes [`Propagation::write_head_to`] writes.
    pub fn head_len(&self) -> u64 {
        bincode::serialized_size(&self.head_ref()).expect("bincode sizes plain numbers")
    }

    /// Writes [`SnapshotBytes::head`] to `writer`, the same bytes, as they are serialised: one
    /// part of [`Propagation::snapshot_bytes`], apart so that whoever stores a snapshot
    /// compresses the head as it goes: a head is mostly Current, a value per texel (3.4 MB for the
    /// Cornell box at l = 8193, N = 256).
    pub fn write_head_to(&self, writer: impl std::io::Write) -> std::io::Result<()> {
        encode_into(writer, &self.head_ref())
    }

    /// The [`MapBatch::to_bytes`] of batch `b`'s mirror maps of `kind`, as held now: one part of
    /// [`Propagation::snapshot_bytes`]. Apart so that whoever stores a snapshot compresses each
    /// batch as it is serialised: all at once, the serialised maps of every direction were held
    /// together, 2.1 GB for a coordinator writing the mirror scene's first snapshot at l = 8193,
    /// N = 256. Maps never shot are not held ([`super::specular::Unheld`]): the batch's zeros are
    /// made for it.
    pub fn map_batch_bytes(&self, b: usize, kind: MapKind) -> Vec<u8> {
        let range = self.batching().range(b);
        let maps: Vec<Cow<[Rgb]>> = self.specular.as_ref().map_or(Vec::new(), |s| {
            let pending = s.pending.is_some();
            range
                .map(|d| match kind {
                    MapKind::Shooting => s.map_or_zeros(d, |m| m.shooting(pending)),
                    MapKind::Totals => s.map_or_zeros(d, |m| &m.total),
                })
                .collect()
        });
        encode(&MapBatchRef {
            version: SPLIT_VERSION,
            iterations: self.iterations_done(),
            batch: b as u32,
            maps: maps.iter().map(|m| m.as_ref()).collect(),
        })
    }

    /// Restores the head of a shooting state: the statistics, Current and
    /// what the pending arrivals come to. The mirror maps held are let go: the snapshot's are
    /// elsewhere ([`super::specular::Unheld::Elsewhere`]) until their batches
    /// are restored ([`Propagation::restore_shooting_batch`],
    /// [`Propagation::restore_totals_batch`]) or adopted
    /// ([`Propagation::adopt_mirrors`]), so a replica holds the maps of the
    /// directions it reads, not of every direction it ever read. Like
    /// [`Propagation::restore_shooting`], for a replica that computes blocks
    /// only. On error the state is unchanged.
    pub fn restore_head(&mut self, head: StateHead) -> crate::Result<()> {
        self.check_unshot_texels(&head.current, &head.stats)?;
        let expected = self.specular.as_ref().map(|_| self.batching().count() as u32);
        if head.mirror_batches != expected {
            return misfit(format!(
                "{:?} batches of mirror maps, the scene has {expected:?}",
                head.mirror_batches
            ));
        }
        self.check_pending(head.pending.as_ref())?;
        let batching = self.batching();
        if let Some(spec) = self.specular.as_mut() {
            spec.pending = head.pending;
            // Arrivals an earlier build left with their `Φ_in` are settled as this build's are.
            spec.settle_pending(&self.scene, &batching);
            spec.release_maps();
        }
        self.current = head.current;
        self.stats = head.stats;
        Ok(())
    }

    /// Restores the shooting maps of one batch of directions, of the
    /// snapshot whose head was restored last (arrivals or unshot maps, as
    /// the head says; arrivals with their `Φ_in`, found from them,
    /// [`super::Specular::know_arrivals`]). On error the state is unchanged.
    pub fn restore_shooting_batch(&mut self, part: MapBatch) -> crate::Result<()> {
        let range = self.check_map_batch(&part)?;
        if let Some(spec) = self.specular.as_mut() {
            let pending = spec.pending.is_some();
            for (own, saved) in spec.maps[range.clone()].iter_mut().zip(part.maps) {
                own.set_shooting(pending, saved);
            }
            // Arrivals: their `Φ_in`, for the gathers that read them.
            spec.know_arrivals(&self.directions, range);
        }
        Ok(())
    }

    /// Restores the total mirror maps of one batch of directions, of the
    /// snapshot whose head was restored last. On error the state is
    /// unchanged.
    pub fn restore_totals_batch(&mut self, part: MapBatch) -> crate::Result<()> {
        let range = self.check_map_batch(&part)?;
        if let Some(spec) = self.specular.as_mut() {
            for (own, saved) in spec.maps[range].iter_mut().zip(part.maps) {
                own.total = saved;
            }
        }
        Ok(())
    }

    /// The directions of a batch of mirror maps that fits this propagation's
    /// state — a batch of its directions, after as many iterations, one value per mirror slot,
    /// finite and non-negative — or why it does not.
    pub fn check_map_batch(&self, part: &MapBatch) -> crate::Result<std::ops::Range<usize>> {
        let batching = self.batching();
        let iterations = self.iterations_done();
        if self.specular.is_none() {
            return misfit("mirror maps for a scene without mirrors".into());
        }
        let b = part.batch as usize;
        if b >= batching.count() || part.iterations != iterations {
            return misfit(format!(
                "mirror maps of batch {b} after {} iterations, for a state after {iterations} with {} batches",
                part.iterations,
                batching.count()
            ));
        }
        let range = batching.range(b);
        if part.maps.len() != range.len() {
            return misfit(format!(
                "batch {b}: {} mirror maps for {} directions",
                part.maps.len(),
                range.len()
            ));
        }
        self.check_mirror_maps(range.start, &part.maps)?;
        Ok(range)
    }
}

/// The bytes earlier builds wrote, for tests of the stores they left: a
/// checkpoint or head without pending arrivals (their shooting maps are
/// unshot maps) in the layouts of version 1 (whole) and 2 (head), and with
/// pending `Φ_in`, dense in those of version 3 (whole) and 4 (head), sparse in
/// 5 and 6. The `Φ_in` of arrivals is what the propagation they come from
/// knows of it: one that ran the whole propagation.
#[doc(hidden)]
pub mod earlier {
    use super::*;
    use crate::propagate::Checkpoint;
    use crate::propagate::specular::MirrorPower;

    #[derive(Serialize)]
    struct WholeV1<'a> {
        version: u32,
        stats: &'a [IterationStats],
        current: &'a [Rgb],
        total: &'a [Rgb],
        mirrors: Option<Vec<(&'a [Rgb], &'a [Rgb])>>,
    }

    #[derive(Serialize)]
    struct HeadV2<'a> {
        version: u32,
        stats: &'a [IterationStats],
        current: &'a [Rgb],
        unshot_batches: Option<u32>,
    }

    /// `checkpoint` as a version 1 blob; `None` with pending arrivals.
    pub fn whole_v1(checkpoint: &Checkpoint) -> Option<Vec<u8>> {
        checkpoint.pending.is_none().then(|| {
            encode(&WholeV1 {
                version: 1,
                stats: &checkpoint.stats,
                current: &checkpoint.current,
                total: &checkpoint.total,
                mirrors: checkpoint
                    .mirrors
                    .as_ref()
                    .map(|m| m.iter().map(|d| (&d.shooting[..], &d.total[..])).collect()),
            })
        })
    }

    /// Every direction's `Φ_in` that `pending` knows, over `directions` directions.
    fn power_in(pending: &Pending, directions: usize) -> Vec<MirrorPower> {
        let known = pending.all_power_in(directions);
        let known = known.expect("the Φ_in of every direction is known where the whole propagation ran");
        known.into_iter().cloned().collect()
    }

    /// `checkpoint` as a version 3 blob (`sparse`: 5), its pending `Φ_in` dense over `mirrors`
    /// mirrors (sparse).
    pub fn whole_of_power(checkpoint: &Checkpoint, mirrors: usize, sparse: bool) -> Vec<u8> {
        fn whole<P: Serialize>(c: &Checkpoint, version: u32, pending: Option<P>) -> Vec<u8> {
            encode(&CheckpointOfPower {
                version,
                stats: c.stats.clone(),
                current: c.current.clone(),
                total: c.total.clone(),
                mirrors: c.mirrors.clone(),
                pending,
            })
        }
        let l = checkpoint.mirrors.as_ref().map_or(0, Vec::len);
        let power = checkpoint.pending.as_ref().map(|p| power_in(p, l));
        match sparse {
            true => whole(checkpoint, 5, power.map(|power_in| SparsePending { power_in })),
            false => whole(checkpoint, 3, power.map(|p| DensePending::of(&p, mirrors))),
        }
    }

    /// `head` (of `directions` directions) as a version 4 blob (`sparse`: 6), its pending `Φ_in`
    /// dense over `mirrors` mirrors (sparse).
    pub fn head_of_power(head: &StateHead, directions: usize, mirrors: usize, sparse: bool) -> Vec<u8> {
        fn old<P: Serialize>(head: &StateHead, version: u32, pending: Option<P>) -> Vec<u8> {
            encode(&StateHeadOfPower {
                version,
                stats: head.stats.clone(),
                current: head.current.clone(),
                mirror_batches: head.mirror_batches,
                pending,
            })
        }
        let power = head.pending.as_ref().map(|p| power_in(p, directions));
        match sparse {
            true => old(head, HEAD_SPARSE, power.map(|power_in| SparsePending { power_in })),
            false => old(head, HEAD_DENSE, power.map(|p| DensePending::of(&p, mirrors))),
        }
    }

    /// `output` as earlier builds wrote it, with `power_in`, the `Φ_in` of its directions, in
    /// place of its arrivals: dense over `mirrors` mirrors, or `sparse`.
    pub fn batch_output_of_power(
        output: &crate::propagate::BatchOutput,
        power_in: &[MirrorPower],
        mirrors: usize,
        sparse: bool,
    ) -> Vec<u8> {
        use crate::propagate::BatchOutput;
        use crate::propagate::output::OutputOfPower;
        fn old<P: Serialize>(output: &BatchOutput, power_in: Vec<P>) -> Vec<u8> {
            encode(&OutputOfPower {
                iteration: output.iteration,
                pass: output.pass,
                batches: output.batches.clone(),
                sum: output.sum.clone(),
                power_in: output.arrivals.as_ref().map(|_| power_in),
            })
        }
        if sparse {
            let mut bytes = 0xB05A_25E2u32.to_le_bytes().to_vec();
            bytes.extend(old(output, power_in.to_vec()));
            return bytes;
        }
        old(output, DensePending::of(power_in, mirrors).power_in)
    }

    /// `head` as a version 2 blob; `None` with pending arrivals.
    pub fn head_v2(head: &StateHead) -> Option<Vec<u8>> {
        head.pending.is_none().then(|| {
            encode(&HeadV2 {
                version: SPLIT_VERSION,
                stats: &head.stats,
                current: &head.current,
                unshot_batches: head.mirror_batches,
            })
        })
    }
}
