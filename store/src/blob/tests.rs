use super::decode::decompress;
use super::encode::{compress_after, encode_streamed};
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

/// A blob's payload compressed at another level is other bytes with the same content, which
/// `same_content` tells; another payload, kind or shape is not the same content, nor is a
/// damaged blob.
#[test]
fn the_same_payload_compressed_otherwise_is_the_same_content() {
    let raw: Vec<u8> = (0..200_000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 27) as u8)
        .collect();
    let kind = BlobKind::BatchOutput;
    let a = encode_bytes(kind, &raw).unwrap();
    // The same payload at zstd's level 19, by hand: what an earlier build might have written.
    let mut b = vec![0u8; HEADER_LEN];
    b.reserve(zstd::zstd_safe::compress_bound(raw.len()));
    compress_after(&raw, 19, 0, &mut b).unwrap();
    let stored_len = b.len() - HEADER_LEN;
    let crc = crc32c::crc32c(&b[HEADER_LEN..]);
    b[..HEADER_LEN].copy_from_slice(&header_bytes(kind, Encoding::Bytes, &[], raw.len(), stored_len, crc));
    assert_ne!(a, b, "other bytes");
    assert_eq!(decode_bytes(&b, kind).unwrap(), raw);
    assert!(same_content(&a, &b) && same_content(&b, &a));
    let mut other = raw.clone();
    other[1000] ^= 1;
    assert!(
        !same_content(&a, &encode_bytes(kind, &other).unwrap()),
        "another payload"
    );
    assert!(
        !same_content(&a, &encode_bytes(BlobKind::Snapshot, &raw).unwrap()),
        "another kind"
    );
    // The same values, so the same payload bytes, as another shape or another encoding.
    let values: Vec<f32> = (0..24).map(|i| i as f32 * 0.25).collect();
    let as_shape = |shape: &[u32], encoding| encode_values(BlobKind::TileRadiance, encoding, shape, &values).unwrap();
    let flat = as_shape(&[8, 3], Encoding::F32);
    assert!(same_content(&flat, &as_shape(&[8, 3], Encoding::F32)));
    assert!(
        !same_content(&flat, &as_shape(&[2, 4, 3], Encoding::F32)),
        "another shape"
    );
    assert!(
        !same_content(&flat, &as_shape(&[8, 3], Encoding::F16)),
        "another encoding"
    );
    let mut damaged = b.clone();
    let last = damaged.len() - 1;
    damaged[last] ^= 0x10;
    assert!(!same_content(&a, &damaged), "a damaged blob");
}
