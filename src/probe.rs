//! `glasshouse secure probe`: tries, from outside, what a secured deployment must refuse, and says
//! which attempts got through (`glasshouse_bus::probe` does the trying).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context};
use glasshouse_bus::probe::{probe, Attempt, ProbeSetup};
use glasshouse_trust::{Identity, Kind, Roster};

#[derive(clap::Args, Debug)]
pub struct ProbeArgs {
    /// Client config of a trolley identity of the roster, used as the rogue: it tries another
    /// trolley's keys, views, ROI clouds, planner and detector tokens and snapshot queries
    /// (e.g. pki/trolley-t2.json5). Its key and certificate also try to connect without the
    /// certificate, and a fresh foreign CA's certificate is tried too.
    #[arg(long, value_name = "FILE")]
    rogue: PathBuf,
    /// The rogue's trolley id [default: from its file name, trolley-<id>.json5].
    #[arg(long, value_name = "ID")]
    rogue_trolley: Option<String>,
    /// The trolley whose keys the rogue tries to use.
    #[arg(long, value_name = "ID", default_value = "t1")]
    victim: String,
    /// Client config of a dashboard identity, which watches what passes the router.
    #[arg(long, value_name = "FILE")]
    observer: PathBuf,
    /// Planner ids whose map snapshots of the victim are asked for, comma-separated.
    #[arg(long, value_name = "IDS", value_delimiter = ',', required = true)]
    planners: Vec<String>,
    /// Client config of a planner identity: first shows that its snapshot query is answered, so
    /// the rogue's unanswered one is a refusal (needs a live planner holding the victim's map).
    #[arg(long, value_name = "FILE")]
    snapshot_control: Option<PathBuf>,
    /// Client configs of detector identities (`detector-<id>.json5`, comma-separated or
    /// repeated), at least two: the one serving the victim shows that its clouds are taken,
    /// another tries the victim's clouds as a compromised detector.
    #[arg(long, value_name = "FILES", value_delimiter = ',')]
    detector_identity: Vec<PathBuf>,
    /// Client configs of planner identities (`planner-<id>.json5`), at least two: the victim's
    /// owner shows that its views are executed (moving the victim's arm once, to a view it
    /// planned), another tries views for the victim as a compromised planner.
    #[arg(long, value_name = "FILES", value_delimiter = ',')]
    planner_identity: Vec<PathBuf>,
    /// Seconds to wait for a session, a control message or an answer.
    #[arg(long, value_name = "S", default_value_t = 10)]
    timeout_s: u64,
    /// Seconds to wait for the rogue's and the observer's sessions and the first control: until
    /// the router has linked them (slow on a loaded machine; the probe goes on as soon as they
    /// are linked).
    #[arg(long, value_name = "S", default_value_t = 90)]
    link_timeout_s: u64,
    /// Also write the attempts as JSON here.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
}

/// The trolley id in a `trolley-<id>.json5` file name.
fn trolley_of(path: &std::path::Path) -> Option<String> {
    id_of(path, Kind::Trolley)
}

/// The id in a `<kind>-<id>.json5` file name.
fn id_of(path: &std::path::Path, kind: Kind) -> Option<String> {
    let stem = path.file_stem()?.to_str()?;
    let prefix = format!("{}-", kind.as_str());
    stem.strip_prefix(&prefix).map(str::to_owned)
}

/// Each config with the id its file name gives.
fn identities(paths: &[PathBuf], kind: Kind) -> anyhow::Result<Vec<(String, PathBuf)>> {
    let named = |path: &PathBuf| {
        let id = id_of(path, kind).with_context(|| {
            format!("{}: not named {}-<id>.json5", path.display(), kind.as_str())
        })?;
        Ok((id, path.clone()))
    };
    paths.iter().map(named).collect()
}

pub async fn run(args: ProbeArgs) -> anyhow::Result<()> {
    let rogue_trolley = match &args.rogue_trolley {
        Some(id) => id.clone(),
        None => trolley_of(&args.rogue).with_context(|| {
            format!(
                "{}: name the rogue's trolley with --rogue-trolley",
                args.rogue.display()
            )
        })?,
    };
    anyhow::ensure!(
        rogue_trolley != args.victim,
        "the rogue and the victim must be different trolleys"
    );
    let scratch = std::env::temp_dir().join(format!("glasshouse-probe-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    // A CA the deployment has never seen, with a certificate for the victim's name.
    let victim = Identity::new(Kind::Trolley, &args.victim)?;
    let roster = Roster {
        trolleys: vec![args.victim.clone()],
        ..Roster::default()
    };
    let foreign = crate::secure::create(&scratch.join("foreign-ca"), &roster, 1)?;
    let setup = ProbeSetup {
        rogue: args.rogue.clone(),
        rogue_trolley,
        victim: args.victim.clone(),
        observer: args.observer.clone(),
        planners: args.planners.clone(),
        snapshot_control: args.snapshot_control.clone(),
        detectors: identities(&args.detector_identity, Kind::Detector)?,
        planner_identities: identities(&args.planner_identity, Kind::Planner)?,
        foreign_key: foreign.key(&victim.common_name()),
        foreign_cert: foreign.cert(&victim.common_name()),
        scratch: scratch.clone(),
        timeout: Duration::from_secs(args.timeout_s.max(1)),
        link_timeout: Duration::from_secs(args.link_timeout_s.max(1)),
    };
    let outcome = probe(&setup).await;
    let _ = std::fs::remove_dir_all(&scratch);
    let attempts = outcome?;
    print_attempts(&attempts);
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_string_pretty(&attempts)?)
            .with_context(|| path.display().to_string())?;
    }
    let holes = attempts.iter().filter(|a| a.accepted).count();
    if holes > 0 {
        bail!("{holes} of {} attempts got through", attempts.len());
    }
    println!("0 of {} attempts got through", attempts.len());
    Ok(())
}

fn print_attempts(attempts: &[Attempt]) {
    for a in attempts {
        let outcome = if a.accepted { "ACCEPTED" } else { "refused" };
        println!("{outcome:>8}  {}", a.what);
    }
}
