//! Depth noise models. The paper's camera draws i.i.d. Gaussian noise per pixel (in `render`);
//! [`DepthNoiseModel::D435`] behaves like a stereo RGB-D camera instead: a low-frequency error
//! that is the same in neighbouring pixels and moves from frame to frame, edges smeared by the
//! stereo matcher's window, and i.i.d. noise whose RMS grows with range squared.

use std::fmt;
use std::str::FromStr;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::standard_normal;

/// ChaCha stream of the stereo model's draws (0 is the paper model's, 1 and 2 the artefacts').
const STEREO_STREAM: u64 = 3;

/// Intel's D4xx RMS error model (white paper "Tuning depth cameras for best performance"):
/// `rms_mm = z_mm² · subpixel / (f_px · baseline_mm)` with the D435 example's constants.
pub const D435_SUBPIXEL: f64 = 0.08;
/// Focal length in pixels of a D435 at 848 px and 90° horizontal field of view.
pub const D435_FOCAL_PX: f64 = 424.0;
pub const D435_BASELINE_M: f64 = 0.050;

/// Correlated depth error of the fruit-mapping literature's stereo simulation: additive 2D
/// sinusoids `(amplitude m, rad per row, rad per column)`.
const ADDITIVE_WAVES: [(f64, f64, f64); 3] =
    [(0.002, 5.3, 5.2), (0.0015, 0.07, 0.1), (0.001, 0.1, 0.5)];
/// Multiplicative sinusoids `(share of depth, rad per row, rad per column)`.
const MULTIPLICATIVE_WAVES: [(f64, f64, f64); 2] = [(0.002, 0.2, 3.3), (0.007, 0.22, 0.1)];

/// How the simulated camera's depth noise behaves. Settings and flags spell it `paper` or
/// `d435`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DepthNoiseModel {
    /// I.i.d. Gaussian noise, 1.5 mm at 1 m growing with depth squared (the paper's camera).
    #[default]
    Paper,
    /// A stereo camera like Intel's D435: correlated sinusoidal error, a 3×3 smear across edges
    /// (flying pixels), then i.i.d. noise of the D4xx RMS model (3.8 mm at 1 m).
    D435,
}

/// A depth noise model name that is not `paper` or `d435`.
#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
#[error("unknown depth noise model {0:?}; valid: paper, d435")]
pub struct ParseDepthNoiseError(pub String);

impl FromStr for DepthNoiseModel {
    type Err = ParseDepthNoiseError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "paper" | "iid" => Ok(DepthNoiseModel::Paper),
            "d435" | "d4xx" | "stereo" => Ok(DepthNoiseModel::D435),
            _ => Err(ParseDepthNoiseError(s.to_string())),
        }
    }
}

impl fmt::Display for DepthNoiseModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            DepthNoiseModel::Paper => "paper",
            DepthNoiseModel::D435 => "d435",
        })
    }
}

/// RMS depth error of a D435 at `depth_m`, in metres.
pub fn d435_rms_m(depth_m: f64) -> f64 {
    depth_m * depth_m * D435_SUBPIXEL / (D435_FOCAL_PX * D435_BASELINE_M)
}

/// Applies the stereo model to noise-free depths (row-major, NaN = invalid), seeded by
/// `noise_seed`; depths that leave `range_m` become invalid.
pub(crate) fn apply_stereo_noise(
    depth_m: &mut [f32],
    width: usize,
    height: usize,
    noise_seed: u64,
    range_m: (f64, f64),
) {
    let mut rng = ChaCha8Rng::seed_from_u64(noise_seed);
    rng.set_stream(STEREO_STREAM);
    let phases: [f64; 5] = std::array::from_fn(|_| rng.gen::<f64>() * std::f64::consts::TAU);
    let mut waved: Vec<f64> = vec![f64::NAN; depth_m.len()];
    for (pixel, (out, &d)) in waved.iter_mut().zip(depth_m.iter()).enumerate() {
        if d.is_finite() {
            let (row, col) = ((pixel / width) as f64, (pixel % width) as f64);
            *out = f64::from(d) + correlated_error_m(f64::from(d), row, col, &phases);
        }
    }
    let smeared = smear_3x3(&waved, width, height);
    let mut spare = None;
    for (out, d) in depth_m.iter_mut().zip(smeared) {
        if !d.is_finite() {
            continue;
        }
        let noisy = d + d435_rms_m(d) * standard_normal(&mut rng, &mut spare);
        *out = if (range_m.0..=range_m.1).contains(&noisy) {
            noisy as f32
        } else {
            f32::NAN
        };
    }
}

/// The sinusoidal error at a pixel: additive waves plus waves proportional to the depth.
fn correlated_error_m(depth_m: f64, row: f64, col: f64, phases: &[f64; 5]) -> f64 {
    let wave = |(amplitude, per_row, per_col): (f64, f64, f64), phase: f64| {
        amplitude * (per_row * row + per_col * col + phase).sin()
    };
    let additive: f64 = ADDITIVE_WAVES
        .iter()
        .zip(phases)
        .map(|(&w, &p)| wave(w, p))
        .sum();
    let multiplicative: f64 = MULTIPLICATIVE_WAVES
        .iter()
        .zip(&phases[3..])
        .map(|(&w, &p)| wave(w, p))
        .sum();
    additive + depth_m * multiplicative
}

/// 3×3 Gaussian (1-2-1) smear over the valid neighbours of each valid pixel: at a depth edge
/// the foreground and background mix, as a stereo matcher's window does.
fn smear_3x3(depth_m: &[f64], width: usize, height: usize) -> Vec<f64> {
    const WEIGHTS: [f64; 3] = [1.0, 2.0, 1.0];
    let mut out = vec![f64::NAN; depth_m.len()];
    for v in 0..height {
        for u in 0..width {
            let here = v * width + u;
            if !depth_m[here].is_finite() {
                continue;
            }
            let (mut sum, mut weight) = (0.0, 0.0);
            for (dv, wv) in WEIGHTS.iter().enumerate() {
                for (du, wu) in WEIGHTS.iter().enumerate() {
                    let (qu, qv) = ((u + du).wrapping_sub(1), (v + dv).wrapping_sub(1));
                    if qu >= width || qv >= height {
                        continue;
                    }
                    let d = depth_m[qv * width + qu];
                    if d.is_finite() {
                        sum += wv * wu * d;
                        weight += wv * wu;
                    }
                }
            }
            out[here] = sum / weight;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn d435_rms_matches_intels_figures() {
        // 0.34 mm at 0.3 m, 3.8 mm at 1 m, 15 mm at 2 m (REAL-WORLD.md).
        assert!((d435_rms_m(0.3) - 0.00034).abs() < 0.00001);
        assert!((d435_rms_m(1.0) - 0.0038).abs() < 0.0001);
        assert!((d435_rms_m(2.0) - 0.0151).abs() < 0.0002);
    }

    #[test]
    fn model_names_parse_and_print() {
        for model in [DepthNoiseModel::Paper, DepthNoiseModel::D435] {
            assert_eq!(model.to_string().parse::<DepthNoiseModel>(), Ok(model));
        }
        assert!("kinect".parse::<DepthNoiseModel>().is_err());
    }

    #[test]
    fn stereo_error_is_correlated_between_neighbours_and_smears_edges() {
        let (w, h) = (64, 48);
        // A plane at 1 m with a step to 2 m on the right half.
        let clean: Vec<f32> = (0..w * h)
            .map(|p| if p % w < w / 2 { 1.0 } else { 2.0 })
            .collect();
        let mut noisy = clean.clone();
        apply_stereo_noise(&mut noisy, w, h, 7, (0.1, 5.0));
        let error: Vec<f64> = noisy
            .iter()
            .zip(&clean)
            .map(|(n, c)| f64::from(*n) - f64::from(*c))
            .collect();
        // Vertical neighbours on the left plane share most of their error (low frequency).
        let (mut same, mut all) = (0.0, 0.0);
        for v in 1..h {
            for u in 2..w / 2 - 2 {
                same += error[v * w + u] * error[(v - 1) * w + u];
                all += error[v * w + u].powi(2);
            }
        }
        assert!(same / all > 0.3, "correlation {}", same / all);
        // The edge column mixes 1 m and 2 m: a flying pixel between them.
        let edge = noisy[10 * w + w / 2 - 1];
        assert!(edge > 1.1 && edge < 1.9, "edge depth {edge}");
        // Same seed, same frame.
        let mut again = clean.clone();
        apply_stereo_noise(&mut again, w, h, 7, (0.1, 5.0));
        assert_eq!(noisy, again);
    }
}
