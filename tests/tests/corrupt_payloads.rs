//! (c) Corrupt, truncated and mislabelled payloads on every key are counted and dropped while the
//! pipeline keeps running.

use std::sync::atomic::Ordering;

use glasshouse_bus::{Delivery, DropCounters, RawPublisher};
use glasshouse_edge::EdgeEvent;
use glasshouse_proto::keys::{self, TrolleyTopic};
use glasshouse_proto::{encode_any, samples, MessageKind};
use glasshouse_tests::{client, test_edge_config, within, Pipeline};
use rand::{Rng, SeedableRng};
use std::sync::Arc;

/// Bad payloads for a key that expects `kind`: garbage, every kind truncated, another kind.
fn bad_payloads(kind: MessageKind, rng: &mut rand_chacha::ChaCha8Rng) -> Vec<Vec<u8>> {
    let valid = encode_any(&samples::header(1), &samples::message(kind));
    let other = if kind == MessageKind::ArmState {
        MessageKind::TrolleyStatus
    } else {
        MessageKind::ArmState
    };
    let mut flipped = valid.clone();
    // Break the root offset so the verifier must reject it.
    flipped[0] ^= 0x5a;
    flipped[1] ^= 0xa5;
    vec![
        (0..64).map(|_| rng.gen()).collect(),
        Vec::new(),
        valid[..valid.len() / 2].to_vec(),
        valid[..9].to_vec(),
        flipped,
        encode_any(&samples::header(1), &samples::message(other)),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn bad_payloads_on_every_key_are_dropped_and_the_loop_goes_on() {
    let mut pipeline = Pipeline::start(test_edge_config(6)).await;
    let attacker = client(&pipeline.endpoint).await;
    let counters = Arc::new(DropCounters::default());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let mut targets: Vec<(String, MessageKind)> = TrolleyTopic::ALL
        .iter()
        .map(|t| {
            (
                keys::trolley_from("t1", *t, "x9").expect("key"),
                t.message_kind(),
            )
        })
        .collect();
    targets.push((
        keys::planner_status("p9").expect("key").to_string(),
        MessageKind::PlannerStatus,
    ));
    targets.push((
        keys::detector_status("d9").expect("key").to_string(),
        MessageKind::DetectorStatus,
    ));
    targets.push((keys::fleet_fruits().to_string(), MessageKind::FleetFruits));
    let mut publishers = Vec::new();
    for (key, kind) in &targets {
        let p = RawPublisher::declare(&attacker, key, Delivery::Reliable, counters.clone())
            .await
            .expect("publisher");
        publishers.push((p, *kind));
    }
    // Inject while the loop runs: after the first view (every service has subscribed by then:
    // the loop went round once), after the second and after the third, so the edge (six views)
    // is still running when the last round arrives.
    let mut sent = 0;
    let mut views = 0;
    let mut rounds = 0;
    within(240, "the loop to finish under fire", async {
        loop {
            if rounds < views && rounds < 3 {
                for (p, kind) in &publishers {
                    for bytes in bad_payloads(*kind, &mut rng) {
                        p.publish_bytes(bytes).await.expect("queued");
                        sent += 1;
                    }
                }
                rounds += 1;
            }
            match pipeline.events.recv().await {
                Some(EdgeEvent::ViewDone { .. }) => views += 1,
                Some(EdgeEvent::Finished { .. }) | None => break,
                Some(_) => {}
            }
        }
    })
    .await;
    assert_eq!(rounds, 3);
    assert!(views >= 5, "only {views} views under fire");
    assert!(sent > 150);

    let corrupt = |c: &DropCounters| c.corrupt.load(Ordering::Relaxed);
    // Each service subscribes to some of the keys and must have dropped what it got there.
    let edge = corrupt(&pipeline.edge_counters.drops);
    let detector = corrupt(&pipeline.detector_counters.drops);
    let planner = corrupt(&pipeline.planner_counters.drops);
    let dashboard = corrupt(&pipeline.dashboard_counters.drops);
    // 3 rounds x 6 bad payloads per key; the edge hears views, the detector frames, the planner
    // clouds + info (+ arm, a stream that may skip some), the dashboard everything but streams.
    assert_eq!(edge, 18, "edge dropped {edge}");
    assert!(detector >= 1, "detector dropped {detector}");
    assert!(planner >= 36, "planner dropped {planner}");
    assert!(dashboard >= 18 * 9, "dashboard dropped {dashboard}");

    let fleet = pipeline.fleet.lock().expect("fleet").clone();
    assert!(
        !fleet.trolleys["t1"].fruits.is_empty(),
        "fruits lost under fire"
    );
    for (p, _) in publishers {
        p.close().await;
    }
    let _ = attacker.close().await;
    pipeline.stop().await;
}
