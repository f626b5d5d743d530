//! What the fake agents of these tests send: a small camera, a uniform RGB-D image and one
//! Gaussian in front of it.

use protocol::messages::{GaussianRecord, Intrinsics, RgbdPixel};

pub const WIDTH: u32 = 32;
pub const HEIGHT: u32 = 24;

pub fn intrinsics() -> Intrinsics {
    Intrinsics {
        fx: 30.0,
        fy: 30.0,
        cx: 16.0,
        cy: 12.0,
        width: WIDTH,
        height: HEIGHT,
    }
}

/// An RGB-D image of WIDTH x HEIGHT pixels, every one 1.5 m away.
pub fn pixels() -> Vec<RgbdPixel> {
    (0..WIDTH * HEIGHT)
        .map(|i| RgbdPixel::new([(i % 251) as u8, 90, 30], 1.5))
        .collect()
}

pub fn gaussian() -> GaussianRecord {
    GaussianRecord {
        mean: [0.0, 0.0, 1.5],
        log_scale: [-4.0, -4.0, -7.0],
        rotation_wxyz: [1.0, 0.0, 0.0, 0.0],
        opacity_logit: 0.0,
        colour: [0.5, 0.4, 0.3],
    }
}
