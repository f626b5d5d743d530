//! Transport behaviour that needs no second process: timeouts, shutdown, idle CPU use, service
//! limit mismatches, message validation, exact bandwidth accounting, keyframe images (segment
//! growth, pixel integrity, drain before goodbye).

mod common;

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use common::unique_namespace;
use protocol::bench::synthetic_descriptor;
use protocol::messages::{
    ControlMessage, CoordinateFrame, GaussianRecord, Intrinsics, KeyframeDescriptor,
    KeyframeImageHeader, KeyframePose, LifecycleKind, Pose, RgbdPixel,
};
use protocol::services::{ServiceNames, Topic};
use protocol::transport::{
    AgentLink, ConsumerLink, Delivery, Direction, FullQueuePolicies, FullQueuePolicy, Incoming,
    KeyframeImageMeta, TransportConfig, TransportError,
};

/// Bound for what should happen at once on a loaded 2-core machine.
const PROMPT: Duration = Duration::from_secs(2);

/// CPU time (user + system) of the calling thread.
fn thread_cpu_time() -> Duration {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage fills the rusage struct behind the valid pointer; RUSAGE_THREAD is
    // supported by every Linux kernel this project targets.
    let usage = unsafe {
        assert_eq!(libc::getrusage(libc::RUSAGE_THREAD, usage.as_mut_ptr()), 0);
        usage.assume_init()
    };
    let micros = |t: libc::timeval| t.tv_sec as u64 * 1_000_000 + t.tv_usec as u64;
    Duration::from_micros(micros(usage.ru_utime) + micros(usage.ru_stime))
}

#[test]
fn idle_waiting_uses_no_cpu() {
    const IDLE: Duration = Duration::from_millis(600);
    let mut consumer =
        ConsumerLink::open(&TransportConfig::with_namespace(unique_namespace("idle"))).unwrap();
    let cpu_before = thread_cpu_time();
    let start = Instant::now();
    assert!(consumer.recv_timeout(IDLE).unwrap().is_none());
    let (wall, cpu) = (start.elapsed(), thread_cpu_time() - cpu_before);
    assert!(wall >= IDLE, "returned early after {wall:?}");
    // A busy spin would burn ~100 % of the wall time; event waits with 50 ms slices burn ~0.
    assert!(cpu < wall / 10, "waiting burned {cpu:?} of CPU in {wall:?}");
}

#[test]
fn shutdown_flag_ends_a_blocking_wait_within_one_slice() {
    let config = TransportConfig::with_namespace(unique_namespace("shutdown"));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let flag = consumer.shutdown_handle();
    let setter = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(100));
        flag.store(true, Ordering::Relaxed);
    });
    let start = Instant::now();
    let result = consumer.recv_timeout(Duration::from_secs(30));
    setter.join().unwrap();
    assert!(
        matches!(result, Err(TransportError::ShutdownRequested)),
        "{:?}",
        result.err()
    );
    assert!(start.elapsed() < PROMPT, "took {:?}", start.elapsed());
}

#[test]
fn send_without_consumer_times_out_with_a_typed_error() {
    let config = TransportConfig {
        delivery_timeout: Duration::from_millis(200),
        ..TransportConfig::with_namespace(unique_namespace("noconsumer"))
    };
    let mut agent = AgentLink::open(&config, 0).unwrap();
    let start = Instant::now();
    match agent.send_descriptor(&synthetic_descriptor(0)) {
        Err(TransportError::NoConsumer {
            attached: 0,
            required: 1,
            waited,
            ..
        }) => {
            assert!(waited >= config.delivery_timeout)
        }
        other => panic!("expected NoConsumer, got {:?}", other.map(|r| r.sequence)),
    }
    assert!(start.elapsed() < PROMPT);
    // A standalone agent (no consensus) sends fire-and-forget.
    let standalone = TransportConfig {
        required_consumers: 0,
        ..config.clone()
    };
    let mut agent_alone = AgentLink::open(
        &TransportConfig {
            namespace: format!("{}-alone", config.namespace),
            ..standalone
        },
        0,
    )
    .unwrap();
    assert_eq!(
        agent_alone
            .send_descriptor(&synthetic_descriptor(0))
            .unwrap()
            .recipients,
        0
    );
}

#[test]
fn invalid_outgoing_messages_are_refused() {
    let config = TransportConfig {
        required_consumers: 0,
        ..TransportConfig::with_namespace(unique_namespace("invalid"))
    };
    let mut agent = AgentLink::open(&config, 0).unwrap();
    let unnormalised = KeyframeDescriptor::new(0, 0, 0.0);
    assert!(matches!(
        agent.send_descriptor(&unnormalised),
        Err(TransportError::InvalidMessage { .. })
    ));
    let mut bad_pose = synthetic_descriptor(0);
    bad_pose.camera_to_agent_world.rotation_wxyz = [0.0; 4];
    let err = agent.send_descriptor(&bad_pose).unwrap_err();
    assert!(err.to_string().contains("camera_to_agent_world"), "{err}");
}

#[test]
fn mismatched_service_limits_are_a_clear_error() {
    let namespace = unique_namespace("limits");
    let _agent = AgentLink::open(&TransportConfig::with_namespace(&namespace), 0).unwrap();
    let bigger = TransportConfig {
        max_consumers: 5,
        ..TransportConfig::with_namespace(&namespace)
    };
    match ConsumerLink::open(&bigger) {
        Err(TransportError::Service { service, reason }) => {
            assert!(service.starts_with(&namespace), "{service}");
            assert!(
                reason.contains("DoesNotSupportRequestedAmountOf"),
                "{reason}"
            );
        }
        Err(other) => panic!("unexpected error {other}"),
        Ok(_) => panic!("a consumer with other limits must be refused"),
    }
}

/// A consensus started for 2 agents sets the swarm's id range: an agent configured with the
/// default range still joins with id 1 (no service-limit mismatch), and id 3 is refused by name.
#[test]
fn swarm_sized_by_the_consensus_admits_its_ids_and_refuses_others_clearly() {
    let namespace = unique_namespace("swarmsize");
    let swarm = TransportConfig::for_swarm(&namespace, Some(2));
    assert_eq!(swarm.max_agents, 2);
    let mut consumer = ConsumerLink::open(&swarm).unwrap();
    let agent_config = TransportConfig::with_namespace(&namespace);
    assert!(
        agent_config.max_agents > 3,
        "the agent's own range must allow id 3"
    );
    match AgentLink::open(&agent_config, 3) {
        Err(
            err @ TransportError::AgentIdOutsideSwarm {
                agent_id: 3,
                swarm_max_agents: 2,
                ..
            },
        ) => {
            let text = err.to_string();
            assert!(text.contains("agent id 3"), "{text}");
            assert!(text.contains("0..2"), "{text}");
            assert!(text.contains(&namespace), "{text}");
        }
        Err(other) => panic!("unexpected error {other}"),
        Ok(_) => panic!("agent id 3 must be refused by a swarm of 2"),
    }
    let mut agent = AgentLink::open(&agent_config, 1).unwrap();
    agent.send_descriptor(&synthetic_descriptor(4)).unwrap();
    let received = consumer
        .recv_timeout(PROMPT)
        .unwrap()
        .expect("descriptor of agent 1");
    assert_eq!(
        (received.agent_id(), received.topic()),
        (1, Topic::Descriptor)
    );
    // The consumer's own range is checked too.
    assert!(matches!(
        consumer.send_correction(2, Pose::IDENTITY, &[]),
        Err(TransportError::AgentIdOutOfRange {
            agent_id: 2,
            max_agents: 2
        })
    ));
}

/// An agent that starts first sets up the shared services for its own (default) range; a
/// consensus for a smaller swarm then joins without a limit mismatch.
#[test]
fn consensus_for_a_smaller_swarm_joins_after_an_agent() {
    let namespace = unique_namespace("swarmlater");
    let mut agent = AgentLink::open(&TransportConfig::with_namespace(&namespace), 0).unwrap();
    let mut consumer =
        ConsumerLink::open(&TransportConfig::for_swarm(&namespace, Some(1))).unwrap();
    agent.send_descriptor(&synthetic_descriptor(0)).unwrap();
    let received = consumer.recv_timeout(PROMPT).unwrap().expect("descriptor");
    assert_eq!(received.agent_id(), 0);
    assert_eq!(
        TransportConfig::for_swarm(&namespace, None).max_agents,
        protocol::transport::DEFAULT_MAX_AGENTS
    );
}

/// Short bound for full-queue tests: long enough to see the wait, short for the test suite.
const FULL_QUEUE_TIMEOUT: Duration = Duration::from_millis(300);

/// `Block` (patches by default): a consumer that does not read makes the sender wait
/// `full_queue_timeout`, then fail with `QueueFull` (counted); once it reads, sends go through,
/// and the failed message shows as a gap.
#[test]
fn full_patch_queue_blocks_for_a_bounded_time_then_reports_queue_full() {
    let namespace = unique_namespace("fullblock");
    let config = TransportConfig {
        patch_queue_depth: 2,
        full_queue_timeout: FULL_QUEUE_TIMEOUT,
        ..TransportConfig::with_namespace(&namespace)
    };
    assert_eq!(config.full_queue.patch, FullQueuePolicy::Block);
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let mut agent = AgentLink::open(&config, 0).unwrap();
    let records = vec![GaussianRecord::default(); 100];
    for keyframe_id in 0..2 {
        agent
            .send_patch(keyframe_id, CoordinateFrame::AgentWorld, &records)
            .unwrap();
    }
    let start = Instant::now();
    match agent.send_patch(2, CoordinateFrame::AgentWorld, &records) {
        Err(
            err @ TransportError::QueueFull {
                topic: Topic::Patch,
                sequence: 2,
                delivered: 0,
                required: 1,
                ..
            },
        ) => {
            let text = err.to_string();
            assert!(
                text.contains(&ServiceNames::new(&namespace).patch(0)),
                "{text}"
            );
            assert!(text.contains("patch topic"), "{text}");
        }
        other => panic!("expected QueueFull, got {:?}", other.map(|r| r.sequence)),
    }
    let waited = start.elapsed();
    assert!(waited >= FULL_QUEUE_TIMEOUT, "gave up after {waited:?}");
    assert!(waited < FULL_QUEUE_TIMEOUT + PROMPT, "took {waited:?}");
    let sent = *agent
        .bandwidth()
        .get(0, Topic::Patch, Direction::Sent)
        .unwrap();
    assert_eq!((sent.messages, sent.full_queue_failures), (2, 1));

    for expected in 0..2 {
        match consumer.recv_timeout(PROMPT).unwrap() {
            Some(Incoming::Patch(patch)) => assert_eq!(patch.header().keyframe_id, expected),
            _ => panic!("expected patch {expected}"),
        }
    }
    agent
        .send_patch(3, CoordinateFrame::AgentWorld, &records)
        .unwrap();
    match consumer.recv_timeout(PROMPT).unwrap() {
        Some(Incoming::Patch(patch)) => {
            assert_eq!(patch.header().keyframe_id, 3);
            assert_eq!(patch.delivery, Delivery::Gap { missed: 1 });
        }
        _ => panic!("expected patch 3"),
    }
}

/// `NewestWins` on descriptors: sends to a consumer that does not read never wait, the queue
/// keeps the newest, and the receiver sees the replaced ones as missed.
#[test]
fn newest_wins_queue_never_blocks_and_keeps_the_newest() {
    const DEPTH: usize = 2;
    const SENT: u64 = 5;
    let config = TransportConfig {
        descriptor_queue_depth: DEPTH,
        full_queue: FullQueuePolicies {
            descriptor: FullQueuePolicy::NewestWins,
            ..FullQueuePolicies::default()
        },
        full_queue_timeout: FULL_QUEUE_TIMEOUT,
        ..TransportConfig::with_namespace(unique_namespace("newest"))
    };
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let mut agent = AgentLink::open(&config, 0).unwrap();
    let start = Instant::now();
    for keyframe_id in 0..SENT {
        agent
            .send_descriptor(&synthetic_descriptor(keyframe_id))
            .unwrap();
    }
    assert!(
        start.elapsed() < FULL_QUEUE_TIMEOUT,
        "{:?}",
        start.elapsed()
    );
    let first_kept = SENT - DEPTH as u64;
    for keyframe_id in first_kept..SENT {
        match consumer.recv_timeout(PROMPT).unwrap() {
            Some(Incoming::Descriptor(descriptor)) => {
                assert_eq!(descriptor.keyframe_id, keyframe_id);
                let expected = if keyframe_id == first_kept {
                    Delivery::NewIncarnation {
                        previous_epoch: None,
                        missed: first_kept,
                    }
                } else {
                    Delivery::InOrder
                };
                assert_eq!(descriptor.delivery, expected);
            }
            _ => panic!("expected descriptor {keyframe_id}"),
        }
    }
    assert!(consumer.try_recv().unwrap().is_none());
}

fn shifted_pose(x: f64) -> Pose {
    Pose {
        translation: [x, 0.0, 0.0],
        ..Pose::IDENTITY
    }
}

/// Corrections are newest-wins by default: the consensus never waits on an agent that does not
/// read, and the agent finds the newest ones. With `Block` it waits, bounded, then `QueueFull`.
#[test]
fn corrections_to_a_slow_agent_overwrite_by_default_and_block_bounded_when_configured() {
    let config = TransportConfig::with_namespace(unique_namespace("corrnewest"));
    assert_eq!(config.full_queue.correction, FullQueuePolicy::NewestWins);
    let depth = config.correction_queue_depth as u64;
    let sent = depth + 2;
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let mut agent = AgentLink::open(&config, 0).unwrap();
    let start = Instant::now();
    for i in 0..sent {
        consumer
            .send_correction(0, shifted_pose(i as f64), &[])
            .unwrap();
    }
    assert!(start.elapsed() < PROMPT, "{:?}", start.elapsed());
    let mut received = Vec::new();
    while let Some(correction) = agent.try_recv_correction().unwrap() {
        received.push((
            correction.header().agent_world_to_world.translation[0] as u64,
            correction.delivery,
        ));
    }
    let kept: Vec<u64> = received.iter().map(|(x, _)| *x).collect();
    assert_eq!(kept, ((sent - depth)..sent).collect::<Vec<_>>());
    assert_eq!(
        received[0].1,
        Delivery::NewIncarnation {
            previous_epoch: None,
            missed: sent - depth
        }
    );

    let blocking = TransportConfig {
        full_queue: FullQueuePolicies {
            correction: FullQueuePolicy::Block,
            ..FullQueuePolicies::default()
        },
        full_queue_timeout: FULL_QUEUE_TIMEOUT,
        ..TransportConfig::with_namespace(unique_namespace("corrblock"))
    };
    let mut consumer = ConsumerLink::open(&blocking).unwrap();
    let _agent = AgentLink::open(&blocking, 0).unwrap();
    for i in 0..blocking.correction_queue_depth {
        consumer
            .send_correction(0, shifted_pose(i as f64), &[])
            .unwrap();
    }
    let start = Instant::now();
    let err = consumer
        .send_correction(0, Pose::IDENTITY, &[])
        .unwrap_err();
    assert!(
        matches!(
            err,
            TransportError::QueueFull {
                topic: Topic::Correction,
                ..
            }
        ),
        "{err}"
    );
    let waited = start.elapsed();
    assert!(
        waited >= FULL_QUEUE_TIMEOUT && waited < FULL_QUEUE_TIMEOUT + PROMPT,
        "{waited:?}"
    );
    let sent = *consumer
        .bandwidth()
        .get(0, Topic::Correction, Direction::Sent)
        .unwrap();
    assert_eq!(
        (sent.messages, sent.full_queue_failures),
        (blocking.correction_queue_depth as u64, 1)
    );
}

/// Control messages (codec frames in a byte slice) reach the agent in order with their
/// sequence, are counted on both sides, and a control message for an id outside the consumer's
/// range is refused by name.
#[test]
fn control_messages_reach_the_agent_in_order_and_are_counted() {
    let config = TransportConfig::with_namespace(unique_namespace("control"));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let mut agent = AgentLink::open(&config, 2).unwrap();
    let messages = [
        ControlMessage::ResendKeyframe {
            keyframe_id: 17,
            reason: "descriptor without keyframe image".into(),
        },
        ControlMessage::Shutdown {
            reason: "consensus stopped by SIGINT".into(),
        },
    ];
    let mut bytes_sent = 0;
    for (sequence, message) in messages.iter().enumerate() {
        let report = consumer.send_control(2, message).unwrap();
        assert_eq!((report.sequence, report.recipients), (sequence as u64, 1));
        bytes_sent += report.bytes as u64;
    }
    for (sequence, message) in messages.iter().enumerate() {
        let received = agent
            .recv_control_timeout(PROMPT)
            .unwrap()
            .expect("control message");
        assert_eq!(&received.message, message);
        assert_eq!(received.header.stamp.sequence, sequence as u64);
        assert_eq!(received.header.target_agent_id, 2);
        let expected = if sequence == 0 {
            Delivery::NewIncarnation {
                previous_epoch: None,
                missed: 0,
            }
        } else {
            Delivery::InOrder
        };
        assert_eq!(received.delivery, expected);
    }
    assert!(agent.try_recv_control().unwrap().is_none());
    let sent = *consumer
        .bandwidth()
        .get(2, Topic::Control, Direction::Sent)
        .unwrap();
    let received = *agent
        .bandwidth()
        .get(2, Topic::Control, Direction::Received)
        .unwrap();
    assert_eq!((sent.messages, sent.bytes), (2, bytes_sent));
    assert_eq!((received.messages, received.bytes), (2, bytes_sent));
    assert!(matches!(
        consumer.send_control(config.max_agents, &messages[1]),
        Err(TransportError::AgentIdOutOfRange { .. })
    ));
    // Nobody attached on agent 0's control topic: refused at once, not waited for.
    let start = Instant::now();
    assert!(matches!(
        consumer.send_control(0, &messages[1]),
        Err(TransportError::Undelivered { delivered: 0, .. })
    ));
    assert!(start.elapsed() < PROMPT);
}

#[test]
fn round_trip_in_one_process_with_exact_accounting() {
    const RECORDS: usize = 70_000; // above the initial segment size: exercises growth
    let config = TransportConfig::with_namespace(unique_namespace("roundtrip"));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let mut agent = AgentLink::open(&config, 5).unwrap();
    agent.send_descriptor(&synthetic_descriptor(9)).unwrap();
    let records: Vec<GaussianRecord> = (0..RECORDS)
        .map(|i| GaussianRecord {
            opacity_logit: i as f32,
            ..Default::default()
        })
        .collect();
    assert_eq!(
        agent
            .send_patch(9, CoordinateFrame::World, &records)
            .unwrap()
            .recipients,
        1
    );

    let mut got_descriptor = false;
    let mut got_patch = false;
    while !(got_descriptor && got_patch) {
        match consumer.recv_timeout(PROMPT).unwrap().expect("message") {
            Incoming::Descriptor(d) => {
                assert_eq!(d.keyframe_id, 9);
                got_descriptor = true;
            }
            Incoming::Patch(p) => {
                assert_eq!(p.header().frame(), Ok(CoordinateFrame::World));
                assert_eq!(p.records(), &records[..]);
                got_patch = true;
            }
            Incoming::KeyframeImage(_) => panic!("this test sends no keyframe image"),
            Incoming::Lifecycle(_) => {}
        }
    }
    let mut shift = Pose::IDENTITY;
    shift.translation = [1.0, 2.0, 3.0];
    let poses = [KeyframePose {
        keyframe_id: 9,
        camera_to_world: shift,
    }];
    consumer.send_correction(5, shift, &poses).unwrap();
    let correction = agent
        .recv_correction_timeout(PROMPT)
        .unwrap()
        .expect("correction");
    assert_eq!(correction.poses(), &poses);
    assert_eq!(correction.header().agent_world_to_world, shift);
    drop(correction);

    let sent = agent.bandwidth();
    let patch = sent.get(5, Topic::Patch, Direction::Sent).unwrap();
    let patch_bytes = (RECORDS * size_of::<GaussianRecord>()) as u64;
    assert_eq!(patch.messages, 1);
    assert_eq!(
        patch.bytes,
        patch_bytes + size_of::<protocol::messages::PatchHeader>() as u64
    );
    assert_eq!(
        patch.bytes_copied, patch_bytes,
        "send_patch copies the records once"
    );
    assert_eq!(
        sent.get(5, Topic::Correction, Direction::Received)
            .unwrap()
            .messages,
        1
    );
    let received = consumer.bandwidth();
    assert_eq!(
        received
            .get(5, Topic::Patch, Direction::Received)
            .unwrap()
            .bytes,
        patch.bytes
    );
    assert_eq!(
        received
            .get(5, Topic::Descriptor, Direction::Received)
            .unwrap()
            .messages,
        1
    );
    assert!(received.bytes_per_second(5, Direction::Received) > 0.0);

    // Corrections to an id outside the swarm are refused.
    assert!(matches!(
        consumer.send_correction(config.max_agents, shift, &poses),
        Err(TransportError::AgentIdOutOfRange { .. })
    ));
}

/// Deterministic pixel `i` of test image `seed`: every field varies, and every 17th pixel has
/// no depth, so a shifted, truncated or byte-swapped image cannot compare equal.
fn test_pixel(seed: u64, i: usize) -> RgbdPixel {
    let mixed = (i as u64).wrapping_mul(2_654_435_761) ^ seed;
    RgbdPixel {
        rgb: [mixed as u8, (mixed >> 8) as u8, (mixed >> 16) as u8],
        reserved: 0,
        depth_mm: if i.is_multiple_of(17) {
            RgbdPixel::INVALID_DEPTH_MM
        } else {
            (500 + (mixed % 7000)) as u16
        },
    }
}

/// Metadata of a test image of `width x height`, with intrinsics scaled to that size from a
/// 640x480 camera and a non-trivial pose, so every header field is distinguishable.
fn test_image_meta(keyframe_id: u64, width: u32, height: u32) -> KeyframeImageMeta {
    let scale = f64::from(width) / 640.0;
    let half_angle = 0.1 * keyframe_id as f64;
    KeyframeImageMeta {
        keyframe_id,
        frame_index: 10 * keyframe_id + 3,
        timestamp_s: 0.5 * keyframe_id as f64 + 0.25,
        camera_to_agent_world: Pose {
            translation: [keyframe_id as f64, -2.0, 0.75],
            rotation_wxyz: [half_angle.cos(), 0.0, 0.0, half_angle.sin()],
        },
        intrinsics: Intrinsics {
            fx: 585.0 * scale,
            fy: 585.0 * scale,
            cx: 319.5 * scale,
            cy: 239.5 * scale,
            width,
            height,
        },
        width,
        height,
    }
}

fn assert_header_matches(header: &KeyframeImageHeader, meta: &KeyframeImageMeta, agent_id: u32) {
    assert_eq!(header.stamp.agent_id, agent_id);
    assert_eq!(header.keyframe_id, meta.keyframe_id);
    assert_eq!(header.frame_index, meta.frame_index);
    assert_eq!(header.timestamp_s, meta.timestamp_s);
    assert_eq!(header.camera_to_agent_world, meta.camera_to_agent_world);
    assert_eq!(header.intrinsics, meta.intrinsics);
    assert_eq!((header.width, header.height), (meta.width, meta.height));
}

#[test]
fn keyframe_images_arrive_intact_and_grow_the_segment() {
    const AGENT: u32 = 3;
    let config = TransportConfig::with_namespace(unique_namespace("kfimage"));
    assert_eq!(config.initial_keyframe_image_pixels, 320 * 240);
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let mut agent = AgentLink::open(&config, AGENT).unwrap();

    // QVGA fits the initial segment; VGA is 4x larger and forces a re-allocation. The third
    // image (VGA again, built in place) reuses the grown segment.
    let sizes = [(320u32, 240u32), (640, 480), (640, 480)];
    let metas: Vec<_> = sizes
        .iter()
        .enumerate()
        .map(|(k, &(w, h))| test_image_meta(k as u64 + 1, w, h))
        .collect();
    let images: Vec<Vec<RgbdPixel>> = metas
        .iter()
        .map(|m| {
            (0..(m.width * m.height) as usize)
                .map(|i| test_pixel(m.keyframe_id, i))
                .collect()
        })
        .collect();
    for (k, (meta, pixels)) in metas.iter().zip(&images).enumerate() {
        let report = if k < 2 {
            agent.send_keyframe_image(meta, pixels).unwrap()
        } else {
            agent
                .send_keyframe_image_with(meta, |i| test_pixel(meta.keyframe_id, i))
                .unwrap()
        };
        assert_eq!(report.sequence, k as u64);
        assert_eq!(report.recipients, 1);
        assert_eq!(
            report.bytes,
            size_of_val(&pixels[..]) + size_of::<KeyframeImageHeader>()
        );
    }

    for (k, (meta, pixels)) in metas.iter().zip(&images).enumerate() {
        let incoming = consumer.recv_timeout(PROMPT).unwrap().expect("image");
        assert_eq!(incoming.topic(), Topic::KeyframeImage);
        assert_eq!(incoming.agent_id(), AGENT);
        assert_eq!(incoming.stamp().sequence, k as u64);
        let expected_delivery = if k == 0 {
            Delivery::NewIncarnation {
                previous_epoch: None,
                missed: 0,
            }
        } else {
            Delivery::InOrder
        };
        assert_eq!(incoming.delivery(), expected_delivery, "image {k}");
        let Incoming::KeyframeImage(image) = incoming else {
            panic!("expected a keyframe image");
        };
        assert_header_matches(image.header(), meta, AGENT);
        assert_eq!(image.header().stamp.epoch, agent.epoch());
        assert_eq!(image.pixels().len(), pixels.len(), "image {k} size");
        if let Some(i) = (0..pixels.len()).find(|&i| image.pixels()[i] != pixels[i]) {
            panic!(
                "image {k} pixel {i} arrived as {:?}, sent {:?}",
                image.pixels()[i],
                pixels[i]
            );
        }
    }
    assert!(
        consumer.try_recv().unwrap().is_none(),
        "nothing else was sent"
    );

    let header_bytes = size_of::<KeyframeImageHeader>() as u64;
    let pixel_bytes: Vec<u64> = images.iter().map(|p| size_of_val(&p[..]) as u64).collect();
    let sent = agent.bandwidth();
    let sent = sent
        .get(AGENT, Topic::KeyframeImage, Direction::Sent)
        .unwrap();
    assert_eq!(sent.messages, 3);
    assert_eq!(
        sent.bytes,
        pixel_bytes.iter().sum::<u64>() + 3 * header_bytes
    );
    assert_eq!(
        sent.bytes_copied,
        pixel_bytes[0] + pixel_bytes[1],
        "send_keyframe_image copies once, send_keyframe_image_with not at all"
    );
    let received = consumer.bandwidth();
    let received = received
        .get(AGENT, Topic::KeyframeImage, Direction::Received)
        .unwrap();
    assert_eq!(
        (received.messages, received.bytes, received.gaps),
        (3, sent.bytes, 0)
    );
}

#[test]
fn invalid_keyframe_images_are_refused_with_a_clear_error() {
    let config = TransportConfig {
        required_consumers: 0,
        ..TransportConfig::with_namespace(unique_namespace("kfinvalid"))
    };
    let mut agent = AgentLink::open(&config, 0).unwrap();
    let meta = test_image_meta(7, 320, 240);
    let pixels = vec![RgbdPixel::default(); 320 * 240];

    match agent.send_keyframe_image(&meta, &pixels[1..]) {
        Err(err @ TransportError::InvalidMessage { .. }) => {
            let text = err.to_string();
            assert!(
                text.contains("320x240") && text.contains("76800") && text.contains("76799"),
                "{text}"
            );
            assert!(text.contains("keyframe_image"), "names the service: {text}");
        }
        other => panic!(
            "expected InvalidMessage, got {:?}",
            other.map(|r| r.sequence)
        ),
    }
    let empty = KeyframeImageMeta { width: 0, ..meta };
    let err = agent.send_keyframe_image(&empty, &[]).unwrap_err();
    assert!(err.to_string().contains("empty"), "{err}");
    let err = agent
        .send_keyframe_image_with(&empty, |_| RgbdPixel::default())
        .unwrap_err();
    assert!(err.to_string().contains("empty"), "{err}");
    // Downscaled image, intrinsics left at full size: the consensus would lift features wrongly.
    let unscaled = KeyframeImageMeta {
        intrinsics: test_image_meta(7, 640, 480).intrinsics,
        ..meta
    };
    let err = agent.send_keyframe_image(&unscaled, &pixels).unwrap_err();
    assert!(err.to_string().contains("intrinsics"), "{err}");
    let mut bad_pose = meta;
    bad_pose.camera_to_agent_world.rotation_wxyz = [0.0; 4];
    let err = agent.send_keyframe_image(&bad_pose, &pixels).unwrap_err();
    assert!(err.to_string().contains("camera_to_agent_world"), "{err}");

    // Refused messages use no sequence number, so receivers see no gap.
    let report = agent.send_keyframe_image(&meta, &pixels).unwrap();
    assert_eq!((report.sequence, report.recipients), (0, 0));
}

#[test]
fn keyframe_image_is_drained_before_the_agents_goodbye() {
    const AGENT: u32 = 1;
    let config = TransportConfig::with_namespace(unique_namespace("kfdrain"));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let agent_config = config.clone();
    // The agent runs on its own thread because close() blocks until the consumer acknowledges.
    let agent = std::thread::spawn(move || {
        let mut agent = AgentLink::open(&agent_config, AGENT)?;
        let meta = test_image_meta(4, 640, 480);
        agent.send_keyframe_image_with(&meta, |i| test_pixel(4, i))?;
        agent.close()
    });
    let mut image_seen = false;
    loop {
        match consumer.recv_timeout(PROMPT).unwrap().expect("message") {
            Incoming::KeyframeImage(image) => {
                assert_eq!(image.header().keyframe_id, 4);
                assert!(
                    image
                        .pixels()
                        .iter()
                        .enumerate()
                        .all(|(i, p)| *p == test_pixel(4, i))
                );
                image_seen = true;
            }
            Incoming::Lifecycle(l) if l.kind() == Ok(LifecycleKind::Goodbye) => break,
            Incoming::Lifecycle(_) => {}
            _ => panic!("only a keyframe image and a goodbye were sent"),
        }
    }
    assert!(image_seen, "the goodbye was delivered before the image");
    agent
        .join()
        .expect("agent thread")
        .expect("goodbye acknowledged");
}
