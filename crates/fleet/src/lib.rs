//! Fleet coordination for the Glasshouse planner cluster, free of I/O (no Zenoh, no async):
//! the services feed it liveliness events and per-trolley fruit lists and publish what it returns.
//!
//! - [`rendezvous`]: which planner owns a trolley, and which one keeps its hot replica.
//! - [`membership`]: live planners and trolleys from liveliness events, and the ownership changes
//!   each event causes.
//! - [`merge`]: the fleet fruit map, de-duplicating fruits seen by several trolleys.
//! - [`epoch`]: ownership epochs, the fencing tokens that let receivers drop what a replaced
//!   owner still sends.
//!
//! # Why rendezvous hashing
//!
//! Every trolley ranks the live planners by a hash weight `h(trolley, planner)` (highest random
//! weight); the first is the owner, the second the hot standby holding a replica map. Every member
//! computes the same ranking from the same membership, so no coordinator is needed. And membership
//! changes move as little as possible:
//!
//! - When a planner leaves, only the trolleys it owned change owner; all other trolleys keep
//!   theirs. The removal does not reorder the remaining planners, so a trolley's new owner is its
//!   previous second-ranked planner, which is exactly the planner already holding the hot replica
//!   map: fail-over loses no map. Only the replica role moves on, to the third-ranked planner,
//!   which loads a snapshot first.
//! - When a planner joins, a trolley changes owner only if the new planner ranks first for it,
//!   so it takes about `1/n` of the trolleys, from every planner evenly.
//!
//! Modulo hashing would reshuffle almost every trolley on each change, and consistent hashing on
//! a ring needs virtual nodes to spread load; with a handful of planners ranking all of them per
//! trolley is cheap and spreads evenly.

pub mod epoch;
pub mod membership;
pub mod merge;
pub mod rendezvous;

pub use epoch::{next_epoch, EpochFence, EpochVerdict, NO_EPOCH};
pub use membership::{Assignment, Membership, MembershipEvent, OwnershipChange, Role};
pub use merge::{merge_fruits, FleetFruit, MergeResult, TrolleyFruit, MERGE_DISTANCE_M};
pub use rendezvous::{first_ranked, rank_planners, top_two, weight};

#[cfg(test)]
mod tests;
