//! The AlexNet feature network, on candle, and the two things mac-ego3d uses it for: the LPIPS
//! image metric ([`lpips`], AlexNet v0.1 linear heads) and the place-recognition descriptor of
//! keyframes ([`descriptor`], GeM-pooled AlexNet features, with a classical fallback when no
//! weights are at hand). [`weights`] finds the one weights file both read.
//!
//! Named after the network rather than after either use: LPIPS and the descriptor share its
//! convolution stack and its weights file, and this is the only crate that depends on candle, so
//! the tracker and the dataset readers build without it.

pub mod descriptor;
pub mod lpips;
pub mod weights;
