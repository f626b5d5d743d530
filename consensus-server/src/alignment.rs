//! Keyframe-to-keyframe alignment in the consensus: the registration crate's
//! [`registration::alignment`] (features, RANSAC, G-ICP, verification; docs/method.md, The
//! consensus: association and alignment) applied to keyframes as the consensus receives them,
//! with the ids of the pair.

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::Isometry3;

use crate::place_recognition::KeyframeRef;
use registration::alignment::{AlignmentConfig, AlignmentInput, PreparedView};
pub use registration::alignment::{CoarseScores, RefinementScores, RejectionReason, Verdict};

/// One keyframe as the consensus receives it.
#[derive(Debug, Clone)]
pub struct Keyframe {
    /// The agent that made the keyframe and its number there.
    pub id: KeyframeRef,
    /// The colour image, registered to `depth` (same size, same camera).
    pub rgb: RgbImage,
    /// Metres, 0 = invalid.
    pub depth: DepthImage,
    /// The pinhole camera of `rgb` and `depth`, in pixels.
    pub intrinsics: Intrinsics,
    /// The keyframe's pose in its agent's own frame (agents start at identity).
    pub agent_from_camera: Isometry3<f64>,
}

/// A keyframe with what alignment computes from it once, however many candidates it is paired
/// with.
pub struct PreparedKeyframe {
    /// The keyframe as received; the depth agreement test projects the other side's points into
    /// its depth image.
    pub keyframe: Keyframe,
    /// The keyframe's lifted keypoints and its point cloud with G-ICP covariances, in its camera
    /// frame.
    pub view: PreparedView,
}

impl PreparedKeyframe {
    /// Computes the keyframe's features and point cloud with `config`'s parameters.
    pub fn new(keyframe: Keyframe, config: &AlignmentConfig) -> Self {
        let _span = tracing::debug_span!("prepare keyframe", id = ?keyframe.id).entered();
        let view = PreparedView::new(&keyframe.rgb, &keyframe.depth, &keyframe.intrinsics, config);
        Self { keyframe, view }
    }

    /// The keyframe as one side of an alignment.
    pub fn input(&self) -> AlignmentInput<'_> {
        AlignmentInput {
            prepared: &self.view,
            depth: &self.keyframe.depth,
            intrinsics: &self.keyframe.intrinsics,
        }
    }
}

/// The outcome of aligning a source keyframe to a target keyframe.
#[derive(Debug, Clone)]
pub struct AlignmentResult {
    /// The keyframe whose camera frame the estimate maps from.
    pub source: KeyframeRef,
    /// The keyframe whose camera frame the estimate maps into.
    pub target: KeyframeRef,
    /// The estimate: refined when refinement ran, the coarse one when refinement failed,
    /// identity when there were too few matches to estimate anything.
    pub target_camera_from_source_camera: Isometry3<f64>,
    /// `None` when there were too few matches to try.
    pub coarse: Option<CoarseScores>,
    /// `None` when refinement did not run or failed.
    pub refinement: Option<RefinementScores>,
    /// Accepted, or rejected with the reason; only an accepted estimate is used.
    pub verdict: Verdict,
}

impl AlignmentResult {
    /// Whether verification accepted the estimate ([`Verdict::Accepted`]).
    pub fn is_accepted(&self) -> bool {
        self.verdict == Verdict::Accepted
    }

    /// The transform between the two agents' frames that this estimate implies:
    /// `target_agent_from_source_agent`.
    pub fn target_agent_from_source_agent(
        &self,
        source_agent_from_camera: &Isometry3<f64>,
        target_agent_from_camera: &Isometry3<f64>,
    ) -> Isometry3<f64> {
        target_agent_from_camera
            * self.target_camera_from_source_camera
            * source_agent_from_camera.inverse()
    }
}

/// Aligns two keyframes; see the module documentation. Prepares both first; use
/// [`align_prepared`] to reuse prepared keyframes across many pairs.
pub fn align(source: Keyframe, target: Keyframe, config: &AlignmentConfig) -> AlignmentResult {
    let source = PreparedKeyframe::new(source, config);
    let target = PreparedKeyframe::new(target, config);
    align_prepared(&source, &target, config)
}

/// Aligns two prepared keyframes.
pub fn align_prepared(
    source: &PreparedKeyframe,
    target: &PreparedKeyframe,
    config: &AlignmentConfig,
) -> AlignmentResult {
    let _span = tracing::info_span!(
        "align",
        source = ?source.keyframe.id,
        target = ?target.keyframe.id
    )
    .entered();
    let alignment = registration::alignment::align(source.input(), target.input(), config);
    AlignmentResult {
        source: source.keyframe.id,
        target: target.keyframe.id,
        target_camera_from_source_camera: alignment.target_camera_from_source_camera,
        coarse: alignment.coarse,
        refinement: alignment.refinement,
        verdict: alignment.verdict,
    }
}
