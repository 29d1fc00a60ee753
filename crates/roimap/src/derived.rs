//! State derived from the voxels and maintained as they change: the ROI set, the two frontier
//! sets (as per-block masks) and the ROI distance field.

use std::collections::{HashMap, VecDeque};

use nalgebra::Point3;

use crate::grid::{
    faces_touched, for_each_bit, has_neighbour_in, key_at, mask_count, mask_is_empty, mask_test,
    Block, Mask, EMPTY, FACE_OFFSETS,
};
use crate::{ChangeLog, KeyBuildHasher, KeySet, RoiMap, VoxelKey, NEIGHBOURS_26};

const FULL: Mask = [u64::MAX; 8];

/// Frontier masks of one block from its masks and its face neighbours' (`None` = no block: all
/// unknown, nothing occupied or ROI). Returns (exploration, ROI) frontier.
fn frontier_masks(b: &Block, n: [Option<&Block>; 6]) -> (Mask, Mask) {
    let mut free = EMPTY;
    let mut unknown = EMPTY;
    for w in 0..8 {
        free[w] = b.known[w] & !b.occupied[w];
        unknown[w] = !b.known[w];
    }
    if mask_is_empty(&free) {
        return (EMPTY, EMPTY);
    }
    let not_known = |m: &Mask| m.map(|w| !w);
    let n_unknown = n.map(|o| o.map_or(FULL, |b| not_known(&b.known)));
    let n_occ = n.map(|o| o.map_or(EMPTY, |b| b.occupied));
    let n_roi = n.map(|o| o.map_or(EMPTY, |b| b.roi_mask));
    let near_unknown = has_neighbour_in(&unknown, &n_unknown);
    let mut base = EMPTY;
    for w in 0..8 {
        base[w] = free[w] & near_unknown[w];
    }
    if mask_is_empty(&base) {
        return (EMPTY, EMPTY);
    }
    let near_occ = has_neighbour_in(&b.occupied, &n_occ);
    let near_roi = has_neighbour_in(&b.roi_mask, &n_roi);
    let mut expl = EMPTY;
    let mut roi = EMPTY;
    for w in 0..8 {
        expl[w] = base[w] & near_occ[w];
        roi[w] = base[w] & near_roi[w];
    }
    (expl, roi)
}

impl RoiMap {
    /// Updates the ROI set, the frontier masks and the distance field for the voxels in `log`.
    pub(crate) fn refresh_derived(&mut self, log: &ChangeLog) {
        if log.blocks.is_empty() {
            return;
        }
        // ROI set.
        let mut added = Vec::new();
        let mut removed = Vec::new();
        for (&bi, (_, roi_changed)) in &log.blocks {
            if mask_is_empty(roi_changed) {
                continue;
            }
            let b = &self.store.blocks[bi as usize];
            let bk = self.store.coords[bi as usize];
            for_each_bit(roi_changed, |l| {
                let k = key_at(bk, l);
                if mask_test(&b.roi_mask, l) {
                    added.push(k);
                } else {
                    removed.push(k);
                }
            });
        }
        for k in &added {
            self.roi_set.insert(*k);
        }
        for k in &removed {
            self.roi_set.remove(k);
        }
        // Frontiers: the changed blocks, and the face neighbours next to changed voxels.
        let mut todo = KeySet::default();
        for (&bi, (state, _)) in &log.blocks {
            let bk = self.store.coords[bi as usize];
            todo.insert(bk);
            for (touches, (dx, dy, dz)) in faces_touched(state).into_iter().zip(FACE_OFFSETS) {
                if touches {
                    todo.insert(bk.offset(dx, dy, dz));
                }
            }
        }
        for bk in todo {
            let Some(&bi) = self.store.index.get(&bk) else {
                continue; // no block: no free voxel, no frontier
            };
            let b = &self.store.blocks[bi as usize];
            let (expl, roi) = frontier_masks(b, self.store.face_neighbours(bk));
            let (old_expl, old_roi) = (b.expl_frontier, b.roi_frontier);
            self.expl_count = self.expl_count + mask_count(&expl) - mask_count(&old_expl);
            self.roi_front_count = self.roi_front_count + mask_count(&roi) - mask_count(&old_roi);
            if mask_is_empty(&expl) {
                self.expl_blocks.remove(&bk);
            } else {
                self.expl_blocks.insert(bk);
            }
            if mask_is_empty(&roi) {
                self.roi_front_blocks.remove(&bk);
            } else {
                self.roi_front_blocks.insert(bk);
            }
            let b = &mut self.store.blocks[bi as usize];
            b.expl_frontier = expl;
            b.roi_frontier = roi;
        }
        // Distance field.
        if !added.is_empty() || !removed.is_empty() {
            let res = self.config.resolution_m;
            let centre = |k: VoxelKey| {
                Point3::new(
                    (f64::from(k.x) + 0.5) * res,
                    (f64::from(k.y) + 0.5) * res,
                    (f64::from(k.z) + 0.5) * res,
                )
            };
            let roi_set = &self.roi_set;
            self.distance
                .update(&added, &removed, |k| roi_set.contains(&k), centre);
        }
    }
}

/// Distance to the nearest ROI voxel centre, up to a maximum, on cells of a fixed size.
///
/// Each cell within the maximum of some ROI voxel stores the distance from its centre to the
/// nearest ROI voxel centre found and that voxel (its *site*). Updates are incremental, after
/// Lau et al.'s dynamic distance maps: a new ROI voxel starts a lowering wave from its cell (a cell
/// takes the site when it is closer than its current one, then offers it to its 26 neighbours);
/// a removed ROI voxel clears the cells whose site it was, and those are refilled from the sites
/// of their neighbours. Distances are exact for the site found; the wave can in rare geometric
/// configurations settle on a site slightly farther than the true nearest (at most about one
/// cell).
#[derive(Clone, Debug)]
pub struct RoiDistanceField {
    cell_m: f64,
    max_m: f64,
    cells: HashMap<VoxelKey, (f32, VoxelKey), KeyBuildHasher>,
}

impl RoiDistanceField {
    pub(crate) fn new(cell_m: f64, max_m: f64) -> Self {
        Self {
            cell_m,
            max_m,
            cells: HashMap::default(),
        }
    }

    fn cell_of(&self, p: &Point3<f64>) -> VoxelKey {
        let c = |v: f64| (v / self.cell_m).floor() as i32;
        VoxelKey::new(c(p.x), c(p.y), c(p.z))
    }

    fn cell_centre(&self, c: VoxelKey) -> Point3<f64> {
        Point3::new(
            (f64::from(c.x) + 0.5) * self.cell_m,
            (f64::from(c.y) + 0.5) * self.cell_m,
            (f64::from(c.z) + 0.5) * self.cell_m,
        )
    }

    /// Cell edge in metres.
    pub fn cell_m(&self) -> f64 {
        self.cell_m
    }

    /// Largest stored distance in metres.
    pub fn max_m(&self) -> f64 {
        self.max_m
    }

    /// Distance from the centre of `p`'s cell to the nearest ROI voxel centre, if within the
    /// maximum.
    pub fn distance_m(&self, p: &Point3<f64>) -> Option<f64> {
        if !p.iter().all(|c| c.is_finite()) {
            return None;
        }
        self.cells.get(&self.cell_of(p)).map(|&(d, _)| f64::from(d))
    }

    /// Cells holding a distance.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    pub(crate) fn heap_bytes(&self) -> usize {
        self.cells.capacity() * (std::mem::size_of::<(VoxelKey, (f32, VoxelKey))>() + 1)
    }

    pub(crate) fn update(
        &mut self,
        added: &[VoxelKey],
        removed: &[VoxelKey],
        is_roi: impl Fn(VoxelKey) -> bool,
        centre: impl Fn(VoxelKey) -> Point3<f64>,
    ) {
        let mut queue: VecDeque<(VoxelKey, VoxelKey)> = VecDeque::new();
        if !removed.is_empty() {
            let gone: KeySet = removed.iter().copied().collect();
            let cleared: Vec<VoxelKey> = self
                .cells
                .iter()
                .filter(|(_, (_, site))| gone.contains(site))
                .map(|(c, _)| *c)
                .collect();
            for c in &cleared {
                self.cells.remove(c);
            }
            for &c in &cleared {
                for &(dx, dy, dz) in &NEIGHBOURS_26 {
                    if let Some(&(_, site)) = self.cells.get(&c.offset(dx, dy, dz)) {
                        if is_roi(site) {
                            queue.push_back((c, site));
                        }
                    }
                }
            }
        }
        for &site in added {
            queue.push_back((self.cell_of(&centre(site)), site));
        }
        while let Some((cell, site)) = queue.pop_front() {
            let d = (self.cell_centre(cell) - centre(site)).norm();
            if d > self.max_m {
                continue;
            }
            let d = d as f32;
            match self.cells.get(&cell) {
                Some(&(cur, cur_site)) if cur < d || (cur == d && cur_site <= site) => continue,
                _ => {}
            }
            self.cells.insert(cell, (d, site));
            for &(dx, dy, dz) in &NEIGHBOURS_26 {
                queue.push_back((cell.offset(dx, dy, dz), site));
            }
        }
    }
}
