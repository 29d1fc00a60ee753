//! The fleet fruit map: per-trolley fruit estimates merged into one list, with fruits seen by
//! several trolleys (where their rows overlap) counted once.
//!
//! Two fruits from different trolleys are the same fruit when their centres are within the merge
//! distance, or when their axis-aligned boxes overlap by more than half of the smaller box's
//! volume. Matches are joined with a union-find, so a chain A~B~C becomes one fruit even if A and C
//! do not match directly. Fruits of the same trolley are never joined, not even through a chain:
//! the planner already separated them, so a union that would put two fruits of one trolley in the
//! same fleet fruit is refused. To keep that deterministic, matches are joined closest first
//! (centre distance, then the ids of the pair).
//!
//! The result depends only on the set of inputs, never on their order.

use std::cmp::Ordering;
use std::collections::{BTreeMap, BTreeSet};

use glasshouse_geom::FruitEstimate;
use nalgebra::Point3;
use serde::{Deserialize, Serialize};

/// Default merge distance between fruit centres, metres.
pub const MERGE_DISTANCE_M: f64 = 0.05;

/// One fruit estimate of one trolley's planner, in the world frame (metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrolleyFruit {
    pub trolley_id: String,
    /// Its id is the planner's stable fruit id within the trolley.
    pub fruit: FruitEstimate,
}

impl TrolleyFruit {
    fn key(&self) -> (&str, u32) {
        (self.trolley_id.as_str(), self.fruit.id)
    }

    fn is_finite(&self) -> bool {
        let f = &self.fruit;
        f.centre
            .iter()
            .chain(f.min.iter())
            .chain(f.max.iter())
            .chain([&f.volume_m3, &f.confidence])
            .all(|v| v.is_finite())
    }
}

/// One fruit of the fleet map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FleetFruit {
    /// `"{trolley}/{fruit}"` of the smallest `(trolley_id, fruit_id)` among the sources: stable as
    /// long as that source keeps being reported.
    pub fleet_id: String,
    /// The estimate kept, as its source reported it.
    pub fruit: FruitEstimate,
    /// The source whose estimate is kept: highest confidence, ties to the smallest
    /// `(trolley_id, fruit_id)`.
    pub estimate_from: (String, u32),
    /// Every `(trolley_id, fruit_id)` merged into this fruit, sorted; at most one per trolley.
    pub sources: Vec<(String, u32)>,
}

/// The merged fleet map and what was left out.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MergeResult {
    /// Sorted by the key of the fleet id: trolley id, then fruit id numerically (so `t1/9` comes
    /// before `t1/10`).
    pub fruits: Vec<FleetFruit>,
    /// Inputs with a non-finite centre, box corner, volume or confidence.
    pub skipped_non_finite: usize,
    /// Inputs repeating a `(trolley_id, fruit_id)` already given; the better estimate of the two
    /// (as for [`FleetFruit::estimate_from`], then by value) is kept.
    pub skipped_duplicate: usize,
}

/// Merges per-trolley fruit lists into the fleet map (see the module documentation).
///
/// `merge_distance_m` is inclusive; a negative or NaN distance merges by box overlap only.
pub fn merge_fruits(inputs: &[TrolleyFruit], merge_distance_m: f64) -> MergeResult {
    let mut skipped_non_finite = 0;
    let mut skipped_duplicate = 0;
    let mut by_key: BTreeMap<(&str, u32), &TrolleyFruit> = BTreeMap::new();
    for input in inputs {
        if !input.is_finite() {
            skipped_non_finite += 1;
            continue;
        }
        match by_key.entry(input.key()) {
            std::collections::btree_map::Entry::Vacant(e) => {
                e.insert(input);
            }
            std::collections::btree_map::Entry::Occupied(mut e) => {
                skipped_duplicate += 1;
                if estimate_cmp(input, e.get()) == Ordering::Less {
                    e.insert(input);
                }
            }
        }
    }
    // Indices follow key order, whatever the input order.
    let fruits: Vec<&TrolleyFruit> = by_key.into_values().collect();

    let mut edges = candidate_matches(&fruits, merge_distance_m);
    edges.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));

    let mut sets = DisjointSets::new(&fruits);
    for &(_, i, j) in &edges {
        sets.union_if_disjoint_trolleys(i, j);
    }

    // Group by root; members come out in index (= key) order.
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for i in 0..fruits.len() {
        groups.entry(sets.find(i)).or_default().push(i);
    }
    let mut groups: Vec<Vec<usize>> = groups.into_values().collect();
    // The first member is the smallest key: order groups by it.
    groups.sort_unstable_by_key(|g| g.first().copied());

    let merged = groups
        .into_iter()
        .filter_map(|members| {
            let best = members
                .iter()
                .map(|&i| fruits[i])
                .min_by(|a, b| estimate_cmp(a, b))?;
            let sources: Vec<(String, u32)> = members
                .iter()
                .map(|&i| (fruits[i].trolley_id.clone(), fruits[i].fruit.id))
                .collect();
            let (first_trolley, first_fruit) = sources.first()?;
            Some(FleetFruit {
                fleet_id: format!("{first_trolley}/{first_fruit}"),
                fruit: best.fruit,
                estimate_from: (best.trolley_id.clone(), best.fruit.id),
                sources,
            })
        })
        .collect();

    MergeResult {
        fruits: merged,
        skipped_non_finite,
        skipped_duplicate,
    }
}

/// Which estimate to keep: `Less` means `a` is better. Highest confidence, then smallest key, then
/// (only between duplicates of one key) the values themselves, so the order is total.
fn estimate_cmp(a: &TrolleyFruit, b: &TrolleyFruit) -> Ordering {
    let values = |f: &TrolleyFruit| {
        let f = &f.fruit;
        let mut v = [0.0; 10];
        v[..3].copy_from_slice(f.centre.coords.as_slice());
        v[3..6].copy_from_slice(f.min.coords.as_slice());
        v[6..9].copy_from_slice(f.max.coords.as_slice());
        v[9] = f.volume_m3;
        v
    };
    b.fruit
        .confidence
        .total_cmp(&a.fruit.confidence)
        .then_with(|| a.key().cmp(&b.key()))
        .then_with(|| {
            values(a)
                .iter()
                .zip(values(b).iter())
                .map(|(x, y)| x.total_cmp(y))
                .find(|o| o.is_ne())
                .unwrap_or(Ordering::Equal)
        })
}

fn distance(a: &Point3<f64>, b: &Point3<f64>) -> f64 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

fn box_volume(min: &Point3<f64>, max: &Point3<f64>) -> f64 {
    (0..3).map(|k| (max[k] - min[k]).max(0.0)).product()
}

fn intersection_volume(a: &FruitEstimate, b: &FruitEstimate) -> f64 {
    (0..3)
        .map(|k| (a.max[k].min(b.max[k]) - a.min[k].max(b.min[k])).max(0.0))
        .product()
}

/// The centre distance of `a` and `b` if they are the same fruit by the merge rule.
fn match_distance(a: &TrolleyFruit, b: &TrolleyFruit, merge_distance_m: f64) -> Option<f64> {
    if a.trolley_id == b.trolley_id {
        return None;
    }
    let (a, b) = (&a.fruit, &b.fruit);
    let d = distance(&a.centre, &b.centre);
    if d <= merge_distance_m {
        return Some(d);
    }
    let smaller = box_volume(&a.min, &a.max).min(box_volume(&b.min, &b.max));
    // NaN (overflowing boxes) compares false: no merge.
    (smaller > 0.0 && intersection_volume(a, b) > 0.5 * smaller).then_some(d)
}

/// All matching pairs `(distance, i, j)` with `i < j`, by sweep and prune along x.
///
/// Each fruit spans `[min(box, centre - h), max(box, centre + h)]` on x with `h` a hair over half
/// the merge distance: two fruits can match only if their spans intersect (box overlap needs the
/// boxes' x ranges to intersect; close centres need `|dx| <= merge distance`).
fn candidate_matches(fruits: &[&TrolleyFruit], merge_distance_m: f64) -> Vec<(f64, usize, usize)> {
    let half = if merge_distance_m > 0.0 {
        merge_distance_m * (0.5 + 1e-9)
    } else {
        0.0
    };
    let spans: Vec<(f64, f64)> = fruits
        .iter()
        .map(|f| {
            let f = &f.fruit;
            (
                f.min[0].min(f.centre[0] - half),
                f.max[0].max(f.centre[0] + half),
            )
        })
        .collect();
    let mut order: Vec<usize> = (0..fruits.len()).collect();
    order.sort_unstable_by(|&a, &b| spans[a].0.total_cmp(&spans[b].0).then(a.cmp(&b)));

    let mut edges = Vec::new();
    let mut active: Vec<usize> = Vec::new();
    for &k in &order {
        let lo = spans[k].0;
        active.retain(|&a| spans[a].1 >= lo);
        for &a in &active {
            if let Some(d) = match_distance(fruits[a], fruits[k], merge_distance_m) {
                edges.push((d, a.min(k), a.max(k)));
            }
        }
        active.push(k);
    }
    edges
}

/// Union-find over fruit indices; each root knows the trolleys of its set.
struct DisjointSets<'a> {
    parent: Vec<usize>,
    trolleys: Vec<BTreeSet<&'a str>>,
}

impl<'a> DisjointSets<'a> {
    fn new(fruits: &[&'a TrolleyFruit]) -> Self {
        Self {
            parent: (0..fruits.len()).collect(),
            trolleys: fruits
                .iter()
                .map(|f| BTreeSet::from([f.trolley_id.as_str()]))
                .collect(),
        }
    }

    fn find(&mut self, mut i: usize) -> usize {
        let mut root = i;
        while self.parent[root] != root {
            root = self.parent[root];
        }
        while self.parent[i] != root {
            let next = self.parent[i];
            self.parent[i] = root;
            i = next;
        }
        root
    }

    /// Joins the sets of `i` and `j` unless they share a trolley.
    fn union_if_disjoint_trolleys(&mut self, i: usize, j: usize) {
        let (ri, rj) = (self.find(i), self.find(j));
        if ri == rj || !self.trolleys[ri].is_disjoint(&self.trolleys[rj]) {
            return;
        }
        let (big, small) = if self.trolleys[ri].len() >= self.trolleys[rj].len() {
            (ri, rj)
        } else {
            (rj, ri)
        };
        let moved = std::mem::take(&mut self.trolleys[small]);
        self.trolleys[big].extend(moved);
        self.parent[small] = big;
    }
}
