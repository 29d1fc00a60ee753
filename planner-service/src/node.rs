//! The planner as a state machine ([`PlannerNode`]): bus events in, actions out, no I/O.
//!
//! It holds the cluster membership, one [`TrolleyPlanner`] per trolley this planner owns or
//! replicates, and the latest fruits of every trolley for the fleet map. Every decision (who owns
//! a trolley, when to ask for a snapshot, what to do with clouds that arrive meanwhile, when to
//! plan) is made here and tested by feeding events; the driver in `lib.rs` only moves messages.
//!
//! A trolley's clouds are taken only from the detector that serves it: the live detector (by
//! liveliness token) ranked first for the trolley ([`glasshouse_fleet::first_ranked`], the
//! ranking the detectors split the trolleys by). The sender is the id its cloud's key ends in
//! (`gh/trolley/{tid}/roi/{did}`: in a secured deployment the router lets only detector `did`
//! put there), which the header's `source_id` must repeat, else the cloud is refused at once
//! (`PlannerStatus::unassigned_clouds`). One stolen detector key thus reaches only the trolleys
//! that detector serves. A cloud from a sender without a token, or from a live detector that
//! does not serve the trolley, waits up to [`UNKNOWN_SOURCE_WAIT_NS`] for the membership to
//! change (a detector's token and its first cloud may arrive in either order; detectors and
//! planners hear of a detector leaving at different times), then is refused and counted
//! (`refused_clouds`, `unassigned_clouds`). Which frames a map takes is
//! [`glasshouse_pipeline::FrameOrder`]'s rule; the frames it refuses are counted too
//! (`PlannerStatus::refused_clouds`).
//!
//! Each cloud the owner registers to its map (`planning.registration`) reports how on the wire:
//! the MapUpdate the cloud produces carries its [`glasshouse_proto::FrameRegistration`] (a
//! rejected cloud's update changes no voxel and carries only that), and PlannerStatus the
//! totals by verdict over the trolleys this planner owns.
//!
//! Fencing ([`glasshouse_fleet::epoch`]): each time this planner becomes a trolley's owner with
//! an up-to-date copy it begins a term, whose epoch is later than every epoch it has seen for the
//! trolley (its owners' fruits and snapshots, the edge's `TrolleyInfo::owner_epoch`), and its
//! views, fruits and map updates carry it; its snapshots carry the newest epoch it knows. Fruits
//! and snapshots of an older epoch than the newest seen for their trolley are dropped and
//! counted (`PlannerStatus::stale_epoch`). An owner that sees a newer epoch than its own term was
//! replaced while it could not hear (paused, cut off): it stops planning, catches up from a
//! snapshot of the other planners (keeping its own copy only when none has one) and begins a new
//! term before it plans again (`PlannerStatus::stepped_down`).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::Arc;
use std::time::Instant;

pub use glasshouse_fleet::Role;
use glasshouse_fleet::{Assignment, EpochFence, Membership, OwnershipChange};
use glasshouse_pipeline::{
    ranked_views, FrameVerdict, PlanningError, PlanningSettings, TrolleyPlanner,
};
use glasshouse_proto::keys;
use glasshouse_proto::FrameId;
use glasshouse_proto::{
    FleetFruits, FrameRegistration, FruitEstimates, Header, MapSnapshot, MapUpdate, PlannerStatus,
    RankedViews, RegistrationTotals, RigidCorrection, RoiCloud, RoiColours, StageTimes,
    TrolleyInfo,
};
use glasshouse_roimap::PriorRules;

mod persist;
mod refresh;
mod takeover;

pub(crate) use persist::StoredMark;
use persist::{store_cloud, store_term_start, store_visit_start, Restored};
pub use persist::{StoreRules, StoreWrite, StoredTrolley};
pub use refresh::DeltaBase;

use crate::fleet_fruits;
use crate::registration::{frame_registration, registration_totals};
use crate::slot::{ReceivedCloud, Slot, Stage};

/// Key whose rendezvous winner among the live planners publishes the fleet fruit map.
pub const FLEET_MAP_KEY: &str = "fleet";

/// How long a cloud from a source that does not serve its trolley (no detector token yet, or
/// another detector ranked first) waits for the membership to change (receiver's clock) before
/// it is refused.
pub const UNKNOWN_SOURCE_WAIT_NS: u64 = 2_000_000_000;
/// Such clouds kept at most, over all sources; the oldest is refused first.
pub const UNKNOWN_SOURCE_CLOUDS: usize = 8;

/// A cloud as it arrived: `sender` is the detector id its key ends in (see [`keys::sender`]).
#[derive(Clone, Debug)]
pub struct KeyedCloud {
    pub sender: String,
    pub header: Header,
    pub cloud: RoiCloud,
}

/// What reaches the planner.
#[derive(Clone, Debug)]
pub enum PlannerEvent {
    PlannerJoined(String),
    PlannerLeft(String),
    TrolleyJoined(String),
    TrolleyLeft(String),
    DetectorJoined(String),
    DetectorLeft(String),
    /// A ROI cloud of a trolley from detector `sender` (the id its key ends in), received when
    /// this process's wall clock read `received_ns` (Unix ns).
    Cloud {
        sender: String,
        header: Header,
        cloud: RoiCloud,
        received_ns: u64,
    },
    /// Clouds that queued up while the planner was busy, in arrival order, the last received at
    /// `received_ns`: each is integrated, and the owner plans once per trolley, on the trolley's
    /// last cloud of the batch. They are handled until one has something to publish, the rest
    /// one [`PlannerEvent::NextCloud`] at a time.
    Clouds {
        clouds: Vec<KeyedCloud>,
        received_ns: u64,
    },
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
    /// Another planner asks for this planner's copy of `tid` (query `query_id`); a standby
    /// copy's refresh says what it holds (`base`), so that the owner may send only what changed.
    SnapshotAsked {
        query_id: u64,
        tid: String,
        base: Option<DeltaBase>,
    },
    /// A trolley this planner took over catches up now (see [`PlannerAction::CatchUp`]).
    CatchUp {
        tid: String,
    },
    /// The clusters, fruit ids and fits of a cloud whose views went out first (see
    /// [`PlannerAction::Finish`]).
    Finish {
        tid: String,
    },
    /// The next cloud of the batch being handled (see [`PlannerAction::NextCloud`]).
    NextCloud,
    /// The answer to a [`PlannerAction::DecodeAhead`]: `copy` decoded from `snapshot` (see
    /// [`decode_ahead`]).
    DecodedAhead(DecodedAhead),
    /// A store write of `tid` failed: the store may miss what it held, so the next checkpoint
    /// of the trolley writes every block again.
    StoreFailed {
        tid: String,
    },
    /// Time to publish the status; `dropped_messages` is the bus's drop count, `now_ns` this
    /// process's wall clock (Unix ns).
    StatusTick {
        dropped_messages: u64,
        now_ns: u64,
    },
}

impl PlannerEvent {
    /// The event's name, for logs and step timings.
    pub fn kind(&self) -> &'static str {
        match self {
            PlannerEvent::PlannerJoined(_) => "planner_joined",
            PlannerEvent::PlannerLeft(_) => "planner_left",
            PlannerEvent::TrolleyJoined(_) => "trolley_joined",
            PlannerEvent::TrolleyLeft(_) => "trolley_left",
            PlannerEvent::DetectorJoined(_) => "detector_joined",
            PlannerEvent::DetectorLeft(_) => "detector_left",
            PlannerEvent::Cloud { .. } => "cloud",
            PlannerEvent::Clouds { .. } => "clouds",
            PlannerEvent::Info { .. } => "info",
            PlannerEvent::Fruits { .. } => "fruits",
            PlannerEvent::SnapshotLoaded { .. } => "snapshot_loaded",
            PlannerEvent::SnapshotAsked { .. } => "snapshot_asked",
            PlannerEvent::CatchUp { .. } => "catch_up",
            PlannerEvent::Finish { .. } => "finish",
            PlannerEvent::NextCloud => "next_cloud",
            PlannerEvent::DecodedAhead(_) => "decoded_ahead",
            PlannerEvent::StoreFailed { .. } => "store_failed",
            PlannerEvent::StatusTick { .. } => "status_tick",
        }
    }
}

/// What a trolley's owner publishes.
#[derive(Clone, Debug, PartialEq)]
pub enum TrolleyOutput {
    Views(RankedViews),
    Fruits(FruitEstimates),
    Map(Box<MapUpdate>),
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
    /// With a `base` (a standby copy's refresh) the answer may be a delta on it.
    AskSnapshot {
        tid: String,
        sources: Vec<String>,
        base: Option<DeltaBase>,
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
    /// Feed `PlannerEvent::CatchUp { tid }` back once the actions before it are done: a planner
    /// that takes over several trolleys at once catches them up one event at a time, so each
    /// trolley's views go out as soon as its own copy is ready.
    CatchUp {
        tid: String,
    },
    /// Feed `PlannerEvent::Finish { tid }` back once the actions before it are done, like
    /// `CatchUp`: after a takeover each trolley's views go out before its clusters, fruit ids
    /// and fits are made, and those come after the catch-ups queued before them. A trolley's
    /// cloud, snapshot or catch-up finishes what is left first, so the order per trolley holds.
    Finish {
        tid: String,
    },
    /// Feed `PlannerEvent::NextCloud` back once the actions before it are done: a batch of
    /// clouds is handled until one of them has something to publish, so a trolley's views go
    /// out before the other trolleys' clouds queued behind its own are integrated.
    NextCloud,
    /// Write to the planner's store before performing the actions after this one.
    Store(StoreWrite),
    /// Decode `snapshot`, a standby copy's, in the background with [`decode_ahead`] (when the
    /// cores are otherwise idle: it is never waited on) and feed the result back as
    /// [`PlannerEvent::DecodedAhead`]: a takeover of the trolley then adopts the decoded copy
    /// instead of decoding. A newer request for the same trolley supersedes an older one.
    DecodeAhead {
        tid: String,
        snapshot: Arc<MapSnapshot>,
    },
}

/// A standby copy's snapshot decoded ahead of a takeover.
#[derive(Clone)]
pub struct DecodedAhead {
    pub tid: String,
    pub snapshot: Arc<MapSnapshot>,
    pub copy: Result<Box<TrolleyPlanner>, PlanningError>,
    pub decode_ms: f64,
}

impl std::fmt::Debug for DecodedAhead {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DecodedAhead")
            .field("tid", &self.tid)
            .field("decoded", &self.copy.as_ref().map(|_| "copy"))
            .field("decode_ms", &self.decode_ms)
            .finish()
    }
}

/// Decodes a standby copy's snapshot (what a [`PlannerAction::DecodeAhead`] asks), with the
/// node's planning settings; pure, so a driver can run it on any thread.
pub fn decode_ahead(
    planning: &PlanningSettings,
    tid: String,
    snapshot: Arc<MapSnapshot>,
) -> PlannerEvent {
    let (copy, decode_ms) = decode_timed(planning, &snapshot);
    PlannerEvent::DecodedAhead(DecodedAhead {
        tid,
        snapshot,
        copy: copy.map(Box::new),
        decode_ms,
    })
}

/// A copy decoded from `snapshot`, with the wall time the decode took in ms (ahead of a
/// takeover or at it).
fn decode_timed(
    planning: &PlanningSettings,
    snapshot: &MapSnapshot,
) -> (Result<TrolleyPlanner, PlanningError>, f64) {
    let started = Instant::now();
    let copy = TrolleyPlanner::from_snapshot(planning.clone(), snapshot);
    (copy, started.elapsed().as_secs_f64() * 1e3)
}

/// Counts the driver mirrors into its counters.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PlannerStats {
    pub clouds_integrated: u64,
    /// Clouds that decoded but could not be integrated (e.g. mismatched lengths, bad ids).
    pub clouds_rejected: u64,
    /// Clouds refused: not from a live detector, or a frame [`glasshouse_pipeline::FrameOrder`]
    /// refuses.
    pub clouds_refused: u64,
    /// Clouds refused: from a live detector that does not serve their trolley, or whose header
    /// names another source than their key.
    pub clouds_unassigned: u64,
    /// Clouds of frames older than the map's last one (not integrated).
    pub clouds_stale: u64,
    /// Clouds integrated without colour: their `roi_rgb` was not one colour per ROI point.
    pub clouds_colourless: u64,
    pub views_published: u64,
    pub last_planning_time_ms: f32,
    pub total_planning_time_ms: f64,
    pub plans: u64,
    /// Time in each stage of cloud handling (this thread's wall clock around each step).
    pub stages: StageTimes,
    /// Time catching up trolleys taken over (decode and replay; the replay also counts in
    /// `stages`).
    pub catch_up_ms: f64,
    /// Fruits and snapshots dropped: an older ownership epoch than the newest seen for their
    /// trolley.
    pub stale_epoch: u64,
    /// Terms this planner gave up on seeing a newer epoch for a trolley it owned.
    pub stepped_down: u64,
    /// Snapshots not loaded after a step-down because this planner's own copy held more
    /// ([`holds_more`]).
    pub kept_own_copy: u64,
    /// Standby copies decoded ahead of a takeover and kept (see
    /// [`PlannerNode::with_standby_decoded_ahead`]).
    pub standby_decodes_ahead: u64,
    /// Takeovers that adopted a copy decoded ahead instead of decoding.
    pub decoded_ahead_adopted: u64,
    /// Standby refreshes this owner answered with the blocks changed since the copy's base.
    pub snapshot_deltas_sent: u64,
    /// Owners' deltas this planner's standby copies applied.
    pub snapshot_deltas_applied: u64,
    /// When the last cloud taken off the batch was received (the event's `received_ns`): the
    /// driver logs how long it waited before its step.
    pub last_cloud_received_ns: u64,
    /// Clouds taken off the batch, handled or refused.
    pub clouds_taken: u64,
}

/// What follows a cloud's insert ([`PlannerNode::integrate_then`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Then {
    /// Clusters and fruit ids (a replica, or an owner's cloud with a later one queued).
    Track,
    /// Also the fits and the views.
    Plan,
    /// The views at once, the rest on [`PlannerEvent::Finish`] (a trolley taken over).
    ViewsFirst,
    /// Clusters, fruit ids and fits, no views (the last cloud a takeover planned past).
    Fit,
}

/// A cloud planned on before its clusters, fruit ids and fits were made: what its map update
/// needs once they are ([`PlannerNode::finish`]).
#[derive(Clone, Debug)]
pub(crate) struct Unfinished {
    header: Header,
    /// The cloud's source frame (its map update and fruits are based on it).
    frame: FrameId,
    registration: Option<glasshouse_proto::FrameRegistration>,
}

/// Milliseconds between successive laps: the stages of one cloud's handling, timed in turn.
struct Laps(Instant);

impl Laps {
    fn start() -> Self {
        Self(Instant::now())
    }

    fn lap_ms(&mut self) -> f64 {
        let now = Instant::now();
        let ms = (now - self.0).as_secs_f64() * 1e3;
        self.0 = now;
        ms
    }
}

/// Whether a cloud's source may send its trolley's clouds (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sender {
    /// No live detector.
    NotLive,
    /// A live detector, but another one is ranked first for the trolley.
    NotServing,
    /// The live detector ranked first for the trolley.
    Serving,
}

/// The planner (see the module docs).
pub struct PlannerNode {
    pid: String,
    /// This process's boot epoch, written into every header it publishes.
    epoch_ns: u64,
    planning: PlanningSettings,
    membership: Membership,
    /// Live detectors: a trolley's clouds are taken from the one ranked first for it.
    detectors: Membership,
    /// Clouds from sources that do not serve their trolley yet, oldest first.
    unknown_source: VecDeque<ReceivedCloud>,
    /// Sources and trolleys whose refused clouds were logged (once each).
    logged_refusals: BTreeSet<String>,
    slots: BTreeMap<String, Slot>,
    /// The newest ownership epoch seen per trolley (own terms included).
    fence: EpochFence,
    /// The latest wall-clock time an event brought (Unix ns): new terms' epochs start here.
    clock_ns: u64,
    latest_fruits: BTreeMap<String, FruitEstimates>,
    stats: PlannerStats,
    status_seq: u64,
    /// Clouds of the batch being handled, in arrival order (see [`PlannerAction::NextCloud`]).
    batch: VecDeque<ReceivedCloud>,
    /// Per trolley, its clouds still to come in `batch`.
    queued_clouds: BTreeMap<String, usize>,
    /// See [`PlannerNode::with_replica_refresh`]; 0: a hot replica.
    replica_refresh_clouds: usize,
    /// See [`PlannerNode::with_takeover_decode_threads`].
    takeover_decode_threads: usize,
    /// See [`PlannerNode::with_standby_decoded_ahead`].
    standby_decoded_ahead: bool,
    /// See [`PlannerNode::with_refresh_by_delta`].
    refresh_by_delta: bool,
    /// See [`PlannerNode::with_store`]; None: no store.
    store: Option<StoreRules>,
    /// How a new visit's prior is made from the previous visit's map.
    revisit_prior: PriorRules,
    /// Until then (this process's clock) no ownership decision is made; `settled` once past it.
    settle_until_ns: u64,
    settled: bool,
    /// Clouds and trolley infos that came while settling, taken once settled.
    settle_held: VecDeque<ReceivedCloud>,
    settle_infos: BTreeMap<String, TrolleyInfo>,
    /// Copies the store held at start that no slot has claimed yet.
    restored: BTreeMap<String, Restored>,
    /// Trolleys whose latest fruits changed since they were last stored.
    fruits_to_store: BTreeSet<String>,
    /// Copies taken over whose held snapshot was decoded (or its standby copy adopted) ahead of
    /// their catch-up, side by side with the others taken over together (see `takeover.rs`).
    decoded_at_takeover: BTreeMap<String, TakeoverDecode>,
}

/// How a copy taken over got its owner's map before its catch-up (see `takeover.rs`).
#[derive(Debug, Clone, Copy)]
struct TakeoverDecode {
    /// Wall time of its decode at the takeover (0 for a standby copy adopted as it is).
    decode_ms: f64,
    /// The copy was decoded in the background while standing by and adopted as it is.
    standby_copy: bool,
}

/// Clouds a standby replica holds before it asks its owner for a snapshot (the default of
/// [`PlannerNode::with_replica_refresh`]): a takeover integrates at most this many.
pub const REPLICA_REFRESH_CLOUDS: usize = 8;

/// Snapshots of trolleys taken over together decoded at once (the default of
/// [`PlannerNode::with_takeover_decode_threads`]).
pub const TAKEOVER_DECODE_THREADS: usize = 8;

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
    /// A planner that knows only itself, started at `epoch_ns` (its process's boot epoch);
    /// `planning` must be valid.
    pub fn new(pid: &str, planning: PlanningSettings, epoch_ns: u64) -> Self {
        let mut membership = Membership::new();
        membership.server_joined(pid);
        Self {
            pid: pid.to_owned(),
            epoch_ns,
            planning,
            membership,
            detectors: Membership::new(),
            unknown_source: VecDeque::new(),
            logged_refusals: BTreeSet::new(),
            slots: BTreeMap::new(),
            fence: EpochFence::new(),
            clock_ns: epoch_ns,
            latest_fruits: BTreeMap::new(),
            stats: PlannerStats::default(),
            status_seq: 0,
            batch: VecDeque::new(),
            queued_clouds: BTreeMap::new(),
            replica_refresh_clouds: REPLICA_REFRESH_CLOUDS,
            takeover_decode_threads: TAKEOVER_DECODE_THREADS,
            standby_decoded_ahead: false,
            refresh_by_delta: true,
            store: None,
            revisit_prior: PriorRules::default(),
            settle_until_ns: epoch_ns,
            settled: true,
            settle_held: VecDeque::new(),
            settle_infos: BTreeMap::new(),
            restored: BTreeMap::new(),
            fruits_to_store: BTreeSet::new(),
            decoded_at_takeover: BTreeMap::new(),
        }
    }

    /// How a replica keeps its copy. With `clouds` > 0 it stands by: it keeps the trolley's
    /// clouds without integrating them and, once `clouds` are held, asks the owner for a
    /// snapshot of its map and drops the clouds the snapshot holds; when it takes over it
    /// integrates the ones left. With 0 it is hot: it integrates every cloud as the owner does.
    pub fn with_replica_refresh(mut self, clouds: usize) -> Self {
        self.replica_refresh_clouds = clouds;
        self
    }

    /// How many of the snapshots held for trolleys taken over together are decoded at once,
    /// before the first of them is planned on (`takeover.rs`); 1 decodes each at its own
    /// catch-up, one after another.
    pub fn with_takeover_decode_threads(mut self, threads: usize) -> Self {
        self.takeover_decode_threads = threads.max(1);
        self
    }

    /// Whether a standby copy's snapshot is decoded as soon as it is held
    /// ([`PlannerAction::DecodeAhead`], off by default): a takeover then adopts the decoded copy
    /// instead of decoding (a standby copy costs its decoded map's memory beside the snapshot,
    /// and every refresh a decode in the background).
    pub fn with_standby_decoded_ahead(mut self, ahead: bool) -> Self {
        self.standby_decoded_ahead = ahead;
        self
    }

    /// Whether a standby copy decoded ahead asks its owner for only the map's blocks changed
    /// since what it holds (a delta, [`DeltaBase`]; on by default); false asks for the whole
    /// map every time.
    pub fn with_refresh_by_delta(mut self, by_delta: bool) -> Self {
        self.refresh_by_delta = by_delta;
        self
    }

    /// This planner's id.
    pub fn pid(&self) -> &str {
        &self.pid
    }

    pub fn stats(&self) -> PlannerStats {
        self.stats
    }

    /// This planner's role for `tid`, if it holds the trolley.
    pub fn role(&self, tid: &str) -> Option<Role> {
        self.slots.get(tid).map(Slot::role)
    }

    /// Clouds a standby copy of `tid` keeps, not yet integrated.
    pub fn pending_clouds(&self, tid: &str) -> usize {
        self.slots.get(tid).map_or(0, Slot::pending_len)
    }

    /// Whether the copy of `tid` waits for a snapshot.
    pub fn is_loading(&self, tid: &str) -> bool {
        self.slots.get(tid).is_some_and(Slot::is_loading)
    }

    /// This planner's copy of `tid`.
    pub fn planner(&self, tid: &str) -> Option<&TrolleyPlanner> {
        self.slots.get(tid).map(|s| s.planner.as_ref())
    }

    /// The epoch of this planner's ownership term of `tid`; None when it does not own the
    /// trolley or its term has not begun (its copy is loading).
    pub fn term(&self, tid: &str) -> Option<u64> {
        self.slots.get(tid).map(Slot::term).filter(|&t| t != 0)
    }

    /// The newest ownership epoch this planner has seen for `tid` (0: none).
    pub fn newest_epoch(&self, tid: &str) -> u64 {
        self.fence.newest(tid)
    }

    /// Feeds one event; returns what to do.
    pub fn handle(&mut self, event: PlannerEvent) -> Vec<PlannerAction> {
        let mut actions = self.handle_event(event);
        actions.extend(self.settle_if_due());
        actions
    }

    fn handle_event(&mut self, event: PlannerEvent) -> Vec<PlannerAction> {
        match event {
            PlannerEvent::PlannerJoined(id) => {
                let changes = self.membership.server_joined(&id);
                self.apply(&changes)
            }
            // Our own token is ours for as long as we run.
            PlannerEvent::PlannerLeft(id) if id == self.pid => Vec::new(),
            PlannerEvent::PlannerLeft(id) => {
                let changes = self.membership.server_left(&id);
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
            PlannerEvent::DetectorJoined(id) => {
                self.detectors.server_joined(id);
                self.retry_held_clouds()
            }
            PlannerEvent::DetectorLeft(id) => {
                self.detectors.server_left(id);
                self.retry_held_clouds()
            }
            PlannerEvent::Cloud {
                sender,
                header,
                cloud,
                received_ns,
            } => {
                self.clock_ns = self.clock_ns.max(received_ns);
                let cloud = KeyedCloud {
                    sender,
                    header,
                    cloud,
                };
                self.on_clouds(vec![cloud], received_ns)
            }
            PlannerEvent::Clouds {
                clouds,
                received_ns,
            } => {
                self.clock_ns = self.clock_ns.max(received_ns);
                self.on_clouds(clouds, received_ns)
            }
            PlannerEvent::Info { header, info } => self.on_info(&header.trolley_id, info),
            PlannerEvent::Fruits { header, fruits } => self.on_fruits(header, fruits),
            PlannerEvent::SnapshotLoaded { tid, snapshot } => {
                self.on_snapshot_loaded(&tid, snapshot)
            }
            PlannerEvent::SnapshotAsked {
                query_id,
                tid,
                base,
            } => self.on_snapshot_asked(query_id, &tid, base),
            PlannerEvent::CatchUp { tid } => self.on_catch_up(&tid),
            PlannerEvent::Finish { tid } => self.finish(&tid),
            PlannerEvent::NextCloud => self.next_of_batch(),
            PlannerEvent::DecodedAhead(decoded) => self.on_decoded_ahead(decoded),
            PlannerEvent::StoreFailed { tid } => {
                if let Some(slot) = self.slots.get_mut(&tid) {
                    slot.stored = StoredMark::default();
                }
                Vec::new()
            }
            PlannerEvent::StatusTick {
                dropped_messages,
                now_ns,
            } => self.on_tick(dropped_messages, now_ns),
        }
    }

    /// A snapshot asked for: a standby copy's refresh, or the copy of a loading trolley.
    fn on_snapshot_loaded(
        &mut self,
        tid: &str,
        snapshot: Option<Box<MapSnapshot>>,
    ) -> Vec<PlannerAction> {
        let refreshing = self.slots.get(tid).is_some_and(|s| {
            matches!(
                s.stage,
                Stage::Standby {
                    refresh_asked: true,
                    ..
                }
            )
        });
        match refreshing {
            true => self.on_refresh(tid, snapshot),
            false => self.on_snapshot(tid, snapshot),
        }
    }

    /// The status period: held clouds that waited too long are refused, the status goes out.
    fn on_tick(&mut self, dropped_messages: u64, now_ns: u64) -> Vec<PlannerAction> {
        self.clock_ns = self.clock_ns.max(now_ns);
        self.expire_unknown_sources(now_ns);
        self.status(dropped_messages)
    }

    /// A standby copy answers with every cloud it holds integrated; an owner asked by a
    /// standby copy of its current term, with the blocks changed since what the copy holds.
    fn on_snapshot_asked(
        &mut self,
        query_id: u64,
        tid: &str,
        base: Option<DeltaBase>,
    ) -> Vec<PlannerAction> {
        let mut actions = self.catch_up(tid, false);
        actions.extend(self.finish(tid));
        let mut laps = Laps::start();
        let delta = base.and_then(|base| self.delta_of(tid, &base));
        let answer = delta.unwrap_or_else(|| self.snapshot_of(tid));
        self.stats.stages.publish_ms += laps.lap_ms();
        actions.push(PlannerAction::ReplySnapshot { query_id, answer });
        actions
    }

    /// A deferred takeover: caught up unless a cloud already did it.
    fn on_catch_up(&mut self, tid: &str) -> Vec<PlannerAction> {
        let due = self
            .slots
            .get(tid)
            .is_some_and(|s| matches!(s.stage, Stage::TakingOver { .. }));
        match due {
            true => self.catch_up(tid, true),
            false => Vec::new(),
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

    /// A trolley's info: its arm and workspace, and the newest ownership epoch its edge took
    /// views under (which may replace this planner as its owner).
    fn on_info(&mut self, tid: &str, info: TrolleyInfo) -> Vec<PlannerAction> {
        if keys::validate_id(tid).is_err() {
            return Vec::new();
        }
        if !self.settled {
            self.fence.observe(tid, info.owner_epoch);
            self.settle_infos.insert(tid.to_owned(), info);
            return Vec::new();
        }
        let mut actions = self.introduce(tid);
        actions.extend(self.note_epoch(tid, info.owner_epoch, &info.owner_id));
        let visit = info.visit;
        if let Some(slot) = self.slots.get_mut(tid) {
            if let Err(e) = slot.planner.set_info(info) {
                tracing::warn!(planner = %self.pid, trolley = %tid, error = %e, "views are not filtered by reach");
            }
        }
        actions.extend(self.begin_visit(tid, visit));
        actions
    }

    /// The trolley is on `visit`: a copy on an earlier one closes it (its fruits go into their
    /// histories) and starts this one from its map made into a prior; the owner keeps the new
    /// map in its store at once (a full checkpoint: the clouds logged belong to the visit
    /// before). Every copy does this on the same info, so replicas stay the owner's equals; a
    /// copy still loading takes the visit from the snapshot it waits for.
    fn begin_visit(&mut self, tid: &str, visit: u32) -> Vec<PlannerAction> {
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        if slot.is_loading() || visit <= slot.planner.visit() {
            return Vec::new();
        }
        let from = slot.planner.visit();
        match slot.planner.start_visit(visit, &self.revisit_prior) {
            Ok(_) => {
                tracing::info!(planner = %self.pid, trolley = %tid, from, visit,
                    season_fruits = slot.planner.season_histories(&[]).len(),
                    "a new visit of the row: the previous visit's map is its prior");
                store_visit_start(self.store, slot, (&self.pid, tid))
                    .into_iter()
                    .collect()
            }
            Err(e) => {
                tracing::warn!(planner = %self.pid, trolley = %tid, visit, error = %e, "the new visit was not started");
                Vec::new()
            }
        }
    }

    /// A trolley's fruits as its owner published them: dropped and counted under an older
    /// ownership epoch than the newest seen for the trolley; taken for the fleet map from the
    /// trolley's owner only; a newer epoch may replace this planner as the trolley's owner.
    fn on_fruits(&mut self, header: Header, fruits: FruitEstimates) -> Vec<PlannerAction> {
        let tid = header.trolley_id.clone();
        if keys::validate_id(&tid).is_err() {
            return Vec::new();
        }
        if self.fence.check(&tid, fruits.owner_epoch).is_stale() {
            self.refuse_stale(&tid, &header.source_id, "fruits", fruits.owner_epoch);
            return Vec::new();
        }
        let actions = match header.source_id == self.pid {
            true => Vec::new(),
            false => self.note_epoch(&tid, fruits.owner_epoch, &header.source_id),
        };
        let owner = self.membership.assignment(&tid).map(|a| a.owner);
        if owner.as_ref() == Some(&header.source_id) {
            if self.store.is_some() {
                self.fruits_to_store.insert(tid.clone());
            }
            self.latest_fruits.insert(tid, fruits);
        }
        actions
    }

    /// Counts (and logs once per trolley and source) a message of `tid` dropped because its
    /// ownership epoch is older than the newest seen.
    fn refuse_stale(&mut self, tid: &str, source: &str, what: &str, epoch: u64) {
        self.stats.stale_epoch += 1;
        if self.logged_refusals.insert(format!("stale {tid} {source}")) {
            tracing::warn!(planner = %self.pid, trolley = %tid, %source, what, epoch, newest = self.fence.newest(tid),
                "dropped: an older ownership epoch than the newest seen (logged once per trolley and source)");
        }
    }

    /// Records `epoch`, seen for `tid` in another planner's or the edge's message, the term of
    /// planner `holder` (empty when unknown). When it is newer than this planner's own term,
    /// another planner owned the trolley meanwhile: step down.
    fn note_epoch(&mut self, tid: &str, epoch: u64, holder: &str) -> Vec<PlannerAction> {
        if !self.fence.observe(tid, epoch).is_newer() {
            return Vec::new();
        }
        match self.slots.get(tid) {
            Some(slot) if slot.term() != 0 && epoch > slot.term() => {
                self.step_down(tid, epoch, holder)
            }
            _ => Vec::new(),
        }
    }

    /// This planner's term of `tid` is over (a newer one, `newer`, began at `holder`): it plans
    /// nothing more on its copy, which may lack what the newer owner integrated, until it has
    /// caught up from a snapshot (its own copy stays only when no one has one); then, still
    /// owner by the ranking, it begins a new term. The snapshot is asked of `holder` first, then
    /// of the other live planners: a planner that was cut off may not see `holder`'s token yet
    /// when it hears of its term.
    fn step_down(&mut self, tid: &str, newer: u64, holder: &str) -> Vec<PlannerAction> {
        let pid = self.pid.clone();
        let mut sources: Vec<String> = Vec::new();
        let ranked = self.membership.rank(tid);
        for p in std::iter::once(holder).chain(ranked) {
            if !p.is_empty() && p != pid && !sources.iter().any(|s| s == p) {
                sources.push(p.to_owned());
            }
        }
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let term = slot.step_down(&pid, tid);
        tracing::warn!(planner = %pid, trolley = %tid, term, newer, ?sources,
            "stepping down: another planner owned the trolley under a newer epoch; catching up from a snapshot");
        self.stats.stepped_down += 1;
        vec![PlannerAction::AskSnapshot {
            tid: tid.to_owned(),
            sources,
            base: None,
        }]
    }

    fn on_cloud(&mut self, received: ReceivedCloud) -> Vec<PlannerAction> {
        let tid = received.header.trolley_id.clone();
        if keys::validate_id(&tid).is_err() {
            self.stats.clouds_rejected += 1;
            tracing::warn!(trolley = %tid, "cloud with an invalid trolley id dropped");
            return Vec::new();
        }
        if !self.settled {
            self.hold_while_settling(received);
            return Vec::new();
        }
        if self.sender_of(&received.header) != Sender::Serving {
            self.hold_unknown_source(received);
            return Vec::new();
        }
        let mut actions = self.introduce(&tid);
        let latest = self.queued_clouds.get(&tid).is_none_or(|&n| n == 0);
        let Some(slot) = self.slots.get_mut(&tid) else {
            return actions;
        };
        match &mut slot.stage {
            Stage::Loading { buffered, .. } => buffered.push(received),
            Stage::Standby { .. } if self.replica_refresh_clouds > 0 => {
                actions.extend(self.stand_by(&tid, received));
            }
            Stage::Standby { .. } => actions.extend(self.integrate(&tid, received, false)),
            Stage::TakingOver { pending, .. } => {
                pending.push(received);
                actions.extend(self.catch_up(&tid, latest));
            }
            Stage::CatchingUp { .. } | Stage::Owning { .. } => {
                actions.extend(self.integrate(&tid, received, latest))
            }
        }
        actions
    }

    /// A standby replica keeps the cloud (unless its map already holds the frame) and asks the
    /// owner for a snapshot once enough are kept.
    fn stand_by(&mut self, tid: &str, received: ReceivedCloud) -> Vec<PlannerAction> {
        let owner = self.membership.assignment(tid).map(|a| a.owner);
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let mark = slot.copy_mark();
        let held = mark.is_some_and(|m| received.cloud.source_frame() <= m);
        slot.last_cloud = Some(received.clone());
        let Stage::Standby {
            pending,
            refresh_asked,
            ..
        } = &mut slot.stage
        else {
            return Vec::new();
        };
        if !held {
            pending.push(received);
        }
        match owner {
            Some(owner) if !*refresh_asked && pending.len() >= self.replica_refresh_clouds => {
                *refresh_asked = true;
                let base = slot.delta_base(&owner).filter(|_| self.refresh_by_delta);
                vec![PlannerAction::AskSnapshot {
                    tid: tid.to_owned(),
                    sources: vec![owner],
                    base,
                }]
            }
            _ => Vec::new(),
        }
    }

    /// Integrates a standby copy's pending clouds in order; with `plan_last` (a takeover) the
    /// last is planned on, or, with none pending, the latest cloud again (the edge may wait on
    /// it).
    fn catch_up(&mut self, tid: &str, plan_last: bool) -> Vec<PlannerAction> {
        let mut actions = self.finish(tid);
        let at_takeover = self.decoded_at_takeover.remove(tid);
        let Some(slot) = self.slots.get_mut(tid) else {
            return actions;
        };
        let Some((held, pending)) = slot.take_backlog() else {
            return actions;
        };
        let started = Instant::now();
        let adopted_ahead = held.as_ref().is_some_and(|h| h.decoded.is_some());
        let decoded = held.map(|held| slot.restore_held(held));
        if let Some(Err(e)) = &decoded {
            tracing::error!(planner = %self.pid, trolley = %tid, error = %e,
                "the owner's snapshot does not load: the kept clouds go on the copy as it is");
        }
        let decode_ms = match at_takeover {
            Some(d) => d.decode_ms,
            None => started.elapsed().as_secs_f64() * 1e3,
        };
        self.stats.decoded_ahead_adopted += u64::from(adopted_ahead);
        let standby_copy = adopted_ahead || at_takeover.is_some_and(|d| d.standby_copy);
        let last = slot.last_cloud.clone();
        let n = pending.len();
        let pending = match plan_last && n > 0 {
            // A takeover plans on the copy as it is and integrates the kept clouds after: the
            // views of the trolleys taken over wait on their decodes only.
            true => match self.views_before_clouds(tid, pending, started) {
                Ok(planned) => {
                    actions.extend(planned);
                    Vec::new()
                }
                Err(pending) => pending,
            },
            false => pending,
        };
        let then = |planned| match planned {
            true => Then::ViewsFirst,
            false => Then::Track,
        };
        let left = pending.len();
        for (i, received) in pending.into_iter().enumerate() {
            actions.extend(self.integrate_then(tid, received, then(plan_last && i + 1 == left)));
        }
        if let (0, true, Some(last)) = (n, plan_last, last) {
            actions.extend(self.integrate_then(tid, last, Then::ViewsFirst));
        }
        if decoded.is_some() || at_takeover.is_some() {
            let total_ms = started.elapsed().as_secs_f64() * 1e3;
            self.stats.catch_up_ms += total_ms;
            let side_by_side = at_takeover.is_some();
            tracing::info!(planner = %self.pid, trolley = %tid, decode_ms, standby_copy, side_by_side, clouds = n, total_ms, "caught up");
        }
        actions
    }

    /// Views planned on the copy as it is, for the last of `clouds` (the frame the edge waits
    /// on); the clouds are integrated, in order, on [`PlannerEvent::Finish`]. The clouds come
    /// back when the copy is no up-to-date owner's.
    fn views_before_clouds(
        &mut self,
        tid: &str,
        clouds: Vec<ReceivedCloud>,
        started: Instant,
    ) -> Result<Vec<PlannerAction>, Vec<ReceivedCloud>> {
        let Some(last) = clouds.last() else {
            return Err(clouds);
        };
        let (header, camera) = (last.header.clone(), last.cloud.world_from_camera);
        let frame = last.cloud.source_frame();
        let Some(slot) = self.slots.get_mut(tid) else {
            return Err(clouds);
        };
        slot.defer(clouds)?;
        let views = self.plan_views(tid, &camera, frame, started);
        let mut laps = Laps::start();
        let mut actions = self.publish(tid, &header, views, None, None);
        self.stats.stages.publish_ms += laps.lap_ms();
        actions.push(PlannerAction::Finish {
            tid: tid.to_owned(),
        });
        Ok(actions)
    }

    /// The owner's snapshot for a standby replica: it becomes the copy (kept encoded), and the
    /// pending clouds it holds are dropped. A snapshot that is missing, damaged or older than
    /// the copy leaves the copy as it is and the pending clouds are integrated instead (they
    /// stay bounded either way).
    fn on_refresh(&mut self, tid: &str, snapshot: Option<Box<MapSnapshot>>) -> Vec<PlannerAction> {
        let pid = self.pid.clone();
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let Stage::Standby { refresh_asked, .. } = &mut slot.stage else {
            return Vec::new();
        };
        *refresh_asked = false;
        // A replaced owner's copy is not kept: the replica integrates its clouds instead.
        let snapshot = match self.fresh(tid, snapshot) {
            Some(delta) if TrolleyPlanner::is_delta(&delta) => {
                return self.on_refresh_delta(tid, delta)
            }
            whole => whole,
        };
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        match snapshot.is_some_and(|snapshot| slot.hold(snapshot, &pid, tid)) {
            true => self.decode_held_ahead(tid),
            false => self.catch_up(tid, false),
        }
    }

    /// Asks for the snapshot `tid`'s standby copy holds to be decoded ahead, when this node
    /// decodes ahead and the copy holds one not yet decoded.
    fn decode_held_ahead(&self, tid: &str) -> Vec<PlannerAction> {
        let snapshot = self.slots.get(tid).and_then(Slot::to_decode);
        match (self.standby_decoded_ahead, snapshot) {
            (true, Some(snapshot)) => vec![PlannerAction::DecodeAhead {
                tid: tid.to_owned(),
                snapshot,
            }],
            _ => Vec::new(),
        }
    }

    /// A copy decoded ahead is kept when its snapshot is still the one held; else dropped.
    fn on_decoded_ahead(&mut self, decoded: DecodedAhead) -> Vec<PlannerAction> {
        let DecodedAhead {
            tid,
            snapshot,
            copy,
            decode_ms,
        } = decoded;
        let copy = match copy {
            Ok(copy) => copy,
            Err(e) => {
                tracing::warn!(planner = %self.pid, trolley = %tid, error = %e,
                    "the held snapshot does not decode ahead: a takeover decodes it then");
                return Vec::new();
            }
        };
        let kept = self
            .slots
            .get_mut(&tid)
            .is_some_and(|slot| slot.keep_decoded(&snapshot, copy));
        self.stats.standby_decodes_ahead += u64::from(kept);
        tracing::debug!(planner = %self.pid, trolley = %tid, decode_ms, kept, "standby copy decoded ahead");
        Vec::new()
    }

    /// Queues a batch of clouds and takes its first step. The clouds are handled one by one, so
    /// that a trolley's clouds queued behind a later one are integrated without fits or
    /// planning (the edge waits only on its latest frame), and each cloud's results go out
    /// before the next cloud is taken.
    fn on_clouds(&mut self, clouds: Vec<KeyedCloud>, received_ns: u64) -> Vec<PlannerAction> {
        self.expire_unknown_sources(received_ns);
        let clouds: Vec<KeyedCloud> = clouds
            .into_iter()
            .filter(|c| self.sent_by_its_key(c))
            .collect();
        // A batch still being handled (its NextCloud not yet fed back) takes these after its
        // own clouds; a step is taken now either way, so no cloud waits on a lost NextCloud.
        for KeyedCloud { header, cloud, .. } in clouds {
            *self
                .queued_clouds
                .entry(header.trolley_id.clone())
                .or_default() += 1;
            self.batch.push_back(ReceivedCloud {
                header,
                cloud,
                received_ns,
            });
        }
        self.next_of_batch()
    }

    /// Handles the batch's clouds in order until one has something to publish; a
    /// [`PlannerAction::NextCloud`] after its actions when more wait.
    fn next_of_batch(&mut self) -> Vec<PlannerAction> {
        let mut actions = Vec::new();
        while actions.is_empty() {
            let Some(received) = self.batch.pop_front() else {
                break;
            };
            self.stats.last_cloud_received_ns = received.received_ns;
            self.stats.clouds_taken += 1;
            let tid = &received.header.trolley_id;
            if let Some(n) = self.queued_clouds.get_mut(tid) {
                *n -= 1;
                if *n == 0 {
                    self.queued_clouds.remove(tid);
                }
            }
            actions = self.on_cloud(received);
        }
        if !self.batch.is_empty() {
            actions.push(PlannerAction::NextCloud);
        }
        actions
    }

    /// Whether a cloud's header names the detector its key does; one that names another is
    /// refused and counted: the header is what the sender wrote, the key what the router let
    /// it put on.
    fn sent_by_its_key(&mut self, c: &KeyedCloud) -> bool {
        if c.sender == c.header.source_id {
            return true;
        }
        self.stats.clouds_unassigned += 1;
        if self.logged_refusals.insert(format!("key {}", c.sender)) {
            tracing::warn!(planner = %self.pid, trolley = %c.header.trolley_id, sender = %c.sender, claimed = %c.header.source_id,
                "cloud refused: its header names another source than its key (logged once per sender)");
        }
        false
    }

    /// Whether `header`'s source may send its trolley's clouds now.
    fn sender_of(&self, header: &Header) -> Sender {
        let (tid, source) = (&header.trolley_id, header.source_id.as_str());
        if !self.detectors.is_server_live(source) {
            return Sender::NotLive;
        }
        match self.detectors.first_ranked(tid) == Some(source) {
            true => Sender::Serving,
            false => Sender::NotServing,
        }
    }

    /// The detector membership changed: the held clouds whose sender now serves their trolley
    /// are taken in order; the others wait on.
    fn retry_held_clouds(&mut self) -> Vec<PlannerAction> {
        let held = std::mem::take(&mut self.unknown_source);
        held.into_iter().flat_map(|c| self.on_cloud(c)).collect()
    }

    /// Keeps a cloud from a source without a detector token for a while (its token may follow).
    fn hold_unknown_source(&mut self, received: ReceivedCloud) {
        self.unknown_source.push_back(received);
        while self.unknown_source.len() > UNKNOWN_SOURCE_CLOUDS {
            if let Some(oldest) = self.unknown_source.pop_front() {
                self.refuse_unknown_source(&oldest);
            }
        }
    }

    /// Refuses the clouds that waited longer than [`UNKNOWN_SOURCE_WAIT_NS`] for a token.
    fn expire_unknown_sources(&mut self, now_ns: u64) {
        while let Some(oldest) = self.unknown_source.front() {
            if now_ns.saturating_sub(oldest.received_ns) <= UNKNOWN_SOURCE_WAIT_NS {
                break;
            }
            if let Some(oldest) = self.unknown_source.pop_front() {
                self.refuse_unknown_source(&oldest);
            }
        }
    }

    fn refuse_unknown_source(&mut self, refused: &ReceivedCloud) {
        let (tid, source) = (&refused.header.trolley_id, &refused.header.source_id);
        let (why, counter) = match self.sender_of(&refused.header) {
            Sender::NotServing => (
                "a live detector that does not serve the trolley",
                &mut self.stats.clouds_unassigned,
            ),
            _ => ("no live detector", &mut self.stats.clouds_refused),
        };
        *counter += 1;
        if self.logged_refusals.insert(format!("{why} {source}")) {
            tracing::warn!(planner = %self.pid, trolley = %tid, %source,
                "cloud refused: its source is {why} (logged once per source and reason)");
        }
    }

    /// Takes on, hands over or drops trolleys as the assignment changed; a trolley this planner
    /// now owns with an up-to-date map is planned on at once (the edge may be waiting on the
    /// lost owner's answer).
    fn apply(&mut self, changes: &[OwnershipChange]) -> Vec<PlannerAction> {
        let mut actions = Vec::new();
        // Settling: every live trolley is assigned at once when it ends.
        if !self.settled {
            return actions;
        }
        // Trolleys whose standby copy this planner now owns, in the order of the changes.
        let mut taken_over = Vec::new();
        for change in changes {
            let pid = &self.pid;
            let tid = change.trolley.clone();
            let before = change.before.as_ref().and_then(|a| a.role_of(pid));
            let after = change.after.as_ref().and_then(|a| a.role_of(pid));
            tracing::info!(planner = %pid, trolley = %tid, before = %describe(&change.before), after = %describe(&change.after), "ownership changed");
            match (after, self.slots.get_mut(&tid)) {
                (None, Some(_)) => {
                    self.slots.remove(&tid);
                    self.decoded_at_takeover.remove(&tid);
                    tracing::info!(planner = %pid, trolley = %tid, "trolley released");
                    actions.push(PlannerAction::Release { tid });
                }
                (None, None) => {}
                (Some(Role::Replica), Some(slot)) => {
                    slot.become_replica();
                    actions.push(PlannerAction::Release { tid });
                }
                (Some(Role::Owner), Some(_)) if before == Some(Role::Owner) => {}
                (Some(Role::Owner), Some(slot)) => {
                    // A copy still loading begins its term once it is loaded.
                    let (fence, clock_ns) = (&mut self.fence, self.clock_ns);
                    let term = slot.take_over(|| fence.begin_term(&tid, clock_ns));
                    tracing::info!(planner = %pid, trolley = %tid, term = term.unwrap_or(0), "took over as owner");
                    if term.is_some() {
                        taken_over.push(tid);
                    }
                }
                (Some(role), None) => actions.extend(self.take_on(change, role)),
            }
        }
        actions.extend(self.catch_up_taken_over(taken_over));
        actions
    }

    /// A trolley new to this planner: an empty copy that buffers clouds until a snapshot from
    /// the planners that may hold one is loaded (or none is found).
    fn take_on(&mut self, change: &OwnershipChange, role: Role) -> Vec<PlannerAction> {
        let tid = change.trolley.clone();
        let slot = match self.claim_restored(&tid) {
            Some(restored) => Slot::loading(restored.planner, role).restored_under(restored.epoch),
            None => match TrolleyPlanner::new(self.planning.clone()) {
                Ok(planner) => Slot::loading(planner, role),
                Err(_) => return Vec::new(),
            },
        };
        self.slots.insert(tid.clone(), slot);
        let sources = snapshot_sources(change, &self.pid);
        vec![PlannerAction::AskSnapshot {
            tid,
            sources,
            base: None,
        }]
    }

    /// `snapshot` unless it comes under an older ownership epoch than the newest seen for
    /// `tid` (a replaced owner's copy, which may lack what the newer owner integrated): then it
    /// is dropped and counted.
    fn fresh(&mut self, tid: &str, snapshot: Option<Box<MapSnapshot>>) -> Option<Box<MapSnapshot>> {
        let snapshot = snapshot?;
        if self.fence.observe(tid, snapshot.owner_epoch).is_stale() {
            self.refuse_stale(tid, &snapshot.planner_id, "snapshot", snapshot.owner_epoch);
            return None;
        }
        Some(snapshot)
    }

    /// The copy of a trolley new to this planner (or of one it stepped down from) is loaded:
    /// from `snapshot` when there is one, else the copy stays as it is. An owner begins its term
    /// and plans on the last cloud.
    fn on_snapshot(&mut self, tid: &str, snapshot: Option<Box<MapSnapshot>>) -> Vec<PlannerAction> {
        let pid = self.pid.clone();
        let standby = self.replica_refresh_clouds > 0;
        if !self.is_loading(tid) {
            return Vec::new();
        }
        let snapshot = self.fresh(tid, snapshot);
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let role = slot.role();
        // A standby replica keeps the snapshot encoded and the buffered clouds pending.
        if standby && role == Role::Replica {
            if let Some(buffered) = slot.end_loading(Stage::standby()) {
                slot.stand_by_loaded(buffered, snapshot, (&pid, tid));
            }
            return self.decode_held_ahead(tid);
        }
        let from_snapshot = snapshot.is_some_and(|s| self.adopt_snapshot(tid, &s));
        let plan_last = role == Role::Owner;
        let next = match plan_last {
            true => {
                let term = self.fence.begin_term(tid, self.clock_ns);
                tracing::info!(planner = %pid, trolley = %tid, term, from_snapshot, "ownership term begins");
                Stage::Owning { term }
            }
            false => Stage::standby(),
        };
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let Some(buffered) = slot.end_loading(next) else {
            return Vec::new();
        };
        // Nothing came while loading: the owner plans on the last cloud it had (a planner that
        // stepped down; the edge may wait on it).
        if let (true, true, Some(last)) = (plan_last, buffered.is_empty(), slot.last_cloud.clone())
        {
            return self.integrate(tid, last, true);
        }
        self.replay_buffered(tid, buffered, plan_last)
    }

    /// The loading copy of `tid` becomes `snapshot`'s map unless its own holds it and more (or
    /// the snapshot is older or unusable); whether it did.
    fn adopt_snapshot(&mut self, tid: &str, snapshot: &MapSnapshot) -> bool {
        let pid = &self.pid;
        let Some(slot) = self.slots.get_mut(tid) else {
            return false;
        };
        if slot.holds_newer_than(snapshot) {
            return false;
        }
        match TrolleyPlanner::from_snapshot(self.planning.clone(), snapshot) {
            // A copy restored from the store yields to a newer term's snapshot (above).
            Ok(loaded) if slot.restored_epoch == 0 && holds_more(&slot.planner, &loaded) => {
                tracing::warn!(planner = %pid, trolley = %tid, from = %snapshot.planner_id,
                    own_scans = slot.planner.map().scans_inserted(), their_scans = loaded.map().scans_inserted(),
                    "kept its own copy: it holds every frame of the snapshot's and more scans");
                self.stats.kept_own_copy += 1;
                false
            }
            Ok(mut loaded) => {
                tracing::info!(planner = %pid, trolley = %tid, from = %snapshot.planner_id, seq = snapshot.based_on_seq, epoch_ns = snapshot.based_on_epoch_ns, voxels = loaded.map().len(), "snapshot loaded");
                if let Some(info) = slot.planner.info() {
                    if let Err(e) = loaded.set_info(info.clone()) {
                        tracing::warn!(planner = %pid, trolley = %tid, error = %e, "views are not filtered by reach");
                    }
                }
                *slot.planner = loaded;
                slot.unfinished = None;
                true
            }
            Err(e) => {
                tracing::warn!(planner = %pid, trolley = %tid, error = %e, "snapshot unusable: starting from the buffered clouds");
                false
            }
        }
    }

    /// The clouds buffered while loading, integrated in order; those the loaded map already
    /// holds are skipped (fed in order they would look like a live stream behind the map's
    /// mark and resync it), but the last one is still planned on by an owner (the edge may
    /// wait on it).
    fn replay_buffered(
        &mut self,
        tid: &str,
        buffered: Vec<ReceivedCloud>,
        plan_last: bool,
    ) -> Vec<PlannerAction> {
        let mark = self.slots.get(tid).and_then(|s| s.planner.last_frame());
        let n = buffered.len();
        let mut actions = Vec::new();
        for (i, received) in buffered.into_iter().enumerate() {
            let last = i + 1 == n;
            let held = mark.is_some_and(|m| received.cloud.source_frame() <= m);
            if !held || last {
                actions.extend(self.integrate(tid, received, plan_last && last));
            }
        }
        actions
    }

    fn snapshot_of(&self, tid: &str) -> Result<(Header, Box<MapSnapshot>), String> {
        let none = || format!("planner {} holds no up-to-date map of {tid}", self.pid);
        let snapshot = match self.slots.get(tid) {
            Some(slot) if !slot.is_loading() => MapSnapshot {
                owner_epoch: self.fence.newest(tid),
                ..slot
                    .planner
                    .snapshot(tid, &self.pid)
                    .map_err(|e| e.to_string())?
            },
            // A copy restored from the store, still loading: under the epoch it was written in.
            Some(slot) if slot.restored_epoch != 0 => MapSnapshot {
                owner_epoch: slot.restored_epoch,
                ..slot
                    .planner
                    .snapshot(tid, &self.pid)
                    .map_err(|e| e.to_string())?
            },
            Some(_) => return Err(none()),
            None => self.restored_snapshot(tid).ok_or_else(none)??,
        };
        tracing::info!(planner = %self.pid, trolley = %tid, "snapshot asked");
        Ok((self.snapshot_header(tid, &snapshot), Box::new(snapshot)))
    }

    /// The header a snapshot of `tid` is sent with.
    fn snapshot_header(&self, tid: &str, snapshot: &MapSnapshot) -> Header {
        Header {
            seq: snapshot.based_on_seq,
            epoch_ns: self.epoch_ns,
            trolley_id: tid.to_owned(),
            source_id: self.pid.clone(),
            frame_id: "world".into(),
            ..Header::default()
        }
    }

    /// Integrates one cloud into the trolley's copy; with `plan` (the owner), also fits, plans and
    /// publishes. An owner's cloud that is not planned on (a later one is queued) still
    /// publishes its map changes. A replica keeps its map, fruit ids and change tracking exactly
    /// as the owner's.
    fn integrate(&mut self, tid: &str, received: ReceivedCloud, plan: bool) -> Vec<PlannerAction> {
        let then = match plan {
            true => Then::Plan,
            false => Then::Track,
        };
        self.integrate_then(tid, received, then)
    }

    /// [`PlannerNode::integrate`], with what follows the insert chosen by `then`.
    fn integrate_then(
        &mut self,
        tid: &str,
        received: ReceivedCloud,
        then: Then,
    ) -> Vec<PlannerAction> {
        let mut actions = self.finish(tid);
        let pid = self.pid.clone();
        let Some(slot) = self.slots.get_mut(tid) else {
            return actions;
        };
        let started = Instant::now();
        actions.extend(store_term_start(self.store, slot, (&pid, tid)));
        let mut laps = Laps::start();
        let (header, cloud) = (&received.header, &received.cloud);
        let frame = cloud.source_frame();
        let (inserted, registration) = insert_registered(&mut slot.planner, &received);
        self.stats.stages.integrate_ms += laps.lap_ms();
        let verdict = inserted.as_ref().ok().cloned();
        let (stats, refusals) = (&mut self.stats, &mut self.logged_refusals);
        if !note_insert(stats, refusals, (&pid, tid), header, frame, inserted) {
            return actions;
        }
        if let Some(verdict) = verdict {
            actions.extend(store_cloud(self.store, slot, tid, &received, &verdict));
        }
        self.stats.clouds_integrated += 1;
        if let RoiColours::WrongLength { bytes, roi_points } = cloud.roi_colours() {
            note_colourless(
                &mut self.stats,
                &mut self.logged_refusals,
                tid,
                bytes,
                roi_points,
            );
        }
        let camera = cloud.world_from_camera;
        let header = received.header.clone();
        slot.last_cloud = Some(received);
        let unfinished = Unfinished {
            header,
            frame,
            registration,
        };
        if then != Then::ViewsFirst {
            let plan = then == Then::Plan;
            let fit = plan || then == Then::Fit;
            actions.extend(self.track_and_publish(tid, unfinished, (fit, plan), started));
            return actions;
        }
        actions.extend(self.views_now_fruits_later(tid, &camera, unfinished, started));
        actions
    }

    /// Planning reads only the map: the views of `unfinished`'s cloud go out now, its clusters,
    /// fruit ids and fits once the other trolleys taken over have theirs (a `Finish`).
    fn views_now_fruits_later(
        &mut self,
        tid: &str,
        camera: &nalgebra::Isometry3<f64>,
        unfinished: Unfinished,
        started: Instant,
    ) -> Vec<PlannerAction> {
        let views = self.plan_views(tid, camera, unfinished.frame, started);
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let header = unfinished.header.clone();
        slot.unfinished = Some(unfinished);
        let mut laps = Laps::start();
        let mut actions = self.publish(tid, &header, views, None, None);
        self.stats.stages.publish_ms += laps.lap_ms();
        actions.push(PlannerAction::Finish {
            tid: tid.to_owned(),
        });
        actions
    }

    /// What a cloud's views were planned without: its clusters, fruit ids, fits, and the
    /// fruits and map update they publish (none while the trolley is no longer this planner's).
    fn finish(&mut self, tid: &str) -> Vec<PlannerAction> {
        let deferred = self
            .slots
            .get_mut(tid)
            .map(Slot::take_deferred)
            .unwrap_or_default();
        if !deferred.is_empty() {
            return self.integrate_deferred(tid, deferred);
        }
        let Some(unfinished) = self.slots.get_mut(tid).and_then(|s| s.unfinished.take()) else {
            return Vec::new();
        };
        self.track_and_publish(tid, unfinished, (true, false), Instant::now())
    }

    /// The clouds a takeover planned past, integrated in order; the last one's clusters,
    /// fruit ids and fits are made and published.
    fn integrate_deferred(&mut self, tid: &str, clouds: Vec<ReceivedCloud>) -> Vec<PlannerAction> {
        let started = Instant::now();
        let n = clouds.len();
        let mut actions = Vec::new();
        for (i, received) in clouds.into_iter().enumerate() {
            let then = if i + 1 == n { Then::Fit } else { Then::Track };
            actions.extend(self.integrate_then(tid, received, then));
        }
        self.stats.catch_up_ms += started.elapsed().as_secs_f64() * 1e3;
        actions
    }

    /// Clusters and tracks the cloud just integrated and publishes its map update; with `fit`
    /// also the fruits, with `plan` also the views (an owner's outputs; a replica publishes
    /// nothing).
    fn track_and_publish(
        &mut self,
        tid: &str,
        done: Unfinished,
        (fit, plan): (bool, bool),
        started: Instant,
    ) -> Vec<PlannerAction> {
        let pid = self.pid.clone();
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        let mut laps = Laps::start();
        slot.planner.cluster();
        self.stats.stages.cluster_ms += laps.lap_ms();
        slot.planner.track();
        self.stats.stages.track_ms += laps.lap_ms();
        let term = slot.term();
        let seq = done.frame.seq;
        let map = MapUpdate {
            registration: done.registration,
            owner_epoch: term,
            ..slot.planner.map_update(seq, &pid)
        };
        self.stats.stages.publish_ms += laps.lap_ms();
        let owner = slot.role() == Role::Owner;
        let fruits = fit.then(|| {
            let fruits = slot.planner.fruits();
            FruitEstimates {
                history: slot.planner.season_histories(&fruits),
                visit: slot.planner.visit(),
                fruits,
                based_on_seq: seq,
                planner_id: pid.clone(),
                owner_epoch: term,
            }
        });
        let fit_ms = laps.lap_ms();
        if fit {
            self.stats.stages.fit_ms += fit_ms;
        }
        let views = match plan {
            true => {
                let Some(last) = slot.last_cloud.as_ref() else {
                    return Vec::new();
                };
                let (camera, frame) = (last.cloud.world_from_camera, last.cloud.source_frame());
                self.plan_views(tid, &camera, frame, started)
            }
            false => None,
        };
        // The planning counted itself (plan stage).
        laps.lap_ms();
        let mut actions = match owner {
            true => self.publish(tid, &done.header, views, fruits, Some(map)),
            false => Vec::new(),
        };
        // After the views: the clouds it covers are in the log already.
        actions.extend(self.store_checkpoint(tid));
        self.stats.stages.publish_ms += laps.lap_ms();
        actions
    }

    /// The owner's ranked views on `frame`, taken from `camera` (`None`: no info yet, or the
    /// planning failed; logged).
    fn plan_views(
        &mut self,
        tid: &str,
        camera: &nalgebra::Isometry3<f64>,
        frame: FrameId,
        started: Instant,
    ) -> Option<RankedViews> {
        let slot = self.slots.get(tid)?;
        let mut laps = Laps::start();
        let planned = slot.planner.plan(camera, frame.seq);
        self.stats.stages.plan_ms += laps.lap_ms();
        match planned {
            Ok(Some(plan)) => {
                let ms = (started.elapsed().as_secs_f64() * 1e3) as f32;
                Some(RankedViews {
                    owner_epoch: slot.term(),
                    ..ranked_views(&plan, frame, ms, &self.pid)
                })
            }
            Ok(None) => {
                tracing::info!(trolley = %tid, "no TrolleyInfo yet: cloud integrated, planning deferred");
                None
            }
            Err(e) => {
                tracing::warn!(trolley = %tid, seq = frame.seq, error = %e, "planning failed");
                None
            }
        }
    }

    fn publish(
        &mut self,
        tid: &str,
        cloud_header: &Header,
        views: Option<RankedViews>,
        fruits: Option<FruitEstimates>,
        map: Option<MapUpdate>,
    ) -> Vec<PlannerAction> {
        let header = Header {
            seq: cloud_header.seq,
            epoch_ns: self.epoch_ns,
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
        outputs.extend(map.map(|m| TrolleyOutput::Map(Box::new(m))));
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
            let slots = self.slots.iter().filter(move |(_, s)| s.role() == role);
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
            refused_clouds: s.clouds_refused,
            stage_totals: s.stages,
            catch_up_ms: s.catch_up_ms,
            map_voxels: self
                .slots
                .values()
                .map(|s| s.planner.map().len() as u64)
                .sum(),
            registrations: self
                .slots
                .values()
                .filter(|s| s.role() == Role::Owner)
                .fold(RegistrationTotals::default(), |mut sum, s| {
                    sum += registration_totals(s.planner.alignment_counts());
                    sum
                }),
            stale_epoch: s.stale_epoch,
            stepped_down: s.stepped_down,
            unassigned_clouds: s.clouds_unassigned,
            colourless_clouds: s.clouds_colourless,
            standby_decodes_ahead: s.standby_decodes_ahead,
            decoded_ahead_adopted: s.decoded_ahead_adopted,
        };
        let header = Header {
            seq: self.status_seq,
            epoch_ns: self.epoch_ns,
            source_id: self.pid.clone(),
            frame_id: "world".into(),
            ..Header::default()
        };
        let mut actions = vec![PlannerAction::PublishStatus {
            header: header.clone(),
            status,
        }];
        actions.extend(self.store_fruits());
        let first = self.membership.first_ranked(FLEET_MAP_KEY) == Some(self.pid.as_str());
        if first && !self.latest_fruits.is_empty() {
            let fruits = fleet_fruits(&self.latest_fruits, &self.pid);
            actions.push(PlannerAction::PublishFleet { header, fruits });
        }
        actions
    }
}

/// Counts a cloud of trolley `tid` taken without colour, `bytes` colour bytes for `roi_points`
/// ROI points (logged once per trolley).
fn note_colourless(
    stats: &mut PlannerStats,
    logged: &mut BTreeSet<String>,
    tid: &str,
    bytes: usize,
    roi_points: usize,
) {
    stats.clouds_colourless += 1;
    if logged.insert(format!("colourless {tid}")) {
        tracing::warn!(trolley = %tid, bytes, roi_points,
            "cloud taken without colour: its roi_rgb is not 3 bytes per ROI point (logged once per trolley)");
    }
}

/// Counts and logs planner `pid`'s map verdict on a cloud of trolley `tid`; whether the cloud
/// goes on to clustering (a cloud the map rejects or refuses changes nothing).
fn note_insert(
    stats: &mut PlannerStats,
    logged_refusals: &mut BTreeSet<String>,
    (pid, tid): (&str, &str),
    header: &Header,
    frame: FrameId,
    inserted: Result<FrameVerdict, PlanningError>,
) -> bool {
    match inserted {
        Err(e) => {
            stats.clouds_rejected += 1;
            tracing::warn!(trolley = %tid, seq = header.seq, error = %e, "cloud dropped");
            return false;
        }
        Ok(FrameVerdict::Refused(why)) => {
            stats.clouds_refused += 1;
            if logged_refusals.insert(format!("frame {tid}")) {
                tracing::warn!(planner = %pid, trolley = %tid, %frame, source = %header.source_id, reason = %why,
                    "cloud refused: no trolley sends this frame (logged once per trolley)");
            }
            return false;
        }
        Ok(FrameVerdict::Resync { mark }) => {
            tracing::warn!(planner = %pid, trolley = %tid, %frame, %mark, "the trolley's stream overrides the map's last frame");
        }
        Ok(FrameVerdict::Stale) => stats.clouds_stale += 1,
        // Left out of the map (the trolley's planner counts why), still planned on: the edge
        // waits for views on this frame.
        Ok(FrameVerdict::Misaligned) => {
            if logged_refusals.insert(format!("misaligned {tid}")) {
                tracing::warn!(planner = %pid, trolley = %tid, %frame,
                    "cloud not inserted: its registration to the map failed (logged once per trolley)");
            }
        }
        Ok(FrameVerdict::Fresh | FrameVerdict::Repeat) => {}
    }
    true
}

/// `received`'s cloud inserted into `planner`, and its registration when the insert registered
/// it (a repeated or stale frame is not registered again, so the last alignment is not its).
fn insert_registered(
    planner: &mut TrolleyPlanner,
    received: &ReceivedCloud,
) -> (
    Result<FrameVerdict, PlanningError>,
    Option<FrameRegistration>,
) {
    let frame = received.cloud.source_frame();
    let registered_before = *planner.alignment_counts();
    let inserted = planner.insert(&received.cloud, received.received_ns);
    let registration = (*planner.alignment_counts() != registered_before)
        .then(|| planner.last_alignment())
        .flatten()
        .map(|alignment| FrameRegistration {
            hand_eye_correction: planner
                .last_hand_eye_correction()
                .map(RigidCorrection::from_isometry),
            ..frame_registration(frame, alignment)
        });
    (inserted, registration)
}

/// Whether a copy of one trolley holds more than `other`: at least as late a frame and at
/// least as many scans, more of one of them. Copies of one trolley take frames of the same
/// stream in order, so such a copy holds every scan the other does (unless each missed a
/// different cloud) and more. A planner that stepped down keeps its own copy then: the newer
/// owner may have taken over from a replica that missed a cloud while its link moved.
fn holds_more(own: &TrolleyPlanner, other: &TrolleyPlanner) -> bool {
    let (own_scans, other_scans) = (own.map().scans_inserted(), other.map().scans_inserted());
    let (own_last, other_last) = (own.last_frame(), other.last_frame());
    own_last >= other_last
        && own_scans >= other_scans
        && (own_last, own_scans) != (other_last, other_scans)
}

#[cfg(test)]
mod tests;
