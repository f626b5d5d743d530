//! Pinhole camera model shared by every reader, the synthetic renderer, tracking and metrics.

use std::path::Path;

use nalgebra::{Point2, Point3};
use serde::{Deserialize, Serialize};

use crate::files::{DatasetError, parse_floats};

/// Pinhole intrinsics of an undistorted image, in pixels.
///
/// Pixel centres sit at integer coordinates: pixel (u, v) covers [u - 0.5, u + 0.5], so the
/// principal point of a 640x480 sensor is near (319.5, 239.5).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Focal length along x, in pixels.
    pub fx: f64,
    /// Focal length along y, in pixels.
    pub fy: f64,
    /// Principal point x (the column the optical axis meets), in pixels.
    pub cx: f64,
    /// Principal point y (the row the optical axis meets), in pixels.
    pub cy: f64,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Intrinsics {
    /// Intrinsics from the focal lengths and principal point (pixels) and the image size. Nothing
    /// is checked here: see [`Intrinsics::validate`].
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32) -> Self {
        Self {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        }
    }

    /// Camera-frame point -> pixel coordinates. `None` for points at or behind the camera.
    pub fn project(&self, p_camera: &Point3<f64>) -> Option<Point2<f64>> {
        if p_camera.z <= 0.0 || !p_camera.z.is_finite() {
            return None;
        }
        Some(Point2::new(
            self.fx * p_camera.x / p_camera.z + self.cx,
            self.fy * p_camera.y / p_camera.z + self.cy,
        ))
    }

    /// Pixel (u, v) with depth z (metres along the optical axis) -> camera-frame point.
    pub fn back_project(&self, u: f64, v: f64, z: f64) -> Point3<f64> {
        Point3::new((u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z)
    }

    /// True when the pixel coordinate lies inside the image.
    pub fn contains(&self, pixel: &Point2<f64>) -> bool {
        pixel.x >= -0.5
            && pixel.y >= -0.5
            && pixel.x < self.width as f64 - 0.5
            && pixel.y < self.height as f64 - 0.5
    }

    /// The same camera for the image binned by `factor` (each pixel the mean of a `factor` x
    /// `factor` block, a partial last block dropped, as render-core's `TargetImage::downscaled`
    /// does): scaled about pixel corners, with the size rounded down as the binning does.
    pub fn binned(&self, factor: u32) -> Self {
        let factor = factor.max(1);
        Self {
            width: self.width / factor,
            height: self.height / factor,
            ..self.scaled(1.0 / f64::from(factor))
        }
    }

    /// The same camera for an image scaled by `factor` (e.g. 0.5 for half resolution).
    pub fn scaled(&self, factor: f64) -> Self {
        let width = (self.width as f64 * factor).round() as u32;
        let height = (self.height as f64 * factor).round() as u32;
        // Scale about pixel corners, not centres, so the image edges stay where they were.
        Self {
            fx: self.fx * factor,
            fy: self.fy * factor,
            cx: (self.cx + 0.5) * factor - 0.5,
            cy: (self.cy + 0.5) * factor - 0.5,
            width,
            height,
        }
    }

    /// Checks that every parameter is finite and positive where it must be.
    pub fn validate(&self) -> Result<(), String> {
        let finite = [self.fx, self.fy, self.cx, self.cy]
            .iter()
            .all(|v| v.is_finite());
        if !finite {
            return Err(format!("non-finite intrinsics {self:?}"));
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(format!(
                "focal lengths must be positive, got fx={} fy={}",
                self.fx, self.fy
            ));
        }
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size must be positive, got {}x{}",
                self.width, self.height
            ));
        }
        Ok(())
    }

    /// Reads a 3x3 K matrix (three rows of three numbers, as 7-Scenes' `camera-intrinsics.txt`)
    /// and combines it with the image size, which the file does not carry.
    pub fn read_k_file(path: &Path, width: u32, height: u32) -> Result<Self, DatasetError> {
        let text = std::fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))?;
        let mut rows: Vec<[f64; 3]> = Vec::with_capacity(3);
        for (line_no, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let values = parse_floats(line)
                .map_err(|reason| DatasetError::format(path, Some(line_no + 1), reason))?;
            if values.len() != 3 {
                return Err(DatasetError::format(
                    path,
                    Some(line_no + 1),
                    format!("expected 3 numbers per row of K, found {}", values.len()),
                ));
            }
            rows.push([values[0], values[1], values[2]]);
        }
        if rows.len() != 3 {
            return Err(DatasetError::format(
                path,
                None,
                format!("expected a 3x3 matrix K, found {} rows", rows.len()),
            ));
        }
        let k = Self::new(
            rows[0][0], rows[1][1], rows[0][2], rows[1][2], width, height,
        );
        k.validate()
            .map_err(|reason| DatasetError::format(path, None, reason))?;
        Ok(k)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binned_intrinsics_drop_the_partial_last_block_and_keep_the_image_edges() {
        let k = Intrinsics::new(525.0, 520.0, 319.5, 239.5, 641, 481);
        let half = k.binned(2);
        assert_eq!((half.width, half.height), (320, 240));
        assert_eq!((half.fx, half.fy), (262.5, 260.0));
        // Pixel corners stay put: the left edge -0.5 maps to -0.5, the centre to the centre.
        assert_eq!((half.cx, half.cy), (159.5, 119.5));
        assert_eq!(k.binned(0), k.binned(1));
        assert_eq!((k.binned(1).width, k.binned(1).fx), (641, 525.0));
    }

    #[test]
    fn project_inverts_back_project() {
        let k = Intrinsics::new(585.0, 585.0, 320.0, 240.0, 640, 480);
        let p = k.back_project(100.25, 400.5, 2.5);
        let px = k.project(&p).unwrap();
        assert!((px.x - 100.25).abs() < 1e-9 && (px.y - 400.5).abs() < 1e-9);
        assert!(k.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
        assert!(k.project(&Point3::new(0.0, 0.0, f64::NAN)).is_none());
    }

    #[test]
    fn k_file_errors_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("camera-intrinsics.txt");
        std::fs::write(&path, "585 0 320\n0 585 x\n0 0 1\n").unwrap();
        let err = Intrinsics::read_k_file(&path, 640, 480)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("camera-intrinsics.txt") && err.contains("line 2"),
            "{err}"
        );
        std::fs::write(&path, "585 0 320\n0 585 240\n0 0 1\n").unwrap();
        let k = Intrinsics::read_k_file(&path, 640, 480).unwrap();
        assert_eq!((k.fx, k.fy, k.cx, k.cy), (585.0, 585.0, 320.0, 240.0));
    }
}
