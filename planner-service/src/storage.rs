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
use glasshouse_proto::{
    decode_typed, encode, FruitEstimates, Header, MapSnapshot, MessageKind, RoiCloud,
};
use glasshouse_store::{BlockCoord, Checkpoint, FrameKey, Store, WriteTotals};

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
        match write {
            StoreWrite::Cloud {
                tid,
                epoch,
                header,
                cloud,
            } => {
                let frame = cloud.source_frame();
                let key = FrameKey {
                    epoch_ns: frame.epoch_ns,
                    seq: frame.seq,
                };
                let bytes = zstd::bulk::compress(&encode(header, cloud.as_ref()), CLOUD_LEVEL)
                    .context("compressing a cloud")?;
                self.store.append_cloud(tid, *epoch, key, &bytes)?;
            }
            StoreWrite::Checkpoint {
                tid,
                epoch,
                copy,
                full,
            } => {
                let meta = &copy.meta;
                let header = Header {
                    trolley_id: tid.clone(),
                    source_id: meta.planner_id.clone(),
                    seq: meta.based_on_seq,
                    frame_id: "world".into(),
                    ..Header::default()
                };
                let meta = MapSnapshot {
                    owner_epoch: *epoch,
                    ..meta.clone()
                };
                let blocks: Vec<(BlockCoord, Vec<u8>)> = copy
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
                let checkpoint = Checkpoint {
                    epoch: *epoch,
                    frame: FrameKey {
                        epoch_ns: meta.based_on_epoch_ns,
                        seq: meta.based_on_seq,
                    },
                    meta: &encode(&header, &meta),
                    blocks: &blocks,
                    full: *full,
                };
                self.store.checkpoint(tid, &checkpoint)?;
            }
            StoreWrite::Fruits(fruits) => {
                for (header, estimates) in fruits {
                    let bytes = encode(header, estimates);
                    self.store
                        .put_fruits(&header.trolley_id, estimates.owner_epoch, &bytes)?;
                }
            }
        }
        Ok(())
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

/// A write queued for the writer thread; `done` is answered once it is durable.
struct Job {
    write: StoreWrite,
    done: Option<tokio::sync::oneshot::Sender<()>>,
}

/// The store behind one writer thread: writes are performed in the order they are queued. A
/// cloud's write is awaited (its views go out only once it is durable); a checkpoint's and the
/// fruits' are not: they overlap the work on the next cloud, whose own write then waits behind
/// them. A failed write is logged and counted, and its trolley reported to the node
/// ([`PlannerEvent::StoreFailed`]) so that its next checkpoint is a full one.
pub struct StoreWriter {
    jobs: std::sync::mpsc::Sender<Job>,
    thread: std::thread::JoinHandle<()>,
}

impl StoreWriter {
    pub fn start(
        store: PlannerStore,
        counters: Arc<PlannerCounters>,
        events: tokio::sync::mpsc::UnboundedSender<PlannerEvent>,
    ) -> anyhow::Result<Self> {
        let (jobs, queue) = std::sync::mpsc::channel::<Job>();
        let thread = std::thread::Builder::new()
            .name("store-writer".into())
            .spawn(move || {
                for job in queue {
                    perform(&store, &job.write, &counters, &events);
                    if let Some(done) = job.done {
                        let _ = done.send(());
                    }
                }
            })
            .context("starting the store writer")?;
        Ok(Self { jobs, thread })
    }

    /// Queues `write`; returns once it is durable for a cloud, at once otherwise.
    pub async fn write(&self, write: StoreWrite) {
        let awaited = matches!(write, StoreWrite::Cloud { .. });
        let (done, written) = tokio::sync::oneshot::channel();
        let job = Job {
            write,
            done: awaited.then_some(done),
        };
        if self.jobs.send(job).is_err() {
            tracing::error!("the store writer has stopped: this write is in memory only");
            return;
        }
        if awaited {
            let _ = written.await;
        }
    }

    /// Performs every queued write, then stops the thread.
    pub fn close(self) {
        drop(self.jobs);
        if self.thread.join().is_err() {
            tracing::error!("the store writer failed");
        }
    }
}

/// One write on the writer thread, counted; a failure logged and reported.
fn perform(
    store: &PlannerStore,
    write: &StoreWrite,
    counters: &PlannerCounters,
    events: &tokio::sync::mpsc::UnboundedSender<PlannerEvent>,
) {
    let before = store.totals().bytes;
    match store.write(write) {
        Ok(()) => {
            let bytes = store.totals().bytes - before;
            counters.store_writes.fetch_add(1, Ordering::Relaxed);
            counters
                .store_bytes_written
                .fetch_add(bytes, Ordering::Relaxed);
        }
        Err(e) => {
            counters.store_errors.fetch_add(1, Ordering::Relaxed);
            tracing::error!(error = %format!("{e:#}"), trolley = write.trolley().unwrap_or("-"),
                "store write failed: the planner goes on, this state is in memory only");
            if let Some(tid) = write.trolley() {
                let _ = events.send(PlannerEvent::StoreFailed {
                    tid: tid.to_owned(),
                });
            }
        }
    }
}
