//! The hand-eye calibration error, estimated across many scans ([`HandEyeEstimator`]).
//!
//! A trolley's camera sits on its flange a little off from where its calibration says: a
//! rotation of a few tenths of a degree and a few millimetres, the same in every frame. Each
//! scan, placed at `world_from_camera · error`, then lands off by an amount that depends on the
//! arm's pose, so scans from different poses disagree where they see the same surface. One scan
//! against a noisy map cannot tell that error from a stereo camera's noise (docs/results.md,
//! "Registration"), but the error is one transform for the whole trolley: summed over the
//! surface two scans share, for every pair of a window of scans, the disagreement's normal
//! equations have six unknowns and tens of thousands of residuals, and the camera's noise,
//! different in every frame, averages out.
//!
//! Each scan keeps a subsample of its points within range, in its camera frame, with the normal
//! of the surface around each (the PCA of the scan's own points near it). The estimate
//! (`camera_believed_from_true`) minimises, by Gauss-Newton with Huber weights, the
//! point-to-plane distance of every query point of a scan to the nearest surface point of every
//! other scan in the window. Directions the poses do not constrain (every view turned about one
//! axis leaves a translation along it) are not updated. No I/O, no clocks, no randomness.

use std::collections::{HashMap, VecDeque};

use glasshouse_roimap::{KeyBuildHasher, VoxelKey};

use nalgebra::{
    Isometry3, Matrix3, Matrix6, Point3, Translation3, UnitQuaternion, Vector3, Vector6,
};
use serde::{Deserialize, Serialize};

use crate::SettingsError;

/// How the hand-eye error is estimated and when its estimate is used. Lengths in metres.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HandEyeSettings {
    /// Off: scans go in with the pose the trolley reports.
    pub enabled: bool,
    /// The estimate is made over this many of the latest scans.
    pub window_scans: usize,
    /// No correction is applied before this many scans were seen.
    pub min_scans: usize,
    /// Surface points kept per scan (each with its normal), the targets of the other scans.
    pub surface_points: usize,
    /// Of those, this many per scan are matched against the other scans.
    pub query_points: usize,
    /// Points farther than this from the camera are not used (stereo noise grows with range
    /// squared: 3.8 mm RMS at 1 m on a D435, 8.5 mm at 1.5 m).
    pub max_range_m: f64,
    /// A point's normal is the PCA of the scan's points within this radius.
    pub normal_radius_m: f64,
    /// Normals fitted to fewer points are not used.
    pub min_normal_points: usize,
    /// Smallest over middle eigenvalue of a normal's fit above which it is no plane.
    pub max_normal_ambiguity: f64,
    /// A query point's match in another scan is that scan's nearest surface point within this.
    pub match_radius_m: f64,
    /// Residuals beyond this get Huber weights.
    pub huber_m: f64,
    /// Matches farther than this from the other scan's plane are not used.
    pub max_plane_distance_m: f64,
    /// Matches whose two normals' cosine is below this are not used.
    pub min_normal_agreement: f64,
    /// Matching rounds per new scan (the estimate is refined from the previous one).
    pub rounds: usize,
    /// After this many scans the estimate is final: the error is the trolley's own and does
    /// not change, and a final estimate costs nothing per scan and keeps no scans.
    pub final_after_scans: usize,
    /// A direction of the normal equations whose eigenvalue is below this share of the
    /// largest is not updated.
    pub degenerate_eigen_ratio: f64,
    /// An estimate beyond these bounds is a wrong match, not a calibration error: not applied.
    pub max_rotation_deg: f64,
    pub max_translation_m: f64,
}

impl Default for HandEyeSettings {
    /// On: in a perfect world the estimate stays within a few hundredths of a degree and a
    /// millimetre of none; with a calibration error it undoes most of it (docs/results.md).
    fn default() -> Self {
        Self {
            enabled: true,
            window_scans: 24,
            min_scans: 6,
            surface_points: 2000,
            query_points: 500,
            max_range_m: 1.3,
            normal_radius_m: 0.025,
            min_normal_points: 8,
            max_normal_ambiguity: 0.3,
            match_radius_m: 0.02,
            huber_m: 0.004,
            max_plane_distance_m: 0.02,
            min_normal_agreement: 0.8,
            rounds: 2,
            final_after_scans: 32,
            degenerate_eigen_ratio: 0.02,
            max_rotation_deg: 3.0,
            max_translation_m: 0.03,
        }
    }
}

impl HandEyeSettings {
    pub fn validate(&self) -> Result<(), SettingsError> {
        let bad = |name, value: f64, expected| SettingsError::OutOfRange {
            name,
            value,
            expected,
        };
        let counts = [
            ("hand_eye.window_scans", self.window_scans, 2, 256),
            (
                "hand_eye.min_scans",
                self.min_scans,
                2,
                self.window_scans.max(2),
            ),
            ("hand_eye.surface_points", self.surface_points, 10, 1 << 16),
            (
                "hand_eye.query_points",
                self.query_points,
                1,
                self.surface_points,
            ),
            (
                "hand_eye.min_normal_points",
                self.min_normal_points,
                3,
                10_000,
            ),
            ("hand_eye.rounds", self.rounds, 1, 20),
            (
                "hand_eye.final_after_scans",
                self.final_after_scans,
                self.min_scans,
                1 << 20,
            ),
        ];
        for (name, value, lo, hi) in counts {
            if !(lo..=hi).contains(&value) {
                return Err(bad(
                    name,
                    value as f64,
                    "a count in its range (see the docs)",
                ));
            }
        }
        let positives = [
            ("hand_eye.max_range_m", self.max_range_m),
            ("hand_eye.normal_radius_m", self.normal_radius_m),
            ("hand_eye.match_radius_m", self.match_radius_m),
            ("hand_eye.huber_m", self.huber_m),
            ("hand_eye.max_plane_distance_m", self.max_plane_distance_m),
            ("hand_eye.max_rotation_deg", self.max_rotation_deg),
            ("hand_eye.max_translation_m", self.max_translation_m),
        ];
        for (name, value) in positives {
            if !(value.is_finite() && value > 0.0) {
                return Err(bad(name, value, "finite and > 0"));
            }
        }
        let shares = [
            ("hand_eye.max_normal_ambiguity", self.max_normal_ambiguity),
            (
                "hand_eye.degenerate_eigen_ratio",
                self.degenerate_eigen_ratio,
            ),
            ("hand_eye.min_normal_agreement", self.min_normal_agreement),
        ];
        for (name, value) in shares {
            if !(0.0..1.0).contains(&value) {
                return Err(bad(name, value, "in 0..1"));
            }
        }
        Ok(())
    }
}

/// A surface point of a scan in its camera frame, with the surface's normal there (single
/// precision: what a snapshot carries is exactly what the estimate reads).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Surfel {
    pub point: Vector3<f32>,
    pub normal: Vector3<f32>,
}

/// What one scan keeps for the estimate: its believed camera pose and surface.
#[derive(Clone, Debug, PartialEq)]
pub struct KeyScan {
    pub world_from_camera: Isometry3<f64>,
    pub surface: Vec<Surfel>,
}

/// Everything an estimator holds, for a snapshot ([`HandEyeEstimator::state`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct HandEyeState {
    pub camera_believed_from_true: Isometry3<f64>,
    pub scans_seen: u32,
    /// The window's scans, oldest first; none once the estimate is final.
    pub scans: Vec<KeyScan>,
}

/// The outcome of the latest estimate.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HandEyeFigures {
    /// Matches used in the last round.
    pub matches: usize,
    /// Their RMS point-to-plane distance after the last round, metres.
    pub rms_m: f64,
    /// Directions the poses constrained in the last round (of 6).
    pub constrained_directions: usize,
}

/// The hand-eye error of one trolley, estimated from its scans (module docs).
#[derive(Clone, Debug)]
pub struct HandEyeEstimator {
    settings: HandEyeSettings,
    scans: VecDeque<KeyScan>,
    scans_seen: u32,
    camera_believed_from_true: Isometry3<f64>,
    figures: HandEyeFigures,
}

impl HandEyeEstimator {
    pub fn new(settings: HandEyeSettings) -> Self {
        Self {
            settings,
            scans: VecDeque::new(),
            scans_seen: 0,
            camera_believed_from_true: Isometry3::identity(),
            figures: HandEyeFigures::default(),
        }
    }

    /// The estimate: the camera's true pose in the frame the trolley believes it in.
    pub fn camera_believed_from_true(&self) -> &Isometry3<f64> {
        &self.camera_believed_from_true
    }

    pub fn figures(&self) -> HandEyeFigures {
        self.figures
    }

    pub fn scans_seen(&self) -> u32 {
        self.scans_seen
    }

    /// Whether the estimate is final (`final_after_scans` were seen).
    pub fn is_final(&self) -> bool {
        self.scans_seen as usize >= self.settings.final_after_scans
    }

    /// What the estimator holds, for a snapshot.
    pub fn state(&self) -> HandEyeState {
        HandEyeState {
            camera_believed_from_true: self.camera_believed_from_true,
            scans_seen: self.scans_seen,
            scans: self.scans.iter().cloned().collect(),
        }
    }

    /// An estimator continuing from `state` (a snapshot's).
    pub fn from_state(settings: HandEyeSettings, state: HandEyeState) -> Self {
        Self {
            settings,
            scans: state.scans.into(),
            scans_seen: state.scans_seen,
            camera_believed_from_true: state.camera_believed_from_true,
            figures: HandEyeFigures::default(),
        }
    }

    /// The estimate without its scans, for the trolley's next visit: the error is the
    /// trolley's own, but the base is localised anew, so the last visit's scans would not
    /// agree with this one's.
    pub fn for_next_visit(&self) -> Self {
        Self {
            scans: VecDeque::new(),
            ..self.clone()
        }
    }

    /// Takes a scan (world-frame points placed with the believed `world_from_camera`) and
    /// refines the estimate with it.
    pub fn add_scan(
        &mut self,
        world_from_camera: &Isometry3<f64>,
        points_in_world: &[Point3<f32>],
    ) {
        self.add_scan_threaded(world_from_camera, points_in_world, 1);
    }

    /// [`HandEyeEstimator::add_scan`] with the scans' matches searched on `threads` threads; any
    /// count gives the same estimate, bit for bit (the sums are made in one order).
    pub fn add_scan_threaded(
        &mut self,
        world_from_camera: &Isometry3<f64>,
        points_in_world: &[Point3<f32>],
        threads: usize,
    ) {
        if !self.settings.enabled || self.is_final() {
            return;
        }
        self.scans_seen += 1;
        if self.is_final() {
            // The last scan counted: the estimate stands as it is, the window is let go.
            self.scans.clear();
            return;
        }
        let surface = surface_of(&self.settings, world_from_camera, points_in_world);
        if surface.is_empty() {
            return;
        }
        self.scans.push_back(KeyScan {
            world_from_camera: *world_from_camera,
            surface,
        });
        while self.scans.len() > self.settings.window_scans {
            self.scans.pop_front();
        }
        if self.scans.len() >= 2 {
            self.refine(threads);
        }
    }

    /// The correction to apply, in the world frame, to a scan placed with `world_from_camera`:
    /// None until `min_scans` were seen.
    pub fn world_correction(&self, world_from_camera: &Isometry3<f64>) -> Option<Isometry3<f64>> {
        if !self.settings.enabled || (self.scans_seen as usize) < self.settings.min_scans {
            return None;
        }
        let corrected = world_from_camera * self.camera_believed_from_true;
        Some(corrected * world_from_camera.inverse())
    }

    fn refine(&mut self, threads: usize) {
        for _ in 0..self.settings.rounds {
            let Some((step, figures)) = self.solve_round(threads) else {
                return;
            };
            let candidate = self.camera_believed_from_true * exp(&step);
            if !within_bounds(&self.settings, &candidate) {
                return;
            }
            self.camera_believed_from_true = candidate;
            self.figures = figures;
        }
    }

    /// One round: every scan's query points matched to the other scans' surfaces under the
    /// current estimate, and the Gauss-Newton step of the right perturbation of the estimate.
    /// The matches (most of the work) are searched on `threads` threads in contiguous runs of
    /// queries; the normal equations are summed afterwards in query order, as on one thread.
    fn solve_round(&self, threads: usize) -> Option<(Vector6<f64>, HandEyeFigures)> {
        let placed: Vec<Placed> = self.scans.iter().map(|s| self.place(s)).collect();
        let grid = Grid::new(&placed, self.settings.match_radius_m);
        let queries: Vec<(u32, u32)> = placed
            .iter()
            .enumerate()
            .flat_map(|(a, scan)| {
                let stride = (scan.surfels.len() / self.settings.query_points).max(1);
                (0..scan.surfels.len())
                    .step_by(stride)
                    .map(move |i| (a as u32, i as u32))
            })
            .collect();
        let search =
            |part: &[(u32, u32)]| grid.matches_of(&placed, part, self.settings.match_radius_m);
        let runs = in_runs(&queries, threads, search);
        let mut normal = Normal::default();
        for &(a, i, b, j) in runs.iter().flatten() {
            let [a, i, b, j] = [a, i, b, j].map(|v| v as usize);
            normal.add(&self.settings, &placed[a], i, &placed[b], j);
        }
        normal.step(&self.settings)
    }

    fn place(&self, scan: &KeyScan) -> Placed {
        let world_from_true = scan.world_from_camera * self.camera_believed_from_true;
        let rotation = *world_from_true.rotation.to_rotation_matrix().matrix();
        let surfels = scan
            .surface
            .iter()
            .map(|s| {
                let point = s.point.cast::<f64>();
                PlacedSurfel {
                    point,
                    world: world_from_true * Point3::from(point),
                    normal_world: rotation * s.normal.cast::<f64>(),
                }
            })
            .collect();
        Placed { rotation, surfels }
    }
}

/// A scan placed in the world under the current estimate.
struct Placed {
    /// The rotation of world_from_camera · estimate.
    rotation: Matrix3<f64>,
    surfels: Vec<PlacedSurfel>,
}

struct PlacedSurfel {
    /// In the camera frame.
    point: Vector3<f64>,
    world: Point3<f64>,
    normal_world: Vector3<f64>,
}

/// The placed surfels of every scan by cell: each cell's surfels lie together in `entries`, in
/// scan and surfel order (the order the matches, and so the sums, are made in), each with its
/// world position, so a query reads its candidates in one run of memory.
struct Grid {
    cell_m: f64,
    /// Per occupied cell, the range of its surfels in `entries`.
    cells: HashMap<VoxelKey, (u32, u32), KeyBuildHasher>,
    entries: Vec<Entry>,
}

#[derive(Clone, Copy)]
struct Entry {
    world: Point3<f64>,
    scan: u32,
    surfel: u32,
}

impl Grid {
    fn new(placed: &[Placed], cell_m: f64) -> Self {
        let total: usize = placed.iter().map(|scan| scan.surfels.len()).sum();
        let mut cells: HashMap<VoxelKey, (u32, u32), KeyBuildHasher> =
            HashMap::with_capacity_and_hasher(total, KeyBuildHasher::default());
        // Counted first, then placed: one allocation for every cell's pairs.
        let cell_of_each: Vec<VoxelKey> = placed
            .iter()
            .flat_map(|scan| scan.surfels.iter().map(|p| cell_of(&p.world, cell_m)))
            .collect();
        for key in &cell_of_each {
            cells.entry(*key).or_insert((0, 0)).1 += 1;
        }
        let mut start = 0;
        for range in cells.values_mut() {
            let len = range.1;
            *range = (start, start);
            start += len;
        }
        let unset = Entry {
            world: Point3::origin(),
            scan: 0,
            surfel: 0,
        };
        let mut entries = vec![unset; total];
        let all = placed.iter().enumerate().flat_map(|(s, scan)| {
            scan.surfels.iter().enumerate().map(move |(i, p)| Entry {
                world: p.world,
                scan: s as u32,
                surfel: i as u32,
            })
        });
        for (key, entry) in cell_of_each.iter().zip(all) {
            if let Some(range) = cells.get_mut(key) {
                entries[range.1 as usize] = entry;
                range.1 += 1;
            }
        }
        Self {
            cell_m,
            cells,
            entries,
        }
    }

    /// Every match of `queries` ((scan, surfel) pairs), in their order: (a, i, b, j) for the
    /// nearest surfel `j` of scan `b` to query surfel `i` of scan `a`.
    fn matches_of(
        &self,
        placed: &[Placed],
        queries: &[(u32, u32)],
        radius_m: f64,
    ) -> Vec<(u32, u32, u32, u32)> {
        let mut nearest = Nearest::new(placed.len());
        let mut out = Vec::new();
        for &(a, i) in queries {
            self.matches(placed, a as usize, i as usize, radius_m, &mut nearest);
            out.extend(
                nearest
                    .found
                    .iter()
                    .map(|&(b, j)| (a, i, b as u32, j as u32)),
            );
        }
        out
    }

    /// The nearest surfel within `radius_m` of surfel `i` of scan `a` in every other scan, into
    /// `nearest.found` (scans in the order first met).
    fn matches(&self, placed: &[Placed], a: usize, i: usize, radius_m: f64, nearest: &mut Nearest) {
        nearest.clear();
        let p = placed[a].surfels[i].world;
        let c = cell_of(&p, self.cell_m);
        for d in NEIGHBOURS {
            let key = VoxelKey {
                x: c.x + d[0],
                y: c.y + d[1],
                z: c.z + d[2],
            };
            let Some(&(from, to)) = self.cells.get(&key) else {
                continue;
            };
            for e in &self.entries[from as usize..to as usize] {
                let s = e.scan as usize;
                if s == a {
                    continue;
                }
                let d2 = (e.world - p).norm_squared();
                if d2 <= radius_m * radius_m {
                    nearest.offer(s, e.surfel as usize, d2);
                }
            }
        }
        nearest.finish();
    }
}

/// `work` over `items` cut into `threads` contiguous runs, one thread each; the results in the
/// runs' order. A thread's panic is the caller's.
fn in_runs<T: Sync, R: Send>(
    items: &[T],
    threads: usize,
    work: impl Fn(&[T]) -> R + Sync,
) -> Vec<R> {
    let run = items.len().div_ceil(threads.max(1)).max(1);
    if threads <= 1 || items.len() <= run {
        return vec![work(items)];
    }
    let work = &work;
    std::thread::scope(|scope| {
        let mut runs = items.chunks(run);
        let first = runs.next().unwrap_or(&[]);
        let others: Vec<_> = runs.map(|part| scope.spawn(move || work(part))).collect();
        let mut out = vec![work(first)];
        for handle in others {
            out.push(
                handle
                    .join()
                    .unwrap_or_else(|e| std::panic::resume_unwind(e)),
            );
        }
        out
    })
}

/// The nearest candidate per scan for one query point: a slot per scan of the window, so a
/// candidate costs one look-up, not a search of the scans met so far.
struct Nearest {
    /// Per scan: its nearest surfel so far and the squared distance (`NONE`: none yet).
    best: Vec<(usize, f64)>,
    /// Scans met, in the order first met.
    met: Vec<usize>,
    /// The matches: (scan, surfel), in the order the scans were first met.
    found: Vec<(usize, usize)>,
}

impl Nearest {
    const NONE: usize = usize::MAX;

    fn new(scans: usize) -> Self {
        Self {
            best: vec![(Self::NONE, 0.0); scans],
            met: Vec::new(),
            found: Vec::new(),
        }
    }

    fn clear(&mut self) {
        for &s in &self.met {
            self.best[s] = (Self::NONE, 0.0);
        }
        self.met.clear();
        self.found.clear();
    }

    /// A candidate replaces the scan's nearest only when strictly nearer (the first met wins
    /// a tie).
    fn offer(&mut self, s: usize, j: usize, d2: f64) {
        let slot = &mut self.best[s];
        if slot.0 == Self::NONE {
            self.met.push(s);
            *slot = (j, d2);
        } else if d2 < slot.1 {
            *slot = (j, d2);
        }
    }

    fn finish(&mut self) {
        let best = &self.best;
        self.found.extend(self.met.iter().map(|&s| (s, best[s].0)));
    }
}

const NEIGHBOURS: [[i32; 3]; 27] = {
    let mut out = [[0; 3]; 27];
    let mut n = 0;
    while n < 27 {
        out[n] = [
            (n / 9) as i32 - 1,
            ((n / 3) % 3) as i32 - 1,
            (n % 3) as i32 - 1,
        ];
        n += 1;
    }
    out
};

fn cell_of(p: &Point3<f64>, cell_m: f64) -> VoxelKey {
    VoxelKey {
        x: (p.x / cell_m).floor() as i32,
        y: (p.y / cell_m).floor() as i32,
        z: (p.z / cell_m).floor() as i32,
    }
}

/// The normal equations of one round.
#[derive(Default)]
struct Normal {
    h: Matrix6<f64>,
    g: Vector6<f64>,
    squares: f64,
    matches: usize,
}

impl Normal {
    /// The residual of query `i` of scan `a` against surfel `j` of scan `b`: the distance
    /// along `b`'s normal, differentiated by the estimate's right perturbation.
    fn add(&mut self, settings: &HandEyeSettings, a: &Placed, i: usize, b: &Placed, j: usize) {
        let (qa, sb) = (&a.surfels[i], &b.surfels[j]);
        let n = sb.normal_world;
        let r = n.dot(&(qa.world - sb.world));
        // Two surfaces, not one: a leaf behind another, or the far side of a fruit.
        if r.abs() > settings.max_plane_distance_m
            || qa.normal_world.dot(&n).abs() < settings.min_normal_agreement
        {
            return;
        }
        let va = a.rotation.transpose() * n;
        let vb = b.rotation.transpose() * n;
        let rot = qa.point.cross(&va) - sb.point.cross(&vb);
        let trans = va - vb;
        let j_row = Vector6::new(rot.x, rot.y, rot.z, trans.x, trans.y, trans.z);
        let w = if r.abs() <= settings.huber_m {
            1.0
        } else {
            settings.huber_m / r.abs()
        };
        self.h += w * j_row * j_row.transpose();
        self.g += w * r * j_row;
        self.squares += r * r;
        self.matches += 1;
    }

    /// The step (rotation vector, translation) on the constrained directions.
    fn step(&self, settings: &HandEyeSettings) -> Option<(Vector6<f64>, HandEyeFigures)> {
        if self.matches < 6 {
            return None;
        }
        let eigen = self.h.symmetric_eigen();
        let largest = eigen.eigenvalues.max();
        if largest <= 0.0 {
            return None;
        }
        let mut step = Vector6::zeros();
        let mut constrained = 0;
        for k in 0..6 {
            let lambda = eigen.eigenvalues[k];
            if lambda < settings.degenerate_eigen_ratio * largest {
                continue;
            }
            let v = eigen.eigenvectors.column(k);
            step -= v * (v.dot(&self.g) / lambda);
            constrained += 1;
        }
        let figures = HandEyeFigures {
            matches: self.matches,
            rms_m: (self.squares / self.matches as f64).sqrt(),
            constrained_directions: constrained,
        };
        Some((step, figures))
    }
}

/// The rigid transform of a step (rotation vector, translation).
fn exp(step: &Vector6<f64>) -> Isometry3<f64> {
    let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(step[0], step[1], step[2]));
    Isometry3::from_parts(Translation3::new(step[3], step[4], step[5]), rotation)
}

fn within_bounds(settings: &HandEyeSettings, estimate: &Isometry3<f64>) -> bool {
    estimate.rotation.angle() <= settings.max_rotation_deg.to_radians()
        && estimate.translation.vector.norm() <= settings.max_translation_m
}

/// The scan's surface points in its camera frame, each with its normal: every point within
/// range is a neighbour, a fixed stride of them are kept.
fn surface_of(
    settings: &HandEyeSettings,
    world_from_camera: &Isometry3<f64>,
    points_in_world: &[Point3<f32>],
) -> Vec<Surfel> {
    let camera_from_world = world_from_camera.inverse();
    let in_range: Vec<Vector3<f64>> = points_in_world
        .iter()
        .filter(|p| p.iter().all(|c| c.is_finite()))
        .map(|p| (camera_from_world * p.cast::<f64>()).coords)
        .filter(|q| q.norm() <= settings.max_range_m)
        .collect();
    if in_range.is_empty() {
        return Vec::new();
    }
    let radius = settings.normal_radius_m;
    let mut cells: HashMap<VoxelKey, Vec<u32>, KeyBuildHasher> = HashMap::default();
    for (i, q) in in_range.iter().enumerate() {
        cells
            .entry(cell_of(&Point3::from(*q), radius))
            .or_default()
            .push(i as u32);
    }
    let stride = (in_range.len() / settings.surface_points).max(1);
    (0..in_range.len())
        .step_by(stride)
        .filter_map(|i| {
            let normal = normal_at(settings, &in_range, &cells, &in_range[i])?;
            Some(Surfel {
                point: in_range[i].cast(),
                normal: normal.cast(),
            })
        })
        .collect()
}

/// The PCA normal of the points within the normal radius of `at`, facing the camera; None for
/// too few points or no plane.
fn normal_at(
    settings: &HandEyeSettings,
    points: &[Vector3<f64>],
    cells: &HashMap<VoxelKey, Vec<u32>, KeyBuildHasher>,
    at: &Vector3<f64>,
) -> Option<Vector3<f64>> {
    let radius = settings.normal_radius_m;
    let c = cell_of(&Point3::from(*at), radius);
    let near: Vec<&Vector3<f64>> = NEIGHBOURS
        .iter()
        .filter_map(|d| {
            cells.get(&VoxelKey {
                x: c.x + d[0],
                y: c.y + d[1],
                z: c.z + d[2],
            })
        })
        .flatten()
        .map(|&i| &points[i as usize])
        .filter(|p| (*p - at).norm_squared() <= radius * radius)
        .collect();
    if near.len() < settings.min_normal_points {
        return None;
    }
    let mean = near.iter().fold(Vector3::zeros(), |s, p| s + *p) / near.len() as f64;
    let cov = near.iter().fold(Matrix3::zeros(), |s, p| {
        let d = *p - mean;
        s + d * d.transpose()
    });
    let eigen = cov.symmetric_eigen();
    let mut order = [0, 1, 2];
    order.sort_by(|&x, &y| eigen.eigenvalues[x].total_cmp(&eigen.eigenvalues[y]));
    let (smallest, middle) = (eigen.eigenvalues[order[0]], eigen.eigenvalues[order[1]]);
    if middle <= 0.0 || smallest / middle > settings.max_normal_ambiguity {
        return None;
    }
    let normal = eigen.eigenvectors.column(order[0]).into_owned();
    // Facing the camera, so two scans' normals of one surface agree in sign.
    Some(if normal.dot(at) > 0.0 {
        -normal
    } else {
        normal
    })
}
