// Gradient accumulation without float atomics: a compare-exchange loop on the f32 bits.
@group(0) @binding(10) var<storage, read_write> screen_gradients: array<atomic<u32>>;

fn add_gradient(index: u32, value: f32) {
    if value == 0.0 {
        return;
    }
    var expected = atomicLoad(&screen_gradients[index]);
    loop {
        let updated = bitcast<u32>(bitcast<f32>(expected) + value);
        let result = atomicCompareExchangeWeak(&screen_gradients[index], expected, updated);
        if result.exchanged {
            break;
        }
        expected = result.old_value;
    }
}
