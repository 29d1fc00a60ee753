//! The planner's OpenMetrics (`--metrics ADDR`): clouds, views, drops, snapshot bytes sent, the
//! trolleys it owns and
//! keeps standby, its map, registrations, and each cloud's time per stage as histograms.

use std::fmt;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;

use glasshouse_bus::metrics::prometheus_client::metrics::family::Family;
use glasshouse_bus::metrics::prometheus_client::metrics::histogram::{
    exponential_buckets, Histogram,
};
use glasshouse_bus::metrics::prometheus_client::registry::{Registry, Unit};
use glasshouse_bus::metrics::{atomic, last, Readings, ServiceMetrics};
use glasshouse_proto::{PlannerStatus, StageTimes};

use crate::PlannerCounters;

type StageFamily = Family<Vec<(&'static str, &'static str)>, Histogram, fn() -> Histogram>;

/// Each cloud's time per stage, seconds: 0.5 ms to about 8 s in doublings.
#[derive(Clone)]
pub struct StageHistograms(StageFamily);

impl Default for StageHistograms {
    fn default() -> Self {
        fn buckets() -> Histogram {
            Histogram::new(exponential_buckets(0.0005, 2.0, 15))
        }
        Self(Family::new_with_constructor(buckets))
    }
}

impl fmt::Debug for StageHistograms {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("StageHistograms")
    }
}

impl StageHistograms {
    /// Observes one cloud's handling: `after - before` of the planner's stage totals.
    pub fn observe(&self, before: &StageTimes, after: &StageTimes) {
        for ((stage, was_ms), (_, now_ms)) in before.named().iter().zip(after.named()) {
            let ms = now_ms - was_ms;
            if ms > 0.0 {
                self.0
                    .get_or_create(&vec![("stage", *stage)])
                    .observe(ms / 1e3);
            }
        }
    }
}

impl ServiceMetrics for PlannerCounters {
    fn kind() -> &'static str {
        "planner"
    }

    fn register(self: Arc<Self>, registry: &mut Registry) {
        registry.register_with_unit(
            "stage",
            "Time a cloud spends in each stage of the planner",
            Unit::Seconds,
            self.stage_seconds.0.clone(),
        );
        let readings = counts(&self, Readings::default()).drops(&self.drops);
        from_status(&self, readings).register(registry);
    }
}

/// What the planner counts itself: clouds, views, snapshot bytes, its store's writes.
fn counts(counters: &Arc<PlannerCounters>, readings: Readings) -> Readings {
    let c = |field: fn(&PlannerCounters) -> &AtomicU64| atomic(counters, field);
    readings
        .counter(
            "clouds_integrated",
            "ROI clouds integrated into a map",
            &[],
            c(|k| &k.clouds_integrated),
        )
        .counter(
            "clouds_rejected",
            "ROI clouds that decoded but could not be integrated",
            &[],
            c(|k| &k.clouds_rejected),
        )
        .counter(
            "clouds_refused",
            "ROI clouds refused: not from a live detector, or a frame no trolley sends",
            &[],
            c(|k| &k.clouds_refused),
        )
        .counter(
            "views_published",
            "Ranked view sets published",
            &[],
            c(|k| &k.views_published),
        )
        .counter(
            "snapshot_deltas_sent",
            "Standby refreshes answered with the map blocks changed since the copy's base",
            &[],
            c(|k| &k.snapshot_deltas_sent),
        )
        .counter(
            "snapshot_deltas_applied",
            "Owners' deltas applied to this planner's standby copies",
            &[],
            c(|k| &k.snapshot_deltas_applied),
        )
        .counter(
            "snapshot_sent",
            "Map snapshot bytes sent to planners taking a trolley over",
            &[],
            c(|k| &k.snapshot_bytes_sent),
        )
        .in_unit(Unit::Bytes)
        .counter(
            "store_writes",
            "Store writes done (a checkpoint, a logged cloud, trolleys' fruits)",
            &[],
            c(|k| &k.store_writes),
        )
        .counter(
            "store_transactions",
            "Store transactions committed (writes queued together share one)",
            &[],
            c(|k| &k.store_transactions),
        )
        .counter(
            "store_errors",
            "Store writes that failed (that state is in memory only)",
            &[],
            c(|k| &k.store_errors),
        )
        .counter(
            "publications_held",
            "Views, fruits and map updates held until their cloud was stored",
            &[],
            c(|k| &k.publications_held),
        )
        .counter(
            "store_written",
            "Key and value bytes the store wrote",
            &[],
            c(|k| &k.store_bytes_written),
        )
        .in_unit(Unit::Bytes)
}

/// A value read off the planner's last status.
type StatusRead = fn(&PlannerStatus) -> f64;

/// What the planner's last status says: its roles, maps, planning, catch-up, registrations.
fn from_status(counters: &Arc<PlannerCounters>, readings: Readings) -> Readings {
    let s = |read: StatusRead| last(counters, |k| &k.status, read);
    let roles: [(&str, StatusRead); 2] = [
        ("owner", |st| st.owned_trolleys.len() as f64),
        ("standby", |st| st.standby_trolleys.len() as f64),
    ];
    let verdicts: [(&str, StatusRead); 4] = [
        ("applied", |st| st.registrations.applied as f64),
        ("kept_as_sent", |st| st.registrations.kept_as_sent as f64),
        ("rejected", |st| st.registrations.rejected as f64),
        ("skipped", |st| st.registrations.skipped as f64),
    ];
    let readings = roles.into_iter().fold(readings, |r, (role, read)| {
        r.gauge("trolleys", "Trolleys by role", &[("role", role)], s(read))
    });
    let readings = readings
        .gauge(
            "map_voxels",
            "Known voxels over every map held",
            &[],
            s(|st| st.map_voxels as f64),
        )
        .gauge(
            "planning_time_mean",
            "Mean planning time per view set",
            &[],
            s(|st| f64::from(st.mean_planning_time_ms) / 1e3),
        )
        .in_unit(Unit::Seconds)
        .counter(
            "catch_up",
            "Time catching up trolleys taken over",
            &[],
            s(|st| st.catch_up_ms / 1e3),
        )
        .in_unit(Unit::Seconds)
        .counter(
            "stepped_down",
            "Ownership terms given up on seeing a newer epoch for the trolley",
            &[],
            s(|st| st.stepped_down as f64),
        )
        .counter(
            "clouds_unassigned",
            "ROI clouds refused: not from the detector serving the trolley",
            &[],
            s(|st| st.unassigned_clouds as f64),
        )
        .counter(
            "clouds_colourless",
            "ROI clouds integrated without colour: roi_rgb not 3 bytes per ROI point",
            &[],
            s(|st| st.colourless_clouds as f64),
        )
        .counter(
            "standby_decodes_ahead",
            "Standby copies decoded ahead of a takeover and kept",
            &[],
            s(|st| st.standby_decodes_ahead as f64),
        )
        .counter(
            "decoded_ahead_adopted",
            "Takeovers that adopted a copy decoded ahead instead of decoding",
            &[],
            s(|st| st.decoded_ahead_adopted as f64),
        );
    verdicts.into_iter().fold(readings, |r, (verdict, read)| {
        r.counter(
            "registrations",
            "Scan registrations of owned trolleys, by verdict",
            &[("verdict", verdict)],
            s(read),
        )
    })
}
