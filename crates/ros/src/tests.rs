#![allow(clippy::unwrap_used)]

use crate::assemble::{transform_of, DropReason, FrameAssembler};
use crate::msg::*;
use crate::settings::RosTopics;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

const T0_NS: u64 = 1_767_225_600_000_000_000;
const PERIOD_NS: u64 = 200_000_000;

fn header(stamp_ns: u64, frame_id: &str) -> Header {
    Header {
        stamp: Time::from_ns(stamp_ns),
        frame_id: frame_id.into(),
    }
}

fn colour(stamp_ns: u64, encoding: &str) -> Image {
    let (w, h) = (4u32, 3u32);
    Image {
        header: header(stamp_ns, "camera_color_optical_frame"),
        height: h,
        width: w,
        encoding: encoding.into(),
        is_bigendian: 0,
        step: w * 3,
        data: (0..w * h * 3).map(|i| i as u8).collect(),
    }
}

fn depth_16(stamp_ns: u64) -> Image {
    let (w, h) = (4u32, 3u32);
    let mm: Vec<u16> = (0..w * h)
        .map(|i| if i == 5 { 0 } else { 500 + i as u16 })
        .collect();
    Image {
        header: header(stamp_ns, "camera_color_optical_frame"),
        height: h,
        width: w,
        encoding: "16UC1".into(),
        is_bigendian: 0,
        step: w * 2,
        data: mm.iter().flat_map(|d| d.to_le_bytes()).collect(),
    }
}

fn camera_info(stamp_ns: u64) -> CameraInfo {
    CameraInfo {
        header: header(stamp_ns, "camera_color_optical_frame"),
        height: 3,
        width: 4,
        distortion_model: "plumb_bob".into(),
        d: vec![0.0; 5],
        k: [3.0, 0.0, 2.0, 0.0, 3.0, 1.5, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [3.0, 0.0, 2.0, 0.0, 0.0, 3.0, 1.5, 0.0, 0.0, 0.0, 1.0, 0.0],
        ..Default::default()
    }
}

fn pose(i: u64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.1 * i as f64, -0.2, 1.0),
        UnitQuaternion::from_euler_angles(0.1, 0.2 * i as f64, -0.3),
    )
}

fn tf(stamp_ns: u64, parent: &str, child: &str, p: &Isometry3<f64>) -> TfMessage {
    TfMessage {
        transforms: vec![TransformStamped {
            header: header(stamp_ns, parent),
            child_frame_id: child.into(),
            transform: transform_of(p),
        }],
    }
}

#[test]
fn cdr_round_trips_and_matches_the_ros_layout() {
    let info = camera_info(T0_NS);
    let bytes = encode_cdr(&info);
    assert_eq!(&bytes[..4], &[0, 1, 0, 0], "CDR_LE encapsulation");
    // The stamp's seconds follow the header at offset 0 of the body.
    let sec = i32::from_le_bytes(bytes[4..8].try_into().unwrap());
    assert_eq!(sec, 1_767_225_600);
    let back: CameraInfo = decode_cdr(&bytes, "CameraInfo").unwrap();
    assert_eq!(back, info);
    // Truncated or foreign payloads are errors, never panics.
    for cut in [0, 3, 10, bytes.len() - 1] {
        assert!(
            decode_cdr::<CameraInfo>(&bytes[..cut], "CameraInfo").is_err(),
            "cut at {cut}"
        );
    }
    assert!(decode_cdr::<Image>(&[7, 7, 0, 0, 1, 2], "Image").is_err());
}

#[test]
fn frames_are_grouped_by_stamp_whatever_the_arrival_order() {
    let mut a = FrameAssembler::new(RosTopics::default());
    a.push_camera_info(camera_info(T0_NS));
    // Frame 1's colour, then frame 2's colour, then frame 1's depth and pose, then frame 2's.
    a.push_colour(colour(T0_NS, "rgb8"));
    a.push_colour(colour(T0_NS + PERIOD_NS, "bgr8"));
    let (frames, dropped) = a.poll(false);
    assert!(
        frames.is_empty() && dropped.is_empty(),
        "nothing complete yet"
    );
    a.push_depth(depth_16(T0_NS));
    a.push_tf(
        &tf(T0_NS, "world", "camera_color_optical_frame", &pose(1)),
        false,
    );
    a.push_depth(depth_16(T0_NS + PERIOD_NS));
    a.push_tf(
        &tf(
            T0_NS + PERIOD_NS,
            "world",
            "camera_color_optical_frame",
            &pose(2),
        ),
        false,
    );
    let (frames, dropped) = a.poll(false);
    assert!(dropped.is_empty(), "{dropped:?}");
    assert_eq!(frames.len(), 2);
    assert_eq!(frames[0].stamp_ns, T0_NS);
    let (f1, f2) = (&frames[0].frame, &frames[1].frame);
    assert_eq!(f1.world_from_camera, pose(1));
    assert!((f2.world_from_camera.translation.vector - pose(2).translation.vector).norm() < 1e-12);
    assert_eq!(
        (f1.intrinsics.fx, f1.intrinsics.cx, f1.intrinsics.cy),
        (3.0, 2.0, 1.5)
    );
    assert_eq!(f1.depth[0], 500);
    assert_eq!(f1.depth[5], 0, "invalid stays invalid");
    assert_eq!(&f1.rgb[..3], &[0, 1, 2]);
    assert_eq!(&f2.rgb[..3], &[2, 1, 0], "bgr8 is swapped to rgb");
}

#[test]
fn a_pose_through_a_chain_of_transforms_and_float_depth() {
    let mut a = FrameAssembler::new(RosTopics::default());
    a.push_camera_info(camera_info(T0_NS));
    let world_from_base = pose(3);
    let base_from_camera = pose(4);
    // The mount is static (stamped long after the frame, when its publisher started: a static
    // transform makes no frame late); the arm's link moves.
    a.push_tf(
        &tf(
            T0_NS + 3_600_000_000_000,
            "world",
            "base_link",
            &world_from_base,
        ),
        true,
    );
    a.push_tf(
        &tf(
            T0_NS + 5_000_000,
            "base_link",
            "camera_color_optical_frame",
            &base_from_camera,
        ),
        false,
    );
    a.push_colour(colour(T0_NS, "rgb8"));
    let (frames, dropped) = a.poll(false);
    assert!(
        frames.is_empty() && dropped.is_empty(),
        "{dropped:?}: waits for its depth"
    );
    let mut depth = depth_16(T0_NS);
    depth.encoding = "32FC1".into();
    depth.step = 16;
    depth.data = [
        0.5f32,
        f32::NAN,
        -1.0,
        70.0,
        1.2344,
        0.0,
        0.5,
        0.5,
        0.5,
        0.5,
        0.5,
        0.5,
    ]
    .iter()
    .flat_map(|d| d.to_le_bytes())
    .collect();
    a.push_depth(depth);
    let (frames, dropped) = a.poll(false);
    assert!(dropped.is_empty(), "{dropped:?}");
    let f = &frames[0].frame;
    let want = world_from_base * base_from_camera;
    assert!((f.world_from_camera.translation.vector - want.translation.vector).norm() < 1e-12);
    assert_eq!(
        &f.depth[..6],
        &[500, 0, 0, 0, 1234, 0],
        "NaN, negative and beyond u16 mm are 0"
    );
}

#[test]
fn bad_frames_are_counted_drops_with_reasons() {
    let mut a = FrameAssembler::new(RosTopics::default());
    a.push_camera_info(camera_info(T0_NS));
    let stamps: Vec<u64> = (0..4).map(|i| T0_NS + i * PERIOD_NS).collect();
    // 0: a colour encoding we cannot read; 1: depth of another size; 2: no pose; 3: good.
    a.push_colour(colour(stamps[0], "yuv422"));
    a.push_colour(colour(stamps[1], "rgb8"));
    a.push_colour(colour(stamps[2], "rgb8"));
    a.push_colour(colour(stamps[3], "rgb8"));
    for (i, s) in stamps.iter().enumerate() {
        let mut d = depth_16(*s);
        if i == 1 {
            d.width = 2;
            d.step = 4;
        }
        a.push_depth(d);
        if i != 2 {
            a.push_tf(
                &tf(*s, "world", "camera_color_optical_frame", &pose(i as u64)),
                false,
            );
        }
    }
    let (frames, _) = a.poll(false);
    let (more, _) = a.poll(true);
    assert_eq!(frames.len() + more.len(), 1, "only the good frame");
    let drops = a.drops();
    assert_eq!(drops.get(&DropReason::Encoding), Some(&1));
    assert_eq!(drops.get(&DropReason::Size), Some(&1));
    assert_eq!(drops.get(&DropReason::MissingTf), Some(&1));
}

#[test]
fn images_whose_data_is_short_of_their_size_are_dropped_not_read_past() {
    let mut a = FrameAssembler::new(RosTopics::default());
    a.push_camera_info(camera_info(T0_NS));
    let mut c = colour(T0_NS, "rgb8");
    c.data.truncate(10);
    a.push_colour(c);
    a.push_depth(depth_16(T0_NS));
    a.push_tf(
        &tf(T0_NS, "world", "camera_color_optical_frame", &pose(1)),
        false,
    );
    let (frames, dropped) = a.poll(false);
    assert!(frames.is_empty());
    assert_eq!(dropped[0].reason, DropReason::Size);
}

#[test]
fn joint_states_pose_frames_through_the_robot_and_bad_ones_are_counted() {
    use crate::settings::PoseSource;
    let robot = glasshouse_arm::Robot::scenario_two();
    let topics = RosTopics {
        pose_source: PoseSource::JointStates,
        ..RosTopics::default()
    };
    let mut names = topics.arm_joints.clone();
    names.extend(robot.mount.axis_names().iter().map(|n| n.to_string()));
    let q = [0.2, -1.1, 1.3, -0.6, 1.4, 0.1];
    let mount = robot.mount.default_state();
    let mut position = q.to_vec();
    position.extend(mount.values());
    let state = |stamp_ns, position: Vec<f64>| JointState {
        header: header(stamp_ns, ""),
        name: names.clone(),
        position,
        ..JointState::default()
    };
    // Without a robot description a joint state gives no pose.
    let mut bare = FrameAssembler::new(topics.clone());
    assert!(bare
        .push_joint_state(&state(T0_NS, position.clone()))
        .is_err());
    assert_eq!(bare.drops().get(&DropReason::JointState), Some(&1));

    let mut a = FrameAssembler::new(topics).with_robot(Some(robot.clone()));
    a.push_camera_info(camera_info(T0_NS));
    a.push_colour(colour(T0_NS, "rgb8"));
    a.push_depth(depth_16(T0_NS));
    a.push_joint_state(&state(T0_NS + 1_000_000, position.clone()))
        .unwrap();
    let mut short = position.clone();
    short.pop();
    assert!(a
        .push_joint_state(&state(T0_NS + 2_000_000, short))
        .is_err());
    let (frames, dropped) = a.poll(false);
    assert!(dropped.is_empty(), "{dropped:?}");
    assert_eq!(frames.len(), 1);
    let want = robot.world_from_camera(&q, &mount).unwrap();
    let got = frames[0].frame.world_from_camera;
    assert!((got.to_homogeneous() - want.to_homogeneous()).abs().max() < 1e-12);
    assert_eq!(a.drops().get(&DropReason::JointState), Some(&1));
    // And the message itself survives CDR.
    let message = state(T0_NS, position);
    assert_eq!(
        decode_cdr::<JointState>(&encode_cdr(&message), "joint state").unwrap(),
        message
    );
}
