//! The planners' cost along the run: CPU per frame in the first and in the last minute (flat
//! along the row or not), and the time per stage of cloud handling the planners report in their
//! status (`PlannerStatus::stage_totals`).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use glasshouse_proto::StageTimes;

/// The planners' CPU seconds (all of them, killed ones up to their kill), sampled along the run.
#[derive(Default)]
pub(super) struct CpuSamples {
    /// (time since the measured run started, CPU seconds since it started).
    samples: Vec<(Duration, f64)>,
}

impl CpuSamples {
    pub(super) fn push(&mut self, since_start: Duration, cpu_s: f64) {
        self.samples.push((since_start, cpu_s));
    }

    /// CPU seconds spent between the samples nearest `from` and `to`, and the window's real
    /// bounds.
    fn between(&self, from: Duration, to: Duration) -> Option<(f64, Duration, Duration)> {
        let nearest = |t: Duration| {
            self.samples
                .iter()
                .min_by_key(|(at, _)| at.abs_diff(t))
                .copied()
        };
        let ((a_at, a), (b_at, b)) = (nearest(from)?, nearest(to)?);
        (b_at > a_at).then_some((b - a, a_at, b_at))
    }
}

/// Planner CPU ms per frame in a window of the run: CPU between the samples around it, over the
/// clouds that arrived in it.
pub(super) fn cpu_ms_per_frame(
    cpu: &CpuSamples,
    started: Instant,
    cloud_times: &[Instant],
    from: Duration,
    to: Duration,
) -> Option<f64> {
    let (cpu_s, from, to) = cpu.between(from, to)?;
    let frames = cloud_times
        .iter()
        .filter(|&&t| (started + from..started + to).contains(&t))
        .count();
    (frames > 0).then(|| cpu_s * 1e3 / frames as f64)
}

/// Each stage's ms per frame over the run: the planners' stage totals at the end less those at
/// the start, over `frames`.
pub(super) fn stage_ms_per_frame(
    at_start: &BTreeMap<String, StageTimes>,
    at_end: &BTreeMap<String, StageTimes>,
    frames: usize,
) -> BTreeMap<String, f64> {
    let mut out: BTreeMap<String, f64> = BTreeMap::new();
    if frames == 0 {
        return out;
    }
    for (pid, end) in at_end {
        let start = at_start.get(pid).copied().unwrap_or_default();
        for ((name, end_ms), (_, start_ms)) in end.named().into_iter().zip(start.named()) {
            *out.entry(name.to_owned()).or_default() += (end_ms - start_ms) / frames as f64;
        }
    }
    out
}

/// The stages in pipeline order with their ms per frame, for a line of text.
pub(super) fn stages_text(stages: &BTreeMap<String, f64>) -> String {
    let parts: Vec<String> = StageTimes::default()
        .named()
        .iter()
        .map(|(name, _)| match stages.get(*name) {
            Some(ms) => format!("{name} {ms:.1}"),
            None => format!("{name} –"),
        })
        .collect();
    parts.join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_per_frame_takes_the_samples_around_the_window_and_the_clouds_in_it() {
        let started = Instant::now();
        let s = Duration::from_secs;
        let mut cpu = CpuSamples::default();
        for (at, cpu_s) in [(0, 0.0), (5, 0.4), (60, 6.0), (115, 12.0), (120, 13.0)] {
            cpu.push(s(at), cpu_s);
        }
        // 60 clouds in the first minute, 20 in the last.
        let mut clouds: Vec<Instant> = (0..60).map(|i| started + s(i)).collect();
        clouds.extend((0..20).map(|i| started + s(61 + 3 * i)));
        let first = cpu_ms_per_frame(&cpu, started, &clouds, s(0), s(60));
        assert_eq!(first, Some(100.0));
        let last = cpu_ms_per_frame(&cpu, started, &clouds, s(60), s(120));
        assert_eq!(last, Some(7000.0 / 20.0));
        assert_eq!(cpu_ms_per_frame(&cpu, started, &[], s(0), s(60)), None);
    }

    #[test]
    fn stage_times_are_summed_over_planners_from_their_start() {
        let at = |integrate_ms, plan_ms| StageTimes {
            integrate_ms,
            plan_ms,
            ..StageTimes::default()
        };
        let start = BTreeMap::from([("p1".to_string(), at(100.0, 10.0))]);
        // p2 joined during the run: all of its time counts.
        let end = BTreeMap::from([
            ("p1".to_string(), at(300.0, 30.0)),
            ("p2".to_string(), at(200.0, 20.0)),
        ]);
        let per_frame = stage_ms_per_frame(&start, &end, 10);
        assert_eq!(per_frame["integrate"], 40.0);
        assert_eq!(per_frame["plan"], 4.0);
        assert_eq!(per_frame["fit"], 0.0);
        assert!(stage_ms_per_frame(&start, &end, 0).is_empty());
        assert!(stages_text(&per_frame).starts_with("integrate 40.0, cluster 0.0"));
    }
}
