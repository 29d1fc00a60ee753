//! A trolley's publications held until the cloud they were planned on is durable.
//!
//! Views, fruits and map updates go out only once the cloud they follow is in the planner's
//! store, so that an arm never acts on a scan a killed planner would lose. The driver does not
//! wait for the disk itself: it queues the cloud's write, holds the trolley's publications
//! behind it here and goes on with other events (its status, snapshot answers, other trolleys'
//! clouds). A slow disk then delays the views of the trolleys whose clouds it holds, not the
//! planner: before, every cloud's write was awaited in the event loop, so one slow write held
//! every trolley, the status and the answers to peers' snapshot queries.
//!
//! Store writes are numbered in the order they are queued and the writer makes them durable in
//! that order, so "durable through n" is one number.

use std::collections::{HashMap, VecDeque};

/// Publications waiting for store writes, in the order they were made.
pub struct Held<T> {
    /// Per trolley, the number of its latest queued cloud write.
    last_cloud: HashMap<String, u64>,
    /// (the write it waits for, trolley, publication), oldest first.
    queue: VecDeque<(u64, String, T)>,
}

impl<T> Default for Held<T> {
    fn default() -> Self {
        Self {
            last_cloud: HashMap::new(),
            queue: VecDeque::new(),
        }
    }
}

impl<T> Held<T> {
    /// Trolley `tid`'s cloud went to the store as write `seq`: its later publications wait
    /// for it.
    pub fn cloud_queued(&mut self, tid: &str, seq: u64) {
        self.last_cloud.insert(tid.to_owned(), seq);
    }

    /// The number of `tid`'s latest queued cloud write, if any.
    pub fn last_cloud(&self, tid: &str) -> Option<u64> {
        self.last_cloud.get(tid).copied()
    }

    /// `item`, a publication of `tid`, back when it may go out now (its trolley's clouds are
    /// durable through `durable` and nothing of it is held before it); otherwise held.
    pub fn pass_or_hold(&mut self, tid: &str, item: T, durable: u64) -> Option<T> {
        let needs = self.last_cloud(tid).unwrap_or(0);
        let earlier_held = self.queue.iter().any(|(_, t, _)| t == tid);
        if needs <= durable && !earlier_held {
            return Some(item);
        }
        self.queue.push_back((needs, tid.to_owned(), item));
        None
    }

    /// The held publications whose writes are durable through `durable`, in the order they
    /// were made. A trolley's own publications keep their order: each waits for a write no
    /// earlier than the one before it did.
    pub fn release(&mut self, durable: u64) -> Vec<(String, T)> {
        let mut released = Vec::new();
        let mut kept = VecDeque::with_capacity(self.queue.len());
        for (needs, tid, item) in self.queue.drain(..) {
            if needs <= durable {
                released.push((tid, item));
            } else {
                kept.push_back((needs, tid, item));
            }
        }
        self.queue = kept;
        released
    }

    /// Forgets `tid`'s cloud writes (its publishers are released; hold nothing for it).
    pub fn forget(&mut self, tid: &str) {
        self.last_cloud.remove(tid);
    }

    /// Publications held.
    #[cfg(test)]
    pub fn len(&self) -> usize {
        self.queue.len()
    }

    /// Whether nothing is held.
    #[cfg(test)]
    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_publication_waits_for_its_own_trolleys_cloud_only() {
        let mut held = Held::default();
        held.cloud_queued("t1", 3);
        // t1's cloud (write 3) is not durable yet; t2 has no cloud waiting.
        assert_eq!(held.pass_or_hold("t1", "t1 views", 2), None);
        assert_eq!(held.pass_or_hold("t2", "t2 views", 2), Some("t2 views"));
        assert_eq!(held.release(2), vec![]);
        assert_eq!(held.release(3), vec![("t1".to_owned(), "t1 views")]);
        assert!(held.is_empty());
        // Once durable, later publications go straight out.
        assert_eq!(held.pass_or_hold("t1", "t1 fruits", 3), Some("t1 fruits"));
    }

    #[test]
    fn a_trolleys_publications_keep_their_order_behind_a_held_one() {
        let mut held = Held::default();
        held.cloud_queued("t1", 5);
        assert_eq!(held.pass_or_hold("t1", 1, 4), None);
        // Durable by now, but the earlier publication of t1 is still held: this one waits too.
        assert_eq!(held.pass_or_hold("t1", 2, 5), None);
        held.cloud_queued("t1", 7);
        assert_eq!(held.pass_or_hold("t1", 3, 5), None);
        held.cloud_queued("t2", 6);
        assert_eq!(held.pass_or_hold("t2", 10, 5), None);
        assert_eq!(held.len(), 4);
        let released: Vec<i32> = held.release(6).into_iter().map(|(_, i)| i).collect();
        assert_eq!(released, vec![1, 2, 10]);
        let released: Vec<i32> = held.release(7).into_iter().map(|(_, i)| i).collect();
        assert_eq!(released, vec![3]);
    }

    #[test]
    fn without_clouds_nothing_is_held() {
        let mut held = Held::default();
        assert_eq!(held.pass_or_hold("t1", "status", 0), Some("status"));
        held.cloud_queued("t1", 1);
        held.forget("t1");
        assert_eq!(held.last_cloud("t1"), None);
        assert_eq!(held.pass_or_hold("t1", "views", 0), Some("views"));
    }
}
