// reduce: sums an array of vec4<f32> in chunks of REDUCE_CHUNK consecutive elements, one invocation
// per chunk walking it serially (64 invocations per workgroup, linear workgroup id over a 2D
// grid), writing one partial sum per chunk. The launcher repeats it until one value remains.
// The fixed chunking and order make the result deterministic (unlike atomics); a serial walk
// costs one load per element on CPU adapters (lavapipe), a tree in workgroup memory dozens.

@group(0) @binding(0) var<uniform> reduce_params: ReduceParams;
@group(0) @binding(1) var<storage, read> reduce_input: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> reduce_output: array<vec4<f32>>;

@compute @workgroup_size(REDUCE_WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let chunk = linear_workgroup(workgroup_id, workgroup_count) * REDUCE_WORKGROUP_SIZE + local_index;
    let first = chunk * REDUCE_CHUNK;
    if first >= reduce_params.count {
        return;
    }
    let last = min(first + REDUCE_CHUNK, reduce_params.count);
    var sum = vec4<f32>(0.0);
    for (var i = first; i < last; i++) {
        sum += reduce_input[i];
    }
    reduce_output[chunk] = sum;
}
