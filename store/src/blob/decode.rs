//! Reading blobs back: the header and checksums checked before zstd sees a byte, the frame
//! checked to end the payload, values checked finite.

use super::*;

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

/// Whether the blobs `a` and `b` hold the same thing, byte for byte once decompressed: the same
/// kind, encoding and shape, and the same payload, however each was compressed (a level, a
/// number of zstd workers, or a build that compressed otherwise). False if either is not a
/// sound blob. What a create-only write that finds other bytes in place asks before it calls
/// them a conflict ([`crate::AsyncStore::put_new`]).
pub fn same_content(a: &[u8], b: &[u8]) -> bool {
    let (Ok(ha), Ok(hb)) = (read_header(a), read_header(b)) else {
        return false;
    };
    // The headers first: blobs of another kind, encoding, shape or length are not the same, and
    // neither payload is decompressed past the length both headers agree on (a stored blob's
    // header could claim any).
    if (ha.kind, ha.encoding, &ha.shape, ha.raw_len) != (hb.kind, hb.encoding, &hb.shape, hb.raw_len) {
        return false;
    }
    let payload = |bytes: &[u8], header: &Header| -> Option<Vec<u8>> {
        decompress(checked_payload(bytes, header).ok()?, header.raw_len).ok()
    };
    match (payload(a, &ha), payload(b, &hb)) {
        (Some(ra), Some(rb)) => ra == rb,
        _ => false,
    }
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

/// Decompresses one zstd frame that must expand to exactly `raw_len` bytes.
///
/// Streams into a buffer of the header's length where one can be had, else into one that grows
/// with the data actually produced. Untouched pages cost nothing, so a header claiming a huge
/// length touches at most about twice what the frame holds (reading zero-fills each piece it
/// hands the decoder); a buffer of 64 MB that then doubled cost a worker a copy and fresh pages
/// for every 93 MB head of the mirror dragon.
pub(super) fn decompress(stored: &[u8], raw_len: u64) -> Result<Vec<u8>, BlobError> {
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
