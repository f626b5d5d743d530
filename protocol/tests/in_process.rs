//! Transport behaviour that needs no second process: timeouts, shutdown, idle CPU use, service
//! limit mismatches, message validation and exact bandwidth accounting.

mod common;

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use common::unique_namespace;
use protocol::bench::synthetic_descriptor;
use protocol::messages::{CoordinateFrame, GaussianRecord, KeyframeDescriptor, KeyframePose, Pose};
use protocol::services::Topic;
use protocol::transport::{
    AgentLink, ConsumerLink, Direction, Incoming, TransportConfig, TransportError,
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
