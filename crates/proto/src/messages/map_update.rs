//! MapUpdate: changed voxels of a trolley's map, owning planner → dashboard, replicas.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

use super::convert::{content, payload, string_or_empty, unknown_enum};
use super::FrameRegistration;
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
    /// How the cloud this update comes from was registered to the map; `None` when the planner
    /// did not register it (a frame it does not insert again: a re-announce, a stale frame). A
    /// rejected cloud changes no voxel: its update carries only this.
    pub registration: Option<FrameRegistration>,
    /// The ownership epoch of the owner that changed the map (0: none).
    pub owner_epoch: u64,
}

fn voxel_state_to_fb(state: VoxelState) -> fb::VoxelState {
    match state {
        VoxelState::Free => fb::VoxelState::Free,
        VoxelState::Occupied => fb::VoxelState::Occupied,
        VoxelState::Roi => fb::VoxelState::Roi,
    }
}

fn voxels_to_fb(voxels: &[VoxelChange]) -> Vec<fb::VoxelChange> {
    let to_fb = |v: &VoxelChange| {
        fb::VoxelChange::new(
            v.key[0],
            v.key[1],
            v.key[2],
            v.occupancy_logodds,
            v.roi_logodds,
            voxel_state_to_fb(v.state),
        )
    };
    voxels.iter().map(to_fb).collect()
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
        let voxels = fbb.create_vector(&voxels_to_fb(&self.voxels));
        let planner = fbb.create_string(&self.planner_id);
        let registration = self.registration.as_ref().map(|r| r.write(fbb));
        fb::MapUpdate::create(
            fbb,
            &fb::MapUpdateArgs {
                resolution_m: self.resolution_m,
                map_seq: self.map_seq,
                based_on_seq: self.based_on_seq,
                full: self.full,
                voxels: Some(voxels),
                planner_id: Some(planner),
                registration,
                owner_epoch: self.owner_epoch,
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
            registration: m
                .registration()
                .map(|r| FrameRegistration::read(&r))
                .transpose()?,
            owner_epoch: m.owner_epoch(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{
        decode_typed, encode, samples, FrameId, Message, RegistrationReason, RegistrationVerdict,
        RigidCorrection,
    };

    /// A MapUpdate as a planner from before `registration` writes it: the first six fields.
    #[derive(Clone, Debug)]
    struct OldSender(MapUpdate);

    impl From<OldSender> for Message {
        fn from(old: OldSender) -> Self {
            Message::MapUpdate(old.0)
        }
    }

    impl Wire for OldSender {
        const KIND: MessageKind = MessageKind::MapUpdate;

        fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
            let m = &self.0;
            let voxels = fbb.create_vector(&voxels_to_fb(&m.voxels));
            let planner = fbb.create_string(&m.planner_id);
            // In the order flatc's `create` of the six-field table added them.
            let mut table = fb::MapUpdateBuilder::new(fbb);
            table.add_based_on_seq(m.based_on_seq);
            table.add_map_seq(m.map_seq);
            table.add_planner_id(planner);
            table.add_voxels(voxels);
            table.add_resolution_m(m.resolution_m);
            table.add_full(m.full);
            table.finish().as_union_value()
        }

        fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
            MapUpdate::read_payload(envelope).map(OldSender)
        }
    }

    fn round_trip(m: &MapUpdate) -> MapUpdate {
        decode_typed::<MapUpdate>(&encode(&samples::header(3), m))
            .expect("decodes")
            .1
    }

    #[test]
    fn a_map_update_and_its_registration_round_trip() {
        let sample = samples::map_update();
        assert!(sample.registration.is_some());
        assert_eq!(round_trip(&sample), sample);
        let without = MapUpdate {
            registration: None,
            ..sample
        };
        assert_eq!(round_trip(&without), without);
    }

    #[test]
    fn an_update_from_a_sender_without_registration_reads_as_none() {
        let mut sample = samples::map_update();
        sample.registration = None;
        // Nor an ownership epoch, which came later.
        sample.owner_epoch = 0;
        let old = encode(&samples::header(3), &OldSender(sample.clone()));
        let (_, read) = decode_typed::<MapUpdate>(&old).expect("an old sender's update decodes");
        assert_eq!(read, sample);
        // What a planner without registration sends now is byte for byte what it sent before.
        assert_eq!(encode(&samples::header(3), &sample), old);
    }

    #[test]
    fn every_verdict_and_reason_round_trips_and_absent_figures_stay_absent() {
        for (verdict, reason) in RegistrationVerdict::ALL
            .into_iter()
            .flat_map(|v| RegistrationReason::ALL.map(|r| (v, r)))
        {
            let mut m = samples::map_update();
            m.voxels.clear();
            m.registration = Some(FrameRegistration {
                frame: FrameId::new(17, 4),
                verdict,
                reason,
                contradicting_points: Some(60),
                ..FrameRegistration::default()
            });
            let read = round_trip(&m);
            assert_eq!(read, m, "{verdict:?} {reason:?}");
            let r = read.registration.expect("registration");
            assert_eq!(
                (r.world_correction, r.rotation_deg, r.inliers),
                (None, None, None)
            );
        }
    }

    #[test]
    fn a_correction_reads_back_as_the_isometry_it_came_from() {
        let rotation = nalgebra::UnitQuaternion::from_euler_angles(0.004, -0.007, 0.011);
        let translation = nalgebra::Translation3::new(0.004, -0.006, 0.002);
        let iso = nalgebra::Isometry3::from_parts(translation, rotation);
        let c = RigidCorrection::from_isometry(&iso);
        assert!((c.angle_deg() - rotation.angle().to_degrees()).abs() < 1e-12);
        let back = c.to_isometry();
        assert!((back.translation.vector - iso.translation.vector).norm() < 1e-15);
        assert!(back.rotation.angle_to(&iso.rotation) < 1e-12);
    }

    #[test]
    fn a_non_finite_correction_is_a_content_error() {
        let mut m = samples::map_update();
        if let Some(r) = m.registration.as_mut() {
            r.world_correction = Some(RigidCorrection {
                translation_m: nalgebra::Vector3::new(f64::NAN, 0.0, 0.0),
                rotation_vector_rad: nalgebra::Vector3::zeros(),
            });
        }
        let bytes = encode(&samples::header(1), &m);
        let err = decode_typed::<MapUpdate>(&bytes).expect_err("NaN correction accepted");
        assert!(err.to_string().contains("world_correction"), "{err}");
    }
}
