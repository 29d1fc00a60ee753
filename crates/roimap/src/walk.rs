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
        if key_origin == key_end {
            return None;
        }
        let mut direction = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
        let length = norm_f32(direction) as f32;
        for d in &mut direction {
            *d /= length;
        }
        let half = [
            (res * 0.5) as f32,
            (-res * 0.5) as f32, // (float)(step * res * 0.5) for step = -1
        ];
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
            let border = (f64::from(ko[i]) + 0.5) * res
                + f64::from(if step[i] > 0 { half[0] } else { half[1] });
            t_max[i] = (border - f64::from(origin[i])) / f64::from(d);
            t_delta[i] = res / f64::from(d).abs();
        }
        Some(Self {
            key_origin,
            key_end,
            step,
            t_max,
            t_delta,
            length: f64::from(length),
        })
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
            let border = (f64::from(ko[i]) + 0.5) * res + f64::from(step[i]) * res * 0.5;
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

/// One ray in flight in [`walk_interleaved`].
#[derive(Clone, Copy)]
struct Lane {
    t: [f64; 3],
    td: [f64; 3],
    c: [i32; 3],
    e: [i32; 3],
    step: [i32; 3],
    left: u64,
    length: f64,
}

impl Lane {
    fn start(s: &RaySetup) -> Self {
        let c = [s.key_origin.x, s.key_origin.y, s.key_origin.z];
        let e = [s.key_end.x, s.key_end.y, s.key_end.z];
        Self {
            t: s.t_max,
            td: s.t_delta,
            c,
            e,
            step: s.step,
            left: (0..3).map(|i| u64::from(c[i].abs_diff(e[i]))).sum(),
            length: s.length,
        }
    }

    /// One step of [`RaySetup::walk`] without dynamic indexing (the axis choice becomes
    /// selects): the next free voxel, or `None` when the ray is done.
    #[inline(always)]
    fn advance(&mut self) -> Option<[i32; 3]> {
        let [t0, t1, t2] = self.t;
        let a = t0 < t1;
        let x = a & (t0 < t2);
        let y = !a & (t1 < t2);
        let z = !(x | y);
        self.t = [
            t0 + if x { self.td[0] } else { 0.0 },
            t1 + if y { self.td[1] } else { 0.0 },
            t2 + if z { self.td[2] } else { 0.0 },
        ];
        self.c[0] += self.step[0] & -i32::from(x);
        self.c[1] += self.step[1] & -i32::from(y);
        self.c[2] += self.step[2] & -i32::from(z);
        self.left = self.left.wrapping_sub(1);
        if self.left == 0 && self.c == self.e {
            return None;
        }
        // min(t) as OctoMap's std::min chain (no NaN handling needed: t is never NaN).
        let m01 = if self.t[0] < self.t[1] {
            self.t[0]
        } else {
            self.t[1]
        };
        let t_min = if m01 < self.t[2] { m01 } else { self.t[2] };
        if t_min > self.length {
            return None;
        }
        Some(self.c)
    }
}

/// Rays walked side by side by [`walk_interleaved`].
const LANES: usize = 8;

/// [`LANES`] rays in flight, one array per field, so that one step of every lane is the same
/// arithmetic on arrays (the compiler turns the loop in [`Lanes::advance`] into vector code).
#[derive(Clone, Copy)]
struct Lanes {
    t: [[f64; LANES]; 3],
    td: [[f64; LANES]; 3],
    c: [[i32; LANES]; 3],
    e: [[i32; LANES]; 3],
    step: [[i32; LANES]; 3],
    left: [u64; LANES],
    length: [f64; LANES],
}

impl Lanes {
    fn new(first: &[Lane; LANES]) -> Self {
        let mut out = Self {
            t: [[0.0; LANES]; 3],
            td: [[0.0; LANES]; 3],
            c: [[0; LANES]; 3],
            e: [[0; LANES]; 3],
            step: [[0; LANES]; 3],
            left: [0; LANES],
            length: [0.0; LANES],
        };
        for (j, l) in first.iter().enumerate() {
            out.load(j, l);
        }
        out
    }

    fn load(&mut self, j: usize, l: &Lane) {
        for i in 0..3 {
            self.t[i][j] = l.t[i];
            self.td[i][j] = l.td[i];
            self.c[i][j] = l.c[i];
            self.e[i][j] = l.e[i];
            self.step[i][j] = l.step[i];
        }
        self.left[j] = l.left;
        self.length[j] = l.length;
    }

    fn lane(&self, j: usize) -> Lane {
        Lane {
            t: [0, 1, 2].map(|i| self.t[i][j]),
            td: [0, 1, 2].map(|i| self.td[i][j]),
            c: [0, 1, 2].map(|i| self.c[i][j]),
            e: [0, 1, 2].map(|i| self.e[i][j]),
            step: [0, 1, 2].map(|i| self.step[i][j]),
            left: self.left[j],
            length: self.length[j],
        }
    }

    /// [`Lane::advance`] for every lane at once; bit `j` of the result is set when lane `j`'s
    /// ray is done (its new voxel is then not a free voxel).
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // one index over seven arrays
    fn advance(&mut self) -> u32 {
        let mut done = [false; LANES];
        for j in 0..LANES {
            let (t0, t1, t2) = (self.t[0][j], self.t[1][j], self.t[2][j]);
            let a = t0 < t1;
            let x = a & (t0 < t2);
            let y = !a & (t1 < t2);
            let z = !(x | y);
            let n0 = t0 + if x { self.td[0][j] } else { 0.0 };
            let n1 = t1 + if y { self.td[1][j] } else { 0.0 };
            let n2 = t2 + if z { self.td[2][j] } else { 0.0 };
            self.t[0][j] = n0;
            self.t[1][j] = n1;
            self.t[2][j] = n2;
            self.c[0][j] += self.step[0][j] & -i32::from(x);
            self.c[1][j] += self.step[1][j] & -i32::from(y);
            self.c[2][j] += self.step[2][j] & -i32::from(z);
            self.left[j] = self.left[j].wrapping_sub(1);
            let at_end = (self.left[j] == 0)
                & (self.c[0][j] == self.e[0][j])
                & (self.c[1][j] == self.e[1][j])
                & (self.c[2][j] == self.e[2][j]);
            let m01 = if n0 < n1 { n0 } else { n1 };
            let t_min = if m01 < n2 { m01 } else { n2 };
            done[j] = at_end | (t_min > self.length[j]);
        }
        done.iter()
            .enumerate()
            .fold(0u32, |acc, (j, &d)| acc | u32::from(d) << j)
    }
}

/// Walks many rays, [`LANES`] at a time (each walk is a chain of dependent floating-point steps;
/// independent rays side by side keep the core busy and let the steps run as vector code).
/// Calls `visit` with every free voxel of every ray, exactly as [`RaySetup::walk`] would, in an
/// interleaved order.
pub(crate) fn walk_interleaved(
    mut rays: impl Iterator<Item = RaySetup>,
    mut visit: impl FnMut([i32; 3]),
) {
    let mut start = |visit: &mut dyn FnMut([i32; 3])| {
        rays.next().map(|s| {
            visit([s.key_origin.x, s.key_origin.y, s.key_origin.z]);
            Lane::start(&s)
        })
    };
    let mut first = Vec::with_capacity(LANES);
    while first.len() < LANES {
        match start(&mut visit) {
            Some(l) => first.push(l),
            None => break,
        }
    }
    let Ok(first) = <[Lane; LANES]>::try_from(first.as_slice()) else {
        // Fewer rays than lanes: one at a time.
        for mut l in first {
            while let Some(c) = l.advance() {
                visit(c);
            }
        }
        return;
    };
    let mut lanes = Lanes::new(&first);
    // Every lane busy; a finished lane takes the next ray. When there is none, the lanes still
    // running are finished one by one.
    let mut rest: Vec<Lane> = Vec::new();
    'steps: loop {
        let done = lanes.advance();
        for j in 0..LANES {
            if done >> j & 1 == 0 {
                visit([lanes.c[0][j], lanes.c[1][j], lanes.c[2][j]]);
                continue;
            }
            match start(&mut visit) {
                Some(next) => lanes.load(j, &next),
                None => {
                    // Lanes before `j` are up to date; lanes after it have stepped but not
                    // yet visited their new voxel.
                    rest.extend((0..j).map(|k| lanes.lane(k)));
                    for k in j + 1..LANES {
                        if done >> k & 1 == 0 {
                            visit([lanes.c[0][k], lanes.c[1][k], lanes.c[2][k]]);
                            rest.push(lanes.lane(k));
                        }
                    }
                    break 'steps;
                }
            }
        }
    }
    for mut l in rest {
        while let Some(c) = l.advance() {
            visit(c);
        }
    }
}
