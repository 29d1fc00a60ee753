//! TrolleyInfo: what a trolley is (arm, mount, limits, workspace), edge → planners, dashboard.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use glasshouse_geom::{Aabb, CameraIntrinsics};
use nalgebra::Isometry3;

use super::convert::{
    box_from_fb, box_to_fb, intrinsics_from_fb, intrinsics_to_fb, payload, pose_from_fb,
    pose_to_fb, string_or_empty, unknown_enum,
};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ArmModel {
    None,
    Ur5e,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MountKind {
    FreeCamera,
    StaticPole,
    CeilingGantry,
    RailLift,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TrolleyInfo {
    pub arm_model: ArmModel,
    pub mount: MountKind,
    pub world_from_base: Isometry3<f64>,
    pub joint_min_rad: Vec<f64>,
    pub joint_max_rad: Vec<f64>,
    pub rail_min_m: f64,
    pub rail_max_m: f64,
    pub lift_min_m: f64,
    pub lift_max_m: f64,
    /// Where the camera centre can be placed.
    pub camera_workspace: Aabb,
    /// Where view targets may lie (the plants).
    pub sampling_region: Aabb,
    pub scenario: String,
    pub scene_seed: u64,
    pub intrinsics: CameraIntrinsics,
    /// The arm and its mount with all their ranges, as JSON (`glasshouse_arm::Robot`), so that
    /// planners propose only views the arm can reach; empty when unknown.
    pub robot_json: String,
}

fn arm_model_to_fb(model: ArmModel) -> fb::ArmModel {
    match model {
        ArmModel::None => fb::ArmModel::None,
        ArmModel::Ur5e => fb::ArmModel::Ur5e,
    }
}

fn mount_to_fb(mount: MountKind) -> fb::MountKind {
    match mount {
        MountKind::FreeCamera => fb::MountKind::FreeCamera,
        MountKind::StaticPole => fb::MountKind::StaticPole,
        MountKind::CeilingGantry => fb::MountKind::CeilingGantry,
        MountKind::RailLift => fb::MountKind::RailLift,
    }
}

fn arm_model_from_fb(model: fb::ArmModel) -> Result<ArmModel> {
    match model {
        fb::ArmModel::None => Ok(ArmModel::None),
        fb::ArmModel::Ur5e => Ok(ArmModel::Ur5e),
        other => Err(unknown_enum(MessageKind::TrolleyInfo, "arm model", other.0)),
    }
}

fn mount_from_fb(mount: fb::MountKind) -> Result<MountKind> {
    match mount {
        fb::MountKind::FreeCamera => Ok(MountKind::FreeCamera),
        fb::MountKind::StaticPole => Ok(MountKind::StaticPole),
        fb::MountKind::CeilingGantry => Ok(MountKind::CeilingGantry),
        fb::MountKind::RailLift => Ok(MountKind::RailLift),
        other => Err(unknown_enum(MessageKind::TrolleyInfo, "mount", other.0)),
    }
}

impl Wire for TrolleyInfo {
    const KIND: MessageKind = MessageKind::TrolleyInfo;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let jmin = fbb.create_vector(&self.joint_min_rad);
        let jmax = fbb.create_vector(&self.joint_max_rad);
        let scenario = fbb.create_string(&self.scenario);
        let robot_json = fbb.create_string(&self.robot_json);
        let base = pose_to_fb(&self.world_from_base);
        let workspace = box_to_fb(&self.camera_workspace);
        let region = box_to_fb(&self.sampling_region);
        let intrinsics = intrinsics_to_fb(&self.intrinsics);
        fb::TrolleyInfo::create(
            fbb,
            &fb::TrolleyInfoArgs {
                arm_model: arm_model_to_fb(self.arm_model),
                mount: mount_to_fb(self.mount),
                world_from_base: Some(&base),
                joint_min_rad: Some(jmin),
                joint_max_rad: Some(jmax),
                rail_min_m: self.rail_min_m,
                rail_max_m: self.rail_max_m,
                lift_min_m: self.lift_min_m,
                lift_max_m: self.lift_max_m,
                camera_workspace: Some(&workspace),
                sampling_region: Some(&region),
                scenario: Some(scenario),
                scene_seed: self.scene_seed,
                intrinsics: Some(&intrinsics),
                robot_json: Some(robot_json),
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let kind = Self::KIND;
        let m = payload(envelope.payload_as_trolley_info())?;
        let floats = |v: Option<flatbuffers::Vector<'_, f64>>| {
            v.map(|v| v.iter().collect()).unwrap_or_default()
        };
        Ok(TrolleyInfo {
            arm_model: arm_model_from_fb(m.arm_model())?,
            mount: mount_from_fb(m.mount())?,
            world_from_base: pose_from_fb(kind, "world_from_base", m.world_from_base())?,
            joint_min_rad: floats(m.joint_min_rad()),
            joint_max_rad: floats(m.joint_max_rad()),
            rail_min_m: m.rail_min_m(),
            rail_max_m: m.rail_max_m(),
            lift_min_m: m.lift_min_m(),
            lift_max_m: m.lift_max_m(),
            camera_workspace: box_from_fb(kind, "camera_workspace", m.camera_workspace())?,
            sampling_region: box_from_fb(kind, "sampling_region", m.sampling_region())?,
            scenario: string_or_empty(m.scenario()),
            scene_seed: m.scene_seed(),
            intrinsics: intrinsics_from_fb(kind, m.intrinsics())?,
            robot_json: string_or_empty(m.robot_json()),
        })
    }
}
