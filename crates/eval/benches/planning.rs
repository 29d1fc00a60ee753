//! One planning iteration mid-run in scenario 2: sample and score the default 100 ROI-targeted and
//! 100 exploration candidates (200 in all) on the map a trial has built after 60 simulated
//! seconds of Ours-U_U. The target is 50 ms on one core; the two-thread row shows the
//! parallel scoring.

use criterion::{criterion_group, criterion_main, Criterion};
use glasshouse_eval::trial::{ArmMotion, Trial};
use glasshouse_eval::{ComputeTime, TrialConfig};
use glasshouse_nbv::{plan_views, Method, PlannerConfig};
use glasshouse_sim::ScenarioKind;

fn mid_run_trial(method: Method) -> Trial<ArmMotion> {
    let mut config = TrialConfig::new(ScenarioKind::Two, method, 3);
    config.compute_time = ComputeTime::Fixed { ms: 50.0 };
    let mut trial = Trial::new(config, ArmMotion::new).expect("scenario 2 trial");
    while trial.clock_s() < 60.0 {
        if !trial.step().expect("trial step") {
            break;
        }
    }
    trial
}

fn planning(c: &mut Criterion) {
    let mut group = c.benchmark_group("plan_views_scenario2_mid_run");
    group.sample_size(20);
    for method in [Method::OursUu, Method::OursUp] {
        let trial = mid_run_trial(method);
        let ctx = trial.planning_context();
        for threads in [1, 2] {
            let config = PlannerConfig {
                scoring_threads: threads,
                ..*trial.planner_config()
            };
            let plan = plan_views(&ctx, &config, trial.plan_seed()).expect("plan");
            eprintln!(
                "{method}: {} candidates scored, {} ROI targets, {} frontier voxels, {} known voxels",
                plan.candidates_scored,
                plan.roi_targets,
                plan.exploration_frontier,
                ctx.map.counts().known,
            );
            group.bench_function(format!("{method}_{threads}_threads"), |b| {
                b.iter(|| plan_views(&ctx, &config, trial.plan_seed()))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, planning);
criterion_main!(benches);
