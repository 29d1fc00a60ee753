//! One trolley as a planner holds it ([`Slot`]): its copy of the map, and where the copy stands
//! ([`Stage`]): one enum whose variants are the legal states, changed only by the transition
//! methods below. The node decides when a transition happens; the slot keeps what each state
//! holds consistent (a term only while owning, a held snapshot only while standing by or taking
//! over, clouds buffered only while loading).

use std::sync::Arc;

use crate::node::{StoredMark, Unfinished};
use glasshouse_fleet::Role;
use glasshouse_pipeline::TrolleyPlanner;
use glasshouse_proto::{FrameId, Header, MapSnapshot, RoiCloud};

/// A cloud with the receiver's wall clock at its arrival.
#[derive(Clone, Debug)]
pub(crate) struct ReceivedCloud {
    pub header: Header,
    pub cloud: RoiCloud,
    pub received_ns: u64,
}

/// The owner's snapshot a standby copy holds, and, once decoded ahead of a takeover (on a
/// background thread, when the planner's cores are idle), the copy decoded from it. Once a
/// delta of the owner's has been applied to the decoded copy ([`Slot::apply_delta`]) the delta
/// stands in for the snapshot (its frame mark, term and visit), and `decoded` is what it
/// stands for: a held delta always has its decoded copy, so nothing ever decodes a delta.
pub(crate) struct Held {
    pub snapshot: Arc<MapSnapshot>,
    pub decoded: Option<Box<TrolleyPlanner>>,
}

impl Held {
    fn new(snapshot: Box<MapSnapshot>) -> Self {
        Self {
            snapshot: Arc::from(snapshot),
            decoded: None,
        }
    }
}

/// Where a planner's copy of a trolley stands.
pub(crate) enum Stage {
    /// Waiting for a snapshot (the trolley is new to this planner, or it stepped down from it):
    /// the trolley's clouds are kept until it is loaded. An owner's term begins once loaded.
    Loading {
        role: Role,
        buffered: Vec<ReceivedCloud>,
    },
    /// A replica's copy: the owner's latest snapshot kept encoded (a tenth of the decoded map's
    /// memory; decoded ahead only when the node is told to, see [`Held`]) and the clouds newer
    /// than it, in arrival order, integrated when it catches up; `refresh_asked` while it waits
    /// for a snapshot it asked of the owner. A hot replica integrates every cloud at once and
    /// holds nothing.
    Standby {
        held: Option<Held>,
        pending: Vec<ReceivedCloud>,
        refresh_asked: bool,
    },
    /// An owner whose term began when it took over a standby copy: it catches up on what the
    /// copy holds (and plans on the last cloud) before anything else.
    TakingOver {
        term: u64,
        held: Option<Held>,
        pending: Vec<ReceivedCloud>,
    },
    /// An owner that took over and sent views planned on its copy before integrating the
    /// clouds the copy kept (`deferred`, in arrival order): they are integrated, in order,
    /// before anything else the trolley brings (the node's `finish`).
    CatchingUp {
        term: u64,
        deferred: Vec<ReceivedCloud>,
    },
    /// An owner with an up-to-date copy, planning under its term.
    Owning { term: u64 },
}

impl Stage {
    /// A standby copy holding nothing beyond its map.
    pub fn standby() -> Stage {
        Stage::Standby {
            held: None,
            pending: Vec::new(),
            refresh_asked: false,
        }
    }
}

/// A trolley this planner owns or replicates.
pub(crate) struct Slot {
    pub planner: Box<TrolleyPlanner>,
    /// The latest cloud: a planner that takes over plans on it at once.
    pub last_cloud: Option<ReceivedCloud>,
    pub stage: Stage,
    /// The latest cloud's clusters, fruit ids and fits, when its views went out first.
    pub unfinished: Option<Unfinished>,
    /// What this planner's store holds of the copy.
    pub stored: StoredMark,
    /// The ownership epoch of the store record the copy was restored from (0: not restored).
    pub restored_epoch: u64,
}

impl Slot {
    /// A copy new to this planner, in `role`: empty, loading.
    pub fn loading(planner: TrolleyPlanner, role: Role) -> Self {
        Self {
            planner: Box::new(planner),
            last_cloud: None,
            unfinished: None,
            stored: StoredMark::default(),
            restored_epoch: 0,
            stage: Stage::Loading {
                role,
                buffered: Vec::new(),
            },
        }
    }

    /// The copy was restored from a store record written under `epoch`.
    pub fn restored_under(mut self, epoch: u64) -> Self {
        self.restored_epoch = epoch;
        self
    }

    /// Whether the copy, restored from the store, is newer than `snapshot`: written in the same
    /// term or a later one, and holding a later frame.
    pub fn holds_newer_than(&self, snapshot: &MapSnapshot) -> bool {
        self.restored_epoch != 0
            && snapshot.owner_epoch <= self.restored_epoch
            && based_on(snapshot) < self.planner.last_frame()
    }

    pub fn role(&self) -> Role {
        match &self.stage {
            Stage::Loading { role, .. } => *role,
            Stage::Standby { .. } => Role::Replica,
            Stage::TakingOver { .. } | Stage::CatchingUp { .. } | Stage::Owning { .. } => {
                Role::Owner
            }
        }
    }

    /// The epoch of the ownership term the copy's outputs carry; 0 while it is no owner, or an
    /// owner whose copy is still loading.
    pub fn term(&self) -> u64 {
        match &self.stage {
            Stage::TakingOver { term, .. }
            | Stage::CatchingUp { term, .. }
            | Stage::Owning { term } => *term,
            Stage::Loading { .. } | Stage::Standby { .. } => 0,
        }
    }

    pub fn is_loading(&self) -> bool {
        matches!(self.stage, Stage::Loading { .. })
    }

    /// Clouds the copy keeps beyond its map, not yet integrated (a standby copy's, or a taking
    /// over owner's).
    pub fn pending_len(&self) -> usize {
        match &self.stage {
            Stage::Standby { pending, .. } | Stage::TakingOver { pending, .. } => pending.len(),
            Stage::CatchingUp { deferred, .. } => deferred.len(),
            Stage::Loading { .. } | Stage::Owning { .. } => 0,
        }
    }

    /// Another planner owns the trolley now: what an owner's copy held stays held as a
    /// standby's; a loading copy goes on loading as a replica's.
    pub fn become_replica(&mut self) {
        self.stage = match std::mem::replace(&mut self.stage, Stage::standby()) {
            Stage::Loading { buffered, .. } => Stage::Loading {
                role: Role::Replica,
                buffered,
            },
            Stage::TakingOver { held, pending, .. } => Stage::Standby {
                held,
                pending,
                refresh_asked: false,
            },
            Stage::CatchingUp { deferred, .. } => Stage::Standby {
                held: None,
                pending: deferred,
                refresh_asked: false,
            },
            Stage::Owning { .. } => Stage::standby(),
            standing_by @ Stage::Standby { .. } => standing_by,
        };
    }

    /// This planner owns the trolley now. A standby copy takes over under the term `begin_term`
    /// gives (returned); a loading copy goes on loading as the owner's and begins its term once
    /// loaded (None); an owner stays as it is (None).
    pub fn take_over(&mut self, begin_term: impl FnOnce() -> u64) -> Option<u64> {
        match std::mem::replace(&mut self.stage, Stage::standby()) {
            Stage::Standby { held, pending, .. } => {
                let term = begin_term();
                self.stage = Stage::TakingOver {
                    term,
                    held,
                    pending,
                };
                Some(term)
            }
            Stage::Loading { buffered, .. } => {
                self.stage = Stage::Loading {
                    role: Role::Owner,
                    buffered,
                };
                None
            }
            owner => {
                self.stage = owner;
                None
            }
        }
    }

    /// The owner's term is over (a newer one began elsewhere): the copy falls back to what this
    /// planner holds, decoded, and loads again, its kept clouds waiting for the snapshot with
    /// the ones to come. Returns the term given up (0 for no owner: nothing changes then).
    pub fn step_down(&mut self, pid: &str, tid: &str) -> u64 {
        let term = self.term();
        let (held, pending) = match std::mem::replace(&mut self.stage, Stage::standby()) {
            Stage::TakingOver { held, pending, .. } => (held, pending),
            Stage::CatchingUp { deferred, .. } => (None, deferred),
            Stage::Owning { .. } => (None, Vec::new()),
            other => {
                self.stage = other;
                return 0;
            }
        };
        // The copy is replaced by a snapshot: what was left of its last cloud goes with it.
        self.unfinished = None;
        if let Some(held) = held {
            if let Err(e) = self.restore_held(held) {
                tracing::warn!(planner = %pid, trolley = %tid, error = %e, "held snapshot not restored");
            }
        }
        self.stage = Stage::Loading {
            role: Role::Owner,
            buffered: pending,
        };
        term
    }

    /// The copy is loaded: it goes on as `next` (an owner's term, a standby copy); returns the
    /// clouds buffered meanwhile. Nothing when it was not loading.
    pub fn end_loading(&mut self, next: Stage) -> Option<Vec<ReceivedCloud>> {
        if !self.is_loading() {
            return None;
        }
        match std::mem::replace(&mut self.stage, next) {
            Stage::Loading { buffered, .. } => Some(buffered),
            _ => None,
        }
    }

    /// Loaded as a standby copy: `buffered` kept pending, `snapshot` held when it is whole and
    /// not older than the copy.
    pub fn stand_by_loaded(
        &mut self,
        buffered: Vec<ReceivedCloud>,
        snapshot: Option<Box<MapSnapshot>>,
        (pid, tid): (&str, &str),
    ) {
        self.last_cloud = buffered.last().cloned();
        self.stage = Stage::Standby {
            held: None,
            pending: buffered,
            refresh_asked: false,
        };
        if let Some(snapshot) = snapshot {
            self.hold(snapshot, pid, tid);
        }
    }

    /// The copy becomes what `held` holds: the copy decoded ahead when there is one, else the
    /// snapshot decoded now.
    pub fn restore_held(&mut self, held: Held) -> Result<(), glasshouse_pipeline::PlanningError> {
        match held.decoded {
            Some(copy) => {
                self.planner.adopt(*copy);
                Ok(())
            }
            None => self.planner.restore(&held.snapshot),
        }
    }

    /// The held snapshot a standby copy has not decoded yet (to be decoded ahead).
    pub fn to_decode(&self) -> Option<Arc<MapSnapshot>> {
        match &self.stage {
            Stage::Standby {
                held: Some(held), ..
            } if held.decoded.is_none() => Some(held.snapshot.clone()),
            _ => None,
        }
    }

    /// Keeps `copy`, decoded ahead from `snapshot`, when `snapshot` is still the one held and
    /// not yet decoded; returns whether it was kept (a newer snapshot supersedes it).
    pub fn keep_decoded(&mut self, snapshot: &Arc<MapSnapshot>, copy: Box<TrolleyPlanner>) -> bool {
        let (Stage::Standby {
            held: Some(held), ..
        }
        | Stage::TakingOver {
            held: Some(held), ..
        }) = &mut self.stage
        else {
            return false;
        };
        if !Arc::ptr_eq(&held.snapshot, snapshot) || held.decoded.is_some() {
            return false;
        }
        held.decoded = Some(copy);
        true
    }

    /// What a copy taking over holds, taken out to be decoded elsewhere (the decoded copy is
    /// then [`TrolleyPlanner::adopt`]ed): the copy stays taking over, its pending clouds newer
    /// than the snapshot. None for any other copy.
    pub fn take_held(&mut self) -> Option<Held> {
        match &mut self.stage {
            Stage::TakingOver { held, .. } => held.take(),
            _ => None,
        }
    }

    /// What the copy holds beyond its map, taken out to be integrated (the held snapshot, the
    /// pending clouds): an owner taking over owns from now on, a standby copy holds nothing more.
    /// None while loading.
    pub fn take_backlog(&mut self) -> Option<(Option<Held>, Vec<ReceivedCloud>)> {
        match &mut self.stage {
            Stage::Loading { .. } => None,
            Stage::Owning { .. } => Some((None, Vec::new())),
            Stage::Standby { held, pending, .. } => Some((held.take(), std::mem::take(pending))),
            Stage::TakingOver {
                term,
                held,
                pending,
            } => {
                let backlog = (held.take(), std::mem::take(pending));
                self.stage = Stage::Owning { term: *term };
                Some(backlog)
            }
            Stage::CatchingUp { term, deferred } => {
                let backlog = (None, std::mem::take(deferred));
                self.stage = Stage::Owning { term: *term };
                Some(backlog)
            }
        }
    }

    /// An owner leaves `clouds` to integrate after the views it plans now (a takeover);
    /// given back unless the copy is an up-to-date owner's.
    pub fn defer(&mut self, clouds: Vec<ReceivedCloud>) -> Result<(), Vec<ReceivedCloud>> {
        match self.stage {
            Stage::Owning { term } => {
                self.stage = Stage::CatchingUp {
                    term,
                    deferred: clouds,
                };
                Ok(())
            }
            _ => Err(clouds),
        }
    }

    /// The clouds an owner deferred, taken to be integrated in order (none for any other copy).
    pub fn take_deferred(&mut self) -> Vec<ReceivedCloud> {
        match &mut self.stage {
            Stage::CatchingUp { term, deferred } => {
                let clouds = std::mem::take(deferred);
                self.stage = Stage::Owning { term: *term };
                clouds
            }
            _ => Vec::new(),
        }
    }

    /// A standby copy keeps `snapshot` encoded when it is whole and not older than the copy, and
    /// drops the pending clouds it holds; returns whether it was kept.
    pub fn hold(&mut self, snapshot: Box<MapSnapshot>, pid: &str, tid: &str) -> bool {
        let snapshot_frame = based_on(&snapshot);
        let mark = self.copy_mark();
        if mark.is_some_and(|m| snapshot_frame.is_none_or(|b| b < m)) {
            return false;
        }
        if let Err(e) = TrolleyPlanner::check_snapshot(&snapshot) {
            tracing::warn!(planner = %pid, trolley = %tid, error = %e, "snapshot damaged");
            return false;
        }
        let Stage::Standby { held, pending, .. } = &mut self.stage else {
            return false;
        };
        pending.retain(|c| snapshot_frame.is_none_or(|b| c.cloud.source_frame() > b));
        *held = Some(Held::new(snapshot));
        self.unfinished = None;
        if let Err(e) = self.planner.clear() {
            tracing::warn!(planner = %pid, trolley = %tid, error = %e, "copy not cleared");
        }
        true
    }

    /// The last frame the copy holds: the held snapshot's, else the map's.
    pub fn copy_mark(&self) -> Option<FrameId> {
        match &self.stage {
            Stage::Standby {
                held: Some(held), ..
            }
            | Stage::TakingOver {
                held: Some(held), ..
            } => based_on(&held.snapshot),
            _ => self.planner.last_frame(),
        }
    }
}

/// The last frame a snapshot holds; None for a map without frames.
pub(crate) fn based_on(snapshot: &MapSnapshot) -> Option<FrameId> {
    let frame = FrameId::new(snapshot.based_on_epoch_ns, snapshot.based_on_seq);
    (frame != FrameId::default()).then_some(frame)
}

#[cfg(test)]
mod tests {
    use glasshouse_pipeline::PlanningSettings;
    use glasshouse_proto::samples;

    use super::*;

    fn slot(role: Role) -> Slot {
        let planner = TrolleyPlanner::new(PlanningSettings::default()).expect("planner");
        Slot::loading(planner, role)
    }

    fn cloud(seq: u64) -> ReceivedCloud {
        ReceivedCloud {
            header: Header::default(),
            cloud: RoiCloud {
                source_frame_seq: seq,
                ..samples::roi_cloud()
            },
            received_ns: seq,
        }
    }

    fn seqs(clouds: &[ReceivedCloud]) -> Vec<u64> {
        clouds.iter().map(|c| c.cloud.source_frame_seq).collect()
    }

    #[test]
    fn a_loading_copy_that_takes_over_begins_its_term_only_once_loaded() {
        let mut s = slot(Role::Replica);
        if let Stage::Loading { buffered, .. } = &mut s.stage {
            buffered.push(cloud(1));
        }
        assert_eq!(s.take_over(|| panic!("no term while loading")), None);
        assert_eq!((s.role(), s.term()), (Role::Owner, 0));
        let buffered = s
            .end_loading(Stage::Owning { term: 5 })
            .expect("was loading");
        assert_eq!(seqs(&buffered), [1]);
        assert_eq!((s.role(), s.term()), (Role::Owner, 5));
        assert!(s.end_loading(Stage::standby()).is_none(), "loaded once");
    }

    #[test]
    fn a_standby_copy_takes_over_under_a_new_term_and_owns_once_caught_up() {
        let mut s = slot(Role::Replica);
        s.end_loading(Stage::standby());
        if let Stage::Standby { pending, .. } = &mut s.stage {
            pending.extend([cloud(1), cloud(2)]);
        }
        assert_eq!(s.take_over(|| 9), Some(9));
        assert!(matches!(s.stage, Stage::TakingOver { term: 9, .. }));
        assert_eq!(s.pending_len(), 2);
        let (held, pending) = s.take_backlog().expect("not loading");
        assert!(held.is_none());
        assert_eq!(seqs(&pending), [1, 2]);
        assert!(matches!(s.stage, Stage::Owning { term: 9 }));
        // Already owner: no second term.
        assert_eq!(s.take_over(|| 10), None);
        assert_eq!(s.term(), 9);
    }

    #[test]
    fn an_owner_handed_over_keeps_what_it_held_as_a_standby_copy() {
        let mut s = slot(Role::Replica);
        s.end_loading(Stage::standby());
        s.take_over(|| 3);
        if let Stage::TakingOver { pending, .. } = &mut s.stage {
            pending.push(cloud(4));
        }
        s.become_replica();
        assert!(matches!(
            s.stage,
            Stage::Standby {
                refresh_asked: false,
                ..
            }
        ));
        assert_eq!((s.role(), s.term(), s.pending_len()), (Role::Replica, 0, 1));
    }

    #[test]
    fn an_owner_steps_down_to_loading_with_its_kept_clouds_and_a_replica_cannot() {
        let mut s = slot(Role::Owner);
        s.end_loading(Stage::standby());
        assert_eq!(s.step_down("p1", "t1"), 0, "a replica has no term");
        assert_eq!(s.role(), Role::Replica);
        s.take_over(|| 7);
        if let Stage::TakingOver { pending, .. } = &mut s.stage {
            pending.push(cloud(8));
        }
        assert_eq!(s.step_down("p1", "t1"), 7);
        let Stage::Loading { role, buffered } = &s.stage else {
            panic!("stepped down to loading");
        };
        assert_eq!((*role, seqs(buffered)), (Role::Owner, vec![8]));
        assert_eq!(s.term(), 0);
    }

    #[test]
    fn an_owners_deferred_clouds_are_kept_until_taken_and_survive_a_hand_over() {
        let mut s = slot(Role::Replica);
        s.end_loading(Stage::standby());
        let refused = s
            .defer(vec![cloud(1)])
            .expect_err("a replica defers nothing");
        assert_eq!(seqs(&refused), [1]);
        s.take_over(|| 4);
        s.take_backlog();
        s.defer(vec![cloud(2), cloud(3)]).expect("an owner defers");
        assert_eq!((s.role(), s.term(), s.pending_len()), (Role::Owner, 4, 2));
        assert_eq!(seqs(&s.take_deferred()), [2, 3]);
        assert!(matches!(s.stage, Stage::Owning { term: 4 }));
        assert!(s.take_deferred().is_empty());
        // Handed over before they were integrated: they stay pending on the standby copy.
        s.defer(vec![cloud(5)]).expect("an owner defers");
        s.become_replica();
        assert_eq!((s.role(), s.pending_len()), (Role::Replica, 1));
        // Or stepped down: they wait for the snapshot with the clouds to come.
        s.take_over(|| 6);
        s.take_backlog();
        s.defer(vec![cloud(7)]).expect("an owner defers");
        assert_eq!(s.step_down("p1", "t1"), 6);
        let Stage::Loading { buffered, .. } = &s.stage else {
            panic!("stepped down to loading");
        };
        assert_eq!(seqs(buffered), [7]);
    }
}
