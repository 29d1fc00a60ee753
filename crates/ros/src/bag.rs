//! A rosbag2 recording (MCAP storage, CDR messages) played as a trolley: its camera frames, in
//! stamp order, behind the loop's [`TrolleySource`]. Views are "reached" as the recording moves
//! on; the motion time of each is the gap to the next frame's stamp, so an edge pacing in real
//! time plays the bag at its recorded speed.

use std::collections::{BTreeMap, VecDeque};
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use glasshouse_geom::{CameraIntrinsics, FruitEstimate};
use glasshouse_pipeline::{Executed, TrolleySource};
use glasshouse_proto::{ArmState, RgbdFrame, TrolleyInfo};
use nalgebra::Isometry3;

use crate::assemble::{DropReason, FrameAssembler, StampedFrame};
use crate::msg::{decode_cdr, CameraInfo, Image, JointState, RosMessage, TfMessage};
use crate::settings::{PoseSource, RosTopics, RosTrolley};
use crate::RosError;

/// The reader of the bag file being played (behind a lock: the reader is not `Sync`, a
/// `TrolleySource` must be, and only the edge's one source task ever takes it).
type Messages = std::sync::Mutex<mcap::io::MessageReader<BufReader<File>>>;

/// A rosbag2 bag (its folder, or one `.mcap` file) as a trolley.
pub struct BagSource {
    files: VecDeque<PathBuf>,
    reading: Option<(PathBuf, Messages)>,
    assembler: FrameAssembler,
    ready: VecDeque<StampedFrame>,
    trolley: RosTrolley,
    intrinsics: Option<CameraIntrinsics>,
    last_pose: Isometry3<f64>,
    last_stamp_ns: Option<u64>,
    frames: u64,
    ended: bool,
}

impl BagSource {
    /// Opens the bag at `path`: a rosbag2 folder (its `.mcap` files in name order) or a single
    /// `.mcap` file. Nothing is read yet but the file list.
    pub fn open(path: &Path, topics: RosTopics, trolley: RosTrolley) -> Result<Self, RosError> {
        topics.validate().map_err(RosError::Settings)?;
        let io = |e: std::io::Error| RosError::Io(path.to_path_buf(), e.to_string());
        let files: VecDeque<PathBuf> = if path.is_dir() {
            let mut files: Vec<PathBuf> = std::fs::read_dir(path)
                .map_err(io)?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
                .collect();
            files.sort();
            files.into()
        } else {
            std::fs::metadata(path).map_err(io)?;
            [path.to_path_buf()].into()
        };
        if files.is_empty() {
            return Err(RosError::NotABag(path.to_path_buf()));
        }
        Ok(Self {
            files,
            reading: None,
            assembler: FrameAssembler::new(topics).with_robot(trolley.robot.clone()),
            ready: VecDeque::new(),
            trolley,
            intrinsics: None,
            last_pose: Isometry3::identity(),
            last_stamp_ns: None,
            frames: 0,
            ended: false,
        })
    }

    /// Frames dropped so far, by reason.
    pub fn drops(&self) -> &BTreeMap<DropReason, u64> {
        self.assembler.drops()
    }

    /// Frames played so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Reads until a frame is ready or the bag ends.
    fn fill(&mut self) {
        while self.ready.is_empty() && !self.ended {
            match self.next_message() {
                Some(message) => {
                    self.dispatch(&message);
                    self.collect(false);
                }
                None => {
                    self.collect(true);
                    self.ended = true;
                }
            }
        }
    }

    fn collect(&mut self, flush: bool) {
        let (frames, dropped) = self.assembler.poll(flush);
        for d in dropped {
            tracing::warn!(
                reason = d.reason.as_str(),
                stamp_ns = d.stamp_ns,
                "bag frame dropped: {}",
                d.detail
            );
        }
        self.ready.extend(frames);
    }

    /// The next message of the bag, opening its files in turn. A file that cannot be read to
    /// its end (truncated, corrupt) ends with an error in the log; its messages so far count.
    fn next_message(&mut self) -> Option<mcap::Message<'static>> {
        loop {
            if self.reading.is_none() {
                let path = self.files.pop_front()?;
                match File::open(&path) {
                    Ok(file) => {
                        tracing::info!(file = %path.display(), "reading bag file");
                        let reader = mcap::io::MessageReader::new(BufReader::new(file));
                        self.reading = Some((path, std::sync::Mutex::new(reader)));
                    }
                    Err(e) => {
                        tracing::error!(file = %path.display(), "cannot open bag file: {e}");
                        continue;
                    }
                }
            }
            let (path, reader) = self.reading.as_mut()?;
            let next = match reader.get_mut() {
                Ok(reader) => reader.next(),
                Err(poisoned) => poisoned.into_inner().next(),
            };
            match next {
                Some(Ok(message)) => return Some(message),
                Some(Err(e)) => {
                    tracing::error!(file = %path.display(), "bag file ends early: {e}");
                    self.reading = None;
                }
                None => self.reading = None,
            }
        }
    }

    fn dispatch(&mut self, message: &mcap::Message<'_>) {
        let topics = self.assembler.topics();
        let topic = message.channel.topic.as_str();
        let data = &message.data;
        let result = if topic == topics.colour {
            decode_typed::<Image>(message).map(|m| self.assembler.push_colour(m))
        } else if topic == topics.depth {
            decode_typed::<Image>(message).map(|m| self.assembler.push_depth(m))
        } else if topic == topics.camera_info {
            decode_typed::<CameraInfo>(message).map(|m| self.assembler.push_camera_info(m))
        } else if topics.pose_source == PoseSource::JointStates {
            if topic == topics.joint_states {
                match decode_typed::<JointState>(message) {
                    Ok(m) => {
                        if let Err(e) = self.assembler.push_joint_state(&m) {
                            tracing::warn!(topic, "joint state dropped: {e}");
                        }
                        Ok(())
                    }
                    Err(e) => Err(e),
                }
            } else {
                Ok(())
            }
        } else if topic == topics.tf || topic == topics.tf_static {
            let is_static = topic == topics.tf_static;
            decode_typed::<TfMessage>(message).map(|m| self.assembler.push_tf(&m, is_static))
        } else {
            Ok(())
        };
        if let Err(e) = result {
            tracing::warn!(topic, bytes = data.len(), "bag message dropped: {e}");
            self.assembler.count_corrupt();
        }
    }

    /// Seconds from the frame played last to the next one (0 at the end).
    fn gap_to_next_s(&mut self) -> f64 {
        self.fill();
        match (self.last_stamp_ns, self.ready.front()) {
            (Some(last), Some(next)) => next.stamp_ns.saturating_sub(last) as f64 * 1e-9,
            _ => 0.0,
        }
    }
}

/// `message` as `M`, checked against its channel's declared type when it has one.
fn decode_typed<M: RosMessage>(message: &mcap::Message<'_>) -> Result<M, RosError> {
    let channel = &message.channel;
    if channel.message_encoding != "cdr" {
        return Err(RosError::Cdr {
            what: channel.topic.clone(),
            reason: format!(
                "message encoding {:?}, cdr wanted",
                channel.message_encoding
            ),
        });
    }
    if let Some(schema) = &channel.schema {
        if schema.name != M::TYPE_NAME {
            return Err(RosError::Cdr {
                what: channel.topic.clone(),
                reason: format!("type {}, {} wanted", schema.name, M::TYPE_NAME),
            });
        }
    }
    decode_cdr(&message.data, M::TYPE_NAME)
}

impl TrolleySource for BagSource {
    fn info(&self) -> TrolleyInfo {
        crate::trolley_info(&self.trolley, self.intrinsics)
    }

    fn ground_truth(&self) -> Option<Vec<FruitEstimate>> {
        None
    }

    fn capture(&mut self, _frame_seq: u64) -> Result<Option<RgbdFrame>, String> {
        self.fill();
        let Some(next) = self.ready.pop_front() else {
            tracing::info!(frames = self.frames, drops = ?self.drops(), "the bag has no more frames");
            return Ok(None);
        };
        self.frames += 1;
        self.last_stamp_ns = Some(next.stamp_ns);
        self.last_pose = next.frame.world_from_camera;
        self.intrinsics = Some(next.frame.intrinsics);
        Ok(Some(next.frame))
    }

    fn arm_state(&self, moving: bool, views_done: u32) -> ArmState {
        crate::arm_state(self.last_pose, moving, views_done)
    }

    fn execute(&mut self, goals: &[Isometry3<f64>]) -> Option<Executed> {
        if goals.is_empty() {
            return None;
        }
        Some(Executed {
            index: 0,
            motion_s: self.gap_to_next_s(),
        })
    }

    fn next_segment(&mut self) -> Option<f64> {
        // A bag is one segment: what was recorded. Play on while it has frames.
        self.fill();
        (!self.ready.is_empty()).then(|| self.gap_to_next_s())
    }
}
