//! Light of the `shadows` world: a sun whose light leaves shadows (a shadow ray per pixel), a
//! sky term that darkens what the canopy covers (one ray straight up), specular highlights on
//! the fruit skin, and an auto-exposure that brings each frame to the clean world's mean
//! brightness, off by a random few per cent per frame. Highlights also decide the specular
//! depth dropouts, which exist with or without this light model.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::shapes::Ray;
use crate::{PerceptionNoise, Scene, AMBIENT, DIFFUSE};

/// ChaCha stream of the per-frame exposure draw.
const EXPOSURE_STREAM: u64 = 4;
/// Auto-exposure's error per frame: a factor in this range on top of the exposure that would
/// give the frame the clean world's mean brightness.
pub const EXPOSURE_RANGE: (f32, f32) = (0.8, 1.2);
/// Auto-exposure's own limits (a dark frame cannot be brightened without bound).
const EXPOSURE_LIMITS: (f64, f64) = (0.5, 2.0);
/// Share of the ambient light left where the sky straight above is covered (a glasshouse's
/// light is diffuse: the roof and the floor scatter it).
pub const COVERED_SKY_SHARE: f32 = 0.6;
/// Blinn-Phong exponent and strength of the fruit skin's highlight.
const SHININESS: i32 = 80;
const SPECULAR: f32 = 0.7;
/// Highlight level above which a stereo camera loses depth (saturated, textureless).
pub const DROPOUT_HIGHLIGHT: f64 = 0.35;
/// Offset of shadow rays off the surface, against self-intersection.
const SURFACE_OFFSET_M: f64 = 1e-4;

/// The light of one frame.
pub(crate) struct Lighting {
    shadows: bool,
    dropouts: bool,
    /// Auto-exposure's error this frame.
    exposure_error: f32,
    sun: Vector3<f64>,
    /// Light factors summed over the frame's surface pixels, with and without this light
    /// model, for the auto-exposure.
    factor_sum: f64,
    clean_factor_sum: f64,
}

impl Lighting {
    pub(crate) fn new(perception: &PerceptionNoise, noise_seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(noise_seed);
        rng.set_stream(EXPOSURE_STREAM);
        let exposure_error = if perception.shadows {
            EXPOSURE_RANGE.0 + (EXPOSURE_RANGE.1 - EXPOSURE_RANGE.0) * rng.gen::<f32>()
        } else {
            1.0
        };
        Self {
            shadows: perception.shadows,
            dropouts: perception.specular_dropouts,
            exposure_error,
            factor_sum: 0.0,
            clean_factor_sum: 0.0,
            // A lower sun than the clean world's light, so leaves cast shadows across plants.
            sun: if perception.shadows {
                Vector3::new(0.55, 0.35, 0.75).normalize()
            } else {
                crate::light_direction()
            },
        }
    }
}

/// A surface point as the camera sees it.
pub(crate) struct SurfaceHit {
    pub point: Vector3<f64>,
    /// Unit normal turned towards the camera.
    pub facing: Vector3<f64>,
    /// Unit direction from the camera to the point.
    pub view_dir: Vector3<f64>,
    pub albedo: [f32; 3],
    /// Fruit skin (shiny): any fruit, whatever its colour.
    pub is_fruit: bool,
}

impl Lighting {
    /// True when colours wait for the frame's exposure ([`Lighting::expose`]).
    pub(crate) fn needs_exposure(&self) -> bool {
        self.shadows
    }

    /// Writes the exposed colours of `radiance` (3 per pixel, before exposure) into `rgb`,
    /// skipping pixels whose radiance is negative (the sky, already coloured).
    pub(crate) fn expose(&self, radiance: &[f32], rgb: &mut [u8]) {
        let auto = if self.factor_sum > 0.0 {
            (self.clean_factor_sum / self.factor_sum).clamp(EXPOSURE_LIMITS.0, EXPOSURE_LIMITS.1)
        } else {
            1.0
        };
        let exposure = auto as f32 * self.exposure_error;
        for (out, &r) in rgb.iter_mut().zip(radiance) {
            if r >= 0.0 {
                *out = (r * exposure + 0.5).min(255.0) as u8;
            }
        }
    }
}

/// What the light does at one pixel: its colour (before exposure when the light model waits
/// for it), and whether a highlight there drops the depth.
pub(crate) struct Shade {
    pub colour: [f32; 3],
    pub dropout: bool,
}

impl Scene {
    /// The light at `hit` under `lighting`.
    pub(crate) fn shade_lit(
        &self,
        lighting: &mut Lighting,
        hit: &SurfaceHit,
        stack: &mut Vec<(u32, f32)>,
    ) -> Shade {
        let sun_visible = !lighting.shadows || !self.occluded(hit, &lighting.sun, stack);
        let half = (lighting.sun - hit.view_dir).normalize();
        let highlight = if hit.is_fruit && sun_visible {
            hit.facing.dot(&half).max(0.0).powi(SHININESS)
        } else {
            0.0
        };
        let dropout = lighting.dropouts && highlight > DROPOUT_HIGHLIGHT;
        if !lighting.shadows {
            let colour = crate::shade(hit.albedo, hit.facing.dot(&lighting.sun)).map(f32::from);
            return Shade { colour, dropout };
        }
        let sky = if self.occluded(hit, &Vector3::z(), stack) {
            COVERED_SKY_SHARE
        } else {
            1.0
        };
        let cos_sun = hit.facing.dot(&lighting.sun).max(0.0) as f32;
        let direct = if sun_visible { cos_sun } else { 0.0 };
        let factor = AMBIENT * sky + DIFFUSE * direct;
        lighting.factor_sum += f64::from(factor);
        let clean_cos = hit.facing.dot(&crate::light_direction()).max(0.0) as f32;
        lighting.clean_factor_sum += f64::from(AMBIENT + DIFFUSE * clean_cos);
        let shine = 255.0 * SPECULAR * highlight as f32;
        let colour = hit.albedo.map(|a| a * factor + shine);
        Shade { colour, dropout }
    }

    /// True when a shape lies between the surface point and the sky in direction `towards`.
    fn occluded(
        &self,
        hit: &SurfaceHit,
        towards: &Vector3<f64>,
        stack: &mut Vec<(u32, f32)>,
    ) -> bool {
        let start = hit.point + hit.facing * SURFACE_OFFSET_M;
        let ray = Ray::new(start, *towards);
        self.bvh
            .closest_hit(&ray, f64::INFINITY, None, stack)
            .is_some()
    }
}
