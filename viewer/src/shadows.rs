//! The objects' shadows per texel: a compute pass that writes, for every texel of the resident
//! static charts, the radiance it loses to the dynamic objects (`shadow_loss` at the texel's
//! centre, `shaders/shadow_texels.wgsl`) into a pool beside the radiance pool, where the view
//! reads it bilinearly (`shadow_from_texels` in `shaders/objects.wgsl`).
//!
//! Per fragment, a view pays `pixels × objects × K` shadow rays every frame; per texel it pays
//! `texels × objects × K` only when the objects move or parts arrive
//! ([`crate::FieldRenderer::shadows_per_texel`]), and nothing while they stand still. The
//! shadow is then as sharp as the field's radiance maps rather than the pixels: what the
//! field itself resolves. `vlf view` shadows per texel; `vlf render --gpu` per fragment, the
//! CPU reference's way.

use crate::field::{BINDINGS, binding_layout, shader_source};
use crate::pass::{READ_ONLY, bind_entry, buffer_entry, uniform_buffer};
use crate::{Gpu, MirrorMode, ViewerError};
use vlf_core::field::LightField;
use wgpu::util::DeviceExt;

/// Texels per work item (`@workgroup_size` of `shadow_texels_main`).
const WORKGROUP: u32 = 64;
/// Workgroups along x per row of the dispatch (the shader's `65535u`).
const ROW: u32 = 65535;

/// The compute pass over a renderer's buffers (see the module docs).
pub(crate) struct TexelShadows {
    pipeline: wgpu::ComputePipeline,
    bind_group: wgpu::BindGroup,
    /// How mirrors are read behind the objects (`TexelParams`).
    params: wgpu::Buffer,
    items: u32,
}

impl TexelShadows {
    /// The pass over the field bound by `bindings` (a renderer's, with objects), whose static
    /// scene and charts are `field`'s.
    pub(crate) fn new(
        gpu: &Gpu,
        bindings: &[wgpu::Buffer; BINDINGS],
        field: &LightField,
    ) -> Result<TexelShadows, ViewerError> {
        // A work item per 64 texels of each static chart with a diffuse reflectance, for the
        // first of its surfaces (a chart's surfaces share its plane and material).
        let mut work: Vec<[u32; 2]> = Vec::new();
        let mut charted = vec![false; field.atlas.charts.len()];
        for (i, _) in field.scene.surfaces.iter().enumerate() {
            let chart = field.atlas.chart_of[i] as usize;
            if charted[chart] || field.scene.material(i).diffuse.iter().all(|&c| c <= 0.0) {
                continue;
            }
            charted[chart] = true;
            let grid = field.atlas.grid(i);
            let texels = grid.width * grid.height;
            work.extend((0..texels.div_ceil(WORKGROUP)).map(|k| [i as u32, k * WORKGROUP]));
        }
        let items = u32::try_from(work.len())
            .ok()
            .filter(|&n| n.div_ceil(ROW) <= gpu.limits.max_compute_workgroups_per_dimension)
            .ok_or_else(|| ViewerError::TooLarge(format!("{} texel work items in one dispatch", work.len())))?;
        if work.is_empty() {
            work.push([0, u32::MAX]);
        }
        gpu.checked(|| {
            let device = &gpu.device;
            let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("shadow texels"),
                source: wgpu::ShaderSource::Wgsl(shader_source(&[include_str!("shaders/shadow_texels.wgsl")]).into()),
            });
            let compute = wgpu::ShaderStages::COMPUTE;
            let mut entries = binding_layout(compute);
            entries.push(buffer_entry(14, compute, READ_ONLY));
            entries.push(buffer_entry(15, compute, wgpu::BufferBindingType::Uniform));
            let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("shadow texels"),
                entries: &entries,
            });
            let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("shadow texels"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
            let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("shadow texels"),
                layout: Some(&pipeline_layout),
                module: &shader,
                entry_point: Some("shadow_texels_main"),
                compilation_options: Default::default(),
                cache: None,
            });
            let work = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("texel work"),
                contents: bytemuck::cast_slice(&work),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let mut entries: Vec<wgpu::BindGroupEntry> = (bindings.iter().enumerate())
                .map(|(b, buffer)| bind_entry(b as u32, buffer))
                .collect();
            let params = uniform_buffer(device, "texel params", 16);
            entries.push(bind_entry(14, &work));
            entries.push(bind_entry(15, &params));
            let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("shadow texels"),
                layout: &layout,
                entries: &entries,
            });
            TexelShadows {
                pipeline,
                bind_group,
                params,
                items,
            }
        })
    }

    /// Records the pass into `encoder`, mirrors behind the objects read as `mirrors` says (as
    /// the view draws them). Its mode is written with `Queue::write_buffer`: one pass per
    /// submission.
    pub(crate) fn dispatch(&self, gpu: &Gpu, encoder: &mut wgpu::CommandEncoder, mirrors: MirrorMode) {
        if self.items == 0 {
            return;
        }
        let (mode, depth) = match mirrors {
            MirrorMode::Rays => (1u32, 0u32),
            MirrorMode::Trace { depth } => (0, depth),
        };
        gpu.queue
            .write_buffer(&self.params, 0, bytemuck::cast_slice(&[mode, depth, 0, 0]));
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("shadow texels"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.dispatch_workgroups(self.items.min(ROW), self.items.div_ceil(ROW), 1);
    }
}
