//! Fencing under a hung or cut-off owner, with the real binaries: router, two planners (each
//! behind its own `glasshouse relay`), a detector and one edge, on a 1 s lease. The trolley's
//! owner is paused (SIGSTOP) or cut off from the router (its relay stops passing bytes: a network
//! partition), with its links left open either way; once its lease expires the other planner
//! takes over under a newer ownership epoch and the trolley is served again. Then the owner comes
//! back (SIGCONT, or the link heals): it still believes it owns the trolley, ranks first again as
//! soon as its token is back, and holds a map without the scans integrated meanwhile.
//!
//! What must hold, read off the edge's own counters (its TrolleyStatus: views executed per
//! ownership term, stale views refused) and the planners' statuses: no view of the paused
//! owner's term is executed after the takeover; what still comes under that term is refused and
//! counted (a copy of its last views delayed past the takeover, aimed at the edge's latest frame:
//! without fencing the arm would move on it; and whatever the woken owner planned on clouds it
//! held before it heard of the newer term); the woken owner steps down, catches up from the other
//! planner's map and serves the trolley again under a newer term, on a map equal voxel for voxel
//! to the one rebuilt from every cloud the trolley's detector published: it did not plan on its
//! stale map. The trolley keeps getting views throughout.

use std::sync::Arc;

use glasshouse_bus::{DropCounters, Publisher};
use glasshouse_proto::keys;
use glasshouse_proto::{Header, PlannerStatus, RankedViews, TrolleyStatus};
use glasshouse_tests::procs::{build_binaries, Proc};
use glasshouse_tests::{
    assert_holds_every_cloud, client, free_port, observe, snapshot_at_last_cloud, within,
};

/// Views the edge executed under `pid`'s term `epoch`, by its status.
fn executed(status: &TrolleyStatus, pid: &str, epoch: u64) -> u32 {
    status
        .owner_terms
        .iter()
        .filter(|t| t.planner_id == pid && t.owner_epoch == epoch)
        .map(|t| t.views_executed)
        .sum()
}

/// The first term in `status` of `pid` newer than `after` with at least `views` executed.
fn term_after(status: &TrolleyStatus, pid: &str, after: u64, views: u32) -> Option<u64> {
    let term = status
        .owner_terms
        .iter()
        .find(|t| t.planner_id == pid && t.owner_epoch > after && t.views_executed >= views)?;
    Some(term.owner_epoch)
}

/// How the owner is lost for a while.
#[derive(Clone, Copy, Debug)]
enum OwnerFault {
    /// SIGSTOP, then SIGCONT.
    Pause,
    /// Its relay to the router cut, then healed.
    Partition,
}

/// A planner process and the relay it reaches the router through.
struct Planner {
    pid: &'static str,
    process: Proc,
    relay: Proc,
}

impl Planner {
    fn lose(&self, fault: OwnerFault) {
        match fault {
            OwnerFault::Pause => self.process.pause(),
            OwnerFault::Partition => self.relay.cut(),
        }
    }

    fn restore(&self, fault: OwnerFault) {
        match fault {
            OwnerFault::Pause => self.process.resume(),
            OwnerFault::Partition => self.relay.heal(),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_paused_owner_that_wakes_up_moves_no_arm() {
    owner_lost_and_back_moves_no_arm(OwnerFault::Pause).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_owner_cut_off_and_healed_moves_no_arm() {
    owner_lost_and_back_moves_no_arm(OwnerFault::Partition).await;
}

async fn owner_lost_and_back_moves_no_arm(fault: OwnerFault) {
    build_binaries();
    let logs = std::env::temp_dir().join(format!(
        "glasshouse-fencing-{fault:?}-{}",
        std::process::id()
    ));
    std::fs::create_dir_all(&logs).expect("log dir");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    // A short lease: a hung process is dropped after 1 s instead of Zenoh's 10 s.
    let base = [
        "-e",
        endpoint.as_str(),
        "--mode",
        "client",
        "--lease-ms",
        "1000",
    ];
    let start = |name: &'static str, bin: &str, extra: &[&str]| {
        let args: Vec<&str> = base.iter().chain(extra).copied().collect();
        Proc::start(name, bin, &args, &logs)
    };
    let _router = Proc::start("router", "glasshouse", &["router", "-l", &endpoint], &logs);
    let observer = client(&endpoint).await;
    let status_sub = observe(&observer, &keys::status("t1").expect("key")).await;
    let views_sub = observe(&observer, &keys::views_from_any("t1").expect("key")).await;
    let planner_sub = observe(&observer, &keys::all_planner_status()).await;
    let clouds_sub = observe(&observer, &keys::roi_from_any("t1").expect("key")).await;
    let _detector = start("detector", "detector-service", &[]);
    let planner = |pid: &'static str, name: &'static str, relay_name: &'static str| {
        let relayed = format!("tcp/127.0.0.1:{}", free_port());
        let relay_args = ["relay", "--listen", &relayed, "--to", &endpoint];
        let relay = Proc::start(relay_name, "glasshouse", &relay_args, &logs);
        let args = [
            "-e",
            &relayed,
            "--mode",
            "client",
            "--lease-ms",
            "1000",
            "--planner-id",
            pid,
            "--replica-refresh-clouds",
            "2",
        ];
        let process = Proc::start(name, "planner-service", &args, &logs);
        Planner {
            pid,
            process,
            relay,
        }
    };
    let planners = [
        planner("p1", "planner-p1", "relay-p1"),
        planner("p2", "planner-p2", "relay-p2"),
    ];
    within(60, "both planners report", async {
        let mut seen = std::collections::BTreeSet::new();
        while seen.len() < 2 {
            seen.insert(planner_sub.recv().await.expect("status").message.planner_id);
        }
    })
    .await;
    let config = logs.join("edge.json5");
    std::fs::write(&config, "{ views_timeout_ms: 2000 }").expect("edge config");
    let config = config.to_string_lossy().into_owned();
    let edge = start(
        "edge",
        "edge",
        &[
            "-c",
            &config,
            "--trolley-id",
            "t1",
            "--scenario",
            "2",
            "--width",
            "160",
        ],
    );

    // 1. The owner serves the trolley: three views executed under its term.
    let (owner, old_epoch, owners_views) =
        within(240, "three views executed under the owner's term", async {
            let mut last_views: Option<(Header, RankedViews)> = None;
            loop {
                tokio::select! {
                    received = views_sub.recv() => {
                        let received = received.expect("views");
                        last_views = Some((received.header, received.message));
                    }
                    received = status_sub.recv() => {
                        let status = received.expect("status").message;
                        let (Some(term), Some(views)) = (status.owner_terms.last(), &last_views)
                        else {
                            continue;
                        };
                        let from_term = views.1.planner_id == term.planner_id
                            && views.1.owner_epoch == term.owner_epoch;
                        if term.views_executed >= 3 && from_term {
                            return (term.planner_id.clone(), term.owner_epoch, views.clone());
                        }
                    }
                }
            }
        })
        .await;
    assert_ne!(old_epoch, 0, "the owner's views carry its term");
    let lost = planners
        .iter()
        .find(|p| p.pid == owner)
        .expect("the owner is one of ours");
    let other = if owner == "p1" { "p2" } else { "p1" };
    eprintln!("owner {owner} under epoch {old_epoch}: {fault:?}");
    lost.lose(fault);

    // 2. The other planner takes over under a newer term; the trolley is served again.
    let (new_epoch, takeover) = within(
        120,
        "views executed under the other planner's term",
        async {
            loop {
                let received = status_sub.recv().await.expect("status");
                if let Some(epoch) = term_after(&received.message, other, old_epoch, 2) {
                    return (epoch, received);
                }
            }
        },
    )
    .await;
    let at_takeover = takeover.message;
    let old_executed = executed(&at_takeover, &owner, old_epoch);
    eprintln!(
        "{other} took over under epoch {new_epoch}; {old_executed} views executed under {owner}'s term"
    );

    // 3. A copy of the paused owner's last views, delayed past the takeover (as a partition or a
    // queue may deliver it), aimed at the frame the edge announced last: refused as stale.
    let mut frame = (takeover.header.epoch_ns, takeover.header.seq);
    let mut stale_before = at_takeover.stale_views;
    while let Some(received) = status_sub.try_recv() {
        frame = (received.header.epoch_ns, received.header.seq);
        stale_before = received.message.stale_views;
    }
    let (header, views) = owners_views;
    let header = Header {
        seq: frame.1,
        ..header
    };
    let views = RankedViews {
        based_on_epoch_ns: frame.0,
        based_on_seq: frame.1,
        ..views
    };
    let delayed = Publisher::declare(
        &observer,
        &keys::views("t1", &header.source_id).expect("key"),
        Arc::new(DropCounters::default()),
    )
    .await
    .expect("publisher");
    delayed.publish(&header, &views).await.expect("published");
    let counted = within(
        60,
        "the delayed views counted as stale by the edge",
        async {
            loop {
                let status = status_sub.recv().await.expect("status").message;
                if status.stale_views > stale_before {
                    return status;
                }
            }
        },
    )
    .await;
    delayed.close().await;
    assert_eq!(executed(&counted, &owner, old_epoch), old_executed);

    // 4. The paused owner resumes. It ranks first again once its token is back: it must step
    // down, catch up from the other planner and serve the trolley under a newer term.
    eprintln!("{owner} back from {fault:?}");
    lost.restore(fault);
    let (resumed_epoch, last) = within(
        180,
        "views executed under the woken owner's new term",
        async {
            loop {
                let status = status_sub.recv().await.expect("status").message;
                if let Some(epoch) = term_after(&status, &owner, new_epoch, 3) {
                    return (epoch, status);
                }
            }
        },
    )
    .await;
    let mut planners_seen = std::collections::BTreeMap::new();
    let stepped_down = within(30, "the woken owner reports stepping down", async {
        loop {
            let status: PlannerStatus = planner_sub.recv().await.expect("status").message;
            planners_seen.insert(status.planner_id.clone(), status.stale_epoch);
            if status.planner_id == owner && status.stepped_down >= 1 {
                return status;
            }
        }
    })
    .await;
    eprintln!(
        "{owner} resumed under epoch {resumed_epoch}; the edge refused {} stale view sets ({} of them sent after the takeover by the planners, 1 injected); stale fruits and snapshots dropped by the planners: {planners_seen:?}; terms {:?}",
        last.stale_views,
        last.stale_views.saturating_sub(stale_before + 1),
        last.owner_terms,
    );
    assert!(stepped_down.owned_trolleys.iter().any(|t| t == "t1"));
    // Not one view of the paused owner's old term was executed after the takeover.
    assert_eq!(executed(&last, &owner, old_epoch), old_executed);
    assert!(last.stale_views >= counted.stale_views);
    assert!(last.views_done > at_takeover.views_done);

    // 5. The woken owner's map holds every scan: the snapshot it caught up from and every cloud
    // since. Compared once it is at the last cloud observed (the detector may still publish the
    // edge's last frame after the edge is gone).
    edge.terminate();
    let at_last = snapshot_at_last_cloud(&observer, &clouds_sub, &owner, "t1").await;
    assert!(at_last.owner_epoch >= resumed_epoch);
    assert_holds_every_cloud(&at_last.map, &at_last.clouds, "the woken owner's");
    let _ = observer.close().await;
    drop(planners);
    let _ = std::fs::remove_dir_all(&logs);
}
