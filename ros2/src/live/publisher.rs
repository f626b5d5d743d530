//! A SLAM system's results published live for rviz2 (docs/ros2.md, Live outputs): tf on `/tf`
//! (reliable, as tf2's broadcasters) and `/tf_static`, a `nav_msgs/Path` and a
//! `sensor_msgs/PointCloud2` per topic (reliable, keep last 1, transient local: an rviz2 started
//! later still gets the latest).

use std::time::Duration;

use ros2_client::qos::{Durability, History, QosProfile, WhenFull};
use ros2_client::{MessageTypeName, Publisher};

use super::{LiveError, join_domain, topic_name};
use crate::msg::{Path, PointCloud2, TfMessage};

/// Publishers of one node, made on first use of each topic.
pub struct LivePublisher {
    domain_id: u16,
    tf: Publisher<TfMessage>,
    tf_static: Publisher<TfMessage>,
    paths: Vec<(String, Publisher<Path>)>,
    clouds: Vec<(String, Publisher<PointCloud2>)>,
    // Dropped last: the node and the participant the publishers belong to.
    node: ros2_client::Node,
    _context: ros2_client::Context,
}

fn latest_only() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .history(History::KeepLast { depth: 1 })
        .durability(Durability::TransientLocal)
}

/// How long [`LivePublisher::linger`] gives reliable samples to reach their subscribers.
pub const LINGER: Duration = Duration::from_secs(3);

impl LivePublisher {
    /// Joins `domain_id` as the node `node_name`, with `/tf` and `/tf_static` ready.
    pub fn connect(domain_id: u16, node_name: &str) -> Result<Self, LiveError> {
        let (context, mut node) = join_domain(domain_id, node_name)?;
        let tf_qos = QosProfile::publisher_default()
            .reliability_reliable(WhenFull::DEFAULT)
            .history(History::KeepLast { depth: 100 });
        let static_qos = latest_only();
        let tf = publisher(
            &mut node,
            domain_id,
            "/tf",
            ("tf2_msgs", "TFMessage"),
            tf_qos,
        )?;
        let tf_static = publisher(
            &mut node,
            domain_id,
            "/tf_static",
            ("tf2_msgs", "TFMessage"),
            static_qos,
        )?;
        Ok(Self {
            domain_id,
            tf,
            tf_static,
            paths: Vec::new(),
            clouds: Vec::new(),
            node,
            _context: context,
        })
    }

    /// Before the process ends: waits [`LINGER`] so that the last samples reach their
    /// subscribers (and are repaired, reliable) before the participant leaves. (ros2-client counts
    /// matched subscriptions only with a node spinner running, which this publisher does not
    /// need otherwise: it always waits.)
    pub fn linger(&self) {
        std::thread::sleep(LINGER);
    }

    /// Publishes on `/tf` (reliable, keep last 100, volatile: a subscriber hears what is sent
    /// after it matched).
    pub fn tf(&self, message: TfMessage) -> Result<(), LiveError> {
        sent(self.tf.publish(message), "/tf")
    }

    /// Publishes on `/tf_static` (reliable, keep last 1, transient local). A late subscriber
    /// gets only the latest message, so one message must hold every static transform.
    pub fn tf_static(&self, message: TfMessage) -> Result<(), LiveError> {
        sent(self.tf_static.publish(message), "/tf_static")
    }

    /// Publishes a path on `topic` (`/agent0/path`), whose publisher is made on its first use
    /// (reliable, keep last 1, transient local).
    pub fn path(&mut self, topic: &str, message: Path) -> Result<(), LiveError> {
        let made = made_for(
            &mut self.paths,
            &mut self.node,
            self.domain_id,
            topic,
            ("nav_msgs", "Path"),
        )?;
        sent(made.publish(message), topic)
    }

    /// Publishes a point cloud on `topic` (`/agent0/map`), whose publisher is made on its first
    /// use (reliable, keep last 1, transient local).
    pub fn cloud(&mut self, topic: &str, message: PointCloud2) -> Result<(), LiveError> {
        let made = made_for(
            &mut self.clouds,
            &mut self.node,
            self.domain_id,
            topic,
            ("sensor_msgs", "PointCloud2"),
        )?;
        sent(made.publish(message), topic)
    }
}

/// The publisher of `topic` in `made`, made (keep-last 1, transient local) on first use.
fn made_for<'a, M: serde::Serialize>(
    made: &'a mut Vec<(String, Publisher<M>)>,
    node: &mut ros2_client::Node,
    domain_id: u16,
    topic: &str,
    type_name: (&str, &str),
) -> Result<&'a Publisher<M>, LiveError> {
    let at = match made.iter().position(|(t, _)| t == topic) {
        Some(at) => at,
        None => {
            let publisher = publisher(node, domain_id, topic, type_name, latest_only())?;
            made.push((topic.to_string(), publisher));
            made.len() - 1
        }
    };
    Ok(&made[at].1)
}

fn publisher<M: serde::Serialize>(
    node: &mut ros2_client::Node,
    domain_id: u16,
    topic: &str,
    (package, type_name): (&str, &str),
    qos: QosProfile,
) -> Result<Publisher<M>, LiveError> {
    let dds = |reason: String| LiveError::Dds { domain_id, reason };
    let made = node
        .create_topic(
            &topic_name(topic)?,
            MessageTypeName::new(package, type_name),
            &qos,
        )
        .map_err(|e| dds(format!("topic {topic}: {e:?}")))?;
    node.create_publisher(&made, Some(qos))
        .map_err(|e| dds(format!("publishing on {topic}: {e:?}")))
}

fn sent<E: std::fmt::Debug>(result: Result<(), E>, topic: &str) -> Result<(), LiveError> {
    result.map_err(|e| LiveError::Publish {
        topic: topic.to_string(),
        reason: format!("{e:?}"),
    })
}
