//! The solid (occupied or ROI) voxels a planner has published in MapUpdates, as one bit mask per
//! 8³ cell (the map's block, the unit its changes arrive in): a scan frees hundreds of thousands
//! of voxels, block by block, and nearly none of them was ever published, so each is checked
//! against its cell's mask (one lookup per run of voxels in the same cell). A planner restored
//! from a snapshot takes the map's solid masks block by block instead of voxel by voxel.

use std::collections::HashMap;

use glasshouse_roimap::{KeyBuildHasher, VoxelKey};

/// log2 of a cell's edge in voxels: the map's block edge.
const CELL_SHIFT: i32 = 3;

/// The cell of `key` and the voxel's bit in the cell's mask (`z * 64 + y * 8 + x`).
fn cell_and_bit(key: VoxelKey) -> (VoxelKey, usize) {
    let cell = VoxelKey::new(
        key.x >> CELL_SHIFT,
        key.y >> CELL_SHIFT,
        key.z >> CELL_SHIFT,
    );
    let local = |v: i32| (v & 7) as usize;
    (cell, local(key.z) * 64 + local(key.y) * 8 + local(key.x))
}

#[derive(Clone, Debug, Default)]
pub(crate) struct PublishedSolid {
    /// Published voxels per cell, bit `z * 64 + y * 8 + x` (cells with none have no entry).
    per_cell: HashMap<VoxelKey, [u64; 8], KeyBuildHasher>,
    /// The last cell looked up and whether it holds a published voxel (reset on any change).
    last_cell: Option<(VoxelKey, bool)>,
}

impl PublishedSolid {
    /// Everything published at once: each cell's mask of solid voxels, as
    /// [`glasshouse_roimap::RoiMap::solid_blocks`] gives them.
    pub(crate) fn from_cells(cells: impl IntoIterator<Item = (VoxelKey, [u64; 8])>) -> Self {
        let per_cell = cells
            .into_iter()
            .filter(|(_, mask)| mask.iter().any(|&w| w != 0))
            .collect();
        Self {
            per_cell,
            last_cell: None,
        }
    }

    /// Records `key` as published solid.
    pub(crate) fn insert(&mut self, key: VoxelKey) {
        let (cell, bit) = cell_and_bit(key);
        self.per_cell.entry(cell).or_default()[bit >> 6] |= 1 << (bit & 63);
        self.last_cell = None;
    }

    /// The published voxels of one cell (the map's block coordinate, a key ÷ 8).
    pub(crate) fn cell(&self, cell: VoxelKey) -> [u64; 8] {
        self.per_cell.get(&cell).copied().unwrap_or_default()
    }

    /// Forgets `key`; whether it was published solid.
    pub(crate) fn remove(&mut self, key: VoxelKey) -> bool {
        let (cell, bit) = cell_and_bit(key);
        if let Some((last, false)) = self.last_cell {
            if last == cell {
                return false;
            }
        }
        let Some(mask) = self.per_cell.get_mut(&cell) else {
            self.last_cell = Some((cell, false));
            return false;
        };
        let (word, flag) = (bit >> 6, 1u64 << (bit & 63));
        let was = mask[word] & flag != 0;
        mask[word] &= !flag;
        if mask.iter().all(|&w| w == 0) {
            self.per_cell.remove(&cell);
            self.last_cell = None;
        }
        was
    }

    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        let ones = |m: &[u64; 8]| m.iter().map(|w| w.count_ones() as usize).sum::<usize>();
        self.per_cell.values().map(ones).sum()
    }
}

impl FromIterator<VoxelKey> for PublishedSolid {
    fn from_iter<I: IntoIterator<Item = VoxelKey>>(keys: I) -> Self {
        let mut published = Self::default();
        for key in keys {
            published.insert(key);
        }
        published
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k(x: i32, y: i32, z: i32) -> VoxelKey {
        VoxelKey::new(x, y, z)
    }

    /// Voxels in four cells, two of them in one cell, on both sides of 0.
    fn spread_keys() -> [VoxelKey; 5] {
        [
            k(0, 0, 0),
            k(7, 7, 7),
            k(8, 0, 0),
            k(-1, 0, 0),
            k(-9, 3, 100),
        ]
    }

    #[test]
    fn removes_exactly_what_was_inserted_across_cells() {
        let inserted = spread_keys();
        let mut published: PublishedSolid = inserted.into_iter().collect();
        published.insert(k(0, 0, 0)); // twice: counted once
        assert_eq!(published.len(), 5);
        // Neighbours in the same cells and in empty ones were never published.
        for key in [
            k(1, 0, 0),
            k(9, 0, 0),
            k(-2, 0, 0),
            k(-8, 3, 100),
            k(100, 0, 0),
        ] {
            assert!(!published.remove(key), "{key:?}");
        }
        // Removing the last voxel of a cell empties it, and the cell cache follows.
        assert!(published.remove(k(8, 0, 0)));
        assert!(!published.remove(k(8, 0, 0)));
        published.insert(k(9, 1, 1));
        assert!(
            published.remove(k(9, 1, 1)),
            "a cell emptied and filled again"
        );
        for key in [k(0, 0, 0), k(7, 7, 7), k(-1, 0, 0), k(-9, 3, 100)] {
            assert!(published.remove(key), "{key:?}");
        }
        assert_eq!(published.len(), 0);
        assert!(published.per_cell.is_empty());
    }

    #[test]
    fn cells_from_the_map_are_its_solid_voxels() {
        let keys = spread_keys();
        let by_voxel: PublishedSolid = keys.into_iter().collect();
        let cells = by_voxel
            .per_cell
            .clone()
            .into_iter()
            .chain([(k(5, 5, 5), [0; 8])]);
        let mut by_cell = PublishedSolid::from_cells(cells);
        assert_eq!(
            by_cell.per_cell, by_voxel.per_cell,
            "an empty cell is not kept"
        );
        for key in keys {
            assert!(by_cell.remove(key), "{key:?}");
        }
        assert_eq!(by_cell.len(), 0);
    }
}
