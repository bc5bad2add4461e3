//! The last pass of a viewer frame: linear radiance to the screen's sRGB (see
//! `shaders/tonemap.wgsl`), the same mapping as the CPU's PNG output.

use crate::Gpu;
use crate::frame::Frame;
use crate::pass::{bind_entry, buffer_entry, color_pass, overlay_pipeline, uniform_buffer};
use bytemuck::{Pod, Zeroable};

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    scale: f32,
    encode: u32,
    _pad: [u32; 2],
}

/// The tone-mapping pipeline for one output format, bound to one frame.
pub struct Tonemap {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    params: wgpu::Buffer,
    /// The frame read, bound: made again only when the frame is (a resize).
    bind_group: wgpu::BindGroup,
    /// Whether the shader must sRGB-encode (the output format does not).
    encode: bool,
}

impl Tonemap {
    /// Tone-maps `frame` onto targets of `format`.
    pub fn new(gpu: &Gpu, format: wgpu::TextureFormat, frame: &Frame) -> Tonemap {
        let device = &gpu.device;
        let shader = device.create_shader_module(wgpu::include_wgsl!("shaders/tonemap.wgsl"));
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tonemap"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: false },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                buffer_entry(1, wgpu::ShaderStages::FRAGMENT, wgpu::BufferBindingType::Uniform),
            ],
        });
        let pipeline = overlay_pipeline(device, "tonemap", &shader, &layout, format, None);
        let params = uniform_buffer(device, "tonemap params", std::mem::size_of::<Params>());
        let bind_group = bind(gpu, &layout, &params, frame);
        Tonemap {
            pipeline,
            layout,
            params,
            bind_group,
            encode: !format.is_srgb(),
        }
    }

    /// Reads `frame` from now on (after a resize made a new one).
    pub fn set_frame(&mut self, gpu: &Gpu, frame: &Frame) {
        self.bind_group = bind(gpu, &self.layout, &self.params, frame);
    }

    /// Draws the frame scaled by `2^exposure` onto `target` (of the frame's size).
    pub fn draw(&self, gpu: &Gpu, encoder: &mut wgpu::CommandEncoder, target: &wgpu::TextureView, exposure: f64) {
        let params = Params {
            scale: exposure.exp2() as f32,
            encode: self.encode as u32,
            _pad: [0; 2],
        };
        gpu.queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let mut pass = color_pass(
            encoder,
            "tonemap",
            target,
            wgpu::LoadOp::Clear(wgpu::Color::BLACK),
            None,
        );
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.draw(0..3, 0..1);
    }
}

fn bind(gpu: &Gpu, layout: &wgpu::BindGroupLayout, params: &wgpu::Buffer, frame: &Frame) -> wgpu::BindGroup {
    gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("tonemap"),
        layout,
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::TextureView(&frame.color_view),
            },
            bind_entry(1, params),
        ],
    })
}
