//! The photometric term of tracking (docs/method.md, One agent: Tracking, "Photometric term"):
//! direct image alignment in the manner of dense RGB-D odometry (Steinbruecker, Sturm, Cremers
//! 2011; Kerl, Sturm, Cremers 2013), minimised together with G-ICP inside its
//! Levenberg-Marquardt loop ([`crate::gicp::register_joint_unless_outscored`]).
//!
//! The reference is the previous placed frame: its textured pixels (intensity gradient above
//! `min_gradient`, at pyramid level `level`) with valid, edge-free depth are lifted to world
//! points `q` at its pose. For the current pose `T` (`world_from_camera`) each is projected into
//! the current image, `x = pi(T^-1 q)`, and its residual is
//!
//! ```text
//!     r = I_cur(x) - (a I_ref + b)
//! ```
//!
//! with `(a, b)` an affine brightness change (auto exposure, white balance drift) fitted in
//! closed form at every linearisation. The cost `weight * sum huber(r)` is linearised with the
//! current image's gradient at `x`: `dr/d(omega, v) = grad I(x) dpi/dc [[c]x, -I]` for `c =
//! T^-1 q` and G-ICP's right perturbation.
//!
//! `intensity.rs` holds the intensity images (binning, gradients, bilinear samples); `term.rs` the
//! reference's selection and the term itself.

mod intensity;
mod term;
#[cfg(test)]
mod tests;

pub use intensity::{IntensityImage, PhotometricFrame};
pub use term::{ColourMotion, PhotometricReference, PhotometricTerm};
