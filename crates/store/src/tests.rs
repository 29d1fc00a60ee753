use std::path::PathBuf;
use std::sync::Arc;

use super::*;

type TestResult = Result<(), StoreError>;

/// A unique directory under the system temp dir, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let dir = std::env::temp_dir().join(format!(
            "glasshouse-store-{name}-{}-{nanos}",
            std::process::id()
        ));
        TempDir(dir)
    }

    /// The database path, in a subdirectory that `Store::open` must create.
    fn db(&self) -> PathBuf {
        self.0.join("state").join("planner.redb")
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn frame(epoch_ns: u64, seq: u64) -> FrameKey {
    FrameKey { epoch_ns, seq }
}

fn coord(x: i32, y: i32, z: i32) -> BlockCoord {
    BlockCoord { x, y, z }
}

fn checkpoint<'a>(
    epoch: u64,
    frame: FrameKey,
    blocks: &'a [(BlockCoord, Vec<u8>)],
    full: bool,
) -> Checkpoint<'a> {
    Checkpoint {
        epoch,
        frame,
        meta: b"meta",
        blocks,
        full,
    }
}

/// The only stored trolley.
fn only_trolley(store: &Store) -> Result<StoredTrolley, StoreError> {
    let (mut trolleys, _) = store.load()?;
    assert_eq!(trolleys.len(), 1, "{trolleys:?}");
    Ok(trolleys.remove(0))
}

#[test]
fn store_is_send_and_sync() {
    fn shareable<T: Send + Sync + 'static>() {}
    shareable::<Store>();
    shareable::<Arc<Store>>();
    shareable::<StoreError>();
}

#[test]
fn round_trip_through_reopen() -> TestResult {
    let dir = TempDir::new("round-trip");
    let blocks = vec![
        (coord(-1, 0, 2), vec![1; 10]),
        (coord(3, -4, 5), vec![2; 20]),
    ];
    {
        let store = Store::open(&dir.db())?;
        store.append_cloud("t1", 3, frame(1, 1), b"early")?;
        store.checkpoint("t1", &checkpoint(3, frame(1, 1), &blocks, true))?;
        store.append_cloud("t1", 3, frame(1, 2), b"c2")?;
        store.append_cloud("t1", 3, frame(1, 3), b"c3")?;
        store.put_fruits("t1", 3, b"fruits")?;
        store.put_fruits("t0", 1, b"other")?;
    }
    let store = Store::open(&dir.db())?;
    let (trolleys, fruits) = store.load()?;
    let expected = StoredTrolley {
        tid: "t1".into(),
        epoch: 3,
        frame: frame(1, 1),
        meta: b"meta".to_vec(),
        blocks,
        clouds: vec![(frame(1, 2), b"c2".to_vec()), (frame(1, 3), b"c3".to_vec())],
    };
    assert_eq!(trolleys, vec![expected]);
    let tids: Vec<_> = fruits.iter().map(|f| (f.tid.as_str(), f.epoch)).collect();
    assert_eq!(tids, vec![("t0", 1), ("t1", 3)]);
    assert_eq!(fruits[1].bytes, b"fruits");
    Ok(())
}

#[test]
fn incremental_checkpoint_upserts_only_given_blocks() -> TestResult {
    let dir = TempDir::new("incremental");
    let store = Store::open(&dir.db())?;
    let first = vec![(coord(0, 0, 0), vec![1]), (coord(1, 0, 0), vec![2])];
    store.checkpoint("t1", &checkpoint(1, frame(1, 1), &first, true))?;
    let changed = vec![(coord(1, 0, 0), vec![20]), (coord(0, 0, 1), vec![3])];
    store.checkpoint("t1", &checkpoint(1, frame(1, 2), &changed, false))?;
    let trolley = only_trolley(&store)?;
    let expected = vec![
        (coord(0, 0, 0), vec![1]),
        (coord(0, 0, 1), vec![3]),
        (coord(1, 0, 0), vec![20]),
    ];
    assert_eq!(trolley.blocks, expected);
    assert_eq!(trolley.frame, frame(1, 2));
    Ok(())
}

#[test]
fn full_checkpoint_replaces_all_blocks_and_clouds() -> TestResult {
    let dir = TempDir::new("full");
    let store = Store::open(&dir.db())?;
    let first = vec![(coord(0, 0, 0), vec![1]), (coord(1, 0, 0), vec![2])];
    store.checkpoint("t1", &checkpoint(1, frame(1, 1), &first, false))?;
    store.checkpoint("t2", &checkpoint(1, frame(1, 1), &first, false))?;
    store.append_cloud("t1", 1, frame(9, 9), b"newer than the checkpoint")?;
    let replacement = vec![(coord(5, 5, 5), vec![5])];
    store.checkpoint("t1", &checkpoint(2, frame(2, 1), &replacement, true))?;
    let (trolleys, _) = store.load()?;
    assert_eq!(trolleys[0].tid, "t1");
    assert_eq!(trolleys[0].blocks, replacement);
    assert!(trolleys[0].clouds.is_empty());
    assert_eq!(trolleys[1].blocks, first, "another trolley's blocks stay");
    Ok(())
}

#[test]
fn checkpoint_drops_covered_clouds_and_keeps_newer_in_order() -> TestResult {
    let dir = TempDir::new("clouds");
    let store = Store::open(&dir.db())?;
    store.checkpoint("t1", &checkpoint(1, frame(0, 0), &[], false))?;
    for (key, bytes) in [
        (frame(2, 1), b"d"),
        (frame(1, 99), b"c"),
        (frame(1, 5), b"b"),
        (frame(1, 4), b"a"),
    ] {
        store.append_cloud("t1", 1, key, bytes)?;
    }
    store.append_cloud("t2", 1, frame(1, 1), b"other trolley")?;
    store.checkpoint("t1", &checkpoint(1, frame(1, 5), &[], false))?;
    let trolley = only_trolley(&store)?;
    let expected = vec![(frame(1, 99), b"c".to_vec()), (frame(2, 1), b"d".to_vec())];
    assert_eq!(trolley.clouds, expected);
    Ok(())
}

#[test]
fn stale_epoch_is_refused_and_nothing_written() -> TestResult {
    let dir = TempDir::new("stale");
    let store = Store::open(&dir.db())?;
    let blocks = vec![(coord(0, 0, 0), vec![1])];
    store.checkpoint("t1", &checkpoint(5, frame(1, 1), &blocks, true))?;
    store.put_fruits("t1", 5, b"new")?;
    let before = store.load()?;
    let totals = store.totals();

    let old_blocks = vec![(coord(0, 0, 0), vec![0]), (coord(7, 7, 7), vec![7])];
    let refused = [
        store.append_cloud("t1", 4, frame(2, 1), b"old"),
        store.checkpoint("t1", &checkpoint(4, frame(2, 2), &old_blocks, true)),
        store.put_fruits("t1", 4, b"old"),
    ];
    for result in refused {
        assert!(
            matches!(
                result,
                Err(StoreError::Stale {
                    stored_epoch: 5,
                    epoch: 4,
                    ..
                })
            ),
            "{result:?}"
        );
    }
    assert_eq!(store.load()?, before);
    assert_eq!(store.totals(), totals);
    store.append_cloud("t1", 5, frame(2, 1), b"same epoch")?;
    store.checkpoint("t1", &checkpoint(6, frame(2, 1), &[], false))?;
    Ok(())
}

#[test]
fn clouds_without_a_checkpoint_are_not_loaded() -> TestResult {
    let dir = TempDir::new("no-checkpoint");
    let store = Store::open(&dir.db())?;
    store.append_cloud("t1", 1, frame(1, 1), b"orphan")?;
    let (trolleys, fruits) = store.load()?;
    assert!(trolleys.is_empty());
    assert!(fruits.is_empty());
    Ok(())
}

#[test]
fn forget_removes_everything_of_the_trolley() -> TestResult {
    let dir = TempDir::new("forget");
    let store = Store::open(&dir.db())?;
    let blocks = vec![(coord(0, 0, 0), vec![1])];
    for tid in ["t1", "t2"] {
        store.checkpoint(tid, &checkpoint(1, frame(1, 1), &blocks, true))?;
        store.append_cloud(tid, 1, frame(1, 2), b"cloud")?;
        store.put_fruits(tid, 1, b"fruits")?;
    }
    store.forget("t1")?;
    let (trolleys, fruits) = store.load()?;
    assert_eq!(trolleys.len(), 1);
    assert_eq!(trolleys[0].tid, "t2");
    assert_eq!(trolleys[0].clouds.len(), 1);
    assert_eq!(fruits.len(), 1);
    // A new checkpoint of t1 finds no leftover blocks or clouds.
    store.checkpoint("t1", &checkpoint(1, frame(1, 0), &[], false))?;
    let (trolleys, _) = store.load()?;
    assert!(trolleys[0].blocks.is_empty() && trolleys[0].clouds.is_empty());
    Ok(())
}

#[test]
fn second_open_of_the_same_file_is_locked() -> TestResult {
    let dir = TempDir::new("locked");
    let store = Store::open(&dir.db())?;
    let second = Store::open(&dir.db());
    assert!(
        matches!(second, Err(StoreError::Locked { .. })),
        "{second:?}"
    );
    let message = second.err().map(|e| e.to_string()).unwrap_or_default();
    assert!(message.contains("another planner already uses this store"));
    drop(store);
    Store::open(&dir.db())?;
    Ok(())
}

#[test]
fn another_format_version_is_refused() -> TestResult {
    let dir = TempDir::new("format");
    let path = dir.db();
    drop(Store::open(&path)?);
    {
        let db = Database::create(&path).map_err(|e| StoreError::Db(e.to_string()))?;
        let txn = db.begin_write()?;
        txn.open_table(FORMAT)?
            .insert(FORMAT_KEY, FORMAT_VERSION + 1)?;
        txn.commit()?;
    }
    let refused = Store::open(&path);
    assert!(
        matches!(
            refused,
            Err(StoreError::Format {
                found: 2,
                expected: 1,
                ..
            })
        ),
        "{refused:?}"
    );
    Ok(())
}

#[test]
fn a_redb_file_without_format_record_is_refused() -> TestResult {
    let dir = TempDir::new("foreign");
    let path = dir.db();
    std::fs::create_dir_all(dir.0.join("state")).map_err(|e| StoreError::Db(e.to_string()))?;
    {
        let db = Database::create(&path).map_err(|e| StoreError::Db(e.to_string()))?;
        let txn = db.begin_write()?;
        txn.open_table(FRUITS)?.insert("t1", (1, b"x".as_slice()))?;
        txn.commit()?;
    }
    let refused = Store::open(&path);
    assert!(
        matches!(refused, Err(StoreError::Foreign { .. })),
        "{refused:?}"
    );
    Ok(())
}

#[test]
fn totals_count_transactions_and_bytes() -> TestResult {
    let dir = TempDir::new("totals");
    let store = Store::open(&dir.db())?;
    assert_eq!(store.totals(), WriteTotals::default());
    store.append_cloud("t1", 1, frame(1, 1), &[0; 1000])?;
    let after_cloud = store.totals();
    assert_eq!(after_cloud.transactions, 1);
    // Key: tid with its length prefix, two u64; value: the bytes.
    assert!((1000 + 2 + 16..1000 + 2 + 16 + 8).contains(&after_cloud.bytes));
    let blocks = vec![
        (coord(0, 0, 0), vec![0; 100]),
        (coord(0, 0, 1), vec![0; 100]),
    ];
    store.checkpoint("t1", &checkpoint(1, frame(1, 1), &blocks, false))?;
    store.forget("t1")?;
    let totals = store.totals();
    assert_eq!(totals.transactions, 3);
    assert!(totals.bytes >= after_cloud.bytes + 2 * (100 + 12) + 4 + 24);
    Ok(())
}

#[test]
fn a_batch_is_one_transaction_and_loads_as_its_writes_one_by_one() -> TestResult {
    let blocks = vec![(coord(0, 0, 0), vec![1]), (coord(0, 0, 1), vec![2])];
    let later = vec![(coord(0, 0, 1), vec![3])];
    let writes = [
        Write::Checkpoint {
            tid: "t1",
            checkpoint: checkpoint(2, frame(1, 1), &blocks, true),
        },
        Write::Cloud {
            tid: "t1",
            epoch: 2,
            frame: frame(1, 2),
            bytes: b"c2",
        },
        Write::Cloud {
            tid: "t1",
            epoch: 2,
            frame: frame(1, 3),
            bytes: b"c3",
        },
        Write::Checkpoint {
            tid: "t1",
            checkpoint: checkpoint(2, frame(1, 2), &later, false),
        },
        Write::Fruits {
            tid: "t1",
            epoch: 2,
            bytes: b"fruits",
        },
    ];
    let dir = TempDir::new("batch");
    let batched = Store::open(&dir.db())?;
    let outcomes = batched.write_all(&writes)?;
    assert!(outcomes.iter().all(Result::is_ok), "{outcomes:?}");
    assert_eq!(batched.totals().transactions, 1);

    let dir = TempDir::new("one-by-one");
    let single = Store::open(&dir.db())?;
    for write in &writes {
        single.write_all(std::slice::from_ref(write))?;
    }
    assert_eq!(single.totals().transactions, 5);
    assert_eq!(batched.totals().bytes, single.totals().bytes);
    assert_eq!(batched.load()?, single.load()?);
    // Frame 3's cloud outlives the checkpoint at frame 2.
    let trolley = only_trolley(&batched)?;
    assert_eq!(trolley.clouds, vec![(frame(1, 3), b"c3".to_vec())]);
    Ok(())
}

#[test]
fn a_stale_write_in_a_batch_is_refused_and_the_others_are_written() -> TestResult {
    let dir = TempDir::new("batch-stale");
    let store = Store::open(&dir.db())?;
    store.checkpoint("t1", &checkpoint(5, frame(1, 1), &[], true))?;
    let outcomes = store.write_all(&[
        Write::Cloud {
            tid: "t1",
            epoch: 4,
            frame: frame(1, 2),
            bytes: b"stale owner",
        },
        Write::Cloud {
            tid: "t1",
            epoch: 5,
            frame: frame(1, 3),
            bytes: b"owner",
        },
    ])?;
    assert!(
        matches!(
            outcomes[0],
            Err(StoreError::Stale {
                stored_epoch: 5,
                epoch: 4,
                ..
            })
        ),
        "{outcomes:?}"
    );
    assert!(outcomes[1].is_ok(), "{outcomes:?}");
    let trolley = only_trolley(&store)?;
    assert_eq!(trolley.clouds, vec![(frame(1, 3), b"owner".to_vec())]);
    Ok(())
}
