//! The reference image: an independent path tracer's rendering of the same
//! scene and camera, or an image the user supplies.
//!
//! The reference renderer is Mitsuba 3 (`scalar_rgb`), driven by the Python
//! script `study/mitsuba/reference.py`, which is compiled into this crate and
//! written next to the cached images when used, so the `vlf` binary needs no
//! checkout. The scene goes to it as JSON ([`SceneExport`]): the *imported*
//! polygons (after validation and convex splitting), fanned into triangles,
//! back in scene units, so both renderers see the same geometry. Renders are
//! cached under `CACHE/<key>/` where the key hashes that JSON, the sample
//! counts and the script: a second study of the same scene and camera costs
//! nothing.

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};
use sha2::Digest;
use std::path::{Path, PathBuf};
use std::process::Command;
use vlf_core::render::{Camera, Image};
use vlf_core::scene::Scene;

/// The Python side, embedded so the binary is self-contained.
pub const SCRIPT: &str = include_str!("../mitsuba/reference.py");
/// The script's pinned requirements, for error messages and the README.
pub const REQUIREMENTS: &str = include_str!("../mitsuba/requirements.txt");

/// One material's triangles, in the JSON the script reads.
#[derive(Serialize)]
struct MeshExport {
    material: String,
    diffuse: [f64; 3],
    specular: [f64; 3],
    emission: [f64; 3],
    positions: Vec<[f64; 3]>,
    triangles: Vec<[u32; 3]>,
}

#[derive(Serialize)]
struct CameraExport {
    eye: [f64; 3],
    target: [f64; 3],
    up: [f64; 3],
    fovy: f64,
    width: u32,
    height: u32,
}

/// A scene and camera as the reference renderer receives them (format
/// `vlf-reference-scene/1`).
#[derive(Serialize)]
pub struct SceneExport {
    format: &'static str,
    camera: CameraExport,
    meshes: Vec<MeshExport>,
}

/// What the reference script cannot draw as this scene has it is refused before anything is
/// rendered: errors against another scene would be wrong, not noisy.
/// * An albedo texture: the export gives Mitsuba each material's factor alone.
/// * A material both diffuse and a mirror whose channels' largest reflectances add past 1
///   (`Kd 0.8 0.1 0.1`, `Ks 0.1 0.9 0.1`): the script blends one diffuse and one mirror BSDF
///   by a single weight, which cannot give each channel its own split.
pub fn check_exportable(scene: &Scene) -> Result<()> {
    let used = |m: usize| scene.surfaces.iter().any(|s| s.material == m);
    for (i, m) in scene.materials.iter().enumerate().filter(|&(i, _)| used(i)) {
        if m.albedo_texture.is_some() {
            bail!(
                "material '{}' has an albedo texture, which the Mitsuba reference does not draw: \
                 give --reference an image of the scene as it is",
                m.name
            );
        }
        let max = |c: [f64; 3]| c.into_iter().fold(0.0, f64::max);
        if m.is_diffuse() && m.is_mirror() && max(m.diffuse) + max(m.specular) > 1.0 + 1e-12 {
            bail!(
                "material '{}' (#{i}): its largest diffuse and mirror reflectances add to {} > 1 \
                 in different channels, which the reference's blend of one diffuse and one mirror \
                 cannot draw: give --reference an image",
                m.name,
                max(m.diffuse) + max(m.specular)
            );
        }
    }
    Ok(())
}

impl SceneExport {
    /// Every surface of `scene`, in scene units, grouped by material; each
    /// convex polygon fanned from its first vertex, keeping its
    /// counter-clockwise order so the front faces agree.
    pub fn new(scene: &Scene, camera: &Camera) -> SceneExport {
        let mut meshes: Vec<MeshExport> = scene
            .materials
            .iter()
            .map(|m| MeshExport {
                material: m.name.clone(),
                diffuse: m.diffuse,
                specular: m.specular,
                emission: m.emission,
                positions: Vec::new(),
                triangles: Vec::new(),
            })
            .collect();
        for s in &scene.surfaces {
            let mesh = &mut meshes[s.material];
            let base = mesh.positions.len() as u32;
            for v in &s.vertices {
                mesh.positions.push(scene.normalisation.to_scene(*v).to_array());
            }
            for i in 1..s.vertices.len() as u32 - 1 {
                mesh.triangles.push([base, base + i, base + i + 1]);
            }
        }
        meshes.retain(|m| !m.triangles.is_empty());
        SceneExport {
            format: "vlf-reference-scene/1",
            camera: CameraExport {
                eye: camera.eye.to_array(),
                target: camera.target.to_array(),
                up: camera.up.to_array(),
                fovy: camera.fovy_degrees,
                width: camera.width,
                height: camera.height,
            },
            meshes,
        }
    }

    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec(self).expect("plain data always serialises")
    }
}

/// How to get the reference renderer going.
#[derive(Clone, Debug)]
pub struct Mitsuba {
    /// Python interpreter with the requirements installed.
    pub python: PathBuf,
    /// Samples per pixel of the reference (even).
    pub spp: u32,
    /// Sample counts of the timed renders for the equal-quality comparison.
    pub ladder: Vec<u32>,
    /// Cache folder.
    pub cache: PathBuf,
}

/// A path tracer's render at a lower sample count, timed.
#[derive(Clone, Debug)]
pub struct LadderImage {
    pub spp: u32,
    pub seconds: f64,
    pub image: Image,
}

/// The reference image and what is known about it.
#[derive(Clone, Debug)]
pub struct Reference {
    pub image: Image,
    /// Where it comes from, for the report.
    pub source: String,
    pub spp: Option<u32>,
    /// Render time of the reference itself.
    pub seconds: Option<f64>,
    /// Its own noise as a relative RMSE over all pixels (estimated by the
    /// renderer from two independent halves).
    pub noise: Option<f64>,
    /// The two independent halves it averages, when known.
    pub halves: Option<(Image, Image)>,
    pub ladder: Vec<LadderImage>,
}

impl Reference {
    /// The reference's own noise as a relative RMSE over `pixels`: the
    /// halves `a`, `b` have `Var(a − b) = 2σ²_half` and the mean of them
    /// `σ = σ_half/√2`, so `σ = RMS(a − b)/2`.
    pub fn noise_over(&self, pixels: vlf_core::render::compare::Pixels) -> Option<f64> {
        let (a, b) = self.halves.as_ref()?;
        let e = vlf_core::render::compare::compare(a, b, 1, pixels).ok()?;
        Some(e.relative_rmse / 2.0)
    }
}

/// What the script prints.
#[derive(Deserialize, Serialize)]
struct Report {
    renderer: String,
    spp: u32,
    seconds: f64,
    noise: Option<f64>,
    ladder: Vec<LadderEntry>,
}

#[derive(Deserialize, Serialize)]
struct LadderEntry {
    spp: u32,
    seconds: f64,
    path: PathBuf,
}

impl Reference {
    /// A reference image given by the user (PFM), checked against the camera's size.
    pub fn from_file(path: &Path, camera: &Camera) -> Result<Reference> {
        let image = Image::load_pfm(path).with_context(|| format!("cannot read reference {}", path.display()))?;
        check_size(&image, camera, path)?;
        // Checked now, not at the first comparison after a propagation.
        if let Some((i, p)) =
            (image.pixels.iter().enumerate()).find(|(_, p)| !p.iter().all(|v| v.is_finite() && *v >= 0.0))
        {
            let (x, y) = (i as u32 % image.width, i as u32 / image.width);
            bail!(
                "reference {}: pixel ({x}, {y}) is {p:?}; a reference's pixels must be finite and not negative",
                path.display()
            );
        }
        Ok(Reference {
            image,
            source: path.display().to_string(),
            spp: None,
            seconds: None,
            noise: None,
            halves: None,
            ladder: Vec::new(),
        })
    }

    /// Renders (or finds in the cache) Mitsuba's reference for `scene` seen by `camera`.
    pub fn mitsuba(scene: &Scene, camera: &Camera, settings: &Mitsuba) -> Result<Reference> {
        if settings.spp < 2 || !settings.spp.is_multiple_of(2) {
            bail!(
                "the reference needs an even sample count of at least 2, got {}",
                settings.spp
            );
        }
        if let Some(bad) = settings.ladder.iter().find(|&&spp| spp == 0) {
            bail!("the timed path-tracer renders need at least 1 sample per pixel, got {bad}");
        }
        check_exportable(scene)?;
        let json = SceneExport::new(scene, camera).to_json();
        let mut hasher = sha2::Sha256::new();
        hasher.update(&json);
        hasher.update(SCRIPT.as_bytes());
        hasher.update(format!("spp={} ladder={:?}", settings.spp, settings.ladder).as_bytes());
        let key: String = hasher.finalize().iter().take(12).map(|b| format!("{b:02x}")).collect();
        let folder = settings.cache.join(&key);
        let (image_path, report_path) = (folder.join("reference.pfm"), folder.join("report.json"));
        if !(image_path.exists() && report_path.exists()) {
            render_with_mitsuba(&folder, &json, settings)?;
        } else {
            tracing::info!(folder = %folder.display(), "reference found in the cache");
        }
        let report: Report = serde_json::from_slice(
            &std::fs::read(&report_path).with_context(|| format!("cannot read {}", report_path.display()))?,
        )
        .with_context(|| format!("malformed {}", report_path.display()))?;
        let image = Image::load_pfm(&image_path)?;
        check_size(&image, camera, &image_path)?;
        let ladder = report
            .ladder
            .iter()
            .map(|entry| {
                let path = folder.join(&entry.path);
                let image = Image::load_pfm(&path)?;
                check_size(&image, camera, &path)?;
                Ok(LadderImage {
                    spp: entry.spp,
                    seconds: entry.seconds,
                    image,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let half = |k: u32| -> Option<Image> {
            let image = Image::load_pfm(folder.join(format!("half-{k}.pfm"))).ok()?;
            ((image.width, image.height) == (camera.width, camera.height)).then_some(image)
        };
        Ok(Reference {
            halves: half(1).zip(half(2)),
            image,
            source: format!("{}, {} spp ({})", report.renderer, report.spp, folder.display()),
            spp: Some(report.spp),
            seconds: Some(report.seconds),
            noise: report.noise,
            ladder,
        })
    }
}

fn check_size(image: &Image, camera: &Camera, path: &Path) -> Result<()> {
    if (image.width, image.height) != (camera.width, camera.height) {
        bail!(
            "reference {} is {}x{}, the study renders {}x{} (give --size to match)",
            path.display(),
            image.width,
            image.height,
            camera.width,
            camera.height
        );
    }
    Ok(())
}

/// Runs the script into `folder` (written through a temporary folder and
/// renamed, so an interrupted render leaves no half cache entry).
fn render_with_mitsuba(folder: &Path, json: &[u8], settings: &Mitsuba) -> Result<()> {
    let parent = folder.parent().context("cache folder has no parent")?;
    std::fs::create_dir_all(parent).with_context(|| format!("cannot create {}", parent.display()))?;
    let partial = parent.join(format!(
        ".partial-{}-{}",
        std::process::id(),
        folder.file_name().and_then(|n| n.to_str()).unwrap_or("x")
    ));
    let _ = std::fs::remove_dir_all(&partial);
    std::fs::create_dir_all(&partial).with_context(|| format!("cannot create {}", partial.display()))?;
    let script = partial.join("reference.py");
    std::fs::write(&script, SCRIPT)?;
    std::fs::write(partial.join("scene.json"), json)?;
    let ladder: Vec<String> = settings.ladder.iter().map(u32::to_string).collect();
    tracing::info!(spp = settings.spp, ladder = ?settings.ladder, "rendering the reference with Mitsuba 3");
    let output = Command::new(&settings.python)
        .arg(&script)
        .arg(partial.join("scene.json"))
        .arg("--out")
        .arg(partial.join("reference.pfm"))
        .arg("--spp")
        .arg(settings.spp.to_string())
        .arg("--ladder")
        .arg(ladder.join(","))
        .arg("--ladder-dir")
        .arg(&partial)
        .stderr(std::process::Stdio::inherit())
        .output()
        .with_context(|| {
            format!(
                "cannot run {} for the reference renderer: install Python 3 and `pip install -r study/mitsuba/requirements.txt` \
                 ({}), or give a reference image with --reference",
                settings.python.display(),
                REQUIREMENTS.lines().filter(|l| !l.starts_with('#')).collect::<Vec<_>>().join(" ")
            )
        })?;
    if !output.status.success() {
        bail!(
            "the reference renderer failed ({}); is mitsuba installed for {}? (`pip install -r study/mitsuba/requirements.txt`)",
            output.status,
            settings.python.display()
        );
    }
    let report: Report = serde_json::from_slice(&output.stdout).context("the reference renderer printed no report")?;
    std::fs::write(partial.join("report.json"), serde_json::to_vec_pretty(&report)?)?;
    // A stale entry (e.g. without its report) is replaced whole.
    let _ = std::fs::remove_dir_all(folder);
    std::fs::rename(&partial, folder).with_context(|| format!("cannot move the reference into {}", folder.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;
    use vlf_core::scene::{ImportOptions, load_obj};

    #[test]
    fn export_keeps_every_polygon_in_scene_units_with_its_winding() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
        let (scene, _) = load_obj(&path, &ImportOptions::default()).unwrap();
        let camera = Camera::new(
            DVec3::new(278.0, 273.0, -800.0),
            DVec3::new(278.0, 273.0, 0.0),
            DVec3::Y,
            39.0,
            8,
            6,
        )
        .unwrap();
        let export = SceneExport::new(&scene, &camera);
        let triangles: usize = export.meshes.iter().map(|m| m.triangles.len()).sum();
        let expected: usize = scene.surfaces.iter().map(|s| s.vertices.len() - 2).sum();
        assert_eq!(triangles, expected);
        // Total area and the area-weighted normal of each material survive.
        for (m, mesh) in export.meshes.iter().enumerate() {
            let material = scene.materials.iter().position(|x| x.name == mesh.material).unwrap();
            let s = 1.0 / scene.normalisation.scale;
            let want: DVec3 = scene
                .surfaces
                .iter()
                .filter(|x| x.material == material)
                .map(|x| x.normal * x.area * s * s)
                .sum();
            let got: DVec3 = mesh
                .triangles
                .iter()
                .map(|t| {
                    let p = |i: u32| DVec3::from_array(mesh.positions[i as usize]);
                    0.5 * (p(t[1]) - p(t[0])).cross(p(t[2]) - p(t[0]))
                })
                .sum();
            assert!(
                (got - want).length() < 1e-6 * want.length().max(1.0),
                "mesh {m}: {got} vs {want}"
            );
        }
        let json: serde_json::Value = serde_json::from_slice(&export.to_json()).unwrap();
        assert_eq!(json["format"], "vlf-reference-scene/1");
        assert_eq!(json["camera"]["fovy"], 39.0);
    }

    #[test]
    fn what_the_reference_cannot_draw_is_refused() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
        let (scene, _) = load_obj(&path, &ImportOptions::default()).unwrap();
        assert!(check_exportable(&scene).is_ok());
        let used = scene.surfaces[0].material;
        let mut textured = scene.clone();
        textured.materials[used].albedo_texture = Some(0);
        let e = format!("{:#}", check_exportable(&textured).unwrap_err());
        assert!(e.contains("albedo texture"), "{e}");
        // ρd + ρs ≤ 1 in each channel, but 0.8 + 0.9 across them: one blend weight cannot.
        let mut mixed = scene.clone();
        mixed.materials[used].diffuse = [0.8, 0.1, 0.1];
        mixed.materials[used].specular = [0.1, 0.9, 0.1];
        let e = format!("{:#}", check_exportable(&mixed).unwrap_err());
        assert!(e.contains("add to 1.7"), "{e}");
        // The same split in every channel is drawn.
        mixed.materials[used].diffuse = [0.3; 3];
        mixed.materials[used].specular = [0.6; 3];
        assert!(check_exportable(&mixed).is_ok());
    }

    #[test]
    fn a_missing_python_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
        let (scene, _) = load_obj(&path, &ImportOptions::default()).unwrap();
        let camera = Camera::new(DVec3::new(0.0, 0.0, -1.0), DVec3::ZERO, DVec3::Y, 39.0, 4, 3).unwrap();
        let settings = Mitsuba {
            python: dir.path().join("no-such-python"),
            spp: 4,
            ladder: vec![],
            cache: dir.path().join("cache"),
        };
        let e = format!("{:#}", Reference::mitsuba(&scene, &camera, &settings).unwrap_err());
        assert!(e.contains("no-such-python") && e.contains("requirements.txt"), "{e}");
        let odd = Mitsuba {
            spp: 3,
            ..settings.clone()
        };
        let e = format!("{:#}", Reference::mitsuba(&scene, &camera, &odd).unwrap_err());
        assert!(e.contains("even sample count"), "{e}");
        let zero = Mitsuba {
            ladder: vec![4, 0],
            ..settings
        };
        let e = format!("{:#}", Reference::mitsuba(&scene, &camera, &zero).unwrap_err());
        assert!(e.contains("at least 1 sample"), "{e}");
    }
}
