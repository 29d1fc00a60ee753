//! Compromised services: a valid detector identity sending clouds for a trolley another detector
//! serves, and a valid planner identity sending views for a trolley another planner owns.
//!
//! The router lets these through (each identity puts under its own id, as its role does); the
//! receivers must refuse them. So each attempt is judged by what the receivers report: the
//! planner owning the victim counts refused clouds in its status and its map and views never
//! show the forged frame; the victim's edge counts refused views in its status and never
//! executes them. Beside them a control, the same kind of message from the identity the victim
//! is assigned to (the detector whose clouds its map takes, the planner whose views its arm
//! executes), must show up, else the probe cannot judge. The control cloud is of a frame older
//! than the map's (planned on, never inserted); the control views are the owner's own latest
//! views aimed at the edge's new frame: the arm moves once, to a view its owner chose.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use glasshouse_proto::keys;
use glasshouse_proto::{
    samples, Header, MapUpdate, PlannerStatus, RankedViews, RoiCloud, TrolleyState, TrolleyStatus,
};
use tokio::time::Instant;
use zenoh::qos::CongestionControl;
use zenoh::Session;

use super::{open_as, zenoh_error, Attempt, ProbeError, ProbeSetup};
use crate::{Delivery, DropCounters, Subscriber};

/// The frame epoch of the probe's clouds: older than any edge's, so a map that takes such a
/// cloud plans on it but does not insert it.
const PROBE_EPOCH_NS: u64 = 1;
/// The probe's frame seqs and view marks start here (no trolley gets this far).
const PROBE_SEQ: u64 = 0x7e57_0000_0000;

/// The start of the probe's marks on its views.
const PROBE_MARK: &str = "glasshouse-probe-";

/// A role's identity: its id and client config.
type Identity = (String, PathBuf);

/// The victim's traffic, as the observer (a dashboard identity) receives it.
struct Victim {
    clouds: Subscriber<RoiCloud>,
    views: Subscriber<RankedViews>,
    maps: Subscriber<MapUpdate>,
    status: Subscriber<TrolleyStatus>,
    planners: Subscriber<PlannerStatus>,
}

impl Victim {
    async fn watch(observer: &Session, tid: &str) -> Result<Victim, ProbeError> {
        let drops = Arc::new(DropCounters::default());
        let key_error = |e: keys::KeyError| ProbeError::Zenoh(e.to_string());
        let declare_error = |e: crate::BusError| ProbeError::Zenoh(e.to_string());
        let monitor = Delivery::Monitor;
        Ok(Victim {
            clouds: Subscriber::declare_with(
                observer,
                &keys::roi_from_any(tid).map_err(key_error)?,
                monitor,
                drops.clone(),
            )
            .await
            .map_err(declare_error)?,
            views: Subscriber::declare_with(
                observer,
                &keys::views_from_any(tid).map_err(key_error)?,
                monitor,
                drops.clone(),
            )
            .await
            .map_err(declare_error)?,
            maps: Subscriber::declare_with(
                observer,
                &keys::map(tid).map_err(key_error)?,
                monitor,
                drops.clone(),
            )
            .await
            .map_err(declare_error)?,
            status: Subscriber::declare_with(
                observer,
                &keys::status(tid).map_err(key_error)?,
                monitor,
                drops.clone(),
            )
            .await
            .map_err(declare_error)?,
            planners: Subscriber::declare_with(
                observer,
                &keys::all_planner_status(),
                monitor,
                drops,
            )
            .await
            .map_err(declare_error)?,
        })
    }
}

/// The identity named `id` among `identities`, and another one: (assigned, rogue).
fn pick<'a>(
    identities: &'a [Identity],
    id: &str,
    role: &str,
) -> Result<(&'a Identity, &'a Identity), ProbeError> {
    let assigned = identities.iter().find(|(i, _)| i == id);
    let rogue = identities.iter().find(|(i, _)| i != id);
    match (assigned, rogue) {
        (Some(assigned), Some(rogue)) => Ok((assigned, rogue)),
        _ => Err(ProbeError::Identities(format!(
            "{role} {id} serves the victim: the probe needs its identity and another {role}'s"
        ))),
    }
}

/// The next message of `subscriber` before `deadline`.
async fn next<M: glasshouse_proto::Wire>(
    subscriber: &Subscriber<M>,
    deadline: Instant,
    what: &str,
) -> Result<crate::Received<M>, ProbeError> {
    match tokio::time::timeout_at(deadline, subscriber.recv()).await {
        Ok(Some(received)) => Ok(received),
        _ => Err(ProbeError::NoSign(what.to_owned())),
    }
}

/// A publisher of the probe's messages on one key.
struct Sender<'a>(zenoh::pubsub::Publisher<'a>);

impl<'a> Sender<'a> {
    /// Declared on `key`, once `session` knows of a subscriber there (a client sends a put only
    /// where it knows one: a put sent earlier would be dropped at the sender and look refused).
    async fn ready<M: glasshouse_proto::Wire>(
        session: &'a Session,
        key: &keys::Key<M>,
        timeout: Duration,
    ) -> Result<Sender<'a>, ProbeError> {
        let publisher = session
            .declare_publisher(key.as_str().to_owned())
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(zenoh_error)?;
        let deadline = Instant::now() + timeout;
        while !publisher
            .matching_status()
            .await
            .map_err(zenoh_error)?
            .matching()
        {
            if Instant::now() > deadline {
                let what = format!("a subscriber of {key} within {timeout:?}");
                return Err(ProbeError::NoSign(what));
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        Ok(Sender(publisher))
    }

    async fn send<M: glasshouse_proto::Wire>(
        &self,
        header: &Header,
        message: &M,
    ) -> Result<(), ProbeError> {
        let bytes = glasshouse_proto::encode(header, message);
        self.0.put(bytes).await.map_err(zenoh_error)
    }
}

/// A compromised detector's clouds for the victim, as itself and claiming the serving detector;
/// none of them may reach the victim's map. Nothing without detector identities.
pub(super) async fn detector_attempts(
    setup: &ProbeSetup,
    observer: &Session,
) -> Result<Vec<Attempt>, ProbeError> {
    if setup.detectors.is_empty() {
        return Ok(Vec::new());
    }
    let tid = setup.victim.as_str();
    let watch = Victim::watch(observer, tid).await?;
    let deadline = Instant::now() + setup.link_timeout;
    let serving = serving_detector(&watch, deadline).await?;
    let ((_, control_config), (rogue, rogue_config)) =
        pick(&setup.detectors, &serving, "detector")?;
    let (owner, refusals_before) = owner_refusals(&watch, tid, deadline).await?;
    let rogue_session = open_as(rogue_config, "compromised detector", setup.timeout).await?;
    let control_session = open_as(control_config, "serving detector", setup.timeout).await?;
    let key = keys::roi(tid, rogue).map_err(zenoh_error)?;
    let rogue_clouds = Sender::ready(&rogue_session, &key, setup.timeout).await?;
    let key = keys::roi(tid, &serving).map_err(zenoh_error)?;
    let control_clouds = Sender::ready(&control_session, &key, setup.timeout).await?;
    let forged = [rogue.as_str(), serving.as_str()];
    for (n, claimed) in (0..).zip(forged) {
        let cloud = probe_cloud(PROBE_SEQ + n);
        rogue_clouds
            .send(&cloud_header(tid, claimed), &cloud)
            .await?;
    }
    let control = (
        &control_clouds,
        &cloud_header(tid, &serving),
        PROBE_SEQ + 10,
    );
    // A loaded machine can take long to plan and publish: as long as the links may take.
    let wait = Instant::now()
        + setup
            .link_timeout
            .max(setup.timeout + Duration::from_secs(5));
    let seen = judge_clouds(&watch, (&owner, refusals_before, 2), control, wait).await?;
    drop((rogue_clouds, control_clouds));
    let _ = rogue_session.close().await;
    let _ = control_session.close().await;
    let attempts = (0..).zip(forged).map(|(n, claimed)| Attempt {
        what: format!(
            "detector {rogue} (not serving {tid}) puts an ROI cloud for {tid} claiming to be {claimed}"
        ),
        accepted: seen.contains(&(PROBE_SEQ + n)),
    });
    Ok(attempts.collect())
}

/// Clouds in a row from one detector before the probe takes it as the victim's: while a
/// fleet settles, two detectors can both send clouds for a trolley for a moment.
const SETTLED_CLOUDS: usize = 3;

/// Frames whose senders the probe remembers while it looks for the serving detector.
const REMEMBERED_FRAMES: usize = 256;

/// The detector serving the victim: the one its last [`SETTLED_CLOUDS`] clouds came from, once
/// the victim's map has taken a frame that detector alone sent. The clouds on the wire show
/// which detector believes it serves the victim; the map shows which one the owner takes
/// clouds from. While a fleet settles the two can differ (a planner that has not yet heard of a
/// detector takes the other's clouds), and a probe that judged by the wire alone once saw the
/// owner take the detector it served from as a forgery.
async fn serving_detector(watch: &Victim, deadline: Instant) -> Result<String, ProbeError> {
    let (mut sender, mut in_a_row) = (String::new(), 0);
    let mut senders_of_frame: std::collections::BTreeMap<u64, Vec<String>> = Default::default();
    let what = "clouds of the victim from one detector, one of them taken into its map";
    loop {
        tokio::select! {
            cloud = next(&watch.clouds, deadline, what) => {
                let cloud = cloud?;
                let from = keys::sender(&cloud.key).unwrap_or_default().to_owned();
                let senders = senders_of_frame.entry(cloud.message.source_frame_seq).or_default();
                if !senders.contains(&from) {
                    senders.push(from.clone());
                }
                while senders_of_frame.len() > REMEMBERED_FRAMES {
                    senders_of_frame.pop_first();
                }
                if from == sender {
                    in_a_row += 1;
                } else {
                    (sender, in_a_row) = (from, 1);
                }
            }
            update = next(&watch.maps, deadline, what) => {
                let taken = senders_of_frame.get(&update?.message.based_on_seq);
                if in_a_row >= SETTLED_CLOUDS && taken.is_some_and(|s| *s == [sender.clone()]) {
                    return Ok(sender);
                }
            }
        }
    }
}

fn cloud_header(tid: &str, source: &str) -> Header {
    Header {
        seq: 1,
        trolley_id: tid.into(),
        source_id: source.into(),
        frame_id: "world".into(),
        ..Header::default()
    }
}

/// A cloud of frame (PROBE_EPOCH_NS, `seq`).
fn probe_cloud(seq: u64) -> RoiCloud {
    RoiCloud {
        source_frame_epoch_ns: PROBE_EPOCH_NS,
        source_frame_seq: seq,
        ..samples::roi_cloud()
    }
}

/// The planner owning `tid` (its status lists it) and its refused clouds so far (refused and
/// unassigned).
async fn owner_refusals(
    watch: &Victim,
    tid: &str,
    deadline: Instant,
) -> Result<(String, u64), ProbeError> {
    loop {
        let status = next(
            &watch.planners,
            deadline,
            "the status of the victim's owner",
        )
        .await?;
        let s = status.message;
        if s.owned_trolleys.iter().any(|t| t == tid) {
            return Ok((s.planner_id, s.refused_clouds + s.unassigned_clouds));
        }
    }
}

/// How often the control cloud is sent again until it shows: an owner with a later cloud of
/// the trolley queued integrates an earlier one without planning on it, so on a loaded machine
/// one control can pass unseen.
const CONTROL_RESEND: Duration = Duration::from_secs(2);

/// Sends the control cloud (`control`: its sender, header and frame seq) and waits until it
/// shows in the victim's map or views, sending it again every [`CONTROL_RESEND`] until then,
/// and until every forged cloud either shows there too (taken) or was counted by the owner
/// (refused clouds over `before`); returns the probe frames seen.
async fn judge_clouds(
    watch: &Victim,
    (owner, before, forged): (&str, u64, u64),
    (sender, header, control): (&Sender<'_>, &Header, u64),
    deadline: Instant,
) -> Result<Vec<u64>, ProbeError> {
    let (mut seen, mut refused) = (Vec::new(), 0);
    let forged_seen = |seen: &Vec<u64>| seen.iter().filter(|&&f| f != control).count() as u64;
    let mut resend = tokio::time::interval(CONTROL_RESEND);
    let unjudged = |seen: &Vec<u64>, refused: u64| {
        ProbeError::NoSign(format!(
            "the control cloud in the map or views (seen: {}) and the forged clouds refused or \
             taken ({} of {forged}) before the deadline",
            seen.contains(&control),
            refused + forged_seen(seen)
        ))
    };
    while !(seen.contains(&control) && refused + forged_seen(&seen) >= forged) {
        let frame = tokio::select! {
            _ = resend.tick(), if !seen.contains(&control) => {
                sender.send(header, &probe_cloud(control)).await?;
                continue;
            }
            m = next(&watch.maps, deadline, "") => match m {
                Ok(m) => m.message.based_on_seq,
                Err(_) => return Err(unjudged(&seen, refused)),
            },
            v = next(&watch.views, deadline, "") => {
                let Ok(v) = v else { return Err(unjudged(&seen, refused)) };
                if v.message.based_on_epoch_ns != PROBE_EPOCH_NS { continue; }
                v.message.based_on_seq
            }
            s = next(&watch.planners, deadline, "") => {
                let Ok(s) = s else { return Err(unjudged(&seen, refused)) };
                if s.message.planner_id == owner {
                    let s = s.message;
                    refused = (s.refused_clouds + s.unassigned_clouds).saturating_sub(before);
                }
                continue;
            }
        };
        if frame >= PROBE_SEQ && !seen.contains(&frame) {
            seen.push(frame);
        }
    }
    Ok(seen)
}

/// A compromised planner's views for the victim, as itself and claiming the owner; the edge
/// must execute none of them. Nothing without planner identities.
pub(super) async fn planner_attempts(
    setup: &ProbeSetup,
    observer: &Session,
) -> Result<Vec<Attempt>, ProbeError> {
    if setup.planner_identities.is_empty() {
        return Ok(Vec::new());
    }
    let tid = setup.victim.as_str();
    let watch = Victim::watch(observer, tid).await?;
    let deadline = Instant::now() + setup.link_timeout;
    let (owner, mut template) = owner_views(&watch, deadline).await?;
    let ((_, owner_config), (rogue, rogue_config)) =
        pick(&setup.planner_identities, &owner, "planner")?;
    let rogue_session = open_as(rogue_config, "compromised planner", setup.timeout).await?;
    let owner_session = open_as(owner_config, "owning planner", setup.timeout).await?;
    // The edge executes the control only when its views beat its planner's on a frame: on a
    // loaded machine that takes some frames, so the wait is as long as the links may take.
    let wait = Instant::now()
        + setup
            .link_timeout
            .max(setup.timeout + Duration::from_secs(20));
    let mut edge = EdgeSeen::default();
    let key = keys::views(tid, rogue).map_err(zenoh_error)?;
    let rogue_views = Sender::ready(&rogue_session, &key, setup.timeout).await?;
    let key = keys::views(tid, &owner).map_err(zenoh_error)?;
    let owner_views = Sender::ready(&owner_session, &key, setup.timeout).await?;
    let forged = [rogue.as_str(), owner.as_str()];
    for (n, claimed) in (0..).zip(forged) {
        let frame = edge.next_frame(&watch, wait).await?;
        let views = aimed(&template, &frame, mark(n));
        rogue_views
            .send(&views_header(tid, claimed), &views)
            .await?;
    }
    // The owner's own views on a new frame, until the edge executed one (its planner's views
    // for the frame may come first). Each time the owner's newest views: the trolley moves on
    // along its row meanwhile, and views planned at an earlier segment may be out of reach.
    while !edge.executed(&mark(10)) {
        let frame = edge.next_frame(&watch, wait).await?;
        newest_views_of(&watch, &owner, &mut template);
        let views = aimed(&template, &frame, mark(10));
        owner_views.send(&views_header(tid, &owner), &views).await?;
        edge.controls_sent += 1;
    }
    // Each forged set was either executed or counted as refused.
    let taken = |edge: &EdgeSeen| (0..2).filter(|&n| edge.executed(&mark(n))).count() as u64;
    while edge.refused + taken(&edge) < edge.refused_before + 2 {
        edge.next_status(&watch, wait).await?;
    }
    drop((rogue_views, owner_views));
    let _ = rogue_session.close().await;
    let _ = owner_session.close().await;
    let attempts = (0..).zip(forged).map(|(n, claimed)| Attempt {
        what: format!(
            "planner {rogue} (not owning {tid}) puts views for {tid} claiming to be {claimed}"
        ),
        accepted: edge.executed(&mark(n)),
    });
    Ok(attempts.collect())
}

/// The probe's mark on its views (their `planner_id`): the edge's status names it among its
/// ownership terms once it executed them.
fn mark(n: u64) -> String {
    format!("{PROBE_MARK}{}", PROBE_SEQ + n)
}

fn views_header(tid: &str, source: &str) -> Header {
    Header {
        trolley_id: tid.into(),
        source_id: source.into(),
        frame_id: "world".into(),
        ..Header::default()
    }
}

/// The planner whose views the victim's edge executes (the sender of views its status counts
/// in its newest term) and its latest views.
async fn owner_views(
    watch: &Victim,
    deadline: Instant,
) -> Result<(String, RankedViews), ProbeError> {
    let mut owner: Option<String> = None;
    loop {
        tokio::select! {
            s = next(&watch.status, deadline, "the victim's edge executing views") => {
                owner = s?.message.owner_terms.last().map(|t| t.planner_id.clone()).or(owner);
            }
            v = next(&watch.views, deadline, "the owner's views") => {
                let v = v?;
                let sender = keys::sender(&v.key).unwrap_or_default();
                if owner.as_deref() == Some(sender) && !v.message.views.is_empty() {
                    return Ok((sender.to_owned(), v.message));
                }
            }
        }
    }
}

/// Replaces `template` by the newest non-empty views `owner` sent that the observer has queued
/// (not the probe's own, which are marked).
fn newest_views_of(watch: &Victim, owner: &str, template: &mut RankedViews) {
    while let Some(v) = watch.views.try_recv() {
        let from_owner = keys::sender(&v.key) == Some(owner);
        let probe = v.message.planner_id.starts_with(PROBE_MARK);
        if from_owner && !probe && !v.message.views.is_empty() {
            *template = v.message;
        }
    }
}

/// `template`'s views, aimed at the edge's frame under its newest ownership epoch, marked.
fn aimed(template: &RankedViews, frame: &(Header, TrolleyStatus), mark: String) -> RankedViews {
    RankedViews {
        based_on_epoch_ns: frame.0.epoch_ns,
        based_on_seq: frame.0.seq,
        owner_epoch: frame.1.owner_epoch,
        planner_id: mark,
        ..template.clone()
    }
}

/// What the victim's edge reported: refused views, and the marks of the views it executed.
#[derive(Default)]
struct EdgeSeen {
    refused_before: u64,
    refused: u64,
    started: bool,
    executed: Vec<String>,
    /// Control views sent, and how many views the edge found out of reach since the first
    /// status (for the message when the probe cannot judge).
    controls_sent: u32,
    unreachable_before: u32,
    unreachable: u32,
    state: Option<TrolleyState>,
}

impl EdgeSeen {
    fn executed(&self, mark: &str) -> bool {
        self.executed.iter().any(|m| m == mark)
    }

    async fn next_status(
        &mut self,
        watch: &Victim,
        deadline: Instant,
    ) -> Result<(Header, TrolleyStatus), ProbeError> {
        let status = match next(&watch.status, deadline, "").await {
            Ok(status) => status,
            Err(_) => return Err(ProbeError::NoSign(self.progress())),
        };
        let s = &status.message;
        if !self.started {
            self.started = true;
            (self.refused_before, self.unreachable_before) = (s.refused_views, s.unreachable_views);
        }
        (self.refused, self.unreachable) = (s.refused_views, s.unreachable_views);
        self.state = Some(s.state);
        for term in &s.owner_terms {
            if term.planner_id.starts_with(PROBE_MARK) && !self.executed(&term.planner_id) {
                self.executed.push(term.planner_id.clone());
            }
        }
        Ok((status.header, status.message))
    }

    /// What the edge showed so far, for the probe's verdict that it cannot judge.
    fn progress(&self) -> String {
        format!(
            "the victim's edge counting the views refused and executing the control (it counted \
             {} refused views of 2 forged, executed {:?}, {} control views sent, {} views out of \
             reach meanwhile, last state {:?})",
            self.refused.saturating_sub(self.refused_before),
            self.executed,
            self.controls_sent,
            self.unreachable.saturating_sub(self.unreachable_before),
            self.state,
        )
    }

    /// The next frame the edge announced and waits for views on (its status header names it).
    async fn next_frame(
        &mut self,
        watch: &Victim,
        deadline: Instant,
    ) -> Result<(Header, TrolleyStatus), ProbeError> {
        // Statuses queued before now name frames already answered.
        while watch.status.try_recv().is_some() {}
        loop {
            let (header, status) = self.next_status(watch, deadline).await?;
            if status.state == TrolleyState::WaitingForViews {
                return Ok((header, status));
            }
        }
    }
}
