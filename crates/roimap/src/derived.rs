//! State derived from the voxels and maintained as they change: the ROI set and the
//! two frontier sets (as per-block masks).

use crate::grid::{
    faces_touched, for_each_bit, has_neighbour_in, key_at, mask_count, mask_is_empty, mask_test,
    Block, Mask, EMPTY, FACE_OFFSETS,
};
use crate::{ChangeLog, KeySet, RoiMap, VoxelKey};

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
    let n_target = n.map(|o| o.map_or(EMPTY, |b| b.roi_target));
    let near_unknown = has_neighbour_in(&unknown, &n_unknown);
    let mut base = EMPTY;
    for w in 0..8 {
        base[w] = free[w] & near_unknown[w];
    }
    if mask_is_empty(&base) {
        return (EMPTY, EMPTY);
    }
    let near_occ = has_neighbour_in(&b.occupied, &n_occ);
    let near_roi = has_neighbour_in(&b.roi_target, &n_target);
    let mut expl = EMPTY;
    let mut roi = EMPTY;
    for w in 0..8 {
        expl[w] = base[w] & near_occ[w];
        roi[w] = base[w] & near_roi[w];
    }
    (expl, roi)
}

impl RoiMap {
    /// Updates the ROI set, and the frontier masks for the voxels in `log`.
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
        self.roi_changes.clear();
        self.roi_changes.extend(added.iter().chain(&removed));
        self.roi_epoch += 1;
        // The changed blocks, and the face neighbours next to changed voxels.
        let mut todo = KeySet::default();
        for (&bi, (state, _)) in &log.blocks {
            let bk = self.store.coords[bi as usize];
            add_with_touched_faces(&mut todo, bk, state);
        }
        // ROI targets there; a changed target also changes the frontier beside it.
        let mut frontier_todo = todo.clone();
        for &bk in &todo {
            if let Some(changed) = self.refresh_targets(bk) {
                add_with_touched_faces(&mut frontier_todo, bk, &changed);
            }
        }
        self.refresh_frontiers(frontier_todo);
    }

    /// Recomputes the ROI targets of block `bk`; returns the voxels whose target state changed.
    fn refresh_targets(&mut self, bk: VoxelKey) -> Option<Mask> {
        let &bi = self.store.index.get(&bk)?;
        let b = &self.store.blocks[bi as usize];
        let targets = if self.config.roi_target_needs_neighbour {
            let n_roi = self
                .store
                .face_neighbours(bk)
                .map(|o| o.map_or(EMPTY, |n| n.roi_mask));
            let supported = has_neighbour_in(&b.roi_mask, &n_roi);
            std::array::from_fn(|w| b.roi_mask[w] & supported[w])
        } else {
            b.roi_mask
        };
        let changed: Mask = std::array::from_fn(|w| targets[w] ^ b.roi_target[w]);
        self.store.blocks[bi as usize].roi_target = targets;
        (!mask_is_empty(&changed)).then_some(changed)
    }

    /// Recomputes the frontier masks and counts of the blocks in `todo`.
    fn refresh_frontiers(&mut self, todo: KeySet) {
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
    }
}

/// Adds block `bk` and the face neighbours that the voxels of `voxels` touch.
fn add_with_touched_faces(todo: &mut KeySet, bk: VoxelKey, voxels: &Mask) {
    todo.insert(bk);
    for (touches, (dx, dy, dz)) in faces_touched(voxels).into_iter().zip(FACE_OFFSETS) {
        if touches {
            todo.insert(bk.offset(dx, dy, dz));
        }
    }
}
