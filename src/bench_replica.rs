//! `glasshouse bench-replica`: what a trolley's replica costs next to its owner.
//!
//! One process, no bus: a simulated trolley's run (the experiments' trial loop) gives the stream
//! of ROI clouds, which two [`PlannerNode`]s (the same state machine the planner service runs)
//! take as owner and replica. The snapshot queries between them are passed by hand, as the
//! driver would. Each node's time per cloud is measured on this thread; at the end the owner is
//! lost, the replica's takeover is timed, and its map is compared with the owner's voxel for
//! voxel.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use glasshouse_eval::{ComputeTime, Trial, TrialConfig};
use glasshouse_nbv::Method;
use glasshouse_pipeline::PlanningSettings;
use glasshouse_planner::node::{
    decode_ahead, PlannerAction, PlannerEvent, PlannerNode, Role, TrolleyOutput,
};
use glasshouse_proto::{Header, RoiCloud, StageTimes, TrolleyInfo};
use glasshouse_roimap::RoiMap;
use glasshouse_sim::ScenarioKind;
use serde::Serialize;

pub(crate) const TROLLEY: &str = "t1";
pub(crate) const DETECTOR: &str = "d1";

#[derive(clap::Args, Debug)]
pub struct BenchReplicaArgs {
    /// Simulated scenario: 1, 2 or row.
    #[arg(long, default_value = "row")]
    scenario: ScenarioKind,
    /// Scene and planner seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Frames of the trolley's run replayed into owner and replica.
    #[arg(long, default_value_t = 60)]
    frames: usize,
    /// Replica settings compared, side by side on the same clouds: clouds a standby replica
    /// keeps before it asks for a snapshot (`replica_refresh_clouds`); 0 is a hot replica.
    #[arg(long, value_delimiter = ',', default_value = "0,4")]
    refresh: Vec<usize>,
    /// Frames at the start and at the end of the run whose owner times are compared.
    #[arg(long, default_value_t = 10)]
    window: usize,
    /// Also write the results as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Replay the clouds without their ROI points' colours (as an older detector sends them):
    /// what the fruits' colours cost per frame is the difference to a run with them.
    #[arg(long)]
    without_colours: bool,
    /// Standby replicas decode each snapshot they hold at once, as the planner service does in
    /// the background by default (`standby_decoded_ahead`): the decodes are timed apart from
    /// the replica's own handling, and the takeover adopts the decoded copy.
    #[arg(long)]
    decoded_ahead: bool,
    /// How an owner answers a standby's refresh, side by side on the same clouds: `true` with
    /// the blocks changed since what the standby holds (a delta, when it holds a decoded copy:
    /// with `--decoded-ahead`), `false` always with the whole map.
    #[arg(long, value_delimiter = ',', default_value = "true")]
    refresh_by_delta: Vec<bool>,
    /// Ranges, metres, up to which owner and replica integrate each cloud's rays (the
    /// planner's `max_range_m`), side by side on the same clouds (recorded by a trolley whose
    /// planner integrates up to the planner's default, 2 m).
    #[arg(long, value_name = "M", value_delimiter = ',', default_values_t = [glasshouse_pipeline::PlanningSettings::default().max_range_m])]
    max_range: Vec<f64>,
    /// Whether owner and replica free one ray per voxel at the range for the points beyond it
    /// (the planner's `merge_far_rays`), side by side on the same clouds: `false,true`.
    #[arg(long, value_name = "BOOL", value_delimiter = ',', default_values_t = [glasshouse_pipeline::PlanningSettings::default().merge_far_rays])]
    merge_far_rays: Vec<bool>,
    /// Write the owner's time on every frame of the first run, by stage, with the cloud's size
    /// and ranges, as CSV (which clouds make the tail).
    #[arg(long, value_name = "FILE")]
    frames_csv: Option<PathBuf>,
}

/// One replica setting's figures (times in ms on this thread).
#[derive(Debug, Serialize)]
struct ReplicaRun {
    replica_refresh_clouds: usize,
    /// Range up to which owner and replica integrated the rays.
    max_range_m: f64,
    /// Whether the points beyond the range freed one ray per voxel at the range.
    merge_far_rays: bool,
    frames: usize,
    owner_ms_per_frame: f64,
    /// The owner's time per frame: median, 90th and 99th percentile, and the slowest frame.
    owner_ms_p50_p90_p99_max: [f64; 4],
    /// The replica's own handling plus the owner's answers to its snapshot queries (without
    /// the decodes ahead, reported apart).
    replica_ms_per_frame: f64,
    replica_share_of_owner: f64,
    /// Snapshots decoded ahead of the takeover (`--decoded-ahead`; the service does it in the
    /// background, on idle cores).
    replica_decode_ahead_ms_per_frame: f64,
    snapshots: usize,
    /// Whether the owner answered refreshes with deltas where it could, how many it sent, the
    /// map bytes of every answer and the owner's time per answer.
    refresh_by_delta: bool,
    deltas: u64,
    snapshot_map_bytes: usize,
    owner_ms_per_answer: f64,
    owner_ms_first_frames: f64,
    owner_ms_last_frames: f64,
    /// The owner's ms per frame in each stage, over the first and the last `window` frames.
    owner_stages_first_frames: BTreeMap<&'static str, f64>,
    owner_stages_last_frames: BTreeMap<&'static str, f64>,
    /// From the owner's loss to the replica's views.
    takeover_ms: f64,
    /// The takeover's clusters, fruit ids and fits, made after the views went out.
    takeover_finish_ms: f64,
    takeover_plans: bool,
    maps_equal: bool,
    map_voxels: usize,
    #[serde(skip)]
    frame_costs: Vec<FrameCost>,
}

/// The owner's time on one frame and what the frame's cloud holds (`--frames-csv`).
#[derive(Debug)]
struct FrameCost {
    points: usize,
    roi_points: usize,
    range_median_m: f64,
    range_p90_m: f64,
    owner_ms: f64,
    stages: StageTimes,
}

impl FrameCost {
    const CSV_HEADER: &'static str =
        "seq,points,roi_points,range_median_m,range_p90_m,owner_ms,integrate_ms,cluster_ms,track_ms,fit_ms,plan_ms,publish_ms";

    fn new(cloud: &RoiCloud, owner_ms: f64, stages: StageTimes) -> Self {
        let origin = cloud.sensor_origin_in_world.cast::<f32>();
        let mut ranges_m: Vec<f64> = cloud
            .points_in_world
            .iter()
            .map(|p| f64::from((p - origin).norm()))
            .filter(|r| r.is_finite())
            .collect();
        ranges_m.sort_by(f64::total_cmp);
        Self {
            points: cloud.points_in_world.len(),
            roi_points: cloud.roi.iter().filter(|&&r| r).count(),
            range_median_m: quantile(&ranges_m, 0.5),
            range_p90_m: quantile(&ranges_m, 0.9),
            owner_ms,
            stages,
        }
    }

    fn csv_row(&self, seq: usize) -> String {
        let stages: Vec<String> = self
            .stages
            .named()
            .iter()
            .map(|(_, ms)| format!("{ms:.3}"))
            .collect();
        format!(
            "{seq},{},{},{:.3},{:.3},{:.3},{}",
            self.points,
            self.roi_points,
            self.range_median_m,
            self.range_p90_m,
            self.owner_ms,
            stages.join(",")
        )
    }
}

fn write_frames_csv(path: &std::path::Path, frames: &[FrameCost]) -> anyhow::Result<()> {
    let mut text = format!("{}\n", FrameCost::CSV_HEADER);
    for (seq, frame) in frames.iter().enumerate() {
        text.push_str(&frame.csv_row(seq));
        text.push('\n');
    }
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

pub fn run(args: BenchReplicaArgs) -> anyhow::Result<()> {
    if args.frames == 0 || args.refresh.is_empty() {
        bail!("--frames and --refresh need at least one value");
    }
    let config = TrialConfig {
        budget_s: 86_400.0,
        compute_time: ComputeTime::Fixed { ms: 100.0 },
        ..TrialConfig::new(args.scenario, Method::OursUu, args.seed)
    };
    let integrations = integration_configs(&args, &config)?;
    let (info, mut clouds) = record_stream(&config, args.frames)?;
    if args.without_colours {
        clouds.iter_mut().for_each(|c| c.roi_rgb.clear());
    }
    let mut runs = Vec::new();
    for config in &integrations {
        for &refresh in &args.refresh {
            for &by_delta in &args.refresh_by_delta {
                let replica = ReplicaSetup {
                    refresh,
                    decoded_ahead: args.decoded_ahead,
                    by_delta,
                };
                let run = replay(config, args.window, replica, &info, &clouds)?;
                print_run(&run);
                runs.push(run);
            }
        }
    }
    if let (Some(path), Some(first)) = (&args.frames_csv, runs.first()) {
        write_frames_csv(path, &first.frame_costs)?;
    }
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&runs)?;
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    if runs.iter().any(|r| !r.maps_equal || !r.takeover_plans) {
        bail!("a replica's takeover did not reproduce the owner's map and plan");
    }
    Ok(())
}

/// The trolley's info and the ROI clouds of its first `frames` planned frames.
pub(crate) fn record_stream(
    config: &TrialConfig,
    frames: usize,
) -> anyhow::Result<(TrolleyInfo, Vec<RoiCloud>)> {
    let mut trial = Trial::new(*config)?;
    let bar = crate::progress::Progress::new("recording", frames as u64);
    let mut clouds = Vec::with_capacity(frames);
    while clouds.len() < frames && trial.step()? {
        clouds.extend(trial.take_last_cloud());
        bar.set_position(clouds.len() as u64);
    }
    bar.finish_and_clear();
    if clouds.is_empty() {
        bail!("the trolley's run planned on no frame");
    }
    Ok((trial.info(), clouds))
}

/// What a planner hears when the trolley and its detector appear (no snapshot to load) and the
/// trolley's info comes.
pub(crate) fn joining(info: &TrolleyInfo) -> [PlannerEvent; 4] {
    let header = Header {
        trolley_id: TROLLEY.into(),
        source_id: "edge".into(),
        ..Header::default()
    };
    [
        PlannerEvent::DetectorJoined(DETECTOR.into()),
        PlannerEvent::TrolleyJoined(TROLLEY.into()),
        PlannerEvent::SnapshotLoaded {
            tid: TROLLEY.into(),
            snapshot: None,
        },
        PlannerEvent::Info {
            header,
            info: info.clone(),
        },
    ]
}

/// How the replica keeps its copy.
#[derive(Clone, Copy, Debug)]
struct ReplicaSetup {
    refresh: usize,
    decoded_ahead: bool,
    by_delta: bool,
}

/// Owner and replica of one trolley, the owner first.
struct Pair {
    owner: PlannerNode,
    replica: PlannerNode,
    queries: u64,
    planning: PlanningSettings,
    /// Time decoding the replica's snapshots ahead, apart from its own handling.
    decode_ahead_ms: f64,
    /// The owner's time answering the replica's refreshes, and the map bytes it sent.
    answer_ms: f64,
    answer_map_bytes: usize,
}

impl Pair {
    fn new(config: &TrialConfig, setup: ReplicaSetup, info: &TrolleyInfo) -> anyhow::Result<Self> {
        let node = |pid: &str| {
            PlannerNode::new(pid, config.planning(), 0)
                .with_replica_refresh(setup.refresh)
                .with_standby_decoded_ahead(setup.decoded_ahead)
                .with_refresh_by_delta(setup.by_delta)
        };
        let mut nodes = [(node("p1"), "p2"), (node("p2"), "p1")];
        for (node, other) in &mut nodes {
            node.handle(PlannerEvent::PlannerJoined(other.to_string()));
            let events = joining(info);
            for event in events {
                node.handle(event);
            }
        }
        let [(a, _), (b, _)] = nodes;
        let (owner, replica) = match a.role(TROLLEY) {
            Some(Role::Owner) => (a, b),
            _ => (b, a),
        };
        if replica.role(TROLLEY) != Some(Role::Replica) {
            bail!("the two planners did not split the trolley into owner and replica");
        }
        Ok(Self {
            owner,
            replica,
            queries: 0,
            planning: config.planning(),
            decode_ahead_ms: 0.0,
            answer_ms: 0.0,
            answer_map_bytes: 0,
        })
    }

    /// The replica's snapshot queries, answered by the owner; returns how many.
    fn answer(&mut self, actions: Vec<PlannerAction>) -> usize {
        let mut answered = 0;
        for action in actions {
            let PlannerAction::AskSnapshot { tid, base, .. } = action else {
                continue;
            };
            self.queries += 1;
            let asked = PlannerEvent::SnapshotAsked {
                query_id: self.queries,
                tid: tid.clone(),
                base,
            };
            let started = Instant::now();
            let reply = self.owner.handle(asked);
            self.answer_ms += ms_since(started);
            let snapshot = reply.into_iter().find_map(|a| match a {
                PlannerAction::ReplySnapshot { answer, .. } => answer.ok().map(|(_, s)| s),
                _ => None,
            });
            self.answer_map_bytes += snapshot.as_ref().map_or(0, |s| s.map.len());
            let loaded = self
                .replica
                .handle(PlannerEvent::SnapshotLoaded { tid, snapshot });
            self.decode_ahead(loaded);
            answered += 1;
        }
        answered
    }

    /// Decodes what the replica asks to be decoded ahead and hands it the copies.
    fn decode_ahead(&mut self, actions: Vec<PlannerAction>) {
        for action in actions {
            let PlannerAction::DecodeAhead { tid, snapshot } = action else {
                continue;
            };
            let started = Instant::now();
            let decoded = decode_ahead(&self.planning, tid, snapshot);
            self.decode_ahead_ms += ms_since(started);
            self.replica.handle(decoded);
        }
    }
}

pub(crate) fn cloud_event(seq: usize, cloud: &RoiCloud) -> PlannerEvent {
    PlannerEvent::Cloud {
        sender: DETECTOR.into(),
        header: Header {
            seq: seq as u64 + 1,
            trolley_id: TROLLEY.into(),
            source_id: DETECTOR.into(),
            ..Header::default()
        },
        cloud: cloud.clone(),
        received_ns: 0,
    }
}

/// The replica takes over from the lost owner `owner_pid`: the ms until its views, the ms of the
/// clusters and fits that follow them (fed back as the driver does), and whether it planned.
fn take_over(replica: &mut PlannerNode, owner_pid: String) -> (f64, f64, bool) {
    let started = Instant::now();
    let actions = replica.handle(PlannerEvent::PlannerLeft(owner_pid));
    let to_views_ms = ms_since(started);
    let plans = actions.iter().any(|a| {
        matches!(
            a,
            PlannerAction::Publish {
                output: TrolleyOutput::Views(_),
                ..
            }
        )
    });
    let started = Instant::now();
    for action in actions {
        if let PlannerAction::Finish { tid } = action {
            replica.handle(PlannerEvent::Finish { tid });
        }
    }
    (to_views_ms, ms_since(started), plans)
}

pub(crate) fn ms_since(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

/// What feeding a run's clouds to owner and replica measured.
struct Fed {
    frame_costs: Vec<FrameCost>,
    replica_ms: f64,
    snapshots: usize,
    /// The owner's stage totals after the first window and before the last one.
    stages_at: (StageTimes, StageTimes),
}

/// Hands every cloud to the owner, then to the replica (answering its snapshot queries), and
/// times each.
fn feed(pair: &mut Pair, clouds: &[RoiCloud], window: usize) -> Fed {
    let frames = clouds.len();
    let mut fed = Fed {
        frame_costs: Vec::with_capacity(frames),
        replica_ms: 0.0,
        snapshots: 0,
        stages_at: (StageTimes::default(), StageTimes::default()),
    };
    let bar = crate::progress::Progress::new("replay", frames as u64);
    for (seq, cloud) in clouds.iter().enumerate() {
        let stages_before = pair.owner.stats().stages;
        if seq == window {
            fed.stages_at.0 = stages_before;
        }
        if seq == frames - window {
            fed.stages_at.1 = stages_before;
        }
        let started = Instant::now();
        pair.owner.handle(cloud_event(seq, cloud));
        let owner_ms = ms_since(started);
        let stages = pair.owner.stats().stages.since(&stages_before);
        fed.frame_costs
            .push(FrameCost::new(cloud, owner_ms, stages));
        let started = Instant::now();
        let actions = pair.replica.handle(cloud_event(seq, cloud));
        fed.snapshots += pair.answer(actions);
        fed.replica_ms += ms_since(started);
        bar.inc(1);
    }
    bar.finish_and_clear();
    fed
}

/// The value at quantile `q` (0..=1) of ascending `sorted`, NaN when empty.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    match sorted.len() {
        0 => f64::NAN,
        n => sorted[((n - 1) as f64 * q).round() as usize],
    }
}

fn replay(
    config: &TrialConfig,
    window: usize,
    replica: ReplicaSetup,
    info: &TrolleyInfo,
    clouds: &[RoiCloud],
) -> anyhow::Result<ReplicaRun> {
    let mut pair = Pair::new(config, replica, info)?;
    let frames = clouds.len();
    let window = window.clamp(1, frames);
    let fed = feed(&mut pair, clouds, window);
    // The decodes ahead ran inside the replica's turn here; the service runs them on idle
    // cores, so they are reported apart.
    let replica_ms = fed.replica_ms - pair.decode_ahead_ms;
    let owner_pid = pair.owner.pid().to_string();
    let (takeover_ms, takeover_finish_ms, takeover_plans) = take_over(&mut pair.replica, owner_pid);
    let owner_map = pair.owner.planner(TROLLEY).context("owner holds t1")?.map();
    let replica_map = pair
        .replica
        .planner(TROLLEY)
        .context("replica holds t1")?
        .map();
    let owner_ms: Vec<f64> = fed.frame_costs.iter().map(|f| f.owner_ms).collect();
    let owner_total: f64 = owner_ms.iter().sum();
    let per_frame = |from: &StageTimes, to: &StageTimes| {
        let lap = to.since(from).named();
        lap.iter()
            .map(|&(name, ms)| (name, ms / window as f64))
            .collect()
    };
    let mean = |s: &[f64]| s.iter().sum::<f64>() / s.len() as f64;
    let mut sorted_ms = owner_ms.clone();
    sorted_ms.sort_by(f64::total_cmp);
    Ok(ReplicaRun {
        replica_refresh_clouds: replica.refresh,
        max_range_m: config.max_range_m,
        merge_far_rays: config.merge_far_rays,
        frames,
        owner_ms_per_frame: owner_total / frames as f64,
        owner_ms_p50_p90_p99_max: [0.5, 0.9, 0.99, 1.0].map(|q| quantile(&sorted_ms, q)),
        replica_ms_per_frame: replica_ms / frames as f64,
        replica_share_of_owner: replica_ms / owner_total,
        replica_decode_ahead_ms_per_frame: pair.decode_ahead_ms / frames as f64,
        snapshots: fed.snapshots,
        refresh_by_delta: replica.by_delta,
        deltas: pair.owner.stats().snapshot_deltas_sent,
        snapshot_map_bytes: pair.answer_map_bytes,
        owner_ms_per_answer: pair.answer_ms / fed.snapshots.max(1) as f64,
        owner_ms_first_frames: mean(&owner_ms[..window]),
        owner_ms_last_frames: mean(&owner_ms[frames - window..]),
        owner_stages_first_frames: per_frame(&StageTimes::default(), &fed.stages_at.0),
        owner_stages_last_frames: per_frame(&fed.stages_at.1, &pair.owner.stats().stages),
        takeover_ms,
        takeover_finish_ms,
        takeover_plans,
        maps_equal: same_map(owner_map, replica_map),
        map_voxels: owner_map.len(),
        frame_costs: fed.frame_costs,
    })
}

/// The recording's settings with each `--max-range` and `--merge-far-rays` value, checked.
fn integration_configs(
    args: &BenchReplicaArgs,
    recording: &TrialConfig,
) -> anyhow::Result<Vec<TrialConfig>> {
    if args.max_range.is_empty() || args.merge_far_rays.is_empty() {
        bail!("--max-range and --merge-far-rays need at least one value each");
    }
    let mut configs = Vec::new();
    for &max_range_m in &args.max_range {
        for &merge_far_rays in &args.merge_far_rays {
            let config = TrialConfig {
                max_range_m,
                merge_far_rays,
                ..*recording
            };
            config
                .validate()
                .with_context(|| format!("--max-range {max_range_m}"))?;
            configs.push(config);
        }
    }
    Ok(configs)
}

/// Whether both maps hold the same voxels with the same values and scan count.
pub(crate) fn same_map(a: &RoiMap, b: &RoiMap) -> bool {
    a.len() == b.len()
        && a.scans_inserted() == b.scans_inserted()
        && a.iter().all(|(key, voxel)| b.get(key) == Some(voxel))
}

fn print_run(run: &ReplicaRun) {
    let mode = match run.replica_refresh_clouds {
        0 => "hot replica (integrates every cloud)".to_string(),
        n => format!("standby replica (snapshot every {n} clouds)"),
    };
    println!(
        "{mode}, rays integrated up to {} m{}, {} frames:",
        run.max_range_m,
        if run.merge_far_rays {
            ", far rays merged"
        } else {
            ""
        },
        run.frames
    );
    println!(
        "  refreshes answered by delta where they can be: {} ({} of {} were); {:.1} ms per answer, {:.2} MB of map in all",
        run.refresh_by_delta,
        run.deltas,
        run.snapshots,
        run.owner_ms_per_answer,
        run.snapshot_map_bytes as f64 / 1e6
    );
    println!(
        "  owner {:.1} ms/frame, replica {:.1} ms/frame ({:.0} % of the owner), {} snapshots",
        run.owner_ms_per_frame,
        run.replica_ms_per_frame,
        run.replica_share_of_owner * 100.0,
        run.snapshots
    );
    let [p50, p90, p99, max] = run.owner_ms_p50_p90_p99_max;
    println!("  owner per frame: p50 {p50:.1}, p90 {p90:.1}, p99 {p99:.1}, slowest {max:.1} ms");
    if run.replica_decode_ahead_ms_per_frame > 0.0 {
        println!(
            "  and the replica's decodes ahead of a takeover (on idle cores in the service): {:.1} ms/frame",
            run.replica_decode_ahead_ms_per_frame
        );
    }
    println!(
        "  owner at the start / end of the run: {:.1} / {:.1} ms/frame",
        run.owner_ms_first_frames, run.owner_ms_last_frames
    );
    let stages = |s: &BTreeMap<&'static str, f64>| {
        let named = StageTimes::default().named();
        let ms = |name: &str| s.get(name).copied().unwrap_or(0.0);
        let parts: Vec<String> = named
            .iter()
            .map(|(name, _)| format!("{name} {:.1}", ms(name)))
            .collect();
        parts.join(", ")
    };
    println!(
        "  owner stages, ms/frame, start: {}",
        stages(&run.owner_stages_first_frames)
    );
    println!(
        "  owner stages, ms/frame, end:   {}",
        stages(&run.owner_stages_last_frames)
    );
    println!(
        "  takeover {:.1} ms to views (plans: {}), then {:.1} ms of clusters and fits; maps equal voxel for voxel: {} ({} voxels)",
        run.takeover_ms, run.takeover_plans, run.takeover_finish_ms, run.maps_equal, run.map_voxels
    );
}
