//! Multi-process tests of the transport: this test process is the consumer (consensus side), a
//! spawned `protocol-peer agent` process is the agent. Each test uses its own namespace.

mod common;

use std::time::Duration;

use common::{Peer, unique_namespace};
use protocol::bench::{
    descriptor_checksum, records_checksum, synthetic_descriptor, synthetic_record,
};
use protocol::messages::{ControlMessage, KeyframePose, LifecycleKind, Pose};
use protocol::services::Topic;
use protocol::transport::{
    AgentLink, ConsumerLink, Delivery, Direction, Incoming, TransportConfig, TransportError,
};

/// Longest wait for the next message from a peer that is expected to send one.
const RECV_TIMEOUT: Duration = Duration::from_secs(30);
/// Time given to a publisher-first agent to reach its handshake wait before the consumer opens.
const PUBLISHER_HEAD_START: Duration = Duration::from_millis(300);

/// What the consumer saw from one agent incarnation.
#[derive(Default, Debug)]
struct Seen {
    hello: Option<(u64, Delivery)>,
    descriptors: Vec<(u64, u64, Delivery, u64)>, // (sequence, keyframe id, delivery, checksum)
    patches: Vec<(u64, usize, u64, Delivery)>,   // (keyframe id, records, checksum, delivery)
    goodbye: bool,
}

/// Receives until agent `agent_id` says goodbye; `on_hello` may answer with a correction.
fn receive_until_goodbye(
    consumer: &mut ConsumerLink,
    agent_id: u32,
    mut on_hello: impl FnMut(&mut ConsumerLink),
) -> Seen {
    let mut seen = Seen::default();
    while !seen.goodbye {
        let incoming = consumer
            .recv_timeout(RECV_TIMEOUT)
            .expect("receive")
            .unwrap_or_else(|| panic!("nothing received within {RECV_TIMEOUT:?}; so far {seen:?}"));
        assert_eq!(incoming.agent_id(), agent_id);
        let delivery = incoming.delivery();
        let sequence = incoming.stamp().sequence;
        let mut hello = false;
        match &incoming {
            Incoming::Lifecycle(l) => match l.kind().expect("known lifecycle kind") {
                LifecycleKind::Hello => {
                    seen.hello = Some((l.stamp.epoch, delivery));
                    hello = true;
                }
                LifecycleKind::Alive => {}
                LifecycleKind::Goodbye => seen.goodbye = true,
            },
            Incoming::Descriptor(d) => seen.descriptors.push((
                sequence,
                d.keyframe_id,
                delivery,
                descriptor_checksum(&d.descriptor),
            )),
            Incoming::Patch(p) => seen.patches.push((
                p.header().keyframe_id,
                p.records().len(),
                records_checksum(p.records()),
                delivery,
            )),
            Incoming::KeyframeImage(k) => {
                panic!(
                    "the test peer sends no keyframe images, got keyframe {}",
                    k.header().keyframe_id
                )
            }
        }
        drop(incoming);
        if hello {
            on_hello(consumer);
        }
    }
    seen
}

fn assert_complete(seen: &Seen, descriptors: u64, patches: u64, patch_records: usize) {
    let (_, hello_delivery) = seen.hello.expect("hello received");
    assert_eq!(
        hello_delivery,
        Delivery::NewIncarnation {
            previous_epoch: None,
            missed: 0
        }
    );
    assert_eq!(
        seen.descriptors.len() as u64,
        descriptors,
        "every descriptor delivered"
    );
    for (i, &(sequence, keyframe_id, delivery, checksum)) in seen.descriptors.iter().enumerate() {
        assert_eq!(sequence, i as u64);
        assert_eq!(keyframe_id, i as u64);
        let expected_delivery = if i == 0 {
            Delivery::NewIncarnation {
                previous_epoch: None,
                missed: 0,
            }
        } else {
            Delivery::InOrder
        };
        assert_eq!(delivery, expected_delivery, "descriptor {i}");
        assert_eq!(
            checksum,
            descriptor_checksum(&synthetic_descriptor(i as u64).descriptor),
            "descriptor {i} content"
        );
    }
    assert_eq!(seen.patches.len() as u64, patches, "every patch delivered");
    for (p, &(keyframe_id, records, checksum, _)) in seen.patches.iter().enumerate() {
        assert_eq!(keyframe_id, p as u64);
        assert_eq!(records, patch_records);
        let expected: Vec<_> = (0..patch_records)
            .map(|i| synthetic_record(p as u64, i))
            .collect();
        assert_eq!(checksum, records_checksum(&expected), "patch {p} content");
    }
}

#[test]
fn subscriber_first_delivers_every_message_and_the_correction() {
    let config = TransportConfig::with_namespace(unique_namespace("subfirst"));
    let mut consumer = ConsumerLink::open(&config).expect("consumer opens");
    let mut agent = Peer::agent(
        &config.namespace,
        0,
        &[
            "--descriptors",
            "100",
            "--patches",
            "3",
            "--patch-records",
            "5000",
            "--await-correction",
        ],
    );
    let correction = [KeyframePose {
        keyframe_id: 42,
        camera_to_world: Pose::IDENTITY,
    }];
    let mut correction_report = None;
    let seen = receive_until_goodbye(&mut consumer, 0, |c| {
        let mut shift = Pose::IDENTITY;
        shift.translation[0] = 1.5;
        correction_report = Some(
            c.send_correction(0, shift, &correction)
                .expect("correction delivered"),
        );
    });
    assert_complete(&seen, 100, 3, 5000);
    assert_eq!(correction_report.expect("correction sent").recipients, 1);
    assert_eq!(
        agent.expect_line("correction"),
        "correction poses=1 first_keyframe=42 tx=1.5"
    );
    let (status, stderr) = agent.wait();
    assert!(status.success(), "agent failed: {stderr}");

    let report = consumer.bandwidth();
    let descriptors = report
        .get(0, Topic::Descriptor, Direction::Received)
        .expect("descriptor traffic");
    assert_eq!(
        (descriptors.messages, descriptors.gaps, descriptors.missed),
        (100, 0, 0)
    );
    assert_eq!(
        descriptors.bytes,
        100 * size_of::<protocol::messages::KeyframeDescriptor>() as u64
    );
    let patches = report
        .get(0, Topic::Patch, Direction::Received)
        .expect("patch traffic");
    assert_eq!(patches.messages, 3);
    assert!(patches.bytes >= 3 * 5000 * size_of::<protocol::messages::GaussianRecord>() as u64);
    assert_eq!(
        report
            .get(0, Topic::Correction, Direction::Sent)
            .map(|t| t.messages),
        Some(1)
    );
}

/// Control messages cross the process boundary as codec frames: the agent process decodes them
/// in order with their sequence numbers.
#[test]
fn control_messages_reach_an_agent_process() {
    let config = TransportConfig::with_namespace(unique_namespace("control"));
    let mut consumer = ConsumerLink::open(&config).expect("consumer opens");
    let mut agent = Peer::agent(
        &config.namespace,
        0,
        &["--descriptors", "1", "--await-control", "2"],
    );
    let messages = [
        ControlMessage::ResendKeyframe {
            keyframe_id: 7,
            reason: "no image".into(),
        },
        ControlMessage::Shutdown {
            reason: "test over".into(),
        },
    ];
    let seen = receive_until_goodbye(&mut consumer, 0, |c| {
        for message in &messages {
            c.send_control(0, message).expect("control delivered");
        }
    });
    assert!(seen.goodbye);
    assert_eq!(
        agent.expect_line("control"),
        "control seq=0 resend_keyframe keyframe=7 reason=no image"
    );
    assert_eq!(
        agent.expect_line("control"),
        "control seq=1 shutdown reason=test over"
    );
    let (status, stderr) = agent.wait();
    assert!(status.success(), "agent failed: {stderr}");
    let sent = consumer
        .bandwidth()
        .get(0, Topic::Control, Direction::Sent)
        .map(|t| t.messages);
    assert_eq!(sent, Some(2));
}

#[test]
fn publisher_first_delivers_every_message() {
    let config = TransportConfig::with_namespace(unique_namespace("pubfirst"));
    let mut agent = Peer::agent(
        &config.namespace,
        1,
        &[
            "--descriptors",
            "50",
            "--patches",
            "2",
            "--patch-records",
            "1000",
        ],
    );
    agent.expect_line("opened");
    // The agent is now blocked in its handshake (announce waits for a consumer).
    std::thread::sleep(PUBLISHER_HEAD_START);
    let mut consumer = ConsumerLink::open(&config).expect("consumer opens");
    let seen = receive_until_goodbye(&mut consumer, 1, |_| {});
    assert_complete(&seen, 50, 2, 1000);
    let (status, stderr) = agent.wait();
    assert!(status.success(), "agent failed: {stderr}");
}

#[test]
fn million_gaussian_patch_arrives_intact() {
    const RECORDS: usize = 1_000_000;
    let config = TransportConfig::with_namespace(unique_namespace("million"));
    let mut consumer = ConsumerLink::open(&config).expect("consumer opens");
    let records = RECORDS.to_string();
    let mut agent = Peer::agent(
        &config.namespace,
        2,
        &["--patches", "1", "--patch-records", &records],
    );
    let seen = receive_until_goodbye(&mut consumer, 2, |_| {});
    assert_complete(&seen, 0, 1, RECORDS);
    let (status, stderr) = agent.wait();
    assert!(status.success(), "agent failed: {stderr}");
}

#[test]
fn sigkill_mid_stream_then_restart_is_accepted() {
    const AGENT: u32 = 3;
    const BEFORE_KILL: usize = 10;
    let config = TransportConfig::with_namespace(unique_namespace("sigkill"));
    let mut consumer = ConsumerLink::open(&config).expect("consumer opens");
    let mut first = Peer::agent(
        &config.namespace,
        AGENT,
        &["--forever", "--interval-ms", "5"],
    );
    let first_epoch: u64 = first.expect_line("opened epoch=")["opened epoch=".len()..]
        .parse()
        .expect("epoch");

    let mut descriptors = 0;
    while descriptors < BEFORE_KILL {
        let incoming = consumer
            .recv_timeout(RECV_TIMEOUT)
            .expect("receive")
            .expect("message before kill");
        if let Incoming::Descriptor(d) = &incoming {
            assert_eq!(d.stamp.epoch, first_epoch);
            descriptors += 1;
        }
    }
    first.kill(); // SIGKILL mid-stream: no goodbye, shared memory left behind.

    let mut second = Peer::agent(&config.namespace, AGENT, &["--descriptors", "5"]);
    let second_line = second.expect_line("opened epoch=");
    let second_epoch: u64 = second_line["opened epoch=".len()..].parse().expect("epoch");
    assert!(second_epoch > first_epoch, "a restart has a larger epoch");

    // Leftover samples of the dead incarnation may still be queued; then the new one follows.
    let mut hello = None;
    let mut fresh = Vec::new();
    let mut goodbye = false;
    while !goodbye {
        let incoming = consumer
            .recv_timeout(RECV_TIMEOUT)
            .expect("receive")
            .expect("message after restart");
        let stamp = incoming.stamp();
        if stamp.epoch == first_epoch {
            continue;
        }
        assert_eq!(stamp.epoch, second_epoch);
        match &incoming {
            Incoming::Lifecycle(l) if l.kind() == Ok(LifecycleKind::Hello) => {
                hello = Some(incoming.delivery())
            }
            Incoming::Lifecycle(l) if l.kind() == Ok(LifecycleKind::Goodbye) => goodbye = true,
            Incoming::Descriptor(_) => fresh.push((stamp.sequence, incoming.delivery())),
            _ => {}
        }
    }
    assert_eq!(
        hello,
        Some(Delivery::NewIncarnation {
            previous_epoch: Some(first_epoch),
            missed: 0
        }),
        "the restarted agent re-announced and was accepted as a new incarnation"
    );
    let sequences: Vec<u64> = fresh.iter().map(|f| f.0).collect();
    assert_eq!(
        sequences,
        vec![0, 1, 2, 3, 4],
        "fresh sequence numbers accepted"
    );
    assert_eq!(
        fresh[0].1,
        Delivery::NewIncarnation {
            previous_epoch: Some(first_epoch),
            missed: 0
        }
    );
    let (status, stderr) = second.wait();
    assert!(status.success(), "restarted agent failed: {stderr}");
    let report = consumer.bandwidth();
    let lifecycle = report
        .get(AGENT, Topic::Lifecycle, Direction::Received)
        .expect("lifecycle traffic");
    assert_eq!(lifecycle.incarnations, 2);
}

#[test]
fn duplicate_agent_id_is_refused_clearly() {
    const AGENT: u32 = 4;
    let config = TransportConfig::with_namespace(unique_namespace("duplicate"));
    let _first = AgentLink::open(&config, AGENT).expect("first agent opens");

    // Same process, same id.
    match AgentLink::open(&config, AGENT) {
        Err(TransportError::DuplicateAgent {
            agent_id: AGENT, ..
        }) => {}
        Err(other) => panic!("unexpected error: {other}"),
        Ok(_) => panic!("a second agent with id {AGENT} must be refused"),
    }

    // Another process, same id.
    let mut twin = Peer::agent(&config.namespace, AGENT, &["--descriptors", "1"]);
    let (status, stderr) = twin.wait();
    assert_eq!(
        status.code(),
        Some(3),
        "exit code for a duplicate agent; stderr: {stderr}"
    );
    assert!(
        stderr.contains(&format!(
            "agent id {AGENT} is already used by a live process"
        )),
        "{stderr}"
    );
}

#[test]
fn ipc_bench_runs_between_two_processes() {
    let config = protocol::bench::IpcBenchConfig {
        latency_samples: 20,
        warmup: 2,
        throughput_messages: 10,
        namespace: unique_namespace("bench"),
        ..protocol::bench::IpcBenchConfig::default()
    };
    let peer = protocol::bench::PeerCommand {
        program: common::peer_binary().into(),
        args: vec!["bench-peer".into()],
    };
    let report = protocol::bench::run_ipc_bench(&config, &peer).expect("bench runs");
    assert_eq!(report.patch_10k.samples, 20);
    assert_eq!(report.patch_10k_after_idle.samples, 20);
    assert!(
        report.patch_10k_median_us > 0.0 && report.patch_10k_p99_us >= report.patch_10k_median_us
    );
    assert!(report.patch_100k_msgs_per_s > 0.0);
    assert!(
        (report.copies_per_patch - 1.0).abs() < 1e-9,
        "copy path copies once: {}",
        report.copies_per_patch
    );
    assert_eq!(report.copies_per_patch_in_place, 0.0);
}
