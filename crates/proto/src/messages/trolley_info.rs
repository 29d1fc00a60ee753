//! TrolleyInfo: what a trolley is (its robot: arm, mount and their ranges; its workspace), edge →
//! planners, dashboard.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use glasshouse_geom::{Aabb, CameraIntrinsics};
use glasshouse_arm::Robot;
use nalgebra::Isometry3;

use super::convert::{
    box_from_fb, content, box_to_fb, intrinsics_from_fb, intrinsics_to_fb, payload, pose_from_fb,
    pose_to_fb, string_or_empty,
};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Debug, PartialEq)]
pub struct TrolleyInfo {
    /// Where the arm's base is now (it moves with the rail, lift or gantry).
    pub world_from_base: Isometry3<f64>,
    /// Where the camera centre can be placed.
    pub camera_workspace: Aabb,
    /// Where view targets may lie (the plants).
    pub sampling_region: Aabb,
    pub scenario: String,
    pub scene_seed: u64,
    pub intrinsics: CameraIntrinsics,
    /// The arm and its mount with all their ranges, so that planners propose only views the arm
    /// can reach; None when unknown (every view is proposed, the edge still checks each).
    pub robot: Option<Box<Robot>>,
    /// The newest ownership epoch the edge has taken views under (0: none yet; a source leaves
    /// it 0, the edge fills it in): a planner owning the trolley under an older one steps down.
    pub owner_epoch: u64,
    /// The planner whose views the edge took under `owner_epoch` (empty: none yet): the one a
    /// replaced owner catches up from.
    pub owner_id: String,
    /// Which visit of its row the trolley is on (0: the first); a planner that sees a higher
    /// one than its copy's starts the new visit from the previous visit's map as a prior.
    pub visit: u32,
}

/// The robot travels as JSON in `robot_json` (one typed value on each side; the schema's older
/// per-field copies are deprecated); text that is not a valid robot is a decode error.
fn robot_from_json(json: &str) -> Result<Option<Box<Robot>>> {
    if json.is_empty() {
        return Ok(None);
    }
    let content = |reason: String| content(MessageKind::TrolleyInfo, reason);
    let robot: Robot =
        serde_json::from_str(json).map_err(|e| content(format!("robot_json: {e}")))?;
    Robot::new(robot.arm, robot.mount)
        .map(|robot| Some(Box::new(robot)))
        .map_err(|e| content(format!("robot_json: {e}")))
}

impl Wire for TrolleyInfo {
    const KIND: MessageKind = MessageKind::TrolleyInfo;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let scenario = fbb.create_string(&self.scenario);
        let robot_json = match &self.robot {
            // A Robot serialises to JSON without fail (plain numbers, enums and arrays).
            Some(robot) => serde_json::to_string(robot).unwrap_or_default(),
            None => String::new(),
        };
        let robot_json = fbb.create_string(&robot_json);
        let owner_id = fbb.create_string(&self.owner_id);
        let base = pose_to_fb(&self.world_from_base);
        let workspace = box_to_fb(&self.camera_workspace);
        let region = box_to_fb(&self.sampling_region);
        let intrinsics = intrinsics_to_fb(&self.intrinsics);
        fb::TrolleyInfo::create(
            fbb,
            &fb::TrolleyInfoArgs {
                world_from_base: Some(&base),
                camera_workspace: Some(&workspace),
                sampling_region: Some(&region),
                scenario: Some(scenario),
                scene_seed: self.scene_seed,
                intrinsics: Some(&intrinsics),
                robot_json: Some(robot_json),
                owner_epoch: self.owner_epoch,
                owner_id: Some(owner_id),
                visit: self.visit,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let kind = Self::KIND;
        let m = payload(envelope.payload_as_trolley_info())?;
        Ok(TrolleyInfo {
            world_from_base: pose_from_fb(kind, "world_from_base", m.world_from_base())?,
            camera_workspace: box_from_fb(kind, "camera_workspace", m.camera_workspace())?,
            sampling_region: box_from_fb(kind, "sampling_region", m.sampling_region())?,
            scenario: string_or_empty(m.scenario()),
            scene_seed: m.scene_seed(),
            intrinsics: intrinsics_from_fb(kind, m.intrinsics())?,
            robot: robot_from_json(m.robot_json().unwrap_or_default())?,
            owner_epoch: m.owner_epoch(),
            owner_id: string_or_empty(m.owner_id()),
            visit: m.visit(),
        })
    }
}
