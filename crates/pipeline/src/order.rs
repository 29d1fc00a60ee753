//! The order of a trolley's frames ([`FrameOrder`]): which cloud a map takes, and why no single
//! message can stop it taking more.
//!
//! Frames are identified by [`FrameId`] (the trolley process's boot epoch, then its frame seq)
//! and a map integrates a frame only when it is newer than the last one it integrated. A
//! restarted edge starts a new, later epoch, so its frames (seq from 1 again) come after all the
//! old ones. Two rules keep one bad message from freezing the map:
//!
//! - Refused (counted, never integrated nor planned on): an epoch more than
//!   [`MAX_EPOCH_LEAD_NS`] ahead of the receiver's clock (no process starts in the future), and a
//!   seq more than [`MAX_SEQ_STEP`] ahead of the last one within its epoch (a trolley captures
//!   one frame per executed view).
//! - Resync: a plausible frame that gets past them (e.g. a later epoch with seq 1) becomes the
//!   mark, and the real stream then looks old. When [`RESYNC_FRAMES`] clouds in a row come that
//!   the mark would not take, each newer than the one before (a live stream, not a straggler), the
//!   stream wins: the last of them is integrated and becomes the mark. The same rule heals a map
//!   whose trolley jumped far ahead while this receiver was cut off.

use glasshouse_proto::FrameId;

/// An epoch further than this ahead of the receiver's clock is refused (clock skew allowance).
pub const MAX_EPOCH_LEAD_NS: u64 = 60_000_000_000;
/// A seq further than this ahead of the last integrated one of the same epoch is refused.
pub const MAX_SEQ_STEP: u64 = 1000;
/// Clouds in a row, each newer than the one before, that override the mark when it refuses them.
pub const RESYNC_FRAMES: u32 = 3;

/// Why a frame was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// The epoch lies this far ahead of the receiver's clock.
    FutureEpoch { lead_ns: u64 },
    /// The seq jumps this far ahead of the last integrated frame of the same epoch.
    SeqJump { step: u64 },
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::FutureEpoch { lead_ns } => {
                write!(
                    f,
                    "epoch {:.1} s ahead of this clock",
                    *lead_ns as f64 / 1e9
                )
            }
            Refusal::SeqJump { step } => write!(f, "seq jumps {step} frames ahead"),
        }
    }
}

/// What to do with a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameVerdict {
    /// Newer than the mark: integrate it.
    Fresh,
    /// Not newer than the mark, but the last of a stream that overrides it: integrate it.
    Resync { mark: FrameId },
    /// The mark itself (a re-announced frame): plan again, do not integrate again.
    Repeat,
    /// Older than the mark: not integrated (still planned on: the edge may wait on it).
    Stale,
    /// Implausible: neither integrated nor planned on.
    Refused(Refusal),
    /// Taken, but its registration to the map failed the checks
    /// (`TrolleyPlanner::last_alignment` says why): not integrated, still planned on.
    Misaligned,
}

impl FrameVerdict {
    /// Whether the frame goes into the map.
    pub fn integrates(&self) -> bool {
        matches!(self, FrameVerdict::Fresh | FrameVerdict::Resync { .. })
    }
}

/// A map's frame mark and the stream seen behind it (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameOrder {
    last: Option<FrameId>,
    /// The newest frame the mark turned away, and how many in a row, each newer than the one
    /// before, it turned away.
    behind: Option<(FrameId, u32)>,
    /// The mark of the snapshot the map was loaded from: frames of its epoch up to it are held.
    held: Option<FrameId>,
}

impl FrameOrder {
    /// The order of a map loaded from a snapshot whose last integrated frame is `last`: it
    /// holds every frame of `last`'s epoch up to `last`.
    pub fn starting_at(last: Option<FrameId>) -> Self {
        Self {
            last,
            behind: None,
            held: last,
        }
    }

    /// Whether the map holds `frame` already, by the snapshot it was loaded from.
    fn holds(&self, frame: FrameId) -> bool {
        self.held
            .is_some_and(|held| frame.epoch_ns == held.epoch_ns && frame.seq <= held.seq)
    }

    /// The last integrated frame.
    pub fn last(&self) -> Option<FrameId> {
        self.last
    }

    /// Judges `frame`, received when the receiver's wall clock read `now_ns`. Call
    /// [`FrameOrder::integrated`] once a frame judged to integrate is in the map.
    pub fn judge(&mut self, frame: FrameId, now_ns: u64) -> FrameVerdict {
        let lead_ns = frame.epoch_ns.saturating_sub(now_ns);
        if lead_ns > MAX_EPOCH_LEAD_NS {
            return FrameVerdict::Refused(Refusal::FutureEpoch { lead_ns });
        }
        let Some(last) = self.last else {
            return FrameVerdict::Fresh;
        };
        let jump = (frame.epoch_ns == last.epoch_ns)
            .then(|| frame.seq.saturating_sub(last.seq))
            .filter(|&step| step > MAX_SEQ_STEP);
        let verdict = match jump {
            Some(step) => FrameVerdict::Refused(Refusal::SeqJump { step }),
            None if frame > last => {
                self.behind = None;
                return FrameVerdict::Fresh;
            }
            None if frame == last => {
                self.behind = None;
                return FrameVerdict::Repeat;
            }
            None if self.holds(frame) => return FrameVerdict::Stale,
            None => FrameVerdict::Stale,
        };
        let run = match self.behind {
            Some((newest, run)) if frame > newest => run + 1,
            Some((newest, run)) if frame == newest => run,
            _ => 1,
        };
        self.behind = Some((frame, run));
        if run >= RESYNC_FRAMES {
            self.behind = None;
            return FrameVerdict::Resync { mark: last };
        }
        verdict
    }

    /// `frame` went into the map: it is the mark now.
    pub fn integrated(&mut self, frame: FrameId) {
        self.last = Some(frame);
        self.behind = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const NOW: u64 = 1_800_000_000_000_000_000;
    const EPOCH: u64 = NOW - 3_600_000_000_000;

    fn feed(order: &mut FrameOrder, frame: FrameId) -> FrameVerdict {
        let verdict = order.judge(frame, NOW);
        if verdict.integrates() {
            order.integrated(frame);
        }
        verdict
    }

    fn at(seq: u64) -> FrameId {
        FrameId::new(EPOCH, seq)
    }

    #[test]
    fn frames_integrate_once_in_order() {
        let mut order = FrameOrder::default();
        assert_eq!(feed(&mut order, at(1)), FrameVerdict::Fresh);
        assert_eq!(feed(&mut order, at(2)), FrameVerdict::Fresh);
        assert_eq!(feed(&mut order, at(2)), FrameVerdict::Repeat);
        assert_eq!(feed(&mut order, at(1)), FrameVerdict::Stale);
        assert_eq!(order.last(), Some(at(2)));
    }

    #[test]
    fn a_restarted_trolley_comes_after_everything_it_sent_before() {
        let mut order = FrameOrder::starting_at(Some(at(57)));
        let restarted = FrameId::new(EPOCH + 1, 1);
        assert_eq!(feed(&mut order, restarted), FrameVerdict::Fresh);
        // A straggler of the old process changes nothing.
        assert_eq!(feed(&mut order, at(58)), FrameVerdict::Stale);
        assert_eq!(
            feed(&mut order, FrameId::new(EPOCH + 1, 2)),
            FrameVerdict::Fresh
        );
    }

    #[test]
    fn implausible_frames_are_refused_and_the_stream_goes_on() {
        let mut order = FrameOrder::starting_at(Some(at(10)));
        let far = feed(&mut order, at(1_000_000_000_000));
        assert_eq!(
            far,
            FrameVerdict::Refused(Refusal::SeqJump {
                step: 1_000_000_000_000 - 10
            })
        );
        let future = feed(&mut order, FrameId::new(NOW + 2 * MAX_EPOCH_LEAD_NS, 1));
        assert!(matches!(
            future,
            FrameVerdict::Refused(Refusal::FutureEpoch { .. })
        ));
        assert_eq!(feed(&mut order, at(11)), FrameVerdict::Fresh);
        // Within the limits is fine: a step of MAX_SEQ_STEP, an epoch just ahead of the clock.
        assert_eq!(feed(&mut order, at(11 + MAX_SEQ_STEP)), FrameVerdict::Fresh);
        let skewed = FrameId::new(NOW + MAX_EPOCH_LEAD_NS, 1);
        assert_eq!(feed(&mut order, skewed), FrameVerdict::Fresh);
    }

    #[test]
    fn a_stream_behind_a_forged_mark_takes_the_map_back() {
        let mut order = FrameOrder::starting_at(Some(at(10)));
        // A plausible forged frame: a later epoch.
        let forged = FrameId::new(NOW, 1);
        assert_eq!(feed(&mut order, forged), FrameVerdict::Fresh);
        assert_eq!(feed(&mut order, at(11)), FrameVerdict::Stale);
        // A re-announce neither breaks nor advances the run.
        assert_eq!(feed(&mut order, at(11)), FrameVerdict::Stale);
        assert_eq!(feed(&mut order, at(12)), FrameVerdict::Stale);
        assert_eq!(
            feed(&mut order, at(13)),
            FrameVerdict::Resync { mark: forged }
        );
        assert_eq!(order.last(), Some(at(13)));
        assert_eq!(feed(&mut order, at(14)), FrameVerdict::Fresh);
    }

    #[test]
    fn frames_a_snapshot_holds_replayed_in_order_do_not_resync() {
        let mut order = FrameOrder::starting_at(Some(at(7)));
        for seq in 3..7 {
            assert_eq!(feed(&mut order, at(seq)), FrameVerdict::Stale);
        }
        assert_eq!(feed(&mut order, at(7)), FrameVerdict::Repeat);
        assert_eq!(feed(&mut order, at(8)), FrameVerdict::Fresh);
        // Behind a mark taken from a cloud (it may be forged) the same run does resync.
        let mut order = FrameOrder::starting_at(Some(at(2)));
        let forged = FrameId::new(EPOCH, 9);
        assert_eq!(feed(&mut order, forged), FrameVerdict::Fresh);
        for seq in 3..5 {
            assert_eq!(feed(&mut order, at(seq)), FrameVerdict::Stale);
        }
        assert_eq!(
            feed(&mut order, at(5)),
            FrameVerdict::Resync { mark: forged }
        );
    }

    #[test]
    fn stragglers_out_of_order_do_not_resync() {
        let mut order = FrameOrder::starting_at(Some(at(50)));
        for seq in [40, 30, 45, 20] {
            assert_eq!(feed(&mut order, at(seq)), FrameVerdict::Stale);
        }
        assert_eq!(order.last(), Some(at(50)));
    }

    #[test]
    fn a_receiver_cut_off_for_long_follows_the_trolley_again() {
        let mut order = FrameOrder::starting_at(Some(at(10)));
        let far = 10 + 5 * MAX_SEQ_STEP;
        for seq in far..far + 2 {
            assert!(matches!(
                feed(&mut order, at(seq)),
                FrameVerdict::Refused(_)
            ));
        }
        assert!(matches!(
            feed(&mut order, at(far + 2)),
            FrameVerdict::Resync { .. }
        ));
        assert_eq!(feed(&mut order, at(far + 3)), FrameVerdict::Fresh);
    }
}
