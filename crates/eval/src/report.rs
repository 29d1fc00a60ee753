//! What an experiment writes: per-trial CSV, Table I in markdown, p-values, `summary.json`, and
//! the mean curves the plots draw. Pure functions from trial results to strings and values.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use glasshouse_nbv::Method;
use serde_json::{json, Map, Value};

use crate::metrics::{greedy_match, volume_accuracy, MATCH_DISTANCE_M};
use crate::stats::{mann_whitney_u, mean_std, Alternative};
use crate::trial::{Sample, TrialResult};
use glasshouse_nbv::evidence::Verdict;
use glasshouse_pipeline::ClusterOutcome;

/// Which values of a metric are better.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Better {
    Higher,
    Lower,
    /// Neither direction (the count ratio is best at 1): no one-sided test.
    Neither,
}

/// One reported metric: its key, its Table I label and which direction is better.
#[derive(Clone, Copy, Debug)]
pub struct MetricDef {
    pub key: &'static str,
    pub label: &'static str,
    pub better: Better,
    /// Decimals in the table.
    pub decimals: usize,
    pub value: fn(&Sample) -> f64,
}

/// The metrics reported at the end of the budget, in table order. `volume_accuracy` keeps every
/// matched pair; the `_gt05` variants keep pairs with accuracy > 0.5 only (the published plots'
/// rule). `_fitted` variants use the fitted ellipsoid estimates (centre; box around it; its box
/// volume `8·a·b·c`, comparable with the truth's box volume). The fruit counts (count ratio,
/// precision, recall, F1, false fruits) are those of the box estimates.
pub const METRICS: [MetricDef; 18] = [
    MetricDef {
        key: "detected",
        label: "detected ROIs",
        better: Better::Higher,
        decimals: 1,
        value: |s| s.boxes.detected as f64,
    },
    MetricDef {
        key: "covered_volume",
        label: "covered ROI volume",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.covered_volume,
    },
    MetricDef {
        key: "center_distance_cm",
        label: "centre distance (cm)",
        better: Better::Lower,
        decimals: 2,
        value: |s| s.boxes.center_distance_cm,
    },
    MetricDef {
        key: "volume_accuracy",
        label: "volume accuracy",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.volume_accuracy,
    },
    MetricDef {
        key: "volume_accuracy_gt05",
        label: "volume accuracy (pairs > 0.5)",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.volume_accuracy_gt05,
    },
    MetricDef {
        key: "volume_accuracy_fitted",
        label: "volume accuracy, fitted",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.fitted.volume_accuracy,
    },
    MetricDef {
        key: "volume_accuracy_fitted_gt05",
        label: "volume accuracy, fitted (pairs > 0.5)",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.fitted.volume_accuracy_gt05,
    },
    MetricDef {
        key: "detected_fitted",
        label: "detected ROIs, fitted",
        better: Better::Higher,
        decimals: 1,
        value: |s| s.fitted.detected as f64,
    },
    MetricDef {
        key: "covered_volume_fitted",
        label: "covered ROI volume, fitted",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.fitted.covered_volume,
    },
    MetricDef {
        key: "center_distance_cm_fitted",
        label: "centre distance (cm), fitted",
        better: Better::Lower,
        decimals: 2,
        value: |s| s.fitted.center_distance_cm,
    },
    MetricDef {
        key: "count_ratio",
        label: "count ratio (reported ÷ true fruits)",
        better: Better::Neither,
        decimals: 2,
        value: |s| s.boxes.counts.count_ratio,
    },
    MetricDef {
        key: "precision",
        label: "fruit precision",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.counts.precision,
    },
    MetricDef {
        key: "recall",
        label: "fruit recall",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.counts.recall,
    },
    MetricDef {
        key: "f1",
        label: "fruit F1",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.counts.f1,
    },
    MetricDef {
        key: "precision_5cm",
        label: "fruit precision, centres within 5 cm",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.counts_near.precision,
    },
    MetricDef {
        key: "recall_5cm",
        label: "fruit recall, centres within 5 cm",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.counts_near.recall,
    },
    MetricDef {
        key: "f1_5cm",
        label: "fruit F1, centres within 5 cm",
        better: Better::Higher,
        decimals: 2,
        value: |s| s.boxes.counts_near.f1,
    },
    MetricDef {
        key: "false_fruits",
        label: "false fruits",
        better: Better::Lower,
        decimals: 1,
        value: |s| s.boxes.counts.false_fruits as f64,
    },
];

/// Share of the true fruits whose detection time is reported.
pub const DETECTED_SHARE: f64 = 0.95;

/// The trials of one method, in trial order.
#[derive(Clone, Debug)]
pub struct MethodRuns {
    pub method: Method,
    pub trials: Vec<TrialResult>,
}

impl MethodRuns {
    /// The metric at the end of the budget, one value per trial (NaN = no value).
    pub fn final_values(&self, metric: &MetricDef) -> Vec<f64> {
        self.trials
            .iter()
            .map(|t| t.last().map_or(f64::NAN, metric.value))
            .collect()
    }

    /// The metric at simulated second `time_s`, one value per trial (NaN where a trial has no
    /// sample that late).
    pub fn values_at(&self, metric: &MetricDef, time_s: u32) -> Vec<f64> {
        self.trials
            .iter()
            .map(|t| {
                t.samples
                    .get(time_s as usize)
                    .map_or(f64::NAN, metric.value)
            })
            .collect()
    }
}

/// Seconds at which the over-time tables and p-values are given: every 30 s before the budget.
pub fn checkpoints(budget_s: f64) -> Vec<u32> {
    (1..)
        .map(|k| 30 * k)
        .take_while(|&t| f64::from(t) < budget_s)
        .collect()
}

/// The paper's label of a method, e.g. `Ours-U_P`.
pub fn method_label(method: Method) -> &'static str {
    match method {
        Method::OursUu => "Ours-U_U",
        Method::OursUp => "Ours-U_P",
        Method::ExploUu => "Explo-U_U",
        Method::ExploUp => "Explo-U_P",
    }
}

/// The metrics the over-time tables follow: the paper's finding is about these two.
pub const OVER_TIME_METRICS: [MetricDef; 2] = [METRICS[0], METRICS[1]];

/// Header of the per-trial CSV.
pub const CSV_HEADER: &str = "time_s,views,frames,estimates,mean_confidence,\
detected,center_distance_cm,volume_accuracy,volume_accuracy_gt05,covered_volume,\
fitted_detected,fitted_center_distance_cm,fitted_volume_accuracy,fitted_volume_accuracy_gt05,fitted_covered_volume,\
count_ratio,precision,recall,f1,false_fruits,\
fitted_precision,fitted_recall,fitted_f1,fitted_false_fruits";

/// A number for CSV: empty for NaN, otherwise fixed 6 decimals (bit-stable across runs).
fn csv_num(v: f64) -> String {
    if v.is_nan() {
        String::new()
    } else {
        format!("{v:.6}")
    }
}

/// The per-second samples of one trial as CSV.
pub fn trial_csv(result: &TrialResult) -> String {
    let mut out = String::from(CSV_HEADER);
    out.push('\n');
    for s in &result.samples {
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            s.time_s,
            s.views,
            s.frames,
            s.estimates,
            csv_num(s.mean_confidence),
            s.boxes.detected,
            csv_num(s.boxes.center_distance_cm),
            csv_num(s.boxes.volume_accuracy),
            csv_num(s.boxes.volume_accuracy_gt05),
            csv_num(s.boxes.covered_volume),
            s.fitted.detected,
            csv_num(s.fitted.center_distance_cm),
            csv_num(s.fitted.volume_accuracy),
            csv_num(s.fitted.volume_accuracy_gt05),
            csv_num(s.fitted.covered_volume),
            csv_num(s.boxes.counts.count_ratio),
            csv_num(s.boxes.counts.precision),
            csv_num(s.boxes.counts.recall),
            csv_num(s.boxes.counts.f1),
            s.boxes.counts.false_fruits,
            csv_num(s.fitted.counts.precision),
            csv_num(s.fitted.counts.recall),
            csv_num(s.fitted.counts.f1),
            s.fitted.counts.false_fruits,
        );
    }
    out
}

/// Header of the per-trial views CSV ([`best_views_csv`]).
pub const VIEWS_CSV_HEADER: &str = "planned_at_s,kind,utility,gain,cost_m,motion_s,detected";

/// The best view of every plan of one trial, in order: when it was planned, its list, scores
/// and motion time, and the fruits detected then. The time to the next row is what the view
/// cost (motion, capture, plan), the change in `detected` what it found.
pub fn best_views_csv(result: &TrialResult) -> String {
    let mut out = String::from(VIEWS_CSV_HEADER);
    out.push('\n');
    for view in &result.best_views {
        let kind = match view.kind {
            glasshouse_nbv::ViewKind::Roi => "roi",
            glasshouse_nbv::ViewKind::Exploration => "exploration",
        };
        let _ = writeln!(
            out,
            "{},{kind},{},{},{},{},{}",
            csv_num(view.planned_at_s),
            csv_num(view.utility),
            csv_num(view.gain),
            csv_num(view.cost_m),
            view.motion_s.map(csv_num).unwrap_or_default(),
            view.detected,
        );
    }
    out
}

/// Header of the per-trial fruit CSV.
pub const FRUITS_CSV_HEADER: &str = "truth_id,truth_x_m,truth_y_m,truth_z_m,\
truth_half_x_m,truth_half_y_m,truth_half_z_m,estimate_id,voxels,fit_kind,fit_confidence,\
fitted_x_m,fitted_y_m,fitted_z_m,semi_x_m,semi_y_m,semi_z_m,\
fitted_distance_cm,fitted_volume_accuracy,box_distance_cm,box_volume_accuracy,\
truth_body_volume_m3,fitted_volume_m3";

const CLUSTERS_CSV_HEADER: &str = "x_m,y_m,z_m,voxels,length_m,width_m,depth_m,bulge,verdict,\
fragment,reported,unknown_inside,free_inside,occupied_inside,roi_inside,nearest_truth_id,nearest_truth_cm,\
body";

/// Every ROI cluster at the end of one trial, reported as a fruit or not, with why (the fruit
/// evidence's verdict, a fragment) and the nearest true fruit: where recall and precision are
/// lost ([`glasshouse_nbv::evidence`]).
pub fn clusters_csv(result: &TrialResult) -> String {
    let mut out = String::from(CLUSTERS_CSV_HEADER);
    out.push('\n');
    for cluster in &result.clusters {
        let nearest = result
            .truths
            .iter()
            .map(|t| (t.id, (t.centre - cluster.centre).norm()))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let inside = cluster.interior;
        let count = |n: Option<u32>| n.map(|n| n.to_string()).unwrap_or_default();
        let mut cells: Vec<String> = cluster.centre.iter().map(|v| csv_num(*v)).collect();
        cells.push(cluster.voxels.to_string());
        cells.extend(cluster.shape.extents_m.iter().map(|v| csv_num(*v)));
        cells.push(csv_num(cluster.shape.bulge));
        cells.push(format!("{:?}", cluster.verdict).to_lowercase());
        cells.push(cluster.fragment.to_string());
        cells.push(cluster.is_reported().to_string());
        cells.push(count(inside.map(|i| i.unknown)));
        cells.push(count(inside.map(|i| i.free)));
        cells.push(count(inside.map(|i| i.occupied)));
        cells.push(count(inside.map(|i| i.occupied_roi)));
        cells.push(nearest.map(|n| n.0.to_string()).unwrap_or_default());
        cells.push(nearest.map(|n| csv_num(100.0 * n.1)).unwrap_or_default());
        cells.push(cluster.body.to_string());
        out.push_str(&cells.join(","));
        out.push('\n');
    }
    out
}

/// A true fruit missed is put down to the largest cluster this near it whose nearest true
/// fruit it is ([`missed_reasons`]).
pub const MISSED_NEAR_M: f64 = 0.08;

/// Why each true fruit that no fitted estimate matched (the matching of [`fruits_csv`]) was
/// missed, counted by reason: the outcome of the largest cluster within [`MISSED_NEAR_M`] whose
/// nearest true fruit it is (too small, flat, a sheet, …), or no such cluster.
pub fn missed_reasons(result: &TrialResult) -> BTreeMap<&'static str, usize> {
    let fitted: Vec<_> = result
        .fruits
        .iter()
        .map(|f| f.solid_or_box().centre)
        .collect();
    let truths: Vec<_> = result.truths.iter().map(|t| t.centre).collect();
    let matches = greedy_match(&fitted, &truths, MATCH_DISTANCE_M);
    let mut reasons = BTreeMap::new();
    for (t, truth) in truths.iter().enumerate() {
        if matches.iter().any(|m| m.truth == t) {
            continue;
        }
        let nearest_is = |c: &&ClusterOutcome| {
            let d = (c.centre - truth).norm();
            d <= MISSED_NEAR_M && truths.iter().all(|o| (c.centre - o).norm() >= d)
        };
        let largest = result
            .clusters
            .iter()
            .filter(nearest_is)
            .max_by_key(|c| c.voxels);
        *reasons.entry(missed_reason(largest)).or_insert(0) += 1;
    }
    reasons
}

fn missed_reason(cluster: Option<&ClusterOutcome>) -> &'static str {
    let Some(cluster) = cluster else {
        return "no cluster within 8 cm";
    };
    match cluster.verdict {
        Verdict::TooSmall => "too small",
        Verdict::Thin => "thin",
        Verdict::TooLarge => "too large",
        Verdict::Flat => "flat",
        Verdict::Sheet => "a sheet (its solid hides nothing)",
        Verdict::Fruit if cluster.fragment => "a second patch of another fruit",
        Verdict::Fruit => "reported, but matched to another fruit",
    }
}

/// The final estimates of one trial against the true fruits, one row per true fruit (estimate
/// columns empty when missed) and one per false fruit (truth columns empty). The pairs are the
/// fitted estimates' matching, so a row says why a trial's fitted figures are what they are:
/// the fitted solid is judged against the body (its centroid and volume), the box against the
/// box, as in the table ([`crate::metrics::TruthMeasure`]).
pub fn fruits_csv(result: &TrialResult) -> String {
    let solids: Vec<_> = result.fruits.iter().map(|f| f.solid_or_box()).collect();
    let fitted: Vec<_> = solids.iter().map(|s| s.centre).collect();
    let truths: Vec<_> = result.truths.iter().map(|t| t.centre).collect();
    let matches = greedy_match(&fitted, &truths, MATCH_DISTANCE_M);
    let mut rows: Vec<(Option<usize>, Option<usize>)> = (0..truths.len())
        .map(|t| {
            (
                Some(t),
                matches.iter().find(|m| m.truth == t).map(|m| m.estimate),
            )
        })
        .collect();
    rows.extend(
        (0..fitted.len())
            .filter(|e| !matches.iter().any(|m| m.estimate == *e))
            .map(|e| (None, Some(e))),
    );
    let mut out = String::from(FRUITS_CSV_HEADER);
    out.push('\n');
    for (truth, estimate) in rows {
        let mut cells: Vec<String> = Vec::with_capacity(23);
        let t = truth.map(|t| &result.truths[t]);
        match t {
            Some(t) => {
                cells.push(t.id.to_string());
                cells.extend(
                    t.centre
                        .iter()
                        .chain(t.half_extents_m.iter())
                        .map(|v| csv_num(*v)),
                );
            }
            None => cells.extend(std::iter::repeat_n(String::new(), 7)),
        }
        match estimate.map(|e| (&result.fruits[e], &solids[e])) {
            Some((f, s)) => {
                cells.push(f.id.to_string());
                cells.push(f.voxel_count.to_string());
                cells.push(format!("{:?}", s.kind).to_lowercase());
                cells.push(csv_num(s.confidence));
                cells.extend(
                    s.centre
                        .iter()
                        .chain(s.semi_axes_m.iter())
                        .map(|v| csv_num(*v)),
                );
                let versus = |centre: &nalgebra::Point3<f64>, volume_m3: f64, body: bool| match t {
                    Some(t) => {
                        let (true_centre, true_m3) = match body {
                            true => (t.body_centre, t.body_volume_m3),
                            false => (t.centre, t.volume_m3),
                        };
                        [
                            csv_num((centre - true_centre).norm() * 100.0),
                            csv_num(volume_accuracy(volume_m3, true_m3)),
                        ]
                    }
                    None => [String::new(), String::new()],
                };
                cells.extend(versus(&s.centre, s.volume_m3, true));
                cells.extend(versus(&f.centre, f.volume_m3, false));
                cells.push(t.map_or(String::new(), |t| csv_num(t.body_volume_m3)));
                cells.push(csv_num(s.volume_m3));
            }
            None => {
                cells.extend(std::iter::repeat_n(String::new(), 14));
                cells.push(t.map_or(String::new(), |t| csv_num(t.body_volume_m3)));
                cells.push(String::new());
            }
        }
        out.push_str(&cells.join(","));
        out.push('\n');
    }
    out
}

/// `"ours-uu > explo-uu"` (or `<` for lower-is-better metrics) → one-sided p-value that the Ours
/// method is better, per metric. Pairs without values on either side are left out.
pub fn p_values(runs: &[MethodRuns]) -> BTreeMap<&'static str, BTreeMap<String, f64>> {
    p_values_of(runs, &METRICS, |run, metric| run.final_values(metric))
}

/// [`p_values`] of `metrics` at simulated second `time_s`.
pub fn p_values_at(
    runs: &[MethodRuns],
    metrics: &[MetricDef],
    time_s: u32,
) -> BTreeMap<&'static str, BTreeMap<String, f64>> {
    p_values_of(runs, metrics, |run, metric| run.values_at(metric, time_s))
}

fn p_values_of(
    runs: &[MethodRuns],
    metrics: &[MetricDef],
    values: impl Fn(&MethodRuns, &MetricDef) -> Vec<f64>,
) -> BTreeMap<&'static str, BTreeMap<String, f64>> {
    let mut out = BTreeMap::new();
    for metric in metrics {
        let (alternative, sign) = match metric.better {
            Better::Higher => (Alternative::Greater, ">"),
            Better::Lower => (Alternative::Less, "<"),
            Better::Neither => continue,
        };
        let mut per_pair = BTreeMap::new();
        for ours in runs.iter().filter(|r| r.method.uses_roi_sampling()) {
            for explo in runs.iter().filter(|r| !r.method.uses_roi_sampling()) {
                if let Some(test) =
                    mann_whitney_u(&values(ours, metric), &values(explo, metric), alternative)
                {
                    per_pair.insert(
                        format!("{} {sign} {}", ours.method, explo.method),
                        test.p_value,
                    );
                }
            }
        }
        out.insert(metric.key, per_pair);
    }
    out
}

/// `{"<metric>": {"<pair>": p}}`.
fn p_values_json(p: BTreeMap<&'static str, BTreeMap<String, f64>>) -> Value {
    let p_json: Map<String, Value> = p
        .into_iter()
        .map(|(metric, pairs)| {
            let pairs: Map<String, Value> =
                pairs.into_iter().map(|(k, v)| (k, number(v))).collect();
            (metric.to_string(), Value::Object(pairs))
        })
        .collect();
    Value::Object(p_json)
}

fn number(v: f64) -> Value {
    serde_json::Number::from_f64(v).map_or(Value::Null, Value::Number)
}

/// `{"mean", "std", "n"}` of the values (NaN skipped; nulls and n = 0 without values).
fn stats_json(values: &[f64]) -> Value {
    match mean_std(values) {
        Some(m) => json!({"mean": number(m.mean), "std": number(m.std), "n": m.n}),
        None => json!({"mean": null, "std": null, "n": 0}),
    }
}

/// `summary.json`: per method and metric the mean and sample std over trials at the end of the
/// budget (`null` without values), `fruits_total` (fruits per scene, the mean over trials when
/// scenes differ), `p_values` (see [`p_values`]) and the run's settings under `settings`.
pub fn summary_json(runs: &[MethodRuns], settings: Value) -> Value {
    let mut root = Map::new();
    let mut fruit_counts = Vec::new();
    for run in runs {
        let mut metrics = Map::new();
        for metric in &METRICS {
            metrics.insert(
                metric.key.to_string(),
                stats_json(&run.final_values(metric)),
            );
        }
        let views: Vec<f64> = run.trials.iter().map(|t| f64::from(t.views)).collect();
        if !views.is_empty() {
            metrics.insert("views".into(), stats_json(&views));
        }
        // Over the trials that reached the share; `n` says how many did.
        let detect_times: Vec<f64> = run
            .trials
            .iter()
            .filter_map(|t| t.time_to_detect_s(DETECTED_SHARE))
            .map(f64::from)
            .collect();
        metrics.insert("time_to_95_s".into(), stats_json(&detect_times));
        fruit_counts.extend(run.trials.iter().map(|t| t.fruits_total as f64));
        root.insert(run.method.to_string(), Value::Object(metrics));
    }
    let fruits_total = match mean_std(&fruit_counts) {
        Some(m) if m.std == 0.0 => json!(m.mean as u64),
        Some(m) => number(m.mean),
        None => json!(0),
    };
    root.insert("fruits_total".into(), fruits_total);
    root.insert("p_values".into(), p_values_json(p_values(runs)));
    let budget_s = runs
        .iter()
        .flat_map(|r| &r.trials)
        .map(|t| t.config.budget_s)
        .fold(0.0, f64::max);
    let over_time: Map<String, Value> = checkpoints(budget_s)
        .into_iter()
        .map(|t| {
            let per_metric = p_values_json(p_values_at(runs, &OVER_TIME_METRICS, t));
            (t.to_string(), per_metric)
        })
        .collect();
    root.insert("p_values_at_s".into(), Value::Object(over_time));
    root.insert("settings".into(), settings);
    Value::Object(root)
}

fn cell(values: &[f64], decimals: usize) -> String {
    match mean_std(values) {
        Some(m) => format!("{:.*} ± {:.*}", decimals, m.mean, decimals, m.std),
        None => "–".to_string(),
    }
}

/// A markdown table's header: the `first` columns, then one per method.
fn write_method_header(out: &mut String, first: &[&str], runs: &[MethodRuns]) {
    let _ = write!(out, "|");
    for column in first {
        let _ = write!(out, " {column} |");
    }
    for r in runs {
        let _ = write!(out, " {} |", method_label(r.method));
    }
    let _ = write!(out, "\n|{}", "---|".repeat(first.len() + runs.len()));
    out.push('\n');
}

/// The missed fruits by reason ([`missed_reasons`]), summed over each method's trials; nothing
/// when no trial kept its clusters.
fn write_missed(out: &mut String, runs: &[MethodRuns]) {
    let trials = || runs.iter().flat_map(|r| &r.trials);
    if trials().all(|t| t.clusters.is_empty()) {
        return;
    }
    let per_method: Vec<BTreeMap<&str, usize>> = runs
        .iter()
        .map(|r| {
            let mut sum = BTreeMap::new();
            for (reason, n) in r.trials.iter().flat_map(missed_reasons) {
                *sum.entry(reason).or_insert(0) += n;
            }
            sum
        })
        .collect();
    let reasons: std::collections::BTreeSet<&str> =
        per_method.iter().flat_map(|m| m.keys().copied()).collect();
    let _ = writeln!(
        out,
        "\n## Missed fruits by reason (sum over trials)\n\n\
         Each true fruit no fitted estimate matched, put down to the largest cluster within 8 cm \
         whose nearest true fruit it is (`trials/*-clusters.csv`).\n"
    );
    write_method_header(out, &["reason"], runs);
    for reason in reasons {
        let _ = write!(out, "| {reason} |");
        for m in &per_method {
            let _ = write!(out, " {} |", m.get(reason).copied().unwrap_or(0));
        }
        out.push('\n');
    }
}

/// Table I in markdown (mean ± std over trials at the end of the budget), then the p-values.
pub fn table_markdown(scenario: &str, runs: &[MethodRuns], budget_s: f64) -> String {
    let mut out = String::new();
    let trials = runs.first().map_or(0, |r| r.trials.len());
    let _ = writeln!(
        out,
        "# Table I: scenario {scenario}, {trials} trials per method, {budget_s} s budget\n"
    );
    let _ = writeln!(
        out,
        "Mean ± sample standard deviation over trials of the metrics at the end of the budget \
         (paper-method §5). The first four rows are the paper's Table I; the others add the \
         > 0.5 rule of the published plots and the fitted ellipsoid estimates.\n"
    );
    write_method_header(&mut out, &["scenario", "metric"], runs);
    write_final_rows(&mut out, scenario, runs);
    write_per_trial_rows(&mut out, scenario, runs);
    write_missed(&mut out, runs);
    let pairs = ours_explo_pairs(runs);
    if !pairs.is_empty() {
        write_p_table(&mut out, runs, &pairs);
        for metric in &OVER_TIME_METRICS {
            write_over_time(&mut out, runs, &pairs, metric, budget_s);
        }
    }
    out
}

/// The metrics at the end of the budget, a row each.
fn write_final_rows(out: &mut String, scenario: &str, runs: &[MethodRuns]) {
    for metric in &METRICS {
        let _ = write!(out, "| {scenario} | {} |", metric.label);
        for r in runs {
            let _ = write!(out, " {} |", cell(&r.final_values(metric), metric.decimals));
        }
        out.push('\n');
    }
}

/// The figures each trial gives once (time to 95 %, views, compute), a row each.
fn write_per_trial_rows(out: &mut String, scenario: &str, runs: &[MethodRuns]) {
    type PerTrial = fn(&TrialResult) -> Option<f64>;
    let rows: [(&str, PerTrial); 5] = [
        (
            "time to 95 % of fruits detected (s; trials reaching it)",
            |t| t.time_to_detect_s(DETECTED_SHARE).map(f64::from),
        ),
        ("share of trials detecting 95 % of fruits", |t| {
            Some(f64::from(u8::from(
                t.time_to_detect_s(DETECTED_SHARE).is_some(),
            )))
        }),
        ("views executed", |t| Some(f64::from(t.views))),
        ("planner compute per frame (ms)", |t| {
            (t.frames > 0).then(|| 1e3 * t.compute_time_s / t.frames as f64)
        }),
        ("frames with no reachable view (%)", |t| {
            (t.frames > 0).then(|| 100.0 * t.frames_without_reachable_view as f64 / t.frames as f64)
        }),
    ];
    for (label, value) in rows {
        let _ = write!(out, "| {scenario} | {label} |");
        for r in runs {
            let values: Vec<f64> = r.trials.iter().filter_map(value).collect();
            let _ = write!(out, " {} |", cell(&values, 1));
        }
        out.push('\n');
    }
}

/// Every (Ours, Explo) pair of methods among `runs`.
fn ours_explo_pairs(runs: &[MethodRuns]) -> Vec<(Method, Method)> {
    runs.iter()
        .filter(|o| o.method.uses_roi_sampling())
        .flat_map(|o| {
            runs.iter()
                .filter(|e| !e.method.uses_roi_sampling())
                .map(move |e| (o.method, e.method))
        })
        .collect()
}

/// The one-sided p-values of the metrics at the end, a column per pair.
fn write_p_table(out: &mut String, runs: &[MethodRuns], pairs: &[(Method, Method)]) {
    let p = p_values(runs);
    let _ = writeln!(
        out,
        "\n## One-sided Mann-Whitney U p-values (Ours better than Explo)\n\n\
         Alternative: the Ours method's values are larger (smaller for centre distance).\n"
    );
    let _ = write!(out, "| metric |");
    for (ours, explo) in pairs {
        let _ = write!(out, " {ours} vs {explo} |");
    }
    let _ = write!(out, "\n|---|");
    for _ in pairs {
        let _ = write!(out, "---|");
    }
    out.push('\n');
    for metric in &METRICS {
        let _ = write!(out, "| {} |", metric.label);
        write_p_cells(out, &p, metric, pairs);
        out.push('\n');
    }
}

/// `metric` over time: each method's mean at every checkpoint, then the pairs' p-values.
fn write_over_time(
    out: &mut String,
    runs: &[MethodRuns],
    pairs: &[(Method, Method)],
    metric: &MetricDef,
    budget_s: f64,
) {
    let _ = writeln!(
        out,
        "\n## {} over time: mean per method, then the one-sided p-values\n",
        metric.label
    );
    let _ = write!(out, "| time (s) |");
    for r in runs {
        let _ = write!(out, " {} |", method_label(r.method));
    }
    for (ours, explo) in pairs {
        let _ = write!(out, " p {ours} vs {explo} |");
    }
    let _ = write!(out, "\n|---|");
    for _ in 0..runs.len() + pairs.len() {
        let _ = write!(out, "---|");
    }
    out.push('\n');
    for t in checkpoints(budget_s) {
        let _ = write!(out, "| {t} |");
        for r in runs {
            let mean = mean_std(&r.values_at(metric, t)).map_or(f64::NAN, |m| m.mean);
            let _ = write!(out, " {:.*} |", metric.decimals, mean);
        }
        let p = p_values_at(runs, std::slice::from_ref(metric), t);
        write_p_cells(out, &p, metric, pairs);
        out.push('\n');
    }
}

/// One table cell per (Ours, Explo) pair: the metric's one-sided p-value, or `–`.
fn write_p_cells(
    out: &mut String,
    p: &BTreeMap<&'static str, BTreeMap<String, f64>>,
    metric: &MetricDef,
    pairs: &[(Method, Method)],
) {
    let sign = if metric.better == Better::Higher {
        ">"
    } else {
        "<"
    };
    for (ours, explo) in pairs {
        let key = format!("{ours} {sign} {explo}");
        match p.get(metric.key).and_then(|r| r.get(&key)) {
            Some(v) => {
                let _ = write!(out, " {v:.4} |");
            }
            None => {
                let _ = write!(out, " – |");
            }
        }
    }
}

/// Mean over trials of a per-second value (NaN values skipped; NaN when none), index = second.
pub fn mean_curve(trials: &[TrialResult], value: fn(&Sample) -> f64) -> Vec<f64> {
    let len = trials.iter().map(|t| t.samples.len()).max().unwrap_or(0);
    (0..len)
        .map(|i| {
            let values: Vec<f64> = trials
                .iter()
                .filter_map(|t| t.samples.get(i).map(value))
                .collect();
            mean_std(&values).map_or(f64::NAN, |m| m.mean)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::metrics::{FruitCounts, Metrics};
    use crate::trial::{ComputeTime, TrialConfig};
    use glasshouse_sim::ScenarioKind;

    fn metrics(detected: usize, cov: f64) -> Metrics {
        Metrics {
            detected,
            // Two reported fruits more than detected.
            counts: FruitCounts::new(detected, detected + 2, 28),
            counts_near: FruitCounts::new(detected, detected + 2, 28),
            center_distance_cm: if detected > 0 { 2.0 } else { f64::NAN },
            volume_accuracy: 0.5,
            volume_accuracy_gt05: f64::NAN,
            covered_volume: cov,
        }
    }

    fn result(method: Method, detected: usize) -> TrialResult {
        let sample = |t: u32, d: usize| Sample {
            time_s: t,
            views: t,
            frames: u64::from(t),
            estimates: d,
            mean_confidence: 0.5,
            boxes: metrics(d, 0.1 * d as f64),
            fitted: metrics(d, 0.2 * d as f64),
        };
        TrialResult {
            config: TrialConfig {
                compute_time: ComputeTime::Fixed { ms: 1.0 },
                ..TrialConfig::new(ScenarioKind::Two, method, 1)
            },
            samples: vec![sample(0, 0), sample(1, detected)],
            fruits_total: 28,
            views: 1,
            frames: 2,
            unreachable_views: 0,
            frames_without_reachable_view: 0,
            compute_time_s: 0.002,
            fruits: Vec::new(),
            fruit_surfaces: Vec::new(),
            clusters: Vec::new(),
            truths: Vec::new(),
            registration: Default::default(),
            plans: Vec::new(),
            best_views: Vec::new(),
        }
    }

    /// Three true fruits a metre apart, none matched: the first has a small patch and a larger
    /// sheet beside it, the second only a flat patch 12 cm away, the third a second patch.
    #[test]
    fn missed_fruits_are_put_down_to_the_largest_cluster_near_them() {
        use glasshouse_nbv::evidence::ClusterShape;
        use glasshouse_sim::FruitTruth;
        use nalgebra::{Point3, Vector3};
        let at = |x: f64| Point3::new(x, 0.0, 1.0);
        let cluster =
            |centre: Point3<f64>, voxels: usize, verdict: Verdict, fragment: bool| ClusterOutcome {
                centre,
                voxels,
                shape: ClusterShape {
                    extents_m: Vector3::new(0.06, 0.05, 0.04),
                    bulge: 0.4,
                },
                verdict,
                fit: None,
                interior: None,
                fragment,
                body: false,
            };
        let mut trial = result(Method::OursUu, 0);
        let half = Vector3::repeat(0.03);
        trial.truths = (0..3)
            .map(|i| FruitTruth::ellipsoid(i, at(f64::from(i)), half))
            .collect();
        trial.clusters = vec![
            cluster(at(0.03), 15, Verdict::TooSmall, false),
            cluster(at(-0.02), 100, Verdict::Sheet, false),
            cluster(at(1.12), 20, Verdict::Flat, false),
            cluster(at(2.01), 40, Verdict::Fruit, true),
        ];
        let reasons = missed_reasons(&trial);
        let expected: BTreeMap<&str, usize> = [
            ("a sheet (its solid hides nothing)", 1),
            ("no cluster within 8 cm", 1),
            ("a second patch of another fruit", 1),
        ]
        .into();
        assert_eq!(reasons, expected);
        let runs = vec![MethodRuns {
            method: Method::OursUu,
            trials: vec![trial],
        }];
        let table = table_markdown("2", &runs, 180.0);
        assert!(table.contains("## Missed fruits by reason"), "{table}");
        assert!(table.contains("| no cluster within 8 cm | 1 |"), "{table}");
        assert!(!table_markdown("2", &super::tests::runs(), 180.0).contains("Missed fruits"));
    }

    fn runs() -> Vec<MethodRuns> {
        vec![
            MethodRuns {
                method: Method::OursUu,
                trials: (0..5).map(|i| result(Method::OursUu, 5 + i)).collect(),
            },
            MethodRuns {
                method: Method::ExploUu,
                trials: (0..5).map(|i| result(Method::ExploUu, i)).collect(),
            },
        ]
    }

    #[test]
    fn csv_has_a_row_per_second_and_empty_cells_for_no_value() {
        let csv = trial_csv(&result(Method::OursUu, 3));
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 3);
        assert_eq!(lines[0], CSV_HEADER);
        let cols = CSV_HEADER.split(',').count();
        assert!(lines.iter().all(|l| l.split(',').count() == cols));
        assert!(lines[1].starts_with("0,0,0,0,0.500000,0,,0.500000,,0.000000,"));
        assert!(lines[2].starts_with("1,1,1,3,0.500000,3,2.000000,"));
        // Count ratio 5/28, precision 3/5, recall 3/28, F1 6/33, 2 false fruits (boxes),
        // then the fitted ones.
        assert!(
            lines[2]
                .ends_with(",0.178571,0.600000,0.107143,0.181818,2,0.600000,0.107143,0.181818,2"),
            "{}",
            lines[2]
        );
    }

    #[test]
    fn summary_has_the_required_shape() {
        let s = summary_json(&runs(), json!({"seed": 1}));
        for m in ["ours-uu", "explo-uu"] {
            for k in [
                "detected",
                "covered_volume",
                "center_distance_cm",
                "volume_accuracy",
                "volume_accuracy_fitted",
            ] {
                assert!(
                    s[m][k]["mean"].is_number() || s[m][k]["mean"].is_null(),
                    "{m} {k}"
                );
                assert!(s[m][k].get("std").is_some());
            }
        }
        assert_eq!(s["ours-uu"]["detected"]["mean"], 7.0);
        assert_eq!(s["explo-uu"]["detected"]["mean"], 2.0);
        assert!((s["ours-uu"]["detected"]["std"].as_f64().unwrap() - 2.5f64.sqrt()).abs() < 1e-12);
        // No pair passed the > 0.5 rule: no value.
        assert!(s["ours-uu"]["volume_accuracy_gt05"]["mean"].is_null());
        assert_eq!(s["fruits_total"], 28);
        // Ours 5..9 vs Explo 0..4: complete separation, exact p = 1 / C(10, 5).
        let p = s["p_values"]["detected"]["ours-uu > explo-uu"]
            .as_f64()
            .unwrap();
        assert!((p - 1.0 / 252.0).abs() < 1e-12, "{p}");
        assert!(s["p_values"]["center_distance_cm"]
            .get("ours-uu < explo-uu")
            .is_some());
        assert_eq!(s["settings"]["seed"], 1);
        // The fruit counts at the end: ours detects 5..9 of 28 with 2 false fruits each.
        assert_eq!(s["ours-uu"]["false_fruits"]["mean"], 2.0);
        let ratio = s["ours-uu"]["count_ratio"]["mean"].as_f64().unwrap();
        assert!((ratio - 9.0 / 28.0).abs() < 1e-12, "{ratio}");
        // The count ratio has no better direction: no one-sided test.
        assert!(s["p_values"].get("count_ratio").is_none());
        assert!(s["p_values"]["f1"].get("ours-uu > explo-uu").is_some());
        assert!(s["p_values"]["false_fruits"]
            .get("ours-uu < explo-uu")
            .is_some());
        // No trial detects 95 % of its 28 fruits.
        assert_eq!(s["ours-uu"]["time_to_95_s"]["n"], 0);
    }

    #[test]
    fn time_to_95_counts_the_trials_that_reach_it() {
        let mut r = runs();
        // Ours trial 0 detects 27 of 28 at 1 s (96 %), trial 1 only 26.
        r[0].trials[0] = result(Method::OursUu, 27);
        r[0].trials[1] = result(Method::OursUu, 26);
        assert_eq!(r[0].trials[0].time_to_detect_s(DETECTED_SHARE), Some(1));
        assert_eq!(r[0].trials[1].time_to_detect_s(DETECTED_SHARE), None);
        let s = summary_json(&r, json!({}));
        assert_eq!(s["ours-uu"]["time_to_95_s"]["n"], 1);
        assert_eq!(s["ours-uu"]["time_to_95_s"]["mean"], 1.0);
        let t = table_markdown("2", &r, 1.0);
        assert!(
            t.contains("| 2 | share of trials detecting 95 % of fruits | 0.2 ± 0.4 | 0.0 ± 0.0 |"),
            "{t}"
        );
        assert!(
            t.contains(
                "| 2 | time to 95 % of fruits detected (s; trials reaching it) | 1.0 ± 0.0 | – |"
            ),
            "{t}"
        );
    }

    #[test]
    fn table_lists_every_metric_and_method() {
        let t = table_markdown("2", &runs(), 1.0);
        assert!(t.contains("| scenario | metric | Ours-U_U | Explo-U_U |"));
        assert!(
            t.contains("| 2 | detected ROIs | 7.0 ± 1.6 | 2.0 ± 1.6 |"),
            "{t}"
        );
        for m in &METRICS {
            assert!(t.contains(m.label), "{}", m.label);
        }
        assert!(t.contains("ours-uu vs explo-uu"));
        assert!(t.contains("| detected ROIs | 0.0040 |"), "{t}");
    }

    #[test]
    fn mean_curves_average_per_second() {
        let r = runs();
        let c = mean_curve(&r[0].trials, |s| s.boxes.detected as f64);
        assert_eq!(c, vec![0.0, 7.0]);
        let c = mean_curve(&r[0].trials, |s| s.boxes.center_distance_cm);
        assert!(c[0].is_nan());
        assert_eq!(c[1], 2.0);
        assert!(mean_curve(&[], |s| s.boxes.covered_volume).is_empty());
    }
}
