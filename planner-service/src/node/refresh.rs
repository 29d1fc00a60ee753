//! A standby copy's refresh by delta: the copy tells its owner what it holds (a snapshot of that
//! owner's, under which term and visit, decoded ahead to a map of so many scans: a
//! [`DeltaBase`]), and an owner still in that term answers with only the map's blocks changed
//! since ([`glasshouse_pipeline::TrolleyPlanner::snapshot_delta`]) instead of the whole map. The copy applies them to
//! its decoded map ([`glasshouse_pipeline::TrolleyPlanner::apply_delta`]). The owner's cost of a refresh then follows
//! what changed, not the map's size, and the copy decodes nothing.
//!
//! An owner's map changes only by its own scans within one term (a new term begins after a
//! takeover, a step-down or a restart; a new visit replaces the map by a prior), so a delta is
//! answered only when the base names this planner, its current term and visit, and a scan count
//! its map has reached; any other ask is answered with the whole map. A delta that does not
//! apply leaves the copy as it was, and its kept clouds are integrated instead, as for a
//! snapshot that does not come.

use std::sync::Arc;

use glasshouse_proto::{Header, MapSnapshot};

use super::{PlannerAction, PlannerNode};
use crate::slot::{based_on, Slot, Stage};

/// What a standby copy holds of its owner's map: the base an owner's delta must start from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DeltaBase {
    /// The planner whose snapshot the copy holds.
    pub planner_id: String,
    /// The ownership epoch that snapshot carried.
    pub owner_epoch: u64,
    /// The trolley's visit it was of.
    pub visit: u32,
    /// The scan count of the map the copy decoded (and brought up to date) from it.
    pub scans: u64,
}

impl DeltaBase {
    /// The query parameter that carries the base: `planner,epoch,visit,scans`.
    pub fn to_parameter(&self) -> String {
        format!(
            "{},{},{},{}",
            self.planner_id, self.owner_epoch, self.visit, self.scans
        )
    }

    /// Reads [`DeltaBase::to_parameter`]; None for anything else (the ask is then answered
    /// with the whole map).
    pub fn parse(parameter: &str) -> Option<Self> {
        let mut parts = parameter.split(',');
        let planner_id = parts.next()?;
        glasshouse_proto::keys::validate_id(planner_id).ok()?;
        let base = Self {
            planner_id: planner_id.to_owned(),
            owner_epoch: parts.next()?.parse().ok()?,
            visit: parts.next()?.parse().ok()?,
            scans: parts.next()?.parse().ok()?,
        };
        parts.next().is_none().then_some(base)
    }
}

impl Slot {
    /// The base of a refresh asked of `owner`: the held snapshot's when it is `owner`'s and
    /// decoded ahead (a delta needs a decoded map to apply to); None asks for the whole map.
    pub fn delta_base(&self, owner: &str) -> Option<DeltaBase> {
        let Stage::Standby {
            held: Some(held), ..
        } = &self.stage
        else {
            return None;
        };
        let copy = held.decoded.as_ref()?;
        (held.snapshot.planner_id == owner).then(|| DeltaBase {
            planner_id: owner.to_owned(),
            owner_epoch: held.snapshot.owner_epoch,
            visit: held.snapshot.visit,
            scans: copy.map().scans_inserted(),
        })
    }

    /// Applies the owner's delta to the decoded copy a standby holds; the delta becomes the
    /// held snapshot (the decoded copy is what it stands for) and the pending clouds it holds
    /// are dropped. On an error (no decoded copy, an older frame, a delta from another base)
    /// nothing changes.
    pub fn apply_delta(&mut self, snapshot: Box<MapSnapshot>) -> Result<(), String> {
        let frame = based_on(&snapshot);
        let Stage::Standby {
            held: Some(held),
            pending,
            ..
        } = &mut self.stage
        else {
            return Err("no held snapshot to apply it to".into());
        };
        let Some(copy) = held.decoded.as_mut() else {
            return Err("the held snapshot is not decoded".into());
        };
        if frame < based_on(&held.snapshot) {
            return Err("older than the copy".into());
        }
        copy.apply_delta(&snapshot).map_err(|e| e.to_string())?;
        pending.retain(|c| frame.is_none_or(|b| c.cloud.source_frame() > b));
        held.snapshot = Arc::from(snapshot);
        self.unfinished = None;
        Ok(())
    }
}

impl PlannerNode {
    /// This owner's answer to a standby copy holding `base`: the blocks changed since, when the
    /// base is this planner's current term and visit; None when only the whole map will do.
    pub(super) fn delta_of(
        &mut self,
        tid: &str,
        base: &DeltaBase,
    ) -> Option<Result<(Header, Box<MapSnapshot>), String>> {
        let slot = self.slots.get(tid)?;
        let epoch = self.fence.newest(tid);
        let current = base.planner_id == self.pid
            && matches!(slot.stage, Stage::Owning { term } if term == epoch)
            && base.owner_epoch == epoch
            && base.visit == slot.planner.visit()
            && base.scans <= slot.planner.map().scans_inserted();
        if !current {
            return None;
        }
        let answer = slot
            .planner
            .snapshot_delta(tid, &self.pid, base.scans)
            .map(|delta| {
                let snapshot = MapSnapshot {
                    owner_epoch: epoch,
                    ..delta
                };
                (self.snapshot_header(tid, &snapshot), Box::new(snapshot))
            })
            .map_err(|e| e.to_string());
        self.stats.snapshot_deltas_sent += u64::from(answer.is_ok());
        tracing::info!(planner = %self.pid, trolley = %tid, since_scans = base.scans, "delta asked");
        Some(answer)
    }

    /// A standby copy's refresh answered with a delta: applied to its decoded copy, or, when
    /// it does not apply, the kept clouds are integrated instead.
    pub(super) fn on_refresh_delta(
        &mut self,
        tid: &str,
        snapshot: Box<MapSnapshot>,
    ) -> Vec<PlannerAction> {
        let Some(slot) = self.slots.get_mut(tid) else {
            return Vec::new();
        };
        match slot.apply_delta(snapshot) {
            Ok(()) => {
                self.stats.snapshot_deltas_applied += 1;
                Vec::new()
            }
            Err(e) => {
                tracing::warn!(planner = %self.pid, trolley = %tid, error = %e,
                    "the owner's delta does not apply: the kept clouds go on the copy as it is");
                self.catch_up(tid, false)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_base_reads_back_from_its_parameter_and_nothing_else_reads_as_one() {
        let base = DeltaBase {
            planner_id: "p-2".into(),
            owner_epoch: 1_790_000_000_000_000_123,
            visit: 3,
            scans: 42,
        };
        assert_eq!(DeltaBase::parse(&base.to_parameter()), Some(base));
        for bad in [
            "",
            "p1",
            "p1,1,2",
            "p1,1,2,3,4",
            "p 1,1,2,3",
            "p1,-1,2,3",
            "p1,1,x,3",
            "p1/x,1,2,3",
        ] {
            assert_eq!(DeltaBase::parse(bad), None, "{bad:?}");
        }
    }
}
