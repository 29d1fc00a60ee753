//! `planner-service`: ROI maps, next best views and fruit estimates for every trolley it hears.

use std::path::PathBuf;
use std::sync::Arc;

use clap::Parser;
use glasshouse_bus::BusArgs;
use glasshouse_planner::{PlannerCounters, PlannerSettings};

/// Integrates ROI clouds into a voxel map per trolley, publishes ranked next best views and
/// fruit estimates.
///
/// Settings: defaults, then `--config FILE` (JSON5: planner_id, status_period_ms, and
/// `planning: { method, seed, resolution_m, max_range_m, min_cluster_voxels, fit,
/// scoring_threads }`), then the flags below.
#[derive(Parser, Debug)]
#[command(name = "planner-service", version)]
struct Cli {
    /// Settings file (JSON5).
    #[arg(short, long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Planner id (one key chunk).
    #[arg(long)]
    planner_id: Option<String>,
    /// Planning method: ours-uu, ours-up, explo-uu or explo-up.
    #[arg(long)]
    method: Option<glasshouse_nbv::Method>,
    /// Planner seed (views are seeded from it and the frame sequence).
    #[arg(long)]
    seed: Option<u64>,
    #[command(flatten)]
    bus: BusArgs,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    glasshouse_bus::init_tracing();
    let cli = Cli::parse();
    let mut settings: PlannerSettings = glasshouse_bus::load_settings(cli.config.as_deref())?;
    if let Some(v) = cli.planner_id {
        settings.planner_id = v;
    }
    if let Some(v) = cli.method {
        settings.planning.method = v;
    }
    if let Some(v) = cli.seed {
        settings.planning.seed = v;
    }
    settings.validate()?;
    let counters = Arc::new(PlannerCounters::default());
    glasshouse_bus::run_service(&cli.bus, |session, shutdown| {
        glasshouse_planner::run(session, settings, shutdown, counters)
    })
    .await
}
