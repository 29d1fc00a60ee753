//! Experiments of the paper's Table I on the simulator (paper-method §5).
//!
//! I/O-free like the other algorithm crates: everything here turns inputs into values, strings or
//! PNG bytes; the `glasshouse eval` command writes them.
//!
//! - [`metrics`]: greedy one-to-one matching of estimates to ground truth and the Table I metrics;
//! - [`stats`]: mean ± std and the one-sided Mann-Whitney U test;
//! - [`trial`]: a seeded trial through the same detector and planner code the services run, on the
//!   simulator's clock, with the [`trial::Motion`] rule deciding reachability and motion time;
//! - [`reach`]: the planner's reach filter for a scene's robot ([`trial::TrialConfig::reach`]);
//! - [`report`]: per-trial CSV, Table I markdown, p-values and `summary.json`;
//! - [`plot`]: PNG line plots of the mean curves.

pub mod metrics;
pub mod plot;
pub mod reach;
pub mod report;
pub mod stats;
pub mod trial;

pub use metrics::{evaluate, greedy_match, BoxEstimate, Match, Metrics, MATCH_DISTANCE_M};
pub use report::{MethodRuns, METRICS};
pub use stats::{mann_whitney_u, mean_std, Alternative, MannWhitney, MeanStd};
pub use trial::{
    run_trial, ArmMotion, ComputeTime, EvalError, Executed, FreeCameraMotion, Motion, MotionKind,
    Sample, Trial, TrialConfig, TrialResult,
};
