//! A map's changes since a scan count, for a copy that holds the map as it was then (a standby
//! replica refreshing from its owner): the blocks changed after that scan, whole, framed like a
//! snapshot (kind 1, `delta`; [`crate::snapshot`]).
//!
//! Body (LZ4, as a snapshot's): the configuration and scan count of the map now (a snapshot's
//! first fields), the scan count the delta starts from (`base`), the block count u32, then each
//! block changed after `base` in a snapshot's block encoding. Blocks are never removed and a
//! known voxel stays known, so a map after `base` scans that takes these blocks holds the map of
//! now, voxel for voxel. A delta applies only to a map that has taken exactly `base` scans
//! ([`SnapshotError::DeltaBase`]); whether that map is the same map as the writer's at `base`
//! is the caller's to know (the same owner, the same term).

use std::collections::HashSet;
use std::io::Write;

use crate::grid::{mask_count, Mask, EMPTY};
use crate::snapshot::{
    frame, unframe, unpack, BlockRecord, Cursor, SnapshotError, HEADER_BYTES, KIND_DELTA,
};
use crate::{ChangeLog, RoiMap};

impl RoiMap {
    /// Writes the blocks changed after the map had taken `base_scans` scans as a delta; a base
    /// later than the map's own scan count is [`SnapshotError::DeltaBase`].
    pub fn write_delta(&self, base_scans: u64, w: impl Write) -> Result<(), SnapshotError> {
        if base_scans > self.scans_inserted {
            return Err(SnapshotError::DeltaBase {
                base: base_scans,
                scans: self.scans_inserted,
            });
        }
        let blocks = &self.store.blocks;
        let changed: Vec<usize> = (0..blocks.len())
            .filter(|&i| mask_count(&blocks[i].known) > 0 && blocks[i].changed_at_scan > base_scans)
            .collect();
        let mut body = Vec::with_capacity(80 + changed.len() * 128);
        self.write_header(&mut body);
        body.extend_from_slice(&base_scans.to_le_bytes());
        body.extend_from_slice(&(changed.len() as u32).to_le_bytes());
        for i in changed {
            self.write_block(i, &mut body);
        }
        let mut w = w;
        frame(
            KIND_DELTA,
            &lz4_flex::block::compress_prepend_size(&body),
            &mut w,
        )
    }

    /// Whether `bytes` are framed as a delta (magic and kind; nothing else is checked).
    pub fn is_delta(bytes: &[u8]) -> bool {
        bytes.len() >= HEADER_BYTES
            && &bytes[..4] == b"GHRM"
            && u16::from_le_bytes([bytes[6], bytes[7]]) == KIND_DELTA
    }

    /// Checks a delta's framing and checksum without decoding its body.
    pub fn check_delta(bytes: &[u8]) -> Result<(), SnapshotError> {
        unframe(KIND_DELTA, bytes).map(|_| ())
    }

    /// Applies a delta [`RoiMap::write_delta`] wrote: the map must have taken exactly the scans
    /// the delta starts from and have the writer's configuration. Every block is read and
    /// checked before the first is applied, so on an error nothing changes.
    pub fn apply_delta(&mut self, bytes: &[u8]) -> Result<(), SnapshotError> {
        let body = unpack(unframe(KIND_DELTA, bytes)?)?;
        let mut c = Cursor::new(&body);
        let now = Self::read_header(&mut c)?;
        if now.config != self.config {
            return Err(SnapshotError::Corrupt(
                "the delta's map configuration differs from the map's".into(),
            ));
        }
        let base = c.u64()?;
        if base != self.scans_inserted || now.scans_inserted < base {
            return Err(SnapshotError::DeltaBase {
                base,
                scans: self.scans_inserted,
            });
        }
        let count = c.u32()? as usize;
        // A block record takes more than 64 bytes: a damaged count reserves no more than that.
        let mut records = Vec::with_capacity(count.min(body.len() / 64));
        let mut seen = HashSet::with_capacity(records.capacity());
        for _ in 0..count {
            let record = BlockRecord::read(&mut c)?;
            if !seen.insert(record.key) {
                return Err(SnapshotError::Corrupt(format!(
                    "block {:?} twice",
                    record.key
                )));
            }
            records.push(record);
        }
        c.finished()?;
        let mut log = ChangeLog::with_capacity(records.len());
        for record in records {
            self.replace_block(record, now.scans_inserted, &mut log);
        }
        self.scans_inserted = now.scans_inserted;
        self.refresh_derived(&log);
        Ok(())
    }

    /// Puts `record` in place of its block (created when new), keeping the counts and noting
    /// the voxels whose state changed for the derived sets.
    fn replace_block(&mut self, record: BlockRecord, changed_at_scan: u64, log: &mut ChangeLog) {
        let thr = self.config.roi_threshold_logodds;
        let bi = self.store.get_or_create(record.key);
        let b = &mut self.store.blocks[bi];
        let occupied = record.occ.mask_where(&record.known, |v| v > 0.0);
        let roi_mask = record.roi.mask_where(&record.known, |v| v >= thr);
        let (mut state, mut roi_flipped): (Mask, Mask) = (EMPTY, EMPTY);
        for w in 0..8 {
            roi_flipped[w] = roi_mask[w] ^ b.roi_mask[w];
            state[w] =
                (record.known[w] ^ b.known[w]) | (occupied[w] ^ b.occupied[w]) | roi_flipped[w];
        }
        self.known_count = self.known_count + mask_count(&record.known) - mask_count(&b.known);
        self.occupied_count = self.occupied_count + mask_count(&occupied) - mask_count(&b.occupied);
        b.known = record.known;
        b.occupied = occupied;
        b.roi_mask = roi_mask;
        b.occ = record.occ;
        b.roi = record.roi;
        b.changed_at_scan = changed_at_scan;
        log.note(bi as u32, &state, &roi_flipped);
    }
}
