//! `dashboard`: subscribes to everything on the Glasshouse bus, records it to Rerun and serves
//! the fleet web page.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use clap::Parser;
use glasshouse_bus::set_flag;
use glasshouse_dashboard::{DashboardSettings, FleetState, ServeSettings};

/// Read-only monitor of the fleet: a web page with fleet, planner and fruit tables (JSON API at
/// /api/fleet, /api/trolleys/{id}/fruits, /healthz), a Rerun recording and/or a live Rerun stream.
///
/// Settings: defaults, then `--config FILE` (JSON5: record, serve {bind_ip, grpc_port,
/// web_viewer_port, public_host, memory_limit_bytes}, http_listen, mcap {dir, max_file_bytes,
/// max_file_s, foxglove, queue}, foxglove {listen, queue}), then the flags below.
#[derive(Parser, Debug)]
#[command(name = "dashboard", version)]
struct Cli {
    /// Write a Rerun recording (.rrd) to FILE.
    #[arg(long, value_name = "FILE")]
    record: Option<PathBuf>,
    /// Serve the live 3D stream: a Rerun gRPC server plus the bundled web viewer.
    #[arg(long)]
    serve: bool,
    /// gRPC port of the live stream (with --serve).
    #[arg(long, default_value_t = 9877)]
    grpc_port: u16,
    /// Port of the Rerun web viewer (with --serve).
    #[arg(long, default_value_t = 9090)]
    web_viewer_port: u16,
    /// Megabytes of log data kept for late viewers (with --serve; oldest dropped first).
    #[arg(long, default_value_t = 512)]
    memory_limit_mb: u64,
    /// Host name used in the viewer URLs (what remote browsers reach this machine as).
    #[arg(long, default_value = "localhost")]
    public_host: String,
    /// Address of the fleet web page and JSON API.
    #[arg(long, value_name = "ADDR", default_value = "0.0.0.0:8080")]
    http: String,
    /// Do not serve the web page.
    #[arg(long)]
    no_http: bool,
    /// Record every key to MCAP files in DIR: our messages (flatbuffer, with their schema) and
    /// the same in Foxglove's schemas; files rotate by size and duration.
    #[arg(long, value_name = "DIR")]
    mcap: Option<PathBuf>,
    /// Serve Foxglove's live WebSocket protocol on ADDR (default 127.0.0.1:8765, Foxglove's own
    /// default; loopback only unless you say otherwise, as the protocol has no authentication):
    /// in Foxglove, "Open connection", Foxglove WebSocket, ws://ADDR.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8765")]
    foxglove: Option<String>,
}

fn main() -> anyhow::Result<()> {
    glasshouse_bus::service_main(apply_flags, |session, settings, shutdown, counters| {
        if let Some(serve) = &settings.serve {
            println!("live 3D view: {}", serve.web_viewer_url());
            println!("Rerun viewer: rerun {}", serve.grpc_url());
        }
        let state = Arc::new(Mutex::new(FleetState::default()));
        glasshouse_dashboard::run(session, settings, shutdown, state, counters)
    })
}

fn apply_flags(cli: Cli, settings: &mut DashboardSettings) -> anyhow::Result<()> {
    set_flag(&mut settings.record, cli.record.map(Some));
    if let Some(dir) = cli.mcap {
        let mcap = settings.mcap.get_or_insert_with(Default::default);
        mcap.dir = dir;
    }
    if let Some(listen) = cli.foxglove {
        let live = settings.foxglove.get_or_insert_with(Default::default);
        live.listen = listen;
    }
    if cli.serve {
        settings.serve = Some(ServeSettings {
            grpc_port: cli.grpc_port,
            web_viewer_port: cli.web_viewer_port,
            memory_limit_bytes: cli.memory_limit_mb << 20,
            public_host: cli.public_host,
            ..ServeSettings::default()
        });
    }
    if cli.no_http {
        settings.http_listen = None;
    } else if settings.http_listen.is_none() || cli.http != "0.0.0.0:8080" {
        settings.http_listen = Some(cli.http);
    }
    Ok(())
}
