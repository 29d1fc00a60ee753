//! The planner as a state machine ([`PlannerNode`]): bus events in, actions out, no I/O.
//!
//! It holds the cluster membership, one [`TrolleyPlanner`] per trolley this planner owns or
//! replicates, and the latest fruits of every trolley for the fleet map. Every decision (who owns
//! a trolley, when to ask for a snapshot, what to do with clouds that arrive meanwhile, when to
//! plan) is made here and tested by feeding events; the driver in `lib.rs` only moves messages.

use std::collections::BTreeMap;
use std::time::Instant;

use glasshouse_fleet::{Assignment, Membership, OwnershipChange, Role};
use glasshouse_pipeline::{ranked_views, PlanningSettings, TrolleyPlanner};
use glasshouse_proto::keys;
use glasshouse_proto::{
    FleetFruits, FruitEstimates, Header, MapSnapshot, MapUpdate, PlannerStatus, RankedViews,
    RoiCloud, TrolleyInfo,
};

use crate::fleet_fruits;

/// Key whose rendezvous winner among the live planners publishes the fleet fruit map.
pub const FLEET_MAP_KEY: &str = "fleet";

/// What reaches the planner.
#[derive(Clone, Debug)]
pub enum PlannerEvent {
    PlannerJoined(String),
    PlannerLeft(String),
    TrolleyJoined(String),
    TrolleyLeft(String),
    /// A detector's ROI cloud of a trolley.
    Cloud {
        header: Header,
        cloud: RoiCloud,
    },
    /// Clouds that queued up while the planner was busy, in arrival order: each is integrated,
    /// and the owner plans once per trolley, on the trolley's last cloud of the batch.
    Clouds(Vec<(Header, RoiCloud)>),
    /// A trolley's workspace and arm.
    Info {
        header: Header,
        info: TrolleyInfo,
    },
    /// A trolley's fruits as its owner published them (for the fleet map).
    Fruits {
        header: Header,
        fruits: FruitEstimates,
    },
    /// The answer to an `AskSnapshot`: the first snapshot a source had, or none.
    SnapshotLoaded {
        tid: String,
        snapshot: Option<Box<MapSnapshot>>,
    },
    /// Another planner asks for this planner's copy of `tid` (query `query_id`).
    SnapshotAsked {
        query_id: u64,
        tid: String,
    },
    /// Time to publish the status; `dropped_messages` is the bus's drop count.
    StatusTick {
        dropped_messages: u64,
    },
}

/// What a trolley's owner publishes.
#[derive(Clone, Debug, PartialEq)]
pub enum TrolleyOutput {
    Views(RankedViews),
    Fruits(FruitEstimates),
    Map(MapUpdate),
}

/// What the driver must do, in order.
#[derive(Clone, Debug, PartialEq)]
pub enum PlannerAction {
    /// Publish on one of the trolley's result keys (declared when first used).
    Publish {
        tid: String,
        header: Header,
        output: TrolleyOutput,
    },
    PublishStatus {
        header: Header,
        status: PlannerStatus,
    },
    PublishFleet {
        header: Header,
        fruits: FleetFruits,
    },
    /// Ask `sources` in turn for a snapshot of `tid`; feed the result as `SnapshotLoaded`.
    AskSnapshot {
        tid: String,
        sources: Vec<String>,
    },
    /// Answer query `query_id`.
    ReplySnapshot {
        query_id: u64,
        answer: Result<(Header, Box<MapSnapshot>), String>,
    },
    /// This planner no longer publishes for `tid`: close its result publishers.
    Release {
        tid: String,
    },
}

/// Counts the driver mirrors into its counters.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PlannerStats {
    pub clouds_integrated: u64,
    /// Clouds that decoded but could not be integrated (e.g. mismatched lengths, bad ids).
    pub clouds_rejected: u64,
    pub views_published: u64,
    pub last_planning_time_ms: f32,
    pub total_planning_time_ms: f64,
    pub plans: u64,
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
    planner: Box<TrolleyPlanner>,
    role: Role,
    sync: SyncState,
    /// The latest cloud: a planner that takes over plans on it at once.
    last_cloud: Option<(Header, RoiCloud)>,
}

/// The planner (see the module docs).
pub struct PlannerNode {
    pid: String,
    planning: PlanningSettings,
    membership: Membership,
    slots: BTreeMap<String, Slot>,
    latest_fruits: BTreeMap<String, FruitEstimates>,
    stats: PlannerStats,
    status_seq: u64,
    /// While a `Clouds` batch is handled: per trolley, its clouds still to come in the batch.
    queued_clouds: BTreeMap<String, usize>,
}

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
pub fn snapshot_sources(change: &OwnershipChange, pid: &str) -> Vec<String> {
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

impl PlannerNode {
    /// A planner that knows only itself; `planning` must be valid.
    pub fn new(pid: &str, planning: PlanningSettings) -> Self {
        let mut membership = Membership::new();
        membership.planner_joined(pid);
        Self {
            pid: pid.to_owned(),
            planning,
            membership,
            slots: BTreeMap::new(),
            latest_fruits: BTreeMap::new(),
            stats: PlannerStats::default(),
            status_seq: 0,
            queued_clouds: BTreeMap::new(),
        }
    }

    pub fn stats(&self) -> PlannerStats {
        self.stats
    }

    /// This planner's role for `tid`, if it holds the trolley.
    pub fn role(&self, tid: &str) -> Option<Role> {
        self.slots.get(tid).map(|s| s.role)
    }

    /// Whether the copy of `tid` waits for a snapshot.
    pub fn is_loading(&self, tid: &str) -> bool {
        matches!(
            self.slots.get(tid).map(|s| &s.sync),
            Some(SyncState::Loading { .. })
        )
    }

    /// This planner's copy of `tid`.
    pub fn planner(&self, tid: &str) -> Option<&TrolleyPlanner> {
        self.slots.get(tid).map(|s| s.planner.as_ref())
    }

    /// Feeds one event; returns what to do.
    pub fn handle(&mut self, event: PlannerEvent) -> Vec<PlannerAction> {
        match event {
            PlannerEvent::PlannerJoined(id) => {
                let changes = self.membership.planner_joined(&id);
                self.apply(&changes)
            }
            // Our own token is ours for as long as we run.
            PlannerEvent::PlannerLeft(id) if id == self.pid => Vec::new(),
            PlannerEvent::PlannerLeft(id) => {
                let changes = self.membership.planner_left(&id);
                self.apply(&changes)
            }
            PlannerEvent::TrolleyJoined(id) => {
                let changes = self.membership.trolley_joined(&id);
                self.apply(&changes)
            }
            // A trolley that goes away (an edge restarting, a link down) keeps its map and its
            // planners: it carries on where it stopped when it comes back.
            PlannerEvent::TrolleyLeft(id) => {
                tracing::info!(planner = %self.pid, trolley = %id, "trolley left; its map is kept");
                Vec::new()
            }
            PlannerEvent::Cloud { header, cloud } => self.on_cloud(header, cloud),
            PlannerEvent::Clouds(clouds) => self.on_clouds(clouds),
            PlannerEvent::Info { header, info } => self.on_info(&header.trolley_id, info),
            PlannerEvent::Fruits { header, fruits } => {
                if keys::validate_id(&header.trolley_id).is_ok() {
                    self.latest_fruits.insert(header.trolley_id, fruits);
                }
                Vec::new()
            }
            PlannerEvent::SnapshotLoaded { tid, snapshot } => self.on_snapshot(&tid, snapshot),
            PlannerEvent::SnapshotAsked { query_id, tid } => vec![PlannerAction::ReplySnapshot {
                query_id,
                answer: self.snapshot_of(&tid),
            }],
            PlannerEvent::StatusTick { dropped_messages } => self.status(dropped_messages),
        }
    }

    /// A trolley heard of for the first time (its cloud or info came before its token).
    fn introduce(&mut self, tid: &str) -> Vec<PlannerAction> {
        if keys::validate_id(tid).is_err() || self.membership.is_trolley_live(tid) {
            return Vec::new();
        }
        let changes = self.membership.trolley_joined(tid);
        self.apply(&changes)
    }

    fn on_info(&mut self, tid: &str, info: TrolleyInfo) -> Vec<PlannerAction> {
        let actions = self.introduce(tid);
        if let Some(slot) = self.slots.get_mut(tid) {
            if let Err(e) = slot.planner.set_info(info) {
                tracing::warn!(planner = %self.pid, trolley = %tid, error = %e, "views are not filtered by reach");
            }
        }
        actions
    }

    fn on_cloud(&mut self, header: Header, cloud: RoiCloud) -> Vec<PlannerAction> {
        let tid = header.trolley_id.clone();
        if keys::validate_id(&tid).is_err() {
            self.stats.clouds_rejected += 1;
            tracing::warn!(trolley = %tid, "cloud with an invalid trolley id dropped");
            return Vec::new();
        }
        let mut actions = self.introduce(&tid);
        let latest = self.queued_clouds.get(&tid).is_none_or(|&n| n == 0);
        let Some(slot) = self.slots.get_mut(&tid) else {
            return actions;
        };
        if let SyncState::Loading { buffered } = &mut slot.sync {
            buffered.push((header, cloud));
            return actions;
        }
        let plan = slot.role == Role::Owner && latest;
        actions.extend(self.integrate(&tid, header, cloud, plan));
        actions
    }

    /// Handles a batch of clouds one by one, so that a trolley's clouds queued behind a later
    /// one are integrated without fits or planning (the edge waits only on its latest frame).
    fn on_clouds(&mut self, clouds: Vec<(Header, RoiCloud)>) -> Vec<PlannerAction> {
        for (header, _) in &clouds {
            *self
                .queued_clouds
                .entry(header.trolley_id.clone())
                .or_default() += 1;
        }
        let mut actions = Vec::new();
        for (header, cloud) in clouds {
            if let Some(n) = self.queued_clouds.get_mut(&header.trolley_id) {
                *n -= 1;
            }
            actions.extend(self.on_cloud(header, cloud));
        }
        self.queued_clouds.clear();
        actions
    }

    /// Takes on, hands over or drops trolleys as the assignment changed; a trolley this planner
    /// now owns with an up-to-date map is planned on at once (the edge may be waiting on the
    /// lost owner's answer).
    fn apply(&mut self, changes: &[OwnershipChange]) -> Vec<PlannerAction> {
        let mut actions = Vec::new();
        for change in changes {
            let pid = &self.pid;
            let tid = change.trolley.clone();
            let before = change.before.as_ref().and_then(|a| a.role_of(pid));
            let after = change.after.as_ref().and_then(|a| a.role_of(pid));
            tracing::info!(planner = %pid, trolley = %tid, before = %describe(&change.before), after = %describe(&change.after), "ownership changed");
            match (after, self.slots.get_mut(&tid)) {
                (None, Some(_)) => {
                    self.slots.remove(&tid);
                    tracing::info!(planner = %pid, trolley = %tid, "trolley released");
                    actions.push(PlannerAction::Release { tid });
                }
                (None, None) => {}
                (Some(role), Some(slot)) => {
                    let took_over = role == Role::Owner && before != Some(Role::Owner);
                    slot.role = role;
                    if role != Role::Owner {
                        actions.push(PlannerAction::Release { tid: tid.clone() });
                    }
                    let live = matches!(slot.sync, SyncState::Live);
                    if took_over {
                        tracing::info!(planner = %pid, trolley = %tid, "took over as owner");
                    }
                    if let (true, true, Some((h, c))) = (took_over, live, slot.last_cloud.clone()) {
                        actions.extend(self.integrate(&tid, h, c, true));
                    }
                }
                (Some(role), None) => actions.extend(self.take_on(change, role)),
            }
        }
        actions
    }

    /// A trolley new to this planner: an empty copy that buffers clouds until a snapshot from
    /// the planners that may hold one is loaded (or none is found).
    fn take_on(&mut self, change: &OwnershipChange, role: Role) -> Vec<PlannerAction> {
        let Ok(planner) = TrolleyPlanner::new(self.planning.clone()) else {
            return Vec::new();
        };
        let tid = change.trolley.clone();
        let slot = Slot {
            planner: Box::new(planner),
            role,
            sync: SyncState::Loading {
                buffered: Vec::new(),
            },
            last_cloud: None,
        };
        self.slots.insert(tid.clone(), slot);
        let sources = snapshot_sources(change, &self.pid);
        vec![PlannerAction::AskSnapshot { tid, sources }]
    }

    fn on_snapshot(&mut self, tid: &str, snapshot: Option<Box<MapSnapshot>>) -> Vec<PlannerAction> {
        let pid = self.pid.clone();
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let SyncState::Loading { buffered } = std::mem::replace(&mut slot.sync, SyncState::Live)
        else {
            return Vec::new();
        };
        if let Some(snapshot) = snapshot {
            match TrolleyPlanner::from_snapshot(self.planning.clone(), &snapshot) {
                Ok(mut loaded) => {
                    tracing::info!(planner = %pid, trolley = %tid, from = %snapshot.planner_id, seq = snapshot.based_on_seq, voxels = loaded.map().len(), "snapshot loaded");
                    if let Some(info) = slot.planner.info() {
                        if let Err(e) = loaded.set_info(info.clone()) {
                            tracing::warn!(planner = %pid, trolley = %tid, error = %e, "views are not filtered by reach");
                        }
                    }
                    *slot.planner = loaded;
                }
                Err(e) => {
                    tracing::warn!(planner = %pid, trolley = %tid, error = %e, "snapshot unusable: starting from the buffered clouds")
                }
            }
        }
        let plan_last = slot.role == Role::Owner;
        let n = buffered.len();
        let mut actions = Vec::new();
        for (i, (header, cloud)) in buffered.into_iter().enumerate() {
            actions.extend(self.integrate(tid, header, cloud, plan_last && i + 1 == n));
        }
        actions
    }

    fn snapshot_of(&self, tid: &str) -> Result<(Header, Box<MapSnapshot>), String> {
        let planner = match self.slots.get(tid) {
            Some(Slot {
                planner,
                sync: SyncState::Live,
                ..
            }) => planner,
            _ => {
                return Err(format!(
                    "planner {} holds no up-to-date map of {tid}",
                    self.pid
                ))
            }
        };
        let snapshot = planner
            .snapshot(tid, &self.pid)
            .map_err(|e| e.to_string())?;
        let header = Header {
            seq: snapshot.based_on_seq,
            trolley_id: tid.to_owned(),
            source_id: self.pid.clone(),
            frame_id: "world".into(),
            ..Header::default()
        };
        tracing::info!(planner = %self.pid, trolley = %tid, "snapshot asked");
        Ok((header, Box::new(snapshot)))
    }

    /// Integrates one cloud into the trolley's copy; with `plan` (the owner), also fits, plans and
    /// publishes. An owner's cloud that is not planned on (a later one is queued) still
    /// publishes its map changes. A replica keeps its map, fruit ids and change tracking exactly
    /// as the owner's.
    fn integrate(
        &mut self,
        tid: &str,
        header: Header,
        cloud: RoiCloud,
        plan: bool,
    ) -> Vec<PlannerAction> {
        let pid = self.pid.clone();
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let started = Instant::now();
        if let Err(e) = slot.planner.integrate(&cloud) {
            self.stats.clouds_rejected += 1;
            tracing::warn!(trolley = %tid, seq = header.seq, error = %e, "cloud dropped");
            return Vec::new();
        }
        self.stats.clouds_integrated += 1;
        let seq = cloud.source_frame_seq;
        let map = slot.planner.map_update(seq, &pid);
        let camera = cloud.world_from_camera;
        slot.last_cloud = Some((header.clone(), cloud));
        if !plan {
            return match slot.role {
                Role::Owner => self.publish(tid, &header, None, None, map),
                Role::Replica => Vec::new(),
            };
        }
        let fruits = FruitEstimates {
            fruits: slot
                .planner
                .fruits()
                .iter()
                .map(|f| f.to_message())
                .collect(),
            based_on_seq: seq,
            planner_id: pid.clone(),
        };
        let views = match slot.planner.plan(&camera, seq) {
            Ok(Some(plan)) => {
                let ms = (started.elapsed().as_secs_f64() * 1e3) as f32;
                Some(ranked_views(&plan, seq, ms, &pid))
            }
            Ok(None) => {
                tracing::info!(trolley = %tid, "no TrolleyInfo yet: cloud integrated, planning deferred");
                None
            }
            Err(e) => {
                tracing::warn!(trolley = %tid, seq, error = %e, "planning failed");
                None
            }
        };
        self.publish(tid, &header, views, Some(fruits), map)
    }

    fn publish(
        &mut self,
        tid: &str,
        cloud_header: &Header,
        views: Option<RankedViews>,
        fruits: Option<FruitEstimates>,
        map: MapUpdate,
    ) -> Vec<PlannerAction> {
        let header = Header {
            seq: cloud_header.seq,
            stamp_ns: cloud_header.stamp_ns,
            trolley_id: tid.to_owned(),
            source_id: self.pid.clone(),
            frame_id: "world".into(),
        };
        let mut outputs = Vec::new();
        if let Some(views) = views {
            let stats = &mut self.stats;
            stats.last_planning_time_ms = views.planning_time_ms;
            stats.total_planning_time_ms += f64::from(views.planning_time_ms);
            stats.plans += 1;
            stats.views_published += 1;
            outputs.push(TrolleyOutput::Views(views));
        }
        outputs.extend(fruits.map(TrolleyOutput::Fruits));
        outputs.push(TrolleyOutput::Map(map));
        let publish = |output| PlannerAction::Publish {
            tid: tid.to_owned(),
            header: header.clone(),
            output,
        };
        outputs.into_iter().map(publish).collect()
    }

    fn status(&mut self, dropped_messages: u64) -> Vec<PlannerAction> {
        self.status_seq += 1;
        let s = self.stats;
        let of_role = |role| {
            let slots = self.slots.iter().filter(move |(_, s)| s.role == role);
            slots.map(|(t, _)| t.clone()).collect()
        };
        let status = PlannerStatus {
            planner_id: self.pid.clone(),
            owned_trolleys: of_role(Role::Owner),
            standby_trolleys: of_role(Role::Replica),
            clouds_integrated: s.clouds_integrated,
            views_published: s.views_published,
            last_planning_time_ms: s.last_planning_time_ms,
            mean_planning_time_ms: if s.plans > 0 {
                (s.total_planning_time_ms / s.plans as f64) as f32
            } else {
                0.0
            },
            dropped_messages: dropped_messages + s.clouds_rejected,
            map_voxels: self
                .slots
                .values()
                .map(|s| s.planner.map().len() as u64)
                .sum(),
        };
        let header = Header {
            seq: self.status_seq,
            source_id: self.pid.clone(),
            frame_id: "world".into(),
            ..Header::default()
        };
        let mut actions = vec![PlannerAction::PublishStatus {
            header: header.clone(),
            status,
        }];
        let live: Vec<String> = self.membership.planners().map(str::to_owned).collect();
        let first = glasshouse_fleet::rank_planners(FLEET_MAP_KEY, &live).first()
            == Some(&self.pid.as_str());
        if first && !self.latest_fruits.is_empty() {
            let fruits = fleet_fruits(&self.latest_fruits, &self.pid);
            actions.push(PlannerAction::PublishFleet { header, fruits });
        }
        actions
    }
}

#[cfg(test)]
mod tests;
