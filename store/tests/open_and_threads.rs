//! Opening stores by URL, local-directory details, and the async core.

use vlf_store::{AsyncStore, Store, StoreError};

fn url_error(url: &str) -> String {
    match Store::open(url) {
        Err(e @ StoreError::Url { .. }) => e.to_string(),
        Err(other) => panic!("{url:?}: expected a URL error, got {other:?}"),
        Ok(_) => panic!("{url:?}: opened"),
    }
}

#[test]
fn bad_urls_give_clear_errors() {
    let supported = "supported: a directory path or file:///PATH, s3://BUCKET[/PREFIX], memory://";
    for (url, says) in [
        ("", "empty URL"),
        ("   ", "empty URL"),
        ("ftp://host/dir", "unsupported scheme `ftp://`"),
        ("gs://bucket/x", "unsupported scheme `gs://`"),
        ("memory://name", "memory:// takes no path"),
        (
            "memory://?latency=20",
            "memory:// takes no path, only a simulated latency",
        ),
        ("memory://?latency=fast ms", "not a number of milliseconds"),
        ("memory://?latency=-5ms", "must be between 0 and 10000 ms"),
        ("memory://?latency=NaNms", "must be between 0 and 10000 ms"),
        ("s3://", "s3:// needs a bucket"),
        ("s3:///prefix", "s3:// needs a bucket"),
        ("file://", "file:// needs a path"),
    ] {
        let msg = url_error(url);
        assert!(msg.contains(says) && msg.contains(supported), "{url:?}: {msg}");
        assert!(msg.contains(&format!("`{url}`")), "{url:?}: {msg}");
    }
    // A path that cannot be a directory.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("plain-file");
    std::fs::write(&file, b"x").unwrap();
    let below = file.join("store");
    let msg = url_error(below.to_str().unwrap());
    assert!(msg.contains("cannot create directory"), "{msg}");
}

#[test]
fn a_memory_store_with_latency_waits_on_every_call_and_keeps_what_it_is_given() {
    let store = Store::open("memory://?latency=25ms").unwrap();
    assert_eq!(store.url(), "memory://?latency=25ms");
    let started = std::time::Instant::now();
    store.put("a/b.bin", b"value".to_vec()).unwrap();
    assert_eq!(&store.get("a/b.bin").unwrap()[..], b"value");
    assert_eq!(store.list("a/").unwrap(), ["a/b.bin"]);
    // Three calls, each waiting at least its latency (a sleep never ends early).
    assert!(
        started.elapsed() >= std::time::Duration::from_millis(75),
        "{:?}",
        started.elapsed()
    );
    assert!(Store::open("memory://?latency=0ms").is_ok());
}

#[test]
fn s3_urls_open_without_contacting_the_server() {
    // Building the client makes no request, so this runs anywhere.
    let store = Store::open("s3://some-bucket/some/prefix/").unwrap();
    assert_eq!(store.url(), "s3://some-bucket/some/prefix/");
    assert!(Store::open("s3://some-bucket").is_ok());
}

#[test]
fn local_store_persists_and_hides_staging_files() {
    let dir = tempfile::tempdir().unwrap();
    let url = format!("file://{}", dir.path().join("a/b").display());
    Store::open(&url).unwrap().put("k/v.bin", b"value".to_vec()).unwrap();
    // Leftovers of an interrupted write (LocalFileSystem's staging names) are not objects.
    std::fs::write(dir.path().join("a/b/k/w.bin#1"), b"half").unwrap();
    let store = Store::open(&url).unwrap();
    assert_eq!(&store.get("k/v.bin").unwrap()[..], b"value");
    assert_eq!(store.list("k/").unwrap(), ["k/v.bin"]);
    assert!(dir.path().join("a/b/k/v.bin").is_file());
}

#[test]
fn async_core_and_blocking_calls_inside_a_runtime() {
    let store = Store::open("memory://").unwrap();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(async {
        let core: &AsyncStore = store.as_async();
        core.put("x/y.bin", b"async".to_vec()).await.unwrap();
        assert_eq!(&core.get("x/y.bin").await.unwrap()[..], b"async");
        assert_eq!(core.list("x/").await.unwrap(), ["x/y.bin"]);
        // The blocking facade refuses instead of stalling the runtime.
        assert!(matches!(store.get("x/y.bin"), Err(StoreError::InsideRuntime { .. })));
        // Dropping a store (and its runtime) inside a runtime is fine.
        drop(Store::open("memory://").unwrap());
    });
    assert_eq!(&store.get("x/y.bin").unwrap()[..], b"async");
}

#[test]
fn a_handle_counts_what_goes_through_it_and_its_clones() {
    let store = Store::open("memory://").unwrap();
    let clone = store.clone();
    store.put("a", vec![1u8; 100]).unwrap();
    clone.put_new("b", vec![2u8; 30]).unwrap();
    // The same bytes again: compared (one read), not written.
    assert_eq!(
        clone.put_new("b", vec![2u8; 30]).unwrap(),
        vlf_store::PutOutcome::Unchanged
    );
    assert_eq!(store.get("a").unwrap().len(), 100);
    assert!(store.get("missing").is_err());
    let t = store.traffic();
    assert_eq!(t, clone.traffic());
    assert_eq!((t.writes, t.written_bytes), (2, 130));
    assert_eq!((t.reads, t.read_bytes), (2, 130));
    // Another handle of another store counts apart.
    assert_eq!(
        Store::open("memory://").unwrap().traffic(),
        vlf_store::Traffic::default()
    );
}
