//! A deployment secured by `glasshouse secure`: the fleet runs over mutual TLS through a router
//! with the generated ACL, while a rogue tries what its certificate does not allow
//! (`glasshouse_bus::probe`, the same attempts `glasshouse secure probe` and the compose rig's
//! rogue container make). A second test shows the probe reports what a router without the ACL
//! lets through.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use glasshouse_bus::probe::{probe, Attempt, ProbeSetup};
use glasshouse_bus::BusArgs;
use glasshouse_dashboard::DashboardSettings;
use glasshouse_edge::EdgeEvent;
use glasshouse_planner::PlannerSettings;
use glasshouse_tests::procs::{bin_dir, build_binaries};
use glasshouse_tests::{free_port, open, test_edge_config, within, FleetSessions, Pipeline};
use serde_json::Value;

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
            &["--detectors", "d1", "--dashboards", "web1"][..],
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
        foreign_key: other.join("trolley-t1.key"),
        foreign_cert: other.join("trolley-t1.pem"),
        scratch: dir.join("probe"),
        timeout: Duration::from_secs(10),
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
    pipeline.start_edge(test_edge_config(4)).await;

    let setup = probe_setup(&dir, &pki, &other, Some(config_of(&pki, "planner-p2")));
    let attempts = within(300, "the probe", probe(&setup))
        .await
        .expect("the probe judges every attempt");
    assert!(attempts.len() >= 14, "too few attempts: {attempts:?}");
    let holes: Vec<&Attempt> = attempts.iter().filter(|a| a.accepted).collect();
    assert!(
        holes.is_empty(),
        "the deployment let these through: {holes:?}"
    );

    let events = pipeline.run_to_end(240).await;
    let views = events
        .iter()
        .filter(|e| matches!(e, EdgeEvent::ViewDone { .. }))
        .count();
    assert!(views >= 3, "only {views} views executed: {events:?}");
    let fleet = pipeline.fleet.lock().expect("fleet state").clone();
    let trolley = fleet
        .trolleys
        .get("t1")
        .expect("the dashboard saw trolley t1");
    assert!(!trolley.fruits.is_empty(), "no fruit found");
    assert!(!fleet.trolleys.contains_key("t2") || fleet.trolleys["t2"].views_messages == 0);
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
    let attempts = within(
        300,
        "the probe",
        probe(&probe_setup(&dir, &pki, &other, None)),
    )
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
