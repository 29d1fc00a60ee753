//! The superellipsoid fit on capsicum-like bodies, and against the axis-aligned fit.

#![allow(clippy::unwrap_used)]

use nalgebra::{Point3, Vector3};

use super::tests_support::*;
use super::*;
use crate::test_bodies::{capsicum, first_hit, Lobe};

/// Volume and centroid of the union of lobes, counted on a 1 mm grid.
fn volume_and_centroid(body: &[Lobe], around: Point3<f64>) -> (f64, Point3<f64>) {
    let step = 0.001;
    let (mut count, mut sum) = (0u64, Vector3::zeros());
    for i in -80..80 {
        for j in -80..80 {
            for k in -80..80 {
                let q =
                    around + Vector3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) * step;
                if body.iter().any(|l| l.holds(&q)) {
                    count += 1;
                    sum += q.coords;
                }
            }
        }
    }
    (
        count as f64 * step.powi(3),
        Point3::from(sum / count as f64),
    )
}

fn scanned(body: &[Lobe], aim: Point3<f64>, eyes: &[Vector3<f64>]) -> (RoiMap, RoiCluster) {
    let mut m = map();
    for eye in eyes {
        scan_with(&mut m, aim, aim + eye * 0.4, |o, d| first_hit(body, o, d));
    }
    let mut clusters = m.clusters(10);
    assert_eq!(clusters.len(), 1);
    (m, clusters.remove(0))
}

fn aligned() -> FitConfig {
    FitConfig {
        model: ShapeModel::AxisAlignedEllipsoid,
        ..clean_scan_config()
    }
}

/// Errors of one fit against the body: |fitted / true volume − 1| and the centre's distance
/// from the body's centroid, for the superellipsoid and the axis-aligned ellipsoid.
#[derive(Default)]
struct Errors {
    volume: Vec<f64>,
    centre_m: Vec<f64>,
    aligned_volume: Vec<f64>,
    aligned_centre_m: Vec<f64>,
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

fn median(v: &[f64]) -> f64 {
    let mut sorted = v.to_vec();
    sorted.sort_by(f64::total_cmp);
    let n = sorted.len();
    (sorted[(n - 1) / 2] + sorted[n / 2]) / 2.0
}

fn most(v: &[f64]) -> f64 {
    v.iter().copied().fold(0.0, f64::max)
}

/// Capsicums of 3 and 4 lobes, round and long, tilted 10-30°, seen from one, two or three
/// sides. From two or three sides every fitted volume is within 15 % of the body's and every
/// centre within 1 cm of its centroid, and the volumes err less than the axis-aligned
/// ellipsoid's. From one side the back is left to the priors: the median volume is within
/// 25 %, every one within 60 % and every centre within 1.5 cm (a lobed body seen towards the
/// valley between two lobes looks flatter, hence larger, than it is), and the centres err less
/// than the axis-aligned ellipsoid's.
#[test]
fn tilted_lobed_capsicum_seen_from_one_two_or_three_sides() {
    let front = Vector3::new(-1.0, -0.2, 0.15).normalize();
    let side = Vector3::new(0.1, 1.0, 0.1).normalize();
    let above = Vector3::new(0.6, -0.5, 0.6).normalize();
    let round = Vector3::new(0.024, 0.022, 0.04);
    let long = Vector3::new(0.021, 0.019, 0.055);
    let (mut one_side, mut more_sides) = (Errors::default(), Errors::default());
    for (lobes, tilt_deg, lobe_m) in [
        (3, 25.0, round),
        (4, 30.0, round),
        (4, 10.0, round),
        (3, 30.0, long),
        (4, 20.0, long),
    ] {
        let c = centre();
        let body = capsicum(c, lobes, tilt_deg, lobe_m);
        let (truth_m3, truth_centre) = volume_and_centroid(&body, c);
        for eyes in [
            vec![front],
            vec![side],
            vec![front, side],
            vec![front, side, above],
        ] {
            let (m, cluster) = scanned(&body, c, &eyes);
            let fit = fit_ellipsoid(&m, &cluster, &clean_scan_config());
            let old = fit_ellipsoid(&m, &cluster, &aligned());
            let case = format!("{lobes} lobes, {tilt_deg}°, {} sides", eyes.len());
            println!(
                "{case}: volume {:.3} (aligned {:.3}), centre {:.1} mm (aligned {:.1}), \
                 ε {:.2?}, k {:.2}, rms {:.1} mm",
                fit.volume_m3 / truth_m3,
                old.volume_m3 / truth_m3,
                (fit.centre - truth_centre).norm() * 1e3,
                (old.centre - truth_centre).norm() * 1e3,
                fit.exponents,
                fit.taper,
                fit.rms_residual_m * 1e3
            );
            assert_eq!(fit.kind, SolidKind::Ellipsoid, "{case}");
            let points: Vec<_> = cluster.voxels.iter().map(|k| m.centre_of(*k)).collect();
            let waist = crate::split::waist_ratio(&points, m.config().resolution_m);
            assert!(waist > 0.9, "{case}: waist {waist}");
            let errors = if eyes.len() == 1 {
                &mut one_side
            } else {
                &mut more_sides
            };
            errors.volume.push((fit.volume_m3 / truth_m3 - 1.0).abs());
            errors.centre_m.push((fit.centre - truth_centre).norm());
            errors
                .aligned_volume
                .push((old.volume_m3 / truth_m3 - 1.0).abs());
            errors
                .aligned_centre_m
                .push((old.centre - truth_centre).norm());
        }
    }
    let e = &more_sides;
    assert!(most(&e.volume) <= 0.15, "{:?}", e.volume);
    assert!(most(&e.centre_m) <= 0.01, "{:?}", e.centre_m);
    assert!(
        mean(&e.volume) < mean(&e.aligned_volume),
        "{:?} vs {:?}",
        e.volume,
        e.aligned_volume
    );
    let e = &one_side;
    assert!(
        median(&e.volume) <= 0.25 && most(&e.volume) <= 0.6,
        "{:?}",
        e.volume
    );
    assert!(most(&e.centre_m) <= 0.015, "{:?}", e.centre_m);
    assert!(
        mean(&e.centre_m) < mean(&e.aligned_centre_m),
        "{:?}",
        e.centre_m
    );
}

/// On ellipsoids, the fruits of the simulator so far, the superellipsoid is no worse than the
/// axis-aligned fit: half-seen spheres at several voxel phases and an ellipsoid seen all round.
#[test]
fn on_axis_aligned_ellipsoids_the_superellipsoid_is_no_worse() {
    let (mut new_error, mut old_error) = (Vec::new(), Vec::new());
    let (mut new_off, mut old_off) = (Vec::new(), Vec::new());
    let mut judge = |m: &RoiMap, c: &Point3<f64>, truth_m3: f64| {
        let cluster = m.clusters(10).remove(0);
        let fit = fit_ellipsoid(m, &cluster, &clean_scan_config());
        let old = fit_ellipsoid(m, &cluster, &aligned());
        assert_eq!(fit.kind, SolidKind::Ellipsoid);
        new_error.push((fit.volume_m3 / truth_m3 - 1.0).abs());
        old_error.push((old.volume_m3 / truth_m3 - 1.0).abs());
        new_off.push((fit.centre - c).norm());
        old_off.push((old.centre - c).norm());
    };
    for off in [0.0, 0.004, 0.007] {
        let c = Point3::new(0.2 + off, -0.1 - off * 1.3, 1.0 + off * 0.7);
        for dir in [
            Vector3::x(),
            -Vector3::y(),
            Vector3::new(1.0, 1.0, 0.3).normalize(),
        ] {
            let r = 0.035;
            let mut m = map();
            scan_at(&mut m, c, c + dir * 0.4, &Vector3::repeat(r));
            judge(&m, &c, 4.0 / 3.0 * std::f64::consts::PI * r.powi(3));
        }
    }
    let axes = Vector3::new(0.03, 0.038, 0.045);
    let mut m = map();
    for dir in [
        Vector3::x(),
        -Vector3::x(),
        Vector3::y(),
        -Vector3::y(),
        Vector3::z(),
    ] {
        scan(&mut m, centre() + dir * 0.4, &axes);
    }
    judge(
        &m,
        &centre(),
        4.0 / 3.0 * std::f64::consts::PI * axes.product(),
    );
    println!(
        "volume error {:.3} (aligned {:.3}), centre {:.1} mm (aligned {:.1})",
        mean(&new_error),
        mean(&old_error),
        mean(&new_off) * 1e3,
        mean(&old_off) * 1e3
    );
    assert!(
        mean(&new_error) <= mean(&old_error) + 0.01,
        "{new_error:?} vs {old_error:?}"
    );
    assert!(
        mean(&new_off) <= mean(&old_off) + 0.001,
        "{new_off:?} vs {old_off:?}"
    );
}

/// A capsicum grown together with two red leaves into one cluster, seen from three sides: no
/// solid fits the cluster and no waist splits it, so without the best part it is reported as
/// its box, several times the body's volume. The solid fitted to the part around the
/// best-supported sphere is within 30 % of the body's volume and 1.5 cm of its centroid.
#[test]
fn a_capsicum_grown_together_with_red_leaves_is_fitted_by_its_best_part() {
    let c = centre();
    let body = capsicum(c, 3, 25.0, Vector3::new(0.024, 0.022, 0.04));
    let (truth_m3, truth_centre) = volume_and_centroid(&body, c);
    // Leaves upright beside the fruit, on its shoulders and under it, pressed into it.
    let leaf = |offset: Vector3<f64>, axis: Vector3<f64>, semi_axes_m: Vector3<f64>| Lobe {
        centre: c + offset,
        world_from_lobe: crate::test_bodies::turn(axis, 10.0),
        semi_axes_m,
    };
    let leaves = [
        leaf(
            Vector3::new(0.0, 0.08, 0.0),
            Vector3::z(),
            Vector3::new(0.003, 0.07, 0.05),
        ),
        leaf(
            Vector3::new(0.03, 0.0, 0.045),
            Vector3::y(),
            Vector3::new(0.07, 0.05, 0.003),
        ),
        leaf(
            Vector3::new(-0.02, -0.02, -0.05),
            Vector3::x(),
            Vector3::new(0.07, 0.05, 0.003),
        ),
    ];
    let scene: Vec<Lobe> = body.iter().chain(leaves.iter()).copied().collect();
    let eyes = [
        Vector3::new(-1.0, -0.2, 0.15).normalize(),
        Vector3::new(-0.3, 1.0, 0.3).normalize(),
        Vector3::new(0.6, -0.5, 0.6).normalize(),
    ];
    // Each view sees the scene up to 1 cm off the others (a pose error): the leaves smear
    // into the fruit.
    let shifts = [
        Vector3::new(0.006, -0.004, 0.005),
        Vector3::new(-0.005, 0.006, -0.004),
        Vector3::new(0.0, -0.006, -0.006),
    ];
    let mut m = map();
    for (eye, shift) in eyes.iter().zip(shifts) {
        scan_with(&mut m, c, c + eye * 0.4, |o, d| {
            first_hit(&scene, &(o + shift), d)
        });
    }
    let mut clusters = m.clusters(10);
    clusters.sort_by_key(|k| std::cmp::Reverse(k.voxels.len()));
    let cluster = clusters.remove(0);
    let whole = FitConfig {
        best_part: false,
        ..clean_scan_config()
    };
    let boxed = fit_ellipsoid(&m, &cluster, &whole);
    let fit = fit_ellipsoid(&m, &cluster, &clean_scan_config());
    println!(
        "{} voxels; box {:.2} of the body; best part {:?} {:.2} of the body, centre {:.1} mm off",
        cluster.voxels.len(),
        boxed.volume_m3 / truth_m3,
        fit.kind,
        fit.volume_m3 / truth_m3,
        (fit.centre - truth_centre).norm() * 1e3
    );
    assert_eq!(boxed.kind, SolidKind::Box);
    assert!(boxed.volume_m3 > 3.0 * truth_m3);
    assert_ne!(fit.kind, SolidKind::Box);
    assert!((fit.volume_m3 / truth_m3 - 1.0).abs() < 0.3);
    assert!((fit.centre - truth_centre).norm() < 0.015);
}

/// Spheres of 2.5-4 cm scanned from five sides into 1 cm voxels: the solid through the voxel
/// centres is too large (the centres of the voxels a convex surface passes through lie outside
/// it on average), the more so the smaller the sphere; shrunk by
/// [`FitConfig::voxel_bias_factor`] · voxel² / R every volume is within 6 % and they err less.
#[test]
fn the_voxel_centres_outward_bias_is_taken_off_the_solid() {
    let eyes = [
        Vector3::new(1.0, 0.1, 0.1),
        Vector3::new(-1.0, 0.2, 0.0),
        Vector3::new(0.1, 1.0, -0.1),
        Vector3::new(0.0, -1.0, 0.2),
        Vector3::new(0.2, 0.1, 1.0),
    ];
    let (mut through_centres, mut unbiased) = (Vec::new(), Vec::new());
    for radius_m in [0.025f64, 0.03, 0.035, 0.04] {
        let axes = Vector3::repeat(radius_m);
        let truth_m3 = 4.0 / 3.0 * std::f64::consts::PI * radius_m.powi(3);
        let mut m = map();
        for eye in eyes {
            scan(&mut m, centre() + eye.normalize() * 0.4, &axes);
        }
        let cluster = m.clusters(10).remove(0);
        let ratio = |factor: f64| {
            let config = FitConfig {
                voxel_bias_factor: factor,
                ..clean_scan_config()
            };
            fit_ellipsoid(&m, &cluster, &config).volume_m3 / truth_m3
        };
        let (before, after) = (ratio(0.0), ratio(FitConfig::default().voxel_bias_factor));
        println!(
            "R {radius_m}: volume ÷ truth {before:.3} through the centres, {after:.3} unbiased"
        );
        assert!(
            (after - 1.0).abs() < 0.06,
            "R {radius_m}: {after} against {before}"
        );
        through_centres.push(before);
        unbiased.push(after);
    }
    let error = |v: &[f64]| mean(&v.iter().map(|r| (r - 1.0).abs()).collect::<Vec<_>>());
    assert!(mean(&through_centres) > 1.03, "{through_centres:?}");
    assert!(
        error(&unbiased) < 0.6 * error(&through_centres),
        "{unbiased:?} against {through_centres:?}"
    );
}
