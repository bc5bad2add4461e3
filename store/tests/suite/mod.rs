//! The store test suite, generic over backends: each case takes an [`Opener`] that opens fresh
//! handles onto one and the same storage (a "restart" of the process is opening a new handle).

use vlf_store::blob::{self, BlobError, BlobKind, Encoding};
use vlf_store::{Job, JobId, JobState, PutOutcome, Stage, Store, StoreError, layout};

/// Declares, for each `test => case`, one test per backend — modules `memory`, `path` (a
/// temporary directory), `file_url` (the same as `file://`) and `s3` (runs when
/// `VLF_TEST_S3_URL` is set) — so that a failure names both the case and the backend. `case` is a
/// `fn(&Opener)`, named from the test crate's root (`crate::…`).
macro_rules! per_backend {
    ($($test:ident => $case:expr),* $(,)?) => {
        per_backend!(@one memory, |_: &str| Some($crate::suite::Opener::memory()), $($test => $case),*);
        per_backend!(@one path, |_: &str| Some($crate::suite::Opener::file(false)), $($test => $case),*);
        per_backend!(@one file_url, |_: &str| Some($crate::suite::Opener::file(true)), $($test => $case),*);
        per_backend!(@one s3, $crate::suite::Opener::s3, $($test => $case),*);
    };
    (@one $backend:ident, $opener:expr, $($test:ident => $case:expr),*) => {
        mod $backend {
            $(
                #[test]
                fn $test() {
                    let open: fn(&str) -> Option<$crate::suite::Opener> = $opener;
                    if let Some(o) = open(stringify!($test)) {
                        ($case)(&o);
                    }
                }
            )*
        }
    };
}

/// Opens handles onto one storage.
pub struct Opener {
    /// The URL every handle is opened with.
    pub url: String,
    /// For `memory://`, the one store all handles share (a new `InMemory` would be empty).
    shared: Option<Store>,
    /// Keeps a temporary directory alive for the life of the test.
    _dir: Option<tempfile::TempDir>,
    /// Whether the backend's create-only put is atomic under concurrent writers (true of the
    /// local and memory backends, AWS S3 and MinIO; not of s3s-fs, whose `If-None-Match` check
    /// races: two of six concurrent creators were seen to succeed). For S3, opt in with
    /// `VLF_TEST_S3_ATOMIC_CREATE=1`.
    pub atomic_create: bool,
}

impl Opener {
    pub fn memory() -> Opener {
        let store = Store::open("memory://").expect("memory store");
        Opener {
            url: "memory://".into(),
            shared: Some(store),
            _dir: None,
            atomic_create: true,
        }
    }

    pub fn file(with_scheme: bool) -> Opener {
        let dir = tempfile::tempdir().expect("temp dir");
        // A directory below the temp dir, so that opening must create it.
        let path = dir.path().join("vlf-store");
        let path = path.to_str().expect("utf-8 temp path");
        let url = if with_scheme {
            format!("file://{path}")
        } else {
            path.to_string()
        };
        Opener {
            url,
            shared: None,
            _dir: Some(dir),
            atomic_create: true,
        }
    }

    /// `VLF_TEST_S3_URL` (e.g. `s3://vlf-test`) plus a prefix unique to this test, or `None`
    /// (with a note) when it is not set.
    pub fn s3(test: &str) -> Option<Opener> {
        let Ok(base) = std::env::var("VLF_TEST_S3_URL") else {
            // CI starts a server and sets this, so the S3 runs cannot be skipped silently there.
            assert!(
                std::env::var_os("VLF_REQUIRE_S3").is_none(),
                "VLF_REQUIRE_S3 is set but VLF_TEST_S3_URL is not"
            );
            println!("note: VLF_TEST_S3_URL is not set; skipping the S3 run of `{test}`");
            return None;
        };
        let url = format!("{}/{}-{test}", base.trim_end_matches('/'), JobId::generate());
        let atomic_create = std::env::var("VLF_TEST_S3_ATOMIC_CREATE").is_ok_and(|v| v == "1");
        Some(Opener {
            url,
            shared: None,
            _dir: None,
            atomic_create,
        })
    }

    pub fn open(&self) -> Store {
        match &self.shared {
            Some(store) => store.clone(),
            None => Store::open(&self.url).unwrap_or_else(|e| panic!("open {}: {e}", self.url)),
        }
    }
}

fn params() -> serde_json::Value {
    serde_json::json!({"directions": 33, "resolution": 16, "tile": 8, "converge": 1e-3})
}

/// Radiance of a tile, different per (iteration, dir, s, t) and exactly representable.
fn tile_values(k: u32, dir: u32, s: u32, t: u32) -> Vec<f32> {
    (0..8 * 8 * 3)
        .map(|i| ((i + k * 7 + dir * 3 + s + t * 5) % 64) as f32 / 16.0)
        .collect()
}

/// Writes a complete snapshot of iteration `k`: state, two diffuse surfaces, a mirror, 2 × 2
/// tiles of 3 directions. `salt` changes the content.
fn write_snapshot(job: &Job, k: u32, salt: u8) -> Result<(), StoreError> {
    let stage = Stage::Iteration(k);
    for dir in 0..3 {
        for s in 0..2 {
            for t in 0..2 {
                let mut v = tile_values(k, dir, s, t);
                v[0] += f32::from(salt);
                job.put_tile(stage, dir, s, t, &[8, 8, 3], &v)?;
            }
        }
    }
    for surface in [0, 5] {
        job.put_diffuse(
            stage,
            surface,
            &[4, 6, 3],
            &vec![0.25 * (k + surface) as f32 + f32::from(salt); 72],
        )?;
    }
    job.put_mirror(stage, 2, &[3, 2, 3], &[1.5; 18])?;
    job.put_state(k, format!("state after iteration {k}, salt {salt}").as_bytes())
}

/// Plain put, get, exists, listing and delete; missing keys name the key and the store.
pub fn put_get_list_delete(o: &Opener) {
    let store = o.open();
    store.put("a/b/one.bin", b"1".to_vec()).unwrap();
    store.put("a/b/two.bin", &b"22"[..]).unwrap();
    store.put("a/c/three.bin", b"333".to_vec()).unwrap();
    store.put("ab/x.bin", b"x".to_vec()).unwrap();
    store.put("a/b/one.bin", b"one".to_vec()).unwrap(); // overwrite
    let store = o.open();
    assert_eq!(&store.get("a/b/one.bin").unwrap()[..], b"one");
    assert!(store.exists("a/c/three.bin").unwrap());
    assert!(!store.exists("a/c/none.bin").unwrap());
    assert_eq!(
        store.list("a/").unwrap(),
        ["a/b/one.bin", "a/b/two.bin", "a/c/three.bin"]
    );
    assert_eq!(store.list("a/b/").unwrap(), ["a/b/one.bin", "a/b/two.bin"]);
    assert_eq!(store.list("").unwrap().len(), 4);
    assert_eq!(store.list("nothing/").unwrap(), Vec::<String>::new());
    assert_eq!(store.list_children("a/").unwrap(), ["b", "c"]);

    store.delete("a/b/one.bin").unwrap();
    store.delete("a/b/one.bin").unwrap(); // deleting a missing key is fine
    let err = store.get("a/b/one.bin").unwrap_err();
    assert!(
        matches!(&err, StoreError::NotFound { key, .. } if key == "a/b/one.bin"),
        "{err:?}"
    );
    let msg = err.to_string();
    assert!(msg.contains("a/b/one.bin") && msg.contains(&o.url), "{msg}");
    assert_eq!(store.list("a/").unwrap(), ["a/b/two.bin", "a/c/three.bin"]);
}

/// Create-only writes: new → created, same bytes → unchanged, other bytes → refused, original kept.
pub fn put_new_is_create_only(o: &Opener) {
    let store = o.open();
    assert_eq!(
        store.put_new("snap/x.blob", b"first".to_vec()).unwrap(),
        PutOutcome::Created
    );
    assert_eq!(
        store.put_new("snap/x.blob", b"first".to_vec()).unwrap(),
        PutOutcome::Unchanged
    );
    let err = o.open().put_new("snap/x.blob", b"second".to_vec()).unwrap_err();
    assert!(
        matches!(&err, StoreError::AlreadyExists { key, .. } if key == "snap/x.blob"),
        "{err:?}"
    );
    assert!(err.to_string().contains(&o.url));
    assert_eq!(&store.get("snap/x.blob").unwrap()[..], b"first");
    // After a plain put, create-only compares against the new content.
    store.put("snap/x.blob", b"second".to_vec()).unwrap();
    assert_eq!(
        store.put_new("snap/x.blob", b"second".to_vec()).unwrap(),
        PutOutcome::Unchanged
    );
    // A blob whose payload another build compressed otherwise (here at zstd's level 19, the
    // header's lengths and checksums made anew) holds the same content: no conflict, and what
    // was there stays. Another payload is one.
    let raw: Vec<u8> = (0..100_000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 27) as u8)
        .collect();
    let ours = blob::encode_bytes(BlobKind::BatchOutput, &raw).unwrap();
    let payload = zstd::bulk::compress(&raw, 19).unwrap();
    let mut theirs = ours[..blob::HEADER_LEN].to_vec();
    theirs[32..40].copy_from_slice(&(payload.len() as u64).to_le_bytes());
    theirs[40..44].copy_from_slice(&crc32c::crc32c(&payload).to_le_bytes());
    let header_crc = crc32c::crc32c(&theirs[..44]);
    theirs[44..48].copy_from_slice(&header_crc.to_le_bytes());
    theirs.extend_from_slice(&payload);
    assert_ne!(ours, theirs);
    assert_eq!(blob::decode_bytes(&theirs, BlobKind::BatchOutput).unwrap(), raw);
    store.put_new("work/block.blob", theirs.clone()).unwrap();
    assert_eq!(store.put_new("work/block.blob", ours).unwrap(), PutOutcome::Unchanged);
    assert_eq!(&store.get("work/block.blob").unwrap()[..], &theirs[..]);
    let mut other = raw;
    other[7] ^= 1;
    let err = store
        .put_new(
            "work/block.blob",
            blob::encode_bytes(BlobKind::BatchOutput, &other).unwrap(),
        )
        .unwrap_err();
    assert!(matches!(err, StoreError::AlreadyExists { .. }), "{err:?}");
}

/// Keys and prefixes outside the key rules are refused before reaching the backend.
pub fn invalid_keys_are_refused(o: &Opener) {
    let store = o.open();
    for key in ["", "/abs", "a//b", "a/../b", "dir/", "sp ace", "a#1"] {
        let err = store.put(key, b"x".to_vec()).unwrap_err();
        assert!(matches!(err, StoreError::InvalidKey { .. }), "{key:?}: {err:?}");
    }
    assert!(matches!(store.list("a"), Err(StoreError::InvalidKey { .. })));
    assert!(matches!(store.list("a//"), Err(StoreError::InvalidKey { .. })));
}

/// Every blob kind and encoding through the store, and every corruption read through the store
/// is a `StoreError::Blob` naming key and store.
pub fn blobs_through_the_store(o: &Opener) {
    let store = o.open();
    for kind in BlobKind::ALL {
        let key = format!("blobs/{kind:?}/bytes.blob");
        store.put(&key, blob::encode_bytes(kind, b"payload").unwrap()).unwrap();
        assert_eq!(store.get_bytes_blob(&key, kind).unwrap(), b"payload");
        for encoding in Encoding::VALUES {
            let key = format!("blobs/{kind:?}/{encoding:?}.blob");
            let rgb = [[0.5f32, 1.0, 2.0], [0.0, 0.125, 4.0]];
            store
                .put(&key, blob::encode_rgb(kind, encoding, &rgb).unwrap())
                .unwrap();
            assert_eq!(store.get_rgb(&key, kind).unwrap(), rgb);
            assert_eq!(store.get_blob(&key, kind).unwrap().encoding, encoding);
        }
    }
    let good = blob::encode_rgb(BlobKind::TileRadiance, Encoding::F16, &[[1.0, 2.0, 3.0]; 10]).unwrap();
    let mut flipped = good.clone();
    let last = flipped.len() - 1;
    flipped[last] ^= 0x40;
    let mut version = good.clone();
    version[4] = 9;
    type Expect = fn(&BlobError) -> bool;
    let cases: Vec<(&str, Vec<u8>, Expect)> = vec![
        ("bad/truncated.blob", good[..good.len() - 3].to_vec(), |e| {
            matches!(e, BlobError::Truncated { .. })
        }),
        ("bad/flipped.blob", flipped, |e| {
            matches!(e, BlobError::ChecksumMismatch { .. })
        }),
        ("bad/version.blob", version, |e| {
            matches!(e, BlobError::UnsupportedVersion { found: 9, .. })
        }),
        ("bad/not-a-blob.blob", b"<html>502</html>".to_vec(), |e| {
            matches!(e, BlobError::BadMagic { .. })
        }),
        ("bad/empty.blob", Vec::new(), |e| {
            matches!(e, BlobError::Truncated { .. })
        }),
    ];
    for (key, bytes, expected) in cases {
        store.put(key, bytes).unwrap();
        let err = store.get_rgb(key, BlobKind::TileRadiance).unwrap_err();
        match &err {
            StoreError::Blob { key: k, source, .. } if k == key && expected(source) => {}
            other => panic!("{key}: unexpected {other:?}"),
        }
        let msg = err.to_string();
        assert!(msg.contains(key) && msg.contains(&o.url), "{msg}");
    }
    store.put("bad/kind.blob", good).unwrap();
    let err = store.get_rgb("bad/kind.blob", BlobKind::DiffuseMaps).unwrap_err();
    assert!(
        matches!(
            &err,
            StoreError::Blob {
                source: BlobError::WrongKind { .. },
                ..
            }
        ),
        "{err:?}"
    );
}

/// A job's life: create, snapshots committed one by one, reading them back after a "restart",
/// listing a job and a direction in one prefix listing each, the final field, job listing.
pub fn job_lifecycle(o: &Opener) {
    let store = o.open();
    let mut job = Job::create(&store, b"normalised scene", "00ff17", params(), Encoding::F16).unwrap();
    let id = job.id().clone();
    assert_eq!(job.manifest().state, JobState::Queued);
    assert_eq!(job.last_finished(), None);
    for k in 0..3 {
        write_snapshot(&job, k, 0).unwrap();
        job.commit_iteration(k).unwrap();
    }
    assert_eq!(job.manifest().state, JobState::Propagating { iteration: 3 });
    for dir in 0..3 {
        for s in 0..2 {
            for t in 0..2 {
                job.put_tile(Stage::Field, dir, s, t, &[8, 8, 3], &tile_values(99, dir, s, t))
                    .unwrap();
            }
        }
    }
    job.put_diffuse(Stage::Field, 0, &[2, 2, 3], &[3.0; 12]).unwrap();
    job.finish().unwrap();

    // "Restart": a fresh handle sees everything committed.
    let store = o.open();
    let job = Job::open(&store, &id).unwrap();
    assert_eq!(job.manifest().finished_iterations, [0, 1, 2]);
    assert_eq!(job.manifest().state, JobState::Finished);
    assert_eq!(job.manifest().encoding, Encoding::F16);
    assert_eq!(job.manifest().parameters, params());
    assert_eq!(job.scene().unwrap(), b"normalised scene");
    assert_eq!(job.get_state(1).unwrap(), b"state after iteration 1, salt 0");
    assert_eq!(
        job.get_tile(Stage::Iteration(2), 1, 1, 0).unwrap(),
        (vec![8, 8, 3], tile_values(2, 1, 1, 0))
    );
    assert_eq!(job.get_tile(Stage::Field, 2, 0, 1).unwrap().1, tile_values(99, 2, 0, 1));
    assert_eq!(job.get_diffuse(Stage::Iteration(1), 5).unwrap().1, vec![1.5; 72]);
    assert_eq!(
        job.get_mirror(Stage::Iteration(0), 2).unwrap(),
        (vec![3, 2, 3], vec![1.5; 18])
    );
    assert_eq!(job.get_diffuse(Stage::Field, 0).unwrap().1, vec![3.0; 12]);

    // One prefix listing: a direction, an iteration, the whole job.
    assert_eq!(
        job.list_tiles(Stage::Iteration(1), 2).unwrap(),
        [(0, 0), (0, 1), (1, 0), (1, 1)]
    );
    let dir_keys = store
        .list(&layout::direction_prefix(&id, Stage::Iteration(1), 2).unwrap())
        .unwrap();
    assert_eq!(dir_keys.len(), 4);
    let iteration = store
        .list(&layout::stage_prefix(&id, Stage::Iteration(1)).unwrap())
        .unwrap();
    assert_eq!(iteration.len(), 12 + 2 + 1 + 1);
    let all = store.list(&layout::job_prefix(&id)).unwrap();
    assert_eq!(all.len(), 2 + 3 * 16 + 12 + 1);
    assert!(all.contains(&layout::manifest(&id)) && all.contains(&layout::scene(&id)));

    // Listing jobs finds this one (and an orphan without manifest is not a job).
    store
        .put(
            "jobs/orphan/scene.blob",
            blob::encode_bytes(BlobKind::Scene, b"s").unwrap(),
        )
        .unwrap();
    let jobs = Job::list(&store).unwrap();
    assert!(jobs.contains(&id), "{jobs:?}");
    assert!(!jobs.iter().any(|j| j.as_str() == "orphan"));

    // A given id cannot be reused.
    let err = Job::create_with_id(&store, id.clone(), b"other", "ab", params(), Encoding::F32).unwrap_err();
    assert!(matches!(err, StoreError::AlreadyExists { .. }), "{err:?}");
    assert_eq!(Job::open(&store, &id).unwrap().scene().unwrap(), b"normalised scene");
}

/// The commit protocol across a simulated crash between writing a snapshot's blobs and updating
/// the manifest.
pub fn crash_between_blobs_and_manifest(o: &Opener) {
    let store = o.open();
    let mut job = Job::create(&store, b"scene", "abc123", params(), Encoding::Rgb9e5).unwrap();
    let id = job.id().clone();
    for k in 0..2 {
        write_snapshot(&job, k, 0).unwrap();
        job.commit_iteration(k).unwrap();
    }
    // Iteration 2's blobs are written, then the process "dies" before committing.
    write_snapshot(&job, 2, 0).unwrap();
    drop(job);

    // Reopened: iteration 1 is the last finished; iteration 2 is invisible.
    let store = o.open();
    let mut job = Job::open(&store, &id).unwrap();
    assert_eq!(job.last_finished(), Some(1));
    assert_eq!(job.manifest().state, JobState::Propagating { iteration: 2 });
    let err = job.get_tile(Stage::Iteration(2), 0, 0, 0).unwrap_err();
    assert!(
        matches!(&err, StoreError::Job { reason, .. } if reason.contains("iteration 2 is not finished")),
        "{err}"
    );
    assert!(job.get_state(2).is_err());
    assert!(job.get_tile(Stage::Field, 0, 0, 0).is_err());

    // Resuming writes iteration 2 again: identical content is fine, and so is different content
    // (the orphan of a crashed run is replaced, it was never committed).
    write_snapshot(&job, 2, 0).unwrap();
    write_snapshot(&job, 2, 1).unwrap();
    job.commit_iteration(2).unwrap();
    assert_eq!(job.get_state(2).unwrap(), b"state after iteration 2, salt 1");

    // Committed iterations are immutable: identical rewrites succeed, different ones fail and
    // leave the committed content.
    write_snapshot(&job, 1, 0).unwrap();
    let err = write_snapshot(&job, 1, 3).unwrap_err();
    assert!(matches!(err, StoreError::AlreadyExists { .. }), "{err:?}");
    assert!(err.to_string().contains(&id.to_string()), "{err}");
    let reopened = Job::open(&o.open(), &id).unwrap();
    assert_eq!(
        reopened.get_tile(Stage::Iteration(1), 0, 0, 0).unwrap().1,
        tile_values(1, 0, 0, 0)
    );

    // Out-of-order and repeated commits.
    job.commit_iteration(1).unwrap(); // already listed: no-op
    write_snapshot(&job, 4, 0).unwrap();
    job.commit_iteration(4).unwrap(); // a gap (iteration 3 not snapshotted) is allowed
    let err = job.commit_iteration(3).unwrap_err();
    assert!(matches!(err, StoreError::Job { .. }), "{err:?}");
    let err = job.commit_iteration(7).unwrap_err(); // no state written
    assert!(err.to_string().contains("resume state is not written"), "{err}");
    assert_eq!(
        Job::open(&o.open(), &id).unwrap().manifest().finished_iterations,
        [0, 1, 2, 4]
    );

    // A failed job is not committed to until it is resumed.
    job.set_state(JobState::Failed {
        message: "out of memory".into(),
    })
    .unwrap();
    write_snapshot(&job, 5, 0).unwrap();
    assert!(job.commit_iteration(5).is_err());
    job.set_state(JobState::Propagating { iteration: 5 }).unwrap();
    job.commit_iteration(5).unwrap();
    let reopened = Job::open(&o.open(), &id).unwrap();
    assert_eq!(reopened.last_finished(), Some(5));
}

/// A damaged or foreign manifest is an error naming its key, never a job.
pub fn corrupted_manifest(o: &Opener) {
    let store = o.open();
    let job = Job::create(&store, b"scene", "abc", params(), Encoding::F32).unwrap();
    let id = job.id().clone();
    let key = layout::manifest(&id);
    let good = store.get(&key).unwrap().to_vec();

    let mut flipped = good.clone();
    let i = flipped.len() - 2;
    flipped[i] ^= 0x01;
    store.put(&key, flipped).unwrap();
    let err = Job::open(&store, &id).unwrap_err();
    assert!(
        matches!(
            err,
            StoreError::Blob {
                source: BlobError::ChecksumMismatch { .. },
                ..
            }
        ),
        "{err:?}"
    );
    assert!(err.to_string().contains(&key), "{err}");

    store.put(&key, good[..good.len() / 2].to_vec()).unwrap();
    let err = Job::open(&store, &id).unwrap_err();
    assert!(
        matches!(
            err,
            StoreError::Blob {
                source: BlobError::Truncated { .. },
                ..
            }
        ),
        "{err:?}"
    );

    store
        .put(
            &key,
            blob::encode_bytes(BlobKind::Manifest, b"{\"format\": 1}").unwrap(),
        )
        .unwrap();
    let err = Job::open(&store, &id).unwrap_err();
    assert!(
        matches!(&err, StoreError::Manifest { key: k, .. } if *k == key),
        "{err:?}"
    );

    // Another job's manifest copied here.
    let other = Job::create(&store, b"scene", "abc", params(), Encoding::F32).unwrap();
    store
        .put(&key, store.get(&layout::manifest(other.id())).unwrap())
        .unwrap();
    let err = Job::open(&store, &id).unwrap_err();
    assert!(err.to_string().contains("belongs to job"), "{err}");

    let missing = JobId::parse("no-such-job").unwrap();
    let err = Job::open(&store, &missing).unwrap_err();
    assert!(matches!(err, StoreError::NotFound { .. }), "{err:?}");
}

/// Encodings a job cannot store are refused with the key named, nothing is written.
pub fn unrepresentable_radiance(o: &Opener) {
    let store = o.open();
    let job = Job::create(&store, b"scene", "abc", params(), Encoding::F16).unwrap();
    let err = job
        .put_diffuse(Stage::Iteration(0), 1, &[1, 3], &[1.0, 1.0e6, 0.0])
        .unwrap_err();
    let key = layout::diffuse(job.id(), Stage::Iteration(0), 1).unwrap();
    assert!(matches!(&err, StoreError::Blob { key: k, source: BlobError::Unrepresentable { .. }, .. } if *k == key));
    assert!(!store.exists(&key).unwrap());
}

/// Many threads sharing one store; racing create-only writes of one key: exactly one creates.
/// (VLF has one writer per job, so the race only matters for the backend's promise itself.)
pub fn concurrent_writers(o: &Opener) {
    let store = o.open();
    std::thread::scope(|scope| {
        for t in 0..4u8 {
            let store = store.clone();
            scope.spawn(move || {
                for i in 0..10usize {
                    let key = format!("threads/t{t}/{i:03}.bin");
                    store.put_new(&key, vec![t; i]).unwrap();
                    assert_eq!(store.get(&key).unwrap().len(), i);
                }
            });
        }
    });
    assert_eq!(store.list("threads/").unwrap().len(), 40);
    if !o.atomic_create {
        println!(
            "note: racing create-only writers not checked on {} (set VLF_TEST_S3_ATOMIC_CREATE=1)",
            o.url
        );
        return;
    }
    let outcomes: Vec<PutOutcome> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..6)
            .map(|_| {
                let store = o.open();
                scope.spawn(move || store.put_new("race/one.bin", b"same".to_vec()).unwrap())
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let created = outcomes.iter().filter(|o| **o == PutOutcome::Created).count();
    assert_eq!(created, 1, "{outcomes:?}");
    let refused = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..6u8)
            .map(|i| {
                let store = o.open();
                scope.spawn(move || store.put_new("race/two.bin", vec![i; 16]))
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap())
            .filter(|r| r.is_err())
            .count()
    });
    assert_eq!(
        refused, 5,
        "of 6 racing writers with different content, all but one are refused"
    );
}
