//! The planner's reach filter for a simulated scene: the scene's robot (arm and mount ranges)
//! and the shared reachability map, as a [`ReachPredicate`] for
//! [`glasshouse_nbv::PlanningContext::reach`].

use glasshouse_arm::{shared_reachability_map, ReachCheck, ReachabilityParams, ViewReachability};
use glasshouse_nbv::ReachPredicate;
use glasshouse_sim::Scene;
use nalgebra::Isometry3;

use crate::trial::EvalError;

/// A reach predicate that can be kept in a trial (owned, shareable across threads).
pub type OwnedReach = Box<dyn Fn(&Isometry3<f64>) -> bool + Send + Sync>;

/// [`ViewReachability`] of the scene's robot over its whole mount range, with the edge's
/// clearance ([`Scene::ARM_CLEARANCE_M`]); the map is built once per process.
pub fn scene_reachability(scene: &Scene, check: ReachCheck) -> Result<ViewReachability, EvalError> {
    let robot = scene.robot();
    let arm_error = |e: glasshouse_arm::ArmError| EvalError::InvalidConfig(e.to_string());
    let map = shared_reachability_map(&ReachabilityParams::paper(&robot.arm)).map_err(arm_error)?;
    ViewReachability::new(robot, map, check, Scene::ARM_CLEARANCE_M).map_err(arm_error)
}

/// [`scene_reachability`] as an owned predicate.
pub fn scene_reach_predicate(scene: &Scene, check: ReachCheck) -> Result<OwnedReach, EvalError> {
    let reach = scene_reachability(scene, check)?;
    Ok(Box::new(move |pose: &Isometry3<f64>| reach.can_reach(pose)))
}

/// The owned predicate as the planner takes it.
pub fn as_predicate(reach: &OwnedReach) -> &ReachPredicate<'_> {
    reach.as_ref()
}

/// No voxel the map knows as occupied within `clearance_m` (a cube of `resolution_m` voxels) of
/// the camera position: the edge refuses a camera closer than that to a solid.
pub fn clear_of_occupied(
    map: &glasshouse_roimap::RoiMap,
    world_from_camera: &Isometry3<f64>,
    clearance_m: f64,
    resolution_m: f64,
) -> bool {
    let eye = nalgebra::Point3::from(world_from_camera.translation.vector);
    let centre = map.key_of(&eye);
    let n = (clearance_m / resolution_m).ceil() as i32;
    for dx in -n..=n {
        for dy in -n..=n {
            for dz in -n..=n {
                if map.occupancy(centre.offset(dx, dy, dz))
                    == glasshouse_roimap::Occupancy::Occupied
                {
                    return false;
                }
            }
        }
    }
    true
}
