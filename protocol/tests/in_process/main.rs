//! Transport behaviour that needs no second process: timeouts, shutdown, idle CPU use, service
//! limit mismatches, message validation, exact bandwidth accounting, keyframe images (segment
//! growth, pixel integrity, drain before goodbye).

#[path = "../common/mod.rs"]
mod common;
mod images;

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use common::unique_namespace;
use protocol::bench::synthetic_descriptor;
use protocol::messages::{
    ControlMessage, CoordinateFrame, GaussianRecord, KeyframeDescriptor, Pose,
};
use protocol::services::{ServiceNames, Topic};
use protocol::transport::{
    AgentLink, ConsumerLink, Delivery, Direction, FullQueuePolicies, FullQueuePolicy, Incoming,
    TransportConfig, TransportError,
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
