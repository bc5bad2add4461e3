//! Drawing a view with dynamic objects in it (the CPU renderer's way).
//!
//! Each camera ray finds the nearer of the static scene and the objects. A static point is
//! shaded from the field less the light the objects take from it ([`super::shadow`]), and a
//! static mirror shows the objects and their shadows. A point of an object is shaded per pixel
//! sample by the gather ([`super::gather`]): its diffuse part is ρd times the cosine-weighted radiance arriving over its hemisphere, its
//! mirror part ρs times what the reflected ray meets. An object hides what lies behind it and
//! is seen in the static scene's mirrors, traced or read from the rays. Back faces of objects
//! are black, as the static scene's are.

use super::gather::Gatherer;
use crate::lookup::SpecularMode;
use crate::render::{Bvh, Camera, Hit, Image, render_rays};
use crate::scene::Rgb;
use glam::DVec3;

/// How far a reflected ray starts off an object's surface.
const RAY_OFFSET: f64 = 1e-7;

/// Draws `gatherer`'s field, with its objects, for `camera` (`samples` per pixel axis).
pub fn render_with_objects(gatherer: &Gatherer, bvh: &Bvh, camera: &Camera, samples: u32) -> Image {
    let depth = match gatherer.mode() {
        SpecularMode::Trace { depth } => depth,
        SpecularMode::Rays => 0,
    };
    render_rays(&gatherer.field().scene, camera, samples, |origin, dir| {
        radiance_along(gatherer, bvh, origin, dir, depth)
    })
}

/// Radiance arriving at `origin` looking along `dir`, with the objects in the scene: the
/// nearer of the static scene and the objects, shaded. Reflections go at most `depth` mirrors
/// deep. A static mirror shows the objects: with ray-traced mirrors ([`SpecularMode::Trace`])
/// its reflected ray sees them like everything else; with mirrors read from the field's rays
/// (propagated without the objects) the reflected ray is traced once to find an object in the
/// way, and where there is one the mirror shows it instead of what the rays hold.
fn radiance_along(gatherer: &Gatherer, bvh: &Bvh, origin: DVec3, dir: DVec3, depth: u32) -> Rgb {
    let field = gatherer.field();
    let objects = gatherer.objects();
    let hit = bvh.intersect(&field.scene, origin, dir, 0.0, f64::INFINITY);
    let t_static = hit.map_or(f64::INFINITY, |h| h.t);
    if let Some((o, object_hit)) = gatherer.nearest_object(origin, dir, t_static) {
        if !object_hit.front {
            return [0.0; 3];
        }
        let object = &objects[o];
        let surface = &object.scene.surfaces[object_hit.surface];
        let material = &object.scene.materials[surface.material];
        let n = surface.normal;
        let mut l: Rgb = [0.0; 3];
        if material.is_diffuse() {
            l = gatherer.diffuse(object_hit.point, n, material.diffuse);
        }
        if material.is_mirror() {
            let reflected = dir - 2.0 * dir.dot(n) * n;
            let origin = object_hit.point + n * RAY_OFFSET;
            // A mirror object reflects the static scene (and other objects, when tracing).
            let m = if depth > 0 {
                radiance_along(gatherer, bvh, origin, reflected, depth - 1)
            } else {
                gatherer.arriving(origin, reflected)
            };
            for c in 0..3 {
                l[c] += material.specular[c] * m[c];
            }
        }
        return l;
    }
    match hit {
        Some(hit) => static_radiance(gatherer, bvh, &hit, dir, depth),
        None => [0.0; 3],
    }
}

/// Radiance the static surface at `hit` sends back along `−dir` with the objects in the
/// scene: its diffuse part with the objects' shadows ([`Gatherer::diffuse_with_shadows`]),
/// its mirror part showing the objects and their shadows. Without objects, the field's own
/// shading.
fn static_radiance(gatherer: &Gatherer, bvh: &Bvh, hit: &Hit, dir: DVec3, depth: u32) -> Rgb {
    let field = gatherer.field();
    if !hit.front {
        return [0.0; 3];
    }
    let mut l = gatherer.diffuse_with_shadows(hit.surface, hit.point);
    let material = field.scene.material(hit.surface);
    if !material.is_mirror() {
        return l;
    }
    let n = field.scene.surfaces[hit.surface].normal;
    let reflected = dir - 2.0 * dir.dot(n) * n;
    let origin = hit.point + n * RAY_OFFSET;
    let mirrored = match gatherer.mode() {
        SpecularMode::Trace { .. } if depth == 0 => [0.0; 3],
        SpecularMode::Trace { .. } => {
            let m = radiance_along(gatherer, bvh, origin, reflected, depth - 1);
            std::array::from_fn(|c| material.specular[c] * m[c])
        }
        SpecularMode::Rays if gatherer.objects().is_empty() => {
            field.mirror_radiance_from_rays(hit.surface, hit.point, -dir)
        }
        SpecularMode::Rays => {
            // The field's rays were propagated without the objects: the reflected ray is
            // traced once. Where it meets an object first, the mirror shows the object; where
            // it meets a static point in an object's shadow, the rays' light less that shadow.
            let behind = bvh.intersect(&field.scene, origin, reflected, 0.0, f64::INFINITY);
            let t_behind = behind.map_or(f64::INFINITY, |h| h.t);
            if gatherer.nearest_object(origin, reflected, t_behind).is_some() {
                let m = radiance_along(gatherer, bvh, origin, reflected, 0);
                std::array::from_fn(|c| material.specular[c] * m[c])
            } else {
                let mut m = field.mirror_radiance_from_rays(hit.surface, hit.point, -dir);
                if let Some(q) = behind.filter(|q| q.front) {
                    let s = &field.scene;
                    let rho = s.albedo_at(q.surface, q.point);
                    if let Some(loss) = gatherer.shadow_loss(q.point, s.surfaces[q.surface].normal, rho) {
                        for c in 0..3 {
                            m[c] = (m[c] - material.specular[c] * loss[c]).max(0.0);
                        }
                    }
                }
                m
            }
        }
    };
    for c in 0..3 {
        l[c] += mirrored[c];
    }
    l
}
