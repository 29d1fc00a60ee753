//! The ROS 2 messages a trolley speaks, in CDR: what a camera and TF publish, what an arm
//! driver takes. Field order and types follow the `.msg` definitions exactly (CDR has no field
//! names), so these decode what `rosbags`, `rclcpp` or `rmw_zenoh` write and the reverse.

use serde::{Deserialize, Serialize};

use crate::RosError;

/// The encapsulation header of little-endian plain CDR (`CDR_LE`), first on every payload.
const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];
/// The same for big-endian CDR (`CDR_BE`), which other peers may send.
const CDR_BE_HEADER: [u8; 2] = [0x00, 0x00];

/// A message serialised as ROS 2 does: the 4-byte encapsulation header, then little-endian CDR.
pub fn encode_cdr<T: Serialize>(message: &T) -> Vec<u8> {
    let body = cdr_encoding::to_vec::<T, byteorder::LittleEndian>(message)
        // Serialising plain structs of numbers, strings and sequences cannot fail.
        .unwrap_or_default();
    let mut out = Vec::with_capacity(4 + body.len());
    out.extend_from_slice(&CDR_LE_HEADER);
    out.extend_from_slice(&body);
    out
}

/// A CDR payload (either byte order, after its encapsulation header) as `T`.
pub fn decode_cdr<T: for<'de> Deserialize<'de>>(payload: &[u8], what: &str) -> Result<T, RosError> {
    let bad = |reason: String| RosError::Cdr {
        what: what.to_string(),
        reason,
    };
    let (header, body) = payload.split_at_checked(4).ok_or_else(|| {
        bad(format!(
            "{} bytes, shorter than the CDR header",
            payload.len()
        ))
    })?;
    let decoded = match header[..2] {
        [0x00, 0x01] => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body),
        _ if header[..2] == CDR_BE_HEADER => {
            cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body)
        }
        _ => return Err(bad(format!("unknown encapsulation {:02x?}", &header[..2]))),
    };
    decoded.map(|(m, _)| m).map_err(|e| bad(e.to_string()))
}

/// `builtin_interfaces/Time`.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize,
)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// Nanoseconds since the epoch (negative times clamp to 0).
    pub fn as_ns(&self) -> u64 {
        let sec = u64::try_from(self.sec).unwrap_or(0);
        sec * 1_000_000_000 + u64::from(self.nanosec)
    }

    pub fn from_ns(ns: u64) -> Self {
        Self {
            sec: i32::try_from(ns / 1_000_000_000).unwrap_or(i32::MAX),
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// `std_msgs/Header`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/Image`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/RegionOfInterest`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

/// `sensor_msgs/CameraInfo`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

/// `geometry_msgs/Vector3` and `geometry_msgs/Point` (the same layout).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/Quaternion`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

/// `geometry_msgs/Transform`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// `geometry_msgs/TransformStamped`: `header.frame_id` is the parent, `child_frame_id` the child.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `geometry_msgs/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Vector3,
    pub orientation: Quaternion,
}

/// `geometry_msgs/PoseStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// `geometry_msgs/PoseArray`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseArray {
    pub header: Header,
    pub poses: Vec<Pose>,
}

/// `std_msgs/Bool`: the arm driver's "view reached" (true) or "view failed" (false).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Bool {
    pub data: bool,
}

/// `sensor_msgs/JointState`: the arm's (and its mount's) joints at one stamp, by name.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    /// Radians (revolute) or metres (prismatic).
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}

/// A ROS 2 message type: its name as `ros2 topic list -t` shows it, and its type hash as
/// rmw_zenoh's keys and liveliness tokens carry it (ROS 2 Iron and later).
pub trait RosMessage: Serialize + for<'de> Deserialize<'de> {
    /// `package/msg/Name`.
    const TYPE_NAME: &'static str;
    /// `RIHS01_` and the SHA-256 of the type description, as rosidl computes it.
    const TYPE_HASH: &'static str;
}

macro_rules! ros_message {
    ($($t:ty => $name:literal, $hash:literal;)*) => {
        $(impl RosMessage for $t {
            const TYPE_NAME: &'static str = $name;
            const TYPE_HASH: &'static str = $hash;
        })*
    };
}

// The hashes as `rosbags` computes them for Jazzy (the same for Humble's definitions of these
// types); the stand-in ROS 2 node of tests/tests/ros.rs checks every hash our tokens announce.
ros_message!(
    Image => "sensor_msgs/msg/Image",
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47";
    CameraInfo => "sensor_msgs/msg/CameraInfo",
        "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275";
    TfMessage => "tf2_msgs/msg/TFMessage",
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087";
    PoseStamped => "geometry_msgs/msg/PoseStamped",
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8";
    PoseArray => "geometry_msgs/msg/PoseArray",
        "RIHS01_af0cc36d190e104d546d168d6b39df04fa4b4ccecf59cb4c9ed328d3d5004aa0";
    Bool => "std_msgs/msg/Bool",
        "RIHS01_feb91e995ff9ebd09c0cb3d2aed18b11077585839fb5db80193b62d74528f6c9";
    JointState => "sensor_msgs/msg/JointState",
        "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e";
);
