//! Red clutter (a red leaf, a clip, a label, a stem) that the fruit evidence turns away by its
//! shape stops drawing ROI-targeted views once scans from several directions have hit it; a
//! fruit is not taken for settled clutter, and with the rule off nothing settles. Found fruit
//! settle by their own rule, and then it is fruit that settles.
#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_pipeline::*;
use glasshouse_proto::FrameId;
use glasshouse_roimap::VoxelKey;
use glasshouse_sim::{FruitTruth, ScenarioKind, WorldSettings};
use glasshouse_simtrolley::*;

/// The settled voxels of a planner after `frames` views of the realistic world's scenario 2
/// (seed `seed`) with clutter settling after `settles_after` directions and fruit after
/// `fruit_settles_after`, and the scene's fruits.
fn settled_after(
    seed: u64,
    frames: u64,
    settles_after: u32,
    fruit_settles_after: u32,
) -> (Vec<VoxelKey>, Vec<FruitTruth>) {
    let mut sim = SimTrolleySettings::new(ScenarioKind::Two, seed, (320, 240), 1.0);
    sim.world = WorldSettings::realistic();
    let mut trolley = SimTrolley::new(sim).unwrap();
    let settings = PlanningSettings {
        clutter_settles_after_views: settles_after,
        fruit_settles_after_views: fruit_settles_after,
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
        planner.settled_voxels().to_vec(),
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

/// Whether `p` lies in `fruit`'s body box grown by `margin_m`.
fn in_body(fruit: &FruitTruth, p: &nalgebra::Point3<f64>, margin_m: f64) -> bool {
    let half = fruit.half_extents_m.add_scalar(margin_m);
    let (lo, hi) = (fruit.centre - half, fruit.centre + half);
    (0..3).all(|i| lo[i] <= p[i] && p[i] <= hi[i])
}

#[test]
fn clutter_seen_from_three_sides_settles_and_no_fruit_does() {
    let (settled, fruits) = settled_after(5, 24, 3, 0);
    assert!(!settled.is_empty(), "no clutter settled");
    // No settled voxel lies in any fruit's body box: a fruit's own patches never settle.
    for fruit in &fruits {
        let inside = settled
            .iter()
            .filter(|&&k| in_body(fruit, &centre_of(k), 0.0))
            .count();
        assert_eq!(
            inside, 0,
            "fruit {} holds {inside} settled voxels",
            fruit.id
        );
    }
    let (never, _) = settled_after(5, 24, 0, 0);
    assert!(never.is_empty(), "{never:?}");
}

#[test]
fn found_fruit_seen_from_three_sides_settle() {
    let (settled, fruits) = settled_after(5, 24, 0, 3);
    assert!(!settled.is_empty(), "no fruit settled");
    // What settles is fruit: the settled voxels lie in the fruits' bodies (3 cm margin), but
    // for a cluster 12 cm from any fruit that the evidence takes for one after 24 frames.
    let in_a_fruit = settled
        .iter()
        .filter(|&&k| fruits.iter().any(|f| in_body(f, &centre_of(k), 0.03)))
        .count();
    assert!(
        in_a_fruit * 10 >= settled.len() * 9,
        "{in_a_fruit} of {} settled voxels in a fruit",
        settled.len()
    );
}
