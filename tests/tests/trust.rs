//! (f) Checks in the processes for peers that are on the bus but wrong: a restarted edge (a new
//! boot epoch, its frames from 1 again) keeps its map growing; a rogue RoiCloud far ahead, from
//! a source that is no detector or impersonating one, and rogue RankedViews from a planner that
//! does not own the trolley are refused and counted while the loop goes on.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use glasshouse_bus::{DropCounters, Publisher};
use glasshouse_dashboard::DashboardSettings;
use glasshouse_edge::EdgeEvent;
use glasshouse_planner::PlannerSettings;
use glasshouse_proto::keys;
use glasshouse_proto::{samples, FrameId, Header, MapSnapshot, RoiCloud};
use glasshouse_roimap::RoiMap;
use glasshouse_tests::{client, observe, test_edge_config, within, Pipeline};

/// Planner p1's copy of t1: its last integrated frame and how many scans went in.
async fn planner_map(observer: &zenoh::Session) -> (FrameId, u64) {
    let key = keys::planner_snapshot("p1", "t1").expect("key");
    let (_, snapshot): (Header, MapSnapshot) =
        glasshouse_bus::ask(observer, &key, Duration::from_secs(20))
            .await
            .expect("p1 answers with its map of t1");
    let map = RoiMap::read_snapshot(snapshot.map.as_slice()).expect("snapshot decodes");
    let last = FrameId::new(snapshot.based_on_epoch_ns, snapshot.based_on_seq);
    (last, map.scans_inserted())
}

/// Frames the edge published in its run, from its `Finished` event.
fn frames_of(events: &[EdgeEvent]) -> u64 {
    events
        .iter()
        .find_map(|e| match e {
            EdgeEvent::Finished { frames, .. } => Some(*frames),
            _ => None,
        })
        .expect("the edge finished")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_restarted_edge_keeps_the_map_growing() {
    let mut pipeline =
        Pipeline::start_services(DashboardSettings::default(), PlannerSettings::default()).await;
    let observer = client(&pipeline.endpoint).await;
    pipeline.start_edge(test_edge_config(4)).await;
    let first = frames_of(&pipeline.run_to_end(240).await);
    // The edge stops once the views on its last frame came: the planner has integrated it.
    let (before, scans_before) = planner_map(&observer).await;
    assert_eq!(before.seq, first);
    assert_eq!(scans_before, first);

    // Same trolley, new session and run: a new epoch, frames 1, 2, 3, all at or below the
    // old run's last seq, so a map ordered by seq alone would take none of them.
    pipeline.restart_edge(test_edge_config(2)).await;
    let second = frames_of(&pipeline.run_to_end(240).await);
    assert!(second <= first, "{second} frames after {first}");
    let (after, scans_after) = planner_map(&observer).await;
    eprintln!("before restart {before} ({scans_before} scans), after {after} ({scans_after})");
    assert!(after.epoch_ns > before.epoch_ns, "the new epoch is later");
    assert_eq!(after.seq, second);
    assert_eq!(
        scans_after,
        scans_before + second,
        "every new frame went in"
    );
    let _ = observer.close().await;
    pipeline.stop().await;
}

/// A header from `source` for trolley t1.
fn rogue_header(source: &str, frame: FrameId) -> Header {
    Header {
        seq: frame.seq,
        epoch_ns: frame.epoch_ns,
        trolley_id: "t1".into(),
        source_id: source.into(),
        frame_id: "world".into(),
        stamp_ns: 0,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn rogue_clouds_and_views_are_refused_and_the_loop_goes_on() {
    let mut pipeline =
        Pipeline::start_services(DashboardSettings::default(), PlannerSettings::default()).await;
    let observer = client(&pipeline.endpoint).await;
    let clouds = observe(&observer, &keys::roi_from_any("t1").expect("key")).await;
    let statuses = observe(&observer, &keys::planner_status("p1").expect("key")).await;
    pipeline.start_edge(test_edge_config(6)).await;
    let attacker = client(&pipeline.endpoint).await;
    let drops = Arc::new(DropCounters::default());
    // An unsecured bus: the attacker may put on any key, its own or the real detector's.
    let mut roi = Vec::new();
    for source in ["rogue", "d1"] {
        let key = keys::roi("t1", source).expect("key");
        let publisher = Publisher::declare(&attacker, &key, drops.clone())
            .await
            .expect("publisher");
        roi.push((source, publisher));
    }
    let views = Publisher::declare(&attacker, &keys::views("t1", "p9").expect("key"), drops)
        .await
        .expect("publisher");
    // The loop went round once: every service has subscribed. The edge's epoch comes with
    // its frames' clouds.
    let epoch_ns = within(240, "a real cloud", clouds.recv())
        .await
        .expect("cloud")
        .message
        .source_frame_epoch_ns;
    within(240, "the first view", async {
        while !matches!(
            pipeline.events.recv().await,
            Some(EdgeEvent::ViewDone { .. })
        ) {}
    })
    .await;

    let far = FrameId::new(epoch_ns, 1_000_000_000_000);
    let rogue_cloud = RoiCloud {
        source_frame_seq: far.seq,
        source_frame_epoch_ns: far.epoch_ns,
        ..samples::roi_cloud()
    };
    // From a source that is no detector, then impersonating the real one.
    for (source, publisher) in &roi {
        let header = rogue_header(source, far);
        publisher
            .publish(&header, &rogue_cloud)
            .await
            .expect("queued");
    }
    let mut rogue_views = samples::ranked_views();
    rogue_views.based_on_epoch_ns = epoch_ns;
    rogue_views.planner_id = "p9".into();
    // Claiming the newest ownership term there can be: refused all the same (p9 is not the
    // owner), and the edge does not take that epoch up (the real owner's views would all be
    // stale after it and the loop would stop).
    rogue_views.owner_epoch = u64::MAX;
    let header = rogue_header("p9", FrameId::new(epoch_ns, 2));
    views.publish(&header, &rogue_views).await.expect("queued");

    let (mut refused_from, mut views_after) = (None, 0);
    let events = within(240, "the loop to finish after the rogues", async {
        let mut events = Vec::new();
        while let Some(event) = pipeline.events.recv().await {
            match &event {
                EdgeEvent::ViewsRefused { source_id, .. } => refused_from = Some(source_id.clone()),
                EdgeEvent::ViewDone { .. } => views_after += 1,
                EdgeEvent::Finished { .. } => {
                    events.push(event);
                    break;
                }
                _ => {}
            }
            events.push(event);
        }
        events
    })
    .await;
    assert_eq!(refused_from.as_deref(), Some("p9"));
    assert!(pipeline.edge_counters.refused_views.load(Ordering::Relaxed) >= 1);
    let stale = &pipeline.edge_counters.drops.stale_epoch;
    assert_eq!(stale.load(Ordering::Relaxed), 0);
    assert!(
        views_after >= 4,
        "only {views_after} views after the rogues"
    );
    // The map took every real frame and none of the rogue's.
    let frames = frames_of(&events);
    let (last, scans) = planner_map(&observer).await;
    assert_eq!(last, FrameId::new(epoch_ns, frames));
    assert_eq!(scans, frames);
    // Both rogue clouds are refused and counted (the one without a detector token once its
    // wait for a token is over).
    within(30, "the planner to report both refusals", async {
        loop {
            let status = statuses.recv().await.expect("status").message;
            if status.refused_clouds >= 2 {
                return;
            }
        }
    })
    .await;
    assert_eq!(
        pipeline
            .planner_counters
            .clouds_refused
            .load(Ordering::Relaxed),
        2
    );
    for (_, publisher) in roi {
        publisher.close().await;
    }
    views.close().await;
    let _ = attacker.close().await;
    let _ = observer.close().await;
    pipeline.stop().await;
}
