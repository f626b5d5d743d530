//! Rendering one view: a ray per pixel through the scene, linear radiance to display values,
//! camera-frame depth quantised as the 7-Scenes reader decodes it.

use image::RgbImage;
use nalgebra::{Isometry3, Vector3};
use rayon::prelude::*;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;

use crate::seven_scenes::{DEPTH_UNITS_PER_METRE, INVALID_DEPTH_RAW};

use super::scene::{DISPLAY_GAMMA, Scene};
use super::shapes::Ray;

/// Entries of the linear-to-display table: fine enough that the 8-bit output matches an exact
/// `powf` to within one level for radiance above 1e-4 (the ambient light keeps every pixel
/// well above that).
const GAMMA_TABLE_SIZE: usize = 1 << 16;

/// Linear radiance -> 8-bit display value by table lookup (three `powf` per pixel were a
/// noticeable share of the rendering time).
fn to_display_u8(linear: f64) -> u8 {
    static TABLE: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        let last = (GAMMA_TABLE_SIZE - 1) as f64;
        (0..GAMMA_TABLE_SIZE)
            .map(|i| ((i as f64 / last).powf(1.0 / DISPLAY_GAMMA) * 255.0).round() as u8)
            .collect()
    });
    table[(linear.clamp(0.0, 1.0) * (GAMMA_TABLE_SIZE - 1) as f64).round() as usize]
}

/// Largest depth the 16-bit millimetre format can hold (65535 is the 7-Scenes hole marker).
const MAX_DEPTH_RAW: u16 = INVALID_DEPTH_RAW - 1;

/// Camera z (metres) -> whole millimetres, 0 when invalid or out of range.
pub(super) fn depth_to_raw(z: f64) -> u16 {
    let millimetres = (z * DEPTH_UNITS_PER_METRE).round();
    if millimetres.is_finite() && millimetres >= 1.0 && millimetres <= MAX_DEPTH_RAW as f64 {
        millimetres as u16
    } else {
        0
    }
}

/// Ray-casts one view: 8-bit RGB and millimetre-quantised depth decoded exactly as the 7-Scenes
/// reader decodes a depth PNG.
pub(super) fn render(
    scene: &Scene,
    intrinsics: &Intrinsics,
    world_from_camera: &Isometry3<f64>,
) -> (RgbImage, DepthImage) {
    let (width, height) = (intrinsics.width as usize, intrinsics.height as usize);
    let rotation = world_from_camera.rotation.to_rotation_matrix();
    let origin = world_from_camera.translation.vector;
    let pixel_angle = 1.0 / intrinsics.fx.min(intrinsics.fy);
    let mut rgb = vec![0u8; width * height * 3];
    let mut raw_depth = vec![0u16; width * height];
    rgb.par_chunks_mut(width * 3)
        .zip(raw_depth.par_chunks_mut(width))
        .enumerate()
        .for_each(|(row, (rgb_row, depth_row))| {
            let y = (row as f64 - intrinsics.cy) / intrinsics.fy;
            for column in 0..width {
                let x = (column as f64 - intrinsics.cx) / intrinsics.fx;
                let ray = Ray {
                    origin,
                    direction: rotation * Vector3::new(x, y, 1.0),
                };
                let Some(hit) = scene.intersect(&ray) else {
                    continue;
                };
                depth_row[column] = depth_to_raw(hit.t);
                let radiance = scene.shade(&ray, &hit, pixel_angle);
                for channel in 0..3 {
                    rgb_row[3 * column + channel] = to_display_u8(radiance[channel]);
                }
            }
        });
    let rgb = RgbImage::from_raw(intrinsics.width, intrinsics.height, rgb)
        .expect("buffer sized width * height * 3");
    let depth = DepthImage::from_raw_u16(
        intrinsics.width,
        intrinsics.height,
        &raw_depth,
        DEPTH_UNITS_PER_METRE,
        Some(INVALID_DEPTH_RAW),
    );
    (rgb, depth)
}
