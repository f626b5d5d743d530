// reduce: sums an array of vec4<f32> in blocks of 256 (one element per invocation, linear
// workgroup id over a 2D grid) with a fixed-shape tree in workgroup memory, writing one
// partial sum per block. The launcher repeats it until one value remains. The fixed tree
// makes the result deterministic (unlike atomics).

struct ReduceParams {
    count: u32,
    padding0: u32,
    padding1: u32,
    padding2: u32,
}

@group(0) @binding(0) var<uniform> reduce_params: ReduceParams;
@group(0) @binding(1) var<storage, read> reduce_input: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> reduce_output: array<vec4<f32>>;

const BLOCK_SIZE: u32 = 256u;
var<workgroup> partial: array<vec4<f32>, BLOCK_SIZE>;

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = workgroup_id.y * workgroup_count.x + workgroup_id.x;
    let index = block * BLOCK_SIZE + local_index;
    var value = vec4<f32>(0.0);
    if index < reduce_params.count {
        value = reduce_input[index];
    }
    partial[local_index] = value;
    workgroupBarrier();
    for (var stride = BLOCK_SIZE / 2u; stride > 0u; stride = stride / 2u) {
        if local_index < stride {
            partial[local_index] += partial[local_index + stride];
        }
        workgroupBarrier();
    }
    if local_index == 0u && block * BLOCK_SIZE < reduce_params.count {
        reduce_output[block] = partial[0];
    }
}
