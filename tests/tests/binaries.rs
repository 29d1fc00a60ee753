//! (b) The four real binaries as separate OS processes on free ports, around a `glasshouse router`.

use std::time::{Duration, Instant};

use std::sync::Arc;

use glasshouse_bus::{Delivery, DropCounters, Subscriber};
use glasshouse_proto::keys;
use glasshouse_proto::TrolleyState;
use glasshouse_tests::procs::{build_binaries, Proc};
use glasshouse_tests::{client, free_port, within};

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
    let args = with(&["--record", &rrd_arg]);
    let dashboard = Proc::start(
        "dashboard",
        "dashboard",
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        &logs,
    );
    let args = with(&[]);
    let detector = Proc::start(
        "detector",
        "detector-service",
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        &logs,
    );
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
    let args = with(&["--max-views", "6", "--width", "160"]);
    let mut edge = Proc::start(
        "edge",
        "edge",
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        &logs,
    );

    // The edge exits by itself once its six views are done.
    let done = within(240, "edge to finish six views", async {
        loop {
            match status_sub.recv().await {
                Some(received) if received.message.state == TrolleyState::Done => {
                    return received.message
                }
                Some(_) => {}
                None => panic!("status subscriber closed"),
            }
        }
    })
    .await;
    assert!(
        done.views_done >= 5,
        "only {} views: {done:?}",
        done.views_done
    );
    let exit = within(30, "edge exit", async {
        loop {
            if let Some(status) = edge.child.try_wait().expect("wait") {
                return status;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    assert!(
        exit.success(),
        "edge exited with {exit}:\n{}",
        edge.log_text()
    );

    let mut fruits = 0;
    while let Some(received) = fruits_sub.try_recv() {
        fruits = received.message.fruits.len();
    }
    assert!(fruits > 0, "no fruit estimates from the planner process");
    drop(status_sub);
    drop(fruits_sub);
    let _ = observer.close().await;

    for p in [planner, detector, dashboard, router] {
        p.terminate();
    }
    let size = std::fs::metadata(&rrd).map(|m| m.len()).unwrap_or(0);
    assert!(size > 10_000, "dashboard recording is {size} bytes");
    let _ = std::fs::remove_dir_all(&logs);
}
