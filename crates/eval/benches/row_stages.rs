//! Where a planner's time per frame goes along the row. A seeded row trial runs for the given
//! simulated minutes with the planner's compute measured; every minute it prints the planner's
//! mean compute per frame over that minute (integrate, cluster, track and plan; the fits are
//! made when the fruits are published), the fruits refitted per frame, and, timed on the map
//! held then, ROI clustering over the whole map, the touching-fruit split over its clusters,
//! fitting every fruit afresh, and one plan. A stage whose time grows from minute 1 to the end
//! works over the whole row rather than what the scan changed. `cargo bench -p glasshouse-eval --bench row_stages [-- MINUTES]` (default 10).

use std::time::Instant;

use glasshouse_eval::{ComputeTime, Trial, TrialConfig};
use glasshouse_nbv::fit::fit_ellipsoid;
use glasshouse_nbv::split::split_touching;
use glasshouse_nbv::Method;
use glasshouse_sim::ScenarioKind;

/// Median milliseconds of `runs` calls of `f`.
fn median_ms(runs: usize, mut f: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..runs)
        .map(|_| {
            let started = Instant::now();
            f();
            started.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[runs / 2]
}

/// Per-minute totals of the trial's frames, compute and refits.
#[derive(Default, Clone, Copy)]
struct Totals {
    frames: u64,
    compute_s: f64,
    refits: usize,
}

fn report(trial: &Trial, minute: &Totals) {
    let planner = trial.planner();
    let map = planner.map();
    let min_voxels = planner.settings().min_cluster_voxels;
    let clusters = map.clusters(min_voxels);
    let fit_config = planner.settings().fit;
    let (pose, seq) = (trial.world_from_camera(), trial.frame_seq());
    let cluster_ms = median_ms(5, || _ = std::hint::black_box(map.clusters(min_voxels)));
    let split_ms = median_ms(5, || {
        _ = std::hint::black_box(split_touching(
            map,
            clusters.clone(),
            min_voxels,
            &fit_config,
        ))
    });
    let fit_all_ms = median_ms(3, || {
        clusters
            .iter()
            .for_each(|c| _ = std::hint::black_box(fit_ellipsoid(map, c, &fit_config)))
    });
    let plan_ms = median_ms(3, || {
        _ = std::hint::black_box(planner.plan(&pose, seq).expect("plan"))
    });
    let frames = minute.frames.max(1) as f64;
    println!(
        "{:>6.0} {:>6} {:>10} {:>7} {:>6} {:>12.1} {:>8.1} {:>10.1} {:>8.1} {:>10.1} {:>8.1}",
        trial.clock_s(),
        seq,
        map.len(),
        map.roi_voxels().len(),
        clusters.len(),
        minute.compute_s * 1e3 / frames,
        minute.refits as f64 / frames,
        cluster_ms,
        split_ms,
        fit_all_ms,
        plan_ms,
    );
}

fn main() {
    let minutes: u32 = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(10);
    let mut config = TrialConfig::new(ScenarioKind::Row, Method::OursUu, 1);
    config.compute_time = ComputeTime::Measured;
    config.budget_s = f64::from(minutes) * 60.0;
    let mut trial = Trial::new(config).expect("row trial");
    println!(
        "{:>6} {:>6} {:>10} {:>7} {:>6} {:>12} {:>8} {:>10} {:>8} {:>10} {:>8}",
        "sim_s",
        "frame",
        "known_vox",
        "roi_vox",
        "fruits",
        "planner_ms/f",
        "refits/f",
        "cluster_ms",
        "split_ms",
        "fit_all_ms",
        "plan_ms"
    );
    let (mut minute, mut next_minute) = (Totals::default(), 1);
    let mut last = (trial.frame_seq(), trial.compute_time_s());
    while trial.step().expect("trial step") {
        let now = (trial.frame_seq(), trial.compute_time_s());
        if now.0 != last.0 {
            minute.frames += now.0 - last.0;
            minute.compute_s += now.1 - last.1;
            minute.refits += trial.planner().last_refits();
            last = now;
        }
        if trial.clock_s() >= f64::from(next_minute) * 60.0 {
            report(&trial, &minute);
            (minute, next_minute) = (Totals::default(), next_minute + 1);
        }
    }
}
