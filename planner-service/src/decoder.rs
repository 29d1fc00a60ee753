//! The driver's background decoder: standby copies' snapshots decoded ahead of a takeover
//! ([`crate::node::PlannerAction::DecodeAhead`]) on one thread of the lowest scheduling class
//! (`SCHED_IDLE` on Linux), so the decoding takes only CPU time that nothing else of the machine
//! wants: the planner's own work, the detectors and the edges always go first.

use std::collections::BTreeMap;
use std::sync::mpsc;
use std::sync::Arc;

use glasshouse_pipeline::PlanningSettings;
use glasshouse_proto::MapSnapshot;
use tokio::sync::mpsc::UnboundedSender;

use crate::node::{decode_ahead, PlannerEvent};

type Job = (String, Arc<MapSnapshot>);

/// Hands snapshots to the decoding thread; the thread stops when this is dropped.
pub(crate) struct StandbyDecoder {
    jobs: mpsc::Sender<Job>,
}

impl StandbyDecoder {
    /// Starts the thread; each decoded copy is fed back to the node through `events`.
    pub fn start(
        planning: PlanningSettings,
        events: UnboundedSender<PlannerEvent>,
    ) -> std::io::Result<Self> {
        let (jobs, queue) = mpsc::channel();
        std::thread::Builder::new()
            .name("standby-decoder".into())
            .spawn(move || decode_queued(&planning, &queue, &events))?;
        Ok(Self { jobs })
    }

    /// Queues `snapshot` of `tid`; a later one of the same trolley queued before the thread
    /// gets to it replaces it.
    pub fn decode(&self, tid: String, snapshot: Arc<MapSnapshot>) {
        // The thread ends only with the node's event queue, which outlives this sender's use.
        let _ = self.jobs.send((tid, snapshot));
    }
}

fn decode_queued(
    planning: &PlanningSettings,
    queue: &mpsc::Receiver<Job>,
    events: &UnboundedSender<PlannerEvent>,
) {
    if let Err(e) = lowest_priority() {
        tracing::warn!(error = %e, "the standby decoder runs at normal priority");
    }
    while let Ok(first) = queue.recv() {
        // Only each trolley's latest snapshot is worth decoding.
        let mut latest: BTreeMap<String, Arc<MapSnapshot>> = BTreeMap::new();
        for (tid, snapshot) in std::iter::once(first).chain(queue.try_iter()) {
            latest.insert(tid, snapshot);
        }
        for (tid, snapshot) in latest {
            if events.send(decode_ahead(planning, tid, snapshot)).is_err() {
                return;
            }
        }
    }
}

/// Puts the calling thread in the idle scheduling class (it runs only on a core nothing else
/// wants).
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
fn lowest_priority() -> std::io::Result<()> {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: sched_setscheduler reads `param` only; pid 0 is the calling thread.
    match unsafe { libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) } {
        0 => Ok(()),
        _ => Err(std::io::Error::last_os_error()),
    }
}

#[cfg(not(target_os = "linux"))]
fn lowest_priority() -> std::io::Result<()> {
    Err(std::io::Error::other(
        "no idle scheduling class on this system",
    ))
}
