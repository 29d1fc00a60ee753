//! One seeded trial: the services' loop (edge → detector → planner → edge) in one thread, with the
//! simulated clock.
//!
//! Each step mirrors the services exactly:
//!
//! 1. **Edge**: render the simulator at the current pose with noise seed
//!    `seed · 1 000 003 + frame_seq` and pack depth as millimetres ([`glasshouse_sim`]).
//! 2. **Detector**: [`glasshouse_detect::detect`] with [`DetectorConfig::default`] (1 cm).
//! 3. **Planner**: insert the cloud into a [`RoiMap`] (1 cm, range 2 m, the planner-service's
//!    [`MapConfig`]), clusters of ≥ 10 voxels, [`FruitTracker`] ids, then [`plan_views`] seeded
//!    with `seed · 0x9E37_79B9_7F4A_7C15 + frame_seq` as the planner-service does; then the
//!    fitted shape of every cluster ([`glasshouse_nbv::fit`], outside the measured compute time).
//! 4. **Edge**: execute the first view [`Motion`] can reach ([`ArmMotion`]: the scene's UR5e, as
//!    the edge does); none reachable costs a capture. The row's segments (the edge moving its rail
//!    on when a segment is done) are not modelled: a `row` trial plans over the whole row.
//!
//! The clock: frame 1 is captured at 0 s; the estimates of a frame are available once the
//! planner's compute time has passed ([`ComputeTime`]); the next frame is captured after the
//! motion and the capture time. Metrics are sampled at every whole simulated second from 0 to the
//! budget, each holding the latest estimates available at that instant (carried across motions).

use std::time::Instant;

use glasshouse_arm::ReachCheck;
use glasshouse_detect::{detect, DepthFrame, DetectorConfig};
use glasshouse_nbv::fit::{fit_ellipsoid, FitConfig, FittedShape};
use glasshouse_nbv::{
    plan_views, FruitEstimate, FruitTracker, Method, PlanError, PlannerConfig, PlanningContext,
    ReachPredicate,
};
use glasshouse_roimap::{MapConfig, MapError, RoiCluster, RoiMap};
use glasshouse_sim::{CameraModel, ScenarioKind, Scene, SimArm, CAMERA_CLEARANCE_M};
use nalgebra::{Isometry3, Point3};
use serde::Serialize;

use crate::metrics::{evaluate, BoxEstimate, Metrics};
use crate::reach::{as_predicate, clear_of_occupied, scene_reach_predicate, OwnedReach};

/// Depth travels as millimetres between the edge and the detector.
pub const DEPTH_SCALE_M: f32 = 0.001;

/// Errors of a trial; configuration errors are found before anything runs.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum EvalError {
    #[error("invalid trial configuration: {0}")]
    InvalidConfig(String),
    #[error(transparent)]
    Map(#[from] MapError),
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error("detection failed: {0}")]
    Detect(#[from] glasshouse_detect::DetectError),
}

/// A view the [`Motion`] executed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Executed {
    /// Index of the executed goal in the ranked list.
    pub index: usize,
    /// Motion time, without capture time.
    pub motion_s: f64,
    /// The camera pose reached.
    pub world_from_camera: Isometry3<f64>,
}

/// Which views the robot can execute and how long the motion takes (the edge's "moveToPose,
/// else the next view"). [`ArmMotion`] is the edge's rule today (the scene's UR5e on its mount);
/// [`FreeCameraMotion`] the earlier free-flying camera.
pub trait Motion {
    /// The camera pose now.
    fn world_from_camera(&self) -> Isometry3<f64>;
    /// Moves to the first of `goals` (best first) that can be reached; `None`, and no motion,
    /// when none can.
    fn execute_first_reachable(
        &mut self,
        scene: &Scene,
        goals: &[Isometry3<f64>],
    ) -> Option<Executed>;
}

/// A free-flying camera: a goal is reachable when its position is free
/// ([`Scene::is_camera_position_free`]: inside the camera workspace box and clear of every solid);
/// the camera moves in a straight line at a constant speed. Starts at the scene's initial view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FreeCameraMotion {
    pub camera_speed_m_per_s: f64,
    pub pose: Isometry3<f64>,
}

impl FreeCameraMotion {
    /// At the scene's initial view, moving at the former edge's default speed, 0.5 m/s.
    pub fn new(scene: &Scene) -> Self {
        Self {
            camera_speed_m_per_s: 0.5,
            pose: scene.initial_camera_pose(),
        }
    }
}

impl Motion for FreeCameraMotion {
    fn world_from_camera(&self) -> Isometry3<f64> {
        self.pose
    }

    fn execute_first_reachable(
        &mut self,
        scene: &Scene,
        goals: &[Isometry3<f64>],
    ) -> Option<Executed> {
        let (index, goal) = goals.iter().enumerate().find(|(_, goal)| {
            let target = Point3::from(goal.translation.vector);
            scene.camera_workspace().contains(&target) && scene.is_camera_position_free(&target)
        })?;
        let distance_m = (goal.translation.vector - self.pose.translation.vector).norm();
        self.pose = *goal;
        Some(Executed {
            index,
            motion_s: distance_m / self.camera_speed_m_per_s,
            world_from_camera: *goal,
        })
    }
}

/// The edge's rule: the scene's UR5e on its mount ([`SimArm`]): a goal is reachable when its
/// camera position is free and the arm reaches it (inverse kinematics, then a collision-free
/// joint path); the motion time is the path's duration.
#[derive(Clone, Debug)]
pub struct ArmMotion {
    pub arm: SimArm,
}

impl ArmMotion {
    /// The arm placed with its camera at the scene's initial view.
    pub fn new(scene: &Scene) -> Result<Self, EvalError> {
        let arm = SimArm::new(scene).map_err(|e| {
            EvalError::InvalidConfig(format!("the arm cannot reach the initial view: {e}"))
        })?;
        Ok(Self { arm })
    }
}

impl Motion for ArmMotion {
    fn world_from_camera(&self) -> Isometry3<f64> {
        self.arm.world_from_camera()
    }

    fn execute_first_reachable(
        &mut self,
        scene: &Scene,
        goals: &[Isometry3<f64>],
    ) -> Option<Executed> {
        let e = self.arm.execute_first_reachable(scene, goals)?;
        Some(Executed {
            index: e.index,
            motion_s: e.motion_s,
            world_from_camera: self.arm.world_from_camera(),
        })
    }
}

/// Which [`Motion`] a trial uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum MotionKind {
    /// [`ArmMotion`], the edge's rule.
    Arm,
    /// [`FreeCameraMotion`].
    FreeCamera,
}

impl std::str::FromStr for MotionKind {
    type Err = EvalError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "arm" | "ur5e" => Ok(MotionKind::Arm),
            "free-camera" | "free" => Ok(MotionKind::FreeCamera),
            _ => Err(EvalError::InvalidConfig(format!(
                "unknown motion {s:?}; valid: arm (ur5e), free-camera"
            ))),
        }
    }
}

impl std::fmt::Display for MotionKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            MotionKind::Arm => "arm",
            MotionKind::FreeCamera => "free-camera",
        })
    }
}

/// The motion of `kind` for a scene, boxed.
pub fn motion_for(kind: MotionKind, scene: &Scene) -> Result<Box<dyn Motion + Send>, EvalError> {
    Ok(match kind {
        MotionKind::Arm => Box::new(ArmMotion::new(scene)?),
        MotionKind::FreeCamera => Box::new(FreeCameraMotion::new(scene)),
    })
}

impl<T: Motion + ?Sized> Motion for Box<T> {
    fn world_from_camera(&self) -> Isometry3<f64> {
        (**self).world_from_camera()
    }

    fn execute_first_reachable(
        &mut self,
        scene: &Scene,
        goals: &[Isometry3<f64>],
    ) -> Option<Executed> {
        (**self).execute_first_reachable(scene, goals)
    }
}

/// How the planner's compute time enters the simulated clock.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub enum ComputeTime {
    /// A fixed time per planning call: runs replay bit for bit.
    Fixed { ms: f64 },
    /// The wall time of the planner's work on a cloud (map insertion, clusters, ids and
    /// planning; not the shape fits), measured by the runner; runs depend on the machine.
    Measured,
}

/// Everything that defines a trial.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TrialConfig {
    pub scenario: ScenarioKind,
    pub method: Method,
    /// Scene, camera-noise and planner seed (as `glasshouse demo --seed`).
    pub seed: u64,
    pub width: u32,
    pub height: u32,
    /// Simulated seconds of the trial.
    pub budget_s: f64,
    pub compute_time: ComputeTime,
    /// Which robot executes the views (used by [`run_trial`]).
    pub motion: MotionKind,
    /// Simulated seconds to capture one view (the edge's default, 0.5 s).
    pub capture_time_s: f64,
    pub resolution_m: f64,
    /// Rays are integrated up to this range (the planner-service's default, 2 m).
    pub max_range_m: f64,
    pub min_cluster_voxels: usize,
    pub fit: FitConfig,
    /// The planner drops candidate views the scene's robot cannot reach, checked this far
    /// ([`crate::reach::scene_reachability`]) or closer than [`CAMERA_CLEARANCE_M`] to a voxel
    /// the map knows as occupied; `None`: it plans over the whole camera workspace, as the
    /// planner-service does today.
    pub reach: Option<ReachCheck>,
}

impl TrialConfig {
    /// The services' defaults for everything but the experiment's choices.
    pub fn new(scenario: ScenarioKind, method: Method, seed: u64) -> Self {
        Self {
            scenario,
            method,
            seed,
            width: 640,
            height: 480,
            budget_s: 180.0,
            compute_time: ComputeTime::Measured,
            motion: MotionKind::Arm,
            capture_time_s: 0.5,
            resolution_m: 0.01,
            max_range_m: 2.0,
            min_cluster_voxels: 10,
            fit: FitConfig::default(),
            reach: None,
        }
    }

    pub fn validate(&self) -> Result<(), EvalError> {
        let bad = |m: &str| Err(EvalError::InvalidConfig(m.to_string()));
        if !((16..=1280).contains(&self.width) && (12..=960).contains(&self.height)) {
            return bad("image size outside 16x12..1280x960");
        }
        if !(self.budget_s.is_finite() && self.budget_s >= 0.0 && self.budget_s <= 86_400.0) {
            return bad("budget must be within 0..=86400 s");
        }
        if !(self.capture_time_s.is_finite() && self.capture_time_s >= 0.0) {
            return bad("capture time must be finite and >= 0");
        }
        if let ComputeTime::Fixed { ms } = self.compute_time {
            if !(ms.is_finite() && ms >= 0.0) {
                return bad("fixed compute time must be finite and >= 0");
            }
        }
        // A trial must make progress: some simulated time per frame.
        let fixed_zero = matches!(self.compute_time, ComputeTime::Fixed { ms } if ms <= 0.0);
        if self.capture_time_s <= 0.0 && fixed_zero {
            return bad("capture time and compute time cannot both be 0");
        }
        self.map_config().validate()?;
        Ok(())
    }

    fn map_config(&self) -> MapConfig {
        MapConfig {
            resolution_m: self.resolution_m,
            max_range_m: Some(self.max_range_m),
            ..MapConfig::default()
        }
    }
}

/// The metrics at one whole simulated second.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Sample {
    pub time_s: u32,
    /// Views executed so far (motions started).
    pub views: u32,
    /// Frames whose estimates are available.
    pub frames: u64,
    /// Fruit estimates (clusters).
    pub estimates: usize,
    /// Mean confidence of the fitted estimates (NaN without estimates).
    pub mean_confidence: f64,
    /// Metrics of the box estimates (the paper's).
    pub boxes: Metrics,
    /// Metrics of the fitted estimates (their boxes and box volumes).
    pub fitted: Metrics,
}

/// One fruit estimate with both shapes.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FruitRecord {
    pub estimate: FruitEstimate,
    pub fitted: FittedShape,
}

impl FruitRecord {
    pub fn box_estimate(&self) -> BoxEstimate {
        BoxEstimate {
            centre: self.estimate.centre,
            min: self.estimate.min,
            max: self.estimate.max,
            volume_m3: self.estimate.volume_m3,
        }
    }

    pub fn fitted_estimate(&self) -> BoxEstimate {
        BoxEstimate {
            centre: self.fitted.centre,
            min: self.fitted.box_min,
            max: self.fitted.box_max,
            volume_m3: self.fitted.box_volume_m3,
        }
    }
}

/// What a finished trial reports.
#[derive(Clone, Debug, Serialize)]
pub struct TrialResult {
    pub config: TrialConfig,
    /// One per whole second from 0 to the budget.
    pub samples: Vec<Sample>,
    pub fruits_total: usize,
    pub views: u32,
    pub frames: u64,
    pub unreachable_views: u64,
    /// Frames whose ranked list held no view the robot could execute (each cost a capture).
    pub frames_without_view: u64,
    /// Sum of the compute times that entered the clock.
    pub compute_time_s: f64,
    /// The estimates at the end of the budget.
    pub fruits: Vec<FruitRecord>,
}

impl TrialResult {
    /// The sample at the end of the budget.
    pub fn last(&self) -> Option<&Sample> {
        self.samples.last()
    }
}

/// The state the metrics see between two planning calls.
#[derive(Clone, Debug)]
struct Published {
    frames: u64,
    fruits: Vec<FruitRecord>,
    boxes: Metrics,
    fitted: Metrics,
}

/// A trial in progress (see the module docs).
pub struct Trial<M: Motion> {
    config: TrialConfig,
    planner: PlannerConfig,
    detector: DetectorConfig,
    scene: Scene,
    camera: CameraModel,
    map: RoiMap,
    tracker: FruitTracker,
    motion: M,
    reach: Option<OwnedReach>,
    pose: Isometry3<f64>,
    /// Capture time of the next frame.
    clock_s: f64,
    frame_seq: u64,
    views: u32,
    unreachable_views: u64,
    frames_without_view: u64,
    compute_time_s: f64,
    published: Published,
    samples: Vec<Sample>,
    /// Whole seconds 0..=last_second are sampled.
    last_second: u32,
}

impl<M: Motion> Trial<M> {
    /// A trial whose motion `make_motion` builds for the generated scene.
    pub fn new(
        config: TrialConfig,
        make_motion: impl FnOnce(&Scene) -> Result<M, EvalError>,
    ) -> Result<Self, EvalError> {
        config.validate()?;
        let planner = PlannerConfig {
            method: config.method,
            // Trials run in parallel, one per core, so each plans on its own thread.
            scoring_threads: 1,
            ..PlannerConfig::default()
        };
        planner.validate()?;
        let scene = Scene::generate(config.scenario, config.seed);
        let motion = make_motion(&scene)?;
        let reach = config
            .reach
            .map(|check| scene_reach_predicate(&scene, check))
            .transpose()?;
        let camera = CameraModel::with_resolution(config.width, config.height);
        let map = RoiMap::new(config.map_config())?;
        let empty_boxes = Metrics::empty(scene.fruits(), config.resolution_m);
        Ok(Self {
            planner,
            detector: DetectorConfig {
                voxel_size_m: config.resolution_m,
                ..DetectorConfig::default()
            },
            pose: motion.world_from_camera(),
            scene,
            camera,
            map,
            tracker: FruitTracker::default(),
            motion,
            reach,
            clock_s: 0.0,
            frame_seq: 0,
            views: 0,
            unreachable_views: 0,
            frames_without_view: 0,
            compute_time_s: 0.0,
            published: Published {
                frames: 0,
                fruits: Vec::new(),
                boxes: empty_boxes,
                fitted: empty_boxes,
            },
            samples: Vec::new(),
            last_second: config.budget_s.floor() as u32,
            config,
        })
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn map(&self) -> &RoiMap {
        &self.map
    }

    /// What the next planning call looks at: the map, the current pose and the scene's regions.
    pub fn planning_context(&self) -> PlanningContext<'_> {
        PlanningContext {
            map: &self.map,
            world_from_camera: self.pose,
            camera_workspace: self.scene.camera_workspace(),
            sampling_region: self.scene.sampling_region(),
            reach: self.reach.as_ref().map(as_predicate),
        }
    }

    /// The planner's configuration for this trial.
    pub fn planner_config(&self) -> &PlannerConfig {
        &self.planner
    }

    /// Seed of the planning call on the latest frame.
    pub fn plan_seed(&self) -> u64 {
        self.config
            .seed
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .wrapping_add(self.frame_seq)
    }

    /// Capture time of the next frame (simulated seconds).
    pub fn clock_s(&self) -> f64 {
        self.clock_s
    }

    pub fn is_done(&self) -> bool {
        self.clock_s > self.config.budget_s
    }

    /// Samples whole seconds before `until_s` (and not past the budget) with the published state.
    fn sample_until(&mut self, until_s: f64) {
        while let Some(next) = self.next_sample_second() {
            if f64::from(next) >= until_s {
                break;
            }
            let fruits = &self.published.fruits;
            let confidences: Vec<f64> = fruits.iter().map(|f| f.fitted.confidence).collect();
            self.samples.push(Sample {
                time_s: next,
                views: self.views,
                frames: self.published.frames,
                estimates: fruits.len(),
                mean_confidence: crate::metrics::mean(&confidences),
                boxes: self.published.boxes,
                fitted: self.published.fitted,
            });
        }
    }

    fn next_sample_second(&self) -> Option<u32> {
        let next = self.samples.len() as u32;
        (next <= self.last_second).then_some(next)
    }

    /// The planner-service's work on one cloud: insert, clusters, ids, fits; then the plan.
    fn plan_on(
        &mut self,
        cloud: &glasshouse_detect::LabelledCloud,
    ) -> Result<(Vec<RoiCluster>, Vec<FruitEstimate>, glasshouse_nbv::Plan), EvalError> {
        self.map.insert_scan(
            &cloud.sensor_origin_in_world,
            &cloud.points_in_world,
            &cloud.roi,
        )?;
        let clusters = self.map.clusters(self.config.min_cluster_voxels);
        let estimates = self.tracker.update(&clusters);
        let base = self.planning_context();
        let map = &self.map;
        let res = self.config.resolution_m;
        // The edge also refuses a camera near a solid: ask for clearance from the known ones.
        let reach_and_clear = move |pose: &Isometry3<f64>| {
            base.reach.is_some_and(|reach| reach(pose))
                && clear_of_occupied(map, pose, CAMERA_CLEARANCE_M, res)
        };
        let ctx = PlanningContext {
            reach: base.reach.map(|_| &reach_and_clear as &ReachPredicate<'_>),
            ..base
        };
        let plan = plan_views(&ctx, &self.planner, self.plan_seed())?;
        Ok((clusters, estimates, plan))
    }

    /// Both shapes of every fruit (the fits are not part of the planner's compute time: the
    /// planner-service does not fit yet, and planning does not depend on them).
    fn fruit_records(
        &self,
        clusters: &[RoiCluster],
        estimates: Vec<FruitEstimate>,
    ) -> Vec<FruitRecord> {
        clusters
            .iter()
            .zip(estimates)
            .map(|(cluster, estimate)| FruitRecord {
                fitted: fit_ellipsoid(&self.map, cluster, &self.config.fit),
                estimate,
            })
            .collect()
    }

    /// One capture → detect → plan → move cycle. Returns false once the budget is spent (the
    /// remaining seconds are then sampled).
    pub fn step(&mut self) -> Result<bool, EvalError> {
        if self.is_done() {
            self.sample_until(f64::INFINITY);
            return Ok(false);
        }
        self.frame_seq += 1;
        let noise_seed = self
            .config
            .seed
            .wrapping_mul(1_000_003)
            .wrapping_add(self.frame_seq);
        let image = self.scene.render(&self.camera, &self.pose, noise_seed);
        let depth = depth_as_millimetres(&image.depth_m);
        let frame = DepthFrame {
            intrinsics: image.intrinsics,
            depth: &depth,
            depth_scale_m: f64::from(DEPTH_SCALE_M),
            rgb: &image.rgb,
        };
        let cloud = detect(&frame, &self.pose, &self.detector)?;

        let started = Instant::now();
        let (clusters, estimates, plan) = self.plan_on(&cloud)?;
        let compute_s = match self.config.compute_time {
            ComputeTime::Fixed { ms } => ms / 1e3,
            ComputeTime::Measured => started.elapsed().as_secs_f64(),
        };
        let fruits = self.fruit_records(&clusters, estimates);
        self.compute_time_s += compute_s;
        let available_s = self.clock_s + compute_s;
        // Seconds before the new estimates exist hold the previous ones.
        self.sample_until(available_s);
        if available_s > self.config.budget_s {
            self.clock_s = available_s;
            self.sample_until(f64::INFINITY);
            return Ok(false);
        }
        let truths = self.scene.fruits();
        let res = self.config.resolution_m;
        let boxes: Vec<BoxEstimate> = fruits.iter().map(FruitRecord::box_estimate).collect();
        let fitted: Vec<BoxEstimate> = fruits.iter().map(FruitRecord::fitted_estimate).collect();
        self.published = Published {
            frames: self.frame_seq,
            boxes: evaluate(&boxes, truths, res),
            fitted: evaluate(&fitted, truths, res),
            fruits,
        };

        // Execute the first reachable view (the edge's Algorithm 1 step).
        let goals: Vec<Isometry3<f64>> = plan.views.iter().map(|v| v.world_from_camera).collect();
        let mut next_clock = available_s + self.config.capture_time_s;
        match self.motion.execute_first_reachable(&self.scene, &goals) {
            Some(executed) => {
                self.unreachable_views += executed.index as u64;
                next_clock += executed.motion_s.max(0.0);
                self.pose = executed.world_from_camera;
                self.views += 1;
            }
            None => {
                self.unreachable_views += goals.len() as u64;
                self.frames_without_view += 1;
            }
        }
        self.clock_s = next_clock;
        Ok(true)
    }

    /// Runs to the end of the budget; `progress` gets the simulated clock after every step.
    pub fn run(mut self, mut progress: impl FnMut(f64)) -> Result<TrialResult, EvalError> {
        while self.step()? {
            progress(self.clock_s.min(self.config.budget_s));
        }
        progress(self.config.budget_s);
        Ok(TrialResult {
            config: self.config,
            fruits_total: self.scene.fruits().len(),
            samples: self.samples,
            views: self.views,
            frames: self.published.frames,
            unreachable_views: self.unreachable_views,
            frames_without_view: self.frames_without_view,
            compute_time_s: self.compute_time_s,
            fruits: self.published.fruits,
        })
    }
}

/// Runs one trial with the motion of `config.motion`; `progress` as in [`Trial::run`].
pub fn run_trial(config: TrialConfig, progress: impl FnMut(f64)) -> Result<TrialResult, EvalError> {
    Trial::new(config, |scene| motion_for(config.motion, scene))?.run(progress)
}

/// The edge's packing of depth: millimetres, 0 = invalid.
pub fn depth_as_millimetres(depth_m: &[f32]) -> Vec<u16> {
    depth_m
        .iter()
        .map(|&d| {
            if d.is_finite() && d > 0.0 {
                (d / DEPTH_SCALE_M).round().clamp(1.0, u16::MAX as f32) as u16
            } else {
                0
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn small(method: Method, budget_s: f64) -> TrialConfig {
        TrialConfig {
            width: 96,
            height: 72,
            budget_s,
            compute_time: ComputeTime::Fixed { ms: 50.0 },
            ..TrialConfig::new(ScenarioKind::Two, method, 3)
        }
    }

    fn free(scene: &Scene) -> Result<FreeCameraMotion, EvalError> {
        Ok(FreeCameraMotion::new(scene))
    }

    #[test]
    fn a_trial_samples_every_second_and_finds_fruit() {
        for motion in [MotionKind::FreeCamera, MotionKind::Arm] {
            let config = TrialConfig {
                motion,
                ..small(Method::OursUu, 20.0)
            };
            let result = run_trial(config, |_| {}).unwrap();
            assert_eq!(result.samples.len(), 21);
            for (i, s) in result.samples.iter().enumerate() {
                assert_eq!(s.time_s, i as u32);
                assert!(s.boxes.detected <= result.fruits_total);
                assert!((0.0..=1.0).contains(&s.boxes.covered_volume));
            }
            // Nothing is known at 0 s; views and frames never decrease.
            assert_eq!(result.samples[0].frames, 0);
            assert_eq!(result.samples[0].boxes.detected, 0);
            assert!(result
                .samples
                .windows(2)
                .all(|w| w[0].views <= w[1].views && w[0].frames <= w[1].frames));
            let last = result.last().unwrap();
            assert!(last.boxes.detected > 0, "{motion}: {last:?}");
            assert!(result.views > 3, "{motion}: {}", result.views);
            // 50 ms per planning call entered the clock.
            assert!((result.compute_time_s - 0.05 * result.frames as f64).abs() < 1e-9);
        }
    }

    #[test]
    fn fixed_compute_time_replays_exactly() {
        for motion in [MotionKind::FreeCamera, MotionKind::Arm] {
            let config = TrialConfig {
                motion,
                ..small(Method::ExploUp, 8.0)
            };
            let (a, b) = (
                run_trial(config, |_| {}).unwrap(),
                run_trial(config, |_| {}).unwrap(),
            );
            assert_eq!(
                serde_json::to_string(&a.samples).unwrap(),
                serde_json::to_string(&b.samples).unwrap()
            );
            assert_eq!(a.views, b.views);
        }
    }

    /// Nothing is reachable: every frame costs a capture and the camera never moves.
    struct Stuck(Isometry3<f64>);

    impl Motion for Stuck {
        fn world_from_camera(&self) -> Isometry3<f64> {
            self.0
        }

        fn execute_first_reachable(&mut self, _: &Scene, _: &[Isometry3<f64>]) -> Option<Executed> {
            None
        }
    }

    #[test]
    fn unreachable_views_cost_a_capture_each() {
        let config = TrialConfig {
            capture_time_s: 1.0,
            compute_time: ComputeTime::Fixed { ms: 0.0 },
            ..small(Method::OursUu, 4.5)
        };
        let result = Trial::new(config, |scene| Ok(Stuck(scene.initial_camera_pose())))
            .unwrap()
            .run(|_| {})
            .unwrap();
        assert_eq!(result.views, 0);
        // Frames at 0, 1, 2, 3, 4 s.
        assert_eq!(result.frames, 5);
        assert!(result.unreachable_views > 0);
        assert_eq!(result.samples.len(), 5);
        // A frame captured at t is available at t (0 ms compute): sample t sees frame t + 1.
        for (t, s) in result.samples.iter().enumerate() {
            assert_eq!(s.frames, t as u64 + 1);
        }
    }

    #[test]
    fn bad_configurations_are_rejected() {
        let bad = [
            TrialConfig {
                width: 0,
                ..small(Method::OursUu, 5.0)
            },
            TrialConfig {
                budget_s: f64::NAN,
                ..small(Method::OursUu, 5.0)
            },
            TrialConfig {
                compute_time: ComputeTime::Fixed { ms: -1.0 },
                ..small(Method::OursUu, 5.0)
            },
            TrialConfig {
                capture_time_s: 0.0,
                compute_time: ComputeTime::Fixed { ms: 0.0 },
                ..small(Method::OursUu, 5.0)
            },
            TrialConfig {
                resolution_m: 0.0,
                ..small(Method::OursUu, 5.0)
            },
        ];
        for config in bad {
            assert!(matches!(
                Trial::new(config, free),
                Err(EvalError::InvalidConfig(_)) | Err(EvalError::Map(_))
            ));
        }
        assert!("ur5e".parse::<MotionKind>().is_ok());
        assert!("teleport".parse::<MotionKind>().is_err());
    }

    #[test]
    fn free_camera_motion_takes_the_first_free_goal() {
        let scene = Scene::generate(ScenarioKind::Two, 3);
        let mut motion = FreeCameraMotion::new(&scene);
        let from = motion.world_from_camera();
        let mut outside = from;
        outside.translation.vector.z = 100.0;
        let mut up = from;
        up.translation.vector.z += 0.1;
        let free = scene.is_camera_position_free(&Point3::from(up.translation.vector));
        match motion.execute_first_reachable(&scene, &[outside, up]) {
            Some(e) => {
                assert!(free);
                assert_eq!(e.index, 1);
                assert!((e.motion_s - 0.2).abs() < 1e-9);
                assert_eq!(motion.world_from_camera(), up);
            }
            None => assert!(!free),
        }
        assert!(motion.execute_first_reachable(&scene, &[outside]).is_none());
    }
}
