//! `edge`: one trolley (simulated glasshouse source) on the Glasshouse bus.

use std::path::PathBuf;
use std::sync::Arc;

use clap::Parser;
use glasshouse_bus::BusArgs;
use glasshouse_edge::{EdgeConfig, EdgeCounters};

/// Streams RGB-D frames and arm state of one trolley and executes the views planners send.
///
/// Settings come from defaults, then `--config FILE` (JSON5 with the fields of EdgeConfig:
/// trolley_id, scenario, seed, width, height, max_views, views_timeout_ms, capture_time_s,
/// frame_interval_ms, segment_length_m, segment_done_utility, replay_dir, record_frames_dir), then
/// the flags below.
#[derive(Parser, Debug)]
#[command(name = "edge", version)]
struct Cli {
    /// Settings file (JSON5).
    #[arg(short, long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Trolley id (one key chunk: letters, digits, '-' and '_').
    #[arg(long)]
    trolley_id: Option<String>,
    /// Simulated scenario: 1, 2 or row.
    #[arg(long)]
    scenario: Option<glasshouse_sim::ScenarioKind>,
    /// Scene seed.
    #[arg(long)]
    seed: Option<u64>,
    /// Stop after this many views (0 = run until stopped).
    #[arg(long)]
    max_views: Option<u32>,
    /// Wall-clock milliseconds at least between two captures (200 = 5 frames/s; 0 = as fast as
    /// the views come).
    #[arg(long, value_name = "MS")]
    frame_interval_ms: Option<u64>,
    /// Image width in pixels (height follows at 4:3 unless --height is given).
    #[arg(long)]
    width: Option<u32>,
    /// Image height in pixels.
    #[arg(long)]
    height: Option<u32>,
    /// Play back the frames recorded in this folder instead of simulating.
    #[arg(long, value_name = "DIR")]
    replay: Option<PathBuf>,
    /// Record every captured frame to this folder (for --replay).
    #[arg(long, value_name = "DIR")]
    record_frames: Option<PathBuf>,
    #[command(flatten)]
    bus: BusArgs,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    glasshouse_bus::init_tracing();
    let cli = Cli::parse();
    let mut config: EdgeConfig = glasshouse_bus::load_settings(cli.config.as_deref())?;
    if let Some(v) = cli.trolley_id {
        config.trolley_id = v;
    }
    if let Some(v) = cli.scenario {
        config.scenario = v;
    }
    if let Some(v) = cli.seed {
        config.seed = v;
    }
    if let Some(v) = cli.max_views {
        config.max_views = v;
    }
    if let Some(v) = cli.frame_interval_ms {
        config.frame_interval_ms = v;
    }
    if let Some(w) = cli.width {
        config.width = w;
        config.height = cli.height.unwrap_or(w * 3 / 4);
    } else if let Some(h) = cli.height {
        config.height = h;
    }
    if cli.replay.is_some() {
        config.replay_dir = cli.replay;
    }
    if cli.record_frames.is_some() {
        config.record_frames_dir = cli.record_frames;
    }
    config.validate()?;
    let counters = Arc::new(EdgeCounters::default());
    glasshouse_bus::run_service(&cli.bus, |session, shutdown| {
        glasshouse_edge::run(session, config, shutdown, None, counters)
    })
    .await
}
