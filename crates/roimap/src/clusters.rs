//! ROI clusters kept up to date as scans change the map, at a cost that follows the ROI voxels a
//! scan changed rather than every ROI voxel of the row.
//!
//! A cluster none of whose voxels changed and that has no changed voxel among its 26 neighbours
//! is still a whole connected component: nothing joined it (a joining voxel would be a changed
//! neighbour) and nothing left it. Only the other clusters and the changed voxels are grown
//! again. The result equals [`RoiMap::clusters`] on the same map.

use std::collections::{BTreeMap, HashMap};

use crate::{KeyBuildHasher, KeySet, Neighbourhood, RoiCluster, RoiMap, VoxelKey};

/// Clusters of one map with at least `min_voxels` voxels, updated by [`Clusters::update`].
#[derive(Clone, Debug)]
pub struct Clusters {
    min_voxels: usize,
    /// The map's ROI epoch these clusters were grown at (`None`: never).
    at_epoch: Option<u64>,
    /// The clusters by their smallest voxel (which orders them as [`RoiMap::clusters`] does).
    by_first: BTreeMap<VoxelKey, RoiCluster>,
    /// The smallest voxel of the cluster each member voxel belongs to.
    first_of: HashMap<VoxelKey, VoxelKey, KeyBuildHasher>,
}

/// What the last [`Clusters::update`] did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ClusterUpdate {
    /// Every ROI voxel was grown again (first update, or the map's changes were not all seen).
    pub full: bool,
    /// Clusters kept as they were.
    pub kept: usize,
    /// The smallest voxels of the clusters grown (again) by this update, sorted; a cluster grown
    /// back to the same voxels is among them.
    pub grown: Vec<VoxelKey>,
}

impl Clusters {
    pub fn new(min_voxels: usize) -> Self {
        Self {
            min_voxels: min_voxels.max(1),
            at_epoch: None,
            by_first: BTreeMap::new(),
            first_of: HashMap::default(),
        }
    }

    /// The clusters at the last update, ordered by their smallest key.
    pub fn iter(&self) -> impl Iterator<Item = &RoiCluster> {
        self.by_first.values()
    }

    /// The cluster whose smallest voxel is `first`.
    pub fn get(&self, first: &VoxelKey) -> Option<&RoiCluster> {
        self.by_first.get(first)
    }

    pub fn len(&self) -> usize {
        self.by_first.len()
    }

    pub fn is_empty(&self) -> bool {
        self.by_first.is_empty()
    }

    /// Forgets the clusters: the next update grows every ROI voxel (after the map was replaced).
    pub fn reset(&mut self) {
        *self = Self::new(self.min_voxels);
    }

    /// Brings the clusters up to date with `map`. Incremental when the map changed its ROI voxels
    /// at most once since the last update (it keeps only the latest change set); otherwise every
    /// ROI voxel is grown again.
    pub fn update(&mut self, map: &RoiMap) -> ClusterUpdate {
        let epoch = map.roi_epoch();
        let update = match self.at_epoch {
            Some(at) if at == epoch => ClusterUpdate {
                kept: self.by_first.len(),
                ..ClusterUpdate::default()
            },
            Some(at) if at + 1 == epoch => self.regrow(map, map.last_roi_changes()),
            _ => {
                self.by_first.clear();
                self.first_of.clear();
                let all = map.clusters(self.min_voxels);
                let grown = all.iter().map(|c| c.voxels[0]).collect();
                all.into_iter().for_each(|c| self.insert(c));
                ClusterUpdate {
                    full: true,
                    kept: 0,
                    grown,
                }
            }
        };
        self.at_epoch = Some(epoch);
        update
    }

    /// Grows again the clusters touched by `changed` (voxels whose ROI state changed) and the
    /// changed voxels that are ROI now; keeps the others.
    fn regrow(&mut self, map: &RoiMap, changed: &[VoxelKey]) -> ClusterUpdate {
        let mut touched: Vec<VoxelKey> = Vec::new();
        for &k in changed {
            let around = std::iter::once(k).chain(k.neighbours(Neighbourhood::TwentySix));
            touched.extend(around.filter_map(|n| self.first_of.get(&n).copied()));
        }
        touched.sort_unstable();
        touched.dedup();
        let roi = map.roi_voxels();
        let mut seeds: Vec<VoxelKey> = changed
            .iter()
            .copied()
            .filter(|k| roi.contains(k))
            .collect();
        for first in &touched {
            let Some(cluster) = self.by_first.remove(first) else {
                continue;
            };
            for k in &cluster.voxels {
                self.first_of.remove(k);
            }
            seeds.extend(cluster.voxels.into_iter().filter(|k| roi.contains(k)));
        }
        let kept = self.by_first.len();
        let grown_clusters = grow(map, roi, seeds, self.min_voxels);
        let mut grown: Vec<VoxelKey> = grown_clusters.iter().map(|c| c.voxels[0]).collect();
        grown.sort_unstable();
        grown_clusters.into_iter().for_each(|c| self.insert(c));
        ClusterUpdate {
            full: false,
            kept,
            grown,
        }
    }

    fn insert(&mut self, cluster: RoiCluster) {
        let first = cluster.voxels[0];
        for &k in &cluster.voxels {
            self.first_of.insert(k, first);
        }
        self.by_first.insert(first, cluster);
    }
}

/// The 26-connected components of `roi` reached from `seeds`, with at least `min_voxels` voxels.
fn grow(
    map: &RoiMap,
    roi: &KeySet,
    mut seeds: Vec<VoxelKey>,
    min_voxels: usize,
) -> Vec<RoiCluster> {
    seeds.sort_unstable();
    seeds.dedup();
    let mut visited = KeySet::default();
    let mut stack = Vec::new();
    let mut out = Vec::new();
    for seed in seeds {
        if !visited.insert(seed) {
            continue;
        }
        let mut members = vec![seed];
        stack.push(seed);
        while let Some(k) = stack.pop() {
            for n in k.neighbours(Neighbourhood::TwentySix) {
                if roi.contains(&n) && visited.insert(n) {
                    members.push(n);
                    stack.push(n);
                }
            }
        }
        if members.len() >= min_voxels {
            out.push(map.cluster_of(members));
        }
    }
    out
}
