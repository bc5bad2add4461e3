//! Dynamic objects lit by the field: the gather's normalisation (a furnace stays a furnace on
//! any object, at any pose), self-occlusion of a concave object against its analytic form
//! factor, objects blocking each other, the response to light from one side, colour bleeding,
//! what an object gathers next to a lit surface, and the gather's cost in rays. Direct light
//! comes from the field in every test (the shadow tests cover exact direct light).

mod common;

use common::closed_box;
use common::material;
use common::objects::{cube, furnace, quad};
use glam::{DQuat, DVec3};
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::{DynamicObject, Pose};
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::Bvh;
use vlf_core::scene::Material;

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
    let cup = DynamicObject::uniform("cup", triangles, Material::grey("cup", 0.8));
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
        Material::grey("plate", 0.5),
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
    let flat = DynamicObject::uniform(
        "flat",
        vec![[DVec3::ZERO, DVec3::X, DVec3::X * 2.0]],
        Material::grey("flat", 0.5),
    );
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
        // Without shadows, so that what changes is the cube and its images only.
        let with = Gatherer::with_directions(&field, &bvh, &placed, mode, 33)
            .unwrap()
            .with_shadow_samples(0);
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

/// A box whose only light is its +x wall (Le = 1, every wall black): the radiance arriving at
/// the centre is Le where a direction meets that wall and 0 elsewhere, so the gathered
/// incident radiance for a normal at angle θ from +x is `E(θ)/π`, with `E` the irradiance from
/// the wall, integrated here over a fine grid of the wall (an independent quadrature).
#[test]
fn light_from_one_side_gives_the_cosine_response() {
    let h = 0.55;
    let scene = closed_box(
        h,
        2,
        &[1],
        vec![material("black", 0.0, 0.0), material("lamp", 0.0, 1.0)],
    );
    let options = Options {
        directions: 513,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(1),
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    p.run(|_| {});
    let field = p.into_field();
    let bvh = Bvh::build(&field.scene);
    let gather = Gatherer::new(&field, &bvh, &[], SpecularMode::Rays).unwrap();
    // Off the centre, so that no direction of the set runs exactly along the wall's edges (a
    // ray through an edge counts whole for one wall, a bias of a few per cent at l = 513).
    let p = DVec3::new(0.0123, -0.0171, 0.0094);
    // E(n) = ∫_wall (n·ω)⁺ cos θ_s / r² dA over the wall x = h, |y|, |z| ≤ h.
    let irradiance = |n: DVec3| {
        let m = 400;
        let step = 2.0 * h / m as f64;
        let mut e = 0.0;
        for i in 0..m {
            for j in 0..m {
                let s = DVec3::new(h, -h + (i as f64 + 0.5) * step, -h + (j as f64 + 0.5) * step) - p;
                let r2 = s.length_squared();
                let w = s / r2.sqrt();
                e += n.dot(w).max(0.0) * w.x / r2 * step * step;
            }
        }
        e
    };
    let top = irradiance(DVec3::X) / std::f64::consts::PI;
    for degrees in [0.0f64, 30.0, 60.0, 90.0, 120.0, 150.0, 180.0] {
        let (s, c) = degrees.to_radians().sin_cos();
        let n = DVec3::new(c, 0.0, s);
        let want = irradiance(n) / std::f64::consts::PI;
        let got = gather.incident(p, n)[0];
        println!("normal at {degrees}° from the lit wall: gathered {got:.5}, analytic {want:.5}");
        assert!((got - want).abs() < 0.03 * top, "{degrees}°: {got} vs {want}");
    }
}

/// The Cornell-like box of the colour tests: a red wall at −x, a green one at +x, a white
/// floor, ceiling and back, a square lamp of half-size `lamp` in the ceiling's middle.
fn coloured_box(lamp: f64) -> LightField {
    let h = 0.55;
    let mut scene = closed_box(
        h,
        2,
        &[],
        vec![
            material("white", 0.7, 0.0),
            material("lamp", 0.0, 4.0),
            material("red", 0.0, 0.0),
            material("green", 0.0, 0.0),
        ],
    );
    scene.materials[2].diffuse = [0.7, 0.1, 0.1];
    scene.materials[3].diffuse = [0.1, 0.7, 0.1];
    for s in scene.surfaces.iter_mut() {
        if s.normal.x > 0.5 {
            s.material = 2;
        } else if s.normal.x < -0.5 {
            s.material = 3;
        }
    }
    scene.surfaces.push(common::rect(
        DVec3::new(0.0, 0.0, h - 1e-3),
        DVec3::X * lamp,
        DVec3::Y * lamp,
        -DVec3::Z,
        1,
    ));
    let options = Options {
        directions: 513,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(6),
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    p.run(|_| {});
    p.into_field()
}

/// An object near the red wall is redder on that side, and greener on the side that faces the
/// green wall.
#[test]
fn an_object_near_a_red_wall_is_redder_on_that_side() {
    let field = coloured_box(0.15);
    let bvh = Bvh::build(&field.scene);
    let objects = [cube("box", DVec3::new(-0.35, 0.0, -0.3), 0.08, 0.8)
        .place(&Pose::IDENTITY, &field.scene.normalisation)
        .unwrap()];
    let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
    let side = |x: f64| gather.incident(DVec3::new(-0.35 + x * 0.0801, 0.0, -0.3), DVec3::new(x, 0.0, 0.0));
    let (red_side, green_side) = (side(-1.0), side(1.0));
    let ratio = |l: [f64; 3]| l[0] / l[1];
    println!(
        "red/green: {:.3} facing the red wall, {:.3} facing the green one",
        ratio(red_side),
        ratio(green_side)
    );
    assert!(ratio(red_side) > 1.5 * ratio(green_side), "{red_side:?} {green_side:?}");
    assert!(
        ratio(red_side) > 1.2 && ratio(green_side) < 1.0,
        "{red_side:?} {green_side:?}"
    );
}

/// The top of a flat object lying just above the floor receives what the floor receives: its
/// gathered radiance is the floor's field radiance over the floor's ρ, averaged under the
/// plate. They differ by the field's noise at this resolution (the floor's values at these
/// points are within 3 % of a 2049/128 field's) and by the gather's direction quadrature,
/// which reads 3–6 % above the finer field here: the target is 7 % on average over six
/// points, 10 % at each.
#[test]
fn an_object_just_above_a_surface_gathers_what_the_surface_receives() {
    let field = coloured_box(0.4);
    let bvh = Bvh::build(&field.scene);
    let plate = DynamicObject::uniform(
        "plate",
        quad(DVec3::new(0.1, 0.1, -0.54), DVec3::X * 0.03, DVec3::Y * 0.03).to_vec(),
        Material::grey("plate", 0.5),
    );
    let objects = [plate.place(&Pose::IDENTITY, &field.scene.normalisation).unwrap()];
    let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
    let floor = (field.scene.surfaces.iter())
        .position(|s| s.normal.z > 0.5 && s.vertices.iter().all(|v| v.x >= -1e-9 && v.y >= -1e-9))
        .unwrap();
    let mut ratios = Vec::new();
    for (x, y) in [
        (0.1, 0.1),
        (0.3, 0.2),
        (0.45, 0.45),
        (0.2, 0.4),
        (0.05, 0.3),
        (0.4, 0.1),
    ] {
        // The floor under the plate's footprint (a texel wide each way), not one texel's value.
        let received = (0..25)
            .map(|k| {
                let (dx, dy) = ((k % 5) as f64 * 0.015 - 0.03, (k / 5) as f64 * 0.015 - 0.03);
                field.radiance_at(floor, DVec3::new(x + dx, y + dy, -0.55))[1] / 0.7
            })
            .sum::<f64>()
            / 25.0;
        let gathered = gather.incident(DVec3::new(x, y, -0.54), DVec3::Z)[1];
        println!("({x}, {y}): the floor receives {received:.4}, the object gathers {gathered:.4}");
        ratios.push(gathered / received);
    }
    let mean = ratios.iter().sum::<f64>() / ratios.len() as f64;
    assert!((mean - 1.0).abs() < 0.07, "{ratios:?}");
    assert!(ratios.iter().all(|r| (r - 1.0).abs() < 0.1), "{ratios:?}");
}

/// The gather traces one ray per direction and point: the count is `L × P`, linear in both
/// (counted, not timed).
#[test]
fn the_gather_costs_one_ray_per_direction_and_point() {
    let (field, _) = furnace(1);
    let bvh = Bvh::build(&field.scene);
    let objects = [cube("box", DVec3::ZERO, 0.1, 0.7)
        .place(&Pose::IDENTITY, &field.scene.normalisation)
        .unwrap()];
    // Normals that no direction of the sets lies exactly across.
    let normals: Vec<DVec3> = (0..7)
        .map(|k| DVec3::new(1.0, 0.13 + 0.37 * k as f64, 0.23 + 0.11 * k as f64).normalize())
        .collect();
    for l in [33, 129, 513] {
        let gather = Gatherer::with_directions(&field, &bvh, &objects, SpecularMode::Rays, l).unwrap();
        for points in [1usize, 7] {
            let before = vlf_core::dynamic::gather::rays_traced();
            for n in &normals[..points] {
                gather.incident(*n * 0.2, *n);
            }
            let rays = vlf_core::dynamic::gather::rays_traced() - before;
            assert_eq!(rays, (l * points) as u64, "l = {l}, {points} points");
        }
    }
}

/// Per vertex or per pixel: an object shaded by gathering at its vertices and interpolating
/// (what a viewer may do every frame) against the gather at every point it shows. The cube's
/// faces are split finer and finer; the interpolation's error falls as the vertices get
/// closer together, and the gathers it costs grow with them (counted). The lamp is large
/// (0.8 wide): with a small one (0.3 wide, a few of the 513 directions) the per-pixel gather
/// itself varies by several per cent from point to point as directions catch the lamp or
/// miss it, and interpolation smooths that out rather than converging to it (measured 6.0,
/// 8.3, 3.9 % for the same splits). The figures are quoted in `docs/dynamic.md`.
#[test]
fn gathering_per_vertex_converges_to_gathering_per_pixel() {
    let field = coloured_box(0.4);
    let bvh = Bvh::build(&field.scene);
    let grey = Material::grey("box", 0.6);
    let mut errors = Vec::new();
    for split in [1usize, 4, 16] {
        let object = DynamicObject::cube("box", DVec3::new(-0.2, 0.1, -0.2), 0.12, split, grey.clone());
        let objects = [object.place(&Pose::IDENTITY, &field.scene.normalisation).unwrap()];
        let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
        // Seen points: a 6 × 6 lattice of barycentric points on every face of the cube (the
        // same points whatever the split), shaded per pixel and from the split's vertices.
        let (mut sum_sq, mut sum, mut count) = (0.0, 0.0, 0usize);
        let vertex_gathers = std::cell::Cell::new(0usize);
        let mut cache: std::collections::HashMap<[u64; 6], f64> = Default::default();
        let mut at_vertex = |p: DVec3, n: DVec3| -> f64 {
            let key = [p.x, p.y, p.z, n.x, n.y, n.z].map(f64::to_bits);
            *cache.entry(key).or_insert_with(|| {
                vertex_gathers.set(vertex_gathers.get() + 1);
                gather.incident(p, n)[1]
            })
        };
        let surfaces = &objects[0].scene.surfaces;
        for s in surfaces {
            let v = &s.vertices;
            let corner = [
                at_vertex(v[0], s.normal),
                at_vertex(v[1], s.normal),
                at_vertex(v[2], s.normal),
            ];
            // A few points inside each triangle, weighted by the triangle's share of its face.
            let weight = s.area;
            for (a, b) in [(1.0 / 3.0, 1.0 / 3.0), (0.6, 0.2), (0.2, 0.6), (0.2, 0.2)] {
                let c = 1.0 - a - b;
                let p = v[0] * a + v[1] * b + v[2] * c;
                let pixel = gather.incident(p, s.normal)[1];
                let interpolated = corner[0] * a + corner[1] * b + corner[2] * c;
                sum_sq += weight * (interpolated - pixel).powi(2);
                sum += weight * pixel;
                count += 1;
            }
        }
        let total: f64 = surfaces.iter().map(|s| s.area).sum::<f64>() * 4.0;
        let error = (sum_sq / total).sqrt() / (sum / total);
        println!(
            "faces split {split} × {split}: per-vertex shading off by {:.1} % (rms, of the mean) at {count} seen points, \
             {} vertex gathers",
            100.0 * error,
            vertex_gathers.get()
        );
        errors.push((error, vertex_gathers.get()));
    }
    assert!(errors[1].0 < errors[0].0 && errors[2].0 < errors[1].0, "{errors:?}");
    assert!(errors[2].1 > errors[1].1 && errors[1].1 > errors[0].1, "{errors:?}");
}

/// What a streaming viewer fetches for an object (`dynamic::needs`) covers what its gather and
/// its shadow read, and no more than what can be seen from around it: in a box cut in two by a
/// partition, every surface a gather ray from the object's vertices meets, and every surface
/// seen past the object from the floor around it, is listed; none of the far room's.
#[test]
fn an_objects_needs_cover_its_gather_and_shadow() {
    use common::{rect, scene};
    use vlf_core::directions::DirectionSet;
    use vlf_core::dynamic::needs::needs_around;
    let h = 0.5;
    let mut box_scene = closed_box(
        h,
        6,
        &[3],
        vec![material("white", 0.7, 0.0), material("lamp", 0.7, 1.0)],
    );
    // The partition at x = 0.1, facing the room at x < 0.1.
    box_scene.surfaces.push(rect(
        DVec3::new(0.1, 0.0, 0.0),
        DVec3::Y * h,
        DVec3::Z * h,
        -DVec3::X,
        0,
    ));
    let scene = scene(box_scene.surfaces, box_scene.materials);
    let options = Options {
        directions: 9,
        grid: GridSize::new(16, 8).unwrap(),
        stop: Stop::Iterations(1),
        ..Options::default()
    };
    let field = Propagation::new(scene, options).unwrap().into_field();
    let bvh = Bvh::build(&field.scene);
    let object = cube("box", DVec3::new(-0.25, -0.35, 0.1), 0.08, 0.7)
        .place(&Pose::IDENTITY, &field.scene.normalisation)
        .unwrap();
    let directions = DirectionSet::new(129).unwrap();
    let needs = needs_around(
        &field,
        &bvh,
        &[(object.center, object.radius)],
        &directions,
        SpecularMode::Rays,
    );
    let seen = |origin: DVec3, dir: DVec3| {
        bvh.intersect(&field.scene, origin, dir, 0.0, f64::INFINITY)
            .filter(|h| h.front)
            .map(|h| h.surface as u32)
    };
    let vertices: Vec<DVec3> = object.scene.surfaces.iter().flat_map(|s| s.vertices.clone()).collect();
    let mut read = std::collections::BTreeSet::new();
    for s in &object.scene.surfaces {
        for &v in &s.vertices {
            let origin = v + s.normal * 1e-6;
            for d in 0..directions.len() {
                let w = directions.get(d).vector;
                let w = if w.dot(s.normal) > 0.0 { w } else { -w };
                read.extend(seen(origin, w));
            }
        }
    }
    for x in -8..8 {
        for z in -8..8 {
            let p = DVec3::new(-0.5 + 0.6 * (x as f64 + 8.5) / 16.0, -h + 1e-6, 0.9 * z as f64 / 8.0);
            for &v in &vertices {
                read.extend(seen(p, (v - p).normalize()));
            }
        }
    }
    let missing: Vec<_> = read.difference(&needs.surfaces).collect();
    assert!(missing.is_empty(), "read but not listed: {missing:?}");
    assert!(read.len() > 50, "{} surfaces read", read.len());
    // Nothing of the far room (beyond the partition, whose back faces the object).
    let far: Vec<_> = (needs.surfaces.iter())
        .filter(|&&s| {
            let v = &field.scene.surfaces[s as usize].vertices;
            v.iter().all(|p| p.x > 0.1 + 1e-9)
        })
        .collect();
    assert!(far.is_empty(), "surfaces of the far room listed: {far:?}");
}
