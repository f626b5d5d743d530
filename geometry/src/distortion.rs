//! Lens distortion: the Brown-Conrady model (OpenCV's, ROS's `plumb_bob`) with coefficients
//! `k1 k2 p1 p2 k3`, in that order as OpenCV, ROS CameraInfo and TUM's calibration list them.
//!
//! A normalised undistorted image point `(x, y) = ((u - cx) / fx, (v - cy) / fy)` appears in the
//! distorted image at
//!
//! ```text
//!   r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
//!   x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
//!   y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
//! ```
//!
//! Readers that find coefficients undistort every frame once (datasets' `undistort`) so the
//! rest of the system sees pinhole images with the same K. All zeros is the pinhole itself.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::files::{DatasetError, parse_floats};

/// Brown-Conrady coefficients (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Distortion {
    /// Radial coefficient of r^2.
    pub k1: f64,
    /// Radial coefficient of r^4.
    pub k2: f64,
    /// First tangential coefficient.
    pub p1: f64,
    /// Second tangential coefficient.
    pub p2: f64,
    /// Radial coefficient of r^6.
    pub k3: f64,
}

/// The file a dataset folder may hold beside `camera-intrinsics.txt`: one line `k1 k2 p1 p2 k3`
/// (`#` comments allowed).
pub const DISTORTION_FILE: &str = "camera-distortion.txt";

impl Distortion {
    /// From `[k1, k2, p1, p2, k3]`.
    pub fn from_coefficients(c: [f64; 5]) -> Self {
        Self {
            k1: c[0],
            k2: c[1],
            p1: c[2],
            p2: c[3],
            k3: c[4],
        }
    }

    /// The coefficients as `[k1, k2, p1, p2, k3]`, the order of
    /// [`Distortion::from_coefficients`] and [`DISTORTION_FILE`].
    pub fn coefficients(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// True when every coefficient is zero: the pinhole model, nothing to undistort.
    pub fn is_zero(&self) -> bool {
        self.coefficients().iter().all(|c| *c == 0.0)
    }

    /// Checks that the coefficients are finite.
    pub fn validate(&self) -> Result<(), String> {
        if self.coefficients().iter().all(|c| c.is_finite()) {
            Ok(())
        } else {
            Err(format!("non-finite distortion coefficients {self:?}"))
        }
    }

    /// Where the normalised undistorted point `(x, y)` lies in the distorted image (normalised).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Reads a [`DISTORTION_FILE`]: exactly five finite numbers on one line.
    pub fn read_file(path: &Path) -> Result<Self, DatasetError> {
        let text = std::fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))?;
        let mut found = None;
        for (line_no, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let values = parse_floats(line)
                .map_err(|reason| DatasetError::format(path, Some(line_no + 1), reason))?;
            if values.len() != 5 || found.is_some() {
                return Err(DatasetError::format(
                    path,
                    Some(line_no + 1),
                    format!(
                        "expected one line of 5 numbers (k1 k2 p1 p2 k3), found {}{}",
                        values.len(),
                        if found.is_some() {
                            " on a second line"
                        } else {
                            ""
                        }
                    ),
                ));
            }
            found = Some(Self::from_coefficients([
                values[0], values[1], values[2], values[3], values[4],
            ]));
        }
        found.ok_or_else(|| {
            DatasetError::format(path, None, "no coefficients (expected k1 k2 p1 p2 k3)")
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_coefficients_are_the_pinhole() {
        let d = Distortion::default();
        assert!(d.is_zero());
        assert_eq!(d.distort(0.3, -0.2), (0.3, -0.2));
    }

    #[test]
    fn radial_and_tangential_terms_follow_opencv() {
        let d = Distortion::from_coefficients([0.1, 0.01, 0.001, 0.002, 0.0001]);
        let (x, y) = (0.4, -0.3);
        let r2: f64 = 0.25;
        let radial = 1.0 + 0.1 * r2 + 0.01 * r2 * r2 + 0.0001 * r2 * r2 * r2;
        let (xd, yd) = d.distort(x, y);
        let xe = x * radial + 2.0 * 0.001 * x * y + 0.002 * (r2 + 2.0 * x * x);
        let ye = y * radial + 0.001 * (r2 + 2.0 * y * y) + 2.0 * 0.002 * x * y;
        assert!((xd - xe).abs() < 1e-15 && (yd - ye).abs() < 1e-15);
    }

    #[test]
    fn the_file_is_read_and_bad_files_name_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(DISTORTION_FILE);
        std::fs::write(
            &path,
            "# k1 k2 p1 p2 k3\n0.2624 -0.9531 -0.0054 0.0026 1.1633\n",
        )
        .unwrap();
        let d = Distortion::read_file(&path).unwrap();
        assert_eq!(d.coefficients(), [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]);
        for (text, expected) in [
            ("0.1 0.2 0.3\n", "found 3"),
            ("0.1 0.2 0.3 0.4 x\n", "\"x\""),
            ("# nothing\n", "no coefficients"),
            ("0 0 0 0 0\n0 0 0 0 0\n", "second line"),
        ] {
            std::fs::write(&path, text).unwrap();
            let error = Distortion::read_file(&path).unwrap_err().to_string();
            assert!(
                error.contains(DISTORTION_FILE) && error.contains(expected),
                "{text:?}: {error}"
            );
        }
    }
}
