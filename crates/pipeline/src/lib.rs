//! The steps of the glasshouse loop, written once: capture, detection, per-trolley planning, view
//! execution and the edge's state machine.
//!
//! ```text
//!  TrolleySource::capture ──RgbdFrame──> detect_frame ──RoiCloud──> TrolleyPlanner
//!        ^                                                   integrate, fruits, plan
//!        └── TrolleySource::execute <──RankedViews── EdgeNode <───────────┘
//! ```
//!
//! The services call these steps across the bus (the edge drives [`EdgeNode`] and a
//! [`TrolleySource`], the detector drives a [`DetectorNode`] and calls [`detect_frame`], the planner keeps a [`TrolleyPlanner`]
//! per trolley); the experiments (`glasshouse-eval`) call the very same steps in one thread with
//! a simulated clock. The plan seed ([`plan_seed`]), the depth packing and the planner's defaults
//! ([`PlanningSettings::default`]) exist only here. No I/O: time and seeds are passed in. The
//! simulator is not here: the simulated trolley (`glasshouse-simtrolley`) is one
//! [`TrolleySource`] among others, and nothing a real trolley runs links it.

mod colour;
mod detection;
mod detector;
mod edge;
pub mod fits;
mod order;
pub mod parallel;
mod planning;
mod published;
mod reach;
mod season;
mod source;

pub use detection::{detect_frame, detect_frame_with};
pub use detector::{DetectorAction, DetectorCounts, DetectorInput, DetectorNode, DetectorReport};
pub use edge::{EdgeAction, EdgeEvent, EdgeInput, EdgeNode, EdgeSettings, RealtimePacer};
pub use glasshouse_register::{Alignment, AlignmentCounts};
pub use order::{
    FrameOrder, FrameVerdict, Refusal, MAX_EPOCH_LEAD_NS, MAX_SEQ_STEP, RESYNC_FRAMES,
};
pub use planning::{
    plan_seed, ranked_views, roi_evidence_logodds, ClusterOutcome, PlanningError, PlanningSettings,
    RoiEvidence, RoiTargets, StoredCopy, TrolleyPlanner, DEFAULT_CLUTTER_SETTLES_AFTER_VIEWS,
    DEFAULT_COST_WEIGHT_PER_S, DEFAULT_EXPLORE_AFTER_FRUITLESS_CLOUDS,
    DEFAULT_FRUIT_SETTLES_AFTER_VIEWS, DEFAULT_ROI_TRIES, ROI_EVIDENCE_LOGODDS,
};
pub use reach::ReachFilter;
pub use source::{Executed, TrolleySource, DEPTH_SCALE_M};

#[cfg(test)]
mod detector_tests;
#[cfg(test)]
mod tests;
