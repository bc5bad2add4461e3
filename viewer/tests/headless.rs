//! The GPU renderer against the CPU renderer, on the bundled scenes.
//!
//! Both draw the same field with the same sample positions and box filter, so they differ only
//! where f32 rasterisation and f64 ray casting disagree: which polygon a sample on an edge
//! belongs to, and the last bits of the bilinear weights. The tolerance says so: at most 1 % of
//! the pixels (edge pixels) differ by more than 10⁻³ relative, at most 0.5 % by more than half,
//! and the image means agree within 5·10⁻⁴. Measured on lavapipe: 0 to 2 pixels of 12288 beyond
//! 10⁻³, means within 1.2·10⁻⁴.
//!
//! CI installs Mesa's lavapipe and sets `VLF_REQUIRE_GPU=1`; elsewhere a machine without any
//! adapter skips these tests with a message.

mod common;

use common::{bundled_field, bundled_field_exact, gpu, readme_camera};
use glam::DVec3;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::render::{Camera, Image};
use vlf_viewer::{FieldRenderer, Gpu, ViewerError};

fn field(scene: &str, iterations: u32) -> LightField {
    bundled_field(scene, 33, iterations)
}

/// Pixels whose channels differ by more than `rel` of the larger value (and 10⁻⁶ absolute).
fn differing(a: &Image, b: &Image, rel: f32) -> usize {
    a.pixels
        .iter()
        .zip(&b.pixels)
        .filter(|(p, q)| (0..3).any(|c| (p[c] - q[c]).abs() > rel * p[c].abs().max(q[c].abs()) + 1e-6))
        .count()
}

fn compare(gpu: &Gpu, field: &LightField, camera: &Camera, samples: u32, mode: SpecularMode) {
    let cpu = field.render(camera, samples, mode);
    let renderer = FieldRenderer::new(gpu, field).expect("upload");
    let gpu_image = vlf_viewer::render(gpu, &renderer, camera, samples, mode).expect("GPU render");
    assert_eq!((gpu_image.width, gpu_image.height), (camera.width, camera.height));
    let pixels = cpu.pixels.len();
    let lit = cpu.pixels.iter().filter(|p| p.iter().any(|&v| v > 0.0)).count();
    assert!(
        lit > pixels / 2,
        "the view sees the scene: {lit} of {pixels} pixels lit"
    );
    // Edge pixels: a sample on a polygon's edge may fall on either side.
    let off = differing(&cpu, &gpu_image, 1e-3);
    eprintln!("{off} of {pixels} pixels differ by more than 1e-3");
    assert!(off * 100 <= pixels, "{off} of {pixels} pixels differ by more than 10⁻³");
    let way_off = differing(&cpu, &gpu_image, 0.5);
    assert!(
        way_off * 200 <= pixels,
        "{way_off} of {pixels} pixels differ by more than half"
    );
    let (m, n) = (cpu.mean(), gpu_image.mean());
    for c in 0..3 {
        assert!(
            (m[c] - n[c]).abs() <= 5e-4 * m[c].abs(),
            "image means differ: CPU {m:?}, GPU {n:?}"
        );
    }
}

#[test]
fn cornell_box_matches_the_cpu_renderer() {
    let Some(gpu) = gpu() else { return };
    let field = field("cornell.obj", 4);
    compare(&gpu, &field, &readme_camera(128, 96), 1, SpecularMode::Rays);
    compare(
        &gpu,
        &field,
        &readme_camera(64, 48),
        3,
        SpecularMode::Trace { depth: 8 },
    );
}

#[test]
fn mirror_scene_matches_the_cpu_renderer_both_ways() {
    let Some(gpu) = gpu() else { return };
    let field = field("mirrors.obj", 3);
    assert!(field.specular.is_some(), "the scene has mirrors");
    let cam = readme_camera(128, 96);
    for depth in [0, 1, 8] {
        compare(&gpu, &field, &cam, 2, SpecularMode::Trace { depth });
    }
    compare(&gpu, &field, &cam, 2, SpecularMode::Rays);
    // From another side, where the floor mirror is seen at a grazing angle.
    let side = Camera::new(
        DVec3::new(500.0, 450.0, -300.0),
        DVec3::new(250.0, 50.0, 300.0),
        DVec3::Y,
        60.0,
        96,
        72,
    )
    .unwrap();
    compare(&gpu, &field, &side, 1, SpecularMode::Rays);
    // Reflections add light: the traced image is brighter than the one without them (+2.0 %
    // here), and so is the one from the rays (+0.8 %: 33 directions after 3 iterations see
    // less of the reflection, a bounce behind and blurred).
    let renderer = FieldRenderer::new(&gpu, &field).unwrap();
    let flat = vlf_viewer::render(&gpu, &renderer, &cam, 1, SpecularMode::Trace { depth: 0 }).unwrap();
    let traced = vlf_viewer::render(&gpu, &renderer, &cam, 1, SpecularMode::Trace { depth: 8 }).unwrap();
    let rays = vlf_viewer::render(&gpu, &renderer, &cam, 1, SpecularMode::Rays).unwrap();
    assert!(
        rays.mean()[0] > flat.mean()[0] * 1.004,
        "{:?} vs {:?}",
        rays.mean(),
        flat.mean()
    );
    assert!(
        traced.mean()[0] > flat.mean()[0] * 1.01,
        "{:?} vs {:?}",
        traced.mean(),
        flat.mean()
    );
}

/// A curved mirror: a ball of 2 208 triangles, about a quarter of a ray cell each at N = 32,
/// floating in the Cornell box. Most of its triangles are crossed
/// by no ray of a direction, so a look-up from the rays reads the rays that cross their
/// neighbours (`LightField::mirror_slot`), which the shader does from its lists of every ray's
/// crossings (`rays.rs`).
#[test]
fn a_curved_mirror_matches_the_cpu_renderer_from_the_rays() {
    let Some(gpu) = gpu() else { return };
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
    let (mut scene, _) = vlf_core::scene::load_obj(&path, &Default::default()).expect("bundled scene");
    scene.materials.push(vlf_core::scene::Material {
        name: "chrome".into(),
        diffuse: [0.0; 3],
        specular: [0.9; 3],
        emission: [0.0; 3],
        albedo_texture: None,
    });
    let chrome = scene.materials.len() - 1;
    // A latitude-longitude ball, wound to face out; in the VLF frame the box spans about
    // ±0.58, and this is (278, 322, 119) in the scene's units, radius 120: above the short
    // block, in front of the tall one.
    let (centre, r, stacks, slices) = (DVec3::new(0.0, 0.1, -0.33), 0.25, 24, 48);
    let at = |i: usize, j: usize| {
        let (theta, phi) = (
            std::f64::consts::PI * i as f64 / stacks as f64,
            std::f64::consts::TAU * j as f64 / slices as f64,
        );
        centre + r * DVec3::new(theta.sin() * phi.cos(), theta.cos(), theta.sin() * phi.sin())
    };
    for i in 0..stacks {
        for j in 0..slices {
            let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
            // A fan at each pole: the other triangle of the quad would have no area.
            let triangles = match i {
                0 => vec![vec![a, c, b]],
                i if i == stacks - 1 => vec![vec![a, d, c]],
                _ => vec![vec![a, d, c], vec![a, c, b]],
            };
            for t in triangles {
                let origin = vlf_core::scene::FaceOrigin { line: 0, face: 0 };
                scene
                    .surfaces
                    .extend(vlf_core::scene::Surface::from_vertices(t, chrome, origin));
            }
        }
    }
    let options = vlf_core::propagate::Options {
        directions: 33,
        grid: vlf_core::psf::GridSize::new(32, 8).unwrap(),
        stop: vlf_core::propagate::Stop::Iterations(3),
        ..Default::default()
    };
    let mut p = vlf_core::propagate::Propagation::new(scene, options).unwrap();
    p.run(|_| {});
    let field = p.into_field();
    let ball: Vec<_> = (field.scene.surfaces.iter()).filter(|s| s.material == chrome).collect();
    assert_eq!(ball.len(), 2 * stacks * slices - 2 * slices);
    assert!(
        (ball.iter()).all(|s| s.normal.dot(s.vertices[0] - centre) > 0.0),
        "the ball faces out"
    );
    // The view sees the ball whole.
    let camera = readme_camera(128, 96);
    let bvh = vlf_core::render::Bvh::build(&field.scene);
    let mut seen = 0;
    for y in 0..camera.height {
        for x in 0..camera.width {
            vlf_core::render::pixel_rays(&camera, &field.scene.normalisation, 1, x, y, |o, d| {
                let hit = bvh.intersect(&field.scene, o, d, 0.0, f64::INFINITY);
                seen += usize::from(hit.is_some_and(|h| field.scene.surfaces[h.surface].material == chrome));
            });
        }
    }
    assert!(seen > 800, "the view shows {seen} pixels of the ball");
    compare(&gpu, &field, &camera, 2, SpecularMode::Rays);
    // The shader's tables grow with the mirror slots, not with directions × mirror planes as
    // dense windows per plane did (five words each).
    let tables = vlf_viewer::rays::RayTables::new(&field, &vlf_core::parts::PartCatalog::new(&field));
    let (l, planes) = (field.specular.as_ref().unwrap().views.len(), ball.len());
    assert!(
        tables.words.len() < l * planes,
        "{} words for {l} directions and {planes} mirror planes",
        tables.words.len()
    );
}

/// Exact direct light (`vlf_core::direct`) on the GPU: the same quadrature points and shadow
/// rays as the CPU's, in f32. Measured on lavapipe: block error 6·10⁻⁵, 2 pixels of 16384 beyond
/// 1 % (on shadow edges, where a shadow ray grazes a box's edge).
#[test]
fn exact_direct_light_matches_the_cpu_renderer() {
    let Some(gpu) = gpu() else { return };
    for (scene, modes) in [
        ("cornell.obj", &[SpecularMode::Rays][..]),
        (
            "mirrors.obj",
            &[SpecularMode::Rays, SpecularMode::Trace { depth: 8 }][..],
        ),
    ] {
        let exact = bundled_field_exact(scene, 33, 3, 64);
        let mut plain = exact.clone();
        plain.exact_direct = None;
        let from_field = vlf_viewer::render(
            &gpu,
            &FieldRenderer::new(&gpu, &plain).unwrap(),
            &readme_camera(96, 72),
            1,
            modes[0],
        )
        .expect("GPU render");
        for &mode in modes {
            let cam = readme_camera(96, 72);
            let cpu = exact.render(&cam, 1, mode);
            let renderer = FieldRenderer::new(&gpu, &exact).expect("upload");
            let gpu_image = vlf_viewer::render(&gpu, &renderer, &cam, 1, mode).expect("GPU render");
            let c = vlf_core::render::compare::compare(&gpu_image, &cpu, 16, Default::default()).unwrap();
            eprintln!(
                "{scene} {mode:?}: block error {:.2e}, mean {:+.2e}",
                c.block_error, c.mean_error
            );
            assert!(
                c.block_error < 0.01 && c.mean_error.abs() < 1e-3,
                "{scene} {mode:?}: {c:?}"
            );
            let off = differing(&cpu, &gpu_image, 0.01);
            assert!(
                off * 100 <= cpu.pixels.len(),
                "{scene}: {off} pixels differ by more than 1 %"
            );
            if mode == modes[0] {
                // Not the field's own direct light: at 33 directions the two differ visibly.
                let c = vlf_core::render::compare::compare(&from_field, &cpu, 16, Default::default()).unwrap();
                assert!(
                    c.block_error > 0.02,
                    "{scene}: exact and field direct light agree: {c:?}"
                );
            }
        }
    }
}

#[test]
fn an_image_samples_the_field_not_a_constant() {
    // The GPU image follows the field: doubling the radiance doubles every pixel, and a field
    // with every map zero renders black.
    let Some(gpu) = gpu() else { return };
    let mut field = field("cornell.obj", 2);
    let cam = readme_camera(48, 36);
    let base = vlf_viewer::render(
        &gpu,
        &FieldRenderer::new(&gpu, &field).unwrap(),
        &cam,
        1,
        SpecularMode::Rays,
    )
    .unwrap();
    for r in &mut field.radiance {
        *r = r.map(|v| v * 2.0);
    }
    let doubled = vlf_viewer::render(
        &gpu,
        &FieldRenderer::new(&gpu, &field).unwrap(),
        &cam,
        1,
        SpecularMode::Rays,
    )
    .unwrap();
    for (a, b) in base.pixels.iter().zip(&doubled.pixels) {
        for c in 0..3 {
            assert_eq!(a[c] * 2.0, b[c]);
        }
    }
    field.radiance.iter_mut().for_each(|r| *r = [0.0; 3]);
    let black = vlf_viewer::render(
        &gpu,
        &FieldRenderer::new(&gpu, &field).unwrap(),
        &cam,
        1,
        SpecularMode::Rays,
    )
    .unwrap();
    assert!(black.pixels.iter().all(|p| *p == [0.0; 3]));
}

#[test]
fn no_adapter_is_a_clear_error() {
    match Gpu::with_backends(wgpu::Backends::empty()) {
        Err(e @ ViewerError::NoAdapter(_)) => {
            let message = e.to_string();
            assert!(message.contains("mesa-vulkan-drivers"), "{message}");
        }
        Err(e) => panic!("expected NoAdapter, got {e}"),
        Ok(gpu) => panic!("no backend allowed, yet got {}", gpu.describe()),
    }
}

#[test]
fn oversized_image_is_refused() {
    let Some(gpu) = gpu() else { return };
    let field = field("cornell.obj", 1);
    let renderer = FieldRenderer::new(&gpu, &field).unwrap();
    let side = gpu.limits.max_texture_dimension_2d + 1;
    let Ok(cam) = Camera::new(
        DVec3::new(278.0, 273.0, -800.0),
        DVec3::new(278.0, 273.0, 0.0),
        DVec3::Y,
        39.0,
        side,
        1,
    ) else {
        return; // the camera's own limit is lower: nothing to test here
    };
    match vlf_viewer::render(&gpu, &renderer, &cam, 1, SpecularMode::Rays) {
        Err(ViewerError::TooLarge(m)) => assert!(m.contains("pixels a side"), "{m}"),
        other => panic!("expected TooLarge, got {:?}", other.map(|_| ())),
    }
}

/// An `Rgba8*` texture of `width × height` to draw into and read back.
fn rgba8_target(gpu: &Gpu, format: wgpu::TextureFormat, width: u32, height: u32) -> wgpu::Texture {
    gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: None,
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}

/// Reads an `Rgba8*` texture of `width × height` back.
fn read_rgba8(gpu: &Gpu, texture: &wgpu::Texture, width: u32, height: u32) -> Vec<u8> {
    let row = (width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: (row * height) as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(height),
            },
        },
        wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
    );
    gpu.queue.submit([encoder.finish()]);
    buffer.slice(..).map_async(wgpu::MapMode::Read, |r| r.expect("map"));
    gpu.device.poll(wgpu::PollType::wait_indefinitely()).expect("poll");
    let bytes = buffer.slice(..).get_mapped_range().expect("mapped");
    bytes
        .chunks_exact(row as usize)
        .flat_map(|r| r[..(width * 4) as usize].to_vec())
        .collect()
}

#[test]
fn the_screen_shows_what_a_png_would() {
    // The viewer's tone-mapping pass, onto an sRGB format (the hardware encodes) and a linear
    // one (the shader encodes), gives the bytes of the CPU's PNG tone map to within one step.
    let Some(gpu) = gpu() else { return };
    let field = field("cornell.obj", 3);
    let renderer = FieldRenderer::new(&gpu, &field).unwrap();
    let (w, h) = (64, 48);
    let frame = vlf_viewer::frame::Frame::new(&gpu, w, h).unwrap();
    let viewpoint = renderer.viewpoint(&readme_camera(w, h), (0.0, 0.0), vlf_viewer::MirrorMode::Rays);
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    renderer.draw(&gpu, &mut encoder, &viewpoint, &frame.color_view, &frame.depth_view);
    gpu.queue.submit([encoder.finish()]);
    let linear = frame.image(&gpu).unwrap();
    for format in [wgpu::TextureFormat::Rgba8UnormSrgb, wgpu::TextureFormat::Rgba8Unorm] {
        let tonemap = vlf_viewer::tonemap::Tonemap::new(&gpu, format, &frame);
        let target = rgba8_target(&gpu, format, w, h);
        for exposure in [-1.0, 1.5] {
            let mut encoder = gpu.device.create_command_encoder(&Default::default());
            let view = target.create_view(&Default::default());
            tonemap.draw(&gpu, &mut encoder, &view, exposure);
            gpu.queue.submit([encoder.finish()]);
            let bytes = read_rgba8(&gpu, &target, w, h);
            let mut worst = 0;
            let mut saturated = 0;
            for (p, q) in linear.pixels.iter().zip(bytes.chunks_exact(4)) {
                for c in 0..3 {
                    let expected = vlf_core::render::image::tone_map(p[c], exposure);
                    worst = worst.max((expected as i32 - q[c] as i32).abs());
                    saturated += (expected == 255) as usize;
                }
            }
            assert!(worst <= 1, "{format:?} exposure {exposure}: off by {worst}");
            assert!(
                saturated < linear.pixels.len() * 3 / 2,
                "{format:?} exposure {exposure}: mostly white"
            );
        }
    }
}

#[test]
fn the_status_line_spells_its_text() {
    // "Ab" at (4, 4), one screen pixel per font pixel, over white: every pixel of the two
    // glyph cells is white exactly where font8x8 sets a bit and 40 % white elsewhere (the
    // translucent band); outside the band the target is untouched.
    let Some(gpu) = gpu() else { return };
    let (w, h) = (32, 16);
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let target = rgba8_target(&gpu, format, w, h);
    let view = target.create_view(&Default::default());
    let mut overlay = vlf_viewer::overlay::Overlay::new(&gpu, format);
    overlay.set_text(&gpu, "Ab");
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    drop(vlf_viewer::pass::color_pass(
        &mut encoder,
        "clear",
        &view,
        wgpu::LoadOp::Clear(wgpu::Color::WHITE),
        None,
    ));
    overlay.draw(&gpu, &mut encoder, &view, (w, h), (4.0, 4.0), 1.0);
    gpu.queue.submit([encoder.finish()]);
    let bytes = read_rgba8(&gpu, &target, w, h);
    let red = |x: u32, y: u32| bytes[((y * w + x) * 4) as usize];
    let mut lit = 0;
    for y in 0..h {
        for x in 0..w {
            let in_band = (2..22).contains(&x) && (2..14).contains(&y);
            let in_text = (4..20).contains(&x) && (4..12).contains(&y);
            let expected = if in_text {
                let glyph = font8x8::legacy::BASIC_LEGACY[if x < 12 { b'A' } else { b'b' } as usize];
                let on = glyph[(y - 4) as usize] >> ((x - 4) % 8) & 1 == 1;
                lit += on as usize;
                if on { 255 } else { 102 }
            } else if in_band {
                102
            } else {
                255
            };
            assert!(
                (red(x, y) as i32 - expected).abs() <= 1,
                "({x}, {y}): {} vs {expected}",
                red(x, y)
            );
        }
    }
    assert!(lit > 20, "the glyphs have pixels: {lit}");
}
