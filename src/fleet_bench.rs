//! `glasshouse fleet-bench`: the whole fleet as real processes on this machine over loopback
//! Zenoh (a router, detectors, planners, simulated trolleys), measured from outside.
//!
//! An observer session records, per trolley, when each frame, its ROI cloud and the views planned
//! on it arrive (the first arrival of each frame sequence), which planner sent the views, and the
//! drop counters every service reports in its status. Each process's CPU time and peak resident
//! memory come from `/proc`. Half-way through (`--fault-at-s`) a fault is injected (`--fault`:
//! the owner of t1 killed, paused or cut off, the router restarted or lost to a second one); for
//! every trolley it moved the report gives the time until its views came again, whether its arm
//! moved on a stale owner's views, and whether its map equals one rebuilt from every cloud
//! (`fault`, `lost`).
//!
//! Several trolley counts (`--trolleys 4,8,16,24`) make a capacity sweep: one fleet per count,
//! one after the other, then a table with a row per count and, with `--plot`, a PNG of frame ->
//! views latency against trolleys (`sweep`).

mod cost;
mod fault;
mod lost;
mod sweep;
mod tail;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{ensure, Context};
use glasshouse_bus::BusArgs;
use glasshouse_proto::keys::{self, ParsedKey, TrolleyTopic};
use glasshouse_proto::{decode_as, Header, Message, StageTimes};
use indicatif::ProgressStyle;

use crate::progress::Progress;
use serde::Serialize;

#[derive(clap::Args, Debug)]
pub struct FleetBenchArgs {
    /// Simulated trolleys (one edge process each, trolley ids t1..tN, seeds 1..N). Several
    /// counts, comma-separated (4,8,16,24), make a capacity sweep: one fleet per count, run one
    /// after the other, and a table with a row per count.
    #[arg(
        long = "trolleys",
        value_name = "N[,N...]",
        value_delimiter = ',',
        default_value = "8"
    )]
    pub trolley_counts: Vec<u32>,
    /// The count of the run in progress (one of `trolley_counts`).
    #[arg(skip)]
    pub trolleys: u32,
    /// Planner processes (p1..pN).
    #[arg(long, default_value_t = 3)]
    pub planners: u32,
    /// Detector processes (d1..dN).
    #[arg(long, default_value_t = 2)]
    pub detectors: u32,
    /// Simulated scenario of every trolley: 1, 2 or row.
    #[arg(long, default_value = "row")]
    pub scenario: String,
    /// Length of the measured run.
    #[arg(long, default_value_t = 2.0)]
    pub minutes: f64,
    /// Frames per second each trolley streams at most.
    #[arg(long, default_value_t = 5.0)]
    pub fps: f64,
    /// Image width (height 3/4 of it).
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// The fault injected during the run: planner faults hit the owner of t1 (kill, stop,
    /// partition), router faults every trolley (router-restart, router-failover).
    #[arg(long, value_enum, default_value = "kill")]
    pub fault: fault::Fault,
    /// Seconds into the run at which the fault is injected (0: never; default: half-way).
    #[arg(long, alias = "kill-at-s")]
    pub fault_at_s: Option<f64>,
    /// How long a stop, partition or router restart lasts before it is undone (SIGCONT, healed,
    /// a new router) [default: 10 s for stop and partition, 1 s for router-restart].
    #[arg(long)]
    pub fault_for_s: Option<f64>,
    /// Zenoh link lease of every process: how soon a killed planner is noticed.
    #[arg(long, default_value_t = 1000)]
    pub lease_ms: u64,
    /// Also write the report as JSON here (a sweep: every count's report, in a list).
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
    /// Also draw p99 (and p50) frame -> views against trolleys as a PNG here.
    #[arg(long, value_name = "FILE")]
    pub plot: Option<PathBuf>,
    /// Keep the processes' logs in this folder (default: a temporary one, removed); a sweep
    /// keeps each count's in DIR/<N>-trolleys.
    #[arg(long, value_name = "DIR")]
    pub logs: Option<PathBuf>,
    /// Run every edge with --realtime: each view's simulated arm motion and capture time
    /// (seconds) passes in wall-clock time, as on a real trolley.
    #[arg(long)]
    pub realtime: bool,
    /// Record the whole run to MCAP in DIR with `glasshouse record` (a process beside the fleet)
    /// and report what it wrote, dropped and cost on disk per frame.
    #[arg(long, value_name = "DIR")]
    pub record: Option<PathBuf>,
    /// Run the fleet secured: a fresh PKI in the logs folder, every process its own identity
    /// over mutual TLS, the router with the generated ACL (what `glasshouse secure` deploys), to
    /// measure what TLS and the ACL cost against a plain run.
    #[arg(long)]
    pub secure: bool,
    /// Every planner's `--replica-refresh-clouds`: clouds a standby replica keeps before it
    /// asks the owner for a snapshot (planner default 8); 0: replicas integrate every cloud.
    #[arg(long)]
    pub replica_refresh_clouds: Option<usize>,
    /// Every planner's `--takeover-decode-threads`: snapshots of trolleys taken over together
    /// decoded at once (planner default 8); 1: each at its own catch-up, one after another.
    #[arg(long)]
    pub takeover_decode_threads: Option<usize>,
    /// Every planner's `--standby-decoded-ahead`: whether standby replicas decode the snapshots
    /// they hold in the background, on idle cores (planner default true).
    #[arg(long, value_name = "BOOL")]
    pub standby_decoded_ahead: Option<bool>,
    /// Every planner's `--refresh-by-delta`: whether standby replicas with a decoded copy ask
    /// for only the map's blocks changed since (planner default true).
    #[arg(long, value_name = "BOOL")]
    pub refresh_by_delta: Option<bool>,
    /// Every planner's `--insert-threads`: threads that cast one cloud's rays into its map
    /// (planner default 0: one per core; the map is the same for any count).
    #[arg(long, value_name = "N")]
    pub insert_threads: Option<usize>,
    /// Every planner's `--fit-threads`: threads that split and fit the fruit clusters a cloud
    /// changed (planner default 0: one per core; the fruits are the same for any count).
    #[arg(long, value_name = "N")]
    pub fit_threads: Option<usize>,
    /// Every planner's `--max-range`: the range, metres, up to which a cloud's rays are
    /// integrated (planner default 2.0).
    #[arg(long, value_name = "M")]
    pub max_range: Option<f64>,
    /// Every planner's `--merge-far-rays`: points beyond the range free one ray per voxel at
    /// the range instead of one each (planner default true).
    #[arg(long, value_name = "BOOL")]
    pub merge_far_rays: Option<bool>,
    /// Every planner's `--body-search`: whether turned-away ROI patches are searched for a
    /// fruit's body under them (planner default true).
    #[arg(long, value_name = "BOOL")]
    pub body_search: Option<bool>,
    /// The simulated trolleys (edge processes) run at this nice value. On a real fleet each
    /// trolley renders nothing and runs on its own computer; here 16 simulators share the
    /// services' cores, and at nice 0 they take them from the planners in turn. 0 runs them
    /// as the services run.
    #[arg(long, value_name = "NICE", default_value_t = 0, value_parser = clap::value_parser!(i32).range(0..=19))]
    pub trolley_nice: i32,
    /// Every planner keeps its trolleys in a store, DIR/<planner>.redb (`planner-service
    /// --store`); `glasshouse bench-store` measures what a store writes per frame. `--fault
    /// restart-all` uses stores in the logs folder when this is not given.
    #[arg(long, value_name = "DIR")]
    pub store: Option<PathBuf>,
    /// A slow disk under every planner's store (`planner-service --store-write-delay-ms`):
    /// each store transaction waits this long first. Needs `--store`.
    #[arg(long, value_name = "MS", requires = "store")]
    pub store_write_delay_ms: Option<u64>,
}

/// One process of the fleet.
struct Proc {
    kind: &'static str,
    name: String,
    child: Child,
    /// CPU seconds (user + system) at the start of the measured run.
    cpu_at_start_s: f64,
    peak_rss_kib: u64,
    killed: bool,
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn clock_ticks_per_s() -> f64 {
    // Linux's USER_HZ is 100 on every architecture Rust supports.
    100.0
}

/// CPU seconds of a process so far, from /proc/<pid>/stat (fields 14 and 15).
fn cpu_seconds(pid: u32) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name may hold spaces: fields start after the closing parenthesis.
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / clock_ticks_per_s())
}

fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
}

fn spawn(
    kind: &'static str,
    name: String,
    (bin, nice): (&Path, i32),
    args: &[String],
    logs: &Path,
) -> anyhow::Result<Proc> {
    let log = std::fs::File::create(logs.join(format!("{name}.log")))?;
    // `nice` execs the binary: the child's pid is the binary's.
    let mut command = match nice {
        0 => Command::new(bin),
        n => {
            let mut c = Command::new("nice");
            c.args(["-n", &n.to_string()]).arg(bin);
            c
        }
    };
    let child = command
        .args(args)
        .env(
            "RUST_LOG",
            std::env::var("RUST_LOG").unwrap_or("info".into()),
        )
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .with_context(|| format!("cannot start {}", bin.display()))?;
    Ok(Proc {
        kind,
        name,
        child,
        cpu_at_start_s: 0.0,
        peak_rss_kib: 0,
        killed: false,
    })
}

/// What the observer saw of one trolley.
#[derive(Default)]
struct TrolleyLog {
    frame_at: HashMap<u64, Instant>,
    cloud_at: HashMap<u64, Instant>,
    /// Frame → cloud, frame → views and cloud → views (the planners' part) latencies, ms.
    frame_to_cloud_ms: Vec<f64>,
    frame_to_views_ms: Vec<f64>,
    cloud_to_views_ms: Vec<f64>,
    views: u64,
    /// Every RankedViews: its arrival, its planner, and when the frame it answers arrived (for
    /// the first views on a frame).
    views_from: Vec<(Instant, String, Option<Instant>)>,
    /// The views its arm executed per ownership term, as its status said, when that changed.
    terms: Vec<(Instant, Vec<glasshouse_proto::OwnerTerm>)>,
    /// Its fruits' ids and centres, when they changed (for the fruit ids lost to a fault).
    fruits: Vec<(Instant, FruitIds)>,
}

#[derive(Default)]
struct Observed {
    trolleys: BTreeMap<String, TrolleyLog>,
    /// Latest drop counter of each reporting member.
    drops: BTreeMap<String, u64>,
    owned: BTreeMap<String, Vec<String>>,
    corrupt: u64,
    /// RGB-D frames seen and their payload bytes (as encoded on the wire).
    rgbd_frames: u64,
    rgbd_bytes: u64,
    /// Each planner's latest stage totals and catch-up time (its status).
    stages: BTreeMap<String, StageTimes>,
    catch_up_ms: BTreeMap<String, f64>,
    /// Every ROI cloud of every trolley since the fleet started (for the scans-lost check).
    clouds: BTreeMap<String, Vec<glasshouse_proto::RoiCloud>>,
}

/// A trolley's fruits as published: each fruit's id and centre (world, m).
type FruitIds = Vec<(u32, [f64; 3])>;

pub(crate) fn percentile(values: &[f64], p: f64) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let rank = ((p / 100.0) * (v.len() - 1) as f64).round() as usize;
    v.get(rank.min(v.len() - 1)).copied()
}

#[derive(Serialize)]
struct KindReport {
    processes: usize,
    cpu_percent_of_one_core: f64,
    peak_rss_mib_per_process: f64,
}

#[derive(Serialize)]
struct Report {
    /// What the MCAP recorder wrote (`--record`).
    recorder: Option<RecorderReport>,
    trolleys: u32,
    planners: u32,
    detectors: u32,
    scenario: String,
    /// "mtls+acl" (`--secure`) or "tcp".
    transport: &'static str,
    realtime: bool,
    /// The planners' `--replica-refresh-clouds` (None: their default).
    replica_refresh_clouds: Option<usize>,
    /// The planners' `--takeover-decode-threads` (None: their default).
    takeover_decode_threads: Option<usize>,
    /// The planners' `--standby-decoded-ahead` (None: their default).
    standby_decoded_ahead: Option<bool>,
    /// The planners' `--refresh-by-delta` (None: their default).
    refresh_by_delta: Option<bool>,
    /// The planners' `--insert-threads` (None: their default).
    insert_threads: Option<usize>,
    /// The planners' `--fit-threads` (None: their default).
    fit_threads: Option<usize>,
    /// The planners' `--max-range` (None: their default).
    max_range_m: Option<f64>,
    /// The planners' `--merge-far-rays` (None: their default).
    merge_far_rays: Option<bool>,
    /// The planners' `--body-search` (None: their default).
    body_search: Option<bool>,
    /// The simulated trolleys' nice value.
    trolley_nice: i32,
    width: u32,
    fps_per_trolley_max: f64,
    measured_s: f64,
    frames_per_s_per_trolley: f64,
    views_per_minute_per_trolley: f64,
    frame_to_cloud_ms_p50: Option<f64>,
    frame_to_cloud_ms_p99: Option<f64>,
    frame_to_views_ms_p50: Option<f64>,
    frame_to_views_ms_p99: Option<f64>,
    /// From the ROI cloud to the first views on its frame: the planners' part of the loop
    /// (queueing behind other trolleys' clouds included).
    cloud_to_views_ms_p50: Option<f64>,
    cloud_to_views_ms_p99: Option<f64>,
    /// The same latency by the planner that answered, and before, around and after the fault.
    frame_to_views_tail: tail::TailReport,
    messages_dropped: u64,
    observer_corrupt: u64,
    /// The fault injected, every trolley it moved and their maps (`fault`).
    fault: Option<fault::FaultReport>,
    /// Mean RGB-D frame payload on the wire.
    bytes_per_frame: Option<f64>,
    /// Share of the arms' time spent waiting for the views on their frames (the sum of frame ->
    /// views latencies over trolleys x time; frames never answered are not counted).
    arm_wait_share: f64,
    /// Planner CPU (all planners) per frame of the fleet.
    planner_cpu_ms_per_frame: Option<f64>,
    /// The same over the first and over the last minute of the run (flat along the row or not).
    planner_cpu_ms_per_frame_minute1: Option<f64>,
    planner_cpu_ms_per_frame_last_minute: Option<f64>,
    /// The planners' own account of that CPU, ms per frame by stage (integrate, cluster, track,
    /// fit, plan, publish), from their status.
    planner_stage_ms_per_frame: BTreeMap<String, f64>,
    /// Time the planners spent catching up trolleys taken over.
    planner_catch_up_ms: f64,
    /// Resident memory of all planners divided by the trolleys, one minute in and at the end.
    planner_rss_mib_per_trolley_minute1: Option<f64>,
    planner_rss_mib_per_trolley_end: Option<f64>,
    per_kind: BTreeMap<String, KindReport>,
}

/// Where the other binaries are: next to this one.
fn sibling(name: &str) -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe().context("own path")?;
    let path = exe
        .parent()
        .context("own folder")?
        .join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    ensure!(
        path.exists(),
        "{} not found: build every binary first (cargo build --release --workspace --bins)",
        path.display()
    );
    Ok(path)
}

fn free_port() -> anyhow::Result<u16> {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").context("no free loopback port")?;
    Ok(listener.local_addr()?.port())
}

pub async fn run(mut args: FleetBenchArgs) -> anyhow::Result<()> {
    validate(&args)?;
    let mut reports = Vec::new();
    let sweep_logs = args.logs.clone().filter(|_| args.trolley_counts.len() > 1);
    for (i, &count) in args.trolley_counts.clone().iter().enumerate() {
        if args.trolley_counts.len() > 1 {
            println!(
                "== capacity sweep: run {} of {}, {count} trolleys",
                i + 1,
                args.trolley_counts.len()
            );
        }
        args.trolleys = count;
        // A sweep keeps each count's logs apart (one folder would hold only the last run's).
        if let Some(dir) = &sweep_logs {
            args.logs = Some(dir.join(format!("{count}-trolleys")));
        }
        let report = run_fleet(&args).await?;
        print_report(&report);
        reports.push(report);
    }
    if reports.len() > 1 {
        sweep::print_table(&reports);
    }
    if let Some(path) = &args.json {
        let text = match &reports[..] {
            [one] => serde_json::to_string_pretty(one)?,
            all => serde_json::to_string_pretty(all)?,
        };
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
        println!("report written to {}", path.display());
    }
    if let Some(path) = &args.plot {
        let png = sweep::plot(&reports)?;
        std::fs::write(path, png).with_context(|| format!("writing {}", path.display()))?;
        println!("plot written to {}", path.display());
    }
    Ok(())
}

/// When the fault comes (none with `--fault-at-s 0`, or a planner fault with one planner).
fn fault_plan(args: &FleetBenchArgs, measured: Duration) -> Option<FaultPlan> {
    let at_s = args.fault_at_s.unwrap_or(measured.as_secs_f64() / 2.0);
    let enabled = at_s > 0.0 && (args.fault.hits_router() || args.planners >= 2);
    enabled.then(|| FaultPlan {
        fault: args.fault,
        at: Duration::from_secs_f64(at_s),
        undo_after: fault::undo_after(args.fault, args.fault_for_s),
    })
}

/// One fleet of `args.trolleys` trolleys: started, warmed up, measured, stopped.
async fn run_fleet(args: &FleetBenchArgs) -> anyhow::Result<Report> {
    let measured = Duration::from_secs_f64(args.minutes * 60.0);
    let plan = fault_plan(args, measured);
    let mut fleet = Fleet::new(args)?;
    fleet.spawn_routers()?;
    let observer = glasshouse_bus::open(&fleet.session_of(BENCH_OBSERVER)).await?;
    let observed = Arc::new(Mutex::new(Observed::default()));
    let subscriber = subscribe_observer(&observer, observed.clone()).await?;
    fleet.spawn_services(args).await?;
    warm_up(&observed, args, &fleet.logs).await?;
    let measurement = measure(&mut fleet, &observed, measured, plan).await?;
    let per_kind = per_kind_usage(&fleet.procs, &measurement);
    let mut report = {
        let o = observed
            .lock()
            .map_err(|_| anyhow::anyhow!("observer state poisoned"))?;
        build_report(args, &o, &measurement, per_kind)
    };
    if let Some(fault) = report.fault.as_mut() {
        let moved: Vec<String> = fault.moved.keys().cloned().collect();
        let settings = args.planning_settings();
        let mut maps = lost::check(&observer, &observed, &mut fleet.procs, &moved, &settings).await;
        for (tid, trolley) in fault.moved.iter_mut() {
            trolley.map = maps.remove(tid);
        }
    }
    drop(subscriber);
    let _ = observer.close().await;
    fleet.stop();
    if let Some(dir) = &args.record {
        report.recorder = Some(recorder_report(dir)?);
    }
    Ok(report)
}

/// What `glasshouse record` wrote (its `summary.json`, written when it stopped).
#[derive(Serialize, serde::Deserialize)]
struct RecorderReport {
    messages: u64,
    frames: u64,
    dropped: u64,
    disk_bytes: u64,
    files: Vec<PathBuf>,
}

fn recorder_report(dir: &Path) -> anyhow::Result<RecorderReport> {
    let path = dir.join("summary.json");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("the recorder left no {} (see its log)", path.display()))?;
    Ok(serde_json::from_str(&text)?)
}

fn validate(args: &FleetBenchArgs) -> anyhow::Result<()> {
    ensure!(
        !(args.secure && args.record.is_some()),
        "--record runs without --secure (the recorder has no identity in the bench's roster)"
    );
    ensure!(
        !args.trolley_counts.is_empty() && args.trolley_counts.iter().all(|n| (1..=64).contains(n)),
        "--trolleys must be counts within 1..=64"
    );
    ensure!(
        (1..=16).contains(&args.planners),
        "--planners must be 1..=16"
    );
    ensure!(
        (1..=16).contains(&args.detectors),
        "--detectors must be 1..=16"
    );
    ensure!(
        args.minutes.is_finite() && args.minutes > 0.0 && args.minutes <= 24.0 * 60.0,
        "--minutes must be in (0, 1440]"
    );
    ensure!(
        args.fps.is_finite() && args.fps > 0.0 && args.fps <= 100.0,
        "--fps must be in (0, 100]"
    );
    ensure!(
        (16..=1280).contains(&args.width),
        "--width must be within 16..=1280"
    );
    ensure!(
        args.fault_for_s.is_none_or(|s| s.is_finite() && s > 0.0),
        "--fault-for-s must be positive"
    );
    ensure!(
        !(args.secure && args.fault == fault::Fault::RouterFailover),
        "--fault router-failover runs without --secure (the roster has one router identity)"
    );
    ["1", "2", "row"]
        .contains(&args.scenario.as_str())
        .then_some(())
        .context("--scenario must be 1, 2 or row")?;
    args.planning_settings()
        .validate()
        .context("the planners' settings (--max-range)")?;
    Ok(())
}

impl FleetBenchArgs {
    /// What the planners integrate with: their defaults and the flags passed on to them.
    fn planning_settings(&self) -> glasshouse_pipeline::PlanningSettings {
        let default = glasshouse_pipeline::PlanningSettings::default();
        glasshouse_pipeline::PlanningSettings {
            max_range_m: self.max_range.unwrap_or(default.max_range_m),
            merge_far_rays: self.merge_far_rays.unwrap_or(default.merge_far_rays),
            ..default
        }
    }
}

/// The observer's identity in a secured bench (a dashboard: it reads everything).
const BENCH_OBSERVER: &str = "dashboard-bench";

/// The fleet's processes, the router they all reach and the folder of their logs.
struct Fleet {
    procs: Vec<Proc>,
    /// Where the routers listen (two with `--fault router-failover`); clients know them all.
    endpoints: Vec<String>,
    /// A planner's own endpoint where it connects through a relay (`--fault partition`).
    relays: BTreeMap<String, String>,
    /// A secured fleet's PKI (`--secure`): every process connects with its own config.
    pki: Option<glasshouse_trust::Layout>,
    lease: String,
    logs: PathBuf,
    /// The logs folder is temporary (no `--logs`): removed at the end.
    temp_logs: bool,
    /// Each planner's name and flags, to start it again (`--fault restart-all`).
    planner_flags: Vec<(String, Vec<String>)>,
    /// The edges' nice value (`--trolley-nice`).
    trolley_nice: i32,
}

impl Fleet {
    fn new(args: &FleetBenchArgs) -> anyhow::Result<Self> {
        let temp_logs = args.logs.is_none();
        let logs = args.logs.clone().unwrap_or_else(|| {
            std::env::temp_dir().join(format!("glasshouse-fleet-bench-{}", std::process::id()))
        });
        std::fs::create_dir_all(&logs).with_context(|| format!("log folder {}", logs.display()))?;
        let port = free_port()?;
        let (endpoint, pki) = if args.secure {
            let endpoint = format!("tls/127.0.0.1:{port}");
            let pki = secured_fleet_pki(args, &endpoint, &logs.join("pki"))?;
            (endpoint, Some(pki))
        } else {
            (format!("tcp/127.0.0.1:{port}"), None)
        };
        let mut endpoints = vec![endpoint];
        if args.fault == fault::Fault::RouterFailover {
            endpoints.push(format!("tcp/127.0.0.1:{}", free_port()?));
        }
        Ok(Fleet {
            procs: Vec::new(),
            endpoints,
            relays: BTreeMap::new(),
            pki,
            lease: args.lease_ms.to_string(),
            logs,
            temp_logs,
            planner_flags: Vec::new(),
            trolley_nice: args.trolley_nice,
        })
    }

    /// How `name` (`router`, `<kind>-<id>`) opens its session: its own config when secured.
    fn session_of(&self, name: &str) -> BusArgs {
        match &self.pki {
            Some(pki) => BusArgs {
                zenoh_config: Some(pki.config(name)),
                ..BusArgs::default()
            },
            None => BusArgs {
                connect: self.endpoints.clone(),
                mode: Some(glasshouse_bus::Mode::Client),
                ..BusArgs::default()
            },
        }
    }

    /// `--zenoh-config FILE` of `name` in a secured fleet, nothing in a plain one.
    fn config_flags(&self, name: &str) -> Vec<String> {
        self.pki.as_ref().map_or_else(Vec::new, |pki| {
            vec![
                "--zenoh-config".into(),
                pki.config(name).to_string_lossy().into_owned(),
            ]
        })
    }

    /// Starts router `index` (`router`, `router2`: the second one connects to the first).
    fn spawn_router(&mut self, index: usize) -> anyhow::Result<()> {
        let mut args = vec!["router".into()];
        args.extend(self.config_flags(glasshouse_trust::ROUTER));
        // Loopback only, whatever the config file's listener says.
        args.extend(["-l".into(), self.endpoints[index].clone()]);
        if index > 0 {
            args.extend(["-e".into(), self.endpoints[0].clone()]);
        }
        args.extend(["--lease-ms".into(), self.lease.clone()]);
        let name = match index {
            0 => "router".to_string(),
            i => format!("router{}", i + 1),
        };
        let bin = sibling("glasshouse")?;
        let router = spawn("router", name, (&bin, 0), &args, &self.logs)?;
        self.procs.push(router);
        Ok(())
    }

    fn spawn_routers(&mut self) -> anyhow::Result<()> {
        (0..self.endpoints.len()).try_for_each(|i| self.spawn_router(i))
    }

    /// A relay between planner `name` and the first router, which `--fault partition` cuts.
    fn spawn_relay(&mut self, name: &str) -> anyhow::Result<()> {
        let router = self.endpoints[0].clone();
        let (proto, _) = router.split_once('/').unwrap_or(("tcp", ""));
        let own = format!("{proto}/127.0.0.1:{}", free_port()?);
        let args = [
            "relay".into(),
            "--listen".into(),
            own.clone(),
            "--to".into(),
            router,
        ];
        let bin = sibling("glasshouse")?;
        let relay = spawn(
            "relay",
            format!("relay-{name}"),
            (&bin, 0),
            &args,
            &self.logs,
        )?;
        self.procs.push(relay);
        self.relays.insert(name.to_owned(), own);
        Ok(())
    }

    /// Starts one client process of the fleet: the session flags, then `extra`.
    fn spawn_client(
        &mut self,
        kind: &'static str,
        name: String,
        bin: &str,
        extra: &[String],
    ) -> anyhow::Result<()> {
        // The CLI's subcommand comes before its session flags.
        let (mut a, extra) = match (bin, extra.split_first()) {
            ("glasshouse", Some((command, rest))) => (vec![command.clone()], rest),
            _ => (Vec::new(), extra),
        };
        let connect = match self.relays.get(&name) {
            Some(relay) => vec![relay.clone()],
            None => self.endpoints.clone(),
        };
        for endpoint in connect {
            a.extend(["-e".into(), endpoint]);
        }
        a.extend(["--mode", "client", "--lease-ms", &self.lease].map(String::from));
        // The edge process is a trolley's identity.
        let role = if kind == "edge" { "trolley" } else { kind };
        a.extend(self.config_flags(&format!("{role}-{name}")));
        a.extend_from_slice(extra);
        let nice = if kind == "edge" { self.trolley_nice } else { 0 };
        let proc = spawn(kind, name, (&sibling(bin)?, nice), &a, &self.logs)?;
        self.procs.push(proc);
        Ok(())
    }

    /// Detectors and planners first, the trolleys once they have found each other.
    async fn spawn_services(&mut self, args: &FleetBenchArgs) -> anyhow::Result<()> {
        for i in 1..=args.detectors {
            let extra = ["--detector-id".into(), format!("d{i}")];
            self.spawn_client("detector", format!("d{i}"), "detector-service", &extra)?;
        }
        for i in 1..=args.planners {
            if args.fault == fault::Fault::Partition {
                self.spawn_relay(&format!("p{i}"))?;
            }
            let mut extra = vec!["--planner-id".into(), format!("p{i}")];
            if let Some(n) = args.replica_refresh_clouds {
                extra.extend(["--replica-refresh-clouds".into(), n.to_string()]);
            }
            if let Some(n) = args.takeover_decode_threads {
                extra.extend(["--takeover-decode-threads".into(), n.to_string()]);
            }
            if let Some(ahead) = args.standby_decoded_ahead {
                extra.extend(["--standby-decoded-ahead".into(), ahead.to_string()]);
            }
            if let Some(by_delta) = args.refresh_by_delta {
                extra.extend(["--refresh-by-delta".into(), by_delta.to_string()]);
            }
            if let Some(n) = args.insert_threads {
                extra.extend(["--insert-threads".into(), n.to_string()]);
            }
            if let Some(n) = args.fit_threads {
                extra.extend(["--fit-threads".into(), n.to_string()]);
            }
            if let Some(range_m) = args.max_range {
                extra.extend(["--max-range".into(), range_m.to_string()]);
            }
            if let Some(merge) = args.merge_far_rays {
                extra.extend(["--merge-far-rays".into(), merge.to_string()]);
            }
            if let Some(search) = args.body_search {
                extra.extend(["--body-search".into(), search.to_string()]);
            }
            if let Some(dir) = self.store_dir(args) {
                let file = dir.join(format!("p{i}.redb"));
                extra.extend(["--store".into(), file.to_string_lossy().into_owned()]);
                if let Some(delay) = args.store_write_delay_ms {
                    extra.extend(["--store-write-delay-ms".into(), delay.to_string()]);
                }
            }
            self.planner_flags.push((format!("p{i}"), extra.clone()));
            self.spawn_client("planner", format!("p{i}"), "planner-service", &extra)?;
        }
        if let Some(dir) = &args.record {
            let extra = [
                "record".into(),
                "--out".into(),
                dir.to_string_lossy().into_owned(),
            ];
            self.spawn_client("recorder", "recorder".into(), "glasshouse", &extra)?;
        }
        // Let the planners and detectors find each other before the trolleys appear.
        tokio::time::sleep(Duration::from_secs(2)).await;
        let interval_ms = (1000.0 / args.fps).round() as u64;
        for i in 1..=args.trolleys {
            let mut extra = vec![
                "--trolley-id".into(),
                format!("t{i}"),
                "--scenario".into(),
                args.scenario.clone(),
                "--seed".into(),
                i.to_string(),
                "--width".into(),
                args.width.to_string(),
                "--frame-interval-ms".into(),
                interval_ms.to_string(),
            ];
            if args.realtime {
                extra.push("--realtime".into());
            }
            self.spawn_client("edge", format!("t{i}"), "edge", &extra)?;
        }
        Ok(())
    }

    /// Where the planners keep their stores: `--store`, or the logs folder for `--fault
    /// restart-all`; None: in memory only.
    fn store_dir(&self, args: &FleetBenchArgs) -> Option<PathBuf> {
        let restarts = args.fault == fault::Fault::RestartAll;
        args.store
            .clone()
            .or_else(|| restarts.then(|| self.logs.join("stores")))
    }

    /// Starts every planner again with the flags it first had (the same id and store).
    fn respawn_planners(&mut self) -> anyhow::Result<()> {
        for (name, extra) in self.planner_flags.clone() {
            self.spawn_client("planner", name, "planner-service", &extra)?;
        }
        Ok(())
    }

    /// Stops every process still running (edges and services first, the router last), then
    /// removes a temporary logs folder.
    fn stop(mut self) {
        for p in self.procs.iter_mut().rev() {
            if !p.killed {
                let _ = Command::new("kill")
                    .args(["-TERM", &p.child.id().to_string()])
                    .status();
            }
        }
        let deadline = Instant::now() + Duration::from_secs(10);
        for p in self.procs.iter_mut() {
            while p.child.try_wait().ok().flatten().is_none() && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        self.procs.clear();
        if self.temp_logs {
            let _ = std::fs::remove_dir_all(&self.logs);
        } else {
            println!("logs in {}", self.logs.display());
        }
    }
}

/// A PKI for the bench's fleet (trolleys t1..tN, planners, detectors, the observer) in `dir`.
fn secured_fleet_pki(
    args: &FleetBenchArgs,
    endpoint: &str,
    dir: &Path,
) -> anyhow::Result<glasshouse_trust::Layout> {
    let ids = |prefix: &str, n: u32| (1..=n).map(|i| format!("{prefix}{i}")).collect();
    let roster = glasshouse_trust::Roster {
        trolleys: ids("t", args.trolleys),
        planners: ids("p", args.planners),
        detectors: ids("d", args.detectors),
        dashboards: vec![BENCH_OBSERVER.trim_start_matches("dashboard-").into()],
        router_endpoint: endpoint.to_owned(),
        ..glasshouse_trust::Roster::default()
    };
    roster.validate()?;
    let _ = std::fs::remove_dir_all(dir);
    crate::secure::create(dir, &roster, 1)
}

/// Records every message on the bus into `observed`, stamped with its arrival.
async fn subscribe_observer(
    observer: &glasshouse_bus::zenoh::Session,
    observed: Arc<Mutex<Observed>>,
) -> anyhow::Result<Vec<glasshouse_bus::zenoh::pubsub::Subscriber<()>>> {
    // One subscriber per key a dashboard may read: a secured router's ACL refuses `gh/**`.
    let mut reads: Vec<String> = TrolleyTopic::ALL
        .iter()
        .map(|&t| keys::all_trolleys(t))
        .collect();
    reads.push(keys::all_planner_status().as_str().to_owned());
    reads.push(keys::all_detector_status().as_str().to_owned());
    let mut subscribers = Vec::new();
    for key in reads {
        let observed = observed.clone();
        let subscriber = observer
            .declare_subscriber(key)
            .callback(move |sample| record_sample(&observed, &sample))
            .await
            .map_err(|e| anyhow::anyhow!("observer subscription: {e}"))?;
        subscribers.push(subscriber);
    }
    Ok(subscribers)
}

fn record_sample(observed: &Mutex<Observed>, sample: &glasshouse_bus::zenoh::sample::Sample) {
    let now = Instant::now();
    let Some(key) = keys::parse(sample.key_expr().as_str()) else {
        return;
    };
    let Some(kind) = key.message_kind() else {
        return;
    };
    let bytes = sample.payload().to_bytes();
    let Ok(mut o) = observed.lock() else { return };
    let Ok((header, message)) = decode_as(&bytes, kind) else {
        o.corrupt += 1;
        return;
    };
    if matches!(
        key,
        ParsedKey::Trolley {
            topic: TrolleyTopic::Rgbd,
            ..
        }
    ) {
        o.rgbd_frames += 1;
        o.rgbd_bytes += bytes.len() as u64;
    }
    o.record(&key, &header, message, now);
}

impl Observed {
    fn record(&mut self, key: &ParsedKey, header: &Header, message: Message, now: Instant) {
        match (key, message) {
            (ParsedKey::Trolley { tid, topic }, message) => {
                self.record_trolley(tid, topic, header, message, now);
            }
            (ParsedKey::PlannerStatus { pid }, Message::PlannerStatus(s)) => {
                self.drops
                    .insert(format!("planner/{pid}"), s.dropped_messages);
                self.owned.insert(pid.clone(), s.owned_trolleys);
                self.stages.insert(pid.clone(), s.stage_totals);
                self.catch_up_ms.insert(pid.clone(), s.catch_up_ms);
            }
            (ParsedKey::DetectorStatus { did }, Message::DetectorStatus(s)) => {
                self.drops
                    .insert(format!("detector/{did}"), s.dropped_messages);
            }
            _ => {}
        }
    }

    fn record_trolley(
        &mut self,
        tid: &str,
        topic: &TrolleyTopic,
        header: &Header,
        message: Message,
        now: Instant,
    ) {
        let t = self.trolleys.entry(tid.to_owned()).or_default();
        match (topic, message) {
            (TrolleyTopic::Rgbd, _) => {
                t.frame_at.entry(header.seq).or_insert(now);
            }
            (TrolleyTopic::Roi, Message::RoiCloud(c)) => {
                self.clouds
                    .entry(tid.to_owned())
                    .or_default()
                    .push(c.clone());
                let seq = c.source_frame_seq;
                if let std::collections::hash_map::Entry::Vacant(e) = t.cloud_at.entry(seq) {
                    e.insert(now);
                    if let Some(f) = t.frame_at.get(&seq) {
                        t.frame_to_cloud_ms
                            .push(now.duration_since(*f).as_secs_f64() * 1e3);
                    }
                }
            }
            (TrolleyTopic::Views, Message::RankedViews(v)) => {
                t.views += 1;
                // The first views on a frame: the loop's latency.
                let frame = t.frame_at.remove(&v.based_on_seq);
                if let Some(f) = frame {
                    t.frame_to_views_ms
                        .push(now.duration_since(f).as_secs_f64() * 1e3);
                    if let Some(c) = t.cloud_at.get(&v.based_on_seq) {
                        t.cloud_to_views_ms
                            .push(now.saturating_duration_since(*c).as_secs_f64() * 1e3);
                    }
                }
                t.views_from.push((now, header.source_id.clone(), frame));
            }
            (TrolleyTopic::Fruits, Message::FruitEstimates(f)) => {
                let ids: FruitIds = f
                    .fruits
                    .iter()
                    .map(|f| (f.id, [f.centre.x, f.centre.y, f.centre.z]))
                    .collect();
                if t.fruits.last().map(|(_, last)| last) != Some(&ids) {
                    t.fruits.push((now, ids));
                }
            }
            (TrolleyTopic::Status, Message::TrolleyStatus(s)) => {
                self.drops
                    .insert(format!("trolley/{tid}"), s.dropped_messages);
                if t.terms.last().map(|(_, terms)| terms) != Some(&s.owner_terms) {
                    t.terms.push((now, s.owner_terms));
                }
            }
            _ => {}
        }
    }
}

/// Waits until every trolley has had views once (at most 120 s).
async fn warm_up(
    observed: &Mutex<Observed>,
    args: &FleetBenchArgs,
    logs: &Path,
) -> anyhow::Result<()> {
    let warm_up_until = Instant::now() + Duration::from_secs(120);
    loop {
        let ready = observed
            .lock()
            .map(|o| o.trolleys.values().filter(|t| t.views > 0).count())
            .unwrap_or(0);
        if ready >= args.trolleys as usize {
            return Ok(());
        }
        ensure!(
            Instant::now() < warm_up_until,
            "only {ready} of {} trolleys got views within 120 s (logs: {})",
            args.trolleys,
            logs.display()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// What the measured run itself yields, beside what the observer saw.
struct Measurement {
    elapsed_s: f64,
    drops_at_start: BTreeMap<String, u64>,
    /// The fault injected, if it was.
    fault: Option<fault::Injected>,
    /// CPU seconds of each killed process at its kill.
    cpu_at_kill: HashMap<String, f64>,
    /// Resident memory of the live planners together, one minute in and at the end.
    planner_rss_kib_minute1: Option<u64>,
    planner_rss_kib_end: Option<u64>,
    started: Instant,
    /// The planners' CPU along the run, and their stage totals and catch-up time at its start.
    planner_cpu: cost::CpuSamples,
    stages_at_start: BTreeMap<String, StageTimes>,
    catch_up_ms_at_start: BTreeMap<String, f64>,
}

/// CPU seconds of the planners together since the measured run started (a killed one's up to
/// its kill).
fn planners_cpu_s(procs: &[Proc], cpu_at_kill: &HashMap<String, f64>) -> f64 {
    let planners = procs.iter().filter(|p| p.kind == "planner");
    planners
        .map(|p| {
            let now = match p.killed {
                true => cpu_at_kill.get(&p.name).copied(),
                false => cpu_seconds(p.child.id()),
            };
            now.unwrap_or(p.cpu_at_start_s) - p.cpu_at_start_s
        })
        .sum()
}

/// Resident memory of the live planners together.
fn planner_rss_kib(procs: &[Proc]) -> Option<u64> {
    procs
        .iter()
        .filter(|p| p.kind == "planner" && !p.killed)
        .map(|p| rss_kib(p.child.id()))
        .sum()
}

/// Measure from here: resets the observer's logs; the drop counters, stage totals and catch-up
/// times the run starts from.
fn reset_observer(
    observed: &Mutex<Observed>,
) -> (
    BTreeMap<String, u64>,
    BTreeMap<String, StageTimes>,
    BTreeMap<String, f64>,
) {
    match observed.lock() {
        Ok(mut o) => {
            for t in o.trolleys.values_mut() {
                *t = TrolleyLog::default();
            }
            o.corrupt = 0;
            o.rgbd_frames = 0;
            o.rgbd_bytes = 0;
            (o.drops.clone(), o.stages.clone(), o.catch_up_ms.clone())
        }
        Err(_) => Default::default(),
    }
}

fn progress_bar(measured: Duration) -> Progress {
    Progress::new("fleet-bench", measured.as_secs()).with_style(
        ProgressStyle::with_template("fleet-bench [{bar:30}] {pos}/{len} s (eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    )
}

/// Raises each live process's peak resident memory to what it uses now.
fn track_peak_rss(procs: &mut [Proc]) {
    for p in procs.iter_mut().filter(|p| !p.killed) {
        if let Some(rss) = rss_kib(p.child.id()) {
            p.peak_rss_kib = p.peak_rss_kib.max(rss);
        }
    }
}

/// When the fault comes during the measured run, and when it is undone.
#[derive(Clone, Copy)]
struct FaultPlan {
    fault: fault::Fault,
    at: Duration,
    undo_after: Option<Duration>,
}

/// The measured run: resets the observer's logs, samples memory, injects the fault and undoes it.
async fn measure(
    fleet: &mut Fleet,
    observed: &Mutex<Observed>,
    measured: Duration,
    plan: Option<FaultPlan>,
) -> anyhow::Result<Measurement> {
    let (drops_at_start, stages_at_start, catch_up_ms_at_start) = reset_observer(observed);
    let mut planner_cpu = cost::CpuSamples::default();
    for p in fleet.procs.iter_mut() {
        p.cpu_at_start_s = cpu_seconds(p.child.id()).unwrap_or(0.0);
    }
    let started = Instant::now();
    let bar = progress_bar(measured);
    let mut injected: Option<fault::Injected> = None;
    let mut cpu_at_kill: HashMap<String, f64> = HashMap::new();
    let mut planner_rss_kib_minute1 = None;
    let mut next_cpu_sample = Duration::ZERO;
    while started.elapsed() < measured {
        tokio::time::sleep(Duration::from_millis(250)).await;
        if started.elapsed() >= next_cpu_sample {
            let cpu = planners_cpu_s(&fleet.procs, &cpu_at_kill);
            planner_cpu.push(started.elapsed(), cpu);
            next_cpu_sample += Duration::from_secs(5);
        }
        track_peak_rss(&mut fleet.procs);
        if let Some(plan) = plan {
            step_fault(
                fleet,
                observed,
                plan,
                started,
                &mut injected,
                &mut cpu_at_kill,
                &bar,
            )?;
        }
        if planner_rss_kib_minute1.is_none() && started.elapsed() >= Duration::from_secs(60) {
            planner_rss_kib_minute1 = planner_rss_kib(&fleet.procs);
        }
        bar.set_position(started.elapsed().as_secs().min(measured.as_secs()));
    }
    bar.finish_and_clear();
    // A fault still under way ends with the run: a stopped planner must hear SIGTERM.
    if let Some(injected) = injected.as_mut() {
        fault::undo(injected, fleet)?;
    }
    planner_cpu.push(
        started.elapsed(),
        planners_cpu_s(&fleet.procs, &cpu_at_kill),
    );
    Ok(Measurement {
        started,
        planner_cpu,
        stages_at_start,
        catch_up_ms_at_start,
        elapsed_s: started.elapsed().as_secs_f64(),
        drops_at_start,
        fault: injected,
        cpu_at_kill,
        planner_rss_kib_minute1,
        planner_rss_kib_end: planner_rss_kib(&fleet.procs),
    })
}

/// Injects the fault when its time comes, and undoes it when its time is up.
fn step_fault(
    fleet: &mut Fleet,
    observed: &Mutex<Observed>,
    plan: FaultPlan,
    started: Instant,
    injected: &mut Option<fault::Injected>,
    cpu_at_kill: &mut HashMap<String, f64>,
    bar: &Progress,
) -> anyhow::Result<()> {
    let elapsed = started.elapsed();
    match injected {
        None if elapsed >= plan.at => {
            *injected = fault::inject(plan.fault, fleet, observed, cpu_at_kill)?;
            if let Some(i) = injected {
                bar.println(format!(
                    "{:?}: {} (moves {}) at {:.1} s",
                    i.fault,
                    i.target,
                    i.moved.join(", "),
                    elapsed.as_secs_f64()
                ));
            }
        }
        Some(i) if plan.undo_after.is_some_and(|d| i.at.elapsed() >= d) && i.ended.is_none() => {
            fault::undo(i, fleet)?;
            bar.println(format!(
                "{:?} undone at {:.1} s",
                i.fault,
                elapsed.as_secs_f64()
            ));
        }
        _ => {}
    }
    Ok(())
}

/// CPU and peak memory per process kind over the measured run.
fn per_kind_usage(procs: &[Proc], m: &Measurement) -> BTreeMap<String, KindReport> {
    let mut per_kind: BTreeMap<String, (usize, f64, u64)> = BTreeMap::new();
    for p in procs {
        let cpu_end = if p.killed {
            m.cpu_at_kill
                .get(&p.name)
                .copied()
                .unwrap_or(p.cpu_at_start_s)
        } else {
            cpu_seconds(p.child.id()).unwrap_or(p.cpu_at_start_s)
        };
        let e = per_kind.entry(p.kind.to_owned()).or_default();
        e.0 += 1;
        e.1 += cpu_end - p.cpu_at_start_s;
        e.2 = e.2.max(p.peak_rss_kib);
    }
    per_kind
        .into_iter()
        .map(|(k, (count, cpu, rss))| {
            (
                k,
                KindReport {
                    processes: count,
                    cpu_percent_of_one_core: 100.0 * cpu / m.elapsed_s,
                    peak_rss_mib_per_process: rss as f64 / 1024.0,
                },
            )
        })
        .collect()
}

/// The planners' cost along the run and by stage (see `cost`).
struct PlannerCost {
    cpu_ms_per_frame_minute1: Option<f64>,
    cpu_ms_per_frame_last_minute: Option<f64>,
    stage_ms_per_frame: BTreeMap<String, f64>,
    catch_up_ms: f64,
}

fn planner_cost(o: &Observed, m: &Measurement, frames: usize) -> PlannerCost {
    let clouds: Vec<Instant> = o
        .trolleys
        .values()
        .flat_map(|t| t.cloud_at.values().copied())
        .collect();
    let minute = Duration::from_secs(60);
    let end = Duration::from_secs_f64(m.elapsed_s);
    let cpu_per_frame =
        |from, to| cost::cpu_ms_per_frame(&m.planner_cpu, m.started, &clouds, from, to);
    let catch_up_ms = o
        .catch_up_ms
        .iter()
        .map(|(pid, ms)| ms - m.catch_up_ms_at_start.get(pid).copied().unwrap_or(0.0))
        .sum();
    PlannerCost {
        cpu_ms_per_frame_minute1: cpu_per_frame(Duration::ZERO, minute.min(end)),
        cpu_ms_per_frame_last_minute: cpu_per_frame(end.saturating_sub(minute), end),
        stage_ms_per_frame: cost::stage_ms_per_frame(&m.stages_at_start, &o.stages, frames),
        catch_up_ms,
    }
}

fn build_report(
    args: &FleetBenchArgs,
    o: &Observed,
    m: &Measurement,
    per_kind: BTreeMap<String, KindReport>,
) -> Report {
    let all_cloud: Vec<f64> = o
        .trolleys
        .values()
        .flat_map(|t| t.frame_to_cloud_ms.iter().copied())
        .collect();
    let all_views: Vec<f64> = o
        .trolleys
        .values()
        .flat_map(|t| t.frame_to_views_ms.iter().copied())
        .collect();
    let all_planned: Vec<f64> = o
        .trolleys
        .values()
        .flat_map(|t| t.cloud_to_views_ms.iter().copied())
        .collect();
    let frames: usize = o.trolleys.values().map(|t| t.cloud_at.len()).sum();
    let views: u64 = o.trolleys.values().map(|t| t.views).sum();
    let dropped: u64 = o
        .drops
        .iter()
        .map(|(k, v)| v.saturating_sub(m.drops_at_start.get(k).copied().unwrap_or(0)))
        .sum();
    let n = f64::from(args.trolleys);
    let elapsed_s = m.elapsed_s;
    let planner_cpu_s = per_kind
        .get("planner")
        .map_or(0.0, |k| k.cpu_percent_of_one_core / 100.0 * elapsed_s);
    let per_trolley_mib = |kib: Option<u64>| kib.map(|k| k as f64 / 1024.0 / n);
    let cost = planner_cost(o, m, frames);
    Report {
        recorder: None,
        planner_cpu_ms_per_frame_minute1: cost.cpu_ms_per_frame_minute1,
        planner_cpu_ms_per_frame_last_minute: cost.cpu_ms_per_frame_last_minute,
        planner_stage_ms_per_frame: cost.stage_ms_per_frame,
        planner_catch_up_ms: cost.catch_up_ms,
        trolleys: args.trolleys,
        planners: args.planners,
        detectors: args.detectors,
        scenario: args.scenario.clone(),
        transport: if args.secure { "mtls+acl" } else { "tcp" },
        realtime: args.realtime,
        replica_refresh_clouds: args.replica_refresh_clouds,
        takeover_decode_threads: args.takeover_decode_threads,
        standby_decoded_ahead: args.standby_decoded_ahead,
        refresh_by_delta: args.refresh_by_delta,
        insert_threads: args.insert_threads,
        fit_threads: args.fit_threads,
        max_range_m: args.max_range,
        merge_far_rays: args.merge_far_rays,
        body_search: args.body_search,
        trolley_nice: args.trolley_nice,
        width: args.width,
        fps_per_trolley_max: args.fps,
        measured_s: elapsed_s,
        frames_per_s_per_trolley: frames as f64 / elapsed_s / n,
        views_per_minute_per_trolley: views as f64 / (elapsed_s / 60.0) / n,
        frame_to_cloud_ms_p50: percentile(&all_cloud, 50.0),
        frame_to_cloud_ms_p99: percentile(&all_cloud, 99.0),
        frame_to_views_ms_p50: percentile(&all_views, 50.0),
        frame_to_views_ms_p99: percentile(&all_views, 99.0),
        cloud_to_views_ms_p50: percentile(&all_planned, 50.0),
        cloud_to_views_ms_p99: percentile(&all_planned, 99.0),
        frame_to_views_tail: tail::report(&o.trolleys, m.fault.as_ref().map(|f| f.at)),
        messages_dropped: dropped,
        observer_corrupt: o.corrupt,
        fault: m.fault.as_ref().map(|f| fault::report(o, f, m.started)),
        bytes_per_frame: (o.rgbd_frames > 0).then(|| o.rgbd_bytes as f64 / o.rgbd_frames as f64),
        arm_wait_share: all_views.iter().sum::<f64>() / 1e3 / (elapsed_s * n),
        planner_cpu_ms_per_frame: (frames > 0).then(|| planner_cpu_s * 1e3 / frames as f64),
        planner_rss_mib_per_trolley_minute1: per_trolley_mib(m.planner_rss_kib_minute1),
        planner_rss_mib_per_trolley_end: per_trolley_mib(m.planner_rss_kib_end),
        per_kind,
    }
}

fn ms(v: Option<f64>) -> String {
    v.map_or("–".into(), |v| format!("{v:.0} ms"))
}

fn mib(v: Option<f64>) -> String {
    v.map_or("–".into(), |v| format!("{v:.0} MiB"))
}

fn print_report(r: &Report) {
    print_throughput(r);
    fault::print(r.fault.as_ref());
    print_resources(r);
}

/// The fleet's pace, latencies, drops and planner cost.
fn print_throughput(r: &Report) {
    println!(
        "fleet-bench: {} trolleys ({} scenario, {} px wide, at most {} frames/s each{}), {} planners, {} detectors, {:.0} s measured over {}",
        r.trolleys,
        r.scenario,
        r.width,
        r.fps_per_trolley_max,
        if r.realtime { ", real-time arms" } else { "" },
        r.planners,
        r.detectors,
        r.measured_s,
        r.transport
    );
    println!(
        "  frames per second per trolley   {:.2}",
        r.frames_per_s_per_trolley
    );
    println!(
        "  views per minute per trolley    {:.1}",
        r.views_per_minute_per_trolley
    );
    println!(
        "  frame -> ROI cloud   p50 {}  p99 {}",
        ms(r.frame_to_cloud_ms_p50),
        ms(r.frame_to_cloud_ms_p99)
    );
    println!(
        "  frame -> views       p50 {}  p99 {}",
        ms(r.frame_to_views_ms_p50),
        ms(r.frame_to_views_ms_p99)
    );
    println!(
        "  ROI cloud -> views   p50 {}  p99 {}",
        ms(r.cloud_to_views_ms_p50),
        ms(r.cloud_to_views_ms_p99)
    );
    println!("{}", tail::text(&r.frame_to_views_tail));
    println!(
        "  messages dropped     {} (services' counters) + {} corrupt at the observer",
        r.messages_dropped, r.observer_corrupt
    );
    println!(
        "  arms waiting for views {:.0} % of the time; planner CPU per frame {}; RGB-D frame {} on the wire",
        100.0 * r.arm_wait_share,
        ms(r.planner_cpu_ms_per_frame),
        r.bytes_per_frame.map_or("–".into(), |b| format!("{:.0} kB", b / 1e3))
    );
    println!(
        "  planner CPU per frame in the first / last minute: {} / {}; by stage (planners' own count, ms per frame): {}",
        ms(r.planner_cpu_ms_per_frame_minute1),
        ms(r.planner_cpu_ms_per_frame_last_minute),
        cost::stages_text(&r.planner_stage_ms_per_frame)
    );
    println!(
        "  planner RSS per trolley: {} at minute 1, {} at the end",
        mib(r.planner_rss_mib_per_trolley_minute1),
        mib(r.planner_rss_mib_per_trolley_end)
    );
}

/// The recorder and each kind of process.
fn print_resources(r: &Report) {
    if let Some(rec) = &r.recorder {
        println!(
            "  MCAP recorder: {} messages ({} frames) in {} file(s), {} dropped, {:.1} MB on disk ({:.0} kB per frame)",
            rec.messages,
            rec.frames,
            rec.files.len(),
            rec.dropped,
            rec.disk_bytes as f64 / 1e6,
            rec.disk_bytes as f64 / 1e3 / rec.frames.max(1) as f64
        );
    }
    println!("  per process kind: CPU (% of one core, all processes of the kind) and peak RSS per process");
    for (kind, k) in &r.per_kind {
        println!(
            "    {kind:<9} x{:<2} CPU {:>6.1} %   RSS {:>7.1} MiB",
            k.processes, k.cpu_percent_of_one_core, k.peak_rss_mib_per_process
        );
    }
}
