// Shared declarations, prepended to project.wgsl and rasterize.wgsl by the Rust launcher.
// Must match `RenderParams` in render-core/src/gpu.rs field for field (all 16-byte vectors).
struct RenderParams {
    // Rows of camera_from_world's rotation; w holds the translation component.
    camera_row0: vec4<f32>,
    camera_row1: vec4<f32>,
    camera_row2: vec4<f32>,
    // fx, fy, cx, cy
    intrinsics: vec4<f32>,
    // width, height, tiles_x, tiles_y
    image_size: vec4<u32>,
    // gaussian count, intersection count, unused, unused
    counts: vec4<u32>,
    // min splat alpha, max splat alpha, min transmittance, low-pass variance
    thresholds: vec4<f32>,
    // near plane, max log-scale, min quaternion norm^2, extent in sigmas
    culling: vec4<f32>,
    // min x/z, max x/z, min y/z, max y/z of projected means (frustum plus guard band)
    frustum: vec4<f32>,
}

const TILE_SIZE: u32 = 16u;
const FLOAT_EXPONENT_MASK: u32 = 0x7f800000u;

// NaN/Inf test on the bit pattern: WGSL lets compilers assume finite maths, so `x != x`
// is not a reliable NaN test.
fn is_finite(x: f32) -> bool {
    return (bitcast<u32>(x) & FLOAT_EXPONENT_MASK) != FLOAT_EXPONENT_MASK;
}

// Linear workgroup index for 1D work spread over a 2D grid (dispatch limit is 65535 per axis).
fn linear_workgroup(workgroup_id: vec3<u32>, workgroup_count: vec3<u32>) -> u32 {
    return workgroup_id.y * workgroup_count.x + workgroup_id.x;
}
