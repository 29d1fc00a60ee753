//! Logging the fleet to Rerun.

use std::collections::HashMap;
use std::path::Path;

use glasshouse_geom::FruitEstimate;
use glasshouse_proto::keys::{ParsedKey, TrolleyTopic};
use glasshouse_proto::{
    ArmState, FrameRegistration, FruitEstimates, Header, Message, PlannerStatus, RankedViews,
    RegistrationVerdict, RgbdFrame, RoiCloud, ViewKind, VoxelState,
};
use nalgebra::{Isometry3, Vector3};
use rerun::RecordingStream;

use crate::ServeSettings;

/// Voxels are re-logged in full at most every this many map updates.
const VOXEL_SNAPSHOT_EVERY: u64 = 5;

/// A Rerun recording of everything the dashboard hears, to a file, a live server, or both.
pub struct Recorder {
    /// One stream per sink (a `.rrd` file, a gRPC server); every message goes to each.
    streams: Vec<RecordingStream>,
    voxels: HashMap<String, TrolleyVoxels>,
    voxel_snapshot: Option<VoxelSnapshot>,
    /// Trolleys whose ground truth was logged (per sink).
    truth_logged: std::sync::Mutex<std::collections::HashSet<(usize, String)>>,
    /// Keeps the web viewer's server alive.
    _web_viewer: Option<Box<dyn std::any::Any + Send>>,
    /// Trolleys seen so far (the layout has a camera view for each).
    trolleys: std::collections::BTreeSet<String>,
    /// Each trolley's last state, for the event log.
    states: HashMap<String, glasshouse_proto::TrolleyState>,
    /// Each planner's owned trolleys, for the event log.
    owners: HashMap<String, Vec<String>>,
}

struct VoxelSnapshot {
    resolution_m: f32,
    roi: Vec<[f32; 3]>,
    occupied: Vec<[f32; 3]>,
}

#[derive(Default)]
struct TrolleyVoxels {
    resolution_m: f32,
    states: HashMap<[i32; 3], VoxelState>,
    updates: u64,
}

fn transform(pose: &Isometry3<f64>) -> rerun::Transform3D {
    let t = pose.translation.vector.cast::<f32>();
    let q = pose.rotation.quaternion().cast::<f32>();
    rerun::Transform3D::from_translation_rotation(
        [t.x, t.y, t.z],
        rerun::Quaternion::from_xyzw([q.i, q.j, q.k, q.w]),
    )
}

impl Recorder {
    /// Records to a `.rrd` file and/or serves live (gRPC server plus the bundled web viewer).
    pub fn new(record: Option<&Path>, serve: Option<&ServeSettings>) -> anyhow::Result<Self> {
        let mut streams = Vec::new();
        if let Some(path) = record {
            streams.push(
                rerun::RecordingStreamBuilder::new("glasshouse")
                    .save(path)
                    .map_err(|e| anyhow::anyhow!("cannot record to {}: {e}", path.display()))?,
            );
        }
        let mut web_viewer: Option<Box<dyn std::any::Any + Send>> = None;
        if let Some(serve) = serve {
            let options = rerun::ServerOptions {
                memory_limit: rerun::MemoryLimit::from_bytes(serve.memory_limit_bytes),
                ..Default::default()
            };
            streams.push(
                rerun::RecordingStreamBuilder::new("glasshouse")
                    .serve_grpc_opts(&serve.bind_ip, serve.grpc_port, options)
                    .map_err(|e| {
                        anyhow::anyhow!("cannot serve gRPC on port {}: {e}", serve.grpc_port)
                    })?,
            );
            let server = rerun::serve_web_viewer(rerun::web_viewer::WebViewerConfig {
                bind_ip: serve.bind_ip.clone(),
                web_port: serve.web_viewer_port.into(),
                connect_to: vec![serve.grpc_url()],
                open_browser: false,
                ..Default::default()
            })
            .map_err(|e| anyhow::anyhow!("cannot serve the web viewer: {e}"))?;
            web_viewer = Some(Box::new(server));
            tracing::info!(grpc = %serve.grpc_url(), viewer = %serve.web_viewer_url(), "serving Rerun");
        }
        for rec in &streams {
            rec.log_static("world", &rerun::ViewCoordinates::RIGHT_HAND_Z_UP())?;
        }
        Ok(Self {
            streams,
            voxels: HashMap::new(),
            voxel_snapshot: None,
            truth_logged: Default::default(),
            _web_viewer: web_viewer,
            trolleys: Default::default(),
            states: HashMap::new(),
            owners: HashMap::new(),
        })
    }

    /// Logs one message to every sink.
    pub fn log(
        &mut self,
        key: &ParsedKey,
        header: &Header,
        message: &Message,
    ) -> anyhow::Result<()> {
        self.voxel_snapshot = match (key, message) {
            (ParsedKey::Trolley { tid, .. }, Message::MapUpdate(m)) => self.fold_map_update(tid, m),
            _ => None,
        };
        self.log_events(key, message)?;
        for i in 0..self.streams.len() {
            let rec = self.streams[i].clone();
            self.log_to(i, &rec, key, header, message)?;
        }
        Ok(())
    }

    /// The event log, and the layout when a trolley first appears.
    fn log_events(&mut self, key: &ParsedKey, message: &Message) -> anyhow::Result<()> {
        let mut events = Vec::new();
        match (key, message) {
            (ParsedKey::Trolley { tid, .. }, _) if !self.trolleys.contains(tid) => {
                self.trolleys.insert(tid.clone());
                let layout = crate::blueprint::layout(&self.trolleys);
                let activation = rerun::blueprint::BlueprintActivation {
                    make_active: true,
                    make_default: true,
                };
                for rec in &self.streams {
                    layout.send(rec, activation)?;
                }
                events.push(format!("trolley {tid} joined"));
            }
            (ParsedKey::Trolley { tid, .. }, Message::TrolleyStatus(s))
                if self.states.get(tid) != Some(&s.state) =>
            {
                self.states.insert(tid.clone(), s.state);
                events.push(format!(
                    "trolley {tid}: {:?}, {} views",
                    s.state, s.views_done
                ));
            }
            (ParsedKey::PlannerStatus { pid }, Message::PlannerStatus(s))
                if self.owners.get(pid) != Some(&s.owned_trolleys) =>
            {
                events.push(format!("planner {pid} owns {:?}", s.owned_trolleys));
                self.owners.insert(pid.clone(), s.owned_trolleys.clone());
            }
            _ => {}
        }
        for line in events {
            for rec in &self.streams {
                rec.log(
                    crate::blueprint::LOG_ENTITY,
                    &rerun::TextLog::new(line.as_str()),
                )?;
            }
        }
        Ok(())
    }

    fn log_to(
        &self,
        sink: usize,
        rec: &RecordingStream,
        key: &ParsedKey,
        header: &Header,
        message: &Message,
    ) -> anyhow::Result<()> {
        rec.set_duration_secs("sim_time", header.stamp_ns as f64 * 1e-9);
        let wall = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs_f64())
            .unwrap_or(0.0);
        rec.set_timestamp_secs_since_epoch("wall_time", wall);
        let (tid, topic) = match key {
            ParsedKey::Trolley { tid, topic } => (tid.as_str(), *topic),
            ParsedKey::PlannerStatus { pid } => {
                if let Message::PlannerStatus(s) = message {
                    log_planner_status(rec, pid, s)?;
                }
                return Ok(());
            }
            _ => return Ok(()),
        };
        let base = format!("world/trolleys/{tid}");
        match (topic, message) {
            (TrolleyTopic::Rgbd, Message::RgbdFrame(f)) => log_frame(rec, &base, f)?,
            (TrolleyTopic::Roi, Message::RoiCloud(c)) => log_cloud(rec, &base, c)?,
            (TrolleyTopic::Views, Message::RankedViews(v)) => log_views(rec, &base, tid, v)?,
            // The truth is static: log it once per trolley.
            (TrolleyTopic::Truth, Message::FruitEstimates(f)) if self.first_truth(sink, tid) => {
                log_truth(rec, &base, f)?
            }
            (TrolleyTopic::Fruits, Message::FruitEstimates(f)) => log_fruits(rec, &base, tid, f)?,
            (TrolleyTopic::Map, Message::MapUpdate(m)) => {
                if let Some(snapshot) = &self.voxel_snapshot {
                    log_voxels(rec, &base, snapshot)?;
                }
                if let Some(r) = &m.registration {
                    log_registration(rec, tid, r)?;
                }
            }
            (TrolleyTopic::Arm, Message::ArmState(a)) if a.moving => {
                log_executed_view(rec, &base, a)?;
            }
            (TrolleyTopic::Status, Message::TrolleyStatus(s)) => {
                rec.log(
                    format!("trolleys/{tid}/views_done"),
                    &rerun::Scalars::single(s.views_done as f64),
                )?;
                rec.log(
                    format!("trolleys/{tid}/dropped"),
                    &rerun::Scalars::single(s.dropped_messages as f64),
                )?;
            }
            _ => {}
        }
        Ok(())
    }

    /// True the first time the ground truth of `tid` reaches `sink` (and only then).
    fn first_truth(&self, sink: usize, tid: &str) -> bool {
        self.truth_logged
            .lock()
            .map(|mut t| t.insert((sink, tid.to_owned())))
            .unwrap_or(false)
    }

    /// Logs one value of a time series to every sink (at the current times).
    pub fn log_scalar(&self, path: &str, value: f64) -> anyhow::Result<()> {
        for rec in &self.streams {
            rec.log(path, &rerun::Scalars::single(value))?;
        }
        Ok(())
    }

    /// Folds a map delta into the trolley's voxel states; every few updates, the solid voxels
    /// to draw (the viewer gets full point sets, not per-voxel edits).
    fn fold_map_update(
        &mut self,
        tid: &str,
        m: &glasshouse_proto::MapUpdate,
    ) -> Option<VoxelSnapshot> {
        let voxels = self.voxels.entry(tid.to_owned()).or_default();
        if m.full {
            voxels.states.clear();
        }
        voxels.resolution_m = m.resolution_m;
        for v in &m.voxels {
            if v.state == VoxelState::Free {
                voxels.states.remove(&v.key);
            } else {
                voxels.states.insert(v.key, v.state);
            }
        }
        voxels.updates += 1;
        if voxels.updates % VOXEL_SNAPSHOT_EVERY != 1 && !m.full {
            return None;
        }
        let res = voxels.resolution_m;
        let centre = |k: &[i32; 3]| {
            [
                (k[0] as f32 + 0.5) * res,
                (k[1] as f32 + 0.5) * res,
                (k[2] as f32 + 0.5) * res,
            ]
        };
        let pick = |state: VoxelState| -> Vec<[f32; 3]> {
            voxels
                .states
                .iter()
                .filter(|(_, s)| **s == state)
                .map(|(k, _)| centre(k))
                .collect()
        };
        Some(VoxelSnapshot {
            resolution_m: res,
            roi: pick(VoxelState::Roi),
            occupied: pick(VoxelState::Occupied),
        })
    }

    /// Flushes and closes every sink.
    pub fn finish(self) -> anyhow::Result<()> {
        for rec in &self.streams {
            rec.flush_blocking()?;
        }
        Ok(())
    }
}

type LogResult = Result<(), rerun::RecordingStreamError>;

fn log_planner_status(rec: &RecordingStream, pid: &str, s: &PlannerStatus) -> LogResult {
    rec.log(
        format!("planners/{pid}/planning_time_ms"),
        &rerun::Scalars::single(s.last_planning_time_ms as f64),
    )?;
    rec.log(
        format!("planners/{pid}/dropped"),
        &rerun::Scalars::single(s.dropped_messages as f64),
    )?;
    let r = &s.registrations;
    for (verdict, clouds) in [
        ("applied", r.applied),
        ("kept_as_sent", r.kept_as_sent),
        ("rejected", r.rejected),
        ("skipped", r.skipped),
    ] {
        rec.log(
            format!("planners/{pid}/registration/{verdict}"),
            &rerun::Scalars::single(clouds as f64),
        )?;
    }
    Ok(())
}

/// The correction the planner applied to a registered cloud (zero when it applied none: the
/// cloud went in as sent, or not at all), mm at the camera and degrees, and the hand-eye
/// estimate's rotation applied before it.
fn log_registration(rec: &RecordingStream, tid: &str, r: &FrameRegistration) -> LogResult {
    let applied = r.verdict == RegistrationVerdict::Applied;
    let (mm, deg) = match applied {
        true => (
            r.sensor_shift_m.map_or(0.0, |m| f64::from(m) * 1e3),
            r.rotation_deg.map_or(0.0, f64::from),
        ),
        false => (0.0, 0.0),
    };
    rec.log(
        format!("trolleys/{tid}/registration/applied_correction_mm"),
        &rerun::Scalars::single(mm),
    )?;
    rec.log(
        format!("trolleys/{tid}/registration/applied_correction_deg"),
        &rerun::Scalars::single(deg),
    )?;
    // The hand-eye estimate's rotation as applied to the cloud (0 while there is none).
    let hand_eye_deg = r
        .hand_eye_correction
        .as_ref()
        .map_or(0.0, |c| c.angle_deg());
    rec.log(
        format!("trolleys/{tid}/registration/hand_eye_correction_deg"),
        &rerun::Scalars::single(hand_eye_deg),
    )
}

/// The camera pose, its pinhole, and the colour and depth images.
fn log_frame(rec: &RecordingStream, base: &str, f: &RgbdFrame) -> LogResult {
    let k = f.intrinsics;
    rec.log(format!("{base}/camera"), &transform(&f.world_from_camera))?;
    rec.log(
        format!("{base}/camera/image"),
        &rerun::Pinhole::from_focal_length_and_resolution(
            [k.fx as f32, k.fy as f32],
            [k.width as f32, k.height as f32],
        )
        .with_principal_point([k.cx as f32, k.cy as f32])
        .with_camera_xyz(rerun::components::ViewCoordinates::RDF),
    )?;
    rec.log(
        format!("{base}/camera/image/rgb"),
        &rerun::Image::from_rgb24(f.rgb.clone(), [k.width, k.height]),
    )?;
    let depth_bytes: Vec<u8> = f.depth.iter().flat_map(|d| d.to_le_bytes()).collect();
    rec.log(
        format!("{base}/camera/image/depth"),
        &rerun::DepthImage::from_gray16(depth_bytes, [k.width, k.height])
            .with_meter(1.0 / f.depth_scale_m),
    )
}

/// The finite points of a cloud, ROI points red, the rest green.
fn log_cloud(rec: &RecordingStream, base: &str, c: &RoiCloud) -> LogResult {
    let points: Vec<[f32; 3]> = c
        .points_in_world
        .iter()
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .map(|p| [p.x, p.y, p.z])
        .collect();
    let colors: Vec<rerun::Color> = c
        .points_in_world
        .iter()
        .zip(&c.roi)
        .filter(|(p, _)| p.iter().all(|v| v.is_finite()))
        .map(|(_, &roi)| {
            if roi {
                rerun::Color::from_rgb(230, 40, 40)
            } else {
                rerun::Color::from_rgb(90, 160, 90)
            }
        })
        .collect();
    rec.log(
        format!("{base}/roi_cloud"),
        &rerun::Points3D::new(points)
            .with_colors(colors)
            .with_radii([0.003]),
    )
}

/// Ranked views as arrows along the camera axis (ROI views red, exploration blue).
fn log_views(rec: &RecordingStream, base: &str, tid: &str, v: &RankedViews) -> LogResult {
    let origins: Vec<[f32; 3]> = v
        .views
        .iter()
        .map(|v| v.world_from_camera.translation.vector.cast::<f32>().into())
        .collect();
    let vectors: Vec<[f32; 3]> = v
        .views
        .iter()
        .map(|v| {
            (v.world_from_camera.rotation * Vector3::z() * 0.15)
                .cast::<f32>()
                .into()
        })
        .collect();
    let colors: Vec<rerun::Color> = v
        .views
        .iter()
        .map(|view| match view.kind {
            ViewKind::Roi => rerun::Color::from_rgb(220, 80, 80),
            ViewKind::Exploration => rerun::Color::from_rgb(80, 120, 220),
        })
        .collect();
    rec.log(
        format!("{base}/views"),
        &rerun::Arrows3D::from_vectors(vectors)
            .with_origins(origins)
            .with_colors(colors),
    )?;
    rec.log(
        format!("trolleys/{tid}/planning_time_ms"),
        &rerun::Scalars::single(v.planning_time_ms as f64),
    )
}

/// The fruits' boxes as Rerun boxes (centres and half sizes), unlabelled and uncoloured.
fn fruit_boxes(fruits: &[FruitEstimate]) -> rerun::Boxes3D {
    let centres: Vec<[f32; 3]> = fruits
        .iter()
        .map(|f| nalgebra::center(&f.min, &f.max).cast::<f32>().into())
        .collect();
    let half_sizes: Vec<[f32; 3]> = fruits
        .iter()
        .map(|f| ((f.max - f.min) * 0.5).cast::<f32>().into())
        .collect();
    rerun::Boxes3D::from_centers_and_half_sizes(centres, half_sizes)
}

fn log_truth(rec: &RecordingStream, base: &str, f: &FruitEstimates) -> LogResult {
    rec.log_static(
        format!("{base}/truth"),
        &fruit_boxes(&f.fruits)
            .with_labels(f.fruits.iter().map(|f| format!("truth #{}", f.id)))
            .with_colors([rerun::Color::from_rgb(40, 160, 255)]),
    )
}

/// Fruit boxes labelled with size, volume and confidence, and the count as a time series.
fn log_fruits(rec: &RecordingStream, base: &str, tid: &str, f: &FruitEstimates) -> LogResult {
    let labels: Vec<String> = f
        .fruits
        .iter()
        .map(|f| {
            let s = (f.max - f.min) * 100.0;
            format!(
                "#{} {:.1}x{:.1}x{:.1} cm {:.0} cm³ conf {:.2}",
                f.id,
                s.x,
                s.y,
                s.z,
                f.volume_m3 * 1e6,
                f.confidence
            )
        })
        .collect();
    rec.log(
        format!("{base}/fruits"),
        &fruit_boxes(&f.fruits)
            .with_labels(labels)
            .with_colors([rerun::Color::from_rgb(220, 20, 60)]),
    )?;
    rec.log(
        format!("trolleys/{tid}/fruits_found"),
        &rerun::Scalars::single(f.fruits.len() as f64),
    )
}

fn log_voxels(rec: &RecordingStream, base: &str, snapshot: &VoxelSnapshot) -> LogResult {
    rec.log(
        format!("{base}/map/roi_voxels"),
        &rerun::Points3D::new(snapshot.roi.clone())
            .with_colors([rerun::Color::from_rgb(255, 30, 30)])
            .with_radii([snapshot.resolution_m * 0.5]),
    )?;
    rec.log(
        format!("{base}/map/occupied_voxels"),
        &rerun::Points3D::new(snapshot.occupied.clone())
            .with_colors([rerun::Color::from_rgb(120, 120, 120)])
            .with_radii([snapshot.resolution_m * 0.4]),
    )
}

/// The edge announces the view it executes as a moving arm state with that pose.
fn log_executed_view(rec: &RecordingStream, base: &str, a: &ArmState) -> LogResult {
    let origin: [f32; 3] = a.world_from_camera.translation.vector.cast::<f32>().into();
    let axis: [f32; 3] = (a.world_from_camera.rotation * Vector3::z() * 0.2)
        .cast::<f32>()
        .into();
    rec.log(
        format!("{base}/executed_view"),
        &rerun::Arrows3D::from_vectors([axis])
            .with_origins([origin])
            .with_colors([rerun::Color::from_rgb(255, 215, 0)])
            .with_radii([0.006]),
    )
}
