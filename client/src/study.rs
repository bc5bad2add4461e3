//! `vlf study`: what accuracy costs in time, measured against a reference
//! path tracer (see the `vlf-study` crate).

use crate::{JobFlags, ViewFlags, parse_size_arg};
use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use vlf_study::reference::Mitsuba;
use vlf_study::sweep::Sweep;
use vlf_study::{ReferenceSource, Study};

#[derive(Args)]
pub struct StudyArgs {
    /// Scene file: Wavefront OBJ (with its MTL) or glTF 2.0 (.gltf, .glb).
    scene: PathBuf,
    /// Output folder (CSV, Markdown, plots, images).
    #[arg(long, default_value = "study-out")]
    out: PathBuf,
    #[command(flatten)]
    view: ViewFlags,
    /// Image size WxH.
    #[arg(long, default_value = "320x240", value_parser = parse_size_arg)]
    size: (u32, u32),
    /// Samples per pixel axis of the field's renders (box filter over samples²).
    #[arg(long, default_value_t = 2)]
    samples: u32,
    /// Reference image (PFM, same camera and size) instead of rendering one with Mitsuba 3.
    #[arg(long, value_name = "PFM")]
    reference: Option<PathBuf>,
    /// Samples per pixel of the Mitsuba reference.
    #[arg(long, default_value_t = 4096)]
    spp: u32,
    /// Sample counts of the timed path-tracer renders (equal-quality comparison); "" for none.
    #[arg(long, default_value = "1,4,16,64", value_delimiter = ',')]
    ladder: Vec<String>,
    /// Python interpreter with study/mitsuba/requirements.txt installed.
    #[arg(long, env = "VLF_PYTHON", default_value = "python3")]
    python: PathBuf,
    /// Cache of reference renders (default: $XDG_CACHE_HOME/vlf/references or ~/.cache/vlf/references).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// (l, N) pairs refined together, as L/N ("" for none).
    #[arg(long, default_value = "33/16,129/32,513/64,2049/128", value_delimiter = ',')]
    sweep_joint: Vec<String>,
    /// Directions l to sweep ("" for none).
    #[arg(long, default_value = "33,129,513,2049", value_delimiter = ',')]
    sweep_directions: Vec<String>,
    /// Resolutions N to sweep ("" for none).
    #[arg(long, default_value = "32,64,128", value_delimiter = ',')]
    sweep_resolution: Vec<String>,
    /// Tiles m to sweep ("" for none).
    #[arg(long, default_value = "4,8,16", value_delimiter = ',')]
    sweep_tile: Vec<String>,
    /// Texel edges (in ray spacings) to sweep ("" for none).
    #[arg(long, default_value = "1,2", value_delimiter = ',')]
    sweep_texel: Vec<String>,
    /// Skip the renders after every iteration of the base propagation.
    #[arg(long)]
    no_iterations: bool,
    /// Skip the runs with perturbation and filtering toggled.
    #[arg(long)]
    no_toggles: bool,
    /// Mirror depth of ray-traced renders.
    #[arg(long, default_value_t = 8)]
    depth: u32,
    /// Quadrature points per emitter for exact direct light.
    #[arg(long, default_value_t = vlf_core::direct::DEFAULT_SAMPLES)]
    direct_samples: u32,
    /// Block edge in pixels of the block error.
    #[arg(long, default_value_t = 16)]
    block: u32,
    /// The base point of the sweep (the other parameters stay at it).
    #[command(flatten)]
    job: JobFlags,
    /// With --object: no sweep; the objects' pixels and their shadows against the path
    /// tracer's render of the scene with them (`docs/dynamic.md`), propagated at the base
    /// point, direct light from the field and exact.
    #[command(flatten)]
    objects: crate::objects::ObjectFlags,
    /// With --object: the gather reads the static scene as the field holds it, without the
    /// objects' shadows on it (to measure what seeing them is worth).
    #[arg(long, requires = "object")]
    no_gather_shadows: bool,
    /// With --object: the shadows take the light behind the objects without giving back the
    /// light the objects reflect.
    #[arg(long, requires = "object")]
    no_bounce_light: bool,
}

fn numbers<T: std::str::FromStr>(name: &str, values: &[String]) -> Result<Vec<T>> {
    values
        .iter()
        .map(|v| v.trim())
        .filter(|v| !v.is_empty())
        .map(|v| {
            v.parse()
                .map_err(|_| anyhow::anyhow!("--{name}: '{v}' is not a number"))
        })
        .collect()
}

fn pairs(values: &[String]) -> Result<Vec<(usize, u32)>> {
    values
        .iter()
        .map(|v| v.trim())
        .filter(|v| !v.is_empty())
        .map(|v| {
            let (l, n) = v
                .split_once('/')
                .ok_or_else(|| anyhow::anyhow!("--sweep-joint: '{v}' is not L/N, e.g. 513/64"))?;
            Ok((
                l.trim()
                    .parse()
                    .map_err(|_| anyhow::anyhow!("--sweep-joint: bad l in '{v}'"))?,
                n.trim()
                    .parse()
                    .map_err(|_| anyhow::anyhow!("--sweep-joint: bad N in '{v}'"))?,
            ))
        })
        .collect()
}

/// `vlf study --object`: the objects against the path tracer (`vlf_study::objects`).
fn objects(args: &StudyArgs, camera: vlf_core::render::Camera, options: vlf_core::propagate::Options) -> Result<()> {
    if args.reference.is_some() {
        bail!("--object renders its two references with Mitsuba 3: drop --reference");
    }
    let scene = crate::propagate::import(&args.scene)?;
    let bvh = vlf_core::render::Bvh::build(&scene);
    let placed = args.objects.place(args.view.up(), &scene, &bvh)?;
    let study = vlf_study::objects::ObjectStudy {
        scene,
        objects: placed,
        camera,
        samples: args.samples,
        options,
        direct_samples: args.direct_samples,
        block: args.block,
        reference: Mitsuba {
            python: args.python.clone(),
            spp: args.spp,
            ladder: Vec::new(),
            cache: args.cache.clone().unwrap_or_else(default_cache),
        },
        out: args.out.clone(),
        gather_shadows: !args.no_gather_shadows,
        bounce_light: !args.no_bounce_light,
        shadow_samples: args.objects.object_shadow_samples,
        directions: args.objects.object_directions,
    };
    let outcome = vlf_study::objects::run(&study, &mut |message| tracing::info!("{message}"))
        .with_context(|| format!("object study of {} failed", args.scene.display()))?;
    for r in &outcome.rows {
        println!(
            "direct light from the {}: objects {:+.2} % mean, {:.2} % relative RMSE; shadow region {:+.2} % mean, {:.2} % relative RMSE, depth {:.3} × the reference's",
            r.direct,
            r.objects.mean_error * 100.0,
            r.objects.relative_rmse * 100.0,
            r.shadow.mean_error * 100.0,
            r.shadow.relative_rmse * 100.0,
            r.depth_ratio
        );
    }
    println!("wrote:");
    for f in &outcome.files {
        println!("  {}", f.display());
    }
    Ok(())
}

fn default_cache() -> PathBuf {
    let base = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .unwrap_or_else(std::env::temp_dir);
    base.join("vlf").join("references")
}

pub fn run(args: StudyArgs) -> Result<()> {
    if !(1..=16).contains(&args.samples) {
        bail!("--samples must be 1..=16, got {}", args.samples);
    }
    if args.block == 0 || args.depth > 64 {
        bail!("--block must be at least 1 and --depth at most 64");
    }
    let camera = args.view.camera(args.size)?;
    let spec = args.job.spec()?;
    if !(1..=65536).contains(&args.direct_samples) {
        bail!("--direct-samples must be 1..=65536, got {}", args.direct_samples);
    }
    // A study measures the fields as propagated: re-sampled mirrors are not part of it.
    if spec.resample {
        bail!("--resample is not measured by a study: leave it out");
    }
    if !args.objects.is_empty() {
        args.objects.check()?;
        return objects(&args, camera, spec.options);
    }
    let reference = match &args.reference {
        Some(path) => ReferenceSource::Image(path.clone()),
        None => ReferenceSource::Mitsuba(Mitsuba {
            python: args.python.clone(),
            spp: args.spp,
            ladder: numbers("ladder", &args.ladder)?,
            cache: args.cache.clone().unwrap_or_else(default_cache),
        }),
    };
    let study = Study {
        scene: args.scene.clone(),
        camera,
        samples: args.samples,
        base: spec.options,
        sweep: Sweep {
            joint: pairs(&args.sweep_joint)?,
            directions: numbers("sweep-directions", &args.sweep_directions)?,
            resolution: numbers("sweep-resolution", &args.sweep_resolution)?,
            tile: numbers("sweep-tile", &args.sweep_tile)?,
            texel: numbers("sweep-texel", &args.sweep_texel)?,
            iterations: !args.no_iterations,
            perturbation: !args.no_toggles,
            filter: !args.no_toggles,
        },
        encoding: spec.encoding,
        trace_depth: args.depth,
        direct_samples: args.direct_samples,
        block: args.block,
        reference,
        out: args.out.clone(),
    };
    let bar = ProgressBar::new(1);
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let outcome = vlf_study::run(&study, &mut |done, total, message| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        bar.set_message(message.to_string());
    })
    .with_context(|| format!("study of {} failed", args.scene.display()))?;
    bar.finish_and_clear();
    if let Some(base) = outcome.rows.iter().find(|r| r.is_base()) {
        println!(
            "base {}: propagation {:.2} s, frame {:.3} s, relative RMSE {:.2} %, block error {:.2} %{}",
            base.label,
            base.propagate_s,
            base.render_s,
            base.error.relative_rmse * 100.0,
            base.error.block_error * 100.0,
            base.break_even_frames().map_or(String::new(), |f| format!(
                ", cheaper than path tracing after {:.0} frames",
                f.ceil()
            ))
        );
    }
    println!("{} rows; wrote:", outcome.rows.len());
    for f in &outcome.files {
        println!("  {}", f.display());
    }
    Ok(())
}
