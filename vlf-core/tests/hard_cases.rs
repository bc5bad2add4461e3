//! Hard cases stay numerically stable.
//!
//! Scenes built to stress the method's arithmetic: light bouncing "forever"
//! between parallel mirrors, grazing incidence, sliver and sub-ray polygons,
//! an emitter coplanar with its ceiling, extreme scene scales, emitters 10⁶
//! apart in radiance, an enclosure with ρ = 0.99 and a box of mirrors. Every
//! case checks that nothing is NaN or infinite (or negative), that each
//! iteration conserves power, that the unshot power falls geometrically, and,
//! where there is one, the analytic or reference answer within a stated bound.

mod common;

use common::*;
use glam::DVec3;
use vlf_core::field::LightField;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::{FaceOrigin, ImportOptions, MAX_MIRROR_REFLECTANCE, Material, Scene};

type Rgb = [f64; 3];

fn lum(c: &Rgb) -> f64 {
    c.iter().sum::<f64>() / 3.0
}

fn options(l: usize, n: u32, stop: Stop) -> Options {
    Options {
        directions: l,
        grid: GridSize::new(n, 8).unwrap(),
        stop,
        ..Options::default()
    }
}

fn propagate(scene: Scene, options: Options) -> Propagation {
    let mut p = Propagation::new(scene, options).expect("propagation setup");
    p.run(|_| {});
    p
}

/// Every number the propagation holds is finite, and every power, area and
/// radiance is non-negative: the Total / Current maps, the discrete areas,
/// the mirror maps and every field of every iteration's statistics.
fn assert_sane(p: &Propagation, case: &str) {
    let ok = |v: f64| v.is_finite() && v >= 0.0;
    for (name, map) in [("total", &p.total), ("current", &p.current)] {
        if let Some((t, v)) = map.iter().enumerate().find(|(_, v)| !v.iter().all(|&c| ok(c))) {
            panic!("{case}: {name}[{t}] = {v:?}");
        }
    }
    if let Some((t, a)) = p.projected_area.iter().enumerate().find(|(_, a)| !ok(**a)) {
        panic!("{case}: projected_area[{t}] = {a}");
    }
    assert!(p.emitted.iter().all(|&c| ok(c)), "{case}: emitted {:?}", p.emitted);
    if let Some(s) = p.specular.as_ref() {
        for (d, m) in s.maps.iter().enumerate() {
            for (name, map) in [("unshot", &m.unshot), ("total", &m.total), ("incident", &m.incident)] {
                if let Some((k, v)) = map.iter().enumerate().find(|(_, v)| !v.iter().all(|&c| ok(c))) {
                    panic!("{case}: mirror map {name} of direction {d}, slot {k} = {v:?}");
                }
            }
        }
    }
    for s in &p.stats {
        let f = &s.flow;
        for (name, v) in [
            ("flow.shot", f.shot),
            ("flow.received", f.received),
            ("flow.escaped", f.escaped),
            ("flow.blocked", f.blocked),
            ("unshot", s.unshot),
            ("exchange.incident", s.exchange.incident),
            ("exchange.reflected", s.exchange.reflected),
            ("specular_unshot", s.specular_unshot),
        ] {
            assert!(
                v.iter().all(|&c| ok(c)),
                "{case}: iteration {}: {name} = {v:?}",
                s.index
            );
        }
        assert!(ok(s.seconds), "{case}: iteration {}: seconds = {}", s.index, s.seconds);
    }
    assert!(
        ok(p.unshot_fraction()),
        "{case}: unshot fraction {}",
        p.unshot_fraction()
    );
}

/// The finished field's radiance maps are finite and non-negative.
fn assert_field_sane(field: &LightField, case: &str) {
    if let Some((t, v)) = field
        .radiance
        .iter()
        .enumerate()
        .find(|(_, v)| !v.iter().all(|&c| c.is_finite() && c >= 0.0))
    {
        panic!("{case}: field radiance[{t}] = {v:?}");
    }
    assert!(field.unshot_fraction.is_finite(), "{case}");
}

/// Power bookkeeping of every iteration, per channel, to `tol` relative:
/// what was unshot after the previous iteration (the emitted power before the
/// first) is exactly what is shot, and what is shot is received, escapes or
/// is blocked. Returns the largest relative error seen.
fn assert_balance(p: &Propagation, tol: f64, case: &str) -> f64 {
    let mut worst: f64 = 0.0;
    let mut before = p.emitted;
    for s in &p.stats {
        let f = &s.flow;
        for c in 0..3 {
            let out = f.received[c] + f.escaped[c] + f.blocked[c];
            if f.shot[c] == 0.0 {
                assert_eq!(
                    out, 0.0,
                    "{case}: iteration {}: nothing shot, yet {out} arrived",
                    s.index
                );
            } else {
                let rel = (f.shot[c] - out).abs() / f.shot[c];
                worst = worst.max(rel);
                assert!(
                    rel <= tol,
                    "{case}: iteration {}, channel {c}: shot {} ≠ received {} + escaped {} + blocked {} (rel {rel:.2e})",
                    s.index,
                    f.shot[c],
                    f.received[c],
                    f.escaped[c],
                    f.blocked[c]
                );
            }
            let rel = (f.shot[c] - before[c]).abs() / before[c].max(f64::MIN_POSITIVE);
            worst = worst.max(rel);
            assert!(
                rel <= tol,
                "{case}: iteration {}, channel {c}: shot {} but {} was unshot (rel {rel:.2e})",
                s.index,
                f.shot[c],
                before[c]
            );
        }
        before = s.unshot;
    }
    worst
}

/// With one ρs for all mirrors: reflected = ρs × incident in every iteration
/// (to `tol` relative). Returns the number of iterations in which light
/// arrived on mirrors.
fn assert_mirror_exchange(p: &Propagation, rho_s: f64, tol: f64, case: &str) -> usize {
    let mut lit = 0;
    for s in &p.stats {
        let x = &s.exchange;
        for c in 0..3 {
            let want = rho_s * x.incident[c];
            assert!(
                (x.reflected[c] - want).abs() <= tol * want,
                "{case}: iteration {}: reflected {} ≠ {rho_s} × incident {}",
                s.index,
                x.reflected[c],
                x.incident[c]
            );
        }
        if lum(&x.incident) > 0.0 {
            lit += 1;
        }
    }
    lit
}

/// Geometric convergence: from iteration `from` on, each iteration's unshot
/// power is at most `factor` (< 1) times the previous one's. Returns the
/// largest ratio seen.
fn assert_geometric(p: &Propagation, factor: f64, from: usize, case: &str) -> f64 {
    assert!(factor < 1.0);
    let mut worst: f64 = 0.0;
    for k in from.max(1)..p.stats.len() {
        let (a, b) = (lum(&p.stats[k - 1].unshot), lum(&p.stats[k].unshot));
        if a == 0.0 {
            assert_eq!(b, 0.0, "{case}: iteration {k}: unshot power appeared from nothing");
            continue;
        }
        let ratio = b / a;
        worst = worst.max(ratio);
        assert!(
            ratio <= factor,
            "{case}: iteration {k}: unshot {b:.4e} > {factor} × previous {a:.4e} (ratio {ratio:.6})"
        );
    }
    worst
}

/// Mean outgoing radiance (luminance) of the given surfaces: their Total
/// power over their discrete areas, in f64.
fn mean_radiance(p: &Propagation, surfaces: &[usize]) -> f64 {
    let (mut power, mut area) = (0.0, 0.0);
    for &s in surfaces {
        let g = &p.atlas.grids[s];
        for t in g.first..g.first + g.len() {
            power += lum(&p.total[t]);
            area += p.projected_area[t];
        }
    }
    assert!(area > 0.0, "no ray crosses surfaces {surfaces:?}");
    power / area
}

fn corner_form_factor(a: f64, b: f64, c: f64) -> f64 {
    let (x, y) = (a / c, b / c);
    let (sx, sy) = ((1.0 + x * x).sqrt(), (1.0 + y * y).sqrt());
    (x / sx * (y / sx).atan() + y / sy * (x / sy).atan()) / (2.0 * std::f64::consts::PI)
}

/// Form factor from a point to an axis-aligned rectangle `[x0,x1]×[z0,z1]`
/// (coordinates relative to the point) in a parallel plane at distance `c`.
fn rect_form_factor(x0: f64, x1: f64, z0: f64, z1: f64, c: f64) -> f64 {
    corner_form_factor(x1, z1, c) - corner_form_factor(x0, z1, c) - corner_form_factor(x1, z0, c)
        + corner_form_factor(x0, z0, c)
}

// ---------------------------------------------------------------------------
// 1. Parallel mirrors
// ---------------------------------------------------------------------------

/// Two parallel mirrors 0.6 apart, 1.2 × 1.2, facing each other along x, and
/// a small one-sided lamp (ρd = 0) between them: light bounces back and forth
/// many times before it walks out sideways.
fn parallel_mirrors(mirror: Material) -> Scene {
    let m = rect(DVec3::new(-0.3, 0.0, 0.0), DVec3::Y * 0.6, DVec3::Z * 0.6, DVec3::X, 0);
    let n = rect(DVec3::new(0.3, 0.0, 0.0), DVec3::Y * 0.6, DVec3::Z * 0.6, -DVec3::X, 0);
    let lamp = rect(DVec3::ZERO, DVec3::Y * 0.05, DVec3::Z * 0.05, DVec3::X, 1);
    scene(vec![m, n, lamp], vec![mirror, material("lamp", 0.0, 1.0)])
}

/// Parallel mirrors with ρs = 0.9: every iteration conserves power to 1e-9,
/// the mirrors reflect exactly 0.9 of what arrives, and — since what is
/// unshot after an iteration is at most ρs times what was shot in it — the
/// unshot power falls at least by the factor 0.9 per iteration from the
/// first mirror bounce on; `Stop::Converge` (1e-3) stops long before its cap.
/// l = 129, N = 64: enough rays that the lamp (0.1 wide, 1.6 ray spacings)
/// shoots along every direction and light keeps bouncing for many iterations.
#[test]
fn parallel_mirrors_converge_geometrically() {
    let rho_s = 0.9;
    let p = propagate(
        parallel_mirrors(mirror("silver", 0.0, rho_s)),
        options(
            129,
            64,
            Stop::Converge {
                epsilon: 1e-3,
                max_iterations: 200,
            },
        ),
    );
    assert_sane(&p, "parallel mirrors");
    let balance = assert_balance(&p, 1e-9, "parallel mirrors");
    let lit = assert_mirror_exchange(&p, rho_s, 1e-9, "parallel mirrors");
    let ratio = assert_geometric(&p, rho_s * (1.0 + 1e-9), 1, "parallel mirrors");
    let k = p.iterations_done();
    println!(
        "parallel mirrors ρs = 0.9: {k} iterations, {lit} with light on the mirrors, worst unshot ratio {ratio:.4}, \
         balance {balance:.1e}, unshot {:.2e}",
        p.unshot_fraction()
    );
    // The light does bounce: several iterations reach the mirrors.
    assert!(lit >= 5, "only {lit} iterations lit the mirrors");
    assert!(
        k < 200 && p.unshot_fraction() < 1e-3,
        "{k} iterations, unshot {}",
        p.unshot_fraction()
    );
    assert_field_sane(&p.into_field(), "parallel mirrors");
}

/// A perfect mirror (Ks = 1) would never let the propagation converge: the
/// importer caps ρs at `MAX_MIRROR_REFLECTANCE` with a warning that says so,
/// and the capped scene then converges: `Stop::Converge { 1e-2, 2000 }` stops
/// with unshot < 1e-2, each iteration keeping at most ρs = 0.999 of the
/// unshot power, and reflected = 0.999 × incident exactly.
/// l = 129, N = 64 as above (the scene is given in its own units, ×10 and
/// off-centre, so the importer normalises it): with ρs = 0.999 the
/// near-normal directions bounce for tens of iterations before walking out.
#[test]
fn perfect_mirror_is_capped_and_converges() {
    let base = parallel_mirrors(mirror("perfect", 0.0, 1.0));
    let polygons: Vec<(Vec<DVec3>, usize, FaceOrigin)> = base
        .surfaces
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let v = s
                .vertices
                .iter()
                .map(|&x| x * 10.0 + DVec3::new(3.0, -2.0, 1.0))
                .collect();
            (v, s.material, FaceOrigin { line: 0, face: k })
        })
        .collect();
    let (scene, warnings) = Scene::from_polygons(&polygons, base.materials.clone(), &ImportOptions::default())
        .expect("a perfect mirror is accepted (and capped)");
    println!("warnings: {warnings:?}");
    assert!(
        warnings.iter().any(|w| w.contains("capped") && w.contains("perfect")),
        "no warning that the perfect mirror was capped: {warnings:?}"
    );
    assert_eq!(scene.materials[0].specular, [MAX_MIRROR_REFLECTANCE; 3]);
    assert!(MAX_MIRROR_REFLECTANCE < 1.0);
    // The lamp is not a mirror: no cap, no warning about it.
    assert!(!warnings.iter().any(|w| w.contains("'lamp'")), "{warnings:?}");
    let p = propagate(
        scene,
        options(
            129,
            64,
            Stop::Converge {
                epsilon: 1e-2,
                max_iterations: 2000,
            },
        ),
    );
    assert_sane(&p, "capped mirror");
    let balance = assert_balance(&p, 1e-9, "capped mirror");
    let lit = assert_mirror_exchange(&p, MAX_MIRROR_REFLECTANCE, 1e-9, "capped mirror");
    let ratio = assert_geometric(&p, MAX_MIRROR_REFLECTANCE * (1.0 + 1e-9), 1, "capped mirror");
    let k = p.iterations_done();
    println!(
        "capped mirror: {k} iterations ({lit} lit), unshot {:.3e}, worst ratio {ratio:.4}, balance {balance:.1e}",
        p.unshot_fraction()
    );
    assert!(
        k < 2000 && p.unshot_fraction() < 1e-2,
        "{k} iterations, unshot {}",
        p.unshot_fraction()
    );
    assert_field_sane(&p.into_field(), "capped mirror");
}

// ---------------------------------------------------------------------------
// 2. Grazing incidence
// ---------------------------------------------------------------------------

/// Height of the mirror plane above the origin in the grazing scenes: with
/// N = 64 a row of rays of the direction along `toward` runs at 0.015625,
/// 0.002 above the plane, through the lamp strip.
const GRAZING_PLANE: f64 = 0.013625;

/// A mirror (ρs = 0.8), nominally in the plane ⟂ `normal` at height
/// [`GRAZING_PLANE`], spanning [-0.6, 0.2] along `toward` and [-0.4, 0.4]
/// sideways, tilted by `tilt` (radians) so that its normal leans towards the
/// lamp; a lamp strip far along `toward` (at 0.9), 0.0005 to 0.0035 above the
/// plane, facing the mirror; a diffuse card (ρd = 0.5) standing beyond the
/// mirror's far end, facing back, catches the grazing reflection. With tilt 0.3° every line from the lamp to the mirror lies
/// within 0.8° of the mirror's plane: light arrives more than 89° from the
/// normal (the ray along `toward`, a line direction of the set, at 89.7°).
fn grazing_scene(normal: DVec3, toward: DVec3, tilt: f64) -> Scene {
    let side = normal.cross(toward);
    let n = normal * tilt.cos() + toward * tilt.sin();
    let t = toward * tilt.cos() - normal * tilt.sin();
    let base = normal * GRAZING_PLANE;
    let mirror_s = rect(base - 0.2 * toward, t * 0.4, side * 0.4, n, 0);
    let lamp = rect(
        base + 0.9 * toward + 0.002 * normal,
        normal * 0.0015,
        side * 0.4,
        -toward,
        1,
    );
    let card = rect(base - 0.75 * toward + 0.1 * normal, normal * 0.1, side * 0.4, toward, 2);
    scene(
        vec![mirror_s, lamp, card],
        vec![
            mirror("mirror", 0.0, 0.8),
            material("lamp", 0.0, 1.0),
            material("card", 0.5, 0.0),
        ],
    )
}

#[test]
fn grazing_incidence_stays_finite_and_balanced() {
    let grazing = 0.3f64.to_radians();
    let cases = [
        ("normal ≈ +z, 89.7°", DVec3::Z, DVec3::X, grazing, true),
        ("normal ≈ +y, 89.7°", DVec3::Y, DVec3::X, grazing, true),
        ("normal ≈ +x, 89.7°", DVec3::X, -DVec3::Z, grazing, true),
        ("normal +z, untilted", DVec3::Z, DVec3::X, 0.0, false),
        ("normal +z tilted 1e-9", DVec3::Z, DVec3::X, 1e-9, false),
        ("normal +y tilted 1e-13", DVec3::Y, DVec3::X, 1e-13, false),
    ];
    for (case, normal, toward, tilt, direct) in cases {
        let (rho_s, rho_d, le) = (0.8, 0.5, 1.0);
        let p = propagate(
            grazing_scene(normal, toward, tilt),
            options(129, 64, Stop::Iterations(4)),
        );
        assert_sane(&p, case);
        let balance = assert_balance(&p, 1e-9, case);
        let lit = assert_mirror_exchange(&p, rho_s, 1e-9, case);
        let incident = lum(&p.stats[0].exchange.incident);
        let max_mirror = p
            .specular
            .iter()
            .flat_map(|s| s.maps.iter())
            .flat_map(|m| m.total.iter())
            .map(|v| v.iter().cloned().fold(0.0, f64::max))
            .fold(0.0, f64::max);
        let card = &p.atlas.grids[2];
        let max_card = (card.first..card.first + card.len())
            .filter(|&t| p.projected_area[t] > 0.0)
            .map(|t| lum(&p.total[t]) / p.projected_area[t])
            .fold(0.0, f64::max);
        println!(
            "{case}: emitted {:.3e}, on the mirror {incident:.3e} ({lit} lit iterations), max mirror radiance \
             {max_mirror:.4} (ρs·Le = {}), max card radiance {max_card:.4} (ρd·Le = {}), balance {balance:.1e}",
            lum(&p.emitted),
            rho_s * le,
            rho_d * le
        );
        if direct {
            assert!(
                incident > 1e-3 * lum(&p.emitted),
                "{case}: the grazing light missed the mirror"
            );
        }
        assert!(
            max_mirror <= rho_s * le * (1.0 + 1e-9),
            "{case}: mirror radiance {max_mirror}"
        );
        assert!(
            max_card <= rho_d * le * (1.0 + 1e-9),
            "{case}: card radiance {max_card}"
        );
        assert_field_sane(&p.into_field(), case);
    }
}


// ---------------------------------------------------------------------------
// 3. Slivers, sub-ray polygons, a huge floor
// ---------------------------------------------------------------------------

/// A triangle facing `normal` (its vertices reordered if needed).
fn triangle(a: DVec3, b: DVec3, c: DVec3, normal: DVec3, material: usize) -> vlf_core::scene::Surface {
    let s = surface(vec![a, b, c], material);
    if s.normal.dot(normal) < 0.0 {
        surface(vec![a, c, b], material)
    } else {
        s
    }
}

/// The floor y = −h of the `closed_box(h, 1, …)` (face 2), as a fan of
/// triangles from an off-centre point to its boundary, where two stretches of
/// the boundary are cut into `slivers` steps of h·1e-4: each such triangle's
/// shortest edge is ~1e-4 of its longest (aspect 1:10⁴). Shared edges
/// everywhere (the boundary points are computed once).
fn sliver_floor(h: f64, slivers: usize, material: usize) -> Vec<vlf_core::scene::Surface> {
    let y = -h;
    let step = h * 1e-4;
    let mut ring: Vec<DVec3> = vec![DVec3::new(-h, y, -h), DVec3::new(h, y, -h)];
    // Along the +x edge (z increasing), slivers from z = 0.1.
    ring.extend((0..=slivers).map(|k| DVec3::new(h, y, 0.1 + k as f64 * step)));
    ring.push(DVec3::new(h, y, h));
    // Along the +z edge (x decreasing), slivers from x = −0.2.
    ring.extend((0..=slivers).map(|k| DVec3::new(-0.2 - k as f64 * step, y, h)));
    ring.push(DVec3::new(-h, y, h));
    let centre = DVec3::new(0.1, y, -0.05);
    (0..ring.len())
        .map(|k| triangle(centre, ring[k], ring[(k + 1) % ring.len()], DVec3::Y, material))
        .collect()
}

/// Sliver triangles (aspect 1:10⁴) in a furnace: a closed box whose floor is
/// a fan of 44 triangles, 40 of them slivers, every wall emitting Le = 1 and
/// reflecting ρ = 0.5. The rasteriser must stay watertight however thin the
/// triangles (escaped and blocked power exactly zero, shot = received to
/// 1e-9), and exact normalisation makes every covered texel — sliver texels
/// included — hold Le·(1 − ρ^(K+1))/(1 − ρ) to 1e-5 (f32 maps).
/// l = 129, N = 32: the slivers are 1/1000 of a ray spacing wide, so only a
/// few of the 129 × 32² rays cross each — enough that some sliver texels are
/// covered, which is the point.
#[test]
fn sliver_triangles_keep_the_furnace_exact() {
    let (rho, le, k) = (0.5, 1.0, 12);
    let mut box_ = closed_box(
        0.55,
        1,
        &[0, 1, 2, 3, 4, 5],
        vec![material("unused", rho, 0.0), material("glow", rho, le)],
    );
    box_.surfaces.remove(2);
    let floor = sliver_floor(0.55, 20, 1);
    let first_floor = box_.surfaces.len();
    let floor_count = floor.len();
    box_.surfaces.extend(floor);
    let slivers: Vec<usize> = (first_floor..first_floor + floor_count)
        .filter(|&s| {
            let v = &box_.surfaces[s].vertices;
            let edges: Vec<f64> = (0..3).map(|i| (v[(i + 1) % 3] - v[i]).length()).collect();
            let (lo, hi) = edges.iter().fold((f64::MAX, 0.0f64), |(a, b), &e| (a.min(e), b.max(e)));
            lo / hi < 2e-4
        })
        .collect();
    assert_eq!(slivers.len(), 40);
    let p = propagate(box_, options(129, 32, Stop::Iterations(k)));
    assert_sane(&p, "sliver furnace");
    let balance = assert_balance(&p, 1e-9, "sliver furnace");
    for s in &p.stats {
        assert_eq!(lum(&s.flow.escaped), 0.0, "iteration {}: light leaked between slivers", s.index);
        assert_eq!(lum(&s.flow.blocked), 0.0, "iteration {}: a sliver was hit from behind", s.index);
    }
    let owners = p.atlas.owners();
    let field = p.into_field();
    assert_field_sane(&field, "sliver furnace");
    let want = le * (1.0 - rho.powi(k as i32 + 1)) / (1.0 - rho);
    let (mut worst, mut checked, mut sliver_texels) = (0.0f64, 0, 0);
    for (t, l) in field.radiance.iter().enumerate() {
        if !field.covered[t] {
            continue;
        }
        for c in l {
            let rel = ((*c as f64) - want).abs() / want;
            worst = worst.max(rel);
            assert!(rel < 1e-5, "texel {t} of surface {}: {c} vs {want}", owners[t]);
        }
        checked += 1;
        if slivers.contains(&(owners[t] as usize)) {
            sliver_texels += 1;
        }
    }
    println!(
        "sliver furnace: {checked} covered texels ({sliver_texels} on slivers), worst error {worst:.1e}, balance {balance:.1e}"
    );
    assert!(sliver_texels >= 5, "only {sliver_texels} sliver texels were crossed by rays");
}

/// A closed box (ρ = 0.5, lamp ceiling Le = 1) with a tiny card and a tiny
/// emitter (Le = 1000) inside, each 1e-4 of a ray spacing across: no ray may
/// cross them. That must be harmless: everything stays finite, power
/// balances to 1e-9 with nothing escaping, and the room matches the same room
/// without the tiny polygons (emitted power and the mean radiance of every
/// wall to 1e-6). A scene whose only emitter is that small is refused with a
/// message saying so, rather than propagating nothing.
/// l = 129, N = 32: 129 × 32² rays, none of which should find a 6e-6 square.
#[test]
fn polygons_far_below_the_ray_spacing_are_harmless() {
    let n = 32;
    let tiny = 1e-4 * 2.0 / n as f64;
    let mats = vec![
        material("wall", 0.5, 0.0),
        material("lamp", 0.5, 1.0),
        material("bright speck", 0.5, 1000.0),
    ];
    let room = closed_box(0.55, 1, &[3], mats.clone());
    let mut cluttered = room.clone();
    let card = rect(DVec3::new(0.1, -0.2, 0.05), DVec3::X * tiny / 2.0, DVec3::Z * tiny / 2.0, DVec3::Y, 0);
    let speck = rect(DVec3::new(-0.13, 0.21, 0.07), DVec3::X * tiny / 2.0, DVec3::Z * tiny / 2.0, -DVec3::Y, 2);
    cluttered.surfaces.extend([card, speck]);
    let stop = Stop::Iterations(6);
    let reference = propagate(room, options(129, n, stop));
    let p = propagate(cluttered, options(129, n, stop));
    assert_sane(&p, "tiny polygons");
    let balance = assert_balance(&p, 1e-9, "tiny polygons");
    assert!(p.stats.iter().all(|s| lum(&s.flow.escaped) == 0.0));
    for s in [6, 7] {
        let g = &p.atlas.grids[s];
        let rays: f64 = p.projected_area[g.first..g.first + g.len()].iter().sum();
        println!("tiny surface {s}: {} texel(s), discrete area {rays}", g.len());
        assert_eq!(rays, 0.0, "a ray crossed tiny surface {s}");
    }
    let rel = (lum(&p.emitted) - lum(&reference.emitted)).abs() / lum(&reference.emitted);
    assert!(rel < 1e-6, "emitted power changed by {rel}");
    let mut worst = 0.0f64;
    for wall in 0..6 {
        let (a, b) = (mean_radiance(&p, &[wall]), mean_radiance(&reference, &[wall]));
        worst = worst.max((a - b).abs() / b);
    }
    println!("tiny polygons: walls differ from the clean room by at most {worst:.1e}, balance {balance:.1e}");
    assert!(worst < 1e-6, "the tiny polygons changed the walls by {worst}");
    let field = p.into_field();
    assert_field_sane(&field, "tiny polygons");
    for s in [6, 7] {
        let g = &field.atlas.grids[s];
        assert!((g.first..g.first + g.len()).all(|t| !field.covered[t]));
    }
    // Only the speck emits: refused, with the reason.
    let mut dark = closed_box(0.55, 1, &[], mats);
    dark.surfaces.push(rect(
        DVec3::new(-0.13, 0.21, 0.07),
        DVec3::X * tiny / 2.0,
        DVec3::Z * tiny / 2.0,
        -DVec3::Y,
        2,
    ));
    match Propagation::new(dark, options(129, n, stop)) {
        Ok(_) => panic!("a scene whose only emitter no ray crosses was accepted"),
        Err(e) => assert!(e.to_string().contains("raise N"), "unhelpful error: {e}"),
    }
}

/// A huge floor (1.4 × 1.4, ρd = 0.5) under a tiny emitter (0.01 × 0.01, a
/// third of a ray spacing, Le = 1, 0.3 above): no NaN, balance to 1e-9, no
/// floor texel brighter than ρd·Le (exact for the discrete areas), and the
/// power the floor receives is the emitter's power times the analytic form
/// factor from the emitter to the floor, within 3 %.
/// l = 513, N = 128: the emitter is crossed by a handful of rays per
/// direction only, so the form factor needs many directions; two surfaces
/// keep it cheap.
#[test]
fn huge_floor_under_a_tiny_emitter() {
    let (h, half, rho, le) = (0.3, 0.005, 0.5, 1.0);
    let floor = rect(DVec3::ZERO, DVec3::X * 0.7, DVec3::Z * 0.7, DVec3::Y, 0);
    let lamp = rect(DVec3::new(0.05, h, -0.03), DVec3::X * half, DVec3::Z * half, -DVec3::Y, 1);
    let p = propagate(
        scene(vec![floor, lamp], vec![material("floor", rho, 0.0), material("lamp", 0.0, le)]),
        options(513, 128, Stop::Iterations(2)),
    );
    assert_sane(&p, "huge floor");
    let balance = assert_balance(&p, 1e-9, "huge floor");
    let f = &p.stats[0].flow;
    let measured = lum(&f.received) / lum(&f.shot);
    let expected = rect_form_factor(-0.75, 0.65, -0.67, 0.73, h);
    let g = &p.atlas.grids[0];
    let max_floor = (g.first..g.first + g.len())
        .filter(|&t| p.projected_area[t] > 0.0)
        .map(|t| lum(&p.total[t]) / p.projected_area[t])
        .fold(0.0, f64::max);
    println!(
        "huge floor: received/shot {measured:.5}, form factor {expected:.5} (rel {:.2e}), max floor radiance \
         {max_floor:.3e} (ρd·Le = {}), balance {balance:.1e}",
        (measured - expected).abs() / expected,
        rho * le
    );
    assert!((measured - expected).abs() < 0.03 * expected);
    assert!(max_floor > 0.0 && max_floor <= rho * le * (1.0 + 1e-9));
    assert_field_sane(&p.into_field(), "huge floor");
}

#[test]
fn zz_probe_floor() {
    for (l, n) in [(129, 64), (129, 128), (513, 64), (513, 128), (2049, 64), (2049, 128)] {
        let (h, half, rho, le) = (0.3, 0.005, 0.5, 1.0);
        let floor = rect(DVec3::ZERO, DVec3::X * 0.7, DVec3::Z * 0.7, DVec3::Y, 0);
        let lamp = rect(DVec3::new(0.05, h, -0.03), DVec3::X * half, DVec3::Z * half, -DVec3::Y, 1);
        let t = std::time::Instant::now();
        let p = propagate(
            scene(vec![floor, lamp], vec![material("floor", rho, 0.0), material("lamp", 0.0, le)]),
            options(l, n, Stop::Iterations(1)),
        );
        let f = &p.stats[0].flow;
        let measured = lum(&f.received) / lum(&f.shot);
        let expected = rect_form_factor(-0.75, 0.65, -0.67, 0.73, h);
        println!("l {l} N {n}: {measured:.5} vs {expected:.5}: {:.2e}  ({:?})", measured / expected - 1.0, t.elapsed());
    }
}
