//! The commands that talk to a coordinator: `submit`, `status`, `watch`, `cancel`, `jobs
//! --server`, and the fetching of a job's blobs for `render --server`.

use crate::{HealthArgs, JobArgs, ServerFlags, SubmitArgs};
use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use std::collections::BTreeMap;
use std::path::Path;
use vlf_proto::health::{HealthCheckRequest, health_check_response::ServingStatus};
use vlf_proto::v1::{self, JobStatus, State};
use vlf_proto::{Clients, ConnectError, Target};
use vlf_server::scheduler::IterationUse;
use vlf_store::{JobId, Stage, Store, layout};

impl ServerFlags {
    pub fn target(&self) -> Target {
        Target {
            url: self.server.clone(),
            token: self.token.clone(),
            ca_cert: self.ca_cert.clone(),
        }
    }
}

/// Connects to `target`, with the URL in the message when nothing answers.
pub async fn connect(target: &Target) -> Result<Clients> {
    target
        .connect()
        .await
        .with_context(|| format!("is a coordinator running at {}? (vlf serve)", target.url))
}

/// A call the coordinator refused, with its code in words.
#[derive(Debug)]
pub struct CallError {
    pub code: tonic::Code,
    pub message: String,
}

impl std::fmt::Display for CallError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let code = match self.code {
            tonic::Code::NotFound => "not found",
            tonic::Code::InvalidArgument => "invalid argument",
            tonic::Code::Unauthenticated => "unauthenticated",
            tonic::Code::ResourceExhausted => "too large",
            tonic::Code::Unavailable => "coordinator unavailable",
            _ => "error",
        };
        write!(f, "{code}: {}", self.message)
    }
}

impl std::error::Error for CallError {}

impl CallError {
    /// Whether asking again cannot help (the job does not exist, the request or the token is
    /// wrong), as opposed to a connection or a server that failed.
    pub fn is_final(&self) -> bool {
        matches!(
            self.code,
            tonic::Code::NotFound
                | tonic::Code::InvalidArgument
                | tonic::Code::Unauthenticated
                | tonic::Code::PermissionDenied
                | tonic::Code::ResourceExhausted
        )
    }
}

fn call_error(status: tonic::Status) -> anyhow::Error {
    CallError {
        code: status.code(),
        message: status.message().to_string(),
    }
    .into()
}

/// The OBJ and the MTL libraries its `mtllib` lines name (those that exist next to it; a missing
/// one is reported by the server's importer, with the line that names it); or a glTF asset and
/// the buffers and images it names by relative URI, in the same map (those that are plain file
/// names next to it; a `.glb` or a `.gltf` with `data:` URIs needs none).
pub fn read_upload(path: &Path) -> Result<v1::SceneUpload> {
    let obj = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let dir = path.parent().unwrap_or(Path::new(""));
    let mut mtl = std::collections::HashMap::new();
    let gltf = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("gltf") || e.eq_ignore_ascii_case("glb"));
    if gltf {
        // A malformed asset is reported by the server's importer, like a malformed OBJ.
        for file in vlf_core::scene::gltf_external_files(path).unwrap_or_default() {
            let plain = file.file_name().map(|f| f == file.as_os_str()) == Some(true);
            if let (true, Some(name)) = (plain, file.to_str())
                && let Ok(bytes) = std::fs::read(dir.join(&file))
            {
                mtl.insert(name.to_string(), bytes);
            }
        }
        let obj_name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "scene.gltf".into());
        return Ok(v1::SceneUpload { obj_name, obj, mtl });
    }
    for line in String::from_utf8_lossy(&obj).lines() {
        let mut words = line.split_whitespace();
        if words.next() != Some("mtllib") {
            continue;
        }
        for name in words {
            let file = dir.join(name);
            let plain = Path::new(name).file_name().map(|f| f == std::ffi::OsStr::new(name)) == Some(true);
            if plain && let Ok(bytes) = std::fs::read(&file) {
                mtl.insert(name.to_string(), bytes);
            }
        }
    }
    let obj_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene.obj".into());
    Ok(v1::SceneUpload { obj_name, obj, mtl })
}

pub async fn submit(args: SubmitArgs) -> Result<()> {
    let parameters = args.job.parameters()?;
    // Refuse bad settings before uploading anything.
    vlf_proto::JobSpec::from_parameters(&parameters)?;
    let upload = read_upload(&args.scene)?;
    let mut clients = connect(&args.server.target()).await?;
    let status = clients
        .jobs
        .submit(v1::SubmitRequest {
            scene: Some(v1::submit_request::Scene::Upload(upload)),
            parameters: Some(parameters),
        })
        .await
        .map_err(call_error)
        .with_context(|| format!("cannot submit {}", args.scene.display()))?
        .into_inner();
    println!("{}", status.job_id);
    if args.watch {
        follow(&mut clients, &status.job_id).await?;
    }
    Ok(())
}

pub async fn status(args: JobArgs) -> Result<()> {
    let mut clients = connect(&args.server.target()).await?;
    let status = clients
        .jobs
        .get(v1::JobRequest {
            job_id: args.job.clone(),
        })
        .await
        .map_err(call_error)?
        .into_inner();
    println!("{}", describe(&status));
    Ok(())
}

pub async fn watch(args: JobArgs) -> Result<()> {
    let mut clients = connect(&args.server.target()).await?;
    follow(&mut clients, &args.job).await.map(|_| ())
}

pub async fn cancel(args: JobArgs) -> Result<()> {
    let mut clients = connect(&args.server.target()).await?;
    let status = clients
        .jobs
        .cancel(v1::JobRequest {
            job_id: args.job.clone(),
        })
        .await
        .map_err(call_error)?
        .into_inner();
    if status.state == State::Cancelled as i32
        || status.state == State::Propagating as i32
        || status.state == State::Queued as i32
    {
        println!("cancelling job {}", status.job_id);
    } else {
        println!("job {} had already ended: {}", status.job_id, describe(&status));
    }
    Ok(())
}

/// `vlf health`: whether the coordinator serves, asked of `grpc.health.v1` (service `""`, the
/// whole server) until it does or `--wait` runs out. A URL, CA file or token that cannot work
/// fails at once; a coordinator that does not answer yet, or answers `NOT_SERVING`, is asked
/// again every 200 ms.
pub async fn health(args: HealthArgs) -> Result<()> {
    if !(args.wait.is_finite() && (0.0..=86_400.0).contains(&args.wait)) {
        bail!("--wait must be between 0 and 86400 seconds, got {}", args.wait);
    }
    let target = args.server.target();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(args.wait);
    loop {
        let answer = match target.connect().await {
            Ok(mut clients) => clients
                .health
                .check(HealthCheckRequest { service: String::new() })
                .await
                .map(|reply| reply.into_inner().status()),
            Err(ConnectError::Transport { source, .. }) => Err(tonic::Status::unavailable(chain(&source))),
            Err(e) => return Err(e.into()),
        };
        let why = match answer {
            Ok(ServingStatus::Serving) => {
                println!("{}: serving", target.url);
                return Ok(());
            }
            Ok(status) => format!("it answers {}", status.as_str_name()),
            // A coordinator without the health service, or one that refuses the call, will not
            // change its mind.
            Err(status) if status.code() != tonic::Code::Unavailable => {
                return Err(call_error(status)).with_context(|| format!("health check of {}", target.url));
            }
            Err(status) => format!("no answer ({})", status.message()),
        };
        if std::time::Instant::now() >= deadline {
            bail!("the coordinator at {} does not serve: {why}", target.url);
        }
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    }
}

/// An error with its causes, `outer: inner: …` (a transport error says only "transport error"
/// itself; the cause says what: a refused connection, an unknown host).
fn chain(error: &dyn std::error::Error) -> String {
    let mut parts = vec![error.to_string()];
    let mut cause = error.source();
    while let Some(c) = cause {
        let part = c.to_string();
        // Wrappers often repeat their cause's words.
        if parts.last() != Some(&part) {
            parts.push(part);
        }
        cause = c.source();
    }
    parts.join(": ")
}

pub async fn jobs(target: Target) -> Result<()> {
    let mut clients = connect(&target).await?;
    let jobs = clients
        .jobs
        .list(v1::ListJobsRequest {})
        .await
        .map_err(call_error)?
        .into_inner()
        .jobs;
    if jobs.is_empty() {
        println!("no job at {}", target.url);
    }
    for status in jobs {
        println!("{}", describe(&status));
    }
    Ok(())
}

/// One line that says where a job stands.
pub fn describe(s: &JobStatus) -> String {
    let state = State::try_from(s.state).unwrap_or(State::Unspecified);
    let what = match state {
        // Its survey leased to the workers: how far they are.
        State::Queued if !s.message.is_empty() && s.batches_total > 0 => format!(
            "queued, {} (survey {}/{} batches, {} leased)",
            s.message, s.batches_done, s.batches_total, s.leases_out
        ),
        State::Queued if !s.message.is_empty() => format!("queued, {}", s.message),
        State::Queued => "queued".to_string(),
        State::Propagating => format!(
            "propagating iteration {}{} ({}/{} batches, {} leased)",
            s.iteration,
            if s.iterations_planned > 0 {
                format!(" of {}", s.iterations_planned)
            } else {
                String::new()
            },
            s.batches_done,
            s.batches_total,
            s.leases_out
        ),
        State::Finished if !s.digest.is_empty() => format!("finished, digest {}", s.digest),
        State::Finished => "finished".to_string(),
        State::Failed => format!("failed: {}", s.message),
        State::Cancelled => "cancelled".to_string(),
        State::Unspecified => "unknown".to_string(),
    };
    // None before the job is set up.
    let unshot = match s.unshot_fraction.is_nan() {
        true => "–".to_string(),
        false => format!("{:.3e}", s.unshot_fraction),
    };
    let mut line = format!("{}  {what}  unshot {unshot}  snapshots {:?}", s.job_id, s.snapshots);
    if state == State::Propagating {
        line += &format!(
            "  {} workers  {:.0} directions/s",
            s.workers_alive, s.directions_per_second
        );
        if s.eta_job_seconds >= 0.0 {
            line += &format!("  ETA {:.1} s", s.eta_job_seconds);
        } else if s.eta_iteration_seconds >= 0.0 {
            line += &format!("  iteration ETA {:.1} s", s.eta_iteration_seconds);
        }
    }
    if let Some(used) = &s.last_iteration {
        line += &format!("  last iteration {}", describe_use(used));
    }
    line
}

/// How an iteration used its workers, in words: whether more workers would help (they computed
/// all along), or their balance or the serial part between iterations is what limits the job.
pub fn describe_use(u: &v1::IterationUse) -> String {
    let u = IterationUse::from_wire(u);
    let ms = |s: f64| format!("{:.1} ms", s * 1e3);
    let Some(balance) = u.balance() else {
        return format!("{}: no work reported", ms(u.seconds));
    };
    format!(
        "{}: {} worker{} {:.0}% busy over {}, {} between iterations",
        ms(u.seconds),
        u.workers,
        if u.workers == 1 { "" } else { "s" },
        100.0 * balance,
        ms(u.span_seconds),
        ms(u.between_seconds()),
    )
}

/// How long [`follow`] waits for a coordinator that went away (stopped, restarted, moved to
/// another machine) to come back and take its jobs up from the store, before it gives up.
const REJOIN: std::time::Duration = std::time::Duration::from_secs(120);

/// Follows a job's status stream with a progress bar per iteration until it ends; returns the
/// final status, or an error when the job failed or was cancelled. A coordinator that goes
/// away meanwhile is waited for ([`REJOIN`]) and the job followed on from it.
pub async fn follow(clients: &mut Clients, job: &str) -> Result<JobStatus> {
    let mut bars = Bars::new();
    let mut last: Option<JobStatus> = None;
    // Since when the coordinator has been away, while it is.
    let mut away: Option<std::time::Instant> = None;
    loop {
        let request = v1::JobRequest {
            job_id: job.to_string(),
        };
        let interrupted = match clients.jobs.watch(request).await {
            Ok(stream) => {
                tracing::debug!(job, "following the job's progress");
                let mut stream = stream.into_inner();
                // Statuses are numbered per stream: a coordinator that took the job up anew
                // counts from 1 again.
                let mut seq = None;
                loop {
                    match stream.message().await {
                        Ok(Some(status)) => {
                            away = None;
                            if let Some(previous) = seq
                                && status.seq <= previous
                            {
                                bail!("progress arrived out of order ({} after {previous})", status.seq);
                            }
                            seq = Some(status.seq);
                            bars.show(&status);
                            last = Some(status);
                        }
                        Ok(None) => break None,
                        Err(status) => break Some(status),
                    }
                }
            }
            Err(status) => Some(status),
        };
        let Some(status) = interrupted else { break };
        let error = CallError {
            code: status.code(),
            message: status.message().to_string(),
        };
        if error.is_final() {
            return Err(error.into());
        }
        let since = *away.get_or_insert_with(|| {
            bars.clear();
            eprintln!(
                "{error}; waiting up to {} s for the coordinator to come back",
                REJOIN.as_secs()
            );
            std::time::Instant::now()
        });
        if since.elapsed() >= REJOIN {
            return Err(anyhow::Error::new(error).context(format!(
                "the coordinator did not come back within {} s",
                REJOIN.as_secs()
            )));
        }
        tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    }
    bars.clear();
    let last = last.context("the coordinator sent no status")?;
    println!("{}", describe(&last));
    match State::try_from(last.state) {
        Ok(State::Finished) => Ok(last),
        Ok(State::Failed) => bail!("job {} failed: {}", last.job_id, last.message),
        Ok(State::Cancelled) => bail!("job {} was cancelled", last.job_id),
        _ => bail!(
            "the coordinator closed the progress stream before job {} ended",
            last.job_id
        ),
    }
}

/// The progress bar of the iteration being propagated, or of the survey the workers learn while
/// the job is set up (iteration 0).
struct Bars {
    style: ProgressStyle,
    bar: Option<(u32, ProgressBar)>,
}

impl Bars {
    fn new() -> Bars {
        let style = ProgressStyle::with_template("{prefix:>14} [{bar:40}] {pos}/{len} batches {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> ");
        Bars { style, bar: None }
    }

    fn show(&mut self, status: &JobStatus) {
        let surveying = status.state == State::Queued as i32 && status.batches_total > 0;
        if status.state != State::Propagating as i32 && !surveying {
            return;
        }
        if self.bar.as_ref().is_none_or(|(k, _)| *k != status.iteration) {
            self.clear();
            let b = ProgressBar::new(u64::from(status.batches_total));
            b.set_style(self.style.clone());
            b.set_prefix(match surveying {
                true => "survey".to_string(),
                false => format!("iteration {}", status.iteration),
            });
            self.bar = Some((status.iteration, b));
        }
        if let Some((_, b)) = &self.bar {
            b.set_length(u64::from(status.batches_total.max(1)));
            b.set_position(u64::from(status.batches_done));
            let workers = format!(
                "{} workers, {:.0} dir/s",
                status.workers_alive, status.directions_per_second
            );
            b.set_message(match surveying {
                true => workers,
                false => format!("unshot {:.2e}, {workers}", status.unshot_fraction),
            });
        }
    }

    fn clear(&mut self) {
        if let Some((_, b)) = self.bar.take() {
            b.finish_and_clear();
        }
    }
}

/// Copies the blobs of `job` that rendering `stage` needs (manifest, scene, the stage) from the
/// coordinator into a fresh in-memory store. Blobs arrive as stored and are verified when read.
/// Returns the store and the stage (the latest, when none is asked for).
pub async fn fetch_job(target: &Target, job: &str, snapshot: Option<u32>) -> Result<(Store, Stage)> {
    JobId::parse(job).map_err(anyhow::Error::msg)?;
    let mut clients = connect(target).await?;
    let status = clients
        .jobs
        .get(v1::JobRequest {
            job_id: job.to_string(),
        })
        .await
        .map_err(call_error)?
        .into_inner();
    let stage = resolve_stage(&status, job, snapshot)?;
    let store = vlf_store::blocking(|| Store::open("memory://")).await??;
    // The manifest first: it says which of the stage's blobs a render reads.
    let described = vec!["manifest.blob".to_string(), "scene.blob".to_string()];
    fetch_into(&mut clients, job, described, &store).await?;
    let id = JobId::parse(job).map_err(anyhow::Error::msg)?;
    let opened = {
        let (store, id) = (store.clone(), id.clone());
        vlf_store::blocking(move || vlf_store::Job::open(&store, &id)).await??
    };
    let listed = stage_blobs(&mut clients, job, stage).await?;
    let mut names = opened.read_by_renders(stage, listed)?;
    names.sort();
    names.dedup();
    fetch_into(&mut clients, job, names, &store).await?;
    Ok((store, stage))
}

/// The stage of `job` to look at: snapshot `k` if asked (it must be finished), else the final
/// field of a finished job, else its latest snapshot.
pub fn resolve_stage(status: &JobStatus, job: &str, snapshot: Option<u32>) -> Result<Stage> {
    Ok(match snapshot {
        Some(k) if status.snapshots.contains(&k) => Stage::Iteration(k),
        Some(k) => bail!(
            "snapshot {k} of job {job} is not finished (finished: {:?})",
            status.snapshots
        ),
        None if status.state == State::Finished as i32 => Stage::Field,
        None => Stage::Iteration(
            *status
                .snapshots
                .last()
                .with_context(|| format!("job {job} has no finished snapshot yet"))?,
        ),
    })
}

/// Fetches the named blobs of `job` (names relative to the job's prefix) over the tile stream
/// into `store` (a `memory://` store standing for the job's part of the server's store);
/// returns the bytes received.
pub async fn fetch_into(clients: &mut Clients, job: &str, names: Vec<String>, store: &Store) -> Result<u64> {
    let id = JobId::parse(job).map_err(anyhow::Error::msg)?;
    let job_prefix = layout::job_prefix(&id);
    let asked = names.len();
    let mut stream = clients
        .tiles
        .fetch(v1::FetchRequest {
            job_id: job.to_string(),
            names,
        })
        .await
        .map_err(call_error)?
        .into_inner();
    let mut blobs = BTreeMap::new();
    while let Some(blob) = stream.message().await.map_err(call_error)? {
        blobs.insert(blob.name, blob.data);
    }
    if blobs.len() != asked {
        bail!("the coordinator sent {} of the {asked} blobs asked for", blobs.len());
    }
    let bytes = blobs.values().map(|d| d.len() as u64).sum();
    let store = store.clone();
    vlf_store::blocking(move || -> Result<()> {
        for (name, data) in blobs {
            store.put(&format!("{job_prefix}{name}"), data)?;
        }
        Ok(())
    })
    .await??;
    Ok(bytes)
}

/// The names of every blob of `stage` of `job` on the coordinator (relative to the job's prefix).
pub async fn stage_blobs(clients: &mut Clients, job: &str, stage: Stage) -> Result<Vec<String>> {
    let id = JobId::parse(job).map_err(anyhow::Error::msg)?;
    let job_prefix = layout::job_prefix(&id);
    let stage_prefix = layout::stage_prefix(&id, stage)?;
    let relative = stage_prefix
        .strip_prefix(&job_prefix)
        .unwrap_or(&stage_prefix)
        .to_string();
    Ok(clients
        .tiles
        .list_blobs(v1::ListBlobsRequest {
            job_id: job.to_string(),
            prefix: relative,
        })
        .await
        .map_err(call_error)?
        .into_inner()
        .names)
}

/// The status of `job` on the coordinator `target`.
pub async fn status_of(target: &Target, job: &str) -> Result<JobStatus> {
    job_status(&mut connect(target).await?, job).await
}

/// The status of `job` over `clients`.
pub async fn job_status(clients: &mut Clients, job: &str) -> Result<JobStatus> {
    Ok(clients
        .jobs
        .get(v1::JobRequest {
            job_id: job.to_string(),
        })
        .await
        .map_err(call_error)?
        .into_inner())
}

/// Whether the job has finished (its final field is stored).
pub fn is_finished(status: &JobStatus) -> bool {
    status.state == State::Finished as i32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_gltf_upload_carries_the_files_it_names() {
        let dir = std::env::temp_dir().join(format!("vlf-client-upload-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let gltf = r#"{"asset": {"version": "2.0"},
            "buffers": [{"byteLength": 4, "uri": "mesh%20data.bin"}, {"byteLength": 4, "uri": "sub/other.bin"},
                        {"byteLength": 1, "uri": "data:application/octet-stream;base64,AA=="}],
            "images": [{"uri": "wood.png"}, {"uri": "missing.png"}]}"#;
        let path = dir.join("lamp.gltf");
        std::fs::write(&path, gltf).unwrap();
        std::fs::write(dir.join("mesh data.bin"), [1, 2, 3, 4]).unwrap();
        std::fs::write(dir.join("wood.png"), [5]).unwrap();
        let upload = read_upload(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(upload.obj_name, "lamp.gltf");
        assert_eq!(upload.obj, gltf.as_bytes());
        // Plain names next to the asset that exist; the server reports the rest.
        let mut names: Vec<&str> = upload.mtl.keys().map(String::as_str).collect();
        names.sort();
        assert_eq!(names, ["mesh data.bin", "wood.png"]);
        assert_eq!(upload.mtl["mesh data.bin"], [1, 2, 3, 4]);
    }

    #[test]
    fn an_iteration_use_reads_as_busy_share_and_serial_part() {
        let used = v1::IterationUse {
            seconds: 0.040,
            busy_seconds: 0.060,
            span_seconds: 0.036,
            workers: 2,
        };
        // 60 ms of compute in 2 × 36 ms: 83 % busy; 4 ms outside the span.
        assert_eq!(
            describe_use(&used),
            "40.0 ms: 2 workers 83% busy over 36.0 ms, 4.0 ms between iterations"
        );
        let idle = v1::IterationUse {
            seconds: 0.010,
            ..Default::default()
        };
        assert_eq!(describe_use(&idle), "10.0 ms: no work reported");
        let status = JobStatus {
            job_id: "j".into(),
            state: State::Finished as i32,
            last_iteration: Some(used),
            ..Default::default()
        };
        assert!(
            describe(&status)
                .ends_with("last iteration 40.0 ms: 2 workers 83% busy over 36.0 ms, 4.0 ms between iterations")
        );
    }
}
