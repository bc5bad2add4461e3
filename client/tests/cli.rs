//! The `vlf` command line end to end: propagate a bundled scene, render it,
//! and refuse bad input with a clear message and a non-zero exit code.

#[path = "../../tests/support/display.rs"]
mod display;

use display::x_display;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use vlf_core::field::LightField;
use vlf_core::propagate::Propagation;
use vlf_store::blob::Encoding;
use vlf_store::{FieldJob, Job, JobId, Stage, Store};

/// `vlf ARGS`, without the coordinator a developer's shell may name (`VLF_SERVER`,
/// `VLF_TOKEN`): what each test asks for is all it gets.
fn vlf(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vlf"))
        .args(args)
        .env_remove("VLF_SERVER")
        .env_remove("VLF_TOKEN")
        .output()
        .expect("run vlf")
}

fn scene(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name)
        .to_string_lossy()
        .into_owned()
}

/// A path that does not exist yet, inside a scratch directory removed when the guard drops
/// (so a test run leaves nothing behind in the temporary folder, pass or fail).
struct Temp {
    _root: tempfile::TempDir,
    path: PathBuf,
}

impl std::ops::Deref for Temp {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.path
    }
}

impl AsRef<Path> for Temp {
    fn as_ref(&self) -> &Path {
        &self.path
    }
}

fn temp(name: &str) -> Temp {
    let root = tempfile::Builder::new()
        .prefix("vlf-cli-")
        .tempdir()
        .expect("scratch directory");
    let path = root.path().join(name);
    Temp { _root: root, path }
}

/// The bundled Cornell scenes' usual camera, as flags.
const CORNELL_VIEW: [&str; 6] = ["--eye", "278,273,-800", "--target", "278,273,0", "--fovy", "39"];

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn propagate(out: &Path, threads: &str) -> Output {
    vlf(&[
        "propagate",
        &scene("cornell.obj"),
        "--out",
        out.to_str().unwrap(),
        "--directions",
        "33",
        "--resolution",
        "32",
        "--tile",
        "8",
        "--iterations",
        "3",
        "--threads",
        threads,
    ])
}

#[test]
fn propagate_then_render_every_format() {
    let out = temp("cornell");
    let o = propagate(&out, "2");
    assert!(o.status.success(), "{}", stderr(&o));
    let summary = String::from_utf8_lossy(&o.stdout);
    for key in ["iterations      3", "unshot fraction", "field memory", "energy balance"] {
        assert!(summary.contains(key), "summary lacks {key:?}: {summary}");
    }
    for ext in ["pfm", "exr", "png"] {
        let image = out.join(format!("view.{ext}"));
        let o = vlf(&[
            "render",
            out.to_str().unwrap(),
            "--eye",
            "278,273,-800",
            "--target",
            "278,273,0",
            "--fovy",
            "39",
            "--size",
            "64x48",
            // The GPU below draws the field's direct light.
            "--direct",
            "field",
            "--out",
            image.to_str().unwrap(),
            "--exposure",
            "-1",
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(std::fs::metadata(&image).map(|m| m.len() > 100).unwrap_or(false));
    }
    let img = vlf_core::render::Image::load_pfm(out.join("view.pfm")).unwrap();
    assert_eq!((img.width, img.height), (64, 48));
    // The same view on the GPU: the same image up to edge pixels (the viewer's tests bound it).
    // Exact direct light too: the GPU's (what auto takes there) is the CPU's.
    let gpu_image = out.join("gpu.pfm");
    let cpu_exact = out.join("exact.pfm");
    let args = [
        &["render", out.to_str().unwrap()][..],
        &CORNELL_VIEW[..],
        &["--size", "64x48"][..],
    ]
    .concat();
    let o = vlf(&[&args[..], &["--direct", "exact", "--out", cpu_exact.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let exact = vlf_core::render::Image::load_pfm(&cpu_exact).unwrap();
    for (direct, cpu) in [("field", &img), ("exact", &exact), ("auto", &exact)] {
        let o = vlf(&[
            &args[..],
            &["--gpu", "--direct", direct, "--out", gpu_image.to_str().unwrap()],
        ]
        .concat());
        if gpu_available(&o) {
            let gpu = vlf_core::render::Image::load_pfm(&gpu_image).unwrap();
            let (a, b) = (cpu.mean(), gpu.mean());
            assert!(
                (0..3).all(|c| (a[c] - b[c]).abs() < 1e-3 * a[c]),
                "--direct {direct}: CPU {a:?} vs GPU {b:?}"
            );
        }
    }
    let (a, b) = (img.mean()[0], exact.mean()[0]);
    assert!(
        (a - b).abs() > 1e-3 * a,
        "exact direct light changes the image: {a} vs {b}"
    );
    let mean = img.mean();
    assert!(
        mean.iter().all(|&c| c > 0.01 && c.is_finite()),
        "dark or broken image: {mean:?}"
    );
    // The red wall is on the left (x = 0) as seen from the camera.
    let left = img.pixels[24 * 64 + 12];
    let right = img.pixels[24 * 64 + 52];
    assert!(
        left[0] > left[1] && right[1] > right[0],
        "walls swapped: left {left:?} right {right:?}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// Whether a `vlf render --gpu` ran: it succeeded, or failed only for want of an adapter on a
/// machine that does not require one (CI installs lavapipe and sets `VLF_REQUIRE_GPU`).
fn gpu_available(o: &Output) -> bool {
    if o.status.success() {
        return true;
    }
    let err = stderr(o);
    assert!(
        err.contains("no GPU adapter") && std::env::var_os("VLF_REQUIRE_GPU").is_none(),
        "vlf render --gpu failed: {err}"
    );
    eprintln!("skipped the GPU render: {err}");
    false
}

/// The newest job of a store directory.
fn only_job(dir: &Path) -> FieldJob {
    let store = Store::open_existing(dir.to_str().unwrap()).unwrap();
    let id = Job::list(&store).unwrap().pop().expect("a job");
    FieldJob::open(&store, &id).unwrap()
}

/// Fields equal up to the wall-clock times in their statistics.
fn same_field(a: &LightField, b: &LightField) -> bool {
    let mut b = b.clone();
    for (sa, sb) in a.stats.iter().zip(b.stats.iter_mut()) {
        sb.seconds = sa.seconds;
    }
    *a == b
}

#[test]
fn thread_count_does_not_change_the_field() {
    let (a, b) = (temp("t1"), temp("t2"));
    assert!(propagate(&a, "1").status.success());
    assert!(propagate(&b, "2").status.success());
    let fa = only_job(&a).load(Stage::Field).unwrap();
    let fb = only_job(&b).load(Stage::Field).unwrap();
    assert!(same_field(&fa, &fb), "fields differ between 1 and 2 threads");
    let _ = std::fs::remove_dir_all(&a);
    let _ = std::fs::remove_dir_all(&b);
}

/// `vlf propagate --resume` finishes a job that stopped after its first
/// snapshot with the same bits as a run that never stopped; snapshots of
/// the job render; a finished job cannot be resumed.
#[test]
fn resume_finishes_an_interrupted_job_with_the_same_bits() {
    let dir = temp("resume");
    let url = dir.to_str().unwrap();
    let o = vlf(&[
        "propagate",
        &scene("mirrors.obj"),
        "--store",
        url,
        "--directions",
        "33",
        "--resolution",
        "16",
        "--tile",
        "4",
        "--iterations",
        "3",
        "--encoding",
        "f32",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let digest_of = |o: &std::process::Output| {
        let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
        let line = stdout.lines().find(|l| l.trim_start().starts_with("digest"));
        let digest = line.and_then(|l| l.split_whitespace().nth(1)).map(str::to_string);
        digest.unwrap_or_else(|| panic!("no digest in:\n{stdout}"))
    };
    let digest = digest_of(&o);
    let straight = only_job(&dir);
    // The same job, stopped (as by a crash) after one committed snapshot.
    let store = Store::open(url).unwrap();
    let mut p = Propagation::new(straight.scene().clone(), straight.options().clone()).unwrap();
    let mut job = FieldJob::create(&store, &p, Encoding::F32).unwrap();
    p.step(|_| {});
    job.write_snapshot(&p).unwrap();
    let id = job.id().to_string();
    drop((job, p));
    let manifest = dir.join("jobs").join(&id).join("manifest.blob");
    let stopped = std::fs::read(&manifest).expect("the stopped job's manifest");
    // `vlf run` of another job over the same store runs that job alone: the stopped one is
    // left as it was (the embedded coordinator used to take up, and drive, every unfinished
    // job of its store).
    let o = vlf(&[
        "run",
        &scene("cornell.obj"),
        "--store",
        url,
        "--directions",
        "9",
        "--resolution",
        "8",
        "--tile",
        "4",
        "--iterations",
        "1",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        std::fs::read(&manifest).unwrap(),
        stopped,
        "vlf run of another job touched the stopped job"
    );
    // A resumed job runs with its own parameters: another flag is refused, not ignored.
    let o = vlf(&["propagate", "--store", url, "--resume", &id, "--iterations", "50"]);
    assert!(
        !o.status.success() && stderr(&o).contains("own parameters"),
        "{}",
        stderr(&o)
    );
    // A store to resume from is opened as it is, not created where a typo points.
    let typo = dir.join("typo");
    let o = vlf(&["run", "--store", typo.to_str().unwrap(), "--resume", &id]);
    assert!(!o.status.success() && !typo.exists(), "{}", stderr(&o));
    assert_eq!(std::fs::read(&manifest).unwrap(), stopped);
    let o = vlf(&["propagate", "--store", url, "--resume", &id, "--threads", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("after 1 iterations"));
    assert_eq!(digest_of(&o), digest, "the same bits, the same digest");
    let resumed = FieldJob::open(&store, &JobId::parse(&id).unwrap()).unwrap();
    assert_eq!(resumed.job().manifest().finished_iterations, vec![0, 1, 2, 3]);
    let (a, b) = (
        resumed.load(Stage::Field).unwrap(),
        straight.load(Stage::Field).unwrap(),
    );
    assert!(
        same_field(&a, &b),
        "the resumed field differs from the uninterrupted one"
    );
    let render_snapshot = |snapshot: &str, direct: &str, out: &str, server: Option<&str>| {
        let mut command = Command::new(env!("CARGO_BIN_EXE_vlf"));
        command.env_remove("VLF_SERVER").env_remove("VLF_TOKEN");
        if let Some(server) = server {
            command.env("VLF_SERVER", server);
        }
        let args = [
            "render",
            url,
            &id,
            "--snapshot",
            snapshot,
            "--direct",
            direct,
            "--eye",
            "278,273,-800",
            "--target",
            "278,273,0",
            "--size",
            "16x16",
            "--out",
            out,
        ];
        command.args(args).output().expect("run vlf")
    };
    for snapshot in ["0", "2"] {
        for direct in ["auto", "field"] {
            let image = dir.join(format!("s{snapshot}-{direct}.pfm"));
            let o = render_snapshot(snapshot, direct, image.to_str().unwrap(), None);
            assert!(o.status.success(), "{}", stderr(&o));
        }
    }
    // Snapshot 0 is the emitters' light alone: exact direct light has nothing to exchange there,
    // so auto draws it as the field has it (it used to take snapshot 1's direct light off the
    // walls, black where it was not made up), and exact is refused.
    let image = |name: &str| std::fs::read(dir.join(name)).unwrap();
    assert_eq!(image("s0-auto.pfm"), image("s0-field.pfm"));
    assert_ne!(image("s2-auto.pfm"), image("s2-field.pfm"));
    let o = render_snapshot("0", "exact", dir.join("x.pfm").to_str().unwrap(), None);
    assert!(
        !o.status.success() && stderr(&o).contains("snapshot 0"),
        "{}",
        stderr(&o)
    );
    let o = vlf(&["view", url, &id, "--snapshot", "0", "--direct", "exact"]);
    assert!(
        !o.status.success() && stderr(&o).contains("snapshot 0"),
        "{}",
        stderr(&o)
    );
    // `VLF_SERVER` names the coordinator of `submit` and `watch`; a store given to `render` is
    // still a store.
    let o = render_snapshot(
        "2",
        "auto",
        dir.join("env.pfm").to_str().unwrap(),
        Some("http://127.0.0.1:9"),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(image("env.pfm"), image("s2-auto.pfm"));
    let o = vlf(&["propagate", "--store", url, "--resume", &id]);
    assert!(!o.status.success() && stderr(&o).contains("finished"), "{}", stderr(&o));
    let finished = std::fs::read(&manifest).unwrap();
    let o = vlf(&["run", "--store", url, "--resume", &id, "--resample"]);
    assert!(
        !o.status.success() && stderr(&o).contains("is finished"),
        "{}",
        stderr(&o)
    );
    assert_eq!(
        std::fs::read(&manifest).unwrap(),
        finished,
        "an ended job was rewritten"
    );
    let o = vlf(&["jobs", url]);
    let listed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(o.status.success(), "{}", stderr(&o));
    for job in [id.clone(), straight.id().to_string()] {
        let line = listed.lines().find(|l| l.starts_with(&job));
        assert!(
            line.is_some_and(|l| l.ends_with(&format!("digest {digest}"))),
            "{listed}"
        );
    }
    // A job whose final summary is damaged is listed as such; the others as before.
    let summary = dir.join("jobs").join(&id).join("field").join("summary.blob");
    assert!(summary.is_file(), "{}", summary.display());
    std::fs::write(&summary, b"not a blob").unwrap();
    let o = vlf(&["jobs", url]);
    let listed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(o.status.success(), "{}", stderr(&o));
    let damaged = listed.lines().find(|l| l.starts_with(&id)).unwrap_or_default();
    assert!(
        damaged.contains("digest unreadable") && damaged.contains("summary"),
        "{listed}"
    );
    assert!(
        listed.contains(&format!("{}  finished", straight.id())) && listed.contains(&digest),
        "{listed}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_input_gets_a_clear_error() {
    let out = temp("bad");
    let o_str = out.to_str().unwrap().to_string();
    // An empty store: no job there.
    std::fs::create_dir_all(&out).unwrap();
    let cornell = scene("cornell.obj");
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["propagate", "/nonexistent/scene.obj", "--out", &o_str],
            "scene.obj",
        ),
        (
            vec!["propagate", &cornell, "--out", &o_str, "--directions", "100"],
            "directions",
        ),
        (vec!["propagate", &cornell, "--out", &o_str, "--tile", "7"], "divide"),
        (
            vec!["propagate", &cornell, "--out", &o_str, "--iterations", "0"],
            "iterations",
        ),
        (
            vec!["propagate", &cornell, "--out", &o_str, "--converge", "2"],
            "threshold",
        ),
        (
            vec!["propagate", &cornell, "--out", &o_str, "--threads", "0"],
            "threads",
        ),
        (
            vec!["propagate", &cornell, "--out", &o_str, "--subfield-memory", "lots"],
            "subfield-memory",
        ),
        (
            vec!["propagate", &cornell, "--out", &o_str, "--resolution", "100000"],
            "resolution",
        ),
        (
            vec![
                "propagate",
                &cornell,
                "--out",
                &o_str,
                "--iterations",
                "2",
                "--converge",
                "0.1",
            ],
            "cannot be used",
        ),
        (
            vec![
                "render",
                "/nonexistent",
                "--eye",
                "0,0,0",
                "--target",
                "0,0,1",
                "--out",
                "x.png",
            ],
            "no store directory",
        ),
        (
            vec![
                "render",
                &o_str,
                "no-such-job",
                "--eye",
                "0,0,0",
                "--target",
                "0,0,1",
                "--out",
                "x.png",
            ],
            "not found",
        ),
        (
            vec!["propagate", "--store", &o_str, "--resume", "Bad Id"],
            "invalid job id",
        ),
        (
            vec!["propagate", &cornell, "--store", "ftp://host/x"],
            "unsupported scheme",
        ),
        (
            vec!["render", &o_str, "--eye", "0,0", "--target", "0,0,1", "--out", "x.png"],
            "X,Y,Z",
        ),
        (
            vec![
                "render", &o_str, "--eye", "0,0,0", "--target", "0,0,1", "--size", "0x10", "--out", "x.png",
            ],
            "width must be between 1 and 16384",
        ),
        // What the output refuses is refused before the store is read (this one has no job).
        (
            vec![
                "render",
                &o_str,
                "--eye",
                "0,0,0",
                "--target",
                "0,0,1",
                "--out",
                "/nonexistent/folder/x.png",
            ],
            "folder /nonexistent/folder does not exist",
        ),
        (
            vec![
                "render", &o_str, "--eye", "0,0,0", "--target", "0,0,1", "--out", "x.jpg",
            ],
            "unsupported extension",
        ),
        (
            vec![
                "render",
                &o_str,
                "--eye",
                "0,0,0",
                "--target",
                "0,0,1",
                "--out",
                "x.png",
                "--object",
                "cube.obj",
                "--object-directions",
                "100",
            ],
            "--object-directions must be one of",
        ),
        (
            vec![
                "render",
                &o_str,
                "--eye",
                "0,0,0",
                "--target",
                "0,0,1",
                "--out",
                "x.png",
                "--exposure",
                "nan",
            ],
            "exposure must be finite",
        ),
    ];
    for (args, needle) in cases {
        let o = vlf(&args);
        assert!(!o.status.success(), "accepted {args:?}");
        let e = stderr(&o);
        assert!(
            e.to_lowercase().contains(&needle.to_lowercase()),
            "{args:?}: message lacks {needle:?}: {e}"
        );
        assert!(!e.contains("panicked"), "{args:?} panicked: {e}");
    }
}

#[test]
fn mirrors_scene_plans_propagates_and_renders_both_ways() {
    let out = temp("mirrors");
    let o = vlf(&[
        "propagate",
        &scene("mirrors.obj"),
        "--out",
        out.to_str().unwrap(),
        "--directions",
        "129",
        "--resolution",
        "32",
        "--iterations",
        "4",
        "--resample",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("2 of 2 mirrors reachable"), "{text}");
    assert!(text.contains("perturbation: off"), "{text}");
    // Recorded with the job, so that whoever resumes it finishes it as asked.
    assert!(only_job(&out).job().manifest().resample, "--resample is not recorded");
    let cornell = vlf(&[
        "propagate",
        &scene("cornell.obj"),
        "--out",
        out.join("c").to_str().unwrap(),
        "--directions",
        "9",
        "--resolution",
        "16",
        "--iterations",
        "1",
    ]);
    assert!(String::from_utf8_lossy(&cornell.stdout).contains("specular: none"));
    let mut means = Vec::new();
    for mode in ["rays", "trace"] {
        let image = out.join(format!("{mode}.pfm"));
        let o = vlf(&[
            "render",
            out.to_str().unwrap(),
            "--eye",
            "278,273,-800",
            "--target",
            "278,273,0",
            "--fovy",
            "39",
            "--size",
            "48x48",
            "--specular",
            mode,
            // The GPU below draws the field's direct light.
            "--direct",
            "field",
            "--out",
            image.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        let img = vlf_core::render::Image::load_pfm(&image).unwrap();
        assert!(img.pixels.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
        means.push(img.mean()[0]);
    }
    // The two mirror modes differ only on the mirrors' pixels.
    assert!((means[0] - means[1]).abs() < 0.25 * means[1], "{means:?}");
    // The GPU draws mirrors both ways, as the CPU does.
    let view = [
        &["render", out.to_str().unwrap()][..],
        &CORNELL_VIEW[..],
        &["--size", "48x48", "--gpu", "--direct", "field"][..],
    ]
    .concat();
    let image = out.join("gpu.pfm");
    for (mode, cpu) in ["rays", "trace"].iter().zip(&means) {
        let o = vlf(&[&view[..], &["--specular", mode, "--out", image.to_str().unwrap()]].concat());
        if gpu_available(&o) {
            let m = vlf_core::render::Image::load_pfm(&image).unwrap().mean()[0];
            assert!((m - cpu).abs() < 1e-3 * cpu, "{mode}: GPU {m} vs CPU {cpu}");
        }
    }
    let o = vlf(&[
        "render",
        out.to_str().unwrap(),
        "--eye",
        "1,1,1",
        "--target",
        "0,0,0",
        "--specular",
        "mirror",
        "--out",
        "x.png",
    ]);
    assert!(!o.status.success() && stderr(&o).contains("rays"));
    let _ = std::fs::remove_dir_all(&out);
}

/// `vlf run` (coordinator and worker replicas in one process, exchanging
/// their work through the store) stores the same field as `vlf propagate`,
/// for 1 and 3 workers, on the mirror scene.
#[test]
fn embedded_service_matches_propagate_bit_for_bit() {
    let dir = temp("run");
    let params = [
        "--directions",
        "33",
        "--resolution",
        "16",
        "--tile",
        "4",
        "--iterations",
        "3",
        "--encoding",
        "f32",
    ];
    let mirrors = scene("mirrors.obj");
    let mut fields = Vec::new();
    for (i, command) in [
        vec!["propagate"],
        vec!["run", "--workers", "1"],
        vec!["run", "--workers", "3"],
    ]
    .into_iter()
    .enumerate()
    {
        // One store each: job ids made within one second do not sort by time.
        let store = dir.join(i.to_string());
        let mut args = command.clone();
        args.extend([mirrors.as_str(), "--store", store.to_str().unwrap()]);
        args.extend(params);
        let o = vlf(&args);
        assert!(o.status.success(), "{command:?}: {}", stderr(&o));
        fields.push(only_job(&store).load(Stage::Field).unwrap());
    }
    assert!(
        same_field(&fields[0], &fields[1]),
        "vlf run (1 worker) differs from vlf propagate"
    );
    assert!(
        same_field(&fields[0], &fields[2]),
        "vlf run (3 workers) differs from vlf propagate"
    );
    let o = vlf(&[
        "run",
        &scene("cornell.obj"),
        "--store",
        dir.to_str().unwrap(),
        "--workers",
        "0",
    ]);
    assert!(!o.status.success() && stderr(&o).contains("--workers"));
    // A `memory://` store lives in the process: the summary reads it through the same handle.
    let mut args = vec!["run", mirrors.as_str(), "--store", "memory://"];
    args.extend(params);
    let o = vlf(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("unshot fraction"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bench_reports_every_way_and_iteration_and_refuses_absurd_counts() {
    let dir = temp("bench");
    std::fs::create_dir_all(&dir).unwrap();
    let report = dir.join("bench.md");
    let cornell = scene("cornell.obj");
    let args = [
        "bench",
        cornell.as_str(),
        "--directions",
        "33",
        "--resolution",
        "16",
        "--tile",
        "4",
        "--iterations",
        "3",
        "--repeat",
        "2",
        "--workers",
        "1,2",
        "--out",
        report.to_str().unwrap(),
    ];
    let o = vlf(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert_eq!(std::fs::read_to_string(&report).unwrap(), printed);
    assert!(printed.contains("Every run gave the in-process bits"), "{printed}");
    for way in [
        "| in-process | ",
        "| in-process, cut in 2 homes | ",
        "| service, 1 worker | ",
        "| service, 2 workers | ",
    ] {
        assert!(printed.contains(way), "{way} missing:\n{printed}");
    }
    assert!(
        !printed.contains("cut in 1 home"),
        "one worker needs no cut:\n{printed}"
    );
    // Two rounds are too few for a confidence interval of the median ratio: the column says so.
    assert!(printed.contains("| × in-process | × 95 % | × range |"), "{printed}");
    let row = printed
        .lines()
        .find(|l| l.starts_with("| service, 2 workers | "))
        .unwrap_or_else(|| panic!("{printed}"));
    assert_eq!(row.split('|').map(str::trim).filter(|c| *c == "–").count(), 1, "{row}");
    // One row per iteration, with the work each service run moved (perturbed: several blobs).
    let rows: Vec<&str> = printed
        .lines()
        .filter(|l| l.starts_with("| 1 |") || l.starts_with("| 2 |") || l.starts_with("| 3 |"))
        .collect();
    assert_eq!(rows.len(), 3, "{printed}");
    assert!(!printed.contains("| 4 |"));
    assert!(rows[0].ends_with("MB |") || rows[0].contains(" / "), "{}", rows[0]);
    assert!(!printed.contains("co-tenant"));
    // What each run cost in CPU, every thread of the process: a row per way, each run having
    // used some, in seconds (a busy share of the cores, not nanoseconds: the bound is loose
    // because a container's CPU quota may let a short run burst over its share of the cores).
    let cpu = printed
        .split("CPU per run")
        .nth(1)
        .and_then(|rest| rest.split("\n\n").nth(1))
        .unwrap_or_else(|| panic!("no CPU table:\n{printed}"));
    for way in [
        "in-process",
        "in-process, cut in 2 homes",
        "service, 1 worker",
        "service, 2 workers",
    ] {
        let row = cpu
            .lines()
            .find(|l| l.starts_with(&format!("| {way} | ")))
            .unwrap_or_else(|| panic!("{way} missing from the CPU table:\n{printed}"));
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        let seconds: f64 = cells[2].parse().unwrap_or_else(|_| panic!("{row}"));
        let busy: f64 = cells[6].parse().unwrap_or_else(|_| panic!("{row}"));
        assert!(seconds > 0.0, "{row}");
        assert!(busy > 0.0 && busy < 64.0, "{row}");
    }
    // The plain iterations' sums, paired by round: a row per way.
    let plain = printed
        .split("(the propagation's throughput")
        .nth(1)
        .and_then(|rest| rest.split("Through the store").next())
        .unwrap_or_else(|| panic!("no plain iterations:\n{printed}"));
    for way in ["| in-process | ", "| service, 1 worker | ", "| service, 2 workers | "] {
        assert!(
            plain.contains(way),
            "{way} missing from the plain iterations:\n{printed}"
        );
    }
    // What the service adds to the cut: a row for two workers, with a ratio in every column
    // that has one (two rounds give no interval).
    let added = plain
        .split("What the service adds to the cut")
        .nth(1)
        .and_then(|rest| rest.split("How the service spent").next())
        .unwrap_or_else(|| panic!("no table of what the service adds to the cut:\n{printed}"));
    let row = added
        .lines()
        .find(|l| l.starts_with("| service, 2 workers | "))
        .unwrap_or_else(|| panic!("{printed}"));
    let ratios: Vec<f64> = row.split('|').filter_map(|c| c.trim().parse().ok()).collect();
    assert_eq!(ratios.len(), 2, "{row}");
    assert!(ratios.iter().all(|r| r.is_finite() && *r > 0.0), "{row}");
    assert!(!added.contains("| service, 1 worker | "), "{printed}");
    // How the service's workers spent them: a row per service way, none for the in-process
    // runs; the workers' compute never exceeds what the span holds (balance in (0, 1]).
    let spent = plain
        .split("How the service spent those iterations")
        .nth(1)
        .unwrap_or_else(|| panic!("no table of how the workers were used:\n{printed}"));
    assert!(!spent.contains("| in-process"), "{printed}");
    for way in ["| service, 1 worker | ", "| service, 2 workers | "] {
        let row = spent
            .lines()
            .find(|l| l.starts_with(way))
            .unwrap_or_else(|| panic!("{way} missing from how the workers were used:\n{printed}"));
        let cells: Vec<f64> = row.split('|').filter_map(|c| c.trim().parse().ok()).collect();
        let [iteration, between, span, balance, waiting] = cells[..] else {
            panic!("{row}");
        };
        assert!(span > 0.0 && span <= iteration && between >= 0.0, "{row}");
        assert!(balance > 0.0 && balance <= 1.0 && waiting >= 0.0, "{row}");
    }
    // With a co-tenant: the same bits, and the report says so.
    let mut shared = args[..10].to_vec();
    shared.extend(["--repeat", "1", "--workers", "2", "--cotenant"]);
    let o = vlf(&shared);
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        printed.contains("Every run gave the in-process bits. With a co-tenant"),
        "{printed}"
    );
    // Over a store with a round trip: the mirror scene, whose workers write their mirror maps
    // behind their compute and read those that cross between them, still gives the
    // in-process bits with two workers, and the report names the store.
    let mirrors = scene("mirrors.obj");
    let mut far = args[..10].to_vec();
    far[1] = mirrors.as_str();
    far.extend(["--repeat", "1", "--workers", "2", "--latency", "2"]);
    let o = vlf(&far);
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        printed.contains("`memory://?latency=2ms` store") && printed.contains("Every run gave the in-process bits"),
        "{printed}"
    );
    // The Cornell box's perturbed iterations over a store 20 ms away: every pass's outputs take
    // longer to write than a worker waits for them, so each lease is reported in the background
    // once they are in while the next one computes — and the bits are still the in-process ones.
    let mut far = args[..10].to_vec();
    far.extend(["--repeat", "1", "--workers", "1,2", "--latency", "20"]);
    let o = vlf(&far);
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(printed.contains("Every run gave the in-process bits"), "{printed}");
    // Into a directory: the same bits, the report names it, and every run's job is deleted once
    // measured (the store holds no object afterwards); with --latency as well, a refusal.
    let local = dir.join("store");
    let mut on_disk = args[..10].to_vec();
    on_disk.extend(["--repeat", "2", "--workers", "1,2", "--store", local.to_str().unwrap()]);
    let o = vlf(&on_disk);
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        printed.contains(&format!("`{}` store", local.display()))
            && printed.contains("Every run gave the in-process bits"),
        "{printed}"
    );
    let files = |root: &Path| -> usize {
        let mut stack = vec![root.to_path_buf()];
        let mut count = 0;
        while let Some(d) = stack.pop() {
            for entry in std::fs::read_dir(&d).unwrap().flatten() {
                match entry.file_type().unwrap().is_dir() {
                    true => stack.push(entry.path()),
                    false => count += 1,
                }
            }
        }
        count
    };
    assert_eq!(files(&local), 0, "the bench left objects in {}", local.display());
    on_disk.extend(["--latency", "2"]);
    let o = vlf(&on_disk);
    assert!(
        !o.status.success() && stderr(&o).contains("--latency"),
        "{}",
        stderr(&o)
    );
    for bad in [
        ["--repeat", "0"],
        ["--workers", "0"],
        ["--threads", "0"],
        ["--latency", "20000"],
    ] {
        let mut a = args[..2].to_vec();
        a.extend(bad);
        let o = vlf(&a);
        assert!(
            !o.status.success() && stderr(&o).contains(bad[0]),
            "{bad:?}: {}",
            stderr(&o)
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--worker-processes`: the service's workers as `vlf worker` processes of their own, each
/// building the job's geometry from its stored survey and opening the store itself — the bits
/// of one process, on the Cornell box and on the mirror scene, in the bench and in its scaling
/// tables; their CPU is counted. Without a store they can open, a clear refusal.
#[test]
fn bench_runs_workers_as_processes_of_their_own() {
    let dir = temp("bench-processes");
    std::fs::create_dir_all(&dir).unwrap();
    let store = dir.join("store");
    let (cornell, mirrors) = (scene("cornell.obj"), scene("mirrors.obj"));
    // A small job, two worker processes, over a directory they open themselves.
    let bench = |scene: &str, rest: &[&str]| -> Output {
        let mut args = vec![
            "bench",
            scene,
            "--directions",
            "33",
            "--resolution",
            "16",
            "--tile",
            "4",
        ];
        args.extend([
            "--repeat",
            "1",
            "--worker-processes",
            "--store",
            store.to_str().unwrap(),
        ]);
        args.extend(rest);
        vlf(&args)
    };
    for scene in [&cornell, &mirrors] {
        let o = bench(scene, &["--iterations", "3", "--workers", "2"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let printed = String::from_utf8_lossy(&o.stdout).into_owned();
        assert!(
            printed.contains("Every run gave the in-process bits. The service's workers are processes of their own"),
            "{printed}"
        );
        let cpu = printed
            .split("CPU per run")
            .nth(1)
            .and_then(|rest| rest.split("\n\n").nth(1))
            .unwrap_or_else(|| panic!("no CPU table:\n{printed}"));
        let row = cpu
            .lines()
            .find(|l| l.starts_with("| service, 2 workers | "))
            .unwrap_or_else(|| panic!("{printed}"));
        let seconds: f64 = row.split('|').nth(2).and_then(|c| c.trim().parse().ok()).unwrap();
        assert!(seconds > 0.0, "{row}");
    }
    let scaling = [
        "--iterations",
        "2",
        "--scaling",
        "--scale-threads",
        "1",
        "--workers",
        "1,2",
    ];
    let o = bench(&cornell, &[&scaling[..], &["--worker-threads", "1"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        printed.contains("## Worker processes (`vlf worker`), 1 thread each"),
        "{printed}"
    );
    assert!(!printed.contains("embedded service"), "{printed}");
    let mut without_store = vec!["bench", cornell.as_str(), "--worker-processes"];
    without_store.extend(scaling);
    let o = vlf(&without_store);
    assert!(
        !o.status.success() && stderr(&o).contains("--worker-processes needs a --store"),
        "{}",
        stderr(&o)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A bench killed outright (SIGKILL: no handler, no `Drop`) leaves no worker process behind:
/// each dies with the thread that started it, rather than retrying to register forever.
#[test]
#[cfg(target_os = "linux")]
fn a_killed_bench_leaves_no_worker_process() {
    let dir = temp("bench-killed");
    std::fs::create_dir_all(&dir).unwrap();
    let store = dir.join("store");
    let store = store.to_str().unwrap();
    let cornell = scene("cornell.obj");
    let mut bench = Command::new(env!("CARGO_BIN_EXE_vlf"))
        .args(["bench", cornell.as_str(), "--directions", "2049", "--resolution", "64"])
        .args([
            "--repeat",
            "3",
            "--workers",
            "2",
            "--worker-processes",
            "--store",
            store,
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // The workers of this bench: `vlf worker` processes whose command line names its store.
    let workers = || -> Vec<u32> {
        std::fs::read_dir("/proc")
            .unwrap()
            .flatten()
            .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok())
            .filter(|pid| {
                let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
                let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
                let zombie = stat.rsplit(')').next().is_some_and(|s| s.trim_start().starts_with('Z'));
                let cmdline = String::from_utf8_lossy(&cmdline);
                let args: Vec<&str> = cmdline.split('\0').collect();
                !zombie && args.get(1) == Some(&"worker") && args.contains(&store)
            })
            .collect()
    };
    let wait_for = |what: &str, done: &dyn Fn() -> bool| {
        for _ in 0..1200 {
            if done() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        panic!("{what}");
    };
    wait_for("the bench started no worker process", &|| !workers().is_empty());
    bench.kill().unwrap();
    bench.wait().unwrap();
    wait_for("worker processes outlived the bench", &|| workers().is_empty());
}

/// The Mitsuba 3 reference of the bundled Cornell box at 64×48 (see `study/tests/tiny_study.rs`).
fn cornell_reference() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../study/tests/data/cornell-64x48.pfm")
}

#[test]
fn exact_direct_light_renders_closer_to_the_path_tracer() {
    use vlf_core::render::compare::{Pixels, compare};
    let out = temp("exact-direct");
    let o = propagate(&out, "2");
    assert!(o.status.success(), "{}", stderr(&o));
    let render = |direct: &str| {
        let image = out.join(format!("{direct}.pfm"));
        let o = vlf(&[
            "render",
            out.to_str().unwrap(),
            "--eye",
            "278,273,-800",
            "--target",
            "278,273,0",
            "--fovy",
            "39",
            "--size",
            "64x48",
            "--direct",
            direct,
            "--direct-samples",
            "32",
            "--out",
            image.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        vlf_core::render::Image::load_pfm(image).unwrap()
    };
    let reference = vlf_core::render::Image::load_pfm(cornell_reference()).unwrap();
    // Leave out the light's pixels (both draw it exactly; only coverage differs).
    let exclude: Vec<bool> = reference.pixels.iter().map(|p| p[0] > 2.0).collect();
    let pixels = Pixels {
        exclude: Some(&exclude),
        mask: None,
    };
    let field = compare(&render("field"), &reference, 8, pixels).unwrap();
    let exact_image = render("exact");
    let exact = compare(&exact_image, &reference, 8, pixels).unwrap();
    // The default, auto, is exact on the CPU where the job has snapshot 1.
    assert_eq!(
        render("auto").pixels,
        exact_image.pixels,
        "--direct auto is not exact here"
    );
    assert!(
        exact.relative_rmse < 0.6 * field.relative_rmse && exact.block_error < field.block_error,
        "exact {exact:?} field {field:?}"
    );
    let o = vlf(&[
        "render",
        out.to_str().unwrap(),
        "--eye",
        "278,273,-800",
        "--target",
        "278,273,0",
        "--direct",
        "exact",
        "--direct-samples",
        "0",
        "--out",
        out.join("x.png").to_str().unwrap(),
    ]);
    assert!(
        !o.status.success() && stderr(&o).contains("--direct-samples"),
        "{}",
        stderr(&o)
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn study_with_a_given_reference_writes_its_report() {
    let out = temp("study");
    let o = vlf(&[
        "study",
        &scene("cornell.obj"),
        "--out",
        out.to_str().unwrap(),
        "--reference",
        cornell_reference().to_str().unwrap(),
        "--eye",
        "278,273,-800",
        "--target",
        "278,273,0",
        "--fovy",
        "39",
        "--size",
        "64x48",
        "--directions",
        "33",
        "--resolution",
        "16",
        "--sweep-joint",
        "",
        "--sweep-directions",
        "9",
        "--sweep-resolution",
        "",
        "--sweep-tile",
        "",
        "--sweep-texel",
        "",
        "--no-toggles",
        "--direct-samples",
        "8",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("base l=33 N=16 m=8"), "{stdout}");
    let csv = std::fs::read_to_string(out.join("study.csv")).unwrap();
    // Base and l = 9, two render modes each, plus the base's iterations but the last.
    assert!(csv.lines().filter(|l| l.starts_with("base,")).count() == 2, "{csv}");
    assert!(
        csv.lines().filter(|l| l.starts_with("directions,")).count() == 2,
        "{csv}"
    );
    for f in [
        "study.md",
        "error-vs-time.png",
        "block-error-vs-time.png",
        "reference.png",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
    // A reference of another size is refused with both sizes named.
    let o = vlf(&[
        "study",
        &scene("cornell.obj"),
        "--out",
        out.to_str().unwrap(),
        "--reference",
        cornell_reference().to_str().unwrap(),
        "--eye",
        "278,273,-800",
        "--target",
        "278,273,0",
        "--size",
        "32x24",
    ]);
    assert!(!o.status.success() && stderr(&o).contains("64x48"), "{}", stderr(&o));
    // The base alone makes no curve: its tables are the report, and the study succeeds (it used
    // to fail with "nothing to plot" once everything was measured).
    let alone = out.join("alone");
    let reference = cornell_reference();
    let mut args = vec![
        "study",
        "--out",
        alone.to_str().unwrap(),
        "--reference",
        reference.to_str().unwrap(),
        "--eye",
        "278,273,-800",
        "--target",
        "278,273,0",
        "--fovy",
        "39",
        "--size",
        "64x48",
        "--directions",
        "9",
        "--resolution",
        "16",
        "--iterations",
        "1",
        "--no-toggles",
        "--no-iterations",
        "--direct-samples",
        "8",
    ];
    let cornell = scene("cornell.obj");
    args.insert(1, &cornell);
    for sweep in [
        "--sweep-joint",
        "--sweep-directions",
        "--sweep-resolution",
        "--sweep-tile",
        "--sweep-texel",
    ] {
        args.extend([sweep, ""]);
    }
    let o = vlf(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(alone.join("study.md").exists() && alone.join("reference.png").exists());
    assert!(!alone.join("error-vs-time.png").exists());
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn view_draws_in_a_window_what_render_draws() {
    let out = temp("view");
    let o = propagate(&out, "2");
    assert!(o.status.success(), "{}", stderr(&o));
    let camera = [&CORNELL_VIEW[..], &["--size", "96x72"][..]].concat();
    // Without any display: a clear error, not a panic.
    let o = Command::new(env!("CARGO_BIN_EXE_vlf"))
        .args([&["view", out.to_str().unwrap()][..], &camera[..], &["--frames", "1"]].concat())
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    assert!(
        !o.status.success() && stderr(&o).contains("cannot open a window"),
        "{}",
        stderr(&o)
    );
    let Some(display) = x_display() else { return };
    let shot = out.join("shot.pfm");
    let o = Command::new(env!("CARGO_BIN_EXE_vlf"))
        .args(
            [
                &["view", out.to_str().unwrap()][..],
                &camera[..],
                // Exact direct light, streamed from snapshot 1 (auto would leave it to a real GPU).
                &["--frames", "3", "--no-vsync", "--direct", "exact"][..],
                &["--screenshot", shot.to_str().unwrap()],
            ]
            .concat(),
        )
        .env("DISPLAY", &display.name)
        .output()
        .unwrap();
    if !gpu_available(&o) {
        return;
    }
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("3 frames") && stdout.contains("direct light exact"),
        "{stdout}"
    );
    // It streamed the parts the view needs, no more than the field has.
    let number_after = |prefix: &str, word: &str| -> Option<usize> {
        let line = stdout.lines().find(|l| l.starts_with(prefix))?;
        let words: Vec<&str> = line.split_whitespace().collect();
        let at = words.iter().position(|w| w.trim_end_matches(',') == word)?;
        words.get(at.checked_sub(1)?)?.parse().ok()
    };
    let parts = number_after("streaming ", "parts");
    let fetched = number_after("streamed ", "parts");
    assert!(
        matches!((parts, fetched), (Some(p), Some(f)) if f > 0 && f <= p),
        "{stdout}"
    );
    // The window's frame is the headless GPU render's with one sample, bit for bit (with the
    // walkthrough's quadrature points: fewer than render's by default).
    let rendered = out.join("render.pfm");
    let walk_samples = vlf_core::direct::WALK_SAMPLES.to_string();
    let o = vlf(&[
        &["render", out.to_str().unwrap()][..],
        &camera[..],
        &[
            "--gpu",
            "--samples",
            "1",
            "--direct",
            "exact",
            "--direct-samples",
            &walk_samples,
            "--out",
            rendered.to_str().unwrap(),
        ],
    ]
    .concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let a = vlf_core::render::Image::load_pfm(&shot).unwrap();
    let b = vlf_core::render::Image::load_pfm(&rendered).unwrap();
    assert_eq!((a.width, a.height), (96, 72));
    assert!(a.pixels == b.pixels, "the window's frame differs from vlf render --gpu");
    assert!(a.mean()[0] > 0.01, "{:?}", a.mean());
    // By default a software adapter draws the field's direct light, a real GPU the exact one.
    let o = Command::new(env!("CARGO_BIN_EXE_vlf"))
        .args(
            [
                &["view", out.to_str().unwrap()][..],
                &camera[..],
                &["--frames", "1", "--no-vsync"],
            ]
            .concat(),
        )
        .env("DISPLAY", &display.name)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    let software = stdout.contains(", Cpu)");
    let want = if software {
        "direct light from the field"
    } else {
        "direct light exact"
    };
    assert!(o.status.success() && stdout.contains(want), "{stdout}{}", stderr(&o));
    let _ = std::fs::remove_dir_all(&out);
}

/// A cube of side 100 around the origin of its own coordinates, no emitter: `DIR/cube.obj`.
fn write_cube(out: &Path) {
    let h = 50.0;
    let corners: Vec<[f64; 3]> = (0..8)
        .map(|i| {
            [
                if i & 1 == 0 { -h } else { h },
                if i & 2 == 0 { -h } else { h },
                if i & 4 == 0 { -h } else { h },
            ]
        })
        .collect();
    let faces = ["1 5 7 3", "2 4 8 6", "1 2 6 5", "3 7 8 4", "1 3 4 2", "5 6 8 7"];
    let mut obj = String::from("mtllib cube.mtl\nusemtl white\n");
    for c in &corners {
        obj += &format!("v {} {} {}\n", c[0], c[1], c[2]);
    }
    for f in faces {
        obj += &format!("f {f}\n");
    }
    std::fs::write(out.join("cube.obj"), obj).unwrap();
    std::fs::write(out.join("cube.mtl"), "newmtl white\nKd 0.75 0.75 0.75\n").unwrap();
}

/// `vlf render --object`: a cube placed in the Cornell box is drawn lit by the field (not
/// black) and hides what is behind it; without shadows the pixels it does not cover are the
/// static view's, bit for bit; with them, the room and the cube darken on the whole; a second object
/// adds its own pixels; `--gpu` draws the same. Bad object input is refused clearly: an
/// emitter, a missing file, a cube through the floor, one outside the box.
#[test]
fn render_draws_a_dynamic_object_lit_by_the_field() {
    let out = temp("cornell");
    let o = propagate(&out, "2");
    assert!(o.status.success(), "{}", stderr(&o));
    write_cube(&out);
    let render = |extra: &[&str], image: &str| {
        let path = out.join(image);
        let mut args = [&["render", out.to_str().unwrap()][..], &CORNELL_VIEW[..]].concat();
        // The field's direct light: with exact direct light, shadow rays would see the cube
        // even without its soft shadows.
        args.extend(["--size", "48x48", "--samples", "1", "--direct", "field"]);
        args.extend(["--out", path.to_str().unwrap()]);
        args.extend(extra);
        let o = vlf(&args);
        (o, path)
    };
    let (o, plain) = render(&[], "plain.pfm");
    assert!(o.status.success(), "{}", stderr(&o));
    let cube = out.join("cube.obj");
    let object = [
        "--object",
        cube.to_str().unwrap(),
        "--object-at",
        "278,260,200",
        "--object-turn",
        "20",
    ];
    let (o, with) = render(&[&object[..], &["--object-shadow-samples", "0"]].concat(), "with.pfm");
    assert!(o.status.success(), "{}", stderr(&o));
    let (o, shadowed) = render(&object, "shadowed.pfm");
    assert!(o.status.success(), "{}", stderr(&o));
    let (o, two) = render(
        &[
            &object[..],
            &["--object", cube.to_str().unwrap(), "--object-at", "400,50,100"],
        ]
        .concat(),
        "two.pfm",
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let load = |p: &std::path::Path| vlf_core::render::Image::load_pfm(p).unwrap();
    let (plain, with, shadowed, two) = (load(&plain), load(&with), load(&shadowed), load(&two));
    let changed: Vec<usize> = (0..plain.pixels.len())
        .filter(|&i| plain.pixels[i] != with.pixels[i])
        .collect();
    // The cube (about 100 units at ~1000 from the camera, 39° field) covers a patch of pixels
    // around the image's centre, and nothing else changes.
    assert!(
        changed.len() > 20 && changed.len() < 48 * 48 / 4,
        "{} pixels changed",
        changed.len()
    );
    for &i in &changed {
        let (x, y) = (i % 48, i / 48);
        assert!(
            (10..38).contains(&x) && (5..40).contains(&y),
            "pixel ({x}, {y}) changed"
        );
        assert!(with.pixels[i].iter().all(|c| c.is_finite() && *c >= 0.0));
    }
    let lit = changed
        .iter()
        .filter(|&&i| with.pixels[i].iter().sum::<f32>() > 0.0)
        .count();
    assert!(
        lit * 2 > changed.len(),
        "the cube is mostly black: {lit} of {} lit",
        changed.len()
    );
    let sum = |image: &vlf_core::render::Image, pixels: &[usize]| -> f64 {
        pixels
            .iter()
            .map(|&i| image.pixels[i].iter().map(|&c| c as f64).sum::<f64>())
            .sum()
    };
    // With shadows, the room around the cube loses light on the whole: it hides more than
    // it gives back (the light it reflects onto the room, `with_bounce_light`).
    let darker: Vec<usize> = (0..plain.pixels.len())
        .filter(|&i| !changed.contains(&i) && shadowed.pixels[i] != plain.pixels[i])
        .collect();
    assert!(darker.len() > 20, "{} pixels in shadow", darker.len());
    assert!(
        sum(&shadowed, &darker) < sum(&plain, &darker),
        "the shadow region brightened"
    );
    // The cube's own pixels: its gather now sees its shadow on the floor, so they darken.
    assert!(sum(&shadowed, &changed) < sum(&with, &changed), "the cube brightened");
    // The second cube (on the floor, to the right) covers pixels the first does not.
    let second = (0..plain.pixels.len())
        .filter(|&i| !changed.contains(&i) && !darker.contains(&i) && two.pixels[i] != plain.pixels[i])
        .count();
    assert!(second > 10, "{second} pixels of the second cube");
    let (o, _) = render(
        &[&object[..], &["--object-shadow-samples", "4000000000"]].concat(),
        "x.pfm",
    );
    assert!(
        !o.status.success() && stderr(&o).contains("--object-shadow-samples"),
        "{}",
        stderr(&o)
    );
    // Bad placements: through the floor (y = 0), far outside the box.
    for (at, says) in [
        ("278,20,200", "crosses a surface"),
        ("278,200,-5000", "outside the scene"),
    ] {
        let (o, _) = render(&["--object", cube.to_str().unwrap(), "--object-at", at], "x.pfm");
        assert!(!o.status.success() && stderr(&o).contains(says), "{at}: {}", stderr(&o));
    }
    // Bad input: a file with an emitter, a missing file.
    std::fs::write(out.join("lamp.mtl"), "newmtl lamp\nKd 0.5 0.5 0.5\nKe 1 1 1\n").unwrap();
    std::fs::write(
        out.join("lamp.obj"),
        "mtllib lamp.mtl\nusemtl lamp\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let lamp = out.join("lamp.obj");
    let (o, _) = render(&["--object", lamp.to_str().unwrap()], "x.pfm");
    assert!(!o.status.success() && stderr(&o).contains("emits"), "{}", stderr(&o));
    let missing = out.join("missing.obj");
    let (o, _) = render(&["--object", missing.to_str().unwrap()], "x.pfm");
    assert!(
        !o.status.success() && stderr(&o).contains("missing.obj"),
        "{}",
        stderr(&o)
    );
    // On the GPU: the same picture, but for a few pixels at polygon edges.
    let (o, gpu_path) = render(&[&object[..], &["--gpu"]].concat(), "gpu.pfm");
    if gpu_available(&o) {
        let gpu = load(&gpu_path);
        let off = (0..shadowed.pixels.len())
            .filter(|&i| {
                (0..3).any(|c| {
                    (gpu.pixels[i][c] - shadowed.pixels[i][c]).abs() > 1e-2 * shadowed.pixels[i][c].abs() + 1e-6
                })
            })
            .count();
        assert!(
            off * 20 <= shadowed.pixels.len(),
            "{off} pixels differ between the GPU and the CPU"
        );
    }
    // Exact direct light among the objects (shadow rays that see the cube): the GPU's is the
    // CPU's too, and not the field's.
    let exact = |gpu: &[&str], image: &str| {
        let path = out.join(image);
        let mut args = [
            &["render", out.to_str().unwrap()][..],
            &CORNELL_VIEW[..],
            &object[..],
            gpu,
        ]
        .concat();
        args.extend(["--size", "48x48", "--samples", "1", "--direct", "exact"]);
        args.extend(["--out", path.to_str().unwrap()]);
        (vlf(&args), path)
    };
    let (o, cpu_path) = exact(&[], "exact.pfm");
    assert!(o.status.success(), "{}", stderr(&o));
    let cpu = load(&cpu_path);
    assert!((cpu.mean()[0] - shadowed.mean()[0]).abs() > 1e-3 * shadowed.mean()[0]);
    let (o, gpu_path) = exact(&["--gpu"], "exact-gpu.pfm");
    if gpu_available(&o) {
        let gpu = load(&gpu_path);
        let off = (0..cpu.pixels.len())
            .filter(|&i| {
                (0..3).any(|c| (gpu.pixels[i][c] - cpu.pixels[i][c]).abs() > 1e-2 * cpu.pixels[i][c].abs() + 1e-6)
            })
            .count();
        assert!(
            off * 20 <= cpu.pixels.len(),
            "{off} pixels differ between the GPU and the CPU"
        );
    }
    // Shadows per texel (the camera's, without the direct part): as sharp as the texels, the
    // same picture on the whole.
    let (o, texel_path) = exact(&["--gpu", "--object-shadows-per-texel"], "texels.pfm");
    if gpu_available(&o) {
        let (a, b) = (load(&texel_path).mean(), cpu.mean());
        assert!((0..3).all(|c| (a[c] - b[c]).abs() < 0.03 * b[c]), "{a:?} vs {b:?}");
    }
}

/// `vlf view --object`: a cube moved by a script (`--object-to`) over the frames is drawn at
/// its end in the last frame exactly as `vlf render --gpu --object-shadows-per-texel` draws it
/// placed there (the view's shadows are per texel): the object's
/// buffers follow its moves, and the streamer fetched what its gather and shadow read. A
/// script into the floor stops the cube at it (moves refused, said so), and a script without
/// --frames is refused.
#[test]
fn view_moves_objects_as_render_places_them() {
    let out = temp("view-objects");
    let o = propagate(&out, "2");
    assert!(o.status.success(), "{}", stderr(&o));
    write_cube(&out);
    let cube = out.join("cube.obj");
    // Exact direct light, which a software adapter's view draws only when asked for, with the
    // same quadrature points in the view and the render (their defaults differ).
    let samples = vlf_core::direct::WALK_SAMPLES.to_string();
    let camera = [
        &CORNELL_VIEW[..],
        &["--size", "64x48", "--direct", "exact", "--direct-samples", &samples][..],
    ]
    .concat();
    let object = ["--object", cube.to_str().unwrap(), "--object-at", "278,260,200"];
    let o = vlf(&[
        &["view", out.to_str().unwrap()][..],
        &camera,
        &object,
        &["--object-to", "150,350,200"],
    ]
    .concat());
    assert!(
        !o.status.success() && stderr(&o).contains("--object-to") && stderr(&o).contains("--frames"),
        "{}",
        stderr(&o)
    );
    let Some(display) = x_display() else { return };
    let view = |extra: &[&str], shot: &Path| {
        Command::new(env!("CARGO_BIN_EXE_vlf"))
            .args(
                [
                    &["view", out.to_str().unwrap()][..],
                    &camera,
                    &object,
                    &["--frames", "4", "--no-vsync", "--screenshot", shot.to_str().unwrap()],
                    extra,
                ]
                .concat(),
            )
            .env("DISPLAY", &display.name)
            .output()
            .unwrap()
    };
    let shot = out.join("moved.pfm");
    let o = view(&["--object-to", "150,350,200"], &shot);
    if !gpu_available(&o) {
        return;
    }
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("4 frames") && !stdout.contains("refused"), "{stdout}");
    let rendered = out.join("placed.pfm");
    let o = vlf(&[
        &["render", out.to_str().unwrap()][..],
        &camera[..],
        &["--object", cube.to_str().unwrap(), "--object-at", "150,350,200"],
        &[
            "--gpu",
            "--object-shadows-per-texel",
            "--samples",
            "1",
            "--out",
            rendered.to_str().unwrap(),
        ],
    ]
    .concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let a = vlf_core::render::Image::load_pfm(&shot).unwrap();
    let b = vlf_core::render::Image::load_pfm(&rendered).unwrap();
    let differ = a.pixels.iter().zip(&b.pixels).filter(|(p, q)| p != q).count();
    assert_eq!(
        differ, 0,
        "{differ} pixels of the view's last frame differ from render --gpu"
    );
    // Where the cube started the view shows something else: it did move.
    let o = vlf(&[
        &["render", out.to_str().unwrap()][..],
        &camera[..],
        &object[..],
        &["--gpu", "--samples", "1", "--out", rendered.to_str().unwrap()],
    ]
    .concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let c = vlf_core::render::Image::load_pfm(&rendered).unwrap();
    assert!(a.pixels != c.pixels);
    // Into the floor: the cube stops where it touches it.
    let o = view(&["--object-to", "278,-200,200"], &shot);
    assert!(o.status.success(), "{}", stderr(&o));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("object moves refused"), "{stdout}");
    let _ = std::fs::remove_dir_all(&out);
}
