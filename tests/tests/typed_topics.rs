//! Typed topics over real Zenoh: a subscriber of `roi` receives `RoiCloud`s, and a payload of
//! another kind on that key is counted and dropped, by the typed and the untyped subscriber alike.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use glasshouse_bus::{AnySubscriber, BusArgs, Delivery, DropCounters, RawPublisher, Subscriber};
use glasshouse_proto::{encode, keys, samples, Message};
use glasshouse_tests::{client, free_port, within};

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_roi_subscriber_receives_clouds_and_drops_other_kinds() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let _router = glasshouse_bus::open(&BusArgs::router(&endpoint))
        .await
        .expect("router");
    let (sender, receiver) = (client(&endpoint).await, client(&endpoint).await);
    let key = keys::roi("t1", "d1").expect("key");
    let typed_drops = Arc::new(DropCounters::default());
    let any_drops = Arc::new(DropCounters::default());
    // Drop-oldest queues: the flood below must never block the receiving session.
    let every_detector = keys::roi_from_any("t1").expect("key");
    let typed = Subscriber::declare_with(
        &receiver,
        &every_detector,
        Delivery::Monitor,
        typed_drops.clone(),
    )
    .await
    .expect("subscriber");
    let any = AnySubscriber::declare(
        &receiver,
        keys::EVERYTHING,
        Delivery::Monitor,
        any_drops.clone(),
    )
    .await
    .expect("subscriber");
    let publisher = RawPublisher::declare(
        &sender,
        key.as_str(),
        Delivery::Reliable,
        Arc::new(DropCounters::default()),
    )
    .await
    .expect("publisher");
    let cloud = samples::roi_cloud();
    let (wrong, right) = (
        encode(&samples::header(1), &samples::arm_state()),
        encode(&samples::header(1), &cloud),
    );
    // Send rounds of (wrong kind, cloud) until the subscription has reached the sender: the first
    // cloud received comes after at least one wrong payload on the same ordered link.
    let sending = tokio::spawn(async move {
        loop {
            let _ = publisher.publish_bytes(wrong.clone()).await;
            let _ = publisher.publish_bytes(right.clone()).await;
            tokio::task::yield_now().await;
        }
    });
    let received = within(30, "a typed cloud", typed.recv())
        .await
        .expect("a cloud");
    let observed = within(30, "an untyped cloud", any.recv())
        .await
        .expect("a cloud");
    // The subscription may reach the sender between a round's two payloads: keep sending until
    // a wrong payload has been dropped by both subscribers too.
    within(30, "a wrong-kind payload dropped by both", async {
        while typed_drops.corrupt.load(Ordering::Relaxed) == 0 {
            let _ = typed.recv().await;
        }
        while any_drops.corrupt.load(Ordering::Relaxed) == 0 {
            let _ = any.recv().await;
        }
    })
    .await;
    sending.abort();

    assert_eq!(received.key, key.as_str());
    assert_eq!(received.message.world_from_camera, cloud.world_from_camera);
    assert_eq!(received.message.source_frame_seq, cloud.source_frame_seq);
    assert!(typed_drops.corrupt.load(Ordering::Relaxed) >= 1);
    assert!(matches!(observed.message, Message::RoiCloud(c) if c.roi == cloud.roi));
    assert!(any_drops.corrupt.load(Ordering::Relaxed) >= 1);
}

/// A standby copy's snapshot query carries its delta base as selector parameters: through a
/// real router the owner's queryable reads back the base that was sent, and the asker gets the
/// answer.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_snapshot_query_carries_its_delta_base_to_the_owner() {
    use glasshouse_planner::node::DeltaBase;
    use glasshouse_planner::{delta_base_of, snapshot_query_parameters};
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let _router = glasshouse_bus::open(&BusArgs::router(&endpoint))
        .await
        .expect("router");
    let (owner, standby) = (client(&endpoint).await, client(&endpoint).await);
    let key = keys::planner_snapshot("p-1", "t1").expect("key");
    let responder = glasshouse_bus::Responder::declare(&owner, &key)
        .await
        .expect("queryable");
    let base = DeltaBase {
        planner_id: "p-1".into(),
        owner_epoch: 1_790_000_000_000_000_123,
        visit: 2,
        scans: 42,
    };
    let answering = tokio::spawn(async move {
        let mut bases = Vec::new();
        while let Some(query) = responder.recv().await {
            let named = delta_base_of(&query);
            let answer = Ok((samples::header(1), samples::map_snapshot()));
            responder.reply(&query, answer).await;
            let last = named.is_none();
            bases.push(named);
            if last {
                return bases;
            }
        }
        bases
    });
    // Asked until the queryable has reached the asker, with a base and then without one.
    for parameters in [snapshot_query_parameters(&base), String::new()] {
        within(20, "an answer to the snapshot query", async {
            loop {
                let asked = glasshouse_bus::ask_with::<glasshouse_proto::MapSnapshot>(
                    &standby,
                    &key,
                    &parameters,
                    std::time::Duration::from_secs(1),
                )
                .await;
                if let Ok((_, snapshot)) = asked {
                    assert_eq!(snapshot, samples::map_snapshot());
                    return;
                }
            }
        })
        .await;
    }
    let bases = within(10, "the owner's queries", answering)
        .await
        .expect("the answering task");
    // A query asked again (a reply later than its timeout) names the same base.
    let (last, with_base) = bases.split_last().expect("queries");
    assert_eq!(*last, None);
    assert!(!with_base.is_empty() && with_base.iter().all(|b| *b == Some(base.clone())));
}
