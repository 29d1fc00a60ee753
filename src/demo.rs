//! `glasshouse demo`: the whole loop in one process over real Zenoh sessions.

use std::net::TcpListener;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use glasshouse_bus::{BusArgs, FleetSessions, Shutdown, ShutdownTrigger};
use glasshouse_dashboard::{DashboardCounters, DashboardSettings, FleetState, ServeSettings};
use glasshouse_detector::{DetectorCounters, DetectorSettings};
use glasshouse_edge::{EdgeConfig, EdgeCounters, EdgeEvent};
use glasshouse_geom::{FruitEstimate as Fruit, SolidKind};
use glasshouse_nbv::Method;
use glasshouse_planner::{PlannerCounters, PlannerSettings};
use glasshouse_proto::ViewKind;
use glasshouse_sim::ScenarioKind;
use glasshouse_trust::{Identity, Kind};
use serde::Serialize;

#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    /// Simulated scenario: 1 (arm on a pole), 2 (arm on a ceiling gantry) or row.
    #[arg(long, default_value = "1")]
    pub scenario: ScenarioKind,
    /// Scene and planner seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Number of views to execute.
    #[arg(long, default_value_t = 20)]
    pub views: u32,
    /// Planning method: ours-uu, ours-up, explo-uu or explo-up.
    #[arg(long, default_value = "ours-uu")]
    pub method: Method,
    /// Image width in pixels (height is 3/4 of it).
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Write a Rerun recording of the run.
    #[arg(long, value_name = "FILE.rrd")]
    pub record: Option<PathBuf>,
    /// Write an MCAP recording of the run to DIR (opens in Foxglove; `glasshouse replay`).
    #[arg(long, value_name = "DIR")]
    pub mcap: Option<PathBuf>,
    /// Serve Foxglove's live WebSocket protocol on ADDR (default 127.0.0.1:8765): in
    /// Foxglove, "Open connection", Foxglove WebSocket, ws://ADDR.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8765")]
    pub foxglove: Option<String>,
    /// Serve while running: the fleet web page, a live Rerun stream and the Rerun web viewer
    /// (the URLs are printed).
    #[arg(long)]
    pub serve: bool,
    /// Address of the fleet web page with --serve.
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:8080")]
    pub http: String,
    /// Keep serving after the run until Ctrl-C (with --serve).
    #[arg(long)]
    pub linger: bool,
    /// Write the result as JSON: {"views", "frames", "fruits": [{centre_m, size_m, volume_m3, ...}]}.
    #[arg(long, value_name = "FILE")]
    pub summary_json: Option<PathBuf>,
    /// Run through a secured bus: a fresh PKI in a temporary directory, the router with mutual
    /// TLS and the generated ACL, each component with its own certificate.
    #[arg(long)]
    pub secure: bool,
    /// Give up when the pipeline makes no progress for this long.
    #[arg(long, default_value_t = 60)]
    pub stall_timeout_s: u64,
    #[command(flatten)]
    pub perception: crate::eval::PerceptionArgs,
}

#[derive(Serialize)]
struct FruitSummary {
    id: u32,
    centre_m: [f32; 3],
    size_m: [f32; 3],
    volume_m3: f32,
    voxel_count: u32,
    confidence: f32,
    /// The whole-fruit ellipsoid fit (absent when the planner sent none).
    fitted: Option<FittedSummary>,
}

#[derive(Serialize)]
struct FittedSummary {
    centre_m: [f32; 3],
    semi_axes_m: [f32; 3],
    volume_m3: f32,
    box_volume_m3: f32,
    confidence: f32,
    is_fit: bool,
}

#[derive(Serialize)]
struct Summary {
    scenario: String,
    seed: u64,
    views: u32,
    frames: u64,
    /// Frames whose ranked views the arm could reach none of.
    frames_without_reachable_view: u64,
    wall_time_s: f64,
    sim_time_s: f64,
    fruits: Vec<FruitSummary>,
}

fn free_port() -> anyhow::Result<u16> {
    let listener = TcpListener::bind("127.0.0.1:0").context("no free loopback port")?;
    Ok(listener.local_addr()?.port())
}

pub async fn run(args: DemoArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let edge_config = EdgeConfig {
        scenario: args.scenario,
        seed: args.seed,
        max_views: args.views.max(1),
        width: args.width,
        height: args.width * 3 / 4,
        world: args.perception.world()?,
        ..EdgeConfig::default()
    };
    edge_config.validate()?;
    let mut planner_settings = PlannerSettings::default();
    planner_settings.planning.method = args.method;
    planner_settings.planning.seed = args.seed;
    planner_settings.validate()?;

    let mut pipeline = Pipeline::start(&args, edge_config, planner_settings).await?;
    let mut progress = Progress::default();
    progress.follow(&args, &mut pipeline, started).await?;
    let fruits = pipeline.stop(&args, progress.interrupted).await?;
    print_fruit_table(&fruits);
    let summary = Summary {
        scenario: args.scenario.to_string(),
        seed: args.seed,
        views: progress.views_done,
        frames: progress.frames,
        frames_without_reachable_view: progress.no_reachable,
        wall_time_s: started.elapsed().as_secs_f64(),
        sim_time_s: progress.sim_time_s,
        fruits: fruits.iter().map(FruitSummary::of).collect(),
    };
    println!(
        "{} views, {} frames ({} with no reachable view), {} fruits in {:.1} s wall ({:.1} s simulated)",
        summary.views,
        summary.frames,
        summary.frames_without_reachable_view,
        summary.fruits.len(),
        summary.wall_time_s,
        summary.sim_time_s
    );
    if let Some(path) = &args.summary_json {
        std::fs::write(path, serde_json::to_string_pretty(&summary)?)
            .with_context(|| format!("writing {}", path.display()))?;
        println!("summary written to {}", path.display());
    }
    if let Some(path) = &args.record {
        println!("recording written to {}", path.display());
    }
    if progress.interrupted {
        anyhow::bail!("interrupted");
    }
    Ok(())
}

type ServiceTask = tokio::task::JoinHandle<anyhow::Result<()>>;

/// The running loop: a router, the four components as tasks, and the edge's events.
struct Pipeline {
    router: glasshouse_bus::zenoh::Session,
    /// Stops the services; the edge has a trigger of its own so it can finish first.
    trigger: ShutdownTrigger,
    edge_trigger: ShutdownTrigger,
    state: Arc<Mutex<FleetState>>,
    tid: String,
    dashboard: ServiceTask,
    detector: ServiceTask,
    planner: ServiceTask,
    edge: ServiceTask,
    events: tokio::sync::mpsc::UnboundedReceiver<EdgeEvent>,
    ctrl_c: tokio::task::JoinHandle<()>,
    /// A secured demo's PKI, removed once the router is closed.
    pki: Option<PathBuf>,
}

/// How the demo's router and components open their sessions.
struct Sessions {
    fleet: FleetSessions,
    /// The secured demo's PKI, removed at the end.
    pki: Option<PathBuf>,
}

impl Sessions {
    fn new(args: &DemoArgs, edge: &EdgeConfig, planner: &PlannerSettings) -> anyhow::Result<Self> {
        let port = free_port()?;
        if !args.secure {
            return Ok(Self {
                fleet: FleetSessions::plain(&format!("tcp/127.0.0.1:{port}")),
                pki: None,
            });
        }
        let endpoint = format!("tls/127.0.0.1:{port}");
        let roster = glasshouse_trust::Roster {
            trolleys: vec![edge.trolley_id.clone()],
            planners: vec![planner.planner_id.clone()],
            detectors: vec![DetectorSettings::default().detector_id],
            dashboards: vec![DEMO_DASHBOARD.into()],
            router_endpoint: endpoint.clone(),
            ..glasshouse_trust::Roster::default()
        };
        roster.validate()?;
        let dir = std::env::temp_dir().join(format!("glasshouse-demo-pki-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let layout = crate::secure::create(&dir, &roster, 1)?;
        println!("secured: a fresh PKI in {}", layout.dir.display());
        let config = |kind, ids: &[String]| -> anyhow::Result<BusArgs> {
            let name = Identity::new(kind, &ids[0])?.common_name();
            Ok(BusArgs {
                zenoh_config: Some(layout.config(&name)),
                ..BusArgs::default()
            })
        };
        let fleet = FleetSessions {
            router: BusArgs {
                zenoh_config: Some(layout.config(glasshouse_trust::ROUTER)),
                listen: vec![endpoint.clone()],
                ..BusArgs::default()
            },
            dashboard: config(Kind::Dashboard, &roster.dashboards)?,
            detector: config(Kind::Detector, &roster.detectors)?,
            planner: config(Kind::Planner, &roster.planners)?,
            edge: config(Kind::Trolley, &roster.trolleys)?,
            endpoint,
        };
        Ok(Self {
            fleet,
            pki: Some(dir),
        })
    }
}

/// The dashboard's identity in a secured demo.
const DEMO_DASHBOARD: &str = "demo";

impl Pipeline {
    async fn start(
        args: &DemoArgs,
        edge_config: EdgeConfig,
        planner_settings: PlannerSettings,
    ) -> anyhow::Result<Self> {
        // An in-process router on a free loopback port; every component is a client of it.
        let sessions = Sessions::new(args, &edge_config, &planner_settings)?;
        let endpoint = sessions.fleet.endpoint.clone();
        let router = glasshouse_bus::open(&sessions.fleet.router).await?;
        let (trigger, shutdown) = Shutdown::new();
        let (edge_trigger, edge_shutdown) = Shutdown::new();

        let state = Arc::new(Mutex::new(FleetState::default()));
        let dashboard_settings = dashboard_settings(args);
        let dashboard = tokio::spawn(glasshouse_dashboard::run(
            glasshouse_bus::open(&sessions.fleet.dashboard).await?,
            dashboard_settings,
            shutdown.clone(),
            state.clone(),
            Arc::new(DashboardCounters::default()),
        ));
        let detector = tokio::spawn(glasshouse_detector::run(
            glasshouse_bus::open(&sessions.fleet.detector).await?,
            DetectorSettings {
                fruit_model: args.perception.fruit_model.clone(),
                ..DetectorSettings::default()
            },
            shutdown.clone(),
            Arc::new(DetectorCounters::default()),
        ));
        let planner = tokio::spawn(glasshouse_planner::run(
            glasshouse_bus::open(&sessions.fleet.planner).await?,
            planner_settings,
            shutdown.clone(),
            Arc::new(PlannerCounters::default()),
        ));
        let (events_tx, events) = tokio::sync::mpsc::unbounded_channel();
        let tid = edge_config.trolley_id.clone();
        let edge = tokio::spawn(glasshouse_edge::run(
            glasshouse_bus::open(&sessions.fleet.edge).await?,
            edge_config,
            edge_shutdown,
            Some(events_tx),
            Arc::new(EdgeCounters::default()),
        ));
        let ctrl_c = tokio::spawn(async move {
            glasshouse_bus::shutdown_signal().await;
        });
        println!(
            "glasshouse demo: scenario {} seed {} views {} method {} (router + 4 Zenoh sessions over {endpoint}{})",
            args.scenario,
            args.seed,
            args.views,
            args.method,
            if args.secure { ", mutual TLS + ACL" } else { "" }
        );
        Ok(Pipeline {
            router,
            trigger,
            edge_trigger,
            state,
            tid,
            dashboard,
            detector,
            planner,
            edge,
            events,
            ctrl_c,
            pki: sessions.pki,
        })
    }

    fn fruit_count(&self) -> usize {
        self.state
            .lock()
            .map(|s| s.trolleys.get(&self.tid).map_or(0, |t| t.fruits.len()))
            .unwrap_or(0)
    }

    /// Stops the edge, then (after lingering if asked) the services and the router; returns the
    /// fruits the dashboard holds for the trolley.
    async fn stop(mut self, args: &DemoArgs, interrupted: bool) -> anyhow::Result<Vec<Fruit>> {
        self.edge_trigger.fire();
        self.edge.await.context("edge task")??;
        if args.serve && args.linger && !interrupted {
            println!("run finished; still serving (Ctrl-C to stop)");
            let _ = (&mut self.ctrl_c).await;
        }
        wait_for_last_fruits(&self.state, &self.tid).await;
        self.trigger.fire();
        for (name, task) in [
            ("planner", self.planner),
            ("detector", self.detector),
            ("dashboard", self.dashboard),
        ] {
            tokio::time::timeout(Duration::from_secs(20), task)
                .await
                .with_context(|| format!("{name} did not stop"))?
                .with_context(|| format!("{name} task"))??;
        }
        self.ctrl_c.abort();
        let _ = self.router.close().await;
        if let Some(pki) = &self.pki {
            let _ = std::fs::remove_dir_all(pki);
        }
        Ok(self
            .state
            .lock()
            .map(|s| {
                s.trolleys
                    .get(&self.tid)
                    .map(|t| t.fruits.clone())
                    .unwrap_or_default()
            })
            .unwrap_or_default())
    }
}

/// How long the demo waits at the end for the fruits of the last frame planned on.
const LAST_FRUITS_WAIT: Duration = Duration::from_secs(10);

/// Waits until the dashboard holds trolley `tid`'s fruits of the frame its last views were
/// planned on: the planner publishes them beside the views, on a key and publisher of their
/// own, so they may arrive after the edge has taken the views and finished. Gives up after
/// `LAST_FRUITS_WAIT` (the table then shows an earlier frame's fruits, and a warning says so).
async fn wait_for_last_fruits(state: &Mutex<FleetState>, tid: &str) {
    let caught_up = || {
        let state = state.lock().ok()?;
        let trolley = state.trolleys.get(tid)?;
        let planned = trolley.last_views.as_ref()?.based_on_seq;
        Some(trolley.fruits_based_on_seq >= planned)
    };
    let started = Instant::now();
    while started.elapsed() < LAST_FRUITS_WAIT {
        // No views at all: nothing to wait for.
        if caught_up().unwrap_or(true) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    tracing::warn!(trolley = %tid, "the fruits of the last frame did not arrive: the table shows an earlier frame's");
}

fn dashboard_settings(args: &DemoArgs) -> DashboardSettings {
    let serve = args.serve.then(|| ServeSettings {
        bind_ip: "127.0.0.1".into(),
        ..ServeSettings::default()
    });
    if let Some(serve) = &serve {
        println!("fleet web page:   http://{}/", args.http);
        println!("live 3D view:     {}", serve.web_viewer_url());
        println!("Rerun viewer:     rerun {}", serve.grpc_url());
    }
    DashboardSettings {
        record: args.record.clone(),
        serve,
        http_listen: args.serve.then(|| args.http.clone()),
        mcap: args
            .mcap
            .clone()
            .map(|dir| glasshouse_dashboard::McapSettings {
                dir,
                ..Default::default()
            }),
        foxglove: args
            .foxglove
            .clone()
            .map(|listen| glasshouse_dashboard::FoxgloveLiveSettings {
                listen,
                ..Default::default()
            }),
    }
}

/// What the edge reported so far.
#[derive(Default)]
struct Progress {
    frames: u64,
    views_done: u32,
    no_reachable: u64,
    sim_time_s: f64,
    interrupted: bool,
}

impl Progress {
    /// Prints the edge's events until it finishes, Ctrl-C, or no progress for the stall timeout.
    async fn follow(
        &mut self,
        args: &DemoArgs,
        pipeline: &mut Pipeline,
        started: Instant,
    ) -> anyhow::Result<()> {
        let stall = Duration::from_secs(args.stall_timeout_s.max(5));
        loop {
            let ctrl_c = &pipeline.ctrl_c;
            let event = tokio::select! {
                _ = async { while !ctrl_c.is_finished() { tokio::time::sleep(Duration::from_millis(100)).await } } => {
                    self.interrupted = true;
                    return Ok(());
                }
                e = tokio::time::timeout(stall, pipeline.events.recv()) => e,
            };
            match event {
                Err(_) => {
                    pipeline.edge_trigger.fire();
                    pipeline.trigger.fire();
                    anyhow::bail!(
                        "no progress for {} s: is a component stuck?",
                        stall.as_secs()
                    );
                }
                Ok(None) => return Ok(()),
                Ok(Some(event)) => {
                    if self.on_event(args, pipeline, event, started) {
                        return Ok(());
                    }
                }
            }
        }
    }

    /// Takes in one event; true once the edge has finished.
    fn on_event(
        &mut self,
        args: &DemoArgs,
        pipeline: &Pipeline,
        event: EdgeEvent,
        started: Instant,
    ) -> bool {
        match event {
            EdgeEvent::ViewDone {
                views_done: n,
                frame_seq,
                view,
                sim_time_s: t,
            } => {
                self.views_done = n;
                self.sim_time_s = t;
                let fruits = pipeline.fruit_count();
                let kind = match view.kind {
                    ViewKind::Roi => "roi",
                    ViewKind::Exploration => "exploration",
                };
                println!(
                    "view {n:>3}/{}  frame {frame_seq:>3}  {kind:<11} utility {:>6.3} gain {:>5.3} move {:>4.2} m  fruits {fruits:>3}  sim {t:>6.1} s  wall {:>5.1} s",
                    args.views,
                    view.utility,
                    view.gain,
                    view.cost_m,
                    started.elapsed().as_secs_f64()
                );
            }
            EdgeEvent::NoReachableView { frame_seq, offered } => {
                self.no_reachable += 1;
                println!("frame {frame_seq}: none of {offered} views reachable, capturing again");
            }
            EdgeEvent::Reannounced { frame_seq } => {
                println!("frame {frame_seq}: no views yet, re-announced");
            }
            EdgeEvent::ViewsRefused { source_id, .. } => {
                println!("views from {source_id} refused: not the trolley's owner");
            }
            EdgeEvent::MisattributedViewsRefused {
                sender, claimed, ..
            } => {
                println!("views from {sender} refused: their header claims {claimed}");
            }
            EdgeEvent::StaleViewsRefused {
                source_id,
                owner_epoch,
                newest,
                ..
            } => {
                println!(
                    "views from {source_id} refused: epoch {owner_epoch}, older than {newest}"
                );
            }
            EdgeEvent::SegmentDone {
                segments_done,
                sim_time_s,
            } => {
                println!(
                    "segment {segments_done} done: moving along the row  sim {sim_time_s:6.1} s"
                );
            }
            EdgeEvent::Finished {
                views_done: n,
                frames: f,
            } => {
                self.views_done = n;
                self.frames = f;
                return true;
            }
        }
        false
    }
}

impl FruitSummary {
    fn of(f: &Fruit) -> Self {
        let size = f.max - f.min;
        FruitSummary {
            id: f.id,
            centre_m: f.centre.cast::<f32>().into(),
            size_m: size.cast::<f32>().into(),
            volume_m3: f.volume_m3 as f32,
            voxel_count: f.voxel_count.min(u32::MAX as usize) as u32,
            confidence: f.confidence as f32,
            fitted: f.solid.as_ref().map(|e| FittedSummary {
                centre_m: e.centre.cast::<f32>().into(),
                semi_axes_m: ((e.box_max - e.box_min) / 2.0).cast::<f32>().into(),
                volume_m3: e.volume_m3 as f32,
                box_volume_m3: e.box_volume_m3 as f32,
                confidence: e.confidence as f32,
                is_fit: e.kind == SolidKind::Ellipsoid,
            }),
        }
    }
}

fn print_fruit_table(fruits: &[Fruit]) {
    println!();
    println!(
        "{:>4}  {:-^56}  {:-^50}",
        "", " box estimate ", " fitted ellipsoid "
    );
    println!(
        "{:>4}  {:>23}  {:>19}  {:>6}  {:>4}  {:>23}  {:>15}  {:>6}  {:>4}",
        "id",
        "centre (m)",
        "size (cm)",
        "cm³",
        "conf",
        "centre (m)",
        "diameters (cm)",
        "cm³",
        "conf"
    );
    for f in fruits {
        let c = f.centre;
        let s = (f.max - f.min) * 100.0;
        let fitted = match &f.solid {
            Some(e) => {
                let fc = e.centre;
                let d = (e.box_max - e.box_min) * 100.0;
                format!(
                    "{:>7.3} {:>7.3} {:>7.3}  {:>4.1} x{:>4.1} x{:>4.1}  {:>6.1}  {:>4.2}{}",
                    fc.x,
                    fc.y,
                    fc.z,
                    d.x,
                    d.y,
                    d.z,
                    e.volume_m3 * 1e6,
                    e.confidence,
                    if e.kind == SolidKind::Ellipsoid {
                        ""
                    } else {
                        " (box)"
                    }
                )
            }
            None => "(no fit)".to_owned(),
        };
        println!(
            "{:>4}  {:>7.3} {:>7.3} {:>7.3}  {:>5.1} x{:>5.1} x{:>5.1}  {:>6.1}  {:>4.2}  {}",
            f.id,
            c.x,
            c.y,
            c.z,
            s.x,
            s.y,
            s.z,
            f.volume_m3 * 1e6,
            f.confidence,
            fitted
        );
    }
    if fruits.is_empty() {
        println!("(no fruit found)");
    }
    println!();
}
