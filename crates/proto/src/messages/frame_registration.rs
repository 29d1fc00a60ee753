//! FrameRegistration: how the owning planner registered one cloud to its trolley's map, carried
//! by the MapUpdate of that cloud (see the schema's `FrameRegistration`).

use flatbuffers::{FlatBufferBuilder, WIPOffset};
use nalgebra::{Isometry3, Vector3};

use super::convert::{content, unknown_enum};
use crate::{fb, FrameId, MessageKind, Result};

/// What registration made of one cloud.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum RegistrationVerdict {
    /// Not checked (registration off, the map still too small, too few points, or space the map
    /// does not know yet): inserted as sent.
    #[default]
    Skipped,
    /// Aligned: inserted with the correction applied.
    Applied,
    /// Inserted as sent: the estimate is below what the map can tell, or it failed a check
    /// while the scan as sent agrees with the map.
    KeptAsSent,
    /// Not inserted: the estimate failed a check and the scan as sent contradicts the map.
    Rejected,
}

impl RegistrationVerdict {
    pub const ALL: [RegistrationVerdict; 4] = [
        Self::Skipped,
        Self::Applied,
        Self::KeptAsSent,
        Self::Rejected,
    ];

    /// A short lower-case name (`kept_as_sent`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Skipped => "skipped",
            Self::Applied => "applied",
            Self::KeptAsSent => "kept_as_sent",
            Self::Rejected => "rejected",
        }
    }

    fn to_fb(self) -> fb::RegistrationVerdict {
        match self {
            Self::Skipped => fb::RegistrationVerdict::Skipped,
            Self::Applied => fb::RegistrationVerdict::Applied,
            Self::KeptAsSent => fb::RegistrationVerdict::KeptAsSent,
            Self::Rejected => fb::RegistrationVerdict::Rejected,
        }
    }

    fn from_fb(v: fb::RegistrationVerdict) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|mine| mine.to_fb() == v)
            .ok_or_else(|| unknown_enum(MessageKind::MapUpdate, "registration verdict", v.0))
    }
}

/// Why a registration ended as it did: a skip's reason, `BelowResolution` for an estimate kept
/// as sent for being too small, or the check an estimate failed (kept as sent or rejected).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum RegistrationReason {
    /// Applied: nothing to explain.
    #[default]
    None,
    Disabled,
    MapTooSmall,
    TooFewPoints,
    NewGround,
    BelowResolution,
    ContradictsMap,
    TooFewInliers,
    LowInlierShare,
    RmsNotImproved,
    CorrectionTooLarge,
    NotConverged,
    Degenerate,
}

impl RegistrationReason {
    pub const ALL: [RegistrationReason; 13] = [
        Self::None,
        Self::Disabled,
        Self::MapTooSmall,
        Self::TooFewPoints,
        Self::NewGround,
        Self::BelowResolution,
        Self::ContradictsMap,
        Self::TooFewInliers,
        Self::LowInlierShare,
        Self::RmsNotImproved,
        Self::CorrectionTooLarge,
        Self::NotConverged,
        Self::Degenerate,
    ];

    /// A short lower-case name (`contradicts_map`).
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Disabled => "disabled",
            Self::MapTooSmall => "map_too_small",
            Self::TooFewPoints => "too_few_points",
            Self::NewGround => "new_ground",
            Self::BelowResolution => "below_resolution",
            Self::ContradictsMap => "contradicts_map",
            Self::TooFewInliers => "too_few_inliers",
            Self::LowInlierShare => "low_inlier_share",
            Self::RmsNotImproved => "rms_not_improved",
            Self::CorrectionTooLarge => "correction_too_large",
            Self::NotConverged => "not_converged",
            Self::Degenerate => "degenerate",
        }
    }

    fn to_fb(self) -> fb::RegistrationReason {
        use fb::RegistrationReason as R;
        match self {
            Self::None => R::None,
            Self::Disabled => R::Disabled,
            Self::MapTooSmall => R::MapTooSmall,
            Self::TooFewPoints => R::TooFewPoints,
            Self::NewGround => R::NewGround,
            Self::BelowResolution => R::BelowResolution,
            Self::ContradictsMap => R::ContradictsMap,
            Self::TooFewInliers => R::TooFewInliers,
            Self::LowInlierShare => R::LowInlierShare,
            Self::RmsNotImproved => R::RmsNotImproved,
            Self::CorrectionTooLarge => R::CorrectionTooLarge,
            Self::NotConverged => R::NotConverged,
            Self::Degenerate => R::Degenerate,
        }
    }

    fn from_fb(r: fb::RegistrationReason) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|mine| mine.to_fb() == r)
            .ok_or_else(|| unknown_enum(MessageKind::MapUpdate, "registration reason", r.0))
    }
}

/// A rigid correction of world-frame points: `p_corrected = R * p + translation_m`, with `R`
/// the rotation about the world origin by the rotation vector (unit axis times angle).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidCorrection {
    pub translation_m: Vector3<f64>,
    pub rotation_vector_rad: Vector3<f64>,
}

impl RigidCorrection {
    pub fn from_isometry(world_correction: &Isometry3<f64>) -> Self {
        Self {
            translation_m: world_correction.translation.vector,
            rotation_vector_rad: world_correction.rotation.scaled_axis(),
        }
    }

    pub fn to_isometry(&self) -> Isometry3<f64> {
        Isometry3::new(self.translation_m, self.rotation_vector_rad)
    }

    /// The rotation's angle, degrees.
    pub fn angle_deg(&self) -> f64 {
        self.rotation_vector_rad.norm().to_degrees()
    }

    fn to_fb(self) -> fb::RigidCorrection {
        let (t, r) = (self.translation_m, self.rotation_vector_rad);
        fb::RigidCorrection::new(
            &fb::Vec3d::new(t.x, t.y, t.z),
            &fb::Vec3d::new(r.x, r.y, r.z),
        )
    }

    fn from_fb(c: &fb::RigidCorrection) -> Result<Self> {
        let vector = |v: &fb::Vec3d| Vector3::new(v.x(), v.y(), v.z());
        let correction = Self {
            translation_m: vector(c.translation_m()),
            rotation_vector_rad: vector(c.rotation_vector_rad()),
        };
        let values = correction.translation_m.iter();
        if values
            .chain(correction.rotation_vector_rad.iter())
            .any(|v| !v.is_finite())
        {
            return Err(content(
                MessageKind::MapUpdate,
                "registration world_correction is not finite",
            ));
        }
        Ok(correction)
    }
}

/// How the owning planner registered one cloud to the trolley's map: the verdict, why, ICP's
/// estimate and its figures. A figure is `None` when the registration did not compute it (a
/// skipped scan has none; a rejected one only those of the check it failed).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameRegistration {
    /// The cloud's frame (its edge's boot epoch and frame seq).
    pub frame: FrameId,
    pub verdict: RegistrationVerdict,
    pub reason: RegistrationReason,
    /// ICP's estimate, taking the scan as sent onto the map (world frame): applied when the
    /// verdict is `Applied`, not when `KeptAsSent`; `None` without an estimate.
    pub world_correction: Option<RigidCorrection>,
    /// Angle of the estimate's rotation, degrees.
    pub rotation_deg: Option<f32>,
    /// How far the estimate moves the sensor origin.
    pub sensor_shift_m: Option<f32>,
    /// How far it moves the farthest-moved subsampled scan point.
    pub max_point_shift_m: Option<f32>,
    /// Truncated RMS of the point-to-plane residuals, as sent and after the estimate.
    pub rms_before_m: Option<f32>,
    pub rms_after_m: Option<f32>,
    /// Subsampled points near the map's surface, and their share of the points the map has an
    /// opinion on.
    pub inliers: Option<u32>,
    pub inlier_share: Option<f32>,
    /// Directions the scan's geometry left unconstrained.
    pub unconstrained_directions: Option<u32>,
    pub iterations: Option<u32>,
    /// Scan points near the map's surface, and where the map saw through (`ContradictsMap`,
    /// `NewGround`).
    pub near_surface_points: Option<u32>,
    pub contradicting_points: Option<u32>,
    /// How far the last iteration still moved the scan (`NotConverged`).
    pub last_step_m: Option<f32>,
    /// The trolley's hand-eye estimate as applied to the cloud before the registration above
    /// (world frame); `None` without an estimate.
    pub hand_eye_correction: Option<RigidCorrection>,
}

impl FrameRegistration {
    /// Whether the cloud went into the map (corrected or as sent).
    pub fn inserted(&self) -> bool {
        self.verdict != RegistrationVerdict::Rejected
    }

    pub(crate) fn write<'a>(
        &self,
        fbb: &mut FlatBufferBuilder<'a>,
    ) -> WIPOffset<fb::FrameRegistration<'a>> {
        let correction = self.world_correction.map(RigidCorrection::to_fb);
        let hand_eye = self.hand_eye_correction.map(RigidCorrection::to_fb);
        fb::FrameRegistration::create(
            fbb,
            &fb::FrameRegistrationArgs {
                frame_epoch_ns: self.frame.epoch_ns,
                frame_seq: self.frame.seq,
                verdict: self.verdict.to_fb(),
                reason: self.reason.to_fb(),
                world_correction: correction.as_ref(),
                rotation_deg: self.rotation_deg,
                sensor_shift_m: self.sensor_shift_m,
                max_point_shift_m: self.max_point_shift_m,
                rms_before_m: self.rms_before_m,
                rms_after_m: self.rms_after_m,
                inliers: self.inliers,
                inlier_share: self.inlier_share,
                unconstrained_directions: self.unconstrained_directions,
                iterations: self.iterations,
                near_surface_points: self.near_surface_points,
                contradicting_points: self.contradicting_points,
                last_step_m: self.last_step_m,
                hand_eye_correction: hand_eye.as_ref(),
            },
        )
    }

    pub(crate) fn read(r: &fb::FrameRegistration<'_>) -> Result<Self> {
        Ok(Self {
            frame: FrameId::new(r.frame_epoch_ns(), r.frame_seq()),
            verdict: RegistrationVerdict::from_fb(r.verdict())?,
            reason: RegistrationReason::from_fb(r.reason())?,
            world_correction: r
                .world_correction()
                .map(RigidCorrection::from_fb)
                .transpose()?,
            rotation_deg: r.rotation_deg(),
            sensor_shift_m: r.sensor_shift_m(),
            max_point_shift_m: r.max_point_shift_m(),
            rms_before_m: r.rms_before_m(),
            rms_after_m: r.rms_after_m(),
            inliers: r.inliers(),
            inlier_share: r.inlier_share(),
            unconstrained_directions: r.unconstrained_directions(),
            iterations: r.iterations(),
            near_surface_points: r.near_surface_points(),
            contradicting_points: r.contradicting_points(),
            last_step_m: r.last_step_m(),
            hand_eye_correction: r
                .hand_eye_correction()
                .map(RigidCorrection::from_fb)
                .transpose()?,
        })
    }
}
