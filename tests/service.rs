//! The distributed service across real processes on loopback: `vlf serve`, `vlf worker` and the
//! client commands as separate processes, killed and restarted the way machines fail.
//!
//! Every job's final field is compared with `vlf propagate`'s (the library in one process): the
//! same bits whatever the number of workers, a worker killed holding a lease, or a coordinator
//! restarted in the middle of an iteration.

#[path = "support/display.rs"]
mod display;
#[path = "support/process.rs"]
mod process;

use process::{PARAMS, Proc, describe, free_port, vlf_command};
use std::path::{Path, PathBuf};
use std::process::Output;
use std::time::{Duration, Instant};
use tonic::Code;
use vlf_core::field::LightField;
use vlf_proto::Target;
use vlf_proto::health::{HealthCheckRequest, HealthCheckResponse, health_check_response::ServingStatus};
use vlf_proto::v1::{self, State};
use vlf_store::{FieldJob, Job, JobId, Stage, Store};

fn spawn(dir: &Path, name: &str, args: &[&str]) -> Proc {
    let mut command = vlf_command();
    command.args(args);
    Proc::spawn(command, dir, name)
}

/// A coordinator on `listen` (port 0: any); returns it and its URL.
fn serve(dir: &Path, store: &Path, listen: &str, extra: &[&str]) -> (Proc, String) {
    let mut args = vec!["serve", "--store", store.to_str().unwrap(), "--listen", listen];
    args.extend(extra);
    let mut server = spawn(dir, "server", &args);
    let line = server.wait_for_line("listening on ");
    let url = line.trim_start_matches("listening on ").trim().to_string();
    (server, url)
}

/// A coordinator whose leases last ten minutes and go one batch at a time, and which takes a
/// worker for dead after a few missed heartbeats of 0.2 s: a lease a killed worker held can
/// only be handed on by its heartbeats stopping.
fn serve_watching_heartbeats(dir: &Path, store: &Path) -> (Proc, String) {
    let flags = [
        "--lease-seconds",
        "600",
        "--heartbeat-seconds",
        "0.2",
        "--max-lease-batches",
        "1",
    ];
    serve(dir, store, "127.0.0.1:0", &flags)
}

fn worker(dir: &Path, name: &str, url: &str, extra: &[&str]) -> Proc {
    let mut args = vec!["worker", "--server", url, "--threads", "1", "--name", name];
    args.extend(extra);
    spawn(dir, name, &args)
}

fn vlf(args: &[&str]) -> Output {
    vlf_command().args(args).output().expect("run vlf")
}

fn text(o: &Output) -> String {
    describe(o)
}

fn scene(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name)
        .to_string_lossy()
        .into_owned()
}

/// A fresh scratch directory, removed when the guard drops (pass or fail).
fn temp(name: &str) -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix(&format!("vlf-service-{name}-"))
        .tempdir()
        .expect("scratch directory")
}

/// `vlf propagate`'s field for the mirror scene with `PARAMS` and `extra`, and the digest it
/// printed for it.
fn reference(dir: &Path, extra: &[&str]) -> (LightField, String) {
    let store = dir.join("reference");
    let mirrors = scene("mirrors.obj");
    let mut args = vec!["propagate", mirrors.as_str(), "--store", store.to_str().unwrap()];
    args.extend(PARAMS);
    args.extend(extra);
    let o = vlf(&args);
    assert!(o.status.success(), "{}", text(&o));
    let store = Store::open_existing(store.to_str().unwrap()).unwrap();
    let id = Job::list(&store).unwrap().pop().unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    let digest = stdout
        .lines()
        .find_map(|l| l.trim().strip_prefix("digest"))
        .unwrap_or_else(|| panic!("no digest in vlf propagate's report:\n{stdout}"))
        .trim()
        .to_string();
    assert_eq!(digest.len(), 64, "{stdout}");
    (FieldJob::open(&store, &id).unwrap().load(Stage::Field).unwrap(), digest)
}

fn field(store: &Path, id: &str) -> LightField {
    let store = Store::open_existing(store.to_str().unwrap()).unwrap();
    FieldJob::open(&store, &JobId::parse(id).unwrap())
        .unwrap()
        .load(Stage::Field)
        .unwrap()
}

/// Fields equal up to the wall-clock times in their statistics.
fn assert_same_field(a: &LightField, b: &LightField, what: &str) {
    let mut b = b.clone();
    for (sa, sb) in a.stats.iter().zip(b.stats.iter_mut()) {
        sb.seconds = sa.seconds;
    }
    assert!(*a == b, "{what}: the field differs from vlf propagate's");
}

/// Submits the mirror scene; returns the job id.
fn submit(url: &str, extra: &[&str]) -> String {
    let mirrors = scene("mirrors.obj");
    let mut args = vec!["submit", mirrors.as_str(), "--server", url];
    args.extend(PARAMS);
    args.extend(extra);
    let o = vlf(&args);
    assert!(o.status.success(), "{}", text(&o));
    String::from_utf8_lossy(&o.stdout)
        .lines()
        .next()
        .unwrap()
        .trim()
        .to_string()
}

/// `vlf watch` to the end; asserts the job finished.
fn watch(url: &str, id: &str) -> String {
    let o = vlf(&["watch", id, "--server", url]);
    assert!(o.status.success(), "{}", text(&o));
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(out.contains("finished"), "{out}");
    out
}

/// The code and message of a failed call (`None` when it succeeded).
fn code<T>(r: Result<tonic::Response<T>, tonic::Status>) -> Option<(Code, String)> {
    r.err().map(|s| (s.code(), s.message().to_string()))
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap()
}

/// Polls `job` until `ok` holds for its status (a minute at most).
fn wait_status(url: &str, id: &str, what: &str, ok: impl Fn(&v1::JobStatus) -> bool) -> v1::JobStatus {
    let rt = runtime();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let status = rt.block_on(async {
            let mut c = Target::new(url).connect().await.ok()?;
            c.jobs
                .get(v1::JobRequest { job_id: id.to_string() })
                .await
                .ok()
                .map(|r| r.into_inner())
        });
        if let Some(s) = status {
            if ok(&s) {
                return s;
            }
            assert!(Instant::now() < deadline, "timed out waiting for {what}: {s:?}");
        } else {
            assert!(Instant::now() < deadline, "timed out waiting for {what}: no answer");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn one_two_and_four_worker_processes_give_propagates_bits() {
    let scratch = temp("workers");
    let dir = scratch.path();
    let (expected, digest) = reference(dir, &["--iterations", "3"]);
    for workers in [1, 2, 4] {
        let store = dir.join(format!("store-{workers}"));
        // With two workers, they and the coordinator hold a few subfields each
        // (`--subfield-memory`): built when needed, dropped, built again; the same field.
        let budget: &[&str] = if workers == 2 {
            &["--subfield-memory", "64KiB"]
        } else {
            &[]
        };
        let (server, url) = serve(dir, &store, "127.0.0.1:0", budget);
        let workers_up: Vec<Proc> = (0..workers)
            .map(|w| worker(dir, &format!("worker-{workers}-{w}"), &url, budget))
            .collect();
        // Registered before the job comes: they learn its survey, not the coordinator.
        for w in &workers_up {
            wait_for_log(w, "registered");
        }
        let id = submit(&url, &["--iterations", "3"]);
        let watched = watch(&url, &id);
        assert_same_field(&expected, &field(&store, &id), &format!("{workers} workers"));
        assert!(
            server.log().contains("survey learnt by the workers"),
            "{}",
            server.log()
        );
        // And says so by the digest: `vlf watch` ends on it, the status carries it.
        assert!(watched.contains(&format!("finished, digest {digest}")), "{watched}");
        // How the last iteration used the workers: some of them computed, never more than the
        // span in which they did holds, and `vlf watch` says so.
        let status = wait_status(&url, &id, "the finished status", |s| s.last_iteration.is_some());
        assert_eq!(status.digest, digest);
        let used = status.last_iteration.unwrap_or_default();
        assert!((1..=workers).contains(&used.workers), "{used:?}");
        assert!(used.span_seconds > 0.0 && used.span_seconds <= used.seconds, "{used:?}");
        let capacity = f64::from(used.workers) * used.span_seconds;
        assert!(
            used.busy_seconds > 0.0 && used.busy_seconds <= capacity + 1e-3,
            "{used:?}"
        );
        assert!(
            watched.contains("last iteration") && watched.contains("% busy"),
            "{watched}"
        );
        // The iteration's work blobs are gone once its snapshot is committed.
        let work = store.join("jobs").join(&id).join("work");
        let left = std::fs::read_dir(&work).map(|d| d.count()).unwrap_or(0);
        assert_eq!(left, 0, "work blobs left in {}", work.display());
    }
}

#[test]
fn a_worker_killed_holding_a_lease_loses_it_and_the_job_finishes_with_the_same_bits() {
    let scratch = temp("kill");
    let dir = scratch.path();
    let (expected, digest) = reference(dir, &["--iterations", "3"]);
    let store = dir.join("store");
    let (_server, url) = serve_watching_heartbeats(dir, &store);
    let id = submit(&url, &["--iterations", "3"]);
    // Leases of one batch, two per iteration (l = 33): the first worker computes 4 batches, then
    // stalls on a fifth lease, in the middle of the third iteration.
    let mut doomed = worker(dir, "doomed", &url, &["--hang-after-leases", "4"]);
    doomed.wait_for_line("stalled holding lease");
    let status = wait_status(&url, &id, "the lease", |s| s.leases_out == 1);
    assert_eq!(status.state, State::Propagating as i32);
    assert!(
        status.batches_done < status.batches_total,
        "killed in the middle of an iteration: {status:?}"
    );
    doomed.kill();
    // The lease lasts ten minutes: only the missed heartbeats can hand the batch on.
    let _rescuer = worker(dir, "rescuer", &url, &[]);
    let watched = watch(&url, &id);
    assert_same_field(&expected, &field(&store, &id), "after a killed worker");
    assert!(watched.contains(&format!("digest {digest}")), "{watched}");
}

/// Stops `proc` as a container runtime stops a container (SIGTERM), and waits (a minute at
/// most) for it to exit; returns how it exited.
fn terminate(proc: &mut Proc) -> std::process::ExitStatus {
    let pid = proc.child.id().to_string();
    let sent = std::process::Command::new("kill").args(["-TERM", &pid]).status();
    assert!(sent.as_ref().is_ok_and(|s| s.success()), "kill -TERM {pid}: {sent:?}");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if let Some(status) = proc.child.try_wait().unwrap() {
            return status;
        }
        assert!(
            Instant::now() < deadline,
            "still running a minute after SIGTERM:\n{}",
            proc.log()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// What `deploy/check.sh` does to a cluster, on processes: workers scaled up while a job runs,
/// one scaled down (stopped as a runtime stops a container), one killed; the job ends with
/// `vlf propagate`'s field and digest.
#[test]
fn workers_that_join_leave_and_die_while_a_job_runs_give_propagates_digest() {
    let scratch = temp("scale");
    let dir = scratch.path();
    let extra = ["--iterations", "4"];
    let (expected, digest) = reference(dir, &extra);
    let store = dir.join("store");
    let (_server, url) = serve_watching_heartbeats(dir, &store);
    let id = submit(&url, &extra);
    // The first worker computes two batches and stalls holding a third lease, which lasts ten
    // minutes while it heartbeats: the job cannot end before it is killed, so all that follows
    // happens while the job runs.
    let mut doomed = worker(dir, "doomed", &url, &["--hang-after-leases", "2"]);
    doomed.wait_for_line("stalled holding lease");
    // Scaled up: two more join and take the job on as far as it goes without that batch.
    let mut leaving = worker(dir, "leaving", &url, &[]);
    let _staying = worker(dir, "staying", &url, &[]);
    let status = wait_status(&url, &id, "three workers", |s| s.workers_alive == 3);
    assert_eq!(status.state, State::Propagating as i32, "{status:?}");
    // Scaled down: one is stopped, and leaves cleanly.
    let stopped = terminate(&mut leaving);
    assert!(stopped.success(), "{stopped:?}:\n{}", leaving.log());
    let status = wait_status(&url, &id, "the job still running", |_| true);
    assert_eq!(status.state, State::Propagating as i32, "{status:?}");
    // And one dies: its lease goes to the worker left once its heartbeats stop.
    doomed.kill();
    let watched = watch(&url, &id);
    assert_same_field(&expected, &field(&store, &id), "after workers joined, left and died");
    assert!(watched.contains(&format!("finished, digest {digest}")), "{watched}");
}

#[test]
fn a_coordinator_restarted_mid_iteration_resumes_with_the_same_bits() {
    let scratch = temp("restart");
    let dir = scratch.path();
    // One pass of 2 batches per iteration (l = 33): 3 batches are snapshot 1 and 1 of iteration
    // 2's 2.
    let extra = ["--iterations", "4", "--perturb", "0"];
    let (expected, digest) = reference(dir, &extra);
    let store = dir.join("store");
    let listen = format!("127.0.0.1:{}", free_port());
    let one = ["--max-lease-batches", "1"];
    let (mut server, url) = serve(dir, &store, &listen, &one);
    let id = submit(&url, &extra);
    let mut stalled = worker(dir, "stalled", &url, &["--hang-after-leases", "3"]);
    stalled.wait_for_line("stalled holding lease");
    let status = wait_status(&url, &id, "snapshot 1", |s| s.snapshots == [0, 1]);
    assert_eq!((status.iteration, status.batches_done), (2, 1), "{status:?}");
    // A client following the job follows it on from the restarted coordinator.
    let mut follower = vlf_command();
    follower
        .args(["watch", &id, "--server", &url])
        .env("RUST_LOG", "vlf=debug");
    let mut watching = Proc::spawn(follower, dir, "watching");
    wait_for_log(&watching, "following the job's progress");
    server.kill();
    stalled.kill();
    // A worker that starts while no coordinator answers waits for one.
    let _patient = worker(dir, "patient", &url, &[]);
    std::thread::sleep(Duration::from_millis(300));
    let (mut server, url) = serve(dir, &store, &listen, &one);
    let resumed = wait_status(&url, &id, "the resumed job", |_| true);
    assert!(resumed.snapshots.starts_with(&[0, 1]), "{resumed:?}");
    watch(&url, &id);
    assert_same_field(&expected, &field(&store, &id), "after a coordinator restart");
    let end = watching.wait_for_line("finished");
    assert!(end.starts_with(&id), "{end}");
    let exited = watching.child.wait().unwrap();
    assert!(exited.success(), "{exited:?}:\n{}", watching.log());
    assert!(watching.log().contains("waiting up to"), "{}", watching.log());
    // A coordinator that finds the job finished in the store reports its digest from there.
    server.kill();
    let (_server, url) = serve(dir, &store, &listen, &one);
    let finished = wait_status(&url, &id, "the finished job", |_| true);
    assert_eq!(finished.state, State::Finished as i32, "{finished:?}");
    assert_eq!(finished.digest, digest);
}

/// A coordinator stopped while its workers learn a job's survey: the next one takes the parts
/// already in the store as they are, has the rest learnt, and the job ends with the bits of
/// `vlf propagate`; the parts go with the first iteration's work.
#[test]
fn a_coordinator_restarted_mid_survey_uses_the_parts_already_learnt() {
    let scratch = temp("restart-survey");
    let dir = scratch.path();
    // l = 33: the survey is 2 batches, leased one at a time.
    let extra = ["--iterations", "2"];
    let (expected, digest) = reference(dir, &extra);
    let store = dir.join("store");
    let listen = format!("127.0.0.1:{}", free_port());
    let one = ["--max-lease-batches", "1"];
    let (mut server, url) = serve(dir, &store, &listen, &one);
    // It learns the survey's first batch and holds the second for ever.
    let mut stalled = worker(dir, "stalled", &url, &["--hang-after-leases", "1"]);
    wait_for_log(&stalled, "registered");
    let id = submit(&url, &extra);
    stalled.wait_for_line("stalled holding lease");
    let status = wait_status(&url, &id, "the survey's first part", |s| s.batches_done == 1);
    assert_eq!(
        (status.state, status.iteration),
        (State::Queued as i32, 0),
        "{status:?}"
    );
    let said = text(&vlf(&["status", &id, "--server", &url]));
    assert!(
        said.contains("queued, setting up (survey 1/2 batches, 1 leased)"),
        "{said}"
    );
    assert!(said.contains("unshot –"), "no unshot power before snapshot 0: {said}");
    let parts = store.join("jobs").join(&id).join("work/00000/survey");
    let names = |dir: &Path| -> Vec<String> {
        let entries = std::fs::read_dir(dir)
            .map(|d| d.flatten().collect::<Vec<_>>())
            .unwrap_or_default();
        entries
            .iter()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect()
    };
    assert_eq!(names(&parts), ["00000-00001.blob"]);
    server.kill();
    stalled.kill();
    let _patient = worker(dir, "patient", &url, &[]);
    let (server, url) = serve(dir, &store, &listen, &one);
    let watched = watch(&url, &id);
    assert!(watched.contains(&format!("digest {digest}")), "{watched}");
    assert_same_field(&expected, &field(&store, &id), "after a restart mid-survey");
    assert!(server.log().contains("stored_before=1"), "{}", server.log());
    assert!(names(&parts).is_empty(), "survey parts left: {:?}", names(&parts));
}

/// A job stored as submitted but not set up yet (its coordinator stopped while setting it up:
/// manifest and scene only) is set up by the coordinator that takes up the store, and ends with
/// the bits of `vlf propagate`.
#[test]
fn a_job_submitted_but_not_set_up_is_set_up_by_the_next_coordinator() {
    let scratch = temp("set-up");
    let dir = scratch.path();
    let extra = ["--iterations", "3"];
    let (expected, _) = reference(dir, &extra);
    let described = {
        let reference = Store::open_existing(dir.join("reference").to_str().unwrap()).unwrap();
        let id = Job::list(&reference).unwrap().pop().unwrap();
        let done = FieldJob::open(&reference, &id).unwrap();
        let store = Store::open(dir.join("store").to_str().unwrap()).unwrap();
        let job = FieldJob::describe(&store, done.scene(), done.options(), vlf_store::Encoding::F32).unwrap();
        assert!(!job.is_set_up());
        job.id().to_string()
    };
    let (_server, url) = serve(dir, &dir.join("store"), "127.0.0.1:0", &[]);
    let _worker = worker(dir, "w", &url, &[]);
    watch(&url, &described);
    assert_same_field(
        &expected,
        &field(&dir.join("store"), &described),
        "set up after a restart",
    );
}

/// A job whose set-up fails — here, emitters too small for any ray to hit — is accepted when
/// submitted (setting up is not waited for) and then fails, with the library's reason in its
/// status and in the store.
#[test]
fn a_job_whose_set_up_fails_fails_with_the_reason() {
    let scratch = temp("set-up-fails");
    let dir = scratch.path();
    let store = dir.join("store");
    let (_server, url) = serve(dir, &store, "127.0.0.1:0", &[]);
    let obj = "mtllib s.mtl\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\n\
               v 0.5 0.5 0.5\nv 0.501 0.5 0.5\nv 0.501 0.5 0.501\nv 0.5 0.5 0.501\n\
               usemtl white\nf 1 4 3 2\nusemtl light\nf 5 6 7 8\n";
    let mtl = "newmtl white\nKd 0.5 0.5 0.5\nnewmtl light\nKd 0 0 0\nKe 10 10 10\n";
    let rt = runtime();
    let submitted = rt.block_on(async {
        let mut c = Target::new(&url).connect().await.unwrap();
        c.jobs
            .submit(v1::SubmitRequest {
                scene: Some(v1::submit_request::Scene::Upload(v1::SceneUpload {
                    obj_name: "tiny.obj".into(),
                    obj: obj.as_bytes().to_vec(),
                    mtl: [("s.mtl".to_string(), mtl.as_bytes().to_vec())].into(),
                })),
                parameters: Some(v1::Parameters {
                    directions: Some(33),
                    resolution: Some(16),
                    ..Default::default()
                }),
            })
            .await
    });
    let id = submitted.expect("submitted").into_inner().job_id;
    let failed = wait_status(&url, &id, "the failed set-up", |s| s.state == State::Failed as i32);
    assert!(failed.message.contains("no emitter is hit by any ray"), "{failed:?}");
    let job = FieldJob::open(
        &Store::open_existing(store.to_str().unwrap()).unwrap(),
        &JobId::parse(&id).unwrap(),
    )
    .unwrap();
    assert!(!job.is_set_up());
    let recorded = format!("{:?}", job.job().manifest().state);
    assert!(recorded.contains("no emitter is hit by any ray"), "{recorded}");
}

/// Waits (a minute at most) until `proc`'s log holds `needle`.
fn wait_for_log(proc: &Proc, needle: &str) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while !proc.log().contains(needle) {
        assert!(
            Instant::now() < deadline,
            "{} never logged {needle:?}:\n{}",
            proc.name,
            proc.log()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn progress_arrives_in_order_and_finished_snapshots_render_while_the_job_runs() {
    let scratch = temp("progress");
    let dir = scratch.path();
    let store = dir.join("store");
    let (_server, url) = serve(
        dir,
        &store,
        "127.0.0.1:0",
        &["--lease-seconds", "1", "--max-lease-batches", "1"],
    );
    let extra = ["--iterations", "3", "--perturb", "0"];
    let id = submit(&url, &extra);
    let rt = runtime();
    // Subscribe before any work is done, so the stream sees the whole job.
    let mut clients = rt.block_on(Target::new(&url).connect()).unwrap();
    let mut stream = rt
        .block_on(clients.jobs.watch(v1::JobRequest { job_id: id.clone() }))
        .unwrap()
        .into_inner();
    // Iterations have 2 batches (l = 33): the fourth lease, iteration 2's last batch, stalls.
    let mut stalled = worker(dir, "stalled", &url, &["--hang-after-leases", "3"]);
    stalled.wait_for_line("stalled holding lease");
    wait_status(&url, &id, "snapshot 1", |s| s.snapshots == [0, 1]);
    // Snapshot 1 renders while iteration 2 runs; snapshot 2 does not exist yet.
    let image = dir.join("snapshot1.pfm");
    let mut render = vec!["render", "--server", url.as_str(), id.as_str(), "--eye", "0.5,0.5,-1.2"];
    render.extend(["--target", "0.5,0.5,0.5", "--size", "32x32", "--samples", "1"]);
    let o = vlf(&[
        render.as_slice(),
        &["--snapshot", "1", "--out", image.to_str().unwrap()],
    ]
    .concat());
    assert!(o.status.success(), "{}", text(&o));
    assert!(std::fs::metadata(&image).unwrap().len() > 32 * 32 * 12);
    let o = vlf(&[
        render.as_slice(),
        &["--snapshot", "2", "--out", image.to_str().unwrap()],
    ]
    .concat());
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("snapshot 2"),
        "{}",
        text(&o)
    );

    // The stalled lease expires after a second and a healthy worker finishes the job.
    let _healthy = worker(dir, "healthy", &url, &[]);
    let events: Vec<v1::JobStatus> = rt.block_on(async {
        let mut events = Vec::new();
        while let Some(s) = stream.message().await.unwrap() {
            events.push(s);
        }
        events
    });
    assert!(events.len() >= 3, "{events:?}");
    assert!(events.windows(2).all(|w| w[0].seq < w[1].seq), "sequence out of order");
    assert!(
        events.windows(2).all(|w| w[0].snapshots.len() <= w[1].snapshots.len()),
        "snapshots went backwards"
    );
    let last = events.last().unwrap();
    assert_eq!(last.state, State::Finished as i32, "{last:?}");
    assert_eq!(last.snapshots, [0, 1, 2, 3]);
    assert!(
        events[..events.len() - 1]
            .iter()
            .all(|s| s.state != State::Finished as i32)
    );
    assert!(
        events
            .iter()
            .any(|s| s.state == State::Propagating as i32 && s.batches_done > 0)
    );
    // The final field renders from the server too.
    let o = vlf(&[render.as_slice(), &["--out", image.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", text(&o));
}

#[test]
fn auth_and_bad_requests_get_their_status_codes() {
    let scratch = temp("auth");
    let dir = scratch.path();
    let store = dir.join("store");
    let (_server, url) = serve(
        dir,
        &store,
        "127.0.0.1:0",
        &["--token", "s3cret", "--max-upload-bytes", "20000"],
    );
    let rt = runtime();

    // Without the token, or with another, nothing is served.
    for token in [None, Some("wrong".to_string())] {
        let target = Target {
            url: url.clone(),
            token,
            ca_cert: None,
        };
        let mut c = rt.block_on(target.connect()).unwrap();
        let r = rt.block_on(c.jobs.list(v1::ListJobsRequest {}));
        assert_eq!(code(r).map(|c| c.0), Some(Code::Unauthenticated));
        let r = rt.block_on(c.workers.register(v1::RegisterRequest::default()));
        assert_eq!(
            code(r).map(|c| c.0),
            Some(Code::Unauthenticated),
            "another deployment's worker"
        );
    }
    let o = vlf(&["jobs", "--server", &url]);
    assert!(
        !o.status.success() && text(&o).contains("unauthenticated"),
        "{}",
        text(&o)
    );
    let o = vlf(&["worker", "--server", &url, "--token", "wrong"]);
    assert!(!o.status.success() && text(&o).contains("refused"), "{}", text(&o));

    // The health service alone answers without the token (probes carry none), and says only
    // whether each API serves.
    let o = vlf(&["health", "--server", &url]);
    assert!(o.status.success() && text(&o).contains("serving"), "{}", text(&o));
    let mut c = rt.block_on(Target::new(url.clone()).connect()).unwrap();
    for service in ["", "vlf.v1.Jobs", "vlf.v1.Workers", "vlf.v1.Tiles"] {
        let r = rt.block_on(c.health.check(HealthCheckRequest {
            service: service.into(),
        }));
        assert_eq!(
            r.map(|r| r.into_inner().status()).ok(),
            Some(ServingStatus::Serving),
            "health of `{service}`"
        );
    }
    let r = rt.block_on(c.health.check(HealthCheckRequest {
        service: "vlf.v1.Nothing".into(),
    }));
    assert_eq!(code(r).map(|c| c.0), Some(Code::NotFound));

    let target = Target {
        url: url.clone(),
        token: Some("s3cret".into()),
        ca_cert: None,
    };
    let mut c = rt.block_on(target.connect()).unwrap();
    let unknown = JobId::generate().to_string();
    let r = rt.block_on(c.jobs.get(v1::JobRequest {
        job_id: unknown.clone(),
    }));
    assert_eq!(code(r).map(|c| c.0), Some(Code::NotFound));
    let r = rt.block_on(c.jobs.watch(v1::JobRequest {
        job_id: unknown.clone(),
    }));
    assert_eq!(code(r).map(|c| c.0), Some(Code::NotFound));
    let r = rt.block_on(c.jobs.get(v1::JobRequest {
        job_id: "../etc".into(),
    }));
    assert_eq!(code(r).map(|c| c.0), Some(Code::InvalidArgument));
    let o = vlf(&["status", &unknown, "--server", &url, "--token", "s3cret"]);
    assert!(!o.status.success() && text(&o).contains("not found"), "{}", text(&o));

    let submit = |obj: &str, parameters: v1::Parameters| {
        let mut c = c.clone();
        rt.block_on(c.jobs.submit(v1::SubmitRequest {
            scene: Some(v1::submit_request::Scene::Upload(v1::SceneUpload {
                obj_name: "bad.obj".into(),
                obj: obj.as_bytes().to_vec(),
                mtl: Default::default(),
            })),
            parameters: Some(parameters),
        }))
    };
    let (c1, m1) = code(submit("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", Default::default())).unwrap();
    assert_eq!(c1, Code::InvalidArgument);
    assert!(m1.contains("bad.obj:2"), "{m1}");
    let (c2, m2) = code(submit(
        "v 0 0 0\n",
        v1::Parameters {
            directions: Some(100),
            ..Default::default()
        },
    ))
    .unwrap();
    assert_eq!(c2, Code::InvalidArgument);
    assert!(m2.contains("directions"), "{m2}");
    let (c3, m3) = code(submit(&"# padding\n".repeat(3000), Default::default())).unwrap();
    assert_eq!(c3, Code::ResourceExhausted);
    assert!(m3.contains("at most 20000 bytes"), "{m3}");

    let r = rt.block_on(c.workers.heartbeat(v1::HeartbeatRequest { worker_id: "w9".into() }));
    assert_eq!(code(r).map(|c| c.0), Some(Code::NotFound));
    let r = rt.block_on(c.workers.lease(v1::LeaseRequest {
        worker_id: "w9".into(),
        wait_ms: 0,
    }));
    assert_eq!(code(r).map(|c| c.0), Some(Code::NotFound));

    // A job with no worker: cancel it; its state is recorded in the store, and the blobs are
    // served (a missing one is NOT_FOUND, a path outside the job INVALID_ARGUMENT).
    let mirrors = scene("mirrors.obj");
    let mut args = vec![
        "submit",
        mirrors.as_str(),
        "--server",
        url.as_str(),
        "--token",
        "s3cret",
    ];
    args.extend(PARAMS);
    let o = vlf(&args);
    assert!(o.status.success(), "{}", text(&o));
    let id = String::from_utf8_lossy(&o.stdout)
        .lines()
        .next()
        .unwrap()
        .trim()
        .to_string();
    let o = vlf(&["cancel", &id, "--server", &url, "--token", "s3cret"]);
    assert!(o.status.success(), "{}", text(&o));
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let o = vlf(&["jobs", store.to_str().unwrap()]);
        if String::from_utf8_lossy(&o.stdout).contains("cancelled") {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the store never recorded the cancellation: {}",
            text(&o)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = vlf(&["watch", &id, "--server", &url, "--token", "s3cret"]);
    assert!(!o.status.success() && text(&o).contains("cancelled"), "{}", text(&o));
    let fetch = |names: &[&str]| {
        let (mut c, id) = (c.clone(), id.clone());
        rt.block_on(async move {
            let mut s = c
                .tiles
                .fetch(v1::FetchRequest {
                    job_id: id.clone(),
                    names: names.iter().map(|n| n.to_string()).collect(),
                })
                .await?
                .into_inner();
            let mut got = Vec::new();
            while let Some(b) = s.message().await? {
                got.push(b);
            }
            Ok::<_, tonic::Status>(got)
        })
    };
    let got = fetch(&["manifest.blob", "iters/00000/summary.blob"]).unwrap();
    assert_eq!(got.len(), 2);
    assert_eq!(fetch(&["field/summary.blob"]).unwrap_err().code(), Code::NotFound);
    assert_eq!(
        fetch(&["../other/manifest.blob"]).unwrap_err().code(),
        Code::InvalidArgument
    );
}

#[test]
fn health_waits_for_a_coordinator_to_start_and_fails_without_one() {
    let scratch = temp("health");
    let dir = scratch.path();
    let port = free_port();
    let url = format!("http://127.0.0.1:{port}");
    let o = vlf(&["health", "--server", &url]);
    assert!(
        !o.status.success() && text(&o).contains("does not serve") && text(&o).contains("refused"),
        "{}",
        text(&o)
    );
    // Asked before the coordinator listens, `--wait` keeps asking until it serves.
    let mut waiting = spawn(dir, "health", &["health", "--server", &url, "--wait", "120"]);
    std::thread::sleep(Duration::from_millis(300));
    assert!(
        waiting.child.try_wait().unwrap().is_none(),
        "health returned before any coordinator started:\n{}",
        waiting.log()
    );
    let store = dir.join("store");
    let (_server, served) = serve(dir, &store, &format!("127.0.0.1:{port}"), &["--token", "t"]);
    assert_eq!(served, url);
    let line = waiting.wait_for_line("serving");
    assert_eq!(line, format!("{url}: serving"));
    let status = waiting.child.wait().unwrap();
    assert!(status.success(), "{status:?}:\n{}", waiting.log());
    let o = vlf(&["health", "--server", &url, "--wait", "nan"]);
    assert!(!o.status.success() && text(&o).contains("--wait"), "{}", text(&o));
}

#[test]
fn a_coordinator_stopped_while_a_client_watches_ends_the_watch_and_exits() {
    let scratch = temp("stop-watched");
    let dir = scratch.path();
    let store = dir.join("store");
    let (mut server, url) = serve(dir, &store, "127.0.0.1:0", &[]);
    // No worker: the job waits for one, and its watch would stay open as long.
    let id = submit(&url, &[]);
    let rt = runtime();
    let mut c = rt.block_on(Target::new(url.clone()).connect()).unwrap();
    let mut stream = rt
        .block_on(c.jobs.watch(v1::JobRequest { job_id: id.clone() }))
        .unwrap()
        .into_inner();
    let first = rt.block_on(stream.message()).unwrap().expect("a first status");
    assert_eq!(first.job_id, id);
    // A client that checks the coordinator's health by streaming it.
    let mut health = rt
        .block_on(c.health.watch(HealthCheckRequest { service: String::new() }))
        .unwrap()
        .into_inner();
    let serving = rt.block_on(health.message()).unwrap().expect("a first health status");
    assert_eq!(serving.status(), ServingStatus::Serving);
    let term = std::process::Command::new("kill")
        .args(["-TERM", &server.child.id().to_string()])
        .status()
        .unwrap();
    assert!(term.success());
    // The stream ends with a reason (statuses may come before it, none after it).
    let end = loop {
        let next = rt.block_on(async { tokio::time::timeout(Duration::from_secs(60), stream.message()).await });
        match next.expect("the watch stayed open after the coordinator was told to stop") {
            Ok(Some(_)) => continue,
            Ok(None) => panic!("the watch ended without saying why"),
            Err(status) => break status,
        }
    };
    assert_eq!(end.code(), Code::Unavailable, "{end:?}");
    assert!(end.message().contains("shutting down"), "{end:?}");
    // The health stream says the coordinator no longer serves, then ends.
    let next = |health: &mut tonic::Streaming<_>| {
        rt.block_on(async { tokio::time::timeout(Duration::from_secs(60), health.message()).await })
            .expect("the health stream stayed open after the coordinator was told to stop")
    };
    let stopping: Option<HealthCheckResponse> = next(&mut health).unwrap();
    assert_eq!(stopping.map(|h| h.status()), Some(ServingStatus::NotServing));
    assert!(next(&mut health).unwrap().is_none(), "the health stream ends");
    // And the coordinator exits (a hang is caught here, not timed).
    let deadline = Instant::now() + Duration::from_secs(60);
    let exited = loop {
        if let Some(status) = server.child.try_wait().unwrap() {
            break status;
        }
        assert!(
            Instant::now() < deadline,
            "the coordinator did not exit:\n{}",
            server.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(exited.success(), "{exited:?}:\n{}", server.log());
}

#[test]
fn tls_with_a_token_serves_workers_and_clients_that_trust_the_ca() {
    let scratch = temp("tls");
    let dir = scratch.path();
    let store = dir.join("store");
    let cert = rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).unwrap();
    let (cert_pem, key_pem, ca) = (dir.join("cert.pem"), dir.join("key.pem"), dir.join("ca.pem"));
    std::fs::write(&cert_pem, cert.cert.pem()).unwrap();
    std::fs::write(&key_pem, cert.signing_key.serialize_pem()).unwrap();
    // Self-signed: the certificate is its own CA.
    std::fs::write(&ca, cert.cert.pem()).unwrap();
    let (_server, url) = serve(
        dir,
        &store,
        "127.0.0.1:0",
        &[
            "--tls-cert",
            cert_pem.to_str().unwrap(),
            "--tls-key",
            key_pem.to_str().unwrap(),
            "--token",
            "t0ken",
        ],
    );
    assert!(url.starts_with("https://"), "{url}");
    let url = url.replace("127.0.0.1", "localhost");
    let ca = ca.to_str().unwrap();
    let _worker = worker(dir, "tls-worker", &url, &["--ca-cert", ca, "--token", "t0ken"]);
    let mirrors = scene("mirrors.obj");
    let mut args = vec!["submit", mirrors.as_str(), "--server", url.as_str(), "--ca-cert", ca];
    args.extend(["--token", "t0ken", "--iterations", "2", "--watch"]);
    args.extend(PARAMS);
    let o = vlf(&args);
    assert!(o.status.success(), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("finished"), "{}", text(&o));
    // A client that does not trust the CA is refused by TLS, before any token is read.
    let o = vlf(&["jobs", "--server", &url, "--token", "t0ken"]);
    assert!(!o.status.success(), "{}", text(&o));
    // Plain HTTP to a TLS port gets no answer either.
    let o = vlf(&[
        "jobs",
        "--server",
        &url.replace("https://", "http://"),
        "--token",
        "t0ken",
    ]);
    assert!(!o.status.success(), "{}", text(&o));
}

/// A TCP proxy in front of `upstream` (an `http://HOST:PORT` URL) that drops connections: the
/// k-th connection it accepts is cut, both ways, once the server has sent `cut × 2^(k-1)` bytes
/// through it. Every call fails on the first connections; later ones live long enough.
struct FlakyProxy {
    url: String,
    cuts: std::sync::Arc<std::sync::atomic::AtomicUsize>,
}

fn flaky_proxy(upstream: &str, cut: usize) -> FlakyProxy {
    use std::io::{Read, Write};
    use std::net::{Shutdown, TcpListener, TcpStream};
    use std::sync::atomic::{AtomicUsize, Ordering};
    let upstream = upstream.trim_start_matches("http://").to_string();
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let cuts = std::sync::Arc::new(AtomicUsize::new(0));
    let counter = cuts.clone();
    std::thread::spawn(move || {
        for (k, client) in listener.incoming().enumerate() {
            let Ok(client) = client else { continue };
            let Ok(server) = TcpStream::connect(&upstream) else {
                continue;
            };
            let limit = cut.saturating_mul(1 << k.min(40));
            let (mut c_in, mut s_out) = (client.try_clone().unwrap(), server.try_clone().unwrap());
            std::thread::spawn(move || {
                let _ = std::io::copy(&mut c_in, &mut s_out);
                let _ = s_out.shutdown(Shutdown::Write);
            });
            let counter = counter.clone();
            std::thread::spawn(move || {
                let (mut from, mut to) = (server, client);
                let mut sent = 0;
                let mut buffer = [0u8; 4096];
                loop {
                    let n = match from.read(&mut buffer) {
                        Ok(0) | Err(_) => break,
                        Ok(n) => n.min(limit - sent),
                    };
                    if to.write_all(&buffer[..n]).is_err() {
                        break;
                    }
                    sent += n;
                    if sent >= limit {
                        counter.fetch_add(1, Ordering::SeqCst);
                        break;
                    }
                }
                let _ = to.shutdown(Shutdown::Both);
                let _ = from.shutdown(Shutdown::Both);
            });
        }
    });
    FlakyProxy { url, cuts }
}

#[test]
fn view_streams_through_a_coordinator_that_drops_connections() {
    let scratch = temp("flaky");
    let dir = scratch.path();
    let store = dir.join("store");
    let (_server, url) = serve(dir, &store, "127.0.0.1:0", &[]);
    let _worker = worker(dir, "w1", &url, &[]);
    let id = submit(&url, &[]);
    watch(&url, &id);
    // An unknown job is a final answer: said once, not asked again.
    let o = vlf(&["view", "--server", &url, "no-such-job"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("not found"), "{}", text(&o));
    assert!(!err.contains("trying again"), "{err}");
    let Some(display) = display::x_display() else { return };
    let proxy = flaky_proxy(&url, 1500);
    // The wall mirror close up, mirrors from the rays: diffuse maps and tiles stream.
    let view = |server: &str, name: &str| -> (Output, PathBuf) {
        let shot = dir.join(name);
        let o = vlf_command()
            .args([
                "view",
                "--server",
                server,
                &id,
                "--eye",
                "300,270,295",
                "--target",
                "0,270,295",
            ])
            .args([
                "--fovy",
                "30",
                "--size",
                "64x48",
                "--frames",
                "2",
                "--no-vsync",
                "--screenshot",
            ])
            .arg(&shot)
            .env("DISPLAY", &display.name)
            .output()
            .expect("run vlf view");
        (o, shot)
    };
    let (direct, a) = view(&url, "direct.pfm");
    if !direct.status.success()
        && String::from_utf8_lossy(&direct.stderr).contains("no GPU adapter")
        && std::env::var_os("VLF_REQUIRE_GPU").is_none()
    {
        eprintln!("skipped: no GPU adapter");
        return;
    }
    assert!(direct.status.success(), "{}", text(&direct));
    let (flaky, b) = view(&proxy.url, "flaky.pfm");
    assert!(flaky.status.success(), "{}", text(&flaky));
    let cuts = proxy.cuts.load(std::sync::atomic::Ordering::SeqCst);
    assert!(cuts >= 2, "the proxy cut {cuts} connections");
    // Nothing half-fetched was drawn: the same frame as over a sound connection.
    let (a, b) = (
        vlf_core::render::Image::load_pfm(&a).unwrap(),
        vlf_core::render::Image::load_pfm(&b).unwrap(),
    );
    assert!(a.pixels == b.pixels, "the frames differ\n{}", text(&flaky));
    assert!(a.mean()[0] > 0.0);
}
