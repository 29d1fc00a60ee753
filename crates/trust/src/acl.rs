//! The router's access control list, generated from the roster.
//!
//! Zenoh checks every message at the router twice: on the way in from its sender (ingress) and on
//! the way out to each receiver (egress); with `default_permission: deny` both must be allowed.
//! Each identity gets [`grants`]: what its role sends and receives, on which key expressions.
//! Besides the data itself a role needs the declarations that make it flow: a publisher is told
//! of the subscribers on its keys (egress `declare_subscriber`: Zenoh clients send only where a
//! subscriber is known), a watcher of liveliness receives the tokens (egress `liveliness_token`)
//! and may ask for the ones it watches (ingress `liveliness_query`, answered with tokens), and a
//! snapshot's answer travels back as a `reply`.
//!
//! Clouds and views are keyed by their sender (`gh/trolley/{tid}/roi/{did}`,
//! `gh/trolley/{tid}/views/{pid}`) and an identity may put them only under its own id, so a
//! receiver reads the sender from the key, proven by the sender's certificate. Which trolleys a
//! detector serves or a planner owns changes with the membership, so that is checked by the
//! receivers (the planners take a trolley's clouds only from the detector ranked first for it,
//! the edge views only from the planner ranked first), not here.

use glasshouse_proto::keys::{self, MemberKind, TrolleyTopic, FLEET_FRUITS, ROOT};
use serde_json::{json, Value};

use crate::{Identity, Kind, Roster};

/// A message type of Zenoh's ACL.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AclMessage {
    Put,
    Delete,
    DeclareSubscriber,
    Query,
    DeclareQueryable,
    Reply,
    LivelinessToken,
    DeclareLivelinessSubscriber,
    LivelinessQuery,
}

impl AclMessage {
    pub const ALL: [AclMessage; 9] = [
        AclMessage::Put,
        AclMessage::Delete,
        AclMessage::DeclareSubscriber,
        AclMessage::Query,
        AclMessage::DeclareQueryable,
        AclMessage::Reply,
        AclMessage::LivelinessToken,
        AclMessage::DeclareLivelinessSubscriber,
        AclMessage::LivelinessQuery,
    ];
}

/// Which way a message crosses the router, seen from the identity's link.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Flow {
    /// From the identity into the router.
    Ingress,
    /// From the router out to the identity.
    Egress,
}

/// One allowance: these messages, this way, on these key expressions (a rule of the ACL).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Grant {
    pub flow: Flow,
    pub messages: Vec<AclMessage>,
    pub key_exprs: Vec<String>,
}

fn grant(flow: Flow, messages: &[AclMessage], key_exprs: Vec<String>) -> Grant {
    Grant {
        flow,
        messages: messages.to_vec(),
        key_exprs,
    }
}

/// Puts on `keys`, and news of the subscribers to those keys (`all`: the same topics of any id,
/// as subscribers may declare them).
fn publish(keys: Vec<String>, all: Vec<String>) -> [Grant; 2] {
    [
        grant(Flow::Ingress, &[AclMessage::Put], keys),
        grant(Flow::Egress, &[AclMessage::DeclareSubscriber], all),
    ]
}

/// Subscribing to `keys` and receiving what is put there.
fn subscribe(keys: Vec<String>) -> [Grant; 2] {
    [
        grant(
            Flow::Ingress,
            &[AclMessage::DeclareSubscriber],
            keys.clone(),
        ),
        grant(Flow::Egress, &[AclMessage::Put], keys),
    ]
}

/// Its own liveliness token.
fn token(kind: MemberKind, id: &str) -> Option<Grant> {
    let key = keys::alive(kind, id).ok()?;
    Some(grant(
        Flow::Ingress,
        &[AclMessage::LivelinessToken],
        vec![key],
    ))
}

/// Following the membership of `kinds` (history included), and asking the router whether a
/// member that left is still declared (`glasshouse_bus::MemberWatch` checks every leave again).
fn watch(kinds: &[MemberKind]) -> [Grant; 2] {
    let all: Vec<String> = kinds.iter().map(|&k| keys::alive_all(k)).collect();
    [
        grant(
            Flow::Ingress,
            &[
                AclMessage::DeclareLivelinessSubscriber,
                AclMessage::LivelinessQuery,
            ],
            all.clone(),
        ),
        grant(Flow::Egress, &[AclMessage::LivelinessToken], all),
    ]
}

fn own(tid: &str, topics: &[TrolleyTopic]) -> Vec<String> {
    topics
        .iter()
        .filter_map(|&t| keys::trolley(tid, t).ok())
        .collect()
}

fn every(topics: &[TrolleyTopic]) -> Vec<String> {
    topics.iter().map(|&t| keys::all_trolleys(t)).collect()
}

/// `topics` of every trolley as `sender` may put them: clouds and views only on keys that end
/// in its own id, which is how receivers know who sent them.
fn every_from(topics: &[TrolleyTopic], sender: &str) -> Vec<String> {
    topics
        .iter()
        .filter_map(|&t| keys::all_trolleys_from(t, sender).ok())
        .collect()
}

/// What an edge publishes about its own trolley.
const TROLLEY_WRITES: [TrolleyTopic; 5] = [
    TrolleyTopic::Rgbd,
    TrolleyTopic::Arm,
    TrolleyTopic::Info,
    TrolleyTopic::Status,
    TrolleyTopic::Truth,
];
/// What the owning planner publishes for a trolley.
const PLANNER_WRITES: [TrolleyTopic; 3] =
    [TrolleyTopic::Views, TrolleyTopic::Fruits, TrolleyTopic::Map];
/// What planners read of every trolley (fruits: the fleet-map planner merges them).
const PLANNER_READS: [TrolleyTopic; 3] =
    [TrolleyTopic::Roi, TrolleyTopic::Info, TrolleyTopic::Fruits];

/// Every planner's snapshot queryable.
fn all_snapshots() -> String {
    format!("{ROOT}/planner/*/snapshot/*")
}

fn trolley_grants(tid: &str) -> Vec<Grant> {
    let mut grants = publish(own(tid, &TROLLEY_WRITES), every(&TROLLEY_WRITES)).to_vec();
    grants.extend(subscribe(own(tid, &[TrolleyTopic::Views])));
    grants.extend(token(MemberKind::Trolley, tid));
    // The edge ranks the planners itself to take views only from its trolley's owner.
    grants.extend(watch(&[MemberKind::Planner]));
    grants
}

/// A recovered topic's cache queryables (`{key}/@adv/pub/{zid}/{eid}/_`, zenoh-ext's form) under
/// `keys`, and the queries that name any sender (`{key}/@adv/*/{zid}/{eid}/**`).
fn caches(keys: &[String]) -> Vec<String> {
    keys.iter().map(|k| format!("{k}/@adv/**")).collect()
}

/// A detector's cache of its own clouds: declared, asked (the planners' queries name no sender),
/// answered only with clouds under its own id.
fn cloud_cache_grants(did: &str) -> Vec<Grant> {
    let mine = every_from(&[TrolleyTopic::Roi], did);
    let mut answers = mine.clone();
    answers.extend(caches(&mine));
    vec![
        grant(
            Flow::Ingress,
            &[AclMessage::DeclareQueryable, AclMessage::Reply],
            answers,
        ),
        grant(
            Flow::Egress,
            &[AclMessage::Query],
            caches(&every(&[TrolleyTopic::Roi])),
        ),
    ]
}

/// A planner asking the detectors' caches for a cloud it missed, and their answers.
fn cloud_recovery_grants() -> Vec<Grant> {
    let clouds = every(&[TrolleyTopic::Roi]);
    vec![
        grant(Flow::Ingress, &[AclMessage::Query], caches(&clouds)),
        grant(
            Flow::Egress,
            &[AclMessage::DeclareQueryable],
            caches(&clouds),
        ),
        grant(Flow::Egress, &[AclMessage::Reply], clouds),
    ]
}

fn detector_grants(did: &str) -> Vec<Grant> {
    let status = keys::detector_status(did).map(|k| k.as_str().to_owned());
    let mut writes = every_from(&[TrolleyTopic::Roi], did);
    writes.extend(status);
    let mut all = every(&[TrolleyTopic::Roi]);
    all.push(keys::all_detector_status().as_str().to_owned());
    let mut grants = publish(writes, all).to_vec();
    grants.extend(subscribe(every(&[TrolleyTopic::Rgbd])));
    grants.extend(cloud_cache_grants(did));
    grants.extend(token(MemberKind::Detector, did));
    grants.extend(watch(&[MemberKind::Detector, MemberKind::Trolley]));
    grants
}

fn planner_grants(pid: &str) -> Vec<Grant> {
    let mut writes = every_from(&PLANNER_WRITES, pid);
    writes.extend(keys::planner_status(pid).map(|k| k.as_str().to_owned()));
    writes.push(FLEET_FRUITS.to_owned());
    let mut all = every(&PLANNER_WRITES);
    all.push(keys::all_planner_status().as_str().to_owned());
    all.push(FLEET_FRUITS.to_owned());
    let mut grants = publish(writes, all).to_vec();
    grants.extend(subscribe(every(&PLANNER_READS)));
    grants.extend(cloud_recovery_grants());
    grants.extend(token(MemberKind::Planner, pid));
    // Clouds are taken only from live detectors.
    grants.extend(watch(&[
        MemberKind::Planner,
        MemberKind::Trolley,
        MemberKind::Detector,
    ]));
    if let Ok(mine) = keys::planner_snapshots(pid) {
        let mine = vec![mine.as_str().to_owned()];
        // Its queryable: declared, queried, answered.
        grants.push(grant(
            Flow::Ingress,
            &[AclMessage::DeclareQueryable, AclMessage::Reply],
            mine.clone(),
        ));
        grants.push(grant(Flow::Egress, &[AclMessage::Query], mine));
    }
    // Asking the other planners: the query out, their queryables and replies back.
    grants.push(grant(
        Flow::Ingress,
        &[AclMessage::Query],
        vec![all_snapshots()],
    ));
    grants.push(grant(
        Flow::Egress,
        &[AclMessage::Reply, AclMessage::DeclareQueryable],
        vec![all_snapshots()],
    ));
    grants
}

fn dashboard_grants() -> Vec<Grant> {
    let mut reads = every(&TrolleyTopic::ALL);
    reads.push(keys::all_planner_status().as_str().to_owned());
    reads.push(keys::all_detector_status().as_str().to_owned());
    reads.push(FLEET_FRUITS.to_owned());
    let mut grants = subscribe(reads).to_vec();
    // Who is live: the fleet page's membership, and what `secure probe` watches for fake tokens.
    grants.extend(watch(&[
        MemberKind::Planner,
        MemberKind::Trolley,
        MemberKind::Detector,
    ]));
    grants
}

/// Everything `identity` may do; anything else is denied.
pub fn grants(identity: &Identity) -> Vec<Grant> {
    match identity.kind {
        Kind::Trolley => trolley_grants(&identity.id),
        Kind::Detector => detector_grants(&identity.id),
        Kind::Planner => planner_grants(&identity.id),
        Kind::Dashboard => dashboard_grants(),
    }
}

/// The `access_control` section of the router's config: default deny, one subject per
/// certificate common name, its grants as rules.
pub fn acl(roster: &Roster) -> Value {
    let (mut rules, mut subjects, mut policies) = (Vec::new(), Vec::new(), Vec::new());
    for identity in roster.identities() {
        let name = identity.common_name();
        let mut ids = Vec::new();
        for (n, g) in grants(&identity).into_iter().enumerate() {
            let id = format!("{name}/{n}");
            rules.push(json!({
                "id": id,
                "permission": "allow",
                "flows": [g.flow],
                "messages": g.messages,
                "key_exprs": g.key_exprs,
            }));
            ids.push(id);
        }
        subjects.push(json!({ "id": name, "cert_common_names": [name] }));
        policies.push(json!({ "id": name, "rules": ids, "subjects": [name] }));
    }
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use AclMessage::*;
    use Flow::*;

    /// Key expression inclusion for the forms used here (`*` is one chunk, which `**` is not;
    /// `**` any number of chunks; neither stands for a verbatim `@` chunk), as Zenoh's ACL
    /// matches a message's key expression against a rule's.
    fn includes(pattern: &str, key: &str) -> bool {
        let (p, k): (Vec<&str>, Vec<&str>) =
            (pattern.split('/').collect(), key.split('/').collect());
        chunks_include(&p, &k)
    }

    fn chunks_include(p: &[&str], k: &[&str]) -> bool {
        let wild = |k: &str| !k.starts_with('@');
        match (p.split_first(), k.split_first()) {
            (None, None) => true,
            (Some((&"**", p_rest)), _) => {
                chunks_include(p_rest, k)
                    || k.split_first()
                        .is_some_and(|(k0, k_rest)| wild(k0) && chunks_include(p, k_rest))
            }
            (Some((p0, p_rest)), Some((k0, k_rest))) => {
                let chunk = (*p0 == "*" && *k0 != "**" && wild(k0)) || p0 == k0;
                chunk && chunks_include(p_rest, k_rest)
            }
            _ => false,
        }
    }

    fn may(kind: Kind, id: &str, flow: Flow, message: AclMessage, key: &str) -> bool {
        let identity = Identity::new(kind, id).expect("valid id");
        grants(&identity).iter().any(|g| {
            g.flow == flow
                && g.messages.contains(&message)
                && g.key_exprs.iter().any(|p| includes(p, key))
        })
    }

    const T: Kind = Kind::Trolley;
    const P: Kind = Kind::Planner;
    const D: Kind = Kind::Detector;
    const W: Kind = Kind::Dashboard;

    /// What identity `kind`-`id` may do, one case a line: `+` allowed or `-` denied, `in`
    /// (ingress) or `out` (egress), the message as the ACL spells it, the key.
    fn check(kind: Kind, id: &str, table: &str) {
        for line in table.lines().map(str::trim).filter(|l| !l.is_empty()) {
            let words: Vec<&str> = line.split_whitespace().collect();
            let &[sign, flow, message, key] = words.as_slice() else {
                panic!("bad case {line:?}");
            };
            let flow = if flow == "in" { Ingress } else { Egress };
            let message: AclMessage =
                serde_json::from_value(json!(message)).expect("an ACL message type");
            let allowed = may(kind, id, flow, message, key);
            assert_eq!(allowed, sign == "+", "{kind:?} {id}: {line}");
        }
    }

    /// Put on `gh/trolley/{tid}/{topic}` for each topic: `sign` `+` allowed, `-` denied.
    fn puts(sign: &str, who: (Kind, &str), tid: &str, topics: &[&str]) {
        for topic in topics {
            check(
                who.0,
                who.1,
                &format!("{sign} in put gh/trolley/{tid}/{topic}"),
            );
        }
    }

    #[test]
    fn a_trolley_writes_only_its_own_keys_and_reads_only_its_views() {
        let own = ["rgbd", "arm", "info", "status", "truth"];
        puts("+", (T, "t1"), "t1", &own);
        puts("-", (T, "t1"), "t2", &own);
        puts(
            "-",
            (T, "t1"),
            "t1",
            &["roi/t1", "views/t1", "fruits", "map"],
        );
        check(
            T,
            "t1",
            "
            + in declare_subscriber gh/trolley/t1/views/*
            + out put gh/trolley/t1/views/p1
            - in declare_subscriber gh/trolley/*/views/*
            - out put gh/trolley/t2/views/p1
            - in declare_subscriber gh/trolley/t1/roi/*
            + in declare_liveliness_subscriber gh/alive/planner/*
            + out liveliness_token gh/alive/planner/p1
            - in declare_liveliness_subscriber gh/alive/detector/*
            + in liveliness_token gh/alive/trolley/t1
            - in liveliness_token gh/alive/trolley/t2
            - in liveliness_token gh/alive/planner/t1
            - in query gh/planner/p1/snapshot/t1
            - out reply gh/planner/p1/snapshot/t1
            + out declare_subscriber gh/trolley/*/rgbd
            ",
        );
    }

    #[test]
    fn a_detector_writes_only_clouds_and_its_status() {
        puts("-", (D, "d1"), "t1", &["rgbd", "views/d1", "fruits", "map"]);
        check(
            D,
            "d1",
            "
            + in put gh/detector/d1/status
            - in put gh/detector/d2/status
            + in declare_subscriber gh/trolley/t1/rgbd
            + out put gh/trolley/t1/rgbd
            - out put gh/trolley/t1/views/p1
            + in liveliness_token gh/alive/detector/d1
            - in liveliness_token gh/alive/planner/d1
            + in declare_liveliness_subscriber gh/alive/trolley/*
            + out liveliness_token gh/alive/detector/d2
            - in query gh/planner/p1/snapshot/t1
            ",
        );
    }

    #[test]
    fn a_detectors_cache_answers_only_with_its_own_clouds_and_planners_may_ask_it() {
        check(
            D,
            "d1",
            "
            + in declare_queryable gh/trolley/t7/roi/d1/@adv/pub/zid/5/_
            - in declare_queryable gh/trolley/t7/roi/d2/@adv/pub/zid/5/_
            - in declare_queryable gh/trolley/t7/views/d1/@adv/pub/zid/5/_
            + in reply gh/trolley/t7/roi/d1
            - in reply gh/trolley/t7/roi/d2
            - in reply gh/planner/p1/snapshot/t7
            + out query gh/trolley/*/roi/*/@adv/*/zid/5/**
            - in query gh/trolley/*/roi/*/@adv/*/zid/5/**
            ",
        );
        check(
            P,
            "p1",
            "
            + in query gh/trolley/*/roi/*/@adv/*/zid/5/**
            + out declare_queryable gh/trolley/t7/roi/d1/@adv/pub/zid/5/_
            + out reply gh/trolley/t7/roi/d1
            - in reply gh/trolley/t7/roi/d1
            - in declare_queryable gh/trolley/t7/roi/p1/@adv/pub/zid/5/_
            - in query gh/trolley/*/views/*/@adv/*/zid/5/**
            ",
        );
        check(
            T,
            "t1",
            "
            - in declare_queryable gh/trolley/t1/roi/t1/@adv/pub/zid/5/_
            - in query gh/trolley/*/roi/*/@adv/*/zid/5/**
            ",
        );
    }

    #[test]
    fn a_detector_puts_clouds_only_under_its_own_id() {
        puts("+", (D, "d1"), "t7", &["roi/d1"]);
        // Another detector's key, a planner's, no sender, or a wildcard standing for any.
        for roi in ["roi/d2", "roi/p1", "roi", "roi/*", "roi/**"] {
            puts("-", (D, "d1"), "t7", &[roi]);
        }
        // Told of the planners' and dashboards' subscriptions to every detector's clouds.
        check(D, "d1", "+ out declare_subscriber gh/trolley/*/roi/*");
    }

    #[test]
    fn a_planner_puts_views_only_under_its_own_id() {
        puts("+", (P, "p1"), "t3", &["views/p1"]);
        for views in ["views/p2", "views/t3", "views", "views/*"] {
            puts("-", (P, "p1"), "t3", &[views]);
        }
        // Told of the edge's subscription to its trolley's views from every planner.
        check(P, "p1", "+ out declare_subscriber gh/trolley/t3/views/*");
    }

    #[test]
    fn a_planner_writes_results_and_only_planners_query_snapshots() {
        puts("+", (P, "p1"), "t3", &["views/p1", "fruits", "map"]);
        puts(
            "-",
            (P, "p1"),
            "t3",
            &["rgbd", "arm", "info", "roi/p1", "status"],
        );
        let snapshot = "gh/planner/p1/snapshot/t1";
        check(
            P,
            "p1",
            "
            + in put gh/planner/p1/status
            - in put gh/planner/p2/status
            + in put gh/fleet/fruits
            + in declare_queryable gh/planner/p1/snapshot/*
            - in declare_queryable gh/planner/p2/snapshot/*
            + out query gh/planner/p1/snapshot/t1
            - out query gh/planner/p2/snapshot/t1
            + in reply gh/planner/p1/snapshot/t1
            - in reply gh/planner/p2/snapshot/t1
            + out put gh/trolley/t3/roi/d1
            - in declare_subscriber gh/trolley/t3/roi
            + out put gh/trolley/t3/info
            + out put gh/trolley/t3/fruits
            - out put gh/trolley/t3/rgbd
            + in liveliness_token gh/alive/planner/p1
            - in liveliness_token gh/alive/trolley/p1
            + in declare_liveliness_subscriber gh/alive/detector/*
            + out liveliness_token gh/alive/detector/d1
            ",
        );
        for (kind, sign) in [(P, "+"), (T, "-"), (D, "-"), (W, "-")] {
            let asking = format!("{sign} in query {snapshot}\n{sign} out reply {snapshot}");
            check(kind, "p2", &asking);
        }
    }

    #[test]
    fn a_dashboard_only_reads() {
        let every_key = [
            "gh/trolley/t1/rgbd",
            "gh/trolley/t1/views/p1",
            "gh/trolley/t1/map",
            "gh/planner/p1/status",
            "gh/detector/d1/status",
            "gh/fleet/fruits",
            "gh/alive/trolley/web1",
            "gh/planner/p1/snapshot/t1",
        ];
        for key in every_key {
            for message in AclMessage::ALL {
                let alive = key.starts_with("gh/alive");
                let subscribing = message == DeclareSubscriber && !key.contains("snapshot");
                let watching = matches!(message, DeclareLivelinessSubscriber | LivelinessQuery);
                assert_eq!(
                    may(W, "web1", Ingress, message, key),
                    if alive { watching } else { subscribing },
                    "{message:?} {key}"
                );
            }
        }
        assert!(may(
            W,
            "web1",
            Ingress,
            DeclareSubscriber,
            "gh/trolley/*/rgbd"
        ));
        assert!(may(W, "web1", Egress, Put, "gh/trolley/t9/truth"));
        assert!(may(
            W,
            "web1",
            Egress,
            LivelinessToken,
            "gh/alive/planner/p1"
        ));
    }

    #[test]
    fn nobody_deletes_and_liveliness_is_queried_only_where_it_is_watched() {
        for kind in Kind::ALL {
            let identity = Identity::new(kind, "x").expect("valid");
            for g in grants(&identity) {
                assert!(!g.messages.contains(&Delete));
                if g.messages.contains(&LivelinessQuery) {
                    assert!(g.messages.contains(&DeclareLivelinessSubscriber), "{g:?}");
                }
            }
        }
        check(
            T,
            "t1",
            "
            + in liveliness_query gh/alive/planner/p1
            - in liveliness_query gh/alive/detector/d1
            - in liveliness_query gh/alive/trolley/t2
            ",
        );
        check(D, "d1", "+ in liveliness_query gh/alive/trolley/t1");
    }

    #[test]
    fn the_acl_has_a_subject_and_a_policy_per_identity() {
        let acl = acl(&crate::tests::roster());
        assert_eq!(acl["default_permission"], "deny");
        let subjects = acl["subjects"].as_array().expect("subjects");
        assert_eq!(subjects.len(), 6);
        assert_eq!(subjects[0]["cert_common_names"], json!(["trolley-t1"]));
        let policy = &acl["policies"][0];
        assert_eq!(policy["subjects"], json!(["trolley-t1"]));
        let rule_ids: Vec<&str> = acl["rules"]
            .as_array()
            .expect("rules")
            .iter()
            .filter_map(|r| r["id"].as_str())
            .collect();
        for id in policy["rules"].as_array().expect("ids") {
            assert!(rule_ids.contains(&id.as_str().expect("id")));
        }
        assert_eq!(acl["rules"][0]["flows"], json!(["ingress"]));
        assert_eq!(acl["rules"][0]["messages"], json!(["put"]));
    }
}
