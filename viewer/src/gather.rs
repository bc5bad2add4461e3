//! The gather on the GPU: the light arriving at points of dynamic objects, one compute
//! invocation per point (`shaders/gather.wgsl`), the GPU twin of
//! [`vlf_core::dynamic::gather::Gatherer::incident`] and tested against it.
//!
//! It runs over a [`FieldRenderer`] built [`FieldRenderer::with_objects`]: the field's
//! surfaces, radiance pool, mirror tables and BVH, with the objects' surfaces and BVH after the
//! scene's (`objects.rs`), so the shader traces the static scene and the objects with one
//! traversal from two roots, over the gatherer's directions. Drawing a view with objects does
//! the same per fragment (`shaders/objects.wgsl`); this pass computes it at given points, for
//! tests, benchmarks and per-vertex shading.

use crate::field::FieldCompute;
use crate::pass::{READ_ONLY, uniform_buffer};
use crate::{FieldRenderer, Gpu, MirrorMode, ViewerError};
use bytemuck::{Pod, Zeroable};
use glam::DVec3;
use vlf_core::scene::Rgb;
use wgpu::util::DeviceExt;

/// Invocations per workgroup (`@workgroup_size` of `gather_main`).
const WORKGROUP: u32 = 64;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    points: u32,
    mode: u32,
    depth: u32,
    _pad: u32,
}

/// A compute pipeline gathering light from a field at points of its dynamic objects.
///
/// It borrows the renderer: the gather may read the objects' shadows per texel, which each
/// run brings up to date first (objects moved with [`FieldRenderer::move_objects`], parts
/// arrived), as a draw does.
pub struct GpuGather<'a> {
    pipeline: wgpu::ComputePipeline,
    shadows: wgpu::ComputePipeline,
    compute: FieldCompute,
    field: &'a FieldRenderer,
    mirrors: MirrorMode,
}

impl<'a> GpuGather<'a> {
    /// A gather over `field`'s renderer (built [`FieldRenderer::with_objects`]: its objects,
    /// directions and emitters), mirrors read as `mirrors` says.
    pub fn new(gpu: &Gpu, field: &'a FieldRenderer, mirrors: MirrorMode) -> Result<GpuGather<'a>, ViewerError> {
        gpu.checked(|| {
            let device = &gpu.device;
            let compute = FieldCompute::new(
                device,
                "gather",
                include_str!("shaders/gather.wgsl"),
                &[
                    wgpu::BufferBindingType::Uniform,
                    READ_ONLY,
                    wgpu::BufferBindingType::Storage { read_only: false },
                ],
                field.direct_parts().is_some(),
            );
            GpuGather {
                pipeline: compute.pipeline(device, "gather_main"),
                shadows: compute.pipeline(device, "shadow_main"),
                compute,
                field,
                mirrors,
            }
        })
    }

    /// The cosine-weighted mean radiance arriving at each `(point, normal)` (VLF frame) over
    /// the hemisphere of its normal: what [`vlf_core::dynamic::gather::Gatherer::incident`]
    /// gives on the CPU, in f32.
    pub fn incident(&self, gpu: &Gpu, points: &[(DVec3, DVec3)]) -> Result<Vec<Rgb>, ViewerError> {
        let points: Vec<(DVec3, DVec3, Rgb)> = points.iter().map(|&(p, n)| (p, n, [0.0; 3])).collect();
        let values = self.run(gpu, &self.pipeline, &points)?;
        Ok(values.into_iter().map(|(l, _)| l).collect())
    }

    /// The radiance each static diffuse point `(point, normal, reflectance)` loses to the
    /// objects, or `None` where they take nothing from it: what
    /// [`vlf_core::dynamic::gather::Gatherer::shadow_loss`] gives on the CPU, in f32.
    pub fn shadow_loss(&self, gpu: &Gpu, points: &[(DVec3, DVec3, Rgb)]) -> Result<Vec<Option<Rgb>>, ViewerError> {
        let values = self.run(gpu, &self.shadows, points)?;
        Ok(values.into_iter().map(|(l, any)| any.then_some(l)).collect())
    }

    /// Runs `pipeline` over `points`: its output per point, and whether its flag is set.
    fn run(
        &self,
        gpu: &Gpu,
        pipeline: &wgpu::ComputePipeline,
        points: &[(DVec3, DVec3, Rgb)],
    ) -> Result<Vec<(Rgb, bool)>, ViewerError> {
        if points.is_empty() {
            return Ok(Vec::new());
        }
        // The gather may read the objects' shadows per texel: up to date for the objects'
        // poses now, not those when the pipeline was made.
        self.field.refresh_shadows(gpu, self.mirrors)?;
        let count = u32::try_from(points.len())
            .ok()
            .filter(|&n| n.div_ceil(WORKGROUP) <= gpu.limits.max_compute_workgroups_per_dimension)
            .ok_or_else(|| ViewerError::TooLarge(format!("{} gather points in one dispatch", points.len())))?;
        let packed: Vec<[f32; 4]> = points
            .iter()
            .flat_map(|&(p, n, rho)| {
                [
                    p.as_vec3().extend(0.0).to_array(),
                    n.as_vec3().extend(0.0).to_array(),
                    [rho[0] as f32, rho[1] as f32, rho[2] as f32, 0.0],
                ]
            })
            .collect();
        let bytes = points.len() as u64 * 16;
        let readback = gpu.checked(|| {
            let device = &gpu.device;
            let params = uniform_buffer(device, "gather params", std::mem::size_of::<Params>());
            let (mode, depth) = match self.mirrors {
                MirrorMode::Rays => (1, 0),
                MirrorMode::Trace { depth } => (0, depth),
            };
            gpu.queue.write_buffer(
                &params,
                0,
                bytemuck::bytes_of(&Params {
                    points: count,
                    mode,
                    depth,
                    _pad: 0,
                }),
            );
            let input = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("gather points"),
                contents: bytemuck::cast_slice(&packed),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let output = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("gathered"),
                size: bytes,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let readback = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("gathered readback"),
                size: bytes,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let bind_group = self
                .compute
                .bind_group(device, &self.field.bindings, &[&params, &input, &output]);
            let mut encoder = device.create_command_encoder(&Default::default());
            {
                let mut pass = encoder.begin_compute_pass(&Default::default());
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, &bind_group, &[]);
                pass.dispatch_workgroups(count.div_ceil(WORKGROUP), 1, 1);
            }
            encoder.copy_buffer_to_buffer(&output, 0, &readback, 0, bytes);
            gpu.queue.submit([encoder.finish()]);
            readback
        })?;
        let values = gpu.read_mapped(&readback, |bytes| {
            let floats: &[f32] = bytemuck::cast_slice(bytes);
            floats
                .chunks_exact(4)
                .map(|v| ([v[0] as f64, v[1] as f64, v[2] as f64], v[3] != 0.0))
                .collect::<Vec<(Rgb, bool)>>()
        })?;
        Ok(values)
    }
}
