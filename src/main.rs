//! The glasshouse command line: demo, router and user-facing tools.

mod bench_map;
mod bench_replica;
mod bench_store;
mod dashboard_bench;
mod dataset;
mod demo;
mod eval;
mod fleet_bench;
mod probe;
mod progress;
mod record;
mod relay;
mod render;
mod secure;

use clap::{Parser, Subcommand};
use glasshouse_bus::BusArgs;

/// Glasshouse: robot eyes that find every fruit on a row of plants.
///
/// Environment: GLASSHOUSE_SIMD=portable|avx2|avx512 caps the vector unit of the map's voxel
/// walks, here and in the services a bench starts (default: the widest the CPU has; every unit
/// gives the same map).
#[derive(Parser, Debug)]
#[command(name = "glasshouse", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the whole pipeline on the simulated glasshouse in one process: a trolley, a detector,
    /// a planner and a dashboard, each with its own Zenoh session over loopback TCP.
    Demo(demo::DemoArgs),
    /// Measure whether the dashboard keeps up with a fleet of synthetic trolleys, and its memory.
    DashboardBench(dashboard_bench::DashboardBenchArgs),
    /// Run the fleet as real processes over loopback Zenoh (router, detectors, planners, simulated
    /// trolleys), inject a fault half-way (a planner killed, paused or cut off; the router
    /// restarted or lost to a second one), and report views per minute, frame → views latency,
    /// drops, CPU and memory per process kind, and for every trolley the fault moved: the time
    /// until it was back on views, arm motions on stale views, and whether its map lost a scan.
    FleetBench(fleet_bench::FleetBenchArgs),
    /// Time the ROI map's scan insertion (OctoMap semantics) on your own PLY clouds.
    BenchMap(bench_map::BenchMapArgs),
    /// Measure what a trolley's replica planner costs next to its owner (hot or standby), its
    /// takeover time, and the owner's time per frame at the start and end of a run.
    BenchReplica(bench_replica::BenchReplicaArgs),
    /// Measure what the planner's store costs per frame (bytes, durable write time) and how long
    /// restoring a fleet's maps from it takes at start.
    BenchStore(bench_store::BenchStoreArgs),
    /// Run the paper's experiments on the simulator: seeded trials per method, Table I, p-values,
    /// per-trial CSVs and plots.
    Eval(eval::EvalArgs),
    /// Write simulator frames with per-pixel fruit labels (from the renderer's hit ids) as NumPy
    /// arrays, to train a learned detector (`scripts/train-detector`).
    Dataset(dataset::DatasetArgs),
    /// Render what the simulated camera sees to a colour PNG and a colour-mapped depth PNG.
    Render(render::RenderArgs),
    /// Secure a deployment: a CA, a certificate per identity, the router's mTLS listener and
    /// access control list, and one client config per identity (`init`, then `issue` to add).
    Secure(secure::SecureArgs),
    /// Record every Glasshouse key to MCAP files (our messages with their schema, and the same in
    /// Foxglove's schemas, so Foxglove opens a run with no plugin); files rotate by size and
    /// duration. Stops on Ctrl-C, SIGTERM or --duration-s.
    Record(record::RecordArgs),
    /// Put an MCAP recording back on the bus with its timing (`--only info,roi` to re-run a
    /// fresh planner on a run's clouds).
    Replay(record::ReplayArgs),
    /// Run a Zenoh router for a deployment: listens where `--zenoh-config` or `-l` says, else on
    /// tcp/0.0.0.0:7447.
    Router {
        #[command(flatten)]
        bus: BusArgs,
    },
    /// A TCP relay that cuts a link without closing it (SIGUSR1) and heals it (SIGUSR2): point a
    /// process at it instead of the router to rehearse a network partition on one machine.
    Relay(relay::RelayArgs),
}

/// Where a router listens when neither its config file nor a flag says.
const DEFAULT_ROUTER_LISTEN: &str = "tcp/0.0.0.0:7447";

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    glasshouse_bus::use_in_process_runtime_pools();
    glasshouse_bus::init_tracing();
    glasshouse_planner::cap_simd_from_env()?;
    match Cli::parse().command {
        Command::Demo(args) => demo::run(args).await,
        Command::DashboardBench(args) => dashboard_bench::run(args).await,
        Command::FleetBench(args) => fleet_bench::run(args).await,
        Command::BenchMap(args) => bench_map::run(args),
        Command::BenchReplica(args) => bench_replica::run(args),
        Command::BenchStore(args) => bench_store::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Render(args) => render::run(args),
        Command::Dataset(args) => dataset::run(args),
        Command::Secure(args) => secure::run(args).await,
        Command::Record(args) => record::record(args).await,
        Command::Replay(args) => record::replay(args).await,
        Command::Relay(args) => relay::run(args).await,
        Command::Router { bus } => {
            let config = glasshouse_bus::router_config(&bus, DEFAULT_ROUTER_LISTEN)?;
            let listen = config.get_json("listen/endpoints").unwrap_or_default();
            let session = zenoh::open(config)
                .await
                .map_err(|e| anyhow::anyhow!("cannot open the router: {e}"))?;
            tracing::info!(zid = %session.zid(), %listen, "router up");
            glasshouse_bus::shutdown_signal().await;
            let _ = session.close().await;
            Ok(())
        }
    }
}
