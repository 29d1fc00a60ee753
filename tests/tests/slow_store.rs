//! A slow disk holds a trolley's views, not the planner. With every store write taking 1.2 s
//! (`store.write_delay_ms`, the planner's fault injection), what must hold: the views planned on
//! a cloud go out only after its write (never sooner than the delay after the cloud), and while
//! a cloud waits for its write the planner keeps publishing its status (every 100 ms here). A
//! planner that awaited each write in its event loop published no status in that window.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use glasshouse_dashboard::DashboardSettings;
use glasshouse_edge::EdgeEvent;
use glasshouse_planner::{PlannerSettings, StoreSettings};
use glasshouse_proto::keys;
use glasshouse_tests::{client, observe, test_edge_config, within, Pipeline};

const WRITE_DELAY: Duration = Duration::from_millis(1200);

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_slow_store_holds_the_views_not_the_planner() {
    let dir = std::env::temp_dir().join(format!("glasshouse-slow-store-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("store dir");
    let planner = PlannerSettings {
        status_period_ms: 100,
        store: Some(StoreSettings {
            path: dir.join("p1.redb"),
            settle_ms: 200,
            write_delay_ms: WRITE_DELAY.as_millis() as u64,
            ..StoreSettings::default()
        }),
        ..PlannerSettings::default()
    };
    let pid = planner.planner_id.clone();
    let mut pipeline = Pipeline::start_services(DashboardSettings::default(), planner).await;
    let observer = client(&pipeline.endpoint).await;
    let clouds = observe(&observer, &keys::roi_from_any("t1").expect("key")).await;
    let views = observe(&observer, &keys::views_from_any("t1").expect("key")).await;
    let status = observe(&observer, &keys::planner_status(&pid).expect("key")).await;

    // Arrival times: each frame's first cloud, each frame's first views, every status.
    let (stop, mut stopped) = tokio::sync::oneshot::channel::<()>();
    let collector = tokio::spawn(async move {
        let (mut cloud_at, mut views_at) = (BTreeMap::new(), BTreeMap::new());
        let mut status_at = Vec::new();
        loop {
            tokio::select! {
                c = clouds.recv() => {
                    let Some(c) = c else { break };
                    cloud_at.entry(c.message.source_frame().seq).or_insert(c.arrived_at);
                }
                v = views.recv() => {
                    let Some(v) = v else { break };
                    views_at.entry(v.message.based_on_seq).or_insert(v.arrived_at);
                }
                s = status.recv() => {
                    let Some(s) = s else { break };
                    status_at.push(s.arrived_at);
                }
                _ = &mut stopped => break,
            }
        }
        (cloud_at, views_at, status_at)
    });
    pipeline.start_edge(test_edge_config(3)).await;
    let events = pipeline.run_to_end(180).await;
    assert!(
        matches!(events.last(), Some(EdgeEvent::Finished { .. })),
        "{events:?}"
    );
    let _ = stop.send(());
    let (cloud_at, views_at, status_at) = within(30, "the collector", collector)
        .await
        .expect("collector task");
    assert!(views_at.len() >= 3, "views for {views_at:?}");

    let mut statuses_while_held = Vec::new();
    for (seq, views) in &views_at {
        let cloud: &Instant = cloud_at
            .get(seq)
            .unwrap_or_else(|| panic!("views on frame {seq} without its cloud"));
        let held = views.saturating_duration_since(*cloud);
        // The write starts at the earliest when the cloud arrives and takes the delay: views
        // sooner than that went out before their cloud was stored. (50 ms: the observer and the
        // planner receive the cloud at slightly different times.)
        assert!(
            held + Duration::from_millis(50) >= WRITE_DELAY,
            "views on frame {seq} {held:?} after its cloud: before it was stored"
        );
        let statuses = status_at
            .iter()
            .filter(|at| *at > cloud && *at < views)
            .count();
        statuses_while_held.push((seq, held, statuses));
    }
    // Each window is at least 1.2 s, twelve status periods: the planner's loop went on.
    for (seq, held, statuses) in &statuses_while_held {
        assert!(
            *statuses >= 4,
            "frame {seq}: {statuses} statuses in the {held:?} its views waited for the store \
             (all: {statuses_while_held:?})"
        );
    }
    let held = pipeline
        .planner_counters
        .publications_held
        .load(std::sync::atomic::Ordering::Relaxed);
    assert!(held >= 3, "{held} publications held");
    let counters = &pipeline.planner_counters;
    let load = |c: &std::sync::atomic::AtomicU64| c.load(std::sync::atomic::Ordering::Relaxed);
    let (writes, transactions) = (
        load(&counters.store_writes),
        load(&counters.store_transactions),
    );
    assert!(
        transactions >= 1 && writes >= transactions,
        "{writes} writes in {transactions} transactions"
    );
    assert_eq!(load(&counters.store_errors), 0);
    pipeline.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}
