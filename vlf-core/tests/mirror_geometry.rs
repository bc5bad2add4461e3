//! A job's stored mirror geometry (`MirrorGeometry`): read back, it is the specular state that
//! set-up computes, to the bit; one that does not fit the job is refused with what is wrong,
//! never indexed.

mod common;

use common::*;
use glam::DVec3;
use vlf_core::propagate::survey::Surveyed;
use vlf_core::propagate::{MirrorGeometry, Options, Propagation, Stop, SurveyParts, Surveyor};
use vlf_core::psf::GridSize;
use vlf_core::scene::Scene;

fn options(l: usize, iterations: u32) -> Options {
    Options {
        directions: l,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(iterations),
        ..Options::default()
    }
}

/// The mirror room (two flat mirror walls) with a faceted mirror ball of 80 triangles in it.
fn room_with_ball() -> Scene {
    let room = mirror_room();
    let mut surfaces = room.surfaces.clone();
    for t in icosphere(DVec3::new(0.05, -0.1, 0.0), 0.15, 1) {
        surfaces.push(surface(t.to_vec(), 2));
    }
    scene(surfaces, room.materials.clone())
}

/// `set_up` failed, with an error about `what` that `says` why.
fn refused(set_up: vlf_core::Result<Propagation>, what: &str, says: &str) {
    let error = set_up.err().expect(says).to_string();
    assert!(error.contains(what) && error.contains(says), "{says}: {error}");
}

fn digest(mut p: Propagation) -> String {
    p.run(|_| {});
    p.into_field().digest()
}

/// Whoever reads the geometry a propagation stores has its views, routes and field (and builds no
/// subfield of the scene); a worker that computes it from the mirror planes alone writes the same
/// bytes; what is read is what the bytes say; a diffuse scene has none.
#[test]
fn a_stored_mirror_geometry_is_the_computed_one() {
    for scene in [room_with_ball(), mirror_room()] {
        let p = Propagation::new(scene.clone(), options(129, 2)).unwrap();
        let bytes = p.mirror_geometry().expect("a mirror scene has a geometry");
        let geometry = MirrorGeometry::from_bytes(&bytes).unwrap();
        assert_eq!(geometry.to_bytes(), bytes);
        // Written into a writer, the same bytes, as long as announced; read out of a reader, the
        // same geometry, and not a byte past it.
        let borrowed = p.mirror_geometry_ref().unwrap();
        let mut written = Vec::new();
        borrowed.write_to(&mut written).unwrap();
        assert_eq!((written.len() as u64, &written), (borrowed.serialized_len(), &bytes));
        let followed = [bytes.as_slice(), &[7, 7, 7]].concat();
        let mut reader = followed.as_slice();
        assert_eq!(
            MirrorGeometry::read_from(&mut reader, followed.len() as u64).unwrap(),
            geometry
        );
        assert_eq!(reader, [7, 7, 7]);
        let read = Propagation::with_stored(scene.clone(), options(129, 2), None, p.survey(), geometry).unwrap();
        assert_eq!(read.subfields.memory().builds, 0);
        let (a, b) = (read.specular.as_ref().unwrap(), p.specular.as_ref().unwrap());
        assert!(a.mirrors == b.mirrors && a.views == b.views && a.routes == b.routes);
        assert_eq!(read.plan.mirror_slots, p.plan.mirror_slots);
        assert!(b.routes.iter().map(Vec::len).sum::<usize>() > 0);
        assert_eq!(digest(read), digest(p.clone()));

        let computed = Propagation::with_survey(scene.clone(), options(129, 2), None, p.survey()).unwrap();
        assert_eq!(computed.mirror_geometry(), Some(bytes.clone()));

        // Read, not found again: a route altered in the bytes is altered in the propagation.
        let mut altered = MirrorGeometry::from_bytes(&bytes).unwrap();
        let t = (0..altered.routes.len())
            .find(|&t| !altered.routes[t].is_empty())
            .unwrap();
        altered.routes[t][0].weight *= 0.5;
        let read = Propagation::with_stored(scene, options(129, 2), None, p.survey(), altered.clone()).unwrap();
        assert_eq!(*read.specular.unwrap().routes, *altered.routes);
    }
    assert!(
        Propagation::new(lit_box(), options(33, 1))
            .unwrap()
            .mirror_geometry()
            .is_none()
    );
}

/// Every way a stored geometry can misfit its job — another scene or options, other mirrors,
/// tables that would index out of bounds or break the routes' order, bytes that are not one —
/// is a decode error that says what, never a panic or a field.
#[test]
fn a_mirror_geometry_that_does_not_fit_is_refused() {
    let scene = room_with_ball();
    let p = Propagation::new(scene.clone(), options(129, 1)).unwrap();
    let bytes = p.mirror_geometry().unwrap();
    let good = MirrorGeometry::from_bytes(&bytes).unwrap();
    let l = good.views.len();
    let tile = good.views[0].grid.tile as u16;
    // A view with spans, a non-mirror surface, a target with several routes.
    let d = (0..l).find(|&d| !good.views[d].spans.is_empty()).unwrap();
    let wall = (0..scene.surfaces.len() as u32)
        .find(|&s| !scene.material(s as usize).is_mirror())
        .unwrap();
    let t = (0..l).find(|&t| good.routes[t].len() > 1).unwrap();
    let other_l = MirrorGeometry::from_bytes(
        &Propagation::new(scene.clone(), options(33, 1))
            .unwrap()
            .mirror_geometry()
            .unwrap(),
    )
    .unwrap();
    let other_scene = MirrorGeometry::from_bytes(
        &Propagation::new(mirror_room(), options(129, 1))
            .unwrap()
            .mirror_geometry()
            .unwrap(),
    )
    .unwrap();

    type Misfit = Box<dyn Fn(&mut MirrorGeometry)>;
    let cases: Vec<(Misfit, &str)> = vec![
        (Box::new(move |g| *g = other_l.clone()), "computed for l = 33"),
        (Box::new(move |g| *g = other_scene.clone()), "another scene"),
        (Box::new(|g| _ = g.mirrors.pop()), "other mirrors"),
        (Box::new(|g| _ = g.views.pop()), "views"),
        (Box::new(|g| g.views.swap(0, 1)), "another frame"),
        (Box::new(move |g| g.views[d].spans[0].end = tile + 1), "outside"),
        (
            Box::new(move |g| g.views[d].spans[0].start = g.views[d].spans[0].end),
            "outside",
        ),
        (Box::new(move |g| g.views[d].entries[0].rays += 1), "miscounts"),
        (
            Box::new(move |g| g.views[d].entries[0].span_count = u32::MAX),
            "past its",
        ),
        (Box::new(move |g| g.views[d].entries[0].surface = wall), "cannot hold"),
        (Box::new(move |g| _ = g.views[d].tile_start.pop()), "tile starts"),
        (
            Box::new(move |g| *g.views[d].tile_start.last_mut().unwrap() += 1),
            "tile starts",
        ),
        (
            Box::new(move |g| g.routes[t][0].source = l as u32),
            "not one of the job's",
        ),
        (Box::new(move |g| g.routes[t][0].mirror = wall), "not one of the job's"),
        (Box::new(move |g| g.routes[t][0].weight = f64::NAN), "share NaN"),
        (Box::new(move |g| g.routes[t].reverse()), "out of order"),
    ];
    for (misfit, says) in cases {
        let mut geometry = good.clone();
        misfit(&mut geometry);
        // Through its bytes, as a store gives it.
        let geometry = MirrorGeometry::from_bytes(&geometry.to_bytes()).unwrap();
        let read = Propagation::with_stored(scene.clone(), options(129, 1), None, p.survey(), geometry);
        refused(read, "mirror geometry", says);
    }
    let mut trailing = bytes.clone();
    trailing.push(0);
    let huge_string = [1, 0, 0, 0, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f].to_vec();
    let mut version = bytes.clone();
    version[0] = 9;
    for (bytes, says) in [
        (bytes[..bytes.len() / 2].to_vec(), "mirror geometry"),
        (trailing, "trailing bytes"),
        (version, "version 9"),
        (vec![1, 0], "too short"),
        // The scene's hash claims 2⁶³ − 1 bytes: refused, not allocated (nor a panic).
        (huge_string.clone(), "mirror geometry"),
    ] {
        let error = MirrorGeometry::from_bytes(&bytes).expect_err(says).to_string();
        assert!(error.contains(says), "{says}: {error}");
    }
    // The same out of a stream, which holds no more than its length says.
    let error = MirrorGeometry::read_from(huge_string.as_slice(), huge_string.len() as u64).unwrap_err();
    assert!(error.to_string().contains("mirror geometry"), "{error}");
    // A diffuse job has none to read, even one that says it is the job's.
    let diffuse = Propagation::new(lit_box(), options(33, 1)).unwrap();
    let mut geometry = good;
    geometry.of = Surveyed::of(&lit_box(), &options(33, 1));
    let error = Propagation::with_stored(lit_box(), options(33, 1), None, diffuse.survey(), geometry)
        .err()
        .unwrap()
        .to_string();
    assert!(error.contains("maps no mirror"), "{error}");
}

/// What a coordinator whose workers learnt the survey sets a job up with: the mirror planes
/// learnt with the survey's parts (here three, of 40, 1 and 88 directions) give the views,
/// routes and field that set-up computes — restricted to the mirrors light reaches, not the
/// one outside the room — and planes that do not fit the directions are refused.
#[test]
fn views_cut_from_the_surveys_mirror_planes_are_the_computed_ones() {
    let room = room_with_ball();
    let mut surfaces = room.surfaces.clone();
    // A mirror outside the closed room, facing away: in every direction's planes, never lit.
    surfaces.push(rect(
        DVec3::new(0.8, 0.0, 0.0),
        DVec3::new(0.0, 0.2, 0.0),
        DVec3::new(0.0, 0.0, 0.2),
        DVec3::X,
        2,
    ));
    let scene = scene(surfaces, room.materials.clone());
    let outside = scene.surfaces.len() as u32 - 1;
    let options = options(129, 2);
    let p = Propagation::new(scene.clone(), options.clone()).unwrap();
    let spec = p.specular.as_ref().unwrap();
    assert!(!spec.mirrors.contains(&outside) && spec.mirrors.len() > 2);

    let surveyor = Surveyor::new(&scene, &options, None).unwrap();
    let mut parts = SurveyParts::new(&scene, &options);
    let mut short = surveyor.part(0..40).unwrap();
    short.mirror_planes.pop();
    let error = parts.add(short).unwrap_err().to_string();
    assert!(error.contains("39 mirror planes for 40"), "{error}");
    for range in [0..40, 40..41, 41..129] {
        parts.add(surveyor.part(range).unwrap()).unwrap();
    }
    let (survey, planes) = parts.finish_with_planes(&scene).unwrap();
    assert!(survey == p.survey());
    let holds_outside = |d: usize| planes[d].entries.iter().any(|e| e.surface == outside);
    assert!((0..129).any(holds_outside), "the planes hold every mirror");

    let cut = Propagation::with_survey_and_planes(scene.clone(), options.clone(), None, survey.clone(), planes.clone())
        .unwrap();
    let (a, b) = (cut.specular.as_ref().unwrap(), spec);
    assert!(a.mirrors == b.mirrors && a.views == b.views && a.routes == b.routes);
    assert_eq!(cut.mirror_geometry(), p.mirror_geometry());
    assert_eq!(digest(cut), digest(p.clone()));

    let wall = (0..scene.surfaces.len() as u32)
        .find(|&s| !scene.material(s as usize).is_mirror())
        .unwrap();
    let d = (0..129).find(|&d| !planes[d].entries.is_empty()).unwrap();
    type Misfit = Box<dyn Fn(&mut Vec<vlf_core::psf::Subfield>)>;
    let cases: Vec<(Misfit, &str)> = vec![
        (Box::new(|planes| _ = planes.pop()), "128 views for 129 directions"),
        (Box::new(|planes| planes.swap(0, 1)), "another frame"),
        (
            Box::new(move |planes| planes[d].entries[0].surface = wall),
            "cannot hold",
        ),
        (Box::new(move |planes| planes[d].entries[0].rays += 1), "miscounts"),
    ];
    for (misfit, says) in cases {
        let mut planes = planes.clone();
        misfit(&mut planes);
        let cut = Propagation::with_survey_and_planes(scene.clone(), options.clone(), None, survey.clone(), planes);
        refused(cut, "the survey's mirror planes", says);
    }
}
