//! The driver's side of the planner's store (`glasshouse_store`, one redb file per planner):
//! opening it, turning what it holds into the node's [`StoredTrolley`]s, and performing the
//! node's [`StoreWrite`]s. Records are the wire's own envelopes (a checkpoint's metadata a
//! `MapSnapshot` whose map is the map's header, logged clouds `RoiCloud`s, fruits
//! `FruitEstimates`), so they are verified on the way back in as a message from the bus is.
//! Logged clouds, most of what a planner writes, are kept zstd-compressed (level 1).

use std::path::Path;

use anyhow::Context;
use glasshouse_proto::{
    decode_typed, encode, FruitEstimates, Header, MapSnapshot, MessageKind, RoiCloud,
};
use glasshouse_store::{BlockCoord, Checkpoint, FrameKey, Store, WriteTotals};

use crate::node::{StoreWrite, StoredTrolley};

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
