//! Device-memory accounting (`GpuContext::buffer_bytes` / `peak_buffer_bytes`), behind the
//! render benchmark's `peak_device_mib`. Its own test binary with its own context: the
//! figures are process-wide, so tests running beside it would change them.

mod common;

use render_core::context::GpuContext;
use render_core::gpu::DeviceGaussians;

/// Bytes of the parameters of one Gaussian as floats (mean 3, log-scales 3, quaternion 4,
/// opacity logit 1, colour 3): a lower bound of what the device map holds per Gaussian.
const PARAMETER_BYTES: u64 = 14 * 4;

#[test]
fn peak_buffer_memory_sees_a_map_that_is_gone_again() {
    let context = GpuContext::new().expect("a wgpu adapter (lavapipe in CI) is required");
    let camera = common::default_camera();
    let count = 20_000;
    let cloud = common::random_scene(&camera, count, 3, (-4.0, -2.0), (-1.0, 3.0));

    context.release_dropped_buffers().unwrap();
    context.reset_peak_buffer_bytes();
    let before = context.buffer_bytes();
    assert_eq!(context.peak_buffer_bytes(), before);

    let map = DeviceGaussians::upload(&context, &cloud).unwrap();
    let with_map = context.buffer_bytes();
    assert!(
        with_map >= before + count as u64 * PARAMETER_BYTES,
        "a map of {count} Gaussians added {} bytes",
        with_map - before
    );
    assert!(context.peak_buffer_bytes() >= with_map);

    drop(map);
    context.release_dropped_buffers().unwrap();
    let after = context.buffer_bytes();
    assert!(
        after < with_map,
        "{after} bytes still held after the map was dropped"
    );
    assert!(
        context.peak_buffer_bytes() >= with_map,
        "the peak forgot the map"
    );

    context.reset_peak_buffer_bytes();
    assert_eq!(context.peak_buffer_bytes(), after);
}
