//! Only bridges holding a certificate from the swarm CA join the swarm. A consumer-role
//! mac-bridge listens on TLS with mutual authentication in front of a consumer (this test
//! process). Three intruders try to join as agent 0 over zenoh, each publishing a hello and
//! descriptors and subscribing to agent 0's corrections: one with a certificate from another
//! CA, one with no certificate, one on plain TCP. All of them trust the swarm CA (its
//! certificate is not secret), the worst case. Nothing they send reaches the consumer and they
//! receive nothing. A peer with a swarm certificate then does the same and is delivered both
//! ways. Needs no root: nothing here shares memory across the zenoh link.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

mod common;

use common::{BRIDGE, Reaped, free_port, make_certs};
use protocol::bench::{SAMPLE_INTRINSICS, synthetic_descriptor};
use protocol::messages::{KeyframePose, Lifecycle, LifecycleKind, Pose, Stamp};
use protocol::transport::{ConsumerLink, Incoming, TransportConfig};
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::{Config, Session, Wait};

const TIMEOUT: Duration = Duration::from_secs(30);
/// How long the intruders keep trying; their handshakes fail at once.
const INTRUSION: Duration = Duration::from_secs(3);
const DESCRIPTORS: u64 = 3;

/// How a test peer presents itself.
enum Credentials {
    /// TLS with this certificate and key; trusts `ca`.
    Certificate {
        ca: PathBuf,
        certificate: PathBuf,
        key: PathBuf,
    },
    /// TLS trusting `ca`, without a certificate of its own.
    NoCertificate {
        ca: PathBuf,
    },
    PlainTcp,
}

fn peer(port: u16, credentials: &Credentials) -> Session {
    let mut config = Config::default();
    let mut set = |key: &str, value: String| config.insert_json5(key, &value).unwrap();
    set("mode", "\"peer\"".into());
    set("scouting/multicast/enabled", "false".into());
    set("connect/exit_on_failure", "false".into());
    let path = |p: &Path| serde_json::to_string(p.to_str().unwrap()).unwrap();
    let tls = "transport/link/tls";
    let scheme = match credentials {
        Credentials::Certificate {
            ca,
            certificate,
            key,
        } => {
            set(&format!("{tls}/root_ca_certificate"), path(ca));
            set(&format!("{tls}/connect_certificate"), path(certificate));
            set(&format!("{tls}/connect_private_key"), path(key));
            set(&format!("{tls}/enable_mtls"), "true".into());
            "tls"
        }
        Credentials::NoCertificate { ca } => {
            set(&format!("{tls}/root_ca_certificate"), path(ca));
            "tls"
        }
        Credentials::PlainTcp => "tcp",
    };
    set(
        "connect/endpoints",
        format!("[\"{scheme}/127.0.0.1:{port}\"]"),
    );
    zenoh::open(config).wait().unwrap()
}

/// Publishes agent 0's hello and descriptors (the bytes a bridge relays) under `epoch`.
fn send_as_agent_0(session: &Session, namespace: &str, epoch: u64) {
    let stamp = |sequence| Stamp {
        agent_id: 0,
        reserved: 0,
        epoch,
        sequence,
    };
    let mut hello = Lifecycle::hello(SAMPLE_INTRINSICS, 7, 0);
    hello.stamp = stamp(0);
    session
        .put(
            format!("{namespace}/agent/0/lifecycle"),
            bytemuck::bytes_of(&hello).to_vec(),
        )
        .wait()
        .unwrap();
    for keyframe in 0..DESCRIPTORS {
        let mut descriptor = synthetic_descriptor(keyframe);
        descriptor.stamp = stamp(keyframe);
        session
            .put(
                format!("{namespace}/agent/0/descriptor"),
                bytemuck::bytes_of(&descriptor).to_vec(),
            )
            .wait()
            .unwrap();
    }
}

fn corrections(session: &Session, namespace: &str) -> Subscriber<FifoChannelHandler<Sample>> {
    session
        .declare_subscriber(format!("{namespace}/agent/0/correction"))
        .wait()
        .unwrap()
}

/// Whether `session` sees the consumer bridge's liveliness token within `within`.
fn sees_consumer_bridge(session: &Session, namespace: &str, within: Duration) -> bool {
    let start = Instant::now();
    while start.elapsed() < within {
        let replies = session
            .liveliness()
            .get(format!("{namespace}/bridge/consumers"))
            .timeout(Duration::from_millis(300))
            .wait()
            .unwrap();
        while let Ok(reply) = replies.recv() {
            if reply.result().is_ok() {
                return true;
            }
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    false
}

#[test]
fn only_peers_with_a_swarm_certificate_reach_the_consumer() {
    let work = tempfile::tempdir().unwrap();
    let (swarm, foreign) = (work.path().join("swarm"), work.path().join("foreign"));
    make_certs(&swarm, &["consensus=127.0.0.1", "agent0"]);
    make_certs(&foreign, &["agent0"]);
    let namespace = format!("authtest{}", std::process::id());
    let port = free_port();

    let config = TransportConfig::for_swarm(namespace.clone(), Some(1));
    let mut consumer = ConsumerLink::open(&config).unwrap();
    let _bridge = Reaped(
        Command::new(BRIDGE)
            .args(["--role", "consumers", "--namespace", &namespace])
            .args(["--agents", "1", "--host", "consensus", "--certificates"])
            .arg(&swarm)
            .args(["--listen", &format!("tls/127.0.0.1:{port}")])
            .spawn()
            .unwrap(),
    );
    let swarm_agent = Credentials::Certificate {
        ca: swarm.join("ca.pem"),
        certificate: swarm.join("agent0.pem"),
        key: swarm.join("agent0.key"),
    };
    // The genuine peer connects first, so the bridge is known to be up while the intruders try.
    let genuine = peer(port, &swarm_agent);
    assert!(
        sees_consumer_bridge(&genuine, &namespace, TIMEOUT),
        "a peer with a swarm certificate never reached the consumer bridge"
    );

    let intruders = [
        Credentials::Certificate {
            ca: swarm.join("ca.pem"),
            certificate: foreign.join("agent0.pem"),
            key: foreign.join("agent0.key"),
        },
        Credentials::NoCertificate {
            ca: swarm.join("ca.pem"),
        },
        Credentials::PlainTcp,
    ]
    .map(|credentials| {
        let session = peer(port, &credentials);
        let subscriber = corrections(&session, &namespace);
        (session, subscriber)
    });
    let start = Instant::now();
    for (i, (session, _)) in intruders.iter().enumerate() {
        assert!(
            !sees_consumer_bridge(session, &namespace, Duration::from_millis(500)),
            "intruder {i} joined the swarm"
        );
    }
    while start.elapsed() < INTRUSION {
        for (i, (session, _)) in intruders.iter().enumerate() {
            send_as_agent_0(session, &namespace, 1000 + i as u64);
        }
        if let Some(incoming) = consumer.recv_timeout(Duration::from_millis(200)).unwrap() {
            panic!(
                "an intruder's message reached the consumer: {:?}",
                incoming.stamp()
            );
        }
    }

    // The genuine peer is delivered, in order, with its stamps.
    let epoch = 42;
    send_as_agent_0(&genuine, &namespace, epoch);
    let mut received = Vec::new();
    let start = Instant::now();
    while received.len() < 1 + DESCRIPTORS as usize {
        assert!(start.elapsed() < TIMEOUT, "received only {received:?}");
        let Some(incoming) = consumer.recv_timeout(Duration::from_millis(200)).unwrap() else {
            continue;
        };
        let stamp = incoming.stamp();
        assert_eq!((stamp.agent_id, stamp.epoch), (0, epoch), "{stamp:?}");
        let kind = match incoming {
            Incoming::Lifecycle(l) => {
                assert_eq!(l.kind(), Ok(LifecycleKind::Hello));
                "hello"
            }
            Incoming::Descriptor(_) => "descriptor",
            _ => "other",
        };
        received.push((kind, stamp.sequence));
    }
    assert_eq!(
        received,
        [
            ("hello", 0),
            ("descriptor", 0),
            ("descriptor", 1),
            ("descriptor", 2)
        ]
    );

    // The way back: the genuine peer gets the consumer's correction, the intruders nothing. It
    // announces itself as agent 0's host, as an agent host's bridge does: the consumer host's
    // bridge sends an agent's corrections only to a host that is there.
    let genuine_corrections = corrections(&genuine, &namespace);
    let _agent_host_token = genuine
        .liveliness()
        .declare_token(format!("{namespace}/bridge/agent/0"))
        .wait()
        .unwrap();
    let poses = [KeyframePose {
        keyframe_id: 1,
        camera_to_world: Pose::IDENTITY,
    }];
    let start = Instant::now();
    let correction = loop {
        assert!(
            start.elapsed() < TIMEOUT,
            "no correction reached the genuine peer"
        );
        let _ = consumer.send_correction(0, Pose::IDENTITY, &poses);
        if let Some(sample) = genuine_corrections
            .recv_timeout(Duration::from_millis(200))
            .unwrap()
        {
            break sample;
        }
    };
    assert!(correction.payload().len() > size_of::<Stamp>());
    for (i, (_, subscriber)) in intruders.iter().enumerate() {
        assert!(
            subscriber.try_recv().unwrap().is_none(),
            "intruder {i} received a correction"
        );
    }
}
