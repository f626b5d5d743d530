//! The configuration file of mac-ego3d (`configs/*.toml`) as one type, [`Config`]: loading with
//! errors that name the file and the field, `--set key=value` overrides, the canonical TOML
//! written next to results, and the hash agents announce. Unknown keys are refused so a typo does
//! not silently fall back to a default.
//!
//! Each section's type, its defaults and its `validate()` live next to the code that reads it:
//! `[tracking]` and `[keyframes]` in the `registration` crate (the tracker decides keyframes),
//! `[noise]` and `[camera]` in `datasets`, `[mapping]` ([`mapping`]), `[consensus]` ([`consensus`]) and `[network]` ([`network`]) here.
//!
//! Why this crate, and why those two sections here: every binary (`mac-agent`,
//! `mac-consensus`, `mac-ego3d`) loads the whole file, so that all processes of a swarm check the
//! same file the same way, and the agent reads `[consensus]` too (`t_comm`, the descriptor
//! weights, re-sending, local corrections). The type of the whole file therefore has to sit below
//! both process crates, and with it the sections that only a process crate reads: were
//! `[consensus]` in mac-consensus, the agent would depend on the consensus; were `[mapping]` in
//! mac-agent, the consensus would depend on the agent, and the two would form a cycle.
//!
//! The crate also holds [`process`], the logging and signal start-up every binary runs right
//! before or after loading its configuration.
//!
//! Defaults are those of a 640x480 sensor (7-Scenes, TUM, the synthetic scene). Replica-like
//! 1200x680 data overrides `pixel_stride`, `truncation_m`, `prune_max_scale_m` and `t_comm`
//! (configs/replica.toml).

pub mod consensus;
pub mod mapping;
pub mod network;
pub mod process;

use std::path::{Path, PathBuf};

use datasets::noise::NoiseConfig;
pub use datasets::rosbag::Ros2Config;
use datasets::undistort::CameraConfig;
use geometry::checks::FieldError;
use registration::config::{KeyframeConfig, TrackingConfig};
use serde::{Deserialize, Serialize};

pub use consensus::{
    AlignmentConfig, ConsensusConfig, FalseClosureConfig, LocalCorrectionConfig,
    MapRegistrationConfig, MergeConfig, PoseGraphConfig, RefinementConfig, ResendConfig,
};
pub use mapping::{MappingConfig, Pace};
pub use network::NetworkConfig;

/// The whole configuration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// Frame-to-model tracking (`[tracking]`): point selection, covariances, G-ICP
    /// ([`TrackingConfig`] gives each key and its default).
    pub tracking: TrackingConfig,
    /// Keyframe selection and the seeding of new Gaussians (`[keyframes]`, [`KeyframeConfig`]).
    pub keyframes: KeyframeConfig,
    /// The agent's pace and its mapper's optimisation and pruning (`[mapping]`, [`MappingConfig`]).
    pub mapping: MappingConfig,
    /// The consensus process and what agents read of it (`[consensus]` and its tables,
    /// [`ConsensusConfig`]).
    pub consensus: ConsensusConfig,
    /// What agents may send between hosts (the agent host's bridge reads it).
    pub network: NetworkConfig,
    /// Sensor noise for robustness runs; absent = clean data.
    pub noise: Option<NoiseConfig>,
    /// Lens parameters that replace the dataset folder's (`distortion`).
    pub camera: CameraConfig,
    /// Which topics of a ROS 2 bag carry the camera and the ground truth.
    pub ros2: Ros2Config,
}

/// A configuration file that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The configuration file.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },
    /// The file is not TOML, or does not fit [`Config`]: an unknown key or section, a value of
    /// the wrong type.
    #[error("{path}: {message}")]
    Parse {
        /// The configuration file.
        path: PathBuf,
        /// The TOML parser's message, which names the line and the key.
        message: String,
    },
    /// A value is out of range ([`Config::validate`]).
    #[error("{path}: {field}: {reason}")]
    Invalid {
        /// The configuration file.
        path: PathBuf,
        /// The offending key's dotted path (`tracking.pixel_stride`).
        field: &'static str,
        /// Why the value is refused.
        reason: String,
    },
}

impl Config {
    /// Loads and validates a TOML file; errors name the file and the field.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let config: Config = toml::from_str(&text).map_err(|e| ConfigError::Parse {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        config
            .validate()
            .map_err(|(field, reason)| ConfigError::Invalid {
                path: path.to_path_buf(),
                field,
                reason,
            })?;
        Ok(config)
    }

    /// The configuration as a TOML file with every key (what [`Config::load`] reads back).
    pub fn to_toml(&self) -> Result<String, String> {
        toml::to_string(self).map_err(|e| e.to_string())
    }

    /// This configuration with `overrides` applied: each `(key, value)` sets the dotted key
    /// (`consensus.t_comm`, `noise.target`) to the TOML value `value` (a bare word that is not
    /// a TOML value is taken as a string). Tables missing from the file are created. The result
    /// is parsed and validated as a file would be: an unknown key or a bad value is refused
    /// with an error naming it.
    pub fn with_overrides(&self, overrides: &[(String, String)]) -> Result<Config, String> {
        let mut root = toml::Table::try_from(self).map_err(|e| e.to_string())?;
        for (key, value) in overrides {
            let parsed = toml::from_str::<toml::Table>(&format!("value = {value}"))
                .ok()
                .and_then(|mut t| t.remove("value"))
                .unwrap_or_else(|| toml::Value::String(value.clone()));
            let path: Vec<&str> = key.split('.').collect();
            if path.iter().any(|part| part.is_empty()) {
                return Err(format!(
                    "{key:?} is not a dotted key such as consensus.t_comm"
                ));
            }
            let (last, tables) = path.split_last().expect("split yields one part at least");
            let mut table = &mut root;
            for part in tables {
                let entry = table
                    .entry(part.to_string())
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                table = match entry {
                    toml::Value::Table(inner) => inner,
                    _ => return Err(format!("{key}: {part} is a value, not a table")),
                };
            }
            table.insert(last.to_string(), parsed);
        }
        let config: Config = toml::Value::Table(root)
            .try_into()
            .map_err(|e: toml::de::Error| e.to_string())?;
        config
            .validate()
            .map_err(|(field, reason)| format!("{field}: {reason}"))?;
        Ok(config)
    }

    /// Checks ranges, section by section (each section type checks its own fields); returns the
    /// offending field (its dotted path in the file) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        self.tracking.validate()?;
        self.keyframes.validate()?;
        self.mapping.validate()?;
        self.consensus.validate()?;
        self.network.validate()?;
        if let Some(noise) = &self.noise {
            noise.validate()?;
        }
        self.camera.validate()?;
        self.ros2.validate()
    }

    /// What this configuration tells the dataset readers ([`datasets::open_with`]).
    pub fn dataset_options(&self) -> datasets::OpenOptions {
        datasets::OpenOptions {
            distortion: self.camera.distortion(),
            ros2: self.ros2.clone(),
        }
    }

    /// Stable 64-bit hash of the configuration (FNV-1a over its canonical TOML), announced by agents
    /// so the consensus can refuse agents running with different parameters.
    pub fn hash(&self) -> u64 {
        const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
        const FNV_PRIME: u64 = 0x0000_0100_0000_01b3;
        let canonical = toml::to_string(self).expect("a Config always serialises");
        canonical
            .bytes()
            .fold(FNV_OFFSET, |h, b| (h ^ b as u64).wrapping_mul(FNV_PRIME))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use registration::config::TrackingKeyframeSeeds;

    #[test]
    fn overrides_set_dotted_keys_and_are_validated() {
        let base = Config::default();
        let set = |pairs: &[(&str, &str)]| {
            let pairs: Vec<(String, String)> = pairs
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect();
            base.with_overrides(&pairs)
        };
        let changed = set(&[
            ("consensus.t_comm", "30"),
            ("noise.target", "rgb"),
            ("consensus.refinement.max_seconds", "12.5"),
        ])
        .unwrap();
        assert_eq!(changed.consensus.t_comm, 30);
        assert!(changed.noise.is_some(), "a missing table is created");
        assert_eq!(changed.consensus.refinement.max_seconds, 12.5);
        assert_eq!(changed.tracking, base.tracking, "the rest stays");
        let unknown = set(&[("consensus.t_com", "30")]).unwrap_err();
        assert!(unknown.contains("t_com"), "{unknown}");
        let invalid = set(&[("consensus.refinement.max_seconds", "-1")]).unwrap_err();
        assert!(invalid.contains("max_seconds"), "{invalid}");
        let not_nice = set(&[("mapping.sensor_background_niceness", "20")]).unwrap_err();
        assert!(
            not_nice.contains("sensor_background_niceness"),
            "{not_nice}"
        );
        assert!(set(&[("consensus..t_comm", "3")]).is_err());
        assert!(set(&[("consensus.t_comm.x", "3")]).is_err());
    }

    fn configs_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs")
    }

    #[test]
    fn every_shipped_config_loads() {
        let mut count = 0;
        for entry in std::fs::read_dir(configs_dir()).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                Config::load(&path).unwrap_or_else(|e| panic!("{e}"));
                count += 1;
            }
        }
        assert!(
            count >= 4,
            "expected the per-dataset configs, found {count}"
        );
    }

    #[test]
    fn dataset_configs_carry_the_spec_values() {
        let seven = Config::load(&configs_dir().join("7scenes.toml")).unwrap();
        // Mapping resolution is a deliberate difference: quarter resolution gives a CPU Vulkan
        // device (lavapipe) more mapping iterations, which limit the map there.
        let mut spec = Config::default();
        spec.mapping.image_downscale = 4;
        // And tracking keyframes seed only uncovered points (a map 2.3x smaller, more mapping
        // iterations, the same PSNR; figures in configs/7scenes.toml).
        spec.keyframes.tracking_keyframe_seeds = TrackingKeyframeSeeds::Uncovered;
        assert_eq!(seven, spec, "7-Scenes uses the method's defaults");
        let replica = Config::load(&configs_dir().join("replica.toml")).unwrap();
        assert_eq!(replica.tracking.pixel_stride, 10);
        assert_eq!(replica.tracking.truncation_m, 12.0);
        assert_eq!(replica.mapping.prune_max_scale_m, 0.25);
        assert_eq!(replica.consensus.t_comm, 150);
        assert_ne!(replica.hash(), seven.hash());
    }

    #[test]
    fn tracking_keyframe_seeds_parse_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("seeds.toml");
        std::fs::write(
            &path,
            "[keyframes]\ntracking_keyframe_seeds = \"uncovered\"\n",
        )
        .unwrap();
        let config = Config::load(&path).unwrap();
        assert_eq!(
            config.keyframes.tracking_keyframe_seeds,
            TrackingKeyframeSeeds::Uncovered
        );
        assert_eq!(
            Config::default().keyframes.tracking_keyframe_seeds,
            TrackingKeyframeSeeds::All,
            "the method's rule is the default"
        );
        std::fs::write(&path, "[keyframes]\ntracking_keyframe_seeds = \"some\"\n").unwrap();
        let err = Config::load(&path).unwrap_err().to_string();
        assert!(err.contains("tracking_keyframe_seeds"), "{err}");
    }

    #[test]
    fn errors_name_the_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.toml");
        std::fs::write(&path, "[tracking]\npixel_strde = 3\n").unwrap();
        let err = Config::load(&path).unwrap_err().to_string();
        assert!(
            err.contains("bad.toml") && err.contains("pixel_strde"),
            "{err}"
        );
        // A value of the wrong type: the message quotes the line, so the field is named.
        std::fs::write(&path, "[tracking]\npixel_stride = \"five\"\n").unwrap();
        let err = Config::load(&path).unwrap_err().to_string();
        assert!(
            err.contains("bad.toml")
                && err.contains("line 2")
                && err.contains("pixel_stride")
                && err.contains("expected usize"),
            "{err}"
        );
        std::fs::write(&path, "[keyframes]\nmin_overlap_fraction = 1.5\n").unwrap();
        let err = Config::load(&path).unwrap_err().to_string();
        assert!(err.contains("keyframes.min_overlap_fraction"), "{err}");
        std::fs::write(
            &path,
            "[consensus.alignment]\ncorrespondence_distances_m = [0.02, 0.1]\n",
        )
        .unwrap();
        assert!(
            Config::load(&path)
                .unwrap_err()
                .to_string()
                .contains("coarse to fine")
        );
    }
}
