//! The mac-ego3d agent (SPEC section 3): one OS process per agent running
//! frame source -> G-ICP tracking -> keyframes -> Gaussian map optimisation, publishing keyframe
//! descriptors and Gaussian patches to the consensus and applying its corrections.
//!
//! Built so far: [`source`], the agent's frame source (prefetching, sanitising, noise, skipping
//! missing frames with a count). Tracking, mapping and the process itself follow (issue 5).

pub mod source;
