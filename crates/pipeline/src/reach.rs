//! Which views the planner proposes: those the trolley's arm can reach ([`ReachFilter`]).

use std::sync::Arc;

use glasshouse_arm::{
    shared_reachability_map, ArmError, ArmPose, MotionLimits, ReachCheck, ReachabilityParams,
    Robot, ViewReachability, ARM_CLEARANCE_M, CAMERA_CLEARANCE_M,
};
use glasshouse_roimap::{Occupancy, RoiMap};
use nalgebra::{Isometry3, Point3};

/// The edge's own test, repeated cheaply for every candidate view before it is scored: the arm
/// reaches the full pose (the 2 cm reachability map over the mount's range, then closed-form IK at
/// the mount states the edge would try), and the camera keeps the edge's clearance from voxels the
/// map knows as occupied. The edge still plans the path; a view passed here can still fail
/// there, but not for being out of reach.
#[derive(Clone, Debug)]
pub struct ReachFilter {
    reach: Arc<ViewReachability>,
}

impl ReachFilter {
    /// The filter for `robot` (the reachability map is built once per process and arm).
    pub fn for_robot(robot: Robot) -> Result<Self, ArmError> {
        let map = shared_reachability_map(&ReachabilityParams::paper(&robot.arm))?;
        let reach = ViewReachability::new(robot, map, ReachCheck::Pose, ARM_CLEARANCE_M)?;
        Ok(Self {
            reach: Arc::new(reach),
        })
    }

    pub fn robot(&self) -> &Robot {
        self.reach.robot()
    }

    /// Where the robot is guessed to be with its camera at `world_from_camera` (`None`: no
    /// placement found), for [`ReachFilter::motion_time_s`].
    pub fn pose_guess(&self, world_from_camera: &Isometry3<f64>) -> Option<ArmPose> {
        self.robot().pose_guess(world_from_camera).ok()
    }

    /// Seconds the robot takes from `from` to the camera at `goal` with the default motion
    /// limits (the edge's own may differ; the ranking only needs the order).
    pub fn motion_time_s(&self, from: &ArmPose, goal: &Isometry3<f64>) -> Option<f64> {
        let limits = MotionLimits::default();
        self.robot().motion_time_to(from, goal, &limits).ok()
    }

    /// Can the camera be placed at `world_from_camera` given what `map` knows?
    pub fn accepts(&self, map: &RoiMap, world_from_camera: &Isometry3<f64>) -> bool {
        self.reach.can_reach(world_from_camera) && clear_of_occupied(map, world_from_camera)
    }
}

/// No voxel the map knows as occupied within the edge's camera clearance of the camera.
fn clear_of_occupied(map: &RoiMap, world_from_camera: &Isometry3<f64>) -> bool {
    let eye = Point3::from(world_from_camera.translation.vector);
    let centre = map.key_of(&eye);
    let n = (CAMERA_CLEARANCE_M / map.config().resolution_m).ceil() as i32;
    (-n..=n).all(|dx| {
        (-n..=n).all(|dy| {
            (-n..=n).all(|dz| map.occupancy(centre.offset(dx, dy, dz)) != Occupancy::Occupied)
        })
    })
}
