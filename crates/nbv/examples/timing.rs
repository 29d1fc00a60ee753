//! Release-mode timing of map insertion and planning on a synthetic plant row.
//!
//! Run with `cargo run --release -p glasshouse-nbv --example timing`. Wall-clock time is read
//! here only, never in the libraries.

use std::time::Instant;

use glasshouse_geom::{look_at, Aabb};
use glasshouse_nbv::{plan_views, FruitTracker, Method, PlannerConfig, PlanningContext};
use glasshouse_roimap::{MapConfig, RoiMap};
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const POINTS_PER_SCAN: usize = 20_000;

fn unit(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    let z: f64 = rng.gen_range(-1.0..=1.0);
    let phi: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
    let r = (1.0 - z * z).sqrt();
    Vector3::new(r * phi.cos(), r * phi.sin(), z)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    // Leaves as small discs (centre, normal), fruits as spheres of 3.5 cm.
    let leaves: Vec<(Point3<f64>, Vector3<f64>)> = (0..300)
        .map(|_| {
            let c = Point3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(0.2..0.6),
                rng.gen_range(0.4..1.6),
            );
            (c, unit(&mut rng))
        })
        .collect();
    let fruits: Vec<Point3<f64>> = (0..28)
        .map(|_| {
            Point3::new(
                rng.gen_range(-0.9..0.9),
                rng.gen_range(0.3..0.5),
                rng.gen_range(0.5..1.5),
            )
        })
        .collect();
    let mut map = RoiMap::new(MapConfig::default())?;
    let mut scan_ms = Vec::new();
    let mut scans = 0;
    while map.len() < 1_000_000 && scans < 200 {
        let origin = Point3::new(rng.gen_range(-0.8..0.8), -0.4, rng.gen_range(0.6..1.4));
        let mut points = Vec::with_capacity(POINTS_PER_SCAN);
        let mut roi = Vec::with_capacity(POINTS_PER_SCAN);
        for i in 0..POINTS_PER_SCAN {
            let is_fruit = i % 4 == 0;
            let p = if is_fruit {
                fruits[rng.gen_range(0..fruits.len())] + unit(&mut rng) * 0.035
            } else {
                let (c, n) = leaves[rng.gen_range(0..leaves.len())];
                let t = n.cross(&unit(&mut rng)).normalize();
                c + t * rng.gen_range(0.0..0.06)
            };
            points.push(p.cast::<f32>());
            roi.push(is_fruit);
        }
        let t0 = Instant::now();
        map.insert_scan(&origin, &points, &roi)?;
        scan_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        map.take_changes();
        scans += 1;
    }
    scan_ms.sort_by(f64::total_cmp);
    println!(
        "map: {} voxels after {} scans of {} points, {:.0} MB; insert_scan median {:.1} ms, max {:.1} ms",
        map.len(),
        scans,
        POINTS_PER_SCAN,
        map.memory_bytes() as f64 / 1e6,
        scan_ms[scan_ms.len() / 2],
        scan_ms[scan_ms.len() - 1]
    );
    let ctx = PlanningContext {
        map: &map,
        world_from_camera: look_at(&Point3::new(0.0, -0.4, 1.0), &Point3::new(0.0, 0.4, 1.0)),
        camera_workspace: Aabb::new(Point3::new(-1.0, -0.6, 0.4), Point3::new(1.0, 0.1, 1.6)),
        sampling_region: Aabb::new(Point3::new(-1.1, -0.2, 0.3), Point3::new(1.1, 0.8, 1.7)),
        reach: None,
        motion_time: None,
        remembered_fruit: &[],
        settled_voxels: &[],
        roi_stalled: false,
    };
    for method in Method::ALL {
        let config = PlannerConfig {
            method,
            ..PlannerConfig::default()
        };
        let mut times = Vec::new();
        let mut last = None;
        for seed in 0..5 {
            let t0 = Instant::now();
            let plan = plan_views(&ctx, &config, seed)?;
            times.push(t0.elapsed().as_secs_f64() * 1e3);
            last = Some(plan);
        }
        times.sort_by(f64::total_cmp);
        if let Some(plan) = last {
            println!(
                "{method}: plan_views median {:.1} ms (max {:.1}); {} views ({:?}), best utility {:.3}, {} ROI targets, {} frontier, {} scored",
                times[2],
                times[4],
                plan.views.len(),
                plan.used_kind,
                plan.views.first().map_or(f64::NAN, |v| v.utility),
                plan.roi_targets,
                plan.exploration_frontier,
                plan.candidates_scored
            );
        }
    }
    let t0 = Instant::now();
    let clusters = map.clusters(10);
    let fruits_seen = FruitTracker::default().update(&clusters);
    println!(
        "clusters + tracker: {} fruits in {:.1} ms",
        fruits_seen.len(),
        t0.elapsed().as_secs_f64() * 1e3
    );
    Ok(())
}
