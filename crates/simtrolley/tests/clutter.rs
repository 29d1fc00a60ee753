//! Red clutter (a red leaf, a clip, a label, a stem) that the fruit evidence turns away by its
//! shape stops drawing ROI-targeted views once scans from several directions have hit it; a
//! fruit is not taken for settled clutter, and with the rule off nothing settles.
#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_pipeline::*;
use glasshouse_proto::FrameId;
use glasshouse_roimap::VoxelKey;
use glasshouse_sim::{FruitTruth, ScenarioKind, WorldSettings};
use glasshouse_simtrolley::*;

/// The settled clutter of a planner after `frames` views of the realistic world's scenario 2
/// (seed `seed`) with `settles_after`, and the scene's fruits.
fn settled_after(seed: u64, frames: u64, settles_after: u32) -> (Vec<VoxelKey>, Vec<FruitTruth>) {
    let mut sim = SimTrolleySettings::new(ScenarioKind::Two, seed, (320, 240), 1.0);
    sim.world = WorldSettings::realistic();
    let mut trolley = SimTrolley::new(sim).unwrap();
    let settings = PlanningSettings {
        clutter_settles_after_views: settles_after,
        ..PlanningSettings::default()
    };
    let mut planner = TrolleyPlanner::new(settings).unwrap();
    planner.set_info(trolley.info()).unwrap();
    for seq in 1..=frames {
        let frame = trolley.capture(seq).unwrap().unwrap();
        let id = FrameId::new(0, seq);
        let cloud = detect_frame(&frame, id, "d1", &DetectorConfig::default()).unwrap();
        planner.integrate(&cloud, 0).unwrap();
        let plan = planner
            .plan(&frame.world_from_camera, seq)
            .unwrap()
            .unwrap();
        let goals: Vec<_> = plan.views.iter().map(|v| v.world_from_camera).collect();
        trolley.execute(&goals);
    }
    (
        planner.settled_clutter().to_vec(),
        trolley.scene().fruits().to_vec(),
    )
}

/// The centre of voxel `k` of the planner's 1 cm map.
fn centre_of(k: VoxelKey) -> nalgebra::Point3<f64> {
    let res = PlanningSettings::default().resolution_m;
    nalgebra::Point3::new(
        (f64::from(k.x) + 0.5) * res,
        (f64::from(k.y) + 0.5) * res,
        (f64::from(k.z) + 0.5) * res,
    )
}

#[test]
fn clutter_seen_from_three_sides_settles_and_no_fruit_does() {
    let (settled, fruits) = settled_after(5, 24, 3);
    assert!(!settled.is_empty(), "no clutter settled");
    // No settled voxel lies in any fruit's body box: a fruit's own patches never settle.
    for fruit in &fruits {
        let (lo, hi) = (
            fruit.centre - fruit.half_extents_m,
            fruit.centre + fruit.half_extents_m,
        );
        let in_body = |p: &nalgebra::Point3<f64>| (0..3).all(|i| lo[i] <= p[i] && p[i] <= hi[i]);
        let inside = settled.iter().filter(|&&k| in_body(&centre_of(k))).count();
        assert_eq!(
            inside, 0,
            "fruit {} holds {inside} settled voxels",
            fruit.id
        );
    }
    let (never, _) = settled_after(5, 24, 0);
    assert!(never.is_empty(), "{never:?}");
}
