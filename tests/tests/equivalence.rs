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
use glasshouse_proto::{keys, FruitEstimates, RankedViews};
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
        &keys::views("t1").expect("key"),
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
    let eval_fruits: Vec<_> = trial.fruits().iter().map(|f| f.to_message()).collect();
    assert!(!eval_fruits.is_empty(), "no fruit found");
    assert_eq!(eval_fruits, fruits.fruits);
}
