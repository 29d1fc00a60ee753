//! Each fruit followed from visit to visit ([`SeasonTracker`]): a revisit's fruits are matched to
//! the fruits known from the visits before, so a fruit seen on Monday keeps its id on Thursday.
//!
//! A fruit grows between visits (towards its stalk end, so its centre moves a few millimetres),
//! the trolley's pose errors move a whole visit by up to a centimetre or two, and leaves move.
//! So a visit is first registered to the fruits known: the pairs within
//! [`SeasonRules::coarse_distance_m`] give the visit's offset (the median of their differences,
//! per axis, with at least [`MIN_PAIRS_FOR_OFFSET`] pairs), and the visit's centres, shifted by
//! it, are matched one to one, greedily from the smallest centre distance, up to
//! [`SeasonRules::max_distance_m`], and only between a fruit and an estimate whose volumes are
//! within [`SeasonRules::max_volume_ratio`] of each other (a fruit does not halve, nor grow
//! eightfold, in a few days). Histories hold the shifted centres: every visit in the first
//! visit's frame. A known fruit that no estimate of a visit matches is closed
//! (harvested, or hidden this time: it may be matched again on a later visit, up to
//! [`SeasonRules::reopen_visits`] visits after it was last seen); an estimate that matches no known fruit is a new
//! fruit with a new id. Each fruit keeps its history: centre, size, volume and observed colour
//! per visit.

use glasshouse_geom::{FruitEstimate, FruitSurface, Rgb};
use nalgebra::{Point3, Vector3};
use serde::Serialize;

use crate::growth::{volume_change_m3, volume_ratio};

/// How visits are matched.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SeasonRules {
    pub max_distance_m: f64,
    /// Pairs this close estimate the visit's offset.
    pub coarse_distance_m: f64,
    pub max_volume_ratio: f64,
    /// A fruit stays matchable this many visits after it was last seen (2: one hidden on one
    /// visit is matched on the next).
    pub reopen_visits: usize,
}

impl Default for SeasonRules {
    fn default() -> Self {
        Self {
            max_distance_m: 0.04,
            coarse_distance_m: 0.08,
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
    /// Its mean observed colour on that visit ([`FruitEstimate::colour`]); `None`: unknown.
    pub colour: Option<Rgb>,
    /// Its volume over the record before it, measured on one shape
    /// ([`crate::growth::volume_ratio`]); `None`: not measured (the first record, a visit taken
    /// without surfaces, a fit missing on either visit).
    pub volume_ratio: Option<f64>,
}

/// A fruit over the season.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SeasonFruit {
    pub id: u32,
    pub history: Vec<VisitRecord>,
    /// The solid and surface of its last record, when that visit was taken with surfaces: what
    /// the next visit's growth is measured against.
    #[serde(skip)]
    pub last_surface: Option<FruitSurface>,
}

impl SeasonFruit {
    fn last(&self) -> Option<&VisitRecord> {
        self.history.last()
    }

    /// Whether it was seen on `visit`: its record then.
    pub fn on(&self, visit: usize) -> Option<&VisitRecord> {
        self.history.iter().find(|r| r.visit == visit)
    }

    /// Its volume change from its record before `visit` to `visit`'s: measured on one shape
    /// where the ratio was ([`crate::growth::volume_change_m3`]), else the difference of the
    /// two records' volumes; `None` without both records.
    pub fn volume_change_m3(&self, visit: usize) -> Option<f64> {
        let at = self.history.iter().position(|r| r.visit == visit)?;
        let (before, now) = (self.history.get(at.checked_sub(1)?)?, &self.history[at]);
        Some(match now.volume_ratio {
            Some(ratio) => volume_change_m3(before.volume_m3, now.volume_m3, ratio),
            None => now.volume_m3 - before.volume_m3,
        })
    }
}

/// Pairs needed to estimate a visit's offset; with fewer the visit is taken as it is.
pub const MIN_PAIRS_FOR_OFFSET: usize = 3;

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

    /// A tracker that knows `fruits` (their histories) and `visits` visits so far (the next
    /// one [`SeasonTracker::observe`] takes is visit `visits`); ids must be 1..=n in order, as
    /// the tracker gives them, else the fruits are renumbered so.
    pub fn from_fruits(rules: SeasonRules, fruits: Vec<SeasonFruit>, visits: usize) -> Self {
        let fruits = fruits
            .into_iter()
            .enumerate()
            .map(|(i, f)| SeasonFruit {
                id: i as u32 + 1,
                ..f
            })
            .collect();
        Self {
            rules,
            fruits,
            visits,
        }
    }

    /// Visits taken so far: the next one [`SeasonTracker::observe`] takes.
    pub fn visits(&self) -> usize {
        self.visits
    }

    /// Takes the next visit's estimates; returns each estimate's season id, in order.
    pub fn observe(&mut self, estimates: &[FruitEstimate]) -> Vec<u32> {
        self.observe_visit(self.visits, estimates)
    }

    /// Takes the estimates of visit `visit` (visits skipped before it saw nothing; an earlier
    /// visit than the next is taken as the next); returns each estimate's season id, in order.
    /// No growth is measured ([`SeasonTracker::observe_visit_measured`]).
    pub fn observe_visit(&mut self, visit: usize, estimates: &[FruitEstimate]) -> Vec<u32> {
        self.observe_visit_measured(visit, estimates, &[])
    }

    /// [`SeasonTracker::observe_visit`], with the surface each estimate's solid was fitted to
    /// (`surfaces[i]` estimate `i`'s voxel centres; missing or empty: none): each fruit's
    /// growth since its last record is measured on one shape ([`VisitRecord::volume_ratio`]),
    /// and its surface kept for the next visit.
    pub fn observe_visit_measured(
        &mut self,
        visit: usize,
        estimates: &[FruitEstimate],
        surfaces: &[Vec<Point3<f64>>],
    ) -> Vec<u32> {
        let visit = visit.max(self.visits);
        self.visits = visit + 1;
        let open: Vec<usize> = (0..self.fruits.len())
            .filter(|&i| {
                self.fruits[i]
                    .last()
                    .is_some_and(|r| visit - r.visit <= self.rules.reopen_visits)
            })
            .collect();
        let coarse = self.matches(
            estimates,
            &open,
            Vector3::zeros(),
            self.rules.coarse_distance_m,
        );
        let offset = self.offset_of(estimates, &coarse);
        let matched = self.matches(estimates, &open, offset, self.rules.max_distance_m);
        let mut ids: Vec<Option<u32>> = vec![None; estimates.len()];
        let surface_of = |e: usize| {
            let points = surfaces.get(e).filter(|p| !p.is_empty())?;
            let solid = estimates[e].solid?;
            Some(FruitSurface {
                solid,
                points_m: thinned(points),
            })
        };
        for (e, f) in matched {
            ids[e] = Some(self.fruits[f].id);
            let fruit = &mut self.fruits[f];
            let surface = surface_of(e);
            let mut now = record(visit, &estimates[e], &offset);
            if let (Some(before), Some(after)) = (&fruit.last_surface, &surface) {
                now.volume_ratio = volume_ratio(before, after);
            }
            fruit.history.push(now);
            fruit.last_surface = surface;
        }
        ids.iter()
            .enumerate()
            .zip(estimates)
            .map(|((e, id), estimate)| {
                id.unwrap_or_else(|| self.open_new(visit, estimate, &offset, surface_of(e)))
            })
            .collect()
    }

    /// One-to-one (estimate, fruit) pairs of the estimates shifted by `offset` within
    /// `max_distance_m`, greedily from the smallest distance.
    fn matches(
        &self,
        estimates: &[FruitEstimate],
        open: &[usize],
        offset: Vector3<f64>,
        max_distance_m: f64,
    ) -> Vec<(usize, usize)> {
        let mut pairs = Vec::new();
        for (e, estimate) in estimates.iter().enumerate() {
            for &f in open {
                if let Some(d) = self.distance(f, estimate, &offset, max_distance_m) {
                    pairs.push((d, e, f));
                }
            }
        }
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        let (mut estimate_taken, mut fruit_taken) =
            (vec![false; estimates.len()], vec![false; self.fruits.len()]);
        let mut out = Vec::new();
        for (_, e, f) in pairs {
            if !estimate_taken[e] && !fruit_taken[f] {
                estimate_taken[e] = true;
                fruit_taken[f] = true;
                out.push((e, f));
            }
        }
        out
    }

    /// The visit's offset against the fruits known: the per-axis median of the pairs'
    /// differences (estimate minus fruit); zero with fewer than [`MIN_PAIRS_FOR_OFFSET`] pairs.
    fn offset_of(&self, estimates: &[FruitEstimate], pairs: &[(usize, usize)]) -> Vector3<f64> {
        if pairs.len() < MIN_PAIRS_FOR_OFFSET {
            return Vector3::zeros();
        }
        let median = |axis: usize| {
            let mut d: Vec<f64> = pairs
                .iter()
                .filter_map(|&(e, f)| {
                    let last = self.fruits[f].last()?;
                    Some(estimates[e].centre[axis] - last.centre[axis])
                })
                .collect();
            d.sort_by(f64::total_cmp);
            d.get(d.len() / 2).copied().unwrap_or(0.0)
        };
        Vector3::new(median(0), median(1), median(2))
    }

    /// The centre distance between fruit `f`'s last record and `estimate` shifted back by
    /// `offset`, when they may be the same fruit.
    fn distance(
        &self,
        f: usize,
        estimate: &FruitEstimate,
        offset: &Vector3<f64>,
        max_distance_m: f64,
    ) -> Option<f64> {
        let last = self.fruits[f].last()?;
        let d = (last.centre - (estimate.centre - offset)).norm();
        let ratio = estimate_volume_m3(estimate) / last.volume_m3;
        let r = self.rules.max_volume_ratio;
        let plausible = ratio.is_finite() && ratio >= 1.0 / r && ratio <= r;
        (d <= max_distance_m && plausible).then_some(d)
    }

    fn open_new(
        &mut self,
        visit: usize,
        estimate: &FruitEstimate,
        offset: &Vector3<f64>,
        surface: Option<FruitSurface>,
    ) -> u32 {
        let id = self.fruits.len() as u32 + 1;
        self.fruits.push(SeasonFruit {
            id,
            history: vec![record(visit, estimate, offset)],
            last_surface: surface,
        });
        id
    }
}

/// A fruit's surface keeps at most this many points (snapshots and the store carry it).
pub const MAX_SURFACE_POINTS: usize = 128;

/// `points`, every k-th kept so that at most [`MAX_SURFACE_POINTS`] remain.
fn thinned(points: &[Point3<f64>]) -> Vec<Point3<f64>> {
    let n = points.len();
    if n <= MAX_SURFACE_POINTS {
        return points.to_vec();
    }
    (0..MAX_SURFACE_POINTS)
        .map(|i| points[i * n / MAX_SURFACE_POINTS])
        .collect()
}

/// An estimate's record, its centre shifted back by its visit's `offset`.
fn record(visit: usize, e: &FruitEstimate, offset: &Vector3<f64>) -> VisitRecord {
    VisitRecord {
        visit,
        centre: e.centre - offset,
        size_m: e.max - e.min,
        volume_m3: estimate_volume_m3(e),
        visit_fruit_id: e.id,
        colour: e.colour,
        volume_ratio: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glasshouse_geom::FruitSolid;

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
    fn each_visit_keeps_the_fruits_colour_then() {
        let mut season = SeasonTracker::new(SeasonRules::default());
        let green = Rgb::new(90, 140, 40);
        let red = Rgb::new(185, 40, 30);
        let with = |f: FruitEstimate, colour| FruitEstimate { colour, ..f };
        season.observe(&[with(fruit(1, 0.0, 0.03), Some(green)), fruit(2, 0.3, 0.03)]);
        season.observe(&[
            with(fruit(4, 0.002, 0.032), Some(red)),
            fruit(5, 0.3, 0.031),
        ]);
        let colours = |i: usize| -> Vec<_> {
            season.fruits()[i]
                .history
                .iter()
                .map(|r| r.colour)
                .collect()
        };
        assert_eq!(colours(0), [Some(green), Some(red)]);
        assert_eq!(colours(1), [None, None], "no colour seen, none made up");
    }

    #[test]
    fn a_visit_shifted_by_the_trolleys_error_is_registered_first() {
        let mut season = SeasonTracker::new(SeasonRules::default());
        let monday: Vec<FruitEstimate> = (0..5)
            .map(|i| fruit(i + 1, 0.1 * f64::from(i), 0.03))
            .collect();
        season.observe(&monday);
        // The whole visit 5 cm off along the row: beyond the match distance, but one offset.
        let thursday: Vec<FruitEstimate> = (0..5)
            .map(|i| fruit(i + 10, 0.1 * f64::from(i) + 0.05, 0.031))
            .collect();
        assert_eq!(season.observe(&thursday), [1, 2, 3, 4, 5]);
        let back = season.fruits()[2]
            .on(1)
            .map(|r| r.centre.x)
            .unwrap_or(f64::NAN);
        assert!((back - 0.2).abs() < 1e-9, "{back}");
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

    /// A round fruit of radius `r_m` at `x` with a fitted sphere, and the voxel centres (5 mm)
    /// of the half of its surface facing +x. (On the planner's 1 cm voxels the way the grid cuts
    /// a small fruit's surface moves a scale by a few per cent; this test is of the tracker.)
    fn round_fruit(id: u32, x: f64, r_m: f64) -> (FruitEstimate, Vec<Point3<f64>>) {
        use crate::superellipsoid::Superellipsoid;
        let c = Point3::new(x, 0.0, 1.0);
        let sphere = Superellipsoid::sphere(c, r_m);
        let points = sphere.seen_voxel_centres(Vector3::x(), 0.005);
        let h = Vector3::repeat(r_m);
        let mut estimate = FruitEstimate::from_box(id, c, c - h, c + h);
        estimate.solid = Some(FruitSolid {
            kind: glasshouse_geom::SolidKind::Ellipsoid,
            volume_m3: sphere.volume_m3(),
            ..estimate.solid_or_box()
        });
        (estimate, points)
    }

    #[test]
    fn growth_is_measured_on_one_shape_when_a_visit_comes_with_its_surfaces() {
        let mut season = SeasonTracker::new(SeasonRules::default());
        let (monday, monday_surface) = round_fruit(1, 0.0, 0.03);
        season.observe_visit_measured(0, &[monday], &[monday_surface]);
        // Thursday's fit made it 30 % too large, but its surface says it grew 10 % in size.
        let (mut thursday, thursday_surface) = round_fruit(4, 0.012, 0.033);
        if let Some(solid) = &mut thursday.solid {
            solid.volume_m3 *= 1.3;
        }
        season.observe_visit_measured(1, &[thursday], &[thursday_surface]);
        let fruit = &season.fruits()[0];
        let ratio = fruit.history[1].volume_ratio.expect("growth measured");
        assert!((ratio / 1.1f64.powi(3) - 1.0).abs() < 0.12, "{ratio}");
        let true_change = 4.0 / 3.0 * std::f64::consts::PI * (0.033f64.powi(3) - 0.03f64.powi(3));
        let measured = fruit.volume_change_m3(1).expect("two records");
        let differenced = fruit.history[1].volume_m3 - fruit.history[0].volume_m3;
        let error = |v: f64| (v - true_change).abs() / true_change;
        assert!(
            error(measured) < 0.5 * error(differenced),
            "{measured} {differenced}"
        );
        // Without surfaces no growth is measured: the difference of the volumes stands.
        let mut plain = SeasonTracker::new(SeasonRules::default());
        plain.observe(&[round_fruit(1, 0.0, 0.03).0]);
        plain.observe(&[thursday]);
        let fruit = &plain.fruits()[0];
        assert_eq!(fruit.history[1].volume_ratio, None);
        assert_eq!(fruit.volume_change_m3(1), Some(differenced));
        assert_eq!(
            fruit.volume_change_m3(0),
            None,
            "no record before the first"
        );
    }
}
