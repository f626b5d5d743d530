// Gradient accumulation with native float atomics (SHADER_FLOAT32_ATOMIC) into binding 10:
// per Gaussian or per tile/Gaussian pair, see add_splat_gradient in
// rasterize_backward_pixels.wgsl.
@group(0) @binding(10) var<storage, read_write> gradient_sums: array<atomic<f32>>;

fn add_gradient(index: u32, value: f32) {
    if value != 0.0 {
        atomicAdd(&gradient_sums[index], value);
    }
}
