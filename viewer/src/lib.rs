//! GPU drawing of a virtual light field with wgpu.
//!
//! Once propagated, a field is drawn without any light transport: every visible
//! point of a diffuse surface (or emitter) reads its outgoing radiance from the
//! surface's radiance map. On the GPU that is a rasteriser pass with a depth
//! buffer for visibility — the CPU renderer casts one ray per sample for the
//! same answer — and a fragment shader doing the bilinear look-up.
//!
//! * [`gpu`]: adapter and device, software ones included (Mesa's lavapipe);
//!   a clear [`ViewerError::NoAdapter`] where there is none.
//! * [`field`]: a field's geometry and radiance maps as GPU buffers, and the
//!   pipeline that draws them.
//! * [`gather`]: the dynamic objects' gather as a compute shader, the twin of
//!   `vlf_core::dynamic::gather`.
//! * [`direct`]: exact direct light, per fragment, as `vlf_core::direct` computes it.
//! * [`headless`]: `vlf render --gpu`: the same sample positions and box filter
//!   as the CPU renderer, into an [`vlf_core::render::Image`].
//!
//! * [`rays`]: mirrors "from the rays": the field's directional maps and the
//!   tables that find a ray again, for the shader.
//! * [`stream`]: the parts of a field a view needs, fetched on a thread into a
//!   bounded pool on the GPU (LRU), for `vlf view`.
//!
//! Mirrors are drawn both ways of the CPU renderer: from the field's rays, or
//! ray traced through the scene's BVH.

pub mod direct;
pub mod field;
pub mod frame;
pub mod gather;
pub mod gpu;
pub mod headless;
mod objects;
pub mod overlay;
pub mod pass;
pub mod placement;
pub mod rays;
mod shadows;
pub mod stream;
pub mod tonemap;
pub mod walk;
pub mod window;

pub use field::{FieldRenderer, MirrorMode, Viewpoint};
pub use gather::GpuGather;
pub use gpu::Gpu;
pub use headless::render;
pub use placement::{ObjectMove, Placement};
pub use stream::{PartSource, StreamConfig, StreamStats, Streamer};
pub use walk::Walk;
pub use window::{Loaded, Loader, Switch, ViewObjects, ViewOptions, ViewStats, view};

/// What can go wrong drawing on the GPU.
#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    /// No adapter at all: no GPU driver and no software one.
    #[error(
        "no GPU adapter found ({0}); install a Vulkan driver — on Debian and Ubuntu, Mesa's software \
         one: apt-get install mesa-vulkan-drivers libvulkan1 — or render on the CPU (drop --gpu)"
    )]
    NoAdapter(String),
    /// The adapter refused a device.
    #[error("the GPU adapter {adapter} refused a device: {message}")]
    Device { adapter: String, message: String },
    /// The field or the image does not fit the adapter's limits.
    #[error("{0}")]
    TooLarge(String),
    /// What the field holds cannot be drawn on the GPU yet.
    #[error("{0}")]
    Unsupported(String),
    /// No window can be opened (no display server).
    #[error("cannot open a window: {0}")]
    NoDisplay(String),
    /// Writing a file (a screenshot) failed.
    #[error("{0}")]
    Io(String),
    /// A GPU operation failed (validation, out of memory, a lost device).
    #[error("GPU error: {0}")]
    Gpu(String),
}
