//! The blob format on its own: round trips of every kind and encoding, the error of the compact
//! encodings, compression ratios, and every way a blob can be broken.

use vlf_store::blob::{self, BlobError, BlobKind, Data, Encoding, FORMAT_VERSION, HEADER_LEN};

/// A small deterministic generator (xorshift64*), so failures reproduce.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A smooth synthetic radiance map, `size × size` RGB: a lit wall with a soft hot spot, a
/// coloured gradient (bleeding) and a penumbra, values ~0.01 … ~20 as in the bundled scenes.
fn smooth_radiance(size: usize) -> Vec<f32> {
    let mut v = Vec::with_capacity(size * size * 3);
    for y in 0..size {
        for x in 0..size {
            let (u, w) = (x as f32 / size as f32, y as f32 / size as f32);
            let spot = 18.0 * (-((u - 0.4).powi(2) + (w - 0.3).powi(2)) / 0.02).exp();
            let shadow = 0.5 + 0.5 * ((u - 0.7) * 25.0).tanh();
            let base = 0.8 * shadow + 0.02;
            v.extend([
                base * (1.0 + 0.6 * (1.0 - u)) + spot,
                base + spot * 0.9,
                base * (1.0 + 0.5 * u) + spot * 0.8,
            ]);
        }
    }
    v
}

/// The same map with ±1 % multiplicative noise (the field is not perfectly smooth).
fn noisy_radiance(size: usize) -> Vec<f32> {
    let mut rng = Rng(7);
    smooth_radiance(size)
        .into_iter()
        .map(|x| x * (1.0 + 0.02 * (rng.unit() - 0.5)))
        .collect()
}

#[test]
fn every_kind_and_encoding_round_trips() {
    let mut rng = Rng(1);
    for kind in BlobKind::ALL {
        // Bytes: empty, short, long.
        for len in [0usize, 1, 17, 100_000] {
            let bytes: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
            let b = blob::encode_bytes(kind, &bytes).unwrap();
            assert_eq!(blob::decode_bytes(&b, kind).unwrap(), bytes);
            let d = blob::decode(&b, kind).unwrap();
            assert_eq!((d.kind, d.encoding, d.shape.len()), (kind, Encoding::Bytes, 0));
        }
        // Values: every encoding, ranks 1 to 3, including empty shapes.
        for encoding in Encoding::VALUES {
            for shape in [vec![0u32, 3], vec![5, 3], vec![4, 7, 3], vec![30], vec![2, 0, 3]] {
                if encoding == Encoding::Rgb9e5 && shape.last() != Some(&3) {
                    continue;
                }
                let n: u32 = shape.iter().product();
                // Values exactly representable in every encoding: small multiples of 1/8.
                let values: Vec<f32> = (0..n).map(|i| (i % 40) as f32 / 8.0).collect();
                let b = blob::encode_values(kind, encoding, &shape, &values).unwrap();
                let (s, v) = blob::decode_values(&b, kind).unwrap();
                assert_eq!((&s, &v), (&shape, &values), "{kind:?} {encoding:?}");
                let d = blob::decode(&b, kind).unwrap();
                assert_eq!((d.kind, d.encoding), (kind, encoding));
                assert_eq!(blob::read_header(&b).unwrap().shape, shape);
            }
            let rgb: Vec<[f32; 3]> = (0..50).map(|i| [i as f32, 0.5, 2.0 * i as f32]).collect();
            let b = blob::encode_rgb(kind, encoding, &rgb).unwrap();
            assert_eq!(blob::decode_rgb(&b, kind).unwrap(), rgb);
        }
    }
    // Lossless F32 keeps every bit, including signed zero, subnormals and extremes.
    let odd = [
        0.0f32,
        -0.0,
        f32::MIN_POSITIVE / 3.0,
        f32::MAX,
        f32::MIN,
        1.0e-30,
        -3.25,
    ];
    let b = blob::encode_values(BlobKind::Raw, Encoding::F32, &[7], &odd).unwrap();
    let (_, back) = blob::decode_values(&b, BlobKind::Raw).unwrap();
    assert_eq!(
        back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        odd.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
    );
}

/// Relative error of F16 on normal values, over a log sweep of the whole normal range and the
/// realistic map: ≤ 2⁻¹¹ (the half ulp of an 11-bit significand).
#[test]
fn f16_error_bound() {
    let mut values: Vec<f32> = Vec::new();
    let mut x = 2f32.powi(-14);
    while x < 65000.0 {
        values.push(x);
        x *= 1.000_37;
    }
    let sweep = values.len();
    values.extend(smooth_radiance(128));
    let rem = values.len() % 3;
    values.truncate(values.len() - rem);
    let n = values.len() as u32;
    let b = blob::encode_values(BlobKind::TileRadiance, Encoding::F16, &[n / 3, 3], &values).unwrap();
    let (_, back) = blob::decode_values(&b, BlobKind::TileRadiance).unwrap();
    let mut worst = (0.0f64, 0.0f32);
    let mut worst_map = 0.0f64;
    for (i, (a, b)) in values.iter().zip(&back).enumerate() {
        let rel = ((f64::from(*b) - f64::from(*a)) / f64::from(*a)).abs();
        if rel > worst.0 {
            worst = (rel, *a);
        }
        if i >= sweep {
            worst_map = worst_map.max(rel);
        }
    }
    println!(
        "F16: max relative error {:.3e} (= 2^{:.3}) at {} over {} values; {:.3e} on the smooth radiance map",
        worst.0,
        worst.0.log2(),
        worst.1,
        values.len(),
        worst_map
    );
    assert!(worst.0 <= 2f64.powi(-11), "F16 relative error {} > 2^-11", worst.0);
}

/// RGB9E5: error relative to the largest channel of each triple, on the realistic map.
#[test]
fn rgb9e5_error_bound() {
    let values = noisy_radiance(128);
    let n = values.len() as u32 / 3;
    let b = blob::encode_values(BlobKind::DiffuseMaps, Encoding::Rgb9e5, &[n, 3], &values).unwrap();
    let (_, back) = blob::decode_values(&b, BlobKind::DiffuseMaps).unwrap();
    let (mut worst_of_max, mut worst_channel) = (0.0f64, 0.0f64);
    for (a, b) in values.chunks_exact(3).zip(back.chunks_exact(3)) {
        let max = a.iter().copied().fold(0.0f32, f32::max);
        let i = a.iter().position(|&v| v == max).unwrap();
        worst_of_max = worst_of_max.max((f64::from(b[i]) - f64::from(max)).abs() / f64::from(max));
        for c in 0..3 {
            worst_channel = worst_channel.max((f64::from(b[c]) - f64::from(a[c])).abs() / f64::from(max));
        }
    }
    println!(
        "RGB9E5: largest channel max relative error {worst_of_max:.3e} (2^{:.3}); any channel, relative to \
         the triple's largest: {worst_channel:.3e} (2^{:.3})",
        worst_of_max.log2(),
        worst_channel.log2()
    );
    assert!(worst_of_max <= 2f64.powi(-9));
    assert!(worst_channel <= 2f64.powi(-9) * 1.0001);
}

/// Compression ratios (raw f32 bytes ÷ blob bytes) of each encoding on the smooth map and on the
/// noisy one. Printed for the README; the assertions only guard against regressions.
#[test]
fn compression_ratios() {
    let size = 256usize;
    for (name, values) in [("smooth", smooth_radiance(size)), ("noisy ±1%", noisy_radiance(size))] {
        let raw = values.len() * 4;
        let mut line = format!("{name} {size}×{size} RGB radiance map ({raw} bytes as f32):");
        for encoding in Encoding::VALUES {
            let b =
                blob::encode_values(BlobKind::DiffuseMaps, encoding, &[size as u32, size as u32, 3], &values).unwrap();
            let ratio = raw as f64 / b.len() as f64;
            line += &format!("  {encoding:?} {} bytes = ×{ratio:.2}", b.len());
            // The frame is compressed into room for the largest it could be; a blob that came out
            // much smaller does not keep that room (a `memory://` store holds blobs as they are).
            assert!(
                b.capacity() <= b.len() + b.len() / 4,
                "{name} {encoding:?}: {} bytes held for a blob of {}",
                b.capacity(),
                b.len()
            );
            let floor = match encoding {
                Encoding::F32 => 1.0,
                Encoding::F16 => 2.0,
                _ => 3.0,
            };
            assert!(ratio > floor, "{name} {encoding:?}: ratio {ratio}");
        }
        println!("{line}");
    }
}

/// Bytes that do not compress give the largest frame zstd can write for them: it must fit the
/// room the blob leaves for it, and read back whole, on every kind (each kind has its level).
#[test]
fn incompressible_payloads_round_trip() {
    let mut rng = Rng(0x5eed_b10b);
    for len in [0usize, 1, 47, 4096, 131_072, 1 << 20] {
        let data: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
        for kind in BlobKind::ALL {
            let b = blob::encode_bytes(kind, &data).unwrap();
            assert!(b.len() >= HEADER_LEN + len, "{kind:?} {len}: {} bytes", b.len());
            assert_eq!(blob::decode_bytes(&b, kind).unwrap(), data, "{kind:?} {len}");
        }
    }
}

#[test]
fn encode_refuses_what_it_cannot_store() {
    let k = BlobKind::TileRadiance;
    let unrep = |r: Result<Vec<u8>, BlobError>| matches!(r, Err(BlobError::Unrepresentable { .. }));
    for e in Encoding::VALUES {
        assert!(
            unrep(blob::encode_values(k, e, &[1, 3], &[0.0, f32::NAN, 0.0])),
            "{e:?} NaN"
        );
        assert!(
            unrep(blob::encode_values(k, e, &[1, 3], &[f32::INFINITY, 0.0, 0.0])),
            "{e:?} inf"
        );
    }
    assert!(unrep(blob::encode_values(
        k,
        Encoding::F16,
        &[1, 3],
        &[7.0e4, 0.0, 0.0]
    )));
    assert!(blob::encode_values(k, Encoding::F16, &[1, 3], &[65504.0, -65504.0, 0.0]).is_ok());
    assert!(unrep(blob::encode_values(
        k,
        Encoding::Rgb9e5,
        &[1, 3],
        &[-1.0e-3, 0.0, 0.0]
    )));
    assert!(unrep(blob::encode_values(
        k,
        Encoding::Rgb9e5,
        &[1, 3],
        &[7.0e4, 0.0, 0.0]
    )));
    let err = blob::encode_values(k, Encoding::F16, &[2, 3], &[0.0, 1.0, 2.0, 3.0, 1.0e6, 0.0]).unwrap_err();
    assert!(err.to_string().contains("value 4 (1000000)"), "{err}");

    let bad_shape = |r: Result<Vec<u8>, BlobError>| matches!(r, Err(BlobError::BadShape { .. }));
    assert!(bad_shape(blob::encode_values(k, Encoding::F32, &[2, 3], &[0.0; 5])));
    assert!(bad_shape(blob::encode_values(k, Encoding::F32, &[], &[])));
    assert!(bad_shape(blob::encode_values(k, Encoding::F32, &[1, 1, 1, 1], &[0.0])));
    assert!(bad_shape(blob::encode_values(k, Encoding::Rgb9e5, &[6], &[0.0; 6])));
    assert!(matches!(
        blob::encode_values(k, Encoding::Bytes, &[1], &[0.0]),
        Err(BlobError::WrongEncoding { .. })
    ));
}

/// A valid F32 blob for the corruption tests.
fn sample() -> Vec<u8> {
    let values: Vec<f32> = (0..60).map(|i| i as f32 * 0.25).collect();
    blob::encode_values(BlobKind::TileRadiance, Encoding::F32, &[20, 3], &values).unwrap()
}

/// Rewrites the header checksum after an edit, so that the edit itself is what decode reports.
fn fix_header_crc(b: &mut [u8]) {
    let crc = crc32c::crc32c(&b[..44]);
    b[44..48].copy_from_slice(&crc.to_le_bytes());
}

/// Builds a blob with a chosen raw payload (already in stored element order) and valid checksums.
fn forge(kind: u16, encoding: u8, dims: [u32; 3], rank: u8, raw: &[u8]) -> Vec<u8> {
    let stored = zstd::bulk::compress(raw, 3).unwrap();
    let mut b = Vec::new();
    b.extend_from_slice(b"VLFB");
    b.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    b.extend_from_slice(&kind.to_le_bytes());
    b.extend_from_slice(&[encoding, rank, 0, 0]);
    for d in dims {
        b.extend_from_slice(&d.to_le_bytes());
    }
    b.extend_from_slice(&(raw.len() as u64).to_le_bytes());
    b.extend_from_slice(&(stored.len() as u64).to_le_bytes());
    b.extend_from_slice(&crc32c::crc32c(&stored).to_le_bytes());
    b.extend_from_slice(&[0; 4]);
    fix_header_crc(&mut b);
    b.extend_from_slice(&stored);
    b
}

#[test]
fn every_corruption_gives_its_error() {
    let k = BlobKind::TileRadiance;
    let good = sample();
    assert!(blob::decode(&good, k).is_ok());
    let decode = |b: &[u8]| blob::decode(b, k).unwrap_err();

    let mut b = good.clone();
    b[0] = b'X';
    assert!(matches!(decode(&b), BlobError::BadMagic { .. }));
    assert!(matches!(decode(b"{\"json\": true}"), BlobError::BadMagic { .. }));

    let mut b = good.clone();
    b[4..6].copy_from_slice(&2u16.to_le_bytes());
    assert_eq!(
        decode(&b),
        BlobError::UnsupportedVersion {
            found: 2,
            supported: FORMAT_VERSION
        }
    );

    let mut b = good.clone();
    b[13] ^= 0x10; // a dimension, checksum not fixed
    assert!(matches!(decode(&b), BlobError::HeaderChecksum { .. }));

    let mut b = good.clone();
    b[6..8].copy_from_slice(&999u16.to_le_bytes());
    fix_header_crc(&mut b);
    assert_eq!(decode(&b), BlobError::UnknownKind(999));

    assert_eq!(
        blob::decode(&good, BlobKind::DiffuseMaps).unwrap_err(),
        BlobError::WrongKind {
            expected: BlobKind::DiffuseMaps,
            found: k
        }
    );

    let mut b = good.clone();
    b[8] = 42;
    fix_header_crc(&mut b);
    assert_eq!(decode(&b), BlobError::UnknownEncoding(42));

    let mut b = good.clone();
    b[8] = Encoding::F16.code(); // same shape, but F16 needs half the raw bytes
    fix_header_crc(&mut b);
    assert!(matches!(decode(&b), BlobError::BadShape { .. }));

    let mut b = good.clone();
    b[12..16].copy_from_slice(&21u32.to_le_bytes()); // shape product no longer matches the length
    fix_header_crc(&mut b);
    assert!(matches!(decode(&b), BlobError::BadShape { .. }));

    let mut b = good.clone();
    b[9] = 4; // rank beyond 3
    fix_header_crc(&mut b);
    assert!(matches!(decode(&b), BlobError::BadShape { .. }));

    let mut b = good.clone();
    b[10] = 1;
    fix_header_crc(&mut b);
    assert_eq!(decode(&b), BlobError::Reserved);

    let mut b = good.clone();
    let last = b.len() - 1;
    b[last] ^= 1;
    assert!(matches!(decode(&b), BlobError::ChecksumMismatch { .. }));

    let mut b = good.clone();
    b.push(0);
    assert_eq!(decode(&b), BlobError::TrailingBytes { extra: 1 });

    // Garbage with a valid checksum: zstd refuses it.
    let mut b = good[..HEADER_LEN].to_vec();
    let garbage = [0xde, 0xad, 0xbe, 0xef, 1, 2, 3, 4, 5, 6, 7, 8];
    b[32..40].copy_from_slice(&(garbage.len() as u64).to_le_bytes());
    b[40..44].copy_from_slice(&crc32c::crc32c(&garbage).to_le_bytes());
    fix_header_crc(&mut b);
    b.extend_from_slice(&garbage);
    assert!(matches!(decode(&b), BlobError::Decompress(_)));

    // A bytes blob whose header claims one byte more than the frame holds.
    let b = forge(BlobKind::Raw.code(), 0, [0; 3], 0, b"hello");
    let mut lying = b.clone();
    lying[24..32].copy_from_slice(&6u64.to_le_bytes());
    fix_header_crc(&mut lying);
    assert!(matches!(
        blob::decode(&lying, BlobKind::Raw),
        Err(BlobError::Decompress(_))
    ));
    assert_eq!(blob::decode_bytes(&b, BlobKind::Raw).unwrap(), b"hello");

    // Well-formed blobs holding NaN or infinity: refused after decoding.
    // (Payloads are byte-shuffled: three NaNs are the low bytes of all three, then the next…)
    let nan_planes: Vec<u8> = f32::NAN.to_le_bytes().iter().flat_map(|&b| [b; 3]).collect();
    let nan = forge(k.code(), Encoding::F32.code(), [1, 3, 0], 2, &nan_planes);
    assert!(matches!(decode(&nan), BlobError::NonFinite { index: 0, .. }));
    let inf = forge(
        k.code(),
        Encoding::F16.code(),
        [1, 3, 0],
        2,
        &[0x00, 0x00, 0x00, 0x7c, 0x7c, 0x7c],
    ); // 3 × 0x7c00
    assert!(
        matches!(decode(&inf), BlobError::NonFinite { .. }),
        "{:?}",
        blob::decode(&inf, k)
    );

    // Typed readers on the wrong sort of blob.
    assert!(matches!(
        blob::decode_bytes(&good, k),
        Err(BlobError::WrongEncoding { .. })
    ));
    assert!(matches!(
        blob::decode_rgb(&b, BlobKind::Raw),
        Err(BlobError::WrongEncoding { .. })
    ));
    let flat = blob::encode_values(k, Encoding::F32, &[6], &[0.0; 6]).unwrap();
    assert!(matches!(blob::decode_rgb(&flat, k), Err(BlobError::BadShape { .. })));

    // Messages say what is wrong.
    assert_eq!(
        blob::decode(&good, BlobKind::Scene).unwrap_err().to_string(),
        "wrong blob kind: expected Scene, found TileRadiance"
    );
}

#[test]
fn every_truncation_is_an_error() {
    for good in [
        sample(),
        blob::encode_bytes(BlobKind::Manifest, b"{\"a\": 1}").unwrap(),
        blob::encode_values(BlobKind::DiffuseMaps, Encoding::Rgb9e5, &[4, 4, 3], &[1.5; 48]).unwrap(),
    ] {
        for len in 0..good.len() {
            match blob::decode(&good[..len], blob::read_header(&good).unwrap().kind) {
                Err(BlobError::Truncated { .. }) => {}
                other => panic!("truncated to {len} of {}: {other:?}", good.len()),
            }
        }
    }
}

/// Every single-bit flip anywhere in a blob is detected (CRC-32C catches all of them).
#[test]
fn every_bit_flip_is_an_error() {
    let good = sample();
    for i in 0..good.len() * 8 {
        let mut b = good.clone();
        b[i / 8] ^= 1 << (i % 8);
        assert!(
            blob::decode(&b, BlobKind::TileRadiance).is_err(),
            "flip of bit {i} undetected"
        );
    }
}

/// Random bytes, random prefixes of valid headers and random multi-byte damage: never a panic,
/// and never a success unless the bytes are unchanged.
#[test]
fn fuzz_never_panics() {
    let mut rng = Rng(0x5eed);
    let good = sample();
    for round in 0..30_000 {
        let mut b: Vec<u8> = match round % 3 {
            0 => (0..rng.next() % 160).map(|_| rng.next() as u8).collect(),
            1 => {
                let mut b = good[..(rng.next() as usize % HEADER_LEN)].to_vec();
                b.extend((0..rng.next() % 120).map(|_| rng.next() as u8));
                b
            }
            _ => good.clone(),
        };
        if round % 3 == 2 {
            for _ in 0..1 + rng.next() % 4 {
                let i = rng.next() as usize % b.len();
                b[i] = rng.next() as u8;
            }
        }
        let changed = b != good;
        for kind in [BlobKind::TileRadiance, BlobKind::Manifest] {
            let result = blob::decode(&b, kind);
            if changed {
                assert!(result.is_err(), "round {round}: damaged blob decoded");
            }
            let _ = blob::decode_rgb(&b, kind);
            let _ = blob::read_header(&b);
        }
    }
}

#[test]
fn decoded_data_variant_matches_encoding() {
    let b = blob::encode_bytes(BlobKind::Scene, b"abc").unwrap();
    assert!(matches!(
        blob::decode(&b, BlobKind::Scene).unwrap().data,
        Data::Bytes(_)
    ));
    let b = blob::encode_rgb(BlobKind::MirrorMaps, Encoding::F16, &[[1.0, 2.0, 3.0]]).unwrap();
    assert!(matches!(
        blob::decode(&b, BlobKind::MirrorMaps).unwrap().data,
        Data::Values(_)
    ));
}

#[test]
fn a_blob_has_the_same_bytes_whatever_its_thread_compressed_before() {
    // Compression contexts are kept per thread and level: what they did before must not show.
    let mut rng = Rng(7);
    let data: Vec<u8> = (0..300_000)
        .map(|i| if i % 7 == 0 { rng.next() as u8 } else { 0 })
        .collect();
    let first = blob::encode_bytes(BlobKind::Snapshot, &data).unwrap();
    let big: Vec<u8> = (0..2_000_000).map(|_| rng.next() as u8 >> 4).collect();
    blob::encode_bytes(BlobKind::Raw, &big).unwrap();
    blob::encode_bytes(BlobKind::Snapshot, &big[..1000]).unwrap();
    blob::encode_bytes(BlobKind::Snapshot, &[]).unwrap();
    let again = blob::encode_bytes(BlobKind::Snapshot, &data).unwrap();
    assert_eq!(first, again);
    // A thread that compressed nothing before (fresh contexts) writes the same bytes.
    let fresh = std::thread::spawn(move || blob::encode_bytes(BlobKind::Snapshot, &data).unwrap())
        .join()
        .unwrap();
    assert_eq!(first, fresh);
    assert_eq!(blob::decode_bytes(&first, BlobKind::Snapshot).unwrap().len(), 300_000);
}

#[test]
fn a_frame_cut_short_leaves_the_threads_decoder_fit_for_the_next_blob() {
    // Decompression contexts are kept per thread too: one left mid-frame must not show.
    let data: Vec<u8> = (0..200_000u32).map(|i| (i % 13 * (i % 7)) as u8).collect();
    let good = blob::encode_bytes(BlobKind::Snapshot, &data).unwrap();
    let mut cut = good[..HEADER_LEN + (good.len() - HEADER_LEN) / 2].to_vec();
    let stored = cut[HEADER_LEN..].to_vec();
    cut[32..40].copy_from_slice(&(stored.len() as u64).to_le_bytes());
    cut[40..44].copy_from_slice(&crc32c::crc32c(&stored).to_le_bytes());
    fix_header_crc(&mut cut);
    for _ in 0..3 {
        assert!(matches!(
            blob::decode_bytes(&cut, BlobKind::Snapshot),
            Err(BlobError::Decompress(_))
        ));
        assert_eq!(blob::decode_bytes(&good, BlobKind::Snapshot).unwrap(), data);
    }
}
