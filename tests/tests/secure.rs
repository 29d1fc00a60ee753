//! A deployment secured by `glasshouse secure`: the fleet runs over mutual TLS through a router
//! with the generated ACL, while a rogue tries what its certificate does not allow
//! (`glasshouse_bus::probe`, the same attempts `glasshouse secure probe` and the compose rig's
//! rogue container make), and a compromised detector and planner send clouds and views for a
//! trolley they do not serve, which the planner and the edge refuse. A second test shows the
//! probe reports what a router without the ACL lets through.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use glasshouse_bus::probe::{probe, Attempt, ProbeSetup};
use glasshouse_bus::{declare_alive, live_members, BusArgs};
use glasshouse_dashboard::DashboardSettings;
use glasshouse_edge::EdgeEvent;
use glasshouse_planner::PlannerSettings;
use glasshouse_proto::keys::MemberKind;
use glasshouse_tests::procs::{bin_dir, build_binaries};
use glasshouse_tests::{free_port, open, test_edge_config, within, FleetSessions, Pipeline};
use serde_json::Value;
use std::sync::atomic::Ordering;

fn glasshouse(args: &[&str]) {
    let out = Command::new(bin_dir().join("glasshouse"))
        .args(args)
        .output()
        .expect("glasshouse runs");
    assert!(
        out.status.success(),
        "glasshouse {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn config_of(pki: &Path, name: &str) -> PathBuf {
    pki.join(format!("{name}.json5"))
}

fn identity(pki: &Path, name: &str) -> BusArgs {
    BusArgs {
        zenoh_config: Some(config_of(pki, name)),
        ..BusArgs::default()
    }
}

/// A deployment's PKI in `dir/pki` (trolley-t2 issued later, signed by the same CA) and a
/// foreign one in `dir/other`, for a router on `endpoint`.
fn make_pkis(dir: &Path, endpoint: &str) -> (PathBuf, PathBuf) {
    let _ = std::fs::remove_dir_all(dir);
    let (pki, other) = (dir.join("pki"), dir.join("other"));
    let (out, other_out) = (pki.to_string_lossy(), other.to_string_lossy());
    let common = ["--router-endpoint", endpoint];
    glasshouse(
        &[
            &[
                "secure",
                "init",
                "--out",
                &out,
                "--trolleys",
                "t1",
                "--planners",
                "p1,p2",
            ],
            // d1 serves t1 beside d3 (d3 ranks below it for t1), p1 owns t1 alone.
            &["--detectors", "d1,d3", "--dashboards", "web1"][..],
            &common[..],
        ]
        .concat(),
    );
    glasshouse(&["secure", "issue", "--out", &out, "--trolley", "t2"]);
    glasshouse(
        &[
            &["secure", "init", "--out", &other_out, "--trolleys", "t1"][..],
            &common,
        ]
        .concat(),
    );
    (pki, other)
}

/// trolley-t2 acts on t1's keys; dashboard-web1 watches.
fn probe_setup(
    dir: &Path,
    pki: &Path,
    other: &Path,
    snapshot_control: Option<PathBuf>,
) -> ProbeSetup {
    ProbeSetup {
        rogue: config_of(pki, "trolley-t2"),
        rogue_trolley: "t2".into(),
        victim: "t1".into(),
        observer: config_of(pki, "dashboard-web1"),
        planners: vec!["p1".into()],
        snapshot_control,
        detectors: ["d1", "d3"]
            .map(|d| (d.to_owned(), config_of(pki, &format!("detector-{d}"))))
            .to_vec(),
        planner_identities: ["p1", "p2"]
            .map(|p| (p.to_owned(), config_of(pki, &format!("planner-{p}"))))
            .to_vec(),
        foreign_key: other.join("trolley-t1.key"),
        foreign_cert: other.join("trolley-t1.pem"),
        scratch: dir.join("probe"),
        timeout: Duration::from_secs(10),
        link_timeout: Duration::from_secs(60),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn only_the_roster_may_do_its_part() {
    build_binaries();
    let dir = std::env::temp_dir().join(format!("glasshouse-secure-{}", std::process::id()));
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let (pki, other) = make_pkis(&dir, &endpoint);
    let sessions = FleetSessions {
        endpoint: endpoint.clone(),
        router: BusArgs {
            listen: vec![endpoint.clone()],
            ..identity(&pki, "router")
        },
        dashboard: identity(&pki, "dashboard-web1"),
        detector: identity(&pki, "detector-d1"),
        planner: identity(&pki, "planner-p1"),
        edge: identity(&pki, "trolley-t1"),
    };
    let mut pipeline = Pipeline::start_services_on(
        sessions,
        DashboardSettings::default(),
        PlannerSettings::new("p1"),
    )
    .await;
    // The edge runs until stopped: the compromised planner's views need frames to aim at.
    pipeline.start_edge(test_edge_config(0)).await;
    // A second live detector, d3, which serves other trolleys than t1.
    assert_eq!(
        glasshouse_fleet::first_ranked("t1", ["d1", "d3"]),
        Some("d1")
    );
    let d3 = open(&identity(&pki, "detector-d3")).await;
    let _d3_alive = declare_alive(&d3, MemberKind::Detector, "d3")
        .await
        .expect("token");

    // A detector may ask the router for the members it watches (the check of a leave), and
    // only those: the planners' tokens are not for it.
    within(20, "d3's query finds trolley t1", async {
        while live_members(&d3, MemberKind::Trolley).await != ["t1"] {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;
    assert_eq!(live_members(&d3, MemberKind::Detector).await, ["d1", "d3"]);
    assert!(live_members(&d3, MemberKind::Planner).await.is_empty());

    let setup = probe_setup(&dir, &pki, &other, Some(config_of(&pki, "planner-p2")));
    let attempts = within(300, "the probe", probe(&setup))
        .await
        .expect("the probe judges every attempt");
    assert!(attempts.len() >= 18, "too few attempts: {attempts:?}");
    let compromised = attempts.iter().filter(|a| a.what.contains("claiming"));
    assert_eq!(compromised.count(), 4, "{attempts:?}");
    let holes: Vec<&Attempt> = attempts.iter().filter(|a| a.accepted).collect();
    assert!(
        holes.is_empty(),
        "the deployment let these through: {holes:?}"
    );
    // The forged clouds were counted as not from t1's detector, the forged views as refused.
    let status = pipeline
        .planner_counters
        .status
        .lock()
        .expect("status")
        .clone();
    let unassigned = status.map_or(0, |s| s.unassigned_clouds);
    assert!(unassigned >= 2, "{unassigned} clouds counted unassigned");
    let refused = pipeline.edge_counters.refused_views.load(Ordering::Relaxed);
    assert!(refused >= 2, "{refused} views refused");

    let views = within(240, "three views after the probe", async {
        let mut views = 0;
        while views < 3 {
            if let Some(EdgeEvent::ViewDone { .. }) = pipeline.events.recv().await {
                views += 1;
            }
        }
        views
    })
    .await;
    assert!(views >= 3);
    let fleet = pipeline.fleet.lock().expect("fleet state").clone();
    let trolley = fleet
        .trolleys
        .get("t1")
        .expect("the dashboard saw trolley t1");
    assert!(!trolley.fruits.is_empty(), "no fruit found");
    assert!(!fleet.trolleys.contains_key("t2") || fleet.trolleys["t2"].views_messages == 0);
    let _ = d3.close().await;
    pipeline.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_probe_reports_what_a_router_without_the_acl_lets_through() {
    build_binaries();
    let dir = std::env::temp_dir().join(format!("glasshouse-open-acl-{}", std::process::id()));
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let (pki, other) = make_pkis(&dir, &endpoint);
    // The same mTLS router with its access control switched off.
    let text = std::fs::read_to_string(config_of(&pki, "router")).expect("router config");
    let mut config: Value = json5::from_str(&text).expect("JSON5");
    config["access_control"]["enabled"] = false.into();
    let open_router = dir.join("router-open.json5");
    std::fs::write(&open_router, config.to_string()).expect("write");
    let router = open(&BusArgs {
        zenoh_config: Some(open_router),
        listen: vec![endpoint],
        ..BusArgs::default()
    })
    .await;
    // No fleet runs here: no compromised services to play.
    let setup = ProbeSetup {
        detectors: Vec::new(),
        planner_identities: Vec::new(),
        ..probe_setup(&dir, &pki, &other, None)
    };
    let attempts = within(300, "the probe", probe(&setup))
        .await
        .expect("the probe judges every attempt");
    for attempt in &attempts {
        // TLS still checks certificates, and no planner answers snapshot queries here.
        let refused_anyway =
            attempt.what.starts_with("connect") || attempt.what.contains("snapshot");
        assert_eq!(attempt.accepted, !refused_anyway, "{attempt:?}");
    }
    let _ = router.close().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// The payload sizes a session's subscriber on `key` receives, in arrival order.
async fn sizes_on(
    session: &zenoh::Session,
    key: &'static str,
) -> (
    zenoh::pubsub::Subscriber<()>,
    tokio::sync::mpsc::UnboundedReceiver<usize>,
) {
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    let subscriber = session
        .declare_subscriber(key)
        .callback(move |sample| {
            let _ = tx.send(sample.payload().len());
        })
        .await
        .expect("subscriber");
    (subscriber, rx)
}

/// The sizes received up to and including the first of `last` bytes.
async fn sizes_until(
    rx: &mut tokio::sync::mpsc::UnboundedReceiver<usize>,
    last: usize,
) -> Vec<usize> {
    let mut seen = Vec::new();
    while seen.last() != Some(&last) {
        seen.push(rx.recv().await.expect("subscriber alive"));
    }
    seen
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn an_oversized_frame_is_dropped_by_the_detectors_transport() {
    build_binaries();
    let dir = std::env::temp_dir().join(format!("glasshouse-oversized-{}", std::process::id()));
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let (pki, _) = make_pkis(&dir, &endpoint);
    let router = open(&BusArgs {
        listen: vec![endpoint],
        ..identity(&pki, "router")
    })
    .await;
    let trolley = open(&identity(&pki, "trolley-t2")).await;
    let detector = open(&identity(&pki, "detector-d1")).await;
    let dashboard = open(&identity(&pki, "dashboard-web1")).await;
    let frames = "gh/trolley/*/rgbd";
    let (_d, mut at_detector) = sizes_on(&detector, frames).await;
    let (_w, mut at_dashboard) = sizes_on(&dashboard, frames).await;
    let put = |bytes: usize| {
        trolley
            .put("gh/trolley/t2/rgbd", vec![7u8; bytes])
            .congestion_control(zenoh::qos::CongestionControl::Block)
    };
    // Small puts until both subscribers are known to the trolley and got one.
    const SMALL: usize = 1000;
    within(
        30,
        "a small frame at the detector and the dashboard",
        async {
            let (mut detector_got, mut dashboard_got) = (false, false);
            while !(detector_got && dashboard_got) {
                put(SMALL).await.expect("put");
                tokio::time::sleep(Duration::from_millis(100)).await;
                detector_got |= at_detector.try_recv().is_ok();
                dashboard_got |= at_dashboard.try_recv().is_ok();
            }
        },
    )
    .await;
    // 20 MB: within the router's and the dashboard's limits, over the detector's (9 MiB).
    const BIG: usize = 20 << 20;
    put(BIG).await.expect("put");
    put(SMALL + 1).await.expect("put");
    let at_dashboard = within(
        60,
        "the control at the dashboard",
        sizes_until(&mut at_dashboard, SMALL + 1),
    )
    .await;
    assert!(
        at_dashboard.contains(&BIG),
        "the router forwarded the big put to the dashboard: {at_dashboard:?}"
    );
    let at_detector = within(
        60,
        "the control at the detector",
        sizes_until(&mut at_detector, SMALL + 1),
    )
    .await;
    assert!(
        !at_detector.contains(&BIG),
        "the detector's transport dropped the big put: {at_detector:?}"
    );
    for session in [trolley, detector, dashboard, router] {
        let _ = session.close().await;
    }
    let _ = std::fs::remove_dir_all(&dir);
}
