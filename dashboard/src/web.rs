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
    /// Share of ground-truth fruit volume inside detected boxes (simulated trolleys only).
    pub covered_volume: Option<f64>,
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
    /// Seconds since its last status (a lost planner's grows).
    pub last_status_age_s: Option<f64>,
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
            .map(|(id, t)| TrolleyRow {
                id: id.clone(),
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
                covered_volume: t.covered_volume,
            })
            .collect(),
        planners: fleet
            .planners
            .iter()
            .map(|(id, p)| PlannerRow {
                id: id.clone(),
                owned: p.owned_trolleys.clone(),
                standby: p.standby_trolleys.clone(),
                clouds_integrated: p.clouds_integrated,
                views_published: p.views_published,
                last_planning_time_ms: p.last_planning_time_ms,
                mean_planning_time_ms: p.mean_planning_time_ms,
                map_voxels: p.map_voxels,
                dropped: p.dropped_messages,
                refused_clouds: p.refused_clouds,
                last_status_age_s: fleet
                    .planner_seen_at
                    .get(id)
                    .map(|t| now.saturating_duration_since(*t).as_secs_f64()),
            })
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

/// The fruits of one trolley, or `None` when the trolley is unknown.
pub fn fruit_docs(fleet: &FleetState, tid: &str) -> Option<Vec<FruitDoc>> {
    let t = fleet.trolleys.get(tid)?;
    Some(
        t.fruits
            .iter()
            .map(|f| FruitDoc {
                id: f.id,
                centre_m: f.centre_in_world.into(),
                size_m: (f.box_max - f.box_min).into(),
                volume_m3: f.volume_m3,
                voxel_count: f.voxel_count,
                confidence: f.confidence,
                fitted_volume_m3: f.fitted.as_ref().map(|e| e.volume_m3),
                fitted_confidence: f.fitted.as_ref().map(|e| e.confidence),
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
