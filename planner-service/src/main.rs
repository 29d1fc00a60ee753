//! `planner-service`: ROI maps, next best views and fruit estimates for every trolley it hears.

use clap::Parser;
use glasshouse_bus::set_flag;
use std::path::PathBuf;

use glasshouse_planner::{PlannerSettings, StoreSettings};

/// Integrates ROI clouds into a voxel map per trolley, publishes ranked next best views and
/// fruit estimates.
///
/// Settings: defaults, then `--config FILE` (JSON5: planner_id, status_period_ms,
/// replica_refresh_clouds, takeover_decode_threads, standby_decoded_ahead, refresh_by_delta, `store: { path, checkpoint_clouds, settle_ms, write_delay_ms }` and
/// `planning: { method, seed, resolution_m, max_range_m, merge_far_rays, min_cluster_voxels, fit,
/// scoring_threads, insert_threads, fit_threads }`), then the flags below.
///
/// Environment: GLASSHOUSE_SIMD=portable|avx2|avx512 caps the vector unit of the map's voxel
/// walks (default: the widest the CPU has; every unit gives the same map).
#[derive(Parser, Debug)]
#[command(name = "planner-service", version)]
struct Cli {
    /// Planner id (one key chunk).
    #[arg(long)]
    planner_id: Option<String>,
    /// Planning method: ours-uu, ours-up, explo-uu or explo-up.
    #[arg(long)]
    method: Option<glasshouse_nbv::Method>,
    /// Planner seed (views are seeded from it and the frame sequence).
    #[arg(long)]
    seed: Option<u64>,
    /// Clouds a standby replica keeps before it asks the owner for a snapshot (default 8; a
    /// takeover integrates at most this many); 0 makes replicas integrate every cloud.
    #[arg(long)]
    replica_refresh_clouds: Option<usize>,
    /// Snapshots of trolleys taken over together (a lost planner's) decoded at once, a thread
    /// each, before the first is planned on (default 8); 1 decodes each trolley at its own
    /// catch-up, one after another.
    #[arg(long)]
    takeover_decode_threads: Option<usize>,
    /// Whether a standby replica decodes each snapshot it holds in the background (on idle
    /// cores), so that a takeover need not decode (default true); false keeps standby copies
    /// encoded only, at about a tenth of the memory, and decodes at the takeover.
    #[arg(long, value_name = "BOOL")]
    standby_decoded_ahead: Option<bool>,
    /// Whether a standby replica with a decoded copy asks its owner for only the map's blocks
    /// changed since what it holds (default true); false asks for the whole map every time.
    #[arg(long, value_name = "BOOL")]
    refresh_by_delta: Option<bool>,
    /// Threads that cast one cloud's rays into its map (default 0: one per core; the map is
    /// the same, voxel for voxel, for any count).
    #[arg(long, value_name = "N")]
    insert_threads: Option<usize>,
    /// Threads that split and fit the fruit clusters a cloud changed (default 0: one per
    /// core; the fruits are the same for any count).
    #[arg(long, value_name = "N")]
    fit_threads: Option<usize>,
    /// Integrate each cloud's rays up to this range, metres (default 2.0; points further
    /// away free their ray up to it and mark nothing).
    #[arg(long, value_name = "M")]
    max_range: Option<f64>,
    /// Points beyond the range free one ray per voxel at the range (aimed at its centre)
    /// instead of one each (default true; false: one ray per point, as OctoMap); points within
    /// the range are unaffected.
    #[arg(long, value_name = "BOOL")]
    merge_far_rays: Option<bool>,
    /// Whether an ROI patch the fruit evidence turns away (too small, flat, hiding nothing)
    /// is searched for a fruit's body in the occupancy map around it, and reported as a fruit
    /// when one is found (default true: a leaf-coloured fruit in shade is labelled only in
    /// patches).
    #[arg(long, value_name = "BOOL")]
    body_search: Option<bool>,
    /// Keep every trolley this planner owns in this store file (created if missing; one per
    /// planner), so that maps and fruit ids survive a restart of every planner. Without it maps
    /// live in memory only. The planner then waits `store.settle_ms` (3 s) for its peers
    /// before it takes on trolleys.
    #[arg(long, value_name = "FILE")]
    store: Option<PathBuf>,
    /// Fault injection for benchmarks and tests: every store transaction waits this long
    /// first, as on a slow or overloaded disk (default 0). A trolley's views still go out only once their
    /// cloud is stored; the planner serves the others meanwhile.
    #[arg(long, value_name = "MS", requires = "store")]
    store_write_delay_ms: Option<u64>,
}

fn main() -> anyhow::Result<()> {
    glasshouse_planner::cap_simd_from_env()?;
    glasshouse_bus::service_main(apply_flags, glasshouse_planner::run)
}

fn apply_flags(cli: Cli, s: &mut PlannerSettings) -> anyhow::Result<()> {
    set_flag(&mut s.planner_id, cli.planner_id);
    set_flag(&mut s.planning.method, cli.method);
    set_flag(&mut s.planning.seed, cli.seed);
    set_flag(&mut s.replica_refresh_clouds, cli.replica_refresh_clouds);
    set_flag(&mut s.takeover_decode_threads, cli.takeover_decode_threads);
    set_flag(&mut s.standby_decoded_ahead, cli.standby_decoded_ahead);
    set_flag(&mut s.refresh_by_delta, cli.refresh_by_delta);
    set_flag(&mut s.planning.insert_threads, cli.insert_threads);
    set_flag(&mut s.planning.fit_threads, cli.fit_threads);
    set_flag(&mut s.planning.max_range_m, cli.max_range);
    set_flag(&mut s.planning.merge_far_rays, cli.merge_far_rays);
    set_flag(&mut s.planning.fit.evidence.body.enabled, cli.body_search);
    if let Some(path) = cli.store {
        s.store = Some(StoreSettings {
            path,
            ..s.store.take().unwrap_or_default()
        });
    }
    if let (Some(store), Some(delay)) = (s.store.as_mut(), cli.store_write_delay_ms) {
        store.write_delay_ms = delay;
    }
    s.validate()
}
