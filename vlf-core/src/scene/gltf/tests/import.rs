//! What a glTF asset imports as: geometry, transforms, materials.

use super::*;

fn cornell_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj")
}

/// The bundled Cornell box as glTF: every surface, back in scene units,
/// fanned into triangles with f32 positions, one primitive per material.
fn cornell_asset(obj: &Scene) -> Asset {
    let mut a = Asset::new();
    for m in &obj.materials {
        let strength = m.emission.iter().copied().fold(0.0, f64::max);
        let mut material = json!({
            "name": m.name,
            "pbrMetallicRoughness": {"baseColorFactor": [m.diffuse[0], m.diffuse[1], m.diffuse[2], 1.0],
                                     "metallicFactor": 0.0, "roughnessFactor": 1.0},
        });
        if strength > 0.0 {
            material["emissiveFactor"] = json!(m.emission.map(|e| e / strength));
            material["extensions"] = json!({"KHR_materials_emissive_strength": {"emissiveStrength": strength}});
        }
        a.material(material);
    }
    a.root["extensionsUsed"] = json!(["KHR_materials_emissive_strength"]);
    let mut primitives = Vec::new();
    for (k, _) in obj.materials.iter().enumerate() {
        let mut points: Vec<[f32; 3]> = Vec::new();
        for s in obj.surfaces.iter().filter(|s| s.material == k) {
            let v: Vec<DVec3> = s.vertices.iter().map(|&v| obj.normalisation.to_scene(v)).collect();
            for i in 1..v.len() - 1 {
                for p in [v[0], v[i], v[i + 1]] {
                    points.push(p.as_vec3().to_array());
                }
            }
        }
        let position = a.positions(&points);
        primitives.push(json!({"attributes": {"POSITION": position}, "material": k}));
    }
    a.mesh_node(primitives, json!({"name": "box"}));
    a
}

fn area_by_material(scene: &Scene) -> Vec<(String, f64)> {
    scene
        .materials
        .iter()
        .enumerate()
        .map(|(k, m)| {
            let area = scene
                .surfaces
                .iter()
                .filter(|s| s.material == k)
                .map(|s| s.area)
                .sum::<f64>();
            (
                m.name.clone(),
                area / (scene.normalisation.scale * scene.normalisation.scale),
            )
        })
        .collect()
}

#[test]
fn the_cornell_box_as_gltf_matches_the_obj() {
    let (obj, _) = load_obj(&cornell_path(), &ImportOptions::default()).unwrap();
    let asset = cornell_asset(&obj);
    let folder = Folder::new();
    let (json, bin) = asset.gltf_external("box%20data.bin");
    let files = [
        folder.write("embedded.gltf", &asset.gltf()),
        folder.write("external.gltf", &json),
        folder.write("binary.glb", &asset.glb()),
    ];
    folder.write("box data.bin", &bin);
    let expected = area_by_material(&obj);
    for path in &files {
        let (scene, warnings) = load_scene(path, &ImportOptions::default()).unwrap();
        assert!(warnings.is_empty(), "{}: {warnings:?}", path.display());
        let areas = area_by_material(&scene);
        assert_eq!(areas.len(), expected.len());
        for ((name, area), (obj_name, obj_area)) in areas.iter().zip(&expected) {
            assert_eq!(name, obj_name);
            assert!(
                (area - obj_area).abs() <= 1e-5 * obj_area,
                "{name}: {area} vs {obj_area}"
            );
        }
        for (m, o) in scene.materials.iter().zip(&obj.materials) {
            assert_rgb(m.diffuse, o.diffuse, 1e-6);
            assert_rgb(m.specular, o.specular, 0.0);
            assert_rgb(m.emission, o.emission, 1e-5 * o.emission[0].max(1.0));
        }
        // Same box: the same normalisation, to f32 rounding.
        assert!((scene.normalisation.center - obj.normalisation.center).length() < 1e-3);
        assert!((scene.normalisation.scale / obj.normalisation.scale - 1.0).abs() < 1e-6);
    }
    // What a copy or an upload of the asset needs besides itself.
    assert_eq!(gltf_external_files(&files[0]).unwrap(), Vec::<PathBuf>::new());
    assert_eq!(gltf_external_files(&files[1]).unwrap(), [PathBuf::from("box data.bin")]);
    assert_eq!(gltf_external_files(&files[2]).unwrap(), Vec::<PathBuf>::new());
    // The extension decides the format, whatever the case.
    let upper = folder.write("BOX.GLB", &asset.glb());
    assert!(load_scene(&upper, &ImportOptions::default()).is_ok());
}

#[test]
fn unknown_formats_are_named() {
    for name in ["scene.fbx", "scene"] {
        let e = load_scene(Path::new(name), &ImportOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains(".obj, .gltf, .glb"), "{e}");
        assert!(e.starts_with(name), "{e}");
    }
}

#[test]
fn node_transforms_compose_down_the_hierarchy() {
    let mut a = with_light();
    let white = a.material(json!({"name": "white",
        "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1], "metallicFactor": 0}}));
    let tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    // Parent: scale 2, then 90° about z, then +10 x; child: +1 x.
    let h = std::f32::consts::FRAC_1_SQRT_2;
    let child = a.triangles(&tri, None, white, json!({"translation": [1.0, 0.0, 0.0]}));
    a.root["scenes"][0]["nodes"].as_array_mut().unwrap().pop();
    let parent = a.push(
        "nodes",
        json!({"translation": [10.0, 0.0, 0.0], "rotation": [0.0, 0.0, h, h], "scale": [2.0, 2.0, 2.0],
               "children": [child]}),
    );
    // A column-major matrix: +5 z. And a mirror (scale -1 in x): fronts stay
    // fronts, so the triangle still faces +z.
    let matrix = json!({"matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 5, 1]});
    a.triangles(&tri, None, white, matrix);
    a.triangles(
        &tri,
        None,
        white,
        json!({"scale": [-1.0, 1.0, 1.0], "translation": [0.0, 0.0, -3.0]}),
    );
    a.root["scenes"][0]["nodes"].as_array_mut().unwrap().push(json!(parent));

    let (scene, warnings) = load(&a.gltf()).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(scene.surfaces.len(), 4);
    let corners = |k: usize| -> Vec<DVec3> {
        scene.surfaces[k]
            .vertices
            .iter()
            .map(|&v| scene.normalisation.to_scene(v))
            .collect()
    };
    let close = |a: &[DVec3], b: &[[f64; 3]]| {
        assert_eq!(a.len(), b.len());
        // Same cycle, from any start.
        let ok = (0..b.len()).any(|r| (0..b.len()).all(|i| (a[i] - DVec3::from(b[(i + r) % b.len()])).length() < 1e-5));
        assert!(ok, "{a:?} vs {b:?}");
    };
    // Scene order: the root nodes as listed (lamp, matrix, mirror, parent).
    close(&corners(1), &[[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 5.0]]);
    close(&corners(2), &[[0.0, 0.0, -3.0], [0.0, 1.0, -3.0], [-1.0, 0.0, -3.0]]);
    close(&corners(3), &[[10.0, 2.0, 0.0], [10.0, 4.0, 0.0], [8.0, 2.0, 0.0]]);
    for k in 1..4 {
        assert!(
            (scene.surfaces[k].normal - DVec3::Z).length() < 1e-6,
            "{k}: {}",
            scene.surfaces[k].normal
        );
    }
    // The scaled triangle has 4× the area.
    let s = scene.normalisation.scale;
    assert!((scene.surfaces[3].area / (s * s) - 2.0).abs() < 1e-5);
}

#[test]
fn double_sided_triangles_face_both_ways() {
    let mut a = with_light();
    let m = a.material(json!({"name": "card", "doubleSided": true, "pbrMetallicRoughness": {"metallicFactor": 0}}));
    let quad = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 1.0, 1.0]];
    a.triangles(&quad, Some(&[0, 1, 2, 0, 2, 3]), m, json!({}));
    let (scene, warnings) = load(&a.gltf()).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(scene.surfaces.len(), 1 + 4);
    let card: Vec<&Surface> = scene.surfaces[1..].iter().collect();
    let up = card.iter().filter(|s| (s.normal - DVec3::Z).length() < 1e-9).count();
    let down = card.iter().filter(|s| (s.normal + DVec3::Z).length() < 1e-9).count();
    assert_eq!((up, down), (2, 2));
    // Each side covers the whole card, from the same triangles.
    let s = scene.normalisation.scale;
    for normal in [DVec3::Z, DVec3::NEG_Z] {
        let area: f64 = card.iter().filter(|c| c.normal.dot(normal) > 0.0).map(|c| c.area).sum();
        assert!((area / (s * s) - 1.0).abs() < 1e-9, "{area}");
    }
    assert_eq!(card[0].origin, card[1].origin);
    assert_eq!(card[0].origin.face, 1);
    assert_eq!(card[2].origin.face, 2);
}

#[test]
fn emissive_strength_scales_the_emission() {
    let mut a = Asset::new();
    let bright = a.material(json!({"name": "bright", "emissiveFactor": [1.0, 0.5, 0.25],
                                   "pbrMetallicRoughness": {"metallicFactor": 0},
                                   "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 8.0}}}));
    let plain = a.material(json!({"name": "plain", "emissiveFactor": [1.0, 0.5, 0.25],
                                  "pbrMetallicRoughness": {"metallicFactor": 0}}));
    a.root["extensionsUsed"] = json!(["KHR_materials_emissive_strength"]);
    a.root["extensionsRequired"] = json!(["KHR_materials_emissive_strength"]);
    a.triangles(&LIGHT, None, bright, json!({}));
    a.triangles(&LIGHT, None, plain, json!({"translation": [0, 0, 1]}));
    let (scene, warnings) = load(&a.gltf()).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(material(&scene, "bright").emission, [8.0, 4.0, 2.0]);
    assert_eq!(material(&scene, "plain").emission, [1.0, 0.5, 0.25]);
    // Default base colour (1) and no metal: a white diffuser.
    assert_eq!(material(&scene, "plain").diffuse, [1.0; 3]);
}

#[test]
fn smooth_metal_is_a_mirror_and_the_rest_is_approximated_with_warnings() {
    let mut a = with_light();
    let pbr = |metallic: f64, roughness: f64| json!({"baseColorFactor": [0.9, 0.8, 0.7, 1.0], "metallicFactor": metallic, "roughnessFactor": roughness});
    let names = ["mirror", "rough_metal", "half_metal", "glass"];
    let materials = [
        json!({"name": "mirror", "pbrMetallicRoughness": pbr(1.0, 0.0)}),
        json!({"name": "rough_metal", "pbrMetallicRoughness": pbr(1.0, 0.5)}),
        json!({"name": "half_metal", "pbrMetallicRoughness": pbr(0.5, 0.05)}),
        json!({"name": "glass", "pbrMetallicRoughness": pbr(0.0, 0.5),
               "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}}}),
    ];
    for (k, m) in materials.into_iter().enumerate() {
        let m = a.material(m);
        a.triangles(&LIGHT, None, m, json!({"translation": [0, 0, k + 1]}));
    }
    let (scene, warnings) = load(&a.gltf()).unwrap();
    let mirror = material(&scene, "mirror");
    assert_eq!(mirror.specular, [0.9f32, 0.8, 0.7].map(f64::from));
    assert_eq!(mirror.diffuse, [0.0; 3]);
    let rough = material(&scene, "rough_metal");
    assert_eq!(
        (rough.diffuse, rough.specular),
        ([0.9f32, 0.8, 0.7].map(f64::from), [0.0; 3])
    );
    let half = material(&scene, "half_metal");
    assert_rgb(half.specular, [0.45, 0.4, 0.35], 1e-7);
    assert_rgb(half.diffuse, [0.45, 0.4, 0.35], 1e-7);
    let glass = material(&scene, "glass");
    assert_rgb(glass.diffuse, [0.9, 0.8, 0.7], 1e-7);
    // One warning each but for the mirror, naming the material.
    assert_eq!(warnings.len(), 3, "{warnings:?}");
    for (w, name) in warnings.iter().zip(&names[1..]) {
        assert!(w.starts_with(&format!("scene.gltf: material '{name}' (#")), "{w}");
    }
    assert!(warnings[0].contains("approximated as diffuse"), "{}", warnings[0]);
    assert!(warnings[1].contains("partial mirror"), "{}", warnings[1]);
    assert!(
        warnings[2].contains("extension KHR_materials_transmission ignored"),
        "{}",
        warnings[2]
    );
}

/// A 2×2 PNG with the given sRGB pixels, as a `data:` URI.
fn png_uri(pixels: [[u8; 3]; 4]) -> String {
    let image = image::RgbImage::from_raw(2, 2, pixels.concat()).unwrap();
    let mut png = std::io::Cursor::new(Vec::new());
    image.write_to(&mut png, image::ImageFormat::Png).unwrap();
    let data = base64::engine::general_purpose::STANDARD.encode(png.into_inner());
    format!("data:image/png;base64,{data}")
}

/// Without texture coordinates, a diffuser's base colour texture reads as its mean colour; an
/// emissive texture is averaged.
#[test]
fn textures_are_averaged_in_linear_colour() {
    // sRGB 128 is linear 0.2158605 (and 0, 255 are 0, 1).
    let uri = png_uri([[255, 128, 0], [0, 128, 255], [128, 128, 128], [255, 255, 255]]);
    let mut a = with_light();
    a.push("images", json!({"uri": uri}));
    a.push("textures", json!({"source": 0}));
    let m = a.material(json!({"name": "painted",
        "pbrMetallicRoughness": {"baseColorFactor": [0.5, 1.0, 1.0, 1.0], "baseColorTexture": {"index": 0},
                                 "metallicFactor": 0}}));
    a.triangles(&LIGHT, None, m, json!({"translation": [0, 0, 1]}));
    // The same texture as the emitter's emissive texture, from the cache.
    a.root["materials"][0]["emissiveTexture"] = json!({"index": 0});
    let (scene, warnings) = load(&a.gltf()).unwrap();
    let l128 = 0.215_860_5;
    let average = [(2.0 + l128) / 4.0, (1.0 + 3.0 * l128) / 4.0, (2.0 + l128) / 4.0];
    let painted = material(&scene, "painted");
    assert_eq!(painted.diffuse, [0.5, 1.0, 1.0]);
    let surface = (0..scene.surfaces.len())
        .find(|&s| scene.material(s).name == "painted")
        .unwrap();
    let rho = scene.albedo_at(surface, scene.surfaces[surface].vertices[0]);
    assert_rgb(rho, [0.5 * average[0], average[1], average[2]], 1e-6);
    assert_rgb(material(&scene, "lamp").emission, average, 1e-6);
    // Averaging the encoded values instead would give about 0.31 in red.
    assert!((rho[0] - 0.3125).abs() > 0.03);
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("'lamp'") && w.contains("emissiveTexture averaged"))
    );
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("primitive 0") && w.contains("no TEXCOORD_0"))
    );
}

/// A dynamic object with a base colour texture (factor 1) gathers with ρd = the texture's mean,
/// not 1: an object's material has one reflectance (`DynamicObject::load` says so in a warning).
#[test]
fn a_textured_object_takes_its_textures_mean_as_its_reflectance() {
    let uri = png_uri([[255, 128, 0], [0, 128, 255], [128, 128, 128], [255, 255, 255]]);
    let mut a = Asset::new();
    a.push("images", json!({"uri": uri}));
    a.push("textures", json!({"source": 0}));
    let m = a.material(json!({"name": "painted",
        "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 0.5, 1.0], "baseColorTexture": {"index": 0},
                                 "metallicFactor": 0}}));
    a.triangles(&LIGHT, None, m, json!({}));
    let folder = Folder::new();
    let path = folder.write("o.gltf", &a.gltf());
    let (object, warnings) = crate::dynamic::DynamicObject::load(&path).unwrap();
    let l128 = 0.215_860_5;
    let mean = [(2.0 + l128) / 4.0, (1.0 + 3.0 * l128) / 4.0, (2.0 + l128) / 4.0];
    let painted = &object.materials[object.material_of[0] as usize];
    assert_rgb(painted.diffuse, [mean[0], mean[1], 0.5 * mean[2]], 1e-6);
    assert_eq!(painted.albedo_texture, None);
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("'painted'") && w.contains("averaged over the object")),
        "{warnings:?}"
    );
}

/// A floor of two triangles whose texture is white on its left half and black on its right
/// (clamped at the edges), under a lamp.
pub(super) fn textured_floor(left: [u8; 3], right: [u8; 3], factor: f32) -> Asset {
    let mut a = Asset::new();
    let lamp = a.material(json!({"name": "lamp", "emissiveFactor": [1.0, 1.0, 1.0],
                                 "pbrMetallicRoughness": {"metallicFactor": 0.0}}));
    // The lamp faces down at z = 1.
    a.triangles(
        &[[0.3, 0.3, 1.0], [0.3, 0.7, 1.0], [0.7, 0.7, 1.0], [0.7, 0.3, 1.0]],
        Some(&[0, 1, 2, 0, 2, 3]),
        lamp,
        json!({}),
    );
    a.push("images", json!({"uri": png_uri([left, right, left, right])}));
    a.push("samplers", json!({"wrapS": 33071, "wrapT": 33071}));
    a.push("textures", json!({"source": 0, "sampler": 0}));
    let floor = a.material(json!({"name": "floor",
        "pbrMetallicRoughness": {"baseColorFactor": [factor, factor, factor, 1.0],
                                 "baseColorTexture": {"index": 0}, "metallicFactor": 0}}));
    let position = a.positions(&[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]);
    let uv = a.texcoords(&[[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]]);
    let indices = a.indices(&[0, 1, 2, 0, 2, 3]);
    a.mesh_node(
        vec![
            json!({"attributes": {"POSITION": position, "TEXCOORD_0": uv}, "indices": indices,
                    "material": floor}),
        ],
        json!({}),
    );
    a
}

/// A base colour texture with texture coordinates is kept and read per texel of the field:
/// the floor's texels reflect the factor times the image's colour under them.
#[test]
fn a_base_colour_texture_is_sampled_per_texel() {
    let (scene, warnings) = load(&textured_floor([255; 3], [0; 3], 0.8).glb()).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(scene.textures.len(), 1);
    assert_eq!(material(&scene, "floor").albedo_texture, Some(0));
    let atlas = crate::maps::TexelAtlas::new(&scene, 2.0 / 64.0, 2.0 / 64.0).unwrap();
    let albedo = crate::maps::albedo::texel_albedo(&scene, &atlas);
    let floor = (0..scene.surfaces.len())
        .find(|&s| scene.material(s).name == "floor")
        .unwrap();
    assert!(scene.surfaces[floor].uv.is_some());
    // Points on the floor (scene x in [0, 1]): the left quarter reads white, the right quarter
    // black, bilinear in between.
    let to_vlf = |x: f64, y: f64| scene.normalisation.to_vlf(DVec3::new(x, y, 0.0));
    let texel = |x: f64, y: f64| {
        let g = atlas.grid(floor);
        g.index(g.coords(to_vlf(x, y)))
    };
    let k = f64::from(0.8f32);
    for y in [0.2, 0.5, 0.8] {
        assert_rgb(albedo[texel(0.1, y)], [k; 3], 1e-9);
        assert_rgb(albedo[texel(0.9, y)], [0.0; 3], 1e-9);
        assert_rgb(scene.albedo_at(floor, to_vlf(0.1, y)), [k; 3], 1e-12);
        assert_rgb(scene.albedo_at(floor, to_vlf(0.5, y)), [k / 2.0; 3], 1e-12);
    }
    // The floor's mean albedo is the image's mean times the factor.
    let g = atlas.grid(floor);
    let inside: Vec<f64> = albedo[g.first..g.first + g.len()].iter().map(|c| c[0]).collect();
    let mean = inside.iter().sum::<f64>() / inside.len() as f64;
    assert!((mean - 0.4).abs() < 0.05, "{mean}");
}

/// Light transport reads the texture: a floor textured in one uniform colour gives the field
/// of the same floor with that colour as its factor, and the black half of a black-and-white
/// floor reflects nothing.
#[test]
fn propagation_reflects_what_the_texture_says() {
    use crate::propagate::{Options, Propagation, Stop};
    let options = Options {
        directions: 129,
        grid: crate::psf::GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(3),
        ..Options::default()
    };
    let field = |asset: Asset| {
        let (scene, _) = load(&asset.glb()).unwrap();
        let mut p = Propagation::new(scene, options.clone()).unwrap();
        p.run(|_| {});
        p
    };
    // sRGB 188 is linear 0.5029.
    let grey = field(textured_floor([188; 3], [188; 3], 1.0));
    let plain = {
        let mut a = textured_floor([188; 3], [188; 3], 1.0);
        let linear = super::super::material::srgb_to_linear(188.0 / 255.0) as f32;
        a.root["materials"][1]["pbrMetallicRoughness"] =
            json!({"baseColorFactor": [linear, linear, linear, 1.0], "metallicFactor": 0});
        field(a)
    };
    assert_eq!(grey.total.len(), plain.total.len());
    for (a, b) in grey.total.iter().zip(&plain.total) {
        for c in 0..3 {
            assert!((a[c] - b[c]).abs() <= 1e-6 * b[c].abs().max(1e-3), "{a:?} vs {b:?}");
        }
    }
    let split = field(textured_floor([255; 3], [0; 3], 1.0));
    let scene = &split.scene;
    let floor = (0..scene.surfaces.len())
        .find(|&s| scene.material(s).name == "floor")
        .unwrap();
    let g = split.atlas.grid(floor);
    let at = |x: f64| {
        let t = g.index(g.coords(scene.normalisation.to_vlf(DVec3::new(x, 0.5, 0.0))));
        split.total[t][0]
    };
    assert!(at(0.1) > 0.0);
    assert_eq!(at(0.9), 0.0, "a black texel reflects nothing");
}

#[test]
fn strips_fans_and_other_modes() {
    let mut a = with_light();
    let m = a.material(diffuse("white"));
    let quad = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0]];
    // A strip 0 1 2 3 and a fan 0 1 3 2 are the same unit quad, facing +z.
    let strip = a.positions(&quad);
    let fan_indices = a.indices(&[0, 1, 3, 2]);
    let lines = a.positions(&quad);
    let triangle = a.positions(&[[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]]);
    a.mesh_node(
        vec![
            json!({"attributes": {"POSITION": strip}, "material": m, "mode": 5}),
            json!({"attributes": {"POSITION": strip}, "indices": fan_indices, "material": m, "mode": 6}),
            json!({"attributes": {"POSITION": lines}, "material": m, "mode": 1}),
            json!({"attributes": {"POSITION": triangle}, "mode": 4}),
        ],
        json!({"name": "modes"}),
    );
    let (scene, warnings) = load(&a.gltf()).unwrap();
    let s = scene.normalisation.scale;
    assert_eq!(scene.surfaces.len(), 1 + 2 + 2 + 1);
    for (k, surface) in scene.surfaces.iter().enumerate().skip(1).take(4) {
        assert!((surface.normal - DVec3::Z).length() < 1e-9, "{k}");
        assert!((surface.area / (s * s) - 0.5).abs() < 1e-9, "{k}");
    }
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(
        warnings[0].contains("mesh #1 primitive 2: mode Lines ignored"),
        "{}",
        warnings[0]
    );
    assert!(
        warnings[1].contains("mesh #1 primitive 3 has no material"),
        "{}",
        warnings[1]
    );
    assert_eq!(material(&scene, "glTF default material").diffuse, [1.0; 3]);
}

#[test]
fn degenerate_triangles_are_named_by_mesh_and_primitive() {
    let mut a = with_light();
    let m = a.material(json!({"name": "white", "doubleSided": true, "pbrMetallicRoughness": {"metallicFactor": 0}}));
    let points = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0], [0.0, 1.0, 1.0]];
    a.triangles(&points, Some(&[0, 1, 3, 0, 1, 2]), m, json!({}));
    a.root["meshes"][1]["name"] = json!("floor");
    let (scene, warnings) = load(&a.gltf()).unwrap();
    assert_eq!(scene.surfaces.len(), 3);
    // Once, though both sides are skipped.
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert_eq!(
        warnings[0],
        "scene.gltf: mesh 'floor' (#1) primitive 0, triangle 1 (face #2) is degenerate (zero area) and was skipped"
    );
}

#[test]
fn without_a_scene_every_root_node_is_imported() {
    let mut a = with_light();
    let m = a.material(diffuse("white"));
    let child = a.triangles(&LIGHT, None, m, json!({"translation": [0, 0, 1]}));
    a.root["nodes"][0]["children"] = json!([child]);
    let mut root = a.root.clone();
    root.as_object_mut().unwrap().remove("scene");
    root.as_object_mut().unwrap().remove("scenes");
    let b = Asset {
        root,
        bin: a.bin.clone(),
    };
    let (scene, warnings) = load(&b.gltf()).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(scene.surfaces.len(), 2);
}
