//! What an imperfect perception adds to a rendered frame: detector label noise and depth
//! artefacts at silhouettes. Both are seeded from the frame's noise seed, each on its own ChaCha
//! stream, so neither moves the depth noise; [`PerceptionNoise::default`] (clean) draws nothing
//! and leaves frames bit for bit as without it.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::generate::LEAF_RANGE;
use crate::DepthNoiseModel;

/// Widest silhouette band accepted, in pixels.
pub const MAX_SILHOUETTE_PX: u32 = 8;

/// Depth step (m) between neighbouring pixels that makes a silhouette.
pub const SILHOUETTE_STEP_M: f64 = 0.03;

/// Share of silhouette pixels whose depth goes missing (0 on the wire).
pub const SILHOUETTE_MISSING_SHARE: f64 = 0.4;

/// Share of silhouette pixels whose depth is a blend of the foreground and background depths
/// ("flying pixels"); the rest keep their depth.
pub const SILHOUETTE_MIXED_SHARE: f64 = 0.4;

/// ChaCha streams of the kinds of noise (stream 0 is the depth noise).
const LABEL_STREAM: u64 = 1;
const SILHOUETTE_STREAM: u64 = 2;

/// Imperfect perception on top of the simulated camera. Settings files spell it
/// `{ label_noise: 0.3, silhouette_px: 1 }`; missing fields are clean.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PerceptionNoise {
    /// Probability in [0, 1] that a pixel's fruit/non-fruit label flips as the detector sees
    /// it: a fruit pixel takes a leaf colour, any other surface pixel a colour of the scene's
    /// fruit (both shaded like the surface). Sky pixels carry no depth and are left.
    pub label_noise: f64,
    /// Width in pixels of the band at plant silhouettes (fruit, leaf and stem edges against
    /// anything more than [`SILHOUETTE_STEP_M`] away in depth) where depth goes missing or
    /// mixes foreground and background; 0 = none.
    pub silhouette_px: u32,
    /// How depth noise behaves: the paper's i.i.d. noise (default) or a stereo camera's
    /// ([`DepthNoiseModel::D435`]: range-squared RMS, correlated error and edge smear).
    pub depth_noise: DepthNoiseModel,
    /// Depth goes missing where the fruit skin shows a specular highlight (stereo matching
    /// fails on saturated pixels).
    pub specular_dropouts: bool,
    /// A sun with shadow rays, a sky term that darkens what the canopy covers, specular
    /// highlights on fruit skin and an exposure that varies per frame.
    pub shadows: bool,
}

/// Perception noise settings out of range.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum PerceptionNoiseError {
    #[error("label noise must be a probability in [0, 1], got {0}")]
    LabelNoise(f64),
    #[error("silhouette artefact width must be 0..={MAX_SILHOUETTE_PX} pixels, got {0}")]
    SilhouettePx(u32),
}

impl PerceptionNoise {
    /// The label noise must be within [0, 1], the silhouette band at most
    /// [`MAX_SILHOUETTE_PX`] wide.
    pub fn validate(&self) -> Result<(), PerceptionNoiseError> {
        if !(0.0..=1.0).contains(&self.label_noise) {
            return Err(PerceptionNoiseError::LabelNoise(self.label_noise));
        }
        if self.silhouette_px > MAX_SILHOUETTE_PX {
            return Err(PerceptionNoiseError::SilhouettePx(self.silhouette_px));
        }
        Ok(())
    }
}

/// Flips pixel labels by swapping albedos, one draw per surface pixel in row-major order.
pub(crate) struct LabelFlips {
    probability: f64,
    /// Albedo range (per channel) a non-fruit pixel takes when its label flips.
    fruit_range: [(f32, f32); 3],
    rng: ChaCha8Rng,
}

impl LabelFlips {
    pub(crate) fn new(
        noise: &PerceptionNoise,
        noise_seed: u64,
        fruit_range: [(f32, f32); 3],
    ) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(noise_seed);
        rng.set_stream(LABEL_STREAM);
        Self {
            probability: noise.label_noise,
            fruit_range,
            rng,
        }
    }

    /// The albedo the detector sees for a surface of `albedo` that it labels fruit when
    /// `is_fruit`: unchanged, or with probability `label_noise` one of the other class.
    /// Draws nothing when the probability is 0.
    pub(crate) fn albedo_seen(&mut self, is_fruit: bool, albedo: [f32; 3]) -> [f32; 3] {
        if self.probability <= 0.0 || self.rng.gen::<f64>() >= self.probability {
            return albedo;
        }
        // Albedos of these ranges look like fruit of the scene's colour, or like leaves, under
        // any shading.
        let range = if is_fruit {
            LEAF_RANGE
        } else {
            self.fruit_range
        };
        range.map(|(lo, hi)| lo + (hi - lo) * self.rng.gen::<f32>())
    }
}

/// Surface code of a pixel whose ray meets the floor.
pub(crate) const FLOOR_SURFACE: u32 = u32::MAX - 1;
/// Surface code of a pixel whose ray meets nothing.
pub(crate) const SKY_SURFACE: u32 = u32::MAX;

/// What each pixel of a frame saw, for the silhouette pass: the surface (shape index,
/// [`FLOOR_SURFACE`] or [`SKY_SURFACE`]) and its noise-free depth (NaN for the sky).
pub(crate) struct SurfaceImage {
    pub width: usize,
    pub height: usize,
    pub surface: Vec<u32>,
    pub depth_m: Vec<f64>,
}

impl SurfaceImage {
    pub(crate) fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            surface: vec![SKY_SURFACE; width * height],
            depth_m: vec![f64::NAN; width * height],
        }
    }

    /// Nearest and farthest depth of the pixels within `radius` of `pixel` across a plant
    /// silhouette from it; `(inf, -inf)` when there is no silhouette, `(NaN, NaN)` when the
    /// other side is only the sky.
    fn silhouette_depths(&self, pixel: usize, radius: usize, is_plant: &[bool]) -> (f64, f64) {
        let plant = |s: u32| is_plant.get(s as usize).copied().unwrap_or(false);
        let (u, v) = (pixel % self.width, pixel / self.width);
        let (here, depth) = (self.surface[pixel], self.depth_m[pixel]);
        let (mut near, mut far, mut sky) = (f64::INFINITY, f64::NEG_INFINITY, false);
        let rows = v.saturating_sub(radius)..=(v + radius).min(self.height - 1);
        for qv in rows {
            for qu in u.saturating_sub(radius)..=(u + radius).min(self.width - 1) {
                let q = qv * self.width + qu;
                let there = self.surface[q];
                if there == here || !(plant(here) || plant(there)) {
                    continue;
                }
                if there == SKY_SURFACE {
                    sky = true;
                } else if (self.depth_m[q] - depth).abs() > SILHOUETTE_STEP_M {
                    near = near.min(self.depth_m[q]);
                    far = far.max(self.depth_m[q]);
                }
            }
        }
        if sky && near > far {
            (f64::NAN, f64::NAN)
        } else {
            (near, far)
        }
    }
}

/// Depth artefacts at plant silhouettes: every pixel with valid depth within `noise.silhouette_px`
/// of a plant silhouette loses its depth ([`SILHOUETTE_MISSING_SHARE`]), takes a uniform blend
/// of the nearest and farthest depth across the silhouette ([`SILHOUETTE_MIXED_SHARE`], dropped
/// when outside `range_m`), or keeps it; one draw per such pixel in row-major order.
pub(crate) fn add_silhouette_artefacts(
    depth_m: &mut [f32],
    seen: &SurfaceImage,
    is_plant: &[bool],
    noise: &PerceptionNoise,
    noise_seed: u64,
    range_m: (f64, f64),
) {
    let radius = noise.silhouette_px as usize;
    if radius == 0 {
        return;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(noise_seed);
    rng.set_stream(SILHOUETTE_STREAM);
    for (pixel, depth) in depth_m.iter_mut().enumerate() {
        if !depth.is_finite() {
            continue;
        }
        let (near, far) = seen.silhouette_depths(pixel, radius, is_plant);
        if near > far {
            continue;
        }
        let draw = rng.gen::<f64>();
        if draw >= SILHOUETTE_MISSING_SHARE + SILHOUETTE_MIXED_SHARE {
            continue;
        }
        // Against the sky there is no background depth to blend with.
        if draw < SILHOUETTE_MISSING_SHARE || near.is_nan() {
            *depth = f32::NAN;
        } else {
            let own = seen.depth_m[pixel];
            let (front, back) = (near.min(own), far.max(own));
            let mixed = front + rng.gen::<f64>() * (back - front);
            *depth = if (range_m.0..=range_m.1).contains(&mixed) {
                mixed as f32
            } else {
                f32::NAN
            };
        }
    }
}
