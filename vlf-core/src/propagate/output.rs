//! What a block of batches produces, as it travels from a worker to the coordinator (through
//! the store in the distributed service): its node sum and flow ([`BatchSum`]), what its
//! directions brought to the mirrors ([`Arrivals`]), and, apart, its directions' mirror maps
//! ([`MirrorBlock`]). Outputs of earlier builds still read.

use super::specular::{BatchArrivals, MirrorPower};
use super::{FlowRecord, Pass};
use crate::scene::Rgb;
use serde::{Deserialize, Serialize};
use std::io::Read;
use std::ops::Range;

/// The output of one batch of a pass.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BatchSum {
    /// Per texel, summed over the batch's directions in order: received
    /// power (shooting passes) or discrete area in channel 0 ([`Pass::Areas`]).
    pub texels: Vec<Rgb>,
    /// Power bookkeeping of the batch (zero for [`Pass::Areas`]).
    pub flow: FlowRecord,
}

/// Everything one aligned block of batches produces for the coordinator, as
/// it travels from a worker (through the store, in the distributed service).
/// A block's mirror maps stay out of it: they are the next snapshot's parts
/// ([`MirrorBlock`]), which go straight to the workers that shoot next.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BatchOutput {
    pub iteration: u32,
    pub pass: Pass,
    /// The block of batches (a node of the pass's reduction tree).
    pub batches: Range<u32>,
    /// The block's node sum.
    pub sum: BatchSum,
    /// When the pass uses mirror maps: what the block's directions brought to the mirrors.
    pub arrivals: Option<Arrivals>,
}

/// What the directions of a block brought to the mirrors, as its [`BatchOutput`] reports it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Arrivals {
    /// Settled by the worker that shot them, per batch of the block, in order
    /// ([`super::Specular::settle_batch`]): what this build writes.
    Settled(Vec<BatchArrivals>),
    /// Per direction of the block, in order, `Φ_in` ([`super::Specular::power_in_of`]): what
    /// earlier builds wrote, settled by whoever absorbs it.
    Power(Vec<MirrorPower>),
}

/// The mirror maps of a block's directions after it shot them: their part of
/// the next snapshot (cut by batch into [`super::MapBatch`]es,
/// [`MirrorBlock::batch_bytes`]).
#[derive(Clone, Debug, PartialEq)]
pub struct MirrorBlock {
    /// The snapshot they belong to: iterations done after this one.
    pub iterations: u32,
    /// The block of batches.
    pub batches: Range<u32>,
    /// Whether `shooting` holds arrivals to gather (the iteration exchanged:
    /// [`super::specular::Pending`]) rather than unshot maps.
    pub pending: bool,
    /// Per direction: what the next iteration shoots from.
    pub shooting: Vec<Vec<Rgb>>,
    /// Per direction: its total map, including what it just sent.
    pub total: Vec<Vec<Rgb>>,
    /// While `pending`, per direction: `Φ_in` of the arrivals `shooting` holds, as the block
    /// settled them ([`super::Specular::power_in_of`]): whoever adopts the block knows it without
    /// one more pass over the maps (empty otherwise).
    pub power_in: Vec<MirrorPower>,
}

impl MirrorBlock {
    /// Bytes of the maps it holds.
    pub fn bytes(&self) -> usize {
        let values: usize = (self.shooting.iter().chain(&self.total)).map(Vec::capacity).sum();
        values * std::mem::size_of::<Rgb>()
    }
}

/// The first four bytes of a [`BatchOutput`] of this build, whose arrivals are [`Arrivals`].
const SETTLED_OUTPUT: u32 = 0xB05A_25E3;

/// The first four bytes of a [`BatchOutput`] with sparse `Φ_in` ([`OutputOfPower`]). Earlier
/// builds' outputs start with their iteration, a number far below it, and hold `Φ_in` dense
/// (one value per mirror).
const SPARSE_OUTPUT: u32 = 0xB05A_25E2;

/// [`BatchOutput`] as earlier builds wrote it, with per direction `Φ_in` `P`: sparse
/// ([`MirrorPower`], after [`SPARSE_OUTPUT`]) or, earlier still, dense (`Vec<Rgb>`, a value per
/// mirror, with no mark).
#[derive(Serialize, Deserialize)]
pub(crate) struct OutputOfPower<P> {
    pub(crate) iteration: u32,
    pub(crate) pass: Pass,
    pub(crate) batches: Range<u32>,
    pub(crate) sum: BatchSum,
    pub(crate) power_in: Option<Vec<P>>,
}

impl BatchOutput {
    /// The output as bytes: [`BatchOutput::write_to`] into memory.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(self.serialized_len() as usize);
        self.write_to(&mut bytes).expect("writing into memory cannot fail");
        bytes
    }

    /// How many bytes [`BatchOutput::write_to`] writes: a writer that compresses as it goes
    /// sizes its frame by it, and nothing holds the whole serialised output at once (a pass of
    /// the Cornell box at l = 8193, N = 256 is 3.4 MB of node sums).
    pub fn serialized_len(&self) -> u64 {
        4 + bincode::serialized_size(self).expect("bincode sizes plain numbers")
    }

    /// Writes the output as this build stores it: a four-byte mark, then the fields (bincode).
    pub fn write_to(&self, mut writer: impl std::io::Write) -> std::io::Result<()> {
        writer.write_all(&SETTLED_OUTPUT.to_le_bytes())?;
        super::checkpoint::encode_into(writer, self)
    }

    /// Reads an output of this build, or of an earlier one (`Φ_in`, sparse or dense, read as
    /// [`Arrivals::Power`]): a coordinator of this build may take over an iteration whose outputs
    /// an earlier one left.
    pub fn from_bytes(bytes: &[u8]) -> crate::Result<BatchOutput> {
        BatchOutput::read_from(bytes)
    }

    /// [`BatchOutput::from_bytes`] from a reader, as its bytes come (out of a decompressor, say):
    /// nothing holds the whole serialised output at once.
    pub fn read_from(mut reader: impl std::io::Read) -> crate::Result<BatchOutput> {
        let bad = |e: bincode::Error| crate::Error::Decode(format!("batch output: {e}"));
        let mut head = [0u8; 4];
        let got = super::checkpoint::read_head(&mut reader, &mut head)
            .map_err(|e| crate::Error::Decode(format!("batch output: {e}")))?;
        let mark = (got == head.len()).then(|| u32::from_le_bytes(head));
        if mark == Some(SETTLED_OUTPUT) {
            return bincode::deserialize_from(reader).map_err(bad);
        }
        let (iteration, pass, batches, sum, power_in) = if mark == Some(SPARSE_OUTPUT) {
            let old: OutputOfPower<MirrorPower> = bincode::deserialize_from(reader).map_err(bad)?;
            (old.iteration, old.pass, old.batches, old.sum, old.power_in)
        } else {
            // An earlier build's output: its first bytes are the iteration's, read again.
            let old: OutputOfPower<Vec<Rgb>> = bincode::deserialize_from((&head[..got]).chain(reader)).map_err(bad)?;
            let sparse = old
                .power_in
                .map(|p| super::checkpoint::DensePending { power_in: p }.sparse());
            (old.iteration, old.pass, old.batches, old.sum, sparse)
        };
        Ok(BatchOutput {
            iteration,
            pass,
            batches,
            sum,
            arrivals: power_in.map(Arrivals::Power),
        })
    }
}
