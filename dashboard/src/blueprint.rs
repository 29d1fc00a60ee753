//! The Rerun layout sent with every recording and live stream: the 3D world first and large,
//! each trolley's camera image (colour, depth and its ROI cloud) beside it, fruit counts and
//! frame → views latency as time series below, and the dashboard's event log at the bottom.
//! Sent again, and made active, when a trolley first appears (the layout grows with the fleet).

use std::collections::BTreeSet;

use rerun::blueprint::{
    Blueprint, ContainerLike, Horizontal, Spatial2DView, Spatial3DView, Tabs, TextLogView,
    TimeSeriesView, Vertical,
};

/// The entity of the dashboard's event log (trolleys joining, state changes, owners).
pub const LOG_ENTITY: &str = "log";

/// The layout for `trolleys`.
pub fn layout(trolleys: &BTreeSet<String>) -> Blueprint {
    let world = Spatial3DView::new("World").with_origin("/world");
    let cameras: Vec<ContainerLike> = trolleys
        .iter()
        .map(|tid| {
            let image = format!("/world/trolleys/{tid}/camera/image");
            Spatial2DView::new(format!("{tid} camera"))
                .with_origin(image)
                .with_contents([
                    "$origin/**".to_string(),
                    format!("/world/trolleys/{tid}/roi_cloud"),
                ])
                .into()
        })
        .collect();
    let series = |name: &str, leaf: &str| {
        TimeSeriesView::new(name.to_string())
            .with_origin("/trolleys")
            .with_contents(trolleys.iter().map(|tid| format!("/trolleys/{tid}/{leaf}")))
    };
    let top: Vec<ContainerLike> = if cameras.is_empty() {
        vec![world.into()]
    } else {
        vec![world.into(), Tabs::new(cameras).into()]
    };
    let columns = top.len();
    let charts = Horizontal::new([
        series("Fruits found", "fruits_found").into(),
        series("Frame → views (ms)", "frame_to_views_ms").into(),
    ]);
    let log = TextLogView::new("Log").with_origin(format!("/{LOG_ENTITY}"));
    Blueprint::new(
        Vertical::new([
            Horizontal::new(top)
                .with_column_shares(if columns == 2 {
                    vec![2.0, 1.0]
                } else {
                    vec![1.0]
                })
                .into(),
            charts.into(),
            log.into(),
        ])
        .with_row_shares([3.0, 1.0, 1.0]),
    )
    .with_auto_views(false)
}
