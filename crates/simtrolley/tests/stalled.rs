//! Plans turn to exploration once the ROI search has stalled: as many clouds in a row as the
//! setting says brought no new fruit-shaped cluster. The count follows the clusters the map
//! holds, and a new fruit-shaped cluster ends the stall.
#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_nbv::ViewKind;
use glasshouse_pipeline::*;
use glasshouse_proto::FrameId;
use glasshouse_sim::{ScenarioKind, WorldSettings};
use glasshouse_simtrolley::*;

/// Per frame of `frames` views of the realistic world's scenario 2 (seed `seed`): the fruit-
/// shaped clusters after the cloud, whether the planner counted the search stalled, and the
/// list the plan took.
fn run(seed: u64, frames: u64, after: u32) -> Vec<(usize, bool, ViewKind)> {
    let mut sim = SimTrolleySettings::new(ScenarioKind::Two, seed, (320, 240), 1.0);
    sim.world = WorldSettings::realistic();
    let mut trolley = SimTrolley::new(sim).unwrap();
    let settings = PlanningSettings {
        explore_after_fruitless_clouds: after,
        ..PlanningSettings::default()
    };
    let mut planner = TrolleyPlanner::new(settings).unwrap();
    planner.set_info(trolley.info()).unwrap();
    let mut steps = Vec::new();
    for seq in 1..=frames {
        let frame = trolley.capture(seq).unwrap().unwrap();
        let id = FrameId::new(0, seq);
        let cloud = detect_frame(&frame, id, "d1", &DetectorConfig::default()).unwrap();
        planner.integrate(&cloud, 0).unwrap();
        let plan = planner
            .plan(&frame.world_from_camera, seq)
            .unwrap()
            .unwrap();
        // Shaped like a fruit, before any fit judges what its solid hides.
        let evidence = planner.settings().fit.evidence;
        let outcomes = planner.cluster_outcomes();
        let fruit_shaped = outcomes
            .iter()
            .filter(|o| o.shape.verdict(&evidence).is_fruit())
            .count();
        steps.push((fruit_shaped, planner.roi_stalled(), plan.used_kind));
        let goals: Vec<_> = plan.views.iter().map(|v| v.world_from_camera).collect();
        trolley.execute(&goals);
    }
    steps
}

#[test]
fn the_search_stalls_after_clouds_without_a_new_fruit_and_then_explores() {
    let after = 3;
    let steps = run(5, 30, after);
    // The stall is exactly "the most fruit-shaped clusters seen has not grown for `after`
    // clouds", recomputed here from the clusters after each cloud.
    let (mut most, mut fruitless) = (0, 0);
    for (i, &(fruit_shaped, stalled, _)) in steps.iter().enumerate() {
        if fruit_shaped > most {
            (most, fruitless) = (fruit_shaped, 0);
        } else {
            fruitless += 1;
        }
        assert_eq!(stalled, fruitless >= after, "frame {}: {steps:?}", i + 1);
    }
    assert!(most > 0, "no fruit found: {steps:?}");
    let stalled: Vec<_> = steps.iter().filter(|s| s.1).collect();
    assert!(!stalled.is_empty(), "never stalled: {steps:?}");
    assert!(
        stalled.iter().any(|s| s.2 == ViewKind::Exploration),
        "stalled but never explored: {steps:?}"
    );
}
