//! The detector process: RGB-D frames in, ROI point clouds out.
//!
//! Stateless: it runs the detection of [`glasshouse_detect`] (the paper's HSI rule after 1 cm
//! down-sampling, back-projected with the frame's intrinsics and pose) on trolley frames and
//! publishes a RoiCloud on the trolley's `roi` key under its own id (`gh/trolley/{tid}/roi/{did}`:
//! in a secured deployment the router lets no other identity put there). Frames are a stream, so
//! a busy detector skips stale frames.
//!
//! Any number of detectors share the fleet by splitting the trolleys (see
//! [`glasshouse_pipeline::DetectorNode`], the state machine this process drives): each detector
//! subscribes only to the frames of the trolleys it ranks first for, so every frame is processed
//! once and frames of other detectors' trolleys never reach it. This file is the driver: it turns
//! liveliness events, frames and the status clock into the node's inputs and performs its actions
//! on the bus (subscriptions, publishers) and on a blocking thread (the detection).

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use glasshouse_bus::{
    declare_alive, wall_clock_ns, DropCounters, MemberEvent, MemberWatch, Publisher, Received,
    Shutdown, Subscriber,
};
use std::path::{Path, PathBuf};

use glasshouse_detect::{DetectorConfig, FruitDetector, HsiVotes};
use glasshouse_fleet::MembershipEvent;
use glasshouse_pipeline::{
    detect_frame_with, DetectorAction, DetectorCounts, DetectorInput, DetectorNode, DetectorReport,
};
use glasshouse_proto::keys::{self, MemberKind};
use glasshouse_proto::{DetectorStatus, Header, RgbdFrame, RoiCloud};
use glasshouse_segment::OnnxFruitModel;
use serde::Deserialize;
use zenoh::Session;

/// Detector settings; a JSON5 file may set any of them.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DetectorSettings {
    pub detector_id: String,
    /// Down-sampling voxel size in metres (the map resolution).
    pub voxel_size_m: f64,
    pub status_period_ms: u64,
    /// ONNX fruit segmentation model (detector-service/model/fruit-segmenter.onnx); unset =
    /// the paper's HSI colour rule.
    pub fruit_model: Option<PathBuf>,
}

impl Default for DetectorSettings {
    fn default() -> Self {
        Self {
            detector_id: "d1".into(),
            voxel_size_m: 0.01,
            status_period_ms: 1000,
            fruit_model: None,
        }
    }
}

impl DetectorSettings {
    pub fn validate(&self) -> anyhow::Result<()> {
        keys::validate_id(&self.detector_id)?;
        anyhow::ensure!(
            self.voxel_size_m.is_finite() && self.voxel_size_m >= 0.001,
            "voxel size {} m is below 1 mm",
            self.voxel_size_m
        );
        Ok(())
    }
}

/// The fruit detector of `model`: the ONNX model in that file (loaded and checked now), else
/// the HSI rule.
pub fn load_fruit_detector(model: Option<&Path>) -> anyhow::Result<Arc<dyn FruitDetector>> {
    let Some(path) = model else {
        return Ok(Arc::new(HsiVotes::default()));
    };
    let bytes = std::fs::read(path)
        .with_context(|| format!("cannot read the fruit model {}", path.display()))?;
    let model = OnnxFruitModel::from_bytes(&bytes)
        .with_context(|| format!("fruit model {}", path.display()))?;
    Ok(Arc::new(model))
}

/// Counters a detector exposes to tests and its status message.
#[derive(Debug, Default)]
pub struct DetectorCounters {
    pub drops: Arc<DropCounters>,
    pub frames_processed: std::sync::atomic::AtomicU64,
    /// Frames that decoded but could not be processed (inconsistent content).
    pub frames_rejected: std::sync::atomic::AtomicU64,
    /// Trolleys whose frames this detector takes now.
    pub trolleys_served: std::sync::atomic::AtomicU64,
}

impl glasshouse_bus::metrics::ServiceMetrics for DetectorCounters {
    fn kind() -> &'static str {
        "detector"
    }

    fn register(
        self: Arc<Self>,
        registry: &mut glasshouse_bus::metrics::prometheus_client::registry::Registry,
    ) {
        let c = |field: fn(&DetectorCounters) -> &std::sync::atomic::AtomicU64| {
            glasshouse_bus::metrics::atomic(&self, field)
        };
        glasshouse_bus::metrics::Readings::default()
            .counter(
                "frames_processed",
                "RGB-D frames turned into ROI clouds",
                &[],
                c(|k| &k.frames_processed),
            )
            .counter(
                "frames_rejected",
                "Frames that decoded but could not be processed",
                &[],
                c(|k| &k.frames_rejected),
            )
            .gauge(
                "trolleys_served",
                "Trolleys whose frames this detector takes now",
                &[],
                c(|k| &k.trolleys_served),
            )
            .drops(&self.drops)
            .register(registry);
    }
}

/// Frames waiting for detection, over all served trolleys.
const FRAME_QUEUE: usize = 4;

impl DetectorCounters {
    /// Shows the node's counts to the metrics.
    fn mirror(&self, counts: DetectorCounts) {
        self.frames_processed
            .store(counts.frames_processed, Ordering::Relaxed);
        self.frames_rejected
            .store(counts.frames_rejected, Ordering::Relaxed);
        self.trolleys_served
            .store(counts.trolleys_served, Ordering::Relaxed);
    }
}

/// The bus side the detector listens to: who is alive, the status clock and the served frames.
struct Inputs {
    detector_watch: MemberWatch,
    trolley_watch: MemberWatch,
    status_tick: tokio::time::Interval,
    frames: tokio::sync::mpsc::Receiver<Received<RgbdFrame>>,
    drops: Arc<DropCounters>,
}

impl Inputs {
    /// The next input for the node; `None` once `shutdown` fires or a membership watch ends.
    async fn next(&mut self, shutdown: &mut Shutdown) -> Option<DetectorInput> {
        loop {
            let input = tokio::select! {
                _ = shutdown.wait() => return None,
                event = self.detector_watch.recv() => DetectorInput::Member(match event? {
                    MemberEvent::Joined(id) => MembershipEvent::ServerJoined(id),
                    MemberEvent::Left(id) => MembershipEvent::ServerLeft(id),
                }),
                event = self.trolley_watch.recv() => DetectorInput::Member(match event? {
                    MemberEvent::Joined(id) => MembershipEvent::TrolleyJoined(id),
                    MemberEvent::Left(id) => MembershipEvent::TrolleyLeft(id),
                }),
                _ = self.status_tick.tick() => DetectorInput::StatusTick {
                    dropped_messages: self.drops.total(),
                },
                received = self.frames.recv() => match received {
                    Some(r) => {
                        // Where a frame's time goes before its cloud (RUST_LOG=glasshouse_detector=debug).
                        tracing::debug!(trolley = %r.header.trolley_id, seq = r.header.seq,
                            waited_ms = r.arrived_at.elapsed().as_secs_f64() * 1e3, "frame taken");
                        DetectorInput::Frame { header: r.header, frame: Box::new(r.message) }
                    }
                    None => continue,
                },
            };
            return Some(input);
        }
    }
}

/// What performs the node's actions: the session, the served trolleys' frame forwarders, the
/// publishers and the fruit detector.
struct Driver {
    did: String,
    session: Session,
    config: Arc<DetectorConfig>,
    fruit_detector: Arc<dyn FruitDetector>,
    drops: Arc<DropCounters>,
    /// Where the forwarders put the served trolleys' frames.
    frame_tx: tokio::sync::mpsc::Sender<Received<RgbdFrame>>,
    /// One subscriber (and forwarding task) per served trolley.
    frame_tasks: HashMap<String, tokio::task::JoinHandle<()>>,
    status_pub: Publisher<DetectorStatus>,
    clouds: HashMap<String, Publisher<RoiCloud>>,
}

impl Driver {
    /// Performs one action; returns what it brings back to the node (a detection's outcome).
    async fn perform(&mut self, action: DetectorAction) -> anyhow::Result<Option<DetectorInput>> {
        match action {
            DetectorAction::Serve(tid) => self.serve(tid).await?,
            DetectorAction::Unserve(tid) => {
                if let Some(task) = self.frame_tasks.remove(&tid) {
                    task.abort();
                }
                tracing::info!(detector = %self.did, trolley = %tid, "trolley handed to another detector");
            }
            DetectorAction::Detect { header, frame } => {
                return Ok(Some(self.detect(header, frame).await?));
            }
            DetectorAction::PublishCloud { header, cloud } => {
                tracing::debug!(
                    seq = header.seq,
                    points = cloud.points_in_world.len(),
                    "cloud published"
                );
                self.cloud_publisher(&header.trolley_id)
                    .await?
                    .publish(&header, &cloud)
                    .await?;
            }
            DetectorAction::PublishStatus { header, status } => {
                self.status_pub.publish(&header, &status).await?;
            }
            DetectorAction::Report(DetectorReport::FrameRejected {
                trolley_id,
                seq,
                reason,
            }) => {
                tracing::warn!(trolley = %trolley_id, seq, error = %reason, "frame rejected");
            }
        }
        Ok(None)
    }

    /// Subscribes to `tid`'s frames and forwards them to the detection queue.
    async fn serve(&mut self, tid: String) -> anyhow::Result<()> {
        let drops = self.drops.clone();
        let frames = Subscriber::declare(&self.session, &keys::rgbd(&tid)?, drops.clone()).await?;
        let tx = self.frame_tx.clone();
        let task = tokio::spawn(async move {
            while let Some(received) = frames.recv().await {
                // A full queue means this detector is behind: the frame is stale anyway.
                if tx.try_send(received).is_err() {
                    drops.overflow.fetch_add(1, Ordering::Relaxed);
                }
            }
        });
        tracing::info!(detector = %self.did, trolley = %tid, "serving trolley");
        if let Some(old) = self.frame_tasks.insert(tid, task) {
            old.abort();
        }
        Ok(())
    }

    /// Runs the detection on a blocking thread; the outcome as the node's input.
    async fn detect(&self, header: Header, frame: Box<RgbdFrame>) -> anyhow::Result<DetectorInput> {
        let started = Instant::now();
        let cfg = self.config.clone();
        let fruit_detector = self.fruit_detector.clone();
        let detector_id = self.did.clone();
        let frame_id = header.frame();
        let result = tokio::task::spawn_blocking(move || {
            detect_frame_with(
                &frame,
                frame_id,
                &detector_id,
                &cfg,
                fruit_detector.as_ref(),
            )
        })
        .await
        .context("detection task failed")?;
        tracing::debug!(
            seq = header.seq,
            detect_ms = started.elapsed().as_secs_f64() * 1e3,
            "frame detected"
        );
        Ok(DetectorInput::Detected {
            header,
            result: result.map(Box::new).map_err(|e| e.to_string()),
            detect_ms: started.elapsed().as_secs_f64() * 1e3,
        })
    }

    /// The publisher of `tid`'s clouds under this detector's id, declared on first use.
    async fn cloud_publisher(&mut self, tid: &str) -> anyhow::Result<&Publisher<RoiCloud>> {
        if !self.clouds.contains_key(tid) {
            let key = keys::roi(tid, &self.did)?;
            let publisher = Publisher::declare(&self.session, &key, self.drops.clone()).await?;
            self.clouds.insert(tid.to_owned(), publisher);
        }
        Ok(&self.clouds[tid])
    }

    async fn close(mut self) {
        for (_, task) in self.frame_tasks.drain() {
            task.abort();
        }
        for (_, p) in self.clouds.drain() {
            p.close().await;
        }
        self.status_pub.close().await;
    }
}

/// Runs the detector until `shutdown` fires.
pub async fn run(
    session: Session,
    settings: DetectorSettings,
    mut shutdown: Shutdown,
    counters: Arc<DetectorCounters>,
) -> anyhow::Result<()> {
    settings.validate()?;
    let fruit_detector = load_fruit_detector(settings.fruit_model.as_deref())?;
    let did = settings.detector_id.clone();
    let (frame_tx, frame_rx) = tokio::sync::mpsc::channel::<Received<RgbdFrame>>(FRAME_QUEUE);
    let mut inputs = Inputs {
        detector_watch: MemberWatch::declare(&session, MemberKind::Detector).await?,
        trolley_watch: MemberWatch::declare(&session, MemberKind::Trolley).await?,
        status_tick: tokio::time::interval(Duration::from_millis(
            settings.status_period_ms.max(50),
        )),
        frames: frame_rx,
        drops: counters.drops.clone(),
    };
    let status_pub = Publisher::declare(
        &session,
        &keys::detector_status(&did)?,
        counters.drops.clone(),
    )
    .await?;
    let _alive = declare_alive(&session, MemberKind::Detector, &did).await?;
    let mut driver = Driver {
        did: did.clone(),
        session: session.clone(),
        config: Arc::new(DetectorConfig {
            voxel_size_m: settings.voxel_size_m,
            ..DetectorConfig::default()
        }),
        fruit_detector,
        drops: counters.drops.clone(),
        frame_tx,
        frame_tasks: HashMap::new(),
        status_pub,
        clouds: HashMap::new(),
    };
    let mut node = DetectorNode::new(&did, wall_clock_ns());
    tracing::info!(detector = %did, fruit_detector = driver.fruit_detector.name(), "detector started");
    while let Some(input) = inputs.next(&mut shutdown).await {
        let mut actions: VecDeque<DetectorAction> = node.handle(input).into();
        while let Some(action) = actions.pop_front() {
            if let Some(outcome) = driver.perform(action).await? {
                actions.extend(node.handle(outcome));
            }
        }
        counters.mirror(node.counts());
    }
    driver.close().await;
    tracing::info!(detector = %did, frames = counters.frames_processed.load(Ordering::Relaxed), dropped = counters.drops.total(), "detector stopped");
    Ok(())
}
