//! The edge's sources: frames recorded from the simulator play back through the same loop, and
//! in the row scenario the trolley works through the row segment by segment.

use glasshouse_edge::{EdgeConfig, EdgeEvent};
use glasshouse_proto::{decode_typed, ImageEncoding, RgbdFrame};
use glasshouse_tests::{test_edge_config, Pipeline};

fn count(events: &[EdgeEvent], f: impl Fn(&EdgeEvent) -> bool) -> usize {
    events.iter().filter(|e| f(e)).count()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn recorded_frames_replay_through_the_loop() {
    let dir = std::env::temp_dir().join(format!("glasshouse-replay-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);

    let mut record = Pipeline::start(EdgeConfig {
        record_frames_dir: Some(dir.clone()),
        ..test_edge_config(3)
    })
    .await;
    let recorded_events = record.run_to_end(180).await;
    record.stop().await;
    let frames = std::fs::read_dir(&dir)
        .expect("recording folder")
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with("frame-"))
        .count();
    assert!(dir.join("info.ghw").is_file());
    let recorded_frames = match recorded_events.last() {
        Some(EdgeEvent::Finished { frames, .. }) => *frames as usize,
        other => panic!("recording did not finish: {other:?}"),
    };
    assert_eq!(frames, recorded_frames);
    // The edge records what it sends: compressed planes, which the replay decodes.
    let first = std::fs::read(dir.join("frame-00000001.ghw")).expect("first frame");
    let (_, frame) = decode_typed::<RgbdFrame>(&first).expect("the recorded frame decodes");
    assert_eq!(frame.depth_encoding, ImageEncoding::LeftDeltaZstd);
    assert_eq!(frame.rgb_encoding, ImageEncoding::LeftDeltaZstd);
    assert!(first.len() < frame.depth.len() * 2, "{} bytes", first.len());

    let mut replay = Pipeline::start(EdgeConfig {
        replay_dir: Some(dir.clone()),
        ..test_edge_config(0)
    })
    .await;
    let events = replay.run_to_end(180).await;
    // Every recorded frame is published once and answered; the last one ends the replay.
    match events.last() {
        Some(EdgeEvent::Finished { frames, views_done }) => {
            assert_eq!(*frames as usize, recorded_frames);
            assert_eq!(*views_done as usize, recorded_frames);
        }
        other => panic!("replay did not finish: {other:?}"),
    }
    let fleet = replay.fleet.lock().expect("fleet").clone();
    let trolley = fleet.trolleys.get("t1").expect("dashboard saw t1");
    assert!(trolley.clouds as usize >= recorded_frames);
    assert!(!trolley.fruits.is_empty(), "no fruits from the replay");
    replay.stop().await;
    let _ = std::fs::remove_dir_all(&dir);

    // A folder that is not a recording is a clear error, not a panic.
    let err =
        glasshouse_edge::source::ReplaySource::open(&std::env::temp_dir().join("no-such-rec"))
            .err()
            .expect("error");
    assert!(format!("{err:#}").contains("info.ghw"), "{err:#}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_row_trolley_moves_on_segment_by_segment() {
    // A threshold no view reaches: every plan says "nothing left here", so the trolley walks
    // the whole row, then executes views in the last segment.
    let config = EdgeConfig {
        scenario: glasshouse_sim::ScenarioKind::Row,
        segment_length_m: 1.0,
        segment_done_utility: 10.0,
        ..test_edge_config(2)
    };
    let scene = glasshouse_sim::Scene::generate(glasshouse_sim::ScenarioKind::Row, config.seed);
    let segments = scene.segments(config.segment_length_m).len();
    let mut pipeline = Pipeline::start(config).await;
    let events = pipeline.run_to_end(300).await;
    let segments_done = count(&events, |e| matches!(e, EdgeEvent::SegmentDone { .. }));
    assert_eq!(segments_done, segments - 1, "{events:?}");
    // Simulated time grows with every move along the row.
    let times: Vec<f64> = events
        .iter()
        .filter_map(|e| match e {
            EdgeEvent::SegmentDone { sim_time_s, .. } => Some(*sim_time_s),
            _ => None,
        })
        .collect();
    assert!(times.windows(2).all(|w| w[1] > w[0]), "{times:?}");
    assert!(matches!(
        events.last(),
        Some(EdgeEvent::Finished { views_done: 2, .. })
    ));
    pipeline.stop().await;
}
