//! Segments and relocalisation (docs/method.md, One agent: Tracking, "Relocalisation").
//!
//! When every guess fails on `max_consecutive_failures` frames in a row, the tracker no longer
//! knows where the camera is. Rather than restart its map at a guessed pose (which chains the
//! rest of the run onto a pose that may be metres off), it starts a new *segment*: a new map in
//! a frame of its own, whose first camera is its origin. The segments that are placed in the
//! agent's frame (the first one, and every one joined since) form the *root*; their map and a
//! bounded archive of their keyframes are kept aside while the new segment is tracked.
//!
//! At each keyframe of an unjoined segment the tracker tries to relocalise it in the root:
//! 1. place recognition: the archived keyframes most like the current frame (normalised
//!    correlation of small grey thumbnails) are aligned with it by image features, RANSAC and
//!    G-ICP with its depth-agreement verification (registration/src/alignment), which gives the
//!    camera's pose in the root;
//! 2. map registration, every few keyframes: the segment's map points registered to the root
//!    map's by FPFH features and RANSAC (registration/src/map_registration), which gives the
//!    segment's pose in the root directly, also where the images share no texture.
//!
//! A candidate is accepted only if the current frame, placed by it, passes the tracking check
//! against the root map (coarse-to-fine G-ICP, then the depth agreement). Joining moves the
//! segment's map points into the root map and reports `root_from_segment` (one rigid edge between
//! the two segments), so callers move what they kept of the segment too. A segment that is
//! never joined stays in its own frame: its poses are reported with its id and belong to a
//! trajectory of their own, never chained onto the root.

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::Isometry3;
use serde::Serialize;

use crate::alignment::{AlignmentConfig, AlignmentInput, PreparedView, align};

use super::recovery::TrustedFrame;

/// Index of a segment: 0 is the first, counted as they start.
pub type SegmentId = usize;

/// Thumbnail size for place recognition (4:3, like the sensors).
const THUMBNAIL_WIDTH: u32 = 32;
const THUMBNAIL_HEIGHT: u32 = 24;

/// A zero-mean, unit-norm grey thumbnail: the dot product of two is their normalised
/// correlation, 1 for the same view (whatever the exposure), near 0 for unrelated ones.
#[derive(Debug, Clone)]
pub struct Thumbnail(Vec<f32>);

impl Thumbnail {
    /// The image's mean luma (BT.601 weights) over each cell of a 32 x 24 grid, made zero-mean
    /// and unit-norm; all zeros for an image of one uniform brightness.
    pub fn of(rgb: &RgbImage) -> Self {
        let (width, height) = rgb.dimensions();
        let mut sums = vec![0.0f32; (THUMBNAIL_WIDTH * THUMBNAIL_HEIGHT) as usize];
        let mut counts = vec![0u32; sums.len()];
        for (x, y, pixel) in rgb.enumerate_pixels() {
            let cell = (y * THUMBNAIL_HEIGHT / height.max(1)) * THUMBNAIL_WIDTH
                + x * THUMBNAIL_WIDTH / width.max(1);
            let [r, g, b] = pixel.0.map(f32::from);
            sums[cell as usize] += 0.299 * r + 0.587 * g + 0.114 * b;
            counts[cell as usize] += 1;
        }
        let mut values: Vec<f32> = sums
            .iter()
            .zip(&counts)
            .map(|(s, &n)| if n > 0 { s / n as f32 } else { 0.0 })
            .collect();
        let mean = values.iter().sum::<f32>() / values.len() as f32;
        values.iter_mut().for_each(|v| *v -= mean);
        let norm = values.iter().map(|v| v * v).sum::<f32>().sqrt();
        if norm > 0.0 {
            values.iter_mut().for_each(|v| *v /= norm);
        }
        Self(values)
    }

    /// Normalised correlation with `other`, in [-1, 1]; 0 when either image is uniform.
    pub fn similarity(&self, other: &Thumbnail) -> f32 {
        self.0.iter().zip(&other.0).map(|(a, b)| a * b).sum()
    }
}

/// A root keyframe kept for relocalisation: the frame (images, pose, prepared view once an
/// alignment needed it) and its thumbnail for place recognition.
pub struct ArchivedKeyframe {
    /// Its pose is in the archive's frame: the root's, or a detached segment's until the segment
    /// is joined and its archive moved into the root ([`KeyframeArchive::transform`]).
    pub frame: TrustedFrame,
    thumbnail: Thumbnail,
}

impl ArchivedKeyframe {
    /// Keeps the frame and computes its thumbnail; the prepared view (features) is built only
    /// when an alignment first needs it.
    pub fn of(frame: TrustedFrame) -> Self {
        Self {
            thumbnail: Thumbnail::of(&frame.rgb),
            frame,
        }
    }
}

/// The root's keyframes kept for relocalisation, at most `capacity`: when full, every other one
/// is dropped, so the archive thins evenly over the whole run instead of forgetting its start.
pub struct KeyframeArchive {
    keyframes: Vec<ArchivedKeyframe>,
    capacity: usize,
    /// Keep every `keep_every`-th offered keyframe (doubles each time the archive is thinned).
    keep_every: usize,
    offered: usize,
}

impl KeyframeArchive {
    /// An empty archive that keeps at most `capacity` keyframes (0 keeps none).
    pub fn new(capacity: usize) -> Self {
        Self {
            keyframes: Vec::new(),
            capacity,
            keep_every: 1,
            offered: 0,
        }
    }

    /// Keyframes kept.
    pub fn len(&self) -> usize {
        self.keyframes.len()
    }

    /// True when no keyframe is kept.
    pub fn is_empty(&self) -> bool {
        self.keyframes.is_empty()
    }

    /// Offers a keyframe; `make` builds it only when it is kept.
    pub fn offer(&mut self, make: impl FnOnce() -> ArchivedKeyframe) {
        if self.capacity == 0 {
            return;
        }
        let kept = self.offered.is_multiple_of(self.keep_every);
        self.offered += 1;
        if !kept {
            return;
        }
        self.keyframes.push(make());
        if self.keyframes.len() > self.capacity {
            let mut index = 0;
            self.keyframes.retain(|_| {
                index += 1;
                index % 2 == 1
            });
            self.keep_every *= 2;
        }
    }

    /// Moves every keyframe by `transform` (a segment joined: its keyframes into the root).
    pub fn transform(&mut self, transform: &Isometry3<f64>) {
        for keyframe in &mut self.keyframes {
            keyframe.frame.world_from_camera = transform * keyframe.frame.world_from_camera;
        }
    }

    /// Takes the other archive's keyframes (a joined segment's, already moved into the root).
    pub fn absorb(&mut self, other: KeyframeArchive) {
        for keyframe in other.keyframes {
            self.offer(|| keyframe);
        }
    }

    /// Place recognition and alignment: the pose in the root frame of the camera that took
    /// (`rgb`, `depth`), from the `candidates` archived keyframes most like it whose alignment is
    /// accepted, best-looking first. Each answer is a guess for the caller's verification.
    pub fn align(
        &self,
        rgb: &RgbImage,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        candidates: usize,
        config: &AlignmentConfig,
    ) -> Vec<Isometry3<f64>> {
        if self.keyframes.is_empty() || candidates == 0 {
            return Vec::new();
        }
        let thumbnail = Thumbnail::of(rgb);
        let mut ranked: Vec<(f32, usize)> = self
            .keyframes
            .iter()
            .enumerate()
            .map(|(i, k)| (k.thumbnail.similarity(&thumbnail), i))
            .collect();
        ranked.sort_by(|a, b| b.0.total_cmp(&a.0));
        let current = PreparedView::new(rgb, depth, intrinsics, config);
        let mut guesses = Vec::new();
        for &(similarity, index) in ranked.iter().take(candidates) {
            let keyframe = &self.keyframes[index].frame;
            let alignment = align(
                AlignmentInput {
                    prepared: &current,
                    depth,
                    intrinsics,
                },
                AlignmentInput {
                    prepared: keyframe.prepared(config),
                    depth: &keyframe.depth,
                    intrinsics: &keyframe.intrinsics,
                },
                config,
            );
            tracing::debug!(
                similarity,
                accepted = alignment.is_accepted(),
                verdict = ?alignment.verdict,
                "relocalisation: alignment with an archived keyframe"
            );
            if alignment.is_accepted() {
                guesses
                    .push(keyframe.world_from_camera * alignment.target_camera_from_source_camera);
            }
        }
        guesses
    }
}

/// A segment joined to the root: `root_from_segment` moves everything of the segment (poses,
/// points) into the root frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SegmentJoin {
    /// The segment joined.
    pub segment: SegmentId,
    /// Maps the segment's frame to the root frame.
    pub root_from_segment: Isometry3<f64>,
    /// Which evidence gave the candidate that passed the check.
    pub evidence: JoinEvidence,
}

impl SegmentJoin {
    /// Moves a pose reported before the join into the root, when it was in the joined segment:
    /// returns the new pose and placement, or `None` when the join does not concern it.
    pub fn moved(
        &self,
        placement: super::Placement,
        world_from_camera: &Isometry3<f64>,
    ) -> Option<(super::Placement, Isometry3<f64>)> {
        (placement == super::Placement::Unjoined(self.segment)).then(|| {
            (
                super::Placement::Root,
                self.root_from_segment * world_from_camera,
            )
        })
    }
}

/// How a segment was placed in the root.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum JoinEvidence {
    /// Place recognition and image-feature alignment with an archived keyframe.
    KeyframeAlignment,
    /// Map registration of the segment's points to the root's.
    MapRegistration,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thumbnails_match_the_same_view_under_another_exposure() {
        let scene = |gain: f32| {
            RgbImage::from_fn(64, 48, |x, y| {
                let v = ((x * 7 + y * 13) % 50) as f32 + if x > 30 { 100.0 } else { 20.0 };
                let v = (v * gain).min(255.0) as u8;
                image::Rgb([v, v, v])
            })
        };
        let other = RgbImage::from_fn(64, 48, |x, y| {
            let v = if y > 20 { 200 } else { 30 } + ((x * 3) % 20) as u8;
            image::Rgb([v, v / 2, v])
        });
        let a = Thumbnail::of(&scene(1.0));
        let darker = Thumbnail::of(&scene(0.6));
        assert!((a.similarity(&a) - 1.0).abs() < 1e-5);
        assert!(a.similarity(&darker) > 0.99);
        assert!(a.similarity(&Thumbnail::of(&other)) < 0.5);
    }

    #[test]
    fn the_archive_thins_evenly_when_full() {
        let mut archive = KeyframeArchive::new(4);
        let keyframe = |i: usize| {
            ArchivedKeyframe::of(TrustedFrame::new(
                RgbImage::new(4, 3),
                DepthImage::new(4, 3),
                Intrinsics::new(4.0, 4.0, 1.5, 1.0, 4, 3),
                Isometry3::translation(i as f64, 0.0, 0.0),
            ))
        };
        for i in 0..12 {
            archive.offer(|| keyframe(i));
        }
        let kept: Vec<f64> = archive
            .keyframes
            .iter()
            .map(|k| k.frame.world_from_camera.translation.x)
            .collect();
        assert!(kept.len() <= 4, "{kept:?}");
        assert_eq!(
            kept.first(),
            Some(&0.0),
            "the start of the run is kept: {kept:?}"
        );
        assert!(kept.windows(2).all(|w| w[1] > w[0]), "{kept:?}");
        assert!(
            *kept.last().unwrap() >= 8.0,
            "the recent end is kept: {kept:?}"
        );
    }
}
