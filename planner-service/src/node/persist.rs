//! What a planner keeps in its store, and what it takes back from it at start.
//!
//! The store is a replica on disk of every trolley this planner owns: a checkpoint (fruit ids,
//! last frame, the map's blocks changed since the last checkpoint; every block at the first
//! checkpoint of a term) and, after it, a log of the clouds integrated since. The node decides
//! what to write ([`StoreWrite`], one [`PlannerAction::Store`] each); the driver queues it and
//! holds the trolley's publications that follow until it is durable (`held`), so a trolley's
//! views go out only once the cloud they were planned on is stored and a killed planner loses no
//! integrated scan.
//!
//! At start the driver hands the node what its store held ([`PlannerNode::restore`]): each
//! trolley's checkpoint with its logged clouds integrated on top, kept as a restored copy until
//! the trolley becomes this planner's (the copy it loads, unless another planner answers with a
//! newer term's), and meanwhile answering other planners' snapshot queries under the epoch it
//! was written in. A planner with a store settles first ([`StoreRules::settle_ns`]): it makes no
//! ownership decision until the planners started with it have announced themselves, so that
//! after a full restart no trolley's term begins on an older copy than a peer's store holds.

use glasshouse_pipeline::{FrameVerdict, StoredCopy, TrolleyPlanner};
use glasshouse_proto::{FruitEstimates, Header, MapSnapshot, RoiCloud};

use super::{PlannerAction, PlannerNode};
use crate::slot::{ReceivedCloud, Slot};

/// Clouds a settling planner keeps for after it settled, over all trolleys; the oldest go first.
const SETTLE_HELD_CLOUDS: usize = 256;

/// A write to the planner's store.
#[derive(Clone, Debug, PartialEq)]
pub enum StoreWrite {
    /// The owner integrated this cloud under its term `epoch`: appended to the trolley's log.
    Cloud {
        tid: String,
        epoch: u64,
        header: Header,
        cloud: Box<RoiCloud>,
    },
    /// The trolley's copy at its last integrated cloud, under term `epoch`: its fruit ids,
    /// frame mark and the map's blocks changed since the previous checkpoint of the term (every
    /// block when `full`). The logged clouds it holds are dropped.
    Checkpoint {
        tid: String,
        epoch: u64,
        copy: Box<StoredCopy>,
        full: bool,
    },
    /// Trolleys' latest fruits as their owners published them (the fleet map's input).
    Fruits(Vec<(Header, FruitEstimates)>),
}

impl StoreWrite {
    /// The trolley a cloud or checkpoint write is of.
    pub fn trolley(&self) -> Option<&str> {
        match self {
            StoreWrite::Cloud { tid, .. } | StoreWrite::Checkpoint { tid, .. } => Some(tid),
            StoreWrite::Fruits(_) => None,
        }
    }
}

/// How a planner uses its store.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StoreRules {
    /// Clouds logged between two checkpoints of a trolley.
    pub checkpoint_clouds: usize,
    /// How long after its start a planner makes no ownership decision (its own clock, ns).
    pub settle_ns: u64,
}

/// One trolley as the store held it, decoded by the driver.
#[derive(Clone, Debug)]
pub struct StoredTrolley {
    pub tid: String,
    /// The ownership epoch of the term that wrote it.
    pub epoch: u64,
    /// The checkpoint's fruit ids, last frame and map header ([`TrolleyPlanner::checkpoint`]).
    pub meta: MapSnapshot,
    /// The newest record of each of the map's blocks.
    pub blocks: Vec<Vec<u8>>,
    /// The clouds logged after the checkpoint, in frame order.
    pub clouds: Vec<(Header, RoiCloud)>,
}

/// A restored copy not yet claimed by a slot.
pub(crate) struct Restored {
    pub planner: TrolleyPlanner,
    /// The ownership epoch its store record was written under.
    pub epoch: u64,
}

/// Where the store stands for a slot: the term it was written under, the map's scan count at
/// the last checkpoint and the clouds logged since.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct StoredMark {
    pub term: u64,
    pub scans: u64,
    pub clouds: usize,
}

/// Before an owner's cloud goes into its copy: the first checkpoint of its term (every block,
/// so that the store never mixes an older term's checkpoint with this term's clouds).
pub(super) fn store_term_start(
    store: Option<StoreRules>,
    slot: &mut Slot,
    (pid, tid): (&str, &str),
) -> Option<PlannerAction> {
    store?;
    let epoch = slot.term();
    (epoch != 0 && slot.stored.term != epoch).then(|| checkpoint(slot, (pid, tid), None))
}

/// After an owner's copy started a new visit: a full checkpoint of its new map (the clouds
/// logged so far belong to the visit before, and a full checkpoint drops them).
pub(super) fn store_visit_start(
    store: Option<StoreRules>,
    slot: &mut Slot,
    (pid, tid): (&str, &str),
) -> Option<PlannerAction> {
    store?;
    (slot.term() != 0 && slot.stored.term == slot.term())
        .then(|| checkpoint(slot, (pid, tid), None))
}

/// The store write of a cloud an owner just integrated, when it goes in the log.
pub(super) fn store_cloud(
    store: Option<StoreRules>,
    slot: &mut Slot,
    tid: &str,
    received: &ReceivedCloud,
    verdict: &FrameVerdict,
) -> Option<PlannerAction> {
    store?;
    let epoch = slot.term();
    if epoch == 0 || slot.stored.term != epoch || !logged(verdict) {
        return None;
    }
    slot.stored.clouds += 1;
    Some(PlannerAction::Store(StoreWrite::Cloud {
        tid: tid.to_owned(),
        epoch,
        header: received.header.clone(),
        cloud: Box::new(received.cloud.clone()),
    }))
}

/// A checkpoint of the slot's copy under its term: the blocks changed after `since_scans`
/// scans (None: every block, a full checkpoint).
fn checkpoint(
    slot: &mut Slot,
    (pid, tid): (&str, &str),
    since_scans: Option<u64>,
) -> PlannerAction {
    let epoch = slot.term();
    let copy = slot.planner.checkpoint(tid, pid, since_scans.unwrap_or(0));
    slot.stored = StoredMark {
        term: epoch,
        scans: copy.scans,
        clouds: 0,
    };
    PlannerAction::Store(StoreWrite::Checkpoint {
        tid: tid.to_owned(),
        epoch,
        copy: Box::new(copy),
        full: since_scans.is_none(),
    })
}

/// Whether a cloud the map judged so goes in the log: the ones that moved the map's frame mark
/// (a replay judges them the same way on the same copy).
pub(crate) fn logged(verdict: &FrameVerdict) -> bool {
    matches!(
        verdict,
        FrameVerdict::Fresh | FrameVerdict::Resync { .. } | FrameVerdict::Misaligned
    )
}

impl PlannerNode {
    /// A planner that keeps every trolley it owns in a store by `rules` (the driver performs
    /// the [`PlannerAction::Store`] writes) and settles for `rules.settle_ns` after its start.
    pub fn with_store(mut self, rules: StoreRules) -> Self {
        self.settle_until_ns = self.epoch_ns.saturating_add(rules.settle_ns);
        self.settled = rules.settle_ns == 0;
        self.store = Some(rules);
        self
    }

    /// Whether the planner still waits for its peers before deciding ownership.
    pub fn is_settling(&self) -> bool {
        self.clock_ns < self.settle_until_ns
    }

    /// Takes back what the store held: each trolley's checkpoint with its logged clouds
    /// integrated, kept until the trolley becomes this planner's, and the latest fruits.
    /// Returns a line per trolley that could not be restored (it is left out; the store keeps it).
    pub fn restore(
        &mut self,
        trolleys: Vec<StoredTrolley>,
        fruits: Vec<(Header, FruitEstimates)>,
    ) -> Vec<String> {
        let mut failed = Vec::new();
        for stored in trolleys {
            let tid = stored.tid.clone();
            match self.restore_one(stored) {
                Ok(restored) => {
                    tracing::info!(planner = %self.pid, trolley = %tid, epoch = restored.epoch,
                        last_frame = ?restored.planner.last_frame(), voxels = restored.planner.map().len(), "restored from the store");
                    self.fence.observe(&tid, restored.epoch);
                    self.restored.insert(tid, restored);
                }
                Err(e) => failed.push(format!("trolley {tid}: {e}")),
            }
        }
        for (header, estimates) in fruits {
            let tid = header.trolley_id.clone();
            if !self.fence.observe(&tid, estimates.owner_epoch).is_stale() {
                self.latest_fruits.insert(tid, estimates);
            }
        }
        failed
    }

    fn restore_one(&self, stored: StoredTrolley) -> anyhow::Result<Restored> {
        let blocks = stored.blocks.iter().map(Vec::as_slice);
        let mut planner = TrolleyPlanner::from_stored(self.planning.clone(), &stored.meta, blocks)?;
        for (_, cloud) in &stored.clouds {
            // Replayed as the owner integrated them, with the clusters and fruit ids each made.
            // The owner judged each against its clock then; the clock of now has no say (a
            // frame's epoch is never ahead of the latest time there is).
            let verdict = planner.insert(cloud, u64::MAX)?;
            if logged(&verdict) {
                planner.cluster();
                planner.track();
            }
        }
        Ok(Restored {
            planner,
            epoch: stored.epoch,
        })
    }

    /// A checkpoint of `tid`'s copy after `checkpoint_clouds` logged clouds: the blocks changed
    /// since the last one.
    pub(super) fn store_checkpoint(&mut self, tid: &str) -> Option<PlannerAction> {
        let rules = self.store?;
        let slot = self.slots.get_mut(tid)?;
        let epoch = slot.term();
        let mark = slot.stored;
        if epoch == 0 || mark.term != epoch || mark.clouds < rules.checkpoint_clouds.max(1) {
            return None;
        }
        Some(checkpoint(slot, (&self.pid, tid), Some(mark.scans)))
    }

    /// The fruits that changed since the last status, for the store.
    pub(super) fn store_fruits(&mut self) -> Option<PlannerAction> {
        self.store?;
        let changed = std::mem::take(&mut self.fruits_to_store);
        let fruits: Vec<(Header, FruitEstimates)> = changed
            .into_iter()
            .filter_map(|tid| {
                let estimates = self.latest_fruits.get(&tid)?.clone();
                let header = Header {
                    trolley_id: tid,
                    source_id: estimates.planner_id.clone(),
                    epoch_ns: self.epoch_ns,
                    frame_id: "world".into(),
                    ..Header::default()
                };
                Some((header, estimates))
            })
            .collect();
        (!fruits.is_empty()).then_some(PlannerAction::Store(StoreWrite::Fruits(fruits)))
    }

    /// The copy a trolley new to this planner starts from: the restored one, if any.
    pub(super) fn claim_restored(&mut self, tid: &str) -> Option<Restored> {
        self.restored.remove(tid)
    }

    /// A restored copy's answer to a snapshot query, under the epoch it was written in.
    pub(super) fn restored_snapshot(&self, tid: &str) -> Option<Result<MapSnapshot, String>> {
        let restored = self.restored.get(tid)?;
        Some(
            restored
                .planner
                .snapshot(tid, &self.pid)
                .map(|s| MapSnapshot {
                    owner_epoch: restored.epoch,
                    ..s
                })
                .map_err(|e| e.to_string()),
        )
    }

    /// Keeps a cloud that came while settling (its trolley's owner is not decided yet).
    pub(super) fn hold_while_settling(&mut self, received: ReceivedCloud) {
        self.settle_held.push_back(received);
        while self.settle_held.len() > SETTLE_HELD_CLOUDS {
            self.settle_held.pop_front();
            self.stats.clouds_refused += 1;
        }
    }

    /// Once settled: every live trolley is assigned as if it had just joined, then the clouds
    /// and infos held meanwhile are taken in order.
    pub(super) fn settle_if_due(&mut self) -> Vec<PlannerAction> {
        if self.settled || self.is_settling() {
            return Vec::new();
        }
        self.settled = true;
        let trolleys: Vec<String> = self.membership.trolleys().map(str::to_owned).collect();
        let changes: Vec<glasshouse_fleet::OwnershipChange> = trolleys
            .into_iter()
            .map(|tid| glasshouse_fleet::OwnershipChange {
                after: self.membership.assignment(&tid),
                before: None,
                trolley: tid,
            })
            .collect();
        tracing::info!(planner = %self.pid, trolleys = changes.len(), planners = self.membership.servers().count(), "settled: taking on trolleys");
        let mut actions = self.apply(&changes);
        let infos = std::mem::take(&mut self.settle_infos);
        for (tid, info) in infos {
            actions.extend(self.on_info(&tid, info));
        }
        let held = std::mem::take(&mut self.settle_held);
        for received in held {
            actions.extend(self.on_cloud(received));
        }
        actions
    }
}
