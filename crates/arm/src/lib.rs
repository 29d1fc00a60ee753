//! UR5e arm for Glasshouse: kinematics, mounts, collision checks, reachability map and motion time.
//!
//! I/O-free except for the reachability cache file ([`ReachabilityMap::load_or_build`]).
//!
//! # Concepts
//! - [`ArmModel`]: a UR-family arm from its standard DH lengths ([`UrDh::UR5E`] by default),
//!   [`JointLimits`] (±2π on every joint by default), the camera on the tool flange
//!   (`flange_from_camera`) and capsules approximating the links. Forward kinematics
//!   ([`ArmModel::base_from_camera`]) and closed-form inverse kinematics with up to eight
//!   solutions ([`ArmModel::ik_flange`], [`ArmModel::ik_camera`]).
//! - [`Mount`]: where the base sits and its extra degrees of freedom, with [`MountState`] holding
//!   their values: a fixed pole (Scenario 1), a ceiling gantry with a retractable pole (Scenario 2,
//!   base upside down) or a rail trolley with a scissor lift (the row).
//! - [`Robot`]: an arm on a mount: world-frame kinematics, [`Robot::solve_camera_pose`],
//!   mount placement heuristics, collision checks of a configuration or a joint-space path
//!   against [`Obstacle`]s and an occupied-voxel query ([`OccupancyQuery`], any
//!   `Fn(Point3<f64>) -> bool`).
//! - [`ReachabilityMap`]: where the camera's optical centre can go (paper §VII: joints sampled at
//!   10°, 2 cm cells), cached on disk by a hash of its parameters, queried in the base frame, in
//!   the world for a mount state, or for some mount state; [`shared_reachability_map`] builds it
//!   once per process.
//! - [`ViewReachability`]: can the robot reach a camera pose for some mount state (map, then the
//!   edge's placement and IK, then the mount's structure), cheap enough to filter every candidate
//!   view of a planner.
//! - [`MotionLimits`]: synchronised trapezoidal joint motion and mount motion in parallel;
//!   [`CAPTURE_TIME_S`] is added by the caller per view.
//!
//! # Frames and units
//! - Metres, radians, seconds. World: right-handed, `z` up (as `glasshouse_geom`).
//! - Poses are named `a_from_b`: they map points in frame `b` to frame `a`.
//! - `base`: the arm's DH frame 0 (z along joint 1, pointing away from the mounting surface);
//!   `flange`: DH frame 6 (z out of the tool flange); `camera`: the optical frame, x right, y down,
//!   z forward along the optical axis — the same `world_from_camera` convention as every other
//!   crate. `world_from_camera = world_from_base(state) · base_from_flange(q) · flange_from_camera`.
//! - Joint vectors ([`JointVector`]) are `[f64; 6]`, base joint first.
//!
//! Bad inputs (NaN, out of limits, mismatched mount state) are [`ArmError`]s, never panics.

mod collision;
mod error;
mod execute;
mod kinematics;
mod motion;
mod mount;
mod reach;
mod robot;
mod view_reach;

pub use collision::{
    CollisionWorld, Contact, ContactWith, Obstacle, OccupancyQuery, PathContact, WorldCapsule,
};
pub use error::{ArmError, Result};
pub use execute::{
    ArmPose, ExecuteSettings, Executed, ViewMotion, ARM_CLEARANCE_M, CAMERA_CLEARANCE_M,
};
pub use kinematics::{
    best_solution, joint_distance, ArmModel, JointLimits, JointVector, LinkCapsule, UrDh,
    CAMERA_FRAME, JOINT_COUNT, UR_ALPHA,
};
pub use motion::{AxisLimit, MotionLimits, CAPTURE_TIME_S};
pub use mount::{Interval, Mount, MountState, POLE_RADIUS_M};
pub use reach::{CacheStatus, ReachabilityMap, ReachabilityParams};
pub use robot::{Robot, MAX_MARGIN_M, MIN_VOXEL_RESOLUTION_M};
pub use view_reach::{shared_reachability_map, ReachCheck, ViewReachability};

#[cfg(test)]
mod tests;
