//! Probabilistic ROI voxel map with OctoMap insertion semantics.
//!
//! The map is a sparse grid of cubic voxels (1 cm by default) in the world frame (z up, metres).
//! Voxel `i` along an axis covers `[i * res, (i + 1) * res)`: its key is
//! `floor(coordinate * (1 / res))`, exactly OctoMap's `coordToKey`, so negative coordinates get
//! negative keys. Every voxel holds two log-odds values:
//!
//! - **occupancy**, updated exactly like OctoMap's `insertPointCloud(cloud, origin, maxrange)` with
//!   `discretize = false`: per scan, the voxels crossed by the rays (Amanatides–Woo walk, end voxel
//!   excluded) form a *free* set, the end-point voxels an *occupied* set, occupied wins over free,
//!   and each voxel is updated once per scan (hit +0.8473, miss −0.4055, clamped to [−2.0, 3.5110]).
//!   A point farther than the maximum range frees its ray up to the range and marks nothing. Like
//!   OctoMap, the origin and points are `f32` and the ray set-up uses OctoMap's float roundings
//!   (see `walk.rs`), so the map agrees with OctoMap 1.9 voxel for voxel (`scripts/octomap-compare
//!   --check`). [`MapConfig::merge_far_rays`] (off by default) departs from it on purpose: the
//!   points beyond the range free one ray per voxel at the range.
//! - **ROI** (fruit), updated from the scan's hit end points only: ROI points' voxels get a hit, the
//!   other end-point voxels a miss unless some ROI point of the same scan fell in them (ROI wins). A
//!   voxel is an ROI voxel when its ROI log-odds is at least the threshold (1.0 by default: two
//!   observations).
//!
//! **Free/unknown rule** (paper-method §6; the original code had two, we use one everywhere): a
//! voxel that was never updated is [`Occupancy::Unknown`]; a voxel whose occupancy log-odds is
//! `> 0` is [`Occupancy::Occupied`]; every other updated voxel (log-odds `<= 0`) is
//! [`Occupancy::Free`]. So a single miss makes a voxel free. Frontiers, gains and clusters all use
//! this rule.
//!
//! Keys are bounded: a coordinate more than `2^20` voxels from the origin (about 10 km at 1 cm) is
//! outside the map (OctoMap's bound is `2^15`); such points are skipped and counted.
//!
//! Storage is blocked: 8×8×8-voxel blocks in a hash map keyed by block, each holding its exact
//! `f32` log-odds as one value, a palette with byte indices, or a flat array (whichever the block
//! needs). The map maintains, as voxels change, the set of ROI voxels and the ROI-frontier and
//! exploration-frontier sets (paper-method §3; recomputed only around the voxels a scan changed).
//!
//! Change tracking: [`RoiMap::take_changes`] returns the voxels changed since its last call. A
//! compressed checksummed snapshot ([`RoiMap::write_snapshot`]) and a PLY export
//! ([`RoiMap::write_ply`]) persist and exchange the map.

mod batch;
mod clusters;
mod delta;
mod derived;
#[doc(hidden)]
pub mod fuzzing;
mod grid;
mod insert;
pub mod ply;
pub mod prior;
pub mod simd;
pub mod snapshot;
pub mod stored;
pub mod testdata;
mod values;
mod walk;

use std::collections::{HashMap, HashSet};
use std::hash::{BuildHasherDefault, Hasher};

use glasshouse_geom::Aabb;
use nalgebra::{Point3, Vector3};

use crate::grid::{
    block_of, for_each_bit, key_at, local_of, mask_is_empty, mask_set, mask_test, Block, Mask,
    Storage, EMPTY,
};
use crate::walk::{axis_key, RaySetup, KEY_LIMIT};

pub use crate::batch::RayCount;
pub use crate::clusters::{ClusterUpdate, Clusters};
pub use crate::insert::RoiInput;
pub use crate::prior::PriorRules;
pub use crate::snapshot::SnapshotError;

/// Offsets of the 6-neighbourhood (face neighbours).
pub const NEIGHBOURS_6: [(i32, i32, i32); 6] = [
    (-1, 0, 0),
    (1, 0, 0),
    (0, -1, 0),
    (0, 1, 0),
    (0, 0, -1),
    (0, 0, 1),
];

/// Offsets of the 18-neighbourhood (faces and edges).
pub const NEIGHBOURS_18: [(i32, i32, i32); 18] = neighbour_offsets::<18>(2);

/// Offsets of the 26-neighbourhood (faces, edges and corners).
pub const NEIGHBOURS_26: [(i32, i32, i32); 26] = neighbour_offsets::<26>(3);

/// The offsets with 1..=`max_nonzero` non-zero components, in x-major order.
const fn neighbour_offsets<const N: usize>(max_nonzero: i32) -> [(i32, i32, i32); N] {
    let mut out = [(0, 0, 0); N];
    let mut n = 0;
    let mut dx = -1;
    while dx <= 1 {
        let mut dy = -1;
        while dy <= 1 {
            let mut dz = -1;
            while dz <= 1 {
                let nz = (dx != 0) as i32 + (dy != 0) as i32 + (dz != 0) as i32;
                if nz >= 1 && nz <= max_nonzero {
                    out[n] = (dx, dy, dz);
                    n += 1;
                }
                dz += 1;
            }
            dy += 1;
        }
        dx += 1;
    }
    out
}

/// Which neighbourhood [`VoxelKey::neighbours`] gives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Neighbourhood {
    /// Faces.
    Six,
    /// Faces and edges.
    Eighteen,
    /// Faces, edges and corners.
    TwentySix,
}

impl Neighbourhood {
    pub fn offsets(self) -> &'static [(i32, i32, i32)] {
        match self {
            Neighbourhood::Six => &NEIGHBOURS_6,
            Neighbourhood::Eighteen => &NEIGHBOURS_18,
            Neighbourhood::TwentySix => &NEIGHBOURS_26,
        }
    }
}

/// Map parameters. [`Default`] gives the paper's values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapConfig {
    /// Voxel edge length in metres.
    pub resolution_m: f64,
    /// Occupancy log-odds added on a hit (p = 0.7).
    pub hit_logodds: f32,
    /// Occupancy log-odds added on a miss (p = 0.4).
    pub miss_logodds: f32,
    /// ROI log-odds added when a scan's end point in the voxel is labelled fruit (the paper:
    /// the occupancy hit, +0.8473).
    pub roi_hit_logodds: f32,
    /// ROI log-odds added when a scan's end points in the voxel are all labelled non-fruit (the
    /// paper: the occupancy miss, −0.4055). With a noisy detector the paper's asymmetry lets
    /// sporadic false labels win; the planner uses a symmetric model (−0.8473).
    pub roi_miss_logodds: f32,
    /// Lower clamp of both log-odds values (p = 0.12).
    pub clamp_min_logodds: f32,
    /// Upper clamp of both log-odds values (p = 0.97).
    pub clamp_max_logodds: f32,
    /// A voxel is ROI when its ROI log-odds is at least this.
    pub roi_threshold_logodds: f32,
    /// ROI-targeted sampling aims at the free face neighbours (with an unknown face neighbour)
    /// of *ROI targets*. `false` (the paper): every ROI voxel is a target. `true`: only an ROI
    /// voxel with an ROI face neighbour is, so the lone ROI voxels a noisy detector leaves on
    /// leaves draw no views; fruit surfaces are patches, and the ROI set itself is unchanged.
    pub roi_target_needs_neighbour: bool,
    /// Sensor range in metres; `None` means unlimited (OctoMap's `maxrange < 0`).
    pub max_range_m: Option<f64>,
    /// Points beyond the maximum range whose rays end in the same voxel at the range free one
    /// ray, aimed at that voxel's centre, instead of one each (their rays cross nearly the same
    /// voxels). `false` (OctoMap): one ray per point. Points within the range are unaffected.
    pub merge_far_rays: bool,
}

impl Default for MapConfig {
    fn default() -> Self {
        Self {
            resolution_m: 0.01,
            hit_logodds: 0.8473,
            miss_logodds: -0.4055,
            roi_hit_logodds: 0.8473,
            roi_miss_logodds: -0.4055,
            clamp_min_logodds: -2.0,
            clamp_max_logodds: 3.5110,
            roi_threshold_logodds: 1.0,
            roi_target_needs_neighbour: false,
            max_range_m: None,
            merge_far_rays: false,
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
        if !(self.roi_hit_logodds.is_finite() && self.roi_hit_logodds > 0.0) {
            return bad(format!(
                "roi_hit_logodds must be finite and > 0, got {}",
                self.roi_hit_logodds
            ));
        }
        if !(self.roi_miss_logodds.is_finite() && self.roi_miss_logodds < 0.0) {
            return bad(format!(
                "roi_miss_logodds must be finite and < 0, got {}",
                self.roi_miss_logodds
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

    /// The neighbour keys of the given neighbourhood.
    pub fn neighbours(self, n: Neighbourhood) -> impl Iterator<Item = VoxelKey> {
        n.offsets()
            .iter()
            .map(move |&(dx, dy, dz)| self.offset(dx, dy, dz))
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
    /// Rays walked: one per usable point, or with `merge_far_rays` one per voxel at the range
    /// for the points beyond it.
    pub rays: usize,
    /// Voxels updated with a miss (once each): the scan's unique free voxels.
    pub free_updates: usize,
    /// Voxels updated with a hit (once each): the scan's unique occupied voxels.
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

/// Voxel counts of the map, all maintained as voxels change.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MapCounts {
    /// Voxels ever updated.
    pub known: usize,
    /// Known voxels with occupancy log-odds > 0.
    pub occupied: usize,
    /// Known voxels that are not occupied.
    pub free: usize,
    /// ROI voxels.
    pub roi: usize,
    /// ROI-frontier voxels (no region filter).
    pub roi_frontier: usize,
    /// Exploration-frontier voxels (no region filter).
    pub exploration_frontier: usize,
    /// Allocated 8×8×8 blocks.
    pub blocks: usize,
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

    fn write_u32(&mut self, v: u32) {
        self.0 = self.0.rotate_left(21) ^ u64::from(v);
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

/// Per block (by index) the voxels whose state (unknown/free/occupied/ROI) changed and those whose
/// ROI status changed, gathered during one update and consumed by [`RoiMap::refresh_derived`].
#[derive(Default)]
pub(crate) struct ChangeLog {
    blocks: HashMap<u32, (Mask, Mask), KeyBuildHasher>,
}

impl ChangeLog {
    pub(crate) fn with_capacity(blocks: usize) -> Self {
        Self {
            blocks: HashMap::with_capacity_and_hasher(blocks, KeyBuildHasher::default()),
        }
    }

    pub(crate) fn note(&mut self, block: u32, state: &Mask, roi: &Mask) {
        if mask_is_empty(state) {
            return;
        }
        let e = self.blocks.entry(block).or_insert((EMPTY, EMPTY));
        for w in 0..8 {
            e.0[w] |= state[w];
            e.1[w] |= roi[w];
        }
    }
}

/// The block coordinates of a box of blocks, x fastest.
struct BlockRange {
    lo: VoxelKey,
    hi: VoxelKey,
    next: Option<VoxelKey>,
}

impl BlockRange {
    fn len(&self) -> usize {
        let span = |a: i32, b: i32| usize::try_from(i64::from(b) - i64::from(a) + 1).unwrap_or(0);
        span(self.lo.x, self.hi.x)
            .saturating_mul(span(self.lo.y, self.hi.y))
            .saturating_mul(span(self.lo.z, self.hi.z))
    }
}

impl Iterator for BlockRange {
    type Item = VoxelKey;

    fn next(&mut self) -> Option<VoxelKey> {
        let current = self.next?;
        let mut n = current;
        n.x += 1;
        if n.x > self.hi.x {
            n.x = self.lo.x;
            n.y += 1;
            if n.y > self.hi.y {
                n.y = self.lo.y;
                n.z += 1;
            }
        }
        self.next = (n.z <= self.hi.z).then_some(n);
        Some(current)
    }
}

/// One block of changed voxels ([`RoiMap::drain_changed_blocks`]). Masks have bit
/// `z * 64 + y * 8 + x` set for the voxel at that offset in the block, as in
/// [`RoiMap::solid_blocks`].
pub struct ChangedBlock<'m> {
    coord: VoxelKey,
    block: &'m Block,
}

impl ChangedBlock<'_> {
    /// The block's coordinate: a voxel key ÷ 8 (rounded down).
    pub fn coord(&self) -> VoxelKey {
        self.coord
    }

    /// The voxels changed since the last drain.
    pub fn changed(&self) -> &[u64; 8] {
        &self.block.dirty
    }

    /// The solid voxels now: occupied (log-odds > 0) or ROI.
    pub fn solid(&self) -> [u64; 8] {
        self.block.solid()
    }

    /// Each voxel of `which` with its values and whether it is ROI, in bit order.
    pub fn for_each(&self, which: &[u64; 8], mut visit: impl FnMut(VoxelKey, Voxel, bool)) {
        let b = self.block;
        for_each_bit(which, |l| {
            let voxel = Voxel {
                occupancy_logodds: b.occ_at(l),
                roi_logodds: b.roi_at(l),
            };
            visit(key_at(self.coord, l), voxel, mask_test(&b.roi_mask, l));
        });
    }
}

/// The ROI voxel map. See the crate docs for the update rules.
#[derive(Clone)]
pub struct RoiMap {
    config: MapConfig,
    inv_res: f64,
    store: Storage,
    /// Blocks (by index) with voxels changed since the last `take_changes`.
    dirty_blocks: HashSet<u32, KeyBuildHasher>,
    roi_set: KeySet,
    /// The voxels whose ROI state the latest update changed, and the count of updates
    /// ([`RoiMap::roi_epoch`]): what [`Clusters`] needs to regrow only what changed.
    roi_changes: Vec<VoxelKey>,
    roi_epoch: u64,
    /// Blocks (by coordinate) with frontier voxels.
    expl_blocks: KeySet,
    roi_front_blocks: KeySet,
    known_count: usize,
    occupied_count: usize,
    expl_count: usize,
    roi_front_count: usize,
    scratch: insert::Scratch,
    scans_inserted: u64,
}

impl std::fmt::Debug for RoiMap {
    // A derived Debug would print every voxel.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RoiMap")
            .field("config", &self.config)
            .field("voxels", &self.known_count)
            .field("blocks", &self.store.blocks.len())
            .field("scans_inserted", &self.scans_inserted)
            .finish()
    }
}

impl RoiMap {
    /// An empty map; fails when the configuration is invalid.
    pub fn new(config: MapConfig) -> Result<Self, MapError> {
        config.validate()?;
        Ok(Self {
            config,
            inv_res: 1.0 / config.resolution_m,
            store: Storage::default(),
            dirty_blocks: HashSet::default(),
            roi_set: KeySet::default(),
            roi_changes: Vec::new(),
            roi_epoch: 0,
            expl_blocks: KeySet::default(),
            roi_front_blocks: KeySet::default(),
            known_count: 0,
            occupied_count: 0,
            expl_count: 0,
            roi_front_count: 0,
            scratch: insert::Scratch::default(),
            scans_inserted: 0,
        })
    }

    pub fn config(&self) -> &MapConfig {
        &self.config
    }

    /// Sets how later scans cast their rays (`max_range_m`, `merge_far_rays`), for a map made
    /// with other rules: the voxels already in the map do not depend on them. An invalid range is
    /// an error and changes nothing.
    pub fn set_ray_rules(
        &mut self,
        max_range_m: Option<f64>,
        merge_far_rays: bool,
    ) -> Result<(), MapError> {
        let config = MapConfig {
            max_range_m,
            merge_far_rays,
            ..self.config
        };
        config.validate()?;
        self.config = config;
        Ok(())
    }

    /// Voxel holding `p`: `floor(p * (1 / res))` per axis (OctoMap's `coordToKey`). Non-finite or
    /// huge coordinates saturate; use [`RoiMap::try_key_of`] when the input is untrusted.
    pub fn key_of(&self, p: &Point3<f64>) -> VoxelKey {
        let r = self.inv_res;
        VoxelKey::new(
            (p.x * r).floor() as i32,
            (p.y * r).floor() as i32,
            (p.z * r).floor() as i32,
        )
    }

    /// Voxel holding `p`, or `None` when `p` is not finite or outside the map's key range.
    pub fn try_key_of(&self, p: &Point3<f64>) -> Option<VoxelKey> {
        let r = self.inv_res;
        Some(VoxelKey::new(
            axis_key(p.x, r)?,
            axis_key(p.y, r)?,
            axis_key(p.z, r)?,
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
        self.insert_scan_threaded(sensor_origin, points_in_world, roi, 1)
    }

    /// Adds log-odds deltas to one voxel (created at 0/0 when new), clamped; records the change.
    pub(crate) fn update_voxel(
        &mut self,
        key: VoxelKey,
        occ_delta: Option<f32>,
        roi_delta: Option<f32>,
        log: &mut ChangeLog,
    ) {
        let (lo, hi) = (self.config.clamp_min_logodds, self.config.clamp_max_logodds);
        let current = self.get(key).unwrap_or(Voxel::NEW);
        let mut v = current;
        if let Some(d) = occ_delta {
            v.occupancy_logodds = (v.occupancy_logodds + d).clamp(lo, hi);
        }
        if let Some(d) = roi_delta {
            v.roi_logodds = (v.roi_logodds + d).clamp(lo, hi);
        }
        self.set_voxel(key, v, log);
    }

    /// Sets one voxel (making it known); records the change when it is new or differs.
    pub(crate) fn set_voxel(&mut self, key: VoxelKey, v: Voxel, log: &mut ChangeLog) {
        let thr = self.config.roi_threshold_logodds;
        let bi = self.store.get_or_create(block_of(key));
        let l = local_of(key);
        let b = &mut self.store.blocks[bi];
        let was_known = mask_test(&b.known, l);
        let was_occ = mask_test(&b.occupied, l);
        let was_roi = mask_test(&b.roi_mask, l);
        let changed =
            !was_known || b.occ_at(l) != v.occupancy_logodds || b.roi_at(l) != v.roi_logodds;
        if !changed {
            return;
        }
        b.occ.set(l, v.occupancy_logodds);
        b.roi.set(l, v.roi_logodds);
        let is_occ = v.occupancy_logodds > 0.0;
        let is_roi = v.roi_logodds >= thr;
        mask_set(&mut b.known, l, true);
        mask_set(&mut b.occupied, l, is_occ);
        mask_set(&mut b.roi_mask, l, is_roi);
        mask_set(&mut b.dirty, l, true);
        b.changed_at_scan = self.scans_inserted + 1;
        self.dirty_blocks.insert(bi as u32);
        if !was_known {
            self.known_count += 1;
        }
        match (was_occ, is_occ) {
            (false, true) => self.occupied_count += 1,
            (true, false) => self.occupied_count -= 1,
            _ => {}
        }
        if !was_known || was_occ != is_occ || was_roi != is_roi {
            let mut state = EMPTY;
            mask_set(&mut state, l, true);
            let mut roi = EMPTY;
            mask_set(&mut roi, l, was_roi != is_roi);
            log.note(bi as u32, &state, &roi);
        }
    }

    pub fn get(&self, key: VoxelKey) -> Option<Voxel> {
        let b = self.store.find(block_of(key))?;
        let l = local_of(key);
        mask_test(&b.known, l).then(|| Voxel {
            occupancy_logodds: b.occ_at(l),
            roi_logodds: b.roi_at(l),
        })
    }

    pub fn occupancy(&self, key: VoxelKey) -> Occupancy {
        match self.store.find(block_of(key)) {
            Some(b) => {
                let l = local_of(key);
                if !mask_test(&b.known, l) {
                    Occupancy::Unknown
                } else if mask_test(&b.occupied, l) {
                    Occupancy::Occupied
                } else {
                    Occupancy::Free
                }
            }
            None => Occupancy::Unknown,
        }
    }

    /// Occupancy log-odds of a known voxel.
    pub fn occupancy_logodds(&self, key: VoxelKey) -> Option<f32> {
        self.get(key).map(|v| v.occupancy_logodds)
    }

    /// ROI log-odds of a known voxel.
    pub fn roi_logodds(&self, key: VoxelKey) -> Option<f32> {
        self.get(key).map(|v| v.roi_logodds)
    }

    /// True when the voxel's ROI log-odds is at least the ROI threshold.
    pub fn is_roi(&self, key: VoxelKey) -> bool {
        self.roi_set.contains(&key)
    }

    /// Number of known (ever updated) voxels.
    pub fn len(&self) -> usize {
        self.known_count
    }

    pub fn is_empty(&self) -> bool {
        self.known_count == 0
    }

    /// Voxel counts, maintained incrementally.
    pub fn counts(&self) -> MapCounts {
        MapCounts {
            known: self.known_count,
            occupied: self.occupied_count,
            free: self.known_count - self.occupied_count,
            roi: self.roi_set.len(),
            roi_frontier: self.roi_front_count,
            exploration_frontier: self.expl_count,
            blocks: self.store.blocks.len(),
        }
    }

    /// Known voxels, block by block.
    pub fn iter(&self) -> impl Iterator<Item = (VoxelKey, Voxel)> + '_ {
        self.store
            .blocks
            .iter()
            .zip(&self.store.coords)
            .flat_map(|(b, &bk)| {
                let mut out = Vec::with_capacity(grid::mask_count(&b.known));
                for_each_bit(&b.known, |l| {
                    out.push((
                        key_at(bk, l),
                        Voxel {
                            occupancy_logodds: b.occ_at(l),
                            roi_logodds: b.roi_at(l),
                        },
                    ))
                });
                out
            })
    }

    /// Each block's solid (occupied or ROI) voxels: the block's coordinate (voxel key ÷ 8) and
    /// a mask with bit `z * 64 + y * 8 + x` set for each solid voxel at that offset in the block.
    pub fn solid_blocks(&self) -> impl Iterator<Item = (VoxelKey, [u64; 8])> + '_ {
        let blocks = self.store.blocks.iter().zip(&self.store.coords);
        blocks.map(|(b, &bk)| (bk, b.solid()))
    }

    /// Keys of all ROI voxels, sorted.
    pub fn roi_keys(&self) -> Vec<VoxelKey> {
        let mut keys: Vec<VoxelKey> = self.roi_set.iter().copied().collect();
        keys.sort_unstable();
        keys
    }

    /// The current ROI voxels (maintained as voxels change), in arbitrary order.
    pub fn roi_voxels(&self) -> &KeySet {
        &self.roi_set
    }

    /// Counts the map's updates (scans, applied voxels, a snapshot read); the voxels whose ROI
    /// state the latest one changed are [`RoiMap::last_roi_changes`].
    pub fn roi_epoch(&self) -> u64 {
        self.roi_epoch
    }

    /// The voxels whose ROI state the latest update ([`RoiMap::roi_epoch`]) changed.
    pub fn last_roi_changes(&self) -> &[VoxelKey] {
        &self.roi_changes
    }

    /// Voxels changed since the last call (sorted by key, with current values); clears the record.
    pub fn take_changes(&mut self) -> Vec<(VoxelKey, Voxel)> {
        let mut out = Vec::new();
        self.drain_changes(|key, voxel, _| out.push((key, voxel)));
        out.sort_unstable_by_key(|(k, _)| *k);
        out
    }

    /// Visits the voxels changed since the last call, block by block in no set order, with their
    /// current values and whether each is ROI ([`RoiMap::is_roi`], read from its block: no
    /// lookup per voxel); clears the record. A scan changes hundreds of thousands of voxels,
    /// mostly freed ones: a caller that keeps a few of them need not sort them all.
    pub fn drain_changes(&mut self, mut visit: impl FnMut(VoxelKey, Voxel, bool)) {
        self.drain_changed_blocks(|block| {
            let changed = *block.changed();
            block.for_each(&changed, &mut visit);
        });
    }

    /// [`RoiMap::drain_changes`] block by block, for a caller that keeps a few of the changed
    /// voxels and can tell which from masks (the solid ones, say): it reads only those voxels'
    /// values, where a scan's hundreds of thousands of freed voxels cost one mask test per block.
    /// Clears the record.
    pub fn drain_changed_blocks(&mut self, mut visit: impl FnMut(ChangedBlock<'_>)) {
        for bi in self.dirty_blocks.drain() {
            let b = &mut self.store.blocks[bi as usize];
            let coord = self.store.coords[bi as usize];
            visit(ChangedBlock { coord, block: b });
            b.dirty = EMPTY;
        }
    }

    /// Overwrites voxel values (for replicas and dashboards) and records them as changes when
    /// they differ. Entries with non-finite log-odds are ignored, so bad input cannot poison the map.
    pub fn apply_voxels(&mut self, voxels: &[(VoxelKey, Voxel)]) {
        let mut log = ChangeLog::default();
        for &(key, value) in voxels {
            if !(value.occupancy_logodds.is_finite() && value.roi_logodds.is_finite()) {
                continue;
            }
            if !(-KEY_LIMIT..KEY_LIMIT).contains(&i64::from(key.x))
                || !(-KEY_LIMIT..KEY_LIMIT).contains(&i64::from(key.y))
                || !(-KEY_LIMIT..KEY_LIMIT).contains(&i64::from(key.z))
            {
                continue;
            }
            self.set_voxel(key, value, &mut log);
        }
        self.refresh_derived(&log);
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
        // Block cache: the walk stays in one block for several steps.
        let mut cached: (VoxelKey, Option<&grid::Block>) =
            (block_of(key_origin), self.store.find(block_of(key_origin)));
        let mut lookup = |k: VoxelKey| -> Option<Voxel> {
            let bk = block_of(k);
            if bk != cached.0 {
                cached = (bk, self.store.find(bk));
            }
            let b = cached.1?;
            let l = local_of(k);
            mask_test(&b.known, l).then(|| Voxel {
                occupancy_logodds: b.occ_at(l),
                roi_logodds: b.roi_at(l),
            })
        };
        let go_on = match RaySetup::exact(origin, &unit, range_m, key_origin, key_end, res) {
            Some(setup) => setup.walk(|c| {
                let k = VoxelKey::new(c[0], c[1], c[2]);
                visit(k, lookup(k))
            }),
            None => true,
        };
        if go_on {
            visit(key_end, lookup(key_end));
        }
    }

    /// Walks exactly the voxels [`RoiMap::insert_scan`] frees for a point at `end` seen from
    /// `origin` (same `f32` inputs, same set-up), then the end voxel. `visit` stops the walk by
    /// returning false. Nothing is visited when a key is outside the map.
    pub fn walk_segment(
        &self,
        origin: &Point3<f32>,
        end: &Point3<f32>,
        mut visit: impl FnMut(VoxelKey, Option<Voxel>) -> bool,
    ) {
        let (o, e) = ([origin.x, origin.y, origin.z], [end.x, end.y, end.z]);
        let (Some(ko), Some(ke)) = (
            walk::key_of_f32(o, self.inv_res),
            walk::key_of_f32(e, self.inv_res),
        ) else {
            return;
        };
        let res = self.config.resolution_m;
        let go_on = match RaySetup::octomap(o, e, ko, ke, res) {
            Some(setup) => setup.walk(|c| {
                let k = VoxelKey::new(c[0], c[1], c[2]);
                visit(k, self.get(k))
            }),
            None => true,
        };
        if go_on {
            visit(ke, self.get(ke));
        }
    }

    /// ROI targets (paper-method §3): free voxels 6-adjacent to an ROI voxel that have an unknown
    /// 6-neighbour, with centre inside `region`; sorted. Maintained incrementally.
    pub fn roi_frontier(&self, region: &Aabb) -> Vec<VoxelKey> {
        self.frontier_in(&self.roi_front_blocks, region, |b| &b.roi_frontier)
    }

    /// Exploration frontier: free voxels with centre in `region` having both an unknown and an
    /// occupied 6-neighbour; sorted. Maintained incrementally.
    pub fn exploration_frontier(&self, region: &Aabb) -> Vec<VoxelKey> {
        self.frontier_in(&self.expl_blocks, region, |b| &b.expl_frontier)
    }

    fn frontier_in(
        &self,
        blocks: &KeySet,
        region: &Aabb,
        mask: impl Fn(&grid::Block) -> &Mask,
    ) -> Vec<VoxelKey> {
        let mut out = Vec::new();
        // A row's map holds far more frontier blocks than one trolley position's region: walk
        // the region's blocks then, so the cost follows the region, not the row.
        let in_region = self.blocks_in(region).filter(|r| r.len() < blocks.len());
        let candidates: Box<dyn Iterator<Item = VoxelKey>> = match in_region {
            Some(r) => Box::new(r.filter(|bk| blocks.contains(bk))),
            None => Box::new(blocks.iter().copied()),
        };
        for bk in candidates {
            let Some(b) = self.store.find(bk) else {
                continue;
            };
            for_each_bit(mask(b), |l| {
                let k = key_at(bk, l);
                if region.contains(&self.centre_of(k)) {
                    out.push(k);
                }
            });
        }
        out.sort_unstable();
        out
    }

    /// The block coordinates of the blocks overlapping `region` (None when it reaches past the
    /// keys' range).
    fn blocks_in(&self, region: &Aabb) -> Option<BlockRange> {
        let lo = grid::block_of(self.try_key_of(&region.min)?);
        let hi = grid::block_of(self.try_key_of(&region.max)?);
        Some(BlockRange {
            lo,
            hi,
            next: (lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z).then_some(lo),
        })
    }

    /// ROI voxels grown into 26-connected clusters; clusters with at least `min_voxels` voxels,
    /// ordered by their smallest key.
    pub fn clusters(&self, min_voxels: usize) -> Vec<RoiCluster> {
        let roi = self.roi_keys();
        let mut unvisited: KeySet = roi.iter().copied().collect();
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
                for n in k.neighbours(Neighbourhood::TwentySix) {
                    if unvisited.remove(&n) {
                        members.push(n);
                        stack.push(n);
                    }
                }
            }
            if members.len() < min_voxels.max(1) {
                continue;
            }
            clusters.push(self.cluster_of(members));
        }
        clusters
    }

    /// The cluster of the given voxels (sorted here): their mean centre and box. `voxels` must
    /// not be empty.
    pub fn cluster_of(&self, mut voxels: Vec<VoxelKey>) -> RoiCluster {
        voxels.sort_unstable();
        let res = self.config.resolution_m;
        let mut sum = Vector3::zeros();
        let first = voxels.first().copied().unwrap_or(VoxelKey::new(0, 0, 0));
        let (mut lo, mut hi) = (first, first);
        for &m in &voxels {
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
        RoiCluster {
            centre: Point3::from(sum / voxels.len().max(1) as f64),
            min: corner(lo, 0),
            max: corner(hi, 1),
            voxels,
        }
    }

    /// Whether a voxel with its centre in the box `[lo, hi]` may have changed since the map had
    /// taken `scans` scans ([`RoiMap::scans_inserted`]). Block-grained, so it can say yes for a
    /// change next to the box, never no for a change inside it: what was computed from the box
    /// then can be reused when this is false.
    pub fn changed_since(&self, lo: &Point3<f64>, hi: &Point3<f64>, scans: u64) -> bool {
        let (Some(a), Some(b)) = (self.try_key_of(lo), self.try_key_of(hi)) else {
            return true;
        };
        let (a, b) = (grid::block_of(a), grid::block_of(b));
        let span = |a: i32, b: i32| i64::from(b) - i64::from(a) + 1;
        if span(a.x, b.x) * span(a.y, b.y) * span(a.z, b.z) > 4096 {
            return true;
        }
        (a.x..=b.x).any(|x| {
            (a.y..=b.y).any(|y| {
                (a.z..=b.z).any(|z| {
                    self.store
                        .find(VoxelKey::new(x, y, z))
                        .is_some_and(|block| block.changed_at_scan > scans)
                })
            })
        })
    }

    /// Number of successful [`RoiMap::insert_scan`] calls.
    pub fn scans_inserted(&self) -> u64 {
        self.scans_inserted
    }

    /// Heap use in bytes: blocks, indexes, derived sets, and scan buffers (hash
    /// tables at their capacity, one control byte per slot).
    pub fn memory_bytes(&self) -> usize {
        let key = std::mem::size_of::<VoxelKey>() + 1;
        std::mem::size_of::<Self>()
            + self.store.heap_bytes()
            + self.dirty_blocks.capacity() * 5
            + (self.roi_set.capacity()
                + self.expl_blocks.capacity()
                + self.roi_front_blocks.capacity())
                * key
            + self.roi_changes.capacity() * std::mem::size_of::<VoxelKey>()
            + self.scratch.heap_bytes()
    }
}

#[cfg(test)]
mod tests;
