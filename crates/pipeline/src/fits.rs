//! Fruit fits kept while nothing they read has changed. A fit reads its cluster's voxels and the
//! map in a box around them (the free voxels beside the cluster, the observed share of the fitted
//! surface), so a scan that changed neither leaves the fit exactly as it was. The per-frame fit
//! cost then follows what the scan touched, not how many fruits the row holds.

use std::collections::HashMap;

use glasshouse_nbv::fit::{fit_ellipsoid, FitConfig, FittedShape};
use glasshouse_roimap::{RoiCluster, RoiMap, VoxelKey};
use nalgebra::{Point3, Vector3};

/// A fit with what it read: the cluster's voxels, the box of the map it looked at and the map's
/// scan count then.
#[derive(Clone, Debug)]
struct CachedFit {
    voxels: Vec<VoxelKey>,
    read_min: Point3<f64>,
    read_max: Point3<f64>,
    at_scans: u64,
    shape: FittedShape,
}

/// The fits of the latest clusters, keyed by each cluster's smallest voxel.
#[derive(Clone, Debug, Default)]
pub(crate) struct FitCache {
    by_first_voxel: HashMap<VoxelKey, CachedFit>,
}

impl FitCache {
    /// The fits of `clusters` on `map`, in cluster order, refitting only the clusters whose
    /// voxels or surroundings changed since their last fit; also returns how many were refitted.
    /// The result equals fitting every cluster afresh.
    pub(crate) fn update(
        &mut self,
        map: &RoiMap,
        clusters: &[RoiCluster],
        config: &FitConfig,
    ) -> (Vec<FittedShape>, usize) {
        let mut previous = std::mem::take(&mut self.by_first_voxel);
        let mut refits = 0;
        let shapes = clusters
            .iter()
            .map(|cluster| {
                let first = cluster.voxels[0];
                let kept = previous.remove(&first).filter(|cached| {
                    cached.voxels == cluster.voxels
                        && !map.changed_since(&cached.read_min, &cached.read_max, cached.at_scans)
                });
                let cached = kept.unwrap_or_else(|| {
                    refits += 1;
                    fit(map, cluster, config)
                });
                let shape = cached.shape.clone();
                self.by_first_voxel.insert(first, cached);
                shape
            })
            .collect();
        (shapes, refits)
    }
}

fn fit(map: &RoiMap, cluster: &RoiCluster, config: &FitConfig) -> CachedFit {
    let shape = fit_ellipsoid(map, cluster, config);
    // What the fit reads: the free-voxel search box around the cluster and the fitted surface's
    // box (its observed share), padded by two voxels for rounding to keys.
    let pad = Vector3::repeat(config.free_search_margin_m.max(0.0));
    let slack = Vector3::repeat(2.0 * map.config().resolution_m);
    let min = (cluster.min - pad).inf(&shape.box_min) - slack;
    let max = (cluster.max + pad).sup(&shape.box_max) + slack;
    CachedFit {
        voxels: cluster.voxels.clone(),
        read_min: min,
        read_max: max,
        at_scans: map.scans_inserted(),
        shape,
    }
}
