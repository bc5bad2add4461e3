//! The deployment files of `deploy/` run the way a container runtime would run them, without
//! Docker or Kubernetes (neither runs on CI's machines): each `vlf` command line of the compose
//! file and of the Kubernetes manifests is started as a process on loopback, with the
//! environment the file gives it, and the service they make must take a job to the end. Only
//! what the runtime provides is replaced: host names by 127.0.0.1, the published port by a free
//! one, and the files' own object store (MinIO, whose image does not run here) by `.ci/run`'s
//! S3 server when there is one, else by a scratch directory.
//!
//! The files are also checked for agreeing with themselves: the port the coordinator listens
//! on is the one it is published, probed and reached on; the workers reach it by its service's
//! name; every key the environment comes from exists; the object store is reached by its
//! service's name and port, with the keys it was given, and its bucket is made before the
//! coordinator needs it.

#[path = "support/process.rs"]
mod process;

use process::{PARAMS, Proc, describe, free_port, vlf_command};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};
use yaml_rust2::{Yaml, YamlLoader};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The YAML documents of `deploy/<path>`.
fn load(path: &str) -> Vec<Yaml> {
    let file = repo().join("deploy").join(path);
    let text = std::fs::read_to_string(&file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    YamlLoader::load_from_str(&text).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// A scalar as the text a container would get (YAML numbers and booleans included).
fn scalar(y: &Yaml) -> Option<String> {
    match y {
        Yaml::String(s) | Yaml::Real(s) => Some(s.clone()),
        Yaml::Integer(i) => Some(i.to_string()),
        Yaml::Boolean(b) => Some(b.to_string()),
        _ => None,
    }
}

fn text(y: &Yaml, what: &str) -> String {
    scalar(y).unwrap_or_else(|| panic!("{what}: expected a scalar, found {y:?}"))
}

fn strings(y: &Yaml, what: &str) -> Vec<String> {
    let items = y
        .as_vec()
        .unwrap_or_else(|| panic!("{what}: expected a list, found {y:?}"));
    items.iter().map(|v| text(v, what)).collect()
}

/// The value that follows `name` in `args`.
fn flag<'a>(args: &'a [String], name: &str) -> &'a str {
    let at = args.iter().position(|a| a == name);
    match at.and_then(|i| args.get(i + 1)) {
        Some(v) => v,
        None => panic!("no {name} in {args:?}"),
    }
}

/// `args` with every occurrence of `from` within an argument replaced by `to`.
fn replaced(args: &[String], from: &str, to: &str) -> Vec<String> {
    args.iter().map(|a| a.replace(from, to)).collect()
}

/// The port of `HOST:PORT` or `SCHEME://HOST:PORT`, with the host.
fn host_port(address: &str) -> (String, u16) {
    let address = address.split("://").last().unwrap_or(address);
    let (host, port) = address
        .rsplit_once(':')
        .unwrap_or_else(|| panic!("no port in {address}"));
    (
        host.to_string(),
        port.parse().unwrap_or_else(|e| panic!("{address}: {e}")),
    )
}

/// A `vlf` process as a deployment file describes it.
#[derive(Clone, Debug)]
struct Role {
    args: Vec<String>,
    env: BTreeMap<String, String>,
}

/// Starts `role` as process `name`, with the environment the file gives it and none of the
/// test's own `VLF_*`, `AWS_*` or `RUST_LOG`.
fn start(dir: &Path, name: &str, role: &Role) -> Proc {
    let mut command = vlf_command();
    for (key, _) in std::env::vars() {
        if key.starts_with("VLF_") || key.starts_with("AWS_") || key == "RUST_LOG" {
            command.env_remove(key);
        }
    }
    command.args(&role.args).envs(&role.env);
    Proc::spawn(command, dir, name)
}

fn vlf(args: &[String], env: &BTreeMap<String, String>) -> Output {
    vlf_command().args(args).envs(env).output().expect("run vlf")
}

/// [`vlf`] for at most `limit` (a job whose workers cannot reach the coordinator would be
/// watched forever): killed then, with what it printed so far.
fn vlf_within(args: &[String], env: &BTreeMap<String, String>, limit: Duration) -> Output {
    let mut child = vlf_command()
        .args(args)
        .envs(env)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run vlf");
    let started = Instant::now();
    while child.try_wait().expect("wait for vlf").is_none() && started.elapsed() < limit {
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = child.kill();
    child.wait_with_output().expect("vlf's output")
}

/// Runs a coordinator, checks that `health` (the probe's `vlf` arguments) passes once it
/// listens, starts `workers`, then submits the mirror scene, small, with `token` and follows it
/// to its end.
fn serve_a_job(dir: &Path, coordinator: &Role, workers: &[Role], health: &[String], url: &str, token: &str) {
    let mut server = start(dir, "coordinator", coordinator);
    let listening = server.wait_for_line("listening on ");
    assert_eq!(listening.trim_start_matches("listening on ").trim(), url);
    // What the runtime's probe asks passes as soon as the coordinator listens: its jobs are
    // taken up from the store before.
    let o = vlf(health, &BTreeMap::new());
    assert!(o.status.success(), "{}\nits log:\n{}", describe(&o), server.log());
    let running: Vec<Proc> = (workers.iter().enumerate())
        .map(|(i, w)| start(dir, &format!("worker-{i}"), w))
        .collect();
    let scene = repo().join("scenes/mirrors.obj");
    let mut submit: Vec<String> = vec!["submit".into(), scene.to_string_lossy().into_owned()];
    submit.extend(["--server", url, "--watch"].map(String::from));
    submit.extend(PARAMS.map(String::from));
    let env = BTreeMap::from([("VLF_TOKEN".to_string(), token.to_string())]);
    let o = vlf_within(&submit, &env, Duration::from_secs(180));
    let logs = || {
        let mut all = format!("coordinator:\n{}", server.log());
        for (i, w) in running.iter().enumerate() {
            all += &format!("\nworker {i}:\n{}", w.log());
        }
        all
    };
    assert!(o.status.success(), "{}\n{}", describe(&o), logs());
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("finished"), "{}\n{}", describe(&o), logs());
    // Every worker registered with the coordinator (and so reached it by the given name).
    let registered = server.log().matches("worker registered").count();
    assert_eq!(registered, workers.len(), "{}", logs());
}

/// Compose's `${NAME}`, `${NAME:-default}` and `${NAME:?error}` in `s`, from `vars`.
fn interpolate(s: &str, vars: &BTreeMap<&str, &str>) -> String {
    let mut out = String::new();
    let mut rest = s;
    while let Some(start) = rest.find("${") {
        out += &rest[..start];
        let end = rest[start..].find('}').map(|e| start + e).expect("closing brace");
        let inner = &rest[start + 2..end];
        let (name, value) = if let Some((name, default)) = inner.split_once(":-") {
            (name, vars.get(name).copied().unwrap_or(default).to_string())
        } else if let Some((name, error)) = inner.split_once(":?") {
            let value = vars.get(name).unwrap_or_else(|| panic!("compose would stop: {error}"));
            (name, value.to_string())
        } else {
            (inner, vars.get(inner).copied().unwrap_or_default().to_string())
        };
        assert!(!name.is_empty(), "empty variable in {s}");
        out += &value;
        rest = &rest[end + 1..];
    }
    out + rest
}

/// A compose service's command and environment (variables unset in the shell are left out, as
/// compose leaves them).
fn compose_role(service: &Yaml, vars: &BTreeMap<&str, &str>, what: &str) -> Role {
    let args = strings(&service["command"], what)
        .iter()
        .map(|a| interpolate(a, vars))
        .collect();
    let mut env = BTreeMap::new();
    let environment = service["environment"].as_hash().expect("environment map");
    for (key, value) in environment {
        let key = text(key, what);
        match value {
            Yaml::Null => {
                if let Some(v) = vars.get(key.as_str()) {
                    env.insert(key, v.to_string());
                }
            }
            v => {
                env.insert(key, interpolate(&text(v, what), vars));
            }
        }
    }
    Role { args, env }
}

/// The store the deployments' services are run against here: `.ci/run`'s S3 server when there
/// is one (a fresh prefix of its bucket, with its endpoint and keys), else a scratch directory.
/// Returned as the environment a user would export to point a deployment at a store.
fn test_store(dir: &Path) -> BTreeMap<String, String> {
    match std::env::var("VLF_TEST_S3_URL") {
        Ok(base) => {
            let unique = format!("deploy-{}-{}", std::process::id(), free_port());
            let mut vars = BTreeMap::from([(
                "VLF_STORE".to_string(),
                format!("{}/{unique}", base.trim_end_matches('/')),
            )]);
            for key in [
                "AWS_ENDPOINT_URL",
                "AWS_ALLOW_HTTP",
                "AWS_REGION",
                "AWS_ACCESS_KEY_ID",
                "AWS_SECRET_ACCESS_KEY",
            ] {
                vars.insert(key.to_string(), std::env::var(key).unwrap_or_default());
            }
            vars
        }
        Err(_) => {
            assert!(
                std::env::var("VLF_REQUIRE_S3").is_err(),
                "VLF_REQUIRE_S3 is set but VLF_TEST_S3_URL is not"
            );
            BTreeMap::from([(
                "VLF_STORE".to_string(),
                dir.join("store").to_string_lossy().into_owned(),
            )])
        }
    }
}

/// The jobs in the store at `url` (an S3 store is opened with the test's `AWS_*`).
fn jobs_in(url: &str) -> usize {
    let store = vlf_store::Store::open_existing(url).unwrap_or_else(|e| panic!("{url}: {e}"));
    vlf_store::Job::list(&store).unwrap().len()
}

#[test]
fn the_compose_files_service_takes_a_job_to_its_end() {
    let docs = load("compose.yaml");
    let services = &docs[0]["services"];
    let (coordinator, worker) = (&services["coordinator"], &services["worker"]);
    let (store, bucket) = (&services["store"], &services["store-bucket"]);

    // One image, built by a Dockerfile that exists, from the repository's root.
    assert_eq!(coordinator["image"], worker["image"]);
    let context = repo()
        .join("deploy")
        .join(text(&coordinator["build"]["context"], "build context"));
    let dockerfile = context.join(text(&coordinator["build"]["dockerfile"], "dockerfile"));
    assert!(dockerfile.is_file(), "{}", dockerfile.display());
    assert!(
        context.join("Cargo.toml").is_file(),
        "the build context is the workspace"
    );

    // What compose is given: the token and the store's keys, nothing else.
    let token = "compose-token";
    let (key, secret) = ("compose-key", "compose-secret");
    let given = BTreeMap::from([
        ("VLF_TOKEN", token),
        ("AWS_ACCESS_KEY_ID", key),
        ("AWS_SECRET_ACCESS_KEY", secret),
    ]);
    let c = compose_role(coordinator, &given, "coordinator");
    let w = compose_role(worker, &given, "worker");
    assert_eq!(c.env.get("VLF_TOKEN").map(String::as_str), Some(token));
    assert_eq!(w.env.get("VLF_TOKEN").map(String::as_str), Some(token));

    // The object store: the coordinator's default store is a bucket of the compose file's own
    // S3 server, which the workers reach the same way, with the keys the server was given.
    let url = flag(&c.args, "--store").to_string();
    let bucket_name = url
        .strip_prefix("s3://")
        .and_then(|rest| rest.split('/').next())
        .unwrap_or_else(|| panic!("the default store is an s3:// URL: {url}"));
    let endpoint = c.env.get("AWS_ENDPOINT_URL").expect("the store's endpoint").clone();
    let (store_host, store_port) = host_port(&endpoint);
    assert!(
        !services[store_host.as_str()].is_badvalue(),
        "{store_host} is a service"
    );
    assert_eq!(
        services[store_host.as_str()],
        *store,
        "the endpoint is the store service"
    );
    let store_args = strings(&store["command"], "store command");
    assert_eq!(
        host_port(flag(&store_args, "--address")).1,
        store_port,
        "the store listens where it is reached"
    );
    let store_env = compose_role(store, &given, "store").env;
    assert_eq!(store_env.get("MINIO_ROOT_USER").map(String::as_str), Some(key));
    assert_eq!(store_env.get("MINIO_ROOT_PASSWORD").map(String::as_str), Some(secret));
    for role in [&c, &w] {
        for var in ["AWS_ENDPOINT_URL", "AWS_ALLOW_HTTP", "AWS_REGION"] {
            assert_eq!(role.env.get(var), c.env.get(var), "{var}: one store for all");
        }
        assert_eq!(role.env.get("AWS_ACCESS_KEY_ID").map(String::as_str), Some(key));
        assert_eq!(role.env.get("AWS_SECRET_ACCESS_KEY").map(String::as_str), Some(secret));
    }
    assert_eq!(
        c.env.get("AWS_ALLOW_HTTP").map(String::as_str),
        Some("true"),
        "{endpoint} is http"
    );
    // The bucket is made, on that server, before the coordinator starts.
    let made = strings(&bucket["command"], "store-bucket command").join(" ");
    assert!(made.contains(&format!("mc alias set store {endpoint} ")), "{made}");
    assert!(
        made.contains(&format!("mc mb --ignore-existing store/{bucket_name}")),
        "{made}"
    );
    assert_eq!(
        bucket["depends_on"]["store"]["condition"].as_str(),
        Some("service_healthy")
    );
    assert_eq!(
        coordinator["depends_on"]["store-bucket"]["condition"].as_str(),
        Some("service_completed_successfully")
    );
    assert!(
        !docs[0]["volumes"]["objects"].is_badvalue(),
        "the store's volume is declared"
    );

    // The port: listened on, published, probed, and what the workers reach by the service's name.
    let listen = flag(&c.args, "--listen").to_string();
    let (host, port) = host_port(&listen);
    assert_eq!(host, "0.0.0.0", "reachable from the other containers");
    assert!(
        strings(&coordinator["ports"], "ports").contains(&format!("{port}:{port}")),
        "published on {port}"
    );
    let probe = strings(&coordinator["healthcheck"]["test"], "healthcheck");
    assert_eq!(probe[..3], ["CMD", "vlf", "health"]);
    let probe_url = flag(&probe, "--server").to_string();
    assert_eq!(host_port(&probe_url), ("127.0.0.1".to_string(), port));
    let server_url = flag(&w.args, "--server").to_string();
    let (server_host, server_port) = host_port(&server_url);
    assert!(
        !services[server_host.as_str()].is_badvalue(),
        "{server_host} is a service"
    );
    assert_eq!(server_port, port);
    let replicas = worker["deploy"]["replicas"].as_i64().expect("replicas") as usize;
    assert!(replicas >= 1);

    // Run it against this machine's store, pointed at the way a user points the file at another
    // store (VLF_STORE and the AWS_* variables); the published port is a free one.
    let scratch = tempfile::tempdir().unwrap();
    let dir = scratch.path();
    let store_vars = test_store(dir);
    let mut vars = given.clone();
    vars.extend(store_vars.iter().map(|(k, v)| (k.as_str(), v.as_str())));
    let c = compose_role(coordinator, &vars, "coordinator");
    let w = compose_role(worker, &vars, "worker");
    let job_store = store_vars["VLF_STORE"].clone();
    assert_eq!(flag(&c.args, "--store"), job_store, "VLF_STORE names the store");
    let free = free_port();
    let url = format!("http://127.0.0.1:{free}");
    let local = |role: &Role| Role {
        args: replaced(
            &replaced(&role.args, &listen, &format!("127.0.0.1:{free}")),
            &server_url,
            &url,
        ),
        env: role.env.clone(),
    };
    let workers = vec![local(&w); replicas];
    let health = replaced(&probe[2..], &probe_url, &url);
    serve_a_job(dir, &local(&c), &workers, &health, &url, token);
    assert_eq!(jobs_in(&job_store), 1, "the job is in the store");
}

/// The Kubernetes objects of the manifests that `kustomization.yaml` lists, by kind and name.
fn k8s_objects() -> BTreeMap<(String, String), Yaml> {
    let kustomization = &load("k8s/kustomization.yaml")[0];
    let resources = strings(&kustomization["resources"], "resources");
    // Every manifest beside it is applied.
    let mut present: Vec<String> = std::fs::read_dir(repo().join("deploy/k8s"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".yaml") && n != "kustomization.yaml")
        .collect();
    present.sort();
    let mut listed = resources.clone();
    listed.sort();
    assert_eq!(listed, present, "kustomization.yaml lists every manifest");
    let mut objects = BTreeMap::new();
    for file in &resources {
        for doc in load(&format!("k8s/{file}")) {
            let key = (text(&doc["kind"], "kind"), text(&doc["metadata"]["name"], "name"));
            assert!(objects.insert(key.clone(), doc).is_none(), "{key:?} twice");
        }
    }
    objects
}

fn object<'a>(objects: &'a BTreeMap<(String, String), Yaml>, kind: &str, name: &str) -> &'a Yaml {
    objects
        .get(&(kind.to_string(), name.to_string()))
        .unwrap_or_else(|| panic!("no {kind} {name}"))
}

/// A container's arguments and environment, its `valueFrom`s looked up in the manifests' config
/// maps and secrets and its `$(VAR)`s expanded, as the kubelet does; `overrides` replace values
/// (the test's store for the placeholders).
fn k8s_role(
    objects: &BTreeMap<(String, String), Yaml>,
    container: &Yaml,
    overrides: &BTreeMap<String, String>,
) -> Role {
    let mut env = BTreeMap::new();
    for var in container["env"].as_vec().expect("env list") {
        let name = text(&var["name"], "env name");
        let from = &var["valueFrom"];
        let value = if !var["value"].is_badvalue() {
            Some(text(&var["value"], "env value"))
        } else {
            let (kind, key_ref, field) = if !from["configMapKeyRef"].is_badvalue() {
                ("ConfigMap", &from["configMapKeyRef"], "data")
            } else {
                ("Secret", &from["secretKeyRef"], "stringData")
            };
            let source = object(objects, kind, &text(&key_ref["name"], "ref name"));
            let value = scalar(&source[field][key_ref["key"].as_str().expect("ref key")]);
            let optional = key_ref["optional"].as_bool().unwrap_or(false);
            assert!(
                value.is_some() || optional,
                "{name}: no key {:?} in its {kind}",
                key_ref["key"]
            );
            value
        };
        if let Some(value) = overrides.get(&name).cloned().or(value) {
            env.insert(name, value);
        }
    }
    let args = strings(&container["args"], "args")
        .iter()
        .map(|a| {
            let mut a = a.clone();
            for (name, value) in &env {
                a = a.replace(&format!("$({name})"), value);
            }
            assert!(!a.contains("$("), "{a}: an unknown variable");
            a
        })
        .collect();
    Role { args, env }
}

fn only_container(deployment: &Yaml) -> &Yaml {
    let containers = deployment["spec"]["template"]["spec"]["containers"]
        .as_vec()
        .expect("containers");
    assert_eq!(containers.len(), 1);
    &containers[0]
}

#[test]
fn the_kubernetes_manifests_service_takes_a_job_to_its_end() {
    let objects = k8s_objects();
    let coordinator = object(&objects, "Deployment", "vlf-coordinator");
    let worker = object(&objects, "Deployment", "vlf-worker");
    let service = object(&objects, "Service", "vlf-coordinator");

    // One coordinator per store, the old one gone before the new one starts.
    assert_eq!(coordinator["spec"]["replicas"].as_i64(), Some(1));
    assert_eq!(coordinator["spec"]["strategy"]["type"].as_str(), Some("Recreate"));

    // The object store of store.yaml is the one the config map points the service at: reached
    // by its Service's name and port, with the keys the coordinator and workers present, its
    // bucket made by the Job.
    let config = object(&objects, "ConfigMap", "vlf-store");
    let endpoint = text(&config["data"]["AWS_ENDPOINT_URL"], "AWS_ENDPOINT_URL");
    let (store_host, store_port) = host_port(&endpoint);
    let store_service = object(&objects, "Service", &store_host);
    assert_eq!(
        store_service["spec"]["ports"][0]["port"].as_i64(),
        Some(i64::from(store_port))
    );
    let minio = object(&objects, "Deployment", "vlf-store");
    let minio_container = only_container(minio);
    let minio_labels = minio["spec"]["template"]["metadata"]["labels"]
        .as_hash()
        .expect("labels");
    for (key, value) in store_service["spec"]["selector"].as_hash().expect("selector") {
        assert_eq!(
            minio_labels.get(key),
            Some(value),
            "the Service selects the store's pod"
        );
    }
    let minio_port = &minio_container["ports"][0];
    assert_eq!(store_service["spec"]["ports"][0]["targetPort"], minio_port["name"]);
    let minio_args = strings(&minio_container["args"], "store args");
    assert_eq!(
        host_port(flag(&minio_args, "--address")).1,
        minio_port["containerPort"].as_i64().expect("containerPort") as u16,
        "the store listens on its declared port"
    );
    let minio_env = k8s_role(&objects, minio_container, &BTreeMap::new()).env;
    let coordinator_env = k8s_role(&objects, only_container(coordinator), &BTreeMap::new()).env;
    assert_eq!(
        minio_env.get("MINIO_ROOT_USER"),
        coordinator_env.get("AWS_ACCESS_KEY_ID")
    );
    assert_eq!(
        minio_env.get("MINIO_ROOT_PASSWORD"),
        coordinator_env.get("AWS_SECRET_ACCESS_KEY")
    );
    let volume = &minio["spec"]["template"]["spec"]["volumes"][0];
    let claim = text(&volume["persistentVolumeClaim"]["claimName"], "claim");
    object(&objects, "PersistentVolumeClaim", &claim);
    let bucket_job = object(&objects, "Job", "vlf-store-bucket");
    let mc = &bucket_job["spec"]["template"]["spec"]["containers"][0];
    let made = strings(&mc["args"], "bucket job args").join(" ");
    let store_url = text(&config["data"]["VLF_STORE"], "VLF_STORE");
    let bucket_name = (store_url.strip_prefix("s3://").and_then(|r| r.split('/').next()))
        .unwrap_or_else(|| panic!("VLF_STORE is an s3:// URL: {store_url}"));
    assert!(made.contains(&format!("alias set store {endpoint} ")), "{made}");
    assert!(
        made.contains(&format!("mb --ignore-existing store/{bucket_name}")),
        "{made}"
    );
    let mc_env = k8s_role(&objects, mc, &BTreeMap::new()).env;
    assert_eq!(
        mc_env.get("AWS_ACCESS_KEY_ID"),
        coordinator_env.get("AWS_ACCESS_KEY_ID")
    );

    // Run against this machine's store: `.ci/run`'s S3 server when there is one (the
    // manifests' keys are placeholders, and no MinIO runs here), else a scratch directory.
    let scratch = tempfile::tempdir().unwrap();
    let dir = scratch.path();
    let overrides = test_store(dir);
    let c_container = only_container(coordinator);
    let w_container = only_container(worker);
    let c = k8s_role(&objects, c_container, &overrides);
    let w = k8s_role(&objects, w_container, &overrides);
    assert_eq!(
        flag(&c.args, "--store"),
        overrides["VLF_STORE"],
        "the store comes from VLF_STORE"
    );
    let token = c.env.get("VLF_TOKEN").expect("the coordinator's token").clone();
    assert_eq!(
        w.env.get("VLF_TOKEN"),
        Some(&token),
        "the workers present the coordinator's token"
    );

    // The port: listened on, declared, probed, served under the Service, reached by its name.
    let listen = flag(&c.args, "--listen").to_string();
    let (host, port) = host_port(&listen);
    assert_eq!(host, "0.0.0.0");
    let ports = c_container["ports"].as_vec().expect("ports");
    assert_eq!(ports.len(), 1);
    assert_eq!(ports[0]["containerPort"].as_i64(), Some(i64::from(port)));
    for probe in ["readinessProbe", "livenessProbe"] {
        assert_eq!(
            c_container[probe]["grpc"]["port"].as_i64(),
            Some(i64::from(port)),
            "{probe}"
        );
    }
    let service_port = &service["spec"]["ports"][0];
    assert_eq!(
        service_port["targetPort"], ports[0]["name"],
        "the Service targets the named port"
    );
    let labels = coordinator["spec"]["template"]["metadata"]["labels"]
        .as_hash()
        .expect("pod labels");
    for (key, value) in service["spec"]["selector"].as_hash().expect("selector") {
        assert_eq!(
            labels.get(key),
            Some(value),
            "the Service selects the coordinator's pods"
        );
    }
    let server_url = flag(&w.args, "--server").to_string();
    let (server_host, server_port) = host_port(&server_url);
    assert_eq!(
        server_host, "vlf-coordinator",
        "the workers reach the Service by its name"
    );
    assert_eq!(service_port["port"].as_i64(), Some(i64::from(server_port)));
    let replicas = worker["spec"]["replicas"].as_i64().expect("replicas") as usize;

    // Run it: what the gRPC probes ask is `vlf health`'s question.
    let free = free_port();
    let url = format!("http://127.0.0.1:{free}");
    let coordinator_here = Role {
        args: replaced(&c.args, &listen, &format!("127.0.0.1:{free}")),
        env: c.env.clone(),
    };
    let worker_here = Role {
        args: replaced(&w.args, &server_url, &url),
        env: w.env.clone(),
    };
    let health = vec!["health".to_string(), "--server".to_string(), url.clone()];
    serve_a_job(
        dir,
        &coordinator_here,
        &vec![worker_here; replicas],
        &health,
        &url,
        &token,
    );
}

#[test]
fn the_dockerfile_builds_this_binary_and_copies_what_exists() {
    let dockerfile = std::fs::read_to_string(repo().join("deploy/Dockerfile")).unwrap();
    // The package it builds is the one whose binary these tests run.
    assert!(
        dockerfile.contains(&format!("cargo build --release --locked -p {}", env!("CARGO_PKG_NAME"))),
        "the Dockerfile builds package {}",
        env!("CARGO_PKG_NAME")
    );
    assert!(dockerfile.contains("ENTRYPOINT [\"vlf\"]"));
    // What it copies from the build context exists (globs: their directory).
    for line in dockerfile
        .lines()
        .filter(|l| l.starts_with("COPY ") && !l.contains("--from="))
    {
        let words: Vec<&str> = line.split_whitespace().collect();
        for source in &words[1..words.len() - 1] {
            let path = repo().join(source);
            let exists = match source.rsplit_once('/') {
                Some((dir, pattern)) if pattern.contains('*') => {
                    let (head, tail) = pattern.split_once('*').unwrap_or((pattern, ""));
                    std::fs::read_dir(repo().join(dir)).unwrap().any(|e| {
                        let name = e.unwrap().file_name().to_string_lossy().into_owned();
                        name.starts_with(head) && name.ends_with(tail)
                    })
                }
                _ => path.exists(),
            };
            assert!(exists, "COPY {source}: nothing there");
        }
    }
    // The workspace builds without a system protobuf compiler (the image installs none).
    let proto_build = std::fs::read_to_string(repo().join("proto/build.rs")).unwrap();
    assert!(proto_build.contains("protoc_bin_vendored"));
}

/// `deploy/check.sh local`: the deployment check's own steps (a reference run, the service
/// with two workers, scaled to four, one killed, scaled to one, the digests compared) on
/// processes of this build. Its other runtimes (compose, kind, k3d) differ only in how they
/// start, scale and kill, and need a Docker engine, which CI lacks.
#[test]
fn the_deployment_check_passes_on_local_processes() {
    let o = std::process::Command::new("bash")
        .arg(repo().join("deploy/check.sh"))
        .args(["local", process::VLF])
        .envs([("L", "2049"), ("N", "32"), ("K", "11")])
        .env("VLF_CHECK_PORT", free_port().to_string())
        .env_remove("VLF_TOKEN")
        .env_remove("VLF_SERVER")
        .output()
        .expect("run bash");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", describe(&o));
    assert!(stdout.contains("the same bits"), "{}", describe(&o));
    for step in ["four workers", "one killed", "one worker"] {
        assert!(stdout.contains(step), "no step {step:?}:\n{}", describe(&o));
    }
}
