//! End-to-end tests of Glasshouse over real Zenoh sessions.
//!
//! Helpers shared by the tests in `tests/`: free loopback ports, an in-process router, the four
//! services as tasks with their own sessions, and every wait bounded by a timeout.

pub mod procs;

use std::future::Future;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use glasshouse_bus::{BusArgs, Shutdown, ShutdownTrigger};
use glasshouse_dashboard::{DashboardCounters, DashboardSettings, FleetState};
use glasshouse_detector::{DetectorCounters, DetectorSettings};
use glasshouse_edge::{EdgeConfig, EdgeCounters, EdgeEvent};
use glasshouse_pipeline::TrolleyPlanner;
use glasshouse_planner::{PlannerCounters, PlannerSettings};
use glasshouse_proto::RoiCloud;
use glasshouse_roimap::RoiMap;
use tokio::task::JoinHandle;
use zenoh::Session;

/// A free TCP port on 127.0.0.1.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

/// An observer's subscriber: a deep drop-oldest queue, so phases that do not read it never
/// push back on the fleet (a test that loses what it needs fails on what it checks).
pub async fn observe<M: glasshouse_proto::Wire>(
    observer: &Session,
    key: &glasshouse_proto::keys::Key<M>,
) -> glasshouse_bus::Subscriber<M> {
    let drops = Arc::new(glasshouse_bus::DropCounters::default());
    glasshouse_bus::Subscriber::declare_with(
        observer,
        key,
        glasshouse_bus::Delivery::Monitor,
        drops,
    )
    .await
    .expect("subscriber")
}

/// Awaits `future` or fails the test after `secs` seconds.
pub async fn within<T>(secs: u64, what: &str, future: impl Future<Output = T>) -> T {
    match tokio::time::timeout(Duration::from_secs(secs), future).await {
        Ok(v) => v,
        Err(_) => panic!("timed out after {secs} s: {what}"),
    }
}

/// Waits until `condition` holds (checked every 50 ms), or fails the test after `secs` seconds.
pub async fn until(secs: u64, what: &str, mut condition: impl FnMut() -> bool) {
    within(secs, what, async {
        while !condition() {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
}

/// A client session to `endpoint`.
pub async fn client(endpoint: &str) -> Session {
    open(&BusArgs::client(endpoint)).await
}

/// A session opened from `args` (flags or a `--zenoh-config` file).
pub async fn open(args: &BusArgs) -> Session {
    within(10, "session", glasshouse_bus::open(args))
        .await
        .expect("session opens")
}

pub use glasshouse_bus::FleetSessions;

/// Plain TCP clients of a router on a free loopback port.
pub fn loopback_sessions() -> FleetSessions {
    FleetSessions::plain(&format!("tcp/127.0.0.1:{}", free_port()))
}

/// Small images keep the debug-build tests quick; the loop is the same.
pub fn test_edge_config(max_views: u32) -> EdgeConfig {
    EdgeConfig {
        width: 160,
        height: 120,
        max_views,
        views_timeout_ms: 2000,
        ..EdgeConfig::default()
    }
}

/// The four services as tasks, each with its own session, around an in-process router.
pub struct Pipeline {
    pub endpoint: String,
    pub router: Session,
    pub edge_counters: Arc<EdgeCounters>,
    pub detector_counters: Arc<DetectorCounters>,
    pub planner_counters: Arc<PlannerCounters>,
    pub dashboard_counters: Arc<DashboardCounters>,
    pub fleet: Arc<Mutex<FleetState>>,
    pub events: tokio::sync::mpsc::UnboundedReceiver<EdgeEvent>,
    events_tx: Option<tokio::sync::mpsc::UnboundedSender<EdgeEvent>>,
    sessions: FleetSessions,
    services: Vec<(&'static str, JoinHandle<anyhow::Result<()>>)>,
    triggers: Vec<ShutdownTrigger>,
}

impl Pipeline {
    /// Starts router, dashboard, detector, planner and edge.
    pub async fn start(edge_config: EdgeConfig) -> Pipeline {
        Self::start_with(edge_config, DashboardSettings::default()).await
    }

    /// Like [`Pipeline::start`] with dashboard settings (web page, recording).
    pub async fn start_with(edge_config: EdgeConfig, dashboard: DashboardSettings) -> Pipeline {
        let mut pipeline = Self::start_services(dashboard, PlannerSettings::default()).await;
        pipeline.start_edge(edge_config).await;
        pipeline
    }

    /// Starts router, dashboard, detector and planner; the edge comes with
    /// [`Pipeline::start_edge`] (observers can subscribe before the first frame).
    pub async fn start_services(
        dashboard: DashboardSettings,
        planner: PlannerSettings,
    ) -> Pipeline {
        Self::start_services_on(loopback_sessions(), dashboard, planner).await
    }

    /// Like [`Pipeline::start_services`], each process opening its session from `sessions`.
    pub async fn start_services_on(
        sessions: FleetSessions,
        dashboard: DashboardSettings,
        planner: PlannerSettings,
    ) -> Pipeline {
        let router = open(&sessions.router).await;
        let (events_tx, events) = tokio::sync::mpsc::unbounded_channel();
        let mut pipeline = Pipeline {
            endpoint: sessions.endpoint.clone(),
            router,
            edge_counters: Arc::new(EdgeCounters::default()),
            detector_counters: Arc::new(DetectorCounters::default()),
            planner_counters: Arc::new(PlannerCounters::default()),
            dashboard_counters: Arc::new(DashboardCounters::default()),
            fleet: Arc::new(Mutex::new(FleetState::default())),
            events,
            events_tx: Some(events_tx),
            sessions,
            services: Vec::new(),
            triggers: Vec::new(),
        };
        let session = open(&pipeline.sessions.dashboard).await;
        let task = glasshouse_dashboard::run(
            session,
            dashboard,
            pipeline.shutdown(),
            pipeline.fleet.clone(),
            pipeline.dashboard_counters.clone(),
        );
        pipeline.services.push(("dashboard", tokio::spawn(task)));
        let session = open(&pipeline.sessions.detector).await;
        let task = glasshouse_detector::run(
            session,
            DetectorSettings::default(),
            pipeline.shutdown(),
            pipeline.detector_counters.clone(),
        );
        pipeline.services.push(("detector", tokio::spawn(task)));
        let session = open(&pipeline.sessions.planner).await;
        let task = glasshouse_planner::run(
            session,
            planner,
            pipeline.shutdown(),
            pipeline.planner_counters.clone(),
        );
        pipeline.services.push(("planner", tokio::spawn(task)));
        pipeline
    }

    /// Stops the edge (its session and liveliness token go away) and checks that it ended
    /// cleanly, then starts a new one on a new session with `edge_config`: a restarted trolley,
    /// with a new boot epoch. The new edge's events arrive on `events`.
    pub async fn restart_edge(&mut self, edge_config: EdgeConfig) {
        let index = self
            .services
            .iter()
            .position(|(name, _)| *name == "edge")
            .expect("an edge runs");
        // Services and their triggers are pushed together, one each.
        self.triggers.remove(index).fire();
        let (name, task) = self.services.remove(index);
        within(20, name, task)
            .await
            .unwrap_or_else(|e| panic!("{name} task panicked: {e}"))
            .unwrap_or_else(|e| panic!("{name} failed: {e:#}"));
        let (events_tx, events) = tokio::sync::mpsc::unbounded_channel();
        self.events = events;
        self.events_tx = Some(events_tx);
        self.start_edge(edge_config).await;
    }

    /// Starts the edge; its events arrive on `events`.
    pub async fn start_edge(&mut self, edge_config: EdgeConfig) {
        let session = open(&self.sessions.edge).await;
        let task = glasshouse_edge::run(
            session,
            edge_config,
            self.shutdown(),
            self.events_tx.take(),
            self.edge_counters.clone(),
        );
        self.services.push(("edge", tokio::spawn(task)));
    }

    fn shutdown(&mut self) -> Shutdown {
        let (trigger, shutdown) = Shutdown::new();
        self.triggers.push(trigger);
        shutdown
    }

    /// Collects edge events until the edge finishes (or `secs` pass).
    pub async fn run_to_end(&mut self, secs: u64) -> Vec<EdgeEvent> {
        let mut events = Vec::new();
        within(secs, "the edge to finish its views", async {
            while let Some(event) = self.events.recv().await {
                let finished = matches!(event, EdgeEvent::Finished { .. });
                events.push(event);
                if finished {
                    break;
                }
            }
        })
        .await;
        if !matches!(events.last(), Some(EdgeEvent::Finished { .. })) {
            self.edge_failure().await;
        }
        events
    }

    /// Panics with the edge's error when its task ended early (its events stopped).
    async fn edge_failure(&mut self) {
        let ended = self
            .services
            .iter()
            .position(|(name, task)| *name == "edge" && task.is_finished());
        if let Some(index) = ended {
            self.triggers.remove(index);
            let (_, task) = self.services.remove(index);
            match task.await {
                Ok(Err(e)) => panic!("the edge failed: {e:#}"),
                Err(e) => panic!("the edge task panicked: {e}"),
                Ok(Ok(())) => {}
            }
        }
    }

    /// Stops every service and checks that each one ended cleanly.
    pub async fn stop(self) {
        for trigger in &self.triggers {
            trigger.fire();
        }
        for (name, task) in self.services {
            within(20, name, task)
                .await
                .unwrap_or_else(|e| panic!("{name} task panicked: {e}"))
                .unwrap_or_else(|e| panic!("{name} failed: {e:#}"));
        }
        let _ = self.router.close().await;
    }
}

/// The workspace's root.
pub fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The Python with rosbags, mcap and zenoh (`scripts/test` makes it: `.venv`).
pub fn python() -> PathBuf {
    let python = std::env::var_os("GLASSHOUSE_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join(".venv/bin/python"));
    assert!(
        python.is_file(),
        "{} missing: run scripts/test (it makes .venv from tests/python-requirements.txt)",
        python.display()
    );
    python
}

/// Runs one of `scripts/` with the project's Python; its stdout.
pub fn script(name: &str, args: &[&str]) -> String {
    let out = Command::new(python())
        .arg(workspace().join("scripts").join(name))
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {name}: {e}"));
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{name} {args:?} failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// The map a planner with default settings builds from these clouds of one edge run, integrating
/// each frame once, in arrival order (the planner's rule for an honest stream), each corrected by
/// the hand-eye estimate its planner makes as it goes.
pub fn rebuild(clouds: &[RoiCloud]) -> RoiMap {
    let settings = PlannerSettings::default();
    let mut planner = TrolleyPlanner::new(settings.planning).expect("planning settings");
    // Later than every frame's stamp: no frame is judged to come from the future.
    let now_ns = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(u64::MAX, |d| d.as_nanos() as u64);
    for c in clouds {
        planner.insert(c, now_ns).expect("cloud integrates");
    }
    planner.into_map()
}

/// A map's voxels (key, occupancy and ROI log-odds bits), sorted: equal lists, equal maps.
pub fn voxels(map: &RoiMap) -> Vec<([i32; 3], u32, u32)> {
    let mut v: Vec<_> = map
        .iter()
        .map(|(k, x)| {
            (
                [k.x, k.y, k.z],
                x.occupancy_logodds.to_bits(),
                x.roi_logodds.to_bits(),
            )
        })
        .collect();
    v.sort_unstable();
    v
}

/// A planner's map once its snapshot is at the last cloud observed, and every cloud observed.
pub struct SnapshotAtLastCloud {
    pub map: RoiMap,
    /// The newest ownership epoch the answering planner knew.
    pub owner_epoch: u64,
    pub clouds: Vec<RoiCloud>,
}

/// Asks `pid` for `tid`'s snapshot until it is at the last cloud `clouds_sub` has seen (the
/// detector may still publish a cloud of the edge's last frame after the edge is gone, and the
/// observer may get it after the planner), at most 60 s.
pub async fn snapshot_at_last_cloud(
    observer: &Session,
    clouds_sub: &glasshouse_bus::Subscriber<RoiCloud>,
    pid: &str,
    tid: &str,
) -> SnapshotAtLastCloud {
    snapshot_at_last_cloud_of(observer, &[clouds_sub], pid, tid).await
}

/// [`snapshot_at_last_cloud`] with the clouds of several subscriptions (one cloud each, in
/// frame order): an observer whose link moves between routers can miss a cloud another
/// session on the router that stays sees.
pub async fn snapshot_at_last_cloud_of(
    observer: &Session,
    clouds_subs: &[&glasshouse_bus::Subscriber<RoiCloud>],
    pid: &str,
    tid: &str,
) -> SnapshotAtLastCloud {
    let key = glasshouse_proto::keys::planner_snapshot(pid, tid).expect("key");
    let mut clouds = Vec::new();
    within(
        60,
        "the planner's snapshot at the last observed cloud",
        async {
            loop {
                for sub in clouds_subs {
                    while let Some(received) = sub.try_recv() {
                        let frame = received.message.source_frame();
                        if !clouds.iter().any(|c: &RoiCloud| c.source_frame() == frame) {
                            clouds.push(received.message);
                        }
                    }
                }
                clouds.sort_by_key(RoiCloud::source_frame);
                let last = clouds.iter().map(RoiCloud::source_frame).max();
                match glasshouse_bus::ask(observer, &key, Duration::from_secs(5)).await {
                    Ok((_, s)) => {
                        let at =
                            glasshouse_proto::FrameId::new(s.based_on_epoch_ns, s.based_on_seq);
                        if Some(at) == last {
                            return SnapshotAtLastCloud {
                                map: RoiMap::read_snapshot(s.map.as_slice())
                                    .expect("snapshot decodes"),
                                owner_epoch: s.owner_epoch,
                                clouds: std::mem::take(&mut clouds),
                            };
                        }
                        eprintln!("{pid} at {at:?}, last cloud observed {last:?}");
                    }
                    Err(e) => eprintln!("no snapshot of {pid} yet: {e}"),
                }
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        },
    )
    .await
}

/// `map` holds every scan of `clouds`: equal, voxel for voxel, to the map rebuilt from them.
pub fn assert_holds_every_cloud(map: &RoiMap, clouds: &[RoiCloud], whose: &str) {
    let expected = rebuild(clouds);
    eprintln!(
        "{} clouds; {whose} map {} voxels after {} scans",
        clouds.len(),
        map.len(),
        map.scans_inserted()
    );
    assert_eq!(map.scans_inserted(), expected.scans_inserted());
    assert!(
        voxels(map) == voxels(&expected),
        "{whose} map differs from the map of every published cloud"
    );
}
