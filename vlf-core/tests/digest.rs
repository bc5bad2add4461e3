//! `LightField::digest`: the fingerprint users compare a cluster's field with a local run's by.
//! It must be the same for the same field however it was computed, and differ for a field
//! that differs in one bit of one value, diffuse or mirror, or in its iteration count.

mod common;

use common::*;
use vlf_core::field::LightField;
use vlf_core::propagate::{Propagation, Stop};

fn field(threads: usize, iterations: u32) -> LightField {
    let options = vlf_core::propagate::Options {
        stop: Stop::Iterations(iterations),
        ..split_options(1)
    };
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    pool.install(|| {
        let mut p = Propagation::new(mirror_room(), options).unwrap();
        p.run(|_| {});
        p.into_field()
    })
}

/// `v` with the lowest bit of its first channel flipped.
fn flipped(v: [f32; 3]) -> [f32; 3] {
    [f32::from_bits(v[0].to_bits() ^ 1), v[1], v[2]]
}

#[test]
fn the_same_field_on_any_thread_count_has_the_same_digest_and_one_bit_changes_it() {
    let one = field(1, 3);
    let two = field(2, 3);
    assert!(one.specular.is_some(), "the scene has lit mirrors");
    // The propagation gives the same bits on 1 and 2 threads (the fields' other parts, such as
    // the subfields' caches, are how a run went, not its result).
    assert!(one.radiance == two.radiance, "diffuse radiance on 1 and 2 threads");
    let mirrors = |f: &LightField| f.specular.as_ref().map(|s| s.totals.clone());
    assert!(mirrors(&one) == mirrors(&two), "mirror totals on 1 and 2 threads");
    let digest = one.digest();
    assert_eq!(digest.len(), 64);
    assert!(digest.chars().all(|c| c.is_ascii_hexdigit() && !c.is_ascii_uppercase()));
    assert_eq!(two.digest(), digest, "the same field, the same digest");
    // Hashing the mirror totals in parallel leaves it as it was.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
    assert_eq!(pool.install(|| one.digest()), digest);

    // One bit of one diffuse texel, anywhere.
    for t in [0, one.radiance.len() / 2, one.radiance.len() - 1] {
        let mut f = one.clone();
        f.radiance[t] = flipped(f.radiance[t]);
        assert_ne!(f.digest(), digest, "texel {t}");
    }
    // One bit of one mirror value, of the first and of the last direction that has any.
    let totals = &one.specular.as_ref().unwrap().totals;
    let lit: Vec<usize> = (0..totals.len()).filter(|&d| !totals[d].is_empty()).collect();
    for d in [lit[0], lit[lit.len() - 1]] {
        let mut f = one.clone();
        let t = &mut f.specular.as_mut().unwrap().totals[d];
        let last = t.len() - 1;
        t[last] = flipped(t[last]);
        assert_ne!(f.digest(), digest, "mirror slot of direction {d}");
    }
    // Values moved from one direction's totals to the next's: the same bytes in a row, another
    // field.
    let mut f = one.clone();
    let totals = &mut f.specular.as_mut().unwrap().totals;
    let (a, b) = (lit[0], lit[1]);
    let moved = totals[a].pop().unwrap();
    totals[b].insert(0, moved);
    assert_ne!(f.digest(), digest, "a value moved across directions");

    // One more iteration is another field.
    assert_ne!(field(1, 4).digest(), digest);
}
