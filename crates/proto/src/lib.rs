//! Glasshouse wire protocol: FlatBuffers schema, generated code, verified decode, key expressions.
//!
//! Every Zenoh payload is one FlatBuffers [`Envelope`](fb::Envelope) (file identifier `GHW1`) holding
//! a protocol version, a [`Header`] and one [`Message`]. Services work with the owned Rust types of
//! this crate, one module per kind implementing [`Wire`]: [`encode`] writes one, [`decode_typed`]
//! reads back an expected kind, and [`decode`] / [`decode_as`] read any kind as a [`Message`].
//! Decoding always runs the FlatBuffers verifier with a per-message size limit ([`MessageKind::max_bytes`])
//! and then checks the content (lengths that must agree, finite poses), so a corrupt, truncated
//! or oversized payload is a typed [`ProtoError`], never a panic.
//!
//! The schema lives in `schema/glasshouse.fbs`; `scripts/gen-proto` regenerates `src/generated/`
//! (Rust) and `python/` (Python) with flatc 25.12.19, and CI fails if they drift.

#[doc(hidden)]
pub mod fuzzing;
pub mod keys;
mod messages;
pub mod pixels;
pub mod samples;

#[allow(unsafe_code, clippy::all, clippy::unwrap_used, dead_code, unused_imports)]
#[rustfmt::skip]
#[path = "generated/glasshouse_generated.rs"]
mod generated;

/// The flatc-generated types, for readers that want zero-copy access.
pub use generated::glasshouse::wire as fb;
pub use messages::*;
pub use pixels::{ImageEncoding, PixelCodecError};

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

/// Version written into every envelope; readers reject other versions.
pub const PROTOCOL_VERSION: u16 = 1;

/// The schema's binary reflection form (`flatc -b --schema`, root type `Envelope`): what a
/// reader needs to decode our messages without our code, stored with every MCAP recording's
/// `flatbuffer` channels. `scripts/gen-proto --check` keeps it equal to the schema.
pub const SCHEMA_BFBS: &[u8] = include_bytes!("../schema/glasshouse.bfbs");

/// The fully qualified name of the schema's root type, as MCAP schema records name it.
pub const SCHEMA_ROOT_NAME: &str = "glasshouse.wire.Envelope";

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

/// One message kind's owned type with its encoder and decoder (one module of `messages/` each).
///
/// [`encode`] and [`decode_typed`] wrap a `Wire` type in the envelope; [`Message`] holds any of
/// them for consumers of every kind.
pub trait Wire: Sized + Clone + Send + Sync + 'static + Into<Message> {
    /// The kind this type is sent as.
    const KIND: MessageKind;

    /// Initial builder capacity in bytes (large messages say how large they are).
    fn size_hint(&self) -> usize {
        1024
    }

    /// Writes the payload table; [`encode`] wraps it in the envelope.
    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset>;

    /// Reads and checks the payload of a verified envelope that holds [`Self::KIND`].
    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self>;
}

/// Which frame of which trolley process: frames are ordered by boot epoch, then sequence, so a
/// restarted edge (a new epoch, its seq from 1 again) comes after everything it sent before.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct FrameId {
    /// Wall-clock ns (Unix epoch) when the trolley's process started.
    pub epoch_ns: u64,
    pub seq: u64,
}

impl FrameId {
    pub fn new(epoch_ns: u64, seq: u64) -> Self {
        Self { epoch_ns, seq }
    }
}

impl std::fmt::Display for FrameId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}@{}", self.seq, self.epoch_ns)
    }
}

/// The envelope fields around every message.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Header {
    /// Per-publisher sequence number (frames: the capture sequence the loop refers to).
    pub seq: u64,
    /// The publisher's boot epoch: wall-clock ns (Unix epoch) when its process started, chosen
    /// once by the process's driver. Receivers order a publisher's messages by (epoch_ns, seq).
    pub epoch_ns: u64,
    /// Time of the data in nanoseconds (simulated or sensor time).
    pub stamp_ns: u64,
    pub trolley_id: String,
    /// Who wrote it: trolley, detector or planner id.
    pub source_id: String,
    /// The frame the data is expressed in (`world` for everything the services publish).
    pub frame_id: String,
}

impl Header {
    /// The frame this header announces (for an RgbdFrame: its capture).
    pub fn frame(&self) -> FrameId {
        FrameId::new(self.epoch_ns, self.seq)
    }
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

fn read_header(envelope: &fb::Envelope<'_>) -> Header {
    let text = |s: Option<&str>| s.unwrap_or_default().to_owned();
    Header {
        seq: envelope.seq(),
        epoch_ns: envelope.epoch_ns(),
        stamp_ns: envelope.stamp_ns(),
        trolley_id: text(envelope.trolley_id()),
        source_id: text(envelope.source_id()),
        frame_id: text(envelope.frame_id()),
    }
}

/// Verifies a payload that must hold a message of `expected` kind, with that kind's size limit.
fn verify_as(bytes: &[u8], expected: MessageKind) -> Result<fb::Envelope<'_>> {
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
    Ok(envelope)
}

/// Decodes a payload that must hold an `M`, with `M`'s size limit.
pub fn decode_typed<M: Wire>(bytes: &[u8]) -> Result<(Header, M)> {
    let envelope = verify_as(bytes, M::KIND)?;
    Ok((read_header(&envelope), M::read_payload(&envelope)?))
}

/// Decodes a payload that must hold a message of `expected` kind, with that kind's size limit.
pub fn decode_as(bytes: &[u8], expected: MessageKind) -> Result<(Header, Message)> {
    let envelope = verify_as(bytes, expected)?;
    Ok((read_header(&envelope), Message::read(&envelope, expected)?))
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
    Ok((read_header(&envelope), Message::read(&envelope, kind)?))
}

/// Encodes one message in an envelope.
pub fn encode<M: Wire>(header: &Header, message: &M) -> Vec<u8> {
    let mut fbb = FlatBufferBuilder::with_capacity(message.size_hint());
    let payload = message.write_payload(&mut fbb);
    let trolley_id = fbb.create_string(&header.trolley_id);
    let source_id = fbb.create_string(&header.source_id);
    let frame_id = fbb.create_string(&header.frame_id);
    let envelope = fb::Envelope::create(
        &mut fbb,
        &fb::EnvelopeArgs {
            version: PROTOCOL_VERSION,
            seq: header.seq,
            stamp_ns: header.stamp_ns,
            trolley_id: Some(trolley_id),
            source_id: Some(source_id),
            frame_id: Some(frame_id),
            payload_type: M::KIND.payload_type(),
            payload: Some(payload),
            epoch_ns: header.epoch_ns,
        },
    );
    fb::finish_envelope_buffer(&mut fbb, envelope);
    fbb.finished_data().to_vec()
}

/// Encodes a message of any kind (recorders, fault injection).
pub fn encode_any(header: &Header, message: &Message) -> Vec<u8> {
    message.encode(header)
}
