//! Scenes sent by clients: an OBJ and the MTL libraries it names, or a glTF 2.0 asset (`.glb`,
//! or `.gltf` with the buffers and images it names, sent in the same map as MTL files), imported
//! with the same importer as a local file (so a bad scene gets the same message, with file and
//! line). The upload's file name decides the format: `.gltf` and `.glb` are glTF, anything else
//! is read as OBJ, as before glTF was accepted.
//!
//! The files are written into a private temporary directory under the names the client gave,
//! which must be plain file names: an upload cannot reach outside that directory.

use std::path::Path;
use vlf_core::scene::{ImportOptions, Scene, load_gltf, load_obj};
use vlf_proto::v1::SceneUpload;

/// Why an upload is refused.
#[derive(Debug, thiserror::Error)]
pub enum UploadError {
    /// Larger than the server accepts.
    #[error(
        "the upload is {size} bytes; this server accepts scenes of at most {limit} bytes (vlf serve --max-upload-bytes)"
    )]
    TooLarge { size: u64, limit: u64 },
    /// A name that is not a plain file name.
    #[error("`{0}` is not a plain file name (no directories, `..` or control characters)")]
    BadName(String),
    /// The importer's message.
    #[error("{0}")]
    Scene(String),
    #[error("cannot stage the upload: {0}")]
    Io(#[from] std::io::Error),
}

/// Total size of an upload's files.
pub fn upload_size(upload: &SceneUpload) -> u64 {
    upload.obj.len() as u64 + upload.mtl.values().map(|m| m.len() as u64).sum::<u64>()
}

/// Imports `upload` (at most `limit` bytes in all). Returns the scene and the importer's warnings.
pub fn import(upload: &SceneUpload, limit: u64) -> Result<(Scene, Vec<String>), UploadError> {
    let size = upload_size(upload);
    if size > limit {
        return Err(UploadError::TooLarge { size, limit });
    }
    let obj_name = if upload.obj_name.is_empty() {
        "scene.obj"
    } else {
        upload.obj_name.as_str()
    };
    check_name(obj_name)?;
    let dir = tempfile::tempdir()?;
    for (name, bytes) in &upload.mtl {
        check_name(name)?;
        std::fs::write(dir.path().join(name), bytes)?;
    }
    let obj = dir.path().join(obj_name);
    std::fs::write(&obj, &upload.obj)?;
    // The glTF importer reads files only inside the asset's folder (no `..`, no absolute paths).
    let gltf = Path::new(obj_name)
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("gltf") || e.eq_ignore_ascii_case("glb"));
    let load = if gltf { load_gltf } else { load_obj };
    let options = ImportOptions {
        confined: true,
        ..Default::default()
    };
    load(&obj, &options).map_err(|e| UploadError::Scene(strip_dir(&e.to_string(), dir.path())))
}

/// The importer names files by their path; the client knows them by name.
fn strip_dir(message: &str, dir: &Path) -> String {
    let prefix = format!("{}{}", dir.display(), std::path::MAIN_SEPARATOR);
    message.replace(&prefix, "").replace(&dir.display().to_string(), ".")
}

fn check_name(name: &str) -> Result<(), UploadError> {
    let plain = !name.is_empty()
        && name.len() <= 255
        && name != "."
        && name != ".."
        && !name.contains(['/', '\\'])
        && !name.chars().any(char::is_control);
    if plain {
        Ok(())
    } else {
        Err(UploadError::BadName(name.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn upload(obj: &str, mtl: &[(&str, &str)]) -> SceneUpload {
        upload_as("room.obj", obj, mtl)
    }

    fn upload_as(name: &str, obj: &str, mtl: &[(&str, &str)]) -> SceneUpload {
        SceneUpload {
            obj_name: name.into(),
            obj: obj.as_bytes().to_vec(),
            mtl: mtl
                .iter()
                .map(|(n, t)| (n.to_string(), t.as_bytes().to_vec()))
                .collect(),
        }
    }

    const QUAD: &str = "mtllib m.mtl\nusemtl lamp\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n";
    const MTL: &str = "newmtl lamp\nKd 0.5 0.5 0.5\nKe 1 1 1\n";

    #[test]
    fn an_upload_imports_like_a_file() {
        let (scene, _) = import(&upload(QUAD, &[("m.mtl", MTL)]), 1 << 20).unwrap();
        assert_eq!(scene.surfaces.len(), 1);
    }

    /// A glTF emitter triangle whose buffer (36 bytes) is `uri`.
    fn gltf(uri: &str) -> String {
        let view = r#""bufferViews": [{"buffer": 0, "byteLength": 36}]"#;
        let accessor = r#""accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}]"#;
        let material = r#""materials": [{"emissiveFactor": [1, 1, 1], "pbrMetallicRoughness": {"metallicFactor": 0}}]"#;
        let mesh = r#""meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "material": 0}]}]"#;
        format!(
            r#"{{"asset": {{"version": "2.0"}}, "buffers": [{{"byteLength": 36, "uri": "{uri}"}}], {view}, {accessor},
                {material}, {mesh}, "nodes": [{{"mesh": 0}}], "scenes": [{{"nodes": [0]}}]}}"#
        )
    }

    /// The triangle's positions, (0,0,0) (1,0,0) (0,1,0) as f32.
    const TRIANGLE: &str = "AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAA";

    #[test]
    fn a_gltf_upload_imports_with_its_buffers() {
        let embedded = gltf(&format!("data:application/octet-stream;base64,{TRIANGLE}"));
        let (scene, _) = import(&upload_as("lamp.gltf", &embedded, &[]), 1 << 20).unwrap();
        assert_eq!(scene.surfaces.len(), 1);
        // An external buffer travels in the map, by name.
        let bin: Vec<u8> = [0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
            .iter()
            .flat_map(|c| c.to_le_bytes())
            .collect();
        let mut up = upload_as("lamp.gltf", &gltf("tri.bin"), &[]);
        up.mtl.insert("tri.bin".into(), bin);
        let (scene, _) = import(&up, 1 << 20).unwrap();
        assert_eq!(scene.surfaces.len(), 1);
        // Missing, or outside the upload's folder: the importer's message, without the folder.
        let e = import(&upload_as("lamp.gltf", &gltf("tri.bin"), &[]), 1 << 20)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("lamp.gltf: ") && e.contains("buffer 0: cannot read 'tri.bin'") && !e.contains("/tmp"),
            "{e}"
        );
        let e = import(&upload_as("lamp.GLTF", &gltf("../tri.bin"), &[]), 1 << 20)
            .unwrap_err()
            .to_string();
        assert!(e.contains("inside the asset's folder"), "{e}");
    }

    #[test]
    fn bad_uploads_are_refused_with_the_reason() {
        let e = import(&upload(QUAD, &[("m.mtl", MTL)]), 10).unwrap_err();
        assert!(e.to_string().contains("at most 10 bytes"), "{e}");
        let e = import(&upload(QUAD, &[("../m.mtl", MTL)]), 1 << 20).unwrap_err();
        assert!(matches!(e, UploadError::BadName(_)), "{e}");
        let e = import(&upload("v 0 0 nan\n", &[]), 1 << 20).unwrap_err().to_string();
        assert!(e.starts_with("room.obj:1"), "{e}");
        let e = import(&upload(QUAD, &[]), 1 << 20).unwrap_err().to_string();
        assert!(e.contains("m.mtl") && !e.contains("/tmp"), "{e}");
        // An OBJ may not make the server read a file outside the upload, even one that exists.
        for outside in ["../m.mtl", "/etc/hostname", "sub/m.mtl"] {
            let obj = QUAD.replace("mtllib m.mtl", &format!("mtllib {outside}"));
            let e = import(&upload(&obj, &[("m.mtl", MTL)]), 1 << 20)
                .unwrap_err()
                .to_string();
            assert!(e.contains("not a plain file name beside the scene"), "{outside}: {e}");
        }
    }
}
