//! Reading only what a view needs: `LightField::view_needs` lists the diffuse maps and mirror
//! tiles a view reads, `FieldJob::load_parts` reads just those, and the partial field draws
//! that view with the same bits as the whole one — with fewer blobs. The streaming viewer's
//! contract.

use glam::DVec3;
use vlf_core::lookup::SpecularMode;
use vlf_core::parts::{Part, PartCatalog};
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::{Camera, Image};
use vlf_core::scene::{ImportOptions, load_obj};
use vlf_store::blob::Encoding;
use vlf_store::{FieldJob, Stage, StageParts, Store};

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
        let reader = StageParts::open(job.clone(), stage).unwrap();
        let geometry = reader.geometry().unwrap();
        let catalog = PartCatalog::new(&geometry);
        let mut keys = reader.keys(&catalog, &catalog.needed(&needs)).unwrap();
        keys.push(vlf_store::layout::summary(&id, stage).unwrap());
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
        // A snapshot's mirror radiance is read by batch of directions: those the view sees.
        if let Stage::Iteration(_) = stage {
            let batches = keys.iter().filter(|k| k.contains("/mirror-radiance/")).count();
            let all = job.options().batching().count();
            eprintln!("close-up of snapshot: {batches} of {all} batches of mirror radiance");
            assert!(batches > 0 && batches < all, "{batches} of {all}");
        }
    }
}

#[test]
fn parts_read_one_by_one_are_the_fields_and_bad_blobs_are_named() {
    let job = mirror_job();
    for stage in [Stage::Field, Stage::Iteration(2)] {
        let whole = job.load(stage).unwrap();
        let reader = StageParts::open(job.clone(), stage).unwrap();
        let geometry = reader.geometry().unwrap();
        let catalog = PartCatalog::new(&geometry);
        assert_eq!(catalog, PartCatalog::new(&whole));
        // Every part, in an order of its own: the whole field's values, bit for bit.
        let parts: Vec<u32> = (0..catalog.len() as u32).rev().collect();
        let values = reader.read(&catalog, &parts).unwrap();
        for (&p, v) in parts.iter().zip(&values) {
            let want = whole.part_values(&catalog, p);
            assert!(
                v.iter()
                    .flatten()
                    .map(|c| c.to_bits())
                    .eq(want.iter().flatten().map(|c| c.to_bits())),
                "{stage:?}: part {p}"
            );
        }
        let (_, job_bytes) = job.stored_bytes(stage).unwrap();
        assert!(reader.bytes_read() > 0 && reader.bytes_read() < job_bytes);
    }
    // A corrupted tile (a direction's blob, a snapshot's batch of mirror radiance), or the blob
    // of a batch with other slots: an error that names its key; the other parts still read.
    let store = job.job().store();
    for stage in [Stage::Field, Stage::Iteration(2)] {
        let reader = StageParts::open(job.clone(), stage).unwrap();
        let geometry = reader.geometry().unwrap();
        let catalog = PartCatalog::new(&geometry);
        let tiles: Vec<u32> = (0..catalog.len() as u32)
            .filter(|&p| matches!(catalog.part(p), Part::Tile { .. }))
            .collect();
        let (tile, last) = (tiles[0], *tiles.last().unwrap());
        let (key, other) = (reader.key(&catalog, tile).unwrap(), reader.key(&catalog, last).unwrap());
        let good = store.get(&key).unwrap().to_vec();
        let mut bytes = good.clone();
        let middle = bytes.len() / 2;
        bytes[middle] ^= 0x55;
        store.put(&key, bytes).unwrap();
        let error = reader.read(&catalog, &[0, tile]).unwrap_err().to_string();
        assert!(error.contains(&key), "{stage:?}: {error}");
        assert!(reader.read(&catalog, &[0]).is_ok());
        if stage != Stage::Field {
            assert!(key.contains("/mirror-radiance/") && key != other, "{key}, {other}");
            store.put(&key, store.get(&other).unwrap()).unwrap();
            let fresh = StageParts::open(job.clone(), stage).unwrap();
            let error = fresh.read(&catalog, &[tile]).unwrap_err().to_string();
            assert!(error.contains(&key) && error.contains("shape"), "{stage:?}: {error}");
        }
        store.put(&key, good).unwrap();
    }
    // A stage that is not committed is refused.
    assert!(StageParts::open(job.clone(), Stage::Iteration(99)).is_err());
}
