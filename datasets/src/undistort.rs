//! Undistortion of frames from a lens with Brown-Conrady distortion
//! ([`geometry::distortion::Distortion`]): every frame is resampled once, as it is loaded, onto a
//! pinhole image, so tracking, mapping and evaluation all see pinhole frames. Each output pixel
//! takes the input at its distorted position: colour bilinearly, depth from the nearest input
//! pixel (interpolating depth across an object boundary would invent surfaces between the object
//! and the background; the depth value itself, metres along the optical axis, does not change
//! with the pixel's position). Output pixels whose distorted position falls outside the input get
//! black colour and invalid depth.
//!
//! Where the depth is, as [`DepthRegistration`] says:
//! - [`DepthRegistration::ColourGrid`]: depth aligned to the colour image pixel for pixel
//!   (RealSense `aligned_depth_to_color`, an Azure Kinect's transformed depth): it shares the
//!   colour camera's distortion, both images are resampled with the same map, and the output
//!   keeps the colour camera's K;
//! - [`DepthRegistration::Pinhole`]: depth registered by the driver to an ideal pinhole camera
//!   with its own K (the Kinect v1's OpenNI registration, which TUM RGB-D's depth images come
//!   from: the factory pinhole fx = fy = 525, not the calibrated colour lens). The depth stays as
//!   it is and the colour image is resampled into that pinhole (undistorted and re-projected with
//!   its K), so the two images agree pixel for pixel again.
//!
//! A dataset whose colour camera has no distortion and whose depth is in the colour grid is not
//! wrapped and costs nothing.

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use geometry::distortion::Distortion;
use geometry::files::DatasetError;
use image::RgbImage;
use nalgebra::Isometry3;

use crate::{Dataset, Frame};

/// The `[camera]` section of the configuration: lens parameters that replace what a dataset folder
/// says.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraConfig {
    /// The colour lens's Brown-Conrady coefficients `[k1, k2, p1, p2, k3]` (OpenCV / ROS
    /// `plumb_bob` order), replacing the folder's `camera-distortion.txt`; all zeros turns
    /// undistortion off. Absent: the folder's file, if any.
    pub distortion: Option<[f64; 5]>,
}

impl CameraConfig {
    /// Checks the coefficients; returns the offending field and why.
    pub fn validate(&self) -> Result<(), geometry::checks::FieldError> {
        match self.distortion {
            Some(c) if !c.iter().all(|v| v.is_finite()) => Err((
                "camera.distortion",
                format!("coefficients must be finite, got {c:?}"),
            )),
            _ => Ok(()),
        }
    }

    /// The configured distortion, if any.
    pub fn distortion(&self) -> Option<Distortion> {
        self.distortion.map(Distortion::from_coefficients)
    }
}

/// Where a dataset's depth pixels are (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DepthRegistration {
    /// Pixel for pixel on the colour image, distortion included.
    ColourGrid,
    /// An ideal pinhole image with these intrinsics (in the colour camera's frame).
    Pinhole(Intrinsics),
}

/// The file a dataset folder may hold to say its depth is a pinhole image with its own K
/// ([`DepthRegistration::Pinhole`]): a 3x3 K as in `camera-intrinsics.txt`.
pub const DEPTH_INTRINSICS_FILE: &str = "depth-intrinsics.txt";

/// The resampling map of one camera: for each output pixel, where to read the input.
#[derive(Debug, Clone)]
pub struct Undistortion {
    /// The colour camera as recorded (distorted).
    input: Intrinsics,
    distortion: Distortion,
    /// The pinhole camera of the output images.
    output: Intrinsics,
    /// Input position (x, y in pixels) per output pixel, row-major; NaN when outside the input.
    source: Vec<[f32; 2]>,
}

impl Undistortion {
    /// The map from the recorded colour camera (`input`, with `distortion`) to the pinhole
    /// camera `output` (the same size; `output = input` for a plain undistortion).
    pub fn new(input: Intrinsics, distortion: Distortion, output: Intrinsics) -> Self {
        let (width, height) = (output.width, output.height);
        let mut source = Vec::with_capacity(width as usize * height as usize);
        for v in 0..height {
            for u in 0..width {
                let x = (f64::from(u) - output.cx) / output.fx;
                let y = (f64::from(v) - output.cy) / output.fy;
                let (xd, yd) = distortion.distort(x, y);
                let pixel =
                    nalgebra::Point2::new(input.fx * xd + input.cx, input.fy * yd + input.cy);
                source.push(if input.contains(&pixel) {
                    [pixel.x as f32, pixel.y as f32]
                } else {
                    [f32::NAN; 2]
                });
            }
        }
        Self {
            input,
            distortion,
            output,
            source,
        }
    }

    /// The lens distortion the map undoes (the recorded colour camera's).
    pub fn distortion(&self) -> &Distortion {
        &self.distortion
    }

    /// The pinhole camera of the resampled images.
    pub fn output(&self) -> Intrinsics {
        self.output
    }

    fn check_size(&self, width: u32, height: u32, what: &str) -> Result<(), DatasetError> {
        if (width, height) == (self.input.width, self.input.height) {
            Ok(())
        } else {
            Err(DatasetError::Invalid(format!(
                "{what} is {width}x{height}, the camera {}x{}",
                self.input.width, self.input.height
            )))
        }
    }

    /// The colour image resampled into the output camera (bilinear).
    pub fn rgb(&self, input: &RgbImage) -> Result<RgbImage, DatasetError> {
        let (width, height) = input.dimensions();
        self.check_size(width, height, "the colour image")?;
        let mut output = RgbImage::new(width, height);
        let clamp_x = |x: i64| x.clamp(0, i64::from(width) - 1) as u32;
        let clamp_y = |y: i64| y.clamp(0, i64::from(height) - 1) as u32;
        for (pixel, [x, y]) in output.pixels_mut().zip(&self.source) {
            if x.is_nan() {
                continue;
            }
            let (x0, y0) = (x.floor() as i64, y.floor() as i64);
            let (fx, fy) = (x - x0 as f32, y - y0 as f32);
            let at = |xi: i64, yi: i64| input.get_pixel(clamp_x(xi), clamp_y(yi)).0;
            let (a, b, c, d) = (
                at(x0, y0),
                at(x0 + 1, y0),
                at(x0, y0 + 1),
                at(x0 + 1, y0 + 1),
            );
            for channel in 0..3 {
                let top = f32::from(a[channel]) * (1.0 - fx) + f32::from(b[channel]) * fx;
                let bottom = f32::from(c[channel]) * (1.0 - fx) + f32::from(d[channel]) * fx;
                pixel.0[channel] = (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8;
            }
        }
        Ok(output)
    }

    /// A depth image in the colour grid resampled into the output camera (nearest input pixel).
    pub fn depth(&self, input: &DepthImage) -> Result<DepthImage, DatasetError> {
        self.check_size(input.width, input.height, "the depth image")?;
        let mut output = DepthImage::new(input.width, input.height);
        for (value, [x, y]) in output.data.iter_mut().zip(&self.source) {
            if !x.is_nan() {
                *value = input.get(x.round() as u32, y.round() as u32);
            }
        }
        Ok(output)
    }
}

/// A dataset whose frames are undistorted as they are loaded (see the module documentation).
pub struct Undistorted {
    inner: Box<dyn Dataset>,
    undistortion: Undistortion,
    depth: DepthRegistration,
}

impl Undistorted {
    /// Wraps `inner` (whose intrinsics are the colour camera's) given the colour lens's
    /// `distortion` and where its depth is, or returns it as it is when there is nothing to do:
    /// no distortion and depth in the colour grid (or a pinhole with the colour camera's K).
    pub fn wrap(
        inner: Box<dyn Dataset>,
        distortion: Distortion,
        depth: DepthRegistration,
    ) -> Result<Box<dyn Dataset>, DatasetError> {
        distortion.validate().map_err(DatasetError::Invalid)?;
        let colour = inner.intrinsics();
        let output = match depth {
            DepthRegistration::ColourGrid => colour,
            DepthRegistration::Pinhole(k) => {
                k.validate().map_err(DatasetError::Invalid)?;
                if (k.width, k.height) != (colour.width, colour.height) {
                    return Err(DatasetError::Invalid(format!(
                        "depth intrinsics are for {}x{} images, the colour camera's {}x{}",
                        k.width, k.height, colour.width, colour.height
                    )));
                }
                k
            }
        };
        if distortion.is_zero() && output == colour {
            return Ok(inner);
        }
        Ok(Box::new(Self {
            undistortion: Undistortion::new(colour, distortion, output),
            inner,
            depth,
        }))
    }
}

impl Dataset for Undistorted {
    fn describe(&self) -> String {
        let [k1, k2, p1, p2, k3] = self.undistortion.distortion().coefficients();
        let depth = match self.depth {
            DepthRegistration::ColourGrid => String::new(),
            DepthRegistration::Pinhole(k) => format!(
                ", colour re-projected into the depth pinhole (fx {} fy {} cx {} cy {})",
                k.fx, k.fy, k.cx, k.cy
            ),
        };
        format!(
            "{}, undistorted (k1 {k1} k2 {k2} p1 {p1} p2 {p2} k3 {k3}){depth}",
            self.inner.describe()
        )
    }

    fn intrinsics(&self) -> Intrinsics {
        self.undistortion.output()
    }

    fn len(&self) -> usize {
        self.inner.len()
    }

    fn frame_index(&self, position: usize) -> usize {
        self.inner.frame_index(position)
    }

    fn timestamp(&self, position: usize) -> f64 {
        self.inner.timestamp(position)
    }

    fn damage(&self) -> Option<String> {
        self.inner.damage()
    }

    fn can_load(&self, position: usize) -> bool {
        self.inner.can_load(position)
    }

    fn ground_truth(&self, position: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
        self.inner.ground_truth(position)
    }

    fn load(&self, position: usize) -> Result<Frame, DatasetError> {
        let mut frame = self.inner.load(position)?;
        frame.rgb = self.undistortion.rgb(&frame.rgb)?;
        if self.depth == DepthRegistration::ColourGrid {
            frame.depth = self.undistortion.depth(&frame.depth)?;
        }
        frame.intrinsics = self.undistortion.output();
        Ok(frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Intrinsics {
        Intrinsics::new(80.0, 80.0, 39.5, 29.5, 80, 60)
    }

    #[test]
    fn a_pinhole_point_lands_where_the_distorted_image_shows_it() {
        // A distorted image with one bright pixel: the undistorted image shows it where the
        // pinhole projection of the same ray falls.
        let k = camera();
        let d = Distortion::from_coefficients([0.2, -0.1, 0.001, -0.002, 0.0]);
        // The undistorted pixel (60, 45) is seen in the distorted image at:
        let (x, y) = ((60.0 - k.cx) / k.fx, (45.0 - k.cy) / k.fy);
        let (xd, yd) = d.distort(x, y);
        let (ud, vd) = (
            (k.fx * xd + k.cx).round() as u32,
            (k.fy * yd + k.cy).round() as u32,
        );
        let mut depth = DepthImage::new(80, 60);
        depth.data[(vd * 80 + ud) as usize] = 1.5;
        let undistortion = Undistortion::new(k, d, k);
        let out = undistortion.depth(&depth).unwrap();
        assert_eq!(out.get(60, 45), 1.5);
        assert_eq!(
            out.valid_count(),
            1,
            "nearest-pixel resampling copies one pixel once here"
        );
        let mut rgb = RgbImage::new(80, 60);
        rgb.put_pixel(ud, vd, image::Rgb([255, 255, 255]));
        let out = undistortion.rgb(&rgb).unwrap();
        assert!(out.get_pixel(60, 45).0[0] > 0);
        assert_eq!(out.get_pixel(10, 10).0, [0, 0, 0]);
    }

    #[test]
    fn zero_coefficients_leave_the_images_unchanged_and_sizes_are_checked() {
        let k = camera();
        let undistortion = Undistortion::new(k, Distortion::default(), k);
        let rgb = RgbImage::from_fn(80, 60, |u, v| image::Rgb([u as u8, v as u8, 7]));
        assert_eq!(undistortion.rgb(&rgb).unwrap(), rgb);
        let wrong = RgbImage::new(40, 30);
        let error = undistortion.rgb(&wrong).unwrap_err().to_string();
        assert!(
            error.contains("40x30") && error.contains("80x60"),
            "{error}"
        );
    }

    #[test]
    fn the_wrapper_undistorts_loaded_frames_and_skips_zero_coefficients() {
        let spec = "synthetic:agents=1,frames=3,width=80,height=60";
        let plain = crate::open(spec, crate::FrameRange::ALL).unwrap();
        let colour_grid = DepthRegistration::ColourGrid;
        let same = Undistorted::wrap(
            crate::open(spec, crate::FrameRange::ALL).unwrap(),
            Distortion::default(),
            colour_grid,
        )
        .unwrap();
        assert_eq!(same.describe(), plain.describe());
        let d = Distortion::from_coefficients([0.1, 0.0, 0.0, 0.0, 0.0]);
        let wrapped = Undistorted::wrap(
            crate::open(spec, crate::FrameRange::ALL).unwrap(),
            d,
            colour_grid,
        )
        .unwrap();
        assert!(wrapped.describe().contains("undistorted"));
        let (a, b) = (plain.load(1).unwrap(), wrapped.load(1).unwrap());
        assert_eq!(a.timestamp, b.timestamp);
        assert_eq!(a.world_from_camera_gt, b.world_from_camera_gt);
        // Barrel-corrected: the centre pixel is unchanged, the corners differ.
        assert_eq!(a.depth.get(40, 30), b.depth.get(40, 30));
        assert_ne!(a.rgb.get_pixel(1, 1), b.rgb.get_pixel(1, 1));
        let bad = Distortion::from_coefficients([f64::NAN, 0.0, 0.0, 0.0, 0.0]);
        let error = Undistorted::wrap(plain, bad, colour_grid)
            .err()
            .unwrap()
            .to_string();
        assert!(error.contains("non-finite"), "{error}");
    }

    #[test]
    fn a_pinhole_depth_keeps_its_pixels_and_the_colour_moves_into_its_camera() {
        let spec = "synthetic:agents=1,frames=2,width=80,height=60";
        let plain = crate::open(spec, crate::FrameRange::ALL).unwrap();
        let colour = plain.intrinsics();
        // The colour image as a camera with a longer focal length and barrel distortion saw it
        // would need both: here the depth's pinhole is the synthetic camera itself and the
        // "recorded" colour camera differs only in its K, so the colour is resampled.
        let depth_k = Intrinsics::new(
            colour.fx * 1.05,
            colour.fy * 1.05,
            colour.cx + 2.0,
            colour.cy,
            80,
            60,
        );
        let wrapped = Undistorted::wrap(
            crate::open(spec, crate::FrameRange::ALL).unwrap(),
            Distortion::default(),
            DepthRegistration::Pinhole(depth_k),
        )
        .unwrap();
        assert_eq!(wrapped.intrinsics(), depth_k);
        let (a, b) = (plain.load(1).unwrap(), wrapped.load(1).unwrap());
        assert_eq!(a.depth, b.depth, "the depth image is left as it is");
        assert_eq!(b.intrinsics, depth_k);
        assert_ne!(a.rgb, b.rgb);
        // The same K as the colour camera and no distortion: nothing to do, not wrapped.
        let same = Undistorted::wrap(
            crate::open(spec, crate::FrameRange::ALL).unwrap(),
            Distortion::default(),
            DepthRegistration::Pinhole(colour),
        )
        .unwrap();
        assert_eq!(same.describe(), plain.describe());
        let wrong_size = Intrinsics {
            width: 40,
            ..depth_k
        };
        let error = Undistorted::wrap(
            plain,
            Distortion::default(),
            DepthRegistration::Pinhole(wrong_size),
        )
        .err()
        .unwrap()
        .to_string();
        assert!(error.contains("40x60"), "{error}");
    }
}
