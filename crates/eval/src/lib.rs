//! Experiments of the paper's Table I on the simulator (paper-method §5).
//!
//! I/O-free like the other algorithm crates: everything here turns inputs into values, strings or
//! PNG bytes; the `glasshouse eval` command writes them.
//!
//! - [`metrics`]: greedy one-to-one matching of estimates to ground truth, the Table I metrics
//!   and the fruit counts that show inflation (count ratio, precision, recall, F1, false fruits,
//!   time to 95 %);
//! - [`stats`]: mean ± std and the one-sided Mann-Whitney U test;
//! - [`trial`]: a seeded trial through the same steps the services run ([`glasshouse_pipeline`]: the
//!   edge's state machine, detection, the per-trolley planner), on the simulator's clock;
//! - [`report`]: per-trial CSV, Table I markdown, p-values and `summary.json`;
//! - [`plot`]: PNG line plots of the mean curves.

pub mod metrics;
pub mod plot;
pub mod report;
pub mod stats;
pub mod trial;
pub mod visits;

/// How detections enter the planner's map, an experiment's choice.
pub use glasshouse_pipeline::{RoiEvidence, RoiTargets};
pub use metrics::{
    covered_volume, evaluate, evaluate_against, greedy_match, time_to_detect_s, FruitCounts, Match,
    Metrics, TruthMeasure, MATCH_DISTANCE_M,
};
pub use report::{Better, MethodRuns, DETECTED_SHARE, METRICS};
pub use stats::{mann_whitney_u, mean_std, Alternative, MannWhitney, MeanStd};
pub use trial::{
    run_trial, run_trial_with, ComputeTime, EvalError, Sample, Trial, TrialConfig, TrialResult,
};
