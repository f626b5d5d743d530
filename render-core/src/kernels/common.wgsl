// Shared WGSL declarations and helpers. The launcher (render-core/src/wgsl.rs, `compose`)
// puts the generated prelude (every constant and uniform struct shared with the host) and then
// this file in front of every kernel.

const FLOAT_EXPONENT_MASK: u32 = 0x7f800000u;

// exp() of larger magnitudes overflows f32; the sigmoid is saturated long before (project and
// project_backward clamp opacity logits to it).
const MAX_ABS_OPACITY_LOGIT: f32 = 80.0;
// Tile rectangles of at most this many tiles get a per-tile ellipse test in project (one mask
// bit per tile), which the binning then follows.
const MAX_MASKED_TILES: u32 = 32u;
// The tile mask of a rectangle that is not masked: every tile.
const ALL_TILES: u32 = 0xffffffffu;

// Offsets of dL/d(mean2d, conic, opacity, colour, depth) within a Gaussian's
// SCREEN_GRADIENT_STRIDE floats of screen_gradients (rasterize_backward writes them,
// project_backward reads them).
const V_MEAN2D: u32 = 0u;
const V_CONIC: u32 = 2u;
const V_OPACITY: u32 = 5u;
const V_COLOUR: u32 = 6u;
const V_DEPTH: u32 = 9u;

// NaN/Inf test on the bit pattern: WGSL lets compilers assume finite maths, so `x != x`
// is not a reliable NaN test.
fn is_finite(x: f32) -> bool {
    return (bitcast<u32>(x) & FLOAT_EXPONENT_MASK) != FLOAT_EXPONENT_MASK;
}

fn all_finite3(v: vec3<f32>) -> bool {
    return is_finite(v.x) && is_finite(v.y) && is_finite(v.z);
}

// Linear workgroup index for 1D work spread over a 2D grid (dispatch limit is 65535 per axis).
fn linear_workgroup(workgroup_id: vec3<u32>, workgroup_count: vec3<u32>) -> u32 {
    return workgroup_id.y * workgroup_count.x + workgroup_id.x;
}

// Relative and absolute margins on the squared Mahalanobis radius of visible_radius_squared:
// they absorb f32 rounding (of the radius, of the quadratic form in ellipse_misses_box and of
// the rasterizer's own power), so no test built on it ever excludes a pixel where the
// rasterizer's alpha test would pass.
const VISIBLE_RADIUS_SQUARED_RELATIVE_MARGIN: f32 = 1e-3;
const VISIBLE_RADIUS_SQUARED_MARGIN: f32 = 0.01;

// The squared Mahalanobis radius r^2 = 2 ln(opacity / min_alpha) of the ellipse
// d^T conic d <= r^2 outside which a splat's alpha opacity * exp(-0.5 d^T conic d) stays below
// min_alpha (the params.min_splat_alpha of a render), with the margins above. Callers handle
// min_alpha <= 0 (no cut-off, no ellipse) themselves.
fn visible_radius_squared(opacity: f32, min_alpha: f32) -> f32 {
    return max(2.0 * log(opacity / min_alpha), 0.0) * (1.0 + VISIBLE_RADIUS_SQUARED_RELATIVE_MARGIN)
        + VISIBLE_RADIUS_SQUARED_MARGIN;
}

fn quadratic(d: vec2<f32>, conic: vec3<f32>) -> f32 {
    return conic.x * d.x * d.x + 2.0 * conic.y * d.x * d.y + conic.z * d.y * d.y;
}

// Minimum of d^T [[a, b], [b, c]] d over the box low <= d <= high (conic = (a, b, c) positive
// definite): 0 when the box holds the origin, else the minimum over its four edges, each a
// 1D quadratic minimised at the clamped stationary point.
fn box_min_quadratic(low: vec2<f32>, high: vec2<f32>, conic: vec3<f32>) -> f32 {
    if all(low <= vec2<f32>(0.0)) && all(high >= vec2<f32>(0.0)) {
        return 0.0;
    }
    var best = quadratic(vec2<f32>(low.x, clamp(-conic.y * low.x / conic.z, low.y, high.y)), conic);
    best = min(best, quadratic(vec2<f32>(high.x, clamp(-conic.y * high.x / conic.z, low.y, high.y)), conic));
    best = min(best, quadratic(vec2<f32>(clamp(-conic.y * low.y / conic.x, low.x, high.x), low.y), conic));
    best = min(best, quadratic(vec2<f32>(clamp(-conic.y * high.y / conic.x, low.x, high.x), high.y), conic));
    return best;
}

// Whether a splat (mean, opacity, conic) misses every pixel centre of the box low ..= high
// (image coordinates): its visible ellipse (visible_radius_squared) and the box do not meet,
// so it adds exactly nothing to those pixels and a rasterizer may skip it there. Never true
// without an alpha cut-off. The conic must be positive definite (project bins no other).
fn ellipse_misses_box(mean: vec2<f32>, opacity: f32, conic: vec3<f32>, min_alpha: f32,
                      low: vec2<f32>, high: vec2<f32>) -> bool {
    if !(min_alpha > 0.0) {
        return false;
    }
    let nearest = box_min_quadratic(low - mean, high - mean, conic);
    return nearest > visible_radius_squared(opacity, min_alpha);
}

const NO_LANE: u32 = 0xffffffffu;

// Removes the lowest set bit of a subgroup ballot (lanes 0..127 over 4 words) and returns its
// lane, or NO_LANE once the ballot is empty. Selects rather than a loop over the words: it
// runs once per splat in the rasterizers' inner loops, and on lavapipe a loop costs a pass
// more than its trips (render-core/README.md).
fn pop_lowest_lane(ballot: ptr<function, vec4<u32>>) -> u32 {
    let words = *ballot;
    let word = select(select(select(3u, 2u, words.z != 0u), 1u, words.y != 0u), 0u,
                      words.x != 0u);
    let bits = select(select(select(words.w, words.z, word == 2u), words.y, word == 1u), words.x,
                      word == 0u);
    *ballot = select(words, vec4<u32>(bits & (bits - 1u)),
                     vec4<u32>(word) == vec4<u32>(0u, 1u, 2u, 3u));
    return select(32u * word + firstTrailingBit(bits), NO_LANE, bits == 0u);
}

// Largest per-pixel step of a splat's power that row_gaussian_values lets its ratio take
// (exp(80) ~ 5.5e34 stays finite in f32; steps in reach of a visible pixel are below 39).
const MAX_PIXEL_STEP_POWER: f32 = 80.0;

// exp(power) of a splat at the 4 pixels x0 .. x0 + 3 of one row (the vec4 components), where
// power = -0.5 (a dx^2 + c dy^2) - b dx dy, conic = (a, b, c), dx = x - mean x (offset_x0 at
// x0) and dy = offset_y. Both rasterizers evaluate splats only through this function, so the
// backward pass recomputes the forward's alpha bit for bit.
// Why not one exp per pixel: on SIMD CPU adapters the exp is half of a pixel's compositing
// arithmetic. power is quadratic in x, so the value at the next pixel is the current one times
// exp(step), and each step is the previous one minus a: one exp at x0, one for the first
// ratio, then multiplications (`ratio_growth` = exp(-a), once per splat, from the caller).
// Range: every conic has a <= 1 / (low-pass variance 0.3 px^2), so in a group with any pixel
// where alpha can reach 1/255 (power >= -5.6) the power at x0 is >= -39 and the steps are
// below 39: no under- or overflow, and the values equal per-pixel exps to a few ulps of the
// power (the CPU reference's tolerance). Elsewhere a value may be 0, above 1, inf or NaN
// (an underflowed value times a huge ratio): callers treat any value not <= 1 as invisible,
// which NaN is too (it compares false), and the ratio cap keeps the valid ones finite.
fn row_gaussian_values(conic: vec3<f32>, offset_x0: f32, offset_y: f32, ratio_growth: f32)
    -> vec4<f32> {
    let power0 = -0.5 * (conic.x * offset_x0 * offset_x0 + conic.z * offset_y * offset_y)
        - conic.y * offset_x0 * offset_y;
    // power(x0 + 1) - power(x0)
    let step0 = -(conic.x * (offset_x0 + 0.5) + conic.y * offset_y);
    let value0 = exp(power0);
    let ratio0 = exp(min(step0, MAX_PIXEL_STEP_POWER));
    let value1 = value0 * ratio0;
    let ratio1 = ratio0 * ratio_growth;
    let value2 = value1 * ratio1;
    let value3 = value2 * (ratio1 * ratio_growth);
    return vec4<f32>(value0, value1, value2, value3);
}

// The ratio_growth of row_gaussian_values for a splat: exp(-a).
fn row_ratio_growth(conic: vec3<f32>) -> f32 {
    return exp(-conic.x);
}
