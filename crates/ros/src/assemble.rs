//! From ROS 2 camera and TF messages to the loop's [`RgbdFrame`]s: colour, aligned depth,
//! camera info and the camera's pose are grouped by their header stamps (not by arrival order),
//! checked and converted. What cannot become a frame is a counted drop with its reason.

use std::collections::{BTreeMap, HashMap, VecDeque};

use glasshouse_geom::CameraIntrinsics;
use glasshouse_pipeline::DEPTH_SCALE_M;
use glasshouse_proto::RgbdFrame;
use nalgebra::{Isometry3, Quaternion as NaQuaternion, Translation3, UnitQuaternion};

use glasshouse_arm::Robot;

use crate::msg::{
    CameraInfo, Header, Image, JointState, TfMessage, Time, Transform, TransformStamped,
};
use crate::settings::RosTopics;

/// Why a frame was dropped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum DropReason {
    /// A colour encoding other than rgb8/bgr8, or a depth encoding other than 16UC1/32FC1.
    Encoding,
    /// Sizes that disagree (data length against width × height × step, colour against depth
    /// or camera info).
    Size,
    /// No camera pose at the frame's stamp (TF from the world frame to the camera frame).
    MissingTf,
    /// Its colour or depth never found a partner within the pairing tolerance.
    Unpaired,
    /// No camera info yet, or one without focal lengths.
    CameraInfo,
    /// A message that does not decode as its type.
    Corrupt,
    /// A joint state that gives no camera pose (a joint missing or out of the mount's range,
    /// or no robot description).
    JointState,
}

impl DropReason {
    pub fn as_str(&self) -> &'static str {
        match self {
            DropReason::Encoding => "encoding",
            DropReason::Size => "size",
            DropReason::MissingTf => "missing_tf",
            DropReason::Unpaired => "unpaired",
            DropReason::CameraInfo => "camera_info",
            DropReason::Corrupt => "corrupt",
            DropReason::JointState => "joint_state",
        }
    }
}

/// A dropped frame: why, and a line for the log.
#[derive(Clone, Debug, PartialEq)]
pub struct Dropped {
    pub reason: DropReason,
    pub stamp_ns: u64,
    pub detail: String,
}

/// A camera frame ready for the loop, with its stamp.
#[derive(Clone, Debug, PartialEq)]
pub struct StampedFrame {
    pub stamp_ns: u64,
    pub frame: RgbdFrame,
}

/// Transforms by child frame, a short history of each (static ones hold at any time).
#[derive(Clone, Debug, Default)]
struct TfBuffer {
    edges: HashMap<String, VecDeque<(u64, String, Transform)>>,
    static_edges: HashMap<String, (String, Transform)>,
}

/// Transforms kept per child frame (about 10 s of a 100 Hz arm).
const TF_HISTORY: usize = 1024;

impl TfBuffer {
    fn insert(&mut self, message: &TfMessage, is_static: bool) {
        for t in &message.transforms {
            let child = t.child_frame_id.trim_start_matches('/').to_string();
            let parent = t.header.frame_id.trim_start_matches('/').to_string();
            if is_static {
                self.static_edges.insert(child, (parent, t.transform));
                continue;
            }
            let history = self.edges.entry(child).or_default();
            history.push_back((t.header.stamp.as_ns(), parent, t.transform));
            if history.len() > TF_HISTORY {
                history.pop_front();
            }
        }
    }

    /// `parent_from_child` of `child`'s edge nearest to `stamp_ns` within `tolerance_ns`.
    fn edge(
        &self,
        child: &str,
        stamp_ns: u64,
        tolerance_ns: u64,
    ) -> Option<(&str, Isometry3<f64>)> {
        if let Some((parent, t)) = self.static_edges.get(child) {
            return Some((parent, isometry(t)?));
        }
        let (_, parent, t) = self
            .edges
            .get(child)?
            .iter()
            .filter(|(s, _, _)| s.abs_diff(stamp_ns) <= tolerance_ns)
            .min_by_key(|(s, _, _)| s.abs_diff(stamp_ns))?;
        Some((parent, isometry(t)?))
    }

    /// `root_from_frame` at `stamp_ns`: the chain of edges from `frame` up to `root`.
    fn lookup(
        &self,
        root: &str,
        frame: &str,
        stamp_ns: u64,
        tolerance_ns: u64,
    ) -> Option<Isometry3<f64>> {
        let mut pose = Isometry3::identity();
        let mut at = frame.to_string();
        // A chain longer than this is a loop in the tree.
        for _ in 0..64 {
            if at == root {
                return Some(pose);
            }
            let (parent, parent_from_at) = self.edge(&at, stamp_ns, tolerance_ns)?;
            pose = parent_from_at * pose;
            at = parent.to_string();
        }
        None
    }

    /// Forgets transforms older than `before_ns`.
    fn prune(&mut self, before_ns: u64) {
        for history in self.edges.values_mut() {
            while history.len() > 1 && history.front().is_some_and(|(s, _, _)| *s < before_ns) {
                history.pop_front();
            }
        }
    }
}

fn isometry(t: &Transform) -> Option<Isometry3<f64>> {
    let v = t.translation;
    let q = t.rotation;
    let quaternion = NaQuaternion::new(q.w, q.x, q.y, q.z);
    let finite = [v.x, v.y, v.z, q.x, q.y, q.z, q.w]
        .iter()
        .all(|x| x.is_finite());
    let norm = quaternion.norm();
    if !finite || !(0.5..2.0).contains(&norm) {
        return None;
    }
    // A rotation that is unit to within rounding is taken as sent, so a pose read back is the
    // pose written, bit for bit; any other is normalised.
    let rotation = if (quaternion.norm_squared() - 1.0).abs() <= 4.0 * f64::EPSILON {
        UnitQuaternion::new_unchecked(quaternion)
    } else {
        UnitQuaternion::from_quaternion(quaternion)
    };
    Some(Isometry3::from_parts(
        Translation3::new(v.x, v.y, v.z),
        rotation,
    ))
}

/// A ROS 2 pose from an isometry.
pub fn transform_of(pose: &Isometry3<f64>) -> Transform {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    Transform {
        translation: crate::msg::Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        },
        rotation: crate::msg::Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        },
    }
}

/// Groups a camera's messages into frames by stamp.
#[derive(Clone, Debug)]
pub struct FrameAssembler {
    topics: RosTopics,
    colour: BTreeMap<u64, Image>,
    depth: BTreeMap<u64, Image>,
    camera_info: Option<CameraInfo>,
    tf: TfBuffer,
    /// The robot description joint states go through (with `pose_source: joint_states`).
    robot: Option<Robot>,
    /// The newest stamp seen on any topic: what is older than it by more than the wait is late.
    newest_ns: u64,
    drops: BTreeMap<DropReason, u64>,
}

impl FrameAssembler {
    pub fn new(topics: RosTopics) -> Self {
        Self {
            topics,
            colour: BTreeMap::new(),
            depth: BTreeMap::new(),
            camera_info: None,
            tf: TfBuffer::default(),
            robot: None,
            newest_ns: 0,
            drops: BTreeMap::new(),
        }
    }

    /// The robot description joint states go through.
    pub fn with_robot(mut self, robot: Option<Robot>) -> Self {
        self.robot = robot;
        self
    }

    pub fn topics(&self) -> &RosTopics {
        &self.topics
    }

    /// Drops so far, by reason.
    pub fn drops(&self) -> &BTreeMap<DropReason, u64> {
        &self.drops
    }

    fn tolerance_ns(&self) -> u64 {
        self.topics.pair_tolerance_ms * 1_000_000
    }

    fn seen(&mut self, stamp: Time) -> u64 {
        let ns = stamp.as_ns();
        self.newest_ns = self.newest_ns.max(ns);
        ns
    }

    pub fn push_colour(&mut self, image: Image) {
        let ns = self.seen(image.header.stamp);
        self.colour.insert(ns, image);
    }

    pub fn push_depth(&mut self, image: Image) {
        let ns = self.seen(image.header.stamp);
        self.depth.insert(ns, image);
    }

    pub fn push_camera_info(&mut self, info: CameraInfo) {
        self.seen(info.header.stamp);
        self.camera_info = Some(info);
    }

    pub fn push_tf(&mut self, message: &TfMessage, is_static: bool) {
        // A static transform holds at any time, whatever its stamp says (publishers stamp it
        // when they start): it does not make older frames late.
        if !is_static {
            for t in &message.transforms {
                self.seen(t.header.stamp);
            }
        }
        self.tf.insert(message, is_static);
    }

    /// The camera pose of a joint state, kept as a world → camera transform at its stamp; a
    /// state that gives none is a counted drop, and the error says why.
    pub fn push_joint_state(&mut self, state: &JointState) -> Result<(), String> {
        let pose = match &self.robot {
            Some(robot) => crate::joints::world_from_camera(state, &self.topics, robot),
            None => Err("no robot description in the trolley settings".into()),
        };
        let world_from_camera = match pose {
            Ok(pose) => pose,
            Err(e) => {
                *self.drops.entry(DropReason::JointState).or_default() += 1;
                return Err(e);
            }
        };
        let edge = TransformStamped {
            header: Header {
                stamp: state.header.stamp,
                frame_id: self.topics.world_frame.clone(),
            },
            child_frame_id: self.topics.camera_frame.clone(),
            transform: transform_of(&world_from_camera),
        };
        self.push_tf(
            &TfMessage {
                transforms: vec![edge],
            },
            false,
        );
        Ok(())
    }

    /// Counts a message that did not decode.
    pub fn count_corrupt(&mut self) {
        *self.drops.entry(DropReason::Corrupt).or_default() += 1;
    }

    /// The frames complete now, oldest first, and the drops decided now. A colour image waits
    /// for its depth and pose until messages `wait_ms` newer than it arrive (or `flush`).
    pub fn poll(&mut self, flush: bool) -> (Vec<StampedFrame>, Vec<Dropped>) {
        let wait_ns = self.topics.wait_ms * 1_000_000;
        let mut frames = Vec::new();
        let mut dropped = Vec::new();
        let stamps: Vec<u64> = self.colour.keys().copied().collect();
        for stamp in stamps {
            let late = flush || self.newest_ns.saturating_sub(stamp) > wait_ns;
            match self.try_frame(stamp) {
                Some(Ok(frame)) => frames.push(StampedFrame {
                    stamp_ns: stamp,
                    frame,
                }),
                Some(Err(drop)) => dropped.push(drop),
                None if late => dropped.push(self.unpaired(stamp)),
                None => continue,
            }
            self.colour.remove(&stamp);
        }
        // What no colour image can still pair with: older than the oldest one waiting, and
        // older than the wait behind the newest stamp (a colour image may yet arrive late).
        let tolerance = self.tolerance_ns();
        let oldest_colour = self.colour.keys().next().copied().unwrap_or(u64::MAX);
        let mut keep_from = oldest_colour.saturating_sub(tolerance);
        if !flush {
            keep_from = keep_from.min(self.newest_ns.saturating_sub(wait_ns + tolerance));
        }
        self.depth = self.depth.split_off(&keep_from);
        self.tf.prune(keep_from);
        for d in &dropped {
            *self.drops.entry(d.reason).or_default() += 1;
        }
        (frames, dropped)
    }

    fn unpaired(&self, stamp_ns: u64) -> Dropped {
        let tolerance = self.tolerance_ns();
        let (reason, detail) = if self.nearest_depth(stamp_ns, tolerance).is_none() {
            (
                DropReason::Unpaired,
                "no depth image within the pairing tolerance".to_string(),
            )
        } else {
            (
                DropReason::MissingTf,
                format!(
                    "no transform {} -> {} at the frame's stamp",
                    self.topics.world_frame, self.topics.camera_frame
                ),
            )
        };
        Dropped {
            reason,
            stamp_ns,
            detail,
        }
    }

    fn nearest_depth(&self, stamp_ns: u64, tolerance_ns: u64) -> Option<u64> {
        let lo = stamp_ns.saturating_sub(tolerance_ns);
        self.depth
            .range(lo..=stamp_ns.saturating_add(tolerance_ns))
            .map(|(s, _)| *s)
            .min_by_key(|s| s.abs_diff(stamp_ns))
    }

    /// The frame at colour stamp `stamp_ns`; None while a part is missing.
    fn try_frame(&mut self, stamp_ns: u64) -> Option<Result<RgbdFrame, Dropped>> {
        let tolerance = self.tolerance_ns();
        let depth_stamp = self.nearest_depth(stamp_ns, tolerance)?;
        let world_from_camera = self.tf.lookup(
            &self.topics.world_frame,
            &self.topics.camera_frame,
            stamp_ns,
            tolerance,
        )?;
        let depth = self.depth.remove(&depth_stamp)?;
        let colour = self.colour.get(&stamp_ns)?;
        let drop = |reason, detail: String| Dropped {
            reason,
            stamp_ns,
            detail,
        };
        let Some(info) = &self.camera_info else {
            return Some(Err(drop(
                DropReason::CameraInfo,
                "no camera info yet".into(),
            )));
        };
        Some(
            convert(colour, &depth, info, &self.topics)
                .map(|mut frame| {
                    frame.world_from_camera = world_from_camera;
                    frame
                })
                .map_err(|(reason, detail)| drop(reason, detail)),
        )
    }
}

type Refusal = (DropReason, String);

/// The frame of a colour and depth pair with its camera info (pose left at identity).
fn convert(
    colour: &Image,
    depth: &Image,
    info: &CameraInfo,
    topics: &RosTopics,
) -> Result<RgbdFrame, Refusal> {
    let (width, height) = (colour.width, colour.height);
    if (depth.width, depth.height) != (width, height) {
        let detail = format!(
            "depth {}x{} against colour {width}x{height} (not aligned to colour?)",
            depth.width, depth.height
        );
        return Err((DropReason::Size, detail));
    }
    if (info.width, info.height) != (width, height) && info.width != 0 {
        let detail = format!(
            "camera info {}x{} against images {width}x{height}",
            info.width, info.height
        );
        return Err((DropReason::Size, detail));
    }
    let (fx, fy, cx, cy) = (info.k[0], info.k[4], info.k[2], info.k[5]);
    if !(fx > 0.0 && fy > 0.0 && cx.is_finite() && cy.is_finite()) {
        let detail = format!("camera info without focal lengths (k = {:?})", info.k);
        return Err((DropReason::CameraInfo, detail));
    }
    Ok(RgbdFrame {
        intrinsics: CameraIntrinsics {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
        },
        world_from_camera: Isometry3::identity(),
        depth_scale_m: DEPTH_SCALE_M,
        min_range_m: topics.min_range_m,
        max_range_m: topics.max_range_m,
        depth: depth_mm(depth, topics)?,
        rgb: rgb8(colour)?,
        depth_encoding: Default::default(),
        rgb_encoding: Default::default(),
    })
}

/// The rows of an image, `bytes_per_pixel` each, checked against its step and data length.
fn rows(image: &Image, bytes_per_pixel: usize) -> Result<impl Iterator<Item = &[u8]>, Refusal> {
    let (w, h) = (image.width as usize, image.height as usize);
    let row = w * bytes_per_pixel;
    let step = image.step as usize;
    if step < row || image.data.len() < step * h.saturating_sub(1) + row || w == 0 || h == 0 {
        let detail = format!(
            "{} image {w}x{h} with step {step} and {} bytes",
            image.encoding,
            image.data.len()
        );
        return Err((DropReason::Size, detail));
    }
    Ok(image
        .data
        .chunks(step.max(1))
        .take(h)
        .map(move |r| &r[..row]))
}

fn rgb8(image: &Image) -> Result<Vec<u8>, Refusal> {
    let swap = match image.encoding.as_str() {
        "rgb8" => false,
        "bgr8" => true,
        other => {
            let detail = format!("colour encoding {other:?} (rgb8 or bgr8 wanted)");
            return Err((DropReason::Encoding, detail));
        }
    };
    let mut out = Vec::with_capacity(image.width as usize * image.height as usize * 3);
    for row in rows(image, 3)? {
        if swap {
            out.extend(row.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]));
        } else {
            out.extend_from_slice(row);
        }
    }
    Ok(out)
}

/// Depth in millimetres; invalid, non-positive and beyond-u16 depths are 0 (the one depth rule).
fn depth_mm(image: &Image, topics: &RosTopics) -> Result<Vec<u16>, Refusal> {
    let big = image.is_bigendian != 0;
    let mut out = Vec::with_capacity(image.width as usize * image.height as usize);
    let to_mm = |m: f32| {
        let mm = (m / DEPTH_SCALE_M).round();
        if m.is_finite() && m > 0.0 && (1.0..=f32::from(u16::MAX)).contains(&mm) {
            mm as u16
        } else {
            0
        }
    };
    match image.encoding.as_str() {
        "16UC1" | "mono16" => {
            let scale = topics.depth_unit_m / DEPTH_SCALE_M;
            for row in rows(image, 2)? {
                out.extend(row.chunks_exact(2).map(|b| {
                    let raw = if big {
                        u16::from_be_bytes([b[0], b[1]])
                    } else {
                        u16::from_le_bytes([b[0], b[1]])
                    };
                    if (scale - 1.0).abs() < f32::EPSILON {
                        raw
                    } else {
                        to_mm(f32::from(raw) * topics.depth_unit_m)
                    }
                }));
            }
        }
        "32FC1" => {
            for row in rows(image, 4)? {
                out.extend(row.chunks_exact(4).map(|b| {
                    let bytes = [b[0], b[1], b[2], b[3]];
                    to_mm(if big {
                        f32::from_be_bytes(bytes)
                    } else {
                        f32::from_le_bytes(bytes)
                    })
                }));
            }
        }
        other => {
            let detail = format!("depth encoding {other:?} (16UC1 or 32FC1 wanted)");
            return Err((DropReason::Encoding, detail));
        }
    }
    Ok(out)
}
