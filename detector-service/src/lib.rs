//! The detector process: RGB-D frames in, ROI point clouds out.
//!
//! Stateless: it subscribes to the frames of every trolley, runs the detection of
//! [`glasshouse_detect`] (the paper's HSI rule after 1 cm down-sampling, back-projected with the
//! frame's intrinsics and pose) and publishes a RoiCloud on the trolley's `roi` key. Any number of
//! detectors can run; frames are a stream, so a busy detector skips stale frames.

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use glasshouse_bus::{
    declare_alive, Delivery, DropCounters, Received, Shutdown, TypedPublisher, TypedSubscriber,
};
use glasshouse_detect::{detect, DepthFrame, DetectorConfig};
use glasshouse_proto::keys::{self, MemberKind, TrolleyTopic};
use glasshouse_proto::{DetectorStatus, Header, Message, RgbdFrame, RoiCloud};
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
}

/// Turns one frame into an ROI cloud.
pub fn frame_to_cloud(
    frame: &RgbdFrame,
    frame_seq: u64,
    detector_id: &str,
    config: &DetectorConfig,
) -> Result<RoiCloud, glasshouse_detect::DetectError> {
    let depth_frame = DepthFrame {
        intrinsics: frame.intrinsics,
        depth: &frame.depth,
        depth_scale_m: frame.depth_scale_m as f64,
        rgb: &frame.rgb,
    };
    let cloud = detect(&depth_frame, &frame.world_from_camera, config)?;
    Ok(RoiCloud {
        points_in_world: cloud.points_in_world,
        roi: cloud.roi,
        sensor_origin_in_world: cloud.sensor_origin_in_world,
        source_frame_seq: frame_seq,
        invalid_pixels: cloud.invalid_pixels.min(u32::MAX as usize) as u32,
        detector_id: detector_id.to_owned(),
    })
}

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
    let frames = TypedSubscriber::declare(
        &session,
        &keys::all_trolleys(TrolleyTopic::Rgbd),
        Delivery::Stream,
        counters.drops.clone(),
    )
    .await?;
    let status_pub = TypedPublisher::declare(
        &session,
        keys::detector_status(&did)?,
        Delivery::Reliable,
        counters.drops.clone(),
    )
    .await?;
    let _alive = declare_alive(&session, MemberKind::Detector, &did).await?;
    let mut clouds: HashMap<String, TypedPublisher> = HashMap::new();
    let mut status_tick =
        tokio::time::interval(Duration::from_millis(settings.status_period_ms.max(50)));
    let mut total_ms = 0.0f64;
    let mut status_seq = 0u64;
    tracing::info!(detector = %did, "detector started");
    loop {
        tokio::select! {
            _ = shutdown.wait() => break,
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
                status_pub.publish(&header, &Message::DetectorStatus(status)).await?;
            }
            received = frames.recv() => {
                let Some(Received { header, message: Message::RgbdFrame(frame), .. }) = received else {
                    if received.is_none() { break; }
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
                let result = tokio::task::spawn_blocking(move || frame_to_cloud(&frame, seq, &detector_id, &cfg))
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
                        TypedPublisher::declare(&session, keys::trolley(&tid, TrolleyTopic::Roi)?, Delivery::Reliable, counters.drops.clone()).await?,
                    ),
                };
                let out = Header { seq, stamp_ns: header.stamp_ns, trolley_id: tid, source_id: did.clone(), frame_id: "world".into() };
                tracing::debug!(seq, points = cloud.points_in_world.len(), "cloud published");
                publisher.publish(&out, &Message::RoiCloud(cloud)).await?;
            }
        }
    }
    for (_, p) in clouds.drain() {
        p.close().await;
    }
    status_pub.close().await;
    tracing::info!(detector = %did, frames = counters.frames_processed.load(Ordering::Relaxed), dropped = counters.drops.total(), "detector stopped");
    Ok(())
}
