//! Recorded trolleys: [`FrameRecorder`] writes what a trolley captures, [`ReplaySource`] plays it
//! back behind the same [`TrolleySource`] trait as the simulated glasshouse
//! ([`glasshouse_simtrolley::SimTrolley`]) and a real camera and arm driver.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::Context;
use glasshouse_pipeline::{Executed, TrolleySource};
use glasshouse_proto::{
    decode_typed, encode, ArmState, Header, MessageKind, RgbdFrame, TrolleyInfo, Wire,
};
use nalgebra::Isometry3;

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

    fn read_next(&mut self) -> anyhow::Result<Option<RgbdFrame>> {
        let Some(path) = self.frames.get(self.next) else {
            return Ok(None);
        };
        let bytes = fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        let (_, frame) = decode_typed::<RgbdFrame>(&bytes)
            .with_context(|| format!("{} is not an RgbdFrame", path.display()))?;
        self.last_pose = frame.world_from_camera;
        Ok(Some(frame))
    }
}

impl TrolleySource for ReplaySource {
    fn info(&self) -> TrolleyInfo {
        self.info.clone()
    }

    fn ground_truth(&self) -> Option<Vec<glasshouse_nbv::FruitEstimate>> {
        None
    }

    fn capture(&mut self, _frame_seq: u64) -> Result<Option<RgbdFrame>, String> {
        self.read_next().map_err(|e| format!("{e:#}"))
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
