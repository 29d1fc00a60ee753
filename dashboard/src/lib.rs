//! The dashboard process: subscribes to everything and logs it to Rerun.
//!
//! Read-only: it declares no publisher. It keeps a [`FleetState`] (what each trolley, planner and
//! detector last said) for embedding processes and, with a recording path, logs every message to a
//! Rerun `.rrd` under `trolleys/{tid}/...`: camera pose and pinhole, colour and depth images, the
//! latest ROI cloud, ROI and occupied voxels (rebuilt from MapUpdate deltas), ranked views as
//! arrows with the executed one highlighted, fruit boxes labelled with size and volume, and time
//! series. Timelines: `sim_time` (the stamp of the data) and `wall_time`.
//!
//! Views, map updates and fruits under an older ownership epoch than the newest seen for their
//! trolley come from a replaced owner (paused, cut off): the fleet state and Rerun leave them out
//! and count them (`dropped_messages{reason="stale_epoch"}`); the MCAP recording keeps every
//! message as received.

pub mod blueprint;
pub mod foxglove;
pub mod foxglove_live;
pub mod mcap_recorder;
mod recorder;
pub mod web;

use std::collections::{BTreeMap, VecDeque};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use glasshouse_bus::{AnySubscriber, Delivery, DropCounters, Received, Shutdown};
use glasshouse_fleet::EpochFence;
use glasshouse_geom::FruitEstimate;
use glasshouse_proto::keys::{self, ParsedKey, Qos, TrolleyTopic};
use glasshouse_proto::{
    DetectorStatus, FleetFruits, FrameId, FrameRegistration, FruitHistory, Header, Message,
    PlannerStatus, RankedViews, TrolleyInfo, TrolleyStatus,
};
use serde::Deserialize;
use zenoh::Session;

pub use foxglove_live::{FoxgloveLive, FoxgloveLiveSettings, FoxgloveLiveSummary};
pub use mcap_recorder::{McapRecorder, McapSettings, McapSummary};
pub use recorder::Recorder;

/// Dashboard settings; a JSON5 file may set any of them.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DashboardSettings {
    /// Write everything to this Rerun recording (.rrd).
    pub record: Option<PathBuf>,
    /// Serve the live stream to Rerun viewers (gRPC) and the bundled web viewer.
    pub serve: Option<ServeSettings>,
    /// Address of the fleet web page and JSON API (e.g. `0.0.0.0:8080`); none = off.
    pub http_listen: Option<String>,
    /// Record every key to MCAP files in a folder (`{ dir, max_file_bytes, max_file_s,
    /// foxglove, queue }`), for Foxglove and for `glasshouse replay`.
    pub mcap: Option<McapSettings>,
    /// Serve Foxglove's live WebSocket protocol (`{ listen, queue }`; listen defaults to
    /// `127.0.0.1:8765`, Foxglove's default connection).
    pub foxglove: Option<FoxgloveLiveSettings>,
}

/// Live Rerun serving: a gRPC server that buffers up to a memory limit, plus the web viewer.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServeSettings {
    pub bind_ip: String,
    pub grpc_port: u16,
    pub web_viewer_port: u16,
    /// Host name put in the viewer URLs printed and linked from the web page.
    pub public_host: String,
    /// Bytes of log data the gRPC server keeps for late viewers (oldest dropped first).
    pub memory_limit_bytes: u64,
}

impl Default for ServeSettings {
    fn default() -> Self {
        Self {
            bind_ip: "0.0.0.0".into(),
            grpc_port: 9877,
            web_viewer_port: 9090,
            public_host: "localhost".into(),
            memory_limit_bytes: 512 << 20,
        }
    }
}

impl ServeSettings {
    /// The gRPC URL a viewer connects to.
    pub fn grpc_url(&self) -> String {
        format!("rerun+http://{}:{}/proxy", self.public_host, self.grpc_port)
    }

    /// The web viewer URL, opening the live stream.
    pub fn web_viewer_url(&self) -> String {
        format!(
            "http://{}:{}/?url={}",
            self.public_host,
            self.web_viewer_port,
            self.grpc_url().replace(':', "%3A").replace('/', "%2F")
        )
    }
}

/// Frame → views latencies kept per trolley (the newest).
const LATENCY_WINDOW: usize = 256;
/// Frames remembered per trolley while waiting for their views.
const PENDING_FRAMES: usize = 64;

/// What the dashboard knows about one trolley.
#[derive(Clone, Debug, Default)]
pub struct TrolleyView {
    /// When the latest frame arrived (wall clock of this process).
    pub last_frame_at: Option<Instant>,
    /// Arrival of recent frames (boot epoch and seq), to time frame → views.
    pending_frames: VecDeque<(FrameId, Instant)>,
    /// Recent frame → views latencies in milliseconds.
    pub latencies_ms: VecDeque<f64>,
    pub info: Option<TrolleyInfo>,
    pub status: Option<TrolleyStatus>,
    pub fruits: Vec<FruitEstimate>,
    /// The frame the latest fruits were estimated on.
    pub fruits_based_on_seq: u64,
    /// The visit of its row the latest fruits are from (0: the first).
    pub visit: u32,
    /// Every fruit of the row's season as the latest fruits carried it.
    pub history: Vec<FruitHistory>,
    pub last_views: Option<RankedViews>,
    pub frames: u64,
    pub clouds: u64,
    pub views_messages: u64,
    pub map_updates: u64,
    pub map_voxels_changed: u64,
    /// How the planner registered the trolley's last registered cloud (its MapUpdate's).
    pub last_registration: Option<FrameRegistration>,
    pub planner_id: String,
    /// Ground truth, when the source is the simulator.
    pub truth: Vec<FruitEstimate>,
    /// Share of the ground-truth fruit voxels inside detected boxes (paper-method §5), when
    /// the truth is known.
    pub covered_volume: Option<f64>,
    /// Where the camera is (world frame, metres), from the latest arm state.
    pub camera_position_m: Option<[f64; 3]>,
}

/// Everything the dashboard has heard.
#[derive(Clone, Debug, Default)]
pub struct FleetState {
    pub trolleys: BTreeMap<String, TrolleyView>,
    pub planners: BTreeMap<String, PlannerStatus>,
    /// When each planner's status last arrived (a lost planner's row ages).
    pub planner_seen_at: BTreeMap<String, Instant>,
    /// The latest merged fleet fruit map.
    pub fleet_fruits: Option<FleetFruits>,
    pub detectors: BTreeMap<String, DetectorStatus>,
    pub messages: u64,
    /// The newest ownership epoch seen per trolley (views, map updates, fruits).
    pub fence: EpochFence,
    /// Views, map updates and fruits left out: an older ownership epoch than the newest seen.
    pub stale_epoch: u64,
}

impl TrolleyView {
    /// Latency percentile (0..=100) over the recent window, in milliseconds.
    pub fn latency_percentile_ms(&self, percentile: f64) -> Option<f64> {
        if self.latencies_ms.is_empty() {
            return None;
        }
        let mut sorted: Vec<f64> = self.latencies_ms.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        let rank = (percentile / 100.0 * (sorted.len() - 1) as f64).round() as usize;
        sorted.get(rank.min(sorted.len() - 1)).copied()
    }

    /// Messages this trolley reported dropping.
    pub fn drops(&self) -> u64 {
        self.status.as_ref().map_or(0, |s| s.dropped_messages)
    }
}

/// The ownership epoch of an owner's output (views, map update, fruits) on a trolley's key;
/// None for every other message (the truth on its own key has no owner).
fn owner_epoch(key: &ParsedKey, message: &Message) -> Option<u64> {
    match (key, message) {
        (ParsedKey::Trolley { topic, .. }, message) => match (topic, message) {
            (TrolleyTopic::Views, Message::RankedViews(v)) => Some(v.owner_epoch),
            (TrolleyTopic::Map, Message::MapUpdate(m)) => Some(m.owner_epoch),
            (TrolleyTopic::Fruits, Message::FruitEstimates(f)) => Some(f.owner_epoch),
            _ => None,
        },
        _ => None,
    }
}

impl TrolleyView {
    /// Folds one message on the trolley's key `topic`, received at `now`, into its row.
    fn apply(&mut self, topic: TrolleyTopic, header: &Header, message: &Message, now: Instant) {
        match (topic, message) {
            (TrolleyTopic::Rgbd, Message::RgbdFrame(_)) => self.note_frame(header, now),
            (TrolleyTopic::Info, Message::TrolleyInfo(info)) => self.info = Some(info.clone()),
            (TrolleyTopic::Arm, Message::ArmState(a)) => {
                self.camera_position_m = Some(a.world_from_camera.translation.vector.into());
            }
            (TrolleyTopic::Status, Message::TrolleyStatus(s)) => self.status = Some(s.clone()),
            (TrolleyTopic::Roi, Message::RoiCloud(_)) => self.clouds += 1,
            (TrolleyTopic::Views, Message::RankedViews(v)) => self.note_views(v, now),
            (TrolleyTopic::Fruits, Message::FruitEstimates(f)) => {
                self.fruits = f.fruits.clone();
                self.fruits_based_on_seq = f.based_on_seq;
                self.visit = f.visit;
                self.history = f.history.clone();
                self.covered_volume = covered_volume(&self.fruits, &self.truth);
            }
            (TrolleyTopic::Truth, Message::FruitEstimates(f)) if self.truth != f.fruits => {
                self.truth = f.fruits.clone();
                self.covered_volume = covered_volume(&self.fruits, &self.truth);
            }
            (TrolleyTopic::Map, Message::MapUpdate(m)) => {
                self.map_updates += 1;
                self.map_voxels_changed += m.voxels.len() as u64;
                // A re-announced frame's update carries none: the last one stays.
                if let Some(r) = &m.registration {
                    self.last_registration = Some(r.clone());
                }
            }
            _ => {}
        }
    }

    /// A frame arrived at `now`; a re-announced frame keeps its first arrival time.
    fn note_frame(&mut self, header: &Header, now: Instant) {
        self.frames += 1;
        self.last_frame_at = Some(now);
        let frame = header.frame();
        if !self.pending_frames.iter().any(|(f, _)| *f == frame) {
            if self.pending_frames.len() >= PENDING_FRAMES {
                self.pending_frames.pop_front();
            }
            self.pending_frames.push_back((frame, now));
        }
    }

    /// Views arrived at `now`: the latency from the frame they were planned on.
    fn note_views(&mut self, views: &RankedViews, now: Instant) {
        self.views_messages += 1;
        if let Some(i) = self
            .pending_frames
            .iter()
            .position(|(frame, _)| *frame == views.based_on())
        {
            let (_, at) = self.pending_frames[i];
            self.pending_frames.drain(..=i);
            if self.latencies_ms.len() >= LATENCY_WINDOW {
                self.latencies_ms.pop_front();
            }
            self.latencies_ms
                .push_back(now.duration_since(at).as_secs_f64() * 1e3);
        }
        self.planner_id = views.planner_id.clone();
        self.last_views = Some(views.clone());
    }
}

impl FleetState {
    /// Folds one received message, received at `now`, into the state; false when it is left out
    /// (an owner's output under an older ownership epoch than the newest seen for its trolley).
    pub fn apply(
        &mut self,
        key: &ParsedKey,
        header: &Header,
        message: &Message,
        now: Instant,
    ) -> bool {
        self.messages += 1;
        if let (ParsedKey::Trolley { tid, .. }, Some(epoch)) = (key, owner_epoch(key, message)) {
            if self.fence.observe(tid, epoch).is_stale() {
                self.stale_epoch += 1;
                return false;
            }
        }
        match (key, message) {
            (ParsedKey::Trolley { tid, topic }, message) => {
                let t = self.trolleys.entry(tid.clone()).or_default();
                t.apply(*topic, header, message, now);
            }
            (ParsedKey::PlannerStatus { pid }, Message::PlannerStatus(s)) => {
                self.planners.insert(pid.clone(), s.clone());
                self.planner_seen_at.insert(pid.clone(), now);
            }
            (ParsedKey::FleetFruits, Message::FleetFruits(f)) => {
                self.fleet_fruits = Some(f.clone());
            }
            (ParsedKey::DetectorStatus { did }, Message::DetectorStatus(s)) => {
                self.detectors.insert(did.clone(), s.clone());
            }
            _ => {}
        }
        true
    }
}

/// Voxel edge of the covered volume the dashboard shows: the planners' default resolution.
pub const COVERED_VOLUME_RESOLUTION_M: f64 = 0.01;

/// Covered ROI volume of the detected boxes over the ground-truth boxes, the experiments' figure
/// ([`glasshouse_geom::covered_volume`], 1 cm voxels); `None` when the truth holds no voxel.
pub fn covered_volume(detected: &[FruitEstimate], truth: &[FruitEstimate]) -> Option<f64> {
    let covered = glasshouse_geom::covered_volume(
        detected.iter().map(FruitEstimate::aabb),
        truth.iter().map(FruitEstimate::aabb),
        COVERED_VOLUME_RESOLUTION_M,
    );
    (!covered.is_nan()).then_some(covered)
}

/// Counters the dashboard exposes, and where it serves.
#[derive(Debug, Default)]
pub struct DashboardCounters {
    pub drops: Arc<DropCounters>,
    /// The bound address of the web page, once it listens.
    pub http_addr: Mutex<Option<SocketAddr>>,
    /// What the MCAP recording wrote, once it is closed.
    pub mcap: Mutex<Option<McapSummary>>,
    /// The Foxglove server's address, once it listens.
    pub foxglove_addr: Mutex<Option<SocketAddr>>,
    /// What the Foxglove server sent, once it is stopped.
    pub foxglove: Mutex<Option<FoxgloveLiveSummary>>,
    /// Messages received (every key).
    pub messages: std::sync::atomic::AtomicU64,
}

impl glasshouse_bus::metrics::ServiceMetrics for DashboardCounters {
    fn kind() -> &'static str {
        "dashboard"
    }

    fn register(
        self: Arc<Self>,
        registry: &mut glasshouse_bus::metrics::prometheus_client::registry::Registry,
    ) {
        let c = |field: fn(&DashboardCounters) -> &std::sync::atomic::AtomicU64| {
            glasshouse_bus::metrics::atomic(&self, field)
        };
        glasshouse_bus::metrics::Readings::default()
            .counter(
                "messages_received",
                "Bus messages received",
                &[],
                c(|k| &k.messages),
            )
            .drops(&self.drops)
            .register(registry);
    }
}

/// Logs the series the dashboard derives itself (latency, covered volume).
fn log_derived(
    recorder: &mut Recorder,
    state: &Mutex<FleetState>,
    key: &ParsedKey,
    message: &Message,
) -> anyhow::Result<()> {
    let ParsedKey::Trolley { tid, topic } = key else {
        return Ok(());
    };
    let (latency, covered) = {
        let Ok(s) = state.lock() else { return Ok(()) };
        let Some(t) = s.trolleys.get(tid) else {
            return Ok(());
        };
        (t.latencies_ms.back().copied(), t.covered_volume)
    };
    match (topic, message) {
        (TrolleyTopic::Views, Message::RankedViews(_)) => {
            if let Some(ms) = latency {
                recorder.log_scalar(&format!("trolleys/{tid}/frame_to_views_ms"), ms)?;
            }
        }
        (TrolleyTopic::Fruits | TrolleyTopic::Truth, Message::FruitEstimates(_)) => {
            if let Some(c) = covered {
                recorder.log_scalar(&format!("trolleys/{tid}/covered_volume"), c)?;
            }
        }
        _ => {}
    }
    Ok(())
}

/// Where every received message goes besides the fleet state: the Rerun recording or stream,
/// the MCAP recording and the Foxglove server, each when configured.
struct Sinks {
    rerun: Option<Recorder>,
    mcap: Option<McapRecorder>,
    foxglove: Option<FoxgloveLive>,
    /// Where the fleet state's stale-epoch count is mirrored.
    drops: Arc<DropCounters>,
}

impl Sinks {
    async fn open(
        settings: &DashboardSettings,
        counters: &DashboardCounters,
    ) -> anyhow::Result<Self> {
        let rerun = if settings.record.is_some() || settings.serve.is_some() {
            Some(Recorder::new(
                settings.record.as_deref(),
                settings.serve.as_ref(),
            )?)
        } else {
            None
        };
        let mcap = match &settings.mcap {
            Some(mcap) => {
                let run = mcap_recorder::run_metadata(glasshouse_bus::wall_clock_ns(), &[]);
                Some(McapRecorder::start(mcap.clone(), run)?)
            }
            None => None,
        };
        let foxglove = match &settings.foxglove {
            Some(live) => {
                let server = FoxgloveLive::start(live).await?;
                if let (Ok(mut addr), Ok(ip)) = (
                    counters.foxglove_addr.lock(),
                    live.listen.parse::<SocketAddr>().map(|a| a.ip()),
                ) {
                    *addr = Some(SocketAddr::new(ip, server.port()));
                }
                Some(server)
            }
            None => None,
        };
        Ok(Self {
            rerun,
            mcap,
            foxglove,
            drops: counters.drops.clone(),
        })
    }

    /// Records `received` (every key to MCAP, the project's keys to Rerun) and applies it to
    /// the fleet state.
    fn take(&mut self, mut received: Received<Message>, state: &Mutex<FleetState>) {
        if let Some(live) = self.foxglove.as_mut() {
            live.offer(
                &received.key,
                &received.payload,
                glasshouse_bus::wall_clock_ns(),
            );
        }
        if let Some(mcap) = &self.mcap {
            let payload = std::mem::take(&mut received.payload);
            mcap.record(&received.key, payload, glasshouse_bus::wall_clock_ns());
        }
        let Some(key) = keys::parse(&received.key) else {
            return;
        };
        let taken = match state.lock() {
            Ok(mut s) => {
                let taken = s.apply(&key, &received.header, &received.message, Instant::now());
                let stale = &self.drops.stale_epoch;
                stale.store(s.stale_epoch, std::sync::atomic::Ordering::Relaxed);
                taken
            }
            Err(_) => true,
        };
        if !taken {
            return;
        }
        if let Some(recorder) = self.rerun.as_mut() {
            if let Err(e) = recorder.log(&key, &received.header, &received.message) {
                tracing::warn!(error = %e, "rerun logging failed");
            }
            if let Err(e) = log_derived(recorder, state, &key, &received.message) {
                tracing::warn!(error = %e, "rerun logging failed");
            }
        }
    }

    /// Flushes the Rerun recording, closes the MCAP files and stops the Foxglove server (their
    /// summaries go to `counters`).
    async fn finish(self, counters: &DashboardCounters) -> anyhow::Result<()> {
        if let Some(live) = self.foxglove {
            let summary = live.finish().await;
            tracing::info!(?summary, "Foxglove server stopped");
            if let Ok(mut c) = counters.foxglove.lock() {
                *c = Some(summary);
            }
        }
        if let Some(recorder) = self.rerun {
            recorder.finish()?;
        }
        if let Some(mcap) = self.mcap {
            let summary = mcap.finish()?;
            tracing::info!(
                files = summary.files.len(),
                messages = summary.messages,
                disk_bytes = summary.disk_bytes,
                dropped = summary.dropped,
                "MCAP recording closed"
            );
            if let Ok(mut c) = counters.mcap.lock() {
                *c = Some(summary);
            }
        }
        Ok(())
    }
}

/// Runs the dashboard until `shutdown` fires; the recordings are flushed before it returns.
pub async fn run(
    session: Session,
    settings: DashboardSettings,
    mut shutdown: Shutdown,
    state: Arc<Mutex<FleetState>>,
    counters: Arc<DashboardCounters>,
) -> anyhow::Result<()> {
    let mut sinks = Sinks::open(&settings, &counters).await?;
    let http = match &settings.http_listen {
        Some(addr) => Some(serve_web(addr, &settings, &shutdown, &state, &counters).await?),
        None => None,
    };
    let (_subscribers, mut rx) = subscribe_all(&session, &counters).await?;
    tracing::info!(record = ?settings.record, mcap = ?settings.mcap.as_ref().map(|m| &m.dir), "dashboard started");
    loop {
        tokio::select! {
            _ = shutdown.wait() => break,
            received = rx.recv() => match received {
                Some(received) => {
                    counters.messages.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    sinks.take(received, &state)
                }
                None => break,
            },
        }
    }
    // Take what already arrived so the recordings end with the latest results.
    while let Ok(received) = rx.try_recv() {
        sinks.take(received, &state);
    }
    sinks.finish(&counters).await?;
    if let Some(http) = http {
        stop_web(http).await;
    }
    let messages = state.lock().map(|s| s.messages).unwrap_or(0);
    tracing::info!(
        messages,
        dropped = counters.drops.total(),
        "dashboard stopped"
    );
    Ok(())
}

type WebTask = tokio::task::JoinHandle<std::io::Result<()>>;

/// Serves the fleet web page on `addr` until `shutdown` fires.
async fn serve_web(
    addr: &str,
    settings: &DashboardSettings,
    shutdown: &Shutdown,
    state: &Arc<Mutex<FleetState>>,
    counters: &Arc<DashboardCounters>,
) -> anyhow::Result<WebTask> {
    let viewer_url = settings.serve.as_ref().map(ServeSettings::web_viewer_url);
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {addr}: {e}"))?;
    let bound = listener.local_addr()?;
    if let Ok(mut a) = counters.http_addr.lock() {
        *a = Some(bound);
    }
    tracing::info!(url = %format!("http://{bound}/"), "fleet web page");
    let app = web::router(web::WebState {
        fleet: state.clone(),
        counters: counters.clone(),
        rerun_viewer_url: viewer_url,
    });
    let mut stop = shutdown.clone();
    Ok(tokio::spawn(async move {
        axum::serve(listener, app)
            .with_graceful_shutdown(async move { stop.wait().await })
            .await
    }))
}

/// Waits (at most 5 s) for the web server to stop.
async fn stop_web(http: WebTask) {
    match tokio::time::timeout(std::time::Duration::from_secs(5), http).await {
        Ok(Ok(Err(e))) => tracing::warn!(error = %e, "web server stopped with an error"),
        Err(_) => tracing::warn!("web server did not stop in time"),
        _ => {}
    }
}

/// Subscribes to every trolley topic and the services' keys; all messages arrive on one queue.
/// The subscribers must be kept for as long as messages are wanted.
async fn subscribe_all(
    session: &Session,
    counters: &DashboardCounters,
) -> anyhow::Result<(
    Vec<Arc<AnySubscriber>>,
    tokio::sync::mpsc::Receiver<Received<Message>>,
)> {
    // Frames and arm states are streams (keep the newest); everything else a deep monitor queue.
    let mut key_exprs: Vec<(String, Delivery)> = TrolleyTopic::ALL
        .into_iter()
        .map(|topic| {
            let delivery = match topic.qos() {
                Qos::Stream => Delivery::Stream,
                Qos::Reliable | Qos::Recovered => Delivery::Monitor,
            };
            (keys::all_trolleys(topic), delivery)
        })
        .collect();
    let services = [
        keys::all_planner_status().to_string(),
        keys::all_detector_status().to_string(),
        keys::fleet_fruits().to_string(),
    ];
    key_exprs.extend(services.map(|key| (key, Delivery::Monitor)));
    let (tx, rx) = tokio::sync::mpsc::channel::<Received<Message>>(64);
    let mut subscribers = Vec::new();
    for (key_expr, delivery) in key_exprs {
        let sub = Arc::new(
            AnySubscriber::declare(session, &key_expr, delivery, counters.drops.clone()).await?,
        );
        subscribers.push(sub.clone());
        let tx = tx.clone();
        tokio::spawn(async move {
            while let Some(received) = sub.recv().await {
                if tx.send(received).await.is_err() {
                    break;
                }
            }
        });
    }
    Ok((subscribers, rx))
}
