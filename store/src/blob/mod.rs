//! The blob format: a fixed 48-byte header, then one zstd frame.
//!
//! Every object VLF stores is a blob, so that any byte string read back is either exactly what
//! was written, of the kind the reader expects, or a [`BlobError`] saying what is wrong — never a
//! panic and never garbage radiance.
//!
//! # Header (all integers little-endian)
//!
//! | offset | size | field | meaning |
//! |---:|---:|---|---|
//! | 0 | 4 | magic | `b"VLFB"` |
//! | 4 | 2 | version | format version, [`FORMAT_VERSION`]; stays at offset 4 in every version |
//! | 6 | 2 | kind | [`BlobKind`] as `u16` |
//! | 8 | 1 | encoding | [`Encoding`] as `u8` |
//! | 9 | 1 | rank | number of dimensions used, 0 ..= 3 |
//! | 10 | 2 | reserved | zero |
//! | 12 | 12 | dims | 3 × `u32`; the first `rank` are the shape, the rest zero |
//! | 24 | 8 | raw length | `u64`, payload bytes before compression |
//! | 32 | 8 | stored length | `u64`, payload bytes after compression (= blob length − 48) |
//! | 40 | 4 | payload crc | CRC-32C of the stored (compressed) payload |
//! | 44 | 4 | header crc | CRC-32C of header bytes 0 .. 44 |
//! | 48 | … | payload | one zstd frame |
//!
//! The payload checksum is of the compressed bytes, so corruption is caught before zstd ever
//! sees them; the header checksum catches a flipped shape or encoding that would otherwise still
//! decode into plausible but wrong numbers.
//!
//! # Payload
//!
//! * [`Encoding::Bytes`]: the caller's bytes (JSON, bincode, …), rank 0.
//! * [`Encoding::F32`], [`Encoding::F16`], [`Encoding::Rgb9e5`]: `f32` values in row-major
//!   order, rank 1 ..= 3, the product of the dims being the number of `f32` values; converted to
//!   the encoding (see the `codec` module), then byte-shuffled into planes. RGB9E5 needs a last
//!   dimension of 3. Decoding checks that every value is finite.

mod decode;
mod encode;

pub use decode::{decode, decode_bytes, decode_bytes_with, decode_rgb, decode_values, same_content};
pub use encode::{STREAM_FROM, encode_bytes, encode_bytes_with, encode_rgb, encode_values};

use crate::codec::{self, Unrepresentable};
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use std::io::{Read, Write};

/// The four bytes every blob starts with.
pub const MAGIC: [u8; 4] = *b"VLFB";

/// The version of the layout above that this crate writes and reads.
pub const FORMAT_VERSION: u16 = 1;

/// Length of the fixed header.
pub const HEADER_LEN: usize = 48;

/// Highest number of dimensions of a shape.
pub const MAX_RANK: usize = 3;

/// zstd level of what is read again and again (the field's tiles and maps, the scene): fast,
/// and within a few percent of the higher levels on radiance.
const ZSTD_LEVEL: i32 = 3;

/// The threads a multithreaded compression runs on: this machine's cores, at most 8.
static ZSTD_WORKERS: std::sync::LazyLock<u32> =
    std::sync::LazyLock::new(|| std::thread::available_parallelism().map_or(1, |n| n.get().min(8) as u32));

/// zstd level of what is written every iteration and read once or twice (a snapshot's resume
/// state, a batch's output): on the f64 sums and mirror maps of the mirror scene it writes ×4
/// faster than level 3 for about 15 % more bytes, which halves what an iteration spends in the
/// store — in-process, and twice over in the service, where workers read the state back.
const ZSTD_LEVEL_TRANSIENT: i32 = -3;

/// What a blob holds. Stored as a `u16`; new kinds get new numbers, never reused ones, and a
/// reader meeting a number it does not know reports [`BlobError::UnknownKind`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[non_exhaustive]
pub enum BlobKind {
    /// A job's manifest (JSON).
    Manifest = 1,
    /// The normalised scene of a job (caller's serialisation).
    Scene = 2,
    /// The resume state of one iteration (caller's serialisation).
    Snapshot = 3,
    /// Total radiance maps of one diffuse surface.
    DiffuseMaps = 4,
    /// Radiance of one tile of one direction's parallel subfield.
    TileRadiance = 5,
    /// Directional maps of one mirror.
    MirrorMaps = 6,
    /// Anything else.
    Raw = 7,
    /// A stage's summary (JSON): iterations, unshot power, statistics.
    Summary = 8,
    /// The output of one block of batches of directions of one pass of an iteration (caller's
    /// serialisation).
    BatchOutput = 9,
    /// What setting a job up learns over all its directions (caller's serialisation).
    Survey = 10,
    /// Radiance of every mirror slot of one direction's parallel subfield, tile after tile: a
    /// final field's mirror radiance, one blob per direction (earlier builds wrote one
    /// [`BlobKind::TileRadiance`] per tile).
    DirectionRadiance = 11,
    /// Radiance of every mirror slot of a batch of directions, direction after direction: a
    /// snapshot's mirror radiance in the job's encoding (`iters/K/mirror-radiance/`), what
    /// renders read of it once its exact `f64` totals are compacted away.
    BatchRadiance = 12,
    /// What a block of a job's directions adds to its survey, learnt by a worker before the job
    /// is set up (caller's serialisation; `jobs/J/work/00000/survey/`).
    SurveyPart = 13,
    /// Every direction's mirror view and the reflection routes of a job with mirrors, computed
    /// when it is set up (caller's serialisation): what its workers read rather than compute.
    MirrorGeometry = 14,
}

impl BlobKind {
    /// Every kind, in numeric order.
    pub const ALL: [BlobKind; 14] = [
        BlobKind::Manifest,
        BlobKind::Scene,
        BlobKind::Snapshot,
        BlobKind::DiffuseMaps,
        BlobKind::TileRadiance,
        BlobKind::MirrorMaps,
        BlobKind::Raw,
        BlobKind::Summary,
        BlobKind::BatchOutput,
        BlobKind::Survey,
        BlobKind::DirectionRadiance,
        BlobKind::BatchRadiance,
        BlobKind::SurveyPart,
        BlobKind::MirrorGeometry,
    ];

    /// The number stored in the header.
    pub fn code(self) -> u16 {
        self as u16
    }

    /// The zstd level blobs of this kind are written with (any level reads back the same way).
    fn zstd_level(self) -> i32 {
        match self {
            BlobKind::Snapshot | BlobKind::BatchOutput | BlobKind::SurveyPart => ZSTD_LEVEL_TRANSIENT,
            _ => ZSTD_LEVEL,
        }
    }

    /// The worker threads that compress a blob of this kind (0: the calling thread alone). A
    /// job's mirror geometry, 168 MB for a curved mirror of 47 794 triangles at l = 2049, N = 128,
    /// which the coordinator compresses while the job's workers wait for it (1.2 s on one thread of
    /// the 2-core VM). What is compressed as it is serialised ([`encode_bytes_with`]) is so too,
    /// whatever its kind. zstd's frame is the same bytes for any number of workers from one on (it
    /// cuts the input into jobs by size, not by worker), so the blob is the same whatever machine
    /// writes it, as a create-only write of it again asks.
    fn zstd_workers(self) -> u32 {
        match self {
            BlobKind::MirrorGeometry => *ZSTD_WORKERS,
            _ => 0,
        }
    }

    /// The kind stored as `code`, if known.
    pub fn from_code(code: u16) -> Option<BlobKind> {
        BlobKind::ALL.into_iter().find(|k| k.code() == code)
    }
}

/// How a blob's payload is represented. Stored as a `u8`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[non_exhaustive]
pub enum Encoding {
    /// Opaque bytes from the caller.
    Bytes = 0,
    /// Lossless `f32`.
    F32 = 1,
    /// IEEE half precision: compact, relative error ≤ 2⁻¹¹ for normal values.
    F16 = 2,
    /// Shared-exponent RGB in 32 bits per triple: most compact, non-negative values only.
    Rgb9e5 = 3,
}

impl Encoding {
    /// Every encoding, in numeric order.
    pub const ALL: [Encoding; 4] = [Encoding::Bytes, Encoding::F32, Encoding::F16, Encoding::Rgb9e5];
    /// The encodings of `f32` values (all but [`Encoding::Bytes`]).
    pub const VALUES: [Encoding; 3] = [Encoding::F32, Encoding::F16, Encoding::Rgb9e5];

    /// The number stored in the header.
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The encoding stored as `code`, if known.
    pub fn from_code(code: u8) -> Option<Encoding> {
        Encoding::ALL.into_iter().find(|e| e.code() == code)
    }

    /// Raw payload bytes for `count` values, or `None` if `count` does not fit the encoding.
    fn raw_len(self, count: u64) -> Option<u64> {
        match self {
            Encoding::Bytes => Some(count),
            Encoding::F32 => count.checked_mul(4),
            Encoding::F16 => count.checked_mul(2),
            Encoding::Rgb9e5 => count.is_multiple_of(3).then_some(count / 3 * 4),
        }
    }

    /// Size of one stored element, the unit of the byte shuffle.
    fn element_size(self) -> usize {
        match self {
            Encoding::Bytes => 1,
            Encoding::F32 | Encoding::Rgb9e5 => 4,
            Encoding::F16 => 2,
        }
    }
}

/// Everything that can be wrong when encoding or decoding a blob.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum BlobError {
    /// Fewer bytes than the header or the header's stored length says.
    #[error("truncated blob: {actual} bytes, expected {expected}")]
    Truncated { expected: u64, actual: u64 },
    /// More bytes than the header's stored length says.
    #[error("blob has {extra} bytes after its payload")]
    TrailingBytes { extra: u64 },
    /// Not a VLF blob at all.
    #[error("not a VLF blob: starts with {found:02x?}, expected \"VLFB\"")]
    BadMagic { found: Vec<u8> },
    /// Written by another version of the format.
    #[error("blob format version {found} is not supported (this build reads version {supported})")]
    UnsupportedVersion { found: u16, supported: u16 },
    /// The header does not match its own checksum.
    #[error("blob header checksum mismatch: stored {stored:08x}, computed {computed:08x}")]
    HeaderChecksum { stored: u32, computed: u32 },
    /// A kind number this build does not know.
    #[error("unknown blob kind {0}")]
    UnknownKind(u16),
    /// A valid blob, but not of the kind the reader asked for.
    #[error("wrong blob kind: expected {expected:?}, found {found:?}")]
    WrongKind { expected: BlobKind, found: BlobKind },
    /// An encoding number this build does not know.
    #[error("unknown blob encoding {0}")]
    UnknownEncoding(u8),
    /// A shape that is inconsistent with itself, the encoding or the data.
    #[error("bad shape {shape:?} for encoding {encoding:?}: {reason}")]
    BadShape {
        shape: Vec<u32>,
        encoding: Encoding,
        reason: String,
    },
    /// The header's reserved bytes are not zero.
    #[error("blob header has non-zero reserved bytes")]
    Reserved,
    /// The payload does not match its checksum.
    #[error("blob payload checksum mismatch: stored {stored:08x}, computed {computed:08x}")]
    ChecksumMismatch { stored: u32, computed: u32 },
    /// zstd could not decompress the payload, or it had another length than the header says.
    #[error("blob payload does not decompress: {0}")]
    Decompress(String),
    /// A decoded radiance value is NaN or infinite.
    #[error("decoded value {index} is not finite ({value})")]
    NonFinite { index: usize, value: f32 },
    /// A value cannot be represented in the requested encoding.
    #[error("value {index} ({value}) cannot be stored as {encoding:?}: {reason}")]
    Unrepresentable {
        index: usize,
        value: f32,
        encoding: Encoding,
        reason: &'static str,
    },
    /// zstd failed to compress (only on allocation failure).
    #[error("cannot compress blob payload: {0}")]
    Compress(String),
    /// The payload's reader stopped before its end ([`decode_bytes_with`]).
    #[error("blob payload holds {raw_len} bytes, of which its reader took {read}")]
    Unread { read: u64, raw_len: u64 },
    /// The operation needs another encoding (e.g. values requested from a `Bytes` blob).
    #[error("encoding {found:?} cannot be used here: {reason}")]
    WrongEncoding { found: Encoding, reason: &'static str },
}

/// The decoded content of a blob.
#[derive(Debug, Clone, PartialEq)]
pub enum Data {
    /// The payload of an [`Encoding::Bytes`] blob.
    Bytes(Vec<u8>),
    /// The values of an F32, F16 or RGB9E5 blob, as `f32`.
    Values(Vec<f32>),
}

/// A decoded blob.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    /// The kind (equal to the one the reader expected).
    pub kind: BlobKind,
    /// How the payload was stored.
    pub encoding: Encoding,
    /// The shape (empty for bytes).
    pub shape: Vec<u32>,
    /// The content.
    pub data: Data,
}

/// The parsed, validated header.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// What the blob holds.
    pub kind: BlobKind,
    /// How its payload is stored.
    pub encoding: Encoding,
    /// Its shape (empty for bytes).
    pub shape: Vec<u32>,
    /// Payload bytes before compression.
    pub raw_len: u64,
    /// Payload bytes after compression.
    pub stored_len: u64,
    /// CRC-32C of the stored payload.
    pub payload_crc: u32,
}

/// Parses and validates the header of `bytes`, including that the blob's length matches it. The
/// payload is not checked (see [`decode`]).
pub fn read_header(bytes: &[u8]) -> Result<Header, BlobError> {
    let prefix = &bytes[..bytes.len().min(MAGIC.len())];
    if prefix != &MAGIC[..prefix.len()] {
        return Err(BlobError::BadMagic { found: prefix.to_vec() });
    }
    let truncated = |expected: u64| BlobError::Truncated {
        expected,
        actual: bytes.len() as u64,
    };
    let h: &[u8; HEADER_LEN] = bytes
        .get(..HEADER_LEN)
        .and_then(|h| h.try_into().ok())
        .ok_or_else(|| truncated(HEADER_LEN as u64))?;
    let u16_at = |i: usize| u16::from_le_bytes([h[i], h[i + 1]]);
    let u32_at = |i: usize| u32::from_le_bytes([h[i], h[i + 1], h[i + 2], h[i + 3]]);
    let u64_at = |i: usize| u64::from(u32_at(i)) | (u64::from(u32_at(i + 4)) << 32);

    let version = u16_at(4);
    if version != FORMAT_VERSION {
        return Err(BlobError::UnsupportedVersion {
            found: version,
            supported: FORMAT_VERSION,
        });
    }
    let computed = crc32c::crc32c(&h[..44]);
    if computed != u32_at(44) {
        return Err(BlobError::HeaderChecksum {
            stored: u32_at(44),
            computed,
        });
    }
    let kind = BlobKind::from_code(u16_at(6)).ok_or(BlobError::UnknownKind(u16_at(6)))?;
    let encoding = Encoding::from_code(h[8]).ok_or(BlobError::UnknownEncoding(h[8]))?;
    if u16_at(10) != 0 {
        return Err(BlobError::Reserved);
    }
    let rank = usize::from(h[9]);
    let dims = [u32_at(12), u32_at(16), u32_at(20)];
    let bad_shape = |reason: String| BlobError::BadShape {
        shape: dims.to_vec(),
        encoding,
        reason,
    };
    if rank > MAX_RANK {
        return Err(bad_shape(format!("rank {rank} exceeds {MAX_RANK}")));
    }
    if dims[rank..].iter().any(|&d| d != 0) {
        return Err(bad_shape(format!("dimensions beyond rank {rank} must be zero")));
    }
    let shape = dims[..rank].to_vec();
    let raw_len = u64_at(24);
    let stored_len = u64_at(32);
    let expected_raw = if encoding == Encoding::Bytes {
        if rank != 0 {
            return Err(bad_shape("opaque bytes have rank 0".into()));
        }
        raw_len
    } else {
        check_value_shape(&shape, encoding).map_err(bad_shape)?;
        shape_product(&shape)
            .and_then(|n| encoding.raw_len(n))
            .ok_or_else(|| bad_shape("element count overflows".into()))?
    };
    if raw_len != expected_raw {
        return Err(bad_shape(format!(
            "shape needs {expected_raw} payload bytes, header says {raw_len}"
        )));
    }
    let total = stored_len
        .checked_add(HEADER_LEN as u64)
        .ok_or_else(|| truncated(u64::MAX))?;
    let actual = bytes.len() as u64;
    if actual < total {
        return Err(truncated(total));
    }
    if actual > total {
        return Err(BlobError::TrailingBytes { extra: actual - total });
    }
    Ok(Header {
        kind,
        encoding,
        shape,
        raw_len,
        stored_len,
        payload_crc: u32_at(40),
    })
}

/// Checks the rank and, for RGB9E5, the last dimension of a shape of values.
fn check_value_shape(shape: &[u32], encoding: Encoding) -> Result<(), String> {
    if shape.is_empty() || shape.len() > MAX_RANK {
        return Err(format!("values need 1 ..= {MAX_RANK} dimensions"));
    }
    if encoding == Encoding::Rgb9e5 && shape.last() != Some(&3) {
        return Err("RGB9E5 needs a last dimension of 3".into());
    }
    Ok(())
}

/// Number of elements of a shape, `None` on overflow.
fn shape_product(shape: &[u32]) -> Option<u64> {
    shape.iter().try_fold(1u64, |acc, &d| acc.checked_mul(u64::from(d)))
}

/// The header of a blob whose payload is `stored_len` bytes with checksum `payload_crc`,
/// `raw_len` before compression.
fn header_bytes(
    kind: BlobKind,
    encoding: Encoding,
    shape: &[u32],
    raw_len: usize,
    stored_len: usize,
    payload_crc: u32,
) -> [u8; HEADER_LEN] {
    let mut header = [0u8; HEADER_LEN];
    let mut at = 0;
    let mut put = |bytes: &[u8]| {
        header[at..at + bytes.len()].copy_from_slice(bytes);
        at += bytes.len();
    };
    put(&MAGIC);
    put(&FORMAT_VERSION.to_le_bytes());
    put(&kind.code().to_le_bytes());
    put(&[encoding.code(), shape.len() as u8]);
    put(&0u16.to_le_bytes());
    for i in 0..MAX_RANK {
        put(&shape.get(i).copied().unwrap_or(0).to_le_bytes());
    }
    put(&(raw_len as u64).to_le_bytes());
    put(&(stored_len as u64).to_le_bytes());
    put(&payload_crc.to_le_bytes());
    let header_crc = crc32c::crc32c(&header[..44]);
    header[44..].copy_from_slice(&header_crc.to_le_bytes());
    header
}

thread_local! {
    /// This thread's zstd compression contexts, one per level and number of workers it used
    /// ([`BlobKind::zstd_workers`]). A context per blob
    /// (thousands per job: every tile of every snapshot) spent more time setting up its tables
    /// than compressing the smaller blobs. A context's state does not carry from one frame to the
    /// next: the bytes are those of a fresh one.
    static COMPRESSORS: RefCell<Vec<((i32, u32), zstd::bulk::Compressor<'static>)>> = const { RefCell::new(Vec::new()) };
    /// This thread's zstd decompression context, for the same reason: a viewer reads thousands
    /// of tiles (a context per blob was 7 % of `vlf render`). Each blob starts a new session.
    static DECOMPRESSOR: RefCell<Option<zstd::zstd_safe::DCtx<'static>>> = const { RefCell::new(None) };
}

#[cfg(test)]
mod tests;
