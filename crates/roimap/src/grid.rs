//! Blocked sparse storage: 8×8×8-voxel blocks with flat arrays, found through a hash map keyed by
//! block coordinate.
//!
//! Inside a block, voxel `(x, y, z)` (each `0..8`) has local index `z * 64 + y * 8 + x`, so a
//! 512-bit mask is eight `u64` words, one z-slice each, bit `y * 8 + x`. The same layout is used by
//! the per-scan grid of the insertion and by the frontier computation, whose 6-neighbour tests are
//! word shifts.

use std::collections::HashMap;

use crate::values::Values;
use crate::{KeyBuildHasher, VoxelKey};

pub(crate) const BLOCK_SHIFT: i32 = 3;
pub(crate) const BLOCK_EDGE: i32 = 1 << BLOCK_SHIFT;
pub(crate) const BLOCK_VOXELS: usize = 512;

/// One bit per voxel of a block.
pub(crate) type Mask = [u64; 8];
pub(crate) const EMPTY: Mask = [0; 8];

/// Block coordinate of a voxel key (floor division by 8).
pub(crate) fn block_of(key: VoxelKey) -> VoxelKey {
    VoxelKey::new(
        key.x >> BLOCK_SHIFT,
        key.y >> BLOCK_SHIFT,
        key.z >> BLOCK_SHIFT,
    )
}

/// Local index `z * 64 + y * 8 + x` of a voxel inside its block.
pub(crate) fn local_of(key: VoxelKey) -> usize {
    let m = BLOCK_EDGE - 1;
    ((key.z & m) as usize) << 6 | ((key.y & m) as usize) << 3 | (key.x & m) as usize
}

/// Voxel key of local index `l` in block `b`.
pub(crate) fn key_at(b: VoxelKey, l: usize) -> VoxelKey {
    VoxelKey::new(
        (b.x << BLOCK_SHIFT) | (l & 7) as i32,
        (b.y << BLOCK_SHIFT) | ((l >> 3) & 7) as i32,
        (b.z << BLOCK_SHIFT) | (l >> 6) as i32,
    )
}

pub(crate) fn mask_is_empty(m: &Mask) -> bool {
    m.iter().all(|&w| w == 0)
}

pub(crate) fn mask_count(m: &Mask) -> usize {
    m.iter().map(|w| w.count_ones() as usize).sum()
}

/// Calls `f(local_index)` for every set bit, in increasing order.
pub(crate) fn for_each_bit(m: &Mask, mut f: impl FnMut(usize)) {
    for (w, &word) in m.iter().enumerate() {
        let mut bits = word;
        while bits != 0 {
            let b = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            f(w * 64 + b);
        }
    }
}

pub(crate) fn mask_test(m: &Mask, l: usize) -> bool {
    m[l >> 6] >> (l & 63) & 1 != 0
}

pub(crate) fn mask_set(m: &mut Mask, l: usize, on: bool) {
    let bit = 1u64 << (l & 63);
    if on {
        m[l >> 6] |= bit;
    } else {
        m[l >> 6] &= !bit;
    }
}

/// Voxels whose column `x` is 0 / 7, and whose row `y` is 0 / 7, within one z-slice word.
const COL0: u64 = 0x0101_0101_0101_0101;
const COL7: u64 = 0x8080_8080_8080_8080;
const ROW0: u64 = 0xFF;
const ROW7: u64 = 0xFF << 56;

/// Mask of the voxels with a 6-neighbour in `s`, given `s` of this block and of the six face
/// neighbours in the order −x, +x, −y, +y, −z, +z.
pub(crate) fn has_neighbour_in(s: &Mask, n: &[Mask; 6]) -> Mask {
    let [nxm, nxp, nym, nyp, nzm, nzp] = n;
    let mut out = [0u64; 8];
    for w in 0..8 {
        let sw = s[w];
        // Neighbour at x+1: own bit x+1, or bit x=0 of the +x block for x=7.
        let xp = ((sw >> 1) & !COL7) | ((nxp[w] & COL0) << 7);
        let xm = ((sw << 1) & !COL0) | ((nxm[w] & COL7) >> 7);
        let yp = (sw >> 8) | ((nyp[w] & ROW0) << 56);
        let ym = (sw << 8) | ((nym[w] & ROW7) >> 56);
        let zp = if w < 7 { s[w + 1] } else { nzp[0] };
        let zm = if w > 0 { s[w - 1] } else { nzm[7] };
        out[w] = xp | xm | yp | ym | zp | zm;
    }
    out
}

/// Which faces of the block a mask touches, in the order −x, +x, −y, +y, −z, +z.
pub(crate) fn faces_touched(m: &Mask) -> [bool; 6] {
    let any = m.iter().fold(0u64, |a, &w| a | w);
    [
        any & COL0 != 0,
        any & COL7 != 0,
        any & ROW0 != 0,
        any & ROW7 != 0,
        m[0] != 0,
        m[7] != 0,
    ]
}

/// Face neighbour offsets in the order of [`has_neighbour_in`]: the map's 6-neighbourhood.
pub(crate) const FACE_OFFSETS: [(i32, i32, i32); 6] = crate::NEIGHBOURS_6;

/// One block of voxels.
#[derive(Clone)]
pub(crate) struct Block {
    /// Occupancy log-odds (0 for unknown voxels).
    pub occ: Values,
    /// ROI log-odds (0 for unknown voxels and voxels never hit as an end point).
    pub roi: Values,
    /// Voxels ever updated.
    pub known: Mask,
    /// Occupancy log-odds > 0.
    pub occupied: Mask,
    /// ROI log-odds >= threshold.
    pub roi_mask: Mask,
    /// ROI targets: `roi_mask`, or its voxels with an ROI face neighbour (`MapConfig::roi_target_needs_neighbour`).
    pub roi_target: Mask,
    /// Exploration-frontier voxels (free, unknown and occupied 6-neighbours).
    pub expl_frontier: Mask,
    /// ROI-frontier voxels (free, unknown and ROI-target 6-neighbours).
    pub roi_frontier: Mask,
    /// Changed since the last `take_changes`.
    pub dirty: Mask,
    /// The scan (1-based count of inserted scans) that last changed a voxel of this block.
    pub changed_at_scan: u64,
}

impl Block {
    pub(crate) fn new() -> Self {
        Self {
            occ: Values::default(),
            roi: Values::default(),
            known: EMPTY,
            occupied: EMPTY,
            roi_mask: EMPTY,
            roi_target: EMPTY,
            expl_frontier: EMPTY,
            roi_frontier: EMPTY,
            dirty: EMPTY,
            changed_at_scan: 0,
        }
    }
}

impl Block {
    /// ROI log-odds of local voxel `l`.
    pub(crate) fn roi_at(&self, l: usize) -> f32 {
        self.roi.get(l)
    }

    /// Occupancy log-odds of local voxel `l`.
    pub(crate) fn occ_at(&self, l: usize) -> f32 {
        self.occ.get(l)
    }

    /// The solid voxels: occupied (log-odds > 0) or ROI.
    pub(crate) fn solid(&self) -> Mask {
        std::array::from_fn(|w| self.occupied[w] | self.roi_mask[w])
    }
}

/// Blocks by coordinate. Blocks are never removed (voxels never become unknown again).
#[derive(Clone, Default)]
pub(crate) struct Storage {
    pub index: HashMap<VoxelKey, u32, KeyBuildHasher>,
    /// Boxed so that growing the vector moves pointers, and its spare capacity costs a pointer
    /// per slot rather than a block.
    #[allow(clippy::vec_box)]
    pub blocks: Vec<Box<Block>>,
    /// Block coordinate of each entry of `blocks`.
    pub coords: Vec<VoxelKey>,
}

impl Storage {
    pub(crate) fn find(&self, b: VoxelKey) -> Option<&Block> {
        self.index.get(&b).map(|&i| &*self.blocks[i as usize])
    }

    /// Room for `more` blocks (a snapshot being read states its count).
    pub(crate) fn reserve(&mut self, more: usize) {
        self.blocks.reserve(more);
        self.coords.reserve(more);
        self.index.reserve(more);
    }

    pub(crate) fn get_or_create(&mut self, b: VoxelKey) -> usize {
        if let Some(&i) = self.index.get(&b) {
            return i as usize;
        }
        let i = self.blocks.len();
        self.blocks.push(Box::new(Block::new()));
        self.coords.push(b);
        self.index.insert(b, i as u32);
        i
    }

    /// The six face neighbours of block `b` (order of [`FACE_OFFSETS`]).
    pub(crate) fn face_neighbours(&self, b: VoxelKey) -> [Option<&Block>; 6] {
        FACE_OFFSETS.map(|(dx, dy, dz)| self.find(b.offset(dx, dy, dz)))
    }

    pub(crate) fn heap_bytes(&self) -> usize {
        self.blocks.len() * std::mem::size_of::<Block>()
            + self.blocks.capacity() * std::mem::size_of::<Box<Block>>()
            + self
                .blocks
                .iter()
                .map(|b| b.occ.heap_bytes() + b.roi.heap_bytes())
                .sum::<usize>()
            + self.coords.capacity() * std::mem::size_of::<VoxelKey>()
            + self.index.capacity() * (std::mem::size_of::<(VoxelKey, u32)>() + 1)
    }
}
