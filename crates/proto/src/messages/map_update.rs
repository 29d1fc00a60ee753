//! MapUpdate: changed voxels of a trolley's map, owning planner → dashboard, replicas.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

use super::convert::{content, payload, string_or_empty, unknown_enum};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelState {
    Free,
    Occupied,
    Roi,
}

/// One voxel's new value; `key = floor(position / resolution)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VoxelChange {
    pub key: [i32; 3],
    pub occupancy_logodds: f32,
    pub roi_logodds: f32,
    pub state: VoxelState,
}

#[derive(Clone, Debug, PartialEq)]
pub struct MapUpdate {
    pub resolution_m: f32,
    pub map_seq: u64,
    pub based_on_seq: u64,
    pub full: bool,
    pub voxels: Vec<VoxelChange>,
    pub planner_id: String,
}

fn voxel_state_to_fb(state: VoxelState) -> fb::VoxelState {
    match state {
        VoxelState::Free => fb::VoxelState::Free,
        VoxelState::Occupied => fb::VoxelState::Occupied,
        VoxelState::Roi => fb::VoxelState::Roi,
    }
}

fn read_voxel(v: &fb::VoxelChange) -> Result<VoxelChange> {
    let state = match v.state() {
        fb::VoxelState::Free => VoxelState::Free,
        fb::VoxelState::Occupied => VoxelState::Occupied,
        fb::VoxelState::Roi => VoxelState::Roi,
        other => return Err(unknown_enum(MessageKind::MapUpdate, "voxel state", other.0)),
    };
    Ok(VoxelChange {
        key: [v.x(), v.y(), v.z()],
        occupancy_logodds: v.occupancy_logodds(),
        roi_logodds: v.roi_logodds(),
        state,
    })
}

impl Wire for MapUpdate {
    const KIND: MessageKind = MessageKind::MapUpdate;

    fn size_hint(&self) -> usize {
        self.voxels.len() * 24 + 1024
    }

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let voxels: Vec<fb::VoxelChange> = self
            .voxels
            .iter()
            .map(|v| {
                fb::VoxelChange::new(
                    v.key[0],
                    v.key[1],
                    v.key[2],
                    v.occupancy_logodds,
                    v.roi_logodds,
                    voxel_state_to_fb(v.state),
                )
            })
            .collect();
        let voxels = fbb.create_vector(&voxels);
        let planner = fbb.create_string(&self.planner_id);
        fb::MapUpdate::create(
            fbb,
            &fb::MapUpdateArgs {
                resolution_m: self.resolution_m,
                map_seq: self.map_seq,
                based_on_seq: self.based_on_seq,
                full: self.full,
                voxels: Some(voxels),
                planner_id: Some(planner),
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_map_update())?;
        let voxels = m
            .voxels()
            .map(|vs| vs.iter().map(read_voxel).collect::<Result<Vec<_>>>())
            .transpose()?
            .unwrap_or_default();
        let resolution_m = m.resolution_m();
        if !(resolution_m.is_finite() && resolution_m > 0.0) {
            return Err(content(
                Self::KIND,
                format!("resolution {resolution_m} is not positive"),
            ));
        }
        Ok(MapUpdate {
            resolution_m,
            map_seq: m.map_seq(),
            based_on_seq: m.based_on_seq(),
            full: m.full(),
            voxels,
            planner_id: string_or_empty(m.planner_id()),
        })
    }
}
