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
use glam::{DVec3, Vec3Swizzles};
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
        for (c, &was) in before.iter().enumerate() {
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
            let rel = (f.shot[c] - was).abs() / was.max(f64::MIN_POSITIVE);
            worst = worst.max(rel);
            assert!(
                rel <= tol,
                "{case}: iteration {}, channel {c}: shot {} but {} was unshot (rel {rel:.2e})",
                s.index,
                f.shot[c],
                was
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
        let g = p.atlas.grid(s);
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
/// l = 129, N = 64: the lamp (0.1 wide, 3.2 ray spacings) is crossed by rays
/// of nearly every direction, and the directions near the mirrors' normal
/// keep the light bouncing for ~15 iterations.
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
/// off-centre, so the importer normalises it); the mirrors stay lit for
/// several iterations before the light walks out or dies on the lamp.
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
    const { assert!(MAX_MIRROR_REFLECTANCE < 1.0) };
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

/// Height of the mirror plane above the origin in the grazing scenes, for the line direction
/// along `toward` of `l` directions on an `n × n` grid: 0.002 below the row of its rays
/// nearest to 0.0156 along `normal` (each direction's lattice has its own phase,
/// `DirectionSet::frame`), so that one row runs through the lamp strip.
fn grazing_plane(normal: DVec3, toward: DVec3, l: usize, n: u32) -> f64 {
    let set = vlf_core::directions::DirectionSet::new(l).unwrap();
    let d = (0..set.len())
        .find(|&d| set.get(d).vector.dot(toward).abs() > 1.0 - 1e-12)
        .expect("a line direction along `toward`");
    let frame = set.frame(d);
    let g = frame.to_grid(normal * 0.015625, n);
    let centre = g.floor() + 0.5;
    frame.ray_origin(centre.x, centre.y, n).dot(normal) - 0.002
}

/// A mirror (ρs = 0.8), nominally in the plane ⟂ `normal` at height
/// [`grazing_plane`] (l = 129, N = 64), spanning [-0.6, 0.2] along `toward` and [-0.4, 0.4]
/// sideways, tilted by `tilt` (radians) so that its normal leans towards the
/// lamp; a lamp strip far along `toward` (at 0.9), 0.0005 to 0.0035 above the
/// plane, facing the mirror; a diffuse card (ρd = 0.5) standing beyond the
/// mirror's far end, facing back, catches the grazing reflection. With tilt
/// 0.3° every line from the lamp to the mirror lies within 0.8° of the
/// mirror's plane: light arrives more than 89° from the normal (along
/// `toward`, a line direction of the set, at 89.7°).
fn grazing_scene(normal: DVec3, toward: DVec3, tilt: f64) -> Scene {
    let side = normal.cross(toward);
    let n = normal * tilt.cos() + toward * tilt.sin();
    let t = toward * tilt.cos() - normal * tilt.sin();
    let base = normal * grazing_plane(normal, toward, 129, 64);
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

/// Grazing incidence: a mirror lit more than 89° from its normal, with the
/// mirror's normal near z (the directions' pole), y and x. Also the mirror
/// untilted (exactly edge-on to the line direction along `toward`), tilted by
/// 1e-9 rad (n·ω ≈ 1e-9: nearly edge-on, rasterised to nothing) and by
/// 1e-13 rad (below the edge-on cut-off): those get no direct light.
/// Asserts: no NaN/∞/negative anywhere, balance to 1e-9, reflected = ρs ×
/// incident, the tilted mirrors are actually lit (> 1e-3 of the emitted
/// power arrives), and nothing blows up: no card texel's radiance exceeds ρd
/// × the brightest radiance in the scene (exact for the discrete areas: a
/// texel's irradiance is at most π × the brightest radiance arriving), and
/// no mirror slot exceeds 2·ρs·Le — a blow-up guard rather than the physical
/// ρs·Le, since the exchange rescales backward-mapped radiance to conserve
/// power, which can lift single slots above ρs·Le (by up to 45 % in a probe
/// at 4° incidence, l = 129, N = 64; 10 % at N = 128). Measured here: 0.217.
/// l = 129, N = 64: the one row of rays along `toward` through the 3 mm lamp
/// strip is placed by [`grazing_plane`]; more directions would add none
/// within 1° of the mirror's plane.
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
        let card = p.atlas.grid(2);
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
        assert!(max_mirror <= 2.0 * rho_s * le, "{case}: mirror radiance {max_mirror}");
        let brightest = le.max(max_mirror);
        assert!(
            max_card <= rho_d * brightest * (1.0 + 1e-9),
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
/// a fan of 46 triangles, 40 of them slivers, every wall emitting Le = 1 and
/// reflecting ρ = 0.5. The rasteriser must stay watertight however thin the
/// triangles (escaped and blocked power exactly zero, shot = received to
/// 1e-9), and exact normalisation makes every covered texel — sliver texels
/// included — hold the furnace's Le·(1 − ρ^(K+1))/(1 − ρ), its reflected part scaled
/// by the walls' emission factors ([`assert_furnace`]), to 1e-5 (f32 maps).
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
        assert_eq!(
            lum(&s.flow.escaped),
            0.0,
            "iteration {}: light leaked between slivers",
            s.index
        );
        assert_eq!(
            lum(&s.flow.blocked),
            0.0,
            "iteration {}: a sliver was hit from behind",
            s.index
        );
    }
    // The fan, slivers included, is one chart: its texels are the floor's, whole.
    let floor_chart = p.atlas.chart_of[first_floor];
    assert!(
        (first_floor..first_floor + floor_count).all(|s| p.atlas.chart_of[s] == floor_chart),
        "the floor's fan was cut into several charts"
    );
    let owners = p.atlas.owners();
    let band = emission_band(&p);
    let field = p.into_field();
    assert_field_sane(&field, "sliver furnace");
    let want = le * (1.0 - rho.powi(k as i32 + 1)) / (1.0 - rho);
    let (checked, worst) = assert_furnace(&field, le, want, band, 1e-5);
    let sliver_texels = (0..field.radiance.len())
        .filter(|&t| field.covered[t] && owners[t] == floor_chart)
        .count();
    println!(
        "sliver furnace: {checked} covered texels ({sliver_texels} on the sliver fan's chart), worst error {worst:.1e}, balance {balance:.1e}"
    );
    assert!(
        sliver_texels >= 5,
        "only {sliver_texels} texels of the fan's chart were crossed by rays"
    );
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
    let card = rect(
        DVec3::new(0.1, -0.2, 0.05),
        DVec3::X * tiny / 2.0,
        DVec3::Z * tiny / 2.0,
        DVec3::Y,
        0,
    );
    let speck = rect(
        DVec3::new(-0.13, 0.21, 0.07),
        DVec3::X * tiny / 2.0,
        DVec3::Z * tiny / 2.0,
        -DVec3::Y,
        2,
    );
    cluttered.surfaces.extend([card, speck]);
    let stop = Stop::Iterations(6);
    let reference = propagate(room, options(129, n, stop));
    let p = propagate(cluttered, options(129, n, stop));
    assert_sane(&p, "tiny polygons");
    let balance = assert_balance(&p, 1e-9, "tiny polygons");
    assert!(p.stats.iter().all(|s| lum(&s.flow.escaped) == 0.0));
    for s in [6, 7] {
        let g = p.atlas.grid(s);
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
        let g = field.atlas.grid(s);
        assert!((g.first..g.first + g.len()).all(|t| !field.covered[t]));
    }
    // Loose pieces no ray crosses touch no light to take: the speck shows its own emission, the
    // card nothing.
    let shown = |s: usize| field.radiance[field.atlas.grid(s).first];
    assert_eq!(shown(6), [0.0; 3]);
    assert_eq!(shown(7), [1000.0; 3]);
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
/// factor from the emitter to the floor, within 10 %: the emitter is crossed
/// by only ~100 rays in all (0.1 per direction), so that fraction is sampled
/// by ~100 rays (one standard deviation ≈ 3.4 %; measured −2.7 % here,
/// −2.6 % / −3.2 % at l = 2049, N = 64 / 128).
/// l = 513, N = 128: the fewest directions and rays that cross the emitter
/// ~100 times; two surfaces keep it at ~0.1 s.
#[test]
fn huge_floor_under_a_tiny_emitter() {
    let (h, half, rho, le) = (0.3, 0.005, 0.5, 1.0);
    let floor = rect(DVec3::ZERO, DVec3::X * 0.7, DVec3::Z * 0.7, DVec3::Y, 0);
    let lamp = rect(
        DVec3::new(0.05, h, -0.03),
        DVec3::X * half,
        DVec3::Z * half,
        -DVec3::Y,
        1,
    );
    let p = propagate(
        scene(
            vec![floor, lamp],
            vec![material("floor", rho, 0.0), material("lamp", 0.0, le)],
        ),
        options(513, 128, Stop::Iterations(2)),
    );
    assert_sane(&p, "huge floor");
    let balance = assert_balance(&p, 1e-9, "huge floor");
    let f = &p.stats[0].flow;
    let measured = lum(&f.received) / lum(&f.shot);
    let expected = rect_form_factor(-0.75, 0.65, -0.67, 0.73, h);
    let g = p.atlas.grid(0);
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
    assert!((measured - expected).abs() < 0.1 * expected);
    assert!(max_floor > 0.0 && max_floor <= rho * le * (1.0 + 1e-9));
    assert_field_sane(&p.into_field(), "huge floor");
}

// ---------------------------------------------------------------------------
// 4. An emitter coplanar with its ceiling
// ---------------------------------------------------------------------------

/// A closed box (ρ = 0.5) whose ceiling, the face ⟂ `up` at +0.55, carries a
/// 0.3 × 0.3 lamp (Le = 1, ρd = 0) `gap` below it, listed before or after the
/// ceiling. Returns the scene and the floor's surface index.
fn lamp_under_ceiling(up: usize, gap: f64, lamp_first: bool) -> (Scene, usize) {
    let mut s = closed_box(
        0.55,
        1,
        &[],
        vec![material("wall", 0.5, 0.0), material("lamp", 0.0, 1.0)],
    );
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    let (a, b) = (axes[(up + 1) % 3], axes[(up + 2) % 3]);
    let lamp = rect(axes[up] * (0.55 - gap), a * 0.15, b * 0.15, -axes[up], 1);
    let floor = 2 * up;
    if lamp_first {
        s.surfaces.insert(0, lamp);
        (s, floor + 1)
    } else {
        s.surfaces.push(lamp);
        (s, floor)
    }
}

/// An emitter exactly coplanar with the ceiling it sits on (and 1e-6 in
/// front of it) must still light the room: rays from below must see the
/// lamp, not the ceiling behind it, whichever order the two are listed in
/// and whether the ceiling is ⟂ y (directions on both sides of it) or ⟂ z
/// (the directions' pole: every direction crosses it the same way). The
/// floor's mean radiance must be within 10 % of the same room with the lamp
/// 1e-3 below the ceiling; no NaN, balance to 1e-9, nothing escapes.
/// l = 129, N = 32: the floor's mean over ~300 texels is a smooth quantity;
/// the lamp spans ~5 ray spacings.
#[test]
fn emitter_coplanar_with_the_ceiling_lights_the_room() {
    let mut failures = Vec::new();
    for up in [1, 2] {
        for lamp_first in [true, false] {
            let (reference, floor) = lamp_under_ceiling(up, 1e-3, lamp_first);
            let r = propagate(reference, options(129, 32, Stop::Iterations(4)));
            let want = mean_radiance(&r, &[floor]);
            for gap in [0.0, 1e-6] {
                let case = format!(
                    "ceiling ⟂ {}, lamp listed {}, gap {gap:e}",
                    ["x", "y", "z"][up],
                    if lamp_first { "first" } else { "last" }
                );
                let (scene, floor) = lamp_under_ceiling(up, gap, lamp_first);
                let p = propagate(scene, options(129, 32, Stop::Iterations(4)));
                assert_sane(&p, &case);
                let balance = assert_balance(&p, 1e-9, &case);
                assert!(
                    p.stats.iter().all(|s| lum(&s.flow.escaped) == 0.0),
                    "{case}: light escaped"
                );
                let got = mean_radiance(&p, &[floor]);
                let rel = (got - want).abs() / want;
                println!(
                    "{case}: floor radiance {got:.5e} vs {want:.5e} with a 1e-3 gap (rel {rel:.2e}), balance {balance:.1e}"
                );
                if !(got > 0.0 && rel < 0.1) {
                    failures.push(format!("{case}: floor {got:.4e} vs {want:.4e} (rel {rel:.2e})"));
                }
                assert_field_sane(&p.into_field(), &case);
            }
        }
    }
    assert!(
        failures.is_empty(),
        "the coplanar lamp does not light the room:\n{}",
        failures.join("\n")
    );
}

// ---------------------------------------------------------------------------
// 5. Scene scale and offset
// ---------------------------------------------------------------------------

/// A closed box [0, size] (walls ρd = 0.6, a tinted back wall), its ceiling
/// split 3 × 3 with a lamp (Le = 2) in the middle tile, and a block (0.3 ×
/// 0.5 × 0.2, outward faces) standing on the floor — in scene units
/// `x·scale + offset`, as polygons for the importer.
fn room(size: DVec3, scale: f64, offset: DVec3) -> Vec<(Vec<DVec3>, usize, FaceOrigin)> {
    let mut faces: Vec<(Vec<DVec3>, usize)> = Vec::new();
    let c = size * 0.5;
    // Walls: -x, +x, -y (floor), -z, +z facing in; the +y ceiling is tiled.
    for (axis, sign, mat) in [
        (DVec3::X, -1.0, 0),
        (DVec3::X, 1.0, 0),
        (DVec3::Y, -1.0, 0),
        (DVec3::Z, -1.0, 2),
        (DVec3::Z, 1.0, 0),
    ] {
        let (a, b) = (axis.yzx() * c, axis.zxy() * c);
        faces.push((rect(c + axis * sign * c, a, b, -axis * sign, mat).vertices, mat));
    }
    let (tx, tz) = (size.x / 3.0, size.z / 3.0);
    for i in 0..3 {
        for j in 0..3 {
            let centre = DVec3::new((i as f64 + 0.5) * tx, size.y, (j as f64 + 0.5) * tz);
            let mat = if i == 1 && j == 1 { 1 } else { 0 };
            faces.push((
                rect(centre, DVec3::X * tx / 2.0, DVec3::Z * tz / 2.0, -DVec3::Y, mat).vertices,
                mat,
            ));
        }
    }
    // The block: 5 outward faces (its bottom rests on the floor).
    let (bc, bh) = (DVec3::new(0.35, 0.25, 0.6), DVec3::new(0.15, 0.25, 0.1));
    for (axis, sign) in [(0, -1.0), (0, 1.0), (1, 1.0), (2, -1.0), (2, 1.0)] {
        let n = [DVec3::X, DVec3::Y, DVec3::Z][axis] * sign;
        let (a, b) = (
            [DVec3::Y, DVec3::Z, DVec3::X][axis],
            [DVec3::Z, DVec3::X, DVec3::Y][axis],
        );
        let (ha, hb) = (a * a.dot(bh), b * b.dot(bh));
        faces.push((rect(bc + n * n.abs().dot(bh), ha, hb, n, 0).vertices, 0));
    }
    faces
        .into_iter()
        .enumerate()
        .map(|(k, (v, m))| {
            (
                v.into_iter().map(|p| p * scale + offset).collect(),
                m,
                FaceOrigin { line: 0, face: k },
            )
        })
        .collect()
}

/// Builds `room(size)` at scale 1 and at scales 1e-3 and 1e5 and offsets of
/// 1e4 units, propagates each, and compares with scale 1: normalised
/// vertices, texel grids, radiance maps. Returns the failures (all cases are
/// run and printed first).
fn scale_invariance(size: DVec3, label: &str) -> Vec<String> {
    let materials = vec![
        material("wall", 0.6, 0.0),
        material("lamp", 0.3, 2.0),
        Material {
            name: "tinted".into(),
            diffuse: [0.7, 0.4, 0.2],
            specular: [0.0; 3],
            emission: [0.0; 3],
            albedo_texture: None,
        },
    ];
    let build = |scale: f64, offset: DVec3| {
        let (scene, warnings) =
            Scene::from_polygons(&room(size, scale, offset), materials.clone(), &ImportOptions::default())
                .expect("room imports");
        // The ceiling's tiles meet the walls in T-junctions, split the same way at every scale.
        assert!(warnings.iter().all(|w| w.contains("T-junction")), "{warnings:?}");
        scene
    };
    let stop = Stop::Iterations(5);
    let reference_scene = build(1.0, DVec3::ZERO);
    let reference = propagate(reference_scene.clone(), options(129, 32, stop));
    assert_sane(&reference, label);
    assert_balance(&reference, 1e-9, label);
    let reference = reference.into_field();
    assert_field_sane(&reference, label);
    let peak = reference.radiance.iter().flatten().fold(0.0f32, |a, &b| a.max(b)) as f64;
    let mut failures = Vec::new();
    for (case, scale, offset) in [
        ("scale 1e-3", 1e-3, DVec3::ZERO),
        ("scale 1e5", 1e5, DVec3::ZERO),
        ("offset 1e4", 1.0, DVec3::new(1e4, -1e4, 1e4)),
        ("scale 1e5, offset 1e4", 1e5, DVec3::splat(1e4)),
    ] {
        let case = format!("{label}, {case}");
        let scene = build(scale, offset);
        let moved = scene
            .surfaces
            .iter()
            .zip(&reference_scene.surfaces)
            .flat_map(|(a, b)| a.vertices.iter().zip(&b.vertices).map(|(p, q)| (*p - *q).length()))
            .fold(0.0, f64::max);
        let p = propagate(scene, options(129, 32, stop));
        assert_sane(&p, &case);
        let balance = assert_balance(&p, 1e-9, &case);
        let field = p.into_field();
        assert_field_sane(&field, &case);
        let regridded: Vec<usize> = (0..field.scene.surfaces.len())
            .filter(|&s| {
                let (a, b) = (field.atlas.grid(s), reference.atlas.grid(s));
                a.width != b.width
                    || a.height != b.height
                    || (a.axis_u - b.axis_u).length() > 1e-9
                    || (a.origin - b.origin).length() > 1e-9
            })
            .collect();
        let worst = field
            .radiance
            .iter()
            .flatten()
            .zip(reference.radiance.iter().flatten())
            .map(|(a, b)| (*a as f64 - *b as f64).abs() / peak)
            .fold(0.0, f64::max);
        println!(
            "{case}: vertices moved by {moved:.1e} in the VLF frame, texel grids laid out differently on surfaces \
             {regridded:?}, radiance differs by {worst:.1e} of the peak {peak:.3}, balance {balance:.1e}"
        );
        if moved >= 1e-9 {
            failures.push(format!("{case}: normalised vertices differ by {moved:.1e}"));
        }
        if !regridded.is_empty() {
            failures.push(format!("{case}: texel grids differ on surfaces {regridded:?}"));
        }
        if worst.is_nan() || worst >= 1e-6 {
            failures.push(format!("{case}: radiance differs by {worst:.1e} of the peak"));
        }
    }
    failures
}

/// Radiance is invariant under a similarity: the same room built at scales
/// 1e-3, 1 and 1e5, and 1e4 units away from the origin, is normalised into
/// the same VLF frame (vertices within 1e-9), gets the same texel grids, and
/// gives the same radiance maps texel by texel to 1e-6 of the brightest
/// texel (the maps are f32). No NaN, balance to 1e-9. This room has no two
/// edges of a polygon equally long (a 1 × 0.8 × 0.9 box).
/// l = 129, N = 32, 5 iterations: invariance is exact or not at any
/// resolution, so the cheapest non-trivial one will do.
#[test]
fn scene_scale_and_offset_do_not_change_the_radiance() {
    let failures = scale_invariance(DVec3::new(1.0, 0.8, 0.9), "1 × 0.8 × 0.9 room");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The same for a cube, whose faces and ceiling tiles are squares: the texel
/// grid of a square may not depend on which of its equally long edges
/// rounding makes a few ulps longer at one scale than at another.
#[test]
fn scene_scale_and_offset_do_not_change_the_radiance_of_a_cube() {
    let failures = scale_invariance(DVec3::ONE, "unit cube room");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

// ---------------------------------------------------------------------------
// 6. Emitters 10⁶ apart
// ---------------------------------------------------------------------------

/// An open scene: a floor split in two halves (x < 0 and x > 0, ρd = 0.5), a
/// back wall (ρd = 0.5, split the same way) along both, a dim lamp (Le = `dim`, ρd = 0.5, 0.4 ×
/// 0.4) 0.3 above the left half and a small bright lamp (Le = `bright`, 0.1 ×
/// 0.1) 0.3 above the far right. With `partition`, a black one-sided wall at
/// x = 0 (0.6 high, as deep as the floor, facing the left half) shades the
/// left half from everything on the right: no straight path leads from a
/// point right of it (at most 0.5 high) to the left floor. Floor halves are
/// surfaces 0 and 1. (The back wall must be split where the partition meets
/// it: a texel straddling the contact line would take light on the right and
/// re-emit it on the left — radiosity's classic light leak, ~1e-5 of the
/// bright lamp's power here, which at 10⁶ swamps the dim half.)
fn two_lamps(dim: f64, bright: f64, partition: bool) -> Scene {
    let mut surfaces = vec![
        rect(
            DVec3::new(-0.35, 0.0, 0.0),
            DVec3::X * 0.35,
            DVec3::Z * 0.5,
            DVec3::Y,
            0,
        ),
        rect(DVec3::new(0.35, 0.0, 0.0), DVec3::X * 0.35, DVec3::Z * 0.5, DVec3::Y, 0),
        rect(
            DVec3::new(-0.35, 0.25, -0.5),
            DVec3::X * 0.35,
            DVec3::Y * 0.25,
            DVec3::Z,
            0,
        ),
        rect(
            DVec3::new(0.35, 0.25, -0.5),
            DVec3::X * 0.35,
            DVec3::Y * 0.25,
            DVec3::Z,
            0,
        ),
        rect(
            DVec3::new(-0.35, 0.3, 0.0),
            DVec3::X * 0.2,
            DVec3::Z * 0.2,
            -DVec3::Y,
            1,
        ),
        rect(
            DVec3::new(0.6, 0.3, 0.2),
            DVec3::X * 0.05,
            DVec3::Z * 0.05,
            -DVec3::Y,
            2,
        ),
    ];
    if partition {
        surfaces.push(rect(
            DVec3::new(0.0, 0.3, 0.0),
            DVec3::Y * 0.3,
            DVec3::Z * 0.5,
            -DVec3::X,
            3,
        ));
    }
    scene(
        surfaces,
        vec![
            material("matte", 0.5, 0.0),
            material("dim", 0.5, dim),
            material("bright", 0.0, bright),
            material("black", 0.0, 0.0),
        ],
    )
}

/// Emitters 10⁶ apart in radiance (dim Le = 1, bright Le = 10⁶).
///
/// Open scene: transport is linear, so the run with both lamps equals the
/// sum of the runs with each lamp alone, texel by texel, to 1e-12 of the
/// texel's value (f64 Total maps); and the dim lamp's share, recovered as
/// (both − bright alone), matches the dim lamp alone to 1e-6 even where the
/// bright lamp's light is 10³–10⁷ times stronger (f64 rounding allows ~1e-9
/// there): the dim light is neither lost nor swamped by rounding.
///
/// With the partition, the left half is the dim lamp's alone: the bright
/// lamp, 10⁶ brighter, must leak exactly nothing onto it (any seam or
/// back-face leak would show at once), and the field (f32) with both lamps
/// equals the dim lamp alone there to 1e-6 relative.
/// No NaN, balance to 1e-9 relative in every run.
/// l = 129, N = 64, 4 iterations: the floor halves get ~500 texels each and
/// the light is interreflected between floor, wall and the dim lamp.
#[test]
fn emitters_a_million_apart_are_both_visible() {
    let stop = Stop::Iterations(4);
    let run = |dim: f64, bright: f64, partition: bool| {
        let case = format!("dim {dim:e}, bright {bright:e}, partition {partition}");
        let p = propagate(two_lamps(dim, bright, partition), options(129, 64, stop));
        assert_sane(&p, &case);
        let balance = assert_balance(&p, 1e-9, &case);
        println!("{case}: emitted {:.4e}, balance {balance:.1e}", lum(&p.emitted));
        p
    };
    let (both, dim, bright) = (run(1.0, 1e6, false), run(1.0, 0.0, false), run(0.0, 1e6, false));
    // Linearity, texel by texel, in f64.
    let mut worst = 0.0f64;
    for t in 0..both.total.len() {
        for c in 0..3 {
            let (a, b) = (both.total[t][c], dim.total[t][c] + bright.total[t][c]);
            if a > 0.0 {
                worst = worst.max((a - b).abs() / a);
            } else {
                assert_eq!(b, 0.0);
            }
        }
    }
    // The dim lamp's share, as both − bright, where it is 10³–10⁷ times
    // smaller (f64 leaves it ~1e-16 × 10⁷ = 1e-9 relative error there).
    let (mut share_err, mut swamped, mut ratio) = (0.0f64, 0, 0.0f64);
    for t in 0..both.total.len() {
        let (a, d, b) = (lum(&both.total[t]), lum(&dim.total[t]), lum(&bright.total[t]));
        if d > 0.0 && b > 1e3 * d && b < 1e7 * d {
            swamped += 1;
            ratio = ratio.max(b / d);
            share_err = share_err.max(((a - b) - d).abs() / d);
        }
    }
    println!(
        "open: linearity {worst:.1e}; dim share recovered in {swamped} texels under up to {ratio:.1e}× more bright \
         light, worst {share_err:.1e}"
    );
    assert!(worst < 1e-12, "both lamps ≠ dim + bright: {worst}");
    assert!(
        swamped > 100,
        "the bright lamp swamps the dim one in only {swamped} texels"
    );
    assert!(
        share_err < 1e-6,
        "the dim lamp's share is lost under the bright one: {share_err}"
    );

    // Behind the partition: the dim lamp's half.
    let (both, dim, bright) = (run(1.0, 1e6, true), run(1.0, 0.0, true), run(0.0, 1e6, true));
    let g = both.atlas.grid(0).clone();
    let leaked = (g.first..g.first + g.len())
        .map(|t| lum(&bright.total[t]))
        .fold(0.0, f64::max);
    let lit = (g.first..g.first + g.len())
        .filter(|&t| lum(&dim.total[t]) > 0.0)
        .count();
    let (fb, fd) = (both.into_field(), dim.into_field());
    assert_field_sane(&fb, "both lamps, partition");
    assert_field_sane(&fd, "dim lamp, partition");
    let region_err = (g.first..g.first + g.len())
        .filter(|&t| fd.covered[t])
        .flat_map(|t| (0..3).map(move |c| (t, c)))
        .map(|(t, c)| (fb.radiance[t][c] as f64 - fd.radiance[t][c] as f64).abs() / fd.radiance[t][c] as f64)
        .fold(0.0, f64::max);
    println!(
        "partition: bright light on the left floor {leaked:e} (of {:.3e} emitted); {lit} texels lit by the dim lamp, \
         both lamps vs dim alone differ by {region_err:.1e} there",
        lum(&bright.emitted)
    );
    assert_eq!(leaked, 0.0, "the bright lamp leaks behind the partition");
    assert!(lit > 300, "{lit}");
    assert!(
        region_err < 1e-6,
        "both lamps vs dim alone behind the partition: {region_err}"
    );
}

// ---------------------------------------------------------------------------
// 7. An enclosure with ρ = 0.99
// ---------------------------------------------------------------------------

/// A closed box with ρ = 0.99 everywhere: in iteration k the unshot power is
/// exactly ρ^k of the emitted, so `Stop::Converge { 1e-3 }` must stop after
/// exactly ⌈ln 1e-3 / ln 0.99⌉ = 688 iterations (0.99^687 = 1.0010e-3,
/// 0.99^688 = 0.9910e-3: no rounding ambiguity), with each iteration's unshot
/// 0.99 × the previous to 1e-9, shot = received to 1e-9 and nothing escaping.
/// As a furnace (every wall emitting Le = 1), every covered texel holds
/// Le·(1 − ρ^(K+1))/(1 − ρ) = 99.9 to 1e-4 relative after those 688
/// iterations (f32 maps: 1e-4 leaves room for 688 f64 additions and the
/// final f32 rounding).
/// l = 33, N = 16: the answer is exact for any discretisation, and 2 × 688
/// iterations must stay cheap.
#[test]
fn enclosure_with_reflectance_099_converges_at_the_predicted_iteration() {
    let rho: f64 = 0.99;
    let predicted = (1e-3f64.ln() / rho.ln()).ceil() as u32;
    assert_eq!(predicted, 688);
    let stop = Stop::Converge {
        epsilon: 1e-3,
        max_iterations: 5000,
    };
    for (case, emitting) in [("one lamp", vec![3]), ("furnace", vec![0, 1, 2, 3, 4, 5])] {
        let scene = closed_box(
            0.55,
            1,
            &emitting,
            vec![material("wall", rho, 0.0), material("glow", rho, 1.0)],
        );
        let started = std::time::Instant::now();
        let p = propagate(scene, options(33, 16, stop));
        let seconds = started.elapsed().as_secs_f64();
        assert_sane(&p, case);
        let balance = assert_balance(&p, 1e-9, case);
        assert!(
            p.stats
                .iter()
                .all(|s| lum(&s.flow.escaped) + lum(&s.flow.blocked) == 0.0)
        );
        let ratio = assert_geometric(&p, rho * (1.0 + 1e-9), 1, case);
        let mut worst_ratio = 0.0f64;
        for w in p.stats.windows(2) {
            worst_ratio = worst_ratio.max((lum(&w[1].unshot) / lum(&w[0].unshot) - rho).abs() / rho);
        }
        let k = p.iterations_done();
        let band = emission_band(&p);
        println!(
            "{case}: stopped after {k} iterations (predicted {predicted}) in {seconds:.2} s, unshot {:.4e}, \
             ratio {ratio:.6} (deviation from ρ {worst_ratio:.1e}), balance {balance:.1e}",
            p.unshot_fraction()
        );
        assert!(
            worst_ratio < 1e-9,
            "{case}: unshot does not fall by exactly ρ: {worst_ratio}"
        );
        assert_eq!(k, predicted, "{case}: stopped after {k} iterations");
        if case == "furnace" {
            let field = p.into_field();
            assert_field_sane(&field, case);
            let want = (1.0 - rho.powi(k as i32 + 1)) / (1.0 - rho);
            let (checked, worst) = assert_furnace(&field, 1.0, want, band, 1e-4);
            println!("furnace: {checked} texels at {want:.4}, reflected light within {worst:.1e}");
            assert!(checked > 300, "{checked}");
        }
    }
}

// ---------------------------------------------------------------------------
// 8. A box of mirrors
// ---------------------------------------------------------------------------

/// A closed box whose walls are all mirrors (ρs = 0.9, ρd = 0) but for one
/// diffuse, black lamp tile in the ceiling (1/54 of the walls): every
/// iteration balances to 1e-9 with nothing escaping or blocked, mirrors
/// reflect exactly 0.9 of what arrives, all unshot power is specular, and
/// the unshot power falls at least by 0.9 per iteration (the lamp absorbs the
/// rest); `Stop::Converge { 1e-3 }` stops before its cap of 300 iterations.
/// l = 129, N = 32: a box of 54 tiles with axis-aligned mirrors, whose
/// reflections map line directions onto line directions; enough for light to
/// keep bouncing for tens of iterations.
#[test]
fn closed_box_of_mirrors_converges() {
    let rho_s = 0.9;
    let mut scene = closed_box(
        0.55,
        3,
        &[],
        vec![mirror("silver", 0.0, rho_s), material("lamp", 0.0, 1.0)],
    );
    // Face 3 (+y) is tiles 27..36; its centre tile is 31.
    scene.surfaces[31].material = 1;
    let p = propagate(
        scene,
        options(
            129,
            32,
            Stop::Converge {
                epsilon: 1e-3,
                max_iterations: 300,
            },
        ),
    );
    let case = "mirror box";
    assert_sane(&p, case);
    let balance = assert_balance(&p, 1e-9, case);
    let lit = assert_mirror_exchange(&p, rho_s, 1e-9, case);
    for s in &p.stats {
        assert_eq!(lum(&s.flow.escaped), 0.0, "iteration {}: light escaped", s.index);
        assert_eq!(lum(&s.flow.blocked), 0.0, "iteration {}: a back face was hit", s.index);
        let rel = (lum(&s.unshot) - lum(&s.specular_unshot)).abs() / lum(&s.unshot);
        assert!(
            rel < 1e-12,
            "iteration {}: unshot power outside the mirror maps",
            s.index
        );
    }
    let ratio = assert_geometric(&p, rho_s * (1.0 + 1e-9), 1, case);
    let k = p.iterations_done();
    println!(
        "mirror box: {k} iterations ({lit} lit), unshot {:.3e}, worst unshot ratio {ratio:.4}, balance {balance:.1e}",
        p.unshot_fraction()
    );
    assert_eq!(lit as u32, k, "every iteration must reach the mirrors");
    assert!(
        k < 300 && p.unshot_fraction() < 1e-3,
        "{k} iterations, unshot {}",
        p.unshot_fraction()
    );
    assert_field_sane(&p.into_field(), case);
}

/// A texel far too small for the scene (valid on its own: the finest grid, the smallest texel
/// multiple) is refused with the texel count it asks for, before any chart lists its cells. Were
/// the surfaces segmented first, the closed box's 6 square units of walls at a texel of 2.4e-5
/// would be 10¹⁰ cells of hash sets: the test would run out of memory instead.
#[test]
fn a_texel_too_small_for_the_scene_is_refused_before_its_cells_are_listed() {
    let scene = closed_box(
        0.5,
        1,
        &[0],
        vec![material("white", 0.5, 0.0), material("light", 0.5, 1.0)],
    );
    let mut o = options(33, 4096, Stop::Iterations(1));
    o.texel_cells = 0.05;
    o.validate().expect("each parameter is within its range");
    match Propagation::new(scene.clone(), o) {
        Err(vlf_core::Error::Parameter(m)) => assert!(m.contains("choose a larger texel"), "{m}"),
        Err(e) => panic!("refused for another reason: {e}"),
        Ok(_) => panic!("10¹⁰ texels accepted"),
    }
    // The same scene at a texel it can hold is set up.
    let mut o = options(33, 64, Stop::Iterations(1));
    o.texel_cells = 1.0;
    assert!(Propagation::new(scene, o).is_ok());
}

/// A chart no ray crosses takes its neighbours' light, scaled by the two reflectances: a
/// square far below the ray spacing set into the floor of a closed room (the floor cut around
/// it, so they share its corners), of another material (ρ 0.25 against the floor's 0.5), shows
/// half the floor's radiance where it lies; a smaller square in its middle (ρ 0.8, emitting
/// 0.5) touching only the first, none of the floor, takes the same irradiance a ring later and
/// shows `0.5 + 0.8·E/π`. A face under the floor, back to back with it on the inlay's corner,
/// faces the unlit outside and is not taken as a neighbour. Before, both were black: the full
/// Stanford dragon at N = 64 had 9 648 such charts at its creases. The propagation itself is
/// untouched (balance).
#[test]
fn a_chart_no_ray_crosses_takes_its_neighbours_light() {
    let n = 32;
    let (h, tiny) = (0.55, 1e-4 * 2.0 / n as f64);
    let mats = vec![
        material("wall", 0.5, 0.0),
        material("lamp", 0.5, 1.0),
        material("inlay", 0.25, 0.0),
        material("jewel", 0.8, 0.5),
    ];
    let mut scene = closed_box(h, 1, &[3], mats);
    // The floor (face 2, −y, facing +y) as a 3 × 3 grid of quads whose middle cell is the inlay,
    // itself a 3 × 3 grid whose middle cell is the jewel: every corner shared exactly.
    let y = -h;
    let (cx, cz) = (0.1, 0.05);
    let floor_lines = [-h, cx - tiny, cx + tiny, h];
    let floor_lines_z = [-h, cz - tiny, cz + tiny, h];
    let cell = |x0: f64, x1: f64, z0: f64, z1: f64, material: usize| {
        let p = |x: f64, z: f64| DVec3::new(x, y, z);
        surface(vec![p(x0, z0), p(x0, z1), p(x1, z1), p(x1, z0)], material)
    };
    let mut floor = Vec::new();
    for i in 0..3 {
        for j in 0..3 {
            let (x0, x1, z0, z1) = (
                floor_lines[i],
                floor_lines[i + 1],
                floor_lines_z[j],
                floor_lines_z[j + 1],
            );
            if (i, j) != (1, 1) {
                floor.push(cell(x0, x1, z0, z1, 0));
                continue;
            }
            let xs = [x0, cx - tiny / 3.0, cx + tiny / 3.0, x1];
            let zs = [z0, cz - tiny / 3.0, cz + tiny / 3.0, z1];
            for a in 0..3 {
                for b in 0..3 {
                    let material = if (a, b) == (1, 1) { 3 } else { 2 };
                    floor.push(cell(xs[a], xs[a + 1], zs[b], zs[b + 1], material));
                }
            }
        }
    }
    let floor_index = 2;
    scene.surfaces.splice(floor_index..floor_index + 1, floor);
    // Under the floor, back to back with it and sharing the inlay's corner: a face of the
    // outside, which no light reaches. It faces the other way, so the inlay takes nothing from
    // it. (Its edges cross the floor's cells, so it stands on none of their edges.)
    let p = |x: f64, z: f64| DVec3::new(x, y, z);
    let (x0, z0) = (floor_lines[1], floor_lines_z[1]);
    scene
        .surfaces
        .push(surface(vec![p(x0, z0), p(-0.4, -0.2), p(-0.2, -0.4)], 0));
    let underside = scene.surfaces.len() - 1;
    assert!(scene.surfaces[underside].normal.y < 0.0);
    // Floor cells (0, 0..3) and (1, 0) come first, then the inlay's nine, the jewel fifth.
    let (inlay, jewel) = (floor_index + 4, floor_index + 8);
    assert_eq!(scene.surfaces[inlay].material, 2, "an inlay cell's index");
    assert_eq!(scene.surfaces[jewel].material, 3, "the jewel's index");

    let p = propagate(scene, options(129, n, Stop::Iterations(6)));
    assert_sane(&p, "inlay");
    assert_balance(&p, 1e-9, "inlay");
    for s in [inlay, jewel] {
        let g = p.atlas.grid(s);
        let rays: f64 = p.projected_area[g.first..g.first + g.len()].iter().sum();
        assert_eq!(
            rays, 0.0,
            "a ray crossed surface {s}: the case needs a chart no ray crosses"
        );
    }
    assert_ne!(p.atlas.chart_of[inlay], p.atlas.chart_of[jewel]);
    let g = p.atlas.grid(underside);
    assert!(p.projected_area[g.first..g.first + g.len()].iter().any(|&a| a > 0.0));
    let floor_grid = p.atlas.grid(floor_index).clone();
    let field = p.into_field();
    assert_field_sane(&field, "inlay");
    // The floor's radiance where the inlay lies (the texel holding its centre, which holds all
    // its corners: it is 1e-4 of a ray spacing across).
    let centre = DVec3::new(cx, y, cz);
    let under = field.radiance[floor_grid.index(floor_grid.coords(centre))];
    assert!(under[0] > 0.0);
    let shown = |s: usize| {
        let g = field.atlas.grid(s);
        field.radiance[g.first..g.first + g.len()].to_vec()
    };
    for (k, l) in shown(inlay).iter().enumerate() {
        let want = under[0] as f64 * 0.25 / 0.5;
        assert!(
            (l[0] as f64 - want).abs() <= 1e-6 * want,
            "inlay texel {k}: {l:?}, the floor under it shows {under:?}, so {want} was due"
        );
    }
    for (k, l) in shown(jewel).iter().enumerate() {
        let want = 0.5 + 0.8 * under[0] as f64 / 0.5;
        assert!(
            (l[0] as f64 - want).abs() <= 1e-6 * want,
            "jewel texel {k}: {l:?}, {want} was due (emission 0.5 and the floor's irradiance)"
        );
    }
}
