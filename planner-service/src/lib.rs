//! The planner process: ROI maps per trolley, ranked next best views, fruit estimates.
//!
//! For every trolley it hears, the planner keeps a [`RoiMap`], integrates each RoiCloud, plans
//! the next views with [`glasshouse_nbv`] (seeded from the planner seed and the frame sequence,
//! so a run replays exactly), and publishes RankedViews, FruitEstimates and the map's changed
//! voxels (MapUpdate). A cloud that fails to integrate is counted and dropped; the map is never
//! partially updated.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use glasshouse_bus::{
    declare_alive, Delivery, DropCounters, Received, Shutdown, TypedPublisher, TypedSubscriber,
};
use glasshouse_geom::look_along;
use glasshouse_nbv::{plan_views, FruitTracker, Method, PlannerConfig, PlanningContext};
use glasshouse_proto::keys::{self, MemberKind, TrolleyTopic};
use glasshouse_proto::{
    Fruit, FruitEstimates, Header, MapUpdate, Message, PlannerStatus, RankedView, RankedViews,
    RoiCloud, TrolleyInfo, ViewKind, VoxelChange, VoxelState,
};
use glasshouse_roimap::{MapConfig, Occupancy, RoiMap, Voxel, VoxelKey};
use nalgebra::{Isometry3, Point3, Vector3};
use serde::Deserialize;
use zenoh::Session;

/// Planner settings; a JSON5 file may set any of them.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlannerSettings {
    pub planner_id: String,
    /// `ours-uu`, `ours-up`, `explo-uu` or `explo-up`.
    pub method: String,
    pub seed: u64,
    pub resolution_m: f64,
    /// Rays are integrated up to this range (points further away free the ray only).
    pub max_range_m: f64,
    pub min_cluster_voxels: usize,
    pub status_period_ms: u64,
}

impl Default for PlannerSettings {
    fn default() -> Self {
        Self {
            planner_id: "p1".into(),
            method: "ours-uu".into(),
            seed: 1,
            resolution_m: 0.01,
            max_range_m: 2.0,
            min_cluster_voxels: 10,
            status_period_ms: 1000,
        }
    }
}

impl PlannerSettings {
    pub fn validate(&self) -> anyhow::Result<Method> {
        keys::validate_id(&self.planner_id)?;
        anyhow::ensure!(
            self.max_range_m.is_finite() && self.max_range_m > 0.0,
            "max range must be positive"
        );
        let method: Method = self.method.parse().map_err(|e| anyhow::anyhow!("{e}"))?;
        self.map_config().validate()?;
        Ok(method)
    }

    fn map_config(&self) -> MapConfig {
        MapConfig {
            resolution_m: self.resolution_m,
            max_range_m: Some(self.max_range_m),
            ..MapConfig::default()
        }
    }
}

/// Counters a planner exposes to tests and its status message.
#[derive(Debug, Default)]
pub struct PlannerCounters {
    pub drops: Arc<DropCounters>,
    pub clouds_integrated: AtomicU64,
    /// Clouds that decoded but could not be integrated (e.g. mismatched lengths).
    pub clouds_rejected: AtomicU64,
    pub views_published: AtomicU64,
}

/// One trolley's planning state.
pub struct TrolleyPlanner {
    pub map: RoiMap,
    tracker: FruitTracker,
    info: Option<TrolleyInfo>,
    world_from_camera: Option<Isometry3<f64>>,
    last_cloud_seq: Option<u64>,
    last_views: Option<RankedViews>,
    map_seq: u64,
    /// Voxels last published as occupied or ROI: MapUpdate carries solid voxels and the ones
    /// that stopped being solid, not every newly freed voxel (those would dominate the traffic).
    published_solid: HashSet<VoxelKey>,
}

/// What one integrated cloud produced.
pub struct CloudOutcome {
    pub views: Option<RankedViews>,
    pub fruits: FruitEstimates,
    pub map_update: MapUpdate,
}

impl TrolleyPlanner {
    pub fn new(settings: &PlannerSettings) -> anyhow::Result<Self> {
        Ok(Self {
            map: RoiMap::new(settings.map_config())?,
            tracker: FruitTracker::default(),
            info: None,
            world_from_camera: None,
            last_cloud_seq: None,
            last_views: None,
            map_seq: 0,
            published_solid: HashSet::new(),
        })
    }

    /// Integrates a cloud, then plans on the updated map (when the trolley's workspace is known).
    pub fn on_cloud(
        &mut self,
        cloud: &RoiCloud,
        settings: &PlannerSettings,
        method: Method,
    ) -> anyhow::Result<CloudOutcome> {
        let started = Instant::now();
        let seq = cloud.source_frame_seq;
        // A re-announced frame comes back as the same cloud: integrate each frame once.
        if self.last_cloud_seq.is_none_or(|last| seq > last) {
            self.map
                .insert_scan(
                    &cloud.sensor_origin_in_world,
                    &cloud.points_in_world,
                    &cloud.roi,
                )
                .context("cloud rejected by the map")?;
            self.last_cloud_seq = Some(seq);
        }
        let clusters = self.map.clusters(settings.min_cluster_voxels);
        let fruits = self
            .tracker
            .update(&clusters)
            .into_iter()
            .map(|f| Fruit {
                id: f.id,
                centre_in_world: f.centre.cast(),
                box_min: f.min.cast(),
                box_max: f.max.cast(),
                volume_m3: f.volume_m3 as f32,
                voxel_count: f.voxel_count.min(u32::MAX as usize) as u32,
                confidence: f.confidence as f32,
            })
            .collect();
        self.map_seq += 1;
        let mut voxels = Vec::new();
        for (key, voxel) in self.map.take_changes() {
            let change = voxel_change(&self.map, key, voxel);
            let was_solid = if change.state == VoxelState::Free {
                self.published_solid.remove(&key)
            } else {
                self.published_solid.insert(key);
                true
            };
            if was_solid {
                voxels.push(change);
            }
        }
        let map_update = MapUpdate {
            resolution_m: settings.resolution_m as f32,
            map_seq: self.map_seq,
            based_on_seq: seq,
            full: false,
            voxels,
            planner_id: settings.planner_id.clone(),
        };
        let views = match &self.info {
            None => None,
            Some(info) => {
                let origin = cloud.sensor_origin_in_world;
                let world_from_camera = self
                    .world_from_camera
                    .filter(|p| (p.translation.vector - origin.coords).norm() < 0.05)
                    .unwrap_or_else(|| look_along(&origin, &Vector3::x()));
                let ctx = PlanningContext {
                    map: &self.map,
                    world_from_camera,
                    camera_workspace: info.camera_workspace,
                    sampling_region: info.sampling_region,
                };
                let config = PlannerConfig {
                    method,
                    ..PlannerConfig::default()
                };
                let plan_seed = settings
                    .seed
                    .wrapping_mul(0x9E37_79B9_7F4A_7C15)
                    .wrapping_add(seq);
                let plan = plan_views(&ctx, &config, plan_seed)?;
                let views = RankedViews {
                    views: plan
                        .views
                        .iter()
                        .map(|v| RankedView {
                            world_from_camera: v.world_from_camera,
                            utility: v.utility as f32,
                            gain: v.gain as f32,
                            cost_m: v.cost_m as f32,
                            kind: match v.kind {
                                glasshouse_nbv::ViewKind::Roi => ViewKind::Roi,
                                glasshouse_nbv::ViewKind::Exploration => ViewKind::Exploration,
                            },
                        })
                        .collect(),
                    based_on_seq: seq,
                    planning_time_ms: (started.elapsed().as_secs_f64() * 1e3) as f32,
                    planner_id: settings.planner_id.clone(),
                };
                self.last_views = Some(views.clone());
                Some(views)
            }
        };
        Ok(CloudOutcome {
            views,
            fruits: FruitEstimates {
                fruits,
                based_on_seq: seq,
                planner_id: settings.planner_id.clone(),
            },
            map_update,
        })
    }
}

fn voxel_change(map: &RoiMap, key: VoxelKey, voxel: Voxel) -> VoxelChange {
    let state = if map.is_roi(key) {
        VoxelState::Roi
    } else if map.occupancy(key) == Occupancy::Occupied {
        VoxelState::Occupied
    } else {
        VoxelState::Free
    };
    VoxelChange {
        key: [key.x, key.y, key.z],
        occupancy_logodds: voxel.occupancy_logodds,
        roi_logodds: voxel.roi_logodds,
        state,
    }
}

struct Outputs {
    views: TypedPublisher,
    fruits: TypedPublisher,
    map: TypedPublisher,
}

/// Runs the planner until `shutdown` fires.
pub async fn run(
    session: Session,
    settings: PlannerSettings,
    mut shutdown: Shutdown,
    counters: Arc<PlannerCounters>,
) -> anyhow::Result<()> {
    let method = settings.validate()?;
    let pid = settings.planner_id.clone();
    let drops = counters.drops.clone();
    let sub = |topic, delivery| {
        let (session, drops) = (session.clone(), drops.clone());
        async move {
            TypedSubscriber::declare(&session, &keys::all_trolleys(topic), delivery, drops).await
        }
    };
    let clouds = sub(TrolleyTopic::Roi, Delivery::Reliable).await?;
    let infos = sub(TrolleyTopic::Info, Delivery::Reliable).await?;
    let arms = sub(TrolleyTopic::Arm, Delivery::Stream).await?;
    let status_pub = TypedPublisher::declare(
        &session,
        keys::planner_status(&pid)?,
        Delivery::Reliable,
        drops.clone(),
    )
    .await?;
    let _alive = declare_alive(&session, MemberKind::Planner, &pid).await?;
    let mut trolleys: BTreeMap<String, Box<TrolleyPlanner>> = BTreeMap::new();
    let mut outputs: HashMap<String, Outputs> = HashMap::new();
    let mut status_tick =
        tokio::time::interval(Duration::from_millis(settings.status_period_ms.max(50)));
    let (mut last_ms, mut total_ms, mut status_seq) = (0.0f32, 0.0f64, 0u64);
    let settings = Arc::new(settings);
    tracing::info!(planner = %pid, %method, "planner started");

    loop {
        tokio::select! {
            _ = shutdown.wait() => break,
            _ = status_tick.tick() => {
                status_seq += 1;
                let integrated = counters.clouds_integrated.load(Ordering::Relaxed);
                let status = PlannerStatus {
                    planner_id: pid.clone(),
                    owned_trolleys: trolleys.keys().cloned().collect(),
                    standby_trolleys: Vec::new(),
                    clouds_integrated: integrated,
                    views_published: counters.views_published.load(Ordering::Relaxed),
                    last_planning_time_ms: last_ms,
                    mean_planning_time_ms: if integrated > 0 { (total_ms / integrated as f64) as f32 } else { 0.0 },
                    dropped_messages: drops.total() + counters.clouds_rejected.load(Ordering::Relaxed),
                    map_voxels: trolleys.values().map(|t| t.map.len() as u64).sum(),
                };
                let header = Header { seq: status_seq, source_id: pid.clone(), frame_id: "world".into(), ..Header::default() };
                status_pub.publish(&header, &Message::PlannerStatus(status)).await?;
            }
            received = infos.recv() => {
                let Some(Received { header, message: Message::TrolleyInfo(info), .. }) = received else { continue };
                if let Some(t) = trolley_entry(&mut trolleys, &header.trolley_id, &settings) {
                    t.info = Some(info);
                }
            }
            received = arms.recv() => {
                let Some(Received { header, message: Message::ArmState(arm), .. }) = received else { continue };
                if let Some(t) = trolley_entry(&mut trolleys, &header.trolley_id, &settings) {
                    if !arm.moving {
                        t.world_from_camera = Some(arm.world_from_camera);
                    }
                }
            }
            received = clouds.recv() => {
                let Some(Received { header, message: Message::RoiCloud(cloud), .. }) = received else {
                    if received.is_none() { break; }
                    continue;
                };
                let tid = header.trolley_id.clone();
                if trolley_entry(&mut trolleys, &tid, &settings).is_none() {
                    counters.clouds_rejected.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                let Some(mut state) = trolleys.remove(&tid) else { continue };
                let task_settings = settings.clone();
                let (state_back, outcome) = tokio::task::spawn_blocking(move || {
                    let outcome = state.on_cloud(&cloud, &task_settings, method);
                    (state, outcome)
                })
                .await
                .context("planning task failed")?;
                trolleys.insert(tid.clone(), state_back);
                let outcome = match outcome {
                    Ok(o) => o,
                    Err(e) => {
                        counters.clouds_rejected.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!(trolley = %tid, seq = header.seq, error = %e, "cloud dropped");
                        continue;
                    }
                };
                counters.clouds_integrated.fetch_add(1, Ordering::Relaxed);
                let out = match outputs.entry(tid.clone()) {
                    std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
                    std::collections::hash_map::Entry::Vacant(e) => {
                        let declare = |topic| {
                            let (session, drops) = (session.clone(), drops.clone());
                            let key = keys::trolley(&tid, topic);
                            async move { TypedPublisher::declare(&session, key?, Delivery::Reliable, drops).await }
                        };
                        e.insert(Outputs {
                            views: declare(TrolleyTopic::Views).await?,
                            fruits: declare(TrolleyTopic::Fruits).await?,
                            map: declare(TrolleyTopic::Map).await?,
                        })
                    }
                };
                let out_header = Header { seq: header.seq, stamp_ns: header.stamp_ns, trolley_id: tid.clone(), source_id: pid.clone(), frame_id: "world".into() };
                if let Some(views) = outcome.views {
                    last_ms = views.planning_time_ms;
                    total_ms += views.planning_time_ms as f64;
                    tracing::debug!(trolley = %tid, seq = header.seq, views = views.views.len(), ms = views.planning_time_ms, "views planned");
                    out.views.publish(&out_header, &Message::RankedViews(views)).await?;
                    counters.views_published.fetch_add(1, Ordering::Relaxed);
                } else {
                    tracing::info!(trolley = %tid, "no TrolleyInfo yet: cloud integrated, planning deferred");
                }
                out.fruits.publish(&out_header, &Message::FruitEstimates(outcome.fruits)).await?;
                out.map.publish(&out_header, &Message::MapUpdate(outcome.map_update)).await?;
            }
        }
    }
    for (_, o) in outputs.drain() {
        o.views.close().await;
        o.fruits.close().await;
        o.map.close().await;
    }
    status_pub.close().await;
    tracing::info!(planner = %pid, clouds = counters.clouds_integrated.load(Ordering::Relaxed), dropped = drops.total(), "planner stopped");
    Ok(())
}

/// The state of trolley `tid`, created on first contact; `None` for an invalid id.
fn trolley_entry<'a>(
    trolleys: &'a mut BTreeMap<String, Box<TrolleyPlanner>>,
    tid: &str,
    settings: &PlannerSettings,
) -> Option<&'a mut Box<TrolleyPlanner>> {
    if keys::validate_id(tid).is_err() {
        tracing::warn!(trolley = %tid, "message with an invalid trolley id dropped");
        return None;
    }
    if !trolleys.contains_key(tid) {
        let planner = TrolleyPlanner::new(settings).ok()?;
        trolleys.insert(tid.to_owned(), Box::new(planner));
    }
    trolleys.get_mut(tid)
}

/// Centre of a voxel key at a resolution (for consumers of MapUpdate).
pub fn voxel_centre(key: [i32; 3], resolution_m: f64) -> Point3<f64> {
    Point3::new(
        (key[0] as f64 + 0.5) * resolution_m,
        (key[1] as f64 + 0.5) * resolution_m,
        (key[2] as f64 + 0.5) * resolution_m,
    )
}
