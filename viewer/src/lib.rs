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
//! * [`headless`]: `vlf render --gpu`: the same sample positions and box filter
//!   as the CPU renderer, into an [`vlf_core::render::Image`].
//!
//! Mirrors are drawn with their diffuse part only so far (the CPU renderer's
//! `Trace { depth: 0 }`); their directional radiance comes next.

pub mod field;
pub mod gpu;
pub mod headless;

pub use field::FieldRenderer;
pub use gpu::Gpu;
pub use headless::render;

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
    /// A GPU operation failed (validation, out of memory, a lost device).
    #[error("GPU error: {0}")]
    Gpu(String),
}
