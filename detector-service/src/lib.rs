//! The detector process: RGB-D frames in, ROI point clouds out.
//!
//! Stateless: it runs the detection of [`glasshouse_detect`] (the paper's HSI rule after 1 cm
//! down-sampling, back-projected with the frame's intrinsics and pose) on trolley frames and
//! publishes a RoiCloud on the trolley's `roi` key under its own id (`gh/trolley/{tid}/roi/{did}`:
//! in a secured deployment the router lets no other identity put there). Frames are a stream, so
//! a busy detector skips stale frames.
//!
//! Any number of detectors share the fleet by splitting the keys: from the liveliness tokens of
//! detectors and trolleys each detector computes the rendezvous ranking of the live detectors per
//! trolley ([`glasshouse_fleet::first_ranked`]) and subscribes only to the frames of the trolleys
//! it ranks first for. Every frame is thus processed once, by one detector, and frames of other
//! detectors' trolleys never reach it. When a detector leaves, its trolleys move to the next
//! ranked one within the liveliness lease. The planners rank the same way and take a trolley's
//! clouds only from the detector ranked first for it.

use std::collections::{BTreeSet, HashMap};
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
use glasshouse_pipeline::detect_frame_with;
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

/// The trolleys `did` serves: those for which it ranks first among the live detectors.
pub fn served_trolleys<'a>(
    did: &str,
    detectors: &BTreeSet<String>,
    trolleys: &'a BTreeSet<String>,
) -> BTreeSet<&'a str> {
    let ranked =
        |tid: &str| glasshouse_fleet::first_ranked(tid, detectors.iter().map(String::as_str));
    trolleys
        .iter()
        .filter(|tid| ranked(tid) == Some(did))
        .map(String::as_str)
        .collect()
}

/// Frames waiting for detection, over all served trolleys.
const FRAME_QUEUE: usize = 4;

/// What wakes the detector up.
enum DetectorEvent {
    Detector(MemberEvent),
    Trolley(MemberEvent),
    StatusTick,
    Frame(Box<Received<RgbdFrame>>),
}

/// The bus side the detector listens to: who is alive, the status clock and the served frames.
struct Inputs {
    detector_watch: MemberWatch,
    trolley_watch: MemberWatch,
    status_tick: tokio::time::Interval,
    frames: tokio::sync::mpsc::Receiver<Received<RgbdFrame>>,
}

impl Inputs {
    /// The next event; `None` once `shutdown` fires or a membership watch ends.
    async fn next(&mut self, shutdown: &mut Shutdown) -> Option<DetectorEvent> {
        loop {
            let event = tokio::select! {
                _ = shutdown.wait() => return None,
                event = self.detector_watch.recv() => DetectorEvent::Detector(event?),
                event = self.trolley_watch.recv() => DetectorEvent::Trolley(event?),
                _ = self.status_tick.tick() => DetectorEvent::StatusTick,
                received = self.frames.recv() => match received {
                    Some(received) => DetectorEvent::Frame(Box::new(received)),
                    None => continue,
                },
            };
            return Some(event);
        }
    }
}

/// A running detector: the live members, the served trolleys' frame forwarders, the publishers.
struct Detector {
    did: String,
    /// This process's boot epoch: every header carries it.
    epoch_ns: u64,
    session: Session,
    config: Arc<DetectorConfig>,
    fruit_detector: Arc<dyn FruitDetector>,
    counters: Arc<DetectorCounters>,
    /// Where the forwarders put the served trolleys' frames.
    frame_tx: tokio::sync::mpsc::Sender<Received<RgbdFrame>>,
    /// One subscriber (and forwarding task) per served trolley.
    frame_tasks: HashMap<String, tokio::task::JoinHandle<()>>,
    live_detectors: BTreeSet<String>,
    live_trolleys: BTreeSet<String>,
    status_pub: Publisher<DetectorStatus>,
    clouds: HashMap<String, Publisher<RoiCloud>>,
    total_ms: f64,
    status_seq: u64,
}

impl Detector {
    /// Takes in one event; true when the live members changed.
    async fn handle(&mut self, event: DetectorEvent) -> anyhow::Result<bool> {
        let changed = match event {
            DetectorEvent::Detector(MemberEvent::Joined(id)) => self.live_detectors.insert(id),
            DetectorEvent::Detector(MemberEvent::Left(id)) if id != self.did => {
                self.live_detectors.remove(&id)
            }
            DetectorEvent::Detector(MemberEvent::Left(_)) => false,
            DetectorEvent::Trolley(MemberEvent::Joined(id)) => self.live_trolleys.insert(id),
            DetectorEvent::Trolley(MemberEvent::Left(id)) => self.live_trolleys.remove(&id),
            DetectorEvent::StatusTick => {
                self.publish_status().await?;
                false
            }
            DetectorEvent::Frame(received) => {
                self.detect(received).await?;
                false
            }
        };
        Ok(changed)
    }

    async fn publish_status(&mut self) -> anyhow::Result<()> {
        self.status_seq += 1;
        let counters = &self.counters;
        let processed = counters.frames_processed.load(Ordering::Relaxed);
        let status = DetectorStatus {
            detector_id: self.did.clone(),
            frames_processed: processed,
            dropped_messages: counters.drops.total()
                + counters.frames_rejected.load(Ordering::Relaxed),
            mean_detect_time_ms: if processed > 0 {
                (self.total_ms / processed as f64) as f32
            } else {
                0.0
            },
        };
        let header = Header {
            seq: self.status_seq,
            epoch_ns: self.epoch_ns,
            source_id: self.did.clone(),
            frame_id: "world".into(),
            ..Header::default()
        };
        self.status_pub.publish(&header, &status).await?;
        Ok(())
    }

    /// Detects the ROI in one frame and publishes its cloud; a bad frame is counted and dropped.
    async fn detect(&mut self, received: Box<Received<RgbdFrame>>) -> anyhow::Result<()> {
        let Received {
            header,
            message: frame,
            ..
        } = *received;
        let tid = header.trolley_id.clone();
        if keys::validate_id(&tid).is_err() {
            self.counters
                .frames_rejected
                .fetch_add(1, Ordering::Relaxed);
            tracing::warn!(trolley = %tid, "frame with an invalid trolley id dropped");
            return Ok(());
        }
        let started = Instant::now();
        let cfg = self.config.clone();
        let fruit_detector = self.fruit_detector.clone();
        let detector_id = self.did.clone();
        let (seq, frame_id) = (header.seq, header.frame());
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
        let cloud = match result {
            Ok(cloud) => cloud,
            Err(e) => {
                self.counters
                    .frames_rejected
                    .fetch_add(1, Ordering::Relaxed);
                tracing::warn!(trolley = %tid, seq, error = %e, "frame rejected");
                return Ok(());
            }
        };
        self.total_ms += started.elapsed().as_secs_f64() * 1e3;
        self.counters
            .frames_processed
            .fetch_add(1, Ordering::Relaxed);
        let publisher = match self.clouds.entry(tid.clone()) {
            std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::hash_map::Entry::Vacant(e) => e.insert(
                Publisher::declare(
                    &self.session,
                    &keys::roi(&tid, &self.did)?,
                    self.counters.drops.clone(),
                )
                .await?,
            ),
        };
        let out = Header {
            seq,
            epoch_ns: self.epoch_ns,
            stamp_ns: header.stamp_ns,
            trolley_id: tid,
            source_id: self.did.clone(),
            frame_id: "world".into(),
        };
        tracing::debug!(seq, points = cloud.points_in_world.len(), "cloud published");
        publisher.publish(&out, &cloud).await?;
        Ok(())
    }

    /// Follows the served trolleys after a membership change: drops the frames of trolleys handed
    /// to another detector, subscribes to those newly served.
    async fn update_served(&mut self) -> anyhow::Result<()> {
        let did = &self.did;
        let served = served_trolleys(did, &self.live_detectors, &self.live_trolleys);
        self.frame_tasks.retain(|tid, task| {
            let keep = served.contains(tid.as_str());
            if !keep {
                task.abort();
                tracing::info!(detector = %did, trolley = %tid, "trolley handed to another detector");
            }
            keep
        });
        for tid in served {
            if self.frame_tasks.contains_key(tid) {
                continue;
            }
            let drops = self.counters.drops.clone();
            let frames =
                Subscriber::declare(&self.session, &keys::rgbd(tid)?, drops.clone()).await?;
            let tx = self.frame_tx.clone();
            let task = tokio::spawn(async move {
                while let Some(received) = frames.recv().await {
                    // A full queue means this detector is behind: the frame is stale anyway.
                    if tx.try_send(received).is_err() {
                        drops.overflow.fetch_add(1, Ordering::Relaxed);
                    }
                }
            });
            tracing::info!(detector = %did, trolley = %tid, "serving trolley");
            self.frame_tasks.insert(tid.to_owned(), task);
        }
        self.counters
            .trolleys_served
            .store(self.frame_tasks.len() as u64, Ordering::Relaxed);
        Ok(())
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
    };
    let status_pub = Publisher::declare(
        &session,
        &keys::detector_status(&did)?,
        counters.drops.clone(),
    )
    .await?;
    let _alive = declare_alive(&session, MemberKind::Detector, &did).await?;
    let mut detector = Detector {
        did: did.clone(),
        epoch_ns: wall_clock_ns(),
        session: session.clone(),
        config: Arc::new(DetectorConfig {
            voxel_size_m: settings.voxel_size_m,
            ..DetectorConfig::default()
        }),
        fruit_detector,
        counters: counters.clone(),
        frame_tx,
        frame_tasks: HashMap::new(),
        live_detectors: BTreeSet::from([did.clone()]),
        live_trolleys: BTreeSet::new(),
        status_pub,
        clouds: HashMap::new(),
        total_ms: 0.0,
        status_seq: 0,
    };
    tracing::info!(detector = %did, fruit_detector = detector.fruit_detector.name(), "detector started");
    while let Some(event) = inputs.next(&mut shutdown).await {
        if detector.handle(event).await? {
            detector.update_served().await?;
        }
    }
    detector.close().await;
    tracing::info!(detector = %did, frames = counters.frames_processed.load(Ordering::Relaxed), dropped = counters.drops.total(), "detector stopped");
    Ok(())
}
