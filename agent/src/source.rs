//! The agent's frame source: frames of its dataset range in order, decoded ahead of time on worker
//! threads, with the input hygiene SLAM needs before tracking sees a frame:
//! - a missing frame (file not there) is skipped with a warning and counted;
//! - a broken frame (corrupt image, wrong bit depth, wrong size, bad pose file) is skipped with an
//!   error log naming the file, and counted; the run goes on, nothing computed is lost;
//! - a frame whose ground-truth pose file is broken (truncated, NaN, not rigid) is tracked and
//!   mapped as usual, with a warning naming the file, and counted: only the evaluation, which
//!   needs ground truth, leaves it out;
//! - NaN, infinite and negative depth become invalid (0) and are counted;
//! - a frame with no valid depth at all is still yielded (tracking must see the gap in time) but
//!   flagged, so the mapper can leave the map untouched;
//! - robustness-protocol noise is added when configured (seeded per frame number);
//! - a dataset damaged part way (a bag cut short) gives its frames before the damage, with an
//!   error log and the damage in the statistics.
//!
//! A live ROS 2 camera ([`FrameSource::live`]) gives frames as they arrive, each pair the camera
//! sent that could not be decoded counted as broken, and ends on a stop request or after
//! `[ros2] idle_timeout_s` without a frame.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use datasets::live::{LiveNext, LiveReport, LiveTopics};
use serde::Serialize;

use crate::run::AgentOptions;
use datasets::noise::NoiseConfig;
use datasets::prefetch::Prefetcher;
use datasets::{Dataset, Frame};
use geometry::files::DatasetError;

/// metrics.json's `live`: a live camera's topics and how its frames ended.
#[derive(Debug, Clone, Serialize)]
pub struct LiveInputReport {
    /// The camera's namespace, domain and what its subscriptions received, paired and dropped
    /// (flattened into `live`).
    #[serde(flatten)]
    pub topics: LiveReport,
    /// Why the frames ended (a stop request, no frame for `[ros2] idle_timeout_s`, ...).
    pub end: Option<String>,
    /// From a frame's stamp to its pose being placed (the wall clock then minus the stamp),
    /// milliseconds, over the frames placed: median and 99th percentile. Absent when the
    /// stamps are plainly another clock's, as for stamp to arrival.
    pub stamp_to_pose_ms_median: Option<f64>,
    /// The 99th percentile of the same latencies, milliseconds; absent whenever the median is.
    pub stamp_to_pose_ms_p99: Option<f64>,
}

impl LiveInputReport {
    /// `camera`'s report with the run's end and its stamp-to-pose latencies.
    pub fn new(camera: &LiveTopics, end: Option<String>, stamp_to_pose_ms: &[f64]) -> Self {
        let agrees = |ms: &f64| ms.abs() < datasets::live::CLOCK_AGREEMENT_MS;
        let median = metrics::stats::median(stamp_to_pose_ms).filter(agrees);
        Self {
            topics: camera.report(),
            end,
            stamp_to_pose_ms_median: median,
            stamp_to_pose_ms_p99: median
                .and_then(|_| metrics::stats::quantile(stamp_to_pose_ms, 0.99)),
        }
    }
}

/// The agent's frames: the dataset, and the live camera itself when the dataset is one (its
/// frames come as they arrive).
pub type OpenedFrames = (Arc<dyn Dataset>, Option<Arc<LiveTopics>>);

/// Opens the agent's frames: a dataset (folder, bag, synthetic scene) or a live camera.
pub fn open_frames(options: &AgentOptions) -> anyhow::Result<OpenedFrames> {
    if datasets::live::is_live(&options.dataset) {
        if options.frames != datasets::FrameRange::ALL {
            anyhow::bail!(
                "{}: a live camera takes no frame range (got {})",
                options.dataset,
                options.frames
            );
        }
        let camera = Arc::new(
            LiveTopics::open(
                &options.dataset,
                &options.config.ros2,
                options.agent_id as usize,
                options.eval_every,
            )
            .with_context(|| format!("subscribing to {}", options.dataset))?,
        );
        return Ok((camera.clone(), Some(camera)));
    }
    let dataset = datasets::open_with(
        &options.dataset,
        options.frames,
        &options.config.dataset_options(),
    )
    .with_context(|| format!("opening dataset {}", options.dataset))?;
    Ok((Arc::from(dataset), None))
}

/// Decoded frames kept ready per decoding thread: enough to hide a slow PNG, small enough to
/// bound memory (a 640x480 RGB-D frame is about 2 MB).
pub const QUEUE_PER_WORKER: usize = 4;

/// What the source has seen so far.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SourceStats {
    /// Frames handed to the caller.
    pub frames_yielded: usize,
    /// Frames skipped because their files are missing.
    pub frames_missing: usize,
    /// Frames skipped because they could not be decoded or validated.
    pub frames_broken: usize,
    /// Yielded frames without a single valid depth pixel.
    pub frames_without_depth: usize,
    /// Yielded frames whose ground-truth pose file is there but broken: tracked, left out of the
    /// evaluation.
    pub ground_truth_broken: usize,
    /// Depth pixels that were NaN, infinite or negative and were made invalid.
    pub depth_pixels_sanitized: usize,
    /// Where the dataset is damaged (a bag cut short): its frames end there.
    pub dataset_damage: Option<String>,
    /// A live camera: why its frames ended (idle, stopped, lost).
    pub live_end: Option<String>,
}

/// A frame ready for tracking, with what the source did to it.
#[derive(Debug, Clone)]
pub struct SourceFrame {
    /// The frame, depth sanitised and noise added when configured.
    pub frame: Frame,
    /// Position of the frame in the dataset (0-based, in range order).
    pub position: usize,
    /// False when the frame has no valid depth pixel: track nothing, map nothing.
    pub has_depth: bool,
}

/// The agent's frames in order, an iterator of [`SourceFrame`]s: a dataset decoded ahead on
/// worker threads ([`Self::new`]) or a live camera ([`Self::live`]). See the module documentation.
pub struct FrameSource<'a> {
    frames: Frames<'a>,
    noise: Option<NoiseConfig>,
    stats: SourceStats,
}

enum Frames<'a> {
    Recorded(Prefetcher),
    Live(LiveFrames<'a>),
}

struct LiveFrames<'a> {
    camera: Arc<LiveTopics>,
    stop: &'a AtomicBool,
    /// None: only a stop request ends the run.
    idle_timeout: Option<Duration>,
    last_frame: Instant,
}

/// How long a live source waits for a frame before it looks at the stop flag again.
const LIVE_WAIT: Duration = Duration::from_millis(200);

impl<'a> FrameSource<'a> {
    /// Streams `dataset` with `decode_workers` decoding threads, adding `noise` if given.
    pub fn new(
        dataset: Arc<dyn Dataset>,
        decode_workers: usize,
        noise: Option<NoiseConfig>,
    ) -> Self {
        let dataset_damage = dataset.damage();
        if let Some(damage) = &dataset_damage {
            tracing::error!(
                %damage,
                "the dataset is damaged: the run uses the frames before the damage"
            );
        }
        Self {
            frames: Frames::Recorded(Prefetcher::new(dataset, decode_workers, QUEUE_PER_WORKER)),
            noise,
            stats: SourceStats {
                dataset_damage,
                ..SourceStats::default()
            },
        }
    }

    /// Streams a live camera until `stop` is set or no frame came for `idle_timeout_s` seconds
    /// (0: no limit).
    pub fn live(
        camera: Arc<LiveTopics>,
        noise: Option<NoiseConfig>,
        stop: &'a AtomicBool,
        idle_timeout_s: f64,
    ) -> Self {
        Self {
            frames: Frames::Live(LiveFrames {
                camera,
                stop,
                idle_timeout: (idle_timeout_s > 0.0)
                    .then(|| Duration::from_secs_f64(idle_timeout_s)),
                last_frame: Instant::now(),
            }),
            noise,
            stats: SourceStats::default(),
        }
    }

    /// What the source has seen so far.
    pub fn stats(&self) -> &SourceStats {
        &self.stats
    }

    /// Frames the dataset range holds, skipped ones included; for a live camera, those received
    /// so far.
    pub fn len(&self) -> usize {
        match &self.frames {
            Frames::Recorded(frames) => frames.len(),
            Frames::Live(live) => live.camera.len(),
        }
    }

    /// Whether [`Self::len`] is 0.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Prepares one decoded frame: depth hygiene, noise, bookkeeping.
    fn prepare(&mut self, position: usize, mut frame: Frame) -> SourceFrame {
        if let Some(error) = &frame.ground_truth_error {
            tracing::warn!(
                frame = frame.index,
                %error,
                "ground-truth pose unusable: the frame is tracked but left out of the evaluation"
            );
            self.stats.ground_truth_broken += 1;
        }
        let sanitized = frame.depth.sanitize();
        if sanitized > 0 {
            tracing::warn!(
                frame = frame.index,
                pixels = sanitized,
                "non-finite or negative depth made invalid"
            );
            self.stats.depth_pixels_sanitized += sanitized;
        }
        if let Some(noise) = &self.noise {
            noise.apply(&mut frame);
        }
        let has_depth = frame.depth.valid_count() > 0;
        if !has_depth {
            tracing::warn!(
                frame = frame.index,
                "frame has no valid depth: it will not be tracked or mapped"
            );
            self.stats.frames_without_depth += 1;
        }
        self.stats.frames_yielded += 1;
        SourceFrame {
            frame,
            position,
            has_depth,
        }
    }

    /// Counts and logs a frame that cannot be used.
    fn skip(&mut self, error: &DatasetError) {
        if error.is_missing_frame() {
            tracing::warn!(%error, "skipping missing frame");
            self.stats.frames_missing += 1;
        } else {
            tracing::error!(%error, "skipping broken frame");
            self.stats.frames_broken += 1;
        }
    }
}

impl FrameSource<'_> {
    /// The next live frame, or why the live run ends.
    fn next_live(&mut self) -> Result<(usize, Frame), String> {
        let Frames::Live(live) = &mut self.frames else {
            unreachable!("next_live on a recorded source")
        };
        loop {
            if live.stop.load(Ordering::Relaxed) {
                return Err("stop requested".into());
            }
            let next = live
                .camera
                .next_frame(LIVE_WAIT)
                .map_err(|e| format!("the camera's topics were lost: {e}"))?;
            match next {
                LiveNext::Frame(frame) => {
                    live.last_frame = Instant::now();
                    return Ok((frame.index, *frame));
                }
                LiveNext::Waiting => {
                    if let Some(timeout) = live.idle_timeout
                        && live.last_frame.elapsed() >= timeout
                    {
                        let report = live.camera.report();
                        return Err(format!(
                            "no frame for {:.1} s (received {} colour and {} depth images, \
                             {} paired)",
                            timeout.as_secs_f64(),
                            report.counts.colour_received,
                            report.counts.depth_received,
                            report.counts.pairing.paired
                        ));
                    }
                }
                LiveNext::Broken(error) => {
                    tracing::error!(%error, "skipping a live frame that cannot be used");
                    self.stats.frames_broken += 1;
                }
            }
        }
    }
}

impl Iterator for FrameSource<'_> {
    type Item = SourceFrame;

    fn next(&mut self) -> Option<SourceFrame> {
        loop {
            let (position, result) = match &mut self.frames {
                Frames::Recorded(frames) => frames.next()?,
                Frames::Live(_) => match self.next_live() {
                    Ok((position, frame)) => (position, Ok(frame)),
                    Err(end) => {
                        if self.stats.live_end.is_none() {
                            tracing::info!(reason = %end, "the live camera's frames end here");
                            self.stats.live_end = Some(end);
                        }
                        return None;
                    }
                },
            };
            match result {
                Ok(frame) => return Some(self.prepare(position, frame)),
                Err(error) => self.skip(&error),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use datasets::FrameRange;
    use datasets::seven_scenes::{SevenScenes, SevenScenesWriter};
    use geometry::camera::Intrinsics;
    use geometry::depth::DepthImage;
    use nalgebra::Isometry3;

    fn frame(index: usize, depth_value: f32) -> Frame {
        let (w, h) = (8, 6);
        let mut depth = DepthImage::new(w, h);
        depth.data.iter_mut().for_each(|d| *d = depth_value);
        Frame {
            index,
            timestamp: index as f64 / 30.0,
            rgb: image::RgbImage::from_pixel(w, h, image::Rgb([100, 150, 200])),
            depth,
            world_from_camera_gt: Some(Isometry3::identity()),
            ground_truth_error: None,
            colour_offset_s: 0.0,
            intrinsics: Intrinsics::new(10.0, 10.0, 3.5, 2.5, w, h),
        }
    }

    #[test]
    fn skips_missing_and_broken_frames_and_counts_them() {
        let dir = tempfile::tempdir().unwrap();
        let mut writer = SevenScenesWriter::create(dir.path(), &frame(0, 1.0).intrinsics).unwrap();
        for i in 0..6 {
            // Frame 4 has no valid depth at all.
            writer
                .write(&frame(i, if i == 4 { 0.0 } else { 1.5 }))
                .unwrap();
        }
        writer.finish().unwrap();
        std::fs::remove_file(dir.path().join("frame-000001.depth.png")).unwrap();
        std::fs::write(dir.path().join("frame-000002.color.png"), b"corrupt").unwrap();
        let dataset = Arc::new(SevenScenes::open(dir.path(), FrameRange::ALL).unwrap());
        let mut source = FrameSource::new(dataset, 2, None);
        let yielded: Vec<(usize, bool)> = source
            .by_ref()
            .map(|f| (f.frame.index, f.has_depth))
            .collect();
        assert_eq!(yielded, vec![(0, true), (3, true), (4, false), (5, true)]);
        let stats = source.stats();
        assert_eq!(
            (
                stats.frames_missing,
                stats.frames_broken,
                stats.frames_without_depth
            ),
            (1, 1, 1)
        );
        assert_eq!(stats.frames_yielded, 4);
    }

    /// A source producing non-finite depth (a float depth sensor or a broken driver).
    struct NanDepth;
    impl Dataset for NanDepth {
        fn describe(&self) -> String {
            "nan depth".into()
        }
        fn intrinsics(&self) -> Intrinsics {
            frame(0, 1.0).intrinsics
        }
        fn len(&self) -> usize {
            2
        }
        fn frame_index(&self, position: usize) -> usize {
            position
        }
        fn timestamp(&self, position: usize) -> f64 {
            position as f64
        }
        fn ground_truth(&self, _: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
            Ok(None)
        }
        fn load(&self, position: usize) -> Result<Frame, DatasetError> {
            let mut f = frame(position, 2.0);
            f.depth.data[0] = f32::NAN;
            f.depth.data[1] = f32::INFINITY;
            f.depth.data[2] = -3.0;
            Ok(f)
        }
    }

    #[test]
    fn non_finite_depth_becomes_invalid_and_noise_is_applied() {
        let noise = NoiseConfig::default();
        let mut source = FrameSource::new(Arc::new(NanDepth), 1, Some(noise));
        let frames: Vec<SourceFrame> = source.by_ref().collect();
        assert_eq!(frames.len(), 2);
        for f in &frames {
            assert!(f.frame.depth.data[..3].iter().all(|&d| d == 0.0));
            assert!(
                f.frame
                    .depth
                    .data
                    .iter()
                    .all(|d| d.is_finite() && *d >= 0.0)
            );
            // Depth noise moved the valid pixels off their clean value.
            assert!(f.frame.depth.data[3..].iter().any(|&d| d != 2.0));
        }
        assert_eq!(source.stats().depth_pixels_sanitized, 6);
    }
}
