//! The camera's pose from `sensor_msgs/JointState` through the trolley's robot description: the
//! arm's six joints and the mount's axes, looked up by name, through the robot's forward
//! kinematics (UR parameters, mount, hand-eye transform).

use glasshouse_arm::{JointVector, Robot, JOINT_COUNT};
use nalgebra::Isometry3;

use crate::msg::JointState;
use crate::settings::RosTopics;

/// `world_from_camera` at the state's stamp; an error says which joint is missing or wrong.
pub fn world_from_camera(
    state: &JointState,
    topics: &RosTopics,
    robot: &Robot,
) -> Result<Isometry3<f64>, String> {
    if state.position.len() != state.name.len() {
        return Err(format!(
            "{} names but {} positions",
            state.name.len(),
            state.position.len()
        ));
    }
    let position = |joint: &str| {
        state
            .name
            .iter()
            .position(|n| n == joint)
            .map(|i| state.position[i])
            .ok_or_else(|| format!("no joint {joint:?} (the state names {:?})", state.name))
    };
    let mut q: JointVector = [0.0; JOINT_COUNT];
    for (value, joint) in q.iter_mut().zip(&topics.arm_joints) {
        *value = position(joint)?;
    }
    let own_axes: Vec<String> = robot
        .mount
        .axis_names()
        .iter()
        .map(|n| n.to_string())
        .collect();
    let axes = if topics.mount_joints.is_empty() {
        &own_axes
    } else {
        &topics.mount_joints
    };
    let values = axes
        .iter()
        .map(|axis| position(axis))
        .collect::<Result<Vec<f64>, String>>()?;
    let mount = robot
        .mount
        .state_from_values(&values)
        .map_err(|e| format!("mount axes {axes:?}: {e}"))?;
    robot
        .world_from_camera(&q, &mount)
        .map_err(|e| format!("arm joints {q:?}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::{Header, Time};
    use glasshouse_arm::Interval;

    fn state(names: &[&str], position: &[f64]) -> JointState {
        JointState {
            header: Header {
                stamp: Time::from_ns(5),
                frame_id: String::new(),
            },
            name: names.iter().map(|n| n.to_string()).collect(),
            position: position.to_vec(),
            ..JointState::default()
        }
    }

    #[test]
    fn joint_states_give_the_robots_forward_kinematics_and_bad_ones_a_reason() {
        let robot = Robot::row(Interval::new(0.0, 4.0));
        let topics = RosTopics::default();
        let q = [0.3, -1.2, 1.4, -0.7, 1.5, 0.2];
        let mut names: Vec<&str> = topics.arm_joints.iter().map(String::as_str).collect();
        names.extend(["rail_position", "lift"]);
        // Any order, extra joints ignored.
        names.reverse();
        names.push("gripper");
        let mut values = vec![0.4, 1.5];
        values.extend(q.iter().rev());
        values.push(9.0);
        let mount = robot
            .mount
            .state_from_values(&[1.5, 0.4])
            .expect("in range");
        let want = robot.world_from_camera(&q, &mount).expect("finite");
        let got = world_from_camera(&state(&names, &values), &topics, &robot).expect("a pose");
        assert!((got.to_homogeneous() - want.to_homogeneous()).abs().max() < 1e-12);

        let missing = state(&names[1..], &values[1..]);
        let err = world_from_camera(&missing, &topics, &robot).expect_err("lift missing");
        assert!(err.contains("lift"), "{err}");
        let mut outside = values.clone();
        outside[1] = 99.0; // the rail
        let err = world_from_camera(&state(&names, &outside), &topics, &robot)
            .expect_err("rail out of range");
        assert!(err.contains("rail_position"), "{err}");
        let short = state(&names, &values[1..]);
        assert!(world_from_camera(&short, &topics, &robot).is_err());
        let mut nan = values;
        nan[3] = f64::NAN;
        assert!(world_from_camera(&state(&names, &nan), &topics, &robot).is_err());
    }
}
