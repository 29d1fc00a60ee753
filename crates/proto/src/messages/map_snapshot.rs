//! MapSnapshot: one planner's copy of a trolley's state, the reply to a snapshot query.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use glasshouse_geom::RgbSum;
use nalgebra::{Isometry3, Point3, Vector3};

use super::convert::{
    content, payload, point3f, pose_from_fb, pose_to_fb, string_or_empty, vec3f,
};
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

/// A scan the hand-eye estimate is made over: its believed camera pose, and surface points
/// with their normals in its camera frame (parallel).
#[derive(Clone, Debug, PartialEq)]
pub struct HandEyeScan {
    pub world_from_camera: Isometry3<f64>,
    pub points_in_camera: Vec<Point3<f32>>,
    pub normals_in_camera: Vec<Vector3<f32>>,
}

/// A trolley's hand-eye calibration error as its planner estimates it, carried in
/// [`MapSnapshot`] so that a copy restored from it corrects the next scans as the owner does.
#[derive(Clone, Debug, PartialEq)]
pub struct HandEye {
    /// The camera's true pose in the frame the trolley believes it in.
    pub camera_believed_from_true: Isometry3<f64>,
    pub scans_seen: u32,
    /// The window of scans, oldest first; none once the estimate is final.
    pub scans: Vec<HandEyeScan>,
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
    /// The hand-eye estimate; None when the planner does not make one.
    pub hand_eye: Option<HandEye>,
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
        let hand_eye = self.hand_eye.as_ref().map(|h| write_hand_eye(fbb, h));
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
                hand_eye,
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
            hand_eye: m.hand_eye().map(|h| read_hand_eye(&h)).transpose()?,
        })
    }
}

fn write_hand_eye<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    hand_eye: &HandEye,
) -> WIPOffset<fb::HandEye<'a>> {
    let scans: Vec<_> = hand_eye
        .scans
        .iter()
        .map(|scan| {
            let points: Vec<fb::Vec3> = scan.points_in_camera.iter().map(vec3f).collect();
            let normals: Vec<fb::Vec3> = scan
                .normals_in_camera
                .iter()
                .map(|n| vec3f(&Point3::from(*n)))
                .collect();
            let args = fb::HandEyeScanArgs {
                world_from_camera: Some(&pose_to_fb(&scan.world_from_camera)),
                points_in_camera: Some(fbb.create_vector(&points)),
                normals_in_camera: Some(fbb.create_vector(&normals)),
            };
            fb::HandEyeScan::create(fbb, &args)
        })
        .collect();
    let args = fb::HandEyeArgs {
        camera_believed_from_true: Some(&pose_to_fb(&hand_eye.camera_believed_from_true)),
        scans_seen: hand_eye.scans_seen,
        scans: Some(fbb.create_vector(&scans)),
    };
    fb::HandEye::create(fbb, &args)
}

/// The hand-eye estimate: its poses whole and finite, every point with a finite normal.
fn read_hand_eye(h: &fb::HandEye<'_>) -> Result<HandEye> {
    let kind = MessageKind::MapSnapshot;
    let field = "hand_eye.camera_believed_from_true";
    let estimate = pose_from_fb(kind, field, h.camera_believed_from_true())?;
    let scans = h.scans().into_iter().flatten().map(|s| read_hand_eye_scan(&s));
    Ok(HandEye {
        camera_believed_from_true: estimate,
        scans_seen: h.scans_seen(),
        scans: scans.collect::<Result<_>>()?,
    })
}

fn read_hand_eye_scan(scan: &fb::HandEyeScan<'_>) -> Result<HandEyeScan> {
    let kind = MessageKind::MapSnapshot;
    let field = "hand_eye.scans.world_from_camera";
    let world_from_camera = pose_from_fb(kind, field, scan.world_from_camera())?;
    let points: Vec<Point3<f32>> = scan
        .points_in_camera()
        .into_iter()
        .flatten()
        .map(point3f)
        .collect();
    let normals: Vec<Vector3<f32>> = scan
        .normals_in_camera()
        .into_iter()
        .flatten()
        .map(|n| point3f(n).coords)
        .collect();
    if points.len() != normals.len() {
        let (p, n) = (points.len(), normals.len());
        return Err(content(kind, format!("hand_eye scan with {p} points but {n} normals")));
    }
    let finite = |v: &Vector3<f32>| v.iter().all(|c| c.is_finite());
    if !points.iter().all(|p| finite(&p.coords)) || !normals.iter().all(finite) {
        return Err(content(kind, "hand_eye scan with a point or normal not finite"));
    }
    Ok(HandEyeScan {
        world_from_camera,
        points_in_camera: points,
        normals_in_camera: normals,
    })
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
