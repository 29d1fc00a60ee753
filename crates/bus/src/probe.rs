//! A secured deployment's refusals, tried from outside: `glasshouse secure probe`, the compose
//! rig's rogue container and the secured-fleet test all run [`probe`].
//!
//! The rogue tries to connect without a certificate and with another CA's, then, as a valid
//! identity of the roster (a trolley), tries what its role does not allow: another trolley's keys,
//! views and ROI clouds, planner and detector liveliness tokens, a map snapshot query.
//!
//! A refusal is shown by a control: the rogue sends the forbidden message and then an allowed one
//! (a put on its own trolley's status) on the same link, so had the router let the first through,
//! the observer (a dashboard identity: it reads every topic and watches every token) would have
//! received it before the control. A snapshot query is refused when nothing answers it.
//!
//! Given detector and planner identities, it also plays a compromised detector and a compromised
//! planner ([`compromised`]): messages the router lets through, which the planners and the edge
//! must refuse.

mod compromised;

use std::path::{Path, PathBuf};
use std::time::Duration;

use glasshouse_proto::keys::{self, MemberKind, TrolleyTopic};
use serde_json::Value;
use tokio::sync::mpsc::{unbounded_channel, UnboundedReceiver, UnboundedSender};
use zenoh::qos::CongestionControl;
use zenoh::Session;

use crate::BusArgs;

/// Who probes what, and with which files.
#[derive(Clone, Debug)]
pub struct ProbeSetup {
    /// Client config of the identity that tries what it may not: a trolley of the roster.
    pub rogue: PathBuf,
    /// That trolley's id (its own status key carries the controls).
    pub rogue_trolley: String,
    /// The trolley whose keys the rogue tries to use.
    pub victim: String,
    /// Client config of a dashboard identity, which watches what passes the router.
    pub observer: PathBuf,
    /// The planners whose snapshot queryables are asked.
    pub planners: Vec<String>,
    /// Client config of a planner identity, to show that a snapshot query can be answered at all
    /// (optional: without it a refused query is only "no answer").
    pub snapshot_control: Option<PathBuf>,
    /// A private key and its certificate signed by another CA.
    pub foreign_key: PathBuf,
    pub foreign_cert: PathBuf,
    /// Where the derived one-try configs are written.
    pub scratch: PathBuf,
    /// How long to wait for a session, a control or an answer.
    pub timeout: Duration,
    /// Detector identities of the roster, (id, client config): the one serving the victim sends
    /// the control clouds, another the forged ones. Empty: no compromised detector.
    pub detectors: Vec<(String, PathBuf)>,
    /// Planner identities likewise: the victim's owner sends the control views, another the
    /// forged ones. Empty: no compromised planner.
    pub planner_identities: Vec<(String, PathBuf)>,
    /// How long to wait for the first control: until the router has told the rogue of the
    /// observer's subscriptions. On a loaded machine (a rig just started, images being built)
    /// links take far longer to come up than one message takes to pass them; this is a wait on
    /// a condition, so a generous bound costs nothing when the links are quick.
    pub link_timeout: Duration,
}

/// One thing the rogue tried.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Attempt {
    pub what: String,
    /// The router let it through (a hole in the deployment).
    pub accepted: bool,
}

/// Why a probe could not judge (as opposed to an attempt that got through).
#[derive(thiserror::Error, Debug)]
pub enum ProbeError {
    #[error("{path}: {why}")]
    Config { path: PathBuf, why: String },
    #[error("the {who} session did not open: {why}")]
    Session { who: &'static str, why: String },
    #[error("{0}")]
    Zenoh(String),
    #[error("control {number} (after: {after}) did not reach the observer within {timeout:?}")]
    NoControl {
        number: u64,
        after: String,
        timeout: Duration,
    },
    #[error("a planner identity's snapshot query got no answer within {0:?}: the control failed")]
    SnapshotControl(Duration),
    #[error("{0}")]
    Identities(String),
    #[error("no sign of {0} in time: the probe cannot judge")]
    NoSign(String),
}

fn zenoh_error(e: impl std::fmt::Display) -> ProbeError {
    ProbeError::Zenoh(e.to_string())
}

/// Runs every attempt; `Ok` lists them with their outcome (any `accepted` is a hole).
pub async fn probe(setup: &ProbeSetup) -> Result<Vec<Attempt>, ProbeError> {
    let mut attempts = connection_attempts(setup).await?;
    let observer = open_as(&setup.observer, "observer", setup.link_timeout).await?;
    let rogue = open_as(&setup.rogue, "rogue", setup.link_timeout).await?;
    let mut watch = Observer::declare(&observer).await?;
    let mut rogue = Rogue {
        session: &rogue,
        control_key: own_key(&setup.rogue_trolley, TrolleyTopic::Status)?,
        sent: 0,
        last: "nothing".into(),
        timeout: setup.timeout,
    };
    // The method itself: a control must arrive (repeated until the rogue knows the observer).
    rogue.first_control(&mut watch, setup.link_timeout).await?;
    for (what, key) in forbidden_puts(setup)? {
        let accepted = rogue.put_passes(&mut watch, &key).await?;
        attempts.push(Attempt { what, accepted });
    }
    for kind in [MemberKind::Planner, MemberKind::Detector] {
        let token =
            keys::alive(kind, &format!("{}-probe", setup.rogue_trolley)).map_err(zenoh_error)?;
        let what = format!("declare a liveliness token {token}");
        let accepted = rogue.token_passes(&mut watch, &token).await?;
        attempts.push(Attempt { what, accepted });
    }
    attempts.push(snapshot_attempt(setup, rogue.session).await?);
    attempts.extend(compromised::detector_attempts(setup, &observer).await?);
    attempts.extend(compromised::planner_attempts(setup, &observer).await?);
    let _ = observer.close().await;
    let _ = rogue.session.close().await;
    Ok(attempts)
}

/// The puts a trolley identity must not make: (what, key).
fn forbidden_puts(setup: &ProbeSetup) -> Result<Vec<(String, String)>, ProbeError> {
    let (me, victim) = (setup.rogue_trolley.as_str(), setup.victim.as_str());
    let cases = [
        (victim, TrolleyTopic::Rgbd, format!("{victim}'s frame")),
        (victim, TrolleyTopic::Status, format!("{victim}'s status")),
        (
            victim,
            TrolleyTopic::Views,
            format!("views that move {victim}'s arm"),
        ),
        (me, TrolleyTopic::Views, "views for itself".to_owned()),
        (
            victim,
            TrolleyTopic::Roi,
            format!("an ROI cloud (a fruit) for {victim}"),
        ),
        (me, TrolleyTopic::Roi, "an ROI cloud for itself".to_owned()),
        (
            victim,
            TrolleyTopic::Fruits,
            format!("{victim}'s fruit estimates"),
        ),
        (victim, TrolleyTopic::Map, format!("{victim}'s map update")),
    ];
    // Clouds and views on the keys of the services that send them (impersonating them).
    let planner = setup.planners.first().map_or("p1", String::as_str);
    let detector = setup.detectors.first().map_or("d1", |(id, _)| id.as_str());
    let mut puts = Vec::new();
    for (tid, topic, what) in cases {
        let sender = match topic {
            TrolleyTopic::Roi => detector,
            _ => planner,
        };
        let key = keys::trolley_from(tid, topic, sender).map_err(zenoh_error)?;
        puts.push((format!("put {what} on {key}"), key));
    }
    puts.push((
        format!("put fleet fruits on {}", keys::FLEET_FRUITS),
        keys::FLEET_FRUITS.to_owned(),
    ));
    Ok(puts)
}

fn own_key(tid: &str, topic: TrolleyTopic) -> Result<String, ProbeError> {
    keys::trolley(tid, topic).map_err(zenoh_error)
}

async fn open_as(
    config: &Path,
    who: &'static str,
    timeout: Duration,
) -> Result<Session, ProbeError> {
    let args = BusArgs {
        zenoh_config: Some(config.to_path_buf()),
        ..BusArgs::default()
    };
    match tokio::time::timeout(timeout, crate::open(&args)).await {
        Ok(Ok(session)) => Ok(session),
        Ok(Err(e)) => Err(ProbeError::Session {
            who,
            why: e.to_string(),
        }),
        Err(_) => Err(ProbeError::Session {
            who,
            why: format!("no connection within {timeout:?}"),
        }),
    }
}

/// Sessions without a certificate of the deployment's CA: each must fail to open.
async fn connection_attempts(setup: &ProbeSetup) -> Result<Vec<Attempt>, ProbeError> {
    // The rogue's own config, made to try once, must connect: else a refusal proves nothing.
    let same = one_try_config(setup, "same", |_| {})?;
    open_once(&same, setup.link_timeout).await?;
    let no_cert = one_try_config(setup, "no-cert", |tls| {
        tls["enable_mtls"] = false.into();
        if let Some(tls) = tls.as_object_mut() {
            tls.remove("connect_private_key");
            tls.remove("connect_certificate");
        }
    })?;
    let foreign = one_try_config(setup, "foreign-ca", |tls| {
        tls["connect_private_key"] = path_value(&setup.foreign_key);
        tls["connect_certificate"] = path_value(&setup.foreign_cert);
    })?;
    let mut attempts = Vec::new();
    for (what, config) in [
        ("connect without a client certificate", no_cert),
        ("connect with a certificate of another CA", foreign),
    ] {
        let accepted = open_once(&config, setup.timeout).await.is_ok();
        attempts.push(Attempt {
            what: what.to_owned(),
            accepted,
        });
    }
    Ok(attempts)
}

fn path_value(path: &Path) -> Value {
    path.to_string_lossy().into_owned().into()
}

/// Opens a session from `config` and closes it again; the error says why it did not open.
async fn open_once(config: &Path, timeout: Duration) -> Result<(), ProbeError> {
    let session = open_as(config, "one-try", timeout).await?;
    let _ = session.close().await;
    Ok(())
}

/// The rogue's config with its TLS section changed by `edit`, trying to connect once only.
fn one_try_config(
    setup: &ProbeSetup,
    name: &str,
    edit: impl FnOnce(&mut Value),
) -> Result<PathBuf, ProbeError> {
    let config_error = |path: &Path, why: String| ProbeError::Config {
        path: path.to_path_buf(),
        why,
    };
    let text = std::fs::read_to_string(&setup.rogue)
        .map_err(|e| config_error(&setup.rogue, e.to_string()))?;
    let mut config: Value =
        json5::from_str(&text).map_err(|e| config_error(&setup.rogue, e.to_string()))?;
    if config["transport"]["link"]["tls"].as_object().is_none() {
        return Err(config_error(
            &setup.rogue,
            "no transport.link.tls section".into(),
        ));
    }
    config["connect"]["timeout_ms"] = 0.into();
    config["connect"]["exit_on_failure"] = true.into();
    edit(&mut config["transport"]["link"]["tls"]);
    std::fs::create_dir_all(&setup.scratch)
        .map_err(|e| config_error(&setup.scratch, e.to_string()))?;
    let path = setup.scratch.join(format!("probe-{name}.json5"));
    std::fs::write(&path, config.to_string()).map_err(|e| config_error(&path, e.to_string()))?;
    Ok(path)
}

/// What the observer receives, in arrival order: (key, payload); tokens carry an empty payload.
struct Observer {
    rx: UnboundedReceiver<(String, Vec<u8>)>,
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
}

fn forward(
    tx: &UnboundedSender<(String, Vec<u8>)>,
) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    let tx = tx.clone();
    move |sample| {
        let key = sample.key_expr().as_str().to_owned();
        let _ = tx.send((key, sample.payload().to_bytes().into_owned()));
    }
}

impl Observer {
    /// Every trolley topic, the fleet fruits and the planner and detector tokens, in one queue.
    /// The status topic, which carries the controls, comes last: declarations reach the rogue in
    /// order, so once a control arrives the rogue knows of every other subscriber too (a client
    /// sends a put only where it knows one).
    async fn declare(session: &Session) -> Result<Observer, ProbeError> {
        let (tx, rx) = unbounded_channel();
        let mut subscribers = Vec::new();
        for kind in [MemberKind::Planner, MemberKind::Detector] {
            let sub = session
                .liveliness()
                .declare_subscriber(keys::alive_all(kind))
                .callback(forward(&tx))
                .await;
            subscribers.push(sub.map_err(zenoh_error)?);
        }
        let mut data: Vec<String> = TrolleyTopic::ALL
            .iter()
            .filter(|&&t| t != TrolleyTopic::Status)
            .map(|&t| keys::all_trolleys(t))
            .collect();
        data.push(keys::FLEET_FRUITS.to_owned());
        data.push(keys::all_trolleys(TrolleyTopic::Status));
        for key in data {
            let sub = session.declare_subscriber(key).callback(forward(&tx)).await;
            subscribers.push(sub.map_err(zenoh_error)?);
        }
        Ok(Observer {
            rx,
            _subscribers: subscribers,
        })
    }
}

/// The rogue's session and its numbered controls.
struct Rogue<'a> {
    session: &'a Session,
    control_key: String,
    sent: u64,
    /// What was tried before the latest control.
    last: String,
    timeout: Duration,
}

impl Rogue<'_> {
    async fn put(&self, key: &str, payload: Vec<u8>) -> Result<(), ProbeError> {
        // A refused put still returns Ok here: the router drops it.
        self.session
            .put(key, payload)
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(zenoh_error)
    }

    /// Puts the next control and waits up to `wait` for it: `Some(true)` when `forbidden`
    /// matched a sample before it, `None` when it did not come.
    async fn control_within(
        &mut self,
        watch: &mut Observer,
        forbidden: impl Fn(&str, &[u8]) -> bool,
        wait: Duration,
    ) -> Result<Option<bool>, ProbeError> {
        self.sent += 1;
        let control = format!("glasshouse-probe control {}", self.sent).into_bytes();
        self.put(&self.control_key, control.clone()).await?;
        let mut seen = false;
        let arrival = async {
            while let Some((key, payload)) = watch.rx.recv().await {
                if key == self.control_key && payload == control {
                    return true;
                }
                seen |= forbidden(&key, &payload);
            }
            false
        };
        let arrived = tokio::time::timeout(wait, arrival).await.unwrap_or(false);
        Ok(arrived.then_some(seen))
    }

    fn no_control(&self) -> ProbeError {
        ProbeError::NoControl {
            number: self.sent,
            after: self.last.clone(),
            timeout: self.timeout,
        }
    }

    /// Puts the next control and waits for it; true when `forbidden` matched a sample before.
    async fn control(
        &mut self,
        watch: &mut Observer,
        forbidden: impl Fn(&str, &[u8]) -> bool,
    ) -> Result<bool, ProbeError> {
        let timeout = self.timeout;
        let seen = self.control_within(watch, forbidden, timeout).await?;
        seen.ok_or_else(|| self.no_control())
    }

    /// Controls until one arrives: a client sends a put only once it has heard of a subscriber,
    /// and the observer's subscriptions reach the rogue through the router a moment later.
    async fn first_control(
        &mut self,
        watch: &mut Observer,
        link_timeout: Duration,
    ) -> Result<(), ProbeError> {
        let deadline = tokio::time::Instant::now() + link_timeout;
        while tokio::time::Instant::now() < deadline {
            let wait = Duration::from_millis(250);
            if self
                .control_within(watch, |_, _| false, wait)
                .await?
                .is_some()
            {
                return Ok(());
            }
        }
        Err(ProbeError::NoControl {
            number: self.sent,
            after: self.last.clone(),
            timeout: link_timeout,
        })
    }

    /// Puts a tagged payload on `key`, then a control; true when the observer saw the first.
    async fn put_passes(&mut self, watch: &mut Observer, key: &str) -> Result<bool, ProbeError> {
        let tagged = format!("glasshouse-probe forbidden {}", self.sent).into_bytes();
        self.last = format!("put on {key}");
        self.put(key, tagged.clone()).await?;
        self.control(watch, |_, p| p == tagged.as_slice()).await
    }

    /// Declares a token on `key`, then a control; true when the observer saw the token.
    async fn token_passes(&mut self, watch: &mut Observer, key: &str) -> Result<bool, ProbeError> {
        let token = self
            .session
            .liveliness()
            .declare_token(key)
            .await
            .map_err(zenoh_error)?;
        self.last = format!("token {key}");
        let seen = self.control(watch, |k, _| k == key).await;
        let _ = token.undeclare().await;
        seen
    }
}

/// Any answer (a map or a refusal) to a query of `victim`'s snapshot on one of `planners`.
async fn answered(
    session: &Session,
    planners: &[String],
    victim: &str,
    timeout: Duration,
) -> Result<bool, ProbeError> {
    for pid in planners {
        let key = keys::planner_snapshot(pid, victim).map_err(zenoh_error)?;
        let replies = session
            .get(key.as_str())
            .timeout(timeout)
            .await
            .map_err(zenoh_error)?;
        if replies.recv_async().await.is_ok() {
            return Ok(true);
        }
    }
    Ok(false)
}

/// [`answered`], asked again until an answer comes or `timeout` passes: a session just opened
/// has not yet heard of the planners' queryables, and its first query gets an empty reply at once.
async fn answered_within(
    session: &Session,
    planners: &[String],
    victim: &str,
    timeout: Duration,
) -> Result<bool, ProbeError> {
    let deadline = tokio::time::Instant::now() + timeout;
    let retry_every = Duration::from_millis(250);
    loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        if answered(session, planners, victim, left.max(retry_every)).await? {
            return Ok(true);
        }
        if tokio::time::Instant::now() + retry_every >= deadline {
            return Ok(false);
        }
        tokio::time::sleep(retry_every).await;
    }
}

async fn snapshot_attempt(setup: &ProbeSetup, rogue: &Session) -> Result<Attempt, ProbeError> {
    let (planners, victim) = (&setup.planners, setup.victim.as_str());
    if let Some(config) = &setup.snapshot_control {
        let planner = open_as(config, "snapshot control", setup.timeout).await?;
        let ok = answered_within(&planner, planners, victim, setup.timeout).await?;
        let _ = planner.close().await;
        if !ok {
            return Err(ProbeError::SnapshotControl(setup.timeout));
        }
    }
    Ok(Attempt {
        what: format!(
            "query {victim}'s map snapshot from planners {}",
            planners.join(",")
        ),
        accepted: answered(rogue, planners, victim, setup.timeout).await?,
    })
}
