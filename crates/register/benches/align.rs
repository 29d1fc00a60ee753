//! Criterion bench of scan registration on the ROI map's shared workload
//! (`glasshouse_roimap::testdata`: 640×480 camera, 30 spheres before a back plane, 1 cm voxels).
//!
//! `cargo bench -p glasshouse-register --bench align -- --warm-up-time 1 --measurement-time 3`
//!
//! The map holds nine filtered scans; the tenth (about 22k points, subsampled to 3000) is
//! aligned as sent by a camera off by 0.7° and 7 mm about its origin (`camera_error`), and as
//! sent by a perfect one (`perfect`).

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion};
use glasshouse_register::{align_scan, Alignment, RegisterSettings, ScanInWorld};
use glasshouse_roimap::testdata::Workload;
use glasshouse_roimap::RoiMap;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

/// A camera off by 0.7° about a fixed axis through `origin`, then 7 mm: its points as sent.
fn sent_by_misplaced_camera(origin: &Point3<f64>, points: &[Point3<f32>]) -> Vec<Point3<f32>> {
    let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
    let rotation = UnitQuaternion::from_scaled_axis(axis * 0.7f64.to_radians());
    let about_origin = Translation3::from(origin.coords - rotation * origin.coords);
    let shift = Translation3::new(0.004, -0.005, 0.003);
    let error = shift * Isometry3::from_parts(about_origin, rotation);
    let to_believed = error.inverse();
    points
        .iter()
        .map(|p| (to_believed * p.cast::<f64>()).cast())
        .collect()
}

fn registration(c: &mut Criterion) {
    let w = Workload::standard(1);
    let scans = w.filtered_scans();
    let mut map = RoiMap::new(w.map_config()).expect("valid config");
    for s in &scans[..9] {
        map.insert_scan(&s.origin, &s.points, &s.roi)
            .expect("valid scan");
    }
    let last = &scans[9];
    let off = sent_by_misplaced_camera(&last.origin, &last.points);
    let settings = RegisterSettings {
        enabled: true,
        ..RegisterSettings::default()
    };
    let align = |points: &[Point3<f32>]| {
        let scan = ScanInWorld {
            sensor_origin_in_world: &last.origin,
            points_in_world: points,
        };
        align_scan(&map, scan, &settings)
    };
    for (name, points) in [("camera_error", &off), ("perfect", &last.points)] {
        match align(points) {
            Alignment::Aligned(a) => eprintln!(
                "{name}: {} points, correction {:.3}° / {:.2} mm at the sensor, rms {:.2} -> {:.2} mm, \
                 {} inliers ({:.0} %), {} iterations, applied: {}",
                points.len(),
                a.rotation_deg,
                a.sensor_shift_m * 1e3,
                a.rms_before_m * 1e3,
                a.rms_after_m * 1e3,
                a.inliers,
                a.inlier_share * 100.0,
                a.iterations,
                a.applied()
            ),
            other => eprintln!("{name}: {other:?}"),
        }
    }
    let mut g = c.benchmark_group("align");
    g.sample_size(20);
    g.bench_function("camera_error", |b| b.iter(|| black_box(align(&off))));
    g.bench_function("perfect", |b| b.iter(|| black_box(align(&last.points))));
    g.finish();
}

criterion_group!(benches, registration);
criterion_main!(benches);
