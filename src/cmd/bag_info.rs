//! The part of `mac-ego3d dataset info` that is about a ROS 2 bag: its files, every topic with
//! type, count and rate, where it is damaged, and what the reader uses (topics, pairs, ground
//! truth).

use datasets::FrameRange;
use datasets::rosbag::{BagChoice, Ros2Config, RosBag};
use serde::Serialize;

/// One topic of the bag.
#[derive(Debug, Serialize)]
pub struct TopicInfo {
    pub name: String,
    pub type_name: String,
    pub count: usize,
    /// Messages per second over the topic's span of receive times.
    pub rate_hz: Option<f64>,
}

/// What `dataset info` adds for a bag.
#[derive(Debug, Serialize)]
pub struct BagInfo {
    pub files: Vec<String>,
    pub topics: Vec<TopicInfo>,
    pub damage: Option<String>,
    /// The topics the reader uses.
    pub uses: BagChoice,
    /// Colour/depth pairs in the whole bag (frames 0..pairs).
    pub pairs: usize,
    pub ground_truth_poses: usize,
}

pub fn bag_info(path: &str, config: &Ros2Config) -> anyhow::Result<BagInfo> {
    let reader = RosBag::open(std::path::Path::new(path), FrameRange::ALL, config)?;
    let bag = reader.bag();
    let topics = bag
        .topics()
        .iter()
        .map(|t| TopicInfo {
            name: t.name.clone(),
            type_name: t.type_name.clone(),
            count: t.count,
            rate_hz: (t.count > 1 && t.last_ns > t.first_ns)
                .then(|| (t.count - 1) as f64 / ((t.last_ns - t.first_ns) as f64 * 1e-9)),
        })
        .collect();
    Ok(BagInfo {
        files: bag.files().map(|f| f.display().to_string()).collect(),
        topics,
        damage: bag.damage().map(|d| d.to_string()),
        uses: reader.choice().clone(),
        pairs: reader.pairs_in_bag(),
        ground_truth_poses: reader.ground_truth_poses(),
    })
}

pub fn print_bag_info(info: &BagInfo) {
    println!("  bag files         {}", info.files.join(", "));
    if let Some(damage) = &info.damage {
        println!("  DAMAGED           {damage}");
    }
    let width = info.topics.iter().map(|t| t.name.len()).max().unwrap_or(0);
    println!("  topics");
    for t in &info.topics {
        let rate = t
            .rate_hz
            .map(|r| format!("{r:.1} Hz"))
            .unwrap_or_else(|| "-".into());
        println!(
            "    {:<width$}  {:<34} {:>7} msgs  {rate}",
            t.name, t.type_name, t.count
        );
    }
    let uses = &info.uses;
    println!("  colour            {}", uses.colour_topic);
    println!("  depth             {}", uses.depth_topic);
    println!("  camera info       {}", uses.camera_info_topic);
    if let Some(topic) = &uses.depth_camera_info_topic {
        println!("  depth camera info {topic} (depth is its own pinhole)");
    }
    println!(
        "  ground truth from {}",
        uses.ground_truth.as_deref().unwrap_or("none")
    );
    println!(
        "  frames            {} colour/depth pairs, {} ground-truth poses",
        info.pairs, info.ground_truth_poses
    );
}
