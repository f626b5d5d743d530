//! The agent's keyframe spool: keyframes delivered to the consensus that it has not confirmed as
//! stored yet, beyond the last `[consensus.resend] agent_keeps` held in memory, kept on disk in
//! the agent's output folder (one file per keyframe), so that a consensus that lost them (killed,
//! and restarted on its store) can be given every one of them again.
//!
//! A keyframe is confirmed when it appears in a correction (the consensus places only keyframes
//! it has committed to its store) or in a resumed consensus's list of the keyframes it holds;
//! its file is deleted then. Each file is written to a temporary name and renamed, so a killed
//! agent never leaves half a keyframe under a keyframe's name; the folder is emptied when the
//! spool is opened (a restarted agent publishes its frames again) and removed at the end of a
//! run. The spool is bounded by `[consensus.resend] agent_spool_bytes`: beyond it, the oldest
//! keyframes are dropped, and reported, to make room.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use geometry::camera::Intrinsics;
use serde::{Deserialize, Serialize};

/// The spool's folder in the agent's output folder.
pub const KEYFRAME_SPOOL_DIR: &str = "keyframe_spool";

/// One keyframe's messages as the spool keeps them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpooledKeyframe {
    /// The keyframe's id (ids count up from 0 in the order the agent made keyframes).
    pub keyframe_id: u64,
    /// The frame's number in its sequence.
    pub frame_index: u64,
    /// The frame's timestamp, seconds.
    pub timestamp_s: f64,
    /// `camera_to_agent_world` as the wire carries it: `[tx, ty, tz, qx, qy, qz, qw]`.
    pub agent_from_camera: [f64; 7],
    /// The intrinsics of the images below.
    pub intrinsics: Intrinsics,
    /// The global descriptor as sent (L2-normalised; the wire's length, checked on reading).
    pub descriptor: Vec<f32>,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Row-major RGB, 3 bytes a pixel.
    pub rgb: Vec<u8>,
    /// Row-major metres, 0 = invalid.
    pub depth_m: Vec<f32>,
    /// The keyframe's Gaussians, structure of arrays as in `splats::GaussianCloud`: here their
    /// means, in the agent's tracked frame (metres).
    pub means: Vec<[f32; 3]>,
    /// Natural-log standard deviations along each Gaussian's axes (metres before the log).
    pub log_scales: Vec<[f32; 3]>,
    /// Rotations, `[w, x, y, z]`.
    pub quaternions: Vec<[f32; 4]>,
    /// Opacities before the sigmoid.
    pub opacity_logits: Vec<f32>,
    /// Linear RGB in `[0, 1]`.
    pub colours: Vec<[f32; 3]>,
}

/// See the module documentation.
pub struct KeyframeSpool {
    dir: PathBuf,
    limit_bytes: u64,
    /// Spooled keyframe id -> file size.
    files: BTreeMap<u64, u64>,
    bytes: u64,
}

impl KeyframeSpool {
    /// Opens the spool in `dir`, emptied, holding at most `limit_bytes`.
    pub fn open(dir: &Path, limit_bytes: u64) -> anyhow::Result<Self> {
        if dir.exists() {
            std::fs::remove_dir_all(dir).with_context(|| {
                format!(
                    "emptying the keyframe spool {} left by an earlier run",
                    dir.display()
                )
            })?;
        }
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating the keyframe spool {}", dir.display()))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            limit_bytes,
            files: BTreeMap::new(),
            bytes: 0,
        })
    }

    /// Writes `keyframe` to the spool. Returns the ids of older keyframes dropped to stay within
    /// the bound; an error (a full disk, a folder without write permission) names the file, and
    /// the spool is as before.
    pub fn put(&mut self, keyframe: &SpooledKeyframe) -> anyhow::Result<Vec<u64>> {
        let id = keyframe.keyframe_id;
        let bytes = bincode::serde::encode_to_vec(keyframe, bincode::config::standard())
            .with_context(|| format!("encoding keyframe {id} for the spool"))?;
        let size = bytes.len() as u64;
        let mut dropped = Vec::new();
        // Spooled again (published again, then evicted again): its file is replaced.
        let replaced = self.files.get(&id).copied().unwrap_or(0);
        while self.bytes - replaced + size > self.limit_bytes
            && let Some(oldest) = self.files.keys().copied().find(|&other| other != id)
        {
            self.remove(oldest)?;
            dropped.push(oldest);
        }
        let path = self.path(id);
        let temporary = self.dir.join(format!(".keyframe_{id}.tmp"));
        let written =
            std::fs::write(&temporary, &bytes).and_then(|()| std::fs::rename(&temporary, &path));
        if let Err(error) = written {
            // Leave nothing half-written behind (it may be what filled the disk).
            let _ = std::fs::remove_file(&temporary);
            return Err(error).with_context(|| {
                format!(
                    "spooling keyframe {id} ({size} bytes) to {}: the consensus cannot be given \
                     it again if it loses it",
                    path.display()
                )
            });
        }
        self.files.insert(id, size);
        self.bytes = self.bytes - replaced + size;
        Ok(dropped)
    }

    /// Reads spooled keyframe `id` back (it stays spooled); `None` when not spooled.
    pub fn get(&self, id: u64) -> anyhow::Result<Option<SpooledKeyframe>> {
        if !self.files.contains_key(&id) {
            return Ok(None);
        }
        let path = self.path(id);
        let bytes = std::fs::read(&path)
            .with_context(|| format!("reading spooled keyframe {}", path.display()))?;
        let (keyframe, _) = bincode::serde::decode_from_slice(&bytes, bincode::config::standard())
            .with_context(|| format!("spooled keyframe {} unreadable", path.display()))?;
        Ok(Some(keyframe))
    }

    /// Deletes the files of the `confirmed` keyframes (those not spooled are skipped).
    pub fn confirm(&mut self, confirmed: impl IntoIterator<Item = u64>) -> anyhow::Result<()> {
        for id in confirmed {
            if self.files.contains_key(&id) {
                self.remove(id)?;
            }
        }
        Ok(())
    }

    /// Spooled keyframe ids, ascending.
    pub fn ids(&self) -> impl Iterator<Item = u64> + '_ {
        self.files.keys().copied()
    }

    /// Bytes spooled now.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Removes the spool folder (the run is over: the consensus has everything or never will).
    pub fn close(self) -> anyhow::Result<()> {
        std::fs::remove_dir_all(&self.dir)
            .with_context(|| format!("removing the keyframe spool {}", self.dir.display()))
    }

    fn remove(&mut self, id: u64) -> anyhow::Result<()> {
        let path = self.path(id);
        std::fs::remove_file(&path)
            .with_context(|| format!("deleting spooled keyframe {}", path.display()))?;
        if let Some(size) = self.files.remove(&id) {
            self.bytes -= size;
        }
        Ok(())
    }

    fn path(&self, id: u64) -> PathBuf {
        self.dir.join(format!("keyframe_{id}.bin"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keyframe(keyframe_id: u64) -> SpooledKeyframe {
        SpooledKeyframe {
            keyframe_id,
            frame_index: keyframe_id * 10,
            timestamp_s: keyframe_id as f64 / 3.0,
            agent_from_camera: [0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0],
            intrinsics: Intrinsics::new(40.0, 40.0, 16.0, 12.0, 4, 2),
            descriptor: vec![0.6, 0.8],
            width: 4,
            height: 2,
            rgb: (0..24).collect(),
            depth_m: vec![1.5; 8],
            means: vec![[1.0, 2.0, 3.0]],
            log_scales: vec![[-4.0; 3]],
            quaternions: vec![[1.0, 0.0, 0.0, 0.0]],
            opacity_logits: vec![0.5],
            colours: vec![[0.25; 3]],
        }
    }

    #[test]
    fn keyframes_come_back_until_confirmed_and_the_bound_drops_the_oldest() {
        let dir = tempfile::tempdir().unwrap();
        let spool_dir = dir.path().join("spool");
        std::fs::create_dir_all(&spool_dir).unwrap();
        std::fs::write(spool_dir.join("keyframe_9.bin"), b"an earlier run's").unwrap();
        let size = bincode::serde::encode_to_vec(keyframe(1), bincode::config::standard())
            .unwrap()
            .len() as u64;
        // Room for two keyframes.
        let mut spool = KeyframeSpool::open(&spool_dir, 2 * size + size / 2).unwrap();
        assert!(!spool_dir.join("keyframe_9.bin").exists());
        assert!(spool.put(&keyframe(1)).unwrap().is_empty());
        assert!(spool.put(&keyframe(2)).unwrap().is_empty());
        assert_eq!(spool.get(2).unwrap(), Some(keyframe(2)));
        assert_eq!(
            spool.put(&keyframe(3)).unwrap(),
            [1],
            "the oldest makes room"
        );
        assert_eq!(spool.ids().collect::<Vec<_>>(), [2, 3]);
        assert!(
            spool.put(&keyframe(3)).unwrap().is_empty(),
            "a keyframe spooled again"
        );
        assert_eq!(spool.bytes(), 2 * size);
        assert_eq!(spool.get(1).unwrap(), None);
        spool.confirm([2, 7]).unwrap();
        assert_eq!(spool.ids().collect::<Vec<_>>(), [3]);
        assert!(!spool_dir.join("keyframe_2.bin").exists());
        assert_eq!(spool.bytes(), size);
        spool.close().unwrap();
        assert!(!spool_dir.exists());
    }

    #[test]
    fn a_spool_that_cannot_be_written_names_the_file_and_keeps_what_it_had() {
        let dir = tempfile::tempdir().unwrap();
        let spool_dir = dir.path().join("spool");
        let mut spool = KeyframeSpool::open(&spool_dir, u64::MAX).unwrap();
        spool.put(&keyframe(1)).unwrap();
        // The folder gone stands for a disk that takes no more (writing fails the same way).
        std::fs::remove_dir_all(&spool_dir).unwrap();
        std::fs::write(&spool_dir, b"a file where the folder was").unwrap();
        let error = format!("{:#}", spool.put(&keyframe(2)).unwrap_err());
        assert!(error.contains("keyframe_2.bin"), "{error}");
        assert!(error.contains("spooling keyframe 2"), "{error}");
        assert_eq!(spool.ids().collect::<Vec<_>>(), [1]);
    }
}
