//! Many rays from one origin walked together (the gain queries of one camera pose): the
//! insertion's eight-lane walk with an early exit per lane, and block lookups shared between
//! neighbouring rays, which cross the same blocks.

use nalgebra::{Point3, Vector3};

use crate::grid::{block_of, local_of, mask_test, Block, Mask, BLOCK_SHIFT};
use crate::walk::{
    walk_lanes, walk_lanes_at, LaneVisitor, PlaneGeometry, RaySetup, KEY_LIMIT, LANES,
};
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
    /// `walk_ray` ray by ray. When the fan is dense enough to pay for it (at most
    /// `PLANE_VOXELS_PER_STEP` box voxels per walk step), its known and occupied masks are first
    /// copied into two dense bit planes over the box its rays span, so each voxel is two bit
    /// tests; a sparse fan looks its voxels up through the block cache.
    pub fn count_unknown_until_occupied(
        &self,
        origin: &Point3<f64>,
        directions: &[Vector3<f64>],
        max_range_m: f64,
    ) -> Vec<RayCount> {
        self.count_unknown_at(crate::simd::level(), origin, directions, max_range_m)
    }

    /// [`RoiMap::count_unknown_until_occupied`] walked on a given vector unit.
    pub(crate) fn count_unknown_at(
        &self,
        level: crate::simd::Level,
        origin: &Point3<f64>,
        directions: &[Vector3<f64>],
        max_range_m: f64,
    ) -> Vec<RayCount> {
        let mut counts = vec![RayCount::default(); directions.len()];
        let mut cache = BlockCache::new(self);
        let mut singles = Vec::new();
        let setups = self.fan_setups(origin, directions, max_range_m, |ray, key| {
            singles.push((ray, key))
        });
        let planes = FanPlanes::new(self, &setups);
        let mut counter = UnknownCounter {
            planes: &planes,
            cache: &mut cache,
            counts: &mut counts,
            lane_ray: [0; LANES],
        };
        for (ray, key) in singles {
            counter.count(ray as u32, key, None);
        }
        walk_lanes_at(level, setups.into_iter(), &planes.geometry, &mut counter);
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
        let setups = self.fan_setups(origin, directions, max_range_m, |ray, key| {
            probe(LANES, ray, key);
        });
        walk_lanes(
            setups.into_iter(),
            &PlaneGeometry::unbounded(),
            &mut Probe(probe),
        );
    }
}

impl RoiMap {
    /// The walks of a ray fan: one set-up per direction with a walk; `single(ray, key)` for each
    /// direction that visits one voxel only (not a finite direction, or its end in the origin's
    /// voxel), as `walk_ray` does. None for an origin off the map's keys or a bad range.
    fn fan_setups(
        &self,
        origin: &Point3<f64>,
        directions: &[Vector3<f64>],
        max_range_m: f64,
        mut single: impl FnMut(usize, VoxelKey),
    ) -> Vec<(u32, RaySetup)> {
        let Some(key_origin) = self.try_key_of(origin) else {
            return Vec::new();
        };
        if !(max_range_m.is_finite() && max_range_m >= 0.0) {
            return Vec::new();
        }
        let res = self.config.resolution_m;
        let range_m = max_range_m.min(KEY_LIMIT as f64 * res);
        let mut setups = Vec::with_capacity(directions.len());
        for (ray, direction) in directions.iter().enumerate() {
            let Some(unit) = direction
                .try_normalize(1e-12)
                .filter(|d| d.iter().all(|c| c.is_finite()))
            else {
                single(ray, key_origin);
                continue;
            };
            let key_end = self.key_of(&(origin + unit * range_m));
            match RaySetup::exact(origin, &unit, range_m, key_origin, key_end, res) {
                Some(s) => setups.push((ray as u32, s)),
                None => single(ray, key_end),
            }
        }
        setups
    }
}

/// Voxels of a fan's dense planes at most (two bits each): larger fans keep to the block cache.
const FAN_PLANE_VOXELS: u64 = 1 << 25;

/// Box voxels the planes may cover per voxel step of the fan's walks. Filling the planes costs
/// about 0.06 ns per box voxel (zeroing, a block lookup per 512, row copies for the blocks
/// present), and a step through them saves about 6 ns of block-cache lookup and mask test
/// (`cargo bench -p glasshouse-roimap -- query/gain_fan`): they pay below about 90 box voxels a
/// step. The 200×150-ray benchmark fan has 0.5, the planner's 8×6-ray fan 180 (7 000 steps at
/// most in a box of 1.3 M voxels), where the planes cost 2.4× the walk alone. The steps are an
/// upper bound (a ray stops at its first occupied voxel), hence a bound well below the break-even.
const PLANE_VOXELS_PER_STEP: u64 = 32;

/// Voxels the walks of `setups` visit at most (each ray's origin to end voxel, one axis step
/// per voxel).
fn fan_steps(setups: &[(u32, RaySetup)]) -> u64 {
    setups
        .iter()
        .map(|(_, s)| {
            let d = s.key_end.x.abs_diff(s.key_origin.x)
                + s.key_end.y.abs_diff(s.key_origin.y)
                + s.key_end.z.abs_diff(s.key_origin.z);
            u64::from(d) + 1
        })
        .sum()
}

/// The known and occupied masks over the block-aligned box a fan's rays span (origin and end
/// voxels, one voxel of margin), x fastest, as the lane walk indexes them.
struct FanPlanes {
    geometry: PlaneGeometry,
    known: Vec<u64>,
    occupied: Vec<u64>,
}

impl FanPlanes {
    fn new(map: &RoiMap, setups: &[(u32, RaySetup)]) -> Self {
        let empty = Self {
            geometry: PlaneGeometry::default(),
            known: Vec::new(),
            occupied: Vec::new(),
        };
        let Some((_, first)) = setups.first() else {
            return empty;
        };
        let o = first.key_origin;
        let (mut lo, mut hi) = ([o.x, o.y, o.z], [o.x, o.y, o.z]);
        for (_, s) in setups {
            let e = [s.key_end.x, s.key_end.y, s.key_end.z];
            for i in 0..3 {
                lo[i] = lo[i].min(e[i]);
                hi[i] = hi[i].max(e[i]);
            }
        }
        let block_lo = lo.map(|k| (k - 1) >> BLOCK_SHIFT);
        let block_hi = hi.map(|k| (k + 1) >> BLOCK_SHIFT);
        let nb = [0, 1, 2].map(|i| (block_hi[i] - block_lo[i] + 1) as u32);
        let voxels = nb.iter().map(|&n| u64::from(n) * 8).product::<u64>();
        if voxels > FAN_PLANE_VOXELS
            || voxels > PLANE_VOXELS_PER_STEP.saturating_mul(fan_steps(setups))
        {
            return empty;
        }
        let Some(geometry) =
            PlaneGeometry::new(block_lo.map(|b| b << BLOCK_SHIFT), nb.map(|n| n * 8))
        else {
            return empty;
        };
        let mut planes = Self {
            geometry,
            known: vec![0; voxels.div_ceil(64) as usize],
            occupied: vec![0; voxels.div_ceil(64) as usize],
        };
        for bz in 0..nb[2] as i32 {
            for by in 0..nb[1] as i32 {
                for bx in 0..nb[0] as i32 {
                    let bk = VoxelKey::new(block_lo[0] + bx, block_lo[1] + by, block_lo[2] + bz);
                    if let Some(block) = map.store.find(bk) {
                        planes.scatter([bx, by, bz].map(|b| b as usize), block);
                    }
                }
            }
        }
        planes
    }

    /// Copies one block's masks into the planes (`b`: the block's place in the box, in blocks).
    fn scatter(&mut self, b: [usize; 3], block: &Block) {
        let (nx, ny) = (self.geometry.n[0] as usize, self.geometry.n[1] as usize);
        for z in 0..8 {
            for y in 0..8 {
                // A block's row of eight voxels is one byte of the plane (the box is block
                // aligned).
                let bit = nx * (b[1] * 8 + y + ny * (b[2] * 8 + z)) + b[0] * 8;
                let (word, shift) = (bit >> 6, bit & 63);
                let row = |m: &Mask| (m[z] >> (y * 8)) & 0xff;
                if let (Some(k), Some(o)) = (self.known.get_mut(word), self.occupied.get_mut(word))
                {
                    *k |= row(&block.known) << shift;
                    *o |= row(&block.occupied) << shift;
                }
            }
        }
    }

    #[inline(always)]
    fn test(plane: &[u64], index: i32) -> bool {
        let i = index as u32 as usize;
        plane.get(i >> 6).is_some_and(|w| w >> (i & 63) & 1 == 1)
    }
}

/// [`RoiMap::count_unknown_until_occupied`]'s visitor: counts each ray's voxels and unknown
/// ones, stops a ray at its first occupied voxel; voxels in the planes are two bit tests, the
/// others go through the block cache.
struct UnknownCounter<'a, 'm> {
    planes: &'a FanPlanes,
    cache: &'a mut BlockCache<'m>,
    counts: &'a mut [RayCount],
    /// The ray each lane walks (set when its origin voxel is visited).
    lane_ray: [u32; LANES],
}

impl UnknownCounter<'_, '_> {
    /// Counts voxel `key` of `ray` (`index`: its bit in the planes, if inside); returns whether
    /// it is occupied.
    #[inline(always)]
    fn count(&mut self, ray: u32, key: VoxelKey, index: Option<i32>) -> bool {
        let (known, occupied) = match index {
            Some(i) => (
                FanPlanes::test(&self.planes.known, i),
                FanPlanes::test(&self.planes.occupied, i),
            ),
            None => self.cache.block(LANES, key).map_or((false, false), |b| {
                let l = local_of(key);
                (mask_test(&b.known, l), mask_test(&b.occupied, l))
            }),
        };
        self.tally(ray, known);
        occupied
    }

    /// One more voxel of `ray`, unknown unless `known`.
    #[inline(always)]
    fn tally(&mut self, ray: u32, known: bool) {
        if let Some(c) = self.counts.get_mut(ray as usize) {
            c.visited += 1;
            c.unknown += u32::from(!known);
        }
    }
}

impl LaneVisitor for UnknownCounter<'_, '_> {
    const WHOLE_STEPS: bool = true;

    #[inline(always)]
    fn mark_lanes(&mut self, index: &[i32; LANES]) -> bool {
        if index
            .iter()
            .any(|&i| FanPlanes::test(&self.planes.occupied, i))
        {
            return false;
        }
        for (&i, ray) in index.iter().zip(self.lane_ray) {
            self.tally(ray, FanPlanes::test(&self.planes.known, i));
        }
        true
    }

    #[inline(always)]
    fn voxel(&mut self, lane: usize, ray: u32, c: [i32; 3], index: i32, inside: bool) -> bool {
        if let Some(r) = self.lane_ray.get_mut(lane) {
            *r = ray;
        }
        let key = VoxelKey::new(c[0], c[1], c[2]);
        !self.count(ray, key, inside.then_some(index))
    }

    fn end(&mut self, ray: u32, key_end: [i32; 3]) {
        let index = self.planes.geometry.index(key_end).map(|i| i as i32);
        self.count(
            ray,
            VoxelKey::new(key_end[0], key_end[1], key_end[2]),
            index,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdata::{unobserved_gain, unobserved_gain_batch, Workload};

    /// The planes are built for a dense fan and skipped for the planner's sparse one, and
    /// both give the ray-by-ray gain bit for bit.
    #[test]
    fn planes_only_for_fans_dense_enough_to_pay_for_them() {
        let w = Workload::small(3, 160, 120, 10, 3);
        let m = w.filtered_map().expect("valid scans");
        for (fan, range_m, planes) in [
            (w.gain_fan(), 1.5, true),
            (w.planner_gain_fan(), 1.0, false),
        ] {
            let (origin, directions) = fan;
            let setups = m.fan_setups(&origin, &directions, range_m, |_, _| {});
            let built = FanPlanes::new(&m, &setups);
            assert_eq!(!built.known.is_empty(), planes, "{} rays", directions.len());
            let ray_by_ray = unobserved_gain(&m, &origin, &directions, range_m);
            // Neither all unknown nor all known: the walks meet the map's surface.
            assert!(ray_by_ray > 0.0 && ray_by_ray < 1.0, "gain {ray_by_ray}");
            assert_eq!(
                ray_by_ray.to_bits(),
                unobserved_gain_batch(&m, &origin, &directions, range_m).to_bits()
            );
        }
    }

    /// Every vector unit this CPU has counts each ray of a dense fan (whole steps in
    /// registers) as the portable walk does.
    #[test]
    fn every_vector_unit_counts_each_ray_alike() {
        use crate::simd::{detected, Level};
        let w = Workload::small(3, 160, 120, 10, 3);
        let m = w.filtered_map().expect("valid scans");
        let (origin, directions) = w.gain_fan();
        let portable = m.count_unknown_at(Level::Portable, &origin, &directions, 1.5);
        let unknown: u32 = portable.iter().map(|c| c.unknown).sum();
        let visited: u32 = portable.iter().map(|c| c.visited).sum();
        assert!(
            unknown > 1000 && unknown < visited,
            "{unknown} of {visited}"
        );
        for level in [Level::Avx2, Level::Avx512] {
            if level <= detected() {
                let wide = m.count_unknown_at(level, &origin, &directions, 1.5);
                assert!(wide == portable, "{level:?} counts differ");
            }
        }
    }
}
