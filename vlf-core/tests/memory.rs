//! A propagation within a subfield budget (`Propagation::with_subfield_budget`): the subfields
//! built on demand and dropped when the budget is full give the same bits as the whole set
//! held, and what is alive stays within the stated bound, `budget + threads · largest`.

mod common;

use common::*;
use vlf_core::propagate::{Options, Pass, Propagation, Survey};
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
        // The whole geometry keeps its gathers' tables, the bounded one finds them every time:
        // both ways give the same bits.
        if let (Some(w), Some(b)) = (&whole.specular, &bounded.specular) {
            assert!(w.keep_gather_tables && !b.keep_gather_tables);
        }
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

/// With the survey known (stored with a job: `Propagation::with_survey`), set-up builds no
/// subfield of a diffuse scene: a block builds those of its own directions when it shoots them,
/// and a whole run builds each once and steps with the same bits as the geometry built whole.
#[test]
fn a_known_survey_builds_only_the_subfields_shot() {
    for perturb in [0, 2] {
        let options = split_options(perturb);
        let mut whole = Propagation::new(lit_box(), options.clone()).unwrap();
        let survey = Survey::from_bytes(&whole.survey().to_bytes()).unwrap();
        assert_eq!(survey, whole.survey());
        let l = whole.directions.len() as u64;

        let mut part = Propagation::with_survey(lit_box(), options.clone(), None, survey.clone()).unwrap();
        assert_eq!(part.subfields.memory().builds, 0, "set-up built subfields");
        if perturb == 0 {
            let work = part.iteration_work();
            let (_, none) = part.compute_block(&work, Pass::Shoot, 2..4).unwrap();
            assert!(none.is_none());
            let shot = part.batching().directions_of(2..4).len() as u64;
            let held = part.subfields.memory();
            assert_eq!(held.builds, shot, "a block of {shot} directions built {held:?}");
            assert_eq!(held.budget, None);
        }

        let mut known = Propagation::with_survey(lit_box(), options, None, survey).unwrap();
        while !whole.finished() {
            whole.step(|_| {});
            known.step(|_| {});
            assert_eq!(
                without_times(known.checkpoint()),
                without_times(whole.checkpoint()),
                "iteration {} differs with the survey known (perturbed {perturb})",
                whole.iterations_done()
            );
        }
        assert_eq!(known.subfields.memory().builds, l, "each subfield built once");
        assert_eq!(known.into_field().radiance, whole.into_field().radiance);
    }
}

/// With mirrors, the survey also says which mirrors light reaches (the plan's search over every
/// subfield); set-up then builds no subfield, the mirror views rasterising the mirror planes
/// alone. The same plan and the same bits.
#[test]
fn a_known_survey_with_mirrors_gives_the_same_bits() {
    let options = split_options(0);
    let mut whole = Propagation::new(mirror_room(), options.clone()).unwrap();
    let survey = whole.survey();
    assert!(!survey.lit_mirrors.is_empty());
    let mut known = Propagation::with_survey(mirror_room(), options, None, survey).unwrap();
    assert_eq!(known.plan, whole.plan);
    assert_eq!(known.subfields.memory().builds, 0);
    while !whole.finished() {
        whole.step(|_| {});
        known.step(|_| {});
    }
    assert_eq!(without_times(known.checkpoint()), without_times(whole.checkpoint()));
}

/// A survey that does not fit the scene is refused with what is wrong with it, never used; bytes
/// that are not a survey are refused when read.
#[test]
fn surveys_that_do_not_fit_are_refused() {
    let options = split_options(0);
    let survey = Propagation::new(mirror_room(), options.clone()).unwrap().survey();
    let texels = survey.projected_area.len();
    let refused = |s: Survey| {
        Propagation::with_survey(mirror_room(), options.clone(), None, s)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default()
    };
    let with_areas = |areas: Vec<f64>| Survey::new(survey.of.clone(), areas, survey.lit_mirrors.clone());
    let short = refused(with_areas(survey.projected_area[1..].to_vec()));
    assert!(short.contains(&format!("{} areas", texels - 1)), "{short}");
    for bad in [f64::NAN, f64::INFINITY, -1.0] {
        let mut wrong = survey.projected_area.clone();
        wrong[7] = bad;
        let message = refused(with_areas(wrong));
        assert!(message.contains("texel 7"), "{bad}: {message}");
    }
    let dark = refused(with_areas(vec![0.0; texels]));
    assert!(dark.contains("no emitter"), "{dark}");
    let (m, k) = survey.lit_mirrors[0];
    let wall = (0..mirror_room().surfaces.len() as u32)
        .find(|&s| !mirror_room().material(s as usize).is_mirror())
        .unwrap();
    for (lit, says) in [
        (vec![(wall, k)], "not a mirror"),
        (vec![(99, k)], "not a mirror"),
        (vec![(m, k), (m, k)], "out of order or twice"),
        (vec![(m, 1000)], "iteration 1000"),
    ] {
        let message = refused(Survey::new(survey.of.clone(), survey.projected_area.clone(), lit));
        assert!(message.contains(says), "{message}");
    }
    // Learnt for other options or another scene: refused even where the texels would match
    // (the number of directions leaves them as they are).
    let fewer = Options {
        directions: 33,
        ..options.clone()
    };
    let other = Propagation::new(mirror_room(), fewer).unwrap().survey();
    assert_eq!(other.projected_area.len(), texels);
    assert!(refused(other).contains("learnt for l = 33"));
    let other = Propagation::new(lit_box(), options.clone()).unwrap().survey();
    assert!(refused(other).contains("learnt for another scene"));

    let bytes = survey.to_bytes();
    for (bytes, says) in [
        (bytes[..bytes.len() - 3].to_vec(), "survey"),
        ([bytes.as_slice(), &[0]].concat(), "trailing"),
        ([&[9, 0, 0, 0][..], &bytes[4..]].concat(), "version 9"),
        (bytes[..2].to_vec(), "too short"),
    ] {
        let message = Survey::from_bytes(&bytes).unwrap_err().to_string();
        assert!(message.contains(says), "{message}");
        assert!(Survey::read_stored(&bytes).is_err(), "{says}");
    }
    // A survey of the earlier layout (version 1, which did not say what it was learnt for) is
    // passed over when stored: the job learns it again.
    assert_eq!(Survey::read_stored(&bytes).unwrap(), Some(survey.clone()));
    let unkeyed = [&[1, 0, 0, 0][..], &bytes[4..]].concat();
    assert_eq!(Survey::read_stored(&unkeyed).unwrap(), None);
    assert!(Survey::from_bytes(&unkeyed).is_err());
}
