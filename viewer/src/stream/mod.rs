//! Streaming a field's radiance to the GPU as the walk needs it.
//!
//! The viewer starts from the field's geometry alone (`StageParts::geometry` in `vlf-store`: no
//! radiance read) and a pool the size of its cache ([`FieldRenderer::streaming`]). A
//! [`Streamer`] thread then, for the latest camera the window gave it ([`Streamer::look`]):
//!
//! 1. lists the parts the view reads ([`LightField::view_needs`], on the CPU: the same look-ups
//!    the shader does), diffuse maps first — they draw every surface, and while a mirror's tiles
//!    are missing the shader traces it through the maps that are resident — then the mirror
//!    tiles; then what the dynamic objects in the view read (`vlf_core::dynamic::needs`: the
//!    surfaces seen from around each object, which its gather and its shadow read);
//! 2. marks them used ([`Residency::touch`]), so the least recently used parts of *other* views
//!    are what the cache evicts;
//! 3. fetches the missing ones from its [`PartSource`] in batches, a place in the pool reserved
//!    for each first, and hands [`Update`]s (evict, upload) to the window, which applies them in
//!    order between frames ([`Streamer::apply`]). A part is resident only once all its values
//!    are uploaded, so a failed or dropped fetch never leaves garbage behind: the batch is
//!    retried with backoff, the error shown on the status line.
//!
//! A newer camera interrupts the work between batches (after the first, so a walk that moves
//! every frame still gets each view's most needed parts): the walk never waits for the network,
//! and most parts of views already left are not fetched. The window only sends cameras and applies
//! updates; it never blocks on the streamer.

pub mod residency;

use crate::direct::DirectParts;
use crate::{FieldRenderer, Gpu, MirrorMode, ViewerError};
use glam::DVec3;
pub use residency::Residency;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, mpsc};
use std::time::Duration;
use vlf_core::directions::DirectionSet;
use vlf_core::dynamic::needs::needs_around;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::parts::PartCatalog;
use vlf_core::render::{Bvh, Camera};

/// Where parts come from: a store, or a coordinator's tile stream. Called from the streamer's
/// thread only.
pub trait PartSource: Send {
    /// The values of `parts` (numbers in the field's [`PartCatalog`]), in that order, in the
    /// field's radiance units; all or an error.
    fn fetch(&mut self, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>, String>;
    /// Bytes read so far (as stored: compressed).
    fn bytes(&self) -> u64;
}

/// A change to the pool, applied by the window in the order sent.
#[derive(Debug)]
pub enum Update {
    Evict(u32),
    Upload {
        part: u32,
        base: usize,
        values: Vec<[f32; 3]>,
    },
}

/// How streaming stands, for the status line.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StreamStats {
    /// Parts resident, and the values they hold.
    pub resident: usize,
    pub resident_values: usize,
    /// Parts being fetched.
    pub in_flight: usize,
    /// Parts the last view planned for needs, and how many of them are not resident yet.
    pub needed: usize,
    pub missing: usize,
    /// The most values a view needed so far: the cache a walk like this one wants.
    pub largest_view_values: usize,
    /// Whether the last view needs more than the cache holds (some of it stays missing), and
    /// how many views so far did.
    pub cache_full: bool,
    pub short_views: u64,
    /// Bytes read from the source.
    pub bytes: u64,
    /// Parts fetched (a part evicted and needed again counts again).
    pub fetched: u64,
    /// Cameras planned for, and the seconds spent finding what they need (CPU ray casting).
    pub views: u64,
    pub planning_seconds: f64,
    /// Failed fetches retried, and the last error (cleared by the next success).
    pub retries: u64,
    pub error: Option<String>,
}

/// How a [`Streamer`] works.
#[derive(Clone, Copy, Debug)]
pub struct StreamConfig {
    /// The pool, in RGB values (12 bytes each).
    pub capacity: usize,
    /// At most this many values per fetch.
    pub batch_values: usize,
    /// At most this many parts per fetch.
    pub batch_parts: usize,
    /// First wait after a failed fetch; doubled per failure up to 32 times this.
    pub backoff: Duration,
    /// With exact direct light: the renderer's direct parts ([`FieldRenderer::direct_parts`]),
    /// each fetched right after its chunk (the source serves them: [`crate::direct::DirectSource`]).
    pub direct: Option<DirectParts>,
}

impl StreamConfig {
    /// A cache of `megabytes` MB (10⁶ bytes) of radiance.
    pub fn with_megabytes(megabytes: f64) -> StreamConfig {
        StreamConfig {
            capacity: (megabytes.max(0.0) * 1e6 / 12.0) as usize,
            batch_values: 1 << 19,
            batch_parts: 256,
            backoff: Duration::from_millis(100),
            direct: None,
        }
    }
}

/// A view to plan for: the camera, how mirrors are drawn, and the bounding spheres (centre and
/// radius, VLF frame) of the dynamic objects in it.
pub type View = (Camera, MirrorMode, Vec<(DVec3, f64)>);

/// Lines of the direction set the objects' needs are sampled along
/// (`vlf_core::dynamic::needs`).
const OBJECT_NEED_DIRECTIONS: usize = 129;

/// What the window asks of the streamer.
struct Request {
    /// The view to plan for; `None` once taken.
    view: Option<View>,
    /// Whether the streamer is planning for a camera it took.
    busy: bool,
    stop: bool,
}

struct Shared {
    request: Mutex<Request>,
    wake: Condvar,
    stats: Mutex<StreamStats>,
    /// Set when a newer view arrives: the work in progress gives way.
    newer: AtomicBool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The streaming thread of one field (see the module docs).
pub struct Streamer {
    shared: Arc<Shared>,
    updates: mpsc::Receiver<Update>,
}

impl Streamer {
    /// Starts streaming parts of `geometry` (a field whose radiance is not read) from `source`
    /// into a pool of `config.capacity` values.
    pub fn start(geometry: Arc<LightField>, source: Box<dyn PartSource>, config: StreamConfig) -> Streamer {
        let shared = Arc::new(Shared {
            request: Mutex::new(Request {
                view: None,
                busy: false,
                stop: false,
            }),
            wake: Condvar::new(),
            stats: Mutex::new(StreamStats::default()),
            newer: AtomicBool::new(false),
        });
        let (sender, updates) = mpsc::channel();
        let worker = Worker {
            catalog: PartCatalog::new(&geometry),
            bvh: None,
            last_view: None,
            object_directions: DirectionSet::new(OBJECT_NEED_DIRECTIONS).expect("a supported direction count"),
            geometry,
            source,
            config,
            shared: shared.clone(),
            sender,
        };
        let spawned = std::thread::Builder::new()
            .name("vlf-stream".into())
            .spawn(move || worker.run());
        if let Err(e) = spawned {
            // Nothing streams; the status line shows the error.
            lock(&shared.stats).error = Some(format!("cannot start the streaming thread: {e}"));
        }
        Streamer { shared, updates }
    }

    /// Asks for what `camera` sees, drawn with `mirrors`; replaces any camera not yet planned
    /// for, and interrupts the fetching for an older one. Never blocks on the network.
    pub fn look(&self, camera: Camera, mirrors: MirrorMode) {
        self.look_around(camera, mirrors, Vec::new());
    }

    /// [`Streamer::look`] for a view with dynamic objects in the bounding spheres `objects`
    /// (centre and radius, VLF frame): what they read is fetched after what the camera sees.
    pub fn look_around(&self, camera: Camera, mirrors: MirrorMode, objects: Vec<(DVec3, f64)>) {
        lock(&self.shared.request).view = Some((camera, mirrors, objects));
        self.shared.newer.store(true, Ordering::Release);
        self.shared.wake.notify_all();
    }

    /// Applies the updates received since the last call to `renderer` (at the next submission);
    /// returns how many.
    pub fn apply(&self, gpu: &Gpu, renderer: &FieldRenderer) -> Result<usize, ViewerError> {
        let mut n = 0;
        while let Ok(update) = self.updates.try_recv() {
            match update {
                Update::Evict(part) => renderer.evict(gpu, part),
                Update::Upload { part, base, values } => renderer.upload(gpu, part, base, &values)?,
            }
            n += 1;
        }
        Ok(n)
    }

    /// Blocks until the streamer has nothing left to do for the last camera (every update sent)
    /// or `timeout` passes; whether it went idle. For scripted runs and tests.
    pub fn wait_idle(&self, timeout: Duration) -> bool {
        let deadline = std::time::Instant::now() + timeout;
        let mut request = lock(&self.shared.request);
        loop {
            let idle = request.view.is_none() && !request.busy && lock(&self.shared.stats).error.is_none();
            if idle || request.stop {
                return idle;
            }
            let now = std::time::Instant::now();
            if now >= deadline {
                return false;
            }
            // Short waits: statistics change without the request's lock held.
            let slice = (deadline - now).min(Duration::from_millis(10));
            request = self
                .shared
                .wake
                .wait_timeout(request, slice)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    pub fn stats(&self) -> StreamStats {
        lock(&self.shared.stats).clone()
    }
}

impl Drop for Streamer {
    /// Tells the thread to stop after the fetch in progress, without waiting for it: a source
    /// stuck on a dead connection must not hold up the window (switching stages, quitting).
    fn drop(&mut self) {
        lock(&self.shared.request).stop = true;
        self.shared.newer.store(true, Ordering::Release);
        self.shared.wake.notify_all();
    }
}

/// The streamer's thread.
struct Worker {
    geometry: Arc<LightField>,
    /// The static scene's BVH, built for the first view with objects.
    bvh: Option<Bvh>,
    /// The last camera planned for and the parts it needs.
    last_view: Option<(Camera, MirrorMode, Vec<u32>)>,
    object_directions: DirectionSet,
    catalog: PartCatalog,
    source: Box<dyn PartSource>,
    config: StreamConfig,
    shared: Arc<Shared>,
    sender: mpsc::Sender<Update>,
}

impl Worker {
    fn run(mut self) {
        let parts = self.config.direct.map_or(self.catalog.len(), |d| d.table_len());
        let sizes = (0..parts as u32).map(|i| self.size(i)).collect();
        let mut residency = Residency::new(sizes, self.config.capacity);
        while let Some((camera, mirrors, objects)) = self.next_view() {
            self.plan(&mut residency, &camera, mirrors, &objects);
            lock(&self.shared.request).busy = false;
            self.shared.wake.notify_all();
        }
    }

    /// Waits for a camera not yet planned for; `None` when told to stop.
    fn next_view(&self) -> Option<View> {
        let mut request = lock(&self.shared.request);
        loop {
            if request.stop {
                return None;
            }
            if let Some(view) = request.view.take() {
                request.busy = true;
                self.shared.newer.store(false, Ordering::Release);
                return Some(view);
            }
            request = self.shared.wake.wait(request).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Makes what `camera` sees resident, as far as the cache allows (see the module docs).
    fn plan(&mut self, residency: &mut Residency, camera: &Camera, mirrors: MirrorMode, objects: &[(DVec3, f64)]) {
        let mode = match mirrors {
            MirrorMode::Rays => SpecularMode::Rays,
            MirrorMode::Trace { depth } => SpecularMode::Trace { depth },
        };
        let started = std::time::Instant::now();
        // Objects moving before a still camera: the camera's own needs are the same.
        let mut needed = match &self.last_view {
            Some((c, m, needed)) if c == camera && *m == mirrors => needed.clone(),
            _ => {
                let needed = self.catalog.needed(&self.geometry.view_needs(camera, 1, mode));
                self.last_view = Some((*camera, mirrors, needed.clone()));
                needed
            }
        };
        if !objects.is_empty() {
            let bvh = self.bvh.get_or_insert_with(|| Bvh::build(&self.geometry.scene));
            let around = needs_around(&self.geometry, bvh, objects, &self.object_directions, mode);
            let seen: std::collections::HashSet<u32> = needed.iter().copied().collect();
            needed.extend(self.catalog.needed(&around).into_iter().filter(|p| !seen.contains(p)));
        }
        if let Some(direct) = self.config.direct {
            // Each chunk's direct part right after it: the two make its surfaces exact.
            needed = (needed.iter())
                .flat_map(|&p| [Some(p), (p < direct.chunks).then(|| direct.of_chunk(p))])
                .flatten()
                .collect();
        }
        let planning = started.elapsed().as_secs_f64();
        let needed_values: usize = needed.iter().map(|&p| self.size(p)).sum();
        residency.touch(&needed);
        let missing: Vec<u32> = needed.iter().copied().filter(|&p| !residency.is_resident(p)).collect();
        self.update_stats(residency, |s| {
            s.views += 1;
            s.largest_view_values = s.largest_view_values.max(needed_values);
            s.planning_seconds += planning;
            s.needed = needed.len();
            s.missing = missing.len();
            s.cache_full = false;
        });
        let mut rest = &missing[..];
        let mut failures = 0u32;
        // Whether a part of this view found no room, and the smallest that did not: a part at
        // least as large finds none either (placing others only takes room), so it is skipped
        // without a look; a smaller one later in the list may still fit.
        let mut full = false;
        let mut too_large = usize::MAX;
        while !rest.is_empty() {
            // A newer camera takes over between batches — but only once this one has had a
            // batch: while the walk moves every frame, each view still gets its most needed
            // parts (planning alone takes longer than a frame).
            if rest.len() < missing.len() && self.interrupted() {
                return;
            }
            // The next batch, each part with a place reserved in the pool; `taken` parts of
            // `rest` are in it or found no room.
            let mut batch = Vec::new();
            let mut values = 0;
            let mut evicted = Vec::new();
            let mut taken = 0;
            for &p in rest {
                let size = self.size(p);
                if !batch.is_empty()
                    && (batch.len() >= self.config.batch_parts || values + size > self.config.batch_values)
                {
                    break;
                }
                taken += 1;
                let placed = match size < too_large {
                    true => residency.place(p, &mut evicted),
                    false => None,
                };
                match placed {
                    Some(_) => {
                        batch.push(p);
                        values += size;
                    }
                    None => {
                        full = true;
                        too_large = too_large.min(size);
                    }
                }
            }
            for &e in &evicted {
                let _ = self.sender.send(Update::Evict(e));
            }
            if batch.is_empty() {
                // Every part left found no room.
                break;
            }
            self.update_stats(residency, |s| s.in_flight = batch.len());
            match self.source.fetch(&batch) {
                Ok(fetched)
                    if fetched.len() == batch.len()
                        && batch.iter().zip(&fetched).all(|(&p, v)| v.len() == self.size(p)) =>
                {
                    for (&part, values) in batch.iter().zip(fetched) {
                        let base = residency.base(part).unwrap_or(0);
                        let _ = self.sender.send(Update::Upload { part, base, values });
                    }
                    failures = 0;
                    let done = batch.len();
                    rest = &rest[taken..];
                    self.update_stats(residency, |s| {
                        s.in_flight = 0;
                        s.fetched += done as u64;
                        s.missing = s.missing.saturating_sub(done);
                        s.error = None;
                        s.cache_full = full;
                    });
                }
                result => {
                    // Nothing of the batch becomes resident; try again after a pause.
                    for &p in &batch {
                        residency.evict(p);
                    }
                    let error = match result {
                        Err(e) => e,
                        Ok(v) => format!(
                            "the source gave {} parts of {} asked for, or parts of the wrong size",
                            v.len(),
                            batch.len()
                        ),
                    };
                    tracing::warn!("fetching {} parts failed (retrying): {error}", batch.len());
                    self.update_stats(residency, |s| {
                        s.in_flight = 0;
                        s.retries += 1;
                        s.error = Some(error);
                    });
                    let pause = self.config.backoff * 2u32.pow(failures.min(5));
                    failures += 1;
                    if self.pause(pause) {
                        return;
                    }
                }
            }
        }
        self.update_stats(residency, |s| {
            s.cache_full = full;
            s.short_views += full as u64;
        });
    }

    /// Values of part `p`: a catalog part's, or a direct part's (its chunk's).
    fn size(&self, p: u32) -> usize {
        match self.config.direct.and_then(|d| d.chunk(p)) {
            Some(chunk) => self.catalog.values(chunk),
            None => self.catalog.values(p),
        }
    }

    /// Whether a newer camera (or a stop) is waiting.
    fn interrupted(&self) -> bool {
        self.shared.newer.load(Ordering::Acquire)
    }

    /// Waits `pause` unless interrupted first; whether it was.
    fn pause(&self, pause: Duration) -> bool {
        let request = lock(&self.shared.request);
        let (request, _) = self
            .shared
            .wake
            .wait_timeout_while(request, pause, |r| r.view.is_none() && !r.stop)
            .unwrap_or_else(|e| e.into_inner());
        request.view.is_some() || request.stop
    }

    fn update_stats(&self, residency: &Residency, change: impl FnOnce(&mut StreamStats)) {
        let mut stats = lock(&self.shared.stats);
        change(&mut stats);
        (stats.resident, stats.resident_values) = residency.resident();
        stats.bytes = self.source.bytes();
        drop(stats);
        self.shared.wake.notify_all();
    }
}

/// A field already in memory as a [`PartSource`]: its parts are copied out (nothing is read).
pub struct FieldParts {
    field: Arc<LightField>,
    catalog: PartCatalog,
}

impl FieldParts {
    pub fn new(field: Arc<LightField>) -> FieldParts {
        FieldParts {
            catalog: PartCatalog::new(&field),
            field,
        }
    }
}

impl PartSource for FieldParts {
    fn fetch(&mut self, parts: &[u32]) -> Result<Vec<Vec<[f32; 3]>>, String> {
        parts
            .iter()
            .map(|&p| {
                if (p as usize) < self.catalog.len() {
                    Ok(self.field.part_values(&self.catalog, p).to_vec())
                } else {
                    Err(format!("the field has no part {p}"))
                }
            })
            .collect()
    }

    fn bytes(&self) -> u64 {
        0
    }
}
