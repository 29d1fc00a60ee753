//! Each fruit followed from visit to visit ([`SeasonTracker`]): a revisit's fruits are matched to
//! the fruits known from the visits before, so a fruit seen on Monday keeps its id on Thursday.
//!
//! A fruit grows between visits (towards its stalk end, so its centre moves a few millimetres),
//! the trolley's pose errors move a whole visit by up to a centimetre or two, and leaves move.
//! Matching is one to one, greedily from the smallest centre distance, up to
//! [`SeasonRules::max_distance_m`], and only between a fruit and an estimate whose volumes are
//! within [`SeasonRules::max_volume_ratio`] of each other (a fruit does not halve, nor grow
//! eightfold, in a few days). A known fruit that no estimate of a visit matches is closed
//! (harvested, or hidden this time: it may be matched again on a later visit, up to
//! [`SeasonRules::reopen_visits`] visits after it was last seen); an estimate that matches no known fruit is a new
//! fruit with a new id. Each fruit keeps its history: centre, size and volume per visit.

use glasshouse_geom::FruitEstimate;
use nalgebra::{Point3, Vector3};
use serde::Serialize;

/// How visits are matched.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SeasonRules {
    pub max_distance_m: f64,
    pub max_volume_ratio: f64,
    /// A fruit stays matchable this many visits after it was last seen (2: one hidden on one
    /// visit is matched on the next).
    pub reopen_visits: usize,
}

impl Default for SeasonRules {
    fn default() -> Self {
        Self {
            max_distance_m: 0.04,
            max_volume_ratio: 4.0,
            reopen_visits: 2,
        }
    }
}

/// One fruit on one visit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct VisitRecord {
    pub visit: usize,
    pub centre: Point3<f64>,
    /// The size of its box (m).
    pub size_m: Vector3<f64>,
    /// The fitted solid's volume, else the box's.
    pub volume_m3: f64,
    /// The estimate's id within that visit.
    pub visit_fruit_id: u32,
}

/// A fruit over the season.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SeasonFruit {
    pub id: u32,
    pub history: Vec<VisitRecord>,
}

impl SeasonFruit {
    fn last(&self) -> Option<&VisitRecord> {
        self.history.last()
    }

    /// Whether it was seen on `visit`: its record then.
    pub fn on(&self, visit: usize) -> Option<&VisitRecord> {
        self.history.iter().find(|r| r.visit == visit)
    }
}

/// The fruits of every visit so far, with stable ids.
#[derive(Clone, Debug, Default)]
pub struct SeasonTracker {
    rules: SeasonRules,
    fruits: Vec<SeasonFruit>,
    visits: usize,
}

/// The volume an estimate reports: its fitted solid's, else its box's.
pub fn estimate_volume_m3(e: &FruitEstimate) -> f64 {
    e.solid.as_ref().map_or(e.volume_m3, |s| s.volume_m3)
}

impl SeasonTracker {
    pub fn new(rules: SeasonRules) -> Self {
        Self {
            rules,
            fruits: Vec::new(),
            visits: 0,
        }
    }

    pub fn fruits(&self) -> &[SeasonFruit] {
        &self.fruits
    }

    /// Takes the next visit's estimates; returns each estimate's season id, in order.
    pub fn observe(&mut self, estimates: &[FruitEstimate]) -> Vec<u32> {
        let visit = self.visits;
        self.visits += 1;
        let open: Vec<usize> = (0..self.fruits.len())
            .filter(|&i| {
                self.fruits[i]
                    .last()
                    .is_some_and(|r| visit - r.visit <= self.rules.reopen_visits)
            })
            .collect();
        let mut pairs = Vec::new();
        for (e, estimate) in estimates.iter().enumerate() {
            for &f in &open {
                if let Some(d) = self.distance(f, estimate) {
                    pairs.push((d, e, f));
                }
            }
        }
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        let mut ids: Vec<Option<u32>> = vec![None; estimates.len()];
        let mut taken = vec![false; self.fruits.len()];
        for (_, e, f) in pairs {
            if ids[e].is_none() && !taken[f] {
                taken[f] = true;
                ids[e] = Some(self.fruits[f].id);
                self.fruits[f].history.push(record(visit, &estimates[e]));
            }
        }
        ids.iter()
            .zip(estimates)
            .map(|(id, estimate)| id.unwrap_or_else(|| self.open_new(visit, estimate)))
            .collect()
    }

    /// The centre distance between fruit `f`'s last record and `estimate`, when they may be
    /// the same fruit.
    fn distance(&self, f: usize, estimate: &FruitEstimate) -> Option<f64> {
        let last = self.fruits[f].last()?;
        let d = (last.centre - estimate.centre).norm();
        let ratio = estimate_volume_m3(estimate) / last.volume_m3;
        let r = self.rules.max_volume_ratio;
        let plausible = ratio.is_finite() && ratio >= 1.0 / r && ratio <= r;
        (d <= self.rules.max_distance_m && plausible).then_some(d)
    }

    fn open_new(&mut self, visit: usize, estimate: &FruitEstimate) -> u32 {
        let id = self.fruits.len() as u32 + 1;
        self.fruits.push(SeasonFruit {
            id,
            history: vec![record(visit, estimate)],
        });
        id
    }
}

fn record(visit: usize, e: &FruitEstimate) -> VisitRecord {
    VisitRecord {
        visit,
        centre: e.centre,
        size_m: e.max - e.min,
        volume_m3: estimate_volume_m3(e),
        visit_fruit_id: e.id,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fruit(id: u32, x: f64, half_m: f64) -> FruitEstimate {
        let c = Point3::new(x, 0.0, 1.0);
        let h = Vector3::repeat(half_m);
        FruitEstimate::from_box(id, c, c - h, c + h)
    }

    #[test]
    fn grown_and_shifted_fruit_keep_their_ids_harvested_close_new_ones_open() {
        let mut season = SeasonTracker::new(SeasonRules::default());
        let monday = [
            fruit(1, 0.0, 0.03),
            fruit(2, 0.2, 0.03),
            fruit(3, 0.4, 0.03),
        ];
        assert_eq!(season.observe(&monday), [1, 2, 3]);
        // Thursday: fruit 1 grew and the visit is 1.5 cm off, fruit 2 was harvested, a new fruit
        // set 10 cm from fruit 3 (further than the match distance), ids within the visit differ.
        let thursday = [
            fruit(7, 0.415, 0.035),
            fruit(8, 0.5, 0.02),
            fruit(9, 0.015, 0.036),
        ];
        assert_eq!(season.observe(&thursday), [3, 4, 1]);
        let one = &season.fruits()[0];
        assert_eq!(one.history.len(), 2);
        assert_eq!(one.on(1).map(|r| r.visit_fruit_id), Some(9));
        assert!(season.fruits()[1].on(1).is_none(), "harvested");
    }

    #[test]
    fn a_fruit_missed_once_is_matched_again_a_volume_jump_is_not_the_same_fruit() {
        let mut season = SeasonTracker::new(SeasonRules::default());
        season.observe(&[fruit(1, 0.0, 0.03), fruit(2, 0.3, 0.03)]);
        season.observe(&[fruit(1, 0.3, 0.03)]);
        // Fruit 1 is back after a visit hidden; at fruit 2's place something 8x larger is not
        // fruit 2.
        assert_eq!(
            season.observe(&[fruit(1, 0.005, 0.031), fruit(2, 0.3, 0.065)]),
            [1, 3]
        );
    }
}
