//! `vlf view`: a walkthrough of a field in a window.
//!
//! Every frame draws the field into a linear [`Frame`] at the window's size (the same pipeline
//! as `vlf render --gpu`, one sample per pixel) and tone-maps it onto the window's surface.
//! The radiance streams in ([`crate::stream`]): the window opens on the field's geometry, tells
//! the [`Streamer`] where the camera is whenever it moves, and applies the parts that arrived
//! before each frame. A status line in the top-left corner (and the window's title) gives the
//! frames per second, the size, the mirror mode, the exposure, the eye's speed, the parts
//! resident and in flight and the bytes streamed.
//! Keys:
//!
//! | key | does |
//! |---|---|
//! | W A S D | walk forward, left, back, right (level, whatever the pitch) |
//! | Q / E | down / up |
//! | drag (any button) | look around |
//! | wheel | walking speed ×1.25 per notch |
//! | M | cycle the mirror mode: from the rays, traced (`--depth` deep, else 8), without reflections |
//! | + / − | exposure ±½ stop |
//! | P | save a screenshot (the linear frame, tone-mapped as on screen, or linear for `.pfm`) |
//! | [ / ] / L | the previous / next / latest snapshot (watch a running job converge) |
//! | Tab | select the next dynamic object |
//! | T F G H | move the selected object forward, left, back, right (level, as the eye looks) |
//! | R / Y | move it down / up |
//! | Z / X | turn it left / right about the vertical through its centre |
//! | Esc | quit |
//!
//! Dynamic objects ([`crate::placement`]) are drawn lit by the field's gather and casting
//! shadows, as `vlf render --gpu --object` draws them; a move that would take one into a wall
//! is refused. The streamer fetches what they read (the surfaces seen from around them) after
//! what the camera sees; until it arrives, their gather averages the light already resident.
//!
//! Switching snapshots opens the other stage on a thread of its own (through the caller's
//! [`Loader`]); the walk goes on meanwhile, and streaming starts again from the new source.

use crate::field::MirrorMode;
use crate::frame::Frame;
use crate::overlay::Overlay;
use crate::placement::{ObjectMove, Placement};
use crate::stream::{PartSource, StreamConfig, StreamStats, Streamer};
use crate::tonemap::Tonemap;
use crate::walk::{Move, Walk};
use crate::{FieldRenderer, Gpu, ViewerError};
use glam::DVec3;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, mpsc};
use std::time::Instant;
use vlf_core::dynamic::gather::Gatherer;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::render::Bvh;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

/// How deep M traces mirrors when the walk did not start traced with reflections (the command
/// line's default `--depth`).
const DEFAULT_TRACE_DEPTH: u32 = 8;

/// How long a scripted run waits for a frame's parts before it gives up waiting.
const SETTLE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(120);

/// A step between the snapshots of a job.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Switch {
    Previous,
    Next,
    Latest,
}

/// Opens the stage one [`Switch`] away from the one shown: `Ok(None)` when there is none (the
/// first snapshot has no previous one), else where its parts come from and a title for the
/// window. The stage must be of the same job (the same geometry). Called on a thread of its
/// own, one call at a time.
pub type Loader = Box<dyn FnMut(Switch) -> Loaded + Send>;

/// What a [`Loader`] gives: another stage's parts and its title, none, or why it failed.
pub type Loaded = Result<Option<(Box<dyn PartSource>, String)>, String>;

/// How `vlf view` starts, and when it stops by itself.
pub struct ViewOptions {
    pub title: String,
    pub size: (u32, u32),
    pub walk: Walk,
    pub exposure: f64,
    pub mirrors: MirrorMode,
    /// Whether presenting waits for the display's refresh.
    pub vsync: bool,
    /// Quit after this many frames (scripted runs, benchmarks).
    pub frames: Option<u64>,
    /// Where `P` writes screenshots: `DIR/vlf-N.png`.
    pub screenshot_dir: PathBuf,
    /// A screenshot of the last frame, written when quitting.
    pub screenshot_at_exit: Option<PathBuf>,
    /// Where other snapshots come from; without one, [ ] L do nothing.
    pub loader: Option<Loader>,
    /// The cache the radiance streams into.
    pub stream: StreamConfig,
    /// Draw each frame only once what it needs is resident (or the cache is full): scripted
    /// runs and screenshots then show the complete view. Given up (with a warning) after a
    /// frame waited two minutes.
    pub settle: bool,
    /// Dynamic objects to draw and move.
    pub objects: Option<ViewObjects>,
    /// Exact direct light from these emitter points ([`crate::direct`]): the sources (the first
    /// and the loader's) must then serve the direct parts too ([`crate::direct::DirectSource`]).
    /// The objects' shadows take the same points.
    pub exact_direct: Option<vlf_core::direct::Emitters>,
    /// Draw exact direct light on a software adapter (Mesa's lavapipe) too. Its shadow rays
    /// per pixel take a CPU seconds per frame at a window's size, so where this is off a
    /// software adapter draws the field's direct light and only a real GPU the exact one.
    pub exact_on_software: bool,
}

/// The dynamic objects of a view and how they are shaded.
pub struct ViewObjects {
    pub placement: Placement,
    /// Lines of the gather's direction set (one of `DirectionSet::SUPPORTED`).
    pub directions: usize,
    /// Cells of each object's shadow cone (0: no shadows).
    pub shadow_samples: u32,
}

/// What a viewing session did.
#[derive(Clone, Debug, Default)]
pub struct ViewStats {
    pub frames: u64,
    pub seconds: f64,
    /// Seconds from the start to the first frame on screen.
    pub first_frame_seconds: Option<f64>,
    pub adapter: String,
    pub screenshots: Vec<PathBuf>,
    /// How streaming stood at the end.
    pub stream: StreamStats,
    /// Seconds spent waiting for parts (`settle`) after the first frame: the frame rate
    /// without them, and without the first frame, is the drawing's own.
    pub settle_seconds: f64,
    /// Object moves refused (into a wall, out of the scene).
    pub refused_moves: u64,
    /// Whether direct light was drawn exact (else the field's).
    pub exact_direct: bool,
}

/// Opens the window on `geometry` (a field whose radiance is not read: it streams from
/// `source`) and runs until it is closed, Esc is pressed or `options.frames` are drawn.
pub fn view(
    geometry: Arc<LightField>,
    source: Box<dyn PartSource>,
    mut options: ViewOptions,
) -> Result<ViewStats, ViewerError> {
    let event_loop = EventLoop::new().map_err(|e| {
        ViewerError::NoDisplay(format!(
            "{e}; set DISPLAY (or WAYLAND_DISPLAY), or run under xvfb-run, or render without a window: vlf render --gpu"
        ))
    })?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let (sender, loaded) = std::sync::mpsc::channel();
    let bvh = Bvh::build(&geometry.scene);
    let mut app = App {
        bvh,
        loader: options.loader.take().map(|l| Arc::new(Mutex::new(l))),
        loading: false,
        trace_depth: trace_depth(options.mirrors),
        sender,
        loaded,
        geometry,
        source: Some(source),
        options,
        started: Instant::now(),
        state: None,
        error: None,
        stats: ViewStats::default(),
    };
    event_loop
        .run_app(&mut app)
        .map_err(|e| ViewerError::NoDisplay(e.to_string()))?;
    match app.error {
        Some(e) => Err(e),
        None => Ok(app.stats),
    }
}

struct App {
    /// The static scene's BVH (where objects may go, the gather's layout).
    bvh: Bvh,
    loader: Option<Arc<Mutex<Loader>>>,
    /// Whether a snapshot is being loaded.
    loading: bool,
    /// How deep M traces mirrors ([`trace_depth`]).
    trace_depth: u32,
    sender: mpsc::Sender<Loaded>,
    loaded: mpsc::Receiver<Loaded>,
    /// The field's geometry (no radiance), shared with the streamer.
    geometry: Arc<LightField>,
    /// The source to stream from once the window is open.
    source: Option<Box<dyn PartSource>>,
    options: ViewOptions,
    started: Instant,
    state: Option<State>,
    error: Option<ViewerError>,
    stats: ViewStats,
}

/// What exists once the window does.
struct State {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    gpu: Gpu,
    renderer: FieldRenderer,
    streamer: Streamer,
    /// The camera, mirror mode and objects' spheres the streamer last planned for.
    planned: Option<crate::stream::View>,
    tonemap: Tonemap,
    status: Overlay,
    frame: Frame,
    last: Instant,
    /// Smoothed frames per second, and when the title was last updated.
    fps: f64,
    titled: Instant,
    /// Where the cursor was while a button is held.
    drag: Option<(f64, f64)>,
    buttons: u32,
}

impl App {
    fn fail(&mut self, event_loop: &ActiveEventLoop, e: ViewerError) {
        self.error.get_or_insert(e);
        event_loop.exit();
    }

    fn start(&mut self, event_loop: &ActiveEventLoop) -> Result<State, ViewerError> {
        let (w, h) = self.options.size;
        let window = Arc::new(
            event_loop
                .create_window(
                    Window::default_attributes()
                        .with_title(&self.options.title)
                        .with_inner_size(PhysicalSize::new(w, h)),
                )
                .map_err(|e| ViewerError::NoDisplay(e.to_string()))?,
        );
        // The primary backends first, OpenGL only without them (as `Gpu::new`).
        let attempt = |backends: wgpu::Backends| -> Result<(wgpu::Surface<'static>, Gpu), ViewerError> {
            let mut desc =
                wgpu::InstanceDescriptor::new_with_display_handle_from_env(Box::new(event_loop.owned_display_handle()));
            desc.backends &= backends;
            let instance = wgpu::Instance::new(desc);
            let surface = instance
                .create_surface(window.clone())
                .map_err(|e| ViewerError::Gpu(format!("cannot draw into the window: {e}")))?;
            let gpu = Gpu::from_instance(&instance, Some(&surface))?;
            Ok((surface, gpu))
        };
        let (surface, gpu) = attempt(wgpu::Backends::PRIMARY)
            .or_else(|primary| attempt(wgpu::Backends::SECONDARY).map_err(|_| primary))?;
        let (width, height) = surface_size(window.inner_size(), &gpu.limits);
        let caps = surface.get_capabilities(&gpu.adapter);
        let format = caps
            .formats
            .iter()
            .copied()
            .find(|f| f.is_srgb())
            .or(caps.formats.first().copied())
            .ok_or_else(|| ViewerError::Gpu(format!("{} cannot present to this window", gpu.describe())))?;
        let mut config = surface
            .get_default_config(&gpu.adapter, width, height)
            .ok_or_else(|| ViewerError::Gpu(format!("{} cannot present to this window", gpu.describe())))?;
        config.format = format;
        config.present_mode = if self.options.vsync {
            wgpu::PresentMode::AutoVsync
        } else {
            wgpu::PresentMode::AutoNoVsync
        };
        gpu.checked(|| surface.configure(&gpu.device, &config))?;
        let source = self
            .source
            .take()
            .ok_or_else(|| ViewerError::Unsupported("the window opened twice".into()))?;
        let (renderer, streamer) = self.stream_from(&gpu, source)?;
        let frame = Frame::new(&gpu, config.width, config.height)?;
        let tonemap = Tonemap::new(&gpu, format, &frame);
        let status = Overlay::new(&gpu, format);
        self.stats.adapter = gpu.describe();
        self.stats.exact_direct = renderer.direct_parts().is_some();
        tracing::info!(adapter = %gpu.describe(), ?format, "viewer window");
        Ok(State {
            window,
            surface,
            config,
            gpu,
            renderer,
            streamer,
            planned: None,
            tonemap,
            status,
            frame,
            last: Instant::now(),
            fps: 0.0,
            titled: Instant::now(),
            drag: None,
            buttons: 0,
        })
    }

    /// A renderer with an empty pool of the cache's size, and a streamer filling it from `source`.
    /// A cache whose pool, or whose objects' shadow pool, is larger than one storage binding of
    /// this adapter is cut down to fit, with a warning.
    fn stream_from(&self, gpu: &Gpu, source: Box<dyn PartSource>) -> Result<(FieldRenderer, Streamer), ViewerError> {
        let mut config = self.options.stream;
        let software = gpu.info.device_type == wgpu::DeviceType::Cpu;
        let exact = match &self.options.exact_direct {
            Some(_) if software && !self.options.exact_on_software => {
                tracing::warn!(
                    "{} is a software adapter: direct light from the field (--direct exact draws it exact, at \
                     seconds a frame)",
                    gpu.describe()
                );
                None
            }
            exact => exact.as_ref(),
        };
        // Bytes a value of the cache takes in the largest buffer bound: 12 in the radiance pool,
        // or 24 in the objects' shadow pool with exact direct light (the gather's shadow and the
        // camera's per value, `FieldRenderer::streaming_with`).
        let value_bytes = if self.options.objects.is_some() && exact.is_some() {
            24
        } else {
            12
        };
        let limit = gpu
            .limits
            .max_storage_buffer_binding_size
            .min(gpu.limits.max_buffer_size)
            / value_bytes;
        if config.capacity as u64 > limit {
            tracing::warn!(
                "{} binds at most {:.1} MB at once: the cache is cut to {:.1} MB",
                gpu.describe(),
                (limit * value_bytes) as f64 * 1e-6,
                limit as f64 * 12e-6
            );
            config.capacity = limit as usize;
        }
        let renderer = match &self.options.objects {
            None => FieldRenderer::streaming_with(gpu, &self.geometry, config.capacity, None, exact)?,
            Some(o) => {
                let mode = match self.options.mirrors {
                    MirrorMode::Rays => SpecularMode::Rays,
                    MirrorMode::Trace { depth } => SpecularMode::Trace { depth },
                };
                let gatherer =
                    Gatherer::with_directions(&self.geometry, &self.bvh, o.placement.placed(), mode, o.directions)
                        .map_err(|e| ViewerError::Unsupported(e.to_string()))?
                        .with_shadow_samples(o.shadow_samples);
                // The objects' shadows take exact direct light's points.
                let gatherer = match exact {
                    Some(e) => gatherer.with_emitters(e.clone()),
                    None => gatherer,
                };
                // The GPU computes the shadows per texel and the objects' light: nothing for the
                // CPU to compute here. Last, since the builders before it compute what the
                // settings ask for (`with_emitters` would, after it).
                let gatherer = gatherer.with_gpu_lighting(true, true);
                let mut renderer =
                    FieldRenderer::streaming_with(gpu, &self.geometry, config.capacity, Some(&gatherer), exact)?;
                // Shadows per texel: a walk pays for them when objects move, not every frame.
                renderer.shadows_per_texel(gpu, &self.geometry)?;
                renderer
            }
        };
        config.direct = renderer.direct_parts();
        let streamer = Streamer::start(self.geometry.clone(), source, config);
        Ok((renderer, streamer))
    }

    /// Draws one frame; `Ok(false)` when the surface had none to give (try again next time).
    fn redraw(&mut self) -> Result<bool, ViewerError> {
        self.take_loaded();
        let Some(s) = self.state.as_mut() else {
            return Ok(false);
        };
        let now = Instant::now();
        let dt = now.duration_since(s.last).as_secs_f64().min(0.25);
        s.last = now;
        self.options.walk.advance(dt);
        let walk = &self.options.walk;
        let camera = walk
            .camera(s.config.width, s.config.height)
            .map_err(|e| ViewerError::Unsupported(e.to_string()))?;
        let mut spheres = Vec::new();
        if let Some(o) = &mut self.options.objects {
            if o.placement
                .advance(dt, walk.speed, walk.forward(), &self.geometry, &self.bvh)
            {
                s.renderer.move_objects(&s.gpu, o.placement.placed())?;
            }
            spheres = o.placement.spheres();
        }
        // The streamer plans for the camera when it moved, or when an object moved far from
        // where it was planned for; what arrived meanwhile is uploaded.
        let replan = match &s.planned {
            Some((c, m, planned)) => *c != camera || *m != self.options.mirrors || moved_far(planned, &spheres),
            None => true,
        };
        if replan {
            s.streamer.look_around(camera, self.options.mirrors, spheres.clone());
            s.planned = Some((camera, self.options.mirrors, spheres));
        }
        let settling = Instant::now();
        if self.options.settle && !s.streamer.wait_idle(SETTLE_TIMEOUT) {
            tracing::warn!(
                "the view's parts did not arrive in {SETTLE_TIMEOUT:?} ({:?}); drawing on without waiting",
                s.streamer.stats().error
            );
            self.options.settle = false;
        }
        if self.stats.frames > 0 {
            self.stats.settle_seconds += settling.elapsed().as_secs_f64();
        }
        s.streamer.apply(&s.gpu, &s.renderer)?;
        let texture = match s.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t) | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => return Ok(false),
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                s.gpu.checked(|| s.surface.configure(&s.gpu.device, &s.config))?;
                return Ok(false);
            }
            wgpu::CurrentSurfaceTexture::Validation => {
                return Err(ViewerError::Gpu("the window's surface refused a frame".into()));
            }
        };
        let viewpoint = s.renderer.viewpoint(&camera, (0.0, 0.0), self.options.mirrors);
        let target = texture.texture.create_view(&Default::default());
        s.gpu.checked(|| {
            let mut encoder = s.gpu.device.create_command_encoder(&Default::default());
            s.renderer.draw(
                &s.gpu,
                &mut encoder,
                &viewpoint,
                &s.frame.color_view,
                &s.frame.depth_view,
            );
            s.tonemap.draw(&s.gpu, &mut encoder, &target, self.options.exposure);
            // The status line over the tone-mapped frame (screenshots read the frame, without it).
            let scale = status_scale(s.config.width);
            s.status.draw(
                &s.gpu,
                &mut encoder,
                &target,
                (s.config.width, s.config.height),
                (4.0 * scale, 4.0 * scale),
                scale,
            );
            s.gpu.queue.submit([encoder.finish()]);
        })?;
        s.gpu.queue.present(texture);
        self.stats.frames += 1;
        self.stats
            .first_frame_seconds
            .get_or_insert(self.started.elapsed().as_secs_f64());
        if dt > 0.0 {
            s.fps = if s.fps == 0.0 { 1.0 / dt } else { 0.9 * s.fps + 0.1 / dt };
        }
        if s.titled.elapsed().as_secs_f64() > 0.5 {
            s.titled = Instant::now();
            let mode = match self.options.mirrors {
                MirrorMode::Rays => "mirrors from the rays".to_string(),
                MirrorMode::Trace { depth: 0 } => "mirrors without reflections".to_string(),
                MirrorMode::Trace { depth } => format!("mirrors traced {depth} deep"),
            };
            let selected = match self.options.objects.as_ref().and_then(|o| o.placement.selected()) {
                Some((k, name)) => format!(" | object {} '{name}'", k + 1),
                None => String::new(),
            };
            let line = format!(
                "{:.1} fps | {}x{} | {mode} | exposure {:+.1} | speed {:.3}{selected} | {}",
                s.fps,
                s.config.width,
                s.config.height,
                self.options.exposure,
                self.options.walk.speed,
                stream_status(&s.streamer.stats(), self.loading)
            );
            s.status.set_text(&s.gpu, &line);
            s.window.set_title(&format!("{} | {line}", self.options.title));
        }
        Ok(true)
    }

    /// Writes the frame on screen to `path`: tone-mapped for PNG, linear for PFM/EXR.
    fn screenshot(&mut self, path: PathBuf) -> Result<(), ViewerError> {
        let Some(s) = self.state.as_ref() else {
            return Ok(());
        };
        let image = s.frame.image(&s.gpu)?;
        image
            .save(&path, self.options.exposure)
            .map_err(|e| ViewerError::Io(format!("cannot write {}: {e}", path.display())))?;
        tracing::info!(path = %path.display(), "screenshot");
        self.stats.screenshots.push(path);
        Ok(())
    }

    /// Starts loading another snapshot, unless one is loading already.
    fn switch(&mut self, switch: Switch) {
        let Some(loader) = self.loader.clone() else {
            tracing::info!("this view has no other snapshots");
            return;
        };
        if self.loading {
            return;
        }
        self.loading = true;
        let sender = self.sender.clone();
        std::thread::spawn(move || {
            let result = match loader.lock() {
                Ok(mut load) => load(switch),
                Err(_) => Err("the snapshot loader failed earlier".to_string()),
            };
            let _ = sender.send(result);
        });
    }

    /// Takes in a snapshot loaded since the last frame. Nothing that goes wrong here ends the
    /// walk: it goes on on the stage it is on.
    fn take_loaded(&mut self) {
        let Ok(loaded) = self.loaded.try_recv() else {
            return;
        };
        self.loading = false;
        match loaded {
            Ok(Some((source, title))) => {
                let Some(s) = self.state.as_ref() else {
                    return;
                };
                // A stage that cannot be drawn (its pool does not fit, the device refused a
                // buffer) leaves the walk on the stage it is on: the error is logged, not fatal.
                match self.stream_from(&s.gpu, source) {
                    Ok((renderer, streamer)) => {
                        if let Some(s) = self.state.as_mut() {
                            (s.renderer, s.streamer, s.planned) = (renderer, streamer, None);
                        }
                        tracing::info!(%title, "stage switched");
                        self.options.title = title;
                    }
                    Err(e) => tracing::error!("cannot switch to {title}: {e}; staying on the stage shown"),
                }
            }
            Ok(None) => tracing::info!("no snapshot that way"),
            Err(e) => tracing::error!("cannot switch snapshot: {e}"),
        }
    }

    fn key(&mut self, event_loop: &ActiveEventLoop, code: KeyCode, pressed: bool) {
        let walk = &mut self.options.walk;
        let movement = match code {
            KeyCode::KeyW | KeyCode::ArrowUp => Some(Move::Forward),
            KeyCode::KeyS | KeyCode::ArrowDown => Some(Move::Back),
            KeyCode::KeyA | KeyCode::ArrowLeft => Some(Move::Left),
            KeyCode::KeyD | KeyCode::ArrowRight => Some(Move::Right),
            KeyCode::KeyQ | KeyCode::PageDown => Some(Move::Down),
            KeyCode::KeyE | KeyCode::PageUp => Some(Move::Up),
            _ => None,
        };
        if let Some(m) = movement {
            walk.set(m, pressed);
            return;
        }
        let object_move = match code {
            KeyCode::KeyT => Some(ObjectMove::Forward),
            KeyCode::KeyG => Some(ObjectMove::Back),
            KeyCode::KeyF => Some(ObjectMove::Left),
            KeyCode::KeyH => Some(ObjectMove::Right),
            KeyCode::KeyR => Some(ObjectMove::Down),
            KeyCode::KeyY => Some(ObjectMove::Up),
            KeyCode::KeyZ => Some(ObjectMove::TurnLeft),
            KeyCode::KeyX => Some(ObjectMove::TurnRight),
            _ => None,
        };
        if let Some(m) = object_move {
            if let Some(o) = &mut self.options.objects {
                o.placement.set(m, pressed);
            }
            return;
        }
        if !pressed {
            return;
        }
        match code {
            KeyCode::Escape => event_loop.exit(),
            KeyCode::KeyM => self.options.mirrors = next_mirror_mode(self.options.mirrors, self.trace_depth),
            KeyCode::Equal | KeyCode::NumpadAdd => self.options.exposure += 0.5,
            KeyCode::Minus | KeyCode::NumpadSubtract => self.options.exposure -= 0.5,
            KeyCode::BracketLeft => self.switch(Switch::Previous),
            KeyCode::BracketRight => self.switch(Switch::Next),
            KeyCode::KeyL => self.switch(Switch::Latest),
            KeyCode::Tab => {
                if let Some(o) = &mut self.options.objects {
                    o.placement.select_next();
                }
            }
            KeyCode::KeyP | KeyCode::F12 => {
                let n = self.stats.screenshots.len() + 1;
                let path = self.options.screenshot_dir.join(format!("vlf-{n}.png"));
                if let Err(e) = self.screenshot(path) {
                    tracing::error!("{e}");
                }
            }
            _ => {}
        }
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.state.is_some() {
            return;
        }
        match self.start(event_loop) {
            Ok(state) => self.state = Some(state),
            Err(e) => self.fail(event_loop, e),
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                let Some(s) = self.state.as_mut() else { return };
                if size.width == 0 || size.height == 0 {
                    return;
                }
                // No larger than the device's textures; a size the surface refuses is an error
                // of the viewer's (checked), not wgpu's panic.
                let (width, height) = surface_size(size, &s.gpu.limits);
                s.config.width = width;
                s.config.height = height;
                if let Err(e) = s.gpu.checked(|| s.surface.configure(&s.gpu.device, &s.config)) {
                    return self.fail(event_loop, e);
                }
                match Frame::new(&s.gpu, width, height) {
                    Ok(frame) => {
                        s.tonemap.set_frame(&s.gpu, &frame);
                        s.frame = frame;
                    }
                    Err(e) => self.fail(event_loop, e),
                }
            }
            WindowEvent::KeyboardInput { event, .. } => {
                if let PhysicalKey::Code(code) = event.physical_key {
                    self.key(event_loop, code, event.state == ElementState::Pressed);
                }
            }
            WindowEvent::MouseInput { state, .. } => {
                let Some(s) = self.state.as_mut() else { return };
                match state {
                    ElementState::Pressed => s.buttons += 1,
                    ElementState::Released => s.buttons = s.buttons.saturating_sub(1),
                }
                if s.buttons == 0 {
                    s.drag = None;
                }
            }
            WindowEvent::CursorMoved { position, .. } => {
                let Some(s) = self.state.as_mut() else { return };
                if s.buttons > 0 {
                    if let Some((x, y)) = s.drag {
                        self.options.walk.look(position.x - x, position.y - y);
                    }
                    s.drag = Some((position.x, position.y));
                }
            }
            WindowEvent::MouseWheel { delta, .. } => {
                let notches = match delta {
                    MouseScrollDelta::LineDelta(_, y) => y as f64,
                    MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
                };
                self.options.walk.wheel(notches);
            }
            WindowEvent::RedrawRequested => {
                match self.redraw() {
                    Ok(_) => {}
                    Err(e) => return self.fail(event_loop, e),
                }
                if self.options.frames.is_some_and(|n| self.stats.frames >= n) {
                    if let Some(path) = self.options.screenshot_at_exit.clone()
                        && let Err(e) = self.screenshot(path)
                    {
                        return self.fail(event_loop, e);
                    }
                    event_loop.exit();
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, _: &ActiveEventLoop) {
        if let Some(s) = &self.state {
            s.window.request_redraw();
        }
    }

    fn exiting(&mut self, _: &ActiveEventLoop) {
        self.stats.seconds = self.started.elapsed().as_secs_f64();
        if let Some(s) = &self.state {
            self.stats.stream = s.streamer.stats();
        }
        if let Some(o) = &self.options.objects {
            self.stats.refused_moves = o.placement.refused;
        }
    }
}

/// The mirror mode after `mode` as M cycles them: from the rays, traced `depth` deep, without
/// reflections, from the rays again. `depth` is the walk's configured depth (`--depth`), so a
/// round of M comes back to what the command line asked for.
fn next_mirror_mode(mode: MirrorMode, depth: u32) -> MirrorMode {
    match mode {
        MirrorMode::Rays => MirrorMode::Trace { depth },
        MirrorMode::Trace { depth: 0 } => MirrorMode::Rays,
        MirrorMode::Trace { .. } => MirrorMode::Trace { depth: 0 },
    }
}

/// How deep M traces mirrors: the configured depth where the walk starts traced with
/// reflections, else [`DEFAULT_TRACE_DEPTH`].
fn trace_depth(mode: MirrorMode) -> u32 {
    match mode {
        MirrorMode::Trace { depth } if depth > 0 => depth,
        _ => DEFAULT_TRACE_DEPTH,
    }
}

/// The window's size clamped to what the device's textures take (at least 1 × 1): the
/// surface and the frame are made at this size.
fn surface_size(size: PhysicalSize<u32>, limits: &wgpu::Limits) -> (u32, u32) {
    let max = limits.max_texture_dimension_2d.max(1);
    (size.width.clamp(1, max), size.height.clamp(1, max))
}

/// Screen pixels per pixel of the status line's 8 × 8 font: 1, and 2 on windows wide enough
/// for the line (160 characters) at that size.
fn status_scale(width: u32) -> f32 {
    if width >= 2 * 8 * crate::overlay::MAX_CHARS as u32 {
        2.0
    } else {
        1.0
    }
}

/// Whether an object moved from where the streamer planned for it by more than a quarter of
/// its radius (or objects came or went): what it reads changes little over shorter moves, and
/// planning again every frame of a slow move would only keep the streaming thread busy.
fn moved_far(planned: &[(DVec3, f64)], now: &[(DVec3, f64)]) -> bool {
    planned.len() != now.len()
        || planned
            .iter()
            .zip(now)
            .any(|(a, b)| a.0.distance(b.0) > 0.25 * a.1.min(b.1))
}

/// The streaming part of the status line: parts resident (and their size) and in flight, bytes
/// streamed, and what is wrong if anything is.
fn stream_status(stats: &StreamStats, loading: bool) -> String {
    let mut line = format!(
        "parts {} ({:.1} MB) | in flight {} | streamed {:.1} MB",
        stats.resident,
        stats.resident_values as f64 * 12e-6,
        stats.in_flight,
        stats.bytes as f64 * 1e-6
    );
    if stats.missing > 0 && stats.cache_full {
        line.push_str(&format!(" | cache full, {} missing", stats.missing));
    }
    if stats.error.is_some() {
        line.push_str(&format!(" | retrying ({})", stats.retries));
    }
    if loading {
        line.push_str(" | switching");
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    /// M goes round the three modes and comes back to the configured depth, whatever it is.
    #[test]
    fn m_cycles_the_mirror_modes_keeping_the_configured_depth() {
        for (start, depth) in [
            (MirrorMode::Trace { depth: 3 }, 3),
            (MirrorMode::Trace { depth: 12 }, 12),
            (MirrorMode::Rays, DEFAULT_TRACE_DEPTH),
            (MirrorMode::Trace { depth: 0 }, DEFAULT_TRACE_DEPTH),
        ] {
            let d = trace_depth(start);
            assert_eq!(d, depth, "{start:?}");
            let mut mode = start;
            let mut seen = Vec::new();
            for _ in 0..3 {
                mode = next_mirror_mode(mode, d);
                seen.push(mode);
            }
            assert_eq!(mode, start, "three presses come back to {start:?}: {seen:?}");
            assert!(seen.contains(&MirrorMode::Trace { depth }), "{seen:?}");
            assert!(seen.contains(&MirrorMode::Rays) && seen.contains(&MirrorMode::Trace { depth: 0 }));
        }
    }

    #[test]
    fn the_surface_is_no_larger_than_the_devices_textures() {
        let limits = wgpu::Limits {
            max_texture_dimension_2d: 4096,
            ..wgpu::Limits::downlevel_defaults()
        };
        assert_eq!(surface_size(PhysicalSize::new(1280, 720), &limits), (1280, 720));
        assert_eq!(surface_size(PhysicalSize::new(9000, 720), &limits), (4096, 720));
        assert_eq!(surface_size(PhysicalSize::new(0, 5000), &limits), (1, 4096));
    }
}
