//! The experiments and the services run the same steps: one seeded trial through `glasshouse-eval`
//! and the same seed through the services over real Zenoh plan the same views (poses and
//! utilities, frame by frame) and end with the same fruits.

use std::collections::BTreeMap;
use std::sync::Arc;

use glasshouse_bus::{Delivery, DropCounters, Subscriber};
use glasshouse_dashboard::DashboardSettings;
use glasshouse_edge::{EdgeConfig, EdgeEvent};
use glasshouse_eval::{ComputeTime, Trial, TrialConfig};
use glasshouse_nbv::Method;
use glasshouse_planner::PlannerSettings;
use glasshouse_proto::{decode_typed, encode, keys, samples, FruitEstimates, RankedViews};
use glasshouse_sim::ScenarioKind;
use glasshouse_tests::{client, within, Pipeline};

const SEED: u64 = 3;
const VIEWS: u32 = 6;
const WIDTH: u32 = 160;
const HEIGHT: u32 = 120;

/// What the services published: views per frame (a re-announced frame may be planned twice,
/// identically) and the fruits of the last frame.
async fn run_services() -> (BTreeMap<u64, RankedViews>, FruitEstimates) {
    let mut planner = PlannerSettings::default();
    planner.planning.method = Method::OursUu;
    planner.planning.seed = SEED;
    let mut pipeline = Pipeline::start_services(DashboardSettings::default(), planner).await;
    let observer = client(&pipeline.endpoint).await;
    let drops = Arc::new(DropCounters::default());
    let views = Subscriber::<RankedViews>::declare_with(
        &observer,
        &keys::views_from_any("t1").expect("key"),
        Delivery::Monitor,
        drops.clone(),
    )
    .await
    .expect("views subscriber");
    let fruits = Subscriber::<FruitEstimates>::declare_with(
        &observer,
        &keys::fruits("t1").expect("key"),
        Delivery::Monitor,
        drops,
    )
    .await
    .expect("fruits subscriber");
    pipeline
        .start_edge(EdgeConfig {
            scenario: ScenarioKind::Two,
            seed: SEED,
            width: WIDTH,
            height: HEIGHT,
            max_views: VIEWS,
            ..EdgeConfig::default()
        })
        .await;
    let events = pipeline.run_to_end(240).await;
    let Some(EdgeEvent::Finished { frames, .. }) = events.last() else {
        panic!("the edge did not finish: {events:?}")
    };
    let frames = *frames;
    let mut by_frame: BTreeMap<u64, RankedViews> = BTreeMap::new();
    let mut last_fruits = None;
    within(30, "the last frame's views and fruits", async {
        while by_frame.len() < frames as usize {
            let views = views.recv().await.expect("views").message;
            if let Some(earlier) = by_frame.get(&views.based_on_seq) {
                assert_same_views(earlier, &views, "a frame planned twice");
            }
            by_frame.insert(views.based_on_seq, views);
        }
        while last_fruits
            .as_ref()
            .is_none_or(|f: &FruitEstimates| f.based_on_seq < frames)
        {
            last_fruits = Some(fruits.recv().await.expect("fruits").message);
        }
    })
    .await;
    let _ = observer.close().await;
    pipeline.stop().await;
    (by_frame, last_fruits.expect("fruits"))
}

fn assert_same_views(a: &RankedViews, b: &RankedViews, what: &str) {
    let seq = a.based_on_seq;
    assert_eq!(a.views.len(), b.views.len(), "{what}: frame {seq}");
    for (i, (x, y)) in a.views.iter().zip(&b.views).enumerate() {
        assert_eq!(
            x.world_from_camera, y.world_from_camera,
            "{what}: frame {seq} view {i}"
        );
        assert_eq!(x.utility, y.utility, "{what}: frame {seq} view {i}");
        assert_eq!(x.kind, y.kind, "{what}: frame {seq} view {i}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn eval_and_the_services_plan_the_same_views_and_find_the_same_fruits() {
    let (services, fruits) = run_services().await;
    let frames = services.len();
    assert!(frames > VIEWS as usize / 2, "only {frames} frames");

    let config = TrialConfig {
        width: WIDTH,
        height: HEIGHT,
        budget_s: 10_000.0,
        compute_time: ComputeTime::Fixed { ms: 100.0 },
        ..TrialConfig::new(ScenarioKind::Two, Method::OursUu, SEED)
    };
    let mut trial = Trial::new(config).expect("trial");
    while trial.plans().len() < frames {
        assert!(trial.step().expect("trial step"), "the trial ended early");
    }
    for (plan, (seq, published)) in trial.plans().iter().zip(&services) {
        assert_eq!(plan.based_on_seq, *seq);
        assert!(!plan.views.is_empty());
        assert_same_views(published, plan, "eval against the services");
    }
    // The trial's fruits as they travel (the wire carries `f32`).
    let sent = FruitEstimates {
        fruits: trial.fruits().to_vec(),
        ..fruits.clone()
    };
    let bytes = encode(&samples::header(0), &sent);
    let (_, eval_fruits) = decode_typed::<FruitEstimates>(&bytes).expect("the trial's fruits");
    assert!(!eval_fruits.fruits.is_empty(), "no fruit found");
    // Debug text: equal bit for bit, NaN residuals of box fallbacks included.
    assert_eq!(
        format!("{:?}", eval_fruits.fruits),
        format!("{:?}", fruits.fruits)
    );
}

#[test]
fn the_dashboard_and_the_experiments_give_the_same_covered_volume() {
    use glasshouse_sim::FruitTruth;
    use nalgebra::{Point3, Vector3};

    // Truths of a scene and estimates around them: one exact, one shifted by half a voxel and
    // shrunk, one on a voxel boundary, one false.
    let truths = [
        FruitTruth::ellipsoid(
            1,
            Point3::new(0.105, 0.0, 1.0),
            Vector3::new(0.03, 0.025, 0.04),
        ),
        FruitTruth::ellipsoid(2, Point3::new(0.5, 0.2, 0.8), Vector3::repeat(0.035)),
        FruitTruth::ellipsoid(
            3,
            Point3::new(-0.3, 0.1, 1.2),
            Vector3::new(0.02, 0.03, 0.025),
        ),
    ];
    let around = |t: &FruitTruth, shift: f64, shrink: f64| {
        let c = t.centre + Vector3::repeat(shift);
        let h = t.half_extents_m * shrink;
        glasshouse_nbv::FruitEstimate::from_box(t.id, c, c - h, c + h)
    };
    let estimates = [
        around(&truths[0], 0.0, 1.0),
        around(&truths[1], 0.005, 0.8),
        around(&truths[2], 0.01, 1.1),
        around(&truths[2], 1.0, 1.0),
    ];
    let resolution_m = 0.01;
    let experiments = glasshouse_eval::evaluate(&estimates, &truths, resolution_m).covered_volume;
    let truth_estimates: Vec<_> = truths.iter().map(|t| t.estimate(resolution_m)).collect();
    let dashboard = glasshouse_dashboard::covered_volume(&estimates, &truth_estimates);
    assert!(experiments > 0.3 && experiments < 1.0, "{experiments}");
    assert_eq!(dashboard, Some(experiments));
    assert_eq!(
        resolution_m,
        glasshouse_dashboard::COVERED_VOLUME_RESOLUTION_M
    );
}
