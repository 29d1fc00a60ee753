//! The Amanatides–Woo voxel walk, set up exactly like OctoMap 1.9's `computeRayKeys`.
//!
//! OctoMap computes in mixed precision: points, origin, direction and length are `float`
//! (`point3d`), keys come from `floor(coordinate * (1 / resolution))` in double, and the walk
//! itself (`tMax`, `tDelta`) is double. [`RaySetup::octomap`] reproduces those roundings step by
//! step so that our free sets equal OctoMap's voxel for voxel; [`RaySetup::exact`] sets the same
//! walk up from `f64` inputs (for queries).

use nalgebra::{Point3, Vector3};

use crate::VoxelKey;

/// Largest absolute key value (exclusive) a voxel may have; keeps rays finite and keys far from
/// `i32` overflow when stepping.
pub(crate) const KEY_LIMIT: i64 = 1 << 20;

/// Key of one coordinate, OctoMap's `coordToKeyChecked` with our wider range.
pub(crate) fn axis_key(coordinate: f64, inv_res: f64) -> Option<i32> {
    let k = (inv_res * coordinate).floor();
    if k.is_finite() && k >= -(KEY_LIMIT as f64) && k < KEY_LIMIT as f64 {
        Some(k as i32)
    } else {
        None
    }
}

pub(crate) fn key_of_f32(p: [f32; 3], inv_res: f64) -> Option<VoxelKey> {
    Some(VoxelKey::new(
        axis_key(f64::from(p[0]), inv_res)?,
        axis_key(f64::from(p[1]), inv_res)?,
        axis_key(f64::from(p[2]), inv_res)?,
    ))
}

/// `float` norm as OctoMap computes it: squares summed in `float`, square root in double.
pub(crate) fn norm_f32(v: [f32; 3]) -> f64 {
    f64::from(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// Everything the walk needs; `key_origin != key_end`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RaySetup {
    pub key_origin: VoxelKey,
    pub key_end: VoxelKey,
    pub step: [i32; 3],
    pub t_max: [f64; 3],
    pub t_delta: [f64; 3],
    /// Segment length; the walk stops once the next voxel starts beyond it.
    pub length: f64,
}

impl RaySetup {
    /// OctoMap's `computeRayKeys(origin, end)` initialisation in OctoMap's precision. `None` when
    /// the two keys are equal (no free voxel).
    pub(crate) fn octomap(
        origin: [f32; 3],
        end: [f32; 3],
        key_origin: VoxelKey,
        key_end: VoxelKey,
        res: f64,
    ) -> Option<Self> {
        let mut direction = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
        let length = norm_f32(direction) as f32;
        for d in &mut direction {
            *d /= length;
        }
        let half = [
            (res * 0.5) as f32,
            (-res * 0.5) as f32, // (float)(step * res * 0.5) for step = -1
        ];
        let (o, d) = (origin.map(f64::from), direction.map(f64::from));
        let offset = |step: i32| f64::from(if step > 0 { half[0] } else { half[1] });
        Self::from_axes([key_origin, key_end], o, d, f64::from(length), res, offset)
    }

    /// The same walk from `f64` inputs: `direction` a finite unit vector, `length` the segment
    /// length. `None` when the two keys are equal.
    pub(crate) fn exact(
        origin: &Point3<f64>,
        direction: &Vector3<f64>,
        length: f64,
        key_origin: VoxelKey,
        key_end: VoxelKey,
        res: f64,
    ) -> Option<Self> {
        let (o, d) = (
            [origin.x, origin.y, origin.z],
            [direction.x, direction.y, direction.z],
        );
        let offset = |step: i32| f64::from(step) * res * 0.5;
        Self::from_axes([key_origin, key_end], o, d, length, res, offset)
    }

    /// The walk from `keys` (origin, end) along the unit `direction`: per axis the step, the ray
    /// parameter of the first voxel border crossed and the parameter between two borders
    /// (`f64::MAX` where the ray is parallel to the axis). `border_offset(step)` is the distance
    /// from the origin voxel's centre to that first border, so each caller keeps its rounding.
    /// `None` when the two keys are equal (no free voxel).
    #[inline(always)]
    fn from_axes(
        [key_origin, key_end]: [VoxelKey; 2],
        origin: [f64; 3],
        direction: [f64; 3],
        length: f64,
        res: f64,
        border_offset: impl Fn(i32) -> f64,
    ) -> Option<Self> {
        if key_origin == key_end {
            return None;
        }
        let mut step = [0i32; 3];
        let mut t_max = [f64::MAX; 3];
        let mut t_delta = [f64::MAX; 3];
        let ko = [key_origin.x, key_origin.y, key_origin.z];
        for i in 0..3 {
            let d = direction[i];
            if d > 0.0 {
                step[i] = 1;
            } else if d < 0.0 {
                step[i] = -1;
            } else {
                continue;
            }
            let border = (f64::from(ko[i]) + 0.5) * res + border_offset(step[i]);
            t_max[i] = (border - origin[i]) / d;
            t_delta[i] = res / d.abs();
        }
        Some(Self {
            key_origin,
            key_end,
            step,
            t_max,
            t_delta,
            length,
        })
    }

    /// Visits the free voxels of the ray: the origin voxel, then every voxel entered before the
    /// end voxel, stopping early when a voxel starts beyond `length` (OctoMap's rounding guard).
    /// `visit` returns false to stop. Returns false when stopped by `visit`.
    #[inline(always)]
    pub(crate) fn walk(&self, mut visit: impl FnMut([i32; 3]) -> bool) -> bool {
        let e = [self.key_end.x, self.key_end.y, self.key_end.z];
        let mut c = [self.key_origin.x, self.key_origin.y, self.key_origin.z];
        if !visit(c) {
            return false;
        }
        let mut t = self.t_max;
        let step = self.step;
        let td = self.t_delta;
        let length = self.length;
        // Each axis only moves towards the end, so the end key can only be reached after
        // exactly this many steps; before that only the length test can stop the walk.
        let n = (0..3).map(|i| u64::from(c[i].abs_diff(e[i]))).sum::<u64>();
        let (mut dim, _) = argmin(&t);
        let mut taken = 0u64;
        loop {
            c[dim] += step[dim];
            t[dim] += td[dim];
            taken += 1;
            if taken == n && c == e {
                return true;
            }
            let (d, t_min) = argmin(&t);
            if t_min > length {
                return true;
            }
            dim = d;
            if !visit(c) {
                return false;
            }
        }
    }
}

/// OctoMap's choice of axis (ties go to the later axis) and the smallest `t`.
#[inline(always)]
fn argmin(t: &[f64; 3]) -> (usize, f64) {
    let a = t[0] < t[1];
    let (m01, d01) = if a { (t[0], 0) } else { (t[1], 1) };
    if m01 < t[2] {
        (d01, m01)
    } else {
        (2, t[2])
    }
}

/// Where the walk's voxels live in a dense bit plane over a key box (x fastest): the bit index
/// of a voxel moves by a fixed stride per axis step, so the walk carries it instead of computing
/// it from the key at every voxel.
/// The default is an empty box (every key outside).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct PlaneGeometry {
    /// Key of the box's low corner.
    pub lo: [i32; 3],
    /// Box size in voxels per axis.
    pub n: [u32; 3],
    /// Bit-index change of one voxel step along each axis: `[1, n_x, n_x * n_y]`.
    pub stride: [i32; 3],
}

impl PlaneGeometry {
    /// A box over `lo` with `n` voxels per axis; `None` when it has more than `i32::MAX` voxels.
    pub(crate) fn new(lo: [i32; 3], n: [u32; 3]) -> Option<Self> {
        let total = u64::from(n[0]) * u64::from(n[1]) * u64::from(n[2]);
        (total <= i32::MAX as u64).then(|| Self {
            lo,
            n,
            stride: [1, n[0] as i32, (n[0] * n[1]) as i32],
        })
    }

    /// Every key inside, no plane (strides zero): for walks that only need the keys.
    pub(crate) fn unbounded() -> Self {
        Self {
            lo: [i32::MIN; 3],
            n: [u32::MAX; 3],
            stride: [0; 3],
        }
    }

    #[inline(always)]
    fn inside(&self, c: [i32; 3]) -> bool {
        (0..3).all(|i| (c[i].wrapping_sub(self.lo[i]) as u32) < self.n[i])
    }

    /// Bit index of a voxel, if inside the box.
    #[inline(always)]
    pub(crate) fn index(&self, c: [i32; 3]) -> Option<usize> {
        self.inside(c).then(|| self.index_unchecked(c) as usize)
    }

    /// Bit index as the walk carries it (meaningless outside the box).
    fn index_unchecked(&self, c: [i32; 3]) -> i32 {
        (0..3).fold(0i32, |acc, i| {
            acc.wrapping_add(c[i].wrapping_sub(self.lo[i]).wrapping_mul(self.stride[i]))
        })
    }
}

/// What a lane walk does with its voxels.
pub(crate) trait LaneVisitor {
    /// False when the visitor ignores bit indices and boxes (the walk then skips them).
    const PLANE: bool = true;
    /// True when steps where every lane is busy and inside the box may go to
    /// [`LaneVisitor::mark_lanes`] in one call, without the per-lane bookkeeping.
    const WHOLE_STEPS: bool = false;
    /// One step of all [`LANES`] lanes, every voxel inside the plane (only with `WHOLE_STEPS`):
    /// does what [`LaneVisitor::voxel`] would do for each lane and returns true, or, when a lane
    /// would stop its ray, does nothing and returns false (the lanes then go to `voxel`).
    fn mark_lanes(&mut self, _index: &[i32; LANES]) -> bool {
        false
    }
    /// Voxel `c` of ray `ray`, walked in lane `lane`; `index` is its bit index in the plane when
    /// `inside` the plane's box. Returns false to stop the ray (no [`LaneVisitor::end`] then).
    fn voxel(&mut self, lane: usize, ray: u32, c: [i32; 3], index: i32, inside: bool) -> bool;
    /// Ray `ray` has walked all its free voxels; `key_end` is its end voxel.
    fn end(&mut self, ray: u32, key_end: [i32; 3]);
}

/// Rays walked side by side by [`walk_lanes`].
pub(crate) const LANES: usize = 8;
/// The lane mask with every lane set.
const ALL_LANES: u32 = (1 << LANES) - 1;

/// [`LANES`] rays in flight, one array per field, so that one step of every lane is the same
/// arithmetic on arrays (the compiler turns the loop in [`Lanes::advance`] into vector code).
#[derive(Clone, Copy)]
struct Lanes {
    t: [[f64; LANES]; 3],
    td: [[f64; LANES]; 3],
    c: [[i32; LANES]; 3],
    e: [[i32; LANES]; 3],
    step: [[i32; LANES]; 3],
    /// Plane stride of one step along each axis, signed like the step.
    stride: [[i32; LANES]; 3],
    index: [i32; LANES],
    left: [u32; LANES],
    length: [f64; LANES],
    ray: [u32; LANES],
}

impl Lanes {
    fn new() -> Self {
        Self {
            t: [[0.0; LANES]; 3],
            td: [[0.0; LANES]; 3],
            c: [[0; LANES]; 3],
            e: [[0; LANES]; 3],
            step: [[0; LANES]; 3],
            stride: [[0; LANES]; 3],
            index: [0; LANES],
            left: [0; LANES],
            length: [0.0; LANES],
            ray: [0; LANES],
        }
    }

    #[inline(always)]
    fn load(&mut self, j: usize, ray: u32, s: &RaySetup, g: &PlaneGeometry) {
        let c = [s.key_origin.x, s.key_origin.y, s.key_origin.z];
        let e = [s.key_end.x, s.key_end.y, s.key_end.z];
        for i in 0..3 {
            self.t[i][j] = s.t_max[i];
            self.td[i][j] = s.t_delta[i];
            self.c[i][j] = c[i];
            self.e[i][j] = e[i];
            self.step[i][j] = s.step[i];
            self.stride[i][j] = s.step[i].wrapping_mul(g.stride[i]);
        }
        self.index[j] = g.index_unchecked(c);
        self.left[j] = (0..3).fold(0u32, |acc, i| acc.wrapping_add(c[i].abs_diff(e[i])));
        self.length[j] = s.length;
        self.ray[j] = ray;
    }

    /// One step of [`RaySetup::walk`] in every lane, without dynamic indexing (the axis choice
    /// becomes selects). Returns two lane masks: rays that are done (their new voxel is then not
    /// a free voxel) and lanes whose new voxel is outside the plane's box.
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // one index over many arrays
    fn advance(&mut self, g: &PlaneGeometry, plane: bool) -> (u32, u32) {
        // Separate simple loops over the lanes, selects as bit masks: each loop becomes vector
        // code (one loop with everything in it stays scalar).
        let mut mask = [[0u64; LANES]; 3];
        for j in 0..LANES {
            let (t0, t1, t2) = (self.t[0][j], self.t[1][j], self.t[2][j]);
            let a = t0 < t1;
            let x = a & (t0 < t2);
            let y = !a & (t1 < t2);
            let z = !(x | y);
            mask[0][j] = 0u64.wrapping_sub(u64::from(x));
            mask[1][j] = 0u64.wrapping_sub(u64::from(y));
            mask[2][j] = 0u64.wrapping_sub(u64::from(z));
        }
        for i in 0..3 {
            for j in 0..LANES {
                // t + (td or +0.0): adding +0.0 leaves t as it is, so this is OctoMap's update.
                let add = f64::from_bits(self.td[i][j].to_bits() & mask[i][j]);
                self.t[i][j] += add;
                let m = mask[i][j] as i32;
                self.c[i][j] = self.c[i][j].wrapping_add(self.step[i][j] & m);
                if plane {
                    self.index[j] = self.index[j].wrapping_add(self.stride[i][j] & m);
                }
            }
        }
        let mut done = [false; LANES];
        let mut outside = [false; LANES];
        for j in 0..LANES {
            self.left[j] = self.left[j].wrapping_sub(1);
            let at_end = (self.left[j] == 0)
                & (self.c[0][j] == self.e[0][j])
                & (self.c[1][j] == self.e[1][j])
                & (self.c[2][j] == self.e[2][j]);
            // min(t) as OctoMap's std::min chain (no NaN handling needed: t is never NaN).
            let (n0, n1, n2) = (self.t[0][j], self.t[1][j], self.t[2][j]);
            let m01 = if n0 < n1 { n0 } else { n1 };
            let t_min = if m01 < n2 { m01 } else { n2 };
            done[j] = at_end | (t_min > self.length[j]);
            outside[j] = plane
                & (((self.c[0][j].wrapping_sub(g.lo[0]) as u32) >= g.n[0])
                    | ((self.c[1][j].wrapping_sub(g.lo[1]) as u32) >= g.n[1])
                    | ((self.c[2][j].wrapping_sub(g.lo[2]) as u32) >= g.n[2]));
        }
        // Eight 0/1 bytes to eight bits with one multiply (lane j's byte lands in bit j).
        let bits = |v: &[bool; LANES]| {
            let bytes = v.map(u8::from);
            (u64::from_le_bytes(bytes).wrapping_mul(0x0102_0408_1020_4080) >> 56) as u32
        };
        (bits(&done), bits(&outside))
    }

    #[inline(always)]
    fn key(&self, j: usize) -> [i32; 3] {
        [self.c[0][j], self.c[1][j], self.c[2][j]]
    }

    #[inline(always)]
    fn key_end(&self, j: usize) -> [i32; 3] {
        [self.e[0][j], self.e[1][j], self.e[2][j]]
    }
}

/// Walks many rays, [`LANES`] at a time (each walk is a chain of dependent floating-point steps;
/// independent rays side by side keep the core busy and let the steps run as vector code).
/// Gives `v` every free voxel of every ray, exactly as [`RaySetup::walk`] would, interleaved
/// between rays but in order within a ray, with its bit index in `g`'s plane.
pub(crate) fn walk_lanes<V: LaneVisitor>(
    rays: impl Iterator<Item = (u32, RaySetup)>,
    g: &PlaneGeometry,
    v: &mut V,
) {
    walk_lanes_at(crate::simd::level(), rays, g, v)
}

/// [`walk_lanes`] on a given vector unit (`level` must not exceed [`crate::simd::detected`]).
pub(crate) fn walk_lanes_at<V: LaneVisitor>(
    level: crate::simd::Level,
    rays: impl Iterator<Item = (u32, RaySetup)>,
    g: &PlaneGeometry,
    v: &mut V,
) {
    let level = level.min(crate::simd::detected());
    #[cfg(target_arch = "x86_64")]
    match level {
        crate::simd::Level::Avx512 => return x86::walk_lanes_avx512(rays, g, v),
        crate::simd::Level::Avx2 => return x86::walk_lanes_avx2(rays, g, v),
        crate::simd::Level::Portable => {}
    }
    walk_lanes_portable(rays, g, v)
}

/// The same walk compiled for wider vector units; chosen at run time by [`crate::simd::level`].
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod x86 {
    use super::*;

    #[target_feature(enable = "avx2,fma,bmi1,bmi2,popcnt,lzcnt")]
    unsafe fn avx2<V: LaneVisitor>(
        rays: impl Iterator<Item = (u32, RaySetup)>,
        g: &PlaneGeometry,
        v: &mut V,
    ) {
        walk_in_registers(rays, g, v, |l, g, v| clean_steps_avx2(l, g, v))
    }

    #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma,bmi1,bmi2,popcnt,lzcnt")]
    unsafe fn avx512<V: LaneVisitor>(
        rays: impl Iterator<Item = (u32, RaySetup)>,
        g: &PlaneGeometry,
        v: &mut V,
    ) {
        walk_in_registers(rays, g, v, |l, g, v| clean_steps(l, g, v))
    }

    /// The lane walk with the whole steps in registers: while every lane holds a ray, `steps`
    /// runs them (a `clean_steps` of one vector unit); the last rays, fewer than eight, finish
    /// on the compiled walk. Inlined into each unit's function, so it is compiled for that unit.
    #[inline(always)]
    fn walk_in_registers<V: LaneVisitor>(
        mut rays: impl Iterator<Item = (u32, RaySetup)>,
        g: &PlaneGeometry,
        v: &mut V,
        steps: impl Fn(&mut Lanes, &PlaneGeometry, &mut V) -> (u32, u32),
    ) {
        if !(V::WHOLE_STEPS && V::PLANE) {
            return walk_lanes_portable(rays, g, v);
        }
        let (mut lanes, mut active) = start_lanes(&mut rays, g, v);
        while active == ALL_LANES {
            let masks = steps(&mut lanes, g, v);
            active = settle(&mut lanes, active, masks, &mut rays, g, v);
        }
        finish_lanes(lanes, active, rays, g, v)
    }

    /// The lane fields a whole step reads, in one vector unit's registers: `T` holds eight
    /// `f64`, `I` eight `i32` (`left` as `i32`, wrapping like the `u32` it is).
    struct Regs<T, I> {
        t: [T; 3],
        td: [T; 3],
        c: [I; 3],
        e: [I; 3],
        step: [I; 3],
        stride: [I; 3],
        index: I,
        left: I,
        length: T,
    }

    impl<T: Copy, I: Copy> Regs<T, I> {
        #[inline(always)]
        fn load(
            lanes: &Lanes,
            ld_t: impl Fn(&[f64; LANES]) -> T,
            ld_i: impl Fn(&[i32; LANES]) -> I,
        ) -> Self {
            let fields = |a: &[[i32; LANES]; 3]| a.each_ref().map(&ld_i);
            Self {
                t: lanes.t.each_ref().map(&ld_t),
                td: lanes.td.each_ref().map(&ld_t),
                c: fields(&lanes.c),
                e: fields(&lanes.e),
                step: fields(&lanes.step),
                stride: fields(&lanes.stride),
                index: ld_i(&lanes.index),
                left: ld_i(&lanes.left.map(|l| l as i32)),
                length: ld_t(&lanes.length),
            }
        }

        /// Stores what the steps changed: `t`, the keys, the bit index and the steps left.
        #[inline(always)]
        fn store(
            &self,
            lanes: &mut Lanes,
            st_t: impl Fn(&mut [f64; LANES], T),
            st_i: impl Fn(&mut [i32; LANES], I),
        ) {
            for axis in 0..3 {
                st_t(&mut lanes.t[axis], self.t[axis]);
                st_i(&mut lanes.c[axis], self.c[axis]);
            }
            st_i(&mut lanes.index, self.index);
            let mut left = [0i32; LANES];
            st_i(&mut left, self.left);
            lanes.left = left.map(|l| l as u32);
        }
    }

    /// [`Lanes::advance`] with the lanes held in AVX-512 registers: steps every lane and gives
    /// the eight voxels to [`LaneVisitor::mark_lanes`] for as long as no lane is done or outside
    /// the plane and the visitor takes the whole step; returns the (done, outside) masks of the
    /// first step where that fails, as `advance` does, with the lanes stored back. The same
    /// `f64` operations as `advance`: a compare for each of its `<`, a masked add where it adds
    /// `td` or `+0.0`, `min` as its `if a < b { a } else { b }`.
    #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2")]
    fn clean_steps<V: LaneVisitor>(lanes: &mut Lanes, g: &PlaneGeometry, v: &mut V) -> (u32, u32) {
        use std::arch::x86_64::*;
        // SAFETY: every pointer is to an array of eight `f64` (64 bytes) or eight `i32`/`u32`
        // (32 bytes) in `lanes` or on the stack, loaded and stored unaligned.
        unsafe {
            let ld_t = |a: &[f64; LANES]| _mm512_loadu_pd(a.as_ptr());
            let ld_i = |a: &[i32; LANES]| _mm256_loadu_si256(a.as_ptr().cast());
            let mut r = Regs::load(lanes, ld_t, ld_i);
            let lo = g.lo.map(|k| _mm256_set1_epi32(k));
            let n = g.n.map(|n| _mm256_set1_epi32(n as i32));
            let (one, zero) = (_mm256_set1_epi32(1), _mm256_setzero_si256());
            let mut marks = [0i32; LANES];
            let (done, outside) = loop {
                let [t0, t1, t2] = r.t;
                let a = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(t0, t1);
                let x = a & _mm512_cmp_pd_mask::<_CMP_LT_OQ>(t0, t2);
                let y = !a & _mm512_cmp_pd_mask::<_CMP_LT_OQ>(t1, t2);
                let z = !(x | y);
                for (axis, m) in [x, y, z].into_iter().enumerate() {
                    r.t[axis] = _mm512_mask_add_pd(r.t[axis], m, r.t[axis], r.td[axis]);
                    r.c[axis] = _mm256_mask_add_epi32(r.c[axis], m, r.c[axis], r.step[axis]);
                    r.index = _mm256_mask_add_epi32(r.index, m, r.index, r.stride[axis]);
                }
                r.left = _mm256_sub_epi32(r.left, one);
                let [c0, c1, c2] = r.c;
                let at_end = _mm256_cmpeq_epi32_mask(r.left, zero)
                    & _mm256_cmpeq_epi32_mask(c0, r.e[0])
                    & _mm256_cmpeq_epi32_mask(c1, r.e[1])
                    & _mm256_cmpeq_epi32_mask(c2, r.e[2]);
                let t_min = _mm512_min_pd(_mm512_min_pd(r.t[0], r.t[1]), r.t[2]);
                let done = at_end | _mm512_cmp_pd_mask::<_CMP_GT_OQ>(t_min, r.length);
                let outside = _mm256_cmpge_epu32_mask(_mm256_sub_epi32(c0, lo[0]), n[0])
                    | _mm256_cmpge_epu32_mask(_mm256_sub_epi32(c1, lo[1]), n[1])
                    | _mm256_cmpge_epu32_mask(_mm256_sub_epi32(c2, lo[2]), n[2]);
                if done | outside != 0 {
                    break (u32::from(done), u32::from(outside));
                }
                _mm256_storeu_si256(marks.as_mut_ptr().cast(), r.index);
                if !v.mark_lanes(&marks) {
                    break (0, 0);
                }
            };
            let st_t = |a: &mut [f64; LANES], v| _mm512_storeu_pd(a.as_mut_ptr(), v);
            let st_i = |a: &mut [i32; LANES], v| _mm256_storeu_si256(a.as_mut_ptr().cast(), v);
            r.store(lanes, st_t, st_i);
            (done, outside)
        }
    }

    /// The two halves of an eight-lane `f64` field, each made by `f` (0: lanes 0-3, 1: 4-7).
    #[inline(always)]
    fn half<T>(f: impl Fn(usize) -> T) -> [T; 2] {
        [f(0), f(1)]
    }

    /// [`clean_steps`] for AVX2: the eight lanes' `f64` fields in two 256-bit registers each
    /// (lanes 0-3 and 4-7), their `i32` fields in one, held in the order 0, 1, 4, 5, 2, 3, 6, 7
    /// in which one `shufps` narrows a pair of `f64` compare masks, so no step reorders a
    /// mask. The same `f64` operations as [`Lanes::advance`]: `t + (td & mask)`, the
    /// compares of its `<`, `min` as its `if a < b { a } else { b }` (`minpd` returns the
    /// second operand unless the first is less).
    #[target_feature(enable = "avx2")]
    fn clean_steps_avx2<V: LaneVisitor>(
        lanes: &mut Lanes,
        g: &PlaneGeometry,
        v: &mut V,
    ) -> (u32, u32) {
        use std::arch::x86_64::*;
        // SAFETY: every pointer is to an array of eight `f64` (two loads or stores of four) or
        // eight `i32` in `lanes` or on the stack, loaded and stored unaligned.
        unsafe {
            // Lane order of the i32 registers; the same permutation undoes itself.
            let order = _mm256_setr_epi32(0, 1, 4, 5, 2, 3, 6, 7);
            let ld_t = |a: &[f64; LANES]| {
                let p = a.as_ptr();
                [_mm256_loadu_pd(p), _mm256_loadu_pd(p.add(4))]
            };
            let ld_i = |a: &[i32; LANES]| {
                _mm256_permutevar8x32_epi32(_mm256_loadu_si256(a.as_ptr().cast()), order)
            };
            // Two 4 × f64 compare masks as one 8 × i32 mask, in the registers' lane order.
            let narrow = |m: [__m256d; 2]| {
                _mm256_castps_si256(_mm256_shuffle_ps::<0b10_00_10_00>(
                    _mm256_castpd_ps(m[0]),
                    _mm256_castpd_ps(m[1]),
                ))
            };
            let mut r = Regs::load(lanes, ld_t, ld_i);
            let lo = g.lo.map(|k| _mm256_set1_epi32(k));
            let n = g.n.map(|n| _mm256_set1_epi32(n as i32));
            let (one, zero) = (_mm256_set1_epi32(1), _mm256_setzero_si256());
            // Lanes whose key left the box: (c − lo) as u32 ≥ n, i.e. max(c − lo, n) = c − lo.
            let out = |axis: usize, c: __m256i| {
                let d = _mm256_sub_epi32(c, lo[axis]);
                _mm256_cmpeq_epi32(_mm256_max_epu32(d, n[axis]), d)
            };
            let mut marks = [0i32; LANES];
            let (done, outside) = loop {
                let [t0, t1, t2] = r.t;
                let a = half(|h| _mm256_cmp_pd::<_CMP_LT_OQ>(t0[h], t1[h]));
                let x = half(|h| _mm256_and_pd(a[h], _mm256_cmp_pd::<_CMP_LT_OQ>(t0[h], t2[h])));
                let y = half(|h| _mm256_andnot_pd(a[h], _mm256_cmp_pd::<_CMP_LT_OQ>(t1[h], t2[h])));
                let not_z = half(|h| _mm256_or_pd(x[h], y[h]));
                let [td0, td1, td2] = r.td;
                r.t[0] = half(|h| _mm256_add_pd(t0[h], _mm256_and_pd(td0[h], x[h])));
                r.t[1] = half(|h| _mm256_add_pd(t1[h], _mm256_and_pd(td1[h], y[h])));
                r.t[2] = half(|h| _mm256_add_pd(t2[h], _mm256_andnot_pd(not_z[h], td2[h])));
                let (x, y, not_z) = (narrow(x), narrow(y), narrow(not_z));
                // Lane masks for axes 0 and 1; axis 2 takes the rest (and-not).
                let chosen = |axis: usize, value: __m256i| match axis {
                    0 => _mm256_and_si256(value, x),
                    1 => _mm256_and_si256(value, y),
                    _ => _mm256_andnot_si256(not_z, value),
                };
                for axis in 0..3 {
                    r.c[axis] = _mm256_add_epi32(r.c[axis], chosen(axis, r.step[axis]));
                    r.index = _mm256_add_epi32(r.index, chosen(axis, r.stride[axis]));
                }
                r.left = _mm256_sub_epi32(r.left, one);
                let [c0, c1, c2] = r.c;
                let at_end = _mm256_and_si256(
                    _mm256_and_si256(
                        _mm256_cmpeq_epi32(r.left, zero),
                        _mm256_cmpeq_epi32(c0, r.e[0]),
                    ),
                    _mm256_and_si256(
                        _mm256_cmpeq_epi32(c1, r.e[1]),
                        _mm256_cmpeq_epi32(c2, r.e[2]),
                    ),
                );
                let beyond = half(|h| {
                    let t_min = _mm256_min_pd(_mm256_min_pd(r.t[0][h], r.t[1][h]), r.t[2][h]);
                    _mm256_cmp_pd::<_CMP_GT_OQ>(t_min, r.length[h])
                });
                let done = _mm256_or_si256(at_end, narrow(beyond));
                let outside = _mm256_or_si256(out(0, c0), _mm256_or_si256(out(1, c1), out(2, c2)));
                if _mm256_testz_si256(_mm256_or_si256(done, outside), _mm256_set1_epi32(-1)) == 0 {
                    let bits = |m: __m256i| {
                        let m = _mm256_permutevar8x32_epi32(m, order);
                        _mm256_movemask_ps(_mm256_castsi256_ps(m)) as u32
                    };
                    break (bits(done), bits(outside));
                }
                _mm256_storeu_si256(
                    marks.as_mut_ptr().cast(),
                    _mm256_permutevar8x32_epi32(r.index, order),
                );
                if !v.mark_lanes(&marks) {
                    break (0, 0);
                }
            };
            let st_t = |a: &mut [f64; LANES], v: [__m256d; 2]| {
                _mm256_storeu_pd(a.as_mut_ptr(), v[0]);
                _mm256_storeu_pd(a.as_mut_ptr().add(4), v[1]);
            };
            let st_i = |a: &mut [i32; LANES], v| {
                _mm256_storeu_si256(a.as_mut_ptr().cast(), _mm256_permutevar8x32_epi32(v, order))
            };
            r.store(lanes, st_t, st_i);
            (done, outside)
        }
    }

    pub(super) fn walk_lanes_avx2<V: LaneVisitor>(
        rays: impl Iterator<Item = (u32, RaySetup)>,
        g: &PlaneGeometry,
        v: &mut V,
    ) {
        // SAFETY: `simd::level` returns Avx2 only when the CPU reports these features.
        unsafe { avx2(rays, g, v) }
    }

    pub(super) fn walk_lanes_avx512<V: LaneVisitor>(
        rays: impl Iterator<Item = (u32, RaySetup)>,
        g: &PlaneGeometry,
        v: &mut V,
    ) {
        // SAFETY: `simd::level` returns Avx512 only when the CPU reports these features.
        unsafe { avx512(rays, g, v) }
    }
}

#[inline(always)]
fn walk_lanes_portable<V: LaneVisitor>(
    mut rays: impl Iterator<Item = (u32, RaySetup)>,
    g: &PlaneGeometry,
    v: &mut V,
) {
    let (lanes, active) = start_lanes(&mut rays, g, v);
    finish_lanes(lanes, active, rays, g, v)
}

/// Fills every lane it can; returns the lanes and the mask of those holding a ray.
#[inline(always)]
fn start_lanes<V: LaneVisitor>(
    rays: &mut impl Iterator<Item = (u32, RaySetup)>,
    g: &PlaneGeometry,
    v: &mut V,
) -> (Lanes, u32) {
    let mut lanes = Lanes::new();
    let mut active = 0u32;
    for j in 0..LANES {
        if refill(rays, &mut lanes, j, g, v) {
            active |= 1 << j;
        }
    }
    (lanes, active)
}

/// Steps the lanes until every ray is walked.
#[inline(always)]
fn finish_lanes<V: LaneVisitor>(
    mut lanes: Lanes,
    mut active: u32,
    mut rays: impl Iterator<Item = (u32, RaySetup)>,
    g: &PlaneGeometry,
    v: &mut V,
) {
    while active != 0 {
        // A constant per visitor type: the unused plane arithmetic is compiled out.
        let (done, outside) = lanes.advance(g, V::PLANE);
        if V::WHOLE_STEPS
            && active == ALL_LANES
            && done | outside == 0
            && v.mark_lanes(&lanes.index)
        {
            continue;
        }
        active = settle(&mut lanes, active, (done, outside), &mut rays, g, v);
    }
}

/// After a step: gives `v` each walking lane's voxel and each finished ray's end, and refills
/// the finished lanes. Returns the lanes still holding a ray.
#[inline(always)]
fn settle<V: LaneVisitor>(
    lanes: &mut Lanes,
    mut active: u32,
    (done, outside): (u32, u32),
    rays: &mut impl Iterator<Item = (u32, RaySetup)>,
    g: &PlaneGeometry,
    v: &mut V,
) -> u32 {
    let mut finished = done & active;
    for j in 0..LANES {
        if (active & !done) >> j & 1 != 0 {
            let inside = outside >> j & 1 == 0;
            if !v.voxel(j, lanes.ray[j], lanes.key(j), lanes.index[j], inside) {
                finished |= 1 << j;
            }
        } else if finished >> j & 1 != 0 {
            v.end(lanes.ray[j], lanes.key_end(j));
        }
    }
    while finished != 0 {
        let j = finished.trailing_zeros() as usize;
        finished &= finished - 1;
        if !refill(rays, lanes, j, g, v) {
            active &= !(1 << j);
        }
    }
    active
}

/// Puts the next ray whose origin voxel does not stop it into lane `j`; false when none is left.
#[inline(always)]
fn refill(
    rays: &mut impl Iterator<Item = (u32, RaySetup)>,
    lanes: &mut Lanes,
    j: usize,
    g: &PlaneGeometry,
    v: &mut impl LaneVisitor,
) -> bool {
    for (ray, s) in rays {
        let c = [s.key_origin.x, s.key_origin.y, s.key_origin.z];
        if v.voxel(j, ray, c, g.index_unchecked(c), g.inside(c)) {
            lanes.load(j, ray, &s, g);
            return true;
        }
    }
    false
}
