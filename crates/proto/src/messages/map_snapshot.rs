//! MapSnapshot: one planner's copy of a trolley's state, the reply to a snapshot query.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use glasshouse_geom::RgbSum;
use nalgebra::Point3;

use super::convert::{content, payload, point3f, string_or_empty, vec3f};
use super::fruit_estimates::{read_histories, write_histories, FruitHistory};
use crate::{fb, MessageKind, Result, Wire};

/// A fruit the tracker follows (id and centre), with the colour samples it gathered on this
/// visit, carried in [`MapSnapshot`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackedFruit {
    pub id: u32,
    pub centre_in_world: Point3<f32>,
    /// No samples in older snapshots.
    pub colour: RgbSum,
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
        let any_colour = self.tracked_fruits.iter().any(|f| f.colour.samples > 0);
        let colours: Vec<fb::RgbSum> = match any_colour {
            true => self
                .tracked_fruits
                .iter()
                .map(|f| rgb_sum_to_fb(&f.colour))
                .collect(),
            false => Vec::new(),
        };
        let colours = any_colour.then(|| fbb.create_vector(&colours));
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
                tracked_colours: colours,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_map_snapshot())?;
        let tracked_fruits = read_tracked(&m)?;
        Ok(MapSnapshot {
            trolley_id: string_or_empty(m.trolley_id()),
            planner_id: string_or_empty(m.planner_id()),
            based_on_seq: m.based_on_seq(),
            based_on_epoch_ns: m.based_on_epoch_ns(),
            map: m.map().map(|b| b.bytes().to_vec()).unwrap_or_default(),
            tracked_fruits,
            next_fruit_id: m.next_fruit_id(),
            owner_epoch: m.owner_epoch(),
            visit: m.visit(),
            season: read_histories(Self::KIND, m.season())?,
        })
    }
}

fn rgb_sum_to_fb(c: &RgbSum) -> fb::RgbSum {
    fb::RgbSum::new(c.r, c.g, c.b, c.samples)
}

/// The tracked fruits with their colour samples: none in older snapshots, else one per fruit.
fn read_tracked(m: &fb::MapSnapshot<'_>) -> Result<Vec<TrackedFruit>> {
    let fruits: Vec<_> = m
        .tracked_fruits()
        .map(|fs| fs.iter().collect())
        .unwrap_or_default();
    let colours: Vec<RgbSum> = m
        .tracked_colours()
        .map(|cs| {
            let sum = |c: &fb::RgbSum| RgbSum {
                r: c.r(),
                g: c.g(),
                b: c.b(),
                samples: c.samples(),
            };
            cs.iter().map(sum).collect()
        })
        .unwrap_or_default();
    if !colours.is_empty() && colours.len() != fruits.len() {
        let why = format!(
            "{} tracked fruits but {} colours",
            fruits.len(),
            colours.len()
        );
        return Err(content(MessageKind::MapSnapshot, why));
    }
    let colour = |i: usize| colours.get(i).copied().unwrap_or_default();
    let tracked = fruits.iter().enumerate().map(|(i, f)| TrackedFruit {
        id: f.id(),
        centre_in_world: point3f(f.centre()),
        colour: colour(i),
    });
    Ok(tracked.collect())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::{decode_typed, encode, samples, ProtoError};

    /// A planner from before the colours: tracked fruits without their colour samples.
    #[derive(Clone, Debug)]
    struct OldSender(MapSnapshot, usize);

    impl From<OldSender> for crate::Message {
        fn from(old: OldSender) -> Self {
            crate::Message::MapSnapshot(old.0)
        }
    }

    impl Wire for OldSender {
        const KIND: MessageKind = MessageKind::MapSnapshot;

        /// Writes `.1` colour sums whatever the tracked fruits (0: none, as an older planner).
        fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
            let tracked: Vec<fb::TrackedFruit> = (self.0.tracked_fruits.iter())
                .map(|f| fb::TrackedFruit::new(f.id, &vec3f(&f.centre_in_world)))
                .collect();
            let tracked = fbb.create_vector(&tracked);
            let sums = vec![fb::RgbSum::new(1, 2, 3, 1); self.1];
            let sums = (self.1 > 0).then(|| fbb.create_vector(&sums));
            let mut t = fb::MapSnapshotBuilder::new(fbb);
            t.add_tracked_fruits(tracked);
            t.add_next_fruit_id(self.0.next_fruit_id);
            if let Some(sums) = sums {
                t.add_tracked_colours(sums);
            }
            t.finish().as_union_value()
        }

        fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
            MapSnapshot::read_payload(envelope).map(|m| OldSender(m, 0))
        }
    }

    #[test]
    fn the_tracked_fruits_colour_samples_round_trip() {
        let sample = samples::map_snapshot();
        let read = decode_typed::<MapSnapshot>(&encode(&samples::header(4), &sample))
            .unwrap()
            .1;
        assert_eq!(read.tracked_fruits[0].colour.samples, 10);
        assert_eq!(read, sample);
    }

    #[test]
    fn a_snapshot_without_colours_reads_without_samples_and_a_wrong_count_is_an_error() {
        let sample = samples::map_snapshot();
        let old = encode(&samples::header(4), &OldSender(sample.clone(), 0));
        let read = decode_typed::<MapSnapshot>(&old).unwrap().1;
        assert_eq!(read.tracked_fruits.len(), 1);
        assert_eq!(read.tracked_fruits[0].id, sample.tracked_fruits[0].id);
        assert_eq!(read.tracked_fruits[0].colour, RgbSum::default());
        let broken = encode(&samples::header(4), &OldSender(sample, 2));
        let err = decode_typed::<MapSnapshot>(&broken).unwrap_err();
        assert!(matches!(err, ProtoError::Content { .. }), "{err}");
    }
}
