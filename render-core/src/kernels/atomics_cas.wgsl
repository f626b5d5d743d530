// Gradient accumulation without float atomics: a compare-exchange loop on the f32 bits, into
// binding 10 (per Gaussian or per tile/Gaussian pair, see rasterize_backward_pixels.wgsl).
@group(0) @binding(10) var<storage, read_write> gradient_sums: array<atomic<u32>>;

fn add_gradient(index: u32, value: f32) {
    if value == 0.0 {
        return;
    }
    var expected = atomicLoad(&gradient_sums[index]);
    loop {
        let updated = bitcast<u32>(bitcast<f32>(expected) + value);
        let result = atomicCompareExchangeWeak(&gradient_sums[index], expected, updated);
        if result.exchanged {
            break;
        }
        expected = result.old_value;
    }
}
