//! Scenes the physics tests build themselves, directly in the VLF frame.
#![allow(dead_code)]

pub mod objects;

use glam::DVec3;
use vlf_core::scene::{FaceOrigin, Material, Normalisation, Scene, Surface};

pub fn material(name: &str, diffuse: f64, emission: f64) -> Material {
    Material {
        name: name.into(),
        diffuse: [diffuse; 3],
        specular: [0.0; 3],
        emission: [emission; 3],
        albedo_texture: None,
    }
}

/// A convex polygon from CCW vertices (VLF frame).
pub fn surface(vertices: Vec<DVec3>, material: usize) -> Surface {
    let mut n = DVec3::ZERO;
    for k in 0..vertices.len() {
        let (a, b) = (vertices[k], vertices[(k + 1) % vertices.len()]);
        n += DVec3::new(
            (a.y - b.y) * (a.z + b.z),
            (a.z - b.z) * (a.x + b.x),
            (a.x - b.x) * (a.y + b.y),
        );
    }
    let area = n.length() * 0.5;
    let normal = n.normalize();
    Surface {
        offset: normal.dot(vertices[0]),
        vertices,
        normal,
        area,
        material,
        origin: FaceOrigin { line: 0, face: 0 },
        uv: None,
    }
}

/// Axis-aligned rectangle with centre `c`, half extents along two axes, facing `normal`.
pub fn rect(c: DVec3, a: DVec3, b: DVec3, normal: DVec3, material: usize) -> Surface {
    let mut v = vec![c - a - b, c + a - b, c + a + b, c - a + b];
    let s = surface(v.clone(), material);
    if s.normal.dot(normal) < 0.0 {
        v.reverse();
    }
    surface(v, material)
}

pub fn scene(surfaces: Vec<Surface>, materials: Vec<Material>) -> Scene {
    Scene {
        surfaces,
        materials,
        normalisation: Normalisation {
            center: DVec3::ZERO,
            scale: 1.0,
        },
        textures: Vec::new(),
    }
}

/// A closed cube of half-size `h` facing inwards, each face split into
/// `split × split` quads (shared edges everywhere). Faces listed in
/// `emitting` (0..6: -x,+x,-y,+y,-z,+z) use material 1, others material 0.
pub fn closed_box(h: f64, split: usize, emitting: &[usize], materials: Vec<Material>) -> Scene {
    let mut surfaces = Vec::new();
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    for face in 0..6 {
        let axis = axes[face / 2];
        let sign = if face % 2 == 0 { -1.0 } else { 1.0 };
        let (ta, tb) = (axes[(face / 2 + 1) % 3], axes[(face / 2 + 2) % 3]);
        let mat = if emitting.contains(&face) { 1 } else { 0 };
        let step = 2.0 * h / split as f64;
        for i in 0..split {
            for j in 0..split {
                let c = axis * sign * h + ta * (-h + (i as f64 + 0.5) * step) + tb * (-h + (j as f64 + 0.5) * step);
                surfaces.push(rect(c, ta * step * 0.5, tb * step * 0.5, -axis * sign, mat));
            }
        }
    }
    scene(surfaces, materials)
}

pub fn mirror(name: &str, diffuse: f64, specular: f64) -> Material {
    Material {
        name: name.into(),
        diffuse: [diffuse; 3],
        specular: [specular; 3],
        emission: [0.0; 3],
        albedo_texture: None,
    }
}

/// A closed box (lamp in the ceiling) with two mirror walls: face 0 (−x) a
/// pure mirror, face 5 (+z) part diffuse, part mirror.
pub fn mirror_room() -> Scene {
    let mut scene = closed_box(
        0.55,
        2,
        &[3],
        vec![
            material("wall", 0.5, 0.0),
            material("lamp", 0.3, 2.0),
            mirror("glass", 0.0, 0.8),
            mirror("satin", 0.2, 0.7),
        ],
    );
    for (k, s) in scene.surfaces.iter_mut().enumerate() {
        match k / 4 {
            0 => s.material = 2,
            5 => s.material = 3,
            _ => {}
        }
    }
    scene
}

/// The range `[k_min, k_max]` of the factors by which the emitters' rays carry more than their
/// radiance so that each emits its true power (`Propagation::emission_scale`).
pub fn emission_band(p: &vlf_core::propagate::Propagation) -> (f64, f64) {
    let emitting =
        (0..p.atlas.charts.len()).filter(|&c| p.scene.materials[p.atlas.chart_material[c] as usize].is_emitter());
    emitting
        .map(|c| p.emission_scale[c])
        .fold((f64::MAX, f64::MIN), |(lo, hi), k| (lo.min(k), hi.max(k)))
}

/// Checks a furnace (every wall emits `le`, reflects ρ) after the iterations that give `want`
/// in the exact solution: every covered texel shows `le` plus reflected light that the walls'
/// factors `band` scale, `le + (want − le)·k` with `k` in the band, to `tolerance` (f32 maps).
/// Returns the texels checked and the largest `|k − 1|` seen.
pub fn assert_furnace(
    field: &vlf_core::field::LightField,
    le: f64,
    want: f64,
    band: (f64, f64),
    tolerance: f64,
) -> (usize, f64) {
    let (mut checked, mut worst) = (0, 0.0f64);
    for (t, l) in field.radiance.iter().enumerate() {
        if !field.covered[t] {
            continue;
        }
        for &c in l {
            let k = (c as f64 - le) / (want - le);
            worst = worst.max((k - 1.0).abs());
            assert!(
                k >= band.0 - tolerance && k <= band.1 + tolerance,
                "texel {t}: {c} is le + (want − le)·{k}, outside the walls' factors {band:?} (want {want})"
            );
        }
        checked += 1;
    }
    (checked, worst)
}

/// Lambert's formula: the projected solid angle of a polygon seen from `p` on a surface of
/// normal `n`, `½·|Σ γ_i n·(a_i × a_i+1)/|a_i × a_i+1||` over its edges (`a_i` unit vectors
/// to the vertices, `γ_i` the angle between them).
pub fn projected_solid_angle(p: DVec3, n: DVec3, polygon: &[DVec3]) -> f64 {
    let mut sum = 0.0;
    for i in 0..polygon.len() {
        let a = (polygon[i] - p).normalize();
        let b = (polygon[(i + 1) % polygon.len()] - p).normalize();
        let c = a.cross(b);
        if c.length() > 1e-15 {
            sum += a.dot(b).clamp(-1.0, 1.0).acos() * n.dot(c.normalize());
        }
    }
    0.5 * sum.abs()
}

/// A small propagation split into 8 batches a pass (l = 129, N = 16, 4 iterations, the filter
/// on), the first `perturb` iterations perturbed through 3 copies: what the tests of a split
/// iteration (workers, threads, budgets) compare against one process.
pub fn split_options(perturb: u32) -> vlf_core::propagate::Options {
    use vlf_core::propagate::{Options, Perturbation, Stop};
    Options {
        directions: 129,
        grid: vlf_core::psf::GridSize::new(16, 4).unwrap(),
        stop: Stop::Iterations(4),
        perturbation: Perturbation {
            iterations: perturb,
            count: 3,
        },
        filter_sigma: Some(0.8),
        ..Options::default()
    }
}

/// A closed box of diffuse walls with one lamp: the perturbed tests' scene.
pub fn lit_box() -> Scene {
    closed_box(
        0.6,
        2,
        &[3],
        vec![material("wall", 0.6, 0.0), material("lamp", 0.2, 1.0)],
    )
}

/// A checkpoint without its wall-clock times, which are not the field's bits.
pub fn without_times(mut c: vlf_core::propagate::Checkpoint) -> vlf_core::propagate::Checkpoint {
    for s in &mut c.stats {
        s.seconds = 0.0;
    }
    c
}

/// The triangles of an icosphere of radius `r` about `centre`, the icosahedron's faces cut in
/// four `levels` times (20·4^levels triangles), each wound counter-clockwise seen from outside
/// (fronts face out). A curved mesh whose every triangle is its own plane.
pub fn icosphere(centre: DVec3, r: f64, levels: u32) -> Vec<[DVec3; 3]> {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut v: Vec<DVec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| DVec3::new(x, y, z).normalize())
    .collect();
    let mut faces: Vec<[usize; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..levels {
        let mut mid = std::collections::HashMap::new();
        let mut next = Vec::new();
        for f in &faces {
            let mut m = [0usize; 3];
            for k in 0..3 {
                let (a, b) = (f[k].min(f[(k + 1) % 3]), f[k].max(f[(k + 1) % 3]));
                m[k] = *mid.entry((a, b)).or_insert_with(|| {
                    v.push(((v[a] + v[b]) * 0.5).normalize());
                    v.len() - 1
                });
            }
            next.push([f[0], m[0], m[2]]);
            next.push([f[1], m[1], m[0]]);
            next.push([f[2], m[2], m[1]]);
            next.push([m[0], m[1], m[2]]);
        }
        faces = next;
    }
    faces.iter().map(|f| f.map(|i| centre + v[i] * r)).collect()
}
