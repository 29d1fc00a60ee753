//! How much the simulated world fights back: every imperfection of a real glasshouse the
//! simulator knows, each a seeded setting that is off by default, and the `realistic` preset
//! that turns them all on.

use std::fmt;
use std::str::FromStr;

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::{
    standard_normal, DepthNoiseModel, FruitShape, PerceptionNoise, PerceptionNoiseError,
    SceneOptions, SceneOptionsError,
};

/// ChaCha streams of the pose errors (seeded from the trolley's scene seed).
const HAND_EYE_STREAM: u64 = 11;
const RAIL_STREAM: u64 = 12;
/// Joint noise is seeded from the frame's noise seed.
const JOINT_STREAM: u64 = 13;
/// A visit's base offset is seeded from the visit's seed (`visit_offset`).
const VISIT_STREAM: u64 = 14;

/// Largest pose errors accepted (beyond them the setting is surely a typo).
pub const MAX_HAND_EYE_ERROR_DEG: f64 = 10.0;
pub const MAX_HAND_EYE_ERROR_MM: f64 = 100.0;
pub const MAX_JOINT_NOISE_DEG: f64 = 2.0;
pub const MAX_RAIL_ERROR_MM: f64 = 200.0;

/// Where the trolley believes its camera is against where it is. The frame reports the
/// believed pose; the renderer uses the true one. Settings files spell it
/// `{ hand_eye_error_deg: 0.5, hand_eye_error_mm: 5, joint_noise_deg: 0.05, rail_error_mm: 10 }`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseError {
    /// Rotation of the camera against its calibrated mounting, fixed per trolley (random axis
    /// from the trolley's seed).
    pub hand_eye_error_deg: f64,
    /// Offset of the camera against its calibrated mounting, fixed per trolley (random
    /// direction from the trolley's seed).
    pub hand_eye_error_mm: f64,
    /// Standard deviation of each joint encoder's error, drawn anew for every frame.
    pub joint_noise_deg: f64,
    /// Standard deviation of the rail odometry's error added at every segment the trolley
    /// moves on (it accumulates along the row); only mounts on a rail have one.
    pub rail_error_mm: f64,
}

/// Pose error settings out of range.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum PoseErrorError {
    #[error("hand-eye error must be 0..={MAX_HAND_EYE_ERROR_DEG} degrees, got {0}")]
    HandEyeDeg(f64),
    #[error("hand-eye error must be 0..={MAX_HAND_EYE_ERROR_MM} mm, got {0}")]
    HandEyeMm(f64),
    #[error("joint noise must be 0..={MAX_JOINT_NOISE_DEG} degrees, got {0}")]
    JointNoise(f64),
    #[error("rail error must be 0..={MAX_RAIL_ERROR_MM} mm, got {0}")]
    Rail(f64),
}

impl PoseError {
    pub fn validate(&self) -> Result<(), PoseErrorError> {
        let within = |v: f64, max: f64| (0.0..=max).contains(&v);
        if !within(self.hand_eye_error_deg, MAX_HAND_EYE_ERROR_DEG) {
            return Err(PoseErrorError::HandEyeDeg(self.hand_eye_error_deg));
        }
        if !within(self.hand_eye_error_mm, MAX_HAND_EYE_ERROR_MM) {
            return Err(PoseErrorError::HandEyeMm(self.hand_eye_error_mm));
        }
        if !within(self.joint_noise_deg, MAX_JOINT_NOISE_DEG) {
            return Err(PoseErrorError::JointNoise(self.joint_noise_deg));
        }
        if !within(self.rail_error_mm, MAX_RAIL_ERROR_MM) {
            return Err(PoseErrorError::Rail(self.rail_error_mm));
        }
        Ok(())
    }

    /// True when the believed pose is the true one.
    pub fn is_exact(&self) -> bool {
        *self == PoseError::default()
    }

    /// The camera's true pose in its believed camera frame (`believed_from_true`): a rotation
    /// of `hand_eye_error_deg` about a random axis and an offset of `hand_eye_error_mm` in a
    /// random direction, both fixed by `trolley_seed`.
    pub fn believed_camera_from_true(&self, trolley_seed: u64) -> Isometry3<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(trolley_seed);
        rng.set_stream(HAND_EYE_STREAM);
        let axis = random_unit_vector(&mut rng);
        let direction = random_unit_vector(&mut rng);
        Isometry3::from_parts(
            Translation3::from(direction.into_inner() * self.hand_eye_error_mm * 1e-3),
            UnitQuaternion::from_axis_angle(&axis, self.hand_eye_error_deg.to_radians()),
        )
    }

    /// Where the trolley really stands on a visit against where it believes (its base localised
    /// anew each visit): an offset along the row (x) with the rail error's size, a third of it
    /// across and up, and a yaw of 0.02° per millimetre of it; seeded by `visit_seed`. None
    /// without a rail error.
    pub fn visit_offset(&self, visit_seed: u64) -> Option<Isometry3<f64>> {
        if self.rail_error_mm <= 0.0 {
            return None;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(visit_seed);
        rng.set_stream(VISIT_STREAM);
        let mut spare = None;
        let mut normal = || standard_normal(&mut rng, &mut spare);
        let sd_m = self.rail_error_mm * 1e-3;
        let (x, y, z) = (
            normal() * sd_m,
            normal() * sd_m / 3.0,
            normal() * sd_m / 3.0,
        );
        let yaw = (normal() * 0.02 * self.rail_error_mm).to_radians();
        Some(Isometry3::from_parts(
            Translation3::new(x, y, z),
            UnitQuaternion::from_axis_angle(&nalgebra::Vector3::z_axis(), yaw),
        ))
    }

    /// Each joint's encoder error for the frame seeded with `noise_seed` (true minus reported
    /// angle), in radians.
    pub fn joint_errors_rad(&self, noise_seed: u64, joints: usize) -> Vec<f64> {
        if self.joint_noise_deg <= 0.0 {
            return vec![0.0; joints];
        }
        let mut rng = ChaCha8Rng::seed_from_u64(noise_seed);
        rng.set_stream(JOINT_STREAM);
        let mut spare = None;
        let std_rad = self.joint_noise_deg.to_radians();
        (0..joints)
            .map(|_| std_rad * standard_normal(&mut rng, &mut spare))
            .collect()
    }

    /// The rail odometry's error (true minus believed position, m) on each of `segments`
    /// segments: a random walk with a step of `rail_error_mm` per segment, seeded by
    /// `trolley_seed`.
    pub fn rail_errors_m(&self, trolley_seed: u64, segments: usize) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(trolley_seed);
        rng.set_stream(RAIL_STREAM);
        let mut spare = None;
        let step_m = self.rail_error_mm * 1e-3;
        let mut error_m = 0.0;
        (0..segments)
            .map(|_| {
                error_m += step_m * standard_normal(&mut rng, &mut spare);
                error_m
            })
            .collect()
    }
}

fn random_unit_vector(rng: &mut ChaCha8Rng) -> Unit<Vector3<f64>> {
    loop {
        let v = Vector3::from_fn(|_, _| 2.0 * rng.gen::<f64>() - 1.0);
        let n = v.norm();
        if n > 1e-3 && n <= 1.0 {
            return Unit::new_normalize(v);
        }
    }
}

/// Everything the simulated world does that a perfect one would not: the camera (depth noise,
/// light, label noise, silhouettes), the scene (fruit shape and colour, red clutter) and the
/// poses. Settings files spell it `world: { perception: {..}, scene: {..}, pose: {..} }`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorldSettings {
    pub perception: PerceptionNoise,
    pub scene: SceneOptions,
    pub pose: PoseError,
}

/// A world setting out of range.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum WorldError {
    #[error(transparent)]
    Perception(#[from] PerceptionNoiseError),
    #[error(transparent)]
    Scene(#[from] SceneOptionsError),
    #[error(transparent)]
    Pose(#[from] PoseErrorError),
}

impl WorldSettings {
    pub fn validate(&self) -> Result<(), WorldError> {
        self.perception.validate()?;
        self.scene.validate()?;
        self.pose.validate()?;
        Ok(())
    }

    /// The preset's world.
    pub fn preset(preset: WorldPreset) -> Self {
        match preset {
            WorldPreset::Clean => Self::default(),
            WorldPreset::Realistic => Self::realistic(),
        }
    }

    /// Every imperfection on at the values a careful real set-up reaches: hand-eye error 0.5°
    /// and 5 mm, joint encoders 0.05°, rail odometry 10 mm per segment, a D435's depth with
    /// 1 px silhouette artefacts and specular dropouts, sun, shadows and varying exposure,
    /// capsicum-shaped fruit, 1.5 % of leaves fruit-red plus clips, labels and red stems.
    /// The fruit stay red (the colour rule's case) and labels are not flipped at random:
    /// the detector's errors here are the persistent ones.
    pub fn realistic() -> Self {
        Self {
            perception: PerceptionNoise {
                label_noise: 0.0,
                silhouette_px: 1,
                depth_noise: DepthNoiseModel::D435,
                specular_dropouts: true,
                shadows: true,
            },
            scene: SceneOptions {
                fruit_shape: FruitShape::Capsicum,
                red_clutter: 0.015,
                ..SceneOptions::default()
            },
            pose: PoseError {
                hand_eye_error_deg: 0.5,
                hand_eye_error_mm: 5.0,
                joint_noise_deg: 0.05,
                rail_error_mm: 10.0,
            },
        }
    }
}

/// Named worlds: `clean` (the default: every imperfection off) and `realistic`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WorldPreset {
    #[default]
    Clean,
    Realistic,
}

/// A world preset name that is not `clean` or `realistic`.
#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
#[error("unknown world {0:?}; valid: clean, realistic")]
pub struct ParseWorldPresetError(pub String);

impl FromStr for WorldPreset {
    type Err = ParseWorldPresetError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "clean" | "perfect" => Ok(WorldPreset::Clean),
            "realistic" | "real" => Ok(WorldPreset::Realistic),
            _ => Err(ParseWorldPresetError(s.to_string())),
        }
    }
}

impl fmt::Display for WorldPreset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            WorldPreset::Clean => "clean",
            WorldPreset::Realistic => "realistic",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_visit_has_its_own_base_offset_of_the_rail_errors_size() {
        let realistic = WorldSettings::realistic().pose;
        let offsets: Vec<Isometry3<f64>> = (0..200)
            .filter_map(|seed| realistic.visit_offset(seed))
            .collect();
        assert_eq!(offsets.len(), 200);
        let along: Vec<f64> = offsets.iter().map(|o| o.translation.x).collect();
        let sd = (along.iter().map(|x| x * x).sum::<f64>() / along.len() as f64).sqrt();
        assert!((sd - 0.010).abs() < 0.002, "{sd}");
        assert_ne!(realistic.visit_offset(1), realistic.visit_offset(2));
        assert_eq!(realistic.visit_offset(1), realistic.visit_offset(1));
        assert!(PoseError::default().visit_offset(1).is_none());
    }

    #[test]
    fn hand_eye_error_has_the_asked_size_and_depends_on_the_seed() {
        let error = PoseError {
            hand_eye_error_deg: 0.5,
            hand_eye_error_mm: 5.0,
            ..PoseError::default()
        };
        let a = error.believed_camera_from_true(3);
        assert!((a.rotation.angle().to_degrees() - 0.5).abs() < 1e-9);
        assert!((a.translation.vector.norm() - 0.005).abs() < 1e-12);
        let b = error.believed_camera_from_true(4);
        assert!((a.translation.vector - b.translation.vector).norm() > 1e-4);
        assert_eq!(a, error.believed_camera_from_true(3));
        let exact = PoseError::default().believed_camera_from_true(3);
        assert!(exact.translation.vector.norm() == 0.0 && exact.rotation.angle() == 0.0);
    }

    #[test]
    fn joint_and_rail_errors_have_the_asked_spread() {
        let error = PoseError {
            joint_noise_deg: 0.05,
            rail_error_mm: 10.0,
            ..PoseError::default()
        };
        let joints: Vec<f64> = (0..2000)
            .flat_map(|seed| error.joint_errors_rad(seed, 6))
            .collect();
        let rms = (joints.iter().map(|e| e * e).sum::<f64>() / joints.len() as f64).sqrt();
        assert!((rms.to_degrees() - 0.05).abs() < 0.003, "joint rms {rms}");
        let rail = error.rail_errors_m(5, 400);
        let steps: Vec<f64> = rail.windows(2).map(|w| w[1] - w[0]).collect();
        let step_rms = (steps.iter().map(|s| s * s).sum::<f64>() / steps.len() as f64).sqrt();
        assert!(
            (step_rms - 0.010).abs() < 0.0015,
            "rail step rms {step_rms}"
        );
        assert_eq!(PoseError::default().joint_errors_rad(1, 6), vec![0.0; 6]);
    }

    #[test]
    fn presets_parse_validate_and_differ() {
        assert_eq!(
            "realistic".parse::<WorldPreset>(),
            Ok(WorldPreset::Realistic)
        );
        assert!("harsh".parse::<WorldPreset>().is_err());
        assert_eq!(
            WorldSettings::preset(WorldPreset::Clean),
            WorldSettings::default()
        );
        let real = WorldSettings::realistic();
        assert_eq!(real.validate(), Ok(()));
        assert!(!real.pose.is_exact());
        let bad = PoseError {
            joint_noise_deg: f64::NAN,
            ..PoseError::default()
        };
        assert!(matches!(bad.validate(), Err(PoseErrorError::JointNoise(_))));
    }

    #[test]
    fn settings_files_spell_the_world_as_documented() {
        let world: WorldSettings = serde_json::from_str(
            r#"{"perception": {"depth_noise": "d435", "shadows": true},
                "scene": {"fruit_shape": "capsicum", "red_clutter": 0.015},
                "pose": {"hand_eye_error_deg": 0.5}}"#,
        )
        .expect("parses");
        assert_eq!(world.perception.depth_noise, DepthNoiseModel::D435);
        assert!(world.perception.shadows);
        assert_eq!(world.pose.hand_eye_error_deg, 0.5);
        assert!(serde_json::from_str::<WorldSettings>(r#"{"pose": {"typo": 1}}"#).is_err());
    }
}
