//! Colour, where the maps have it: what separates a box-shaped room from itself turned by 90 or
//! 180 degrees when geometry cannot.
//!
//! **Which colour.** Map colours are RGB in `[0, 1]`, the space the agents' Gaussians carry
//! (`8-bit value / 255`, as they are seeded from and fitted to the keyframes' pixels); keyframe
//! depth points take their pixel in that space too. Surfaces of the synthetic room are Lambertian
//! (the same colour from every viewpoint), but real cameras have auto-exposure: the same wall is
//! brighter in one agent's frames than in the other's. Everything here is therefore invariant to
//! scaling a colour: it uses the *chromaticity* `(r, g, b) / (r + g + b)` only, taken as two
//! opponent coordinates,
//!
//! ```text
//!     o1 = (r - g) / s,    o2 = (2 b - r - g) / (sqrt 3 s),    s = r + g + b,
//! ```
//!
//! an orthogonal projection of the chromaticity triangle (a grey is the origin; the *chroma*
//! `|o|` is a saturation, its angle a hue). Colours darker than [`MIN_INTENSITY`] carry no
//! reliable chromaticity (sensor noise dominates the ratios) and are left out of every colour
//! measure.
//!
//! **Signature** ([`signatures`]): the colour part of a point's descriptor, from its neighbours
//! within the feature radius (the FPFH neighbourhood): a histogram of their hues, each
//! neighbour's unit weight split between its hue (linearly between the two nearest of
//! [`HUE_BINS`] bins, so a hue near a bin edge does not jump) and one achromatic bin, in
//! proportion to how saturated it is; [`SIGNATURE_LEN`] values summing to 1, invariant to rigid
//! motion and to a global scale of the colours. A neighbourhood histogram rather than the
//! point's own colour: one voxel's colour is a sample of a texture, the mix of colours around
//! it (a red wall meeting a grey floor) is what identifies the place.
//!
//! A histogram of the neighbours' intensities relative to their mean (the texture's contrast)
//! was measured as a third part and dropped: on 7-Scenes it cost a fifth of the true
//! correspondences (relative intensities change with the camera's exposure curve and blur),
//! and on the synthetic wide-baseline maps it added nothing the hues did not already give.
//!
//! **Agreement** ([`chroma_distance`]): two points agree in colour when their chromaticities are
//! close, the verification's measure of an overlap (see `verification`).

use rayon::prelude::*;

use super::fpfh::Neighbourhoods;

/// An RGB colour in `[0, 1]`.
pub type Rgb = [f32; 3];

/// Hue bins of a [`Signature`].
pub const HUE_BINS: usize = 6;
/// Length of a colour signature: hue bins, then the achromatic bin.
pub const SIGNATURE_LEN: usize = HUE_BINS + 1;
/// One point's colour signature (see the module documentation).
pub type Signature = [f32; SIGNATURE_LEN];

/// Colours with a mean channel below this carry no reliable chromaticity.
pub const MIN_INTENSITY: f32 = 0.03;
/// Chroma `|o|` at which a colour counts fully towards its hue; greyer colours split their
/// weight between the hue and the achromatic bin in proportion. Synthetic walls and furniture
/// have chromas of 0.05-0.5; the white balance of real cameras leaves greys within ~0.03.
const FULL_CHROMA: f32 = 0.12;

/// Points per rayon task.
const POINTS_PER_TASK: usize = 256;

/// Mean of the three channels.
#[inline]
pub fn intensity(c: &Rgb) -> f32 {
    (c[0] + c[1] + c[2]) / 3.0
}

/// The opponent chromaticity `(o1, o2)` (module documentation); `None` for a colour darker than
/// [`MIN_INTENSITY`] or not finite.
#[inline]
pub fn chromaticity(c: &Rgb) -> Option<[f32; 2]> {
    let s = c[0] + c[1] + c[2];
    // Not finite (NaN or infinite), or too dark.
    if !s.is_finite() || intensity(c) < MIN_INTENSITY {
        return None;
    }
    Some([
        (c[0] - c[1]) / s,
        (2.0 * c[2] - c[0] - c[1]) / (3f32.sqrt() * s),
    ])
}

/// Distance between the chromaticities of two colours; `None` when either has none.
#[inline]
pub fn chroma_distance(a: &Rgb, b: &Rgb) -> Option<f32> {
    let (a, b) = (chromaticity(a)?, chromaticity(b)?);
    Some(((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt())
}

/// Adds `weight` to a histogram of `bins` bins over a circle at the continuous position `at`
/// (in bins), split linearly between the two nearest bin centres.
#[inline]
fn add_circular(histogram: &mut [f32], at: f32, weight: f32) {
    let bins = histogram.len();
    let shifted = at - 0.5;
    let lower = shifted.floor();
    let fraction = shifted - lower;
    let lower = (lower as i64).rem_euclid(bins as i64) as usize;
    histogram[lower] += weight * (1.0 - fraction);
    histogram[(lower + 1) % bins] += weight * fraction;
}

/// What a colour contributes to signatures, computed once per point: where its hue falls (in
/// bins) and how much of its unit weight goes to the hue (the rest is achromatic).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColourTerms {
    hue_bin: f32,
    saturated: f32,
}

impl ColourTerms {
    /// `None` for colours without a chromaticity.
    pub fn of(c: &Rgb) -> Option<Self> {
        let o = chromaticity(c)?;
        let chroma = (o[0] * o[0] + o[1] * o[1]).sqrt();
        let hue = o[1].atan2(o[0]).rem_euclid(std::f32::consts::TAU);
        Some(Self {
            hue_bin: hue * (HUE_BINS as f32 / std::f32::consts::TAU),
            saturated: (chroma / FULL_CHROMA).min(1.0),
        })
    }
}

/// The colour signature of a set of colours' terms (`None` entries are left out; `None` when
/// no entry is left).
pub fn signature_of<'a>(terms: impl Iterator<Item = &'a Option<ColourTerms>>) -> Option<Signature> {
    let mut signature = [0.0f32; SIGNATURE_LEN];
    let mut count = 0usize;
    for t in terms.flatten() {
        count += 1;
        if t.saturated > 0.0 {
            add_circular(&mut signature[..HUE_BINS], t.hue_bin, t.saturated);
        }
        signature[HUE_BINS] += 1.0 - t.saturated;
    }
    if count == 0 {
        return None;
    }
    let n = count as f32;
    signature.iter_mut().for_each(|v| *v /= n);
    Some(signature)
}

/// The colour signature of each point of `points` (indices into `colours`) from its neighbours
/// (itself included) in `neighbourhoods`; `None` for a point with no coloured neighbour.
pub fn signatures(
    colours: &[Rgb],
    neighbourhoods: &Neighbourhoods,
    points: &[u32],
) -> Vec<Option<Signature>> {
    let terms: Vec<Option<ColourTerms>> = colours
        .par_iter()
        .with_min_len(POINTS_PER_TASK)
        .map(ColourTerms::of)
        .collect();
    points
        .par_iter()
        .with_min_len(POINTS_PER_TASK)
        .map(|&i| {
            signature_of(
                neighbourhoods
                    .of(i as usize)
                    .iter()
                    .map(|&j| &terms[j as usize]),
            )
        })
        .collect()
}

/// Width of a bin of the log-chromaticity histograms [`relative_white_balance`] compares.
const BALANCE_BIN: f32 = 0.02;
/// Bins per axis: log-ratios within +-1 (a factor of 2.7 between channels).
const BALANCE_BINS: usize = 100;

/// A map's colours as a histogram over `(ln(r / g), ln(b / g))`, blurred over the 3 x 3 bins
/// around each (so that a gain between two bins still matches); colours without a
/// chromaticity or outside the range are left out.
fn log_chroma_histogram(colours: &[Rgb]) -> Vec<f32> {
    let mut counts = vec![0.0f32; BALANCE_BINS * BALANCE_BINS];
    let bin = |v: f32| {
        let b = (v / BALANCE_BIN + (BALANCE_BINS / 2) as f32).floor();
        (b >= 0.0 && b < BALANCE_BINS as f32).then_some(b as usize)
    };
    for c in colours.iter().filter(|c| chromaticity(c).is_some()) {
        if c.iter().all(|&v| v > 0.0)
            && let (Some(x), Some(y)) = (bin((c[0] / c[1]).ln()), bin((c[2] / c[1]).ln()))
        {
            counts[y * BALANCE_BINS + x] += 1.0;
        }
    }
    let mut blurred = vec![0.0f32; counts.len()];
    for y in 0..BALANCE_BINS {
        for x in 0..BALANCE_BINS {
            let mut sum = 0.0;
            for (dx, dy) in (0..9).map(|k| (k % 3, k / 3)) {
                let (xx, yy) = ((x + dx).wrapping_sub(1), (y + dy).wrapping_sub(1));
                if xx < BALANCE_BINS && yy < BALANCE_BINS {
                    sum += counts[yy * BALANCE_BINS + xx];
                }
            }
            blurred[y * BALANCE_BINS + x] = sum;
        }
    }
    blurred
}

/// The per-channel gains (green's 1) that make the `source` map's colours look as through the
/// `target` map's camera: the shift of the source's log-chromaticity histogram that overlays it
/// best on the target's, within `max_log_gain` per channel. `[1, 1, 1]` when either map has no
/// chromatic colours.
///
/// Two cameras with other white balances see every surface with other per-channel gains, which
/// shift every point's `(ln(r / g), ln(b / g))` by the same amount. The surfaces both maps hold
/// (and indoors, the many neutral walls and floors) make the two histograms peak at the same
/// places up to that shift; where one map holds surfaces the other does not, they add to one
/// histogram only, which moves the best overlay little. So the shift is found by correlating
/// the histograms over every shift within range, at [`BALANCE_BIN`] steps (2 % of a gain).
pub fn relative_white_balance(source: &[Rgb], target: &[Rgb], max_log_gain: f64) -> [f32; 3] {
    let (from, to) = rayon::join(
        || log_chroma_histogram(source),
        || log_chroma_histogram(target),
    );
    if from.iter().all(|&v| v == 0.0) || to.iter().all(|&v| v == 0.0) {
        return [1.0; 3];
    }
    let reach = (max_log_gain as f32 / BALANCE_BIN).floor() as isize;
    let n = BALANCE_BINS as isize;
    let shifts: Vec<(isize, isize)> = (-reach..=reach)
        .flat_map(|dy| (-reach..=reach).map(move |dx| (dx, dy)))
        .collect();
    let score = |&(dx, dy): &(isize, isize)| -> f64 {
        let mut sum = 0.0f64;
        for y in 0.max(-dy)..n.min(n - dy) {
            for x in 0.max(-dx)..n.min(n - dx) {
                let a = from[(y * n + x) as usize];
                if a > 0.0 {
                    sum += f64::from(a * to[((y + dy) * n + x + dx) as usize]);
                }
            }
        }
        sum
    };
    let scores: Vec<f64> = shifts.par_iter().map(score).collect();
    // The best score; among equals, the smallest shift (then the first).
    let best = (0..shifts.len())
        .max_by(|&a, &b| {
            scores[a].total_cmp(&scores[b]).then_with(|| {
                let size = |(dx, dy): (isize, isize)| dx * dx + dy * dy;
                size(shifts[b]).cmp(&size(shifts[a]))
            })
        })
        .expect("at least the zero shift");
    let (dx, dy) = shifts[best];
    [
        (dx as f32 * BALANCE_BIN).exp(),
        1.0,
        (dy as f32 * BALANCE_BIN).exp(),
    ]
}

/// `colours` with each channel multiplied by its gain.
pub fn balanced(colours: &[Rgb], gains: [f32; 3]) -> Vec<Rgb> {
    colours
        .iter()
        .map(|c| [c[0] * gains[0], c[1] * gains[1], c[2] * gains[2]])
        .collect()
}

/// Euclidean distance between two signatures.
pub fn signature_distance(a: &Signature, b: &Signature) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f32>()
        .sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chromaticity_ignores_exposure_and_dark_colours_have_none() {
        let wall = [0.6f32, 0.4, 0.2];
        let darker = wall.map(|v| v * 0.5);
        let (a, b) = (chromaticity(&wall).unwrap(), chromaticity(&darker).unwrap());
        assert!((a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6);
        assert_eq!(chromaticity(&[0.5, 0.5, 0.5]), Some([0.0, 0.0]));
        assert_eq!(chromaticity(&[0.01, 0.02, 0.0]), None);
        assert_eq!(chromaticity(&[f32::NAN, 0.5, 0.5]), None);
        assert!(chroma_distance(&wall, &darker).unwrap() < 1e-6);
        assert!(chroma_distance(&wall, &[0.2, 0.4, 0.6]).unwrap() > 0.3);
        assert_eq!(chroma_distance(&wall, &[0.0; 3]), None);
    }

    #[test]
    fn signatures_are_histograms_invariant_to_exposure() {
        // A neighbourhood of two colours (a checker-like texture).
        let colours: Vec<Rgb> = (0..20)
            .map(|k| {
                if k % 2 == 0 {
                    [0.7, 0.3, 0.2]
                } else {
                    [0.3, 0.35, 0.6]
                }
            })
            .collect();
        let terms = |colours: &[Rgb]| -> Vec<Option<ColourTerms>> {
            colours.iter().map(ColourTerms::of).collect()
        };
        let s = signature_of(terms(&colours).iter()).unwrap();
        assert!((s.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        // Both colours are saturated: nothing achromatic.
        assert!(s[HUE_BINS] < 1e-6, "{s:?}");
        let exposed: Vec<Rgb> = colours.iter().map(|c| c.map(|v| v * 0.6)).collect();
        let t = signature_of(terms(&exposed).iter()).unwrap();
        assert!(
            s.iter().zip(&t).all(|(a, b)| (a - b).abs() < 1e-5),
            "{s:?} {t:?}"
        );
        // A grey neighbourhood is all achromatic, a greyish one mostly.
        let grey = signature_of(terms(&[[0.5f32; 3]; 5]).iter()).unwrap();
        assert!((grey[HUE_BINS] - 1.0).abs() < 1e-6);
        let greyish = signature_of(terms(&[[0.52f32, 0.5, 0.48]; 5]).iter()).unwrap();
        assert!(
            greyish[HUE_BINS] > 0.7 && greyish[HUE_BINS] < 1.0,
            "{greyish:?}"
        );
        // Another hue lands in other bins.
        let green = signature_of(terms(&[[0.2f32, 0.7, 0.2]; 5]).iter()).unwrap();
        let overlap: f32 = s[..HUE_BINS]
            .iter()
            .zip(&green[..HUE_BINS])
            .map(|(a, b)| a.min(*b))
            .sum();
        assert!(overlap < 0.2, "{s:?} {green:?}");
        assert!(signature_distance(&s, &green) > 0.5);
        assert_eq!(signature_of(terms(&[[0.0f32; 3]; 3]).iter()), None);
    }

    #[test]
    fn the_relative_white_balance_of_two_maps_is_found() {
        // Mostly neutral surfaces of several brightnesses and a few coloured ones; the other
        // map holds part of them (and one colour of its own), through another white balance.
        let scene: Vec<Rgb> = (0..400)
            .map(|k| match k % 10 {
                0 => [0.7, 0.3, 0.2],
                1 => [0.2, 0.5, 0.3],
                2 => [0.55, 0.5, 0.42],
                _ => [0.5, 0.5, 0.5].map(|v| v * (0.6 + 0.002 * k as f32)),
            })
            .collect();
        let mut other: Vec<Rgb> = scene[..250]
            .iter()
            .map(|c| [c[0] * 1.12, c[1], c[2] * 0.9])
            .collect();
        other.extend([[0.3, 0.3, 0.7]; 40]);
        let gains = relative_white_balance(&scene, &other, 0.26);
        assert!(
            (gains[0] - 1.12).abs() < 0.03 && gains[1] == 1.0 && (gains[2] - 0.9).abs() < 0.03,
            "{gains:?}"
        );
        let same = relative_white_balance(&scene, &scene, 0.26);
        assert_eq!(same, [1.0; 3]);
        assert_eq!(
            relative_white_balance(&scene, &[[0.0; 3]; 4], 0.26),
            [1.0; 3]
        );
    }
}
