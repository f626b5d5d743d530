//! Two-process IPC benchmark (`mac-ego3d bench ipc`): one-way latency and throughput of the real
//! transport for a keyframe descriptor and for Gaussian patches of 10k and 100k records.
//!
//! The driver (this process) is agent 0: it sends one message, the peer process (a
//! [`ConsumerLink`]) receives it, notes the receive time, checksums what it read in place, and
//! answers with an acknowledgement on the correction topic carrying `[receive time, checksum]`.
//! Latency = peer receive time - driver time just before the send call; both are
//! `CLOCK_MONOTONIC`, which is one clock for all processes of a machine. So a latency sample
//! includes loaning, writing the records into shared memory, sending, the wake-up and the
//! consumer's receive. Throughput runs keep `window` patches in flight (credit = acks), so the
//! consumer's queue never overflows and every patch is read and checksummed.
//!
//! The latency cases send back to back, as a stream: the peer's next message follows its
//! acknowledgement within its poll window ([`TransportConfig::poll_before_wait`]), so it finds
//! the message while polling. `patch_10k_after_idle` sends the same patches one at a time with
//! the peer idle for longer than that window, so it is blocked and must be woken: the latency a
//! consumer sees for a message that comes alone.
//!
//! Each latency case also reports the duration of the driver's send call alone (`*_send_call`:
//! loan, writing the records, `send()`, waking the consumer), so a report shows where the time
//! goes: for a 10k patch sent with `send_patch` the send call is mostly the one 560 KB copy into
//! shared memory, the rest of the one-way latency is the consumer's receive (or wake-up), and on
//! a loaded machine the tail comes from the processes being scheduled out, not from the
//! transport. The driver and the peer are pinned to two CPUs when [`IpcBenchConfig::cpus`] says
//! so.
//!
//! Copies are counted by the transport (bytes it copied from caller memory into shared memory),
//! not asserted: the copying path (`send_patch` from the agent's Vec) is 1 copy, the in-place
//! path (`send_patch_with`, records built directly in the loaned sample) is 0; the consumer reads
//! the sample where it lies (0 copies).

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::messages::{
    CoordinateFrame, GaussianRecord, Intrinsics, KeyframeDescriptor, KeyframePose, LifecycleKind,
    Pose, RgbdPixel,
};
use crate::services::Topic;
use crate::transport::{
    AgentLink, ConsumerLink, Direction, Incoming, TransportConfig, TransportError,
};

/// Agent id the benchmark driver uses.
const BENCH_AGENT_ID: u32 = 0;
/// Records of the small patch (the `patch_10k*` keys of the report).
pub const SMALL_PATCH_RECORDS: usize = 10_000;
/// Records of the large patch (the `patch_100k*` keys).
pub const LARGE_PATCH_RECORDS: usize = 100_000;
/// Patch publisher sizing: the next power of two above the largest patch, so no data segment
/// grows (and is zeroed) during timing.
const BENCH_INITIAL_PATCH_RECORDS: usize = 131_072;
/// Per-consumer patch queue in the benchmark; also the throughput window.
const BENCH_PATCH_QUEUE_DEPTH: usize = 4;
/// Idle time before each send of the `after_idle` case beyond twice the poll window: the peer
/// has certainly stopped polling and blocks on its wake-up event.
const PEER_BLOCKED_AFTER: Duration = Duration::from_millis(1);
/// Longest wait for one acknowledgement before the peer is declared lost.
const ACK_TIMEOUT: Duration = Duration::from_secs(10);
/// Longest idle wait of the peer between two messages.
const PEER_IDLE_TIMEOUT: Duration = Duration::from_secs(30);
/// Longest wait for the peer process to exit after the driver's goodbye.
const PEER_EXIT_TIMEOUT: Duration = Duration::from_secs(5);
const PEER_EXIT_POLL: Duration = Duration::from_millis(10);
/// Fixed content seed, so the driver knows the checksum the peer must report.
const CONTENT_SEED: u64 = 0x6d61_6365_676f_3364;
/// Percentile reported besides the median.
const TAIL_PERCENTILE: f64 = 0.99;
const NS_PER_US: f64 = 1e3;

/// FNV-1a 64-bit parameters (a simple, dependency-free integrity checksum).
const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
const FNV_PRIME: u64 = 0x0000_0100_0000_01b3;

/// Why the IPC benchmark failed.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// Opening a link, sending or receiving failed.
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// The peer process could not be started.
    #[error("could not start the benchmark peer '{program}': {reason}")]
    PeerSpawn {
        /// The executable.
        program: String,
        /// The operating system's error.
        reason: String,
    },
    /// No acknowledgement (driver) or no message (peer) arrived within this time.
    #[error("the benchmark peer sent no acknowledgement within {0:?}")]
    PeerTimeout(Duration),
    /// The peer exited unsuccessfully, could not be waited for, or was killed for not exiting.
    #[error("the benchmark peer exited with {status}")]
    PeerFailed {
        /// Its exit status, or what went wrong.
        status: String,
    },
    /// An acknowledgement did not hold the two poses `[receive time, checksum]`.
    #[error("acknowledgement is malformed: {0}")]
    BadAck(String),
    /// The checksum the peer computed differs from that of what the driver sent.
    #[error(
        "message content was corrupted in transit: {case} checksum {received:#x}, expected {expected:#x}"
    )]
    Corrupted {
        /// The case (its report key).
        case: &'static str,
        /// Checksum the peer reported.
        received: u64,
        /// Checksum of what the driver sent.
        expected: u64,
    },
    /// The driver or the peer could not be restricted to its CPU.
    #[error("could not pin the benchmark to CPU {cpu}: {reason}")]
    Pin {
        /// The CPU index.
        cpu: usize,
        /// The operating system's error.
        reason: String,
    },
    /// The settings cannot run (no latency samples or no throughput messages).
    #[error("invalid benchmark configuration: {0}")]
    InvalidConfig(String),
}

/// Benchmark settings.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IpcBenchConfig {
    /// Timed one-way samples per latency case.
    pub latency_samples: usize,
    /// Untimed messages before each case (page faults of fresh shared memory, caches).
    pub warmup: usize,
    /// Patches per throughput case.
    pub throughput_messages: usize,
    /// Service-name namespace; unique per run so runs never share services.
    pub namespace: String,
    /// Both processes' [`TransportConfig::poll_before_wait`]; zero measures receivers that
    /// block at once (the wake-up cost shows as the gap between send call and latency).
    pub poll_before_wait: Duration,
    /// `[driver CPU, peer CPU]` to pin the two processes to, or `None` to leave placement to
    /// the scheduler. Pinning keeps the figures from depending on whether the scheduler puts
    /// both processes on one core (then each poll or wake-up waits for the other's time slice).
    pub cpus: Option<[usize; 2]>,
}

impl Default for IpcBenchConfig {
    fn default() -> Self {
        Self {
            latency_samples: 1000,
            warmup: 50,
            throughput_messages: 500,
            namespace: format!("mac-bench-{}", std::process::id()),
            poll_before_wait: TransportConfig::default().poll_before_wait,
            cpus: None,
        }
    }
}

/// How to start the peer process: `program args... --namespace NS --poll-before-wait-us US`.
#[derive(Debug, Clone)]
pub struct PeerCommand {
    /// The executable to run.
    pub program: PathBuf,
    /// Its arguments, before the `--namespace` and `--poll-before-wait-us` the driver appends.
    pub args: Vec<String>,
}

/// Median and tail of one latency case, microseconds.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LatencySummary {
    /// Median, microseconds.
    pub median_us: f64,
    /// 99th percentile, microseconds.
    pub p99_us: f64,
    /// Largest sample, microseconds.
    pub max_us: f64,
    /// Timed samples summarised (warm-up excluded); all figures are 0 when there are none.
    pub samples: usize,
}

impl LatencySummary {
    fn from_ns(mut samples_ns: Vec<u64>) -> Self {
        samples_ns.sort_unstable();
        let n = samples_ns.len();
        let at = |q: f64| {
            samples_ns
                .get(((n as f64 - 1.0) * q).round() as usize)
                .copied()
                .unwrap_or(0) as f64
                / NS_PER_US
        };
        Self {
            median_us: at(0.5),
            p99_us: at(TAIL_PERCENTILE),
            max_us: at(1.0),
            samples: n,
        }
    }
}

/// The benchmark's result (`--json` prints it).
#[derive(Debug, Clone, Serialize)]
pub struct IpcBenchReport {
    /// Median one-way latency of a keyframe descriptor, microseconds.
    pub descriptor_median_us: f64,
    /// 99th percentile of the same, microseconds.
    pub descriptor_p99_us: f64,
    /// 10k-record patch copied from the agent's buffer (`send_patch`).
    pub patch_10k_median_us: f64,
    /// 99th percentile of the same, microseconds.
    pub patch_10k_p99_us: f64,
    /// Messages per second of the same patches, with as many in flight as the peer's queue holds.
    pub patch_10k_msgs_per_s: f64,
    /// 10k-record patch sent after the peer has been idle (blocked, not polling): includes
    /// waking the peer process.
    pub patch_10k_after_idle_median_us: f64,
    /// 99th percentile of the same, microseconds.
    pub patch_10k_after_idle_p99_us: f64,
    /// 10k-record patch built in place in shared memory (`send_patch_with`); includes building.
    pub patch_10k_in_place_median_us: f64,
    /// 99th percentile of the same, microseconds.
    pub patch_10k_in_place_p99_us: f64,
    /// Median one-way latency of a 100k-record patch copied with `send_patch`, microseconds.
    pub patch_100k_median_us: f64,
    /// 99th percentile of the same, microseconds.
    pub patch_100k_p99_us: f64,
    /// Messages per second of the same patches, with as many in flight as the peer's queue holds.
    pub patch_100k_msgs_per_s: f64,
    /// Copies of the records from the agent's buffer to the consumer, measured by the
    /// transport's byte counters for the `patch_10k` path (`send_patch`).
    pub copies_per_patch: f64,
    /// Same for the in-place path.
    pub copies_per_patch_in_place: f64,
    /// The consumer reads records in shared memory.
    pub receiver_copies_per_patch: f64,
    /// One-way latency of the descriptor case in full.
    pub descriptor: LatencySummary,
    /// One-way latency of the `patch_10k` case in full.
    pub patch_10k: LatencySummary,
    /// One-way latency of the `patch_10k_after_idle` case in full.
    pub patch_10k_after_idle: LatencySummary,
    /// One-way latency of the `patch_10k_in_place` case in full.
    pub patch_10k_in_place: LatencySummary,
    /// One-way latency of the `patch_100k` case in full.
    pub patch_100k: LatencySummary,
    /// The driver's send call alone in each latency case (part of the one-way latency above).
    pub descriptor_send_call: LatencySummary,
    /// The same for `patch_10k`.
    pub patch_10k_send_call: LatencySummary,
    /// The same for `patch_10k_after_idle`.
    pub patch_10k_after_idle_send_call: LatencySummary,
    /// The same for `patch_10k_in_place`.
    pub patch_10k_in_place_send_call: LatencySummary,
    /// The same for `patch_100k`.
    pub patch_100k_send_call: LatencySummary,
    /// Bytes of one [`GaussianRecord`] on the wire.
    pub record_bytes: usize,
    /// Bytes of one [`KeyframeDescriptor`] message on the wire.
    pub descriptor_bytes: usize,
    /// Receivers' poll before blocking ([`TransportConfig::poll_before_wait`]), microseconds.
    pub poll_before_wait_us: f64,
    /// `[driver CPU, peer CPU]` the processes were pinned to; `None`: placed by the scheduler.
    pub cpus: Option<[usize; 2]>,
}

/// Deterministic record `index` of a synthetic patch (plausible values, distinct per index).
pub fn synthetic_record(seed: u64, index: usize) -> GaussianRecord {
    let base = (seed as f32).fract() + index as f32 * 1e-3;
    GaussianRecord {
        mean: [base, base * 0.5, -base],
        log_scale: [-4.0, -4.5, -5.0 + (index % 7) as f32 * 0.1],
        rotation_wxyz: [1.0, 0.0, 0.0, 0.0],
        opacity_logit: (index % 97) as f32 * 0.01 - 2.0,
        colour: [
            (index % 255) as f32 / 255.0,
            0.5,
            ((seed as usize ^ index) % 255) as f32 / 255.0,
        ],
    }
}

/// Order-sensitive FNV-1a checksum over every field of every record.
pub fn records_checksum(records: &[GaussianRecord]) -> u64 {
    let mut hash = FNV_OFFSET;
    for r in records {
        let fields = r
            .mean
            .iter()
            .chain(&r.log_scale)
            .chain(&r.rotation_wxyz)
            .chain([&r.opacity_logit])
            .chain(&r.colour);
        for v in fields {
            hash = (hash ^ u64::from(v.to_bits())).wrapping_mul(FNV_PRIME);
        }
    }
    hash
}

/// Order-sensitive FNV-1a checksum over every field of every pixel.
pub fn pixels_checksum(pixels: &[RgbdPixel]) -> u64 {
    pixels.iter().fold(FNV_OFFSET, |h, p| {
        let bytes = p.rgb.iter().copied().chain([p.reserved]).map(u64::from);
        bytes
            .chain([u64::from(p.depth_mm)])
            .fold(h, |h, v| (h ^ v).wrapping_mul(FNV_PRIME))
    })
}

/// FNV-1a checksum of a descriptor vector.
pub fn descriptor_checksum(descriptor: &[f32]) -> u64 {
    descriptor.iter().fold(FNV_OFFSET, |h, v| {
        (h ^ u64::from(v.to_bits())).wrapping_mul(FNV_PRIME)
    })
}

/// Camera of the sample messages the benchmark and the test peer send: a 640x480 Kinect-like
/// sensor (the wire type needs plausible values; nothing is rendered with it).
pub const SAMPLE_INTRINSICS: Intrinsics = Intrinsics {
    fx: 585.0,
    fy: 585.0,
    cx: 320.0,
    cy: 240.0,
    width: 640,
    height: 480,
};

/// A unit-norm synthetic descriptor.
pub fn synthetic_descriptor(keyframe_id: u64) -> KeyframeDescriptor {
    let mut d = KeyframeDescriptor::new(keyframe_id, keyframe_id, keyframe_id as f64);
    for (i, v) in d.descriptor.iter_mut().enumerate() {
        *v = ((i as u64 + keyframe_id) % 13) as f32 + 1.0;
    }
    d.normalise_descriptor();
    d.intrinsics = SAMPLE_INTRINSICS;
    d
}

/// `CLOCK_MONOTONIC` in nanoseconds: comparable between processes of one machine, unlike
/// `Instant`, which cannot leave its process.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec into the valid pointer; CLOCK_MONOTONIC exists
    // on every Linux kernel, so the call cannot fail.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Transport settings of both benchmark processes (they must agree).
pub fn bench_transport_config(namespace: &str, poll_before_wait: Duration) -> TransportConfig {
    TransportConfig {
        poll_before_wait,
        max_agents: 1,
        max_consumers: 1,
        required_consumers: 1,
        patch_queue_depth: BENCH_PATCH_QUEUE_DEPTH,
        initial_patch_records: BENCH_INITIAL_PATCH_RECORDS,
        ..TransportConfig::with_namespace(namespace)
    }
}

/// The peer role: acknowledges every descriptor, patch and keyframe image with
/// `[receive time, checksum]` until the driver says goodbye.
pub fn run_peer(namespace: &str, poll_before_wait: Duration) -> Result<(), BenchError> {
    let config = bench_transport_config(namespace, poll_before_wait);
    let mut consumer = ConsumerLink::open(&config)?;
    loop {
        let incoming = consumer
            .recv_timeout(PEER_IDLE_TIMEOUT)?
            .ok_or(BenchError::PeerTimeout(PEER_IDLE_TIMEOUT))?;
        let received_ns = monotonic_ns();
        let checksum = match &incoming {
            Incoming::Lifecycle(l) if l.kind() == Ok(LifecycleKind::Goodbye) => return Ok(()),
            Incoming::Lifecycle(_) => continue,
            Incoming::Descriptor(d) => descriptor_checksum(&d.descriptor),
            Incoming::Patch(p) => records_checksum(p.records()),
            Incoming::KeyframeImage(k) => pixels_checksum(k.pixels()),
        };
        // Release the shared-memory sample before answering, as a real consumer would.
        drop(incoming);
        let ack = [
            KeyframePose {
                keyframe_id: received_ns,
                camera_to_world: Pose::IDENTITY,
            },
            KeyframePose {
                keyframe_id: checksum,
                camera_to_world: Pose::IDENTITY,
            },
        ];
        consumer.send_correction(BENCH_AGENT_ID, Pose::IDENTITY, &ack)?;
    }
}

/// What the driver sends in one case.
#[derive(Clone, Copy)]
enum Case {
    Descriptor,
    PatchCopy(usize),
    PatchInPlace(usize),
}

struct Driver {
    agent: AgentLink,
    descriptor: KeyframeDescriptor,
    small_patch: Vec<GaussianRecord>,
    large_patch: Vec<GaussianRecord>,
}

impl Driver {
    fn expected_checksum(&self, case: Case) -> u64 {
        match case {
            Case::Descriptor => descriptor_checksum(&self.descriptor.descriptor),
            Case::PatchCopy(n) | Case::PatchInPlace(n) => {
                records_checksum(if n == SMALL_PATCH_RECORDS {
                    &self.small_patch
                } else {
                    &self.large_patch
                })
            }
        }
    }

    fn send(&mut self, case: Case) -> Result<(), BenchError> {
        match case {
            Case::Descriptor => self.agent.send_descriptor(&self.descriptor)?,
            Case::PatchCopy(n) => {
                let records = if n == SMALL_PATCH_RECORDS {
                    &self.small_patch
                } else {
                    &self.large_patch
                };
                self.agent
                    .send_patch(0, CoordinateFrame::AgentWorld, records)?
            }
            Case::PatchInPlace(n) => {
                self.agent
                    .send_patch_with(0, CoordinateFrame::AgentWorld, n, |i| {
                        synthetic_record(CONTENT_SEED, i)
                    })?
            }
        };
        Ok(())
    }

    /// Waits for one acknowledgement; returns (peer receive time, checksum).
    fn ack(&mut self) -> Result<(u64, u64), BenchError> {
        let ack = self
            .agent
            .recv_correction_timeout(ACK_TIMEOUT)?
            .ok_or(BenchError::PeerTimeout(ACK_TIMEOUT))?;
        match ack.poses() {
            [time, checksum] => Ok((time.keyframe_id, checksum.keyframe_id)),
            other => Err(BenchError::BadAck(format!(
                "{} poses, expected 2",
                other.len()
            ))),
        }
    }

    /// One-way latencies of `case`, and the durations of the send calls alone.
    /// With `idle_before_send`, the driver sleeps that long before each send, so that the
    /// peer has stopped polling and blocks: the latency then includes its wake-up.
    fn latency(
        &mut self,
        case: Case,
        name: &'static str,
        warmup: usize,
        samples: usize,
        idle_before_send: Option<Duration>,
    ) -> Result<(LatencySummary, LatencySummary), BenchError> {
        let expected = self.expected_checksum(case);
        let mut latencies = Vec::with_capacity(samples);
        let mut send_calls = Vec::with_capacity(samples);
        for i in 0..warmup + samples {
            if let Some(idle) = idle_before_send {
                std::thread::sleep(idle);
            }
            let sent_ns = monotonic_ns();
            self.send(case)?;
            let send_returned_ns = monotonic_ns();
            let (received_ns, checksum) = self.ack()?;
            if checksum != expected {
                return Err(BenchError::Corrupted {
                    case: name,
                    received: checksum,
                    expected,
                });
            }
            if i >= warmup {
                latencies.push(received_ns.saturating_sub(sent_ns));
                send_calls.push(send_returned_ns - sent_ns);
            }
        }
        Ok((
            LatencySummary::from_ns(latencies),
            LatencySummary::from_ns(send_calls),
        ))
    }

    /// Messages per second with `window` patches in flight.
    fn throughput(
        &mut self,
        case: Case,
        name: &'static str,
        messages: usize,
        window: usize,
    ) -> Result<f64, BenchError> {
        let expected = self.expected_checksum(case);
        let start = Instant::now();
        let (mut sent, mut acked) = (0, 0);
        while acked < messages {
            if sent < messages && sent - acked < window {
                self.send(case)?;
                sent += 1;
                continue;
            }
            let (_, checksum) = self.ack()?;
            if checksum != expected {
                return Err(BenchError::Corrupted {
                    case: name,
                    received: checksum,
                    expected,
                });
            }
            acked += 1;
        }
        Ok(messages as f64 / start.elapsed().as_secs_f64())
    }

    /// Copies per patch record byte sent since `before` (bytes copied / record bytes).
    fn copies_since(&self, before: (u64, u64)) -> f64 {
        let (copied, bytes) = self.patch_counters();
        let messages_bytes = bytes - before.1;
        if messages_bytes == 0 {
            0.0
        } else {
            (copied - before.0) as f64 / messages_bytes as f64
        }
    }

    /// (bytes copied, record bytes) of the patch topic so far (header bytes excluded).
    fn patch_counters(&self) -> (u64, u64) {
        let report = self.agent.bandwidth();
        report
            .get(BENCH_AGENT_ID, Topic::Patch, Direction::Sent)
            .map(|t| {
                (
                    t.bytes_copied,
                    t.bytes - t.messages * size_of::<crate::messages::PatchHeader>() as u64,
                )
            })
            .unwrap_or((0, 0))
    }
}

/// Restricts the calling process (and the threads it starts later) to `cpu`.
fn pin_to_cpu(cpu: usize) -> Result<(), BenchError> {
    set_affinity(cpu).map_err(|e| BenchError::Pin {
        cpu,
        reason: e.to_string(),
    })
}

fn set_affinity(cpu: usize) -> std::io::Result<()> {
    if cpu >= libc::CPU_SETSIZE as usize {
        return Err(std::io::Error::from_raw_os_error(libc::EINVAL));
    }
    // SAFETY: cpu_set_t is a plain bit set for which all-zero is the empty set; CPU_SET writes
    // one bit inside it (cpu < CPU_SETSIZE, checked above); sched_setaffinity reads exactly
    // size_of::<cpu_set_t>() bytes from the valid pointer. pid 0 is the calling thread. Only
    // async-signal-safe calls are made, so this may also run between fork and exec.
    let result = unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        libc::sched_setaffinity(0, size_of::<libc::cpu_set_t>(), &set)
    };
    if result == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// The first two CPUs this process may run on, or `None` on a single-CPU machine.
pub fn first_two_cpus() -> Option<[usize; 2]> {
    // SAFETY: as in `set_affinity`; sched_getaffinity writes at most the given size.
    let allowed = unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, size_of::<libc::cpu_set_t>(), &mut set) != 0 {
            return None;
        }
        (0..libc::CPU_SETSIZE as usize)
            .filter(|&cpu| libc::CPU_ISSET(cpu, &set))
            .take(2)
            .collect::<Vec<_>>()
    };
    match allowed[..] {
        [driver, peer] => Some([driver, peer]),
        _ => None,
    }
}

fn spawn_peer(
    peer: &PeerCommand,
    namespace: &str,
    poll_before_wait: Duration,
    cpu: Option<usize>,
) -> Result<Child, BenchError> {
    let mut command = Command::new(&peer.program);
    if let Some(cpu) = cpu {
        use std::os::unix::process::CommandExt;
        // SAFETY: the closure runs in the child between fork and exec and makes only the
        // async-signal-safe sched_setaffinity call (no allocation, no locks).
        unsafe {
            command.pre_exec(move || set_affinity(cpu));
        }
    }
    command
        .args(&peer.args)
        .args(["--namespace", namespace])
        .args([
            "--poll-before-wait-us".to_string(),
            poll_before_wait.as_micros().to_string(),
        ])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .spawn()
        .map_err(|e| BenchError::PeerSpawn {
            program: peer.program.display().to_string(),
            reason: e.to_string(),
        })
}

fn wait_for_exit(child: &mut Child) -> Result<(), BenchError> {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().map_err(|e| BenchError::PeerFailed {
            status: e.to_string(),
        })? {
            return if status.success() {
                Ok(())
            } else {
                Err(BenchError::PeerFailed {
                    status: status.to_string(),
                })
            };
        }
        if start.elapsed() > PEER_EXIT_TIMEOUT {
            let _ = child.kill();
            return Err(BenchError::PeerFailed {
                status: format!("no exit within {PEER_EXIT_TIMEOUT:?}; killed"),
            });
        }
        std::thread::sleep(PEER_EXIT_POLL);
    }
}

/// Runs the benchmark against a freshly spawned peer process.
pub fn run_ipc_bench(
    config: &IpcBenchConfig,
    peer: &PeerCommand,
) -> Result<IpcBenchReport, BenchError> {
    if config.latency_samples == 0 || config.throughput_messages == 0 {
        return Err(BenchError::InvalidConfig(
            "latency_samples and throughput_messages must be positive".into(),
        ));
    }
    if let Some([driver_cpu, _]) = config.cpus {
        pin_to_cpu(driver_cpu)?;
    }
    let transport = bench_transport_config(&config.namespace, config.poll_before_wait);
    let agent = AgentLink::open(&transport, BENCH_AGENT_ID)?;
    let peer_cpu = config.cpus.map(|[_, peer_cpu]| peer_cpu);
    let mut child = spawn_peer(peer, &config.namespace, config.poll_before_wait, peer_cpu)?;
    let result = drive(config, agent);
    match result {
        Ok(report) => {
            wait_for_exit(&mut child)?;
            Ok(report)
        }
        Err(e) => {
            let _ = child.kill();
            let _ = child.wait();
            Err(e)
        }
    }
}

fn drive(config: &IpcBenchConfig, mut agent: AgentLink) -> Result<IpcBenchReport, BenchError> {
    // Blocks until the peer's subscribers are attached: the delivery handshake.
    agent.announce(Intrinsics::default(), 0, 0)?;
    let mut driver = Driver {
        agent,
        descriptor: synthetic_descriptor(1),
        small_patch: (0..SMALL_PATCH_RECORDS)
            .map(|i| synthetic_record(CONTENT_SEED, i))
            .collect(),
        large_patch: (0..LARGE_PATCH_RECORDS)
            .map(|i| synthetic_record(CONTENT_SEED, i))
            .collect(),
    };
    let (warmup, samples) = (config.warmup, config.latency_samples);
    let (descriptor, descriptor_send_call) =
        driver.latency(Case::Descriptor, "descriptor", warmup, samples, None)?;

    let before_copy = driver.patch_counters();
    let (patch_10k, patch_10k_send_call) = driver.latency(
        Case::PatchCopy(SMALL_PATCH_RECORDS),
        "patch_10k",
        warmup,
        samples,
        None,
    )?;
    let copies_per_patch = driver.copies_since(before_copy);
    // The same patches one at a time with the peer idle long enough to be blocked.
    let idle = config.poll_before_wait * 2 + PEER_BLOCKED_AFTER;
    let (patch_10k_after_idle, patch_10k_after_idle_send_call) = driver.latency(
        Case::PatchCopy(SMALL_PATCH_RECORDS),
        "patch_10k_after_idle",
        warmup,
        samples,
        Some(idle),
    )?;

    let before_in_place = driver.patch_counters();
    let in_place = SMALL_PATCH_RECORDS;
    let (patch_10k_in_place, patch_10k_in_place_send_call) = driver.latency(
        Case::PatchInPlace(in_place),
        "patch_10k_in_place",
        warmup,
        samples,
        None,
    )?;
    let copies_per_patch_in_place = driver.copies_since(before_in_place);

    let (patch_100k, patch_100k_send_call) = driver.latency(
        Case::PatchCopy(LARGE_PATCH_RECORDS),
        "patch_100k",
        warmup,
        samples,
        None,
    )?;
    let window = BENCH_PATCH_QUEUE_DEPTH;
    let patch_10k_msgs_per_s = driver.throughput(
        Case::PatchCopy(SMALL_PATCH_RECORDS),
        "patch_10k",
        config.throughput_messages,
        window,
    )?;
    let patch_100k_msgs_per_s = driver.throughput(
        Case::PatchCopy(LARGE_PATCH_RECORDS),
        "patch_100k",
        config.throughput_messages,
        window,
    )?;
    driver.agent.close()?;

    Ok(IpcBenchReport {
        descriptor_median_us: descriptor.median_us,
        descriptor_p99_us: descriptor.p99_us,
        patch_10k_median_us: patch_10k.median_us,
        patch_10k_p99_us: patch_10k.p99_us,
        patch_10k_msgs_per_s,
        patch_10k_after_idle_median_us: patch_10k_after_idle.median_us,
        patch_10k_after_idle_p99_us: patch_10k_after_idle.p99_us,
        patch_10k_in_place_median_us: patch_10k_in_place.median_us,
        patch_10k_in_place_p99_us: patch_10k_in_place.p99_us,
        patch_100k_median_us: patch_100k.median_us,
        patch_100k_p99_us: patch_100k.p99_us,
        patch_100k_msgs_per_s,
        copies_per_patch,
        copies_per_patch_in_place,
        receiver_copies_per_patch: 0.0,
        descriptor,
        patch_10k,
        patch_10k_after_idle,
        patch_10k_in_place,
        patch_100k,
        descriptor_send_call,
        patch_10k_send_call,
        patch_10k_after_idle_send_call,
        patch_10k_in_place_send_call,
        patch_100k_send_call,
        record_bytes: size_of::<GaussianRecord>(),
        descriptor_bytes: size_of::<KeyframeDescriptor>(),
        poll_before_wait_us: config.poll_before_wait.as_secs_f64() * 1e6,
        cpus: config.cpus,
    })
}

#[cfg(test)]
mod tests;
