//! [`LiveView`]: the bounded queue the process's threads put items on, and the background thread
//! that owns the rerun stream.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use anyhow::Context;
use crossbeam_channel::{Receiver, Sender, TrySendError};
use geometry::camera::Intrinsics;
use image::RgbImage;
use nalgebra::Isometry3;
use serde::Serialize;

use crate::items::{ClosureLine, FrameItem, Item, Recorder};
use crate::points::ColouredPoints;

/// How much the live view sends, and how long it waits at the end.
#[derive(Debug, Clone)]
pub struct LiveViewSettings {
    /// Items waiting for the background thread before new ones are dropped (64: a few seconds
    /// of frames at most, a few MB of images and points).
    pub queue_capacity: usize,
    /// Points shown of one agent's map (20 000: enough to see the scene fill in, small enough to
    /// log every few seconds).
    pub map_points_max: usize,
    /// An agent's map is logged again at most this often (5 s); the final map always.
    pub map_interval: Duration,
    /// Frame images are binned by an integer factor to at most this width (160 pixels) and
    /// stored as JPEG.
    pub image_max_width: u32,
    /// One frame out of this many (5) carries its colour image; every frame logs its pose.
    pub image_every: usize,
    /// The trajectory line is logged again every this many frames (10) and at the end.
    pub trajectory_every_frames: usize,
    /// [`LiveView::finish`] waits this long (5 s) for the queue to be logged and flushed; a
    /// viewer that takes nothing cannot hold the process longer.
    pub finish_timeout: Duration,
}

impl Default for LiveViewSettings {
    fn default() -> Self {
        Self {
            queue_capacity: 64,
            map_points_max: 20_000,
            map_interval: Duration::from_secs(5),
            image_max_width: 160,
            image_every: 5,
            trajectory_every_frames: 10,
            finish_timeout: Duration::from_secs(5),
        }
    }
}

/// What the live view took and dropped (metrics.json `live_view`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct LiveViewStats {
    /// Items put on the queue (each logged unless `finished` is false).
    pub items_queued: u64,
    /// Items dropped because the queue was full.
    pub items_dropped: u64,
    /// Of those, camera frames.
    pub frames_queued: u64,
    /// Of `items_dropped`, camera frames.
    pub frames_dropped: u64,
    /// The background thread logged every queued item and flushed within the finish timeout.
    pub finished: bool,
}

/// The process's handle on the live view: cheap to clone, shared by its threads. Every method
/// returns at once; [`LiveView::disabled`] does nothing at all.
#[derive(Clone, Default)]
pub struct LiveView {
    shared: Option<Arc<Shared>>,
}

struct Shared {
    items: Sender<Message>,
    done: Receiver<()>,
    settings: LiveViewSettings,
    items_queued: AtomicU64,
    items_dropped: AtomicU64,
    frames_queued: AtomicU64,
    frames_dropped: AtomicU64,
    frames_offered: AtomicU64,
    finish_requested: AtomicBool,
    finished: AtomicBool,
}

enum Message {
    Item(Item),
    Finish,
}

impl std::fmt::Debug for LiveView {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.shared {
            None => f.write_str("LiveView(disabled)"),
            Some(shared) => write!(f, "LiveView({:?})", shared.stats()),
        }
    }
}

impl LiveView {
    /// A live view that logs nothing and costs nothing.
    pub fn disabled() -> Self {
        Self::default()
    }

    /// Logs to a viewer at `viewer_url` (gRPC, `rerun+http://HOST:PORT/proxy`) and / or to the
    /// .rrd file `file`, under `recording_id`.
    pub fn open(
        recording_id: &str,
        viewer_url: Option<&str>,
        file: Option<&Path>,
        settings: LiveViewSettings,
    ) -> anyhow::Result<Self> {
        let mut sinks: Vec<Box<dyn rerun::sink::LogSink>> = Vec::new();
        if let Some(url) = viewer_url {
            let uri = match url.parse::<rerun::external::re_uri::RedapUri>() {
                Ok(rerun::external::re_uri::RedapUri::Proxy(uri)) => uri,
                Ok(_) => anyhow::bail!("--viewer {url}: not a viewer address (…/proxy)"),
                Err(error) => anyhow::bail!("--viewer {url}: {error}"),
            };
            sinks.push(Box::new(rerun::sink::GrpcSink::new(uri)));
        }
        if let Some(path) = file {
            let sink = rerun::sink::FileSink::new(path)
                .with_context(|| format!("--record: cannot write {}", path.display()))?;
            sinks.push(Box::new(sink));
        }
        let stream = rerun::RecordingStreamBuilder::new(crate::APPLICATION_ID)
            .recording_id(recording_id)
            .set_sinks(sinks)
            .context("starting the rerun recording stream")?;
        Self::with_stream(stream, settings)
    }

    /// Logs to `stream` (any sink), through the bounded queue.
    pub fn with_stream(
        stream: rerun::RecordingStream,
        settings: LiveViewSettings,
    ) -> anyhow::Result<Self> {
        let (items_tx, items_rx) = crossbeam_channel::bounded(settings.queue_capacity.max(1));
        let (done_tx, done_rx) = crossbeam_channel::bounded(1);
        let recorder = Recorder::new(stream, settings.clone());
        let flush_timeout = settings.finish_timeout / 2;
        std::thread::Builder::new()
            .name("live-view".into())
            .spawn(move || run_recorder(recorder, items_rx, done_tx, flush_timeout))
            .context("starting the live-view thread")?;
        Ok(Self {
            shared: Some(Arc::new(Shared {
                items: items_tx,
                done: done_rx,
                settings,
                items_queued: AtomicU64::new(0),
                items_dropped: AtomicU64::new(0),
                frames_queued: AtomicU64::new(0),
                frames_dropped: AtomicU64::new(0),
                frames_offered: AtomicU64::new(0),
                finish_requested: AtomicBool::new(false),
                finished: AtomicBool::new(false),
            })),
        })
    }

    /// Whether this handle logs anything (false for [`LiveView::disabled`]): callers skip
    /// gathering what they would show when it does not.
    pub fn is_enabled(&self) -> bool {
        self.shared.is_some()
    }

    /// One tracked frame of agent `agent_id`: the camera pose in the agent's frame, its
    /// intrinsics, and (one frame in `image_every`) its colour image.
    pub fn frame(
        &self,
        agent_id: u32,
        frame_index: usize,
        world_from_camera: &Isometry3<f64>,
        intrinsics: &Intrinsics,
        rgb: &RgbImage,
    ) {
        let Some(shared) = &self.shared else {
            return;
        };
        let offered = shared.frames_offered.fetch_add(1, Ordering::Relaxed);
        let with_image = offered.is_multiple_of(shared.settings.image_every.max(1) as u64);
        let queued = shared.offer(|| {
            Item::Frame(Box::new(FrameItem {
                agent_id,
                frame_index,
                world_from_camera: *world_from_camera,
                intrinsics: *intrinsics,
                rgb: with_image.then(|| rgb.clone()),
            }))
        });
        let counter = if queued {
            &shared.frames_queued
        } else {
            &shared.frames_dropped
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// A keyframe of agent `agent_id`, at its camera pose in the agent's frame.
    pub fn keyframe(&self, agent_id: u32, world_from_camera: &Isometry3<f64>) {
        self.offer(|| Item::Keyframe {
            agent_id,
            world_from_camera: *world_from_camera,
        });
    }

    /// Points added to agent `agent_id`'s map (positions in the agent's frame, colours in 0..1),
    /// at most `map_points_max` of them; `is_final` replaces the map shown so far.
    pub fn map_points(
        &self,
        agent_id: u32,
        positions: &[[f32; 3]],
        colours: &[[f32; 3]],
        is_final: bool,
    ) {
        let Some(shared) = &self.shared else {
            return;
        };
        let max_points = shared.settings.map_points_max;
        shared.offer(|| Item::MapPoints {
            agent_id,
            points: ColouredPoints::sampled(positions, colours, max_points),
            is_final,
        });
    }

    /// Where the consensus placed agent `agent_id`: its frame's transform in the world.
    pub fn agent_placement(&self, agent_id: u32, world_from_agent: &Isometry3<f64>) {
        self.offer(|| Item::AgentPlacement {
            agent_id,
            world_from_agent: *world_from_agent,
        });
    }

    /// Every closure attempt so far (the set shown is replaced).
    pub fn closures(&self, lines: Vec<ClosureLine>) {
        self.offer(|| Item::Closures(lines));
    }

    /// Every agent's keyframe positions in the world after a pose-graph solve.
    pub fn consensus_trajectories(&self, trajectories: BTreeMap<u32, Vec<[f64; 3]>>) {
        self.offer(|| Item::ConsensusTrajectories(trajectories));
    }

    /// The merged world map (colours in 0..1), at most `map_points_max` points of it.
    pub fn merged_map(&self, positions: &[[f32; 3]], colours: &[[f32; 3]]) {
        let Some(shared) = &self.shared else {
            return;
        };
        let max_points = shared.settings.map_points_max;
        shared.offer(|| Item::MergedMap(ColouredPoints::sampled(positions, colours, max_points)));
    }

    /// One value of the time series at `path` (see [`crate::paths`]).
    pub fn scalar(&self, path: impl Into<String>, value: f64) {
        self.offer(|| Item::Scalar {
            path: path.into(),
            value,
        });
    }

    /// What was queued and dropped so far.
    pub fn stats(&self) -> Option<LiveViewStats> {
        self.shared.as_ref().map(|shared| shared.stats())
    }

    /// Asks the background thread to log what is queued, flush and close the stream, and waits
    /// for it at most `finish_timeout`; the final figures. Items offered afterwards are dropped.
    pub fn finish(&self) -> Option<LiveViewStats> {
        let shared = self.shared.as_ref()?;
        if !shared.finish_requested.swap(true, Ordering::Relaxed) {
            let timeout = shared.settings.finish_timeout;
            let finished = shared.items.send_timeout(Message::Finish, timeout).is_ok()
                && shared.done.recv_timeout(timeout).is_ok();
            if !finished {
                tracing::warn!(
                    timeout_s = timeout.as_secs_f64(),
                    "live view: the viewer or recording did not take everything in time; \
                     the rest is dropped"
                );
            }
            shared.finished.store(finished, Ordering::Relaxed);
        }
        Some(shared.stats())
    }

    fn offer(&self, make: impl FnOnce() -> Item) -> bool {
        self.shared
            .as_ref()
            .is_some_and(|shared| shared.offer(make))
    }
}

impl Shared {
    /// Queues the item `make` builds, unless the queue is full (then nothing is built).
    fn offer(&self, make: impl FnOnce() -> Item) -> bool {
        let queued = !self.finish_requested.load(Ordering::Relaxed)
            && !self.items.is_full()
            && match self.items.try_send(Message::Item(make())) {
                Ok(()) => true,
                Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => false,
            };
        let counter = if queued {
            &self.items_queued
        } else {
            &self.items_dropped
        };
        counter.fetch_add(1, Ordering::Relaxed);
        queued
    }

    fn stats(&self) -> LiveViewStats {
        LiveViewStats {
            items_queued: self.items_queued.load(Ordering::Relaxed),
            items_dropped: self.items_dropped.load(Ordering::Relaxed),
            frames_queued: self.frames_queued.load(Ordering::Relaxed),
            frames_dropped: self.frames_dropped.load(Ordering::Relaxed),
            finished: self.finished.load(Ordering::Relaxed),
        }
    }
}

/// The background thread: logs items until asked to finish (or every handle is gone), then the
/// trajectories and maps as they stand, flushes and closes the stream.
fn run_recorder(
    mut recorder: Recorder,
    items: Receiver<Message>,
    done: Sender<()>,
    flush_timeout: Duration,
) {
    let mut failures = 0usize;
    let mut log = |result: rerun::RecordingStreamResult<()>| {
        if let Err(error) = result {
            // Visualisation only: the run goes on; the first failure says why.
            if failures == 0 {
                tracing::warn!(%error, "live view: logging failed");
            }
            failures += 1;
        }
    };
    log(recorder.log_world_axes());
    for message in &items {
        match message {
            Message::Item(item) => log(recorder.log(item)),
            Message::Finish => break,
        }
    }
    log(recorder.log_trajectories());
    log(recorder.log_pending_maps());
    if let Err(error) = recorder.stream().flush_with_timeout(flush_timeout) {
        tracing::warn!(%error, "live view: flushing the rerun stream failed");
    }
    drop(recorder);
    let _ = done.send(());
}
