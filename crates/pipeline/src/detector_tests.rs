#![allow(clippy::unwrap_used)]

use glasshouse_fleet::{first_ranked, MembershipEvent};
use glasshouse_proto::{samples, Header};

use super::*;

const EPOCH_NS: u64 = 1_790_000_000_000_000_000;

fn trolleys(n: usize) -> Vec<String> {
    (1..=n).map(|i| format!("t{i}")).collect()
}

/// The trolleys a `Serve` in `actions` names, minus those an `Unserve` names.
fn serves(actions: &[DetectorAction]) -> (Vec<String>, Vec<String>) {
    let mut serve = Vec::new();
    let mut unserve = Vec::new();
    for action in actions {
        match action {
            DetectorAction::Serve(t) => serve.push(t.clone()),
            DetectorAction::Unserve(t) => unserve.push(t.clone()),
            other => panic!("unexpected action {other:?}"),
        }
    }
    (serve, unserve)
}

fn frame_header(tid: &str, seq: u64) -> Header {
    Header {
        seq,
        epoch_ns: 42,
        stamp_ns: 7_000,
        trolley_id: tid.into(),
        source_id: tid.into(),
        frame_id: "world".into(),
    }
}

#[test]
fn a_lone_detector_serves_every_trolley_once_until_it_leaves() {
    let mut node = DetectorNode::new("d1", EPOCH_NS);
    for tid in trolleys(3) {
        let actions = node.handle(DetectorInput::Member(MembershipEvent::TrolleyJoined(
            tid.clone(),
        )));
        assert_eq!(actions, vec![DetectorAction::Serve(tid.clone())]);
        // A second join of the same token changes nothing.
        assert!(node
            .handle(DetectorInput::Member(MembershipEvent::TrolleyJoined(tid)))
            .is_empty());
    }
    assert_eq!(node.counts().trolleys_served, 3);
    let actions = node.handle(DetectorInput::Member(MembershipEvent::TrolleyLeft(
        "t2".into(),
    )));
    assert_eq!(actions, vec![DetectorAction::Unserve("t2".into())]);
    assert_eq!(node.served().len(), 2);
}

#[test]
fn two_detectors_split_the_trolleys_as_the_ranking_says_and_the_survivor_takes_all() {
    let mut d1 = DetectorNode::new("d1", EPOCH_NS);
    let mut d2 = DetectorNode::new("d2", EPOCH_NS);
    for node in [&mut d1, &mut d2] {
        for tid in trolleys(12) {
            node.handle(DetectorInput::Member(MembershipEvent::TrolleyJoined(tid)));
        }
    }
    let (_, unserve) = serves(
        &d1.handle(DetectorInput::Member(MembershipEvent::ServerJoined(
            "d2".into(),
        ))),
    );
    d2.handle(DetectorInput::Member(MembershipEvent::ServerJoined(
        "d1".into(),
    )));
    // Every trolley served by exactly the detector ranked first for it.
    for tid in trolleys(12) {
        let first = first_ranked(&tid, ["d1", "d2"]).unwrap();
        assert_eq!(d1.served().contains(&tid), first == "d1", "{tid}");
        assert_eq!(d2.served().contains(&tid), first == "d2", "{tid}");
        assert_eq!(unserve.contains(&tid), first == "d2", "{tid}");
    }
    assert!(!d1.served().is_empty() && !d2.served().is_empty());
    // d2 leaves: d1 serves its trolleys again, and only those are new.
    let (serve, unserve) = serves(
        &d1.handle(DetectorInput::Member(MembershipEvent::ServerLeft(
            "d2".into(),
        ))),
    );
    assert!(unserve.is_empty());
    assert_eq!(serve, d2.served().iter().cloned().collect::<Vec<_>>());
    assert_eq!(d1.served().len(), 12);
}

#[test]
fn a_detector_never_believes_its_own_leave() {
    let mut node = DetectorNode::new("d1", EPOCH_NS);
    node.handle(DetectorInput::Member(MembershipEvent::TrolleyJoined(
        "t1".into(),
    )));
    assert!(node
        .handle(DetectorInput::Member(MembershipEvent::ServerLeft(
            "d1".into()
        )))
        .is_empty());
    assert!(node.served().contains("t1"));
}

#[test]
fn a_frame_is_detected_and_its_cloud_published_under_the_detectors_id_and_epoch() {
    let mut node = DetectorNode::new("d1", EPOCH_NS);
    let header = frame_header("t1", 9);
    let frame = Box::new(samples::rgbd_frame());
    let actions = node.handle(DetectorInput::Frame {
        header: header.clone(),
        frame: frame.clone(),
    });
    assert_eq!(
        actions,
        vec![DetectorAction::Detect {
            header: header.clone(),
            frame
        }]
    );
    let cloud = samples::roi_cloud();
    let actions = node.handle(DetectorInput::Detected {
        header,
        result: Ok(Box::new(cloud.clone())),
        detect_ms: 12.0,
    });
    let [DetectorAction::PublishCloud {
        header,
        cloud: sent,
    }] = actions.as_slice()
    else {
        panic!("expected one cloud, got {actions:?}");
    };
    // (The sample cloud holds a NaN point: compared by what identifies it.)
    assert_eq!(sent.points_in_world.len(), cloud.points_in_world.len());
    assert_eq!(sent.source_frame(), cloud.source_frame());
    assert_eq!((header.seq, header.stamp_ns), (9, 7_000));
    assert_eq!(
        (header.epoch_ns, header.source_id.as_str()),
        (EPOCH_NS, "d1")
    );
    assert_eq!(header.trolley_id, "t1");
    assert_eq!(node.counts().frames_processed, 1);
}

#[test]
fn bad_frames_are_counted_and_never_published() {
    let mut node = DetectorNode::new("d1", EPOCH_NS);
    let actions = node.handle(DetectorInput::Frame {
        header: frame_header("t/1", 1),
        frame: Box::new(samples::rgbd_frame()),
    });
    assert!(matches!(
        actions.as_slice(),
        [DetectorAction::Report(DetectorReport::FrameRejected {
            seq: 1,
            ..
        })]
    ));
    let actions = node.handle(DetectorInput::Detected {
        header: frame_header("t1", 2),
        result: Err("depth and rgb sizes differ".into()),
        detect_ms: 1.0,
    });
    assert!(matches!(
        actions.as_slice(),
        [DetectorAction::Report(DetectorReport::FrameRejected {
            seq: 2,
            ..
        })]
    ));
    let counts = node.counts();
    assert_eq!((counts.frames_rejected, counts.frames_processed), (2, 0));
}

#[test]
fn the_status_counts_frames_drops_and_the_mean_detection_time() {
    let mut node = DetectorNode::new("d1", EPOCH_NS);
    for (seq, ms) in [(1, 10.0), (2, 30.0)] {
        node.handle(DetectorInput::Detected {
            header: frame_header("t1", seq),
            result: Ok(Box::new(samples::roi_cloud())),
            detect_ms: ms,
        });
    }
    node.handle(DetectorInput::Detected {
        header: frame_header("t1", 3),
        result: Err("bad".into()),
        detect_ms: 1.0,
    });
    let statuses: Vec<_> = (0..2)
        .map(|_| {
            node.handle(DetectorInput::StatusTick {
                dropped_messages: 5,
            })
        })
        .collect();
    let [DetectorAction::PublishStatus { header, status }] = statuses[1].as_slice() else {
        panic!("expected a status, got {statuses:?}");
    };
    assert_eq!(header.seq, 2);
    assert_eq!(status.frames_processed, 2);
    assert_eq!(status.dropped_messages, 6);
    assert_eq!(status.mean_detect_time_ms, 20.0);
}
