//! Shadows that moving objects cast on the static scene: the loss against its analytic value
//! (light from the field, and with exact direct light), no shadow through a wall, the same
//! bits wherever the object takes no light, soft penumbrae that do not pop as a small object
//! moves, a concave object shadowing itself, and what it costs in rays.

mod common;

use common::objects::{cube, furnace, furnace_with_first};
use common::{closed_box, material, rect};
use glam::DVec3;
use vlf_core::dynamic::gather::{Gatherer, rays_traced};
use vlf_core::dynamic::view::render_with_objects;
use vlf_core::dynamic::{DynamicObject, PlacedObject, Pose};
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::{Bvh, Camera};
use vlf_core::scene::Material;

/// A horizontal disc (a 48-gon) of radius `a` at height `z`, centred on the z axis, facing down.
fn disc(a: f64, z: f64) -> DynamicObject {
    let c = DVec3::new(0.0, 0.0, z);
    let k = 48;
    let at = |i: usize| {
        let t = std::f64::consts::TAU * i as f64 / k as f64;
        c + DVec3::new(a * t.cos(), a * t.sin(), 0.0)
    };
    // Clockwise seen from above: facing down.
    let triangles = (0..k).map(|i| [c, at(i + 1), at(i)]).collect();
    DynamicObject::uniform("disc", triangles, Material::grey("disc", 0.5))
}

/// The radiance a floor point of reflectance ρ loses under a disc of radius `a` at height `h`
/// above it, when radiance `L` arrives from every direction: `ρ/π · L · π a²/(h² + a²)` (the
/// disc's projected solid angle).
fn disc_loss(rho: f64, l: f64, a: f64, h: f64) -> f64 {
    rho * l * a * a / (h * h + a * a)
}

fn placed(object: &DynamicObject, field: &LightField) -> PlacedObject {
    object.place(&Pose::IDENTITY, &field.scene.normalisation).unwrap()
}

/// In a furnace (radiance L everywhere) the floor under a small disc loses ρ·L·a²/(h² + a²),
/// whatever the disc's size and height; direct light from the field.
#[test]
fn a_disc_takes_its_projected_solid_angle_of_light() {
    let (field, l) = furnace(6);
    let bvh = Bvh::build(&field.scene);
    let floor = -0.55;
    let p = DVec3::new(0.0, 0.0, floor);
    for (a, h) in [(0.05, 0.1), (0.1, 0.05), (0.02, 0.3), (0.005, 0.5)] {
        let objects = [placed(&disc(a, floor + h), &field)];
        let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
        let loss = gather.shadow_loss(p, DVec3::Z, [0.5; 3]).expect("the disc is overhead")[0];
        let want = disc_loss(0.5, l, a, h);
        println!("disc a = {a}, h = {h}: loss {loss:.5}, analytic {want:.5}");
        assert!((loss / want - 1.0).abs() < 0.1, "a = {a}, h = {h}: {loss} vs {want}");
    }
}

/// With exact direct light, the direct part of the shadow comes from shadow rays that the disc
/// stops, and the indirect part from the cone without the emitters' own light: the total is
/// the same analytic loss.
#[test]
fn with_exact_direct_light_the_shadow_rays_see_the_object() {
    let rho = 0.5;
    let (first, mut field, l) = furnace_with_first(6);
    field.use_exact_direct(&first, 1024).unwrap();
    let bvh = Bvh::build(&field.scene);
    let floor = -0.55;
    let point = DVec3::new(0.0, 0.0, floor);
    let floor_surface = (field.scene.surfaces.iter())
        .position(|s| s.normal.z > 0.5 && s.vertices.iter().all(|v| v.x >= -1e-9 && v.y >= -1e-9))
        .unwrap();
    for (a, h) in [(0.05, 0.1), (0.1, 0.3)] {
        let objects = [placed(&disc(a, floor + h), &field)];
        let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
        let free = Gatherer::new(&field, &bvh, &[], SpecularMode::Rays).unwrap();
        let (with, without) = (
            gather.diffuse_with_shadows(floor_surface, point)[0],
            free.diffuse_with_shadows(floor_surface, point)[0],
        );
        // Read from the field's maps, the loss is the same: its direct part counted on the
        // emitters' points, its indirect part over the cone.
        let maps = gather.shadow_loss(point, DVec3::Z, [rho; 3]).unwrap()[0];
        let want = disc_loss(rho, l, a, h);
        println!(
            "exact direct, disc a = {a}, h = {h}: loss {:.5} (from the maps {maps:.5}), analytic {want:.5}",
            without - with
        );
        assert!(
            ((without - with) / want - 1.0).abs() < 0.1,
            "{} vs {want}",
            without - with
        );
        assert!((maps / want - 1.0).abs() < 0.1, "{maps}");
    }
}

/// A box split by a wall (two-sided, at x = 0, from the floor up to z = 0.1), lit by a lamp on
/// each side: the object stands on the −x side.
fn split_box() -> LightField {
    let h = 0.55;
    let mut scene = closed_box(h, 2, &[], vec![material("white", 0.6, 0.0), material("lamp", 0.0, 3.0)]);
    for (x, normal) in [(-1e-3, -DVec3::X), (1e-3, DVec3::X)] {
        scene.surfaces.push(rect(
            DVec3::new(x, 0.0, -0.225),
            DVec3::Y * h,
            DVec3::Z * 0.325,
            normal,
            0,
        ));
    }
    for x in [-0.3, 0.3] {
        scene.surfaces.push(rect(
            DVec3::new(x, 0.0, h - 1e-3),
            DVec3::X * 0.1,
            DVec3::Y * 0.1,
            -DVec3::Z,
            1,
        ));
    }
    let options = Options {
        directions: 129,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(4),
        ..Options::default()
    };
    let mut p = Propagation::new(scene, options).unwrap();
    p.run(|_| {});
    p.into_field()
}

/// Rendered from above the −x half, looking down at an angle so that the wall's top and the
/// +x half's floor are in view too.
fn top_view() -> Camera {
    Camera::new(
        DVec3::new(-0.3, -0.5, 0.5),
        DVec3::new(0.05, 0.2, -0.55),
        DVec3::Z,
        70.0,
        48,
        36,
    )
    .unwrap()
}

/// A pixel-by-pixel look at a view with a cube on the floor: the cube's shadow darkens the
/// floor around it; nothing beyond the wall changes, bit for bit; moving the cube away and
/// back gives the first image's bits again.
#[test]
fn shadows_stay_on_their_side_of_a_wall_and_leave_other_pixels_alone() {
    let field = split_box();
    let bvh = Bvh::build(&field.scene);
    let camera = top_view();
    let cube = cube("cube", DVec3::ZERO, 0.08, 0.6);
    let at = |x: f64, y: f64| Pose {
        rotation: glam::DQuat::IDENTITY,
        translation: DVec3::new(x, y, -0.55 + 0.08),
    };
    let render = |pose: Option<Pose>| {
        let objects: Vec<PlacedObject> = pose
            .map(|p| cube.place(&p, &field.scene.normalisation).unwrap())
            .into_iter()
            .collect();
        let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
        render_with_objects(&gather, &bvh, &camera, 1)
    };
    let empty = render(None);
    let here = render(Some(at(-0.25, 0.05)));
    let there = render(Some(at(-0.4, -0.2)));
    let back = render(Some(at(-0.25, 0.05)));
    assert_eq!(here.pixels, back.pixels, "the same pose gives the same bits");
    assert_ne!(here.pixels, there.pixels);
    // Classify every pixel by what its camera ray meets first.
    let (mut darker, mut beyond) = (0, 0);
    for y in 0..camera.height {
        for x in 0..camera.width {
            let (o, d) = camera.ray(x as f64 + 0.5, y as f64 + 0.5);
            let Some(hit) = bvh.intersect(&field.scene, o, d, 0.0, f64::INFINITY) else {
                continue;
            };
            let i = (y * camera.width + x) as usize;
            let placed = cube.place(&at(-0.25, 0.05), &field.scene.normalisation).unwrap();
            let on_cube = placed.bvh.intersect(&placed.scene, o, d, 0.0, hit.t).is_some();
            // Beyond the wall and below its top: no line from there reaches the cube.
            if hit.point.x > 1e-3 && hit.point.z < 0.0 {
                beyond += 1;
                assert_eq!(
                    here.pixels[i], empty.pixels[i],
                    "pixel ({x}, {y}) beyond the wall changed"
                );
            } else if here.pixels[i][1] < empty.pixels[i][1] {
                darker += 1;
            }
            assert!(
                on_cube || here.pixels[i][1] <= empty.pixels[i][1],
                "pixel ({x}, {y}) brighter"
            );
        }
    }
    println!("{darker} pixels darkened on the cube's side, {beyond} beyond the wall unchanged");
    assert!(beyond > 100 && darker > 100, "{beyond} beyond, {darker} darker");
}

/// Under a large lamp the shadow is soft: the loss falls off smoothly from the middle of the
/// shadow, and a small object moving in small steps changes it in small steps (coverage is a
/// solid angle, not a count of the field's directions).
#[test]
fn shadows_are_soft_and_do_not_pop_as_an_object_moves() {
    let (field, l) = furnace(6);
    let bvh = Bvh::build(&field.scene);
    let floor = -0.55;
    // A flat square of side 0.008, facing down.
    let small = DynamicObject::uniform(
        "pebble",
        common::objects::quad(DVec3::ZERO, DVec3::Y * 0.004, DVec3::X * 0.004).to_vec(),
        Material::grey("pebble", 0.5),
    );
    let loss_at = |x: f64| {
        let pose = Pose {
            rotation: glam::DQuat::IDENTITY,
            translation: DVec3::new(x, 0.0, floor + 0.1),
        };
        let objects = [small.place(&pose, &field.scene.normalisation).unwrap()];
        let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
        gather
            .shadow_loss(DVec3::new(0.0, 0.0, floor), DVec3::Z, [0.5; 3])
            .map_or(0.0, |c| c[0])
    };
    // A square of side s = 0.008 at height h = 0.1, moved x to the side, covers s² cos θ / r²
    // of the floor point's sky at angle θ (cos θ = h/r) and takes ρ/π · L · s² cos⁴θ / h² of
    // its light.
    let analytic = |x: f64| {
        let cos = 0.1 / (0.01 + x * x).sqrt();
        0.5 / std::f64::consts::PI * l * 0.008 * 0.008 * cos.powi(4) / 0.01
    };
    let xs: Vec<f64> = (0..=40).map(|k| 0.0025 * k as f64).collect();
    let steps: Vec<f64> = xs.iter().map(|&x| loss_at(x)).collect();
    let peak = analytic(0.0);
    for (k, &x) in xs.iter().enumerate() {
        assert!(
            (steps[k] - analytic(x)).abs() < 0.05 * peak,
            "x = {x}: {} vs {}",
            steps[k],
            analytic(x)
        );
        if k > 0 {
            // Each step of the motion changes the shadow as the analytic curve does, to within
            // 3 % of its depth (the cone's K = 128 cells meet the square's edge a little
            // differently each time). Counted in the field's 513 directions (cells of 0.012 sr),
            // the square (0.0064 sr) would be all or nothing.
            let (got, want) = (steps[k] - steps[k - 1], analytic(x) - analytic(xs[k - 1]));
            assert!(
                (got - want).abs() < 0.03 * peak,
                "x = {x}: a step of {got}, analytic {want}"
            );
        }
    }
}

/// A cup shadows its own floor: a point on the static floor under the cup's open mouth, and a
/// point of the cup gathering inside it, both lose light to the cup's walls.
#[test]
fn a_concave_object_shadows_itself_and_what_lies_under_it() {
    let (field, l) = furnace(6);
    let bvh = Bvh::build(&field.scene);
    let a = 0.1;
    let base = DVec3::new(0.0, 0.0, -0.45);
    let mut triangles: Vec<[DVec3; 3]> = Vec::new();
    // Floor (facing up) and four walls (facing in), open at the top; thin-walled.
    triangles.extend(common::objects::quad(base, DVec3::X * a, DVec3::Y * a));
    for (axis, side) in [
        (DVec3::X, DVec3::Y),
        (DVec3::Y, -DVec3::X),
        (-DVec3::X, -DVec3::Y),
        (-DVec3::Y, DVec3::X),
    ] {
        triangles.extend(common::objects::quad(
            base + axis * a + DVec3::Z * (a / 2.0),
            DVec3::Z * (a / 2.0),
            side * a,
        ));
    }
    let cup = DynamicObject::uniform("cup", triangles, Material::grey("cup", 0.5));
    let objects = [placed(&cup, &field)];
    let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
    let inside = gather.incident(base + DVec3::Z * 1e-4, DVec3::Z)[0] / l;
    assert!(inside < 0.65, "the cup's walls take light from its floor: {inside}");
    // The static floor under the cup sees nothing but the cup's underside: a fraction of its
    // hemisphere over its distance 0.1 to a square of half-size 0.1 is gone.
    let loss = gather
        .shadow_loss(DVec3::new(0.0, 0.0, -0.55), DVec3::Z, [0.5; 3])
        .unwrap()[0];
    assert!(loss > 0.5 * l * 0.5, "{loss}");
}

/// Shadow cones cost K rays per object and static point that sees the object, none for a point
/// that does not (the object is below its horizon).
#[test]
fn shadows_cost_k_rays_per_object_and_point() {
    let (field, _) = furnace(1);
    let bvh = Bvh::build(&field.scene);
    let objects = [
        placed(&cube("a", DVec3::new(0.2, 0.0, 0.0), 0.05, 0.5), &field),
        placed(&cube("b", DVec3::new(-0.2, 0.0, 0.0), 0.05, 0.5), &field),
    ];
    for k in [16, 64] {
        let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays)
            .unwrap()
            .with_shadow_samples(k);
        let before = rays_traced();
        gather.shadow_loss(DVec3::new(0.0, 0.0, -0.55), DVec3::Z, [0.5; 3]);
        assert_eq!(rays_traced() - before, 2 * k as u64);
        let before = rays_traced();
        // On the ceiling facing up (away from the room): both objects are below its horizon.
        assert!(
            gather
                .shadow_loss(DVec3::new(0.0, 0.0, 0.55), DVec3::Z, [0.5; 3])
                .is_none()
        );
        assert_eq!(rays_traced() - before, 0);
    }
}

/// A lamp that a large object hides is seen by few of the object's cone cells: its direct
/// light is counted on the lamp's own points instead, so the shadow is smooth from one floor
/// point to the next (no speckles), and under the object's middle the lamp is gone.
#[test]
fn a_small_lamp_behind_a_large_object_casts_a_smooth_shadow() {
    let field = split_box();
    let bvh = Bvh::build(&field.scene);
    let plate = DynamicObject::uniform(
        "plate",
        common::objects::quad(DVec3::new(-0.3, 0.0, -0.2), DVec3::Y * 0.2, DVec3::X * 0.2).to_vec(),
        Material::grey("plate", 0.5),
    );
    let objects = [placed(&plate, &field)];
    let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
    let losses: Vec<f64> = (0..=120)
        .map(|k| {
            let p = DVec3::new(-0.3, -0.45 + 0.0075 * k as f64, -0.55);
            gather.shadow_loss(p, DVec3::Z, [0.6; 3]).map_or(0.0, |l| l[1])
        })
        .collect();
    let peak = losses.iter().copied().fold(0.0, f64::max);
    // The penumbra is a linear ramp (a square lamp behind a straight edge), so the loss's
    // second differences are small: at most the ramp's slope (7 % of the peak per step) at its
    // two ends, where it starts and stops, and about 1 % everywhere else. A speckle (the lamp,
    // about 80 % of the loss, caught by a cell at one point and not the next: it covers 1.6
    // cells here) would be a spike of tens of per cent.
    for w in losses.windows(3) {
        assert!((w[2] - 2.0 * w[1] + w[0]).abs() < 0.1 * peak, "{losses:?}");
    }
    // In the umbra (under the middle) the lamp's direct light, ρ/π · E, is all lost.
    let e = gather
        .emitters()
        .irradiance(DVec3::new(-0.3, 0.0, -0.55), DVec3::Z, |o, w, t| {
            bvh.intersect(&field.scene, o, w, 0.0, t).is_some()
        });
    assert!(
        losses[60] > 0.6 / std::f64::consts::PI * e[1],
        "{} vs {e:?}",
        losses[60]
    );
}

/// What leaving out the light an object reflects onto the static scene costs: next to a grey
/// cube on the floor, the shadow takes `ΔL` and the cube would give back
/// `ρ/π ∫ L_obj (n·ω)⁺ dω` over the directions it covers (integrated here on 400 cells of
/// its cone, the cube's radiance gathered at each). The ratio is the shadow's relative error
/// there without it, quoted in `docs/dynamic.md`; `with_bounce_light` gives it back.
#[test]
fn the_light_an_object_reflects_onto_the_scene_is_measured() {
    let field = split_box();
    let bvh = Bvh::build(&field.scene);
    let cube = cube("cube", DVec3::new(-0.3, 0.0, -0.47), 0.08, 0.6);
    let objects = [placed(&cube, &field)];
    let gather = Gatherer::with_directions(&field, &bvh, &objects, SpecularMode::Rays, 129).unwrap();
    let bouncing = Gatherer::with_directions(&field, &bvh, &objects, SpecularMode::Rays, 129)
        .unwrap()
        .with_bounce_light(true);
    let mut ratios = Vec::new();
    for gap in [0.02, 0.1] {
        let p = DVec3::new(-0.3 + 0.08 + gap, 0.01, -0.55);
        let loss = gather.shadow_loss(p, DVec3::Z, [0.6; 3]).unwrap()[1];
        let floor = (field.scene.surfaces.iter())
            .position(|s| s.normal.z > 0.5 && s.vertices.iter().all(|v| v.x <= 1e-9 && v.y >= -1e-9))
            .unwrap();
        let lit = field.radiance_at(floor, p)[1];
        // Cells of equal solid angle over the cone of the cube's bounding sphere.
        let o = &objects[0];
        let to = o.center - p;
        let cos_alpha = (1.0 - (o.radius / to.length()).powi(2)).max(0.0).sqrt();
        let axis = to.normalize();
        let (u, v) = axis.any_orthonormal_pair();
        let cells = 400;
        let cell = std::f64::consts::TAU * (1.0 - cos_alpha) / cells as f64;
        let mut given_back = 0.0;
        for i in 0..cells {
            let z = 1.0 - (1.0 - cos_alpha) * (i as f64 + 0.5) / cells as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * 2.399_963_229_728_653;
            let w = (u * (r * phi.cos()) + v * (r * phi.sin()) + axis * z).normalize();
            if w.z <= 0.0 {
                continue;
            }
            if let Some(hit) = o.intersect(p + DVec3::Z * 1e-7, w, f64::INFINITY).filter(|h| h.front) {
                let n = o.scene.surfaces[hit.surface].normal;
                let l = gather.diffuse(hit.point + n * 1e-7, n, [0.6; 3])[1];
                given_back += 0.6 / std::f64::consts::PI * l * w.z * cell;
            }
        }
        println!(
            "floor {gap} from a grey cube (radiance {lit:.4} without it): the shadow takes {loss:.5}, \
             the cube would give back {given_back:.5} ({:.0} % of the shadow, {:.1} % of the floor)",
            100.0 * given_back / loss,
            100.0 * given_back / lit
        );
        ratios.push(given_back / loss);
        // Given back (`with_bounce_light`, the cube's light flat per triangle): the loss less
        // what the 400 cells found, within a tenth of it.
        let returned = loss - bouncing.shadow_loss(p, DVec3::Z, [0.6; 3]).unwrap()[1];
        println!("  with the cube's light given back, {returned:.5} of it");
        assert!(
            (returned - given_back).abs() < 0.1 * given_back,
            "{returned} vs {given_back}"
        );
    }
    assert!(ratios.iter().all(|&r| r > 0.0 && r < 0.5), "{ratios:?}");
}

/// A gather ray that meets the static scene where an object shades it reads the shadowed
/// radiance (`with_gather_shadows`): a cube's face turned away from the lamp, which sees mostly
/// the floor in the cube's own shadow, gathers what the brute-force sum does — every gather
/// ray's radiance less the exact shadow loss where it lands — within 3 %, where the gather
/// that does not see the shadow is several times further off. Direct light from the field.
#[test]
fn the_gather_sees_the_objects_shadows_on_the_scene() {
    let field = split_box();
    let bvh = Bvh::build(&field.scene);
    // Under the lamp at (−0.3, 0), shifted towards −y: its −y face looks at its own shadow.
    let objects = [placed(&cube("box", DVec3::new(-0.3, -0.25, -0.47), 0.08, 0.6), &field)];
    objects[0].check_clear(&field.scene, &bvh).unwrap();
    let plain = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays).unwrap();
    let seeing = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays)
        .unwrap()
        .with_gather_shadows(true);
    let n = -DVec3::Y;
    let p = DVec3::new(-0.3, -0.33 - 1e-6, -0.47);
    let origin = p + n * 1e-6;
    let (mut sum, mut weights) = (0.0, 0.0);
    let set = plain.directions();
    for d in 0..set.len() {
        let direction = set.get(d);
        let c = n.dot(direction.vector);
        let (dir, w) = if c > 0.0 {
            (direction.vector, c * direction.weight)
        } else {
            (-direction.vector, -c * direction.weight)
        };
        let mut l = plain.arriving(origin, dir)[0];
        if let Some(hit) = bvh.intersect(&field.scene, origin, dir, 0.0, f64::INFINITY)
            && plain.nearest_object(origin, dir, hit.t).is_none()
        {
            let rho = field.scene.material(hit.surface).diffuse;
            let normal = field.scene.surfaces[hit.surface].normal;
            l -= plain.shadow_loss(hit.point, normal, rho).map_or(0.0, |loss| loss[0]);
        }
        sum += l.max(0.0) * w;
        weights += w;
    }
    let brute = sum / weights;
    let (blind, sees) = (plain.incident(p, n)[0], seeing.incident(p, n)[0]);
    println!("gathered: blind to the shadow {blind:.4}, seeing it {sees:.4}, brute force {brute:.4}");
    assert!(blind > 1.05 * brute, "the shadow matters here: {blind} vs {brute}");
    assert!((sees - brute).abs() < 0.03 * brute, "{sees} vs {brute}");
    assert!(
        (sees - brute).abs() < 0.25 * (blind - brute),
        "{sees} vs {brute} and {blind}"
    );
    // Beyond the wall, looking down at the floor and the walls there, which the cube cannot
    // see: the same but for the few texels at the wall's foot whose centres lie on the cube's
    // side (a texel straddling an edge reads both sides, as the field's radiance does).
    let far = DVec3::new(0.3, 0.3, -0.3);
    let (a, b) = (plain.incident(far, -DVec3::Z)[0], seeing.incident(far, -DVec3::Z)[0]);
    assert!((a - b).abs() < 1e-4 * a, "{a} vs {b}");
}

/// With the objects' light given back (`with_bounce_light`), a disc of reflectance ρd over a
/// furnace floor sends back ρd·L of the L it hides: the floor loses (1 − ρd)·ρ·L·a²/(h² + a²).
/// Direct light from the field.
#[test]
fn a_disc_gives_back_the_light_it_reflects() {
    let (field, l) = furnace(6);
    let bvh = Bvh::build(&field.scene);
    let floor = -0.55;
    let p = DVec3::new(0.0, 0.0, floor);
    for (a, h) in [(0.05, 0.1), (0.1, 0.05)] {
        let objects = [placed(&disc(a, floor + h), &field)];
        let gather = Gatherer::new(&field, &bvh, &objects, SpecularMode::Rays)
            .unwrap()
            .with_bounce_light(true);
        let light = gather.object_light_cache().expect("computed")[0][0][0];
        assert!(
            (light - 0.5 * l).abs() < 1e-3 * l,
            "the disc sends {light}, want {}",
            0.5 * l
        );
        let loss = gather.shadow_loss(p, DVec3::Z, [0.5; 3]).expect("the disc is overhead")[0];
        let want = (1.0 - 0.5) * disc_loss(0.5, l, a, h);
        println!("disc a = {a}, h = {h}, giving back its light: loss {loss:.5}, analytic {want:.5}");
        assert!((loss / want - 1.0).abs() < 0.1, "a = {a}, h = {h}: {loss} vs {want}");
    }
}
