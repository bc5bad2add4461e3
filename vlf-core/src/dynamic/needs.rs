//! What the objects read of the field: the parts a streaming viewer must fetch for them.
//!
//! A view's own needs ([`LightField::view_needs`]) are the surfaces its pixels see. An object
//! reads others: its gather ([`super::gather`]) reads the static surfaces seen *from the
//! object*, and its shadow ([`super::shadow`]) the surfaces *behind* it as seen from the static
//! points around it — every such ray passes through the object's bounding sphere, so what it
//! reads is a surface seen from a point of that sphere. Both sets are therefore covered by the
//! surfaces seen from the sphere, which [`needs_around`] samples: from the sphere's centre and
//! [`SPHERE_POINTS`] points spread over its surface, along both ends of every line of a
//! direction set (the gather's own), following mirrors as the view's mode reads them.
//!
//! It is a sampling: a surface seen from the sphere only between the sampled rays (a small
//! one, far away) is missed until the view itself needs it. While a part is missing the viewer
//! leaves it out of the gather's mean (see `viewer/src/shaders/objects.wgsl`), so an object is
//! lit by what is resident, not drawn black.

use crate::directions::DirectionSet;
use crate::field::LightField;
use crate::lookup::{SpecularMode, ViewNeeds};
use crate::render::Bvh;
use glam::DVec3;

/// Points on each bounding sphere rays are cast from (besides its centre).
pub const SPHERE_POINTS: usize = 32;

/// The static surfaces (and mirror tiles) seen from the spheres `(centre, radius)` (VLF frame)
/// along `directions`, as shading with `mode` reads them: what objects inside the spheres
/// gather from and shadow (see the module docs).
pub fn needs_around(
    field: &LightField,
    bvh: &Bvh,
    spheres: &[(DVec3, f64)],
    directions: &DirectionSet,
    mode: SpecularMode,
) -> ViewNeeds {
    let mut needs = ViewNeeds::default();
    for &(center, radius) in spheres {
        for origin in sphere_points(center, radius) {
            for d in 0..directions.len() {
                let v = directions.get(d).vector;
                for dir in [v, -v] {
                    field.needs_along(bvh, origin, dir, mode, &mut needs);
                }
            }
        }
    }
    needs.mirror_tiles = needs.tile_weight.keys().copied().collect();
    needs
}

/// The centre of the sphere and [`SPHERE_POINTS`] points on it, spread evenly (a Fibonacci
/// spiral: equal areas along `z`, the golden angle about it).
fn sphere_points(center: DVec3, radius: f64) -> impl Iterator<Item = DVec3> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let n = SPHERE_POINTS as f64;
    std::iter::once(center).chain((0..SPHERE_POINTS).map(move |i| {
        let z = 1.0 - (i as f64 + 0.5) * 2.0 / n;
        let r = (1.0 - z * z).max(0.0).sqrt();
        let phi = i as f64 * golden;
        center + radius * DVec3::new(r * phi.cos(), r * phi.sin(), z)
    }))
}
