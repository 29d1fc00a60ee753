//! `detector-service`: RGB-D frames in, ROI point clouds out.

use clap::Parser;
use glasshouse_bus::set_flag;
use glasshouse_detector::DetectorSettings;

/// Turns the RGB-D frames of every trolley into ROI-labelled world point clouds (the HSI colour
/// rule, or a learned ONNX segmentation model with --fruit-model).
///
/// Settings: defaults, then `--config FILE` (JSON5: detector_id, voxel_size_m,
/// status_period_ms, fruit_model), then the flags below.
#[derive(Parser, Debug)]
#[command(name = "detector-service", version)]
struct Cli {
    /// Detector id (one key chunk).
    #[arg(long)]
    detector_id: Option<String>,
    /// ONNX fruit segmentation model (e.g. detector-service/model/fruit-segmenter.onnx) to label
    /// fruit with instead of the HSI colour rule; its probabilities go into the clouds.
    #[arg(long, value_name = "FILE")]
    fruit_model: Option<std::path::PathBuf>,
}

fn main() -> anyhow::Result<()> {
    glasshouse_bus::service_main(apply_flags, glasshouse_detector::run)
}

fn apply_flags(cli: Cli, s: &mut DetectorSettings) -> anyhow::Result<()> {
    set_flag(&mut s.detector_id, cli.detector_id);
    set_flag(&mut s.fruit_model, cli.fruit_model.map(Some));
    s.validate()
}
