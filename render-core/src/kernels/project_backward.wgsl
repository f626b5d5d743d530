// project_backward: one invocation per chunk of PROJECT_BACKWARD_CHUNK consecutive
// Gaussians, walked serially (64 invocations per workgroup, linear id over a 2D grid). For each
// Gaussian it recomputes the forward projection and chains the accumulated screen-space
// gradients (mean2d, conic, opacity, colour, depth; written by rasterize_backward) back to the
// Gaussian's parameters and to the camera pose. Invariants: culled Gaussians (radius 0 in
// splat_conic.w) keep the zero gradients of the launcher's fresh (zero-filled) buffers,
// unwritten; each invocation writes only its own Gaussians' entries, and the sum of their
// 6-DoF pose contributions (left perturbation of camera_from_world, [translation, rotation])
// to pose_translation / pose_rotation[chunk], summed afterwards by reduce.wgsl (a fixed
// order: deterministic).

@group(0) @binding(0) var<uniform> params: RenderParams;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> quaternions: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(5) var<storage, read> splat_conic: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> screen_gradients: array<f32>;
// Packed like the parameters: 3, 3, 4, 1 and 3 floats per Gaussian.
@group(0) @binding(7) var<storage, read_write> v_means: array<f32>;
@group(0) @binding(8) var<storage, read_write> v_log_scales: array<f32>;
@group(0) @binding(9) var<storage, read_write> v_quaternions: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> v_opacity_logits: array<f32>;
@group(0) @binding(11) var<storage, read_write> v_colours: array<f32>;
@group(0) @binding(12) var<storage, read_write> pose_translation: array<vec4<f32>>;
@group(0) @binding(13) var<storage, read_write> pose_rotation: array<vec4<f32>>;

// Element (row, column) of a column-major matrix.
fn at(m: mat3x3<f32>, row: u32, column: u32) -> f32 {
    return m[column][row];
}

fn write_gradients(index: u32, v_mean: vec3<f32>, v_log_scale: vec3<f32>, v_quaternion: vec4<f32>,
                   v_logit: f32, v_colour: vec3<f32>) {
    for (var k = 0u; k < 3u; k++) {
        v_means[3u * index + k] = v_mean[k];
        v_log_scales[3u * index + k] = v_log_scale[k];
        v_colours[3u * index + k] = v_colour[k];
    }
    v_quaternions[index] = v_quaternion;
    v_opacity_logits[index] = v_logit;
}

struct PoseGradient {
    translation: vec3<f32>,
    rotation: vec3<f32>,
}

@compute @workgroup_size(PROJECT_BACKWARD_WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let chunk = linear_workgroup(workgroup_id, workgroup_count) * PROJECT_BACKWARD_WORKGROUP_SIZE + local_index;
    let first = chunk * PROJECT_BACKWARD_CHUNK;
    if first >= params.gaussian_count {
        return;
    }
    let last = min(first + PROJECT_BACKWARD_CHUNK, params.gaussian_count);
    var pose = PoseGradient(vec3<f32>(0.0), vec3<f32>(0.0));
    for (var index = first; index < last; index++) {
        let contribution = chain_gaussian(index);
        pose.translation += contribution.translation;
        pose.rotation += contribution.rotation;
    }
    pose_translation[chunk] = vec4<f32>(pose.translation, 0.0);
    pose_rotation[chunk] = vec4<f32>(pose.rotation, 0.0);
}

// Writes Gaussian `index`'s parameter gradients and returns its pose contribution.
fn chain_gaussian(index: u32) -> PoseGradient {
    let zero3 = vec3<f32>(0.0);
    if !(splat_conic[index].w > 0.0) {
        // Culled: its gradients stay the zeros the fresh buffers hold (wgpu zero-fills new
        // buffers), so nothing is written.
        return PoseGradient(zero3, zero3);
    }
    let g = index * SCREEN_GRADIENT_STRIDE;
    let v_mean2d = vec2<f32>(screen_gradients[g + V_MEAN2D], screen_gradients[g + V_MEAN2D + 1u]);
    let v_conic = vec3<f32>(screen_gradients[g + V_CONIC], screen_gradients[g + V_CONIC + 1u],
                            screen_gradients[g + V_CONIC + 2u]);
    let v_opacity = screen_gradients[g + V_OPACITY];
    let v_colour = vec3<f32>(screen_gradients[g + V_COLOUR], screen_gradients[g + V_COLOUR + 1u],
                             screen_gradients[g + V_COLOUR + 2u]);
    let v_depth = screen_gradients[g + V_DEPTH];

    // Forward recomputation (identical to project.wgsl).
    let mean = vec3<f32>(means[3u * index], means[3u * index + 1u], means[3u * index + 2u]);
    let log_scale = vec3<f32>(log_scales[3u * index], log_scales[3u * index + 1u], log_scales[3u * index + 2u]);
    let raw_quaternion = quaternions[index];
    let quaternion_norm = sqrt(dot(raw_quaternion, raw_quaternion));
    let q = raw_quaternion / quaternion_norm;
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let rotation = mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
    let scale = exp(log_scale);
    let scaled_rotation = mat3x3<f32>(rotation[0] * scale.x, rotation[1] * scale.y, rotation[2] * scale.z);
    let world_covariance = scaled_rotation * transpose(scaled_rotation);
    let camera_rotation = transpose(mat3x3<f32>(
        params.camera_row0.xyz, params.camera_row1.xyz, params.camera_row2.xyz));
    let camera_translation = vec3<f32>(params.camera_row0.w, params.camera_row1.w, params.camera_row2.w);
    let p = camera_rotation * mean + camera_translation;
    let camera_covariance = camera_rotation * world_covariance * transpose(camera_rotation);
    let fx = params.fx;
    let fy = params.fy;
    let z2 = p.z * p.z;
    let z3 = z2 * p.z;
    let jacobian = mat3x2<f32>(
        vec2<f32>(fx / p.z, 0.0),
        vec2<f32>(0.0, fy / p.z),
        vec2<f32>(-fx * p.x / z2, -fy * p.y / z2),
    );
    let cov2d = jacobian * camera_covariance * transpose(jacobian)
        + mat2x2<f32>(vec2<f32>(params.low_pass_variance, 0.0), vec2<f32>(0.0, params.low_pass_variance));
    let det = cov2d[0][0] * cov2d[1][1] - cov2d[1][0] * cov2d[1][0];
    let conic = mat2x2<f32>(vec2<f32>(cov2d[1][1], -cov2d[0][1]) / det, vec2<f32>(-cov2d[1][0], cov2d[0][0]) / det);

    // Conic = inverse(cov2d): V_cov2d = -K V_K K (b is shared by both off-diagonal entries).
    let v_conic_matrix = mat2x2<f32>(vec2<f32>(v_conic.x, 0.5 * v_conic.y), vec2<f32>(0.5 * v_conic.y, v_conic.z));
    let v_cov2d = -1.0 * (conic * v_conic_matrix * conic);
    // cov2d = J W J^T: V_W = J^T V J, V_J = 2 V J W.
    let v_camera_covariance = transpose(jacobian) * v_cov2d * jacobian;
    let v_jacobian = 2.0 * (v_cov2d * jacobian * camera_covariance);
    var v_p = vec3<f32>(0.0);
    v_p.x = v_jacobian[2][0] * (-fx / z2) + v_mean2d.x * fx / p.z;
    v_p.y = v_jacobian[2][1] * (-fy / z2) + v_mean2d.y * fy / p.z;
    v_p.z = v_jacobian[0][0] * (-fx / z2) + v_jacobian[2][0] * (2.0 * fx * p.x / z3)
        + v_jacobian[1][1] * (-fy / z2) + v_jacobian[2][1] * (2.0 * fy * p.y / z3)
        - v_mean2d.x * fx * p.x / z2 - v_mean2d.y * fy * p.y / z2 + v_depth;

    let v_mean = transpose(camera_rotation) * v_p;
    let v_world_covariance = transpose(camera_rotation) * v_camera_covariance * camera_rotation;
    // Sigma = M M^T, M = R S.
    let v_scaled_rotation = 2.0 * (v_world_covariance * scaled_rotation);
    let v_rotation = mat3x3<f32>(v_scaled_rotation[0] * scale.x, v_scaled_rotation[1] * scale.y,
                                 v_scaled_rotation[2] * scale.z);
    let v_scale = vec3<f32>(dot(v_scaled_rotation[0], rotation[0]), dot(v_scaled_rotation[1], rotation[1]),
                            dot(v_scaled_rotation[2], rotation[2]));
    let v_log_scale = v_scale * scale;

    let vr = v_rotation;
    let v_w = 2.0 * (-z * at(vr, 0u, 1u) + y * at(vr, 0u, 2u) + z * at(vr, 1u, 0u) - x * at(vr, 1u, 2u)
        - y * at(vr, 2u, 0u) + x * at(vr, 2u, 1u));
    let v_x = 2.0 * (y * at(vr, 0u, 1u) + z * at(vr, 0u, 2u) + y * at(vr, 1u, 0u) - 2.0 * x * at(vr, 1u, 1u)
        - w * at(vr, 1u, 2u) + z * at(vr, 2u, 0u) + w * at(vr, 2u, 1u) - 2.0 * x * at(vr, 2u, 2u));
    let v_y = 2.0 * (-2.0 * y * at(vr, 0u, 0u) + x * at(vr, 0u, 1u) + w * at(vr, 0u, 2u) + x * at(vr, 1u, 0u)
        + z * at(vr, 1u, 2u) - w * at(vr, 2u, 0u) + z * at(vr, 2u, 1u) - 2.0 * y * at(vr, 2u, 2u));
    let v_z = 2.0 * (-2.0 * z * at(vr, 0u, 0u) - w * at(vr, 0u, 1u) + x * at(vr, 0u, 2u) + w * at(vr, 1u, 0u)
        - 2.0 * z * at(vr, 1u, 1u) + y * at(vr, 1u, 2u) + x * at(vr, 2u, 0u) + y * at(vr, 2u, 1u));
    let v_normalised = vec4<f32>(v_w, v_x, v_y, v_z);
    let v_quaternion = (v_normalised - q * dot(q, v_normalised)) / quaternion_norm;

    let logit = clamp(opacity_logits[index], -MAX_ABS_OPACITY_LOGIT, MAX_ABS_OPACITY_LOGIT);
    let opacity = 1.0 / (1.0 + exp(-logit));
    let v_logit = v_opacity * opacity * (1.0 - opacity);

    // Pose (left perturbation): d p = rho + phi x p; inside W, d R_cw = [phi]x R_cw.
    let v_camera_rotation = 2.0 * (v_camera_covariance * camera_rotation * world_covariance);
    let pm = v_camera_rotation * transpose(camera_rotation);
    let v_phi_covariance = vec3<f32>(at(pm, 2u, 1u) - at(pm, 1u, 2u), at(pm, 0u, 2u) - at(pm, 2u, 0u),
                                     at(pm, 1u, 0u) - at(pm, 0u, 1u));
    let v_rotation_pose = cross(p, v_p) + v_phi_covariance;
    write_gradients(index, v_mean, v_log_scale, v_quaternion, v_logit, v_colour);
    return PoseGradient(v_p, v_rotation_pose);
}
