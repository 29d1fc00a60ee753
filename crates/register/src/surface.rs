//! The map's occupied surface as ICP sees it: for a point, the nearest occupied voxel within the
//! search radius and that voxel's plane (the PCA of the occupied voxel centres around it).

use std::collections::HashMap;

use glasshouse_roimap::{KeyBuildHasher, Occupancy, RoiMap, VoxelKey};
use nalgebra::{Matrix3, Point3, Unit, Vector3};

use crate::memo::OccupancyMemo;
use crate::RegisterSettings;

/// A local plane of the map's surface, world frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Plane {
    pub centroid: Point3<f64>,
    pub normal: Unit<Vector3<f64>>,
}

impl Plane {
    /// Signed distance of `p` from the plane.
    pub fn residual_m(&self, p: &Point3<f64>) -> f64 {
        self.normal.dot(&(p - self.centroid))
    }
}

/// What the map says about one scan point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Probe {
    /// Occupied surface within the search radius, with a usable plane.
    Surface(Plane),
    /// Occupied surface within the search radius whose normal is ambiguous (an edge, a stem).
    Ambiguous,
    /// No surface near, and the point's voxel is known free: the map saw through here.
    Free,
    /// No surface near, the point's voxel is unknown, and the first known voxel on the way back
    /// to the sensor is occupied: the scan claims to see through surface the map knows.
    Behind,
    /// No surface near, and the map knows nothing of the point's voxel (new surface).
    Unknown,
}

impl Probe {
    /// Whether the map contradicts a point: it lies where the map saw empty space or behind
    /// surface the map knows.
    pub fn contradicts_map(&self) -> bool {
        matches!(self, Probe::Free | Probe::Behind)
    }
}

/// Key offsets within a radius, nearest first, and the same offsets in the memo's box.
struct Offsets {
    radius: i32,
    keys: Vec<(i32, i32, i32)>,
    linear: Vec<isize>,
}

impl Offsets {
    fn within(radius: u32, memo: &OccupancyMemo) -> Self {
        let keys = offsets_within(radius);
        Self {
            radius: radius as i32,
            linear: memo.linear_offsets(&keys),
            keys,
        }
    }
}

/// Integer offsets within a radius, nearest first (ties in a fixed order).
fn offsets_within(radius: u32) -> Vec<(i32, i32, i32)> {
    let r = radius as i32;
    let mut out = Vec::new();
    for dx in -r..=r {
        for dy in -r..=r {
            for dz in -r..=r {
                if dx * dx + dy * dy + dz * dz <= r * r {
                    out.push((dx, dy, dz));
                }
            }
        }
    }
    out.sort_by_key(|&(dx, dy, dz)| dx * dx + dy * dy + dz * dz);
    out
}

/// The map's surface near the scan, with the planes fitted so far kept by voxel.
pub(crate) struct Surface<'m> {
    map: &'m RoiMap,
    memo: OccupancyMemo,
    resolution_m: f64,
    search: Offsets,
    neighbourhood: Offsets,
    planes: HashMap<VoxelKey, Option<Plane>, KeyBuildHasher>,
    min_normal_voxels: usize,
    max_normal_ambiguity: f64,
}

impl<'m> Surface<'m> {
    /// The surface near the points `sample` (world frame).
    pub fn new(map: &'m RoiMap, sample: &[Point3<f64>], settings: &RegisterSettings) -> Self {
        // Room for the searches, the plane fits and a few voxels of correction.
        let margin = (settings.search_radius_voxels + settings.normal_radius_voxels + 3) as i32;
        let keys = sample.iter().filter_map(|p| map.try_key_of(p));
        let memo = OccupancyMemo::around(keys, margin);
        Self {
            map,
            resolution_m: map.config().resolution_m,
            search: Offsets::within(settings.search_radius_voxels, &memo),
            neighbourhood: Offsets::within(settings.normal_radius_voxels, &memo),
            memo,
            planes: HashMap::default(),
            min_normal_voxels: settings.min_normal_voxels,
            max_normal_ambiguity: settings.max_normal_ambiguity,
        }
    }

    /// Calls `visit` with each occupied voxel (offset index, offset) among the first `limit`
    /// offsets of the search (else of the plane neighbourhood) around `key`, nearest first,
    /// until it returns false.
    fn occupied_around(
        &mut self,
        key: VoxelKey,
        (search, limit): (bool, usize),
        mut visit: impl FnMut(usize, (i32, i32, i32)) -> bool,
    ) {
        let offsets = if search {
            &self.search
        } else {
            &self.neighbourhood
        };
        let base = self.memo.index_with_room(key, offsets.radius);
        for (i, &(dx, dy, dz)) in offsets.keys.iter().enumerate().take(limit) {
            let k = key.offset(dx, dy, dz);
            let occupied = match base {
                // Inside the box: no bounds to check per voxel.
                Some(base) => {
                    let at = base.wrapping_add_signed(offsets.linear[i]);
                    self.memo.occupied_at(self.map, at, k)
                }
                None => self.memo.occupied(self.map, k),
            };
            if occupied && !visit(i, (dx, dy, dz)) {
                return;
            }
        }
    }

    /// What the map says about the point `p` (world frame), searching its surface within the
    /// search radius.
    pub fn probe(&mut self, p: &Point3<f64>) -> Probe {
        self.probe_within(p, self.search.keys.len())
    }

    /// The surface of the point `p` (world frame) within a voxel's diagonal (18-neighbourhood):
    /// a pair once the scan is roughly aligned. Farther surface there is most often another
    /// surface than the point's (new surface beside known one), which would pull the scan.
    pub fn near_surface(&mut self, p: &Point3<f64>) -> Option<Plane> {
        match self.probe_within(p, NEAR_OFFSETS) {
            Probe::Surface(plane) => Some(plane),
            _ => None,
        }
    }

    /// [`Surface::probe`] over the first `offsets` search offsets.
    fn probe_within(&mut self, p: &Point3<f64>, offsets: usize) -> Probe {
        let Some(key) = self.map.try_key_of(p) else {
            return Probe::Unknown;
        };
        let mut nearest = None;
        self.occupied_around(key, (true, offsets), |_, (dx, dy, dz)| {
            nearest = Some(key.offset(dx, dy, dz));
            false
        });
        match nearest {
            Some(surface) => match self.plane(surface) {
                Some(plane) => Probe::Surface(plane),
                None => Probe::Ambiguous,
            },
            None if self.map.occupancy(key) == Occupancy::Free => Probe::Free,
            None => Probe::Unknown,
        }
    }

    /// [`Surface::probe`], then for a point in unknown space whether it lies behind known
    /// surface as seen from `sensor` (both world frame).
    pub fn classify(&mut self, p: &Point3<f64>, sensor: &Point3<f64>) -> Probe {
        match self.probe(p) {
            Probe::Unknown if self.first_known_is_occupied(p, sensor) => Probe::Behind,
            probe => probe,
        }
    }

    /// Whether the first known voxel from `p` towards `sensor` is occupied.
    fn first_known_is_occupied(&self, p: &Point3<f64>, sensor: &Point3<f64>) -> bool {
        let mut occupied = false;
        let towards = sensor - p;
        self.map
            .walk_ray(p, &towards, towards.norm(), |_, voxel| match voxel {
                Some(v) => {
                    occupied = v.occupancy_logodds > 0.0;
                    false
                }
                None => true,
            });
        occupied
    }

    /// The plane of the occupied voxels around `key`, fitted once per call of the registration.
    fn plane(&mut self, key: VoxelKey) -> Option<Plane> {
        if let Some(&plane) = self.planes.get(&key) {
            return plane;
        }
        let plane = self.fit_plane(key);
        self.planes.insert(key, plane);
        plane
    }

    /// PCA of the occupied voxel centres within the neighbourhood of `key`; None when too few
    /// or when the smallest spread is not clearly below the middle one (no single normal).
    /// The plane passes through the centroid of the occupied voxels of the 3×3×3 cube around
    /// `key` only: over the whole neighbourhood a curved surface (a 4 cm fruit) would put it
    /// millimetres inside, and over the voxel alone the plane would carry the voxel's
    /// quantisation (measured on simulated plants, the cube's centroid gave the least biased
    /// alignments).
    fn fit_plane(&mut self, key: VoxelKey) -> Option<Plane> {
        // Offsets in voxels, relative to `key`, so the sums stay small and exact.
        let (mut n, mut n_inner) = (0usize, 0usize);
        let (mut sum, mut sum_inner) = (Vector3::<f64>::zeros(), Vector3::<f64>::zeros());
        let mut outer = Matrix3::<f64>::zeros();
        self.occupied_around(key, (false, usize::MAX), |i, (dx, dy, dz)| {
            let d = Vector3::new(f64::from(dx), f64::from(dy), f64::from(dz));
            n += 1;
            sum += d;
            outer += d * d.transpose();
            if i < INNER_CUBE {
                n_inner += 1;
                sum_inner += d;
            }
            true
        });
        if n < self.min_normal_voxels {
            return None;
        }
        let mean = sum / n as f64;
        let covariance = outer / n as f64 - mean * mean.transpose();
        let normal = flattest_direction(&covariance, self.max_normal_ambiguity)?;
        let offset = sum_inner / n_inner.max(1) as f64 * self.resolution_m;
        let centroid = self.map.centre_of(key) + offset;
        Some(Plane { centroid, normal })
    }
}

/// The offsets nearest first begin with the voxel and its face neighbours (7), then its edge
/// neighbours (19 in all), then its corner neighbours (the 3×3×3 cube, 27).
const NEAR_OFFSETS: usize = 19;
const INNER_CUBE: usize = 27;

/// The eigenvector of the smallest eigenvalue of a symmetric 3×3 covariance, when that
/// eigenvalue is at most `max_ambiguity` times the middle one (else the normal is ambiguous).
/// Closed form (trigonometric eigenvalues, then the null space of `A − λI` by cross products):
/// an iterative solver was most of the fit's cost.
fn flattest_direction(a: &Matrix3<f64>, max_ambiguity: f64) -> Option<Unit<Vector3<f64>>> {
    let off = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    let q = a.trace() / 3.0;
    let p2 =
        (a[(0, 0)] - q).powi(2) + (a[(1, 1)] - q).powi(2) + (a[(2, 2)] - q).powi(2) + 2.0 * off;
    let p = (p2 / 6.0).sqrt();
    if p.is_nan() || p <= 1e-12 {
        return None; // isotropic: no direction stands out
    }
    let b = (a - Matrix3::identity() * q) / p;
    let phi = (b.determinant() / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    let largest = q + 2.0 * p * phi.cos();
    let smallest = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
    let middle = 3.0 * q - largest - smallest;
    if middle <= 0.0 || smallest > max_ambiguity * middle {
        return None;
    }
    let m = a - Matrix3::identity() * smallest;
    let (r0, r1, r2) = (
        m.row(0).transpose(),
        m.row(1).transpose(),
        m.row(2).transpose(),
    );
    let candidates = [r0.cross(&r1), r0.cross(&r2), r1.cross(&r2)];
    let best = candidates
        .into_iter()
        .max_by(|x, y| x.norm_squared().total_cmp(&y.norm_squared()))?;
    Unit::try_new(best, 1e-12)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn offsets_come_nearest_first_and_stay_in_the_sphere() {
        let offsets = offsets_within(2);
        assert_eq!(offsets[0], (0, 0, 0));
        assert_eq!(offsets.len(), 33);
        let d2: Vec<i32> = offsets
            .iter()
            .map(|&(x, y, z)| x * x + y * y + z * z)
            .collect();
        assert!(d2.windows(2).all(|w| w[0] <= w[1]));
        assert!(d2.iter().all(|&d| d <= 4));
        assert!(d2[..NEAR_OFFSETS].iter().all(|&d| d <= 2));
        assert!(d2[NEAR_OFFSETS..].iter().all(|&d| d > 2));
        assert!(d2[..INNER_CUBE].iter().all(|&d| d <= 3));
        assert!(d2[INNER_CUBE..].iter().all(|&d| d > 3));
    }

    #[test]
    fn the_closed_form_normal_matches_an_iterative_solver() {
        let spreads = [
            Matrix3::new(4.0, 0.3, -0.2, 0.3, 2.0, 0.1, -0.2, 0.1, 0.2),
            Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.05),
            Matrix3::new(2.0, 1.9, 0.0, 1.9, 2.0, 0.0, 0.0, 0.0, 3.0),
        ];
        for a in spreads {
            let n = flattest_direction(&a, 0.5).unwrap();
            let eigen = nalgebra::SymmetricEigen::new(a);
            let i = eigen.eigenvalues.imin();
            let expected = eigen.eigenvectors.column(i);
            assert!((n.dot(&expected).abs() - 1.0).abs() < 1e-9, "{a}");
        }
        // A line (two small spreads) and a blob (three equal) have no normal.
        let line = Matrix3::new(4.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.1);
        assert!(flattest_direction(&line, 0.3).is_none());
        assert!(flattest_direction(&Matrix3::identity(), 0.3).is_none());
    }
}
