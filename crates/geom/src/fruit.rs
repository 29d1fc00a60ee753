//! One fruit estimate, from the map to the wire to the metrics, and the one covered-volume rule.
//!
//! [`FruitEstimate`] is what the planner finds (the paper's box over the cluster and the fitted
//! solid), what travels in FruitEstimates and FleetFruits, and what the experiments and the
//! dashboard judge. [`box_voxel_keys`] is the only rule saying which voxels a box covers and
//! [`covered_volume`] the only covered-ROI-volume figure: the experiments and the dashboard both
//! call them.

use std::collections::HashSet;

use nalgebra::{Point3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::{Aabb, Rgb};

/// How a [`FruitSolid`] was obtained.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum SolidKind {
    /// A fitted (super)ellipsoid: [`FruitSolid::exponents`] say which.
    Ellipsoid,
    /// The fit was degenerate: the ellipsoid inscribed in the cluster's box.
    Box,
}

/// The whole-fruit solid fitted to a cluster: a rotated, tapered superellipsoid, world frame,
/// metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FruitSolid {
    pub kind: SolidKind,
    /// Centroid of the solid (its body origin too, unless tapered).
    pub centre: Point3<f64>,
    /// Semi-axes along the body axes (the columns of `world_from_body`).
    pub semi_axes_m: Vector3<f64>,
    /// Orientation of the body axes; the identity for axis-aligned fits and box fallbacks.
    pub world_from_body: UnitQuaternion<f64>,
    /// Shape exponents `[ε1, ε2]`; `[1, 1]` is an ellipsoid.
    pub exponents: [f64; 2],
    /// Taper along body z: the cross-section at `z = ±c` is `1 ± taper` times as wide as at the
    /// middle; 0 for ellipsoids.
    pub taper: f64,
    /// Volume of the solid (`4/3·π·a·b·c` for an ellipsoid).
    pub volume_m3: f64,
    /// World-axis box around the solid (`centre ∓ semi_axes` when axis-aligned).
    pub box_min: Point3<f64>,
    pub box_max: Point3<f64>,
    /// Volume of that box (comparable with box ground truth; `8·a·b·c` when axis-aligned).
    pub box_volume_m3: f64,
    /// Share of the fitted surface the map has observed, in [0, 1].
    pub confidence: f64,
    /// Root mean square distance of the cluster's voxel centres from the fitted surface, metres
    /// (the surface they were fitted to, before the fit's voxel bias was taken off the solid).
    pub rms_residual_m: f64,
}

/// One fruit: an ROI cluster with a stable id, its box, and the solid fitted to it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FruitEstimate {
    /// Stable within its trolley; 0 is never a fruit.
    pub id: u32,
    /// Mean of the voxel centres, world frame (for ground truth: the body's centroid).
    pub centre: Point3<f64>,
    /// Box over the cluster's voxels, world frame.
    pub min: Point3<f64>,
    pub max: Point3<f64>,
    /// Volume of the box (for ground truth: the body's volume).
    pub volume_m3: f64,
    pub voxel_count: usize,
    /// That the cluster is a fruit, in [0, 1]: the share of its box's surface voxels seen as ROI
    /// as the tracker gives it, the fruit evidence's confidence once judged (what is published).
    pub confidence: f64,
    /// Distinct directions from which scans hit this fruit; 0 when none were noted.
    pub view_directions: u32,
    /// The fitted whole-fruit solid; `None` when no fit was made.
    pub solid: Option<FruitSolid>,
    /// The mean colour of the detector's fruit points that fell in the fruit's voxels on this
    /// visit; `None` when none carried a colour (an older detector, or not seen yet).
    #[serde(default)]
    pub colour: Option<Rgb>,
}

impl FruitEstimate {
    /// A fruit known only by its box: volume from the box, nothing seen, no solid.
    pub fn from_box(id: u32, centre: Point3<f64>, min: Point3<f64>, max: Point3<f64>) -> Self {
        Self {
            id,
            centre,
            min,
            max,
            volume_m3: Aabb::new(min, max).volume_m3(),
            voxel_count: 0,
            confidence: 0.0,
            view_directions: 0,
            solid: None,
            colour: None,
        }
    }

    /// The box over the cluster's voxels.
    pub fn aabb(&self) -> Aabb {
        Aabb::new(self.min, self.max)
    }

    /// The fitted solid, or without one the ellipsoid inscribed in the box ([`SolidKind::Box`],
    /// nothing observed).
    pub fn solid_or_box(&self) -> FruitSolid {
        if let Some(solid) = self.solid {
            return solid;
        }
        let semi = (self.max - self.min).map(|v| v.max(0.0)) / 2.0;
        let abc = semi.x * semi.y * semi.z;
        FruitSolid {
            kind: SolidKind::Box,
            centre: nalgebra::center(&self.min, &self.max),
            semi_axes_m: semi,
            world_from_body: UnitQuaternion::identity(),
            exponents: [1.0, 1.0],
            taper: 0.0,
            volume_m3: 4.0 / 3.0 * std::f64::consts::PI * abc,
            box_min: self.min,
            box_max: self.max,
            box_volume_m3: 8.0 * abc,
            confidence: 0.0,
            rms_residual_m: 0.0,
        }
    }
}

/// A fruit's fitted solid on one visit with the surface it was fitted to (its cluster's voxel
/// centres, world frame): what the next visit's growth is measured against.
#[derive(Clone, Debug, PartialEq)]
pub struct FruitSurface {
    pub solid: FruitSolid,
    pub points_m: Vec<Point3<f64>>,
}

/// The volume change from a visit of volume `a_m3` to one of `b_m3` whose volumes' ratio was
/// measured as `ratio` (on one shape, `glasshouse_nbv::growth::volume_ratio`): both fitted
/// volumes brought to one base, `V_a' = √(V_a · V_b / r)`, and the change `V_a'·(r − 1)`.
pub fn volume_change_m3(a_m3: f64, b_m3: f64, ratio: f64) -> f64 {
    (a_m3 * b_m3 / ratio).sqrt() * (ratio - 1.0)
}

/// Boxes spanning more voxels than this along an axis cover none: no fruit is metres long, and
/// a damaged or hostile box must not cost an unbounded loop.
pub const MAX_BOX_VOXELS_PER_AXIS: i64 = 300;

/// Voxel keys `k = floor(p / resolution_m)` whose centres `(k + 0.5)·resolution_m` lie inside
/// the box (bounds included). Empty for a non-positive or non-finite resolution, a non-finite or
/// inverted box, or one longer than [`MAX_BOX_VOXELS_PER_AXIS`] voxels along an axis.
pub fn box_voxel_keys(b: &Aabb, resolution_m: f64) -> Vec<[i32; 3]> {
    if !(resolution_m.is_finite() && resolution_m > 0.0) {
        return Vec::new();
    }
    let range = |i: usize| {
        let lo = (b.min[i] / resolution_m - 0.5).ceil();
        let hi = (b.max[i] / resolution_m - 0.5).floor();
        let fits = |v: f64| v.is_finite() && v.abs() < f64::from(i32::MAX);
        if !(fits(lo) && fits(hi)) || hi - lo + 1.0 > MAX_BOX_VOXELS_PER_AXIS as f64 {
            return None;
        }
        Some(lo as i32..=hi as i32)
    };
    let (Some(xs), Some(ys), Some(zs)) = (range(0), range(1), range(2)) else {
        return Vec::new();
    };
    let mut keys = Vec::new();
    for x in xs {
        for y in ys.clone() {
            for z in zs.clone() {
                keys.push([x, y, z]);
            }
        }
    }
    keys
}

/// Covered ROI volume: `|voxels of the estimated boxes ∩ voxels of the true boxes| / |voxels of
/// the true boxes|`, both sides unions over all their boxes, a box's voxels by
/// [`box_voxel_keys`]; NaN when the true boxes hold no voxel.
pub fn covered_volume(
    estimated: impl IntoIterator<Item = Aabb>,
    truth: impl IntoIterator<Item = Aabb>,
    resolution_m: f64,
) -> f64 {
    let truth: HashSet<[i32; 3]> = truth
        .into_iter()
        .flat_map(|b| box_voxel_keys(&b, resolution_m))
        .collect();
    if truth.is_empty() {
        return f64::NAN;
    }
    let estimated: HashSet<[i32; 3]> = estimated
        .into_iter()
        .flat_map(|b| box_voxel_keys(&b, resolution_m))
        .collect();
    let covered = estimated.iter().filter(|k| truth.contains(*k)).count();
    covered as f64 / truth.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cube(centre: [f64; 3], half: f64) -> Aabb {
        let c = Point3::from(centre);
        Aabb::new(c - Vector3::repeat(half), c + Vector3::repeat(half))
    }

    #[test]
    fn box_voxels_are_those_whose_centres_lie_inside() {
        let keys = box_voxel_keys(&cube([0.1, 0.2, 0.3], 0.02), 0.01);
        assert_eq!(keys.len(), 4 * 4 * 4);
        assert!(keys.contains(&[8, 18, 28]) && keys.contains(&[11, 21, 31]));
        let p = Point3::new;
        let nan = Aabb::new(p(0.0, 0.0, 0.0), p(f64::NAN, 1.0, 1.0));
        assert!(box_voxel_keys(&nan, 0.01).is_empty());
        assert!(box_voxel_keys(&cube([0.0; 3], 0.1), 0.0).is_empty());
        let inverted = Aabb::new(p(0.1, 0.0, 0.0), p(0.0, 1.0, 1.0));
        assert!(box_voxel_keys(&inverted, 0.01).is_empty());
        assert!(box_voxel_keys(&cube([0.0; 3], 2.0), 0.01).is_empty());
    }

    #[test]
    fn covered_volume_counts_the_union_intersection() {
        let p = Point3::new;
        let truth = [cube([0.02, 0.02, 0.02], 0.02)];
        let half = Aabb::new(p(0.0, 0.0, 0.0), p(0.02, 0.04, 0.04));
        let inner = Aabb::new(p(0.0, 0.0, 0.0), p(0.02, 0.02, 0.04));
        let far = cube([1.0, 1.0, 1.0], 0.02);
        let c = covered_volume([half, inner, far], truth, 0.01);
        assert!((c - 0.5).abs() < 1e-12, "{c}");
        assert_eq!(covered_volume([], truth, 0.01), 0.0);
        assert!(covered_volume([half], [], 0.01).is_nan());
        assert_eq!(covered_volume([cube([0.02; 3], 0.1)], truth, 0.01), 1.0);
    }
}
