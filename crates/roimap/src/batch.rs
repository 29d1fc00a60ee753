//! Many rays from one origin walked together (the gain queries of one camera pose): the
//! insertion's eight-lane walk with an early exit per lane, and block lookups shared between
//! neighbouring rays, which cross the same blocks.

use nalgebra::{Point3, Vector3};

use crate::grid::{block_of, local_of, mask_test, Block};
use crate::walk::{walk_lanes, LaneVisitor, PlaneGeometry, RaySetup, KEY_LIMIT, LANES};
use crate::{RoiMap, Voxel, VoxelKey};

/// Per-ray result of [`RoiMap::count_unknown_until_occupied`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RayCount {
    /// Voxels walked, the occupied voxel that stops the ray included.
    pub visited: u32,
    /// Unknown voxels among them.
    pub unknown: u32,
}

/// Slots of the shared block cache (direct-mapped by block coordinate).
const SHARED_SLOTS: usize = 1024;

/// Block lookups for the walk: one entry per lane (a ray stays in a block for several steps)
/// in front of a small direct-mapped cache shared by all lanes.
struct BlockCache<'m> {
    map: &'m RoiMap,
    lane: [Option<(VoxelKey, Option<&'m Block>)>; LANES + 1],
    shared: Vec<Option<(VoxelKey, Option<&'m Block>)>>,
}

impl<'m> BlockCache<'m> {
    fn new(map: &'m RoiMap) -> Self {
        Self {
            map,
            lane: [None; LANES + 1],
            shared: vec![None; SHARED_SLOTS],
        }
    }

    /// The block holding `key`, looked up through the cache of `lane` (`LANES` for walks
    /// outside the lanes).
    #[inline(always)]
    fn block(&mut self, lane: usize, key: VoxelKey) -> Option<&'m Block> {
        let bk = block_of(key);
        let slot = self.lane.get_mut(lane)?;
        if let Some((k, b)) = *slot {
            if k == bk {
                return b;
            }
        }
        let h = (bk.x as u32)
            .wrapping_mul(0x9E37_79B1)
            .wrapping_add((bk.y as u32).wrapping_mul(0x85EB_CA77))
            .wrapping_add((bk.z as u32).wrapping_mul(0xC2B2_AE3D));
        let shared = self.shared.get_mut((h >> 22) as usize % SHARED_SLOTS)?;
        let b = match *shared {
            Some((k, b)) if k == bk => b,
            _ => {
                let b = self.map.store.find(bk);
                *shared = Some((bk, b));
                b
            }
        };
        *slot = Some((bk, b));
        b
    }
}

/// Adapts a per-voxel probe `(lane, ray, key) -> go on` to the lane walk.
struct Probe<F>(F);

impl<F: FnMut(usize, usize, VoxelKey) -> bool> LaneVisitor for Probe<F> {
    const PLANE: bool = false;

    #[inline(always)]
    fn voxel(&mut self, lane: usize, ray: u32, c: [i32; 3], _: i32, _: bool) -> bool {
        (self.0)(lane, ray as usize, VoxelKey::new(c[0], c[1], c[2]))
    }

    fn end(&mut self, ray: u32, key_end: [i32; 3]) {
        (self.0)(
            LANES,
            ray as usize,
            VoxelKey::new(key_end[0], key_end[1], key_end[2]),
        );
    }
}

impl RoiMap {
    /// [`RoiMap::walk_ray`] for every direction in `directions` from one origin, walked
    /// together: `visit(ray_index, key, voxel)` gets, for each ray, exactly the voxels and values
    /// `walk_ray` would give it, in the same order within the ray, the rays interleaved.
    /// Returning false stops that ray only.
    pub fn walk_rays_from(
        &self,
        origin: &Point3<f64>,
        directions: &[Vector3<f64>],
        max_range_m: f64,
        mut visit: impl FnMut(usize, VoxelKey, Option<Voxel>) -> bool,
    ) {
        let mut cache = BlockCache::new(self);
        self.walk_batch(origin, directions, max_range_m, |lane, ray, key| {
            let value = cache.block(lane, key).and_then(|b| {
                let l = local_of(key);
                mask_test(&b.known, l).then(|| Voxel {
                    occupancy_logodds: b.occ_at(l),
                    roi_logodds: b.roi_at(l),
                })
            });
            visit(ray, key, value)
        });
    }

    /// The unobserved-voxel count of a ray fan (paper eq. 1's U_U terms): along each ray from
    /// `origin`, the voxels [`RoiMap::walk_ray`] visits up to and including the first occupied
    /// one, and how many of them are unknown. One entry per direction; equal to counting with
    /// `walk_ray` ray by ray.
    pub fn count_unknown_until_occupied(
        &self,
        origin: &Point3<f64>,
        directions: &[Vector3<f64>],
        max_range_m: f64,
    ) -> Vec<RayCount> {
        let mut counts = vec![RayCount::default(); directions.len()];
        let mut cache = BlockCache::new(self);
        self.walk_batch(origin, directions, max_range_m, |lane, ray, key| {
            let l = local_of(key);
            let (known, occupied) = cache.block(lane, key).map_or((false, false), |b| {
                (mask_test(&b.known, l), mask_test(&b.occupied, l))
            });
            if let Some(c) = counts.get_mut(ray) {
                c.visited += 1;
                c.unknown += u32::from(!known);
            }
            !occupied
        });
        counts
    }

    /// The walk of [`RoiMap::walk_ray`] for many rays: `probe(lane, ray, key)` per voxel, lane
    /// `LANES` for voxels visited outside the lanes.
    fn walk_batch(
        &self,
        origin: &Point3<f64>,
        directions: &[Vector3<f64>],
        max_range_m: f64,
        mut probe: impl FnMut(usize, usize, VoxelKey) -> bool,
    ) {
        let Some(key_origin) = self.try_key_of(origin) else {
            return;
        };
        if !(max_range_m.is_finite() && max_range_m >= 0.0) {
            return;
        }
        let res = self.config.resolution_m;
        let range_m = max_range_m.min(KEY_LIMIT as f64 * res);
        // Rays with a walk go to the lanes; the others visit one voxel here, as walk_ray does.
        let mut setups = Vec::with_capacity(directions.len());
        for (ray, direction) in directions.iter().enumerate() {
            let Some(unit) = direction
                .try_normalize(1e-12)
                .filter(|d| d.iter().all(|c| c.is_finite()))
            else {
                probe(LANES, ray, key_origin);
                continue;
            };
            let key_end = self.key_of(&(origin + unit * range_m));
            match RaySetup::exact(origin, &unit, range_m, key_origin, key_end, res) {
                Some(s) => setups.push((ray as u32, s)),
                None => {
                    probe(LANES, ray, key_end);
                }
            }
        }
        walk_lanes(
            setups.into_iter(),
            &PlaneGeometry::unbounded(),
            &mut Probe(probe),
        );
    }
}
