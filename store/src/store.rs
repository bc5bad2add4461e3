//! The store: named byte strings in a backend chosen by URL (see [`crate::backend`]), with a
//! blocking facade for the rest of VLF (rayon workers, the CLI) and an async core for servers.
//!
//! Every method is one backend request (or, for [`AsyncStore::put_new`] on a conflict, two), and
//! every error names the key and the store URL — but for the bulk ones ([`AsyncStore::put_all`],
//! [`AsyncStore::get_all`], [`AsyncStore::delete_all`]), which keep up to
//! [`AsyncStore::in_flight`] requests going at once ([`IN_FLIGHT`], or [`file_threads`] to a local
//! directory). A blocking read of a few objects of a local directory is read on its caller's
//! thread instead ([`READ_HERE`]).
//!
//! **Why bulk calls.** A request to an object store waits a round trip (an S3 request in the same
//! region: some 10–30 ms to its first byte) in which it uses no CPU. A snapshot is hundreds of
//! blobs (one per surface); written one request per compute thread, as a `par_iter` of blocking
//! puts does, a 2-core machine kept two requests in flight, and the bundled mirror scene, whose
//! propagation takes 0.4 s, took 38 s over a store 10 ms away (`memory://?latency=10ms`). Callers
//! encode with their threads and hand the encoded blobs over in one call: the requests then
//! overlap each other's round trips, whatever the number of cores.

use crate::blob::{self, BlobError, BlobKind, Decoded};
use crate::error::StoreError;
use bytes::Bytes;
use futures::{StreamExt, TryStreamExt};
use object_store::path::Path;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload};
use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// What a create-only write did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PutOutcome {
    /// The key did not exist; it now holds the new content.
    Created,
    /// The key already held this content (the same bytes, or the same blob payload compressed
    /// otherwise: [`blob::same_content`]); nothing was written.
    Unchanged,
}

/// What went through a store handle (and its clones) since it was opened: objects and bytes
/// read and written, as stored (compressed). How `vlf bench` measures what a run moves.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Traffic {
    pub reads: u64,
    pub read_bytes: u64,
    pub writes: u64,
    pub written_bytes: u64,
    /// The most gets, puts, existence checks and deletes that were waiting for the backend at
    /// once: how much of their round trips overlapped (see the module docs).
    pub most_in_flight: u64,
    /// Calls of the blocking [`Store`], a bulk call counting once: the round trips to the
    /// backend its callers waited through one after another.
    pub round_trips: u64,
}

/// A get, put, existence check or delete waiting for the backend, counted in
/// [`Traffic::most_in_flight`] while it lives.
struct InFlight<'a>(&'a Counters);

impl<'a> InFlight<'a> {
    fn new(counters: &'a Counters) -> InFlight<'a> {
        let now = counters.in_flight.fetch_add(1, Ordering::Relaxed) + 1;
        counters.most_in_flight.fetch_max(now, Ordering::Relaxed);
        InFlight(counters)
    }
}

impl Drop for InFlight<'_> {
    fn drop(&mut self) {
        self.0.in_flight.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Most requests a bulk call keeps in flight at once. An object store serves many more; this
/// bounds the memory of the blobs in flight and the connections one process opens.
pub const IN_FLIGHT: usize = 256;

/// Most calls a bulk call keeps in flight to a local directory, in place of [`IN_FLIGHT`]: the
/// machine's cores, and at least 4.
///
/// `object_store` runs each call to a local file system as a blocking task on the caller's
/// runtime, and tokio starts a thread for each task that finds none idle, up to 512. A bulk write
/// of a job's field (6 000 tiles, 256 at a time) ran about 500 threads, and with transparent huge
/// pages each new thread's allocator heap faulted in a fresh 2 MB page. On this project's 2-core
/// VM that was 0.7 s of CPU in a 30-iteration mirror-scene `vlf run` into a directory on tmpfs,
/// and 0.4 s of its 2 s. With this many calls in flight tokio still starts a few dozen threads
/// (a call's tasks follow each other faster than a thread goes idle), so a [`Store`]'s own
/// runtime also runs no more than this many.
///
/// Why so few: a call into the page cache (tmpfs, or a disk's writes before the commit's sync)
/// is CPU work, so threads beyond the cores only queue for them. With 16, two workers on this
/// VM often waited 5 ms for a 0.2-ms read of the next iteration's head while the coordinator's
/// background commit kept the threads busy (8–23 of 52 reads in 30-iteration runs); with 4,
/// about half as often (5–10).
pub fn file_threads() -> usize {
    // Asked once: every bulk call needs it, and the answer reads the process's cgroup files.
    static THREADS: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *THREADS.get_or_init(|| std::thread::available_parallelism().map_or(4, |n| n.get().max(4)))
}

/// Most objects a [`Store`]'s blocking read of a local directory reads on its caller's thread
/// ([`Store::get`], [`Store::get_all`], [`Store::get_each`]); more go to the store's threads, which
/// read them in parallel.
///
/// Why: the caller waits anyway, and `object_store` runs a local read as two blocking tasks (open,
/// then read) queued behind every call the store's threads have in hand — on a worker, the map
/// parts of its last block still being written; on the coordinator's side, the background commit
/// of the last snapshot. With two workers into a directory on tmpfs on this project's 2-core VM,
/// a worker's read of the next iteration's head waited for them: 0.36 ms in the median, 2 ms on
/// average, up to 5 ms. Read on its own thread: 0.18 ms and 0.6 ms. The objects an iteration's
/// path reads are that few: the head and the map parts a block gathers.
pub const READ_HERE: usize = 8;

/// One object for [`AsyncStore::put_all`] to write.
#[derive(Debug, Clone)]
pub struct Put {
    pub key: String,
    pub bytes: Bytes,
    /// Written with [`AsyncStore::put_new`] (create-only: the same content again is accepted,
    /// other content refused) rather than [`AsyncStore::put`] (replacing).
    pub create_only: bool,
}

#[derive(Debug, Default)]
struct Counters {
    reads: AtomicU64,
    read_bytes: AtomicU64,
    writes: AtomicU64,
    written_bytes: AtomicU64,
    in_flight: AtomicU64,
    most_in_flight: AtomicU64,
    round_trips: AtomicU64,
}

impl Counters {
    fn read(&self, bytes: usize) {
        self.reads.fetch_add(1, Ordering::Relaxed);
        self.read_bytes.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    fn wrote(&self, bytes: usize) {
        self.writes.fetch_add(1, Ordering::Relaxed);
        self.written_bytes.fetch_add(bytes as u64, Ordering::Relaxed);
    }
}

/// The async core of a store. Cheap to clone. Use it from inside a tokio runtime; elsewhere use
/// [`Store`].
#[derive(Debug, Clone)]
pub struct AsyncStore {
    backend: Arc<dyn ObjectStore>,
    url: Arc<str>,
    /// The directory of a local store: whose writes [`AsyncStore::flush`] must sync, and where a
    /// [`Store`]'s blocking read of a few objects reads them on its caller's thread
    /// ([`AsyncStore::read_here`]).
    local_root: Option<Arc<std::path::Path>>,
    counters: Arc<Counters>,
}

impl AsyncStore {
    /// Opens the store that `url` names (see [`crate::backend`] for the URL forms).
    pub fn open(url: &str) -> Result<AsyncStore, StoreError> {
        AsyncStore::open_with(url, true)
    }

    /// As [`AsyncStore::open`], but a local directory must already exist (for readers: a
    /// mistyped path is an error, not a new empty store).
    pub fn open_existing(url: &str) -> Result<AsyncStore, StoreError> {
        AsyncStore::open_with(url, false)
    }

    fn open_with(url: &str, create: bool) -> Result<AsyncStore, StoreError> {
        let backend = crate::backend::open(url, create)?;
        Ok(AsyncStore {
            backend: backend.store,
            url: url.trim().into(),
            local_root: backend.local_root.map(Arc::from),
            counters: Arc::default(),
        })
    }

    /// Makes every write made so far durable (survives a power loss). A local store on Linux
    /// syncs its file system once (see [`crate::backend`]); object stores are durable when a put
    /// returns, and memory never is, so for them this does nothing.
    pub async fn flush(&self) -> Result<(), StoreError> {
        // Elsewhere a local store syncs each file as it writes it (see `crate::backend`).
        let Some(root) = self.local_root.clone().filter(|_| cfg!(target_os = "linux")) else {
            return Ok(());
        };
        let synced = tokio::task::spawn_blocking(move || -> std::io::Result<()> {
            let dir = std::fs::File::open(&*root)?;
            #[cfg(target_os = "linux")]
            rustix::fs::syncfs(&dir)?;
            #[cfg(not(target_os = "linux"))]
            dir.sync_all()?;
            Ok(())
        })
        .await;
        match synced {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(self.backend_error(
                "flush",
                "",
                object_store::Error::Generic {
                    store: "LocalFileSystem",
                    source: Box::new(e),
                },
            )),
            Err(e) => Err(StoreError::Runtime {
                url: self.url.to_string(),
                reason: format!("flush task failed: {e}"),
            }),
        }
    }

    /// How many calls a bulk call keeps in flight: [`IN_FLIGHT`] to an object store or memory,
    /// [`file_threads`] to a local directory, whose calls each take a thread.
    pub fn in_flight(&self) -> usize {
        match self.local_root {
            Some(_) => file_threads(),
            None => IN_FLIGHT,
        }
    }

    /// The URL the store was opened with.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Reads `key` of the local directory `root` (this store's) on this thread, as
    /// [`AsyncStore::get`] would: the same bytes, counters and errors. For callers that block
    /// anyway ([`Store`]'s reads of a few objects, see [`READ_HERE`]).
    fn read_here(&self, root: &std::path::Path, key: &str) -> Result<Bytes, StoreError> {
        // The key's rules keep the path inside the root: no empty, `.` or `..` segment.
        self.path(key)?;
        let _waiting = InFlight::new(&self.counters);
        let bytes = std::fs::read(root.join(key)).map_err(|e| {
            let source = Box::new(e);
            let e = match source.kind() {
                std::io::ErrorKind::NotFound => object_store::Error::NotFound {
                    path: key.to_string(),
                    source,
                },
                _ => object_store::Error::Generic {
                    store: "LocalFileSystem",
                    source,
                },
            };
            self.backend_error("get", key, e)
        })?;
        self.counters.read(bytes.len());
        Ok(Bytes::from(bytes))
    }

    /// What went through this handle and its clones so far (not through other handles of the
    /// same store).
    pub fn traffic(&self) -> Traffic {
        let c = &self.counters;
        Traffic {
            reads: c.reads.load(Ordering::Relaxed),
            read_bytes: c.read_bytes.load(Ordering::Relaxed),
            writes: c.writes.load(Ordering::Relaxed),
            written_bytes: c.written_bytes.load(Ordering::Relaxed),
            most_in_flight: c.most_in_flight.load(Ordering::Relaxed),
            round_trips: c.round_trips.load(Ordering::Relaxed),
        }
    }

    /// Writes `bytes` at `key`, replacing what was there. Atomic: readers see the old or the new
    /// object, never a mix (a staging file and a rename locally, a single PUT on S3).
    pub async fn put(&self, key: &str, bytes: impl Into<Bytes>) -> Result<(), StoreError> {
        let path = self.path(key)?;
        let bytes = bytes.into();
        let len = bytes.len();
        let _waiting = InFlight::new(&self.counters);
        self.backend
            .put(&path, PutPayload::from_bytes(bytes))
            .await
            .map_err(|e| self.backend_error("put", key, e))?;
        self.counters.wrote(len);
        Ok(())
    }

    /// Writes `bytes` at `key` only if `key` does not exist yet (atomically, by the backend's
    /// create-only put). If it exists with the same content this is a success
    /// ([`PutOutcome::Unchanged`]) so that repeating an interrupted step is harmless — the same
    /// bytes, or, for blobs, the same payload compressed otherwise ([`blob::same_content`]: a
    /// block that a worker of an earlier build wrote, then died before it reported, during a
    /// rolling upgrade); with different content it is [`StoreError::AlreadyExists`] and the
    /// object is left as it was.
    pub async fn put_new(&self, key: &str, bytes: impl Into<Bytes>) -> Result<PutOutcome, StoreError> {
        let path = self.path(key)?;
        let bytes = bytes.into();
        let opts = PutOptions {
            mode: PutMode::Create,
            ..Default::default()
        };
        let created = {
            let _waiting = InFlight::new(&self.counters);
            self.backend
                .put_opts(&path, PutPayload::from_bytes(bytes.clone()), opts)
                .await
        };
        match created {
            Ok(_) => {
                self.counters.wrote(bytes.len());
                Ok(PutOutcome::Created)
            }
            Err(object_store::Error::AlreadyExists { .. } | object_store::Error::Precondition { .. }) => {
                let stored = self.get(key).await?;
                if stored == bytes || crate::blob::same_content(&stored, &bytes) {
                    Ok(PutOutcome::Unchanged)
                } else {
                    Err(StoreError::AlreadyExists {
                        url: self.url.to_string(),
                        key: key.to_string(),
                    })
                }
            }
            Err(e) => Err(self.backend_error("create-only put", key, e)),
        }
    }

    /// Reads the object at `key`; [`StoreError::NotFound`] if there is none.
    pub async fn get(&self, key: &str) -> Result<Bytes, StoreError> {
        let path = self.path(key)?;
        let read = async {
            let _waiting = InFlight::new(&self.counters);
            self.backend.get(&path).await?.bytes().await
        };
        let bytes = read.await.map_err(|e| self.backend_error("get", key, e))?;
        self.counters.read(bytes.len());
        Ok(bytes)
    }

    /// Whether an object exists at `key` (one HEAD request).
    pub async fn exists(&self, key: &str) -> Result<bool, StoreError> {
        let path = self.path(key)?;
        let _waiting = InFlight::new(&self.counters);
        match self.backend.head(&path).await {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(self.backend_error("head", key, e)),
        }
    }

    /// Every key under `prefix`, at any depth, sorted. `prefix` is `""` (the whole store) or ends
    /// with `/` (e.g. `jobs/abc/`): listing is by whole path segments, one prefix listing.
    pub async fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        Ok(self.list_sizes(prefix).await?.into_iter().map(|(key, _)| key).collect())
    }

    /// [`AsyncStore::list`] with each object's size in bytes (what the store holds).
    pub async fn list_sizes(&self, prefix: &str) -> Result<Vec<(String, u64)>, StoreError> {
        let path = self.prefix_path(prefix)?;
        let metas: Vec<_> = self
            .backend
            .list(path.as_ref())
            .try_collect()
            .await
            .map_err(|e| self.backend_error("list", prefix, e))?;
        let mut keys: Vec<(String, u64)> = metas.into_iter().map(|m| (m.location.to_string(), m.size)).collect();
        keys.sort_unstable();
        Ok(keys)
    }

    /// The names of the immediate "sub-directories" of `prefix` (the next path segment of every
    /// key below it), sorted: one delimiter listing. `prefix` is `""` or ends with `/`.
    pub async fn list_children(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        let path = self.prefix_path(prefix)?;
        let listing = self
            .backend
            .list_with_delimiter(path.as_ref())
            .await
            .map_err(|e| self.backend_error("list", prefix, e))?;
        let mut names: Vec<String> = listing
            .common_prefixes
            .iter()
            .filter_map(|p| p.filename().map(str::to_string))
            .collect();
        names.sort_unstable();
        Ok(names)
    }

    /// Deletes the object at `key`; deleting a missing key succeeds (on every backend alike).
    pub async fn delete(&self, key: &str) -> Result<(), StoreError> {
        let path = self.path(key)?;
        let _waiting = InFlight::new(&self.counters);
        match self.backend.delete(&path).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(self.backend_error("delete", key, e)),
        }
    }

    /// Writes every object of `puts`, up to [`AsyncStore::in_flight`] requests at once, in no
    /// particular order (see the module docs). Stops at the first error, which it returns; of the
    /// others, some may be written — each object is written whole or not at all, as by
    /// [`AsyncStore::put`] and [`AsyncStore::put_new`].
    pub async fn put_all(&self, puts: Vec<Put>) -> Result<(), StoreError> {
        futures::stream::iter(puts)
            .map(|put| async move {
                match put.create_only {
                    true => self.put_new(&put.key, put.bytes).await.map(|_| ()),
                    false => self.put(&put.key, put.bytes).await,
                }
            })
            .buffer_unordered(self.in_flight())
            .try_collect()
            .await
    }

    /// Reads the objects at `keys`, up to [`AsyncStore::in_flight`] requests at once, and returns
    /// their contents in the order of `keys`. The first error is returned.
    pub async fn get_all(&self, keys: &[String]) -> Result<Vec<Bytes>, StoreError> {
        futures::stream::iter(keys)
            .map(|key| self.get(key))
            .buffered(self.in_flight())
            .try_collect()
            .await
    }

    /// Reads the objects at `keys` as [`AsyncStore::get_all`] does, but each on its own: one
    /// that is missing or cannot be read is an error in its place, and the others are read.
    pub async fn get_each(&self, keys: &[String]) -> Vec<Result<Bytes, StoreError>> {
        futures::stream::iter(keys)
            .map(|key| self.get(key))
            .buffered(self.in_flight())
            .collect()
            .await
    }

    /// Whether an object exists at each of `keys`, in their order, up to
    /// [`AsyncStore::in_flight`] requests at once.
    pub async fn exist_all(&self, keys: &[String]) -> Result<Vec<bool>, StoreError> {
        futures::stream::iter(keys)
            .map(|key| self.exists(key))
            .buffered(self.in_flight())
            .try_collect()
            .await
    }

    /// Deletes the objects at `keys` (missing ones included, as [`AsyncStore::delete`]), up to
    /// [`AsyncStore::in_flight`] requests at once.
    pub async fn delete_all(&self, keys: &[String]) -> Result<(), StoreError> {
        futures::stream::iter(keys)
            .map(|key| self.delete(key))
            .buffer_unordered(self.in_flight())
            .try_collect()
            .await
    }

    /// Reads and decodes the blob at `key`, which must be of `kind`.
    pub async fn get_blob(&self, key: &str, kind: BlobKind) -> Result<Decoded, StoreError> {
        let bytes = self.get(key).await?;
        self.decode_with(key, &bytes, |b| blob::decode(b, kind))
    }

    /// Decodes `bytes` read from `key` with `decode`, naming the key and store on failure.
    pub fn decode_with<T>(
        &self,
        key: &str,
        bytes: &[u8],
        decode: impl FnOnce(&[u8]) -> Result<T, BlobError>,
    ) -> Result<T, StoreError> {
        decode(bytes).map_err(|source| StoreError::Blob {
            url: self.url.to_string(),
            key: key.to_string(),
            source,
        })
    }

    /// Checks `key` and turns it into a backend path. Keys are `/`-separated segments of ASCII
    /// letters, digits, `.`, `-` and `_`; no segment is empty, `.` or `..`.
    fn path(&self, key: &str) -> Result<Path, StoreError> {
        check_key(key).map_err(|reason| self.invalid_key(key, reason))?;
        Path::parse(key).map_err(|e| self.invalid_key(key, e.to_string()))
    }

    /// Checks a listing prefix: `""` or a valid key followed by `/`.
    fn prefix_path(&self, prefix: &str) -> Result<Option<Path>, StoreError> {
        if prefix.is_empty() {
            return Ok(None);
        }
        match prefix.strip_suffix('/') {
            Some(dir) => self
                .path(dir)
                .map(Some)
                .map_err(|_| self.invalid_key(prefix, "not a valid prefix".into())),
            None => Err(self.invalid_key(prefix, "a listing prefix must be empty or end with `/`".into())),
        }
    }

    fn invalid_key(&self, key: &str, reason: String) -> StoreError {
        StoreError::InvalidKey {
            url: self.url.to_string(),
            key: key.to_string(),
            reason,
        }
    }

    fn backend_error(&self, op: &'static str, key: &str, e: object_store::Error) -> StoreError {
        let (url, key) = (self.url.to_string(), key.to_string());
        match e {
            object_store::Error::NotFound { .. } => StoreError::NotFound { url, key },
            source => StoreError::Backend {
                op,
                url,
                key,
                source: Box::new(source),
            },
        }
    }
}

/// The rules of [`AsyncStore::path`].
fn check_key(key: &str) -> Result<(), String> {
    if key.is_empty() {
        return Err("empty key".into());
    }
    for segment in key.split('/') {
        if segment.is_empty() || segment == "." || segment == ".." {
            return Err(format!("bad path segment `{segment}`"));
        }
        if let Some(c) = segment
            .chars()
            .find(|c| !(c.is_ascii_alphanumeric() || "._-".contains(*c)))
        {
            return Err(format!(
                "character {c:?} is not allowed (use ASCII letters, digits, `.`, `-`, `_`)"
            ));
        }
    }
    Ok(())
}

/// A store with blocking methods, for code that is not async. Cheap to clone; clones share one
/// internal two-thread tokio runtime that drives the backend's I/O.
///
/// The blocking methods must not be called from inside an async runtime (they would stall its
/// worker): there they return [`StoreError::InsideRuntime`]; use [`Store::as_async`] instead.
#[derive(Debug, Clone)]
pub struct Store {
    inner: AsyncStore,
    runtime: Arc<Runtime>,
}

impl Store {
    /// Opens the store that `url` names: a directory path or `file:///PATH`, `s3://BUCKET[/PREFIX]`
    /// (configured from the environment, see [`crate::backend`]), or `memory://`.
    pub fn open(url: &str) -> Result<Store, StoreError> {
        Store::with_runtime(AsyncStore::open(url)?)
    }

    /// Blocking [`AsyncStore::open_existing`].
    pub fn open_existing(url: &str) -> Result<Store, StoreError> {
        Store::with_runtime(AsyncStore::open_existing(url)?)
    }

    fn with_runtime(inner: AsyncStore) -> Result<Store, StoreError> {
        let url = inner.url().to_string();
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            // The runtime runs a local directory's calls: no more threads than they need.
            .max_blocking_threads(file_threads())
            .thread_name("vlf-store-io")
            .enable_all()
            .build()
            .map_err(|e| StoreError::Runtime {
                url: url.to_string(),
                reason: e.to_string(),
            })?;
        Ok(Store {
            inner,
            runtime: Arc::new(Runtime(Some(runtime))),
        })
    }

    /// The async core, for use inside an async runtime.
    pub fn as_async(&self) -> &AsyncStore {
        &self.inner
    }

    /// The URL the store was opened with.
    pub fn url(&self) -> &str {
        self.inner.url()
    }

    /// See [`AsyncStore::traffic`].
    pub fn traffic(&self) -> Traffic {
        self.inner.traffic()
    }

    /// Blocking [`AsyncStore::put`].
    pub fn put(&self, key: &str, bytes: impl Into<Bytes>) -> Result<(), StoreError> {
        self.block_on(self.inner.put(key, bytes))?
    }

    /// Blocking [`AsyncStore::put_new`].
    pub fn put_new(&self, key: &str, bytes: impl Into<Bytes>) -> Result<PutOutcome, StoreError> {
        self.block_on(self.inner.put_new(key, bytes))?
    }

    /// Blocking [`AsyncStore::get`].
    pub fn get(&self, key: &str) -> Result<Bytes, StoreError> {
        if let Some(root) = self.inner.local_root.as_deref() {
            self.inner.counters.round_trips.fetch_add(1, Ordering::Relaxed);
            return self.inner.read_here(root, key);
        }
        self.block_on(self.inner.get(key))?
    }

    /// Blocking [`AsyncStore::put_all`].
    pub fn put_all(&self, puts: Vec<Put>) -> Result<(), StoreError> {
        if puts.is_empty() {
            return Ok(());
        }
        self.block_on(self.inner.put_all(puts))?
    }

    /// Starts [`AsyncStore::put_all`] and returns at once: the caller goes on computing while
    /// the requests wait for their round trips, and [`Writing::wait`]s before it relies on the
    /// objects being there. Dropped without a wait, the writes still complete.
    pub fn put_all_behind(&self, puts: Vec<Put>) -> Result<Writing, StoreError> {
        let inner = self.inner.clone();
        self.behind(async move { inner.put_all(puts).await })
    }

    /// `task` on the store's runtime, as a [`Writing`].
    fn behind(
        &self,
        task: impl Future<Output = Result<(), StoreError>> + Send + 'static,
    ) -> Result<Writing, StoreError> {
        let Some(runtime) = &self.runtime.0 else {
            return Err(StoreError::Runtime {
                url: self.url().to_string(),
                reason: "runtime shut down".into(),
            });
        };
        Ok(Writing {
            task: runtime.spawn(task),
            store: self.clone(),
        })
    }

    /// Blocking [`AsyncStore::get_all`].
    pub fn get_all(&self, keys: &[String]) -> Result<Vec<Bytes>, StoreError> {
        if keys.is_empty() {
            return Ok(Vec::new());
        }
        if let Some(root) = self.few_here(keys) {
            return keys.iter().map(|key| self.inner.read_here(root, key)).collect();
        }
        self.block_on(self.inner.get_all(keys))?
    }

    /// Blocking [`AsyncStore::get_each`].
    pub fn get_each(&self, keys: &[String]) -> Result<Vec<Result<Bytes, StoreError>>, StoreError> {
        if let Some(root) = self.few_here(keys) {
            return Ok(keys.iter().map(|key| self.inner.read_here(root, key)).collect());
        }
        self.block_on(self.inner.get_each(keys))
    }

    /// The local directory to read `keys` from on this thread, one after the other: when they are
    /// at most [`READ_HERE`] objects of one (counted as one round trip, as a bulk read is).
    fn few_here(&self, keys: &[String]) -> Option<&std::path::Path> {
        let root = self.inner.local_root.as_deref().filter(|_| keys.len() <= READ_HERE)?;
        self.inner.counters.round_trips.fetch_add(1, Ordering::Relaxed);
        Some(root)
    }

    /// Blocking [`AsyncStore::exist_all`].
    pub fn exist_all(&self, keys: &[String]) -> Result<Vec<bool>, StoreError> {
        if keys.is_empty() {
            return Ok(Vec::new());
        }
        self.block_on(self.inner.exist_all(keys))?
    }

    /// Blocking [`AsyncStore::delete_all`].
    pub fn delete_all(&self, keys: &[String]) -> Result<(), StoreError> {
        if keys.is_empty() {
            return Ok(());
        }
        self.block_on(self.inner.delete_all(keys))?
    }

    /// Blocking [`AsyncStore::exists`].
    pub fn exists(&self, key: &str) -> Result<bool, StoreError> {
        self.block_on(self.inner.exists(key))?
    }

    /// Blocking [`AsyncStore::list`].
    pub fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        self.block_on(self.inner.list(prefix))?
    }

    /// Blocking [`AsyncStore::flush`].
    pub fn flush(&self) -> Result<(), StoreError> {
        self.block_on(self.inner.flush())?
    }

    /// Blocking [`AsyncStore::list_sizes`].
    pub fn list_sizes(&self, prefix: &str) -> Result<Vec<(String, u64)>, StoreError> {
        self.block_on(self.inner.list_sizes(prefix))?
    }

    /// Blocking [`AsyncStore::list_children`].
    pub fn list_children(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        self.block_on(self.inner.list_children(prefix))?
    }

    /// Blocking [`AsyncStore::delete`].
    pub fn delete(&self, key: &str) -> Result<(), StoreError> {
        self.block_on(self.inner.delete(key))?
    }

    /// Blocking [`AsyncStore::get_blob`].
    pub fn get_blob(&self, key: &str, kind: BlobKind) -> Result<Decoded, StoreError> {
        self.block_on(self.inner.get_blob(key, kind))?
    }

    /// Reads the [`Encoding::Bytes`](crate::Encoding::Bytes) blob of `kind` at `key`.
    pub fn get_bytes_blob(&self, key: &str, kind: BlobKind) -> Result<Vec<u8>, StoreError> {
        let bytes = self.get(key)?;
        self.inner.decode_with(key, &bytes, |b| blob::decode_bytes(b, kind))
    }

    /// Reads the blob of values of `kind` at `key`: its shape and values.
    pub fn get_values(&self, key: &str, kind: BlobKind) -> Result<(Vec<u32>, Vec<f32>), StoreError> {
        let bytes = self.get(key)?;
        self.inner.decode_with(key, &bytes, |b| blob::decode_values(b, kind))
    }

    /// Reads the RGB blob of `kind` at `key`.
    pub fn get_rgb(&self, key: &str, kind: BlobKind) -> Result<Vec<[f32; 3]>, StoreError> {
        let bytes = self.get(key)?;
        self.inner.decode_with(key, &bytes, |b| blob::decode_rgb(b, kind))
    }

    /// Runs `future` to completion on the internal runtime.
    fn block_on<F: Future>(&self, future: F) -> Result<F::Output, StoreError> {
        if tokio::runtime::Handle::try_current().is_ok() {
            return Err(StoreError::InsideRuntime {
                url: self.url().to_string(),
            });
        }
        match &self.runtime.0 {
            Some(runtime) => {
                self.inner.counters.round_trips.fetch_add(1, Ordering::Relaxed);
                Ok(runtime.block_on(future))
            }
            None => Err(StoreError::Runtime {
                url: self.url().to_string(),
                reason: "runtime shut down".into(),
            }),
        }
    }
}

/// Writes started by [`Store::put_all_behind`].
#[must_use = "wait for the writes before relying on them"]
pub struct Writing {
    task: tokio::task::JoinHandle<Result<(), StoreError>>,
    store: Store,
}

/// A bulk write's task that ended without finishing (it panicked or its runtime shut down).
fn write_stopped(url: &str, e: tokio::task::JoinError) -> StoreError {
    StoreError::Runtime {
        url: url.to_string(),
        reason: format!("a bulk write stopped: {e}"),
    }
}

impl Writing {
    /// Waits until every write is done; the first error if one failed.
    pub fn wait(self) -> Result<(), StoreError> {
        Writing::wait_all(vec![self])
    }

    /// The writes of all of `writings`, started on `store`, as one.
    pub fn all(store: &Store, writings: Vec<Writing>) -> Result<Writing, StoreError> {
        let url = store.url().to_string();
        let task = async move {
            let tasks = futures::future::join_all(writings.into_iter().map(|w| w.task)).await;
            for done in tasks {
                done.map_err(|e| write_stopped(&url, e))??;
            }
            Ok(())
        };
        store.behind(task)
    }

    /// Waits, without blocking a thread, until every write is done; the first error if one
    /// failed. For a caller in an async context (a worker that reports once its outputs are in).
    pub async fn finished(self) -> Result<(), StoreError> {
        let url = self.store.url().to_string();
        self.task.await.map_err(|e| write_stopped(&url, e))?
    }

    /// Waits for all of `writings` (started on one store) at once: one round trip, however many
    /// bulk writes overlap in it.
    pub fn wait_all(writings: Vec<Writing>) -> Result<(), StoreError> {
        match writings.first().map(|w| w.store.clone()) {
            Some(store) => store.put_all_waiting(Vec::new(), writings),
            None => Ok(()),
        }
    }
}

impl Store {
    /// [`Store::put_all`] of `puts`, and waits for `writings` (started on this store) in the
    /// same round trip. The puts run on the calling thread, as a blocking call's do; only
    /// writes that overlap some computing need to be started behind it.
    pub fn put_all_waiting(&self, puts: Vec<Put>, writings: Vec<Writing>) -> Result<(), StoreError> {
        if puts.is_empty() && writings.is_empty() {
            return Ok(());
        }
        let tasks = futures::future::join_all(writings.into_iter().map(|w| w.task));
        let (put, waited) = self.block_on(futures::future::join(self.inner.put_all(puts), tasks))?;
        for done in waited {
            done.map_err(|e| write_stopped(self.url(), e))??;
        }
        put
    }
}

/// The internal runtime, shut down without blocking when the last clone of the store goes, so
/// that dropping a [`Store`] is fine anywhere, even inside another runtime.
#[derive(Debug)]
struct Runtime(Option<tokio::runtime::Runtime>);

impl Drop for Runtime {
    fn drop(&mut self) {
        if let Some(runtime) = self.0.take() {
            runtime.shutdown_background();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::check_key;

    #[test]
    fn keys() {
        assert!(check_key("jobs/abc/manifest.blob").is_ok());
        for bad in ["", "/a", "a/", "a//b", "a/../b", "./a", "a b", "a#1", "é", "a\\b"] {
            assert!(check_key(bad).is_err(), "{bad:?} accepted");
        }
    }
}
