//! Streaming on the GPU (`vlf_viewer::stream`): the parts a view needs are all it fetches, a
//! view drawn from a streamed pool is the complete field's image, a cache smaller than the
//! walk's working set evicts and fetches again and still draws every view right, and a source
//! that fails now and then is retried without leaving anything wrong behind.
//!
//! "The complete field's image" is bit for bit where the GPU reads only what the CPU's
//! `view_needs` lists; where f32 and f64 disagree on a ray at a cell's edge the GPU may read a
//! tile the CPU did not list and trace that pixel instead (see `shaders/field.wgsl`). The
//! tolerance says so: at most 0.5 % of the pixels differ. Measured on lavapipe: none.

mod common;

use common::{bundled_field_with_texel, bundled_first_and_last, gpu};
use glam::DVec3;
use std::collections::BTreeSet;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::parts::PartCatalog;
use vlf_core::render::{Camera, Image};
use vlf_viewer::direct::DirectSource;
use vlf_viewer::stream::{FieldParts, StreamConfig, Streamer};
use vlf_viewer::{FieldRenderer, Gpu, MirrorMode, PartSource};

/// The bundled mirror scene, coarse.
/// Fine texels, so that the diffuse maps come in several chunks and each view needs some of
/// them, not all.
fn field() -> LightField {
    let field = bundled_field_with_texel("mirrors.obj", 129, 3, 0.1);
    let chunks = PartCatalog::new(&field).chunks();
    assert!(chunks >= 3, "{chunks} chunks of diffuse maps");
    field
}

/// The field with its radiance zero: what a viewer starts from.
fn geometry(field: &LightField) -> LightField {
    let mut g = field.clone();
    g.radiance.iter_mut().for_each(|v| *v = [0.0; 3]);
    if let Some(spec) = &mut g.specular {
        spec.totals.iter_mut().flatten().for_each(|v| *v = [0.0; 3]);
    }
    g
}

/// Two views apart — the wall mirror close up, the back of the box — and the whole box from the
/// front (both mirrors among the walls).
fn views() -> [Camera; 3] {
    let camera = |eye: DVec3, target: DVec3, fovy| Camera::new(eye, target, DVec3::Y, fovy, 64, 48).expect("camera");
    [
        camera(DVec3::new(300.0, 270.0, 295.0), DVec3::new(0.0, 270.0, 295.0), 30.0),
        camera(DVec3::new(278.0, 273.0, 100.0), DVec3::new(278.0, 273.0, 600.0), 30.0),
        camera(DVec3::new(278.0, 273.0, -800.0), DVec3::new(278.0, 273.0, 0.0), 39.0),
    ]
}

/// A source that records what it is asked for and fails every `fail_every`-th call.
struct Recording {
    inner: FieldParts,
    asked: Arc<Mutex<Vec<u32>>>,
    calls: u64,
    fail_every: u64,
}

impl PartSource for Recording {
    fn fetch(&mut self, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>, String> {
        self.calls += 1;
        if self.fail_every > 0 && self.calls.is_multiple_of(self.fail_every) {
            return Err("connection reset by peer (simulated)".into());
        }
        self.asked.lock().unwrap().extend_from_slice(parts);
        self.inner.fetch(parts)
    }

    fn bytes(&self) -> u64 {
        0
    }
}

/// The parts a view reads with mirrors from the rays.
fn needed(field: &LightField, catalog: &PartCatalog, camera: &Camera) -> BTreeSet<u32> {
    catalog
        .needed(&field.view_needs(camera, 1, SpecularMode::Rays))
        .into_iter()
        .collect()
}

fn differing(a: &Image, b: &Image) -> usize {
    a.pixels.iter().zip(&b.pixels).filter(|(p, q)| p != q).count()
}

struct Setup {
    field: Arc<LightField>,
    geometry: Arc<LightField>,
    catalog: PartCatalog,
}

fn setup() -> Setup {
    let field = field();
    let geometry = geometry(&field);
    Setup {
        catalog: PartCatalog::new(&field),
        field: Arc::new(field),
        geometry: Arc::new(geometry),
    }
}

/// Looks at `camera`, waits for the streamer, uploads, draws.
fn draw(gpu: &Gpu, renderer: &FieldRenderer, streamer: &Streamer, camera: &Camera) -> Image {
    streamer.look(*camera, MirrorMode::Rays);
    assert!(streamer.wait_idle(Duration::from_secs(120)), "{:?}", streamer.stats());
    streamer.apply(gpu, renderer).expect("apply");
    vlf_viewer::render(gpu, renderer, camera, 1, SpecularMode::Rays).expect("render")
}

fn config(capacity: usize) -> StreamConfig {
    StreamConfig {
        capacity,
        batch_values: 4096,
        batch_parts: 16,
        backoff: Duration::from_millis(1),
        direct: None,
    }
}

#[test]
fn a_small_cache_fetches_what_each_view_needs_evicts_and_draws_every_view_right() {
    let Some(gpu) = gpu() else { return };
    let s = setup();
    let complete = FieldRenderer::new(&gpu, &s.field).expect("upload");
    let [a, b, _] = views();
    let (need_a, need_b) = (needed(&s.field, &s.catalog, &a), needed(&s.field, &s.catalog, &b));
    let values = |set: &BTreeSet<u32>| set.iter().map(|&p| s.catalog.values(p)).sum::<usize>();
    let union: BTreeSet<u32> = need_a.union(&need_b).copied().collect();
    // Room for either view (and some), not for both.
    let (big, small) = (
        values(&need_a).max(values(&need_b)),
        values(&need_a).min(values(&need_b)),
    );
    let capacity = big + small / 2;
    assert!(
        capacity < values(&union),
        "the walk's working set must exceed the cache: {} + {} values, {} together",
        values(&need_a),
        values(&need_b),
        values(&union)
    );
    assert!(
        values(&union) < s.catalog.total_values(),
        "a view needs part of the field"
    );

    let asked = Arc::new(Mutex::new(Vec::new()));
    let source = Recording {
        inner: FieldParts::new(s.field.clone()),
        asked: asked.clone(),
        calls: 0,
        fail_every: 0,
    };
    let renderer = FieldRenderer::streaming(&gpu, &s.geometry, capacity).expect("pool");
    let streamer = Streamer::start(s.geometry.clone(), Box::new(source), config(capacity));
    let mut fetched_before = 0;
    for (camera, need) in [(&a, &need_a), (&b, &need_b), (&a, &need_a)] {
        let image = draw(&gpu, &renderer, &streamer, camera);
        let expected = vlf_viewer::render(&gpu, &complete, camera, 1, SpecularMode::Rays).expect("render");
        let off = differing(&image, &expected);
        eprintln!(
            "{off} of {} pixels differ from the complete field's",
            image.pixels.len()
        );
        assert!(off * 200 <= image.pixels.len(), "{off} pixels differ");
        // Everything it fetched for this view, the view needs.
        let asked: Vec<u32> = asked.lock().unwrap()[fetched_before..].to_vec();
        fetched_before += asked.len();
        let distinct: BTreeSet<u32> = asked.iter().copied().collect();
        assert_eq!(distinct.len(), asked.len(), "no part fetched twice for one view");
        assert!(distinct.is_subset(need), "fetched parts the view does not need");
        if fetched_before == asked.len() {
            // The first view, into an empty cache: exactly what it touches.
            assert_eq!(&distinct, need);
        }
        let stats = streamer.stats();
        assert!(!stats.cache_full && stats.missing == 0, "{stats:?}");
        assert!(stats.resident_values <= capacity);
    }
    // The second view evicted parts of the first, which came back for the third: fetched more
    // than the union, and the first view's own parts are all the third fetched.
    let stats = streamer.stats();
    assert!(
        stats.fetched as usize > union.len(),
        "{stats:?} vs {} parts",
        union.len()
    );
    eprintln!(
        "views need {} + {} parts ({} together, {} values; cache {capacity}); fetched {}",
        need_a.len(),
        need_b.len(),
        union.len(),
        values(&union),
        stats.fetched
    );
}

#[test]
fn a_failing_source_is_retried_and_a_cache_too_small_for_a_view_draws_what_fits() {
    let Some(gpu) = gpu() else { return };
    let s = setup();
    let complete = FieldRenderer::new(&gpu, &s.field).expect("upload");
    let [_, _, a] = views();
    let need_a = needed(&s.field, &s.catalog, &a);
    let values: usize = need_a.iter().map(|&p| s.catalog.values(p)).sum();

    // Every other fetch fails: retried until everything is there, same image.
    let source = Recording {
        inner: FieldParts::new(s.field.clone()),
        asked: Arc::new(Mutex::new(Vec::new())),
        calls: 0,
        fail_every: 2,
    };
    let renderer = FieldRenderer::streaming(&gpu, &s.geometry, values).expect("pool");
    let streamer = Streamer::start(s.geometry.clone(), Box::new(source), config(values));
    let image = draw(&gpu, &renderer, &streamer, &a);
    let expected = vlf_viewer::render(&gpu, &complete, &a, 1, SpecularMode::Rays).expect("render");
    assert!(differing(&image, &expected) * 200 <= image.pixels.len());
    let stats = streamer.stats();
    assert!(stats.retries > 0 && stats.error.is_none(), "{stats:?}");
    assert_eq!(stats.fetched as usize, need_a.len());

    // Room for the view's diffuse maps, not its tiles: the maps come first, so every surface is
    // drawn right, and the mirrors are traced through the maps that are there meanwhile; the
    // streamer says the cache is full.
    let maps: usize = need_a
        .iter()
        .filter(|&&p| matches!(s.catalog.part(p), vlf_core::parts::Part::Chunk(_)))
        .map(|&p| s.catalog.values(p))
        .sum();
    assert!(maps < values);
    let renderer = FieldRenderer::streaming(&gpu, &s.geometry, maps).expect("pool");
    let streamer = Streamer::start(
        s.geometry.clone(),
        Box::new(FieldParts::new(s.field.clone())),
        config(maps),
    );
    let image = draw(&gpu, &renderer, &streamer, &a);
    let stats = streamer.stats();
    assert!(stats.cache_full && stats.missing > 0, "{stats:?}");
    // Off the mirrors (where the complete field shows no reflection), the complete image.
    let flat = vlf_viewer::render(&gpu, &complete, &a, 1, SpecularMode::Trace { depth: 0 }).expect("render");
    let (mut off_mirror, mut same) = (0, 0);
    for ((p, e), f) in image.pixels.iter().zip(&expected.pixels).zip(&flat.pixels) {
        if e == f {
            off_mirror += 1;
            same += (p == e) as usize;
        }
    }
    assert!(off_mirror > image.pixels.len() / 10, "the view shows more than mirrors");
    assert!(
        same * 200 >= off_mirror * 199,
        "{same} of {off_mirror} pixels off the mirrors"
    );
    assert!(
        differing(&image, &expected) > 0,
        "the mirror is traced, not drawn from rays it lacks"
    );
    assert!(image.pixels.iter().flatten().all(|c| c.is_finite()));
}

#[test]
fn a_camera_that_never_stops_still_gets_parts() {
    // No GPU needed: the streamer alone. A new camera arrives every 0.1 ms, much faster than a
    // view is planned; each view must still get its first batch.
    let s = setup();
    let [a, b, _] = views();
    let streamer = Streamer::start(
        s.geometry.clone(),
        Box::new(FieldParts::new(s.field.clone())),
        config(s.catalog.total_values()),
    );
    let until = std::time::Instant::now() + Duration::from_millis(300);
    let mut turn = 0u64;
    while std::time::Instant::now() < until {
        streamer.look(if turn.is_multiple_of(2) { a } else { b }, MirrorMode::Rays);
        turn += 1;
        std::thread::sleep(Duration::from_micros(100));
    }
    let stats = streamer.stats();
    assert!(stats.fetched > 0, "nothing fetched while the camera moved: {stats:?}");
    // Once it stops, the last view is completed.
    assert!(streamer.wait_idle(Duration::from_secs(60)));
    assert_eq!(streamer.stats().missing, 0);
}

/// Gives the first batch with its parts cut short, then the right ones.
struct ShortFirst {
    inner: FieldParts,
    calls: u32,
}

impl PartSource for ShortFirst {
    fn fetch(&mut self, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>, String> {
        self.calls += 1;
        let mut values = self.inner.fetch(parts)?;
        if self.calls == 1 {
            values.iter_mut().for_each(|v| {
                v.pop();
            });
        }
        Ok(values)
    }

    fn bytes(&self) -> u64 {
        0
    }
}

#[test]
fn parts_of_the_wrong_size_are_refused_and_fetched_again() {
    let s = setup();
    let [a, _, _] = views();
    let need = needed(&s.field, &s.catalog, &a);
    let source = ShortFirst {
        inner: FieldParts::new(s.field.clone()),
        calls: 0,
    };
    let streamer = Streamer::start(s.geometry.clone(), Box::new(source), config(s.catalog.total_values()));
    streamer.look(a, MirrorMode::Rays);
    assert!(streamer.wait_idle(Duration::from_secs(60)));
    let stats = streamer.stats();
    assert_eq!(stats.retries, 1, "{stats:?}");
    assert_eq!(stats.fetched as usize, need.len(), "{stats:?}");
    assert_eq!((stats.missing, stats.resident), (0, need.len()), "{stats:?}");
}

/// Exact direct light streamed: the direct parts come from snapshot 1 through a
/// [`DirectSource`], each after its chunk, and every view then draws what the complete exact
/// renderer draws. Until a surface's direct part is resident it shows the field's own direct
/// light: with only the field's parts uploaded, the image is the plain field's.
#[test]
fn exact_direct_light_streams_its_direct_parts_from_snapshot_one() {
    let Some(gpu) = gpu() else { return };
    let (first, last) = bundled_first_and_last("mirrors.obj", 129, 3, 0.1);
    let mut exact = last.clone();
    exact.use_exact_direct(&first, 64).expect("exact direct light");
    let complete = FieldRenderer::new(&gpu, &exact).expect("upload");
    let plain = FieldRenderer::new(&gpu, &last).expect("upload");
    let geometry = Arc::new(geometry(&last));
    let catalog = PartCatalog::new(&geometry);
    let emitters = vlf_core::direct::Emitters::new(&geometry.scene, 64).unwrap();
    let capacity = catalog.total_values() + geometry.atlas.texels;
    let [a, b, c] = views();

    // The field's parts alone: the field's direct light.
    let renderer = FieldRenderer::streaming_with(&gpu, &geometry, capacity, None, Some(&emitters)).expect("pool");
    let direct = renderer.direct_parts().expect("direct parts");
    assert_eq!(direct.chunks as usize, catalog.chunks());
    let mut base = 0;
    for p in 0..catalog.len() as u32 {
        renderer.upload(&gpu, p, base, last.part_values(&catalog, p)).unwrap();
        base += catalog.values(p);
    }
    let image = vlf_viewer::render(&gpu, &renderer, &c, 1, SpecularMode::Rays).unwrap();
    let expected = vlf_viewer::render(&gpu, &plain, &c, 1, SpecularMode::Rays).unwrap();
    assert_eq!(differing(&image, &expected), 0, "without direct parts: the plain field");
    // A direct part of the wrong size is refused.
    assert!(renderer.upload(&gpu, direct.of_chunk(0), base, &[[0.0; 3]]).is_err());

    // Streamed: the direct parts come after their chunks, and every view is the exact one.
    let renderer = FieldRenderer::streaming_with(&gpu, &geometry, capacity, None, Some(&emitters)).expect("pool");
    let asked = Arc::new(Mutex::new(Vec::new()));
    let field_parts = Recording {
        inner: FieldParts::new(Arc::new(last)),
        asked: asked.clone(),
        calls: 0,
        fail_every: 0,
    };
    let source = DirectSource::new(
        Box::new(field_parts),
        Box::new(FieldParts::new(Arc::new(first))),
        geometry.clone(),
    );
    let config = StreamConfig {
        direct: renderer.direct_parts(),
        ..config(capacity)
    };
    let streamer = Streamer::start(geometry.clone(), Box::new(source), config);
    for (k, camera) in [a, b, c].into_iter().enumerate() {
        let image = draw(&gpu, &renderer, &streamer, &camera);
        let expected = vlf_viewer::render(&gpu, &complete, &camera, 1, SpecularMode::Rays).unwrap();
        let off = differing(&image, &expected);
        eprintln!(
            "{off} of {} pixels differ from the complete exact field's",
            image.pixels.len()
        );
        assert!(off * 200 <= image.pixels.len(), "{off} pixels differ");
        let unexact = vlf_viewer::render(&gpu, &plain, &camera, 1, SpecularMode::Rays).unwrap();
        let changed = differing(&image, &unexact);
        eprintln!("{changed} pixels differ from the plain field's");
        // The first view sees the wall mirror alone (ρd = 0, reflections from the rays: nothing
        // exact about it); the others see diffuse walls.
        assert!(
            k == 0 || changed * 4 > image.pixels.len(),
            "exact direct light is drawn: {changed} pixels changed"
        );
    }
    // The field's source was never asked for a direct part.
    assert!(asked.lock().unwrap().iter().all(|&p| (p as usize) < catalog.len()));
    let stats = streamer.stats();
    assert!(stats.resident > catalog.chunks() && stats.missing == 0, "{stats:?}");
}

/// A part that finds no room in the cache does not end the view's planning: the smaller parts
/// after it that still fit are fetched (no GPU needed: the streamer's own bookkeeping).
#[test]
fn a_part_without_room_leaves_room_for_smaller_ones_after_it() {
    let field = Arc::new(field());
    let catalog = PartCatalog::new(&field);
    let camera = views()[2];
    let need = catalog.needed(&field.view_needs(&camera, 1, SpecularMode::Rays));
    let sizes: Vec<usize> = need.iter().map(|&p| catalog.values(p)).collect();
    // A part with a smaller one after it: room for every part before it and that smaller one.
    let (large, smallest) = (0..sizes.len())
        .filter_map(|k| {
            let m = sizes[k + 1..].iter().copied().min()?;
            (m < sizes[k]).then_some((k, m))
        })
        .max_by_key(|&(k, _)| sizes[k])
        .expect("a part with a smaller one after it");
    let capacity = sizes[..large].iter().sum::<usize>() + smallest;
    let streamer = Streamer::start(
        field.clone(),
        Box::new(FieldParts::new(field.clone())),
        config(capacity),
    );
    streamer.look(camera, MirrorMode::Rays);
    assert!(streamer.wait_idle(Duration::from_secs(120)), "{:?}", streamer.stats());
    let stats = streamer.stats();
    println!(
        "{} parts needed; part {large} of {} values finds no room in {capacity}; {} fetched",
        need.len(),
        sizes[large],
        stats.fetched
    );
    assert!(stats.cache_full && stats.missing > 0, "{stats:?}");
    assert!(
        stats.fetched as usize > large,
        "planning stopped at the part without room: {stats:?}"
    );
    assert_eq!(stats.short_views, 1, "{stats:?}");
}
