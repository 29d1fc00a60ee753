//! ArmState: the arm's joints and camera pose, edge → planners, dashboard.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use nalgebra::Isometry3;

use super::convert::{payload, pose_from_fb, pose_to_fb};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Debug, PartialEq)]
pub struct ArmState {
    pub joint_angles_rad: Vec<f64>,
    pub world_from_camera: Isometry3<f64>,
    pub rail_position_m: f64,
    pub lift_height_m: f64,
    pub moving: bool,
    pub views_done: u32,
}

impl Wire for ArmState {
    const KIND: MessageKind = MessageKind::ArmState;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let joints = fbb.create_vector(&self.joint_angles_rad);
        let pose = pose_to_fb(&self.world_from_camera);
        fb::ArmState::create(
            fbb,
            &fb::ArmStateArgs {
                joint_angles_rad: Some(joints),
                world_from_camera: Some(&pose),
                rail_position_m: self.rail_position_m,
                lift_height_m: self.lift_height_m,
                moving: self.moving,
                views_done: self.views_done,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_arm_state())?;
        Ok(ArmState {
            joint_angles_rad: m
                .joint_angles_rad()
                .map(|v| v.iter().collect())
                .unwrap_or_default(),
            world_from_camera: pose_from_fb(Self::KIND, "world_from_camera", m.world_from_camera())?,
            rail_position_m: m.rail_position_m(),
            lift_height_m: m.lift_height_m(),
            moving: m.moving(),
            views_done: m.views_done(),
        })
    }
}
