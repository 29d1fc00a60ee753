//! Glasshouse wire protocol: FlatBuffers schema, generated code, verified decode, key expressions.
//!
//! Every Zenoh payload is one FlatBuffers [`Envelope`](fb::Envelope) (file identifier `GHW1`) holding
//! a protocol version, a [`Header`] and one [`Message`]. Services work with the owned Rust types of
//! this crate; [`encode`] writes them and [`decode`] / [`decode_as`] read them back. Decoding
//! always runs the FlatBuffers verifier with a per-message size limit ([`MessageKind::max_bytes`])
//! and then checks the content (lengths that must agree, finite poses), so a corrupt, truncated
//! or oversized payload is a typed [`ProtoError`], never a panic.
//!
//! The schema lives in `schema/glasshouse.fbs`; `scripts/gen-proto` regenerates `src/generated/`
//! (Rust) and `python/` (Python) with flatc 25.12.19, and CI fails if they drift.

pub mod keys;
mod messages;
pub mod samples;

#[allow(unsafe_code, clippy::all, clippy::unwrap_used, dead_code, unused_imports)]
#[rustfmt::skip]
#[path = "generated/glasshouse_generated.rs"]
mod generated;

/// The flatc-generated types, for readers that want zero-copy access.
pub use generated::glasshouse::wire as fb;
pub use messages::*;

/// Version written into every envelope; readers reject other versions.
pub const PROTOCOL_VERSION: u16 = 1;

/// Errors of decoding a received payload.
#[derive(thiserror::Error, Debug)]
pub enum ProtoError {
    #[error("payload of {len} bytes exceeds the {limit}-byte limit for {kind}")]
    TooLarge {
        kind: MessageKind,
        len: usize,
        limit: usize,
    },
    #[error(
        "payload does not carry the file identifier {}",
        fb::ENVELOPE_IDENTIFIER
    )]
    WrongIdentifier,
    #[error("FlatBuffers verification failed: {0}")]
    Invalid(#[from] flatbuffers::InvalidFlatbuffer),
    #[error("protocol version {found}, this build speaks {expected}")]
    Version { found: u16, expected: u16 },
    #[error("envelope holds no message")]
    NoPayload,
    #[error("expected a {expected} message, the envelope holds {found}")]
    UnexpectedKind {
        expected: MessageKind,
        found: MessageKind,
    },
    #[error("{kind}: {reason}")]
    Content { kind: MessageKind, reason: String },
}

pub type Result<T, E = ProtoError> = std::result::Result<T, E>;

/// Which message an envelope holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MessageKind {
    RgbdFrame,
    ArmState,
    TrolleyInfo,
    RoiCloud,
    RankedViews,
    FruitEstimates,
    MapUpdate,
    PlannerStatus,
    TrolleyStatus,
    DetectorStatus,
    MapSnapshot,
    FleetFruits,
}

impl MessageKind {
    pub const ALL: [MessageKind; 12] = [
        MessageKind::RgbdFrame,
        MessageKind::ArmState,
        MessageKind::TrolleyInfo,
        MessageKind::RoiCloud,
        MessageKind::RankedViews,
        MessageKind::FruitEstimates,
        MessageKind::MapUpdate,
        MessageKind::PlannerStatus,
        MessageKind::TrolleyStatus,
        MessageKind::DetectorStatus,
        MessageKind::MapSnapshot,
        MessageKind::FleetFruits,
    ];

    /// Largest accepted payload in bytes. Frames allow a 1280x960 RGB-D image; point clouds and
    /// map updates a few hundred thousand entries; control messages stay small.
    pub fn max_bytes(self) -> usize {
        const MIB: usize = 1 << 20;
        match self {
            MessageKind::RgbdFrame => 8 * MIB,
            MessageKind::RoiCloud => 16 * MIB,
            MessageKind::MapUpdate => 64 * MIB,
            // A whole row segment's map.
            MessageKind::MapSnapshot => 512 * MIB,
            MessageKind::FruitEstimates => 2 * MIB,
            MessageKind::FleetFruits => 16 * MIB,
            MessageKind::RankedViews | MessageKind::TrolleyInfo => 256 * 1024,
            MessageKind::ArmState
            | MessageKind::PlannerStatus
            | MessageKind::TrolleyStatus
            | MessageKind::DetectorStatus => 64 * 1024,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            MessageKind::RgbdFrame => "RgbdFrame",
            MessageKind::ArmState => "ArmState",
            MessageKind::TrolleyInfo => "TrolleyInfo",
            MessageKind::RoiCloud => "RoiCloud",
            MessageKind::RankedViews => "RankedViews",
            MessageKind::FruitEstimates => "FruitEstimates",
            MessageKind::MapUpdate => "MapUpdate",
            MessageKind::PlannerStatus => "PlannerStatus",
            MessageKind::TrolleyStatus => "TrolleyStatus",
            MessageKind::DetectorStatus => "DetectorStatus",
            MessageKind::MapSnapshot => "MapSnapshot",
            MessageKind::FleetFruits => "FleetFruits",
        }
    }

    fn from_payload_type(t: fb::Payload) -> Option<Self> {
        Some(match t {
            fb::Payload::RgbdFrame => MessageKind::RgbdFrame,
            fb::Payload::ArmState => MessageKind::ArmState,
            fb::Payload::TrolleyInfo => MessageKind::TrolleyInfo,
            fb::Payload::RoiCloud => MessageKind::RoiCloud,
            fb::Payload::RankedViews => MessageKind::RankedViews,
            fb::Payload::FruitEstimates => MessageKind::FruitEstimates,
            fb::Payload::MapUpdate => MessageKind::MapUpdate,
            fb::Payload::PlannerStatus => MessageKind::PlannerStatus,
            fb::Payload::TrolleyStatus => MessageKind::TrolleyStatus,
            fb::Payload::DetectorStatus => MessageKind::DetectorStatus,
            fb::Payload::MapSnapshot => MessageKind::MapSnapshot,
            fb::Payload::FleetFruits => MessageKind::FleetFruits,
            _ => return None,
        })
    }
}

impl std::fmt::Display for MessageKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The envelope fields around every message.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Header {
    /// Per-publisher sequence number (frames: the capture sequence the loop refers to).
    pub seq: u64,
    /// Time of the data in nanoseconds (simulated or sensor time).
    pub stamp_ns: u64,
    pub trolley_id: String,
    /// Who wrote it: trolley, detector or planner id.
    pub source_id: String,
    /// The frame the data is expressed in (`world` for everything the services publish).
    pub frame_id: String,
}

/// Largest accepted payload of any kind.
pub fn max_bytes_any() -> usize {
    MessageKind::ALL
        .iter()
        .map(|k| k.max_bytes())
        .max()
        .unwrap_or(0)
}

fn verify(bytes: &[u8], limit: usize) -> Result<fb::Envelope<'_>> {
    // The identifier sits after the 4-byte root offset; flatbuffers' own check asserts on short input.
    if bytes.get(4..8) != Some(fb::ENVELOPE_IDENTIFIER.as_bytes()) {
        return Err(ProtoError::WrongIdentifier);
    }
    let opts = flatbuffers::VerifierOptions {
        max_apparent_size: limit,
        ..Default::default()
    };
    let envelope = fb::root_as_envelope_with_opts(&opts, bytes)?;
    if envelope.version() != PROTOCOL_VERSION {
        return Err(ProtoError::Version {
            found: envelope.version(),
            expected: PROTOCOL_VERSION,
        });
    }
    Ok(envelope)
}

fn envelope_kind(envelope: &fb::Envelope<'_>) -> Result<MessageKind> {
    MessageKind::from_payload_type(envelope.payload_type()).ok_or(ProtoError::NoPayload)
}

/// Decodes a payload that must hold a message of `expected` kind, with that kind's size limit.
pub fn decode_as(bytes: &[u8], expected: MessageKind) -> Result<(Header, Message)> {
    let limit = expected.max_bytes();
    if bytes.len() > limit {
        return Err(ProtoError::TooLarge {
            kind: expected,
            len: bytes.len(),
            limit,
        });
    }
    let envelope = verify(bytes, limit)?;
    let found = envelope_kind(&envelope)?;
    if found != expected {
        return Err(ProtoError::UnexpectedKind { expected, found });
    }
    messages::read_envelope(&envelope, found)
}

/// Decodes a payload of any kind (the dashboard's view), applying the limit of the kind it holds.
pub fn decode(bytes: &[u8]) -> Result<(Header, Message)> {
    let envelope = verify(bytes, max_bytes_any())?;
    let kind = envelope_kind(&envelope)?;
    if bytes.len() > kind.max_bytes() {
        return Err(ProtoError::TooLarge {
            kind,
            len: bytes.len(),
            limit: kind.max_bytes(),
        });
    }
    messages::read_envelope(&envelope, kind)
}

/// Encodes one message in an envelope.
pub fn encode(header: &Header, message: &Message) -> Vec<u8> {
    messages::write_envelope(header, message)
}
