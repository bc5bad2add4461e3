//! A light field's diffuse surfaces on the GPU: geometry, radiance maps and the pipeline that
//! draws them.
//!
//! Radiance lives in a *pool* part by part (`vlf_core::parts`: a surface's diffuse map, a mirror
//! tile): a part table gives each part's place in the pool, or `NONE` while it is not resident.
//! A complete field fills the pool once ([`FieldRenderer::new`]); a streaming viewer gives the
//! pool the size of its cache and moves parts in and out as the view changes
//! ([`FieldRenderer::streaming`], [`FieldRenderer::upload`], [`FieldRenderer::evict`]). What is
//! missing draws black, and a mirror missing a tile of the view falls back to ray tracing
//! through the diffuse maps that are there (see `shaders/field.wgsl`).
//!
//! Geometry stays in the VLF frame (the scene normalised into `[-1, 1]³`), where f32 keeps
//! about 10⁻⁷ of the scene's size; the view matrix carries the camera into it. Every convex
//! polygon becomes a triangle fan whose vertices carry their texel coordinates in the polygon's
//! grid, computed in f64 (see `shaders/field.wgsl`).

use crate::direct::{DirectParts, EmitterBuffers};
use crate::objects::{ObjectData, ObjectGeometry, ObjectsUniform, StaticCounts};
use crate::pass::{READ_ONLY, bind_entry, buffer_entry, color_pass, uniform_buffer};
use crate::rays::{NONE, RayTables};
use crate::shadows::TexelShadows;
use crate::{Gpu, ViewerError};
use bytemuck::{Pod, Zeroable};
use glam::{DMat4, DVec3, Mat4, Vec3};
use std::cell::Cell;
use vlf_core::direct::Emitters;
use vlf_core::dynamic::PlacedObject;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::parts::PartCatalog;
use vlf_core::render::{Bvh, Camera};
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
pub(crate) struct Vertex {
    pub position: [f32; 3],
    pub texel: [f32; 2],
    pub surface: u32,
}

/// A surface as the shader reads it (`Surface` in `shaders/field.wgsl`: WGSL's layout, where a
/// `vec3<f32>` takes 12 bytes aligned to 16 and the next scalar fills the gap).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(crate) struct GpuSurface {
    pub normal: [f32; 3],
    pub offset: f32,
    pub specular: [f32; 3],
    pub mirror: u32,
    pub grid_origin: [f32; 3],
    pub inv_texel: f32,
    pub axis_u: [f32; 3],
    /// The part number of the chunk holding the surface's chart (its entry in the part table).
    pub part: u32,
    pub axis_v: [f32; 3],
    pub width: u32,
    pub first_vertex: u32,
    pub vertex_count: u32,
    pub height: u32,
    pub mirror_index: u32,
    /// Where the chart's texels start in its chunk.
    pub texel_offset: u32,
    pub _pad: [u32; 3],
    /// A dynamic object's diffuse reflectance (0 for the static scene's surfaces).
    pub diffuse: [f32; 3],
    pub _pad2: u32,
}

impl GpuSurface {
    /// A dynamic object's surface: a plane and a material, no radiance map (the gather shades
    /// it); its polygon's vertices are set by the caller.
    pub(crate) fn object(normal: DVec3, offset: f64, material: &vlf_core::scene::Material) -> GpuSurface {
        GpuSurface {
            normal: normal.as_vec3().to_array(),
            offset: offset as f32,
            specular: material.specular.map(|c| c as f32),
            mirror: material.is_mirror() as u32,
            grid_origin: [0.0; 3],
            inv_texel: 0.0,
            axis_u: [0.0; 3],
            part: 0,
            axis_v: [0.0; 3],
            width: 0,
            first_vertex: 0,
            vertex_count: 0,
            height: 0,
            mirror_index: NONE,
            texel_offset: 0,
            _pad: [0; 3],
            diffuse: material.diffuse.map(|c| c as f32),
            _pad2: 0,
        }
    }
}

/// A BVH node as the shader reads it (the layout of `vlf_core::render::bvh::Node`).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(crate) struct GpuNode {
    pub min: [f32; 3],
    pub max: [f32; 3],
    pub index: u32,
    pub count: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct ViewUniform {
    clip_from_vlf: [[f32; 4]; 4],
    eye: [f32; 4],
    depth: u32,
    mode: u32,
    /// The first direct part, `NONE` without exact direct light.
    direct_parts: u32,
    _pad: u32,
}

/// Where the field is seen from, as the shader needs it.
#[derive(Clone, Copy, Debug)]
pub struct Viewpoint {
    /// The VLF frame to clip space.
    pub clip_from_vlf: Mat4,
    /// The eye in the VLF frame.
    pub eye: Vec3,
    /// How mirrors are drawn.
    pub mirrors: MirrorMode,
}

/// How the shader draws mirrors (the CPU renderer's `SpecularMode`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MirrorMode {
    /// From the field's directional radiance maps.
    Rays,
    /// Ray traced through the scene at most `depth` mirrors deep (0: no reflections).
    Trace { depth: u32 },
}

impl From<SpecularMode> for MirrorMode {
    fn from(mode: SpecularMode) -> MirrorMode {
        match mode {
            SpecularMode::Rays => MirrorMode::Rays,
            SpecularMode::Trace { depth } => MirrorMode::Trace { depth },
        }
    }
}

/// A field's surfaces and radiance maps, uploaded, with the pipeline that draws them.
pub struct FieldRenderer {
    pipeline: wgpu::RenderPipeline,
    /// Resident radiance, 3 floats per value, part after part wherever they were put.
    pool: wgpu::Buffer,
    /// Per part: its first value in the pool, or `NONE`.
    parts: wgpu::Buffer,
    /// Values the pool holds.
    capacity: usize,
    catalog: PartCatalog,
    bind_group: wgpu::BindGroup,
    view: wgpu::Buffer,
    vertices: wgpu::Buffer,
    vertex_count: u32,
    /// Maps the scene's units into the VLF frame.
    normalisation: vlf_core::scene::Normalisation,
    /// The buffers bound at 0..=12 of `shaders/field.wgsl` and `shaders/objects.wgsl`, in
    /// binding order, for other pipelines over the same field (the gather).
    pub(crate) bindings: [wgpu::Buffer; BINDINGS],
    /// Where the objects' entries start in the buffers, and their layout (what a move must
    /// keep).
    objects: (StaticCounts, ObjectGeometry),
    objects_uniform: ObjectsUniform,
    /// The pass computing the objects' shadows per texel, once turned on
    /// ([`FieldRenderer::shadows_per_texel`]).
    texel_shadows: Option<TexelShadows>,
    /// Whether the shadows per texel must be computed again before the next draw (objects
    /// moved, parts arrived), and the mirror mode they were computed for.
    shadows_stale: Cell<bool>,
    shadows_mode: Cell<Option<MirrorMode>>,
    /// Passes computing the shadows per texel so far ([`FieldRenderer::shadow_passes`]).
    shadow_passes: Cell<u64>,
    /// With exact direct light: where its direct parts are.
    direct: Option<DirectParts>,
}

/// Buffers of the field and its objects, bound at 0..BINDINGS.
pub(crate) const BINDINGS: usize = 15;

/// The layout of the field's and objects' bindings as `stages` read them: the view uniform
/// (the vertex stage reads it too), seven storage buffers of the field, the objects' uniform,
/// four storage buffers of the objects, and their shadows per texel and their own light
/// (written by [`crate::shadows`]).
pub(crate) fn binding_layout(stages: wgpu::ShaderStages) -> Vec<wgpu::BindGroupLayoutEntry> {
    (0..BINDINGS as u32)
        .map(|b| match b {
            0 => buffer_entry(0, stages | wgpu::ShaderStages::VERTEX, wgpu::BufferBindingType::Uniform),
            8 => buffer_entry(8, stages, wgpu::BufferBindingType::Uniform),
            13 | 14 => buffer_entry(b, stages, wgpu::BufferBindingType::Storage { read_only: false }),
            _ => buffer_entry(b, stages, READ_ONLY),
        })
        .collect()
}

/// The field's shader with the objects' (they call each other), followed by `more`.
pub(crate) fn shader_source(more: &[&str]) -> String {
    let mut source = format!(
        "{}\n{}",
        include_str!("shaders/field.wgsl"),
        include_str!("shaders/objects.wgsl")
    );
    for m in more {
        source.push('\n');
        source.push_str(m);
    }
    source
}

/// Compute passes over a field's buffers (bound at 0..BINDINGS, as [`FieldRenderer::bindings`])
/// and buffers of their own bound after them: the gather at given points, the shadows per
/// texel. `source` is appended to the field's and the objects' shaders.
pub(crate) struct FieldCompute {
    layout: wgpu::BindGroupLayout,
    pipeline_layout: wgpu::PipelineLayout,
    shader: wgpu::ShaderModule,
    /// Whether the field is drawn with exact direct light (the shader's `EXACT_DIRECT`).
    exact: bool,
}

impl FieldCompute {
    /// The pass's own buffers are of the types `extra`, bound at `BINDINGS`, `BINDINGS + 1`, …;
    /// `exact`: the field is drawn with exact direct light, which the gather then adds too.
    pub(crate) fn new(
        device: &wgpu::Device,
        label: &str,
        source: &str,
        extra: &[wgpu::BufferBindingType],
        exact: bool,
    ) -> FieldCompute {
        let compute = wgpu::ShaderStages::COMPUTE;
        let mut entries = binding_layout(compute);
        entries.extend((extra.iter().enumerate()).map(|(k, &ty)| buffer_entry((BINDINGS + k) as u32, compute, ty)));
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(label),
            entries: &entries,
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(label),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(shader_source(&[source]).into()),
        });
        FieldCompute {
            layout,
            pipeline_layout,
            shader,
            exact,
        }
    }

    /// The pipeline of the shader's entry point `entry`.
    pub(crate) fn pipeline(&self, device: &wgpu::Device, entry: &str) -> wgpu::ComputePipeline {
        device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(entry),
            layout: Some(&self.pipeline_layout),
            module: &self.shader,
            entry_point: Some(entry),
            compilation_options: exact_direct_constant(self.exact),
            cache: None,
        })
    }

    /// The field's buffers `field` and the pass's own `extra`, bound.
    pub(crate) fn bind_group(
        &self,
        device: &wgpu::Device,
        field: &[wgpu::Buffer; BINDINGS],
        extra: &[&wgpu::Buffer],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = (field.iter().chain(extra.iter().copied()).enumerate())
            .map(|(b, buffer)| bind_entry(b as u32, buffer))
            .collect();
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &self.layout,
            entries: &entries,
        })
    }
}

/// The shader's `EXACT_DIRECT` override: set where exact direct light is drawn, so that
/// elsewhere the driver drops its code.
fn exact_direct_constant(exact: bool) -> wgpu::PipelineCompilationOptions<'static> {
    wgpu::PipelineCompilationOptions {
        constants: if exact { &[("EXACT_DIRECT", 1.0)] } else { &[] },
        ..Default::default()
    }
}

impl FieldRenderer {
    /// Uploads `field`'s surfaces, materials and BVH, and all of its radiance.
    ///
    /// A field that shades with exact direct light ([`LightField::use_exact_direct`]) is drawn
    /// with it: its emitters' points and its direct maps are uploaded too (see [`crate::direct`]).
    pub fn new(gpu: &Gpu, field: &LightField) -> Result<FieldRenderer, ViewerError> {
        FieldRenderer::complete(gpu, field, None)
    }

    /// Uploads `field`'s surfaces, materials and BVH (its radiance is not read) with a pool of
    /// `capacity` RGB values and no part resident: radiance comes with [`FieldRenderer::upload`].
    pub fn streaming(gpu: &Gpu, field: &LightField, capacity: usize) -> Result<FieldRenderer, ViewerError> {
        FieldRenderer::build(gpu, field, capacity, None, None)
    }

    /// [`FieldRenderer::streaming`] with the objects of `gatherer` if any, and exact direct
    /// light from `exact`'s points if given (the gatherer's must be the same:
    /// `Gatherer::with_emitters`). With exact direct light the direct parts
    /// ([`FieldRenderer::direct_parts`]) come with [`FieldRenderer::upload`] like the others,
    /// and a surface shows the field's own direct light until its direct part is resident.
    pub fn streaming_with(
        gpu: &Gpu,
        field: &LightField,
        capacity: usize,
        gatherer: Option<&Gatherer>,
        exact: Option<&Emitters>,
    ) -> Result<FieldRenderer, ViewerError> {
        FieldRenderer::build(gpu, field, capacity, gatherer, exact)
    }

    /// [`FieldRenderer::streaming`] with the dynamic objects of `gatherer`, as
    /// [`FieldRenderer::with_objects`] draws them; they move with
    /// [`FieldRenderer::move_objects`]. While a surface the gather reads is not resident, the
    /// gather's mean leaves it out (see `shaders/objects.wgsl`).
    pub fn streaming_with_objects(
        gpu: &Gpu,
        field: &LightField,
        capacity: usize,
        gatherer: &Gatherer,
    ) -> Result<FieldRenderer, ViewerError> {
        FieldRenderer::build(gpu, field, capacity, Some(gatherer), None)
    }

    /// [`FieldRenderer::new`] with the dynamic objects of `gatherer` (which must be over
    /// `field`): drawn with the scene, shaded by the gather over its directions, casting shadows
    /// with its cells and emitter points, as `vlf_core::dynamic::view` draws them on the CPU
    /// (see `shaders/objects.wgsl`).
    pub fn with_objects(gpu: &Gpu, field: &LightField, gatherer: &Gatherer) -> Result<FieldRenderer, ViewerError> {
        FieldRenderer::complete(gpu, field, Some(gatherer))
    }

    fn complete(gpu: &Gpu, field: &LightField, gatherer: Option<&Gatherer>) -> Result<FieldRenderer, ViewerError> {
        let catalog = PartCatalog::new(field);
        let exact = field.exact_direct.as_ref();
        let capacity = catalog.total_values() + exact.map_or(0, |e| e.direct().len());
        let renderer = FieldRenderer::build(gpu, field, capacity, gatherer, exact.map(|e| e.emitters()))?;
        let mut base = 0;
        for i in 0..catalog.len() as u32 {
            renderer.upload(gpu, i, base, field.part_values(&catalog, i))?;
            base += catalog.values(i);
        }
        if let (Some(exact), Some(direct)) = (exact, renderer.direct) {
            for c in 0..direct.chunks {
                renderer.upload(gpu, direct.of_chunk(c), base, &exact.direct()[catalog.range(c)])?;
                base += catalog.values(c);
            }
        }
        Ok(renderer)
    }

    fn build(
        gpu: &Gpu,
        field: &LightField,
        capacity: usize,
        gatherer: Option<&Gatherer>,
        exact: Option<&Emitters>,
    ) -> Result<FieldRenderer, ViewerError> {
        let scene = &field.scene;
        if exact.is_some() {
            crate::direct::check_scene(scene)?;
        }
        if gatherer.is_some_and(|g| !g.objects().is_empty()) {
            crate::direct::check_scene_for_objects(scene)?;
        }
        // One set of emitter points serves exact direct light and the objects' shadows.
        if let (Some(e), Some(g)) = (exact, gatherer)
            && g.emitters() != e
        {
            return Err(ViewerError::Unsupported(
                "exact direct light and the objects' shadows must share their emitter points: give the \
                 gatherer the field's direct light samples (Gatherer::with_direct_samples)"
                    .into(),
            ));
        }
        let atlas = &field.atlas;
        if atlas.chart_of.len() != scene.surfaces.len() || field.radiance.len() != atlas.texels {
            return Err(ViewerError::Unsupported(format!(
                "inconsistent field: {} surfaces, {} charted, {} texels, {} radiance values",
                scene.surfaces.len(),
                atlas.chart_of.len(),
                atlas.texels,
                field.radiance.len()
            )));
        }
        let catalog = PartCatalog::new(field);
        let direct = exact.map(|_| DirectParts::new(&catalog));
        let table_len = direct.map_or(catalog.len(), |d| d.table_len());
        let started = std::time::Instant::now();
        let rays = RayTables::new(field, &catalog);
        tracing::debug!(
            mb = std::mem::size_of_val(rays.words.as_slice()) as f64 / 1e6,
            seconds = started.elapsed().as_secs_f64(),
            "mirror ray tables built"
        );
        // Per surface: its fan for the rasteriser, its polygon, grid and material for the shader.
        let mut vertices = Vec::new();
        let mut polygon_vertices: Vec<[f32; 4]> = Vec::new();
        let mut surfaces = Vec::with_capacity(scene.surfaces.len());
        for (i, surface) in scene.surfaces.iter().enumerate() {
            let grid = atlas.grid(i);
            let part = catalog.chunk_of_surface(i);
            let corner = |v: DVec3| Vertex {
                position: v.as_vec3().to_array(),
                texel: (grid.coords(v) - 0.5).as_vec2().to_array(),
                surface: i as u32,
            };
            // A convex polygon, counter-clockwise about its front normal: a fan.
            for k in 1..surface.vertices.len().saturating_sub(1) {
                vertices.push(corner(surface.vertices[0]));
                vertices.push(corner(surface.vertices[k]));
                vertices.push(corner(surface.vertices[k + 1]));
            }
            let material = scene.material(i);
            surfaces.push(GpuSurface {
                normal: surface.normal.as_vec3().to_array(),
                offset: surface.offset as f32,
                specular: material.specular.map(|c| c as f32),
                mirror: material.is_mirror() as u32,
                grid_origin: grid.origin.as_vec3().to_array(),
                inv_texel: (1.0 / grid.texel) as f32,
                axis_u: grid.axis_u.as_vec3().to_array(),
                part,
                axis_v: grid.axis_v.as_vec3().to_array(),
                width: grid.width,
                first_vertex: polygon_vertices.len() as u32,
                vertex_count: surface.vertices.len() as u32,
                height: grid.height,
                mirror_index: rays.mirror_index[i],
                texel_offset: (grid.first - catalog.range(part).start) as u32,
                _pad: [0; 3],
                diffuse: material.diffuse.map(|c| c as f32),
                _pad2: 0,
            });
            polygon_vertices.extend(surface.vertices.iter().map(|v| v.as_vec3().extend(0.0).to_array()));
        }
        let bvh = Bvh::build(scene);
        let gpu_node = |n: &vlf_core::render::Node| GpuNode {
            min: n.min,
            max: n.max,
            index: n.index,
            count: n.count,
        };
        let mut nodes: Vec<GpuNode> = bvh.nodes().iter().map(gpu_node).collect();
        let mut primitives: Vec<u32> = bvh.primitives().to_vec();
        // Dynamic objects after the scene (see `objects.rs`).
        let counts = StaticCounts {
            vertices: vertices.len(),
            surfaces: surfaces.len(),
            polygon_vertices: polygon_vertices.len(),
            nodes: nodes.len(),
            primitives: primitives.len(),
        };
        let mut objects = ObjectData::new(scene, gatherer, counts);
        // With exact direct light, the camera's shadows per texel follow the gather's.
        let camera_shadows = exact.is_some() && gatherer.is_some();
        if camera_shadows {
            objects.uniform.camera_shadows = (capacity * 3) as u32;
        }
        // The emitters' points: exact direct light's, which are the objects' shadows' too where
        // both are drawn (checked above).
        let emitters = match exact {
            Some(e) => EmitterBuffers::new(scene, e),
            None => std::mem::take(&mut objects.emitters),
        };
        let moving = &objects.geometry;
        surfaces.extend_from_slice(&moving.surfaces);
        polygon_vertices.extend_from_slice(&moving.polygon_vertices);
        nodes.extend_from_slice(&moving.nodes);
        primitives.extend_from_slice(&moving.primitives);
        vertices.extend_from_slice(&moving.raster);
        // Every storage buffer must fit one binding, and the shader indexes them with u32 words.
        let limit = gpu
            .limits
            .max_storage_buffer_binding_size
            .min(gpu.limits.max_buffer_size);
        for (what, bytes) in [
            ("radiance pool", capacity * 12),
            ("objects' shadow pool", if camera_shadows { capacity * 24 } else { 0 }),
            ("part table", table_len * 4),
            ("mirror rays", std::mem::size_of_val(rays.words.as_slice())),
            ("surfaces", std::mem::size_of_val(surfaces.as_slice())),
            ("polygon vertices", std::mem::size_of_val(polygon_vertices.as_slice())),
            ("BVH nodes", std::mem::size_of_val(nodes.as_slice())),
        ] {
            if bytes as u64 > limit || bytes / 4 > u32::MAX as usize {
                return Err(ViewerError::TooLarge(format!(
                    "the field's {what} take {:.1} MB; {} binds at most {:.1} MB",
                    bytes as f64 / 1e6,
                    gpu.describe(),
                    limit.min(4 * u32::MAX as u64) as f64 / 1e6
                )));
            }
        }
        // Empty buffers cannot be bound: a scene without surfaces still gets one padding element.
        let nonempty = |bytes: &[u8], min: usize| {
            let mut v = bytes.to_vec();
            v.resize(v.len().max(min), 0);
            v
        };
        let mut renderer = gpu.checked(|| {
            let device = &gpu.device;
            let view = uniform_buffer(device, "view", std::mem::size_of::<ViewUniform>());
            let storage = |label, contents: &[u8]| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: &nonempty(contents, 256),
                    // Written again where objects move.
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                })
            };
            let surfaces = storage("surfaces", bytemuck::cast_slice(&surfaces));
            let polygon_vertices = storage("polygon vertices", bytemuck::cast_slice(&polygon_vertices));
            let nodes_buffer = storage("bvh nodes", bytemuck::cast_slice(&nodes));
            let primitives = storage("bvh primitives", bytemuck::cast_slice(&primitives));
            let pool = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("radiance pool"),
                size: (capacity as u64 * 12).max(256),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let parts = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("part table"),
                contents: &nonempty(bytemuck::cast_slice(&vec![NONE; table_len]), 256),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            });
            let rays = storage("mirror rays", bytemuck::cast_slice(&rays.words));
            let vertex_count = vertices.len() as u32;
            let vertices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("vertices"),
                contents: &nonempty(bytemuck::cast_slice(&vertices), 4),
                usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
            });
            let objects_uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("objects"),
                contents: bytemuck::bytes_of(&objects.uniform),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            });
            // As large as the pool where objects cast shadows per texel; a stub without objects.
            let shadow_pool = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("shadow pool"),
                size: match gatherer {
                    Some(_) => (capacity as u64 * if camera_shadows { 24 } else { 12 }).max(256),
                    None => 256,
                },
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let object_light = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("object light"),
                size: (moving.surfaces.len() as u64 * 12).max(256),
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            });
            let spheres = storage("object spheres", bytemuck::cast_slice(&moving.spheres));
            let directions = storage("gather directions", bytemuck::cast_slice(&objects.directions));
            let emitter_points = storage("emitter points", bytemuck::cast_slice(&emitters.points));
            let emitter_groups = storage("emitter groups", bytemuck::cast_slice(&emitters.groups));
            // Without objects, the field's shader alone (see `shaders/field.wgsl`).
            let (source, fragment) = match gatherer {
                Some(_) => (shader_source(&[]), "fs_objects"),
                None => (include_str!("shaders/field.wgsl").to_string(), "fs_main"),
            };
            let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("field"),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
            let bindings = [
                view.clone(),
                surfaces,
                pool.clone(),
                polygon_vertices,
                nodes_buffer,
                primitives,
                rays,
                parts.clone(),
                objects_uniform,
                spheres,
                directions,
                emitter_points,
                emitter_groups,
                shadow_pool,
                object_light,
            ];
            let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("field"),
                entries: &binding_layout(wgpu::ShaderStages::FRAGMENT),
            });
            let entries: Vec<wgpu::BindGroupEntry> = (bindings.iter().enumerate())
                .map(|(b, buffer)| bind_entry(b as u32, buffer))
                .collect();
            let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("field"),
                layout: &layout,
                entries: &entries,
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
                    entry_point: Some(fragment),
                    compilation_options: exact_direct_constant(direct.is_some()),
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
                pool,
                parts,
                capacity,
                catalog,
                bind_group,
                view,
                vertices,
                vertex_count,
                normalisation: scene.normalisation,
                bindings,
                objects: (counts, objects.geometry.clone()),
                objects_uniform: objects.uniform,
                texel_shadows: None,
                shadows_stale: Cell::new(true),
                shadows_mode: Cell::new(None),
                shadow_passes: Cell::new(0),
                direct,
            }
        })?;
        // The gather sees the objects' shadows per texel, or the shadows give back the objects'
        // light: their passes are needed from the start.
        if gatherer.is_some_and(|g| g.gather_shadows() || g.bounce_light()) {
            renderer.texel_shadows = Some(renderer.new_texel_shadows(gpu, field)?);
        }
        Ok(renderer)
    }

    /// Moves the objects to where `objects` have them: the same objects as the renderer was
    /// built with (the same surfaces, in the same order), at other poses. Takes effect at the
    /// next submission.
    pub fn move_objects(&self, gpu: &Gpu, objects: &[PlacedObject]) -> Result<(), ViewerError> {
        let (counts, layout) = &self.objects;
        let moved = ObjectGeometry::new(objects, counts);
        if !layout.same_layout(&moved) {
            return Err(ViewerError::Unsupported(format!(
                "{} objects of {} surfaces moved, but the view was built for {} of {}",
                moved.spheres.len(),
                moved.surfaces.len(),
                layout.spheres.len(),
                layout.surfaces.len()
            )));
        }
        let write = |buffer: &wgpu::Buffer, first: usize, item: usize, bytes: &[u8]| {
            if !bytes.is_empty() {
                gpu.queue.write_buffer(buffer, (first * item) as u64, bytes);
            }
        };
        let b = &self.bindings;
        write(
            &b[1],
            counts.surfaces,
            std::mem::size_of::<GpuSurface>(),
            bytemuck::cast_slice(&moved.surfaces),
        );
        write(
            &b[3],
            counts.polygon_vertices,
            16,
            bytemuck::cast_slice(&moved.polygon_vertices),
        );
        write(
            &b[4],
            counts.nodes,
            std::mem::size_of::<GpuNode>(),
            bytemuck::cast_slice(&moved.nodes),
        );
        write(&b[5], counts.primitives, 4, bytemuck::cast_slice(&moved.primitives));
        write(&b[9], 0, 16, bytemuck::cast_slice(&moved.spheres));
        write(
            &self.vertices,
            counts.vertices,
            std::mem::size_of::<Vertex>(),
            bytemuck::cast_slice(&moved.raster),
        );
        self.shadows_stale.set(true);
        Ok(())
    }

    /// Casts the objects' shadows per texel of the static charts from now on, rather than per
    /// fragment: computed for every resident texel when the objects move or parts arrive
    /// ([`crate::shadows`]), read bilinearly like the radiance. A walk whose objects stand
    /// still then pays nothing for their shadows, and a moving object pays per texel, not per
    /// pixel; the shadow is as sharp as the radiance maps (the field's own resolution), where
    /// per fragment it is as sharp as the pixels. A renderer without objects is left as it is.
    ///
    /// With exact direct light each texel holds two shadows: the gather's, which reads the
    /// maps and so loses direct light too, and the camera's, which leaves direct light to the
    /// shadow rays (those see the objects).
    pub fn shadows_per_texel(&mut self, gpu: &Gpu, field: &LightField) -> Result<(), ViewerError> {
        if self.objects_uniform.count == 0 || self.objects_uniform.shadow_texels == 1 {
            return Ok(());
        }
        if self.texel_shadows.is_none() {
            self.texel_shadows = Some(self.new_texel_shadows(gpu, field)?);
        }
        self.objects_uniform.shadow_texels = 1;
        gpu.queue
            .write_buffer(&self.bindings[8], 0, bytemuck::bytes_of(&self.objects_uniform));
        self.shadows_stale.set(true);
        Ok(())
    }

    fn new_texel_shadows(&self, gpu: &Gpu, field: &LightField) -> Result<TexelShadows, ViewerError> {
        let surfaces = self.objects.1.surfaces.len() as u32;
        TexelShadows::new(
            gpu,
            &self.bindings,
            field,
            surfaces,
            self.objects_uniform.bounce_light != 0,
            self.direct.is_some(),
        )
    }

    /// Records the pass computing the objects' shadows per texel into `encoder`, where they
    /// are out of date (objects moved, parts arrived, another mirror mode) and computed at all
    /// (drawn per texel, or seen by the gather).
    fn update_shadows(&self, gpu: &Gpu, encoder: &mut wgpu::CommandEncoder, mirrors: MirrorMode) {
        if let Some(shadows) = &self.texel_shadows
            && self.shadows_due(mirrors)
        {
            shadows.dispatch(gpu, encoder, mirrors);
            self.shadows_stale.set(false);
            self.shadows_mode.set(Some(mirrors));
            self.shadow_passes.set(self.shadow_passes.get() + 1);
        }
    }

    /// Whether the shadows per texel are out of date for `mirrors`.
    fn shadows_due(&self, mirrors: MirrorMode) -> bool {
        self.shadows_stale.get() || self.shadows_mode.get() != Some(mirrors)
    }

    /// Brings the objects' shadows per texel up to date for `mirrors` now (a draw does it
    /// itself; compute passes over the renderer's buffers, the gather's, call this first).
    /// Submits nothing where they are up to date.
    pub fn refresh_shadows(&self, gpu: &Gpu, mirrors: MirrorMode) -> Result<(), ViewerError> {
        if self.texel_shadows.is_none() || !self.shadows_due(mirrors) {
            return Ok(());
        }
        gpu.checked(|| {
            let mut encoder = gpu.device.create_command_encoder(&Default::default());
            self.update_shadows(gpu, &mut encoder, mirrors);
            gpu.queue.submit([encoder.finish()]);
        })
    }

    /// How many times the shadows per texel were computed so far: a pass costs `texels ×
    /// objects × K` rays, so tests hold it to the changes that need one.
    pub fn shadow_passes(&self) -> u64 {
        self.shadow_passes.get()
    }

    /// What every value of the pool loses to the objects' shadows, as last computed per texel
    /// (zeros before), as the gather reads it: for tests.
    pub fn texel_shadows(&self, gpu: &Gpu) -> Result<Vec<[f32; 3]>, ViewerError> {
        self.read_shadows(gpu, 0)
    }

    /// [`FieldRenderer::texel_shadows`] as the camera reads them with exact direct light
    /// (`Gatherer::shadow_loss_seen`), `None` without: for tests.
    pub fn texel_shadows_seen(&self, gpu: &Gpu) -> Result<Option<Vec<[f32; 3]>>, ViewerError> {
        match self.objects_uniform.camera_shadows {
            0 => Ok(None),
            _ => self.read_shadows(gpu, self.capacity as u64 * 12).map(Some),
        }
    }

    /// The pool's worth of shadows from byte `offset` of the shadow pool.
    fn read_shadows(&self, gpu: &Gpu, offset: u64) -> Result<Vec<[f32; 3]>, ViewerError> {
        let size = (self.capacity * 12) as u64;
        let readback = gpu.checked(|| {
            let readback = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("shadow readback"),
                size: size.max(4),
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let mut encoder = gpu.device.create_command_encoder(&Default::default());
            let available = self.bindings[13].size().saturating_sub(offset);
            encoder.copy_buffer_to_buffer(&self.bindings[13], offset, &readback, 0, size.min(available));
            gpu.queue.submit([encoder.finish()]);
            readback
        })?;
        gpu.read_mapped(&readback, |bytes| {
            bytemuck::cast_slice::<u8, [f32; 3]>(&bytes[..size as usize]).to_vec()
        })
    }

    /// The parts of the field, numbered as [`FieldRenderer::upload`] takes them.
    pub fn catalog(&self) -> &PartCatalog {
        &self.catalog
    }

    /// Where the direct parts of exact direct light are in the part table (numbers
    /// [`FieldRenderer::upload`] takes after the catalog's), `None` when it is off.
    pub fn direct_parts(&self) -> Option<DirectParts> {
        self.direct
    }

    /// Values of part `part` of the part table: a catalog part's, or a direct part's (its
    /// chunk's); `None` for a number beyond the table.
    pub fn part_len(&self, part: u32) -> Option<usize> {
        if (part as usize) < self.catalog.len() {
            return Some(self.catalog.values(part));
        }
        let chunk = self.direct?.chunk(part)?;
        Some(self.catalog.values(chunk))
    }

    /// RGB values the pool holds.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Puts part `part`'s `values` into the pool from value `base` on and makes it resident.
    /// Takes effect at the next submission, after the uploads and evictions before it: a part
    /// evicted and another uploaded where it was, in that order, leave the pool consistent.
    pub fn upload(&self, gpu: &Gpu, part: u32, base: usize, values: &[[f32; 3]]) -> Result<(), ViewerError> {
        let fits = base.checked_add(values.len()).is_some_and(|end| end <= self.capacity);
        if self.part_len(part) != Some(values.len()) || !fits {
            return Err(ViewerError::Unsupported(format!(
                "part {part} of {} values at {base} does not fit (catalog of {}, pool of {} values)",
                values.len(),
                self.catalog.len(),
                self.capacity
            )));
        }
        if !values.is_empty() {
            gpu.queue
                .write_buffer(&self.pool, base as u64 * 12, bytemuck::cast_slice(values));
        }
        gpu.queue
            .write_buffer(&self.parts, part as u64 * 4, bytemuck::bytes_of(&(base as u32)));
        if self.shadows_read(part) {
            self.shadows_stale.set(true);
        }
        Ok(())
    }

    /// Whether the shadows per texel read part `part`, so that its arrival makes them stale: a
    /// chunk's diffuse maps (its texels get shadows, and the radiance behind the objects is
    /// read from the maps), and a mirror tile while they were computed with mirrors from the
    /// rays. Not a direct part: the shadow passes read the maps as the gather does, never
    /// exact direct light's direct parts. Each pass costs `texels × objects × K` rays; one
    /// for every direct part or tile streamed in would be wasted.
    fn shadows_read(&self, part: u32) -> bool {
        if part as usize >= self.catalog.len() {
            return false;
        }
        match self.catalog.part(part) {
            vlf_core::parts::Part::Chunk(_) => true,
            vlf_core::parts::Part::Tile { .. } => !matches!(self.shadows_mode.get(), Some(MirrorMode::Trace { .. })),
        }
    }

    /// Makes part `part` non-resident (its place in the pool may be reused).
    pub fn evict(&self, gpu: &Gpu, part: u32) {
        if self.part_len(part).is_some() {
            gpu.queue
                .write_buffer(&self.parts, part as u64 * 4, bytemuck::bytes_of(&NONE));
        }
    }

    /// Where `camera` (scene units) sees the field from, mirrors drawn as `mirrors` says,
    /// and the image content shifted by `jitter` pixels (x right, y down): the rasteriser's
    /// sample at a pixel's centre `x + ½` then sees what the camera's ray through `x + ½ −
    /// jitter` sees.
    ///
    /// The projection is [`Camera::ray`]'s: forward, right and up from `look_at`, the vertical
    /// field of view and the image's aspect; depth is reversed and infinite.
    pub fn viewpoint(&self, camera: &Camera, jitter: (f64, f64), mirrors: MirrorMode) -> Viewpoint {
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
        Viewpoint {
            clip_from_vlf: (shift * projection * view).as_mat4(),
            eye: eye.as_vec3(),
            mirrors,
        }
    }

    /// Draws the field seen from `viewpoint` into `color` (cleared to black) with `depth`
    /// (cleared), both of the same size, in formats [`COLOR_FORMAT`] and [`DEPTH_FORMAT`].
    ///
    /// The viewpoint is written with `Queue::write_buffer`, which takes effect at the next
    /// submission: one draw per submitted encoder.
    pub fn draw(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        viewpoint: &Viewpoint,
        color: &wgpu::TextureView,
        depth: &wgpu::TextureView,
    ) {
        let uniform = ViewUniform {
            clip_from_vlf: viewpoint.clip_from_vlf.to_cols_array_2d(),
            eye: viewpoint.eye.extend(1.0).to_array(),
            depth: match viewpoint.mirrors {
                MirrorMode::Trace { depth } => depth,
                MirrorMode::Rays => 0,
            },
            mode: (viewpoint.mirrors == MirrorMode::Rays) as u32,
            direct_parts: self.direct.map_or(NONE, |d| d.first),
            _pad: 0,
        };
        gpu.queue.write_buffer(&self.view, 0, bytemuck::bytes_of(&uniform));
        // Before the view in the same submission: it reads them.
        self.update_shadows(gpu, encoder, viewpoint.mirrors);
        let depth = wgpu::RenderPassDepthStencilAttachment {
            view: depth,
            depth_ops: Some(wgpu::Operations {
                load: wgpu::LoadOp::Clear(0.0),
                store: wgpu::StoreOp::Discard,
            }),
            stencil_ops: None,
        };
        let mut pass = color_pass(
            encoder,
            "field",
            color,
            wgpu::LoadOp::Clear(wgpu::Color::BLACK),
            Some(depth),
        );
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.set_vertex_buffer(0, self.vertices.slice(..));
        pass.draw(0..self.vertex_count, 0..1);
    }
}
