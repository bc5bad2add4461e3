//! # vlf-study: what accuracy costs in time
//!
//! A user choosing the number of directions `l`, the resolution `N`, the
//! tile `m`, the iteration count and the renderer's modes wants to know what
//! each choice buys in error and costs in time and memory. `vlf study`
//! answers with measurements:
//!
//! 1. a **reference** image from an independent path tracer, Mitsuba 3
//!    ([`reference`]), or an image the user gives;
//! 2. a **sweep** of the parameters one at a time around the defaults
//!    ([`sweep`]), each propagation timed and its peak memory and stored
//!    size measured ([`memory`]), each field rendered every way;
//! 3. the **errors** of every rendering against the reference
//!    ([`vlf_core::render::compare`]);
//! 4. a **report** ([`report`]): CSV, a Markdown table with the best setting
//!    per time budget and the break-even walkthrough length against path
//!    tracing every frame, plots of error against time ([`plot`]) and error
//!    maps.

pub mod memory;
pub mod objects;
pub mod plot;
pub mod reference;
pub mod report;
pub mod sweep;

use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::Options;
use vlf_core::render::compare::{compare, error_map, false_colour};
use vlf_core::render::{Camera, Image};
use vlf_core::scene::{ImportOptions, Scene, load_scene};
use vlf_store::Encoding;

use reference::{Mitsuba, Reference};
use report::{PathTracerFit, Row};
use sweep::{RenderMode, Run, Sweep};

/// Where the reference comes from.
#[derive(Clone, Debug)]
pub enum ReferenceSource {
    /// A PFM image of the same camera and size.
    Image(PathBuf),
    /// Rendered (or found in the cache) by Mitsuba 3.
    Mitsuba(Mitsuba),
}

/// Everything a study needs.
#[derive(Clone, Debug)]
pub struct Study {
    pub scene: PathBuf,
    pub camera: Camera,
    /// Samples per pixel axis of the field's renders (box filter).
    pub samples: u32,
    pub base: Options,
    pub sweep: Sweep,
    pub encoding: Encoding,
    /// Mirror depth of ray-traced specular renders.
    pub trace_depth: u32,
    /// Quadrature points per emitter for exact direct light.
    pub direct_samples: u32,
    /// Block edge (pixels) of the block error.
    pub block: u32,
    pub reference: ReferenceSource,
    /// Output folder.
    pub out: PathBuf,
}

/// What a study produced.
pub struct Outcome {
    pub rows: Vec<Row>,
    pub reference: Reference,
    /// Files written, in order.
    pub files: Vec<PathBuf>,
}

/// Runs the study, writing its files into `study.out`. `progress` hears a
/// line before each step (for a progress display).
pub fn run(study: &Study, progress: &mut dyn FnMut(usize, usize, &str)) -> Result<Outcome> {
    std::fs::create_dir_all(&study.out).with_context(|| format!("cannot create {}", study.out.display()))?;
    let (scene, warnings) = load_scene(&study.scene, &ImportOptions::default())
        .with_context(|| format!("cannot import {}", study.scene.display()))?;
    for w in warnings {
        tracing::warn!("{w}");
    }
    let reference = match &study.reference {
        ReferenceSource::Image(path) => Reference::from_file(path, &study.camera)?,
        ReferenceSource::Mitsuba(settings) => {
            progress(0, 1, "rendering the reference with Mitsuba 3");
            Reference::mitsuba(&scene, &study.camera, settings)?
        }
    };
    let has_mirrors = scene.materials.iter().any(|m| m.is_mirror());
    let masks = sweep::PixelMasks::new(&scene, &study.camera);
    let pixels = masks.pixels(has_mirrors);
    let fit = PathTracerFit::new(&reference, study.block, pixels)?;
    let modes = render_modes(study, has_mirrors);

    // The toggles vary what the plan decides for this scene (the filter, by its mirrors).
    let runs = sweep::plan(&study.base.resolved_for(&scene), &study.sweep);
    let total = runs.len() + usize::from(study.sweep.iterations);
    let mut rows = Vec::new();
    let mut files = Vec::new();
    let mut base_run: Option<Run> = None;
    let exposure = exposure_for(&reference.image);
    let measure = |image: &Image| compare(image, &reference.image, study.block, pixels);

    // What ran, as the plan made it: a toggle that comes out as a run already made (no
    // perturbation where light reaches a mirror) is left out rather than reported twice.
    let mut ran: Vec<Options> = Vec::new();
    // The joint points' base renders, for the images kept of the coarsest and the finest.
    let mut joint_images: Vec<(Row, Image)> = Vec::new();
    for (i, spec) in runs.iter().enumerate() {
        // Where light reaches a mirror no iteration is perturbed, whatever the options ask (the
        // plan's rule): the toggle would run the base again.
        if spec.axis == "perturbation"
            && let Some(base) = &base_run
            && base.field.specular.is_some()
        {
            tracing::warn!("no perturbation toggle: light reaches a mirror, so no iteration is perturbed");
            continue;
        }
        progress(
            i,
            total,
            &format!("propagating {} ({})", sweep::describe(&spec.options), spec.axis),
        );
        // A point the method cannot run (a lamp no ray of a coarse grid hits) is left out with
        // its reason; the others are measured.
        // Only a refusal of the options is skipped; any other error (the store, an encoding) ends
        // the study, as it would any run.
        let run = match sweep::propagate(&scene, spec, study.encoding) {
            Ok(run) => run,
            Err(e)
                if spec.axis != "base"
                    && matches!(e.downcast_ref::<vlf_core::Error>(), Some(vlf_core::Error::Parameter(_))) =>
            {
                tracing::warn!("skipping {} ({}): {e:#}", sweep::describe(&spec.options), spec.axis);
                continue;
            }
            Err(e) => return Err(e),
        };
        if ran.contains(&run.spec.options) {
            tracing::warn!(
                "{} ({}) ran as a point already measured: left out",
                sweep::describe(&run.spec.options),
                spec.axis
            );
            continue;
        }
        ran.push(run.spec.options.clone());
        let first = run.first_field();
        for &mode in &modes {
            let (image, render_s) = sweep::render(&run.field, &first, &study.camera, study.samples, mode)?;
            let error = measure(&image)?;
            let row = make_row(
                spec.axis,
                &run,
                run.field.stats.len() as u32,
                run.propagate_s,
                mode,
                render_s,
                error,
                fit,
            );
            match kept_images(&row) {
                Keep::Now => files.extend(save_images(&study.out, &row, &image, &reference.image, exposure)?),
                // Which joint points are the coarsest and finest is known once all have run (a
                // point the method cannot run is left out).
                Keep::IfExtreme => joint_images.push((row.clone(), image)),
                Keep::No => {}
            }
            rows.push(row);
        }
        if spec.axis == "base" {
            base_run = Some(run);
        }
    }

    let ls = || joint_images.iter().map(|(row, _)| row.directions);
    let (lo, hi) = (ls().min(), ls().max());
    for (row, image) in &joint_images {
        if Some(row.directions) == lo || Some(row.directions) == hi {
            files.extend(save_images(&study.out, row, image, &reference.image, exposure)?);
        }
    }

    if study.sweep.iterations
        && let Some(base) = &base_run
    {
        progress(runs.len(), total, "rendering the base field after every iteration");
        let fields = sweep::fields_per_iteration(&scene, &base.spec.options)?;
        let first = base.first_field();
        let mode = modes[0];
        let mut elapsed = base.setup_s;
        for (k, field) in fields.iter().enumerate().take(fields.len().saturating_sub(1)) {
            elapsed += base.iteration_s.get(k).copied().unwrap_or(0.0);
            let (image, render_s) = sweep::render(field, &first, &study.camera, study.samples, mode)?;
            let mut row = make_row(
                "iterations",
                base,
                k as u32 + 1,
                elapsed,
                mode,
                render_s,
                measure(&image)?,
                fit,
            );
            row.peak_mb = None;
            row.stored_mb = None;
            row.unshot = field.unshot_fraction;
            rows.push(row);
        }
    }
    progress(total, total, "writing the report");

    let name = study
        .scene
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("scene")
        .to_string();
    let csv = study.out.join("study.csv");
    report::write_csv(&csv, &rows)?;
    let md = study.out.join("study.md");
    let camera = &study.camera;
    report::write_markdown(
        &md,
        &report::Setting {
            scene: &name,
            camera: format!(
                "eye {} target {} fovy {}° {}×{}",
                fmt_vec(camera.eye),
                fmt_vec(camera.target),
                camera.fovy_degrees,
                camera.width,
                camera.height
            ),
            samples: study.samples,
            threads: rayon::current_num_threads(),
            reference: &reference,
            fit,
            encoding: encoding_name(study.encoding),
            noise: reference.noise_over(pixels),
            excluded: masks.emitters.iter().filter(|&&e| e).count(),
        },
        &rows,
    )?;
    files.push(csv);
    files.push(md);
    for (measure, file) in [
        (plot::Measure::RelativeRmse, "error-vs-time.png"),
        (plot::Measure::BlockError, "block-error-vs-time.png"),
    ] {
        let path = study.out.join(file);
        // A study of too few points has no curve to draw: its tables are its report.
        if !plot::has_curve(&rows, measure) {
            tracing::warn!("no plot {}: no sweep has two points", path.display());
            continue;
        }
        plot::error_vs_time(
            &path,
            &format!("{name}: error against propagation time"),
            &rows,
            measure,
        )?;
        files.push(path);
    }
    let path = study.out.join("reference.png");
    reference.image.save(&path, exposure)?;
    files.push(path);
    Ok(Outcome { rows, reference, files })
}

/// The render modes of every field: the base way first (mirrors ray traced,
/// direct light from the field), then exact direct light, then (with
/// mirrors) mirrors from the rays.
fn render_modes(study: &Study, has_mirrors: bool) -> Vec<RenderMode> {
    let trace = SpecularMode::Trace {
        depth: study.trace_depth,
    };
    let mut modes = vec![
        RenderMode {
            specular: trace,
            exact_direct: None,
        },
        RenderMode {
            specular: trace,
            exact_direct: Some(study.direct_samples),
        },
    ];
    if has_mirrors {
        modes.push(RenderMode {
            specular: SpecularMode::Rays,
            exact_direct: None,
        });
    }
    modes
}

#[allow(clippy::too_many_arguments)]
fn make_row(
    axis: &str,
    run: &Run,
    iterations: u32,
    propagate_s: f64,
    mode: RenderMode,
    render_s: f64,
    error: vlf_core::render::compare::Comparison,
    fit: Option<PathTracerFit>,
) -> Row {
    let o = &run.spec.options;
    let mb = |b: f64| b / (1 << 20) as f64;
    Row {
        axis: axis.into(),
        label: sweep::describe(o),
        directions: o.directions,
        resolution: o.grid.resolution,
        tile: o.grid.tile,
        texel: o.texel_cells,
        iterations,
        perturbation: sweep::perturbed(o),
        filter: o.filter_sigma.is_some(),
        specular: mode.specular_name(),
        direct: mode.direct_name(),
        propagate_s,
        render_s,
        peak_mb: run.peak_bytes.map(|b| mb(b as f64)),
        field_mb: mb(run.field_bytes as f64),
        stored_mb: Some(mb(run.stored_bytes as f64)),
        unshot: run.unshot_fraction,
        pt_equal_s: fit.map(|f| f.seconds_for_rmse(error.relative_rmse)),
        pt_equal_block_s: fit.map(|f| f.seconds_for_block(error.block_error)),
        error,
    }
}

/// Whether a row's images are kept: the base point's (every render mode) at once, and the
/// joint (l, N) points' base render if theirs is the coarsest or finest point that ran.
enum Keep {
    Now,
    IfExtreme,
    No,
}

fn kept_images(row: &Row) -> Keep {
    match row.axis.as_str() {
        "base" => Keep::Now,
        "joint" if row.specular == "trace" && row.direct == "field" => Keep::IfExtreme,
        _ => Keep::No,
    }
}

/// Writes the rendering (tone-mapped PNG) and its false-colour error map
/// (full scale: an error of the reference's mean). Returns the paths.
fn save_images(out: &Path, row: &Row, image: &Image, reference: &Image, exposure: f64) -> Result<Vec<PathBuf>> {
    let stem = format!(
        "{}-l{}-N{}-m{}-{}-{}",
        row.axis, row.directions, row.resolution, row.tile, row.specular, row.direct
    );
    let render = out.join(format!("{stem}.png"));
    image.save(&render, exposure)?;
    let map = error_map(image, reference)?;
    let rgb = false_colour(&map, 1.0);
    let path = out.join(format!("{stem}-error.png"));
    image::RgbImage::from_raw(map.width, map.height, rgb)
        .context("error map size")?
        .save_with_format(&path, image::ImageFormat::Png)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(vec![render, path])
}

/// Exposure (stops) that puts the reference's mean at 18 % grey.
fn exposure_for(reference: &Image) -> f64 {
    let m = reference.mean();
    let mean = (m[0] + m[1] + m[2]) / 3.0;
    if mean > 0.0 { (0.18 / mean).log2() } else { 0.0 }
}

fn fmt_vec(v: glam::DVec3) -> String {
    format!("{},{},{}", v.x, v.y, v.z)
}

fn encoding_name(e: Encoding) -> &'static str {
    match e {
        Encoding::F32 => "f32",
        Encoding::F16 => "f16",
        Encoding::Rgb9e5 => "rgb9e5",
        _ => "other",
    }
}

/// The scene as imported, for callers that need it (e.g. to export it).
pub fn import(path: &Path) -> Result<Scene> {
    let (scene, _) =
        load_scene(path, &ImportOptions::default()).with_context(|| format!("cannot import {}", path.display()))?;
    Ok(scene)
}
