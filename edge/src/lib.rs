//! The trolley process: streams RGB-D frames and arm state, executes ranked views.
//!
//! The loop is the paper's Algorithm 1 split across machines: capture a frame (seq n) and publish
//! it with the arm state; wait for RankedViews planned on frame n; execute the first view the arm
//! can reach; capture again. When no planner answers in time the edge re-announces frame n.
//! The source is the simulated glasshouse ([`glasshouse_sim`]); the clock is simulated: each view
//! costs its motion time plus a capture time.

pub mod source;

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use glasshouse_bus::{declare_alive, DropCounters, Publisher, Received, Shutdown, Subscriber};
use glasshouse_proto::keys::{self, MemberKind};
use glasshouse_proto::{
    FruitEstimates, Header, RankedView, RgbdFrame, TrolleyState, TrolleyStatus,
};
use glasshouse_sim::{CameraModel, ScenarioKind, Scene};
use nalgebra::Isometry3;
use serde::Deserialize;
use source::{FrameRecorder, ReplaySource, SimSource, TrolleySource};
use zenoh::Session;

/// Depth is sent in millimetres.
pub const DEPTH_SCALE_M: f32 = 0.001;

/// Edge settings; every field has a default, a JSON5 file may set any of them.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EdgeConfig {
    pub trolley_id: String,
    /// Scenario name: `1`, `2` or `row`.
    pub scenario: String,
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
}

impl Default for EdgeConfig {
    fn default() -> Self {
        Self {
            trolley_id: "t1".into(),
            scenario: "1".into(),
            seed: 1,
            width: 640,
            height: 480,
            max_views: 0,
            views_timeout_ms: 3000,
            capture_time_s: glasshouse_arm::CAPTURE_TIME_S,
            segment_length_m: 1.0,
            segment_done_utility: 0.2,
            replay_dir: None,
            record_frames_dir: None,
            frame_interval_ms: 0,
        }
    }
}

impl EdgeConfig {
    pub fn validate(&self) -> anyhow::Result<ScenarioKind> {
        keys::validate_id(&self.trolley_id)?;
        anyhow::ensure!(
            (16..=1280).contains(&self.width) && (12..=960).contains(&self.height),
            "image size {}x{} outside 16x12..1280x960",
            self.width,
            self.height
        );
        anyhow::ensure!(
            self.capture_time_s.is_finite() && self.capture_time_s >= 0.0,
            "capture time must be finite and >= 0"
        );
        anyhow::ensure!(
            self.segment_length_m.is_finite() && self.segment_length_m > 0.0,
            "segment length must be finite and > 0"
        );
        self.scenario
            .parse::<ScenarioKind>()
            .map_err(|e| anyhow::anyhow!("{e}"))
    }
}

/// What the edge reports to an embedding process (the demo prints these).
#[derive(Clone, Debug)]
pub enum EdgeEvent {
    /// A view was executed.
    ViewDone {
        views_done: u32,
        frame_seq: u64,
        view: RankedView,
        sim_time_s: f64,
    },
    /// Nothing above the threshold was left in a segment; the trolley moved to the next one.
    SegmentDone { segments_done: u32, sim_time_s: f64 },
    /// No planner answered frame `frame_seq` in time; it was published again.
    Reannounced { frame_seq: u64 },
    /// The view budget is spent and the last frame was answered.
    Finished { views_done: u32, frames: u64 },
}

/// Counters the edge exposes to tests and status messages.
#[derive(Debug, Default)]
pub struct EdgeCounters {
    pub drops: Arc<DropCounters>,
}

/// Runs the trolley until its view budget is spent or `shutdown` fires.
pub async fn run(
    session: Session,
    config: EdgeConfig,
    mut shutdown: Shutdown,
    events: Option<tokio::sync::mpsc::UnboundedSender<EdgeEvent>>,
    counters: Arc<EdgeCounters>,
) -> anyhow::Result<()> {
    let scenario = config.validate()?;
    let tid = config.trolley_id.clone();
    let drops = counters.drops.clone();
    let rgbd = Publisher::declare(&session, &keys::rgbd(&tid)?, drops.clone()).await?;
    let arm = Publisher::declare(&session, &keys::arm(&tid)?, drops.clone()).await?;
    let info_pub = Publisher::declare(&session, &keys::info(&tid)?, drops.clone()).await?;
    let status_pub = Publisher::declare(&session, &keys::status(&tid)?, drops.clone()).await?;
    let truth_pub = Publisher::declare(&session, &keys::truth(&tid)?, drops.clone()).await?;
    let views_sub = Subscriber::declare(&session, &keys::views(&tid)?, drops.clone()).await?;
    let _alive = declare_alive(&session, MemberKind::Trolley, &tid).await?;

    let mut source: Box<dyn TrolleySource> = match &config.replay_dir {
        Some(dir) => Box::new(ReplaySource::open(dir)?),
        None => Box::new(SimSource::new(&config)?),
    };
    let recorder = config
        .record_frames_dir
        .as_deref()
        .map(FrameRecorder::create)
        .transpose()?;
    let truth = source.ground_truth().map(|fruits| FruitEstimates {
        fruits,
        based_on_seq: 0,
        planner_id: format!("truth-{tid}"),
    });
    let mut sim_time_s = 0.0;
    let mut frame_seq = 0u64;
    let mut segments_done = 0u32;
    let mut status = TrolleyStatus {
        state: TrolleyState::Starting,
        views_done: 0,
        frames_published: 0,
        unreachable_views: 0,
        reannounces: 0,
        dropped_messages: 0,
        last_views_seq: 0,
        message: String::new(),
    };
    tracing::info!(trolley = %tid, %scenario, seed = config.seed, "edge started");
    let header = |seq: u64, sim_time_s: f64| Header {
        seq,
        stamp_ns: (sim_time_s * 1e9) as u64,
        trolley_id: tid.clone(),
        source_id: tid.clone(),
        frame_id: "world".into(),
    };
    let emit = |event: EdgeEvent| {
        if let Some(tx) = &events {
            let _ = tx.send(event);
        }
    };

    let mut next_capture = tokio::time::Instant::now();
    'capture: loop {
        if shutdown.is_set() {
            break;
        }
        if config.frame_interval_ms > 0 {
            tokio::time::sleep_until(next_capture).await;
            next_capture =
                tokio::time::Instant::now() + Duration::from_millis(config.frame_interval_ms);
        }
        frame_seq += 1;
        status.state = TrolleyState::Capturing;
        let (returned, frame) = tokio::task::spawn_blocking(move || {
            let frame = source.capture(frame_seq);
            (source, frame)
        })
        .await
        .context("capture task failed")?;
        source = returned;
        let Some(frame) = frame? else {
            tracing::info!(trolley = %tid, "the source has no more frames");
            emit(EdgeEvent::Finished {
                views_done: status.views_done,
                frames: status.frames_published,
            });
            break;
        };
        let info_msg = source.info();
        let frame_msg = frame;
        if let Some(recorder) = &recorder {
            let h = header(frame_seq, sim_time_s);
            recorder.write(&h, &info_msg)?;
            recorder.write(&h, &frame_msg)?;
        }
        let arm_msg = source.arm_state(false, status.views_done);
        let announce = |seq: u64, t: f64| {
            let h = header(seq, t);
            let (info_pub, arm, rgbd, truth_pub) = (&info_pub, &arm, &rgbd, &truth_pub);
            let (info_msg, arm_msg, frame_msg, truth) = (&info_msg, &arm_msg, &frame_msg, &truth);
            async move {
                info_pub.publish(&h, info_msg).await?;
                if let Some(truth) = truth {
                    truth_pub.publish(&h, truth).await?;
                }
                arm.publish(&h, arm_msg).await?;
                rgbd.publish(&h, frame_msg).await
            }
        };
        announce(frame_seq, sim_time_s).await?;
        status.frames_published += 1;
        status.state = TrolleyState::WaitingForViews;
        status.dropped_messages = drops.total();
        status_pub
            .publish(&header(frame_seq, sim_time_s), &status)
            .await?;

        // Wait for views planned on this frame; re-announce it when nobody answers.
        let views = loop {
            let timeout = Duration::from_millis(config.views_timeout_ms);
            tokio::select! {
                _ = shutdown.wait() => break 'capture,
                received = tokio::time::timeout(timeout, views_sub.recv()) => match received {
                    Err(_) => {
                        status.reannounces += 1;
                        tracing::info!(trolley = %tid, frame_seq, "no views yet; re-announcing the frame");
                        emit(EdgeEvent::Reannounced { frame_seq });
                        announce(frame_seq, sim_time_s).await?;
                    }
                    Ok(None) => break 'capture,
                    Ok(Some(Received { header, message: views, .. })) => {
                        if header.trolley_id == tid && views.based_on_seq == frame_seq {
                            break views;
                        }
                        tracing::debug!(based_on = views.based_on_seq, frame_seq, "ignoring views planned on another frame");
                    }
                },
            }
        };
        status.last_views_seq = views.based_on_seq;
        if config.max_views > 0 && status.views_done >= config.max_views {
            emit(EdgeEvent::Finished {
                views_done: status.views_done,
                frames: status.frames_published,
            });
            break;
        }
        // Nothing worth a look is left in this segment: move on along the row.
        let best_utility = views.views.first().map_or(f32::NEG_INFINITY, |v| v.utility);
        if f64::from(best_utility) <= config.segment_done_utility {
            match source.next_segment() {
                Some(motion_s) => {
                    segments_done += 1;
                    sim_time_s += motion_s + config.capture_time_s;
                    tracing::info!(trolley = %tid, frame_seq, best_utility, segment = segments_done, "segment done; moving along the row");
                    emit(EdgeEvent::SegmentDone {
                        segments_done,
                        sim_time_s,
                    });
                    continue;
                }
                None if !views.views.is_empty() => {}
                None => {
                    tracing::info!(trolley = %tid, frame_seq, "row done: no view left above the threshold");
                    emit(EdgeEvent::Finished {
                        views_done: status.views_done,
                        frames: status.frames_published,
                    });
                    break;
                }
            }
        }
        // Execute the first reachable view (Algorithm 1: "moveToPose, else the next view"):
        // inverse kinematics, then a collision-free joint path.
        let goals: Vec<Isometry3<f64>> = views.views.iter().map(|v| v.world_from_camera).collect();
        let executed = source.execute(&goals);
        status.unreachable_views += executed.map_or(goals.len(), |e| e.index) as u32;
        let Some(executed) = executed else {
            tracing::info!(trolley = %tid, frame_seq, offered = views.views.len(), "no reachable view; capturing again");
            sim_time_s += config.capture_time_s;
            continue;
        };
        let view = views.views[executed.index].clone();
        status.state = TrolleyState::Moving;
        sim_time_s += executed.motion_s + config.capture_time_s;
        arm.publish(
            &header(frame_seq, sim_time_s),
            &source.arm_state(true, status.views_done),
        )
        .await?;
        status.views_done += 1;
        emit(EdgeEvent::ViewDone {
            views_done: status.views_done,
            frame_seq,
            view,
            sim_time_s,
        });
    }

    status.state = TrolleyState::Done;
    status.dropped_messages = drops.total();
    status.message = format!(
        "{} views, {} frames",
        status.views_done, status.frames_published
    );
    status_pub
        .publish(&header(frame_seq, sim_time_s), &status)
        .await?;
    rgbd.close().await;
    arm.close().await;
    info_pub.close().await;
    status_pub.close().await;
    truth_pub.close().await;
    tracing::info!(trolley = %tid, views = status.views_done, frames = status.frames_published,
        dropped = drops.total(), corrupt = drops.corrupt.load(Ordering::Relaxed), "edge stopped");
    Ok(())
}

/// Renders the simulated camera and packs the frame for the wire (depth in millimetres).
pub fn render_frame(
    scene: &Scene,
    camera: &CameraModel,
    world_from_camera: &Isometry3<f64>,
    noise_seed: u64,
) -> RgbdFrame {
    let image = scene.render(camera, world_from_camera, noise_seed);
    let depth = image
        .depth_m
        .iter()
        .map(|&d| {
            if d.is_finite() && d > 0.0 {
                (d / DEPTH_SCALE_M).round().clamp(1.0, u16::MAX as f32) as u16
            } else {
                0
            }
        })
        .collect();
    RgbdFrame {
        intrinsics: image.intrinsics,
        world_from_camera: *world_from_camera,
        depth_scale_m: DEPTH_SCALE_M,
        min_range_m: camera.min_range_m as f32,
        max_range_m: camera.max_range_m as f32,
        depth,
        rgb: image.rgb,
    }
}
