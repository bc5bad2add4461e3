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
//! CPU reference's way. Gather rays read these shadows too (`Gatherer::with_gather_shadows`).
//!
//! Where the shadows give back the objects' own light (`Gatherer::with_bounce_light`), the
//! pass runs in three steps, as `Gatherer::prepared` does on the CPU: the texels' shadows
//! without the objects' light, the objects' light gathered at each of their surfaces
//! (`object_light_main`, seeing those shadows), then the texels' shadows with it.

use crate::field::{BINDINGS, FieldCompute};
use crate::pass::{READ_ONLY, uniform_buffer};
use crate::{Gpu, MirrorMode, ViewerError};
use vlf_core::field::LightField;
use wgpu::util::DeviceExt;

/// Texels per work item (`@workgroup_size` of `shadow_texels_main`).
const WORKGROUP: u32 = 64;
/// Workgroups along x per row of the dispatch (the shader's `65535u`).
const ROW: u32 = 65535;

/// The compute pass over a renderer's buffers (see the module docs).
pub(crate) struct TexelShadows {
    texels: wgpu::ComputePipeline,
    object_light: wgpu::ComputePipeline,
    /// Bound with `TexelParams` without the objects' light given back, and with it.
    first: wgpu::BindGroup,
    last: wgpu::BindGroup,
    params: [wgpu::Buffer; 2],
    items: u32,
    /// The objects' surfaces, and whether the shadows give back their light.
    object_surfaces: u32,
    bounce: bool,
}

impl TexelShadows {
    /// The pass over the field bound by `bindings` (a renderer's, with objects), whose static
    /// scene and charts are `field`'s.
    pub(crate) fn new(
        gpu: &Gpu,
        bindings: &[wgpu::Buffer; BINDINGS],
        field: &LightField,
        object_surfaces: u32,
        bounce: bool,
        exact: bool,
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
            let compute = FieldCompute::new(
                device,
                "shadow texels",
                include_str!("shaders/shadow_texels.wgsl"),
                &[READ_ONLY, wgpu::BufferBindingType::Uniform],
                exact,
            );
            let work = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("texel work"),
                contents: bytemuck::cast_slice(&work),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let params = [0, 1].map(|_| uniform_buffer(device, "texel params", 16));
            TexelShadows {
                texels: compute.pipeline(device, "shadow_texels_main"),
                object_light: compute.pipeline(device, "object_light_main"),
                first: compute.bind_group(device, bindings, &[&work, &params[0]]),
                last: compute.bind_group(device, bindings, &[&work, &params[1]]),
                params,
                items,
                object_surfaces,
                bounce,
            }
        })
    }

    /// Records the passes into `encoder`, mirrors behind the objects read as `mirrors` says
    /// (as the view draws them): the texels' shadows, and where the shadows give back the
    /// objects' light, that light and the texels' shadows again (see the module docs). The
    /// parameters are written with `Queue::write_buffer`: one call per submission.
    pub(crate) fn dispatch(&self, gpu: &Gpu, encoder: &mut wgpu::CommandEncoder, mirrors: MirrorMode) {
        let (mode, depth) = match mirrors {
            MirrorMode::Rays => (1u32, 0u32),
            MirrorMode::Trace { depth } => (0, depth),
        };
        for (params, bounce) in self.params.iter().zip([0, self.bounce as u32]) {
            gpu.queue.write_buffer(
                params,
                0,
                bytemuck::cast_slice(&[mode, depth, bounce, self.object_surfaces]),
            );
        }
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("shadow texels"),
            timestamp_writes: None,
        });
        let texels = |pass: &mut wgpu::ComputePass, group: &wgpu::BindGroup| {
            if self.items > 0 {
                pass.set_pipeline(&self.texels);
                pass.set_bind_group(0, group, &[]);
                pass.dispatch_workgroups(self.items.min(ROW), self.items.div_ceil(ROW), 1);
            }
        };
        if self.bounce && self.object_surfaces > 0 {
            texels(&mut pass, &self.first);
            pass.set_pipeline(&self.object_light);
            pass.set_bind_group(0, &self.first, &[]);
            pass.dispatch_workgroups(self.object_surfaces.div_ceil(WORKGROUP), 1, 1);
        }
        texels(&mut pass, &self.last);
    }
}
