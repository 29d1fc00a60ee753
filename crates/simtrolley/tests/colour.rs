//! Each fruit's observed colour through the loop's steps on a simulated trolley: the detector
//! gives every ROI point its pixels' mean colour, the planner gives each fruit the mean of the
//! points in its voxels, and copies of the planner (from a snapshot, from a store's checkpoint)
//! go on with the same colours.
#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_geom::{Rgb, RgbSum};
use glasshouse_pipeline::*;
use glasshouse_proto::{FrameId, MapSnapshot, RoiCloud, RoiColours};
use glasshouse_sim::ScenarioKind;
use glasshouse_simtrolley::*;

fn sim() -> SimTrolley {
    SimTrolley::new(SimTrolleySettings::new(
        ScenarioKind::Two,
        3,
        (320, 240),
        1.0,
    ))
    .unwrap()
}

fn detect(trolley: &mut SimTrolley, seq: u64) -> RoiCloud {
    let frame = trolley.capture(seq).unwrap().unwrap();
    detect_frame(
        &frame,
        FrameId::new(0, seq),
        "d1",
        &DetectorConfig::default(),
    )
    .unwrap()
}

/// The mean colour of a cloud's ROI points.
fn mean_roi_colour(cloud: &RoiCloud) -> Option<Rgb> {
    let RoiColours::Rgb(colours) = cloud.roi_colours() else {
        return None;
    };
    let mut sum = RgbSum::default();
    colours.iter().for_each(|&c| sum.add(Rgb::from(c)));
    sum.mean()
}

/// A planner that took `frames` frames of the loop: capture, detect, integrate, plan, and the
/// trolley moved to the first view it reaches; with the clouds it took.
fn planner_after(trolley: &mut SimTrolley, frames: u64) -> (TrolleyPlanner, Vec<RoiCloud>) {
    let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    planner.set_info(trolley.info()).unwrap();
    let mut clouds = Vec::new();
    for seq in 1..=frames {
        let cloud = detect(trolley, seq);
        planner.integrate(&cloud, 0).unwrap();
        clouds.push(cloud);
        let plan = planner
            .plan(&trolley.world_from_camera(), seq)
            .unwrap()
            .unwrap();
        let poses: Vec<_> = plan.views.iter().map(|v| v.world_from_camera).collect();
        trolley.execute(&poses);
    }
    (planner, clouds)
}

fn colours_by_id(planner: &mut TrolleyPlanner) -> Vec<(u32, Option<Rgb>)> {
    planner.fruits().iter().map(|f| (f.id, f.colour)).collect()
}

#[test]
fn the_detector_gives_each_roi_point_its_pixels_colour_red_for_red_fruit() {
    let cloud = detect(&mut sim(), 1);
    let roi_points = cloud.roi.iter().filter(|&&r| r).count();
    assert!(roi_points > 100, "{roi_points} ROI points");
    let RoiColours::Rgb(colours) = cloud.roi_colours() else {
        panic!("no colours: {:?}", cloud.roi_colours());
    };
    assert_eq!(colours.len(), roi_points);
    let mean = mean_roi_colour(&cloud).unwrap();
    assert!(mean.is_red_dominant(60), "{mean:?}");
    // Point by point: red the largest channel of nearly every one.
    let red = colours.iter().filter(|c| Rgb::from(**c).is_red_dominant(0));
    assert!(red.count() * 100 >= colours.len() * 95);
}

#[test]
fn the_planner_reports_each_fruit_red_as_the_points_in_its_voxels() {
    let (mut planner, clouds) = planner_after(&mut sim(), 8);
    let fruits = planner.fruits();
    assert!(fruits.len() >= 2, "{} fruits", fruits.len());
    for f in &fruits {
        let colour = f
            .colour
            .unwrap_or_else(|| panic!("fruit {} has no colour", f.id));
        assert!(colour.is_red_dominant(40), "fruit {}: {colour:?}", f.id);
    }
    // Not one cloud's colour: each fruit's own mean (the fruits differ).
    let distinct: std::collections::HashSet<_> = fruits.iter().map(|f| f.colour).collect();
    assert!(distinct.len() > 1, "{distinct:?}");
    assert!(clouds.iter().all(|c| mean_roi_colour(c).is_some()));
}

#[test]
fn clouds_without_colours_or_with_a_wrong_length_give_fruit_without_colour() {
    let mut trolley = sim();
    let clouds: Vec<_> = (1..=3).map(|seq| detect(&mut trolley, seq)).collect();
    for strip in [0, 1] {
        let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
        for cloud in &clouds {
            let mut cloud = cloud.clone();
            // An older detector sends none; a broken one a byte short.
            match strip {
                0 => cloud.roi_rgb.clear(),
                _ => cloud.roi_rgb.truncate(cloud.roi_rgb.len() - 1),
            }
            planner.integrate(&cloud, 0).unwrap();
        }
        let fruits = planner.fruits();
        assert!(!fruits.is_empty());
        assert!(fruits.iter().all(|f| f.colour.is_none()), "{fruits:?}");
    }
}

/// The snapshot with every tracked fruit's colour samples forgotten.
fn without_colours(snapshot: &MapSnapshot) -> MapSnapshot {
    let mut stripped = snapshot.clone();
    for f in &mut stripped.tracked_fruits {
        f.colour = RgbSum::default();
    }
    stripped
}

#[test]
fn colours_survive_a_snapshot_and_a_stores_checkpoint() {
    let mut trolley = sim();
    let (mut planner, _) = planner_after(&mut trolley, 4);
    let settings = planner.settings().clone();
    let snapshot = planner.snapshot("t1", "p1").unwrap();
    let samples: u64 = snapshot
        .tracked_fruits
        .iter()
        .map(|f| f.colour.samples)
        .sum();
    assert!(samples > 0, "the snapshot carries the colour samples");
    let mut copy = TrolleyPlanner::from_snapshot(settings.clone(), &snapshot).unwrap();
    let mut forgetful =
        TrolleyPlanner::from_snapshot(settings.clone(), &without_colours(&snapshot)).unwrap();
    let stored = planner.checkpoint("t1", "p1", 0);
    let blocks = stored.blocks.iter().map(|(_, b)| b.as_slice());
    let mut restored = TrolleyPlanner::from_stored(settings, &stored.meta, blocks).unwrap();
    // The next cloud into each: the copies report what the original does.
    let next = detect(&mut trolley, 5);
    for p in [&mut planner, &mut copy, &mut forgetful, &mut restored] {
        p.integrate(&next, 0).unwrap();
    }
    let original = colours_by_id(&mut planner);
    assert!(
        original.iter().filter(|(_, c)| c.is_some()).count() >= 2,
        "{original:?}"
    );
    assert_eq!(colours_by_id(&mut copy), original);
    assert_eq!(colours_by_id(&mut restored), original);
    // Without the samples the copy knows only the last cloud's: the check can fail.
    assert_ne!(colours_by_id(&mut forgetful), original);
}
