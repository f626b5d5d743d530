// adam: one Adam step on one parameter group, restricted to the Gaussians in view of the frame
// the gradients came from ("selective" Adam). One invocation per Gaussian (256 per workgroup,
// linear id over a 2D grid) walks the group's `width` values of its Gaussian.
// Why only the Gaussians in view: a Gaussian the frame culled (radius 0 in splat_conic.w, see
// project.wgsl) has a zero gradient only because it was not seen; plain Adam would still decay
// its moments and move it by its stale momentum, away from what the views that do see it
// asked for. Skipping it also skips most of the work when a view sees a small part of a map,
// which is the mapper's common case. Consecutive Gaussians were usually seeded from one
// keyframe, so whole SIMD groups skip together.
// Bias corrections are computed on the host from the step count (one count for the whole
// map, as in 3DGS), so nothing is read back. A non-finite gradient element is treated as zero
// so one bad pixel cannot poison the parameters.
// Invariants: only Gaussians < count are touched; a Gaussian out of view keeps its values and
// moments bit for bit.

struct AdamParams {
    // Gaussians, values per Gaussian in this group, unused, unused
    counts: vec4<u32>,
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
// The frame's splat_conic read as floats: (conic a, b, c, radius) per Gaussian, radius 0 when
// the frame culled the Gaussian.
@group(0) @binding(5) var<storage, read> splat_conic: array<f32>;

const FLOAT_EXPONENT_MASK: u32 = 0x7f800000u;
const SPLAT_RADIUS: u32 = 3u;

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let gaussian = (workgroup_id.y * workgroup_count.x + workgroup_id.x) * 256u + local_index;
    if gaussian >= adam_params.counts.x || !(splat_conic[4u * gaussian + SPLAT_RADIUS] > 0.0) {
        return;
    }
    let width = adam_params.counts.y;
    let learning_rate = adam_params.rates.x;
    let beta1 = adam_params.rates.y;
    let beta2 = adam_params.rates.z;
    let epsilon = adam_params.rates.w;
    for (var k = 0u; k < width; k++) {
        let index = gaussian * width + k;
        var gradient = gradients[index];
        if (bitcast<u32>(gradient) & FLOAT_EXPONENT_MASK) == FLOAT_EXPONENT_MASK {
            gradient = 0.0;
        }
        let m = beta1 * first_moments[index] + (1.0 - beta1) * gradient;
        let v = beta2 * second_moments[index] + (1.0 - beta2) * gradient * gradient;
        first_moments[index] = m;
        second_moments[index] = v;
        let m_hat = m * adam_params.corrections.x;
        let v_hat = v * adam_params.corrections.y;
        parameters[index] -= learning_rate * m_hat / (sqrt(v_hat) + epsilon);
    }
}
