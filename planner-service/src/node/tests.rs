#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_pipeline::Alignment;
use glasshouse_pipeline::{detect_frame, TrolleySource};
use glasshouse_proto::{FrameId, FrameRegistration, RegistrationReason, RegistrationVerdict};
use glasshouse_sim::ScenarioKind;
use glasshouse_simtrolley::{SimTrolley, SimTrolleySettings};

use super::*;

/// The receiver's wall clock in these tests (Unix ns).
const NOW_NS: u64 = 1_790_000_000_000_000_000;
/// The boot epoch of trolley t1's edge: an hour before now.
const EDGE_EPOCH_NS: u64 = NOW_NS - 3_600_000_000_000;

/// Trolley t1's info and `n` clouds (frames 1..=n of its edge's epoch) of scenario 2 at a small
/// resolution.
fn trolley_clouds(n: u64) -> (TrolleyInfo, Vec<RoiCloud>) {
    let mut trolley =
        SimTrolley::new(SimTrolleySettings::new(ScenarioKind::Two, 3, (96, 72), 1.0)).unwrap();
    let clouds = (1..=n)
        .map(|seq| {
            let frame = trolley.capture(seq).unwrap().unwrap();
            let frame_id = FrameId::new(EDGE_EPOCH_NS, seq);
            detect_frame(&frame, frame_id, "d1", &DetectorConfig::default()).unwrap()
        })
        .collect();
    (trolley.info(), clouds)
}

fn header(tid: &str, seq: u64) -> Header {
    Header {
        seq,
        trolley_id: tid.into(),
        source_id: "d1".into(),
        frame_id: "world".into(),
        ..Header::default()
    }
}

fn cloud_event(cloud: &RoiCloud) -> PlannerEvent {
    cloud_from("d1", cloud, NOW_NS)
}

/// A cloud as it arrives on `header.source_id`'s key.
fn keyed(header: Header, cloud: RoiCloud) -> KeyedCloud {
    KeyedCloud {
        sender: header.source_id.clone(),
        header,
        cloud,
    }
}

fn cloud_from(source: &str, cloud: &RoiCloud, received_ns: u64) -> PlannerEvent {
    PlannerEvent::Cloud {
        sender: source.into(),
        header: Header {
            source_id: source.into(),
            ..header("t1", cloud.source_frame_seq)
        },
        cloud: cloud.clone(),
        received_ns,
    }
}

fn status_tick(now_ns: u64) -> PlannerEvent {
    PlannerEvent::StatusTick {
        dropped_messages: 4,
        now_ns,
    }
}

fn info_event(info: &TrolleyInfo) -> PlannerEvent {
    PlannerEvent::Info {
        header: header("t1", 0),
        info: info.clone(),
    }
}

/// A planner that knows detector d1, with hot replicas (they integrate every cloud).
fn node(pid: &str) -> PlannerNode {
    node_with_refresh(pid, 0)
}

/// A planner that knows detector d1; its replicas stand by for `refresh` clouds (0: hot).
fn node_with_refresh(pid: &str, refresh: usize) -> PlannerNode {
    let mut node = PlannerNode::new(
        pid,
        PlanningSettings {
            scoring_threads: 1,
            ..PlanningSettings::default()
        },
        NOW_NS,
    )
    .with_replica_refresh(refresh);
    assert!(node
        .handle(PlannerEvent::DetectorJoined("d1".into()))
        .is_empty());
    node
}

fn asks(actions: &[PlannerAction]) -> Vec<(String, Vec<String>)> {
    actions
        .iter()
        .filter_map(|a| match a {
            PlannerAction::AskSnapshot { tid, sources, .. } => Some((tid.clone(), sources.clone())),
            _ => None,
        })
        .collect()
}

/// `actions` and what the `Finish` and `NextCloud` events they ask for give, fed back as the
/// driver does.
fn settle(node: &mut PlannerNode, actions: Vec<PlannerAction>) -> Vec<PlannerAction> {
    let mut out = Vec::new();
    for action in actions {
        let back = match &action {
            PlannerAction::Finish { tid } => Some(PlannerEvent::Finish { tid: tid.clone() }),
            PlannerAction::NextCloud => Some(PlannerEvent::NextCloud),
            _ => None,
        };
        out.push(action);
        if let Some(event) = back {
            let more = node.handle(event);
            out.extend(settle(node, more));
        }
    }
    out
}

fn views_of(actions: &[PlannerAction]) -> Vec<RankedViews> {
    actions
        .iter()
        .filter_map(|a| match a {
            PlannerAction::Publish {
                output: TrolleyOutput::Views(v),
                ..
            } => Some(v.clone()),
            _ => None,
        })
        .collect()
}

/// Two planners that both know each other and t1, with empty, live copies of t1.
fn pair() -> (PlannerNode, PlannerNode) {
    pair_with_refresh(0)
}

/// [`pair`] with replicas that stand by for `refresh` clouds.
fn pair_with_refresh(refresh: usize) -> (PlannerNode, PlannerNode) {
    let (mut a, mut b) = (
        node_with_refresh("p1", refresh),
        node_with_refresh("p2", refresh),
    );
    for (n, other) in [(&mut a, "p2"), (&mut b, "p1")] {
        n.handle(PlannerEvent::PlannerJoined(other.into()));
        let actions = n.handle(PlannerEvent::TrolleyJoined("t1".into()));
        assert_eq!(
            asks(&actions),
            vec![("t1".to_string(), vec![other.to_string()])]
        );
        assert!(n.is_loading("t1"));
        n.handle(PlannerEvent::SnapshotLoaded {
            tid: "t1".into(),
            snapshot: None,
        });
        assert!(!n.is_loading("t1"));
    }
    (a, b)
}

/// (owner, replica) of t1.
fn roles((a, b): (PlannerNode, PlannerNode)) -> (PlannerNode, PlannerNode) {
    match (a.role("t1"), b.role("t1")) {
        (Some(Role::Owner), Some(Role::Replica)) => (a, b),
        (Some(Role::Replica), Some(Role::Owner)) => (b, a),
        other => panic!("one owner and one replica expected, got {other:?}"),
    }
}

/// (owner, replica) of t1, both with t1's info.
fn informed_owner_and_replica(info: &TrolleyInfo) -> (PlannerNode, PlannerNode) {
    let (mut owner, mut replica) = roles(pair());
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(info));
    }
    (owner, replica)
}

#[test]
fn the_owner_plans_and_publishes_the_replica_only_integrates() {
    let (info, clouds) = trolley_clouds(2);
    let (mut owner, mut replica) = informed_owner_and_replica(&info);
    for cloud in &clouds {
        let published = owner.handle(cloud_event(cloud));
        let views = views_of(&published);
        assert_eq!(views.len(), 1);
        assert_eq!(views[0].based_on_seq, cloud.source_frame_seq);
        assert_eq!(published.len(), 3, "views, fruits and map");
        assert!(replica.handle(cloud_event(cloud)).is_empty());
    }
    assert_eq!(owner.stats().clouds_integrated, 2);
    assert_eq!(replica.stats().clouds_integrated, 2);
    assert_eq!(owner.stats().views_published, 2);
    let (om, rm) = (owner.planner("t1").unwrap(), replica.planner("t1").unwrap());
    assert_eq!(om.map().len(), rm.map().len());
    assert_eq!(om.last_frame(), Some(FrameId::new(EDGE_EPOCH_NS, 2)));
    // Every stage is timed on the owner; the replica integrates, clusters and tracks only.
    let (o, r) = (owner.stats().stages, replica.stats().stages);
    assert!(o.integrate_ms > 0.0 && o.fit_ms > 0.0 && o.plan_ms > 0.0 && o.publish_ms > 0.0);
    assert!(r.integrate_ms > 0.0 && r.cluster_ms > 0.0);
    assert_eq!((r.fit_ms, r.plan_ms), (0.0, 0.0));
    let actions = owner.handle(status_tick(NOW_NS));
    let PlannerAction::PublishStatus { status, .. } = &actions[0] else {
        panic!("{actions:?}")
    };
    assert_eq!(status.stage_totals, o);
}

#[test]
fn planning_waits_for_the_trolley_info() {
    let (info, clouds) = trolley_clouds(2);
    let (mut owner, _) = roles(pair());
    let actions = owner.handle(cloud_event(&clouds[0]));
    assert!(views_of(&actions).is_empty());
    assert_eq!(owner.stats().clouds_integrated, 1);
    owner.handle(info_event(&info));
    assert_eq!(views_of(&owner.handle(cloud_event(&clouds[1]))).len(), 1);
}

/// `n` clouds of a trolley, and its owner and hot replica, informed, with the first integrated.
fn owner_and_replica_on_the_first_of(n: u64) -> (Vec<RoiCloud>, PlannerNode, PlannerNode) {
    let (info, clouds) = trolley_clouds(n);
    let (mut owner, mut replica) = roles(pair());
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
        n.handle(cloud_event(&clouds[0]));
    }
    (clouds, owner, replica)
}

#[test]
fn a_cloud_after_a_takeover_finishes_the_one_before_first() {
    let (clouds, mut owner, mut replica) = owner_and_replica_on_the_first_of(2);
    let taken = replica.handle(PlannerEvent::PlannerLeft(owner.pid.clone()));
    assert_eq!(outputs_for(&taken, "t1"), (1, 0, 0), "{taken:?}");
    // The next cloud comes before the Finish event: frame 1's fruits and map go out first,
    // each based on its frame (not on the message's own seq).
    let PlannerEvent::Cloud {
        sender,
        mut header,
        cloud,
        received_ns,
    } = cloud_event(&clouds[1])
    else {
        unreachable!("cloud_event makes a cloud")
    };
    header.seq = 99;
    let second = PlannerEvent::Cloud {
        sender,
        header,
        cloud,
        received_ns,
    };
    let actions = replica.handle(second);
    let maps: Vec<u64> = actions
        .iter()
        .filter_map(|a| match a {
            PlannerAction::Publish {
                output: TrolleyOutput::Map(m),
                ..
            } => Some(m.based_on_seq),
            _ => None,
        })
        .collect();
    assert_eq!(maps, vec![1, 2]);
    assert_eq!(outputs_for(&actions, "t1"), (1, 2, 2), "{actions:?}");
    assert!(replica
        .handle(PlannerEvent::Finish { tid: "t1".into() })
        .is_empty());
    owner.handle(cloud_event(&clouds[1]));
    let ids = |n: &PlannerNode| {
        let snapshot = n.planner("t1").expect("holds t1").snapshot("t1", "p");
        let fruits = snapshot.expect("a snapshot").tracked_fruits;
        fruits.iter().map(|f| f.id).collect::<Vec<_>>()
    };
    assert_eq!(
        ids(&replica),
        ids(&owner),
        "the same fruit ids as the lost owner's"
    );
}

#[test]
fn the_replica_takes_over_and_plans_on_the_latest_cloud_at_once() {
    let (_, owner, mut replica) = owner_and_replica_on_the_first_of(1);
    let lost = owner.pid.clone();
    let actions = replica.handle(PlannerEvent::PlannerLeft(lost));
    assert_eq!(replica.role("t1"), Some(Role::Owner));
    let views = views_of(&actions);
    assert_eq!(views.len(), 1, "{actions:?}");
    assert_eq!(views[0].based_on_seq, 1);
    // The views go out first; the clusters, fruit ids and fits follow on the event asked for.
    assert_eq!(outputs_for(&actions, "t1"), (1, 0, 0), "{actions:?}");
    let finish = PlannerAction::Finish { tid: "t1".into() };
    assert_eq!(actions.last(), Some(&finish));
    let finished = replica.handle(PlannerEvent::Finish { tid: "t1".into() });
    assert_eq!(outputs_for(&finished, "t1"), (0, 1, 1), "{finished:?}");
    let term = replica.term("t1").expect("the new owner's term");
    assert_eq!(epochs_of(&finished), vec![term; 2]);
    assert!(replica
        .handle(PlannerEvent::Finish { tid: "t1".into() })
        .is_empty());
    // The frame was not inserted twice.
    assert_eq!(replica.stats().clouds_integrated, 2);
    assert_eq!(
        replica.planner("t1").unwrap().map().len(),
        owner.planner("t1").unwrap().map().len()
    );
}

#[test]
fn our_own_token_going_away_changes_nothing() {
    let (mut a, _) = pair();
    // Our own token going away is not news.
    assert!(a.handle(PlannerEvent::PlannerLeft("p1".into())).is_empty());
    assert!(a.role("t1").is_some());
}

/// Planner p1, alone with t1 (no snapshot to load), after `info` and `clouds`.
fn alone_with(info: &TrolleyInfo, clouds: &[RoiCloud]) -> PlannerNode {
    let mut p1 = node("p1");
    p1.handle(PlannerEvent::TrolleyJoined("t1".into()));
    p1.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: None,
    });
    p1.handle(info_event(info));
    for c in clouds {
        p1.handle(cloud_event(c));
    }
    p1
}

/// Planner p2, joining a cluster where p1 is live.
fn joining_p1() -> PlannerNode {
    let mut p2 = node("p2");
    p2.handle(PlannerEvent::PlannerJoined("p1".into()));
    p2
}

/// p2, a planner that knows p1, told of t1 (`info`).
fn p2_told_of(info: &TrolleyInfo) -> PlannerNode {
    let mut p2 = joining_p1();
    p2.handle(PlannerEvent::TrolleyJoined("t1".into()));
    p2.handle(info_event(info));
    p2
}

/// Loads into `to` the map of t1 that `from` holds now.
fn load_t1_from(from: &PlannerNode, to: &mut PlannerNode) {
    let Ok((_, snapshot)) = from.snapshot_of("t1") else {
        panic!("{} holds t1", from.pid)
    };
    to.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(snapshot),
    });
}

#[test]
fn a_late_planner_buffers_clouds_until_the_snapshot_is_loaded() {
    let (info, clouds) = trolley_clouds(3);
    // p1 alone owns t1 and integrates two clouds.
    let mut p1 = alone_with(&info, &clouds[..2]);
    // p2 joins: it asks p1 for a snapshot and buffers the third cloud meanwhile.
    let mut p2 = joining_p1();
    let actions = p2.handle(PlannerEvent::TrolleyJoined("t1".into()));
    assert_eq!(
        asks(&actions),
        vec![("t1".to_string(), vec!["p1".to_string()])]
    );
    p1.handle(PlannerEvent::PlannerJoined("p2".into()));
    assert!(p2.handle(info_event(&info)).is_empty());
    assert!(p2.handle(cloud_event(&clouds[2])).is_empty());
    assert!(p2.is_loading("t1"));
    assert_eq!(p2.stats().clouds_integrated, 0);
    // Nobody gets a snapshot of a copy that is still loading.
    let refused = p2.handle(PlannerEvent::SnapshotAsked {
        query_id: 9,
        tid: "t1".into(),
        base: None,
    });
    assert!(matches!(
        &refused[..],
        [PlannerAction::ReplySnapshot {
            query_id: 9,
            answer: Err(_)
        }]
    ));
    let reply = p1.handle(PlannerEvent::SnapshotAsked {
        query_id: 1,
        tid: "t1".into(),
        base: None,
    });
    let [PlannerAction::ReplySnapshot {
        answer: Ok((h, snapshot)),
        ..
    }] = &reply[..]
    else {
        panic!("{reply:?}")
    };
    assert_eq!((h.seq, snapshot.based_on_seq), (2, 2));
    let loaded = p2.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(snapshot.clone()),
    });
    assert!(!p2.is_loading("t1"));
    // The buffered cloud is integrated on top of the snapshot: the same map as p1's after it.
    p1.handle(cloud_event(&clouds[2]));
    let (m1, m2) = (
        p1.planner("t1").unwrap().map(),
        p2.planner("t1").unwrap().map(),
    );
    assert_eq!(m1.len(), m2.len());
    assert!(m1.iter().all(|(k, v)| m2.get(k) == Some(v)));
    assert_eq!(
        p2.planner("t1").unwrap().last_frame(),
        Some(FrameId::new(EDGE_EPOCH_NS, 3))
    );
    // As owner it plans on the last buffered cloud, as replica it stays quiet.
    let planned = views_of(&loaded);
    match p2.role("t1") {
        Some(Role::Owner) => assert_eq!(planned[0].based_on_seq, 3),
        _ => assert!(planned.is_empty()),
    }
}

#[test]
fn a_trolley_that_leaves_and_returns_keeps_its_map() {
    let (info, clouds) = trolley_clouds(2);
    let (mut owner, _) = roles(pair());
    owner.handle(info_event(&info));
    owner.handle(cloud_event(&clouds[0]));
    let known = owner.planner("t1").unwrap().map().len();
    assert!(owner
        .handle(PlannerEvent::TrolleyLeft("t1".into()))
        .is_empty());
    assert_eq!(owner.role("t1"), Some(Role::Owner));
    let back = owner.handle(PlannerEvent::TrolleyJoined("t1".into()));
    assert!(asks(&back).is_empty(), "no snapshot needed: {back:?}");
    assert_eq!(owner.planner("t1").unwrap().map().len(), known);
    assert_eq!(views_of(&owner.handle(cloud_event(&clouds[1]))).len(), 1);
}

#[test]
fn bad_clouds_are_counted_and_leave_the_map_alone() {
    let (info, clouds) = trolley_clouds(1);
    let (mut owner, _) = roles(pair());
    owner.handle(info_event(&info));
    let mut bad_id = cloud_event(&clouds[0]);
    if let PlannerEvent::Cloud { header, .. } = &mut bad_id {
        header.trolley_id = "t1/../x".into();
    }
    assert!(owner.handle(bad_id).is_empty());
    let mut short = clouds[0].clone();
    short.roi.pop();
    assert!(owner.handle(cloud_event(&short)).is_empty());
    assert_eq!(owner.stats().clouds_rejected, 2);
    assert_eq!(owner.planner("t1").unwrap().map().len(), 0);
}

#[test]
fn a_cloud_whose_colours_are_not_one_per_roi_point_is_taken_without_colour_and_counted() {
    let (info, clouds) = trolley_clouds(3);
    let (mut owner, _) = roles(pair());
    owner.handle(info_event(&info));
    let mut broken = clouds[0].clone();
    assert!(!broken.roi_rgb.is_empty(), "the detector sends colours");
    broken.roi_rgb.pop();
    let actions = owner.handle(cloud_event(&broken));
    assert_eq!(views_of(&actions).len(), 1, "planned on as any cloud");
    let fruits = published_fruits(&actions).expect("fruits");
    assert!(
        fruits.fruits.iter().all(|f| f.colour.is_none()),
        "{fruits:?}"
    );
    assert_eq!(owner.stats().clouds_colourless, 1);
    assert_eq!(
        status_of(&owner.handle(status_tick(NOW_NS))).colourless_clouds,
        1
    );
    // The next clouds' colours are taken.
    owner.handle(cloud_event(&clouds[1]));
    let fruits = published_fruits(&owner.handle(cloud_event(&clouds[2]))).expect("fruits");
    assert!(
        fruits.fruits.iter().any(|f| f.colour.is_some()),
        "{fruits:?}"
    );
    assert_eq!(owner.stats().clouds_colourless, 1);
}

#[test]
fn the_status_lists_owned_and_standby_trolleys() {
    let (owner, replica) = roles(pair());
    for (mut n, owned) in [(owner, true), (replica, false)] {
        let actions = n.handle(status_tick(NOW_NS));
        let PlannerAction::PublishStatus { status, .. } = &actions[0] else {
            panic!("{actions:?}")
        };
        let t1 = vec!["t1".to_string()];
        let (o, s) = if owned {
            (t1, Vec::new())
        } else {
            (Vec::new(), t1)
        };
        assert_eq!(
            (
                status.owned_trolleys.clone(),
                status.standby_trolleys.clone()
            ),
            (o, s)
        );
        assert_eq!(status.dropped_messages, 4);
    }
}

/// The outputs published for `tid`, by kind: (views, fruits, map updates).
fn outputs_for(actions: &[PlannerAction], tid: &str) -> (usize, usize, usize) {
    let mut counts = (0, 0, 0);
    for action in actions {
        if let PlannerAction::Publish { tid: t, output, .. } = action {
            if t != tid {
                continue;
            }
            match output {
                TrolleyOutput::Views(_) => counts.0 += 1,
                TrolleyOutput::Fruits(_) => counts.1 += 1,
                TrolleyOutput::Map(_) => counts.2 += 1,
            }
        }
    }
    counts
}

#[test]
fn queued_clouds_are_all_integrated_and_planned_once_on_the_latest() {
    let (info, clouds) = trolley_clouds(3);
    let (mut owner, mut replica) = informed_owner_and_replica(&info);
    let batch = || {
        let queued = clouds
            .iter()
            .map(|c| keyed(header("t1", c.source_frame_seq), c.clone()));
        PlannerEvent::Clouds {
            clouds: queued.collect(),
            received_ns: NOW_NS,
        }
    };
    let actions = feed(&mut owner, batch());
    assert_eq!(owner.stats().clouds_integrated, 3);
    assert_eq!(owner.stats().plans, 1);
    let views = views_of(&actions);
    assert_eq!(views.len(), 1);
    assert_eq!(views[0].based_on_seq, 3);
    // Every cloud's map changes go out; fruits with the one plan.
    assert_eq!(outputs_for(&actions, "t1"), (1, 1, 3));
    assert!(replica.handle(batch()).is_empty());
    assert_eq!(replica.stats().clouds_integrated, 3);
    // The same map as integrating the clouds one at a time.
    let (mut single, _) = roles(pair());
    single.handle(info_event(&info));
    for cloud in &clouds {
        single.handle(cloud_event(cloud));
    }
    let (batched, one_by_one) = (owner.planner("t1").unwrap(), single.planner("t1").unwrap());
    assert_eq!(batched.map().len(), one_by_one.map().len());
    assert_eq!(batched.last_frame().map(|f| f.seq), Some(3));
    // A later single cloud is planned on at once again.
    let (_, more) = trolley_clouds(4);
    assert_eq!(views_of(&owner.handle(cloud_event(&more[3]))).len(), 1);
    assert_eq!(owner.stats().plans, 2);
}

#[test]
fn a_batch_of_several_trolleys_plans_each_once_on_its_own_latest() {
    let (info, clouds) = trolley_clouds(3);
    let mut solo = owning_t1_and_t2(&info);
    let batch = vec![
        keyed_as("t1", &clouds[0]),
        keyed_as("t2", &clouds[0]),
        keyed_as("t1", &clouds[1]),
        keyed_as("t1", &clouds[2]),
        keyed_as("t2", &clouds[1]),
    ];
    let actions = feed(
        &mut solo,
        PlannerEvent::Clouds {
            clouds: batch,
            received_ns: NOW_NS,
        },
    );
    assert_eq!(solo.stats().clouds_integrated, 5);
    assert_eq!(solo.stats().plans, 2);
    assert_eq!(outputs_for(&actions, "t1"), (1, 1, 3));
    assert_eq!(outputs_for(&actions, "t2"), (1, 1, 2));
    assert_eq!(
        views_for(&actions),
        vec![("t1".into(), 3), ("t2".into(), 2)]
    );
}

/// `cloud` as trolley `tid`'s, sent by its detector.
fn keyed_as(tid: &str, cloud: &RoiCloud) -> KeyedCloud {
    keyed(header(tid, cloud.source_frame_seq), cloud.clone())
}

/// A planner owning t1 and t2 alone, both informed.
fn owning_t1_and_t2(info: &TrolleyInfo) -> PlannerNode {
    let mut solo = node("p1");
    for tid in ["t1", "t2"] {
        solo.handle(PlannerEvent::TrolleyJoined(tid.into()));
        solo.handle(PlannerEvent::SnapshotLoaded {
            tid: tid.into(),
            snapshot: None,
        });
        solo.handle(PlannerEvent::Info {
            header: header(tid, 0),
            info: info.clone(),
        });
    }
    solo
}

fn views_for(actions: &[PlannerAction]) -> Vec<(String, u64)> {
    actions
        .iter()
        .filter_map(|a| match a {
            PlannerAction::Publish {
                tid,
                output: TrolleyOutput::Views(v),
                ..
            } => Some((tid.clone(), v.based_on_seq)),
            _ => None,
        })
        .collect()
}

#[test]
fn a_trolleys_views_go_out_before_the_next_trolleys_cloud_is_integrated() {
    let (info, clouds) = trolley_clouds(3);
    let mut solo = owning_t1_and_t2(&info);
    let first = solo.handle(PlannerEvent::Clouds {
        clouds: vec![keyed_as("t1", &clouds[0]), keyed_as("t2", &clouds[0])],
        received_ns: NOW_NS,
    });
    assert_eq!(views_for(&first), vec![("t1".into(), 1)]);
    assert_eq!(first.last(), Some(&PlannerAction::NextCloud));
    assert_eq!(solo.stats().clouds_integrated, 1);
    // Clouds that come before the NextCloud is fed back queue behind the batch's own.
    let more = solo.handle(PlannerEvent::Clouds {
        clouds: vec![keyed_as("t1", &clouds[1])],
        received_ns: NOW_NS,
    });
    assert_eq!(views_for(&more), vec![("t2".into(), 1)]);
    assert_eq!(more.last(), Some(&PlannerAction::NextCloud));
    let last = solo.handle(PlannerEvent::NextCloud);
    assert_eq!(views_for(&last), vec![("t1".into(), 2)]);
    assert!(!last.contains(&PlannerAction::NextCloud));
    // A NextCloud left over after the batch is done changes nothing.
    assert!(solo.handle(PlannerEvent::NextCloud).is_empty());
    assert_eq!(solo.stats().clouds_integrated, 3);
    assert_eq!(solo.stats().plans, 3);
}

/// The owner of t1 with its info and the first cloud integrated.
fn owner_with_first_cloud(info: &TrolleyInfo, first: &RoiCloud) -> PlannerNode {
    let (mut owner, _) = roles(pair());
    owner.handle(info_event(info));
    assert_eq!(views_of(&owner.handle(cloud_event(first))).len(), 1);
    owner
}

#[test]
fn a_restarted_edge_keeps_the_map_growing() {
    let (info, clouds) = trolley_clouds(3);
    let mut owner = owner_with_first_cloud(&info, &clouds[0]);
    owner.handle(cloud_event(&clouds[1]));
    let before = owner.planner("t1").unwrap().map().scans_inserted();
    // The edge restarts: a new epoch, its frames from 1 again.
    let mut restarted = clouds[2].clone();
    restarted.source_frame_epoch_ns = EDGE_EPOCH_NS + 60_000_000_000;
    restarted.source_frame_seq = 1;
    let views = views_of(&owner.handle(cloud_event(&restarted)));
    assert_eq!(views.len(), 1);
    assert_eq!(views[0].based_on(), restarted.source_frame());
    let planner = owner.planner("t1").unwrap();
    assert_eq!(planner.map().scans_inserted(), before + 1);
    assert_eq!(planner.last_frame(), Some(restarted.source_frame()));
    // A straggler of the old process is neither integrated nor a reason to stop.
    owner.handle(cloud_event(&clouds[1]));
    assert_eq!(owner.stats().clouds_stale, 1);
    assert_eq!(
        owner.planner("t1").unwrap().map().scans_inserted(),
        before + 1
    );
}

#[test]
fn a_frame_far_ahead_is_refused_and_counted_and_the_map_goes_on() {
    let (info, clouds) = trolley_clouds(2);
    let mut owner = owner_with_first_cloud(&info, &clouds[0]);
    let mut rogue = clouds[1].clone();
    rogue.source_frame_seq = 1_000_000_000_000;
    assert!(owner.handle(cloud_event(&rogue)).is_empty());
    let mut future = clouds[1].clone();
    future.source_frame_epoch_ns = NOW_NS + 3_600_000_000_000;
    assert!(owner.handle(cloud_event(&future)).is_empty());
    assert_eq!(owner.stats().clouds_refused, 2);
    assert_eq!(owner.planner("t1").unwrap().map().scans_inserted(), 1);
    // The next real frame is integrated and planned on.
    assert_eq!(views_of(&owner.handle(cloud_event(&clouds[1]))).len(), 1);
    assert_eq!(owner.planner("t1").unwrap().map().scans_inserted(), 2);
    let actions = owner.handle(status_tick(NOW_NS));
    let PlannerAction::PublishStatus { status, .. } = &actions[0] else {
        panic!("{actions:?}")
    };
    assert_eq!(status.refused_clouds, 2);
}

#[test]
fn clouds_from_a_source_that_is_no_detector_are_refused() {
    let (info, clouds) = trolley_clouds(2);
    let mut owner = owner_with_first_cloud(&info, &clouds[0]);
    // Held while its token may still come, refused once the wait is over.
    assert!(owner
        .handle(cloud_from("rogue", &clouds[1], NOW_NS))
        .is_empty());
    assert_eq!(owner.stats().clouds_refused, 0);
    owner.handle(status_tick(NOW_NS + UNKNOWN_SOURCE_WAIT_NS / 2));
    assert_eq!(owner.stats().clouds_refused, 0);
    owner.handle(status_tick(NOW_NS + UNKNOWN_SOURCE_WAIT_NS + 1));
    assert_eq!(owner.stats().clouds_refused, 1);
    assert_eq!(owner.planner("t1").unwrap().map().scans_inserted(), 1);
    // A flood from unknown sources is bounded: the oldest are refused at once.
    for i in 0..UNKNOWN_SOURCE_CLOUDS + 3 {
        owner.handle(cloud_from(&format!("r{i}"), &clouds[1], NOW_NS + 1));
    }
    assert_eq!(owner.stats().clouds_refused, 4);
    // A detector that left is no source either.
    owner.handle(PlannerEvent::DetectorLeft("d1".into()));
    owner.handle(cloud_event(&clouds[1]));
    owner.handle(status_tick(NOW_NS + 2 * UNKNOWN_SOURCE_WAIT_NS));
    assert_eq!(owner.planner("t1").unwrap().map().scans_inserted(), 1);
    assert_eq!(
        owner.stats().clouds_refused,
        5 + UNKNOWN_SOURCE_CLOUDS as u64
    );
}

/// Scans in `node`'s map of t1.
fn scans(node: &PlannerNode) -> u64 {
    node.planner("t1").unwrap().map().scans_inserted()
}

#[test]
fn clouds_are_taken_only_from_the_detector_serving_the_trolley() {
    let (info, clouds) = trolley_clouds(3);
    let mut owner = owner_with_first_cloud(&info, &clouds[0]);
    // d2 joins and ranks first for t1 (the ranking the detectors split the trolleys by): d1,
    // still live, serves other trolleys now.
    owner.handle(PlannerEvent::DetectorJoined("d2".into()));
    let live = ["d1", "d2"];
    assert_eq!(glasshouse_fleet::first_ranked("t1", live), Some("d2"));
    // d1's cloud waits for the membership to change, then is refused as unassigned.
    assert!(owner
        .handle(cloud_from("d1", &clouds[1], NOW_NS))
        .is_empty());
    owner.handle(status_tick(NOW_NS + UNKNOWN_SOURCE_WAIT_NS + 1));
    assert_eq!(owner.stats().clouds_unassigned, 1);
    assert_eq!(scans(&owner), 1);
    // The same cloud from the serving detector is taken and planned on.
    assert_eq!(
        views_of(&owner.handle(cloud_from("d2", &clouds[1], NOW_NS))).len(),
        1
    );
    assert_eq!(scans(&owner), 2);
    // d2 leaves: d1 serves t1 again, and its cloud that waited is taken.
    assert!(owner
        .handle(cloud_from("d1", &clouds[2], NOW_NS))
        .is_empty());
    let actions = owner.handle(PlannerEvent::DetectorLeft("d2".into()));
    assert_eq!(views_of(&actions).len(), 1);
    assert_eq!(scans(&owner), 3);
    let PlannerAction::PublishStatus { status, .. } = &owner.handle(status_tick(NOW_NS))[0] else {
        panic!("no status")
    };
    assert_eq!((status.unassigned_clouds, status.refused_clouds), (1, 0));
}

#[test]
fn a_cloud_whose_header_names_another_detector_than_its_key_is_refused_at_once() {
    let (info, clouds) = trolley_clouds(2);
    let mut owner = owner_with_first_cloud(&info, &clouds[0]);
    owner.handle(PlannerEvent::DetectorJoined("d3".into()));
    // d1 serves t1 beside d3. d3, on its own key, claims to be d1.
    assert_eq!(
        glasshouse_fleet::first_ranked("t1", ["d1", "d3"]),
        Some("d1")
    );
    let claiming = |sender: &str| PlannerEvent::Cloud {
        sender: sender.into(),
        header: header("t1", 2),
        cloud: clouds[1].clone(),
        received_ns: NOW_NS,
    };
    assert!(owner.handle(claiming("d3")).is_empty());
    // A key that named no detector (the driver passes an empty sender) is refused too.
    assert!(owner.handle(claiming("")).is_empty());
    assert_eq!(owner.stats().clouds_unassigned, 2);
    assert_eq!(scans(&owner), 1);
    // Nothing waits: no refusal comes later, and the serving detector's cloud is taken.
    owner.handle(status_tick(NOW_NS + 2 * UNKNOWN_SOURCE_WAIT_NS));
    assert_eq!(owner.stats().clouds_unassigned, 2);
    assert_eq!(views_of(&owner.handle(claiming("d1"))).len(), 1);
    assert_eq!(scans(&owner), 2);
}

#[test]
fn a_cloud_that_arrives_before_its_detector_token_is_taken_with_the_token() {
    let (info, clouds) = trolley_clouds(1);
    let (mut owner, _) = roles(pair());
    owner.handle(info_event(&info));
    assert!(owner
        .handle(cloud_from("d2", &clouds[0], NOW_NS))
        .is_empty());
    // d2 ranks first for t1 among d1 and d2: it serves t1 once its token is known.
    let actions = owner.handle(PlannerEvent::DetectorJoined("d2".into()));
    assert_eq!(views_of(&actions).len(), 1);
    assert_eq!(owner.stats().clouds_refused, 0);
    assert_eq!(owner.planner("t1").unwrap().map().scans_inserted(), 1);
    // Nothing is left to refuse later.
    owner.handle(status_tick(NOW_NS + 2 * UNKNOWN_SOURCE_WAIT_NS));
    assert_eq!(owner.stats().clouds_refused, 0);
}

#[test]
fn the_fleet_map_takes_fruits_from_the_trolley_owner_only() {
    let (owner, replica) = roles(pair());
    let (owner_id, replica_id) = (owner.pid.clone(), replica.pid.clone());
    let mut fleet = node(&owner_id);
    fleet.handle(PlannerEvent::PlannerJoined(replica_id.clone()));
    fleet.handle(PlannerEvent::TrolleyJoined("t1".into()));
    let fruits = glasshouse_proto::samples::fruit_estimates();
    for source in [replica_id.as_str(), "rogue"] {
        fleet.handle(PlannerEvent::Fruits {
            header: Header {
                source_id: source.into(),
                ..header("t1", 1)
            },
            fruits: fruits.clone(),
        });
    }
    assert!(fleet.latest_fruits.is_empty());
    fleet.handle(PlannerEvent::Fruits {
        header: Header {
            source_id: owner_id,
            ..header("t1", 1)
        },
        fruits,
    });
    assert_eq!(fleet.latest_fruits.len(), 1);
}

#[test]
fn buffered_clouds_the_snapshot_holds_are_not_inserted_again() {
    let (info, clouds) = trolley_clouds(6);
    let mut p1 = alone_with(&info, &clouds[..5]);
    // p2 took t1 on after frame 1 and buffered frames 2..=6; the snapshot it gets holds 1..=5.
    let mut p2 = p2_told_of(&info);
    for c in &clouds[1..] {
        assert!(p2.handle(cloud_event(c)).is_empty());
    }
    load_t1_from(&p1, &mut p2);
    p1.handle(cloud_event(&clouds[5]));
    let (m1, m2) = (
        p1.planner("t1").unwrap().map(),
        p2.planner("t1").unwrap().map(),
    );
    assert_eq!(m2.scans_inserted(), 6);
    assert_eq!(m1.scans_inserted(), m2.scans_inserted());
    assert!(m1.len() == m2.len() && m1.iter().all(|(k, v)| m2.get(k) == Some(v)));
}

#[test]
fn clouds_a_loaded_snapshot_holds_replayed_after_the_load_are_not_inserted_again() {
    let (info, clouds) = trolley_clouds(7);
    let mut p1 = alone_with(&info, &clouds[..6]);
    let mut p2 = p2_told_of(&info);
    load_t1_from(&p1, &mut p2);
    // A detector's cloud cache answers the gap p2 saw while it was cut off: frames 2..=6 again,
    // in order, after the snapshot that holds them (more than the resync run of a live stream).
    for c in &clouds[1..6] {
        p2.handle(cloud_event(c));
    }
    assert_eq!(p2.planner("t1").unwrap().map().scans_inserted(), 6);
    p1.handle(cloud_event(&clouds[6]));
    p2.handle(cloud_event(&clouds[6]));
    assert!(same_map(&p1, &p2, "t1"));
}

/// Whether two planners hold the same map of `tid`: the same voxels, values and scan count.
fn same_map(a: &PlannerNode, b: &PlannerNode, tid: &str) -> bool {
    let (a, b) = (a.planner(tid).unwrap().map(), b.planner(tid).unwrap().map());
    a.len() == b.len()
        && a.scans_inserted() == b.scans_inserted()
        && a.iter().all(|(key, voxel)| b.get(key) == Some(voxel))
}

/// Answers the replica's snapshot requests in `actions` from `owner`, with the base each asks
/// on (a delta where the owner can); returns how many.
fn answer_refreshes(
    owner: &mut PlannerNode,
    replica: &mut PlannerNode,
    actions: Vec<PlannerAction>,
) -> usize {
    let mut asked = 0;
    for action in actions {
        let PlannerAction::AskSnapshot { tid, sources, base } = action else {
            continue;
        };
        assert_eq!(sources, vec![owner.pid.clone()], "a standby asks its owner");
        let reply = owner.handle(PlannerEvent::SnapshotAsked {
            query_id: 1,
            tid: tid.clone(),
            base,
        });
        let snapshot = reply.into_iter().find_map(|a| match a {
            PlannerAction::ReplySnapshot { answer, .. } => answer.ok().map(|(_, s)| s),
            _ => None,
        });
        assert!(snapshot.is_some(), "the owner answers");
        let loaded = replica.handle(PlannerEvent::SnapshotLoaded { tid, snapshot });
        decode_ahead_as_the_driver_does(replica, loaded);
        asked += 1;
    }
    asked
}

/// Performs the node's [`PlannerAction::DecodeAhead`]s among `actions` and feeds the copies back.
fn decode_ahead_as_the_driver_does(node: &mut PlannerNode, actions: Vec<PlannerAction>) {
    for action in actions {
        if let PlannerAction::DecodeAhead { tid, snapshot } = action {
            let decoded = super::decode_ahead(&node.planning, tid, snapshot);
            assert!(node.handle(decoded).is_empty());
        }
    }
}

#[test]
fn a_standby_replica_keeps_clouds_and_refreshes_from_the_owner() {
    let (info, clouds) = trolley_clouds(7);
    let (mut owner, mut replica) = roles(pair_with_refresh(3));
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
    }
    let mut refreshes = Vec::new();
    for cloud in &clouds {
        owner.handle(cloud_event(cloud));
        let actions = replica.handle(cloud_event(cloud));
        assert!(views_of(&actions).is_empty(), "a replica never plans");
        refreshes.push(answer_refreshes(&mut owner, &mut replica, actions));
    }
    // A snapshot after the 3rd and the 6th cloud; the replica integrated nothing itself, keeps
    // the snapshot encoded and holds no decoded map.
    assert_eq!(refreshes, vec![0, 0, 1, 0, 0, 1, 0]);
    assert_eq!(replica.stats().clouds_integrated, 0);
    assert_eq!(replica.pending_clouds("t1"), 1);
    assert!(replica.planner("t1").unwrap().map().is_empty());
    // Caught up (here by a snapshot query): the snapshot of frame 6 plus frame 7.
    replica.handle(PlannerEvent::SnapshotAsked {
        query_id: 2,
        tid: "t1".into(),
        base: None,
    });
    assert_eq!(replica.stats().clouds_integrated, 1);
    assert!(same_map(&replica, &owner, "t1"));
    let copy = replica.planner("t1").unwrap();
    assert_eq!(copy.last_frame(), Some(FrameId::new(EDGE_EPOCH_NS, 7)));
    assert!(copy.filters_reach(), "the refresh keeps the trolley's arm");
}

#[test]
fn a_damaged_snapshot_is_not_kept_and_the_clouds_are_integrated() {
    let (info, clouds) = trolley_clouds(2);
    let (mut owner, mut replica) = roles(pair_with_refresh(2));
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
        for cloud in &clouds {
            n.handle(cloud_event(cloud));
        }
    }
    let Ok((_, mut damaged)) = owner.snapshot_of("t1") else {
        panic!("the owner holds t1")
    };
    let middle = damaged.map.len() / 2;
    damaged.map[middle] ^= 0x10;
    replica.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(damaged),
    });
    assert_eq!(replica.pending_clouds("t1"), 0);
    assert_eq!(replica.stats().clouds_integrated, 2);
    assert!(same_map(&replica, &owner, "t1"));
}

#[test]
fn a_standby_replica_takes_over_with_the_owners_map_and_plans_at_once() {
    let (info, clouds) = trolley_clouds(5);
    let (mut owner, mut replica) = roles(pair_with_refresh(3));
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
    }
    for cloud in &clouds {
        owner.handle(cloud_event(cloud));
        let actions = replica.handle(cloud_event(cloud));
        answer_refreshes(&mut owner, &mut replica, actions);
    }
    // Frames 4 and 5 are pending: the last one planned on at the takeover, both integrated
    // after the views.
    let actions = replica.handle(PlannerEvent::PlannerLeft(owner.pid.clone()));
    assert_eq!(replica.role("t1"), Some(Role::Owner));
    let views = views_of(&actions);
    assert_eq!(views.len(), 1, "{actions:?}");
    assert_eq!(views[0].based_on_seq, 5);
    assert_eq!(replica.stats().clouds_integrated, 0);
    settle(&mut replica, actions);
    assert_eq!(replica.stats().clouds_integrated, 2);
    assert!(same_map(&replica, &owner, "t1"));
    let ids = |p: &PlannerNode| {
        let mut p = p.planner("t1").unwrap().clone();
        p.fruits().iter().map(|f| f.id).collect::<Vec<_>>()
    };
    assert_eq!(ids(&replica), ids(&owner), "fruit ids carry over");
}

#[test]
fn a_standby_replica_asked_for_a_snapshot_answers_with_every_cloud() {
    let (info, clouds) = trolley_clouds(2);
    let (mut owner, mut replica) = roles(pair_with_refresh(8));
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
        for cloud in &clouds {
            n.handle(cloud_event(cloud));
        }
    }
    assert_eq!(replica.stats().clouds_integrated, 0);
    let reply = replica.handle(PlannerEvent::SnapshotAsked {
        query_id: 4,
        tid: "t1".into(),
        base: None,
    });
    let [PlannerAction::ReplySnapshot {
        answer: Ok((_, snapshot)),
        ..
    }] = &reply[..]
    else {
        panic!("{reply:?}")
    };
    assert_eq!(snapshot.based_on_seq, 2);
    assert!(same_map(&replica, &owner, "t1"));
}

#[test]
fn a_refresh_without_answer_integrates_the_pending_clouds() {
    let (info, clouds) = trolley_clouds(2);
    let (mut owner, mut replica) = roles(pair_with_refresh(2));
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
    }
    for cloud in &clouds {
        owner.handle(cloud_event(cloud));
        replica.handle(cloud_event(cloud));
    }
    replica.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: None,
    });
    assert_eq!(replica.stats().clouds_integrated, 2);
    assert!(same_map(&replica, &owner, "t1"));
}

#[test]
fn a_refresh_answered_after_the_takeover_is_ignored() {
    let (info, clouds) = trolley_clouds(3);
    let (mut owner, mut replica) = roles(pair_with_refresh(2));
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
    }
    for cloud in &clouds[..2] {
        owner.handle(cloud_event(cloud));
        assert!(views_of(&replica.handle(cloud_event(cloud))).is_empty());
    }
    // The owner answered with frames 1..=2, then the replica took over and took frame 3.
    let Ok((_, late)) = owner.snapshot_of("t1") else {
        panic!("the owner holds t1")
    };
    owner.handle(cloud_event(&clouds[2]));
    replica.handle(PlannerEvent::PlannerLeft(owner.pid.clone()));
    replica.handle(cloud_event(&clouds[2]));
    replica.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(late),
    });
    let copy = replica.planner("t1").unwrap();
    assert_eq!(copy.last_frame(), Some(FrameId::new(EDGE_EPOCH_NS, 3)));
    assert!(same_map(&replica, &owner, "t1"));
}

fn cloud_for(tid: &str, cloud: &RoiCloud) -> PlannerEvent {
    PlannerEvent::Cloud {
        sender: "d1".into(),
        header: header(tid, cloud.source_frame_seq),
        cloud: cloud.clone(),
        received_ns: NOW_NS,
    }
}

/// Planners p1 and p2 (standby replicas refreshed every `refresh` clouds) with eight loaded
/// trolleys, and three of the trolleys p2 owns (p1 their replica).
fn two_planners_eight_trolleys(refresh: usize) -> (PlannerNode, PlannerNode, Vec<String>) {
    let (mut a, mut b) = (
        node_with_refresh("p1", refresh),
        node_with_refresh("p2", refresh),
    );
    let tids: Vec<String> = (1..=8).map(|i| format!("t{i}")).collect();
    for (n, other) in [(&mut a, "p2"), (&mut b, "p1")] {
        n.handle(PlannerEvent::PlannerJoined(other.into()));
        for tid in &tids {
            n.handle(PlannerEvent::TrolleyJoined(tid.clone()));
            n.handle(PlannerEvent::SnapshotLoaded {
                tid: tid.clone(),
                snapshot: None,
            });
        }
    }
    let owned: Vec<String> = tids
        .iter()
        .filter(|t| b.role(t) == Some(Role::Owner))
        .take(3)
        .cloned()
        .collect();
    assert_eq!(owned.len(), 3, "rendezvous hashing gives p2 three of eight");
    (a, b, owned)
}

#[test]
fn trolleys_taken_over_together_catch_up_one_event_each() {
    let (info, clouds) = trolley_clouds(2);
    let (mut a, mut b, owned) = two_planners_eight_trolleys(8);
    // Three trolleys p2 owns and p1 stands by for, each with two clouds.
    for tid in &owned {
        for n in [&mut a, &mut b] {
            n.handle(PlannerEvent::Info {
                header: header(tid, 0),
                info: info.clone(),
            });
            for cloud in &clouds {
                n.handle(cloud_for(tid, cloud));
            }
        }
    }
    let actions = a.handle(PlannerEvent::PlannerLeft("p2".into()));
    let is_finish = |x: &PlannerAction| matches!(x, PlannerAction::Finish { .. });
    let is_catch_up = |x: &PlannerAction| matches!(x, PlannerAction::CatchUp { .. });
    let finish_at = actions
        .iter()
        .position(is_finish)
        .expect("the first one's rest");
    let last_catch_up = actions.iter().rposition(is_catch_up).expect("two more");
    assert!(
        last_catch_up < finish_at,
        "the first trolley's rest waits for the others' catch-ups: {actions:?}"
    );
    let actions = settle(&mut a, actions);
    let deferred: Vec<String> = actions
        .iter()
        .filter_map(|x| match x {
            PlannerAction::CatchUp { tid } => Some(tid.clone()),
            _ => None,
        })
        .collect();
    // One trolley is planned on at once, the other two wait for their own event.
    assert_eq!(views_of(&actions).len(), 1);
    assert_eq!(deferred.len(), 2);
    let caught = feed(
        &mut a,
        PlannerEvent::CatchUp {
            tid: deferred[0].clone(),
        },
    );
    assert_eq!(views_of(&caught).len(), 1);
    // A cloud of the last one catches it up first; its CatchUp then finds nothing to do.
    let (_, later) = trolley_clouds(3);
    let planned = feed(&mut a, cloud_for(&deferred[1], &later[2]));
    assert_eq!(views_of(&planned)[0].based_on_seq, 3);
    let copy = a.planner(&deferred[1]).unwrap();
    assert_eq!(copy.map().scans_inserted(), 3);
    assert!(a
        .handle(PlannerEvent::CatchUp {
            tid: deferred[1].clone(),
        })
        .is_empty());
    for tid in &owned {
        assert!(same_map(&a, &b, tid) || tid == &deferred[1]);
    }
}

/// Feeds `owned`'s info and clouds to the owner `b` and the standby replica `a`, answering the
/// replica's snapshot queries from the owner as the driver does.
fn stand_by_on_owners_snapshots(
    a: &mut PlannerNode,
    b: &mut PlannerNode,
    owned: &[String],
    info: &TrolleyInfo,
    clouds: &[RoiCloud],
) {
    for tid in owned {
        for n in [&mut *a, &mut *b] {
            n.handle(PlannerEvent::Info {
                header: header(tid, 0),
                info: info.clone(),
            });
        }
        for cloud in clouds {
            b.handle(cloud_for(tid, cloud));
            let actions = a.handle(cloud_for(tid, cloud));
            answer_refreshes(b, a, actions);
        }
    }
}

#[test]
fn trolleys_taken_over_together_are_decoded_before_the_first_is_planned_on() {
    let (info, clouds) = trolley_clouds(3);
    let (mut a, mut b, owned) = two_planners_eight_trolleys(2);
    // p1 stands by with p2's snapshot after two clouds of each, the third pending.
    stand_by_on_owners_snapshots(&mut a, &mut b, &owned, &info, &clouds);
    for tid in &owned {
        assert_eq!(
            a.planner(tid).unwrap().map().scans_inserted(),
            0,
            "kept encoded"
        );
        assert_eq!(a.pending_clouds(tid), 1);
    }
    let actions = a.handle(PlannerEvent::PlannerLeft("p2".into()));
    let actions = settle(&mut a, actions);
    let deferred: Vec<String> = actions
        .iter()
        .filter_map(|x| match x {
            PlannerAction::CatchUp { tid } => Some(tid.clone()),
            _ => None,
        })
        .collect();
    assert_eq!(deferred.len(), 2, "{actions:?}");
    for tid in &deferred {
        // Decoded with the first one, before its own catch-up: the held snapshot's two scans.
        assert_eq!(a.planner(tid).unwrap().map().scans_inserted(), 2);
        let caught = feed(&mut a, PlannerEvent::CatchUp { tid: tid.clone() });
        assert_eq!(views_of(&caught).len(), 1);
        assert_eq!(views_of(&caught)[0].based_on_seq, 3);
    }
    for tid in &owned {
        assert!(same_map(&a, &b, tid), "{tid}");
    }
    assert_eq!(a.stats().clouds_integrated, 3, "only the pending clouds");
}

#[test]
fn a_standby_copy_decoded_ahead_is_adopted_at_the_takeover_and_plans_on_the_owners_map() {
    let (info, clouds) = trolley_clouds(3);
    let (mut a, mut b, owned) = two_planners_eight_trolleys(2);
    a.standby_decoded_ahead = true;
    stand_by_on_owners_snapshots(&mut a, &mut b, &owned, &info, &clouds);
    for tid in &owned {
        assert_eq!(a.pending_clouds(tid), 1);
    }
    assert_eq!(
        a.stats().standby_decodes_ahead,
        3,
        "one decoded copy per snapshot held"
    );
    // A copy decoded from another snapshot than the one held is not kept.
    let Ok((_, other)) = b.snapshot_of(&owned[0]) else {
        panic!("p2 owns {}", owned[0])
    };
    let stray = super::decode_ahead(&a.planning, owned[0].clone(), Arc::from(other));
    a.handle(stray);
    assert_eq!(a.stats().standby_decodes_ahead, 3);
    let actions = a.handle(PlannerEvent::PlannerLeft("p2".into()));
    let mut actions = settle(&mut a, actions);
    for tid in actions.clone().iter().filter_map(|x| match x {
        PlannerAction::CatchUp { tid } => Some(tid.clone()),
        _ => None,
    }) {
        actions.extend(feed(&mut a, PlannerEvent::CatchUp { tid }));
    }
    assert_eq!(
        a.stats().decoded_ahead_adopted,
        3,
        "no snapshot decoded again"
    );
    let status = status_of(&a.handle(status_tick(NOW_NS)));
    assert_eq!(
        (status.standby_decodes_ahead, status.decoded_ahead_adopted),
        (3, 3),
        "the status reports both"
    );
    let views = views_of(&actions);
    assert_eq!(views.len(), 3, "{actions:?}");
    assert!(views.iter().all(|v| v.based_on_seq == 3));
    for tid in &owned {
        assert!(same_map(&a, &b, tid), "{tid}");
    }
    assert_eq!(a.stats().clouds_integrated, 3, "only the pending clouds");
}

#[test]
fn a_new_standby_replica_keeps_the_snapshot_encoded() {
    let (info, clouds) = trolley_clouds(3);
    // p2 alone owns t1 with two clouds; p1 joins and ranks second for t1: the new replica.
    let mut p2 = node_with_refresh("p2", 8);
    p2.handle(PlannerEvent::TrolleyJoined("t1".into()));
    p2.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: None,
    });
    p2.handle(info_event(&info));
    for cloud in &clouds[..2] {
        p2.handle(cloud_event(cloud));
    }
    let mut p1 = node_with_refresh("p1", 8);
    p1.handle(PlannerEvent::PlannerJoined("p2".into()));
    p1.handle(PlannerEvent::TrolleyJoined("t1".into()));
    p2.handle(PlannerEvent::PlannerJoined("p1".into()));
    assert_eq!(p1.role("t1"), Some(Role::Replica));
    p1.handle(info_event(&info));
    let Ok((_, snapshot)) = p2.snapshot_of("t1") else {
        panic!("p2 holds t1")
    };
    for n in [&mut p1, &mut p2] {
        n.handle(cloud_event(&clouds[2]));
    }
    p1.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(snapshot),
    });
    assert!(!p1.is_loading("t1"));
    assert_eq!(p1.stats().clouds_integrated, 0);
    assert_eq!(
        p1.pending_clouds("t1"),
        1,
        "frame 3 came after the snapshot"
    );
    assert!(p1.planner("t1").unwrap().map().is_empty());
    // The views for frame 3 go out planned on the snapshot; frame 3 is integrated after them.
    let actions = p1.handle(PlannerEvent::PlannerLeft("p2".into()));
    assert_eq!(views_of(&actions)[0].based_on_seq, 3);
    assert_eq!(p1.planner("t1").unwrap().map().scans_inserted(), 2);
    assert_eq!(p1.pending_clouds("t1"), 1, "frame 3 deferred, not lost");
    let finished = settle(&mut p1, actions);
    assert_eq!(outputs_for(&finished, "t1"), (1, 1, 1), "{finished:?}");
    assert_eq!(p1.pending_clouds("t1"), 0);
    assert!(same_map(&p1, &p2, "t1"));
}

/// The registrations on the map updates published for t1, in order.
fn registrations_of(actions: &[PlannerAction]) -> Vec<Option<FrameRegistration>> {
    actions
        .iter()
        .filter_map(|a| match a {
            PlannerAction::Publish {
                output: TrolleyOutput::Map(m),
                ..
            } => Some(m.registration.clone()),
            _ => None,
        })
        .collect()
}

fn status_of(actions: &[PlannerAction]) -> PlannerStatus {
    match actions.first() {
        Some(PlannerAction::PublishStatus { status, .. }) => status.clone(),
        other => panic!("a status first, got {other:?}"),
    }
}

/// [`pair`] of planners that register every cloud to the map before inserting it (the replica
/// hot: it integrates, and registers, every cloud).
fn registering_pair() -> (PlannerNode, PlannerNode) {
    let mut planning = PlanningSettings {
        scoring_threads: 1,
        ..PlanningSettings::default()
    };
    planning.registration.enabled = true;
    // The test's small clouds make a small map.
    planning.registration.min_map_occupied_voxels = 200;
    planning.registration.min_scan_points = 100;
    planning.registration.min_inliers = 80;
    let mut nodes = ["p1", "p2"].map(|pid| {
        let mut n = PlannerNode::new(pid, planning.clone(), NOW_NS).with_replica_refresh(0);
        n.handle(PlannerEvent::DetectorJoined("d1".into()));
        n
    });
    for (n, other) in nodes.iter_mut().zip(["p2", "p1"]) {
        n.handle(PlannerEvent::PlannerJoined(other.into()));
        n.handle(PlannerEvent::TrolleyJoined("t1".into()));
        n.handle(PlannerEvent::SnapshotLoaded {
            tid: "t1".into(),
            snapshot: None,
        });
    }
    let [a, b] = nodes;
    roles((a, b))
}

#[test]
fn each_inserted_cloud_reports_its_registration_on_its_map_update() {
    let (info, clouds) = trolley_clouds(4);
    let (mut owner, mut replica) = registering_pair();
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
    }
    let mut records = Vec::new();
    for cloud in &clouds {
        let actions = owner.handle(cloud_event(cloud));
        let registrations = registrations_of(&actions);
        assert_eq!(registrations.len(), 1, "one map update per cloud");
        let r = registrations[0].clone().expect("the cloud's registration");
        assert_eq!(r.frame, cloud.source_frame());
        assert_eq!(
            r.verdict,
            match owner.planner("t1").unwrap().last_alignment() {
                Some(Alignment::Aligned(a)) if a.applied() => RegistrationVerdict::Applied,
                Some(Alignment::Aligned(_)) => RegistrationVerdict::KeptAsSent,
                Some(Alignment::Rejected(_)) => RegistrationVerdict::Rejected,
                _ => RegistrationVerdict::Skipped,
            }
        );
        replica.handle(cloud_event(cloud));
        records.push(r);
    }
    // The first cloud meets an empty map; the later ones are checked against it (in this
    // perfect world, their estimates are too small to apply).
    assert_eq!(
        (records[0].verdict, records[0].reason),
        (
            RegistrationVerdict::Skipped,
            RegistrationReason::MapTooSmall
        )
    );
    let estimated = records.iter().filter(|r| r.world_correction.is_some());
    assert!(
        estimated.clone().count() >= 1 && estimated.clone().all(|r| r.iterations.is_some()),
        "{records:?}"
    );
    let counts = *owner.planner("t1").unwrap().alignment_counts();
    // A re-announced frame is not registered again: its update carries no registration.
    let again = owner.handle(cloud_event(&clouds[3]));
    assert_eq!(registrations_of(&again), vec![None]);
    let status = status_of(&owner.handle(status_tick(NOW_NS)));
    assert_eq!(
        status.registrations.total(),
        4,
        "{:?}",
        status.registrations
    );
    // The replica registers the same clouds, but reports only the trolleys it owns.
    assert_eq!(*replica.planner("t1").unwrap().alignment_counts(), counts);
    let replica_status = status_of(&replica.handle(status_tick(NOW_NS)));
    assert_eq!(replica_status.registrations, RegistrationTotals::default());
}

#[test]
fn a_rejected_cloud_is_reported_on_a_map_update_without_voxels() {
    let (info, clouds) = trolley_clouds(4);
    let (mut owner, _) = registering_pair();
    owner.handle(info_event(&info));
    for cloud in &clouds[..3] {
        owner.handle(cloud_event(cloud));
    }
    let voxels = owner.planner("t1").unwrap().map().len();
    // The last frame as a trolley 20 cm off along x would send it.
    let shift = nalgebra::Isometry3::translation(0.2, 0.0, 0.0);
    let wild = RoiCloud {
        points_in_world: glasshouse_register::corrected_points(&shift, &clouds[3].points_in_world),
        sensor_origin_in_world: shift * clouds[3].sensor_origin_in_world,
        ..clouds[3].clone()
    };
    let actions = owner.handle(cloud_event(&wild));
    let maps: Vec<&MapUpdate> = actions
        .iter()
        .filter_map(|a| match a {
            PlannerAction::Publish {
                output: TrolleyOutput::Map(m),
                ..
            } => Some(&**m),
            _ => None,
        })
        .collect();
    assert_eq!(maps.len(), 1);
    assert!(
        maps[0].voxels.is_empty(),
        "a rejected cloud changes no voxel"
    );
    let r = maps[0].registration.as_ref().expect("the refusal");
    assert_eq!(r.verdict, RegistrationVerdict::Rejected, "{r:?}");
    assert_eq!(r.frame, wild.source_frame());
    assert!(!r.inserted());
    assert_eq!(owner.planner("t1").unwrap().map().len(), voxels);
    // Still planned on: the edge waits for views on this frame.
    assert_eq!(views_of(&actions).len(), 1);
    let status = status_of(&owner.handle(status_tick(NOW_NS)));
    assert_eq!(status.registrations.rejected, 1);
    assert_eq!(status.registrations.total(), 4);
}

#[test]
fn without_registration_every_cloud_reports_it_skipped() {
    let (info, clouds) = trolley_clouds(2);
    let mut p1 = alone_with(&info, &[]);
    for cloud in &clouds {
        let registrations = registrations_of(&p1.handle(cloud_event(cloud)));
        let r = registrations[0].clone().expect("registration");
        assert_eq!(
            (r.verdict, r.reason, r.world_correction),
            (
                RegistrationVerdict::Skipped,
                RegistrationReason::Disabled,
                None
            )
        );
    }
    let status = status_of(&p1.handle(status_tick(NOW_NS)));
    assert_eq!(status.registrations.skipped, 2);
}

// Fencing: ownership epochs.

/// The ownership epoch of every output published in `actions`.
fn epochs_of(actions: &[PlannerAction]) -> Vec<u64> {
    actions
        .iter()
        .filter_map(|a| match a {
            PlannerAction::Publish { output, .. } => Some(match output {
                TrolleyOutput::Views(v) => v.owner_epoch,
                TrolleyOutput::Fruits(f) => f.owner_epoch,
                TrolleyOutput::Map(m) => m.owner_epoch,
            }),
            _ => None,
        })
        .collect()
}

/// Feeds the fruits published in `actions` to `to`, as the bus would.
fn hear_fruits(to: &mut PlannerNode, actions: &[PlannerAction]) -> Vec<PlannerAction> {
    let mut out = Vec::new();
    for action in actions {
        if let PlannerAction::Publish {
            header,
            output: TrolleyOutput::Fruits(fruits),
            ..
        } = action
        {
            out.extend(to.handle(PlannerEvent::Fruits {
                header: header.clone(),
                fruits: fruits.clone(),
            }));
        }
    }
    out
}

/// Trolley t1's info as its edge sends it, naming the newest ownership epoch it took views
/// under and whose views they were.
fn info_under(info: &TrolleyInfo, owner_epoch: u64, owner_id: &str) -> PlannerEvent {
    PlannerEvent::Info {
        header: header("t1", 0),
        info: TrolleyInfo {
            owner_epoch,
            owner_id: owner_id.into(),
            ..info.clone()
        },
    }
}

/// `from`'s answer to a snapshot query for t1.
fn snapshot_from(from: &mut PlannerNode) -> Box<MapSnapshot> {
    let reply = from.handle(PlannerEvent::SnapshotAsked {
        query_id: 1,
        tid: "t1".into(),
        base: None,
    });
    match reply.into_iter().last() {
        Some(PlannerAction::ReplySnapshot {
            answer: Ok((_, snapshot)),
            ..
        }) => snapshot,
        other => panic!("no snapshot: {other:?}"),
    }
}

#[test]
fn a_paused_owner_that_wakes_up_steps_down_catches_up_and_begins_a_newer_term() {
    let (info, clouds) = trolley_clouds(4);
    let (mut a, mut b) = informed_owner_and_replica(&info);
    let a_id = a.pid.clone();
    // Frame 1: the owner plans under its term, and every output carries it; the replica hears
    // its fruits.
    let published = a.handle(cloud_event(&clouds[0]));
    let term_a = a.term("t1").expect("the owner's term began");
    assert_eq!(epochs_of(&published), vec![term_a; 3]);
    b.handle(cloud_event(&clouds[0]));
    hear_fruits(&mut b, &published);
    assert_eq!((b.term("t1"), b.newest_epoch("t1")), (None, term_a));
    // The owner is paused: its token goes. The replica takes over under a newer term and plans
    // frame 1 at once; frames 2 and 3 reach it alone.
    let taken = b.handle(PlannerEvent::PlannerLeft(a_id.clone()));
    let taken = settle(&mut b, taken);
    let term_b = b.term("t1").expect("the new owner's term began");
    assert!(term_b > term_a, "{term_b} after {term_a}");
    assert_eq!(views_of(&taken).len(), 1);
    assert_eq!(epochs_of(&taken), vec![term_b; 3]);
    for cloud in &clouds[1..3] {
        assert_eq!(epochs_of(&b.handle(cloud_event(cloud))), vec![term_b; 3]);
    }
    // The paused owner wakes up. Its link was closed while it slept, so it saw b's token go
    // (and come back later); with it alone, it still owned t1.
    assert!(views_of(&a.handle(PlannerEvent::PlannerLeft(b.pid.clone()))).is_empty());
    assert_eq!(a.role("t1"), Some(Role::Owner));
    // Its token is back: it ranks first again and the other planner stands by.
    b.handle(PlannerEvent::PlannerJoined(a_id));
    assert_eq!((b.role("t1"), b.term("t1")), (Some(Role::Replica), None));
    // It never saw itself lose the trolley, but the edge's info names b's term: it steps down
    // and asks b, whose token it has not seen again yet.
    let stepped = a.handle(info_under(&info, term_b, &b.pid));
    assert_eq!(
        asks(&stepped),
        vec![("t1".to_string(), vec![b.pid.clone()])]
    );
    assert!(a.is_loading("t1"));
    assert_eq!((a.term("t1"), a.stats().stepped_down), (None, 1));
    // Frame 4 comes meanwhile: kept, nothing planned or published on the stale map.
    assert!(a.handle(cloud_event(&clouds[3])).is_empty());
    b.handle(cloud_event(&clouds[3]));
    // b's copy (frames 1..=4, under b's term) loads; a begins a newer term and plans frame 4.
    let snapshot = snapshot_from(&mut b);
    assert_eq!(snapshot.owner_epoch, term_b);
    let resumed = a.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(snapshot),
    });
    let term_a2 = a.term("t1").expect("a new term began");
    assert!(term_a2 > term_b, "{term_a2} after {term_b}");
    let views = views_of(&resumed);
    assert_eq!((views.len(), views[0].based_on_seq), (1, 4));
    assert!(epochs_of(&resumed).iter().all(|&e| e == term_a2));
    assert!(same_map(&a, &b, "t1"), "a plans on b's map, not on its own");
    let status = status_of(&a.handle(status_tick(NOW_NS)));
    assert_eq!((status.stepped_down, status.stale_epoch), (1, 0));
}

#[test]
fn an_owner_alone_that_steps_down_keeps_its_copy_and_begins_a_newer_term() {
    let (info, clouds) = trolley_clouds(2);
    let mut p1 = alone_with(&info, &clouds[..1]);
    let term = p1.term("t1").expect("a term");
    // Someone else owned t1 meanwhile and is gone: it is asked, and does not answer.
    let stepped = p1.handle(info_under(&info, term + 10, "p9"));
    assert_eq!(
        asks(&stepped),
        vec![("t1".to_string(), vec!["p9".to_string()])]
    );
    let resumed = p1.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: None,
    });
    assert!(p1.term("t1").expect("a new term") > term + 10);
    // It plans on the last cloud it had, on its own copy.
    assert_eq!(views_of(&resumed)[0].based_on_seq, 1);
    assert_eq!(p1.planner("t1").unwrap().map().scans_inserted(), 1);
}

#[test]
fn every_ownership_change_begins_a_later_term() {
    let (info, clouds) = trolley_clouds(3);
    let (mut a, mut b) = informed_owner_and_replica(&info);
    let a_id = a.pid.clone();
    let mut terms = vec![a.term("t1").unwrap()];
    // The owner leaves and comes back over and over; each time the other one takes over. The
    // planners hear each other's fruits, and their clocks move on by a second.
    for (round, cloud) in clouds.iter().enumerate() {
        let now_ns = NOW_NS + (round as u64 + 1) * 1_000_000_000;
        for n in [&mut a, &mut b] {
            n.handle(status_tick(now_ns));
        }
        let published = a.handle(cloud_event(cloud));
        hear_fruits(&mut b, &published);
        b.handle(cloud_event(cloud));
        let published = b.handle(PlannerEvent::PlannerLeft(a_id.clone()));
        let published = settle(&mut b, published);
        terms.push(b.term("t1").unwrap());
        hear_fruits(&mut a, &published);
        b.handle(PlannerEvent::PlannerJoined(a_id.clone()));
        // a kept believing it owns t1: b's fruits replace it, and it catches up from b.
        assert_eq!(a.term("t1"), None, "round {round}");
        let snapshot = snapshot_from(&mut b);
        a.handle(PlannerEvent::SnapshotLoaded {
            tid: "t1".into(),
            snapshot: Some(snapshot),
        });
        terms.push(a.term("t1").unwrap());
    }
    assert!(terms.windows(2).all(|w| w[0] < w[1]), "{terms:?}");
    assert_eq!(a.stats().stepped_down, 3);
}

#[test]
fn a_standby_replica_refuses_the_snapshot_of_a_replaced_owner() {
    let (info, clouds) = trolley_clouds(2);
    let (mut owner, mut replica) = roles(pair_with_refresh(2));
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&info));
    }
    // The replica has heard of a newer term than the owner's (another planner owned t1 while
    // the owner was paused), before the owner did.
    let term = owner.term("t1").unwrap();
    replica.handle(info_under(&info, term + 5, "p9"));
    assert_eq!(
        replica.stats().stepped_down,
        0,
        "a replica has no term to give up"
    );
    // Two clouds: the replica asks its owner for a snapshot, which answers under its old term.
    let mut asked = 0;
    for cloud in &clouds {
        owner.handle(cloud_event(cloud));
        let actions = replica.handle(cloud_event(cloud));
        asked += answer_refreshes(&mut owner, &mut replica, actions);
    }
    assert_eq!(asked, 1);
    // Refused and counted: the replica integrated the clouds it kept instead.
    assert_eq!(replica.stats().stale_epoch, 1);
    assert_eq!(replica.pending_clouds("t1"), 0);
    assert_eq!(replica.stats().clouds_integrated, 2);
    assert!(same_map(&replica, &owner, "t1"));
    let status = status_of(&replica.handle(status_tick(NOW_NS)));
    assert_eq!(status.stale_epoch, 1);
}

#[test]
fn fruits_under_an_older_epoch_are_dropped_and_counted() {
    let (owner, replica) = roles(pair());
    let (owner_id, replica_id) = (owner.pid.clone(), replica.pid.clone());
    let mut fleet = node(&replica_id);
    fleet.handle(PlannerEvent::PlannerJoined(owner_id.clone()));
    fleet.handle(PlannerEvent::TrolleyJoined("t1".into()));
    let from_owner = |owner_epoch| PlannerEvent::Fruits {
        header: Header {
            source_id: owner_id.clone(),
            ..header("t1", 1)
        },
        fruits: FruitEstimates {
            owner_epoch,
            ..glasshouse_proto::samples::fruit_estimates()
        },
    };
    fleet.handle(from_owner(20));
    assert_eq!(fleet.latest_fruits["t1"].owner_epoch, 20);
    fleet.handle(from_owner(10));
    assert_eq!(fleet.latest_fruits["t1"].owner_epoch, 20);
    assert_eq!(fleet.stats().stale_epoch, 1);
    assert_eq!(fleet.newest_epoch("t1"), 20);
}

/// A fresh store file for a test (removed first if a run before left it).
fn store_file(name: &str) -> std::path::PathBuf {
    let path = std::env::temp_dir().join(format!(
        "glasshouse-node-{name}-{}.redb",
        std::process::id()
    ));
    let _ = std::fs::remove_file(&path);
    path
}

/// Store rules with checkpoints every `clouds` clouds and no settling.
fn rules(clouds: usize) -> StoreRules {
    StoreRules {
        checkpoint_clouds: clouds,
        settle_ns: 0,
    }
}

/// The store writes among `actions`, in order.
fn store_writes(actions: &[PlannerAction]) -> Vec<&StoreWrite> {
    let writes = actions.iter().filter_map(|a| match a {
        PlannerAction::Store(w) => Some(w),
        _ => None,
    });
    writes.collect()
}

/// Feeds `event` and the `Finish` events it asks for; every action.
fn feed(node: &mut PlannerNode, event: PlannerEvent) -> Vec<PlannerAction> {
    let actions = node.handle(event);
    settle(node, actions)
}

/// [`feed`], performing the store writes on `store` as the driver does.
fn perform_writes(
    node: &mut PlannerNode,
    store: &crate::storage::PlannerStore,
    event: PlannerEvent,
) -> Vec<PlannerAction> {
    let actions = feed(node, event);
    for w in store_writes(&actions) {
        store.write(w).unwrap();
    }
    actions
}

/// The fruit ids `actions` publish last.
fn fruit_ids(actions: &[PlannerAction]) -> Vec<u32> {
    published_fruits(actions).map_or_else(Vec::new, |f| f.fruits.iter().map(|f| f.id).collect())
}

/// Each published fruit's id and colour.
fn fruit_colours(actions: &[PlannerAction]) -> Vec<(u32, Option<glasshouse_geom::Rgb>)> {
    let fruits = published_fruits(actions)
        .map(|f| f.fruits)
        .unwrap_or_default();
    fruits.iter().map(|f| (f.id, f.colour)).collect()
}

#[test]
fn an_owner_stores_a_full_checkpoint_then_its_clouds_then_the_changed_blocks() {
    let (info, clouds) = trolley_clouds(5);
    let mut p1 = node("p1").with_store(rules(2));
    p1.handle(PlannerEvent::TrolleyJoined("t1".into()));
    p1.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: None,
    });
    p1.handle(info_event(&info));
    let mut kinds = Vec::new();
    for cloud in &clouds {
        let actions = feed(&mut p1, cloud_event(cloud));
        // The cloud's own write comes before its views (they go out once it is stored); a
        // checkpoint of blocks may follow them (the log holds what it covers).
        let position = |want: fn(&PlannerAction) -> bool| actions.iter().position(want);
        let views = position(|a| {
            matches!(
                a,
                PlannerAction::Publish {
                    output: TrolleyOutput::Views(_),
                    ..
                }
            )
        });
        let cloud = position(|a| matches!(a, PlannerAction::Store(StoreWrite::Cloud { .. })));
        assert!(cloud.unwrap() < views.unwrap(), "{actions:?}");
        kinds.extend(store_writes(&actions).into_iter().map(|w| match w {
            StoreWrite::Checkpoint {
                full: true, copy, ..
            } => format!("full@{}", copy.meta.based_on_seq),
            StoreWrite::Checkpoint { copy, .. } => format!("blocks@{}", copy.meta.based_on_seq),
            StoreWrite::Cloud { cloud, epoch, .. } => {
                assert_eq!(Some(*epoch), p1.term("t1"));
                format!("cloud{}", cloud.source_frame_seq)
            }
            StoreWrite::Fruits(_) => "fruits".into(),
        }));
    }
    assert_eq!(
        kinds,
        ["full@0", "cloud1", "cloud2", "blocks@2", "cloud3", "cloud4", "blocks@4", "cloud5"]
    );
}

#[test]
fn a_planner_restarted_from_its_store_goes_on_with_the_same_map_and_fruit_ids() {
    let path = store_file("restart");
    let (info, clouds) = trolley_clouds(7);
    let store = crate::storage::PlannerStore::open(&path).unwrap();
    let mut p1 = node("p1").with_store(rules(3));
    let mut uninterrupted = node("p1");
    for n in [&mut p1, &mut uninterrupted] {
        n.handle(PlannerEvent::TrolleyJoined("t1".into()));
        n.handle(PlannerEvent::SnapshotLoaded {
            tid: "t1".into(),
            snapshot: None,
        });
        n.handle(info_event(&info));
    }
    for cloud in &clouds[..5] {
        perform_writes(&mut p1, &store, cloud_event(cloud));
        feed(&mut uninterrupted, cloud_event(cloud));
    }
    let term = p1.term("t1").unwrap();
    drop((p1, store));
    // Restarted: the checkpoint at frame 3 and the two clouds logged after it.
    let store = crate::storage::PlannerStore::open(&path).unwrap();
    let loaded = store.load().unwrap();
    assert!(loaded.unreadable.is_empty());
    assert_eq!(loaded.trolleys.len(), 1);
    assert_eq!(loaded.trolleys[0].clouds.len(), 2);
    let mut p1 = node("p1").with_store(rules(3));
    assert!(p1.restore(loaded.trolleys, loaded.fruits).is_empty());
    assert_eq!(p1.newest_epoch("t1"), term);
    let actions = p1.handle(PlannerEvent::TrolleyJoined("t1".into()));
    assert_eq!(asks(&actions).len(), 1);
    // Nobody else has a copy: the restored one is the map, under a newer term.
    p1.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: None,
    });
    assert!(p1.term("t1").unwrap() > term);
    p1.handle(info_event(&info));
    assert!(same_map(&p1, &uninterrupted, "t1"));
    for cloud in &clouds[5..] {
        let restarted = perform_writes(&mut p1, &store, cloud_event(cloud));
        let through = feed(&mut uninterrupted, cloud_event(cloud));
        assert_eq!(fruit_ids(&restarted), fruit_ids(&through));
        // The colours too: the checkpoint carried each fruit's samples so far.
        let colours = fruit_colours(&restarted);
        assert!(colours.iter().any(|(_, c)| c.is_some()), "{colours:?}");
        assert_eq!(colours, fruit_colours(&through));
        assert_eq!(views_of(&restarted)[0].views, views_of(&through)[0].views);
    }
    assert!(same_map(&p1, &uninterrupted, "t1"));
    drop(store);
    let _ = std::fs::remove_file(&path);
}

#[test]
fn a_settling_planner_decides_nothing_and_takes_what_came_once_settled() {
    let (info, clouds) = trolley_clouds(1);
    let settle_ns = 2_000_000_000;
    let mut p1 = node("p1").with_store(StoreRules {
        checkpoint_clouds: 8,
        settle_ns,
    });
    assert!(p1.is_settling());
    assert!(p1
        .handle(PlannerEvent::TrolleyJoined("t1".into()))
        .is_empty());
    assert!(p1.handle(info_event(&info)).is_empty());
    assert!(p1.handle(cloud_event(&clouds[0])).is_empty());
    assert!(p1
        .handle(PlannerEvent::PlannerJoined("p2".into()))
        .is_empty());
    assert_eq!(p1.role("t1"), None);
    // Settled: t1 is assigned with both planners known, and its cloud waits for the snapshot.
    let actions = p1.handle(status_tick(NOW_NS + settle_ns));
    assert!(!p1.is_settling());
    assert_eq!(asks(&actions), [("t1".to_string(), vec!["p2".to_string()])]);
    let loaded = p1.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: None,
    });
    assert_eq!(p1.stats().clouds_integrated, 1);
    if p1.role("t1") == Some(Role::Owner) {
        assert_eq!(views_of(&settle(&mut p1, loaded)).len(), 1, "info kept too");
    }
}

#[test]
fn a_restored_copy_answers_under_its_epoch_and_a_newer_terms_snapshot_wins() {
    let path = store_file("answer");
    let (info, clouds) = trolley_clouds(4);
    let store = crate::storage::PlannerStore::open(&path).unwrap();
    let mut p1 = node("p1").with_store(rules(8));
    perform_writes(&mut p1, &store, PlannerEvent::TrolleyJoined("t1".into()));
    for event in [
        PlannerEvent::SnapshotLoaded {
            tid: "t1".into(),
            snapshot: None,
        },
        info_event(&info),
        cloud_event(&clouds[0]),
        cloud_event(&clouds[1]),
    ] {
        perform_writes(&mut p1, &store, event);
    }
    let term = p1.term("t1").unwrap();
    drop(store);
    let store = crate::storage::PlannerStore::open(&path).unwrap();
    let loaded = store.load().unwrap();
    // Restarted but not yet holding t1: a peer asking gets the stored copy under its epoch.
    let mut restarted = node("p1").with_store(rules(8));
    restarted.restore(loaded.trolleys, loaded.fruits);
    let answer = restarted.handle(PlannerEvent::SnapshotAsked {
        query_id: 2,
        tid: "t1".into(),
        base: None,
    });
    let [PlannerAction::ReplySnapshot {
        answer: Ok((_, stored)),
        ..
    }] = &answer[..]
    else {
        panic!("{answer:?}")
    };
    assert_eq!((stored.owner_epoch, stored.based_on_seq), (term, 2));
    // An older snapshot of the same term does not replace the restored copy...
    restarted.handle(PlannerEvent::TrolleyJoined("t1".into()));
    let older = MapSnapshot {
        based_on_seq: 1,
        ..(**stored).clone()
    };
    restarted.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(Box::new(older)),
    });
    assert_eq!(
        restarted.planner("t1").unwrap().last_frame(),
        Some(FrameId::new(EDGE_EPOCH_NS, 2))
    );
    // ...a newer term's does, whatever its frame.
    let mut again = node("p1").with_store(rules(8));
    let loaded = store.load().unwrap();
    again.restore(loaded.trolleys, loaded.fruits);
    again.handle(PlannerEvent::TrolleyJoined("t1".into()));
    let newer = MapSnapshot {
        based_on_seq: 1,
        owner_epoch: term + 1,
        ..(**stored).clone()
    };
    again.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(Box::new(newer)),
    });
    assert_eq!(
        again.planner("t1").unwrap().last_frame(),
        Some(FrameId::new(EDGE_EPOCH_NS, 1))
    );
    assert!(again.term("t1").unwrap() > term + 1);
    drop(store);
    let _ = std::fs::remove_file(&path);
}

/// The fruits `actions` publish last.
fn published_fruits(actions: &[PlannerAction]) -> Option<FruitEstimates> {
    actions.iter().rev().find_map(|a| match a {
        PlannerAction::Publish {
            output: TrolleyOutput::Fruits(f),
            ..
        } => Some(f.clone()),
        _ => None,
    })
}

#[test]
fn a_later_visit_starts_every_copy_on_the_prior_and_the_fruits_keep_their_histories() {
    let (info, clouds) = trolley_clouds(4);
    let (mut owner, mut replica) = informed_owner_and_replica(&info);
    let mut first_visit = None;
    for cloud in &clouds {
        first_visit = published_fruits(&feed(&mut owner, cloud_event(cloud))).or(first_visit);
        feed(&mut replica, cloud_event(cloud));
    }
    let first_visit = first_visit.expect("fruits on the first visit");
    assert_eq!(first_visit.visit, 0);
    assert!(!first_visit.fruits.is_empty());
    assert_eq!(first_visit.history.len(), first_visit.fruits.len());
    // The trolley comes back: both copies start visit 1 on the same prior.
    let back = TrolleyInfo {
        visit: 1,
        ..info.clone()
    };
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(&back));
        assert_eq!(n.planner("t1").unwrap().visit(), 1);
        assert_eq!(n.planner("t1").unwrap().last_frame(), None);
    }
    assert!(same_map(&owner, &replica, "t1"));
    // An older visit's info changes nothing.
    owner.handle(info_event(&info));
    assert_eq!(owner.planner("t1").unwrap().visit(), 1);
    // The revisit's first frame: its fruits carry the first visit's season ids.
    let revisit = published_fruits(&feed(&mut owner, cloud_event(&clouds[3])))
        .expect("fruits on the revisit");
    assert_eq!(revisit.visit, 1);
    let season_ids = |f: &FruitEstimates| -> Vec<u32> {
        f.history
            .iter()
            .filter(|h| h.fruit_id != 0)
            .map(|h| h.season_id)
            .collect()
    };
    let seen_again: Vec<_> = season_ids(&revisit)
        .into_iter()
        .filter(|id| season_ids(&first_visit).contains(id))
        .collect();
    assert!(!seen_again.is_empty(), "{revisit:?}");
    for h in revisit
        .history
        .iter()
        .filter(|h| seen_again.contains(&h.season_id))
    {
        let visits: Vec<u32> = h.visits.iter().map(|v| v.visit).collect();
        assert_eq!(visits, [0, 1]);
        // A colour per visit: the fruit's red as seen on each.
        for v in &h.visits {
            let colour = v.colour.expect("a colour per visit");
            assert!(colour.is_red_dominant(30), "{h:?}");
        }
    }
}

#[test]
fn an_owner_with_a_store_keeps_a_new_visit_as_a_full_checkpoint() {
    let (info, clouds) = trolley_clouds(3);
    let mut p1 = node("p1").with_store(rules(8));
    p1.handle(PlannerEvent::TrolleyJoined("t1".into()));
    p1.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: None,
    });
    p1.handle(info_event(&info));
    for cloud in &clouds {
        feed(&mut p1, cloud_event(cloud));
    }
    let actions = p1.handle(info_event(&TrolleyInfo { visit: 1, ..info }));
    let full: Vec<_> = store_writes(&actions)
        .into_iter()
        .filter_map(|w| match w {
            StoreWrite::Checkpoint {
                full: true, copy, ..
            } => Some(copy.meta.visit),
            _ => None,
        })
        .collect();
    assert_eq!(full, [1], "{actions:?}");
}

#[test]
fn an_owner_that_steps_down_keeps_its_copy_when_the_new_owners_missed_a_cloud() {
    let (info, clouds) = trolley_clouds(3);
    let (mut a, mut b) = informed_owner_and_replica(&info);
    let a_id = a.pid.clone();
    // Frame 1 reaches both; frame 2 only the owner (the replica's link was moving).
    let published = a.handle(cloud_event(&clouds[0]));
    b.handle(cloud_event(&clouds[0]));
    hear_fruits(&mut b, &published);
    a.handle(cloud_event(&clouds[1]));
    // Each loses the other's token: b takes over under a newer term on its copy without frame
    // 2, a goes on owning in its own view. Frame 3 reaches both.
    let taken = b.handle(PlannerEvent::PlannerLeft(a_id.clone()));
    settle(&mut b, taken);
    let term_b = b.term("t1").expect("b's term");
    a.handle(PlannerEvent::PlannerLeft(b.pid.clone()));
    a.handle(cloud_event(&clouds[2]));
    b.handle(cloud_event(&clouds[2]));
    assert_eq!((scans(&a), scans(&b)), (3, 2));
    // The links are back: a hears b's term and steps down, and b's copy lacks frame 2.
    b.handle(PlannerEvent::PlannerJoined(a_id));
    a.handle(info_under(&info, term_b, &b.pid));
    assert!(a.is_loading("t1"));
    let resumed = a.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(snapshot_from(&mut b)),
    });
    // a keeps its own copy (every frame), begins a newer term and plans frame 3 on it.
    assert_eq!(scans(&a), 3, "a took b's copy, which lacks frame 2");
    assert_eq!(a.stats().kept_own_copy, 1);
    assert!(a.term("t1").expect("a new term") > term_b);
    assert_eq!(views_of(&resumed)[0].based_on_seq, 3);
}

/// (owner, replica) of t1 with its info; the replica stands by, refreshed every `refresh`
/// clouds, and decodes what it holds ahead.
fn owner_and_decoding_standby(info: &TrolleyInfo, refresh: usize) -> (PlannerNode, PlannerNode) {
    let (mut owner, mut replica) = roles(pair_with_refresh(refresh));
    replica.standby_decoded_ahead = true;
    for n in [&mut owner, &mut replica] {
        n.handle(info_event(info));
    }
    (owner, replica)
}

/// The owner's answer to a refresh of t1 on `base`.
fn answer_on(owner: &mut PlannerNode, base: Option<DeltaBase>) -> Box<MapSnapshot> {
    let reply = owner.handle(PlannerEvent::SnapshotAsked {
        query_id: 7,
        tid: "t1".into(),
        base,
    });
    reply
        .into_iter()
        .find_map(|a| match a {
            PlannerAction::ReplySnapshot { answer, .. } => answer.ok().map(|(_, s)| s),
            _ => None,
        })
        .expect("the owner answers")
}

#[test]
fn a_standby_copy_refreshes_by_delta_and_takes_over_with_the_owners_map() {
    let (info, clouds) = trolley_clouds(7);
    let (mut owner, mut replica) = owner_and_decoding_standby(&info, 2);
    for cloud in &clouds {
        owner.handle(cloud_event(cloud));
        let actions = replica.handle(cloud_event(cloud));
        answer_refreshes(&mut owner, &mut replica, actions);
    }
    // Refreshes after clouds 2, 4 and 6: the first for the whole map (nothing decoded yet), the
    // others for what changed since the copy's.
    assert_eq!(owner.stats().snapshot_deltas_sent, 2);
    assert_eq!(replica.stats().snapshot_deltas_applied, 2);
    assert_eq!(replica.stats().clouds_integrated, 0);
    assert_eq!(replica.pending_clouds("t1"), 1);
    let actions = replica.handle(PlannerEvent::PlannerLeft(owner.pid().to_owned()));
    let actions = settle(&mut replica, actions);
    let views = views_of(&actions);
    assert_eq!(views.len(), 1, "{actions:?}");
    assert_eq!(views[0].based_on_seq, 7);
    assert_eq!(
        replica.stats().decoded_ahead_adopted,
        1,
        "nothing decoded again"
    );
    assert_eq!(
        replica.stats().clouds_integrated,
        1,
        "only the pending cloud"
    );
    assert!(same_map(&replica, &owner, "t1"));
    let (a, b) = (owner.planner("t1").unwrap(), replica.planner("t1").unwrap());
    assert_eq!(a.last_frame(), b.last_frame());
    let (sa, sb) = (
        a.snapshot("t1", "x").unwrap(),
        b.snapshot("t1", "x").unwrap(),
    );
    assert_eq!(
        (sa.tracked_fruits, sa.next_fruit_id),
        (sb.tracked_fruits, sb.next_fruit_id),
        "the same fruit ids"
    );
}

#[test]
fn an_owner_sends_a_delta_only_on_a_base_of_its_own_current_term() {
    let (info, clouds) = trolley_clouds(3);
    let (mut owner, _) = owner_and_decoding_standby(&info, 8);
    for cloud in &clouds {
        owner.handle(cloud_event(cloud));
    }
    let scans = owner.planner("t1").unwrap().map().scans_inserted();
    let base = DeltaBase {
        planner_id: owner.pid().to_owned(),
        owner_epoch: owner.fence.newest("t1"),
        visit: 0,
        scans: scans - 1,
    };
    let delta = answer_on(&mut owner, Some(base.clone()));
    assert!(TrolleyPlanner::is_delta(&delta));
    assert_eq!(delta.owner_epoch, base.owner_epoch);
    let others = [
        None,
        Some(DeltaBase {
            planner_id: "p9".into(),
            ..base.clone()
        }),
        Some(DeltaBase {
            owner_epoch: base.owner_epoch - 1,
            ..base.clone()
        }),
        Some(DeltaBase {
            visit: 1,
            ..base.clone()
        }),
        Some(DeltaBase {
            scans: scans + 1,
            ..base.clone()
        }),
    ];
    for other in others {
        let answer = answer_on(&mut owner, other.clone());
        assert!(!TrolleyPlanner::is_delta(&answer), "{other:?}");
        TrolleyPlanner::check_snapshot(&answer).expect("the whole map");
    }
    assert_eq!(owner.stats().snapshot_deltas_sent, 1);
}

#[test]
fn a_delta_that_does_not_apply_leaves_the_copy_and_its_clouds_are_integrated() {
    let (info, clouds) = trolley_clouds(5);
    let (mut owner, mut replica) = owner_and_decoding_standby(&info, 2);
    for cloud in &clouds[..4] {
        owner.handle(cloud_event(cloud));
        let actions = replica.handle(cloud_event(cloud));
        answer_refreshes(&mut owner, &mut replica, actions);
    }
    assert_eq!(replica.stats().snapshot_deltas_applied, 1);
    owner.handle(cloud_event(&clouds[4]));
    replica.handle(cloud_event(&clouds[4]));
    // A delta from a scan the copy is not at (its copy holds 4 scans).
    let wrong = DeltaBase {
        planner_id: owner.pid().to_owned(),
        owner_epoch: owner.fence.newest("t1"),
        visit: 0,
        scans: 3,
    };
    let delta = answer_on(&mut owner, Some(wrong));
    assert!(TrolleyPlanner::is_delta(&delta));
    if let Some(Slot {
        stage: Stage::Standby { refresh_asked, .. },
        ..
    }) = replica.slots.get_mut("t1")
    {
        *refresh_asked = true;
    }
    replica.handle(PlannerEvent::SnapshotLoaded {
        tid: "t1".into(),
        snapshot: Some(delta),
    });
    assert_eq!(replica.stats().snapshot_deltas_applied, 1, "not applied");
    assert_eq!(
        replica.stats().clouds_integrated,
        1,
        "the kept cloud instead"
    );
    assert!(same_map(&replica, &owner, "t1"));
}
