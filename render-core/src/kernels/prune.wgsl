// prune: one invocation per live Gaussian (WORKGROUP_SIZE per workgroup, linear workgroup id
// over a 2D grid). Writes keep_flags[i] = 1 when Gaussian i survives the prune criteria
// (docs/method.md, One agent: Pruning) and 0 when it is removed: any non-finite parameter,
// opacity below the minimum, largest scale above the maximum, or largest scale above
// max_elongation x the sum of the other two.
// The host passes the opacity test as a logit threshold and the size test as a log-scale
// threshold, so both compare the stored values directly (exactly as PruneCriteria::keeps does
// on the host, with no activation function whose rounding could differ).
// Invariant: only indices < count are read or written.

@group(0) @binding(0) var<uniform> prune_params: PruneParams;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> quaternions: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(5) var<storage, read> colours: array<f32>;
@group(0) @binding(6) var<storage, read_write> keep_flags: array<u32>;

// Largest scale > max_elongation x (sum of the other two): a needle-shaped Gaussian.
fn is_elongated(log_scale: vec3<f32>, max_elongation: f32) -> bool {
    let scale = exp(log_scale);
    var largest = scale.x;
    var others = scale.y + scale.z;
    if scale.y > largest {
        largest = scale.y;
        others = scale.x + scale.z;
    }
    if scale.z > largest {
        largest = scale.z;
        others = scale.x + scale.y;
    }
    return largest > max_elongation * others;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let index = linear_workgroup(workgroup_id, workgroup_count) * WORKGROUP_SIZE + local_index;
    if index >= prune_params.count {
        return;
    }
    let mean = vec3<f32>(means[3u * index], means[3u * index + 1u], means[3u * index + 2u]);
    let log_scale = vec3<f32>(
        log_scales[3u * index], log_scales[3u * index + 1u], log_scales[3u * index + 2u]);
    let quaternion = quaternions[index];
    let opacity_logit = opacity_logits[index];
    let colour = vec3<f32>(colours[3u * index], colours[3u * index + 1u], colours[3u * index + 2u]);
    let finite = all_finite3(mean) && all_finite3(log_scale) && all_finite3(colour)
        && all_finite3(quaternion.xyz) && is_finite(quaternion.w) && is_finite(opacity_logit);
    var keep = false;
    if finite {
        let transparent = opacity_logit < prune_params.opacity_logit_threshold;
        let largest_log_scale = max(max(log_scale.x, log_scale.y), log_scale.z);
        let too_large = largest_log_scale > prune_params.max_log_scale;
        keep = !transparent && !too_large
            && !is_elongated(log_scale, prune_params.max_elongation);
    }
    keep_flags[index] = select(0u, 1u, keep);
}
