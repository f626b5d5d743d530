//! A live ROS 2 camera as a frame source, written `ros2:NAMESPACE` (`ros2:/robot0`; `ros2` alone
//! takes `[ros2] namespace`): the `[ros2]` topics under that namespace, received over DDS by
//! [`ros2::live::LiveCamera`] (docs/ros2.md, Live topics).
//!
//! Frames come as the camera sends them ([`LiveTopics::next_frame`]); intrinsics and the lens
//! come from the first CameraInfo, which [`LiveTopics::open`] waits for. The run is also
//! recorded as a [`Dataset`], so that what needs frames after the fact (the map evaluation)
//! reads them like any dataset's: every frame's stamp, and the frames themselves at evenly
//! spaced positions (every `evaluation_every`-th, thinned by half whenever more than
//! `[ros2] evaluation_frames` would be held), since a live run has no files to read again.

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::time::Duration;

use geometry::camera::Intrinsics;
use geometry::distortion::Distortion;
use geometry::files::DatasetError;
use nalgebra::Isometry3;
use ros2::live::{LiveCamera, LiveCounts, LiveOptions, LivePair};
use serde::Serialize;

use crate::rosbag::{Ros2Config, distortion_of, intrinsics_of};
use crate::undistort::Undistortion;
use crate::{Dataset, Frame};

/// The spec prefix of a live camera.
pub const SPEC_PREFIX: &str = "ros2";

/// True when `spec` names a live camera (`ros2` or `ros2:NAMESPACE`).
pub fn is_live(spec: &str) -> bool {
    spec == SPEC_PREFIX || spec.starts_with("ros2:")
}

/// The namespace a live spec names, or the configured one.
pub fn namespace_of(spec: &str, config: &Ros2Config) -> String {
    match spec.strip_prefix("ros2:") {
        Some(namespace) if !namespace.is_empty() => namespace.to_string(),
        _ => config.namespace.clone(),
    }
}

/// What [`LiveTopics::next_frame`] found.
pub enum LiveNext {
    /// A frame, ready for tracking.
    Frame(Box<Frame>),
    /// Nothing arrived within the wait.
    Waiting,
    /// A pair arrived but could not be turned into a frame (the error names the topic and
    /// stamp); counted, and the run goes on.
    Broken(DatasetError),
}

/// What a live run received, paired, dropped and could not use: metrics.json's `live`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LiveReport {
    /// The namespace the camera's topics were under (`/robot0`; empty for none).
    pub namespace: String,
    /// The DDS domain the topics were received on.
    pub domain_id: u16,
    /// What the subscriptions received, paired and dropped (its fields sit beside these in
    /// metrics.json).
    #[serde(flatten)]
    pub counts: LiveCounts,
    /// Pairs handed to the agent as frames.
    pub frames: u64,
    /// Pairs whose images could not be decoded or did not match the CameraInfo.
    pub decode_errors: u64,
    /// Median time from a pair's arrival to its frame being handed over (decoding,
    /// undistortion), milliseconds.
    pub handover_ms_median: Option<f64>,
    /// Median of the wall clock at arrival minus the header stamp, milliseconds: the transport
    /// latency when the publisher stamps with this host's clock; absent when the stamps are
    /// plainly another clock's (more than 10 s away).
    pub stamp_to_arrival_ms_median: Option<f64>,
}

struct Recording {
    stamps: Vec<f64>,
    retained: BTreeMap<usize, Frame>,
    /// Positions retained are the multiples of this.
    stride: usize,
    decode_errors: u64,
    handover_ms: Vec<f64>,
    stamp_to_arrival_ms: Vec<f64>,
}

/// A live camera (see the module documentation).
pub struct LiveTopics {
    camera: LiveCamera,
    namespace: String,
    /// The recorded camera (CameraInfo's K).
    recorded: Intrinsics,
    /// The pinhole camera frames are handed over in (the recorded one, undistorted).
    intrinsics: Intrinsics,
    undistortion: Option<Undistortion>,
    evaluation_frames: usize,
    recording: Mutex<Recording>,
}

/// How long to wait for the depth's CameraInfo once colour's came (both come with every frame).
const DEPTH_CAMERA_INFO_WAIT: Duration = Duration::from_secs(1);

/// A median stamp-to-arrival gap beyond this says the publisher's stamps are not this host's
/// clock (a replayed recording): no latency is reported then.
pub const CLOCK_AGREEMENT_MS: f64 = 10_000.0;

/// Latency samples kept for the medians: the latest ones (a long run keeps its recent past).
const LATENCY_SAMPLES: usize = 4096;

impl LiveTopics {
    /// Subscribes to the camera named by `spec` and waits up to `[ros2] wait_for_camera_s` for
    /// its first CameraInfo. `evaluation_every`: the frames the evaluation will ask for.
    pub fn open(
        spec: &str,
        config: &Ros2Config,
        agent_id: usize,
        evaluation_every: usize,
    ) -> Result<Self, DatasetError> {
        let namespace = namespace_of(spec, config);
        let qualified = |topic: &str| format!("{}{}", namespace.trim_end_matches('/'), topic);
        let options = LiveOptions {
            domain_id: config.domain_id(),
            node_name: format!("mac_ego3d_agent{agent_id}"),
            colour_topic: qualified(&config.colour_topic),
            depth_topic: qualified(&config.depth_topic),
            camera_info_topic: qualified(&config.camera_info_topic),
            depth_camera_info_topic: Some(crate::rosbag::camera_info_beside(&qualified(
                &config.depth_topic,
            )))
            .filter(|topic| *topic != qualified(&config.camera_info_topic)),
            pairing_tolerance_s: config.pairing_tolerance_s,
            reliable: config.reliable,
            queue_pairs: config.queue_pairs,
        };
        let camera = LiveCamera::connect(options.clone())
            .map_err(|e| DatasetError::Invalid(format!("{spec}: {e}")))?;
        let wait = Duration::from_secs_f64(config.wait_for_camera_s);
        let info = camera
            .camera_info(wait)
            .map_err(|e| DatasetError::Invalid(format!("{spec}: {e}")))?
            .ok_or_else(|| {
                DatasetError::Invalid(format!(
                    "{spec}: no CameraInfo on {} within {} s (domain {}): is the camera \
                     publishing, on this ROS_DOMAIN_ID, and reachable from this host?",
                    options.camera_info_topic, config.wait_for_camera_s, options.domain_id
                ))
            })?;
        let invalid = |reason: String| {
            DatasetError::Invalid(format!("{}: {reason}", options.camera_info_topic))
        };
        let recorded = intrinsics_of(&info).map_err(invalid)?;
        // A depth CameraInfo with a K of its own says the depth is an ideal pinhole image with
        // that K (a Kinect's registration), not the colour lens's grid: colour is re-projected
        // into it, as for a bag or a folder with depth-intrinsics.txt. The driver publishes it
        // with every frame, beside the colour one; a camera without one has depth on colour's
        // grid (a RealSense's aligned depth, whose CameraInfo is colour's).
        let depth_info = match &options.depth_camera_info_topic {
            Some(_) => camera
                .depth_camera_info(DEPTH_CAMERA_INFO_WAIT)
                .map_err(|e| DatasetError::Invalid(format!("{spec}: {e}")))?,
            None => None,
        };
        let depth_pinhole = match (&depth_info, &options.depth_camera_info_topic) {
            (Some(depth_info), Some(topic)) if depth_info.k != info.k => Some(
                intrinsics_of(depth_info)
                    .map_err(|reason| DatasetError::Invalid(format!("{topic}: {reason}")))?,
            ),
            _ => None,
        };
        if let Some(k) = depth_pinhole
            && (k.width, k.height) != (recorded.width, recorded.height)
        {
            return Err(DatasetError::Invalid(format!(
                "{}: depth is {}x{}, the colour camera {}x{}",
                options
                    .depth_camera_info_topic
                    .as_deref()
                    .unwrap_or_default(),
                k.width,
                k.height,
                recorded.width,
                recorded.height
            )));
        }
        let output = depth_pinhole.unwrap_or(recorded);
        let distortion = distortion_of(&info)
            .map_err(invalid)?
            .filter(|d: &Distortion| !d.is_zero());
        let undistortion = match (distortion, depth_pinhole) {
            (None, None) => None,
            (distortion, _) => Some(Undistortion::new(
                recorded,
                distortion.unwrap_or_default(),
                output,
            )),
        };
        tracing::info!(
            namespace,
            fx = recorded.fx,
            width = recorded.width,
            height = recorded.height,
            undistorted = undistortion.is_some(),
            depth_pinhole_fx = depth_pinhole.map(|k| k.fx),
            "live camera found"
        );
        Ok(Self {
            camera,
            namespace,
            recorded,
            intrinsics: output,
            undistortion,
            evaluation_frames: config.evaluation_frames.max(1),
            recording: Mutex::new(Recording {
                stamps: Vec::new(),
                retained: BTreeMap::new(),
                stride: evaluation_every.max(1),
                decode_errors: 0,
                handover_ms: Vec::new(),
                stamp_to_arrival_ms: Vec::new(),
            }),
        })
    }

    /// The next frame, waiting up to `timeout`.
    pub fn next_frame(&self, timeout: Duration) -> Result<LiveNext, DatasetError> {
        let pair = match self.camera.next_pair(timeout) {
            Ok(Some(pair)) => pair,
            Ok(None) => return Ok(LiveNext::Waiting),
            Err(e) => return Err(DatasetError::Invalid(format!("{}: {e}", self.namespace))),
        };
        let mut recording = self.recording.lock().expect("live recording");
        let position = recording.stamps.len();
        let frame = match self.frame_of(&pair, position) {
            Ok(frame) => frame,
            Err(error) => {
                recording.decode_errors += 1;
                return Ok(LiveNext::Broken(error));
            }
        };
        recording.stamps.push(pair.stamp_s);
        push_sample(
            &mut recording.handover_ms,
            pair.received_at.elapsed().as_secs_f64() * 1e3,
        );
        push_sample(
            &mut recording.stamp_to_arrival_ms,
            (pair.received_wall_s - pair.stamp_s) * 1e3,
        );
        if position.is_multiple_of(recording.stride) {
            recording.retained.insert(position, frame.clone());
            if recording.retained.len() > self.evaluation_frames {
                // Keep every other one: evenly spaced again, at twice the stride.
                recording.stride *= 2;
                let stride = recording.stride;
                recording.retained.retain(|p, _| p.is_multiple_of(stride));
            }
        }
        Ok(LiveNext::Frame(Box::new(frame)))
    }

    fn frame_of(&self, pair: &LivePair, position: usize) -> Result<Frame, DatasetError> {
        let fail = |topic: &str, reason: &dyn std::fmt::Display| {
            DatasetError::Invalid(format!("{topic} at stamp {:.6}: {reason}", pair.stamp_s))
        };
        let options = self.camera.options();
        let rgb = pair
            .colour
            .colour()
            .map_err(|e| fail(&options.colour_topic, &e))?;
        let depth = pair
            .depth
            .depth()
            .map_err(|e| fail(&options.depth_topic, &e))?;
        let expected = (self.recorded.width, self.recorded.height);
        for (topic, size) in [
            (&options.colour_topic, rgb.dimensions()),
            (&options.depth_topic, (depth.width, depth.height)),
        ] {
            if size != expected {
                return Err(fail(
                    topic,
                    &format!(
                        "image is {}x{}, but the CameraInfo says {}x{}",
                        size.0, size.1, expected.0, expected.1
                    ),
                ));
            }
        }
        let (colour_frame, depth_frame) = (
            &pair.colour.header().frame_id,
            &pair.depth.header().frame_id,
        );
        if !colour_frame.is_empty() && !depth_frame.is_empty() && colour_frame != depth_frame {
            return Err(fail(
                &options.depth_topic,
                &format!(
                    "depth is in frame {depth_frame:?}, colour in {colour_frame:?}: depth must be \
                     registered to colour; subscribe to the driver's aligned depth ({}{}) instead",
                    self.namespace.trim_end_matches('/'),
                    Ros2Config::default().depth_topic
                ),
            ));
        }
        let (rgb, depth) = match &self.undistortion {
            // Depth on the colour lens's grid is resampled with colour; depth that is its own
            // pinhole image (`intrinsics` differ from the recorded lens's) already is the output.
            Some(u) if self.intrinsics == self.recorded => (u.rgb(&rgb)?, u.depth(&depth)?),
            Some(u) => (u.rgb(&rgb)?, depth),
            None => (rgb, depth),
        };
        Ok(Frame {
            index: position,
            timestamp: pair.stamp_s,
            rgb,
            depth,
            world_from_camera_gt: None,
            ground_truth_error: None,
            colour_offset_s: 0.0,
            intrinsics: self.intrinsics,
        })
    }

    /// What the subscriptions and the hand-over saw so far.
    pub fn report(&self) -> LiveReport {
        let recording = self.recording.lock().expect("live recording");
        LiveReport {
            namespace: self.namespace.clone(),
            domain_id: self.camera.options().domain_id,
            counts: self.camera.counts(),
            frames: recording.stamps.len() as u64,
            decode_errors: recording.decode_errors,
            handover_ms_median: median(&recording.handover_ms),
            stamp_to_arrival_ms_median: median(&recording.stamp_to_arrival_ms)
                .filter(|ms| ms.abs() < CLOCK_AGREEMENT_MS),
        }
    }
}

fn push_sample(samples: &mut Vec<f64>, value: f64) {
    if samples.len() == LATENCY_SAMPLES {
        samples.remove(0);
    }
    samples.push(value);
}

fn median(samples: &[f64]) -> Option<f64> {
    if samples.is_empty() {
        return None;
    }
    let mut sorted = samples.to_vec();
    sorted.sort_by(f64::total_cmp);
    Some(sorted[sorted.len() / 2])
}

impl Dataset for LiveTopics {
    fn describe(&self) -> String {
        let options = self.camera.options();
        format!(
            "live ROS 2 camera {} + {} (domain {}){}",
            options.colour_topic,
            options.depth_topic,
            options.domain_id,
            if self.undistortion.is_some() {
                ", undistorted"
            } else {
                ""
            }
        )
    }
    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }
    /// The frames received so far.
    fn len(&self) -> usize {
        self.recording.lock().expect("live recording").stamps.len()
    }
    fn frame_index(&self, position: usize) -> usize {
        position
    }
    fn timestamp(&self, position: usize) -> f64 {
        self.recording.lock().expect("live recording").stamps[position]
    }
    fn ground_truth(&self, _position: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
        Ok(None)
    }
    fn can_load(&self, position: usize) -> bool {
        self.recording
            .lock()
            .expect("live recording")
            .retained
            .contains_key(&position)
    }
    fn load(&self, position: usize) -> Result<Frame, DatasetError> {
        self.recording
            .lock()
            .expect("live recording")
            .retained
            .get(&position)
            .cloned()
            .ok_or_else(|| {
                DatasetError::Invalid(format!(
                    "live frame {position} was not kept (a live run keeps evenly spaced frames \
                     for the evaluation only)"
                ))
            })
    }
}
