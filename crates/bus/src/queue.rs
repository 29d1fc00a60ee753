//! A small bounded queue between Zenoh callbacks, producers and async consumers.

use std::collections::VecDeque;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Condvar, Mutex};

use crate::DropCounters;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Overflow {
    /// Drop the oldest entry and count it.
    DropOldest,
    /// Make the producer wait for space.
    Wait,
}

struct State<T> {
    items: VecDeque<T>,
    closed: bool,
}

pub(crate) struct SampleQueue<T> {
    state: Mutex<State<T>>,
    space: Condvar,
    space_async: tokio::sync::Notify,
    ready: tokio::sync::Notify,
    capacity: usize,
    overflow: Overflow,
    counters: Arc<DropCounters>,
}

impl<T> SampleQueue<T> {
    pub(crate) fn new(capacity: usize, overflow: Overflow, counters: Arc<DropCounters>) -> Self {
        Self {
            state: Mutex::new(State {
                items: VecDeque::with_capacity(capacity),
                closed: false,
            }),
            space: Condvar::new(),
            space_async: tokio::sync::Notify::new(),
            ready: tokio::sync::Notify::new(),
            capacity: capacity.max(1),
            overflow,
            counters,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State<T>> {
        // A panic while holding the lock cannot leave the deque inconsistent, so keep going.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Tries to push without waiting; gives the item back when the queue is full and waits.
    fn try_push(&self, item: T) -> Result<bool, T> {
        let mut state = self.lock();
        if state.closed {
            return Ok(false);
        }
        if state.items.len() >= self.capacity {
            match self.overflow {
                Overflow::DropOldest => {
                    state.items.pop_front();
                    self.counters.overflow.fetch_add(1, Ordering::Relaxed);
                }
                Overflow::Wait => return Err(item),
            }
        }
        state.items.push_back(item);
        drop(state);
        self.ready.notify_one();
        Ok(true)
    }

    /// Pushes from async code; false when closed.
    pub(crate) async fn push(&self, mut item: T) -> bool {
        loop {
            let notified = self.space_async.notified();
            match self.try_push(item) {
                Ok(pushed) => return pushed,
                Err(back) => {
                    item = back;
                    notified.await;
                }
            }
        }
    }

    /// Pushes from a synchronous callback, blocking the calling thread while full.
    pub(crate) fn push_blocking(&self, mut item: T) {
        loop {
            match self.try_push(item) {
                Ok(_) => return,
                Err(back) => {
                    item = back;
                    let state = self.lock();
                    if state.items.len() >= self.capacity && !state.closed {
                        let _unused = self
                            .space
                            .wait_timeout(state, std::time::Duration::from_millis(50));
                    }
                }
            }
        }
    }

    /// The next item if one is waiting, without waiting.
    pub(crate) fn try_pop(&self) -> Option<T> {
        let item = self.lock().items.pop_front()?;
        self.space.notify_one();
        self.space_async.notify_one();
        Some(item)
    }

    /// Next item; `None` once closed and drained.
    pub(crate) async fn pop(&self) -> Option<T> {
        loop {
            let notified = self.ready.notified();
            {
                let mut state = self.lock();
                if let Some(item) = state.items.pop_front() {
                    drop(state);
                    self.space.notify_one();
                    self.space_async.notify_one();
                    return Some(item);
                }
                if state.closed {
                    return None;
                }
            }
            notified.await;
        }
    }

    pub(crate) fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_waiters();
        self.space.notify_all();
        self.space_async.notify_waiters();
    }
}

impl<T> Drop for SampleQueue<T> {
    fn drop(&mut self) {
        self.space.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn stream_queue_drops_oldest_and_counts() {
        let counters = Arc::new(DropCounters::default());
        let q = SampleQueue::new(2, Overflow::DropOldest, counters.clone());
        for i in 0..5 {
            assert!(q.push(i).await);
        }
        assert_eq!(counters.overflow.load(Ordering::Relaxed), 3);
        assert_eq!(q.pop().await, Some(3));
        assert_eq!(q.pop().await, Some(4));
        q.close();
        assert_eq!(q.pop().await, None);
    }

    #[tokio::test]
    async fn reliable_queue_waits_for_space_and_loses_nothing() {
        let counters = Arc::new(DropCounters::default());
        let q = Arc::new(SampleQueue::new(2, Overflow::Wait, counters.clone()));
        let producer = {
            let q = q.clone();
            tokio::spawn(async move {
                for i in 0..50 {
                    assert!(q.push(i).await);
                }
                q.close();
            })
        };
        let mut got = Vec::new();
        while let Some(i) = tokio::time::timeout(std::time::Duration::from_secs(5), q.pop())
            .await
            .expect("no deadlock")
        {
            got.push(i);
        }
        producer.await.expect("producer finished");
        assert_eq!(got, (0..50).collect::<Vec<_>>());
        assert_eq!(counters.total(), 0);
    }
}
