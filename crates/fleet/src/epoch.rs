//! Ownership epochs: the fencing tokens of trolley ownership.
//!
//! Liveliness is eventually consistent: during a partition, a lease expiry or a paused process,
//! two planners can both believe they own a trolley. Every ownership term therefore has an
//! *epoch*, a `u64` that only grows per trolley, and everything an owner publishes for the
//! trolley carries it. Receivers keep the newest epoch they have seen per trolley
//! ([`EpochFence`]) and drop what comes under an older one ([`EpochVerdict::Stale`]); an owner
//! that sees a newer epoch than its own term knows it was replaced meanwhile.
//!
//! A planner beginning a term picks [`next_epoch`]: its clock reading, or one more than the
//! newest epoch it has seen for the trolley if that is later. No coordinator is involved: the
//! newest epoch travels with the owner's messages and snapshots, and the trolley's edge echoes
//! the newest one it took views under, so a new owner starts above every term it could have
//! heard of. The clock part makes the epochs of two planners that begin terms independently (a
//! partition) differ in practice; the max makes them grow even with clocks that disagree. `0`
//! means "no epoch" (a sender without fencing): it is older than every term.

use std::collections::BTreeMap;

/// The epoch of a message from a sender without fencing; older than every term.
pub const NO_EPOCH: u64 = 0;

/// The epoch of a new ownership term: `now_ns` (the planner's wall clock, Unix ns), or one more
/// than `newest_seen` when that is not earlier. Always greater than `newest_seen` (saturating at
/// `u64::MAX`).
pub fn next_epoch(newest_seen: u64, now_ns: u64) -> u64 {
    now_ns.max(newest_seen.saturating_add(1))
}

/// What a message's epoch is against the newest seen for its trolley.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EpochVerdict {
    /// Older than the newest seen: the message comes from a replaced owner; drop and count it.
    Stale { newest: u64 },
    /// The newest seen.
    Current,
    /// Newer than anything seen before (`previous`): a new term began.
    Newer { previous: u64 },
}

impl EpochVerdict {
    /// `epoch` against `newest`, the newest epoch seen so far.
    pub fn of(epoch: u64, newest: u64) -> Self {
        match epoch.cmp(&newest) {
            std::cmp::Ordering::Less => EpochVerdict::Stale { newest },
            std::cmp::Ordering::Equal => EpochVerdict::Current,
            std::cmp::Ordering::Greater => EpochVerdict::Newer { previous: newest },
        }
    }

    pub fn is_stale(self) -> bool {
        matches!(self, EpochVerdict::Stale { .. })
    }

    pub fn is_newer(self) -> bool {
        matches!(self, EpochVerdict::Newer { .. })
    }
}

/// The newest ownership epoch seen per trolley.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct EpochFence {
    newest: BTreeMap<String, u64>,
}

impl EpochFence {
    pub fn new() -> Self {
        Self::default()
    }

    /// The newest epoch seen for `trolley` ([`NO_EPOCH`] when none).
    pub fn newest(&self, trolley: &str) -> u64 {
        self.newest.get(trolley).copied().unwrap_or(NO_EPOCH)
    }

    /// Judges `epoch` for `trolley` and, unless it is stale, makes it the newest.
    pub fn observe(&mut self, trolley: &str, epoch: u64) -> EpochVerdict {
        let verdict = EpochVerdict::of(epoch, self.newest(trolley));
        if let EpochVerdict::Newer { .. } = verdict {
            self.newest.insert(trolley.to_owned(), epoch);
        }
        verdict
    }

    /// Judges `epoch` for `trolley` without recording it.
    pub fn check(&self, trolley: &str, epoch: u64) -> EpochVerdict {
        EpochVerdict::of(epoch, self.newest(trolley))
    }

    /// Begins a term for `trolley` at `now_ns`: its epoch ([`next_epoch`] over the newest
    /// seen), recorded as the newest.
    pub fn begin_term(&mut self, trolley: &str, now_ns: u64) -> u64 {
        let epoch = next_epoch(self.newest(trolley), now_ns);
        self.newest.insert(trolley.to_owned(), epoch);
        epoch
    }
}
