//! Frames that end with no reachable view, with and without the planner's reach filter.
//!
//! `cargo run --release -p glasshouse-eval --example reach -- [seeds] [budget_s] [checks] [scenarios]`
//! (defaults: 3 seeds, 180 s, `none,position,pose,pose-clear`, `1,2,row`). Scenario 1, 2 and the row,
//! Ours-UU, the edge's arm motion, 100 ms fixed compute time, 320x240 images.

use glasshouse_arm::ReachCheck;
use glasshouse_eval::{run_trial, ComputeTime, EvalError, TrialConfig, TrialResult};
use glasshouse_nbv::Method;
use glasshouse_sim::ScenarioKind;

fn parse_check(s: &str) -> Option<Option<ReachCheck>> {
    match s {
        "none" => Some(None),
        "position" => Some(Some(ReachCheck::Position)),
        "pose" => Some(Some(ReachCheck::Pose)),
        "pose-clear" => Some(Some(ReachCheck::PoseClear)),
        _ => None,
    }
}

fn main() -> Result<(), EvalError> {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(3);
    let budget_s: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(180.0);
    let checks: Vec<Option<ReachCheck>> = args
        .get(3)
        .map_or("none,position,pose,pose-clear", String::as_str)
        .split(',')
        .filter_map(parse_check)
        .collect();
    println!("| scenario | reach check | frames | frames with no reachable view | unreachable views / frame | views | fruits detected | covered volume |");
    println!("|---|---|---|---|---|---|---|---|");
    let scenarios: Vec<ScenarioKind> = args
        .get(4)
        .map_or("1,2,row", String::as_str)
        .split(',')
        .filter_map(|s| match s {
            "1" => Some(ScenarioKind::One),
            "2" => Some(ScenarioKind::Two),
            "row" => Some(ScenarioKind::Row),
            _ => None,
        })
        .collect();
    for &scenario in &scenarios {
        for &reach in &checks {
            let configs: Vec<TrialConfig> = (1..=seeds)
                .map(|seed| TrialConfig {
                    width: 320,
                    height: 240,
                    budget_s,
                    compute_time: ComputeTime::Fixed { ms: 100.0 },
                    reach,
                    ..TrialConfig::new(scenario, Method::OursUu, seed)
                })
                .collect();
            let results = run_all(&configs)?;
            print_row(scenario, reach, &results);
        }
    }
    Ok(())
}

/// Two trials at a time (one per core).
fn run_all(configs: &[TrialConfig]) -> Result<Vec<TrialResult>, EvalError> {
    let mut out = Vec::new();
    for pair in configs.chunks(2) {
        let results: Vec<Result<TrialResult, EvalError>> = std::thread::scope(|scope| {
            let workers: Vec<_> = pair
                .iter()
                .map(|&c| scope.spawn(move || run_trial(c, |_| {})))
                .collect();
            workers
                .into_iter()
                .map(|w| {
                    w.join().unwrap_or_else(|_| {
                        Err(EvalError::InvalidConfig("a trial panicked".to_string()))
                    })
                })
                .collect()
        });
        for r in results {
            out.push(r?);
        }
    }
    Ok(out)
}

fn print_row(scenario: ScenarioKind, reach: Option<ReachCheck>, results: &[TrialResult]) {
    let frames: u64 = results.iter().map(|r| r.frames).sum();
    let without: u64 = results.iter().map(|r| r.frames_without_view).sum();
    let unreachable: u64 = results.iter().map(|r| r.unreachable_views).sum();
    let views: u32 = results.iter().map(|r| r.views).sum();
    let n = results.len().max(1) as f64;
    let detected: f64 = results
        .iter()
        .filter_map(|r| {
            r.last()
                .map(|s| s.boxes.detected as f64 / r.fruits_total.max(1) as f64)
        })
        .sum::<f64>()
        / n;
    let covered: f64 = results
        .iter()
        .filter_map(|r| r.last().map(|s| s.boxes.covered_volume))
        .sum::<f64>()
        / n;
    let per_frame = |v: f64| v / frames.max(1) as f64;
    let check = reach.map_or("none".to_string(), |c| format!("{c:?}"));
    println!(
        "| {scenario:?} | {check} | {frames} | {without} ({:.1} %) | {:.2} | {views} | {:.1} % | {:.1} % |",
        100.0 * per_frame(without as f64),
        per_frame(unreachable as f64),
        100.0 * detected,
        100.0 * covered,
    );
}
