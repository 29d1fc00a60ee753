//! Real trolleys' formats, checked with tools nobody on the team wrote: a rosbag2 MCAP written
//! by `rosbags` plays as a trolley and finds the fruits the direct run found; bad bags are
//! counted drops; a run recorded to MCAP opens in the stock `mcap` reader, every channel with a
//! schema, and replays through a fresh planner to the same fruits; a stand-in ROS 2 node made of
//! the Python Zenoh client drives the edge's ROS 2 source.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use glasshouse_dashboard::{DashboardSettings, FoxgloveLiveSettings, McapSettings};
use glasshouse_edge::{EdgeConfig, EdgeEvent, SourceKind};
use glasshouse_geom::FruitEstimate;
use glasshouse_pipeline::TrolleySource;
use glasshouse_planner::PlannerSettings;
use glasshouse_proto::{decode_typed, TrolleyInfo};
use glasshouse_ros::{BagSource, DropReason, RosTopics, RosTrolley};
use glasshouse_tests::{procs, script, test_edge_config, until, within, Pipeline};

fn temp_dir(what: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("glasshouse-{what}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// The trolley a recorded `info.ghw` describes, for a ROS source's settings.
fn recorded_trolley(frames: &Path) -> RosTrolley {
    let bytes = std::fs::read(frames.join("info.ghw")).expect("info.ghw");
    let (_, info) = decode_typed::<TrolleyInfo>(&bytes).expect("a TrolleyInfo");
    RosTrolley {
        camera_workspace: info.camera_workspace,
        sampling_region: info.sampling_region,
        robot: info.robot.map(|r| *r),
        scenario: info.scenario,
    }
}

/// The run's fruits once the planner has published them for frame `last_seq`.
async fn fruits_after(pipeline: &Pipeline, last_seq: u64) -> Vec<FruitEstimate> {
    within(60, "fruits of the last frame", async {
        loop {
            let fruits = pipeline.fleet.lock().ok().and_then(|f| {
                let t = f.trolleys.get("t1")?;
                (t.fruits_based_on_seq == last_seq).then(|| t.fruits.clone())
            });
            if let Some(fruits) = fruits {
                return fruits;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
}

fn finished_frames(events: &[EdgeEvent]) -> u64 {
    match events.last() {
        Some(EdgeEvent::Finished { frames, .. }) => *frames,
        other => panic!("the run did not finish: {other:?}"),
    }
}

/// Every fruit of `a` has one in `b` within `mm` millimetres, and the counts agree.
fn same_fruits(a: &[FruitEstimate], b: &[FruitEstimate], mm: f64) {
    assert_eq!(a.len(), b.len(), "fruit counts differ:\n{a:?}\n{b:?}");
    for f in a {
        let nearest = b
            .iter()
            .map(|g| (g.centre - f.centre).norm())
            .fold(f64::INFINITY, f64::min);
        assert!(
            nearest * 1e3 <= mm,
            "fruit {} has no partner within {mm} mm ({nearest} m)",
            f.id
        );
    }
}

/// Records a short simulated run's frames; its fruits and frame count.
async fn record_simulated_run(frames_dir: &Path, views: u32) -> (Vec<FruitEstimate>, u64) {
    let mut pipeline = Pipeline::start(EdgeConfig {
        record_frames_dir: Some(frames_dir.to_path_buf()),
        scenario: glasshouse_sim::ScenarioKind::Two,
        ..test_edge_config(views)
    })
    .await;
    let frames = finished_frames(&pipeline.run_to_end(180).await);
    let fruits = fruits_after(&pipeline, frames).await;
    pipeline.stop().await;
    (fruits, frames)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_rosbag_of_a_simulated_trolley_finds_the_same_fruits() {
    let dir = temp_dir("rosbag");
    let frames_dir = dir.join("frames");
    let (direct, frames) = record_simulated_run(&frames_dir, 4).await;
    assert!(!direct.is_empty(), "the direct run found no fruit");
    let bag = dir.join("bag");
    let bag_arg = bag.to_string_lossy().into_owned();
    script(
        "frames-to-rosbag",
        &[&frames_dir.to_string_lossy(), &bag_arg],
    );
    let stats = script("rosbag-stats", &[&bag_arg]);
    assert!(stats.contains("sensor_msgs/msg/Image"), "{stats}");

    let config = EdgeConfig {
        source: SourceKind::Bag,
        bag: Some(bag.clone()),
        ros: glasshouse_edge::RosSettings {
            trolley: recorded_trolley(&frames_dir),
            ..Default::default()
        },
        ..test_edge_config(0)
    };
    let mut pipeline = Pipeline::start(config).await;
    let played = finished_frames(&pipeline.run_to_end(180).await);
    assert_eq!(played, frames, "every recorded frame is played once");
    let from_bag = fruits_after(&pipeline, frames).await;
    pipeline.stop().await;
    same_fruits(&direct, &from_bag, 2.0);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Plays a whole bag through a `BagSource`; the frames it gave.
fn play(bag: &Path, trolley: RosTrolley) -> (u64, BagSource) {
    let mut source = BagSource::open(bag, RosTopics::default(), trolley).expect("a bag");
    let mut frames = 0;
    while let Some(frame) = source.capture(frames + 1).expect("capture never fails") {
        assert_eq!(frame.depth.len(), frame.rgb.len() / 3);
        frames += 1;
        source.execute(&[nalgebra::Isometry3::identity()]);
    }
    (frames, source)
}

#[test]
fn bad_bags_give_counted_drops_and_clear_errors_never_panics() {
    let dir = temp_dir("bad-bags");
    let frames = dir.join("frames");
    let frames_arg = frames.to_string_lossy().into_owned();
    script(
        "fake-frames",
        &[
            &frames_arg,
            "--frames",
            "6",
            "--width",
            "16",
            "--height",
            "12",
        ],
    );
    let bad = dir.join("bad");
    script(
        "frames-to-rosbag",
        &[
            &frames_arg,
            &bad.to_string_lossy(),
            "--omit-tf-frame",
            "2",
            "--depth-size-mismatch-frame",
            "3",
            "--bad-encoding-frame",
            "4",
        ],
    );
    let (played, source) = play(&bad, RosTrolley::default());
    assert_eq!(played, 3, "frames 1, 5 and 6 are good");
    let drops = source.drops();
    assert_eq!(drops.get(&DropReason::MissingTf), Some(&1), "{drops:?}");
    assert_eq!(drops.get(&DropReason::Size), Some(&1), "{drops:?}");
    assert_eq!(drops.get(&DropReason::Encoding), Some(&1), "{drops:?}");

    // A truncated file: the frames before the cut play, then the bag ends.
    let good = dir.join("good");
    script("frames-to-rosbag", &[&frames_arg, &good.to_string_lossy()]);
    let mcap = std::fs::read_dir(&good)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| p.extension().is_some_and(|e| e == "mcap"))
        .expect("the bag's mcap file");
    let bytes = std::fs::read(&mcap).unwrap();
    let truncated = dir.join("truncated.mcap");
    std::fs::write(&truncated, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let (played, _) = play(&truncated, RosTrolley::default());
    assert!(played < 6, "{played} frames from two thirds of a bag");
    // Not a bag at all, and no such path: clear errors.
    let err = BagSource::open(
        &dir.join("nothing-here"),
        RosTopics::default(),
        RosTrolley::default(),
    )
    .err()
    .expect("an error");
    assert!(err.to_string().contains("nothing-here"), "{err}");
    std::fs::write(dir.join("junk.mcap"), b"not an mcap file at all").unwrap();
    let (played, _) = play(&dir.join("junk.mcap"), RosTrolley::default());
    assert_eq!(played, 0);
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_recording_opens_in_the_mcap_reader_and_replays_to_the_same_fruits() {
    procs::build_binaries();
    let dir = temp_dir("mcap");
    let dashboard = DashboardSettings {
        mcap: Some(McapSettings {
            dir: dir.clone(),
            ..McapSettings::default()
        }),
        foxglove: Some(FoxgloveLiveSettings {
            listen: "127.0.0.1:0".into(),
            ..FoxgloveLiveSettings::default()
        }),
        ..DashboardSettings::default()
    };
    let mut live = Pipeline::start_services(dashboard, PlannerSettings::default()).await;
    // A Foxglove client watches the run live: connected before the trolley starts.
    let counters = live.dashboard_counters.clone();
    until(30, "the Foxglove server up", || {
        counters.foxglove_addr.lock().is_ok_and(|a| a.is_some())
    })
    .await;
    let foxglove_addr = counters.foxglove_addr.lock().unwrap().expect("listening");
    let (ready, foxglove_summary) = (dir.join("foxglove.ready"), dir.join("foxglove.json"));
    let mut args = vec![
        "--url".to_string(),
        format!("ws://{foxglove_addr}"),
        "--ready-file".into(),
        ready.to_string_lossy().into_owned(),
        "--summary".into(),
        foxglove_summary.to_string_lossy().into_owned(),
        "--timeout-s".into(),
        "150".into(),
        "--want-topic".into(),
        "gh/trolley/t1/fruits".into(),
    ];
    for schema in [
        "glasshouse.wire.Envelope",
        "foxglove.RawImage",
        "foxglove.CameraCalibration",
        "foxglove.FrameTransform",
        "foxglove.PointCloud",
        "foxglove.SceneUpdate",
    ] {
        args.extend(["--want".to_string(), schema.to_string()]);
    }
    let client = tokio::task::spawn_blocking(move || {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        script("foxglove-client", &args)
    });
    until(60, "the Foxglove client connected", || {
        ready.exists() || client.is_finished()
    })
    .await;
    live.start_edge(EdgeConfig {
        scenario: glasshouse_sim::ScenarioKind::Two,
        ..test_edge_config(4)
    })
    .await;
    let frames = finished_frames(&live.run_to_end(180).await);
    within(160, "the Foxglove client to finish", client)
        .await
        .expect("client task");
    let seen: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&foxglove_summary).expect("summary"))
            .expect("summary JSON");
    assert_eq!(seen["ok"].as_bool(), Some(true), "{seen}");
    assert_eq!(seen["server_name"].as_str(), Some("glasshouse"), "{seen}");
    let live_fruits = fruits_after(&live, frames).await;
    live.stop().await;
    let report = script(
        "check-mcap",
        &[&dir.to_string_lossy(), "--expect-trolley", "t1"],
    );
    assert!(report.contains("check-mcap: OK"), "{report}");

    // A fresh planner hears the run's trolley info and clouds again, with their timing.
    let fresh =
        Pipeline::start_services(DashboardSettings::default(), PlannerSettings::default()).await;
    let status = Command::new(procs::bin_dir().join("glasshouse"))
        .args([
            "replay",
            &dir.to_string_lossy(),
            "--only",
            "info,roi",
            "--speed",
            "4",
        ])
        .args(["--mode", "client", "-e", &fresh.endpoint])
        .status()
        .expect("glasshouse replay runs");
    assert!(status.success());
    let replayed = fruits_after(&fresh, frames).await;
    same_fruits(&live_fruits, &replayed, 0.5);
    fresh.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_standin_ros2_node_drives_the_ros2_source() {
    let dir = temp_dir("ros2");
    let frames_dir = dir.join("frames");
    let (_, frames) = record_simulated_run(&frames_dir, 3).await;
    let bag = dir.join("bag");
    script(
        "frames-to-rosbag",
        &[&frames_dir.to_string_lossy(), &bag.to_string_lossy()],
    );

    let mut pipeline =
        Pipeline::start_services(DashboardSettings::default(), PlannerSettings::default()).await;
    // The node latches its static transform before the edge exists: the edge's transient-local
    // /tf_static subscription can only get it from the publisher's cache.
    let summary = dir.join("standin.json");
    let ready = dir.join("standin.ready");
    let endpoint = pipeline.endpoint.clone();
    let args: Vec<String> = [
        "--connect",
        &endpoint,
        "--bag",
        &bag.to_string_lossy(),
        "--static-tf",
        "--ready-file",
        &ready.to_string_lossy(),
        "--timeout-s",
        "60",
        "--linger-s",
        "8",
        "--summary",
        &summary.to_string_lossy(),
    ]
    .map(String::from)
    .to_vec();
    let standin = tokio::task::spawn_blocking(move || {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        script("ros2-standin", &args)
    });
    until(60, "the stand-in node up", || {
        ready.exists() || standin.is_finished()
    })
    .await;
    // The edge captures one frame after its last view: that one gets views but none is executed.
    let views = u32::try_from(frames - 1).unwrap();
    pipeline
        .start_edge(EdgeConfig {
            source: SourceKind::Ros2,
            ros: glasshouse_edge::RosSettings {
                trolley: recorded_trolley(&frames_dir),
                ..Default::default()
            },
            ..test_edge_config(views)
        })
        .await;
    let events = pipeline.run_to_end(180).await;
    assert_eq!(finished_frames(&events), frames);
    within(90, "the stand-in node to finish", standin)
        .await
        .expect("stand-in task");
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&summary).expect("summary")).expect("summary JSON");
    assert_eq!(
        summary["views_received"].as_u64(),
        Some(frames - 1),
        "{summary}"
    );
    assert_eq!(summary["attachment_ok"].as_bool(), Some(true), "{summary}");
    assert_eq!(
        summary["static_tf_subscribers_at_publish"].as_u64(),
        Some(0),
        "the static transform went out before the edge subscribed: {summary}"
    );
    // Our tokens: the type hashes rosbags computes, and /tf_static as transient local.
    assert_eq!(
        summary["hash_mismatches"],
        serde_json::json!([]),
        "{summary}"
    );
    assert_eq!(
        summary["qos"]["MS /tf_static"].as_str(),
        Some("1:1:1,1:,:,:,,"),
        "{summary}"
    );
    assert!(
        summary["ranked_views_received"].as_u64() >= Some(frames - 1),
        "{summary}"
    );
    let topics: Vec<&str> = summary["topics"]
        .as_array()
        .expect("topics")
        .iter()
        .filter_map(|t| t.as_str())
        .collect();
    for want in [
        "/glasshouse/next_view [geometry_msgs/msg/PoseStamped]",
        "/glasshouse/ranked_views [geometry_msgs/msg/PoseArray]",
        "/camera/color/image_raw [sensor_msgs/msg/Image]",
        "/tf [tf2_msgs/msg/TFMessage]",
    ] {
        assert!(topics.contains(&want), "{want} not in {topics:?}");
    }
    // The edge's frames came from the node: the dashboard saw them, with the recorded poses.
    let clouds = pipeline
        .fleet
        .lock()
        .unwrap()
        .trolleys
        .get("t1")
        .map_or(0, |t| t.clouds);
    assert!(clouds >= frames, "{clouds} clouds");
    pipeline.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}
