//! A propagation within a subfield budget (`Propagation::with_subfield_budget`): the subfields
//! built on demand and dropped when the budget is full give the same bits as the whole set
//! held, and what is alive stays within the stated bound, `budget + threads · largest`.

mod common;

use common::*;
use vlf_core::propagate::{Options, Propagation};
use vlf_core::scene::Scene;

/// Runs `scene` holding every subfield and within a quarter of them, on `threads` threads;
/// checks the bits and the bound.
fn same_bits_within_a_quarter(scene: Scene, options: Options, threads: usize) {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    pool.install(|| {
        let mut whole = Propagation::new(scene.clone(), options.clone()).unwrap();
        let all = whole.subfields.memory().live;
        let largest = whole.subfields.map(|_, s| s.memory_bytes()).into_iter().max().unwrap();
        let budget = all / 4;
        let mut bounded = Propagation::with_subfield_budget(scene, options, Some(budget)).unwrap();
        while !whole.finished() {
            whole.step(|_| {});
            bounded.step(|_| {});
            assert_eq!(
                without_times(bounded.checkpoint()),
                without_times(whole.checkpoint()),
                "iteration {} differs within a budget on {threads} threads",
                whole.iterations_done()
            );
        }
        let held = bounded.subfields.memory();
        let l = bounded.directions.len() as u64;
        assert!(
            held.builds > 2 * l,
            "a quarter's budget rebuilds every iteration: {held:?}"
        );
        assert!(
            held.peak <= budget + threads * largest,
            "{} bytes alive at once, over {budget} + {threads}·{largest}",
            held.peak
        );
        assert!(held.peak < all / 2, "the bound is no bound: {held:?} of {all}");
        // The finished field reads its mirror tiles' subfields through the same budget.
        let subfields = bounded.subfields.clone();
        let (field, reference) = (bounded.into_field(), whole.into_field());
        assert_eq!(field.radiance, reference.radiance);
        assert_eq!(
            field.specular.as_ref().map(|s| &s.totals),
            reference.specular.as_ref().map(|s| &s.totals)
        );
        let parts = vlf_core::parts::PartCatalog::new(&field);
        assert_eq!(
            parts,
            vlf_core::parts::PartCatalog::new(&reference),
            "another tile layout"
        );
        assert!(
            subfields.memory().peak <= budget + threads * largest,
            "the field's assembly held {:?}",
            subfields.memory()
        );
    });
}

#[test]
fn diffuse_and_perturbed_within_a_budget() {
    same_bits_within_a_quarter(lit_box(), split_options(0), 1);
    same_bits_within_a_quarter(lit_box(), split_options(2), 2);
}

#[test]
fn mirrors_within_a_budget() {
    // The gather reads a source direction's subfield for every route: two alive per thread.
    same_bits_within_a_quarter(mirror_room(), split_options(0), 2);
}
