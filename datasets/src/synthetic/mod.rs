//! The embedded synthetic multi-agent RGB-D dataset: needs no download and is the default
//! everywhere (docs/method.md, Datasets).
//!
//! A procedural room (6 x 5 x 3 m: textured floor, ceiling and walls, a table with objects on
//! it, a cabinet, a shelf, a bench, a pillar, a bin, a ball, stacked boxes, posters) is ray-cast
//! analytically (rays against planes, boxes, spheres and cylinders; no mesh files) to RGB and
//! exact depth. Textures are procedural (multi-octave value noise, checkers, stripes, tiles,
//! planks, each with colour variation) and filtered by the pixel footprint so they do not alias;
//! shading is Lambertian with fixed point lights, so a surface point has the same colour from
//! every viewpoint (what photometric map optimisation assumes).
//!
//! `agents` cameras walk smooth loops around the table, alternating direction, looking towards
//! the room's interior with slow gaze wander, head-bob and roll; consecutive agents cover
//! overlapping stretches of the same loop, so their views overlap. Ground truth is exact. The
//! world frame is the room frame (x east, y north, z up, floor at z = 0, origin in the middle of
//! the floor), so no agent starts at the identity: the SLAM system must find the inter-agent
//! transforms.
//!
//! Depth is the camera-frame z in metres (not the ray length), quantised to whole millimetres
//! exactly as the 7-Scenes depth PNG reader decodes them (`raw_mm as f32 * (1/1000 as f32)`), so
//! a frame written with [`write_seven_scenes`] and read back has bit-identical colour, depth,
//! timestamp and pose translation; the pose rotation differs by ~1e-13 rad because the pose
//! reader re-orthonormalises the stored matrix. Depth beyond 65.534 m, or rays that leave the
//! scene, is 0 (invalid); inside the closed room every pixel has valid depth.
//!
//! Everything is a pure function of [`SyntheticSpec`]: textures, object placement and trajectory
//! jitter come from ChaCha RNGs seeded from `seed`, and pixels are computed independently, so the
//! output is bit-identical across runs and rayon thread counts.
//!
//! Files by concern: [`spec`] (what to produce), [`shapes`] and [`texture`] (the geometry and
//! surfaces the room is made of), [`layout`] (what stands where), [`scene`] (ray casting and
//! shading), [`render`] (one view to RGB and depth), [`walk`] (the agents' camera paths),
//! [`dataset`] (frames on demand) and [`writer`] (the 7-Scenes folders `mac-ego3d synth` writes).

mod dataset;
mod layout;
mod render;
mod scene;
mod shapes;
mod spec;
mod texture;
mod walk;
mod writer;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub use dataset::SyntheticDataset;
pub use shapes::{ROOM_MAX, ROOM_MIN};
pub use spec::{
    DEFAULT_AGENTS, DEFAULT_FRAMES, DEFAULT_HEIGHT, DEFAULT_SEED, DEFAULT_WIDTH, FRAMES_PER_SECOND,
    MAX_AGENTS, MAX_FRAMES, MAX_IMAGE_SIDE, MIN_IMAGE_SIDE, SPEC_PREFIX, SyntheticSpec,
};
pub use writer::{SCENE_FILE, agent_folder, remove_written, write_seven_scenes};

use texture::mix64;

/// Salts that give each part of the generator its own RNG stream for a seed, so changing one
/// part (e.g. the number of agents) never moves another (e.g. the furniture).
const SCENE_STREAM: u64 = 0x5CE4_E000_0000_0001;
const TRAJECTORY_STREAM: u64 = 0x7A4E_C700_0000_0002;

fn stream_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(mix64(seed ^ mix64(stream)))
}

fn symmetric(rng: &mut ChaCha8Rng, amplitude: f64) -> f64 {
    rng.random_range(-amplitude..=amplitude)
}

#[cfg(test)]
mod tests;
