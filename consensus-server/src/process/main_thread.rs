//! The main thread: owns the transport, routes every received message (lifecycle, keyframe
//! parts through the [`KeyframeInbox`], Gaussians) to the worker, asks agents to publish again
//! what arrived incomplete, forwards every solution to the agents as corrections, and keeps the
//! per-agent records.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use crossbeam_channel::Sender;
use geometry::se3::isometry_to_tum;
use nalgebra::Isometry3;
use protocol::messages::{
    ControlMessage, FINAL_MAP_KEYFRAME_ID, GaussianRecord, KeyframeImageHeader, KeyframePose,
    LifecycleKind, Pose, RgbdPixel,
};
use protocol::services::Topic;
use protocol::transport::{ConsumerLink, Incoming};

use super::ConsensusOptions;
use super::outputs::AgentRecord;
use super::worker::{SnapshotRequest, SolutionUpdate, WorkerHandle, WorkerInput};
use crate::alignment::Keyframe;
use crate::engine::KeyframeArrival;
use crate::inbox::KeyframeInbox;
use crate::place_recognition::KeyframeRef;
use crate::store::{Store, StoredCorrection, StoredInput, StoredKeyframe};
use protocol::convert;

/// The main thread's state: the transport and what it learnt of each agent.
pub(super) struct Listener {
    link: ConsumerLink,
    started: Instant,
    agents: BTreeMap<u32, AgentRecord>,
    first_seen: BTreeMap<u32, Instant>,
    /// Agents that said goodbye (and did not come back).
    finished: BTreeSet<u32>,
    inbox: KeyframeInbox,
    /// The latest solution's frame of each linked agent.
    world_from_agent: BTreeMap<u32, Isometry3<f64>>,
    latencies: Vec<f64>,
    /// Every accepted input is committed here before it is acted on.
    store: Store,
}

/// The re-request policy: under a bandwidth budget a keyframe's parts are deferred, not lost,
/// so the consensus waits longer before asking again (`[network] resend_allowance_s`).
fn resend_policy(config: &config::Config) -> config::ResendConfig {
    let mut policy = config.consensus.resend.clone();
    policy.after_s = config.network.resend_after_s(policy.after_s);
    policy
}

impl Listener {
    pub fn new(
        link: ConsumerLink,
        options: &ConsensusOptions,
        started: Instant,
        store: Store,
    ) -> Self {
        Self {
            store,
            link,
            started,
            agents: BTreeMap::new(),
            first_seen: BTreeMap::new(),
            finished: BTreeSet::new(),
            inbox: KeyframeInbox::new(resend_policy(&options.config))
                .with_loss_report_after(options.config.consensus.resend.after_s),
            world_from_agent: BTreeMap::new(),
            latencies: Vec::new(),
        }
    }

    /// The consensus store's file.
    pub fn store_path(&self) -> &std::path::Path {
        self.store.path()
    }

    /// Replays a resumed store's `inputs` through the routes live messages take (nothing is
    /// committed again), then tells every agent that may still run that the consensus is back
    /// and which of its keyframes it holds ([`ControlMessage::ConsensusResumed`]), so the agent
    /// publishes again what it still holds of the rest.
    pub fn resume(
        &mut self,
        inputs: Vec<StoredInput>,
        options: &ConsensusOptions,
        to_worker: &Sender<WorkerInput>,
    ) -> anyhow::Result<()> {
        let replayed = inputs.len();
        for input in inputs {
            self.replay(input, to_worker)?;
        }
        let keyframes: usize = self.agents.values().map(|r| r.keyframes).sum();
        tracing::info!(
            inputs = replayed,
            keyframes,
            agents = self.agents.len(),
            finished = self.finished.len(),
            "resumed from the consensus store: keyframes and map rebuilt from its inputs, closures from its decisions"
        );
        // Agents the store knows, and those the run waits for (an agent whose hello was lost
        // with the previous process is still running).
        let mut agents: BTreeSet<u32> = self.agents.keys().copied().collect();
        agents.extend(0..options.expected_agents.unwrap_or(0));
        let last_corrections = self.store.last_corrections()?;
        for (agent_id, correction) in &last_corrections {
            self.world_from_agent
                .insert(*agent_id, correction.world_from_agent.isometry());
        }
        for agent_id in agents.difference(&self.finished) {
            let message = ControlMessage::ConsensusResumed {
                keyframes_held: self.inbox.complete_keyframes(*agent_id),
            };
            match self.link.send_control(*agent_id, &message) {
                Ok(_) => tracing::info!(agent_id, "told the agent the consensus is back"),
                // Not running now: if it comes back, it starts over with a hello.
                Err(error) => tracing::info!(agent_id, %error, "agent not reached on resume"),
            }
            // The last correction it was sent, again: the agent may have missed it while the
            // consensus was down, and the next solve may be a while.
            if let Some(correction) = last_corrections.get(agent_id) {
                tracing::info!(
                    agent_id,
                    sequence = correction.sequence,
                    "last stored correction sent again"
                );
                send_correction(&mut self.link, correction, &mut self.agents);
            }
        }
        Ok(())
    }

    /// Routes one stored input as if it had just arrived.
    fn replay(
        &mut self,
        input: StoredInput,
        to_worker: &Sender<WorkerInput>,
    ) -> anyhow::Result<()> {
        let (agent_id, epoch) = match &input {
            StoredInput::Hello {
                agent_id, epoch, ..
            }
            | StoredInput::Patch {
                agent_id, epoch, ..
            } => (*agent_id, *epoch),
            StoredInput::Keyframe(keyframe) => (keyframe.agent_id, keyframe.epoch),
            // A goodbye's epoch is not used.
            StoredInput::Goodbye { agent_id } => (*agent_id, 0),
        };
        let mut route = Route {
            agent_id,
            epoch,
            record: self.agents.entry(agent_id).or_default(),
            inbox: &mut self.inbox,
            to_worker,
            store: None,
        };
        match input {
            StoredInput::Hello {
                run_anchor,
                config_hash,
                ..
            } => route.hello(run_anchor, config_hash, &mut self.finished),
            StoredInput::Goodbye { .. } => route.goodbye(&mut self.finished),
            StoredInput::Keyframe(keyframe) => route.stored_keyframe(&keyframe),
            StoredInput::Patch {
                keyframe_id,
                records,
                ..
            } => route.patch(keyframe_id, &records),
        }
    }

    /// Receives and routes messages until every expected agent has said goodbye or `stop` is
    /// raised (then, with `stop_agents_wait`, until the running agents are done or the wait is
    /// over); writes a snapshot each time `snapshot` is raised. Returns whether it was stopped.
    pub fn listen(
        &mut self,
        worker: &WorkerHandle,
        options: &ConsensusOptions,
        stop: &AtomicBool,
        snapshot: &AtomicBool,
    ) -> anyhow::Result<bool> {
        let mut interrupted = false;
        // When the agents were asked to stop (with `stop_agents_wait`).
        let mut agents_asked_to_stop: Option<Instant> = None;
        let mut bandwidth = super::live::BandwidthProbe::new();
        loop {
            bandwidth.sample(&options.live_view, &self.link);
            if stop.load(Ordering::Relaxed) {
                interrupted = true;
                if !self.waits_for_agents(options.stop_agents_wait, &mut agents_asked_to_stop) {
                    tracing::warn!("stop requested: writing outputs");
                    break;
                }
            }
            if let Some(expected) = options.expected_agents
                && (0..expected).all(|id| self.finished.contains(&id))
            {
                tracing::info!("every agent said goodbye");
                break;
            }
            self.receive(options.transport.wait_slice, &worker.inputs)?;
            request_resends(
                &mut self.link,
                &mut self.inbox,
                &self.finished,
                &mut self.agents,
            );
            for update in worker.solutions.try_iter() {
                self.apply_solution(update)?;
            }
            self.latencies.extend(worker.latencies.try_iter());
            if snapshot.swap(false, Ordering::Relaxed) {
                tracing::info!("snapshot requested: writing the outputs as they stand");
                self.request_snapshot(&worker.inputs)?;
            }
        }
        Ok(interrupted)
    }

    /// After a stop request: whether to go on receiving (the agents' last keyframes, final maps
    /// and goodbyes). Only with `stop_agents_wait`: the running agents are asked to stop once,
    /// and waited for until they are done or the wait is over.
    fn waits_for_agents(
        &mut self,
        stop_agents_wait: Option<Duration>,
        asked_at: &mut Option<Instant>,
    ) -> bool {
        let running = running_agents(&self.agents, &self.finished);
        let Some(wait_for_agents) = stop_agents_wait else {
            return false;
        };
        let asked = *asked_at.get_or_insert_with(|| {
            ask_agents_to_stop(&mut self.link, &running);
            Instant::now()
        });
        let waiting = !running.is_empty() && asked.elapsed() < wait_for_agents;
        if !waiting && !running.is_empty() {
            tracing::warn!(
                agents = ?running,
                "agents did not say goodbye within {wait_for_agents:?}"
            );
        }
        waiting
    }

    /// Waits up to `wait` for one message and routes it.
    fn receive(&mut self, wait: Duration, to_worker: &Sender<WorkerInput>) -> anyhow::Result<()> {
        match self.link.recv_timeout(wait) {
            Ok(Some(message)) => {
                let agent_id = message.agent_id();
                let record = self.agents.entry(agent_id).or_default();
                self.first_seen.entry(agent_id).or_insert_with(Instant::now);
                if matches!(
                    message.delivery(),
                    protocol::transport::Delivery::Gap { .. }
                ) {
                    record.gaps += 1;
                    tracing::warn!(agent_id, topic = %message.topic(), "messages lost");
                    // A lost heartbeat carries nothing to recover; a lost keyframe part may
                    // have taken a whole keyframe with it.
                    if message.topic() != Topic::Lifecycle {
                        self.inbox.messages_lost(agent_id, Instant::now());
                    }
                }
                let mut route = Route {
                    agent_id,
                    epoch: message.stamp().epoch,
                    record,
                    inbox: &mut self.inbox,
                    to_worker,
                    store: Some(&mut self.store),
                };
                route.message(message, &mut self.finished)?;
            }
            Ok(None) => {}
            Err(error) => tracing::warn!(%error, "receive failed"),
        }
        Ok(())
    }

    /// Sends `update` to the agents as corrections (committed to the store first) and keeps
    /// its agents' frames.
    fn apply_solution(&mut self, update: SolutionUpdate) -> anyhow::Result<()> {
        let corrections = corrections_due(&update, &self.inbox, &mut self.agents);
        let corrections = self.store.append_corrections(corrections)?;
        for correction in &corrections {
            send_correction(&mut self.link, correction, &mut self.agents);
        }
        self.world_from_agent = update.world_from_agent;
        Ok(())
    }

    /// Asks the worker to write the outputs as they stand.
    fn request_snapshot(&self, to_worker: &Sender<WorkerInput>) -> anyhow::Result<()> {
        let mut records = self.agents.clone();
        fill_records(
            &mut records,
            &self.world_from_agent,
            &self.link,
            &self.first_seen,
        );
        fill_inbox_counts(&mut records, &self.inbox);
        to_worker
            .send(WorkerInput::Snapshot(Box::new(SnapshotRequest {
                agents: records,
                latencies: self.latencies.clone(),
                wall_s: self.started.elapsed().as_secs_f64(),
            })))
            .context("the consensus worker stopped")
    }

    /// Once the worker is done: its last `updates` sent as corrections, its last `latencies`
    /// kept; returns the completed per-agent records and every latency.
    pub fn finish(
        mut self,
        updates: Vec<SolutionUpdate>,
        latencies: Vec<f64>,
    ) -> (BTreeMap<u32, AgentRecord>, Vec<f64>) {
        for update in updates {
            if let Err(error) = self.apply_solution(update) {
                // The outputs are written anyway; an agent misses these last corrections.
                tracing::error!("{error:#}: last corrections not sent");
            }
        }
        self.latencies.extend(latencies);
        fill_records(
            &mut self.agents,
            &self.world_from_agent,
            &self.link,
            &self.first_seen,
        );
        fill_inbox_counts(&mut self.agents, &self.inbox);
        let write_ms = self.store.keyframe_write_ms();
        if !write_ms.is_empty() {
            tracing::info!(
                keyframes = write_ms.len(),
                median_ms = metrics::stats::median(write_ms),
                max_ms = write_ms.iter().copied().fold(0.0, f64::max),
                store = %self.store.path().display(),
                "store: keyframe commits"
            );
        }
        for (agent_id, record) in self.agents.iter_mut() {
            if record.keyframes_incomplete > 0 {
                tracing::warn!(
                    agent_id,
                    keyframes = record.keyframes_incomplete,
                    "keyframes never arrived complete"
                );
            }
        }
        (self.agents, self.latencies)
    }
}

/// One received message on its way: who sent it, and where its parts go.
struct Route<'a> {
    agent_id: u32,
    epoch: u64,
    record: &'a mut AgentRecord,
    inbox: &'a mut KeyframeInbox,
    to_worker: &'a Sender<WorkerInput>,
    /// Where accepted inputs are committed; `None` while replaying the store itself.
    store: Option<&'a mut Store>,
}

impl Route<'_> {
    /// Commits `input` to the store (when live) before the caller acts on it.
    fn commit(&mut self, input: impl FnOnce() -> StoredInput) -> anyhow::Result<()> {
        match self.store.as_deref_mut() {
            Some(store) => store.append(&input()),
            None => Ok(()),
        }
    }

    /// Routes the message by kind.
    fn message(&mut self, message: Incoming, finished: &mut BTreeSet<u32>) -> anyhow::Result<()> {
        match message {
            Incoming::Lifecycle(lifecycle) => match lifecycle.kind() {
                Ok(LifecycleKind::Hello) => {
                    self.hello(lifecycle.run_anchor, lifecycle.config_hash, finished)
                }
                Ok(LifecycleKind::Alive) => Ok(()),
                Ok(LifecycleKind::Goodbye) => self.goodbye(finished),
                Err(error) => {
                    tracing::warn!(agent_id = self.agent_id, %error, "lifecycle message ignored");
                    Ok(())
                }
            },
            Incoming::Descriptor(descriptor) => {
                let id = KeyframeRef {
                    agent_id: self.agent_id,
                    keyframe_id: descriptor.keyframe_id,
                };
                match self.inbox.descriptor(
                    id,
                    self.epoch,
                    descriptor.descriptor.to_vec(),
                    Instant::now(),
                ) {
                    Some(arrival) => self.forward(arrival),
                    None => Ok(()),
                }
            }
            Incoming::KeyframeImage(image) => self.keyframe_image(image.header(), image.pixels()),
            Incoming::Patch(patch) => self.patch(patch.header().keyframe_id, patch.records()),
        }
    }

    /// Hello: a (re)started agent is in the run.
    fn hello(
        &mut self,
        run_anchor: u64,
        config_hash: u64,
        finished: &mut BTreeSet<u32>,
    ) -> anyhow::Result<()> {
        let (agent_id, epoch) = (self.agent_id, self.epoch);
        self.commit(|| StoredInput::Hello {
            agent_id,
            epoch,
            run_anchor,
            config_hash,
        })?;
        let record = &mut *self.record;
        record.hellos += 1;
        if record.hellos > 1 && record.config_hash != config_hash {
            tracing::warn!(agent_id, "agent restarted with a different configuration");
        }
        record.config_hash = config_hash;
        self.inbox.hello(agent_id, epoch, run_anchor);
        // A restarted agent is back in the run; its previous process's incomplete
        // keyframes are gone with it.
        finished.remove(&agent_id);
        if record.hellos > 1 {
            self.inbox.forget_incomplete(agent_id);
        }
        tracing::info!(agent_id, "agent joined");
        Ok(())
    }

    /// Goodbye: the agent is done (until it says hello again).
    fn goodbye(&mut self, finished: &mut BTreeSet<u32>) -> anyhow::Result<()> {
        let agent_id = self.agent_id;
        self.commit(|| StoredInput::Goodbye { agent_id })?;
        self.record.goodbyes += 1;
        finished.insert(agent_id);
        tracing::info!(agent_id, "agent left");
        Ok(())
    }

    /// A keyframe's RGB-D image, to the inbox.
    fn keyframe_image(
        &mut self,
        header: &KeyframeImageHeader,
        pixels: &[RgbdPixel],
    ) -> anyhow::Result<()> {
        let id = KeyframeRef {
            agent_id: self.agent_id,
            keyframe_id: header.keyframe_id,
        };
        let (rgb, depth) = convert::rgbd_images(header.width, header.height, pixels);
        let keyframe = Keyframe {
            id,
            rgb,
            depth,
            intrinsics: (&header.intrinsics).into(),
            agent_from_camera: header.camera_to_agent_world.to_isometry(),
        };
        match self.inbox.image(
            id,
            self.epoch,
            keyframe,
            header.frame_index,
            header.timestamp_s,
            Instant::now(),
        ) {
            Some(arrival) => self.forward(arrival),
            None => Ok(()),
        }
    }

    /// A stored keyframe (descriptor and image together), through the inbox as when it came.
    fn stored_keyframe(&mut self, stored: &StoredKeyframe) -> anyhow::Result<()> {
        let now = Instant::now();
        let id = stored.id();
        let from_descriptor = self
            .inbox
            .descriptor(id, self.epoch, stored.descriptor.clone(), now);
        let arrival = match from_descriptor {
            Some(arrival) => Some(arrival),
            None => self.inbox.image(
                id,
                self.epoch,
                stored.keyframe()?,
                stored.frame_index,
                stored.timestamp_s,
                now,
            ),
        };
        match arrival {
            Some(arrival) => self.forward(arrival),
            None => {
                tracing::warn!(
                    agent_id = id.agent_id,
                    keyframe_id = id.keyframe_id,
                    "stored keyframe not taken again on replay"
                );
                Ok(())
            }
        }
    }

    /// A keyframe's Gaussians, or the agent's final map, to the worker unless repeated or from
    /// a run restarted on other frames.
    fn patch(&mut self, keyframe_id: u64, records: &[GaussianRecord]) -> anyhow::Result<()> {
        let agent_id = self.agent_id;
        let id = KeyframeRef {
            agent_id,
            keyframe_id,
        };
        if id.keyframe_id == FINAL_MAP_KEYFRAME_ID {
            if self.inbox.ignores(agent_id, self.epoch) {
                tracing::warn!(
                    agent_id,
                    "final map of a run restarted on other frames (a frame of its own): \
                     ignored"
                );
                return Ok(());
            }
        } else if !self.inbox.patch(id, self.epoch, Instant::now()) {
            // Already stored (a resend crossing a late original), or from a run restarted
            // on other frames.
            return Ok(());
        }
        let epoch = self.epoch;
        self.commit(|| StoredInput::Patch {
            agent_id,
            keyframe_id,
            epoch,
            records: records.to_vec(),
        })?;
        let (cloud, dropped) = convert::gaussian_cloud(records);
        if dropped > 0 {
            tracing::warn!(
                agent_id,
                dropped,
                "patch records with non-finite values dropped"
            );
        }
        self.record.gaussians_received += cloud.len();
        self.to_worker
            .send(WorkerInput::Gaussians(id, cloud))
            .context("the consensus worker stopped")
    }

    /// Hands a keyframe whose descriptor and image are both there to the worker.
    fn forward(&mut self, arrival: KeyframeArrival) -> anyhow::Result<()> {
        // The keyframe's consensus latency counts from here, its commit included.
        let complete_at = Instant::now();
        let epoch = self.epoch;
        self.commit(|| StoredInput::Keyframe(Box::new(StoredKeyframe::new(&arrival, epoch))))?;
        self.record.keyframes += 1;
        self.to_worker
            .send(WorkerInput::Keyframe(Box::new(arrival), complete_at))
            .context("the consensus worker stopped")
    }
}

/// Asks agents to publish again the keyframes that waited too long for a missing part, and
/// tells agents whose messages were lost what arrived of theirs (the agent publishes the rest
/// again).
fn request_resends(
    link: &mut ConsumerLink,
    inbox: &mut KeyframeInbox,
    finished: &BTreeSet<u32>,
    agents: &mut BTreeMap<u32, AgentRecord>,
) {
    for request in inbox.due_requests(Instant::now(), finished) {
        let agent_id = request.keyframe.agent_id;
        tracing::warn!(
            agent_id,
            keyframe_id = request.keyframe.keyframe_id,
            reason = %request.reason,
            "keyframe incomplete: asking the agent to publish it again"
        );
        agents.entry(agent_id).or_default().resend_requests += 1;
        let message = ControlMessage::ResendKeyframe {
            keyframe_id: request.keyframe.keyframe_id,
            reason: request.reason,
        };
        if let Err(error) = link.send_control(agent_id, &message) {
            // Asked again after the next wait, up to the configured number of requests.
            tracing::debug!(agent_id, %error, "resend request not delivered");
        }
    }
    for report in inbox.due_loss_reports(Instant::now(), finished) {
        let agent_id = report.agent_id;
        tracing::warn!(
            agent_id,
            held = report.keyframes_held.len(),
            in_part = report.keyframes_in_part.len(),
            newest_seen = report.newest_seen,
            "messages of the agent were lost: telling it what arrived"
        );
        agents.entry(agent_id).or_default().loss_reports += 1;
        let message = ControlMessage::MessagesLost {
            keyframes_held: report.keyframes_held,
            keyframes_in_part: report.keyframes_in_part,
            newest_seen: report.newest_seen,
        };
        if let Err(error) = link.send_control(agent_id, &message) {
            // Keyframes still missing a part are asked for as usual; a later loss reports again.
            tracing::warn!(agent_id, %error, "loss report not delivered");
        }
    }
}

/// The correction of each agent linked to the world: its frame and its keyframes' corrected
/// poses (numbered by the store).
fn corrections_due(
    update: &SolutionUpdate,
    inbox: &KeyframeInbox,
    agents: &mut BTreeMap<u32, AgentRecord>,
) -> Vec<StoredCorrection> {
    let mut corrections = Vec::new();
    for (agent_id, world_from_agent) in &update.world_from_agent {
        if inbox.latest_is_foreign(*agent_id) {
            // Its keyframe ids name other frames in the running process.
            agents.entry(*agent_id).or_default().corrections_withheld += 1;
            continue;
        }
        corrections.push(StoredCorrection {
            agent_id: *agent_id,
            sequence: 0,
            world_from_agent: world_from_agent.into(),
            world_from_camera: update
                .world_from_camera
                .iter()
                .filter(|(id, _)| id.agent_id == *agent_id)
                .map(|(id, pose)| (id.keyframe_id, pose.into()))
                .collect(),
        });
    }
    corrections
}

/// Sends one correction to its agent.
fn send_correction(
    link: &mut ConsumerLink,
    correction: &StoredCorrection,
    agents: &mut BTreeMap<u32, AgentRecord>,
) {
    let agent_id = correction.agent_id;
    let poses: Vec<KeyframePose> = correction
        .world_from_camera
        .iter()
        .map(|(keyframe_id, pose)| KeyframePose {
            keyframe_id: *keyframe_id,
            camera_to_world: Pose::from(&pose.isometry()),
        })
        .collect();
    let world_from_agent = Pose::from(&correction.world_from_agent.isometry());
    let record = agents.entry(agent_id).or_default();
    match link.send_correction(agent_id, world_from_agent, &poses) {
        Ok(_) => record.corrections_sent += 1,
        Err(error) => {
            // An agent that left or crashed simply misses this correction; the final
            // outputs carry it anyway.
            record.corrections_undelivered += 1;
            tracing::debug!(agent_id, %error, "correction not delivered");
        }
    }
}

/// Agents that said hello and have not said goodbye since.
fn running_agents(agents: &BTreeMap<u32, AgentRecord>, finished: &BTreeSet<u32>) -> Vec<u32> {
    agents
        .iter()
        .filter(|(id, record)| record.hellos > 0 && !finished.contains(id))
        .map(|(id, _)| *id)
        .collect()
}

/// Sends `ControlMessage::Shutdown` to each of `agent_ids`.
fn ask_agents_to_stop(link: &mut ConsumerLink, agent_ids: &[u32]) {
    if agent_ids.is_empty() {
        return;
    }
    tracing::warn!(
        agents = ?agent_ids,
        "stop requested: asking the running agents to stop and send their final maps"
    );
    let message = ControlMessage::Shutdown {
        reason: "the consensus was asked to stop".into(),
    };
    for &agent_id in agent_ids {
        if let Err(error) = link.send_control(agent_id, &message) {
            tracing::warn!(agent_id, %error, "stop request not delivered");
        }
    }
}

/// Copies the inbox's per-agent counts into the records.
fn fill_inbox_counts(agents: &mut BTreeMap<u32, AgentRecord>, inbox: &KeyframeInbox) {
    for (agent_id, record) in agents.iter_mut() {
        record.keyframes_incomplete = inbox.incomplete(*agent_id);
        record.duplicate_parts = inbox.duplicates(*agent_id);
        record.keyframe_id_conflicts = inbox.conflicts(*agent_id);
        record.restarts_on_other_frames = inbox.foreign_incarnations(*agent_id);
        record.restart_parts_ignored = inbox.foreign_parts(*agent_id);
        record.last_run_on_other_frames = inbox.latest_is_foreign(*agent_id);
    }
}

/// Completes the per-agent records with what the transport and the solution know.
fn fill_records(
    agents: &mut BTreeMap<u32, AgentRecord>,
    world_from_agent: &BTreeMap<u32, Isometry3<f64>>,
    link: &ConsumerLink,
    first_seen: &BTreeMap<u32, Instant>,
) {
    let bandwidth = link.bandwidth();
    for (id, record) in agents.iter_mut() {
        record.world_from_agent = world_from_agent.get(id).map(isometry_to_tum);
        record.bytes_received = bandwidth
            .entries
            .iter()
            .filter(|e| e.agent_id == *id)
            .map(|e| e.traffic.bytes)
            .sum();
        record.seconds_seen = first_seen
            .get(id)
            .map_or(0.0, |at| at.elapsed().as_secs_f64());
    }
}
