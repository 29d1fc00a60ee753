//! Each fruit's observed colour ([`FruitColours`]): the colours of the detector's ROI points
//! (`RoiCloud::roi_rgb`) that fall in a fruit's voxels, summed per tracked fruit.
//!
//! Per fruit rather than per voxel: a snapshot then carries one sum per tracked fruit (32 bytes)
//! rather than one per ROI voxel. A cloud's points count for the fruits whose clusters hold
//! their voxels at the track that follows the cloud; a point whose voxel is not (yet) in a
//! cluster then is not counted later. Copies of a trolley's planner integrate the same clouds
//! and track after each, so they gather the same samples; the sums are integers, and a snapshot
//! carries them ([`glasshouse_proto::TrackedFruit::colour`]), so a copy made from it goes on
//! exactly as its original. Colours follow the tracker's ids: a fruit keeps its sum as long as
//! it keeps its id; each visit starts afresh (a visit's planner starts without ids).

use std::collections::HashMap;

use glasshouse_geom::{FruitEstimate, Rgb, RgbSum};
use glasshouse_proto::{RoiCloud, RoiColours, TrackedFruit};
use glasshouse_roimap::{KeyBuildHasher, RoiCluster, RoiMap, VoxelKey};
use nalgebra::Point3;

/// The colour samples of the tracked fruits, and those of the clouds inserted since the last
/// track.
#[derive(Clone, Debug, Default)]
pub(crate) struct FruitColours {
    /// Per fruit id of the last track (ids without samples left out).
    sums: HashMap<u32, RgbSum>,
    /// The ROI points' colours of the clouds inserted since the last track, per voxel.
    pending: HashMap<VoxelKey, RgbSum, KeyBuildHasher>,
    /// The world box around those points (min, max), to skip the clusters far from them.
    pending_box: Option<(Point3<f64>, Point3<f64>)>,
}

impl FruitColours {
    /// The sums a snapshot carried for its tracked fruits.
    pub(crate) fn from_tracked(tracked: &[TrackedFruit]) -> Self {
        let with_samples = tracked.iter().filter(|f| f.colour.samples > 0);
        Self {
            sums: with_samples.map(|f| (f.id, f.colour)).collect(),
            ..Self::default()
        }
    }

    /// Fruit `id`'s samples (none for an id it does not know).
    pub(crate) fn sum_of(&self, id: u32) -> RgbSum {
        self.sums.get(&id).copied().unwrap_or_default()
    }

    /// Notes the colours of `cloud`'s ROI points at `points`, its points as inserted (after
    /// registration, in the cloud's order). A cloud without colours, or with colours not one
    /// per ROI point ([`RoiColours::WrongLength`], which the planner service counts), adds
    /// none. Points outside the map's key range are skipped, as the map skips them.
    pub(crate) fn note_cloud(&mut self, map: &RoiMap, points: &[Point3<f32>], cloud: &RoiCloud) {
        let RoiColours::Rgb(colours) = cloud.roi_colours() else {
            return;
        };
        let roi_points = points.iter().zip(&cloud.roi).filter(|(_, &is_roi)| is_roi);
        for ((p, _), &rgb) in roi_points.zip(colours) {
            let p = p.cast::<f64>();
            let Some(key) = map.try_key_of(&p) else {
                continue;
            };
            self.pending.entry(key).or_default().add(Rgb::from(rgb));
            let (lo, hi) = self.pending_box.get_or_insert((p, p));
            (*lo, *hi) = (lo.inf(&p), hi.sup(&p));
        }
    }

    /// After the tracker gave `estimates` (ids) to `clusters` (same order): adds the noted
    /// samples that fall in each cluster's voxels to its fruit's sum, sets each estimate's
    /// colour to its mean, and forgets the ids no longer tracked.
    pub(crate) fn update(&mut self, clusters: &[RoiCluster], estimates: &mut [FruitEstimate]) {
        let mut sums = HashMap::with_capacity(estimates.len());
        for (cluster, estimate) in clusters.iter().zip(estimates.iter_mut()) {
            let mut sum = self.sums.remove(&estimate.id).unwrap_or_default();
            if self.near_pending(cluster) {
                for voxel in &cluster.voxels {
                    if let Some(samples) = self.pending.get(voxel) {
                        sum.merge(samples);
                    }
                }
            }
            estimate.colour = sum.mean();
            if sum.samples > 0 {
                sums.insert(estimate.id, sum);
            }
        }
        self.sums = sums;
        self.pending.clear();
        self.pending_box = None;
    }

    /// Whether the cluster's box meets the noted points' box.
    fn near_pending(&self, cluster: &RoiCluster) -> bool {
        let Some((lo, hi)) = &self.pending_box else {
            return false;
        };
        (0..3).all(|a| cluster.min[a] <= hi[a] && lo[a] <= cluster.max[a])
    }
}
