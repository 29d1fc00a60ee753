//! The fruit rule on synthetic scans of fruit and of the red things the colour detector
//! believes.

#![allow(clippy::unwrap_used)]

use glasshouse_roimap::{RoiCluster, RoiMap};
use nalgebra::{Point3, Rotation3, Vector3};

use super::*;
use crate::fit::fit_ellipsoid;
use crate::fit::tests_support::{centre, clean_scan_config, map, scan_with};
use crate::test_bodies::{capsicum, first_hit, turn, Cuboid, Cylinder, Lobe};
use crate::FruitTracker;

/// Eyes 0.4 m from `aim` in the directions `towards` (from the body to the eye).
fn eyes(aim: Point3<f64>, towards: &[Vector3<f64>]) -> Vec<Point3<f64>> {
    towards.iter().map(|t| aim + t.normalize() * 0.4).collect()
}

/// Scans `hit` from each eye, noting each scan in a tracker; the largest cluster (of any size),
/// the map and the view directions the tracker counted for it.
fn scanned(
    eyes: &[Point3<f64>],
    hit: impl Fn(&Point3<f64>, &Vector3<f64>) -> Option<f64>,
) -> (RoiMap, RoiCluster, u32) {
    let mut m = map();
    let mut tracker = FruitTracker::default();
    for eye in eyes {
        let hits = scan_with(&mut m, centre(), *eye, &hit);
        tracker.note_scan(*eye, hits.iter().map(|p| m.key_of(p)).collect());
    }
    let (cluster, views) = largest(&m, &mut tracker);
    (m, cluster, views)
}

/// The map's largest cluster (of any size) and the view directions the tracker counted for it.
fn largest(m: &RoiMap, tracker: &mut FruitTracker) -> (RoiCluster, u32) {
    let clusters = m.clusters(1);
    let estimates = tracker.update(&clusters);
    let largest = (0..clusters.len())
        .max_by_key(|&i| clusters[i].voxels.len())
        .unwrap();
    (
        clusters[largest].clone(),
        estimates[largest].view_directions,
    )
}

/// What the fruit rule says of the map's largest cluster.
fn judged_largest(m: &RoiMap, tracker: &mut FruitTracker) -> FruitEvidence {
    judged_largest_with(m, tracker, &EvidenceConfig::default())
}

fn judged_largest_with(
    m: &RoiMap,
    tracker: &mut FruitTracker,
    config: &EvidenceConfig,
) -> FruitEvidence {
    let (cluster, views) = largest(m, tracker);
    judged_with(m, &cluster, views, config)
}

fn judged(m: &RoiMap, cluster: &RoiCluster, views: u32) -> FruitEvidence {
    judged_with(m, cluster, views, &EvidenceConfig::default())
}

fn judged_with(
    m: &RoiMap,
    cluster: &RoiCluster,
    views: u32,
    config: &EvidenceConfig,
) -> FruitEvidence {
    let fit = fit_ellipsoid(m, cluster, &clean_scan_config());
    let seen = ClusterEvidence::of(m, cluster);
    let inside = Interior::of_fruit(m, &fit);
    FruitEvidence::judge(&seen, &fit, inside, views, config)
}

/// Front, the two sides and the back of a body facing −x, slightly from above and below.
fn all_round() -> Vec<Vector3<f64>> {
    vec![
        Vector3::new(-1.0, 0.1, 0.2),
        Vector3::new(-1.0, -0.6, -0.1),
        Vector3::new(-0.7, 0.7, 0.3),
        Vector3::new(1.0, 0.2, 0.1),
        Vector3::new(0.8, -0.5, -0.2),
        Vector3::new(-0.2, 0.1, 1.0),
    ]
}

#[test]
fn a_flat_red_leaf_seen_many_times_is_rejected() {
    // A 6 x 4 cm disc, 1 mm thick, tilted 35° back and turned 20°.
    let leaf = Lobe {
        centre: centre(),
        world_from_lobe: turn(Vector3::z(), 20.0) * turn(Vector3::y(), 55.0),
        semi_axes_m: Vector3::new(0.03, 0.02, 0.0005),
    };
    let (m, cluster, views) = scanned(&eyes(centre(), &all_round()), |o, d| leaf.hit(o, d));
    let evidence = judged(&m, &cluster, views);
    assert!(views >= 3, "{views}");
    assert_eq!(evidence.verdict, Verdict::Flat, "{evidence:?}");
    assert!(evidence.shape.bulge < 0.08, "{evidence:?}");
    assert_eq!(evidence.confidence, 0.0);
}

/// A 6.4 x 4.8 cm red leaf lying nearly flat (tilted 8°), `offset_m` along its normal from the
/// scene's centre: where a view with a pose error of that much along the normal sees it.
fn leaf(offset_m: f64) -> Lobe {
    let tilt = turn(Vector3::new(1.0, 0.3, 0.0), 8.0);
    Lobe {
        centre: centre() + tilt * Vector3::z() * offset_m,
        world_from_lobe: tilt,
        semi_axes_m: Vector3::new(0.032, 0.024, 0.0005),
    }
}

/// A red leaf lying nearly flat with its red petiole hanging below, seen from above and below by
/// a camera whose views disagree by 4 mm along the leaf's normal (a 0.5° hand-eye error at 0.4
/// m), so that the leaf comes out two voxels thick in places: still flat. (Views 7 mm or more
/// apart make a leaf a 2 cm deep patch, which the rule takes for fruit.)
#[test]
fn a_red_leaf_two_voxels_thick_with_its_petiole_is_rejected() {
    let c = centre();
    let petiole = Cylinder {
        centre: c - Vector3::z() * 0.02,
        world_from_cylinder: Rotation3::identity(),
        radius_m: 0.0025,
        length_m: 0.04,
    };
    let (above, below) = (leaf(0.0), leaf(0.004));
    let eyes_above = eyes(
        c,
        &[Vector3::new(-0.5, 0.2, 1.0), Vector3::new(0.4, -0.6, 1.0)],
    );
    let eyes_below = eyes(
        c,
        &[Vector3::new(-0.6, 0.1, -1.0), Vector3::new(0.5, 0.5, -1.0)],
    );
    let mut m = map();
    let mut tracker = FruitTracker::default();
    for (eye, sheet) in eyes_above
        .iter()
        .map(|e| (e, above))
        .chain(eyes_below.iter().map(|e| (e, below)))
    {
        let hit = |o: &Point3<f64>, d: &Vector3<f64>| {
            [sheet.hit(o, d), petiole.hit(o, d)]
                .into_iter()
                .flatten()
                .min_by(f64::total_cmp)
        };
        let hits = scan_with(&mut m, c, *eye, hit);
        tracker.note_scan(*eye, hits.iter().map(|p| m.key_of(p)).collect());
    }
    let evidence = judged_largest(&m, &mut tracker);
    assert_eq!(evidence.verdict, Verdict::Flat, "{evidence:?}");
}

/// The leaf above, but the views below see it 12 mm nearer the views above (a pose error of a
/// degree or a centimetre, or a stereo camera's correlated error): a 2 cm deep red patch whose
/// shape passes for a fruit's cap. The views below see through where the views above saw the
/// leaf, so nothing inside the solid fitted to it is unknown: a sheet, not a fruit.
#[test]
fn a_red_leaf_doubled_by_a_pose_error_hides_nothing() {
    let c = centre();
    let (above, below) = (leaf(0.0), leaf(0.012));
    let towards_above = [Vector3::new(-0.5, 0.2, 1.0), Vector3::new(0.4, -0.6, 1.0)];
    let towards_below = [Vector3::new(-0.6, 0.1, -1.0), Vector3::new(0.5, 0.5, -1.0)];
    let mut m = map();
    let mut tracker = FruitTracker::default();
    let scans = eyes(c, &towards_above)
        .into_iter()
        .map(|e| (e, above))
        .chain(eyes(c, &towards_below).into_iter().map(|e| (e, below)));
    for (eye, sheet) in scans {
        let hits = scan_with(&mut m, c, eye, |o, d| sheet.hit(o, d));
        tracker.note_scan(eye, hits.iter().map(|p| m.key_of(p)).collect());
    }
    let evidence = judged_largest(&m, &mut tracker);
    let config = EvidenceConfig::default();
    assert_eq!(
        evidence.shape.verdict(&config),
        Verdict::Fruit,
        "{evidence:?}"
    );
    assert_eq!(evidence.interior.unknown, 0, "{evidence:?}");
    assert_eq!(evidence.verdict, Verdict::Sheet, "{evidence:?}");
    assert_eq!(evidence.confidence, 0.0);
    let off = EvidenceConfig {
        min_unknown_inside: 0,
        ..config
    };
    assert!(
        interior_holds(&evidence.interior, &evidence.shape, &off),
        "0 turns the test off"
    );
}

/// A fruit hides its inside from every side: seen all round, the voxels deep inside the solid
/// fitted to it are still unknown.
#[test]
fn a_fruit_seen_all_round_hides_its_inside() {
    let body = capsicum(centre(), 4, 25.0, Vector3::new(0.024, 0.022, 0.04));
    let (m, cluster, views) = scanned(&eyes(centre(), &all_round()), |o, d| first_hit(&body, o, d));
    let evidence = judged(&m, &cluster, views);
    assert!(views >= 4, "{views}");
    assert!(evidence.interior.unknown >= 20, "{evidence:?}");
    assert_eq!(evidence.verdict, Verdict::Fruit, "{evidence:?}");
}

/// The capsicum above, each view seeing it 2-3.5 cm away from where the others do (a 1° and
/// 10 mm hand-eye error with a stereo camera's correlated error on top): the smeared skin fills
/// the solid fitted to it, so it hides nothing, but it is round, so where round bodies may pass
/// it is still a fruit. By default (the hand-eye estimate undoes such an error) it is a sheet.
#[test]
fn a_fruit_smeared_by_pose_errors_is_round_though_it_hides_nothing() {
    let shifts = [
        Vector3::new(0.024, -0.016, 0.012),
        Vector3::new(-0.020, 0.024, -0.008),
        Vector3::new(0.008, 0.020, 0.024),
        Vector3::new(-0.024, -0.012, 0.020),
        Vector3::new(0.016, 0.008, -0.028),
        Vector3::new(-0.012, -0.024, -0.020),
    ];
    let mut m = map();
    let mut tracker = FruitTracker::default();
    for (eye, shift) in eyes(centre(), &all_round()).into_iter().zip(shifts) {
        let body = capsicum(centre() + shift, 4, 25.0, Vector3::new(0.024, 0.022, 0.04));
        let hits = scan_with(&mut m, centre(), eye, |o, d| first_hit(&body, o, d));
        tracker.note_scan(eye, hits.iter().map(|p| m.key_of(p)).collect());
    }
    let round_bodies = EvidenceConfig {
        round_bodies: true,
        ..EvidenceConfig::default()
    };
    let evidence = judged_largest_with(&m, &mut tracker, &round_bodies);
    assert_eq!(evidence.interior.unknown, 0, "{evidence:?}");
    assert!(evidence.shape.is_round(&round_bodies));
    assert_eq!(evidence.verdict, Verdict::Fruit, "{evidence:?}");
    let by_default = EvidenceConfig::default();
    assert!(!interior_holds(
        &evidence.interior,
        &evidence.shape,
        &by_default
    ));
    assert_eq!(
        judged_largest(&m, &mut tracker).verdict,
        Verdict::Sheet,
        "by default"
    );
}

#[test]
fn a_red_label_is_rejected() {
    // A 5 x 3 cm label, 2 mm thick, hanging tilted.
    let label = Cuboid {
        centre: centre(),
        world_from_box: turn(Vector3::new(1.0, 1.0, 0.0), 25.0),
        half_m: Vector3::new(0.001, 0.025, 0.015),
    };
    let (m, cluster, views) = scanned(&eyes(centre(), &all_round()[..3]), |o, d| label.hit(o, d));
    assert_eq!(judged(&m, &cluster, views).verdict, Verdict::Flat);
}

#[test]
fn a_red_clip_is_too_small() {
    // 1.5 x 1 x 3 cm, at two tilts, seen all round.
    for tilt in [0.0, 40.0] {
        let clip = Cuboid {
            centre: centre(),
            world_from_box: turn(Vector3::new(1.0, 0.3, 0.2), tilt),
            half_m: Vector3::new(0.0075, 0.005, 0.015),
        };
        let (m, cluster, views) = scanned(&eyes(centre(), &all_round()), |o, d| clip.hit(o, d));
        let evidence = judged(&m, &cluster, views);
        assert_eq!(evidence.verdict, Verdict::TooSmall, "{tilt}: {evidence:?}");
    }
}

#[test]
fn a_red_stem_is_thin() {
    // 8 mm thick, 10 cm long, upright and leaning 35°.
    for lean in [0.0, 35.0] {
        let stem = Cylinder {
            centre: centre(),
            world_from_cylinder: turn(Vector3::new(0.3, 1.0, 0.0), lean),
            radius_m: 0.004,
            length_m: 0.1,
        };
        let (m, cluster, views) = scanned(&eyes(centre(), &all_round()), |o, d| stem.hit(o, d));
        let evidence = judged(&m, &cluster, views);
        assert_eq!(evidence.verdict, Verdict::Thin, "{lean}: {evidence:?}");
    }
}

#[test]
fn fruit_seen_from_one_side_is_kept_and_from_two_sides_is_surer() {
    let c = centre();
    let round = Vector3::new(0.024, 0.022, 0.04);
    let small = [Lobe {
        centre: c,
        world_from_lobe: Rotation3::identity(),
        semi_axes_m: Vector3::new(0.025, 0.025, 0.03),
    }];
    let bodies = [
        ("capsicum", capsicum(c, 4, 25.0, round)),
        ("3 lobes", capsicum(c, 3, 10.0, round)),
        ("small fruit", small.to_vec()),
    ];
    let front = Vector3::new(-1.0, -0.2, 0.15);
    let side = Vector3::new(0.1, 1.0, 0.1);
    for (name, body) in bodies {
        for one in [front, side, Vector3::new(-0.5, -0.5, 0.7)] {
            let (m, cluster, views) = scanned(&eyes(c, &[one]), |o, d| first_hit(&body, o, d));
            let evidence = judged(&m, &cluster, views);
            assert_eq!(views, 1);
            assert!(evidence.is_fruit(), "{name} from {one:?}: {evidence:?}");
            assert!(evidence.shape.bulge > 0.2, "{name}: {evidence:?}");
            assert!(
                (0.55..0.85).contains(&evidence.confidence),
                "{name}: {evidence:?}"
            );
        }
        let (m, one_cluster, _) = scanned(&eyes(c, &[front]), |o, d| first_hit(&body, o, d));
        let one = judged(&m, &one_cluster, 1);
        let (m, cluster, views) = scanned(&eyes(c, &[front, side]), |o, d| first_hit(&body, o, d));
        let two = judged(&m, &cluster, views);
        assert_eq!(views, 2);
        assert!(two.is_fruit(), "{name}: {two:?}");
        assert!(
            two.confidence > one.confidence + 0.05,
            "{name}: {one:?} {two:?}"
        );
    }
}

#[test]
fn the_tracker_counts_distinct_directions_and_keeps_them_with_the_id() {
    let fruit = Lobe {
        centre: centre(),
        world_from_lobe: Rotation3::identity(),
        semi_axes_m: Vector3::repeat(0.035),
    };
    let mut m = map();
    let mut tracker = FruitTracker::default();
    let note = |m: &mut RoiMap, tracker: &mut FruitTracker, towards: Vector3<f64>| {
        let eye = eyes(centre(), &[towards])[0];
        let hits = scan_with(m, centre(), eye, |o, d| fruit.hit(o, d));
        tracker.note_scan(eye, hits.iter().map(|p| m.key_of(p)).collect());
        tracker.update(&m.clusters(10))
    };
    let first = note(&mut m, &mut tracker, Vector3::new(-1.0, 0.0, 0.0));
    assert_eq!(first[0].view_directions, 1);
    // 20° away: the same side.
    let near = note(&mut m, &mut tracker, Vector3::new(-1.0, 0.36, 0.0));
    assert_eq!((near[0].id, near[0].view_directions), (first[0].id, 1));
    // 90° away: a second side; kept by the next update without scans.
    let side = note(&mut m, &mut tracker, Vector3::new(0.0, 1.0, 0.0));
    assert_eq!(side[0].view_directions, 2);
    assert_eq!(tracker.update(&m.clusters(10))[0].view_directions, 2);
    // A scan that missed the fruit adds nothing.
    tracker.note_scan(Point3::new(5.0, 5.0, 5.0), Vec::new());
    assert_eq!(tracker.update(&m.clusters(10))[0].view_directions, 2);
    // A tracker continuing from the state counts afresh.
    let (tracked, next) = tracker.state();
    let mut copy = FruitTracker::from_state(tracked, next);
    assert_eq!(copy.update(&m.clusters(10))[0].view_directions, 0);
}

/// A cluster shape of these extents (metres, longest first) and bulge.
fn shape(extents: [f64; 3], bulge: f64) -> ClusterShape {
    ClusterShape {
        extents_m: Vector3::from(extents),
        bulge,
    }
}

#[test]
fn thresholds_and_switch() {
    let config = EvidenceConfig::default();
    assert_eq!(
        shape([0.08, 0.07, 0.04], 0.4).verdict(&config),
        Verdict::Fruit
    );
    assert_eq!(
        shape([0.2, 0.1, 0.1], 0.4).verdict(&config),
        Verdict::TooLarge
    );
    assert_eq!(
        shape([0.1, 0.02, 0.02], 0.4).verdict(&config),
        Verdict::Thin
    );
    assert_eq!(
        shape([0.04, 0.03, 0.02], 0.4).verdict(&config),
        Verdict::TooSmall
    );
    assert_eq!(
        shape([0.08, 0.06, 0.01], 0.05).verdict(&config),
        Verdict::Flat
    );
    let off = EvidenceConfig {
        enabled: false,
        ..config
    };
    assert_eq!(
        shape([0.08, 0.06, 0.01], 0.05).verdict(&off),
        Verdict::Fruit
    );
    assert!(ClusterShape::of(&[], 0.01).verdict(&config) != Verdict::Fruit);
}

/// The default bar: a solid hiding two unknown voxels is a sheet (a curled leaf smeared by the
/// stereo noise hides one or two), three passes; a round shape no longer lets a solid hiding
/// nothing through unless round bodies are allowed.
#[test]
fn a_solid_must_hide_three_unknown_voxels_by_default() {
    let config = EvidenceConfig::default();
    let cap = shape([0.08, 0.07, 0.03], 0.5);
    let round = shape([0.08, 0.07, 0.06], 0.8);
    // A third of the known voxels inside free: a leaf's solid, never a filled body.
    let hiding = |unknown| Interior {
        unknown,
        free: 15,
        occupied: 30,
        occupied_roi: 0,
    };
    assert!(!interior_holds(&hiding(2), &cap, &config));
    assert!(interior_holds(&hiding(3), &cap, &config));
    assert!(round.is_round(&config));
    assert!(!interior_holds(&hiding(0), &round, &config));
    let round_bodies = EvidenceConfig {
        round_bodies: true,
        ..config
    };
    assert!(interior_holds(&hiding(0), &round, &round_bodies));
    assert!(!interior_holds(&hiding(0), &cap, &round_bodies));
}

/// A filled body: a solid hiding no unknown voxel passes when few of its deep voxels are free
/// and the cluster is deep and bulging like a fruit (a young fruit smeared by the depth noise);
/// the same solid with the air a curled leaf encloses, or the same interior on a flat cap, is a
/// sheet.
#[test]
fn a_filled_round_solid_passes_without_unknown_voxels() {
    let config = EvidenceConfig::default();
    let young_fruit = shape([0.05, 0.045, 0.035], 0.6);
    let flat_cap = shape([0.05, 0.045, 0.02], 0.6);
    let shallow_bulge = shape([0.05, 0.045, 0.035], 0.3);
    let inside = |free, occupied| Interior {
        unknown: 0,
        free,
        occupied,
        occupied_roi: occupied,
    };
    assert!(young_fruit.is_full_bodied(&config) && !flat_cap.is_full_bodied(&config));
    assert!(interior_holds(&inside(2, 22), &young_fruit, &config));
    assert!(interior_holds(&inside(5, 20), &young_fruit, &config));
    assert!(!interior_holds(&inside(6, 19), &young_fruit, &config));
    assert!(!interior_holds(&inside(2, 22), &flat_cap, &config));
    assert!(!interior_holds(&inside(2, 22), &shallow_bulge, &config));
    assert!(!interior_holds(&inside(0, 0), &young_fruit, &config));
}

/// A revisit's prior holds the last visit's fruit skin as hints; the grown fruit hides them
/// inside its new skin, where no ray of this visit reaches. They are no knowledge of its
/// inside: its solid hides what it would in a map without them (counted as free, a grown
/// fruit looked like a sheet).
#[test]
fn a_grown_fruit_hides_the_last_visits_skin() {
    let young = capsicum(centre(), 4, 25.0, Vector3::new(0.022, 0.020, 0.036));
    let grown = capsicum(centre(), 4, 25.0, Vector3::new(0.026, 0.024, 0.043));
    let views = eyes(centre(), &all_round());
    let (first_visit, _, _) = scanned(&views, |o, d| first_hit(&young, o, d));
    let mut revisit = first_visit.prior(&glasshouse_roimap::PriorRules::default());
    let mut fresh = map();
    for eye in &views {
        scan_with(&mut revisit, centre(), *eye, |o, d| first_hit(&grown, o, d));
        scan_with(&mut fresh, centre(), *eye, |o, d| first_hit(&grown, o, d));
    }
    let clusters = fresh.clusters(1);
    let cluster = clusters.iter().max_by_key(|c| c.voxels.len()).unwrap();
    let fit = fit_ellipsoid(&fresh, cluster, &clean_scan_config());
    let body = Superellipsoid::from(&fit);
    let deep = 0.5 * revisit.config().resolution_m;
    let hints_inside = revisit
        .unobserved_hints()
        .into_iter()
        .filter(|&k| body.holds(&revisit.centre_of(k), deep))
        .count();
    assert!(
        hints_inside >= 10,
        "{hints_inside} hints inside the grown fruit"
    );
    let (on_prior, on_empty) = (
        Interior::of_fruit(&revisit, &fit),
        Interior::of_fruit(&fresh, &fit),
    );
    let counts = |i: Interior| (i.unknown, i.free, i.occupied);
    assert_eq!(counts(on_prior), counts(on_empty));
    assert!(on_prior.unknown >= 20, "{on_prior:?}");
    // Nor do they bound the fit as free space would: the same cluster fits the same solid.
    let refit = fit_ellipsoid(&revisit, cluster, &clean_scan_config());
    assert_eq!(refit.semi_axes_m, fit.semi_axes_m);
}
