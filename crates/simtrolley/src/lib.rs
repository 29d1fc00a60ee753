//! The simulated trolley: a seeded glasshouse scene rendered at the camera pose of the scene's
//! UR5e, behind the loop's [`TrolleySource`], for the edge's `--source sim` and the experiments.
//! Nothing on a real trolley's path links this crate (`scripts/check-layers`).

use glasshouse_arm::MountState;
use glasshouse_geom::FruitEstimate;
use glasshouse_proto::{ArmState, RgbdFrame, TrolleyInfo};
use glasshouse_sim::{
    CameraModel, PerceptionNoise, ScenarioKind, Scene, Segment, SimArm, WorldError, WorldSettings,
};
use nalgebra::{Isometry3, Translation3};

use glasshouse_pipeline::{Executed, TrolleySource, DEPTH_SCALE_M};

/// Why a simulated trolley cannot be set up.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum CaptureError {
    #[error("the arm cannot reach the scene's initial view: {0}")]
    InitialView(String),
    #[error("segment length must be finite and > 0, got {0}")]
    SegmentLength(f64),
    #[error("image size {0}x{1} outside 16x12..1280x960")]
    ImageSize(u32, u32),
    #[error(transparent)]
    World(#[from] WorldError),
}

/// The seed of what differs between two visits of one trolley to its scene (`day`: see
/// `SceneOptions::day`): its odometry, its encoders' noise and its camera noise; the scene seed
/// itself without visits. The hand-eye error stays the trolley's own.
pub fn visit_seed(scene_seed: u64, day: Option<f64>) -> u64 {
    match day {
        Some(d) => scene_seed ^ d.to_bits().rotate_left(17) ^ 0x005E_A50F_DA75,
        None => scene_seed,
    }
}

/// Seed of the camera noise of frame `frame_seq` of a scene seeded with `scene_seed`.
pub fn noise_seed(scene_seed: u64, frame_seq: u64) -> u64 {
    scene_seed.wrapping_mul(1_000_003).wrapping_add(frame_seq)
}

/// Renders the simulated camera with `perception` noise on top (seeded from `noise_seed` too)
/// and packs the frame for the wire. Depth is in millimetres with one rule for every consumer:
/// invalid and over-range depths are both 0 ([`glasshouse_sim::RgbdImage::depth_as_u16`]).
pub fn render_frame(
    scene: &Scene,
    camera: &CameraModel,
    world_from_camera: &Isometry3<f64>,
    noise_seed: u64,
    perception: &PerceptionNoise,
) -> RgbdFrame {
    let image = scene.render_with(camera, world_from_camera, noise_seed, perception);
    RgbdFrame {
        depth: image.depth_as_u16(f64::from(DEPTH_SCALE_M)),
        intrinsics: image.intrinsics,
        world_from_camera: *world_from_camera,
        depth_scale_m: DEPTH_SCALE_M,
        min_range_m: camera.min_range_m as f32,
        max_range_m: camera.max_range_m as f32,
        rgb: image.rgb,
        depth_encoding: Default::default(),
        rgb_encoding: Default::default(),
    }
}

/// The settings that define a simulated trolley.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimTrolleySettings {
    pub scenario: ScenarioKind,
    /// Scene and camera-noise seed.
    pub seed: u64,
    pub width: u32,
    pub height: u32,
    /// Length along the row of the part the trolley works on at a time (row scenario).
    pub segment_length_m: f64,
    /// What the simulated world does that a perfect one would not: camera noise and light,
    /// fruit shape and colour, red clutter, pose errors (clean by default).
    pub world: WorldSettings,
}

impl SimTrolleySettings {
    /// The image must be 16x12 to 1280x960 pixels and the perception noise in range.
    pub fn validate(&self) -> Result<(), CaptureError> {
        let (w, h) = (self.width, self.height);
        if !((16..=1280).contains(&w) && (12..=960).contains(&h)) {
            return Err(CaptureError::ImageSize(w, h));
        }
        self.world.validate()?;
        Ok(())
    }
}

impl SimTrolleySettings {
    /// Scene `scenario` seeded with `seed`, images of `size` (width, height) pixels, row
    /// segments `segment_length_m` long, clean perception.
    pub fn new(scenario: ScenarioKind, seed: u64, size: (u32, u32), segment_length_m: f64) -> Self {
        let (width, height) = size;
        Self {
            scenario,
            seed,
            width,
            height,
            segment_length_m,
            world: WorldSettings::default(),
        }
    }
}

/// The simulated glasshouse: renders the scene at the camera pose of the scene's UR5e, which
/// executes views (IK, then a collision-free joint path) and moves along the row's segments.
#[derive(Clone, Debug)]
pub struct SimTrolley {
    scene: Scene,
    camera: CameraModel,
    arm: SimArm,
    segments: Vec<Segment>,
    segment: usize,
    settings: SimTrolleySettings,
    /// The camera's true pose in the frame the trolley believes it in (hand-eye error).
    believed_camera_from_true: Isometry3<f64>,
    /// True minus believed rail position on each segment (odometry error), metres.
    rail_errors_m: Vec<f64>,
    /// [`visit_seed`] of this trolley's visit.
    visit_seed: u64,
    /// Where the trolley's base really is against where it believes, on this visit.
    visit_offset: Option<Isometry3<f64>>,
}

impl SimTrolley {
    pub fn new(settings: SimTrolleySettings) -> Result<Self, CaptureError> {
        settings.validate()?;
        let (w, h) = (settings.width, settings.height);
        let scene = Scene::generate_with(settings.scenario, settings.seed, &settings.world.scene);
        let arm = SimArm::new(&scene).map_err(|e| CaptureError::InitialView(e.to_string()))?;
        let segments = scene.segments(settings.segment_length_m);
        if segments.is_empty() {
            return Err(CaptureError::SegmentLength(settings.segment_length_m));
        }
        // Start in the segment that holds the initial view.
        let eye = arm.world_from_camera().translation.vector;
        let segment = segments
            .iter()
            .position(|s| s.camera_workspace.contains(&eye.into()))
            .unwrap_or(0);
        let pose_error = settings.world.pose;
        let day = settings.world.scene.day;
        let visit = visit_seed(settings.seed, day);
        Ok(Self {
            visit_seed: visit,
            visit_offset: day.and_then(|_| pose_error.visit_offset(visit)),
            camera: CameraModel::with_resolution(w, h),
            scene,
            arm,
            believed_camera_from_true: pose_error.believed_camera_from_true(settings.seed),
            rail_errors_m: pose_error.rail_errors_m(visit, segments.len()),
            segments,
            segment,
            settings,
        })
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Where the trolley believes its camera is (what its frames report).
    pub fn world_from_camera(&self) -> Isometry3<f64> {
        self.arm.world_from_camera()
    }

    /// Where the camera really is for frame `frame_seq`: the believed pose with the rail's
    /// odometry error, the joint encoders' errors of that frame and the hand-eye error.
    pub fn true_world_from_camera(&self, frame_seq: u64) -> Isometry3<f64> {
        let pose_error = &self.settings.world.pose;
        if pose_error.is_exact() {
            return self.arm.world_from_camera();
        }
        let arm_pose = self.arm.pose();
        let errors = pose_error.joint_errors_rad(
            noise_seed(self.visit_seed, frame_seq),
            arm_pose.joints.len(),
        );
        let mut joints = arm_pose.joints;
        for (q, e) in joints.iter_mut().zip(errors) {
            *q += e;
        }
        let robot = self.arm.robot();
        let flange_truth = robot
            .world_from_camera(&joints, &arm_pose.mount)
            .unwrap_or_else(|_| self.arm.world_from_camera());
        // Rails run along the world x axis; other mounts have no odometry.
        let rail_m = match arm_pose.mount {
            MountState::Rail { .. } => self.rail_errors_m.get(self.segment).copied(),
            _ => None,
        };
        let visit = self.visit_offset.unwrap_or_else(Isometry3::identity);
        visit
            * Translation3::new(rail_m.unwrap_or(0.0), 0.0, 0.0)
            * flange_truth
            * self.believed_camera_from_true
    }

    /// The segment the trolley works on now.
    pub fn segment(&self) -> Segment {
        self.segments.get(self.segment).copied().unwrap_or(Segment {
            camera_workspace: self.scene.camera_workspace(),
            sampling_region: self.scene.sampling_region(),
        })
    }
}

impl TrolleySource for SimTrolley {
    fn info(&self) -> TrolleyInfo {
        let robot = self.arm.robot();
        let segment = self.segment();
        TrolleyInfo {
            world_from_base: robot
                .world_from_base(&self.arm.pose().mount)
                .unwrap_or_else(|_| Isometry3::identity()),
            camera_workspace: segment.camera_workspace,
            sampling_region: segment.sampling_region,
            scenario: self.settings.scenario.to_string(),
            scene_seed: self.settings.seed,
            intrinsics: self.camera.intrinsics,
            robot: Some(Box::new(robot.clone())),
            // The edge fills in the ownership term it obeys and its visit.
            owner_epoch: 0,
            owner_id: String::new(),
            visit: 0,
        }
    }

    fn ground_truth(&self) -> Option<Vec<FruitEstimate>> {
        let truth = self.scene.fruits().iter().map(|f| f.estimate(0.01));
        Some(truth.collect())
    }

    fn capture(&mut self, frame_seq: u64) -> Result<Option<RgbdFrame>, String> {
        let seed = noise_seed(self.visit_seed, frame_seq);
        let noise = &self.settings.world.perception;
        let truth = self.true_world_from_camera(frame_seq);
        let mut frame = render_frame(&self.scene, &self.camera, &truth, seed, noise);
        // The frame says where the trolley believes it was, as a real one's would.
        frame.world_from_camera = self.arm.world_from_camera();
        Ok(Some(frame))
    }

    fn arm_state(&self, moving: bool, views_done: u32) -> ArmState {
        let (rail_position_m, lift_height_m) = match self.arm.pose().mount {
            MountState::Rail { position_m, lift_m } => (position_m, lift_m),
            MountState::Gantry { extension_m, .. } => (0.0, extension_m),
            MountState::Fixed => (0.0, 0.0),
        };
        ArmState {
            joint_angles_rad: self.arm.pose().joints.to_vec(),
            world_from_camera: self.arm.world_from_camera(),
            rail_position_m,
            lift_height_m,
            moving,
            views_done,
        }
    }

    fn execute(&mut self, goals: &[Isometry3<f64>]) -> Option<Executed> {
        self.arm.execute_first_reachable(&self.scene, goals)
    }

    fn next_segment(&mut self) -> Option<f64> {
        let next = self.segment + 1;
        let segment = *self.segments.get(next)?;
        // The same view of the plants, shifted to the next segment; else its workspace centre
        // looking across the row.
        let here = self.arm.world_from_camera();
        let from = self.segments.get(self.segment)?.camera_workspace.centre();
        let to = segment.camera_workspace.centre();
        let shifted = Isometry3::from_parts(
            (here.translation.vector + (to - from)).into(),
            here.rotation,
        );
        let across = glasshouse_geom::look_at(&to, &segment.sampling_region.centre());
        let executed = self
            .arm
            .execute_first_reachable(&self.scene, &[shifted, across]);
        self.segment = next;
        Some(executed.map_or(0.0, |e| e.motion_s))
    }
}
