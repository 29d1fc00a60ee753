//! The detector service with the committed ONNX fruit model, over real Zenoh sessions: a
//! trolley of unripe green fruit gets ROI clouds with the model's confidences, where the HSI
//! rule finds no fruit on the same frames.

use std::path::PathBuf;
use std::sync::Arc;

use glasshouse_bus::{BusArgs, DropCounters, Shutdown, Subscriber};
use glasshouse_detector::{DetectorCounters, DetectorSettings};
use glasshouse_proto::{keys, RoiCloud};
use glasshouse_sim::{FruitColour, ScenarioKind};
use glasshouse_tests::{client, free_port, test_edge_config, within};

fn committed_model() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../detector-service/model/fruit-segmenter.onnx")
}

/// The first cloud of trolley t1 from detector `did`, run with `fruit_model`, on a green-fruit
/// scenario-2 trolley.
async fn first_green_cloud(did: &str, fruit_model: Option<PathBuf>) -> RoiCloud {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let router = glasshouse_bus::open(&BusArgs::router(&endpoint))
        .await
        .expect("router");
    let observer = client(&endpoint).await;
    let clouds = Subscriber::<RoiCloud>::declare(
        &observer,
        &keys::roi_from_any("t1").expect("key"),
        Arc::new(DropCounters::default()),
    )
    .await
    .expect("subscriber");
    let (stop, shutdown) = Shutdown::new();
    let settings = DetectorSettings {
        detector_id: did.into(),
        fruit_model,
        ..DetectorSettings::default()
    };
    let detector = tokio::spawn(glasshouse_detector::run(
        client(&endpoint).await,
        settings,
        shutdown.clone(),
        Arc::new(DetectorCounters::default()),
    ));
    let mut edge_config = test_edge_config(1);
    edge_config.scenario = ScenarioKind::Two;
    edge_config.seed = 11;
    edge_config.world.scene.fruit_colour = FruitColour::Green;
    edge_config.width = 320;
    edge_config.height = 240;
    let edge = tokio::spawn(glasshouse_edge::run(
        client(&endpoint).await,
        edge_config,
        shutdown,
        None,
        Arc::new(glasshouse_edge::EdgeCounters::default()),
    ));
    let cloud = within(60, "the first ROI cloud", clouds.recv())
        .await
        .expect("a cloud");
    stop.fire();
    for task in [detector, edge] {
        within(20, "services to stop", task)
            .await
            .expect("no panic")
            .expect("clean stop");
    }
    drop(clouds);
    let _ = observer.close().await;
    let _ = router.close().await;
    cloud.message
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_learned_detector_finds_green_fruit_and_sends_its_confidence() {
    let learned = first_green_cloud("d1", Some(committed_model())).await;
    let roi = learned.roi.iter().filter(|&&r| r).count();
    assert!(roi >= 20, "{roi} ROI points from the model");
    assert_eq!(learned.roi_confidence.len(), learned.points_in_world.len());
    for (&r, &c) in learned.roi.iter().zip(&learned.roi_confidence) {
        assert_eq!(r, c >= 128, "roi {r} with confidence {c}");
    }

    let hsi = first_green_cloud("d2", None).await;
    let hsi_roi = hsi.roi.iter().filter(|&&r| r).count();
    assert!(
        hsi_roi * 20 <= roi,
        "HSI {hsi_roi} against the model's {roi}"
    );
    // The colour rule's pixel votes are confidences too.
    assert_eq!(hsi.roi_confidence.len(), hsi.points_in_world.len());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_detector_with_a_missing_model_fails_at_start_with_the_path() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let router = glasshouse_bus::open(&BusArgs::router(&endpoint))
        .await
        .expect("router");
    let (_stop, shutdown) = Shutdown::new();
    let settings = DetectorSettings {
        fruit_model: Some("no/such/model.onnx".into()),
        ..DetectorSettings::default()
    };
    let result = within(
        20,
        "the detector to give up",
        glasshouse_detector::run(
            client(&endpoint).await,
            settings,
            shutdown,
            Arc::new(DetectorCounters::default()),
        ),
    )
    .await;
    let message = format!("{:#}", result.expect_err("a missing model is an error"));
    assert!(message.contains("no/such/model.onnx"), "{message}");
    let _ = router.close().await;
}
