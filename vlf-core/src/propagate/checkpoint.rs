//! Checkpoints: the state of a propagation between two iterations, enough
//! to resume it with **the same bits** as if it had never stopped.
//!
//! Everything else a [`Propagation`] holds — directions, subfields, texel
//! grids, discrete areas, mirror layouts and reflection routes — is a
//! deterministic function of the scene and the [`Options`], so it is rebuilt
//! rather than stored (a job stores its [survey](super::survey) as well, the
//! part that costs a pass over every subfield to learn). What remains is
//! small and exact (f64, never a lossy encoding):
//!
//! * the diffuse Current (unshot) and Total maps, per texel;
//! * with mirrors, every direction's total map over its mirror slots and
//!   what the next iteration shoots from: the arrivals of the last iteration
//!   and what they come to when they wait to be reflected
//!   ([`super::specular::Pending`], the usual case), else the unshot maps;
//! * the statistics of the iterations done, whose count is the next
//!   iteration's index (which seeds the perturbation and the mirror plan).
//!
//! **Two halves.** Shooting the next iteration reads the shooting maps; the
//! totals are read by whoever shoots a direction (its total grows by what it
//! sends), by whoever finishes iterations (the diffuse Total) and by a viewer
//! of the snapshot (a snapshot's mirror radiance is its mirror totals). So a
//! checkpoint splits into the [`ShootingState`] (statistics, Current, what the
//! pending arrivals come to, shooting maps) and the [`Totals`] (Total, mirror totals);
//! [`Checkpoint::join`] puts them back together. How they are stored — the
//! mirror maps cut further, by batch of directions — is [`super::snapshot`].
//!
//! Serialised with bincode behind a version number, one per layout: 7 is the
//! whole checkpoint in one blob, 8 the shooting state's head, 2 the other
//! parts. Stores written by earlier builds hold version 1 (a whole
//! checkpoint without pending arrivals: its shooting maps are unshot maps),
//! version 2 heads (the same, in parts), versions 3 and 4 (whole and head
//! with pending `Φ_in` dense, a value for every mirror) or 5 and 6 (the same,
//! `Φ_in` sparse, [`super::specular::MirrorPower`]), where this build's hold
//! the arrivals settled instead ([`super::specular::Settled`]): all are still
//! read, and their `Φ_in` settled as they are restored.
//! [`Checkpoint::from_bytes`] and [`Propagation::resume`] refuse anything
//! that does not fit the rebuilt geometry, or that is not finite and
//! non-negative, with an [`Error::Decode`].

use super::specular::{MirrorPower, Pending};
use super::{IterationStats, Options, Propagation};
use crate::error::Error;
use crate::scene::{Rgb, Scene};
use serde::{Deserialize, Serialize};

/// The whole checkpoint of earlier builds, without pending arrivals.
const WHOLE_V1: u32 = 1;
/// The parts' serialisation ([`Totals`], [`super::MapBatch`]; and the head
/// of earlier builds, without pending arrivals).
pub(crate) const SPLIT_VERSION: u32 = 2;
/// The whole checkpoint of earlier builds, with dense pending `Φ_in`.
const CHECKPOINT_DENSE: u32 = 3;
/// The shooting state's head of earlier builds, with dense pending `Φ_in`.
pub(crate) const HEAD_DENSE: u32 = 4;
/// The whole checkpoint of earlier builds, with sparse pending `Φ_in`.
const CHECKPOINT_SPARSE: u32 = 5;
/// The shooting state's head of earlier builds, with sparse pending `Φ_in`.
pub(crate) const HEAD_SPARSE: u32 = 6;
/// The whole checkpoint (one blob).
const CHECKPOINT_VERSION: u32 = 7;
/// The shooting state's head ([`super::StateHead`]).
pub(crate) const HEAD_VERSION: u32 = 8;

/// Pending arrivals as the builds of versions 5 and 6 stored them: `Φ_in` of every direction,
/// sparse.
#[derive(Serialize, Deserialize)]
pub(crate) struct SparsePending {
    pub(crate) power_in: Vec<MirrorPower>,
}

/// Pending arrivals as earlier builds stored them: `Φ_in` of every mirror of
/// every direction, zeros included.
#[derive(Serialize, Deserialize)]
pub(crate) struct DensePending {
    pub(crate) power_in: Vec<Vec<Rgb>>,
}

impl DensePending {
    /// The same `Φ_in` with its zeros left out.
    pub(crate) fn sparse(self) -> Vec<MirrorPower> {
        (self.power_in.into_iter())
            .map(|dense| {
                (dense.into_iter().enumerate())
                    .filter(|(_, v)| v.iter().any(|&c| c != 0.0))
                    .map(|(k, v)| (k as u32, v))
                    .collect()
            })
            .collect()
    }

    /// `power_in` with a value for each of `mirrors` mirrors.
    pub(crate) fn of(power_in: &[MirrorPower], mirrors: usize) -> DensePending {
        let power_in = (power_in.iter())
            .map(|sparse| {
                let mut dense = vec![[0.0; 3]; mirrors];
                for &(k, v) in sparse {
                    dense[k as usize] = v;
                }
                dense
            })
            .collect();
        DensePending { power_in }
    }
}

/// The bincode bytes of `value`.
pub(crate) fn encode(value: &impl Serialize) -> Vec<u8> {
    bincode::serialize(value).expect("bincode into memory cannot fail for plain numbers")
}

/// [`encode`] into `writer`, as its bytes are made: what a writer that compresses as it goes
/// takes (a batch output, a snapshot's head). Its errors are the writer's.
pub(crate) fn encode_into(writer: impl std::io::Write, value: &impl Serialize) -> std::io::Result<()> {
    bincode::serialize_into(writer, value).map_err(|e| match *e {
        bincode::ErrorKind::Io(e) => e,
        other => std::io::Error::other(other.to_string()),
    })
}

/// Reads the first bytes of `reader` into `head`, as many as it has up to `head`'s length: how
/// a reader's leading mark or version is told before what follows it is deserialised. Returns
/// how many were read (fewer where the reader ends first).
pub(crate) fn read_head(mut reader: impl std::io::Read, head: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < head.len() {
        match reader.read(&mut head[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// The serialisation version a checkpoint blob starts with (bincode writes
/// the leading `u32` little-endian), if it is long enough to have one.
pub(crate) fn version_of(bytes: &[u8]) -> Option<u32> {
    bytes.get(..4).map(|v| u32::from_le_bytes([v[0], v[1], v[2], v[3]]))
}

/// The specular maps of one direction in a checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DirectionCheckpoint {
    /// What the next iteration shoots from: the pending arrivals (incident
    /// radiance) when the checkpoint has [`Checkpoint::pending`], else the
    /// unshot radiance.
    pub shooting: Vec<Rgb>,
    pub total: Vec<Rgb>,
}

/// The state of a propagation after `stats.len()` iterations.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    version: u32,
    pub stats: Vec<IterationStats>,
    /// Unshot power per texel.
    pub current: Vec<Rgb>,
    /// Power that left each texel so far.
    pub total: Vec<Rgb>,
    /// Per direction, `None` without specular machinery.
    pub mirrors: Option<Vec<DirectionCheckpoint>>,
    /// What the arrivals the shooting maps hold come to, when they wait to be
    /// reflected.
    pub pending: Option<Pending>,
}

/// [`Checkpoint`] with pending `Φ_in`, dense (version 3, `P` = [`DensePending`]) or sparse
/// (version 5, [`SparsePending`]).
#[derive(Serialize, Deserialize)]
pub(crate) struct CheckpointOfPower<P> {
    pub(crate) version: u32,
    pub(crate) stats: Vec<IterationStats>,
    pub(crate) current: Vec<Rgb>,
    pub(crate) total: Vec<Rgb>,
    pub(crate) mirrors: Option<Vec<DirectionCheckpoint>>,
    pub(crate) pending: Option<P>,
}

/// [`Checkpoint`] as earlier builds wrote it (version 1).
#[derive(Deserialize)]
struct CheckpointV1 {
    version: u32,
    stats: Vec<IterationStats>,
    current: Vec<Rgb>,
    total: Vec<Rgb>,
    mirrors: Option<Vec<DirectionCheckpoint>>,
}

impl Checkpoint {
    /// A checkpoint of this build's version from its parts (however they were read).
    pub fn new(
        stats: Vec<IterationStats>,
        current: Vec<Rgb>,
        total: Vec<Rgb>,
        mirrors: Option<Vec<DirectionCheckpoint>>,
        pending: Option<Pending>,
    ) -> Checkpoint {
        Checkpoint {
            version: CHECKPOINT_VERSION,
            stats,
            current,
            total,
            mirrors,
            pending,
        }
    }

    /// Iterations done when the checkpoint was taken.
    pub fn iterations(&self) -> u32 {
        self.stats.len() as u32
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    /// Reads a whole checkpoint (one blob, of this build or an earlier one).
    pub fn from_bytes(bytes: &[u8]) -> crate::Result<Checkpoint> {
        let bad = |e: bincode::Error| Error::Decode(format!("checkpoint: {e}"));
        match version_of(bytes) {
            Some(CHECKPOINT_VERSION) => bincode::deserialize(bytes).map_err(bad),
            Some(CHECKPOINT_DENSE) => {
                let old: CheckpointOfPower<DensePending> = bincode::deserialize(bytes).map_err(bad)?;
                let pending = old.pending.map(|p| Pending::of_power_in(p.sparse()));
                Ok(Checkpoint::new(old.stats, old.current, old.total, old.mirrors, pending))
            }
            Some(CHECKPOINT_SPARSE) => {
                let old: CheckpointOfPower<SparsePending> = bincode::deserialize(bytes).map_err(bad)?;
                let pending = old.pending.map(|p| Pending::of_power_in(p.power_in));
                Ok(Checkpoint::new(old.stats, old.current, old.total, old.mirrors, pending))
            }
            Some(WHOLE_V1) => {
                let old: CheckpointV1 = bincode::deserialize(bytes).map_err(bad)?;
                debug_assert_eq!(old.version, WHOLE_V1);
                Ok(Checkpoint::new(old.stats, old.current, old.total, old.mirrors, None))
            }
            Some(SPLIT_VERSION | HEAD_DENSE | HEAD_SPARSE | HEAD_VERSION) => Err(Error::Decode(
                "checkpoint: this is the head of a split checkpoint (read it with its other parts)".into(),
            )),
            Some(v) => Err(Error::Decode(format!(
                "checkpoint version {v} (this build reads {WHOLE_V1}, {CHECKPOINT_DENSE}, {CHECKPOINT_SPARSE} and {CHECKPOINT_VERSION})"
            ))),
            None => Err(Error::Decode("checkpoint: truncated".into())),
        }
    }

    /// Whether `bytes` hold the head of a split checkpoint (whose mirror
    /// maps and totals are in other blobs, see [`super::snapshot`]) rather
    /// than a whole one.
    pub fn is_split(bytes: &[u8]) -> bool {
        matches!(
            version_of(bytes),
            Some(SPLIT_VERSION | HEAD_DENSE | HEAD_SPARSE | HEAD_VERSION)
        )
    }

    /// The two halves of this checkpoint.
    pub fn split(self) -> (ShootingState, Totals) {
        let (shooting, totals) = match self.mirrors {
            Some(maps) => {
                let (shooting, total) = maps.into_iter().map(|m| (m.shooting, m.total)).unzip();
                (Some(shooting), Some(total))
            }
            None => (None, None),
        };
        let iterations = self.stats.len() as u32;
        (
            ShootingState {
                stats: self.stats,
                current: self.current,
                mirrors: shooting,
                pending: self.pending,
            },
            Totals {
                version: SPLIT_VERSION,
                iterations,
                total: self.total,
                mirrors: totals,
            },
        )
    }

    /// Puts the halves of one checkpoint back together: they must be of the
    /// same snapshot and have their mirror maps for the same directions and
    /// slots. (Whether they fit a scene is [`Propagation::restore`]'s check.)
    pub fn join(state: ShootingState, totals: Totals) -> crate::Result<Checkpoint> {
        let bad = |m: String| Err(Error::Decode(format!("checkpoint halves do not match: {m}")));
        if state.iterations() != totals.iterations {
            return bad(format!(
                "shooting state after {} iterations, totals after {}",
                state.iterations(),
                totals.iterations
            ));
        }
        if state.current.len() != totals.total.len() {
            return bad(format!(
                "{} unshot and {} total texel values",
                state.current.len(),
                totals.total.len()
            ));
        }
        let mirrors = match (state.mirrors, totals.mirrors) {
            (None, None) => None,
            (Some(shooting), Some(total)) => {
                if shooting.len() != total.len() {
                    return bad(format!(
                        "shooting mirror maps of {} directions, totals of {}",
                        shooting.len(),
                        total.len()
                    ));
                }
                if let Some(d) = shooting.iter().zip(&total).position(|(u, t)| u.len() != t.len()) {
                    return bad(format!("direction {d}: shooting and total maps of different sizes"));
                }
                Some(
                    shooting
                        .into_iter()
                        .zip(total)
                        .map(|(shooting, total)| DirectionCheckpoint { shooting, total })
                        .collect(),
                )
            }
            _ => return bad("only one half has mirror maps".into()),
        };
        Ok(Checkpoint::new(
            state.stats,
            state.current,
            totals.total,
            mirrors,
            state.pending,
        ))
    }
}

/// What shooting the next iteration reads of a checkpoint: the statistics of
/// the iterations done (their count is the next one's index), the diffuse
/// unshot power and every direction's shooting mirror map (see
/// [`DirectionCheckpoint::shooting`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ShootingState {
    pub stats: Vec<IterationStats>,
    /// Unshot power per texel.
    pub current: Vec<Rgb>,
    /// Per direction, its shooting mirror map; `None` without specular machinery.
    pub mirrors: Option<Vec<Vec<Rgb>>>,
    /// What the arrivals the shooting maps hold come to, when they wait to be
    /// reflected.
    pub pending: Option<Pending>,
}

impl ShootingState {
    /// Iterations done when the checkpoint was taken.
    pub fn iterations(&self) -> u32 {
        self.stats.len() as u32
    }
}

/// The totals half of a checkpoint: the power that left every texel and
/// every mirror slot so far (what a snapshot shows).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Totals {
    version: u32,
    /// Iterations done when the checkpoint was taken.
    pub iterations: u32,
    /// Power that left each texel so far.
    pub total: Vec<Rgb>,
    /// Per direction, its total mirror map; `None` without specular
    /// machinery, and in the totals blob of a snapshot whose mirror totals
    /// are stored by batch ([`super::snapshot`]).
    pub mirrors: Option<Vec<Vec<Rgb>>>,
}

impl Totals {
    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    /// Reads totals, or takes them out of a whole (version 1) checkpoint.
    pub fn from_bytes(bytes: &[u8]) -> crate::Result<Totals> {
        if version_of(bytes) == Some(SPLIT_VERSION) {
            bincode::deserialize(bytes).map_err(|e| Error::Decode(format!("checkpoint totals: {e}")))
        } else {
            Checkpoint::from_bytes(bytes).map(|c| c.split().1)
        }
    }
}

impl Propagation {
    /// The state to resume from after the iterations done so far.
    pub fn checkpoint(&self) -> Checkpoint {
        Checkpoint {
            version: CHECKPOINT_VERSION,
            stats: self.stats.clone(),
            current: self.current.clone(),
            total: self.total.clone(),
            mirrors: self.specular.as_ref().map(|s| {
                let pending = s.pending.is_some();
                (0..s.maps.len())
                    .map(|d| DirectionCheckpoint {
                        shooting: s.map_or_zeros(d, |m| m.shooting(pending)).into_owned(),
                        total: s.map_or_zeros(d, |m| &m.total).into_owned(),
                    })
                    .collect()
            }),
            pending: self.specular.as_ref().and_then(|s| s.pending.clone()),
        }
    }

    /// Rebuilds the propagation of `scene` with `options` and restores
    /// `checkpoint` into it: stepping on gives the same bits as the run the
    /// checkpoint was taken from.
    pub fn resume(scene: Scene, options: Options, checkpoint: Checkpoint) -> crate::Result<Propagation> {
        Propagation::resume_within(scene, options, checkpoint, None)
    }

    /// [`Propagation::resume`] holding at most `budget` bytes of subfields, when one is given
    /// ([`Propagation::with_subfield_budget`]).
    pub fn resume_within(
        scene: Scene,
        options: Options,
        checkpoint: Checkpoint,
        budget: Option<usize>,
    ) -> crate::Result<Propagation> {
        let mut p = Propagation::with_subfield_budget(scene, options, budget)?;
        p.restore(checkpoint)?;
        Ok(p)
    }

    /// Replaces this propagation's state by `checkpoint` (of the same scene
    /// and options), keeping the geometry. On error the state is unchanged.
    pub fn restore(&mut self, checkpoint: Checkpoint) -> crate::Result<()> {
        let (state, totals) = checkpoint.split();
        let texels = self.atlas.texels;
        if totals.total.len() != texels {
            return misfit(format!("{} total texel values for {texels} texels", totals.total.len()));
        }
        if !valid(&totals.total) {
            return misfit("negative or non-finite power".into());
        }
        // A mismatch of mirrors and no mirrors is the shooting half's error.
        if let (Some(spec), Some(maps)) = (&self.specular, &totals.mirrors) {
            if maps.len() != spec.maps.len() {
                return misfit(format!(
                    "mirror maps for {} directions, expected {}",
                    maps.len(),
                    spec.maps.len()
                ));
            }
            self.check_mirror_maps(0, maps)?;
        }
        self.restore_shooting(state)?;
        self.total = totals.total;
        if let (Some(spec), Some(maps)) = (&mut self.specular, totals.mirrors) {
            for (own, saved) in spec.maps.iter_mut().zip(maps) {
                own.total = saved;
                // Every map is restored or cleared: those not held are zeros.
                own.unheld = super::specular::Unheld::Zero;
            }
        }
        Ok(())
    }

    /// Replaces this propagation's state by snapshot `head` and its diffuse totals `total`
    /// (of the same scene and options), keeping the geometry, without its mirror maps: what a
    /// coordinator resumes from, whose workers read and write the maps. Those are left where
    /// they are — zeros, when no iteration so far shot any (`Ok(true)`: the coordinator then
    /// writes them into the snapshots until one does), else in the snapshot's parts
    /// (`Ok(false)`, [`super::specular::Unheld::Elsewhere`]). Whole, the maps were three times
    /// the field's mirror totals in the coordinator's memory (the mirror scene at l = 8193,
    /// N = 256: 2.1 GB read back, decoded and held only to be let go after the next iteration).
    /// On error the state is unchanged.
    pub fn restore_without_maps(&mut self, head: super::StateHead, total: Vec<Rgb>) -> crate::Result<bool> {
        if total.len() != self.atlas.texels {
            return misfit(format!(
                "{} total texel values for {} texels",
                total.len(),
                self.atlas.texels
            ));
        }
        if !valid(&total) {
            return misfit("negative or non-finite power".into());
        }
        let iterations = head.iterations();
        self.restore_head(head)?;
        self.total = total;
        // Before the first iteration light can reach a mirror, no iteration uses the maps
        // (`iteration_work`): they are the zeros they started as.
        let first_lit = self.plan.first_mirror_iteration().unwrap_or(u32::MAX);
        let zeros = iterations <= first_lit;
        if zeros && let Some(spec) = self.specular.as_mut() {
            spec.maps
                .iter_mut()
                .for_each(|m| m.unheld = super::specular::Unheld::Zero);
        }
        Ok(zeros)
    }

    /// Replaces the state that shooting reads — the statistics, Current,
    /// the pending arrivals and the shooting mirror maps — by `state`, keeping
    /// the geometry: how a worker moves on to the next iteration from half of
    /// the checkpoint. The totals are left as they were, so a propagation
    /// restored this way computes blocks of the next iteration
    /// ([`Propagation::compute_block`]) with the same bits where it holds the
    /// right totals of the block's directions, but must not step, finish
    /// iterations or be checkpointed (restore a whole checkpoint for that).
    /// On error the state is unchanged.
    pub fn restore_shooting(&mut self, state: ShootingState) -> crate::Result<()> {
        self.check_unshot_texels(&state.current, &state.stats)?;
        self.check_pending(state.pending.as_ref())?;
        let batching = self.batching();
        match (&mut self.specular, state.mirrors) {
            (None, None) => {}
            (Some(spec), Some(maps)) => {
                if maps.len() != spec.maps.len() {
                    return misfit(format!(
                        "mirror maps for {} directions, expected {}",
                        maps.len(),
                        spec.maps.len()
                    ));
                }
                check_maps(spec, 0, &maps)?;
                let pending = state.pending.is_some();
                for (own, saved) in spec.maps.iter_mut().zip(maps) {
                    own.set_shooting(pending, saved);
                }
                spec.pending = state.pending;
                // Every arrival map is here: their `Φ_in` is known (what an earlier build stored
                // of it is the same, found again), and arrivals an earlier build left are settled.
                spec.know_arrivals(&self.directions, 0..self.directions.len());
                spec.settle_pending(&self.scene, &batching);
            }
            (Some(_), None) => return misfit("the scene has mirrors, the checkpoint none".into()),
            (None, Some(_)) => return misfit("the checkpoint has mirror maps, the scene no mirror".into()),
        }
        self.current = state.current;
        self.stats = state.stats;
        Ok(())
    }

    /// Refuses pending arrivals that do not fit the directions, mirrors and batches: settled,
    /// power that is negative or not finite, or sources of batches that do not exist; as an
    /// earlier build stored them, `Φ_in` of other directions or mirrors, negative or not finite.
    pub(crate) fn check_pending(&self, pending: Option<&Pending>) -> crate::Result<()> {
        let Some(p) = pending else {
            return Ok(());
        };
        let Some(spec) = &self.specular else {
            return misfit("pending mirror arrivals for a scene without mirrors".into());
        };
        let l = self.directions.len();
        let batches = self.batching().count();
        if let Some(settled) = p.settled() {
            let x = &settled.exchange;
            if !valid(&[x.incident, x.reflected]) {
                return misfit("negative or non-finite pending mirror power".into());
            }
            let fits =
                |s: &Vec<u32>| s.windows(2).all(|w| w[0] < w[1]) && s.last().is_none_or(|&b| (b as usize) < batches);
            if settled.sources.len() != batches || !settled.sources.iter().all(fits) {
                return misfit(format!(
                    "pending mirror arrivals read from batches that do not fit {batches} batches"
                ));
            }
            return Ok(());
        }
        let Some(power_in) = p.all_power_in(l) else {
            return misfit(format!("pending mirror power not of {l} directions"));
        };
        let mirrors = spec.mirrors.len() as u32;
        if p.power_in(l).is_some() {
            return misfit(format!("pending mirror power for more than {l} directions"));
        }
        if let Some(d) = power_in.iter().position(|v| !mirror_power_fits(v, mirrors)) {
            return misfit(format!(
                "direction {d}'s pending mirror power does not fit {mirrors} mirrors \
                 (increasing mirror numbers, non-negative finite power)"
            ));
        }
        Ok(())
    }

    /// Refuses a Current map and iteration statistics that do not fit: the
    /// wrong texel count, statistics out of order, negative or non-finite
    /// power.
    pub(crate) fn check_unshot_texels(&self, current: &[Rgb], stats: &[IterationStats]) -> crate::Result<()> {
        let texels = self.atlas.texels;
        if current.len() != texels {
            return misfit(format!("{} unshot texel values for {texels} texels", current.len()));
        }
        if let Some(i) = stats.iter().enumerate().position(|(i, s)| s.index != i as u32) {
            return misfit(format!("iteration statistics out of order at {i}"));
        }
        if !valid(current) {
            return misfit("negative or non-finite power".into());
        }
        Ok(())
    }

    /// Refuses mirror maps of the directions from `first` on that do not fit
    /// their mirror slots or hold negative or non-finite radiance.
    pub(crate) fn check_mirror_maps(&self, first: usize, maps: &[Vec<Rgb>]) -> crate::Result<()> {
        match &self.specular {
            Some(spec) => check_maps(spec, first, maps),
            None => misfit("mirror maps for a scene without mirrors".into()),
        }
    }
}

/// [`Propagation::check_mirror_maps`] on `spec` (borrowed apart from the
/// rest of the propagation).
fn check_maps(spec: &super::Specular, first: usize, maps: &[Vec<Rgb>]) -> crate::Result<()> {
    for (d, saved) in (first..).zip(maps) {
        let slots = spec.views.get(d).map_or(0, |v| v.slots());
        if saved.len() != slots {
            return misfit(format!(
                "direction {d}: mirror maps do not match its {slots} mirror slots"
            ));
        }
        if !valid(saved) {
            return misfit(format!("direction {d}: negative or non-finite mirror radiance"));
        }
    }
    Ok(())
}

pub(crate) fn misfit<T>(m: String) -> crate::Result<T> {
    Err(Error::Decode(format!(
        "checkpoint does not fit the scene and options: {m}"
    )))
}

/// Finite and non-negative, as power is. Every value is looked at, with no early exit, so that
/// the check runs in vector registers: it covers every map a worker reads back, megabytes per
/// iteration, and an early exit only pays for data that is bad.
pub(crate) fn valid(v: &[Rgb]) -> bool {
    // `0 ≤ c ≤ MAX` is false for NaN, for infinities and for negative values.
    let power = 0.0..=f64::MAX;
    v.as_flattened().iter().fold(true, |ok, c| ok & power.contains(c))
}

/// Whether `power` is one direction's `Φ_in` over `mirrors` mirrors
/// ([`super::specular::MirrorPower`]): strictly increasing mirror numbers
/// below `mirrors`, non-negative finite power.
pub(crate) fn mirror_power_fits(power: &[(u32, Rgb)], mirrors: u32) -> bool {
    power.windows(2).all(|w| w[0].0 < w[1].0)
        && power.last().is_none_or(|&(k, _)| k < mirrors)
        && power.iter().all(|(_, v)| valid(std::slice::from_ref(v)))
}

#[cfg(test)]
mod tests {
    use super::valid;

    #[test]
    fn power_is_valid_only_when_every_value_is_finite_and_not_negative() {
        let good = [0.0, -0.0, f64::MIN_POSITIVE, 1.0, f64::MAX];
        assert!(valid(&[]));
        assert!(valid(&[[0.0, -0.0, 1.0], [f64::MAX, f64::MIN_POSITIVE, 2.5]]));
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -f64::MIN_POSITIVE, -1.0] {
            // Anywhere among many good values: first, in the middle, last, in any channel.
            for at in [0, 17, 99] {
                for channel in 0..3 {
                    let mut v: Vec<[f64; 3]> = (0..100).map(|i| [good[i % 5]; 3]).collect();
                    v[at][channel] = bad;
                    assert!(!valid(&v), "{bad} at {at}.{channel} passed");
                }
            }
        }
    }
}
