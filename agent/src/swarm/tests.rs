//! The agent's link against a consumer in the same process: refused keyframes, re-sends on
//! request and after lost messages, the spool.

use std::time::Duration;

use protocol::convert::{gaussian_record, rgbd_pixel};
use protocol::messages::{ControlMessage, GaussianRecord, Pose, RgbdPixel};

use super::*;

/// The keyframe messages waiting at `consumer`.
#[derive(Default)]
struct Received {
    descriptors: Vec<u64>,
    images: Vec<(u64, Vec<RgbdPixel>)>,
    patches: Vec<(u64, Vec<GaussianRecord>)>,
}

/// One frame's link work, with the keyframe it published described and sent.
fn after_frame(swarm: &mut SwarmLink) -> Option<ReceivedCorrection> {
    let correction = swarm.after_frame();
    let link_up = swarm.link_up;
    swarm.deliver_described(link_up, true);
    correction
}

impl Received {
    /// Keyframe ids: (descriptors, images, patches).
    fn ids(&self) -> (Vec<u64>, Vec<u64>, Vec<u64>) {
        (
            self.descriptors.clone(),
            self.images.iter().map(|(id, _)| *id).collect(),
            self.patches.iter().map(|(id, _)| *id).collect(),
        )
    }
}

fn received_keyframes(consumer: &mut protocol::transport::ConsumerLink) -> Received {
    use protocol::transport::Incoming;
    const QUIET: Duration = Duration::from_millis(500);
    let mut received = Received::default();
    while let Some(message) = consumer.recv_timeout(QUIET).unwrap() {
        match message {
            Incoming::Descriptor(d) => received.descriptors.push(d.keyframe_id),
            Incoming::KeyframeImage(k) => received
                .images
                .push((k.header().keyframe_id, k.pixels().to_vec())),
            Incoming::Patch(p) => received
                .patches
                .push((p.header().keyframe_id, p.records().to_vec())),
            Incoming::Lifecycle(_) => {}
        }
    }
    received
}

/// A consumer and agent 0 announced to it (publishing every keyframe), in a namespace of
/// its own, with the agent's 32x24 camera.
fn announced_agent(namespace: &str) -> (protocol::transport::ConsumerLink, SwarmLink, Intrinsics) {
    announced_agent_with(namespace, &Config::default(), None)
}

/// [`announced_agent`] with `config` (publishing every keyframe) and a keyframe spool in
/// `spool`.
fn announced_agent_with(
    namespace: &str,
    config: &Config,
    spool: Option<&Path>,
) -> (protocol::transport::ConsumerLink, SwarmLink, Intrinsics) {
    let transport = TransportConfig::with_namespace(format!("{namespace}-{}", std::process::id()));
    let consumer = protocol::transport::ConsumerLink::open(&transport).unwrap();
    let mut config = config.clone();
    config.consensus.t_comm = 1;
    let mut swarm = SwarmLink::connect(0, &transport, &config, LinkPlan::always_up()).unwrap();
    if let Some(dir) = spool {
        swarm = swarm.with_spool(dir).unwrap();
    }
    let intrinsics = Intrinsics::new(40.0, 40.0, 16.0, 12.0, 32, 24);
    swarm.announce(&intrinsics, run_anchor("synthetic", 0, 0.0));
    (consumer, swarm, intrinsics)
}

#[test]
fn a_keyframe_whose_depth_and_colour_sizes_differ_is_refused_not_sent() {
    let (mut consumer, mut swarm, intrinsics) = announced_agent("size-mismatch");
    swarm.on_keyframe(PublishableKeyframe {
        keyframe_id: 3,
        frame_index: 30,
        timestamp_s: 3.0,
        agent_from_camera: Isometry3::identity(),
        intrinsics,
        rgb: RgbImage::from_pixel(32, 24, image::Rgb([1, 2, 3])),
        depth: DepthImage {
            width: 16,
            height: 12,
            data: vec![1.5; 16 * 12],
        },
        gaussians: GaussianCloud::default(),
    });
    after_frame(&mut swarm);
    assert_eq!(
        received_keyframes(&mut consumer).ids(),
        (vec![], vec![], vec![])
    );
    assert_eq!(swarm.summary().send_failures, 1);
}

#[test]
fn a_keyframe_the_consensus_asks_for_again_is_published_again() {
    let (mut consumer, mut swarm, intrinsics) = announced_agent("resend-agent");
    let keyframe = |keyframe_id| PublishableKeyframe {
        keyframe_id,
        frame_index: keyframe_id * 10,
        timestamp_s: keyframe_id as f64,
        agent_from_camera: Isometry3::identity(),
        intrinsics,
        rgb: RgbImage::from_fn(32, 24, |x, y| {
            image::Rgb([(x * 8) as u8, (y * 10) as u8, 7])
        }),
        depth: DepthImage {
            width: 32,
            height: 24,
            data: vec![1.5; 32 * 24],
        },
        gaussians: {
            let mut cloud = GaussianCloud::default();
            for i in 0..5 {
                let v = i as f32;
                cloud.push(
                    [v, 1.0, 2.0],
                    [-4.0; 3],
                    [1.0, 0.0, 0.0, v],
                    v - 2.0,
                    [0.5; 3],
                );
            }
            cloud
        },
    };
    // What the consumer must see: the keyframe's pixels and Gaussians, built in place.
    let expected_pixels: Vec<RgbdPixel> = {
        let k = keyframe(7);
        (0..32 * 24)
            .map(|i| rgbd_pixel(&k.rgb, &k.depth, i))
            .collect()
    };
    let expected_records: Vec<GaussianRecord> = {
        let k = keyframe(7);
        (0..5).map(|i| gaussian_record(&k.gaussians, i)).collect()
    };
    assert_eq!(expected_pixels[33].rgb, [8, 10, 7]);
    assert_eq!(expected_records[3].mean, [3.0, 1.0, 2.0]);
    let content_is_the_keyframes = |received: &Received| {
        assert_eq!(received.images[0].1, expected_pixels);
        assert_eq!(received.patches[0].1, expected_records);
    };
    swarm.on_keyframe(keyframe(7));
    assert!(after_frame(&mut swarm).is_none());
    let received = received_keyframes(&mut consumer);
    assert_eq!(received.ids(), (vec![7], vec![7], vec![7]));
    content_is_the_keyframes(&received);

    let ask = |keyframe_id| ControlMessage::ResendKeyframe {
        keyframe_id,
        reason: "test".into(),
    };
    consumer.send_control(0, &ask(7)).unwrap();
    consumer.send_control(0, &ask(99)).unwrap();
    after_frame(&mut swarm);
    let received = received_keyframes(&mut consumer);
    assert_eq!(
        received.ids(),
        (vec![7], vec![7], vec![7]),
        "keyframe 7 again, nothing for the unknown 99"
    );
    content_is_the_keyframes(&received);
    let summary = swarm.summary();
    assert_eq!(summary.resend_requests, 2);
    assert_eq!(summary.keyframes_resent, 1);
    assert_eq!(summary.resend_unavailable, 1);
    assert_eq!(summary.send_failures, 0);
}

#[test]
fn after_lost_messages_what_arrived_nowhere_up_to_the_newest_seen_is_published_again() {
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join(crate::spool::KEYFRAME_SPOOL_DIR);
    let mut config = Config::default();
    // Two in memory, the older ones on the spool: both places are looked in.
    config.consensus.resend.agent_keeps = 2;
    let (mut consumer, mut swarm, intrinsics) =
        announced_agent_with("lost-messages", &config, Some(&spool));
    for keyframe_id in 1..=6 {
        swarm.on_keyframe(small_keyframe(keyframe_id, intrinsics));
        after_frame(&mut swarm);
        received_keyframes(&mut consumer);
    }
    // The consensus holds 1 and 4 whole and 3 in part, and has seen nothing newer than 5:
    // 2 (spooled) and 5 (in memory) arrived nowhere; 6 may still be on the way.
    consumer
        .send_control(
            0,
            &ControlMessage::MessagesLost {
                keyframes_held: vec![1, 4],
                keyframes_in_part: vec![3],
                newest_seen: 5,
            },
        )
        .unwrap();
    after_frame(&mut swarm);
    let again = received_keyframes(&mut consumer);
    assert_eq!(again.ids(), (vec![2, 5], vec![2, 5], vec![2, 5]));
    let summary = swarm.summary();
    assert_eq!(summary.messages_lost_reports, 1);
    assert_eq!(summary.keyframes_resent, 2);
    assert!(summary.keyframes_unrecoverable.is_empty());
}

/// Keyframe `keyframe_id` of a 32x24 camera with two Gaussians.
fn small_keyframe(keyframe_id: u64, intrinsics: Intrinsics) -> PublishableKeyframe {
    let mut gaussians = GaussianCloud::default();
    for i in 0..2 {
        let v = (keyframe_id + i) as f32;
        gaussians.push([v, 1.0, 2.0], [-4.0; 3], [1.0, 0.0, 0.0, v], 0.5, [0.5; 3]);
    }
    PublishableKeyframe {
        keyframe_id,
        frame_index: keyframe_id * 10,
        timestamp_s: keyframe_id as f64,
        agent_from_camera: Isometry3::translation(keyframe_id as f64, 0.0, 0.0),
        intrinsics,
        rgb: RgbImage::from_fn(32, 24, |x, y| {
            image::Rgb([(x * 8) as u8, (y * 10) as u8, keyframe_id as u8])
        }),
        depth: DepthImage {
            width: 32,
            height: 24,
            data: vec![1.5; 32 * 24],
        },
        gaussians,
    }
}

#[test]
fn keyframes_beyond_those_in_memory_are_spooled_until_confirmed_and_none_is_unrecoverable() {
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join(crate::spool::KEYFRAME_SPOOL_DIR);
    let mut config = Config::default();
    // Nothing in memory: every keyframe the consensus lacks comes from the spool.
    config.consensus.resend.agent_keeps = 0;
    let (mut consumer, mut swarm, intrinsics) =
        announced_agent_with("spool-agent", &config, Some(&spool));
    let mut first = Received::default();
    for keyframe_id in 1..=3 {
        swarm.on_keyframe(small_keyframe(keyframe_id, intrinsics));
        after_frame(&mut swarm);
        // Taken as they come: the patch queue holds few samples.
        let received = received_keyframes(&mut consumer);
        first.descriptors.extend(received.descriptors);
        first.images.extend(received.images);
        first.patches.extend(received.patches);
    }
    assert_eq!(first.ids(), (vec![1, 2, 3], vec![1, 2, 3], vec![1, 2, 3]));
    let spooled = |spool: &Path| {
        let mut names: Vec<String> = std::fs::read_dir(spool)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    assert_eq!(
        spooled(&spool),
        ["keyframe_1.bin", "keyframe_2.bin", "keyframe_3.bin"]
    );

    // A consensus restarted on a store that holds keyframe 1 only.
    consumer
        .send_control(
            0,
            &ControlMessage::ConsensusResumed {
                keyframes_held: vec![1],
            },
        )
        .unwrap();
    after_frame(&mut swarm);
    let again = received_keyframes(&mut consumer);
    assert_eq!(again.ids(), (vec![2, 3], vec![2, 3], vec![2, 3]));
    assert_eq!(again.images[0].1, first.images[1].1, "keyframe 2's pixels");
    assert_eq!(
        again.patches[1].1, first.patches[2].1,
        "keyframe 3's Gaussians"
    );
    assert_eq!(spooled(&spool), ["keyframe_2.bin", "keyframe_3.bin"]);
    assert!(swarm.summary().keyframes_unrecoverable.is_empty());

    // A correction naming them confirms them.
    let pose = |keyframe_id| protocol::messages::KeyframePose {
        keyframe_id,
        camera_to_world: Pose::IDENTITY,
    };
    consumer
        .send_correction(0, Pose::IDENTITY, &[pose(1), pose(2), pose(3)])
        .unwrap();
    after_frame(&mut swarm);
    assert!(spooled(&spool).is_empty());
    let summary = swarm.summary();
    assert_eq!(summary.keyframes_resent, 2);
    assert_eq!(summary.spool_failures, 0);
    assert!(summary.keyframes_spooled >= 3);
}

/// A keyframe whose send fails (its consensus died) is not dropped: it waits in the queue and
/// goes out whole to the consensus that comes back, counted once as published.
#[test]
fn a_keyframe_whose_send_fails_goes_out_to_the_consensus_that_comes_back() {
    let mut transport =
        TransportConfig::with_namespace(format!("failed-send-{}", std::process::id()));
    transport.delivery_timeout = Duration::from_millis(300);
    let consumer = protocol::transport::ConsumerLink::open(&transport).unwrap();
    let mut config = Config::default();
    config.consensus.t_comm = 1;
    let mut swarm = SwarmLink::connect(0, &transport, &config, LinkPlan::always_up()).unwrap();
    let intrinsics = Intrinsics::new(40.0, 40.0, 16.0, 12.0, 32, 24);
    swarm.announce(&intrinsics, run_anchor("synthetic", 0, 0.0));
    drop(consumer);

    swarm.on_keyframe(small_keyframe(3, intrinsics));
    after_frame(&mut swarm);
    assert_eq!(swarm.summary().send_failures, 1);
    assert!(swarm.summary().keyframes_published_ids.is_empty());
    assert_eq!(swarm.status().queued_keyframes, 1, "queued, not dropped");

    let mut consumer = protocol::transport::ConsumerLink::open(&transport).unwrap();
    // The agent looks for its consensus once a second, and waits as long after a failure.
    std::thread::sleep(Duration::from_millis(1200));
    after_frame(&mut swarm);
    let received = received_keyframes(&mut consumer);
    assert_eq!(received.ids(), (vec![3], vec![3], vec![3]));
    let summary = swarm.summary();
    assert_eq!(summary.keyframes_published, 1);
    assert_eq!(
        summary
            .keyframes_published_ids
            .iter()
            .copied()
            .collect::<Vec<_>>(),
        [3]
    );
    assert_eq!(swarm.status().queued_keyframes, 0);
}

/// A consensus restarted near the end of the run can tell this agent what it lacks too late
/// (after the agent's last look at its control topic): every keyframe it has not confirmed
/// goes out again before the final map and the goodbye; a confirmed one does not.
#[test]
fn at_the_end_keyframes_the_consensus_has_not_confirmed_go_out_again_before_the_goodbye() {
    use protocol::messages::{FINAL_MAP_KEYFRAME_ID, LifecycleKind};
    use protocol::transport::{ConsumerLink, Incoming};

    let mut transport =
        TransportConfig::with_namespace(format!("end-resend-{}", std::process::id()));
    transport.delivery_timeout = Duration::from_secs(3);
    let mut first = ConsumerLink::open(&transport).unwrap();
    let mut config = Config::default();
    config.consensus.t_comm = 1;
    let mut swarm = SwarmLink::connect(0, &transport, &config, LinkPlan::always_up()).unwrap();
    let intrinsics = Intrinsics::new(40.0, 40.0, 16.0, 12.0, 32, 24);
    swarm.announce(&intrinsics, run_anchor("synthetic", 0, 0.0));
    let mut delivered = Received::default();
    for keyframe_id in 1..=3 {
        swarm.on_keyframe(small_keyframe(keyframe_id, intrinsics));
        after_frame(&mut swarm);
        delivered
            .descriptors
            .extend(received_keyframes(&mut first).descriptors);
    }
    assert_eq!(delivered.descriptors, [1, 2, 3]);
    // The first consensus confirms keyframe 1 (a correction places it), then dies.
    let pose = protocol::messages::KeyframePose {
        keyframe_id: 1,
        camera_to_world: Pose::IDENTITY,
    };
    first.send_correction(0, Pose::IDENTITY, &[pose]).unwrap();
    after_frame(&mut swarm);
    drop(first);

    // Its successor is up before the agent ends; what it would say on resuming never arrives.
    let (ready, attached) = std::sync::mpsc::channel();
    let successor = std::thread::spawn(move || {
        let mut consumer = ConsumerLink::open(&transport).unwrap();
        ready.send(()).unwrap();
        let (mut keyframes, mut patches, mut goodbye) = (Vec::new(), Vec::new(), false);
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        while !goodbye && std::time::Instant::now() < deadline {
            match consumer.recv_timeout(Duration::from_millis(100)).unwrap() {
                Some(Incoming::Descriptor(d)) => keyframes.push(d.keyframe_id),
                Some(Incoming::Patch(p)) => patches.push(p.header().keyframe_id),
                Some(Incoming::Lifecycle(l)) => {
                    goodbye |= matches!(l.kind(), Ok(LifecycleKind::Goodbye));
                }
                Some(Incoming::KeyframeImage(_)) | None => {}
            }
        }
        (keyframes, patches, goodbye)
    });
    attached.recv().unwrap();
    let summary = swarm.finish(&small_keyframe(9, intrinsics).gaussians);
    let (keyframes, patches, goodbye) = successor.join().unwrap();
    assert!(goodbye, "the successor heard the goodbye");
    assert_eq!(keyframes, [2, 3], "the unconfirmed keyframes, again");
    assert_eq!(patches, [2, 3, FINAL_MAP_KEYFRAME_ID]);
    assert_eq!(summary.keyframes_resent_at_end, 2);
    assert!(summary.keyframes_unrecoverable.is_empty());
}
