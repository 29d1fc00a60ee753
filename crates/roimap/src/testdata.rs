//! The shared benchmark and test workload (seeded, no I/O): a pinhole RGB-D camera looking at 30
//! spheres in front of a back plane.
//!
//! - Camera: 640×480, fx = fy = 525, cx = 319.5, cy = 239.5, looking from near the world origin
//!   at (0.8, 0, 0) (z up).
//! - Scene: 30 spheres of radius 3–5 cm, centres 0.4–1.2 m along +x and inside the view (seeded),
//!   and a plane at x = 1.5 m. Sphere points are ROI, plane points are not.
//! - Maximum range 1.5 m, 1 cm voxels.
//! - *raw* scan: one point per pixel that sees something (307,200 rays on the standard scene);
//!   *filtered* scan: one averaged point per 1 cm voxel (about 22k points).
//! - Ten scans from ten nearby origins (the first at the world origin).

use std::collections::BTreeMap;

use glasshouse_geom::CameraIntrinsics;
use nalgebra::{Point3, Vector3};

use crate::{MapConfig, MapError, RoiMap, VoxelKey};

/// Small seeded generator (SplitMix64).
#[derive(Clone, Debug)]
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [lo, hi).
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
}

/// The workload's camera: 640×480, f = 525, centre (319.5, 239.5).
pub const STANDARD_CAMERA: CameraIntrinsics = CameraIntrinsics {
    width: 640,
    height: 480,
    fx: 525.0,
    fy: 525.0,
    cx: 319.5,
    cy: 239.5,
};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sphere {
    pub centre: Point3<f64>,
    pub radius_m: f64,
}

/// One scan: sensor origin, points and ROI labels.
#[derive(Clone, Debug, PartialEq)]
pub struct Scan {
    pub origin: Point3<f64>,
    pub points: Vec<Point3<f32>>,
    pub roi: Vec<bool>,
}

/// A seeded scene and camera.
#[derive(Clone, Debug, PartialEq)]
pub struct Workload {
    pub camera: CameraIntrinsics,
    pub spheres: Vec<Sphere>,
    pub plane_x_m: f64,
    pub max_range_m: f64,
    pub resolution_m: f64,
    pub look_at: Point3<f64>,
    pub origins: Vec<Point3<f64>>,
}

/// Camera axes (right, down, forward) of a camera at `origin` looking at `target`, z up.
pub fn camera_axes(origin: &Point3<f64>, target: &Point3<f64>) -> [Vector3<f64>; 3] {
    let forward = (target - origin).normalize();
    let right = forward
        .cross(&Vector3::z())
        .try_normalize(1e-9)
        .unwrap_or_else(|| -Vector3::y());
    let down = forward.cross(&right);
    [right, down, forward]
}

impl Workload {
    /// The benchmark workload (30 spheres, 640×480, ten origins).
    pub fn standard(seed: u64) -> Self {
        Self::generate(seed, STANDARD_CAMERA, 30, 10)
    }

    /// A small variant for tests: the same scene layout seen by a `width`×`height` camera with
    /// the same field of view.
    pub fn small(seed: u64, width: u32, height: u32, spheres: usize, scans: usize) -> Self {
        let s = f64::from(width) / 640.0;
        let camera = CameraIntrinsics {
            width,
            height,
            fx: 525.0 * s,
            fy: 525.0 * s,
            cx: (f64::from(width) - 1.0) / 2.0,
            cy: (f64::from(height) - 1.0) / 2.0,
        };
        Self::generate(seed, camera, spheres, scans)
    }

    fn generate(seed: u64, camera: CameraIntrinsics, n_spheres: usize, n_scans: usize) -> Self {
        let mut rng = SplitMix64(seed);
        let half_w = f64::from(camera.width) / 2.0 / camera.fx;
        let half_h = f64::from(camera.height) / 2.0 / camera.fy;
        let spheres = (0..n_spheres)
            .map(|_| {
                let x = rng.uniform(0.4, 1.2);
                let radius_m = rng.uniform(0.03, 0.05);
                Sphere {
                    centre: Point3::new(
                        x,
                        rng.uniform(-0.8, 0.8) * half_w * x,
                        rng.uniform(-0.8, 0.8) * half_h * x,
                    ),
                    radius_m,
                }
            })
            .collect();
        let origins = (0..n_scans)
            .map(|i| {
                if i == 0 {
                    Point3::origin()
                } else {
                    Point3::new(
                        rng.uniform(-0.05, 0.05),
                        rng.uniform(-0.1, 0.1),
                        rng.uniform(-0.1, 0.1),
                    )
                }
            })
            .collect();
        Self {
            camera,
            spheres,
            plane_x_m: 1.5,
            max_range_m: 1.5,
            resolution_m: 0.01,
            look_at: Point3::new(0.8, 0.0, 0.0),
            origins,
        }
    }

    /// Map configuration of the workload (1 cm, 1.5 m range).
    pub fn map_config(&self) -> MapConfig {
        MapConfig {
            resolution_m: self.resolution_m,
            max_range_m: Some(self.max_range_m),
            ..MapConfig::default()
        }
    }

    /// First hit of the ray `origin + t * dir` (`dir` unit) and whether it is on a sphere.
    fn cast(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<(f64, bool)> {
        let mut best: Option<(f64, bool)> = None;
        for s in &self.spheres {
            let oc = origin - s.centre;
            let b = oc.dot(dir);
            let c = oc.norm_squared() - s.radius_m * s.radius_m;
            let disc = b * b - c;
            if disc < 0.0 {
                continue;
            }
            let t = -b - disc.sqrt();
            if t > 1e-6 && best.is_none_or(|(bt, _)| t < bt) {
                best = Some((t, true));
            }
        }
        if dir.x > 1e-12 {
            let t = (self.plane_x_m - origin.x) / dir.x;
            if t > 1e-6 && best.is_none_or(|(bt, _)| t < bt) {
                best = Some((t, false));
            }
        }
        best
    }

    /// Every pixel's point seen from `origin` looking at `look_at` (pixels that see nothing are
    /// left out; on this scene every pixel sees the plane or a sphere).
    pub fn raw_scan(&self, origin: &Point3<f64>) -> Scan {
        let [right, down, forward] = camera_axes(origin, &self.look_at);
        let c = &self.camera;
        let n = (c.width * c.height) as usize;
        let mut points = Vec::with_capacity(n);
        let mut roi = Vec::with_capacity(n);
        for v in 0..c.height {
            for u in 0..c.width {
                let d = (forward
                    + right * ((f64::from(u) - c.cx) / c.fx)
                    + down * ((f64::from(v) - c.cy) / c.fy))
                    .normalize();
                if let Some((t, on_sphere)) = self.cast(origin, &d) {
                    points.push((origin + d * t).cast::<f32>());
                    roi.push(on_sphere);
                }
            }
        }
        Scan {
            origin: *origin,
            points,
            roi,
        }
    }

    /// The raw scan averaged per voxel: one point per 1 cm voxel (ROI when most of its points
    /// are), sorted by voxel key.
    pub fn filtered_scan(&self, origin: &Point3<f64>) -> Scan {
        downsample(&self.raw_scan(origin), self.resolution_m)
    }

    /// Raw scans from all origins.
    pub fn raw_scans(&self) -> Vec<Scan> {
        self.origins.iter().map(|o| self.raw_scan(o)).collect()
    }

    /// Filtered scans from all origins.
    pub fn filtered_scans(&self) -> Vec<Scan> {
        self.origins.iter().map(|o| self.filtered_scan(o)).collect()
    }

    /// A map with every filtered scan inserted.
    pub fn filtered_map(&self) -> Result<RoiMap, MapError> {
        let mut map = RoiMap::new(self.map_config())?;
        for s in self.filtered_scans() {
            map.insert_scan(&s.origin, &s.points, &s.roi)?;
        }
        Ok(map)
    }

    /// Pose of the gain benchmark's camera: a new view beside the scan origins.
    pub fn gain_view(&self) -> (Point3<f64>, Point3<f64>) {
        (Point3::new(0.05, -0.25, 0.12), self.look_at)
    }

    /// The gain benchmark's camera origin and its 200×150 ray fan (60°×45°).
    pub fn gain_fan(&self) -> (Point3<f64>, Vec<Vector3<f64>>) {
        let (origin, target) = self.gain_view();
        let fan = ray_fan(
            &origin,
            &target,
            200,
            150,
            60f64.to_radians(),
            45f64.to_radians(),
        );
        (origin, fan)
    }

    /// The planner's gain fan from the same view: 8×6 rays over 80°×62° (a 4:3 image), as
    /// `PlannerConfig::default` scores each candidate view with (rays of 1 m).
    pub fn planner_gain_fan(&self) -> (Point3<f64>, Vec<Vector3<f64>>) {
        let (origin, target) = self.gain_view();
        let hfov_rad = 80f64.to_radians();
        let vfov_rad = 2.0 * ((hfov_rad / 2.0).tan() * 0.75).atan();
        (origin, ray_fan(&origin, &target, 8, 6, hfov_rad, vfov_rad))
    }
}

/// One averaged point per voxel of `resolution_m`, ROI by majority, sorted by voxel key.
pub fn downsample(scan: &Scan, resolution_m: f64) -> Scan {
    let inv = 1.0 / resolution_m;
    let mut cells: BTreeMap<VoxelKey, (Vector3<f64>, u32, u32)> = BTreeMap::new();
    for (p, &r) in scan.points.iter().zip(&scan.roi) {
        let p: Point3<f64> = p.cast();
        let k = VoxelKey::new(
            (p.x * inv).floor() as i32,
            (p.y * inv).floor() as i32,
            (p.z * inv).floor() as i32,
        );
        let e = cells.entry(k).or_insert((Vector3::zeros(), 0, 0));
        e.0 += p.coords;
        e.1 += 1;
        e.2 += u32::from(r);
    }
    let mut points = Vec::with_capacity(cells.len());
    let mut roi = Vec::with_capacity(cells.len());
    for (sum, n, r) in cells.into_values() {
        points.push(Point3::from(sum / f64::from(n)).cast::<f32>());
        roi.push(2 * r > n);
    }
    Scan {
        origin: scan.origin,
        points,
        roi,
    }
}

/// Unit ray directions of a `width`×`height` fan spanning `hfov_rad`×`vfov_rad` (pinhole grid)
/// for a camera at `origin` looking at `target`.
pub fn ray_fan(
    origin: &Point3<f64>,
    target: &Point3<f64>,
    width: usize,
    height: usize,
    hfov_rad: f64,
    vfov_rad: f64,
) -> Vec<Vector3<f64>> {
    let [right, down, forward] = camera_axes(origin, target);
    let mut out = Vec::with_capacity(width * height);
    for row in 0..height {
        let v = vfov_rad * ((row as f64 + 0.5) / height as f64 - 0.5);
        for col in 0..width {
            let h = hfov_rad * ((col as f64 + 0.5) / width as f64 - 0.5);
            out.push((forward + right * h.tan() + down * v.tan()).normalize());
        }
    }
    out
}

/// Unobserved-voxel gain U_U (paper eq. 1): along each ray count the unknown voxels until an
/// occupied voxel (which counts in N) or the range; mean over rays of unknown / visited.
pub fn unobserved_gain(
    map: &RoiMap,
    origin: &Point3<f64>,
    fan: &[Vector3<f64>],
    range_m: f64,
) -> f64 {
    let counts = fan.iter().map(|dir| {
        let (mut visited, mut unknown) = (0u32, 0u32);
        map.walk_ray(origin, dir, range_m, |_, v| {
            visited += 1;
            match v {
                None => {
                    unknown += 1;
                    true
                }
                Some(v) => v.occupancy_logodds <= 0.0,
            }
        });
        (visited, unknown)
    });
    mean_unknown_share(counts, fan.len())
}

/// [`unobserved_gain`] through the batch walk ([`RoiMap::count_unknown_until_occupied`]): the
/// same value, the rays walked eight at a time.
pub fn unobserved_gain_batch(
    map: &RoiMap,
    origin: &Point3<f64>,
    fan: &[Vector3<f64>],
    range_m: f64,
) -> f64 {
    if fan.is_empty() {
        return 0.0;
    }
    let counts = map.count_unknown_until_occupied(origin, fan, range_m);
    mean_unknown_share(counts.iter().map(|c| (c.visited, c.unknown)), fan.len())
}

/// Mean over `rays` rays of unknown / visited, from each ray's (visited, unknown) count; a ray
/// that visited nothing counts 0.
fn mean_unknown_share(counts: impl Iterator<Item = (u32, u32)>, rays: usize) -> f64 {
    if rays == 0 {
        return 0.0;
    }
    let total = counts
        .filter(|&(visited, _)| visited > 0)
        .fold(0.0, |total, (visited, unknown)| {
            total + f64::from(unknown) / f64::from(visited)
        });
    total / rays as f64
}
