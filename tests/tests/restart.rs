//! (g) A full restart: every planner and the router killed (SIGKILL) mid-row, then started again,
//! each planner on its own store (`planner-service --store`). What must hold: the trolley is
//! served again, every fruit id its fruits carried before the kill comes back at the same place,
//! and its owner's map at the end equals, voxel for voxel, the map rebuilt from every cloud the
//! detector published (before and after the restart): no integrated scan is lost.

use std::collections::BTreeSet;
use std::path::Path;

use glasshouse_proto::keys;
use glasshouse_tests::procs::{build_binaries, Proc};
use glasshouse_tests::{
    assert_holds_every_cloud, client, free_port, observe, snapshot_at_last_cloud, within,
};

/// Fruit ids and centres (world, m) as published.
type Fruits = Vec<(u32, [f64; 3])>;

fn router(endpoint: &str, logs: &Path) -> Proc {
    let args = ["router", "-l", endpoint, "--lease-ms", "1000"];
    Proc::start("router", "glasshouse", &args, logs)
}

/// Planner `pid` on its store in `logs`.
fn planner(pid: &'static str, endpoint: &str, logs: &Path) -> Proc {
    let store = logs.join(format!("{pid}.redb"));
    let store = store.to_string_lossy().into_owned();
    let args = [
        "-e",
        endpoint,
        "--mode",
        "client",
        "--lease-ms",
        "1000",
        "--planner-id",
        pid,
        "--replica-refresh-clouds",
        "2",
        "--store",
        &store,
    ];
    let name = if pid == "p1" {
        "planner-p1"
    } else {
        "planner-p2"
    };
    Proc::start(name, "planner-service", &args, logs)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_restart_loses_no_scan_and_no_fruit_id() {
    build_binaries();
    let logs = std::env::temp_dir().join(format!("glasshouse-restart-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&logs);
    std::fs::create_dir_all(&logs).expect("log dir");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let client_args = [
        "-e",
        endpoint.as_str(),
        "--mode",
        "client",
        "--lease-ms",
        "1000",
    ];
    let with = |extra: &[&str]| -> Vec<String> {
        client_args
            .iter()
            .chain(extra)
            .map(|s| s.to_string())
            .collect()
    };
    let start = |name: &'static str, bin: &str, extra: &[&str]| {
        let args = with(extra);
        Proc::start(
            name,
            bin,
            &args.iter().map(String::as_str).collect::<Vec<_>>(),
            &logs,
        )
    };
    let mut first_router = router(&endpoint, &logs);
    let observer = client(&endpoint).await;
    let clouds_sub = observe(&observer, &keys::roi_from_any("t1").expect("key")).await;
    let views_sub = observe(&observer, &keys::views_from_any("t1").expect("key")).await;
    let fruits_sub = observe(&observer, &keys::fruits("t1").expect("key")).await;
    let status_sub = observe(&observer, &keys::all_planner_status()).await;
    let _detector = start("detector", "detector-service", &[]);
    let mut planners = [
        planner("p1", &endpoint, &logs),
        planner("p2", &endpoint, &logs),
    ];
    within(60, "two planners report", async {
        let mut seen = BTreeSet::new();
        while seen.len() < 2 {
            seen.insert(status_sub.recv().await.expect("status").message.planner_id);
        }
    })
    .await;
    let edge = start(
        "edge",
        "edge",
        &["--trolley-id", "t1", "--scenario", "row", "--width", "160"],
    );

    // Mid-row: views on several frames and some fruit found.
    let before: Fruits = within(240, "views on 8 frames and fruits", async {
        let (mut frames, mut fruits) = (BTreeSet::new(), Fruits::new());
        loop {
            tokio::select! {
                v = views_sub.recv() => { frames.insert(v.expect("views").message.based_on_seq); }
                f = fruits_sub.recv() => {
                    let f = f.expect("fruits").message;
                    fruits = f.fruits.iter().map(|f| (f.id, [f.centre.x, f.centre.y, f.centre.z])).collect();
                }
            }
            if frames.len() >= 8 && !fruits.is_empty() {
                return fruits;
            }
        }
    })
    .await;

    // Everything but the edge and the detector goes at once.
    for p in &mut planners {
        p.kill();
    }
    first_router.kill();
    eprintln!("killed every planner and the router; fruits before: {before:?}");
    while fruits_sub.try_recv().is_some() {}
    while views_sub.try_recv().is_some() {}
    let _router = router(&endpoint, &logs);
    let planners = [
        planner("p1", &endpoint, &logs),
        planner("p2", &endpoint, &logs),
    ];

    // Served again, and every fruit id back at its place.
    let (owner, after) = within(180, "views on three frames and fruits after the restart", async {
        let (mut frames, mut owner, mut after) = (BTreeSet::new(), None, None::<Fruits>);
        loop {
            tokio::select! {
                v = views_sub.recv() => {
                    let v = v.expect("views");
                    frames.insert(v.message.based_on_seq);
                    owner = Some(v.header.source_id);
                }
                f = fruits_sub.recv() => {
                    let f = f.expect("fruits").message;
                    after.get_or_insert_with(|| f.fruits.iter().map(|f| (f.id, [f.centre.x, f.centre.y, f.centre.z])).collect());
                }
            }
            if let (true, Some(owner), Some(after)) = (frames.len() >= 3, &owner, &after) {
                return (owner.clone(), after.clone());
            }
        }
    })
    .await;
    let restored = |(id, at): &(u32, [f64; 3])| {
        after.iter().any(|(other, place)| {
            let d2: f64 = at.iter().zip(place).map(|(a, b)| (a - b) * (a - b)).sum();
            other == id && d2.sqrt() <= 0.05
        })
    };
    let lost: Vec<_> = before.iter().filter(|f| !restored(f)).collect();
    assert!(
        lost.is_empty(),
        "fruit ids lost by the restart: {lost:?} (after: {after:?})"
    );
    let log =
        std::fs::read_to_string(logs.join(format!("planner-{owner}.log"))).unwrap_or_default();
    assert!(
        log.contains("restored from the store"),
        "{owner} restored nothing:\n{log}"
    );

    edge.terminate();
    let at_last = snapshot_at_last_cloud(&observer, &clouds_sub, &owner, "t1").await;
    assert_holds_every_cloud(&at_last.map, &at_last.clouds, "the restarted owner's");
    let _ = observer.close().await;
    drop(planners);
    let _ = std::fs::remove_dir_all(&logs);
}
