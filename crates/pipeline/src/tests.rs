#![allow(clippy::unwrap_used)]

use glasshouse_proto::{Header, RankedView, RankedViews, TrolleyState, ViewKind, OWNER_TERMS};
use nalgebra::{Isometry3, Translation3};

use super::*;

/// The edge's boot epoch in these tests.
const EPOCH_NS: u64 = 1_790_000_000_000_000_000;

fn settings() -> EdgeSettings {
    EdgeSettings {
        trolley_id: "t1".into(),
        max_views: 0,
        capture_time_s: 0.5,
        segment_done_utility: 0.2,
    }
}

fn views(seq: u64, utilities: &[f32]) -> RankedViews {
    let views = utilities
        .iter()
        .enumerate()
        .map(|(i, &utility)| RankedView {
            world_from_camera: Isometry3::from_parts(
                Translation3::new(i as f64, 0.0, 1.0),
                Default::default(),
            ),
            utility,
            gain: utility,
            cost_m: 0.0,
            kind: ViewKind::Roi,
        });
    RankedViews {
        views: views.collect(),
        based_on_seq: seq,
        based_on_epoch_ns: EPOCH_NS,
        planning_time_ms: 1.0,
        planner_id: "p1".into(),
        owner_epoch: 0,
    }
}

fn views_header(tid: &str, pid: &str) -> Header {
    Header {
        trolley_id: tid.into(),
        source_id: pid.into(),
        ..Header::default()
    }
}

/// Views on frame `seq` of this epoch from the owner of t1.
fn views_for(seq: u64, utilities: &[f32]) -> EdgeInput {
    EdgeInput::Views {
        sender: String::from("p1"),
        header: views_header("t1", "p1"),
        views: views(seq, utilities),
    }
}

/// A node that knows planner p1 (so p1 owns t1).
fn node(settings: EdgeSettings) -> EdgeNode {
    let mut node = EdgeNode::new(settings, EPOCH_NS);
    assert!(node
        .handle(EdgeInput::PlannerJoined("p1".into()))
        .is_empty());
    assert_eq!(node.owner(), Some("p1"));
    node
}

/// A node that has announced frame 1 and waits for views.
fn waiting(settings: EdgeSettings) -> EdgeNode {
    let mut node = node(settings);
    assert_eq!(
        node.handle(EdgeInput::Start),
        vec![EdgeAction::Capture { frame_seq: 1 }]
    );
    let actions = node.handle(EdgeInput::Captured { frame: true });
    assert!(matches!(
        actions[0],
        EdgeAction::Announce { frame_seq: 1, .. }
    ));
    assert_eq!(actions.last(), Some(&EdgeAction::AwaitViews));
    assert!(node.is_waiting_for_views());
    node
}

fn executed(index: usize, motion_s: f64) -> EdgeInput {
    EdgeInput::Executed(Some(Executed { index, motion_s }))
}

#[test]
fn a_view_is_executed_then_the_next_frame_captured() {
    let mut node = waiting(settings());
    let actions = node.handle(views_for(1, &[0.9, 0.5]));
    let EdgeAction::Execute { goals } = &actions[0] else {
        panic!("{actions:?}")
    };
    assert_eq!(goals.len(), 2);
    let actions = node.handle(executed(1, 2.0));
    assert!(matches!(
        actions[0],
        EdgeAction::PublishArmMoving { views_done: 0, .. }
    ));
    let EdgeAction::Report(EdgeEvent::ViewDone {
        view, views_done, ..
    }) = &actions[1]
    else {
        panic!("{actions:?}")
    };
    assert_eq!((*views_done, view.utility), (1, 0.5));
    assert_eq!(actions[2], EdgeAction::Capture { frame_seq: 2 });
    // The first view was not reachable; motion 2 s plus capture 0.5 s.
    assert_eq!(node.status().unreachable_views, 1);
    assert!((node.sim_time_s() - 2.5).abs() < 1e-12);
}

#[test]
fn no_answer_reannounces_the_same_frame() {
    let mut node = waiting(settings());
    for n in 1..=2 {
        let actions = node.handle(EdgeInput::ViewsTimedOut);
        assert_eq!(
            actions[0],
            EdgeAction::Report(EdgeEvent::Reannounced { frame_seq: 1 })
        );
        assert!(matches!(
            actions[1],
            EdgeAction::Announce { frame_seq: 1, .. }
        ));
        assert_eq!(node.status().reannounces, n);
    }
    // Late views for frame 1 are still taken.
    assert!(matches!(
        node.handle(views_for(1, &[0.9]))[0],
        EdgeAction::Execute { .. }
    ));
}

#[test]
fn views_on_another_frame_or_trolley_are_ignored() {
    let mut node = waiting(settings());
    assert!(node.handle(views_for(7, &[0.9])).is_empty());
    let other = EdgeInput::Views {
        sender: String::from("p1"),
        header: views_header("t2", "p1"),
        views: views(1, &[0.9]),
    };
    assert!(node.handle(other).is_empty());
    // The same seq of an earlier process of this trolley is another frame.
    let mut earlier = views(1, &[0.9]);
    earlier.based_on_epoch_ns = EPOCH_NS - 1;
    let earlier = EdgeInput::Views {
        sender: String::from("p1"),
        header: views_header("t1", "p1"),
        views: earlier,
    };
    assert!(node.handle(earlier).is_empty());
    assert!(node.is_waiting_for_views());
    // Events that do not fit the phase change nothing.
    assert!(node.handle(executed(0, 1.0)).is_empty());
    assert!(node.handle(EdgeInput::Start).is_empty());
    assert!(node.is_waiting_for_views());
}

#[test]
fn views_from_a_planner_that_does_not_own_the_trolley_are_refused() {
    let mut node = waiting(settings());
    // p9 is no member at all; p2 is live but ranks below p1 for t1 or above: whoever is not
    // the owner is refused, whatever its views say.
    node.handle(EdgeInput::PlannerJoined("p2".into()));
    let owner = node.owner().unwrap().to_owned();
    let other = if owner == "p1" { "p2" } else { "p1" };
    for (n, source) in [(1, "p9"), (2, other)] {
        let rogue = EdgeInput::Views {
            sender: String::from(source),
            header: views_header("t1", source),
            views: views(1, &[0.9]),
        };
        let actions = node.handle(rogue);
        assert_eq!(
            actions,
            vec![EdgeAction::Report(EdgeEvent::ViewsRefused {
                source_id: source.into(),
                owner: Some(owner.clone()),
                refused: n,
            })]
        );
        assert!(node.is_waiting_for_views());
    }
    assert_eq!(node.status().refused_views, 2);
    // The owner's views on the frame are executed.
    let from_owner = EdgeInput::Views {
        sender: String::from(&owner),
        header: views_header("t1", &owner),
        views: views(1, &[0.9]),
    };
    assert!(matches!(
        node.handle(from_owner)[0],
        EdgeAction::Execute { .. }
    ));
    // The owner leaves: the other planner takes over, and its views count from now on.
    node.handle(EdgeInput::PlannerLeft(owner));
    assert_eq!(node.owner(), Some(other));
    // Without any live planner no views are taken.
    node.handle(EdgeInput::PlannerLeft(other.into()));
    assert_eq!(node.owner(), None);
    assert_eq!(node.handle(views_for(2, &[0.9])).len(), 1);
    assert_eq!(node.status().refused_views, 3);
}

#[test]
fn views_whose_header_names_another_planner_than_their_key_are_refused() {
    let mut node = waiting(settings());
    node.handle(EdgeInput::PlannerJoined("p2".into()));
    let owner = node.owner().unwrap().to_owned();
    let other = if owner == "p1" { "p2" } else { "p1" };
    // A live planner that does not own t1, on its own key, claiming to be the owner under the
    // newest term there can be; then views on a key that names no planner.
    let claiming_owner = RankedViews {
        planner_id: owner.clone(),
        owner_epoch: u64::MAX,
        ..views(1, &[0.9])
    };
    let forged = [(other, claiming_owner), ("", views(1, &[0.9]))];
    for (n, (sender, views)) in (1..).zip(forged) {
        let input = EdgeInput::Views {
            sender: sender.into(),
            header: views_header("t1", &owner),
            views,
        };
        let refused = EdgeEvent::MisattributedViewsRefused {
            sender: sender.into(),
            claimed: owner.clone(),
            refused: n,
        };
        assert_eq!(node.handle(input), vec![EdgeAction::Report(refused)]);
    }
    assert_eq!(node.status().refused_views, 2);
    // Nothing was taken from them: no term, still waiting.
    assert_eq!(node.owner_epoch(), 0);
    assert!(node.is_waiting_for_views());
    // The same views on the owner's own key move the arm.
    let from_owner = EdgeInput::Views {
        sender: owner.clone(),
        header: views_header("t1", &owner),
        views: views(1, &[0.9]),
    };
    assert!(matches!(
        node.handle(from_owner)[0],
        EdgeAction::Execute { .. }
    ));
}

/// Views on frame `seq` of this epoch from `pid`, under its ownership epoch `owner_epoch`.
fn views_under(pid: &str, seq: u64, owner_epoch: u64) -> EdgeInput {
    EdgeInput::Views {
        sender: String::from(pid),
        header: views_header("t1", pid),
        views: RankedViews {
            planner_id: pid.into(),
            owner_epoch,
            ..views(seq, &[0.9])
        },
    }
}

/// Executes the views just taken and announces the next frame; the ownership term it announces
/// (epoch and planner).
fn execute_and_announce(node: &mut EdgeNode, seq: u64) -> (u64, String) {
    let actions = node.handle(executed(0, 1.0));
    assert_eq!(
        actions.last(),
        Some(&EdgeAction::Capture { frame_seq: seq })
    );
    let mut actions = node.handle(EdgeInput::Captured { frame: true });
    let EdgeAction::Announce {
        frame_seq,
        owner_epoch,
        owner_id,
        ..
    } = actions.remove(0)
    else {
        panic!("{actions:?}")
    };
    assert_eq!(frame_seq, seq);
    (owner_epoch, owner_id)
}

#[test]
fn views_of_a_replaced_owner_are_refused_and_counted_never_executed() {
    let live = ["p1".to_string(), "p2".to_string()];
    let ranked = glasshouse_fleet::rank_planners("t1", &live);
    let (first, second) = (ranked[0], ranked[1]);
    let mut node = EdgeNode::new(settings(), EPOCH_NS);
    for p in &live {
        node.handle(EdgeInput::PlannerJoined(p.clone()));
    }
    node.handle(EdgeInput::Start);
    node.handle(EdgeInput::Captured { frame: true });
    // The owner's term 10: its views are executed, and the next frame announces the epoch.
    assert!(matches!(
        node.handle(views_under(first, 1, 10))[0],
        EdgeAction::Execute { .. }
    ));
    assert_eq!(execute_and_announce(&mut node, 2), (10, first.to_owned()));
    // The owner pauses; its token goes, the other planner takes over under term 20.
    node.handle(EdgeInput::PlannerLeft(first.into()));
    assert!(matches!(
        node.handle(views_under(second, 2, 20))[0],
        EdgeAction::Execute { .. }
    ));
    assert_eq!(execute_and_announce(&mut node, 3), (20, second.to_owned()));
    // The paused owner wakes up: its token is back, it ranks first again, and it plans the
    // latest frame under its old term. Refused and counted: the arm does not move. The frame
    // goes out again at once, its info naming the newer term, so the woken owner learns of it.
    node.handle(EdgeInput::PlannerJoined(first.into()));
    assert_eq!(node.owner(), Some(first));
    let refused = EdgeEvent::StaleViewsRefused {
        source_id: first.into(),
        owner_epoch: 10,
        newest: 20,
        stale: 1,
    };
    assert_eq!(
        node.handle(views_under(first, 3, 10)),
        vec![
            EdgeAction::Report(refused),
            EdgeAction::Report(EdgeEvent::Reannounced { frame_seq: 3 }),
            EdgeAction::Announce {
                frame_seq: 3,
                sim_time_s: node.sim_time_s(),
                owner_epoch: 20,
                owner_id: second.into(),
            },
            EdgeAction::AwaitViews,
        ]
    );
    // Once per frame: more of its stale views are only counted.
    assert_eq!(node.handle(views_under(first, 3, 10)).len(), 1);
    // So are views without any epoch (a planner without fencing), from anyone.
    let unfenced = views_under(second, 3, 0);
    assert_eq!(node.handle(unfenced).len(), 1);
    assert_eq!(node.status().stale_views, 3);
    assert!(node.is_waiting_for_views());
    // The other planner is no longer the owner: refused as before, whatever its epoch.
    node.handle(views_under(second, 3, 20));
    assert_eq!(node.status().refused_views, 1);
    // Caught up, the woken owner begins a newer term, and its views are executed.
    assert!(matches!(
        node.handle(views_under(first, 3, 30))[0],
        EdgeAction::Execute { .. }
    ));
    assert_eq!(execute_and_announce(&mut node, 4), (30, first.to_owned()));
    let terms: Vec<(&str, u64, u32)> = node
        .status()
        .owner_terms
        .iter()
        .map(|t| (t.planner_id.as_str(), t.owner_epoch, t.views_executed))
        .collect();
    assert_eq!(terms, vec![(first, 10, 1), (second, 20, 1), (first, 30, 1)]);
    assert_eq!(node.status().owner_epoch, 30);
}

#[test]
fn views_without_an_epoch_are_taken_until_an_epoch_is_seen() {
    // A planner without fencing (or the experiments' in-process loop) sends epoch 0.
    let mut node = waiting(settings());
    assert!(matches!(
        node.handle(views_for(1, &[0.9]))[0],
        EdgeAction::Execute { .. }
    ));
    assert_eq!(execute_and_announce(&mut node, 2), (0, "p1".to_owned()));
    assert_eq!(node.status().stale_views, 0);
    assert_eq!(node.status().owner_terms.len(), 1);
}

#[test]
fn the_status_keeps_the_last_terms() {
    let mut node = waiting(settings());
    for (i, epoch) in (1..=OWNER_TERMS as u64 + 3).enumerate() {
        let seq = i as u64 + 1;
        node.handle(views_under("p1", seq, epoch));
        execute_and_announce(&mut node, seq + 1);
    }
    let terms = &node.status().owner_terms;
    assert_eq!(terms.len(), OWNER_TERMS);
    assert_eq!(terms.first().map(|t| t.owner_epoch), Some(4));
    assert_eq!(
        terms.last().map(|t| t.owner_epoch),
        Some(OWNER_TERMS as u64 + 3)
    );
}

#[test]
fn no_reachable_view_costs_a_capture_and_captures_again() {
    let mut node = waiting(settings());
    node.handle(views_for(1, &[0.9, 0.8, 0.7]));
    let actions = node.handle(EdgeInput::Executed(None));
    assert_eq!(
        actions,
        vec![
            EdgeAction::Report(EdgeEvent::NoReachableView {
                frame_seq: 1,
                offered: 3
            }),
            EdgeAction::Capture { frame_seq: 2 }
        ]
    );
    assert_eq!(node.status().unreachable_views, 3);
    assert_eq!(node.status().views_done, 0);
    assert!((node.sim_time_s() - 0.5).abs() < 1e-12);
}

#[test]
fn low_utility_moves_to_the_next_segment() {
    let mut node = waiting(settings());
    assert_eq!(
        node.handle(views_for(1, &[0.1])),
        vec![EdgeAction::MoveToNextSegment]
    );
    let actions = node.handle(EdgeInput::SegmentMoved(Some(3.0)));
    assert_eq!(
        actions[0],
        EdgeAction::Report(EdgeEvent::SegmentDone {
            segments_done: 1,
            sim_time_s: 3.5
        })
    );
    assert_eq!(actions[1], EdgeAction::Capture { frame_seq: 2 });
}

#[test]
fn a_quicker_view_ranked_before_a_better_one_does_not_end_the_segment() {
    let mut node = waiting(settings());
    // The planner ranked a quick view of low utility first; the list still holds one above
    // the segment's threshold (0.2).
    let actions = node.handle(views_for(1, &[0.1, 0.5]));
    assert!(
        matches!(actions[0], EdgeAction::Execute { .. }),
        "{actions:?}"
    );
}

#[test]
fn at_the_row_end_low_views_are_still_executed_and_none_finishes() {
    let mut node = waiting(settings());
    node.handle(views_for(1, &[0.1]));
    assert!(matches!(
        node.handle(EdgeInput::SegmentMoved(None))[0],
        EdgeAction::Execute { .. }
    ));
    let mut node = waiting(settings());
    node.handle(views_for(1, &[]));
    let actions = node.handle(EdgeInput::SegmentMoved(None));
    assert!(matches!(
        actions[0],
        EdgeAction::Report(EdgeEvent::Finished { .. })
    ));
    assert_eq!(actions.last(), Some(&EdgeAction::Stop));
    assert!(node.is_done());
}

#[test]
fn the_view_budget_ends_the_run_once_the_last_frame_is_answered() {
    let mut node = waiting(EdgeSettings {
        max_views: 1,
        ..settings()
    });
    node.handle(views_for(1, &[0.9]));
    node.handle(executed(0, 1.0));
    node.handle(EdgeInput::Captured { frame: true });
    let actions = node.handle(views_for(2, &[0.9]));
    assert_eq!(
        actions[0],
        EdgeAction::Report(EdgeEvent::Finished {
            views_done: 1,
            frames: 2
        })
    );
    let EdgeAction::PublishStatus { status, .. } = &actions[1] else {
        panic!("{actions:?}")
    };
    assert_eq!(status.state, TrolleyState::Done);
    assert_eq!(actions[2], EdgeAction::Stop);
    // Nothing happens after the end.
    assert!(node.handle(EdgeInput::ViewsTimedOut).is_empty());
}

#[test]
fn a_source_without_frames_finishes() {
    let mut node = node(settings());
    node.handle(EdgeInput::Start);
    let actions = node.handle(EdgeInput::Captured { frame: false });
    assert!(matches!(
        actions[0],
        EdgeAction::Report(EdgeEvent::Finished {
            views_done: 0,
            frames: 0
        })
    ));
    assert_eq!(actions.last(), Some(&EdgeAction::Stop));
}
fn pace(pacer: &mut RealtimePacer, node: &mut EdgeNode, input: EdgeInput, now_s: f64) -> f64 {
    let now = std::time::Duration::from_secs_f64(now_s);
    let actions = node.handle(input);
    let waits: Vec<f64> = actions
        .iter()
        .map(|a| pacer.wait_before(a, node.sim_time_s(), now).as_secs_f64())
        .collect();
    waits.last().copied().unwrap_or(0.0)
}

#[test]
fn realtime_pacing_waits_out_motion_and_capture_from_when_the_motion_began() {
    let mut pacer = RealtimePacer::default();
    // The first capture does not wait.
    let mut node = EdgeNode::new(settings(), EPOCH_NS);
    assert_eq!(pace(&mut pacer, &mut node, EdgeInput::Start, 0.0), 0.0);
    // Views arrive at wall 10 s: the arm starts moving.
    let mut node = waiting(settings());
    assert_eq!(pace(&mut pacer, &mut node, views_for(1, &[0.9]), 10.0), 0.0);
    // IK took 0.3 s; motion 2 s + capture 0.5 s are due at 12.5 s.
    let wait_s = pace(&mut pacer, &mut node, executed(0, 2.0), 10.3);
    assert!((wait_s - 2.2).abs() < 1e-9, "{wait_s}");
    // Late already (the driver was slow): no wait, and no wait owed to the next capture.
    let mut node = waiting(settings());
    pace(&mut pacer, &mut node, views_for(1, &[0.9]), 20.0);
    assert_eq!(pace(&mut pacer, &mut node, executed(0, 1.0), 30.0), 0.0);
    assert_eq!(
        pacer.wait_before(
            &EdgeAction::Capture { frame_seq: 9 },
            99.0,
            Default::default()
        ),
        std::time::Duration::ZERO
    );
}

#[test]
fn realtime_pacing_of_an_unreachable_view_and_a_segment_move() {
    let mut pacer = RealtimePacer::default();
    let mut node = waiting(settings());
    pace(&mut pacer, &mut node, views_for(1, &[0.9]), 5.0);
    // Nothing reachable: only the capture time (0.5 s) is waited out.
    let wait_s = pace(&mut pacer, &mut node, EdgeInput::Executed(None), 5.1);
    assert!((wait_s - 0.4).abs() < 1e-9, "{wait_s}");
    // A segment move of 3 s plus the capture.
    let mut node = waiting(settings());
    pace(&mut pacer, &mut node, views_for(1, &[0.1]), 7.0);
    let wait_s = pace(
        &mut pacer,
        &mut node,
        EdgeInput::SegmentMoved(Some(3.0)),
        7.0,
    );
    assert!((wait_s - 3.5).abs() < 1e-9, "{wait_s}");
}
