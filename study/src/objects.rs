//! Dynamic objects against the path tracer: how right an object lit by the field looks, and
//! how right its shadow is, in a scene propagated without it (`vlf_core::dynamic`).
//!
//! The path tracer renders the scene twice, with the objects in it and without; the field is
//! propagated once, for the static scene, and drawn with the objects (gathered and casting
//! shadows) and without, with direct light from the field and exact. The errors are measured
//! over two regions of the image:
//!
//! - **the objects' pixels**: where the pixel's centre ray meets an object first;
//! - **the shadow region**: other pixels that the objects change by more than
//!   [`SHADOW_THRESHOLD`] of their brightness in the path tracer's renders (darker in their
//!   shadow, brighter where they reflect light), each image averaged over 3 × 3 pixels first
//!   so that the reference's noise does not pick the pixels; emitters left out. The region is
//!   the reference's, the same whatever the field's settings.
//!
//! Over the shadow region, besides the image's own error, the *shadow depth* is compared: how
//! much light the objects take away, `Σ (static − with)`, in the field's renders against the
//! path tracer's. The field leaves out the light the objects reflect onto the scene (see
//! `docs/dynamic.md`), so its shadows are expected too deep by about that light.

use crate::reference::{Mitsuba, Reference};
use crate::sweep::{self, PixelMasks, RunSpec};
use anyhow::{Context, Result};
use std::fmt::Write as _;
use std::path::PathBuf;
use vlf_core::dynamic::PlacedObject;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::view::render_with_objects;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::Options;
use vlf_core::render::compare::{Comparison, Pixels, compare};
use vlf_core::render::{Bvh, Camera, Image};
use vlf_core::scene::Scene;
use vlf_store::Encoding;

/// A static pixel is in the shadow region where the objects change its brightness by more than
/// this fraction (in the path tracer's renders, 3 × 3 averaged).
pub const SHADOW_THRESHOLD: f64 = 0.01;

/// Everything an object study needs.
pub struct ObjectStudy {
    /// The static scene.
    pub scene: Scene,
    /// The objects, placed in the scene (its VLF frame).
    pub objects: Vec<PlacedObject>,
    pub camera: Camera,
    /// Samples per pixel axis of the field's renders.
    pub samples: u32,
    /// How the static scene is propagated.
    pub options: Options,
    /// Quadrature points per emitter of exact direct light.
    pub direct_samples: u32,
    pub block: u32,
    pub reference: Mitsuba,
    pub out: PathBuf,
    /// Whether the gather sees the objects' shadows (`Gatherer::with_gather_shadows`).
    pub gather_shadows: bool,
    /// Whether the shadows give back the objects' light (`Gatherer::with_bounce_light`).
    pub bounce_light: bool,
    /// Cells of each object's shadow cone per shaded point (`Gatherer::with_shadow_samples`).
    pub shadow_samples: u32,
    /// Directions of the objects' gather (`Gatherer::with_directions`); `None`: the field's.
    pub directions: Option<usize>,
}

/// The errors of one way of drawing the objects.
#[derive(Clone, Debug)]
pub struct ObjectRow {
    /// "field" or "exact": where direct light comes from.
    pub direct: &'static str,
    /// Over the objects' pixels.
    pub objects: Comparison,
    /// Over the shadow region.
    pub shadow: Comparison,
    /// The field's shadow depth over the path tracer's, over the shadow region.
    pub depth_ratio: f64,
    /// Seconds to render the view with the objects.
    pub render_s: f64,
}

/// What an object study measured.
pub struct ObjectOutcome {
    pub rows: Vec<ObjectRow>,
    pub object_pixels: usize,
    pub shadow_pixels: usize,
    pub propagate_s: f64,
    /// The static scene's options as its propagation ran them ([`sweep::propagate`]: the
    /// plan's perturbation and filter).
    pub ran: Options,
    /// The report and images written.
    pub files: Vec<PathBuf>,
}

/// The static scene with the objects' surfaces (and materials) added: what the path tracer
/// renders.
pub fn with_objects(scene: &Scene, objects: &[PlacedObject]) -> Scene {
    let mut merged = scene.clone();
    for o in objects {
        let first = merged.materials.len();
        merged.materials.extend(o.scene.materials.iter().cloned());
        merged.surfaces.extend(o.scene.surfaces.iter().map(|s| {
            let mut s = s.clone();
            s.material += first;
            s
        }));
    }
    merged
}

/// Runs the study (see the module docs); `progress` hears what is being done.
pub fn run(study: &ObjectStudy, progress: &mut dyn FnMut(&str)) -> Result<ObjectOutcome> {
    std::fs::create_dir_all(&study.out).with_context(|| format!("cannot create {}", study.out.display()))?;
    let camera = &study.camera;
    progress("rendering the reference with the objects (Mitsuba 3)");
    let merged = with_objects(&study.scene, &study.objects);
    let reference_with = Reference::mitsuba(&merged, camera, &study.reference)?.image;
    progress("rendering the reference without them");
    let reference_static = Reference::mitsuba(&study.scene, camera, &study.reference)?.image;

    progress("propagating the static scene");
    let spec = RunSpec {
        axis: "base",
        options: study.options.clone(),
    };
    let run = sweep::propagate(&study.scene, &spec, Encoding::F32)?;
    let directions = study.directions.unwrap_or(run.field.options.directions);
    let bvh = Bvh::build(&study.scene);
    let mut exact = run.field.clone();
    exact.use_exact_direct(&run.first_field(), study.direct_samples)?;

    let masks = PixelMasks::new(&merged, camera);
    let object_mask = object_pixels(&study.scene, &bvh, &study.objects, camera);
    let mut rows = Vec::new();
    let mut images = Vec::new();
    for (direct, field) in [("exact", &exact), ("field", &run.field)] {
        let how = if direct == "exact" { "exact" } else { "from the field" };
        progress(&format!("drawing the objects, direct light {how}"));
        let mut gatherer = Gatherer::with_directions(field, &bvh, &study.objects, SpecularMode::Rays, directions)?
            .with_shadow_samples(study.shadow_samples);
        if field.exact_direct.is_some() {
            // The objects' shadows and exact direct light share their emitter points, as in
            // `vlf render`.
            gatherer = gatherer.with_direct_samples(study.direct_samples)?;
        }
        let gatherer = gatherer
            .with_gather_shadows(study.gather_shadows)
            .with_bounce_light(study.bounce_light);
        let started = std::time::Instant::now();
        let with = render_with_objects(&gatherer, &bvh, camera, study.samples);
        let render_s = started.elapsed().as_secs_f64();
        let without = field.render(camera, study.samples, SpecularMode::Rays);
        images.push((direct, with, without, render_s));
    }
    // The shadow region, from the path tracer's pair.
    let (w, h) = (camera.width as usize, camera.height as usize);
    let (a, b) = (box3(&reference_static, w, h), box3(&reference_with, w, h));
    let shadow_mask: Vec<bool> = (0..w * h)
        .map(|i| !object_mask[i] && !masks.emitters[i] && a[i] > 0.0 && (a[i] - b[i]).abs() > SHADOW_THRESHOLD * a[i])
        .collect();
    let region = |mask: &[bool]| -> Vec<bool> { mask.iter().map(|&m| !m).collect() };
    let (not_objects, not_shadow) = (region(&object_mask), region(&shadow_mask));
    let over = |image: &Image, reference: &Image, exclude: &[bool]| {
        compare(
            image,
            reference,
            study.block,
            Pixels {
                exclude: Some(exclude),
                mask: None,
            },
        )
    };
    let depth = |a: &Image, b: &Image| -> f64 {
        (0..a.pixels.len())
            .filter(|&i| shadow_mask[i])
            .map(|i| brightness(a.pixels[i]) - brightness(b.pixels[i]))
            .sum()
    };
    let reference_depth = depth(&reference_static, &reference_with);
    let mut files = Vec::new();
    for (direct, with, without, render_s) in &images {
        rows.push(ObjectRow {
            direct,
            objects: over(with, &reference_with, &not_objects)?,
            shadow: over(with, &reference_with, &not_shadow)?,
            depth_ratio: depth(without, with) / reference_depth,
            render_s: *render_s,
        });
        let path = study.out.join(format!("objects-{direct}.pfm"));
        with.save(&path, 0.0)?;
        files.push(path);
    }
    let path = study.out.join("objects-reference.pfm");
    reference_with.save(&path, 0.0)?;
    files.push(path);
    let outcome = ObjectOutcome {
        object_pixels: object_mask.iter().filter(|&&m| m).count(),
        shadow_pixels: shadow_mask.iter().filter(|&&m| m).count(),
        propagate_s: run.propagate_s,
        ran: run.spec.options.clone(),
        rows,
        files,
    };
    let report = study.out.join("objects.md");
    std::fs::write(&report, markdown(study, &outcome)).with_context(|| format!("cannot write {}", report.display()))?;
    let mut outcome = outcome;
    outcome.files.push(report);
    Ok(outcome)
}

/// Pixels whose centre ray meets an object before the static scene.
fn object_pixels(scene: &Scene, bvh: &Bvh, objects: &[PlacedObject], camera: &Camera) -> Vec<bool> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut mask = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let (origin, dir) = camera.ray(x as f64 + 0.5, y as f64 + 0.5);
            let origin = scene.normalisation.to_vlf(origin);
            let t_static = bvh
                .intersect(scene, origin, dir, 0.0, f64::INFINITY)
                .map_or(f64::INFINITY, |h| h.t);
            mask[y * w + x] = objects.iter().any(|o| o.intersect(origin, dir, t_static).is_some());
        }
    }
    mask
}

/// Brightness averaged over the 3 × 3 pixels around each pixel (fewer at the image's edges).
fn box3(image: &Image, w: usize, h: usize) -> Vec<f64> {
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let (mut sum, mut n) = (0.0, 0.0);
            for j in y.saturating_sub(1)..(y + 2).min(h) {
                for i in x.saturating_sub(1)..(x + 2).min(w) {
                    sum += brightness(image.pixels[j * w + i]);
                    n += 1.0;
                }
            }
            out[y * w + x] = sum / n;
        }
    }
    out
}

fn brightness(p: [f32; 3]) -> f64 {
    p.iter().map(|&c| c as f64).sum::<f64>() / 3.0
}

fn markdown(study: &ObjectStudy, outcome: &ObjectOutcome) -> String {
    let mut md = String::new();
    let _ = writeln!(
        md,
        "# Dynamic objects against the path tracer\n\n{} object(s) in a {} × {} view; the static scene propagated at {} in {:.1} s; the objects gather over {} directions with {} shadow cells a point. Reference: Mitsuba 3 at {} spp, with and without the objects. {} object pixels; {} pixels in the shadow region (changed by more than {:.0} % in the reference). The gather {} the objects' shadows on the scene; the shadows {} the objects' own light.\n",
        study.objects.len(),
        study.camera.width,
        study.camera.height,
        sweep::describe(&outcome.ran),
        outcome.propagate_s,
        study.directions.unwrap_or(outcome.ran.directions),
        study.shadow_samples,
        study.reference.spp,
        outcome.object_pixels,
        outcome.shadow_pixels,
        SHADOW_THRESHOLD * 100.0,
        if study.gather_shadows { "sees" } else { "does not see" },
        if study.bounce_light {
            "give back"
        } else {
            "do not give back"
        }
    );
    let _ = writeln!(
        md,
        "| direct light | objects: mean error | objects: relative RMSE | objects: block-{b} error | shadow region: mean error | shadow region: relative RMSE | shadow depth / reference | render s |\n|---|---|---|---|---|---|---|---|",
        b = study.block
    );
    for r in &outcome.rows {
        let _ = writeln!(
            md,
            "| {} | {:+.2} % | {:.2} % | {:.2} % | {:+.2} % | {:.2} % | {:.3} | {:.2} |",
            r.direct,
            r.objects.mean_error * 100.0,
            r.objects.relative_rmse * 100.0,
            r.objects.block_error * 100.0,
            r.shadow.mean_error * 100.0,
            r.shadow.relative_rmse * 100.0,
            r.depth_ratio,
            r.render_s
        );
    }
    md
}
