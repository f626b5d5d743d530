// adam: one Adam step on one parameter group, one invocation per f32 element (256 per
// workgroup, linear id over a 2D grid). Bias corrections are computed on the host from the step
// count, so nothing is read back. A non-finite gradient element is treated as zero so one bad
// pixel cannot poison the parameters.

struct AdamParams {
    count: u32,
    padding0: u32,
    padding1: u32,
    padding2: u32,
    // learning rate, beta1, beta2, epsilon
    rates: vec4<f32>,
    // 1 / (1 - beta1^t), 1 / (1 - beta2^t), unused, unused
    corrections: vec4<f32>,
}

@group(0) @binding(0) var<uniform> adam_params: AdamParams;
@group(0) @binding(1) var<storage, read_write> parameters: array<f32>;
@group(0) @binding(2) var<storage, read> gradients: array<f32>;
@group(0) @binding(3) var<storage, read_write> first_moments: array<f32>;
@group(0) @binding(4) var<storage, read_write> second_moments: array<f32>;

const FLOAT_EXPONENT_MASK: u32 = 0x7f800000u;

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let index = (workgroup_id.y * workgroup_count.x + workgroup_id.x) * 256u + local_index;
    if index >= adam_params.count {
        return;
    }
    var gradient = gradients[index];
    if (bitcast<u32>(gradient) & FLOAT_EXPONENT_MASK) == FLOAT_EXPONENT_MASK {
        gradient = 0.0;
    }
    let learning_rate = adam_params.rates.x;
    let beta1 = adam_params.rates.y;
    let beta2 = adam_params.rates.z;
    let epsilon = adam_params.rates.w;
    let m = beta1 * first_moments[index] + (1.0 - beta1) * gradient;
    let v = beta2 * second_moments[index] + (1.0 - beta2) * gradient * gradient;
    first_moments[index] = m;
    second_moments[index] = v;
    let m_hat = m * adam_params.corrections.x;
    let v_hat = v * adam_params.corrections.y;
    parameters[index] -= learning_rate * m_hat / (sqrt(v_hat) + epsilon);
}
