//! The trolley process: streams RGB-D frames and arm state, executes ranked views.
//!
//! The loop itself is [`glasshouse_pipeline::EdgeNode`] (capture, announce, wait for views on
//! the latest frame or announce it again, execute the first reachable view, move along the row);
//! this crate is its driver: it performs the node's actions on the bus and on a
//! [`TrolleySource`] (the simulated glasshouse by default, a recording with `replay_dir`), and
//! feeds back what happened. The clock is simulated: each view costs its motion time plus a
//! capture time.

pub mod ros2;
pub mod source;
mod world_args;
pub use world_args::WorldArgs;

use std::collections::{BTreeSet, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use glasshouse_bus::{
    declare_alive, wall_clock_ns, DropCounters, MemberEvent, MemberWatch, Publisher, Received,
    Shutdown, Subscriber,
};
use glasshouse_pipeline::{
    EdgeAction, EdgeInput, EdgeNode, EdgeSettings, RealtimePacer, TrolleySource,
};
use glasshouse_proto::keys::{self, MemberKind};
use glasshouse_proto::{
    ArmState, FruitEstimates, Header, ImageEncoding, RgbdFrame, TrolleyInfo, TrolleyStatus,
};
use glasshouse_sim::{ScenarioKind, WorldSettings};
use glasshouse_simtrolley::{SimTrolley, SimTrolleySettings};
use serde::Deserialize;
use source::{FrameRecorder, ReplaySource};
use tokio::time::Instant;
use zenoh::Session;

pub use glasshouse_pipeline::EdgeEvent;

/// Where the edge's frames come from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum SourceKind {
    /// The simulated glasshouse (`scenario`, `seed`, `world`).
    #[default]
    Sim,
    /// Frames recorded by an edge with `record_frames_dir` (`replay_dir`).
    Replay,
    /// A rosbag2 recording (MCAP storage, `bag`) with a camera's colour, aligned depth, camera
    /// info and TF (`ros.topics`), played as a trolley.
    Bag,
    /// A live ROS 2 camera, TF and arm driver over Zenoh, as rmw_zenoh speaks it (`ros`).
    Ros2,
}

/// A ROS 2 or bag source: the camera's topics and frames, and what ROS messages do not carry.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RosSettings {
    pub topics: glasshouse_ros::RosTopics,
    pub trolley: glasshouse_ros::RosTrolley,
    /// The live source's domain, node name, timeouts.
    pub live: ros2::Ros2Settings,
}

/// Edge settings; every field has a default, a JSON5 file may set any of them.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EdgeConfig {
    pub trolley_id: String,
    /// Where frames come from: `sim` (default), `replay` or `bag`.
    pub source: SourceKind,
    /// The rosbag2 bag (its folder or one `.mcap` file) of the `bag` source.
    pub bag: Option<PathBuf>,
    /// Topics, frames and the trolley of the `bag` source.
    pub ros: RosSettings,
    /// Scenario: `1`, `2` or `row`.
    pub scenario: ScenarioKind,
    pub seed: u64,
    pub width: u32,
    pub height: u32,
    /// Stop after this many executed views (0 = run until shut down).
    pub max_views: u32,
    /// Re-announce the current frame when no views arrive within this time.
    pub views_timeout_ms: u64,
    /// Simulated time to capture one view (the arm's motion time comes from its joint and
    /// mount speed limits).
    pub capture_time_s: f64,
    /// Length along the row of the part the trolley works on at a time (row scenario).
    pub segment_length_m: f64,
    /// The trolley moves on to the next segment when the best view it is sent has a utility no
    /// higher than this (the planner's switching threshold): nothing worth a look is left here.
    pub segment_done_utility: f64,
    /// Play back frames recorded with `record_frames_dir` instead of simulating.
    pub replay_dir: Option<PathBuf>,
    /// Record every captured frame (and the trolley info) to this folder.
    pub record_frames_dir: Option<PathBuf>,
    /// Wall-clock time at least between two captures (0: capture as soon as the last view is
    /// done). A real camera streams at a fixed rate; 200 ms paces a trolley at 5 frames/s.
    pub frame_interval_ms: u64,
    /// The simulated world: camera noise and light, fruit shape and colour, red clutter, pose
    /// errors (`{ perception: {..}, scene: {..}, pose: {..} }`; clean by default).
    pub world: WorldSettings,
    /// Send frames compressed (lossless left delta + zstd per plane, ~10x smaller); false sends
    /// the raw planes, for readers that predate `ImageEncoding`.
    pub compress_frames: bool,
    /// Take as long in wall-clock time as the simulated arm: wait out each view's motion and
    /// capture time before capturing the next frame (false: capture as soon as the view is
    /// executed; the simulated clock alone counts the time).
    pub realtime: bool,
    /// Which visit of its row this run is (0: the first; count up by one per pass of the row,
    /// days apart). Announced in TrolleyInfo: a planner that sees a later visit than its copy's
    /// closes the one before (its fruits go into their histories) and starts this one from the
    /// previous visit's map as a prior.
    pub visit: u32,
}

impl Default for EdgeConfig {
    fn default() -> Self {
        Self {
            trolley_id: "t1".into(),
            source: SourceKind::Sim,
            bag: None,
            ros: RosSettings::default(),
            scenario: ScenarioKind::One,
            seed: 1,
            width: 640,
            height: 480,
            max_views: 0,
            views_timeout_ms: 3000,
            capture_time_s: glasshouse_arm::CAPTURE_TIME_S,
            segment_length_m: 1.0,
            segment_done_utility: glasshouse_nbv::PlannerConfig::default().utility_threshold,
            replay_dir: None,
            record_frames_dir: None,
            frame_interval_ms: 0,
            world: WorldSettings::default(),
            compress_frames: true,
            realtime: false,
            visit: 0,
        }
    }
}

impl EdgeConfig {
    pub fn validate(&self) -> anyhow::Result<()> {
        keys::validate_id(&self.trolley_id)?;
        self.sim().validate()?;
        if self.source == SourceKind::Ros2 {
            self.ros.topics.validate().map_err(anyhow::Error::msg)?;
        }
        if self.source == SourceKind::Bag {
            anyhow::ensure!(
                self.bag.is_some(),
                "the bag source needs a bag (`--source bag FILE`)"
            );
            self.ros.topics.validate().map_err(anyhow::Error::msg)?;
        }
        if self.source == SourceKind::Replay {
            anyhow::ensure!(
                self.replay_dir.is_some(),
                "the replay source needs a folder (`--source replay DIR`)"
            );
        }
        anyhow::ensure!(
            self.capture_time_s.is_finite() && self.capture_time_s >= 0.0,
            "capture time must be finite and >= 0"
        );
        anyhow::ensure!(
            self.segment_length_m.is_finite() && self.segment_length_m > 0.0,
            "segment length must be finite and > 0"
        );
        Ok(())
    }

    /// The loop's settings.
    pub fn loop_settings(&self) -> EdgeSettings {
        EdgeSettings {
            trolley_id: self.trolley_id.clone(),
            max_views: self.max_views,
            // A bag's motion times are the recorded gaps between frames, capture included.
            capture_time_s: match self.source {
                SourceKind::Bag => 0.0,
                _ => self.capture_time_s,
            },
            segment_done_utility: self.segment_done_utility,
        }
    }

    /// The simulated trolley these settings describe.
    pub fn sim(&self) -> SimTrolleySettings {
        let size = (self.width, self.height);
        SimTrolleySettings {
            world: self.world,
            ..SimTrolleySettings::new(self.scenario, self.seed, size, self.segment_length_m)
        }
    }

    /// How the edge sends each frame's planes.
    pub fn frame_encoding(&self) -> ImageEncoding {
        if self.compress_frames {
            ImageEncoding::LeftDeltaZstd
        } else {
            ImageEncoding::Raw
        }
    }

    fn open_source(
        &self,
        session: &Session,
        drops: &Arc<DropCounters>,
    ) -> anyhow::Result<Box<dyn TrolleySource>> {
        let source = match (self.source, &self.replay_dir) {
            // An older settings file names only the folder.
            (SourceKind::Sim, Some(_)) => SourceKind::Replay,
            (kind, _) => kind,
        };
        Ok(match source {
            SourceKind::Sim => Box::new(SimTrolley::new(self.sim())?),
            SourceKind::Replay => {
                let dir = self.replay_dir.as_deref().context("no replay folder")?;
                Box::new(ReplaySource::open(dir)?)
            }
            SourceKind::Bag => {
                let bag = self.bag.as_deref().context("no bag")?;
                let (topics, trolley) = (self.ros.topics.clone(), self.ros.trolley.clone());
                let source = glasshouse_ros::BagSource::open(bag, topics, trolley)
                    .with_context(|| format!("cannot play {}", bag.display()))?;
                Box::new(source)
            }
            SourceKind::Ros2 => {
                let ros = &self.ros;
                let source = ros2::Ros2Source::open(
                    session,
                    ros.live.clone(),
                    ros.topics.clone(),
                    ros.trolley.clone(),
                    drops.clone(),
                )?;
                Box::new(source)
            }
        })
    }
}

/// Counters the edge exposes to tests and status messages.
#[derive(Debug, Default)]
pub struct EdgeCounters {
    pub drops: Arc<DropCounters>,
    /// RankedViews refused because they did not come from the planner owning the trolley.
    pub refused_views: std::sync::atomic::AtomicU64,
    /// The loop's status after its last step (frames, views, unreachable views, re-announces).
    pub status: std::sync::Mutex<Option<TrolleyStatus>>,
}

impl EdgeCounters {
    /// The loop's refusals so far: views not from the owner, and views of an older epoch (a
    /// drop of reason `stale_epoch`).
    fn note_refusals(&self, status: &TrolleyStatus) {
        self.refused_views
            .store(status.refused_views, Ordering::Relaxed);
        self.drops
            .stale_epoch
            .store(status.stale_views, Ordering::Relaxed);
    }
}

impl glasshouse_bus::metrics::ServiceMetrics for EdgeCounters {
    fn kind() -> &'static str {
        "edge"
    }

    fn register(
        self: Arc<Self>,
        registry: &mut glasshouse_bus::metrics::prometheus_client::registry::Registry,
    ) {
        use glasshouse_bus::metrics::{atomic, last};
        let c = |field: fn(&EdgeCounters) -> &std::sync::atomic::AtomicU64| atomic(&self, field);
        let s = |read: fn(&TrolleyStatus) -> f64| last(&self, |k| &k.status, read);
        glasshouse_bus::metrics::Readings::default()
            .counter(
                "frames_published",
                "RGB-D frames published",
                &[],
                s(|st| st.frames_published as f64),
            )
            .counter(
                "views_executed",
                "Views the arm moved to",
                &[],
                s(|st| f64::from(st.views_done)),
            )
            .counter(
                "unreachable_views",
                "View sets none of whose views the arm reached",
                &[],
                s(|st| f64::from(st.unreachable_views)),
            )
            .counter(
                "reannounces",
                "Frames announced again after no views came in time",
                &[],
                s(|st| f64::from(st.reannounces)),
            )
            .counter(
                "refused_views",
                "View sets refused: not from the trolley's owner",
                &[],
                c(|k| &k.refused_views),
            )
            .drops(&self.drops)
            .register(registry);
    }
}

/// The edge's publishers.
struct Outputs {
    rgbd: Publisher<RgbdFrame>,
    arm: Publisher<ArmState>,
    info: Publisher<TrolleyInfo>,
    status: Publisher<TrolleyStatus>,
    truth: Publisher<FruitEstimates>,
}

impl Outputs {
    async fn declare(
        session: &Session,
        tid: &str,
        drops: &Arc<DropCounters>,
    ) -> anyhow::Result<Self> {
        Ok(Self {
            rgbd: Publisher::declare(session, &keys::rgbd(tid)?, drops.clone()).await?,
            arm: Publisher::declare(session, &keys::arm(tid)?, drops.clone()).await?,
            info: Publisher::declare(session, &keys::info(tid)?, drops.clone()).await?,
            status: Publisher::declare(session, &keys::status(tid)?, drops.clone()).await?,
            truth: Publisher::declare(session, &keys::truth(tid)?, drops.clone()).await?,
        })
    }

    async fn close(self) {
        self.rgbd.close().await;
        self.arm.close().await;
        self.info.close().await;
        self.status.close().await;
        self.truth.close().await;
    }
}

/// The messages that announce the latest frame (published again on a re-announce).
struct Announcement {
    info: TrolleyInfo,
    arm: ArmState,
    frame: RgbdFrame,
    /// Written to the recording (once, at its first announcement, with its capture time).
    recorded: bool,
}

/// Performs the node's actions on the bus and the source.
struct Driver {
    config: EdgeConfig,
    /// This process's boot epoch: every header carries it.
    epoch_ns: u64,
    /// Sources whose refused views were logged (once each).
    logged_refusals: BTreeSet<String>,
    source: Option<Box<dyn TrolleySource>>,
    out: Outputs,
    drops: Arc<DropCounters>,
    recorder: Option<FrameRecorder>,
    truth: Option<FruitEstimates>,
    announcement: Option<Announcement>,
    views_deadline: Option<Instant>,
    next_capture: Instant,
    views_done: u32,
    events: Option<tokio::sync::mpsc::UnboundedSender<EdgeEvent>>,
    /// With `realtime`: the pacer and the origin of its wall clock.
    pacer: Option<(RealtimePacer, Instant)>,
    /// Cuts a pacing wait short.
    shutdown: Shutdown,
}

impl Driver {
    fn header(&self, seq: u64, sim_time_s: f64) -> Header {
        let tid = &self.config.trolley_id;
        Header {
            seq,
            epoch_ns: self.epoch_ns,
            stamp_ns: (sim_time_s * 1e9) as u64,
            trolley_id: tid.clone(),
            source_id: tid.clone(),
            frame_id: "world".into(),
        }
    }

    /// Runs `f` on the source on a blocking thread (rendering and IK are heavy).
    async fn on_source<T: Send + 'static>(
        &mut self,
        f: impl FnOnce(&mut dyn TrolleySource) -> T + Send + 'static,
    ) -> anyhow::Result<T> {
        let mut source = self.source.take().context("the source is busy")?;
        let (source, value) = tokio::task::spawn_blocking(move || {
            let value = f(source.as_mut());
            (source, value)
        })
        .await
        .context("source task failed")?;
        self.source = Some(source);
        Ok(value)
    }

    async fn capture(&mut self, frame_seq: u64) -> anyhow::Result<EdgeInput> {
        if self.config.frame_interval_ms > 0 {
            tokio::time::sleep_until(self.next_capture).await;
            self.next_capture =
                Instant::now() + Duration::from_millis(self.config.frame_interval_ms);
        }
        let views_done = self.views_done;
        let captured = self
            .on_source(move |s| {
                let frame = s.capture(frame_seq)?;
                Ok::<_, String>(frame.map(|f| (f, s.info(), s.arm_state(false, views_done))))
            })
            .await?
            .map_err(|e| anyhow::anyhow!("capture failed: {e}"))?;
        let Some((frame, info, arm)) = captured else {
            tracing::info!(trolley = %self.config.trolley_id, "the source has no more frames");
            return Ok(EdgeInput::Captured { frame: false });
        };
        self.announcement = Some(Announcement {
            info,
            arm,
            frame: frame.encoded_as(self.config.frame_encoding()),
            recorded: false,
        });
        Ok(EdgeInput::Captured { frame: true })
    }

    /// Publishes the announcement; its info carries the newest ownership epoch views were
    /// taken under, and whose views they were.
    async fn announce(
        &mut self,
        header: &Header,
        owner_epoch: u64,
        owner_id: String,
    ) -> anyhow::Result<()> {
        let Some(a) = &mut self.announcement else {
            return Ok(());
        };
        a.info.owner_epoch = owner_epoch;
        a.info.owner_id = owner_id;
        a.info.visit = self.config.visit;
        if let (Some(recorder), false) = (&self.recorder, a.recorded) {
            recorder.write(header, &a.info)?;
            recorder.write(header, &a.frame)?;
            a.recorded = true;
        }
        self.out.info.publish(header, &a.info).await?;
        if let Some(truth) = &self.truth {
            self.out.truth.publish(header, truth).await?;
        }
        self.out.arm.publish(header, &a.arm).await?;
        self.out.rgbd.publish(header, &a.frame).await?;
        Ok(())
    }

    fn report(&mut self, event: EdgeEvent) {
        let tid = &self.config.trolley_id;
        match &event {
            EdgeEvent::ViewDone { views_done, .. } => self.views_done = *views_done,
            EdgeEvent::NoReachableView { frame_seq, offered } => {
                tracing::info!(trolley = %tid, frame_seq, offered, "no reachable view; capturing again")
            }
            EdgeEvent::Reannounced { frame_seq } => {
                tracing::info!(trolley = %tid, frame_seq, "no views yet; re-announcing the frame")
            }
            EdgeEvent::SegmentDone { segments_done, .. } => {
                tracing::info!(trolley = %tid, segment = segments_done, "segment done; moving along the row")
            }
            EdgeEvent::ViewsRefused {
                source_id,
                owner,
                refused,
            } if self.logged_refusals.insert(source_id.clone()) => {
                tracing::warn!(trolley = %tid, source = %source_id, owner = owner.as_deref().unwrap_or("none"), refused,
                    "views refused: not from the trolley's owner (logged once per source)");
            }
            EdgeEvent::MisattributedViewsRefused {
                sender,
                claimed,
                refused,
            } if self.logged_refusals.insert(format!("key {sender}")) => {
                tracing::warn!(trolley = %tid, %sender, %claimed, refused,
                    "views refused: their header names another planner than their key (logged once per sender)");
            }
            EdgeEvent::StaleViewsRefused {
                source_id,
                owner_epoch,
                newest,
                stale,
            } if self
                .logged_refusals
                .insert(format!("{source_id} epoch {owner_epoch}")) =>
            {
                tracing::warn!(trolley = %tid, source = %source_id, owner_epoch, newest, stale,
                    "views refused: an older ownership epoch than the newest taken, from a replaced owner (logged once per source and epoch)");
            }
            _ => {}
        }
        if let Some(tx) = &self.events {
            let _ = tx.send(event);
        }
    }

    /// Performs one action; the event it produced, if any.
    async fn perform(&mut self, action: EdgeAction) -> anyhow::Result<Option<EdgeInput>> {
        Ok(match action {
            EdgeAction::Capture { frame_seq } => Some(self.capture(frame_seq).await?),
            EdgeAction::Announce {
                frame_seq,
                sim_time_s,
                owner_epoch,
                owner_id,
            } => {
                let header = self.header(frame_seq, sim_time_s);
                self.announce(&header, owner_epoch, owner_id).await?;
                None
            }
            EdgeAction::AwaitViews => {
                let timeout = Duration::from_millis(self.config.views_timeout_ms);
                self.views_deadline = Some(Instant::now() + timeout);
                None
            }
            EdgeAction::PublishStatus {
                frame_seq,
                sim_time_s,
                mut status,
            } => {
                status.dropped_messages = self.drops.total();
                let header = self.header(frame_seq, sim_time_s);
                self.out.status.publish(&header, &status).await?;
                None
            }
            EdgeAction::Execute { goals } => Some(EdgeInput::Executed(
                self.on_source(move |s| s.execute(&goals)).await?,
            )),
            EdgeAction::PublishArmMoving {
                frame_seq,
                sim_time_s,
                views_done,
            } => {
                let arm = self
                    .on_source(move |s| s.arm_state(true, views_done))
                    .await?;
                let header = self.header(frame_seq, sim_time_s);
                self.out.arm.publish(&header, &arm).await?;
                None
            }
            EdgeAction::MoveToNextSegment => Some(EdgeInput::SegmentMoved(
                self.on_source(|s| s.next_segment()).await?,
            )),
            EdgeAction::Report(event) => {
                self.report(event);
                None
            }
            EdgeAction::Stop => None,
        })
    }

    /// With `realtime`, waits out the simulated time the pacer says is due before `action`.
    async fn pace(&mut self, action: &EdgeAction, sim_time_s: f64) {
        let Some((pacer, origin)) = &mut self.pacer else {
            return;
        };
        let wait = pacer.wait_before(action, sim_time_s, origin.elapsed());
        if !wait.is_zero() {
            tokio::select! {
                _ = tokio::time::sleep(wait) => {}
                _ = self.shutdown.wait() => {}
            }
        }
    }

    /// Performs actions (and those their outcomes cause) until none is left.
    async fn drain(&mut self, node: &mut EdgeNode, actions: Vec<EdgeAction>) -> anyhow::Result<()> {
        let mut queue: VecDeque<EdgeAction> = actions.into();
        while let Some(action) = queue.pop_front() {
            self.pace(&action, node.sim_time_s()).await;
            if let Some(input) = self.perform(action).await? {
                queue.extend(node.handle(input));
            }
        }
        Ok(())
    }
}

impl Driver {
    /// The driver of a trolley with `config` and its opened `source`, publishing on `out`.
    fn new(
        config: EdgeConfig,
        source: Box<dyn TrolleySource>,
        out: Outputs,
        drops: Arc<DropCounters>,
        events: Option<tokio::sync::mpsc::UnboundedSender<EdgeEvent>>,
        shutdown: Shutdown,
    ) -> anyhow::Result<Self> {
        let tid = &config.trolley_id;
        let truth = source.ground_truth().map(|fruits| FruitEstimates {
            fruits,
            based_on_seq: 0,
            planner_id: format!("truth-{tid}"),
            // The truth has no owner.
            owner_epoch: 0,
            visit: config.visit,
            history: Vec::new(),
        });
        let recorder = config
            .record_frames_dir
            .as_deref()
            .map(FrameRecorder::create)
            .transpose()?;
        Ok(Self {
            epoch_ns: wall_clock_ns(),
            logged_refusals: BTreeSet::new(),
            recorder,
            source: Some(source),
            out,
            drops,
            truth,
            announcement: None,
            views_deadline: None,
            next_capture: Instant::now(),
            views_done: 0,
            events,
            pacer: config
                .realtime
                .then(|| (RealtimePacer::default(), Instant::now())),
            shutdown,
            config,
        })
    }
}

/// Runs the trolley until its view budget is spent, its source ends or `shutdown` fires.
pub async fn run(
    session: Session,
    config: EdgeConfig,
    mut shutdown: Shutdown,
    events: Option<tokio::sync::mpsc::UnboundedSender<EdgeEvent>>,
    counters: Arc<EdgeCounters>,
) -> anyhow::Result<()> {
    config.validate()?;
    let tid = config.trolley_id.clone();
    let drops = counters.drops.clone();
    let out = Outputs::declare(&session, &tid, &drops).await?;
    let views = Subscriber::declare(&session, &keys::views_from_any(&tid)?, drops.clone()).await?;
    let mut planners = MemberWatch::declare(&session, MemberKind::Planner).await?;
    let _alive = declare_alive(&session, MemberKind::Trolley, &tid).await?;
    let source = config.open_source(&session, &drops)?;
    let mut driver = Driver::new(config, source, out, drops.clone(), events, shutdown.clone())?;
    tracing::info!(trolley = %tid, scenario = %driver.config.scenario, seed = driver.config.seed, "edge started");
    let mut node = EdgeNode::new(driver.config.loop_settings(), driver.epoch_ns);
    let start = node.handle(EdgeInput::Start);
    driver.drain(&mut node, start).await?;
    while !node.is_done() {
        let deadline = driver.views_deadline.unwrap_or_else(Instant::now);
        let input = tokio::select! {
            _ = shutdown.wait() => break,
            received = views.recv() => match received {
                Some(Received { key, header, message, .. }) => EdgeInput::Views {
                    sender: keys::sender(&key).unwrap_or_default().to_owned(),
                    header,
                    views: message,
                },
                None => break,
            },
            member = planners.recv() => match member {
                Some(MemberEvent::Joined(id)) => EdgeInput::PlannerJoined(id),
                Some(MemberEvent::Left(id)) => EdgeInput::PlannerLeft(id),
                None => break,
            },
            _ = tokio::time::sleep_until(deadline), if node.is_waiting_for_views() => EdgeInput::ViewsTimedOut,
        };
        let actions = node.handle(input);
        counters.note_refusals(node.status());
        driver.drain(&mut node, actions).await?;
        if let Ok(mut status) = counters.status.lock() {
            *status = Some(node.status().clone());
        }
    }
    let last = node.finish();
    driver.drain(&mut node, last).await?;
    driver.out.close().await;
    let status = node.status();
    tracing::info!(trolley = %tid, views = status.views_done, frames = status.frames_published,
        dropped = drops.total(), corrupt = drops.corrupt.load(Ordering::Relaxed), "edge stopped");
    Ok(())
}
