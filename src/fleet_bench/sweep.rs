//! The capacity sweep of `fleet-bench --trolleys 4,8,16,...`: one row per trolley count and a
//! plot of frame -> views latency against trolleys.

use glasshouse_eval::plot::{render_png, PlotSpec, Series, PALETTE};

use super::{mib, ms, Report};

/// The p99 frame -> views the fleet should hold (the capacity goal), drawn on the plot.
const GOAL_P99_MS: f64 = 250.0;

fn secs(s: Option<f64>) -> String {
    s.map_or("–".into(), |s| format!("{s:.2} s"))
}

/// Scans lost over every moved trolley, and whether every map equals its rebuild.
fn scans_lost(f: &super::fault::FaultReport) -> String {
    let maps: Vec<_> = f.moved.values().filter_map(|m| m.map.as_ref()).collect();
    let lost: u64 = maps.iter().map(|m| m.scans_lost).sum();
    let equal = maps.len() == f.moved.len() && maps.iter().all(|m| m.maps_equal);
    match equal {
        true => format!("{lost} (maps equal)"),
        false => format!("{lost} (maps differ or unchecked)"),
    }
}

/// One line per count: latency, waiting arms, planner cost and memory, wire size, drops, takeover.
pub(super) fn print_table(reports: &[Report]) {
    println!();
    println!("capacity sweep ({} runs)", reports.len());
    println!(
        "| trolleys | frames/s per trolley | frame -> views p50 / p99 | arms waiting | planner CPU per frame: run / minute 1 / last minute | planner RSS per trolley, minute 1 / end | bytes per frame | drops | back on views after the fault: t1 / last | scans lost (moved trolleys) |"
    );
    println!("|---:|---:|---|---:|---:|---|---:|---:|---:|---:|");
    for r in reports {
        println!(
            "| {} | {:.2} | {} / {} | {:.0} % | {} / {} / {} | {} / {} | {} | {} | {} / {} | {} |",
            r.trolleys,
            r.frames_per_s_per_trolley,
            ms(r.frame_to_views_ms_p50),
            ms(r.frame_to_views_ms_p99),
            100.0 * r.arm_wait_share,
            ms(r.planner_cpu_ms_per_frame),
            ms(r.planner_cpu_ms_per_frame_minute1),
            ms(r.planner_cpu_ms_per_frame_last_minute),
            mib(r.planner_rss_mib_per_trolley_minute1),
            mib(r.planner_rss_mib_per_trolley_end),
            r.bytes_per_frame
                .map_or("–".into(), |b| format!("{:.0} kB", b / 1e3)),
            r.messages_dropped,
            secs(r.fault.as_ref().and_then(|f| f.t1_s)),
            secs(r.fault.as_ref().and_then(|f| f.last_s)),
            r.fault.as_ref().map_or("–".into(), scans_lost),
        );
    }
    println!();
    println!("planner time per frame by stage (the planners' own count, ms), and catch-ups after the fault");
    println!(
        "| trolleys | integrate | cluster | track | fit | plan | publish | catch-ups (s, all) |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in reports {
        let stage = |name: &str| {
            r.planner_stage_ms_per_frame
                .get(name)
                .map_or("–".into(), |ms| format!("{ms:.1}"))
        };
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {:.2} |",
            r.trolleys,
            stage("integrate"),
            stage("cluster"),
            stage("track"),
            stage("fit"),
            stage("plan"),
            stage("publish"),
            r.planner_catch_up_ms / 1e3,
        );
    }
}

/// p99 and p50 frame -> views (ms) against trolleys, with the goal as a dashed line.
pub(super) fn plot(reports: &[Report]) -> anyhow::Result<Vec<u8>> {
    let points = |pick: fn(&Report) -> Option<f64>| -> Vec<(f64, f64)> {
        reports
            .iter()
            .map(|r| (f64::from(r.trolleys), pick(r).unwrap_or(f64::NAN)))
            .collect()
    };
    let p99 = points(|r| r.frame_to_views_ms_p99);
    let p50 = points(|r| r.frame_to_views_ms_p50);
    let x_max = reports.iter().map(|r| r.trolleys).max().unwrap_or(1);
    let highest = p99
        .iter()
        .map(|p| p.1)
        .filter(|v| v.is_finite())
        .fold(GOAL_P99_MS, f64::max);
    let spec = PlotSpec {
        title: "fleet capacity".into(),
        x_label: "trolleys".into(),
        y_label: "frame to views (ms)".into(),
        x_max: f64::from(x_max),
        y_min: 0.0,
        y_max: (highest * 1.1 / 100.0).ceil() * 100.0,
        width: 900,
        height: 560,
    };
    let series = [
        Series {
            label: "p99".into(),
            color: PALETTE[3],
            dashed: false,
            points: p99,
        },
        Series {
            label: "p50".into(),
            color: PALETTE[0],
            dashed: false,
            points: p50,
        },
        Series {
            label: "goal p99".into(),
            color: PALETTE[2],
            dashed: true,
            points: vec![(0.0, GOAL_P99_MS), (f64::from(x_max), GOAL_P99_MS)],
        },
    ];
    Ok(render_png(&spec, &series)?)
}
