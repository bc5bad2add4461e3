//! `vlf`: the command line of the virtual light field.
//!
//! `vlf propagate` imports a scene, propagates its light field and writes it
//! to a directory; `vlf render` renders an image of a propagated field from
//! any viewpoint. Exact flags are part of the interface: scripts rely on them.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::time::Instant;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Perturbation, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::Camera;
use vlf_core::render::camera::{parse_size, parse_vec3};
use vlf_core::scene::{ImportOptions, load_obj};

#[derive(Parser)]
#[command(
    name = "vlf",
    version,
    about = "Virtual light field: propagate globally illuminated scenes, render any view"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Propagate the light of a scene (OBJ + MTL) into a light field directory.
    Propagate(PropagateArgs),
    /// Render an image of a propagated light field.
    Render(RenderArgs),
}

#[derive(Args)]
struct PropagateArgs {
    /// Wavefront OBJ scene (materials from its MTL; see the README's conventions).
    scene: PathBuf,
    /// Directory to write the field into.
    #[arg(long)]
    out: PathBuf,
    /// Number of directions l = 2·4^k + 1: 9, 33, 129, 513, 2049 or 8193.
    #[arg(long, default_value_t = 513)]
    directions: usize,
    /// Rays per side N of every parallel subfield.
    #[arg(long, default_value_t = 64)]
    resolution: u32,
    /// Tile size m (rays per tile side; divides N).
    #[arg(long, default_value_t = 8)]
    tile: u32,
    /// Run exactly K iterations.
    #[arg(long, conflicts_with = "converge")]
    iterations: Option<u32>,
    /// Iterate until the unshot power is below EPS × the emitted power (default 1e-3).
    #[arg(long)]
    converge: Option<f64>,
    /// Worker threads (default: all cores). Results are the same bits for any value.
    #[arg(long)]
    threads: Option<usize>,
    /// Texel edge in ray spacings (2/N in the normalised frame).
    #[arg(long, default_value_t = 1.0)]
    texel: f64,
    /// Deferred propagation: surfaces with less than this fraction of the unshot power wait.
    #[arg(long)]
    defer: Option<f64>,
    /// Perturb the direction set in the first ITERS iterations (remedy for holes; 0 = off).
    #[arg(long, default_value_t = 2)]
    perturb: u32,
    /// Rotated copies of the direction set per perturbed iteration.
    #[arg(long, default_value_t = 4)]
    perturb_count: u32,
    /// After the last iteration, re-sample the mirrors' directional maps by
    /// backward ray tracing (sharper reflections when rendering from the rays).
    #[arg(long)]
    resample: bool,
    /// Gaussian filter of the Next maps, σ in texels (0 = off).
    #[arg(long, default_value_t = 1.0)]
    filter: f64,
}

#[derive(Args)]
struct RenderArgs {
    /// Light field directory written by `vlf propagate`.
    field: PathBuf,
    /// Eye position, scene units.
    #[arg(long, value_parser = parse_vec3_arg, allow_hyphen_values = true)]
    eye: glam::DVec3,
    /// Point looked at, scene units.
    #[arg(long, value_parser = parse_vec3_arg, allow_hyphen_values = true)]
    target: glam::DVec3,
    /// Up vector.
    #[arg(long, value_parser = parse_vec3_arg, allow_hyphen_values = true, default_value = "0,1,0")]
    up: glam::DVec3,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 45.0)]
    fovy: f64,
    /// Image size WxH.
    #[arg(long, default_value = "512x512", value_parser = parse_size_arg)]
    size: (u32, u32),
    /// Output image: .pfm (linear), .exr (linear) or .png (tone-mapped sRGB).
    #[arg(long)]
    out: PathBuf,
    /// Exposure in stops for .png output (pixel × 2^exposure).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    exposure: f64,
    /// Samples per pixel axis (box filter over samples²).
    #[arg(long, default_value_t = 2)]
    samples: u32,
    /// How mirrors are shaded: from the field's rays, or ray traced.
    #[arg(long, value_enum, default_value_t = SpecularArg::Rays)]
    specular: SpecularArg,
    /// Maximum number of mirror bounces when ray tracing.
    #[arg(long, default_value_t = 8)]
    depth: u32,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum SpecularArg {
    /// Look up the mirrors' directional radiance maps (the light field).
    Rays,
    /// Reflect eye rays until they reach a diffuse surface.
    Trace,
}

fn parse_vec3_arg(s: &str) -> Result<glam::DVec3, String> {
    parse_vec3(s).map_err(|e| e.to_string())
}

fn parse_size_arg(s: &str) -> Result<(u32, u32), String> {
    parse_size(s).map_err(|e| e.to_string())
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Propagate(args) => propagate(args),
        Command::Render(args) => render(args),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn propagate(args: PropagateArgs) -> Result<()> {
    let stop = match (args.iterations, args.converge) {
        (Some(k), _) => Stop::Iterations(k),
        (None, eps) => Stop::Converge {
            epsilon: eps.unwrap_or(1e-3),
            max_iterations: 1000,
        },
    };
    let options = Options {
        directions: args.directions,
        grid: GridSize::new(args.resolution, args.tile)?,
        stop,
        texel_cells: args.texel,
        deferral: args.defer,
        perturbation: Perturbation {
            iterations: args.perturb,
            count: args.perturb_count,
        },
        filter_sigma: (args.filter != 0.0).then_some(args.filter),
    };
    options.validate()?;
    let threads = args.threads.unwrap_or(0);
    if args.threads == Some(0) || threads > 1024 {
        bail!("--threads must be between 1 and 1024");
    }
    let resample = args.resample;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("cannot start the worker threads")?;
    let started = Instant::now();
    let (scene, warnings) = load_obj(&args.scene, &ImportOptions::default())
        .with_context(|| format!("cannot import {}", args.scene.display()))?;
    for w in &warnings {
        tracing::warn!("{w}");
    }
    tracing::info!(
        surfaces = scene.surfaces.len(),
        materials = scene.materials.len(),
        "scene imported"
    );
    let (field, iterations, field_bytes) = pool.install(|| -> Result<_> {
        let mut prop = Propagation::new(scene, options).context("cannot set up the light field")?;
        print!("{}", prop.plan);
        tracing::info!(
            directions = prop.directions.len(),
            texels = prop.atlas.texels,
            setup_s = format!("{:.2}", started.elapsed().as_secs_f64()),
            "subfields rasterised"
        );
        let bar = ProgressBar::new(prop.directions.len() as u64);
        bar.set_style(
            ProgressStyle::with_template("{prefix:>14} [{bar:40}] {pos}/{len} directions {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        while !prop.finished() {
            let k = prop.iterations_done();
            bar.set_prefix(format!("iteration {}", k + 1));
            bar.set_message(format!("unshot {:.2e}", prop.unshot_fraction()));
            bar.set_position(0);
            prop.step(|p| {
                bar.set_length(p.directions_total as u64);
                bar.set_position(p.directions_done as u64);
            });
        }
        bar.finish_and_clear();
        let bytes = prop.field_bytes();
        let k = prop.iterations_done();
        let mut field = prop.into_field();
        if resample {
            field.resample_mirrors(8);
        }
        Ok((field, k, bytes))
    })?;
    field.save(&args.out)?;
    let elapsed = started.elapsed().as_secs_f64();
    let balance = field
        .stats
        .iter()
        .map(|s| {
            let f = &s.flow;
            let shot: f64 = f.shot.iter().sum();
            let accounted: f64 = (0..3).map(|c| f.received[c] + f.escaped[c] + f.blocked[c]).sum();
            if shot > 0.0 {
                ((shot - accounted) / shot).abs()
            } else {
                0.0
            }
        })
        .fold(0.0, f64::max);
    println!("propagated {} in {elapsed:.2} s", args.scene.display());
    println!("  iterations      {iterations}");
    println!("  unshot fraction {:.3e}", field.unshot_fraction);
    println!("  energy balance  {balance:.1e} (worst relative mismatch of an iteration)");
    println!("  field memory    {:.1} MB", field_bytes as f64 / 1e6);
    if let Some(peak) = peak_memory_kb() {
        println!("  peak memory     {:.1} MB", peak as f64 / 1024.0);
    }
    println!("  written to      {}", args.out.display());
    Ok(())
}

fn render(args: RenderArgs) -> Result<()> {
    if !(1..=16).contains(&args.samples) {
        bail!("--samples must be 1..=16, got {}", args.samples);
    }
    let field = LightField::load(&args.field)
        .with_context(|| format!("cannot read the light field in {}", args.field.display()))?;
    let camera = Camera::new(args.eye, args.target, args.up, args.fovy, args.size.0, args.size.1)?;
    let started = Instant::now();
    if args.depth > 64 {
        bail!("--depth must be at most 64, got {}", args.depth);
    }
    let mode = match args.specular {
        SpecularArg::Rays => SpecularMode::Rays,
        SpecularArg::Trace => SpecularMode::Trace { depth: args.depth },
    };
    let image = field.render(&camera, args.samples, mode);
    image
        .save(&args.out, args.exposure)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    println!(
        "rendered {}x{} in {:.2} s → {}",
        args.size.0,
        args.size.1,
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
    Ok(())
}

/// Peak resident memory of this process (Linux), in KiB.
fn peak_memory_kb() -> Option<u64> {
    let status = std::fs::read_to_string(Path::new("/proc/self/status")).ok()?;
    status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}
