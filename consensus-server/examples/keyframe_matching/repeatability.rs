//! Repeatability of A's keypoints in B, and how discriminable the repeated ones are, per local
//! rotation, scale change and pyramid level.

use config::AlignmentConfig;
use geometry::camera::Intrinsics;
use nalgebra::Isometry3;

use crate::descriptors::DescriptorTable;
use crate::measure::Truth;
use crate::report::{Bucket, median, wrap_deg};

/// Per bucket: repeatable keypoints, those with a correct nearest neighbour, and the Hamming
/// distances to their true partners.
pub type RawBucket = (usize, usize, Vec<u32>);

pub fn buckets(raw: Vec<RawBucket>, labels: &[&str]) -> Vec<Bucket> {
    raw.into_iter()
        .zip(labels)
        .map(|((repeatable, nn_correct, mut d), label)| Bucket {
            label: label.to_string(),
            repeatable,
            nn_correct,
            median_true_hamming: median(&mut d).unwrap_or(0),
        })
        .collect()
}

/// Repeatability of A's keypoints in B and how discriminable they are, per local rotation,
/// scale change and pyramid level.
pub struct Repeatability {
    pub covisible_a: usize,
    pub repeatable: usize,
    pub nn_correct: usize,
    pub top2_correct: usize,
    pub orientation_errors: Vec<f64>,
    pub by_rotation: Vec<RawBucket>,
    pub by_scale: Vec<RawBucket>,
    /// Per level of A: repeatable keypoints, correct configured matches, correct nearest
    /// neighbours.
    pub by_level: Vec<[usize; 3]>,
    /// Per keypoint of A: 0 not repeatable, 1 repeatable, 2 correct nearest neighbour.
    pub status: Vec<u8>,
}

impl Repeatability {
    pub fn of(truth: &Truth<'_>, table: &DescriptorTable, config: &AlignmentConfig) -> Self {
        let levels = config.pyramid_levels.max(1);
        let mut this = Self {
            covisible_a: 0,
            repeatable: 0,
            nn_correct: 0,
            top2_correct: 0,
            orientation_errors: Vec::new(),
            by_rotation: vec![(0, 0, vec![]); 5],
            by_scale: vec![(0, 0, vec![]); 4],
            by_level: vec![[0usize; 3]; levels],
            status: vec![0u8; truth.a.len()],
        };
        for i in 0..truth.a.len() {
            this.add_keypoint(truth, table, i, levels);
        }
        for i in 0..truth.a.len() {
            let level = truth.a.keypoints[i].level.min(levels - 1);
            if let Some(j) = table.mutual(i, config.max_hamming_distance, config.match_ratio)
                && truth.is_correct(i, j)
            {
                this.by_level[level][1] += 1;
            }
            if let Some(j) = table.nearest(i)
                && truth.is_correct(i, j)
            {
                this.by_level[level][2] += 1;
            }
        }
        this
    }

    /// A's keypoint `i`: covisible, repeatable, and its nearest neighbour's correctness filed
    /// under its local rotation and scale change.
    fn add_keypoint(
        &mut self,
        truth: &Truth<'_>,
        table: &DescriptorTable,
        i: usize,
        levels: usize,
    ) {
        let (fa, fb) = (truth.a, truth.b);
        let kp = fa.keypoints[i];
        if truth.seen_in_b(i).is_some() {
            self.covisible_a += 1;
        }
        let partners: Vec<usize> = (0..table.nb).filter(|&j| truth.is_correct(i, j)).collect();
        if partners.is_empty() {
            return;
        }
        self.repeatable += 1;
        self.by_level[kp.level.min(levels - 1)][0] += 1;
        let true_distance = partners.iter().map(|&j| table.row(i)[j]).min().unwrap();
        let ((best_j, _), (second_j, _)) = table.forward[i];
        let nn_ok = truth.is_correct(i, best_j);
        self.nn_correct += nn_ok as usize;
        self.status[i] = 1 + nn_ok as u8;
        self.top2_correct +=
            (nn_ok || (second_j != usize::MAX && truth.is_correct(i, second_j))) as usize;
        let Some((rotation, scale)) = local_warp(
            &truth.pair.a.intrinsics,
            &truth.pair.b.intrinsics,
            &truth.b_from_a,
            kp.u,
            kp.v,
            fa.camera_points[i].z,
        ) else {
            return;
        };
        // The partner closest in 3-D for the orientation comparison.
        let nearest = *partners
            .iter()
            .min_by(|&&x, &&y| {
                (truth.moved[i] - fb.camera_points[x])
                    .norm()
                    .total_cmp(&(truth.moved[i] - fb.camera_points[y]).norm())
            })
            .unwrap();
        let predicted = kp.angle as f64 + rotation.to_radians();
        self.orientation_errors
            .push(wrap_deg((fb.keypoints[nearest].angle as f64 - predicted).to_degrees()).abs());
        let r = [15.0, 30.0, 60.0, 90.0, 180.0]
            .iter()
            .position(|&e| rotation.abs() < e)
            .unwrap_or(4);
        let s = [1.25, 1.6, 2.0, 100.0]
            .iter()
            .position(|&e| scale.max(1.0 / scale) < e)
            .unwrap_or(3);
        for bucket in [&mut self.by_rotation[r], &mut self.by_scale[s]] {
            bucket.0 += 1;
            bucket.1 += nn_ok as usize;
            bucket.2.push(true_distance);
        }
    }
}

/// In-plane rotation (degrees, from +x towards +y in the image) and scale change of the image
/// neighbourhood of a keypoint of A seen in B, assuming a fronto-parallel patch.
fn local_warp(
    ka: &Intrinsics,
    kb: &Intrinsics,
    b_from_a: &Isometry3<f64>,
    u: f64,
    v: f64,
    z: f64,
) -> Option<(f64, f64)> {
    const STEP: f64 = 10.0;
    let p0 = kb.project(&(b_from_a * ka.back_project(u, v, z)))?;
    let p1 = kb.project(&(b_from_a * ka.back_project(u + STEP, v, z)))?;
    let d = p1 - p0;
    // Image coordinates (y down), the convention of the keypoint orientations.
    Some((d.y.atan2(d.x).to_degrees(), d.norm() / STEP))
}
