// compact: stable stream compaction of one per-Gaussian array, one invocation per 32-bit
// element (WORKGROUP_SIZE per workgroup, linear workgroup id over a 2D grid); element e belongs to
// Gaussian e / width. kept_through[i] is the inclusive prefix sum of the keep flags, so
// Gaussian i is kept iff kept_through[i] exceeds kept_through[i - 1] (or is 1 for i = 0), and
// it lands in slot kept_through[i] - 1: kept Gaussians keep their relative order.
// Elements are moved as u32 bit patterns so that every value (NaN payloads included) arrives
// unchanged. Invariants: reads only elements < count * width of `source_values`; writes only
// the slots of kept Gaussians in `destination_values`, a different buffer, so nothing is
// overwritten before it is read.

@group(0) @binding(0) var<uniform> compact_params: CompactParams;
@group(0) @binding(1) var<storage, read> kept_through: array<u32>;
@group(0) @binding(2) var<storage, read> source_values: array<u32>;
@group(0) @binding(3) var<storage, read_write> destination_values: array<u32>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let element = linear_workgroup(workgroup_id, workgroup_count) * WORKGROUP_SIZE + local_index;
    let width = compact_params.width;
    if element >= compact_params.count * width {
        return;
    }
    let gaussian = element / width;
    let component = element - gaussian * width;
    let kept_before = select(0u, kept_through[gaussian - 1u], gaussian > 0u);
    let slot_plus_one = kept_through[gaussian];
    if slot_plus_one > kept_before {
        destination_values[(slot_plus_one - 1u) * width + component] = source_values[element];
    }
}
