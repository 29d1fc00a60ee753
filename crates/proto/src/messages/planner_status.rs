//! PlannerStatus: a planner's health and ownership, planner → dashboard, other planners.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

use super::convert::{payload, string_or_empty, strings, strings_from_fb};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlannerStatus {
    pub planner_id: String,
    pub owned_trolleys: Vec<String>,
    pub standby_trolleys: Vec<String>,
    pub clouds_integrated: u64,
    pub views_published: u64,
    pub last_planning_time_ms: f32,
    pub mean_planning_time_ms: f32,
    pub dropped_messages: u64,
    pub map_voxels: u64,
    /// RoiClouds refused: not from a live detector, or a frame id no honest trolley sends.
    pub refused_clouds: u64,
}

impl Wire for PlannerStatus {
    const KIND: MessageKind = MessageKind::PlannerStatus;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let pid = fbb.create_string(&self.planner_id);
        let owned = strings(fbb, &self.owned_trolleys);
        let standby = strings(fbb, &self.standby_trolleys);
        fb::PlannerStatus::create(
            fbb,
            &fb::PlannerStatusArgs {
                planner_id: Some(pid),
                owned_trolleys: Some(owned),
                standby_trolleys: Some(standby),
                clouds_integrated: self.clouds_integrated,
                views_published: self.views_published,
                last_planning_time_ms: self.last_planning_time_ms,
                mean_planning_time_ms: self.mean_planning_time_ms,
                dropped_messages: self.dropped_messages,
                map_voxels: self.map_voxels,
                refused_clouds: self.refused_clouds,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_planner_status())?;
        Ok(PlannerStatus {
            planner_id: string_or_empty(m.planner_id()),
            owned_trolleys: strings_from_fb(m.owned_trolleys()),
            standby_trolleys: strings_from_fb(m.standby_trolleys()),
            clouds_integrated: m.clouds_integrated(),
            views_published: m.views_published(),
            last_planning_time_ms: m.last_planning_time_ms(),
            mean_planning_time_ms: m.mean_planning_time_ms(),
            dropped_messages: m.dropped_messages(),
            map_voxels: m.map_voxels(),
            refused_clouds: m.refused_clouds(),
        })
    }
}
