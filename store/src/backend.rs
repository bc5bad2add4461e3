//! Which `object_store` backend a store URL names.
//!
//! | URL | backend |
//! |---|---|
//! | `PATH` (no `scheme://`) or `file://PATH` | [`LocalFileSystem`] rooted at `PATH`, created if missing: the embedded default, no set-up |
//! | `s3://BUCKET` or `s3://BUCKET/PREFIX` | [`AmazonS3`](object_store::aws::AmazonS3) configured from the environment (below), keys under `PREFIX/` |
//! | `memory://` | [`InMemory`], for tests: lives as long as the `Store` and its clones |
//! | `memory://?latency=20ms` | the same, every call (get, put, list, delete) first waiting that long: what a round trip to a remote object store costs, for measuring it (`vlf bench --latency`) without one |
//!
//! # S3 environment
//!
//! Read by [`AmazonS3Builder::from_env`], so any S3-compatible server works (AWS, MinIO, Ceph,
//! s3s-fs, moto…):
//!
//! | variable | meaning |
//! |---|---|
//! | `AWS_ENDPOINT_URL` (or `AWS_ENDPOINT`) | server URL, e.g. `http://127.0.0.1:9000`; unset = AWS |
//! | `AWS_ALLOW_HTTP` | `true` to allow a plain-HTTP endpoint (a loopback test server) |
//! | `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY` | credentials (`AWS_SESSION_TOKEN` for temporary ones) |
//! | `AWS_REGION` (or `AWS_DEFAULT_REGION`) | region; default `us-east-1` |
//! | `AWS_VIRTUAL_HOSTED_STYLE_REQUEST` | `true` for `BUCKET.host` URLs; default path style, which self-hosted servers expect |
//!
//! The bucket must exist. Create-only writes use `If-None-Match: *` (S3 since 2024, MinIO, R2).
//!
//! # Local durability
//!
//! [`LocalFileSystem`] writes each object to a staging file in the same directory and renames (or,
//! for create-only writes, hard-links) it into place, so a reader never sees half an object.
//! Durability is batched: on Linux, [`crate::AsyncStore::flush`] makes everything written so far
//! durable with one `syncfs(2)` of the store's file system, and [`crate::job`] flushes before and
//! after every manifest write, so the commit order (blobs first, manifest last) survives a power
//! loss, not just a crash. That costs one sync per commit instead of one `fsync` per blob (a stage
//! of a mirror scene has thousands of tile blobs: 42 000 blobs took 14.7 s with an fsync each,
//! 3.2 s without). Elsewhere every object is fsynced as it is written.

use crate::error::StoreError;
use object_store::ObjectStore;
use object_store::aws::AmazonS3Builder;
use object_store::local::LocalFileSystem;
use object_store::memory::InMemory;
use object_store::prefix::PrefixStore;
use object_store::throttle::{ThrottleConfig, ThrottledStore};
use std::sync::Arc;
use std::time::Duration;

/// A backend, and the directory it lives in when it is local: what [`crate::AsyncStore::flush`]
/// syncs, and where a blocking read of a few objects reads them itself
/// ([`crate::Store::get_each`]).
pub(crate) struct Backend {
    pub store: Arc<dyn ObjectStore>,
    pub local_root: Option<std::path::PathBuf>,
}

/// Opens the backend that `url` names.
pub(crate) fn open(url: &str, create: bool) -> Result<Backend, StoreError> {
    let fail = |reason: String| StoreError::Url {
        url: url.to_string(),
        reason,
    };
    let trimmed = url.trim();
    if trimmed.is_empty() {
        return Err(fail("empty URL".into()));
    }
    match trimmed.split_once("://") {
        None => local(trimmed, create).map_err(fail),
        Some(("file", path)) => local(path, create).map_err(fail),
        Some(("memory", "")) => Ok(remote(Arc::new(InMemory::new()))),
        Some(("memory", rest)) => memory_with_latency(rest).map(remote).map_err(fail),
        Some(("s3", rest)) => s3(rest).map(remote).map_err(fail),
        Some((scheme, _)) if scheme.chars().all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c)) => {
            Err(fail(format!("unsupported scheme `{scheme}://`")))
        }
        // Something like `./odd://name`: a path with `://` in it.
        Some(_) => local(trimmed, create).map_err(fail),
    }
}

/// `memory://?latency=MSms`: an in-memory store whose every call waits `MS` milliseconds
/// first ([`ThrottledStore`]), as a call to a remote object store waits for its round trip (an S3
/// request in the same region takes some 10–30 ms to its first byte). Only a round trip: the
/// bytes themselves move at memory speed.
fn memory_with_latency(rest: &str) -> Result<Arc<dyn ObjectStore>, String> {
    const FORM: &str = "memory:// takes no path, only a simulated latency: `memory://?latency=20ms`";
    let ms = rest
        .strip_prefix("?latency=")
        .and_then(|v| v.strip_suffix("ms"))
        .ok_or_else(|| FORM.to_string())?;
    let ms: f64 = ms
        .parse()
        .map_err(|_| format!("latency `{ms}`: not a number of milliseconds ({FORM})"))?;
    if !(0.0..=10_000.0).contains(&ms) {
        return Err(format!("latency {ms} ms: must be between 0 and 10000 ms"));
    }
    let wait = Duration::from_secs_f64(ms / 1e3);
    let config = ThrottleConfig {
        wait_get_per_call: wait,
        wait_put_per_call: wait,
        wait_list_per_call: wait,
        wait_list_with_delimiter_per_call: wait,
        wait_delete_per_call: wait,
        ..ThrottleConfig::default()
    };
    Ok(Arc::new(ThrottledStore::new(InMemory::new(), config)))
}

fn remote(store: Arc<dyn ObjectStore>) -> Backend {
    Backend {
        store,
        local_root: None,
    }
}

/// A local directory, created if missing and `create`.
fn local(path: &str, create: bool) -> Result<Backend, String> {
    if path.is_empty() {
        return Err("file:// needs a path, e.g. file:///var/vlf".into());
    }
    if !create && !std::path::Path::new(path).is_dir() {
        return Err(format!("no store directory `{path}`"));
    }
    std::fs::create_dir_all(path).map_err(|e| format!("cannot create directory `{path}`: {e}"))?;
    let fs = LocalFileSystem::new_with_prefix(path)
        .map_err(|e| e.to_string())?
        .with_fsync(!cfg!(target_os = "linux"))
        .with_automatic_cleanup(true);
    Ok(Backend {
        store: Arc::new(fs),
        local_root: Some(std::path::PathBuf::from(path)),
    })
}

/// An S3 bucket, optionally under a prefix, configured from the environment.
fn s3(rest: &str) -> Result<Arc<dyn ObjectStore>, String> {
    let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
    if bucket.is_empty() {
        return Err("s3:// needs a bucket, e.g. s3://my-bucket/vlf".into());
    }
    let prefix = prefix.trim_end_matches('/');
    let s3 = AmazonS3Builder::from_env()
        .with_bucket_name(bucket)
        .build()
        .map_err(|e| e.to_string())?;
    if prefix.is_empty() {
        return Ok(Arc::new(s3));
    }
    let prefix = object_store::path::Path::parse(prefix).map_err(|e| format!("bad prefix `{prefix}`: {e}"))?;
    Ok(Arc::new(PrefixStore::new(s3, prefix)))
}
