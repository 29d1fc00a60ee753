//! Where a trolley's frames come from and what moves its camera.
//!
//! [`TrolleySource`] is the seam between the edge's loop and the hardware: [`SimSource`] is the
//! simulated glasshouse with its UR5e, [`ReplaySource`] plays back frames recorded with
//! [`FrameRecorder`], and a real camera and arm driver implements the same trait.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::Context;
use glasshouse_arm::{Interval, Mount, MountState};
use glasshouse_proto::{
    decode_typed, encode, ArmModel, ArmState, Fruit, Header, MessageKind, MountKind, RgbdFrame,
    TrolleyInfo, Wire,
};
use glasshouse_sim::{CameraModel, Scene, Segment, SimArm};
use nalgebra::Isometry3;

use crate::{render_frame, EdgeConfig};

/// A view the source executed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Executed {
    /// Index of the executed view in the ranked list.
    pub index: usize,
    /// Time the motion took (simulated or measured), without capture time.
    pub motion_s: f64,
}

/// A trolley's camera and arm, as the edge's loop sees them.
pub trait TrolleySource: Send {
    /// What planners need to know about this trolley now (regions follow the segment).
    fn info(&self) -> TrolleyInfo;
    /// Ground truth, when the source knows it (the simulator does).
    fn ground_truth(&self) -> Option<Vec<Fruit>>;
    /// Captures a frame at the current pose. None when the source has no more frames.
    fn capture(&mut self, frame_seq: u64) -> anyhow::Result<Option<RgbdFrame>>;
    /// The arm now.
    fn arm_state(&self, moving: bool, views_done: u32) -> ArmState;
    /// Moves to the first view of `goals` (best first) the arm can reach; None, and no motion,
    /// when it reaches none.
    fn execute(&mut self, goals: &[Isometry3<f64>]) -> Option<Executed>;
    /// Moves on to the next part of the row; the motion time, or None when the row is done.
    fn next_segment(&mut self) -> Option<f64>;
}

/// The simulated glasshouse: renders the scene at the arm's camera pose.
pub struct SimSource {
    scene: Scene,
    camera: CameraModel,
    arm: SimArm,
    segments: Vec<Segment>,
    segment: usize,
    config: EdgeConfig,
}

impl SimSource {
    pub fn new(config: &EdgeConfig) -> anyhow::Result<Self> {
        let scene = Scene::generate(config.validate()?, config.seed);
        let arm = SimArm::new(&scene).context("the arm cannot reach the scene's initial view")?;
        let segments = scene.segments(config.segment_length_m);
        anyhow::ensure!(!segments.is_empty(), "segment length must be > 0");
        // Start in the segment that holds the initial view.
        let eye = arm.world_from_camera().translation.vector;
        let segment = segments
            .iter()
            .position(|s| s.camera_workspace.contains(&eye.into()))
            .unwrap_or(0);
        Ok(Self {
            camera: CameraModel::with_resolution(config.width, config.height),
            scene,
            arm,
            segments,
            segment,
            config: config.clone(),
        })
    }

    pub fn world_from_camera(&self) -> Isometry3<f64> {
        self.arm.world_from_camera()
    }
}

impl TrolleySource for SimSource {
    fn info(&self) -> TrolleyInfo {
        let robot = self.arm.robot();
        let (mount, rail, lift) = match &robot.mount {
            Mount::Fixed { .. } => (MountKind::StaticPole, None, None),
            Mount::CeilingGantry {
                max_extension_m, ..
            } => (
                MountKind::CeilingGantry,
                None,
                Some(Interval::new(0.0, *max_extension_m)),
            ),
            Mount::RailLift {
                position_m, lift_m, ..
            } => (MountKind::RailLift, Some(*position_m), Some(*lift_m)),
        };
        let zero = Interval::new(0.0, 0.0);
        let (rail, lift) = (rail.unwrap_or(zero), lift.unwrap_or(zero));
        let segment = self.segments.get(self.segment).copied().unwrap_or(Segment {
            camera_workspace: self.scene.camera_workspace(),
            sampling_region: self.scene.sampling_region(),
        });
        TrolleyInfo {
            arm_model: ArmModel::Ur5e,
            mount,
            world_from_base: robot
                .world_from_base(&self.arm.pose().mount)
                .unwrap_or_else(|_| Isometry3::identity()),
            joint_min_rad: robot.arm.limits.lower.to_vec(),
            joint_max_rad: robot.arm.limits.upper.to_vec(),
            rail_min_m: rail.min,
            rail_max_m: rail.max,
            lift_min_m: lift.min,
            lift_max_m: lift.max,
            camera_workspace: segment.camera_workspace,
            sampling_region: segment.sampling_region,
            scenario: self.config.scenario.clone(),
            scene_seed: self.config.seed,
            intrinsics: self.camera.intrinsics,
        }
    }

    fn ground_truth(&self) -> Option<Vec<Fruit>> {
        Some(
            self.scene
                .fruits()
                .iter()
                .map(|f| {
                    let aabb = f.aabb();
                    Fruit {
                        id: f.id,
                        centre_in_world: f.centre.cast(),
                        box_min: aabb.min.cast(),
                        box_max: aabb.max.cast(),
                        volume_m3: f.volume_m3 as f32,
                        voxel_count: f.voxel_keys(0.01).len().min(u32::MAX as usize) as u32,
                        confidence: 1.0,
                        fitted: None,
                    }
                })
                .collect(),
        )
    }

    fn capture(&mut self, frame_seq: u64) -> anyhow::Result<Option<RgbdFrame>> {
        let noise_seed = self
            .config
            .seed
            .wrapping_mul(1_000_003)
            .wrapping_add(frame_seq);
        let pose = self.arm.world_from_camera();
        Ok(Some(render_frame(
            &self.scene,
            &self.camera,
            &pose,
            noise_seed,
        )))
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
        self.arm
            .execute_first_reachable(&self.scene, goals)
            .map(|e| Executed {
                index: e.index,
                motion_s: e.motion_s,
            })
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

/// Writes every captured frame (and the trolley's info) to a folder, one verified envelope per
/// file, for [`ReplaySource`].
pub struct FrameRecorder {
    dir: PathBuf,
}

impl FrameRecorder {
    pub fn create(dir: &Path) -> anyhow::Result<Self> {
        fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        Ok(Self {
            dir: dir.to_path_buf(),
        })
    }

    pub fn write<M: Wire>(&self, header: &Header, message: &M) -> anyhow::Result<()> {
        let name = match M::KIND {
            MessageKind::TrolleyInfo => "info.ghw".to_string(),
            MessageKind::RgbdFrame => format!("frame-{:08}.ghw", header.seq),
            _ => anyhow::bail!("only frames and trolley info are recorded"),
        };
        let path = self.dir.join(name);
        fs::write(&path, encode(header, message))
            .with_context(|| format!("cannot write {}", path.display()))
    }
}

/// Plays back frames recorded by [`FrameRecorder`], in order: each executed view brings the
/// next recorded frame. Views are "reached" as the recording moved on, with no motion time.
pub struct ReplaySource {
    info: TrolleyInfo,
    frames: Vec<PathBuf>,
    next: usize,
    last_pose: Isometry3<f64>,
}

impl ReplaySource {
    pub fn open(dir: &Path) -> anyhow::Result<Self> {
        let info_path = dir.join("info.ghw");
        let bytes = fs::read(&info_path)
            .with_context(|| format!("cannot read {} (not a recording?)", info_path.display()))?;
        let (_, info) = decode_typed::<TrolleyInfo>(&bytes)
            .with_context(|| format!("{} is not a TrolleyInfo", info_path.display()))?;
        let mut frames: Vec<PathBuf> = fs::read_dir(dir)
            .with_context(|| format!("cannot list {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("frame-") && n.ends_with(".ghw"))
            })
            .collect();
        frames.sort();
        anyhow::ensure!(!frames.is_empty(), "no frames in {}", dir.display());
        Ok(Self {
            info,
            frames,
            next: 0,
            last_pose: Isometry3::identity(),
        })
    }
}

impl TrolleySource for ReplaySource {
    fn info(&self) -> TrolleyInfo {
        self.info.clone()
    }

    fn ground_truth(&self) -> Option<Vec<Fruit>> {
        None
    }

    fn capture(&mut self, _frame_seq: u64) -> anyhow::Result<Option<RgbdFrame>> {
        let Some(path) = self.frames.get(self.next) else {
            return Ok(None);
        };
        let bytes = fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        let (_, frame) = decode_typed::<RgbdFrame>(&bytes)
            .with_context(|| format!("{} is not an RgbdFrame", path.display()))?;
        self.last_pose = frame.world_from_camera;
        Ok(Some(frame))
    }

    fn arm_state(&self, moving: bool, views_done: u32) -> ArmState {
        ArmState {
            joint_angles_rad: Vec::new(),
            world_from_camera: self.last_pose,
            rail_position_m: 0.0,
            lift_height_m: 0.0,
            moving,
            views_done,
        }
    }

    fn execute(&mut self, goals: &[Isometry3<f64>]) -> Option<Executed> {
        if goals.is_empty() {
            return None;
        }
        self.next += 1;
        Some(Executed {
            index: 0,
            motion_s: 0.0,
        })
    }

    fn next_segment(&mut self) -> Option<f64> {
        // A recording has one segment: what was recorded.
        self.execute(&[Isometry3::identity()]).map(|e| e.motion_s)
    }
}
