//! The benchmark scene's layout and the host-side workload counts.

use super::scene::{FARTHEST_SURFACE, NEAREST_SURFACE};
use super::workload::VisibleEllipse;
use super::*;
use render_core::reference;

#[test]
fn raster_workload_counts_band_steps_and_visible_pixels() {
    // One opaque-ish splat near the corner of a 32x32 image (2x2 tiles of 16), small
    // enough (visible box about 4 pixels each way) to stay inside tile (0, 0)'s first
    // band of 8 rows and its left 8 columns.
    let camera = bench_camera(32, 32);
    let mut cloud = GaussianCloud::default();
    let depth = 2.0;
    let (u, v) = (3.5, 3.5);
    let mean = [
        (u - camera.cx) / camera.fx * depth,
        (v - camera.cy) / camera.fy * depth,
        depth,
    ];
    // About one pixel of standard deviation; opacity 0.9 (logit ln 9).
    let sigma = depth / camera.fx;
    cloud.push(
        mean,
        [sigma.ln(); 3],
        [1.0, 0.0, 0.0, 0.0],
        9f32.ln(),
        [0.5; 3],
    );
    let raster = RasterConfig::default();
    let workload = raster_workload(&cloud, &camera, &raster, 16, 8, 16).unwrap();
    assert_eq!(workload.pairs, 1);
    assert_eq!(workload.band_steps, 1);
    assert_eq!(workload.evaluations, 16 * 8);
    // It stays in the tile's left half: halves evaluate that half only.
    let halves = raster_workload(&cloud, &camera, &raster, 16, 8, 8).unwrap();
    assert_eq!(halves.band_steps, 1);
    assert_eq!(halves.evaluations, 8 * 8);
    assert_eq!(halves.visible_evaluations, workload.visible_evaluations);
    assert!(workload.visible_evaluations > 0);
    assert!(workload.visible_evaluations < workload.evaluations);
    // Bands of a whole tile evaluate the tile once; the visible count does not change.
    let whole = raster_workload(&cloud, &camera, &raster, 16, 16, 16).unwrap();
    assert_eq!(whole.evaluations, 16 * 16);
    assert_eq!(whole.visible_evaluations, workload.visible_evaluations);
    assert!(raster_workload(&cloud, &camera, &raster, 16, 5, 16).is_err());
    assert!(raster_workload(&cloud, &camera, &raster, 16, 8, 5).is_err());
}

#[test]
fn visible_ellipse_x_extent_matches_a_dense_scan() {
    let mean = [10.0, 20.0];
    // A tilted ellipse (b != 0).
    let conic = [0.2, 0.12, 0.1];
    let radius_squared = 4.0;
    for (y_min, y_max) in [(14.0, 16.0), (18.0, 30.0), (25.0, 27.0), (0.0, 5.0)] {
        let mut scanned: Option<(f64, f64)> = None;
        for step in 0..=2000 {
            let y = y_min + (y_max - y_min) * f64::from(step) / 2000.0;
            for x_step in 0..=4000 {
                let x = -20.0 + 60.0 * f64::from(x_step) / 4000.0;
                let (dx, dy) = (x - mean[0], y - mean[1]);
                let q = conic[0] * dx * dx + 2.0 * conic[1] * dx * dy + conic[2] * dy * dy;
                if q <= radius_squared {
                    scanned = Some(scanned.map_or((x, x), |(l, r)| (l.min(x), r.max(x))));
                }
            }
        }
        let ellipse = VisibleEllipse {
            mean,
            conic,
            radius_squared,
        };
        let exact = ellipse.x_extent((y_min, y_max));
        match (exact, scanned) {
            (None, None) => {}
            (Some((l, r)), Some((sl, sr))) => {
                // The scan's grid is 0.015 pixel wide.
                assert!(
                    l <= sl + 1e-9 && l > sl - 0.02,
                    "left {l} vs {sl} for {y_min}..{y_max}"
                );
                assert!(
                    r >= sr - 1e-9 && r < sr + 0.02,
                    "right {r} vs {sr} for {y_min}..{y_max}"
                );
            }
            other => panic!("rows {y_min}..{y_max}: {other:?}"),
        }
    }
}

#[test]
fn raster_workload_is_bounded_and_narrower_bands_see_the_same_image() {
    let camera = bench_camera(160, 120);
    let cloud = realistic_scene(&camera, 5_000, 7);
    let raster = RasterConfig::default();
    let bands_of_8 = raster_workload(&cloud, &camera, &raster, 16, 8, 16).unwrap();
    let bands_of_4 = raster_workload(&cloud, &camera, &raster, 16, 4, 16).unwrap();
    let halves_of_8 = raster_workload(&cloud, &camera, &raster, 16, 8, 8).unwrap();
    assert!(bands_of_8.visible_evaluations > 0);
    assert!(bands_of_8.visible_evaluations <= bands_of_8.evaluations);
    assert!(bands_of_8.evaluations <= bands_of_8.pairs * 16 * 16);
    // Narrower bands skip more and never see a different image.
    assert!(bands_of_4.evaluations <= bands_of_8.evaluations);
    assert_eq!(
        bands_of_4.visible_evaluations,
        bands_of_8.visible_evaluations
    );
    // So do narrower parts.
    assert!(halves_of_8.evaluations < bands_of_8.evaluations);
    assert_eq!(
        halves_of_8.visible_evaluations,
        bands_of_8.visible_evaluations
    );
}

#[test]
fn realistic_scene_is_deterministic_and_fills_the_view() {
    const COUNT: usize = 20_000;
    let camera = bench_camera(640, 480);
    let cloud = realistic_scene(&camera, COUNT, 3);
    assert_eq!(cloud, realistic_scene(&camera, COUNT, 3));
    assert_ne!(cloud, realistic_scene(&camera, COUNT, 4));
    cloud.validate_lengths().unwrap();
    let visible = reference::project_and_sort(&cloud, &camera);
    assert!(
        // The margin around the image holds about 15% of the centres.
        visible.len() > cloud.len() * 3 / 4,
        "only {} of {} Gaussians are in view",
        visible.len(),
        cloud.len()
    );
    for splat in &visible {
        let depth = splat.camera_point[2] as f32;
        assert!((NEAREST_SURFACE..=FARTHEST_SURFACE).contains(&depth));
    }
    // Every 16x16 tile is covered by some splat (the scene fills the view).
    let (tiles_x, tiles_y) = camera.tile_counts();
    let mut covered = vec![false; (tiles_x * tiles_y) as usize];
    for splat in &visible {
        let [x0, y0, x1, y1] = splat.tile_rect;
        for ty in y0..=y1 {
            for tx in x0..=x1 {
                covered[(ty * tiles_x + tx) as usize] = true;
            }
        }
    }
    assert!(covered.iter().all(|&c| c));
}
