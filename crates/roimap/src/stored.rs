//! The map as a store keeps it: a header (configuration and scan count) and one record per
//! 8×8×8 block, so that a checkpoint writes only the blocks changed since the last one.
//!
//! A block record is the snapshot's block encoding (its coordinate as 3 × i32, its known mask,
//! the occupancy and ROI log-odds as one value, a palette or a flat array; see
//! [`crate::snapshot`]), uncompressed: most blocks of a glasshouse map are one value or a small
//! palette, tens of bytes. Blocks are never removed from a map (a known voxel stays known), so a
//! later record of a block replaces the earlier one and a map is its header plus the newest
//! record of each block.

use crate::grid::mask_count;
use crate::snapshot::{Cursor, SnapshotError};
use crate::{ChangeLog, RoiMap, VoxelKey};

impl RoiMap {
    /// The configuration and scan count, as [`RoiMap::from_stored`] reads them.
    pub fn stored_header(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(64);
        self.write_header(&mut out);
        out
    }

    /// Every block changed after the map had taken `scans` scans ([`RoiMap::scans_inserted`];
    /// 0: every known block), as its block coordinate and record. What a block held at `scans`
    /// and was not changed since is left out, so a store that kept the records of then and
    /// takes these holds the map of now.
    pub fn stored_blocks_since(&self, scans: u64) -> Vec<(VoxelKey, Vec<u8>)> {
        let blocks = &self.store.blocks;
        (0..blocks.len())
            .filter(|&i| {
                let b = &blocks[i];
                mask_count(&b.known) > 0 && (scans == 0 || b.changed_at_scan > scans)
            })
            .map(|i| {
                let mut record = Vec::with_capacity(128);
                self.write_block(i, &mut record);
                (self.store.coords[i], record)
            })
            .collect()
    }

    /// The map of a header and block records ([`RoiMap::stored_header`],
    /// [`RoiMap::stored_blocks_since`]), each block once. A damaged record, or a block given
    /// twice, is an error naming it; nothing is half-loaded.
    pub fn from_stored<'a>(
        header: &[u8],
        blocks: impl IntoIterator<Item = &'a [u8]>,
    ) -> Result<RoiMap, SnapshotError> {
        let mut c = Cursor::new(header);
        let mut map = Self::read_header(&mut c)?;
        c.finished()?;
        let mut log = ChangeLog::default();
        for record in blocks {
            let mut c = Cursor::new(record);
            map.read_block(&mut c, &mut log)?;
            c.finished()?;
        }
        map.refresh_derived(&log);
        Ok(map)
    }
}

/// The block coordinate a stored record names (its first 12 bytes), without decoding the rest.
pub fn stored_block_coord(record: &[u8]) -> Option<VoxelKey> {
    let int = |at: usize| {
        let b = record.get(at..at + 4)?;
        Some(i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    Some(VoxelKey::new(int(0)?, int(4)?, int(8)?))
}
