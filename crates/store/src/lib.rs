//! The planner's embedded persistent store: what a planner needs to take a trolley's map back
//! after a restart or a takeover, as opaque byte records in one [redb] file.
//!
//! The store knows nothing of the project's message types: a planner encodes its map blocks,
//! clouds and fruits itself and hands over bytes.
//!
//! # Layout
//!
//! | table         | key                                   | value                                    |
//! | ------------- | ------------------------------------- | ---------------------------------------- |
//! | `format`      | `"version"`                           | [`FORMAT_VERSION`] (`u64`)               |
//! | `checkpoints` | `tid`                                 | `(epoch, frame epoch_ns, frame seq, meta)` |
//! | `blocks`      | `(tid, x, y, z)` (`i32` block coords) | block bytes                              |
//! | `clouds`      | `(tid, frame epoch_ns, frame seq)`    | cloud bytes                              |
//! | `fruits`      | `tid`                                 | `(epoch, fruits bytes)`                  |
//!
//! Keys sort by `tid` first, so one trolley's blocks and clouds are each one key range, and its
//! clouds sort by frame ([`FrameKey`]: `epoch_ns`, then `seq`). A trolley's state is its
//! checkpoint, its blocks (a checkpoint upserts the changed ones; only a full checkpoint or
//! [`Store::forget`] removes any) and the clouds integrated after the checkpoint's frame, a
//! write-ahead log replayed on top of the blocks. A checkpoint drops the logged clouds it covers.
//!
//! # Durability
//!
//! Every call is one redb transaction committed with redb's default immediate durability (an
//! `fdatasync` on Linux before the call returns): a planner publishes its views only after the
//! write returns, and a killed process must not lose a scan it already integrated.
//! [`Store::write_all`] puts several writes in one transaction (one `fdatasync` for all). After a kill,
//! the next open repairs the file (redb walks all of it: ~70 ms for 70 MB here). A file is used
//! by one process at a time (redb locks it); a second opener gets [`StoreError::Locked`].
//!
//! # Epoch rule
//!
//! Each write carries the ownership epoch of the planner term that makes it. A cloud or a
//! checkpoint whose epoch is older than the epoch of the trolley's stored checkpoint, and fruits
//! older than the stored fruits, are refused with [`StoreError::Stale`] and nothing is written:
//! a replaced owner cannot overwrite a newer term's state. The check and the write are one
//! transaction.

#[cfg(test)]
mod tests;

use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use redb::{
    Database, DatabaseError, ReadOnlyTable, ReadTransaction, ReadableDatabase, ReadableTable,
    TableDefinition, TableHandle, Value, WriteTransaction,
};

/// The layout version this build reads and writes; a file of another version is refused.
pub const FORMAT_VERSION: u64 = 1;

/// redb's page cache bound (its default is 1 GiB); the planner keeps its maps in memory anyway.
const CACHE_SIZE_BYTES: usize = 64 * 1024 * 1024;

const FORMAT_KEY: &str = "version";

type CheckpointValue = (u64, u64, u64, &'static [u8]);
type BlockKey = (&'static str, i32, i32, i32);
type CloudKey = (&'static str, u64, u64);
type FruitsValue = (u64, &'static [u8]);

const FORMAT: TableDefinition<&str, u64> = TableDefinition::new("format");
const CHECKPOINTS: TableDefinition<&str, CheckpointValue> = TableDefinition::new("checkpoints");
const BLOCKS: TableDefinition<BlockKey, &[u8]> = TableDefinition::new("blocks");
const CLOUDS: TableDefinition<CloudKey, &[u8]> = TableDefinition::new("clouds");
const FRUITS: TableDefinition<&str, FruitsValue> = TableDefinition::new("fruits");

/// A frame's identity: the trolley's clock epoch (ns) and the frame's sequence number in it.
/// Ordered by `epoch_ns`, then `seq`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FrameKey {
    pub epoch_ns: u64,
    pub seq: u64,
}

impl FrameKey {
    /// The last possible frame: a log range up to it covers every cloud.
    pub const MAX: FrameKey = FrameKey {
        epoch_ns: u64::MAX,
        seq: u64::MAX,
    };
}

/// A map block's integer coordinates (in blocks, not metres).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BlockCoord {
    pub x: i32,
    pub y: i32,
    pub z: i32,
}

/// What a checkpoint writes for one trolley.
#[derive(Clone, Copy, Debug)]
pub struct Checkpoint<'a> {
    /// The ownership epoch of the planner term that writes it.
    pub epoch: u64,
    /// The last frame whose cloud the blocks include; logged clouds up to it are dropped.
    pub frame: FrameKey,
    /// Opaque planner metadata, replaced whole.
    pub meta: &'a [u8],
    /// The blocks to upsert: the changed ones, or all of them when `full`.
    pub blocks: &'a [(BlockCoord, Vec<u8>)],
    /// Remove every stored block and logged cloud of the trolley first.
    pub full: bool,
}

/// One write of a batch ([`Store::write_all`]); each is what the method of its name writes.
#[derive(Clone, Copy, Debug)]
pub enum Write<'a> {
    /// [`Store::append_cloud`].
    Cloud {
        tid: &'a str,
        epoch: u64,
        frame: FrameKey,
        bytes: &'a [u8],
    },
    /// [`Store::checkpoint`].
    Checkpoint {
        tid: &'a str,
        checkpoint: Checkpoint<'a>,
    },
    /// [`Store::put_fruits`].
    Fruits {
        tid: &'a str,
        epoch: u64,
        bytes: &'a [u8],
    },
}

/// A trolley's stored state, as [`Store::load`] returns it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoredTrolley {
    pub tid: String,
    pub epoch: u64,
    pub frame: FrameKey,
    pub meta: Vec<u8>,
    /// In coordinate order.
    pub blocks: Vec<(BlockCoord, Vec<u8>)>,
    /// The clouds logged after the checkpoint, in ascending frame order.
    pub clouds: Vec<(FrameKey, Vec<u8>)>,
}

/// A trolley's latest stored fruits.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoredFruits {
    pub tid: String,
    pub epoch: u64,
    pub bytes: Vec<u8>,
}

/// Writes committed since [`Store::open`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WriteTotals {
    /// Committed write transactions.
    pub transactions: u64,
    /// Key and value bytes inserted (as redb encodes them); removals count nothing.
    pub bytes: u64,
}

/// Why a store call failed. [`StoreError::Locked`] and [`StoreError::Stale`] are the ones a
/// planner acts on; the others it reports.
#[derive(thiserror::Error, Debug)]
pub enum StoreError {
    #[error("cannot open the store {path}: another planner already uses this store (the file is locked)")]
    Locked { path: PathBuf },
    #[error("cannot open the store {path}: {source}")]
    Open {
        path: PathBuf,
        #[source]
        source: DatabaseError,
    },
    #[error("cannot create the store's directory {path}: {source}")]
    CreateDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the store {path} has format version {found}; this build reads version {expected}")]
    Format {
        path: PathBuf,
        found: u64,
        expected: u64,
    },
    #[error("{path} is a redb database but not a glasshouse store (it has no format record)")]
    Foreign { path: PathBuf },
    #[error("store database error: {0}")]
    Db(String),
    #[error("stale write for trolley {tid}: epoch {epoch} is older than the stored epoch {stored_epoch}")]
    Stale {
        tid: String,
        stored_epoch: u64,
        epoch: u64,
    },
}

/// redb's error types (after open) become [`StoreError::Db`]: callers only log them.
macro_rules! db_error_from {
    ($($error:ty),+) => {
        $(impl From<$error> for StoreError {
            fn from(error: $error) -> Self {
                StoreError::Db(error.to_string())
            }
        })+
    };
}

db_error_from!(
    redb::TransactionError,
    redb::TableError,
    redb::StorageError,
    redb::CommitError
);

/// The store: one redb file, used by one process. `Send + Sync`, so it can sit in an `Arc`.
#[derive(Debug)]
pub struct Store {
    db: Database,
    transactions: AtomicU64,
    bytes: AtomicU64,
}

impl Store {
    /// Opens or creates the database file at `path` (creating parent directories).
    pub fn open(path: &Path) -> Result<Store, StoreError> {
        create_parent(path)?;
        let db = Database::builder()
            .set_cache_size(CACHE_SIZE_BYTES)
            .create(path)
            .map_err(|source| open_error(path, source))?;
        init_format(&db, path)?;
        Ok(Store {
            db,
            transactions: AtomicU64::new(0),
            bytes: AtomicU64::new(0),
        })
    }

    /// Appends an integrated cloud to `tid`'s log. Refused ([`StoreError::Stale`], nothing
    /// written) when `epoch` is older than the epoch of `tid`'s stored checkpoint; accepted when
    /// no checkpoint is stored yet.
    pub fn append_cloud(
        &self,
        tid: &str,
        epoch: u64,
        frame: FrameKey,
        bytes: &[u8],
    ) -> Result<(), StoreError> {
        self.write_one(&Write::Cloud {
            tid,
            epoch,
            frame,
            bytes,
        })
    }

    /// In one transaction: (when `full`, first removes every block and logged cloud of `tid`)
    /// upserts the given blocks, sets the checkpoint (epoch, frame, meta) and drops the logged
    /// clouds up to the checkpoint's frame. A stale epoch is refused as by
    /// [`Store::append_cloud`].
    pub fn checkpoint(&self, tid: &str, checkpoint: &Checkpoint<'_>) -> Result<(), StoreError> {
        self.write_one(&Write::Checkpoint {
            tid,
            checkpoint: *checkpoint,
        })
    }

    /// Replaces `tid`'s latest fruits; refused ([`StoreError::Stale`]) when `epoch` is older
    /// than the stored fruits' epoch.
    pub fn put_fruits(&self, tid: &str, epoch: u64, bytes: &[u8]) -> Result<(), StoreError> {
        self.write_one(&Write::Fruits { tid, epoch, bytes })
    }

    /// Performs `writes` in order in one transaction: one commit, one `fdatasync`, for all of
    /// them (a writer that fell behind its disk catches up with what queued meanwhile). A
    /// write refused for its epoch ([`StoreError::Stale`]) writes nothing and leaves the others
    /// be; its error is in its place of the result. Any other error aborts the transaction:
    /// nothing of the batch is written.
    pub fn write_all(
        &self,
        writes: &[Write<'_>],
    ) -> Result<Vec<Result<(), StoreError>>, StoreError> {
        let txn = self.db.begin_write()?;
        let mut written = 0;
        let mut outcomes = Vec::with_capacity(writes.len());
        for write in writes {
            match write_in(&txn, write) {
                Ok(bytes) => {
                    written += bytes;
                    outcomes.push(Ok(()));
                }
                Err(stale @ StoreError::Stale { .. }) => outcomes.push(Err(stale)),
                Err(e) => return Err(e),
            }
        }
        self.commit(txn, written)?;
        Ok(outcomes)
    }

    /// One write in its own transaction; a refused one commits nothing.
    fn write_one(&self, write: &Write<'_>) -> Result<(), StoreError> {
        let txn = self.db.begin_write()?;
        let written = write_in(&txn, write)?;
        self.commit(txn, written)
    }

    /// Every trolley with a checkpoint (the logged clouds of a trolley without one are ignored)
    /// and every stored fruits record, each sorted by `tid`.
    pub fn load(&self) -> Result<(Vec<StoredTrolley>, Vec<StoredFruits>), StoreError> {
        let txn = self.db.begin_read()?;
        Ok((load_trolleys(&txn)?, load_fruits(&txn)?))
    }

    /// Removes everything of `tid`: checkpoint, blocks, logged clouds and fruits.
    pub fn forget(&self, tid: &str) -> Result<(), StoreError> {
        let txn = self.db.begin_write()?;
        txn.open_table(CHECKPOINTS)?.remove(tid)?;
        txn.open_table(FRUITS)?.remove(tid)?;
        remove_blocks(&txn, tid)?;
        remove_clouds_through(&txn, tid, FrameKey::MAX)?;
        self.commit(txn, 0)
    }

    /// The writes committed since [`Store::open`].
    pub fn totals(&self) -> WriteTotals {
        WriteTotals {
            transactions: self.transactions.load(Ordering::Relaxed),
            bytes: self.bytes.load(Ordering::Relaxed),
        }
    }

    /// Commits (durably) and counts the transaction.
    fn commit(&self, txn: WriteTransaction, written_bytes: u64) -> Result<(), StoreError> {
        txn.commit()?;
        self.transactions.fetch_add(1, Ordering::Relaxed);
        self.bytes.fetch_add(written_bytes, Ordering::Relaxed);
        Ok(())
    }
}

/// Creates the directory the database file goes in.
fn create_parent(path: &Path) -> Result<(), StoreError> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => {
            std::fs::create_dir_all(dir).map_err(|source| StoreError::CreateDir {
                path: dir.to_path_buf(),
                source,
            })
        }
        _ => Ok(()),
    }
}

/// Tells a file locked by another opener from other open failures.
fn open_error(path: &Path, source: DatabaseError) -> StoreError {
    let path = path.to_path_buf();
    match source {
        DatabaseError::DatabaseAlreadyOpen => StoreError::Locked { path },
        source => StoreError::Open { path, source },
    }
}

/// Writes the format record and creates the tables in a new file; checks the record of an
/// existing one (before creating anything in it).
fn init_format(db: &Database, path: &Path) -> Result<(), StoreError> {
    let txn = db.begin_write()?;
    let names: Vec<String> = txn.list_tables()?.map(|t| t.name().to_owned()).collect();
    if names.is_empty() {
        txn.open_table(FORMAT)?.insert(FORMAT_KEY, FORMAT_VERSION)?;
    } else {
        check_format(&txn, &names, path)?;
    }
    create_tables(&txn)?;
    txn.commit()?;
    Ok(())
}

/// Refuses a file without our format record or with another version.
fn check_format(txn: &WriteTransaction, names: &[String], path: &Path) -> Result<(), StoreError> {
    let foreign = || StoreError::Foreign {
        path: path.to_path_buf(),
    };
    if !names.iter().any(|name| name == FORMAT.name()) {
        return Err(foreign());
    }
    let found = txn.open_table(FORMAT)?.get(FORMAT_KEY)?.map(|v| v.value());
    match found {
        Some(FORMAT_VERSION) => Ok(()),
        Some(found) => Err(StoreError::Format {
            path: path.to_path_buf(),
            found,
            expected: FORMAT_VERSION,
        }),
        None => Err(foreign()),
    }
}

/// Creates the data tables, so that read transactions can open them all.
fn create_tables(txn: &WriteTransaction) -> Result<(), StoreError> {
    txn.open_table(CHECKPOINTS)?;
    txn.open_table(BLOCKS)?;
    txn.open_table(CLOUDS)?;
    txn.open_table(FRUITS)?;
    Ok(())
}

/// Performs one write in `txn` (its epoch checked first); returns the bytes written.
fn write_in(txn: &WriteTransaction, write: &Write<'_>) -> Result<u64, StoreError> {
    match *write {
        Write::Cloud {
            tid,
            epoch,
            frame,
            bytes,
        } => {
            check_epoch(txn, tid, epoch)?;
            let key = (tid, frame.epoch_ns, frame.seq);
            let written = encoded_len::<CloudKey>(&key) + len_u64(bytes);
            txn.open_table(CLOUDS)?.insert(key, bytes)?;
            Ok(written)
        }
        Write::Checkpoint { tid, checkpoint } => {
            check_epoch(txn, tid, checkpoint.epoch)?;
            if checkpoint.full {
                remove_blocks(txn, tid)?;
                remove_clouds_through(txn, tid, FrameKey::MAX)?;
            }
            let written = put_blocks(txn, tid, checkpoint.blocks)?;
            let written = written + put_checkpoint(txn, tid, &checkpoint)?;
            remove_clouds_through(txn, tid, checkpoint.frame)?;
            Ok(written)
        }
        Write::Fruits { tid, epoch, bytes } => put_fruits_in(txn, tid, epoch, bytes),
    }
}

/// Refuses a write of `epoch` when `tid`'s stored checkpoint is of a newer epoch.
fn check_epoch(txn: &WriteTransaction, tid: &str, epoch: u64) -> Result<(), StoreError> {
    let stored = txn.open_table(CHECKPOINTS)?.get(tid)?.map(|v| v.value().0);
    refuse_older(tid, stored, epoch)
}

/// [`StoreError::Stale`] when `epoch` is older than `stored`.
fn refuse_older(tid: &str, stored: Option<u64>, epoch: u64) -> Result<(), StoreError> {
    match stored {
        Some(stored_epoch) if epoch < stored_epoch => Err(StoreError::Stale {
            tid: tid.to_owned(),
            stored_epoch,
            epoch,
        }),
        _ => Ok(()),
    }
}

/// Upserts blocks; returns the bytes written.
fn put_blocks(
    txn: &WriteTransaction,
    tid: &str,
    blocks: &[(BlockCoord, Vec<u8>)],
) -> Result<u64, StoreError> {
    let mut table = txn.open_table(BLOCKS)?;
    let mut written = 0;
    for (coord, bytes) in blocks {
        let key = (tid, coord.x, coord.y, coord.z);
        written += encoded_len::<BlockKey>(&key) + len_u64(bytes);
        table.insert(key, bytes.as_slice())?;
    }
    Ok(written)
}

/// Sets the checkpoint record; returns the bytes written.
fn put_checkpoint(
    txn: &WriteTransaction,
    tid: &str,
    checkpoint: &Checkpoint<'_>,
) -> Result<u64, StoreError> {
    let frame = checkpoint.frame;
    let value = (checkpoint.epoch, frame.epoch_ns, frame.seq, checkpoint.meta);
    let written = encoded_len::<&str>(&tid) + encoded_len::<CheckpointValue>(&value);
    txn.open_table(CHECKPOINTS)?.insert(tid, value)?;
    Ok(written)
}

/// Replaces the fruits record unless it is stale; returns the bytes written.
fn put_fruits_in(
    txn: &WriteTransaction,
    tid: &str,
    epoch: u64,
    bytes: &[u8],
) -> Result<u64, StoreError> {
    let mut table = txn.open_table(FRUITS)?;
    let stored = table.get(tid)?.map(|v| v.value().0);
    refuse_older(tid, stored, epoch)?;
    let value = (epoch, bytes);
    let written = encoded_len::<&str>(&tid) + encoded_len::<FruitsValue>(&value);
    table.insert(tid, value)?;
    Ok(written)
}

/// Removes every block of `tid`.
fn remove_blocks(txn: &WriteTransaction, tid: &str) -> Result<(), StoreError> {
    txn.open_table(BLOCKS)?
        .retain_in(block_range(tid), |_, _| false)?;
    Ok(())
}

/// Removes `tid`'s logged clouds with a frame up to `last` (inclusive).
fn remove_clouds_through(
    txn: &WriteTransaction,
    tid: &str,
    last: FrameKey,
) -> Result<(), StoreError> {
    txn.open_table(CLOUDS)?
        .retain_in(cloud_range(tid, last), |_, _| false)?;
    Ok(())
}

/// Every block key of `tid`.
fn block_range(tid: &str) -> RangeInclusive<(&str, i32, i32, i32)> {
    (tid, i32::MIN, i32::MIN, i32::MIN)..=(tid, i32::MAX, i32::MAX, i32::MAX)
}

/// `tid`'s cloud keys up to the frame `last` (inclusive).
fn cloud_range(tid: &str, last: FrameKey) -> RangeInclusive<(&str, u64, u64)> {
    (tid, 0, 0)..=(tid, last.epoch_ns, last.seq)
}

/// Every checkpointed trolley with its blocks and logged clouds, by `tid`.
fn load_trolleys(txn: &ReadTransaction) -> Result<Vec<StoredTrolley>, StoreError> {
    let checkpoints = txn.open_table(CHECKPOINTS)?;
    let blocks = txn.open_table(BLOCKS)?;
    let clouds = txn.open_table(CLOUDS)?;
    let mut trolleys = Vec::new();
    for entry in checkpoints.iter()? {
        let (tid, value) = entry?;
        let tid = tid.value();
        let (epoch, epoch_ns, seq, meta) = value.value();
        trolleys.push(StoredTrolley {
            tid: tid.to_owned(),
            epoch,
            frame: FrameKey { epoch_ns, seq },
            meta: meta.to_vec(),
            blocks: read_blocks(&blocks, tid)?,
            clouds: read_clouds(&clouds, tid)?,
        });
    }
    Ok(trolleys)
}

/// `tid`'s blocks in coordinate order.
fn read_blocks(
    table: &ReadOnlyTable<BlockKey, &'static [u8]>,
    tid: &str,
) -> Result<Vec<(BlockCoord, Vec<u8>)>, StoreError> {
    let mut blocks = Vec::new();
    for entry in ReadableTable::range(table, block_range(tid))? {
        let (key, value) = entry?;
        let (_, x, y, z) = key.value();
        blocks.push((BlockCoord { x, y, z }, value.value().to_vec()));
    }
    Ok(blocks)
}

/// `tid`'s logged clouds in frame order.
fn read_clouds(
    table: &ReadOnlyTable<CloudKey, &'static [u8]>,
    tid: &str,
) -> Result<Vec<(FrameKey, Vec<u8>)>, StoreError> {
    let mut clouds = Vec::new();
    for entry in ReadableTable::range(table, cloud_range(tid, FrameKey::MAX))? {
        let (key, value) = entry?;
        let (_, epoch_ns, seq) = key.value();
        clouds.push((FrameKey { epoch_ns, seq }, value.value().to_vec()));
    }
    Ok(clouds)
}

/// Every stored fruits record, by `tid`.
fn load_fruits(txn: &ReadTransaction) -> Result<Vec<StoredFruits>, StoreError> {
    let table = txn.open_table(FRUITS)?;
    let mut fruits = Vec::new();
    for entry in table.iter()? {
        let (tid, value) = entry?;
        let (epoch, bytes) = value.value();
        fruits.push(StoredFruits {
            tid: tid.value().to_owned(),
            epoch,
            bytes: bytes.to_vec(),
        });
    }
    Ok(fruits)
}

/// The length of `value` as redb stores it.
fn encoded_len<T: Value>(value: &T::SelfType<'_>) -> u64 {
    len_u64(T::as_bytes(value).as_ref())
}

/// A slice's length in bytes, as `u64`.
fn len_u64(bytes: &[u8]) -> u64 {
    u64::try_from(bytes.len()).unwrap_or(u64::MAX)
}
