//! The viewer's on-screen status line (frames per second, what is drawn, how much of the field
//! has arrived), drawn over the tone-mapped frame with an 8×8 bitmap font (`shaders/overlay.wgsl`).

use crate::Gpu;
use bytemuck::{Pod, Zeroable};

/// Characters the line holds at most; longer text is cut.
pub const MAX_CHARS: usize = 160;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    origin: [f32; 2],
    scale: f32,
    count: u32,
    screen: [f32; 2],
    _pad: [f32; 2],
}

/// The status line's pipeline and buffers, for one output format.
pub struct Overlay {
    pipeline: wgpu::RenderPipeline,
    bind_group: wgpu::BindGroup,
    params: wgpu::Buffer,
    text: wgpu::Buffer,
    count: u32,
}

impl Overlay {
    pub fn new(gpu: &Gpu, format: wgpu::TextureFormat) -> Overlay {
        let device = &gpu.device;
        let glyphs: Vec<u32> = font8x8::legacy::BASIC_LEGACY
            .iter()
            .flat_map(|g| {
                [
                    u32::from_le_bytes([g[0], g[1], g[2], g[3]]),
                    u32::from_le_bytes([g[4], g[5], g[6], g[7]]),
                ]
            })
            .collect();
        let glyphs = wgpu::util::DeviceExt::create_buffer_init(
            device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("font"),
                contents: bytemuck::cast_slice(&glyphs),
                usage: wgpu::BufferUsages::STORAGE,
            },
        );
        let text = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("status text"),
            size: (MAX_CHARS * 4) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let params = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("status params"),
            size: std::mem::size_of::<Params>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let shader = device.create_shader_module(wgpu::include_wgsl!("shaders/overlay.wgsl"));
        let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
            ty: wgpu::BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let storage = wgpu::BufferBindingType::Storage { read_only: true };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("status"),
            entries: &[
                entry(0, wgpu::BufferBindingType::Uniform),
                entry(1, storage),
                entry(2, storage),
            ],
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("status"),
            layout: &layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: params.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: glyphs.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: text.as_entire_binding(),
                },
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("status"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("status"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: Default::default(),
            depth_stencil: None,
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format,
                    blend: Some(wgpu::BlendState::ALPHA_BLENDING),
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        Overlay {
            pipeline,
            bind_group,
            params,
            text,
            count: 0,
        }
    }

    /// Sets the line's text (ASCII; other characters show as blanks; cut at [`MAX_CHARS`]).
    pub fn set_text(&mut self, gpu: &Gpu, text: &str) {
        let codes: Vec<u32> = text
            .chars()
            .take(MAX_CHARS)
            .map(|c| if c.is_ascii() { c as u32 } else { b' ' as u32 })
            .collect();
        self.count = codes.len() as u32;
        if !codes.is_empty() {
            gpu.queue.write_buffer(&self.text, 0, bytemuck::cast_slice(&codes));
        }
    }

    /// Draws the line over `target` (of `width × height` pixels, kept as it is elsewhere), its
    /// top-left corner at `origin`, each font pixel `scale` pixels wide.
    #[allow(clippy::too_many_arguments)]
    pub fn draw(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        (width, height): (u32, u32),
        origin: (f32, f32),
        scale: f32,
    ) {
        if self.count == 0 {
            return;
        }
        let params = Params {
            origin: [origin.0, origin.1],
            scale,
            count: self.count,
            screen: [width as f32, height as f32],
            _pad: [0.0; 2],
        };
        gpu.queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("status"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Load,
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.draw(0..6, 0..1);
    }
}
