//! What a worker spends turning a block's output into a blob, and a coordinator turning it back.
//!
//! `cargo bench -p vlf-store --bench outputs`: the output of a whole pass of the 47 794-triangle
//! mirror dragon at l = 2049, N = 128 (one worker's lease): a dense sum over 52 000 texels and
//! its arrivals settled by batch ([`vlf_core::propagate::Arrivals::Settled`], 64 batches, each
//! feeding every batch). Beside it, the same pass as earlier builds reported it, per direction
//! `Φ_in` on the 1 600 mirror triangles it lights ([`vlf_core::propagate::Arrivals::Power`]),
//! about 93 MB serialised. Its powers are random, so they hardly compress: the compressor's
//! share here is its floor.
//!
//! Each way both directions: serialised into memory, then compressed (`in memory`), as block
//! outputs were written until this bench; and serialised into the compressor as it goes
//! (`streamed`, [`vlf_store::blob::encode_bytes_with`]), as they are now — and read back the
//! same two ways.

use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;
use vlf_core::propagate::specular::BatchArrivals;
use vlf_core::propagate::{Arrivals, BatchOutput, BatchSum, Exchange, Pass};
use vlf_store::BlobKind;
use vlf_store::blob::{decode_bytes, decode_bytes_with, encode_bytes, encode_bytes_with};

/// A deterministic stand-in for a pass's output: `directions` lists of `lit` mirrors each, out
/// of `mirrors`, with powers that vary in their low bits as real sums do; `settled`, those of
/// the 64 batches settled instead.
fn pass_output(texels: usize, directions: usize, mirrors: u32, lit: usize, settled: bool) -> BatchOutput {
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let mut value = || (next() >> 11) as f64 / (1u64 << 53) as f64;
    let texels = (0..texels).map(|_| [value(), value(), value()]).collect();
    let power_in: Vec<Vec<(u32, [f64; 3])>> = (0..directions)
        .map(|_| {
            let mut list: Vec<(u32, [f64; 3])> = Vec::with_capacity(lit);
            let step = mirrors / lit as u32;
            for i in 0..lit as u32 {
                let k = i * step + (value() * f64::from(step)) as u32;
                list.push((k, [value(), value(), value()]));
            }
            list
        })
        .collect();
    BatchOutput {
        iteration: 2,
        pass: Pass::Shoot,
        batches: 0..64,
        sum: BatchSum {
            texels,
            flow: Default::default(),
        },
        arrivals: Some(match settled {
            false => Arrivals::Power(power_in),
            true => Arrivals::Settled(
                (0..64)
                    .map(|_| BatchArrivals {
                        exchange: Exchange {
                            incident: [value(), value(), value()],
                            reflected: [value(), value(), value()],
                        },
                        feeds: (0..64).collect(),
                    })
                    .collect(),
            ),
        }),
    }
}

fn outputs(c: &mut Criterion) {
    for (name, settled) in [
        ("mirror dragon pass output", true),
        ("the same, as earlier builds", false),
    ] {
        let out = pass_output(52_000, 2049, 47_794, 1600, settled);
        let bytes = out.to_bytes();
        let blob = encode_bytes(BlobKind::BatchOutput, &bytes).expect("encodes");
        eprintln!(
            "{name}: {:.1} MB serialised, {:.1} MB as a blob",
            bytes.len() as f64 / 1e6,
            blob.len() as f64 / 1e6
        );
        let mut group = c.benchmark_group(name);
        group.sample_size(10);
        group.bench_function("serialise", |b| b.iter(|| black_box(out.to_bytes())));
        group.bench_function("encode blob in memory", |b| {
            b.iter(|| black_box(encode_bytes(BlobKind::BatchOutput, &out.to_bytes()).expect("encodes")))
        });
        group.bench_function("encode blob streamed", |b| {
            b.iter(|| {
                let blob = encode_bytes_with(BlobKind::BatchOutput, out.serialized_len(), |w| out.write_to(w));
                black_box(blob.expect("encodes"))
            })
        });
        group.bench_function("decode blob in memory", |b| {
            b.iter(|| {
                let bytes = decode_bytes(&blob, BlobKind::BatchOutput).expect("decodes");
                black_box(BatchOutput::from_bytes(&bytes).expect("reads"))
            })
        });
        group.bench_function("decode blob streamed", |b| {
            b.iter(|| {
                let read = decode_bytes_with(&blob, BlobKind::BatchOutput, |r| BatchOutput::read_from(r));
                black_box(read.expect("decodes").expect("reads"))
            })
        });
        group.finish();
    }
}

criterion_group!(benches, outputs);
criterion_main!(benches);
