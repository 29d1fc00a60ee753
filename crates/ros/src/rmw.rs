//! How ROS 2 speaks over Zenoh (`rmw_zenoh`): topic key expressions, the attachment of every
//! sample, and the liveliness tokens through which `ros2 topic list` sees a node and its
//! publishers and subscriptions. Formats only; the edge's ROS 2 source moves the bytes.

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

/// The QoS of our endpoints in a token: reliable, volatile, keep last 10, other fields default.
pub const QOS_RELIABLE_KEEP_LAST_10: &str = "1:2:1,10:,:,:,,";

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
            QOS_RELIABLE_KEEP_LAST_10
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
        );
        assert!(token.starts_with("@ros2_lv/0/abc/0/4/MP/%/%/glasshouse_edge/%glasshouse%next_view/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_"));
        assert!(token.ends_with("/1:2:1,10:,:,:,,"));
        let humble = node.endpoint_token::<PoseStamped>(4, Endpoint::Publisher, "/v", true);
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
