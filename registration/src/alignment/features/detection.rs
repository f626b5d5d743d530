//! Keypoint detection: the image pyramid, FAST corners thinned to local maxima, and their
//! spread over the image.

use image::GrayImage;
use image::imageops::FilterType;
use imageproc::corners::corners_fast9;

use super::patch::PATCH_SIZE;
use super::{Candidate, KEYPOINT_BORDER};

/// Image pyramid of `grey`: level `l` is `scale^l` times smaller; levels stop before the image
/// gets smaller than a patch.
pub(super) fn pyramid(grey: &GrayImage, scale: f64, levels: usize) -> Vec<GrayImage> {
    let scale = scale.max(1.0);
    (0..levels.max(1))
        .take_while(|&level| {
            let factor = scale.powi(level as i32);
            level == 0 || grey.width().min(grey.height()) as f64 / factor > PATCH_SIZE as f64
        })
        .map(|level| {
            if level == 0 {
                return grey.clone();
            }
            let factor = scale.powi(level as i32);
            let width = (grey.width() as f64 / factor).round().max(1.0) as u32;
            let height = (grey.height() as f64 / factor).round().max(1.0) as u32;
            image::imageops::resize(grey, width, height, FilterType::Triangle)
        })
        .collect()
}

/// FAST-9 corners at `threshold` inside the keypoint border that are local maxima of the FAST
/// score in their 3x3 neighbourhood (ties go to the first in raster order): a corner makes a
/// blob of adjacent detections, of which one is kept. `(x, y, score)`, raster order.
pub(super) fn local_maxima(image: &GrayImage, threshold: u8) -> Vec<(u32, u32, u8)> {
    let (width, height) = image.dimensions();
    let mut scores = vec![0u8; (width * height) as usize];
    let mut corners = Vec::new();
    for corner in corners_fast9(image, threshold) {
        let inside = |c: u32, limit: u32| c >= KEYPOINT_BORDER && c + KEYPOINT_BORDER < limit;
        if !inside(corner.x, width) || !inside(corner.y, height) {
            continue;
        }
        // The score is at least the threshold; store it + 1 so that 0 means "no corner".
        let score = (corner.score as u8).saturating_add(1);
        scores[(corner.y * width + corner.x) as usize] = score;
        corners.push((corner.x, corner.y, score));
    }
    corners.retain(|&(x, y, score)| {
        let mut keep = true;
        for ny in y - 1..=y + 1 {
            for nx in x - 1..=x + 1 {
                let other = scores[(ny * width + nx) as usize];
                let earlier = (ny, nx) < (y, x);
                keep &= other < score || (other == score && !earlier);
            }
        }
        keep
    });
    corners
        .into_iter()
        .map(|(x, y, score)| (x, y, score - 1))
        .collect()
}

/// Up to `wanted` candidates spread over a grid of `cell_px`-pixel cells: the strongest of every
/// cell first (strongest cells first), then the second of every cell, and so on. With `cell_px`
/// 0, the strongest overall. Deterministic: ties keep raster order.
pub(super) fn spread(
    mut candidates: Vec<Candidate>,
    wanted: usize,
    cell_px: u32,
    image: &GrayImage,
) -> Vec<Candidate> {
    // Stable: equal scores keep raster order.
    candidates.sort_by_key(|c| std::cmp::Reverse(c.score));
    if cell_px == 0 || candidates.len() <= wanted {
        candidates.truncate(wanted);
        return candidates;
    }
    let columns = image.width().div_ceil(cell_px) as usize;
    let cell = |c: &Candidate| (c.y / cell_px) as usize * columns + (c.x / cell_px) as usize;
    // Rank of each candidate within its cell, in the strongest-first order.
    let mut seen = vec![0usize; columns * image.height().div_ceil(cell_px) as usize];
    let mut ranked: Vec<(usize, Candidate)> = candidates
        .into_iter()
        .map(|c| {
            let slot = &mut seen[cell(&c)];
            *slot += 1;
            (*slot - 1, c)
        })
        .collect();
    // Stable again: within a rank, strongest first.
    ranked.sort_by_key(|&(rank, _)| rank);
    ranked.truncate(wanted);
    ranked.into_iter().map(|(_, c)| c).collect()
}
