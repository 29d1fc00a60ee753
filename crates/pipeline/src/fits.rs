//! Fruit fits kept while nothing they read has changed. A fit reads its cluster's voxels and the
//! map in a box around them (the free voxels beside the cluster, the observed share of the fitted
//! surface), so a scan that changed neither leaves the fit exactly as it was. The per-frame fit
//! cost then follows what the scan touched, not how many fruits the row holds. The evidence
//! that a cluster is a fruit (its shape and colour, [`ClusterEvidence`]) reads only the cluster's
//! voxels, and what the map knows inside the fitted solid ([`Interior`]) only the map within the
//! solid's box, which the fit reads too, so both are kept with the fit. The same holds for the touching-fruit splits
//! ([`SplitCache`]).

use std::collections::HashMap;

use glasshouse_nbv::evidence::{find_body, Body, ClusterEvidence, ClusterShape, Interior};
use glasshouse_nbv::fit::{fit_ellipsoid, fit_read_box, FitConfig, FruitSolid, SolidKind};
use glasshouse_nbv::split::{split_cluster, ReadBox};
use glasshouse_nbv::superellipsoid::Superellipsoid;
use glasshouse_roimap::{RoiCluster, RoiMap, VoxelKey};

use crate::parallel::in_parallel;
use nalgebra::Point3;

/// What a kept result read: the cluster's voxels, the box of the map it looked at and the map's
/// scan count then. It holds while the voxels are the same and nothing changed in the box.
#[derive(Clone, Debug)]
struct Reading {
    voxels: Vec<VoxelKey>,
    min: Point3<f64>,
    max: Point3<f64>,
    at_scans: u64,
}

impl Reading {
    fn of(map: &RoiMap, cluster: &RoiCluster, (min, max): ReadBox) -> Self {
        Self {
            voxels: cluster.voxels.clone(),
            min,
            max,
            at_scans: map.scans_inserted(),
        }
    }

    fn holds(&self, map: &RoiMap, cluster: &RoiCluster) -> bool {
        self.voxels == cluster.voxels && !map.changed_since(&self.min, &self.max, self.at_scans)
    }
}

/// A fit with what it read.
#[derive(Clone, Debug)]
struct CachedFit {
    read: Reading,
    shape: FruitSolid,
    evidence: ClusterEvidence,
    interior: Interior,
}

/// The fits of the latest clusters, keyed by each cluster's smallest voxel, and the shapes of
/// their voxels.
#[derive(Clone, Debug, Default)]
pub struct FitCache {
    by_first_voxel: HashMap<VoxelKey, CachedFit>,
    shapes: HashMap<VoxelKey, (Vec<VoxelKey>, ClusterShape)>,
    bodies: HashMap<VoxelKey, CachedBody>,
}

/// The body found under a turned-away cluster, fitted, with what the search and the fit read.
#[derive(Clone, Debug)]
struct CachedBody {
    read: Reading,
    fit: Option<FruitSolid>,
}

impl FitCache {
    /// The fits of `clusters` on `map`, in cluster order, refitting only the clusters whose
    /// voxels or surroundings changed since their last fit, on `threads` threads; also returns
    /// how many were refitted. The result equals fitting every cluster afresh, on any number of
    /// threads.
    pub fn update<'a>(
        &mut self,
        map: &RoiMap,
        clusters: impl IntoIterator<Item = &'a RoiCluster>,
        config: &FitConfig,
        threads: usize,
    ) -> (Vec<FruitSolid>, usize) {
        let clusters: Vec<&RoiCluster> = clusters.into_iter().collect();
        let compute = |c: &RoiCluster| fit(map, c, config);
        let cache = &mut self.by_first_voxel;
        refreshed(
            cache,
            map,
            &clusters,
            |c| &c.read,
            threads,
            compute,
            |c| c.shape,
        )
    }
}

/// For each of `clusters`, in order, `pick` of its cached result: kept where its reading still
/// holds, computed anew (on `threads` threads) where not; every result goes back into `cache`,
/// the rest is dropped. Also returns how many were computed.
fn refreshed<C: Send, T>(
    cache: &mut HashMap<VoxelKey, C>,
    map: &RoiMap,
    clusters: &[&RoiCluster],
    reading: impl Fn(&C) -> &Reading,
    threads: usize,
    compute: impl Fn(&RoiCluster) -> C + Sync,
    pick: impl Fn(&C) -> T,
) -> (Vec<T>, usize) {
    let kept = still_valid(cache, map, clusters, reading);
    let stale: Vec<usize> = (0..clusters.len()).filter(|&i| kept[i].is_none()).collect();
    let mut computed =
        in_parallel(stale.len(), threads, |j| compute(clusters[stale[j]])).into_iter();
    let picked = clusters
        .iter()
        .zip(kept)
        .map(|(cluster, kept)| {
            let result =
                kept.unwrap_or_else(|| computed.next().expect("a result per stale cluster"));
            let value = pick(&result);
            cache.insert(cluster.voxels[0], result);
            value
        })
        .collect();
    (picked, stale.len())
}

/// Takes every result out of `cache` and returns, in cluster order, those still valid: the
/// cluster's voxels the same and nothing changed in the box it read. The rest are dropped.
fn still_valid<C>(
    cache: &mut HashMap<VoxelKey, C>,
    map: &RoiMap,
    clusters: &[&RoiCluster],
    reading: impl Fn(&C) -> &Reading,
) -> Vec<Option<C>> {
    let mut previous = std::mem::take(cache);
    clusters
        .iter()
        .map(|cluster| {
            previous
                .remove(&cluster.voxels[0])
                .filter(|cached| reading(cached).holds(map, cluster))
        })
        .collect()
}

impl FitCache {
    /// A fit of `cluster` made elsewhere (by its split) on `map`, reading `read`: kept as if
    /// made here, so the cluster is not fitted twice.
    pub(crate) fn offer(
        &mut self,
        map: &RoiMap,
        cluster: &RoiCluster,
        shape: FruitSolid,
        read: ReadBox,
    ) {
        let cached = CachedFit {
            read: Reading::of(map, cluster, read),
            interior: Interior::of_fruit(map, &shape),
            shape,
            evidence: ClusterEvidence::of(map, cluster),
        };
        self.by_first_voxel.insert(cluster.voxels[0], cached);
    }

    /// What the voxels of `cluster` say (its shape and colour), kept since its last fit by
    /// [`FitCache::update`]; `None` for a cluster that update did not see.
    pub(crate) fn evidence_of(&self, cluster: &RoiCluster) -> Option<&ClusterEvidence> {
        self.cached(cluster).map(|cached| &cached.evidence)
    }

    /// What the map knew inside the fitted solid of `cluster` at its last fit; `None` for a
    /// cluster that update did not see.
    pub(crate) fn interior_of(&self, cluster: &RoiCluster) -> Option<Interior> {
        self.cached(cluster).map(|cached| cached.interior)
    }

    fn cached(&self, cluster: &RoiCluster) -> Option<&CachedFit> {
        let cached = self.by_first_voxel.get(cluster.voxels.first()?)?;
        (cached.read.voxels == cluster.voxels).then_some(cached)
    }

    /// The shape of each cluster's voxels ([`ClusterShape`]), in cluster order, computed again
    /// only for clusters whose voxels changed: it tells which clusters need a fit at all.
    pub(crate) fn shapes(&mut self, map: &RoiMap, clusters: &[RoiCluster]) -> Vec<ClusterShape> {
        let mut previous = std::mem::take(&mut self.shapes);
        let resolution_m = map.config().resolution_m;
        clusters
            .iter()
            .map(|cluster| {
                let first = cluster.voxels[0];
                let kept = previous
                    .remove(&first)
                    .filter(|(v, _)| *v == cluster.voxels);
                let (voxels, shape) = kept.unwrap_or_else(|| {
                    let centres: Vec<_> =
                        cluster.voxels.iter().map(|k| map.centre_of(*k)).collect();
                    (
                        cluster.voxels.clone(),
                        ClusterShape::of(&centres, resolution_m),
                    )
                });
                self.shapes.insert(first, (voxels, shape));
                shape
            })
            .collect()
    }
}

impl FitCache {
    /// For each of `clusters` (turned away by their shape or inside), the solid of the fruit
    /// body under it ([`glasshouse_nbv::evidence::body`]), if any, in cluster order; searched
    /// again only where the cluster or the map around it changed, on `threads` threads.
    pub(crate) fn bodies(
        &mut self,
        map: &RoiMap,
        clusters: &[&RoiCluster],
        config: &FitConfig,
        threads: usize,
    ) -> Vec<Option<FruitSolid>> {
        let compute = |c: &RoiCluster| body_fit(map, c, config);
        let cache = &mut self.bodies;
        refreshed(
            cache,
            map,
            clusters,
            |c| &c.read,
            threads,
            compute,
            |c| c.fit,
        )
        .0
    }
}

/// The solid of the fruit body under `cluster` ([`find_body`]), if there is one: the fit of the
/// body's surface voxels, or the sphere found when that fit gives only a box. What the planner
/// reports for a turned-away cluster (`TrolleyPlanner::cluster_outcomes`).
pub fn body_solid(map: &RoiMap, cluster: &RoiCluster, config: &FitConfig) -> Option<FruitSolid> {
    body_solid_read(map, cluster, config).map(|(solid, _)| solid)
}

/// [`body_solid`] and the box of the map its fit read.
fn body_solid_read(
    map: &RoiMap,
    cluster: &RoiCluster,
    config: &FitConfig,
) -> Option<(FruitSolid, ReadBox)> {
    let body = find_body(map, cluster, &config.evidence.body)?;
    let surface = map.cluster_of(body.surface.clone());
    let fitted = fit_ellipsoid(map, &surface, config);
    let read = fit_read_box(map, &surface, &fitted, config);
    let solid = match fitted.kind {
        SolidKind::Box => sphere_solid(&body),
        _ => fitted,
    };
    Some((solid, read))
}

/// [`body_solid`] with what the search and the fit read: the search's neighbourhood and the
/// fit's box.
fn body_fit(map: &RoiMap, cluster: &RoiCluster, config: &FitConfig) -> CachedBody {
    let res = map.config().resolution_m;
    let reach = f64::from(config.evidence.body.reach_voxels + 1) * res;
    let hood = nalgebra::Vector3::repeat(reach);
    let (mut min, mut max) = (cluster.centre - hood, cluster.centre + hood);
    let found = body_solid_read(map, cluster, config);
    if let Some((_, (lo, hi))) = found {
        (min, max) = (min.inf(&lo), max.sup(&hi));
    }
    CachedBody {
        read: Reading::of(map, cluster, (min, max)),
        fit: found.map(|(solid, _)| solid),
    }
}

fn sphere_solid(body: &Body) -> FruitSolid {
    Superellipsoid {
        centre: body.centre,
        world_from_body: nalgebra::Rotation3::identity(),
        semi_axes_m: nalgebra::Vector3::repeat(body.radius_m),
        exponents: [1.0, 1.0],
        taper: 0.0,
    }
    .to_solid(1.0, 0.0)
}

fn fit(map: &RoiMap, cluster: &RoiCluster, config: &FitConfig) -> CachedFit {
    let shape = fit_ellipsoid(map, cluster, config);
    let read = fit_read_box(map, cluster, &shape, config);
    CachedFit {
        read: Reading::of(map, cluster, read),
        interior: Interior::of_fruit(map, &shape),
        shape,
        evidence: ClusterEvidence::of(map, cluster),
    }
}

/// A split of one ROI cluster with what its fits read.
#[derive(Clone, Debug)]
struct CachedSplit {
    read: Reading,
    parts: Vec<RoiCluster>,
}

/// The touching-fruit splits of the latest ROI clusters ([`split_cluster`]), keyed by each
/// cluster's smallest voxel and kept while neither the cluster nor what its fits read changed:
/// a cluster long enough to be tried costs up to three fits, and a row holds many of them.
#[derive(Clone, Debug, Default)]
pub struct SplitCache {
    by_first_voxel: HashMap<VoxelKey, CachedSplit>,
}

impl SplitCache {
    /// The fruit clusters of `clusters` on `map`, ordered by their smallest voxel: equal to
    /// [`glasshouse_nbv::split::split_touching`], trying again only the clusters whose voxels
    /// or surroundings changed since their last split (on `threads` threads, the same splits on
    /// any number); also returns how many were tried again. The fits a split makes of its parts
    /// go to `fits`.
    pub fn update<'a>(
        &mut self,
        map: &RoiMap,
        clusters: impl Iterator<Item = &'a RoiCluster>,
        min_voxels: usize,
        config: &FitConfig,
        fits: &mut FitCache,
        threads: usize,
    ) -> (Vec<RoiCluster>, usize) {
        let clusters: Vec<&RoiCluster> = clusters.collect();
        let kept = still_valid(&mut self.by_first_voxel, map, &clusters, |c| &c.read);
        let stale: Vec<usize> = (0..clusters.len()).filter(|&i| kept[i].is_none()).collect();
        let mut splits = in_parallel(stale.len(), threads, |j| {
            split_cluster(map, clusters[stale[j]].clone(), min_voxels, config)
        })
        .into_iter();
        let (mut out, mut tries) = (Vec::new(), 0);
        for (cluster, kept) in clusters.into_iter().zip(kept) {
            let first = cluster.voxels[0];
            if let Some(cached) = kept {
                out.extend(cached.parts.iter().cloned());
                self.by_first_voxel.insert(first, cached);
                continue;
            }
            let split = splits.next().expect("a split per stale cluster");
            out.extend(split.parts.iter().cloned());
            for (part, fit) in split.parts.iter().zip(split.fits) {
                if let Some((shape, read)) = fit {
                    fits.offer(map, part, shape, read);
                }
            }
            if let Some(read) = split.read {
                tries += 1;
                let cached = CachedSplit {
                    read: Reading::of(map, cluster, read),
                    parts: split.parts,
                };
                self.by_first_voxel.insert(first, cached);
            }
        }
        out.sort_by_key(|c| c.voxels.first().copied());
        (out, tries)
    }
}
