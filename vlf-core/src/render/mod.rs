//! CPU rendering of a view: camera rays, primary visibility, a pixel filter.
//!
//! Once the light field has converged, a view costs no further light
//! transport: each camera ray only needs the first surface it meets and the
//! radiance leaving that surface towards the eye, which the light field
//! stores. This module supplies everything but that last look-up — the
//! pinhole [`Camera`] (in scene units), the [`Bvh`] for ray casting in the
//! VLF frame, and the [`Image`] written to disk — and [`render`] takes the
//! look-up as a closure, so the same loop serves the light field's renderer,
//! debug views (normals, surface ids) and tests.
//!
//! Rendering is deterministic: every pixel is computed independently, in a
//! fixed sample order, so the image does not depend on the number of rayon
//! threads.

pub mod bvh;
pub mod camera;
pub mod compare;
pub mod image;

pub use self::bvh::{Bvh, Hit, Node};
pub use self::camera::{Camera, parse_size, parse_vec3};
pub use self::image::Image;

use glam::DVec3;
use rayon::prelude::*;

use crate::scene::Scene;

/// Renders `scene` as seen by `camera`.
///
/// Each pixel averages (box filter) `samples_per_axis²` samples on a regular
/// sub-pixel grid: sample `(sx, sy)` of pixel `(x, y)` is at
/// `(x + (sx + ½) / n, y + (sy + ½) / n)`, so `n = 1` is the pixel centre
/// (0 is treated as 1). Camera rays are converted into the VLF frame with
/// `scene.normalisation` — the origin with [`crate::scene::Normalisation::to_vlf`],
/// the unit direction unchanged since the map is a similarity with positive
/// scale — and cast with `bvh` (which must have been built from `scene`).
/// A hit is shaded by `shade(hit, direction)` with the direction in the VLF
/// frame; a miss is black. Rows are rendered in parallel with rayon; the
/// output is identical whatever the number of threads.
pub fn render<F>(scene: &Scene, bvh: &Bvh, camera: &Camera, samples_per_axis: u32, shade: F) -> Image
where
    F: Fn(&Hit, DVec3) -> [f64; 3] + Sync,
{
    render_rays(scene, camera, samples_per_axis, |origin, dir| {
        match bvh.intersect(scene, origin, dir, 0.0, f64::INFINITY) {
            Some(hit) => shade(&hit, dir),
            None => [0.0; 3],
        }
    })
}

/// [`render`] with the radiance of every camera ray given by `radiance(origin, dir)` (VLF
/// frame): for views that hold more than the static scene (dynamic objects).
pub fn render_rays<F>(scene: &Scene, camera: &Camera, samples_per_axis: u32, radiance: F) -> Image
where
    F: Fn(DVec3, DVec3) -> [f64; 3] + Sync,
{
    render_rays_with_progress(scene, camera, samples_per_axis, radiance, &|| {})
}

/// [`render_rays`], calling `row_done` as each row of pixels is finished (from the rendering
/// threads, in no particular order): for a progress bar where shading is slow (exact direct
/// light).
pub fn render_rays_with_progress<F>(
    scene: &Scene,
    camera: &Camera,
    samples_per_axis: u32,
    radiance: F,
    row_done: &(dyn Fn() + Sync),
) -> Image
where
    F: Fn(DVec3, DVec3) -> [f64; 3] + Sync,
{
    let n = samples_per_axis.max(1);
    let samples = n as f64 * n as f64;
    let mut image = Image::new(camera.width, camera.height);
    if image.pixels.is_empty() {
        return image;
    }
    let normalisation = scene.normalisation;
    let started = std::time::Instant::now();
    image
        .pixels
        .par_chunks_mut(camera.width as usize)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, pixel) in row.iter_mut().enumerate() {
                let mut sum = [0.0f64; 3];
                pixel_rays(camera, &normalisation, n, x as u32, y as u32, |origin, dir| {
                    let c = radiance(origin, dir);
                    for k in 0..3 {
                        sum[k] += c[k];
                    }
                });
                *pixel = sum.map(|s| (s / samples) as f32);
            }
            row_done();
        });
    tracing::debug!(
        width = camera.width,
        height = camera.height,
        samples_per_axis = n,
        seconds = started.elapsed().as_secs_f64(),
        "rendered view"
    );
    image
}

/// Visits the `n × n` camera rays of pixel `(x, y)` in [`render`]'s order and positions, as
/// (origin in the VLF frame, unit direction): what every per-sample loop over a view shares.
pub fn pixel_rays(
    camera: &Camera,
    normalisation: &crate::scene::Normalisation,
    n: u32,
    x: u32,
    y: u32,
    mut visit: impl FnMut(DVec3, DVec3),
) {
    for sy in 0..n {
        let py = y as f64 + (sy as f64 + 0.5) / n as f64;
        for sx in 0..n {
            let px = x as f64 + (sx as f64 + 0.5) / n as f64;
            let (origin, dir) = camera.ray(px, py);
            visit(normalisation.to_vlf(origin), dir);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::bvh::tests::{random_scene, scene_of, surface};
    use super::*;
    use crate::scene::Normalisation;

    fn pool(threads: usize) -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool")
    }

    #[test]
    fn square_facing_the_camera() {
        // A square of side 2 (scene units) around `center`, facing +z, in a
        // frame where VLF = (scene − center) × 0.5.
        let center = DVec3::new(1.0, 2.0, 3.0);
        let normalisation = Normalisation { center, scale: 0.5 };
        let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(x, y)| center + DVec3::new(x, y, 0.0));
        let mut scene = scene_of(vec![surface(
            corners.iter().map(|&c| normalisation.to_vlf(c)).collect(),
        )]);
        scene.normalisation = normalisation;
        let bvh = Bvh::build(&scene);
        let camera = Camera::new(center + DVec3::new(0.0, 0.0, 4.0), center, DVec3::Y, 60.0, 40, 30).unwrap();
        // The square appears as an axis-aligned rectangle of the image.
        let projected: Vec<(f64, f64)> = corners.iter().map(|&c| camera.project(c).unwrap()).collect();
        let x0 = projected.iter().map(|p| p.0).fold(f64::INFINITY, f64::min);
        let x1 = projected.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
        let y0 = projected.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
        let y1 = projected.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
        let constant = [0.25, 0.5, 1.5];
        let shade = |hit: &Hit, dir: DVec3| {
            // Front face, the hit in the VLF frame, a unit direction.
            let vlf_ok =
                hit.point.z.abs() < 1e-12 && hit.point.x.abs() <= 0.5 + 1e-9 && hit.point.y.abs() <= 0.5 + 1e-9;
            if hit.front && vlf_ok && (dir.length() - 1.0).abs() < 1e-12 {
                constant
            } else {
                [-1.0; 3]
            }
        };
        for n in [1u32, 2, 3] {
            let image = render(&scene, &bvh, &camera, n, shade);
            assert_eq!((image.width, image.height), (40, 30));
            let (mut full, mut empty, mut partial) = (0, 0, 0);
            for y in 0..30u32 {
                for x in 0..40u32 {
                    // Count the samples inside the projected rectangle.
                    let mut covered = 0.0f64;
                    for sy in 0..n {
                        for sx in 0..n {
                            let px = x as f64 + (sx as f64 + 0.5) / n as f64;
                            let py = y as f64 + (sy as f64 + 0.5) / n as f64;
                            if px > x0 && px < x1 && py > y0 && py < y1 {
                                covered += 1.0;
                            }
                        }
                    }
                    let fraction = covered / (n * n) as f64;
                    let expected = constant.map(|c| (c * fraction) as f32);
                    let got = image.get(x, y);
                    for k in 0..3 {
                        assert!(
                            (got[k] - expected[k]).abs() <= 1e-6,
                            "n={n} ({x}, {y}): {got:?} vs {expected:?}"
                        );
                    }
                    if fraction == 1.0 {
                        assert_eq!(got, constant.map(|c| c as f32), "n={n} ({x}, {y})");
                        full += 1;
                    } else if fraction == 0.0 {
                        assert_eq!(got, [0.0; 3], "n={n} ({x}, {y})");
                        empty += 1;
                    } else {
                        partial += 1;
                    }
                }
            }
            assert!(full > 100 && empty > 600, "n={n}: {full} full, {empty} empty");
            if n == 2 {
                // Edges at half pixels cut the 2 × 2 grids in halves.
                assert!(partial > 0);
            }
        }
    }

    #[test]
    fn same_image_with_one_and_two_threads_and_as_reference() {
        let mut scene = random_scene(5, 200);
        scene.normalisation = Normalisation {
            center: DVec3::new(-3.0, 0.5, 10.0),
            scale: 0.25,
        };
        let bvh = Bvh::build(&scene);
        let eye = scene.normalisation.to_scene(DVec3::new(0.3, 0.4, 2.5));
        let target = scene.normalisation.center;
        let camera = Camera::new(eye, target, DVec3::Y, 45.0, 48, 36).unwrap();
        let shade = |hit: &Hit, dir: DVec3| {
            let base = if hit.front { 1.0 } else { 0.5 };
            [
                base * hit.point.x.abs(),
                dir.y.abs() + hit.t,
                hit.surface as f64 / 200.0,
            ]
        };
        let one = pool(1).install(|| render(&scene, &bvh, &camera, 2, shade));
        let two = pool(2).install(|| render(&scene, &bvh, &camera, 2, shade));
        let bits = |i: &Image| i.pixels.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&one), bits(&two));
        // Straightforward reference: 2 × 2 samples at quarter positions,
        // rays converted into the VLF frame, misses black.
        let mut hits = 0;
        for y in 0..36u32 {
            for x in 0..48u32 {
                let mut sum = [0.0f64; 3];
                for (dx, dy) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
                    let (o, d) = camera.ray(x as f64 + dx, y as f64 + dy);
                    let o = (o - scene.normalisation.center) * 0.25;
                    if let Some(hit) = bvh::intersect_brute_force(&scene, o, d, 0.0, f64::INFINITY) {
                        hits += 1;
                        let c = shade(&hit, d);
                        for k in 0..3 {
                            sum[k] += c[k];
                        }
                    }
                }
                let expected = sum.map(|s| (s / 4.0) as f32);
                let got = one.get(x, y);
                for k in 0..3 {
                    assert!(
                        (got[k] - expected[k]).abs() <= 1e-5 * expected[k].abs().max(1.0),
                        "({x}, {y}) {got:?} vs {expected:?}"
                    );
                }
            }
        }
        assert!(hits > 1000 && hits < 36 * 48 * 4, "{hits}");
    }

    #[test]
    fn empty_scene_is_black_and_zero_samples_means_one() {
        let scene = scene_of(Vec::new());
        let bvh = Bvh::build(&scene);
        let camera = Camera::new(DVec3::Z, DVec3::ZERO, DVec3::Y, 40.0, 5, 4).unwrap();
        let image = render(&scene, &bvh, &camera, 0, |_, _| [1.0; 3]);
        assert_eq!(image, Image::new(5, 4));
    }
}
