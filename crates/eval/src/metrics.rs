//! Ground-truth matching and the metrics of the paper's Table I (paper-method §5).
//!
//! - **Matching**: every estimate-truth centre distance, taken greedily from the smallest (ties:
//!   lower estimate index, then lower truth index), one to one, up to
//!   [`MATCH_DISTANCE_M`] inclusive.
//! - **Detected ROIs**: matched pairs.
//! - **Centre distance**: mean distance of matched pairs, in centimetres.
//! - **Volume accuracy**: mean over matched pairs of `1 − |V_det − V_gt| / V_gt` (box volumes
//!   against box volumes; for fitted solids, [`TruthMeasure::Body`]: the solid's volume against
//!   the body's real volume, its centroid against the body's centroid); also the mean over the pairs
//!   whose accuracy is `> 0.5` only (the rule of the published plots).
//! - **Covered ROI volume**: `|voxels of the estimated boxes ∩ voxels of the truth boxes| /
//!   |voxels of the truth boxes|`, where a box's voxels are those whose centres lie inside it
//!   and both sides are unions over all boxes: [`glasshouse_geom::covered_volume`], the figure
//!   the dashboard shows too.
//!
//! - **Fruit counts** (what inflates when the detector errs): count ratio = reported fruits ÷
//!   true fruits; precision = matched ÷ reported; recall = matched ÷ true; F1 = their harmonic
//!   mean, `2·matched / (reported + true)`; false fruits = reported − matched. A fruit is found
//!   by the same matching as above.
//! - **Fruit counts within 5 cm** ([`Metrics::counts_near`]): the same, matching only pairs
//!   whose centres are at most [`NEAR_MATCH_DISTANCE_M`] apart. The paper's 20 cm is wider than
//!   two capsicum side by side: a false fruit a leaf away from a fruit the map missed counts as
//!   that fruit found. Within 5 cm an estimate's centre lies inside the fruit it is matched to.
//! - **Time to 95 %**: the first sampled second at which at least 95 % of the true fruits are
//!   matched ([`time_to_detect_s`]); none when it never happens.
//!
//! Means and ratios over an empty set are NaN ("no value"), never 0, so they cannot pass for a
//! result.

use glasshouse_geom::{Aabb, FruitEstimate};
use glasshouse_sim::FruitTruth;
use nalgebra::Point3;
use serde::Serialize;

/// Largest centre distance of a matched pair (paper: 0.20 m).
pub const MATCH_DISTANCE_M: f64 = 0.20;

/// Largest centre distance of a pair the fruit counts within 5 cm match: less than a capsicum's
/// radius plus a centimetre.
pub const NEAR_MATCH_DISTANCE_M: f64 = 0.05;

/// A matched estimate-truth pair (indices into the inputs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Match {
    pub estimate: usize,
    pub truth: usize,
    pub distance_m: f64,
}

/// Greedy one-to-one matching of centres, smallest distance first, up to `max_distance_m`
/// inclusive. Pairs with a non-finite distance never match. The result is sorted by distance.
pub fn greedy_match(
    estimates: &[Point3<f64>],
    truths: &[Point3<f64>],
    max_distance_m: f64,
) -> Vec<Match> {
    let mut pairs: Vec<Match> = Vec::new();
    for (estimate, e) in estimates.iter().enumerate() {
        for (truth, t) in truths.iter().enumerate() {
            let distance_m = (e - t).norm();
            if distance_m.is_finite() && distance_m <= max_distance_m {
                pairs.push(Match {
                    estimate,
                    truth,
                    distance_m,
                });
            }
        }
    }
    pairs.sort_by(|a, b| {
        a.distance_m
            .total_cmp(&b.distance_m)
            .then(a.estimate.cmp(&b.estimate))
            .then(a.truth.cmp(&b.truth))
    });
    let mut estimate_taken = vec![false; estimates.len()];
    let mut truth_taken = vec![false; truths.len()];
    let mut out = Vec::new();
    for p in pairs {
        if !estimate_taken[p.estimate] && !truth_taken[p.truth] {
            estimate_taken[p.estimate] = true;
            truth_taken[p.truth] = true;
            out.push(p);
        }
    }
    out
}

/// `1 − |V_det − V_gt| / V_gt`; NaN when `V_gt` is not positive.
pub fn volume_accuracy(detected_m3: f64, truth_m3: f64) -> f64 {
    if truth_m3 > 0.0 {
        1.0 - (detected_m3 - truth_m3).abs() / truth_m3
    } else {
        f64::NAN
    }
}

/// Covered ROI volume of the estimates' boxes ([`glasshouse_geom::covered_volume`]); NaN when
/// the truth has no voxels.
pub fn covered_volume(estimates: &[Aabb], truths: &[FruitTruth], resolution_m: f64) -> f64 {
    glasshouse_geom::covered_volume(
        estimates.iter().copied(),
        truths.iter().map(FruitTruth::aabb),
        resolution_m,
    )
}

/// Mean of the values; NaN for none.
pub fn mean(values: &[f64]) -> f64 {
    if values.is_empty() {
        f64::NAN
    } else {
        values.iter().sum::<f64>() / values.len() as f64
    }
}

/// `numerator / denominator`; NaN when the denominator is 0.
fn ratio(numerator: usize, denominator: usize) -> f64 {
    if denominator == 0 {
        f64::NAN
    } else {
        numerator as f64 / denominator as f64
    }
}

/// How the reported fruits compare with the true ones (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct FruitCounts {
    /// Reported ÷ true fruits (NaN without true fruits); above 1 the map over-counts.
    pub count_ratio: f64,
    /// Matched ÷ reported (NaN without reported fruits).
    pub precision: f64,
    /// Matched ÷ true (NaN without true fruits).
    pub recall: f64,
    /// `2·matched / (reported + true)` (NaN when both are 0).
    pub f1: f64,
    /// Reported fruits that match no true fruit.
    pub false_fruits: usize,
}

impl FruitCounts {
    /// From the counts of matched pairs, reported and true fruits (`matched` is capped at both).
    pub fn new(matched: usize, reported: usize, truths: usize) -> Self {
        let matched = matched.min(reported).min(truths);
        Self {
            count_ratio: ratio(reported, truths),
            precision: ratio(matched, reported),
            recall: ratio(matched, truths),
            f1: ratio(2 * matched, reported + truths),
            false_fruits: reported - matched,
        }
    }
}

/// The first of `detected_at` (second, matched fruits), in time order, at which at least `share`
/// of `truths` fruits are matched; None when never, or without true fruits.
pub fn time_to_detect_s(
    detected_at: impl IntoIterator<Item = (u32, usize)>,
    truths: usize,
    share: f64,
) -> Option<u32> {
    if truths == 0 || !(share.is_finite() && share > 0.0) {
        return None;
    }
    // The small margin keeps 19 of 20 at 95 % from failing on rounding.
    let needed = (share * truths as f64 - 1e-9).ceil().max(1.0) as usize;
    detected_at
        .into_iter()
        .find(|&(_, detected)| detected >= needed)
        .map(|(time_s, _)| time_s)
}

/// The Table I metrics of one set of estimates at one instant.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Metrics {
    /// Matched pairs.
    pub detected: usize,
    /// Count ratio, precision, recall, F1 and false fruits.
    pub counts: FruitCounts,
    /// The same, matching only centres within [`NEAR_MATCH_DISTANCE_M`] (module docs).
    pub counts_near: FruitCounts,
    /// Mean centre distance of matched pairs in cm (NaN without pairs).
    pub center_distance_cm: f64,
    /// Mean volume accuracy over matched pairs (NaN without pairs).
    pub volume_accuracy: f64,
    /// Mean volume accuracy over matched pairs with accuracy > 0.5 (NaN without such pairs).
    pub volume_accuracy_gt05: f64,
    /// Covered ROI volume in [0, 1].
    pub covered_volume: f64,
}

impl Metrics {
    /// The metrics of no estimates at all.
    pub fn empty(truths: &[FruitTruth], resolution_m: f64) -> Self {
        evaluate(&[], truths, resolution_m)
    }
}

/// Which figures of an estimate are judged against which of a true fruit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TruthMeasure {
    /// The estimate's box, centre and box volume against the fruit's axis-aligned box: its centre
    /// and box volume (the paper's box metrics).
    Box,
    /// The estimate's fitted solid (its centroid, volume and world box;
    /// [`FruitEstimate::solid_or_box`]) against the fruit's body: its centroid and real volume.
    Body,
}

impl TruthMeasure {
    fn centre(self, truth: &FruitTruth) -> Point3<f64> {
        match self {
            TruthMeasure::Box => truth.centre,
            TruthMeasure::Body => truth.body_centre,
        }
    }

    fn volume_m3(self, truth: &FruitTruth) -> f64 {
        match self {
            TruthMeasure::Box => truth.volume_m3,
            TruthMeasure::Body => truth.body_volume_m3,
        }
    }

    /// The centre, box and volume of `estimate` this measure judges.
    fn judged(self, estimate: &FruitEstimate) -> (Point3<f64>, Aabb, f64) {
        match self {
            TruthMeasure::Box => (estimate.centre, estimate.aabb(), estimate.volume_m3),
            TruthMeasure::Body => {
                let s = estimate.solid_or_box();
                (s.centre, Aabb::new(s.box_min, s.box_max), s.volume_m3)
            }
        }
    }
}

/// All metrics of the estimates' boxes against the truths' boxes (voxels of `resolution_m` for
/// the covered volume).
pub fn evaluate(estimates: &[FruitEstimate], truths: &[FruitTruth], resolution_m: f64) -> Metrics {
    evaluate_against(estimates, truths, resolution_m, TruthMeasure::Box)
}

/// All metrics of the estimates' figures of `measure` against the truths' centres and volumes
/// of `measure`; the covered volume counts the truths' box voxels either way.
pub fn evaluate_against(
    estimates: &[FruitEstimate],
    truths: &[FruitTruth],
    resolution_m: f64,
    measure: TruthMeasure,
) -> Metrics {
    let judged: Vec<(Point3<f64>, Aabb, f64)> =
        estimates.iter().map(|e| measure.judged(e)).collect();
    let centres: Vec<Point3<f64>> = judged.iter().map(|j| j.0).collect();
    let truth_centres: Vec<Point3<f64>> = truths.iter().map(|t| measure.centre(t)).collect();
    let matches = greedy_match(&centres, &truth_centres, MATCH_DISTANCE_M);
    let near = greedy_match(&centres, &truth_centres, NEAR_MATCH_DISTANCE_M);
    let distances: Vec<f64> = matches.iter().map(|m| m.distance_m * 100.0).collect();
    let accuracies: Vec<f64> = matches
        .iter()
        .map(|m| {
            let truth_m3 = measure.volume_m3(&truths[m.truth]);
            volume_accuracy(judged[m.estimate].2, truth_m3)
        })
        .collect();
    let above: Vec<f64> = accuracies.iter().copied().filter(|a| *a > 0.5).collect();
    Metrics {
        detected: matches.len(),
        counts: FruitCounts::new(matches.len(), estimates.len(), truths.len()),
        counts_near: FruitCounts::new(near.len(), estimates.len(), truths.len()),
        center_distance_cm: mean(&distances),
        volume_accuracy: mean(&accuracies),
        volume_accuracy_gt05: mean(&above),
        covered_volume: covered_volume(
            &judged.iter().map(|j| j.1).collect::<Vec<_>>(),
            truths,
            resolution_m,
        ),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use nalgebra::Vector3;

    fn p(x: f64, y: f64, z: f64) -> Point3<f64> {
        Point3::new(x, y, z)
    }

    fn truth(id: u32, centre: Point3<f64>, half: f64) -> FruitTruth {
        FruitTruth::ellipsoid(id, centre, Vector3::repeat(half))
    }

    #[test]
    fn body_measure_judges_centre_and_volume_against_the_body() {
        // A body whose centroid sits 1 cm below its box centre, with 60 % of the box volume.
        let mut t = truth(0, p(0.0, 0.0, 0.0), 0.03);
        t.body_centre = p(0.0, 0.0, -0.01);
        t.body_volume_m3 = 0.6 * t.volume_m3;
        let mut on_body = FruitEstimate {
            volume_m3: t.body_volume_m3,
            ..estimate(t.body_centre, 0.03)
        };
        // Its solid sits on the body's centroid with the body's volume.
        on_body.solid = Some(glasshouse_geom::FruitSolid {
            volume_m3: t.body_volume_m3,
            ..on_body.solid_or_box()
        });
        let body = evaluate_against(
            &[on_body],
            std::slice::from_ref(&t),
            0.01,
            TruthMeasure::Body,
        );
        assert!(body.center_distance_cm.abs() < 1e-9);
        assert!((body.volume_accuracy - 1.0).abs() < 1e-12);
        let boxed = evaluate(&[on_body], &[t], 0.01);
        assert!((boxed.center_distance_cm - 1.0).abs() < 1e-9);
        assert!((boxed.volume_accuracy - 0.6).abs() < 1e-12);
    }

    fn estimate(centre: Point3<f64>, half: f64) -> FruitEstimate {
        FruitEstimate {
            volume_m3: 8.0 * half.powi(3),
            ..FruitEstimate::from_box(
                0,
                centre,
                centre - Vector3::repeat(half),
                centre + Vector3::repeat(half),
            )
        }
    }

    #[test]
    fn greedy_matching_takes_smallest_distances_first_one_to_one() {
        // e0 is 0.05 from t0 and 0.06 from t1; e1 is 0.04 from t0 and 0.30 from t1.
        // Greedy: (e1, t0, 0.04) first; then e0 can only take t1 (0.06).
        let truths = [p(0.0, 0.0, 0.0), p(0.11, 0.0, 0.0)];
        let estimates = [p(0.05, 0.0, 0.0), p(-0.04, 0.0, 0.0)];
        let m = greedy_match(&estimates, &truths, 0.2);
        assert_eq!(m.len(), 2);
        assert_eq!((m[0].estimate, m[0].truth), (1, 0));
        assert!((m[0].distance_m - 0.04).abs() < 1e-12);
        assert_eq!((m[1].estimate, m[1].truth), (0, 1));
        assert!((m[1].distance_m - 0.06).abs() < 1e-12);
    }

    #[test]
    fn matching_respects_the_distance_limit_inclusively_and_one_to_one() {
        let truths = [p(0.0, 0.0, 0.0)];
        // Two estimates for one fruit: only the nearer matches.
        let m = greedy_match(&[p(0.1, 0.0, 0.0), p(0.0, 0.05, 0.0)], &truths, 0.2);
        assert_eq!(m.len(), 1);
        assert_eq!(m[0].estimate, 1);
        // Exactly at the limit matches, beyond it does not.
        assert_eq!(greedy_match(&[p(0.25, 0.0, 0.0)], &truths, 0.25).len(), 1);
        assert!(greedy_match(&[p(0.2000001, 0.0, 0.0)], &truths, 0.2).is_empty());
        // Non-finite centres never match; empty inputs give nothing.
        assert!(greedy_match(&[p(f64::NAN, 0.0, 0.0)], &truths, 0.2).is_empty());
        assert!(greedy_match(&[], &truths, 0.2).is_empty());
        assert!(greedy_match(&truths, &[], 0.2).is_empty());
        // Equal distances: the lower estimate index wins.
        let m = greedy_match(&[p(0.1, 0.0, 0.0), p(-0.1, 0.0, 0.0)], &truths, 0.2);
        assert_eq!(m[0].estimate, 0);
    }

    #[test]
    fn volume_accuracy_is_one_minus_relative_error() {
        assert_eq!(volume_accuracy(1.0, 1.0), 1.0);
        assert!((volume_accuracy(0.5, 1.0) - 0.5).abs() < 1e-12);
        assert!((volume_accuracy(1.25, 1.0) - 0.75).abs() < 1e-12);
        // More than twice the truth goes negative.
        assert!((volume_accuracy(3.0, 1.0) + 1.0).abs() < 1e-12);
        assert!(volume_accuracy(1.0, 0.0).is_nan());
    }

    #[test]
    fn truth_voxels_follow_the_box_rule() {
        let t = truth(0, p(0.1, 0.2, 0.3), 0.02);
        assert_eq!(
            t.voxel_keys(0.01),
            glasshouse_geom::box_voxel_keys(&t.aabb(), 0.01)
        );
        assert_eq!(t.voxel_keys(0.01).len(), 4 * 4 * 4);
    }

    #[test]
    fn covered_volume_counts_the_union_intersection() {
        // Truth: a 4x4x4-voxel box (64 voxels) at the origin corner; estimates covering the lower
        // half in x, one inside it (counted once) and one far away.
        let truths = [truth(0, p(0.02, 0.02, 0.02), 0.02)];
        let half = Aabb::new(p(0.0, 0.0, 0.0), p(0.02, 0.04, 0.04));
        let inner = Aabb::new(p(0.0, 0.0, 0.0), p(0.02, 0.02, 0.04));
        let far = estimate(p(1.0, 1.0, 1.0), 0.02).aabb();
        let c = covered_volume(&[half, inner, far], &truths, 0.01);
        assert!((c - 0.5).abs() < 1e-12, "{c}");
        assert_eq!(covered_volume(&[], &truths, 0.01), 0.0);
        assert!(covered_volume(&[half], &[], 0.01).is_nan());
    }

    #[test]
    fn evaluate_computes_every_metric() {
        let truths = [
            truth(0, p(0.0, 0.0, 1.0), 0.02),
            truth(1, p(0.5, 0.0, 1.0), 0.02),
            truth(2, p(1.0, 0.0, 1.0), 0.02),
        ];
        let v = 8.0 * 0.02f64.powi(3);
        let estimates = [
            // 1 cm off, exact volume: accuracy 1.
            FruitEstimate {
                volume_m3: v,
                ..estimate(p(0.01, 0.0, 1.0), 0.02)
            },
            // 3 cm off, 40 % of the volume: accuracy 0.4 (dropped by the > 0.5 rule).
            FruitEstimate {
                volume_m3: 0.4 * v,
                ..estimate(p(0.5, 0.03, 1.0), 0.02)
            },
            // 30 cm from everything: unmatched.
            estimate(p(1.0, 0.3, 1.0), 0.02),
        ];
        let m = evaluate(&estimates, &truths, 0.01);
        assert_eq!(m.detected, 2);
        assert!((m.center_distance_cm - 2.0).abs() < 1e-9, "{m:?}");
        assert!((m.volume_accuracy - 0.7).abs() < 1e-9, "{m:?}");
        assert!((m.volume_accuracy_gt05 - 1.0).abs() < 1e-9, "{m:?}");
        assert!(m.covered_volume > 0.0 && m.covered_volume < 1.0, "{m:?}");
        let empty = Metrics::empty(&truths, 0.01);
        assert_eq!(empty.detected, 0);
        assert!(empty.center_distance_cm.is_nan() && empty.volume_accuracy.is_nan());
        assert!(empty.volume_accuracy_gt05.is_nan());
        assert_eq!(empty.covered_volume, 0.0);
    }

    #[test]
    fn fruit_counts_catch_inflation() {
        // 28 true fruits, 52 reported, 20 of them matched: the map over-counts.
        let c = FruitCounts::new(20, 52, 28);
        assert!((c.count_ratio - 52.0 / 28.0).abs() < 1e-12, "{c:?}");
        assert!((c.precision - 20.0 / 52.0).abs() < 1e-12, "{c:?}");
        assert!((c.recall - 20.0 / 28.0).abs() < 1e-12, "{c:?}");
        let f1 = 2.0 * c.precision * c.recall / (c.precision + c.recall);
        assert!((c.f1 - f1).abs() < 1e-12, "{c:?}");
        assert_eq!(c.false_fruits, 32);
        // A perfect report.
        let perfect = FruitCounts::new(7, 7, 7);
        assert_eq!(
            (
                perfect.count_ratio,
                perfect.precision,
                perfect.recall,
                perfect.f1
            ),
            (1.0, 1.0, 1.0, 1.0)
        );
        assert_eq!(perfect.false_fruits, 0);
        // Nothing reported: recall and F1 are 0, precision has no value.
        let none = FruitCounts::new(0, 0, 7);
        assert_eq!((none.count_ratio, none.recall, none.f1), (0.0, 0.0, 0.0));
        assert!(none.precision.is_nan());
        // No true fruits: only precision and F1 have values.
        let no_truth = FruitCounts::new(0, 3, 0);
        assert!(no_truth.count_ratio.is_nan() && no_truth.recall.is_nan());
        assert_eq!((no_truth.precision, no_truth.f1), (0.0, 0.0));
        assert_eq!(no_truth.false_fruits, 3);
        assert!(FruitCounts::new(0, 0, 0).f1.is_nan());
        // More matches than either side cannot happen; they are capped rather than underflow.
        assert_eq!(FruitCounts::new(9, 3, 5).false_fruits, 0);
    }

    #[test]
    fn a_false_fruit_beside_a_missed_one_is_found_only_at_20_cm() {
        let truths = [
            truth(0, p(0.0, 0.0, 1.0), 0.03),
            truth(1, p(1.0, 0.0, 1.0), 0.03),
        ];
        // The first fruit found 1 cm off; a red leaf 12 cm from the second, which was missed.
        let estimates = [
            estimate(p(0.01, 0.0, 1.0), 0.03),
            estimate(p(1.12, 0.0, 1.0), 0.03),
        ];
        let m = evaluate(&estimates, &truths, 0.01);
        assert_eq!((m.counts.recall, m.counts.f1), (1.0, 1.0));
        assert_eq!((m.counts_near.recall, m.counts_near.precision), (0.5, 0.5));
        assert_eq!(m.counts_near.false_fruits, 1);
    }

    #[test]
    fn evaluate_counts_reported_and_false_fruits() {
        let truths = [
            truth(0, p(0.0, 0.0, 1.0), 0.02),
            truth(1, p(1.0, 0.0, 1.0), 0.02),
        ];
        // One estimate per fruit, two more near the first (one-to-one: they stay unmatched even
        // within 20 cm), one far away.
        let estimates = [
            estimate(p(0.0, 0.0, 1.0), 0.02),
            estimate(p(1.0, 0.0, 1.0), 0.02),
            estimate(p(0.05, 0.0, 1.0), 0.02),
            estimate(p(0.0, 0.1, 1.0), 0.02),
            estimate(p(3.0, 0.0, 1.0), 0.02),
        ];
        let m = evaluate(&estimates, &truths, 0.01);
        assert_eq!(m.detected, 2);
        assert_eq!(m.counts.false_fruits, 3);
        assert_eq!(m.counts_near.count_ratio, 2.5);
        assert_eq!(m.counts.count_ratio, 2.5);
        assert_eq!(m.counts.precision, 0.4);
        assert_eq!(m.counts.recall, 1.0);
        assert!((m.counts.f1 - 4.0 / 7.0).abs() < 1e-12);
    }

    #[test]
    fn time_to_detect_is_the_first_second_reaching_the_share() {
        let curve = [(0, 0), (1, 10), (2, 18), (3, 19), (4, 20), (5, 19)];
        // 95 % of 20 = 19 fruits, first at 3 s.
        assert_eq!(time_to_detect_s(curve, 20, 0.95), Some(3));
        // 95 % of 28 = 26.6: 27 needed.
        let curve = [(0, 0), (7, 26), (9, 27)];
        assert_eq!(time_to_detect_s(curve, 28, 0.95), Some(9));
        assert_eq!(time_to_detect_s([(0, 0), (1, 26)], 28, 0.95), None);
        assert_eq!(time_to_detect_s([(0, 5)], 0, 0.95), None);
        assert_eq!(time_to_detect_s([(0, 5)], 5, f64::NAN), None);
        assert_eq!(time_to_detect_s([(4, 1)], 1, 1.0), Some(4));
    }

    #[test]
    fn evaluate_covered_volume_of_exact_boxes_is_one() {
        let truths = [
            truth(0, p(0.105, 0.0, 1.0), 0.03),
            truth(1, p(0.5, 0.0, 1.0), 0.025),
        ];
        let estimates: Vec<FruitEstimate> = truths
            .iter()
            .map(|t| estimate(t.centre, t.half_extents_m.x))
            .collect();
        let m = evaluate(&estimates, &truths, 0.01);
        assert_eq!(m.detected, 2);
        assert_eq!(m.covered_volume, 1.0);
        assert!(m.center_distance_cm.abs() < 1e-12);
        assert!((m.volume_accuracy - 1.0).abs() < 1e-12);
    }
}
