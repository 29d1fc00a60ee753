//! `detector-service`: RGB-D frames in, ROI point clouds out.

use std::path::PathBuf;
use std::sync::Arc;

use clap::Parser;
use glasshouse_bus::BusArgs;
use glasshouse_detector::{DetectorCounters, DetectorSettings};

/// Turns the RGB-D frames of every trolley into ROI-labelled world point clouds (HSI rule).
///
/// Settings: defaults, then `--config FILE` (JSON5: detector_id, voxel_size_m,
/// status_period_ms), then the flags below.
#[derive(Parser, Debug)]
#[command(name = "detector-service", version)]
struct Cli {
    /// Settings file (JSON5).
    #[arg(short, long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Detector id (one key chunk).
    #[arg(long)]
    detector_id: Option<String>,
    #[command(flatten)]
    bus: BusArgs,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    glasshouse_bus::init_tracing();
    let cli = Cli::parse();
    let mut settings: DetectorSettings = glasshouse_bus::load_settings(cli.config.as_deref())?;
    if let Some(v) = cli.detector_id {
        settings.detector_id = v;
    }
    settings.validate()?;
    let counters = Arc::new(DetectorCounters::default());
    glasshouse_bus::run_service(&cli.bus, |session, shutdown| {
        glasshouse_detector::run(session, settings, shutdown, counters)
    })
    .await
}
