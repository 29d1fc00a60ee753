//! A fruit the colour labels only touch: the body under a patch ([`find_body`]).
//!
//! A fruit in a leaf's colour and in shade is labelled only where its outline or its sunlit cap
//! gives it away, so its ROI cluster is a patch of a few voxels: too small, flat, or a solid that
//! hides nothing once fitted to so little. The occupancy map holds more of it than the labels:
//! every view that hit the fruit put occupied voxels on its skin, labelled or not, and no ray ever
//! passed through it, so its inside stays unknown. A leaf patch has no such body behind it: the
//! air on both sides of a leaf is seen.
//!
//! So for a cluster the shape rule turned away, a sphere is searched among the occupied voxels
//! around it (RANSAC: spheres through four of them, each scored by the occupied voxels on its
//! surface less [`BodyConfig::free_weight`] for every free voxel inside it; the random draws
//! seeded from the cluster's first voxel, so every copy of a map finds the same body). The best
//! one is a fruit's body when it hides at least [`BodyConfig::min_unknown_inside`] unknown
//! voxels deeper than half a voxel. On tuning seeds 101-108 of the realistic world with
//! leaf-green fruit and the learned detector (docs/results.md, "The body under a patch"), 32 of
//! the 45 turned-away clusters within 6 cm of a missed fruit had such a body, and 5 of the 431
//! farther than 8 cm from any fruit.

use glasshouse_roimap::{Occupancy, RoiCluster, RoiMap, VoxelKey};
use nalgebra::{Matrix4, Point3, Vector4};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// How the body under a turned-away cluster is searched for (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BodyConfig {
    /// Off: a cluster the shape rule turns away stays turned away.
    pub enabled: bool,
    /// The neighbourhood read: this many voxels each way from the cluster's centre.
    pub reach_voxels: u32,
    /// Spheres are drawn through occupied voxels this near the cluster's centre, metres.
    pub sample_m: f64,
    /// A body's radius, metres: a young capsicum to a grown one.
    pub min_radius_m: f64,
    pub max_radius_m: f64,
    /// An occupied voxel this near the sphere is on its surface, metres.
    pub surface_m: f64,
    /// Spheres tried per cluster.
    pub hypotheses: u32,
    /// What a free voxel inside a sphere costs it, in surface voxels: rays pass through leaves'
    /// gaps, never through a fruit.
    pub free_weight: f64,
    /// Fewer unknown voxels than this inside the best sphere: no body.
    pub min_unknown_inside: u32,
}

impl Default for BodyConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            reach_voxels: 8,
            sample_m: 0.06,
            min_radius_m: 0.015,
            max_radius_m: 0.06,
            surface_m: 0.006,
            hypotheses: 400,
            free_weight: 2.0,
            min_unknown_inside: 16,
        }
    }
}

impl BodyConfig {
    /// Checks that every value is finite and in range.
    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("sample_m", self.sample_m),
            ("min_radius_m", self.min_radius_m),
            ("surface_m", self.surface_m),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("body.{name} must be finite and > 0, got {v}"));
            }
        }
        if !(self.max_radius_m.is_finite() && self.max_radius_m >= self.min_radius_m) {
            return Err(format!(
                "body.max_radius_m must be finite and >= min_radius_m ({}), got {}",
                self.min_radius_m, self.max_radius_m
            ));
        }
        if !(self.free_weight.is_finite() && self.free_weight >= 0.0) {
            return Err(format!(
                "body.free_weight must be finite and >= 0, got {}",
                self.free_weight
            ));
        }
        if !(1..=32).contains(&self.reach_voxels) || !(1..=10_000).contains(&self.hypotheses) {
            return Err(format!(
                "body.reach_voxels must be 1..=32 and body.hypotheses 1..=10000, got {} and {}",
                self.reach_voxels, self.hypotheses
            ));
        }
        Ok(())
    }
}

/// A fruit's body found under a cluster.
#[derive(Clone, Debug, PartialEq)]
pub struct Body {
    pub centre: Point3<f64>,
    pub radius_m: f64,
    /// The occupied voxels on its surface, sorted.
    pub surface: Vec<VoxelKey>,
    pub unknown_inside: u32,
    pub free_inside: u32,
}

/// The map around a cluster, by observed occupancy (a revisit's hints are unknown).
struct Neighbourhood {
    occupied: Vec<(VoxelKey, Point3<f64>)>,
    free: Vec<Point3<f64>>,
    unknown: Vec<Point3<f64>>,
}

impl Neighbourhood {
    fn read(map: &RoiMap, around: VoxelKey, reach: i32) -> Self {
        let mut hood = Self {
            occupied: Vec::new(),
            free: Vec::new(),
            unknown: Vec::new(),
        };
        for x in around.x - reach..=around.x + reach {
            for y in around.y - reach..=around.y + reach {
                for z in around.z - reach..=around.z + reach {
                    let key = VoxelKey::new(x, y, z);
                    let centre = map.centre_of(key);
                    match map.observed_occupancy(key) {
                        Occupancy::Occupied => hood.occupied.push((key, centre)),
                        Occupancy::Free => hood.free.push(centre),
                        Occupancy::Unknown => hood.unknown.push(centre),
                    }
                }
            }
        }
        hood
    }
}

/// The sphere through four points; `None` when they lie on a plane.
fn sphere_through(p: [Point3<f64>; 4]) -> Option<(Point3<f64>, f64)> {
    // |x|² = 2 c·x + (r² − |c|²), linear in c and d = r² − |c|².
    let a = Matrix4::from_fn(|i, j| if j < 3 { 2.0 * p[i][j] } else { 1.0 });
    let b = Vector4::from_fn(|i, _| p[i].coords.norm_squared());
    let x = a.lu().solve(&b)?;
    let centre = Point3::new(x[0], x[1], x[2]);
    let r2 = x[3] + centre.coords.norm_squared();
    (r2.is_finite() && r2 > 0.0).then(|| (centre, r2.sqrt()))
}

fn within(points: &[Point3<f64>], centre: &Point3<f64>, radius_m: f64) -> u32 {
    let r2 = radius_m * radius_m;
    points
        .iter()
        .filter(|q| (*q - centre).norm_squared() < r2)
        .count() as u32
}

fn seed_of(key: VoxelKey) -> u64 {
    let part = |v: i32| u64::from(v as u32);
    part(key.x) ^ part(key.y).rotate_left(21) ^ part(key.z).rotate_left(42)
}

/// The body under `cluster` (module docs), if the map shows one.
pub fn find_body(map: &RoiMap, cluster: &RoiCluster, config: &BodyConfig) -> Option<Body> {
    let first = *cluster.voxels.first()?;
    let reach = i32::try_from(config.reach_voxels).ok()?;
    let hood = Neighbourhood::read(map, map.try_key_of(&cluster.centre)?, reach);
    let near: Vec<Point3<f64>> = hood
        .occupied
        .iter()
        .map(|(_, p)| *p)
        .filter(|p| (p - cluster.centre).norm() < config.sample_m)
        .collect();
    if near.len() < 8 {
        return None;
    }
    let half_voxel = 0.5 * map.config().resolution_m;
    let on_surface = |centre: &Point3<f64>, r: f64, q: &Point3<f64>| {
        ((q - centre).norm() - r).abs() < config.surface_m
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed_of(first));
    let mut best: Option<(f64, Point3<f64>, f64)> = None;
    for _ in 0..config.hypotheses {
        let pick = rand::seq::index::sample(&mut rng, near.len(), 4);
        let Some((centre, r)) = sphere_through([0, 1, 2, 3].map(|i| near[pick.index(i)])) else {
            continue;
        };
        let in_range = (config.min_radius_m..=config.max_radius_m).contains(&r);
        if !in_range || (centre - cluster.centre).norm() > r + 2.0 * half_voxel {
            continue;
        }
        let surface = hood
            .occupied
            .iter()
            .filter(|(_, q)| on_surface(&centre, r, q))
            .count();
        // The free voxels only lower a score: a sphere whose surface alone cannot beat the best
        // is not counted further (the same best, found sooner).
        if best.is_some_and(|(s, _, _)| surface as f64 <= s) {
            continue;
        }
        let free = within(&hood.free, &centre, r - half_voxel);
        let score = surface as f64 - config.free_weight * f64::from(free);
        if best.is_none_or(|(s, _, _)| score > s) {
            best = Some((score, centre, r));
        }
    }
    let (_, centre, radius_m) = best?;
    let unknown_inside = within(&hood.unknown, &centre, radius_m - half_voxel);
    if unknown_inside < config.min_unknown_inside {
        return None;
    }
    let surface = hood
        .occupied
        .iter()
        .filter(|(_, q)| on_surface(&centre, radius_m, q))
        .map(|(k, _)| *k)
        .collect();
    Some(Body {
        centre,
        radius_m,
        surface,
        unknown_inside,
        free_inside: within(&hood.free, &centre, radius_m - half_voxel),
    })
}

#[cfg(test)]
mod tests;
