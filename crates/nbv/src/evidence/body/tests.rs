#![allow(clippy::unwrap_used)]

use glasshouse_roimap::{RoiCluster, RoiMap};
use nalgebra::{Point3, Vector3};

use super::*;
use crate::evidence::{ClusterShape, EvidenceConfig, Verdict};
use crate::fit::tests_support::{centre, hit_ellipsoid, map, scan_labelled};
use crate::test_bodies::{turn, Lobe};

/// The largest ROI cluster of the map.
fn patch(m: &RoiMap) -> RoiCluster {
    let clusters = m.clusters(1);
    clusters.into_iter().max_by_key(|c| c.voxels.len()).unwrap()
}

const FRUIT_R: f64 = 0.035;

/// A round fruit at the scene's centre seen from three eyes 0.4 m away on its −x side, labelled
/// only within 1.8 cm of the point of its skin nearest the first eye (its sunlit cap).
fn shaded_fruit() -> (RoiMap, RoiCluster) {
    let axes = Vector3::repeat(FRUIT_R);
    let towards = [
        Vector3::new(-1.0, 0.0, 0.1),
        Vector3::new(-0.7, 0.7, 0.0),
        Vector3::new(-0.7, -0.6, 0.3),
    ];
    let cap = centre() + towards[0].normalize() * FRUIT_R;
    let mut m = map();
    for t in towards {
        let eye = centre() + t.normalize() * 0.4;
        let hit = |o: &Point3<f64>, d: &Vector3<f64>| hit_ellipsoid(o, d, &centre(), &axes);
        scan_labelled(&mut m, centre(), eye, hit, |p| (p - cap).norm() < 0.018);
    }
    let cluster = patch(&m);
    (m, cluster)
}

#[test]
fn a_fruit_labelled_only_in_a_patch_has_its_body_found() {
    let (m, cluster) = shaded_fruit();
    // The shape rule turns the patch away: it is a small, shallow cap.
    let shape = ClusterShape::of(
        &cluster
            .voxels
            .iter()
            .map(|k| m.centre_of(*k))
            .collect::<Vec<_>>(),
        0.01,
    );
    let verdict = shape.verdict(&EvidenceConfig::default());
    assert_ne!(verdict, Verdict::Fruit, "{shape:?}");
    let body = find_body(&m, &cluster, &BodyConfig::default()).unwrap();
    assert!((body.radius_m - FRUIT_R).abs() < 0.008, "{body:?}");
    assert!((body.centre - centre()).norm() < 0.01, "{body:?}");
    assert!(body.unknown_inside >= 16, "{body:?}");
    // Many more surface voxels than the labels cover, and the same body every time.
    assert!(body.surface.len() > 2 * cluster.voxels.len(), "{body:?}");
    assert_eq!(find_body(&m, &cluster, &BodyConfig::default()), Some(body));
}

#[test]
fn the_search_can_be_switched_off_and_asks_for_a_hidden_inside() {
    let (m, cluster) = shaded_fruit();
    let strict = BodyConfig {
        min_unknown_inside: 100_000,
        ..BodyConfig::default()
    };
    assert_eq!(find_body(&m, &cluster, &strict), None);
    assert!(
        !EvidenceConfig {
            body: BodyConfig {
                enabled: false,
                ..BodyConfig::default()
            },
            ..EvidenceConfig::default()
        }
        .body
        .enabled
    );
}

#[test]
fn a_leaf_seen_from_both_sides_has_no_body_under_its_patch() {
    // A 7 x 5 cm leaf, 1 mm thick, facing the eyes on both sides, labelled in a patch.
    let leaf = Lobe {
        centre: centre(),
        world_from_lobe: turn(Vector3::z(), 15.0) * turn(Vector3::y(), 80.0),
        semi_axes_m: Vector3::new(0.035, 0.025, 0.0005),
    };
    let mut m = map();
    for t in [
        Vector3::new(-1.0, 0.1, 0.1),
        Vector3::new(-0.8, -0.5, 0.2),
        Vector3::new(1.0, 0.2, -0.1),
        Vector3::new(0.8, -0.4, 0.3),
    ] {
        let eye = centre() + t.normalize() * 0.4;
        let labelled = |p: &Point3<f64>| (p - centre()).norm() < 0.02;
        scan_labelled(&mut m, centre(), eye, |o, d| leaf.hit(o, d), labelled);
    }
    let cluster = patch(&m);
    assert!(cluster.voxels.len() >= 4, "{}", cluster.voxels.len());
    assert_eq!(find_body(&m, &cluster, &BodyConfig::default()), None);
}

#[test]
fn bad_settings_are_refused() {
    assert!(BodyConfig::default().validate().is_ok());
    let bad = [
        BodyConfig {
            sample_m: f64::NAN,
            ..BodyConfig::default()
        },
        BodyConfig {
            max_radius_m: 0.01,
            ..BodyConfig::default()
        },
        BodyConfig {
            free_weight: -1.0,
            ..BodyConfig::default()
        },
        BodyConfig {
            hypotheses: 0,
            ..BodyConfig::default()
        },
        BodyConfig {
            reach_voxels: 1000,
            ..BodyConfig::default()
        },
    ];
    for config in bad {
        let message = config.validate().unwrap_err();
        assert!(message.starts_with("body."), "{message}");
    }
}
