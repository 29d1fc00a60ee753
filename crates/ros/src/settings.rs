//! What a ROS 2 or bag source needs to know: topics and frames (the camera's side), and what ROS
//! messages do not carry (the trolley's side: workspace, sampling region, robot, depth range).

use glasshouse_arm::Robot;
use glasshouse_geom::Aabb;
use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::rmw::{Durability, Qos};

/// Where the camera's pose comes from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseSource {
    /// `world_frame` → `camera_frame` through `/tf` and `/tf_static`.
    #[default]
    Tf,
    /// `sensor_msgs/JointState` through the trolley's robot description (its UR parameters,
    /// mount and hand-eye transform in [`RosTrolley::robot`]).
    JointStates,
}

/// The QoS of each topic, announced in the graph and acted on: a `transient_local`
/// subscription asks the publishers' caches for what they latched before it joined.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TopicQos {
    /// Colour, depth and camera info.
    pub camera: Qos,
    pub tf: Qos,
    pub tf_static: Qos,
    pub joint_states: Qos,
    /// The chosen and the ranked views (volatile only: a latched view would move an arm
    /// driver that starts later to a view nobody sent it).
    pub views: Qos,
    pub view_reached: Qos,
}

impl Default for TopicQos {
    fn default() -> Self {
        Self {
            camera: Qos::reliable(10),
            tf: Qos::reliable(100),
            tf_static: Qos::latched(1),
            joint_states: Qos::reliable(10),
            views: Qos::reliable(10),
            view_reached: Qos::reliable(10),
        }
    }
}

/// Topics, frames and pairing of a RealSense-style camera driver and the arm's driver. The
/// defaults are `realsense2_camera`'s topics with `align_depth` on, and TF from `world`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RosTopics {
    /// `sensor_msgs/Image`, rgb8 or bgr8.
    pub colour: String,
    /// `sensor_msgs/Image` aligned to the colour image, 16UC1 (see `depth_unit_m`) or 32FC1 metres.
    pub depth: String,
    /// `sensor_msgs/CameraInfo` of the colour image.
    pub camera_info: String,
    /// `tf2_msgs/TFMessage`, and the latched static transforms.
    pub tf: String,
    pub tf_static: String,
    /// The frame poses are expressed in (the map's world frame, z up).
    pub world_frame: String,
    /// The colour camera's optical frame (x right, y down, z forward).
    pub camera_frame: String,
    /// Colour, depth and the pose belong to one frame when their stamps differ by at most this.
    pub pair_tolerance_ms: u64,
    /// A colour image waits this long (in stamp time) for its depth and pose before it is dropped.
    pub wait_ms: u64,
    /// Metres per unit of a 16UC1 depth image (RealSense: 0.001).
    pub depth_unit_m: f32,
    /// The camera's valid depth range, metres (what the messages do not say).
    pub min_range_m: f32,
    pub max_range_m: f32,
    /// Where the chosen view is published (`geometry_msgs/PoseStamped` in `world_frame`).
    pub view: String,
    /// Where the ranked views are published (`geometry_msgs/PoseArray`, best first).
    pub ranked_views: String,
    /// The arm driver's answer to a view (`std_msgs/Bool`: reached, or not reachable).
    pub view_reached: String,
    /// How long to wait for that answer before the view counts as not reached.
    pub view_reached_timeout_ms: u64,
    /// Where the camera pose comes from: TF, or joint states through the robot description.
    pub pose_source: PoseSource,
    /// `sensor_msgs/JointState` of the arm and the mount's axes (with `joint_states`).
    pub joint_states: String,
    /// The arm's six joints in JointState, base to wrist (`ur_robot_driver`'s names).
    pub arm_joints: Vec<String>,
    /// The mount's axes in JointState, in the robot's axis order (gantry: x, y, extension;
    /// rail: position, lift); empty: the robot's own axis names.
    pub mount_joints: Vec<String>,
    /// QoS of every topic.
    pub qos: TopicQos,
}

impl Default for RosTopics {
    fn default() -> Self {
        Self {
            colour: "/camera/color/image_raw".into(),
            depth: "/camera/aligned_depth_to_color/image_raw".into(),
            camera_info: "/camera/color/camera_info".into(),
            tf: "/tf".into(),
            tf_static: "/tf_static".into(),
            world_frame: "world".into(),
            camera_frame: "camera_color_optical_frame".into(),
            pair_tolerance_ms: 20,
            wait_ms: 500,
            depth_unit_m: 0.001,
            min_range_m: 0.15,
            max_range_m: 3.0,
            view: "/glasshouse/next_view".into(),
            ranked_views: "/glasshouse/ranked_views".into(),
            view_reached: "/glasshouse/view_reached".into(),
            view_reached_timeout_ms: 30_000,
            pose_source: PoseSource::Tf,
            joint_states: "/joint_states".into(),
            arm_joints: [
                "shoulder_pan_joint",
                "shoulder_lift_joint",
                "elbow_joint",
                "wrist_1_joint",
                "wrist_2_joint",
                "wrist_3_joint",
            ]
            .map(String::from)
            .to_vec(),
            mount_joints: Vec::new(),
            qos: TopicQos::default(),
        }
    }
}

impl RosTopics {
    /// Every topic a name, tolerances and ranges in order.
    pub fn validate(&self) -> Result<(), String> {
        let topics = [
            &self.colour,
            &self.depth,
            &self.camera_info,
            &self.tf,
            &self.tf_static,
            &self.view,
            &self.ranked_views,
            &self.view_reached,
            &self.joint_states,
        ];
        if let Some(bad) = topics.iter().find(|t| !valid_topic(t)) {
            return Err(format!(
                "topic {bad:?}: letters, digits, '_' and '/' only, not empty"
            ));
        }
        if self.world_frame.is_empty() || self.camera_frame.is_empty() {
            return Err("world_frame and camera_frame must be named".into());
        }
        let range_ok = self.min_range_m > 0.0 && self.max_range_m > self.min_range_m;
        if !range_ok || !self.max_range_m.is_finite() {
            return Err(format!(
                "depth range {}..{} m: need 0 < min < max",
                self.min_range_m, self.max_range_m
            ));
        }
        if !(self.depth_unit_m > 0.0 && self.depth_unit_m.is_finite()) {
            return Err(format!("depth_unit_m {} must be > 0", self.depth_unit_m));
        }
        if self.arm_joints.len() != glasshouse_arm::JOINT_COUNT {
            return Err(format!(
                "arm_joints names {} joints; the arm has {}",
                self.arm_joints.len(),
                glasshouse_arm::JOINT_COUNT
            ));
        }
        if self.qos.views.durability == Durability::TransientLocal {
            return Err(
                "qos.views must be volatile: a latched view would move an arm driver \
                        that starts later to a view nobody sent it"
                    .into(),
            );
        }
        Ok(())
    }
}

fn valid_topic(topic: &str) -> bool {
    let name = topic.trim_start_matches('/');
    !name.is_empty()
        && !name.ends_with('/')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '/')
}

/// The trolley behind a ROS 2 camera: what planners need and ROS messages do not carry. The
/// defaults are the simulated scenario 2 trolley's (the ceiling gantry over four plants).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RosTrolley {
    /// Where the camera centre can be placed (world frame, metres).
    pub camera_workspace: Aabb,
    /// Where view targets may lie: the plants.
    pub sampling_region: Aabb,
    /// The arm and its mount, for planners to propose only reachable views; null: unknown.
    pub robot: Option<Robot>,
    /// A name for the dashboard and the recordings.
    pub scenario: String,
}

impl Default for RosTrolley {
    fn default() -> Self {
        Self {
            camera_workspace: Aabb::new(Point3::new(-1.1, -1.1, 0.2), Point3::new(1.1, 1.1, 1.6)),
            sampling_region: Aabb::new(Point3::new(-0.9, -0.9, 0.0), Point3::new(0.9, 0.9, 1.5)),
            robot: Some(Robot::scenario_two()),
            scenario: "ros2".into(),
        }
    }
}
