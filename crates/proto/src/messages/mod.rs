//! The message kinds: one module each (owned type, encoder, decoder) and the one list below from
//! which [`MessageKind`], [`Message`], the names and the size limits all come.
//!
//! Adding a kind: its table in the schema, its module here implementing [`Wire`](crate::Wire),
//! and one line in [`message_kinds!`] (plus an example in `samples.rs`, which the compiler asks for).

mod convert;
mod frame_registration;

pub use frame_registration::*;

use crate::{fb, Header, Result, Wire};

const KIB: usize = 1 << 10;
const MIB: usize = 1 << 20;

macro_rules! message_kinds {
    ($($name:ident in $module:ident, max $max_bytes:expr;)+) => {
        $(mod $module;)+
        $(pub use $module::*;)+

        /// Which message an envelope holds.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        pub enum MessageKind {
            $($name,)+
        }

        impl MessageKind {
            const COUNT: usize = [$(MessageKind::$name,)+].len();
            pub const ALL: [MessageKind; Self::COUNT] = [$(MessageKind::$name,)+];

            /// Largest accepted payload in bytes.
            pub fn max_bytes(self) -> usize {
                match self {
                    $(MessageKind::$name => $max_bytes,)+
                }
            }

            pub fn name(self) -> &'static str {
                match self {
                    $(MessageKind::$name => stringify!($name),)+
                }
            }

            pub(crate) fn from_payload_type(t: fb::Payload) -> Option<Self> {
                Self::ALL.into_iter().find(|kind| kind.payload_type() == t)
            }

            pub(crate) fn payload_type(self) -> fb::Payload {
                match self {
                    $(MessageKind::$name => fb::Payload::$name,)+
                }
            }
        }

        /// Any message of the protocol.
        #[derive(Clone, Debug, PartialEq)]
        pub enum Message {
            $($name($name),)+
        }

        impl Message {
            pub fn kind(&self) -> MessageKind {
                match self {
                    $(Message::$name(_) => MessageKind::$name,)+
                }
            }

            pub(crate) fn encode(&self, header: &Header) -> Vec<u8> {
                match self {
                    $(Message::$name(m) => crate::encode(header, m),)+
                }
            }

            pub(crate) fn read(envelope: &fb::Envelope<'_>, kind: MessageKind) -> Result<Self> {
                match kind {
                    $(MessageKind::$name => $name::read_payload(envelope).map(Message::$name),)+
                }
            }
        }

        $(
            impl From<$name> for Message {
                fn from(m: $name) -> Self {
                    Message::$name(m)
                }
            }

            impl TryFrom<Message> for $name {
                /// The message, when it is of another kind.
                type Error = Message;

                fn try_from(m: Message) -> std::result::Result<Self, Message> {
                    match m {
                        Message::$name(m) => Ok(m),
                        other => Err(other),
                    }
                }
            }
        )+
    };
}

// The one list of message kinds: type, module, largest accepted payload. Frames allow a
// 1280x960 RGB-D image; point clouds and map updates a few hundred thousand entries; a snapshot a
// whole row segment's map; control messages stay small.
message_kinds! {
    RgbdFrame in rgbd_frame, max 8 * MIB;
    ArmState in arm_state, max 64 * KIB;
    TrolleyInfo in trolley_info, max 256 * KIB;
    RoiCloud in roi_cloud, max 16 * MIB;
    RankedViews in ranked_views, max 256 * KIB;
    FruitEstimates in fruit_estimates, max 2 * MIB;
    MapUpdate in map_update, max 64 * MIB;
    PlannerStatus in planner_status, max 64 * KIB;
    TrolleyStatus in trolley_status, max 64 * KIB;
    DetectorStatus in detector_status, max 64 * KIB;
    MapSnapshot in map_snapshot, max 512 * MIB;
    FleetFruits in fleet_fruits, max 16 * MIB;
}

impl std::fmt::Display for MessageKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}
