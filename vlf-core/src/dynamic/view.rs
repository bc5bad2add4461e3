//! Drawing a view with dynamic objects in it (the CPU renderer's way).
//!
//! Each camera ray finds the nearer of the static scene and the objects. A static point is
//! shaded from the field as without objects (the shadows objects cast on it are not drawn
//! yet). A point of an object is shaded per pixel sample by the gather ([`super::gather`]):
//! its diffuse part is ρd times the cosine-weighted radiance arriving over its hemisphere, its
//! mirror part ρs times what the reflected ray meets. An object hides what lies behind it and
//! is seen in the static scene's mirrors, traced or read from the rays. Back faces of objects
//! are black, as the static scene's are.

use super::PlacedObject;
use super::gather::Gatherer;
use crate::lookup::SpecularMode;
use crate::render::{Bvh, Camera, Image, render_rays};
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
    if let Some((o, object_hit)) = nearest_object(objects, origin, dir, t_static) {
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
    let Some(hit) = hit else {
        return [0.0; 3];
    };
    let material = field.scene.material(hit.surface);
    match gatherer.mode() {
        SpecularMode::Trace { .. } if hit.front && material.is_mirror() => {
            let mut l = field.diffuse_radiance_at(bvh, hit.surface, hit.point);
            if depth > 0 {
                let n = field.scene.surfaces[hit.surface].normal;
                let reflected = dir - 2.0 * dir.dot(n) * n;
                let m = radiance_along(gatherer, bvh, hit.point + n * RAY_OFFSET, reflected, depth - 1);
                for c in 0..3 {
                    l[c] += material.specular[c] * m[c];
                }
            }
            l
        }
        SpecularMode::Rays if hit.front && material.is_mirror() && !objects.is_empty() => {
            // The field's rays were propagated without the objects: where the reflected ray
            // meets an object before the static scene, the object is what the mirror shows.
            let n = field.scene.surfaces[hit.surface].normal;
            let reflected = dir - 2.0 * dir.dot(n) * n;
            let origin = hit.point + n * RAY_OFFSET;
            let t_behind = bvh
                .intersect(&field.scene, origin, reflected, 0.0, f64::INFINITY)
                .map_or(f64::INFINITY, |h| h.t);
            if nearest_object(objects, origin, reflected, t_behind).is_none() {
                return field.shade(bvh, &hit, dir, SpecularMode::Rays);
            }
            let mut l = field.diffuse_radiance_at(bvh, hit.surface, hit.point);
            let m = radiance_along(gatherer, bvh, origin, reflected, 0);
            for c in 0..3 {
                l[c] += material.specular[c] * m[c];
            }
            l
        }
        mode => field.shade(bvh, &hit, dir, mode),
    }
}

/// The nearest object hit before `t_max`: the object's index and the hit.
fn nearest_object(
    objects: &[PlacedObject],
    origin: DVec3,
    dir: DVec3,
    t_max: f64,
) -> Option<(usize, crate::render::Hit)> {
    let mut best: Option<(usize, crate::render::Hit)> = None;
    for (k, o) in objects.iter().enumerate() {
        let limit = best.map_or(t_max, |(_, h)| h.t);
        if let Some(h) = o.bvh.intersect(&o.scene, origin, dir, 0.0, limit) {
            best = Some((k, h));
        }
    }
    best
}
