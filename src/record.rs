//! `glasshouse record` and `glasshouse replay`: MCAP recordings of the bus, and putting one back
//! on the bus with its timing.

use std::collections::{BTreeMap, BTreeSet};
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use glasshouse_bus::{BusArgs, Delivery, DropCounters, RawPublisher, Shutdown};
use glasshouse_dashboard::{DashboardCounters, DashboardSettings, FleetState, McapSettings};
use glasshouse_proto::keys::{self, MemberKind, ParsedKey};
use glasshouse_proto::SCHEMA_ROOT_NAME;

/// `glasshouse record`.
#[derive(Args, Debug)]
pub struct RecordArgs {
    /// Folder for the MCAP files (created when missing).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Begin a new file past this many megabytes of messages.
    #[arg(long, default_value_t = 2048)]
    max_file_mb: u64,
    /// Begin a new file after this many seconds.
    #[arg(long, default_value_t = 600)]
    max_file_s: u64,
    /// Only our flatbuffer channels, not the Foxglove copies (about half the bytes).
    #[arg(long)]
    no_foxglove: bool,
    /// Stop after this many seconds (default: until Ctrl-C or SIGTERM).
    #[arg(long)]
    duration_s: Option<f64>,
    #[command(flatten)]
    bus: BusArgs,
}

pub async fn record(args: RecordArgs) -> anyhow::Result<()> {
    let session = glasshouse_bus::open(&args.bus).await?;
    let settings = DashboardSettings {
        mcap: Some(McapSettings {
            dir: args.out.clone(),
            max_file_bytes: args.max_file_mb << 20,
            max_file_s: args.max_file_s,
            foxglove: !args.no_foxglove,
            ..McapSettings::default()
        }),
        ..DashboardSettings::default()
    };
    let (trigger, shutdown) = Shutdown::new();
    let duration = args.duration_s.map(Duration::from_secs_f64);
    tokio::spawn(async move {
        match duration {
            Some(d) => {
                tokio::select! {
                    _ = tokio::time::sleep(d) => {}
                    _ = glasshouse_bus::shutdown_signal() => {}
                }
            }
            None => glasshouse_bus::shutdown_signal().await,
        }
        trigger.fire();
    });
    let counters = Arc::new(DashboardCounters::default());
    let state = Arc::new(Mutex::new(FleetState::default()));
    glasshouse_dashboard::run(session, settings, shutdown, state, counters.clone()).await?;
    let summary = counters
        .mcap
        .lock()
        .ok()
        .and_then(|s| s.clone())
        .context("no recording")?;
    println!(
        "recorded {} messages ({} frames) to {} file(s) in {}: {} bytes on disk ({:.0} per frame), {} dropped",
        summary.messages,
        summary.frames,
        summary.files.len(),
        args.out.display(),
        summary.disk_bytes,
        summary.disk_bytes as f64 / summary.frames.max(1) as f64,
        summary.dropped
    );
    let path = args.out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&summary)?)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// `glasshouse replay`.
#[derive(Args, Debug)]
pub struct ReplayArgs {
    /// An MCAP file, or a folder of them (played in name order).
    path: PathBuf,
    /// Only these topics of each trolley (rgbd, arm, info, roi, views, fruits, map, status,
    /// truth) and service keys (planner_status, detector_status, fleet_fruits); default: all.
    /// `--only info,roi` feeds a fresh planner the clouds of the run.
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Playback speed: 1 keeps the recorded timing, 0 plays as fast as the bus takes it.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Keep the trolleys' liveliness for this long after the last message (planners finish).
    #[arg(long, default_value_t = 2.0)]
    linger_s: f64,
    #[command(flatten)]
    bus: BusArgs,
}

/// The topic name `--only` matches a key by.
fn topic_name(key: &ParsedKey) -> Option<String> {
    Some(match key {
        ParsedKey::Trolley { topic, .. } => topic.as_str().to_string(),
        ParsedKey::PlannerStatus { .. } => "planner_status".into(),
        ParsedKey::DetectorStatus { .. } => "detector_status".into(),
        ParsedKey::FleetFruits => "fleet_fruits".into(),
        _ => return None,
    })
}

pub async fn replay(args: ReplayArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.speed >= 0.0 && args.speed.is_finite(),
        "--speed must be >= 0"
    );
    let files = if args.path.is_dir() {
        glasshouse_dashboard::mcap_recorder::recording_files(&args.path)?
    } else {
        vec![args.path.clone()]
    };
    anyhow::ensure!(
        !files.is_empty(),
        "no .mcap file in {}",
        args.path.display()
    );
    let only: BTreeSet<String> = args.only.iter().map(|s| s.trim().to_string()).collect();
    let session = glasshouse_bus::open(&args.bus).await?;
    let mut player = Player::new(session, only, args.speed);
    for file in &files {
        player.play(file).await?;
    }
    tokio::time::sleep(Duration::from_secs_f64(args.linger_s.max(0.0))).await;
    println!(
        "replayed {} messages from {} file(s) ({} skipped by --only, {} not ours)",
        player.published,
        files.len(),
        player.skipped,
        player.foreign
    );
    player.close().await;
    Ok(())
}

struct Player {
    session: zenoh::Session,
    only: BTreeSet<String>,
    speed: f64,
    publishers: BTreeMap<String, RawPublisher>,
    alive: BTreeMap<String, zenoh::liveliness::LivelinessToken>,
    drops: Arc<DropCounters>,
    /// Recorded and wall-clock time of the first message played.
    start: Option<(u64, tokio::time::Instant)>,
    published: u64,
    skipped: u64,
    foreign: u64,
}

impl Player {
    fn new(session: zenoh::Session, only: BTreeSet<String>, speed: f64) -> Self {
        Self {
            session,
            only,
            speed,
            publishers: BTreeMap::new(),
            alive: BTreeMap::new(),
            drops: Arc::new(DropCounters::default()),
            start: None,
            published: 0,
            skipped: 0,
            foreign: 0,
        }
    }

    async fn play(&mut self, path: &Path) -> anyhow::Result<()> {
        let file = File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
        for message in mcap::io::MessageReader::new(BufReader::new(file)) {
            let message = message
                .with_context(|| format!("{} is not a readable MCAP file", path.display()))?;
            let ours = message.channel.message_encoding == "flatbuffer"
                && message
                    .channel
                    .schema
                    .as_ref()
                    .is_some_and(|s| s.name == SCHEMA_ROOT_NAME);
            let key = message.channel.topic.clone();
            let Some(parsed) = keys::parse(&key).filter(|_| ours) else {
                self.foreign += 1;
                continue;
            };
            let wanted =
                self.only.is_empty() || topic_name(&parsed).is_some_and(|t| self.only.contains(&t));
            if !wanted {
                self.skipped += 1;
                continue;
            }
            self.wait_until(message.log_time).await;
            self.publish(&key, &parsed, message.data.into_owned())
                .await?;
        }
        Ok(())
    }

    async fn wait_until(&mut self, log_time_ns: u64) {
        let (first, started) = *self
            .start
            .get_or_insert((log_time_ns, tokio::time::Instant::now()));
        if self.speed > 0.0 {
            let offset_s = log_time_ns.saturating_sub(first) as f64 * 1e-9 / self.speed;
            tokio::time::sleep_until(started + Duration::from_secs_f64(offset_s)).await;
        }
    }

    /// Declares `id` alive as a `kind` (once): planners take clouds only from live detectors
    /// and serve only live trolleys, as they did when the run was recorded.
    async fn alive(&mut self, kind: MemberKind, id: &str) -> anyhow::Result<()> {
        let name = format!("{kind:?}/{id}");
        if !self.alive.contains_key(&name) {
            let token = glasshouse_bus::declare_alive(&self.session, kind, id).await?;
            self.alive.insert(name, token);
        }
        Ok(())
    }

    async fn publish(
        &mut self,
        key: &str,
        parsed: &ParsedKey,
        payload: Vec<u8>,
    ) -> anyhow::Result<()> {
        if let ParsedKey::Trolley { tid, topic } = parsed {
            self.alive(MemberKind::Trolley, tid).await?;
            if *topic == keys::TrolleyTopic::Roi {
                if let Ok((header, _)) = glasshouse_proto::decode(&payload) {
                    self.alive(MemberKind::Detector, &header.source_id).await?;
                }
            }
        }
        if !self.publishers.contains_key(key) {
            let delivery = match parsed {
                ParsedKey::Trolley { topic, .. } => topic.qos().into(),
                _ => Delivery::Reliable,
            };
            let publisher =
                RawPublisher::declare(&self.session, key, delivery, self.drops.clone()).await?;
            self.publishers.insert(key.to_string(), publisher);
        }
        if let Some(publisher) = self.publishers.get(key) {
            publisher.publish_bytes(payload).await?;
            self.published += 1;
        }
        Ok(())
    }

    async fn close(self) {
        for (_, publisher) in self.publishers {
            publisher.close().await;
        }
        drop(self.alive);
        let _ = self.session.close().await;
    }
}
