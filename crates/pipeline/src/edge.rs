//! The edge's loop as a state machine ([`EdgeNode`]): events in, actions out, no I/O.
//!
//! The loop is the paper's Algorithm 1 split across machines: capture frame n and announce it;
//! wait for RankedViews planned on frame n (announce it again when none come in time); execute
//! the first view the arm can reach; capture again. In a row, when the best view offered is not
//! worth a look, the trolley moves on to the next segment instead. The clock is simulated: each
//! view costs its motion time plus a capture time.
//!
//! The edge executes views only from the planner its own membership view ranks owner of its
//! trolley (the live planners' tokens, ranked with the planners' own rendezvous hash), and only
//! views planned on its latest frame (boot epoch and seq): views from anyone else are refused and
//! counted (`TrolleyStatus::refused_views`). Who sent views is the planner id their key ends in
//! (`gh/trolley/{tid}/views/{pid}`: in a secured deployment the router lets only planner `pid`
//! put there); views whose header names another planner are refused and counted the same way,
//! before anything else is read from them, so a stolen planner key moves only the arms of the
//! trolleys that planner owns. Views also carry their owner's ownership epoch
//! ([`glasshouse_fleet::epoch`]): views under an older epoch than the newest the edge has taken
//! come from a replaced owner (paused, cut off) and are refused and counted
//! (`TrolleyStatus::stale_views`), whoever sent them. The newest epoch goes out with every frame
//! (`TrolleyInfo::owner_epoch`), so a replaced owner learns it was replaced; when the planner
//! ranked owner is the one sending stale views (it ranks first again, but has not heard of the
//! newer term yet), the frame is announced again at once rather than after the views timeout.
//!
//! The edge service's driver performs the actions on the bus and on its [`TrolleySource`]
//! (`crate::TrolleySource`); the experiments perform them in-process. Both feed the outcomes
//! back as events.

use glasshouse_fleet::EpochVerdict;
use glasshouse_proto::{
    FrameId, Header, OwnerTerm, RankedView, RankedViews, TrolleyState, TrolleyStatus, OWNER_TERMS,
};
use nalgebra::Isometry3;

use crate::Executed;

/// What the edge's loop is configured to do.
#[derive(Clone, Debug, PartialEq)]
pub struct EdgeSettings {
    pub trolley_id: String,
    /// Stop after this many executed views (0 = no limit).
    pub max_views: u32,
    /// Simulated time to capture one view.
    pub capture_time_s: f64,
    /// The trolley moves on to the next segment when the best view it is sent has a utility no
    /// higher than this (the planner's switching threshold): nothing worth a look is left.
    pub segment_done_utility: f64,
}

/// What the edge reports to whoever embeds it (the demo prints these, the experiments count them).
#[derive(Clone, Debug, PartialEq)]
pub enum EdgeEvent {
    /// A view was executed.
    ViewDone {
        views_done: u32,
        frame_seq: u64,
        view: RankedView,
        sim_time_s: f64,
    },
    /// No view of the ranked list planned on `frame_seq` could be reached; capturing again.
    NoReachableView { frame_seq: u64, offered: usize },
    /// Nothing above the threshold was left in a segment; the trolley moved to the next one.
    SegmentDone { segments_done: u32, sim_time_s: f64 },
    /// No planner answered frame `frame_seq` in time; it was announced again.
    Reannounced { frame_seq: u64 },
    /// The run is over: the view budget is spent, the row is done or the source has no frames.
    Finished { views_done: u32, frames: u64 },
    /// Views from `source_id`, not from the trolley's owner (`owner`, if any planner is live),
    /// were refused; `refused` counts every refusal so far.
    ViewsRefused {
        source_id: String,
        owner: Option<String>,
        refused: u64,
    },
    /// Views put on planner `sender`'s key whose header claims planner `claimed` were refused;
    /// `refused` counts every refusal so far (these and [`EdgeEvent::ViewsRefused`]).
    MisattributedViewsRefused {
        sender: String,
        claimed: String,
        refused: u64,
    },
    /// Views from `source_id` under ownership epoch `owner_epoch`, older than the `newest` the
    /// edge has taken views under, were refused (a replaced owner's); `stale` counts every such
    /// refusal so far.
    StaleViewsRefused {
        source_id: String,
        owner_epoch: u64,
        newest: u64,
        stale: u64,
    },
}

/// An event the driver feeds in.
#[derive(Clone, Debug, PartialEq)]
pub enum EdgeInput {
    /// Begin the loop.
    Start,
    /// The capture asked for finished: `true` with a frame, `false` when the source has no more.
    Captured { frame: bool },
    /// No views arrived within the driver's timeout since the last `AwaitViews`.
    ViewsTimedOut,
    /// Views arrived on the trolley's views key of planner `sender` (the id the key ends in);
    /// the header names the trolley and, again, the planner.
    Views {
        sender: String,
        header: Header,
        views: RankedViews,
    },
    /// A planner's liveliness token appeared.
    PlannerJoined(String),
    /// A planner's liveliness token went away.
    PlannerLeft(String),
    /// The outcome of an `Execute` action.
    Executed(Option<Executed>),
    /// The outcome of a `MoveToNextSegment` action: the motion time, or None at the row's end.
    SegmentMoved(Option<f64>),
}

/// What the driver must do, in order.
#[derive(Clone, Debug, PartialEq)]
pub enum EdgeAction {
    /// Capture frame `frame_seq` at the current pose, then feed `Captured`.
    Capture { frame_seq: u64 },
    /// Publish the captured frame with the trolley info (carrying `owner_epoch`, the newest
    /// ownership epoch views were taken under, and `owner_id`, whose views they were), arm state
    /// (still) and ground truth.
    Announce {
        frame_seq: u64,
        sim_time_s: f64,
        owner_epoch: u64,
        owner_id: String,
    },
    /// (Re)start the timeout for views on the announced frame.
    AwaitViews,
    /// Publish the trolley's status (the driver fills in its drop count).
    PublishStatus {
        frame_seq: u64,
        sim_time_s: f64,
        status: TrolleyStatus,
    },
    /// Move to the first reachable of `goals` (best first), then feed `Executed`.
    Execute { goals: Vec<Isometry3<f64>> },
    /// Publish the arm state while it moves to the executed view.
    PublishArmMoving {
        frame_seq: u64,
        sim_time_s: f64,
        views_done: u32,
    },
    /// Move the trolley to the next segment of the row, then feed `SegmentMoved`.
    MoveToNextSegment,
    /// Tell the embedder.
    Report(EdgeEvent),
    /// The loop is over: publish nothing more after the actions before this one.
    Stop,
}

#[derive(Clone, Debug, PartialEq)]
enum Phase {
    Idle,
    Capturing,
    WaitingForViews,
    Executing(RankedViews),
    MovingSegment(RankedViews),
    Done,
}

/// The edge's loop (see the module docs).
#[derive(Clone, Debug)]
pub struct EdgeNode {
    settings: EdgeSettings,
    /// This process's boot epoch: its frames are (epoch_ns, frame_seq).
    epoch_ns: u64,
    /// The live planners, as their liveliness tokens say.
    planners: glasshouse_fleet::Membership,
    /// The planner whose views were taken under the newest ownership epoch.
    owner_id: String,
    /// The frame announced again at once because the owner sent stale views on it (once each).
    told_stale_owner: u64,
    frame_seq: u64,
    sim_time_s: f64,
    segments_done: u32,
    status: TrolleyStatus,
    phase: Phase,
}

impl EdgeNode {
    /// A node whose frames carry the boot epoch `epoch_ns` (chosen once by its process).
    pub fn new(settings: EdgeSettings, epoch_ns: u64) -> Self {
        Self {
            settings,
            epoch_ns,
            planners: glasshouse_fleet::Membership::new(),
            owner_id: String::new(),
            told_stale_owner: 0,
            frame_seq: 0,
            sim_time_s: 0.0,
            segments_done: 0,
            status: TrolleyStatus {
                state: TrolleyState::Starting,
                views_done: 0,
                frames_published: 0,
                unreachable_views: 0,
                reannounces: 0,
                dropped_messages: 0,
                last_views_seq: 0,
                message: String::new(),
                refused_views: 0,
                stale_views: 0,
                owner_epoch: 0,
                owner_terms: Vec::new(),
            },
            phase: Phase::Idle,
        }
    }

    /// Simulated seconds spent moving and capturing so far.
    pub fn sim_time_s(&self) -> f64 {
        self.sim_time_s
    }

    /// The latest frame sequence (the frame views are awaited for).
    pub fn frame_seq(&self) -> u64 {
        self.frame_seq
    }

    /// The latest frame: this process's epoch and the frame sequence.
    pub fn frame(&self) -> FrameId {
        FrameId::new(self.epoch_ns, self.frame_seq)
    }

    /// The planner this node takes views from: the live planner ranked first for its trolley.
    pub fn owner(&self) -> Option<&str> {
        self.planners.first_ranked(&self.settings.trolley_id)
    }

    pub fn status(&self) -> &TrolleyStatus {
        &self.status
    }

    /// The newest ownership epoch views were taken under (0: none yet).
    pub fn owner_epoch(&self) -> u64 {
        self.status.owner_epoch
    }

    pub fn is_done(&self) -> bool {
        self.phase == Phase::Done
    }

    /// Waiting for views on the latest frame (the driver's timeout applies).
    pub fn is_waiting_for_views(&self) -> bool {
        self.phase == Phase::WaitingForViews
    }

    /// Feeds one event; returns what to do. Events that do not fit the current phase (views on
    /// an older frame, a stray timeout) change nothing.
    pub fn handle(&mut self, input: EdgeInput) -> Vec<EdgeAction> {
        let input = match input {
            EdgeInput::PlannerJoined(id) => {
                self.planners.server_joined(id);
                return Vec::new();
            }
            EdgeInput::PlannerLeft(id) => {
                self.planners.server_left(id);
                return Vec::new();
            }
            // The key says who sent them; a header claiming another planner is not read further.
            EdgeInput::Views { sender, header, .. } if sender != header.source_id => {
                return self.refuse_misattributed(sender, header.source_id);
            }
            EdgeInput::Views { header, views, .. }
                if EpochVerdict::of(views.owner_epoch, self.status.owner_epoch).is_stale() =>
            {
                return self.refuse_stale(header.source_id, views.owner_epoch);
            }
            EdgeInput::Views { header, .. } if self.owner() != Some(&header.source_id) => {
                return self.refuse(header.source_id);
            }
            EdgeInput::Views {
                sender,
                header,
                views,
            } => {
                // From the owner, under the newest epoch or a newer one: the owner's term.
                self.status.owner_epoch = views.owner_epoch;
                self.owner_id.clone_from(&header.source_id);
                EdgeInput::Views {
                    sender,
                    header,
                    views,
                }
            }
            input => input,
        };
        match (std::mem::replace(&mut self.phase, Phase::Idle), input) {
            (Phase::Idle, EdgeInput::Start) => self.capture(),
            (Phase::Capturing, EdgeInput::Captured { frame: true }) => self.announce(),
            (Phase::Capturing, EdgeInput::Captured { frame: false }) => self.finish(),
            (Phase::WaitingForViews, EdgeInput::ViewsTimedOut) => self.reannounce(),
            (Phase::WaitingForViews, EdgeInput::Views { header, views, .. }) => {
                self.on_views(&header.trolley_id, views)
            }
            (Phase::Executing(views), EdgeInput::Executed(executed)) => {
                self.on_executed(&views, executed)
            }
            (Phase::MovingSegment(views), EdgeInput::SegmentMoved(moved)) => {
                self.on_segment_moved(views, moved)
            }
            (phase, _) => {
                self.phase = phase;
                Vec::new()
            }
        }
    }

    /// Ends the loop now (shutdown, or the end of the run): the final status, then `Stop`.
    /// Nothing when the loop is already over.
    pub fn finish(&mut self) -> Vec<EdgeAction> {
        if self.phase == Phase::Done {
            return Vec::new();
        }
        let mut actions = vec![EdgeAction::Report(EdgeEvent::Finished {
            views_done: self.status.views_done,
            frames: self.status.frames_published,
        })];
        self.phase = Phase::Done;
        self.status.state = TrolleyState::Done;
        self.status.message = format!(
            "{} views, {} frames",
            self.status.views_done, self.status.frames_published
        );
        actions.push(self.status_action());
        actions.push(EdgeAction::Stop);
        actions
    }

    /// Views not from the owner: counted, reported, never executed.
    fn refuse(&mut self, source_id: String) -> Vec<EdgeAction> {
        self.status.refused_views += 1;
        vec![EdgeAction::Report(EdgeEvent::ViewsRefused {
            source_id,
            owner: self.owner().map(str::to_owned),
            refused: self.status.refused_views,
        })]
    }

    /// Views whose header names another planner than their key: counted, reported, never
    /// executed.
    fn refuse_misattributed(&mut self, sender: String, claimed: String) -> Vec<EdgeAction> {
        self.status.refused_views += 1;
        vec![EdgeAction::Report(EdgeEvent::MisattributedViewsRefused {
            sender,
            claimed,
            refused: self.status.refused_views,
        })]
    }

    /// Views under an older ownership epoch than the newest taken: counted, reported, never
    /// executed. When they come from the planner ranked owner while the edge waits, that planner
    /// has not heard of the newer term (it was paused or cut off): the frame is announced again
    /// at once, its info carrying the newest epoch, instead of after the views timeout (once per
    /// frame).
    fn refuse_stale(&mut self, source_id: String, owner_epoch: u64) -> Vec<EdgeAction> {
        self.status.stale_views += 1;
        let tell = self.owner() == Some(source_id.as_str())
            && self.phase == Phase::WaitingForViews
            && self.told_stale_owner != self.frame_seq;
        let mut actions = vec![EdgeAction::Report(EdgeEvent::StaleViewsRefused {
            source_id,
            owner_epoch,
            newest: self.status.owner_epoch,
            stale: self.status.stale_views,
        })];
        if tell {
            self.told_stale_owner = self.frame_seq;
            actions.extend(self.reannounce());
        }
        actions
    }

    /// Counts an executed view in its ownership term (the last [`OWNER_TERMS`] are kept).
    fn count_term(&mut self, views: &RankedViews) {
        let terms = &mut self.status.owner_terms;
        let same = |t: &&mut OwnerTerm| {
            t.owner_epoch == views.owner_epoch && t.planner_id == views.planner_id
        };
        if let Some(term) = terms.iter_mut().rev().find(same) {
            term.views_executed += 1;
            return;
        }
        if terms.len() >= OWNER_TERMS {
            terms.remove(0);
        }
        terms.push(OwnerTerm {
            planner_id: views.planner_id.clone(),
            owner_epoch: views.owner_epoch,
            views_executed: 1,
        });
    }

    fn status_action(&self) -> EdgeAction {
        EdgeAction::PublishStatus {
            frame_seq: self.frame_seq,
            sim_time_s: self.sim_time_s,
            status: self.status.clone(),
        }
    }

    fn capture(&mut self) -> Vec<EdgeAction> {
        self.frame_seq += 1;
        self.status.state = TrolleyState::Capturing;
        self.phase = Phase::Capturing;
        vec![EdgeAction::Capture {
            frame_seq: self.frame_seq,
        }]
    }

    fn announce(&mut self) -> Vec<EdgeAction> {
        self.status.frames_published += 1;
        self.status.state = TrolleyState::WaitingForViews;
        self.phase = Phase::WaitingForViews;
        vec![
            EdgeAction::Announce {
                frame_seq: self.frame_seq,
                sim_time_s: self.sim_time_s,
                owner_epoch: self.status.owner_epoch,
                owner_id: self.owner_id.clone(),
            },
            self.status_action(),
            EdgeAction::AwaitViews,
        ]
    }

    fn reannounce(&mut self) -> Vec<EdgeAction> {
        self.status.reannounces += 1;
        self.phase = Phase::WaitingForViews;
        vec![
            EdgeAction::Report(EdgeEvent::Reannounced {
                frame_seq: self.frame_seq,
            }),
            EdgeAction::Announce {
                frame_seq: self.frame_seq,
                sim_time_s: self.sim_time_s,
                owner_epoch: self.status.owner_epoch,
                owner_id: self.owner_id.clone(),
            },
            EdgeAction::AwaitViews,
        ]
    }

    fn on_views(&mut self, trolley_id: &str, views: RankedViews) -> Vec<EdgeAction> {
        self.phase = Phase::WaitingForViews;
        if trolley_id != self.settings.trolley_id || views.based_on() != self.frame() {
            return Vec::new();
        }
        self.status.last_views_seq = views.based_on_seq;
        let max = self.settings.max_views;
        if max > 0 && self.status.views_done >= max {
            return self.finish();
        }
        // The best utility of the list, wherever it is ranked: a planner may rank a quicker
        // view first.
        let best_utility = views
            .views
            .iter()
            .map(|v| v.utility)
            .fold(f32::NEG_INFINITY, f32::max);
        if f64::from(best_utility) <= self.settings.segment_done_utility {
            self.phase = Phase::MovingSegment(views);
            return vec![EdgeAction::MoveToNextSegment];
        }
        self.execute(views)
    }

    fn execute(&mut self, views: RankedViews) -> Vec<EdgeAction> {
        let goals = views.views.iter().map(|v| v.world_from_camera).collect();
        self.phase = Phase::Executing(views);
        vec![EdgeAction::Execute { goals }]
    }

    fn on_segment_moved(&mut self, views: RankedViews, moved: Option<f64>) -> Vec<EdgeAction> {
        match moved {
            Some(motion_s) => {
                self.segments_done += 1;
                self.sim_time_s += motion_s.max(0.0) + self.settings.capture_time_s;
                let mut actions = vec![EdgeAction::Report(EdgeEvent::SegmentDone {
                    segments_done: self.segments_done,
                    sim_time_s: self.sim_time_s,
                })];
                actions.extend(self.capture());
                actions
            }
            // The row is done, but views below the threshold are still views: take them.
            None if !views.views.is_empty() => self.execute(views),
            None => self.finish(),
        }
    }

    fn on_executed(&mut self, views: &RankedViews, executed: Option<Executed>) -> Vec<EdgeAction> {
        let offered = views.views.len();
        let unreachable = executed.map_or(offered, |e| e.index.min(offered));
        self.status.unreachable_views = self
            .status
            .unreachable_views
            .saturating_add(unreachable as u32);
        let Some(executed) = executed.filter(|e| e.index < offered) else {
            self.sim_time_s += self.settings.capture_time_s;
            let mut actions = vec![EdgeAction::Report(EdgeEvent::NoReachableView {
                frame_seq: self.frame_seq,
                offered,
            })];
            actions.extend(self.capture());
            return actions;
        };
        self.status.state = TrolleyState::Moving;
        self.sim_time_s += executed.motion_s.max(0.0) + self.settings.capture_time_s;
        let moving = EdgeAction::PublishArmMoving {
            frame_seq: self.frame_seq,
            sim_time_s: self.sim_time_s,
            views_done: self.status.views_done,
        };
        self.status.views_done += 1;
        self.count_term(views);
        let done = EdgeEvent::ViewDone {
            views_done: self.status.views_done,
            frame_seq: self.frame_seq,
            view: views.views[executed.index].clone(),
            sim_time_s: self.sim_time_s,
        };
        let mut actions = vec![moving, EdgeAction::Report(done)];
        actions.extend(self.capture());
        actions
    }
}

/// Wall-clock pacing of the simulated clock (`edge --realtime`): a view's motion and capture
/// take as long in wall-clock time as the simulated arm says they take.
///
/// The spending starts when the driver performs an `Execute` or `MoveToNextSegment` (the arm
/// or trolley starts to move); the next `Capture` waits until that instant plus the simulated
/// seconds the node added meanwhile (motion + capture, or the capture alone when no view was
/// reachable). Time is passed in, so the durations are unit-tested without sleeping.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RealtimePacer {
    /// The wall-clock instant (since any fixed origin) and the node's simulated time when the
    /// current motion began.
    motion_started: Option<(std::time::Duration, f64)>,
}

impl RealtimePacer {
    /// How long to wait before performing `action`, given the node's simulated time and the
    /// wall-clock time now (both from the same origin on every call).
    pub fn wait_before(
        &mut self,
        action: &EdgeAction,
        sim_time_s: f64,
        wall_now: std::time::Duration,
    ) -> std::time::Duration {
        match action {
            EdgeAction::Execute { .. } | EdgeAction::MoveToNextSegment => {
                self.motion_started = Some((wall_now, sim_time_s));
                std::time::Duration::ZERO
            }
            EdgeAction::Capture { .. } => {
                let Some((wall_start, sim_start_s)) = self.motion_started.take() else {
                    return std::time::Duration::ZERO;
                };
                let spent_s = (sim_time_s - sim_start_s).max(0.0);
                let due = wall_start + std::time::Duration::from_secs_f64(spent_s);
                due.saturating_sub(wall_now)
            }
            _ => std::time::Duration::ZERO,
        }
    }
}
