//! Taking over several trolleys at once (a lost planner's, say): their held snapshots are
//! decoded side by side, one thread each, before the first of them is planned on.
//!
//! A standby copy keeps its owner's snapshot encoded and decodes it only when it takes over.
//! Decoded one after another, each further trolley's first views waited on every decode before
//! its own: with six trolleys moved by a killed planner in the 16-trolley row, the last one was
//! back on views 1.4 s after the kill, about a quarter of a second per trolley before it.
//! Decoding is pure (a snapshot in, a copy out), so the decodes run on scoped threads: with a
//! core per decode every trolley taken over waits for the slowest of them, on fewer cores for
//! their sum over the cores, against the sum of those before its own; the views then go
//! out one trolley after another as before, and each copy's kept clouds are integrated after
//! all of them. A copy whose snapshot was already decoded in the background while it stood by
//! (`PlannerNode::with_standby_decoded_ahead`) is not decoded again.

use std::sync::Arc;
use std::time::Instant;

use glasshouse_pipeline::{PlanningError, TrolleyPlanner};
use glasshouse_proto::MapSnapshot;

use super::{decode_timed, PlannerAction, PlannerNode, TakeoverDecode};
use crate::slot::Held;

impl PlannerNode {
    /// Catches up the trolleys `taken_over` (in order): the first at once, the others one
    /// [`PlannerAction::CatchUp`] event each, so that other events are heard between them; the
    /// first one's rest (its kept clouds, clusters and fits) goes after the others' views.
    pub(super) fn catch_up_taken_over(&mut self, taken_over: Vec<String>) -> Vec<PlannerAction> {
        let mut taken_over = taken_over.into_iter();
        let Some(first) = taken_over.next() else {
            return Vec::new();
        };
        let rest: Vec<String> = taken_over.collect();
        if !rest.is_empty() && self.takeover_decode_threads > 1 {
            let all: Vec<&str> = std::iter::once(first.as_str())
                .chain(rest.iter().map(String::as_str))
                .collect();
            self.decode_side_by_side(&all);
        }
        let (finishes, mut actions): (Vec<_>, Vec<_>) = self
            .catch_up(&first, true)
            .into_iter()
            .partition(|a| matches!(a, PlannerAction::Finish { .. }));
        actions.extend(rest.into_iter().map(|tid| PlannerAction::CatchUp { tid }));
        actions.extend(finishes);
        actions
    }

    /// Decodes the snapshots the copies of `tids` hold, side by side, and has each copy adopt
    /// its own (a copy decoded in the background while standing by is adopted as it is); a
    /// snapshot that does not decode leaves its copy as it is, as a catch-up would.
    fn decode_side_by_side(&mut self, tids: &[&str]) {
        let started = Instant::now();
        let mut held: Vec<(String, Arc<MapSnapshot>)> = Vec::new();
        for &tid in tids {
            let Some(slot) = self.slots.get_mut(tid) else {
                continue;
            };
            match slot.take_held() {
                Some(Held {
                    decoded: Some(copy),
                    ..
                }) => {
                    slot.planner.adopt(*copy);
                    let adopted = TakeoverDecode {
                        decode_ms: 0.0,
                        standby_copy: true,
                    };
                    self.decoded_at_takeover.insert(tid.to_owned(), adopted);
                    self.stats.decoded_ahead_adopted += 1;
                }
                Some(Held { snapshot, .. }) => held.push((tid.to_owned(), snapshot)),
                None => {}
            }
        }
        let threads = self.takeover_decode_threads;
        for (tid, decoded, ms) in decode_all(&self.planning, held, threads) {
            match (decoded, self.slots.get_mut(&tid)) {
                (Ok(copy), Some(slot)) => {
                    slot.planner.adopt(copy);
                    let decoded = TakeoverDecode {
                        decode_ms: ms,
                        standby_copy: false,
                    };
                    self.decoded_at_takeover.insert(tid, decoded);
                }
                (Err(e), _) => {
                    tracing::error!(planner = %self.pid, trolley = %tid, error = %e,
                        "the owner's snapshot does not load: the kept clouds go on the copy as it is");
                }
                (Ok(_), None) => {}
            }
        }
        self.stats.catch_up_ms += started.elapsed().as_secs_f64() * 1e3;
    }
}

/// Each trolley's copy decoded from its snapshot, with the ms its decode took, in input order.
type Decoded = (String, Result<TrolleyPlanner, PlanningError>, f64);

fn decode_all(
    settings: &glasshouse_pipeline::PlanningSettings,
    held: Vec<(String, Arc<MapSnapshot>)>,
    threads: usize,
) -> Vec<Decoded> {
    glasshouse_pipeline::parallel::in_parallel(held.len(), threads, |i| {
        let (tid, snapshot) = &held[i];
        let (copy, ms) = decode_timed(settings, snapshot);
        (tid.clone(), copy, ms)
    })
}
