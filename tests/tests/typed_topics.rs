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
