//! Writing blobs: a header, then the payload as one zstd frame (compressed on worker threads
//! for large blobs, streamed for those written as they are made).

use super::*;

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
pub(super) fn encode_streamed(
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

/// Appends `raw` as one zstd frame at `level`, compressed on `workers` threads (0: this one), to
/// `out`, which must have room for [`zstd::zstd_safe::compress_bound`] bytes more; with this
/// thread's context for that level and number of workers.
pub(super) fn compress_after(raw: &[u8], level: i32, workers: u32, out: &mut Vec<u8>) -> std::io::Result<()> {
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
