//! `vlf view`: a walkthrough of a job's field in a window (`vlf_viewer::view`), its radiance
//! streamed part by part as the view needs it (`vlf_viewer::stream`): read straight from a
//! store, or fetched over a coordinator's tile stream (`--server`).

use crate::{DirectArg, SpecularArg, ViewArgs};
use anyhow::{Context, Result, bail};
use glam::DVec3;
use std::sync::Arc;
use std::time::Duration;
use vlf_core::direct::Emitters;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::parts::PartCatalog;
use vlf_store::{FieldJob, JobId, Stage, StageParts, Store};
use vlf_viewer::direct::DirectSource;
use vlf_viewer::{Loader, PartSource, StreamConfig, Switch, ViewOptions, Walk};

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
    if !(args.cache_mb.is_finite() && args.cache_mb > 0.0 && args.cache_mb <= 1e6) {
        bail!(
            "--cache-mb must be a positive number of megabytes (at most 10⁶), got {}",
            args.cache_mb
        );
    }
    if !args.turn.is_finite() {
        bail!("--turn must be a finite number of degrees, got {}", args.turn);
    }
    if (args.turn != 0.0 || args.to.is_some()) && args.frames.is_none() {
        bail!("--turn and --to script a walk over --frames N; give --frames");
    }
    if !args.object_to.is_empty() && args.frames.is_none() {
        bail!("--object-to scripts the objects' moves over --frames N; give --frames");
    }
    if args.object_to.len() > args.objects.object.len() {
        bail!(
            "{} --object-to for {} --object: at most one per object",
            args.object_to.len(),
            args.objects.object.len()
        );
    }
    args.objects.check()?;
    let specular = match args.specular {
        SpecularArg::Rays => SpecularMode::Rays,
        SpecularArg::Trace => SpecularMode::Trace { depth: args.depth },
    };
    // The stage's parts: read from the store, or fetched from the coordinator (which first
    // sends the job's manifest, scene and the stage's summary).
    let (source, stage, id): (Box<dyn StageSource>, Stage, JobId) = match args.source.remote("view")? {
        None => {
            let opened = args.source.open("view")?;
            let job =
                FieldJob::open(&opened.store, &opened.id).with_context(|| format!("cannot open job {}", opened.id))?;
            let stage = match opened.stage {
                Some(stage) => stage,
                None => crate::render::shown_stage(&job)?,
            };
            let parts = StageParts::open(job, stage)
                .with_context(|| format!("cannot read {} of job {}", crate::render::describe(stage), opened.id))?;
            (Box::new(StoreParts::new(parts, None)?), stage, opened.id)
        }
        Some((target, job)) => {
            let mut remote = Remote::new(target, job)?;
            let status = remote.call(|r, c| {
                let (mut c, job) = (c.clone(), r.job.clone());
                Box::pin(async move { crate::remote::job_status(&mut c, &job).await })
            })?;
            let stage = crate::remote::resolve_stage(&status, &remote.job, args.source.snapshot)?;
            let id = JobId::parse(&remote.job).map_err(anyhow::Error::msg)?;
            (Box::new(RemoteParts::open(remote, stage, None)?), stage, id)
        }
    };
    let geometry = source.geometry().clone();
    let remote = args.source.remote("view")?.map(|(target, _)| target);
    // Snapshot 0 is the emitters' light alone: exact direct light has nothing to exchange there.
    let (exact, first) = match (stage, args.direct) {
        (Stage::Iteration(0), DirectArg::Exact) => return Err(crate::render::no_exact_at_snapshot_zero("view")),
        (Stage::Iteration(0), _) => (None, None),
        _ => exact_direct(&args, remote.as_ref(), source.store(), &id, &geometry)?.unzip(),
    };
    // The scene spans about 2 / scale scene units (the VLF frame is [-1, 1]³).
    let n = geometry.scene.normalisation;
    let size = 2.0 / n.scale;
    let eye = args.eye.unwrap_or(n.center);
    let target = args.target.unwrap_or(eye + DVec3::Z);
    if eye == target || !(eye.is_finite() && target.is_finite()) {
        bail!("--eye and --target must be finite and apart, got {eye} and {target}");
    }
    let mut walk = Walk::new(eye, target, args.fovy, args.speed.unwrap_or(0.25 * size));
    walk.camera(args.size.0, args.size.1)?;
    if let Some(frames) = args.frames
        && (args.turn != 0.0 || args.to.is_some())
    {
        walk.script(args.to.unwrap_or(eye), args.turn, frames)?;
    }
    let catalog = PartCatalog::new(&geometry);
    // Exact direct light streams a direct map for every chunk too.
    let direct_values = exact.as_ref().map_or(0, |_| geometry.atlas.texels);
    let (field_values, cache_values) = (
        catalog.total_values() + direct_values,
        (args.cache_mb * 1e6 / 12.0) as usize,
    );
    println!(
        "streaming {} of job {id}: {} parts, {:.2} MB of radiance{}; cache {:.2} MB{}",
        crate::render::describe(stage),
        catalog.len() + exact.as_ref().map_or(0, |_| catalog.chunks()),
        field_values as f64 * 12e-6,
        match exact {
            Some(_) => ", direct maps for exact direct light included",
            None => "",
        },
        args.cache_mb,
        if cache_values >= field_values {
            " (holds it all)"
        } else {
            ""
        }
    );
    let stream = StreamConfig {
        capacity: cache_values.min(field_values),
        ..StreamConfig::with_megabytes(args.cache_mb)
    };
    let loader = snapshot_loader(
        remote.clone(),
        source.store().clone(),
        id.clone(),
        stage,
        geometry.clone(),
        exact.is_some(),
    );
    let objects = match args.objects.is_empty() {
        true => None,
        false => {
            let bvh = vlf_core::render::Bvh::build(&geometry.scene);
            let mut placement = vlf_viewer::Placement::new(args.objects.load(DVec3::Y)?, &geometry, &bvh)
                .context("cannot place the objects there")?;
            if let Some(frames) = args.frames
                && !args.object_to.is_empty()
            {
                placement.script(args.object_to.iter().map(|&p| Some(p)).collect(), frames)?;
            }
            Some(vlf_viewer::ViewObjects {
                placement,
                directions: args.objects.directions(&geometry),
                shadow_samples: args.objects.object_shadow_samples,
            })
        }
    };
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
        stream,
        settle: args.frames.is_some(),
        objects,
        exact_direct: exact,
        // Auto leaves a software adapter the field's direct light; exact asked for is drawn.
        exact_on_software: args.direct == DirectArg::Exact,
    };
    let mut source = source.into_part_source();
    if let Some(first) = first {
        source = Box::new(DirectSource::new(source, first, geometry.clone()));
    }
    let stats = vlf_viewer::view(geometry, source, options)?;
    if stats.frames > 0 {
        let first = stats.first_frame_seconds.unwrap_or(0.0);
        let drawing = stats.seconds - first - stats.settle_seconds;
        let rate = |frames: f64, seconds: f64| match frames / seconds.max(1e-9) {
            fps if fps >= 1.0 => format!("{fps:.1} fps"),
            fps => format!("{:.2} s a frame", 1.0 / fps.max(1e-12)),
        };
        println!(
            "{} frames in {:.2} s ({}) on {}, direct light {}; first frame after {:.2} s; after it {} drawing ({:.2} s waiting for parts left out)",
            stats.frames,
            stats.seconds,
            rate(stats.frames as f64, stats.seconds),
            stats.adapter,
            if stats.exact_direct { "exact" } else { "from the field" },
            stats.first_frame_seconds.unwrap_or(f64::NAN),
            rate((stats.frames - 1) as f64, drawing),
            stats.settle_seconds
        );
    }
    if stats.refused_moves > 0 {
        println!(
            "{} object moves refused (into a wall or out of the scene)",
            stats.refused_moves
        );
    }
    let s = &stats.stream;
    println!(
        "streamed {:.2} MB: {} parts fetched for {} views ({:.0} ms each to find what it needs), {} resident ({:.2} MB) at the end{}{}",
        s.bytes as f64 * 1e-6,
        s.fetched,
        s.views,
        1e3 * s.planning_seconds / s.views.max(1) as f64,
        s.resident,
        s.resident_values as f64 * 12e-6,
        if s.retries > 0 {
            format!(", {} fetches retried", s.retries)
        } else {
            String::new()
        },
        if s.short_views > 0 {
            format!(
                ", {} views needed more than the cache (the largest {:.2} MB)",
                s.short_views,
                s.largest_view_values as f64 * 12e-6
            )
        } else {
            String::new()
        }
    );
    for path in &stats.screenshots {
        println!("screenshot → {}", path.display());
    }
    Ok(())
}

/// Exact direct light's emitter points and snapshot 1's parts, if the view draws it
/// (`--direct`): auto where the job has snapshot 1 and the GPU can draw the scene exactly,
/// without objects.
fn exact_direct(
    args: &ViewArgs,
    remote: Option<&vlf_proto::Target>,
    store: &Store,
    id: &JobId,
    geometry: &Arc<LightField>,
) -> Result<Option<(Emitters, Box<dyn PartSource>)>> {
    if args.direct == DirectArg::Field {
        return Ok(None);
    }
    let emitters = Emitters::new(&geometry.scene, args.direct_samples).context("--direct-samples")?;
    let first = if let Err(e) = vlf_viewer::direct::check_scene(&geometry.scene) {
        Err(e.to_string())
    } else {
        first_snapshot(remote, store, id, geometry)
            .map_err(|e| format!("exact direct light needs snapshot 1 of job {id}: {e:#}"))
    };
    match (first, args.direct) {
        (Ok(first), _) => Ok(Some((emitters, first))),
        (Err(why), DirectArg::Exact) => bail!("--direct exact: {why}"),
        (Err(why), _) => {
            tracing::warn!("{why}: direct light from the field");
            Ok(None)
        }
    }
}

/// Snapshot 1's parts (what exact direct light's direct parts are made of), from the store or
/// the coordinator.
fn first_snapshot(
    remote: Option<&vlf_proto::Target>,
    store: &Store,
    id: &JobId,
    geometry: &Arc<LightField>,
) -> Result<Box<dyn PartSource>> {
    let first = Stage::Iteration(1);
    Ok(match remote {
        Some(target) => {
            let remote = Remote::new(target.clone(), id.to_string())?;
            Box::new(RemoteParts::open(remote, first, Some(geometry.clone()))?)
        }
        None => {
            let job = FieldJob::open(store, id)?;
            Box::new(StoreParts::new(StageParts::open(job, first)?, Some(geometry.clone()))?)
        }
    })
}

fn title(id: &JobId, stage: Stage) -> String {
    format!("vlf view {id} {}", crate::render::describe(stage))
}

/// A stage's parts with the geometry they fit, from a store or a coordinator.
trait StageSource: PartSource {
    fn geometry(&self) -> &Arc<LightField>;
    /// The store the job's description was read from (the memory store fetched into, with
    /// `--server`).
    fn store(&self) -> &Store;
    fn into_part_source(self: Box<Self>) -> Box<dyn PartSource>;
}

/// Parts read straight from a store.
struct StoreParts {
    parts: StageParts,
    geometry: Arc<LightField>,
    catalog: PartCatalog,
}

impl StoreParts {
    /// `parts` with the geometry of its job: `geometry` if given (any stage of the same job has
    /// the same), else rebuilt.
    fn new(parts: StageParts, geometry: Option<Arc<LightField>>) -> Result<StoreParts> {
        let geometry = match geometry {
            Some(g) => g,
            None => Arc::new(parts.geometry()?),
        };
        Ok(StoreParts {
            catalog: PartCatalog::new(&geometry),
            geometry,
            parts,
        })
    }
}

impl PartSource for StoreParts {
    fn fetch(&mut self, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>, String> {
        self.read(parts).map_err(|e| format!("{e:#}"))
    }

    fn bytes(&self) -> u64 {
        self.parts.bytes_read()
    }
}

impl StageSource for StoreParts {
    fn geometry(&self) -> &Arc<LightField> {
        &self.geometry
    }

    fn store(&self) -> &Store {
        self.parts.job().job().store()
    }

    fn into_part_source(self: Box<Self>) -> Box<dyn PartSource> {
        self
    }
}

/// Parts fetched from a coordinator's tile stream: the blobs holding them are fetched into a
/// memory store, read from it like a store's and dropped from it (a snapshot's checkpoint, which
/// holds all its tiles, is kept). A dropped connection is reconnected on the next fetch.
struct RemoteParts {
    remote: Remote,
    local: StoreParts,
    /// Bytes received over the network.
    bytes: u64,
}

impl RemoteParts {
    /// Fetches the job's description and `stage`'s summary, and opens the stage (with
    /// `geometry`, if known, as in [`StoreParts::new`]).
    fn open(mut remote: Remote, stage: Stage, geometry: Option<Arc<LightField>>) -> Result<RemoteParts> {
        let id = JobId::parse(&remote.job).map_err(anyhow::Error::msg)?;
        let store = Store::open("memory://")?;
        let summary = relative(&id, &vlf_store::layout::summary(&id, stage)?);
        let names = vec!["manifest.blob".to_string(), "scene.blob".to_string(), summary];
        let bytes = remote.fetch(names, &store)?;
        let job = FieldJob::open(&store, &id).with_context(|| format!("cannot open job {id}"))?;
        let parts = StageParts::open(job, stage)
            .with_context(|| format!("cannot read {} of job {id}", crate::render::describe(stage)))?;
        Ok(RemoteParts {
            remote,
            local: StoreParts::new(parts, geometry)?,
            bytes,
        })
    }
}

impl PartSource for RemoteParts {
    fn fetch(&mut self, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>, String> {
        let mut result = || -> Result<Vec<Vec<[f32; 3]>>> {
            let local = &self.local;
            let store = local.store();
            let id = local.parts.job().id().clone();
            let mut keys = local.parts.keys(&local.catalog, parts)?;
            keys.retain(|k| !store.exists(k).unwrap_or(false));
            let names = keys.iter().map(|k| relative(&id, k)).collect();
            self.bytes += self.remote.fetch(names, store)?;
            let values = local.read(parts);
            // A snapshot's mirror totals stay: every tile of their directions is cut from them.
            for key in keys.iter().filter(|k| !local.parts.is_shared(k)) {
                store.delete(key)?;
            }
            values
        };
        result().map_err(|e| format!("{e:#}"))
    }

    fn bytes(&self) -> u64 {
        self.bytes
    }
}

impl StoreParts {
    fn read(&self, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>> {
        Ok(self.parts.read(&self.catalog, parts)?)
    }
}

impl StageSource for RemoteParts {
    fn geometry(&self) -> &Arc<LightField> {
        self.local.geometry()
    }

    fn store(&self) -> &Store {
        self.local.store()
    }

    fn into_part_source(self: Box<Self>) -> Box<dyn PartSource> {
        self
    }
}

/// `key` relative to the job's prefix (how the tile service names blobs).
fn relative(id: &JobId, key: &str) -> String {
    let prefix = vlf_store::layout::job_prefix(id);
    key.strip_prefix(&prefix).unwrap_or(key).to_string()
}

/// A connection to the coordinator, made again after a call fails (the server may have dropped
/// it), with every call bounded in time.
struct Remote {
    runtime: tokio::runtime::Runtime,
    target: vlf_proto::Target,
    clients: Option<vlf_proto::Clients>,
    job: String,
}

/// How long one call may take before the connection is given up.
const CALL_TIMEOUT: Duration = Duration::from_secs(60);
/// Tries of a call, each on a fresh connection after a failure.
const ATTEMPTS: u32 = 3;

type Call<'a, T> = std::pin::Pin<Box<dyn std::future::Future<Output = Result<T>> + Send + 'a>>;

impl Remote {
    fn new(target: vlf_proto::Target, job: String) -> Result<Remote> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .context("cannot start the async runtime")?;
        Ok(Remote {
            runtime,
            target,
            clients: None,
            job,
        })
    }

    /// Runs `call` on the connection (connecting first if there is none). A failed call drops
    /// the connection (the server may have dropped it) and is tried again on a new one, up to
    /// [`ATTEMPTS`] times in all — unless the coordinator's answer is final (no such job, a bad
    /// token).
    fn call<T>(&mut self, call: impl Fn(&Remote, &mut vlf_proto::Clients) -> Call<'static, T>) -> Result<T> {
        let mut attempt = 1;
        loop {
            match self.call_once(&call) {
                Ok(value) => return Ok(value),
                Err(e) if attempt >= ATTEMPTS => return Err(e),
                Err(e)
                    if e.downcast_ref::<crate::remote::CallError>()
                        .is_some_and(|c| c.is_final()) =>
                {
                    return Err(e);
                }
                Err(e) => {
                    tracing::warn!("{e:#}; trying again on a new connection");
                    std::thread::sleep(Duration::from_millis(100 << attempt));
                    attempt += 1;
                }
            }
        }
    }

    fn call_once<T>(&mut self, call: &impl Fn(&Remote, &mut vlf_proto::Clients) -> Call<'static, T>) -> Result<T> {
        let mut clients = match self.clients.take() {
            Some(c) => c,
            None => self.runtime.block_on(async {
                tokio::time::timeout(CALL_TIMEOUT, crate::remote::connect(&self.target))
                    .await
                    .map_err(|_| anyhow::anyhow!("connecting to {} timed out", self.target.url))?
            })?,
        };
        let future = call(self, &mut clients);
        let result = self.runtime.block_on(async {
            tokio::time::timeout(CALL_TIMEOUT, future)
                .await
                .map_err(|_| anyhow::anyhow!("no answer from {} in {CALL_TIMEOUT:?}", self.target.url))?
        });
        if result.is_ok() {
            self.clients = Some(clients);
        }
        result
    }

    /// Fetches `names` (relative to the job) into `store`; the bytes received.
    fn fetch(&mut self, names: Vec<String>, store: &Store) -> Result<u64> {
        if names.is_empty() {
            return Ok(0);
        }
        self.call(|r, c| {
            let (mut c, job, names, store) = (c.clone(), r.job.clone(), names.clone(), store.clone());
            Box::pin(async move { crate::remote::fetch_into(&mut c, &job, names, &store).await })
        })
    }
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

/// Opens the stages around the one shown for streaming: from the store, re-reading the job's
/// manifest each time (a running job finishes new ones), or from `--server` over a new
/// connection. The geometry is the job's, whatever the stage.
fn snapshot_loader(
    remote: Option<vlf_proto::Target>,
    store: Store,
    id: JobId,
    mut current: Stage,
    geometry: Arc<LightField>,
    exact: bool,
) -> Loader {
    Box::new(move |switch| {
        let mut found = || -> Result<Option<(Box<dyn PartSource>, String)>> {
            let (finished, done) = match &remote {
                Some(target) => {
                    let status = crate::block_on_value(crate::remote::status_of(target, id.as_str()))?;
                    (status.snapshots.clone(), crate::remote::is_finished(&status))
                }
                None => {
                    let job = FieldJob::open(&store, &id)?;
                    let m = job.job().manifest();
                    (m.finished_iterations.clone(), job.latest_stage() == Some(Stage::Field))
                }
            };
            // Snapshot 0 is the emitters' light alone, with no direct part for exact direct
            // light to stand in for: a view drawing it exactly steps from snapshot 1.
            let finished: Vec<u32> = finished.into_iter().filter(|&k| !(exact && k == 0)).collect();
            let Some(next) = step(current, &finished, done, switch) else {
                return Ok(None);
            };
            let mut source: Box<dyn PartSource> = match &remote {
                Some(target) => {
                    let remote = Remote::new(target.clone(), id.to_string())?;
                    Box::new(RemoteParts::open(remote, next, Some(geometry.clone()))?)
                }
                None => {
                    let job = FieldJob::open(&store, &id)?;
                    Box::new(StoreParts::new(StageParts::open(job, next)?, Some(geometry.clone()))?)
                }
            };
            if exact {
                let first = first_snapshot(remote.as_ref(), &store, &id, &geometry)?;
                source = Box::new(DirectSource::new(source, first, geometry.clone()));
            }
            current = next;
            Ok(Some((source, title(&id, next))))
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

    #[test]
    fn the_loader_walks_a_running_jobs_snapshots() {
        let (store, id, mut p) = running_job();
        let job = FieldJob::open(&store, &id).unwrap();
        let geometry = Arc::new(StageParts::open(job, Stage::Iteration(1)).unwrap().geometry().unwrap());
        let catalog = PartCatalog::new(&geometry);
        let mut loader = snapshot_loader(None, store.clone(), id.clone(), Stage::Iteration(1), geometry, false);
        // The stage a switch opens, told by its title and checked by its parts: every one is the
        // stage's, read whole.
        let mut stage_of = |switch| -> Option<String> {
            let (mut parts, title) = loader(switch).unwrap()?;
            let stage = match title.rsplit_once("snapshot ") {
                Some((_, k)) => Stage::Iteration(k.parse().unwrap()),
                None => Stage::Field,
            };
            let whole = FieldJob::open(&store, &id).unwrap().load(stage).unwrap();
            let all: Vec<u32> = (0..catalog.len() as u32).collect();
            let values = parts.fetch(&all).unwrap();
            for (&i, v) in all.iter().zip(&values) {
                assert!(v.as_slice() == whole.part_values(&catalog, i), "{title}: part {i}");
            }
            Some(title)
        };
        let title = stage_of(Switch::Next).expect("snapshot 2");
        assert!(title.ends_with("snapshot 2"), "{title}");
        assert!(stage_of(Switch::Next).is_none(), "nothing after the newest snapshot");
        assert!(stage_of(Switch::Previous).unwrap().ends_with("snapshot 1"));
        assert!(stage_of(Switch::Previous).unwrap().ends_with("snapshot 0"));
        assert!(stage_of(Switch::Previous).is_none());
        // The job goes on: the next snapshot and then the final field appear.
        let mut job = FieldJob::open(&store, &id).unwrap();
        p.step(|_| {});
        job.write_snapshot(&p).unwrap();
        assert!(stage_of(Switch::Latest).unwrap().ends_with("snapshot 3"));
        job.finish(&p.field_now(), false).unwrap();
        let title = stage_of(Switch::Next).expect("the final field");
        assert!(title.ends_with("the final field"), "{title}");
    }

    /// With exact direct light, every stage the loader opens serves the direct parts too: snapshot
    /// 1's chunks less the emitters' own emission, whatever the stage shown.
    #[test]
    fn an_exact_loader_serves_the_direct_parts_from_snapshot_one() {
        let (store, id, _) = running_job();
        let job = FieldJob::open(&store, &id).unwrap();
        let geometry = Arc::new(
            StageParts::open(job.clone(), Stage::Iteration(2))
                .unwrap()
                .geometry()
                .unwrap(),
        );
        let catalog = PartCatalog::new(&geometry);
        let mut loader = snapshot_loader(
            None,
            store.clone(),
            id.clone(),
            Stage::Iteration(2),
            geometry.clone(),
            true,
        );
        let (mut parts, title) = loader(Switch::Previous).unwrap().expect("snapshot 1");
        assert!(title.ends_with("snapshot 1"), "{title}");
        let first = job.load(Stage::Iteration(1)).unwrap();
        let exact = vlf_core::direct::ExactDirect::new(&first, 4).unwrap();
        let direct: Vec<u32> = (0..catalog.chunks() as u32).map(|c| catalog.len() as u32 + c).collect();
        // Asked together with a field part, in any order.
        let asked: Vec<u32> = std::iter::once(0).chain(direct.iter().copied()).collect();
        let values = parts.fetch(&asked).unwrap();
        assert!(values[0].as_slice() == first.part_values(&catalog, 0));
        for (c, v) in values[1..].iter().enumerate() {
            assert!(
                v.as_slice() == &exact.direct()[catalog.range(c as u32)],
                "direct part of chunk {c}"
            );
        }
        // The lamp's texels lose its emission: its direct part is far below its radiance.
        let sum = |v: &[[f32; 3]]| v.iter().map(|t| t[0] as f64).sum::<f64>();
        assert!(sum(exact.direct()) < sum(&first.radiance));
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
