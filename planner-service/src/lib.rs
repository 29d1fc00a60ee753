//! The planner process: ROI maps per trolley, ranked next best views, fruit estimates.
//!
//! Planners form a cluster. From the liveliness tokens of planners and trolleys every planner
//! computes the same assignment ([`glasshouse_fleet`]: rendezvous hashing): each trolley has one
//! *owner* and, with two or more planners, one *replica*. Both keep a [`RoiMap`] of the trolley
//! and integrate each of its RoiClouds; only the owner plans the next views with
//! [`glasshouse_nbv`] (seeded from the planner seed and the frame sequence, so a run replays
//! exactly) and publishes RankedViews, FruitEstimates (box and fitted ellipsoid) and the map's
//! changed voxels (MapUpdate). When the owner is lost the replica already holds the map and takes
//! over; a planner that gains a trolley without a map (a new replica, a late joiner) asks the
//! planners that may hold one for a snapshot (the queryable `gh/planner/{pid}/snapshot/{tid}`),
//! buffers the trolley's clouds meanwhile, loads the snapshot and integrates the buffered clouds
//! newer than it, so no scan is lost. Ownership changes are logged and reported in PlannerStatus.
//!
//! Trolleys stay assigned once seen: a trolley whose token goes away keeps its map and planners.
//!
//! The planner ranked first for the fleet (the rendezvous winner for the key `fleet`) also
//! merges every trolley's fruits into the fleet map on `gh/fleet/fruits`.
//!
//! A cloud that fails to integrate is counted and dropped; the map is never partially updated.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use glasshouse_bus::{
    ask, declare_alive, Delivery, DropCounters, MemberEvent, MemberWatch, Publisher, Received,
    Responder, Shutdown, Subscriber,
};
use glasshouse_fleet::{
    merge_fruits, Assignment, FleetFruitInput, Membership, OwnershipChange, Role,
};
use glasshouse_geom::look_along;
use glasshouse_nbv::fit::{fit_ellipsoid, FitConfig, ShapeKind};
use glasshouse_nbv::{plan_views, FruitTracker, Method, PlannerConfig, PlanningContext};
use glasshouse_proto::keys::{self, MemberKind};
use glasshouse_proto::{
    FittedEllipsoid, FleetFruit, FleetFruits, Fruit, FruitEstimates, Header, MapSnapshot,
    MapUpdate, PlannerStatus, RankedView, RankedViews, RoiCloud, TrackedFruit, TrolleyInfo,
    ViewKind, VoxelChange, VoxelState,
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
    /// The whole-fruit ellipsoid fit published with every fruit.
    pub fit: FitConfig,
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
            fit: FitConfig::default(),
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
    /// The latest cloud with its header: a planner that takes over plans on it at once.
    last_cloud: Option<(Header, RoiCloud)>,
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
            last_cloud: None,
            last_views: None,
            map_seq: 0,
            published_solid: HashSet::new(),
        })
    }

    /// The trolley's state for another planner (the reply to a snapshot query).
    pub fn snapshot(&self, tid: &str, pid: &str) -> anyhow::Result<MapSnapshot> {
        let mut map = Vec::new();
        self.map.write_snapshot(&mut map)?;
        let (tracked, next_fruit_id) = self.tracker.state();
        Ok(MapSnapshot {
            trolley_id: tid.to_owned(),
            planner_id: pid.to_owned(),
            based_on_seq: self.last_cloud_seq.unwrap_or(0),
            map,
            tracked_fruits: tracked
                .into_iter()
                .map(|(id, c)| TrackedFruit {
                    id,
                    centre_in_world: c.cast(),
                })
                .collect(),
            next_fruit_id,
        })
    }

    /// A planner state continuing from another planner's snapshot: its map, fruit ids and last
    /// integrated frame; the voxels it holds count as published (the former owner published them).
    pub fn from_snapshot(
        settings: &PlannerSettings,
        snapshot: &MapSnapshot,
    ) -> anyhow::Result<Self> {
        let map = RoiMap::read_snapshot(snapshot.map.as_slice()).context("map snapshot")?;
        let wanted = settings.map_config();
        anyhow::ensure!(
            map.config().resolution_m == wanted.resolution_m
                && map.config().max_range_m == wanted.max_range_m,
            "snapshot map settings differ from this planner's"
        );
        let mut planner = Self::new(settings)?;
        planner.published_solid = map
            .iter()
            .filter(|(key, voxel)| voxel.occupancy() == Occupancy::Occupied || map.is_roi(*key))
            .map(|(key, _)| key)
            .collect();
        planner.map = map;
        planner.tracker = FruitTracker::from_state(
            snapshot
                .tracked_fruits
                .iter()
                .map(|f| (f.id, f.centre_in_world.cast()))
                .collect(),
            snapshot.next_fruit_id,
        );
        planner.last_cloud_seq = (snapshot.based_on_seq > 0).then_some(snapshot.based_on_seq);
        Ok(planner)
    }

    /// The last frame sequence integrated, if any.
    pub fn last_cloud_seq(&self) -> Option<u64> {
        self.last_cloud_seq
    }

    /// Integrates a cloud, then (`plan`: as the owner) fits the fruits and plans on the updated
    /// map when the trolley's workspace is known. A replica (`plan` false) keeps its map, fruit
    /// ids and change tracking exactly as the owner's, and skips the fits and the planning.
    pub fn on_cloud(
        &mut self,
        cloud: &RoiCloud,
        settings: &PlannerSettings,
        method: Method,
        plan: bool,
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
        let estimates = self.tracker.update(&clusters);
        let fruits = clusters
            .iter()
            .zip(estimates)
            .filter(|_| plan)
            .map(|(cluster, f)| {
                let fitted = fit_ellipsoid(&self.map, cluster, &settings.fit);
                Fruit {
                    id: f.id,
                    centre_in_world: f.centre.cast(),
                    box_min: f.min.cast(),
                    box_max: f.max.cast(),
                    volume_m3: f.volume_m3 as f32,
                    voxel_count: f.voxel_count.min(u32::MAX as usize) as u32,
                    confidence: f.confidence as f32,
                    fitted: Some(FittedEllipsoid {
                        centre_in_world: fitted.centre.cast(),
                        semi_axes_m: fitted.semi_axes_m.cast(),
                        volume_m3: fitted.volume_m3 as f32,
                        box_volume_m3: fitted.box_volume_m3 as f32,
                        confidence: fitted.confidence as f32,
                        is_fit: fitted.kind == ShapeKind::Ellipsoid,
                    }),
                }
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
            _ if !plan => None,
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
    views: Publisher<RankedViews>,
    fruits: Publisher<FruitEstimates>,
    map: Publisher<MapUpdate>,
}

impl Outputs {
    async fn declare(
        session: &Session,
        tid: &str,
        drops: &Arc<DropCounters>,
    ) -> anyhow::Result<Self> {
        Ok(Self {
            views: Publisher::declare(session, &keys::views(tid)?, drops.clone()).await?,
            fruits: Publisher::declare(session, &keys::fruits(tid)?, drops.clone()).await?,
            map: Publisher::declare(session, &keys::map(tid)?, drops.clone()).await?,
        })
    }

    async fn close(self) {
        self.views.close().await;
        self.fruits.close().await;
        self.map.close().await;
    }
}

/// How far this planner's copy of a trolley is.
enum SyncState {
    /// Up to date with the trolley's cloud stream.
    Live,
    /// Waiting for a snapshot; the trolley's clouds are kept until it is loaded.
    Loading { buffered: Vec<(Header, RoiCloud)> },
}

/// A trolley this planner owns or replicates.
struct Slot {
    /// `None` only while a blocking task works on it.
    planner: Option<Box<TrolleyPlanner>>,
    role: Role,
    sync: SyncState,
}

/// Snapshots are asked of each candidate in turn for this long: a row's map is hundreds of MB and
/// takes seconds to write and send; a candidate without the map declines at once.
const SNAPSHOT_TIMEOUT: Duration = Duration::from_secs(30);

/// Key whose rendezvous winner among the live planners publishes the fleet fruit map.
const FLEET_MAP_KEY: &str = "fleet";

fn describe(a: &Option<Assignment>) -> String {
    match a {
        None => "none".into(),
        Some(a) => format!(
            "owner {} replica {}",
            a.owner,
            a.replica.as_deref().unwrap_or("-")
        ),
    }
}

/// Planners that may hold a map of the trolley, most likely first: the owner and replica after
/// the change, then before it; never `pid`.
fn snapshot_sources(change: &OwnershipChange, pid: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for a in [&change.after, &change.before].into_iter().flatten() {
        for p in std::iter::once(&a.owner).chain(a.replica.as_ref()) {
            if p != pid && !out.contains(p) {
                out.push(p.clone());
            }
        }
    }
    out
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
    let clouds = Subscriber::declare(&session, &keys::all_roi(), drops.clone()).await?;
    let infos = Subscriber::declare(&session, &keys::all_info(), drops.clone()).await?;
    let arms = Subscriber::declare(&session, &keys::all_arm(), drops.clone()).await?;
    let fruit_reports = Subscriber::declare_with(
        &session,
        &keys::all_fruits(),
        Delivery::Monitor,
        drops.clone(),
    )
    .await?;
    let planner_watch = MemberWatch::declare(&session, MemberKind::Planner).await?;
    let trolley_watch = MemberWatch::declare(&session, MemberKind::Trolley).await?;
    let snapshots = Responder::declare(&session, &keys::planner_snapshots(&pid)?).await?;
    let status_pub =
        Publisher::declare(&session, &keys::planner_status(&pid)?, drops.clone()).await?;
    let fleet_pub = Publisher::declare(&session, &keys::fleet_fruits(), drops.clone()).await?;
    let _alive = declare_alive(&session, MemberKind::Planner, &pid).await?;
    let mut membership = Membership::new();
    membership.planner_joined(&pid);
    let mut slots: BTreeMap<String, Slot> = BTreeMap::new();
    let mut outputs: HashMap<String, Outputs> = HashMap::new();
    let mut latest_fruits: BTreeMap<String, FruitEstimates> = BTreeMap::new();
    let (snapshot_tx, mut snapshot_rx) =
        tokio::sync::mpsc::unbounded_channel::<(String, Option<MapSnapshot>)>();
    let mut status_tick =
        tokio::time::interval(Duration::from_millis(settings.status_period_ms.max(50)));
    let (mut last_ms, mut total_ms, mut status_seq) = (0.0f32, 0.0f64, 0u64);
    let mut planned = 0u64;
    let settings = Arc::new(settings);
    tracing::info!(planner = %pid, %method, "planner started");

    loop {
        // Membership changes first collect here, then are applied after the select.
        let mut changes: Vec<OwnershipChange> = Vec::new();
        tokio::select! {
            _ = shutdown.wait() => break,
            event = planner_watch.recv() => {
                match event {
                    Some(MemberEvent::Joined(id)) => changes = membership.planner_joined(&id),
                    // Our own token is ours for as long as we run.
                    Some(MemberEvent::Left(id)) if id != pid => changes = membership.planner_left(&id),
                    Some(MemberEvent::Left(_)) => {}
                    None => break,
                }
            }
            event = trolley_watch.recv() => {
                match event {
                    Some(MemberEvent::Joined(id)) => changes = membership.trolley_joined(&id),
                    // A trolley that goes away (an edge restarting, a link down) keeps its map
                    // and its planners: it carries on where it stopped when it comes back.
                    Some(MemberEvent::Left(id)) => tracing::info!(planner = %pid, trolley = %id, "trolley left; its map is kept"),
                    None => break,
                }
            }
            query = snapshots.recv() => {
                let Some(query) = query else { break };
                let tid = match keys::parse(query.key_expr().as_str()) {
                    Some(keys::ParsedKey::PlannerSnapshot { tid, .. }) => tid,
                    _ => {
                        snapshots.reply(&query, Err("not a snapshot key".into())).await;
                        continue;
                    }
                };
                let answer = match slots.get(&tid) {
                    Some(Slot { planner: Some(p), sync: SyncState::Live, .. }) => p
                        .snapshot(&tid, &pid)
                        .map(|m| {
                            let header = Header { seq: m.based_on_seq, trolley_id: tid.clone(), source_id: pid.clone(), frame_id: "world".into(), ..Header::default() };
                            (header, m)
                        })
                        .map_err(|e| e.to_string()),
                    _ => Err(format!("planner {pid} holds no up-to-date map of {tid}")),
                };
                tracing::info!(planner = %pid, trolley = %tid, ok = answer.is_ok(), "snapshot asked");
                snapshots.reply(&query, answer).await;
            }
            loaded = snapshot_rx.recv() => {
                let Some((tid, snapshot)) = loaded else { continue };
                let Some(slot) = slots.get_mut(&tid) else { continue };
                let SyncState::Loading { buffered } = std::mem::replace(&mut slot.sync, SyncState::Live) else { continue };
                if let Some(snapshot) = snapshot {
                    match TrolleyPlanner::from_snapshot(&settings, &snapshot) {
                        Ok(p) => {
                            tracing::info!(planner = %pid, trolley = %tid, from = %snapshot.planner_id, seq = snapshot.based_on_seq, voxels = p.map.len(), "snapshot loaded");
                            slot.planner = Some(Box::new(p));
                        }
                        Err(e) => tracing::warn!(planner = %pid, trolley = %tid, error = %e, "snapshot unusable: starting from the buffered clouds"),
                    }
                }
                let plan_last = slot.role == Role::Owner;
                let n = buffered.len();
                for (i, (header, cloud)) in buffered.into_iter().enumerate() {
                    let plan = plan_last && i + 1 == n;
                    integrate(&session, &pid, &drops, &counters, &settings, method, &mut slots, &mut outputs, &tid, &header, cloud, plan, &mut last_ms, &mut total_ms, &mut planned).await?;
                }
            }
            _ = status_tick.tick() => {
                status_seq += 1;
                let integrated = counters.clouds_integrated.load(Ordering::Relaxed);
                let of_role = |role| slots.iter().filter(|(_, s)| s.role == role).map(|(t, _)| t.clone()).collect();
                let status = PlannerStatus {
                    planner_id: pid.clone(),
                    owned_trolleys: of_role(Role::Owner),
                    standby_trolleys: of_role(Role::Replica),
                    clouds_integrated: integrated,
                    views_published: counters.views_published.load(Ordering::Relaxed),
                    last_planning_time_ms: last_ms,
                    mean_planning_time_ms: if planned > 0 { (total_ms / planned as f64) as f32 } else { 0.0 },
                    dropped_messages: drops.total() + counters.clouds_rejected.load(Ordering::Relaxed),
                    map_voxels: slots.values().filter_map(|s| s.planner.as_ref()).map(|p| p.map.len() as u64).sum(),
                };
                let header = Header { seq: status_seq, source_id: pid.clone(), frame_id: "world".into(), ..Header::default() };
                status_pub.publish(&header, &status).await?;
                let live: Vec<String> = membership.planners().map(str::to_owned).collect();
                if glasshouse_fleet::rank_planners(FLEET_MAP_KEY, &live).first() == Some(&pid.as_str()) && !latest_fruits.is_empty() {
                    let fleet = fleet_fruits(&latest_fruits, &pid);
                    fleet_pub.publish(&header, &fleet).await?;
                }
            }
            received = fruit_reports.recv() => {
                let Some(Received { header, message: f, .. }) = received else { continue };
                if keys::validate_id(&header.trolley_id).is_ok() {
                    latest_fruits.insert(header.trolley_id.clone(), f);
                }
            }
            received = infos.recv() => {
                let Some(Received { header, message: info, .. }) = received else { continue };
                // Info is periodic: it also introduces trolleys whose token we have not seen.
                if keys::validate_id(&header.trolley_id).is_ok() && !membership.is_trolley_live(&header.trolley_id) {
                    changes = membership.trolley_joined(&header.trolley_id);
                }
                if let Some(p) = slots.get_mut(&header.trolley_id).and_then(|s| s.planner.as_mut()) {
                    p.info = Some(info);
                }
            }
            received = arms.recv() => {
                let Some(Received { header, message: arm, .. }) = received else { continue };
                if let Some(p) = slots.get_mut(&header.trolley_id).and_then(|s| s.planner.as_mut()) {
                    if !arm.moving {
                        p.world_from_camera = Some(arm.world_from_camera);
                    }
                }
            }
            received = clouds.recv() => {
                let Some(Received { header, message: cloud, .. }) = received else { break };
                let tid = header.trolley_id.clone();
                if keys::validate_id(&tid).is_err() {
                    counters.clouds_rejected.fetch_add(1, Ordering::Relaxed);
                    tracing::warn!(trolley = %tid, "cloud with an invalid trolley id dropped");
                    continue;
                }
                if !membership.is_trolley_live(&tid) {
                    let joined = membership.trolley_joined(&tid);
                    apply_changes(&joined, &pid, &session, &settings, &mut slots, &mut outputs, &snapshot_tx).await;
                }
                let Some(slot) = slots.get_mut(&tid) else { continue };
                if let SyncState::Loading { buffered } = &mut slot.sync {
                    buffered.push((header, cloud));
                    continue;
                }
                let plan = slot.role == Role::Owner;
                integrate(&session, &pid, &drops, &counters, &settings, method, &mut slots, &mut outputs, &tid, &header, cloud, plan, &mut last_ms, &mut total_ms, &mut planned).await?;
            }
        }
        if !changes.is_empty() {
            let took_over = apply_changes(
                &changes,
                &pid,
                &session,
                &settings,
                &mut slots,
                &mut outputs,
                &snapshot_tx,
            )
            .await;
            // The edge may be waiting for views on a frame the lost owner never answered: plan on
            // the latest cloud now rather than when the edge re-announces it.
            for tid in took_over {
                let last = slots
                    .get(&tid)
                    .and_then(|s| s.planner.as_ref())
                    .and_then(|p| p.last_cloud.clone());
                if let Some((header, cloud)) = last {
                    integrate(
                        &session,
                        &pid,
                        &drops,
                        &counters,
                        &settings,
                        method,
                        &mut slots,
                        &mut outputs,
                        &tid,
                        &header,
                        cloud,
                        true,
                        &mut last_ms,
                        &mut total_ms,
                        &mut planned,
                    )
                    .await?;
                }
            }
        }
    }
    for (_, o) in outputs.drain() {
        o.close().await;
    }
    status_pub.close().await;
    fleet_pub.close().await;
    tracing::info!(planner = %pid, clouds = counters.clouds_integrated.load(Ordering::Relaxed), dropped = drops.total(), "planner stopped");
    Ok(())
}

/// Takes on, hands over or drops trolleys as the assignment changed; logs every change.
async fn apply_changes(
    changes: &[OwnershipChange],
    pid: &str,
    session: &Session,
    settings: &Arc<PlannerSettings>,
    slots: &mut BTreeMap<String, Slot>,
    outputs: &mut HashMap<String, Outputs>,
    snapshot_tx: &tokio::sync::mpsc::UnboundedSender<(String, Option<MapSnapshot>)>,
) -> Vec<String> {
    let mut took_over = Vec::new();
    for change in changes {
        let tid = &change.trolley;
        let before = change.before.as_ref().and_then(|a| a.role_of(pid));
        let after = change.after.as_ref().and_then(|a| a.role_of(pid));
        tracing::info!(planner = %pid, trolley = %tid, before = %describe(&change.before), after = %describe(&change.after), "ownership changed");
        match (after, slots.get_mut(tid)) {
            (None, Some(_)) => {
                slots.remove(tid);
                if let Some(o) = outputs.remove(tid) {
                    o.close().await;
                }
                tracing::info!(planner = %pid, trolley = %tid, "trolley released");
            }
            (None, None) => {}
            (Some(role), Some(slot)) => {
                if role == Role::Owner && before != Some(Role::Owner) {
                    tracing::info!(planner = %pid, trolley = %tid, "took over as owner");
                    if matches!(slot.sync, SyncState::Live) {
                        took_over.push(tid.clone());
                    }
                }
                if role != Role::Owner {
                    if let Some(o) = outputs.remove(tid) {
                        o.close().await;
                    }
                }
                slot.role = role;
            }
            (Some(role), None) => {
                let Ok(planner) = TrolleyPlanner::new(settings) else {
                    continue;
                };
                let sources = snapshot_sources(change, pid);
                slots.insert(
                    tid.clone(),
                    Slot {
                        planner: Some(Box::new(planner)),
                        role,
                        sync: SyncState::Loading {
                            buffered: Vec::new(),
                        },
                    },
                );
                let (session, tid, pid, tx) = (
                    session.clone(),
                    tid.clone(),
                    pid.to_owned(),
                    snapshot_tx.clone(),
                );
                tokio::spawn(async move {
                    let mut loaded = None;
                    for source in sources {
                        let Ok(key) = keys::planner_snapshot(&source, &tid) else {
                            continue;
                        };
                        match ask(&session, &key, SNAPSHOT_TIMEOUT).await {
                            Ok((_, m)) => {
                                loaded = Some(m);
                                break;
                            }
                            Err(e) => {
                                tracing::debug!(planner = %pid, trolley = %tid, %source, error = %e, "no snapshot")
                            }
                        }
                    }
                    let _ = tx.send((tid, loaded));
                });
            }
        }
    }
    took_over
}

/// Integrates one cloud into the trolley's slot; as the owner (`plan`), plans and publishes.
#[allow(clippy::too_many_arguments)]
async fn integrate(
    session: &Session,
    pid: &str,
    drops: &Arc<DropCounters>,
    counters: &Arc<PlannerCounters>,
    settings: &Arc<PlannerSettings>,
    method: Method,
    slots: &mut BTreeMap<String, Slot>,
    outputs: &mut HashMap<String, Outputs>,
    tid: &str,
    header: &Header,
    cloud: RoiCloud,
    plan: bool,
    last_ms: &mut f32,
    total_ms: &mut f64,
    planned: &mut u64,
) -> anyhow::Result<()> {
    let Some(mut state) = slots.get_mut(tid).and_then(|s| s.planner.take()) else {
        return Ok(());
    };
    let task_settings = settings.clone();
    let task_header = header.clone();
    let (state_back, outcome) = tokio::task::spawn_blocking(move || {
        let outcome = state.on_cloud(&cloud, &task_settings, method, plan);
        if outcome.is_ok() {
            state.last_cloud = Some((task_header, cloud));
        }
        (state, outcome)
    })
    .await
    .context("planning task failed")?;
    if let Some(slot) = slots.get_mut(tid) {
        slot.planner = Some(state_back);
    }
    let outcome = match outcome {
        Ok(o) => o,
        Err(e) => {
            counters.clouds_rejected.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(trolley = %tid, seq = header.seq, error = %e, "cloud dropped");
            return Ok(());
        }
    };
    counters.clouds_integrated.fetch_add(1, Ordering::Relaxed);
    if !plan {
        return Ok(());
    }
    let out = match outputs.entry(tid.to_owned()) {
        std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
        std::collections::hash_map::Entry::Vacant(e) => {
            e.insert(Outputs::declare(session, tid, drops).await?)
        }
    };
    let out_header = Header {
        seq: header.seq,
        stamp_ns: header.stamp_ns,
        trolley_id: tid.to_owned(),
        source_id: pid.to_owned(),
        frame_id: "world".into(),
    };
    if let Some(views) = outcome.views {
        *last_ms = views.planning_time_ms;
        *total_ms += views.planning_time_ms as f64;
        *planned += 1;
        tracing::debug!(trolley = %tid, seq = header.seq, views = views.views.len(), ms = views.planning_time_ms, "views planned");
        out.views.publish(&out_header, &views).await?;
        counters.views_published.fetch_add(1, Ordering::Relaxed);
    } else {
        tracing::info!(trolley = %tid, "no TrolleyInfo yet: cloud integrated, planning deferred");
    }
    out.fruits.publish(&out_header, &outcome.fruits).await?;
    out.map.publish(&out_header, &outcome.map_update).await?;
    Ok(())
}

/// Every trolley's latest fruits merged into the fleet map (de-duplicated where rows overlap).
pub fn fleet_fruits(latest: &BTreeMap<String, FruitEstimates>, pid: &str) -> FleetFruits {
    let inputs: Vec<FleetFruitInput> = latest
        .iter()
        .flat_map(|(tid, estimates)| {
            estimates.fruits.iter().map(move |f| FleetFruitInput {
                trolley_id: tid.clone(),
                fruit_id: f.id,
                centre: f.centre_in_world.cast::<f64>().coords.into(),
                min: f.box_min.cast::<f64>().coords.into(),
                max: f.box_max.cast::<f64>().coords.into(),
                volume_m3: f64::from(f.volume_m3),
                confidence: f64::from(f.confidence),
            })
        })
        .collect();
    let merged = merge_fruits(&inputs, glasshouse_fleet::MERGE_DISTANCE_M);
    let fruits = merged
        .fruits
        .into_iter()
        .filter_map(|m| {
            let (tid, fid) = &m.estimate_from;
            let fruit = latest
                .get(tid)?
                .fruits
                .iter()
                .find(|f| f.id == *fid)?
                .clone();
            Some(FleetFruit {
                fleet_id: m.fleet_id,
                fruit,
                sources: m.sources.iter().map(|(t, f)| format!("{t}/{f}")).collect(),
            })
        })
        .collect();
    FleetFruits {
        fruits,
        planner_id: pid.to_owned(),
        trolleys: latest.len() as u32,
    }
}

/// Centre of a voxel key at a resolution (for consumers of MapUpdate).
pub fn voxel_centre(key: [i32; 3], resolution_m: f64) -> Point3<f64> {
    Point3::new(
        (key[0] as f64 + 0.5) * resolution_m,
        (key[1] as f64 + 0.5) * resolution_m,
        (key[2] as f64 + 0.5) * resolution_m,
    )
}
