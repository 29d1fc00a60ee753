//! Glasshouse on ROS 2 robots: the messages a RealSense-style camera, TF and an arm driver speak
//! (CDR, [`msg`]), their grouping into the loop's frames by stamp ([`assemble`]), rosbag2
//! recordings played as a trolley ([`bag`]), and rmw_zenoh's key expressions, liveliness tokens
//! and attachments ([`rmw`]) for the edge's live ROS 2 source.
//!
//! No zenoh, tokio or rerun here (the edge moves the bytes), and no simulator: a real trolley
//! runs this crate (`scripts/check-layers`).

pub mod assemble;
pub mod bag;
pub mod joints;
pub mod msg;
pub mod rmw;
pub mod settings;

use std::path::PathBuf;

use glasshouse_geom::CameraIntrinsics;
use glasshouse_proto::{ArmState, TrolleyInfo};
use nalgebra::Isometry3;

pub use assemble::{DropReason, Dropped, FrameAssembler, StampedFrame};
pub use bag::BagSource;
pub use settings::{PoseSource, RosTopics, RosTrolley, TopicQos};

/// Why a ROS 2 input cannot be used.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum RosError {
    #[error("{0}: {1}")]
    Io(PathBuf, String),
    #[error("{0} holds no .mcap file (not a rosbag2 bag?)")]
    NotABag(PathBuf),
    #[error("{what}: not valid CDR: {reason}")]
    Cdr { what: String, reason: String },
    #[error("ROS 2 settings: {0}")]
    Settings(String),
}

/// What planners are told about a ROS 2 trolley: its settings, and the camera as last seen.
pub fn trolley_info(trolley: &RosTrolley, intrinsics: Option<CameraIntrinsics>) -> TrolleyInfo {
    TrolleyInfo {
        world_from_base: Isometry3::identity(),
        camera_workspace: trolley.camera_workspace,
        sampling_region: trolley.sampling_region,
        scenario: trolley.scenario.clone(),
        scene_seed: 0,
        intrinsics: intrinsics.unwrap_or(CameraIntrinsics {
            width: 0,
            height: 0,
            fx: 0.0,
            fy: 0.0,
            cx: 0.0,
            cy: 0.0,
        }),
        robot: trolley.robot.clone().map(Box::new),
        // The edge fills in the ownership term it obeys and its visit.
        owner_epoch: 0,
        owner_id: String::new(),
        visit: 0,
    }
}

/// The arm as a ROS 2 source knows it: the camera pose of its last frame (joints are the arm
/// driver's business).
pub fn arm_state(world_from_camera: Isometry3<f64>, moving: bool, views_done: u32) -> ArmState {
    ArmState {
        joint_angles_rad: Vec::new(),
        world_from_camera,
        rail_position_m: 0.0,
        lift_height_m: 0.0,
        moving,
        views_done,
    }
}

#[cfg(test)]
mod tests;
