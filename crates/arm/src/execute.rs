//! Executing a view: the "moveToPose, else the next view" half of the paper's Algorithm 1.
//!
//! For a ranked list of camera goals, [`Robot::first_reachable`] returns the first the arm can
//! reach: a mount state from the placement heuristic, inverse kinematics, then a joint-space path
//! free of collisions with the mount's own structure (pole, floor, ceiling, trolley) and any
//! extra obstacles, with the time the motion takes.

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::{
    ArmError, CollisionWorld, JointVector, MotionLimits, MountState, Obstacle, Result, Robot,
};

/// Where the robot is: its joints and its mount's extra axes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ArmPose {
    pub joints: JointVector,
    pub mount: MountState,
}

/// A motion the robot can execute to bring its camera to a goal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewMotion {
    /// Index of the goal in the list given to [`Robot::first_reachable`].
    pub index: usize,
    pub target: ArmPose,
    /// The camera pose at `target` (the goal, up to the IK's round-off).
    pub world_from_camera: Isometry3<f64>,
    /// Arm and mount motion time (without capture time).
    pub duration_s: f64,
}

/// What executing a view did: which goal of the list, and how long the motion took.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Executed {
    /// Index of the executed goal in the list.
    pub index: usize,
    /// Arm and mount motion time, without capture time.
    pub motion_s: f64,
}

impl From<ViewMotion> for Executed {
    fn from(motion: ViewMotion) -> Self {
        Self {
            index: motion.index,
            motion_s: motion.duration_s,
        }
    }
}

/// Clearance the camera centre keeps from every solid the trolley knows of (a view closer than
/// this is not taken, and a planner does not propose it).
pub const CAMERA_CLEARANCE_M: f64 = 0.05;

/// Clearance every link capsule keeps from the mount's structure when the arm is placed or moved.
pub const ARM_CLEARANCE_M: f64 = 0.02;

/// Settings of view execution.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExecuteSettings {
    pub limits: MotionLimits,
    /// Largest joint step between collision-checked configurations along a path.
    pub path_step_rad: f64,
    /// Clearance added to every link capsule.
    pub margin_m: f64,
}

impl Default for ExecuteSettings {
    fn default() -> Self {
        Self {
            limits: MotionLimits::default(),
            path_step_rad: 5f64.to_radians(),
            margin_m: ARM_CLEARANCE_M,
        }
    }
}

impl Robot {
    /// The motion to `goal` from `from`, or why there is none. The mount moves to the first
    /// suggested state with IK solutions; solutions are tried closest first, and the first whose
    /// path (checked at the target mount state) is collision-free is taken.
    pub fn motion_to(
        &self,
        from: &ArmPose,
        goal: &Isometry3<f64>,
        obstacles: &[Obstacle],
        settings: &ExecuteSettings,
    ) -> Result<ViewMotion> {
        let (state, solutions) = self.place_mount_for(goal, Some(&from.joints))?;
        let mut world_obstacles = self.mount.structure(&state)?;
        world_obstacles.extend_from_slice(obstacles);
        let world = CollisionWorld::obstacles(&world_obstacles).with_margin(settings.margin_m);
        for joints in solutions {
            if self
                .check_path(
                    &from.joints,
                    &joints,
                    &state,
                    settings.path_step_rad,
                    &world,
                )?
                .is_some()
            {
                continue;
            }
            let duration_s = settings.limits.motion_time(
                &self.mount,
                (&from.joints, &from.mount),
                (&joints, &state),
            )?;
            return Ok(ViewMotion {
                index: 0,
                target: ArmPose {
                    joints,
                    mount: state,
                },
                world_from_camera: self.world_from_camera(&joints, &state)?,
                duration_s,
            });
        }
        Err(ArmError::Unreachable)
    }

    /// Algorithm 1's "moveToPose, else the next view": the first goal of `goals` (best first)
    /// that `camera_position_free` accepts (the camera's clearance from what the caller knows of
    /// the world) and the robot can move to on a collision-free path, with its index; None when
    /// none can be reached. Goals that are errors (non-finite, out of reach, in collision) are
    /// skipped: a bad view never stops the trolley.
    pub fn first_reachable(
        &self,
        from: &ArmPose,
        goals: &[Isometry3<f64>],
        obstacles: &[Obstacle],
        settings: &ExecuteSettings,
        camera_position_free: impl Fn(&nalgebra::Point3<f64>) -> bool,
    ) -> Option<ViewMotion> {
        goals.iter().enumerate().find_map(|(index, goal)| {
            if !camera_position_free(&goal.translation.vector.into()) {
                return None;
            }
            self.motion_to(from, goal, obstacles, settings)
                .ok()
                .map(|m| ViewMotion { index, ..m })
        })
    }

    /// A collision-free pose with the camera at `goal`, for starting a run there (no path check:
    /// the robot is placed, not moved).
    pub fn pose_at(
        &self,
        goal: &Isometry3<f64>,
        obstacles: &[Obstacle],
        margin_m: f64,
    ) -> Result<ArmPose> {
        let (state, solutions) = self.place_mount_for(goal, None)?;
        let mut world_obstacles = self.mount.structure(&state)?;
        world_obstacles.extend_from_slice(obstacles);
        let world = CollisionWorld::obstacles(&world_obstacles).with_margin(margin_m);
        for joints in solutions {
            if self.check_configuration(&joints, &state, &world)?.is_none() {
                return Ok(ArmPose {
                    joints,
                    mount: state,
                });
            }
        }
        Err(ArmError::Unreachable)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glasshouse_geom::look_at;
    use nalgebra::Point3;

    fn start(robot: &Robot) -> ArmPose {
        let goal = look_at(&Point3::new(0.35, 0.0, 1.1), &Point3::new(0.8, 0.0, 0.8));
        robot
            .pose_at(&goal, &[], 0.02)
            .expect("a start pose in front of the pole")
    }

    #[test]
    fn reaches_a_near_view_and_skips_unreachable_ones() {
        let robot = Robot::scenario_one();
        let from = start(&robot);
        let far = look_at(&Point3::new(3.0, 0.0, 1.0), &Point3::new(4.0, 0.0, 1.0));
        let bad = Isometry3::translation(f64::NAN, 0.0, 1.0);
        let near = look_at(&Point3::new(0.3, 0.3, 1.0), &Point3::new(0.7, 0.5, 0.8));
        let motion = robot
            .first_reachable(
                &from,
                &[far, bad, near],
                &[],
                &ExecuteSettings::default(),
                |_| true,
            )
            .expect("the near view is reachable");
        assert_eq!(motion.index, 2);
        let reached = motion.world_from_camera.translation.vector;
        assert!((reached - near.translation.vector).norm() < 1e-6);
        assert!(motion.duration_s > 0.0 && motion.duration_s < 10.0);
        assert!(robot
            .first_reachable(&from, &[far, bad], &[], &ExecuteSettings::default(), |_| {
                true
            })
            .is_none());
        // A goal whose camera position the caller rules out is skipped like an unreachable one.
        let not_near = |p: &Point3<f64>| (p.coords - near.translation.vector).norm() > 0.01;
        let settings = ExecuteSettings::default();
        assert!(robot
            .first_reachable(&from, &[far, near], &[], &settings, not_near)
            .is_none());
    }

    #[test]
    fn an_obstacle_on_every_path_makes_the_view_unreachable() {
        let robot = Robot::scenario_one();
        let from = start(&robot);
        let goal = look_at(&Point3::new(-0.3, 0.3, 1.0), &Point3::new(-0.7, 0.5, 0.8));
        let settings = ExecuteSettings::default();
        assert!(robot.motion_to(&from, &goal, &[], &settings).is_ok());
        // A ball enclosing the goal: every configuration reaching it collides.
        let ball = Obstacle::Capsule {
            a: Point3::from(goal.translation.vector),
            b: Point3::from(goal.translation.vector),
            radius_m: 0.15,
        };
        assert!(matches!(
            robot.motion_to(&from, &goal, &[ball], &settings),
            Err(ArmError::Unreachable)
        ));
    }

    #[test]
    fn staying_put_takes_no_time() {
        let robot = Robot::scenario_one();
        let from = start(&robot);
        let here = robot
            .world_from_camera(&from.joints, &from.mount)
            .expect("fk");
        let motion = robot
            .motion_to(&from, &here, &[], &ExecuteSettings::default())
            .expect("the current pose is reachable");
        assert!(motion.duration_s < 1e-6, "{}", motion.duration_s);
    }

    #[test]
    fn the_estimated_motion_time_is_the_executed_one() {
        // The gantry moves the mount as well as the arm: the estimate must place both as a
        // motion does.
        let robot = Robot::scenario_two();
        let settings = ExecuteSettings::default();
        let from_goal = look_at(&Point3::new(0.2, -0.3, 1.0), &Point3::new(0.2, 0.2, 0.9));
        let from = robot.pose_guess(&from_goal).expect("a placement");
        let here = robot
            .world_from_camera(&from.joints, &from.mount)
            .expect("fk");
        assert!(
            here.translation
                .vector
                .metric_distance(&from_goal.translation.vector)
                < 1e-6
        );
        let mut compared = 0;
        for (x, z) in [(-0.4, 0.8), (0.5, 1.2), (0.0, 0.6), (0.6, 0.9)] {
            let goal = look_at(&Point3::new(x, -0.35, z), &Point3::new(x * 0.5, 0.2, 0.9));
            let Ok(motion) = robot.motion_to(&from, &goal, &[], &settings) else {
                continue;
            };
            let estimate = robot
                .motion_time_to(&from, &goal, &settings.limits)
                .expect("reachable, so estimated");
            assert!(
                (estimate - motion.duration_s).abs() < 1e-9,
                "{estimate} {motion:?}"
            );
            assert!(estimate > 0.1, "a real move: {estimate}");
            compared += 1;
        }
        assert!(compared >= 3, "only {compared} goals reachable");
        let nowhere = Isometry3::translation(f64::NAN, 0.0, 1.0);
        assert!(robot
            .motion_time_to(&from, &nowhere, &settings.limits)
            .is_err());
    }
}
