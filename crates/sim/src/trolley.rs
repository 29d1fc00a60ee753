//! The simulated robot of a scene: a UR5e on the scenario's mount that executes views.

use glasshouse_arm::{ArmPose, ExecuteSettings, Robot};
use nalgebra::{Isometry3, Point3};

use crate::Scene;

/// The outcome of [`SimArm::execute_first_reachable`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Executed {
    /// Index of the executed goal in the list.
    pub index: usize,
    /// Arm and mount motion time, without capture time.
    pub motion_s: f64,
}

/// The arm of a simulated trolley and where it is.
#[derive(Clone, Debug)]
pub struct SimArm {
    robot: Robot,
    pose: ArmPose,
    settings: ExecuteSettings,
}

impl SimArm {
    /// The scene's robot placed with its camera at the scene's initial view.
    pub fn new(scene: &Scene) -> Result<Self, glasshouse_arm::ArmError> {
        let robot = scene.robot();
        let pose = robot.pose_at(&scene.initial_camera_pose(), &[], Scene::ARM_CLEARANCE_M)?;
        Ok(Self {
            robot,
            pose,
            settings: ExecuteSettings {
                margin_m: Scene::ARM_CLEARANCE_M,
                ..ExecuteSettings::default()
            },
        })
    }

    pub fn robot(&self) -> &Robot {
        &self.robot
    }

    pub fn pose(&self) -> &ArmPose {
        &self.pose
    }

    /// The camera pose now.
    pub fn world_from_camera(&self) -> Isometry3<f64> {
        self.robot
            .world_from_camera(&self.pose.joints, &self.pose.mount)
            .unwrap_or_else(|_| Isometry3::identity())
    }

    /// Algorithm 1's "moveToPose, else the next view": moves to the first goal whose camera
    /// position is clear of the scene's solids and that the arm reaches on a collision-free
    /// path. None (and no motion) when no goal can be reached.
    pub fn execute_first_reachable(
        &mut self,
        scene: &Scene,
        goals: &[Isometry3<f64>],
    ) -> Option<Executed> {
        let motion = goals.iter().enumerate().find_map(|(index, goal)| {
            let eye = Point3::from(goal.translation.vector);
            if !scene.is_camera_position_free(&eye) {
                return None;
            }
            self.robot
                .motion_to(&self.pose, goal, &[], &self.settings)
                .ok()
                .map(|m| (index, m))
        })?;
        let (index, motion) = motion;
        self.pose = motion.target;
        Some(Executed {
            index,
            motion_s: motion.duration_s,
        })
    }
}
