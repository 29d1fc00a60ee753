//! The planner process: ROI maps per trolley, ranked next best views, fruit estimates.
//!
//! Planners form a cluster. From the liveliness tokens of planners and trolleys every planner
//! computes the same assignment ([`glasshouse_fleet`]: rendezvous hashing): each trolley has one
//! *owner* and, with two or more planners, one *replica*. The owner keeps the trolley's
//! [`glasshouse_pipeline::TrolleyPlanner`], integrates each of its RoiClouds, fits the fruits,
//! plans the next views (seeded from the planner seed and the frame sequence, so a run replays
//! exactly) and publishes RankedViews, FruitEstimates and MapUpdate. The replica stands by: it
//! keeps the clouds, and every few clouds loads a snapshot of the owner's map and drops the
//! clouds it holds. When the owner is lost the replica integrates the clouds it kept and takes
//! over with the owner's map (`replica_refresh_clouds: 0` makes it integrate every cloud
//! instead); a planner that gains a trolley
//! without a map asks the planners that may hold one for a snapshot (the queryable
//! `gh/planner/{pid}/snapshot/{tid}`), buffers the trolley's clouds meanwhile, loads the snapshot
//! and integrates the buffered clouds newer than it, so no scan is lost.
//!
//! Every ownership term has an epoch (a fencing token, [`glasshouse_fleet::epoch`]) that the
//! owner's outputs carry: receivers drop what a replaced owner still sends, and an owner that
//! sees a newer epoch than its own (it was paused or cut off while another planner took over)
//! catches up from a snapshot before it plans again.
//!
//! The decisions live in [`node::PlannerNode`] (a state machine without I/O); [`run`] is its
//! driver: it turns bus messages into [`node::PlannerEvent`]s and performs the
//! [`node::PlannerAction`]s. The planner ranked first for the fleet (the rendezvous winner for
//! the key `fleet`) also merges every trolley's fruits into the fleet map on `gh/fleet/fruits`.

mod decoder;
mod held;
pub mod metrics;
pub mod node;
mod registration;
mod slot;
pub mod storage;

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use glasshouse_bus::{
    ask_with, declare_alive, wall_clock_ns, Delivery, DropCounters, MemberEvent, MemberWatch,
    Publisher, Received, Responder, Shutdown, Subscriber,
};
use glasshouse_fleet::{merge_fruits, TrolleyFruit};
use glasshouse_pipeline::PlanningSettings;
use glasshouse_proto::keys::{self, MemberKind};
use glasshouse_proto::{
    FleetFruit, FleetFruits, FruitEstimates, Header, MapSnapshot, MapUpdate, PlannerStatus,
    RankedViews, RoiCloud, StageTimes, TrolleyInfo,
};
use held::Held;
use node::{
    DeltaBase, KeyedCloud, PlannerAction, PlannerEvent, PlannerNode, StoreRules, StoreWrite,
    TrolleyOutput,
};
use serde::Deserialize;
use zenoh::Session;

/// Planner settings; a JSON5 file may set any of them.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlannerSettings {
    /// This planner's id in the cluster (one key chunk).
    pub planner_id: String,
    pub status_period_ms: u64,
    /// A replica stands by with this many of the trolley's clouds before it asks the owner for
    /// a snapshot (a takeover integrates at most this many); 0: it integrates every cloud.
    pub replica_refresh_clouds: usize,
    /// Snapshots of trolleys taken over together (a lost planner's) decoded at once, a thread
    /// each, before the first is planned on; 1 decodes each at its own catch-up.
    pub takeover_decode_threads: usize,
    /// A standby replica decodes each snapshot it holds in the background, on a thread of the
    /// idle scheduling class, so a takeover adopts the decoded copy instead of decoding (it costs
    /// the decoded map's memory beside the snapshot, and a decode per refresh on idle cores).
    pub standby_decoded_ahead: bool,
    /// A standby replica with a decoded copy asks its owner for only the map's blocks changed
    /// since (a delta), so neither the owner's answer nor the copy's update follows the map's
    /// size; false asks for the whole map every time.
    pub refresh_by_delta: bool,
    /// Method, seed, map and fit settings (the experiments use the same defaults).
    pub planning: PlanningSettings,
    /// Where the planner keeps the trolleys it owns, so that they outlive it (none: in memory
    /// only).
    pub store: Option<StoreSettings>,
}

/// The planner's store: every trolley it owns, kept so that a restart loses no integrated
/// scan and no fruit id.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StoreSettings {
    /// The database file (created with its folders). Each planner has its own: a file is
    /// locked by the planner that opened it.
    pub path: PathBuf,
    /// Clouds logged between two checkpoints of a trolley's map (each checkpoint writes the
    /// blocks changed since the last).
    pub checkpoint_clouds: usize,
    /// How long after its start the planner waits for its peers before it takes on trolleys,
    /// so that after a full restart each trolley goes on from the newest copy any store holds.
    pub settle_ms: u64,
    /// Fault injection: every store transaction (the writes queued meanwhile, together) waits
    /// this long first, as on a slow or overloaded disk (benchmarks and tests; 0 in deployment).
    pub write_delay_ms: u64,
}

impl Default for StoreSettings {
    fn default() -> Self {
        Self {
            path: PathBuf::from("glasshouse-planner.redb"),
            checkpoint_clouds: node::REPLICA_REFRESH_CLOUDS,
            settle_ms: 3000,
            write_delay_ms: 0,
        }
    }
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
            replica_refresh_clouds: node::REPLICA_REFRESH_CLOUDS,
            takeover_decode_threads: node::TAKEOVER_DECODE_THREADS,
            standby_decoded_ahead: true,
            refresh_by_delta: true,
            // A planner has the machine's cores for itself and its trolleys' clouds: one
            // cloud's rays are cast, and the clusters it changed fitted, on all of them (the
            // experiments run trials side by side and keep the shared default, one).
            planning: PlanningSettings {
                insert_threads: 0,
                fit_threads: 0,
                ..PlanningSettings::default()
            },
            store: None,
        }
    }

    pub fn validate(&self) -> anyhow::Result<()> {
        keys::validate_id(&self.planner_id)?;
        self.planning.validate()?;
        anyhow::ensure!(
            self.takeover_decode_threads > 0,
            "takeover_decode_threads: at least 1 (1 decodes each trolley taken over in turn)"
        );
        if let Some(store) = &self.store {
            anyhow::ensure!(
                !store.path.as_os_str().is_empty(),
                "store.path: a file name is needed"
            );
            anyhow::ensure!(
                store.checkpoint_clouds > 0,
                "store.checkpoint_clouds: at least 1 (clouds logged between two checkpoints)"
            );
            anyhow::ensure!(
                store.write_delay_ms <= 60_000,
                "store.write_delay_ms: at most 60000 (a fault injected for tests, 0 in deployment)"
            );
        }
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
    /// Clouds refused: not from a live detector, or a frame no trolley sends (see
    /// [`node::PlannerNode`]).
    pub clouds_refused: AtomicU64,
    pub views_published: AtomicU64,
    /// The last status the planner published (its roles, map size and registrations).
    pub status: std::sync::Mutex<Option<PlannerStatus>>,
    /// Each cloud's time per stage.
    pub stage_seconds: metrics::StageHistograms,
    /// Map snapshot bytes sent to planners taking a trolley over.
    pub snapshot_bytes_sent: AtomicU64,
    /// Standby refreshes answered with a delta, and owners' deltas applied here
    /// ([`node::DeltaBase`]).
    pub snapshot_deltas_sent: AtomicU64,
    pub snapshot_deltas_applied: AtomicU64,
    /// Store writes performed, their bytes (keys and values) and the writes that failed.
    pub store_writes: AtomicU64,
    pub store_bytes_written: AtomicU64,
    pub store_errors: AtomicU64,
    /// Store transactions committed (writes queued together share one).
    pub store_transactions: AtomicU64,
    /// Views, fruits and map updates that waited for their cloud's store write before they went
    /// out (the planner went on with other events meanwhile).
    pub publications_held: AtomicU64,
}

/// The snapshot query's parameter that carries a standby copy's [`DeltaBase`].
const DELTA_BASE_PARAMETER: &str = "base";

/// The selector parameters of a standby copy's snapshot query on `base`.
pub fn snapshot_query_parameters(base: &DeltaBase) -> String {
    format!("{DELTA_BASE_PARAMETER}={}", base.to_parameter())
}

/// The base a snapshot query names ([`snapshot_query_parameters`]); a missing or malformed
/// one is none, and the whole map is sent.
pub fn delta_base_of(query: &zenoh::query::Query) -> Option<DeltaBase> {
    query
        .parameters()
        .get(DELTA_BASE_PARAMETER)
        .and_then(DeltaBase::parse)
}

/// Snapshots are asked of each candidate in turn for this long: a row's map is hundreds of MB and
/// takes seconds to write and send; a candidate without the map declines at once.
const SNAPSHOT_TIMEOUT: Duration = Duration::from_secs(30);

/// The bus side of a planner: what it listens to.
struct Inputs {
    clouds: Subscriber<RoiCloud>,
    infos: Subscriber<TrolleyInfo>,
    fruit_reports: Subscriber<FruitEstimates>,
    planner_watch: MemberWatch,
    trolley_watch: MemberWatch,
    detector_watch: MemberWatch,
    snapshots: Responder<MapSnapshot>,
    /// Snapshot queries waiting for the node's answer.
    queries: HashMap<u64, zenoh::query::Query>,
    next_query: u64,
    /// Events from tasks the driver started (snapshot answers).
    events: tokio::sync::mpsc::UnboundedReceiver<PlannerEvent>,
    status_tick: tokio::time::Interval,
    /// Wakes when a store write is done (none without a store, or once the writer stopped).
    stored: Option<tokio::sync::watch::Receiver<u64>>,
}

/// What woke the driver: an event for the node, or store writes done (held publications may
/// go out).
enum Wake {
    Event(Box<PlannerEvent>),
    Stored,
}

/// Waits until a store write is done; when the writer has stopped, wakes once more and then
/// never again.
async fn stored(watch: &mut Option<tokio::sync::watch::Receiver<u64>>) {
    let closed = match watch.as_mut() {
        Some(rx) => rx.changed().await.is_err(),
        None => std::future::pending().await,
    };
    if closed {
        *watch = None;
    }
}

impl Inputs {
    async fn declare(
        session: &Session,
        settings: &PlannerSettings,
        drops: &Arc<DropCounters>,
        events: tokio::sync::mpsc::UnboundedReceiver<PlannerEvent>,
    ) -> anyhow::Result<Self> {
        let period = Duration::from_millis(settings.status_period_ms.max(50));
        let snapshots_key = keys::planner_snapshots(&settings.planner_id)?;
        Ok(Self {
            clouds: Subscriber::declare(session, &keys::all_roi(), drops.clone()).await?,
            infos: Subscriber::declare(session, &keys::all_info(), drops.clone()).await?,
            fruit_reports: Subscriber::declare_with(
                session,
                &keys::all_fruits(),
                Delivery::Monitor,
                drops.clone(),
            )
            .await?,
            planner_watch: MemberWatch::declare(session, MemberKind::Planner).await?,
            trolley_watch: MemberWatch::declare(session, MemberKind::Trolley).await?,
            detector_watch: MemberWatch::declare(session, MemberKind::Detector).await?,
            snapshots: Responder::declare(session, &snapshots_key).await?,
            queries: HashMap::new(),
            next_query: 0,
            events,
            status_tick: tokio::time::interval(period),
            stored: None,
        })
    }

    /// The next event for the node, or store writes done; None when shutdown fired or an input
    /// closed.
    async fn next(&mut self, shutdown: &mut Shutdown, drops: &DropCounters) -> Option<Wake> {
        // The node's own events first: a trolley taken over catches up before the clouds that
        // queued meanwhile (a batch of them integrated first held each further trolley taken
        // over back by their integration, about 0.75 s each on a loaded two-core machine).
        if let Ok(event) = self.events.try_recv() {
            return Some(Wake::Event(Box::new(event)));
        }
        loop {
            let event = tokio::select! {
                _ = shutdown.wait() => return None,
                _ = stored(&mut self.stored) => return Some(Wake::Stored),
                e = self.planner_watch.recv() => match e? {
                    MemberEvent::Joined(id) => PlannerEvent::PlannerJoined(id),
                    MemberEvent::Left(id) => PlannerEvent::PlannerLeft(id),
                },
                e = self.trolley_watch.recv() => match e? {
                    MemberEvent::Joined(id) => PlannerEvent::TrolleyJoined(id),
                    MemberEvent::Left(id) => PlannerEvent::TrolleyLeft(id),
                },
                e = self.detector_watch.recv() => match e? {
                    MemberEvent::Joined(id) => PlannerEvent::DetectorJoined(id),
                    MemberEvent::Left(id) => PlannerEvent::DetectorLeft(id),
                },
                query = self.snapshots.recv() => match self.snapshot_query(query?).await {
                    Some(event) => event,
                    None => continue,
                },
                e = self.events.recv() => e?,
                _ = self.status_tick.tick() => PlannerEvent::StatusTick { dropped_messages: drops.total(), now_ns: wall_clock_ns() },
                r = self.fruit_reports.recv() => {
                    let Received { header, message, .. } = r?;
                    PlannerEvent::Fruits { header, fruits: message }
                }
                r = self.infos.recv() => {
                    let Received { header, message, .. } = r?;
                    PlannerEvent::Info { header, info: message }
                }
                r = self.clouds.recv() => {
                    // Clouds that queued up while the node was busy go in as one batch: each is
                    // integrated, each trolley planned once, on its latest.
                    let first = r?;
                    // The batch is as old as its first cloud: a cloud's wait in the queue
                    // counts from there (the step's `waited_ms`).
                    let waited_ns = first.arrived_at.elapsed().as_nanos() as u64;
                    let mut clouds = vec![keyed(first)];
                    while let Some(received) = self.clouds.try_recv() {
                        clouds.push(keyed(received));
                    }
                    PlannerEvent::Clouds {
                        clouds,
                        received_ns: wall_clock_ns().saturating_sub(waited_ns),
                    }
                }
            };
            return Some(Wake::Event(Box::new(event)));
        }
    }
}

/// A received cloud with the detector its key names (empty when the key names none: refused).
fn keyed(received: Received<RoiCloud>) -> KeyedCloud {
    KeyedCloud {
        sender: keys::sender(&received.key).unwrap_or_default().to_owned(),
        header: received.header,
        cloud: received.message,
    }
}

impl Inputs {
    /// A snapshot query becomes an event; a query on a key that is not a snapshot is refused.
    async fn snapshot_query(&mut self, query: zenoh::query::Query) -> Option<PlannerEvent> {
        match keys::parse(query.key_expr().as_str()) {
            Some(keys::ParsedKey::PlannerSnapshot { tid, .. }) => {
                let base = delta_base_of(&query);
                self.next_query += 1;
                self.queries.insert(self.next_query, query);
                Some(PlannerEvent::SnapshotAsked {
                    query_id: self.next_query,
                    tid,
                    base,
                })
            }
            _ => {
                let refusal = Err("not a snapshot key".to_string());
                self.snapshots.reply(&query, refusal).await;
                None
            }
        }
    }

    /// Answers query `query_id` (the node's `ReplySnapshot`).
    /// Answers a snapshot query; the snapshot bytes sent.
    async fn reply(
        &mut self,
        query_id: u64,
        answer: Result<(Header, Box<MapSnapshot>), String>,
    ) -> usize {
        match self.queries.remove(&query_id) {
            Some(query) => {
                let answer = answer.map(|(header, snapshot)| (header, *snapshot));
                self.snapshots.reply(&query, answer).await
            }
            None => 0,
        }
    }
}

/// One trolley's result publishers.
struct TrolleyPublishers {
    views: Publisher<RankedViews>,
    fruits: Publisher<FruitEstimates>,
    map: Publisher<MapUpdate>,
}

/// Store writes queued but not yet done beyond which the planner waits for its disk: a disk
/// slower than the clouds come must slow the planner down (its inputs then drop the oldest
/// clouds, counted) rather than grow the writer's queue without bound.
const STORE_WRITES_IN_FLIGHT: u64 = 32;

/// The bus side of a planner: what it publishes and the snapshots it asks for.
struct Outputs {
    session: Session,
    pid: String,
    drops: Arc<DropCounters>,
    status: Publisher<PlannerStatus>,
    fleet: Publisher<FleetFruits>,
    trolleys: HashMap<String, TrolleyPublishers>,
    events: tokio::sync::mpsc::UnboundedSender<PlannerEvent>,
    store: Option<storage::StoreWriter>,
    /// Publications waiting for their cloud's store write.
    held: Held<(Header, TrolleyOutput)>,
    counters: Arc<PlannerCounters>,
    decoder: Option<decoder::StandbyDecoder>,
}

impl Outputs {
    async fn declare(
        session: &Session,
        pid: &str,
        counters: &Arc<PlannerCounters>,
        events: tokio::sync::mpsc::UnboundedSender<PlannerEvent>,
    ) -> anyhow::Result<Self> {
        let drops = &counters.drops;
        Ok(Self {
            session: session.clone(),
            pid: pid.to_owned(),
            drops: drops.clone(),
            status: Publisher::declare(session, &keys::planner_status(pid)?, drops.clone()).await?,
            fleet: Publisher::declare(session, &keys::fleet_fruits(), drops.clone()).await?,
            trolleys: HashMap::new(),
            events,
            store: None,
            held: Held::default(),
            counters: counters.clone(),
            decoder: None,
        })
    }

    async fn trolley(&mut self, tid: &str) -> anyhow::Result<&TrolleyPublishers> {
        if !self.trolleys.contains_key(tid) {
            let (session, drops) = (&self.session, &self.drops);
            // Views under this planner's own id: the router lets no other identity put there.
            let views = keys::views(tid, &self.pid)?;
            let publishers = TrolleyPublishers {
                views: Publisher::declare(session, &views, drops.clone()).await?,
                fruits: Publisher::declare(session, &keys::fruits(tid)?, drops.clone()).await?,
                map: Publisher::declare(session, &keys::map(tid)?, drops.clone()).await?,
            };
            self.trolleys.insert(tid.to_owned(), publishers);
        }
        self.trolleys.get(tid).context("trolley publishers")
    }

    async fn release(&mut self, tid: &str) {
        if let Some(p) = self.trolleys.remove(tid) {
            p.views.close().await;
            p.fruits.close().await;
            p.map.close().await;
        }
    }

    /// Asks each source in turn for a snapshot of `tid`; the answer comes back as an event.
    fn ask_snapshot(&self, tid: String, sources: Vec<String>, base: Option<DeltaBase>) {
        let (session, pid, tx) = (self.session.clone(), self.pid.clone(), self.events.clone());
        let parameters = base
            .as_ref()
            .map_or_else(String::new, snapshot_query_parameters);
        tokio::spawn(async move {
            let mut loaded = None;
            for source in sources {
                let Ok(key) = keys::planner_snapshot(&source, &tid) else {
                    continue;
                };
                match ask_with(&session, &key, &parameters, SNAPSHOT_TIMEOUT).await {
                    Ok((_, snapshot)) => {
                        loaded = Some(Box::new(snapshot));
                        break;
                    }
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

    /// Queues a store write; a cloud's holds its trolley's next publications. When the disk
    /// falls [`STORE_WRITES_IN_FLIGHT`] writes behind, waits for it first (what the writer
    /// queues is held in memory).
    async fn queue_store(&mut self, write: StoreWrite) {
        let Some(store) = &mut self.store else {
            return;
        };
        if let Some(behind) = store.queued().checked_sub(STORE_WRITES_IN_FLIGHT) {
            store.wait_durable(behind).await;
        }
        let cloud_of = match &write {
            StoreWrite::Cloud { tid, .. } => Some(tid.clone()),
            _ => None,
        };
        if let (Some(seq), Some(tid)) = (store.queue(write), cloud_of) {
            self.held.cloud_queued(&tid, seq);
        }
    }

    /// Store writes done, in queue order (all without a store).
    fn durable_through(&self) -> u64 {
        self.store
            .as_ref()
            .map_or(u64::MAX, storage::StoreWriter::durable_through)
    }

    /// Publishes `output` of `tid` now if the cloud it follows is durable, else holds it.
    async fn publish_when_stored(
        &mut self,
        tid: String,
        header: Header,
        output: TrolleyOutput,
    ) -> anyhow::Result<()> {
        let durable = self.durable_through();
        match self.held.pass_or_hold(&tid, (header, output), durable) {
            Some((header, output)) => self.publish(&tid, &header, output).await,
            None => {
                self.counters
                    .publications_held
                    .fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
        }
    }

    /// Publishes what was held for store writes now durable.
    async fn publish_stored(&mut self) -> anyhow::Result<()> {
        let durable = self.durable_through();
        for (tid, (header, output)) in self.held.release(durable) {
            self.publish(&tid, &header, output).await?;
        }
        Ok(())
    }

    /// Before `tid`'s publishers go: waits for its clouds' writes and publishes what they held.
    async fn flush(&mut self, tid: &str) -> anyhow::Result<()> {
        if let (Some(seq), Some(store)) = (self.held.last_cloud(tid), &self.store) {
            store.wait_durable(seq).await;
        }
        self.held.forget(tid);
        self.publish_stored().await
    }

    async fn publish(
        &mut self,
        tid: &str,
        header: &Header,
        output: TrolleyOutput,
    ) -> anyhow::Result<()> {
        let p = self.trolley(tid).await?;
        match output {
            TrolleyOutput::Views(v) => p.views.publish(header, &v).await?,
            TrolleyOutput::Fruits(f) => p.fruits.publish(header, &f).await?,
            TrolleyOutput::Map(m) => p.map.publish(header, &m).await?,
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

/// Performs one of the node's actions; the snapshot bytes it sent (0 for every other action).
async fn perform(
    action: PlannerAction,
    inputs: &mut Inputs,
    out: &mut Outputs,
) -> anyhow::Result<u64> {
    match action {
        PlannerAction::Publish {
            tid,
            header,
            output,
        } => out.publish_when_stored(tid, header, output).await?,
        PlannerAction::PublishStatus { header, status } => {
            out.status.publish(&header, &status).await?
        }
        PlannerAction::PublishFleet { header, fruits } => {
            out.fleet.publish(&header, &fruits).await?
        }
        PlannerAction::AskSnapshot { tid, sources, base } => out.ask_snapshot(tid, sources, base),
        PlannerAction::ReplySnapshot { query_id, answer } => {
            return Ok(inputs.reply(query_id, answer).await as u64);
        }
        PlannerAction::Release { tid } => {
            out.flush(&tid).await?;
            out.release(&tid).await
        }
        PlannerAction::CatchUp { tid } => {
            // Back into the event queue: the node picks it up after what is already waiting.
            let _ = out.events.send(PlannerEvent::CatchUp { tid });
        }
        PlannerAction::Finish { tid } => {
            let _ = out.events.send(PlannerEvent::Finish { tid });
        }
        PlannerAction::NextCloud => {
            let _ = out.events.send(PlannerEvent::NextCloud);
        }
        PlannerAction::Store(write) => out.queue_store(write).await,
        PlannerAction::DecodeAhead { tid, snapshot } => {
            if let Some(decoder) = &out.decoder {
                decoder.decode(tid, snapshot);
            }
        }
    }
    Ok(0)
}

/// Opens the store and hands the node what it holds (decoding every map takes a while: a
/// blocking thread).
async fn open_store(
    settings: &StoreSettings,
    node: Box<PlannerNode>,
    pid: &str,
) -> anyhow::Result<(Box<PlannerNode>, storage::PlannerStore)> {
    let path = settings.path.clone();
    let rules = StoreRules {
        checkpoint_clouds: settings.checkpoint_clouds,
        settle_ns: settings.settle_ms.saturating_mul(1_000_000),
    };
    let pid = pid.to_owned();
    tokio::task::spawn_blocking(move || {
        let started = std::time::Instant::now();
        let store = storage::PlannerStore::open(&path)?;
        let loaded = store.load()?;
        let mut node = Box::new(node.with_store(rules));
        for line in &loaded.unreadable {
            tracing::error!(planner = %pid, record = %line, "store record unreadable: left out");
        }
        let trolleys = loaded.trolleys.len();
        for line in node.restore(loaded.trolleys, loaded.fruits) {
            tracing::error!(planner = %pid, trolley = %line, "stored trolley not restored: left out");
        }
        tracing::info!(planner = %pid, path = %path.display(), trolleys, restore_ms = started.elapsed().as_secs_f64() * 1e3, "store opened");
        Ok((node, store))
    })
    .await
    .context("store task failed")?
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
    let mut out = Outputs::declare(&session, &pid, &counters, events_tx).await?;
    let _alive = declare_alive(&session, MemberKind::Planner, &pid).await?;
    let mut node = start_node(&settings, &mut out, &counters).await?;
    inputs.stored = out.store.as_ref().map(storage::StoreWriter::durable_watch);
    tracing::info!(planner = %pid, method = %settings.planning.method, "planner started");
    while let Some(wake) = inputs.next(&mut shutdown, &drops).await {
        match wake {
            Wake::Event(event) => {
                node = step(node, *event, &mut inputs, &mut out, &counters).await?
            }
            Wake::Stored => out.publish_stored().await?,
        }
    }
    if let Some(store) = out.store.take() {
        // The writes still queued are done before the planner stops, then what they held goes.
        if let Err(e) = tokio::task::spawn_blocking(move || store.close()).await {
            tracing::error!(planner = %pid, error = %e, "closing the store failed");
        }
    }
    out.publish_stored().await?;
    out.close().await;
    tracing::info!(planner = %pid, clouds = node.stats().clouds_integrated, dropped = drops.total(), "planner stopped");
    Ok(())
}

/// The node as `settings` make it, with the standby decoder and the store it uses started
/// (the store's trolleys restored into it).
async fn start_node(
    settings: &PlannerSettings,
    out: &mut Outputs,
    counters: &Arc<PlannerCounters>,
) -> anyhow::Result<Box<PlannerNode>> {
    let pid = &settings.planner_id;
    let node = PlannerNode::new(pid, settings.planning.clone(), wall_clock_ns())
        .with_replica_refresh(settings.replica_refresh_clouds)
        .with_takeover_decode_threads(settings.takeover_decode_threads)
        .with_standby_decoded_ahead(settings.standby_decoded_ahead)
        .with_refresh_by_delta(settings.refresh_by_delta);
    if settings.standby_decoded_ahead {
        let events = out.events.clone();
        out.decoder = Some(
            decoder::StandbyDecoder::start(settings.planning.clone(), events)
                .context("the standby decoder did not start")?,
        );
    }
    let mut node = Box::new(node);
    if let Some(store) = &settings.store {
        let (restored, opened) = open_store(store, node, pid).await?;
        node = restored;
        let events = out.events.clone();
        let write_delay = Duration::from_millis(store.write_delay_ms);
        out.store = Some(storage::StoreWriter::start(
            opened,
            counters.clone(),
            events,
            write_delay,
        )?);
    }
    Ok(node)
}

/// One event through the node (on a blocking thread: integration, fits and planning are
/// heavy), its actions performed in order, its time logged at debug level.
async fn step(
    mut node: Box<PlannerNode>,
    event: PlannerEvent,
    inputs: &mut Inputs,
    out: &mut Outputs,
    counters: &PlannerCounters,
) -> anyhow::Result<Box<PlannerNode>> {
    let stages_before = node.stats().stages;
    let (kind, batch) = (event.kind(), event_clouds(&event));
    let step_started = Instant::now();
    let started_ns = wall_clock_ns();
    let taken_before = node.stats().clouds_taken;
    let (back, actions, costs) = tokio::task::spawn_blocking(move || {
        let before = StepCosts::now();
        let actions = node.handle(event);
        (node, actions, StepCosts::now().since(&before))
    })
    .await
    .context("planner task failed")?;
    node = back;
    let handled = step_started.elapsed();
    // How long the cloud this step took waited since it was received (0: no cloud taken).
    let waited_ms = match node.stats().clouds_taken != taken_before {
        true => started_ns.saturating_sub(node.stats().last_cloud_received_ns) as f64 / 1e6,
        false => 0.0,
    };
    mirror_stats(counters, &stages_before, &node.stats());
    let stages = node.stats().stages.since(&stages_before);
    let n_actions = actions.len();
    for action in actions {
        if let PlannerAction::PublishStatus { status, .. } = &action {
            if let Ok(mut last) = counters.status.lock() {
                *last = Some(status.clone());
            }
        }
        let snapshot_bytes = perform(action, inputs, out).await?;
        counters
            .snapshot_bytes_sent
            .fetch_add(snapshot_bytes, Ordering::Relaxed);
    }
    // Where a planner's wall time goes, step by step (RUST_LOG=glasshouse_planner=debug).
    tracing::debug!(
        planner = %node.pid(),
        event = kind,
        clouds = batch,
        actions = n_actions,
        waited_ms,
        handle_ms = handled.as_secs_f64() * 1e3,
        handle_cpu_ms = costs.thread_cpu_ms,
        handle_process_cpu_ms = costs.process_cpu_ms,
        handle_run_delay_ms = costs.run_delay_ms,
        perform_ms = (step_started.elapsed() - handled).as_secs_f64() * 1e3,
        integrate_ms = stages.integrate_ms,
        fit_ms = stages.fit_ms,
        plan_ms = stages.plan_ms,
        publish_ms = stages.publish_ms,
        "step"
    );
    Ok(node)
}

/// What a step cost beside its wall time, ms: the CPU of the thread that ran it, the CPU of the
/// whole process meanwhile (the step's ray and fit threads, and the bus's), and the time the
/// step's thread was ready to run but waited for a core. Wall time minus the thread's CPU and
/// its wait is the time it waited for its helper threads.
#[derive(Clone, Copy)]
struct StepCosts {
    thread_cpu_ms: f64,
    process_cpu_ms: f64,
    run_delay_ms: f64,
}

impl StepCosts {
    fn now() -> Self {
        Self {
            thread_cpu_ms: cpu_clock_ms(libc::CLOCK_THREAD_CPUTIME_ID),
            process_cpu_ms: cpu_clock_ms(libc::CLOCK_PROCESS_CPUTIME_ID),
            run_delay_ms: thread_run_delay_ms(),
        }
    }

    fn since(&self, before: &Self) -> Self {
        Self {
            thread_cpu_ms: self.thread_cpu_ms - before.thread_cpu_ms,
            process_cpu_ms: self.process_cpu_ms - before.process_cpu_ms,
            run_delay_ms: self.run_delay_ms - before.run_delay_ms,
        }
    }
}

/// A CPU-time clock, ms (0 where it cannot be read).
#[allow(unsafe_code)]
fn cpu_clock_ms(clock: libc::clockid_t) -> f64 {
    let mut now = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec through the pointer it is given.
    match unsafe { libc::clock_gettime(clock, &mut now) } {
        0 => now.tv_sec as f64 * 1e3 + now.tv_nsec as f64 / 1e6,
        _ => 0.0,
    }
}

/// Time the calling thread has spent ready to run but waiting for a core, ms: the second field
/// of Linux's `/proc/thread-self/schedstat` (0 where it cannot be read).
fn thread_run_delay_ms() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|line| line.split_whitespace().nth(1)?.parse::<u64>().ok())
        .map_or(0.0, |ns| ns as f64 / 1e6)
}

/// The clouds an event brings (0 for every other kind).
fn event_clouds(event: &PlannerEvent) -> usize {
    match event {
        PlannerEvent::Clouds { clouds, .. } => clouds.len(),
        PlannerEvent::Cloud { .. } => 1,
        _ => 0,
    }
}

/// Mirrors the node's counts into the counters tests and `/metrics` read.
fn mirror_stats(
    counters: &PlannerCounters,
    stages_before: &StageTimes,
    stats: &node::PlannerStats,
) {
    counters.stage_seconds.observe(stages_before, &stats.stages);
    let set = |counter: &AtomicU64, value: u64| counter.store(value, Ordering::Relaxed);
    set(&counters.clouds_integrated, stats.clouds_integrated);
    set(&counters.clouds_rejected, stats.clouds_rejected);
    set(&counters.views_published, stats.views_published);
    set(&counters.clouds_refused, stats.clouds_refused);
    set(&counters.drops.stale_epoch, stats.stale_epoch);
    set(&counters.snapshot_deltas_sent, stats.snapshot_deltas_sent);
    set(
        &counters.snapshot_deltas_applied,
        stats.snapshot_deltas_applied,
    );
}

/// Environment variable that caps the map's vector unit (`portable`, `avx2` or `avx512`), for
/// side-by-side measurements; unset, the voxel walks use the widest unit the CPU has.
pub const SIMD_ENV: &str = "GLASSHOUSE_SIMD";

/// Applies [`SIMD_ENV`] when set; an unknown value is an error naming the accepted ones.
pub fn cap_simd_from_env() -> anyhow::Result<()> {
    let Ok(name) = std::env::var(SIMD_ENV) else {
        return Ok(());
    };
    let level = glasshouse_roimap::simd::Level::from_name(&name)
        .with_context(|| format!("{SIMD_ENV}={name}: expected portable, avx2 or avx512"))?;
    glasshouse_roimap::simd::set_cap(level);
    Ok(())
}

/// Every trolley's latest fruits merged into the fleet map (de-duplicated where rows overlap).
pub fn fleet_fruits(latest: &BTreeMap<String, FruitEstimates>, pid: &str) -> FleetFruits {
    let inputs: Vec<TrolleyFruit> = latest
        .iter()
        .flat_map(|(tid, estimates)| {
            estimates.fruits.iter().map(move |f| TrolleyFruit {
                trolley_id: tid.clone(),
                fruit: *f,
            })
        })
        .collect();
    let merged = merge_fruits(&inputs, glasshouse_fleet::MERGE_DISTANCE_M);
    let fruits = merged
        .fruits
        .into_iter()
        .map(|m| FleetFruit {
            fleet_id: m.fleet_id,
            fruit: m.fruit,
            sources: m.sources.iter().map(|(t, f)| format!("{t}/{f}")).collect(),
        })
        .collect();
    FleetFruits {
        fruits,
        planner_id: pid.to_owned(),
        trolleys: latest.len() as u32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_refuse_zero_takeover_decode_threads() {
        let mut s = PlannerSettings::new("p1");
        assert!(s.validate().is_ok());
        s.takeover_decode_threads = 0;
        let Err(e) = s.validate() else {
            panic!("0 decode threads accepted")
        };
        assert!(e.to_string().contains("takeover_decode_threads"), "{e}");
    }
}
