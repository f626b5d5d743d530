// Gradient accumulation with native float atomics (SHADER_FLOAT32_ATOMIC).
@group(0) @binding(10) var<storage, read_write> screen_gradients: array<atomic<f32>>;

fn add_gradient(index: u32, value: f32) {
    if value != 0.0 {
        atomicAdd(&screen_gradients[index], value);
    }
}
