//! Planning: one trolley's map, fruit tracker, fits and next best views ([`TrolleyPlanner`]),
//! with the settings and seeds the planner service and the experiments share.

use std::borrow::Cow;

use glasshouse_arm::Robot;
use glasshouse_nbv::evidence::{interior_holds, ClusterShape, Interior, Verdict};
use glasshouse_nbv::fit::{FitConfig, FruitSolid};
use glasshouse_nbv::season::SeasonTracker;
use glasshouse_nbv::split::fragments;
use glasshouse_nbv::{
    plan_views, FruitEstimate, FruitTracker, Method, MotionTime, Plan, PlanError, PlannerConfig,
    PlanningContext, ReachPredicate,
};
use glasshouse_proto::{
    FrameId, HandEye, HandEyeScan, MapSnapshot, MapUpdate, RankedView, RankedViews, RoiCloud,
    TrackedFruit, TrolleyInfo, ViewKind, VoxelChange, VoxelState,
};
use glasshouse_register::{
    align_scan, corrected_points, Alignment, AlignmentCounts, HandEyeEstimator, HandEyeSettings,
    HandEyeState, KeyScan, RegisterSettings, ScanInWorld, Surfel,
};
use glasshouse_roimap::{
    Clusters, MapConfig, MapError, Occupancy, RoiCluster, RoiMap, Voxel, VoxelKey,
};
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use crate::colour::FruitColours;
use crate::fits::{FitCache, SplitCache};
use crate::published::PublishedSolid;
use crate::{FrameOrder, FrameVerdict, ReachFilter};

/// Why a planning step failed; the trolley's state is left as it was before the step.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum PlanningError {
    #[error("invalid planning settings: {0}")]
    Settings(String),
    #[error("cloud rejected by the map: {0}")]
    Map(#[from] MapError),
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error("unusable map snapshot: {0}")]
    Snapshot(String),
}

/// What the planner does with each trolley; the planner service's settings file and the
/// experiments both start from [`PlanningSettings::default`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlanningSettings {
    pub method: Method,
    /// Plans are seeded from this and the frame sequence ([`plan_seed`]).
    pub seed: u64,
    pub resolution_m: f64,
    /// Rays are integrated up to this range (points further away free the ray only).
    pub max_range_m: f64,
    /// A cloud's points beyond `max_range_m` free one ray per voxel at the range instead of one
    /// each (`MapConfig::merge_far_rays`; on by default): more than half of a row's points lie
    /// beyond it, and their rays are the longest. Points within the range, so every occupied
    /// and ROI voxel, are unaffected; the free voxels are 99 % the same (docs/fleet.md).
    pub merge_far_rays: bool,
    /// ROI clusters smaller than this are not fruits.
    pub min_cluster_voxels: usize,
    /// The whole-fruit ellipsoid fit published with every fruit.
    pub fit: FitConfig,
    /// Threads that score candidates (0: one per core); any count gives the same plan.
    pub scoring_threads: usize,
    /// Threads that cast a cloud's rays into the map and search the hand-eye estimate's
    /// matches (0: one per core); any count gives the same map, voxel for voxel, and the same
    /// estimate, bit for bit.
    pub insert_threads: usize,
    /// ROI targets nearer the camera drawn more often (weight `exp(−distance / this)`, metres;
    /// 0: uniformly, as the paper).
    pub roi_target_near_m: f64,
    /// Threads that split and fit the clusters a cloud changed (0: one per core); any count
    /// gives the same fruits.
    pub fit_threads: usize,
    /// How a cloud's detections enter the ROI map.
    pub roi_evidence: RoiEvidence,
    /// Which ROI voxels ROI-targeted sampling aims at.
    pub roi_targets: RoiTargets,
    /// Each cloud is aligned to the map before it goes in ([`align_scan`]); a cloud whose
    /// alignment fails the checks is not inserted. On by default: in a perfect world the
    /// corrections found are below what the map can tell and are not applied.
    pub registration: RegisterSettings,
    /// The trolley's hand-eye calibration error, estimated across its scans and undone before
    /// each scan is registered and inserted ([`HandEyeEstimator`]).
    pub hand_eye: HandEyeSettings,
    /// On a revisit, ROI-targeted sampling also aims at the previous visit's fruit voxels no
    /// scan has touched and no fruit found again covers ([`TrolleyPlanner::remembered_fruit`]).
    pub aim_at_remembered_fruit: bool,
    /// Utility lost per second the trolley's robot takes to reach a view, by which the views
    /// of the chosen list are ranked (the threshold and the choice between the ROI and the
    /// exploration list stay the paper's). 0: the paper's ranking, by utility alone. Known
    /// only with the trolley's robot (`TrolleyInfo::robot_json`): the arm and mount motion
    /// from where the camera is, placed as the edge places it.
    pub cost_weight_per_s: f64,
    /// An ROI cluster whose shape says it is not a fruit (flat, thin or too small) once scans
    /// from this many directions have hit it is settled clutter: ROI-targeted sampling stops
    /// aiming at the ROI frontier beside it (a red leaf's back is never seen, so its frontier
    /// would draw views for ever). 0 (the default): every cluster stays a target, as in the
    /// paper; 3 saved Ours 2 s to 95 % of the fruits on the tuning seeds, within their spread
    /// (docs/results.md, "Settled clutter").
    pub clutter_settles_after_views: u32,
    /// An ROI cluster the fruit evidence takes for a fruit, once scans from this many distinct
    /// directions have hit it, is settled the same way: its hidden back (pressed against a leaf
    /// or the stem) no longer draws ROI-targeted views, so the search moves on to fruit not yet
    /// found. 0 (the default): found fruit stay targets, as in the paper; 4 was 11 s sooner to
    /// 95 % of the fruits on the tuning seeds and 11 s later on the report seeds
    /// (docs/results.md, "Settled fruit").
    pub fruit_settles_after_views: u32,
    /// Once this many clouds in a row have brought no new fruit-shaped cluster (the most seen
    /// at once has not grown), a plan takes the exploration list whenever one of its views
    /// beats the threshold ([`PlanningContext::roi_stalled`]): the ROI targets left are then
    /// mostly the never-seen backs of found fruit and red clutter, and the fruit not found yet
    /// lie where no ROI target points. 0 (the default): the paper's choice. The count is the
    /// planner's own and starts again on a copy made from a snapshot or the store (a takeover,
    /// a restart), so a new owner plans as the paper until it has counted anew.
    pub explore_after_fruitless_clouds: u32,
    /// Tries of ROI-targeted sampling drawn until its 100 candidates survive the workspace,
    /// occlusion and reach checks ([`PlannerConfig::roi_tries`]; 0: the paper's 100 tries).
    pub roi_tries: usize,
    /// A voxel above this occupancy log-odds between an ROI target and a camera drops the
    /// candidate as occluded ([`PlannerConfig::occlusion_occupancy_logodds`]; the paper's
    /// p > 0.6, which one hit passes).
    pub occlusion_occupancy_logodds: f32,
}

/// Which ROI voxels ROI-targeted sampling aims at (their free neighbours next to unknown space).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RoiTargets {
    /// Every ROI voxel (the paper).
    Every,
    /// ROI voxels with an ROI face neighbour: fruit surfaces are patches, while the lone ROI
    /// voxels a noisy detector leaves on leaves would draw views to nothing. Which voxels are
    /// ROI, and so the fruits, is unchanged.
    #[default]
    Patches,
}

impl std::str::FromStr for RoiTargets {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "every" => Ok(Self::Every),
            "patches" => Ok(Self::Patches),
            _ => Err(format!("ROI targets must be every or patches, got {s:?}")),
        }
    }
}

impl std::fmt::Display for RoiTargets {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Every => "every",
            Self::Patches => "patches",
        })
    }
}

/// How a cloud's detections enter the ROI map.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RoiEvidence {
    /// Each point's ROI label at full strength, ±[`ROI_EVIDENCE_LOGODDS`]. The detector's
    /// confidence has already weighted every pixel in the voxel's vote that set the label.
    #[default]
    Labels,
    /// Each point's confidence as its own log-odds, capped at the labels' strength
    /// ([`roi_evidence_logodds`]): split votes count little. Slower to fill in fruit edges seen
    /// by few pixels (docs/results.md, "ROI evidence").
    Confidence,
}

impl std::str::FromStr for RoiEvidence {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "labels" => Ok(Self::Labels),
            "confidence" => Ok(Self::Confidence),
            _ => Err(format!(
                "ROI evidence must be labels or confidence, got {s:?}"
            )),
        }
    }
}

impl std::fmt::Display for RoiEvidence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Labels => "labels",
            Self::Confidence => "confidence",
        })
    }
}

impl Default for PlanningSettings {
    fn default() -> Self {
        Self {
            method: Method::OursUu,
            seed: 1,
            resolution_m: 0.01,
            max_range_m: 2.0,
            merge_far_rays: true,
            min_cluster_voxels: 10,
            fit: FitConfig::default(),
            scoring_threads: 0,
            insert_threads: 1,
            fit_threads: 1,
            roi_target_near_m: 0.0,
            roi_evidence: RoiEvidence::Labels,
            roi_targets: RoiTargets::default(),
            registration: RegisterSettings::default(),
            hand_eye: HandEyeSettings::default(),
            aim_at_remembered_fruit: true,
            cost_weight_per_s: DEFAULT_COST_WEIGHT_PER_S,
            clutter_settles_after_views: DEFAULT_CLUTTER_SETTLES_AFTER_VIEWS,
            fruit_settles_after_views: DEFAULT_FRUIT_SETTLES_AFTER_VIEWS,
            explore_after_fruitless_clouds: DEFAULT_EXPLORE_AFTER_FRUITLESS_CLOUDS,
            roi_tries: DEFAULT_ROI_TRIES,
            occlusion_occupancy_logodds: PlannerConfig::default().occlusion_occupancy_logodds,
        }
    }
}

/// `threads`, or one per core for 0.
fn threads_or_cores(threads: usize) -> usize {
    match threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    }
}

/// [`PlanningSettings::clutter_settles_after_views`] by default: off.
pub const DEFAULT_CLUTTER_SETTLES_AFTER_VIEWS: u32 = 0;
/// [`PlanningSettings::fruit_settles_after_views`] by default: off.
pub const DEFAULT_FRUIT_SETTLES_AFTER_VIEWS: u32 = 0;
/// [`PlanningSettings::explore_after_fruitless_clouds`] by default: off.
pub const DEFAULT_EXPLORE_AFTER_FRUITLESS_CLOUDS: u32 = 0;
/// [`PlanningSettings::roi_tries`] by default: the paper's.
pub const DEFAULT_ROI_TRIES: usize = 0;

impl PlanningSettings {
    pub fn validate(&self) -> Result<(), PlanningError> {
        if !(self.max_range_m.is_finite() && self.max_range_m > 0.0) {
            return Err(PlanningError::Settings(format!(
                "max range must be finite and > 0, got {}",
                self.max_range_m
            )));
        }
        self.map_config().validate()?;
        self.planner_config().validate()?;
        let registration = self.registration.validate();
        registration.map_err(|e| PlanningError::Settings(e.to_string()))?;
        let hand_eye = self.hand_eye.validate();
        hand_eye.map_err(|e| PlanningError::Settings(e.to_string()))?;
        self.fit
            .evidence
            .body
            .validate()
            .map_err(PlanningError::Settings)?;
        let factor = self.fit.voxel_bias_factor;
        if !(factor.is_finite() && (0.0..=1.0).contains(&factor)) {
            return Err(PlanningError::Settings(format!(
                "fit.voxel_bias_factor must be in [0, 1], got {factor}"
            )));
        }
        for (name, threads) in [
            ("insert_threads", self.insert_threads),
            ("fit_threads", self.fit_threads),
        ] {
            if threads > 64 {
                return Err(PlanningError::Settings(format!(
                    "{name} must be <= 64 (0 = one per core), got {threads}"
                )));
            }
        }
        Ok(())
    }

    pub fn map_config(&self) -> MapConfig {
        MapConfig {
            resolution_m: self.resolution_m,
            max_range_m: Some(self.max_range_m),
            merge_far_rays: self.merge_far_rays,
            // A symmetric ROI sensor model: a non-fruit label is as strong evidence as a fruit
            // label, so sporadic false labels (a noisy detector) fade instead of adding up to
            // fruit; two more fruit than non-fruit labels still make an ROI voxel.
            roi_miss_logodds: -ROI_EVIDENCE_LOGODDS,
            roi_hit_logodds: ROI_EVIDENCE_LOGODDS,
            roi_target_needs_neighbour: self.roi_targets == RoiTargets::Patches,
            ..MapConfig::default()
        }
    }

    pub fn planner_config(&self) -> PlannerConfig {
        PlannerConfig {
            method: self.method,
            scoring_threads: self.scoring_threads,
            cost_weight_per_s: self.cost_weight_per_s,
            roi_target_near_m: self.roi_target_near_m,
            roi_tries: self.roi_tries,
            occlusion_occupancy_logodds: self.occlusion_occupancy_logodds,
            ..PlannerConfig::default()
        }
    }
}

/// The ranking's cost of the robot's motion time, per second: a view 1 s further away must
/// see 1.5 more of the mean ray's share of unknown voxels (gain ≤ 1). Chosen on scenario 2's
/// tuning seeds 101-108 (0.2-4 tried; 1.5-3 gave the same recall), checked on 109-116
/// (docs/results.md, "Views ranked by the time they take").
pub const DEFAULT_COST_WEIGHT_PER_S: f64 = 1.5;

/// ROI log-odds of one fruit or non-fruit label: a detector right 70 % of the time.
pub const ROI_EVIDENCE_LOGODDS: f32 = 0.8473;

/// The ROI evidence of each point of a cloud that carries detection confidences: the
/// confidence's own log-odds, `ln(c / (1 − c))`, capped at ±[`ROI_EVIDENCE_LOGODDS`]. A voxel seen
/// by many pixels that agree counts fully, a split vote (a few pixels, or a noisy detector's
/// mixed labels) only a little; so fruit needs consistent evidence over several views before it
/// is ROI. `None` for clouds without confidences (a detector whose labels are certain), which
/// the map takes as full-strength labels.
pub fn roi_evidence_logodds(cloud: &RoiCloud) -> Option<Vec<f32>> {
    if cloud.roi_confidence.is_empty() {
        return None;
    }
    let table = confidence_logodds_table();
    Some(
        cloud
            .roi_confidence
            .iter()
            .map(|&c| table[usize::from(c)])
            .collect(),
    )
}

/// [`roi_evidence_logodds`] of each confidence byte `c` (confidence `c / 255`).
fn confidence_logodds_table() -> &'static [f32; 256] {
    static TABLE: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        std::array::from_fn(|c| {
            let p = c as f64 / 255.0;
            // p = 0 and 1 give ∓infinity, which the cap turns into the full label.
            let logodds = (p / (1.0 - p)).ln() as f32;
            logodds.clamp(-ROI_EVIDENCE_LOGODDS, ROI_EVIDENCE_LOGODDS)
        })
    })
}

/// Seed of the plan made on frame `frame_seq` by a planner seeded with `seed`.
pub fn plan_seed(seed: u64, frame_seq: u64) -> u64 {
    seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(frame_seq)
}

/// The ranked views of a plan on frame `based_on` as they travel on the bus.
pub fn ranked_views(
    plan: &Plan,
    based_on: FrameId,
    planning_time_ms: f32,
    pid: &str,
) -> RankedViews {
    let views = plan.views.iter().map(|v| RankedView {
        world_from_camera: v.world_from_camera,
        utility: v.utility as f32,
        gain: v.gain as f32,
        cost_m: v.cost_m as f32,
        kind: match v.kind {
            glasshouse_nbv::ViewKind::Roi => ViewKind::Roi,
            glasshouse_nbv::ViewKind::Exploration => ViewKind::Exploration,
        },
    });
    RankedViews {
        views: views.collect(),
        based_on_seq: based_on.seq,
        based_on_epoch_ns: based_on.epoch_ns,
        planning_time_ms,
        planner_id: pid.to_owned(),
        // The planner service sets its ownership term; the experiments run without fencing.
        owner_epoch: glasshouse_fleet::NO_EPOCH,
    }
}

/// One trolley's planning state: its ROI map, the fruit tracker with the latest clusters, the
/// trolley's info, and what the map changes already published.
#[derive(Clone)]
pub struct TrolleyPlanner {
    pub(crate) settings: PlanningSettings,
    pub(crate) map: RoiMap,
    tracker: FruitTracker,
    pub(crate) info: Option<TrolleyInfo>,
    /// Views the arm cannot reach are never proposed (once the trolley's robot is known).
    pub(crate) reach: Option<ReachFilter>,
    /// Which frames the map takes (the last one integrated, see [`FrameOrder`]).
    order: FrameOrder,
    /// The map's ROI clusters, regrown only where a scan changed ROI voxels.
    roi_clusters: Clusters,
    /// The touching-fruit splits of the ROI clusters, kept while what they read is unchanged.
    split_cache: SplitCache,
    /// The fruit clusters: the ROI clusters with touching fruits split apart.
    clusters: Vec<RoiCluster>,
    estimates: Vec<FruitEstimate>,
    /// Each tracked fruit's colour samples (its estimate's mean colour).
    colours: FruitColours,
    /// The fitted shape of each cluster, and the fits kept between frames.
    fits: Vec<FruitSolid>,
    fit_cache: FitCache,
    /// The clusters changed since the fits were last made.
    fits_stale: bool,
    /// Clusters refitted by the last fit update (the others kept their fits).
    last_refits: usize,
    map_seq: u64,
    /// Voxels last published as occupied or ROI: MapUpdate carries solid voxels and the ones
    /// that stopped being solid, not every newly freed voxel (those would dominate the traffic).
    pub(crate) published_solid: PublishedSolid,
    /// The next map update replaces what a dashboard holds (`MapUpdate::full`): set when a new
    /// visit starts, whose map no longer holds the last visit's solid voxels.
    pub(crate) publish_full: bool,
    /// The registration of the last cloud taken, and how every registration so far ended.
    last_alignment: Option<Alignment>,
    pub(crate) alignment_counts: AlignmentCounts,
    /// The hand-eye error estimated from the clouds taken so far.
    pub(crate) hand_eye: HandEyeEstimator,
    /// The hand-eye correction applied to the last cloud registered (world frame).
    last_hand_eye_correction: Option<Isometry3<f64>>,
    /// The trolley's visit of its row this copy is on, and the fruits of the visits before it.
    pub(crate) visit: u32,
    pub(crate) season: SeasonTracker,
    /// The prior's fruit hints a plan aims at until a scan touches them (empty on a first visit).
    remembered_fruit: Vec<VoxelKey>,
    /// The voxels, sorted, of the latest clusters that are settled (clutter and found fruit)
    /// ([`TrolleyPlanner::track`]).
    settled_voxels: Vec<VoxelKey>,
    /// The most fruit-shaped clusters seen at once this visit, and the clouds tracked since
    /// that number last grew ([`PlanningSettings::explore_after_fruitless_clouds`]).
    most_fruit_shaped: usize,
    fruitless_clouds: u32,
}

impl TrolleyPlanner {
    pub fn new(settings: PlanningSettings) -> Result<Self, PlanningError> {
        settings.validate()?;
        Ok(Self {
            map: RoiMap::new(settings.map_config())?,
            roi_clusters: Clusters::new(settings.min_cluster_voxels),
            split_cache: SplitCache::default(),
            hand_eye: HandEyeEstimator::new(settings.hand_eye.clone()),
            last_hand_eye_correction: None,
            settings,
            tracker: FruitTracker::default(),
            info: None,
            reach: None,
            order: FrameOrder::default(),
            clusters: Vec::new(),
            estimates: Vec::new(),
            colours: FruitColours::default(),
            fits: Vec::new(),
            fit_cache: FitCache::default(),
            fits_stale: false,
            last_refits: 0,
            map_seq: 0,
            published_solid: PublishedSolid::default(),
            publish_full: false,
            last_alignment: None,
            alignment_counts: AlignmentCounts::default(),
            visit: 0,
            season: SeasonTracker::default(),
            remembered_fruit: Vec::new(),
            settled_voxels: Vec::new(),
            most_fruit_shaped: 0,
            fruitless_clouds: 0,
        })
    }

    pub fn map(&self) -> &RoiMap {
        &self.map
    }

    pub fn settings(&self) -> &PlanningSettings {
        &self.settings
    }

    /// How the last cloud taken was registered to the map (None before the first).
    pub fn last_alignment(&self) -> Option<&Alignment> {
        self.last_alignment.as_ref()
    }

    /// How the registrations of the clouds taken so far ended (aligned, skipped, rejected by
    /// reason).
    pub fn alignment_counts(&self) -> &AlignmentCounts {
        &self.alignment_counts
    }

    /// The last frame integrated, if any.
    pub fn last_frame(&self) -> Option<FrameId> {
        self.order.last()
    }

    pub fn info(&self) -> Option<&TrolleyInfo> {
        self.info.as_ref()
    }

    /// The trolley's latest workspace and arm (TrolleyInfo); planning waits for the first one.
    /// Its robot switches the reach filter on; one whose reachability cannot be built is an
    /// error and leaves the filter off (the info itself is kept: the edge still checks every
    /// view).
    pub fn set_info(&mut self, info: TrolleyInfo) -> Result<(), PlanningError> {
        let same_robot = self.info.as_ref().map(|i| &i.robot) == Some(&info.robot);
        let robot = info.robot.as_deref().cloned();
        self.info = Some(info);
        if same_robot {
            return Ok(());
        }
        self.set_robot(robot)
    }

    /// Inserts the cloud into the map when [`FrameOrder`] takes its frame (each frame once: a
    /// re-announced frame comes back as the same cloud), then updates the ROI clusters and the
    /// fruit ids: [`TrolleyPlanner::insert`], [`TrolleyPlanner::cluster`] and
    /// [`TrolleyPlanner::track`] in turn. `now_ns` is the receiver's wall clock (0 where frames
    /// carry epoch 0, as in the experiments). Returns the verdict on the frame; a refused cloud
    /// changes nothing, and a cloud the map rejects leaves the map untouched.
    pub fn integrate(
        &mut self,
        cloud: &RoiCloud,
        now_ns: u64,
    ) -> Result<FrameVerdict, PlanningError> {
        let verdict = self.insert(cloud, now_ns)?;
        if !matches!(verdict, FrameVerdict::Refused(_)) {
            self.cluster();
            self.track();
        }
        Ok(verdict)
    }

    /// The map part of [`TrolleyPlanner::integrate`]: the cloud goes into the map when its frame
    /// is taken, aligned to the map first ([`TrolleyPlanner::last_alignment`]); a cloud whose
    /// alignment is rejected stays out ([`FrameVerdict::Misaligned`]). Unless the verdict is a
    /// refusal, [`TrolleyPlanner::cluster`] and [`TrolleyPlanner::track`] must follow (they are
    /// separate steps so that a service can time each).
    pub fn insert(&mut self, cloud: &RoiCloud, now_ns: u64) -> Result<FrameVerdict, PlanningError> {
        let frame = cloud.source_frame();
        let verdict = self.order.judge(frame, now_ns);
        if !verdict.integrates() {
            return Ok(verdict);
        }
        let Some(RegisteredScan { origin, points }) = self.register(cloud) else {
            // Judged once: a re-announce of the frame is a repeat, not a second registration.
            self.order.integrated(frame);
            return Ok(FrameVerdict::Misaligned);
        };
        let threads = threads_or_cores(self.settings.insert_threads);
        let evidence = match self.settings.roi_evidence {
            RoiEvidence::Labels => None,
            RoiEvidence::Confidence => roi_evidence_logodds(cloud),
        };
        match evidence {
            Some(evidence) => self
                .map
                .insert_scan_evidence(&origin, &points, &evidence, threads)?,
            None => self
                .map
                .insert_scan_threaded(&origin, &points, &cloud.roi, threads)?,
        };
        // Which fruit this view saw, from where: the fruit evidence's directions.
        self.note_view(&origin, &points, &cloud.roi);
        self.colours.note_cloud(&self.map, &points, cloud);
        let map = &self.map;
        self.remembered_fruit.retain(|&k| map.is_unobserved_hint(k));
        self.order.integrated(frame);
        Ok(verdict)
    }

    /// The cloud's sensor origin and points aligned to the map (as sent when the alignment was
    /// skipped or its correction not applied); None when the alignment was rejected.
    fn register<'c>(&mut self, cloud: &'c RoiCloud) -> Option<RegisteredScan<'c>> {
        let calibrated = self.undo_hand_eye_error(cloud);
        self.last_hand_eye_correction = calibrated.as_ref().map(|(c, _)| *c);
        let calibrated = calibrated.map(|(_, scan)| scan);
        let (origin, points) = match &calibrated {
            Some(scan) => (scan.origin, scan.points.as_ref()),
            None => (
                cloud.sensor_origin_in_world,
                cloud.points_in_world.as_slice(),
            ),
        };
        let scan = ScanInWorld {
            sensor_origin_in_world: &origin,
            points_in_world: points,
        };
        let alignment = align_scan(&self.map, scan, &self.settings.registration);
        self.alignment_counts.record(&alignment);
        let registered = match (alignment.inserts(), alignment.correction_to_apply()) {
            (false, _) => None,
            (true, None) => Some(calibrated.unwrap_or(RegisteredScan {
                origin,
                points: Cow::Borrowed(cloud.points_in_world.as_slice()),
            })),
            (true, Some(world_correction)) => Some(RegisteredScan {
                origin: world_correction * origin,
                points: Cow::Owned(corrected_points(world_correction, points)),
            }),
        };
        self.last_alignment = Some(alignment);
        registered
    }

    /// The cloud moved to where the hand-eye estimate says its camera really was, once the
    /// estimator (which takes the cloud first) has one; None when off or not yet estimated.
    fn undo_hand_eye_error<'c>(
        &mut self,
        cloud: &RoiCloud,
    ) -> Option<(Isometry3<f64>, RegisteredScan<'c>)> {
        if !self.settings.hand_eye.enabled {
            return None;
        }
        let world_from_camera = &cloud.world_from_camera;
        // The estimate's match search is part of the integration: it takes the insert's threads.
        let threads = threads_or_cores(self.settings.insert_threads);
        self.hand_eye
            .add_scan_threaded(world_from_camera, &cloud.points_in_world, threads);
        let world_correction = self.hand_eye.world_correction(world_from_camera)?;
        let scan = RegisteredScan {
            origin: world_correction * cloud.sensor_origin_in_world,
            points: Cow::Owned(corrected_points(&world_correction, &cloud.points_in_world)),
        };
        Some((world_correction, scan))
    }

    /// The hand-eye correction (world frame) applied to the last cloud registered; None when
    /// it went in without one.
    pub fn last_hand_eye_correction(&self) -> Option<&Isometry3<f64>> {
        self.last_hand_eye_correction.as_ref()
    }

    /// The hand-eye error estimated so far: the camera's true pose in the frame the trolley
    /// believes it in (identity while off).
    pub fn hand_eye(&self) -> &HandEyeEstimator {
        &self.hand_eye
    }

    /// The fruit clusters after an insert: the ROI clusters (regrown only where the scan changed
    /// ROI voxels), with touching fruits split apart.
    pub fn cluster(&mut self) {
        let min_voxels = self.settings.min_cluster_voxels;
        self.roi_clusters.update(&self.map);
        (self.clusters, _) = self.split_cache.update(
            &self.map,
            self.roi_clusters.iter(),
            min_voxels,
            &self.settings.fit,
            &mut self.fit_cache,
            threads_or_cores(self.settings.fit_threads),
        );
    }

    /// The fruit ids of the clusters after [`TrolleyPlanner::cluster`], with the view
    /// directions of the clouds noted since ([`TrolleyPlanner::note_view`]) and their colours.
    pub fn track(&mut self) {
        self.estimates = self.tracker.update(&self.clusters);
        self.colours.update(&self.clusters, &mut self.estimates);
        self.fits_stale = true;
        self.forget_found_again();
        self.settle_clusters();
        self.count_fruitless_clouds();
    }

    /// Whether the last cloud brought a new fruit-shaped cluster
    /// ([`PlanningSettings::explore_after_fruitless_clouds`]; nothing is computed while off).
    fn count_fruitless_clouds(&mut self) {
        if self.settings.explore_after_fruitless_clouds == 0 {
            return;
        }
        let evidence = self.settings.fit.evidence;
        let shapes = self.fit_cache.shapes(&self.map, &self.clusters);
        let fruit_shaped = shapes
            .iter()
            .filter(|s| s.verdict(&evidence).is_fruit())
            .count();
        if fruit_shaped > self.most_fruit_shaped {
            self.most_fruit_shaped = fruit_shaped;
            self.fruitless_clouds = 0;
        } else {
            self.fruitless_clouds = self.fruitless_clouds.saturating_add(1);
        }
    }

    /// Whether the ROI views have stopped finding fruit: as many clouds in a row as
    /// [`PlanningSettings::explore_after_fruitless_clouds`] brought no new fruit-shaped cluster.
    pub fn roi_stalled(&self) -> bool {
        let after = self.settings.explore_after_fruitless_clouds;
        after > 0 && self.fruitless_clouds >= after
    }

    /// The voxels of the latest clusters that are settled, sorted: clutter
    /// ([`PlanningSettings::clutter_settles_after_views`]) and found fruit
    /// ([`PlanningSettings::fruit_settles_after_views`]).
    fn settle_clusters(&mut self) {
        self.settled_voxels.clear();
        let clutter_after = self.settings.clutter_settles_after_views;
        let fruit_after = self.settings.fruit_settles_after_views;
        if clutter_after == 0 && fruit_after == 0 {
            return;
        }
        let evidence = self.settings.fit.evidence;
        let shapes = self.fit_cache.shapes(&self.map, &self.clusters);
        let clusters = self.clusters.iter().zip(&self.estimates).zip(&shapes);
        for ((cluster, estimate), shape) in clusters {
            let after = match shape.verdict(&evidence) {
                Verdict::Flat | Verdict::Thin | Verdict::TooSmall => clutter_after,
                Verdict::Fruit => fruit_after,
                Verdict::TooLarge | Verdict::Sheet => 0,
            };
            if after > 0 && estimate.view_directions >= after {
                self.settled_voxels.extend_from_slice(&cluster.voxels);
            }
        }
        self.settled_voxels.sort_unstable();
    }

    /// Remembered fruit voxels inside a cluster's box stop being targets: that fruit is found
    /// again, and as it grew its new surface hides the old one (no scan would ever touch those
    /// voxels); the ROI frontier aims at the fruit from now on. (Boxes grown by 1 or 3 cm
    /// were no better on the tuning seeds, docs/seasons.md.)
    fn forget_found_again(&mut self) {
        if self.remembered_fruit.is_empty() {
            return;
        }
        let (clusters, map) = (&self.clusters, &self.map);
        self.remembered_fruit.retain(|&k| {
            let p = map.centre_of(k);
            !clusters
                .iter()
                .any(|c| (0..3).all(|i| c.min[i] <= p[i] && p[i] <= c.max[i]))
        });
    }

    /// Notes where a cloud the map took was taken from and which voxels its ROI points fell in
    /// (the origin and points as inserted, after registration): at the next
    /// [`TrolleyPlanner::track`], each fruit it hit counts its direction
    /// ([`FruitTracker::note_scan`]), and fruits seen from more sides are reported with more
    /// confidence. Call it for every cloud inserted (from [`TrolleyPlanner::insert`]).
    pub fn note_view(
        &mut self,
        sensor_origin_in_world: &nalgebra::Point3<f64>,
        points_in_world: &[nalgebra::Point3<f32>],
        roi: &[bool],
    ) {
        let roi_points = points_in_world.iter().zip(roi).filter(|(_, r)| **r);
        let keys = roi_points.filter_map(|(p, _)| self.map.try_key_of(&p.cast()));
        self.tracker
            .note_scan(*sensor_origin_in_world, keys.collect());
    }

    /// The voxel centres (world frame) of the latest clusters whose fruits have the ids `ids`:
    /// the surface each fruit was fitted to; empty for an id no latest cluster carries.
    pub fn fruit_voxel_centres(&self, ids: &[u32]) -> Vec<Vec<nalgebra::Point3<f64>>> {
        ids.iter()
            .map(|id| {
                let Some(i) = self.estimates.iter().position(|e| e.id == *id) else {
                    return Vec::new();
                };
                let voxels = &self.clusters[i].voxels;
                voxels.iter().map(|k| self.map.centre_of(*k)).collect()
            })
            .collect()
    }

    /// Every fruit of the latest clusters with its fitted solid and, as its confidence, the
    /// evidence's that it is a fruit: the clusters [`TrolleyPlanner::cluster_outcomes`] reports.
    pub fn fruits(&mut self) -> Vec<FruitEstimate> {
        let outcomes = self.cluster_outcomes();
        outcomes
            .iter()
            .enumerate()
            .filter(|(_, outcome)| outcome.is_reported())
            .filter_map(|(i, outcome)| Some(self.record(i, outcome.fit.as_ref()?, outcome.body)))
            .collect()
    }

    /// What becomes of each latest cluster (same order): clusters whose shape says they are not
    /// fruit ([`glasshouse_nbv::evidence`]: flat, thin, too small or too large) are not fitted
    /// at all; clusters whose fitted solid hides nothing are sheets; clusters that are a second
    /// patch of a fruit another cluster reports are fragments ([`fragments`]); the rest are
    /// reported as fruit. Fits are made here, not on integration (a replica integrates without
    /// them), and only for the fruits whose voxels or surroundings changed since their last fit.
    pub fn cluster_outcomes(&mut self) -> Vec<ClusterOutcome> {
        let evidence_config = self.settings.fit.evidence;
        let shapes = self.fit_cache.shapes(&self.map, &self.clusters);
        let mut outcomes: Vec<ClusterOutcome> = self
            .clusters
            .iter()
            .zip(&shapes)
            .map(|(cluster, shape)| ClusterOutcome {
                centre: cluster.centre,
                voxels: cluster.voxels.len(),
                shape: *shape,
                verdict: shape.verdict(&evidence_config),
                fit: None,
                interior: None,
                fragment: false,
                body: false,
            })
            .collect();
        let shaped: Vec<usize> = (0..outcomes.len())
            .filter(|&i| outcomes[i].verdict.is_fruit())
            .collect();
        if self.fits_stale {
            let clusters = shaped.iter().map(|&i| &self.clusters[i]);
            let threads = threads_or_cores(self.settings.fit_threads);
            (self.fits, self.last_refits) =
                self.fit_cache
                    .update(&self.map, clusters, &self.settings.fit, threads);
            self.fits_stale = false;
        }
        for (&i, fitted) in shaped.iter().zip(&self.fits) {
            let interior = self.fit_cache.interior_of(&self.clusters[i]);
            let outcome = &mut outcomes[i];
            (outcome.fit, outcome.interior) = (Some(*fitted), interior);
            let holds = |inside| interior_holds(&inside, &outcome.shape, &evidence_config);
            if !interior.is_none_or(holds) {
                outcome.verdict = Verdict::Sheet;
            }
        }
        self.find_bodies(&mut outcomes);
        let (solid, fits): (Vec<usize>, Vec<FruitSolid>) = (0..outcomes.len())
            .filter(|&i| outcomes[i].verdict.is_fruit())
            .filter_map(|i| Some((i, outcomes[i].fit?)))
            .unzip();
        let counts: Vec<usize> = solid.iter().map(|&i| outcomes[i].voxels).collect();
        for (i, fragment) in solid.into_iter().zip(fragments(&fits, &counts)) {
            outcomes[i].fragment = fragment;
        }
        outcomes
    }

    /// Turned-away clusters (too small, flat, sheets) with a fruit's body under them
    /// ([`glasshouse_nbv::evidence::body`]) become fruit, the body's solid their fit.
    fn find_bodies(&mut self, outcomes: &mut [ClusterOutcome]) {
        if !self.settings.fit.evidence.enabled || !self.settings.fit.evidence.body.enabled {
            return;
        }
        let turned_away =
            |v: Verdict| matches!(v, Verdict::TooSmall | Verdict::Flat | Verdict::Sheet);
        let candidates: Vec<usize> = (0..outcomes.len())
            .filter(|&i| turned_away(outcomes[i].verdict))
            .collect();
        let clusters: Vec<&RoiCluster> = candidates.iter().map(|&i| &self.clusters[i]).collect();
        let threads = threads_or_cores(self.settings.fit_threads);
        let bodies = self
            .fit_cache
            .bodies(&self.map, &clusters, &self.settings.fit, threads);
        for (i, body) in candidates.into_iter().zip(bodies) {
            if let Some(fit) = body {
                let outcome = &mut outcomes[i];
                (outcome.verdict, outcome.fit, outcome.body) = (Verdict::Fruit, Some(fit), true);
                outcome.interior = None;
            }
        }
    }

    /// The fruit of cluster `i`, fitted `fitted` (the solid of the `body` under it, if found so),
    /// with its evidence's confidence.
    fn record(&self, i: usize, fitted: &FruitSolid, body: bool) -> FruitEstimate {
        use glasshouse_nbv::evidence::{ClusterEvidence, FruitEvidence};
        let (cluster, estimate) = (&self.clusters[i], &self.estimates[i]);
        let seen = match self.fit_cache.evidence_of(cluster) {
            Some(seen) => *seen,
            None => ClusterEvidence::of(&self.map, cluster),
        };
        let views = estimate.view_directions;
        // A body's solid is not the cluster's own fit: what it hides is read from the map.
        let interior = match self.fit_cache.interior_of(cluster).filter(|_| !body) {
            Some(inside) => inside,
            None => Interior::of_fruit(&self.map, fitted),
        };
        let config = &self.settings.fit.evidence;
        let evidence = FruitEvidence::judge(&seen, fitted, interior, views, config);
        FruitEstimate {
            confidence: evidence.confidence,
            solid: Some(*fitted),
            ..*estimate
        }
    }

    /// How many fruits the last [`TrolleyPlanner::fruits`] refitted; the others' surroundings had
    /// not changed.
    pub fn last_refits(&self) -> usize {
        self.last_refits
    }

    /// The next best views from the camera at `world_from_camera`, seeded for frame `frame_seq`;
    /// None until the trolley's info (its workspace) is known.
    pub fn plan(
        &self,
        world_from_camera: &Isometry3<f64>,
        frame_seq: u64,
    ) -> Result<Option<Plan>, PlanningError> {
        let Some(mut ctx) = self.context(world_from_camera) else {
            return Ok(None);
        };
        let map = &self.map;
        let reach = self.reach.as_ref();
        let accepts = move |pose: &Isometry3<f64>| reach.is_none_or(|r| r.accepts(map, pose));
        if reach.is_some() {
            ctx.reach = Some(&accepts as &ReachPredicate<'_>);
        }
        // The robot's pose is placed only when the ranking charges its time.
        let timed = reach.filter(|_| self.settings.cost_weight_per_s > 0.0);
        let from = timed.and_then(|r| Some((r, r.pose_guess(world_from_camera)?)));
        let motion_time = move |pose: &Isometry3<f64>| {
            let (reach, from) = from.as_ref()?;
            reach.motion_time_s(from, pose)
        };
        if from.is_some() {
            ctx.motion_time = Some(&motion_time as &MotionTime<'_>);
        }
        let seed = plan_seed(self.settings.seed, frame_seq);
        Ok(Some(plan_views(
            &ctx,
            &self.settings.planner_config(),
            seed,
        )?))
    }

    /// The trolley's arm and mount: from now on only views it can reach are proposed (`None`:
    /// any pose in the camera workspace).
    pub fn set_robot(&mut self, robot: Option<Robot>) -> Result<(), PlanningError> {
        if self.reach.as_ref().map(ReachFilter::robot) == robot.as_ref() {
            return Ok(());
        }
        self.reach = None;
        if let Some(robot) = robot {
            let filter = ReachFilter::for_robot(robot)
                .map_err(|e| PlanningError::Settings(format!("the trolley's robot: {e}")))?;
            self.reach = Some(filter);
        }
        Ok(())
    }

    /// Whether proposed views are filtered by the arm's reach.
    pub fn filters_reach(&self) -> bool {
        self.reach.is_some()
    }

    /// What a plan from `world_from_camera` looks at; None until the trolley's info is known.
    pub fn context(&self, world_from_camera: &Isometry3<f64>) -> Option<PlanningContext<'_>> {
        let info = self.info.as_ref()?;
        Some(PlanningContext {
            map: &self.map,
            world_from_camera: *world_from_camera,
            camera_workspace: info.camera_workspace,
            sampling_region: info.sampling_region,
            reach: None,
            motion_time: None,
            remembered_fruit: match self.settings.aim_at_remembered_fruit {
                true => &self.remembered_fruit,
                false => &[],
            },
            settled_voxels: &self.settled_voxels,
            roi_stalled: self.roi_stalled(),
        })
    }

    /// The solid voxels changed since the last call (and the ones that stopped being solid);
    /// the first after a new visit starts is `full`: every solid voxel of the visit's map.
    pub fn map_update(&mut self, based_on_seq: u64, pid: &str) -> MapUpdate {
        self.map_seq += 1;
        let mut voxels = Vec::new();
        let published_solid = &mut self.published_solid;
        self.map.drain_changed_blocks(|block| {
            // A changed voxel is news when it is solid now or was published solid: the rest
            // (nearly all of a scan's freed voxels) are never read.
            let (changed, solid) = (block.changed(), block.solid());
            let published = published_solid.cell(block.coord());
            let news: [u64; 8] = std::array::from_fn(|w| changed[w] & (solid[w] | published[w]));
            block.for_each(&news, |key, voxel, is_roi| {
                let change = voxel_change(key, voxel, is_roi);
                let was_solid = if change.state == VoxelState::Free {
                    published_solid.remove(key)
                } else {
                    published_solid.insert(key);
                    true
                };
                if was_solid {
                    voxels.push(change);
                }
            });
        });
        // Only the few kept voxels are sorted (by key, for a deterministic message).
        voxels.sort_unstable_by_key(|c| c.key);
        MapUpdate {
            resolution_m: self.settings.resolution_m as f32,
            map_seq: self.map_seq,
            based_on_seq,
            full: std::mem::take(&mut self.publish_full),
            voxels,
            planner_id: pid.to_owned(),
            registration: None,
            // Set by the planner service (its ownership term).
            owner_epoch: glasshouse_fleet::NO_EPOCH,
        }
    }

    /// The trolley's state for another planner (the reply to a snapshot query).
    pub fn snapshot(&self, tid: &str, pid: &str) -> Result<MapSnapshot, PlanningError> {
        let mut map = Vec::new();
        self.map
            .write_snapshot(&mut map)
            .map_err(|e| PlanningError::Snapshot(e.to_string()))?;
        Ok(self.snapshot_with_map(tid, pid, map))
    }

    /// The trolley's state as [`TrolleyPlanner::snapshot`] gives it, but with only the map's
    /// blocks changed after it had taken `base_scans` scans (a delta,
    /// [`RoiMap::write_delta`]): the answer to a standby copy that holds this copy's map as it
    /// was then ([`TrolleyPlanner::apply_delta`]).
    pub fn snapshot_delta(
        &self,
        tid: &str,
        pid: &str,
        base_scans: u64,
    ) -> Result<MapSnapshot, PlanningError> {
        let mut map = Vec::new();
        self.map
            .write_delta(base_scans, &mut map)
            .map_err(|e| PlanningError::Snapshot(e.to_string()))?;
        Ok(self.snapshot_with_map(tid, pid, map))
    }

    /// Whether a snapshot carries a delta of the map ([`TrolleyPlanner::snapshot_delta`]).
    pub fn is_delta(snapshot: &MapSnapshot) -> bool {
        RoiMap::is_delta(&snapshot.map)
    }

    /// Brings this copy to what a delta snapshot holds: its map takes the delta's blocks, and
    /// the fruit ids, frame mark, season and hand-eye estimate become the snapshot's, as
    /// [`TrolleyPlanner::from_snapshot`] makes them from a whole one; the trolley's info, reach
    /// filter and registration counts are kept. The delta must start from this copy's map (the
    /// same owner's, at its scan count); on an error nothing changes.
    pub fn apply_delta(&mut self, snapshot: &MapSnapshot) -> Result<(), PlanningError> {
        let empty =
            RoiMap::new(*self.map.config()).map_err(|e| PlanningError::Snapshot(e.to_string()))?;
        self.map
            .apply_delta(&snapshot.map)
            .map_err(|e| PlanningError::Snapshot(e.to_string()))?;
        let map = std::mem::replace(&mut self.map, empty);
        // The map passed the same settings check when this copy was made: this cannot fail.
        let restored = Self::from_map(self.settings.clone(), map, snapshot)?;
        self.adopt(restored);
        Ok(())
    }

    /// A snapshot of this copy's state around `map` (a whole map or a delta).
    fn snapshot_with_map(&self, tid: &str, pid: &str, map: Vec<u8>) -> MapSnapshot {
        let (tracked, next_fruit_id) = self.tracker.state();
        let tracked_fruits = tracked.into_iter().map(|(id, c)| TrackedFruit {
            id,
            centre_in_world: c.cast(),
            colour: self.colours.sum_of(id),
        });
        MapSnapshot {
            trolley_id: tid.to_owned(),
            planner_id: pid.to_owned(),
            based_on_seq: self.order.last().map_or(0, |f| f.seq),
            based_on_epoch_ns: self.order.last().map_or(0, |f| f.epoch_ns),
            map,
            tracked_fruits: tracked_fruits.collect(),
            next_fruit_id,
            // Set by the planner service (the newest ownership epoch it knows).
            owner_epoch: glasshouse_fleet::NO_EPOCH,
            visit: self.visit,
            season: self.committed_season(),
            hand_eye: self.hand_eye_on_the_wire(),
        }
    }

    /// The hand-eye estimator as a snapshot carries it (None while it is off).
    fn hand_eye_on_the_wire(&self) -> Option<HandEye> {
        if !self.settings.hand_eye.enabled {
            return None;
        }
        let state = self.hand_eye.state();
        let scans = state.scans.into_iter().map(|scan| HandEyeScan {
            world_from_camera: scan.world_from_camera,
            points_in_camera: scan.surface.iter().map(|s| s.point.into()).collect(),
            normals_in_camera: scan.surface.iter().map(|s| s.normal).collect(),
        });
        Some(HandEye {
            camera_believed_from_true: state.camera_believed_from_true,
            scans_seen: state.scans_seen,
            scans: scans.collect(),
        })
    }

    /// The hand-eye estimator a snapshot carried (a fresh one when it carried none).
    fn hand_eye_from_the_wire(
        settings: &HandEyeSettings,
        wire: Option<&HandEye>,
    ) -> HandEyeEstimator {
        let Some(wire) = wire else {
            return HandEyeEstimator::new(settings.clone());
        };
        let scans = wire.scans.iter().map(|scan| KeyScan {
            world_from_camera: scan.world_from_camera,
            surface: scan
                .points_in_camera
                .iter()
                .zip(&scan.normals_in_camera)
                .map(|(p, n)| Surfel {
                    point: p.coords,
                    normal: *n,
                })
                .collect(),
        });
        let state = HandEyeState {
            camera_believed_from_true: wire.camera_believed_from_true,
            scans_seen: wire.scans_seen,
            scans: scans.collect(),
        };
        HandEyeEstimator::from_state(settings.clone(), state)
    }

    /// A planner continuing from another planner's snapshot: its map, fruit ids and last
    /// integrated frame; the voxels it holds count as published (the former owner published them).
    pub fn from_snapshot(
        settings: PlanningSettings,
        snapshot: &MapSnapshot,
    ) -> Result<Self, PlanningError> {
        let map = RoiMap::read_snapshot(snapshot.map.as_slice())
            .map_err(|e| PlanningError::Snapshot(e.to_string()))?;
        Self::from_map(settings, map, snapshot)
    }

    /// What a store keeps of this copy at a checkpoint: its fruit ids and last frame (`meta`, a
    /// snapshot whose `map` is the map's [`RoiMap::stored_header`]) and the map's blocks
    /// changed after it had taken `since_scans` scans (0: every block).
    pub fn checkpoint(&self, tid: &str, pid: &str, since_scans: u64) -> StoredCopy {
        let (tracked, next_fruit_id) = self.tracker.state();
        let tracked_fruits = tracked.into_iter().map(|(id, c)| TrackedFruit {
            id,
            centre_in_world: c.cast(),
            colour: self.colours.sum_of(id),
        });
        let meta = MapSnapshot {
            trolley_id: tid.to_owned(),
            planner_id: pid.to_owned(),
            based_on_seq: self.order.last().map_or(0, |f| f.seq),
            based_on_epoch_ns: self.order.last().map_or(0, |f| f.epoch_ns),
            map: self.map.stored_header(),
            tracked_fruits: tracked_fruits.collect(),
            next_fruit_id,
            owner_epoch: glasshouse_fleet::NO_EPOCH,
            visit: self.visit,
            season: self.committed_season(),
            hand_eye: self.hand_eye_on_the_wire(),
        };
        StoredCopy {
            meta,
            blocks: self.map.stored_blocks_since(since_scans),
            scans: self.map.scans_inserted(),
        }
    }

    /// A copy from what a store kept: the newest checkpoint's `meta` and the newest record of
    /// each block ([`TrolleyPlanner::checkpoint`]).
    pub fn from_stored<'a>(
        settings: PlanningSettings,
        meta: &MapSnapshot,
        blocks: impl IntoIterator<Item = &'a [u8]>,
    ) -> Result<Self, PlanningError> {
        let map = RoiMap::from_stored(&meta.map, blocks)
            .map_err(|e| PlanningError::Snapshot(e.to_string()))?;
        Self::from_map(settings, map, meta)
    }

    /// A planner starting a new visit of its trolley's row on `prior` (the previous visit's map
    /// made into a prior, [`glasshouse_roimap::RoiMap::prior`]): no fruit ids, no frame yet.
    pub fn on_prior(settings: PlanningSettings, prior: RoiMap) -> Result<Self, PlanningError> {
        let remembered_fruit = prior.unobserved_hints();
        let mut planner = Self::with_map(settings, prior)?;
        planner.remembered_fruit = remembered_fruit;
        Ok(planner)
    }

    /// The voxels, sorted, of the latest clusters that are settled: ROI-targeted sampling does
    /// not aim beside them alone ([`PlanningSettings::clutter_settles_after_views`],
    /// [`PlanningSettings::fruit_settles_after_views`]).
    pub fn settled_voxels(&self) -> &[VoxelKey] {
        &self.settled_voxels
    }

    /// The previous visit's fruit voxels a plan still aims at (no scan of this visit has
    /// touched them).
    pub fn remembered_fruit(&self) -> &[VoxelKey] {
        &self.remembered_fruit
    }

    /// The map, given up (the experiments keep a visit's map for the next one's prior).
    pub fn into_map(self) -> RoiMap {
        self.map
    }

    /// A planner on `map` (its resolution must be this planner's), no fruit ids yet. Later
    /// clouds go in with this planner's ray rules (range, merged far rays), whatever rules made
    /// the map: a map kept before the settings changed is carried on, not refused.
    fn with_map(settings: PlanningSettings, mut map: RoiMap) -> Result<Self, PlanningError> {
        let wanted = settings.map_config();
        if map.config().resolution_m != wanted.resolution_m {
            return Err(PlanningError::Snapshot(format!(
                "its map has {} m voxels, this planner {} m",
                map.config().resolution_m,
                wanted.resolution_m
            )));
        }
        map.set_ray_rules(wanted.max_range_m, wanted.merge_far_rays)?;
        let mut planner = Self::new(settings)?;
        planner.published_solid = PublishedSolid::from_cells(map.solid_blocks());
        planner.map = map;
        Ok(planner)
    }

    /// A copy of `map` with the fruit ids and last frame of `snapshot`.
    fn from_map(
        settings: PlanningSettings,
        map: RoiMap,
        snapshot: &MapSnapshot,
    ) -> Result<Self, PlanningError> {
        let mut planner = Self::with_map(settings, map)?;
        let tracked = snapshot.tracked_fruits.iter();
        planner.tracker = FruitTracker::from_state(
            tracked.map(|f| (f.id, f.centre_in_world.cast())).collect(),
            snapshot.next_fruit_id,
        );
        planner.colours = FruitColours::from_tracked(&snapshot.tracked_fruits);
        let last = FrameId::new(snapshot.based_on_epoch_ns, snapshot.based_on_seq);
        planner.order = FrameOrder::starting_at((last != FrameId::default()).then_some(last));
        planner.set_season(snapshot.visit, &snapshot.season);
        planner.hand_eye =
            Self::hand_eye_from_the_wire(&planner.settings.hand_eye, snapshot.hand_eye.as_ref());
        if snapshot.visit > 0 {
            // A later visit's copy: its map still holds the hints no scan has touched.
            planner.remembered_fruit = planner.map.unobserved_hints();
        }
        Ok(planner)
    }
}

impl TrolleyPlanner {
    /// Replaces the map, fruit ids and frame mark with a snapshot's, keeping the trolley's info,
    /// reach filter and registration counts (a standby replica catching up with its owner). On
    /// an error nothing changes.
    pub fn restore(&mut self, snapshot: &MapSnapshot) -> Result<(), PlanningError> {
        let restored = Self::from_snapshot(self.settings.clone(), snapshot)?;
        self.adopt(restored);
        Ok(())
    }

    /// Becomes `restored` (a copy [`TrolleyPlanner::from_snapshot`] decoded elsewhere, for
    /// example on another thread), keeping the trolley's info, reach filter and registration
    /// counts, as [`TrolleyPlanner::restore`] does.
    pub fn adopt(&mut self, mut restored: TrolleyPlanner) {
        restored.info = self.info.take();
        restored.reach = self.reach.take();
        restored.alignment_counts = self.alignment_counts;
        *self = restored;
    }

    /// Whether a snapshot's map arrived whole (framing and checksum), without decoding it.
    pub fn check_snapshot(snapshot: &MapSnapshot) -> Result<(), PlanningError> {
        RoiMap::check_snapshot(&snapshot.map).map_err(|e| PlanningError::Snapshot(e.to_string()))
    }

    /// Forgets the map and everything derived from it, keeping the trolley's info, reach filter
    /// and registration counts (a standby replica holds the owner's snapshot instead).
    pub fn clear(&mut self) -> Result<(), PlanningError> {
        let mut fresh = Self::new(self.settings.clone())?;
        fresh.info = self.info.take();
        fresh.reach = self.reach.take();
        fresh.alignment_counts = self.alignment_counts;
        fresh.visit = self.visit;
        fresh.season = std::mem::take(&mut self.season);
        *self = fresh;
        Ok(())
    }
}

/// A trolley's copy as a store keeps it ([`TrolleyPlanner::checkpoint`]).
#[derive(Clone, Debug, PartialEq)]
pub struct StoredCopy {
    /// Fruit ids, last frame and the map's header (`map`); the owner epoch is the caller's.
    pub meta: MapSnapshot,
    /// Block coordinates and records of the blocks changed since the checkpoint asked about.
    pub blocks: Vec<(glasshouse_roimap::VoxelKey, Vec<u8>)>,
    /// The map's scan count: the next checkpoint's `since_scans`.
    pub scans: u64,
}

/// A cloud's sensor origin and points as they go into the map, world frame.
struct RegisteredScan<'c> {
    origin: Point3<f64>,
    points: Cow<'c, [Point3<f32>]>,
}

fn voxel_change(key: VoxelKey, voxel: Voxel, is_roi: bool) -> VoxelChange {
    let state = if is_roi {
        VoxelState::Roi
    } else if voxel.occupancy() == Occupancy::Occupied {
        VoxelState::Occupied
    } else {
        VoxelState::Free
    };
    VoxelChange {
        key: [key.x, key.y, key.z],
        occupancy_logodds: voxel.occupancy_logodds,
        roi_logodds: voxel.roi_logodds,
        state,
    }
}

/// What became of one ROI cluster ([`TrolleyPlanner::cluster_outcomes`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClusterOutcome {
    pub centre: Point3<f64>,
    pub voxels: usize,
    pub shape: ClusterShape,
    /// The shape rule's verdict; [`Verdict::Sheet`] when its fitted solid hides nothing.
    pub verdict: Verdict,
    /// The fitted solid (`None`: the shape rule refused the cluster, so it was not fitted).
    pub fit: Option<FruitSolid>,
    /// What the map knows inside the fitted solid.
    pub interior: Option<Interior>,
    /// A second patch of a fruit another cluster reports.
    pub fragment: bool,
    /// Turned away by its shape or inside, and reported for the fruit body found under it
    /// ([`glasshouse_nbv::evidence::body`]); `fit` is the body's.
    pub body: bool,
}

impl ClusterOutcome {
    /// Whether the cluster is reported as a fruit.
    pub fn is_reported(&self) -> bool {
        self.verdict.is_fruit() && !self.fragment && self.fit.is_some()
    }
}

#[cfg(test)]
mod settings_tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn bad_registration_settings_are_refused() {
        let mut hand_eye = PlanningSettings::default();
        hand_eye.hand_eye.min_normal_agreement = 2.0;
        assert!(matches!(
            hand_eye.validate(),
            Err(PlanningError::Settings(_))
        ));
        hand_eye.hand_eye = HandEyeSettings {
            query_points: 5000,
            ..HandEyeSettings::default()
        };
        assert!(matches!(
            hand_eye.validate(),
            Err(PlanningError::Settings(_))
        ));
        let mut settings = PlanningSettings::default();
        settings.registration.max_rotation_deg = -1.0;
        assert!(matches!(
            TrolleyPlanner::new(settings),
            Err(PlanningError::Settings(_))
        ));
        let json = r#"{ "registration": { "enabled": true } }"#;
        let read: PlanningSettings = serde_json::from_str(json).unwrap();
        assert!(read.registration.enabled);
        assert_eq!(
            read.registration.max_scan_points,
            RegisterSettings::default().max_scan_points
        );
    }

    #[test]
    fn the_voxel_bias_factor_is_read_from_settings_and_checked() {
        let json = r#"{ "fit": { "voxel_bias_factor": 0 } }"#;
        let read: PlanningSettings = serde_json::from_str(json).unwrap();
        assert_eq!(read.fit.voxel_bias_factor, 0.0);
        assert!(read.validate().is_ok());
        assert!(PlanningSettings::default().fit.voxel_bias_factor > 0.0);
        for bad in [-0.1, 1.5, f64::NAN] {
            let mut settings = PlanningSettings::default();
            settings.fit.voxel_bias_factor = bad;
            let error = settings.validate().unwrap_err().to_string();
            assert!(error.contains("voxel_bias_factor"), "{bad}: {error}");
        }
    }

    #[test]
    fn settling_is_off_by_default_and_read_from_settings() {
        let default = PlanningSettings::default();
        assert_eq!(
            (
                default.clutter_settles_after_views,
                default.fruit_settles_after_views
            ),
            (0, 0)
        );
        let json = r#"{ "clutter_settles_after_views": 3, "fruit_settles_after_views": 4 }"#;
        let read: PlanningSettings = serde_json::from_str(json).unwrap();
        assert_eq!(
            (
                read.clutter_settles_after_views,
                read.fruit_settles_after_views
            ),
            (3, 4)
        );
        assert!(read.validate().is_ok());
    }

    #[test]
    fn the_roi_sampling_options_are_the_papers_by_default_and_reach_the_planner() {
        let paper = PlanningSettings::default().planner_config();
        assert_eq!(paper.roi_tries, 0);
        assert_eq!(
            paper.occlusion_occupancy_logodds,
            PlannerConfig::default().occlusion_occupancy_logodds
        );
        assert_eq!(
            PlanningSettings::default().explore_after_fruitless_clouds,
            0
        );
        let json = r#"{ "roi_tries": 1000, "explore_after_fruitless_clouds": 4,
            "occlusion_occupancy_logodds": 1.0 }"#;
        let read: PlanningSettings = serde_json::from_str(json).unwrap();
        assert!(read.validate().is_ok());
        let config = read.planner_config();
        assert_eq!(
            (config.roi_tries, config.occlusion_occupancy_logodds),
            (1000, 1.0)
        );
        assert_eq!(read.explore_after_fruitless_clouds, 4);
        let bad = PlanningSettings {
            occlusion_occupancy_logodds: f32::NAN,
            ..read.clone()
        };
        assert!(bad.validate().is_err());
        let bad = PlanningSettings {
            roi_tries: 1_000_000,
            ..read
        };
        assert!(bad.validate().is_err());
    }

    #[test]
    fn a_motion_cost_is_read_from_settings_and_a_negative_one_refused() {
        let paper: PlanningSettings =
            serde_json::from_str(r#"{ "cost_weight_per_s": 0 }"#).unwrap();
        assert_eq!(paper.planner_config().cost_weight_per_s, 0.0);
        let default = PlanningSettings::default().planner_config();
        assert_eq!(default.cost_weight_per_s, DEFAULT_COST_WEIGHT_PER_S);
        for bad in [-1.0, f64::NAN, f64::INFINITY] {
            let settings = PlanningSettings {
                cost_weight_per_s: bad,
                ..PlanningSettings::default()
            };
            let error = settings.validate().unwrap_err().to_string();
            assert!(error.contains("cost_weight_per_s"), "{error}");
        }
    }
}
