//! DetectorStatus: a detector's health, detector → dashboard.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

use super::convert::{payload, string_or_empty};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Debug, Default, PartialEq)]
pub struct DetectorStatus {
    pub detector_id: String,
    pub frames_processed: u64,
    pub dropped_messages: u64,
    pub mean_detect_time_ms: f32,
}

impl Wire for DetectorStatus {
    const KIND: MessageKind = MessageKind::DetectorStatus;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let did = fbb.create_string(&self.detector_id);
        fb::DetectorStatus::create(
            fbb,
            &fb::DetectorStatusArgs {
                detector_id: Some(did),
                frames_processed: self.frames_processed,
                dropped_messages: self.dropped_messages,
                mean_detect_time_ms: self.mean_detect_time_ms,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_detector_status())?;
        Ok(DetectorStatus {
            detector_id: string_or_empty(m.detector_id()),
            frames_processed: m.frames_processed(),
            dropped_messages: m.dropped_messages(),
            mean_detect_time_ms: m.mean_detect_time_ms(),
        })
    }
}
