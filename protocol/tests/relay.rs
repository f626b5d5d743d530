//! The relay ports between two swarm namespaces of one process, standing for two hosts (the
//! network between them is the test moving each relayed message by hand): an agent on "host A"
//! reaches a consumer on "host B" and back, with every stamp unchanged, in the agent's order.

use std::time::Duration;

use protocol::bench::{SAMPLE_INTRINSICS, synthetic_descriptor, synthetic_record};
use protocol::messages::{CONSUMER_AGENT_ID, CoordinateFrame, KeyframePose, Pose};
use protocol::services::Topic;
use protocol::transport::relay::{
    AgentHostEgress, AgentHostIngress, ConsumerHostEgress, ConsumerHostIngress,
    ConsumerHostOutgoing,
};
use protocol::transport::{AgentLink, ConsumerLink, Incoming, TransportConfig};

const WAIT: Duration = Duration::from_secs(5);

#[test]
fn relay_ports_carry_messages_between_namespaces_with_stamps_unchanged() {
    let pid = std::process::id();
    let host_a = TransportConfig::for_swarm(format!("relay-a-{pid}"), Some(1));
    let host_b = TransportConfig::for_swarm(format!("relay-b-{pid}"), Some(1));
    let mut consumer = ConsumerLink::open(&host_b).unwrap();
    let mut to_consumers = ConsumerHostIngress::open(&host_b).unwrap();
    let mut from_consumers = ConsumerHostEgress::open(&host_b).unwrap();
    assert!(to_consumers.consumers_attached());
    let mut from_agents = AgentHostEgress::open(&host_a, &[0]).unwrap();
    let mut to_agents = AgentHostIngress::open(&host_a, &[0]).unwrap();
    let mut agent = AgentLink::open(&host_a, 0).unwrap();

    agent.announce(SAMPLE_INTRINSICS, 7, 0).unwrap();
    agent.send_descriptor(&synthetic_descriptor(0)).unwrap();
    let records: Vec<_> = (0..1000).map(|i| synthetic_record(3, i)).collect();
    agent
        .send_patch(0, CoordinateFrame::AgentWorld, &records)
        .unwrap();

    // A -> B: lifecycle first, then the data, each forwarded as it came.
    let mut topics = Vec::new();
    for _ in 0..3 {
        let message = from_agents.recv_timeout(WAIT).unwrap().expect("a message");
        assert_eq!(message.stamp.epoch, agent.epoch());
        topics.push(message.topic);
        to_consumers.forward(&message).unwrap();
    }
    assert_eq!(topics[0], Topic::Lifecycle);
    let mut patch_seen = false;
    for _ in 0..3 {
        let incoming = consumer
            .recv_timeout(WAIT)
            .unwrap()
            .expect("relayed message");
        assert_eq!(incoming.stamp().epoch, agent.epoch());
        assert_eq!(incoming.stamp().sequence, 0);
        if let Incoming::Patch(patch) = incoming {
            assert_eq!(patch.records(), &records[..]);
            patch_seen = true;
        }
    }
    assert!(patch_seen);

    // B -> A: a correction keeps the consumer's stamp.
    let poses = [KeyframePose {
        keyframe_id: 0,
        camera_to_world: Pose::IDENTITY,
    }];
    consumer.send_correction(0, Pose::IDENTITY, &poses).unwrap();
    let relayed = match from_consumers.recv_timeout(WAIT).unwrap() {
        Some(ConsumerHostOutgoing::Message(message)) => message,
        other => panic!("expected the correction, got {other:?}"),
    };
    assert_eq!(relayed.topic, Topic::Correction);
    to_agents.forward(&relayed).unwrap();
    let correction = agent.recv_correction_timeout(WAIT).unwrap().unwrap();
    assert_eq!(correction.header().stamp, relayed.stamp);
    assert_eq!(correction.header().stamp.agent_id, CONSUMER_AGENT_ID);
    assert_eq!(correction.poses(), &poses[..]);

    // A relayed message cannot speak for another agent.
    let mut forged = from_agents_message_for(&mut agent, &mut from_agents);
    forged.agent_id = 0;
    forged.bytes[0] ^= 1; // the stamp's agent id is now 1
    assert!(to_consumers.forward(&forged).is_err());
}

fn from_agents_message_for(
    agent: &mut AgentLink,
    from_agents: &mut AgentHostEgress,
) -> protocol::transport::relay::RelayedMessage {
    agent.send_descriptor(&synthetic_descriptor(1)).unwrap();
    from_agents
        .recv_timeout(WAIT)
        .unwrap()
        .expect("a descriptor")
}
