//! How ROS 2 speaks over Zenoh (`rmw_zenoh`): topic key expressions, the attachment of every
//! sample, and the liveliness tokens through which `ros2 topic list` sees a node and its
//! publishers and subscriptions. Formats only; the edge's ROS 2 source moves the bytes.

use serde::{Deserialize, Serialize};

use crate::msg::RosMessage;

/// A ROS 2 type as rmw_zenoh spells it in keys: `sensor_msgs::msg::dds_::Image_`.
pub fn dds_type_name(type_name: &str) -> String {
    let mut parts: Vec<&str> = type_name.split('/').collect();
    let name = parts.pop().unwrap_or_default();
    format!("{}::dds_::{name}_", parts.join("::"))
}

/// What ROS 2 Humble peers put where later releases put the type hash.
pub const NO_TYPE_HASH: &str = "TypeHashNotSupported";

/// The type hash as peers of `humble` (or later releases) spell it.
pub fn type_hash<M: RosMessage>(humble: bool) -> &'static str {
    if humble {
        NO_TYPE_HASH
    } else {
        M::TYPE_HASH
    }
}

/// The data key of `topic` carrying `M` in `domain`:
/// `<domain>/<topic without its leading slash>/<dds type>/<type hash>` (Humble subscribers listen
/// on [`NO_TYPE_HASH`], later ones on the real hash).
pub fn topic_key<M: RosMessage>(domain: u32, topic: &str, humble: bool) -> String {
    format!(
        "{domain}/{}/{}/{}",
        topic.trim_start_matches('/'),
        dds_type_name(M::TYPE_NAME),
        type_hash::<M>(humble)
    )
}

/// The key expression a subscription of `topic` listens on: any type hash, so publishers of
/// Humble (`TypeHashNotSupported`) and of later releases are both heard.
pub fn topic_subscription_key<M: RosMessage>(domain: u32, topic: &str) -> String {
    format!(
        "{domain}/{}/{}/*",
        topic.trim_start_matches('/'),
        dds_type_name(M::TYPE_NAME)
    )
}

/// A name inside a liveliness token: `/` becomes `%`, an empty name is `%`.
pub fn mangle(name: &str) -> String {
    if name.is_empty() {
        "%".into()
    } else {
        name.replace('/', "%")
    }
}

/// Whether lost samples are sent again.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Reliability {
    Reliable,
    BestEffort,
}

/// Whether a subscription that joins late gets what was published before it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Durability {
    Volatile,
    /// Latched: publishers keep their last `depth` samples for late subscriptions
    /// (`/tf_static`, `/robot_description`).
    TransientLocal,
}

/// How many samples are kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum History {
    KeepLast,
    KeepAll,
}

/// A ROS 2 QoS profile, the part rmw_zenoh acts on (deadline, lifespan and liveliness stay at
/// their defaults, as rmw_zenoh implements none of them).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Qos {
    pub reliability: Reliability,
    pub durability: Durability,
    pub history: History,
    /// Samples kept with `keep_last` (0: rmw_zenoh's default of 42).
    pub depth: u32,
}

impl Qos {
    /// Reliable, volatile, keep last `depth`: ROS 2's default profile.
    pub const fn reliable(depth: u32) -> Self {
        Self {
            reliability: Reliability::Reliable,
            durability: Durability::Volatile,
            history: History::KeepLast,
            depth,
        }
    }

    /// Reliable, transient local, keep last `depth`: what `/tf_static` publishers use.
    pub const fn latched(depth: u32) -> Self {
        Self {
            durability: Durability::TransientLocal,
            ..Self::reliable(depth)
        }
    }

    /// The profile as the last field of a liveliness token spells it:
    /// `<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>` with
    /// rmw's numbering (reliable 1, best effort 2; transient local 1, volatile 2; keep last 1,
    /// keep all 2) and the unimplemented fields empty.
    pub fn token(&self) -> String {
        let reliability = match self.reliability {
            Reliability::Reliable => 1,
            Reliability::BestEffort => 2,
        };
        let durability = match self.durability {
            Durability::TransientLocal => 1,
            Durability::Volatile => 2,
        };
        let history = match self.history {
            History::KeepLast => 1,
            History::KeepAll => 2,
        };
        format!("{reliability}:{durability}:{history},{}:,:,:,,", self.depth)
    }

    /// The profile a token's QoS field announces; None when it is not one.
    pub fn from_token(field: &str) -> Option<Self> {
        let mut parts = field.split(':');
        let reliability = match parts.next()? {
            "1" | "" => Reliability::Reliable,
            "2" => Reliability::BestEffort,
            _ => return None,
        };
        let durability = match parts.next()? {
            "1" => Durability::TransientLocal,
            "2" | "" => Durability::Volatile,
            _ => return None,
        };
        let (history, depth) = parts.next()?.split_once(',')?;
        let history = match history {
            "1" | "" => History::KeepLast,
            "2" => History::KeepAll,
            _ => return None,
        };
        let depth = if depth.is_empty() {
            0
        } else {
            depth.parse().ok()?
        };
        Some(Self {
            reliability,
            durability,
            history,
            depth,
        })
    }
}

/// The suffix under which a latched publisher's cache answers late subscriptions
/// (zenoh-ext's advanced publisher, which rmw_zenoh uses for transient local): a late
/// subscription asks `<data key>/@adv/**` once, accepting replies on the data key itself.
pub const LATCHED_CACHE_SUFFIX: &str = "@adv/**";

/// A ROS 2 node as a liveliness token sees it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RosNode {
    pub domain: u32,
    /// The Zenoh session id, as the session prints it.
    pub zid: String,
    /// The node's id within the session.
    pub node_id: u32,
    pub namespace: String,
    pub name: String,
    pub enclave: String,
}

/// What a liveliness token announces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Endpoint {
    Publisher,
    Subscription,
}

impl RosNode {
    fn prefix(&self, entity_id: u32, kind: &str) -> String {
        // The root namespace is `%`; any other keeps its leading slash, mangled (`%robot1`).
        let namespace = match self.namespace.as_str() {
            "" | "/" => "",
            ns => ns,
        };
        format!(
            "@ros2_lv/{}/{}/{}/{entity_id}/{kind}/{}/{}/{}",
            self.domain,
            self.zid,
            self.node_id,
            mangle(&self.enclave),
            mangle(namespace),
            mangle(&self.name)
        )
    }

    /// The node's own token (`NN`).
    pub fn node_token(&self) -> String {
        self.prefix(self.node_id, "NN")
    }

    /// The token of a publisher (`MP`) or subscription (`MS`) of `topic` carrying `M`.
    pub fn endpoint_token<M: RosMessage>(
        &self,
        entity_id: u32,
        endpoint: Endpoint,
        topic: &str,
        humble: bool,
        qos: &Qos,
    ) -> String {
        let kind = match endpoint {
            Endpoint::Publisher => "MP",
            Endpoint::Subscription => "MS",
        };
        format!(
            "{}/{}/{}/{}/{}",
            self.prefix(entity_id, kind),
            mangle(topic),
            dds_type_name(M::TYPE_NAME),
            type_hash::<M>(humble),
            qos.token()
        )
    }
}

/// A publisher's 16-byte id, from its liveliness token (unique per endpoint, as rmw_zenoh's).
pub fn publisher_gid(token: &str) -> [u8; 16] {
    // FNV-1a, twice with different offsets: stable across runs and builds.
    let fnv = |offset: u64| {
        token.bytes().fold(offset, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
        })
    };
    let mut gid = [0u8; 16];
    gid[..8].copy_from_slice(&fnv(0xcbf2_9ce4_8422_2325).to_le_bytes());
    gid[8..].copy_from_slice(&fnv(0x8422_2325_cbf2_9ce4).to_le_bytes());
    gid
}

/// The attachment of a sample: its publisher's sequence number, the source time and the
/// publisher's 16-byte id (zenoh-ext serialization: two little-endian i64, then the id as a
/// sequence with its length).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Attachment {
    pub sequence_number: i64,
    pub source_timestamp_ns: i64,
    pub source_gid: [u8; 16],
}

impl Attachment {
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(33);
        out.extend_from_slice(&self.sequence_number.to_le_bytes());
        out.extend_from_slice(&self.source_timestamp_ns.to_le_bytes());
        out.push(16); // LEB128 length of the id
        out.extend_from_slice(&self.source_gid);
        out
    }

    /// Reads an attachment (with or without the id's length); None when it is not one.
    pub fn decode(bytes: &[u8]) -> Option<Self> {
        let i64_at = |at: usize| Some(i64::from_le_bytes(bytes.get(at..at + 8)?.try_into().ok()?));
        let gid = match bytes.len() {
            33 if bytes[16] == 16 => &bytes[17..33],
            32 => &bytes[16..32],
            _ => return None,
        };
        Some(Self {
            sequence_number: i64_at(0)?,
            source_timestamp_ns: i64_at(8)?,
            source_gid: gid.try_into().ok()?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::{Image, PoseStamped};

    #[test]
    fn keys_and_tokens_spell_what_rmw_zenoh_spells() {
        assert_eq!(
            dds_type_name("sensor_msgs/msg/Image"),
            "sensor_msgs::msg::dds_::Image_"
        );
        assert_eq!(
            topic_key::<Image>(0, "/camera/color/image_raw", false),
            format!(
                "0/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/{}",
                Image::TYPE_HASH
            )
        );
        assert_eq!(
            topic_subscription_key::<Image>(3, "/camera/color/image_raw"),
            "3/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/*"
        );
        let node = RosNode {
            domain: 0,
            zid: "abc".into(),
            node_id: 0,
            namespace: "/".into(),
            name: "glasshouse_edge".into(),
            enclave: String::new(),
        };
        assert_eq!(
            node.node_token(),
            "@ros2_lv/0/abc/0/0/NN/%/%/glasshouse_edge"
        );
        let token = node.endpoint_token::<PoseStamped>(
            4,
            Endpoint::Publisher,
            "/glasshouse/next_view",
            false,
            &Qos::reliable(10),
        );
        assert!(token.starts_with("@ros2_lv/0/abc/0/4/MP/%/%/glasshouse_edge/%glasshouse%next_view/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_"));
        assert!(token.ends_with("/1:2:1,10:,:,:,,"));
        let humble = node.endpoint_token::<PoseStamped>(
            4,
            Endpoint::Publisher,
            "/v",
            true,
            &Qos::reliable(10),
        );
        assert!(
            humble.contains("::PoseStamped_/TypeHashNotSupported/"),
            "{humble}"
        );
        let robot1 = RosNode {
            namespace: "/robot1".into(),
            ..node
        };
        assert_eq!(
            robot1.node_token(),
            "@ros2_lv/0/abc/0/0/NN/%/%robot1/glasshouse_edge"
        );
        assert_ne!(publisher_gid("a"), publisher_gid("b"));
    }

    #[test]
    fn qos_profiles_round_trip_through_their_token_field() {
        // What rmw_zenoh announces for ROS 2's default profile and for /tf_static.
        assert_eq!(Qos::reliable(10).token(), "1:2:1,10:,:,:,,");
        assert_eq!(Qos::latched(1).token(), "1:1:1,1:,:,:,,");
        let sensor = Qos {
            reliability: Reliability::BestEffort,
            durability: Durability::Volatile,
            history: History::KeepLast,
            depth: 5,
        };
        for qos in [Qos::reliable(10), Qos::latched(1), sensor] {
            assert_eq!(Qos::from_token(&qos.token()), Some(qos));
        }
        // Empty fields are rmw's defaults; garbage is refused.
        assert_eq!(Qos::from_token("::,:,:,:,,"), Some(Qos::reliable(0)));
        assert_eq!(Qos::from_token("3:2:1,10:,:,:,,"), None);
        assert_eq!(Qos::from_token("1:2:1"), None);
    }

    #[test]
    fn attachments_round_trip_and_bad_ones_are_refused() {
        let a = Attachment {
            sequence_number: 7,
            source_timestamp_ns: 1_767_225_600_000_000_000,
            source_gid: [9; 16],
        };
        let bytes = a.encode();
        assert_eq!(bytes.len(), 33);
        assert_eq!(Attachment::decode(&bytes), Some(a));
        assert_eq!(Attachment::decode(&bytes[..20]), None);
    }
}
