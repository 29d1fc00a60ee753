//! Red clutter (a red leaf, a clip, a label, a stem) that the fruit evidence turns away by its
//! shape stops drawing ROI-targeted views once scans from several directions have hit it; a
//! fruit is not taken for settled clutter, and with the rule off nothing settles.
#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_geom::Aabb;
use glasshouse_pipeline::*;
use glasshouse_proto::FrameId;
use glasshouse_sim::{FruitTruth, ScenarioKind, WorldSettings};
use glasshouse_simtrolley::*;

/// The settled clutter of a planner after `frames` views of the realistic world's scenario 2
/// (seed `seed`) with `settles_after`, and the scene's fruits.
fn settled_after(seed: u64, frames: u64, settles_after: u32) -> (Vec<Aabb>, Vec<FruitTruth>) {
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

#[test]
fn clutter_seen_from_three_sides_settles_and_no_fruit_does() {
    let (settled, fruits) = settled_after(5, 24, 3);
    assert!(!settled.is_empty(), "no clutter settled");
    for fruit in &fruits {
        let inside = settled.iter().find(|b| b.contains(&fruit.body_centre));
        assert!(
            inside.is_none(),
            "fruit {} settled as clutter: {inside:?}",
            fruit.id
        );
    }
    let (never, _) = settled_after(5, 24, 0);
    assert!(never.is_empty(), "{never:?}");
}
