//! RankedViews: candidate views, best first, owning planner → edge, dashboard.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use nalgebra::Isometry3;

use super::convert::{payload, pose_from_fb, pose_to_fb, string_or_empty, unknown_enum};
use crate::{fb, FrameId, MessageKind, Result, Wire};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewKind {
    Roi,
    Exploration,
}

#[derive(Clone, Debug, PartialEq)]
pub struct RankedView {
    pub world_from_camera: Isometry3<f64>,
    pub utility: f32,
    pub gain: f32,
    pub cost_m: f32,
    pub kind: ViewKind,
}

/// Candidate views, best first.
#[derive(Clone, Debug, PartialEq)]
pub struct RankedViews {
    pub views: Vec<RankedView>,
    /// The frame sequence these views were planned on.
    pub based_on_seq: u64,
    /// The boot epoch of the trolley that captured that frame.
    pub based_on_epoch_ns: u64,
    pub planning_time_ms: f32,
    pub planner_id: String,
    /// The ownership epoch of the planner's term as the trolley's owner (0: none): the edge
    /// refuses views of an older epoch than the newest it has taken.
    pub owner_epoch: u64,
}

fn view_kind_to_fb(kind: ViewKind) -> fb::ViewKind {
    match kind {
        ViewKind::Roi => fb::ViewKind::Roi,
        ViewKind::Exploration => fb::ViewKind::Exploration,
    }
}

fn view_kind_from_fb(v: fb::ViewKind) -> Result<ViewKind> {
    match v {
        fb::ViewKind::Roi => Ok(ViewKind::Roi),
        fb::ViewKind::Exploration => Ok(ViewKind::Exploration),
        other => Err(unknown_enum(MessageKind::RankedViews, "view kind", other.0)),
    }
}

fn read_view(v: &fb::View) -> Result<RankedView> {
    Ok(RankedView {
        world_from_camera: pose_from_fb(
            MessageKind::RankedViews,
            "view pose",
            Some(v.world_from_camera()),
        )?,
        utility: v.utility(),
        gain: v.gain(),
        cost_m: v.cost_m(),
        kind: view_kind_from_fb(v.kind())?,
    })
}

impl RankedViews {
    /// The frame these views were planned on.
    pub fn based_on(&self) -> FrameId {
        FrameId::new(self.based_on_epoch_ns, self.based_on_seq)
    }
}

impl Wire for RankedViews {
    const KIND: MessageKind = MessageKind::RankedViews;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let views: Vec<fb::View> = self
            .views
            .iter()
            .map(|v| {
                fb::View::new(
                    &pose_to_fb(&v.world_from_camera),
                    v.utility,
                    v.gain,
                    v.cost_m,
                    view_kind_to_fb(v.kind),
                )
            })
            .collect();
        let views = fbb.create_vector(&views);
        let planner = fbb.create_string(&self.planner_id);
        fb::RankedViews::create(
            fbb,
            &fb::RankedViewsArgs {
                views: Some(views),
                based_on_seq: self.based_on_seq,
                planning_time_ms: self.planning_time_ms,
                planner_id: Some(planner),
                based_on_epoch_ns: self.based_on_epoch_ns,
                owner_epoch: self.owner_epoch,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_ranked_views())?;
        let views = m
            .views()
            .map(|vs| vs.iter().map(read_view).collect::<Result<Vec<_>>>())
            .transpose()?
            .unwrap_or_default();
        Ok(RankedViews {
            views,
            based_on_seq: m.based_on_seq(),
            based_on_epoch_ns: m.based_on_epoch_ns(),
            planning_time_ms: m.planning_time_ms(),
            planner_id: string_or_empty(m.planner_id()),
            owner_epoch: m.owner_epoch(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{decode_typed, encode, samples, Message};

    /// RankedViews as a planner from before ownership epochs writes them.
    #[derive(Clone, Debug)]
    struct OldSender(RankedViews);

    impl From<OldSender> for Message {
        fn from(old: OldSender) -> Self {
            Message::RankedViews(old.0)
        }
    }

    impl Wire for OldSender {
        const KIND: MessageKind = MessageKind::RankedViews;

        fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
            let m = &self.0;
            let planner = fbb.create_string(&m.planner_id);
            let mut table = fb::RankedViewsBuilder::new(fbb);
            table.add_based_on_epoch_ns(m.based_on_epoch_ns);
            table.add_based_on_seq(m.based_on_seq);
            table.add_planner_id(planner);
            table.add_planning_time_ms(m.planning_time_ms);
            table.finish().as_union_value()
        }

        fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
            RankedViews::read_payload(envelope).map(OldSender)
        }
    }

    #[test]
    fn the_ownership_epoch_round_trips_and_an_older_sender_reads_epoch_zero() {
        let sample = samples::ranked_views();
        assert_ne!(sample.owner_epoch, 0);
        let bytes = encode(&samples::header(4), &sample);
        assert_eq!(decode_typed::<RankedViews>(&bytes).expect("decodes").1, sample);
        let old = encode(&samples::header(4), &OldSender(sample.clone()));
        let (_, read) = decode_typed::<RankedViews>(&old).expect("an old sender's views decode");
        assert_eq!(read.owner_epoch, 0);
        assert_eq!(read.based_on(), sample.based_on());
    }
}
