//! An offscreen frame: the linear radiance a field is drawn into, with its depth buffer, and the
//! way to read it back (headless renders, the viewer's screenshots).

use crate::field::{COLOR_FORMAT, DEPTH_FORMAT};
use crate::{Gpu, ViewerError};
use vlf_core::render::Image;

/// Bytes per pixel of [`COLOR_FORMAT`].
const PIXEL_BYTES: u32 = 16;

/// A colour ([`COLOR_FORMAT`]) and depth target of one size, with a buffer to read the colour back.
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Bytes per row in the read-back buffer: rows are padded to wgpu's copy alignment.
    row_bytes: u32,
    color: wgpu::Texture,
    pub color_view: wgpu::TextureView,
    pub depth_view: wgpu::TextureView,
    readback: wgpu::Buffer,
}

impl Frame {
    pub fn new(gpu: &Gpu, width: u32, height: u32) -> Result<Frame, ViewerError> {
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
                wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::COPY_SRC
                    | wgpu::TextureUsages::TEXTURE_BINDING,
            );
            let depth = texture("depth", DEPTH_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT);
            let readback = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size: row_bytes as u64 * height as u64,
                usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
                mapped_at_creation: false,
            });
            Frame {
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

    /// Reads the colour back once what was submitted so far is done: RGBA f32, row by row,
    /// unpadded.
    pub fn read(&self, gpu: &Gpu) -> Result<Vec<f32>, ViewerError> {
        gpu.checked(|| {
            let mut encoder = gpu.device.create_command_encoder(&Default::default());
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
        let (width, row_bytes) = (self.width, self.row_bytes);
        let out = gpu.read_mapped(&self.readback, |bytes| {
            let mut out = Vec::with_capacity((width * self.height * 4) as usize);
            for row in bytes.chunks_exact(row_bytes as usize) {
                let pixels = &row[..(width * PIXEL_BYTES) as usize];
                out.extend(
                    pixels
                        .chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                );
            }
            out
        })?;
        Ok(out)
    }

    /// The colour read back as an image (alpha dropped).
    pub fn image(&self, gpu: &Gpu) -> Result<Image, ViewerError> {
        let rgba = self.read(gpu)?;
        let mut image = Image::new(self.width, self.height);
        for (pixel, p) in image.pixels.iter_mut().zip(rgba.chunks_exact(4)) {
            *pixel = [p[0], p[1], p[2]];
        }
        Ok(image)
    }
}
