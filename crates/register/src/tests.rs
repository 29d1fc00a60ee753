#![allow(clippy::unwrap_used)]

use std::collections::BTreeMap;

use glasshouse_roimap::{MapConfig, RoiMap, VoxelKey};
use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;

/// A ray-cast test scene: spheres, boxes (any orientation) and planes, z up.
#[derive(Clone, Default)]
struct Scene {
    spheres: Vec<(Point3<f64>, f64)>,
    /// Box pose (world from box) and half extents.
    boxes: Vec<(Isometry3<f64>, Vector3<f64>)>,
    /// A point on the plane and its normal.
    planes: Vec<(Point3<f64>, Unit<Vector3<f64>>)>,
}

impl Scene {
    /// Fruit-sized spheres, boxes and a tilted back wall over a floor, in front of the cameras
    /// of [`origins`] (0.6–1.4 m away).
    fn glasshouse(seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut scene = Scene::default();
        for _ in 0..10 {
            let centre = Point3::new(
                rng.gen_range(0.7..1.1),
                rng.gen_range(-0.35..0.35),
                rng.gen_range(0.1..0.6),
            );
            scene.spheres.push((centre, rng.gen_range(0.04..0.07)));
        }
        for _ in 0..4 {
            let centre = Vector3::new(
                rng.gen_range(0.8..1.2),
                rng.gen_range(-0.4..0.4),
                rng.gen_range(0.05..0.5),
            );
            let axis = Vector3::new(rng.gen(), rng.gen(), rng.gen::<f64>()) - Vector3::repeat(0.5);
            let turn = UnitQuaternion::from_scaled_axis(axis * 1.5);
            let half = Vector3::new(
                rng.gen_range(0.03..0.08),
                rng.gen_range(0.03..0.08),
                rng.gen_range(0.05..0.15),
            );
            scene
                .boxes
                .push((Isometry3::from_parts(centre.into(), turn), half));
        }
        scene
            .planes
            .push((Point3::new(0.0, 0.0, -0.004), Vector3::z_axis()));
        let wall = Unit::new_normalize(Vector3::new(-0.95, 0.3, 0.1));
        scene.planes.push((Point3::new(1.45, 0.0, 0.0), wall));
        scene
    }

    /// Distance along the unit ray `origin + t * dir` to the first surface.
    fn cast(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        let spheres = self.spheres.iter().filter_map(|(c, r)| {
            let oc = origin - c;
            let b = oc.dot(dir);
            let disc = b * b - (oc.norm_squared() - r * r);
            (disc >= 0.0).then(|| -b - disc.sqrt())
        });
        let boxes = self.boxes.iter().filter_map(|(pose, half)| {
            let (o, d) = (
                pose.inverse_transform_point(origin),
                pose.inverse_transform_vector(dir),
            );
            let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
            for a in 0..3 {
                let (t1, t2) = ((-half[a] - o[a]) / d[a], (half[a] - o[a]) / d[a]);
                near = near.max(t1.min(t2));
                far = far.min(t1.max(t2));
            }
            (near <= far).then_some(near)
        });
        let planes = self.planes.iter().filter_map(|(p, n)| {
            let denom = n.dot(dir);
            (denom.abs() > 1e-9).then(|| n.dot(&(p - origin)) / denom)
        });
        spheres
            .chain(boxes)
            .chain(planes)
            .filter(|&t| t > 1e-6 && t < 3.0)
            .min_by(f64::total_cmp)
    }

    /// The raw points a 160×120 camera (60° across) at `origin` looking at `target` sees.
    fn raw_scan(&self, origin: &Point3<f64>, target: &Point3<f64>) -> Vec<Point3<f64>> {
        let forward = (target - origin).normalize();
        let right = forward.cross(&Vector3::z()).normalize();
        let down = forward.cross(&right);
        let (w, h, f) = (160, 120, 140.0);
        let mut out = Vec::new();
        for v in 0..h {
            for u in 0..w {
                let d = (forward
                    + right * ((f64::from(u) - 79.5) / f)
                    + down * ((f64::from(v) - 59.5) / f))
                    .normalize();
                if let Some(t) = self.cast(origin, &d) {
                    out.push(origin + d * t);
                }
            }
        }
        out
    }
}

/// The detector's cloud: one averaged point per 1 cm voxel of the (believed) world frame.
fn downsample(points: &[Point3<f64>]) -> Vec<Point3<f32>> {
    let mut cells: BTreeMap<VoxelKey, (Vector3<f64>, u32)> = BTreeMap::new();
    for p in points {
        let k = VoxelKey::new(
            (p.x * 100.0).floor() as i32,
            (p.y * 100.0).floor() as i32,
            (p.z * 100.0).floor() as i32,
        );
        let e = cells.entry(k).or_insert((Vector3::zeros(), 0));
        e.0 += p.coords;
        e.1 += 1;
    }
    let avg = cells
        .into_values()
        .map(|(s, n)| Point3::from(s / f64::from(n)).cast());
    avg.collect()
}

const TARGET: Point3<f64> = Point3::new(1.0, 0.0, 0.3);

/// Camera origins 0.7–1.1 m from the scene's middle; the last one is the scan's.
fn origins() -> Vec<Point3<f64>> {
    vec![
        Point3::new(0.0, 0.0, 0.35),
        Point3::new(0.05, -0.25, 0.5),
        Point3::new(0.1, 0.25, 0.2),
        Point3::new(-0.05, 0.1, 0.6),
        Point3::new(0.2, -0.1, 0.3),
    ]
}

fn map_config() -> MapConfig {
    MapConfig {
        resolution_m: 0.01,
        max_range_m: Some(2.0),
        ..MapConfig::default()
    }
}

/// The map of the scene seen from every origin but the last.
fn map_of(scene: &Scene) -> RoiMap {
    let mut map = RoiMap::new(map_config()).unwrap();
    let origins = origins();
    for origin in &origins[..origins.len() - 1] {
        let points = downsample(&scene.raw_scan(origin, &TARGET));
        map.insert_scan(origin, &points, &vec![false; points.len()])
            .unwrap();
    }
    map
}

/// The last origin's scan as a trolley off by `error` sends it: the camera's true pose is
/// `error * believed`, so its points land at `error⁻¹ * truth`. Returns the sensor origin
/// and the points in the believed world frame.
fn scan_with_error(scene: &Scene, error: &Isometry3<f64>) -> (Point3<f64>, Vec<Point3<f32>>) {
    let origin = *origins().last().unwrap();
    let truth = scene.raw_scan(&origin, &TARGET);
    let to_believed = error.inverse();
    let sent: Vec<Point3<f64>> = truth.iter().map(|p| to_believed * p).collect();
    (to_believed * origin, downsample(&sent))
}

/// A camera error of `deg` about a random axis through the sensor origin, plus `mm` along a
/// random direction.
fn camera_error(rng: &mut ChaCha8Rng, deg: f64, mm: f64) -> Isometry3<f64> {
    let mut unit = || {
        let v = Vector3::new(rng.gen::<f64>(), rng.gen(), rng.gen()) - Vector3::repeat(0.5);
        v.normalize()
    };
    let (axis, direction) = (unit(), unit());
    let origin = origins().last().unwrap().coords;
    let rotation = UnitQuaternion::from_scaled_axis(axis * deg.to_radians());
    let about_origin = Translation3::from(origin - rotation * origin);
    Translation3::from(direction * mm * 1e-3) * Isometry3::from_parts(about_origin, rotation)
}

fn align(map: &RoiMap, origin: &Point3<f64>, points: &[Point3<f32>]) -> Alignment {
    let scan = ScanInWorld {
        sensor_origin_in_world: origin,
        points_in_world: points,
    };
    align_scan(map, scan, &enabled())
}

fn aligned(alignment: Alignment) -> Aligned {
    match alignment {
        Alignment::Aligned(a) => a,
        other => panic!("expected an alignment, got {other:?}"),
    }
}

/// How far `residual` (the correction after the error) still moves the scan: angle in degrees
/// and the largest point displacement over the scan.
fn remaining(residual: &Isometry3<f64>, points: &[Point3<f32>]) -> (f64, f64) {
    let shift = points
        .iter()
        .map(|p| {
            let p = p.cast::<f64>();
            (residual * p - p).norm()
        })
        .fold(0.0, f64::max);
    (residual.rotation.angle().to_degrees(), shift)
}

#[test]
fn a_small_camera_error_is_undone() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for seed in 0..4 {
        let scene = Scene::glasshouse(seed);
        let map = map_of(&scene);
        let (deg, mm) = (rng.gen_range(0.5..1.0), rng.gen_range(5.0..10.0));
        let error = camera_error(&mut rng, deg, mm);
        let (origin, points) = scan_with_error(&scene, &error);
        let found = aligned(align(&map, &origin, &points));
        assert!(found.applied());
        // The sent points are `error⁻¹ * truth`: the correction should be `error`.
        let (angle_deg, shift_m) = remaining(&(error.inverse() * found.world_correction), &points);
        eprintln!(
            "seed {seed}: error {deg:.2}° {mm:.1} mm, left {angle_deg:.3}° {:.2} mm, rms {:.2} -> {:.2} mm, {} inliers ({:.0} %), {} iterations",
            shift_m * 1e3,
            found.rms_before_m * 1e3,
            found.rms_after_m * 1e3,
            found.inliers,
            found.inlier_share * 100.0,
            found.iterations
        );
        assert!(angle_deg < 0.1, "seed {seed}: {angle_deg}° left");
        assert!(shift_m < 0.0025, "seed {seed}: {shift_m} m left");
        assert!(found.rms_after_m < found.rms_before_m);
        assert_eq!(found.unconstrained_directions, 0);
    }
}

#[test]
fn a_perfect_scan_is_left_as_it_is() {
    for seed in 0..3 {
        let scene = Scene::glasshouse(seed);
        let map = map_of(&scene);
        let (origin, points) = scan_with_error(&scene, &Isometry3::identity());
        let found = aligned(align(&map, &origin, &points));
        eprintln!(
            "seed {seed}: estimate {:.3}° moving points up to {:.2} mm",
            found.rotation_deg,
            found.max_point_shift_m * 1e3
        );
        assert_eq!(
            found.kept_as_sent,
            Some(KeptAsSent::BelowResolution),
            "seed {seed}: {found:?}"
        );
    }
}

#[test]
fn empty_map_and_first_scans_are_skipped() {
    let scene = Scene::glasshouse(1);
    let (origin, points) = scan_with_error(&scene, &Isometry3::identity());
    let empty = RoiMap::new(map_config()).unwrap();
    assert_eq!(
        align(&empty, &origin, &points),
        Alignment::Skipped(SkipReason::MapTooSmall { occupied_voxels: 0 })
    );
    let off = RegisterSettings {
        enabled: false,
        ..enabled()
    };
    let scan = ScanInWorld {
        sensor_origin_in_world: &origin,
        points_in_world: &points,
    };
    let map = map_of(&scene);
    assert_eq!(
        align_scan(&map, scan, &off),
        Alignment::Skipped(SkipReason::Disabled)
    );
}

#[test]
fn nan_points_are_ignored_and_never_panic() {
    let scene = Scene::glasshouse(2);
    let map = map_of(&scene);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let error = camera_error(&mut rng, 0.7, 7.0);
    let (origin, points) = scan_with_error(&scene, &error);
    let nan = Point3::new(f32::NAN, 0.0, 1.0);
    let inf = Point3::new(0.0, f32::INFINITY, 1.0);
    let mut dirty = Vec::new();
    for (i, p) in points.iter().enumerate() {
        dirty.push(*p);
        if i % 3 == 0 {
            dirty.extend([nan, inf]);
        }
    }
    // The non-finite points are left out before the stride: the very same alignment.
    let clean = align(&map, &origin, &points);
    assert!(matches!(clean, Alignment::Aligned(_)));
    assert_eq!(align(&map, &origin, &dirty), clean);
    let all_nan = vec![nan; 5000];
    assert_eq!(
        align(&map, &origin, &all_nan),
        Alignment::Skipped(SkipReason::TooFewPoints { points: 0 })
    );
    let nan_origin = Point3::new(f64::NAN, 0.0, 0.0);
    assert!(matches!(
        align(&map, &nan_origin, &points),
        Alignment::Skipped(SkipReason::TooFewPoints { .. })
    ));
    // The corrected cloud keeps the non-finite points non-finite (the map skips them).
    let moved = corrected_points(&error, &dirty);
    assert_eq!(moved.len(), dirty.len());
    assert!(moved[1].x.is_nan());
}

#[test]
fn a_wildly_wrong_scan_is_rejected() {
    let scene = Scene::glasshouse(3);
    let map = map_of(&scene);
    let shifts = [
        Vector3::new(0.2, 0.0, 0.0),
        Vector3::new(-0.2, 0.0, 0.0),
        Vector3::new(0.0, 0.2, 0.0),
        Vector3::new(0.0, 0.0, 0.2),
        Vector3::new(0.0, -0.12, 0.12),
    ];
    for shift in shifts {
        let error = Isometry3::translation(shift.x, shift.y, shift.z);
        let (origin, points) = scan_with_error(&scene, &error);
        let found = align(&map, &origin, &points);
        eprintln!("shift {shift:?}: {found:?}");
        assert!(
            matches!(found, Alignment::Rejected(_)),
            "{shift:?}: {found:?}"
        );
        assert!(!found.inserts());
    }
    // A turn of 10° about the camera is no calibration error either.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let error = camera_error(&mut rng, 10.0, 0.0);
    let (origin, points) = scan_with_error(&scene, &error);
    let found = align(&map, &origin, &points);
    assert!(matches!(found, Alignment::Rejected(_)), "{found:?}");
}

#[test]
fn a_scan_in_space_the_map_saw_empty_is_rejected() {
    let scene = Scene::glasshouse(6);
    let map = map_of(&scene);
    // 40 cm up: most points land in the air the cameras looked through at the wall.
    let error = Isometry3::translation(0.0, 0.0, -0.4);
    let (origin, points) = scan_with_error(&scene, &error);
    let found = align(&map, &origin, &points);
    assert!(
        matches!(
            found,
            Alignment::Rejected(RejectReason::ContradictsMap { .. })
        ),
        "{found:?}"
    );
}

/// A scene of one tilted plane: three directions (the in-plane moves, the turn about the
/// normal) are not constrained by it.
#[test]
fn a_planar_scene_is_corrected_only_where_it_constrains() {
    let normal = Unit::new_normalize(Vector3::new(-1.0, 0.2, 0.3));
    let scene = Scene {
        planes: vec![(Point3::new(1.2, 0.0, 0.3), normal)],
        ..Scene::default()
    };
    let map = map_of(&scene);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let error = camera_error(&mut rng, 0.8, 8.0);
    let (origin, points) = scan_with_error(&scene, &error);
    let found = aligned(align(&map, &origin, &points));
    assert_eq!(found.unconstrained_directions, 3);
    // After the correction the points lie on the plane again (what a plane can tell)...
    let corrected = corrected_points(&found.world_correction, &points);
    let off_plane = |p: &Point3<f32>| {
        normal
            .dot(&(p.cast::<f64>() - Point3::new(1.2, 0.0, 0.3)))
            .abs()
    };
    let worst_before = points.iter().map(off_plane).fold(0.0, f64::max);
    let worst_after = corrected.iter().map(off_plane).fold(0.0, f64::max);
    eprintln!("off the plane: {worst_before:.4} -> {worst_after:.4} m");
    assert!(worst_before > 0.005);
    assert!(worst_after < 0.003);
    // ...and nothing moved within it: no turn about the normal.
    let turn = found.world_correction.rotation.scaled_axis();
    assert!(turn.dot(&normal).abs().to_degrees() < 0.01, "{turn:?}");
    // Stricter settings refuse the estimate: the scan goes in as sent, since as sent the map
    // contradicts none of it.
    let strict = RegisterSettings {
        max_degenerate_directions: 2,
        ..enabled()
    };
    let scan = ScanInWorld {
        sensor_origin_in_world: &origin,
        points_in_world: &points,
    };
    let degenerate = RejectReason::Degenerate {
        unconstrained_directions: 3,
    };
    let kept = aligned(align_scan(&map, scan, &strict));
    assert_eq!(
        kept.kept_as_sent,
        Some(KeptAsSent::EstimateFailed(degenerate))
    );
    assert!(align_scan(&map, scan, &strict)
        .correction_to_apply()
        .is_none());
}

#[test]
fn a_view_of_unmapped_space_goes_in_as_sent() {
    let scene = Scene::glasshouse(4);
    let map = map_of(&scene);
    // Objects where the map's cameras never looked (behind them).
    let elsewhere = Scene {
        spheres: vec![
            (Point3::new(-1.0, 0.0, 0.3), 0.2),
            (Point3::new(-1.0, 0.4, 0.4), 0.15),
        ],
        ..Scene::default()
    };
    let origin = Point3::new(-0.2, 0.0, 0.35);
    let points = downsample(&elsewhere.raw_scan(&origin, &Point3::new(-1.0, 0.1, 0.3)));
    assert!(points.len() > 500);
    let found = align(&map, &origin, &points);
    assert!(
        matches!(found, Alignment::Skipped(SkipReason::NewGround { .. })),
        "{found:?}"
    );
    assert!(found.inserts());
    assert!(found.correction_to_apply().is_none());
}

#[test]
fn alignment_is_deterministic() {
    let scene = Scene::glasshouse(5);
    let map = map_of(&scene);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let error = camera_error(&mut rng, 0.9, 9.0);
    let (origin, points) = scan_with_error(&scene, &error);
    assert_eq!(align(&map, &origin, &points), align(&map, &origin, &points));
}

#[test]
fn counts_follow_the_outcomes() {
    let mut counts = AlignmentCounts::default();
    counts.record(&Alignment::Skipped(SkipReason::Disabled));
    counts.record(&Alignment::Rejected(RejectReason::TooFewInliers {
        inliers: 3,
    }));
    counts.record(&Alignment::Rejected(RejectReason::Degenerate {
        unconstrained_directions: 4,
    }));
    assert_eq!(counts.skipped, 1);
    assert_eq!(counts.rejected(), 2);
    assert_eq!(counts.rejected_too_few_inliers, 1);
    assert_eq!(counts.aligned, 0);
    // Summed over trials, outcome by outcome.
    let mut total = counts;
    total += counts;
    assert_eq!(total.skipped, 2);
    assert_eq!(total.rejected_degenerate, 2);
    assert_eq!(total.rejected(), 4);
}

#[test]
fn settings_validate_and_read_back() {
    let defaults = RegisterSettings::default();
    assert!(!defaults.enabled);
    defaults.validate().unwrap();
    let bad = [
        RegisterSettings {
            huber_m: 0.0,
            ..defaults.clone()
        },
        RegisterSettings {
            max_rotation_deg: f64::NAN,
            ..defaults.clone()
        },
        RegisterSettings {
            min_inlier_share: 1.5,
            ..defaults.clone()
        },
        RegisterSettings {
            max_scan_points: 0,
            ..defaults.clone()
        },
        RegisterSettings {
            min_scan_points: 5000,
            ..defaults.clone()
        },
    ];
    for settings in bad {
        assert!(matches!(
            settings.validate(),
            Err(SettingsError::OutOfRange { .. })
        ));
    }
    let partial: RegisterSettings = serde_json::from_str(r#"{"max_rotation_deg": 2.0}"#).unwrap();
    assert_eq!(partial.max_rotation_deg, 2.0);
    assert_eq!(partial.max_scan_points, defaults.max_scan_points);
    assert!(serde_json::from_str::<RegisterSettings>(r#"{"max_rotation": 2.0}"#).is_err());
    let text = serde_json::to_string(&defaults).unwrap();
    assert_eq!(
        serde_json::from_str::<RegisterSettings>(&text).unwrap(),
        defaults
    );
}

/// The defaults, switched on.
fn enabled() -> RegisterSettings {
    RegisterSettings {
        enabled: true,
        ..RegisterSettings::default()
    }
}
