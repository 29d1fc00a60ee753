//! Every Zenoh key expression of Glasshouse is built here, one function per key.
//!
//! Tree (ids are single chunks of `[A-Za-z0-9_-]`):
//! - `gh/trolley/{tid}/{rgbd|arm|info|fruits|map|status|truth}`: one trolley's data and results
//!   (`truth`: the simulator's ground truth);
//! - `gh/trolley/{tid}/roi/{did}`, `gh/trolley/{tid}/views/{pid}`: the clouds and views of one
//!   trolley, keyed by their sender (detector `did`, planner `pid`), so that the router's ACL
//!   binds the sender's id to its certificate ([`TrolleyTopic::keyed_by_sender`], [`sender`]);
//! - `gh/planner/{pid}/status`, `gh/detector/{did}/status`: service health;
//! - `gh/planner/{pid}/snapshot/{tid}`: the queryable through which planner `pid` hands out its
//!   copy of trolley `tid`'s map (MapSnapshot replies);
//! - `gh/fleet/fruits`: the merged fruit map;
//! - `gh/alive/{trolley|planner|detector}/{id}`: liveliness tokens (membership), outside the data tree.
//!
//! A data key is a [`Key<M>`]: it names the message type `M` published on it and how that data
//! travels by default ([`Qos`]), so a publisher or subscriber declared from it can only carry `M`.
//! Untyped expressions (`String`) remain for observers of many kinds and for [`parse`].

use std::marker::PhantomData;

use crate::{
    ArmState, DetectorStatus, FleetFruits, FruitEstimates, MapSnapshot, MapUpdate, MessageKind,
    PlannerStatus, RankedViews, RgbdFrame, RoiCloud, TrolleyInfo, TrolleyStatus, Wire,
};

/// Root of every key of this project.
pub const ROOT: &str = "gh";
/// Everything the dashboard subscribes to.
pub const EVERYTHING: &str = "gh/**";
/// The merged fruit map of the fleet.
pub const FLEET_FRUITS: &str = "gh/fleet/fruits";
/// Longest id accepted.
pub const MAX_ID_LEN: usize = 64;

#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
pub enum KeyError {
    #[error("id {0:?} is empty, longer than {MAX_ID_LEN} characters, or has a character outside [A-Za-z0-9_-]")]
    InvalidId(String),
}

/// Checks that an id is one key chunk: 1..=64 characters of `[A-Za-z0-9_-]`.
pub fn validate_id(id: &str) -> Result<(), KeyError> {
    let ok = !id.is_empty()
        && id.len() <= MAX_ID_LEN
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
    if ok {
        Ok(())
    } else {
        Err(KeyError::InvalidId(id.to_owned()))
    }
}

/// How a key's data travels unless its user says otherwise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Qos {
    /// Sensor streams: newer samples replace older ones under load.
    Stream,
    /// Results and control: never dropped.
    Reliable,
    /// The maps' inputs (ROI clouds): never dropped, and a subscriber that misses one (its link
    /// was moving to another router when it was put) gets it again, in order, from the
    /// publisher's cache.
    Recovered,
}

/// A key expression that carries messages of type `M`.
pub struct Key<M> {
    expr: String,
    qos: Qos,
    _message: PhantomData<fn() -> M>,
}

impl<M: Wire> Key<M> {
    fn new(expr: String, qos: Qos) -> Self {
        Self {
            expr,
            qos,
            _message: PhantomData,
        }
    }

    /// The Zenoh key expression.
    pub fn as_str(&self) -> &str {
        &self.expr
    }

    /// How this key's data travels by default.
    pub fn qos(&self) -> Qos {
        self.qos
    }

    /// The message kind published on this key.
    pub fn kind(&self) -> MessageKind {
        M::KIND
    }
}

// Manual impls: a key is cloneable and printable whatever `M` is.
impl<M> Clone for Key<M> {
    fn clone(&self) -> Self {
        Self {
            expr: self.expr.clone(),
            qos: self.qos,
            _message: PhantomData,
        }
    }
}

impl<M> std::fmt::Debug for Key<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Key")
            .field("expr", &self.expr)
            .field("qos", &self.qos)
            .finish()
    }
}

impl<M> std::fmt::Display for Key<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.expr)
    }
}

/// The per-trolley topics.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TrolleyTopic {
    /// RgbdFrame, edge → detectors (stream).
    Rgbd,
    /// ArmState, edge → planners, dashboard (stream).
    Arm,
    /// TrolleyInfo, edge → planners, dashboard (reliable, periodic).
    Info,
    /// RoiCloud, detector → planners, dashboard (reliable).
    Roi,
    /// RankedViews, owning planner → edge, dashboard (reliable).
    Views,
    /// FruitEstimates, owning planner → dashboard (reliable).
    Fruits,
    /// MapUpdate, owning planner → dashboard, replicas (reliable).
    Map,
    /// TrolleyStatus, edge → dashboard (reliable, periodic).
    Status,
    /// FruitEstimates holding the ground truth, simulated edges → dashboard (reliable, with info).
    Truth,
}

impl TrolleyTopic {
    pub const ALL: [TrolleyTopic; 9] = [
        TrolleyTopic::Rgbd,
        TrolleyTopic::Arm,
        TrolleyTopic::Info,
        TrolleyTopic::Roi,
        TrolleyTopic::Views,
        TrolleyTopic::Fruits,
        TrolleyTopic::Map,
        TrolleyTopic::Status,
        TrolleyTopic::Truth,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            TrolleyTopic::Rgbd => "rgbd",
            TrolleyTopic::Arm => "arm",
            TrolleyTopic::Info => "info",
            TrolleyTopic::Roi => "roi",
            TrolleyTopic::Views => "views",
            TrolleyTopic::Fruits => "fruits",
            TrolleyTopic::Map => "map",
            TrolleyTopic::Status => "status",
            TrolleyTopic::Truth => "truth",
        }
    }

    /// The one message kind this topic carries.
    pub fn message_kind(self) -> MessageKind {
        match self {
            TrolleyTopic::Rgbd => MessageKind::RgbdFrame,
            TrolleyTopic::Arm => MessageKind::ArmState,
            TrolleyTopic::Info => MessageKind::TrolleyInfo,
            TrolleyTopic::Roi => MessageKind::RoiCloud,
            TrolleyTopic::Views => MessageKind::RankedViews,
            TrolleyTopic::Fruits => MessageKind::FruitEstimates,
            TrolleyTopic::Map => MessageKind::MapUpdate,
            TrolleyTopic::Status => MessageKind::TrolleyStatus,
            TrolleyTopic::Truth => MessageKind::FruitEstimates,
        }
    }

    /// How the topic's data travels by default.
    pub fn qos(self) -> Qos {
        match self {
            TrolleyTopic::Rgbd | TrolleyTopic::Arm => Qos::Stream,
            TrolleyTopic::Roi => Qos::Recovered,
            _ => Qos::Reliable,
        }
    }

    /// Whether the topic's keys end in their sender's id (`gh/trolley/{tid}/roi/{did}`,
    /// `gh/trolley/{tid}/views/{pid}`): only the identity named there may put on them, so a
    /// receiver knows who sent a cloud or views from the key, not from what the sender wrote.
    pub fn keyed_by_sender(self) -> bool {
        matches!(self, TrolleyTopic::Roi | TrolleyTopic::Views)
    }

    fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|t| t.as_str() == s)
    }
}

fn trolley_key<M: Wire>(tid: &str, topic: TrolleyTopic) -> Result<Key<M>, KeyError> {
    debug_assert_eq!(M::KIND, topic.message_kind());
    Ok(Key::new(trolley(tid, topic)?, topic.qos()))
}

fn trolley_key_from<M: Wire>(
    tid: &str,
    topic: TrolleyTopic,
    sender: &str,
) -> Result<Key<M>, KeyError> {
    debug_assert_eq!(M::KIND, topic.message_kind());
    Ok(Key::new(trolley_from(tid, topic, sender)?, topic.qos()))
}

fn all_trolleys_key<M: Wire>(topic: TrolleyTopic) -> Key<M> {
    debug_assert_eq!(M::KIND, topic.message_kind());
    Key::new(all_trolleys(topic), topic.qos())
}

/// One constructor for trolley `tid`'s key of a topic and one for that topic of every trolley.
macro_rules! trolley_keys {
    ($($(#[$doc:meta])* $one:ident, $all:ident: $topic:ident => $message:ty;)+) => {
        $(
            $(#[$doc])*
            #[doc = concat!("\n\n`gh/trolley/{tid}/", stringify!($one), "`.")]
            pub fn $one(tid: &str) -> Result<Key<$message>, KeyError> {
                trolley_key(tid, TrolleyTopic::$topic)
            }

            #[doc = concat!("`gh/trolley/*/", stringify!($one), "`: [`", stringify!($one), "`] of every trolley.")]
            pub fn $all() -> Key<$message> {
                all_trolleys_key(TrolleyTopic::$topic)
            }
        )+
    };
}

trolley_keys! {
    /// RgbdFrame, edge → detectors (stream).
    rgbd, all_rgbd: Rgbd => RgbdFrame;
    /// ArmState, edge → planners, dashboard (stream).
    arm, all_arm: Arm => ArmState;
    /// TrolleyInfo, edge → planners, dashboard (reliable, periodic).
    info, all_info: Info => TrolleyInfo;
    /// FruitEstimates, owning planner → dashboard (reliable).
    fruits, all_fruits: Fruits => FruitEstimates;
    /// MapUpdate, owning planner → dashboard, replicas (reliable).
    map, all_map: Map => MapUpdate;
    /// TrolleyStatus, edge → dashboard (reliable, periodic).
    status, all_status: Status => TrolleyStatus;
    /// FruitEstimates holding the ground truth, simulated edges → dashboard (reliable).
    truth, all_truth: Truth => FruitEstimates;
}

/// `gh/trolley/{tid}/roi/{did}`: detector `did`'s RoiClouds of trolley `tid`, detector →
/// planners, dashboard (reliable).
pub fn roi(tid: &str, did: &str) -> Result<Key<RoiCloud>, KeyError> {
    trolley_key_from(tid, TrolleyTopic::Roi, did)
}

/// `gh/trolley/{tid}/roi/*`: [`roi`] of trolley `tid` from every detector.
pub fn roi_from_any(tid: &str) -> Result<Key<RoiCloud>, KeyError> {
    trolley_key(tid, TrolleyTopic::Roi)
}

/// `gh/trolley/*/roi/*`: [`roi`] of every trolley from every detector.
pub fn all_roi() -> Key<RoiCloud> {
    all_trolleys_key(TrolleyTopic::Roi)
}

/// `gh/trolley/{tid}/views/{pid}`: planner `pid`'s RankedViews for trolley `tid`, owning
/// planner → edge, dashboard (reliable).
pub fn views(tid: &str, pid: &str) -> Result<Key<RankedViews>, KeyError> {
    trolley_key_from(tid, TrolleyTopic::Views, pid)
}

/// `gh/trolley/{tid}/views/*`: [`views`] for trolley `tid` from every planner.
pub fn views_from_any(tid: &str) -> Result<Key<RankedViews>, KeyError> {
    trolley_key(tid, TrolleyTopic::Views)
}

/// `gh/trolley/*/views/*`: [`views`] for every trolley from every planner.
pub fn all_views() -> Key<RankedViews> {
    all_trolleys_key(TrolleyTopic::Views)
}

/// Every key of trolley `tid`'s topic, untyped, for observers of many topics:
/// `gh/trolley/{tid}/{topic}`, and `gh/trolley/{tid}/{topic}/*` (any sender) for a topic
/// [keyed by its sender](TrolleyTopic::keyed_by_sender). Publishers use [`trolley_from`];
/// publishers and subscribers of one message type use the typed constructors ([`roi`], ...).
pub fn trolley(tid: &str, topic: TrolleyTopic) -> Result<String, KeyError> {
    validate_id(tid)?;
    Ok(with_any_sender(
        format!("{ROOT}/trolley/{tid}/{}", topic.as_str()),
        topic,
    ))
}

/// The key `sender` puts trolley `tid`'s topic on: `gh/trolley/{tid}/{topic}/{sender}` for a
/// topic keyed by its sender, else `gh/trolley/{tid}/{topic}` (`sender` not used).
pub fn trolley_from(tid: &str, topic: TrolleyTopic, sender: &str) -> Result<String, KeyError> {
    validate_id(tid)?;
    let key = format!("{ROOT}/trolley/{tid}/{}", topic.as_str());
    if !topic.keyed_by_sender() {
        return Ok(key);
    }
    validate_id(sender)?;
    Ok(format!("{key}/{sender}"))
}

/// `gh/trolley/*/{topic}` untyped (`gh/trolley/*/{topic}/*` for a topic keyed by its sender):
/// one topic of every trolley (typed: [`all_roi`], ...).
pub fn all_trolleys(topic: TrolleyTopic) -> String {
    with_any_sender(format!("{ROOT}/trolley/*/{}", topic.as_str()), topic)
}

/// `gh/trolley/*/{topic}/{sender}`: every key `sender` may put a topic keyed by its sender on
/// (what the router's ACL grants it); [`all_trolleys`] for other topics.
pub fn all_trolleys_from(topic: TrolleyTopic, sender: &str) -> Result<String, KeyError> {
    let all = format!("{ROOT}/trolley/*/{}", topic.as_str());
    if !topic.keyed_by_sender() {
        return Ok(all);
    }
    validate_id(sender)?;
    Ok(format!("{all}/{sender}"))
}

fn with_any_sender(key: String, topic: TrolleyTopic) -> String {
    match topic.keyed_by_sender() {
        true => format!("{key}/*"),
        false => key,
    }
}

/// The sender's id in a concrete key of a topic [keyed by its sender](TrolleyTopic::keyed_by_sender)
/// (`d1` in `gh/trolley/t1/roi/d1`); `None` for any other key, or a sender chunk that is no
/// valid id (a wildcard).
pub fn sender(key: &str) -> Option<&str> {
    let rest = key.strip_prefix(ROOT)?.strip_prefix("/trolley/")?;
    let parts: Vec<&str> = rest.split('/').collect();
    let &[tid, topic, sender] = parts.as_slice() else {
        return None;
    };
    let keyed = TrolleyTopic::parse(topic).is_some_and(TrolleyTopic::keyed_by_sender);
    (keyed && validate_id(tid).is_ok() && validate_id(sender).is_ok()).then_some(sender)
}

/// `gh/planner/{pid}/status`: PlannerStatus (reliable).
pub fn planner_status(pid: &str) -> Result<Key<PlannerStatus>, KeyError> {
    validate_id(pid)?;
    Ok(Key::new(
        format!("{ROOT}/planner/{pid}/status"),
        Qos::Reliable,
    ))
}

/// `gh/planner/*/status`: every planner's status.
pub fn all_planner_status() -> Key<PlannerStatus> {
    Key::new(format!("{ROOT}/planner/*/status"), Qos::Reliable)
}

/// `gh/planner/{pid}/snapshot/{tid}`: planner `pid`'s MapSnapshot of trolley `tid` (a query).
pub fn planner_snapshot(pid: &str, tid: &str) -> Result<Key<MapSnapshot>, KeyError> {
    validate_id(pid)?;
    validate_id(tid)?;
    Ok(Key::new(
        format!("{ROOT}/planner/{pid}/snapshot/{tid}"),
        Qos::Reliable,
    ))
}

/// `gh/planner/{pid}/snapshot/*`: what planner `pid`'s snapshot queryable answers.
pub fn planner_snapshots(pid: &str) -> Result<Key<MapSnapshot>, KeyError> {
    validate_id(pid)?;
    Ok(Key::new(
        format!("{ROOT}/planner/{pid}/snapshot/*"),
        Qos::Reliable,
    ))
}

/// `gh/detector/{did}/status`: DetectorStatus (reliable).
pub fn detector_status(did: &str) -> Result<Key<DetectorStatus>, KeyError> {
    validate_id(did)?;
    Ok(Key::new(
        format!("{ROOT}/detector/{did}/status"),
        Qos::Reliable,
    ))
}

/// `gh/detector/*/status`: every detector's status.
pub fn all_detector_status() -> Key<DetectorStatus> {
    Key::new(format!("{ROOT}/detector/*/status"), Qos::Reliable)
}

/// `gh/fleet/fruits`: the merged fruit map of the fleet (reliable).
pub fn fleet_fruits() -> Key<FleetFruits> {
    Key::new(FLEET_FRUITS.to_owned(), Qos::Reliable)
}

/// Kinds of member that announce themselves with a liveliness token.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MemberKind {
    Trolley,
    Planner,
    Detector,
}

impl MemberKind {
    pub fn as_str(self) -> &'static str {
        match self {
            MemberKind::Trolley => "trolley",
            MemberKind::Planner => "planner",
            MemberKind::Detector => "detector",
        }
    }
}

/// `gh/alive/{kind}/{id}`: a member's liveliness token.
pub fn alive(kind: MemberKind, id: &str) -> Result<String, KeyError> {
    validate_id(id)?;
    Ok(format!("{ROOT}/alive/{}/{id}", kind.as_str()))
}

/// `gh/alive/{kind}/*`: every member of a kind.
pub fn alive_all(kind: MemberKind) -> String {
    format!("{ROOT}/alive/{}/*", kind.as_str())
}

/// What a received key names.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ParsedKey {
    Trolley { tid: String, topic: TrolleyTopic },
    PlannerStatus { pid: String },
    PlannerSnapshot { pid: String, tid: String },
    DetectorStatus { did: String },
    FleetFruits,
    Alive { kind: MemberKind, id: String },
}

impl ParsedKey {
    /// The message kind published on this key, if it carries messages.
    pub fn message_kind(&self) -> Option<MessageKind> {
        match self {
            ParsedKey::Trolley { topic, .. } => Some(topic.message_kind()),
            ParsedKey::PlannerStatus { .. } => Some(MessageKind::PlannerStatus),
            ParsedKey::PlannerSnapshot { .. } => Some(MessageKind::MapSnapshot),
            ParsedKey::DetectorStatus { .. } => Some(MessageKind::DetectorStatus),
            ParsedKey::FleetFruits => Some(MessageKind::FleetFruits),
            ParsedKey::Alive { .. } => None,
        }
    }
}

/// Parses a concrete key of this project's tree; `None` for anything else.
pub fn parse(key: &str) -> Option<ParsedKey> {
    let rest = key.strip_prefix(ROOT)?.strip_prefix('/')?;
    let parts: Vec<&str> = rest.split('/').collect();
    let valid = |id: &str| validate_id(id).is_ok();
    match parts.as_slice() {
        ["trolley", tid, topic, rest @ ..] if valid(tid) => {
            let topic = TrolleyTopic::parse(topic)?;
            // Roi and views keys end in their sender's id (see [`sender`]).
            let complete = match (topic.keyed_by_sender(), rest) {
                (true, [sender]) => valid(sender),
                (false, []) => true,
                _ => false,
            };
            complete.then(|| ParsedKey::Trolley {
                tid: (*tid).to_owned(),
                topic,
            })
        }
        ["planner", pid, "status"] if valid(pid) => Some(ParsedKey::PlannerStatus {
            pid: (*pid).to_owned(),
        }),
        ["planner", pid, "snapshot", tid] if valid(pid) && valid(tid) => {
            Some(ParsedKey::PlannerSnapshot {
                pid: (*pid).to_owned(),
                tid: (*tid).to_owned(),
            })
        }
        ["detector", did, "status"] if valid(did) => Some(ParsedKey::DetectorStatus {
            did: (*did).to_owned(),
        }),
        ["fleet", "fruits"] => Some(ParsedKey::FleetFruits),
        ["alive", kind, id] if valid(id) => {
            let kind = [
                MemberKind::Trolley,
                MemberKind::Planner,
                MemberKind::Detector,
            ]
            .into_iter()
            .find(|k| k.as_str() == *kind)?;
            Some(ParsedKey::Alive {
                kind,
                id: (*id).to_owned(),
            })
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_round_trip_through_parse() {
        for topic in TrolleyTopic::ALL {
            let key = trolley_from("t-1", topic, "d_2").expect("valid id");
            assert_eq!(
                parse(&key),
                Some(ParsedKey::Trolley {
                    tid: "t-1".into(),
                    topic
                })
            );
        }
        assert_eq!(
            parse(planner_status("p1").expect("valid").as_str()),
            Some(ParsedKey::PlannerStatus { pid: "p1".into() })
        );
        assert_eq!(
            parse(&alive(MemberKind::Planner, "p2").expect("valid")),
            Some(ParsedKey::Alive {
                kind: MemberKind::Planner,
                id: "p2".into()
            })
        );
        assert_eq!(parse(FLEET_FRUITS), Some(ParsedKey::FleetFruits));
        assert_eq!(
            parse(planner_snapshot("p1", "t2").expect("valid").as_str()),
            Some(ParsedKey::PlannerSnapshot {
                pid: "p1".into(),
                tid: "t2".into()
            })
        );
        assert!(planner_snapshot("p1", "a/b").is_err());
        assert_eq!(parse("gh/trolley/t1/bogus"), None);
        assert_eq!(parse("other/trolley/t1/rgbd"), None);
    }

    #[test]
    fn clouds_and_views_are_keyed_by_their_sender() {
        let cloud = roi("t1", "d1").expect("valid");
        assert_eq!(cloud.as_str(), "gh/trolley/t1/roi/d1");
        assert_eq!(sender(cloud.as_str()), Some("d1"));
        assert_eq!(
            sender(views("t1", "p2").expect("valid").as_str()),
            Some("p2")
        );
        assert_eq!(
            roi_from_any("t1").expect("valid").as_str(),
            "gh/trolley/t1/roi/*"
        );
        assert_eq!(all_views().as_str(), "gh/trolley/*/views/*");
        assert_eq!(
            trolley("t1", TrolleyTopic::Views).expect("valid"),
            "gh/trolley/t1/views/*"
        );
        assert_eq!(
            trolley("t1", TrolleyTopic::Map).expect("valid"),
            "gh/trolley/t1/map"
        );
        assert_eq!(
            trolley_from("t1", TrolleyTopic::Map, "p1").expect("valid"),
            "gh/trolley/t1/map"
        );
        assert_eq!(
            all_trolleys_from(TrolleyTopic::Roi, "d1").expect("valid"),
            "gh/trolley/*/roi/d1"
        );
        assert!(roi("t1", "*").is_err() && views("t1", "a/b").is_err());
        // No sender, a wildcard or an extra chunk: not a key of the tree, no sender.
        for bad in [
            "gh/trolley/t1/roi",
            "gh/trolley/t1/roi/*",
            "gh/trolley/t1/views/**",
            "gh/trolley/t1/views/p1/x",
            "gh/trolley/t1/map/p1",
        ] {
            assert_eq!((parse(bad), sender(bad)), (None, None), "{bad}");
        }
        assert_eq!(sender("gh/trolley/t1/map"), None);
    }

    #[test]
    fn ids_must_be_single_chunks() {
        for bad in ["", "a/b", "*", "a b", "t$", &"x".repeat(65)] {
            assert!(
                trolley(bad, TrolleyTopic::Rgbd).is_err(),
                "{bad:?} accepted"
            );
        }
        assert!(validate_id("trolley_07-b").is_ok());
    }

    fn parsed_kind<M: Wire>(key: &Key<M>) -> Option<MessageKind> {
        parse(key.as_str()).and_then(|k| k.message_kind())
    }

    #[test]
    fn typed_keys_name_the_kind_their_key_carries() {
        assert_eq!(
            parsed_kind(&rgbd("t1").expect("valid")),
            Some(MessageKind::RgbdFrame)
        );
        assert_eq!(
            parsed_kind(&arm("t1").expect("valid")),
            Some(MessageKind::ArmState)
        );
        assert_eq!(
            parsed_kind(&info("t1").expect("valid")),
            Some(MessageKind::TrolleyInfo)
        );
        assert_eq!(
            parsed_kind(&roi("t1", "d1").expect("valid")),
            Some(MessageKind::RoiCloud)
        );
        assert_eq!(
            parsed_kind(&views("t1", "p1").expect("valid")),
            Some(MessageKind::RankedViews)
        );
        assert_eq!(
            parsed_kind(&fruits("t1").expect("valid")),
            Some(MessageKind::FruitEstimates)
        );
        assert_eq!(
            parsed_kind(&map("t1").expect("valid")),
            Some(MessageKind::MapUpdate)
        );
        assert_eq!(
            parsed_kind(&status("t1").expect("valid")),
            Some(MessageKind::TrolleyStatus)
        );
        assert_eq!(
            parsed_kind(&truth("t1").expect("valid")),
            Some(MessageKind::FruitEstimates)
        );
        assert_eq!(
            parsed_kind(&detector_status("d1").expect("valid")),
            Some(MessageKind::DetectorStatus)
        );
        assert_eq!(parsed_kind(&fleet_fruits()), Some(MessageKind::FleetFruits));
        assert_eq!(rgbd("t1").expect("valid").qos(), Qos::Stream);
        assert_eq!(roi("t1", "d1").expect("valid").qos(), Qos::Recovered);
        assert_eq!(all_roi().as_str(), "gh/trolley/*/roi/*");
        assert_eq!(all_planner_status().as_str(), "gh/planner/*/status");
        assert_eq!(all_detector_status().as_str(), "gh/detector/*/status");
        assert_eq!(
            planner_snapshots("p1").expect("valid").as_str(),
            "gh/planner/p1/snapshot/*"
        );
        assert!(roi("a/b", "d1").is_err());
    }
}
