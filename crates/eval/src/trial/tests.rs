#![allow(clippy::unwrap_used)]

use glasshouse_pipeline::Executed;
use glasshouse_proto::{ArmState, TrolleyInfo};
use nalgebra::Isometry3;

use glasshouse_sim::{PerceptionNoise, WorldSettings};

use super::*;

fn small(method: Method, budget_s: f64) -> TrialConfig {
    TrialConfig {
        width: 96,
        height: 72,
        budget_s,
        compute_time: ComputeTime::Fixed { ms: 50.0 },
        ..TrialConfig::new(ScenarioKind::Two, method, 3)
    }
}

#[test]
fn a_trial_samples_every_second_and_finds_fruit() {
    let result = run_trial(small(Method::OursUu, 20.0), |_| {}).unwrap();
    assert_eq!(result.samples.len(), 21);
    for (i, s) in result.samples.iter().enumerate() {
        assert_eq!(s.time_s, i as u32);
        assert!(s.boxes.detected <= result.fruits_total);
        assert!((0.0..=1.0).contains(&s.boxes.covered_volume));
    }
    // Nothing is known at 0 s; views and frames never decrease.
    assert_eq!(result.samples[0].frames, 0);
    assert_eq!(result.samples[0].boxes.detected, 0);
    assert!(result
        .samples
        .windows(2)
        .all(|w| w[0].views <= w[1].views && w[0].frames <= w[1].frames));
    let last = result.last().unwrap();
    assert!(last.boxes.detected > 0, "{last:?}");
    assert!(result.views > 3, "{}", result.views);
    // 50 ms per planning call entered the clock.
    assert!((result.compute_time_s - 0.05 * result.frames as f64).abs() < 1e-9);
    // One ranked list per frame, planned on that frame.
    assert_eq!(result.plans.len() as u64, result.frames);
    for (i, plan) in result.plans.iter().enumerate() {
        assert_eq!(plan.based_on_seq, i as u64 + 1);
    }
}

#[test]
fn each_plan_s_best_view_is_kept_with_when_it_was_planned_and_what_was_found_by_then() {
    let result = run_trial(small(Method::OursUu, 20.0), |_| {}).unwrap();
    assert_eq!(result.best_views.len(), result.plans.len());
    for (best, plan) in result.best_views.iter().zip(&result.plans) {
        let first = &plan.views[0];
        assert_eq!(best.utility as f32, first.utility);
        assert_eq!(best.gain as f32, first.gain);
        assert!(best.motion_s.is_some_and(|t| t >= 0.0), "{best:?}");
        assert!(best.detected <= result.fruits_total);
    }
    // Each view costs its motion, a capture and 50 ms of planning before the next plan.
    for pair in result.best_views.windows(2) {
        assert!(
            pair[1].planned_at_s >= pair[0].planned_at_s + 0.05,
            "{pair:?}"
        );
    }
    let last = result.best_views.last().unwrap();
    assert!(last.planned_at_s <= 20.0);
    // The samples see what the plans saw: the fruits detected at the last plan are those of
    // the second it was planned in.
    let second = last.planned_at_s.ceil() as usize;
    assert_eq!(result.samples[second].boxes.detected, last.detected);
    let csv = crate::report::best_views_csv(&result);
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines[0], crate::report::VIEWS_CSV_HEADER);
    assert_eq!(lines.len(), result.best_views.len() + 1);
    assert!(lines[1..].iter().all(|l| l
        .split(',')
        .nth(1)
        .is_some_and(|k| k == "roi" || k == "exploration")));
}

#[test]
fn fixed_compute_time_replays_exactly() {
    let config = small(Method::ExploUp, 8.0);
    let (a, b) = (
        run_trial(config, |_| {}).unwrap(),
        run_trial(config, |_| {}).unwrap(),
    );
    assert_eq!(
        serde_json::to_string(&a.samples).unwrap(),
        serde_json::to_string(&b.samples).unwrap()
    );
    assert_eq!(a.views, b.views);
    assert_eq!(a.plans, b.plans);
}

/// The simulated trolley with an arm that reaches nothing: every frame costs a capture and the
/// camera never moves.
struct Stuck(SimTrolley);

impl TrolleySource for Stuck {
    fn info(&self) -> TrolleyInfo {
        self.0.info()
    }
    fn ground_truth(&self) -> Option<Vec<glasshouse_geom::FruitEstimate>> {
        self.0.ground_truth()
    }
    fn capture(&mut self, frame_seq: u64) -> Result<Option<RgbdFrame>, String> {
        self.0.capture(frame_seq)
    }
    fn arm_state(&self, moving: bool, views_done: u32) -> ArmState {
        self.0.arm_state(moving, views_done)
    }
    fn execute(&mut self, _: &[Isometry3<f64>]) -> Option<Executed> {
        None
    }
    fn next_segment(&mut self) -> Option<f64> {
        None
    }
}

#[test]
fn unreachable_views_cost_a_capture_each() {
    let config = TrialConfig {
        capture_time_s: 1.0,
        compute_time: ComputeTime::Fixed { ms: 0.0 },
        ..small(Method::OursUu, 4.5)
    };
    let source = Stuck(SimTrolley::new(config.sim()).unwrap());
    let result = Trial::with_source(config, source)
        .unwrap()
        .run(|_| {})
        .unwrap();
    assert_eq!(result.views, 0);
    // Frames at 0, 1, 2, 3, 4 s.
    assert_eq!(result.frames, 5);
    assert_eq!(result.frames_without_reachable_view, 5);
    assert!(result.unreachable_views > 0);
    assert_eq!(result.samples.len(), 5);
    // A frame captured at t is available at t (0 ms compute): sample t sees frame t + 1.
    for (t, s) in result.samples.iter().enumerate() {
        assert_eq!(s.frames, t as u64 + 1);
    }
}

#[test]
fn bad_configurations_are_rejected() {
    let bad = [
        TrialConfig {
            width: 0,
            ..small(Method::OursUu, 5.0)
        },
        TrialConfig {
            budget_s: f64::NAN,
            ..small(Method::OursUu, 5.0)
        },
        TrialConfig {
            compute_time: ComputeTime::Fixed { ms: -1.0 },
            ..small(Method::OursUu, 5.0)
        },
        TrialConfig {
            capture_time_s: 0.0,
            compute_time: ComputeTime::Fixed { ms: 0.0 },
            ..small(Method::OursUu, 5.0)
        },
        TrialConfig {
            segment_length_m: 0.0,
            ..small(Method::OursUu, 5.0)
        },
        TrialConfig {
            world: WorldSettings {
                perception: PerceptionNoise {
                    label_noise: 1.5,
                    silhouette_px: 0,
                    ..Default::default()
                },
                ..Default::default()
            },
            ..small(Method::OursUu, 5.0)
        },
    ];
    for config in bad {
        assert!(matches!(
            Trial::new(config),
            Err(EvalError::InvalidConfig(_)) | Err(EvalError::Capture(_))
        ));
    }
}

/// The trial's perception noise reaches its frames (other plans, other fruits than the clean
/// detector on the same scene), and the fruit counts add up.
#[test]
fn perception_noise_reaches_the_trial_and_the_counts_add_up() {
    let clean = run_trial(small(Method::OursUu, 20.0), |_| {}).unwrap();
    let noisy_config = TrialConfig {
        world: WorldSettings {
            perception: PerceptionNoise {
                label_noise: 0.3,
                silhouette_px: 1,
                ..Default::default()
            },
            ..Default::default()
        },
        ..small(Method::OursUu, 20.0)
    };
    let noisy = run_trial(noisy_config, |_| {}).unwrap();
    assert_ne!(clean.plans, noisy.plans);
    for result in [&clean, &noisy] {
        let last = result.last().unwrap();
        let counts = last.boxes.counts;
        assert_eq!(last.estimates, last.boxes.detected + counts.false_fruits);
        let recall = last.boxes.detected as f64 / result.fruits_total as f64;
        assert!((counts.recall - recall).abs() < 1e-12, "{counts:?}");
        let ratio = last.estimates as f64 / result.fruits_total as f64;
        assert!((counts.count_ratio - ratio).abs() < 1e-12, "{counts:?}");
    }
}
