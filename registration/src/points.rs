//! Step 1 of the pipeline: the points of a depth image.
//!
//! Every `pixel_stride`-th pixel in x and y is back-projected through the pinhole model
//! (docs/method.md, One agent: Points and covariances). Pixels without usable depth are dropped: depth <= 0 (the readers
//! store every invalid marker, including 7-Scenes' 65535, as 0), non-finite values (a noisy or
//! corrupted depth image must not poison the map) and depth at or beyond the truncation distance.

use nalgebra::Point3;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;

use crate::covariance::Covariance;

/// A cloud of 3-D points in one frame (camera or world, the owner's name says which), with one
/// G-ICP covariance per point once [`super::covariance::estimate_covariances`] has run.
///
/// Positions are `f32`: depth is measured in millimetres, so `f32`'s 7 significant digits are far
/// finer than the data, and half-size points keep nearest-neighbour search in cache. Poses and the
/// normal equations stay `f64`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    /// Point positions in metres, in the cloud's frame.
    pub positions: Vec<Point3<f32>>,
    /// One per position, or empty before covariances are estimated.
    pub covariances: Vec<Covariance>,
    /// Row-major pixel index (`v * width + u`) each point came from, so callers can fetch its
    /// colour (Gaussian seeding); empty for clouds that do not come from an image.
    pub pixels: Vec<u32>,
    /// The sampling grid of a cloud back-projected from an image (enables the image-grid
    /// neighbour search of [`super::covariance`]); `None` for other clouds.
    pub grid: Option<PixelGrid>,
}

/// The image grid a cloud was sampled on: every `stride`-th pixel of an image with these
/// intrinsics, starting at pixel (0, 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelGrid {
    /// Intrinsics of the full-resolution image the grid samples.
    pub intrinsics: Intrinsics,
    /// Pixels between grid cells in x and y (at least 1).
    pub stride: usize,
}

impl PixelGrid {
    /// Grid columns and rows.
    pub fn dimensions(&self) -> (usize, usize) {
        (
            (self.intrinsics.width as usize).div_ceil(self.stride),
            (self.intrinsics.height as usize).div_ceil(self.stride),
        )
    }

    /// Grid cell (column, row) of a row-major pixel index.
    pub fn cell_of_pixel(&self, pixel: u32) -> (usize, usize) {
        let width = self.intrinsics.width as usize;
        let pixel = pixel as usize;
        ((pixel % width) / self.stride, (pixel / width) / self.stride)
    }
}

impl PointCloud {
    /// A cloud without covariances or pixels.
    pub fn from_positions(positions: Vec<Point3<f32>>) -> Self {
        Self {
            positions,
            covariances: Vec::new(),
            pixels: Vec::new(),
            grid: None,
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when the cloud has no points.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// True when every point has a covariance.
    pub fn has_covariances(&self) -> bool {
        self.covariances.len() == self.positions.len()
    }
}

/// Back-projects every `pixel_stride`-th pixel with depth in (0, `truncation_m`) into the camera
/// frame (x right, y down, z forward). The sampled pixels are (0, 0), (stride, 0), ... so the
/// result is a regular grid over the image, which [`super::covariance`] exploits.
///
/// `depth` and `intrinsics` must describe the same image size; a mismatch is a programming error
/// upstream (the readers check sizes), so it panics rather than tracking garbage.
pub fn points_from_depth(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    pixel_stride: usize,
    truncation_m: f64,
) -> PointCloud {
    assert_eq!(
        (depth.width, depth.height),
        (intrinsics.width, intrinsics.height),
        "depth image and intrinsics disagree on the image size"
    );
    let stride = pixel_stride.max(1);
    let truncation = truncation_m as f32;
    let width = depth.width as usize;
    let capacity = depth.width.div_ceil(stride as u32) as usize
        * depth.height.div_ceil(stride as u32) as usize;
    let mut cloud = PointCloud {
        positions: Vec::with_capacity(capacity),
        covariances: Vec::new(),
        pixels: Vec::with_capacity(capacity),
        grid: Some(PixelGrid {
            intrinsics: *intrinsics,
            stride,
        }),
    };
    // Per-column factors (u - cx) / fx computed once; the inner loop is then two multiplies.
    let x_factor: Vec<f32> = (0..width)
        .step_by(stride)
        .map(|u| ((u as f64 - intrinsics.cx) / intrinsics.fx) as f32)
        .collect();
    for v in (0..depth.height as usize).step_by(stride) {
        let y_factor = ((v as f64 - intrinsics.cy) / intrinsics.fy) as f32;
        let row = &depth.data[v * width..(v + 1) * width];
        for (column, u) in (0..width).step_by(stride).enumerate() {
            let z = row[u];
            // `z > 0.0` is false for NaN, so one comparison pair drops every invalid value.
            if !(z > 0.0 && z < truncation) {
                continue;
            }
            cloud
                .positions
                .push(Point3::new(x_factor[column] * z, y_factor * z, z));
            cloud.pixels.push((v * width + u) as u32);
        }
    }
    cloud
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drops_invalid_depth_and_matches_the_camera_model() {
        let k = Intrinsics::new(100.0, 110.0, 5.0, 4.0, 10, 8);
        let mut depth = DepthImage::new(10, 8);
        depth.data.fill(2.0);
        depth.data[0] = 0.0; // invalid marker
        depth.data[2] = f32::NAN;
        depth.data[4] = f32::INFINITY;
        depth.data[6] = 12.0; // beyond truncation
        depth.data[8] = -1.0;
        let cloud = points_from_depth(&depth, &k, 2, 10.0);
        // 5 x 4 sampled pixels, the first row loses u = 0, 2, 4, 6, 8: all five.
        assert_eq!(cloud.len(), 15);
        assert_eq!(cloud.pixels.len(), cloud.len());
        for (p, &pixel) in cloud.positions.iter().zip(&cloud.pixels) {
            let (u, v) = ((pixel % 10) as f64, (pixel / 10) as f64);
            let expected = k.back_project(u, v, 2.0);
            assert!((p.cast::<f64>() - expected).norm() < 1e-6);
            assert_eq!(u as usize % 2, 0);
            assert_eq!(v as usize % 2, 0);
        }
    }

    #[test]
    fn all_invalid_depth_gives_an_empty_cloud() {
        let k = Intrinsics::new(100.0, 100.0, 5.0, 4.0, 10, 8);
        let mut depth = DepthImage::new(10, 8);
        depth.data.fill(f32::NAN);
        assert!(points_from_depth(&depth, &k, 1, 10.0).is_empty());
    }
}
