//! The light field must not depend on how a surface is tessellated: texels belong to charts
//! (`vlf_core::maps::charts`), not to polygons.
//!
//! * A closed room whose walls are plain quads, the same walls as a regular grid of triangles,
//!   and as an irregular split, render alike (block-16 difference ≤ 3 %, image means within
//!   1 %).
//! * The integrating sphere, an analytic case for curved meshes: inside a closed sphere of area
//!   `A` and reflectance ρ, a patch emitting power Φ gives every wall point the same reflected
//!   radiance `ρ·Φ / (π·A·(1 − ρ))`.

mod common;

use common::*;
use glam::DVec3;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::Camera;
use vlf_core::render::compare::{Comparison, Pixels, compare};
use vlf_core::scene::{FaceOrigin, ImportOptions, Scene, Surface};

/// How a wall quad (corners counter-clockwise about its front) is cut into polygons.
#[derive(Clone, Copy, Debug)]
enum Split {
    Quad,
    /// `k × k` cells, each two triangles (diagonals alternating).
    Grid(usize),
    /// A fan from an off-centre point to the corners, each fan triangle cut again at an
    /// interior point: 12 triangles of uneven shapes.
    Irregular,
}

fn tri(a: DVec3, b: DVec3, c: DVec3, material: usize) -> Surface {
    surface(vec![a, b, c], material)
}

fn split_quad(q: [DVec3; 4], split: Split, material: usize, seed: &mut u64) -> Vec<Surface> {
    let [p00, p10, p11, p01] = q;
    let at = |u: f64, v: f64| p00 + (p10 - p00) * u + (p01 - p00) * v;
    let _ = p11;
    match split {
        Split::Quad => vec![surface(q.to_vec(), material)],
        Split::Grid(k) => {
            let mut out = Vec::new();
            let f = |i: usize| i as f64 / k as f64;
            for i in 0..k {
                for j in 0..k {
                    let (a, b, c, d) = (
                        at(f(i), f(j)),
                        at(f(i + 1), f(j)),
                        at(f(i + 1), f(j + 1)),
                        at(f(i), f(j + 1)),
                    );
                    if (i + j) % 2 == 0 {
                        out.push(tri(a, b, c, material));
                        out.push(tri(a, c, d, material));
                    } else {
                        out.push(tri(a, b, d, material));
                        out.push(tri(b, c, d, material));
                    }
                }
            }
            out
        }
        Split::Irregular => {
            let mut rnd = || {
                *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (*seed >> 11) as f64 / (1u64 << 53) as f64
            };
            let centre = at(0.3 + 0.4 * rnd(), 0.3 + 0.4 * rnd());
            let corners = [p00, p10, p11, p01];
            let mut out = Vec::new();
            for k in 0..4 {
                let (a, b) = (corners[k], corners[(k + 1) % 4]);
                // An interior point of the fan triangle (centre, a, b): positive weights.
                let w = [0.2 + rnd(), 0.2 + rnd(), 0.2 + rnd()];
                let sum = w[0] + w[1] + w[2];
                let inner = (centre * w[0] + a * w[1] + b * w[2]) / sum;
                out.push(tri(centre, a, inner, material));
                out.push(tri(a, b, inner, material));
                out.push(tri(b, centre, inner, material));
            }
            out
        }
    }
}

/// A closed grey room (ρ = 0.6) with a lamp below its ceiling and a block on the floor, every
/// wall of the room and face of the block cut by `split`.
fn room(split: Split) -> Scene {
    room_of(split, material("grey", 0.6, 0.0))
}

/// [`room`] with walls and block of material `walls`.
fn room_of(split: Split, walls: vlf_core::scene::Material) -> Scene {
    let h = 0.55;
    let mut seed = 0x5eed_u64;
    let mut surfaces = Vec::new();
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    // Room walls, facing inwards.
    for face in 0..6 {
        let axis = axes[face / 2];
        let sign = if face % 2 == 0 { -1.0 } else { 1.0 };
        let (ta, tb) = (axes[(face / 2 + 1) % 3], axes[(face / 2 + 2) % 3]);
        let c = axis * sign * h;
        let mut q = [
            c - ta * h - tb * h,
            c + ta * h - tb * h,
            c + ta * h + tb * h,
            c - ta * h + tb * h,
        ];
        if (q[1] - q[0]).cross(q[3] - q[0]).dot(-axis * sign) < 0.0 {
            q.swap(1, 3);
        }
        surfaces.extend(split_quad(q, split, 0, &mut seed));
    }
    // A block on the floor, facing outwards.
    let (bc, bh) = (DVec3::new(0.15, -h + 0.2, -0.1), DVec3::new(0.15, 0.2, 0.2));
    for face in 0..6 {
        let axis = axes[face / 2];
        let sign = if face % 2 == 0 { -1.0 } else { 1.0 };
        if face == 2 {
            continue; // the bottom lies on the floor
        }
        let (ta, tb) = (axes[(face / 2 + 1) % 3], axes[(face / 2 + 2) % 3]);
        let c = bc + axis * sign * axis.dot(bh);
        let (a, b) = (ta * ta.dot(bh), tb * tb.dot(bh));
        let mut q = [c - a - b, c + a - b, c + a + b, c - a + b];
        if (q[1] - q[0]).cross(q[3] - q[0]).dot(axis * sign) < 0.0 {
            q.swap(1, 3);
        }
        surfaces.extend(split_quad(q, split, 0, &mut seed));
    }
    // The lamp: a plain quad facing down, just below the ceiling.
    surfaces.push(rect(
        DVec3::new(-0.1, h - 0.01, 0.05),
        DVec3::X * 0.15,
        DVec3::Z * 0.15,
        -DVec3::Y,
        1,
    ));
    scene(surfaces, vec![walls, material("lamp", 0.0, 4.0)])
}

/// Propagates to convergence, checking the closed scene's bookkeeping: at most `max_escape` of
/// the shot power escapes, and what is shot arrives (or meets the lamp's back).
fn propagate(scene: Scene, l: usize, n: u32, max_escape: f64) -> LightField {
    let options = Options {
        directions: l,
        grid: GridSize::new(n, 8).unwrap(),
        stop: Stop::Converge {
            epsilon: 1e-3,
            max_iterations: 200,
        },
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    p.run(|_| {});
    for st in &p.stats {
        let f = &st.flow;
        assert!(
            f.escaped[0] <= max_escape * f.shot[0],
            "iteration {}: light escaped a closed scene ({:.2e} of {:.3e} shot)",
            st.index,
            f.escaped[0],
            f.shot[0]
        );
        let accounted = f.received[0] + f.blocked[0] + f.escaped[0];
        assert!(
            (f.shot[0] - accounted).abs() <= 1e-9 * f.shot[0],
            "iteration {}: shot {} vs received + blocked {accounted}",
            st.index,
            f.shot[0]
        );
    }
    p.into_field()
}

fn render(field: &LightField) -> vlf_core::render::Image {
    render_with(field, SpecularMode::Trace { depth: 2 })
}

fn render_with(field: &LightField, mode: SpecularMode) -> vlf_core::render::Image {
    let camera = Camera::new(
        DVec3::new(-0.35, 0.1, 0.45),
        DVec3::new(0.3, -0.25, -0.4),
        DVec3::Y,
        70.0,
        96,
        72,
    )
    .unwrap();
    field.render(&camera, 2, mode)
}

/// Two renders alike: block-16 difference at most 3 %, image means within 1 %.
fn assert_alike(c: &Comparison, what: &str) {
    assert!(
        c.block_error <= 0.03,
        "{what}: block-16 difference {:.4}",
        c.block_error
    );
    assert!(
        c.mean_error.abs() <= 0.01,
        "{what}: image means differ by {:.4}",
        c.mean_error
    );
}

#[test]
fn a_room_renders_alike_however_its_walls_are_tessellated() {
    let (l, n) = (129, 32);
    let plain = propagate(room(Split::Quad), l, n, 0.0);
    let reference = render(&plain);
    for split in [Split::Grid(16), Split::Irregular] {
        let scene = room(split);
        let polygons = scene.surfaces.len();
        let field = propagate(scene, l, n, 0.0);
        // Every wall is one chart again, however it was cut.
        assert_eq!(field.atlas.charts.len(), plain.atlas.charts.len(), "{split:?}: charts");
        assert_eq!(field.atlas.texels, plain.atlas.texels, "{split:?}: texels");
        let image = render(&field);
        let c = compare(&image, &reference, 16, Pixels::default()).unwrap();
        println!(
            "{split:?} ({polygons} polygons): block-16 {:.4}, mean {:+.4}, pixel rrmse {:.4}",
            c.block_error, c.mean_error, c.relative_rmse
        );
        assert_alike(&c, &format!("{split:?}"));
    }
}

/// The room with every wall and block face a half mirror (ρd 0.3, ρs 0.5), cut as above: a
/// mirror's polygons share their plane's slots and routes, so the mirrors seen from the rays
/// (the field's directional maps, `SpecularMode::Rays`) and traced render alike too, with as
/// many slots (to 10⁻³) however the walls were cut.
#[test]
fn a_mirror_room_renders_alike_however_its_walls_are_tessellated() {
    let (l, n) = (129, 32);
    let half_mirror = || vlf_core::scene::Material {
        specular: [0.5; 3],
        ..material("half mirror", 0.3, 0.0)
    };
    let plain = propagate(room_of(Split::Quad, half_mirror()), l, n, 0.0);
    let modes = [SpecularMode::Rays, SpecularMode::Trace { depth: 2 }];
    let references = modes.map(|mode| render_with(&plain, mode));
    let plain_mirrors = plain.specular.as_ref().unwrap();
    for split in [Split::Grid(16), Split::Irregular] {
        let scene = room_of(split, half_mirror());
        let polygons = scene.surfaces.len();
        let field = propagate(scene, l, n, 0.0);
        let mirrors = field.specular.as_ref().unwrap();
        // The same rays cross the mirrors, but for a ray through an edge where the cut walls
        // meet the block's footprint (there the floor is two planes, as in the diffuse room).
        let slots = |f: &vlf_core::field::SpecularField| f.views.iter().map(|v| v.slots() as f64).sum::<f64>();
        let (a, b) = (slots(mirrors), slots(plain_mirrors));
        assert!((a - b).abs() <= 1e-3 * b, "{split:?}: {a} mirror slots against {b}");
        for (mode, reference) in modes.iter().zip(&references) {
            let c = compare(&render_with(&field, *mode), reference, 16, Pixels::default()).unwrap();
            println!(
                "{split:?} ({polygons} polygons), {mode:?}: block-16 {:.4}, mean {:+.4}",
                c.block_error, c.mean_error
            );
            assert_alike(&c, &format!("{split:?}, {mode:?}"));
        }
    }
}

/// An icosphere of radius `r` subdivided `levels` times (`icosphere`), facing inwards;
/// triangles whose centroid is above `cap` (y) emit.
fn integrating_sphere(r: f64, levels: u32, cap: f64) -> Scene {
    let surfaces = icosphere(DVec3::ZERO, r, levels)
        .into_iter()
        .map(|[a, b, c]| {
            // Outward-wound faces reversed: fronts face the centre.
            let emits = (a + b + c).y / 3.0 > cap;
            tri(a, c, b, usize::from(emits))
        })
        .collect();
    scene(surfaces, vec![material("wall", 0.5, 0.0), material("lamp", 0.5, 1.0)])
}

#[test]
fn an_integrating_sphere_is_uniformly_lit_at_the_analytic_radiance() {
    let (rho, le) = (0.5, 1.0);
    let scene = integrating_sphere(0.95, 3, 0.85);
    let area: f64 = scene.surfaces.iter().map(|s| s.area).sum();
    let lamp: f64 = scene.surfaces.iter().filter(|s| s.material == 1).map(|s| s.area).sum();
    let triangles = scene.surfaces.len();
    // A ray passing within 1/512 of a ray cell outside the sphere's silhouette may be counted
    // as crossing the two facets of the fold there (the rasteriser snaps vertices to 1/256 of a
    // cell), whose planes it meets in the wrong order: ~1e-5 of the power escapes.
    let field = propagate(scene, 513, 64, 1e-4);
    // Φ = π·Le·A_e; the lamp reflects too, so the whole sphere is one enclosure of reflectance
    // ρ: the reflected radiance everywhere is ρ·Φ / (π·A·(1 − ρ)).
    let want = rho * le * lamp / (area * (1.0 - rho));
    // Sampled at four points of every wall triangle; grouped by chart too.
    let mut values = Vec::new();
    let mut per_chart = vec![(0.0, 0usize); field.atlas.charts.len()];
    for (s, surface) in field.scene.surfaces.iter().enumerate() {
        if surface.material != 0 {
            continue;
        }
        let v = &surface.vertices;
        for (a, b) in [(1.0 / 3.0, 1.0 / 3.0), (0.6, 0.2), (0.2, 0.6), (0.2, 0.2)] {
            let p = v[0] + (v[1] - v[0]) * a + (v[2] - v[0]) * b;
            let x = field.radiance_at(s, p)[0];
            values.push(x);
            let c = &mut per_chart[field.atlas.chart_of[s] as usize];
            *c = (c.0 + x, c.1 + 1);
        }
    }
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    let rms = (values.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / values.len() as f64).sqrt();
    let chart_worst = (per_chart.iter())
        .filter(|c| c.1 > 0)
        .map(|c| (c.0 / c.1 as f64 / want - 1.0).abs())
        .fold(0.0, f64::max);
    println!(
        "integrating sphere ({triangles} triangles, {} charts): want {want:.5}, mean {mean:.5} ({:+.4}), \
         worst chart mean {chart_worst:.4}, point spread rms {:.4} (relative)",
        field.atlas.charts.len(),
        mean / want - 1.0,
        rms / mean,
    );
    assert!(field.atlas.charts.len() < triangles / 10, "the sphere was not charted");
    // The mean: the analytic value to 2 % (the facets' flatness and the discrete directions).
    assert!((mean / want - 1.0).abs() <= 0.02, "mean {mean} vs {want}");
    // Uniform: every chart (≈ 30 triangles) within 4 % of the formula — no chart, and so no
    // polygon, reads brighter or darker for how it was cut; point by point the texels' own noise
    // at N = 64 (a texel is one ray spacing, crossed by a few rays per direction) stays below 8 %.
    assert!(chart_worst <= 0.04, "a chart's mean is off by {chart_worst:.4}");
    assert!(rms / mean <= 0.08, "not uniform: rms {:.4}", rms / mean);
}

/// A closed room whose walls meet in T-junctions, inside each wall and across its corners:
/// every wall is a tall quad on its left and a stack of strips on its right, so the tall quad's
/// right edge carries the strips' corners, and so does the next wall's edge along the corner.
/// The importer splits the faces there (with a warning) and not a ray escapes.
#[test]
fn t_junctions_leak_no_light() {
    let h = 0.55;
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    let mut polygons = Vec::new();
    let heights = [0.0, 0.13, 0.41, 0.52, 0.77, 1.0];
    for face in 0..6 {
        let axis = axes[face / 2];
        let sign = if face % 2 == 0 { -1.0 } else { 1.0 };
        let (ta, tb) = (axes[(face / 2 + 1) % 3], axes[(face / 2 + 2) % 3]);
        let c = axis * sign * h;
        let at = |u: f64, v: f64| c + ta * h * (2.0 * u - 1.0) + tb * h * (2.0 * v - 1.0);
        let facing = -axis * sign;
        let mut push = |q: Vec<DVec3>| {
            let n = (q[1] - q[0]).cross(q[2] - q[0]);
            let q = if n.dot(facing) < 0.0 {
                q.into_iter().rev().collect()
            } else {
                q
            };
            let material = usize::from(face == 3 && q.iter().all(|p| p.dot(ta) < 0.0));
            polygons.push((
                q,
                material,
                FaceOrigin {
                    line: 0,
                    face: polygons.len(),
                },
            ));
        };
        let split = 0.37;
        push(vec![at(0.0, 0.0), at(split, 0.0), at(split, 1.0), at(0.0, 1.0)]);
        for w in heights.windows(2) {
            push(vec![at(split, w[0]), at(1.0, w[0]), at(1.0, w[1]), at(split, w[1])]);
        }
    }
    let materials = vec![material("grey", 0.7, 0.0), material("lamp", 0.5, 1.0)];
    let (scene, warnings) = Scene::from_polygons(&polygons, materials, &ImportOptions::default()).unwrap();
    assert!(
        warnings.iter().any(|w| w.contains("T-junction")),
        "no T-junction warning: {warnings:?}"
    );
    // Every edge is now shared exactly: no vertex of the scene lies inside an edge.
    let vertices: Vec<DVec3> = scene.surfaces.iter().flat_map(|s| s.vertices.clone()).collect();
    for s in &scene.surfaces {
        for i in 0..s.vertices.len() {
            let (a, b) = (s.vertices[i], s.vertices[(i + 1) % s.vertices.len()]);
            for &p in &vertices {
                let t = (p - a).dot(b - a) / (b - a).length_squared();
                if t > 1e-6 && t < 1.0 - 1e-6 {
                    assert!((a + (b - a) * t - p).length() > 1e-9, "a T-junction remains at {p}");
                }
            }
        }
    }
    // 513 directions × 64² rays: any seam would let some through.
    let field = propagate(scene, 513, 64, 0.0);
    assert!(field.stats.len() > 3);
}
