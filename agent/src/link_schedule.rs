//! Simulated intermittent links: a schedule file says, per agent, in which time
//! windows its link to the consensus is up, so a swarm on one host behaves like robots that lose
//! and regain their radio.
//!
//! # File format (TOML)
//!
//! ```toml
//! # Bound of each agent's queue of unsent keyframes (MiB); optional, default 256.
//! queue_limit_mib = 256
//!
//! # Agent 1: up for the first 10 s, down from 10 s to 25 s, up again from 25 s to the end.
//! [[agent]]
//! id = 1
//! up = [{ from_s = 0, until_s = 10 }, { from_s = 25 }]
//! ```
//!
//! - Times are seconds since the agent process started; a window is `[from_s, until_s)`, and a
//!   window without `until_s` lasts to the end of the run. Windows are listed in time order and
//!   must not overlap; `until_s` must come after `from_s`.
//! - Outside its windows an agent's link is down. `up = []` keeps it down for the whole run.
//! - An agent without an `[[agent]]` entry is always up. Entries for ids that no agent of the
//!   swarm uses are ignored (the agents and `mac-agent --check-link-schedule` say so).
//!
//! # What a down link does (see [`crate::swarm::SwarmLink`])
//!
//! - **Queue and deliver.** What the agent would publish (its hello, and each keyframe's
//!   descriptor, RGB-D image and Gaussian patch) is queued in order and delivered when the link is
//!   up again; nothing is re-requested. Each keyframe is prepared (descriptor computed) when it
//!   is due, so a reconnect only copies queued messages into shared memory.
//! - **Bounded.** The queue of keyframes holds at most `queue_limit_mib`; beyond that the oldest
//!   keyframes are dropped, with a warning, and counted in metrics.json (`swarm.link`). The hello
//!   is never dropped.
//! - **Corrections wait.** Corrections from the consensus are not applied while the link is down;
//!   the newest one is taken at reconnect and supersedes older ones (an agent only ever applies its
//!   latest `world_from_agent`), as if the consensus re-sent its latest solution then.
//! - **Heartbeats stop.** A down link carries no heartbeat either. The consensus does not treat
//!   silence as death: it waits for each expected agent's goodbye.
//! - **Goodbye always arrives.** At the end of the run the link is opened regardless of the
//!   schedule: the queue is flushed, then the final map and the goodbye go out, so the consensus
//!   gets every keyframe and never waits for an agent that has finished.

use std::collections::{BTreeMap, VecDeque};
use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

/// Default bound of an agent's queue of unsent keyframes. A 640x480 keyframe (image, descriptor,
/// patch) is about 2 MB, so this holds over a hundred of them.
pub const DEFAULT_QUEUE_LIMIT_MIB: f64 = 256.0;

const BYTES_PER_MIB: f64 = 1024.0 * 1024.0;

/// The file as written (see the module documentation).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScheduleFile {
    #[serde(default = "default_queue_limit_mib")]
    queue_limit_mib: f64,
    #[serde(default, rename = "agent")]
    agents: Vec<AgentEntry>,
}

fn default_queue_limit_mib() -> f64 {
    DEFAULT_QUEUE_LIMIT_MIB
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct AgentEntry {
    id: u32,
    up: Vec<WindowEntry>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct WindowEntry {
    from_s: f64,
    until_s: Option<f64>,
}

/// A bad schedule file; every message names the file, and the agent and window at fault.
#[derive(Debug, thiserror::Error)]
pub enum LinkScheduleError {
    /// The file could not be read.
    #[error("link schedule {path}: {source}")]
    Read {
        /// The schedule file.
        path: PathBuf,
        /// Why reading it failed.
        source: std::io::Error,
    },
    /// The file is not valid TOML, or has unknown, missing or mistyped keys.
    #[error("link schedule {path}: {message}")]
    Syntax {
        /// The schedule file.
        path: PathBuf,
        /// The TOML parser's message (it names the line).
        message: String,
    },
    /// `queue_limit_mib` is not a finite number above 0.
    #[error("link schedule {path}: queue_limit_mib = {value}: expected a positive number of MiB")]
    QueueLimit {
        /// The schedule file.
        path: PathBuf,
        /// The value given, in MiB.
        value: f64,
    },
    /// Two `[[agent]]` entries have the same id.
    #[error("link schedule {path}: agent {agent} is listed twice")]
    DuplicateAgent {
        /// The schedule file.
        path: PathBuf,
        /// The repeated agent id.
        agent: u32,
    },
    /// A window of an agent's `up` list is invalid: a negative or non-finite start, an end not
    /// after its start, or out of time order or overlapping the window before it.
    #[error("link schedule {path}: agent {agent}, window {window} ({text}): {reason}")]
    Window {
        /// The schedule file.
        path: PathBuf,
        /// The agent whose list holds the window.
        agent: u32,
        /// 1-based position in the agent's `up` list.
        window: usize,
        /// The window as written (`from_s = ..., until_s = ...`).
        text: String,
        /// What is wrong with it.
        reason: String,
    },
}

/// One window in which a link is up: `[from_s, until_s)`, seconds since the agent started.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UpWindow {
    /// Start, in seconds since the agent started (finite, 0 or more); the window includes it.
    pub from_s: f64,
    /// `f64::INFINITY`: up to the end of the run.
    pub until_s: f64,
}

impl UpWindow {
    fn contains(&self, t_s: f64) -> bool {
        self.from_s <= t_s && t_s < self.until_s
    }
}

impl fmt::Display for UpWindow {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.until_s.is_finite() {
            write!(f, "{} s to {} s", self.from_s, self.until_s)
        } else {
            write!(f, "{} s to the end", self.from_s)
        }
    }
}

/// When one agent's link is up.
#[derive(Debug, Clone, PartialEq)]
pub enum UpWindows {
    /// No entry in the schedule (or no schedule).
    Always,
    /// Up only inside these windows (time order, no overlap; possibly none).
    Within(Vec<UpWindow>),
}

impl UpWindows {
    /// Whether the link is up `t_s` seconds after the agent started.
    pub fn is_up(&self, t_s: f64) -> bool {
        match self {
            UpWindows::Always => true,
            UpWindows::Within(windows) => windows.iter().any(|w| w.contains(t_s)),
        }
    }
}

impl fmt::Display for UpWindows {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            UpWindows::Always => write!(f, "always up"),
            UpWindows::Within(windows) if windows.is_empty() => {
                write!(f, "down for the whole run (until the final goodbye)")
            }
            UpWindows::Within(windows) => {
                let parts: Vec<String> = windows.iter().map(ToString::to_string).collect();
                write!(f, "up {}", parts.join(", "))
            }
        }
    }
}

/// A validated schedule file.
#[derive(Debug, Clone)]
pub struct LinkSchedule {
    path: PathBuf,
    queue_limit_bytes: u64,
    agents: BTreeMap<u32, Vec<UpWindow>>,
}

impl LinkSchedule {
    /// Reads and validates the schedule file at `path`.
    pub fn load(path: &Path) -> Result<Self, LinkScheduleError> {
        let text = std::fs::read_to_string(path).map_err(|source| LinkScheduleError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// Parses and validates `text`; `path` only names the file in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self, LinkScheduleError> {
        let file: ScheduleFile =
            toml::from_str(text).map_err(|error| LinkScheduleError::Syntax {
                path: path.to_path_buf(),
                message: error.to_string().trim_end().to_string(),
            })?;
        if !(file.queue_limit_mib.is_finite() && file.queue_limit_mib > 0.0) {
            return Err(LinkScheduleError::QueueLimit {
                path: path.to_path_buf(),
                value: file.queue_limit_mib,
            });
        }
        let mut agents = BTreeMap::new();
        for entry in file.agents {
            let windows = validate_windows(path, entry.id, &entry.up)?;
            if agents.insert(entry.id, windows).is_some() {
                return Err(LinkScheduleError::DuplicateAgent {
                    path: path.to_path_buf(),
                    agent: entry.id,
                });
            }
        }
        Ok(Self {
            path: path.to_path_buf(),
            queue_limit_bytes: (file.queue_limit_mib * BYTES_PER_MIB).round() as u64,
            agents,
        })
    }

    /// The file the schedule was read from (or that `parse` was given).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bound of each agent's queue of unsent keyframes, in bytes (`queue_limit_mib` x 2^20).
    pub fn queue_limit_bytes(&self) -> u64 {
        self.queue_limit_bytes
    }

    /// When agent `agent_id`'s link is up (always, when the file does not list it).
    pub fn windows(&self, agent_id: u32) -> UpWindows {
        match self.agents.get(&agent_id) {
            Some(windows) => UpWindows::Within(windows.clone()),
            None => UpWindows::Always,
        }
    }

    /// Ids in the file that a swarm of agents `0..agent_count` does not have (they are ignored).
    pub fn agents_outside(&self, agent_count: u32) -> Vec<u32> {
        self.agents
            .keys()
            .copied()
            .filter(|id| *id >= agent_count)
            .collect()
    }

    /// Every agent's windows in a swarm of `agents`, and the ids in the file that swarm does
    /// not have (`mac-agent --check-link-schedule`, `mac-ego3d swarm --link-schedule`).
    pub fn describe(&self, agents: u32) -> String {
        let mut text = format!(
            "link schedule {} (queue bound {:.0} MiB per agent)\n",
            self.path().display(),
            self.queue_limit_bytes() as f64 / (1024.0 * 1024.0)
        );
        for agent_id in 0..agents {
            text += &format!("  agent {agent_id}: {}\n", self.windows(agent_id));
        }
        for agent_id in self.agents_outside(agents) {
            text += &format!("  agent {agent_id}: not in this swarm of {agents} agents: ignored\n");
        }
        text
    }

    /// The link plan of one agent whose clock started at `started`.
    pub fn plan(&self, agent_id: u32, started: Instant) -> LinkPlan {
        LinkPlan {
            windows: self.windows(agent_id),
            queue_limit_bytes: self.queue_limit_bytes,
            started,
        }
    }
}

fn validate_windows(
    path: &Path,
    agent: u32,
    entries: &[WindowEntry],
) -> Result<Vec<UpWindow>, LinkScheduleError> {
    let mut windows: Vec<UpWindow> = Vec::with_capacity(entries.len());
    for (i, entry) in entries.iter().enumerate() {
        let text = match entry.until_s {
            Some(until) => format!("from_s = {}, until_s = {until}", entry.from_s),
            None => format!("from_s = {}", entry.from_s),
        };
        let fail = |reason: String| LinkScheduleError::Window {
            path: path.to_path_buf(),
            agent,
            window: i + 1,
            text: text.clone(),
            reason,
        };
        if !(entry.from_s.is_finite() && entry.from_s >= 0.0) {
            return Err(fail(
                "from_s must be a finite number of seconds, 0 or more".into(),
            ));
        }
        let until_s = entry.until_s.unwrap_or(f64::INFINITY);
        if until_s.is_nan() {
            return Err(fail("until_s is not a number".into()));
        }
        if until_s <= entry.from_s {
            return Err(fail(
                "reversed or empty window: until_s must come after from_s".into(),
            ));
        }
        if let Some(previous) = windows.last() {
            if entry.from_s < previous.from_s {
                return Err(fail(format!(
                    "starts before window {i} ({previous}): list windows in time order"
                )));
            }
            if entry.from_s < previous.until_s {
                return Err(fail(format!("overlaps window {i} ({previous})")));
            }
        }
        windows.push(UpWindow {
            from_s: entry.from_s,
            until_s,
        });
    }
    Ok(windows)
}

/// How one agent's link behaves: its windows, on the clock that started with the agent, and the
/// bound of its queue.
#[derive(Debug, Clone)]
pub struct LinkPlan {
    /// When the link is up, in seconds since `started`.
    pub windows: UpWindows,
    /// Bound of the queue of unsent keyframes, in bytes.
    pub queue_limit_bytes: u64,
    /// The moment the agent's link clock started (time 0 of `windows`).
    pub started: Instant,
}

impl LinkPlan {
    /// No schedule: the link is always up (the queue is then never used).
    pub fn always_up() -> Self {
        Self {
            windows: UpWindows::Always,
            queue_limit_bytes: (DEFAULT_QUEUE_LIMIT_MIB * BYTES_PER_MIB) as u64,
            started: Instant::now(),
        }
    }

    /// Seconds since the agent started.
    pub fn elapsed_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// Whether the schedule has the link up at this moment.
    pub fn is_up_now(&self) -> bool {
        self.windows.is_up(self.elapsed_s())
    }
}

/// A FIFO bounded by the bytes of its items: pushing beyond the bound drops the oldest items
/// (the newest one too, when it alone exceeds the bound).
#[derive(Debug)]
pub struct BoundedQueue<T> {
    items: VecDeque<(T, u64)>,
    bytes: u64,
    limit_bytes: u64,
}

impl<T> BoundedQueue<T> {
    /// An empty queue that holds at most `limit_bytes` (as its items' sizes are given).
    pub fn new(limit_bytes: u64) -> Self {
        Self {
            items: VecDeque::new(),
            bytes: 0,
            limit_bytes,
        }
    }

    /// Appends `item` of `bytes`; returns the items dropped to stay within the bound, oldest first.
    pub fn push(&mut self, item: T, bytes: u64) -> Vec<(T, u64)> {
        self.items.push_back((item, bytes));
        self.bytes += bytes;
        let mut dropped = Vec::new();
        while self.bytes > self.limit_bytes {
            let Some(oldest) = self.pop_front_with_bytes() else {
                break;
            };
            dropped.push(oldest);
        }
        dropped
    }

    /// Takes the oldest item; `None` when the queue is empty.
    pub fn pop_front(&mut self) -> Option<T> {
        self.pop_front_with_bytes().map(|(item, _)| item)
    }

    /// Puts back at the head an item just taken with [`Self::pop_front`] (one whose delivery
    /// failed): nothing is dropped for it, the bound holds again once it goes out.
    pub fn push_front(&mut self, item: T, bytes: u64) {
        self.items.push_front((item, bytes));
        self.bytes += bytes;
    }

    fn pop_front_with_bytes(&mut self) -> Option<(T, u64)> {
        let (item, bytes) = self.items.pop_front()?;
        self.bytes -= bytes;
        Some((item, bytes))
    }

    /// Number of items held.
    pub fn len(&self) -> usize {
        self.items.len()
    }

    /// Whether no item is held.
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    /// Sum of the held items' sizes, as given to `push` and `push_front`.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

/// Corrections while the link is down: only the newest is kept (an agent applies only its
/// latest `world_from_agent`), and it is released once the link is up again.
#[derive(Debug)]
pub struct CorrectionGate<T> {
    held: Option<T>,
}

impl<T> Default for CorrectionGate<T> {
    fn default() -> Self {
        Self { held: None }
    }
}

/// What became of an arriving correction.
#[derive(Debug, PartialEq)]
pub enum CorrectionArrival<T> {
    /// The link is up: apply it now.
    Apply(T),
    /// The link is down: held; `superseded` when it replaced an older held one.
    Held {
        /// Whether an older held correction was replaced (and so will never be applied).
        superseded: bool,
    },
}

impl<T> CorrectionGate<T> {
    /// Takes a correction that just arrived: with the link up it is to be applied now (and
    /// anything held, being older, is discarded); with it down it is held in place of any older
    /// one.
    pub fn arrive(&mut self, correction: T, link_up: bool) -> CorrectionArrival<T> {
        if link_up {
            // Anything held is older than this one.
            self.held = None;
            return CorrectionArrival::Apply(correction);
        }
        CorrectionArrival::Held {
            superseded: self.held.replace(correction).is_some(),
        }
    }

    /// The held correction, to apply now that the link is up.
    pub fn release(&mut self) -> Option<T> {
        self.held.take()
    }
}

/// What the simulated link did, for metrics.json (`swarm.link`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct LinkSummary {
    /// The agent's windows, in words ("always up" without a schedule).
    pub schedule: String,
    /// Bound of the queue of unsent keyframes, in bytes.
    pub queue_limit_bytes: u64,
    /// When the link was seen to go down (seconds since the agent started; the state is checked
    /// between frames).
    pub went_down_at_s: Vec<f64>,
    /// When the link was seen to come back up (seconds since the agent started).
    pub came_up_at_s: Vec<f64>,
    /// Keyframes (descriptor + image + patch each) produced while the link was down.
    pub keyframes_queued: usize,
    /// Queued keyframes delivered later: at a reconnect, or at the end before the goodbye.
    pub keyframes_delivered_late: usize,
    /// Of those, the ones delivered at the end while the schedule still had the link down.
    pub keyframes_flushed_at_goodbye: usize,
    /// Queued keyframes dropped because the queue exceeded its bound (oldest first).
    pub keyframes_dropped_queue_full: usize,
    /// Size of those dropped keyframes' messages, in bytes.
    pub bytes_dropped_queue_full: u64,
    /// Largest size the queue reached, in bytes.
    pub queue_peak_bytes: u64,
    /// Longest time a keyframe delivered late waited in the queue, in seconds.
    pub late_delivery_s_max: f64,
    /// Mean time a keyframe delivered late waited in the queue, in seconds.
    pub late_delivery_s_mean: f64,
    /// Whether the hello itself waited for the link.
    pub hello_delivered_late: bool,
    /// Corrections that arrived while the link was down and waited for it.
    pub corrections_held: usize,
    /// Held corrections replaced by a newer one before the link came back (never applied).
    pub corrections_superseded: usize,
}

impl LinkSummary {
    /// An empty summary of `plan`'s link: its windows in words and its queue bound.
    pub fn new(plan: &LinkPlan) -> Self {
        Self {
            schedule: plan.windows.to_string(),
            queue_limit_bytes: plan.queue_limit_bytes,
            ..Self::default()
        }
    }

    /// Records one late delivery that waited `waited_s` in the queue.
    pub fn delivered_late(&mut self, waited_s: f64, with_link_down: bool) {
        let previous = self.keyframes_delivered_late as f64;
        self.keyframes_delivered_late += 1;
        self.late_delivery_s_mean = (self.late_delivery_s_mean * previous + waited_s)
            / self.keyframes_delivered_late as f64;
        self.late_delivery_s_max = self.late_delivery_s_max.max(waited_s);
        if with_link_down {
            self.keyframes_flushed_at_goodbye += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<LinkSchedule, LinkScheduleError> {
        LinkSchedule::parse(text, Path::new("links.toml"))
    }

    fn error(text: &str) -> String {
        parse(text)
            .expect_err("the schedule must be refused")
            .to_string()
    }

    const TWO_WINDOWS: &str = r#"
        queue_limit_mib = 8
        [[agent]]
        id = 1
        up = [{ from_s = 0, until_s = 10 }, { from_s = 25.5 }]
        [[agent]]
        id = 2
        up = []
    "#;

    #[test]
    fn parses_windows_and_answers_up_or_down_at_given_times() {
        let schedule = parse(TWO_WINDOWS).unwrap();
        assert_eq!(schedule.queue_limit_bytes(), 8 * 1024 * 1024);
        let agent_1 = schedule.windows(1);
        for (t_s, up) in [
            (0.0, true),
            (9.99, true),
            (10.0, false),
            (25.0, false),
            (25.5, true),
            (1e6, true),
        ] {
            assert_eq!(agent_1.is_up(t_s), up, "agent 1 at {t_s} s");
        }
        assert!(!schedule.windows(2).is_up(0.0), "up = [] is never up");
        assert_eq!(schedule.windows(0), UpWindows::Always);
        assert!(schedule.windows(0).is_up(1234.0));
        assert_eq!(
            agent_1.to_string(),
            "up 0 s to 10 s, 25.5 s to the end",
            "described in words for logs and metrics"
        );
    }

    #[test]
    fn an_empty_file_keeps_every_link_up_with_the_default_bound() {
        let schedule = parse("").unwrap();
        assert!(schedule.windows(3).is_up(0.0));
        assert_eq!(
            schedule.queue_limit_bytes(),
            (DEFAULT_QUEUE_LIMIT_MIB * BYTES_PER_MIB) as u64
        );
    }

    #[test]
    fn ids_outside_the_swarm_are_reported() {
        let schedule = parse(TWO_WINDOWS).unwrap();
        assert_eq!(schedule.agents_outside(2), vec![2]);
        assert!(schedule.agents_outside(3).is_empty());
    }

    #[test]
    fn overlapping_windows_name_the_file_agent_and_window() {
        let message = error(
            "[[agent]]\nid = 4\nup = [{ from_s = 0, until_s = 10 }, { from_s = 5, until_s = 20 }]",
        );
        assert!(message.contains("links.toml"), "{message}");
        assert!(message.contains("agent 4, window 2"), "{message}");
        assert!(message.contains("overlaps window 1"), "{message}");
    }

    #[test]
    fn a_window_after_an_open_ended_one_overlaps_it() {
        let message = error("[[agent]]\nid = 0\nup = [{ from_s = 0 }, { from_s = 5 }]");
        assert!(
            message.contains("window 2") && message.contains("overlaps"),
            "{message}"
        );
    }

    #[test]
    fn reversed_empty_and_unordered_windows_are_refused() {
        let reversed = error("[[agent]]\nid = 1\nup = [{ from_s = 10, until_s = 5 }]");
        assert!(reversed.contains("agent 1, window 1"), "{reversed}");
        assert!(reversed.contains("reversed"), "{reversed}");
        let empty = error("[[agent]]\nid = 1\nup = [{ from_s = 3, until_s = 3 }]");
        assert!(empty.contains("empty"), "{empty}");
        let unordered = error(
            "[[agent]]\nid = 1\nup = [{ from_s = 20, until_s = 30 }, { from_s = 0, until_s = 5 }]",
        );
        assert!(unordered.contains("time order"), "{unordered}");
        let negative = error("[[agent]]\nid = 1\nup = [{ from_s = -1, until_s = 5 }]");
        assert!(negative.contains("from_s"), "{negative}");
    }

    #[test]
    fn touching_windows_are_accepted() {
        let schedule = parse(
            "[[agent]]\nid = 0\nup = [{ from_s = 0, until_s = 5 }, { from_s = 5, until_s = 9 }]",
        )
        .unwrap();
        assert!(schedule.windows(0).is_up(5.0));
        assert!(!schedule.windows(0).is_up(9.0));
    }

    #[test]
    fn duplicate_agents_unknown_keys_and_bad_bounds_are_refused() {
        let duplicate = error("[[agent]]\nid = 1\nup = []\n[[agent]]\nid = 1\nup = []");
        assert!(duplicate.contains("agent 1 is listed twice"), "{duplicate}");
        let typo = error("[[agent]]\nid = 1\nup = [{ from = 0 }]");
        assert!(
            typo.contains("links.toml") && typo.contains("from"),
            "{typo}"
        );
        let bound = error("queue_limit_mib = 0");
        assert!(bound.contains("queue_limit_mib"), "{bound}");
        let missing = error("[[agent]]\nid = 1");
        assert!(missing.contains("up"), "{missing}");
    }

    #[test]
    fn a_missing_file_is_named() {
        let error = LinkSchedule::load(Path::new("/nonexistent/links.toml")).unwrap_err();
        assert!(error.to_string().contains("/nonexistent/links.toml"));
    }

    #[test]
    fn the_queue_keeps_order_and_drops_the_oldest_beyond_its_bound() {
        let mut queue = BoundedQueue::new(10);
        assert!(queue.push("a", 4).is_empty());
        assert!(queue.push("b", 4).is_empty());
        assert_eq!(queue.bytes(), 8);
        let dropped = queue.push("c", 4);
        assert_eq!(dropped, vec![("a", 4)], "the oldest goes first");
        assert_eq!(queue.bytes(), 8);
        assert_eq!(queue.len(), 2);
        assert_eq!(queue.pop_front(), Some("b"));
        assert_eq!(queue.pop_front(), Some("c"));
        assert!(queue.is_empty());
        assert_eq!(queue.bytes(), 0);
    }

    #[test]
    fn an_item_larger_than_the_whole_bound_is_dropped_too() {
        let mut queue = BoundedQueue::new(10);
        queue.push("small", 3);
        let dropped = queue.push("huge", 11);
        assert_eq!(dropped, vec![("small", 3), ("huge", 11)]);
        assert!(queue.is_empty());
        assert_eq!(queue.bytes(), 0);
    }

    #[test]
    fn held_corrections_wait_for_the_link_and_the_newest_wins() {
        let mut gate = CorrectionGate::default();
        assert_eq!(gate.arrive(1, true), CorrectionArrival::Apply(1));
        assert_eq!(gate.release(), None);
        assert_eq!(
            gate.arrive(2, false),
            CorrectionArrival::Held { superseded: false }
        );
        assert_eq!(
            gate.arrive(3, false),
            CorrectionArrival::Held { superseded: true }
        );
        assert_eq!(gate.release(), Some(3), "the newest held correction");
        assert_eq!(gate.release(), None);
        gate.arrive(4, false);
        assert_eq!(gate.arrive(5, true), CorrectionArrival::Apply(5));
        assert_eq!(
            gate.release(),
            None,
            "a newer correction replaced the held one"
        );
    }

    #[test]
    fn late_deliveries_update_the_wait_figures() {
        let mut summary = LinkSummary::default();
        summary.delivered_late(2.0, false);
        summary.delivered_late(4.0, true);
        assert_eq!(summary.keyframes_delivered_late, 2);
        assert_eq!(summary.keyframes_flushed_at_goodbye, 1);
        assert_eq!(summary.late_delivery_s_max, 4.0);
        assert!((summary.late_delivery_s_mean - 3.0).abs() < 1e-12);
    }
}
