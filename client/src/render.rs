//! `vlf render` and `vlf jobs`: read a job's field back from a store and
//! render it; list a store's jobs.

use crate::{JobsArgs, RenderArgs, SpecularArg};
use anyhow::{Context, Result, bail};
use std::time::Instant;
use vlf_core::lookup::SpecularMode;
use vlf_core::render::Camera;
use vlf_store::{FieldJob, Job, JobId, JobState, Stage, Store};

pub fn run(args: RenderArgs) -> Result<()> {
    if !(1..=16).contains(&args.samples) {
        bail!("--samples must be 1..=16, got {}", args.samples);
    }
    if args.depth > 64 {
        bail!("--depth must be at most 64, got {}", args.depth);
    }
    let camera = Camera::new(args.eye, args.target, args.up, args.fovy, args.size.0, args.size.1)?;
    let mode = match args.specular {
        SpecularArg::Rays => SpecularMode::Rays,
        SpecularArg::Trace => SpecularMode::Trace { depth: args.depth },
    };
    let store = Store::open_existing(&args.store)?;
    let id = match &args.job {
        Some(id) => JobId::parse(id).map_err(anyhow::Error::msg)?,
        None => newest_job(&store)?
            .with_context(|| format!("no job in store {} (run `vlf propagate` first)", args.store))?,
    };
    let job = FieldJob::open(&store, &id).with_context(|| format!("cannot open job {id}"))?;
    let stage = match args.snapshot {
        Some(k) => Stage::Iteration(k),
        None => job.latest_stage(),
    };
    let started = Instant::now();
    let field = job
        .load(stage)
        .with_context(|| format!("cannot read {} of job {id}", describe(stage)))?;
    let loaded = started.elapsed().as_secs_f64();
    let image = field.render(&camera, args.samples, mode);
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

pub fn jobs(args: JobsArgs) -> Result<()> {
    let store = Store::open_existing(&args.store)?;
    let ids = Job::list(&store)?;
    if ids.is_empty() {
        println!("no job in {}", args.store);
    }
    for id in ids {
        let job = Job::open(&store, &id)?;
        let m = job.manifest();
        let state = match &m.state {
            JobState::Queued => "queued".to_string(),
            JobState::Propagating { iteration } => format!("propagating iteration {iteration}"),
            JobState::Finished => "finished".to_string(),
            JobState::Failed { message } => format!("failed: {message}"),
            JobState::Cancelled => "cancelled".to_string(),
        };
        println!(
            "{id}  {state:<24} snapshots {:?}  scene {}  {:?}",
            m.finished_iterations,
            &m.scene_hash[..12.min(m.scene_hash.len())],
            m.encoding
        );
    }
    Ok(())
}

/// The most recently created job of `store` (ties within a second: the last id).
fn newest_job(store: &Store) -> Result<Option<JobId>> {
    let mut newest: Option<(u64, JobId)> = None;
    for id in Job::list(store)? {
        let created = Job::open(store, &id)?.manifest().created;
        if newest.as_ref().is_none_or(|(t, _)| created >= *t) {
            newest = Some((created, id));
        }
    }
    Ok(newest.map(|(_, id)| id))
}

fn describe(stage: Stage) -> String {
    match stage {
        Stage::Iteration(k) => format!("snapshot {k}"),
        Stage::Field => "the final field".into(),
    }
}
