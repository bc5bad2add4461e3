//! Reading only what a view needs: `LightField::view_needs` lists the diffuse maps and mirror
//! tiles a view reads, `FieldJob::load_parts` reads just those, and the partial field draws
//! that view with the same bits as the whole one — with fewer blobs. The streaming viewer's
//! contract.

use glam::DVec3;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::{Camera, Image};
use vlf_core::scene::{ImportOptions, load_obj};
use vlf_store::blob::Encoding;
use vlf_store::{FieldJob, Stage, Store};

fn mirror_job() -> FieldJob {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/mirrors.obj");
    let scene = load_obj(&path, &ImportOptions::default()).expect("bundled scene").0;
    let options = Options {
        directions: 129,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(3),
        ..Options::default()
    };
    let store = Store::open("memory://").unwrap();
    let mut p = Propagation::new(scene, options).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    while !p.finished() {
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
    }
    job.finish(&p.into_field(), false).unwrap();
    job
}

fn views() -> Vec<Camera> {
    vec![
        // The whole box from the open side.
        Camera::new(
            DVec3::new(278.0, 273.0, -800.0),
            DVec3::new(278.0, 273.0, 0.0),
            DVec3::Y,
            39.0,
            48,
            36,
        )
        .unwrap(),
        // Close up on the wall mirror (on the x = 1 wall, facing +x).
        Camera::new(
            DVec3::new(300.0, 270.0, 295.0),
            DVec3::new(0.0, 270.0, 295.0),
            DVec3::Y,
            30.0,
            40,
            30,
        )
        .unwrap(),
    ]
}

fn bits(i: &Image) -> Vec<u32> {
    i.pixels.iter().flatten().map(|v| v.to_bits()).collect()
}

#[test]
fn a_view_renders_the_same_from_just_what_it_needs() {
    let job = mirror_job();
    for stage in [Stage::Field, Stage::Iteration(3)] {
        let (whole, all_blobs) = job.load_parts(stage, None).unwrap();
        for camera in views() {
            for mode in [SpecularMode::Rays, SpecularMode::Trace { depth: 4 }] {
                let needs = whole.view_needs(&camera, 2, mode);
                let (part, read) = job.load_parts(stage, Some(&needs)).unwrap();
                let expected = whole.render(&camera, 2, mode);
                assert!(
                    bits(&part.render(&camera, 2, mode)) == bits(&expected),
                    "{stage:?} {mode:?}: not the same bits"
                );
                assert!(read < all_blobs, "{stage:?} {mode:?}: read {read} of {all_blobs} blobs");
                assert!(!needs.surfaces.is_empty());
                if mode == SpecularMode::Rays {
                    assert!(!needs.mirror_tiles.is_empty(), "the views see a mirror");
                } else {
                    assert!(needs.mirror_tiles.is_empty(), "tracing reads no mirror tile");
                }
                // And the needs are needed: without its mirror tiles the view changes.
                if mode == SpecularMode::Rays {
                    let mut less = needs.clone();
                    less.mirror_tiles.clear();
                    let (poorer, _) = job.load_parts(stage, Some(&less)).unwrap();
                    assert!(
                        bits(&poorer.render(&camera, 2, mode)) != bits(&expected),
                        "{stage:?}: tiles not needed"
                    );
                }
            }
        }
    }
}

#[test]
fn a_close_view_needs_a_fraction_of_the_tiles() {
    let job = mirror_job();
    let (whole, all_blobs) = job.load_parts(Stage::Field, None).unwrap();
    let close = &views()[1];
    let needs = whole.view_needs(close, 1, SpecularMode::Rays);
    let (_, read) = job.load_parts(Stage::Field, Some(&needs)).unwrap();
    eprintln!(
        "close-up: {} surfaces, {} mirror tiles: {read} of {all_blobs} blobs",
        needs.surfaces.len(),
        needs.mirror_tiles.len()
    );
    assert!(read * 2 < all_blobs, "{read} of {all_blobs}");
}

#[test]
fn the_needed_keys_are_all_a_view_reads() {
    // A store holding the manifest, the scene and the needed keys only — what a streaming
    // viewer fetched first — draws the view with the same bits.
    let job = mirror_job();
    let id = job.id().clone();
    let camera = &views()[1];
    for stage in [Stage::Field, Stage::Iteration(3)] {
        let whole = job.load(stage).unwrap();
        let needs = whole.view_needs(camera, 1, SpecularMode::Rays);
        let keys = job.needed_keys(stage, &needs).unwrap();
        let partial = Store::open("memory://").unwrap();
        for key in [vlf_store::layout::manifest(&id), vlf_store::layout::scene(&id)]
            .iter()
            .chain(&keys)
        {
            partial.put(key, job.job().store().get(key).unwrap()).unwrap();
        }
        let job_there = FieldJob::open(&partial, &id).unwrap();
        let (field, read) = job_there.load_parts(stage, Some(&needs)).unwrap();
        assert_eq!(
            read + 1,
            keys.len(),
            "{stage:?}: every key but the summary is a radiance blob read"
        );
        let expected = whole.render(camera, 1, SpecularMode::Rays);
        assert!(
            bits(&field.render(camera, 1, SpecularMode::Rays)) == bits(&expected),
            "{stage:?}"
        );
    }
}
