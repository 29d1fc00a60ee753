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
pub fn as_predicate(reach: &OwnedReach) -> &ReachPredicate {
    reach.as_ref()
}
