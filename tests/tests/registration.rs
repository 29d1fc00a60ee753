//! The planner reports its registration of each cloud on the wire: with registration on, every
//! frame's MapUpdate carries how its cloud was registered (frame id, verdict, correction), the
//! planner's status the totals, and the dashboard shows the last one.

use std::collections::BTreeSet;
use std::sync::Arc;

use glasshouse_bus::{Delivery, DropCounters, Subscriber};
use glasshouse_dashboard::DashboardSettings;
use glasshouse_edge::EdgeEvent;
use glasshouse_planner::PlannerSettings;
use glasshouse_proto::{keys, MapUpdate, PlannerStatus, RegistrationReason, RegistrationVerdict};
use glasshouse_tests::{client, test_edge_config, within, Pipeline};

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn every_frame_reports_its_registration_and_the_status_counts_them() {
    let mut planner = PlannerSettings::default();
    planner.planning.registration.enabled = true;
    let pid = planner.planner_id.clone();
    let mut pipeline = Pipeline::start_services(DashboardSettings::default(), planner).await;
    let observer = client(&pipeline.endpoint).await;
    let drops = Arc::new(DropCounters::default());
    let maps = Subscriber::<MapUpdate>::declare_with(
        &observer,
        &keys::map("t1").expect("key"),
        Delivery::Monitor,
        drops.clone(),
    )
    .await
    .expect("map subscriber");
    let status = Subscriber::<PlannerStatus>::declare_with(
        &observer,
        &keys::planner_status(&pid).expect("key"),
        Delivery::Monitor,
        drops,
    )
    .await
    .expect("status subscriber");
    pipeline.start_edge(test_edge_config(4)).await;
    let events = pipeline.run_to_end(240).await;
    let Some(EdgeEvent::Finished { frames, .. }) = events.last() else {
        panic!("the edge did not finish: {events:?}")
    };
    let frames = *frames;

    // Each frame's cloud is registered once; its update says so, for its own frame.
    let mut registered = Vec::new();
    within(30, "every frame's registration", async {
        while registered.len() < frames as usize {
            let m = maps.recv().await.expect("map update").message;
            if let Some(r) = m.registration {
                assert_eq!(r.frame.seq, m.based_on_seq, "{r:?}");
                assert!(r.frame.epoch_ns > 0, "{r:?}");
                registered.push(r);
            }
        }
    })
    .await;
    let seqs: BTreeSet<u64> = registered.iter().map(|r| r.frame.seq).collect();
    assert_eq!(seqs, (1..=frames).collect(), "{registered:?}");
    assert_eq!(
        (registered[0].verdict, registered[0].reason),
        (
            RegistrationVerdict::Skipped,
            RegistrationReason::MapTooSmall
        ),
        "the first cloud meets an empty map"
    );
    // An estimate comes with the figures it was judged by.
    for r in registered.iter().filter(|r| r.world_correction.is_some()) {
        assert!(r.rotation_deg.is_some() && r.iterations.is_some(), "{r:?}");
    }

    let totals = within(10, "a status counting every frame", async {
        loop {
            let s = status.recv().await.expect("status").message;
            if s.registrations.total() >= frames {
                return s.registrations;
            }
        }
    })
    .await;
    assert_eq!(totals.total(), frames, "{totals:?}");

    // The dashboard shows the last frame's registration and the same totals.
    let fleet = pipeline.fleet.clone();
    within(10, "the dashboard to show the totals", async {
        loop {
            let shown = fleet
                .lock()
                .expect("fleet state")
                .planners
                .get(&pid)
                .map(|p| p.registrations);
            if shown == Some(totals) {
                break;
            }
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        }
    })
    .await;
    let fleet = fleet.lock().expect("fleet state").clone();
    let last = fleet.trolleys["t1"].last_registration.clone();
    assert_eq!(last.map(|r| r.frame.seq), Some(frames));
    pipeline.stop().await;
}
