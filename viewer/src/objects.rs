//! Dynamic objects on the GPU: what `shaders/objects.wgsl` reads to draw them, shade them by
//! the gather and cast their shadows, laid out from a [`Gatherer`] (the CPU reference it is
//! the twin of: the same objects, gather directions, shadow cells and emitter points).
//!
//! The objects' surfaces follow the static scene's in the surface and polygon-vertex arrays,
//! and one BVH over all of them follows the scene's nodes and primitives, its indices shifted
//! to point into the same arrays: the shader's one traversal (`trace_from`) serves both, from
//! two roots.

use crate::direct::EmitterBuffers;
use crate::field::{GpuNode, GpuSurface, Vertex};
use crate::rays::NONE;
use bytemuck::{Pod, Zeroable};
use glam::DVec3;
use vlf_core::dynamic::PlacedObject;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::render::Bvh;
use vlf_core::scene::{Normalisation, Scene};

/// `Objects` in `shaders/objects.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(crate) struct ObjectsUniform {
    first_surface: u32,
    root: u32,
    pub count: u32,
    directions: u32,
    shadow_cells: u32,
    emitter_groups: u32,
    /// 1 where static surfaces read their shadows per texel.
    pub shadow_texels: u32,
    /// 1 where gather rays see the objects' shadows (per texel).
    pub gather_shadows: u32,
    /// 1 where shadows give back the objects' own light.
    pub bounce_light: u32,
    /// Where the camera's shadows per texel start in the shadow pool, in floats (0: none; see
    /// `camera_shadows` in the shader).
    pub camera_shadows: u32,
    _pad: [u32; 2],
}

/// Where the static scene's arrays end: the objects' entries go after.
#[derive(Clone, Copy)]
pub(crate) struct StaticCounts {
    pub vertices: usize,
    pub surfaces: usize,
    pub polygon_vertices: usize,
    pub nodes: usize,
    pub primitives: usize,
}

/// Everything the objects add, ready to upload.
pub(crate) struct ObjectData {
    pub geometry: ObjectGeometry,
    pub uniform: ObjectsUniform,
    /// Per gather direction: unit vector and weight.
    pub directions: Vec<[f32; 4]>,
    /// The gatherer's emitter points, for the shadows.
    pub emitters: EmitterBuffers,
}

/// What moves with the objects: their surfaces, their BVH, their triangles for the rasteriser
/// and their bounding spheres.
#[derive(Clone)]
pub(crate) struct ObjectGeometry {
    pub surfaces: Vec<GpuSurface>,
    pub polygon_vertices: Vec<[f32; 4]>,
    pub nodes: Vec<GpuNode>,
    pub primitives: Vec<u32>,
    /// The objects' triangles for the rasteriser.
    pub raster: Vec<Vertex>,
    /// The BVH's root among all nodes, `NONE` without surfaces.
    pub root: u32,
    /// Per object: bounding sphere centre and radius.
    pub spheres: Vec<[f32; 4]>,
}

impl ObjectData {
    /// The layout of `gatherer`'s objects (none without one) after a static `scene` of
    /// `counts`.
    pub fn new(scene: &Scene, gatherer: Option<&Gatherer>, counts: StaticCounts) -> ObjectData {
        let objects = gatherer.map_or(&[][..], |g| g.objects());
        let geometry = ObjectGeometry::new(objects, &counts);
        let mut data = ObjectData {
            uniform: ObjectsUniform {
                first_surface: counts.surfaces as u32,
                root: geometry.root,
                count: objects.len() as u32,
                directions: 0,
                shadow_cells: 0,
                emitter_groups: 0,
                shadow_texels: 0,
                gather_shadows: gatherer.is_some_and(|g| g.gather_shadows()) as u32,
                bounce_light: gatherer.is_some_and(|g| g.bounce_light()) as u32,
                camera_shadows: 0,
                _pad: [0; 2],
            },
            geometry,
            directions: Vec::new(),
            emitters: EmitterBuffers::default(),
        };
        let Some(gatherer) = gatherer else {
            return data;
        };
        let set = gatherer.directions();
        data.directions = (0..set.len())
            .map(|d| {
                let direction = set.get(d);
                direction.vector.as_vec3().extend(direction.weight as f32).to_array()
            })
            .collect();
        data.uniform.directions = set.len() as u32;
        data.uniform.shadow_cells = gatherer.shadow_samples();
        data.emitters = EmitterBuffers::new(scene, gatherer.emitters());
        data.uniform.emitter_groups = data.emitters.group_count();
        data
    }
}

impl ObjectGeometry {
    /// The surfaces, BVH, triangles and spheres of `objects` after a static scene of `counts`.
    /// The node array always holds `2·surfaces` entries (a BVH over P primitives has at most
    /// 2P − 1 nodes; unused ones are zero): objects moved to other poses get BVHs of other
    /// shapes, written over the same buffers ([`crate::FieldRenderer::move_objects`]).
    pub fn new(objects: &[PlacedObject], counts: &StaticCounts) -> ObjectGeometry {
        let first_surface = counts.surfaces as u32;
        let mut geometry = ObjectGeometry {
            surfaces: Vec::new(),
            polygon_vertices: Vec::new(),
            nodes: Vec::new(),
            primitives: Vec::new(),
            raster: Vec::new(),
            root: NONE,
            spheres: objects
                .iter()
                .map(|o| o.center.as_vec3().extend(o.radius as f32).to_array())
                .collect(),
        };
        for o in objects {
            for surface in &o.scene.surfaces {
                let material = &o.scene.materials[surface.material];
                let index = first_surface + geometry.surfaces.len() as u32;
                geometry.surfaces.push(GpuSurface {
                    first_vertex: (counts.polygon_vertices + geometry.polygon_vertices.len()) as u32,
                    vertex_count: surface.vertices.len() as u32,
                    ..GpuSurface::object(surface.normal, surface.offset, material)
                });
                geometry
                    .polygon_vertices
                    .extend(surface.vertices.iter().map(|v| v.as_vec3().extend(0.0).to_array()));
                for k in 1..surface.vertices.len().saturating_sub(1) {
                    for v in [surface.vertices[0], surface.vertices[k], surface.vertices[k + 1]] {
                        geometry.raster.push(Vertex {
                            position: v.as_vec3().to_array(),
                            texel: [0.0; 2],
                            surface: index,
                        });
                    }
                }
            }
        }
        let all = Scene {
            surfaces: objects.iter().flat_map(|o| o.scene.surfaces.iter().cloned()).collect(),
            materials: Vec::new(),
            normalisation: Normalisation {
                center: DVec3::ZERO,
                scale: 1.0,
            },
            textures: Vec::new(),
        };
        if !all.surfaces.is_empty() {
            let bvh = Bvh::build(&all);
            let (first_node, first_primitive) = (counts.nodes as u32, counts.primitives as u32);
            geometry.nodes = (bvh.nodes().iter())
                .map(|n| GpuNode {
                    min: n.min,
                    max: n.max,
                    index: n.index + if n.count > 0 { first_primitive } else { first_node },
                    count: n.count,
                })
                .collect();
            geometry.nodes.resize(2 * all.surfaces.len(), GpuNode::zeroed());
            geometry.primitives = bvh.primitives().iter().map(|&p| p + first_surface).collect();
            geometry.root = first_node;
        }
        geometry
    }

    /// Whether `other` fits the buffers laid out for `self`: the same surfaces, polygons and
    /// triangles (objects moved, not changed).
    pub fn same_layout(&self, other: &ObjectGeometry) -> bool {
        self.surfaces.len() == other.surfaces.len()
            && self.polygon_vertices.len() == other.polygon_vertices.len()
            && self.nodes.len() == other.nodes.len()
            && self.primitives.len() == other.primitives.len()
            && self.raster.len() == other.raster.len()
            && self.spheres.len() == other.spheres.len()
    }
}
