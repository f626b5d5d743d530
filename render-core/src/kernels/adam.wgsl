// adam: one Adam step on one parameter group of adam_params.count f32 elements. Bias
// corrections are computed on the host from the step count, so nothing is read back. A
// non-finite gradient element is treated as zero so one bad pixel cannot poison the
// parameters.
// - `main`: one invocation per 4 consecutive elements (vec4 loads and stores; WORKGROUP_SIZE
//   per workgroup, linear id over a 2D grid), for the first count / 4 vectors. On CPU adapters
//   (lavapipe) every load or store runs as a loop over the lanes per instruction, so a vec4
//   costs about what an f32 does: four elements per invocation cut the group's loop trips
//   by four (docs/benchmarks.md).
// - `tail`: the last count % 4 elements, one invocation each, through f32 views of the same
//   buffers (bindings 5 .. 8).

@group(0) @binding(0) var<uniform> adam_params: AdamParams;
@group(0) @binding(1) var<storage, read_write> parameters: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> gradients: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> first_moments: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> second_moments: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> tail_parameters: array<f32>;
@group(0) @binding(6) var<storage, read> tail_gradients: array<f32>;
@group(0) @binding(7) var<storage, read_write> tail_first_moments: array<f32>;
@group(0) @binding(8) var<storage, read_write> tail_second_moments: array<f32>;

struct AdamState {
    parameter: vec4<f32>,
    first_moment: vec4<f32>,
    second_moment: vec4<f32>,
}

// The step for four elements at once (a scalar in .x for the tail).
fn adam_update(state: AdamState, raw_gradient: vec4<f32>) -> AdamState {
    let non_finite = (bitcast<vec4<u32>>(raw_gradient) & vec4<u32>(FLOAT_EXPONENT_MASK))
        == vec4<u32>(FLOAT_EXPONENT_MASK);
    let gradient = select(raw_gradient, vec4<f32>(0.0), non_finite);
    let beta1 = adam_params.beta1;
    let beta2 = adam_params.beta2;
    let m = beta1 * state.first_moment + (1.0 - beta1) * gradient;
    let v = beta2 * state.second_moment + (1.0 - beta2) * gradient * gradient;
    let m_hat = m * adam_params.bias_correction1;
    let v_hat = v * adam_params.bias_correction2;
    let step = adam_params.learning_rate * m_hat / (sqrt(v_hat) + adam_params.epsilon);
    return AdamState(state.parameter - step, m, v);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let index = linear_workgroup(workgroup_id, workgroup_count) * WORKGROUP_SIZE + local_index;
    if index >= adam_params.count / 4u {
        return;
    }
    let next = adam_update(
        AdamState(parameters[index], first_moments[index], second_moments[index]),
        gradients[index]);
    parameters[index] = next.parameter;
    first_moments[index] = next.first_moment;
    second_moments[index] = next.second_moment;
}

@compute @workgroup_size(4)
fn tail(@builtin(local_invocation_index) local_index: u32) {
    let index = adam_params.count / 4u * 4u + local_index;
    if index >= adam_params.count {
        return;
    }
    let next = adam_update(
        AdamState(vec4<f32>(tail_parameters[index]), vec4<f32>(tail_first_moments[index]),
                  vec4<f32>(tail_second_moments[index])),
        vec4<f32>(tail_gradients[index]));
    tail_parameters[index] = next.parameter.x;
    tail_first_moments[index] = next.first_moment.x;
    tail_second_moments[index] = next.second_moment.x;
}
