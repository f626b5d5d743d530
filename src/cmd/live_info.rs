//! `mac-ego3d dataset info ros2:[NAMESPACE]`: what a live camera looks like from here, as
//! `ros2 topic list -t` and `ros2 topic hz` would say, without a ROS installation: every ROS 2
//! topic announced on the DDS domain, which of them the agent would subscribe to, and what came on
//! those in a few seconds (received, paired, the CameraInfo's size and lens).

use std::time::Duration;

use datasets::live::namespace_of;
use datasets::rosbag::Ros2Config;
use ros2::live::{LiveCamera, LiveOptions, discover_topics};
use serde::Serialize;

/// How long the discovery takes (before this command subscribes, so that the topics listed are
/// the others'), then the listening.
const DISCOVERY: Duration = Duration::from_secs(2);
const LISTEN: Duration = Duration::from_secs(3);

#[derive(Debug, Serialize)]
pub struct LiveInfo {
    pub namespace: String,
    pub domain_id: u16,
    /// Every ROS 2 topic announced on the domain: (name, type).
    pub topics: Vec<(String, String)>,
    /// The agent's topics, with whether each was announced.
    pub uses: Vec<(String, bool)>,
    pub listened_s: f64,
    /// What came on the agent's topics while listening.
    pub counts: ros2::live::LiveCounts,
    /// The CameraInfo received, as `WIDTHxHEIGHT fx fy cx cy, model [d...]`.
    pub camera_info: Option<String>,
}

pub fn live_info(spec: &str, config: &Ros2Config) -> anyhow::Result<LiveInfo> {
    let namespace = namespace_of(spec, config);
    let qualified = |topic: &str| format!("{}{}", namespace.trim_end_matches('/'), topic);
    let domain_id = config.domain_id();
    let topics = discover_topics(domain_id, DISCOVERY)?;
    let wanted = [
        qualified(&config.colour_topic),
        qualified(&config.depth_topic),
        qualified(&config.camera_info_topic),
    ];
    let camera = LiveCamera::connect(LiveOptions {
        domain_id,
        node_name: "mac_ego3d_info".into(),
        colour_topic: wanted[0].clone(),
        depth_topic: wanted[1].clone(),
        camera_info_topic: wanted[2].clone(),
        depth_camera_info_topic: None,
        pairing_tolerance_s: config.pairing_tolerance_s,
        reliable: config.reliable,
        queue_pairs: config.queue_pairs,
    })?;
    std::thread::sleep(LISTEN);
    let uses = wanted
        .iter()
        .map(|t| (t.clone(), topics.iter().any(|(name, _)| name == t)))
        .collect();
    let camera_info = camera.camera_info(Duration::ZERO)?.map(|i| {
        format!(
            "{}x{} fx {} fy {} cx {} cy {}, {} {:?}",
            i.width, i.height, i.k[0], i.k[4], i.k[2], i.k[5], i.distortion_model, i.d
        )
    });
    Ok(LiveInfo {
        namespace: namespace.trim_end_matches('/').to_string(),
        domain_id,
        topics,
        uses,
        listened_s: LISTEN.as_secs_f64(),
        counts: camera.counts(),
        camera_info,
    })
}

pub fn print_live_info(info: &LiveInfo) {
    println!("ROS 2 topics on DDS domain {}:", info.domain_id);
    if info.topics.is_empty() {
        println!("  none announced within {} s", DISCOVERY.as_secs_f64());
    }
    for (name, type_name) in &info.topics {
        println!("  {name:<60} {type_name}");
    }
    println!("the agent subscribes to:");
    for (topic, announced) in &info.uses {
        println!(
            "  {topic:<60} {}",
            if *announced {
                "announced"
            } else {
                "NOT ANNOUNCED"
            }
        );
    }
    // Not there, but image_transport's compressed variant is: say which key to set.
    for ((topic, announced), key) in info.uses.iter().zip(["colour_topic", "depth_topic"]) {
        if *announced {
            continue;
        }
        for suffix in ["/compressed", "/compressedDepth"] {
            let variant = format!("{topic}{suffix}");
            if info.topics.iter().any(|(name, _)| *name == variant) {
                println!(
                    "  hint: {variant} is announced: set [ros2] {key} = \"{}\"",
                    variant.strip_prefix(&info.namespace).unwrap_or(&variant)
                );
            }
        }
    }
    let c = &info.counts;
    println!(
        "in {:.0} s: {} colour, {} depth, {} CameraInfo received; {} pairs ({:.1} Hz)",
        info.listened_s,
        c.colour_received,
        c.depth_received,
        c.camera_info_received,
        c.pairing.paired,
        c.pairing.paired as f64 / info.listened_s
    );
    match &info.camera_info {
        Some(info) => println!("camera: {info}"),
        None => println!("camera: no CameraInfo received"),
    }
}
