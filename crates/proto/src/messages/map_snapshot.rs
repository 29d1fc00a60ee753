//! MapSnapshot: one planner's copy of a trolley's state, the reply to a snapshot query.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use nalgebra::Point3;

use super::convert::{payload, point3f, string_or_empty, vec3f};
use super::fruit_estimates::{read_histories, write_histories, FruitHistory};
use crate::{fb, MessageKind, Result, Wire};

/// A fruit the tracker follows (id and centre), carried in [`MapSnapshot`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackedFruit {
    pub id: u32,
    pub centre_in_world: Point3<f32>,
}

/// One planner's copy of a trolley's state (reply to a snapshot query).
#[derive(Clone, Debug, PartialEq)]
pub struct MapSnapshot {
    pub trolley_id: String,
    pub planner_id: String,
    /// The last RoiCloud frame seq integrated into the map.
    pub based_on_seq: u64,
    /// The boot epoch of the trolley that captured that frame.
    pub based_on_epoch_ns: u64,
    /// `glasshouse_roimap` snapshot bytes.
    pub map: Vec<u8>,
    pub tracked_fruits: Vec<TrackedFruit>,
    pub next_fruit_id: u32,
    /// The newest ownership epoch the answering planner knows for the trolley (its own term
    /// when it owns it); a receiver that has seen a newer one refuses the snapshot as stale.
    pub owner_epoch: u64,
    /// The trolley's visit the map is from, and the fruits of the visits before it.
    pub visit: u32,
    pub season: Vec<FruitHistory>,
}

impl Wire for MapSnapshot {
    const KIND: MessageKind = MessageKind::MapSnapshot;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let trolley = fbb.create_string(&self.trolley_id);
        let planner = fbb.create_string(&self.planner_id);
        let map = fbb.create_vector(&self.map);
        let tracked: Vec<fb::TrackedFruit> = self
            .tracked_fruits
            .iter()
            .map(|f| fb::TrackedFruit::new(f.id, &vec3f(&f.centre_in_world)))
            .collect();
        let tracked = fbb.create_vector(&tracked);
        let season = write_histories(fbb, &self.season);
        fb::MapSnapshot::create(
            fbb,
            &fb::MapSnapshotArgs {
                trolley_id: Some(trolley),
                planner_id: Some(planner),
                based_on_seq: self.based_on_seq,
                map: Some(map),
                tracked_fruits: Some(tracked),
                next_fruit_id: self.next_fruit_id,
                based_on_epoch_ns: self.based_on_epoch_ns,
                owner_epoch: self.owner_epoch,
                visit: self.visit,
                season: Some(season),
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_map_snapshot())?;
        let tracked = |f: &fb::TrackedFruit| TrackedFruit {
            id: f.id(),
            centre_in_world: point3f(f.centre()),
        };
        Ok(MapSnapshot {
            trolley_id: string_or_empty(m.trolley_id()),
            planner_id: string_or_empty(m.planner_id()),
            based_on_seq: m.based_on_seq(),
            based_on_epoch_ns: m.based_on_epoch_ns(),
            map: m.map().map(|b| b.bytes().to_vec()).unwrap_or_default(),
            tracked_fruits: m
                .tracked_fruits()
                .map(|fs| fs.iter().map(tracked).collect())
                .unwrap_or_default(),
            next_fruit_id: m.next_fruit_id(),
            owner_epoch: m.owner_epoch(),
            visit: m.visit(),
            season: read_histories(Self::KIND, m.season())?,
        })
    }
}
