//! The viewer's on-screen status line (frames per second, what is drawn, how much of the field
//! has arrived), drawn over the tone-mapped frame with an 8×8 bitmap font (`shaders/overlay.wgsl`).

use crate::Gpu;
use crate::pass::{READ_ONLY, bind_entry, buffer_entry, color_pass, overlay_pipeline, uniform_buffer};
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
        let params = uniform_buffer(device, "status params", std::mem::size_of::<Params>());
        let shader = device.create_shader_module(wgpu::include_wgsl!("shaders/overlay.wgsl"));
        let both = wgpu::ShaderStages::VERTEX_FRAGMENT;
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("status"),
            entries: &[
                buffer_entry(0, both, wgpu::BufferBindingType::Uniform),
                buffer_entry(1, both, READ_ONLY),
                buffer_entry(2, both, READ_ONLY),
            ],
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("status"),
            layout: &layout,
            entries: &[bind_entry(0, &params), bind_entry(1, &glyphs), bind_entry(2, &text)],
        });
        let blend = Some(wgpu::BlendState::ALPHA_BLENDING);
        let pipeline = overlay_pipeline(device, "status", &shader, &layout, format, blend);
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
        let mut pass = color_pass(encoder, "status", target, wgpu::LoadOp::Load, None);
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.draw(0..6, 0..1);
    }
}
