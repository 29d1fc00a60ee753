//! The fleet web page and its JSON API. Read-only: handlers only read the fleet state.
//!
//! - `GET /`: the page (plain HTML/CSS/JS embedded in the binary; polls the API every second);
//! - `GET /api/fleet`: trolleys, planners, detectors, the Rerun viewer link;
//! - `GET /api/trolleys/{id}/fruits` (`?format=csv` for CSV): one trolley's fruit estimates;
//! - `GET /api/trolleys/{id}/season` (`?format=csv` for CSV, `?download=1` to save the JSON):
//!   every fruit of one trolley's row over the visits (centre, size, volume and observed colour
//!   per visit) and whether it was seen on the current visit;
//! - `GET /api/season`: a row per trolley: its visit, fruits seen now and known this season,
//!   fruits not seen or new on this visit, mean volume now and on the previous visit;
//! - `GET /healthz`: `ok`.
//!
//! A season record holding a non-finite value is left out of both: JSON has no NaN.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use glasshouse_geom::{volume_change_m3, Rgb};
use glasshouse_proto::{FrameRegistration, FruitHistory, FruitVisit, RigidCorrection};
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
    /// The trolley's hand-eye estimate as applied to the cloud before: its rotation, degrees;
    /// absent while its planner has none.
    pub hand_eye_deg: Option<f64>,
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
            hand_eye_deg: r
                .hand_eye_correction
                .as_ref()
                .map(RigidCorrection::angle_deg),
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
    /// Clouds taken without colour (their colours not one per ROI point).
    pub colourless_clouds: u64,
    /// Standby copies decoded ahead of a takeover, and takeovers that adopted one.
    pub standby_decodes_ahead: u64,
    pub decoded_ahead_adopted: u64,
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
    /// Mean observed colour, `#rrggbb`; null when unknown.
    pub colour: Option<String>,
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
            colourless_clouds: p.colourless_clouds,
            standby_decodes_ahead: p.standby_decodes_ahead,
            decoded_ahead_adopted: p.decoded_ahead_adopted,
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
                colour: f.colour.as_ref().map(Rgb::hex),
            })
            .collect(),
    )
}

/// CSV of fruit estimates with a header line.
pub fn fruits_csv(fruits: &[FruitDoc]) -> String {
    let mut out = String::from(
        "id,centre_x_m,centre_y_m,centre_z_m,size_x_m,size_y_m,size_z_m,volume_m3,voxel_count,confidence,fitted_volume_m3,fitted_confidence,colour\n",
    );
    for f in fruits {
        out.push_str(&format!(
            "{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.8},{},{:.3},{},{},{}\n",
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
            f.colour.as_deref().unwrap_or_default(),
        ));
    }
    out
}

/// `status` of a fruit its estimate was matched to on the current visit.
pub const SEEN: &str = "seen";
/// `status` of a fruit known from earlier visits but not seen on this one (hidden or harvested).
pub const NOT_SEEN: &str = "not seen this visit";

/// The `/api/trolleys/{id}/season` document: every fruit of the trolley's row this season.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct SeasonDoc {
    pub trolley: String,
    /// The visit of its row the trolley is on (0: the first).
    pub visit: u32,
    pub fruits: Vec<SeasonFruitDoc>,
}

/// One fruit over the visits.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct SeasonFruitDoc {
    /// Stable from visit to visit.
    pub season_id: u32,
    /// Its estimate's id on the current visit (the fruit table's id); 0 when not seen on it.
    pub fruit_id: u32,
    /// [`SEEN`] or [`NOT_SEEN`].
    pub status: &'static str,
    /// Oldest visit first.
    pub visits: Vec<SeasonVisitDoc>,
}

/// One fruit on one visit.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct SeasonVisitDoc {
    pub visit: u32,
    /// World frame (the first visit's), metres.
    pub centre_m: [f64; 3],
    /// The fruit's box, metres.
    pub size_m: [f64; 3],
    /// The fitted solid's volume, else the box's.
    pub volume_cm3: f64,
    /// Its mean observed colour on that visit, `#rrggbb`; null when unknown.
    pub colour: Option<String>,
    /// Its volume over the record before, measured on one shape; null when not measured.
    pub volume_ratio: Option<f64>,
    /// Its volume change since the record before: measured on one shape where the ratio was
    /// (`glasshouse_geom::volume_change_m3`); null where it was not.
    pub growth_cm3: Option<f64>,
}

impl SeasonVisitDoc {
    /// The record in the page's units, `before` the fruit's record before it; `None` when a
    /// value is not finite.
    fn new(v: &FruitVisit, before: Option<&FruitVisit>) -> Option<Self> {
        let growth_m3 = match (before, v.volume_ratio) {
            (Some(b), Some(ratio)) => Some(volume_change_m3(b.volume_m3, v.volume_m3, ratio)),
            _ => None,
        };
        let doc = Self {
            visit: v.visit,
            centre_m: v.centre.coords.into(),
            size_m: v.size_m.into(),
            volume_cm3: v.volume_m3 * 1e6,
            colour: v.colour.as_ref().map(Rgb::hex),
            volume_ratio: v.volume_ratio,
            growth_cm3: growth_m3.map(|g| g * 1e6).filter(|g| g.is_finite()),
        };
        let values = doc.centre_m.iter().chain(&doc.size_m);
        let finite = values.chain([&doc.volume_cm3]).all(|x| x.is_finite());
        finite.then_some(doc)
    }
}

impl SeasonFruitDoc {
    fn new(h: &FruitHistory) -> Self {
        Self {
            season_id: h.season_id,
            fruit_id: h.fruit_id,
            status: if h.fruit_id == 0 { NOT_SEEN } else { SEEN },
            visits: (0..h.visits.len())
                .filter_map(|i| {
                    let before = i.checked_sub(1).map(|b| &h.visits[b]);
                    SeasonVisitDoc::new(&h.visits[i], before)
                })
                .collect(),
        }
    }

    fn seen(&self) -> bool {
        self.fruit_id != 0
    }

    /// Its volume on `visit`, when it has a record of it.
    fn volume_cm3_on(&self, visit: u32) -> Option<f64> {
        let record = self.visits.iter().find(|v| v.visit == visit);
        record.map(|v| v.volume_cm3)
    }
}

/// The season of one trolley, or `None` when the trolley is unknown.
pub fn season_doc(fleet: &FleetState, tid: &str) -> Option<SeasonDoc> {
    let t = fleet.trolleys.get(tid)?;
    Some(SeasonDoc {
        trolley: tid.to_owned(),
        visit: t.visit,
        fruits: t.history.iter().map(SeasonFruitDoc::new).collect(),
    })
}

/// CSV of a season: a header line, then a line per fruit and visit (`colour`: `#rrggbb`, empty
/// when unknown).
pub fn season_csv(season: &SeasonDoc) -> String {
    let mut out = String::from(
        "season_id,visit,centre_x_m,centre_y_m,centre_z_m,size_x_m,size_y_m,size_z_m,volume_cm3,seen_this_visit,colour,volume_ratio,growth_cm3\n",
    );
    let optional =
        |v: Option<f64>, digits: usize| v.map_or(String::new(), |v| format!("{v:.digits$}"));
    for f in &season.fruits {
        for v in &f.visits {
            let [cx, cy, cz] = v.centre_m;
            let [sx, sy, sz] = v.size_m;
            out.push_str(&format!(
                "{},{},{cx:.4},{cy:.4},{cz:.4},{sx:.4},{sy:.4},{sz:.4},{:.3},{},{},{},{}\n",
                f.season_id,
                v.visit,
                v.volume_cm3,
                f.seen(),
                v.colour.as_deref().unwrap_or_default(),
                optional(v.volume_ratio, 4),
                optional(v.growth_cm3, 3),
            ));
        }
    }
    out
}

/// One trolley's row of `/api/season`.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct SeasonRow {
    pub trolley: String,
    pub visit: u32,
    /// Fruits seen on the current visit.
    pub fruits_now: usize,
    /// Fruits of the season: seen now or on an earlier visit.
    pub fruits_known: usize,
    pub not_seen_this_visit: usize,
    /// Fruits whose first record is the current visit.
    pub new_this_visit: usize,
    /// Mean volume of the fruits with a record of the current visit; null when none has.
    pub mean_volume_cm3_now: Option<f64>,
    /// Mean volume of the fruits with a record of the visit before (each fruit recorded then,
    /// seen now or not); null on the first visit or when none has.
    pub mean_volume_cm3_previous_visit: Option<f64>,
}

/// The `/api/season` document.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct SeasonTable {
    pub trolleys: Vec<SeasonRow>,
}

impl SeasonRow {
    pub fn new(season: &SeasonDoc) -> Self {
        let fruits = &season.fruits;
        let visit = season.visit;
        let is_new = |f: &&SeasonFruitDoc| f.visits.first().is_some_and(|v| v.visit == visit);
        let mean_on = |visit: u32| mean(fruits.iter().filter_map(|f| f.volume_cm3_on(visit)));
        Self {
            trolley: season.trolley.clone(),
            visit,
            fruits_now: fruits.iter().filter(|f| f.seen()).count(),
            fruits_known: fruits.len(),
            not_seen_this_visit: fruits.iter().filter(|f| !f.seen()).count(),
            new_this_visit: fruits.iter().filter(is_new).count(),
            mean_volume_cm3_now: mean_on(visit),
            mean_volume_cm3_previous_visit: visit.checked_sub(1).and_then(mean_on),
        }
    }
}

/// Every trolley's season row.
pub fn season_table(fleet: &FleetState) -> SeasonTable {
    let docs = fleet.trolleys.keys().filter_map(|id| season_doc(fleet, id));
    SeasonTable {
        trolleys: docs.map(|doc| SeasonRow::new(&doc)).collect(),
    }
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(sum, n), v| (sum + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// The HTTP routes.
pub fn router(state: WebState) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/healthz", get(|| async { "ok" }))
        .route("/api/fleet", get(fleet))
        .route("/api/trolleys/{id}/fruits", get(fruits))
        .route("/api/trolleys/{id}/season", get(season))
        .route("/api/season", get(season_all))
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
        Some("csv") => attachment(
            "text/csv; charset=utf-8",
            &format!("fruits-{id}.csv"),
            fruits_csv(&docs),
        ),
        None | Some("json") => Json(docs).into_response(),
        Some(other) => (
            StatusCode::BAD_REQUEST,
            format!("unknown format {other:?}: use json or csv"),
        )
            .into_response(),
    }
}

/// A file name for a download of trolley `tid`'s `what`: characters a header or a file system
/// could take for something else become `_`.
fn download_name(tid: &str, what: &str) -> String {
    let safe = |c: char| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.');
    let tid: String = tid.chars().map(|c| if safe(c) { c } else { '_' }).collect();
    format!("{tid}-{what}")
}

/// `body` as a download named `filename`.
fn attachment(content_type: &str, filename: &str, body: String) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type.to_owned()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{filename}\""),
            ),
        ],
        body,
    )
        .into_response()
}

async fn season(
    State(state): State<WebState>,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
) -> Response {
    let doc = season_doc(&locked(&state), &id);
    let Some(doc) = doc else {
        return (StatusCode::NOT_FOUND, format!("no trolley {id:?}")).into_response();
    };
    let download = query.get("download").is_some_and(|d| d == "1");
    match query.get("format").map(String::as_str) {
        Some("csv") => attachment(
            "text/csv; charset=utf-8",
            &download_name(&id, "season.csv"),
            season_csv(&doc),
        ),
        None | Some("json") if download => match serde_json::to_string_pretty(&doc) {
            Ok(json) => attachment("application/json", &download_name(&id, "season.json"), json),
            Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
        },
        None | Some("json") => Json(doc).into_response(),
        Some(other) => (
            StatusCode::BAD_REQUEST,
            format!("unknown format {other:?}: use json or csv"),
        )
            .into_response(),
    }
}

async fn season_all(State(state): State<WebState>) -> Response {
    Json(season_table(&locked(&state))).into_response()
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
        assert!(near(r.hand_eye_deg, 0.2562), "{r:?}");
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
        assert_eq!(doc.hand_eye_deg, None);
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

    fn fruits_key(tid: &str) -> ParsedKey {
        ParsedKey::Trolley {
            tid: tid.into(),
            topic: TrolleyTopic::Fruits,
        }
    }

    /// The sample's season (visit 2; fruit 5 seen on visits 0 and 2, green then red) plus fruit
    /// 6, seen on visit 1 only and of unknown colour, fruit 7, new on visit 2, and fruit 8,
    /// whose one record holds a NaN.
    fn season_fleet() -> FleetState {
        let mut estimates = samples::fruit_estimates();
        let record = estimates.history[0].visits[0];
        let on = |visit: u32, volume_m3: f64| FruitVisit {
            visit,
            volume_m3,
            ..record
        };
        estimates.history.extend([
            FruitHistory {
                season_id: 6,
                fruit_id: 0,
                visits: vec![FruitVisit {
                    colour: None,
                    ..on(1, 2e-4)
                }],
                last_surface: None,
            },
            FruitHistory {
                season_id: 7,
                fruit_id: 9,
                visits: vec![on(2, 1e-4)],
                last_surface: None,
            },
            FruitHistory {
                season_id: 8,
                fruit_id: 0,
                visits: vec![on(1, f64::NAN)],
                last_surface: None,
            },
        ]);
        let mut fleet = FleetState::default();
        let message = Message::FruitEstimates(estimates);
        fleet.apply(
            &fruits_key("t1"),
            &samples::header(1),
            &message,
            Instant::now(),
        );
        fleet
    }

    /// The sample fruit's record of its visit `i`-th (0: visit 0, 1: visit 2).
    fn sample_record(i: usize) -> FruitVisit {
        samples::fruit_estimates().history[0].visits[i]
    }

    fn near(value: f64, expected: f64) -> bool {
        (value - expected).abs() < 1e-6
    }

    #[test]
    fn the_season_document_shows_each_fruit_over_the_visits_and_whether_it_was_seen() {
        let fleet = season_fleet();
        let doc = season_doc(&fleet, "t1").expect("t1 is known");
        assert_eq!((doc.trolley.as_str(), doc.visit), ("t1", 2));
        let ids: Vec<_> = doc.fruits.iter().map(|f| (f.season_id, f.status)).collect();
        assert_eq!(ids, [(5, SEEN), (6, NOT_SEEN), (7, SEEN), (8, NOT_SEEN)]);
        let sample = &doc.fruits[0];
        assert_eq!(sample.fruit_id, samples::fruit_estimates().fruits[0].id);
        let visits: Vec<_> = sample.visits.iter().map(|v| v.visit).collect();
        assert_eq!(visits, [0, 2]);
        let (last, sent) = (&sample.visits[1], sample_record(1));
        assert!(near(last.volume_cm3, sent.volume_m3 * 1e6), "{last:?}");
        assert_eq!(last.size_m, <[f64; 3]>::from(sent.size_m));
        assert_eq!(last.centre_m, <[f64; 3]>::from(sent.centre.coords));
        // Its colour on each visit: green, then red; fruit 6's unknown.
        let colours: Vec<_> = sample.visits.iter().map(|v| v.colour.as_deref()).collect();
        assert_eq!(colours, [Some("#6e9628"), Some("#be2319")]);
        assert_eq!(doc.fruits[1].visits[0].colour, None);
        // The NaN record is left out, so the document is valid JSON.
        assert!(doc.fruits[3].visits.is_empty());
        let json = serde_json::to_string(&doc).expect("json");
        assert!(
            json.contains("\"status\":\"not seen this visit\""),
            "{json}"
        );
        assert!(json.contains("\"colour\":\"#be2319\""), "{json}");
        assert!(json.contains("\"colour\":null"), "{json}");
        assert!(season_doc(&fleet, "t2").is_none());
    }

    #[test]
    fn the_season_csv_has_a_line_per_fruit_and_visit() {
        let doc = season_doc(&season_fleet(), "t1").expect("t1 is known");
        let csv = season_csv(&doc);
        let lines: Vec<_> = csv.lines().collect();
        assert_eq!(
            lines[0],
            "season_id,visit,centre_x_m,centre_y_m,centre_z_m,size_x_m,size_y_m,size_z_m,volume_cm3,seen_this_visit,colour,volume_ratio,growth_cm3"
        );
        // Fruit 5's two visits, fruit 6's and fruit 7's one each; fruit 8's NaN left out.
        assert_eq!(lines.len(), 1 + 4, "{csv}");
        let r = sample_record(1);
        let (c, size) = (r.centre, r.size_m);
        let expected = format!(
            "5,2,{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.3},true,#be2319,1.9531,116.348",
            c.x,
            c.y,
            c.z,
            size.x,
            size.y,
            size.z,
            r.volume_m3 * 1e6
        );
        assert_eq!(lines[2], expected);
        // The first visit has no growth to measure: empty fields.
        assert!(lines[1].ends_with(",true,#6e9628,,"), "{csv}");
        // Fruit 6's colour is unknown: an empty field.
        assert!(lines[3].starts_with("6,1,") && lines[3].ends_with(",200.000,false,,,"));
        assert!(lines.iter().all(|l| l.split(',').count() == 13), "{csv}");
    }

    #[test]
    fn the_fruits_document_and_csv_carry_each_fruits_colour() {
        let fleet = season_fleet();
        let docs = fruit_docs(&fleet, "t1").expect("t1 is known");
        assert_eq!(docs[0].colour.as_deref(), Some("#be2319"));
        let csv = fruits_csv(&docs);
        let lines: Vec<_> = csv.lines().collect();
        assert!(lines[0].ends_with(",fitted_confidence,colour"), "{csv}");
        assert!(lines[1].ends_with(",#be2319"), "{csv}");
        let mut unknown = docs[0].clone();
        unknown.colour = None;
        let csv = fruits_csv(&[unknown]);
        assert!(
            csv.lines().nth(1).is_some_and(|l| l.ends_with(',')),
            "{csv}"
        );
    }

    #[test]
    fn the_season_row_counts_fruits_now_known_missing_and_new() {
        let table = season_table(&season_fleet());
        let row = &table.trolleys[0];
        let counts = (
            row.fruits_now,
            row.fruits_known,
            row.not_seen_this_visit,
            row.new_this_visit,
        );
        assert_eq!(counts, (2, 4, 2, 1));
        // Visit 2: fruit 5 and 7 (100 cm³); visit 1: fruit 6 (200), 8's NaN left out.
        let now = row.mean_volume_cm3_now.expect("a mean now");
        let fruit_5_cm3 = sample_record(1).volume_m3 * 1e6;
        assert!(near(now, (fruit_5_cm3 + 100.0) / 2.0), "{row:?}");
        let before = row.mean_volume_cm3_previous_visit.expect("a mean before");
        assert!(near(before, 200.0), "{row:?}");
    }

    #[test]
    fn a_trolley_without_a_season_has_an_empty_row() {
        let mut fleet = FleetState::default();
        let first_visit = Message::FruitEstimates(glasshouse_proto::FruitEstimates {
            visit: 0,
            history: Vec::new(),
            ..samples::fruit_estimates()
        });
        fleet.apply(
            &fruits_key("t1"),
            &samples::header(1),
            &first_visit,
            Instant::now(),
        );
        let row = &season_table(&fleet).trolleys[0];
        assert_eq!((row.visit, row.fruits_known, row.fruits_now), (0, 0, 0));
        let means = (row.mean_volume_cm3_now, row.mean_volume_cm3_previous_visit);
        assert_eq!(means, (None, None));
        let json = serde_json::to_string(&season_table(&fleet)).expect("json");
        assert!(json.contains("\"mean_volume_cm3_now\":null"), "{json}");
    }

    fn web_state(fleet: FleetState) -> WebState {
        WebState {
            fleet: Arc::new(Mutex::new(fleet)),
            counters: Arc::default(),
            rerun_viewer_url: None,
        }
    }

    async fn season_response(tid: &str, query: &[(&str, &str)]) -> (StatusCode, String, String) {
        let query = query.iter().map(|(k, v)| (k.to_string(), v.to_string()));
        let response = season(
            State(web_state(season_fleet())),
            Path(tid.to_owned()),
            Query(query.collect()),
        )
        .await;
        let status = response.status();
        let disposition = response
            .headers()
            .get(header::CONTENT_DISPOSITION)
            .map_or(String::new(), |h| h.to_str().unwrap_or("?").to_owned());
        let body = axum::body::to_bytes(response.into_body(), 1 << 20)
            .await
            .expect("body");
        (status, disposition, String::from_utf8_lossy(&body).into())
    }

    #[tokio::test]
    async fn the_season_route_answers_csv_and_json_downloads_and_404_for_an_unknown_trolley() {
        let (status, disposition, body) = season_response("t1", &[("format", "csv")]).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(disposition, "attachment; filename=\"t1-season.csv\"");
        assert!(body.starts_with("season_id,visit,"), "{body}");

        let (status, disposition, body) = season_response("t1", &[("download", "1")]).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(disposition, "attachment; filename=\"t1-season.json\"");
        let json: serde_json::Value = serde_json::from_str(&body).expect("json");
        assert_eq!(json["fruits"][0]["season_id"], 5);

        let (status, disposition, _) = season_response("t1", &[]).await;
        assert_eq!((status, disposition.as_str()), (StatusCode::OK, ""));

        let (status, _, body) = season_response("t9", &[("format", "csv")]).await;
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert_eq!(body, "no trolley \"t9\"");

        let (status, _, _) = season_response("t1", &[("format", "xml")]).await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
    }

    #[test]
    fn a_download_name_keeps_only_plain_characters() {
        assert_eq!(download_name("t1", "season.csv"), "t1-season.csv");
        assert_eq!(download_name("a\"b/c\n", "season.csv"), "a_b_c_-season.csv");
    }
}
