//! Look-ups: the radiance leaving a surface point towards a viewer, read from
//! a propagated [`LightField`], and the CPU renderer built on them.
//!
//! * Diffuse surfaces (and emitters): their radiance maps, bilinear
//!   ([`LightField::radiance_at`]).
//! * Mirrors, two ways ([`SpecularMode`]):
//!   - **from the rays** (the light field proper): the outgoing direction `v`
//!     lies in a spherical triangle of three directions with barycentric
//!     weights `b_k`; in each direction's subfield the point falls between
//!     four rays, whose mirror radiance is interpolated bilinearly; the three
//!     are blended by `b_k`. No searching but finding the mirror in a tile's
//!     short list. Blurry where directions are sparse, but constant time. On
//!     a curved mirror, whose triangles are mostly smaller than a ray cell, a
//!     ray that misses the triangle's plane is read where it crosses a
//!     neighbouring triangle ([`LightField::mirror_slot`]);
//!   - **ray traced**: reflect the eye ray until it meets a diffuse surface
//!     and read its map (sharp reflections; cost grows with depth).

use crate::field::LightField;
use crate::propagate::specular::MirrorLayout;
use crate::psf::{Subfield, SurfaceProjection};
use crate::render::{Bvh, Camera, Hit, Image};
use crate::scene::Rgb;
use glam::DVec3;
use serde::{Deserialize, Serialize};

/// How mirrors are shaded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum SpecularMode {
    /// From the field's directional radiance maps (the paper's section 6.1).
    Rays,
    /// Recursive reflection through the scene, at most `depth` mirrors deep
    /// (the paper's section 6.3).
    Trace { depth: u32 },
}

/// One ray read by a look-up from the rays (see [`LightField::mirror_rays`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayRead {
    /// Which vertex of the spherical triangle (0..3).
    pub vertex: usize,
    /// Its line direction.
    pub direction: usize,
    /// The vertex's barycentric weight.
    pub barycentric: f64,
    /// The ray's bilinear weight in the subfield.
    pub bilinear: f64,
    /// The tile holding the ray (row-major over the subfield's tiles).
    pub tile: u32,
    /// The ray's mirror slot in the direction's maps.
    pub slot: u32,
}

/// What a view reads from a field ([`LightField::view_needs`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ViewNeeds {
    /// Surfaces whose diffuse map is read.
    pub surfaces: std::collections::BTreeSet<u32>,
    /// Mirror tiles read, as (line direction, tile index).
    pub mirror_tiles: std::collections::BTreeSet<(u32, u32)>,
    /// How much each mirror tile makes of the image: the sum over the view's samples of the
    /// weights (barycentric × bilinear) its rays get. A streaming viewer fetches the heaviest
    /// first: the directions nearest to the visible mirrors' reflections.
    pub tile_weight: std::collections::BTreeMap<(u32, u32), f64>,
}

impl ViewNeeds {
    /// Both needs together (while `view_needs` gathers them: the tiles are the weights' keys).
    pub fn merged(mut self, other: ViewNeeds) -> ViewNeeds {
        self.surfaces.extend(other.surfaces);
        for (tile, w) in other.tile_weight {
            *self.tile_weight.entry(tile).or_default() += w;
        }
        self
    }
}

/// Offset along the normal for secondary rays (VLF frame: the scene spans 2).
const RAY_EPSILON: f64 = 1e-7;

/// How far along a ray, in ray spacings, a neighbouring mirror's crossing may lie from the
/// looked-up polygon's plane and still stand for it ([`LightField::mirror_slot`]). A ray read
/// by a look-up passes within √2 spacings of the point, so on the same smooth sheet of the
/// surface, not seen too obliquely, the two crossings lie about that close; another part of
/// the object along the ray (the far side of a fold, a claw behind) lies further. Chosen on the
/// mirror dragon: 1 and 4 spacings gave images alike (2-core VM, l = 513, N = 64).
pub const NEIGHBOUR_DEPTH_CELLS: f64 = 2.0;
/// The least cosine between the normals of a looked-up mirror polygon and a neighbour that
/// stands for it ([`LightField::mirror_slot`]): 60°.
pub const NEIGHBOUR_ANGLE_COS: f64 = 0.5;

impl LightField {
    /// Radiance leaving mirror `surface` at `p` (VLF frame) along unit
    /// direction `outgoing`, from the directional maps. Zero if the field has
    /// no mirror maps or no ray of the three directions meets `p`.
    pub fn mirror_radiance_from_rays(&self, surface: usize, p: DVec3, outgoing: DVec3) -> Rgb {
        let Some(spec) = &self.specular else {
            return [0.0; 3];
        };
        // Per vertex of the triangle: Σ w·total over its rays, Σ w, and its weight b.
        let mut value = [[0.0f64; 3]; 3];
        let mut w_sum = [0.0f64; 3];
        let mut b = [0.0f64; 3];
        self.mirror_rays(surface, p, outgoing, |r| {
            let t = spec.totals[r.direction][r.slot as usize];
            for c in 0..3 {
                value[r.vertex][c] += t[c] as f64 * r.bilinear;
            }
            w_sum[r.vertex] += r.bilinear;
            b[r.vertex] = r.barycentric;
        });
        let mut out = [0.0; 3];
        let mut weight = 0.0;
        for v in 0..3 {
            if w_sum[v] > 0.0 {
                for c in 0..3 {
                    out[c] += value[v][c] / w_sum[v] * b[v];
                }
                weight += b[v];
            }
        }
        if weight > 0.0 {
            for v in &mut out {
                *v /= weight;
            }
        }
        out
    }

    /// Visits, in order, every ray a look-up from the rays reads (see the module docs): for each
    /// direction of the spherical triangle around `outgoing` with a positive weight, each of the
    /// four rays around `p`'s projection with a positive bilinear weight that crosses mirror
    /// `surface`. What [`LightField::mirror_radiance_from_rays`] blends, and what a viewer that
    /// streams the field must have fetched ([`LightField::view_needs`]).
    pub fn mirror_rays(&self, surface: usize, p: DVec3, outgoing: DVec3, mut visit: impl FnMut(RayRead)) {
        let Some(spec) = &self.specular else {
            return;
        };
        let tri = spec.directions.triangle(outgoing);
        for (vertex, (o, b)) in tri.vertices.iter().zip(tri.weights).enumerate() {
            if b <= 0.0 {
                continue;
            }
            let d = o.index as usize;
            let (sub, layout) = (&spec.views[d].sub, &spec.views[d].layout);
            let n = sub.grid.resolution;
            // Bilinear between the four rays around p's projection.
            let g = sub.frame.to_grid(p, n) - 0.5;
            let (x0, y0) = (g.x.floor(), g.y.floor());
            let (fx, fy) = (g.x - x0, g.y - y0);
            for (dx, dy, w) in [
                (0.0, 0.0, (1.0 - fx) * (1.0 - fy)),
                (1.0, 0.0, fx * (1.0 - fy)),
                (0.0, 1.0, (1.0 - fx) * fy),
                (1.0, 1.0, fx * fy),
            ] {
                let (x, y) = (x0 + dx, y0 + dy);
                if w <= 0.0 || x < 0.0 || y < 0.0 {
                    continue;
                }
                let (x, y) = (x as u32, y as u32);
                if let Some(slot) = self.mirror_slot(sub, layout, surface as u32, x, y) {
                    let m = sub.grid.tile;
                    visit(RayRead {
                        vertex,
                        direction: d,
                        barycentric: b,
                        bilinear: w,
                        tile: (y / m) * sub.grid.tiles_per_side() + x / m,
                        slot,
                    });
                }
            }
        }
    }

    /// The mirror slot that stands for ray `(x, y)` of subfield `sub` (its mirror layout
    /// `layout`) in a look-up on mirror polygon `surface`: where the ray crosses the polygon's
    /// plane, that crossing ([`MirrorLayout::locate_on_plane`]); else the ray's crossing of a
    /// *neighbouring* mirror, if one lies close by.
    ///
    /// **Why neighbours.** A look-up reads the four rays around its point. On a plane mirror
    /// they cross the plane wherever the point is inside it. A curved mirror, though, is many
    /// small planes (a scanned chrome object: triangles far smaller than a ray cell), and the
    /// four rays mostly cross *other* triangles of it than the one hit: read on its own plane
    /// only, such a mirror came out black but for the few triangles a ray happens to cross.
    /// The radiance leaving a smooth mirror along a direction varies smoothly over it, so the
    /// ray's crossing of the neighbouring triangle is as good a sample of it as any ray a cell
    /// away on a plane: the bilinear interpolation then reads the surface, not the polygon.
    ///
    /// **Which neighbour.** Of the mirror surfaces the ray crosses, one that
    /// - faces the same side of the line as the polygon (its slot holds light leaving along
    ///   the same oriented direction),
    /// - has a normal within [`NEIGHBOUR_ANGLE_COS`] of the polygon's (a fold or a corner of
    ///   the mirror is not a neighbour: the two planes of a mirrored corner keep their own
    ///   rays, as before; facets less than 60° apart, though, read each other's rays near their
    ///   shared edge), and
    /// - crosses the ray within [`NEIGHBOUR_DEPTH_CELLS`] ray spacings of where the polygon's
    ///   plane does (the same sheet of the surface, not another part of the object behind);
    ///
    /// the nearest such crossing, the lower surface on a tie. The viewer's shader applies the
    /// same rule, in `f32`, to every ray's list of crossings (`viewer/src/rays.rs`,
    /// `mirror_slot` in `field.wgsl`), with these constants from its tables' header.
    pub fn mirror_slot(&self, sub: &Subfield, layout: &MirrorLayout, surface: u32, x: u32, y: u32) -> Option<u32> {
        if let Some(slot) = layout.locate_on_plane(sub, &self.atlas.plane_rep, surface, x, y) {
            return Some(slot);
        }
        let surfaces = &self.scene.surfaces;
        let polygon = surfaces.get(surface as usize)?;
        let rep = self.atlas.plane_rep.get(surface as usize).copied().unwrap_or(surface);
        let w = sub.frame.w;
        let side = w.dot(polygon.normal);
        let n = sub.grid.resolution;
        let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
        let depth_on =
            |s: &crate::scene::Surface| SurfaceProjection::new(&sub.frame, n, s.normal, s.offset).depth_at(cx, cy);
        let here = depth_on(polygon);
        let reach = NEIGHBOUR_DEPTH_CELLS * 2.0 / n as f64;
        // The nearest, then the lower surface (as the shader, which lists crossings otherwise).
        let mut best: Option<(f64, u32, u32)> = None;
        for (entry, offset) in sub.entries_at(x, y, |entry| layout.slot(entry, 0).is_some()) {
            let other = sub.entries[entry].surface;
            let (Some(slot), Some(s)) = (layout.slot(entry, offset), surfaces.get(other as usize)) else {
                continue;
            };
            if other == rep || s.normal.dot(w) * side <= 0.0 || s.normal.dot(polygon.normal) < NEIGHBOUR_ANGLE_COS {
                continue;
            }
            let distance = (depth_on(s) - here).abs();
            if distance <= reach && best.is_none_or(|(d, o, _)| (distance, other) < (d, o)) {
                best = Some((distance, other, slot));
            }
        }
        best.map(|(_, _, slot)| slot)
    }

    /// What drawing `camera`'s view with `samples_per_axis²` samples per pixel reads from this
    /// field: the diffuse maps of the surfaces seen (directly, or through mirrors when traced)
    /// and, from the rays, the mirror tiles. Everything else can stay unfetched: a field holding
    /// just these renders the view with the same bits.
    pub fn view_needs(&self, camera: &Camera, samples_per_axis: u32, mode: SpecularMode) -> ViewNeeds {
        use rayon::prelude::*;
        let bvh = Bvh::build(&self.scene);
        let n = samples_per_axis.max(1);
        let normalisation = self.scene.normalisation;
        // Row by row in parallel, each worker filling its own lists, merged at the end.
        let mut needs = (0..camera.height)
            .into_par_iter()
            .fold(ViewNeeds::default, |mut needs, y| {
                for x in 0..camera.width {
                    crate::render::pixel_rays(camera, &normalisation, n, x, y, |origin, dir| {
                        if let Some(hit) = bvh.intersect(&self.scene, origin, dir, 0.0, f64::INFINITY) {
                            self.needs_of(&bvh, &hit, dir, mode, &mut needs);
                        }
                    });
                }
                needs
            })
            .reduce(ViewNeeds::default, ViewNeeds::merged);
        needs.mirror_tiles = needs.tile_weight.keys().copied().collect();
        needs
    }

    /// Adds to `needs` what shading the first static surface along the ray from `origin` along
    /// unit `dir` reads (nothing when the ray leaves the scene or meets a back face): what a
    /// gather ray, or a shadow cell's ray behind an object, reads (`dynamic::needs`).
    pub fn needs_along(&self, bvh: &Bvh, origin: DVec3, dir: DVec3, mode: SpecularMode, needs: &mut ViewNeeds) {
        if let Some(hit) = bvh.intersect(&self.scene, origin, dir, 0.0, f64::INFINITY) {
            self.needs_of(bvh, &hit, dir, mode, needs);
        }
    }

    /// What [`LightField::shade`] reads for `hit`.
    fn needs_of(&self, bvh: &Bvh, hit: &Hit, dir: DVec3, mode: SpecularMode, needs: &mut ViewNeeds) {
        if !hit.front {
            return;
        }
        needs.surfaces.insert(hit.surface as u32);
        if !self.scene.material(hit.surface).is_mirror() {
            return;
        }
        match mode {
            // The tiles themselves are the weights' keys (filled in by `view_needs`).
            SpecularMode::Rays => self.mirror_rays(hit.surface, hit.point, -dir, |r| {
                *needs.tile_weight.entry((r.direction as u32, r.tile)).or_default() += r.barycentric * r.bilinear;
            }),
            SpecularMode::Trace { depth: 0 } => {}
            SpecularMode::Trace { depth } => {
                let n = self.scene.surfaces[hit.surface].normal;
                let reflected = dir - 2.0 * dir.dot(n) * n;
                let origin = hit.point + n * RAY_EPSILON;
                if let Some(next) = bvh.intersect(&self.scene, origin, reflected, RAY_EPSILON, f64::INFINITY) {
                    self.needs_of(bvh, &next, reflected, SpecularMode::Trace { depth: depth - 1 }, needs);
                }
            }
        }
    }

    /// Radiance arriving at `origin` from direction `-dir` (i.e. seen looking
    /// along `dir`), by tracing through mirrors at most `depth` deep.
    pub fn traced_radiance(&self, bvh: &Bvh, origin: DVec3, dir: DVec3, depth: u32) -> Rgb {
        self.traced_by(bvh, origin, dir, depth, &|surface, p| {
            self.diffuse_radiance_at(bvh, surface, p)
        })
    }

    /// [`LightField::traced_radiance`] with the diffuse part of every surface met given by
    /// `diffuse`, however deep.
    fn traced_by(
        &self,
        bvh: &Bvh,
        origin: DVec3,
        dir: DVec3,
        depth: u32,
        diffuse: &dyn Fn(usize, DVec3) -> Rgb,
    ) -> Rgb {
        match bvh.intersect(&self.scene, origin, dir, RAY_EPSILON, f64::INFINITY) {
            Some(hit) => self.shade_by(bvh, &hit, dir, SpecularMode::Trace { depth }, diffuse, diffuse),
            None => [0.0; 3],
        }
    }

    /// Radiance leaving `hit` towards the viewer looking along `dir`.
    pub fn shade(&self, bvh: &Bvh, hit: &Hit, dir: DVec3, mode: SpecularMode) -> Rgb {
        let exact = |surface, p| self.diffuse_radiance_at(bvh, surface, p);
        self.shade_by(bvh, hit, dir, mode, &exact, &exact)
    }

    /// [`LightField::shade`] with the diffuse part read from the field's maps even when exact
    /// direct light is on, in the mirrors traced too: for light gathered over many directions
    /// at once (dynamic objects), where the maps' resolution is enough and a shadow ray per
    /// emitter sample and direction is not affordable.
    pub fn shade_from_maps(&self, bvh: &Bvh, hit: &Hit, dir: DVec3, mode: SpecularMode) -> Rgb {
        let maps = |surface, p| self.radiance_at(surface, p);
        self.shade_by(bvh, hit, dir, mode, &maps, &maps)
    }

    /// [`LightField::shade`] with the diffuse part of the surface hit given by `diffuse`, and
    /// that of every surface its traced mirrors meet by `traced`.
    pub(crate) fn shade_by(
        &self,
        bvh: &Bvh,
        hit: &Hit,
        dir: DVec3,
        mode: SpecularMode,
        diffuse: &dyn Fn(usize, DVec3) -> Rgb,
        traced: &dyn Fn(usize, DVec3) -> Rgb,
    ) -> Rgb {
        if !hit.front {
            return [0.0; 3];
        }
        let mut out = diffuse(hit.surface, hit.point);
        let material = self.scene.material(hit.surface);
        if !material.is_mirror() {
            return out;
        }
        let n = self.scene.surfaces[hit.surface].normal;
        let reflected = dir - 2.0 * dir.dot(n) * n;
        let mirrored = match mode {
            SpecularMode::Rays => self.mirror_radiance_from_rays(hit.surface, hit.point, -dir),
            SpecularMode::Trace { depth: 0 } => [0.0; 3],
            SpecularMode::Trace { depth } => {
                let l = self.traced_by(bvh, hit.point + n * RAY_EPSILON, reflected, depth - 1, traced);
                [
                    l[0] * material.specular[0],
                    l[1] * material.specular[1],
                    l[2] * material.specular[2],
                ]
            }
        };
        for c in 0..3 {
            out[c] += mirrored[c];
        }
        out
    }

    /// Renders the field for a pinhole camera: primary visibility by ray
    /// casting, then [`LightField::shade`]. `samples` per pixel axis (box
    /// filter).
    pub fn render(&self, camera: &Camera, samples: u32, mode: SpecularMode) -> Image {
        self.render_with_progress(camera, samples, mode, &|| {})
    }

    /// [`LightField::render`], calling `row_done` as each row of pixels is finished.
    pub fn render_with_progress(
        &self,
        camera: &Camera,
        samples: u32,
        mode: SpecularMode,
        row_done: &(dyn Fn() + Sync),
    ) -> Image {
        let bvh = Bvh::build(&self.scene);
        let shade = |origin: DVec3, dir: DVec3| match bvh.intersect(&self.scene, origin, dir, 0.0, f64::INFINITY) {
            Some(hit) => self.shade(&bvh, &hit, dir, mode),
            None => [0.0; 3],
        };
        crate::render::render_rays_with_progress(&self.scene, camera, samples, shade, row_done)
    }

    /// The paper's backward ray-traced re-sampling of mirror totals: every
    /// mirror slot's radiance is replaced by what a ray traced back along its
    /// reflection finds (`ρs` × the radiance arriving from the mirror image
    /// direction), following real ray paths through further mirrors up to
    /// `depth`. Sharpens reflections seen "from the rays"; done once, after
    /// the last iteration.
    pub fn resample_mirrors(&mut self, depth: u32) {
        use rayon::prelude::*;
        let Some(spec) = &self.specular else {
            return;
        };
        let bvh = Bvh::build(&self.scene);
        let scene = &self.scene;
        let field = &*self;
        let totals: Vec<Vec<[f32; 3]>> = (0..spec.directions.len())
            .into_par_iter()
            .map(|d| {
                let (sub, layout) = (&spec.views[d].sub, &spec.views[d].layout);
                let mut out = spec.totals[d].clone();
                let w = spec.directions.get(d).vector;
                for &(surface, k, e) in &layout.entries {
                    let s = &scene.surfaces[surface as usize];
                    let rho = scene.materials[s.material].specular;
                    let outgoing = if w.dot(s.normal) > 0.0 { w } else { -w };
                    // Light leaving along `outgoing` arrived from its mirror image.
                    let towards_source = -(outgoing - 2.0 * outgoing.dot(s.normal) * s.normal);
                    let proj = crate::psf::SurfaceProjection::new(&sub.frame, sub.grid.resolution, s.normal, s.offset);
                    let entry = &sub.entries[e as usize];
                    let base = layout.entry_base[e as usize];
                    sub.rays_of(k as usize, entry, |slot, x, y| {
                        let p = proj.point_at(x as f64 + 0.5, y as f64 + 0.5);
                        let l = field.traced_radiance(&bvh, p + s.normal * RAY_EPSILON, towards_source, depth);
                        out[(base + slot - entry.first_ray) as usize] =
                            [(l[0] * rho[0]) as f32, (l[1] * rho[1]) as f32, (l[2] * rho[2]) as f32];
                    });
                }
                out
            })
            .collect();
        if let Some(spec) = &mut self.specular {
            spec.totals = totals;
        }
    }
}
