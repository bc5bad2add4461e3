//! glTF import tests: assets are assembled here, byte by byte (JSON, binary
//! buffers, `data:` URIs, `.glb` containers, a PNG texture), so every
//! expectation is known independently of the importer. This file holds
//! the asset builder and helpers; `import.rs` what imports, `errors.rs`
//! what is refused.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use base64::Engine;
use glam::DVec3;
use serde_json::{Value, json};

use super::*;
use crate::scene::{Surface, load_obj, load_scene};

mod errors;
mod import;

/// A glTF asset being assembled: the JSON root and one binary buffer.
struct Asset {
    root: Value,
    bin: Vec<u8>,
}

impl Asset {
    fn new() -> Self {
        Asset {
            root: json!({
                "asset": {"version": "2.0"},
                "buffers": [], "bufferViews": [], "accessors": [],
                "meshes": [], "nodes": [], "materials": [], "images": [], "textures": [], "samplers": [],
                "scenes": [{"nodes": []}], "scene": 0,
            }),
            bin: Vec::new(),
        }
    }

    fn push(&mut self, array: &str, item: Value) -> usize {
        let list = self.root[array].as_array_mut().unwrap();
        list.push(item);
        list.len() - 1
    }

    /// Appends `bytes` to the buffer (4-aligned) as a new buffer view.
    fn view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.push(
            "bufferViews",
            json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}),
        )
    }

    fn positions(&mut self, points: &[[f32; 3]]) -> usize {
        let bytes: Vec<u8> = points.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        let view = self.view(&bytes);
        let min: Vec<f32> = (0..3)
            .map(|c| points.iter().map(|p| p[c]).fold(f32::INFINITY, f32::min))
            .collect();
        let max: Vec<f32> = (0..3)
            .map(|c| points.iter().map(|p| p[c]).fold(f32::NEG_INFINITY, f32::max))
            .collect();
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": 5126, "count": points.len(), "type": "VEC3",
                   "min": min, "max": max}),
        )
    }

    fn texcoords(&mut self, uv: &[[f32; 2]]) -> usize {
        let bytes: Vec<u8> = uv.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        let view = self.view(&bytes);
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": 5126, "count": uv.len(), "type": "VEC2"}),
        )
    }

    fn indices(&mut self, indices: &[u16]) -> usize {
        let bytes: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
        let view = self.view(&bytes);
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": 5123, "count": indices.len(), "type": "SCALAR"}),
        )
    }

    fn material(&mut self, material: Value) -> usize {
        self.push("materials", material)
    }

    /// A mesh of one primitive per `(positions, indices, material)`, and a
    /// root node with it.
    fn mesh_node(&mut self, primitives: Vec<Value>, node: Value) -> usize {
        let mesh = self.push("meshes", json!({"primitives": primitives}));
        let mut node = node;
        node["mesh"] = json!(mesh);
        let n = self.push("nodes", node);
        self.root["scenes"][0]["nodes"].as_array_mut().unwrap().push(json!(n));
        n
    }

    /// A triangle-list mesh on a root node (indexed if `indices` is given).
    fn triangles(&mut self, points: &[[f32; 3]], indices: Option<&[u16]>, material: usize, node: Value) -> usize {
        let position = self.positions(points);
        let mut primitive = json!({"attributes": {"POSITION": position}, "material": material});
        if let Some(indices) = indices {
            primitive["indices"] = json!(self.indices(indices));
        }
        self.mesh_node(vec![primitive], node)
    }

    /// The JSON with the buffer as a base64 `data:` URI.
    fn gltf(&self) -> Vec<u8> {
        let mut root = self.root.clone();
        let data = base64::engine::general_purpose::STANDARD.encode(&self.bin);
        root["buffers"] = json!([{"byteLength": self.bin.len(),
                                  "uri": format!("data:application/octet-stream;base64,{data}")}]);
        serde_json::to_vec_pretty(&root).unwrap()
    }

    /// The JSON with the buffer in the file `bin`, and that file's bytes.
    fn gltf_external(&self, bin: &str) -> (Vec<u8>, Vec<u8>) {
        let mut root = self.root.clone();
        root["buffers"] = json!([{"byteLength": self.bin.len(), "uri": bin}]);
        (serde_json::to_vec(&root).unwrap(), self.bin.clone())
    }

    /// A binary `.glb`: header, JSON chunk (space-padded), BIN chunk
    /// (zero-padded).
    fn glb(&self) -> Vec<u8> {
        let mut root = self.root.clone();
        root["buffers"] = json!([{"byteLength": self.bin.len()}]);
        let mut json = serde_json::to_vec(&root).unwrap();
        while !json.len().is_multiple_of(4) {
            json.push(b' ');
        }
        let mut bin = self.bin.clone();
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let total = 12 + 8 + json.len() + 8 + bin.len();
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(b"glTF");
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&(total as u32).to_le_bytes());
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(b"JSON");
        out.extend_from_slice(&json);
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
        out
    }
}

/// A fresh folder under the temp dir, removed on drop.
struct Folder(PathBuf);

impl Folder {
    fn new() -> Self {
        static COUNTER: AtomicUsize = AtomicUsize::new(0);
        let dir = std::env::temp_dir().join(format!(
            "vlf-core-gltf-test-{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).unwrap();
        Folder(dir)
    }

    fn write(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let path = self.0.join(name);
        std::fs::write(&path, bytes).unwrap();
        path
    }
}

impl Drop for Folder {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Imports bytes as `scene.gltf` in an empty folder.
fn load(bytes: &[u8]) -> Result<(Scene, Vec<String>), Error> {
    import(
        bytes,
        "scene.gltf",
        Path::new("/nonexistent"),
        &ImportOptions::default(),
    )
}

fn error(bytes: &[u8]) -> String {
    match load(bytes) {
        Err(e @ Error::Scene { .. }) => e.to_string(),
        Err(e) => panic!("expected a scene error, got {e}"),
        Ok(_) => panic!("expected an error, the asset loaded"),
    }
}

const LIGHT: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

/// An asset with an emitting triangle (material 0, `LIGHT`, facing +z).
fn with_light() -> Asset {
    let mut a = Asset::new();
    let m = a.material(json!({"name": "lamp", "emissiveFactor": [1.0, 1.0, 1.0],
                              "pbrMetallicRoughness": {"metallicFactor": 0.0}}));
    a.triangles(&LIGHT, None, m, json!({"name": "lamp"}));
    a
}

/// A white diffuser (glTF's default metallic factor is 1: a rough metal).
fn diffuse(name: &str) -> Value {
    json!({"name": name, "pbrMetallicRoughness": {"metallicFactor": 0.0}})
}

fn material<'a>(scene: &'a Scene, name: &str) -> &'a Material {
    scene
        .materials
        .iter()
        .find(|m| m.name == name)
        .unwrap_or_else(|| panic!("no material {name}"))
}

fn assert_rgb(a: [f64; 3], b: [f64; 3], tolerance: f64) {
    for c in 0..3 {
        assert!((a[c] - b[c]).abs() <= tolerance, "{a:?} vs {b:?}");
    }
}
