//! Scans lost in the takeover: after the measured run, t1's map at the planner that owns it
//! then (the survivor of the kill) is compared voxel for voxel with the map rebuilt offline from
//! every ROI cloud of t1 the observer saw, through the same planning steps
//! (`TrolleyPlanner::insert`).

use std::sync::Mutex;
use std::time::{Duration, Instant};

use glasshouse_pipeline::{PlanningSettings, TrolleyPlanner};
use glasshouse_proto::{keys, FrameId, RoiCloud};
use glasshouse_roimap::RoiMap;
use serde::Serialize;

use super::{Observed, Proc};

/// How long the survivor has to reach the last cloud observed once t1's edge is stopped.
const SETTLE: Duration = Duration::from_secs(30);

#[derive(Debug, Serialize)]
pub(super) struct LostReport {
    /// The planner holding t1 at the end.
    pub survivor: String,
    pub clouds_observed: usize,
    pub scans_in_survivor_map: u64,
    pub scans_rebuilt: u64,
    /// Scans the rebuild holds that the survivor's map does not (0: none lost).
    pub scans_lost: u64,
    /// The survivor's map equals the rebuild voxel for voxel, log-odds bit for bit.
    pub maps_equal: bool,
}

/// Stops t1's edge, waits until t1's owner answers with a snapshot at the last cloud observed,
/// and compares its map with the offline rebuild.
pub(super) async fn check_t1(
    observer: &glasshouse_bus::zenoh::Session,
    observed: &Mutex<Observed>,
    procs: &mut [Proc],
) -> anyhow::Result<LostReport> {
    if let Some(edge) = procs
        .iter_mut()
        .find(|p| p.kind == "edge" && p.name == "t1")
    {
        let _ = edge.child.kill();
        let _ = edge.child.wait();
        edge.killed = true;
    }
    let deadline = Instant::now() + SETTLE;
    loop {
        // Every planner whose latest status lists t1: the killed owner's last status may still
        // list it.
        let (clouds, owners) = {
            let o = observed
                .lock()
                .map_err(|_| anyhow::anyhow!("observer state poisoned"))?;
            let owners: Vec<String> = o
                .owned
                .iter()
                .filter(|(_, t)| t.iter().any(|t| t == "t1"))
                .map(|(pid, _)| pid.clone())
                .collect();
            (o.t1_clouds.clone(), owners)
        };
        let last = clouds.iter().map(RoiCloud::source_frame).max();
        for owner in owners {
            let key = keys::planner_snapshot(&owner, "t1")?;
            if let Ok((_, s)) = glasshouse_bus::ask(observer, &key, Duration::from_secs(5)).await {
                if Some(FrameId::new(s.based_on_epoch_ns, s.based_on_seq)) == last {
                    let survivor = RoiMap::read_snapshot(s.map.as_slice())?;
                    return compare(owner, &survivor, &clouds);
                }
            }
        }
        anyhow::ensure!(
            Instant::now() < deadline,
            "t1's owner did not reach the last cloud observed within {} s",
            SETTLE.as_secs()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

fn compare(survivor: String, map: &RoiMap, clouds: &[RoiCloud]) -> anyhow::Result<LostReport> {
    let mut rebuilt = TrolleyPlanner::new(PlanningSettings::default())?;
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
