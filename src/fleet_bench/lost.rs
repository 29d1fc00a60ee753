//! Scans lost to the fault: after the measured run, the map of every trolley the fault moved, at
//! the planner that owns it then, is compared voxel for voxel with the map rebuilt offline from
//! every ROI cloud of that trolley the observer saw, through the same planning steps
//! (`TrolleyPlanner::insert`).

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use glasshouse_pipeline::{PlanningSettings, TrolleyPlanner};
use glasshouse_proto::{keys, FrameId, RoiCloud};
use glasshouse_roimap::RoiMap;
use serde::Serialize;

use super::{Observed, Proc};

/// How long the owners have to reach the last cloud observed once the edges are stopped.
const SETTLE: Duration = Duration::from_secs(30);

#[derive(Debug, Serialize)]
pub(super) struct LostReport {
    /// The planner holding the trolley at the end.
    pub survivor: String,
    pub clouds_observed: usize,
    pub scans_in_survivor_map: u64,
    pub scans_rebuilt: u64,
    /// Scans the rebuild holds that the survivor's map does not (0: none lost).
    pub scans_lost: u64,
    /// The survivor's map equals the rebuild voxel for voxel, log-odds bit for bit.
    pub maps_equal: bool,
}

/// Stops the edges of `tids`, waits until each trolley's owner answers with a snapshot at the
/// last cloud observed, and compares its map with the offline rebuild; a trolley whose check
/// failed is reported on stderr and left out.
pub(super) async fn check(
    observer: &glasshouse_bus::zenoh::Session,
    observed: &Mutex<Observed>,
    procs: &mut [Proc],
    tids: &[String],
    settings: &PlanningSettings,
) -> BTreeMap<String, LostReport> {
    for edge in procs
        .iter_mut()
        .filter(|p| p.kind == "edge" && tids.contains(&p.name))
    {
        let _ = edge.child.kill();
        let _ = edge.child.wait();
        edge.killed = true;
    }
    let deadline = Instant::now() + SETTLE;
    let mut reports = BTreeMap::new();
    for tid in tids {
        match check_one(observer, observed, tid, deadline, settings).await {
            Ok(report) => {
                reports.insert(tid.clone(), report);
            }
            Err(e) => eprintln!("fleet-bench: scans lost of {tid} not measured: {e:#}"),
        }
    }
    reports
}

/// Every planner whose latest status lists `tid` (a replaced owner's last status may still), and
/// the clouds of `tid` observed.
fn owners_and_clouds(
    observed: &Mutex<Observed>,
    tid: &str,
) -> anyhow::Result<(Vec<String>, Vec<RoiCloud>)> {
    let o = observed
        .lock()
        .map_err(|_| anyhow::anyhow!("observer state poisoned"))?;
    let owners = o
        .owned
        .iter()
        .filter(|(_, t)| t.iter().any(|t| t == tid))
        .map(|(pid, _)| pid.clone())
        .collect();
    Ok((owners, o.clouds.get(tid).cloned().unwrap_or_default()))
}

async fn check_one(
    observer: &glasshouse_bus::zenoh::Session,
    observed: &Mutex<Observed>,
    tid: &str,
    deadline: Instant,
    settings: &PlanningSettings,
) -> anyhow::Result<LostReport> {
    // What each planner asked last answered: its snapshot's frame, or why it did not answer.
    let mut answers = BTreeMap::new();
    loop {
        let (owners, clouds) = owners_and_clouds(observed, tid)?;
        let last = clouds.iter().map(RoiCloud::source_frame).max();
        for owner in owners {
            let key = keys::planner_snapshot(&owner, tid)?;
            match glasshouse_bus::ask(observer, &key, Duration::from_secs(5)).await {
                Ok((_, s)) if Some(FrameId::new(s.based_on_epoch_ns, s.based_on_seq)) == last => {
                    let survivor = RoiMap::read_snapshot(s.map.as_slice())?;
                    return compare(owner, &survivor, &clouds, settings);
                }
                Ok((_, s)) => {
                    answers.insert(owner, format!("a snapshot at frame {}", s.based_on_seq))
                }
                Err(e) => answers.insert(owner, format!("no snapshot ({e})")),
            };
        }
        anyhow::ensure!(
            Instant::now() < deadline,
            "{tid}'s owner did not reach the last cloud observed (frame {}, {} clouds) within {} s; \
             planners asked: {answers:?}",
            last.map_or(0, |f| f.seq),
            clouds.len(),
            SETTLE.as_secs()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// `settings`: the planners' (the rebuild must integrate as they do).
fn compare(
    survivor: String,
    map: &RoiMap,
    clouds: &[RoiCloud],
    settings: &PlanningSettings,
) -> anyhow::Result<LostReport> {
    let mut rebuilt = TrolleyPlanner::new(settings.clone())?;
    // Later than every frame's stamp: no frame is judged to come from the future.
    let now_ns = u64::try_from(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)?
            .as_nanos(),
    )?;
    for cloud in clouds {
        rebuilt.insert(cloud, now_ns)?;
    }
    let rebuilt = rebuilt.map();
    let same = |a: &RoiMap, b: &RoiMap| {
        a.len() == b.len()
            && a.iter().all(|(k, v)| {
                b.get(k).is_some_and(|w| {
                    (w.occupancy_logodds.to_bits(), w.roi_logodds.to_bits())
                        == (v.occupancy_logodds.to_bits(), v.roi_logodds.to_bits())
                })
            })
    };
    Ok(LostReport {
        survivor,
        clouds_observed: clouds.len(),
        scans_in_survivor_map: map.scans_inserted(),
        scans_rebuilt: rebuilt.scans_inserted(),
        scans_lost: rebuilt
            .scans_inserted()
            .saturating_sub(map.scans_inserted()),
        maps_equal: map.scans_inserted() == rebuilt.scans_inserted() && same(map, rebuilt),
    })
}
