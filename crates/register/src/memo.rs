//! The map's occupancy in a box around the scan, read from the map once per voxel.
//!
//! ICP asks about the same voxels again and again (every iteration re-searches each point's
//! neighbourhood, and neighbouring planes share voxels); a map lookup is a hash probe, a lookup
//! here two bit tests.

use glasshouse_roimap::{Occupancy, RoiMap, VoxelKey};

/// Boxes larger than this many voxels (16 Mi: 4 MiB of bits) are not cached: lookups go to
/// the map.
const MAX_VOXELS: usize = 1 << 24;

pub(crate) struct OccupancyMemo {
    lo: VoxelKey,
    size: [usize; 3],
    /// One bit per voxel of the box, x fastest: whether the map was asked, and its answer.
    asked: Vec<u64>,
    occupied: Vec<u64>,
}

impl OccupancyMemo {
    /// A memo over the box of `keys` grown by `margin` voxels on every side; an empty one (every
    /// lookup goes to the map) when there are no keys or the box is too large.
    pub fn around(keys: impl Iterator<Item = VoxelKey>, margin: i32) -> Self {
        let mut bounds: Option<(VoxelKey, VoxelKey)> = None;
        for k in keys {
            let (lo, hi) = bounds.get_or_insert((k, k));
            *lo = VoxelKey::new(lo.x.min(k.x), lo.y.min(k.y), lo.z.min(k.z));
            *hi = VoxelKey::new(hi.x.max(k.x), hi.y.max(k.y), hi.z.max(k.z));
        }
        let empty = Self {
            lo: VoxelKey::new(0, 0, 0),
            size: [0; 3],
            asked: Vec::new(),
            occupied: Vec::new(),
        };
        let Some((lo, hi)) = bounds else {
            return empty;
        };
        let span =
            |a: i32, b: i32| (i64::from(b) - i64::from(a) + 1 + 2 * i64::from(margin)) as usize;
        let size = [span(lo.x, hi.x), span(lo.y, hi.y), span(lo.z, hi.z)];
        let voxels = size.iter().try_fold(1usize, |n, &s| n.checked_mul(s));
        match voxels {
            Some(n) if n <= MAX_VOXELS => Self {
                lo: lo.offset(-margin, -margin, -margin),
                size,
                asked: vec![0; n.div_ceil(64)],
                occupied: vec![0; n.div_ceil(64)],
            },
            _ => empty,
        }
    }

    fn index(&self, k: VoxelKey) -> Option<usize> {
        let local = |v: i32, lo: i32, size: usize| {
            usize::try_from(i64::from(v) - i64::from(lo))
                .ok()
                .filter(|&i| i < size)
        };
        let x = local(k.x, self.lo.x, self.size[0])?;
        let y = local(k.y, self.lo.y, self.size[1])?;
        let z = local(k.z, self.lo.z, self.size[2])?;
        Some((z * self.size[1] + y) * self.size[0] + x)
    }

    /// The memo's offsets of the key offsets `offsets` (x fastest).
    pub fn linear_offsets(&self, offsets: &[(i32, i32, i32)]) -> Vec<isize> {
        let (sx, sy) = (self.size[0] as isize, self.size[1] as isize);
        let linear =
            |&(dx, dy, dz): &(i32, i32, i32)| (dz as isize * sy + dy as isize) * sx + dx as isize;
        offsets.iter().map(linear).collect()
    }

    /// The index of `k` when every key within `radius` voxels of it (per axis) is in the box:
    /// then `index + linear offset` is the index of each of them.
    pub fn index_with_room(&self, k: VoxelKey, radius: i32) -> Option<usize> {
        let lo = k.offset(-radius, -radius, -radius);
        let hi = k.offset(radius, radius, radius);
        self.index(hi)?;
        self.index(lo)?;
        self.index(k)
    }

    /// Whether the map's voxel `k` is occupied.
    pub fn occupied(&mut self, map: &RoiMap, k: VoxelKey) -> bool {
        match self.index(k) {
            Some(i) => self.occupied_at(map, i, k),
            None => map.occupancy(k) == Occupancy::Occupied,
        }
    }

    /// Whether the map's voxel `k`, at index `i` of the box, is occupied.
    pub fn occupied_at(&mut self, map: &RoiMap, i: usize, k: VoxelKey) -> bool {
        let (word, bit) = (i / 64, 1u64 << (i % 64));
        if self.asked[word] & bit == 0 {
            self.asked[word] |= bit;
            if map.occupancy(k) == Occupancy::Occupied {
                self.occupied[word] |= bit;
            }
        }
        self.occupied[word] & bit != 0
    }
}
