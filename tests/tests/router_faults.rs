//! The router lost, with the real binaries: two planners, a detector and one edge on a 1 s lease,
//! every client knowing the routers there are. The router is killed (SIGKILL) and either started
//! again on the same endpoint (a restart) or not at all, the clients moving to a second router
//! meshed with the first (a failover). Every membership is lost at once and comes back; what
//! must hold: the trolley is served again, its arm executes no view of an ownership term older
//! than one it has taken views under, and its owner's map at the end equals, voxel for voxel, the
//! map rebuilt from every cloud the detector published.

use glasshouse_bus::BusArgs;
use glasshouse_proto::{keys, TrolleyStatus};
use glasshouse_tests::procs::{build_binaries, Proc};
use glasshouse_tests::{
    assert_holds_every_cloud, free_port, observe, open, snapshot_at_last_cloud_of, within,
};

#[derive(Clone, Copy, Debug, PartialEq)]
enum RouterFault {
    /// The router killed and started again on the same endpoint.
    Restart,
    /// The router killed; the clients move to the second router.
    Failover,
}

/// Views executed in all terms up to `epoch`.
fn executed_up_to(status: &TrolleyStatus, epoch: u64) -> u32 {
    status
        .owner_terms
        .iter()
        .filter(|t| t.owner_epoch <= epoch)
        .map(|t| t.views_executed)
        .sum()
}

fn newest_term(status: &TrolleyStatus) -> u64 {
    status
        .owner_terms
        .iter()
        .map(|t| t.owner_epoch)
        .max()
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_router_loses_no_scan_and_moves_no_stale_arm() {
    router_lost_and_back(RouterFault::Restart).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_fail_over_to_the_second_router_without_losing_a_scan() {
    router_lost_and_back(RouterFault::Failover).await;
}

/// Starts router `name` listening on `listen`, meshed with `peer` if given.
fn router(name: &'static str, listen: &str, peer: Option<&str>, logs: &std::path::Path) -> Proc {
    let mut args = vec!["router", "-l", listen, "--lease-ms", "1000"];
    if let Some(peer) = peer {
        args.extend(["-e", peer]);
    }
    Proc::start(name, "glasshouse", &args, logs)
}

async fn router_lost_and_back(fault: RouterFault) {
    build_binaries();
    let logs = std::env::temp_dir().join(format!(
        "glasshouse-router-{fault:?}-{}",
        std::process::id()
    ));
    std::fs::create_dir_all(&logs).expect("log dir");
    let first = format!("tcp/127.0.0.1:{}", free_port());
    let second = format!("tcp/127.0.0.1:{}", free_port());
    let mut routers = vec![router("router", &first, None, &logs)];
    let mut endpoints = vec![first.clone()];
    if fault == RouterFault::Failover {
        routers.push(router("router2", &second, Some(&first), &logs));
        endpoints.push(second.clone());
    }
    let mut base: Vec<&str> = Vec::new();
    for e in &endpoints {
        base.extend(["-e", e.as_str()]);
    }
    base.extend(["--mode", "client", "--lease-ms", "1000"]);
    let start = |name: &'static str, bin: &str, extra: &[&str]| {
        let args: Vec<&str> = base.iter().chain(extra).copied().collect();
        Proc::start(name, bin, &args, &logs)
    };
    let observer = open(&BusArgs {
        connect: endpoints.clone(),
        mode: Some(glasshouse_bus::Mode::Client),
        lease_ms: Some(1000),
        ..BusArgs::default()
    })
    .await;
    let status_sub = observe(&observer, &keys::status("t1").expect("key")).await;
    let clouds_sub = observe(&observer, &keys::roi_from_any("t1").expect("key")).await;
    // The observer's link moves with the clients in a failover and can miss a cloud meanwhile:
    // a second session on the router that stays sees the ones after the fault.
    let stays = open(&BusArgs {
        connect: vec![endpoints.last().expect("a router").clone()],
        mode: Some(glasshouse_bus::Mode::Client),
        lease_ms: Some(1000),
        ..BusArgs::default()
    })
    .await;
    let clouds_stays = observe(&stays, &keys::roi_from_any("t1").expect("key")).await;
    let _detector = start("detector", "detector-service", &[]);
    let _p1 = start("planner-p1", "planner-service", &["--planner-id", "p1"]);
    let _p2 = start("planner-p2", "planner-service", &["--planner-id", "p2"]);
    let config = logs.join("edge.json5");
    std::fs::write(&config, "{ views_timeout_ms: 2000 }").expect("edge config");
    let config = config.to_string_lossy().into_owned();
    let edge_args = ["-c", &config, "--trolley-id", "t1", "--scenario", "2"];
    let edge = start(
        "edge",
        "edge",
        &[&edge_args[..], &["--width", "160"]].concat(),
    );

    // 1. Served: three views executed.
    let before = within(240, "three views executed", async {
        loop {
            let status = status_sub.recv().await.expect("status").message;
            if status.views_done >= 3 {
                return status;
            }
        }
    })
    .await;
    let term_at_fault = newest_term(&before);
    eprintln!("served under term {term_at_fault}: killing the router ({fault:?})");
    routers[0].kill();
    if fault == RouterFault::Restart {
        routers[0] = router("router-restarted", &first, None, &logs);
    }

    // 2. Served again: three more views executed after the fault.
    let after = within(120, "three more views executed after the fault", async {
        loop {
            let status = status_sub.recv().await.expect("status").message;
            if status.views_done >= before.views_done + 3 {
                return status;
            }
        }
    })
    .await;
    eprintln!("served again, terms {:?}", after.owner_terms);
    if newest_term(&after) > term_at_fault {
        // Once a newer term had views executed, no older term's may be.
        let switched = executed_up_to(&after, term_at_fault);
        let last = within(60, "a later status", async {
            status_sub.recv().await.expect("status").message
        })
        .await;
        assert_eq!(executed_up_to(&last, term_at_fault), switched);
    }

    // 3. The owner's map holds every scan: the owner the edge took its last views from (a
    // standby that missed a cloud while its link moved is not asked).
    edge.terminate();
    let mut last = after;
    while let Some(received) = status_sub.try_recv() {
        last = received.message;
    }
    let owner = last
        .owner_terms
        .iter()
        .max_by_key(|t| t.owner_epoch)
        .map(|t| t.planner_id.clone())
        .expect("an owner");
    let subs = [&clouds_sub, &clouds_stays];
    let at_last = snapshot_at_last_cloud_of(&observer, &subs, &owner, "t1").await;
    assert_holds_every_cloud(&at_last.map, &at_last.clouds, &format!("{owner}'s"));
    let _ = observer.close().await;
    let _ = stays.close().await;
    let _ = std::fs::remove_dir_all(&logs);
}
