//! [`DeviceGaussians`]: the Gaussian parameters resident on the device, and the identity of
//! their current arrangement ([`LayoutId`]).

use std::sync::atomic::{AtomicU64, Ordering};

use crate::context::{GpuContext, GpuError};
use crate::passes::VEC4_BYTES;
use crate::types::GaussianCloud;

/// Parameter groups of a Gaussian: means, log-scales, quaternions, opacity logits, colours.
pub(crate) const PARAMETER_GROUPS: usize = 5;
/// f32 values per Gaussian of each parameter group, in the order of [`PARAMETER_GROUPS`].
pub(crate) const PARAMETER_GROUP_WIDTHS: [u32; PARAMETER_GROUPS] = [3, 3, 4, 1, 3];

/// Gaussian parameters resident on the device (same layout and conventions as
/// [`GaussianCloud`]: means/log-scales/colours as packed f32 triples, quaternions `[w, x, y, z]`).
///
/// The buffers hold `capacity()` Gaussians of which the first `len()` are live; every kernel
/// works on the live count only. Structural edits (append, prune, retain, rigid transform)
/// happen in place on the device, see [`crate::map`].
pub struct DeviceGaussians {
    pub(crate) count: u32,
    /// Gaussians the buffers have room for (`>= count`).
    pub(crate) capacity: u32,
    /// Identifies the current order and number of Gaussians: renewed by every change of
    /// either, so frames, gradients and Adam state built for an older layout are rejected.
    pub(crate) layout: LayoutId,
    pub(crate) means: wgpu::Buffer,
    pub(crate) log_scales: wgpu::Buffer,
    pub(crate) quaternions: wgpu::Buffer,
    pub(crate) opacity_logits: wgpu::Buffer,
    pub(crate) colours: wgpu::Buffer,
}

impl DeviceGaussians {
    /// Copies `cloud` to the device, with room for exactly its Gaussians and a fresh layout.
    /// Fails with [`GpuError::InvalidInput`] when the cloud's vectors differ in length and
    /// [`GpuError::TooLarge`] when its widest buffer (16 bytes per Gaussian) exceeds one
    /// storage binding or the count exceeds `u32`.
    pub fn upload(context: &GpuContext, cloud: &GaussianCloud) -> Result<Self, GpuError> {
        cloud.validate_lengths().map_err(GpuError::InvalidInput)?;
        let count = u32::try_from(cloud.len())
            .map_err(|_| GpuError::TooLarge(format!("{} Gaussians exceed u32", cloud.len())))?;
        let widest = cloud.len() as u64 * VEC4_BYTES;
        if widest > context.max_storage_binding_bytes() {
            return Err(GpuError::TooLarge(format!(
                "{} Gaussians need {widest}-byte bindings, the adapter allows {}",
                cloud.len(),
                context.max_storage_binding_bytes()
            )));
        }
        let min = VEC4_BYTES as usize;
        Ok(Self {
            count,
            capacity: count,
            layout: LayoutId::fresh(),
            means: context.storage_buffer_init("means", bytemuck::cast_slice(&cloud.means), min),
            log_scales: context.storage_buffer_init(
                "log_scales",
                bytemuck::cast_slice(&cloud.log_scales),
                min,
            ),
            quaternions: context.storage_buffer_init(
                "quaternions",
                bytemuck::cast_slice(&cloud.quaternions),
                min,
            ),
            opacity_logits: context.storage_buffer_init(
                "opacity_logits",
                bytemuck::cast_slice(&cloud.opacity_logits),
                min,
            ),
            colours: context.storage_buffer_init(
                "colours",
                bytemuck::cast_slice(&cloud.colours),
                min,
            ),
        })
    }

    /// Number of live Gaussians (the first `len()` entries of the buffers).
    pub fn len(&self) -> usize {
        self.count as usize
    }

    /// True when there are no live Gaussians.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Gaussians the device buffers hold before [`DeviceGaussians::append`] must grow them.
    pub fn capacity(&self) -> usize {
        self.capacity as usize
    }

    /// The parameter buffers in [`PARAMETER_GROUP_WIDTHS`] order.
    pub(crate) fn parameter_buffers(&self) -> [&wgpu::Buffer; PARAMETER_GROUPS] {
        [
            &self.means,
            &self.log_scales,
            &self.quaternions,
            &self.opacity_logits,
            &self.colours,
        ]
    }

    /// Copies the parameters back to the host.
    pub fn download(&self, context: &GpuContext) -> Result<GaussianCloud, GpuError> {
        let n = self.len();
        Ok(GaussianCloud {
            means: context.read_vec(&self.means, n)?,
            log_scales: context.read_vec(&self.log_scales, n)?,
            quaternions: context.read_vec(&self.quaternions, n)?,
            opacity_logits: context.read_vec(&self.opacity_logits, n)?,
            colours: context.read_vec(&self.colours, n)?,
        })
    }
}

/// Identity of one arrangement (order and count) of a [`DeviceGaussians`]' entries; unique
/// within the process.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct LayoutId(u64);

impl LayoutId {
    pub(crate) fn fresh() -> Self {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        Self(NEXT.fetch_add(1, Ordering::Relaxed))
    }
}
