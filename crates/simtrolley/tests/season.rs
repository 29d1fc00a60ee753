//! A trolley's visits on the planner's copy: a new visit starts on the previous visit's map made
//! into a prior, and each fruit keeps its season id and history, through snapshots too.
#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_pipeline::*;
use glasshouse_proto::FrameId;
use glasshouse_roimap::PriorRules;
use glasshouse_sim::ScenarioKind;
use glasshouse_simtrolley::*;

/// A planner that integrated three frames of scenario 2's first view, and its fruits.
fn planner_with_fruit() -> (TrolleyPlanner, Vec<glasshouse_geom::FruitEstimate>) {
    let mut trolley = SimTrolley::new(SimTrolleySettings::new(
        ScenarioKind::Two,
        3,
        (320, 240),
        1.0,
    ))
    .unwrap();
    let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    planner.set_info(trolley.info()).unwrap();
    let detector = DetectorConfig::default();
    for seq in 1..=3 {
        let frame = trolley.capture(seq).unwrap().unwrap();
        let cloud = detect_frame(&frame, FrameId::new(0, seq), "d", &detector).unwrap();
        planner.integrate(&cloud, 0).unwrap();
    }
    let fruits = planner.fruits();
    (planner, fruits)
}

#[test]
fn a_new_visit_starts_on_a_prior_and_keeps_the_fruits_histories() {
    let (mut planner, seen) = planner_with_fruit();
    assert!(!seen.is_empty(), "no fruit in the first view");
    let known_before = planner.map().counts().known;
    assert!(!planner.start_visit(0, &PriorRules::default()).unwrap());
    assert!(planner.start_visit(1, &PriorRules::default()).unwrap());
    assert_eq!(planner.visit(), 1);
    assert!(planner.fruits().is_empty(), "no fruit on the prior's word");
    let known = planner.map().counts().known;
    assert!(
        known > 0 && known < known_before,
        "{known} of {known_before}"
    );
    assert_eq!(planner.last_frame(), None);
    // Not seen yet on this visit: the first visit's fruits, each with one record.
    let histories = planner.season_histories(&[]);
    assert_eq!(histories.len(), seen.len());
    assert!(histories
        .iter()
        .all(|h| h.fruit_id == 0 && h.visits.len() == 1 && h.visits[0].visit == 0));
    // Seen again: the same season ids, a record of this visit each, this visit's fruit ids.
    let again = planner.season_histories(&seen);
    assert_eq!(again.len(), seen.len());
    for (h, before) in again.iter().zip(&histories) {
        assert_eq!(h.season_id, before.season_id);
        assert_eq!(h.visits.len(), 2);
        assert_eq!(h.visits[1].visit, 1);
        assert!(seen.iter().any(|f| f.id == h.fruit_id));
    }
    // A snapshot (and so a store's checkpoint and a replica) carries the visit and histories.
    let snapshot = planner.snapshot("t1", "p1").unwrap();
    assert_eq!(snapshot.visit, 1);
    let copy = TrolleyPlanner::from_snapshot(planner.settings().clone(), &snapshot).unwrap();
    assert_eq!(copy.visit(), 1);
    assert_eq!(copy.season_histories(&seen), again);
    // A bad prior rule is refused, nothing changed.
    let bad = PriorRules {
        fruit_below_threshold_logodds: 0.0,
        ..PriorRules::default()
    };
    assert!(planner.start_visit(2, &bad).is_err());
    assert_eq!(planner.visit(), 1);
}

#[test]
fn a_revisit_aims_at_the_previous_visits_fruit_until_a_scan_looks_there() {
    let (mut planner, _) = planner_with_fruit();
    let roi_voxels = planner.map().roi_voxels().len();
    planner.start_visit(1, &PriorRules::default()).unwrap();
    let remembered = planner.remembered_fruit().len();
    assert_eq!(remembered, roi_voxels, "every fruit voxel is remembered");
    let mut trolley = SimTrolley::new(SimTrolleySettings::new(
        ScenarioKind::Two,
        3,
        (320, 240),
        1.0,
    ))
    .unwrap();
    // The map is empty but for the hints: the plan aims at them.
    let pose = trolley.world_from_camera();
    let plan = planner.plan(&pose, 1).unwrap().unwrap();
    assert!(plan.roi_targets > 0, "no remembered fruit in the region");
    assert_eq!(plan.used_kind, glasshouse_nbv::ViewKind::Roi);
    // A copy of the visit made from a snapshot remembers the same.
    let snapshot = planner.snapshot("t1", "p1").unwrap();
    let copy = TrolleyPlanner::from_snapshot(planner.settings().clone(), &snapshot).unwrap();
    assert_eq!(copy.remembered_fruit(), planner.remembered_fruit());
    // A scan of the same view touches the fruit it sees: those are no longer targets.
    let frame = trolley.capture(1).unwrap().unwrap();
    let cloud = detect_frame(&frame, FrameId::new(0, 1), "d", &DetectorConfig::default()).unwrap();
    planner.integrate(&cloud, 0).unwrap();
    let left = planner.remembered_fruit().len();
    assert!(left < remembered / 2, "{left} of {remembered} left");
    // None is left inside a fruit found again (its grown surface hides the old one).
    let found = planner.fruits();
    assert!(!found.is_empty());
    let inside = |k: &glasshouse_roimap::VoxelKey, f: &glasshouse_geom::FruitEstimate| {
        let p = planner.map().centre_of(*k);
        (0..3).all(|i| f.min[i] <= p[i] && p[i] <= f.max[i])
    };
    assert!(!planner
        .remembered_fruit()
        .iter()
        .any(|k| found.iter().any(|f| inside(k, f))));
}

#[test]
fn a_visits_first_map_update_replaces_the_last_visits_voxels() {
    use glasshouse_proto::VoxelState;
    use glasshouse_roimap::{Occupancy, VoxelKey};
    let (mut planner, _) = planner_with_fruit();
    let first = planner.map_update(3, "p1");
    assert!(!first.full && first.voxels.iter().any(|v| v.state == VoxelState::Roi));
    planner.start_visit(1, &PriorRules::default()).unwrap();
    let solid_cells = planner
        .map()
        .solid_blocks()
        .filter(|(_, m)| m.iter().any(|&w| w != 0));
    assert_eq!(solid_cells.count(), 0, "a prior holds no solid voxel");
    let mut trolley = SimTrolley::new(SimTrolleySettings::new(
        ScenarioKind::Two,
        3,
        (320, 240),
        1.0,
    ))
    .unwrap();
    let frame = trolley.capture(1).unwrap().unwrap();
    let cloud = detect_frame(&frame, FrameId::new(0, 1), "d", &DetectorConfig::default()).unwrap();
    planner.integrate(&cloud, 0).unwrap();
    // The visit's first update is the whole map: every solid voxel, nothing else.
    let update = planner.map_update(1, "p1");
    assert!(update.full);
    let mut sent: Vec<[i32; 3]> = update.voxels.iter().map(|v| v.key).collect();
    assert!(update.voxels.iter().all(|v| v.state != VoxelState::Free));
    let map = planner.map();
    let mut solid: Vec<[i32; 3]> = map
        .iter()
        .map(|(k, _)| k)
        .filter(|&k| map.occupancy(k) == Occupancy::Occupied || map.is_roi(k))
        .map(|k: VoxelKey| [k.x, k.y, k.z])
        .collect();
    sent.sort_unstable();
    solid.sort_unstable();
    assert!(!solid.is_empty());
    assert_eq!(sent, solid);
    // The next ones are changes again.
    assert!(!planner.map_update(2, "p1").full);
}

/// Integrates frames `seqs` of `trolley` (its view does not change between them).
fn integrate(planner: &mut TrolleyPlanner, trolley: &mut SimTrolley, seqs: std::ops::Range<u64>) {
    let detector = DetectorConfig::default();
    for seq in seqs {
        let frame = trolley.capture(seq).unwrap().unwrap();
        let cloud = detect_frame(&frame, FrameId::new(0, seq), "d", &detector).unwrap();
        planner.integrate(&cloud, 0).unwrap();
    }
}

#[test]
fn a_revisits_growth_is_measured_on_one_shape_against_what_a_snapshot_carries() {
    let settings = SimTrolleySettings::new(ScenarioKind::Two, 3, (320, 240), 1.0);
    let mut trolley = SimTrolley::new(settings).unwrap();
    let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    planner.set_info(trolley.info()).unwrap();
    integrate(&mut planner, &mut trolley, 1..4);
    let fitted = planner
        .fruits()
        .iter()
        .filter(|f| f.solid.is_some())
        .count();
    assert!(fitted > 0, "no fitted fruit in the first view");
    assert!(planner.start_visit(1, &PriorRules::default()).unwrap());
    // Each fitted fruit's surface is kept for the next visit, and a snapshot carries it.
    let committed = planner.committed_season();
    let surfaces: Vec<_> = committed
        .iter()
        .filter_map(|h| h.last_surface.as_ref())
        .collect();
    assert_eq!(surfaces.len(), fitted);
    assert!(
        surfaces.iter().all(|s| s.points_m.len() >= 12),
        "too few points"
    );
    let snapshot = planner.snapshot("t1", "p1").unwrap();
    let mut copy = TrolleyPlanner::from_snapshot(planner.settings().clone(), &snapshot).unwrap();
    let carried = copy.committed_season();
    for (a, b) in committed.iter().zip(&carried) {
        let (a, b) = (a.last_surface.as_ref(), b.last_surface.as_ref());
        assert_eq!(a.map(|s| s.points_m.len()), b.map(|s| s.points_m.len()));
    }
    // The same view again (the fruits did not grow): owner and copy measure a ratio near 1
    // for every fruit seen on both visits, and the same one.
    let mut again = SimTrolley::new(settings).unwrap();
    integrate(&mut planner, &mut trolley, 4..7);
    integrate(&mut copy, &mut again, 4..7);
    assert!(planner.start_visit(2, &PriorRules::default()).unwrap());
    assert!(copy.start_visit(2, &PriorRules::default()).unwrap());
    let ratios = |p: &TrolleyPlanner| -> Vec<f64> {
        let season = p.committed_season();
        let on_visit_1 = season
            .iter()
            .flat_map(|h| h.visits.iter().filter(|v| v.visit == 1));
        on_visit_1.filter_map(|v| v.volume_ratio).collect()
    };
    let (owner, copied) = (ratios(&planner), ratios(&copy));
    assert!(!owner.is_empty(), "no growth measured");
    assert!(owner.iter().all(|r| (r - 1.0).abs() < 0.1), "{owner:?}");
    assert_eq!(owner.len(), copied.len());
    for (a, b) in owner.iter().zip(&copied) {
        assert!((a - b).abs() < 1e-3, "{owner:?} against {copied:?}");
    }
}

#[test]
fn a_map_kept_under_other_ray_rules_is_carried_on_with_the_planners() {
    let (planner, _) = planner_with_fruit();
    let snapshot = planner.snapshot("t1", "p1").unwrap();
    let defaults = planner.settings().clone();
    // Settings changed since the map was kept: the map is adopted, later clouds follow them.
    let changed = PlanningSettings {
        max_range_m: 1.5,
        merge_far_rays: !defaults.merge_far_rays,
        ..defaults.clone()
    };
    let copy = TrolleyPlanner::from_snapshot(changed, &snapshot).unwrap();
    assert_eq!(copy.map().config().max_range_m, Some(1.5));
    assert_eq!(copy.map().config().merge_far_rays, !defaults.merge_far_rays);
    assert_eq!(copy.map().len(), planner.map().len());
    assert_eq!(copy.map().scans_inserted(), planner.map().scans_inserted());
    // Another voxel size cannot be carried on: a clear error.
    let coarser = PlanningSettings {
        resolution_m: 0.02,
        ..defaults
    };
    let refused = TrolleyPlanner::from_snapshot(coarser, &snapshot);
    assert!(
        matches!(&refused, Err(PlanningError::Snapshot(m)) if m.contains("0.02 m")),
        "{:?}",
        refused.err()
    );
}
