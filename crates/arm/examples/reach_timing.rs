//! Cost of the reachability map's build and of one `ViewReachability::can_reach` call per check,
//! over seeded random views around each scenario's robot.
//!
//! `cargo run --release -p glasshouse-arm --example reach_timing`

use std::sync::Arc;
use std::time::Instant;

use glasshouse_arm::{
    ArmError, Interval, ReachCheck, ReachabilityMap, ReachabilityParams, Robot, ViewReachability,
};
use glasshouse_geom::look_at;
use nalgebra::{Isometry3, Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const CALLS: usize = 20_000;

fn random_views(rng: &mut ChaCha8Rng, lo: [f64; 3], hi: [f64; 3]) -> Vec<Isometry3<f64>> {
    (0..CALLS)
        .map(|_| {
            let eye = Point3::new(
                rng.gen_range(lo[0]..hi[0]),
                rng.gen_range(lo[1]..hi[1]),
                rng.gen_range(lo[2]..hi[2]),
            );
            let dir = Vector3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            );
            look_at(&eye, &(eye + dir))
        })
        .collect()
}

fn main() -> Result<(), ArmError> {
    let params = ReachabilityParams::paper(&glasshouse_arm::ArmModel::ur5e());
    let started = Instant::now();
    let map = Arc::new(ReachabilityMap::build(&params)?);
    println!(
        "map build: {:.2} s ({} threads)",
        started.elapsed().as_secs_f64(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    // Boxes around each robot's working volume, a little larger than its reach.
    let robots = [
        (
            "scenario 1",
            Robot::scenario_one(),
            [-1.2, -1.2, 0.0],
            [1.2, 1.2, 2.2],
        ),
        (
            "scenario 2",
            Robot::scenario_two(),
            [-1.5, -1.5, 0.0],
            [1.5, 1.5, 2.4],
        ),
        (
            "row",
            Robot::row(Interval::new(0.0, 4.0)),
            [-0.5, -1.2, 0.0],
            [4.5, 1.2, 2.4],
        ),
    ];
    for (name, robot, lo, hi) in robots {
        let views = random_views(&mut rng, lo, hi);
        for check in [
            ReachCheck::Position,
            ReachCheck::Pose,
            ReachCheck::PoseClear,
        ] {
            let reach = ViewReachability::new(robot.clone(), Arc::clone(&map), check, 0.02)?;
            let started = Instant::now();
            let accepted = views.iter().filter(|v| reach.can_reach(v)).count();
            let per_call_us = started.elapsed().as_secs_f64() * 1e6 / CALLS as f64;
            println!(
                "{name:>10} {:>10}: {per_call_us:7.2} µs/call, {:5.1} % accepted",
                format!("{check:?}"),
                100.0 * accepted as f64 / CALLS as f64
            );
        }
    }
    Ok(())
}
