//! The planner process: ROI maps per trolley, ranked next best views, fruit estimates.
//!
//! Planners form a cluster. From the liveliness tokens of planners and trolleys every planner
//! computes the same assignment ([`glasshouse_fleet`]: rendezvous hashing): each trolley has one
//! *owner* and, with two or more planners, one *replica*. Both keep the trolley's
//! [`glasshouse_pipeline::TrolleyPlanner`] and integrate each of its RoiClouds; only the owner
//! fits the fruits, plans the next views (seeded from the planner seed and the frame sequence, so
//! a run replays exactly) and publishes RankedViews, FruitEstimates and MapUpdate. When the owner
//! is lost the replica already holds the map and takes over; a planner that gains a trolley
//! without a map asks the planners that may hold one for a snapshot (the queryable
//! `gh/planner/{pid}/snapshot/{tid}`), buffers the trolley's clouds meanwhile, loads the snapshot
//! and integrates the buffered clouds newer than it, so no scan is lost.
//!
//! The decisions live in [`node::PlannerNode`] (a state machine without I/O); [`run`] is its
//! driver: it turns bus messages into [`node::PlannerEvent`]s and performs the
//! [`node::PlannerAction`]s. The planner ranked first for the fleet (the rendezvous winner for
//! the key `fleet`) also merges every trolley's fruits into the fleet map on `gh/fleet/fruits`.

pub mod node;

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use glasshouse_bus::{
    ask, declare_alive, reply, Delivery, DropCounters, MemberEvent, MemberWatch, Received,
    Responder, Shutdown, TypedPublisher, TypedSubscriber,
};
use glasshouse_fleet::{merge_fruits, FleetFruitInput};
use glasshouse_geom::look_along;
use glasshouse_pipeline::PlanningSettings;
use glasshouse_proto::keys::{self, MemberKind, TrolleyTopic};
use glasshouse_proto::{FleetFruit, FleetFruits, FruitEstimates, Message, RoiCloud};
use nalgebra::{Isometry3, Vector3};
use node::{PlannerAction, PlannerEvent, PlannerNode, TrolleyOutput};
use serde::Deserialize;
use zenoh::Session;

/// Planner settings; a JSON5 file may set any of them.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlannerSettings {
    /// This planner's id in the cluster (one key chunk).
    pub planner_id: String,
    pub status_period_ms: u64,
    /// Method, seed, map and fit settings (the experiments use the same defaults).
    pub planning: PlanningSettings,
}

impl Default for PlannerSettings {
    fn default() -> Self {
        Self::new("p1")
    }
}

impl PlannerSettings {
    /// A planner with the shared planning defaults, reporting its status every second.
    pub fn new(planner_id: &str) -> Self {
        Self {
            planner_id: planner_id.to_owned(),
            status_period_ms: 1000,
            planning: PlanningSettings::default(),
        }
    }

    pub fn validate(&self) -> anyhow::Result<()> {
        keys::validate_id(&self.planner_id)?;
        self.planning.validate()?;
        Ok(())
    }
}

/// Counters a planner exposes to tests.
#[derive(Debug, Default)]
pub struct PlannerCounters {
    pub drops: Arc<DropCounters>,
    pub clouds_integrated: AtomicU64,
    /// Clouds that decoded but could not be integrated (e.g. mismatched lengths).
    pub clouds_rejected: AtomicU64,
    pub views_published: AtomicU64,
}

/// The camera pose a cloud was captured from.
pub(crate) fn camera_pose_of(cloud: &RoiCloud) -> Isometry3<f64> {
    look_along(&cloud.sensor_origin_in_world, &Vector3::x())
}

/// Snapshots are asked of each candidate in turn for this long: a row's map is hundreds of MB and
/// takes seconds to write and send; a candidate without the map declines at once.
const SNAPSHOT_TIMEOUT: Duration = Duration::from_secs(30);

/// The bus side of a planner: what it listens to.
struct Inputs {
    clouds: TypedSubscriber,
    infos: TypedSubscriber,
    fruit_reports: TypedSubscriber,
    planner_watch: MemberWatch,
    trolley_watch: MemberWatch,
    snapshots: Responder,
    /// Events from tasks the driver started (snapshot answers).
    events: tokio::sync::mpsc::UnboundedReceiver<PlannerEvent>,
    status_tick: tokio::time::Interval,
}

impl Inputs {
    async fn declare(
        session: &Session,
        settings: &PlannerSettings,
        drops: &Arc<DropCounters>,
        events: tokio::sync::mpsc::UnboundedReceiver<PlannerEvent>,
    ) -> anyhow::Result<Self> {
        let sub = |topic, delivery| {
            let (session, drops) = (session.clone(), drops.clone());
            async move {
                TypedSubscriber::declare(&session, &keys::all_trolleys(topic), delivery, drops)
                    .await
            }
        };
        let period = Duration::from_millis(settings.status_period_ms.max(50));
        Ok(Self {
            clouds: sub(TrolleyTopic::Roi, Delivery::Reliable).await?,
            infos: sub(TrolleyTopic::Info, Delivery::Reliable).await?,
            fruit_reports: sub(TrolleyTopic::Fruits, Delivery::Monitor).await?,
            planner_watch: MemberWatch::declare(session, MemberKind::Planner).await?,
            trolley_watch: MemberWatch::declare(session, MemberKind::Trolley).await?,
            snapshots: Responder::declare(session, keys::planner_snapshots(&settings.planner_id)?)
                .await?,
            events,
            status_tick: tokio::time::interval(period),
        })
    }

    /// The next event for the node; None when shutdown fired or an input closed.
    async fn next(&mut self, shutdown: &mut Shutdown, out: &mut Outputs) -> Option<PlannerEvent> {
        loop {
            let event = tokio::select! {
                _ = shutdown.wait() => return None,
                e = self.planner_watch.recv() => match e? {
                    MemberEvent::Joined(id) => PlannerEvent::PlannerJoined(id),
                    MemberEvent::Left(id) => PlannerEvent::PlannerLeft(id),
                },
                e = self.trolley_watch.recv() => match e? {
                    MemberEvent::Joined(id) => PlannerEvent::TrolleyJoined(id),
                    MemberEvent::Left(id) => PlannerEvent::TrolleyLeft(id),
                },
                query = self.snapshots.recv() => match out.snapshot_query(query?).await {
                    Some(event) => event,
                    None => continue,
                },
                e = self.events.recv() => e?,
                _ = self.status_tick.tick() => PlannerEvent::StatusTick { dropped_messages: out.drops.total() },
                r = self.fruit_reports.recv() => match r? {
                    Received { header, message: Message::FruitEstimates(fruits), .. } => PlannerEvent::Fruits { header, fruits },
                    _ => continue,
                },
                r = self.infos.recv() => match r? {
                    Received { header, message: Message::TrolleyInfo(info), .. } => PlannerEvent::Info { header, info },
                    _ => continue,
                },
                r = self.clouds.recv() => match r? {
                    Received { header, message: Message::RoiCloud(cloud), .. } => PlannerEvent::Cloud { header, cloud },
                    _ => continue,
                },
            };
            return Some(event);
        }
    }
}

/// One trolley's result publishers.
struct TrolleyPublishers {
    views: TypedPublisher,
    fruits: TypedPublisher,
    map: TypedPublisher,
}

/// The bus side of a planner: what it publishes and the queries it answers.
struct Outputs {
    session: Session,
    pid: String,
    drops: Arc<DropCounters>,
    status: TypedPublisher,
    fleet: TypedPublisher,
    trolleys: HashMap<String, TrolleyPublishers>,
    queries: HashMap<u64, zenoh::query::Query>,
    next_query: u64,
    events: tokio::sync::mpsc::UnboundedSender<PlannerEvent>,
}

impl Outputs {
    async fn declare(
        session: &Session,
        pid: &str,
        drops: &Arc<DropCounters>,
        events: tokio::sync::mpsc::UnboundedSender<PlannerEvent>,
    ) -> anyhow::Result<Self> {
        let declare =
            |key: String| TypedPublisher::declare(session, key, Delivery::Reliable, drops.clone());
        Ok(Self {
            session: session.clone(),
            pid: pid.to_owned(),
            drops: drops.clone(),
            status: declare(keys::planner_status(pid)?).await?,
            fleet: declare(keys::FLEET_FRUITS.to_owned()).await?,
            trolleys: HashMap::new(),
            queries: HashMap::new(),
            next_query: 0,
            events,
        })
    }

    /// A snapshot query becomes an event; a query on a key that is not a snapshot is refused.
    async fn snapshot_query(&mut self, query: zenoh::query::Query) -> Option<PlannerEvent> {
        match keys::parse(query.key_expr().as_str()) {
            Some(keys::ParsedKey::PlannerSnapshot { tid, .. }) => {
                self.next_query += 1;
                self.queries.insert(self.next_query, query);
                Some(PlannerEvent::SnapshotAsked {
                    query_id: self.next_query,
                    tid,
                })
            }
            _ => {
                reply(&query, Err("not a snapshot key".into())).await;
                None
            }
        }
    }

    async fn trolley(&mut self, tid: &str) -> anyhow::Result<&TrolleyPublishers> {
        if !self.trolleys.contains_key(tid) {
            let declare = |topic| {
                let (session, drops) = (self.session.clone(), self.drops.clone());
                let key = keys::trolley(tid, topic);
                async move { TypedPublisher::declare(&session, key?, Delivery::Reliable, drops).await }
            };
            let publishers = TrolleyPublishers {
                views: declare(TrolleyTopic::Views).await?,
                fruits: declare(TrolleyTopic::Fruits).await?,
                map: declare(TrolleyTopic::Map).await?,
            };
            self.trolleys.insert(tid.to_owned(), publishers);
        }
        self.trolleys.get(tid).context("trolley publishers")
    }

    async fn release(&mut self, tid: &str) {
        if let Some(p) = self.trolleys.remove(tid) {
            for publisher in [p.views, p.fruits, p.map] {
                publisher.close().await;
            }
        }
    }

    /// Asks each source in turn for a snapshot of `tid`; the answer comes back as an event.
    fn ask_snapshot(&self, tid: String, sources: Vec<String>) {
        let (session, pid, tx) = (self.session.clone(), self.pid.clone(), self.events.clone());
        tokio::spawn(async move {
            let mut loaded = None;
            for source in sources {
                let Ok(key) = keys::planner_snapshot(&source, &tid) else {
                    continue;
                };
                match ask(&session, &key, SNAPSHOT_TIMEOUT).await {
                    Ok((_, Message::MapSnapshot(m))) => {
                        loaded = Some(Box::new(m));
                        break;
                    }
                    Ok(_) => {}
                    Err(e) => {
                        tracing::debug!(planner = %pid, trolley = %tid, %source, error = %e, "no snapshot")
                    }
                }
            }
            let _ = tx.send(PlannerEvent::SnapshotLoaded {
                tid,
                snapshot: loaded,
            });
        });
    }

    async fn perform(&mut self, action: PlannerAction) -> anyhow::Result<()> {
        match action {
            PlannerAction::Publish {
                tid,
                header,
                output,
            } => {
                let p = self.trolley(&tid).await?;
                let (publisher, message) = match output {
                    TrolleyOutput::Views(v) => (&p.views, Message::RankedViews(v)),
                    TrolleyOutput::Fruits(f) => (&p.fruits, Message::FruitEstimates(f)),
                    TrolleyOutput::Map(m) => (&p.map, Message::MapUpdate(m)),
                };
                publisher.publish(&header, &message).await?;
            }
            PlannerAction::PublishStatus { header, status } => {
                let message = Message::PlannerStatus(status);
                self.status.publish(&header, &message).await?;
            }
            PlannerAction::PublishFleet { header, fruits } => {
                let message = Message::FleetFruits(fruits);
                self.fleet.publish(&header, &message).await?;
            }
            PlannerAction::AskSnapshot { tid, sources } => self.ask_snapshot(tid, sources),
            PlannerAction::ReplySnapshot { query_id, answer } => {
                if let Some(query) = self.queries.remove(&query_id) {
                    let answer = answer.map(|(h, m)| (h, Message::MapSnapshot(*m)));
                    reply(&query, answer).await;
                }
            }
            PlannerAction::Release { tid } => self.release(&tid).await,
        }
        Ok(())
    }

    async fn close(mut self) {
        let tids: Vec<String> = self.trolleys.keys().cloned().collect();
        for tid in tids {
            self.release(&tid).await;
        }
        self.status.close().await;
        self.fleet.close().await;
    }
}

/// Runs the planner until `shutdown` fires.
pub async fn run(
    session: Session,
    settings: PlannerSettings,
    mut shutdown: Shutdown,
    counters: Arc<PlannerCounters>,
) -> anyhow::Result<()> {
    settings.validate()?;
    let pid = settings.planner_id.clone();
    let drops = counters.drops.clone();
    let (events_tx, events_rx) = tokio::sync::mpsc::unbounded_channel();
    let mut inputs = Inputs::declare(&session, &settings, &drops, events_rx).await?;
    let mut out = Outputs::declare(&session, &pid, &drops, events_tx).await?;
    let _alive = declare_alive(&session, MemberKind::Planner, &pid).await?;
    let mut node = Box::new(PlannerNode::new(&pid, settings.planning.clone()));
    tracing::info!(planner = %pid, method = %settings.planning.method, "planner started");
    while let Some(event) = inputs.next(&mut shutdown, &mut out).await {
        // Integration, fits and planning are heavy: the node works on a blocking thread.
        let (back, actions) = tokio::task::spawn_blocking(move || {
            let actions = node.handle(event);
            (node, actions)
        })
        .await
        .context("planner task failed")?;
        node = back;
        let stats = node.stats();
        counters
            .clouds_integrated
            .store(stats.clouds_integrated, Ordering::Relaxed);
        counters
            .clouds_rejected
            .store(stats.clouds_rejected, Ordering::Relaxed);
        counters
            .views_published
            .store(stats.views_published, Ordering::Relaxed);
        for action in actions {
            out.perform(action).await?;
        }
    }
    out.close().await;
    tracing::info!(planner = %pid, clouds = node.stats().clouds_integrated, dropped = drops.total(), "planner stopped");
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
