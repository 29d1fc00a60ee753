//! Live planners and trolleys, from liveliness events, and who owns and replicates each trolley.
//!
//! Every planner of the cluster keeps one [`Membership`] fed from the same liveliness tokens
//! (`gh/alive/planner/{pid}`, `gh/alive/trolley/{tid}`), so all of them agree on every
//! [`Assignment`] without talking to each other. [`Membership::apply`] returns what an event
//! changed, for the service to log, publish, and act on (start or stop following a trolley, load a
//! snapshot when it becomes a replica).

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::rendezvous::{rank_iter, top_two};

/// Who plans for a trolley: the owner, and the hot standby keeping a replica map.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Assignment {
    /// The highest-ranked live planner: it plans and publishes views for the trolley.
    pub owner: String,
    /// The second-ranked live planner, if there is one: it consumes the same ROI clouds and keeps a
    /// replica map, so it can take over without losing the map.
    pub replica: Option<String>,
}

impl Assignment {
    /// The role `planner_id` has in this assignment, if any.
    pub fn role_of(&self, planner_id: &str) -> Option<Role> {
        if self.owner == planner_id {
            Some(Role::Owner)
        } else if self.replica.as_deref() == Some(planner_id) {
            Some(Role::Replica)
        } else {
            None
        }
    }
}

/// A planner's role for one trolley.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub enum Role {
    Owner,
    Replica,
}

/// A liveliness event: a token appeared or disappeared.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum MembershipEvent {
    PlannerJoined(String),
    PlannerLeft(String),
    TrolleyJoined(String),
    TrolleyLeft(String),
}

/// A trolley whose owner or replica changed with one event.
///
/// `before` is `None` when the trolley was not live or no planner was; `after` likewise.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct OwnershipChange {
    pub trolley: String,
    pub before: Option<Assignment>,
    pub after: Option<Assignment>,
}

impl OwnershipChange {
    /// Whether the owner changed (not only the replica).
    pub fn owner_changed(&self) -> bool {
        self.before.as_ref().map(|a| &a.owner) != self.after.as_ref().map(|a| &a.owner)
    }
}

/// The live planners and trolleys of the fleet.
///
/// Events are idempotent: a join of a member already live, or a leave of one not live, changes
/// nothing and returns no change.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Membership {
    planners: BTreeSet<String>,
    trolleys: BTreeSet<String>,
}

impl Membership {
    /// No planners, no trolleys.
    pub fn new() -> Self {
        Self::default()
    }

    /// A planner's liveliness token appeared. Same as [`Membership::apply`].
    pub fn planner_joined(&mut self, id: impl Into<String>) -> Vec<OwnershipChange> {
        self.apply(MembershipEvent::PlannerJoined(id.into()))
    }

    /// A planner's liveliness token disappeared. Same as [`Membership::apply`].
    pub fn planner_left(&mut self, id: impl Into<String>) -> Vec<OwnershipChange> {
        self.apply(MembershipEvent::PlannerLeft(id.into()))
    }

    /// A trolley's liveliness token appeared. Same as [`Membership::apply`].
    pub fn trolley_joined(&mut self, id: impl Into<String>) -> Vec<OwnershipChange> {
        self.apply(MembershipEvent::TrolleyJoined(id.into()))
    }

    /// A trolley's liveliness token disappeared. Same as [`Membership::apply`].
    pub fn trolley_left(&mut self, id: impl Into<String>) -> Vec<OwnershipChange> {
        self.apply(MembershipEvent::TrolleyLeft(id.into()))
    }

    /// Applies one event and returns, sorted by trolley id, every trolley whose owner or replica
    /// changed (including trolleys that gained or lost an assignment altogether).
    pub fn apply(&mut self, event: MembershipEvent) -> Vec<OwnershipChange> {
        match event {
            MembershipEvent::PlannerJoined(id) => {
                if self.planners.contains(&id) {
                    return Vec::new();
                }
                let before = self.all_assignments();
                self.planners.insert(id);
                self.diff(before)
            }
            MembershipEvent::PlannerLeft(id) => {
                if !self.planners.contains(&id) {
                    return Vec::new();
                }
                let before = self.all_assignments();
                self.planners.remove(&id);
                self.diff(before)
            }
            MembershipEvent::TrolleyJoined(id) => {
                if self.trolleys.contains(&id) {
                    return Vec::new();
                }
                let after = self.assign(&id);
                self.trolleys.insert(id.clone());
                match after {
                    Some(after) => vec![OwnershipChange {
                        trolley: id,
                        before: None,
                        after: Some(after),
                    }],
                    None => Vec::new(),
                }
            }
            MembershipEvent::TrolleyLeft(id) => {
                if !self.trolleys.remove(&id) {
                    return Vec::new();
                }
                match self.assign(&id) {
                    Some(before) => vec![OwnershipChange {
                        trolley: id,
                        before: Some(before),
                        after: None,
                    }],
                    None => Vec::new(),
                }
            }
        }
    }

    /// The owner and replica of a live trolley; `None` if the trolley is not live or no planner is.
    pub fn assignment(&self, trolley_id: &str) -> Option<Assignment> {
        if self.trolleys.contains(trolley_id) {
            self.assign(trolley_id)
        } else {
            None
        }
    }

    /// The live planners ranked for `trolley_id` (live or not), best first.
    pub fn rank(&self, trolley_id: &str) -> Vec<&str> {
        rank_iter(trolley_id, self.planners.iter().map(String::as_str))
    }

    /// The live trolleys `planner_id` owns or replicates, by trolley id.
    pub fn roles_of(&self, planner_id: &str) -> BTreeMap<String, Role> {
        let mut roles = BTreeMap::new();
        for trolley in &self.trolleys {
            let (owner, replica) = top_two(trolley, self.planners.iter().map(String::as_str));
            if owner == Some(planner_id) {
                roles.insert(trolley.clone(), Role::Owner);
            } else if replica == Some(planner_id) {
                roles.insert(trolley.clone(), Role::Replica);
            }
        }
        roles
    }

    /// The live planners, by id.
    pub fn planners(&self) -> impl Iterator<Item = &str> {
        self.planners.iter().map(String::as_str)
    }

    /// The live trolleys, by id.
    pub fn trolleys(&self) -> impl Iterator<Item = &str> {
        self.trolleys.iter().map(String::as_str)
    }

    /// Whether `planner_id` is live.
    pub fn is_planner_live(&self, planner_id: &str) -> bool {
        self.planners.contains(planner_id)
    }

    /// Whether `trolley_id` is live.
    pub fn is_trolley_live(&self, trolley_id: &str) -> bool {
        self.trolleys.contains(trolley_id)
    }

    /// The assignment of `trolley_id` over the live planners, whether the trolley is live or not.
    fn assign(&self, trolley_id: &str) -> Option<Assignment> {
        let (owner, replica) = top_two(trolley_id, self.planners.iter().map(String::as_str));
        owner.map(|owner| Assignment {
            owner: owner.to_owned(),
            replica: replica.map(str::to_owned),
        })
    }

    /// The assignment of every live trolley that has one.
    fn all_assignments(&self) -> BTreeMap<String, Assignment> {
        self.trolleys
            .iter()
            .filter_map(|t| self.assign(t).map(|a| (t.clone(), a)))
            .collect()
    }

    /// The changes from `before` to the current assignments, for the same live trolleys.
    fn diff(&self, mut before: BTreeMap<String, Assignment>) -> Vec<OwnershipChange> {
        let mut changes = Vec::new();
        for trolley in &self.trolleys {
            let was = before.remove(trolley);
            let now = self.assign(trolley);
            if was != now {
                changes.push(OwnershipChange {
                    trolley: trolley.clone(),
                    before: was,
                    after: now,
                });
            }
        }
        // Iterating the BTreeSet already yields trolley order.
        changes
    }
}
