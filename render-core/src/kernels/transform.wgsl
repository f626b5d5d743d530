// transform: applies a rigid transform p -> R p + t to every live Gaussian in place, one
// invocation per Gaussian (WORKGROUP_SIZE per workgroup, linear workgroup id over a 2D grid).
// Either one transform for the whole map (an agent-to-world correction: group_mode 0) or one
// per group, with the group of Gaussian i in group_of[i] (a non-rigid correction that moves each
// keyframe's Gaussians with their keyframe: group_mode 1); a group index >= transform_count
// leaves the Gaussian unchanged.
// mean <- R mean + t; quaternion <- q_R * q (Hamilton product, [w, x, y, z]), which
// left-multiplies the Gaussian's rotation by R so its covariance becomes R Sigma R^T.
// Log-scales, opacity and colour do not depend on the frame and stay as they are. q_R is the
// unit quaternion of R, computed on the host, so |q| is preserved.
// Invariant: only indices < count are read or written; group_of is read only in group mode.

@group(0) @binding(0) var<uniform> transform_params: TransformParams;
@group(0) @binding(1) var<storage, read_write> means: array<f32>;
@group(0) @binding(2) var<storage, read_write> quaternions: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> transforms: array<GroupTransform>;
@group(0) @binding(4) var<storage, read> group_of: array<u32>;

// Hamilton product a * b of quaternions stored as (w, x, y, z).
fn quaternion_multiply(a: vec4<f32>, b: vec4<f32>) -> vec4<f32> {
    let a_vector = a.yzw;
    let b_vector = b.yzw;
    let w = a.x * b.x - dot(a_vector, b_vector);
    let vector = a.x * b_vector + b.x * a_vector + cross(a_vector, b_vector);
    return vec4<f32>(w, vector);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let index = linear_workgroup(workgroup_id, workgroup_count) * WORKGROUP_SIZE + local_index;
    if index >= transform_params.gaussian_count {
        return;
    }
    var group = 0u;
    if transform_params.group_mode == TRANSFORM_BY_GROUP {
        group = group_of[index];
    }
    if group >= transform_params.transform_count {
        return;
    }
    let transform = transforms[group];
    let mean = vec4<f32>(means[3u * index], means[3u * index + 1u], means[3u * index + 2u], 1.0);
    means[3u * index] = dot(transform.row0, mean);
    means[3u * index + 1u] = dot(transform.row1, mean);
    means[3u * index + 2u] = dot(transform.row2, mean);
    quaternions[index] = quaternion_multiply(transform.rotation_quaternion, quaternions[index]);
}
