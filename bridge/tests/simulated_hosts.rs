//! Two simulated hosts joined only by their bridges' zenoh connection on 127.0.0.1 (TLS with
//! mutual authentication, the bridges' default, with certificates from `mac-bridge certs`):
//! host A (an agent and an agent-role bridge) runs in a mount namespace of its own with a
//! private /dev/shm and iceoryx2 root (scripts/simulated_host.sh), so no shared memory can reach
//! host B (this test process as the consumer, and a consumer-role bridge). A message can only
//! cross through the bridges. Needs root (unshare --mount); skipped with a message otherwise.
//!
//! The agent is this test binary itself, started again inside host A with `AGENT_ROLE` set (it
//! then runs [`agent_on_host_a`] only).

use std::io::{BufRead, BufReader};
use std::process::Stdio;
use std::time::{Duration, Instant};

mod common;

use common::{Reaped, TwoHosts, is_root};
use protocol::bench::{SAMPLE_INTRINSICS, synthetic_descriptor, synthetic_record};
use protocol::messages::{CoordinateFrame, KeyframePose, LifecycleKind, Pose};
use protocol::transport::{AgentLink, ConsumerLink, Delivery, Incoming, TransportConfig};

/// Environment variable that makes this test binary the agent of host A; its value is the
/// swarm namespace.
const AGENT_ROLE: &str = "MAC_BRIDGE_TEST_AGENT_NAMESPACE";
/// Records of the large patch (56 MB): the size of a large merged map.
const LARGE_PATCH_RECORDS: usize = 1_000_000;
const DESCRIPTORS: u64 = 3;
const PATCH_SEED: u64 = 42;
const TIMEOUT: Duration = Duration::from_secs(120);

/// The agent of host A: hello, descriptors, one large patch; waits for the correction the
/// consumer sends back over the network, then says goodbye (which returns only once the far
/// consumer acknowledged it). Prints its epoch and what it received for the test to check.
#[test]
#[ignore = "runs only as the agent process of `large_patch_and_stamps_cross_between_simulated_hosts`"]
fn agent_on_host_a() {
    let Ok(namespace) = std::env::var(AGENT_ROLE) else {
        return;
    };
    let config = TransportConfig::for_swarm(namespace, Some(1));
    let mut link = AgentLink::open(&config, 0).unwrap();
    println!("epoch={}", link.epoch());
    link.announce(SAMPLE_INTRINSICS, 7, 0).unwrap();
    for keyframe in 0..DESCRIPTORS {
        link.send_descriptor(&synthetic_descriptor(keyframe))
            .unwrap();
    }
    link.send_patch_with(
        DESCRIPTORS,
        CoordinateFrame::AgentWorld,
        LARGE_PATCH_RECORDS,
        |i| synthetic_record(PATCH_SEED, i),
    )
    .unwrap();
    let correction = link
        .recv_correction_timeout(TIMEOUT)
        .unwrap()
        .expect("a correction from the far consumer");
    println!(
        "correction poses={} sequence={} in_order={}",
        correction.poses().len(),
        correction.header().stamp.sequence,
        matches!(
            correction.delivery,
            Delivery::NewIncarnation { missed: 0, .. }
        )
    );
    drop(correction);
    link.close().unwrap();
    println!("closed");
}

#[test]
fn large_patch_and_stamps_cross_between_simulated_hosts() {
    if !is_root() {
        eprintln!("skipped: simulated hosts need root (unshare --mount)");
        return;
    }
    let hosts = TwoHosts::new("bridgetest");

    // Host B: this process and the consumer-role bridge.
    let config = TransportConfig::for_swarm(hosts.namespace.clone(), Some(1));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let _consumer_bridge = hosts.consumer_bridge();

    // Host A: the agent (this binary again) and the agent-role bridge.
    let mut agent = Reaped(
        hosts
            .agent_host(&[], "agent_on_host_a", &["--nocapture"], AGENT_ROLE)
            .stdout(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let agent_lines = agent.0.stdout.take().unwrap();
    let (lines_tx, lines_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(agent_lines).lines().map_while(Result::ok) {
            let _ = lines_tx.send(line);
        }
    });
    let next_line = |prefix: &str| -> String {
        let start = Instant::now();
        loop {
            let wait = TIMEOUT.saturating_sub(start.elapsed());
            let line = lines_rx
                .recv_timeout(wait)
                .unwrap_or_else(|_| panic!("agent never printed '{prefix}...'"));
            if let Some(rest) = line.strip_prefix(prefix) {
                return rest.to_string();
            }
        }
    };
    let epoch: u64 = next_line("epoch=").parse().unwrap();

    // Everything the agent sent arrives, in order, with its own stamps.
    let mut hello = false;
    let mut descriptors = Vec::new();
    let start = Instant::now();
    let patch = loop {
        assert!(start.elapsed() < TIMEOUT, "the patch did not arrive");
        let Some(incoming) = consumer.recv_timeout(Duration::from_secs(1)).unwrap() else {
            continue;
        };
        let stamp = incoming.stamp();
        assert_eq!((stamp.agent_id, stamp.epoch), (0, epoch), "{stamp:?}");
        match incoming {
            Incoming::Lifecycle(l) if l.kind() == Ok(LifecycleKind::Hello) => {
                assert_eq!(l.config_hash, 7);
                hello = true;
            }
            Incoming::Lifecycle(_) => {}
            Incoming::Descriptor(d) => {
                assert!(hello, "the hello comes before the data");
                assert_eq!(d.keyframe_id, descriptors.len() as u64);
                descriptors.push(d.stamp.sequence);
            }
            Incoming::Patch(p) => break p,
            Incoming::KeyframeImage(_) => panic!("no image was sent"),
        }
    };
    assert_eq!(descriptors, (0..DESCRIPTORS).collect::<Vec<_>>());
    assert_eq!(patch.header().stamp.sequence, 0);
    assert_eq!(patch.header().keyframe_id, DESCRIPTORS);
    assert_eq!(patch.records().len(), LARGE_PATCH_RECORDS);
    let corrupted = patch
        .records()
        .iter()
        .enumerate()
        .filter(|&(i, record)| *record != synthetic_record(PATCH_SEED, i))
        .count();
    assert_eq!(corrupted, 0, "records changed on the way");
    drop(patch);

    // The way back: a correction reaches the agent with the consumer's stamp.
    let poses = [KeyframePose {
        keyframe_id: 1,
        camera_to_world: Pose::IDENTITY,
    }];
    let start = Instant::now();
    while consumer.send_correction(0, Pose::IDENTITY, &poses).is_err() {
        assert!(
            start.elapsed() < TIMEOUT,
            "the correction could not be sent"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(next_line("correction "), "poses=1 sequence=0 in_order=true");

    // The goodbye crosses after the data, and the agent's close returns only once this consumer
    // acknowledged it (relayed back by the bridges).
    let start = Instant::now();
    loop {
        assert!(start.elapsed() < TIMEOUT, "no goodbye");
        if let Some(Incoming::Lifecycle(l)) = consumer.recv_timeout(Duration::from_secs(1)).unwrap()
            && l.kind() == Ok(LifecycleKind::Goodbye)
        {
            break;
        }
    }
    next_line("closed");
    let status = agent.0.wait().unwrap();
    assert!(status.success(), "host A ended with {status}");
}
