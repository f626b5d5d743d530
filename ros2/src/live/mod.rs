//! Live ROS 2 topics over DDS, with no ROS installation (docs/ros2.md, Live topics).
//!
//! [`LiveCamera`] joins a DDS domain through ros2-client (RustDDS: standard RTPS discovery, the
//! ROS 2 topic and type name mangling, `rt/...` and `sensor_msgs::msg::dds_::Image_`) and
//! subscribes to a camera's colour, depth and CameraInfo topics. One thread receives; colour and
//! depth are paired by stamp ([`pairing`]) and the pairs wait in a short queue for the consumer,
//! where the newest pair wins: a consumer slower than the camera gets the latest pair, and every
//! pair it never took is counted as dropped. Images are decoded by the consumer, not the
//! receiving thread, so a slow decode never stalls the network.

pub mod pairing;
pub mod publisher;

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use ros2_client::dds::rustdds::mio1::{Events, Interest, Poll, Token};
use ros2_client::qos::{History, QosProfile, WhenFull};
use ros2_client::{Context, ContextOptions, MessageTypeName, Name, NodeName, NodeOptions};
use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::image::ImageError;
use crate::msg::{self, CameraInfo, CompressedImage, Header, Image};
use pairing::{Pairing, PairingCounts};

/// How a live camera is reached.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveOptions {
    /// The DDS domain (`ROS_DOMAIN_ID`).
    pub domain_id: u16,
    /// This node's name (`mac_ego3d_agent0`); it appears in `ros2 node list`.
    pub node_name: String,
    /// Fully qualified topic names. A colour topic ending in `/compressed` carries
    /// `sensor_msgs/CompressedImage`, a depth topic ending in `/compressedDepth` or
    /// `/compressed` too (image_transport's names); any other, `sensor_msgs/Image`.
    pub colour_topic: String,
    /// The depth topic: depth registered to colour, in the colour camera's frame
    /// (`/robot0/camera/camera/aligned_depth_to_color/image_raw`). Its type follows its name,
    /// as for `colour_topic`.
    pub depth_topic: String,
    /// The colour camera's `sensor_msgs/CameraInfo` topic.
    pub camera_info_topic: String,
    /// The depth image's own CameraInfo topic, when one is to be read (a camera that registers
    /// depth into a pinhole of its own, as a Kinect does, says so there).
    pub depth_camera_info_topic: Option<String>,
    /// Largest stamp difference between a colour image and its depth, seconds.
    pub pairing_tolerance_s: f64,
    /// Subscribe reliably: only reliable publishers match. Best effort (false) matches both
    /// kinds, sensor-data publishers included.
    pub reliable: bool,
    /// Pairs waiting for the consumer at most; beyond it the oldest is dropped (1: always the
    /// newest pair).
    pub queue_pairs: usize,
}

/// Why a live camera could not be used.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// A configured topic is not a valid fully qualified ROS 2 name (`/a/b`).
    #[error("ROS 2 topic name {topic:?}: {reason}")]
    TopicName {
        /// The name as configured.
        topic: String,
        /// Why it is refused (no leading `/`, an empty part, a part starting with a digit).
        reason: String,
    },
    /// ros2-client refused the participant, the node, a topic, a subscription or a publisher.
    #[error("joining DDS domain {domain_id}: {reason}")]
    Dds {
        /// The domain being joined.
        domain_id: u16,
        /// What failed, with ros2-client's error.
        reason: String,
    },
    /// The receiving thread did not start, ended before subscribing, or stopped on an error
    /// (polling its readers failed); the reason says which.
    #[error("the ROS 2 receiving thread stopped: {0}")]
    Receiver(String),
    /// A sample could not be published.
    #[error("publishing on {topic}: {reason}")]
    Publish {
        /// The topic published on (`/tf`, `/agent0/path`).
        topic: String,
        /// ros2-client's error.
        reason: String,
    },
}

/// A colour or depth message as it arrived: raw or compressed.
#[derive(Debug, Clone)]
pub enum ImageMessage {
    /// A `sensor_msgs/Image`: the topic's name does not end in `/compressed` or
    /// `/compressedDepth`.
    Raw(Image),
    /// A `sensor_msgs/CompressedImage`: the topic's name ends in `/compressed` or
    /// `/compressedDepth`.
    Compressed(CompressedImage),
}

impl ImageMessage {
    /// The message's header: its capture stamp and the camera frame.
    pub fn header(&self) -> &Header {
        match self {
            Self::Raw(image) => &image.header,
            Self::Compressed(image) => &image.header,
        }
    }

    /// The colour image, whatever its encoding.
    pub fn colour(&self) -> Result<image::RgbImage, ImageError> {
        match self {
            Self::Raw(image) => crate::image::colour_from_image(image),
            Self::Compressed(image) => crate::image::colour_from_compressed(image),
        }
    }

    /// The depth image in metres, whatever its encoding.
    pub fn depth(&self) -> Result<geometry::depth::DepthImage, ImageError> {
        match self {
            Self::Raw(image) => crate::image::depth_from_image(image),
            Self::Compressed(image) => crate::image::depth_from_compressed(image),
        }
    }
}

/// One colour image and its depth, paired by stamp.
#[derive(Debug, Clone)]
pub struct LivePair {
    /// The colour image's stamp, seconds.
    pub stamp_s: f64,
    /// The colour message, not decoded yet ([`ImageMessage::colour`] decodes it).
    pub colour: ImageMessage,
    /// The depth message, not decoded yet ([`ImageMessage::depth`] decodes it).
    pub depth: ImageMessage,
    /// When the second of the two arrived.
    pub received_at: Instant,
    /// The same moment on the wall clock, seconds since the Unix epoch: against `stamp_s` it
    /// is the transport latency when the publisher stamps with the same clock.
    pub received_wall_s: f64,
}

/// What the subscriptions received and what became of it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct LiveCounts {
    /// Colour messages taken from the DDS reader, paired or not.
    pub colour_received: u64,
    /// Depth messages taken from the DDS reader, paired or not.
    pub depth_received: u64,
    /// CameraInfo messages taken, counted once per wake-up of the receiving thread (only the
    /// latest of those that arrived together is kept).
    pub camera_info_received: u64,
    /// What the pairing made of the colour and depth messages (its fields sit beside these in
    /// metrics.json).
    #[serde(flatten)]
    pub pairing: PairingCounts,
    /// Pairs the consumer never took: a newer pair replaced them (the consumer was slower
    /// than the camera).
    pub dropped: u64,
    /// Of `dropped`, those replaced before the consumer took its first pair (it was still
    /// starting).
    pub dropped_while_starting: u64,
    /// Samples the DDS reader could not deserialise (a wrong type on the topic).
    pub read_errors: u64,
}

#[derive(Default)]
struct State {
    pairs: VecDeque<LivePair>,
    camera_info: Option<CameraInfo>,
    depth_camera_info: Option<CameraInfo>,
    counts: LiveCounts,
    /// The consumer has taken a pair.
    taken_any: bool,
    /// Set when the receiving thread ended on an error.
    failed: Option<String>,
}

struct Shared {
    state: Mutex<State>,
    changed: Condvar,
    stop: AtomicBool,
}

/// A camera's topics, subscribed; see the module documentation.
pub struct LiveCamera {
    options: LiveOptions,
    shared: Arc<Shared>,
    receiver: Option<JoinHandle<()>>,
}

/// How often the receiving thread looks at the stop flag when nothing arrives.
const POLL_INTERVAL: Duration = Duration::from_millis(100);

impl LiveCamera {
    /// Joins the domain and subscribes; returns once the subscriptions exist (publishers may
    /// appear later).
    pub fn connect(options: LiveOptions) -> Result<Self, LiveError> {
        let shared = Arc::new(Shared {
            state: Mutex::new(State::default()),
            changed: Condvar::new(),
            stop: AtomicBool::new(false),
        });
        let (started_tx, started_rx) = std::sync::mpsc::channel();
        let thread_shared = shared.clone();
        let thread_options = options.clone();
        let receiver = std::thread::Builder::new()
            .name("ros2-receive".into())
            .spawn(move || {
                let topics = match Subscriptions::create(&thread_options) {
                    Ok(topics) => {
                        let _ = started_tx.send(Ok(()));
                        topics
                    }
                    Err(error) => {
                        let _ = started_tx.send(Err(error));
                        return;
                    }
                };
                if let Err(reason) = topics.receive(&thread_options, &thread_shared) {
                    tracing::error!(%reason, "the ROS 2 receiving thread stopped");
                    thread_shared.state.lock().expect("live state").failed = Some(reason);
                    thread_shared.changed.notify_all();
                }
            })
            .map_err(|e| LiveError::Receiver(e.to_string()))?;
        match started_rx.recv() {
            Ok(Ok(())) => Ok(Self {
                options,
                shared,
                receiver: Some(receiver),
            }),
            Ok(Err(error)) => {
                let _ = receiver.join();
                Err(error)
            }
            Err(_) => {
                let _ = receiver.join();
                Err(LiveError::Receiver("it ended before subscribing".into()))
            }
        }
    }

    /// The options it was connected with.
    pub fn options(&self) -> &LiveOptions {
        &self.options
    }

    /// The latest CameraInfo, waiting up to `timeout` for the first one.
    pub fn camera_info(&self, timeout: Duration) -> Result<Option<CameraInfo>, LiveError> {
        self.wait_for(timeout, |state| state.camera_info.clone())
    }

    /// The latest depth CameraInfo (`LiveOptions::depth_camera_info_topic`), waiting up to
    /// `timeout` for the first one; `None` when none came (or none is subscribed).
    pub fn depth_camera_info(&self, timeout: Duration) -> Result<Option<CameraInfo>, LiveError> {
        self.wait_for(timeout, |state| state.depth_camera_info.clone())
    }

    /// The oldest waiting pair (with the default queue of one, the newest pair received),
    /// waiting up to `timeout` for one; `None` when none came.
    pub fn next_pair(&self, timeout: Duration) -> Result<Option<LivePair>, LiveError> {
        self.wait_for(timeout, |state| {
            let pair = state.pairs.pop_front();
            state.taken_any |= pair.is_some();
            pair
        })
    }

    /// What `take` finds in the receiver's state, waiting up to `timeout` for it; an error once
    /// the receiving thread has failed.
    fn wait_for<T>(
        &self,
        timeout: Duration,
        mut take: impl FnMut(&mut State) -> Option<T>,
    ) -> Result<Option<T>, LiveError> {
        let deadline = Instant::now() + timeout;
        let mut state = self.shared.state.lock().expect("live state");
        loop {
            if let Some(found) = take(&mut state) {
                return Ok(Some(found));
            }
            if let Some(reason) = &state.failed {
                return Err(LiveError::Receiver(reason.clone()));
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            state = self
                .shared
                .changed
                .wait_timeout(state, left)
                .expect("live state")
                .0;
        }
    }

    /// What the subscriptions received so far and what became of it.
    pub fn counts(&self) -> LiveCounts {
        self.shared.state.lock().expect("live state").counts
    }
}

impl Drop for LiveCamera {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(receiver) = self.receiver.take() {
            let _ = receiver.join();
        }
    }
}

/// The type a topic carries, by image_transport's naming.
fn is_compressed(topic: &str) -> bool {
    topic.ends_with("/compressed") || topic.ends_with("/compressedDepth")
}

/// `/a/b/c` as ros2-client's (namespace, base name).
fn topic_name(topic: &str) -> Result<Name, LiveError> {
    let invalid = |reason: String| LiveError::TopicName {
        topic: topic.to_string(),
        reason,
    };
    let Some((namespace, base)) = topic.rsplit_once('/') else {
        return Err(invalid("not a name starting with /".into()));
    };
    if !topic.starts_with('/') {
        return Err(invalid("not a name starting with /".into()));
    }
    let namespace = if namespace.is_empty() { "/" } else { namespace };
    Name::new(namespace, base).map_err(|e| invalid(format!("{e:?}")))
}

/// The ROS 2 topics (name, type) other participants on `domain_id` announced within `wait`, as
/// `ros2 topic list -t` names them (`/camera/color/image_raw`, `sensor_msgs/msg/Image`), sorted.
pub fn discover_topics(domain_id: u16, wait: Duration) -> Result<Vec<(String, String)>, LiveError> {
    let (context, _node) = join_domain(domain_id, "mac_ego3d_discovery")?;
    std::thread::sleep(wait);
    let mut topics: Vec<(String, String)> = context
        .discovered_topics()
        .into_iter()
        .filter_map(|t| {
            let name = t.name.strip_prefix("rt")?.to_string();
            Some((name, ros_type_name(&t.type_name)))
        })
        .collect();
    topics.sort();
    topics.dedup();
    Ok(topics)
}

/// `sensor_msgs::msg::dds_::Image_` as `sensor_msgs/msg/Image`; other names as they are.
fn ros_type_name(dds: &str) -> String {
    match dds.split_once("::dds_::") {
        Some((package, name)) => format!(
            "{}/{}",
            package.replace("::", "/"),
            name.strip_suffix('_').unwrap_or(name)
        ),
        None => dds.to_string(),
    }
}

/// A DDS participant on `domain_id` and a ROS 2 node named `node_name` in it.
fn join_domain(domain_id: u16, node_name: &str) -> Result<(Context, ros2_client::Node), LiveError> {
    let dds = |reason: String| LiveError::Dds { domain_id, reason };
    let context = Context::with_options(ContextOptions::new().domain_id(domain_id))
        .map_err(|e| dds(format!("{e:?}")))?;
    let name = NodeName::new("/", node_name).map_err(|e| dds(format!("node name: {e:?}")))?;
    let node = context
        .new_node(name, NodeOptions::new().enable_rosout(false))
        .map_err(|e| dds(format!("{e:?}")))?;
    Ok((context, node))
}

enum ImageSubscription {
    Raw(ros2_client::Subscription<Image>),
    Compressed(ros2_client::Subscription<CompressedImage>),
}

/// Takes every waiting sample; `Err` only for a sample that cannot be read.
fn take_all<M: DeserializeOwned + 'static>(
    subscription: &ros2_client::Subscription<M>,
    mut each: impl FnMut(M),
    read_errors: &mut u64,
) {
    loop {
        match subscription.take() {
            Ok(Some((message, _info))) => each(message),
            Ok(None) => break,
            Err(error) => {
                *read_errors += 1;
                tracing::warn!(?error, "a ROS 2 sample could not be read");
            }
        }
    }
}

struct Subscriptions {
    // Fields drop in this order: the readers, then the node and the context that own the DDS
    // participant (a reader dropped after its participant cannot be removed cleanly).
    colour: ImageSubscription,
    depth: ImageSubscription,
    camera_info: ros2_client::Subscription<CameraInfo>,
    depth_camera_info: Option<ros2_client::Subscription<CameraInfo>>,
    _node: ros2_client::Node,
    _context: Context,
}

const COLOUR: Token = Token(0);
const DEPTH: Token = Token(1);
const CAMERA_INFO: Token = Token(2);
const DEPTH_CAMERA_INFO: Token = Token(3);

impl Subscriptions {
    fn create(options: &LiveOptions) -> Result<Self, LiveError> {
        let dds = |reason: String| LiveError::Dds {
            domain_id: options.domain_id,
            reason,
        };
        let (context, mut node) = join_domain(options.domain_id, &options.node_name)?;
        // Keep a few samples per reader so a burst is not lost before the thread takes it;
        // reliability as configured (best effort matches every publisher).
        let base = QosProfile::subscription_default().history(History::KeepLast { depth: 4 });
        let qos = if options.reliable {
            base.reliability_reliable(WhenFull::DEFAULT)
        } else {
            base
        };
        let mut image = |topic: &str| -> Result<ImageSubscription, LiveError> {
            let name = topic_name(topic)?;
            let (type_name, compressed) = if is_compressed(topic) {
                ("CompressedImage", true)
            } else {
                ("Image", false)
            };
            let dds_topic = node
                .create_topic(&name, MessageTypeName::new("sensor_msgs", type_name), &qos)
                .map_err(|e| dds(format!("topic {topic}: {e:?}")))?;
            Ok(if compressed {
                ImageSubscription::Compressed(
                    node.create_subscription(&dds_topic, Some(qos.clone()))
                        .map_err(|e| dds(format!("subscribing to {topic}: {e:?}")))?,
                )
            } else {
                ImageSubscription::Raw(
                    node.create_subscription(&dds_topic, Some(qos.clone()))
                        .map_err(|e| dds(format!("subscribing to {topic}: {e:?}")))?,
                )
            })
        };
        let colour = image(&options.colour_topic)?;
        let depth = image(&options.depth_topic)?;
        let mut info = |topic: &str| -> Result<ros2_client::Subscription<CameraInfo>, LiveError> {
            let dds_topic = node
                .create_topic(
                    &topic_name(topic)?,
                    MessageTypeName::new("sensor_msgs", "CameraInfo"),
                    &qos,
                )
                .map_err(|e| dds(format!("topic {topic}: {e:?}")))?;
            node.create_subscription(&dds_topic, Some(qos.clone()))
                .map_err(|e| dds(format!("subscribing to {topic}: {e:?}")))
        };
        let camera_info = info(&options.camera_info_topic)?;
        let depth_camera_info = options
            .depth_camera_info_topic
            .as_deref()
            .map(&mut info)
            .transpose()?;
        tracing::info!(
            domain_id = options.domain_id,
            colour = %options.colour_topic,
            depth = %options.depth_topic,
            camera_info = %options.camera_info_topic,
            "subscribed to the camera's ROS 2 topics"
        );
        Ok(Self {
            colour,
            depth,
            camera_info,
            depth_camera_info,
            _node: node,
            _context: context,
        })
    }

    /// Receives until the stop flag is set.
    fn receive(mut self, options: &LiveOptions, shared: &Shared) -> Result<(), String> {
        let poll_error = |e: std::io::Error| format!("polling the DDS readers: {e}");
        let mut poll = Poll::new().map_err(poll_error)?;
        let registry = poll.registry();
        match &mut self.colour {
            ImageSubscription::Raw(s) => registry.register(s, COLOUR, Interest::READABLE),
            ImageSubscription::Compressed(s) => registry.register(s, COLOUR, Interest::READABLE),
        }
        .map_err(poll_error)?;
        match &mut self.depth {
            ImageSubscription::Raw(s) => registry.register(s, DEPTH, Interest::READABLE),
            ImageSubscription::Compressed(s) => registry.register(s, DEPTH, Interest::READABLE),
        }
        .map_err(poll_error)?;
        registry
            .register(&mut self.camera_info, CAMERA_INFO, Interest::READABLE)
            .map_err(poll_error)?;
        if let Some(depth_info) = self.depth_camera_info.as_mut() {
            registry
                .register(depth_info, DEPTH_CAMERA_INFO, Interest::READABLE)
                .map_err(poll_error)?;
        }
        let mut events = Events::with_capacity(16);
        let mut pairing: Pairing<ImageMessage, ImageMessage> =
            Pairing::new(options.pairing_tolerance_s);
        let queue_pairs = options.queue_pairs.max(1);
        while !shared.stop.load(Ordering::Relaxed) {
            if let Err(e) = poll.poll(&mut events, Some(POLL_INTERVAL))
                && e.kind() != std::io::ErrorKind::Interrupted
            {
                return Err(poll_error(e));
            }
            // Every reader is drained on every wake-up (edge-triggered readiness, and cheap).
            let mut counts = LiveCounts::default();
            let mut colour = Vec::new();
            let mut depth = Vec::new();
            let mut info = None;
            let mut read_errors = 0;
            self.colour.take_all(|m| colour.push(m), &mut read_errors);
            self.depth.take_all(|m| depth.push(m), &mut read_errors);
            take_all(&self.camera_info, |m| info = Some(m), &mut read_errors);
            let mut depth_info = None;
            if let Some(subscription) = &self.depth_camera_info {
                take_all(subscription, |m| depth_info = Some(m), &mut read_errors);
            }
            counts.colour_received = colour.len() as u64;
            counts.depth_received = depth.len() as u64;
            counts.read_errors = read_errors;
            let mut formed = Vec::new();
            // Colour first, then depth: within one wake-up the order of arrival between the two
            // topics is not known, and pairing does not depend on it.
            for message in colour {
                let stamp = message.header().stamp.seconds();
                formed.extend(pairing.push_colour(stamp, message));
            }
            for message in depth {
                let stamp = message.header().stamp.seconds();
                formed.extend(pairing.push_depth(stamp, message));
            }
            let mut state = shared.state.lock().expect("live state");
            let any = !formed.is_empty() || info.is_some() || depth_info.is_some();
            if let Some(depth_info) = depth_info {
                state.depth_camera_info = Some(depth_info);
            }
            if let Some(info) = info {
                state.counts.camera_info_received += 1;
                state.camera_info = Some(info);
            }
            state.counts.colour_received += counts.colour_received;
            state.counts.depth_received += counts.depth_received;
            state.counts.read_errors += counts.read_errors;
            state.counts.pairing = pairing.counts();
            let now = Instant::now();
            let wall = SystemTime::now()
                .duration_since(SystemTime::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64());
            for (stamp_s, colour, depth) in formed {
                if state.pairs.len() == queue_pairs {
                    state.pairs.pop_front();
                    state.counts.dropped += 1;
                    if !state.taken_any {
                        state.counts.dropped_while_starting += 1;
                    }
                }
                state.pairs.push_back(LivePair {
                    stamp_s,
                    colour,
                    depth,
                    received_at: now,
                    received_wall_s: wall,
                });
            }
            if any {
                shared.changed.notify_all();
            }
        }
        Ok(())
    }
}

impl ImageSubscription {
    fn take_all(&self, each: impl FnMut(ImageMessage), read_errors: &mut u64) {
        let mut each = each;
        match self {
            Self::Raw(s) => take_all(s, |m| each(ImageMessage::Raw(m)), read_errors),
            Self::Compressed(s) => take_all(s, |m| each(ImageMessage::Compressed(m)), read_errors),
        }
    }
}

// The messages published live (ros2-client wants them marked).
impl ros2_client::Message for msg::TfMessage {}
impl ros2_client::Message for msg::Path {}
impl ros2_client::Message for msg::PointCloud2 {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topic_names_split_into_namespace_and_base() {
        assert!(topic_name("/camera/camera/color/image_raw").is_ok());
        assert!(topic_name("/image").is_ok());
        for bad in ["image", "/camera//image", "/camera/", "/camera/9image"] {
            assert!(topic_name(bad).is_err(), "{bad}");
        }
        assert!(is_compressed("/c/image_raw/compressed"));
        assert!(is_compressed("/d/image_raw/compressedDepth"));
        assert!(!is_compressed("/c/image_raw"));
    }

    #[test]
    fn dds_type_names_read_as_ros_names() {
        assert_eq!(
            ros_type_name("sensor_msgs::msg::dds_::Image_"),
            "sensor_msgs/msg/Image"
        );
        assert_eq!(ros_type_name("custom"), "custom");
    }
}
