//! Recovered delivery over real Zenoh: clouds put while the router was down reach a planner's
//! subscriber after the router is back, from the detector's cache, in order; a plain
//! subscriber beside it loses them (the control that shows the fault happened).

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use glasshouse_bus::{BusArgs, Delivery, DropCounters, Publisher, Subscriber};
use glasshouse_proto::{keys, samples, RoiCloud, TrolleyStatus};
use glasshouse_tests::{client, free_port, open, within};

/// Clouds published while the router is down: fewer than the detector's cache holds.
const PUT_WHILE_DOWN: u64 = 3;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clouds_put_while_the_router_was_down_are_recovered_in_order() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let router = open(&BusArgs::router(&endpoint)).await;
    let (detector, planner) = (client(&endpoint).await, client(&endpoint).await);
    let counters = || Arc::new(DropCounters::default());
    let recovered_drops = counters();
    let recovered = Subscriber::declare(&planner, &keys::all_roi(), recovered_drops.clone())
        .await
        .expect("recovered subscriber");
    let plain =
        Subscriber::declare_with(&planner, &keys::all_roi(), Delivery::Reliable, counters())
            .await
            .expect("plain subscriber");
    let pings = Subscriber::declare(&planner, &keys::status("t1").expect("key"), counters())
        .await
        .expect("ping subscriber");
    let clouds = Publisher::declare(&detector, &keys::roi("t1", "d1").expect("key"), counters())
        .await
        .expect("cloud publisher");
    let pinger = Publisher::declare(&detector, &keys::status("t1").expect("key"), counters())
        .await
        .expect("ping publisher");
    let cloud = samples::roi_cloud();

    // 1. Clouds until one arrives: the route is up, and the first delivered is the baseline.
    let mut seq = 0;
    let first = within(30, "a first cloud", async {
        loop {
            seq += 1;
            clouds
                .publish(&samples::header(seq), &cloud)
                .await
                .expect("put");
            let got = tokio::time::timeout(Duration::from_millis(200), recovered.recv()).await;
            if let Ok(Some(got)) = got {
                return got.header.seq;
            }
        }
    })
    .await;
    drain_until(&plain, seq).await;
    while recovered.try_recv().is_some() {}

    // 2. The router goes; clouds are put with nobody to carry them.
    router.close().await.expect("router closes");
    let missed: Vec<u64> = (seq + 1..=seq + PUT_WHILE_DOWN).collect();
    for &s in &missed {
        clouds
            .publish(&samples::header(s), &cloud)
            .await
            .expect("put");
    }
    seq += PUT_WHILE_DOWN;

    // 3. The router is back: once a ping gets through, clouds again until one arrives.
    let _router = open(&BusArgs::router(&endpoint)).await;
    wait_for_ping(&pinger, &pings).await;
    let mut after = Vec::new();
    within(30, "a cloud after the restart", async {
        while after.is_empty() {
            seq += 1;
            clouds
                .publish(&samples::header(seq), &cloud)
                .await
                .expect("put");
            let got = tokio::time::timeout(Duration::from_millis(500), recovered.recv()).await;
            if let Ok(Some(got)) = got {
                after.push(got.header.seq);
            }
        }
    })
    .await;
    // The held-back cloud comes with the recovered ones: read until the last put has arrived.
    within(10, "every cloud up to the last put", async {
        while after.last() != Some(&seq) {
            after.push(recovered.recv().await.expect("a cloud").header.seq);
        }
    })
    .await;

    let expected: Vec<u64> = (first + 1..=seq).collect();
    assert_eq!(
        after, expected,
        "every cloud after the first, in order, none twice"
    );
    assert_eq!(recovered_drops.unrecovered.load(Ordering::Relaxed), 0);
    let plain_after = drain_until(&plain, seq).await;
    assert!(
        missed.iter().all(|s| !plain_after.contains(s)),
        "the plain subscriber lost the clouds put while the router was down: {plain_after:?}"
    );
}

/// Pings every 100 ms until one reaches the planner's session.
async fn wait_for_ping(pinger: &Publisher<TrolleyStatus>, pings: &Subscriber<TrolleyStatus>) {
    within(30, "a ping through the restarted router", async {
        for n in 1.. {
            pinger
                .publish(&samples::header(n), &samples::trolley_status())
                .await
                .expect("ping");
            let got = tokio::time::timeout(Duration::from_millis(100), pings.recv()).await;
            if matches!(got, Ok(Some(_))) {
                return;
            }
        }
    })
    .await;
}

/// The sequence numbers `subscriber` receives until it receives `last`.
async fn drain_until(subscriber: &Subscriber<RoiCloud>, last: u64) -> Vec<u64> {
    within(10, "the plain subscriber's clouds", async {
        let mut seqs = Vec::new();
        while seqs.last() != Some(&last) {
            seqs.push(subscriber.recv().await.expect("a cloud").header.seq);
        }
        seqs
    })
    .await
}
