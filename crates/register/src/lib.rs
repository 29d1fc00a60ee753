//! Scan registration before map insertion.
//!
//! A trolley's camera pose is off by its hand-eye calibration error (0.5–1°, 5–10 mm), its joint
//! encoders' noise and its rail odometry, so every RGB-D scan lands in the world a little off.
//! [`align_scan`] aligns a scan (world-frame points, as the detector sends them) to the map's
//! occupied surface by point-to-plane ICP, then checks the estimate before anyone inserts it:
//!
//! - **consistency**: few of the points the map has an opinion on lie where it saw empty space
//!   or behind surface it knows (`max_contradicting_share`);
//! - **overlap**: enough inliers (points within `inlier_m` of the map's surface), and a large
//!   enough share of them among the points the map has an opinion on;
//! - **residual**: the truncated RMS of the point-to-plane residuals did not grow;
//! - **bounds**: the correction turns the scan by at most `max_rotation_deg` and moves the
//!   sensor origin by at most `max_sensor_shift_m` (a bigger one is a wrong match, not a
//!   calibration error);
//! - **convergence**: the last iteration moved the scan by less than `converged_shift_m`;
//! - **conditioning**: the 6×6 normal equations are solved in their eigenbasis; directions the
//!   geometry does not constrain (a single plane leaves three) are not corrected, and more than
//!   `max_degenerate_directions` of them fail the estimate.
//!
//! An estimate that passes is applied unless it is below what the map can tell (it moves no
//! point by `min_applied_shift_m`, or lowers the residual RMS by less than `min_rms_gain_m`):
//! in a perfect world no correction is applied. An estimate that fails lets the scan in as sent
//! only when, as sent, the map does not contradict it ([`KeptAsSent`]); otherwise the scan is
//! [`Alignment::Rejected`] and must not be inserted. A scan that cannot be checked (the map is
//! still small, the scan has few points, or it looks at space the map knows nothing of and
//! contradicts little of it) is [`Alignment::Skipped`]: it goes in as sent, since only such
//! scans can grow the map into new space.
//!
//! The map side is read through [`RoiMap`]'s occupancy test only (memoised over the scan's box):
//! the nearest occupied voxel of each scan point is searched in a sphere of voxel keys, and its
//! plane (normal and centroid) is the PCA of the occupied voxel centres around it, kept per
//! voxel for the call. No I/O, no clocks, no randomness: the scan is subsampled with a fixed
//! stride.

mod hand_eye;
mod icp;
mod memo;
mod surface;

use glasshouse_roimap::RoiMap;
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

pub use crate::hand_eye::{
    HandEyeEstimator, HandEyeFigures, HandEyeSettings, HandEyeState, KeyScan, Surfel,
};
use crate::icp::Registration;

/// How scans are registered and when an alignment is accepted. Every length is in metres,
/// every angle in degrees, every radius counted in map voxels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RegisterSettings {
    /// Off: every scan goes into the map as sent.
    pub enabled: bool,
    /// The scan is subsampled to at most this many points (fixed stride).
    pub max_scan_points: usize,
    /// Points farther than this from the sensor are not used: depth noise grows with range
    /// squared (a stereo camera's 8.5 mm RMS at 1.5 m is a voxel; 24 mm at 2.5 m is not), so a
    /// stereo camera wants about 1.5 m here.
    pub max_range_m: f64,
    /// Scans with fewer finite points than this are not registered.
    pub min_scan_points: usize,
    /// Registration starts once the map holds this many occupied voxels.
    pub min_map_occupied_voxels: usize,
    /// A scan point's map surface is the nearest occupied voxel within this radius.
    pub search_radius_voxels: u32,
    /// A map voxel's plane is fitted to the occupied voxels within this radius.
    pub normal_radius_voxels: u32,
    /// Planes fitted to fewer occupied voxels are not used.
    pub min_normal_voxels: usize,
    /// Smallest over middle eigenvalue of a plane fit above which its normal is ambiguous (an
    /// edge, a stem, a corner) and the plane is not used.
    pub max_normal_ambiguity: f64,
    /// Residuals beyond this get Huber weights (moving leaves, new surface).
    pub huber_m: f64,
    /// A point whose residual after alignment is within this is an inlier.
    pub inlier_m: f64,
    pub max_iterations: usize,
    /// The alignment stops once an iteration moves no scan point further than this.
    pub converged_shift_m: f64,
    /// Fewer inliers than this reject the alignment.
    pub min_inliers: usize,
    /// A scan with fewer than `min_inliers` points near map surface is rejected when at least
    /// this many of its points, and more than lie near surface, lie where the map saw empty
    /// space or behind surface it knows; else it is new ground and goes in as sent.
    pub min_contradicting_points: usize,
    /// Inliers over the points the map has an opinion on (near its surface, in space it saw
    /// empty, or behind surface it knows) below this reject the alignment.
    pub min_inlier_share: f64,
    /// A pose where more than this share of the points the map has an opinion on lie where
    /// it saw empty space or behind surface it knows contradicts the map. A scan whose
    /// alignment failed a check still goes in as sent when as sent it does not contradict the
    /// map; else it is rejected.
    pub max_contradicting_share: f64,
    pub max_rotation_deg: f64,
    /// Largest correction of the sensor origin's position.
    pub max_sensor_shift_m: f64,
    /// A direction of the normal equations whose eigenvalue is below this share of the largest
    /// is not constrained by the geometry, and is not corrected.
    pub degenerate_eigen_ratio: f64,
    /// More unconstrained directions than this reject the alignment.
    pub max_degenerate_directions: usize,
    /// Corrections that move no scan point by this much, or lower the residual RMS by less
    /// than `min_rms_gain_m`, are not applied: they are below what a map of this resolution
    /// can tell, and a perfect world gets its map unchanged.
    pub min_applied_shift_m: f64,
    pub min_rms_gain_m: f64,
}

impl Default for RegisterSettings {
    /// Off by default: with a stereo camera's noise (`--world realistic`) the map-contradiction
    /// checks refuse good scans (docs/results.md, "Registration"); on, it is harmless in a
    /// perfect world and undoes a calibration error on clean depth.
    fn default() -> Self {
        Self {
            enabled: false,
            max_scan_points: 3000,
            max_range_m: 3.0,
            min_scan_points: 200,
            min_map_occupied_voxels: 1000,
            search_radius_voxels: 3,
            normal_radius_voxels: 2,
            min_normal_voxels: 8,
            max_normal_ambiguity: 0.3,
            huber_m: 0.005,
            inlier_m: 0.01,
            max_iterations: 12,
            converged_shift_m: 0.0003,
            min_inliers: 150,
            min_contradicting_points: 50,
            min_inlier_share: 0.7,
            max_contradicting_share: 0.25,
            max_rotation_deg: 3.0,
            max_sensor_shift_m: 0.05,
            degenerate_eigen_ratio: 0.05,
            max_degenerate_directions: 3,
            min_applied_shift_m: 0.003,
            min_rms_gain_m: 0.0005,
        }
    }
}

/// A registration setting out of range.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum SettingsError {
    #[error("registration setting {name} must be {expected}, got {value}")]
    OutOfRange {
        name: &'static str,
        value: f64,
        expected: &'static str,
    },
}

impl RegisterSettings {
    pub fn validate(&self) -> Result<(), SettingsError> {
        let check = |name, value: f64, ok: bool, expected| match ok && value.is_finite() {
            true => Ok(()),
            false => Err(SettingsError::OutOfRange {
                name,
                value,
                expected,
            }),
        };
        let count = |name, value: usize, lo: usize, hi: usize| {
            let ok = (lo..=hi).contains(&value);
            check(
                name,
                value as f64,
                ok,
                "a count in its range (see the docs)",
            )
        };
        let positive = |name, value: f64| check(name, value, value > 0.0, "finite and > 0");
        let share = |name, value: f64| check(name, value, (0.0..=1.0).contains(&value), "in 0..=1");
        count("max_scan_points", self.max_scan_points, 1, 1 << 20)?;
        positive("max_range_m", self.max_range_m)?;
        count(
            "min_scan_points",
            self.min_scan_points,
            1,
            self.max_scan_points,
        )?;
        count(
            "search_radius_voxels",
            self.search_radius_voxels as usize,
            1,
            8,
        )?;
        count(
            "normal_radius_voxels",
            self.normal_radius_voxels as usize,
            1,
            4,
        )?;
        count("min_normal_voxels", self.min_normal_voxels, 3, 729)?;
        count("max_iterations", self.max_iterations, 1, 100)?;
        count(
            "max_degenerate_directions",
            self.max_degenerate_directions,
            0,
            5,
        )?;
        count(
            "min_contradicting_points",
            self.min_contradicting_points,
            1,
            usize::MAX,
        )?;
        share("max_normal_ambiguity", self.max_normal_ambiguity)?;
        share("min_inlier_share", self.min_inlier_share)?;
        share("max_contradicting_share", self.max_contradicting_share)?;
        positive("huber_m", self.huber_m)?;
        positive("inlier_m", self.inlier_m)?;
        positive("converged_shift_m", self.converged_shift_m)?;
        positive("max_sensor_shift_m", self.max_sensor_shift_m)?;
        let deg = self.max_rotation_deg;
        check(
            "max_rotation_deg",
            deg,
            deg > 0.0 && deg <= 30.0,
            "in (0, 30]",
        )?;
        let ratio = self.degenerate_eigen_ratio;
        check(
            "degenerate_eigen_ratio",
            ratio,
            (0.0..1.0).contains(&ratio),
            "in 0..1",
        )?;
        let min_shift = self.min_applied_shift_m;
        check(
            "min_applied_shift_m",
            min_shift,
            min_shift >= 0.0,
            "finite and >= 0",
        )?;
        let min_gain = self.min_rms_gain_m;
        check(
            "min_rms_gain_m",
            min_gain,
            min_gain >= 0.0,
            "finite and >= 0",
        )
    }
}

/// One scan as the detector sends it: the sensor origin and the points, both in the world frame
/// the trolley believes in.
#[derive(Clone, Copy, Debug)]
pub struct ScanInWorld<'a> {
    pub sensor_origin_in_world: &'a Point3<f64>,
    pub points_in_world: &'a [Point3<f32>],
}

/// An accepted alignment: the scan goes in, corrected or as sent.
#[derive(Clone, Debug, PartialEq)]
pub struct Aligned {
    /// ICP's estimate. It takes the scan's world points as sent onto the map (both in the world
    /// frame): `p_map = world_correction * p_sent`; the sensor origin moves the same way.
    pub world_correction: Isometry3<f64>,
    /// None when the estimate is applied; else why the scan goes in as sent.
    pub kept_as_sent: Option<KeptAsSent>,
    /// Angle of the estimate's rotation.
    pub rotation_deg: f64,
    /// How far the estimate moves the sensor origin.
    pub sensor_shift_m: f64,
    /// How far the estimate moves the farthest-moved subsampled scan point.
    pub max_point_shift_m: f64,
    /// Truncated RMS of the point-to-plane residuals of the points that saw map surface as sent,
    /// as sent and after the estimate (each residual capped at `inlier_m`).
    pub rms_before_m: f64,
    pub rms_after_m: f64,
    /// Subsampled points within `inlier_m` of the map surface, as the scan goes in.
    pub inliers: usize,
    /// Inliers over the subsampled points the map has an opinion on, as the scan goes in.
    pub inlier_share: f64,
    /// Directions the geometry left unconstrained, hence not corrected.
    pub unconstrained_directions: usize,
    pub iterations: usize,
}

impl Aligned {
    /// Whether the scan goes in corrected by [`Aligned::world_correction`].
    pub fn applied(&self) -> bool {
        self.kept_as_sent.is_none()
    }
}

/// Why an accepted scan goes in as sent.
#[derive(Clone, Debug, PartialEq)]
pub enum KeptAsSent {
    /// The estimate moves no scan point by `min_applied_shift_m`, or lowers the residual RMS by
    /// less than `min_rms_gain_m`: below what the map can tell (a perfect world ends here).
    BelowResolution,
    /// The estimate failed this check, but the scan as sent does not contradict the map
    /// (`max_contradicting_share`): ICP wandered along geometry that constrains it weakly, such
    /// as thin leaves, or the overlap is too small to trust a correction.
    EstimateFailed(RejectReason),
}

/// Why an alignment was rejected; the scan must not be inserted.
#[derive(Clone, Debug, PartialEq)]
pub enum RejectReason {
    /// Few of the scan's points lie near map surface, many where the map saw empty space or
    /// behind surface it knows.
    ContradictsMap {
        near_surface: usize,
        contradicting: usize,
    },
    TooFewInliers {
        inliers: usize,
    },
    LowInlierShare {
        inlier_share: f64,
    },
    RmsNotImproved {
        rms_before_m: f64,
        rms_after_m: f64,
    },
    CorrectionTooLarge {
        rotation_deg: f64,
        sensor_shift_m: f64,
    },
    /// The iterations still moved the scan by more than `converged_shift_m` at the last one:
    /// no consistent match (a good one settles in a few).
    NotConverged {
        last_step_m: f64,
    },
    /// Too many directions the scan's geometry leaves unconstrained.
    Degenerate {
        unconstrained_directions: usize,
    },
}

impl std::fmt::Display for RejectReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::ContradictsMap {
                near_surface,
                contradicting,
            } => write!(
                f,
                "contradicts the map: {contradicting} points where it saw through, {near_surface} near surface"
            ),
            Self::TooFewInliers { inliers } => write!(f, "too few inliers ({inliers})"),
            Self::LowInlierShare { inlier_share } => {
                write!(f, "inlier share {:.0} % too low", inlier_share * 100.0)
            }
            Self::RmsNotImproved {
                rms_before_m,
                rms_after_m,
            } => write!(
                f,
                "residual RMS grew from {:.1} to {:.1} mm",
                rms_before_m * 1e3,
                rms_after_m * 1e3
            ),
            Self::CorrectionTooLarge {
                rotation_deg,
                sensor_shift_m,
            } => write!(
                f,
                "correction too large ({rotation_deg:.2}°, {:.1} mm at the sensor)",
                sensor_shift_m * 1e3
            ),
            Self::NotConverged { last_step_m } => write!(
                f,
                "not converged (last step {:.2} mm)",
                last_step_m * 1e3
            ),
            Self::Degenerate {
                unconstrained_directions,
            } => write!(f, "{unconstrained_directions} unconstrained directions"),
        }
    }
}

/// Why a scan was not registered; it goes in as sent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SkipReason {
    Disabled,
    /// The map is too small to register against (the first scans).
    MapTooSmall {
        occupied_voxels: usize,
    },
    /// Too few finite points to tell anything.
    TooFewPoints {
        points: usize,
    },
    /// Too few points near map surface, and too few in known free space to contradict the map:
    /// the scan looks at space the map does not know yet.
    NewGround {
        near_surface: usize,
    },
}

/// What [`align_scan`] decided.
#[derive(Clone, Debug, PartialEq)]
pub enum Alignment {
    Aligned(Aligned),
    /// The scan must not be inserted.
    Rejected(RejectReason),
    /// Nothing to check against: the scan goes in as sent.
    Skipped(SkipReason),
}

impl Alignment {
    /// Whether the scan may go into the map.
    pub fn inserts(&self) -> bool {
        !matches!(self, Alignment::Rejected(_))
    }

    /// The correction to apply to the scan before inserting it, if any.
    pub fn correction_to_apply(&self) -> Option<&Isometry3<f64>> {
        match self {
            Alignment::Aligned(a) if a.applied() => Some(&a.world_correction),
            _ => None,
        }
    }
}

/// How many scans ended each way.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct AlignmentCounts {
    /// Accepted, with the correction applied.
    pub aligned: u64,
    /// Accepted as sent: the correction was below what the map can tell.
    pub kept_below_resolution: u64,
    /// Accepted as sent: the estimate failed a check, the scan as sent passed the overlap ones.
    pub kept_estimate_failed: u64,
    pub skipped: u64,
    pub rejected_contradicts_map: u64,
    pub rejected_too_few_inliers: u64,
    pub rejected_low_inlier_share: u64,
    pub rejected_rms_not_improved: u64,
    pub rejected_correction_too_large: u64,
    pub rejected_not_converged: u64,
    pub rejected_degenerate: u64,
}

impl std::ops::AddAssign for AlignmentCounts {
    /// Adds another planner's (or trial's) counts, outcome by outcome.
    fn add_assign(&mut self, other: Self) {
        self.aligned += other.aligned;
        self.kept_below_resolution += other.kept_below_resolution;
        self.kept_estimate_failed += other.kept_estimate_failed;
        self.skipped += other.skipped;
        self.rejected_contradicts_map += other.rejected_contradicts_map;
        self.rejected_too_few_inliers += other.rejected_too_few_inliers;
        self.rejected_low_inlier_share += other.rejected_low_inlier_share;
        self.rejected_rms_not_improved += other.rejected_rms_not_improved;
        self.rejected_correction_too_large += other.rejected_correction_too_large;
        self.rejected_not_converged += other.rejected_not_converged;
        self.rejected_degenerate += other.rejected_degenerate;
    }
}

impl AlignmentCounts {
    pub fn record(&mut self, alignment: &Alignment) {
        let counter = match alignment {
            Alignment::Aligned(a) => match a.kept_as_sent {
                None => &mut self.aligned,
                Some(KeptAsSent::BelowResolution) => &mut self.kept_below_resolution,
                Some(KeptAsSent::EstimateFailed(_)) => &mut self.kept_estimate_failed,
            },
            Alignment::Skipped(_) => &mut self.skipped,
            Alignment::Rejected(reason) => match reason {
                RejectReason::ContradictsMap { .. } => &mut self.rejected_contradicts_map,
                RejectReason::TooFewInliers { .. } => &mut self.rejected_too_few_inliers,
                RejectReason::LowInlierShare { .. } => &mut self.rejected_low_inlier_share,
                RejectReason::RmsNotImproved { .. } => &mut self.rejected_rms_not_improved,
                RejectReason::CorrectionTooLarge { .. } => &mut self.rejected_correction_too_large,
                RejectReason::NotConverged { .. } => &mut self.rejected_not_converged,
                RejectReason::Degenerate { .. } => &mut self.rejected_degenerate,
            },
        };
        *counter += 1;
    }

    /// Every rejection, whatever its reason.
    pub fn rejected(&self) -> u64 {
        self.rejected_contradicts_map
            + self.rejected_too_few_inliers
            + self.rejected_low_inlier_share
            + self.rejected_rms_not_improved
            + self.rejected_correction_too_large
            + self.rejected_not_converged
            + self.rejected_degenerate
    }
}

/// Aligns `scan` to the occupied surface of `map` and checks the result (see the crate docs).
/// Non-finite points and points outside the map's key range are ignored. The settings are
/// assumed valid ([`RegisterSettings::validate`]).
pub fn align_scan(map: &RoiMap, scan: ScanInWorld<'_>, settings: &RegisterSettings) -> Alignment {
    if !settings.enabled {
        return Alignment::Skipped(SkipReason::Disabled);
    }
    let occupied_voxels = map.counts().occupied;
    if occupied_voxels < settings.min_map_occupied_voxels {
        return Alignment::Skipped(SkipReason::MapTooSmall { occupied_voxels });
    }
    let sensor = scan.sensor_origin_in_world;
    let sample = subsample(map, sensor, scan.points_in_world, settings);
    if sample.len() < settings.min_scan_points || !is_finite(sensor) {
        let points = sample.len();
        return Alignment::Skipped(SkipReason::TooFewPoints { points });
    }
    Registration::new(map, &sample, scan.sensor_origin_in_world, settings).run()
}

/// The scan's points after a correction, in the world frame (non-finite points stay so).
pub fn corrected_points(
    world_correction: &Isometry3<f64>,
    points_in_world: &[Point3<f32>],
) -> Vec<Point3<f32>> {
    points_in_world
        .iter()
        .map(|p| (world_correction * p.cast::<f64>()).cast::<f32>())
        .collect()
}

/// At most `max_scan_points` of the finite points within the map's maximum range of the sensor
/// (farther ones never become surface) and `max_range_m` (farther ones are too noisy) and inside its key range, with a fixed stride
/// (deterministic: owner and replica planners register alike).
fn subsample(
    map: &RoiMap,
    sensor: &Point3<f64>,
    points: &[Point3<f32>],
    settings: &RegisterSettings,
) -> Vec<Point3<f64>> {
    let max_points = settings.max_scan_points;
    let range_m = map
        .config()
        .max_range_m
        .map_or(settings.max_range_m, |r| r.min(settings.max_range_m));
    let range_sq = range_m * range_m;
    let usable: Vec<Point3<f64>> = points
        .iter()
        .map(|p| p.cast::<f64>())
        .filter(|p| is_finite(p) && (p - sensor).norm_squared() <= range_sq)
        .collect();
    let stride = usable.len().div_ceil(max_points.max(1)).max(1);
    let kept = usable.into_iter().step_by(stride);
    kept.filter(|p| map.try_key_of(p).is_some()).collect()
}

fn is_finite(p: &Point3<f64>) -> bool {
    p.iter().all(|c| c.is_finite())
}

#[cfg(test)]
mod tests;
