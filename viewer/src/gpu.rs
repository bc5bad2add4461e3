//! The adapter and device everything is drawn with.

use crate::ViewerError;

/// A wgpu device and its queue, with what the adapter is (for logs and reports).
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter: wgpu::Adapter,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
}

impl Gpu {
    /// The best adapter of any backend this build supports — a real GPU if there is one, else a
    /// software one such as Mesa's lavapipe — with the adapter's own limits, so large fields
    /// fit where the hardware allows.
    ///
    /// The primary backends (Vulkan, Metal, DirectX 12) are tried first and OpenGL only if they
    /// have no adapter: probing EGL where Vulkan works only logs driver errors.
    pub fn new() -> Result<Gpu, ViewerError> {
        Gpu::with_backends(wgpu::Backends::PRIMARY)
            .or_else(|primary| Gpu::with_backends(wgpu::Backends::SECONDARY).map_err(|_| primary))
    }

    /// As [`Gpu::new`], looking only at `backends` (`WGPU_BACKEND` in the environment narrows it
    /// further, as wgpu documents).
    pub fn with_backends(backends: wgpu::Backends) -> Result<Gpu, ViewerError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        desc.backends &= backends;
        Gpu::from_instance(&wgpu::Instance::new(desc), None)
    }

    /// The best adapter of `instance` that can present to `surface` (if any), and its device.
    pub fn from_instance(instance: &wgpu::Instance, surface: Option<&wgpu::Surface<'_>>) -> Result<Gpu, ViewerError> {
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: surface,
            apply_limit_buckets: false,
        }))
        .map_err(|e| ViewerError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("vlf"),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| ViewerError::Device {
            adapter: describe(&info),
            message: e.to_string(),
        })?;
        tracing::debug!(adapter = %describe(&info), "GPU device");
        Ok(Gpu {
            device,
            queue,
            adapter,
            info,
            limits,
        })
    }

    /// The adapter in words: `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan, Cpu)`.
    pub fn describe(&self) -> String {
        describe(&self.info)
    }

    /// Runs `f` and turns any validation or out-of-memory error it raised into a
    /// [`ViewerError::Gpu`] instead of wgpu's default, which panics.
    /// Waits for what was submitted so far, maps `buffer` (made with `MAP_READ`) and returns
    /// what `read` makes of its bytes; unmaps it again.
    pub fn read_mapped<T>(&self, buffer: &wgpu::Buffer, read: impl FnOnce(&[u8]) -> T) -> Result<T, ViewerError> {
        let slice = buffer.slice(..);
        let (sender, receiver) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = sender.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| ViewerError::Gpu(e.to_string()))?;
        receiver
            .recv()
            .map_err(|e| ViewerError::Gpu(e.to_string()))?
            .map_err(|e| ViewerError::Gpu(e.to_string()))?;
        let out = {
            let mapped = slice.get_mapped_range().map_err(|e| ViewerError::Gpu(e.to_string()))?;
            read(&mapped)
        };
        buffer.unmap();
        Ok(out)
    }

    pub fn checked<T>(&self, f: impl FnOnce() -> T) -> Result<T, ViewerError> {
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let memory = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let out = f();
        let oom = pollster::block_on(memory.pop());
        let invalid = pollster::block_on(validation.pop());
        match (invalid, oom) {
            (Some(e), _) | (None, Some(e)) => Err(ViewerError::Gpu(e.to_string())),
            (None, None) => Ok(out),
        }
    }
}

fn describe(info: &wgpu::AdapterInfo) -> String {
    format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type)
}
