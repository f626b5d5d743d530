//! The reverse direction of network_faults.rs: the consumer keeps sending control messages to
//! an agent on another simulated host while that host's bridge is SIGKILLed (and started again by
//! scripts/simulated_host.sh a second later). Every control message reaches the agent once, in
//! order: the consumer host's bridge keeps what the agent host has not acknowledged and sends it
//! again when the agent host's bridge is back. Host A (agent and agent-role bridge) runs in a
//! mount namespace of its own; host B is this test process as the consumer and its consumer-role
//! bridge. Needs root (unshare --mount); skipped with a message otherwise.
//!
//! The agent is this test binary itself, started again inside host A with `AGENT_ROLE` set; it
//! fails (and the test with it) unless it got every message in order.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;

use common::{BRIDGE, Reaped, TwoHosts, is_root};
use protocol::bench::SAMPLE_INTRINSICS;
use protocol::messages::{ControlMessage, LifecycleKind};
use protocol::transport::{AgentLink, ConsumerLink, Incoming, TransportConfig};

const AGENT_ROLE: &str = "MAC_BRIDGE_CONTROL_TEST_AGENT_NAMESPACE";
const MESSAGES: u64 = 80;
const SEND_EVERY: Duration = Duration::from_millis(25);
/// Messages sent before the agent host's bridge is killed.
const KILL_AFTER: u64 = 20;
const TIMEOUT: Duration = Duration::from_secs(90);

/// The agent of host A: collects the keyframe ids of the re-send requests until a shutdown,
/// checks them, says goodbye.
#[test]
#[ignore = "runs only as the agent process of `every_control_message_crosses_an_agent_bridge_kill_and_restart`"]
fn control_receiving_agent_on_host_a() {
    let Ok(namespace) = std::env::var(AGENT_ROLE) else {
        return;
    };
    let config = TransportConfig::for_swarm(namespace, Some(1));
    let mut link = AgentLink::open(&config, 0).unwrap();
    link.announce(SAMPLE_INTRINSICS, 7, 0).unwrap();
    let mut ids = Vec::new();
    let start = Instant::now();
    loop {
        assert!(start.elapsed() < TIMEOUT, "no shutdown; ids so far {ids:?}");
        let Some(control) = link
            .recv_control_timeout(Duration::from_millis(100))
            .unwrap()
        else {
            let _ = link.heartbeat();
            continue;
        };
        match control.message {
            ControlMessage::ResendKeyframe { keyframe_id, .. } => ids.push(keyframe_id),
            ControlMessage::Shutdown { .. } => break,
            _ => {}
        }
    }
    assert_eq!(
        ids,
        (0..MESSAGES).collect::<Vec<_>>(),
        "every control message once, in order"
    );
    if let Err(e) = link.close() {
        eprintln!("goodbye: {e}");
    }
}

#[test]
fn every_control_message_crosses_an_agent_bridge_kill_and_restart() {
    if !is_root() {
        eprintln!("skipped: simulated hosts need root (unshare --mount)");
        return;
    }
    let hosts = TwoHosts::new("controltest");
    let config = TransportConfig::for_swarm(hosts.namespace.clone(), Some(1));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let _consumer_bridge = hosts.consumer_bridge();
    let mut agent = Reaped(
        hosts
            .agent_host(&[], "control_receiving_agent_on_host_a", &[], AGENT_ROLE)
            .stdout(Stdio::null())
            .spawn()
            .unwrap(),
    );

    // The agent's hello says its host is joined.
    let start = Instant::now();
    loop {
        assert!(start.elapsed() < TIMEOUT, "no hello from the agent");
        if let Some(Incoming::Lifecycle(l)) =
            consumer.recv_timeout(Duration::from_millis(100)).unwrap()
            && l.kind() == Ok(LifecycleKind::Hello)
        {
            break;
        }
    }
    // The bridge process itself (its command line starts with the binary), not the host script
    // that supervises it.
    let agent_bridge = format!(
        "^{BRIDGE} --role agents --local-agent 0 --connect {}",
        hosts.endpoint
    );
    for keyframe_id in 0..MESSAGES {
        if keyframe_id == KILL_AFTER {
            let killed = Command::new("pkill")
                .args(["-KILL", "-f", &agent_bridge])
                .status()
                .unwrap();
            assert!(killed.success(), "the agent host's bridge was not found");
        }
        let request = ControlMessage::ResendKeyframe {
            keyframe_id,
            reason: "test".into(),
        };
        // The consumer host's bridge takes it whether or not the agent host is reachable.
        consumer.send_control(0, &request).unwrap();
        std::thread::sleep(SEND_EVERY);
    }
    consumer
        .send_control(
            0,
            &ControlMessage::Shutdown {
                reason: "test done".into(),
            },
        )
        .unwrap();
    let start = Instant::now();
    loop {
        assert!(start.elapsed() < TIMEOUT, "the agent never ended");
        if agent.0.try_wait().unwrap().is_some() {
            break;
        }
        let _ = consumer.recv_timeout(Duration::from_millis(100));
    }
    let status = agent.0.wait().unwrap();
    assert!(
        status.success(),
        "host A ended with {status}: the agent did not get every control message in order"
    );
}
