//! OBJ + MTL import tests: small files written into a temporary folder.

use super::*;
use crate::scene::newell_normal;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Joins lines with `\n`, so that line `k` of a test file is `lines[k-1]`.
fn text(lines: &[&str]) -> String {
    lines.join("\n") + "\n"
}

/// Writes `scene.obj` (and `scene.mtl`) into a fresh folder under the
/// temp dir, loads it with `options`, removes the folder.
fn load_with(obj: &str, mtl: Option<&str>, options: &ImportOptions) -> Result<(Scene, Vec<String>), Error> {
    static COUNTER: AtomicUsize = AtomicUsize::new(0);
    let dir = std::env::temp_dir().join(format!(
        "vlf-core-import-test-{}-{}",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("scene.obj");
    std::fs::write(&path, obj).unwrap();
    if let Some(mtl) = mtl {
        std::fs::write(dir.join("scene.mtl"), mtl).unwrap();
    }
    let result = load_obj(&path, options);
    std::fs::remove_dir_all(&dir).unwrap();
    result
}

fn load(obj: &str, mtl: &str) -> Result<(Scene, Vec<String>), Error> {
    load_with(obj, Some(mtl), &ImportOptions::default())
}

/// The error's message, checked to be a `Scene` error.
fn scene_error(obj: &str, mtl: &str) -> String {
    match load(obj, mtl) {
        Err(e @ Error::Scene { .. }) => e.to_string(),
        Err(e) => panic!("expected a scene error, got {e}"),
        Ok(_) => panic!("expected an error, the scene loaded"),
    }
}

fn mtl() -> String {
    text(&[
        "newmtl white",              // 1
        "Kd 0.75 0.75 0.75",         // 2
        "newmtl red",                // 3
        "Kd 0.75 0.25 0.25",         // 4
        "newmtl light",              // 5
        "Kd 0.5",                    // 6
        "Ke 10 10 8",                // 7
        "newmtl mirror",             // 8
        "Kd 0.1 0.1 0.1",            // 9
        "Ks 0.9 0.8 0.9",            // 10
        "illum 3",                   // 11
        "newmtl glossy",             // 12
        "Kd 0.8 0.8 0.8",            // 13
        "Ks 0.5 0.5 0.5",            // 14
        "illum 2",                   // 15
        "newmtl grey_light",         // 16
        "Ke 5",                      // 17
        "newmtl unused_and_invalid", // 18
        "Kd 2 -1 0",                 // 19
    ])
}

/// A unit emitter quad (lines 1–7) followed by `extra` from line 8 on.
fn with_emitter(extra: &[&str]) -> String {
    let mut lines = vec![
        "mtllib scene.mtl",
        "v 0 0 0",
        "v 1 0 0",
        "v 1 1 0",
        "v 0 1 0",
        "usemtl light",
        "f 1 2 3 4",
    ];
    lines.extend_from_slice(extra);
    text(&lines)
}

fn cornell() -> String {
    text(&[
        "# Cornell-like box [0,2]³, walls facing inwards", // 1
        "mtllib scene.mtl",                                // 2
        "v 0 0 0",                                         // 3
        "v 2 0 0",
        "v 2 2 0",
        "v 0 2 0",
        "v 0 0 2",
        "v 2 0 2",
        "v 2 2 2",
        "v 0 2 2",               // 10
        "usemtl white",          // 11
        "o floor",               // 12
        "f 1 5 6 2",             // 13 floor, +y
        "f 4 3 7 8",             // 14 ceiling, -y
        "f 1 2 3 4",             // 15 back, +z
        "usemtl red",            // 16
        "f 1 4 8 5",             // 17 left, +x
        "f 2/1/1 6//2 7/3 3",    // 18 right, -x
        "v 0.75 1.99 0.75",      // 19
        "v 1.25 1.99 0.75",      // 20
        "v 1.25 1.99 1.25",      // 21
        "v 0.75 1.99 1.25",      // 22
        "usemtl light",          // 23
        "f -4 -3 -2 -1 # light", // 24, facing down
    ])
}

#[test]
fn cornell_box_loads_and_is_normalised() {
    let (scene, warnings) = load(&cornell(), &mtl()).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(scene.surfaces.len(), 6);
    // Only the used materials, in order of first use.
    let names: Vec<&str> = scene.materials.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(names, ["white", "red", "light"]);

    let expected = [
        (13, DVec3::Y, "white"),
        (14, DVec3::NEG_Y, "white"),
        (15, DVec3::Z, "white"),
        (17, DVec3::X, "red"),
        (18, DVec3::NEG_X, "red"),
        (24, DVec3::NEG_Y, "light"),
    ];
    for (k, (line, normal, material)) in expected.into_iter().enumerate() {
        let s = &scene.surfaces[k];
        assert_eq!(s.origin, FaceOrigin { line, face: k });
        assert!((s.normal - normal).length() < 1e-12, "{line}: {}", s.normal);
        assert_eq!(scene.materials[s.material].name, material);
        // CCW about the normal, on the plane.
        assert!(newell_normal(&s.vertices).normalize().dot(s.normal) > 1.0 - 1e-12);
        for v in &s.vertices {
            assert!((s.normal.dot(*v) - s.offset).abs() < 1e-12);
        }
    }
    assert_eq!(scene.materials[2].emission, [10.0, 10.0, 8.0]);
    assert_eq!(scene.materials[2].diffuse, [0.5; 3]);

    // Centre of the box, farthest corners at √3.
    let norm = scene.normalisation;
    assert!((norm.center - DVec3::ONE).length() < 1e-15);
    let scale = Scene::FRAME_RADIUS / 3f64.sqrt();
    assert!((norm.scale - scale).abs() < 1e-14);
    let area: f64 = scene.surfaces.iter().map(|s| s.area).sum();
    let expected_area = (5.0 * 4.0 + 0.25) * scale * scale;
    assert!((area - expected_area).abs() < 1e-12, "{area} vs {expected_area}");
    assert!((scene.surfaces[5].area - 0.25 * scale * scale).abs() < 1e-14);

    let radii = scene
        .surfaces
        .iter()
        .flat_map(|s| s.vertices.iter().map(|v| v.length()));
    let max = radii.clone().fold(0.0, f64::max);
    assert!(radii.clone().all(|r| r <= Scene::FRAME_RADIUS));
    assert!(max > Scene::FRAME_RADIUS - 1e-12, "{max}");
    // Back to scene units.
    let corner = norm.to_scene(scene.surfaces[0].vertices[0]);
    assert!((corner - DVec3::ZERO).length() < 1e-12, "{corner}");
}

#[test]
fn crlf_comments_and_continuations_are_read() {
    let obj = "mtllib scene.mtl\r\nv 0 0 0 # origin\r\nv 1 0 0\r\nv 1 1 0\r\n\
               v 0 1 0\r\nusemtl light\r\nf 1 2 \\\r\n 3 4\r\n";
    let (scene, _) = load(obj, &mtl()).unwrap();
    assert_eq!(scene.surfaces.len(), 1);
    assert_eq!(scene.surfaces[0].vertices.len(), 4);
    assert_eq!(scene.surfaces[0].origin.line, 7);
}

#[test]
fn non_convex_face_splits_into_convex_pieces() {
    // An L-shaped hexagon, area 3, emitting towards +z.
    let obj = text(&[
        "mtllib scene.mtl",
        "v 0 0 0",
        "v 2 0 0",
        "v 2 1 0",
        "v 1 1 0",
        "v 1 2 0",
        "v 0 2 0",
        "usemtl light",
        "f 1 2 3 4 5 6",
    ]);
    let (scene, warnings) = load(&obj, &mtl()).unwrap();
    assert!(warnings.is_empty());
    assert!(scene.surfaces.len() >= 2, "{}", scene.surfaces.len());
    let scale = scene.normalisation.scale;
    let area: f64 = scene.surfaces.iter().map(|s| s.area).sum();
    assert!((area - 3.0 * scale * scale).abs() < 1e-12);
    for s in &scene.surfaces {
        assert_eq!(s.normal, DVec3::Z);
        assert_eq!(s.origin, FaceOrigin { line: 9, face: 0 });
        assert!(crate::scene::polygon::is_convex(&s.vertices));
        assert!(newell_normal(&s.vertices).normalize().dot(DVec3::Z) > 1.0 - 1e-12);
    }
}

#[test]
fn mirror_needs_illum_3_and_grey_ke() {
    let obj = with_emitter(&[
        "v 0 0 1",
        "v 1 0 1",
        "v 0 1 1",
        "usemtl mirror",
        "f 5 6 7",
        "usemtl glossy",
        "f 5 6 7",
        "usemtl grey_light",
        "f 5 6 7",
    ]);
    let (scene, _) = load(&obj, &mtl()).unwrap();
    let m = |name: &str| scene.materials.iter().find(|m| m.name == name).unwrap().clone();
    let mirror = m("mirror");
    assert_eq!(mirror.specular, [0.9, 0.8, 0.9]);
    assert_eq!(mirror.diffuse, [0.1; 3]);
    assert!(mirror.is_mirror() && !mirror.is_emitter());
    // illum 2: Ks ignored, so 0.8 + 0.5 is no error either.
    let glossy = m("glossy");
    assert_eq!(glossy.specular, [0.0; 3]);
    assert!(!glossy.is_mirror());
    let grey = m("grey_light");
    assert_eq!(grey.emission, [5.0; 3]);
    assert_eq!(grey.diffuse, [0.0; 3]);
}

#[test]
fn degenerate_faces_are_skipped_with_a_warning() {
    let obj = with_emitter(&[
        "v 2 0 0",     // 8: vertex 5, collinear with 1 and 2
        "f 1 2 5",     // 9: collinear
        "f 1 2 2",     // 10: repeated vertex
        "f 3 3 3 3",   // 11: a point
        "f 1 2 5 2 1", // 12: a spike
    ]);
    let (scene, warnings) = load(&obj, &mtl()).unwrap();
    assert_eq!(scene.surfaces.len(), 1);
    assert_eq!(warnings.len(), 4, "{warnings:?}");
    for (w, line) in warnings.iter().zip(9..) {
        assert!(w.contains(&format!("scene.obj:{line}:")), "{w}");
        assert!(w.contains("degenerate"), "{w}");
    }
}

#[test]
fn lines_and_points_are_ignored_with_a_warning() {
    let obj = with_emitter(&["l 1 2 3", "p 4", "l 1 2"]);
    let (scene, warnings) = load(&obj, &mtl()).unwrap();
    assert_eq!(scene.surfaces.len(), 1);
    assert_eq!(warnings.len(), 1);
    assert!(warnings[0].contains("3 line/point element(s)"), "{}", warnings[0]);
}

#[test]
fn missing_files_are_errors() {
    let missing = std::env::temp_dir().join("vlf-core-no-such-dir/none.obj");
    let e = load_obj(&missing, &ImportOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Io { .. }), "{e}");
    assert!(e.to_string().contains("none.obj"), "{e}");

    let obj = text(&["# header", "mtllib nothere.mtl", "usemtl light"]);
    let e = scene_error(&obj, &mtl());
    assert!(e.contains("scene.obj:2:"), "{e}");
    assert!(e.contains("nothere.mtl"), "{e}");
}

#[test]
fn material_reference_errors_name_the_line() {
    let e = scene_error(&with_emitter(&["usemtl nosuch", "f 1 2 3"]), &mtl());
    assert!(e.contains("scene.obj:8:") && e.contains("nosuch"), "{e}");

    let obj = text(&["mtllib scene.mtl", "v 0 0 0", "v 1 0 0", "v 0 1 0", "f 1 2 3"]);
    let e = scene_error(&obj, &mtl());
    assert!(e.contains("scene.obj:5:") && e.contains("usemtl"), "{e}");

    // No mtllib at all.
    let obj = text(&["v 0 0 0", "v 1 0 0", "v 0 1 0", "usemtl light", "f 1 2 3"]);
    let e = scene_error(&obj, &mtl());
    assert!(e.contains("scene.obj:4:") && e.contains("no mtllib"), "{e}");
}

#[test]
fn malformed_vertices_name_the_line() {
    for (bad, what) in [
        ("v 1 x 0", "malformed number 'x'"),
        ("v 1 2", "expected 3 coordinates"),
        ("v nan 0 0", "not finite"),
        ("v 1e999 0 0", "not finite"),
        ("v 0 -inf 0", "not finite"),
        ("v 1 1 1 0", "weight"),
    ] {
        let e = scene_error(&with_emitter(&[bad]), &mtl());
        assert!(e.contains("scene.obj:8:") && e.contains(what), "{bad}: {e}");
    }
}

#[test]
fn malformed_faces_name_the_line() {
    for (bad, what) in [
        ("f 1 2 9", "out of range"),
        ("f 0 1 2", "index 0"),
        ("f -9 1 2", "before the first vertex"),
        ("f 1 2", "at least 3"),
        ("f 1 2 3.5", "malformed vertex reference"),
        ("f 1/a 2 3", "malformed texture index"),
        ("f 1//0 2 3", "normal index 0"),
        ("f 1/2/3/4 2 3", "malformed vertex reference"),
    ] {
        let e = scene_error(&with_emitter(&["v 5 5 5", bad, "v 6 6 6"]), &mtl());
        assert!(e.contains("scene.obj:9:") && e.contains(what), "{bad}: {e}");
    }
    // Forward references are allowed, relative ones count back.
    let obj = with_emitter(&["usemtl white", "f 5 6 -1", "v 0 0 1", "v 1 0 1", "v 0 1 1"]);
    let (scene, _) = load(&obj, &mtl()).unwrap();
    assert_eq!(scene.surfaces.len(), 2);
}

#[test]
fn non_planar_faces_are_triangulated_and_self_intersecting_ones_are_errors() {
    let bent = with_emitter(&[
        "v 0 0 1",
        "v 1 0 1",
        "v 1 1 1.1",
        "v 0 1 1",
        "usemtl white",
        "f 5 6 7 8", // 13
    ]);
    let (scene, warnings) = load(&bent, &mtl()).unwrap();
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    let w = &warnings[0];
    assert!(w.contains("scene.obj:13: face #1 is not planar"), "{w}");
    // The measured deviation from the Newell plane (≈ 0.025), absolute
    // and relative to the diameter √(1 + 1 + 0.01).
    assert!(w.contains("lies 2.494e-2 from"), "{w}");
    assert!(w.contains("1.759e-2 × the face's diameter 1.418e0"), "{w}");
    assert!(w.contains("split into 2 triangles"), "{w}");
    assert_eq!(scene.surfaces.len(), 3);
    // Both triangles on exactly the original vertices (in the VLF frame).
    let originals: Vec<DVec3> = [(0.0, 0.0, 1.0), (1.0, 0.0, 1.0), (1.0, 1.0, 1.1), (0.0, 1.0, 1.0)]
        .iter()
        .map(|&(x, y, z)| scene.normalisation.to_vlf(DVec3::new(x, y, z)))
        .collect();
    let triangles = &scene.surfaces[1..];
    for s in triangles {
        assert_eq!(s.vertices.len(), 3);
        assert_eq!(s.origin, FaceOrigin { line: 13, face: 1 });
        assert!(s.vertices.iter().all(|v| originals.contains(v)), "{:?}", s.vertices);
        assert!(s.normal.z > 0.99, "{}", s.normal);
    }
    let used: Vec<DVec3> = triangles.iter().flat_map(|s| s.vertices.clone()).collect();
    assert!(originals.iter().all(|v| used.contains(v)));

    // The same face written as those two triangles: the same surfaces,
    // bit for bit, but for where they came from.
    let corner = |v: DVec3| originals.iter().position(|&o| o == v).unwrap() + 5;
    let mut explicit = bent.replace("f 5 6 7 8\n", "");
    for s in triangles {
        let refs: Vec<String> = s.vertices.iter().map(|&v| corner(v).to_string()).collect();
        explicit += &format!("f {}\n", refs.join(" "));
    }
    let (split, warnings) = load(&explicit, &mtl()).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(split.normalisation, scene.normalisation);
    assert_eq!(split.surfaces.len(), 3);
    for (a, b) in split.surfaces.iter().zip(&scene.surfaces) {
        assert_eq!(
            (&a.vertices, a.normal, a.offset, a.area, a.material),
            (&b.vertices, b.normal, b.offset, b.area, b.material)
        );
    }
    // And given as polygons with the quad's origin: identical surfaces.
    let light = scene.materials[0].clone();
    let white = scene.materials[1].clone();
    let unit = |v: DVec3| scene.normalisation.to_scene(v);
    let square = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)].map(|(x, y)| DVec3::new(x, y, 0.0));
    let quad: Vec<DVec3> = [(0.0, 0.0, 1.0), (1.0, 0.0, 1.0), (1.0, 1.0, 1.1), (0.0, 1.0, 1.0)]
        .map(|(x, y, z)| DVec3::new(x, y, z))
        .to_vec();
    let from_quad = Scene::from_polygons(
        &[
            (square.to_vec(), 0, FaceOrigin { line: 7, face: 0 }),
            (quad, 1, FaceOrigin { line: 13, face: 1 }),
        ],
        vec![light.clone(), white.clone()],
        &ImportOptions::default(),
    )
    .unwrap()
    .0;
    assert_eq!(from_quad.surfaces, scene.surfaces);
    let mut polygons = vec![(square.to_vec(), 0, FaceOrigin { line: 7, face: 0 })];
    for s in triangles {
        // Back from the VLF frame to the file's exact numbers.
        let vertices = s.vertices.iter().map(|&v| quad_vertex(unit(v))).collect();
        polygons.push((vertices, 1, FaceOrigin { line: 13, face: 1 }));
    }
    let (from_triangles, warnings) =
        Scene::from_polygons(&polygons, vec![light, white], &ImportOptions::default()).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(from_triangles.surfaces, scene.surfaces);
    assert_eq!(from_triangles, from_quad);

    // A looser tolerance flattens it instead, silently.
    let loose = ImportOptions {
        planarity_tolerance: 0.05,
        ..Default::default()
    };
    let (scene, warnings) = load_with(&bent, Some(&mtl()), &loose).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(scene.surfaces.len(), 2);
    let s = &scene.surfaces[1];
    for v in &s.vertices {
        assert!((s.normal.dot(*v) - s.offset).abs() < 1e-12);
    }

    let bow = with_emitter(&[
        "v 0 0 1",
        "v 3 3 1",
        "v 3 0 1",
        "v 0 1 1",
        "usemtl white",
        "f 5 6 7 8", // 13
    ]);
    let e = scene_error(&bow, &mtl());
    assert!(e.contains("scene.obj:13:") && e.contains("self-intersecting"), "{e}");
}

/// The vertex of the bent quad of the test above nearest to `p` (which
/// is it, to rounding).
fn quad_vertex(p: DVec3) -> DVec3 {
    [(0.0, 0.0, 1.0), (1.0, 0.0, 1.0), (1.0, 1.0, 1.1), (0.0, 1.0, 1.0)]
        .map(|(x, y, z)| DVec3::new(x, y, z))
        .into_iter()
        .min_by(|a, b| a.distance(p).total_cmp(&b.distance(p)))
        .unwrap()
}

#[test]
fn material_errors_name_the_material_and_mtl_file() {
    for (bad, what) in [
        ("Kd -0.1 0.5 0.5", "negative"),
        ("Kd 1.5", "exceeds 1"),
        ("Ke nan 1 1", "not finite"),
        ("Ke 1 -1 1", "negative"),
        ("Ke 1e999", "not finite"),
    ] {
        let lib = text(&["newmtl light", "Ke 1", "newmtl bad", bad]);
        let e = scene_error(&with_emitter(&["usemtl bad", "f 1 2 3"]), &lib);
        assert!(
            e.contains("scene.mtl:3:") && e.contains("'bad'") && e.contains(what),
            "{bad}: {e}"
        );
    }
    // ρd + ρs > 1 with illum 3 (green channel).
    let lib = text(&[
        "newmtl light",
        "Ke 1",
        "newmtl shiny",
        "Kd 0.5 0.6 0.5",
        "Ks 0.5 0.5 0.5",
        "illum 3",
    ]);
    let e = scene_error(&with_emitter(&["usemtl shiny", "f 1 2 3"]), &lib);
    assert!(e.contains("scene.mtl:3:") && e.contains("'shiny'"), "{e}");
    assert!(e.contains("exceeds 1 in the green channel"), "{e}");
    // Exactly 1 is fine despite decimal rounding.
    let lib = lib
        .replace("Kd 0.5 0.6 0.5", "Kd 0.7 0.7 0.7")
        .replace("Ks 0.5 0.5 0.5", "Ks 0.3");
    assert!(load(&with_emitter(&["usemtl shiny", "f 1 2 3"]), &lib).is_ok());

    for (bad, line, what) in [
        ("Kd 0.5 x 0.5", 3, "malformed number 'x'"),
        ("Kd 0.1 0.2", 3, "expected 1 or 3 numbers"),
        ("Kd spectral file.rfl", 3, "not supported"),
        ("illum three", 3, "illum"),
    ] {
        let lib = text(&["newmtl light", "Ke 1", bad]);
        let e = scene_error(&with_emitter(&[]), &lib);
        assert!(
            e.contains(&format!("scene.mtl:{line}:")) && e.contains(what),
            "{bad}: {e}"
        );
    }
    let e = scene_error(&with_emitter(&[]), &text(&["Kd 1", "newmtl light", "Ke 1"]));
    assert!(e.contains("scene.mtl:1:") && e.contains("before any newmtl"), "{e}");
}

#[test]
fn scenes_without_faces_or_emitters_are_errors() {
    let obj = text(&["mtllib scene.mtl", "v 0 0 0", "v 1 0 0", "v 0 1 0"]);
    let e = scene_error(&obj, &mtl());
    assert!(e.contains("no faces"), "{e}");

    let obj = with_emitter(&[]).replace("usemtl light", "usemtl white");
    let e = scene_error(&obj, &mtl());
    assert!(e.contains("no emitter"), "{e}");

    // The only emitter is degenerate: nothing emits.
    let obj = text(&[
        "mtllib scene.mtl",
        "v 0 0 0",
        "v 1 0 0",
        "v 2 0 0",
        "v 0 1 0",
        "usemtl light",
        "f 1 2 3",
        "usemtl white",
        "f 1 2 4",
    ]);
    let e = scene_error(&obj, &mtl());
    assert!(e.contains("no emitter"), "{e}");
}

#[test]
fn invalid_options_are_parameter_errors() {
    for t in [-1.0, f64::NAN, f64::INFINITY] {
        let options = ImportOptions {
            planarity_tolerance: t,
            ..Default::default()
        };
        let e = load_with(&with_emitter(&[]), Some(&mtl()), &options).unwrap_err();
        assert!(matches!(e, Error::Parameter(_)), "{e}");
    }
    assert_eq!(ImportOptions::default().planarity_tolerance, 1e-3);
}
