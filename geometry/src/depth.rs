//! Depth images: metres as `f32`, row-major, exactly `0.0` where the sensor has no depth. The
//! readers decode them, tracking back-projects them, the metrics and the consensus's alignment
//! compare them.

/// A depth image in metres, row-major. Invalid pixels are exactly `0.0`.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height` depths in metres, row-major (pixel (x, y) at `y * width + x`); `0.0` is
    /// invalid.
    pub data: Vec<f32>,
}

impl DepthImage {
    /// An image of the given size with every pixel invalid (`0.0`).
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0.0; width as usize * height as usize],
        }
    }

    /// Builds a depth image from raw 16-bit sensor units: `metres = raw / units_per_metre`.
    /// `invalid_raw` values (besides 0) are also mapped to invalid (7-Scenes marks holes 65535).
    pub fn from_raw_u16(
        width: u32,
        height: u32,
        raw: &[u16],
        units_per_metre: f64,
        invalid_raw: Option<u16>,
    ) -> Self {
        // Divide in f64 so that e.g. 1234 mm becomes exactly the f32 nearest 1.234 m.
        let data = raw
            .iter()
            .map(|&r| {
                if r == 0 || Some(r) == invalid_raw {
                    0.0
                } else {
                    (r as f64 / units_per_metre) as f32
                }
            })
            .collect();
        Self {
            width,
            height,
            data,
        }
    }

    /// Depth at pixel (x, y) in metres, `0.0` where invalid. The caller keeps (x, y) inside the
    /// image: only an index past the end of `data` panics, and an `x` beyond the width reads the
    /// next row.
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> f32 {
        self.data[y as usize * self.width as usize + x as usize]
    }

    /// Replaces NaN, infinite and negative values by 0 (invalid). Returns how many were replaced.
    pub fn sanitize(&mut self) -> usize {
        let mut replaced = 0;
        for d in &mut self.data {
            if !d.is_finite() || *d < 0.0 {
                *d = 0.0;
                replaced += 1;
            }
        }
        replaced
    }

    /// Number of valid (> 0) pixels.
    pub fn valid_count(&self) -> usize {
        self.data.iter().filter(|&&d| d > 0.0).count()
    }

    /// Converts to 16-bit units (`raw = round(metres * units_per_metre)`, saturating), 0 = invalid.
    pub fn to_raw_u16(&self, units_per_metre: f64) -> Vec<u16> {
        self.data
            .iter()
            .map(|&d| {
                if d > 0.0 {
                    (d as f64 * units_per_metre).round().clamp(1.0, 65534.0) as u16
                } else {
                    0
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_from_raw_marks_invalid() {
        let d = DepthImage::from_raw_u16(2, 2, &[0, 1000, 65535, 2500], 1000.0, Some(65535));
        assert_eq!(d.data, vec![0.0, 1.0, 0.0, 2.5]);
        assert_eq!(d.valid_count(), 2);
        assert_eq!(d.to_raw_u16(1000.0), vec![0, 1000, 0, 2500]);
    }

    #[test]
    fn sanitize_replaces_nan_inf_negative() {
        let mut d = DepthImage {
            width: 4,
            height: 1,
            data: vec![f32::NAN, f32::INFINITY, -1.0, 2.0],
        };
        assert_eq!(d.sanitize(), 3);
        assert_eq!(d.data, vec![0.0, 0.0, 0.0, 2.0]);
    }
}
