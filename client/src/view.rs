//! `vlf view`: a walkthrough of a job's field in a window (`vlf_viewer::view`).

use crate::{FieldSource, SpecularArg, ViewArgs};
use anyhow::{Context, Result, bail};
use glam::DVec3;
use vlf_core::field::LightField;
use vlf_core::lookup::{SpecularMode, ViewNeeds};
use vlf_store::{FieldJob, JobId, Stage, Store};
use vlf_viewer::{Loader, Switch, ViewOptions, Walk};

pub fn run(args: ViewArgs) -> Result<()> {
    if args.depth > 64 {
        bail!("--depth must be at most 64, got {}", args.depth);
    }
    if !args.exposure.is_finite() {
        bail!("--exposure must be finite, got {}", args.exposure);
    }
    if let Some(speed) = args.speed
        && !(speed.is_finite() && speed > 0.0)
    {
        bail!("--speed must be a positive number of scene units per second, got {speed}");
    }
    let specular = match args.specular {
        SpecularArg::Rays => SpecularMode::Rays,
        SpecularArg::Trace => SpecularMode::Trace { depth: args.depth },
    };
    // The job's description first: the store's, or its manifest, scene and the stage's summary
    // fetched from the coordinator into a memory store that the rest streams into.
    let mut remote = args.source.remote("view")?.map(Remote::connect).transpose()?;
    let (store, id, stage) = match &mut remote {
        None => {
            let opened = args.source.open("view", false)?;
            let job =
                FieldJob::open(&opened.store, &opened.id).with_context(|| format!("cannot open job {}", opened.id))?;
            let stage = opened.stage.unwrap_or_else(|| job.latest_stage());
            (opened.store, opened.id, stage)
        }
        Some(remote) => {
            let id = JobId::parse(&remote.job).map_err(anyhow::Error::msg)?;
            let status = remote.status()?;
            let stage = crate::remote::resolve_stage(&status, &remote.job, args.source.snapshot)?;
            let store = Store::open("memory://")?;
            let summary = relative(&id, &vlf_store::layout::summary(&id, stage)?);
            remote.fetch(vec!["manifest.blob".into(), "scene.blob".into(), summary], &store)?;
            (store, id, stage)
        }
    };
    let job = FieldJob::open(&store, &id).with_context(|| format!("cannot open job {id}"))?;
    // The geometry alone (no radiance read) places the walk and finds what the first view needs.
    let (geometry, _) = job.load_parts(stage, Some(&ViewNeeds::default()))?;
    // The scene spans about 2 / scale scene units (the VLF frame is [-1, 1]³).
    let n = geometry.scene.normalisation;
    let size = 2.0 / n.scale;
    let eye = args.eye.unwrap_or(n.center);
    let target = args.target.unwrap_or(eye + DVec3::Z);
    if eye == target || !(eye.is_finite() && target.is_finite()) {
        bail!("--eye and --target must be finite and apart, got {eye} and {target}");
    }
    let walk = Walk::new(eye, target, args.fovy, args.speed.unwrap_or(0.25 * size));
    let camera = walk.camera(args.size.0, args.size.1)?;
    let needs = geometry.view_needs(&camera, 1, specular);
    let first_keys = job.needed_keys(stage, &needs)?;
    // Every key of the stage, full: listed by the coordinator, or in the store.
    let stage_keys: Vec<String> = match &mut remote {
        Some(remote) => {
            let prefix = vlf_store::layout::job_prefix(&id);
            let names = remote.stage_blobs(stage)?;
            names.into_iter().map(|n| format!("{prefix}{n}")).collect()
        }
        None => store.list(&vlf_store::layout::stage_prefix(&id, stage)?)?,
    };
    if let Some(remote) = &mut remote {
        remote.fetch(first_keys.iter().map(|k| relative(&id, k)).collect(), &store)?;
    }
    let (first, _) = job.load_parts(stage, Some(&needs))?;
    println!(
        "first view: {} of the {} blobs of {} ({} surfaces, {} mirror tiles); the rest follows",
        first_keys.len(),
        stage_keys.len(),
        crate::render::describe(stage),
        needs.surfaces.len(),
        needs.mirror_tiles.len()
    );
    // The rest of the stage on a thread, over the same connection.
    let rest = {
        let (store, id) = (store.clone(), id.clone());
        let fetched: std::collections::BTreeSet<String> = first_keys.into_iter().collect();
        move || -> vlf_viewer::Loaded {
            let all = || -> Result<(LightField, String)> {
                if let Some(mut remote) = remote {
                    let names = stage_keys
                        .iter()
                        .filter(|k| !fetched.contains(*k))
                        .map(|k| relative(&id, k))
                        .collect();
                    remote.fetch(names, &store)?;
                }
                Ok((load(&store, &id, stage)?, title(&id, stage)))
            };
            all().map(Some).map_err(|e| format!("{e:#}"))
        }
    };
    let loader = snapshot_loader(&args.source, store, id.clone(), stage);
    let options = ViewOptions {
        title: title(&id, stage),
        size: args.size,
        walk,
        exposure: args.exposure,
        mirrors: specular.into(),
        vsync: !args.no_vsync,
        frames: args.frames,
        screenshot_dir: args.screenshot_dir,
        screenshot_at_exit: args.screenshot,
        loader: Some(loader),
        rest: Some(Box::new(rest)),
    };
    let stats = vlf_viewer::view(first, options)?;
    if stats.frames > 0 {
        println!(
            "{} frames in {:.2} s ({:.1} fps) on {}; first frame after {:.2} s",
            stats.frames,
            stats.seconds,
            stats.frames as f64 / stats.seconds.max(1e-9),
            stats.adapter,
            stats.first_frame_seconds.unwrap_or(f64::NAN)
        );
    }
    for path in &stats.screenshots {
        println!("screenshot → {}", path.display());
    }
    Ok(())
}

/// `key` relative to the job's prefix (how the tile service names blobs).
fn relative(id: &JobId, key: &str) -> String {
    let prefix = vlf_store::layout::job_prefix(id);
    key.strip_prefix(&prefix).unwrap_or(key).to_string()
}

/// One connection to the coordinator (and the runtime it lives on), kept from the job's
/// description to the rest of the stage.
struct Remote {
    runtime: tokio::runtime::Runtime,
    clients: vlf_proto::Clients,
    job: String,
}

impl Remote {
    fn connect((target, job): (vlf_proto::Target, String)) -> Result<Remote> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .context("cannot start the async runtime")?;
        let clients = runtime.block_on(crate::remote::connect(&target))?;
        Ok(Remote { runtime, clients, job })
    }

    fn status(&mut self) -> Result<vlf_proto::v1::JobStatus> {
        self.runtime
            .block_on(crate::remote::job_status(&mut self.clients, &self.job))
    }

    fn stage_blobs(&mut self, stage: Stage) -> Result<Vec<String>> {
        self.runtime
            .block_on(crate::remote::stage_blobs(&mut self.clients, &self.job, stage))
    }

    fn fetch(&mut self, names: Vec<String>, store: &Store) -> Result<u64> {
        self.runtime
            .block_on(crate::remote::fetch_into(&mut self.clients, &self.job, names, store))
    }
}

fn title(id: &JobId, stage: Stage) -> String {
    format!("vlf view {id} {}", crate::render::describe(stage))
}

fn load(store: &Store, id: &JobId, stage: Stage) -> Result<LightField> {
    let job = FieldJob::open(store, id).with_context(|| format!("cannot open job {id}"))?;
    job.load(stage)
        .with_context(|| format!("cannot read {} of job {id}", crate::render::describe(stage)))
}

/// The stage one `switch` away from `current`, in the order snapshot 0, 1, …, then the final
/// field (`finished` lists the finished snapshots in order); `None` past either end.
fn step(current: Stage, finished: &[u32], field: bool, switch: Switch) -> Option<Stage> {
    let mut order: Vec<Stage> = finished.iter().map(|&k| Stage::Iteration(k)).collect();
    if field {
        order.push(Stage::Field);
    }
    let here = order.iter().position(|&s| s == current);
    let next = match (switch, here) {
        (Switch::Latest, _) => order.last().copied(),
        (Switch::Previous, Some(i)) => i.checked_sub(1).map(|i| order[i]),
        (Switch::Next, Some(i)) => order.get(i + 1).copied(),
        // The stage shown is gone (the job was resumed elsewhere): start again from the newest.
        (_, None) => order.last().copied(),
    };
    next.filter(|&s| s != current)
}

/// Loads the snapshots around the one shown: from the store, re-reading the job's manifest each
/// time (a running job finishes new ones), or fetched again from `--server`.
fn snapshot_loader(source: &FieldSource, store: Store, id: JobId, mut current: Stage) -> Loader {
    let remote = source.server.clone().map(|url| vlf_proto::Target {
        url,
        token: source.token.clone(),
        ca_cert: source.ca_cert.clone(),
    });
    Box::new(move |switch| {
        let mut found = || -> Result<Option<(LightField, String)>> {
            let (finished, done) = match &remote {
                Some(target) => {
                    let status = crate::block_on_value(crate::remote::status_of(target, id.as_str()))?;
                    (status.snapshots.clone(), crate::remote::is_finished(&status))
                }
                None => {
                    let job = FieldJob::open(&store, &id)?;
                    let m = job.job().manifest();
                    (m.finished_iterations.clone(), job.latest_stage() == Stage::Field)
                }
            };
            let Some(next) = step(current, &finished, done, switch) else {
                return Ok(None);
            };
            let field = match &remote {
                Some(target) => {
                    let k = match next {
                        Stage::Iteration(k) => Some(k),
                        Stage::Field => None,
                    };
                    let (fetched, stage) = crate::block_on_value(crate::remote::fetch_job(target, id.as_str(), k))?;
                    load(&fetched, &id, stage)?
                }
                None => load(&store, &id, next)?,
            };
            current = next;
            Ok(Some((field, title(&id, next))))
        };
        found().map_err(|e| format!("{e:#}"))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use vlf_core::propagate::{Options, Propagation, Stop};
    use vlf_core::psf::GridSize;

    /// A job in a `memory://` store with snapshots 0..=2, running (no final field yet).
    fn running_job() -> (Store, JobId, Propagation) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
        let scene = crate::propagate::import(&path).unwrap();
        let options = Options {
            directions: 9,
            grid: GridSize::new(16, 8).unwrap(),
            stop: Stop::Iterations(3),
            ..Options::default()
        };
        let store = Store::open("memory://").unwrap();
        let mut p = Propagation::new(scene, options).unwrap();
        let mut job = FieldJob::create(&store, &p, vlf_store::blob::Encoding::F32).unwrap();
        for _ in 0..2 {
            p.step(|_| {});
            job.write_snapshot(&p).unwrap();
        }
        (store, job.id().clone(), p)
    }

    fn source() -> FieldSource {
        FieldSource {
            store: None,
            server: None,
            token: None,
            ca_cert: None,
            job: None,
            snapshot: None,
        }
    }

    #[test]
    fn the_loader_walks_a_running_jobs_snapshots() {
        let (store, id, mut p) = running_job();
        let mut loader = snapshot_loader(&source(), store.clone(), id.clone(), Stage::Iteration(1));
        let mut stage_of = |switch| {
            loader(switch)
                .unwrap()
                .map(|(field, title): (LightField, String)| (field.stats.len(), title))
        };
        let (iterations, title) = stage_of(Switch::Next).expect("snapshot 2");
        assert_eq!(iterations, 2);
        assert!(title.ends_with("snapshot 2"), "{title}");
        assert!(stage_of(Switch::Next).is_none(), "nothing after the newest snapshot");
        assert_eq!(stage_of(Switch::Previous).unwrap().0, 1);
        assert_eq!(stage_of(Switch::Previous).unwrap().0, 0);
        assert!(stage_of(Switch::Previous).is_none());
        // The job goes on: the next snapshot and then the final field appear.
        let mut job = FieldJob::open(&store, &id).unwrap();
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
        assert_eq!(stage_of(Switch::Latest).unwrap().0, 3);
        job.finish(&p.field_now(), false).unwrap();
        let (_, title) = stage_of(Switch::Next).expect("the final field");
        assert!(title.ends_with("the final field"), "{title}");
    }

    #[test]
    fn steps_through_snapshots_then_the_field() {
        let it = Stage::Iteration;
        let finished = [0, 1, 2, 3];
        assert_eq!(step(it(2), &finished, false, Switch::Previous), Some(it(1)));
        assert_eq!(step(it(2), &finished, false, Switch::Next), Some(it(3)));
        assert_eq!(step(it(3), &finished, false, Switch::Next), None);
        assert_eq!(step(it(3), &finished, true, Switch::Next), Some(Stage::Field));
        assert_eq!(step(it(0), &finished, true, Switch::Previous), None);
        assert_eq!(step(Stage::Field, &finished, true, Switch::Previous), Some(it(3)));
        assert_eq!(step(it(1), &finished, true, Switch::Latest), Some(Stage::Field));
        assert_eq!(step(it(1), &finished, false, Switch::Latest), Some(it(3)));
        assert_eq!(step(it(3), &finished, false, Switch::Latest), None);
        // A stage no longer listed: the newest.
        assert_eq!(step(it(9), &finished, false, Switch::Previous), Some(it(3)));
    }
}
