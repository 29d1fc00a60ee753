//! The camera's reachability (workspace) map: where the camera's optical centre can be placed.
//!
//! The paper samples the first five joints at 10° steps and marks the 2 cm cells of the camera
//! positions. Joint 1 only rotates the result about the base z axis, so this map samples joints
//! 2–5 (and 6 when the camera sits off the flange axis) with joint 1 at zero and stores, per cell
//! of a (radius from the base axis, height along it) table, the azimuths that joint 1 can turn
//! the sample to: every azimuth when joint 1 turns a full circle (the default), else a 64-bin
//! mask of the swept interval. That treats joint 1 as continuous, which is what the arm does, and
//! costs 36⁴ ≈ 1.7 M position evaluations instead of 36⁵.
//!
//! Cells are 2 cm in radius and height; a point is reachable when its (radius, height) cell was
//! hit by a sample (and, with a restricted joint 1, its azimuth bin is set).

use std::f64::consts::TAU;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use crate::error::{ensure_finite, invalid, ArmError, Result};
use crate::kinematics::{dh_frame, ArmModel, Frame, JointLimits, UrDh, JOINT_COUNT};
use crate::mount::{Mount, MountState};

const MAGIC: &[u8; 8] = b"GHREACH\0";
const FORMAT_VERSION: u32 = 1;
const AZIMUTH_BINS: usize = 64;
/// Cap on the table size (cells) and samples, so absurd parameters fail instead of exhausting
/// memory or time.
const MAX_CELLS: usize = 50_000_000;
const MAX_SAMPLES: f64 = 2e9;

/// Everything the map depends on; its hash names the cache file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReachabilityParams {
    pub dh: UrDh,
    pub limits: JointLimits,
    pub flange_from_camera: Isometry3<f64>,
    /// Joint sampling step, radians (paper: 10°).
    pub step_rad: f64,
    /// Cell edge, metres (paper: 2 cm).
    pub cell_m: f64,
}

impl ReachabilityParams {
    /// The paper's sampling (10° steps, 2 cm cells) for an arm model.
    pub fn paper(arm: &ArmModel) -> Self {
        Self {
            dh: arm.dh,
            limits: arm.limits,
            flange_from_camera: arm.flange_from_camera,
            step_rad: 10f64.to_radians(),
            cell_m: 0.02,
        }
    }

    fn validate(&self) -> Result<()> {
        self.dh.validate()?;
        self.limits.validate()?;
        ensure_finite(
            self.flange_from_camera.translation.vector.as_slice(),
            "flange_from_camera",
        )?;
        ensure_finite(
            self.flange_from_camera.rotation.coords.as_slice(),
            "flange_from_camera",
        )?;
        ensure_finite(&[self.step_rad, self.cell_m], "reachability step")?;
        if self.step_rad <= 0.0 {
            return Err(invalid("step_rad", "must be > 0"));
        }
        if self.cell_m <= 0.0 {
            return Err(invalid("cell_m", "must be > 0"));
        }
        Ok(())
    }

    /// Stable 64-bit key (FNV-1a over the bit patterns of every parameter and the file format
    /// version): the same parameters always give the same file name.
    pub fn cache_key(&self) -> u64 {
        let mut h = Fnv::new();
        h.write(&FORMAT_VERSION.to_le_bytes());
        let dh = &self.dh;
        for v in [dh.d1, dh.a2, dh.a3, dh.d4, dh.d5, dh.d6] {
            h.write_f64(v);
        }
        for v in self.limits.lower.iter().chain(&self.limits.upper) {
            h.write_f64(*v);
        }
        for v in self.flange_from_camera.translation.vector.iter() {
            h.write_f64(*v);
        }
        for v in self.flange_from_camera.rotation.coords.iter() {
            h.write_f64(*v);
        }
        h.write_f64(self.step_rad);
        h.write_f64(self.cell_m);
        h.finish()
    }

    /// File name of the cache for these parameters.
    pub fn cache_file_name(&self) -> String {
        format!("reachability-{:016x}.bin", self.cache_key())
    }

    /// Table layout: (radius cells, height cells, lowest height).
    fn layout(&self) -> Result<(usize, usize, f64)> {
        let bound = self.dh.reach_bound() + self.flange_from_camera.translation.vector.norm();
        let r_cells = (bound / self.cell_m).ceil() as usize + 1;
        let z_cells = 2 * r_cells;
        if r_cells.saturating_mul(z_cells) > MAX_CELLS {
            return Err(invalid("cell_m", "too small for the arm's size"));
        }
        Ok((r_cells, z_cells, -(r_cells as f64) * self.cell_m))
    }
}

struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.0 ^= u64::from(*b);
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
    }
    fn write_f64(&mut self, v: f64) {
        // +0.0 and -0.0 are the same parameter.
        let v = if v == 0.0 { 0.0 } else { v };
        self.write(&v.to_bits().to_le_bytes());
    }
    fn finish(&self) -> u64 {
        self.0
    }
}

/// How [`ReachabilityMap::load_or_build_with_status`] obtained the map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CacheStatus {
    /// Read from a valid cache file.
    Loaded,
    /// Built; there was no cache file.
    Built,
    /// Built; the cache file was unreadable or corrupt and has been replaced.
    Rebuilt,
}

/// Camera reachability in the base frame, with queries in the world for every kind of mount.
#[derive(Clone, Debug, PartialEq)]
pub struct ReachabilityMap {
    params: ReachabilityParams,
    r_cells: usize,
    z_cells: usize,
    z_min_m: f64,
    /// Azimuth bin masks, index `iz * r_cells + ir`.
    masks: Vec<u64>,
    /// Summed-area table of `mask != 0`, `(r_cells + 1) × (z_cells + 1)`, row `iz`.
    prefix: Vec<u32>,
}

/// Sample angles of a joint: a full circle at `step` when the joint turns one, else its range
/// from the lower limit at `step`, plus the upper limit.
fn joint_samples(limits: &JointLimits, joint: usize, step: f64) -> Vec<f64> {
    let (lo, hi) = (limits.lower[joint], limits.upper[joint]);
    if limits.is_full_circle(joint) {
        let n = (TAU / step - 1e-9).ceil().max(1.0) as usize;
        return (0..n).map(|k| k as f64 * step).collect();
    }
    let mut out = Vec::new();
    let mut k = 0usize;
    loop {
        let v = lo + k as f64 * step;
        if v > hi + 1e-12 {
            break;
        }
        out.push(v);
        k += 1;
    }
    if out.last().is_none_or(|last| hi - last > 1e-12) {
        out.push(hi);
    }
    out
}

/// Bins of `[start, start + len]` (radians) in a 64-bin azimuth mask.
fn arc_mask(start: f64, len: f64) -> u64 {
    if len >= TAU - 1e-12 {
        return u64::MAX;
    }
    let bin = TAU / AZIMUTH_BINS as f64;
    let first = (start.rem_euclid(TAU) / bin).floor() as i64;
    let last = ((start.rem_euclid(TAU) + len) / bin).floor() as i64;
    let mut mask = 0u64;
    for b in first..=last {
        mask |= 1u64 << (b.rem_euclid(AZIMUTH_BINS as i64) as u32);
    }
    mask
}

fn azimuth_bin(x: f64, y: f64) -> u32 {
    let bin = TAU / AZIMUTH_BINS as f64;
    ((y.atan2(x).rem_euclid(TAU) / bin).floor() as usize).min(AZIMUTH_BINS - 1) as u32
}

impl ReachabilityMap {
    /// Builds the map, using every available core. Errors for invalid parameters.
    pub fn build(params: &ReachabilityParams) -> Result<Self> {
        params.validate()?;
        let (r_cells, z_cells, z_min_m) = params.layout()?;
        let dh = params.dh;
        let limits = &params.limits;
        let step = params.step_rad;
        let camera = Point3::from(params.flange_from_camera.translation.vector);
        let off_axis = camera.x.hypot(camera.y) > 1e-9;
        let samples: Vec<Vec<f64>> = (1..JOINT_COUNT)
            .map(|j| {
                if j == 5 && !off_axis {
                    vec![0.0]
                } else {
                    joint_samples(limits, j, step)
                }
            })
            .collect();
        let total: f64 = samples.iter().map(|s| s.len() as f64).product();
        if total > MAX_SAMPLES {
            return Err(invalid("step_rad", "too small: too many samples"));
        }
        // Joints 2-4 as precomputed transforms per sample; joints 5 and 6 folded into the list of
        // camera positions in frame 4, so the inner loop is one rotation and a translation.
        let frames: Vec<Vec<Frame>> = samples
            .iter()
            .take(3)
            .enumerate()
            .map(|(k, angles)| angles.iter().map(|&a| dh_frame(&dh, k + 1, a)).collect())
            .collect();
        let mut tail: Vec<[f64; 3]> = Vec::new();
        for &q5 in samples.get(3).map(Vec::as_slice).unwrap_or(&[]) {
            for &q6 in samples.get(4).map(Vec::as_slice).unwrap_or(&[]) {
                let p = dh_frame(&dh, 4, q5)
                    .mul(&dh_frame(&dh, 5, q6))
                    .point(&camera);
                tail.push([p.x, p.y, p.z]);
            }
        }
        let base_to_1 = dh_frame(&dh, 0, 0.0);
        let (q1_lo, q1_hi) = (limits.lower[0], limits.upper[0]);
        let full_q1 = limits.is_full_circle(0);
        let cell = params.cell_m;

        let [f2, f3, f4] = match <[Vec<Frame>; 3]>::try_from(frames) {
            Ok(f) => f,
            Err(_) => return Err(invalid("joints", "expected three sampled joints")),
        };
        let threads = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
            .clamp(1, f2.len().max(1));
        let chunks: Vec<Vec<u64>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..threads)
                .map(|t| {
                    let (f2, f3, f4, tail) = (&f2, &f3, &f4, &tail);
                    scope.spawn(move || {
                        let mut masks = vec![0u64; r_cells * z_cells];
                        for a2 in f2.iter().skip(t).step_by(threads) {
                            let t2 = base_to_1.mul(a2);
                            for a3 in f3 {
                                let t3 = t2.mul(a3);
                                for a4 in f4 {
                                    let t4 = t3.mul(a4);
                                    let m: [f64; 9] = std::array::from_fn(|i| t4.r[(i / 3, i % 3)]);
                                    let (tx, ty, tz) = (t4.t.x, t4.t.y, t4.t.z);
                                    for v in tail {
                                        let x = m[0] * v[0] + m[1] * v[1] + m[2] * v[2] + tx;
                                        let y = m[3] * v[0] + m[4] * v[1] + m[5] * v[2] + ty;
                                        let z = m[6] * v[0] + m[7] * v[1] + m[8] * v[2] + tz;
                                        let ir = ((x * x + y * y).sqrt() / cell).floor();
                                        let iz = ((z - z_min_m) / cell).floor();
                                        if ir < 0.0
                                            || iz < 0.0
                                            || ir >= r_cells as f64
                                            || iz >= z_cells as f64
                                        {
                                            continue;
                                        }
                                        let bits = if full_q1 {
                                            u64::MAX
                                        } else {
                                            arc_mask(y.atan2(x) + q1_lo, q1_hi - q1_lo)
                                        };
                                        if let Some(mask) =
                                            masks.get_mut(iz as usize * r_cells + ir as usize)
                                        {
                                            *mask |= bits;
                                        }
                                    }
                                }
                            }
                        }
                        masks
                    })
                })
                .collect();
            handles.into_iter().filter_map(|h| h.join().ok()).collect()
        });
        if chunks.len() != threads {
            return Err(invalid("build", "a worker thread panicked"));
        }
        let mut masks = vec![0u64; r_cells * z_cells];
        for chunk in chunks {
            for (m, c) in masks.iter_mut().zip(chunk) {
                *m |= c;
            }
        }
        Ok(Self::from_parts(
            params.clone(),
            r_cells,
            z_cells,
            z_min_m,
            masks,
        ))
    }

    fn from_parts(
        params: ReachabilityParams,
        r_cells: usize,
        z_cells: usize,
        z_min_m: f64,
        masks: Vec<u64>,
    ) -> Self {
        let w = r_cells + 1;
        let mut prefix = vec![0u32; w * (z_cells + 1)];
        for iz in 0..z_cells {
            let mut row = 0u32;
            for ir in 0..r_cells {
                row += u32::from(masks[iz * r_cells + ir] != 0);
                prefix[(iz + 1) * w + ir + 1] = prefix[iz * w + ir + 1] + row;
            }
        }
        Self {
            params,
            r_cells,
            z_cells,
            z_min_m,
            masks,
            prefix,
        }
    }

    /// Loads the map for `params` from `dir` (created if missing), or builds it and writes the
    /// cache atomically (temporary file, then rename). A corrupt or mismatching cache file is
    /// rebuilt and replaced.
    pub fn load_or_build(dir: &Path, params: &ReachabilityParams) -> Result<Self> {
        Self::load_or_build_with_status(dir, params).map(|(map, _)| map)
    }

    /// [`ReachabilityMap::load_or_build`], also telling whether the cache was used.
    pub fn load_or_build_with_status(
        dir: &Path,
        params: &ReachabilityParams,
    ) -> Result<(Self, CacheStatus)> {
        params.validate()?;
        let path = dir.join(params.cache_file_name());
        let status = match fs::read(&path) {
            Ok(bytes) => match Self::decode(&bytes, params) {
                Some(map) => return Ok((map, CacheStatus::Loaded)),
                None => CacheStatus::Rebuilt,
            },
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => CacheStatus::Built,
            Err(_) => CacheStatus::Rebuilt,
        };
        let map = Self::build(params)?;
        map.write_atomically(dir, &path)?;
        Ok((map, status))
    }

    /// Path of the cache file for `params` in `dir`.
    pub fn cache_path(dir: &Path, params: &ReachabilityParams) -> PathBuf {
        dir.join(params.cache_file_name())
    }

    fn write_atomically(&self, dir: &Path, path: &Path) -> Result<()> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| ArmError::Io { path, source }
        };
        fs::create_dir_all(dir).map_err(io(dir))?;
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        let tmp = dir.join(format!(
            ".{}.tmp-{}-{}",
            self.params.cache_file_name(),
            std::process::id(),
            nanos
        ));
        let result = (|| {
            let mut file = fs::File::create(&tmp).map_err(io(&tmp))?;
            file.write_all(&self.encode()).map_err(io(&tmp))?;
            file.sync_all().map_err(io(&tmp))?;
            drop(file);
            fs::rename(&tmp, path).map_err(io(path))
        })();
        if result.is_err() {
            let _ = fs::remove_file(&tmp);
        }
        result
    }

    fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(48 + 8 * self.masks.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&self.params.cache_key().to_le_bytes());
        out.extend_from_slice(&(self.r_cells as u64).to_le_bytes());
        out.extend_from_slice(&(self.z_cells as u64).to_le_bytes());
        out.extend_from_slice(&self.z_min_m.to_bits().to_le_bytes());
        for m in &self.masks {
            out.extend_from_slice(&m.to_le_bytes());
        }
        let mut h = Fnv::new();
        h.write(&out);
        out.extend_from_slice(&h.finish().to_le_bytes());
        out
    }

    /// The map in `bytes` if it is intact and was built from `params`.
    fn decode(bytes: &[u8], params: &ReachabilityParams) -> Option<Self> {
        let (body, sum) = bytes.split_at_checked(bytes.len().checked_sub(8)?)?;
        let mut h = Fnv::new();
        h.write(body);
        if h.finish() != u64::from_le_bytes(sum.try_into().ok()?) {
            return None;
        }
        let (magic, rest) = body.split_at_checked(8)?;
        if magic != MAGIC {
            return None;
        }
        let mut words = rest.get(4..)?.chunks_exact(8).map(|c| {
            let mut b = [0u8; 8];
            b.copy_from_slice(c);
            u64::from_le_bytes(b)
        });
        let version = u32::from_le_bytes(rest.get(..4)?.try_into().ok()?);
        let key = words.next()?;
        let r_cells = usize::try_from(words.next()?).ok()?;
        let z_cells = usize::try_from(words.next()?).ok()?;
        let z_min_m = f64::from_bits(words.next()?);
        let (want_r, want_z, want_zmin) = params.layout().ok()?;
        if version != FORMAT_VERSION
            || key != params.cache_key()
            || (r_cells, z_cells) != (want_r, want_z)
            || z_min_m.to_bits() != want_zmin.to_bits()
        {
            return None;
        }
        let masks: Vec<u64> = words.collect();
        if masks.len() != r_cells * z_cells || (rest.len() - 4) % 8 != 0 {
            return None;
        }
        Some(Self::from_parts(
            params.clone(),
            r_cells,
            z_cells,
            z_min_m,
            masks,
        ))
    }

    pub fn params(&self) -> &ReachabilityParams {
        &self.params
    }

    /// Number of (radius, height) cells that some sample reached.
    pub fn reached_cell_count(&self) -> usize {
        self.masks.iter().filter(|m| **m != 0).count()
    }

    /// Largest distance from the base axis and the height range (base frame) of the reached
    /// cells, outer cell edges; None for an empty map.
    pub fn extent_in_base(&self) -> Option<(f64, f64, f64)> {
        let cell = self.params.cell_m;
        let mut r_max: Option<usize> = None;
        let mut z_lo: Option<usize> = None;
        let mut z_hi: Option<usize> = None;
        for (i, m) in self.masks.iter().enumerate() {
            if *m != 0 {
                let (iz, ir) = (i / self.r_cells, i % self.r_cells);
                r_max = Some(r_max.map_or(ir, |v| v.max(ir)));
                z_lo = Some(z_lo.map_or(iz, |v| v.min(iz)));
                z_hi = Some(z_hi.map_or(iz, |v| v.max(iz)));
            }
        }
        Some((
            (r_max? + 1) as f64 * cell,
            self.z_min_m + z_lo? as f64 * cell,
            self.z_min_m + (z_hi? + 1) as f64 * cell,
        ))
    }

    fn cell_index(&self, r: f64, z: f64) -> Option<(usize, usize)> {
        let ir = (r / self.params.cell_m).floor();
        let iz = ((z - self.z_min_m) / self.params.cell_m).floor();
        if ir >= 0.0 && iz >= 0.0 && ir < self.r_cells as f64 && iz < self.z_cells as f64 {
            Some((ir as usize, iz as usize))
        } else {
            None
        }
    }

    /// Can the camera's optical centre be placed at `p` (base frame)? False for non-finite `p`.
    pub fn contains_in_base(&self, p: &Point3<f64>) -> bool {
        if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
            return false;
        }
        let Some((ir, iz)) = self.cell_index(p.x.hypot(p.y), p.z) else {
            return false;
        };
        let mask = self.masks.get(iz * self.r_cells + ir).copied().unwrap_or(0);
        mask != 0 && (mask == u64::MAX || mask & (1u64 << azimuth_bin(p.x, p.y)) != 0)
    }

    /// Can the camera reach world point `p` with the mount in `state`?
    pub fn contains_in_world(
        &self,
        mount: &Mount,
        state: &MountState,
        p: &Point3<f64>,
    ) -> Result<bool> {
        ensure_finite(p.coords.as_slice(), "point")?;
        let base = mount.world_from_base(state)?;
        Ok(self.contains_in_base(&base.inverse_transform_point(p)))
    }

    /// Can the camera reach world point `p` for some state of the mount? O(1): for a moving
    /// mount the point's (radius, height) in the base frame sweeps a rectangle over the mount's
    /// ranges, tested against a summed-area table. With a joint 1 that cannot turn a full circle,
    /// the azimuth is ignored for moving mounts (an over-approximation).
    pub fn reachable_for_some_state(&self, mount: &Mount, p: &Point3<f64>) -> Result<bool> {
        ensure_finite(p.coords.as_slice(), "point")?;
        mount.validate()?;
        let Some((r, z)) = mount.swept_cylindrical_range(p) else {
            return self.contains_in_world(mount, &MountState::Fixed, p);
        };
        let cell = self.params.cell_m;
        let clamp_r = |v: f64| (v / cell).floor().clamp(-1.0, self.r_cells as f64);
        let clamp_z = |v: f64| {
            ((v - self.z_min_m) / cell)
                .floor()
                .clamp(-1.0, self.z_cells as f64)
        };
        let (r0, r1) = (
            clamp_r(r.min).max(0.0),
            clamp_r(r.max).min(self.r_cells as f64 - 1.0),
        );
        let (z0, z1) = (
            clamp_z(z.min).max(0.0),
            clamp_z(z.max).min(self.z_cells as f64 - 1.0),
        );
        if r0 > r1 || z0 > z1 {
            return Ok(false);
        }
        let (r0, r1, z0, z1) = (r0 as usize, r1 as usize + 1, z0 as usize, z1 as usize + 1);
        let w = self.r_cells + 1;
        let at =
            |iz: usize, ir: usize| i64::from(self.prefix.get(iz * w + ir).copied().unwrap_or(0));
        Ok(at(z1, r1) - at(z0, r1) - at(z1, r0) + at(z0, r0) > 0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arc_masks() {
        assert_eq!(arc_mask(0.0, TAU), u64::MAX);
        assert_eq!(arc_mask(0.01, 0.0), 1);
        // Wraps past 2π.
        let m = arc_mask(TAU - 0.01, 0.05);
        assert_eq!(m, 1 | (1 << 63));
    }

    #[test]
    fn joint_samples_cover_the_range_once() {
        let mut limits = JointLimits::ur5e_elbow_pi();
        let step = 10f64.to_radians();
        // ±2π and ±π are both one full circle: 36 samples.
        assert_eq!(joint_samples(&limits, 0, step).len(), 36);
        assert_eq!(joint_samples(&limits, 2, step).len(), 36);
        limits.lower[2] = -std::f64::consts::FRAC_PI_2;
        limits.upper[2] = 1.6;
        let elbow = joint_samples(&limits, 2, step);
        // -90°..90° in 19 steps plus the upper limit.
        assert_eq!(elbow.len(), 20);
        assert_eq!(elbow.first(), Some(&-std::f64::consts::FRAC_PI_2));
        assert_eq!(elbow.last(), Some(&1.6));
    }
}
