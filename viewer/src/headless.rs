//! Headless rendering (`vlf render --gpu`): a view of a field into an [`Image`], with the CPU
//! renderer's sample positions and box filter so the two can be compared pixel for pixel.
//!
//! The CPU renderer averages `n × n` samples per pixel at `(x + (sx + ½)/n, y + (sy + ½)/n)`.
//! Here every sample `(sx, sy)` is one pass at the image's own size with the projection shifted
//! by `(½ − (sx + ½)/n)` pixels, so the rasteriser's pixel centres fall on exactly those
//! positions; the passes are read back and averaged in f64. Any `n` works within the adapter's
//! texture size limit, without a `n`-times larger target.

use crate::frame::Frame;
use crate::{FieldRenderer, Gpu, ViewerError};
use vlf_core::lookup::SpecularMode;
use vlf_core::render::{Camera, Image};

/// Renders `field` as seen by `camera` with `samples_per_axis²` samples per pixel (0 counts as 1),
/// shading mirrors as `mode` says — as [`vlf_core::field::LightField::render`] does on the CPU.
pub fn render(
    gpu: &Gpu,
    field: &FieldRenderer,
    camera: &Camera,
    samples_per_axis: u32,
    mode: SpecularMode,
) -> Result<Image, ViewerError> {
    let (width, height) = (camera.width, camera.height);
    let max = gpu.limits.max_texture_dimension_2d;
    if width > max || height > max {
        return Err(ViewerError::TooLarge(format!(
            "a {width}×{height} image is larger than {} draws ({max} pixels a side at most)",
            gpu.describe()
        )));
    }
    let n = samples_per_axis.max(1);
    let frame = Frame::new(gpu, width, height)?;
    let mut sum = vec![[0.0f64; 3]; (width as usize) * (height as usize)];
    for sy in 0..n {
        for sx in 0..n {
            let at = |s: u32| 0.5 - (s as f64 + 0.5) / n as f64;
            let viewpoint = field.viewpoint(camera, (at(sx), at(sy)), mode.into());
            gpu.checked(|| {
                // One submission per sample: the viewpoint is a uniform written at submission.
                let mut encoder = gpu.device.create_command_encoder(&Default::default());
                field.draw(gpu, &mut encoder, &viewpoint, &frame.color_view, &frame.depth_view);
                gpu.queue.submit([encoder.finish()]);
            })?;
            let pass = frame.read(gpu)?;
            for (s, p) in sum.iter_mut().zip(pass.chunks_exact(4)) {
                for c in 0..3 {
                    s[c] += p[c] as f64;
                }
            }
        }
    }
    let samples = (n * n) as f64;
    let mut image = Image::new(width, height);
    for (pixel, s) in image.pixels.iter_mut().zip(&sum) {
        *pixel = s.map(|v| (v / samples) as f32);
    }
    Ok(image)
}
