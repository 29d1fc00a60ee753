//! The fault `fleet-bench --fault` injects half-way through the run, and what it did to every
//! trolley it moved: when each was back on views, whether an arm moved on a stale owner's views,
//! and (`lost`) whether its map lost a scan.
//!
//! Planner faults hit the owner of t1 and move every trolley it owned then: `kill` (SIGKILL: its
//! links close at once), `stop` (SIGSTOP: a hung planner whose links stay open until the lease
//! expires; SIGCONT after `--fault-for-s`) and `partition` (its link to the router cut by the
//! relay it connects through, `glasshouse relay`: no byte passes and no connection closes, as
//! behind a dead switch; healed after `--fault-for-s`). Router faults move every trolley:
//! `router-restart` (SIGKILL, a new router on the same endpoint after `--fault-for-s`) and
//! `router-failover` (two routers, every client knowing both; the one they use is killed).
//! `restart-all` kills every planner and the router, then starts them again after
//! `--fault-for-s` on the planners' stores: every trolley's map and fruit ids come back from
//! disk. For every fault each moved trolley's fruit ids are checked too: an id its fruits carried
//! before the fault that no fruits after it carry at the same place is lost.

use std::collections::{BTreeMap, HashMap};
use std::process::Command;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use glasshouse_proto::OwnerTerm;
use serde::Serialize;

use super::lost::LostReport;
use super::{cpu_seconds, percentile, Fleet, Observed, Proc, TrolleyLog};

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Fault {
    /// SIGKILL the owner of t1.
    Kill,
    /// SIGSTOP the owner of t1 (hung, links open), SIGCONT after --fault-for-s.
    Stop,
    /// Cut the owner of t1 off the router without closing its links, heal after --fault-for-s.
    Partition,
    /// SIGKILL the router, start a new one on the same endpoint after --fault-for-s.
    RouterRestart,
    /// Two routers, every client knowing both: SIGKILL the one the clients use.
    RouterFailover,
    /// SIGKILL every planner and the router; start them again after --fault-for-s, each planner
    /// on its store.
    RestartAll,
}

impl Fault {
    /// The fault hits the router, not a planner: every trolley is moved.
    pub fn hits_router(self) -> bool {
        matches!(
            self,
            Fault::RouterRestart | Fault::RouterFailover | Fault::RestartAll
        )
    }

    /// How long the fault lasts unless `--fault-for-s` says (None: it is not undone).
    pub fn default_for_s(self) -> Option<f64> {
        match self {
            Fault::Kill | Fault::RouterFailover => None,
            Fault::Stop | Fault::Partition => Some(10.0),
            Fault::RouterRestart => Some(1.0),
            Fault::RestartAll => Some(2.0),
        }
    }
}

/// A fault under way: what it hit, when, and the trolleys it moved.
pub(super) struct Injected {
    pub fault: Fault,
    /// The planner hit (`p2`), or `router`.
    pub target: String,
    pub at: Instant,
    /// When the fault was undone (resumed, healed, router back), if it was.
    pub ended: Option<Instant>,
    pub moved: Vec<String>,
}

/// What happened to one trolley the fault moved.
#[derive(Debug, Serialize)]
pub(super) struct MovedTrolley {
    /// Seconds from the fault to its first views from a planner other than the one hit (from any
    /// planner after a router fault); None: none before the run ended.
    pub back_on_views_s: Option<f64>,
    /// Of that, the time its arm waited: from the fault or from the frame those views answer,
    /// whichever came later (an arm still moving when the fault came sends its next frame only
    /// once it is there, and waits only from then on); from the fault after a router fault.
    pub waited_s: Option<f64>,
    pub served_by: Option<String>,
    /// Views its arm executed under the ownership term current at the fault (or an older one)
    /// after it had taken views under a newer term: motions on a stale owner's word.
    pub stale_motions: u64,
    /// Its map at its owner after the run against one rebuilt offline from every cloud observed.
    pub map: Option<LostReport>,
    /// Fruit ids of its last fruits before the fault, and those of them no fruits after the
    /// fault carry within 5 cm of where they were (None: no fruits before the fault).
    pub fruit_ids_before: Option<usize>,
    pub fruit_ids_lost: Option<usize>,
}

#[derive(Debug, Serialize)]
pub(super) struct FaultReport {
    pub fault: Fault,
    pub target: String,
    /// Seconds into the measured run.
    pub at_s: f64,
    /// How long it lasted (None: not undone).
    pub lasted_s: Option<f64>,
    pub moved: BTreeMap<String, MovedTrolley>,
    /// Back on views: t1's (the first caught up by construction), the p99 and the last.
    pub t1_s: Option<f64>,
    pub p99_s: Option<f64>,
    /// None when a moved trolley never got views again.
    pub last_s: Option<f64>,
    /// The longest an arm waited for those views (see `MovedTrolley::waited_s`).
    pub longest_wait_s: Option<f64>,
    pub stale_motions: u64,
    /// Fruit ids lost over every moved trolley (see `MovedTrolley::fruit_ids_lost`).
    pub fruit_ids_lost: usize,
}

/// Where a fruit id may move between two estimates and still be the same fruit.
const SAME_FRUIT_M: f64 = 0.05;

/// The fruit ids of `log`'s last fruits before `at`, and how many of them no fruits after `at`
/// carry within [`SAME_FRUIT_M`] of where they were.
fn fruit_ids_lost(log: &TrolleyLog, at: Instant) -> Option<(usize, usize)> {
    let (_, before) = log.fruits.iter().rev().find(|(when, _)| *when <= at)?;
    let after: Vec<&(u32, [f64; 3])> = log
        .fruits
        .iter()
        .filter(|(when, _)| *when > at)
        .flat_map(|(_, fruits)| fruits)
        .collect();
    let near = |a: &[f64; 3], b: &[f64; 3]| {
        let d2: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
        d2.sqrt() <= SAME_FRUIT_M
    };
    let kept = |(id, centre): &(u32, [f64; 3])| {
        after
            .iter()
            .any(|(other, place)| other == id && near(centre, place))
    };
    let lost = before.iter().filter(|f| !kept(f)).count();
    Some((before.len(), lost))
}

/// `log`'s first views after the fault not from `hit` (a planner fault) or from anyone (a
/// router fault).
struct BackOnViews {
    after_fault_s: f64,
    waited_s: f64,
    from: String,
}

fn back_on_views(log: &TrolleyLog, fault: &Injected) -> Option<BackOnViews> {
    let from_other = |from: &String| fault.fault.hits_router() || *from != fault.target;
    let (when, from, frame) = log
        .views_from
        .iter()
        .find(|(when, from, _)| *when > fault.at && from_other(from))?;
    // Frames sent while the router is gone reach no one, the observer included: after a router
    // fault the arm is taken to have waited from the fault on.
    let waiting_since = match (fault.fault.hits_router(), frame) {
        (false, Some(f)) => (*f).max(fault.at),
        _ => fault.at,
    };
    Some(BackOnViews {
        after_fault_s: when.duration_since(fault.at).as_secs_f64(),
        waited_s: when.duration_since(waiting_since).as_secs_f64(),
        from: from.clone(),
    })
}

/// Views executed under terms up to `epoch`.
fn executed_up_to(terms: &[OwnerTerm], epoch: u64) -> u64 {
    terms
        .iter()
        .filter(|t| t.owner_epoch <= epoch)
        .map(|t| u64::from(t.views_executed))
        .sum()
}

/// Motions under the term current at `at` (or older) after the edge took a newer term, from its
/// status history (changes only). The edge keeps its last few terms: one that falls out of its
/// status only makes the count smaller, never larger.
pub(super) fn stale_motions(history: &[(Instant, Vec<OwnerTerm>)], at: Instant) -> u64 {
    let Some((_, before)) = history.iter().rev().find(|(t, _)| *t <= at) else {
        return 0;
    };
    let Some(current) = before.iter().map(|t| t.owner_epoch).max() else {
        return 0;
    };
    let newer = |terms: &[OwnerTerm]| terms.iter().any(|t| t.owner_epoch > current);
    let Some((_, switched)) = history.iter().find(|(t, terms)| *t > at && newer(terms)) else {
        return 0;
    };
    let last = history
        .last()
        .map_or(&[][..], |(_, terms)| terms.as_slice());
    executed_up_to(last, current).saturating_sub(executed_up_to(switched, current))
}

/// Every moved trolley timed and checked; the maps are added by the scans-lost check.
pub(super) fn report(o: &Observed, fault: &Injected, started: Instant) -> FaultReport {
    let moved: BTreeMap<String, MovedTrolley> = fault
        .moved
        .iter()
        .map(|tid| {
            let log = o.trolleys.get(tid);
            let back = log.and_then(|l| back_on_views(l, fault));
            let stale = log.map_or(0, |l| stale_motions(&l.terms, fault.at));
            let ids = log.and_then(|l| fruit_ids_lost(l, fault.at));
            let trolley = MovedTrolley {
                fruit_ids_before: ids.map(|(before, _)| before),
                fruit_ids_lost: ids.map(|(_, lost)| lost),
                back_on_views_s: back.as_ref().map(|b| b.after_fault_s),
                waited_s: back.as_ref().map(|b| b.waited_s),
                served_by: back.map(|b| b.from),
                stale_motions: stale,
                map: None,
            };
            (tid.clone(), trolley)
        })
        .collect();
    let times: Vec<f64> = moved.values().filter_map(|m| m.back_on_views_s).collect();
    let waits: Vec<f64> = moved.values().filter_map(|m| m.waited_s).collect();
    let all_back = times.len() == moved.len();
    FaultReport {
        fault: fault.fault,
        target: fault.target.clone(),
        at_s: fault.at.duration_since(started).as_secs_f64(),
        lasted_s: fault
            .ended
            .map(|e| e.duration_since(fault.at).as_secs_f64()),
        t1_s: moved.get("t1").and_then(|m| m.back_on_views_s),
        p99_s: percentile(&times, 99.0).filter(|_| all_back),
        last_s: times.iter().copied().reduce(f64::max).filter(|_| all_back),
        longest_wait_s: waits.iter().copied().reduce(f64::max).filter(|_| all_back),
        stale_motions: moved.values().map(|m| m.stale_motions).sum(),
        fruit_ids_lost: moved.values().filter_map(|m| m.fruit_ids_lost).sum(),
        moved,
    }
}

/// The report's lines on the fault.
pub(super) fn print(report: Option<&FaultReport>) {
    let Some(r) = report else {
        println!("  fault: none injected");
        return;
    };
    let lasted = r
        .lasted_s
        .map_or(String::new(), |s| format!(", undone after {s:.1} s"));
    let secs = |s: Option<f64>| s.map_or("NEVER".to_string(), |s| format!("{s:.2} s"));
    println!(
        "  fault: {:?} of {} at {:.1} s{lasted}; {} trolleys moved, back on views: t1 {}, p99 {}, last {} (longest an arm waited {}); stale arm motions {}; fruit ids lost {}",
        r.fault,
        r.target,
        r.at_s,
        r.moved.len(),
        secs(r.t1_s),
        secs(r.p99_s),
        secs(r.last_s),
        secs(r.longest_wait_s),
        r.stale_motions,
        r.fruit_ids_lost
    );
    for (tid, m) in &r.moved {
        let map = m.map.as_ref().map_or("map not checked".to_string(), |l| {
            format!(
                "scans lost {} ({} in its map at {}, {} rebuilt from {} clouds), equal voxel for voxel: {}",
                l.scans_lost, l.scans_in_survivor_map, l.survivor, l.scans_rebuilt, l.clouds_observed, l.maps_equal
            )
        });
        let ids = match (m.fruit_ids_before, m.fruit_ids_lost) {
            (Some(before), Some(lost)) => format!("fruit ids lost {lost} of {before}"),
            _ => "no fruits before the fault".to_string(),
        };
        println!(
            "    {tid}: back on views {} (waited {}) from {}; {ids}; {map}",
            secs(m.back_on_views_s),
            secs(m.waited_s),
            m.served_by.as_deref().unwrap_or("nobody")
        );
    }
}

/// The time the fault is undone, if it is.
pub(super) fn undo_after(fault: Fault, for_s: Option<f64>) -> Option<Duration> {
    for_s
        .or(fault.default_for_s())
        .filter(|_| fault.default_for_s().is_some())
        .map(Duration::from_secs_f64)
}

/// Sends `signal` (`STOP`, `CONT`, `USR1`, ...) to `proc`.
fn signal(proc: &Proc, signal: &str) -> anyhow::Result<()> {
    let status = Command::new("kill")
        .args([format!("-{signal}"), proc.child.id().to_string()])
        .status()?;
    anyhow::ensure!(status.success(), "kill -{signal} {} failed", proc.name);
    Ok(())
}

fn find<'a>(procs: &'a mut [Proc], kind: &str, name: &str) -> Option<&'a mut Proc> {
    procs
        .iter_mut()
        .find(|p| p.kind == kind && p.name == name && !p.killed)
}

/// SIGKILLs `proc`, noting its CPU time.
fn kill(proc: &mut Proc, cpu_at_kill: &mut HashMap<String, f64>) {
    let cpu = cpu_seconds(proc.child.id()).unwrap_or(proc.cpu_at_start_s);
    cpu_at_kill.insert(proc.name.clone(), cpu);
    let _ = proc.child.kill();
    let _ = proc.child.wait();
    proc.killed = true;
}

/// The planner owning t1 and the trolleys it owns, by the planners' statuses.
fn owner_of_t1(observed: &Mutex<Observed>) -> Option<(String, Vec<String>)> {
    let o = observed.lock().ok()?;
    o.owned
        .iter()
        .find(|(_, trolleys)| trolleys.iter().any(|t| t == "t1"))
        .map(|(pid, owned)| (pid.clone(), owned.clone()))
}

/// Injects `fault` now; None while no planner is known to own t1 (a planner fault).
pub(super) fn inject(
    fault: Fault,
    fleet: &mut Fleet,
    observed: &Mutex<Observed>,
    cpu_at_kill: &mut HashMap<String, f64>,
) -> anyhow::Result<Option<Injected>> {
    let (target, moved) = if fault.hits_router() {
        let trolleys = observed
            .lock()
            .map(|o| o.trolleys.keys().cloned().collect())
            .unwrap_or_default();
        ("router".to_string(), trolleys)
    } else {
        match owner_of_t1(observed) {
            Some(owner) => owner,
            None => return Ok(None),
        }
    };
    let at = Instant::now();
    let procs = &mut fleet.procs;
    let missing = || anyhow::anyhow!("no process for {target}");
    match fault {
        Fault::Kill => kill(
            find(procs, "planner", &target).ok_or_else(missing)?,
            cpu_at_kill,
        ),
        Fault::Stop => signal(find(procs, "planner", &target).ok_or_else(missing)?, "STOP")?,
        Fault::Partition => {
            let relay = format!("relay-{target}");
            signal(find(procs, "relay", &relay).ok_or_else(missing)?, "USR1")?
        }
        Fault::RouterRestart | Fault::RouterFailover => kill(
            find(procs, "router", "router").ok_or_else(missing)?,
            cpu_at_kill,
        ),
        Fault::RestartAll => {
            for p in procs.iter_mut() {
                if !p.killed && matches!(p.kind, "planner" | "router") {
                    kill(p, cpu_at_kill);
                }
            }
        }
    }
    Ok(Some(Injected {
        fault,
        target,
        at,
        ended: None,
        moved,
    }))
}

/// Undoes a stop, a partition or a router restart (the others are not undone).
pub(super) fn undo(injected: &mut Injected, fleet: &mut Fleet) -> anyhow::Result<()> {
    if injected.ended.is_some() {
        return Ok(());
    }
    let target = injected.target.clone();
    let missing = || anyhow::anyhow!("no process for {target}");
    match injected.fault {
        Fault::Stop => signal(
            find(&mut fleet.procs, "planner", &target).ok_or_else(missing)?,
            "CONT",
        )?,
        Fault::Partition => {
            let relay = format!("relay-{target}");
            signal(
                find(&mut fleet.procs, "relay", &relay).ok_or_else(missing)?,
                "USR2",
            )?
        }
        Fault::RouterRestart => fleet.spawn_router(0)?,
        Fault::RestartAll => {
            fleet.spawn_router(0)?;
            fleet.respawn_planners()?;
        }
        Fault::Kill | Fault::RouterFailover => return Ok(()),
    }
    injected.ended = Some(Instant::now());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn term(pid: &str, epoch: u64, executed: u32) -> OwnerTerm {
        OwnerTerm {
            planner_id: pid.into(),
            owner_epoch: epoch,
            views_executed: executed,
        }
    }

    #[test]
    fn motions_on_the_old_term_after_the_new_one_are_stale() {
        let t0 = Instant::now();
        let at = |ms| t0 + Duration::from_millis(ms);
        let history = vec![
            (at(0), vec![term("p1", 5, 10)]),
            // The fault at 100 ms; one more old-term view executed before the switch is fine.
            (at(150), vec![term("p1", 5, 11)]),
            (at(200), vec![term("p1", 5, 11), term("p2", 7, 1)]),
            (at(300), vec![term("p1", 5, 13), term("p2", 7, 4)]),
        ];
        assert_eq!(stale_motions(&history, at(100)), 2);
        let clean = &history[..3];
        assert_eq!(stale_motions(clean, at(100)), 0);
    }

    #[test]
    fn no_newer_term_no_stale_motion() {
        let t0 = Instant::now();
        let history = vec![(t0, vec![term("p1", 5, 10)])];
        assert_eq!(stale_motions(&history, t0 + Duration::from_secs(1)), 0);
    }

    #[test]
    fn only_faults_that_end_are_undone() {
        assert_eq!(undo_after(Fault::Kill, Some(3.0)), None);
        assert_eq!(undo_after(Fault::Stop, None), Some(Duration::from_secs(10)));
        assert_eq!(
            undo_after(Fault::Partition, Some(2.5)),
            Some(Duration::from_secs_f64(2.5))
        );
    }
}
