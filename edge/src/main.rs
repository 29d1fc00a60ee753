//! `edge`: one trolley on the Glasshouse bus: the simulated glasshouse, recorded frames, or a
//! rosbag2 recording of a ROS 2 camera.

use std::path::PathBuf;

use clap::Parser;
use glasshouse_bus::set_flag;
use glasshouse_edge::EdgeConfig;

/// Streams RGB-D frames and arm state of one trolley and executes the views planners send.
///
/// Sources: `--source sim` (default: the simulated glasshouse), `--source replay DIR` (frames an
/// edge recorded with --record-frames), `--source bag FILE.mcap|BAG_DIR` (a rosbag2 recording of
/// a camera: colour `sensor_msgs/Image` rgb8/bgr8, aligned depth 16UC1 mm or 32FC1 m, its
/// `CameraInfo`, and `/tf` from the world frame to the camera's optical frame, grouped by stamp;
/// topics, frames and the trolley's workspace and robot in the settings file's `ros: { topics:
/// {..}, trolley: {..} }`). With --realtime a bag plays at its recorded speed. `--source ros2`
/// drives a live ROS 2 robot over the edge's Zenoh session the way rmw_zenoh does (same topics,
/// plus `ros.live: { domain_id, node_name, .. }`): the chosen view goes out as
/// `geometry_msgs/PoseStamped`, the ranked views as `PoseArray`, and the arm's driver answers
/// on `view_reached` (`std_msgs/Bool`).
///
/// Settings come from defaults, then `--config FILE` (JSON5 with the fields of EdgeConfig:
/// trolley_id, scenario, seed, width, height, max_views, views_timeout_ms, capture_time_s,
/// frame_interval_ms, segment_length_m, segment_done_utility, source, bag, ros, replay_dir,
/// record_frames_dir, visit,
/// world: { perception: {..}, scene: {..}, pose: {..} }, compress_frames, realtime), then the
/// flags below (`--world` replaces the file's world with a preset, the other world flags
/// override one part of it).
#[derive(Parser, Debug)]
#[command(name = "edge", version)]
struct Cli {
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
    /// Where frames come from: sim, replay (a folder from --record-frames), bag (a rosbag2 MCAP
    /// file or bag folder) or ros2 (a live ROS 2 robot); replay and bag take the PATH that follows.
    #[arg(long, value_enum)]
    source: Option<glasshouse_edge::SourceKind>,
    /// The folder (replay) or bag (bag) of --source.
    #[arg(value_name = "PATH")]
    path: Option<PathBuf>,
    /// Play back the frames recorded in this folder instead of simulating (= --source replay DIR).
    #[arg(long, value_name = "DIR")]
    replay: Option<PathBuf>,
    /// Record every captured frame to this folder (for --replay).
    #[arg(long, value_name = "DIR")]
    record_frames: Option<PathBuf>,
    #[command(flatten)]
    world: glasshouse_edge::WorldArgs,
    /// Send (and record) frames uncompressed: 1.5 MB per 640x480 frame instead of ~0.13 MB, for
    /// readers that predate the frame encodings.
    #[arg(long)]
    raw_frames: bool,
    /// Run in real time: wait out each view's simulated arm motion and capture time (seconds,
    /// from the arm's joint speed limits) in wall-clock time before the next capture.
    #[arg(long)]
    realtime: bool,
    /// Which visit of its row this run is (0: the first; one more per pass of the row, days
    /// apart): a planner starts a later visit from the previous visit's map as a prior and
    /// keeps each fruit's id and history from visit to visit.
    #[arg(long, value_name = "N")]
    visit: Option<u32>,
}

fn main() -> anyhow::Result<()> {
    glasshouse_bus::service_main(apply_flags, |session, config, shutdown, counters| {
        glasshouse_edge::run(session, config, shutdown, None, counters)
    })
}

fn apply_flags(cli: Cli, c: &mut EdgeConfig) -> anyhow::Result<()> {
    set_flag(&mut c.trolley_id, cli.trolley_id);
    set_flag(&mut c.scenario, cli.scenario);
    set_flag(&mut c.seed, cli.seed);
    set_flag(&mut c.max_views, cli.max_views);
    set_flag(&mut c.frame_interval_ms, cli.frame_interval_ms);
    set_flag(&mut c.visit, cli.visit);
    if let Some(width) = cli.width {
        c.width = width;
        c.height = cli.height.unwrap_or(width * 3 / 4);
    } else {
        set_flag(&mut c.height, cli.height);
    }
    set_flag(&mut c.replay_dir, cli.replay.map(Some));
    if let Some(source) = cli.source {
        c.source = source;
    }
    match (c.source, cli.path) {
        (glasshouse_edge::SourceKind::Bag, Some(path)) => c.bag = Some(path),
        (glasshouse_edge::SourceKind::Replay, Some(path)) => c.replay_dir = Some(path),
        (glasshouse_edge::SourceKind::Sim | glasshouse_edge::SourceKind::Ros2, Some(path)) => {
            anyhow::bail!(
                "--source {:?} takes no PATH (got {})",
                c.source,
                path.display()
            )
        }
        _ => {}
    }
    set_flag(&mut c.record_frames_dir, cli.record_frames.map(Some));
    c.world = cli.world.apply_to(c.world)?;
    if cli.raw_frames {
        c.compress_frames = false;
    }
    if cli.realtime {
        c.realtime = true;
    }
    c.validate()
}
