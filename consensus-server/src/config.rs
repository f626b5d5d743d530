//! The consensus's parameters live in the workspace configuration
//! ([`slam_core::config::ConsensusConfig`], the `[consensus]` tables of configs/*.toml); re-exported
//! here for the modules of this crate.

pub use slam_core::config::{AlignmentConfig, ConsensusConfig, PoseGraphConfig, RefinementConfig};
