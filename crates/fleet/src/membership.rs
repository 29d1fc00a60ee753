//! Live servers and trolleys, from liveliness events, and which server comes first and second for
//! each trolley.
//!
//! One type for every service that ranks. The servers are the planners in a planner's own
//! membership and in the edge's (which planner may move its arm); they are the detectors in a
//! detector's (which trolleys' frames it takes) and in a planner's check of which detector may
//! send a trolley's clouds. Every member keeps one [`Membership`] fed from the same liveliness tokens
//! (`gh/alive/planner/{pid}`, `gh/alive/detector/{did}`, `gh/alive/trolley/{tid}`), so all of
//! them agree on every [`Assignment`] without talking to each other. [`Membership::apply`]
//! returns what an event changed, for the service to log, publish, and act on (start or stop
//! following a trolley, load a snapshot when it becomes a replica, subscribe to its frames).

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::rendezvous::{rank_iter, top_two};

/// Who serves a trolley: among planners the owner and the hot standby keeping a replica map;
/// among detectors the one taking its frames (the replica is unused).
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Assignment {
    /// The highest-ranked live server: the planner that plans and publishes views for the
    /// trolley, the detector that takes its frames.
    pub owner: String,
    /// The second-ranked live server, if there is one: a planner consumes the same ROI clouds and
    /// keeps a replica map, so it can take over without losing the map.
    pub replica: Option<String>,
}

impl Assignment {
    /// The role `server_id` has in this assignment, if any.
    pub fn role_of(&self, server_id: &str) -> Option<Role> {
        if self.owner == server_id {
            Some(Role::Owner)
        } else if self.replica.as_deref() == Some(server_id) {
            Some(Role::Replica)
        } else {
            None
        }
    }
}

/// A server's role for one trolley.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub enum Role {
    Owner,
    Replica,
}

/// A liveliness event: a token appeared or disappeared.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum MembershipEvent {
    ServerJoined(String),
    ServerLeft(String),
    TrolleyJoined(String),
    TrolleyLeft(String),
}

/// A trolley whose owner or replica changed with one event.
///
/// `before` is `None` when the trolley was not live or no server was; `after` likewise.
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

/// The live servers (planners or detectors) and trolleys of the fleet.
///
/// Events are idempotent: a join of a member already live, or a leave of one not live, changes
/// nothing and returns no change.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Membership {
    servers: BTreeSet<String>,
    trolleys: BTreeSet<String>,
}

impl Membership {
    /// No servers, no trolleys.
    pub fn new() -> Self {
        Self::default()
    }

    /// A server's liveliness token appeared. Same as [`Membership::apply`].
    pub fn server_joined(&mut self, id: impl Into<String>) -> Vec<OwnershipChange> {
        self.apply(MembershipEvent::ServerJoined(id.into()))
    }

    /// A server's liveliness token disappeared. Same as [`Membership::apply`].
    pub fn server_left(&mut self, id: impl Into<String>) -> Vec<OwnershipChange> {
        self.apply(MembershipEvent::ServerLeft(id.into()))
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
            MembershipEvent::ServerJoined(id) => {
                if self.servers.contains(&id) {
                    return Vec::new();
                }
                let before = self.all_assignments();
                self.servers.insert(id);
                self.diff(before)
            }
            MembershipEvent::ServerLeft(id) => {
                if !self.servers.contains(&id) {
                    return Vec::new();
                }
                let before = self.all_assignments();
                self.servers.remove(&id);
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

    /// The owner and replica of a live trolley; `None` if the trolley is not live or no server is.
    pub fn assignment(&self, trolley_id: &str) -> Option<Assignment> {
        if self.trolleys.contains(trolley_id) {
            self.assign(trolley_id)
        } else {
            None
        }
    }

    /// The live servers ranked for `trolley_id` (live or not), best first.
    pub fn rank(&self, trolley_id: &str) -> Vec<&str> {
        rank_iter(trolley_id, self.servers.iter().map(String::as_str))
    }

    /// The live server ranked first for `trolley_id`, whether the trolley is live or not (an
    /// edge knows its own trolley without its token; a planner checks a cloud's sender).
    pub fn first_ranked(&self, trolley_id: &str) -> Option<&str> {
        top_two(trolley_id, self.servers.iter().map(String::as_str)).0
    }

    /// The live trolleys `server_id` ranks first for (a detector: the trolleys it serves).
    pub fn served_by(&self, server_id: &str) -> BTreeSet<String> {
        let first = |t: &&String| self.first_ranked(t) == Some(server_id);
        self.trolleys.iter().filter(first).cloned().collect()
    }

    /// The live trolleys `server_id` owns or replicates, by trolley id.
    pub fn roles_of(&self, server_id: &str) -> BTreeMap<String, Role> {
        let mut roles = BTreeMap::new();
        for trolley in &self.trolleys {
            let (owner, replica) = top_two(trolley, self.servers.iter().map(String::as_str));
            if owner == Some(server_id) {
                roles.insert(trolley.clone(), Role::Owner);
            } else if replica == Some(server_id) {
                roles.insert(trolley.clone(), Role::Replica);
            }
        }
        roles
    }

    /// The live servers, by id.
    pub fn servers(&self) -> impl Iterator<Item = &str> {
        self.servers.iter().map(String::as_str)
    }

    /// The live trolleys, by id.
    pub fn trolleys(&self) -> impl Iterator<Item = &str> {
        self.trolleys.iter().map(String::as_str)
    }

    /// Whether `server_id` is live.
    pub fn is_server_live(&self, server_id: &str) -> bool {
        self.servers.contains(server_id)
    }

    /// Whether `trolley_id` is live.
    pub fn is_trolley_live(&self, trolley_id: &str) -> bool {
        self.trolleys.contains(trolley_id)
    }

    /// The assignment of `trolley_id` over the live servers, whether the trolley is live or not.
    fn assign(&self, trolley_id: &str) -> Option<Assignment> {
        let (owner, replica) = top_two(trolley_id, self.servers.iter().map(String::as_str));
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
