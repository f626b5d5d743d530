//! `--dump`: each pair side by side with its keypoints, as a PNG.

use std::path::Path;

use image::RgbImage;
use registration::alignment::features::Features;

use crate::pairs::Pair;

/// Writes `pair` side by side into `dir` (named after the pair and `variant`): A's keypoints
/// green with a correct nearest neighbour, yellow when only repeatable, grey otherwise (`status`
/// 2, 1, 0); B's keypoints blue.
pub fn write_pair_image(
    dir: &Path,
    pair: &Pair,
    variant: &str,
    fa: &Features,
    fb: &Features,
    status: &[u8],
) {
    let (w, h) = (pair.a.rgb.width(), pair.a.rgb.height());
    let mut canvas = RgbImage::new(w + pair.b.rgb.width(), h.max(pair.b.rgb.height()));
    image::imageops::replace(&mut canvas, &pair.a.rgb, 0, 0);
    image::imageops::replace(&mut canvas, &pair.b.rgb, w as i64, 0);
    let mut mark = |x: f64, y: f64, colour: [u8; 3]| {
        for d in -3i64..=3 {
            for (px, py) in [(x as i64 + d, y as i64), (x as i64, y as i64 + d)] {
                if px >= 0
                    && py >= 0
                    && (px as u32) < canvas.width()
                    && (py as u32) < canvas.height()
                {
                    canvas.put_pixel(px as u32, py as u32, image::Rgb(colour));
                }
            }
        }
    };
    for (k, p) in fa.keypoints.iter().enumerate() {
        let colour = [[160, 160, 160], [255, 255, 0], [0, 255, 0]][status[k] as usize];
        mark(p.u, p.v, colour);
    }
    for p in &fb.keypoints {
        mark(p.u + w as f64, p.v, [0, 200, 255]);
    }
    let name: String = format!("{}_{}", pair.name, variant)
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    let _ = std::fs::create_dir_all(dir);
    if let Err(error) = canvas.save(dir.join(format!("{name}.png"))) {
        eprintln!("cannot write the pair image: {error}");
    }
}
