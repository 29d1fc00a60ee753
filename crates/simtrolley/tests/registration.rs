//! Registration in the planner's steps: a simulated trolley with a known calibration error, its
//! clouds aligned to the map before insertion.
#![allow(clippy::unwrap_used)]
use glasshouse_detect::DetectorConfig;
use glasshouse_proto::{FrameId, RoiCloud};
use glasshouse_register::{corrected_points, HandEyeEstimator, HandEyeSettings};
use glasshouse_sim::ScenarioKind;
use glasshouse_sim::WorldSettings;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use glasshouse_pipeline::*;
use glasshouse_simtrolley::{SimTrolley, SimTrolleySettings};

/// Scan-to-map registration on or off, without the hand-eye estimate.
fn settings(registration: bool) -> PlanningSettings {
    let mut settings = PlanningSettings::default();
    settings.registration.enabled = registration;
    settings.hand_eye.enabled = false;
    settings
}

/// The clouds of a perfect simulated trolley's first `frames` views (each view planned on
/// the clouds before it, without registration: the same clouds for every test).
fn clouds(frames: u64) -> Vec<RoiCloud> {
    clouds_in(WorldSettings::default(), 3, frames).0
}

fn planner_with(registration: bool, clouds: &[RoiCloud]) -> TrolleyPlanner {
    let mut planner = TrolleyPlanner::new(settings(registration)).unwrap();
    for cloud in clouds {
        planner.integrate(cloud, 0).unwrap();
    }
    planner
}

/// The cloud as sent by a trolley whose camera is really at `error * believed`.
fn sent_with_error(cloud: &RoiCloud, error: &Isometry3<f64>) -> RoiCloud {
    let to_believed = error.inverse();
    RoiCloud {
        points_in_world: corrected_points(&to_believed, &cloud.points_in_world),
        sensor_origin_in_world: to_believed * cloud.sensor_origin_in_world,
        ..cloud.clone()
    }
}

/// A camera error of `deg` about `axis` through the sensor origin, then `mm` along `dir`.
fn camera_error(cloud: &RoiCloud, (deg, axis): (f64, Vector3<f64>), mm: f64) -> Isometry3<f64> {
    let origin = cloud.sensor_origin_in_world.coords;
    let rotation = UnitQuaternion::from_scaled_axis(axis.normalize() * deg.to_radians());
    let about_origin = Translation3::from(origin - rotation * origin);
    let dir = Vector3::new(0.6, -0.3, 0.74).normalize();
    Translation3::from(dir * mm * 1e-3) * Isometry3::from_parts(about_origin, rotation)
}

/// How far `residual` moves the cloud's points within the map's range, at most.
fn max_shift_m(residual: &Isometry3<f64>, cloud: &RoiCloud) -> f64 {
    let origin = cloud.sensor_origin_in_world;
    let in_range = cloud.points_in_world.iter().map(|p| p.cast::<f64>());
    in_range
        .filter(|p| (p - origin).norm() <= PlanningSettings::default().max_range_m)
        .map(|p| (residual * p - p).norm())
        .fold(0.0, f64::max)
}

#[test]
fn registration_is_off_by_default_and_harmless_in_a_perfect_world() {
    assert!(!PlanningSettings::default().registration.enabled);
    let clouds = clouds(8);
    let (on, off) = (planner_with(true, &clouds), planner_with(false, &clouds));
    // Every cloud went in as sent: the same map, voxel for voxel.
    let counts = on.alignment_counts();
    assert_eq!((counts.aligned, counts.rejected()), (0, 0), "{counts:?}");
    assert_eq!(
        counts.skipped + counts.kept_below_resolution + counts.kept_estimate_failed,
        8
    );
    let voxels = |p: &TrolleyPlanner| p.map().iter().collect::<Vec<_>>();
    assert_eq!(voxels(&on), voxels(&off));
    assert_eq!(off.alignment_counts().skipped, 8);
}

#[test]
fn a_misplaced_camera_is_corrected_before_insertion() {
    let clouds = clouds(8);
    let errors = [
        ((0.5, Vector3::new(-0.7, 0.2, 0.1)), 5.0),
        ((1.0, Vector3::new(0.1, 0.9, -0.3)), 10.0),
    ];
    let (mut before_m, mut after_m) = (0.0, 0.0);
    for k in 2..clouds.len() {
        let planner = planner_with(true, &clouds[..k]);
        for &(rotation, mm) in &errors {
            let error = camera_error(&clouds[k], rotation, mm);
            let sent = sent_with_error(&clouds[k], &error);
            let mut planner = planner.clone();
            assert_eq!(planner.integrate(&sent, 0).unwrap(), FrameVerdict::Fresh);
            let applied = planner.last_alignment().unwrap().correction_to_apply();
            // What is left of the error as the cloud went in.
            let residual = error.inverse() * applied.copied().unwrap_or_default();
            let (before, after) = (max_shift_m(&error, &sent), max_shift_m(&residual, &sent));
            assert!(after <= before * 1.05, "cloud {k}: {before} -> {after} m");
            before_m += before;
            after_m += after;
        }
    }
    // Thin plants constrain some directions weakly (those are left as they were), so not
    // every error is undone; on these clouds it more than halves.
    let n = 2.0 * (clouds.len() - 2) as f64;
    eprintln!(
        "largest point error in range, mean over the clouds: {:.1} -> {:.1} mm",
        before_m / n * 1e3,
        after_m / n * 1e3
    );
    assert!(after_m < 0.5 * before_m, "{before_m} -> {after_m}");
}

#[test]
fn a_wildly_misplaced_cloud_is_not_inserted() {
    let clouds = clouds(8);
    let mut planner = planner_with(true, &clouds[..7]);
    let map_before = planner.map().iter().collect::<Vec<_>>();
    let wild = sent_with_error(&clouds[7], &Isometry3::translation(0.2, 0.0, 0.0));
    assert_eq!(
        planner.integrate(&wild, 0).unwrap(),
        FrameVerdict::Misaligned
    );
    assert!(matches!(
        planner.last_alignment(),
        Some(Alignment::Rejected(_))
    ));
    assert_eq!(planner.alignment_counts().rejected(), 1);
    assert_eq!(planner.map().iter().collect::<Vec<_>>(), map_before);
    // The frame was judged: announced again, it is planned on, not registered again.
    assert_eq!(planner.last_frame(), Some(wild.source_frame()));
    assert_eq!(planner.integrate(&wild, 0).unwrap(), FrameVerdict::Repeat);
    assert_eq!(planner.alignment_counts().rejected(), 1);
}

/// The clouds of a simulated trolley in `world` (seed `seed`) over its first `frames` views,
/// and the trolley's true hand-eye error.
fn clouds_in(world: WorldSettings, seed: u64, frames: u64) -> (Vec<RoiCloud>, Isometry3<f64>) {
    let mut sim = SimTrolleySettings::new(ScenarioKind::Two, seed, (320, 240), 1.0);
    sim.world = world;
    let truth = sim.world.pose.believed_camera_from_true(seed);
    let mut trolley = SimTrolley::new(sim).unwrap();
    let mut planner = TrolleyPlanner::new(settings(false)).unwrap();
    planner.set_info(trolley.info()).unwrap();
    let mut out = Vec::new();
    for seq in 1..=frames {
        let frame = trolley.capture(seq).unwrap().unwrap();
        let cloud = detect_frame(
            &frame,
            FrameId::new(0, seq),
            "d1",
            &DetectorConfig::default(),
        );
        let cloud = cloud.unwrap();
        planner.integrate(&cloud, 0).unwrap();
        let plan = planner.plan(&frame.world_from_camera, seq).unwrap();
        let goals: Vec<_> = plan
            .unwrap()
            .views
            .iter()
            .map(|v| v.world_from_camera)
            .collect();
        trolley.execute(&goals);
        out.push(cloud);
    }
    (out, truth)
}

/// Degrees and millimetres between two hand-eye transforms.
fn apart(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let d = a.inverse() * b;
    (
        d.rotation.angle().to_degrees(),
        d.translation.vector.norm() * 1e3,
    )
}

#[test]
fn the_hand_eye_error_is_estimated_across_scans() {
    // Every imperfection of the realistic world: D435 depth, joint noise, red clutter, lobed
    // fruit; the calibration error at the preset's size and doubled.
    let mut doubled = WorldSettings::realistic();
    doubled.pose.hand_eye_error_deg = 1.0;
    doubled.pose.hand_eye_error_mm = 10.0;
    // Seeds the estimator's settings were not chosen on (those were 3, 5, 7 and 9).
    for (world, seed) in [(WorldSettings::realistic(), 11), (doubled, 13)] {
        let (clouds, truth) = clouds_in(world, seed, 32);
        let mut estimator = HandEyeEstimator::new(HandEyeSettings {
            enabled: true,
            ..HandEyeSettings::default()
        });
        let mut spent = std::time::Duration::ZERO;
        for cloud in &clouds {
            let start = std::time::Instant::now();
            estimator.add_scan(&cloud.world_from_camera, &cloud.points_in_world);
            spent += start.elapsed();
        }
        let before = apart(&Isometry3::identity(), &truth);
        let left = apart(estimator.camera_believed_from_true(), &truth);
        eprintln!(
            "seed {seed}: {before:.2?} -> {left:.3?} (deg, mm), {:?}, {:.1} ms a scan",
            estimator.figures(),
            spent.as_secs_f64() * 1e3 / clouds.len() as f64
        );
        // On seeds 11-19 the rotation left was 0.08-0.33 of the error, the offset 0.02-0.22.
        assert!(left.0 < 0.4 * before.0, "{before:?} -> {left:?}");
        assert!(left.1 < 0.3 * before.1, "{before:?} -> {left:?}");
    }
}

#[test]
fn the_hand_eye_estimate_is_the_same_on_any_number_of_threads() {
    let (clouds, truth) = clouds_in(WorldSettings::realistic(), 5, 12);
    let estimate_on = |threads: usize| {
        let mut estimator = HandEyeEstimator::new(HandEyeSettings::default());
        let mut after_each = Vec::new();
        for cloud in &clouds {
            estimator.add_scan_threaded(&cloud.world_from_camera, &cloud.points_in_world, threads);
            after_each.push((*estimator.camera_believed_from_true(), estimator.figures()));
        }
        after_each
    };
    let one = estimate_on(1);
    // The estimate moved: the comparison is of real work, not of identities.
    let (deg, mm) = apart(&one[one.len() - 1].0, &Isometry3::identity());
    assert!(
        deg > 0.05 && mm > 0.5,
        "{deg} deg, {mm} mm (truth {truth:?})"
    );
    assert!(one.iter().any(|(_, f)| f.matches > 1000), "{one:?}");
    for threads in [2, 3, 7] {
        assert_eq!(estimate_on(threads), one, "{threads} threads");
    }
}

#[test]
fn in_a_perfect_world_the_hand_eye_estimate_stays_near_none() {
    let (clouds, truth) = clouds_in(WorldSettings::default(), 3, 32);
    assert_eq!(truth, Isometry3::identity());
    let mut estimator = HandEyeEstimator::new(HandEyeSettings::default());
    for cloud in &clouds {
        estimator.add_scan(&cloud.world_from_camera, &cloud.points_in_world);
    }
    assert!(estimator.is_final());
    let (deg, mm) = apart(estimator.camera_believed_from_true(), &truth);
    eprintln!("perfect world: {deg:.3} deg, {mm:.2} mm");
    assert!(deg < 0.03 && mm < 0.5, "{deg} deg, {mm} mm");
}

#[test]
fn a_copy_from_a_snapshot_corrects_the_next_scans_as_the_owner_does() {
    let (clouds, _) = clouds_in(WorldSettings::realistic(), 7, 12);
    let defaults = PlanningSettings::default();
    assert!(
        defaults.hand_eye.enabled,
        "the planner estimates it by default"
    );
    let mut owner = TrolleyPlanner::new(defaults.clone()).unwrap();
    for cloud in &clouds[..8] {
        owner.integrate(cloud, 0).unwrap();
    }
    assert!(owner.last_hand_eye_correction().is_some());
    let snapshot = owner.snapshot("t1", "p1").unwrap();
    let carried = snapshot.hand_eye.as_ref().unwrap();
    assert_eq!((carried.scans_seen, carried.scans.len()), (8, 8));
    // Through the wire and back, as a replica gets it.
    let bytes = glasshouse_proto::encode(&Default::default(), &snapshot);
    let (_, snapshot): (_, glasshouse_proto::MapSnapshot) =
        glasshouse_proto::decode_typed(&bytes).unwrap();
    let mut copy = TrolleyPlanner::from_snapshot(defaults.clone(), &snapshot).unwrap();
    let mut fresh = TrolleyPlanner::from_snapshot(
        defaults,
        &glasshouse_proto::MapSnapshot {
            hand_eye: None,
            ..snapshot.clone()
        },
    )
    .unwrap();
    for cloud in &clouds[8..] {
        for planner in [&mut owner, &mut copy, &mut fresh] {
            planner.integrate(cloud, 0).unwrap();
        }
    }
    let voxels = |p: &TrolleyPlanner| p.map().iter().collect::<Vec<_>>();
    assert_eq!(voxels(&copy), voxels(&owner));
    assert_eq!(
        copy.hand_eye().camera_believed_from_true(),
        owner.hand_eye().camera_believed_from_true()
    );
    // Without the estimator's state the copy would correct differently (not yet estimating).
    assert!(fresh.last_hand_eye_correction().is_none());
    assert_ne!(voxels(&fresh), voxels(&owner));
}
