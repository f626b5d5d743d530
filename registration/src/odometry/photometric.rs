//! The photometric term's images on the ordinary path (docs/method.md, One agent: Tracking,
//! "Photometric term"): the current frame's, its colour camera's motion when its colour image
//! was taken apart from its depth image, and the reference a placed frame becomes.

use nalgebra::Isometry3;

use super::prediction::ConstantVelocity;
use super::{FrameInput, Odometry, OdometryMode};
use crate::photometric::{ColourMotion, PhotometricFrame, PhotometricReference};

impl Odometry {
    /// The current frame's images for the photometric term: frame-to-model, with colour of the
    /// depth camera's size, when the term is on.
    pub(super) fn photometric_frame(&self, input: &FrameInput<'_>) -> Option<PhotometricFrame> {
        let config = &self.tracking.photometric;
        if self.mode != OdometryMode::FrameToModel || !config.enabled() {
            return None;
        }
        PhotometricFrame::new(input.rgb?, input.intrinsics, config.level)
    }

    /// How the current frame's colour camera moves with the pose tried, when its colour image
    /// was taken apart from its depth image and the offset is modelled.
    pub(super) fn colour_motion(
        &self,
        input: &FrameInput<'_>,
        world_from_previous: &Isometry3<f64>,
    ) -> Option<ColourMotion> {
        let offset_s = input.colour_offset_s;
        if !self.tracking.photometric.model_colour_offset
            || offset_s == 0.0
            || !offset_s.is_finite()
        {
            return None;
        }
        self.depth_since_previous_s.map(|span_s| ColourMotion {
            world_from_previous: *world_from_previous,
            steps: offset_s / span_s,
        })
    }

    /// The placed frame becomes the photometric term's reference (none without images).
    pub(super) fn note_photometric_reference(
        &mut self,
        frame: Option<PhotometricFrame>,
        input: &FrameInput<'_>,
        world_from_camera: &Isometry3<f64>,
    ) {
        // The reference's colour camera a moment before or after its depth camera, at the
        // velocity of the step that placed it: in a fast turn a colour image 10 ms off its depth
        // image sees the scene a degree turned, as much as the term otherwise resolves.
        let colour_from_depth = if self.tracking.photometric.model_colour_offset {
            // The step's motion over the time between its depth images.
            let step = ConstantVelocity {
                span_s: self.depth_since_previous_s,
                ..self.velocity
            };
            step.now_from_later(input.colour_offset_s).inverse()
        } else {
            Isometry3::identity()
        };
        self.photometric_reference = frame.map(|frame| {
            PhotometricReference::select(
                &frame.with_colour_from_depth(colour_from_depth),
                input.depth,
                world_from_camera,
                &self.tracking.photometric,
                self.tracking.truncation_m,
            )
        });
    }
}
