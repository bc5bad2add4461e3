//! `vlf render` and `vlf jobs`: read a job's field back from a store and
//! render it; list a store's jobs.

use crate::{DirectArg, FieldSource, JobsArgs, RenderArgs, SpecularArg};
use anyhow::{Context, Result, bail};
use std::time::Instant;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::dynamic::view::render_with_objects;
use vlf_core::lookup::SpecularMode;
use vlf_core::render::Bvh;
use vlf_proto::Target;
use vlf_store::{FieldJob, Job, JobId, JobState, Stage, Store};

pub fn run(args: RenderArgs) -> Result<()> {
    if !(1..=16).contains(&args.samples) {
        bail!("--samples must be 1..=16, got {}", args.samples);
    }
    if args.depth > 64 {
        bail!("--depth must be at most 64, got {}", args.depth);
    }
    let camera = args.view.camera(args.size)?;
    let mode = match args.specular {
        SpecularArg::Rays => SpecularMode::Rays,
        SpecularArg::Trace => SpecularMode::Trace { depth: args.depth },
    };
    if args.object_shadows_per_texel && !args.gpu {
        bail!("--object-shadows-per-texel draws as vlf view does, on the GPU: add --gpu");
    }
    if args.direct != DirectArg::Field && !(1..=65536).contains(&args.direct_samples) {
        bail!("--direct-samples must be 1..=65536, got {}", args.direct_samples);
    }
    // What can be refused without reading anything is refused before the store is read.
    vlf_core::render::Image::check_output(&args.out, args.exposure)?;
    args.objects.check()?;
    let Opened {
        store,
        id,
        stage,
        remote,
    } = args.source.open("render")?;
    let job = FieldJob::open(&store, &id).with_context(|| format!("cannot open job {id}"))?;
    let stage = match stage {
        Some(stage) => stage,
        None => shown_stage(&job)?,
    };
    // Exact direct light exchanges the field's direct part (snapshot 1's) for the exact one.
    // Snapshot 0 is the emitters' light alone: it has no direct part, so nothing to exchange.
    // Auto asks for snapshot 1 and does without it; Exact requires it.
    let exact_direct = args.direct == DirectArg::Exact;
    let try_exact = match (args.direct, stage) {
        (DirectArg::Exact, Stage::Iteration(0)) => return Err(no_exact_at_snapshot_zero("render")),
        (DirectArg::Field, _) | (_, Stage::Iteration(0)) => false,
        _ => true,
    };
    let started = Instant::now();
    let cannot_read = || format!("cannot read {} of job {id}", describe(stage));
    // Snapshot 1 from the same store is read on the same geometry, built once; from a
    // coordinator it is fetched into a store of its own.
    let (field, first) = match (try_exact, &remote) {
        (true, None) => {
            let mut loaded = job
                .load_each(&[stage, Stage::Iteration(1)])
                .with_context(cannot_read)?
                .into_iter();
            (loaded.next(), loaded.next())
        }
        _ => (Some(job.load(stage)), None),
    };
    let mut field = field.context("no field read")?.with_context(cannot_read)?;
    if try_exact {
        let first = match (first, &remote) {
            (Some(first), _) => first.map_err(anyhow::Error::from),
            (None, Some((target, job))) => crate::block_on_value(crate::remote::fetch_job(target, job, Some(1)))
                .and_then(|(first, _)| {
                    FieldJob::open(&first, &id)
                        .with_context(|| format!("cannot open job {id}"))?
                        .load(Stage::Iteration(1))
                        .map_err(anyhow::Error::from)
                }),
            (None, None) => job.load(Stage::Iteration(1)).map_err(anyhow::Error::from),
        };
        match first {
            Ok(first) => field.use_exact_direct(&first, args.direct_samples)?,
            Err(e) if exact_direct => {
                return Err(e).with_context(|| format!("exact direct light needs snapshot 1 of job {id}"));
            }
            Err(e) => tracing::warn!("no snapshot 1 of job {id} ({e:#}): direct light from the field"),
        }
        // What the GPU cannot draw exactly (albedo textures) auto draws with the field's.
        if args.gpu
            && !exact_direct
            && let Err(e) = vlf_viewer::direct::check_scene(&field.scene)
        {
            tracing::warn!(%e, "direct light from the field");
            field.exact_direct = None;
        }
    }
    tracing::info!(exact = field.exact_direct.is_some(), "direct light");
    let loaded = started.elapsed().as_secs_f64();
    let objects = &args.objects;
    let image = match objects.is_empty() {
        false => {
            let bvh = Bvh::build(&field.scene);
            let placed = objects.place(args.view.up(), &field.scene, &bvh)?;
            let mut gatherer = Gatherer::with_directions(&field, &bvh, &placed, mode, objects.directions(&field))
                .context("--object-directions")?
                .with_shadow_samples(objects.object_shadow_samples);
            if field.exact_direct.is_some() {
                // The objects' shadows and exact direct light share their emitter points.
                gatherer = gatherer.with_direct_samples(args.direct_samples)?;
            }
            // The gather sees the objects' shadows, and the shadows give back the objects'
            // light: on the GPU its passes compute them, on the CPU the gatherer does.
            let gatherer = match args.gpu {
                true => gatherer.with_gpu_lighting(true, true),
                false => gatherer.with_gather_shadows(true).with_bounce_light(true),
            };
            if args.gpu {
                let gpu = vlf_viewer::Gpu::new()?;
                tracing::info!(adapter = %gpu.describe(), "rendering on the GPU");
                let mut renderer = vlf_viewer::FieldRenderer::with_objects(&gpu, &field, &gatherer)?;
                if args.object_shadows_per_texel {
                    renderer.shadows_per_texel(&gpu, &field)?;
                }
                vlf_viewer::render(&gpu, &renderer, &camera, args.samples, mode)?
            } else {
                render_with_objects(&gatherer, &bvh, &camera, args.samples)
            }
        }
        true if args.gpu => gpu_render(&field, &camera, args.samples, mode)?,
        true => {
            // Exact direct light costs a second or more per frame: show the rows going by.
            let bar = indicatif::ProgressBar::new(camera.height as u64);
            bar.set_style(
                indicatif::ProgressStyle::with_template("rendering [{bar:40}] {pos}/{len} rows {elapsed}")
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                    .progress_chars("=> "),
            );
            let image = field.render_with_progress(&camera, args.samples, mode, &|| bar.inc(1));
            bar.finish_and_clear();
            image
        }
    };
    image
        .save(&args.out, args.exposure)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    println!(
        "rendered {} of job {id}, {}x{}, in {:.2} s ({loaded:.2} s reading the store) → {}",
        describe(stage),
        args.size.0,
        args.size.1,
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
    Ok(())
}

/// `--gpu`: the same view drawn by wgpu.
fn gpu_render(
    field: &vlf_core::field::LightField,
    camera: &vlf_core::render::Camera,
    samples: u32,
    mode: SpecularMode,
) -> Result<vlf_core::render::Image> {
    let gpu = vlf_viewer::Gpu::new()?;
    tracing::info!(adapter = %gpu.describe(), "rendering on the GPU");
    let renderer = vlf_viewer::FieldRenderer::new(&gpu, field)?;
    Ok(vlf_viewer::render(&gpu, &renderer, camera, samples, mode)?)
}

/// A job opened for looking at.
pub struct Opened {
    pub store: Store,
    pub id: JobId,
    /// The stage asked for, if any.
    pub stage: Option<Stage>,
    /// With `--server`: the coordinator and the job, for fetching more of it (snapshot 1).
    pub remote: Option<(Target, String)>,
}

impl FieldSource {
    /// With `--server`: the coordinator and the job (with `--server` the one positional argument
    /// is the job).
    pub fn remote(&self, command: &str) -> Result<Option<(Target, String)>> {
        let Some(server) = &self.server else {
            return Ok(None);
        };
        let job = match (&self.store, &self.job) {
            (Some(job), None) | (None, Some(job)) => job.clone(),
            _ => bail!("with --server, give the job and no store: vlf {command} --server URL JOB"),
        };
        let target = Target {
            url: server.clone(),
            token: self.token.clone(),
            ca_cert: self.ca_cert.clone(),
        };
        Ok(Some((target, job)))
    }

    /// Opens the job: from the store, or the asked stage fetched from `--server`. `command`
    /// names the command in messages.
    pub fn open(&self, command: &str) -> Result<Opened> {
        match (self.remote(command)?, &self.store) {
            (Some((target, job)), _) => {
                let (store, stage) = crate::block_on_value(crate::remote::fetch_job(&target, &job, self.snapshot))?;
                Ok(Opened {
                    store,
                    id: JobId::parse(&job).map_err(anyhow::Error::msg)?,
                    stage: Some(stage),
                    remote: Some((target, job)),
                })
            }
            (None, Some(url)) => {
                let store = Store::open_existing(url)?;
                let id = match &self.job {
                    Some(id) => JobId::parse(id).map_err(anyhow::Error::msg)?,
                    None => {
                        newest_job(&store)?.with_context(|| format!("no job in store {url} (run `vlf run` first)"))?
                    }
                };
                Ok(Opened {
                    store,
                    id,
                    stage: self.snapshot.map(Stage::Iteration),
                    remote: None,
                })
            }
            (None, None) => bail!("give a store, or --server and a job"),
        }
    }
}

pub fn jobs(args: JobsArgs) -> Result<()> {
    let url = match (&args.server, &args.store) {
        (Some(server), _) => {
            return crate::block_on(crate::remote::jobs(Target {
                url: server.clone(),
                token: args.token.clone(),
                ca_cert: args.ca_cert.clone(),
            }));
        }
        (None, Some(url)) => url,
        (None, None) => bail!("give a store, or --server"),
    };
    let store = Store::open_existing(url)?;
    let ids = Job::list(&store)?;
    if ids.is_empty() {
        println!("no job in {url}");
    }
    for id in ids {
        let job = Job::open(&store, &id)?;
        let m = job.manifest();
        let state = m.state.to_string();
        // A finished job's digest (see `LightField::digest`), to compare with another run's.
        // A summary that cannot be read is said so on its job's line; the others are listed.
        let digest = match m.state {
            JobState::Finished => match vlf_store::Summary::read(&job, Stage::Field) {
                Ok(summary) => summary.digest.map(|d| format!("  digest {d}")).unwrap_or_default(),
                Err(e) => format!("  digest unreadable: {e}"),
            },
            _ => String::new(),
        };
        println!(
            "{id}  {state:<24} snapshots {:?}  scene {}  {:?}{digest}",
            m.finished_iterations,
            &m.scene_hash[..12.min(m.scene_hash.len())],
            m.encoding
        );
    }
    Ok(())
}

/// The most recently created job of `store`. Jobs are dated to the second: two created in the
/// newest second are not told apart by a guess, the caller is asked to name one.
fn newest_job(store: &Store) -> Result<Option<JobId>> {
    let mut newest: Vec<(u64, JobId)> = Vec::new();
    for id in Job::list(store)? {
        let created = Job::open(store, &id)?.manifest().created;
        match newest.first() {
            Some((t, _)) if created < *t => {}
            Some((t, _)) if created == *t => newest.push((created, id)),
            _ => newest = vec![(created, id)],
        }
    }
    match &newest[..] {
        [] => Ok(None),
        [(_, id)] => Ok(Some(id.clone())),
        several => {
            let ids: Vec<String> = several.iter().map(|(_, id)| id.to_string()).collect();
            bail!(
                "the newest jobs of the store were created in the same second ({}): name the one to \
                 show after the store",
                ids.join(", ")
            )
        }
    }
}

/// The stage a look at `job` shows unless told: its final field, else its last finished
/// snapshot; an error naming the job's state while none is finished.
pub fn shown_stage(job: &FieldJob) -> Result<Stage> {
    job.latest_stage().with_context(|| {
        format!(
            "job {} has no finished snapshot yet ({})",
            job.id(),
            job.job().manifest().state
        )
    })
}

/// `--direct exact` asked of snapshot 0, refused: `command` (render, view) names the way out.
pub fn no_exact_at_snapshot_zero(command: &str) -> anyhow::Error {
    anyhow::anyhow!(
        "--direct exact: snapshot 0 is the emitters' own light, before any light reached a surface, \
         so it has no direct light to compute exactly: {command} it with --direct field"
    )
}

pub fn describe(stage: Stage) -> String {
    match stage {
        Stage::Iteration(k) => format!("snapshot {k}"),
        Stage::Field => "the final field".into(),
    }
}
