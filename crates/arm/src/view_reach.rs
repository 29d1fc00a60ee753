//! Which camera poses a robot can reach, cheaply enough for a planner to ask about every
//! candidate view before scoring it.
//!
//! [`ViewReachability`] answers for the robot's whole mount range (a trolley's rail and lift, a
//! gantry's travel and pole), in stages that each reject what the next would: the reachability
//! map (is the camera position reachable for some mount state, O(1)), then the edge's own
//! placement (the suggested mount states and closed-form IK of the full pose, orientation
//! included), then a collision check of the reached configuration against the mount's structure.
//! The edge still plans the path from where the arm is; a pose accepted here can still fail there
//! (a blocked path), but not for being out of reach.
//!
//! The map costs seconds to build: [`shared_reachability_map`] builds it once per process and
//! parameters and shares it; services that restart often use
//! [`ReachabilityMap::load_or_build`]'s disk cache instead.

use std::sync::{Arc, Mutex, OnceLock};

use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use crate::error::{invalid, Result};
use crate::{CollisionWorld, ReachabilityMap, ReachabilityParams, Robot, MAX_MARGIN_M};

/// How much of the edge's test [`ViewReachability::can_reach`] repeats.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ReachCheck {
    /// The camera position is in the reachability map for some mount state.
    Position,
    /// Also: the full pose has IK solutions at one of [`Robot::suggest_mount_states`] (what the
    /// edge's placement tries).
    Pose,
    /// Also: at the first of those states with solutions (the one the edge moves the mount to),
    /// one solution is clear of the mount's own structure.
    PoseClear,
}

/// A robot's reachable camera poses (see the module docs).
#[derive(Clone, Debug)]
pub struct ViewReachability {
    robot: Robot,
    map: Arc<ReachabilityMap>,
    check: ReachCheck,
    margin_m: f64,
}

impl ViewReachability {
    /// For `robot` with `map` (built for the robot's arm and camera) and the given check;
    /// `margin_m` is the clearance of [`ReachCheck::PoseClear`]'s collision check (the edge's).
    /// Errors for an invalid robot or a map of another arm.
    pub fn new(
        robot: Robot,
        map: Arc<ReachabilityMap>,
        check: ReachCheck,
        margin_m: f64,
    ) -> Result<Self> {
        let robot = Robot::new(robot.arm, robot.mount)?;
        let built_for = map.params();
        let arm = &robot.arm;
        if built_for.dh != arm.dh
            || built_for.limits != arm.limits
            || built_for.flange_from_camera != arm.flange_from_camera
        {
            return Err(invalid("map", "built for another arm or camera"));
        }
        if !(margin_m.is_finite() && (0.0..=MAX_MARGIN_M).contains(&margin_m)) {
            return Err(invalid(
                "margin_m",
                format!("must be in [0, {MAX_MARGIN_M}] m"),
            ));
        }
        Ok(Self {
            robot,
            map,
            check,
            margin_m,
        })
    }

    pub fn robot(&self) -> &Robot {
        &self.robot
    }

    pub fn map(&self) -> &ReachabilityMap {
        &self.map
    }

    pub fn check(&self) -> ReachCheck {
        self.check
    }

    /// Can the robot bring its camera to `world_from_camera` for some mount state? False for a
    /// non-finite pose (never a panic).
    pub fn can_reach(&self, world_from_camera: &Isometry3<f64>) -> bool {
        let finite = |v: &[f64]| v.iter().all(|c| c.is_finite());
        if !(finite(world_from_camera.translation.vector.as_slice())
            && finite(world_from_camera.rotation.coords.as_slice()))
        {
            return false;
        }
        let eye = Point3::from(world_from_camera.translation.vector);
        if !self
            .map
            .reachable_for_some_state(&self.robot.mount, &eye)
            .unwrap_or(false)
        {
            return false;
        }
        if self.check == ReachCheck::Position {
            return true;
        }
        let Ok(states) = self.robot.suggest_mount_states(world_from_camera) else {
            return false;
        };
        for state in states {
            let solutions = self
                .robot
                .solve_camera_pose(world_from_camera, &state)
                .unwrap_or_default();
            if solutions.is_empty() {
                continue;
            }
            if self.check == ReachCheck::Pose {
                return true;
            }
            // The edge commits to the first state with solutions: only its solutions count.
            let Ok(structure) = self.robot.mount.structure(&state) else {
                return false;
            };
            let world = CollisionWorld::obstacles(&structure).with_margin(self.margin_m);
            return solutions
                .iter()
                .any(|q| matches!(self.robot.check_configuration(q, &state, &world), Ok(None)));
        }
        false
    }
}

type SharedMaps = Mutex<Vec<(ReachabilityParams, Arc<ReachabilityMap>)>>;

/// The map for `params`, built on first use and shared for the life of the process (no file
/// I/O). Concurrent first callers wait for one build.
pub fn shared_reachability_map(params: &ReachabilityParams) -> Result<Arc<ReachabilityMap>> {
    static MAPS: OnceLock<SharedMaps> = OnceLock::new();
    let maps = MAPS.get_or_init(|| Mutex::new(Vec::new()));
    // A panic elsewhere while holding the lock leaves the list valid: keep using it.
    let mut maps = maps.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    if let Some((_, map)) = maps.iter().find(|(p, _)| p == params) {
        return Ok(Arc::clone(map));
    }
    let map = Arc::new(ReachabilityMap::build(params)?);
    maps.push((params.clone(), Arc::clone(&map)));
    Ok(map)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::{ArmModel, Interval, MountState};

    fn reach(robot: Robot, check: ReachCheck) -> ViewReachability {
        let map = shared_reachability_map(&ReachabilityParams::paper(&robot.arm)).unwrap();
        ViewReachability::new(robot, map, check, 0.02).unwrap()
    }

    fn look_at(eye: &Point3<f64>, target: &Point3<f64>) -> Isometry3<f64> {
        glasshouse_geom::look_at(eye, target)
    }

    #[test]
    fn the_shared_map_is_built_once() {
        let params = ReachabilityParams::paper(&ArmModel::ur5e());
        let (a, b) = (
            shared_reachability_map(&params).unwrap(),
            shared_reachability_map(&params).unwrap(),
        );
        assert!(Arc::ptr_eq(&a, &b));
    }

    #[test]
    fn poses_the_arm_reaches_are_accepted() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for robot in [Robot::scenario_one(), Robot::scenario_two()] {
            let position = reach(robot.clone(), ReachCheck::Position);
            let pose = reach(robot.clone(), ReachCheck::Pose);
            let mut misses = 0;
            for _ in 0..200 {
                let limits = &robot.arm.limits;
                let q = std::array::from_fn(|i| rng.gen_range(limits.lower[i]..=limits.upper[i]));
                // A state the placement heuristic suggests, so the edge would try it.
                let state = match robot.mount {
                    crate::Mount::Fixed { .. } => MountState::Fixed,
                    _ => {
                        let probe = Isometry3::translation(1.0, 1.0, 1.0);
                        robot.suggest_mount_states(&probe).unwrap()[0]
                    }
                };
                let goal = robot.world_from_camera(&q, &state).unwrap();
                // Sampled continuously: allow the rare boundary miss of the 10° map.
                misses += usize::from(!position.can_reach(&goal));
                if robot.mount == crate::Mount::scenario_one() {
                    assert_eq!(pose.can_reach(&goal), position.can_reach(&goal), "{q:?}");
                }
            }
            assert!(misses <= 1, "{misses}");
        }
    }

    #[test]
    fn the_pose_check_agrees_with_the_edges_placement() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let robots = [
            Robot::scenario_one(),
            Robot::scenario_two(),
            Robot::row(Interval::new(0.0, 3.0)),
        ];
        for robot in robots {
            let pose = reach(robot.clone(), ReachCheck::Pose);
            let position = reach(robot.clone(), ReachCheck::Position);
            let (mut accepted, mut rejected, mut map_misses) = (0, 0, 0);
            for _ in 0..300 {
                let eye = Point3::new(
                    rng.gen_range(-1.5..4.5),
                    rng.gen_range(-1.5..1.5),
                    rng.gen_range(0.0..2.5),
                );
                let dir = Vector3::new(
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                );
                let goal = look_at(&eye, &(eye + dir));
                let placed = robot.place_mount_for(&goal, None).is_ok();
                let in_map = position.can_reach(&goal);
                assert_eq!(pose.can_reach(&goal), placed && in_map, "{eye:?} {dir:?}");
                // The map misses a reachable position only in a rare boundary cell.
                map_misses += usize::from(placed && !in_map);
                if placed {
                    accepted += 1;
                } else {
                    rejected += 1;
                }
            }
            assert!(accepted > 10 && rejected > 10, "{accepted} {rejected}");
            assert!(map_misses <= 1, "{map_misses}");
        }
    }

    #[test]
    fn far_and_non_finite_poses_are_rejected() {
        for check in [
            ReachCheck::Position,
            ReachCheck::Pose,
            ReachCheck::PoseClear,
        ] {
            let reach = reach(Robot::scenario_one(), check);
            let far = look_at(&Point3::new(5.0, 0.0, 1.0), &Point3::new(6.0, 0.0, 1.0));
            assert!(!reach.can_reach(&far));
            let nan = Isometry3::translation(f64::NAN, 0.0, 1.0);
            assert!(!reach.can_reach(&nan));
            let mut bad_rotation =
                look_at(&Point3::new(0.3, 0.3, 1.0), &Point3::new(0.7, 0.5, 0.8));
            bad_rotation.rotation = nalgebra::UnitQuaternion::new_unchecked(
                nalgebra::Quaternion::new(f64::NAN, 0.0, 0.0, 0.0),
            );
            assert!(!reach.can_reach(&bad_rotation));
            let near = look_at(&Point3::new(0.3, 0.3, 1.0), &Point3::new(0.7, 0.5, 0.8));
            assert!(reach.can_reach(&near), "{check:?}");
        }
    }

    #[test]
    fn a_map_of_another_arm_or_a_bad_margin_is_an_error() {
        let robot = Robot::scenario_one();
        let mut other = ReachabilityParams::paper(&robot.arm);
        other.step_rad = 30f64.to_radians();
        other.flange_from_camera = Isometry3::identity();
        let map = Arc::new(ReachabilityMap::build(&other).unwrap());
        assert!(ViewReachability::new(robot.clone(), map, ReachCheck::Pose, 0.02).is_err());
        let map = shared_reachability_map(&ReachabilityParams::paper(&robot.arm)).unwrap();
        for margin_m in [f64::NAN, -0.1, 2.0] {
            let made =
                ViewReachability::new(robot.clone(), Arc::clone(&map), ReachCheck::Pose, margin_m);
            assert!(made.is_err());
        }
    }
}
