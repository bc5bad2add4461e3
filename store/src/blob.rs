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

/// Encodes opaque bytes (JSON, bincode, …) as a blob of `kind`.
///
/// Fails only if zstd cannot allocate its context ([`BlobError::Compress`]).
pub fn encode_bytes(kind: BlobKind, data: &[u8]) -> Result<Vec<u8>, BlobError> {
    assemble(kind, Encoding::Bytes, &[], data)
}

/// Encodes as a blob of `kind` the `raw_len` bytes that `write` writes, compressing them as they
/// come: no buffer holds the whole payload. For the large payloads serialised from a structure
/// every iteration (a pass's output of a mirror scan, the next snapshot's head: 93 MB of `Φ_in`
/// each on the mirror dragon), where serialising into memory first cost as much as compressing —
/// every iteration's buffer is fresh memory, which the system zeroes page by page. They are
/// written while the threads that would compute wait for them (a worker ending its lease, a
/// coordinator releasing the next iteration), so the compression runs on this machine's cores,
/// at most 8, while `write` fills it: the frame is the same bytes for any number of them.
///
/// Payloads under [`STREAM_FROM`] are serialised into memory and encoded as [`encode_bytes`]
/// encodes them, the same bytes, on this thread's reused context: a multithreaded context made
/// for each blob cost more than it saved on the small outputs of a diffuse scene. Which way a
/// payload goes depends on its length alone, so a blob is the same whatever machine writes it.
/// (A build before this one compressed large outputs on one thread: a block it wrote and this
/// build computes again is refused as a conflict, as any other create-only write of other
/// bytes.)
///
/// The blob reads back as any other ([`decode_bytes`], [`decode_bytes_with`]). Fails if `write`
/// fails or writes another number of bytes than `raw_len` ([`BlobError::Compress`]).
pub fn encode_bytes_with(
    kind: BlobKind,
    raw_len: u64,
    write: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<Vec<u8>, BlobError> {
    if raw_len >= STREAM_FROM {
        return encode_streamed(kind, *ZSTD_WORKERS, raw_len, write);
    }
    let mut raw = Vec::with_capacity(raw_len as usize);
    write(&mut raw).map_err(|e| BlobError::Compress(e.to_string()))?;
    wrote_as_announced(raw.len() as u64, raw_len)?;
    encode_bytes(kind, &raw)
}

/// Whether a payload's writer wrote the `raw_len` bytes it announced.
fn wrote_as_announced(wrote: u64, raw_len: u64) -> Result<(), BlobError> {
    match wrote == raw_len {
        true => Ok(()),
        false => Err(BlobError::Compress(format!(
            "the payload's writer wrote {wrote} bytes, {raw_len} announced"
        ))),
    }
}

/// The length from which [`encode_bytes_with`] compresses a payload as it is written.
pub const STREAM_FROM: u64 = 8 << 20;

/// [`encode_bytes_with`] on `workers` compressing threads (0: the calling thread alone).
fn encode_streamed(
    kind: BlobKind,
    workers: u32,
    raw_len: u64,
    write: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<Vec<u8>, BlobError> {
    let fail = |e: std::io::Error| BlobError::Compress(e.to_string());
    // Room for the largest frame: pages the frame does not reach are never touched.
    let too_long = || BlobError::Compress(format!("a payload of {raw_len} bytes is too long to compress"));
    let bound = usize::try_from(raw_len)
        .ok()
        .map(zstd::zstd_safe::compress_bound)
        .and_then(|bound| bound.checked_add(HEADER_LEN))
        .ok_or_else(too_long)?;
    let mut blob = Vec::new();
    blob.try_reserve_exact(bound).map_err(|_| too_long())?;
    blob.resize(HEADER_LEN, 0);
    let mut encoder = zstd::stream::write::Encoder::new(blob, kind.zstd_level()).map_err(fail)?;
    if workers > 0 {
        encoder.multithread(workers).map_err(fail)?;
    }
    encoder.set_pledged_src_size(Some(raw_len)).map_err(fail)?;
    // Serialisers write a few bytes at a time: they go to zstd in large pieces.
    let mut counted = Counted {
        inner: std::io::BufWriter::with_capacity(1 << 18, encoder),
        bytes: 0,
    };
    write(&mut counted).map_err(fail)?;
    wrote_as_announced(counted.bytes, raw_len)?;
    let encoder = counted.inner.into_inner().map_err(|e| fail(e.into_error()))?;
    let mut blob = encoder.finish().map_err(fail)?;
    let stored = &blob[HEADER_LEN..];
    let header = header_bytes(
        kind,
        Encoding::Bytes,
        &[],
        raw_len as usize,
        stored.len(),
        crc32c::crc32c(stored),
    );
    blob[..HEADER_LEN].copy_from_slice(&header);
    Ok(blob)
}

/// A writer that counts what goes through it.
struct Counted<W> {
    inner: W,
    bytes: u64,
}

impl<W: Write> Write for Counted<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.bytes += n as u64;
        Ok(n)
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.inner.write_all(buf)?;
        self.bytes += buf.len() as u64;
        Ok(())
    }

    /// Nothing: a flush would end a zstd block where the writer happened to flush, and the
    /// frame is to depend on the bytes alone. The whole payload goes out when it is finished.
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Encodes `values` (row-major, `shape.iter().product()` of them) as a blob of `kind`.
///
/// Fails if `encoding` is [`Encoding::Bytes`], if the shape does not match the values, or if a
/// value cannot be represented (NaN/∞ in any encoding, beyond ±65504 in F16, negative or beyond
/// 65408 in RGB9E5) — a compact encoding never silently turns radiance into something else.
pub fn encode_values(kind: BlobKind, encoding: Encoding, shape: &[u32], values: &[f32]) -> Result<Vec<u8>, BlobError> {
    let bad_shape = |reason: String| BlobError::BadShape {
        shape: shape.to_vec(),
        encoding,
        reason,
    };
    if encoding == Encoding::Bytes {
        return Err(BlobError::WrongEncoding {
            found: encoding,
            reason: "use encode_bytes for opaque bytes",
        });
    }
    check_value_shape(shape, encoding).map_err(bad_shape)?;
    let count = shape_product(shape);
    if count != Some(values.len() as u64) {
        return Err(bad_shape(format!(
            "shape has {count:?} elements but {} values were given",
            values.len()
        )));
    }
    let unrepresentable = |(index, why): (usize, Unrepresentable)| BlobError::Unrepresentable {
        index,
        value: values[index],
        encoding,
        reason: match (why, encoding) {
            (Unrepresentable::NonFinite, _) => "radiance must be finite",
            (Unrepresentable::OutOfRange, Encoding::F16) => "beyond ±65504, the range of f16; use F32",
            (Unrepresentable::OutOfRange, _) => "outside [0, 65408], the range of RGB9E5; use F32 or F16",
        },
    };
    let raw = match encoding {
        Encoding::F32 => {
            codec::check_finite(values).map_err(unrepresentable)?;
            codec::f32_to_bytes(values)
        }
        Encoding::F16 => codec::f32_to_f16_bytes(values).map_err(unrepresentable)?,
        _ => codec::f32_to_rgb9e5_bytes(values).map_err(unrepresentable)?,
    };
    assemble(kind, encoding, shape, &codec::shuffle(&raw, encoding.element_size()))
}

/// Encodes RGB triples as a blob of shape `[n, 3]`.
pub fn encode_rgb(kind: BlobKind, encoding: Encoding, rgb: &[[f32; 3]]) -> Result<Vec<u8>, BlobError> {
    let n = u32::try_from(rgb.len()).map_err(|_| BlobError::BadShape {
        shape: vec![],
        encoding,
        reason: format!("{} triples do not fit a u32 dimension", rgb.len()),
    })?;
    encode_values(kind, encoding, &[n, 3], rgb.as_flattened())
}

/// The header of `bytes`, which must be a blob of the `expected` kind.
fn header_of_kind(bytes: &[u8], expected: BlobKind) -> Result<Header, BlobError> {
    let header = read_header(bytes)?;
    if header.kind != expected {
        return Err(BlobError::WrongKind {
            expected,
            found: header.kind,
        });
    }
    Ok(header)
}

/// The stored (compressed) payload of `bytes`, whose `header` was read, once its checksum
/// matches the header's: checked before a byte of it is decompressed.
fn checked_payload<'a>(bytes: &'a [u8], header: &Header) -> Result<&'a [u8], BlobError> {
    let stored = &bytes[HEADER_LEN..];
    let computed = crc32c::crc32c(stored);
    if computed != header.payload_crc {
        return Err(BlobError::ChecksumMismatch {
            stored: header.payload_crc,
            computed,
        });
    }
    Ok(stored)
}

/// Decodes a blob, checking that it is of the `expected` kind.
pub fn decode(bytes: &[u8], expected: BlobKind) -> Result<Decoded, BlobError> {
    let header = header_of_kind(bytes, expected)?;
    let stored = checked_payload(bytes, &header)?;
    let raw = decompress(stored, header.raw_len)?;
    let data = match header.encoding {
        Encoding::Bytes => Data::Bytes(raw),
        encoding => {
            let raw = codec::unshuffle(&raw, encoding.element_size());
            let values = match encoding {
                Encoding::F32 => codec::bytes_to_f32(&raw),
                Encoding::F16 => codec::f16_bytes_to_f32(&raw),
                _ => codec::rgb9e5_bytes_to_f32(&raw),
            };
            if let Some(index) = values.iter().position(|v| !v.is_finite()) {
                return Err(BlobError::NonFinite {
                    index,
                    value: values[index],
                });
            }
            Data::Values(values)
        }
    };
    Ok(Decoded {
        kind: header.kind,
        encoding: header.encoding,
        shape: header.shape,
        data,
    })
}

/// Decodes an [`Encoding::Bytes`] blob of the `expected` kind.
pub fn decode_bytes(bytes: &[u8], expected: BlobKind) -> Result<Vec<u8>, BlobError> {
    let decoded = decode(bytes, expected)?;
    match decoded.data {
        Data::Bytes(b) => Ok(b),
        Data::Values(_) => Err(BlobError::WrongEncoding {
            found: decoded.encoding,
            reason: "expected opaque bytes",
        }),
    }
}

/// What `read` makes of the payload of an [`Encoding::Bytes`] blob of the `expected` kind,
/// decompressed as `read` asks for it: no buffer holds the whole payload (see
/// [`encode_bytes_with`]). The blob is checked as [`decode_bytes`] checks it — header, kind,
/// checksum before a byte is decompressed, a payload of exactly the header's length — and `read`
/// must take all of it ([`BlobError::Unread`]). What `read` reports is returned inside: the
/// outer error is the blob's, the inner one the reader's. Where the frame itself is corrupt,
/// the blob's error is returned, whatever `read` made of it.
pub fn decode_bytes_with<T, E>(
    bytes: &[u8],
    expected: BlobKind,
    read: impl FnOnce(&mut dyn Read) -> Result<T, E>,
) -> Result<Result<T, E>, BlobError> {
    let header = header_of_kind(bytes, expected)?;
    if header.encoding != Encoding::Bytes {
        return Err(BlobError::WrongEncoding {
            found: header.encoding,
            reason: "expected opaque bytes",
        });
    }
    let stored = checked_payload(bytes, &header)?;
    let decoder = zstd::stream::read::Decoder::with_buffer(stored)
        .map_err(|e| BlobError::Decompress(e.to_string()))?
        .single_frame();
    // Deserialisers read a few bytes at a time: they come out of zstd in large pieces.
    let mut payload = Payload {
        inner: std::io::BufReader::with_capacity(1 << 18, decoder.take(header.raw_len.saturating_add(1))),
        bytes: 0,
        failed: None,
    };
    let made = read(&mut payload);
    // What `read` left (none, when it read a whole payload), up to where the frame ends: the
    // frame's own faults come first, then its length, then what `read` made of it.
    let left = std::io::copy(&mut payload, &mut std::io::sink());
    if let Some(e) = payload.failed.take() {
        return Err(BlobError::Decompress(e));
    }
    let left = left.map_err(|e| BlobError::Decompress(e.to_string()))?;
    let expanded = payload.bytes;
    frame_ends_the_payload(payload.inner.into_inner().into_inner())?;
    if expanded != header.raw_len {
        return Err(BlobError::Decompress(format!(
            "payload expands to {expanded}{} bytes, header says {}",
            if expanded > header.raw_len { "+" } else { "" },
            header.raw_len
        )));
    }
    match made {
        Ok(_) if left > 0 => Err(BlobError::Unread {
            read: expanded - left,
            raw_len: header.raw_len,
        }),
        made => Ok(made),
    }
}

/// The payload as a reader decompresses it: counts the bytes and keeps the first error, so that
/// a corrupt frame is reported as such rather than as what its reader made of it.
struct Payload<R> {
    inner: R,
    bytes: u64,
    failed: Option<String>,
}

impl<R: Read> Read for Payload<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        match self.inner.read(buf) {
            Ok(n) => {
                self.bytes += n as u64;
                Ok(n)
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => Err(e),
            Err(e) => {
                self.failed.get_or_insert_with(|| e.to_string());
                Err(e)
            }
        }
    }
}

/// Decodes a blob of values of the `expected` kind: its shape and values as `f32`.
pub fn decode_values(bytes: &[u8], expected: BlobKind) -> Result<(Vec<u32>, Vec<f32>), BlobError> {
    let decoded = decode(bytes, expected)?;
    match decoded.data {
        Data::Values(v) => Ok((decoded.shape, v)),
        Data::Bytes(_) => Err(BlobError::WrongEncoding {
            found: decoded.encoding,
            reason: "expected radiance values",
        }),
    }
}

/// Decodes a blob of RGB values (any shape whose last dimension is 3) of the `expected` kind.
pub fn decode_rgb(bytes: &[u8], expected: BlobKind) -> Result<Vec<[f32; 3]>, BlobError> {
    let (shape, values) = decode_values(bytes, expected)?;
    if shape.last() != Some(&3) {
        let encoding = read_header(bytes)?.encoding;
        return Err(BlobError::BadShape {
            shape,
            encoding,
            reason: "RGB data needs a last dimension of 3".into(),
        });
    }
    Ok(values.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
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

/// The blob of `raw`: the header, then `raw` compressed straight after it, in one buffer (no
/// second buffer for the frame, and no copy of it).
fn assemble(kind: BlobKind, encoding: Encoding, shape: &[u32], raw: &[u8]) -> Result<Vec<u8>, BlobError> {
    let mut blob = Vec::with_capacity(HEADER_LEN + zstd::zstd_safe::compress_bound(raw.len()));
    blob.resize(HEADER_LEN, 0);
    // Only an allocation failure inside zstd can make this fail: the buffer has room for the
    // largest frame `raw` can give.
    compress_after(raw, kind.zstd_level(), kind.zstd_workers(), &mut blob)
        .map_err(|e| BlobError::Compress(e.to_string()))?;
    let stored = &blob[HEADER_LEN..];
    let header = header_bytes(kind, encoding, shape, raw.len(), stored.len(), crc32c::crc32c(stored));
    blob[..HEADER_LEN].copy_from_slice(&header);
    // Room the frame did not need is given back when it is much (radiance that compressed well),
    // which moves the blob; a frame about as large as its input (resume state, batch outputs:
    // numbers that hardly compress) keeps its place.
    if blob.capacity() - blob.len() > blob.len() / 4 {
        blob.shrink_to_fit();
    }
    Ok(blob)
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

/// Appends `raw` as one zstd frame at `level`, compressed on `workers` threads (0: this one), to
/// `out`, which must have room for [`zstd::zstd_safe::compress_bound`] bytes more; with this
/// thread's context for that level and number of workers.
fn compress_after(raw: &[u8], level: i32, workers: u32, out: &mut Vec<u8>) -> std::io::Result<()> {
    COMPRESSORS.with(|compressors| {
        let mut compressors = compressors.borrow_mut();
        let at = match compressors.iter().position(|(key, _)| *key == (level, workers)) {
            Some(at) => at,
            None => {
                let mut compressor = zstd::bulk::Compressor::new(level)?;
                if workers > 0 {
                    compressor.set_parameter(zstd::zstd_safe::CParameter::NbWorkers(workers))?;
                }
                compressors.push(((level, workers), compressor));
                compressors.len() - 1
            }
        };
        // The frame goes after what `out` holds: a cursor at its end.
        let mut after = std::io::Cursor::new(out);
        after.set_position(after.get_ref().len() as u64);
        let compressed = compressors[at].1.compress_to_buffer(raw, &mut after);
        if compressed.is_err() {
            // A context whose frame failed on a worker thread refuses the next ones: a new one then.
            compressors.swap_remove(at);
        }
        compressed.map(|_| ())
    })
}

/// Decompresses one zstd frame that must expand to exactly `raw_len` bytes.
///
/// Streams into a buffer of the header's length where one can be had, else into one that grows
/// with the data actually produced. Untouched pages cost nothing, so a header claiming a huge
/// length touches at most about twice what the frame holds (reading zero-fills each piece it
/// hands the decoder); a buffer of 64 MB that then doubled cost a worker a copy and fresh pages
/// for every 93 MB head of the mirror dragon.
fn decompress(stored: &[u8], raw_len: u64) -> Result<Vec<u8>, BlobError> {
    const INITIAL_CAPACITY_LIMIT: u64 = 64 << 20;
    let mut raw = Vec::new();
    let whole = usize::try_from(raw_len).is_ok_and(|n| raw.try_reserve_exact(n).is_ok());
    if !whole {
        raw.reserve_exact(usize::try_from(raw_len.min(INITIAL_CAPACITY_LIMIT)).unwrap_or(0));
    }
    DECOMPRESSOR.with(|slot| {
        let mut slot = slot.borrow_mut();
        let context = match slot.as_mut() {
            Some(context) => context,
            None => slot.insert(
                zstd::zstd_safe::DCtx::try_create()
                    .ok_or_else(|| BlobError::Decompress("cannot allocate a zstd context".into()))?,
            ),
        };
        // `with_context` starts a new session, whatever the last blob left.
        let decoder = zstd::stream::read::Decoder::with_context(stored, context).single_frame();
        read_frame(decoder, raw_len, raw)
    })
}

/// Reads the one frame of `decoder` into `raw`, which must expand to exactly `raw_len` bytes.
fn read_frame(mut decoder: Decoder<'_>, raw_len: u64, mut raw: Vec<u8>) -> Result<Vec<u8>, BlobError> {
    let fail = |e: std::io::Error| BlobError::Decompress(e.to_string());
    (&mut decoder)
        .take(raw_len.saturating_add(1))
        .read_to_end(&mut raw)
        .map_err(fail)?;
    if raw.len() as u64 != raw_len {
        return Err(BlobError::Decompress(format!(
            "payload expands to {}{} bytes, header says {raw_len}",
            raw.len(),
            if raw.len() as u64 > raw_len { "+" } else { "" }
        )));
    }
    frame_ends_the_payload(decoder)?;
    Ok(raw)
}

/// A zstd reader of one frame out of a blob's stored payload.
type Decoder<'a> = zstd::stream::read::Decoder<'a, &'a [u8]>;

/// Checks that `decoder`'s frame, read to its end, is all of the stored payload: bytes after it
/// are corruption (the reader of one frame stops at its end, and would never see them).
fn frame_ends_the_payload(mut decoder: Decoder<'_>) -> Result<(), BlobError> {
    decoder
        .finish_frame()
        .map_err(|e| BlobError::Decompress(e.to_string()))?;
    match decoder.get_ref().len() {
        0 => Ok(()),
        n => Err(BlobError::Decompress(format!(
            "payload has {n} bytes after its zstd frame"
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame compressed on worker threads is the same bytes for one, two or four of them, and
    /// reads back: what lets a job's mirror geometry be written create-only from any machine.
    #[test]
    fn a_multithreaded_frame_is_the_same_for_any_number_of_workers() {
        // 24 MB that compresses, but not to nothing: several of zstd's jobs.
        let raw: Vec<u8> = (0..24u32 << 20)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 29) as u8 ^ (i >> 13) as u8)
            .collect();
        let frame = |workers| {
            let mut out = Vec::with_capacity(zstd::zstd_safe::compress_bound(raw.len()));
            compress_after(&raw, ZSTD_LEVEL, workers, &mut out).unwrap();
            out
        };
        let one = frame(1);
        assert!(one.len() < raw.len() / 2);
        assert!(frame(2) == one && frame(4) == one);
        assert!(decompress(&one, raw.len() as u64).unwrap() == raw);
        let blob = encode_bytes(BlobKind::MirrorGeometry, &raw).unwrap();
        assert!(decode_bytes(&blob, BlobKind::MirrorGeometry).unwrap() == raw);
    }

    /// `len` bytes that compress, but not to nothing.
    fn compressible(len: u32) -> Vec<u8> {
        (0..len)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 29) as u8 ^ (i >> 13) as u8)
            .collect()
    }

    /// Writes `raw` in pieces of an odd size, as a serialiser would.
    fn in_pieces(raw: &[u8]) -> impl FnOnce(&mut dyn Write) -> std::io::Result<()> + '_ {
        |w: &mut dyn Write| raw.chunks(4097).try_for_each(|piece| w.write_all(piece))
    }

    /// A blob compressed as its payload is written is the same bytes on one, two or four
    /// compressing threads — a block's output is written create-only, from machines with any
    /// number of cores — and reads back whole, in memory or as a stream.
    #[test]
    fn a_streamed_blob_is_the_same_for_any_number_of_workers_and_reads_back() {
        let raw = compressible(24 << 20);
        let kind = BlobKind::BatchOutput;
        let blob = |workers| encode_streamed(kind, workers, raw.len() as u64, in_pieces(&raw)).unwrap();
        let one = blob(1);
        assert!(one.len() < raw.len() / 2);
        assert!(blob(2) == one && blob(4) == one);
        assert!(encode_bytes_with(kind, raw.len() as u64, in_pieces(&raw)).unwrap() == one);
        assert!(decode_bytes(&one, kind).unwrap() == raw);
        let streamed = decode_bytes_with(&one, kind, |r| {
            let mut back = Vec::new();
            r.read_to_end(&mut back).map(|_| back)
        });
        assert!(streamed.unwrap().unwrap() == raw);
        // On the calling thread alone: another frame, the same payload.
        let alone = blob(0);
        assert!(decode_bytes(&alone, kind).unwrap() == raw);
        // An empty payload.
        let empty = encode_bytes_with(kind, 0, |_| Ok(())).unwrap();
        assert_eq!(decode_bytes(&empty, kind).unwrap(), Vec::<u8>::new());
    }

    /// Short of [`STREAM_FROM`], a payload is encoded in memory, the bytes [`encode_bytes`]
    /// gives; from there on, as it is written.
    #[test]
    fn small_payloads_are_encoded_in_memory() {
        let kind = BlobKind::BatchOutput;
        for len in [0, 1000, STREAM_FROM as u32 - 1] {
            let raw = compressible(len);
            let blob = encode_bytes_with(kind, raw.len() as u64, in_pieces(&raw)).unwrap();
            assert!(blob == encode_bytes(kind, &raw).unwrap(), "{len}");
        }
        let raw = compressible(STREAM_FROM as u32);
        let streamed = encode_bytes_with(kind, raw.len() as u64, in_pieces(&raw)).unwrap();
        assert!(streamed == encode_streamed(kind, 1, raw.len() as u64, in_pieces(&raw)).unwrap());
        assert!(streamed != encode_bytes(kind, &raw).unwrap());
    }

    #[test]
    fn a_streamed_writer_must_write_what_it_announced() {
        let raw = compressible(1000);
        for announced in [999u64, 1001] {
            let written = encode_bytes_with(BlobKind::BatchOutput, announced, in_pieces(&raw));
            assert!(
                matches!(written, Err(BlobError::Compress(_))),
                "{announced}: {written:?}"
            );
            let streamed = encode_streamed(BlobKind::BatchOutput, 1, announced, in_pieces(&raw));
            assert!(
                matches!(streamed, Err(BlobError::Compress(_))),
                "{announced}: {streamed:?}"
            );
        }
        let huge = encode_streamed(BlobKind::BatchOutput, 1, u64::MAX, in_pieces(&raw));
        assert!(matches!(huge, Err(BlobError::Compress(_))), "{huge:?}");
        let failing = encode_bytes_with(BlobKind::BatchOutput, 10, |_| Err(std::io::Error::other("full")));
        assert!(matches!(failing, Err(BlobError::Compress(m)) if m.contains("full")));
    }

    /// `blob` with a header made right for what it stores now (its length and checksum), and
    /// claiming `raw_len` bytes of payload.
    fn with_header(kind: BlobKind, mut blob: Vec<u8>, raw_len: usize) -> Vec<u8> {
        let stored = &blob[HEADER_LEN..];
        let header = header_bytes(
            kind,
            Encoding::Bytes,
            &[],
            raw_len,
            stored.len(),
            crc32c::crc32c(stored),
        );
        blob[..HEADER_LEN].copy_from_slice(&header);
        blob
    }

    /// A streamed read takes the whole payload and nothing else; a corrupt frame is the blob's
    /// fault, whatever its reader made of it; the reader's own errors come back inside.
    #[test]
    fn a_streamed_read_checks_the_blob_as_a_whole_read_does() {
        let raw = compressible(300_000);
        let kind = BlobKind::BatchOutput;
        let blob = encode_bytes(kind, &raw).unwrap();
        let take = |bytes: &[u8], n: usize| {
            decode_bytes_with(bytes, kind, |r| {
                let mut part = vec![0; n];
                r.read_exact(&mut part).map(|_| part)
            })
        };
        assert!(take(&blob, raw.len()).unwrap().unwrap() == raw);
        assert!(matches!(
            take(&blob, 10),
            Err(BlobError::Unread {
                read: 10,
                raw_len: 300_000
            })
        ));
        // Past the end: the reader's error.
        assert!(matches!(take(&blob, raw.len() + 1), Ok(Err(_))));
        assert!(matches!(
            decode_bytes_with(&blob, BlobKind::Snapshot, |_| Ok::<_, ()>(())),
            Err(BlobError::WrongKind { .. })
        ));
        // A byte changed: the checksum catches it before anything is decompressed.
        let mut flipped = blob.clone();
        flipped[HEADER_LEN + 100] ^= 0x40;
        assert!(matches!(take(&flipped, 10), Err(BlobError::ChecksumMismatch { .. })));
        // A frame cut short, its checksum made right: the frame's fault, not the reader's.
        let cut = with_header(kind, blob[..blob.len() - 20].to_vec(), raw.len());
        for n in [10, raw.len()] {
            assert!(matches!(take(&cut, n), Err(BlobError::Decompress(_))), "{n}");
        }
        // A byte after the frame, its checksum and length made right: corrupt, read either way.
        let mut after = blob.clone();
        after.push(0);
        let after = with_header(kind, after, raw.len());
        assert!(matches!(take(&after, raw.len()), Err(BlobError::Decompress(_))));
        assert!(matches!(decode_bytes(&after, kind), Err(BlobError::Decompress(_))));
        // A header that claims another length.
        for claimed in [raw.len() - 1, raw.len() + 1] {
            let lying = with_header(kind, blob.clone(), claimed);
            let read = decode_bytes_with(&lying, kind, |r| {
                let mut all = Vec::new();
                r.read_to_end(&mut all).map(|_| all)
            });
            assert!(matches!(read, Err(BlobError::Decompress(_))), "{claimed}: {read:?}");
        }
    }
}
