//! Scan insertion: OctoMap's `insertPointCloud` on a dense per-scan bit grid.
//!
//! 1. Every point becomes a ray end in OctoMap's float precision (range-limited when beyond the
//!    maximum range); their keys give the scan's key box.
//! 2. Rays are walked into a *free* bit plane over that box (one plane per thread; a ray revisits
//!    the same voxels as its neighbours, and a bit plane over the scan's extent stays in cache where
//!    a hash set would miss on almost every insert). The free plane is x-fastest, so the walk
//!    steps its bit index by a fixed stride per axis. Keys outside the box (rounding overshoot by
//!    more than the margin, or a box too large for a dense grid) go to hash sets.
//! 3. End points mark *occupied*, *ROI* and *non-ROI* planes laid out block by block with the
//!    storage's 8×8×8 layout; the free plane is gathered into the same layout one row of blocks at
//!    a time. Then block by block: occupied wins over free, ROI over non-ROI, and each marked voxel
//!    is updated once, with one hash lookup per block. Planes are zeroed as they are consumed,
//!    ready for the next scan.

use nalgebra::Point3;

use crate::grid::{block_of, Mask, BLOCK_EDGE, BLOCK_SHIFT, EMPTY};
use crate::values::Step;
use crate::walk::{key_of_f32, norm_f32, walk_lanes, LaneVisitor, PlaneGeometry, RaySetup, LANES};
use crate::{ChangeLog, KeySet, MapError, RoiMap, ScanStats, VoxelKey};

/// Largest dense grid in blocks (2^17 blocks = 64M voxels, 8 MB per bit plane).
const MAX_GRID_BLOCKS: usize = 1 << 17;
/// Per-scan buffers up to this size are kept for the next scan; larger ones are freed.
const KEEP_SCRATCH_BYTES: usize = 256 << 10;
/// Margin in voxels around the key box: absorbs the walk's rounding overshoot.
const MARGIN: i32 = 2;

/// Where one point's ray ends and whether its end voxel is hit.
#[derive(Clone, Copy, Debug)]
struct RayEnd {
    end: [f32; 3],
    key_end: VoxelKey,
    /// False for points beyond the maximum range (ray freed up to the range only).
    hit: bool,
    /// ROI log-odds added to the end voxel (the labels' hit or miss, or the caller's evidence).
    roi_delta: f32,
}

/// What a scan says about ROI, per point.
#[derive(Clone, Copy, Debug)]
pub enum RoiInput<'a> {
    /// ROI or not: the configured hit or miss, ROI winning within a voxel (OctoMap-style).
    Labels(&'a [bool]),
    /// A ROI log-odds delta per point, e.g. from a detector's confidence; within a voxel the
    /// largest delta wins (a generalisation of "ROI wins"), 0 (or non-finite) adds no evidence.
    Evidence(&'a [f32]),
}

impl RoiInput<'_> {
    fn len(&self) -> usize {
        match self {
            Self::Labels(l) => l.len(),
            Self::Evidence(e) => e.len(),
        }
    }

    fn delta(&self, i: usize, hit: f32, miss: f32) -> f32 {
        match self {
            Self::Labels(l) => {
                if l[i] {
                    hit
                } else {
                    miss
                }
            }
            Self::Evidence(e) if e[i].is_finite() => e[i],
            Self::Evidence(_) => 0.0,
        }
    }
}

/// One thread's free marks.
#[derive(Clone, Default)]
struct Worker {
    /// x-fastest bit plane over the grid's box.
    free: Vec<u64>,
    overflow: KeySet,
}

/// Marks the walk's voxels in a free plane (keys outside the box in a set).
pub(crate) struct FreeMarker<'a> {
    pub(crate) free: &'a mut [u64],
    pub(crate) overflow: &'a mut KeySet,
}

impl LaneVisitor for FreeMarker<'_> {
    const WHOLE_STEPS: bool = true;

    #[inline(always)]
    fn mark_lanes(&mut self, index: &[i32; LANES]) -> bool {
        for &i in index {
            let i = i as u32 as usize;
            if let Some(w) = self.free.get_mut(i >> 6) {
                *w |= 1 << (i & 63);
            }
        }
        true
    }

    #[inline(always)]
    fn voxel(&mut self, _: usize, _: u32, c: [i32; 3], index: i32, inside: bool) -> bool {
        if inside {
            let i = index as u32 as usize;
            if let Some(w) = self.free.get_mut(i >> 6) {
                *w |= 1 << (i & 63);
            }
        } else {
            self.overflow.insert(VoxelKey::new(c[0], c[1], c[2]));
        }
        true
    }

    fn end(&mut self, _: u32, _: [i32; 3]) {}
}

/// Dense bit grid over a block-aligned key box.
#[derive(Clone, Default)]
struct ScanGrid {
    /// Voxel key of the box's low corner (multiple of the block edge).
    lo: [i32; 3],
    /// Box size in blocks.
    nb: [usize; 3],
    /// The box in voxels, for the free planes.
    geometry: PlaneGeometry,
    occ: Vec<u64>,
    roi: Vec<u64>,
    non_roi: Vec<u64>,
    overflow_occ: KeySet,
    overflow_roi: KeySet,
    overflow_non_roi: KeySet,
}

impl ScanGrid {
    fn blocks(&self) -> usize {
        self.nb[0] * self.nb[1] * self.nb[2]
    }

    /// Makes the grid cover `lo..=hi` (empty when too large). Planes must be all zero.
    fn reset(&mut self, lo: VoxelKey, hi: VoxelKey, workers: &mut [Worker]) {
        let lo_k = [lo.x, lo.y, lo.z].map(|v| (v - MARGIN) >> BLOCK_SHIFT);
        let hi_k = [hi.x, hi.y, hi.z].map(|v| (v + MARGIN) >> BLOCK_SHIFT);
        let nb = [0, 1, 2].map(|i| (i64::from(hi_k[i]) - i64::from(lo_k[i]) + 1) as usize);
        let total = nb[0].saturating_mul(nb[1]).saturating_mul(nb[2]);
        let nb = if total > MAX_GRID_BLOCKS { [0; 3] } else { nb };
        self.lo = lo_k.map(|b| b << BLOCK_SHIFT);
        self.nb = nb;
        let edge = BLOCK_EDGE as usize;
        // At most MAX_GRID_BLOCKS blocks, far below i32::MAX voxels.
        self.geometry =
            PlaneGeometry::new(self.lo, nb.map(|b| (b * edge) as u32)).unwrap_or_default();
        let words = self.blocks() * 8;
        for plane in [&mut self.occ, &mut self.roi, &mut self.non_roi] {
            plane.resize(words, 0);
        }
        for w in workers {
            w.free.resize(words, 0);
            w.overflow.clear();
        }
        self.overflow_occ.clear();
        self.overflow_roi.clear();
        self.overflow_non_roi.clear();
    }

    /// Bit index of a voxel in the block-by-block planes, if inside the grid.
    fn bit(&self, c: [i32; 3]) -> Option<usize> {
        self.geometry.index(c)?;
        let u = [0, 1, 2].map(|i| c[i].wrapping_sub(self.lo[i]) as usize);
        let block = (u[0] >> 3) + self.nb[0] * ((u[1] >> 3) + self.nb[1] * (u[2] >> 3));
        Some(block * 512 + ((u[2] & 7) << 6 | (u[1] & 7) << 3 | (u[0] & 7)))
    }

    /// ORs the free plane's voxels of the block row `(by, bz)` into `out` (one mask per block
    /// along x), in the storage's block layout.
    fn gather_block_row(&self, plane: &[u64], by: usize, bz: usize, out: &mut [Mask]) {
        let g = &self.geometry;
        let (nx, ny) = (g.n[0] as usize, g.n[1] as usize);
        for z in 0..8 {
            for y in 0..8 {
                // Rows start on a byte: the box is a whole number of blocks wide.
                let row = nx * (by * 8 + y + ny * (bz * 8 + z));
                for (bx, m) in out.iter_mut().enumerate() {
                    let bit = row + bx * 8;
                    let byte = plane.get(bit >> 6).map_or(0, |w| w >> (bit & 63) & 0xff);
                    m[z] |= byte << (y * 8);
                }
            }
        }
    }

    fn set(&self, plane: &mut [u64], overflow: &mut KeySet, key: VoxelKey) {
        match self.bit([key.x, key.y, key.z]) {
            Some(i) => plane[i >> 6] |= 1 << (i & 63),
            None => {
                overflow.insert(key);
            }
        }
    }

    /// Walks the free voxels of `ends` into `worker`.
    fn walk_rays(
        &self,
        origin: [f32; 3],
        key_origin: VoxelKey,
        res: f64,
        ends: &[RayEnd],
        worker: &mut Worker,
    ) {
        let Worker { free, overflow } = worker;
        let rays = ends
            .iter()
            .filter_map(|e| RaySetup::octomap(origin, e.end, key_origin, e.key_end, res))
            .map(|s| (0, s));
        walk_lanes(rays, &self.geometry, &mut FreeMarker { free, overflow });
    }
}

/// Reused per-scan buffers, so insertion allocates only when a scan is larger than any before.
#[derive(Clone, Default)]
pub(crate) struct Scratch {
    ends: Vec<RayEnd>,
    /// With `merge_far_rays`: the voxels at the range already given a ray.
    far_ray_of_voxel: KeySet,
    grid: ScanGrid,
    workers: Vec<Worker>,
}

impl Scratch {
    pub(crate) fn heap_bytes(&self) -> usize {
        let g = &self.grid;
        let set = |s: &KeySet| s.capacity() * (std::mem::size_of::<VoxelKey>() + 1);
        self.ends.capacity() * std::mem::size_of::<RayEnd>()
            + set(&self.far_ray_of_voxel)
            + (g.occ.capacity() + g.roi.capacity() + g.non_roi.capacity()) * 8
            + set(&g.overflow_occ)
            + set(&g.overflow_roi)
            + set(&g.overflow_non_roi)
            + self
                .workers
                .iter()
                .map(|w| w.free.capacity() * 8 + set(&w.overflow))
                .sum::<usize>()
    }
}

/// Where the ray from `origin` towards `p` ends, and whether that end is a hit: `p` itself, or
/// beyond the maximum range the point at the range along the ray (OctoMap's `float` arithmetic:
/// `origin + (p - origin).normalized() * (float) maxrange`).
fn ray_end(origin: [f32; 3], p: [f32; 3], max_range: Option<f64>) -> ([f32; 3], bool) {
    let diff = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
    let len = norm_f32(diff);
    match max_range {
        Some(range) if len > range => {
            let mut d = diff;
            if len > 0.0 {
                for v in &mut d {
                    *v /= len as f32;
                }
            }
            let r = range as f32;
            let end = [0, 1, 2].map(|i| origin[i] + d[i] * r);
            (end, false)
        }
        _ => (p, true),
    }
}

fn or_words(a: &[u64]) -> Mask {
    let mut m = EMPTY;
    m.copy_from_slice(&a[..8]);
    m
}

impl RoiMap {
    /// Integrates one scan with up to `threads` threads casting rays (1 = the calling thread
    /// only). Same result as [`RoiMap::insert_scan`] for any thread count.
    pub fn insert_scan_threaded(
        &mut self,
        sensor_origin: &Point3<f64>,
        points_in_world: &[Point3<f32>],
        roi: &[bool],
        threads: usize,
    ) -> Result<ScanStats, MapError> {
        self.insert_scan_input(
            sensor_origin,
            points_in_world,
            RoiInput::Labels(roi),
            threads,
        )
    }

    /// Integrates one scan whose ROI evidence is a log-odds delta per point (see
    /// [`RoiInput::Evidence`]); occupancy is updated exactly as by [`RoiMap::insert_scan`].
    pub fn insert_scan_evidence(
        &mut self,
        sensor_origin: &Point3<f64>,
        points_in_world: &[Point3<f32>],
        roi_logodds: &[f32],
        threads: usize,
    ) -> Result<ScanStats, MapError> {
        let roi = RoiInput::Evidence(roi_logodds);
        self.insert_scan_input(sensor_origin, points_in_world, roi, threads)
    }

    fn insert_scan_input(
        &mut self,
        sensor_origin: &Point3<f64>,
        points_in_world: &[Point3<f32>],
        roi: RoiInput<'_>,
        threads: usize,
    ) -> Result<ScanStats, MapError> {
        if points_in_world.len() != roi.len() {
            return Err(MapError::LengthMismatch {
                points: points_in_world.len(),
                roi: roi.len(),
            });
        }
        if !sensor_origin.iter().all(|c| c.is_finite()) {
            return Err(MapError::NonFiniteOrigin);
        }
        // OctoMap's origin is a float point3d.
        let origin = [
            sensor_origin.x as f32,
            sensor_origin.y as f32,
            sensor_origin.z as f32,
        ];
        let inv_res = self.inv_res;
        let res = self.config.resolution_m;
        let key_origin = key_of_f32(origin, inv_res)
            .filter(|_| origin.iter().all(|c| c.is_finite()))
            .ok_or(MapError::OriginOutOfBounds)?;

        let mut stats = ScanStats {
            points: points_in_world.len(),
            ..ScanStats::default()
        };
        let mut s = std::mem::take(&mut self.scratch);
        s.ends.clear();
        let max_range = self.config.max_range_m;

        // Pass 1: ray ends in OctoMap's precision and the key box.
        let (mut lo, mut hi) = (key_origin, key_origin);
        let (roi_hit, roi_miss) = (self.config.roi_hit_logodds, self.config.roi_miss_logodds);
        let mut far_ray_of_voxel = std::mem::take(&mut s.far_ray_of_voxel);
        far_ray_of_voxel.clear();
        for (i, p) in points_in_world.iter().enumerate() {
            if !p.iter().all(|c| c.is_finite()) {
                stats.skipped_non_finite += 1;
                continue;
            }
            let (mut end, hit) = ray_end(origin, [p.x, p.y, p.z], max_range);
            let Some(key_end) = key_of_f32(end, inv_res) else {
                stats.skipped_out_of_bounds += 1;
                continue;
            };
            if !hit {
                stats.beyond_range += 1;
                if self.config.merge_far_rays {
                    // One ray per voxel at the range, aimed at its centre: rays that end in
                    // the same voxel cross nearly the same voxels on the way.
                    if !far_ray_of_voxel.insert(key_end) {
                        continue;
                    }
                    end = self.centre_of(key_end).map(|c| c as f32).into();
                }
            }
            lo = VoxelKey::new(
                lo.x.min(key_end.x),
                lo.y.min(key_end.y),
                lo.z.min(key_end.z),
            );
            hi = VoxelKey::new(
                hi.x.max(key_end.x),
                hi.y.max(key_end.y),
                hi.z.max(key_end.z),
            );
            s.ends.push(RayEnd {
                end,
                key_end,
                hit,
                roi_delta: roi.delta(i, roi_hit, roi_miss),
            });
        }
        s.far_ray_of_voxel = far_ray_of_voxel;
        stats.rays = s.ends.len();

        // Pass 2: free marks, in parallel over contiguous chunks of rays.
        let threads = threads.clamp(1, 64).min(s.ends.len().max(1));
        if s.workers.len() < threads {
            s.workers.resize_with(threads, Worker::default);
        }
        s.grid.reset(lo, hi, &mut s.workers[..threads]);
        {
            let grid = &s.grid;
            let ends = &s.ends;
            let chunk = ends.len().div_ceil(threads).max(1);
            let (first, rest) = s.workers[..threads].split_at_mut(1);
            std::thread::scope(|scope| {
                for (w, part) in rest.iter_mut().zip(ends.chunks(chunk).skip(1)) {
                    scope.spawn(move || grid.walk_rays(origin, key_origin, res, part, w));
                }
                let part = ends.chunks(chunk).next().unwrap_or(&[]);
                grid.walk_rays(origin, key_origin, res, part, &mut first[0]);
            });
        }

        // Pass 3: end-point marks.
        {
            let g = &mut s.grid;
            let mut occ = std::mem::take(&mut g.occ);
            let mut roi_p = std::mem::take(&mut g.roi);
            let mut non_roi = std::mem::take(&mut g.non_roi);
            let (mut o_occ, mut o_roi, mut o_non) = (
                std::mem::take(&mut g.overflow_occ),
                std::mem::take(&mut g.overflow_roi),
                std::mem::take(&mut g.overflow_non_roi),
            );
            for end in s.ends.iter().filter(|e| e.hit) {
                g.set(&mut occ, &mut o_occ, end.key_end);
                match roi {
                    RoiInput::Evidence(_) => {}
                    RoiInput::Labels(_) if end.roi_delta == roi_hit => {
                        g.set(&mut roi_p, &mut o_roi, end.key_end)
                    }
                    RoiInput::Labels(_) => g.set(&mut non_roi, &mut o_non, end.key_end),
                }
            }
            g.occ = occ;
            g.roi = roi_p;
            g.non_roi = non_roi;
            g.overflow_occ = o_occ;
            g.overflow_roi = o_roi;
            g.overflow_non_roi = o_non;
        }

        // Pass 4: apply block by block.
        let mut log = ChangeLog::default();
        self.apply_planes(&mut s, threads, &mut stats, &mut log);
        // Keys outside the dense grid, one by one.
        let mut free_keys: Vec<VoxelKey> = Vec::new();
        for w in &mut s.workers[..threads] {
            free_keys.extend(w.overflow.drain());
        }
        free_keys.sort_unstable();
        free_keys.dedup();
        let g = &mut s.grid;
        let cfg = self.config;
        for key in free_keys {
            if g.overflow_occ.contains(&key) {
                continue; // occupied wins within a scan
            }
            stats.free_updates += 1;
            self.update_voxel(key, Some(cfg.miss_logodds), None, &mut log);
        }
        for key in g.overflow_occ.drain() {
            stats.occupied_updates += 1;
            self.update_voxel(key, Some(cfg.hit_logodds), None, &mut log);
        }
        for &key in &g.overflow_roi {
            stats.roi_updates += 1;
            self.update_voxel(key, None, Some(cfg.roi_hit_logodds), &mut log);
        }
        for key in g.overflow_non_roi.drain() {
            if g.overflow_roi.contains(&key) {
                continue; // ROI wins within a scan
            }
            stats.non_roi_updates += 1;
            self.update_voxel(key, None, Some(cfg.roi_miss_logodds), &mut log);
        }
        g.overflow_roi.clear();
        if let RoiInput::Evidence(_) = roi {
            self.apply_evidence(&s.ends, &mut stats, &mut log);
        }

        // The per-scan buffers are as large as the map itself after a few scans (the scan's key
        // box as bit planes); keeping them would double the map's memory for ~1 ms a scan.
        if s.heap_bytes() <= KEEP_SCRATCH_BYTES {
            self.scratch = s;
        }
        self.refresh_derived(&log);
        self.scans_inserted += 1;
        Ok(stats)
    }

    /// Adds each hit end voxel's largest ROI delta (the evidence path keeps no ROI planes).
    fn apply_evidence(&mut self, ends: &[RayEnd], stats: &mut ScanStats, log: &mut ChangeLog) {
        let mut deltas: Vec<(VoxelKey, f32)> = ends
            .iter()
            .filter(|e| e.hit)
            .map(|e| (e.key_end, e.roi_delta))
            .collect();
        // Block by block in key order, the largest delta of a voxel first.
        deltas.sort_unstable_by(|a, b| {
            (block_of(a.0), a.0)
                .cmp(&(block_of(b.0), b.0))
                .then(b.1.total_cmp(&a.1))
        });
        deltas.dedup_by_key(|d| d.0);
        for (key, delta) in deltas {
            if delta > 0.0 {
                stats.roi_updates += 1;
            } else if delta < 0.0 {
                stats.non_roi_updates += 1;
            } else {
                continue;
            }
            self.update_voxel(key, None, Some(delta), log);
        }
    }

    /// Applies the dense planes block by block in memory order and zeroes them.
    fn apply_planes(
        &mut self,
        s: &mut Scratch,
        threads: usize,
        stats: &mut ScanStats,
        log: &mut ChangeLog,
    ) {
        let nb = s.grid.nb;
        let lo_block = [0, 1, 2].map(|i| s.grid.lo[i] >> BLOCK_SHIFT);
        let mut row_free = vec![EMPTY; nb[0]];
        let mut b = 0usize;
        for bz in 0..nb[2] {
            for by in 0..nb[1] {
                row_free.fill(EMPTY);
                for w in &s.workers[..threads] {
                    s.grid.gather_block_row(&w.free, by, bz, &mut row_free);
                }
                for (bx, free) in row_free.iter().enumerate() {
                    let words = b * 8..b * 8 + 8;
                    b += 1;
                    let g = &mut s.grid;
                    let occ = or_words(&g.occ[words.clone()]);
                    if occ == EMPTY && *free == EMPTY {
                        continue;
                    }
                    let roi_m = or_words(&g.roi[words.clone()]);
                    let non_roi = or_words(&g.non_roi[words.clone()]);
                    g.occ[words.clone()].fill(0);
                    g.roi[words.clone()].fill(0);
                    g.non_roi[words].fill(0);
                    let key = VoxelKey::new(
                        lo_block[0] + bx as i32,
                        lo_block[1] + by as i32,
                        lo_block[2] + bz as i32,
                    );
                    self.apply_block(key, free, &occ, &roi_m, &non_roi, stats, log);
                }
            }
        }
        for w in &mut s.workers[..threads] {
            w.free.fill(0);
        }
    }

    /// Applies one block's marks: each marked voxel updated once, occupied over free and ROI over
    /// non-ROI.
    #[allow(clippy::too_many_arguments)]
    fn apply_block(
        &mut self,
        key: VoxelKey,
        free: &Mask,
        occ: &Mask,
        roi: &Mask,
        non_roi: &Mask,
        stats: &mut ScanStats,
        log: &mut ChangeLog,
    ) {
        let cfg = self.config;
        let step = Step {
            hit: cfg.hit_logodds,
            miss: cfg.miss_logodds,
            lo: cfg.clamp_min_logodds,
            hi: cfg.clamp_max_logodds,
        };
        let roi_step = Step {
            hit: cfg.roi_hit_logodds,
            miss: cfg.roi_miss_logodds,
            ..step
        };
        let thr = cfg.roi_threshold_logodds;
        let (mut touched, mut roi_touched) = (EMPTY, EMPTY);
        for w in 0..8 {
            let f = free[w] & !occ[w];
            let n = non_roi[w] & !roi[w];
            touched[w] = f | occ[w];
            roi_touched[w] = roi[w] | n;
            stats.free_updates += f.count_ones() as usize;
            stats.occupied_updates += occ[w].count_ones() as usize;
            stats.roi_updates += roi[w].count_ones() as usize;
            stats.non_roi_updates += n.count_ones() as usize;
        }
        let bi = self.store.get_or_create(key);
        let block = &mut self.store.blocks[bi];
        let (mut changed, occupied_now) = block.occ.update(&touched, occ, step, |v| v > 0.0);
        let (roi_changed_values, roi_now) = if roi_touched == EMPTY {
            (EMPTY, EMPTY)
        } else {
            block.roi.update(&roi_touched, roi, roi_step, |v| v >= thr)
        };
        let mut state_changed = EMPTY;
        let mut roi_changed = EMPTY;
        let mut any_changed = false;
        let (mut d_known, mut d_occ) = (0isize, 0isize);
        for w in 0..8 {
            let t = touched[w];
            let known_before = block.known[w];
            let occ_before = block.occupied[w];
            let roi_before = block.roi_mask[w];
            changed[w] |= roi_changed_values[w] | (t & !known_before);
            block.known[w] |= t;
            block.occupied[w] = (occ_before & !t) | occupied_now[w];
            block.roi_mask[w] = (roi_before & !roi_touched[w]) | roi_now[w];
            d_known +=
                (block.known[w].count_ones() as isize) - (known_before.count_ones() as isize);
            d_occ += (block.occupied[w].count_ones() as isize) - (occ_before.count_ones() as isize);
            roi_changed[w] = roi_before ^ block.roi_mask[w];
            state_changed[w] =
                (known_before ^ block.known[w]) | (occ_before ^ block.occupied[w]) | roi_changed[w];
            block.dirty[w] |= changed[w];
            any_changed |= changed[w] != 0;
        }
        self.known_count = self.known_count.wrapping_add_signed(d_known);
        self.occupied_count = self.occupied_count.wrapping_add_signed(d_occ);
        if any_changed {
            block.changed_at_scan = self.scans_inserted + 1;
            self.dirty_blocks.insert(bi as u32);
        }
        log.note(bi as u32, &state_changed, &roi_changed);
    }
}
