//! Where the frame → views tail comes from: the loop's latency split by the planner that answered
//! and by the run's phase around a fault (before it, the half minute after it, the rest).

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use serde::Serialize;

use super::{percentile, TrolleyLog};

/// How long after a fault its takeovers and catch-ups are taken to weigh on the latency.
const FAULT_WINDOW: Duration = Duration::from_secs(30);

/// Frames answered and their frame → views latency (ms).
#[derive(Debug, Default, PartialEq, Serialize)]
pub(super) struct Latency {
    pub frames: usize,
    /// Trolleys among those frames.
    pub trolleys: usize,
    pub p50_ms: Option<f64>,
    pub p99_ms: Option<f64>,
}

/// The loop's latency by answering planner, and by phase when a fault was injected.
#[derive(Debug, Default, PartialEq, Serialize)]
pub(super) struct TailReport {
    pub by_planner: BTreeMap<String, Latency>,
    /// `before_fault`, `fault_window` (the 30 s after it) and `after_fault`; empty without one.
    pub by_phase: BTreeMap<&'static str, Latency>,
}

/// One answered frame: when the views came, who sent them, the trolley, the latency in ms.
struct Answer<'a> {
    at: Instant,
    planner: &'a str,
    trolley: &'a str,
    ms: f64,
}

fn latency<'a>(answers: impl Iterator<Item = &'a Answer<'a>>) -> Latency {
    let mut ms = Vec::new();
    let mut trolleys = BTreeSet::new();
    for a in answers {
        ms.push(a.ms);
        trolleys.insert(a.trolley);
    }
    Latency {
        frames: ms.len(),
        trolleys: trolleys.len(),
        p50_ms: percentile(&ms, 50.0),
        p99_ms: percentile(&ms, 99.0),
    }
}

fn phase(at: Instant, fault_at: Instant) -> &'static str {
    match at.checked_duration_since(fault_at) {
        None => "before_fault",
        Some(d) if d < FAULT_WINDOW => "fault_window",
        Some(_) => "after_fault",
    }
}

/// The tail of the trolleys' first views on each frame, split by planner and by phase.
pub(super) fn report<'a>(
    trolleys: impl IntoIterator<Item = (&'a String, &'a TrolleyLog)>,
    fault_at: Option<Instant>,
) -> TailReport {
    let answers: Vec<Answer> = trolleys
        .into_iter()
        .flat_map(|(tid, log)| {
            log.views_from
                .iter()
                .filter_map(move |(at, planner, frame)| {
                    frame.map(|f| Answer {
                        at: *at,
                        planner,
                        trolley: tid,
                        ms: at.duration_since(f).as_secs_f64() * 1e3,
                    })
                })
        })
        .collect();
    let planners: BTreeSet<&str> = answers.iter().map(|a| a.planner).collect();
    let by_planner = planners
        .into_iter()
        .map(|p| {
            let of_p = answers.iter().filter(|a| a.planner == p);
            (p.to_owned(), latency(of_p))
        })
        .collect();
    let by_phase = fault_at.map_or_else(BTreeMap::new, |fault_at| {
        ["before_fault", "fault_window", "after_fault"]
            .into_iter()
            .map(|name| {
                let in_phase = answers.iter().filter(|a| phase(a.at, fault_at) == name);
                (name, latency(in_phase))
            })
            .collect()
    });
    TailReport {
        by_planner,
        by_phase,
    }
}

/// One line per planner and phase, for the report's text.
pub(super) fn text(tail: &TailReport) -> String {
    let ms = |v: Option<f64>| v.map_or("–".to_owned(), |v| format!("{v:.0}"));
    let line = |name: &str, l: &Latency| {
        format!(
            "    {name}: {} frames of {} trolleys, p50 / p99 {} / {} ms",
            l.frames,
            l.trolleys,
            ms(l.p50_ms),
            ms(l.p99_ms)
        )
    };
    let planners = tail.by_planner.iter().map(|(p, l)| line(p, l));
    let phases = tail.by_phase.iter().map(|(p, l)| line(p, l));
    let head = "  frame -> views by the planner that answered, and by phase".to_owned();
    std::iter::once(head)
        .chain(planners)
        .chain(phases)
        .collect::<Vec<_>>()
        .join("\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn log(start: Instant, answers: &[(u64, &str, u64)]) -> TrolleyLog {
        let mut log = TrolleyLog::default();
        for &(frame_ms, planner, latency_ms) in answers {
            let frame = start + Duration::from_millis(frame_ms);
            let at = frame + Duration::from_millis(latency_ms);
            log.views_from.push((at, planner.to_owned(), Some(frame)));
        }
        // Views not answering a new frame do not count.
        log.views_from.push((start, "p1".to_owned(), None));
        log
    }

    #[test]
    fn splits_the_latency_by_planner_and_by_phase_around_the_fault() {
        let start = Instant::now();
        let t1 = log(
            start,
            &[(0, "p1", 100), (1_000, "p2", 300), (40_000, "p2", 50)],
        );
        let t2 = log(start, &[(2_000, "p1", 200), (5_000, "p1", 900)]);
        let trolleys = BTreeMap::from([("t1".to_owned(), t1), ("t2".to_owned(), t2)]);
        let tail = report(&trolleys, Some(start + Duration::from_secs(4)));
        let p1 = &tail.by_planner["p1"];
        assert_eq!((p1.frames, p1.trolleys), (3, 2));
        assert_eq!((p1.p50_ms, p1.p99_ms), (Some(200.0), Some(900.0)));
        let p2 = &tail.by_planner["p2"];
        assert_eq!((p2.frames, p2.trolleys, p2.p99_ms), (2, 1, Some(300.0)));
        let frames = |name| tail.by_phase[name].frames;
        assert_eq!(
            (
                frames("before_fault"),
                frames("fault_window"),
                frames("after_fault")
            ),
            (3, 1, 1)
        );
        assert_eq!(tail.by_phase["fault_window"].p99_ms, Some(900.0));
        assert!(text(&tail).contains("p2: 2 frames of 1 trolleys, p50 / p99 300 / 300 ms"));
    }

    #[test]
    fn without_a_fault_there_are_no_phases() {
        let start = Instant::now();
        let t1 = log(start, &[(0, "p1", 100)]);
        let tail = report(&BTreeMap::from([("t1".to_owned(), t1)]), None);
        assert!(tail.by_phase.is_empty());
        assert_eq!(tail.by_planner["p1"].frames, 1);
    }
}
