//! Dynamic objects lit by the field: the gather's normalisation (a furnace stays a furnace on
//! any object, at any pose), self-occlusion of a concave object against its analytic form
//! factor, and objects blocking each other. Direct light comes from the field in every test.

mod common;

use common::{closed_box, material};
use glam::{DQuat, DVec3};
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::{DynamicObject, Pose};
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::Bvh;
use vlf_core::scene::Material;

/// A furnace (every wall emits Le = 1 and reflects ρ = 0.5) after `k` iterations: uniform
/// radiance `Le·(1 − ρ^(k+1))/(1 − ρ)` in every texel, to 1e-5.
fn furnace(k: u32) -> (LightField, f64) {
    let (rho, le) = (0.5, 1.0);
    let scene = closed_box(
        0.55,
        2,
        &[0, 1, 2, 3, 4, 5],
        vec![material("unused", rho, 0.0), material("glow", rho, le)],
    );
    let options = Options {
        directions: 129,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(k),
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    p.run(|_| {});
    (p.into_field(), le * (1.0 - rho.powi(k as i32 + 1)) / (1.0 - rho))
}

fn grey(name: &str, rho: f64) -> Material {
    Material {
        name: name.into(),
        diffuse: [rho; 3],
        specular: [0.0; 3],
        emission: [0.0; 3],
        albedo_texture: None,
    }
}

/// The two triangles of the quad `c ± a ± b`, facing `a × b`.
fn quad(c: DVec3, a: DVec3, b: DVec3) -> [[DVec3; 3]; 2] {
    let (p0, p1, p2, p3) = (c - a - b, c + a - b, c + a + b, c - a + b);
    [[p0, p1, p2], [p0, p2, p3]]
}

/// A cube of half-size `h` around `c`, facing out.
fn cube(name: &str, c: DVec3, h: f64, rho: f64) -> DynamicObject {
    let mut triangles = Vec::new();
    for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
        let u = if axis == DVec3::X {
            DVec3::Y
        } else if axis == DVec3::Y {
            DVec3::Z
        } else {
            DVec3::X
        };
        let v = axis.cross(u);
        triangles.extend(quad(c + axis * h, u * h, v * h));
        triangles.extend(quad(c - axis * h, v * h, u * h));
    }
    DynamicObject::uniform(name, triangles, grey(name, rho))
}

/// A uniform field gives every point of an object exactly ρ·L, whatever its normal and pose:
/// the gather divides by its own quadrature's cosine sum.
#[test]
fn a_furnace_lights_an_object_uniformly() {
    let (field, want) = furnace(6);
    let bvh = Bvh::build(&field.scene);
    let object = cube("box", DVec3::ZERO, 0.1, 0.7);
    for pose in [
        Pose::IDENTITY,
        Pose {
            rotation: DQuat::from_axis_angle(DVec3::new(1.0, 2.0, 0.5).normalize(), 0.8),
            translation: DVec3::new(0.12, -0.2, 0.05),
        },
    ] {
        let placed = object.place(&pose, &field.scene.normalisation).unwrap();
        let objects = [placed];
        let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
        for s in &objects[0].scene.surfaces {
            let centre = s.vertices.iter().copied().sum::<DVec3>() / 3.0;
            let l = gather.diffuse(centre, s.normal, [0.7; 3]);
            for c in l {
                assert!((c - 0.7 * want).abs() < 1e-4 * want, "{c} vs {}", 0.7 * want);
            }
        }
    }
}

/// A cup (a square floor of side 2a with walls of height a, open at the top) in a uniform
/// field: at the centre of its floor only the opening lets light in, so the gathered radiance
/// is L times the opening's form factor, 4·F(1, 1) = 0.5541 (point to a parallel rectangle).
/// The object blocks its own gather.
#[test]
fn a_concave_object_shades_itself_by_its_form_factor() {
    let (field, want) = furnace(6);
    let bvh = Bvh::build(&field.scene);
    let a = 0.15;
    let base = DVec3::new(0.0, 0.0, -0.2);
    let mut triangles = Vec::new();
    triangles.extend(quad(base, DVec3::X * a, DVec3::Y * a)); // floor, facing +z
    for (axis, side) in [
        (DVec3::X, DVec3::Y),
        (DVec3::Y, -DVec3::X),
        (-DVec3::X, -DVec3::Y),
        (-DVec3::Y, DVec3::X),
    ] {
        // A wall at `axis·a`, from the floor up to a, facing in.
        triangles.extend(quad(
            base + axis * a + DVec3::Z * (a / 2.0),
            DVec3::Z * (a / 2.0),
            side * a,
        ));
    }
    let cup = DynamicObject::uniform("cup", triangles, grey("cup", 0.8));
    let n = &field.scene.normalisation;
    let objects = [cup.place(&Pose::IDENTITY, n).unwrap()];
    let f = |x: f64, y: f64| {
        let (sx, sy) = ((1.0 + x * x).sqrt(), (1.0 + y * y).sqrt());
        (x / sx * (y / sx).atan() + y / sy * (x / sy).atan()) / (2.0 * std::f64::consts::PI)
    };
    let form_factor = 4.0 * f(1.0, 1.0);
    assert!((form_factor - 0.5541).abs() < 1e-3);
    // The discrete directions see the opening's edge to about a direction's width: the error
    // falls as the set grows (measured 0.087, 0.036, 0.020, 0.009 for l = 129 … 8193).
    let errors: Vec<f64> = [513, 2049, 8193]
        .iter()
        .map(|&l| {
            let g = Gatherer::with_directions(&field, &bvh, &objects, SpecularMode::Rays, l).unwrap();
            let ratio = g.incident(n.to_vlf(base), DVec3::Z)[0] / want;
            println!("cup floor, l = {l}: gathered {ratio:.4} of L, the opening's form factor is {form_factor:.4}");
            (ratio - form_factor).abs()
        })
        .collect();
    assert!(
        errors[0] < 0.05 && errors[1] < errors[0] && errors[2] < errors[1] && errors[2] < 0.012,
        "{errors:?}"
    );
    // Without the cup in the way, the full field arrives.
    let free = Gatherer::new(&field, &bvh, &[], SpecularMode::Rays).unwrap();
    assert!((free.incident(n.to_vlf(base), DVec3::Z)[0] / want - 1.0).abs() < 1e-4);
}

/// One object blocks another's gather where it stands in the way, and nowhere else.
#[test]
fn objects_block_each_other() {
    let (field, want) = furnace(6);
    let bvh = Bvh::build(&field.scene);
    let n = &field.scene.normalisation;
    let small = cube("small", DVec3::ZERO, 0.02, 0.5);
    // A large plate just above the small cube's top face, facing down.
    let plate = DynamicObject::uniform(
        "plate",
        quad(DVec3::new(0.0, 0.0, 0.1), DVec3::Y * 0.3, DVec3::X * 0.3).to_vec(),
        grey("plate", 0.5),
    );
    let objects = [
        small.place(&Pose::IDENTITY, n).unwrap(),
        plate.place(&Pose::IDENTITY, n).unwrap(),
    ];
    let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
    let top = gather.incident(n.to_vlf(DVec3::new(0.0, 0.0, 0.02)), DVec3::Z)[0] / want;
    let bottom = gather.incident(n.to_vlf(DVec3::new(0.0, 0.0, -0.02)), -DVec3::Z)[0] / want;
    // The plate (half-size 0.3 at height 0.08 above the top face) covers most of its sky.
    assert!(top < 0.2, "{top}");
    assert!((bottom - 1.0).abs() < 1e-4, "{bottom}");
}

/// Bad objects are refused with their name.
#[test]
fn bad_objects_are_refused() {
    let n = vlf_core::scene::Normalisation {
        center: DVec3::ZERO,
        scale: 1.0,
    };
    let mut o = cube("lamp", DVec3::ZERO, 0.1, 0.5);
    o.materials[0].emission = [1.0; 3];
    let e = o.place(&Pose::IDENTITY, &n).unwrap_err().to_string();
    assert!(e.contains("object 'lamp'") && e.contains("emits"), "{e}");
    let mut o = cube("nan", DVec3::ZERO, 0.1, 0.5);
    o.triangles[3][1].x = f64::NAN;
    assert!(
        o.place(&Pose::IDENTITY, &n)
            .unwrap_err()
            .to_string()
            .contains("triangle 3")
    );
    let mut o = cube("bright", DVec3::ZERO, 0.1, 0.5);
    o.materials[0].diffuse = [1.2; 3];
    assert!(
        o.place(&Pose::IDENTITY, &n)
            .unwrap_err()
            .to_string()
            .contains("not physical")
    );
    let flat = DynamicObject::uniform("flat", vec![[DVec3::ZERO, DVec3::X, DVec3::X * 2.0]], grey("flat", 0.5));
    assert!(
        flat.place(&Pose::IDENTITY, &n)
            .unwrap_err()
            .to_string()
            .contains("no triangle has an area")
    );
}

/// An object file is read in the scene's coordinates, with no emitter and several materials:
/// placed with the field's normalisation, its vertices land where the scene's would.
#[test]
fn objects_load_in_scene_coordinates_without_an_emitter() {
    let dir = std::env::temp_dir().join(format!("vlf-dynamic-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("o.mtl"),
        "newmtl red\nKd 0.8 0.1 0.1\nnewmtl blue\nKd 0.1 0.1 0.8\n",
    )
    .unwrap();
    let obj = "mtllib o.mtl\nv 10 0 0\nv 12 0 0\nv 12 2 0\nv 10 2 0\nv 10 0 1\n\
               usemtl red\nf 1 2 3 4\nusemtl blue\nf 1 5 2\n";
    std::fs::write(dir.join("o.obj"), obj).unwrap();
    let (object, warnings) = DynamicObject::load(&dir.join("o.obj")).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(object.triangles.len(), 3, "a quad in two triangles and a triangle");
    assert_eq!(object.materials.len(), 2);
    for t in &object.triangles {
        for p in t {
            assert!(
                (p.x >= 10.0 - 1e-9 && p.x <= 12.0 + 1e-9) && p.z.abs() <= 1.0 + 1e-9,
                "{p}"
            );
        }
    }
    // Placed in a field whose scene is elsewhere, with that scene's normalisation.
    let (field, _) = furnace(1);
    let n = field.scene.normalisation;
    let placed = object.place(&Pose::IDENTITY, &n).unwrap();
    let v = placed.scene.surfaces[0].vertices[0];
    assert!((n.to_scene(v) - object.triangles[0][0]).length() < 1e-9);
    let reds: Vec<f64> = (placed.scene.surfaces.iter())
        .map(|s| placed.scene.materials[s.material].diffuse[0])
        .collect();
    assert_eq!(reds, [0.8, 0.8, 0.1], "each triangle keeps its material");
    // A file whose material emits is not an object.
    std::fs::write(dir.join("lamp.mtl"), "newmtl lamp\nKd 0.5 0.5 0.5\nKe 1 1 1\n").unwrap();
    std::fs::write(
        dir.join("lamp.obj"),
        "mtllib lamp.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl lamp\nf 1 2 3\n",
    )
    .unwrap();
    let e = DynamicObject::load(&dir.join("lamp.obj")).unwrap_err().to_string();
    assert!(e.contains("emits"), "{e}");
    // A malformed file is the importer's error.
    std::fs::write(dir.join("bad.obj"), "v 0 0 nan\nf 1 1 1\n").unwrap();
    assert!(DynamicObject::load(&dir.join("bad.obj")).is_err());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An object is seen in the static scene's mirrors, traced or read from the field's rays: next
/// to the cube's own pixels (what changes when mirrors reflect nothing, depth 0), pixels of the
/// wall mirror change too.
#[test]
fn an_object_is_seen_in_mirrors() {
    use vlf_core::dynamic::view::render_with_objects;
    use vlf_core::render::Camera;
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/mirrors.obj");
    let (scene, _) = vlf_core::scene::load_scene(&path, &Default::default()).unwrap();
    let options = Options {
        directions: 33,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(2),
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    p.run(|_| {});
    let field = p.into_field();
    let bvh = Bvh::build(&field.scene);
    let camera = Camera::new(
        DVec3::new(278.0, 273.0, -800.0),
        DVec3::new(278.0, 273.0, 0.0),
        DVec3::Y,
        39.0,
        40,
        40,
    )
    .unwrap();
    // A cube near the back of the wall mirror (x = 1, facing +x): its image in the mirror is
    // seen from the camera through the mirror's middle.
    let cube = cube("cube", DVec3::new(60.0, 250.0, 500.0), 40.0, 0.7);
    let placed = [cube.place(&Pose::IDENTITY, &field.scene.normalisation).unwrap()];
    let changed = |mode: SpecularMode| {
        let with = Gatherer::with_directions(&field, &bvh, &placed, mode, 33).unwrap();
        let without = Gatherer::with_directions(&field, &bvh, &[], mode, 33).unwrap();
        let (a, b) = (
            render_with_objects(&with, &bvh, &camera, 1),
            render_with_objects(&without, &bvh, &camera, 1),
        );
        (0..a.pixels.len())
            .filter(|&i| a.pixels[i] != b.pixels[i])
            .collect::<Vec<usize>>()
    };
    let direct = changed(SpecularMode::Trace { depth: 0 });
    assert!(!direct.is_empty());
    for mode in [SpecularMode::Rays, SpecularMode::Trace { depth: 4 }] {
        let seen = changed(mode);
        assert!(
            direct.iter().all(|i| seen.contains(i)),
            "the cube's own pixels change ({mode:?})"
        );
        let in_mirror: Vec<usize> = seen.iter().copied().filter(|i| !direct.contains(i)).collect();
        assert!(
            in_mirror.len() >= 4,
            "the cube is not seen in the mirror ({mode:?}): {in_mirror:?}"
        );
        // The mirror is on the wall x = 1, which this camera (looking along +z, up +y) sees on
        // the image's right.
        assert!(in_mirror.iter().all(|&i| i % 40 >= 20), "{mode:?}: {in_mirror:?}");
    }
}
