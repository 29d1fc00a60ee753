//! The simulated robot of a scene: a UR5e on the scenario's mount that executes views.

use glasshouse_arm::{ArmPose, ExecuteSettings, Executed, Robot};
use nalgebra::Isometry3;

use crate::Scene;

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

    /// Moves to the first goal whose camera position is clear of the scene's solids and that
    /// the arm reaches on a collision-free path ([`Robot::first_reachable`]). None (and no
    /// motion) when no goal can be reached.
    pub fn execute_first_reachable(
        &mut self,
        scene: &Scene,
        goals: &[Isometry3<f64>],
    ) -> Option<Executed> {
        let free = |eye: &nalgebra::Point3<f64>| scene.is_camera_position_free(eye);
        let motion = self
            .robot
            .first_reachable(&self.pose, goals, &[], &self.settings, free)?;
        self.pose = motion.target;
        Some(motion.into())
    }
}
