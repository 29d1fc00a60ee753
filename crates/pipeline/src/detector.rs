//! The detector's loop as a state machine ([`DetectorNode`]): events in, actions out, no I/O.
//!
//! Any number of detectors share the fleet by splitting the trolleys: from the liveliness tokens
//! of detectors and trolleys each detector keeps a [`Membership`] (the detectors are its
//! servers) and serves the trolleys it ranks first for ([`Membership::served_by`]); the driver
//! subscribes to the frames of exactly those (`Serve` / `Unserve`). Every frame is thus
//! processed once, by one detector. When a detector leaves, its trolleys move to the next ranked
//! one within the liveliness lease. The planners rank the same way and take a trolley's clouds
//! only from the detector ranked first for it. A detector never believes its own leave: its
//! token is its own, and a leave of it seen through a router fault is stale.
//!
//! Detection is the driver's work (it is heavy and runs off the event loop): a frame becomes a
//! `Detect` action, and its outcome comes back as `Detected`, which becomes the cloud to
//! publish under the detector's own id and the frame's seq, or a counted rejection.

use std::collections::BTreeSet;

use glasshouse_fleet::{Membership, MembershipEvent};
use glasshouse_proto::{DetectorStatus, Header, RgbdFrame, RoiCloud};

/// What reaches the detector.
#[derive(Clone, Debug)]
pub enum DetectorInput {
    /// A detector's or trolley's liveliness token appeared or went (detectors are the servers).
    Member(MembershipEvent),
    /// A frame of a served trolley.
    Frame {
        header: Header,
        frame: Box<RgbdFrame>,
    },
    /// The outcome of a `Detect`: the cloud (boxed: the other inputs are small) or why the
    /// frame could not be processed, and how long the detection took.
    Detected {
        header: Header,
        result: Result<Box<RoiCloud>, String>,
        detect_ms: f64,
    },
    /// Time to publish the status; `dropped_messages` are the driver's bus drops so far.
    StatusTick { dropped_messages: u64 },
}

/// What the driver does for the detector.
#[derive(Clone, Debug, PartialEq)]
pub enum DetectorAction {
    /// Take this trolley's frames from now on.
    Serve(String),
    /// Stop taking this trolley's frames (another detector ranks first for it now, or it left).
    Unserve(String),
    /// Run the detection on `frame` and feed the outcome back as `Detected` with this header.
    Detect {
        header: Header,
        frame: Box<RgbdFrame>,
    },
    PublishCloud {
        header: Header,
        cloud: RoiCloud,
    },
    PublishStatus {
        header: Header,
        status: DetectorStatus,
    },
    /// Something worth a log line.
    Report(DetectorReport),
}

/// What the detector reports for the log.
#[derive(Clone, Debug, PartialEq)]
pub enum DetectorReport {
    /// A frame was not processed (an invalid trolley id, or content the detection refused).
    FrameRejected {
        trolley_id: String,
        seq: u64,
        reason: String,
    },
}

/// The detector's counters, as its status and metrics show them.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DetectorCounts {
    pub frames_processed: u64,
    /// Frames that decoded but could not be processed (inconsistent content, a bad trolley id).
    pub frames_rejected: u64,
    pub trolleys_served: u64,
    /// Detection time summed over the processed frames, in milliseconds.
    pub detect_ms_total: f64,
}

/// The detector (see the module docs).
#[derive(Clone, Debug)]
pub struct DetectorNode {
    did: String,
    /// This process's boot epoch: every header it publishes carries it.
    epoch_ns: u64,
    membership: Membership,
    served: BTreeSet<String>,
    counts: DetectorCounts,
    status_seq: u64,
}

impl DetectorNode {
    /// Detector `did`, booted at `epoch_ns`; it counts itself live from the start.
    pub fn new(did: &str, epoch_ns: u64) -> Self {
        let mut membership = Membership::new();
        membership.server_joined(did);
        Self {
            did: did.to_owned(),
            epoch_ns,
            membership,
            served: BTreeSet::new(),
            counts: DetectorCounts::default(),
            status_seq: 0,
        }
    }

    pub fn counts(&self) -> DetectorCounts {
        self.counts
    }

    /// The trolleys whose frames this detector takes now.
    pub fn served(&self) -> &BTreeSet<String> {
        &self.served
    }

    /// Feeds one event; returns what to do.
    pub fn handle(&mut self, input: DetectorInput) -> Vec<DetectorAction> {
        match input {
            // Its own token is its own: a leave of it is stale news.
            DetectorInput::Member(MembershipEvent::ServerLeft(id)) if id == self.did => Vec::new(),
            DetectorInput::Member(event) => {
                self.membership.apply(event);
                self.update_served()
            }
            DetectorInput::Frame { header, frame } => self.on_frame(header, frame),
            DetectorInput::Detected {
                header,
                result,
                detect_ms,
            } => self.on_detected(header, result, detect_ms),
            DetectorInput::StatusTick { dropped_messages } => vec![self.status(dropped_messages)],
        }
    }

    /// `Unserve` for the trolleys no longer served, then `Serve` for the new ones, by id.
    fn update_served(&mut self) -> Vec<DetectorAction> {
        let now = self.membership.served_by(&self.did);
        let dropped = self
            .served
            .difference(&now)
            .cloned()
            .map(DetectorAction::Unserve);
        let added = now
            .difference(&self.served)
            .cloned()
            .map(DetectorAction::Serve);
        let actions = dropped.chain(added).collect();
        self.served = now;
        self.counts.trolleys_served = self.served.len() as u64;
        actions
    }

    fn on_frame(&mut self, header: Header, frame: Box<RgbdFrame>) -> Vec<DetectorAction> {
        if let Err(e) = glasshouse_proto::keys::validate_id(&header.trolley_id) {
            return vec![self.reject(&header, e.to_string())];
        }
        vec![DetectorAction::Detect { header, frame }]
    }

    fn on_detected(
        &mut self,
        header: Header,
        result: Result<Box<RoiCloud>, String>,
        detect_ms: f64,
    ) -> Vec<DetectorAction> {
        let cloud = match result {
            Ok(cloud) => *cloud,
            Err(reason) => return vec![self.reject(&header, reason)],
        };
        self.counts.frames_processed += 1;
        self.counts.detect_ms_total += detect_ms.max(0.0);
        let header = Header {
            seq: header.seq,
            epoch_ns: self.epoch_ns,
            stamp_ns: header.stamp_ns,
            trolley_id: header.trolley_id,
            source_id: self.did.clone(),
            frame_id: "world".into(),
        };
        vec![DetectorAction::PublishCloud { header, cloud }]
    }

    fn reject(&mut self, header: &Header, reason: String) -> DetectorAction {
        self.counts.frames_rejected += 1;
        DetectorAction::Report(DetectorReport::FrameRejected {
            trolley_id: header.trolley_id.clone(),
            seq: header.seq,
            reason,
        })
    }

    fn status(&mut self, dropped_messages: u64) -> DetectorAction {
        self.status_seq += 1;
        let processed = self.counts.frames_processed;
        let mean_ms = match processed {
            0 => 0.0,
            n => self.counts.detect_ms_total / n as f64,
        };
        let status = DetectorStatus {
            detector_id: self.did.clone(),
            frames_processed: processed,
            dropped_messages: dropped_messages + self.counts.frames_rejected,
            mean_detect_time_ms: mean_ms as f32,
        };
        let header = Header {
            seq: self.status_seq,
            epoch_ns: self.epoch_ns,
            source_id: self.did.clone(),
            frame_id: "world".into(),
            ..Header::default()
        };
        DetectorAction::PublishStatus { header, status }
    }
}
