//! Probabilistic ROI voxel map with OctoMap insertion semantics.
//!
//! The map is a sparse grid of cubic voxels (1 cm by default) in the world frame (z up, metres).
//! Voxel `i` along an axis covers `[i * res, (i + 1) * res)`, so keys come from `floor`, not
//! truncation, and negative coordinates get negative keys. Every voxel holds two log-odds values:
//!
//! - **occupancy**, updated exactly like OctoMap's `insertPointCloud(cloud, origin, maxrange)` with
//!   `discretize = false`: per scan, the voxels crossed by the rays (Amanatides–Woo walk, end voxel
//!   excluded) form a *free* set, the end-point voxels an *occupied* set, occupied wins over free,
//!   and each voxel is updated once per scan (hit +0.8473, miss −0.4055, clamped to [−2.0, 3.5110]);
//! - **ROI** (fruit), updated from the scan's end points only: ROI points' voxels get a hit, the other
//!   end-point voxels a miss unless some ROI point of the same scan fell in them (ROI wins). A voxel is
//!   an ROI voxel when its ROI log-odds is at least the threshold (1.0 by default: two observations).
//!
//! **Free/unknown rule** (the original code had two; we use one everywhere): a voxel that was never
//! updated is [`Occupancy::Unknown`]; a voxel whose occupancy log-odds is `> 0` is
//! [`Occupancy::Occupied`]; every other updated voxel (log-odds `<= 0`) is [`Occupancy::Free`]. So a
//! single miss makes a voxel free.
//!
//! Keys are bounded: a coordinate more than `2^20` voxels from the origin (about 10 km at 1 cm) is
//! outside the map, like OctoMap's `coordToKeyChecked`; such points are skipped and counted.
//!
//! The map records which voxels changed since the last [`RoiMap::take_changes`], so replicas and
//! dashboards receive deltas rather than whole maps.

use std::collections::{HashMap, HashSet};
use std::hash::{BuildHasherDefault, Hasher};

use glasshouse_geom::Aabb;
use nalgebra::{Point3, Vector3};

/// Largest absolute key value (exclusive) a voxel may have; keeps rays finite and keys far from
/// `i32` overflow when stepping.
const KEY_LIMIT: i64 = 1 << 20;

/// Offsets of the 6-neighbourhood (face neighbours).
const NEIGHBOURS_6: [(i32, i32, i32); 6] = [
    (-1, 0, 0),
    (1, 0, 0),
    (0, -1, 0),
    (0, 1, 0),
    (0, 0, -1),
    (0, 0, 1),
];

/// Map parameters. [`Default`] gives the paper's values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapConfig {
    /// Voxel edge length in metres.
    pub resolution_m: f64,
    /// Occupancy/ROI log-odds added on a hit (p = 0.7).
    pub hit_logodds: f32,
    /// Occupancy/ROI log-odds added on a miss (p = 0.4).
    pub miss_logodds: f32,
    /// Lower clamp of both log-odds values (p = 0.12).
    pub clamp_min_logodds: f32,
    /// Upper clamp of both log-odds values (p = 0.97).
    pub clamp_max_logodds: f32,
    /// A voxel is ROI when its ROI log-odds is at least this.
    pub roi_threshold_logodds: f32,
    /// Sensor range in metres; `None` means unlimited (OctoMap's `maxrange < 0`).
    pub max_range_m: Option<f64>,
}

impl Default for MapConfig {
    fn default() -> Self {
        Self {
            resolution_m: 0.01,
            hit_logodds: 0.8473,
            miss_logodds: -0.4055,
            clamp_min_logodds: -2.0,
            clamp_max_logodds: 3.5110,
            roi_threshold_logodds: 1.0,
            max_range_m: None,
        }
    }
}

impl MapConfig {
    /// Checks that every value is finite and consistent.
    pub fn validate(&self) -> Result<(), MapError> {
        let bad = |msg: String| Err(MapError::InvalidConfig(msg));
        if !(self.resolution_m.is_finite() && self.resolution_m > 0.0) {
            return bad(format!(
                "resolution_m must be finite and > 0, got {}",
                self.resolution_m
            ));
        }
        if !(self.hit_logodds.is_finite() && self.hit_logodds > 0.0) {
            return bad(format!(
                "hit_logodds must be finite and > 0, got {}",
                self.hit_logodds
            ));
        }
        if !(self.miss_logodds.is_finite() && self.miss_logodds < 0.0) {
            return bad(format!(
                "miss_logodds must be finite and < 0, got {}",
                self.miss_logodds
            ));
        }
        // New voxels start at 0, so the clamp interval must contain it.
        if !(self.clamp_min_logodds.is_finite()
            && self.clamp_max_logodds.is_finite()
            && self.clamp_min_logodds <= 0.0
            && self.clamp_max_logodds >= 0.0
            && self.clamp_min_logodds < self.clamp_max_logodds)
        {
            return bad(format!(
                "clamps must be finite with min <= 0 <= max and min < max, got [{}, {}]",
                self.clamp_min_logodds, self.clamp_max_logodds
            ));
        }
        if !self.roi_threshold_logodds.is_finite() {
            return bad("roi_threshold_logodds must be finite".to_string());
        }
        if let Some(range) = self.max_range_m {
            if !(range.is_finite() && range > 0.0) {
                return bad(format!(
                    "max_range_m must be finite and > 0 when set, got {range}"
                ));
            }
        }
        Ok(())
    }
}

/// Integer voxel coordinates: voxel `x` covers `[x * res, (x + 1) * res)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VoxelKey {
    pub x: i32,
    pub y: i32,
    pub z: i32,
}

impl VoxelKey {
    pub const fn new(x: i32, y: i32, z: i32) -> Self {
        Self { x, y, z }
    }

    /// This key moved by the given offset.
    pub const fn offset(self, dx: i32, dy: i32, dz: i32) -> Self {
        Self::new(self.x + dx, self.y + dy, self.z + dz)
    }

    fn axis(self, i: usize) -> i32 {
        match i {
            0 => self.x,
            1 => self.y,
            _ => self.z,
        }
    }

    fn axis_mut(&mut self, i: usize) -> &mut i32 {
        match i {
            0 => &mut self.x,
            1 => &mut self.y,
            _ => &mut self.z,
        }
    }
}

/// The two log-odds values of one voxel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Voxel {
    pub occupancy_logodds: f32,
    pub roi_logodds: f32,
}

/// Occupancy state under the documented rule (see the crate docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Occupancy {
    Unknown,
    Free,
    Occupied,
}

impl Voxel {
    const NEW: Voxel = Voxel {
        occupancy_logodds: 0.0,
        roi_logodds: 0.0,
    };

    /// Occupancy state of an existing voxel: log-odds > 0 is occupied, otherwise free.
    pub fn occupancy(&self) -> Occupancy {
        if self.occupancy_logodds > 0.0 {
            Occupancy::Occupied
        } else {
            Occupancy::Free
        }
    }
}

/// What one [`RoiMap::insert_scan`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ScanStats {
    /// Points given (including skipped ones).
    pub points: usize,
    /// Points with a NaN or infinite coordinate, ignored.
    pub skipped_non_finite: usize,
    /// Finite points (or range-limited ray ends) outside the map's key range, ignored.
    pub skipped_out_of_bounds: usize,
    /// Points farther than the maximum range: their ray is freed up to the range, nothing occupied.
    pub beyond_range: usize,
    /// Voxels updated with a miss (once each).
    pub free_updates: usize,
    /// Voxels updated with a hit (once each).
    pub occupied_updates: usize,
    /// Voxels whose ROI log-odds got a hit.
    pub roi_updates: usize,
    /// Voxels whose ROI log-odds got a miss.
    pub non_roi_updates: usize,
}

/// A connected group of ROI voxels (26-neighbourhood).
#[derive(Clone, Debug, PartialEq)]
pub struct RoiCluster {
    /// Member voxels, sorted.
    pub voxels: Vec<VoxelKey>,
    /// Mean of the voxel centres, world frame.
    pub centre: Point3<f64>,
    /// Min corner of the box over the voxel cubes, world frame.
    pub min: Point3<f64>,
    /// Max corner of the box over the voxel cubes, world frame.
    pub max: Point3<f64>,
}

/// Errors of the map. On any error the map is left untouched.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum MapError {
    #[error("invalid map configuration: {0}")]
    InvalidConfig(String),
    #[error("point cloud has {points} points but {roi} ROI labels")]
    LengthMismatch { points: usize, roi: usize },
    #[error("sensor origin is not finite")]
    NonFiniteOrigin,
    #[error("sensor origin lies outside the map's key range")]
    OriginOutOfBounds,
}

/// Cheap hasher for [`VoxelKey`]: the three `i32` fields are packed into one `u64` (21 bits
/// apart, injective for keys within the map's range) and finished with MurmurHash3's 64-bit
/// avalanche, so both the bucket bits (low) and the tag bits (high) depend on every coordinate.
#[derive(Clone, Copy, Debug, Default)]
pub struct VoxelKeyHasher(u64);

impl Hasher for VoxelKeyHasher {
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = self.0.rotate_left(8) ^ u64::from(b);
        }
    }

    fn write_i32(&mut self, v: i32) {
        self.0 = self.0.rotate_left(21) ^ u64::from(v as u32);
    }

    fn finish(&self) -> u64 {
        let mut h = self.0;
        h ^= h >> 33;
        h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
        h ^= h >> 33;
        h = h.wrapping_mul(0xC4CE_B9FE_1A85_EC53);
        h ^ (h >> 33)
    }
}

/// Hash-map building block keyed by voxel.
pub type KeyBuildHasher = BuildHasherDefault<VoxelKeyHasher>;
/// Set of voxel keys with the cheap hasher.
pub type KeySet = HashSet<VoxelKey, KeyBuildHasher>;
type KeyMap<V> = HashMap<VoxelKey, V, KeyBuildHasher>;

/// Largest key box (in voxels) a scan's dense key set covers: 2^26 bits = 8 MB.
const MAX_DENSE_VOXELS: u64 = 1 << 26;

/// A set of voxel keys for one scan. Keys inside a box given per scan live in a bitset (rays
/// revisit the same voxels many times, and a bitset over the scan's extent stays in cache where a
/// hash set would miss on almost every insert); keys outside it (or every key, when the box is
/// too large) go to a hash set. Insertion order is kept for deterministic iteration.
#[derive(Clone, Debug)]
struct ScanKeySet {
    lo: VoxelKey,
    dims: [u64; 3],
    bits: Vec<u64>,
    keys: Vec<VoxelKey>,
    outside: KeySet,
}

impl Default for ScanKeySet {
    fn default() -> Self {
        Self {
            lo: VoxelKey::new(0, 0, 0),
            dims: [0; 3],
            bits: Vec::new(),
            keys: Vec::new(),
            outside: KeySet::default(),
        }
    }
}

impl ScanKeySet {
    /// Empties the set and makes `lo..=hi` its dense box (when small enough).
    fn reset(&mut self, lo: VoxelKey, hi: VoxelKey) {
        self.keys.clear();
        self.outside.clear();
        let extent = |a: i32, b: i32| (i64::from(b) - i64::from(a) + 1).max(0) as u64;
        let dims = [extent(lo.x, hi.x), extent(lo.y, hi.y), extent(lo.z, hi.z)];
        let volume = dims[0].saturating_mul(dims[1]).saturating_mul(dims[2]);
        if volume == 0 || volume > MAX_DENSE_VOXELS {
            self.dims = [0; 3];
            self.bits.clear();
        } else {
            self.lo = lo;
            self.dims = dims;
            let words = volume.div_ceil(64) as usize;
            self.bits.clear();
            self.bits.resize(words, 0);
        }
    }

    /// Bit index of `key` in the dense box, if inside.
    fn index(&self, key: VoxelKey) -> Option<u64> {
        let dx = u64::try_from(i64::from(key.x) - i64::from(self.lo.x)).ok()?;
        let dy = u64::try_from(i64::from(key.y) - i64::from(self.lo.y)).ok()?;
        let dz = u64::try_from(i64::from(key.z) - i64::from(self.lo.z)).ok()?;
        let [nx, ny, nz] = self.dims;
        (dx < nx && dy < ny && dz < nz).then_some((dz * ny + dy) * nx + dx)
    }

    fn insert(&mut self, key: VoxelKey) {
        let new = match self.index(key) {
            Some(i) => {
                let (word, mask) = ((i / 64) as usize, 1u64 << (i % 64));
                let new = self.bits[word] & mask == 0;
                self.bits[word] |= mask;
                new
            }
            None => self.outside.insert(key),
        };
        if new {
            self.keys.push(key);
        }
    }

    fn contains(&self, key: VoxelKey) -> bool {
        match self.index(key) {
            Some(i) => self.bits[(i / 64) as usize] & (1u64 << (i % 64)) != 0,
            None => self.outside.contains(&key),
        }
    }

    fn heap_bytes(&self) -> usize {
        self.bits.capacity() * 8
            + self.keys.capacity() * std::mem::size_of::<VoxelKey>()
            + self.outside.capacity() * (std::mem::size_of::<VoxelKey>() + 1)
    }
}

/// Where one point's ray ends and whether its end voxel is hit.
#[derive(Clone, Copy, Debug)]
struct RayEnd {
    end_in_world: Point3<f64>,
    key_end: VoxelKey,
    /// False for points beyond the maximum range (ray freed up to the range only).
    hit: bool,
    is_roi: bool,
}

/// Reused per-scan buffers, so insertion allocates only when a scan is larger than any before.
#[derive(Clone, Debug, Default)]
struct Scratch {
    ends: Vec<RayEnd>,
    free: ScanKeySet,
    occupied: ScanKeySet,
    roi: KeySet,
    non_roi: KeySet,
}

/// The ROI voxel map. See the crate docs for the update rules.
#[derive(Clone)]
pub struct RoiMap {
    config: MapConfig,
    voxels: KeyMap<Voxel>,
    changed: KeySet,
    scratch: Scratch,
    scans_inserted: u64,
}

impl std::fmt::Debug for RoiMap {
    // A derived Debug would print every voxel.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RoiMap")
            .field("config", &self.config)
            .field("voxels", &self.voxels.len())
            .field("pending_changes", &self.changed.len())
            .field("scans_inserted", &self.scans_inserted)
            .finish()
    }
}

/// Key of a coordinate already divided by the resolution, if inside the key range.
fn checked_axis_key(scaled: f64) -> Option<i32> {
    let k = scaled.floor();
    if k.is_finite() && k >= -(KEY_LIMIT as f64) && k < KEY_LIMIT as f64 {
        Some(k as i32)
    } else {
        None
    }
}

/// Per-axis geometry of an Amanatides–Woo walk, set up exactly like OctoMap's `computeRayKeys`.
struct RayWalk {
    key: VoxelKey,
    step: [i32; 3],
    t_max: [f64; 3],
    t_delta: [f64; 3],
}

impl RayWalk {
    /// `direction` must be a unit vector with finite components.
    fn new(origin: &Point3<f64>, key_origin: VoxelKey, direction: &Vector3<f64>, res: f64) -> Self {
        let mut step = [0i32; 3];
        let mut t_max = [f64::INFINITY; 3];
        let mut t_delta = [f64::INFINITY; 3];
        for i in 0..3 {
            let d = direction[i];
            if d > 0.0 {
                step[i] = 1;
            } else if d < 0.0 {
                step[i] = -1;
            }
            if step[i] != 0 {
                // Border of the origin voxel in the step direction: centre + step * res / 2.
                let border =
                    (f64::from(key_origin.axis(i)) + 0.5) * res + f64::from(step[i]) * res * 0.5;
                t_max[i] = (border - origin[i]) / d;
                t_delta[i] = res / d.abs();
            }
        }
        Self {
            key: key_origin,
            step,
            t_max,
            t_delta,
        }
    }

    /// Advances one voxel; returns the distance along the ray at which the new voxel is left.
    fn advance(&mut self) -> f64 {
        let t = &self.t_max;
        // OctoMap's tie rule, kept verbatim so the same voxels are chosen.
        let dim = if t[0] < t[1] {
            if t[0] < t[2] {
                0
            } else {
                2
            }
        } else if t[1] < t[2] {
            1
        } else {
            2
        };
        *self.key.axis_mut(dim) += self.step[dim];
        self.t_max[dim] += self.t_delta[dim];
        self.t_max[0].min(self.t_max[1]).min(self.t_max[2])
    }
}

/// OctoMap's `computeRayKeys` with a callback instead of a key list: calls `add` for the voxels of
/// the segment origin→end, origin voxel first (unless it equals the end voxel), end voxel excluded.
/// Both keys must be precomputed with the same resolution. Stops early when `add` returns false.
fn compute_ray_keys(
    origin: &Point3<f64>,
    end: &Point3<f64>,
    key_origin: VoxelKey,
    key_end: VoxelKey,
    res: f64,
    mut add: impl FnMut(VoxelKey) -> bool,
) {
    if key_origin == key_end {
        return;
    }
    if !add(key_origin) {
        return;
    }
    let delta = end - origin;
    let length = delta.norm();
    if length.is_nan() || length <= 0.0 {
        return;
    }
    let direction = delta / length;
    let mut walk = RayWalk::new(origin, key_origin, &direction, res);
    loop {
        let exit_distance_m = walk.advance();
        if walk.key == key_end || exit_distance_m > length {
            return;
        }
        if !add(walk.key) {
            return;
        }
    }
}

fn clamp_add(value: f32, delta: f32, lo: f32, hi: f32) -> f32 {
    (value + delta).clamp(lo, hi)
}

impl RoiMap {
    /// An empty map; fails when the configuration is invalid.
    pub fn new(config: MapConfig) -> Result<Self, MapError> {
        config.validate()?;
        Ok(Self {
            config,
            voxels: KeyMap::default(),
            changed: KeySet::default(),
            scratch: Scratch::default(),
            scans_inserted: 0,
        })
    }

    pub fn config(&self) -> &MapConfig {
        &self.config
    }

    /// Voxel holding `p`: `floor(p / res)` per axis. Non-finite or huge coordinates saturate; use
    /// [`RoiMap::try_key_of`] when the input is untrusted.
    pub fn key_of(&self, p: &Point3<f64>) -> VoxelKey {
        let r = self.config.resolution_m;
        VoxelKey::new(
            (p.x / r).floor() as i32,
            (p.y / r).floor() as i32,
            (p.z / r).floor() as i32,
        )
    }

    /// Voxel holding `p`, or `None` when `p` is not finite or outside the map's key range.
    pub fn try_key_of(&self, p: &Point3<f64>) -> Option<VoxelKey> {
        let r = self.config.resolution_m;
        Some(VoxelKey::new(
            checked_axis_key(p.x / r)?,
            checked_axis_key(p.y / r)?,
            checked_axis_key(p.z / r)?,
        ))
    }

    /// Centre of a voxel in the world frame: `(key + 0.5) * res`.
    pub fn centre_of(&self, key: VoxelKey) -> Point3<f64> {
        let r = self.config.resolution_m;
        Point3::new(
            (f64::from(key.x) + 0.5) * r,
            (f64::from(key.y) + 0.5) * r,
            (f64::from(key.z) + 0.5) * r,
        )
    }

    /// Integrates one scan taken from `sensor_origin` (world frame). `roi[i]` labels
    /// `points_in_world[i]`. Follows OctoMap's `insertPointCloud` (see the crate docs); non-finite
    /// points are skipped and counted. On error the map is untouched.
    pub fn insert_scan(
        &mut self,
        sensor_origin: &Point3<f64>,
        points_in_world: &[Point3<f32>],
        roi: &[bool],
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
        let key_origin = self
            .try_key_of(sensor_origin)
            .ok_or(MapError::OriginOutOfBounds)?;

        let mut stats = ScanStats {
            points: points_in_world.len(),
            ..ScanStats::default()
        };
        // Take the scratch buffers out so the key helpers can borrow `self`.
        let mut s = std::mem::take(&mut self.scratch);
        s.ends.clear();
        s.roi.clear();
        s.non_roi.clear();

        let res = self.config.resolution_m;
        let max_range = self.config.max_range_m;
        // Pass 1: classify points and find the key box of all rays (they stay between their
        // origin and end voxels), so the ray sets can use a dense bitset over it.
        let (mut lo, mut hi) = (key_origin, key_origin);
        for (p32, &is_roi) in points_in_world.iter().zip(roi) {
            if !p32.iter().all(|c| c.is_finite()) {
                stats.skipped_non_finite += 1;
                continue;
            }
            let p: Point3<f64> = p32.cast();
            let distance_m = (p - sensor_origin).norm();
            let (end_in_world, hit) = match max_range {
                Some(range) if distance_m > range => (
                    sensor_origin + (p - sensor_origin) * (range / distance_m),
                    false,
                ),
                _ => (p, true),
            };
            let Some(key_end) = self.try_key_of(&end_in_world) else {
                stats.skipped_out_of_bounds += 1;
                continue;
            };
            if !hit {
                stats.beyond_range += 1;
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
                end_in_world,
                key_end,
                hit,
                is_roi,
            });
        }

        // Pass 2: OctoMap's key sets. A margin of one voxel absorbs rounding at box faces; keys
        // beyond it still land in the sets' hash part, so the result is exact either way.
        s.free.reset(lo.offset(-1, -1, -1), hi.offset(1, 1, 1));
        s.occupied.reset(lo, hi);
        for end in &s.ends {
            let free = &mut s.free;
            compute_ray_keys(
                sensor_origin,
                &end.end_in_world,
                key_origin,
                end.key_end,
                res,
                |k| {
                    free.insert(k);
                    true
                },
            );
            if end.hit {
                s.occupied.insert(end.key_end);
                // ROI labels come from the hit end points only; ROI wins is applied below.
                if end.is_roi {
                    s.roi.insert(end.key_end);
                } else {
                    s.non_roi.insert(end.key_end);
                }
            }
        }

        let cfg = self.config;
        let (clamp_lo, clamp_hi) = (cfg.clamp_min_logodds, cfg.clamp_max_logodds);
        for &key in &s.free.keys {
            if s.occupied.contains(key) {
                continue; // occupied wins within a scan
            }
            stats.free_updates += 1;
            self.update(key, |v| {
                v.occupancy_logodds =
                    clamp_add(v.occupancy_logodds, cfg.miss_logodds, clamp_lo, clamp_hi)
            });
        }
        for &key in &s.occupied.keys {
            stats.occupied_updates += 1;
            self.update(key, |v| {
                v.occupancy_logodds =
                    clamp_add(v.occupancy_logodds, cfg.hit_logodds, clamp_lo, clamp_hi)
            });
        }
        for &key in &s.roi {
            stats.roi_updates += 1;
            self.update(key, |v| {
                v.roi_logodds = clamp_add(v.roi_logodds, cfg.hit_logodds, clamp_lo, clamp_hi)
            });
        }
        for &key in &s.non_roi {
            if s.roi.contains(&key) {
                continue; // ROI wins within a scan
            }
            stats.non_roi_updates += 1;
            self.update(key, |v| {
                v.roi_logodds = clamp_add(v.roi_logodds, cfg.miss_logodds, clamp_lo, clamp_hi)
            });
        }
        self.scratch = s;
        self.scans_inserted += 1;
        Ok(stats)
    }

    /// Applies `f` to the voxel (created at 0/0 when new) and records a change when it changed.
    fn update(&mut self, key: VoxelKey, f: impl FnOnce(&mut Voxel)) {
        let mut created = false;
        let voxel = self.voxels.entry(key).or_insert_with(|| {
            created = true;
            Voxel::NEW
        });
        let before = *voxel;
        f(voxel);
        if created || *voxel != before {
            self.changed.insert(key);
        }
    }

    pub fn get(&self, key: VoxelKey) -> Option<Voxel> {
        self.voxels.get(&key).copied()
    }

    pub fn occupancy(&self, key: VoxelKey) -> Occupancy {
        self.voxels
            .get(&key)
            .map_or(Occupancy::Unknown, Voxel::occupancy)
    }

    /// True when the voxel's ROI log-odds is at least the ROI threshold.
    pub fn is_roi(&self, key: VoxelKey) -> bool {
        self.voxels.get(&key).is_some_and(|v| self.voxel_is_roi(v))
    }

    fn voxel_is_roi(&self, v: &Voxel) -> bool {
        v.roi_logodds >= self.config.roi_threshold_logodds
    }

    /// Number of known (ever updated) voxels.
    pub fn len(&self) -> usize {
        self.voxels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.voxels.is_empty()
    }

    /// Known voxels in arbitrary order.
    pub fn iter(&self) -> impl Iterator<Item = (VoxelKey, Voxel)> + '_ {
        self.voxels.iter().map(|(k, v)| (*k, *v))
    }

    /// Keys of all ROI voxels, sorted.
    pub fn roi_keys(&self) -> Vec<VoxelKey> {
        let mut keys: Vec<VoxelKey> = self
            .voxels
            .iter()
            .filter(|(_, v)| self.voxel_is_roi(v))
            .map(|(k, _)| *k)
            .collect();
        keys.sort_unstable();
        keys
    }

    /// Voxels changed since the last call (sorted by key, with current values); clears the record.
    pub fn take_changes(&mut self) -> Vec<(VoxelKey, Voxel)> {
        let mut out: Vec<(VoxelKey, Voxel)> = self
            .changed
            .drain()
            .filter_map(|k| self.voxels.get(&k).map(|v| (k, *v)))
            .collect();
        out.sort_unstable_by_key(|(k, _)| *k);
        out
    }

    /// Overwrites voxel values (for replicas and dashboards) and records them as changes when
    /// they differ. Entries with non-finite log-odds are ignored, so bad input cannot poison the map.
    pub fn apply_voxels(&mut self, voxels: &[(VoxelKey, Voxel)]) {
        for &(key, value) in voxels {
            if !(value.occupancy_logodds.is_finite() && value.roi_logodds.is_finite()) {
                continue;
            }
            if self.voxels.insert(key, value) != Some(value) {
                self.changed.insert(key);
            }
        }
    }

    /// Walks the voxels of the segment `origin + t * direction`, `t` in `[0, max_range_m]`, with the
    /// same Amanatides–Woo traversal as insertion: first the voxels insertion would free for a point
    /// at the segment's end (origin voxel first), then the end voxel itself. `visit` gets each key
    /// and its voxel (`None` = unknown) and stops the walk by returning false. Nothing is visited
    /// when the origin is non-finite or outside the map, or `max_range_m` is negative or
    /// non-finite; a zero direction visits the origin voxel only.
    pub fn walk_ray(
        &self,
        origin: &Point3<f64>,
        direction: &Vector3<f64>,
        max_range_m: f64,
        mut visit: impl FnMut(VoxelKey, Option<Voxel>) -> bool,
    ) {
        let Some(key_origin) = self.try_key_of(origin) else {
            return;
        };
        if !(max_range_m.is_finite() && max_range_m >= 0.0) {
            return;
        }
        let Some(unit) = direction
            .try_normalize(1e-12)
            .filter(|d| d.iter().all(|c| c.is_finite()))
        else {
            visit(key_origin, self.get(key_origin));
            return;
        };
        // Bounded so the walk stays well inside i32 keys.
        let res = self.config.resolution_m;
        let range_m = max_range_m.min(KEY_LIMIT as f64 * res);
        let end = origin + unit * range_m;
        let key_end = self.key_of(&end);
        let mut stopped = false;
        compute_ray_keys(origin, &end, key_origin, key_end, res, |k| {
            let go_on = visit(k, self.get(k));
            stopped = !go_on;
            go_on
        });
        if !stopped {
            visit(key_end, self.get(key_end));
        }
    }

    /// Keys of known voxels matching `pred`, e.g. every occupied or every ROI voxel.
    fn keys_where(&self, pred: impl Fn(&Voxel) -> bool) -> Vec<VoxelKey> {
        self.voxels
            .iter()
            .filter(|(_, v)| pred(v))
            .map(|(k, _)| *k)
            .collect()
    }

    fn has_neighbour_6(&self, key: VoxelKey, state: Occupancy) -> bool {
        NEIGHBOURS_6
            .iter()
            .any(|&(dx, dy, dz)| self.occupancy(key.offset(dx, dy, dz)) == state)
    }

    /// Free 6-neighbours of `seeds` whose centre lies in `region` and that have an unknown
    /// 6-neighbour; sorted and unique.
    fn free_unknown_neighbours_of(&self, seeds: &[VoxelKey], region: &Aabb) -> Vec<VoxelKey> {
        let mut found = KeySet::default();
        for &seed in seeds {
            for &(dx, dy, dz) in &NEIGHBOURS_6 {
                let n = seed.offset(dx, dy, dz);
                // Cheapest tests first: the region test needs no map lookup.
                if !region.contains(&self.centre_of(n))
                    || found.contains(&n)
                    || self.occupancy(n) != Occupancy::Free
                {
                    continue;
                }
                if self.has_neighbour_6(n, Occupancy::Unknown) {
                    found.insert(n);
                }
            }
        }
        let mut out: Vec<VoxelKey> = found.into_iter().collect();
        out.sort_unstable();
        out
    }

    /// ROI targets (paper-method §3): free voxels 6-adjacent to an ROI voxel that have an unknown
    /// 6-neighbour, with centre inside `region`; sorted.
    pub fn roi_frontier(&self, region: &Aabb) -> Vec<VoxelKey> {
        let roi = self.keys_where(|v| self.voxel_is_roi(v));
        self.free_unknown_neighbours_of(&roi, region)
    }

    /// Exploration frontier: free voxels with centre in `region` having both an unknown and an
    /// occupied 6-neighbour; sorted. Found from the occupied voxels, which are far fewer than the
    /// free ones.
    pub fn exploration_frontier(&self, region: &Aabb) -> Vec<VoxelKey> {
        let occupied = self.keys_where(|v| v.occupancy() == Occupancy::Occupied);
        self.free_unknown_neighbours_of(&occupied, region)
    }

    /// ROI voxels grown into 26-connected clusters; clusters with at least `min_voxels` voxels,
    /// ordered by their smallest key.
    pub fn clusters(&self, min_voxels: usize) -> Vec<RoiCluster> {
        let roi = self.roi_keys();
        let mut unvisited: KeySet = roi.iter().copied().collect();
        let res = self.config.resolution_m;
        let mut clusters = Vec::new();
        let mut stack = Vec::new();
        // Seeds are taken in sorted order, so each cluster starts at its smallest key and the
        // output is already ordered by smallest key.
        for &seed in &roi {
            if !unvisited.remove(&seed) {
                continue;
            }
            let mut members = vec![seed];
            stack.push(seed);
            while let Some(k) = stack.pop() {
                for dx in -1..=1 {
                    for dy in -1..=1 {
                        for dz in -1..=1 {
                            let n = k.offset(dx, dy, dz);
                            if unvisited.remove(&n) {
                                members.push(n);
                                stack.push(n);
                            }
                        }
                    }
                }
            }
            if members.len() < min_voxels.max(1) {
                continue;
            }
            members.sort_unstable();
            let mut sum = Vector3::zeros();
            let mut lo = members[0];
            let mut hi = members[0];
            for &m in &members {
                sum += self.centre_of(m).coords;
                lo = VoxelKey::new(lo.x.min(m.x), lo.y.min(m.y), lo.z.min(m.z));
                hi = VoxelKey::new(hi.x.max(m.x), hi.y.max(m.y), hi.z.max(m.z));
            }
            let corner = |k: VoxelKey, add: i32| {
                Point3::new(
                    f64::from(k.x + add) * res,
                    f64::from(k.y + add) * res,
                    f64::from(k.z + add) * res,
                )
            };
            clusters.push(RoiCluster {
                centre: Point3::from(sum / members.len() as f64),
                min: corner(lo, 0),
                max: corner(hi, 1),
                voxels: members,
            });
        }
        clusters
    }

    /// Number of successful [`RoiMap::insert_scan`] calls.
    pub fn scans_inserted(&self) -> u64 {
        self.scans_inserted
    }

    /// Approximate heap use in bytes (hash tables at their capacity, one control byte per slot).
    pub fn memory_bytes(&self) -> usize {
        let entry = std::mem::size_of::<(VoxelKey, Voxel)>() + 1;
        let key = std::mem::size_of::<VoxelKey>() + 1;
        let s = &self.scratch;
        std::mem::size_of::<Self>()
            + self.voxels.capacity() * entry
            + (self.changed.capacity() + s.roi.capacity() + s.non_roi.capacity()) * key
            + s.ends.capacity() * std::mem::size_of::<RayEnd>()
            + s.free.heap_bytes()
            + s.occupied.heap_bytes()
    }
}

#[cfg(test)]
mod tests;
