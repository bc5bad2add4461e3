//! Headless rendering (`vlf render --gpu`): a view of a field into an [`Image`], with the CPU
//! renderer's sample positions and box filter so the two can be compared pixel for pixel.
//!
//! The CPU renderer averages `n × n` samples per pixel at `(x + (sx + ½)/n, y + (sy + ½)/n)`.
//! Here every sample `(sx, sy)` is one pass at the image's own size with the projection shifted
//! by `(½ − (sx + ½)/n)` pixels, so the rasteriser's pixel centres fall on exactly those
//! positions; the passes are read back and averaged in f64. Any `n` works within the adapter's
//! texture size limit, without a `n`-times larger target.

use crate::field::{COLOR_FORMAT, DEPTH_FORMAT};
use crate::{FieldRenderer, Gpu, ViewerError};
use vlf_core::render::{Camera, Image};

/// Bytes per pixel of [`COLOR_FORMAT`].
const PIXEL_BYTES: u32 = 16;

/// Renders `field` as seen by `camera` with `samples_per_axis²` samples per pixel (0 counts as 1).
pub fn render(gpu: &Gpu, field: &FieldRenderer, camera: &Camera, samples_per_axis: u32) -> Result<Image, ViewerError> {
    let (width, height) = (camera.width, camera.height);
    let max = gpu.limits.max_texture_dimension_2d;
    if width > max || height > max {
        return Err(ViewerError::TooLarge(format!(
            "a {width}×{height} image is larger than {} draws ({max} pixels a side at most)",
            gpu.describe()
        )));
    }
    let n = samples_per_axis.max(1);
    let target = Target::new(gpu, width, height)?;
    let mut sum = vec![[0.0f64; 3]; (width as usize) * (height as usize)];
    for sy in 0..n {
        for sx in 0..n {
            let at = |s: u32| 0.5 - (s as f64 + 0.5) / n as f64;
            let clip = field.clip_from_vlf(camera, (at(sx), at(sy)));
            let pass = target.draw(gpu, |encoder, color, depth| {
                field.draw(gpu, encoder, clip, color, depth)
            })?;
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

/// An offscreen colour and depth target of one size, with a buffer to read the colour back.
struct Target {
    width: u32,
    height: u32,
    /// Bytes per row in the read-back buffer: rows are padded to wgpu's copy alignment.
    row_bytes: u32,
    color: wgpu::Texture,
    color_view: wgpu::TextureView,
    depth_view: wgpu::TextureView,
    readback: wgpu::Buffer,
}

impl Target {
    fn new(gpu: &Gpu, width: u32, height: u32) -> Result<Target, ViewerError> {
        let row_bytes =
            (width * PIXEL_BYTES).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        gpu.checked(|| {
            let size = wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            };
            let texture = |label, format, usage| {
                gpu.device.create_texture(&wgpu::TextureDescriptor {
                    label: Some(label),
                    size,
                    mip_level_count: 1,
                    sample_count: 1,
                    dimension: wgpu::TextureDimension::D2,
                    format,
                    usage,
                    view_formats: &[],
                })
            };
            let color = texture(
                "color",
                COLOR_FORMAT,
                wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            );
            let depth = texture("depth", DEPTH_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT);
            let readback = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size: row_bytes as u64 * height as u64,
                usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
                mapped_at_creation: false,
            });
            Target {
                width,
                height,
                row_bytes,
                color_view: color.create_view(&Default::default()),
                depth_view: depth.create_view(&Default::default()),
                color,
                readback,
            }
        })
    }

    /// Records `draw` into a fresh encoder, submits it (so uniforms written by `draw` apply to
    /// this pass alone), and reads the colour back: RGBA f32, row by row, unpadded.
    fn draw(
        &self,
        gpu: &Gpu,
        draw: impl FnOnce(&mut wgpu::CommandEncoder, &wgpu::TextureView, &wgpu::TextureView),
    ) -> Result<Vec<f32>, ViewerError> {
        gpu.checked(|| {
            let mut encoder = gpu.device.create_command_encoder(&Default::default());
            draw(&mut encoder, &self.color_view, &self.depth_view);
            encoder.copy_texture_to_buffer(
                self.color.as_image_copy(),
                wgpu::TexelCopyBufferInfo {
                    buffer: &self.readback,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(self.row_bytes),
                        rows_per_image: Some(self.height),
                    },
                },
                wgpu::Extent3d {
                    width: self.width,
                    height: self.height,
                    depth_or_array_layers: 1,
                },
            );
            gpu.queue.submit([encoder.finish()]);
        })?;
        let slice = self.readback.slice(..);
        let (sender, receiver) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = sender.send(r);
        });
        gpu.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| ViewerError::Gpu(e.to_string()))?;
        receiver
            .recv()
            .map_err(|e| ViewerError::Gpu(e.to_string()))?
            .map_err(|e| ViewerError::Gpu(e.to_string()))?;
        let mut out = Vec::with_capacity((self.width * self.height * 4) as usize);
        {
            let bytes = slice.get_mapped_range().map_err(|e| ViewerError::Gpu(e.to_string()))?;
            for row in bytes.chunks_exact(self.row_bytes as usize) {
                let pixels = &row[..(self.width * PIXEL_BYTES) as usize];
                out.extend(
                    pixels
                        .chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                );
            }
        }
        self.readback.unmap();
        Ok(out)
    }
}
