//! (a) The four services as tasks with separate Zenoh sessions over loopback TCP: the loop closes.

use glasshouse_edge::EdgeEvent;
use std::sync::Arc;

use glasshouse_bus::{Delivery, DropCounters, Subscriber};
use glasshouse_proto::keys;
use glasshouse_tests::{client, test_edge_config, within, Pipeline};

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn loop_closes_for_six_views_and_fruits_are_published() {
    let mut pipeline = Pipeline::start(test_edge_config(6)).await;
    // An independent observer on its own session sees the fruit estimates on the bus.
    let observer = client(&pipeline.endpoint).await;
    // A drop-oldest queue: the observer reads the fruits only at the end.
    let observer_drops = Arc::new(DropCounters::default());
    let fruits_sub = Subscriber::declare_with(
        &observer,
        &keys::fruits("t1").expect("key"),
        Delivery::Monitor,
        observer_drops.clone(),
    )
    .await
    .expect("subscriber");

    let events = pipeline.run_to_end(180).await;
    let views: Vec<(u32, u64)> = events
        .iter()
        .filter_map(|e| match e {
            EdgeEvent::ViewDone {
                views_done,
                frame_seq,
                ..
            } => Some((*views_done, *frame_seq)),
            _ => None,
        })
        .collect();
    assert!(
        views.len() >= 5,
        "only {} views executed: {events:?}",
        views.len()
    );
    // Each view was planned on the frame captured after the previous move: frame → cloud →
    // views → move → new frame.
    for pair in views.windows(2) {
        assert_eq!(pair[1].0, pair[0].0 + 1);
        assert!(
            pair[1].1 > pair[0].1,
            "views not planned on fresh frames: {views:?}"
        );
    }
    assert!(matches!(
        events.last(),
        Some(EdgeEvent::Finished { views_done: 6, .. })
    ));

    let mut last_fruit_count = 0;
    while let Some(received) = fruits_sub.try_recv() {
        last_fruit_count = received.message.fruits.len();
    }
    assert_eq!(
        observer_drops
            .corrupt
            .load(std::sync::atomic::Ordering::Relaxed),
        0
    );
    assert!(
        last_fruit_count > 0,
        "no fruit estimates reached the observer"
    );

    let fleet = pipeline.fleet.lock().expect("fleet state").clone();
    let trolley = fleet.trolleys.get("t1").expect("dashboard saw trolley t1");
    assert!(trolley.frames >= 6 && trolley.clouds >= 6 && trolley.views_messages >= 6);
    assert!(!trolley.fruits.is_empty());
    assert!(trolley.map_updates >= 6);
    let corrupt = pipeline
        .planner_counters
        .drops
        .corrupt
        .load(std::sync::atomic::Ordering::Relaxed);
    assert_eq!(corrupt, 0, "clean run counted corrupt messages");
    within(10, "observer close", async { observer.close().await })
        .await
        .expect("closed");
    pipeline.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn edge_holds_still_and_reannounces_until_a_planner_answers() {
    use glasshouse_bus::{BusArgs, Shutdown};
    use std::sync::Arc;

    let endpoint = format!("tcp/127.0.0.1:{}", glasshouse_tests::free_port());
    let router = glasshouse_bus::open(&BusArgs::router(&endpoint))
        .await
        .expect("router");
    let (edge_stop, edge_shutdown) = Shutdown::new();
    let (tx, mut events) = tokio::sync::mpsc::unbounded_channel();
    let mut config = test_edge_config(2);
    config.views_timeout_ms = 300;
    let edge = tokio::spawn(glasshouse_edge::run(
        client(&endpoint).await,
        config,
        edge_shutdown,
        Some(tx),
        Arc::new(glasshouse_edge::EdgeCounters::default()),
    ));
    // Nobody plans: the edge re-announces its first frame and does not move.
    let mut reannounced = 0;
    while reannounced < 2 {
        match within(10, "a re-announcement", events.recv()).await {
            Some(EdgeEvent::Reannounced { frame_seq }) => {
                assert_eq!(frame_seq, 1, "the edge captured again without views");
                reannounced += 1;
            }
            other => panic!("unexpected event without a planner: {other:?}"),
        }
    }
    // A detector and a planner come up late; the loop starts from the re-announced frame.
    let (stop, shutdown) = Shutdown::new();
    let detector = tokio::spawn(glasshouse_detector::run(
        client(&endpoint).await,
        glasshouse_detector::DetectorSettings::default(),
        shutdown.clone(),
        Arc::new(glasshouse_detector::DetectorCounters::default()),
    ));
    let planner = tokio::spawn(glasshouse_planner::run(
        client(&endpoint).await,
        glasshouse_planner::PlannerSettings::default(),
        shutdown,
        Arc::new(glasshouse_planner::PlannerCounters::default()),
    ));
    let first_view = within(60, "the first view after planners joined", async {
        loop {
            match events.recv().await {
                Some(EdgeEvent::ViewDone { frame_seq, .. }) => return frame_seq,
                Some(_) => {}
                None => panic!("edge stopped"),
            }
        }
    })
    .await;
    assert_eq!(
        first_view, 1,
        "the first view must be planned on the re-announced frame"
    );
    edge_stop.fire();
    stop.fire();
    for task in [edge, detector, planner] {
        within(20, "service stop", task)
            .await
            .expect("task")
            .expect("service ended cleanly");
    }
    let _ = router.close().await;
}
