//! An agent on simulated host A publishes keyframes (descriptor, 320x240 RGB-D image with noisy
//! colour, patch of 10,000 random Gaussians: little for a compressor to find) as fast as it can
//! through an agent-role bridge capped at 100 kB/s
//! (`[network] agent_kb_per_s` in the file given with `--config`); host B is this test process
//! as the consumer and its consumer-role bridge. Every message arrives once, in order, decoded
//! back to the shared-memory layout and close to what was published; the bytes on the network
//! keep to the cap over the time they took; the encodings made them several times smaller.
//! Needs root (unshare --mount); skipped with a message otherwise.
//!
//! The agent is this test binary itself, started again inside host A with `AGENT_ROLE` set.

use std::process::Stdio;
use std::time::{Duration, Instant};

mod common;

use common::{Reaped, TwoHosts, is_root};
use protocol::bench::{SAMPLE_INTRINSICS, synthetic_descriptor};
use protocol::messages::{
    CoordinateFrame, GaussianRecord, Intrinsics, LifecycleKind, Pose, RgbdPixel,
};
use protocol::transport::{AgentLink, ConsumerLink, Incoming, KeyframeImageMeta, TransportConfig};

const AGENT_ROLE: &str = "MAC_BRIDGE_BUDGET_TEST_AGENT_NAMESPACE";
const KEYFRAMES: u64 = 6;
const RECORDS: usize = 10_000;
const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;
const CAP_KB_PER_S: f64 = 100.0;
const TIMEOUT: Duration = Duration::from_secs(120);

fn intrinsics() -> Intrinsics {
    Intrinsics {
        width: WIDTH,
        height: HEIGHT,
        fx: SAMPLE_INTRINSICS.fx / 2.0,
        fy: SAMPLE_INTRINSICS.fy / 2.0,
        cx: 159.5,
        cy: 119.5,
    }
}

/// A well-mixed 32-bit hash of (keyframe, index, field).
fn hash(keyframe: u64, index: usize, field: u64) -> u32 {
    let mut x = keyframe
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(index as u64)
        .wrapping_mul(0xBF58_476D_1CE4_E5B9)
        .wrapping_add(field.wrapping_mul(0x94D0_49BB_1331_11EB));
    x ^= x >> 31;
    x = x.wrapping_mul(0xD6E8_FEB8_6659_FD93);
    (x >> 32) as u32
}

fn unit(keyframe: u64, index: usize, field: u64) -> f32 {
    hash(keyframe, index, field) as f32 / u32::MAX as f32
}

/// A slanted wall (depth 1.5-2.3 m) with noisy colour.
fn pixel(keyframe: u64, i: usize) -> RgbdPixel {
    let (x, y) = ((i as u32 % WIDTH) as f32, (i as u32 / WIDTH) as f32);
    let noise = hash(keyframe, i, 0).to_le_bytes();
    RgbdPixel::new([noise[0], noise[1], noise[2]], 1.5 + 0.002 * x + 0.001 * y)
}

/// A random Gaussian in a 5 m box, visible (opacity 0.12-0.88).
fn record(keyframe: u64, i: usize) -> GaussianRecord {
    let u = |field| unit(keyframe, i, field);
    GaussianRecord {
        mean: [5.0 * u(1), 5.0 * u(2), 5.0 * u(3)],
        log_scale: [-6.0 + 3.0 * u(4), -6.0 + 3.0 * u(5), -6.0 + 3.0 * u(6)],
        rotation_wxyz: [1.0, u(7) - 0.5, u(8) - 0.5, u(9) - 0.5],
        opacity_logit: -2.0 + 4.0 * u(10),
        colour: [u(11), u(12), u(13)],
    }
}

#[test]
#[ignore = "runs only as the agent process of `a_capped_agent_keeps_to_its_budget_and_loses_nothing`"]
fn bulk_publishing_agent_on_host_a() {
    let Ok(namespace) = std::env::var(AGENT_ROLE) else {
        return;
    };
    let config = TransportConfig::for_swarm(namespace, Some(1));
    let mut link = AgentLink::open(&config, 0).unwrap();
    link.announce(SAMPLE_INTRINSICS, 7, 0).unwrap();
    for keyframe in 0..KEYFRAMES {
        while let Err(e) = link.send_descriptor(&synthetic_descriptor(keyframe)) {
            eprintln!("descriptor {keyframe} not delivered yet: {e}");
        }
        let meta = KeyframeImageMeta {
            keyframe_id: keyframe,
            frame_index: keyframe * 10,
            timestamp_s: keyframe as f64,
            camera_to_agent_world: Pose::IDENTITY,
            intrinsics: intrinsics(),
            width: WIDTH,
            height: HEIGHT,
        };
        while let Err(e) = link.send_keyframe_image_with(&meta, |i| pixel(keyframe, i)) {
            eprintln!("image {keyframe} not delivered yet: {e}");
        }
        while let Err(e) =
            link.send_patch_with(keyframe, CoordinateFrame::AgentWorld, RECORDS, |i| {
                record(keyframe, i)
            })
        {
            eprintln!("patch {keyframe} not delivered yet: {e}");
        }
    }
    // The goodbye waits behind what the budget defers, so its acknowledgement may come after
    // the agent stops waiting (the agent goes anyway; the bridge delivers it later).
    if let Err(e) = link.close() {
        eprintln!("goodbye: {e}");
    }
}

#[test]
fn a_capped_agent_keeps_to_its_budget_and_loses_nothing() {
    if !is_root() {
        eprintln!("skipped: simulated hosts need root (unshare --mount)");
        return;
    }
    let hosts = TwoHosts::new("budgettest");
    let run_config = hosts.work.path().join("config.toml");
    std::fs::write(
        &run_config,
        format!("[network]\nagent_kb_per_s = {CAP_KB_PER_S}\n"),
    )
    .unwrap();
    let report = hosts.work.path().join("bridge_agent_0.json");

    let config = TransportConfig::for_swarm(hosts.namespace.clone(), Some(1));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let _consumer_bridge = hosts.consumer_bridge();
    let bridge_args = [
        "--config".as_ref(),
        run_config.as_os_str(),
        "--report".as_ref(),
        report.as_os_str(),
    ];
    let mut agent = Reaped(
        hosts
            .agent_host(
                &bridge_args,
                "bulk_publishing_agent_on_host_a",
                &[],
                AGENT_ROLE,
            )
            .stdout(Stdio::null())
            .spawn()
            .unwrap(),
    );

    let (mut descriptors, mut images, mut patches) = (Vec::new(), Vec::new(), Vec::new());
    let mut first_bulk: Option<Instant> = None;
    let mut last_bulk = Instant::now();
    let start = Instant::now();
    loop {
        assert!(
            start.elapsed() < TIMEOUT,
            "no goodbye; images {images:?}, patches {patches:?}"
        );
        let Some(incoming) = consumer.recv_timeout(Duration::from_millis(100)).unwrap() else {
            continue;
        };
        match incoming {
            Incoming::Descriptor(d) => descriptors.push(d.keyframe_id),
            Incoming::KeyframeImage(image) => {
                let header = *image.header();
                let id = header.keyframe_id;
                // Full or half resolution, with intrinsics that match.
                let binning = WIDTH / header.width;
                assert!(
                    binning == 1 || binning == 2,
                    "image {id}: {}x{}",
                    header.width,
                    header.height
                );
                assert_eq!(
                    (header.width * binning, header.height * binning),
                    (WIDTH, HEIGHT)
                );
                assert_eq!(
                    (header.intrinsics.width, header.intrinsics.height),
                    (header.width, header.height)
                );
                assert!((header.intrinsics.fx * f64::from(binning) - intrinsics().fx).abs() < 1e-9);
                for (i, p) in image.pixels().iter().enumerate() {
                    let (x, y) = (i as u32 % header.width, i as u32 / header.width);
                    let original = pixel(id, ((y * binning) * WIDTH + x * binning) as usize);
                    let (got, want) = (p.depth_m().unwrap(), original.depth_m().unwrap());
                    assert!(
                        (got - want).abs() < 0.005,
                        "image {id} pixel {i}: depth {got} vs {want}"
                    );
                }
                images.push(id);
                first_bulk.get_or_insert_with(Instant::now);
                last_bulk = Instant::now();
            }
            Incoming::Patch(patch) => {
                let id = patch.header().keyframe_id;
                assert_eq!(patch.records().len(), RECORDS, "patch {id}");
                for (i, r) in patch.records().iter().enumerate() {
                    let original = record(id, i);
                    for axis in 0..3 {
                        assert!(
                            (r.mean[axis] - original.mean[axis]).abs() < 1e-3,
                            "patch {id} record {i}"
                        );
                        assert!((r.colour[axis] - original.colour[axis]).abs() <= 1.0 / 255.0);
                    }
                    assert!((r.opacity_logit - original.opacity_logit).abs() < 5e-3);
                }
                patches.push(id);
                first_bulk.get_or_insert_with(Instant::now);
                last_bulk = Instant::now();
            }
            Incoming::Lifecycle(l) if l.kind() == Ok(LifecycleKind::Goodbye) => break,
            _ => {}
        }
    }
    let all: Vec<u64> = (0..KEYFRAMES).collect();
    assert_eq!(descriptors, all, "every descriptor once, in order");
    assert_eq!(images, all, "every image once, in order");
    assert_eq!(patches, all, "every patch once, in order");
    let status = agent.0.wait().unwrap();
    assert!(status.success(), "host A ended with {status}");

    // Host A's bridge wrote its report when the host stopped.
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let budget = &report["budget"]["0"];
    let (raw, wire) = (
        budget["raw_bytes"].as_f64().unwrap(),
        budget["wire_bytes"].as_f64().unwrap(),
    );
    let span = (last_bulk - first_bulk.unwrap()).as_secs_f64();
    eprintln!("raw {raw} bytes, on the network {wire} bytes in {span:.2} s; budget {budget}");
    assert!(raw >= KEYFRAMES as f64 * (RECORDS * 56 + (WIDTH * HEIGHT * 6) as usize) as f64);
    assert!(raw / wire >= 2.5, "encodings: {raw} -> {wire} bytes");
    let cap = CAP_KB_PER_S * 1000.0;
    // The token bucket: at most one second of burst plus the rate over the span, and the
    // last message (which may put the bucket in debt); and the cap did hold messages back.
    let largest = 400_000.0;
    assert!(
        wire <= cap * (span + 1.0) + largest,
        "{wire} bytes in {span} s"
    );
    assert!(
        span >= (wire - cap - largest) / cap,
        "{wire} bytes in only {span} s"
    );
    assert!(budget["deferral_max_s"].as_f64().unwrap() > 1.0);
}
