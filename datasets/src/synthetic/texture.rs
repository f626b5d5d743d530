//! Procedural textures: value noise, checkers, stripes, tiles and planks, each with colour
//! variation, filtered by the pixel footprint so they do not alias.

use std::f64::consts::TAU;

/// Octaves of the value-noise sum (see [`fbm_bands`]); each doubles the frequency and scales the
/// amplitude by [`NOISE_GAIN`].
const COARSE_OCTAVES: usize = 4;
const FINE_OCTAVES: usize = 4;
const NOISE_GAIN: f64 = 0.55;
/// Texture detail whose period spans fewer than `FADE_END` pixels on screen is replaced by its
/// mean (fully so below [`FADE_START`] pixels): a cheap pre-filter that keeps far or grazing
/// surfaces from aliasing into flicker, which would break photometric consistency between views.
const FADE_START_PX: f64 = 2.0;
const FADE_END_PX: f64 = 5.0;
/// How far value-noise contrast is stretched around 0.5 (raw sums cluster near the middle).
const NOISE_CONTRAST: f64 = 2.6;
/// Warm/cool colour shift driven by the base noise, for colour variation inside a pattern.
const COLOUR_SHIFT: f64 = 0.22;
/// Floor planks: half width of the joints (m), their relative brightness, the wood grain's line
/// spacing (m) and how many grain periods the noise bends it by.
const PLANK_GAP_HALF_WIDTH: f64 = 0.004;
const PLANK_GAP_BRIGHTNESS: f64 = 0.45;
const WOOD_GRAIN_PERIOD: f64 = 0.02;
const WOOD_GRAIN_WARP: f64 = 6.0;
/// Smallest cosine between the viewing ray and a surface used to stretch the pixel footprint
/// (grazing angles would otherwise blow it up without bound).
pub(super) const MIN_FOOTPRINT_COSINE: f64 = 0.15;

/// splitmix64 finaliser: a fast, well-mixed integer hash.
pub(super) fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Uniform value in [0, 1) for an integer lattice point.
fn lattice_value(ix: i64, iy: i64, seed: u64) -> f64 {
    // Distinct odd multipliers and a rotation keep (ix, iy) and (iy, ix) apart; one finaliser
    // round then mixes every input bit into the output.
    let key = (ix as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (iy as u64)
            .wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            .rotate_left(29);
    let h = mix64(seed ^ key);
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Quintic fade: C2-continuous interpolation, so the noise has no visible grid creases.
fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// `x.floor()` without the libm call (x86-64's baseline has no rounding instruction); exact for
/// |x| < 2^53, far beyond any texture coordinate here.
fn fast_floor(x: f64) -> f64 {
    let truncated = x as i64 as f64;
    if truncated > x {
        truncated - 1.0
    } else {
        truncated
    }
}

fn value_noise(x: f64, y: f64, seed: u64) -> f64 {
    let (fx, fy) = (fast_floor(x), fast_floor(y));
    let (ix, iy) = (fx as i64, fy as i64);
    let (sx, sy) = (fade(x - fx), fade(y - fy));
    let v00 = lattice_value(ix, iy, seed);
    let v10 = lattice_value(ix + 1, iy, seed);
    let v01 = lattice_value(ix, iy + 1, seed);
    let v11 = lattice_value(ix + 1, iy + 1, seed);
    let bottom = v00 + (v10 - v00) * sx;
    let top = v01 + (v11 - v01) * sx;
    bottom + (top - bottom) * sy
}

/// 0 when a feature of `period` covers fewer than FADE_START_PX pixels of `footprint`, 1 when it
/// covers more than FADE_END_PX, smooth in between.
fn visibility(period: f64, footprint: f64) -> f64 {
    let pixels = period / footprint.max(f64::MIN_POSITIVE);
    ((pixels - FADE_START_PX) / (FADE_END_PX - FADE_START_PX)).clamp(0.0, 1.0)
}

/// Multi-octave value noise, band-limited to the pixel footprint (same units as x, y), split
/// into two bands that are each normalised to [0, 1] around 0.5: the first [`COARSE_OCTAVES`]
/// (large blotches that modulate patterns and colour) and the next [`FINE_OCTAVES`] (grain that
/// modulates brightness). One pass for both bands costs less than two separate sums.
fn fbm_bands(x: f64, y: f64, seed: u64, footprint: f64) -> (f64, f64) {
    let mut bands = [(0.0, 0.0); 2];
    let (mut amplitude, mut frequency) = (1.0, 1.0);
    for octave in 0..COARSE_OCTAVES + FINE_OCTAVES {
        if octave == COARSE_OCTAVES {
            amplitude = 1.0;
        }
        let band = &mut bands[usize::from(octave >= COARSE_OCTAVES)];
        let weight = visibility(1.0 / frequency, footprint);
        let value = if weight > 0.0 {
            // Offsets decorrelate octaves that share lattice points at the origin.
            let noise = value_noise(
                x * frequency + 31.7 * octave as f64,
                y * frequency - 17.3 * octave as f64,
                seed.wrapping_add(octave as u64),
            );
            0.5 + weight * (noise - 0.5)
        } else {
            0.5
        };
        band.0 += amplitude * value;
        band.1 += amplitude;
        amplitude *= NOISE_GAIN;
        frequency *= 2.0;
    }
    (bands[0].0 / bands[0].1, bands[1].0 / bands[1].1)
}

/// Anti-aliased square wave of `period` in [-1, 1]: +1 on the first half-period, -1 on the
/// second, ramping linearly over one footprint at each edge and fading to its mean 0 when the
/// period is too small to resolve.
fn square_wave(x: f64, period: f64, footprint: f64) -> f64 {
    let phase = x / period - fast_floor(x / period);
    let sign = if phase < 0.5 { 1.0 } else { -1.0 };
    let edge_distance = period * phase.min((phase - 0.5).abs()).min(1.0 - phase);
    sign * (edge_distance / footprint.max(f64::MIN_POSITIVE)).min(1.0)
        * visibility(period, footprint)
}

/// Anti-aliased grid line mask: 1 within `half_width` of a multiple of `period`, 0 elsewhere,
/// fading to the line's area fraction when the period is too small to resolve.
fn grid_line(x: f64, period: f64, half_width: f64, footprint: f64) -> f64 {
    let phase = x / period - fast_floor(x / period);
    let distance = period * phase.min(1.0 - phase);
    let sharp = ((half_width + footprint - distance) / (2.0 * footprint).max(f64::MIN_POSITIVE))
        .clamp(0.0, 1.0);
    let mean = (2.0 * half_width / period).min(1.0);
    mean + (sharp - mean) * visibility(period, footprint)
}

pub(super) type Rgb = [f64; 3];

fn mix_rgb(a: &Rgb, b: &Rgb, t: f64) -> Rgb {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

pub(super) fn hsv_to_rgb(hue: f64, saturation: f64, value: f64) -> Rgb {
    let h = (hue - hue.floor()) * 6.0;
    let chroma = value * saturation;
    let x = chroma * (1.0 - ((h % 2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (chroma, x, 0.0),
        1 => (x, chroma, 0.0),
        2 => (0.0, chroma, x),
        3 => (0.0, x, chroma),
        4 => (x, 0.0, chroma),
        _ => (chroma, 0.0, x),
    };
    let m = value - chroma;
    [r + m, g + m, b + m]
}

#[derive(Debug, Clone, Copy)]
pub(super) enum Pattern {
    /// Contrast-stretched multi-octave noise (plaster, stone).
    Marble,
    /// Two-colour checkerboard of `period` (one light and one dark square per period).
    Checker { period: f64 },
    /// Stripes of `period` along direction `angle` (wallpaper).
    Stripes {
        period: f64,
        cos_angle: f64,
        sin_angle: f64,
    },
    /// Square tiles with grout lines; each tile gets its own tint.
    Tiles { period: f64, grout_half_width: f64 },
    /// Floor planks with wood grain, staggered joints and a tint per plank.
    Planks { width: f64, length: f64 },
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Material {
    pub(super) pattern: Pattern,
    pub(super) primary: Rgb,
    pub(super) secondary: Rgb,
    /// Seed of this material's noise, so no two surfaces share a texture.
    pub(super) noise_seed: u64,
    /// Frequency of the lowest noise octave, cycles per metre.
    pub(super) noise_frequency: f64,
    /// Relative brightness variation from fine noise.
    pub(super) detail_strength: f64,
    /// Relative brightness variation between tiles or planks.
    pub(super) cell_tint: f64,
}

impl Material {
    /// Reflectance (linear, 0..1) at surface coordinates `uv` (metres), filtered for a pixel
    /// footprint of `footprint` metres.
    pub(super) fn albedo(&self, uv: [f64; 2], footprint: f64) -> Rgb {
        let [u, v] = uv;
        let f = self.noise_frequency;
        let (base, detail) = fbm_bands(u * f, v * f, self.noise_seed, footprint * f);
        let stretched = ((base - 0.5) * NOISE_CONTRAST + 0.5).clamp(0.0, 1.0);
        let (mix, cell_brightness) = match self.pattern {
            Pattern::Marble => (stretched, 1.0),
            Pattern::Checker { period } => {
                let checker = square_wave(u, period, footprint) * square_wave(v, period, footprint);
                (0.5 + 0.4 * checker + 0.2 * (stretched - 0.5), 1.0)
            }
            Pattern::Stripes {
                period,
                cos_angle,
                sin_angle,
            } => {
                let along = u * cos_angle + v * sin_angle;
                let stripe = square_wave(along, period, footprint);
                // A thinner stripe at a third of the period makes the pattern non-repetitive within
                // one period, which helps matching along the stripes.
                let fine = square_wave(along + 0.37 * period, period / 3.0, footprint);
                (
                    0.5 + 0.3 * stripe + 0.1 * fine + 0.25 * (stretched - 0.5),
                    1.0,
                )
            }
            Pattern::Tiles {
                period,
                grout_half_width,
            } => {
                let grout = grid_line(u, period, grout_half_width, footprint).max(grid_line(
                    v,
                    period,
                    grout_half_width,
                    footprint,
                ));
                let cell = lattice_value(
                    (u / period).floor() as i64,
                    (v / period).floor() as i64,
                    self.noise_seed ^ 0x7A11,
                );
                // The per-tile tint jumps at tile edges, which the grout hides; fade it with the
                // grout's own visibility so far tiles do not shimmer.
                let tint =
                    1.0 + self.cell_tint * (cell - 0.5) * 2.0 * visibility(period, footprint);
                (
                    grout + (1.0 - grout) * 0.35 * stretched,
                    tint * (1.0 - grout) + grout,
                )
            }
            Pattern::Planks { width, length } => {
                let row = (v / width).floor();
                let stagger = lattice_value(row as i64, 0, self.noise_seed ^ 0x9A4C) * length;
                let plank = ((u + stagger) / length).floor();
                let gap = grid_line(v, width, PLANK_GAP_HALF_WIDTH, footprint).max(grid_line(
                    u + stagger,
                    length,
                    PLANK_GAP_HALF_WIDTH,
                    footprint,
                ));
                let cell = lattice_value(row as i64, plank as i64, self.noise_seed ^ 0x51D3);
                let tint = 1.0 + self.cell_tint * (cell - 0.5) * 2.0 * visibility(width, footprint);
                // Grain: lines along the plank, warped by the noise; fades out below pixel size.
                let grain = 0.5
                    + 0.5
                        * (TAU * (v / WOOD_GRAIN_PERIOD + WOOD_GRAIN_WARP * base)).sin()
                        * visibility(WOOD_GRAIN_PERIOD, footprint);
                // Mostly grain, some blotches, kept away from both ends of the colour ramp.
                let wood = 0.25 + 0.3 * grain + 0.2 * stretched;
                // Gaps are dark: the mix goes to the primary colour at reduced brightness.
                (
                    wood * (1.0 - gap),
                    tint * (1.0 - gap) + PLANK_GAP_BRIGHTNESS * gap,
                )
            }
        };
        let mut colour = mix_rgb(&self.primary, &self.secondary, mix.clamp(0.0, 1.0));
        let brightness = cell_brightness * (1.0 + self.detail_strength * (detail - 0.5) * 2.0);
        let shift = COLOUR_SHIFT * (base - 0.5);
        colour[0] *= brightness * (1.0 + shift);
        colour[1] *= brightness;
        colour[2] *= brightness * (1.0 - shift);
        colour
    }
}
