//! Intensity images at one pyramid level, with their gradients, sampled bilinearly.

use geometry::camera::Intrinsics;
use image::RgbImage;
use nalgebra::Isometry3;

/// A single-channel image of intensities in [0, 1], row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct IntensityImage {
    /// Columns, in pixels.
    pub width: u32,
    /// Rows, in pixels.
    pub height: u32,
    /// `width * height` values, pixel (x, y) at `y * width + x`.
    pub data: Vec<f32>,
}

impl IntensityImage {
    /// Luma (ITU-R BT.601 weights) of an 8-bit colour image, binned by `factor` x `factor`
    /// blocks (a partial last block dropped, as [`Intrinsics::binned`] assumes).
    pub fn luma_binned(rgb: &RgbImage, factor: u32) -> Self {
        let factor = factor.max(1);
        let (width, height) = (rgb.width() / factor, rgb.height() / factor);
        let scale = 1.0 / (255.0 * (factor * factor) as f32);
        let raw = rgb.as_raw();
        let row_stride = rgb.width() as usize * 3;
        let mut data = vec![0.0f32; width as usize * height as usize];
        for y in 0..height as usize {
            for x in 0..width as usize {
                let mut sum = 0.0f32;
                for dy in 0..factor as usize {
                    let row = (y * factor as usize + dy) * row_stride;
                    for dx in 0..factor as usize {
                        let i = row + (x * factor as usize + dx) * 3;
                        sum += 0.299 * f32::from(raw[i])
                            + 0.587 * f32::from(raw[i + 1])
                            + 0.114 * f32::from(raw[i + 2]);
                    }
                }
                data[y * width as usize + x] = sum * scale;
            }
        }
        Self {
            width,
            height,
            data,
        }
    }

    /// The value at pixel (x, y). Not bounds-checked per axis: `x` must be below `width` and
    /// `y` below `height` (an index past the data panics).
    #[inline]
    pub fn at(&self, x: u32, y: u32) -> f32 {
        self.data[y as usize * self.width as usize + x as usize]
    }

    /// Central-difference gradients (x, y); zero on the border, where one neighbour is missing.
    pub fn gradients(&self) -> (Self, Self) {
        let (w, h) = (self.width as usize, self.height as usize);
        let mut gx = vec![0.0f32; w * h];
        let mut gy = vec![0.0f32; w * h];
        for y in 1..h.saturating_sub(1) {
            for x in 1..w.saturating_sub(1) {
                let i = y * w + x;
                gx[i] = 0.5 * (self.data[i + 1] - self.data[i - 1]);
                gy[i] = 0.5 * (self.data[i + w] - self.data[i - w]);
            }
        }
        let image = |data| Self {
            width: self.width,
            height: self.height,
            data,
        };
        (image(gx), image(gy))
    }

    /// Bilinear sample at pixel coordinates (pixel centres at integers); `None` outside the
    /// pixels whose four neighbours exist.
    #[inline]
    pub fn bilinear(&self, x: f64, y: f64) -> Option<f32> {
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let w = self.width as usize;
        if x0 + 1 >= w || y0 + 1 >= self.height as usize {
            return None;
        }
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let i = y0 * w + x0;
        let top = self.data[i] + fx * (self.data[i + 1] - self.data[i]);
        let bottom = self.data[i + w] + fx * (self.data[i + w + 1] - self.data[i + w]);
        Some(top + fy * (bottom - top))
    }
}

/// One frame's images at the photometric term's pyramid level.
#[derive(Debug, Clone)]
pub struct PhotometricFrame {
    /// Binning factor from the full image: 2^level.
    pub factor: u32,
    /// The camera at this level.
    pub intrinsics: Intrinsics,
    /// Luma in [0, 1], binned to this level.
    pub intensity: IntensityImage,
    /// Central-difference gradient of `intensity` along x (intensity per level pixel).
    pub gradient_x: IntensityImage,
    /// Central-difference gradient of `intensity` along y (intensity per level pixel).
    pub gradient_y: IntensityImage,
    /// The colour camera when the colour image was taken, seen from the depth camera when the
    /// depth image was (`colour_from_depth`; the identity for images taken together): the term
    /// lifts and projects points with the depth image's pose and samples intensities where the
    /// colour camera saw them.
    pub colour_from_depth: Isometry3<f64>,
}

impl PhotometricFrame {
    /// The frame at `level` (binned by 2^level); `None` when the colour image's size is not the
    /// depth camera's (colour not registered to depth: the term cannot pair them).
    pub fn new(rgb: &RgbImage, intrinsics: &Intrinsics, level: u32) -> Option<Self> {
        if rgb.width() != intrinsics.width || rgb.height() != intrinsics.height {
            return None;
        }
        let factor = 1u32 << level;
        let intensity = IntensityImage::luma_binned(rgb, factor);
        let (gradient_x, gradient_y) = intensity.gradients();
        Some(Self {
            factor,
            intrinsics: intrinsics.binned(factor),
            intensity,
            gradient_x,
            gradient_y,
            colour_from_depth: Isometry3::identity(),
        })
    }

    /// The frame with its colour image taken from `colour_from_depth` (see the field).
    pub fn with_colour_from_depth(mut self, colour_from_depth: Isometry3<f64>) -> Self {
        self.colour_from_depth = colour_from_depth;
        self
    }

    /// Intensity and gradient at a pixel of this level (bilinear), if inside.
    #[inline]
    pub fn sample(&self, x: f64, y: f64) -> Option<(f32, f32, f32)> {
        Some((
            self.intensity.bilinear(x, y)?,
            self.gradient_x.bilinear(x, y)?,
            self.gradient_y.bilinear(x, y)?,
        ))
    }
}
