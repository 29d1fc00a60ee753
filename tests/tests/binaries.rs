//! (b) The four real binaries as separate OS processes on free ports, around a `glasshouse router`,
//! each serving OpenMetrics on `--metrics`, scraped during the run and parsed with the Prometheus
//! project's own Python parser.

use std::time::{Duration, Instant};

use std::sync::Arc;

use glasshouse_bus::{Delivery, DropCounters, Subscriber};
use glasshouse_proto::keys;
use glasshouse_proto::TrolleyState;
use glasshouse_tests::procs::{build_binaries, Proc};
use glasshouse_tests::{client, free_port, script, within};

/// `GET /metrics` of a service, as text (HTTP/1.0, so the body ends with the connection).
fn scrape(port: u16) -> String {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).expect("metrics port");
    stream
        .write_all(b"GET /metrics HTTP/1.0\r\nHost: localhost\r\n\r\n")
        .expect("request");
    let mut response = String::new();
    stream.read_to_string(&mut response).expect("response");
    let (head, body) = response.split_once("\r\n\r\n").expect("an HTTP response");
    assert!(
        head.starts_with("HTTP/1.0 200") || head.starts_with("HTTP/1.1 200"),
        "{head}"
    );
    assert!(head.contains("application/openmetrics-text"), "{head}");
    body.to_string()
}

/// Whether a planner's metrics text says it owns one trolley.
fn owns_one(text: &str) -> bool {
    text.lines().any(|line| {
        line.starts_with("glasshouse_planner_trolleys{")
            && line.contains("role=\"owner\"")
            && line
                .split_whitespace()
                .last()
                .and_then(|v| v.parse::<f64>().ok())
                == Some(1.0)
    })
}

/// The value of `sample` (with `labels`, a subset) in a check-metrics family; None if absent.
fn sample(
    families: &serde_json::Value,
    family: &str,
    sample: &str,
    labels: &[(&str, &str)],
) -> Option<f64> {
    families[family]["samples"]
        .as_array()?
        .iter()
        .find_map(|s| {
            let matches = s[0] == sample && labels.iter().all(|(k, v)| s[1][k] == *v);
            matches.then(|| s[2].as_f64()).flatten()
        })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn real_binaries_close_the_loop() {
    let t0 = Instant::now();
    build_binaries();
    eprintln!("binaries ready after {:.1} s", t0.elapsed().as_secs_f64());
    let logs = std::env::temp_dir().join(format!("glasshouse-binaries-{}", std::process::id()));
    std::fs::create_dir_all(&logs).expect("log dir");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let rrd = logs.join("run.rrd");
    let rrd_arg = rrd.to_string_lossy().into_owned();
    let connect = ["-e", endpoint.as_str(), "--mode", "client"];
    let with = |extra: &[&str]| -> Vec<String> {
        connect.iter().chain(extra).map(|s| s.to_string()).collect()
    };
    // The router's listener comes from its config file (no -l): the file is respected.
    let router_config = logs.join("router.json5");
    std::fs::write(
        &router_config,
        format!("{{ listen: {{ endpoints: [\"{endpoint}\"] }} }}"),
    )
    .expect("router config");
    let router_config = router_config.to_string_lossy().into_owned();
    let router = Proc::start(
        "router",
        "glasshouse",
        &["router", "--zenoh-config", &router_config],
        &logs,
    );
    // Clients retry their connection, so the start order does not matter.
    let metrics: Vec<(&str, u16)> = ["dashboard", "detector", "planner", "edge"]
        .iter()
        .map(|kind| (*kind, free_port()))
        .collect();
    let metrics_of = |kind: &str| {
        let port = metrics.iter().find(|(k, _)| *k == kind).expect("a port").1;
        (format!("127.0.0.1:{port}"), port)
    };
    let (dashboard_metrics, _) = metrics_of("dashboard");
    // Its web page on a free port too: the default, 8080, may be taken on the machine.
    let dashboard_http = format!("127.0.0.1:{}", free_port());
    let args = with(&[
        "--record",
        &rrd_arg,
        "--metrics",
        &dashboard_metrics,
        "--http",
        &dashboard_http,
    ]);
    let dashboard = Proc::start(
        "dashboard",
        "dashboard",
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        &logs,
    );
    let (detector_metrics, _) = metrics_of("detector");
    let args = with(&["--metrics", &detector_metrics]);
    let detector = Proc::start(
        "detector",
        "detector-service",
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        &logs,
    );
    let (planner_metrics, planner_port) = metrics_of("planner");
    let planner_config = logs.join("planner.json5");
    std::fs::write(&planner_config, "{ status_period_ms: 100 }").expect("planner config");
    let planner_config = planner_config.to_string_lossy().into_owned();
    let args = with(&["--metrics", &planner_metrics, "-c", &planner_config]);
    let planner = Proc::start(
        "planner",
        "planner-service",
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        &logs,
    );

    let observer = client(&endpoint).await;
    // Drop-oldest queues: the observer reads the fruits only at the end.
    let drops = Arc::new(DropCounters::default());
    let status_key = keys::status("t1").expect("key");
    let status_sub =
        Subscriber::declare_with(&observer, &status_key, Delivery::Monitor, drops.clone())
            .await
            .expect("subscriber");
    let fruits_key = keys::fruits("t1").expect("key");
    let fruits_sub = Subscriber::declare_with(&observer, &fruits_key, Delivery::Monitor, drops)
        .await
        .expect("subscriber");
    let (edge_metrics, edge_port) = metrics_of("edge");
    let args = with(&[
        "--max-views",
        "6",
        "--width",
        "160",
        "--metrics",
        &edge_metrics,
    ]);
    let mut edge = Proc::start(
        "edge",
        "edge",
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        &logs,
    );

    // The edge exits by itself once its six views are done: scraped after its second view. The
    // planner is scraped from then on until a status of its (every 100 ms) says it owns the
    // trolley; once the edge has left, it no longer does. The edge's exit ends the wait too: its
    // last status can be the one message still queued when its session closes.
    let mut edge_text = None;
    let mut planner_text = None;
    let mut last_status = None;
    let exit = within(240, "edge to finish six views and exit", async {
        let mut poll = tokio::time::interval(Duration::from_millis(50));
        loop {
            tokio::select! {
                received = status_sub.recv() => {
                    let status = received.expect("status subscriber closed").message;
                    if status.views_done >= 2 {
                        edge_text.get_or_insert_with(|| scrape(edge_port));
                        if planner_text.is_none() {
                            planner_text = Some(scrape(planner_port)).filter(|t| owns_one(t));
                        }
                    }
                    last_status = Some(status);
                }
                _ = poll.tick() => {
                    if let Some(status) = edge.child.try_wait().expect("wait") {
                        return status;
                    }
                }
            }
        }
    })
    .await;
    assert!(
        exit.success(),
        "edge exited with {exit}:\n{}",
        edge.log_text()
    );
    // Statuses still on their way when the edge exited.
    while let Some(received) = status_sub.try_recv() {
        last_status = Some(received.message);
    }
    let last = last_status.expect("no status from the edge");
    assert!(
        last.views_done >= 5,
        "only {} views: {last:?}",
        last.views_done
    );
    if last.state != TrolleyState::Done {
        eprintln!("the edge's last status before it exited did not arrive: {last:?}");
    }

    let mut fruits = 0;
    while let Some(received) = fruits_sub.try_recv() {
        fruits = received.message.fruits.len();
    }
    assert!(fruits > 0, "no fruit estimates from the planner process");
    drop(status_sub);
    drop(fruits_sub);
    let _ = observer.close().await;

    // Every service's metrics, parsed by the stock OpenMetrics parser.
    let mut files = Vec::new();
    for (kind, port) in &metrics {
        let text = match *kind {
            "edge" => edge_text.clone().expect("the edge was scraped"),
            "planner" => planner_text
                .clone()
                .expect("no planner status said it owned the trolley while the edge ran"),
            _ => scrape(*port),
        };
        let file = logs.join(format!("{kind}.metrics"));
        std::fs::write(&file, text).expect("metrics file");
        files.push(file.to_string_lossy().into_owned());
    }
    let parsed: serde_json::Value = serde_json::from_str(&script(
        "check-metrics",
        &files.iter().map(String::as_str).collect::<Vec<_>>(),
    ))
    .expect("check-metrics JSON");
    let of = |kind: &str| {
        &parsed[logs
            .join(format!("{kind}.metrics"))
            .to_string_lossy()
            .as_ref()]
    };
    let planner_m = of("planner");
    let positive =
        |families: &serde_json::Value, family: &str, name: &str, labels: &[(&str, &str)]| {
            let value = sample(families, family, name, labels);
            assert!(
                value.is_some_and(|v| v > 0.0),
                "{name} {labels:?}: {value:?} in {families}"
            );
        };
    positive(
        planner_m,
        "glasshouse_planner_clouds_integrated",
        "glasshouse_planner_clouds_integrated_total",
        &[],
    );
    positive(
        planner_m,
        "glasshouse_planner_stage_seconds",
        "glasshouse_planner_stage_seconds_count",
        &[("stage", "integrate")],
    );
    positive(
        planner_m,
        "glasshouse_planner_stage_seconds",
        "glasshouse_planner_stage_seconds_bucket",
        &[("stage", "plan"), ("le", "+Inf")],
    );
    assert_eq!(
        planner_m["glasshouse_planner_stage_seconds"]["type"],
        "histogram"
    );
    // One planner: no takeover, no snapshot sent; the counter is there, in bytes.
    assert_eq!(
        sample(
            planner_m,
            "glasshouse_planner_snapshot_sent_bytes",
            "glasshouse_planner_snapshot_sent_bytes_total",
            &[]
        ),
        Some(0.0)
    );
    assert_eq!(
        sample(
            planner_m,
            "glasshouse_planner_trolleys",
            "glasshouse_planner_trolleys",
            &[("role", "owner")]
        ),
        Some(1.0)
    );
    positive(
        planner_m,
        "glasshouse_planner_process_resident_memory_bytes",
        "glasshouse_planner_process_resident_memory_bytes",
        &[],
    );
    positive(
        of("detector"),
        "glasshouse_detector_frames_processed",
        "glasshouse_detector_frames_processed_total",
        &[],
    );
    positive(
        of("edge"),
        "glasshouse_edge_frames_published",
        "glasshouse_edge_frames_published_total",
        &[],
    );
    positive(
        of("dashboard"),
        "glasshouse_dashboard_messages_received",
        "glasshouse_dashboard_messages_received_total",
        &[],
    );
    assert_eq!(
        sample(
            of("dashboard"),
            "glasshouse_dashboard_dropped_messages",
            "glasshouse_dashboard_dropped_messages_total",
            &[("reason", "corrupt")]
        ),
        Some(0.0)
    );

    for p in [planner, detector, dashboard, router] {
        p.terminate();
    }
    let size = std::fs::metadata(&rrd).map(|m| m.len()).unwrap_or(0);
    assert!(size > 10_000, "dashboard recording is {size} bytes");
    let _ = std::fs::remove_dir_all(&logs);
}
