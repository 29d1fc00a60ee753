//! The driver's side of the planner's store (`glasshouse_store`, one redb file per planner):
//! opening it, turning what it holds into the node's [`StoredTrolley`]s, and performing the
//! node's [`StoreWrite`]s. Records are the wire's own envelopes (a checkpoint's metadata a
//! `MapSnapshot` whose map is the map's header, logged clouds `RoiCloud`s, fruits
//! `FruitEstimates`), so they are verified on the way back in as a message from the bus is.
//! Logged clouds, most of what a planner writes, are kept zstd-compressed (level 1).

use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use anyhow::Context;
use glasshouse_pipeline::StoredCopy;
use glasshouse_proto::{
    decode_typed, encode, FruitEstimates, Header, MapSnapshot, MessageKind, RoiCloud,
};
use glasshouse_store::{BlockCoord, Checkpoint, FrameKey, Store, Write, WriteTotals};

use crate::node::{PlannerEvent, StoreWrite, StoredTrolley};
use crate::PlannerCounters;

/// A planner's store.
pub struct PlannerStore {
    store: Store,
}

/// What a store held at start.
pub struct Loaded {
    pub trolleys: Vec<StoredTrolley>,
    pub fruits: Vec<(Header, FruitEstimates)>,
    /// A line per record that could not be read (left out; the store keeps it).
    pub unreadable: Vec<String>,
}

impl PlannerStore {
    /// Opens (or creates) the store file at `path`.
    pub fn open(path: &Path) -> anyhow::Result<Self> {
        let store = Store::open(path)?;
        Ok(Self { store })
    }

    /// Bytes and transactions written since it was opened.
    pub fn totals(&self) -> WriteTotals {
        self.store.totals()
    }

    /// Everything the store holds, decoded.
    pub fn load(&self) -> anyhow::Result<Loaded> {
        let (trolleys, fruits) = self.store.load()?;
        let mut loaded = Loaded {
            trolleys: Vec::new(),
            fruits: Vec::new(),
            unreadable: Vec::new(),
        };
        for t in trolleys {
            match decode_trolley(t) {
                Ok(t) => loaded.trolleys.push(t),
                Err(e) => loaded.unreadable.push(format!("{e:#}")),
            }
        }
        for f in fruits {
            match decode_typed::<FruitEstimates>(&f.bytes) {
                Ok(fruits) => loaded.fruits.push(fruits),
                Err(e) => loaded
                    .unreadable
                    .push(format!("fruits of trolley {}: {e:#}", f.tid)),
            }
        }
        Ok(loaded)
    }

    /// Performs one of the node's writes; it is durable when this returns.
    pub fn write(&self, write: &StoreWrite) -> anyhow::Result<()> {
        self.write_all(&[write])?.remove(0)
    }

    /// Performs the node's writes in order in one transaction (one `fdatasync`); all are
    /// durable when this returns. Each write's own outcome is in its place (a refused or
    /// unencodable one writes nothing); an error of the transaction writes none of them.
    pub fn write_all(&self, writes: &[&StoreWrite]) -> anyhow::Result<Vec<anyhow::Result<()>>> {
        let prepared: Vec<anyhow::Result<Vec<Prepared>>> =
            writes.iter().map(|w| prepare(w)).collect();
        let mut batch = Vec::new();
        let mut owner = Vec::new();
        for (i, records) in prepared.iter().enumerate() {
            for record in records.iter().flatten() {
                batch.push(record.as_write());
                owner.push(i);
            }
        }
        let stored = self.store.write_all(&batch)?;
        let mut outcomes: Vec<anyhow::Result<()>> =
            prepared.into_iter().map(|p| p.map(|_| ())).collect();
        for (i, result) in owner.into_iter().zip(stored) {
            if let (Ok(()), Err(e)) = (&outcomes[i], result) {
                outcomes[i] = Err(e.into());
            }
        }
        Ok(outcomes)
    }
}

/// A store record made from one of the node's writes, owning its bytes.
enum Prepared {
    Cloud {
        tid: String,
        epoch: u64,
        frame: FrameKey,
        bytes: Vec<u8>,
    },
    Checkpoint {
        tid: String,
        epoch: u64,
        frame: FrameKey,
        meta: Vec<u8>,
        blocks: Vec<(BlockCoord, Vec<u8>)>,
        full: bool,
    },
    Fruits {
        tid: String,
        epoch: u64,
        bytes: Vec<u8>,
    },
}

impl Prepared {
    fn as_write(&self) -> Write<'_> {
        match self {
            Prepared::Cloud {
                tid,
                epoch,
                frame,
                bytes,
            } => Write::Cloud {
                tid,
                epoch: *epoch,
                frame: *frame,
                bytes,
            },
            Prepared::Checkpoint {
                tid,
                epoch,
                frame,
                meta,
                blocks,
                full,
            } => Write::Checkpoint {
                tid,
                checkpoint: Checkpoint {
                    epoch: *epoch,
                    frame: *frame,
                    meta,
                    blocks,
                    full: *full,
                },
            },
            Prepared::Fruits { tid, epoch, bytes } => Write::Fruits {
                tid,
                epoch: *epoch,
                bytes,
            },
        }
    }
}

/// The store records of one of the node's writes: a cloud compressed, a checkpoint's metadata
/// and blocks, each trolley's fruits encoded.
fn prepare(write: &StoreWrite) -> anyhow::Result<Vec<Prepared>> {
    Ok(match write {
        StoreWrite::Cloud {
            tid,
            epoch,
            header,
            cloud,
        } => {
            let source = cloud.source_frame();
            let bytes = zstd::bulk::compress(&encode(header, cloud.as_ref()), CLOUD_LEVEL)
                .context("compressing a cloud")?;
            vec![Prepared::Cloud {
                tid: tid.clone(),
                epoch: *epoch,
                frame: FrameKey {
                    epoch_ns: source.epoch_ns,
                    seq: source.seq,
                },
                bytes,
            }]
        }
        StoreWrite::Checkpoint {
            tid,
            epoch,
            copy,
            full,
        } => vec![prepare_checkpoint(tid, *epoch, copy, *full)],
        StoreWrite::Fruits(fruits) => fruits
            .iter()
            .map(|(header, estimates)| Prepared::Fruits {
                tid: header.trolley_id.clone(),
                epoch: estimates.owner_epoch,
                bytes: encode(header, estimates),
            })
            .collect(),
    })
}

/// A checkpoint's record: the copy's metadata as a `MapSnapshot` envelope (its map the map's
/// header) under `epoch`, and its blocks.
fn prepare_checkpoint(tid: &str, epoch: u64, copy: &StoredCopy, full: bool) -> Prepared {
    let meta = &copy.meta;
    let header = Header {
        trolley_id: tid.to_owned(),
        source_id: meta.planner_id.clone(),
        seq: meta.based_on_seq,
        frame_id: "world".into(),
        ..Header::default()
    };
    let meta = MapSnapshot {
        owner_epoch: epoch,
        ..meta.clone()
    };
    let blocks = copy
        .blocks
        .iter()
        .map(|(k, record)| {
            let coord = BlockCoord {
                x: k.x,
                y: k.y,
                z: k.z,
            };
            (coord, record.clone())
        })
        .collect();
    Prepared::Checkpoint {
        tid: tid.to_owned(),
        epoch,
        frame: FrameKey {
            epoch_ns: meta.based_on_epoch_ns,
            seq: meta.based_on_seq,
        },
        meta: encode(&header, &meta),
        blocks,
        full,
    }
}

/// zstd's level for logged clouds: its fastest, the write is on the path to the views.
const CLOUD_LEVEL: i32 = 1;

/// A logged cloud back: decompressed (at most a cloud's size limit on the wire), then verified.
fn decode_cloud(bytes: &[u8]) -> anyhow::Result<(Header, RoiCloud)> {
    let limit = MessageKind::RoiCloud.max_bytes();
    let bytes = zstd::bulk::decompress(bytes, limit).context("decompressing")?;
    Ok(decode_typed::<RoiCloud>(&bytes)?)
}

fn decode_trolley(t: glasshouse_store::StoredTrolley) -> anyhow::Result<StoredTrolley> {
    let tid = t.tid;
    let (_, meta) = decode_typed::<MapSnapshot>(&t.meta)
        .with_context(|| format!("checkpoint of trolley {tid}"))?;
    let clouds = t
        .clouds
        .iter()
        .map(|(frame, bytes)| {
            decode_cloud(bytes).with_context(|| {
                format!(
                    "logged cloud {}/{} of trolley {tid}",
                    frame.epoch_ns, frame.seq
                )
            })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(StoredTrolley {
        epoch: t.epoch,
        meta,
        blocks: t.blocks.into_iter().map(|(_, record)| record).collect(),
        clouds,
        tid,
    })
}

/// A write queued for the writer thread, numbered in queue order.
struct Job {
    seq: u64,
    write: StoreWrite,
}

/// The store behind one writer thread: writes are performed in the order they are queued and
/// each is numbered, so that "durable through n" ([`StoreWriter::durable_through`]) says which
/// are on disk. What queued while a transaction was being written goes in the next one together
/// (up to [`WRITES_PER_TRANSACTION`]): one `fdatasync` for all of it, so a slow disk is caught up
/// with rather than fallen further behind. Nothing here waits for the disk: the driver holds a trolley's views until its
/// cloud's write is durable ([`crate::held`]) and goes on meanwhile. A failed write is logged and
/// counted (and still counts as done: its state is in memory only), and its trolley reported to
/// the node ([`PlannerEvent::StoreFailed`]) so that its next checkpoint is a full one.
pub struct StoreWriter {
    jobs: std::sync::mpsc::Sender<Job>,
    thread: std::thread::JoinHandle<()>,
    queued: u64,
    durable: tokio::sync::watch::Receiver<u64>,
}

impl StoreWriter {
    /// Starts the writer thread. `write_delay` is waited before every transaction (fault
    /// injection: a slow disk; zero in deployment).
    pub fn start(
        store: PlannerStore,
        counters: Arc<PlannerCounters>,
        events: tokio::sync::mpsc::UnboundedSender<PlannerEvent>,
        write_delay: std::time::Duration,
    ) -> anyhow::Result<Self> {
        let (jobs, queue) = std::sync::mpsc::channel::<Job>();
        let (done, durable) = tokio::sync::watch::channel(0);
        let thread = std::thread::Builder::new()
            .name("store-writer".into())
            .spawn(move || {
                while let Ok(first) = queue.recv() {
                    let mut jobs = vec![first];
                    while jobs.len() < WRITES_PER_TRANSACTION {
                        match queue.try_recv() {
                            Ok(job) => jobs.push(job),
                            Err(_) => break,
                        }
                    }
                    if !write_delay.is_zero() {
                        std::thread::sleep(write_delay);
                    }
                    perform(&store, &jobs, &counters, &events);
                    done.send_replace(jobs[jobs.len() - 1].seq);
                }
            })
            .context("starting the store writer")?;
        Ok(Self {
            jobs,
            thread,
            queued: 0,
            durable,
        })
    }

    /// Queues `write`; its number, or None when the writer has stopped (the write is then in
    /// memory only, and nothing waits for it).
    pub fn queue(&mut self, write: StoreWrite) -> Option<u64> {
        let seq = self.queued + 1;
        if self.jobs.send(Job { seq, write }).is_err() {
            tracing::error!("the store writer has stopped: this write is in memory only");
            return None;
        }
        self.queued = seq;
        Some(seq)
    }

    /// The number of the last write queued.
    pub fn queued(&self) -> u64 {
        self.queued
    }

    /// Every write numbered up to this is done (all of them once the writer has stopped).
    pub fn durable_through(&self) -> u64 {
        match self.durable.has_changed() {
            Ok(_) => *self.durable.borrow(),
            Err(_) => u64::MAX,
        }
    }

    /// A receiver that wakes whenever a write is done (closed once the writer has stopped).
    pub fn durable_watch(&self) -> tokio::sync::watch::Receiver<u64> {
        self.durable.clone()
    }

    /// Returns once write `seq` is done (at once if the writer has stopped).
    pub async fn wait_durable(&self, seq: u64) {
        let mut durable = self.durable.clone();
        let _ = durable.wait_for(|done| *done >= seq).await;
    }

    /// Performs every queued write, then stops the thread.
    pub fn close(self) {
        drop(self.jobs);
        if self.thread.join().is_err() {
            tracing::error!("the store writer failed");
        }
    }
}

/// Writes queued together that go into one transaction at most.
const WRITES_PER_TRANSACTION: usize = 32;

/// A batch of writes on the writer thread, in one transaction, counted; each failure logged and
/// reported.
fn perform(
    store: &PlannerStore,
    jobs: &[Job],
    counters: &PlannerCounters,
    events: &tokio::sync::mpsc::UnboundedSender<PlannerEvent>,
) {
    let before = store.totals();
    let writes: Vec<&StoreWrite> = jobs.iter().map(|job| &job.write).collect();
    let outcomes: Vec<Result<(), String>> = match store.write_all(&writes) {
        Ok(outcomes) => outcomes
            .into_iter()
            .map(|o| o.map_err(|e| format!("{e:#}")))
            .collect(),
        Err(e) => vec![Err(format!("{e:#}")); writes.len()],
    };
    let after = store.totals();
    counters
        .store_bytes_written
        .fetch_add(after.bytes - before.bytes, Ordering::Relaxed);
    counters
        .store_transactions
        .fetch_add(after.transactions - before.transactions, Ordering::Relaxed);
    for (write, outcome) in writes.into_iter().zip(outcomes) {
        match outcome {
            Ok(()) => {
                counters.store_writes.fetch_add(1, Ordering::Relaxed);
            }
            Err(error) => {
                counters.store_errors.fetch_add(1, Ordering::Relaxed);
                tracing::error!(%error, trolley = write.trolley().unwrap_or("-"),
                    "store write failed: the planner goes on, this state is in memory only");
                if let Some(tid) = write.trolley() {
                    let _ = events.send(PlannerEvent::StoreFailed {
                        tid: tid.to_owned(),
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn fruits_of(tid: &str) -> StoreWrite {
        let header = Header {
            trolley_id: tid.to_owned(),
            ..Header::default()
        };
        let fruits = FruitEstimates {
            fruits: Vec::new(),
            based_on_seq: 1,
            planner_id: "p1".into(),
            owner_epoch: 1,
            visit: 0,
            history: Vec::new(),
        };
        StoreWrite::Fruits(vec![(header, fruits)])
    }

    #[tokio::test]
    async fn writes_queued_behind_a_slow_transaction_go_into_the_next_one_together() {
        let dir = std::env::temp_dir().join(format!("glasshouse-writer-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let store = PlannerStore::open(&dir.join("p1.redb")).expect("store opens");
        let counters = Arc::new(PlannerCounters::default());
        let (events, _) = tokio::sync::mpsc::unbounded_channel();
        let delay = Duration::from_millis(300);
        let mut writer =
            StoreWriter::start(store, counters.clone(), events, delay).expect("writer");
        let seqs: Vec<u64> = ["t1", "t2", "t3", "t4", "t5"]
            .iter()
            .map(|tid| writer.queue(fruits_of(tid)).expect("queued"))
            .collect();
        assert_eq!(seqs, vec![1, 2, 3, 4, 5]);
        assert!(
            writer.durable_through() < 5,
            "done before the slow disk wrote"
        );
        writer.wait_durable(5).await;
        assert_eq!(writer.durable_through(), 5);
        // The first may go alone before the rest are queued; the rest wait and go together.
        let transactions = counters.store_transactions.load(Ordering::Relaxed);
        assert!(
            (1..=2).contains(&transactions),
            "{transactions} transactions"
        );
        assert_eq!(counters.store_writes.load(Ordering::Relaxed), 5);
        writer.close();
        let reopened = PlannerStore::open(&dir.join("p1.redb")).expect("store reopens");
        assert_eq!(reopened.load().expect("loads").fruits.len(), 5);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
