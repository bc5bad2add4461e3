//! What a walkthrough's frame costs on the GPU: `cargo bench -p vlf-viewer --bench frame`.
//!
//! The bundled scenes propagated at the defaults (l = 513, N = 64, the plan's remedies), drawn
//! at 1280 × 720 from the README's viewpoint as `vlf view` draws them: one pass of
//! `shaders/field.wgsl` into a colour and depth target, submitted and waited for (no read-back,
//! no tone mapping, no present). Each scene twice:
//!
//! - **direct light from the field**: every fragment looks up its texel;
//! - **exact direct light** (`--direct exact`, what `vlf view --direct auto` draws on a hardware
//!   adapter): every diffuse fragment also sums the emitters' quadrature points with one shadow
//!   ray each through the scene's BVH (`viewer/src/direct.rs`), at the default 64 points an
//!   emitter and at 16 (`--direct-samples 16`: a quarter of the shadow rays).
//!
//! The mirror scene is drawn with its mirrors from the rays (the view's default) and traced
//! 8 deep. Skips (with a message) where there is no adapter; on lavapipe an exact frame takes
//! seconds.

#[allow(dead_code)]
#[path = "../tests/common/mod.rs"]
mod common;

use criterion::{Criterion, criterion_group, criterion_main};
use vlf_core::dynamic::gather::DEFAULT_DIRECT_SAMPLES;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation};
use vlf_viewer::FieldRenderer;
use vlf_viewer::frame::Frame;

/// A bundled scene propagated at the defaults: the field after the first iteration (snapshot
/// 1, whose direct light exact rendering replaces) and the final one.
fn propagated(name: &str) -> (LightField, LightField) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name);
    let (scene, _) = vlf_core::scene::load_scene(&path, &Default::default()).expect("a bundled scene");
    let options = Options::recommended();
    let mut p = Propagation::new(scene, options).expect("setup");
    p.step(|_| {});
    let first = p.field_now();
    p.run(|_| {});
    (first, p.into_field())
}

fn bench(c: &mut Criterion) {
    let Some(gpu) = common::gpu() else {
        return;
    };
    let camera = common::readme_camera(1280, 720);
    let frame = Frame::new(&gpu, camera.width, camera.height).expect("a 1280x720 target");
    let mut group = c.benchmark_group(format!("GPU frame 1280x720 on {}", gpu.describe()));
    group.sample_size(20);
    for (scene, modes) in [
        ("cornell.obj", &[SpecularMode::Rays][..]),
        (
            "mirrors.obj",
            &[SpecularMode::Rays, SpecularMode::Trace { depth: 8 }][..],
        ),
    ] {
        let (first, plain) = propagated(scene);
        let exact = |samples: u32| {
            let mut field = plain.clone();
            field.use_exact_direct(&first, samples).expect("exact direct light");
            (format!("exact, {samples} points an emitter"), field)
        };
        let fields = [
            ("from the field".to_string(), plain.clone()),
            exact(DEFAULT_DIRECT_SAMPLES / 4),
            exact(DEFAULT_DIRECT_SAMPLES),
        ];
        for (direct, field) in &fields {
            let renderer = FieldRenderer::new(&gpu, field).expect("upload");
            for &mode in modes {
                let viewpoint = renderer.viewpoint(&camera, (0.0, 0.0), mode.into());
                let name = format!("{scene}, mirrors {mode:?}, direct light {direct}");
                group.bench_function(name, |b| {
                    b.iter(|| {
                        gpu.checked(|| {
                            let mut encoder = gpu.device.create_command_encoder(&Default::default());
                            renderer.draw(&gpu, &mut encoder, &viewpoint, &frame.color_view, &frame.depth_view);
                            gpu.queue.submit([encoder.finish()]);
                            gpu.device
                                .poll(wgpu::PollType::wait_indefinitely())
                                .expect("the frame completes");
                        })
                        .expect("a frame")
                    })
                });
            }
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
