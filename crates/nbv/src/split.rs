//! Touching fruits: one ROI cluster that is two fruits.
//!
//! Fruits that touch (or whose surfaces are one voxel apart) grow into one 26-connected cluster.
//! Reported as one fruit, such a pair costs a fruit in the count and gives a box and a solid
//! twice the size of either. [`split_touching`] tries a cluster as two when it is longer than
//! [`FitConfig::split_extent_m`] along some axis *and* either no single solid fits it
//! ([`fit_ellipsoid`] falls back to the box) or it has a waist ([`waist_ratio`]): touching
//! fruits narrow where they meet, and a superellipsoid bends enough to wrap two of them, while a
//! single fruit, lobed, tapered or tilted, has no waist. The voxels are divided by 2-means,
//! started at the two ends of the longest axis; the split is kept only when each half has
//! enough voxels and fits a solid of its own. A big single fruit fits one solid and is never
//! split; a split half is tried again (three fruits in a row), up to [`MAX_PARTS`]. A cluster
//! longer than any fruit (the fruit evidence's [`crate::evidence::EvidenceConfig::max_length_m`])
//! is split whatever its halves' fits say: whole it is dropped as too large, and in the
//! realistic world the fruits merged with each other or with red leaves into such clusters
//! (3 of 8 tuning trials, 6 fruits) fit poorly half by half.
//!
//! The converse, one fruit as two clusters (a leaf across it leaves two patches that do not
//! touch), is caught after fitting: [`fragments`] marks a cluster whose fitted centre lies inside
//! the fitted solid of a larger cluster, or whose solid overlaps it by more than a tenth of
//! their sizes ([`OVERLAP_RATIO`]). Solid fruits cannot hold each other's centres nor overlap,
//! so only a second view of the same fruit can: with pose errors its two patches are fitted a
//! few centimetres apart.

use glasshouse_roimap::{RoiCluster, RoiMap, VoxelKey};
use nalgebra::{Point3, Vector3};

use crate::evidence::principal_axes;
use crate::fit::{fit_ellipsoid, fit_read_box, FitConfig, FruitSolid, SolidKind};
use crate::superellipsoid::Superellipsoid;

/// Most fruits one cluster is split into.
pub const MAX_PARTS: usize = 4;
/// Width of the slabs of [`waist_ratio`], in voxels.
const WAIST_SLAB_VOXELS: f64 = 2.0;
/// A cluster narrower than this in the middle ([`waist_ratio`]) has a waist: touching fruits
/// measure 0.65-0.8 where they meet, single fruits (lobed, tapered, tilted) 0.94-1.
const WAIST_RATIO: f64 = 0.88;
/// Two fitted solids whose centres are closer than this share of the sum of their mean
/// semi-axes are one fruit (module docs). On tuning seeds 101-116 of the realistic world and
/// 101-108 with the hand-eye error doubled (scenario 2), the pairs of reported fruits this close
/// (0.53-0.85, ten pairs) were each one fruit reported twice, or a fruit and a patch 5 cm off
/// it; the nearest two different fruits were 1.05 apart.
pub const OVERLAP_RATIO: f64 = 0.9;
/// 2-means iterations (the assignment settles in a few).
const ITERATIONS: usize = 12;

/// Each cluster, or the touching fruits it is made of (see the module docs), ordered by their
/// smallest voxel. Parts keep at least `min_voxels` voxels.
pub fn split_touching(
    map: &RoiMap,
    clusters: Vec<RoiCluster>,
    min_voxels: usize,
    config: &FitConfig,
) -> Vec<RoiCluster> {
    let mut out = Vec::with_capacity(clusters.len());
    for cluster in clusters {
        out.extend(split_cluster(map, cluster, min_voxels, config).parts);
    }
    out.sort_by_key(|c| c.voxels.first().copied());
    out
}

/// One cluster as the fruits it is made of, with the part of the map the split read.
#[derive(Clone, Debug)]
pub struct Split {
    /// The cluster itself, or its parts (in no particular order).
    pub parts: Vec<RoiCluster>,
    /// Each part's fit when the split made one (same order as `parts`), with the box it read:
    /// exactly what [`fit_ellipsoid`] and [`fit_read_box`] give for that part on this map.
    pub fits: Vec<Option<(FruitSolid, ReadBox)>>,
    /// The box holding every voxel the fits tried read; `None` when the cluster is too short or
    /// too small to be tried, so nothing but its voxels decided.
    pub read: Option<ReadBox>,
}

/// A box of the map (min, max corners, world frame) that a computation read.
pub type ReadBox = (Point3<f64>, Point3<f64>);

/// The fits made while splitting one cluster, each made once.
#[derive(Default)]
struct Fits(Vec<(Vec<VoxelKey>, FruitSolid, ReadBox)>);

impl Fits {
    /// Whether `c` fits one solid, fitting it unless it was fitted before.
    fn ellipsoid(&mut self, map: &RoiMap, c: &RoiCluster, config: &FitConfig) -> bool {
        if let Some((_, shape, _)) = self.0.iter().find(|(v, _, _)| *v == c.voxels) {
            return shape.kind == SolidKind::Ellipsoid;
        }
        let shape = fit_ellipsoid(map, c, config);
        let read = fit_read_box(map, c, &shape, config);
        let ellipsoid = shape.kind == SolidKind::Ellipsoid;
        self.0.push((c.voxels.clone(), shape, read));
        ellipsoid
    }

    fn of(&self, c: &RoiCluster) -> Option<(FruitSolid, ReadBox)> {
        let found = self.0.iter().find(|(v, _, _)| *v == c.voxels);
        found.map(|(_, shape, read)| (*shape, *read))
    }

    fn read(&self) -> Option<ReadBox> {
        let boxes = self.0.iter().map(|(_, _, read)| *read);
        boxes.reduce(|(a, b), (lo, hi)| (a.inf(&lo), b.sup(&hi)))
    }
}

/// [`split_touching`] for one cluster: the same parts, their fits where the split made them,
/// and what was read to find them (so a caller can keep the result while that part of the map
/// is unchanged).
pub fn split_cluster(
    map: &RoiMap,
    cluster: RoiCluster,
    min_voxels: usize,
    config: &FitConfig,
) -> Split {
    let mut pending = vec![cluster];
    let mut parts = Vec::new();
    let mut fits = Fits::default();
    while let Some(c) = pending.pop() {
        if parts.len() + pending.len() + 1 >= MAX_PARTS {
            parts.push(c);
            continue;
        }
        match split_once(map, &c, min_voxels, config, &mut fits) {
            Some((a, b)) => pending.extend([a, b]),
            None => parts.push(c),
        }
    }
    Split {
        fits: parts.iter().map(|p| fits.of(p)).collect(),
        read: fits.read(),
        parts,
    }
}

/// For each fit (with its cluster's voxel count), whether it is a fragment of a fruit that a
/// larger cluster's fitted solid already holds or overlaps (see the module docs). Larger
/// clusters are judged first; a fragment never holds another. Box fallbacks hold nothing.
pub fn fragments(fits: &[FruitSolid], voxel_counts: &[usize]) -> Vec<bool> {
    let mut order: Vec<usize> = (0..fits.len().min(voxel_counts.len())).collect();
    order.sort_by_key(|&i| (std::cmp::Reverse(voxel_counts[i]), i));
    let mut fragment = vec![false; fits.len()];
    let mut holders: Vec<usize> = Vec::new();
    for i in order {
        let held = holders.iter().any(|&h| same_fruit(&fits[h], &fits[i]));
        if held {
            fragment[i] = true;
        } else if fits[i].kind == SolidKind::Ellipsoid {
            holders.push(i);
        }
    }
    fragment
}

/// Whether `part` is a second patch of the fruit fitted as `holder`: its centre lies inside
/// `holder`, or the two overlap ([`OVERLAP_RATIO`]).
fn same_fruit(holder: &FruitSolid, part: &FruitSolid) -> bool {
    let apart_m = (part.centre - holder.centre).norm();
    let sizes_m = holder.semi_axes_m.mean() + part.semi_axes_m.mean();
    apart_m < OVERLAP_RATIO * sizes_m || Superellipsoid::from(holder).holds(&part.centre, 0.0)
}

fn longest_extent_m(cluster: &RoiCluster) -> f64 {
    (cluster.max - cluster.min).max()
}

/// The two fruits `cluster` is made of, when it is one of those (the fits tried are kept in
/// `fits`).
fn split_once(
    map: &RoiMap,
    cluster: &RoiCluster,
    min_voxels: usize,
    config: &FitConfig,
    fits: &mut Fits,
) -> Option<(RoiCluster, RoiCluster)> {
    let min_voxels = min_voxels.max(config.min_voxels).max(1);
    if longest_extent_m(cluster) <= config.split_extent_m || cluster.voxels.len() < 2 * min_voxels {
        return None;
    }
    let too_long = too_long_for_a_fruit(map, cluster, config);
    let one_solid = fits.ellipsoid(map, cluster, config);
    if one_solid && !has_waist(map, cluster) && !too_long {
        return None;
    }
    let (a, b) = two_means(map, &cluster.voxels);
    if a.len() < min_voxels || b.len() < min_voxels {
        return None;
    }
    let (a, b) = (map.cluster_of(a), map.cluster_of(b));
    let halves_fit = fits.ellipsoid(map, &a, config) && fits.ellipsoid(map, &b, config);
    (halves_fit || too_long).then_some((a, b))
}

/// Whether the fruit evidence would call `cluster` too large for one fruit
/// ([`crate::evidence::Verdict::TooLarge`]): it is then split whatever its halves' fits say,
/// since whole it is no fruit at all.
fn too_long_for_a_fruit(map: &RoiMap, cluster: &RoiCluster, config: &FitConfig) -> bool {
    let points: Vec<Point3<f64>> = cluster.voxels.iter().map(|k| map.centre_of(*k)).collect();
    // The evidence's length, `√12·σ` along the first principal axis (its bulge is not needed).
    let length_m = principal_axes(&points).map_or(0.0, |pca| (12.0 * pca.variances_m2[0]).sqrt());
    config.evidence.enabled && length_m > config.evidence.max_length_m
}

/// The narrowest middle cross-section of `points` along their longest principal axis, relative
/// to the wider sections on both sides of it: the RMS distance from the axis in slabs of 2
/// voxels, each interior slab's over the smaller of the largest on its left and on its right
/// (1 or more: no waist).
pub fn waist_ratio(points: &[Point3<f64>], resolution_m: f64) -> f64 {
    let Some(pca) = principal_axes(points) else {
        return 1.0;
    };
    let axis: Vector3<f64> = pca.axes.column(0).into_owned();
    let along: Vec<f64> = points.iter().map(|p| (p - pca.mean).dot(&axis)).collect();
    let lo = along.iter().copied().fold(f64::INFINITY, f64::min);
    let slab_m = WAIST_SLAB_VOXELS * resolution_m;
    let slabs = ((along.iter().copied().fold(lo, f64::max) - lo) / slab_m).floor() as usize + 1;
    let mut sums = vec![(0.0, 0usize); slabs];
    for (p, t) in points.iter().zip(&along) {
        let i = (((t - lo) / slab_m) as usize).min(slabs - 1);
        let off_axis = (p - pca.mean) - axis * *t;
        sums[i].0 += off_axis.norm_squared();
        sums[i].1 += 1;
    }
    // Slabs with few voxels (the ends of the cluster) say little.
    let spread: Vec<Option<f64>> = sums
        .iter()
        .map(|&(s, n)| (n >= 4).then(|| (s / n as f64).sqrt()))
        .collect();
    let widest = |range: &[Option<f64>]| range.iter().flatten().copied().fold(0.0, f64::max);
    (1..slabs.saturating_sub(1))
        .filter_map(|i| {
            let here = spread[i]?;
            let sides = widest(&spread[..i]).min(widest(&spread[i + 1..]));
            (sides > 0.0).then(|| here / sides)
        })
        .fold(1.0, f64::min)
}

fn has_waist(map: &RoiMap, cluster: &RoiCluster) -> bool {
    let points: Vec<Point3<f64>> = cluster.voxels.iter().map(|k| map.centre_of(*k)).collect();
    waist_ratio(&points, map.config().resolution_m) < WAIST_RATIO
}

/// Divides voxels into two groups by 2-means on their centres, started at the voxels at either
/// end of the longest axis of their box (deterministic: no seed needed).
fn two_means(map: &RoiMap, voxels: &[VoxelKey]) -> (Vec<VoxelKey>, Vec<VoxelKey>) {
    let points: Vec<Point3<f64>> = voxels.iter().map(|k| map.centre_of(*k)).collect();
    let (lo, hi) = points.iter().fold(
        (
            Vector3::repeat(f64::INFINITY),
            Vector3::repeat(f64::NEG_INFINITY),
        ),
        |(lo, hi), p| (lo.inf(&p.coords), hi.sup(&p.coords)),
    );
    let axis = (hi - lo).imax();
    // The first voxel at each end (min_by keeps the first of equals).
    let lowest = points.iter().min_by(|a, b| a[axis].total_cmp(&b[axis]));
    let highest = points.iter().min_by(|a, b| b[axis].total_cmp(&a[axis]));
    let mut centres = [lowest, highest].map(|p| p.copied().unwrap_or_else(Point3::origin));
    let mut side = vec![false; points.len()];
    for _ in 0..ITERATIONS {
        for (s, p) in side.iter_mut().zip(&points) {
            *s = (p - centres[1]).norm_squared() < (p - centres[0]).norm_squared();
        }
        let mut sums = [Vector3::zeros(); 2];
        let mut counts = [0usize; 2];
        for (s, p) in side.iter().zip(&points) {
            sums[usize::from(*s)] += p.coords;
            counts[usize::from(*s)] += 1;
        }
        let next = [0, 1].map(|i| {
            if counts[i] == 0 {
                centres[i]
            } else {
                Point3::from(sums[i] / counts[i] as f64)
            }
        });
        if next == centres {
            break;
        }
        centres = next;
    }
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for (k, s) in voxels.iter().zip(&side) {
        if *s {
            b.push(*k);
        } else {
            a.push(*k);
        }
    }
    (a, b)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::fit::tests_support::*;

    fn around(map: &mut RoiMap, fruits: &[(Point3<f64>, Vector3<f64>)]) {
        let c = fruits[0].0;
        for eye in [
            Point3::new(c.x - 0.4, c.y - 0.05, c.z + 0.1),
            Point3::new(c.x + 0.4, c.y + 0.05, c.z + 0.1),
            Point3::new(c.x + 0.05, c.y - 0.4, c.z - 0.1),
            Point3::new(c.x, c.y + 0.4, c.z + 0.05),
        ] {
            scan_all(map, fruits, eye);
        }
    }

    /// Two fruits whose surfaces touch along x, scanned all round: the map, their centres and
    /// the map's clusters.
    fn touching_pair() -> (RoiMap, [Point3<f64>; 2], Vec<RoiCluster>) {
        let r = Vector3::new(0.035, 0.032, 0.04);
        let a = centre();
        let b = a + Vector3::new(0.071, 0.0, 0.004);
        let mut m = map();
        around(&mut m, &[(a, r), (b, r)]);
        let clusters = m.clusters(10);
        (m, [a, b], clusters)
    }

    #[test]
    fn two_touching_fruits_are_split_and_a_big_one_is_not() {
        let (m, [a, b], clusters) = touching_pair();
        assert_eq!(clusters.len(), 1, "the pair touches");
        let config = clean_scan_config();
        let split = split_touching(&m, clusters, 10, &config);
        assert_eq!(split.len(), 2);
        let mut found: Vec<Point3<f64>> = split
            .iter()
            .map(|c| fit_ellipsoid(&m, c, &config).centre)
            .collect();
        found.sort_by(|p, q| p.x.total_cmp(&q.x));
        assert!((found[0] - a).norm() < 0.01, "{found:?}");
        assert!((found[1] - b).norm() < 0.01, "{found:?}");
        assert!(split[0].voxels.first() < split[1].voxels.first());

        // One fruit as long as the pair's half-width plus more: fits one ellipsoid, kept whole.
        let big = Vector3::new(0.065, 0.04, 0.045);
        let mut m = map();
        around(&mut m, &[(a, big)]);
        let clusters = m.clusters(10);
        assert_eq!(clusters.len(), 1);
        assert!(longest_extent_m(&clusters[0]) > config.split_extent_m);
        assert_eq!(split_touching(&m, clusters.clone(), 10, &config), clusters);
    }

    #[test]
    fn a_second_patch_of_one_fruit_is_a_fragment_and_neighbours_are_not() {
        // A leaf band across the fruit at x = c.x ± 0.006 leaves two patches.
        let r = Vector3::new(0.035, 0.032, 0.04);
        let c = centre();
        let mut m = map();
        around(&mut m, &[(c, r)]);
        let mut whole = m.clusters(10);
        assert_eq!(whole.len(), 1);
        let (left, right): (Vec<_>, Vec<_>) = whole
            .remove(0)
            .voxels
            .into_iter()
            .filter(|k| (m.centre_of(*k).x - c.x).abs() > 0.006)
            .partition(|k| m.centre_of(*k).x < c.x);
        let config = clean_scan_config();
        let fit = |v: &Vec<VoxelKey>| fit_ellipsoid(&m, &m.cluster_of(v.clone()), &config);
        let (fl, fr) = (fit(&left), fit(&right));
        assert_eq!(fl.kind, SolidKind::Ellipsoid);
        let counts = [left.len(), right.len()];
        let marked = fragments(&[fl, fr], &counts);
        assert_eq!(marked.iter().filter(|f| **f).count(), 1, "{fl:?} {fr:?}");

        // Two fruits side by side, and a box fallback, hold nothing.
        let other = FruitSolid {
            centre: fl.centre + Vector3::new(2.0 * r.x + 0.002, 0.0, 0.0),
            ..fl
        };
        assert_eq!(fragments(&[fl, other], &[50, 40]), [false, false]);
        // A second patch fitted a few centimetres off (a pose error) overlaps: one fruit.
        let sizes_m = 2.0 * fl.semi_axes_m.mean();
        let shifted = |ratio: f64| FruitSolid {
            centre: fl.centre + Vector3::new(0.6, 0.0, 0.8) * (ratio * sizes_m),
            ..fl
        };
        assert_eq!(fragments(&[fl, shifted(0.8)], &[50, 40]), [false, true]);
        assert_eq!(fragments(&[fl, shifted(1.0)], &[50, 40]), [false, false]);
        let boxed = FruitSolid {
            kind: SolidKind::Box,
            ..fl
        };
        assert_eq!(fragments(&[boxed, fl], &[50, 40]), [false, false]);
        assert_eq!(fragments(&[fl, fl], &[40, 50]), [true, false]);
    }

    #[test]
    fn touching_fruits_have_a_waist_and_one_long_fruit_has_none() {
        let points = |m: &RoiMap| -> Vec<Point3<f64>> {
            let clusters = m.clusters(10);
            assert_eq!(clusters.len(), 1);
            clusters[0].voxels.iter().map(|k| m.centre_of(*k)).collect()
        };
        let (m, _, _) = touching_pair();
        let all_round = waist_ratio(&points(&m), 0.01);
        // The pair seen from one side only.
        let r = Vector3::new(0.035, 0.032, 0.04);
        let (a, b) = (centre(), centre() + Vector3::new(0.071, 0.0, 0.004));
        let mut m = map();
        scan_all(
            &mut m,
            &[(a, r), (b, r)],
            a + Vector3::new(0.05, -0.4, -0.1),
        );
        let one_side = waist_ratio(&points(&m), 0.01);
        let mut m = map();
        around(&mut m, &[(a, Vector3::new(0.065, 0.04, 0.045))]);
        let long = waist_ratio(&points(&m), 0.01);
        assert!(
            all_round < WAIST_RATIO && one_side < WAIST_RATIO,
            "{all_round} {one_side}"
        );
        assert!(long > 0.95, "{long}");
    }

    /// A red cluster 24 cm long fits one solid and has no waist, but no fruit is that long:
    /// whole it would be dropped as too large, so it is split and each part judged on its own.
    #[test]
    fn a_cluster_too_long_for_a_fruit_is_split_without_a_waist() {
        let mut m = map();
        around(&mut m, &[(centre(), Vector3::new(0.12, 0.035, 0.035))]);
        let clusters = m.clusters(10);
        assert_eq!(clusters.len(), 1);
        let config = clean_scan_config();
        let points: Vec<Point3<f64>> = clusters[0].voxels.iter().map(|k| m.centre_of(*k)).collect();
        let whole = crate::evidence::ClusterShape::of(&points, 0.01);
        assert_eq!(
            whole.verdict(&config.evidence),
            crate::evidence::Verdict::TooLarge
        );
        assert!(waist_ratio(&points, 0.01) >= WAIST_RATIO);
        assert!(split_touching(&m, clusters.clone(), 10, &config).len() >= 2);
        let judged_whole = FitConfig {
            evidence: crate::evidence::EvidenceConfig {
                enabled: false,
                ..config.evidence
            },
            ..config
        };
        assert_eq!(
            split_touching(&m, clusters.clone(), 10, &judged_whole),
            clusters
        );
    }

    #[test]
    fn small_clusters_and_disabled_splitting_are_left_alone() {
        let (m, _, clusters) = touching_pair();
        let off = FitConfig {
            split_extent_m: f64::INFINITY,
            ..clean_scan_config()
        };
        assert_eq!(split_touching(&m, clusters.clone(), 10, &off), clusters);
        // Halves must keep the minimum size.
        let n = clusters[0].voxels.len();
        let config = clean_scan_config();
        assert_eq!(split_touching(&m, clusters.clone(), n, &config), clusters);
        assert!(split_touching(&m, Vec::new(), 10, &config).is_empty());
    }
}
