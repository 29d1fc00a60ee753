//! Next-best-view planning over the ROI map and fruit estimates from ROI clusters.
//!
//! One planning call ([`plan_views`]) follows the paper's Algorithm 1 with the original code's
//! defects fixed:
//!
//! - **ROI-targeted sampling**: targets are the map's ROI frontier (free voxels next to fruit with
//!   unknown space beside them; with the map's `roi_target_needs_neighbour`, lone ROI voxels
//!   are left out); the camera sits on a random sphere of radius U(0.3, 0.5) m around a
//!   target, looking at it, inside the camera workspace and with no occupied voxel
//!   (log-odds > ln(0.6/0.4)) on the segment target→camera.
//! - **Exploration sampling**: frontier voxels (free, with an unknown and an occupied face
//!   neighbour); the camera sits along the local surface normal (minus the sum of the occupied
//!   18-neighbour offsets) looking back at the surface.
//! - **Gain**: a `fan_width × fan_height` grid of rays spread over the field of view around the
//!   camera's *optical* axis (camera `z`), each walked up to `gain_ray_range_m` or the first occupied
//!   voxel. U_U is the mean share of unknown voxels per ray; U_P weighs unknown voxels 0.5, more when
//!   close to a known ROI voxel. Empty rays contribute 0.
//! - **Utility** = gain − `cost_weight_per_m` · (distance from the current camera).
//! - **Selection**: Ours methods use the ROI list when its best utility exceeds the threshold,
//!   otherwise the exploration list; Explo methods always explore. The result is ranked best first
//!   and never empty when the workspace is a valid box: if nothing beats the threshold the best views
//!   are returned anyway, and with no candidates at all random fallback views are scored.
//! - **Ranking by time** (not the paper's): with a [`PlanningContext::motion_time`] and
//!   `cost_weight_per_s` > 0, the chosen list is ranked by the utility less that weight per
//!   second the robot takes to reach each view (`ScoredView::rank_utility`); which list is
//!   chosen still follows the utility. With no motion time, or a weight of 0, the paper's plan.
//! - **Reach**: with a predicate in [`PlanningContext::reach`] (the robot's reachability, e.g.
//!   `glasshouse_arm::ViewReachability`), every sampler (ROI, exploration, fallback) drops the
//!   poses it rejects before scoring, so an unreachable view is never ranked. A rejected pose is
//!   a spent try, as an occluded one is: the number of tries and the random draws stay those of
//!   the paper, and the predicate is asked only after a try's draws, so the same seed gives the
//!   same plan, and `reach: None` the plans of the planner without it. When the predicate
//!   rejects every fallback try too, the plan is empty: the robot has no view it can reach.
//!
//! Free/unknown follows the map's single rule (see `glasshouse_roimap`): never updated is unknown,
//! occupancy log-odds > 0 is occupied, anything else free.
//!
//! [`FruitTracker`] turns ROI clusters into fruit estimates with ids that stay stable across
//! updates, and counts the directions each fruit was seen from; [`evidence`] says which clusters
//! are fruit at all. Everything is deterministic for a given seed: randomness comes from `ChaCha8Rng`
//! streams derived from it.

pub mod evidence;
pub mod fit;
pub mod growth;
pub mod season;
pub mod split;
pub mod superellipsoid;
#[cfg(test)]
mod test_bodies;

use std::collections::HashMap;
use std::fmt;
use std::str::FromStr;

use glasshouse_geom::{look_along, look_at, Aabb};
use glasshouse_roimap::{KeyBuildHasher, Neighbourhood, Occupancy, RoiCluster, RoiMap, VoxelKey};
use nalgebra::{Isometry3, Point3, Vector3};
use rand::distributions::{Distribution, WeightedIndex};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Which sampler produced a view.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ViewKind {
    Roi,
    Exploration,
}

/// Information gain of a view.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum GainKind {
    /// U_U: share of unobserved voxels along the rays.
    UnobservedVoxels,
    /// U_P: unobserved voxels weighted up near known ROI voxels.
    Proximity,
}

/// The paper's four planners.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    OursUu,
    OursUp,
    ExploUu,
    ExploUp,
}

impl Method {
    pub const ALL: [Method; 4] = [
        Method::OursUu,
        Method::OursUp,
        Method::ExploUu,
        Method::ExploUp,
    ];

    pub fn gain(&self) -> GainKind {
        match self {
            Method::OursUu | Method::ExploUu => GainKind::UnobservedVoxels,
            Method::OursUp | Method::ExploUp => GainKind::Proximity,
        }
    }

    /// True for the paper's "Ours" methods, which sample around ROI targets first.
    pub fn uses_roi_sampling(&self) -> bool {
        matches!(self, Method::OursUu | Method::OursUp)
    }

    pub fn name(&self) -> &'static str {
        match self {
            Method::OursUu => "ours-uu",
            Method::OursUp => "ours-up",
            Method::ExploUu => "explo-uu",
            Method::ExploUp => "explo-up",
        }
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Method {
    type Err = PlanError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Method::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| PlanError::UnknownMethod(s.to_string()))
    }
}

/// Errors of planning. Bad input never panics.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum PlanError {
    #[error("invalid planner configuration: {0}")]
    InvalidConfig(String),
    #[error("unknown method {0:?}; valid methods: ours-uu, ours-up, explo-uu, explo-up")]
    UnknownMethod(String),
    #[error("invalid {name}: bounds must be finite with min <= max")]
    InvalidRegion { name: &'static str },
    #[error("current camera pose is not finite")]
    NonFinitePose,
}

/// Planner parameters. [`Default`] gives the paper's values.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PlannerConfig {
    pub method: Method,
    /// ROI-targeted candidates wanted: the paper's tries of ROI-targeted sampling.
    pub roi_samples: usize,
    /// Tries of ROI-targeted sampling drawn until `roi_samples` candidates survive the
    /// workspace, occlusion and reach checks; 0: `roi_samples` tries, as the paper. With noisy
    /// depth and an arm's reach most tries are dropped (of the paper's 100, 0-19 survived on
    /// the realistic world's tuning seeds), and the exploration list wins by default.
    pub roi_tries: usize,
    /// Frontier voxels drawn for exploration sampling (at most).
    pub exploration_samples: usize,
    /// Camera distance from its target, lower bound.
    pub min_view_distance_m: f64,
    /// Camera distance from its target, upper bound.
    pub max_view_distance_m: f64,
    /// Gain rays across the image.
    pub fan_width: usize,
    /// Gain rays down the image.
    pub fan_height: usize,
    pub horizontal_fov_rad: f64,
    pub vertical_fov_rad: f64,
    /// Length of each gain ray.
    pub gain_ray_range_m: f64,
    /// Utility lost per metre of camera travel (α).
    pub cost_weight_per_m: f64,
    /// Utility lost per second the robot takes to reach the view, when the context knows it
    /// ([`PlanningContext::motion_time`]; 0: the paper's distance cost alone).
    pub cost_weight_per_s: f64,
    /// ROI views are used when the best beats this; views at or below it are not ranked unless
    /// nothing else is left.
    pub utility_threshold: f64,
    /// Distance up to which U_P raises the weight of unknown voxels near ROI.
    pub proximity_max_dist_m: f64,
    /// Voxels above this occupancy log-odds occlude ROI targets.
    pub occlusion_occupancy_logodds: f32,
    /// Length of the ranked list.
    pub max_ranked_views: usize,
    /// Threads that score candidates; 0 means one per core. Any value gives the same plan.
    pub scoring_threads: usize,
    /// ROI targets drawn nearer the camera more often: target `t` with weight
    /// `exp(−|t − camera| / roi_target_near_m)`, metres; 0 draws them uniformly, as the paper.
    pub roi_target_near_m: f64,
}

impl Default for PlannerConfig {
    fn default() -> Self {
        Self {
            method: Method::OursUu,
            roi_samples: 100,
            roi_tries: 0,
            exploration_samples: 100,
            min_view_distance_m: 0.3,
            max_view_distance_m: 0.5,
            fan_width: 8,
            fan_height: 6,
            horizontal_fov_rad: 80f64.to_radians(),
            // 4:3 image with an 80° horizontal field of view.
            vertical_fov_rad: 2.0 * (40f64.to_radians().tan() * 0.75).atan(),
            gain_ray_range_m: 1.0,
            cost_weight_per_m: 0.2,
            cost_weight_per_s: 0.0,
            utility_threshold: 0.2,
            proximity_max_dist_m: 0.3,
            occlusion_occupancy_logodds: (0.6f32 / 0.4).ln(),
            max_ranked_views: 20,
            scoring_threads: 0,
            roi_target_near_m: 0.0,
        }
    }
}

impl PlannerConfig {
    pub fn validate(&self) -> Result<(), PlanError> {
        let bad = |msg: &str| Err(PlanError::InvalidConfig(msg.to_string()));
        let pos = |v: f64| v.is_finite() && v > 0.0;
        if !(pos(self.min_view_distance_m)
            && pos(self.max_view_distance_m)
            && self.min_view_distance_m <= self.max_view_distance_m)
        {
            return bad("view distances must be finite, > 0 and min <= max");
        }
        if self.fan_width == 0 || self.fan_height == 0 {
            return bad("fan_width and fan_height must be >= 1");
        }
        if self.fan_width.saturating_mul(self.fan_height) > 100_000 {
            return bad("fan has too many rays (> 100000)");
        }
        let fov_ok = |v: f64| pos(v) && v < std::f64::consts::PI;
        if !(fov_ok(self.horizontal_fov_rad) && fov_ok(self.vertical_fov_rad)) {
            return bad("fields of view must be in (0, pi) radians");
        }
        if !(pos(self.gain_ray_range_m) && self.gain_ray_range_m <= 100.0) {
            return bad("gain_ray_range_m must be in (0, 100] m");
        }
        if !(self.cost_weight_per_m.is_finite() && self.cost_weight_per_m >= 0.0) {
            return bad("cost_weight_per_m must be finite and >= 0");
        }
        if !(self.roi_target_near_m.is_finite() && self.roi_target_near_m >= 0.0) {
            return bad("roi_target_near_m must be finite and >= 0");
        }
        if !(self.cost_weight_per_s.is_finite() && self.cost_weight_per_s >= 0.0) {
            return bad("cost_weight_per_s must be finite and >= 0");
        }
        if self.roi_tries > MAX_ROI_TRIES {
            return Err(PlanError::InvalidConfig(format!(
                "roi_tries must be <= {MAX_ROI_TRIES}, got {}",
                self.roi_tries
            )));
        }
        if !self.utility_threshold.is_finite() {
            return bad("utility_threshold must be finite");
        }
        if !pos(self.proximity_max_dist_m) {
            return bad("proximity_max_dist_m must be finite and > 0");
        }
        if !self.occlusion_occupancy_logodds.is_finite() {
            return bad("occlusion_occupancy_logodds must be finite");
        }
        if self.max_ranked_views == 0 {
            return bad("max_ranked_views must be >= 1");
        }
        if self.scoring_threads > 256 {
            return bad("scoring_threads must be <= 256 (0 = one per core)");
        }
        Ok(())
    }
}

/// Can the robot bring its camera to a `world_from_camera` pose? Called once per candidate pose
/// that passed the samplers' own checks, so it should be cheap (microseconds).
pub type ReachPredicate<'a> = dyn Fn(&Isometry3<f64>) -> bool + Sync + 'a;

/// How many seconds the robot takes from where it is to a `world_from_camera` pose (`None`:
/// unknown, e.g. no placement found). Called once per scored candidate.
pub type MotionTime<'a> = dyn Fn(&Isometry3<f64>) -> Option<f64> + Sync + 'a;

/// Everything a planning call looks at.
#[derive(Clone, Copy)]
pub struct PlanningContext<'a> {
    pub map: &'a RoiMap,
    /// The current camera pose.
    pub world_from_camera: Isometry3<f64>,
    /// Where the camera may be placed.
    pub camera_workspace: Aabb,
    /// Where targets and frontiers may lie.
    pub sampling_region: Aabb,
    /// Which poses the robot can reach; candidates it rejects are dropped before scoring and
    /// never ranked. `None`: every pose in the camera workspace counts as reachable.
    pub reach: Option<&'a ReachPredicate<'a>>,
    /// The robot's motion time to a pose, charged at [`PlannerConfig::cost_weight_per_s`]
    /// (`None`: only the distance is charged).
    pub motion_time: Option<&'a MotionTime<'a>>,
    /// Where the previous visit's fruit were (a revisit's prior hints,
    /// [`RoiMap::unobserved_hints`]): ROI-targeted sampling aims at those no scan of this visit
    /// has touched yet as at the ROI frontier. Empty on a first visit.
    pub remembered_fruit: &'a [VoxelKey],
    /// The voxels, sorted, of settled ROI clusters: judged not fruit by their shape after being
    /// seen from several directions (a red leaf, a clip, a label, a stem), or found fruit seen
    /// from enough directions (their backs, pressed against a leaf, are never seen). An ROI
    /// target whose every ROI face neighbour is one of them is no target (a cluster touching
    /// a settled one keeps the targets beside its own voxels). They stay ROI; only the views
    /// they drew are saved.
    pub settled_voxels: &'a [VoxelKey],
    /// The ROI views have stopped finding fruit (the pipeline's count of clouds without a new
    /// fruit-shaped cluster): the exploration list is used whenever one of its views beats the
    /// threshold, so the search moves to parts of the scene no ROI target points at. `false`:
    /// the paper's choice.
    pub roi_stalled: bool,
}

impl fmt::Debug for PlanningContext<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("PlanningContext")
            .field("map", &self.map)
            .field("world_from_camera", &self.world_from_camera)
            .field("camera_workspace", &self.camera_workspace)
            .field("sampling_region", &self.sampling_region)
            .field("reach", &self.reach.map(|_| "predicate"))
            .field("motion_time", &self.motion_time.map(|_| "function"))
            .field("remembered_fruit", &self.remembered_fruit.len())
            .field("settled_voxels", &self.settled_voxels.len())
            .field("roi_stalled", &self.roi_stalled)
            .finish()
    }
}

impl PlanningContext<'_> {
    /// True when no reach predicate is set or it accepts the pose.
    fn reachable(&self, world_from_camera: &Isometry3<f64>) -> bool {
        self.reach.is_none_or(|reach| reach(world_from_camera))
    }
}

/// A candidate view with its score.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ScoredView {
    pub world_from_camera: Isometry3<f64>,
    /// gain − cost_weight · cost: the paper's utility, which the threshold is applied to.
    pub utility: f64,
    /// The utility less the motion time's cost ([`PlannerConfig::cost_weight_per_s`]): what
    /// the views of a list are ranked by (the utility when the time is not known).
    #[serde(default)]
    pub rank_utility: f64,
    pub gain: f64,
    /// Straight-line distance from the current camera position.
    pub cost_m: f64,
    /// The robot's motion time to the view, when the planning context knows it.
    #[serde(default)]
    pub motion_s: Option<f64>,
    pub kind: ViewKind,
}

/// Result of [`plan_views`].
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Plan {
    /// Best first.
    pub views: Vec<ScoredView>,
    /// Size of the ROI frontier (0 for Explo methods, which do not compute it).
    pub roi_targets: usize,
    /// Size of the exploration frontier.
    pub exploration_frontier: usize,
    /// Candidates whose gain was computed (ROI, exploration and fallback).
    pub candidates_scored: usize,
    /// Which list the views came from (fallback views count as exploration).
    pub used_kind: ViewKind,
}

/// Edge of the cells of the ROI distance grid used by U_P (as in the original code).
const ROI_DISTANCE_CELL_M: f64 = 0.05;

/// Distance from 5 cm cells to the nearest known ROI voxel, stored only for cells closer than
/// `max_dist`. ROI voxels are first reduced to one centroid per 5 cm cell, which keeps building
/// cheap at the price of a few centimetres of error (as coarse as the original's grid).
struct RoiDistanceField {
    max_dist_m: f64,
    distance_m: HashMap<VoxelKey, f32, KeyBuildHasher>,
}

fn cell_of(p: &Point3<f64>) -> VoxelKey {
    let c = |v: f64| (v / ROI_DISTANCE_CELL_M).floor() as i32;
    VoxelKey::new(c(p.x), c(p.y), c(p.z))
}

impl RoiDistanceField {
    fn new(map: &RoiMap, max_dist_m: f64) -> Self {
        let mut sums: HashMap<VoxelKey, (Vector3<f64>, u32), KeyBuildHasher> = HashMap::default();
        for key in map.roi_keys() {
            let centre = map.centre_of(key);
            let e = sums
                .entry(cell_of(&centre))
                .or_insert((Vector3::zeros(), 0));
            e.0 += centre.coords;
            e.1 += 1;
        }
        let mut reps: Vec<(VoxelKey, Point3<f64>)> = sums
            .into_iter()
            .map(|(cell, (sum, n))| (cell, Point3::from(sum / f64::from(n))))
            .collect();
        reps.sort_by_key(|(cell, _)| *cell);
        let reach = (max_dist_m / ROI_DISTANCE_CELL_M).ceil() as i32 + 1;
        let mut distance_m: HashMap<VoxelKey, f32, KeyBuildHasher> = HashMap::default();
        for (cell, rep) in &reps {
            for dx in -reach..=reach {
                for dy in -reach..=reach {
                    for dz in -reach..=reach {
                        let c = cell.offset(dx, dy, dz);
                        let centre = Point3::new(
                            (f64::from(c.x) + 0.5) * ROI_DISTANCE_CELL_M,
                            (f64::from(c.y) + 0.5) * ROI_DISTANCE_CELL_M,
                            (f64::from(c.z) + 0.5) * ROI_DISTANCE_CELL_M,
                        );
                        let d = (centre - rep).norm();
                        if d < max_dist_m {
                            let slot = distance_m.entry(c).or_insert(f32::INFINITY);
                            *slot = slot.min(d as f32);
                        }
                    }
                }
            }
        }
        Self {
            max_dist_m,
            distance_m,
        }
    }

    /// U_P weight of the unknown voxels in a 5 cm cell.
    fn cell_weight(&self, cell: VoxelKey) -> f64 {
        match self.distance_m.get(&cell) {
            Some(&d) if f64::from(d) < self.max_dist_m => {
                0.5 + 0.5 * (self.max_dist_m - f64::from(d)) / self.max_dist_m
            }
            _ => 0.5,
        }
    }
}

/// Computes the gain of views over one map; build once per planning call.
pub struct GainEvaluator<'a> {
    map: &'a RoiMap,
    ray_range_m: f64,
    /// Unit ray directions in the camera (optical) frame.
    fan_in_camera: Vec<Vector3<f64>>,
    /// Present for U_P.
    proximity: Option<RoiDistanceField>,
}

impl<'a> GainEvaluator<'a> {
    /// Gain of the kind `config.method.gain()`; the config should be valid.
    pub fn new(map: &'a RoiMap, config: &PlannerConfig) -> Self {
        let (w, h) = (config.fan_width.max(1), config.fan_height.max(1));
        let mut fan_in_camera = Vec::with_capacity(w * h);
        for row in 0..h {
            let v_angle = config.vertical_fov_rad * ((row as f64 + 0.5) / h as f64 - 0.5);
            for col in 0..w {
                let h_angle = config.horizontal_fov_rad * ((col as f64 + 0.5) / w as f64 - 0.5);
                // Pinhole grid: x right, y down, z forward (optical axis).
                fan_in_camera.push(Vector3::new(h_angle.tan(), v_angle.tan(), 1.0).normalize());
            }
        }
        let proximity = match config.method.gain() {
            GainKind::Proximity => Some(RoiDistanceField::new(map, config.proximity_max_dist_m)),
            GainKind::UnobservedVoxels => None,
        };
        Self {
            map,
            ray_range_m: config.gain_ray_range_m,
            fan_in_camera,
            proximity,
        }
    }

    /// Mean over the fan of the per-ray weighted share of unknown voxels, in [0, 1].
    pub fn gain(&self, world_from_camera: &Isometry3<f64>) -> f64 {
        if self.fan_in_camera.is_empty() {
            return 0.0;
        }
        if self.proximity.is_some() {
            return self.gain_ray_by_ray(world_from_camera);
        }
        // U_U weighs every unknown voxel 1: the map's batch walk counts them for the whole fan
        // (the same voxels as `walk_ray`, so the same sum in the same order).
        let camera_in_world = Point3::from(world_from_camera.translation.vector);
        let directions: Vec<Vector3<f64>> = self
            .fan_in_camera
            .iter()
            .map(|d| world_from_camera.rotation * d)
            .collect();
        let counts =
            self.map
                .count_unknown_until_occupied(&camera_in_world, &directions, self.ray_range_m);
        let total = counts
            .iter()
            .filter(|c| c.visited > 0)
            .fold(0.0, |total, c| {
                total + f64::from(c.unknown) / f64::from(c.visited)
            });
        total / self.fan_in_camera.len() as f64
    }

    /// [`GainEvaluator::gain`] walking the fan ray by ray (any gain kind).
    pub fn gain_ray_by_ray(&self, world_from_camera: &Isometry3<f64>) -> f64 {
        if self.fan_in_camera.is_empty() {
            return 0.0;
        }
        let camera_in_world = Point3::from(world_from_camera.translation.vector);
        let mut total = 0.0;
        for dir_in_camera in &self.fan_in_camera {
            let dir_in_world = world_from_camera.rotation * dir_in_camera;
            let mut visited = 0usize;
            let mut weight_sum = 0.0;
            // A ray crosses about five voxels per 5 cm cell: look each cell up once.
            let mut last_cell: Option<(VoxelKey, f64)> = None;
            self.map.walk_ray(
                &camera_in_world,
                &dir_in_world,
                self.ray_range_m,
                |key, voxel| {
                    visited += 1;
                    match voxel {
                        None => {
                            weight_sum += match &self.proximity {
                                None => 1.0,
                                Some(field) => {
                                    let cell = cell_of(&self.map.centre_of(key));
                                    match last_cell {
                                        Some((c, w)) if c == cell => w,
                                        _ => {
                                            let w = field.cell_weight(cell);
                                            last_cell = Some((cell, w));
                                            w
                                        }
                                    }
                                }
                            };
                            true
                        }
                        // The occupied voxel that stops the ray still counts in N.
                        Some(v) => v.occupancy() != Occupancy::Occupied,
                    }
                },
            );
            if visited > 0 {
                total += weight_sum / visited as f64;
            }
        }
        total / self.fan_in_camera.len() as f64
    }
}

fn region_ok(b: &Aabb) -> bool {
    (0..3).all(|i| b.min[i].is_finite() && b.max[i].is_finite() && b.min[i] <= b.max[i])
}

fn uniform_in(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    if lo < hi {
        rng.gen_range(lo..=hi)
    } else {
        lo
    }
}

fn uniform_unit_vector(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    let z: f64 = rng.gen_range(-1.0..=1.0);
    let phi: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
    let r = (1.0 - z * z).max(0.0).sqrt();
    Vector3::new(r * phi.cos(), r * phi.sin(), z)
}

fn point_in(rng: &mut ChaCha8Rng, b: &Aabb) -> Point3<f64> {
    Point3::new(
        uniform_in(rng, b.min.x, b.max.x),
        uniform_in(rng, b.min.y, b.max.y),
        uniform_in(rng, b.min.z, b.max.z),
    )
}

/// Independent random streams per sampler, so one sampler's draws never shift another's.
fn rng_stream(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// ROI-targeted candidate poses.
fn sample_roi_views(
    ctx: &PlanningContext,
    config: &PlannerConfig,
    targets: &[VoxelKey],
    rng: &mut ChaCha8Rng,
) -> Vec<Isometry3<f64>> {
    let mut poses = Vec::new();
    if targets.is_empty() {
        return poses;
    }
    let near = near_camera_weights(ctx, config, targets);
    let tries = match config.roi_tries {
        0 => config.roi_samples,
        n => n,
    };
    // Draws stop once enough candidates survived; with the paper's tries (as many as the
    // samples) every try is drawn.
    for _ in 0..tries {
        if poses.len() >= config.roi_samples {
            break;
        }
        let pick = match &near {
            Some(weights) => weights.sample(rng),
            None => rng.gen_range(0..targets.len()),
        };
        let target_in_world = ctx.map.centre_of(targets[pick]);
        let direction = uniform_unit_vector(rng);
        let radius_m = uniform_in(rng, config.min_view_distance_m, config.max_view_distance_m);
        let camera_in_world = target_in_world + direction * radius_m;
        if !ctx.camera_workspace.contains(&camera_in_world) {
            continue;
        }
        let mut occluded = false;
        ctx.map
            .walk_ray(&target_in_world, &direction, radius_m, |_, voxel| {
                occluded =
                    voxel.is_some_and(|v| v.occupancy_logodds > config.occlusion_occupancy_logodds);
                !occluded
            });
        if occluded {
            continue;
        }
        let pose = look_at(&camera_in_world, &target_in_world);
        // After every draw of the try, so a predicate never shifts the random stream.
        if ctx.reachable(&pose) {
            poses.push(pose);
        }
    }
    poses
}

/// The draw of ROI targets weighted towards the camera ([`PlannerConfig::roi_target_near_m`]);
/// `None` for the paper's uniform draw.
fn near_camera_weights(
    ctx: &PlanningContext,
    config: &PlannerConfig,
    targets: &[VoxelKey],
) -> Option<WeightedIndex<f64>> {
    if config.roi_target_near_m <= 0.0 {
        return None;
    }
    let camera = Point3::from(ctx.world_from_camera.translation.vector);
    let weights = targets.iter().map(|&k| {
        let distance_m = (ctx.map.centre_of(k) - camera).norm();
        // Never 0: a far target stays possible (and the weights never all vanish).
        (-distance_m / config.roi_target_near_m).exp().max(1e-12)
    });
    WeightedIndex::new(weights).ok()
}

/// Exploration candidate poses from the frontier.
fn sample_exploration_views(
    ctx: &PlanningContext,
    config: &PlannerConfig,
    frontier: &[VoxelKey],
    rng: &mut ChaCha8Rng,
) -> Vec<Isometry3<f64>> {
    let amount = config.exploration_samples.min(frontier.len());
    let mut picks = rand::seq::index::sample(rng, frontier.len(), amount).into_vec();
    // Visit in frontier order so the candidate order does not depend on the sampler's internals.
    picks.sort_unstable();
    let mut poses = Vec::new();
    for index in picks {
        let key = frontier[index];
        let mut sum = Vector3::<f64>::zeros();
        for dx in -1i32..=1 {
            for dy in -1i32..=1 {
                for dz in -1i32..=1 {
                    let manhattan = dx.abs() + dy.abs() + dz.abs();
                    if (1..=2).contains(&manhattan)
                        && ctx.map.occupancy(key.offset(dx, dy, dz)) == Occupancy::Occupied
                    {
                        sum += Vector3::new(f64::from(dx), f64::from(dy), f64::from(dz));
                    }
                }
            }
        }
        // Occupied neighbours on opposite sides cancel: no usable normal.
        let Some(normal) = (-sum).try_normalize(1e-9) else {
            continue;
        };
        let radius_m = uniform_in(rng, config.min_view_distance_m, config.max_view_distance_m);
        let camera_in_world = ctx.map.centre_of(key) + normal * radius_m;
        if !ctx.camera_workspace.contains(&camera_in_world)
            || ctx.map.occupancy(ctx.map.key_of(&camera_in_world)) == Occupancy::Occupied
        {
            continue;
        }
        let pose = look_along(&camera_in_world, &(-normal));
        if ctx.reachable(&pose) {
            poses.push(pose);
        }
    }
    poses
}

/// Random views from the workspace towards the sampling region, for when no sampler found any.
fn sample_fallback_views(
    ctx: &PlanningContext,
    config: &PlannerConfig,
    rng: &mut ChaCha8Rng,
) -> Vec<Isometry3<f64>> {
    let wanted = config.exploration_samples.max(1);
    let mut poses = Vec::with_capacity(wanted);
    let mut last = None;
    for _ in 0..wanted * 4 {
        if poses.len() == wanted {
            break;
        }
        let camera_in_world = point_in(rng, &ctx.camera_workspace);
        let target_in_world = point_in(rng, &ctx.sampling_region);
        let pose = look_at(&camera_in_world, &target_in_world);
        // An unreachable pose is never a view, not even the last resort below.
        if !ctx.reachable(&pose) {
            continue;
        }
        if ctx.map.occupancy(ctx.map.key_of(&camera_in_world)) == Occupancy::Occupied {
            last = Some(pose);
            continue;
        }
        poses.push(pose);
    }
    // Even a workspace full of occupied voxels yields a view, so the robot is never left idle
    // (unless the reach predicate rejected every try).
    if poses.is_empty() {
        poses.extend(last);
    }
    poses
}

fn score(
    poses: Vec<Isometry3<f64>>,
    kind: ViewKind,
    evaluator: &GainEvaluator,
    ctx: &PlanningContext,
    config: &PlannerConfig,
) -> Vec<ScoredView> {
    let camera_in_world = Point3::from(ctx.world_from_camera.translation.vector);
    let timed = ctx.motion_time.filter(|_| config.cost_weight_per_s > 0.0);
    let score_one = |pose: &Isometry3<f64>| {
        let gain = evaluator.gain(pose);
        let cost_m = (Point3::from(pose.translation.vector) - camera_in_world).norm();
        let motion_s = timed.and_then(|time| time(pose));
        let utility = gain - config.cost_weight_per_m * cost_m;
        ScoredView {
            world_from_camera: *pose,
            utility,
            rank_utility: utility - motion_s.map_or(0.0, |t| config.cost_weight_per_s * t),
            gain,
            cost_m,
            motion_s,
            kind,
        }
    };
    let threads = match config.scoring_threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    }
    .min(poses.len().div_ceil(MIN_CANDIDATES_PER_THREAD))
    .max(1);
    let mut views: Vec<ScoredView> = if threads == 1 {
        poses.iter().map(score_one).collect()
    } else {
        // Contiguous chunks joined in order: the same list as the serial loop.
        let chunk = poses.len().div_ceil(threads);
        std::thread::scope(|scope| {
            let workers: Vec<_> = poses
                .chunks(chunk)
                .map(|part| scope.spawn(move || part.iter().map(score_one).collect::<Vec<_>>()))
                .collect();
            workers
                .into_iter()
                .flat_map(|w| {
                    w.join()
                        .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
                })
                .collect()
        })
    };
    // Stable sort: equal utilities keep their (seeded) generation order.
    views.sort_by(|a, b| b.rank_utility.total_cmp(&a.rank_utility));
    views
}

/// Most tries of ROI-targeted sampling one plan may draw.
const MAX_ROI_TRIES: usize = 100_000;

/// Below this many candidates per thread, spawning costs more than it saves.
const MIN_CANDIDATES_PER_THREAD: usize = 16;

/// Views above the threshold, or, when there are none, the best views anyway.
fn rank(views: &[ScoredView], config: &PlannerConfig) -> Vec<ScoredView> {
    let above: Vec<ScoredView> = views
        .iter()
        .filter(|v| v.rank_utility > config.utility_threshold)
        .take(config.max_ranked_views)
        .cloned()
        .collect();
    if above.is_empty() {
        views
            .iter()
            .take(config.max_ranked_views)
            .cloned()
            .collect()
    } else {
        above
    }
}

/// The ROI frontier in the sampling region beside more than settled voxels, then the
/// remembered fruit in it that no scan of this visit has touched.
fn roi_targets_of(ctx: &PlanningContext) -> Vec<VoxelKey> {
    let mut targets = ctx.map.roi_frontier(&ctx.sampling_region);
    if !ctx.settled_voxels.is_empty() {
        let settled = |n: &VoxelKey| ctx.settled_voxels.binary_search(n).is_ok();
        targets.retain(|&k| {
            let mut roi_beside = k
                .neighbours(Neighbourhood::Six)
                .filter(|&n| ctx.map.is_roi(n));
            !roi_beside.all(|n| settled(&n))
        });
    }
    targets.extend(ctx.remembered_fruit.iter().copied().filter(|&k| {
        ctx.sampling_region.contains(&ctx.map.centre_of(k)) && ctx.map.is_unobserved_hint(k)
    }));
    targets
}

/// One planning call: sample, score and rank candidate views (see the crate docs).
pub fn plan_views(
    ctx: &PlanningContext,
    config: &PlannerConfig,
    seed: u64,
) -> Result<Plan, PlanError> {
    config.validate()?;
    if !region_ok(&ctx.camera_workspace) {
        return Err(PlanError::InvalidRegion {
            name: "camera workspace",
        });
    }
    if !region_ok(&ctx.sampling_region) {
        return Err(PlanError::InvalidRegion {
            name: "sampling region",
        });
    }
    let pose = &ctx.world_from_camera;
    if !(pose.translation.vector.iter().all(|c| c.is_finite())
        && pose.rotation.coords.iter().all(|c| c.is_finite()))
    {
        return Err(PlanError::NonFinitePose);
    }
    let evaluator = GainEvaluator::new(ctx.map, config);

    let (roi_targets, roi_views) = if config.method.uses_roi_sampling() {
        let targets = roi_targets_of(ctx);
        let poses = sample_roi_views(ctx, config, &targets, &mut rng_stream(seed, 0));
        let views = score(poses, ViewKind::Roi, &evaluator, ctx, config);
        (targets.len(), views)
    } else {
        (0, Vec::new())
    };
    let frontier = ctx.map.exploration_frontier(&ctx.sampling_region);
    let poses = sample_exploration_views(ctx, config, &frontier, &mut rng_stream(seed, 1));
    let exploration_views = score(poses, ViewKind::Exploration, &evaluator, ctx, config);
    let mut candidates_scored = roi_views.len() + exploration_views.len();

    let above = |views: &[ScoredView]| views.iter().any(|v| v.utility > config.utility_threshold);
    let use_roi = above(&roi_views) && !(ctx.roi_stalled && above(&exploration_views));
    let (views, used_kind) = if use_roi {
        (rank(&roi_views, config), ViewKind::Roi)
    } else if !exploration_views.is_empty() {
        (rank(&exploration_views, config), ViewKind::Exploration)
    } else if !roi_views.is_empty() {
        // Weak ROI views still beat standing still.
        (rank(&roi_views, config), ViewKind::Roi)
    } else {
        let poses = sample_fallback_views(ctx, config, &mut rng_stream(seed, 2));
        let views = score(poses, ViewKind::Exploration, &evaluator, ctx, config);
        candidates_scored += views.len();
        (rank(&views, config), ViewKind::Exploration)
    };
    Ok(Plan {
        views,
        roi_targets,
        exploration_frontier: frontier.len(),
        candidates_scored,
        used_kind,
    })
}

/// One fruit: an ROI cluster with a stable id (the one fruit type of the project, see
/// [`glasshouse_geom::fruit`]). The tracker gives its box, voxel count, the share of its box's
/// surface voxels seen as ROI as its confidence, and its view directions; no solid.
pub use glasshouse_geom::FruitEstimate;

/// Largest centre movement between updates for a cluster to keep its fruit id.
pub const TRACK_MATCH_DISTANCE_M: f64 = 0.05;

/// Share of the voxels on the surface of the cluster's key-space box that belong to the cluster:
/// a fully observed fruit fills its box's faces more than a half-seen one.
pub fn fruit_confidence(cluster: &RoiCluster) -> f64 {
    let Some(first) = cluster.voxels.first() else {
        return 0.0;
    };
    let (mut lo, mut hi) = (*first, *first);
    for k in &cluster.voxels {
        lo = VoxelKey::new(lo.x.min(k.x), lo.y.min(k.y), lo.z.min(k.z));
        hi = VoxelKey::new(hi.x.max(k.x), hi.y.max(k.y), hi.z.max(k.z));
    }
    let extent = |a: i32, b: i32| (i64::from(b) - i64::from(a) + 1) as f64;
    let (nx, ny, nz) = (extent(lo.x, hi.x), extent(lo.y, hi.y), extent(lo.z, hi.z));
    let inner = (nx - 2.0).max(0.0) * (ny - 2.0).max(0.0) * (nz - 2.0).max(0.0);
    let surface = nx * ny * nz - inner;
    let on_surface = cluster
        .voxels
        .iter()
        .filter(|k| {
            k.x == lo.x || k.x == hi.x || k.y == lo.y || k.y == hi.y || k.z == lo.z || k.z == hi.z
        })
        .count() as f64;
    if surface > 0.0 {
        (on_surface / surface).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// Two view directions count as distinct when at least this far apart: about the angle over
/// which a camera 0.3-0.5 m away sees a new side of a 5-10 cm fruit.
pub const VIEW_SEPARATION_DEG: f64 = 45.0;
/// A scan whose ROI points fall in fewer of a fruit's voxels did not see it.
pub const MIN_VIEW_HITS: usize = 3;
/// View directions kept per fruit (more add nothing to its confidence).
const MAX_VIEW_DIRECTIONS: usize = 8;
/// Scans noted between two updates that are kept (a replica may integrate many at once).
const MAX_PENDING_SCANS: usize = 16;

/// One noted scan: where the sensor was and the sorted keys of the voxels its ROI points hit.
#[derive(Clone, Debug)]
struct ScanHits {
    sensor_origin_in_world: Point3<f64>,
    roi_keys: Vec<VoxelKey>,
}

/// Keeps fruit ids stable across cluster updates, with the directions each fruit was seen from.
#[derive(Clone, Debug)]
pub struct FruitTracker {
    previous: Vec<(u32, Point3<f64>)>,
    next_id: u32,
    /// Unit directions from each tracked fruit towards the sensors whose scans hit it.
    views: HashMap<u32, Vec<Vector3<f64>>>,
    /// Scans noted since the last update.
    pending: Vec<ScanHits>,
}

impl FruitTracker {
    /// The tracked fruits (id, centre) and the next free id: what another planner needs to carry
    /// on with the same ids ([`FruitTracker::from_state`]). The view directions are not part of
    /// it: a tracker continuing from it counts directions afresh.
    pub fn state(&self) -> (Vec<(u32, Point3<f64>)>, u32) {
        (self.previous.clone(), self.next_id)
    }

    /// A tracker that continues from [`FruitTracker::state`]. The next id is kept above every
    /// tracked id, so ids are never reused.
    pub fn from_state(tracked: Vec<(u32, Point3<f64>)>, next_id: u32) -> Self {
        let above_tracked = tracked.iter().map(|(id, _)| id.saturating_add(1)).max();
        Self {
            next_id: next_id.max(above_tracked.unwrap_or(1)).max(1),
            previous: tracked,
            ..Self::default()
        }
    }

    /// Notes a scan taken from `sensor_origin_in_world` whose ROI points fell in `roi_keys`: at
    /// the next [`FruitTracker::update`], every fruit with at least [`MIN_VIEW_HITS`] of its
    /// voxels among them counts the scan's direction.
    pub fn note_scan(&mut self, sensor_origin_in_world: Point3<f64>, mut roi_keys: Vec<VoxelKey>) {
        roi_keys.sort_unstable();
        roi_keys.dedup();
        if self.pending.len() == MAX_PENDING_SCANS {
            self.pending.remove(0);
        }
        self.pending.push(ScanHits {
            sensor_origin_in_world,
            roi_keys,
        });
    }

    /// The view directions of fruit `id` at `centre` (a cluster of `voxels`) after the noted
    /// scans: its former directions plus each new one that is distinct from all of them.
    fn seen_from(
        &mut self,
        id: u32,
        centre: &Point3<f64>,
        voxels: &[VoxelKey],
    ) -> Vec<Vector3<f64>> {
        let mut directions = self.views.remove(&id).unwrap_or_default();
        let distinct = VIEW_SEPARATION_DEG.to_radians().cos();
        for scan in &self.pending {
            let hits = voxels
                .iter()
                .filter(|k| scan.roi_keys.binary_search(k).is_ok())
                .count();
            let Some(towards) = (scan.sensor_origin_in_world - centre).try_normalize(1e-9) else {
                continue;
            };
            if hits >= MIN_VIEW_HITS
                && directions.len() < MAX_VIEW_DIRECTIONS
                && directions.iter().all(|d| d.dot(&towards) < distinct)
            {
                directions.push(towards);
            }
        }
        directions
    }
}

impl Default for FruitTracker {
    fn default() -> Self {
        // Ids start at 1 so that 0 can mean "no fruit" in messages.
        Self {
            previous: Vec::new(),
            next_id: 1,
            views: HashMap::new(),
            pending: Vec::new(),
        }
    }
}

impl FruitTracker {
    /// Estimates for `clusters` (same order). Each cluster takes the id of the previous estimate
    /// with the nearest centre within [`TRACK_MATCH_DISTANCE_M`] (greedy one-to-one, smallest
    /// distance first); the others get fresh ids. Ids are never reused. Scans noted since the
    /// last update add their directions to the fruits they hit.
    pub fn update(&mut self, clusters: &[RoiCluster]) -> Vec<FruitEstimate> {
        let id_of = self.match_ids(clusters);
        let mut views = HashMap::with_capacity(clusters.len());
        let estimates: Vec<FruitEstimate> = clusters
            .iter()
            .zip(id_of)
            .map(|(cluster, id)| {
                let id = id.unwrap_or_else(|| {
                    let fresh = self.next_id;
                    // 4 billion fruits will not happen; saturate rather than wrap to a used id.
                    self.next_id = self.next_id.saturating_add(1);
                    fresh
                });
                let directions = self.seen_from(id, &cluster.centre, &cluster.voxels);
                let view_directions = directions.len() as u32;
                views.insert(id, directions);
                let size = cluster.max - cluster.min;
                FruitEstimate {
                    id,
                    centre: cluster.centre,
                    min: cluster.min,
                    max: cluster.max,
                    volume_m3: size.x.max(0.0) * size.y.max(0.0) * size.z.max(0.0),
                    voxel_count: cluster.voxels.len(),
                    confidence: fruit_confidence(cluster),
                    view_directions,
                    solid: None,
                    // The pipeline adds the colours of the scans' fruit points.
                    colour: None,
                }
            })
            .collect();
        self.previous = estimates.iter().map(|e| (e.id, e.centre)).collect();
        self.views = views;
        self.pending.clear();
        estimates
    }

    /// The previous id each cluster keeps, if any (see [`FruitTracker::update`]).
    fn match_ids(&self, clusters: &[RoiCluster]) -> Vec<Option<u32>> {
        let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
        for (ci, cluster) in clusters.iter().enumerate() {
            for (pi, (_, centre)) in self.previous.iter().enumerate() {
                let d = (cluster.centre - centre).norm();
                if d <= TRACK_MATCH_DISTANCE_M {
                    pairs.push((d, ci, pi));
                }
            }
        }
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        let mut id_of: Vec<Option<u32>> = vec![None; clusters.len()];
        let mut taken = vec![false; self.previous.len()];
        for (_, ci, pi) in pairs {
            if id_of[ci].is_none() && !taken[pi] {
                id_of[ci] = Some(self.previous[pi].0);
                taken[pi] = true;
            }
        }
        id_of
    }
}

#[cfg(test)]
mod tests;
