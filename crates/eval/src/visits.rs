//! A season of visits (`glasshouse eval --days N`): the same seeded scene looked at on several
//! days (`SceneOptions::day`: fruit grown, set and harvested, leaves moved), one trial per visit,
//! and each fruit followed from visit to visit ([`glasshouse_nbv::season::SeasonTracker`]).
//!
//! Judged against the simulator's fruit ids, which stay the same over the days:
//! - **identity**, per pair of consecutive visits: a *link* is a season id carried by an
//!   estimate of each visit, both matched to a true fruit within 5 cm
//!   ([`NEAR_MATCH_DISTANCE_M`]); it is correct when the two are the same true fruit. Possible
//!   links: the true fruits matched on both visits. Precision = correct / links, recall =
//!   correct / possible, F1 their harmonic mean.
//! - **growth**, over the correct links whose true fruit grew by at least [`MIN_GROWTH_SHARE`]
//!   of its volume: the estimated volume change against the true one, `|ΔV_est − ΔV_true| /
//!   ΔV_true`, and the share of links within 15 %.
//! - the paper's figures per visit (fitted solids against bodies), and the time to 95 % of the
//!   fruits on each revisit against the first visit's; since a first visit in the realistic
//!   world seldom finds 95 % of all the fruits, also the time of every visit to 95 % of what
//!   the first visit found ([`SeasonFigures::first_visit_level`]).

use glasshouse_geom::FruitEstimate;
use glasshouse_nbv::season::{estimate_volume_m3, SeasonRules, SeasonTracker};
use glasshouse_sim::FruitTruth;
use nalgebra::Point3;
use serde::Serialize;

use crate::metrics::{greedy_match, NEAR_MATCH_DISTANCE_M};
use crate::TrialResult;

/// A true fruit counts for the growth figure when it grew by at least this share of its volume.
pub const MIN_GROWTH_SHARE: f64 = 0.05;
/// The growth goal: an estimated change within this share of the true change.
pub const GROWTH_TOLERANCE: f64 = 0.15;

/// One visit's figures.
#[derive(Clone, Debug, Serialize)]
pub struct VisitFigures {
    pub day: f64,
    pub fruits_true: usize,
    pub count_ratio: f64,
    pub f1: f64,
    pub f1_near: f64,
    pub centre_cm: f64,
    pub volume_accuracy: f64,
    /// Simulated seconds to 95 % of the fruits (None: not within the budget).
    pub time_to_95_s: Option<u32>,
    /// Share of the true fruits detected (box estimates) at the end of the budget.
    pub detected_share: f64,
    /// Simulated seconds to 95 % of the first visit's detected share at its end
    /// ([`SeasonFigures::first_visit_level`]; None: not within the budget).
    pub time_to_first_level_s: Option<u32>,
}

/// Links between consecutive visits.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct IdentityCounts {
    pub possible: usize,
    pub made: usize,
    pub correct: usize,
}

impl IdentityCounts {
    pub fn precision(&self) -> f64 {
        self.correct as f64 / self.made as f64
    }

    pub fn recall(&self) -> f64 {
        self.correct as f64 / self.possible as f64
    }

    pub fn f1(&self) -> f64 {
        2.0 * self.correct as f64 / (self.made + self.possible) as f64
    }

    pub fn add(&mut self, other: &IdentityCounts) {
        self.possible += other.possible;
        self.made += other.made;
        self.correct += other.correct;
    }
}

/// A season's figures: per visit, identity and growth.
#[derive(Clone, Debug, Serialize)]
pub struct SeasonFigures {
    pub visits: Vec<VisitFigures>,
    pub identity: IdentityCounts,
    /// `|ΔV_est − ΔV_true| / ΔV_true` of every correct link of a growing fruit, the change
    /// measured on one shape ([`glasshouse_nbv::season::SeasonFruit::volume_change_m3`]; where it cannot be, the
    /// difference of the two visits' volumes).
    pub growth_errors: Vec<f64>,
    /// The same links' errors with the change taken as the difference of the two visits'
    /// fitted volumes: the estimate before the change was measured on one shape, side by side.
    pub differenced_growth_errors: Vec<f64>,
    /// Fruits the season tracker knows at the end.
    pub season_fruits: usize,
    /// 95 % of the share of true fruits the first visit detected by its end: the level every
    /// visit's `time_to_first_level_s` is timed to (a first visit rarely finds 95 % of all the
    /// fruits in the realistic world, so the paper's time to 95 % seldom exists for it).
    pub first_visit_level: f64,
}

/// An estimate of one visit: its season id and the true fruit (index) it is matched to.
struct Judged {
    season_id: u32,
    volume_m3: f64,
    truth: Option<usize>,
    /// Its fruit's volume change since its record before this visit, as the season tracker
    /// gives it ([`glasshouse_nbv::season::SeasonFruit::volume_change_m3`]).
    change_m3: Option<f64>,
}

/// The figures of one trial's visits, in day order (`days[k]` the day of `visits[k]`).
pub fn season_figures(visits: &[TrialResult], days: &[f64], rules: SeasonRules) -> SeasonFigures {
    let mut tracker = SeasonTracker::new(rules);
    let judged: Vec<Vec<Judged>> = visits
        .iter()
        .map(|result| judge(&mut tracker, result))
        .collect();
    let mut identity = IdentityCounts::default();
    let (mut growth_errors, mut differenced_growth_errors) = (Vec::new(), Vec::new());
    for k in 1..visits.len() {
        let (before, after) = (&visits[k - 1], &visits[k]);
        let counts = links(
            before,
            after,
            &judged[k - 1],
            &judged[k],
            (&mut growth_errors, &mut differenced_growth_errors),
        );
        identity.add(&counts);
    }
    let first_visit_level = visits
        .first()
        .map_or(f64::NAN, |r| REVISIT_LEVEL * detected_share(r));
    SeasonFigures {
        visits: visits
            .iter()
            .zip(days)
            .map(|(r, &day)| visit_figures(r, day, first_visit_level))
            .collect(),
        identity,
        growth_errors,
        differenced_growth_errors,
        season_fruits: tracker.fruits().len(),
        first_visit_level,
    }
}

/// Where an estimate's fruit is: its fitted solid's centre, else its voxels' mean.
fn centre_of(e: &FruitEstimate) -> Point3<f64> {
    e.solid.as_ref().map_or(e.centre, |s| s.centre)
}

fn judge(tracker: &mut SeasonTracker, result: &TrialResult) -> Vec<Judged> {
    let visit = tracker.visits();
    let ids = tracker.observe_visit_measured(visit, &result.fruits, &result.fruit_surfaces);
    let centres: Vec<Point3<f64>> = result.fruits.iter().map(centre_of).collect();
    let truths: Vec<Point3<f64>> = result.truths.iter().map(|t| t.body_centre).collect();
    let mut truth_of = vec![None; centres.len()];
    for m in greedy_match(&centres, &truths, NEAR_MATCH_DISTANCE_M) {
        truth_of[m.estimate] = Some(m.truth);
    }
    let change_of = |season_id: u32| {
        let fruit = tracker.fruits().iter().find(|f| f.id == season_id)?;
        fruit.volume_change_m3(visit)
    };
    result
        .fruits
        .iter()
        .zip(ids)
        .zip(truth_of)
        .map(|((e, season_id), truth)| Judged {
            season_id,
            volume_m3: estimate_volume_m3(e),
            truth,
            change_m3: change_of(season_id),
        })
        .collect()
}

/// The links between two consecutive visits; the growth errors of the correct ones are added.
fn links(
    before: &TrialResult,
    after: &TrialResult,
    a: &[Judged],
    b: &[Judged],
    (growth_errors, differenced_errors): (&mut Vec<f64>, &mut Vec<f64>),
) -> IdentityCounts {
    let true_id = |r: &TrialResult, j: &Judged| j.truth.map(|t| r.truths[t].id);
    let ids_a: Vec<u32> = a.iter().filter_map(|j| true_id(before, j)).collect();
    let possible = b
        .iter()
        .filter_map(|j| true_id(after, j))
        .filter(|id| ids_a.contains(id))
        .count();
    let mut counts = IdentityCounts {
        possible,
        ..IdentityCounts::default()
    };
    for jb in b.iter().filter(|j| j.truth.is_some()) {
        let Some(ja) = a
            .iter()
            .find(|j| j.season_id == jb.season_id && j.truth.is_some())
        else {
            continue;
        };
        counts.made += 1;
        let (Some(ta), Some(tb)) = (ja.truth, jb.truth) else {
            continue;
        };
        let (fa, fb): (&FruitTruth, &FruitTruth) = (&before.truths[ta], &after.truths[tb]);
        if fa.id != fb.id {
            continue;
        }
        counts.correct += 1;
        let true_change = fb.body_volume_m3 - fa.body_volume_m3;
        if true_change >= MIN_GROWTH_SHARE * fa.body_volume_m3 {
            let differenced = jb.volume_m3 - ja.volume_m3;
            let error = |estimated: f64| (estimated - true_change).abs() / true_change;
            growth_errors.push(error(jb.change_m3.unwrap_or(differenced)));
            differenced_errors.push(error(differenced));
        }
    }
    counts
}

/// The share of the first visit's final detections every visit is timed to.
pub const REVISIT_LEVEL: f64 = 0.95;

/// The share of the true fruits the box estimates detect at the end.
fn detected_share(r: &TrialResult) -> f64 {
    let detected = r.last().map_or(0, |s| s.boxes.detected);
    detected as f64 / r.fruits_total.max(1) as f64
}

fn visit_figures(r: &TrialResult, day: f64, first_visit_level: f64) -> VisitFigures {
    let fitted = r.last().map(|s| s.fitted);
    let nan = f64::NAN;
    VisitFigures {
        day,
        fruits_true: r.fruits_total,
        count_ratio: fitted.as_ref().map_or(nan, |m| m.counts.count_ratio),
        f1: fitted.as_ref().map_or(nan, |m| m.counts.f1),
        f1_near: fitted.as_ref().map_or(nan, |m| m.counts_near.f1),
        centre_cm: fitted.as_ref().map_or(nan, |m| m.center_distance_cm),
        volume_accuracy: fitted.as_ref().map_or(nan, |m| m.volume_accuracy),
        time_to_95_s: r.time_to_detect_s(0.95),
        detected_share: detected_share(r),
        time_to_first_level_s: r.time_to_detect_s(first_visit_level),
    }
}

#[cfg(test)]
mod tests;
