//! wgpu adapter, device and the capabilities the kernels care about.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{OnceLock, mpsc};

use crate::map::MapKernels;

use wgpu::util::DeviceExt;

/// Errors of the wgpu path.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter was found, or none matches [`ADAPTER_ENV`] (the message then lists those
    /// there are).
    #[error("no wgpu adapter available: {0}")]
    NoAdapter(String),
    /// The adapter refused to create the device (wgpu's message).
    #[error("wgpu device request failed: {0}")]
    RequestDevice(String),
    /// The adapter offers fewer storage buffers per shader stage than the kernels bind
    /// ([`REQUIRED_STORAGE_BUFFERS_PER_STAGE`]).
    #[error("adapter limit too small: {0}")]
    Limits(String),
    /// A buffer would exceed the adapter's largest storage binding, or a count exceeds `u32`
    /// (too many Gaussians or tile/Gaussian pairs for one frame).
    #[error("scene too large for this adapter: {0}")]
    TooLarge(String),
    /// The caller's data does not fit together: attribute vectors of different lengths, an
    /// empty image, a frame, gradients or Adam state built for other Gaussians or another
    /// image size, and the like (the message says which).
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// Waiting for the device or mapping a buffer for reading failed (wgpu's message).
    #[error("reading back a device buffer failed: {0}")]
    Readback(String),
}

/// Storage buffers the widest kernel (project_backward) binds at once. The device is created
/// with exactly this many per stage, so a kernel that binds more fails to compile on every
/// adapter (and in the tests), not only on one that offers no more.
pub const REQUIRED_STORAGE_BUFFERS_PER_STAGE: u32 = 13;

/// An adapter, its device and queue, and what the kernels may rely on.
pub struct GpuContext {
    /// The device every buffer and pipeline of this context is created on.
    pub device: wgpu::Device,
    /// The device's queue, to which every pass is submitted.
    pub queue: wgpu::Queue,
    /// Name, backend and driver of the adapter chosen (see [`adapter_label`]).
    pub adapter_info: wgpu::AdapterInfo,
    /// The limits the device was created with: the adapter's own, except
    /// `max_storage_buffers_per_shader_stage` ([`REQUIRED_STORAGE_BUFFERS_PER_STAGE`]).
    pub limits: wgpu::Limits,
    /// `SHADER_FLOAT32_ATOMIC` is enabled on the device.
    pub has_float_atomics: bool,
    /// `SUBGROUP` is enabled on the device: the rasterizers use subgroup operations (every
    /// kernel has a variant without them, see [`crate::gpu::Subgroups`]).
    pub has_subgroups: bool,
    /// Kernels of the map edits (prune, compaction, rigid transform), compiled on first use
    /// so that the edit methods need no kernel object from the caller.
    pub(crate) map_kernels: OnceLock<MapKernels>,
    /// Largest [`GpuContext::buffer_bytes`] seen right after a buffer was created since the
    /// context was made or [`GpuContext::reset_peak_buffer_bytes`] was called. Buffer memory
    /// only grows when a buffer is created, and every buffer of the workspace is created by
    /// this context's helpers, so sampling there catches the exact peak.
    peak_buffer_bytes: AtomicU64,
}

impl GpuContext {
    /// Creates a context on the default adapter, blocking until it is ready.
    pub fn new() -> Result<Self, GpuError> {
        pollster::block_on(Self::new_async())
    }

    /// [`GpuContext::new`] without blocking. Picks the adapter [`ADAPTER_ENV`] names, else the
    /// most preferred one (a discrete GPU first), and enables float atomics and subgroups where
    /// the adapter has them. Fails with [`GpuError::NoAdapter`], [`GpuError::Limits`] or
    /// [`GpuError::RequestDevice`].
    pub async fn new_async() -> Result<Self, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle());
        let adapter = choose_adapter(&instance).await?;
        let adapter_features = adapter.features();
        let mut limits = adapter.limits();
        if limits.max_storage_buffers_per_shader_stage < REQUIRED_STORAGE_BUFFERS_PER_STAGE {
            return Err(GpuError::Limits(format!(
                "max_storage_buffers_per_shader_stage is {}, the kernels need {}",
                limits.max_storage_buffers_per_shader_stage, REQUIRED_STORAGE_BUFFERS_PER_STAGE
            )));
        }
        limits.max_storage_buffers_per_shader_stage = REQUIRED_STORAGE_BUFFERS_PER_STAGE;
        let has_float_atomics = adapter_features.contains(wgpu::Features::SHADER_FLOAT32_ATOMIC);
        let has_subgroups = adapter_features.contains(wgpu::Features::SUBGROUP);
        let mut required_features = wgpu::Features::empty();
        if has_float_atomics {
            required_features |= wgpu::Features::SHADER_FLOAT32_ATOMIC;
        }
        if has_subgroups {
            required_features |= wgpu::Features::SUBGROUP;
        }
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("render-core"),
                required_features,
                required_limits: limits.clone(),
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::RequestDevice(e.to_string()))?;
        Ok(Self {
            device,
            queue,
            adapter_info: adapter.get_info(),
            limits,
            has_float_atomics,
            has_subgroups,
            map_kernels: OnceLock::new(),
            peak_buffer_bytes: AtomicU64::new(0),
        })
    }

    /// Device memory held by live buffers now, in bytes, as wgpu's backend counts it (the
    /// sub-allocations of buffers, not the larger memory blocks they are carved from). Buffers
    /// dropped by the host count until the device is polled after their last use
    /// ([`GpuContext::wait_idle`]).
    pub fn buffer_bytes(&self) -> u64 {
        let bytes = self.device.get_internal_counters().hal.buffer_memory.read();
        u64::try_from(bytes).unwrap_or(0)
    }

    /// The most device memory buffers held at once since the last
    /// [`GpuContext::reset_peak_buffer_bytes`] (or since the context was made), in bytes.
    pub fn peak_buffer_bytes(&self) -> u64 {
        self.peak_buffer_bytes
            .load(Ordering::Relaxed)
            .max(self.buffer_bytes())
    }

    /// Starts a new peak measurement from the memory buffers hold now.
    pub fn reset_peak_buffer_bytes(&self) {
        self.peak_buffer_bytes
            .store(self.buffer_bytes(), Ordering::Relaxed);
    }

    /// Called after every buffer creation: updates the peak.
    fn record_allocation(&self) {
        self.peak_buffer_bytes
            .fetch_max(self.buffer_bytes(), Ordering::Relaxed);
    }

    /// Largest size in bytes of one storage binding.
    pub fn max_storage_binding_bytes(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    /// Blocks until every submitted command has finished (used by benchmarks and read-backs).
    pub fn wait_idle(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Readback(e.to_string()))
    }

    /// Frees the device memory of buffers the host has dropped: wgpu releases a dropped
    /// buffer at a device poll after a submission that follows its last use, so this submits
    /// an empty batch and waits for the device. Used before memory is measured.
    pub fn release_dropped_buffers(&self) -> Result<(), GpuError> {
        self.queue.submit([]);
        self.wait_idle()
    }

    /// A one-line description: adapter name, backend and capabilities.
    pub fn describe(&self) -> String {
        format!(
            "{}, float atomics: {}, subgroups: {}, max storage binding: {} MiB",
            adapter_label(&self.adapter_info),
            self.has_float_atomics,
            self.has_subgroups,
            self.max_storage_binding_bytes() >> 20
        )
    }

    /// A storage buffer holding `contents` (padded to at least `min_bytes`, since zero-sized
    /// bindings are invalid).
    pub(crate) fn storage_buffer_init(
        &self,
        label: &str,
        contents: &[u8],
        min_bytes: usize,
    ) -> wgpu::Buffer {
        let usage = wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST;
        let buffer = if contents.len() >= min_bytes {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage,
                })
        } else {
            let mut padded = contents.to_vec();
            padded.resize(min_bytes, 0);
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: &padded,
                    usage,
                })
        };
        self.record_allocation();
        buffer
    }

    /// An uninitialised (zeroed) storage buffer of at least `bytes` (minimum 16).
    pub(crate) fn storage_buffer(&self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        /// Smallest buffer we create: one vec4, so every binding is valid.
        const MIN_BUFFER_BYTES: u64 = 16;
        let size = bytes.max(MIN_BUFFER_BYTES);
        if size > self.max_storage_binding_bytes() {
            return Err(GpuError::TooLarge(format!(
                "buffer `{label}` needs {size} bytes, the adapter binds at most {}",
                self.max_storage_binding_bytes()
            )));
        }
        let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.record_allocation();
        Ok(buffer)
    }

    pub(crate) fn uniform_buffer(&self, label: &str, contents: &[u8]) -> wgpu::Buffer {
        let buffer = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: wgpu::BufferUsages::UNIFORM,
            });
        self.record_allocation();
        buffer
    }

    /// Copies `bytes` bytes from `offset` in `buffer` to the host (blocks until done).
    pub(crate) fn read_bytes(
        &self,
        buffer: &wgpu::Buffer,
        offset: u64,
        bytes: u64,
    ) -> Result<Vec<u8>, GpuError> {
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback staging"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.record_allocation();
        let mut encoder = self.device.create_command_encoder(&Default::default());
        encoder.copy_buffer_to_buffer(buffer, offset, &staging, 0, bytes);
        self.queue.submit([encoder.finish()]);
        let (sender, receiver) = mpsc::channel();
        staging
            .slice(..)
            .map_async(wgpu::MapMode::Read, move |result| {
                // The receiver outlives the poll below; a failed send only means it was dropped.
                let _ = sender.send(result);
            });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        receiver
            .recv()
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let view = staging
            .slice(..)
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let data = view.to_vec();
        drop(view);
        staging.unmap();
        Ok(data)
    }

    pub(crate) fn read_vec<T: bytemuck::Pod>(
        &self,
        buffer: &wgpu::Buffer,
        count: usize,
    ) -> Result<Vec<T>, GpuError> {
        let bytes = self.read_bytes(buffer, 0, (count * std::mem::size_of::<T>()) as u64)?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }
}

/// Environment variable that picks the adapter: a case-insensitive part of its label
/// ([`adapter_label`], as [`GpuContext::describe`] prints it), e.g. `Mesa 22` or `NVIDIA`.
pub const ADAPTER_ENV: &str = "MAC_EGO3D_ADAPTER";

/// The adapter's name, backend and driver, e.g. `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan,
/// Mesa 25.0.7 (LLVM 15.0.6))`: the driver tells two lavapipes apart.
pub fn adapter_label(info: &wgpu::AdapterInfo) -> String {
    if info.driver_info.is_empty() {
        format!("{} ({:?})", info.name, info.backend)
    } else {
        format!("{} ({:?}, {})", info.name, info.backend, info.driver_info)
    }
}

/// The version of Mesa in a driver description such as `Mesa 25.0.7-2~bpo12+1 (LLVM 15.0.6)`.
pub fn mesa_version(driver_info: &str) -> Option<[u32; 3]> {
    let rest = &driver_info[driver_info.find("Mesa ")? + "Mesa ".len()..];
    let digits_and_dots = rest
        .split(|c: char| !(c.is_ascii_digit() || c == '.'))
        .next()
        .filter(|text| text.starts_with(|c: char| c.is_ascii_digit()))?;
    let mut version = [0; 3];
    let mut parts = digits_and_dots.split('.');
    for slot in &mut version {
        match parts.next() {
            Some(part) if !part.is_empty() => *slot = part.parse().ok()?,
            _ => break,
        }
    }
    Some(version)
}

/// The adapter [`ADAPTER_ENV`] names, else the best by [`adapter_preference`] (the first
/// enumerated on a tie); `request_adapter`'s choice when enumeration finds none.
async fn choose_adapter(instance: &wgpu::Instance) -> Result<wgpu::Adapter, GpuError> {
    let adapters = instance.enumerate_adapters(wgpu::Backends::all()).await;
    if let Some(wanted) = std::env::var(ADAPTER_ENV).ok().filter(|v| !v.is_empty()) {
        let needle = wanted.to_lowercase();
        let labels: Vec<String> = adapters
            .iter()
            .map(|a| adapter_label(&a.get_info()))
            .collect();
        return match labels
            .iter()
            .position(|l| l.to_lowercase().contains(&needle))
        {
            Some(index) => Ok(adapters
                .into_iter()
                .nth(index)
                .expect("index from the list")),
            None => Err(GpuError::NoAdapter(format!(
                "{ADAPTER_ENV}={wanted} matches none of: {}",
                labels.join("; ")
            ))),
        };
    }
    let mut best: Option<(wgpu::Adapter, (u8, [u32; 3]))> = None;
    for adapter in adapters {
        let preference = adapter_preference(&adapter.get_info());
        if best.as_ref().is_none_or(|(_, kept)| preference > *kept) {
            best = Some((adapter, preference));
        }
    }
    match best {
        Some((adapter, _)) => Ok(adapter),
        None => instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::NoAdapter(e.to_string())),
    }
}

/// Larger is better: a discrete GPU, then an integrated, a virtual one, a CPU adapter; among
/// equals the newer Mesa. Two lavapipes side by side (the system's and the one
/// scripts/setup.sh provisions) differ up to about 2x in speed: Mesa 22.3 runs every
/// storage-buffer access as a loop over the SIMD lanes, Mesa 25 as a vector gather.
pub fn adapter_preference(info: &wgpu::AdapterInfo) -> (u8, [u32; 3]) {
    let kind = match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 4,
        wgpu::DeviceType::IntegratedGpu => 3,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 1,
        wgpu::DeviceType::Other => 0,
    };
    (kind, mesa_version(&info.driver_info).unwrap_or([0; 3]))
}

#[cfg(test)]
mod adapter_tests {
    use super::*;

    #[test]
    fn mesa_versions_are_read_from_driver_descriptions() {
        assert_eq!(
            mesa_version("Mesa 25.0.7-2~bpo12+1 (LLVM 15.0.6)"),
            Some([25, 0, 7])
        );
        assert_eq!(mesa_version("Mesa 22.3.6 (LLVM 15.0.6)"), Some([22, 3, 6]));
        assert_eq!(mesa_version("Mesa 24.1"), Some([24, 1, 0]));
        assert_eq!(mesa_version("535.104.05"), None);
        assert_eq!(mesa_version("Mesa x"), None);
    }

    fn info(device_type: wgpu::DeviceType, driver_info: &str) -> wgpu::AdapterInfo {
        wgpu::AdapterInfo {
            driver_info: driver_info.into(),
            ..wgpu::AdapterInfo::new(device_type, wgpu::Backend::Vulkan)
        }
    }

    #[test]
    fn a_gpu_beats_any_lavapipe_and_the_newer_lavapipe_beats_the_older() {
        let old = adapter_preference(&info(wgpu::DeviceType::Cpu, "Mesa 22.3.6 (LLVM 15.0.6)"));
        let new = adapter_preference(&info(wgpu::DeviceType::Cpu, "Mesa 25.0.7 (LLVM 15.0.6)"));
        let gpu = adapter_preference(&info(wgpu::DeviceType::DiscreteGpu, "535.104.05"));
        assert!(new > old);
        assert!(gpu > new);
    }
}
