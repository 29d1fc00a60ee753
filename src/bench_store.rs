//! `glasshouse bench-store`: what keeping a trolley in the planner's store costs, and how long a
//! restart takes to bring a fleet's maps back.
//!
//! One process, no bus: a simulated trolley's run gives the stream of ROI clouds, which an owner
//! [`PlannerNode`] with a store takes; every write it asks for is performed on a real store file
//! (`glasshouse_planner::storage`, redb) as the planner's driver would. Per frame: the bytes
//! written and the time the writes took. Then the owner's final copy is written as `--trolleys`
//! trolleys into a fresh store, and opening it, reading it and restoring every map into a new
//! node (what a planner does at start) is timed; the restored map is compared with the owner's.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use glasshouse_eval::{ComputeTime, TrialConfig};
use glasshouse_nbv::Method;
use glasshouse_planner::node::{PlannerAction, PlannerEvent, PlannerNode, StoreRules, StoreWrite};
use glasshouse_planner::storage::PlannerStore;
use glasshouse_proto::{RoiCloud, TrolleyInfo};
use glasshouse_sim::ScenarioKind;
use serde::Serialize;

use crate::bench_replica::{cloud_event, joining, ms_since, record_stream, same_map, TROLLEY};

#[derive(clap::Args, Debug)]
pub struct BenchStoreArgs {
    /// Simulated scenario: 1, 2 or row.
    #[arg(long, default_value = "row")]
    scenario: ScenarioKind,
    /// Scene and planner seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Frames of the trolley's run given to the owner.
    #[arg(long, default_value_t = 120)]
    frames: usize,
    /// Clouds logged between two checkpoints (the planner's `store.checkpoint_clouds`).
    #[arg(long, default_value_t = 8)]
    checkpoint_clouds: usize,
    /// Trolleys whose maps are restored together (each a copy of the run's final map).
    #[arg(long, default_value_t = 16)]
    trolleys: usize,
    /// Folder for the store files (default: a temporary one, removed).
    #[arg(long, value_name = "DIR")]
    dir: Option<PathBuf>,
    /// Also write the results as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Debug, Default, Serialize)]
struct StoreRun {
    frames: usize,
    checkpoint_clouds: usize,
    map_voxels: usize,
    /// The owner's own handling per frame (integration, fits, planning; the writes' encoding).
    owner_ms_per_frame: f64,
    /// Bytes handed to the store per frame, in all and by kind of write.
    bytes_per_frame: f64,
    cloud_bytes_per_frame: f64,
    checkpoint_bytes_per_frame: f64,
    full_checkpoint_bytes: u64,
    /// Time of each frame's cloud write, on the path to its views (durable when done): mean,
    /// p99 and the longest.
    cloud_write_ms: f64,
    cloud_write_ms_p99: f64,
    cloud_write_ms_max: f64,
    /// Time of a checkpoint's write, off that path (the writer thread does it while the
    /// planner works on the next cloud): mean and the longest.
    checkpoint_write_ms: f64,
    checkpoint_write_ms_max: f64,
    /// The store file's size at the end.
    file_bytes: u64,
    /// A full checkpoint of the final map (what a takeover writes first): its bytes, the time to
    /// encode it (the node) and to write it (the writer thread; the takeover's first cloud write
    /// waits behind it).
    final_map_checkpoint_bytes: u64,
    final_map_checkpoint_encode_ms: f64,
    final_map_checkpoint_write_ms: f64,
    trolleys_restored: usize,
    /// Open, read and decode every record (`PlannerStore::load`), then rebuild every map with
    /// its logged clouds (`PlannerNode::restore`).
    restore_load_ms: f64,
    restore_decode_ms: f64,
    restored_maps_equal: bool,
}

pub fn run(args: BenchStoreArgs) -> anyhow::Result<()> {
    if args.frames == 0 || args.trolleys == 0 || args.checkpoint_clouds == 0 {
        bail!("--frames, --trolleys and --checkpoint-clouds need at least 1");
    }
    let config = TrialConfig {
        budget_s: 86_400.0,
        compute_time: ComputeTime::Fixed { ms: 100.0 },
        ..TrialConfig::new(args.scenario, Method::OursUu, args.seed)
    };
    let (dir, temporary) = match &args.dir {
        Some(dir) => (dir.clone(), false),
        None => (
            std::env::temp_dir().join(format!("glasshouse-bench-store-{}", std::process::id())),
            true,
        ),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let (info, clouds) = record_stream(&config, args.frames)?;
    let result = measure(&args, &config, &dir, (&info, &clouds));
    if temporary {
        let _ = std::fs::remove_dir_all(&dir);
    }
    let run = result?;
    print_run(&run);
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&run)?;
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    if !run.restored_maps_equal {
        bail!("a map restored from the store differs from the owner's");
    }
    Ok(())
}

fn measure(
    args: &BenchStoreArgs,
    config: &TrialConfig,
    dir: &std::path::Path,
    (info, clouds): (&TrolleyInfo, &[RoiCloud]),
) -> anyhow::Result<StoreRun> {
    let rules = StoreRules {
        checkpoint_clouds: args.checkpoint_clouds,
        settle_ns: 0,
    };
    let path = dir.join("owner.redb");
    let _ = std::fs::remove_file(&path);
    let store = PlannerStore::open(&path)?;
    let mut owner = owner(config, rules, info);
    let mut run = StoreRun {
        frames: clouds.len(),
        checkpoint_clouds: args.checkpoint_clouds,
        ..StoreRun::default()
    };
    let (mut owner_ms, mut cloud_ms, mut checkpoint_ms) = (0.0, Vec::new(), Vec::new());
    let bar = crate::progress::Progress::new("bench-store", clouds.len() as u64);
    for (seq, cloud) in clouds.iter().enumerate() {
        let started = Instant::now();
        let mut actions = owner.handle(cloud_event(seq, cloud));
        actions.extend(finish(&mut owner, &actions));
        owner_ms += ms_since(started);
        for action in &actions {
            if let PlannerAction::Store(write) = action {
                let (before, started) = (store.totals().bytes, Instant::now());
                store.write(write)?;
                match write {
                    StoreWrite::Cloud { .. } => cloud_ms.push(ms_since(started)),
                    _ => checkpoint_ms.push(ms_since(started)),
                }
                note_write(&mut run, write, store.totals().bytes - before);
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let frames = clouds.len() as f64;
    let total = store.totals().bytes as f64;
    cloud_ms.sort_by(f64::total_cmp);
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    run.owner_ms_per_frame = owner_ms / frames;
    run.bytes_per_frame = total / frames;
    run.cloud_bytes_per_frame /= frames;
    run.checkpoint_bytes_per_frame /= frames;
    run.cloud_write_ms = mean(&cloud_ms);
    run.cloud_write_ms_p99 = crate::fleet_bench::percentile(&cloud_ms, 99.0).unwrap_or(0.0);
    run.cloud_write_ms_max = max(&cloud_ms);
    run.checkpoint_write_ms = mean(&checkpoint_ms);
    run.checkpoint_write_ms_max = max(&checkpoint_ms);
    drop(store);
    run.file_bytes = std::fs::metadata(&path)?.len();
    restore_fleet(args, config, dir, &owner, &mut run)?;
    Ok(run)
}

/// A planner alone with the trolley, owning it, with a store.
fn owner(config: &TrialConfig, rules: StoreRules, info: &TrolleyInfo) -> PlannerNode {
    let mut node = PlannerNode::new("p1", config.planning(), 0).with_store(rules);
    for event in joining(info) {
        node.handle(event);
    }
    node
}

/// The `Finish` events `actions` ask for, fed back as the driver does; what they give.
fn finish(node: &mut PlannerNode, actions: &[PlannerAction]) -> Vec<PlannerAction> {
    let mut more = Vec::new();
    for action in actions {
        if let PlannerAction::Finish { tid } = action {
            more.extend(node.handle(PlannerEvent::Finish { tid: tid.clone() }));
        }
    }
    more
}

fn note_write(run: &mut StoreRun, write: &StoreWrite, bytes: u64) {
    match write {
        StoreWrite::Cloud { .. } => run.cloud_bytes_per_frame += bytes as f64,
        StoreWrite::Checkpoint { full, .. } => {
            run.checkpoint_bytes_per_frame += bytes as f64;
            if *full {
                run.full_checkpoint_bytes += bytes;
            }
        }
        StoreWrite::Fruits(_) => {}
    }
}

/// Writes the owner's final copy as `args.trolleys` trolleys into a fresh store, then times
/// what a planner does at start: open, load, restore.
fn restore_fleet(
    args: &BenchStoreArgs,
    config: &TrialConfig,
    dir: &std::path::Path,
    owner: &PlannerNode,
    run: &mut StoreRun,
) -> anyhow::Result<()> {
    let path = dir.join("fleet.redb");
    let _ = std::fs::remove_file(&path);
    let planner = owner
        .planner(TROLLEY)
        .context("the owner holds the trolley")?;
    let epoch = owner.term(TROLLEY).unwrap_or(1);
    {
        let store = PlannerStore::open(&path)?;
        let (mut encode_ms, mut write_ms) = (0.0, 0.0);
        for i in 1..=args.trolleys {
            let started = Instant::now();
            let copy = planner.checkpoint(&format!("t{i}"), "p1", 0);
            encode_ms += ms_since(started);
            let started = Instant::now();
            store.write(&StoreWrite::Checkpoint {
                tid: format!("t{i}"),
                epoch,
                copy: Box::new(copy),
                full: true,
            })?;
            write_ms += ms_since(started);
        }
        let n = args.trolleys as f64;
        run.final_map_checkpoint_bytes = store.totals().bytes / args.trolleys as u64;
        run.final_map_checkpoint_encode_ms = encode_ms / n;
        run.final_map_checkpoint_write_ms = write_ms / n;
    }
    let started = Instant::now();
    let store = PlannerStore::open(&path)?;
    let loaded = store.load()?;
    run.restore_load_ms = ms_since(started);
    run.trolleys_restored = loaded.trolleys.len();
    let started = Instant::now();
    let mut node = PlannerNode::new("p1", config.planning(), 0).with_store(StoreRules {
        checkpoint_clouds: args.checkpoint_clouds,
        settle_ns: 0,
    });
    let failed = node.restore(loaded.trolleys, loaded.fruits);
    run.restore_decode_ms = ms_since(started);
    if !failed.is_empty() {
        bail!("not restored: {}", failed.join("; "));
    }
    run.map_voxels = planner.map().len();
    // Claimed as owner, the restored copy is the owner's map.
    node.handle(PlannerEvent::TrolleyJoined(TROLLEY.into()));
    node.handle(PlannerEvent::SnapshotLoaded {
        tid: TROLLEY.into(),
        snapshot: None,
    });
    let restored = node.planner(TROLLEY).context("restored t1")?;
    run.restored_maps_equal = same_map(planner.map(), restored.map());
    Ok(())
}

fn print_run(r: &StoreRun) {
    println!(
        "bench-store: {} frames, checkpoint every {} clouds, final map {} voxels",
        r.frames, r.checkpoint_clouds, r.map_voxels
    );
    println!(
        "  owner {:.1} ms per frame; its cloud's durable write {:.2} ms (p99 {:.2}, max {:.2}) before the views; a checkpoint {:.1} ms (max {:.1}) after them",
        r.owner_ms_per_frame,
        r.cloud_write_ms,
        r.cloud_write_ms_p99,
        r.cloud_write_ms_max,
        r.checkpoint_write_ms,
        r.checkpoint_write_ms_max
    );
    println!(
        "  written per frame {:.1} kB (clouds {:.1} kB, checkpoints {:.1} kB); first full checkpoint {:.1} kB; file {:.1} MB",
        r.bytes_per_frame / 1e3,
        r.cloud_bytes_per_frame / 1e3,
        r.checkpoint_bytes_per_frame / 1e3,
        r.full_checkpoint_bytes as f64 / 1e3,
        r.file_bytes as f64 / 1e6
    );
    println!(
        "  a full checkpoint of the final map (a takeover's first write): {:.1} MB, encoded in {:.0} ms, written in {:.0} ms",
        r.final_map_checkpoint_bytes as f64 / 1e6,
        r.final_map_checkpoint_encode_ms,
        r.final_map_checkpoint_write_ms
    );
    println!(
        "  restore of {} trolleys' maps: read {:.0} ms, rebuilt {:.0} ms; equal to the owner's: {}",
        r.trolleys_restored, r.restore_load_ms, r.restore_decode_ms, r.restored_maps_equal
    );
}
