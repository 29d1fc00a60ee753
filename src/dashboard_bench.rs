//! `glasshouse dashboard-bench`: does the dashboard keep up with a fleet, in bounded memory?
//!
//! Synthetic trolleys (one Zenoh session each) publish full-size frames, arm states, ROI clouds,
//! views, fruits and map deltas at a fixed rate through an in-process router to a dashboard that
//! serves its web page (and optionally records). Every few seconds it prints the process's
//! resident memory and what the dashboard handled and dropped.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use glasshouse_bus::zenoh::Session;
use glasshouse_bus::{BusArgs, DropCounters, Publisher, Shutdown};
use glasshouse_dashboard::{DashboardCounters, DashboardSettings, FleetState};
use glasshouse_proto::keys;
use glasshouse_proto::{
    samples, ArmState, FrameId, FruitEstimates, Header, MapUpdate, RankedViews, RgbdFrame,
    RoiCloud, TrolleyStatus, VoxelChange,
};
use nalgebra::Point3;

#[derive(clap::Args, Debug)]
pub struct DashboardBenchArgs {
    /// Number of synthetic trolleys.
    #[arg(long, default_value_t = 8)]
    pub trolleys: usize,
    /// Frames per second per trolley (each frame also brings a cloud, views, fruits, a map delta).
    #[arg(long, default_value_t = 5.0)]
    pub fps: f64,
    /// Run time in minutes.
    #[arg(long, default_value_t = 2.0)]
    pub minutes: f64,
    /// Frame width in pixels (height 3/4 of it).
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Also record to this .rrd file.
    #[arg(long)]
    pub record: Option<std::path::PathBuf>,
}

/// Resident memory of this process in bytes (Linux).
fn rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

fn synthetic_frame(width: u32, seq: u64) -> RgbdFrame {
    let intrinsics = glasshouse_geom::CameraIntrinsics::from_horizontal_fov(
        width,
        width * 3 / 4,
        80f64.to_radians(),
    );
    let pixels = intrinsics.pixel_count();
    RgbdFrame {
        intrinsics,
        depth: (0..pixels)
            .map(|i| 500 + ((i as u64 + seq) % 2000) as u16)
            .collect(),
        rgb: (0..pixels * 3)
            .map(|i| (i as u64 * 31 + seq) as u8)
            .collect(),
        ..samples::rgbd_frame()
    }
}

fn synthetic_cloud(frame: FrameId) -> RoiCloud {
    let seq = frame.seq;
    let points: Vec<Point3<f32>> = (0..20_000)
        .map(|i| {
            let f = i as f32;
            Point3::new(
                (f * 0.37).sin(),
                (f * 0.11).cos(),
                0.5 + (f * 0.05).sin() * 0.5,
            )
        })
        .collect();
    let roi: Vec<bool> = (0..points.len()).map(|i| i % 17 == 0).collect();
    // Red fruit points, as a detector sends them.
    let roi_rgb = [190, 35, 25].repeat(roi.iter().filter(|&&r| r).count());
    RoiCloud {
        points_in_world: points,
        roi,
        sensor_origin_in_world: Point3::new(0.0, -0.5, 1.0),
        world_from_camera: nalgebra::Isometry3::translation(0.0, -0.5, 1.0),
        source_frame_seq: seq,
        source_frame_epoch_ns: frame.epoch_ns,
        invalid_pixels: 0,
        detector_id: "bench".into(),
        roi_confidence: Vec::new(),
        roi_rgb,
    }
}

fn synthetic_map(seq: u64) -> MapUpdate {
    let mut m = samples::map_update();
    // A few thousand changed solid voxels per frame, moving through space so the folded map
    // grows like a real one.
    m.voxels = (0..2_000)
        .map(|i| VoxelChange {
            key: [(seq % 200) as i32, i % 50, i / 50],
            ..m.voxels[0]
        })
        .collect();
    m.map_seq = seq;
    m
}

/// What one synthetic trolley publishes, with the traffic of a trolley, its detector and its
/// planner.
struct TrolleyPublishers {
    rgbd: Publisher<RgbdFrame>,
    arm: Publisher<ArmState>,
    roi: Publisher<RoiCloud>,
    views: Publisher<RankedViews>,
    fruits: Publisher<FruitEstimates>,
    map: Publisher<MapUpdate>,
    status: Publisher<TrolleyStatus>,
}

impl TrolleyPublishers {
    async fn declare(session: &Session, tid: &str) -> anyhow::Result<Self> {
        let drops = Arc::new(DropCounters::default());
        Ok(Self {
            rgbd: Publisher::declare(session, &keys::rgbd(tid)?, drops.clone()).await?,
            arm: Publisher::declare(session, &keys::arm(tid)?, drops.clone()).await?,
            roi: Publisher::declare(session, &keys::roi(tid, "d1")?, drops.clone()).await?,
            views: Publisher::declare(session, &keys::views(tid, "p1")?, drops.clone()).await?,
            fruits: Publisher::declare(session, &keys::fruits(tid)?, drops.clone()).await?,
            map: Publisher::declare(session, &keys::map(tid)?, drops.clone()).await?,
            status: Publisher::declare(session, &keys::status(tid)?, drops).await?,
        })
    }

    async fn publish(&self, header: &Header, width: u32) -> anyhow::Result<()> {
        let seq = header.seq;
        let views = RankedViews {
            based_on_seq: seq,
            based_on_epoch_ns: header.epoch_ns,
            ..samples::ranked_views()
        };
        self.rgbd
            .publish(header, &synthetic_frame(width, seq))
            .await?;
        self.arm.publish(header, &samples::arm_state()).await?;
        self.roi
            .publish(header, &synthetic_cloud(header.frame()))
            .await?;
        self.views.publish(header, &views).await?;
        self.fruits
            .publish(header, &samples::fruit_estimates())
            .await?;
        self.map.publish(header, &synthetic_map(seq)).await?;
        self.status
            .publish(header, &samples::trolley_status())
            .await?;
        Ok(())
    }

    async fn close(self) {
        self.rgbd.close().await;
        self.arm.close().await;
        self.roi.close().await;
        self.views.close().await;
        self.fruits.close().await;
        self.map.close().await;
        self.status.close().await;
    }
}

async fn trolley(
    endpoint: String,
    tid: String,
    args_fps: f64,
    width: u32,
    mut stop: Shutdown,
) -> anyhow::Result<u64> {
    let session = glasshouse_bus::open(&BusArgs::client(&endpoint)).await?;
    let publishers = TrolleyPublishers::declare(&session, &tid).await?;
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / args_fps.max(0.1)));
    let mut seq = 0u64;
    let epoch_ns = glasshouse_bus::wall_clock_ns();
    loop {
        tokio::select! {
            _ = stop.wait() => break,
            _ = tick.tick() => {}
        }
        seq += 1;
        let header = Header {
            seq,
            epoch_ns,
            stamp_ns: seq * 200_000_000,
            trolley_id: tid.clone(),
            source_id: tid.clone(),
            frame_id: "world".into(),
        };
        publishers.publish(&header, width).await?;
    }
    publishers.close().await;
    let _ = session.close().await;
    Ok(seq)
}

pub async fn run(args: DashboardBenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.trolleys >= 1 && args.fps > 0.0 && args.minutes > 0.0,
        "need trolleys >= 1, fps > 0, minutes > 0"
    );
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let router = glasshouse_bus::open(&BusArgs::router(&endpoint)).await?;
    let (trigger, stop) = Shutdown::new();
    let fleet = Arc::new(Mutex::new(FleetState::default()));
    let counters = Arc::new(DashboardCounters::default());
    let dashboard = tokio::spawn(glasshouse_dashboard::run(
        glasshouse_bus::open(&BusArgs::client(&endpoint)).await?,
        DashboardSettings {
            record: args.record.clone(),
            serve: None,
            http_listen: Some("127.0.0.1:0".into()),
            mcap: None,
            foxglove: None,
        },
        stop.clone(),
        fleet.clone(),
        counters.clone(),
    ));
    let rss_start = rss_bytes().unwrap_or(0);
    let mut trolleys = Vec::new();
    for i in 0..args.trolleys {
        trolleys.push(tokio::spawn(trolley(
            endpoint.clone(),
            format!("bench{i}"),
            args.fps,
            args.width,
            stop.clone(),
        )));
    }
    println!(
        "dashboard-bench: {} trolleys x {} frames/s ({}x{} frames) for {} min",
        args.trolleys,
        args.fps,
        args.width,
        args.width * 3 / 4,
        args.minutes
    );
    let samples_rss = sample_memory(&args, &fleet, &counters).await;
    trigger.fire();
    let mut frames = 0;
    for t in trolleys {
        frames += t.await??;
    }
    dashboard.await??;
    let _ = router.close().await;
    let messages = fleet.lock().map(|f| f.messages).unwrap_or(0);
    print_totals(&args, frames, messages, &counters, rss_start, &samples_rss);
    Ok(())
}

/// Prints memory and throughput every 10 s for the run's length; returns (seconds, RSS bytes)
/// of every sample.
async fn sample_memory(
    args: &DashboardBenchArgs,
    fleet: &Mutex<FleetState>,
    counters: &DashboardCounters,
) -> Vec<(f64, u64)> {
    println!(
        "{:>7}  {:>9}  {:>10}  {:>10}  {:>9}",
        "time s", "RSS MiB", "messages", "msg/s", "dropped"
    );
    let started = Instant::now();
    let total = Duration::from_secs_f64(args.minutes * 60.0);
    let (mut last_messages, mut last_t) = (0u64, 0.0f64);
    let mut samples_rss = Vec::new();
    while started.elapsed() < total {
        tokio::time::sleep(Duration::from_secs(10).min(total.saturating_sub(started.elapsed())))
            .await;
        let t = started.elapsed().as_secs_f64();
        let messages = fleet.lock().map(|f| f.messages).unwrap_or(0);
        let rss = rss_bytes().unwrap_or(0);
        samples_rss.push((t, rss));
        println!(
            "{t:>7.0}  {:>9.1}  {messages:>10}  {:>10.0}  {:>9}",
            mib(rss),
            (messages - last_messages) as f64 / (t - last_t).max(1e-3),
            counters.drops.total()
        );
        (last_messages, last_t) = (messages, t);
    }
    samples_rss
}

fn print_totals(
    args: &DashboardBenchArgs,
    frames: u64,
    messages: u64,
    counters: &DashboardCounters,
    rss_start: u64,
    samples_rss: &[(f64, u64)],
) {
    let half = samples_rss
        .iter()
        .find(|(t, _)| *t >= args.minutes * 30.0)
        .map_or(0, |s| s.1);
    let end = samples_rss.last().map_or(0, |s| s.1);
    let peak = samples_rss.iter().map(|s| s.1).max().unwrap_or(0);
    println!(
        "published {frames} frames; dashboard handled {messages} messages, dropped {} (overflow {}, corrupt {})",
        counters.drops.total(),
        counters.drops.overflow.load(std::sync::atomic::Ordering::Relaxed),
        counters.drops.corrupt.load(std::sync::atomic::Ordering::Relaxed)
    );
    println!(
        "RSS: start {:.1} MiB, half-time {:.1} MiB, end {:.1} MiB, peak {:.1} MiB (growth over the second half {:+.1} MiB)",
        mib(rss_start),
        mib(half),
        mib(end),
        mib(peak),
        mib(end) - mib(half)
    );
}
