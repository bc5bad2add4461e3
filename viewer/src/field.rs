//! A light field's diffuse surfaces on the GPU: geometry, radiance maps and the pipeline that
//! draws them.
//!
//! Geometry stays in the VLF frame (the scene normalised into `[-1, 1]³`), where f32 keeps
//! about 10⁻⁷ of the scene's size; the view matrix carries the camera into it. Every convex
//! polygon becomes a triangle fan whose vertices carry their texel coordinates in the polygon's
//! grid, computed in f64 (see `shaders/field.wgsl`).

use crate::{Gpu, ViewerError};
use bytemuck::{Pod, Zeroable};
use glam::{DMat4, DVec3, Mat4};
use vlf_core::field::LightField;
use vlf_core::render::Camera;
use wgpu::util::DeviceExt;

/// The colour format drawn into: linear radiance, no clamping (tone mapping comes after).
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;
/// Depth with reversed Z (1 near, 0 at infinity): f32 depth then keeps its precision far away.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Near plane in the VLF frame, whose scene spans 2: a camera can come within 10⁻⁵ of the
/// scene's size of a wall.
const NEAR: f64 = 1e-5;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Vertex {
    position: [f32; 3],
    texel: [f32; 2],
    surface: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Grid {
    first: u32,
    width: u32,
    height: u32,
    _pad: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct ViewUniform {
    clip_from_vlf: [[f32; 4]; 4],
}

/// A field's surfaces and radiance maps, uploaded, with the pipeline that draws them.
pub struct FieldRenderer {
    pipeline: wgpu::RenderPipeline,
    bind_group: wgpu::BindGroup,
    view: wgpu::Buffer,
    vertices: wgpu::Buffer,
    vertex_count: u32,
    /// Maps the scene's units into the VLF frame.
    normalisation: vlf_core::scene::Normalisation,
}

impl FieldRenderer {
    /// Uploads `field`'s surfaces and diffuse radiance maps.
    pub fn new(gpu: &Gpu, field: &LightField) -> Result<FieldRenderer, ViewerError> {
        let scene = &field.scene;
        let atlas = &field.atlas;
        if atlas.grids.len() != scene.surfaces.len() || field.radiance.len() != atlas.texels {
            return Err(ViewerError::Unsupported(format!(
                "inconsistent field: {} surfaces, {} grids, {} texels, {} radiance values",
                scene.surfaces.len(),
                atlas.grids.len(),
                atlas.texels,
                field.radiance.len()
            )));
        }
        let mut vertices = Vec::new();
        for (i, (surface, grid)) in scene.surfaces.iter().zip(&atlas.grids).enumerate() {
            let corner = |v: DVec3| {
                let c = grid.coords(v) - 0.5;
                Vertex {
                    position: v.as_vec3().to_array(),
                    texel: c.as_vec2().to_array(),
                    surface: i as u32,
                }
            };
            // A convex polygon, counter-clockwise about its front normal: a fan.
            for k in 1..surface.vertices.len().saturating_sub(1) {
                vertices.push(corner(surface.vertices[0]));
                vertices.push(corner(surface.vertices[k]));
                vertices.push(corner(surface.vertices[k + 1]));
            }
        }
        let grids: Vec<Grid> = atlas
            .grids
            .iter()
            .map(|g| Grid {
                first: g.first as u32,
                width: g.width,
                height: g.height,
                _pad: 0,
            })
            .collect();
        let radiance: Vec<f32> = field.radiance.iter().flatten().copied().collect();
        let radiance_bytes = (radiance.len() * 4) as u64;
        let limit = gpu
            .limits
            .max_storage_buffer_binding_size
            .min(gpu.limits.max_buffer_size);
        if radiance_bytes > limit || atlas.texels > u32::MAX as usize / 3 {
            return Err(ViewerError::TooLarge(format!(
                "the field's radiance maps take {:.1} MB; {} binds at most {:.1} MB",
                radiance_bytes as f64 / 1e6,
                gpu.describe(),
                limit as f64 / 1e6
            )));
        }
        // Empty buffers cannot be bound: a scene without surfaces still gets one padding element.
        let nonempty = |bytes: &[u8], min: usize| {
            let mut v = bytes.to_vec();
            v.resize(v.len().max(min), 0);
            v
        };
        gpu.checked(|| {
            let device = &gpu.device;
            let view = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("view"),
                size: std::mem::size_of::<ViewUniform>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let grids = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("grids"),
                contents: &nonempty(bytemuck::cast_slice(&grids), 16),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let radiance = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("radiance"),
                contents: &nonempty(bytemuck::cast_slice(&radiance), 16),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let vertex_count = vertices.len() as u32;
            let vertices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("vertices"),
                contents: &nonempty(bytemuck::cast_slice(&vertices), 4),
                usage: wgpu::BufferUsages::VERTEX,
            });
            let shader = device.create_shader_module(wgpu::include_wgsl!("shaders/field.wgsl"));
            let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("field"),
                entries: &[
                    binding(0, wgpu::ShaderStages::VERTEX, wgpu::BufferBindingType::Uniform),
                    binding(
                        1,
                        wgpu::ShaderStages::FRAGMENT,
                        wgpu::BufferBindingType::Storage { read_only: true },
                    ),
                    binding(
                        2,
                        wgpu::ShaderStages::FRAGMENT,
                        wgpu::BufferBindingType::Storage { read_only: true },
                    ),
                ],
            });
            let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("field"),
                layout: &layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: view.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: grids.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: radiance.as_entire_binding(),
                    },
                ],
            });
            let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("field"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
            let attributes = wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x2, 2 => Uint32];
            let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("field"),
                layout: Some(&pipeline_layout),
                vertex: wgpu::VertexState {
                    module: &shader,
                    entry_point: Some("vs_main"),
                    compilation_options: Default::default(),
                    buffers: &[Some(wgpu::VertexBufferLayout {
                        array_stride: std::mem::size_of::<Vertex>() as u64,
                        step_mode: wgpu::VertexStepMode::Vertex,
                        attributes: &attributes,
                    })],
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    front_face: wgpu::FrontFace::Ccw,
                    // Back faces are drawn (black): they hide what is behind them.
                    cull_mode: None,
                    ..Default::default()
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    depth_write_enabled: Some(true),
                    depth_compare: Some(wgpu::CompareFunction::Greater),
                    stencil: Default::default(),
                    bias: Default::default(),
                }),
                multisample: Default::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &shader,
                    entry_point: Some("fs_main"),
                    compilation_options: Default::default(),
                    targets: &[Some(wgpu::ColorTargetState {
                        format: COLOR_FORMAT,
                        blend: None,
                        write_mask: wgpu::ColorWrites::ALL,
                    })],
                }),
                multiview_mask: None,
                cache: None,
            });
            FieldRenderer {
                pipeline,
                bind_group,
                view,
                vertices,
                vertex_count,
                normalisation: scene.normalisation,
            }
        })
    }

    /// The matrix from the VLF frame to clip space for `camera` (scene units), with the image
    /// content shifted by `jitter` pixels (x right, y down): the rasteriser's sample at a pixel's
    /// centre `x + ½` then sees what the camera's ray through `x + ½ − jitter` sees.
    ///
    /// The projection is [`Camera::ray`]'s: forward, right and up from `look_at`, the vertical
    /// field of view and the image's aspect; depth is reversed and infinite.
    pub fn clip_from_vlf(&self, camera: &Camera, jitter: (f64, f64)) -> Mat4 {
        let n = self.normalisation;
        let eye = n.to_vlf(camera.eye);
        let target = n.to_vlf(camera.target);
        let aspect = camera.width as f64 / camera.height as f64;
        let view = glam::dcamera::rh::view::look_at_mat4(eye, target, camera.up);
        // wgpu's clip space is DirectX's: z in [0, 1], y up.
        let projection = glam::dcamera::rh::proj::directx::perspective_infinite_reverse(
            camera.fovy_degrees.to_radians(),
            aspect,
            NEAR,
        );
        // NDC x grows with pixels to the right, NDC y with pixels upwards.
        let shift = DMat4::from_translation(DVec3::new(
            2.0 * jitter.0 / camera.width as f64,
            -2.0 * jitter.1 / camera.height as f64,
            0.0,
        ));
        (shift * projection * view).as_mat4()
    }

    /// Draws the field seen through `clip_from_vlf` into `color` (cleared to black) with `depth`
    /// (cleared), both of the same size, in formats [`COLOR_FORMAT`] and [`DEPTH_FORMAT`].
    pub fn draw(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        clip_from_vlf: Mat4,
        color: &wgpu::TextureView,
        depth: &wgpu::TextureView,
    ) {
        let uniform = ViewUniform {
            clip_from_vlf: clip_from_vlf.to_cols_array_2d(),
        };
        gpu.queue.write_buffer(&self.view, 0, bytemuck::bytes_of(&uniform));
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("field"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: color,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: depth,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(0.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.set_vertex_buffer(0, self.vertices.slice(..));
        pass.draw(0..self.vertex_count, 0..1);
    }
}

fn binding(index: u32, visibility: wgpu::ShaderStages, ty: wgpu::BufferBindingType) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding: index,
        visibility,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}
