//! (e) Planner failover: three planner processes share a trolley; the owner is killed (SIGKILL)
//! mid-run, the standby replica takes over, views resume, and the survivor's map equals the map
//! rebuilt offline from every ROI cloud the trolley's detector published: no scan is lost. The
//! replica refreshes from the owner's snapshot every 2 clouds here (4 by default), so snapshots
//! go over the bus before the kill and clouds are still pending at it.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use glasshouse_proto::keys;
use glasshouse_tests::procs::{build_binaries, Proc};
use glasshouse_tests::{
    assert_holds_every_cloud, client, free_port, observe, snapshot_at_last_cloud, within,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn killed_owner_is_replaced_without_losing_a_scan() {
    build_binaries();
    let logs = std::env::temp_dir().join(format!("glasshouse-failover-{}", std::process::id()));
    std::fs::create_dir_all(&logs).expect("log dir");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let base = [
        "-e",
        endpoint.as_str(),
        "--mode",
        "client",
        "--lease-ms",
        "1000",
    ];
    let args = |extra: &[&str]| -> Vec<String> {
        base.iter().chain(extra).map(|s| s.to_string()).collect()
    };
    let start = |name: &'static str, bin: &str, extra: &[&str]| {
        let a = args(extra);
        Proc::start(
            name,
            bin,
            &a.iter().map(String::as_str).collect::<Vec<_>>(),
            &logs,
        )
    };
    let _router = Proc::start("router", "glasshouse", &["router", "-l", &endpoint], &logs);
    let observer = client(&endpoint).await;
    let clouds_sub = observe(&observer, &keys::roi_from_any("t1").expect("key")).await;
    let views_sub = observe(&observer, &keys::views_from_any("t1").expect("key")).await;
    let status_sub = observe(&observer, &keys::all_planner_status()).await;
    let _detector = start("detector", "detector-service", &[]);
    let mut planners: Vec<(String, Proc)> = ["p1", "p2", "p3"]
        .into_iter()
        .map(|pid| {
            let name: &'static str = match pid {
                "p1" => "planner-p1",
                "p2" => "planner-p2",
                _ => "planner-p3",
            };
            (
                pid.to_owned(),
                start(
                    name,
                    "planner-service",
                    &["--planner-id", pid, "--replica-refresh-clouds", "2"],
                ),
            )
        })
        .collect();

    // The planners see each other before the trolley appears.
    within(60, "three planners report", async {
        let mut seen = BTreeSet::new();
        while seen.len() < 3 {
            let status = status_sub.recv().await.expect("status");
            seen.insert(status.message.planner_id);
        }
    })
    .await;
    let edge = start(
        "edge",
        "edge",
        &["--trolley-id", "t1", "--scenario", "2", "--width", "160"],
    );

    // Owner: the planner the views come from, which its own status reports as owner; replica:
    // the one planner reporting t1 on standby. Waiting for statuses that agree (rather than for
    // a fixed time) lets the planners' membership settle first.
    let (owner, replica) = within(
        180,
        "views from the owner and a replica on standby",
        async {
            let mut latest: BTreeMap<String, (bool, bool)> = BTreeMap::new();
            let (mut views_from, mut views) = (None::<String>, 0);
            loop {
                tokio::select! {
                    received = views_sub.recv() => {
                        views += 1;
                        views_from = Some(received.expect("views").header.source_id);
                    }
                    received = status_sub.recv() => {
                        let s = received.expect("status").message;
                        let holds = |list: &[String]| list.iter().any(|t| t == "t1");
                        let roles = (holds(&s.owned_trolleys), holds(&s.standby_trolleys));
                        latest.insert(s.planner_id, roles);
                    }
                }
                let of_role = |want: fn(&(bool, bool)) -> bool| -> Vec<String> {
                    latest
                        .iter()
                        .filter(|(_, r)| want(r))
                        .map(|(p, _)| p.clone())
                        .collect()
                };
                let (owners, replicas) = (of_role(|r| r.0), of_role(|r| r.1));
                if let ([o], [r], Some(v)) = (&owners[..], &replicas[..], &views_from) {
                    if views >= 7 && o == v && o != r {
                        return (o.clone(), r.clone());
                    }
                }
            }
        },
    )
    .await;

    let killed = Instant::now();
    let (_, victim) = planners
        .iter_mut()
        .find(|(pid, _)| *pid == owner)
        .expect("the owner is one of ours");
    victim.kill();
    eprintln!("killed owner {owner}; replica {replica}");
    // The replica stood by: the owner answered its snapshot queries before the kill.
    let answered = victim.log_text().matches("snapshot asked").count();
    assert!(answered >= 1, "the owner answered no snapshot query");
    let deltas = victim.log_text().matches("delta asked").count();
    eprintln!("the owner answered {answered} refreshes with its whole map, {deltas} with a delta");
    // The loop goes on: views on three new frames from the replica.
    let takeover = within(
        120,
        "views on three frames from the replica after the kill",
        async {
            let mut frames = BTreeSet::new();
            let mut first = None;
            loop {
                let received = views_sub.recv().await.expect("views");
                let (h, v) = (received.header, received.message);
                if h.source_id != owner {
                    assert_eq!(
                        h.source_id, replica,
                        "views from a planner that was not the replica"
                    );
                    first.get_or_insert_with(|| killed.elapsed());
                    frames.insert(v.based_on_seq);
                    if frames.len() >= 3 {
                        return first.unwrap_or_default();
                    }
                }
            }
        },
    )
    .await;
    eprintln!(
        "views resumed {:.2} s after the kill",
        takeover.as_secs_f64()
    );

    edge.terminate();
    let at_last = snapshot_at_last_cloud(&observer, &clouds_sub, &replica, "t1").await;
    let last_seq = at_last
        .clouds
        .iter()
        .map(|c| c.source_frame().seq)
        .max()
        .expect("clouds");
    assert!(last_seq >= 5, "only {} frames", last_seq);
    assert_holds_every_cloud(&at_last.map, &at_last.clouds, "the survivor's");
    let _ = observer.close().await;
    for (_, p) in planners {
        drop(p);
    }
    let _ = std::fs::remove_dir_all(&logs);
}
