//! Bulk store calls: many objects in one call, their requests overlapping their round trips.

use vlf_store::{Put, Store, StoreError};

fn puts(n: usize, create_only: bool) -> Vec<Put> {
    (0..n)
        .map(|i| Put {
            key: format!("bulk/{i:03}.bin"),
            bytes: format!("object {i}").into_bytes().into(),
            create_only,
        })
        .collect()
}

fn keys(n: usize) -> Vec<String> {
    (0..n).map(|i| format!("bulk/{i:03}.bin")).collect()
}

#[test]
fn bulk_calls_overlap_their_round_trips_and_keep_the_order_of_the_keys() {
    // Every call waits 100 ms for the backend: 20 puts one after another would never have more
    // than one waiting at once.
    let store = Store::open("memory://?latency=100ms").unwrap();
    store.put_all(puts(20, false)).unwrap();
    let wrote = store.traffic();
    assert_eq!(wrote.writes, 20);
    assert!(wrote.most_in_flight >= 10, "{wrote:?}");

    // Read back in the order asked, which is not the order written.
    let mut wanted = keys(20);
    wanted.reverse();
    let got = store.get_all(&wanted).unwrap();
    for (key, bytes) in wanted.iter().zip(&got) {
        let i: usize = key["bulk/".len()..key.len() - ".bin".len()].parse().unwrap();
        assert_eq!(&bytes[..], format!("object {i}").as_bytes(), "{key}");
    }
    assert_eq!(store.traffic().reads, 20);

    store.delete_all(&keys(20)).unwrap();
    assert!(store.list("bulk/").unwrap().is_empty());
    // Deleting what is not there is fine, as one delete is.
    store.delete_all(&keys(3)).unwrap();
}

#[test]
fn single_calls_wait_one_at_a_time() {
    let store = Store::open("memory://").unwrap();
    for put in puts(5, false) {
        store.put(&put.key, put.bytes).unwrap();
    }
    assert_eq!(store.traffic().most_in_flight, 1);
}

#[test]
fn bulk_create_only_writes_accept_the_same_bytes_and_refuse_others() {
    let store = Store::open("memory://").unwrap();
    store.put_all(puts(4, true)).unwrap();
    // The same bytes again: accepted (a block computed twice).
    store.put_all(puts(4, true)).unwrap();
    // Different bytes for one key: refused, naming it; what was stored stays.
    let mut changed = puts(4, true);
    changed[2].bytes = b"something else".to_vec().into();
    match store.put_all(changed) {
        Err(StoreError::AlreadyExists { key, .. }) => assert_eq!(key, "bulk/002.bin"),
        other => panic!("expected AlreadyExists, got {other:?}"),
    }
    assert_eq!(&store.get("bulk/002.bin").unwrap()[..], b"object 2");
    // Replacing writes replace.
    let mut replaced = puts(1, false);
    replaced[0].bytes = b"new".to_vec().into();
    store.put_all(replaced).unwrap();
    assert_eq!(&store.get("bulk/000.bin").unwrap()[..], b"new");
}

#[test]
fn a_bulk_read_of_a_missing_object_names_it() {
    let store = Store::open("memory://").unwrap();
    store.put_all(puts(2, false)).unwrap();
    let mut wanted = keys(2);
    wanted.push("bulk/missing.bin".into());
    match store.get_all(&wanted) {
        Err(e @ StoreError::NotFound { .. }) => assert!(e.to_string().contains("bulk/missing.bin"), "{e}"),
        other => panic!("expected NotFound, got {other:?}"),
    }
}

#[test]
fn writes_behind_are_there_once_waited_for_and_report_their_errors() {
    let store = Store::open("memory://?latency=20ms").unwrap();
    let writing = store.put_all_behind(puts(8, true)).unwrap();
    writing.wait().unwrap();
    assert_eq!(store.list("bulk/").unwrap(), keys(8));
    // A conflicting write behind fails when waited for, and leaves the object as it was.
    let mut changed = puts(1, true);
    changed[0].bytes = b"other".to_vec().into();
    match store.put_all_behind(changed).unwrap().wait() {
        Err(StoreError::AlreadyExists { key, .. }) => assert_eq!(key, "bulk/000.bin"),
        other => panic!("expected AlreadyExists, got {other:?}"),
    }
    assert_eq!(&store.get("bulk/000.bin").unwrap()[..], b"object 0");
}

#[test]
fn listing_jobs_checks_their_manifests_together() {
    use vlf_store::Job;
    use vlf_store::blob::Encoding;
    let store = Store::open("memory://?latency=20ms").unwrap();
    let made: Vec<_> = (0..12)
        .map(|i| {
            let scene = format!("scene {i}");
            let job = Job::create(&store, scene.as_bytes(), "ab", serde_json::json!({}), Encoding::F32);
            job.unwrap().id().clone()
        })
        .collect();
    // Creating a job is calls one after another.
    assert_eq!(store.traffic().most_in_flight, 1);
    let mut listed = Job::list(&store).unwrap();
    listed.sort();
    let mut made = made;
    made.sort();
    assert_eq!(listed, made);
    assert!(store.traffic().most_in_flight >= 6, "{:?}", store.traffic());
}

/// A few objects of a local directory are read on the caller's thread (`READ_HERE`), more on the
/// store's threads: both give the same bytes, the same traffic and the same errors.
#[test]
fn reads_of_a_directory_on_the_callers_thread_match_the_store_threads() {
    use vlf_store::READ_HERE;
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path().to_str().unwrap()).unwrap();
    let n = READ_HERE + 4;
    store.put_all(puts(n, true)).unwrap();
    let all = keys(n);
    let before = store.traffic();
    // More than READ_HERE: the store's threads.
    let bulk = store.get_all(&all).unwrap();
    // READ_HERE at most: this thread, in the order asked.
    let few: Vec<String> = all[..READ_HERE].iter().rev().cloned().collect();
    let here = store.get_all(&few).unwrap();
    let each = store.get_each(&few).unwrap();
    for (i, key) in few.iter().enumerate() {
        let at = all.iter().position(|k| k == key).unwrap();
        assert_eq!(here[i], bulk[at], "{key}");
        assert_eq!(each[i].as_ref().unwrap(), &bulk[at], "{key}");
        assert_eq!(store.get(key).unwrap(), bulk[at], "{key}");
        assert_eq!(&bulk[at][..], format!("object {at}").as_bytes());
    }
    // Every read counted, each bulk call as one round trip, each `get` as one.
    let read = store.traffic();
    assert_eq!(read.reads - before.reads, (n + 3 * READ_HERE) as u64);
    let bytes = |keys: &[String]| -> u64 {
        keys.iter()
            .map(|k| bulk[all.iter().position(|a| a == k).unwrap()].len() as u64)
            .sum()
    };
    assert_eq!(read.read_bytes - before.read_bytes, bytes(&all) + 3 * bytes(&few));
    assert_eq!(read.round_trips - before.round_trips, 3 + READ_HERE as u64);

    // A missing object: `NotFound`, named, whichever thread reads it; the others still read.
    let mut gaps = few.clone();
    gaps[1] = "bulk/missing.bin".into();
    match store.get_all(&gaps) {
        Err(StoreError::NotFound { key, .. }) => assert_eq!(key, "bulk/missing.bin"),
        other => panic!("expected NotFound, got {other:?}"),
    }
    let each = store.get_each(&gaps).unwrap();
    assert!(matches!(&each[1], Err(StoreError::NotFound { key, .. }) if key == "bulk/missing.bin"));
    assert_eq!(each[0].as_ref().unwrap(), &here[0]);
    let mut many = all.clone();
    many.push("bulk/missing.bin".into());
    assert!(matches!(store.get_all(&many), Err(StoreError::NotFound { .. })));
    // A key that would leave the directory is refused, not read.
    std::fs::write(dir.path().parent().unwrap().join("outside.bin"), b"secret").ok();
    for bad in ["../outside.bin", "bulk/../../outside.bin", "/bulk/000.bin"] {
        assert!(
            matches!(store.get(bad), Err(StoreError::InvalidKey { .. })),
            "{bad}: {:?}",
            store.get(bad)
        );
        let each = store.get_each(&[bad.to_string()]).unwrap();
        assert!(matches!(&each[0], Err(StoreError::InvalidKey { .. })), "{bad}");
    }
}
