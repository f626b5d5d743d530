//! Which synthetic sequence to produce: [`SyntheticSpec`], its `synthetic:key=value,...` text
//! form and its limits.

use std::fmt;
use std::str::FromStr;

use geometry::camera::Intrinsics;
use geometry::trajectory::NO_CLOCK_FRAMES_PER_SECOND;
use serde::{Deserialize, Serialize};

/// The word that selects this dataset in `--dataset` arguments and configs.
pub const SPEC_PREFIX: &str = "synthetic";
/// Default `agents`: three agents share the scene.
pub const DEFAULT_AGENTS: usize = 3;
/// Default `frames` per agent: 300 (10 s at 30 frames per second).
pub const DEFAULT_FRAMES: usize = 300;
/// Default `seed` (textures, object placement, trajectory jitter).
pub const DEFAULT_SEED: u64 = 0;
/// Default `width`: 640 pixels, a Kinect-like 640x480 image with [`DEFAULT_HEIGHT`].
pub const DEFAULT_WIDTH: u32 = 640;
/// Default `height`: 480 pixels.
pub const DEFAULT_HEIGHT: u32 = 480;
/// Limits that keep a typo from asking for terabytes or a degenerate camera.
pub const MAX_AGENTS: usize = 64;
/// Largest `frames` (per agent) accepted.
pub const MAX_FRAMES: usize = 1_000_000;
/// Smallest `width` and `height` accepted, pixels.
pub const MIN_IMAGE_SIDE: u32 = 16;
/// Largest `width` and `height` accepted, pixels.
pub const MAX_IMAGE_SIDE: u32 = 8192;

/// Focal length in pixels at the reference width (a Kinect-like 525 px at 640 px); other widths
/// scale it so the horizontal field of view stays the same.
const REFERENCE_FOCAL_PX: f64 = 525.0;
const REFERENCE_WIDTH_PX: f64 = 640.0;
/// Camera rate. The same rate the 7-Scenes reader assumes for its clock-less frames, so written
/// and read-back timestamps agree.
pub const FRAMES_PER_SECOND: f64 = NO_CLOCK_FRAMES_PER_SECOND;

/// Which synthetic sequence to produce: `synthetic` or
/// `synthetic:agents=3,agent=1,frames=300,seed=7,width=320,height=240` (any subset of keys, any
/// order; missing keys take the defaults).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct SyntheticSpec {
    /// Number of agents sharing the scene (the trajectories depend on it: agents are spread
    /// evenly around the loop).
    pub agents: usize,
    /// Which agent this sequence is (0-based, < agents).
    pub agent: usize,
    /// Frames per agent, 30 per second.
    pub frames: usize,
    /// Seed of textures, object placement and trajectory jitter.
    pub seed: u64,
    /// Image width in pixels (16 to 8192; default 640).
    pub width: u32,
    /// Image height in pixels (16 to 8192; default 480).
    pub height: u32,
}

impl Default for SyntheticSpec {
    fn default() -> Self {
        Self {
            agents: DEFAULT_AGENTS,
            agent: 0,
            frames: DEFAULT_FRAMES,
            seed: DEFAULT_SEED,
            width: DEFAULT_WIDTH,
            height: DEFAULT_HEIGHT,
        }
    }
}

impl SyntheticSpec {
    /// The same sequence for another agent.
    pub fn with_agent(self, agent: usize) -> Self {
        Self { agent, ..self }
    }

    /// Pinhole intrinsics: fx = fy = 525 px at 640 px width (scaled with the width), principal
    /// point in the image centre. 640x480 gives fx = fy = 525, cx = 319.5, cy = 239.5.
    pub fn intrinsics(&self) -> Intrinsics {
        let focal = REFERENCE_FOCAL_PX * self.width as f64 / REFERENCE_WIDTH_PX;
        Intrinsics::new(
            focal,
            focal,
            (self.width as f64 - 1.0) / 2.0,
            (self.height as f64 - 1.0) / 2.0,
            self.width,
            self.height,
        )
    }

    /// Checks every field; the message names the offending key.
    pub fn validate(&self) -> Result<(), String> {
        if self.agents == 0 || self.agents > MAX_AGENTS {
            return Err(format!(
                "agents={} is out of range 1..={MAX_AGENTS}",
                self.agents
            ));
        }
        if self.agent >= self.agents {
            return Err(format!(
                "agent={} is out of range: with agents={} the agent must be 0..={}",
                self.agent,
                self.agents,
                self.agents - 1
            ));
        }
        if self.frames == 0 || self.frames > MAX_FRAMES {
            return Err(format!(
                "frames={} is out of range 1..={MAX_FRAMES}",
                self.frames
            ));
        }
        for (key, value) in [("width", self.width), ("height", self.height)] {
            if !(MIN_IMAGE_SIDE..=MAX_IMAGE_SIDE).contains(&value) {
                return Err(format!(
                    "{key}={value} is out of range {MIN_IMAGE_SIDE}..={MAX_IMAGE_SIDE}"
                ));
            }
        }
        Ok(())
    }
}

impl FromStr for SyntheticSpec {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let text = text.trim();
        let rest = text
            .strip_prefix(SPEC_PREFIX)
            .ok_or_else(|| format!("{text:?} is not a synthetic spec: expected `{SPEC_PREFIX}` or `{SPEC_PREFIX}:key=value,...`"))?;
        let mut spec = Self::default();
        let options = match rest.strip_prefix(':') {
            Some(options) => options,
            None if rest.is_empty() => "",
            None => {
                return Err(format!(
                    "{text:?} is not a synthetic spec: expected `:` after `{SPEC_PREFIX}`"
                ));
            }
        };
        let mut seen: Vec<&str> = Vec::new();
        for item in options
            .split(',')
            .map(str::trim)
            .filter(|item| !item.is_empty())
        {
            let (key, value) = item
                .split_once('=')
                .map(|(k, v)| (k.trim(), v.trim()))
                .ok_or_else(|| format!("{item:?} in synthetic spec {text:?} is not key=value"))?;
            if seen.contains(&key) {
                return Err(format!(
                    "key {key:?} appears twice in synthetic spec {text:?}"
                ));
            }
            seen.push(key);
            let bad = |expected: &str| {
                format!(
                    "bad value {value:?} for key {key:?} in synthetic spec {text:?}: expected {expected}"
                )
            };
            match key {
                "agents" => spec.agents = value.parse().map_err(|_| bad("a positive integer"))?,
                "agent" => spec.agent = value.parse().map_err(|_| bad("an agent number from 0"))?,
                "frames" => spec.frames = value.parse().map_err(|_| bad("a positive integer"))?,
                "seed" => {
                    spec.seed = value
                        .parse()
                        .map_err(|_| bad("an unsigned 64-bit integer"))?
                }
                "width" => spec.width = value.parse().map_err(|_| bad("a width in pixels"))?,
                "height" => spec.height = value.parse().map_err(|_| bad("a height in pixels"))?,
                _ => {
                    return Err(format!(
                        "unknown key {key:?} in synthetic spec {text:?}: expected agents, agent, frames, seed, width or height"
                    ));
                }
            }
        }
        spec.validate()
            .map_err(|reason| format!("synthetic spec {text:?}: {reason}"))?;
        Ok(spec)
    }
}

impl fmt::Display for SyntheticSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{SPEC_PREFIX}:agents={},agent={},frames={},seed={},width={},height={}",
            self.agents, self.agent, self.frames, self.seed, self.width, self.height
        )
    }
}
