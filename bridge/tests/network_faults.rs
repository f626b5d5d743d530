//! The consumer host's bridge is SIGKILLed mid-run and started again after an outage, while an
//! agent on another simulated host keeps publishing: every message the agent published reaches
//! the consumer once, in order (what was lost in flight is sent again from the agent host's
//! bridge, repeats are dropped by stamp). Host A (agent and agent-role bridge) runs in a mount
//! namespace of its own (scripts/simulated_host.sh); host B is this test process as the consumer
//! and its consumer-role bridge. Needs root (unshare --mount); skipped with a message otherwise.
//!
//! The agent is this test binary itself, started again inside host A with `AGENT_ROLE` set (it
//! then runs [`publishing_agent_on_host_a`] only).

use std::process::Stdio;
use std::time::{Duration, Instant};

mod common;

use common::{Reaped, TwoHosts, is_root};
use protocol::bench::{SAMPLE_INTRINSICS, synthetic_descriptor};
use protocol::messages::LifecycleKind;
use protocol::transport::{AgentLink, ConsumerLink, Incoming, TransportConfig};

/// Environment variable that makes this test binary the agent of host A; its value is the
/// swarm namespace.
const AGENT_ROLE: &str = "MAC_BRIDGE_FAULT_TEST_AGENT_NAMESPACE";
const KEYFRAMES: u64 = 120;
/// Between two of the agent's descriptors: the run lasts a few seconds, the outage falls in it.
const PUBLISH_EVERY: Duration = Duration::from_millis(25);
/// Descriptors received before the consumer host's bridge is killed.
const KILL_AFTER: usize = 20;
/// How long the consumer host stays without a bridge.
const OUTAGE: Duration = Duration::from_secs(3);
const TIMEOUT: Duration = Duration::from_secs(90);

/// The agent of host A: hello, then a descriptor every `PUBLISH_EVERY`; a send that finds no
/// consumer (its host unreachable) is tried again, as an agent queues a keyframe. Then goodbye.
#[test]
#[ignore = "runs only as the agent process of `every_message_crosses_a_consumer_bridge_kill_and_restart`"]
fn publishing_agent_on_host_a() {
    let Ok(namespace) = std::env::var(AGENT_ROLE) else {
        return;
    };
    let config = TransportConfig::for_swarm(namespace, Some(1));
    let mut link = AgentLink::open(&config, 0).unwrap();
    link.announce(SAMPLE_INTRINSICS, 7, 0).unwrap();
    for keyframe in 0..KEYFRAMES {
        while let Err(e) = link.send_descriptor(&synthetic_descriptor(keyframe)) {
            eprintln!("keyframe {keyframe} not delivered yet: {e}");
        }
        std::thread::sleep(PUBLISH_EVERY);
    }
    link.close().unwrap();
}

#[test]
fn every_message_crosses_a_consumer_bridge_kill_and_restart() {
    if !is_root() {
        eprintln!("skipped: simulated hosts need root (unshare --mount)");
        return;
    }
    let hosts = TwoHosts::new("faulttest");

    // Host B: this process and the consumer-role bridge.
    let config = TransportConfig::for_swarm(hosts.namespace.clone(), Some(1));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let start_consumer_bridge = || hosts.consumer_bridge();
    let mut consumer_bridge = Some(start_consumer_bridge());

    // Host A: the agent (this binary again) and the agent-role bridge.
    let mut agent = Reaped(
        hosts
            .agent_host(&[], "publishing_agent_on_host_a", &[], AGENT_ROLE)
            .stdout(Stdio::null())
            .spawn()
            .unwrap(),
    );

    let mut keyframes = Vec::new();
    let mut sequences = Vec::new();
    let mut killed_at: Option<Instant> = None;
    let start = Instant::now();
    loop {
        assert!(
            start.elapsed() < TIMEOUT,
            "no goodbye; keyframes so far {keyframes:?}"
        );
        if killed_at.is_none() && keyframes.len() >= KILL_AFTER {
            let mut bridge = consumer_bridge.take().unwrap();
            bridge.0.kill().unwrap(); // SIGKILL
            bridge.0.wait().unwrap();
            killed_at = Some(Instant::now());
        }
        if consumer_bridge.is_none() && killed_at.is_some_and(|at| at.elapsed() >= OUTAGE) {
            consumer_bridge = Some(start_consumer_bridge());
        }
        let Some(incoming) = consumer.recv_timeout(Duration::from_millis(100)).unwrap() else {
            continue;
        };
        match incoming {
            Incoming::Descriptor(d) => {
                keyframes.push(d.keyframe_id);
                sequences.push(d.stamp.sequence);
            }
            Incoming::Lifecycle(l) if l.kind() == Ok(LifecycleKind::Goodbye) => break,
            _ => {}
        }
    }
    assert!(killed_at.is_some(), "the bridge was never killed");
    assert_eq!(
        keyframes,
        (0..KEYFRAMES).collect::<Vec<_>>(),
        "every keyframe once, in order"
    );
    let status = agent.0.wait().unwrap();
    assert!(status.success(), "host A ended with {status}");
    eprintln!("descriptor sequence numbers: {sequences:?}");
}
