// adam: one Adam step on one parameter group, one invocation per f32 element
// (WORKGROUP_SIZE per workgroup, linear id over a 2D grid). Bias corrections are computed on the host from the step
// count, so nothing is read back. A non-finite gradient element is treated as zero so one bad
// pixel cannot poison the parameters.

@group(0) @binding(0) var<uniform> adam_params: AdamParams;
@group(0) @binding(1) var<storage, read_write> parameters: array<f32>;
@group(0) @binding(2) var<storage, read> gradients: array<f32>;
@group(0) @binding(3) var<storage, read_write> first_moments: array<f32>;
@group(0) @binding(4) var<storage, read_write> second_moments: array<f32>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let index = linear_workgroup(workgroup_id, workgroup_count) * WORKGROUP_SIZE + local_index;
    if index >= adam_params.count {
        return;
    }
    var gradient = gradients[index];
    if (bitcast<u32>(gradient) & FLOAT_EXPONENT_MASK) == FLOAT_EXPONENT_MASK {
        gradient = 0.0;
    }
    let learning_rate = adam_params.learning_rate;
    let beta1 = adam_params.beta1;
    let beta2 = adam_params.beta2;
    let epsilon = adam_params.epsilon;
    let m = beta1 * first_moments[index] + (1.0 - beta1) * gradient;
    let v = beta2 * second_moments[index] + (1.0 - beta2) * gradient * gradient;
    first_moments[index] = m;
    second_moments[index] = v;
    let m_hat = m * adam_params.bias_correction1;
    let v_hat = v * adam_params.bias_correction2;
    parameters[index] -= learning_rate * m_hat / (sqrt(v_hat) + epsilon);
}
