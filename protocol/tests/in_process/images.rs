//! Exact bandwidth accounting on a round trip, and keyframe images: segment growth, pixel
//! integrity, refusal of invalid ones, drain before the agent's goodbye.

use protocol::bench::synthetic_descriptor;
use protocol::messages::{
    CoordinateFrame, GaussianRecord, Intrinsics, KeyframeImageHeader, KeyframePose, LifecycleKind,
    Pose, RgbdPixel,
};
use protocol::services::Topic;
use protocol::transport::{
    AgentLink, ConsumerLink, Delivery, Direction, Incoming, KeyframeImageMeta, TransportConfig,
    TransportError,
};

/// Bound for what should happen at once on a loaded 2-core machine.
use super::PROMPT;
use crate::common::unique_namespace;

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
