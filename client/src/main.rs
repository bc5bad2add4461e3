//! `vlf`: the command line of the virtual light field.
//!
//! `vlf propagate` imports a scene, propagates its light field into a job of
//! a store (a directory, `s3://…` or `memory://`), writing a snapshot after
//! every iteration; `vlf render` renders any snapshot of a job from any
//! viewpoint; `vlf jobs` lists a store's jobs. Exact flags are part of the
//! interface: scripts rely on them.

use vlf_core::propagate::defaults;

mod bench;
mod objects;
mod processes;
mod propagate;
mod remote;
mod render;
mod run;
mod study;
mod view;

use anyhow::Result;
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;
use vlf_core::render::camera::{parse_size, parse_vec3};

/// mimalloc keeps freed pages for reuse, where glibc's malloc hands large blocks back to the
/// system and faults them in again: an iteration allocates and frees megabytes of maps, blobs and
/// buffers, and on a VM the page faults cost more than the copies.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

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
    /// Propagate the light of a scene (OBJ + MTL) into a job of a store, in this process.
    Propagate(PropagateArgs),
    /// Propagate through the embedded service: a coordinator and worker replicas in this
    /// process, exchanging every iteration's work through the store (same bits as propagate).
    Run(RunArgs),
    /// Render an image of a job's field (or of one of its snapshots), from a store or a server.
    Render(RenderArgs),
    /// Walk through a job's field in a window (wgpu): WASD and Q/E move, a drag looks, the wheel
    /// sets the speed, M cycles the mirror mode, + and − the exposure, P saves a screenshot.
    View(ViewArgs),
    /// List the jobs of a store, or of a server (--server).
    Jobs(JobsArgs),
    /// Run the coordinator: jobs, leases to workers, progress, tiles (gRPC).
    Serve(vlf_server::cli::ServeArgs),
    /// Run a worker for a coordinator.
    Worker(vlf_worker::cli::WorkerArgs),
    /// Submit a scene to a coordinator; prints the job id.
    Submit(SubmitArgs),
    /// Show a job's status.
    Status(JobArgs),
    /// Follow a job's progress until it ends.
    Watch(JobArgs),
    /// Cancel a job.
    Cancel(JobArgs),
    /// Ask a coordinator whether it serves (the standard gRPC health check, which needs no
    /// token); exits with 0 when it does. For container health checks and start-up scripts.
    Health(HealthArgs),
    /// Measure what accuracy costs: sweep the parameters against a reference path tracer
    /// (Mitsuba 3, or a given image) and write CSV, Markdown and plots.
    Study(study::StudyArgs),
    /// Measure what the distributed service costs over an in-process propagation (same bits,
    /// 1 and k workers, work moved per iteration).
    Bench(bench::BenchArgs),
}

#[derive(Args)]
pub struct SubmitArgs {
    /// Scene file: Wavefront OBJ (its MTL libraries are sent with it) or glTF 2.0 (.glb, or .gltf
    /// with the buffers and images it names next to it).
    scene: PathBuf,
    #[command(flatten)]
    server: ServerFlags,
    #[command(flatten)]
    job: JobFlags,
    /// Follow the job's progress until it ends.
    #[arg(long)]
    watch: bool,
}

#[derive(Args)]
pub struct HealthArgs {
    #[command(flatten)]
    server: ServerFlags,
    /// Keep asking for up to this many seconds while the coordinator does not answer or does
    /// not serve yet.
    #[arg(long, value_name = "SECONDS", default_value_t = 0.0)]
    wait: f64,
}

#[derive(Args)]
pub struct JobArgs {
    /// Job id.
    job: String,
    #[command(flatten)]
    server: ServerFlags,
}

#[derive(Args)]
pub struct PropagateArgs {
    /// Scene file: Wavefront OBJ (materials from its MTL) or glTF 2.0 (.gltf, .glb); see the
    /// conventions in docs/scenes.md.
    /// Not needed with --resume (the job holds its scene).
    #[arg(required_unless_present = "resume")]
    scene: Option<PathBuf>,
    /// Store to write the job into: a directory, file:///PATH, s3://BUCKET/PREFIX or memory://.
    #[arg(long, visible_alias = "out", value_name = "URL")]
    store: String,
    /// Resume job JOB of the store from its last finished snapshot (its scene and parameters
    /// are the job's; only --threads, --subfield-memory and --resample apply). Gives the same
    /// bits as a run that never stopped.
    #[arg(long, value_name = "JOB", conflicts_with = "scene")]
    resume: Option<String>,
    /// Worker threads (default: all cores). Results are the same bits for any value.
    #[arg(long)]
    threads: Option<usize>,
    /// Hold at most this much of the subfields (e.g. 512MiB, 2GB), building the others when
    /// a direction is shot: the same bits in less memory, at the cost of rebuilding (see
    /// docs/scaling.md). Default: all held.
    #[arg(long, value_name = "SIZE")]
    subfield_memory: Option<bytesize::ByteSize>,
    #[command(flatten)]
    job: JobFlags,
}

/// What a job computes: the settings of `vlf_proto::v1::Parameters`, shared by `propagate`, `run`
/// and `submit`. Their defaults are `vlf_core::propagate::defaults`, as the service's.
#[derive(Args, Clone)]
pub struct JobFlags {
    /// Encoding of the stored radiance: f32 (lossless), f16 or rgb9e5 (compact).
    #[arg(long, value_enum, default_value_t = EncodingArg::F16)]
    encoding: EncodingArg,
    /// Number of directions l = 2·4^k + 1: 9, 33, 129, 513, 2049 or 8193.
    #[arg(long, default_value_t = defaults::DIRECTIONS)]
    directions: usize,
    /// Rays per side N of every parallel subfield.
    #[arg(long, default_value_t = defaults::RESOLUTION)]
    resolution: u32,
    /// Tile size m (rays per tile side; divides N).
    #[arg(long, default_value_t = defaults::TILE)]
    tile: u32,
    /// Run exactly K iterations.
    #[arg(long, conflicts_with = "converge")]
    iterations: Option<u32>,
    /// Iterate until the unshot power is below EPS × the emitted power (default 1e-3, at most
    /// 1000 iterations).
    #[arg(long)]
    converge: Option<f64>,
    /// Texel edge in ray spacings (2/N in the normalised frame).
    #[arg(long, default_value_t = defaults::TEXEL_CELLS)]
    texel: f64,
    /// Deferred propagation: surfaces with less than this fraction of the unshot power wait.
    #[arg(long)]
    defer: Option<f64>,
    /// Perturb the direction set in the first ITERS iterations (remedy for holes; 0 = off).
    #[arg(long, default_value_t = defaults::PERTURB_ITERATIONS)]
    perturb: u32,
    /// Rotated copies of the direction set per perturbed iteration.
    #[arg(long, default_value_t = defaults::PERTURB_COUNT)]
    perturb_count: u32,
    /// After the last iteration, re-sample the mirrors' directional maps by
    /// backward ray tracing (sharper reflections when rendering from the rays).
    #[arg(long)]
    resample: bool,
    /// Gaussian filter of the Next maps, σ in texels (0 = off); by default σ = 1 where the
    /// scene's mirrors receive light and off elsewhere (docs/accuracy.md: where direct light is
    /// exact, as renders make it by default, the filter costs accuracy).
    #[arg(long)]
    filter: Option<f64>,
    /// Batches each pass is cut into (a power of two up to 1024; a batch holds at least 16
    /// directions, so l = 513 gets at most 32): the unit of work a worker leases and of the
    /// reduction, so part of the field's bits. More balance more workers, and cost more
    /// outputs through the store (docs/scaling.md, *Finer batches*).
    #[arg(long, default_value_t = defaults::PASS_BATCHES)]
    pass_batches: u32,
    /// Consecutive directions of a batch that one thread shoots into one field-sized buffer
    /// before adding it to the batch's sum (a power of two up to 16): fewer passes of that
    /// buffer through memory, and part of the field's bits (docs/scaling.md, *Stints*).
    #[arg(long, default_value_t = defaults::STINT_DIRECTIONS)]
    stint_directions: u32,
    /// Keep every snapshot resumable. By default, once a snapshot is committed the one before
    /// keeps only what renders read (its exact state is deleted): it still renders, and the last
    /// snapshot resumes, but the job's store is a third of the size or less (docs/store.md).
    #[arg(long)]
    keep_checkpoints: bool,
}

/// How to reach a coordinator.
#[derive(Args, Clone)]
pub struct ServerFlags {
    /// The coordinator: http://HOST:PORT, or https:// for TLS.
    #[arg(
        long,
        env = "VLF_SERVER",
        default_value = "http://127.0.0.1:7464",
        value_name = "URL"
    )]
    server: String,
    /// Bearer token, when the coordinator requires one.
    #[arg(long, env = "VLF_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// PEM of the CA that signed the coordinator's certificate.
    #[arg(long, value_name = "PEM")]
    ca_cert: Option<PathBuf>,
}

#[derive(Args)]
pub struct RunArgs {
    #[command(flatten)]
    propagate: PropagateArgs,
    /// Worker replicas, sharing the threads (each builds its own copy of the geometry; one worker
    /// with every core is the fastest on one machine).
    #[arg(long, default_value_t = 1)]
    workers: usize,
}

/// Where a field to look at comes from: a store and a job, or a coordinator and a job; which
/// snapshot. Shared by `render` and `view`.
#[derive(Args)]
pub struct FieldSource {
    /// Store holding the job (a directory, file:///PATH, s3://BUCKET/PREFIX); not with --server.
    #[arg(required_unless_present = "server")]
    store: Option<String>,
    /// Read the job from this coordinator instead of a store: `vlf render --server URL JOB …`.
    /// Given on the command line only: `VLF_SERVER`, which names the coordinator of `submit`,
    /// `watch` and the other commands that need one, would make the store's path a job id.
    #[arg(long, value_name = "URL")]
    server: Option<String>,
    /// Bearer token for --server.
    #[arg(long, env = "VLF_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// PEM of the CA that signed the coordinator's certificate.
    #[arg(long, value_name = "PEM")]
    ca_cert: Option<PathBuf>,
    /// Job id (default: the newest job of the store).
    job: Option<String>,
    /// Use the snapshot after K iterations (default: the final field of a finished job, else
    /// its last finished snapshot).
    #[arg(long, value_name = "K")]
    snapshot: Option<u32>,
}

#[derive(Args)]
pub struct RenderArgs {
    #[command(flatten)]
    source: FieldSource,
    #[command(flatten)]
    view: ViewFlags,
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
    /// Direct light: exact (shadow rays to the emitters per pixel, in place of the field's
    /// direct part; needs the job's snapshot 1), from the field, or auto: exact where the job
    /// has snapshot 1 (docs/accuracy.md measures both).
    #[arg(long, value_enum, default_value_t = DirectArg::Auto)]
    direct: DirectArg,
    /// Quadrature points per emitter for --direct exact.
    #[arg(long, default_value_t = vlf_core::direct::DEFAULT_SAMPLES)]
    direct_samples: u32,
    /// Draw with the GPU (wgpu; a software adapter such as Mesa's lavapipe will do), with the
    /// same sample positions and filter as the CPU, mirrors either way.
    #[arg(long)]
    gpu: bool,
    /// Dynamic objects (on the CPU, or with --gpu: the same gather and shadows in shaders).
    #[command(flatten)]
    objects: crate::objects::ObjectFlags,
    /// With --gpu: the objects' shadows on the static scene per texel, as `vlf view` draws
    /// them, rather than per pixel.
    #[arg(long, requires = "object")]
    object_shadows_per_texel: bool,
}

#[derive(Args)]
pub struct ViewArgs {
    #[command(flatten)]
    source: FieldSource,
    /// Where the walk starts, scene units (default: the middle of the scene).
    #[arg(long, value_parser = parse_vec3_arg, allow_hyphen_values = true)]
    eye: Option<glam::DVec3>,
    /// A point looked at from the start (default: along +z from the eye).
    #[arg(long, value_parser = parse_vec3_arg, allow_hyphen_values = true)]
    target: Option<glam::DVec3>,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 45.0)]
    fovy: f64,
    /// Window size WxH (physical pixels).
    #[arg(long, default_value = "1280x720", value_parser = parse_size_arg)]
    size: (u32, u32),
    /// Exposure in stops (pixel × 2^exposure); + and − change it while viewing.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    exposure: f64,
    /// How mirrors are drawn at the start (M cycles while viewing).
    #[arg(long, value_enum, default_value_t = SpecularArg::Rays)]
    specular: SpecularArg,
    /// Maximum number of mirror bounces when ray tracing.
    #[arg(long, default_value_t = 8)]
    depth: u32,
    /// Walking speed in scene units per second (default: a quarter of the scene's size); the
    /// wheel changes it while viewing.
    #[arg(long)]
    speed: Option<f64>,
    /// Quit after this many frames (scripted runs and benchmarks); prints the frame rate.
    #[arg(long)]
    frames: Option<u64>,
    /// Write the last frame to this image when quitting (.png tone-mapped, .pfm/.exr linear).
    #[arg(long, value_name = "IMAGE")]
    screenshot: Option<PathBuf>,
    /// Directory for the screenshots taken with P.
    #[arg(long, default_value = ".")]
    screenshot_dir: PathBuf,
    /// Draw as fast as possible instead of at the display's refresh rate.
    #[arg(long)]
    no_vsync: bool,
    /// Radiance kept on the GPU, in MB: the least recently used parts of the field make room
    /// for what the view needs.
    #[arg(long, default_value_t = 256.0)]
    cache_mb: f64,
    /// Direct light: exact (shadow rays to the emitters per pixel, the field's direct part
    /// streamed from snapshot 1), from the field, or auto: exact where the job has snapshot 1,
    /// the adapter is a real GPU and no albedo texture stands in the way.
    #[arg(long, value_enum, default_value_t = DirectArg::Auto)]
    direct: DirectArg,
    /// Quadrature points per emitter for exact direct light: fewer than `render`'s 64 by
    /// default, a quarter of the frame's cost at an accuracy the study cannot tell apart on the
    /// bundled scenes (docs/gpu.md).
    #[arg(long, default_value_t = vlf_core::direct::WALK_SAMPLES)]
    direct_samples: u32,
    /// A scripted walk over --frames: turn this many degrees (to the left) …
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    turn: f64,
    /// … while walking from --eye to this point.
    #[arg(long, value_parser = parse_vec3_arg, allow_hyphen_values = true)]
    to: Option<glam::DVec3>,
    /// Dynamic objects to walk among: Tab selects one, T F G H move it, R / Y lower and raise
    /// it, Z / X turn it.
    #[command(flatten)]
    objects: crate::objects::ObjectFlags,
    /// A scripted move over --frames: where each --object ends, in order (the translation its
    /// pose ends with, scene units), from its --object-at.
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3_arg, allow_hyphen_values = true, requires = "object")]
    object_to: Vec<glam::DVec3>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum DirectArg {
    /// Exact where it can be: when the job has snapshot 1 (and, on the GPU, no albedo texture
    /// is in the way).
    Auto,
    /// Read from the field like all other light.
    Field,
    /// Computed per pixel: sharp shadows, exact to the quadrature.
    Exact,
}

/// Where a camera stands and looks (scene units), shared by `render` and `study`; the image size
/// is each command's own (their defaults differ).
#[derive(Args, Clone, Copy)]
pub struct ViewFlags {
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
}

impl ViewFlags {
    /// The validated camera for an image of `size`.
    pub fn camera(&self, size: (u32, u32)) -> vlf_core::Result<vlf_core::render::Camera> {
        vlf_core::render::Camera::new(self.eye, self.target, self.up, self.fovy, size.0, size.1)
    }

    /// The up vector (validated by [`ViewFlags::camera`]).
    pub fn up(&self) -> glam::DVec3 {
        self.up
    }
}

#[derive(Args)]
pub struct JobsArgs {
    /// Store to list (a directory, file:///PATH, s3://BUCKET/PREFIX); not with --server.
    #[arg(required_unless_present = "server")]
    store: Option<String>,
    /// List the jobs of this coordinator instead (given on the command line only, as for
    /// `render`).
    #[arg(long, value_name = "URL", conflicts_with = "store")]
    server: Option<String>,
    /// Bearer token for --server.
    #[arg(long, env = "VLF_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// PEM of the CA that signed the coordinator's certificate.
    #[arg(long, value_name = "PEM")]
    ca_cert: Option<PathBuf>,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum SpecularArg {
    /// Look up the mirrors' directional radiance maps (the light field).
    Rays,
    /// Reflect eye rays until they reach a diffuse surface.
    Trace,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum EncodingArg {
    /// 32-bit floats: lossless.
    F32,
    /// 16-bit floats: relative error ≤ 2⁻¹¹.
    F16,
    /// Shared-exponent RGB (RGB9E5), 4 bytes per texel: relative error ≤ 2⁻⁹ of the largest channel.
    Rgb9e5,
}

fn parse_vec3_arg(s: &str) -> Result<glam::DVec3, String> {
    parse_vec3(s).map_err(|e| e.to_string())
}

fn parse_size_arg(s: &str) -> Result<(u32, u32), String> {
    parse_size(s).map_err(|e| e.to_string())
}

/// Runs an async command on a multi-threaded runtime.
fn block_on(command: impl std::future::Future<Output = Result<()>>) -> Result<()> {
    block_on_value(command)
}

/// Runs a future to its value on a multi-threaded runtime.
fn block_on_value<T>(future: impl std::future::Future<Output = Result<T>>) -> Result<T> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| anyhow::anyhow!("cannot start the async runtime: {e}"))?
        .block_on(future)
}

fn main() {
    vlf_proto::init_logging();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Propagate(args) => propagate::run(args),
        Command::Run(args) => run::run(args),
        Command::Render(args) => render::run(args),
        Command::View(args) => view::run(args),
        Command::Jobs(args) => render::jobs(args),
        Command::Serve(args) => block_on(vlf_server::cli::serve(args)),
        Command::Worker(args) => block_on(vlf_worker::cli::work(args)),
        Command::Submit(args) => block_on(remote::submit(args)),
        Command::Status(args) => block_on(remote::status(args)),
        Command::Watch(args) => block_on(remote::watch(args)),
        Command::Cancel(args) => block_on(remote::cancel(args)),
        Command::Health(args) => block_on(remote::health(args)),
        Command::Study(args) => study::run(args),
        Command::Bench(args) => bench::run(args),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    /// A job started from the command line without settings, from `submit` or from the
    /// service's messages gets the same options: `Options::recommended`, from one table.
    #[test]
    fn a_job_without_settings_gets_the_recommended_options() {
        for line in [
            &["vlf", "propagate", "scene.obj", "--store", "memory://"][..],
            &["vlf", "submit", "scene.obj"][..],
        ] {
            let spec = match Cli::parse_from(line).command {
                Command::Propagate(args) => args.job.spec().unwrap(),
                Command::Submit(args) => args.job.spec().unwrap(),
                _ => unreachable!("parsed as another command"),
            };
            assert_eq!(spec.options, vlf_core::propagate::Options::recommended(), "{line:?}");
        }
        let wire = vlf_proto::JobSpec::from_parameters(&Default::default()).unwrap();
        assert_eq!(wire.options, vlf_core::propagate::Options::recommended());
    }
}
