//! The detector process: RGB-D frames in, ROI point clouds out.
//!
//! Stateless: it runs the detection of [`glasshouse_detect`] (the paper's HSI rule after 1 cm
//! down-sampling, back-projected with the frame's intrinsics and pose) on trolley frames and
//! publishes a RoiCloud on the trolley's `roi` key. Frames are a stream, so a busy detector skips
//! stale frames.
//!
//! Any number of detectors share the fleet by splitting the keys: from the liveliness tokens of
//! detectors and trolleys each detector computes the rendezvous ranking of the live detectors per
//! trolley ([`glasshouse_fleet::rank_planners`]) and subscribes only to the frames of the trolleys
//! it ranks first for. Every frame is thus processed once, by one detector, and frames of other
//! detectors' trolleys never reach it. When a detector leaves, its trolleys move to the next
//! ranked one within the liveliness lease.

use std::collections::{BTreeSet, HashMap};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use glasshouse_bus::{
    declare_alive, DropCounters, MemberEvent, MemberWatch, Publisher, Received, Shutdown,
    Subscriber,
};
use glasshouse_detect::DetectorConfig;
use glasshouse_pipeline::detect_frame;
use glasshouse_proto::keys::{self, MemberKind};
use glasshouse_proto::{DetectorStatus, Header, RgbdFrame, RoiCloud};
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
}

impl Default for DetectorSettings {
    fn default() -> Self {
        Self {
            detector_id: "d1".into(),
            voxel_size_m: 0.01,
            status_period_ms: 1000,
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

/// The trolleys `did` serves: those for which it ranks first among the live detectors.
pub fn served_trolleys<'a>(
    did: &str,
    detectors: &BTreeSet<String>,
    trolleys: &'a BTreeSet<String>,
) -> BTreeSet<&'a str> {
    let detectors: Vec<String> = detectors.iter().cloned().collect();
    trolleys
        .iter()
        .filter(|tid| glasshouse_fleet::rank_planners(tid, &detectors).first() == Some(&did))
        .map(String::as_str)
        .collect()
}

/// Frames waiting for detection, over all served trolleys.
const FRAME_QUEUE: usize = 4;

/// Runs the detector until `shutdown` fires.
pub async fn run(
    session: Session,
    settings: DetectorSettings,
    mut shutdown: Shutdown,
    counters: Arc<DetectorCounters>,
) -> anyhow::Result<()> {
    settings.validate()?;
    let did = settings.detector_id.clone();
    let config = Arc::new(DetectorConfig {
        voxel_size_m: settings.voxel_size_m,
        ..DetectorConfig::default()
    });
    // Frames of the served trolleys, one subscriber (and forwarding task) per trolley.
    let (frame_tx, mut frame_rx) = tokio::sync::mpsc::channel::<Received<RgbdFrame>>(FRAME_QUEUE);
    let mut frame_tasks: HashMap<String, tokio::task::JoinHandle<()>> = HashMap::new();
    let detector_watch = MemberWatch::declare(&session, MemberKind::Detector).await?;
    let trolley_watch = MemberWatch::declare(&session, MemberKind::Trolley).await?;
    let mut live_detectors: BTreeSet<String> = BTreeSet::from([did.clone()]);
    let mut live_trolleys: BTreeSet<String> = BTreeSet::new();
    let status_pub = Publisher::declare(
        &session,
        &keys::detector_status(&did)?,
        counters.drops.clone(),
    )
    .await?;
    let _alive = declare_alive(&session, MemberKind::Detector, &did).await?;
    let mut clouds: HashMap<String, Publisher<RoiCloud>> = HashMap::new();
    let mut status_tick =
        tokio::time::interval(Duration::from_millis(settings.status_period_ms.max(50)));
    let mut total_ms = 0.0f64;
    let mut status_seq = 0u64;
    tracing::info!(detector = %did, "detector started");
    loop {
        let mut membership_changed = false;
        tokio::select! {
            _ = shutdown.wait() => break,
            event = detector_watch.recv() => {
                match event {
                    Some(MemberEvent::Joined(id)) => membership_changed = live_detectors.insert(id),
                    Some(MemberEvent::Left(id)) if id != did => membership_changed = live_detectors.remove(&id),
                    Some(MemberEvent::Left(_)) => {}
                    None => break,
                }
            }
            event = trolley_watch.recv() => {
                match event {
                    Some(MemberEvent::Joined(id)) => membership_changed = live_trolleys.insert(id),
                    Some(MemberEvent::Left(id)) => membership_changed = live_trolleys.remove(&id),
                    None => break,
                }
            }
            _ = status_tick.tick() => {
                status_seq += 1;
                let processed = counters.frames_processed.load(Ordering::Relaxed);
                let status = DetectorStatus {
                    detector_id: did.clone(),
                    frames_processed: processed,
                    dropped_messages: counters.drops.total() + counters.frames_rejected.load(Ordering::Relaxed),
                    mean_detect_time_ms: if processed > 0 { (total_ms / processed as f64) as f32 } else { 0.0 },
                };
                let header = Header { seq: status_seq, source_id: did.clone(), frame_id: "world".into(), ..Header::default() };
                status_pub.publish(&header, &status).await?;
            }
            received = frame_rx.recv() => {
                let Some(Received { header, message: frame, .. }) = received else {
                    continue;
                };
                let tid = header.trolley_id.clone();
                if keys::validate_id(&tid).is_err() {
                    counters.frames_rejected.fetch_add(1, Ordering::Relaxed);
                    tracing::warn!(trolley = %tid, "frame with an invalid trolley id dropped");
                    continue;
                }
                let started = Instant::now();
                let cfg = config.clone();
                let detector_id = did.clone();
                let seq = header.seq;
                let result = tokio::task::spawn_blocking(move || detect_frame(&frame, seq, &detector_id, &cfg))
                    .await
                    .context("detection task failed")?;
                let cloud = match result {
                    Ok(cloud) => cloud,
                    Err(e) => {
                        counters.frames_rejected.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!(trolley = %tid, seq, error = %e, "frame rejected");
                        continue;
                    }
                };
                total_ms += started.elapsed().as_secs_f64() * 1e3;
                counters.frames_processed.fetch_add(1, Ordering::Relaxed);
                let publisher = match clouds.entry(tid.clone()) {
                    std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
                    std::collections::hash_map::Entry::Vacant(e) => e.insert(
                        Publisher::declare(&session, &keys::roi(&tid)?, counters.drops.clone()).await?,
                    ),
                };
                let out = Header { seq, stamp_ns: header.stamp_ns, trolley_id: tid, source_id: did.clone(), frame_id: "world".into() };
                tracing::debug!(seq, points = cloud.points_in_world.len(), "cloud published");
                publisher.publish(&out, &cloud).await?;
            }
        }
        if membership_changed {
            let served = served_trolleys(&did, &live_detectors, &live_trolleys);
            frame_tasks.retain(|tid, task| {
                let keep = served.contains(tid.as_str());
                if !keep {
                    task.abort();
                    tracing::info!(detector = %did, trolley = %tid, "trolley handed to another detector");
                }
                keep
            });
            for tid in served {
                if frame_tasks.contains_key(tid) {
                    continue;
                }
                let frames =
                    Subscriber::declare(&session, &keys::rgbd(tid)?, counters.drops.clone())
                        .await?;
                let (tx, drops) = (frame_tx.clone(), counters.drops.clone());
                let task = tokio::spawn(async move {
                    while let Some(received) = frames.recv().await {
                        // A full queue means this detector is behind: the frame is stale anyway.
                        if tx.try_send(received).is_err() {
                            drops.overflow.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                });
                tracing::info!(detector = %did, trolley = %tid, "serving trolley");
                frame_tasks.insert(tid.to_owned(), task);
            }
            counters
                .trolleys_served
                .store(frame_tasks.len() as u64, Ordering::Relaxed);
        }
    }
    for (_, task) in frame_tasks.drain() {
        task.abort();
    }
    for (_, p) in clouds.drain() {
        p.close().await;
    }
    status_pub.close().await;
    tracing::info!(detector = %did, frames = counters.frames_processed.load(Ordering::Relaxed), dropped = counters.drops.total(), "detector stopped");
    Ok(())
}
