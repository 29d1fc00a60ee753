//! One seeded trial: the services' loop in one thread, through the same steps the services call
//! ([`glasshouse_pipeline`]), on the simulated clock.
//!
//! - **Edge**: the edge's state machine ([`EdgeNode`]) drives a [`TrolleySource`] (by default the
//!   scene's [`SimTrolley`]: the UR5e on its mount, the row's segments, the seeded camera noise).
//! - **Detector**: [`detect_frame`] with [`DetectorConfig::default`] at the map resolution.
//! - **Planner**: a [`TrolleyPlanner`] with the planner service's [`PlanningSettings`] (scoring on
//!   one thread, as trials already run one per core): integrate, fruit ids, plan, fits.
//!
//! What experiments add is the clock, the ground truth and the metrics. Frame 1 is captured at
//! 0 s; the estimates of a frame are available once the planner's compute time has passed
//! ([`ComputeTime`]); the next frame is captured after the edge's motion and capture time.
//! Metrics are sampled at every whole simulated second from 0 to the budget, each holding the
//! latest estimates available at that instant.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Instant;

use glasshouse_detect::{DetectorConfig, FruitDetector, HsiVotes};
use glasshouse_geom::FruitEstimate;
use glasshouse_nbv::Method;
use glasshouse_pipeline::{
    detect_frame_with, ranked_views, ClusterOutcome, EdgeAction, EdgeEvent, EdgeInput, EdgeNode,
    EdgeSettings, PlanningError, PlanningSettings, RoiEvidence, RoiTargets, TrolleyPlanner,
    TrolleySource,
};
use glasshouse_proto::{FrameId, Header, RankedViews, RgbdFrame, RoiCloud, TrolleyInfo};
use glasshouse_sim::{FruitTruth, ScenarioKind, Scene, WorldSettings};
use glasshouse_simtrolley::{CaptureError, SimTrolley, SimTrolleySettings};
use serde::Serialize;

use crate::metrics::{evaluate, evaluate_against, Metrics, TruthMeasure};

/// Errors of a trial; configuration errors are found before anything runs.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum EvalError {
    #[error("invalid trial configuration: {0}")]
    InvalidConfig(String),
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error("capture failed: {0}")]
    CaptureFailed(String),
    #[error(transparent)]
    Planning(#[from] PlanningError),
    #[error("detection failed: {0}")]
    Detect(#[from] glasshouse_detect::DetectError),
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

/// Everything that defines a trial; the rest are the services' defaults.
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
    /// Simulated seconds to capture one view (the edge's default).
    pub capture_time_s: f64,
    /// Row segments (the edge's default).
    pub segment_length_m: f64,
    /// The simulated world: camera noise and light, fruit shape and colour, red clutter, pose
    /// errors (clean by default).
    pub world: WorldSettings,
    /// How detections enter the map (the planner's default: labels).
    pub roi_evidence: RoiEvidence,
    /// Which ROI voxels ROI-targeted sampling aims at (the planner's default: patches).
    pub roi_targets: RoiTargets,
    /// Align each scan to the map before inserting it (the planner's default: off).
    pub registration: bool,
    /// Estimate the trolley's hand-eye error across its scans and undo it before each scan
    /// goes in (`PlanningSettings::hand_eye`; the planner's default: on).
    pub hand_eye: bool,
    /// A revisit's plans aim at the previous visit's fruit
    /// (`PlanningSettings::aim_at_remembered_fruit`).
    pub revisit_aim: bool,
    /// The ranking's cost per second of robot motion (`PlanningSettings::cost_weight_per_s`;
    /// 0: the paper's ranking).
    pub motion_cost_per_s: f64,
    /// Scan directions after which a cluster shaped like no fruit stops drawing ROI views
    /// (`PlanningSettings::clutter_settles_after_views`; 0: never).
    pub clutter_settles_after_views: u32,
    /// Scan directions after which a cluster taken for a fruit stops drawing ROI views
    /// (`PlanningSettings::fruit_settles_after_views`; 0: never).
    pub fruit_settles_after_views: u32,
    /// Clouds without a new fruit-shaped cluster after which plans prefer exploration views
    /// (`PlanningSettings::explore_after_fruitless_clouds`; 0: never).
    pub explore_after_fruitless_clouds: u32,
    /// Tries of ROI-targeted sampling until its candidates are drawn
    /// (`PlanningSettings::roi_tries`; 0: the paper's).
    pub roi_tries: usize,
    /// Whether turned-away clusters are searched for a fruit body under them
    /// (`EvidenceConfig::body`; on by default).
    pub body_search: bool,
    /// Occupancy log-odds above which a voxel occludes an ROI target
    /// (`PlanningSettings::occlusion_occupancy_logodds`).
    pub occlusion_occupancy_logodds: f32,
    /// Fitted solids shrunk by this times voxel² / R (`FitConfig::voxel_bias_factor`).
    pub voxel_bias_factor: f64,
    /// Rays are integrated up to this range, metres (`PlanningSettings::max_range_m`).
    pub max_range_m: f64,
    /// Points beyond the range free one ray per voxel at the range
    /// (`PlanningSettings::merge_far_rays`).
    pub merge_far_rays: bool,
    /// ROI targets nearer the camera drawn more often (`PlanningSettings::roi_target_near_m`).
    pub roi_target_near_m: f64,
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
            capture_time_s: glasshouse_arm::CAPTURE_TIME_S,
            segment_length_m: 1.0,
            world: WorldSettings::default(),
            roi_evidence: RoiEvidence::Labels,
            roi_targets: RoiTargets::default(),
            registration: false,
            hand_eye: true,
            revisit_aim: true,
            motion_cost_per_s: glasshouse_pipeline::DEFAULT_COST_WEIGHT_PER_S,
            clutter_settles_after_views: glasshouse_pipeline::DEFAULT_CLUTTER_SETTLES_AFTER_VIEWS,
            fruit_settles_after_views: glasshouse_pipeline::DEFAULT_FRUIT_SETTLES_AFTER_VIEWS,
            explore_after_fruitless_clouds:
                glasshouse_pipeline::DEFAULT_EXPLORE_AFTER_FRUITLESS_CLOUDS,
            roi_tries: glasshouse_pipeline::DEFAULT_ROI_TRIES,
            body_search: true,
            occlusion_occupancy_logodds: PlanningSettings::default().occlusion_occupancy_logodds,
            voxel_bias_factor: PlanningSettings::default().fit.voxel_bias_factor,
            max_range_m: PlanningSettings::default().max_range_m,
            merge_far_rays: PlanningSettings::default().merge_far_rays,
            roi_target_near_m: PlanningSettings::default().roi_target_near_m,
        }
    }

    pub fn validate(&self) -> Result<(), EvalError> {
        let bad = |m: &str| Err(EvalError::InvalidConfig(m.to_string()));
        if !((16..=1280).contains(&self.width) && (12..=960).contains(&self.height)) {
            return bad("image size outside 16x12..1280x960");
        }
        if let Err(e) = self.world.validate() {
            return bad(&e.to_string());
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
        self.planning().validate()?;
        Ok(())
    }

    /// The planner service's settings with this trial's method and seed.
    pub fn planning(&self) -> PlanningSettings {
        let mut settings = PlanningSettings {
            method: self.method,
            seed: self.seed,
            // Trials run in parallel, one per core, so each plans on its own thread.
            scoring_threads: 1,
            roi_evidence: self.roi_evidence,
            roi_targets: self.roi_targets,
            max_range_m: self.max_range_m,
            merge_far_rays: self.merge_far_rays,
            roi_target_near_m: self.roi_target_near_m,
            ..PlanningSettings::default()
        };
        settings.registration.enabled = self.registration;
        settings.hand_eye.enabled = self.hand_eye;
        settings.aim_at_remembered_fruit = self.revisit_aim;
        settings.cost_weight_per_s = self.motion_cost_per_s;
        settings.clutter_settles_after_views = self.clutter_settles_after_views;
        settings.fruit_settles_after_views = self.fruit_settles_after_views;
        settings.explore_after_fruitless_clouds = self.explore_after_fruitless_clouds;
        settings.roi_tries = self.roi_tries;
        settings.fit.evidence.body.enabled = self.body_search;
        settings.occlusion_occupancy_logodds = self.occlusion_occupancy_logodds;
        settings.fit.voxel_bias_factor = self.voxel_bias_factor;
        settings
    }

    fn edge(&self) -> EdgeSettings {
        EdgeSettings {
            trolley_id: "t1".into(),
            max_views: 0,
            capture_time_s: self.capture_time_s,
            segment_done_utility: glasshouse_nbv::PlannerConfig::default().utility_threshold,
        }
    }

    fn sim(&self) -> SimTrolleySettings {
        let size = (self.width, self.height);
        SimTrolleySettings {
            world: self.world,
            ..SimTrolleySettings::new(self.scenario, self.seed, size, self.segment_length_m)
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
    /// Metrics of the fitted estimates: their centres and solid volumes against the bodies'
    /// own centres and volumes (their boxes for the covered volume).
    pub fitted: Metrics,
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
    /// Ranked views the arm could not reach, summed over frames.
    pub unreachable_views: u64,
    /// Frames whose ranked list held no view the arm could reach.
    pub frames_without_reachable_view: u64,
    /// Sum of the compute times that entered the clock.
    pub compute_time_s: f64,
    /// The estimates at the end of the budget.
    pub fruits: Vec<FruitEstimate>,
    /// The surface each of `fruits` was fitted to (its cluster's voxel centres, world frame),
    /// in the same order; empty where the planner no longer holds the cluster.
    #[serde(skip)]
    pub fruit_surfaces: Vec<Vec<nalgebra::Point3<f64>>>,
    /// What became of every ROI cluster at the end of the budget (reported, or why not).
    #[serde(skip)]
    pub clusters: Vec<ClusterOutcome>,
    /// The scene's true fruits.
    pub truths: Vec<FruitTruth>,
    /// How the registration of every cloud ended (aligned, kept, skipped, rejected by reason).
    pub registration: glasshouse_pipeline::AlignmentCounts,
    /// The views planned on every frame, in order (what the planner service would publish).
    #[serde(skip)]
    pub plans: Vec<RankedViews>,
    /// The best view of every plan (the one the edge tries first), with when it was planned.
    #[serde(skip)]
    pub best_views: Vec<PlannedView>,
}

/// The best view of one plan ([`TrialResult::best_views`]): what the time to the next plan
/// went on (the motion to it, the capture there and the plan on that frame) and which list
/// it came from, to read where a planner's time goes and what each kind of view finds.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedView {
    /// Simulated clock when the plan's views were available, seconds.
    pub planned_at_s: f64,
    pub kind: glasshouse_nbv::ViewKind,
    /// The paper's utility (gain less the distance cost).
    pub utility: f64,
    pub gain: f64,
    /// Straight-line distance from the camera, metres.
    pub cost_m: f64,
    /// The robot's motion time to the view, when the planner knew it.
    pub motion_s: Option<f64>,
    /// True fruits matched by a box estimate when the plan's views were available.
    pub detected: usize,
}

impl TrialResult {
    /// The sample at the end of the budget.
    pub fn last(&self) -> Option<&Sample> {
        self.samples.last()
    }

    /// The first sampled second at which `share` of the true fruits are matched by box
    /// estimates; None when that never happens within the budget.
    pub fn time_to_detect_s(&self, share: f64) -> Option<u32> {
        let curve = self.samples.iter().map(|s| (s.time_s, s.boxes.detected));
        crate::metrics::time_to_detect_s(curve, self.fruits_total, share)
    }
}

/// The state the metrics see between two planning calls.
#[derive(Clone, Debug)]
struct Published {
    frames: u64,
    fruits: Vec<FruitEstimate>,
    boxes: Metrics,
    fitted: Metrics,
}

/// A trial in progress (see the module docs).
pub struct Trial<S: TrolleySource = SimTrolley> {
    config: TrialConfig,
    detector: DetectorConfig,
    /// What labels the points fruit: the HSI rule unless [`Trial::with_fruit_detector`].
    fruit_detector: Arc<dyn FruitDetector>,
    scene: Scene,
    source: S,
    planner: TrolleyPlanner,
    edge: EdgeNode,
    actions: VecDeque<EdgeAction>,
    frame: Option<RgbdFrame>,
    /// Capture time of the latest frame.
    clock_s: f64,
    compute_time_s: f64,
    views: u32,
    frames_without_reachable_view: u64,
    published: Published,
    samples: Vec<Sample>,
    plans: Vec<RankedViews>,
    best_views: Vec<PlannedView>,
    /// Whole seconds 0..=last_second are sampled.
    last_second: u32,
    /// The ROI cloud of the latest frame planned on.
    last_cloud: Option<RoiCloud>,
}

/// The id the trial's detector and planner sign their messages with.
const EVAL_ID: &str = "eval";

impl Trial<SimTrolley> {
    /// A trial on the scene's simulated trolley.
    pub fn new(config: TrialConfig) -> Result<Self, EvalError> {
        config.validate()?;
        Self::with_source(config, SimTrolley::new(config.sim())?)
    }
}

impl<S: TrolleySource> Trial<S> {
    /// A trial whose frames and motions come from `source` (ground truth from the config's scene).
    pub fn with_source(config: TrialConfig, source: S) -> Result<Self, EvalError> {
        config.validate()?;
        let planning = config.planning();
        let scene = Scene::generate_with(config.scenario, config.seed, &config.world.scene);
        let empty = Metrics::empty(scene.fruits(), planning.resolution_m);
        // One process on a simulated clock: boot epoch 0, and the one planner owns the trolley.
        let mut edge = EdgeNode::new(config.edge(), 0);
        edge.handle(EdgeInput::PlannerJoined(EVAL_ID.into()));
        Ok(Self {
            detector: DetectorConfig {
                voxel_size_m: planning.resolution_m,
                ..DetectorConfig::default()
            },
            fruit_detector: Arc::new(HsiVotes::default()),
            planner: TrolleyPlanner::new(planning)?,
            actions: edge.handle(EdgeInput::Start).into(),
            edge,
            scene,
            source,
            frame: None,
            clock_s: 0.0,
            compute_time_s: 0.0,
            views: 0,
            frames_without_reachable_view: 0,
            published: Published {
                frames: 0,
                fruits: Vec::new(),
                boxes: empty,
                fitted: empty,
            },
            samples: Vec::new(),
            plans: Vec::new(),
            best_views: Vec::new(),
            last_second: config.budget_s.floor() as u32,
            last_cloud: None,
            config,
        })
    }

    /// The same trial with its points labelled by `detector` (a learned model, say).
    pub fn with_fruit_detector(mut self, detector: Arc<dyn FruitDetector>) -> Self {
        self.fruit_detector = detector;
        self
    }

    /// The same trial starting from `prior` instead of an empty map (a revisit: the previous
    /// visit's map made into a prior, [`glasshouse_roimap::RoiMap::prior`]).
    pub fn with_prior(mut self, prior: glasshouse_roimap::RoiMap) -> Result<Self, EvalError> {
        self.planner = TrolleyPlanner::on_prior(self.config.planning(), prior)?;
        Ok(self)
    }

    /// The ROI cloud of the latest frame planned on, taken (a bench replays the stream).
    pub fn take_last_cloud(&mut self) -> Option<RoiCloud> {
        self.last_cloud.take()
    }

    /// The trolley's workspace and arm, as its edge announces them.
    pub fn info(&self) -> TrolleyInfo {
        self.source.info()
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The planner's state: its map, settings and the trolley's latest info.
    pub fn planner(&self) -> &TrolleyPlanner {
        &self.planner
    }

    /// The camera pose now.
    pub fn world_from_camera(&self) -> nalgebra::Isometry3<f64> {
        self.source.arm_state(false, 0).world_from_camera
    }

    /// The views planned on every frame so far, in order.
    pub fn plans(&self) -> &[RankedViews] {
        &self.plans
    }

    /// The fruits of the latest frame whose estimates are available.
    pub fn fruits(&self) -> &[FruitEstimate] {
        &self.published.fruits
    }

    /// The latest frame sequence.
    pub fn frame_seq(&self) -> u64 {
        self.edge.frame_seq()
    }

    /// Capture time of the latest frame (simulated seconds).
    pub fn clock_s(&self) -> f64 {
        self.clock_s
    }

    /// Planner compute charged to the clock so far, seconds.
    pub fn compute_time_s(&self) -> f64 {
        self.compute_time_s
    }

    pub fn is_done(&self) -> bool {
        self.clock_s > self.config.budget_s || self.edge.is_done()
    }

    /// Samples whole seconds before `until_s` (and not past the budget) with the published state.
    fn sample_until(&mut self, until_s: f64) {
        while let Some(next) = self.next_sample_second() {
            if f64::from(next) >= until_s {
                break;
            }
            let fruits = &self.published.fruits;
            let confidences: Vec<f64> =
                fruits.iter().map(|f| f.solid_or_box().confidence).collect();
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

    /// One frame of the loop: the edge's actions up to and including the plan on its next frame.
    /// Returns false once the budget is spent or the edge stopped (the remaining seconds are then
    /// sampled).
    pub fn step(&mut self) -> Result<bool, EvalError> {
        while let Some(action) = self.actions.pop_front() {
            let input = match action {
                EdgeAction::Capture { frame_seq } => self.capture(frame_seq)?,
                EdgeAction::Announce { frame_seq, .. } => match self.plan_on(frame_seq)? {
                    Some(views) => {
                        let header = Header {
                            trolley_id: "t1".into(),
                            source_id: EVAL_ID.into(),
                            ..Header::default()
                        };
                        self.feed(EdgeInput::Views {
                            sender: EVAL_ID.into(),
                            header,
                            views,
                        });
                        return Ok(true);
                    }
                    None => None,
                },
                EdgeAction::Execute { goals } => {
                    Some(EdgeInput::Executed(self.source.execute(&goals)))
                }
                EdgeAction::MoveToNextSegment => {
                    Some(EdgeInput::SegmentMoved(self.source.next_segment()))
                }
                EdgeAction::Report(event) => {
                    self.count(&event);
                    None
                }
                EdgeAction::Stop => None,
                EdgeAction::AwaitViews
                | EdgeAction::PublishStatus { .. }
                | EdgeAction::PublishArmMoving { .. } => None,
            };
            if let Some(input) = input {
                self.feed(input);
            }
            if self.is_done() {
                break;
            }
        }
        self.sample_until(f64::INFINITY);
        Ok(false)
    }

    fn feed(&mut self, input: EdgeInput) {
        let actions = self.edge.handle(input);
        self.actions.extend(actions);
    }

    fn count(&mut self, event: &EdgeEvent) {
        match event {
            EdgeEvent::ViewDone { .. } => self.views += 1,
            EdgeEvent::NoReachableView { .. } => self.frames_without_reachable_view += 1,
            _ => {}
        }
    }

    /// The capture at the edge's clock plus the compute time so far; none past the budget.
    fn capture(&mut self, frame_seq: u64) -> Result<Option<EdgeInput>, EvalError> {
        self.clock_s = self.edge.sim_time_s() + self.compute_time_s;
        if self.is_done() {
            return Ok(None);
        }
        self.frame = self
            .source
            .capture(frame_seq)
            .map_err(EvalError::CaptureFailed)?;
        Ok(Some(EdgeInput::Captured {
            frame: self.frame.is_some(),
        }))
    }

    /// The detector's and the planner's work on frame `frame_seq`; the views, or None when the
    /// budget ends before they are available.
    fn plan_on(&mut self, frame_seq: u64) -> Result<Option<RankedViews>, EvalError> {
        let Some(frame) = self.frame.take() else {
            return Ok(None);
        };
        let frame_id = FrameId::new(0, frame_seq);
        let cloud = detect_frame_with(
            &frame,
            frame_id,
            EVAL_ID,
            &self.detector,
            self.fruit_detector.as_ref(),
        )?;
        let started = Instant::now();
        self.planner.set_info(self.source.info())?;
        self.planner.integrate(&cloud, 0)?;
        let plan = self.planner.plan(&frame.world_from_camera, frame_seq)?;
        let compute_s = match self.config.compute_time {
            ComputeTime::Fixed { ms } => ms / 1e3,
            ComputeTime::Measured => started.elapsed().as_secs_f64(),
        };
        let views = plan
            .as_ref()
            .map(|p| ranked_views(p, frame_id, (compute_s * 1e3) as f32, EVAL_ID));
        self.compute_time_s += compute_s;
        let available_s = self.clock_s + compute_s;
        // Seconds before the new estimates exist hold the previous ones.
        self.sample_until(available_s);
        if available_s > self.config.budget_s {
            self.clock_s = available_s;
            return Ok(None);
        }
        self.publish(frame_seq);
        if let Some(best) = plan.as_ref().and_then(|p| p.views.first()) {
            self.best_views.push(PlannedView {
                planned_at_s: available_s,
                kind: best.kind,
                utility: best.utility,
                gain: best.gain,
                cost_m: best.cost_m,
                motion_s: best.motion_s,
                detected: self.published.boxes.detected,
            });
        }
        self.last_cloud = Some(cloud);
        if let Some(views) = &views {
            self.plans.push(views.clone());
        }
        Ok(views)
    }

    /// The fruits of the latest frame become what the metrics see.
    fn publish(&mut self, frame_seq: u64) {
        let fruits = self.planner.fruits();
        let truths = self.scene.fruits();
        let res = self.planner.settings().resolution_m;
        self.published = Published {
            frames: frame_seq,
            boxes: evaluate(&fruits, truths, res),
            fitted: evaluate_against(&fruits, truths, res, TruthMeasure::Body),
            fruits,
        };
    }

    /// Runs to the end of the budget; `progress` gets the simulated clock after every step.
    pub fn run(self, progress: impl FnMut(f64)) -> Result<TrialResult, EvalError> {
        Ok(self.run_keeping_map(progress)?.0)
    }

    /// [`Trial::run`], and the planner's map at the end (a season's next visit starts from it).
    pub fn run_keeping_map(
        mut self,
        mut progress: impl FnMut(f64),
    ) -> Result<(TrialResult, glasshouse_roimap::RoiMap), EvalError> {
        while self.step()? {
            progress(self.clock_s.min(self.config.budget_s));
        }
        progress(self.config.budget_s);
        let clusters = self.planner.cluster_outcomes();
        let ids: Vec<u32> = self.published.fruits.iter().map(|f| f.id).collect();
        let fruit_surfaces = self.planner.fruit_voxel_centres(&ids);
        let registration = *self.planner.alignment_counts();
        let result = TrialResult {
            config: self.config,
            fruits_total: self.scene.fruits().len(),
            samples: self.samples,
            views: self.views,
            frames: self.published.frames,
            unreachable_views: u64::from(self.edge.status().unreachable_views),
            frames_without_reachable_view: self.frames_without_reachable_view,
            compute_time_s: self.compute_time_s,
            fruits: self.published.fruits,
            fruit_surfaces,
            clusters,
            truths: self.scene.fruits().to_vec(),
            registration,
            plans: self.plans,
            best_views: self.best_views,
        };
        Ok((result, self.planner.into_map()))
    }
}

/// Runs one trial on the scene's simulated trolley; `progress` as in [`Trial::run`].
pub fn run_trial(config: TrialConfig, progress: impl FnMut(f64)) -> Result<TrialResult, EvalError> {
    Trial::new(config)?.run(progress)
}

/// [`run_trial`] with the points labelled by `detector`.
pub fn run_trial_with(
    config: TrialConfig,
    detector: Arc<dyn FruitDetector>,
    progress: impl FnMut(f64),
) -> Result<TrialResult, EvalError> {
    Trial::new(config)?
        .with_fruit_detector(detector)
        .run(progress)
}

#[cfg(test)]
mod tests;
