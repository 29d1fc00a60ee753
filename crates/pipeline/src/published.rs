//! The solid (occupied or ROI) voxels a planner has published in MapUpdates, counted per 8³ cell:
//! a scan frees hundreds of thousands of voxels, arriving block by block, and nearly none of them
//! was ever published, so each is first checked against its cell (one lookup per run of voxels in
//! the same cell) rather than against the whole set.

use std::collections::HashMap;

use glasshouse_roimap::{KeyBuildHasher, KeySet, VoxelKey};

/// log2 of a cell's edge in voxels: the map's block edge, the unit its changes arrive in.
const CELL_SHIFT: i32 = 3;

fn cell_of(key: VoxelKey) -> VoxelKey {
    VoxelKey::new(
        key.x >> CELL_SHIFT,
        key.y >> CELL_SHIFT,
        key.z >> CELL_SHIFT,
    )
}

#[derive(Clone, Debug, Default)]
pub(crate) struct PublishedSolid {
    voxels: KeySet,
    /// Published voxels per cell (cells with none have no entry).
    per_cell: HashMap<VoxelKey, u32, KeyBuildHasher>,
    /// The last cell looked up and whether it holds a published voxel (reset on any change).
    last_cell: Option<(VoxelKey, bool)>,
}

impl PublishedSolid {
    /// Records `key` as published solid.
    pub(crate) fn insert(&mut self, key: VoxelKey) {
        if self.voxels.insert(key) {
            *self.per_cell.entry(cell_of(key)).or_default() += 1;
            self.last_cell = None;
        }
    }

    /// Forgets `key`; whether it was published solid.
    pub(crate) fn remove(&mut self, key: VoxelKey) -> bool {
        let cell = cell_of(key);
        let occupied_cell = match self.last_cell {
            Some((last, any)) if last == cell => any,
            _ => {
                let any = self.per_cell.contains_key(&cell);
                self.last_cell = Some((cell, any));
                any
            }
        };
        if !occupied_cell || !self.voxels.remove(&key) {
            return false;
        }
        if let Some(count) = self.per_cell.get_mut(&cell) {
            *count -= 1;
            if *count == 0 {
                self.per_cell.remove(&cell);
            }
        }
        self.last_cell = None;
        true
    }

    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.voxels.len()
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

    #[test]
    fn removes_exactly_what_was_inserted_across_cells() {
        let inserted = [
            k(0, 0, 0),
            k(7, 7, 7),
            k(8, 0, 0),
            k(-1, 0, 0),
            k(-9, 3, 100),
        ];
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
}
