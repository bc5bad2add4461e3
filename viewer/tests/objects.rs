//! Dynamic objects on the GPU against the CPU reference (`vlf_core::dynamic`), on the bundled
//! scenes with cubes in them: the gather at points of a cube and around it (mirrors read
//! either way, objects blocking the gather), and whole views with objects, their shadows and
//! their images in mirrors. Lavapipe in CI.

mod common;

use common::{bundled_field, bundled_field_exact, gpu};
use glam::DVec3;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::{DynamicObject, PlacedObject, Pose};
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::render::Bvh;
use vlf_core::scene::Material;
use vlf_viewer::{FieldRenderer, GpuGather};

/// A grey cube of half-size `h` (scene units) around `c`.
fn cube(c: DVec3, h: f64) -> DynamicObject {
    let grey = Material::grey("grey", 0.6);
    DynamicObject::cube("cube", c, h, 1, grey)
}

/// Two cubes in a bundled scene: one on the floor, one in the air.
fn two_cubes(field: &LightField) -> Vec<PlacedObject> {
    let n = field.scene.normalisation;
    [
        (DVec3::new(400.0, 51.0, 150.0), 50.0),
        (DVec3::new(170.0, 380.0, 260.0), 40.0),
    ]
    .map(|(c, h)| cube(c, h).place(&Pose::IDENTITY, &n).unwrap())
    .to_vec()
}

/// Points just off the cube's faces (normals out) and points around it, in the VLF frame.
fn points(field: &LightField, c: DVec3, h: f64) -> Vec<(DVec3, DVec3)> {
    let n = field.scene.normalisation;
    let mut out = Vec::new();
    for (k, normal) in [DVec3::X, -DVec3::X, DVec3::Y, DVec3::Z, -DVec3::Z]
        .into_iter()
        .enumerate()
    {
        let (u, v) = normal.any_orthonormal_pair();
        for j in 0..4 {
            let s = (j as f64 - 1.37) * 0.31 + 0.07 * k as f64;
            out.push((
                n.to_vlf(c + normal * (h * 1.001) + (u * s + v * (0.5 - s)) * h * 0.8),
                normal,
            ));
        }
    }
    for j in 0..12 {
        let a = 0.5 + j as f64;
        let at = c + DVec3::new(a.cos(), 0.3 * (j % 3) as f64 - 0.4, a.sin()) * (2.5 * h);
        out.push((n.to_vlf(at), DVec3::new(a.sin(), 0.8, -a.cos()).normalize()));
    }
    out
}

fn compare(scene: &str, c: DVec3, h: f64, modes: &[SpecularMode], gather_shadows: bool, exact: bool) {
    let Some(gpu) = gpu() else { return };
    let field = match exact {
        true => bundled_field_exact(scene, 129, 3, 64),
        false => bundled_field(scene, 129, 3),
    };
    let bvh = Bvh::build(&field.scene);
    let placed: Vec<PlacedObject> = vec![cube(c, h).place(&Pose::IDENTITY, &field.scene.normalisation).unwrap()];
    let points = points(&field, c, h);
    for &mode in modes {
        let cpu = Gatherer::with_directions(&field, &bvh, &placed, mode, 129)
            .unwrap()
            .with_gather_shadows(gather_shadows);
        let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
        let want: Vec<[f64; 3]> = points.iter().map(|&(p, n)| cpu.incident(p, n)).collect();
        let got = GpuGather::new(&gpu, &renderer, mode.into())
            .unwrap()
            .incident(&gpu, &points)
            .unwrap();
        let scale = want.iter().flatten().copied().fold(0.0, f64::max);
        assert!(scale > 0.0);
        let mut worst = 0.0f64;
        let mut total = 0.0;
        for (k, (g, w)) in got.iter().zip(&want).enumerate() {
            for c in 0..3 {
                let e = (g[c] - w[c]).abs() / scale;
                worst = worst.max(e);
                total += e;
                assert!(e < 1e-3, "{scene} {mode:?} point {k}: GPU {g:?}, CPU {w:?}");
            }
        }
        let mean = total / (3 * got.len()) as f64;
        println!(
            "{scene} {mode:?}, gather shadows {gather_shadows}, exact {exact}: GPU vs CPU gather, mean {mean:.2e}, worst {worst:.2e} of the brightest point"
        );
        assert!(mean < 1e-4, "{mean}");
    }
}

/// The gather, blind to the cube's shadow and seeing it (`with_gather_shadows`: the GPU's
/// shadows per texel against the CPU's `texel_shadows`).
#[test]
fn the_gpu_gathers_what_the_cpu_gathers() {
    for gather_shadows in [false, true] {
        compare(
            "cornell.obj",
            DVec3::new(420.0, 60.0, 120.0),
            50.0,
            &[SpecularMode::Rays],
            gather_shadows,
            false,
        );
    }
}

/// With exact direct light the gather takes the emitters' light by shadow rays, which the
/// objects stop too, and the rest from the maps less the emitters' own emission.
#[test]
fn the_gpu_gathers_exact_direct_light_as_the_cpu_does() {
    compare(
        "cornell.obj",
        DVec3::new(420.0, 60.0, 120.0),
        50.0,
        &[SpecularMode::Rays],
        true,
        true,
    );
}

#[test]
fn the_gpu_gathers_mirrors_as_the_cpu_does() {
    compare(
        "mirrors.obj",
        DVec3::new(300.0, 250.0, 300.0),
        60.0,
        &[SpecularMode::Trace { depth: 3 }, SpecularMode::Rays],
        true,
        false,
    );
}

/// Without objects nothing blocks: a point inside where the cube would be gathers light.
#[test]
fn objects_block_the_gpu_gather() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field("cornell.obj", 33, 2);
    let c = DVec3::new(420.0, 60.0, 120.0);
    let placed = vec![
        cube(c, 50.0)
            .place(&Pose::IDENTITY, &field.scene.normalisation)
            .unwrap(),
    ];
    let inside = [(field.scene.normalisation.to_vlf(c), DVec3::Y)];
    let bvh = Bvh::build(&field.scene);
    let gather = |objects: &[PlacedObject]| {
        let cpu = Gatherer::new(&field, &bvh, objects, SpecularMode::Rays).unwrap();
        let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
        GpuGather::new(&gpu, &renderer, SpecularMode::Rays.into())
            .unwrap()
            .incident(&gpu, &inside)
            .unwrap()[0]
    };
    assert_eq!(
        gather(&placed),
        [0.0; 3],
        "inside the cube, the cube blocks every direction"
    );
    assert!(gather(&[])[1] > 0.0);
}

/// Pixels whose channels differ by more than `rel` of the larger value (and 10⁻⁶ absolute).
fn differing(a: &vlf_core::render::Image, b: &vlf_core::render::Image, rel: f32) -> usize {
    a.pixels
        .iter()
        .zip(&b.pixels)
        .filter(|(p, q)| (0..3).any(|c| (p[c] - q[c]).abs() > rel * p[c].abs().max(q[c].abs()) + 1e-6))
        .count()
}

/// A view with two cubes (one on the floor, one in the air) drawn by `render --gpu` and by the
/// CPU's `render_with_objects`: the same pixels but for a few at polygon edges, in the cubes,
/// their shadows and the mirrors; and the cubes change the view (their shadows darken it).
fn view_matches(scene: &str, modes: &[SpecularMode], exact: bool) {
    let Some(gpu) = gpu() else { return };
    let field = match exact {
        true => bundled_field_exact(scene, 33, 3, 64),
        false => bundled_field(scene, 33, 3),
    };
    let bvh = Bvh::build(&field.scene);
    let placed = two_cubes(&field);
    let camera = vlf_core::render::Camera::new(
        DVec3::new(278.0, 273.0, -800.0),
        DVec3::new(278.0, 273.0, 0.0),
        DVec3::Y,
        39.0,
        32,
        32,
    )
    .unwrap();
    for &mode in modes {
        let cpu = Gatherer::with_directions(&field, &bvh, &placed, mode, 33)
            .unwrap()
            .with_shadow_samples(32);
        let want = vlf_core::dynamic::view::render_with_objects(&cpu, &bvh, &camera, 1);
        let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
        let got = vlf_viewer::render(&gpu, &renderer, &camera, 1, mode).unwrap();
        let plain = field.render(&camera, 1, mode);
        let pixels = want.pixels.len();
        let changed = differing(&want, &plain, 1e-3);
        let off = differing(&want, &got, 1e-2);
        let way_off = differing(&want, &got, 0.5);
        let (m, g) = (want.mean(), got.mean());
        println!(
            "{scene} {mode:?}, exact {exact}: the cubes change {changed} of {pixels} pixels; GPU vs CPU: {off} \
             differ by 1 %, {way_off} by half; means {m:?} vs {g:?}"
        );
        assert!(changed > pixels / 10, "{changed}");
        assert!(off * 20 <= pixels, "{off} of {pixels} pixels differ by more than 1 %");
        assert!(
            way_off * 100 <= pixels,
            "{way_off} of {pixels} pixels differ by more than half"
        );
        for c in 0..3 {
            assert!(
                (m[c] - g[c]).abs() <= 5e-3 * m[c].abs(),
                "image means differ: CPU {m:?}, GPU {g:?}"
            );
        }
    }
}

#[test]
fn the_gpu_draws_objects_and_their_shadows_as_the_cpu_does() {
    view_matches("cornell.obj", &[SpecularMode::Rays], false);
}

#[test]
fn the_gpu_draws_objects_in_mirrors_as_the_cpu_does() {
    view_matches(
        "mirrors.obj",
        &[SpecularMode::Trace { depth: 4 }, SpecularMode::Rays],
        false,
    );
}

/// Exact direct light among objects: their sharp shadows by shadow rays that see them, the
/// cells' shadows without the emitters' light, the objects lit by shadow rays too; in mirrors
/// traced and read from the rays (whose light keeps the field's direct part and its shadow).
#[test]
fn the_gpu_draws_objects_with_exact_direct_light_as_the_cpu_does() {
    view_matches("cornell.obj", &[SpecularMode::Rays], true);
    view_matches(
        "mirrors.obj",
        &[SpecularMode::Trace { depth: 4 }, SpecularMode::Rays],
        true,
    );
}

/// Every `step`-th texel of every static surface of a complete renderer's pool (parts in
/// catalog order, `FieldRenderer::with_objects`): the surface, the texel's place in the pool
/// and its centre on the surface's plane (VLF frame).
fn pool_texels(field: &LightField, step: usize) -> Vec<(usize, usize, DVec3)> {
    let catalog = vlf_core::parts::PartCatalog::new(field);
    let mut bases = vec![0usize; catalog.len()];
    for i in 1..catalog.len() {
        bases[i] = bases[i - 1] + catalog.values(i as u32 - 1);
    }
    let mut out = Vec::new();
    for i in 0..field.scene.surfaces.len() {
        let grid = field.atlas.grid(i);
        let part = catalog.chunk_of_surface(i);
        let first = bases[part as usize] + grid.first - catalog.range(part).start;
        for t in (0..(grid.width * grid.height) as usize).step_by(step) {
            let (x, y) = (
                (t % grid.width as usize) as f64 + 0.5,
                (t / grid.width as usize) as f64 + 0.5,
            );
            out.push((
                i,
                first + t,
                grid.origin + (grid.axis_u * x + grid.axis_v * y) * grid.texel,
            ));
        }
    }
    out
}

/// With exact direct light each texel holds two shadows: the gather's (it reads the maps, so
/// it loses direct light too) and the camera's, which leaves direct light to the shadow rays:
/// `Gatherer::shadow_loss_seen` at the texel centres. Emitter points other than exact direct
/// light's are refused.
#[test]
fn shadows_per_texel_with_exact_direct_light_leave_it_to_the_shadow_rays() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field_exact("cornell.obj", 33, 3, 64);
    let bvh = Bvh::build(&field.scene);
    let placed = two_cubes(&field);
    let cpu = Gatherer::with_directions(&field, &bvh, &placed, SpecularMode::Rays, 33)
        .unwrap()
        .with_gather_shadows(true);
    let mut renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
    renderer.shadows_per_texel(&gpu, &field).unwrap();
    renderer.refresh_shadows(&gpu, vlf_viewer::MirrorMode::Rays).unwrap();
    let seen = renderer
        .texel_shadows_seen(&gpu)
        .unwrap()
        .expect("the camera's shadows");
    let gathered = renderer.texel_shadows(&gpu).unwrap();
    let (mut worst, mut scale, mut less) = (0.0f64, 0.0f64, 0);
    for (i, at, p) in pool_texels(&field, 5) {
        let (normal, rho) = (field.scene.surfaces[i].normal, field.scene.material(i).diffuse);
        let want = cpu.shadow_loss_seen(p, normal, rho).unwrap_or([0.0; 3]);
        let (have, full) = (seen[at], gathered[at]);
        less += (full[0] > have[0] * 1.05 + 1e-6) as usize;
        for c in 0..3 {
            scale = scale.max(want[c].abs());
            worst = worst.max((have[c] as f64 - want[c]).abs());
        }
    }
    println!("camera's shadows per texel against the CPU: worst {worst:.2e} of {scale:.2e}; {less} texels lose less");
    assert!(scale > 0.0 && worst < 1e-3 * scale, "worst {worst} of {scale}");
    assert!(less > 0, "the camera's shadows leave the direct part out somewhere");
    // Emitter points other than exact direct light's are refused.
    let other = Gatherer::with_directions(&field, &bvh, &placed, SpecularMode::Rays, 33)
        .unwrap()
        .with_direct_samples(16)
        .unwrap();
    let e = FieldRenderer::with_objects(&gpu, &field, &other)
        .err()
        .expect("refused")
        .to_string();
    assert!(e.contains("emitter points"), "{e}");
}

/// Shadows at 64 points of the floor around two cubes (one on it, one in the air), GPU against
/// CPU: the same loss, direct part (the lamp's points) and indirect part (the cones' cells).
#[test]
fn the_gpu_casts_the_shadows_the_cpu_casts() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field("cornell.obj", 33, 3);
    let bvh = Bvh::build(&field.scene);
    let placed = two_cubes(&field);
    let cpu = Gatherer::with_directions(&field, &bvh, &placed, SpecularMode::Rays, 33)
        .unwrap()
        .with_shadow_samples(32);
    let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
    let gather = GpuGather::new(&gpu, &renderer, SpecularMode::Rays.into()).unwrap();
    let mut points = Vec::new();
    for i in 0..8 {
        for j in 0..8 {
            let (x, z) = (30.0 + 70.0 * i as f64, 20.0 + 70.0 * j as f64);
            points.push((
                field.scene.normalisation.to_vlf(DVec3::new(x, 0.0, z)),
                DVec3::Y,
                [0.7; 3],
            ));
        }
    }
    let want: Vec<Option<[f64; 3]>> = points
        .iter()
        .map(|&(p, normal, rho)| cpu.shadow_loss(p, normal, rho))
        .collect();
    let got = gather.shadow_loss(&gpu, &points).unwrap();
    let scale = want.iter().flatten().flatten().copied().fold(0.0, f64::max);
    for (k, (g, w)) in got.iter().zip(&want).enumerate() {
        let (g, w) = (g.unwrap_or([0.0; 3]), w.unwrap_or([0.0; 3]));
        for c in 0..3 {
            assert!((g[c] - w[c]).abs() < 1e-3 * scale, "point {k}: GPU {g:?}, CPU {w:?}");
        }
    }
}

/// While the surfaces an object gathers from stream in, its gather is the mean over those
/// resident, not a mean with the missing ones black: in a field whose radiance is L everywhere,
/// a cube gathers L with only some of the field's parts resident, as with all of them.
#[test]
fn a_gather_over_missing_parts_averages_what_is_resident() {
    let Some(gpu) = gpu() else { return };
    // The Cornell box closed by a front wall (at z = 0, facing in), so that every gather ray
    // meets a surface.
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
    let (mut scene, _) = vlf_core::scene::load_obj(&path, &Default::default()).unwrap();
    let n = scene.normalisation;
    let corners = [(0.0, 0.0), (555.0, 0.0), (555.0, 555.0), (0.0, 555.0)];
    let front = corners.map(|(x, y)| n.to_vlf(DVec3::new(x, y, 0.0))).to_vec();
    let origin = vlf_core::scene::FaceOrigin { line: 0, face: 0 };
    scene
        .surfaces
        .push(vlf_core::scene::Surface::from_vertices(front, 0, origin).unwrap());
    let options = vlf_core::propagate::Options {
        directions: 9,
        grid: vlf_core::psf::GridSize::new(32, 8).unwrap(),
        stop: vlf_core::propagate::Stop::Iterations(1),
        texel_cells: 0.1,
        ..Default::default()
    };
    let mut field = vlf_core::propagate::Propagation::new(scene, options)
        .unwrap()
        .into_field();
    let l = 0.37f32;
    field.radiance.iter_mut().for_each(|v| *v = [l; 3]);
    let catalog = vlf_core::parts::PartCatalog::new(&field);
    assert!(catalog.chunks() >= 3, "{} chunks", catalog.chunks());
    let bvh = Bvh::build(&field.scene);
    let (c, h) = (DVec3::new(200.0, 420.0, 200.0), 40.0);
    let placed = vec![cube(c, h).place(&Pose::IDENTITY, &field.scene.normalisation).unwrap()];
    placed[0].check_clear(&field.scene, &bvh).unwrap();
    let gatherer = Gatherer::with_directions(&field, &bvh, &placed, SpecularMode::Rays, 129).unwrap();
    let points: Vec<(DVec3, DVec3)> = points(&field, c, h).into_iter().take(20).collect();
    let renderer = FieldRenderer::streaming_with_objects(&gpu, &field, catalog.total_values(), &gatherer).unwrap();
    // Every other part resident.
    let mut base = 0;
    for i in (0..catalog.len() as u32).step_by(2) {
        renderer.upload(&gpu, i, base, field.part_values(&catalog, i)).unwrap();
        base += catalog.values(i);
    }
    let got = GpuGather::new(&gpu, &renderer, SpecularMode::Rays.into())
        .unwrap()
        .incident(&gpu, &points)
        .unwrap();
    for (k, g) in got.iter().enumerate() {
        for c in g {
            assert!((c - l as f64).abs() < 1e-5, "point {k}: {g:?}, want {l}");
        }
    }
}

/// A streamed view with objects, drawn after the streamer fetched what the camera sees and
/// what the objects read (`Streamer::look_around`), is the complete field's view with them;
/// the camera's parts alone are not enough for it (the objects read surfaces the camera does
/// not see). Moving the objects on the GPU (`move_objects`) draws what a renderer built with
/// them at their new poses draws.
#[test]
fn a_streamed_view_fetches_what_its_objects_read_and_follows_their_moves() {
    use std::time::Duration;
    use vlf_core::render::Camera;
    use vlf_viewer::MirrorMode;
    use vlf_viewer::stream::{FieldParts, StreamConfig, Streamer};
    let Some(gpu) = gpu() else { return };
    let field = std::sync::Arc::new(common::bundled_field_with_texel("cornell.obj", 33, 2, 0.1));
    let catalog = vlf_core::parts::PartCatalog::new(&field);
    let bvh = Bvh::build(&field.scene);
    let n = field.scene.normalisation;
    let at = |c: DVec3| {
        let placed = cube(c, 40.0).place(&Pose::IDENTITY, &n).unwrap();
        placed.check_clear(&field.scene, &bvh).unwrap();
        vec![placed]
    };
    let (here, there) = (at(DVec3::new(200.0, 420.0, 200.0)), at(DVec3::new(240.0, 400.0, 150.0)));
    // Looking down at the cube and the floor around it: the walls it gathers from are out of
    // view.
    let camera = Camera::new(
        DVec3::new(200.0, 540.0, 200.0),
        DVec3::new(200.0, 0.0, 200.0),
        DVec3::Z,
        50.0,
        64,
        48,
    )
    .unwrap();
    let mode = SpecularMode::Rays;
    let gatherer = |placed: &[PlacedObject]| {
        let g = Gatherer::with_directions(&field, &bvh, placed, mode, 129).unwrap();
        // A gatherer borrows the placed objects: lay the renderer out now.
        FieldRenderer::with_objects(&gpu, &field, &g).unwrap()
    };
    let complete = gatherer(&here);
    let want = vlf_viewer::render(&gpu, &complete, &camera, 1, mode).unwrap();
    let view_only: std::collections::BTreeSet<u32> = catalog
        .needed(&field.view_needs(&camera, 1, mode))
        .into_iter()
        .collect();
    assert!(view_only.len() < catalog.len(), "the view alone needs every part");
    let streamed = |spheres: Vec<(DVec3, f64)>| {
        let g = Gatherer::with_directions(&field, &bvh, &here, mode, 129).unwrap();
        let renderer = FieldRenderer::streaming_with_objects(&gpu, &field, catalog.total_values(), &g).unwrap();
        let config = StreamConfig {
            capacity: catalog.total_values(),
            batch_values: 1 << 16,
            batch_parts: 16,
            backoff: Duration::from_millis(1),
            direct: None,
        };
        let streamer = Streamer::start(field.clone(), Box::new(FieldParts::new(field.clone())), config);
        streamer.look_around(camera, MirrorMode::Rays, spheres);
        assert!(streamer.wait_idle(Duration::from_secs(120)), "{:?}", streamer.stats());
        streamer.apply(&gpu, &renderer).unwrap();
        let image = vlf_viewer::render(&gpu, &renderer, &camera, 1, mode).unwrap();
        (image, streamer.stats().fetched as usize, renderer)
    };
    let (alone, fetched_alone, _) = streamed(Vec::new());
    assert_eq!(fetched_alone, view_only.len());
    let (around, fetched_around, renderer) = streamed(vec![(here[0].center, here[0].radius)]);
    assert!(fetched_around > fetched_alone, "{fetched_around} parts");
    let off = |a: &vlf_core::render::Image| differing(a, &want, 0.0);
    println!(
        "of {} pixels, {} differ from the complete view with the camera's parts alone, {} with the objects' too",
        want.pixels.len(),
        off(&alone),
        off(&around)
    );
    assert!(off(&alone) > 0, "the camera's parts alone drew the objects completely");
    assert_eq!(off(&around), 0);
    // Moved to `there` on the GPU: as a renderer built with the cube there draws it (all parts
    // resident for the comparison).
    let mut base = 0;
    for i in 0..catalog.len() as u32 {
        renderer.upload(&gpu, i, base, field.part_values(&catalog, i)).unwrap();
        base += catalog.values(i);
    }
    renderer.move_objects(&gpu, &there).unwrap();
    let moved = vlf_viewer::render(&gpu, &renderer, &camera, 1, mode).unwrap();
    let built = vlf_viewer::render(&gpu, &gatherer(&there), &camera, 1, mode).unwrap();
    assert_eq!(differing(&moved, &built, 0.0), 0);
    assert!(differing(&moved, &want, 0.0) > 0, "the cube did not move");
    // Other objects than the renderer's are refused.
    let two = [here.clone(), there.clone()].concat();
    assert!(renderer.move_objects(&gpu, &two).is_err());
}

/// The objects' shadows per texel (`shadows_per_texel`, what `vlf view` draws) are the CPU's
/// `shadow_loss` at every texel's centre, the cube's own light given back (computed on the GPU
/// from its gather, as on the CPU), recomputed when the objects move; a view reading them is
/// the view shading every fragment but for the shadow's sharpness.
#[test]
fn shadows_per_texel_are_the_cpu_shadow_at_texel_centres_and_follow_moves() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field("cornell.obj", 129, 3);
    let bvh = Bvh::build(&field.scene);
    let n = field.scene.normalisation;
    let at = |c: DVec3| vec![cube(c, 50.0).place(&Pose::IDENTITY, &n).unwrap()];
    let (here, there) = (at(DVec3::new(400.0, 51.0, 150.0)), at(DVec3::new(170.0, 380.0, 260.0)));
    let camera = vlf_core::render::Camera::new(
        DVec3::new(278.0, 273.0, -800.0),
        DVec3::new(278.0, 273.0, 0.0),
        DVec3::Y,
        39.0,
        64,
        64,
    )
    .unwrap();
    // The gather seeing the shadows, and the shadows giving back the cube's light: the GPU's
    // three passes against the CPU's `prepared`.
    fn full<'a>(field: &'a LightField, bvh: &'a Bvh, placed: &'a [PlacedObject]) -> Gatherer<'a> {
        Gatherer::with_directions(field, bvh, placed, SpecularMode::Rays, 129)
            .unwrap()
            .with_gather_shadows(true)
            .with_bounce_light(true)
    }
    let g = full(&field, &bvh, &here);
    let per_fragment = FieldRenderer::with_objects(&gpu, &field, &g).unwrap();
    let mut renderer = FieldRenderer::with_objects(&gpu, &field, &g).unwrap();
    renderer.shadows_per_texel(&gpu, &field).unwrap();
    let texels = pool_texels(&field, 7);
    let check = |placed: &[PlacedObject]| {
        let cpu = full(&field, &bvh, placed);
        let got = renderer.texel_shadows(&gpu).unwrap();
        let (mut worst, mut scale, mut shadowed) = (0.0f64, 0.0f64, 0);
        let (mut total, mut count) = (0.0f64, 0usize);
        for &(i, at, p) in &texels {
            let (normal, rho) = (field.scene.surfaces[i].normal, field.scene.material(i).diffuse);
            let want = cpu.shadow_loss(p, normal, rho).unwrap_or([0.0; 3]);
            let have = got[at];
            shadowed += (want[0] != 0.0) as usize;
            for c in 0..3 {
                scale = scale.max(want[c].abs());
                worst = worst.max((have[c] as f64 - want[c]).abs());
                (total, count) = (total + (have[c] as f64 - want[c]).abs(), count + 1);
            }
        }
        let mean = total / count as f64;
        println!(
            "shadows per texel: {shadowed} texels shadowed; difference mean {mean:.2e}, worst {worst:.2e} of {scale:.2e}"
        );
        assert!(shadowed > 100, "{shadowed}");
        // The cube's light is gathered in f32 from the f32 shadows of the pass before, and
        // given back: 3·10⁻³ of the deepest shadow at worst.
        assert!(worst <= 3e-3 * scale, "{worst} of {scale}");
        assert!(mean <= 1e-4 * scale, "{mean} of {scale}");
    };
    let texel_view = vlf_viewer::render(&gpu, &renderer, &camera, 1, SpecularMode::Rays).unwrap();
    check(&here);
    let fragment_view = vlf_viewer::render(&gpu, &per_fragment, &camera, 1, SpecularMode::Rays).unwrap();
    let (a, b) = (texel_view.mean(), fragment_view.mean());
    println!("image means per texel {a:?}, per fragment {b:?}");
    for c in 0..3 {
        assert!((a[c] - b[c]).abs() <= 0.01 * b[c], "{a:?} vs {b:?}");
    }
    renderer.move_objects(&gpu, &there).unwrap();
    vlf_viewer::render(&gpu, &renderer, &camera, 1, SpecularMode::Rays).unwrap();
    check(&there);
}

/// A chrome cube (ρs 0.8, ρd 0.1) in the air of the Cornell box under exact direct light, seen
/// from above: its top face reflects the lamp. The reflected ray has no shadow ray to count the
/// lamp's light, so it keeps the emission (`Gatherer::arriving` on the CPU); the GPU once took
/// it off as it does for a gather ray and drew the lamp black in the mirror. Mirrors from the
/// rays, and traced (where the path goes on past the cube's mirror, as `render_with_objects`
/// recurses).
#[test]
fn a_mirror_object_reflects_the_lamp_as_the_cpu_does() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field_exact("cornell.obj", 33, 3, 64);
    let bvh = Bvh::build(&field.scene);
    let chrome = Material {
        name: "chrome".into(),
        diffuse: [0.1; 3],
        specular: [0.8; 3],
        emission: [0.0; 3],
        albedo_texture: None,
    };
    let n = field.scene.normalisation;
    let placed = vec![
        DynamicObject::cube("chrome cube", DVec3::new(278.0, 260.0, 200.0), 50.0, 1, chrome)
            .place(&Pose::IDENTITY, &n)
            .unwrap(),
    ];
    placed[0].check_clear(&field.scene, &bvh).unwrap();
    let camera = vlf_core::render::Camera::new(
        DVec3::new(278.0, 500.0, 160.0),
        DVec3::new(278.0, 310.0, 205.0),
        DVec3::Z,
        39.0,
        32,
        32,
    )
    .unwrap();
    // The lamp's radiance (17, 12, 4) times ρs: a pixel of the cube that shows it.
    let lamp_in_mirror = 0.5 * 0.8 * 17.0;
    for mode in [SpecularMode::Rays, SpecularMode::Trace { depth: 4 }] {
        let cpu = Gatherer::with_directions(&field, &bvh, &placed, mode, 33)
            .unwrap()
            .with_shadow_samples(16);
        let want = vlf_core::dynamic::view::render_with_objects(&cpu, &bvh, &camera, 1);
        let renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
        let got = vlf_viewer::render(&gpu, &renderer, &camera, 1, mode).unwrap();
        let lamp: Vec<usize> = (0..want.pixels.len())
            .filter(|&i| want.pixels[i][0] > lamp_in_mirror)
            .collect();
        let off = differing(&want, &got, 1e-2);
        let lamp_off = lamp
            .iter()
            .filter(|&&i| (0..3).any(|c| (want.pixels[i][c] - got.pixels[i][c]).abs() > 1e-2 * want.pixels[i][c]))
            .count();
        println!(
            "{mode:?}: {} pixels show the lamp in the cube, {lamp_off} of them differ by 1 %; {off} of {} pixels in all",
            lamp.len(),
            want.pixels.len()
        );
        assert!(lamp.len() >= 20, "the cube reflects the lamp in {} pixels", lamp.len());
        assert!(
            lamp_off * 20 <= lamp.len(),
            "{lamp_off} of {} lamp pixels differ",
            lamp.len()
        );
        assert!(off * 20 <= want.pixels.len(), "{off} pixels differ by more than 1 %");
    }
}

/// With objects in the view, a static mirror whose tiles of the rays are not resident (a
/// streaming view) is traced through the diffuse maps that are, as a view without objects
/// traces it (`shade`), not drawn black. The objects' pass without objects in it draws what the
/// plain pass draws: with only the diffuse maps resident, both images are the same.
#[test]
fn mirrors_missing_their_tiles_are_traced_among_objects_too() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field("mirrors.obj", 33, 3);
    let catalog = vlf_core::parts::PartCatalog::new(&field);
    let bvh = Bvh::build(&field.scene);
    let camera = common::readme_camera(32, 32);
    let mode = SpecularMode::Rays;
    let none: Vec<PlacedObject> = Vec::new();
    let gatherer = Gatherer::with_directions(&field, &bvh, &none, mode, 33).unwrap();
    let capacity = catalog.total_values();
    let among = FieldRenderer::streaming_with_objects(&gpu, &field, capacity, &gatherer).unwrap();
    let plain = FieldRenderer::streaming(&gpu, &field, capacity).unwrap();
    // The diffuse maps only (the chunks come first in the catalog).
    let mut base = 0;
    for i in 0..catalog.chunks() as u32 {
        for r in [&among, &plain] {
            r.upload(&gpu, i, base, field.part_values(&catalog, i)).unwrap();
        }
        base += catalog.values(i);
    }
    let a = vlf_viewer::render(&gpu, &among, &camera, 1, mode).unwrap();
    let b = vlf_viewer::render(&gpu, &plain, &camera, 1, mode).unwrap();
    let complete = field.render(&camera, 1, mode);
    let mirrored = differing(&b, &complete, 1e-2);
    let off = differing(&a, &b, 1e-3);
    println!(
        "diffuse maps only: {mirrored} pixels differ from the complete field's (mirrors traced); among objects {off} differ from them"
    );
    assert!(mirrored > 0 && mirrored * 2 < a.pixels.len(), "{mirrored}");
    assert_eq!(off, 0, "the objects' pass draws the mirrors the plain pass draws");
}

/// The objects' shadows on the GPU take each static material's ρd: a static scene with an
/// albedo texture is refused with objects in it (the CPU reads the texture per point), and
/// drawn without them.
#[test]
fn objects_in_a_textured_scene_are_refused_on_the_gpu() {
    let Some(gpu) = gpu() else { return };
    let mut field = bundled_field("cornell.obj", 9, 1);
    field.scene.textures.push(vlf_core::scene::Texture {
        name: "checks".into(),
        width: 2,
        height: 1,
        texels: vec![[0.2; 3], [0.9; 3]],
        wrap: [vlf_core::scene::Wrap::Repeat; 2],
    });
    let floor = field.scene.surfaces[0].material;
    field.scene.materials[floor].albedo_texture = Some(0);
    let bvh = Bvh::build(&field.scene);
    let placed = two_cubes(&field);
    let with = Gatherer::with_directions(&field, &bvh, &placed, SpecularMode::Rays, 9).unwrap();
    let e = FieldRenderer::with_objects(&gpu, &field, &with)
        .err()
        .expect("refused")
        .to_string();
    assert!(e.contains("albedo texture") && e.contains("drop --gpu"), "{e}");
    let none: Vec<PlacedObject> = Vec::new();
    let without = Gatherer::with_directions(&field, &bvh, &none, SpecularMode::Rays, 9).unwrap();
    assert!(FieldRenderer::with_objects(&gpu, &field, &without).is_ok());
}

/// A gather made before the objects moved (`move_objects`) reads their shadows per texel where
/// they are now: each run brings them up to date first, as a draw does.
#[test]
fn a_gather_follows_the_objects_moves() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field("cornell.obj", 33, 3);
    let bvh = Bvh::build(&field.scene);
    let n = field.scene.normalisation;
    let (c, h) = (DVec3::new(420.0, 60.0, 120.0), 50.0);
    let at = |c: DVec3| vec![cube(c, h).place(&Pose::IDENTITY, &n).unwrap()];
    let (here, there) = (at(DVec3::new(150.0, 380.0, 300.0)), at(c));
    fn gatherer<'a>(field: &'a LightField, bvh: &'a Bvh, placed: &'a [PlacedObject]) -> Gatherer<'a> {
        Gatherer::with_directions(field, bvh, placed, SpecularMode::Rays, 33)
            .unwrap()
            .with_gather_shadows(true)
    }
    let renderer = FieldRenderer::with_objects(&gpu, &field, &gatherer(&field, &bvh, &here)).unwrap();
    let gather = GpuGather::new(&gpu, &renderer, SpecularMode::Rays.into()).unwrap();
    let points = points(&field, c, h);
    // Gathered once where the cube was, then moved under the gather.
    gather.incident(&gpu, &points).unwrap();
    renderer.move_objects(&gpu, &there).unwrap();
    let got = gather.incident(&gpu, &points).unwrap();
    let cpu = gatherer(&field, &bvh, &there);
    let want: Vec<[f64; 3]> = points.iter().map(|&(p, n)| cpu.incident(p, n)).collect();
    let scale = want.iter().flatten().copied().fold(0.0, f64::max);
    let worst = (got.iter().zip(&want))
        .flat_map(|(g, w)| (0..3).map(move |c| (g[c] - w[c]).abs() / scale))
        .fold(0.0, f64::max);
    println!("a gather after the cube moved: worst {worst:.2e} of the brightest point");
    assert!(worst < 1e-3, "{worst}");
}

/// The shadows per texel are computed again for what they read (a chunk's maps; a mirror
/// tile when mirrors are read from the rays) and not for what they do not (exact direct
/// light's direct parts, tiles while mirrors are traced): each pass costs texels × objects × K
/// rays.
#[test]
fn shadows_per_texel_are_computed_again_only_for_parts_they_read() {
    let Some(gpu) = gpu() else { return };
    let field = bundled_field_exact("mirrors.obj", 33, 2, 64);
    let catalog = vlf_core::parts::PartCatalog::new(&field);
    let bvh = Bvh::build(&field.scene);
    let placed = two_cubes(&field);
    let cpu = Gatherer::with_directions(&field, &bvh, &placed, SpecularMode::Rays, 33)
        .unwrap()
        .with_gpu_lighting(true, true);
    let mut renderer = FieldRenderer::with_objects(&gpu, &field, &cpu).unwrap();
    renderer.shadows_per_texel(&gpu, &field).unwrap();
    let exact = field.exact_direct.as_ref().unwrap();
    let direct = renderer.direct_parts().expect("exact direct light");
    // Where `with_objects` put the parts: the catalog's in order, then the direct parts.
    let base_of = |part: u32| (0..part).map(|p| renderer.part_len(p).unwrap()).sum::<usize>();
    let tile = (catalog.chunks() as u32..catalog.len() as u32)
        .find(|&p| catalog.values(p) > 0)
        .expect("a mirror tile");
    let traced = vlf_viewer::MirrorMode::Trace { depth: 2 };
    let rays = vlf_viewer::MirrorMode::Rays;
    let passes_after = |mode, upload: Option<u32>| {
        if let Some(p) = upload {
            let values = match direct.chunk(p) {
                Some(c) => &exact.direct()[catalog.range(c)],
                None => field.part_values(&catalog, p),
            };
            renderer.upload(&gpu, p, base_of(p), values).unwrap();
        }
        renderer.refresh_shadows(&gpu, mode).unwrap();
        renderer.shadow_passes()
    };
    assert_eq!(passes_after(traced, None), 1);
    assert_eq!(passes_after(traced, None), 1, "nothing changed");
    assert_eq!(passes_after(traced, Some(direct.of_chunk(0))), 1, "a direct part");
    assert_eq!(passes_after(traced, Some(tile)), 1, "a tile, mirrors traced");
    assert_eq!(passes_after(rays, None), 2, "another mirror mode");
    assert_eq!(passes_after(rays, Some(tile)), 3, "a tile, mirrors from the rays");
    assert_eq!(passes_after(rays, Some(0)), 4, "a chunk");
}
