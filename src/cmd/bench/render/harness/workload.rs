//! The (pixel, splat) work of a tile rasterizer on one view, counted on the host.

use render_core::context::GpuError;
use render_core::reference::{ProjectedGaussian, project_and_sort, splat_at_pixel};
use render_core::{Camera, RasterConfig};
use splats::GaussianCloud;

/// The (pixel, splat) work of a tile rasterizer on one view, counted on the host (no device):
/// what the rasterizer kernels spend their arithmetic on, against what contributes to the
/// image. Splats are the reference projection's, binned into every tile their visible ellipse
/// (where opacity x exp(power) can reach `min_splat_alpha`) reaches, as the renderer's tile
/// masks do, and walked front to back per band of `band_rows` tile rows, as the subgroup
/// rasterizers walk them per subgroup, each band tested in parts of `band_columns` columns
/// (8, the rasterizers' two halves of a tile; 16, the whole tile): a part the
/// splat's visible ellipse misses is skipped, any other costs one evaluation per pixel of the
/// part, until every pixel of the band has terminated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RasterWorkload {
    pub tile_size: u32,
    /// Tile rows one skip test and one early-termination test cover (the subgroup's rows in
    /// the subgroup rasterizer: one row per lane).
    pub band_rows: u32,
    /// Columns of one skip test (a divisor of `tile_size`).
    pub band_columns: u32,
    /// Tile/splat pairs. Within 1 % of the renderer's on the benchmark scene, which masks
    /// tiles by the ellipse only for rectangles of up to 32 tiles and adds safety margins.
    pub pairs: u64,
    /// (band part, splat) steps that were not skipped.
    pub band_steps: u64,
    /// Pixel evaluations: `band_steps` x pixels per band part.
    pub evaluations: u64,
    /// Evaluations where the pixel was still compositing and the splat's alpha reached
    /// `min_splat_alpha`: the part of the arithmetic that changes the image.
    pub visible_evaluations: u64,
}

/// Counts [`RasterWorkload`] for `cloud` seen by `camera` with `tile_size` x `tile_size` tiles
/// walked in bands of `band_rows` rows, skip-tested in parts of `band_columns` columns
/// (divisors of `tile_size`). The early-termination test
/// runs after every splat here; the kernels test after every batch of one splat per lane, so
/// they run a few more steps than counted.
pub fn raster_workload(
    cloud: &GaussianCloud,
    camera: &Camera,
    raster: &RasterConfig,
    tile_size: u32,
    band_rows: u32,
    band_columns: u32,
) -> Result<RasterWorkload, GpuError> {
    for (what, length) in [("rows", band_rows), ("columns", band_columns)] {
        if tile_size == 0 || length == 0 || !tile_size.is_multiple_of(length) {
            return Err(GpuError::InvalidInput(format!(
                "band of {length} {what} does not divide a tile of {tile_size} pixels"
            )));
        }
    }
    let (width, height) = (camera.width, camera.height);
    let min_transmittance = f64::from(raster.min_transmittance);
    let splats = project_and_sort(cloud, camera);
    let ellipses: Vec<VisibleEllipse> = splats
        .iter()
        .map(|splat| VisibleEllipse::of(splat, raster))
        .collect();
    let tiles_x = width.div_ceil(tile_size);
    let tiles_y = height.div_ceil(tile_size);
    // Inclusive pixel-centre range of tile k along one axis.
    let tile_span = |k: u32| (f64::from(k * tile_size), f64::from((k + 1) * tile_size - 1));
    let mut workload = RasterWorkload {
        tile_size,
        band_rows,
        band_columns,
        pairs: 0,
        band_steps: 0,
        evaluations: 0,
        visible_evaluations: 0,
    };

    // Binning: each splat into the tiles its visible ellipse reaches, in depth order.
    let mut lists: Vec<Vec<usize>> = vec![Vec::new(); (tiles_x * tiles_y) as usize];
    for (index, ellipse) in ellipses.iter().enumerate() {
        let Some((x_min, x_max)) = ellipse
            .x_extent((0.0, f64::from(height - 1)))
            .filter(|&(left, right)| right >= 0.0 && left <= f64::from(width - 1))
        else {
            continue;
        };
        let [_, half_y] = ellipse.half_extents();
        let y_min = (ellipse.mean[1] - half_y).max(0.0);
        let first_x = (x_min.max(0.0) / f64::from(tile_size)) as u32;
        let last_x = ((x_max / f64::from(tile_size)) as u32).min(tiles_x - 1);
        let first_y = (y_min / f64::from(tile_size)) as u32;
        let last_y = (((ellipse.mean[1] + half_y) / f64::from(tile_size)) as u32).min(tiles_y - 1);
        for tile_y in first_y..=last_y {
            let Some((reach_min, reach_max)) = ellipse.x_extent(tile_span(tile_y)) else {
                continue;
            };
            for tile_x in first_x..=last_x {
                let (columns_min, columns_max) = tile_span(tile_x);
                if reach_max >= columns_min && reach_min <= columns_max {
                    lists[(tile_y * tiles_x + tile_x) as usize].push(index);
                    workload.pairs += 1;
                }
            }
        }
    }

    // Compositing, band by band, with the per-pixel arithmetic of the CPU reference.
    let band_pixels = band_rows * tile_size;
    let mut transmittance = vec![1.0f64; band_pixels as usize];
    let mut done = vec![false; band_pixels as usize];
    for tile_y in 0..tiles_y {
        for tile_x in 0..tiles_x {
            let list = &lists[(tile_y * tiles_x + tile_x) as usize];
            for first_row in
                (tile_y * tile_size..(tile_y + 1) * tile_size).step_by(band_rows as usize)
            {
                let pixel_at = |p: u32| {
                    (
                        tile_x * tile_size + p % tile_size,
                        first_row + p / tile_size,
                    )
                };
                let mut compositing = 0;
                for p in 0..band_pixels {
                    let (column, row) = pixel_at(p);
                    transmittance[p as usize] = 1.0;
                    done[p as usize] = column >= width || row >= height;
                    compositing += usize::from(!done[p as usize]);
                }
                let band_rows_span = (f64::from(first_row), f64::from(first_row + band_rows - 1));
                for &index in list {
                    if compositing == 0 {
                        break;
                    }
                    let reached_parts = (0..tile_size / band_columns)
                        .filter(|part| {
                            let first = f64::from(tile_x * tile_size + part * band_columns);
                            let columns = (first, first + f64::from(band_columns - 1));
                            !ellipses[index].misses_box(band_rows_span, columns)
                        })
                        .count() as u64;
                    if reached_parts == 0 {
                        continue;
                    }
                    workload.band_steps += reached_parts;
                    workload.evaluations += reached_parts * u64::from(band_rows * band_columns);
                    for p in 0..band_pixels {
                        if done[p as usize] {
                            continue;
                        }
                        let (column, row) = pixel_at(p);
                        let pixel = [f64::from(column), f64::from(row)];
                        let Some(hit) = splat_at_pixel(&splats[index], pixel, raster) else {
                            continue;
                        };
                        workload.visible_evaluations += 1;
                        let next = transmittance[p as usize] * (1.0 - hit.alpha);
                        if next < min_transmittance {
                            done[p as usize] = true;
                            compositing -= 1;
                        } else {
                            transmittance[p as usize] = next;
                        }
                    }
                }
            }
        }
    }
    Ok(workload)
}

/// Where a projected splat can reach `min_splat_alpha`: the ellipse conic(offset) <=
/// radius_squared, radius_squared = 2 ln(opacity / min_alpha), around its mean (the host
/// counterpart of `visible_radius_squared` in common.wgsl, without its safety margins). The conic
/// `[a, b, c]` is the quadratic form a dx^2 + 2 b dx dy + c dy^2.
pub(super) struct VisibleEllipse {
    pub(super) mean: [f64; 2],
    pub(super) conic: [f64; 3],
    pub(super) radius_squared: f64,
}

impl VisibleEllipse {
    pub(super) fn of(splat: &ProjectedGaussian, raster: &RasterConfig) -> Self {
        let min_alpha = f64::from(raster.min_splat_alpha);
        Self {
            mean: splat.mean2d,
            conic: splat.conic,
            radius_squared: (2.0 * (splat.opacity / min_alpha).ln()).max(0.0),
        }
    }

    /// Half extents (x, y) of its bounding box: sqrt(r^2 * covariance) per axis. NaN for a
    /// degenerate conic.
    pub(super) fn half_extents(&self) -> [f64; 2] {
        let [a, b, c] = self.conic;
        let determinant = a * c - b * b;
        [
            (self.radius_squared * c / determinant).sqrt(),
            (self.radius_squared * a / determinant).sqrt(),
        ]
    }

    /// Whether it misses the box of pixel centres `columns` x `rows` (inclusive ranges), as
    /// the subgroup rasterizers' skip test (`ellipse_misses_box` in common.wgsl) decides.
    pub(super) fn misses_box(&self, rows: (f64, f64), (x_min, x_max): (f64, f64)) -> bool {
        self.x_extent(rows)
            .is_none_or(|(left, right)| right < x_min || left > x_max)
    }

    /// Its x range over the rows `y_min ..= y_max`, or `None` when it misses them (or is
    /// degenerate).
    pub(super) fn x_extent(&self, (y_min, y_max): (f64, f64)) -> Option<(f64, f64)> {
        let [a, b, c] = self.conic;
        let [half_x, half_y] = self.half_extents();
        let mean = self.mean;
        let low = y_min.max(mean[1] - half_y);
        let high = y_max.min(mean[1] + half_y);
        // A degenerate conic gives NaN bounds: that misses too.
        if low.is_nan() || high.is_nan() || low > high {
            return None;
        }
        // The chord at row y: centre mean.x - b dy / a, half-width sqrt(a r^2 - det dy^2) / a.
        let determinant = a * c - b * b;
        let chord = |y: f64| {
            let dy = y - mean[1];
            let centre = mean[0] - b * dy / a;
            let half = (a * self.radius_squared - determinant * dy * dy)
                .max(0.0)
                .sqrt()
                / a;
            (centre - half, centre + half)
        };
        let (low_left, low_right) = chord(low);
        let (high_left, high_right) = chord(high);
        let (mut left, mut right) = (low_left.min(high_left), low_right.max(high_right));
        // The extreme points (dx = +-half_x, where the gradient is horizontal: b dx + c dy = 0)
        // bound the range when their rows lie inside.
        let rightmost_dy = -b * half_x / c;
        if (low..=high).contains(&(mean[1] + rightmost_dy)) {
            right = mean[0] + half_x;
        }
        if (low..=high).contains(&(mean[1] - rightmost_dy)) {
            left = mean[0] - half_x;
        }
        Some((left, right))
    }
}
