//! What the planner reports of its registrations: each cloud's, as the [`FrameRegistration`] of
//! the MapUpdate that cloud produces, and the totals of the trolleys it owns, in PlannerStatus.

use glasshouse_pipeline::{Alignment, AlignmentCounts};
use glasshouse_proto::{
    FrameId, FrameRegistration, RegistrationReason, RegistrationTotals, RegistrationVerdict,
    RigidCorrection,
};
use glasshouse_register::{KeptAsSent, RejectReason, SkipReason};

/// The wire record of how the cloud of `frame` was registered (`alignment`: the trolley's
/// planner's `last_alignment` right after that cloud was inserted).
pub fn frame_registration(frame: FrameId, alignment: &Alignment) -> FrameRegistration {
    let record = FrameRegistration {
        frame,
        ..FrameRegistration::default()
    };
    match alignment {
        Alignment::Aligned(a) => {
            let (verdict, reason) = match &a.kept_as_sent {
                None => (RegistrationVerdict::Applied, RegistrationReason::None),
                Some(KeptAsSent::BelowResolution) => (
                    RegistrationVerdict::KeptAsSent,
                    RegistrationReason::BelowResolution,
                ),
                Some(KeptAsSent::EstimateFailed(failed)) => {
                    (RegistrationVerdict::KeptAsSent, reject_reason(failed))
                }
            };
            // The estimate's own figures; of the failed check's, only those it does not have.
            let failed = match &a.kept_as_sent {
                Some(KeptAsSent::EstimateFailed(failed)) => {
                    with_reject_figures(FrameRegistration::default(), failed)
                }
                _ => FrameRegistration::default(),
            };
            FrameRegistration {
                verdict,
                reason,
                world_correction: Some(RigidCorrection::from_isometry(&a.world_correction)),
                rotation_deg: Some(a.rotation_deg as f32),
                sensor_shift_m: Some(a.sensor_shift_m as f32),
                max_point_shift_m: Some(a.max_point_shift_m as f32),
                rms_before_m: Some(a.rms_before_m as f32),
                rms_after_m: Some(a.rms_after_m as f32),
                inliers: Some(count(a.inliers)),
                inlier_share: Some(a.inlier_share as f32),
                unconstrained_directions: Some(count(a.unconstrained_directions)),
                iterations: Some(count(a.iterations)),
                near_surface_points: failed.near_surface_points,
                contradicting_points: failed.contradicting_points,
                last_step_m: failed.last_step_m,
                ..record
            }
        }
        Alignment::Rejected(reason) => with_reject_figures(
            FrameRegistration {
                verdict: RegistrationVerdict::Rejected,
                reason: reject_reason(reason),
                ..record
            },
            reason,
        ),
        Alignment::Skipped(skip) => {
            let (reason, near_surface_points) = match *skip {
                SkipReason::Disabled => (RegistrationReason::Disabled, None),
                SkipReason::MapTooSmall { .. } => (RegistrationReason::MapTooSmall, None),
                SkipReason::TooFewPoints { .. } => (RegistrationReason::TooFewPoints, None),
                SkipReason::NewGround { near_surface } => {
                    (RegistrationReason::NewGround, Some(count(near_surface)))
                }
            };
            FrameRegistration {
                verdict: RegistrationVerdict::Skipped,
                reason,
                near_surface_points,
                ..record
            }
        }
    }
}

/// A trolley planner's registration counts by verdict.
pub fn registration_totals(counts: &AlignmentCounts) -> RegistrationTotals {
    RegistrationTotals {
        applied: counts.aligned,
        kept_as_sent: counts.kept_below_resolution + counts.kept_estimate_failed,
        rejected: counts.rejected(),
        skipped: counts.skipped,
    }
}

fn reject_reason(reason: &RejectReason) -> RegistrationReason {
    match reason {
        RejectReason::ContradictsMap { .. } => RegistrationReason::ContradictsMap,
        RejectReason::TooFewInliers { .. } => RegistrationReason::TooFewInliers,
        RejectReason::LowInlierShare { .. } => RegistrationReason::LowInlierShare,
        RejectReason::RmsNotImproved { .. } => RegistrationReason::RmsNotImproved,
        RejectReason::CorrectionTooLarge { .. } => RegistrationReason::CorrectionTooLarge,
        RejectReason::NotConverged { .. } => RegistrationReason::NotConverged,
        RejectReason::Degenerate { .. } => RegistrationReason::Degenerate,
    }
}

/// `record` with the figures of the check that failed.
fn with_reject_figures(record: FrameRegistration, reason: &RejectReason) -> FrameRegistration {
    match *reason {
        RejectReason::ContradictsMap {
            near_surface,
            contradicting,
        } => FrameRegistration {
            near_surface_points: Some(count(near_surface)),
            contradicting_points: Some(count(contradicting)),
            ..record
        },
        RejectReason::TooFewInliers { inliers } => FrameRegistration {
            inliers: Some(count(inliers)),
            ..record
        },
        RejectReason::LowInlierShare { inlier_share } => FrameRegistration {
            inlier_share: Some(inlier_share as f32),
            ..record
        },
        RejectReason::RmsNotImproved {
            rms_before_m,
            rms_after_m,
        } => FrameRegistration {
            rms_before_m: Some(rms_before_m as f32),
            rms_after_m: Some(rms_after_m as f32),
            ..record
        },
        RejectReason::CorrectionTooLarge {
            rotation_deg,
            sensor_shift_m,
        } => FrameRegistration {
            rotation_deg: Some(rotation_deg as f32),
            sensor_shift_m: Some(sensor_shift_m as f32),
            ..record
        },
        RejectReason::NotConverged { last_step_m } => FrameRegistration {
            last_step_m: Some(last_step_m as f32),
            ..record
        },
        RejectReason::Degenerate {
            unconstrained_directions,
        } => FrameRegistration {
            unconstrained_directions: Some(count(unconstrained_directions)),
            ..record
        },
    }
}

fn count(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

#[cfg(test)]
mod tests {
    use glasshouse_register::Aligned;
    use nalgebra::{Isometry3, Vector3};

    use super::*;

    fn aligned(kept_as_sent: Option<KeptAsSent>) -> Alignment {
        Alignment::Aligned(Aligned {
            world_correction: Isometry3::new(
                Vector3::new(0.004, -0.003, 0.001),
                Vector3::new(0.0, 0.0, 0.6f64.to_radians()),
            ),
            kept_as_sent,
            rotation_deg: 0.6,
            sensor_shift_m: 0.007,
            max_point_shift_m: 0.011,
            rms_before_m: 0.004,
            rms_after_m: 0.002,
            inliers: 1500,
            inlier_share: 0.82,
            unconstrained_directions: 1,
            iterations: 6,
        })
    }

    #[test]
    fn an_applied_correction_carries_its_estimate_and_figures() {
        let frame = FrameId::new(5, 9);
        let r = frame_registration(frame, &aligned(None));
        assert_eq!(r.frame, frame);
        assert_eq!(
            (r.verdict, r.reason),
            (RegistrationVerdict::Applied, RegistrationReason::None)
        );
        let correction = r.world_correction.expect("estimate");
        assert!((correction.angle_deg() - 0.6).abs() < 1e-9);
        assert!((correction.translation_m.x - 0.004).abs() < 1e-15);
        assert_eq!((r.iterations, r.inliers), (Some(6), Some(1500)));
        assert_eq!(r.sensor_shift_m, Some(0.007));
        assert_eq!((r.contradicting_points, r.last_step_m), (None, None));
        assert!(r.inserted());
    }

    #[test]
    fn kept_and_rejected_scans_say_why() {
        let failed = RejectReason::NotConverged { last_step_m: 0.002 };
        let kept = frame_registration(
            FrameId::default(),
            &aligned(Some(KeptAsSent::EstimateFailed(failed))),
        );
        assert_eq!(
            (kept.verdict, kept.reason),
            (
                RegistrationVerdict::KeptAsSent,
                RegistrationReason::NotConverged
            )
        );
        assert_eq!(kept.last_step_m, Some(0.002));
        assert!(kept.world_correction.is_some());
        let small = frame_registration(
            FrameId::default(),
            &aligned(Some(KeptAsSent::BelowResolution)),
        );
        assert_eq!(small.reason, RegistrationReason::BelowResolution);

        let rejected = frame_registration(
            FrameId::default(),
            &Alignment::Rejected(RejectReason::ContradictsMap {
                near_surface: 40,
                contradicting: 300,
            }),
        );
        assert_eq!(rejected.verdict, RegistrationVerdict::Rejected);
        assert_eq!(rejected.reason, RegistrationReason::ContradictsMap);
        assert_eq!(
            (rejected.near_surface_points, rejected.contradicting_points),
            (Some(40), Some(300))
        );
        assert_eq!(
            (rejected.world_correction, rejected.rotation_deg),
            (None, None)
        );
        assert!(!rejected.inserted());

        let skipped = frame_registration(
            FrameId::default(),
            &Alignment::Skipped(SkipReason::MapTooSmall {
                occupied_voxels: 12,
            }),
        );
        assert_eq!(
            (skipped.verdict, skipped.reason),
            (
                RegistrationVerdict::Skipped,
                RegistrationReason::MapTooSmall
            )
        );
    }

    #[test]
    fn totals_fold_the_outcomes_by_verdict() {
        let counts = AlignmentCounts {
            aligned: 3,
            kept_below_resolution: 2,
            kept_estimate_failed: 1,
            skipped: 4,
            rejected_contradicts_map: 2,
            rejected_degenerate: 1,
            ..AlignmentCounts::default()
        };
        let totals = registration_totals(&counts);
        assert_eq!(
            totals,
            RegistrationTotals {
                applied: 3,
                kept_as_sent: 3,
                rejected: 3,
                skipped: 4
            }
        );
    }
}
