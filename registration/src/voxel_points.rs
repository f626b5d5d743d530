//! The points of one voxel of [`crate::voxel_map::VoxelMap`], laid out for the nearest-point scan.
//!
//! Why blocks: a tracking query scans every point of its home voxel (tens of points at the default
//! 6 cm voxels), and that scan is where frame-to-model tracking spends most of its time. Stored as
//! `[x, y, z, slot]` per point the compiler scans one point at a time; stored as blocks of
//! [`LANES`] points with each coordinate in its own lane array, the squared distances of a whole
//! block are computed at once with 128-bit vector instructions (the `wide` crate: SSE2 on x86-64,
//! NEON on aarch64, a scalar fallback elsewhere; the compiler did not vectorise the scalar form of
//! this loop by itself). A block
//! is 64 bytes, one cache line, like four points of the per-point layout: the memory traffic is
//! unchanged.
//!
//! Unused lanes of the last block hold NaN coordinates: their distance is NaN, and NaN compares
//! false against any bound, so the scan needs no length check inside a block.

use wide::{bytemuck::cast, f32x4, u32x4};

/// Points per block: four 32-bit lanes fill one 128-bit vector, the width every x86-64 and
/// aarch64 machine has.
const LANES: usize = 4;

#[derive(Debug, Clone, Copy)]
#[repr(C, align(64))]
struct Block {
    x: [f32; LANES],
    y: [f32; LANES],
    z: [f32; LANES],
    slot: [u32; LANES],
}

const EMPTY_BLOCK: Block = Block {
    x: [f32::NAN; LANES],
    y: [f32::NAN; LANES],
    z: [f32::NAN; LANES],
    slot: [u32::MAX; LANES],
};

/// A voxel's points: positions and the map slots they belong to, in insertion order except that
/// a removal moves the last point into the removed one's place.
#[derive(Debug, Clone, Default)]
pub(crate) struct VoxelPoints {
    blocks: Vec<Block>,
    len: usize,
}

impl VoxelPoints {
    pub(crate) fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub(crate) fn len(&self) -> usize {
        self.len
    }

    pub(crate) fn push(&mut self, position: [f32; 3], slot: u32) {
        if self.len.is_multiple_of(LANES) {
            self.blocks.push(EMPTY_BLOCK);
        }
        self.len += 1;
        self.set(self.len - 1, position, slot);
    }

    /// The position and slot at `index` (insertion order as described on the type).
    fn get(&self, index: usize) -> ([f32; 3], u32) {
        let (block, lane) = (&self.blocks[index / LANES], index % LANES);
        (
            [block.x[lane], block.y[lane], block.z[lane]],
            block.slot[lane],
        )
    }

    fn set(&mut self, index: usize, position: [f32; 3], slot: u32) {
        let (block, lane) = (&mut self.blocks[index / LANES], index % LANES);
        [block.x[lane], block.y[lane], block.z[lane]] = position;
        block.slot[lane] = slot;
    }

    /// Removes the point of `slot`, moving the last point into its place. Returns false when the
    /// voxel does not hold that slot.
    pub(crate) fn remove_slot(&mut self, slot: u32) -> bool {
        let Some(at) = (0..self.len).find(|&i| self.get(i).1 == slot) else {
            return false;
        };
        let last = self.len - 1;
        let (position, moved_slot) = self.get(last);
        self.set(at, position, moved_slot);
        if last.is_multiple_of(LANES) {
            self.blocks.pop();
        } else {
            self.set(last, [f32::NAN; 3], u32::MAX);
        }
        self.len = last;
        true
    }

    /// The map slots of the points, in order.
    pub(crate) fn slots(&self) -> impl Iterator<Item = u32> + '_ {
        (0..self.len).map(|i| self.get(i).1)
    }

    /// The point nearest to `query` whose squared distance is at most `*best_sq`: its slot and
    /// squared distance, with `*best_sq` lowered to it. `None` (and `*best_sq` unchanged) when no
    /// point is that close. Among points at exactly the same distance, which one is returned is
    /// unspecified.
    pub(crate) fn nearest(&self, query: [f32; 3], best_sq: &mut f32) -> Option<(u32, f32)> {
        let [qx, qy, qz] = query.map(f32x4::splat);
        let mut lane_best = f32x4::splat(*best_sq);
        let mut lane_slot = u32x4::splat(u32::MAX);
        let mut found = u32x4::splat(0);
        for block in &self.blocks {
            let dx = f32x4::from(block.x) - qx;
            let dy = f32x4::from(block.y) - qy;
            let dz = f32x4::from(block.z) - qz;
            // The same operations in the same order as a scalar `dx*dx + dy*dy + dz*dz`.
            let d = dx * dx + dy * dy + dz * dz;
            let closer = d.simd_le(lane_best);
            lane_best = closer.bitselect(d, lane_best);
            let closer: u32x4 = cast(closer);
            lane_slot = (u32x4::from(block.slot) & closer) | (lane_slot & !closer);
            found |= closer;
        }
        let (lane_best, lane_slot, found) =
            (lane_best.to_array(), lane_slot.to_array(), found.to_array());
        let mut best = None;
        for lane in 0..LANES {
            if found[lane] != 0 && lane_best[lane] <= *best_sq {
                *best_sq = lane_best[lane];
                best = Some((lane_slot[lane], lane_best[lane]));
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute_nearest(points: &[([f32; 3], u32)], q: [f32; 3], bound: f32) -> Option<f32> {
        points
            .iter()
            .map(|(p, _)| (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2))
            .filter(|d| *d <= bound)
            .min_by(f32::total_cmp)
    }

    fn position(i: u32) -> [f32; 3] {
        let f = i.wrapping_mul(2_654_435_761) as f32;
        [
            (f * 1.3e-4).sin() * 0.03,
            (f * 3.1e-5).cos() * 0.03,
            (f * 7.2e-5).sin() * 0.03,
        ]
    }

    /// Every count from empty to several blocks, with removals from the front, middle and end:
    /// the scan finds what a brute-force search finds, never an empty lane, and the slots stay
    /// the ones inserted and not removed.
    #[test]
    fn scan_matches_brute_force_through_pushes_and_removals() {
        for count in 0..13u32 {
            let mut voxel = VoxelPoints::default();
            let mut expected: Vec<([f32; 3], u32)> = Vec::new();
            for i in 0..count {
                voxel.push(position(i), 100 + i);
                expected.push((position(i), 100 + i));
            }
            for removal in [0usize, 5, usize::MAX] {
                if expected.is_empty() {
                    break;
                }
                let at = removal.min(expected.len() - 1);
                let slot = expected[at].1;
                assert!(voxel.remove_slot(slot));
                assert!(!voxel.remove_slot(slot), "removed twice");
                let last = expected.pop().unwrap();
                if at < expected.len() {
                    expected[at] = last;
                }
                assert_eq!(voxel.len, expected.len());
                assert_eq!(
                    voxel.slots().collect::<Vec<_>>(),
                    expected.iter().map(|e| e.1).collect::<Vec<_>>()
                );
                for q in 0..20u32 {
                    let query = position(1000 + q);
                    for bound in [1e-4f32, 4e-4, f32::INFINITY] {
                        let mut best_sq = bound;
                        let found = voxel.nearest(query, &mut best_sq);
                        let truth = brute_nearest(&expected, query, bound);
                        assert_eq!(found.map(|f| f.1), truth, "count {count} bound {bound}");
                        if let Some((slot, d)) = found {
                            assert_eq!(best_sq, d);
                            let (p, _) = expected.iter().find(|e| e.1 == slot).unwrap();
                            let dp = (p[0] - query[0]).powi(2)
                                + (p[1] - query[1]).powi(2)
                                + (p[2] - query[2]).powi(2);
                            assert_eq!(dp, d, "the slot returned is the point measured");
                        } else {
                            assert_eq!(best_sq, bound, "bound unchanged without a match");
                        }
                    }
                }
            }
            assert_eq!(voxel.is_empty(), expected.is_empty());
        }
    }
}
