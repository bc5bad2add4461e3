//! `vlf propagate`: import a scene (or resume a job), propagate its light
//! field iteration by iteration, and write every iteration's snapshot and the
//! final field into a job of a store.

use crate::{EncodingArg, JobFlags, PropagateArgs};
use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use std::time::Instant;
use vlf_core::propagate::Propagation;
use vlf_core::scene::{ImportOptions, Scene, load_scene};
use vlf_proto::JobSpec;
use vlf_proto::v1::{Encoding as WireEncoding, Parameters};
use vlf_store::{FieldJob, JobId, SnapshotWriter, Stage, Store, Summary};

pub fn run(args: PropagateArgs) -> Result<()> {
    let pool = thread_pool(&args)?;
    let started = Instant::now();
    let (mut job, mut prop) = start(&args, &pool)?;
    let setup_seconds = started.elapsed().as_secs_f64();
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
    // Each snapshot is written while the next iteration runs; `store_seconds` is the time the
    // propagation waited for the store (encoding a snapshot, and the one before it to be
    // committed).
    let mut store_seconds = 0.0;
    let mut snapshots = SnapshotWriter::new();
    let outcome = pool.install(|| -> Result<()> {
        while !prop.finished() {
            let k = prop.iterations_done();
            bar.set_prefix(format!("iteration {}", k + 1));
            bar.set_message(format!("unshot {:.2e}", prop.unshot_fraction()));
            bar.set_position(0);
            prop.step(|p| {
                bar.set_length(p.directions_total as u64);
                bar.set_position(p.directions_done as u64);
            });
            let t = Instant::now();
            snapshots
                .write(&mut job, &prop)
                .with_context(|| format!("cannot write snapshot {} or {}", k, k + 1))?;
            store_seconds += t.elapsed().as_secs_f64();
        }
        let t = Instant::now();
        snapshots
            .finish(&mut job)
            .with_context(|| format!("cannot write snapshot {}", prop.iterations_done()))?;
        store_seconds += t.elapsed().as_secs_f64();
        Ok(())
    });
    bar.finish_and_clear();
    outcome?;

    let field_bytes = prop.field_bytes();
    // Read at the end, after everything that may build subfields.
    let subfields = prop.subfields.clone();
    let geometry = format!(
        "{} polygons in {} charts, {} texels",
        prop.scene.surfaces.len(),
        prop.atlas.charts.len(),
        prop.atlas.texels
    );
    let mut field = pool.install(|| prop.into_field());
    // As the job was created, or asked for now: whoever finishes a job does what was asked.
    let resample = job.job().manifest().resample || args.job.resample;
    if resample {
        pool.install(|| field.resample_mirrors(8));
    }
    let t = Instant::now();
    pool.install(|| job.finish(&field, resample))
        .context("cannot write the final field")?;
    store_seconds += t.elapsed().as_secs_f64();

    let summary = job.summary(Stage::Field)?;
    print_summary(&args, &job, &summary, started, store_seconds, Some(field_bytes))?;
    // Where the time went: set-up (import or resume, charts, subfields, discrete areas, snapshot
    // 0), propagation, and the store's writes after it.
    let total = started.elapsed().as_secs_f64();
    println!(
        "  time split      setup_s={setup_seconds:.2} propagate_s={:.2} store_s={store_seconds:.2}",
        (total - setup_seconds - store_seconds).max(0.0)
    );
    println!("  geometry        {geometry}");
    let subfields = subfields.memory();
    if let Some(budget) = subfields.budget {
        println!(
            "  subfields       budget {:.1} MB, at most {:.1} MB held at once, {} built for {} directions",
            budget as f64 / 1e6,
            subfields.peak as f64 / 1e6,
            subfields.builds,
            job.options().directions
        );
    }
    Ok(())
}

/// Opens the job to work on: a new one for `args.scene` (snapshot 0 written), or the job named by
/// `--resume` at its last finished snapshot. Prints the job id.
pub fn start(args: &PropagateArgs, pool: &rayon::ThreadPool) -> Result<(FieldJob, Propagation)> {
    let (job, prop) = match &args.resume {
        Some(id) => {
            let id = JobId::parse(id).map_err(anyhow::Error::msg)?;
            if args.job.given_beyond_resample()? {
                bail!(
                    "--resume goes on with the job's own parameters: drop the job's flags (only \
                     --threads, --subfield-memory and --resample apply)"
                );
            }
            let store = Store::open_existing(&args.store)?;
            let mut job = FieldJob::open(&store, &id).with_context(|| format!("cannot open job {id}"))?;
            let prop = pool
                .install(|| job.resume_within(args.subfield_budget()))
                .with_context(|| format!("cannot resume job {id}"))?;
            println!(
                "resuming job {id} in {} after {} iterations",
                args.store,
                prop.iterations_done()
            );
            (job, prop)
        }
        None => {
            let spec = args.job.spec()?;
            let path = args
                .scene
                .as_ref()
                .context("a scene is needed unless --resume is given")?;
            let scene = import(path)?;
            tracing::info!(
                surfaces = scene.surfaces.len(),
                materials = scene.materials.len(),
                "scene imported"
            );
            let prop = pool
                .install(|| Propagation::with_subfield_budget(scene, spec.options, args.subfield_budget()))
                .context("cannot set up the light field")?;
            let store = Store::open(&args.store)?;
            let mut job = pool.install(|| FieldJob::create(&store, &prop, spec.encoding))?;
            if !spec.keep_checkpoints {
                job.set_compact(true)?;
            }
            // Recorded, so that whoever resumes the job (`vlf run --resume`, a coordinator)
            // finishes it as asked.
            if spec.resample {
                job.set_resample(true)?;
            }
            println!("job {} in {}", job.id(), args.store);
            (job, prop)
        }
    };
    Ok((job, prop))
}

/// Imports a scene file (OBJ with its MTL, or glTF 2.0 `.gltf`/`.glb`: the extension decides),
/// logging the importer's warnings.
pub fn import(path: &std::path::Path) -> Result<Scene> {
    let (scene, warnings) =
        load_scene(path, &ImportOptions::default()).with_context(|| format!("cannot import {}", path.display()))?;
    for w in &warnings {
        tracing::warn!("{w}");
    }
    Ok(scene)
}

/// Prints what a finished run did: time, iterations, unshot fraction, energy balance, memory
/// and the store's figures.
pub fn print_summary(
    args: &PropagateArgs,
    job: &FieldJob,
    summary: &Summary,
    started: Instant,
    store_seconds: f64,
    field_bytes: Option<usize>,
) -> Result<()> {
    let (stored_field, stored_job) = job.stored_bytes(Stage::Field)?;
    let elapsed = started.elapsed().as_secs_f64();
    let balance = summary
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
    let what = match &args.scene {
        Some(path) => path.display().to_string(),
        None => format!("job {}", job.id()),
    };
    if store_seconds.is_nan() {
        println!("propagated {what} in {elapsed:.2} s");
    } else {
        println!("propagated {what} in {elapsed:.2} s ({store_seconds:.2} s writing the store)");
    }
    println!("  iterations      {}", summary.iterations);
    println!("  unshot fraction {:.3e}", summary.unshot_fraction);
    println!("  energy balance  {balance:.1e} (worst relative mismatch of an iteration)");
    if let Some(bytes) = field_bytes {
        println!("  field memory    {:.1} MB", bytes as f64 / 1e6);
    }
    println!(
        "  stored field    {:.2} MB compressed ({:?}); whole job with snapshots {:.2} MB",
        stored_field as f64 / 1e6,
        job.job().manifest().encoding,
        stored_job as f64 / 1e6
    );
    if let Some(peak) = peak_memory_kb() {
        println!("  peak memory     {:.1} MB", peak as f64 / 1024.0);
    }
    if let Some(digest) = &summary.digest {
        // What `vlf status` shows for the same field computed by a service.
        println!("  digest          {digest}");
    }
    println!("  job             {} in {}", job.id(), args.store);
    Ok(())
}

impl PropagateArgs {
    /// `--subfield-memory` in bytes.
    pub fn subfield_budget(&self) -> Option<usize> {
        self.subfield_memory
            .map(|b| usize::try_from(b.as_u64()).unwrap_or(usize::MAX))
    }
}

/// The thread pool `--threads` asks for (default: all cores).
pub fn thread_pool(args: &PropagateArgs) -> Result<rayon::ThreadPool> {
    let threads = args.threads.unwrap_or(0);
    if args.threads == Some(0) || threads > 1024 {
        bail!("--threads must be between 1 and 1024");
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("cannot start the worker threads")
}

impl JobFlags {
    /// The job settings the flags ask for, as the API carries them (one meaning for `propagate`,
    /// `run` and `submit`).
    pub fn parameters(&self) -> Result<Parameters> {
        let directions = u32::try_from(self.directions).map_err(|_| anyhow::anyhow!("--directions is absurd"))?;
        Ok(Parameters {
            directions: Some(directions),
            resolution: Some(self.resolution),
            tile: Some(self.tile),
            iterations: self.iterations,
            converge: self.converge,
            texel: Some(self.texel),
            defer: self.defer,
            perturb: Some(self.perturb),
            perturb_count: Some(self.perturb_count),
            filter: self.filter,
            pass_batches: Some(self.pass_batches),
            stint_directions: Some(self.stint_directions),
            resample: self.resample,
            keep_checkpoints: self.keep_checkpoints,
            encoding: match self.encoding {
                EncodingArg::F32 => WireEncoding::F32,
                EncodingArg::F16 => WireEncoding::F16,
                EncodingArg::Rgb9e5 => WireEncoding::Rgb9e5,
            } as i32,
        })
    }

    /// Whether a flag other than `--resample` asks for something other than its default. A
    /// resumed job goes on with its own parameters, so such a flag would be ignored in silence.
    pub fn given_beyond_resample(&self) -> Result<bool> {
        use clap::{Args, FromArgMatches};
        let command = JobFlags::augment_args(clap::Command::new("defaults"));
        let defaults = JobFlags::from_arg_matches(&command.try_get_matches_from(["defaults"])?)?;
        let (mut mine, theirs) = (self.parameters()?, defaults.parameters()?);
        mine.resample = theirs.resample;
        Ok(mine != theirs)
    }

    /// The validated settings.
    pub fn spec(&self) -> Result<JobSpec> {
        Ok(JobSpec::from_parameters(&self.parameters()?)?)
    }
}

/// Peak resident memory of this process (Linux), in KiB.
fn peak_memory_kb() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}
