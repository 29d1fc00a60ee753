//! Red clutter (a red leaf, a clip, a label, a stem) that the fruit evidence turns away by its
//! shape stops drawing ROI-targeted views once scans from several directions have hit it; a
//! fruit is not taken for settled clutter, and with the rule off nothing settles. Found fruit
//! settle by their own rule, and then it is fruit that settles. Once the ROI search stalls
//! (clouds in a row without a new fruit-shaped cluster) plans turn to exploration.
#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_nbv::{Plan, ViewKind};
use glasshouse_pipeline::*;
use glasshouse_proto::FrameId;
use glasshouse_roimap::VoxelKey;
use glasshouse_sim::{FruitTruth, ScenarioKind, WorldSettings};
use glasshouse_simtrolley::*;

/// Drives a planner with `settings` through `frames` views of the realistic world's scenario 2
/// (seed `seed`), calling `after_plan` with the planner and its plan after every frame; the
/// scene's fruits.
fn drive(
    seed: u64,
    frames: u64,
    settings: PlanningSettings,
    mut after_plan: impl FnMut(&mut TrolleyPlanner, &Plan),
) -> Vec<FruitTruth> {
    let mut sim = SimTrolleySettings::new(ScenarioKind::Two, seed, (320, 240), 1.0);
    sim.world = WorldSettings::realistic();
    let mut trolley = SimTrolley::new(sim).unwrap();
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
        after_plan(&mut planner, &plan);
        let goals: Vec<_> = plan.views.iter().map(|v| v.world_from_camera).collect();
        trolley.execute(&goals);
    }
    trolley.scene().fruits().to_vec()
}

/// The settled voxels of a planner after `frames` views of the realistic world's scenario 2
/// (seed `seed`) with clutter settling after `settles_after` directions and fruit after
/// `fruit_settles_after`, and the scene's fruits.
fn settled_after(
    seed: u64,
    frames: u64,
    settles_after: u32,
    fruit_settles_after: u32,
) -> (Vec<VoxelKey>, Vec<FruitTruth>) {
    let settings = PlanningSettings {
        clutter_settles_after_views: settles_after,
        fruit_settles_after_views: fruit_settles_after,
        ..PlanningSettings::default()
    };
    let mut settled = Vec::new();
    let fruits = drive(seed, frames, settings, |planner, _| {
        settled = planner.settled_voxels().to_vec();
    });
    (settled, fruits)
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

/// Per frame of `frames` views of seed `seed` with the search stalled after `after` clouds:
/// the fruit-shaped clusters after the cloud, whether the planner counted the search
/// stalled, and the list the plan took.
fn stalls(seed: u64, frames: u64, after: u32) -> Vec<(usize, bool, ViewKind)> {
    let settings = PlanningSettings {
        explore_after_fruitless_clouds: after,
        ..PlanningSettings::default()
    };
    let mut steps = Vec::new();
    drive(seed, frames, settings, |planner, plan| {
        // Shaped like a fruit, before any fit judges what its solid hides.
        let evidence = planner.settings().fit.evidence;
        let outcomes = planner.cluster_outcomes();
        let fruit_shaped = outcomes
            .iter()
            .filter(|o| o.shape.verdict(&evidence).is_fruit())
            .count();
        steps.push((fruit_shaped, planner.roi_stalled(), plan.used_kind));
    });
    steps
}

#[test]
fn the_search_stalls_after_clouds_without_a_new_fruit_and_then_explores() {
    let after = 3;
    let steps = stalls(5, 30, after);
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
