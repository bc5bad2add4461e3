//! What a glTF asset is refused for: every error names what is wrong,
//! none panics.

use super::*;

#[test]
fn missing_buffers_and_files_are_errors() {
    let a = with_light();
    let (json, _) = a.gltf_external("missing.bin");
    let folder = Folder::new();
    let path = folder.write("scene.gltf", &json);
    let e = load_gltf(&path, &ImportOptions::default()).unwrap_err().to_string();
    assert!(e.contains("buffer 0") && e.contains("cannot read 'missing.bin'"), "{e}");
    // Outside the asset's folder, or with a scheme: refused before reading.
    for uri in [
        "../secret.bin",
        "/etc/passwd",
        "http://example.com/a.bin",
        "file:///etc/passwd",
        "bad%zz.bin",
        "%+1.bin",
    ] {
        let (json, _) = a.gltf_external(uri);
        let e = error(&json);
        assert!(e.contains("only data: URIs and relative paths"), "{uri}: {e}");
    }
    // A .glb whose buffer has no uri but no BIN chunk either.
    let mut root = a.root.clone();
    root["buffers"] = json!([{"byteLength": 36}]);
    let e = error(&serde_json::to_vec(&root).unwrap());
    assert!(e.contains("buffer 0: has no uri"), "{e}");
    // A buffer shorter than its byteLength.
    let mut root: Value = serde_json::from_slice(&a.gltf()).unwrap();
    root["buffers"][0]["byteLength"] = json!(40);
    let e = error(&serde_json::to_vec(&root).unwrap());
    assert!(e.contains("byteLength is 40 but its data has only 36 bytes"), "{e}");
    // A buffer view past the end of its buffer, an accessor past its view.
    let mut root: Value = serde_json::from_slice(&a.gltf()).unwrap();
    root["bufferViews"][0]["byteOffset"] = json!(8);
    let e = error(&serde_json::to_vec(&root).unwrap());
    assert!(e.contains("bufferView 0") && e.contains("lies outside buffer 0"), "{e}");
    let mut root: Value = serde_json::from_slice(&a.gltf()).unwrap();
    root["accessors"][0]["count"] = json!(4);
    let e = error(&serde_json::to_vec(&root).unwrap());
    assert!(
        e.contains("POSITION of mesh #0 primitive 0: accessor 0") && e.contains("do not fit"),
        "{e}"
    );
    let mut root: Value = serde_json::from_slice(&a.gltf()).unwrap();
    root["accessors"][0]["count"] = json!(0);
    let e = error(&serde_json::to_vec(&root).unwrap());
    assert!(e.contains("no faces"), "{e}");
    let missing = error(&{
        let mut root: Value = serde_json::from_slice(&a.gltf()).unwrap();
        root["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = json!(7);
        serde_json::to_vec(&root).unwrap()
    });
    assert!(missing.contains("accessor 7: does not exist"), "{missing}");
}

#[test]
fn bad_indices_positions_and_accessor_types_are_errors() {
    let mut a = with_light();
    let m = a.material(diffuse("white"));
    a.triangles(&LIGHT, Some(&[0, 1, 5]), m, json!({}));
    let e = error(&a.gltf());
    assert!(
        e.contains("mesh #1 primitive 0: index 5 (element 2 of the indices) is out of range"),
        "{e}"
    );

    let mut a = with_light();
    a.triangles(
        &[[0.0, 0.0, 1.0], [f32::NAN, 0.0, 1.0], [0.0, 1.0, 1.0]],
        None,
        0,
        json!({}),
    );
    let e = error(&a.gltf());
    assert!(e.contains("mesh #1 primitive 0: POSITION 1 is not finite"), "{e}");

    let mut root: Value = serde_json::from_slice(&with_light().gltf()).unwrap();
    root["accessors"][0]["type"] = json!("VEC2");
    let e = error(&serde_json::to_vec(&root).unwrap());
    assert!(e.contains("accessor 0: is VEC2 of FLOAT, expected VEC3"), "{e}");

    let mut a = with_light();
    let m = a.material(diffuse("white"));
    a.triangles(&LIGHT, Some(&[0, 1, 2]), m, json!({}));
    a.root["accessors"][2]["componentType"] = json!(5126);
    let e = error(&a.gltf());
    assert!(
        e.contains("indices of mesh #1 primitive 0: accessor 2: is SCALAR of FLOAT"),
        "{e}"
    );
    let mut a = with_light();
    let m = a.material(diffuse("white"));
    a.triangles(&LIGHT, Some(&[0, 1, 2, 0]), m, json!({}));
    let e = error(&a.gltf());
    assert!(e.contains("4 vertices, not a multiple of 3"), "{e}");

    // A transform beyond f32 (read as infinite); a large one is fine, in f64.
    let mut a = with_light();
    a.triangles(&LIGHT, None, 0, json!({"name": "far", "scale": [1e39, 1.0, 1.0]}));
    let e = error(&a.gltf());
    // serde_json refuses the number itself where the workspace enables its exact float parsing.
    assert!(
        e.contains("node 'far' (#1): its transform is not finite") || e.contains("number out of range"),
        "{e}"
    );
    let mut a = with_light();
    a.triangles(&LIGHT, None, 0, json!({"scale": [3e38, 3e38, 3e38]}));
    assert!(load(&a.gltf()).is_ok());
}

#[test]
fn malformed_files_are_errors() {
    let e = error(b"{ \"asset\": {\"version\": \"2.0\"}, ");
    assert!(e.contains("not valid JSON") && e.contains("line 1"), "{e}");
    let e = error(b"{\"meshes\": []}");
    assert!(
        e.contains("not a valid glTF 2.0 document") && e.contains("asset"),
        "{e}"
    );
    let e = import(
        b"PK\x03\x04",
        "scene.glb",
        Path::new("/nonexistent"),
        &ImportOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.starts_with("scene.glb: not a binary glTF"), "{e}");
    // A byte order mark is tolerated.
    let mut bom = b"\xEF\xBB\xBF".to_vec();
    bom.extend(with_light().gltf());
    assert!(load(&bom).is_ok());
    let e = error(b"{\"asset\": {\"version\": \"1.0\"}}");
    assert!(e.contains("glTF version 1.0 is not supported"), "{e}");

    for ext in [
        "KHR_draco_mesh_compression",
        "EXT_meshopt_compression",
        "KHR_materials_volume",
    ] {
        let mut a = with_light();
        a.root["extensionsUsed"] = json!([ext]);
        a.root["extensionsRequired"] = json!([ext]);
        let e = error(&a.gltf());
        assert!(
            e.contains(&format!("requires extension {ext}, which is not supported")),
            "{e}"
        );
    }

    // Every truncation of a valid .glb is an error, never a panic.
    let glb = with_light().glb();
    assert!(load(&glb).is_ok());
    for n in 0..glb.len() {
        let e = load(&glb[..n]);
        assert!(e.is_err(), "{n} bytes loaded");
    }
    let e = error(&glb[..glb.len() - 1]);
    assert!(e.contains("malformed binary glTF (.glb): truncated"), "{e}");
    let e = error(&glb[..6]);
    assert!(e.contains("shorter than the 12-byte header"), "{e}");
    // Every corrupted byte is an error or a scene, never a panic.
    for n in 0..glb.len() {
        let mut bad = glb.clone();
        bad[n] ^= 0xff;
        let _ = load(&bad);
    }

    // A node hierarchy with a cycle.
    let mut a = with_light();
    a.root["nodes"][0]["children"] = json!([0]);
    let e = error(&a.gltf());
    assert!(e.contains("node 0 is reached twice"), "{e}");
}

/// Texture coordinates that do not fit their positions are errors naming the primitive.
#[test]
fn bad_texture_coordinates_are_errors() {
    use super::import::textured_floor;
    // One coordinate short.
    let mut a = textured_floor([255; 3], [0; 3], 1.0);
    a.root["accessors"][3]["count"] = json!(3);
    let e = error(&a.gltf());
    assert!(
        e.contains("TEXCOORD_0 of mesh #1 primitive 0") && e.contains("3 coordinates for 4 vertices"),
        "{e}"
    );
    // A VEC3 where VEC2 is expected.
    let mut a = textured_floor([255; 3], [0; 3], 1.0);
    a.root["accessors"][3]["type"] = json!("VEC3");
    a.root["accessors"][3]["count"] = json!(2);
    let e = error(&a.gltf());
    assert!(e.contains("expected VEC2 of FLOAT"), "{e}");
    // A non-finite coordinate.
    let mut a = textured_floor([255; 3], [0; 3], 1.0);
    let view = a.root["accessors"][3]["bufferView"].as_u64().unwrap() as usize;
    let offset = a.root["bufferViews"][view]["byteOffset"].as_u64().unwrap() as usize;
    a.bin[offset..offset + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let e = error(&a.gltf());
    assert!(e.contains("coordinate 0 is not finite"), "{e}");
    // A texture that does not exist.
    let mut a = textured_floor([255; 3], [0; 3], 1.0);
    a.root["materials"][1]["pbrMetallicRoughness"]["baseColorTexture"]["index"] = json!(7);
    let e = error(&a.gltf());
    assert!(e.contains("baseColorTexture: texture 7 does not exist"), "{e}");
}

/// Faces past the scene's limit are refused as they are read, before they are held: here a file
/// of a kilobyte whose accessor of 2²⁴ − 1 implicit zeros (no bufferView) is 5.6 million triangles,
/// double-sided, 11 million faces.
#[test]
fn a_small_file_that_makes_too_many_faces_is_refused() {
    let mut a = with_light();
    let m = a.material(json!({"name": "white", "doubleSided": true, "pbrMetallicRoughness": {"metallicFactor": 0}}));
    let zeros = a.push(
        "accessors",
        json!({"componentType": 5126, "count": (1 << 24) - 1, "type": "VEC3"}),
    );
    a.mesh_node(
        vec![json!({"attributes": {"POSITION": zeros}, "material": m})],
        json!({}),
    );
    let e = error(&a.gltf());
    assert!(
        e.contains("mesh #1 primitive 0") && e.contains(&format!("a scene has at most {}", crate::scene::MAX_FACES)),
        "{e}"
    );
}

/// The CRC-32 of PNG chunks (ISO 3309), bit by bit.
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

/// An image that would decode to more than the importer allows (a PNG of a few dozen bytes can
/// claim 100 000 × 100 000 pixels, 10 GB) is refused with its size before its pixels are
/// allocated, as base colour and as emission.
#[test]
fn an_image_too_large_to_decode_is_refused() {
    let chunk = |kind: &[u8], data: &[u8]| {
        let mut c = (data.len() as u32).to_be_bytes().to_vec();
        let body = [kind, data].concat();
        c.extend_from_slice(&body);
        c.extend_from_slice(&crc32(&body).to_be_bytes());
        c
    };
    let side = 100_000u32.to_be_bytes();
    // 8-bit grey, no interlace; an empty zlib stream for pixels.
    let png = [
        &b"\x89PNG\r\n\x1a\n"[..],
        &chunk(b"IHDR", &[&side[..], &side[..], &[8, 0, 0, 0, 0]].concat()),
        &chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]),
        &chunk(b"IEND", &[]),
    ]
    .concat();
    let data = base64::engine::general_purpose::STANDARD.encode(png);
    for slot in ["baseColorTexture", "emissiveTexture"] {
        let mut a = with_light();
        a.push("images", json!({"uri": format!("data:image/png;base64,{data}")}));
        a.push("textures", json!({"source": 0}));
        let m = match slot {
            "baseColorTexture" => a.material(json!({"name": "painted",
                "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0}})),
            _ => a.material(
                json!({"name": "painted", "emissiveFactor": [1, 1, 1], "emissiveTexture": {"index": 0},
                "pbrMetallicRoughness": {"metallicFactor": 0}}),
            ),
        };
        a.triangles(&LIGHT, None, m, json!({"translation": [0, 0, 1]}));
        let e = error(&a.gltf());
        assert!(e.contains("image 0 decodes to more than 512 MiB"), "{slot}: {e}");
    }
}

/// Nodes that instance a mesh multiply its primitives: past [`MAX_PRIMITIVES`] in all (here a
/// mesh of 1 025 point primitives, which make no face, on 1 024 nodes) the file is refused, and
/// the warnings each instance gives are listed up to [`MAX_LISTED_WARNINGS`] and counted past.
#[test]
fn instanced_primitives_are_bounded_and_their_warnings_counted() {
    use crate::scene::MAX_LISTED_WARNINGS;
    let points = |a: &mut Asset, n: usize| {
        let position = a.positions(&LIGHT);
        let primitive = json!({"attributes": {"POSITION": position}, "mode": 0});
        let mesh = a.push("meshes", json!({"primitives": vec![primitive; n]}));
        (mesh, position)
    };
    // Within the bound: 3 nodes × 50 primitives, 150 warnings, 100 listed.
    let mut a = with_light();
    let (mesh, _) = points(&mut a, 50);
    for _ in 0..3 {
        let n = a.push("nodes", json!({"mesh": mesh}));
        a.root["scenes"][0]["nodes"].as_array_mut().unwrap().push(json!(n));
    }
    let (_, warnings) = load(&a.gltf()).unwrap();
    assert_eq!(warnings.len(), MAX_LISTED_WARNINGS + 1, "{warnings:?}");
    let ignored = warnings.iter().filter(|w| w.contains("mode Points ignored")).count();
    let summary = (warnings.iter())
        .find(|w| w.ends_with("more warnings like those above (not listed)"))
        .expect("a count of the warnings not listed");
    let counted: usize = summary
        .split(": ")
        .nth(1)
        .unwrap()
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        ignored < 150 && ignored + counted == 150,
        "{ignored} listed, {counted} counted"
    );
    // Past it.
    let mut a = with_light();
    let (mesh, _) = points(&mut a, 1025);
    for _ in 0..1024 {
        let n = a.push("nodes", json!({"mesh": mesh}));
        a.root["scenes"][0]["nodes"].as_array_mut().unwrap().push(json!(n));
    }
    let e = error(&a.gltf());
    assert!(e.contains(&format!("more than {MAX_PRIMITIVES} primitives")), "{e}");
}

/// Nodes that instance a mesh read its accessors again: past [`MAX_ACCESSOR_VALUES`] read in all
/// (here one triangle indexing an accessor of 2²⁴ − 1 implicit zeros, on six nodes) the file is
/// refused.
#[test]
fn accessor_reads_are_bounded_in_all() {
    let mut a = with_light();
    let m = a.material(diffuse("white"));
    let zeros = a.push(
        "accessors",
        json!({"componentType": 5126, "count": (1 << 24) - 1, "type": "VEC3"}),
    );
    let indices = a.indices(&[0, 1, 2]);
    let mesh = a.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": zeros}, "indices": indices, "material": m}]}),
    );
    for _ in 0..6 {
        let n = a.push("nodes", json!({"mesh": mesh}));
        a.root["scenes"][0]["nodes"].as_array_mut().unwrap().push(json!(n));
    }
    let e = error(&a.gltf());
    assert!(
        e.contains(&format!("more than {} accessor values", data::MAX_ACCESSOR_VALUES)),
        "{e}"
    );
}

/// Primitives that share one vertex buffer (an exporter's per-material split), and the instances
/// of a mesh, decode it once while it stays among the recent reads: here 70 primitives index one
/// accessor of 4.2 million values, 2.9·10⁸ values were each read counted, past
/// [`MAX_ACCESSOR_VALUES`], and the file imports.
#[test]
fn primitives_that_share_an_accessor_decode_it_once() {
    let mut a = with_light();
    let m = a.material(diffuse("white"));
    let count = data::RECENT_VALUES / 4;
    assert!(70 * 3 * count as u64 > data::MAX_ACCESSOR_VALUES);
    let zeros = a.push(
        "accessors",
        json!({"componentType": 5126, "count": count, "type": "VEC3"}),
    );
    let indices = a.indices(&[0, 1, 2]);
    let primitive = json!({"attributes": {"POSITION": zeros}, "indices": indices, "material": m});
    a.mesh_node(vec![primitive; 70], json!({}));
    let (scene, warnings) = load(&a.gltf()).unwrap();
    // The light alone: every shared triangle is degenerate, and says so.
    assert_eq!(scene.surfaces.len(), 1);
    assert!(warnings.iter().any(|w| w.contains("is degenerate")), "{warnings:?}");
}
