//! Highest-random-weight (rendezvous) hashing of trolleys onto planners.
//!
//! The weight of a (trolley, planner) pair is [`weight`]: 64-bit FNV-1a over the bytes
//! `planner_id, 0x00, trolley_id`, then the splitmix64 finaliser (`mix64`) so that ids differing
//! in their last byte still get unrelated weights. Both are fixed here and depend neither on
//! `std`'s `RandomState` nor on the Rust version, so every planner of the cluster, whatever it was
//! built with, ranks the same way. Changing this function reassigns trolleys across the fleet:
//! all members must then be upgraded together.
//!
//! A trolley ranks the planners by weight, highest first; equal weights are ordered by planner id
//! (ascending), so the order is total and deterministic.

use std::cmp::Ordering;

/// FNV-1a 64-bit offset basis.
const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
/// FNV-1a 64-bit prime.
const FNV_PRIME: u64 = 0x0000_0100_0000_01b3;

/// Continues a 64-bit FNV-1a hash `state` over `bytes`.
pub(crate) fn fnv1a64(mut state: u64, bytes: &[u8]) -> u64 {
    for &b in bytes {
        state ^= u64::from(b);
        state = state.wrapping_mul(FNV_PRIME);
    }
    state
}

/// The splitmix64 finaliser (Steele, Lea, Flood 2014; constants of `java.util.SplittableRandom`).
pub(crate) fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The rendezvous weight of `planner_id` for `trolley_id`: `mix64(fnv1a64(planner ‖ 0x00 ‖ trolley))`.
///
/// Stable across platforms, processes and compiler versions (see the module documentation).
pub fn weight(trolley_id: &str, planner_id: &str) -> u64 {
    let h = fnv1a64(FNV_OFFSET, planner_id.as_bytes());
    let h = fnv1a64(h, &[0]);
    let h = fnv1a64(h, trolley_id.as_bytes());
    mix64(h)
}

/// Ranking order of `(weight, planner id)` pairs: `Less` means `a` ranks before `b`.
fn rank_cmp(a: (u64, &str), b: (u64, &str)) -> Ordering {
    b.0.cmp(&a.0).then_with(|| a.1.cmp(b.1))
}

/// The planners ranked for `trolley_id`, best (the owner) first, then the replica, and so on.
///
/// Ties in weight are broken by planner id, so the result does not depend on the order of
/// `planners`. A planner id listed several times is ranked once.
pub fn rank_planners<'a>(trolley_id: &str, planners: &'a [String]) -> Vec<&'a str> {
    rank_iter(trolley_id, planners.iter().map(String::as_str))
}

/// [`rank_planners`] over any iterator of planner ids.
pub(crate) fn rank_iter<'a>(
    trolley_id: &str,
    planners: impl IntoIterator<Item = &'a str>,
) -> Vec<&'a str> {
    let mut ranked: Vec<(u64, &'a str)> = planners
        .into_iter()
        .map(|p| (weight(trolley_id, p), p))
        .collect();
    ranked.sort_unstable_by(|a, b| rank_cmp(*a, *b));
    // Equal ids have equal weights, so duplicates are adjacent after sorting.
    ranked.dedup_by(|a, b| a.1 == b.1);
    ranked.into_iter().map(|(_, p)| p).collect()
}

/// The member ranked first for `trolley_id`: among planners its owner, among detectors the one
/// that serves it (takes its frames and alone may send its clouds). `None` without members.
pub fn first_ranked<'a>(
    trolley_id: &str,
    members: impl IntoIterator<Item = &'a str>,
) -> Option<&'a str> {
    top_two(trolley_id, members).0
}

/// The first two of [`rank_planners`] (owner, replica) in one pass without allocating.
///
/// `(None, None)` without planners; the replica is `None` with a single distinct planner.
pub fn top_two<'a>(
    trolley_id: &str,
    planners: impl IntoIterator<Item = &'a str>,
) -> (Option<&'a str>, Option<&'a str>) {
    let mut first: Option<(u64, &'a str)> = None;
    let mut second: Option<(u64, &'a str)> = None;
    for p in planners {
        let cand = (weight(trolley_id, p), p);
        match first {
            Some(f) if f.1 == p => {}
            Some(f) if rank_cmp(cand, f) != Ordering::Less => match second {
                Some(s) if s.1 == p || rank_cmp(cand, s) != Ordering::Less => {}
                _ => second = Some(cand),
            },
            _ => {
                second = first;
                first = Some(cand);
            }
        }
    }
    (first.map(|f| f.1), second.map(|s| s.1))
}
