//! The fleet web page and its JSON API. Read-only: handlers only read the fleet state.
//!
//! - `GET /`: the page (plain HTML/CSS/JS embedded in the binary; polls the API every second);
//! - `GET /api/fleet`: trolleys, planners, detectors, the Rerun viewer link;
//! - `GET /api/trolleys/{id}/fruits` (`?format=csv` for CSV): one trolley's fruit estimates;
//! - `GET /healthz`: `ok`.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use glasshouse_proto::{FrameRegistration, RigidCorrection};
use serde::Serialize;

use crate::{DashboardCounters, FleetState};

const INDEX_HTML: &str = include_str!("../web/index.html");

/// What the handlers read.
#[derive(Clone)]
pub struct WebState {
    pub fleet: Arc<Mutex<FleetState>>,
    pub counters: Arc<DashboardCounters>,
    pub rerun_viewer_url: Option<String>,
}

#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct TrolleyRow {
    pub id: String,
    pub planner: String,
    pub state: String,
    pub views_done: u32,
    pub fruits: usize,
    pub frames: u64,
    pub last_frame_age_s: Option<f64>,
    pub latency_p50_ms: Option<f64>,
    pub latency_p99_ms: Option<f64>,
    pub drops: u64,
    /// RankedViews the trolley refused: not from the planner owning it.
    pub refused_views: u64,
    /// RankedViews the trolley refused: an older ownership epoch than the newest it took (a
    /// replaced owner's).
    pub stale_views: u64,
    /// The newest ownership epoch the trolley took views under.
    pub owner_epoch: u64,
    /// Share of ground-truth fruit volume inside detected boxes (simulated trolleys only).
    pub covered_volume: Option<f64>,
    /// How the planner registered the trolley's last registered cloud.
    pub registration: Option<RegistrationDoc>,
    /// The camera's position seen from above (world x, y, metres), for the plan view.
    pub camera_xy_m: Option<[f64; 2]>,
    /// The plants the trolley samples views around, from above: min and max (x, y), metres.
    pub region_xy_m: Option<[[f64; 2]; 2]>,
}

/// One cloud's registration to its trolley's map, as the owning planner reported it.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct RegistrationDoc {
    /// The cloud's frame seq.
    pub frame_seq: u64,
    /// `applied`, `kept_as_sent`, `rejected` or `skipped`.
    pub verdict: &'static str,
    /// Why (`none` for an applied correction), e.g. `below_resolution`, `contradicts_map`.
    pub reason: &'static str,
    /// ICP's correction: how far it moves the camera (mm) and turns the scan (degrees). Applied
    /// only when the verdict is `applied`; absent when there was no estimate.
    pub correction_mm: Option<f64>,
    pub correction_deg: Option<f64>,
    /// Share of the scan's points near the map's surface, and their residual RMS (mm), as the
    /// scan went in.
    pub inlier_share: Option<f32>,
    pub rms_mm: Option<f64>,
}

impl RegistrationDoc {
    pub fn new(r: &FrameRegistration) -> Self {
        let estimate = r.world_correction.as_ref();
        Self {
            frame_seq: r.frame.seq,
            verdict: r.verdict.name(),
            reason: r.reason.name(),
            correction_mm: r.sensor_shift_m.map(|m| f64::from(m) * 1e3),
            correction_deg: r
                .rotation_deg
                .map(f64::from)
                .or_else(|| estimate.map(RigidCorrection::angle_deg)),
            inlier_share: r.inlier_share,
            rms_mm: r.rms_after_m.map(|m| f64::from(m) * 1e3),
        }
    }
}

#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct PlannerRow {
    pub id: String,
    pub owned: Vec<String>,
    pub standby: Vec<String>,
    pub clouds_integrated: u64,
    pub views_published: u64,
    pub last_planning_time_ms: f32,
    pub mean_planning_time_ms: f32,
    pub map_voxels: u64,
    pub dropped: u64,
    /// RoiClouds refused: not from a live detector, or a frame no trolley sends.
    pub refused_clouds: u64,
    /// Fruits and snapshots dropped: an older ownership epoch than the newest seen.
    pub stale_epoch: u64,
    /// Ownership terms given up on seeing a newer epoch (it was replaced while paused or cut
    /// off).
    pub stepped_down: u64,
    /// Seconds since its last status (a lost planner's grows).
    pub last_status_age_s: Option<f64>,
    /// Clouds of the trolleys it owns registered to their maps, by verdict: corrected, let in
    /// as sent, kept out, not checked.
    pub registration_applied: u64,
    pub registration_kept_as_sent: u64,
    pub registration_rejected: u64,
    pub registration_skipped: u64,
}

#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct DetectorRow {
    pub id: String,
    pub frames_processed: u64,
    pub mean_detect_time_ms: f32,
    pub dropped: u64,
}

/// The `/api/fleet` document.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct FleetDoc {
    pub trolleys: Vec<TrolleyRow>,
    pub planners: Vec<PlannerRow>,
    pub detectors: Vec<DetectorRow>,
    pub messages: u64,
    pub dashboard_drops: u64,
    pub rerun_viewer_url: Option<String>,
    /// Fruits in the merged fleet map (`gh/fleet/fruits`), and the planner that merged them.
    pub fleet_fruits: usize,
    pub fleet_map_planner: Option<String>,
}

/// One fruit of `/api/trolleys/{id}/fruits`.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct FruitDoc {
    pub id: u32,
    pub centre_m: [f32; 3],
    pub size_m: [f32; 3],
    pub volume_m3: f32,
    pub voxel_count: u32,
    pub confidence: f32,
    /// Volume of the fitted whole-fruit ellipsoid, when the planner sent one.
    pub fitted_volume_m3: Option<f32>,
    /// Share of the fitted surface observed.
    pub fitted_confidence: Option<f32>,
}

/// Builds the fleet document from the state at `now`.
pub fn fleet_doc(
    fleet: &FleetState,
    now: Instant,
    dashboard_drops: u64,
    viewer: Option<String>,
) -> FleetDoc {
    FleetDoc {
        trolleys: fleet
            .trolleys
            .iter()
            .map(|(id, t)| TrolleyRow::new(id, t, now))
            .collect(),
        planners: fleet
            .planners
            .iter()
            .map(|(id, p)| PlannerRow::new(id, p, fleet.planner_seen_at.get(id), now))
            .collect(),
        detectors: fleet
            .detectors
            .iter()
            .map(|(id, d)| DetectorRow {
                id: id.clone(),
                frames_processed: d.frames_processed,
                mean_detect_time_ms: d.mean_detect_time_ms,
                dropped: d.dropped_messages,
            })
            .collect(),
        messages: fleet.messages,
        dashboard_drops,
        rerun_viewer_url: viewer,
        fleet_fruits: fleet.fleet_fruits.as_ref().map_or(0, |f| f.fruits.len()),
        fleet_map_planner: fleet.fleet_fruits.as_ref().map(|f| f.planner_id.clone()),
    }
}

impl TrolleyRow {
    /// The row of trolley `id` as the dashboard sees it at `now`.
    fn new(id: &str, t: &crate::TrolleyView, now: Instant) -> Self {
        TrolleyRow {
            id: id.to_owned(),
            planner: t.planner_id.clone(),
            state: t
                .status
                .as_ref()
                .map_or("Unknown".to_owned(), |s| format!("{:?}", s.state)),
            views_done: t.status.as_ref().map_or(0, |s| s.views_done),
            fruits: t.fruits.len(),
            frames: t.frames,
            last_frame_age_s: t
                .last_frame_at
                .map(|at| now.duration_since(at).as_secs_f64()),
            latency_p50_ms: t.latency_percentile_ms(50.0),
            latency_p99_ms: t.latency_percentile_ms(99.0),
            drops: t.drops(),
            refused_views: t.status.as_ref().map_or(0, |s| s.refused_views),
            stale_views: t.status.as_ref().map_or(0, |s| s.stale_views),
            owner_epoch: t.status.as_ref().map_or(0, |s| s.owner_epoch),
            covered_volume: t.covered_volume,
            registration: t.last_registration.as_ref().map(RegistrationDoc::new),
            camera_xy_m: t.camera_position_m.map(|p| [p[0], p[1]]),
            region_xy_m: t.info.as_ref().map(|i| {
                let r = &i.sampling_region;
                [[r.min.x, r.min.y], [r.max.x, r.max.y]]
            }),
        }
    }
}

impl PlannerRow {
    /// The row of planner `id` from its latest status, last seen at `seen_at`.
    fn new(
        id: &str,
        p: &glasshouse_proto::PlannerStatus,
        seen_at: Option<&Instant>,
        now: Instant,
    ) -> Self {
        PlannerRow {
            id: id.to_owned(),
            owned: p.owned_trolleys.clone(),
            standby: p.standby_trolleys.clone(),
            clouds_integrated: p.clouds_integrated,
            views_published: p.views_published,
            last_planning_time_ms: p.last_planning_time_ms,
            mean_planning_time_ms: p.mean_planning_time_ms,
            map_voxels: p.map_voxels,
            dropped: p.dropped_messages,
            refused_clouds: p.refused_clouds,
            stale_epoch: p.stale_epoch,
            stepped_down: p.stepped_down,
            last_status_age_s: seen_at.map(|t| now.saturating_duration_since(*t).as_secs_f64()),
            registration_applied: p.registrations.applied,
            registration_kept_as_sent: p.registrations.kept_as_sent,
            registration_rejected: p.registrations.rejected,
            registration_skipped: p.registrations.skipped,
        }
    }
}

/// The fruits of one trolley, or `None` when the trolley is unknown.
pub fn fruit_docs(fleet: &FleetState, tid: &str) -> Option<Vec<FruitDoc>> {
    let t = fleet.trolleys.get(tid)?;
    Some(
        t.fruits
            .iter()
            .map(|f| FruitDoc {
                id: f.id,
                centre_m: f.centre.cast::<f32>().into(),
                size_m: (f.max - f.min).cast::<f32>().into(),
                volume_m3: f.volume_m3 as f32,
                voxel_count: f.voxel_count.min(u32::MAX as usize) as u32,
                confidence: f.confidence as f32,
                fitted_volume_m3: f.solid.as_ref().map(|e| e.volume_m3 as f32),
                fitted_confidence: f.solid.as_ref().map(|e| e.confidence as f32),
            })
            .collect(),
    )
}

/// CSV of fruit estimates with a header line.
pub fn fruits_csv(fruits: &[FruitDoc]) -> String {
    let mut out = String::from(
        "id,centre_x_m,centre_y_m,centre_z_m,size_x_m,size_y_m,size_z_m,volume_m3,voxel_count,confidence,fitted_volume_m3,fitted_confidence\n",
    );
    for f in fruits {
        out.push_str(&format!(
            "{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.8},{},{:.3},{},{}\n",
            f.id,
            f.centre_m[0],
            f.centre_m[1],
            f.centre_m[2],
            f.size_m[0],
            f.size_m[1],
            f.size_m[2],
            f.volume_m3,
            f.voxel_count,
            f.confidence,
            f.fitted_volume_m3
                .map_or_else(String::new, |v| format!("{v:.8}")),
            f.fitted_confidence
                .map_or_else(String::new, |c| format!("{c:.3}")),
        ));
    }
    out
}

/// The HTTP routes.
pub fn router(state: WebState) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/healthz", get(|| async { "ok" }))
        .route("/api/fleet", get(fleet))
        .route("/api/trolleys/{id}/fruits", get(fruits))
        .with_state(state)
}

async fn index() -> Html<&'static str> {
    Html(INDEX_HTML)
}

/// The fleet state, also after a panic elsewhere poisoned the lock: it is plain data that every
/// update leaves consistent, so serving it stays correct.
fn locked(state: &WebState) -> std::sync::MutexGuard<'_, FleetState> {
    state
        .fleet
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

async fn fleet(State(state): State<WebState>) -> Response {
    let drops = state.counters.drops.total();
    let fleet = locked(&state);
    Json(fleet_doc(
        &fleet,
        Instant::now(),
        drops,
        state.rerun_viewer_url.clone(),
    ))
    .into_response()
}

async fn fruits(
    State(state): State<WebState>,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
) -> Response {
    let docs = fruit_docs(&locked(&state), &id);
    let Some(docs) = docs else {
        return (StatusCode::NOT_FOUND, format!("no trolley {id:?}")).into_response();
    };
    match query.get("format").map(String::as_str) {
        Some("csv") => (
            [
                (header::CONTENT_TYPE, "text/csv; charset=utf-8".to_owned()),
                (
                    header::CONTENT_DISPOSITION,
                    format!("attachment; filename=\"fruits-{id}.csv\""),
                ),
            ],
            fruits_csv(&docs),
        )
            .into_response(),
        None | Some("json") => Json(docs).into_response(),
        Some(other) => (
            StatusCode::BAD_REQUEST,
            format!("unknown format {other:?}: use json or csv"),
        )
            .into_response(),
    }
}

#[cfg(test)]
mod tests {
    use glasshouse_proto::keys::{ParsedKey, TrolleyTopic};
    use glasshouse_proto::{samples, Message, RegistrationReason, RegistrationVerdict};

    use super::*;

    fn map_key() -> ParsedKey {
        ParsedKey::Trolley {
            tid: "t1".into(),
            topic: TrolleyTopic::Map,
        }
    }

    #[test]
    fn the_fleet_document_shows_the_last_registration_and_the_planner_totals() {
        let mut fleet = FleetState::default();
        let now = Instant::now();
        let header = samples::header(42);
        let update = samples::map_update();
        fleet.apply(
            &map_key(),
            &header,
            &Message::MapUpdate(update.clone()),
            now,
        );
        // A re-announced frame's update carries no registration: the last one stays.
        let repeat = glasshouse_proto::MapUpdate {
            registration: None,
            ..update
        };
        fleet.apply(&map_key(), &header, &Message::MapUpdate(repeat), now);
        let status_key = ParsedKey::PlannerStatus { pid: "p1".into() };
        let status = Message::PlannerStatus(samples::planner_status());
        fleet.apply(&status_key, &samples::header(1), &status, now);

        let doc = fleet_doc(&fleet, now, 0, None);
        let r = doc.trolleys[0].registration.as_ref().expect("registration");
        assert_eq!((r.frame_seq, r.verdict, r.reason), (42, "applied", "none"));
        let near =
            |value: Option<f64>, expected: f64| value.is_some_and(|v| (v - expected).abs() < 1e-3);
        assert!(near(r.correction_mm, 6.5), "{r:?}");
        assert!(near(r.correction_deg, 0.5), "{r:?}");
        assert!(near(r.rms_mm, 1.8), "{r:?}");
        let p = &doc.planners[0];
        let totals = (
            p.registration_applied,
            p.registration_kept_as_sent,
            p.registration_rejected,
            p.registration_skipped,
        );
        assert_eq!(totals, (6, 2, 1, 1));
        let json = serde_json::to_string(&doc).expect("json");
        assert!(json.contains("\"verdict\":\"applied\""), "{json}");
    }

    #[test]
    fn a_rejected_cloud_shows_why_without_a_correction() {
        let rejected = FrameRegistration {
            verdict: RegistrationVerdict::Rejected,
            reason: RegistrationReason::ContradictsMap,
            near_surface_points: Some(12),
            contradicting_points: Some(300),
            ..FrameRegistration::default()
        };
        let doc = RegistrationDoc::new(&rejected);
        assert_eq!((doc.verdict, doc.reason), ("rejected", "contradicts_map"));
        assert_eq!((doc.correction_mm, doc.correction_deg), (None, None));
    }

    #[test]
    fn a_replaced_owners_views_map_and_fruits_are_left_out_and_counted() {
        let mut fleet = FleetState::default();
        let now = Instant::now();
        let key = |topic| ParsedKey::Trolley {
            tid: "t1".into(),
            topic,
        };
        let header = samples::header(1);
        let views = |owner_epoch| {
            Message::RankedViews(glasshouse_proto::RankedViews {
                owner_epoch,
                ..samples::ranked_views()
            })
        };
        let map = Message::MapUpdate(glasshouse_proto::MapUpdate {
            owner_epoch: 10,
            ..samples::map_update()
        });
        let fruits = |owner_epoch| {
            Message::FruitEstimates(glasshouse_proto::FruitEstimates {
                owner_epoch,
                ..samples::fruit_estimates()
            })
        };
        assert!(fleet.apply(&key(TrolleyTopic::Views), &header, &views(20), now));
        // The owner replaced under epoch 20 still sends under 10: left out, counted.
        assert!(!fleet.apply(&key(TrolleyTopic::Views), &header, &views(10), now));
        assert!(!fleet.apply(&key(TrolleyTopic::Map), &header, &map, now));
        assert!(!fleet.apply(&key(TrolleyTopic::Fruits), &header, &fruits(10), now));
        let t = &fleet.trolleys["t1"];
        assert_eq!((t.views_messages, t.map_updates), (1, 0));
        assert!(t.fruits.is_empty());
        assert_eq!(fleet.stale_epoch, 3);
        // The simulator's truth has no owner: taken whatever its epoch.
        assert!(fleet.apply(&key(TrolleyTopic::Truth), &header, &fruits(0), now));
        assert!(fleet.apply(&key(TrolleyTopic::Fruits), &header, &fruits(20), now));
        assert_eq!(fleet.trolleys["t1"].fruits.len(), 1);
    }
}
