//! The consensus's inbox of published keyframes: joins each keyframe's three messages
//! (descriptor, RGB-D image, Gaussian patch; different topics, any order), hands a keyframe to
//! the engine once its descriptor and image are both there, ignores parts that arrive twice, and
//! says which keyframes have waited too long for a missing part, so that the process can ask the
//! agent to publish them again (`[consensus.resend]`, `ControlMessage::ResendKeyframe`). A
//! keyframe none of whose parts arrived is unknown here; when an agent's messages were lost (its
//! sequence numbers jumped), the inbox says what it holds of that agent, so that the agent
//! publishes again what is missing (`ControlMessage::MessagesLost`).
//!
//! Free of transport and clocks: callers pass `now`, so the rule is testable without waiting.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use config::ResendConfig;
use splats::GaussianCloud;

use crate::alignment::Keyframe;
use crate::engine::KeyframeArrival;
use crate::place_recognition::KeyframeRef;

/// Parts of one keyframe received so far.
struct Pending {
    descriptor: Option<Vec<f32>>,
    image: Option<(Keyframe, u64, f64)>,
    /// Descriptor and image went to the engine: the frame index the image showed.
    forwarded: Option<u64>,
    patch: bool,
    /// First part's arrival, or the last request (the next request waits from there).
    waiting_since: Instant,
    requests: usize,
}

impl Pending {
    fn new(now: Instant) -> Self {
        Self {
            descriptor: None,
            image: None,
            forwarded: None,
            patch: false,
            waiting_since: now,
            requests: 0,
        }
    }

    /// What is still missing, for the request's reason.
    fn missing(&self) -> Vec<&'static str> {
        let mut missing = Vec::new();
        if self.forwarded.is_none() && self.descriptor.is_none() {
            missing.push("descriptor");
        }
        if self.forwarded.is_none() && self.image.is_none() {
            missing.push("RGB-D image");
        }
        if !self.patch {
            missing.push("Gaussian patch");
        }
        missing
    }
}

/// The incarnations (process epochs, `Stamp::epoch`) of one agent, as far as its frame goes.
/// The keyframes the engine holds for an agent are in the tracked frame of the run that sent
/// them, anchored at that run's first frame; each run's hello carries a hash of its dataset and
/// first frame (`Lifecycle::run_anchor`). A restart that replays the same frames has the same
/// anchor and tracks in the same frame, so its keyframes are welcome (repeats are dropped; a
/// keyframe id may show another frame than in the first run, since keyframe decisions depend on
/// when corrections arrived: that image alone is ignored as a conflict). A restart on other
/// frames has another anchor and tracks in a frame of its own that the consensus cannot relate
/// to the agent's: it is "foreign" and everything it publishes is ignored, or its new keyframe
/// ids would place keyframes and Gaussians in the wrong frame. The agent's frame is that of the
/// first run whose keyframe reached the engine.
#[derive(Default)]
struct AgentIncarnations {
    /// The largest epoch seen: the running incarnation (a restart has a later start time).
    latest: Option<u64>,
    /// Run anchor of each incarnation whose hello arrived.
    anchors: BTreeMap<u64, u64>,
    /// Anchor of the agent's frame: that of the first incarnation whose keyframe went to the
    /// engine (None before, or when that incarnation's hello was never seen).
    frame_anchor: Option<u64>,
    foreign: BTreeSet<u64>,
    /// Keyframe parts of foreign incarnations, ignored.
    ignored_parts: usize,
}

impl AgentIncarnations {
    /// Notes a message of incarnation `epoch` and marks the incarnation foreign when its
    /// anchor differs from the agent's frame (once, with a warning).
    fn observe(&mut self, agent_id: u32, epoch: u64) {
        self.latest = self.latest.max(Some(epoch));
        let (Some(frame), Some(&anchor)) = (self.frame_anchor, self.anchors.get(&epoch)) else {
            return;
        };
        if anchor != frame && self.foreign.insert(epoch) {
            tracing::warn!(
                agent_id,
                "agent restarted on other frames: it tracks in a frame of its own, which the \
                 consensus cannot place; everything this run publishes is ignored (start it \
                 as a new agent id to have it joined)"
            );
        }
    }
}

/// A request the process should send: agent, keyframe and the reason for its log.
#[derive(Debug, Clone, PartialEq)]
pub struct ResendRequest {
    /// The incomplete keyframe; its agent is the one asked.
    pub keyframe: KeyframeRef,
    /// Which parts are missing and for how long (`"Gaussian patch missing after 2.0 s"`).
    pub reason: String,
}

/// What the inbox holds of an agent whose messages were lost, for `ControlMessage::MessagesLost`.
#[derive(Debug, Clone, PartialEq)]
pub struct LossReport {
    /// The agent whose messages were lost.
    pub agent_id: u32,
    /// Keyframes of which every part arrived.
    pub keyframes_held: Vec<u64>,
    /// Keyframes of which some part arrived (the missing ones are asked for by
    /// [`KeyframeInbox::due_requests`]).
    pub keyframes_in_part: Vec<u64>,
    /// The newest keyframe id seen of the agent.
    pub newest_seen: u64,
}

/// See the module documentation.
pub struct KeyframeInbox {
    policy: ResendConfig,
    pending: BTreeMap<KeyframeRef, Pending>,
    /// Every part arrived: the frame index of the keyframe's image.
    complete: BTreeMap<KeyframeRef, u64>,
    duplicates: BTreeMap<u32, usize>,
    /// Keyframe images whose id was already taken by another frame (see [`Self::image`]).
    conflicts: BTreeMap<u32, usize>,
    given_up: BTreeSet<KeyframeRef>,
    incarnations: BTreeMap<u32, AgentIncarnations>,
    /// Agents with lost messages not reported yet: when the first such loss was seen.
    losses: BTreeMap<u32, Instant>,
    /// How long a loss waits before its report (see [`Self::with_loss_report_after`]).
    loss_report_after: Duration,
}

impl KeyframeInbox {
    /// An empty inbox that asks for missing parts by `policy` (`[consensus.resend]`, its wait
    /// possibly lengthened by the process for a bandwidth budget).
    pub fn new(policy: ResendConfig) -> Self {
        Self {
            pending: BTreeMap::new(),
            complete: BTreeMap::new(),
            duplicates: BTreeMap::new(),
            conflicts: BTreeMap::new(),
            given_up: BTreeSet::new(),
            incarnations: BTreeMap::new(),
            losses: BTreeMap::new(),
            loss_report_after: Duration::from_secs_f64(policy.after_s),
            policy,
        }
    }

    /// Loss reports wait `after_s` instead of the policy's (which may include a bandwidth
    /// budget's allowance for deferred parts): a report names only keyframes up to the newest
    /// the consensus has seen, and an agent's descriptors are never deferred, so it needs no
    /// allowance, and an agent may finish its run within one.
    pub fn with_loss_report_after(mut self, after_s: f64) -> Self {
        self.loss_report_after = Duration::from_secs_f64(after_s);
        self
    }

    /// Notes a message of incarnation `epoch` of `agent_id`; true when that incarnation is
    /// foreign (see [`AgentIncarnations`]), in which case the part is counted as ignored. The
    /// keyframe parts below call it themselves; the process calls it for an agent's final map.
    pub fn ignores(&mut self, agent_id: u32, epoch: u64) -> bool {
        let agent = self.incarnations.entry(agent_id).or_default();
        agent.observe(agent_id, epoch);
        let foreign = agent.foreign.contains(&epoch);
        if foreign {
            agent.ignored_parts += 1;
        }
        foreign
    }

    /// The hello of incarnation `epoch` of `agent_id` arrived with `run_anchor`.
    pub fn hello(&mut self, agent_id: u32, epoch: u64, run_anchor: u64) {
        let agent = self.incarnations.entry(agent_id).or_default();
        agent.anchors.insert(epoch, run_anchor);
        agent.observe(agent_id, epoch);
    }

    /// Whether incarnation `epoch` of `agent_id` was found to track in a frame of its own.
    pub fn is_foreign(&self, agent_id: u32, epoch: u64) -> bool {
        self.incarnations
            .get(&agent_id)
            .is_some_and(|agent| agent.foreign.contains(&epoch))
    }

    /// Whether the running (latest seen) incarnation of `agent_id` is foreign: corrections for
    /// the agent's keyframes would name keyframes it does not have, and the trajectory and map it
    /// writes at its end are in its own frame.
    pub fn latest_is_foreign(&self, agent_id: u32) -> bool {
        self.incarnations
            .get(&agent_id)
            .and_then(|agent| agent.latest.map(|latest| agent.foreign.contains(&latest)))
            .unwrap_or(false)
    }

    /// Restarts of `agent_id` found to run on other frames (their keyframes are ignored).
    pub fn foreign_incarnations(&self, agent_id: u32) -> usize {
        self.incarnations
            .get(&agent_id)
            .map_or(0, |agent| agent.foreign.len())
    }

    /// Keyframe parts of those restarts, ignored.
    pub fn foreign_parts(&self, agent_id: u32) -> usize {
        self.incarnations
            .get(&agent_id)
            .map_or(0, |agent| agent.ignored_parts)
    }

    /// The pending entry for a part not seen before (`seen`: whether the entry already has
    /// it); `None`, counted as a duplicate, for a repeat or a part of a complete keyframe.
    fn fresh_part(
        &mut self,
        id: KeyframeRef,
        now: Instant,
        seen: fn(&Pending) -> bool,
    ) -> Option<&mut Pending> {
        if self.complete.contains_key(&id) || self.pending.get(&id).is_some_and(seen) {
            *self.duplicates.entry(id.agent_id).or_default() += 1;
            return None;
        }
        Some(self.pending.entry(id).or_insert_with(|| Pending::new(now)))
    }

    /// A descriptor (L2-normalised values) of incarnation `epoch` arrived; returns the keyframe
    /// for the engine when this completes it.
    pub fn descriptor(
        &mut self,
        id: KeyframeRef,
        epoch: u64,
        descriptor: Vec<f32>,
        now: Instant,
    ) -> Option<KeyframeArrival> {
        if self.ignores(id.agent_id, epoch) {
            return None;
        }
        let pending =
            self.fresh_part(id, now, |p| p.forwarded.is_some() || p.descriptor.is_some())?;
        pending.descriptor = Some(descriptor);
        self.forward_if_ready(id, epoch)
    }

    /// An RGB-D image of incarnation `epoch` arrived; returns the keyframe for the engine when
    /// this completes it.
    ///
    /// An image whose keyframe id already went to the engine for another frame is a conflict,
    /// not a repeat: a restarted agent numbers its keyframes from 0 again, and a replay may
    /// choose other keyframes. Such an image is ignored and counted ([`Self::conflicts`]), with
    /// a warning. Images of a restart on other frames are ignored whole (see
    /// [`AgentIncarnations`]).
    pub fn image(
        &mut self,
        id: KeyframeRef,
        epoch: u64,
        keyframe: Keyframe,
        frame_index: u64,
        timestamp_s: f64,
        now: Instant,
    ) -> Option<KeyframeArrival> {
        if self.ignores(id.agent_id, epoch) {
            return None;
        }
        let earlier_frame = match self.complete.get(&id) {
            Some(&frame) => Some(frame),
            None => self.pending.get(&id).and_then(|p| p.forwarded),
        };
        if let Some(earlier_frame) = earlier_frame.filter(|&earlier| earlier != frame_index) {
            *self.conflicts.entry(id.agent_id).or_default() += 1;
            tracing::warn!(
                agent_id = id.agent_id,
                keyframe_id = id.keyframe_id,
                earlier_frame,
                frame_index,
                "keyframe id already used by another frame of this agent (a restart that chose \
                 other keyframes): this keyframe is ignored"
            );
            return None;
        }
        let pending = self.fresh_part(id, now, |p| p.forwarded.is_some() || p.image.is_some())?;
        pending.image = Some((keyframe, frame_index, timestamp_s));
        self.forward_if_ready(id, epoch)
    }

    /// A keyframe's patch of incarnation `epoch` arrived. Returns false for a repeat, which the
    /// caller drops (the Gaussians of the first one are already on their way), and for a patch
    /// of a foreign incarnation (its Gaussians are in another frame).
    pub fn patch(&mut self, id: KeyframeRef, epoch: u64, now: Instant) -> bool {
        if self.ignores(id.agent_id, epoch) {
            return false;
        }
        let Some(pending) = self.fresh_part(id, now, |p| p.patch) else {
            return false;
        };
        pending.patch = true;
        self.retire_if_complete(id);
        true
    }

    /// Hands the keyframe to the engine once descriptor and image are there; the first
    /// incarnation (`epoch`: the one whose part completed it) to do so for an agent sets the
    /// agent's frame anchor.
    fn forward_if_ready(&mut self, id: KeyframeRef, epoch: u64) -> Option<KeyframeArrival> {
        let pending = self.pending.get_mut(&id)?;
        if pending.descriptor.is_none() || pending.image.is_none() {
            return None;
        }
        let agent = self.incarnations.entry(id.agent_id).or_default();
        if agent.frame_anchor.is_none() {
            agent.frame_anchor = agent.anchors.get(&epoch).copied();
        }
        let descriptor = pending.descriptor.take()?;
        let (keyframe, frame_index, timestamp_s) = pending.image.take()?;
        pending.forwarded = Some(frame_index);
        self.retire_if_complete(id);
        Some(KeyframeArrival {
            keyframe,
            frame_index,
            timestamp_s,
            descriptor,
            gaussians: GaussianCloud::default(),
        })
    }

    fn retire_if_complete(&mut self, id: KeyframeRef) {
        let forwarded_with_patch = self.pending.get(&id).filter(|p| p.patch);
        if let Some(frame_index) = forwarded_with_patch.and_then(|p| p.forwarded) {
            self.pending.remove(&id);
            self.given_up.remove(&id);
            self.complete.insert(id, frame_index);
        }
    }

    /// An agent started again (a second hello): what its previous process left incomplete will
    /// never be completed, and the new process does not hold those keyframes.
    pub fn forget_incomplete(&mut self, agent_id: u32) {
        self.pending.retain(|id, _| id.agent_id != agent_id);
    }

    /// Keyframes that have waited `after_s` for a missing part since their first part or their
    /// last request, of agents not in `finished`, each at most `max_requests` times. Each
    /// returned request counts as sent.
    pub fn due_requests(&mut self, now: Instant, finished: &BTreeSet<u32>) -> Vec<ResendRequest> {
        let wait = Duration::from_secs_f64(self.policy.after_s);
        let mut due = Vec::new();
        for (id, pending) in &mut self.pending {
            if finished.contains(&id.agent_id)
                || now.saturating_duration_since(pending.waiting_since) < wait
            {
                continue;
            }
            if pending.requests >= self.policy.max_requests {
                if self.given_up.insert(*id) {
                    tracing::warn!(
                        agent_id = id.agent_id,
                        keyframe_id = id.keyframe_id,
                        requests = pending.requests,
                        missing = pending.missing().join(", "),
                        "keyframe still incomplete: no more requests"
                    );
                }
                continue;
            }
            pending.requests += 1;
            pending.waiting_since = now;
            due.push(ResendRequest {
                keyframe: *id,
                reason: format!(
                    "{} missing after {:.1} s",
                    pending.missing().join(" and "),
                    self.policy.after_s
                ),
            });
        }
        due
    }

    /// Messages of `agent_id` carrying keyframe parts were lost (a sequence gap): a keyframe may
    /// be missing whole, which no part can say. Reported by [`Self::due_loss_reports`].
    pub fn messages_lost(&mut self, agent_id: u32, now: Instant) {
        self.losses.entry(agent_id).or_insert(now);
    }

    /// Reports for agents not in `finished` whose loss was seen `after_s` ago or more
    /// ([`Self::with_loss_report_after`]): the
    /// messages sent after the loss have arrived by then, so the report names what is really
    /// missing. Each loss is reported once (a later loss makes a new report); none when
    /// `max_requests` is 0 (never ask) or nothing of the agent was seen.
    pub fn due_loss_reports(&mut self, now: Instant, finished: &BTreeSet<u32>) -> Vec<LossReport> {
        let wait = self.loss_report_after;
        let due: Vec<u32> = self
            .losses
            .iter()
            .filter(|&(_, &seen)| now.saturating_duration_since(seen) >= wait)
            .map(|(&agent_id, _)| agent_id)
            .collect();
        let mut reports = Vec::new();
        for agent_id in due {
            self.losses.remove(&agent_id);
            if finished.contains(&agent_id) || self.policy.max_requests == 0 {
                continue;
            }
            let keyframes_held = self.complete_keyframes(agent_id);
            let keyframes_in_part: Vec<u64> = self
                .pending
                .keys()
                .filter(|id| id.agent_id == agent_id)
                .map(|id| id.keyframe_id)
                .collect();
            let newest = keyframes_held
                .iter()
                .chain(&keyframes_in_part)
                .copied()
                .max();
            let Some(newest_seen) = newest else {
                continue;
            };
            reports.push(LossReport {
                agent_id,
                keyframes_held,
                keyframes_in_part,
                newest_seen,
            });
        }
        reports
    }

    /// Ids of `agent_id`'s keyframes of which every part arrived, in order.
    pub fn complete_keyframes(&self, agent_id: u32) -> Vec<u64> {
        self.complete
            .keys()
            .filter(|id| id.agent_id == agent_id)
            .map(|id| id.keyframe_id)
            .collect()
    }

    /// Keyframes of `agent_id` still missing a part.
    pub fn incomplete(&self, agent_id: u32) -> usize {
        self.pending
            .keys()
            .filter(|id| id.agent_id == agent_id)
            .count()
    }

    /// Parts of `agent_id`'s keyframes that arrived more than once (ignored).
    pub fn duplicates(&self, agent_id: u32) -> usize {
        self.duplicates.get(&agent_id).copied().unwrap_or(0)
    }

    /// Keyframe images of `agent_id` ignored because their id was taken by another frame.
    pub fn conflicts(&self, agent_id: u32) -> usize {
        self.conflicts.get(&agent_id).copied().unwrap_or(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geometry::camera::Intrinsics;
    use geometry::depth::DepthImage;
    use nalgebra::Isometry3;

    /// Epochs of an agent's first run and of its restart.
    const FIRST_RUN: u64 = 1_000;
    const RESTART: u64 = 2_000;
    /// Run anchors of the first run's frames and of other frames.
    const FIRST_FRAMES: u64 = 77;
    const OTHER_FRAMES: u64 = 88;

    fn id(keyframe_id: u64) -> KeyframeRef {
        KeyframeRef {
            agent_id: 3,
            keyframe_id,
        }
    }

    fn keyframe(keyframe_id: u64) -> Keyframe {
        let intrinsics = Intrinsics::new(50.0, 50.0, 2.0, 2.0, 4, 4);
        Keyframe {
            id: id(keyframe_id),
            rgb: image::RgbImage::new(4, 4),
            depth: DepthImage {
                width: 4,
                height: 4,
                data: vec![1.0; 16],
            },
            intrinsics,
            agent_from_camera: Isometry3::identity(),
        }
    }

    /// The first run's hello (anchor FIRST_FRAMES) and keyframes 0 .. count, each complete
    /// (keyframe k shows frame 10 k).
    fn first_run_keyframes(inbox: &mut KeyframeInbox, count: u64, now: Instant) {
        inbox.hello(3, FIRST_RUN, FIRST_FRAMES);
        for k in 0..count {
            assert!(inbox.patch(id(k), FIRST_RUN, now));
            assert!(inbox.descriptor(id(k), FIRST_RUN, vec![1.0], now).is_none());
            let arrival = inbox.image(id(k), FIRST_RUN, keyframe(k), 10 * k, 0.5, now);
            assert!(arrival.is_some());
        }
    }

    fn policy() -> ResendConfig {
        ResendConfig {
            after_s: 2.0,
            max_requests: 2,
            ..ResendConfig::default()
        }
    }

    #[test]
    fn a_keyframe_goes_to_the_engine_once_whatever_the_order_and_repeats() {
        let mut inbox = KeyframeInbox::new(policy());
        let now = Instant::now();
        assert!(inbox.patch(id(1), FIRST_RUN, now));
        assert!(
            inbox
                .image(id(1), FIRST_RUN, keyframe(1), 10, 0.5, now)
                .is_none()
        );
        let arrival = inbox
            .descriptor(id(1), FIRST_RUN, vec![1.0], now)
            .expect("descriptor and image are both there");
        assert_eq!(arrival.frame_index, 10);
        assert_eq!(inbox.incomplete(3), 0);
        // Everything again (a resend that crossed a late original): nothing new.
        assert!(inbox.descriptor(id(1), FIRST_RUN, vec![1.0], now).is_none());
        assert!(
            inbox
                .image(id(1), FIRST_RUN, keyframe(1), 10, 0.5, now)
                .is_none()
        );
        assert!(!inbox.patch(id(1), FIRST_RUN, now));
        assert_eq!(inbox.duplicates(3), 3);
        assert!(
            inbox
                .due_requests(now + Duration::from_secs(60), &BTreeSet::new())
                .is_empty()
        );
    }

    #[test]
    fn an_id_reused_for_another_frame_is_a_conflict_not_a_duplicate() {
        let mut inbox = KeyframeInbox::new(policy());
        let now = Instant::now();
        assert!(inbox.patch(id(5), FIRST_RUN, now));
        assert!(inbox.descriptor(id(5), FIRST_RUN, vec![1.0], now).is_none());
        let arrival = inbox.image(id(5), FIRST_RUN, keyframe(5), 10, 0.5, now);
        assert_eq!(arrival.expect("complete").frame_index, 10);
        // The same run's keyframe 5 again (a resend that crossed the original): a repeat.
        assert!(
            inbox
                .image(id(5), FIRST_RUN, keyframe(5), 10, 0.5, now)
                .is_none()
        );
        assert_eq!((inbox.conflicts(3), inbox.duplicates(3)), (0, 1));
        // Forwarded but still waiting for its patch: another frame under its id conflicts too.
        assert!(inbox.descriptor(id(6), FIRST_RUN, vec![1.0], now).is_none());
        assert!(
            inbox
                .image(id(6), FIRST_RUN, keyframe(6), 20, 1.0, now)
                .is_some()
        );
        // A restarted agent's keyframe 5 shows frame 99, and its keyframe 6 frame 21: each
        // ignored, counted as a conflict, whether the first run's keyframe was complete (5) or
        // still waiting for its patch (6).
        assert!(
            inbox
                .image(id(5), RESTART, keyframe(5), 99, 3.0, now)
                .is_none()
        );
        assert_eq!((inbox.conflicts(3), inbox.duplicates(3)), (1, 1));
        assert!(
            inbox
                .image(id(6), RESTART, keyframe(6), 21, 1.1, now)
                .is_none()
        );
        assert_eq!((inbox.conflicts(3), inbox.duplicates(3)), (2, 1));
        // No hello with another run anchor: the restart may run in the same frame, so it is
        // not foreign.
        assert!(!inbox.is_foreign(3, RESTART));
    }

    #[test]
    fn a_restart_on_other_frames_is_ignored_even_under_new_keyframe_ids() {
        let mut inbox = KeyframeInbox::new(policy());
        let now = Instant::now();
        first_run_keyframes(&mut inbox, 3, now);
        assert!(!inbox.latest_is_foreign(3));
        // The agent restarts on frames 300..: its hello has another anchor, so it tracks in a
        // frame of its own, before any of its keyframes arrives.
        inbox.hello(3, RESTART, OTHER_FRAMES);
        assert!(inbox.is_foreign(3, RESTART));
        assert!(inbox.latest_is_foreign(3));
        // Its keyframes 0 (an id the first run used) and 3 (one it did not) are ignored whole:
        // the new id must not land in the first run's frame.
        for (k, frame) in [(0, 300), (3, 330)] {
            assert!(!inbox.patch(id(k), RESTART, now));
            assert!(inbox.descriptor(id(k), RESTART, vec![1.0], now).is_none());
            let arrival = inbox.image(id(k), RESTART, keyframe(k), frame, 30.0, now);
            assert!(arrival.is_none());
        }
        assert_eq!(
            inbox.incomplete(3),
            0,
            "nothing of the restart waits for its parts"
        );
        assert_eq!((inbox.conflicts(3), inbox.duplicates(3)), (0, 0));
        assert_eq!(inbox.foreign_incarnations(3), 1);
        assert_eq!(inbox.foreign_parts(3), 6);
        // A late message of the first run still counts as that run's.
        assert!(!inbox.is_foreign(3, FIRST_RUN));
    }

    #[test]
    fn a_restart_replaying_the_same_frames_continues_the_agents_frame() {
        let mut inbox = KeyframeInbox::new(policy());
        let now = Instant::now();
        first_run_keyframes(&mut inbox, 2, now);
        inbox.hello(3, RESTART, FIRST_FRAMES);
        // Same command again: keyframe 0 shows the same frame (a repeat); keyframe 1 another
        // frame than in the first run (keyframe decisions depend on when corrections came):
        // that image alone is ignored; keyframe 2 is new and joins the agent's frame.
        assert!(!inbox.patch(id(0), RESTART, now));
        assert!(
            inbox
                .image(id(0), RESTART, keyframe(0), 0, 0.5, now)
                .is_none()
        );
        assert!(
            inbox
                .image(id(1), RESTART, keyframe(1), 12, 0.6, now)
                .is_none()
        );
        assert!(inbox.patch(id(2), RESTART, now));
        assert!(inbox.descriptor(id(2), RESTART, vec![1.0], now).is_none());
        assert!(
            inbox
                .image(id(2), RESTART, keyframe(2), 20, 2.0, now)
                .is_some()
        );
        assert!(!inbox.latest_is_foreign(3));
        assert_eq!((inbox.conflicts(3), inbox.foreign_parts(3)), (1, 0));
    }

    #[test]
    fn a_missing_part_is_requested_after_the_wait_at_most_max_requests_times() {
        let mut inbox = KeyframeInbox::new(policy());
        let start = Instant::now();
        let at = |s: f64| start + Duration::from_secs_f64(s);
        assert!(
            inbox
                .descriptor(id(4), FIRST_RUN, vec![1.0], start)
                .is_none()
        );
        assert!(inbox.due_requests(at(1.9), &BTreeSet::new()).is_empty());
        let first = inbox.due_requests(at(2.0), &BTreeSet::new());
        assert_eq!(first.len(), 1);
        assert_eq!(first[0].keyframe, id(4));
        assert!(
            first[0].reason.contains("RGB-D image") && first[0].reason.contains("patch"),
            "{}",
            first[0].reason
        );
        // The next request waits again from the last one.
        assert!(inbox.due_requests(at(3.0), &BTreeSet::new()).is_empty());
        assert_eq!(inbox.due_requests(at(4.0), &BTreeSet::new()).len(), 1);
        // max_requests = 2: no third request.
        assert!(inbox.due_requests(at(10.0), &BTreeSet::new()).is_empty());
        assert_eq!(inbox.incomplete(3), 1);
        // A late answer still completes it.
        assert!(
            inbox
                .image(id(4), FIRST_RUN, keyframe(4), 40, 4.0, at(11.0))
                .is_some()
        );
        assert!(inbox.patch(id(4), FIRST_RUN, at(11.0)));
        assert_eq!(inbox.incomplete(3), 0);
    }

    #[test]
    fn a_loss_is_reported_once_after_the_wait_with_what_is_held_whole_and_in_part() {
        // A bandwidth budget's allowance delays requests for parts, not loss reports.
        let deferring = ResendConfig {
            after_s: 62.0,
            ..policy()
        };
        let mut inbox = KeyframeInbox::new(deferring).with_loss_report_after(2.0);
        let start = Instant::now();
        let at = |s: f64| start + Duration::from_secs_f64(s);
        // Keyframes 0, 1 complete; 5 in part (its descriptor only); 2-4 never seen.
        first_run_keyframes(&mut inbox, 2, start);
        assert!(
            inbox
                .descriptor(id(5), FIRST_RUN, vec![1.0], start)
                .is_none()
        );
        assert!(
            inbox
                .due_loss_reports(at(100.0), &BTreeSet::new())
                .is_empty()
        );

        inbox.messages_lost(3, at(1.0));
        // A second gap before the report does not move it.
        inbox.messages_lost(3, at(2.5));
        assert!(inbox.due_loss_reports(at(2.9), &BTreeSet::new()).is_empty());
        let reports = inbox.due_loss_reports(at(3.0), &BTreeSet::new());
        assert_eq!(
            reports,
            [LossReport {
                agent_id: 3,
                keyframes_held: vec![0, 1],
                keyframes_in_part: vec![5],
                newest_seen: 5,
            }]
        );
        // Reported once; a later loss makes a new report.
        assert!(
            inbox
                .due_loss_reports(at(10.0), &BTreeSet::new())
                .is_empty()
        );
        inbox.messages_lost(3, at(11.0));
        assert_eq!(inbox.due_loss_reports(at(13.0), &BTreeSet::new()).len(), 1);

        // Not for a finished agent, nor when requests are off, nor for an agent never seen.
        inbox.messages_lost(3, at(20.0));
        assert!(
            inbox
                .due_loss_reports(at(30.0), &BTreeSet::from([3]))
                .is_empty()
        );
        let mut never_ask = KeyframeInbox::new(ResendConfig {
            max_requests: 0,
            ..policy()
        });
        first_run_keyframes(&mut never_ask, 2, start);
        never_ask.messages_lost(3, start);
        assert!(
            never_ask
                .due_loss_reports(at(30.0), &BTreeSet::new())
                .is_empty()
        );
        inbox.messages_lost(9, at(40.0));
        assert!(
            inbox
                .due_loss_reports(at(50.0), &BTreeSet::new())
                .is_empty()
        );
    }

    #[test]
    fn finished_agents_are_not_asked_and_a_restart_forgets_the_old_process() {
        let mut inbox = KeyframeInbox::new(policy());
        let start = Instant::now();
        assert!(
            inbox
                .image(id(2), FIRST_RUN, keyframe(2), 20, 2.0, start)
                .is_none()
        );
        let late = start + Duration::from_secs(5);
        assert!(inbox.due_requests(late, &BTreeSet::from([3])).is_empty());
        inbox.forget_incomplete(3);
        assert_eq!(inbox.incomplete(3), 0);
        assert!(inbox.due_requests(late, &BTreeSet::new()).is_empty());
    }
}
