//! The trolley as the edge's loop sees it ([`TrolleySource`]): the simulator (in
//! `glasshouse-simtrolley`), a recording, a rosbag2 file or a ROS 2 robot.

use glasshouse_geom::FruitEstimate;
use glasshouse_proto::{ArmState, RgbdFrame, TrolleyInfo};
use nalgebra::Isometry3;

pub use glasshouse_arm::Executed;

/// Depth travels as millimetres.
pub const DEPTH_SCALE_M: f32 = 0.001;

/// A trolley's camera and arm, as the edge's loop sees them: the simulator, a recording, or a
/// real driver.
pub trait TrolleySource: Send + Sync {
    /// What planners need to know about this trolley now (regions follow the segment).
    fn info(&self) -> TrolleyInfo;
    /// Ground truth, when the source knows it (the simulator does).
    fn ground_truth(&self) -> Option<Vec<FruitEstimate>>;
    /// Captures frame `frame_seq` at the current pose. `Ok(None)` when the source has no more
    /// frames; `Err` with a reason when the capture failed.
    fn capture(&mut self, frame_seq: u64) -> Result<Option<RgbdFrame>, String>;
    /// The arm now.
    fn arm_state(&self, moving: bool, views_done: u32) -> ArmState;
    /// Moves to the first of `goals` (best first) the arm can reach; None, and no motion, when it
    /// reaches none.
    fn execute(&mut self, goals: &[Isometry3<f64>]) -> Option<Executed>;
    /// Moves on to the next part of the row; the motion time, or None when the row is done.
    fn next_segment(&mut self) -> Option<f64>;
}
