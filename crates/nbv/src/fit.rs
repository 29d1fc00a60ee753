//! Fitted fruit shape: a rotated superellipsoid (or, on request, an axis-aligned ellipsoid)
//! fitted to an ROI cluster, kept out of the free space the camera has observed, so that the
//! volume of a half-seen fruit is not halved.
//!
//! [`fit_ellipsoid`] works in these steps:
//!
//! 1. **Start**: an algebraic least-squares sphere through the cluster's voxel centres (the ROI
//!    voxels are where rays ended, so they lie on the seen part of the fruit's surface); the
//!    cluster's box when that sphere is degenerate.
//! 2. **Axis-aligned fit**: Levenberg-Marquardt over centre and log semi-axes minimising, in
//!    voxels,
//!    - the radial distance of every cluster voxel centre from the ellipsoid surface,
//!    - a hinge penalty for every voxel the map knows to be free whose centre lies deeper than
//!      [`FitConfig::free_margin_voxels`] inside the ellipsoid (free space the camera saw through),
//!    - a roundness prior (log semi-axes pulled towards their mean), which decides the depth of a
//!      fruit seen from one side only, where the surface alone leaves it open; it is weakened as
//!      the cluster covers more directions around the centre, so a fruit seen all round keeps its
//!      own proportions;
//!    - a size prior of the same weight ([`SizePrior`]: the mean semi-axis pulled towards the
//!      crop's typical one), which decides how far a cap seen from one side closes.
//! 3. **Superellipsoid** ([`ShapeModel::Superellipsoid`], the default; `solid`, `refine`): the
//!    same residuals on a rotated, tapered superellipsoid ([`Superellipsoid`]: orientation, the
//!    two shape exponents within [`FitConfig::exponent_range`] and the taper within
//!    [`FitConfig::max_taper`] free), with priors of the roundness prior's weight (a round
//!    cross-section, exponents near 1, no taper, body z near vertical). It starts from a few
//!    steps of the axis-aligned fit and from the cluster's principal axes (tilted fruit); the
//!    start ahead after a few steps goes on, with the free-space penalty made strict, so that
//!    the solver rather than step 4 clears free space (shortening a tapered fruit at its tip, not
//!    at both ends). Capsicums are blocky (exponents below 1), tapered, tilted up to 30° and
//!    lobed; an axis-aligned ellipsoid fits none of that. The result must also fit within
//!    [`FitConfig::max_superellipsoid_rms_voxels`] and stay no more than twice the cluster's
//!    size. A solid that fails only the RMS check is fitted once more, to the voxels within
//!    [`FitConfig::outlier_band_voxels`] of its surface, when they are at least
//!    [`FitConfig::min_inlier_share`] of the cluster: a leaf tip, a stalk or a clip touching
//!    the fruit, or the shell a pose error smears around it, no longer turns the estimate into
//!    the cluster's box.
//! 4. **Free-space check**: while free voxels remain inside the shape, the semi-axis along which
//!    they lie is shrunk (by 5 % for the ellipsoid, 1 % for the superellipsoid, whose solver
//!    left them within a voxel of the surface).
//! 5. **Confidence**: the share of points spread over the fitted surface whose voxel the map
//!    knows (free or occupied, not unknown). Voxels are coarse next to a fruit (1 cm against
//!    3-4.5 cm semi-axes): rays passing the silhouette make a band of the hidden side known, so a
//!    fruit seen from one side scores about 0.7-0.8 rather than 0.5; all sides seen scores ~1.
//!
//! A fit that is degenerate (too few voxels, non-finite, semi-axes outside
//! `[resolution / 2, max_semi_axis_m]`, centre far from the cluster, or a poor surface fit) falls
//! back: a failed superellipsoid to the axis-aligned ellipsoid; a failed ellipsoid to the
//! superellipsoid fitted to the part of the cluster around its best-supported fruit-sized
//! sphere ([`FitConfig::best_part`], a fruit grown together with red leaves); and when that
//! fails too, to the cluster's box (the ellipsoid inscribed in it, [`SolidKind::Box`]).
//!
//! Ground truth comes as boxes, so the fitted estimate is compared to the truth through the
//! world-axis box around the fitted solid ([`FruitSolid::box_volume_m3`]).

mod consensus;
mod refine;
#[cfg(test)]
mod shape_tests;
mod solid;

use glasshouse_roimap::{Occupancy, RoiCluster, RoiMap, VoxelKey};
use nalgebra::{Matrix6, Point3, UnitQuaternion, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use crate::evidence::EvidenceConfig;
pub use glasshouse_geom::{FruitSolid, SolidKind};

use crate::superellipsoid::Superellipsoid;

/// Which solid [`fit_ellipsoid`] fits.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ShapeModel {
    /// An ellipsoid with its axes along world x, y, z.
    AxisAlignedEllipsoid,
    /// A rotated superellipsoid ([`Superellipsoid`]).
    #[default]
    Superellipsoid,
}

/// Parameters of [`fit_ellipsoid`]. [`Default`] suits the simulator's 5-9 cm fruits at 1 cm.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FitConfig {
    /// The solid fitted.
    pub model: ShapeModel,
    /// Range of both superellipsoid exponents. Below ~0.4 the corners of a fruit-sized shape
    /// are sharper than a 1 cm voxel can show, so the data cannot tell them apart, and blocky
    /// capsicums sit at 0.5-0.8; above 1.5 the shape grows points that fruit do not have (2 is
    /// an octahedron).
    pub exponent_range: [f64; 2],
    /// Largest taper of the superellipsoid: a capsicum's tip is about half as wide as its
    /// shoulders (0.35); 0 switches tapering off.
    pub max_taper: f64,
    /// Largest accepted RMS surface distance of the superellipsoid, in voxels: it bends to more
    /// shapes than the ellipsoid, two touching fruits included (~1.3 voxels, where a lobed
    /// capsicum fits within 0.7), so a poor fit is caught earlier.
    pub max_superellipsoid_rms_voxels: f64,
    /// Clusters with fewer voxels are not fitted (box fallback).
    pub min_voxels: usize,
    /// Largest accepted semi-axis.
    pub max_semi_axis_m: f64,
    /// Free voxels up to this deep inside the surface (in voxels) are tolerated: surface voxels
    /// grazed by rays can be free, and a stereo camera's depth noise and flying pixels at the
    /// silhouette carve free voxels up to about a voxel into a fruit. At 0.75 the fits under
    /// `--world realistic` were a fifth too small (median fitted/true volume 0.83, tuning seeds
    /// 101-108), at 1.5 they are not (0.98).
    pub free_margin_voxels: f64,
    /// Weight of the free-space penalty relative to one surface voxel.
    pub free_weight: f64,
    /// Weight of the roundness prior, multiplied by `sqrt(voxels)` and by `2·(1 − coverage)`
    /// clamped to [0.1, 1], where coverage is the share of directions around the centre in which
    /// the cluster has voxels.
    pub roundness_weight: f64,
    /// Free voxels are looked for this far around the cluster's box.
    pub free_search_margin_m: f64,
    /// What a fruit's size is likely to be where the data leave it open.
    pub size_prior: SizePrior,
    /// A superellipsoid that fails the RMS check is fitted again to the voxels within this
    /// many voxels of its surface (a fruit with a leaf tip or a clip touching it, or smeared by
    /// a pose error), ...
    pub outlier_band_voxels: f64,
    /// ... when they are at least this share of the cluster.
    pub min_inlier_share: f64,
    /// When no solid fits the whole cluster, fit one to the part around its best-supported
    /// fruit-sized sphere before falling back to the box (a fruit grown together with red
    /// leaves; [`consensus`]).
    pub best_part: bool,
    /// Largest accepted RMS surface distance, in voxels.
    pub max_rms_voxels: f64,
    /// Clusters longer than this along some axis, which no single ellipsoid fits, are tried as
    /// two touching fruits ([`crate::split::split_touching`]).
    pub split_extent_m: f64,
    /// Points spread over the surface for the confidence.
    pub surface_samples: usize,
    /// The fitted solid is shrunk by this times `voxel² / R` on every semi-axis (`R` the
    /// geometric mean of its semi-axes): the voxels a convex surface passes through have their
    /// centres outside it on average (more of a shell around a convex surface lies outside it
    /// than inside; for cubes of side `v` about `2·E[h²] / (3R) ≈ 0.38·v² / R`, `h` a cube's
    /// half-width along the normal), so a solid through them is too large, the more so the
    /// smaller the fruit: 1.1 mm on a 7 cm fruit in 1 cm voxels. 0: the solid through the
    /// voxel centres.
    pub voxel_bias_factor: f64,
    pub max_iterations: usize,
    /// Which clusters are reported as fruit ([`crate::evidence`]).
    pub evidence: EvidenceConfig,
}

impl Default for FitConfig {
    fn default() -> Self {
        Self {
            model: ShapeModel::default(),
            exponent_range: [0.4, 1.5],
            max_taper: 0.6,
            max_superellipsoid_rms_voxels: 1.0,
            min_voxels: 10,
            max_semi_axis_m: 0.15,
            free_margin_voxels: 1.5,
            free_weight: 1.0,
            roundness_weight: 3.0,
            free_search_margin_m: 0.06,
            size_prior: SizePrior::default(),
            outlier_band_voxels: 1.5,
            min_inlier_share: 0.4,
            best_part: true,
            max_rms_voxels: 1.5,
            split_extent_m: 0.11,
            surface_samples: 256,
            voxel_bias_factor: 0.3,
            max_iterations: 60,
            evidence: EvidenceConfig::default(),
        }
    }
}

/// The crop's typical fruit size, pulling the mean semi-axis of a fit towards it with the
/// roundness prior's coverage-scaled weight (times `weight`). A fruit seen from one side shows
/// a cap of its surface, whose curvature tells its size poorly (a 1 cm voxel blurs it): the
/// fit shrinks onto the cap and loses half its volume. A crop's fruit size is known (capsicum
/// 6-10 cm across), so where the data leave the size open the prior decides it, and where the
/// fruit was seen all round (coverage high, the weight near its floor) the data do.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SizePrior {
    /// Typical semi-axis (geometric mean of the three), metres; 0 switches the prior off.
    pub typical_semi_axis_m: f64,
    /// Weight relative to the roundness prior.
    pub weight: f64,
}

impl Default for SizePrior {
    /// The simulator's capsicum: bodies 5-8 cm across.
    fn default() -> Self {
        Self {
            typical_semi_axis_m: 0.032,
            weight: 1.0,
        }
    }
}

impl SizePrior {
    /// The prior's residual weight at roundness weight `w` and the log of the typical
    /// semi-axis; `None` when off.
    pub(crate) fn weighted(&self, w: f64) -> Option<(f64, f64)> {
        let on = self.typical_semi_axis_m > 0.0 && self.weight > 0.0;
        let ok = self.typical_semi_axis_m.is_finite() && self.weight.is_finite();
        (on && ok).then(|| (w * self.weight, self.typical_semi_axis_m.ln()))
    }
}

/// Parameters: centre (m) and the natural logarithm of the semi-axes (m).
type Params = Vector6<f64>;

fn unpack(p: &Params) -> (Point3<f64>, Vector3<f64>) {
    (
        Point3::new(p[0], p[1], p[2]),
        Vector3::new(p[3].exp(), p[4].exp(), p[5].exp()),
    )
}

/// Normalised radius: 1 on the surface, < 1 inside.
fn rho(q: &Point3<f64>, centre: &Point3<f64>, axes: &Vector3<f64>) -> f64 {
    (q - centre).component_div(axes).norm()
}

/// Geometric mean of the semi-axes: converts normalised radii into metres.
fn mean_axis(axes: &Vector3<f64>) -> f64 {
    (axes.x * axes.y * axes.z).cbrt()
}

struct Problem<'a> {
    /// Weight of each roundness residual.
    prior_weight: f64,
    surface: &'a [Point3<f64>],
    free: &'a [Point3<f64>],
    resolution_m: f64,
    config: &'a FitConfig,
}

impl Problem<'_> {
    fn residuals(&self, p: &Params, out: &mut Vec<f64>) {
        out.clear();
        let (centre, axes) = unpack(p);
        let scale = mean_axis(&axes) / self.resolution_m;
        for q in self.surface {
            out.push((rho(q, &centre, &axes) - 1.0) * scale);
        }
        for f in self.free {
            let depth_voxels = (1.0 - rho(f, &centre, &axes)) * scale;
            out.push(
                self.config.free_weight * (depth_voxels - self.config.free_margin_voxels).max(0.0),
            );
        }
        let w = self.prior_weight;
        let mean_log = (p[3] + p[4] + p[5]) / 3.0;
        for i in 3..6 {
            out.push(w * (p[i] - mean_log));
        }
        if let Some((ws, typical_ln)) = self.config.size_prior.weighted(w) {
            out.push(ws * (mean_log - typical_ln));
        }
    }

    fn cost(&self, p: &Params, scratch: &mut Vec<f64>) -> f64 {
        self.residuals(p, scratch);
        scratch.iter().map(|r| r * r).sum()
    }

    /// Levenberg-Marquardt with central-difference Jacobians, at most `iterations` steps.
    fn solve(&self, start: Params, iterations: usize) -> Params {
        let mut p = start;
        let mut r0 = Vec::new();
        let mut plus = Vec::new();
        let mut minus = Vec::new();
        let mut scratch = Vec::new();
        let mut cost = self.cost(&p, &mut scratch);
        let mut lambda = 1e-3;
        for _ in 0..iterations {
            self.residuals(&p, &mut r0);
            let mut jtj = Matrix6::<f64>::zeros();
            let mut jtr = Vector6::<f64>::zeros();
            let mut columns: Vec<Vec<f64>> = Vec::with_capacity(6);
            for j in 0..6 {
                let h = if j < 3 { 1e-5 } else { 1e-4 };
                let mut pp = p;
                pp[j] += h;
                self.residuals(&pp, &mut plus);
                let mut pm = p;
                pm[j] -= h;
                self.residuals(&pm, &mut minus);
                columns.push(
                    plus.iter()
                        .zip(&minus)
                        .map(|(a, b)| (a - b) / (2.0 * h))
                        .collect(),
                );
            }
            for a in 0..6 {
                jtr[a] = columns[a].iter().zip(&r0).map(|(j, r)| j * r).sum();
                for b in a..6 {
                    let v: f64 = columns[a].iter().zip(&columns[b]).map(|(x, y)| x * y).sum();
                    jtj[(a, b)] = v;
                    jtj[(b, a)] = v;
                }
            }
            let mut improved = false;
            for _ in 0..10 {
                let mut damped = jtj;
                for d in 0..6 {
                    damped[(d, d)] += lambda * jtj[(d, d)].max(1e-9);
                }
                let Some(step) = damped.lu().solve(&(-jtr)) else {
                    lambda *= 10.0;
                    continue;
                };
                let candidate = p + step;
                let c = self.cost(&candidate, &mut scratch);
                if c.is_finite() && c < cost {
                    let relative = (cost - c) / cost.max(1e-300);
                    p = candidate;
                    cost = c;
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = relative > 1e-10;
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        p
    }
}

/// Least-squares sphere `|x|² + D·x + G = 0` through the points; `None` when degenerate.
fn algebraic_sphere(points: &[Point3<f64>]) -> Option<(Point3<f64>, f64)> {
    let n = points.len() as f64;
    let mean = points.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    // Centred and scaled to ~1 for conditioning.
    let scale = 0.05;
    let mut ata = nalgebra::Matrix4::<f64>::zeros();
    let mut atb = nalgebra::Vector4::<f64>::zeros();
    for p in points {
        let q = (p.coords - mean) / scale;
        let row = nalgebra::Vector4::new(q.x, q.y, q.z, 1.0);
        ata += row * row.transpose();
        atb += row * (-q.norm_squared());
    }
    let sol = ata.lu().solve(&atb)?;
    let c = Vector3::new(-sol[0] / 2.0, -sol[1] / 2.0, -sol[2] / 2.0);
    let r2 = c.norm_squared() - sol[3];
    if !(r2.is_finite() && r2 > 0.0) {
        return None;
    }
    Some((Point3::from(mean + c * scale), r2.sqrt() * scale))
}

/// Share of 32 evenly spread directions from `centre` that some point lies nearest to: about 0.5
/// for a fruit seen from one side, 1 for one seen all round.
fn angular_coverage(points: &[Point3<f64>], centre: &Point3<f64>) -> f64 {
    const BINS: usize = 32;
    let directions: Vec<Vector3<f64>> = fibonacci_sphere(BINS).collect();
    let mut hit = [false; BINS];
    for p in points {
        let Some(d) = (p - centre).try_normalize(1e-12) else {
            continue;
        };
        let nearest = directions
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.dot(&d).total_cmp(&b.1.dot(&d)))
            .map(|(i, _)| i);
        if let Some(i) = nearest {
            hit[i] = true;
        }
    }
    hit.iter().filter(|h| **h).count() as f64 / BINS as f64
}

/// `n` points spread evenly over the unit sphere (Fibonacci lattice).
fn fibonacci_sphere(n: usize) -> impl Iterator<Item = Vector3<f64>> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n).map(move |i| {
        let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
        let r = (1.0 - z * z).max(0.0).sqrt();
        let phi = golden * i as f64;
        Vector3::new(r * phi.cos(), r * phi.sin(), z)
    })
}

/// Share of surface points whose voxel is known.
fn observed_share(map: &RoiMap, centre: &Point3<f64>, axes: &Vector3<f64>, samples: usize) -> f64 {
    if samples == 0 {
        return 0.0;
    }
    let known = fibonacci_sphere(samples)
        .filter(|u| {
            let p = centre + axes.component_mul(u);
            map.try_key_of(&p)
                .is_some_and(|k| map.observed_occupancy(k) != Occupancy::Unknown)
        })
        .count();
    known as f64 / samples as f64
}

/// Centres of the voxels this visit saw free ([`RoiMap::observed_occupancy`]) in the box
/// `[lo, hi]` (world coordinates).
fn free_voxels_in(map: &RoiMap, lo: &Point3<f64>, hi: &Point3<f64>) -> Vec<Point3<f64>> {
    let (Some(a), Some(b)) = (map.try_key_of(lo), map.try_key_of(hi)) else {
        return Vec::new();
    };
    // A fruit-sized box; bound the walk anyway so absurd input cannot stall.
    let span = |a: i32, b: i32| i64::from(b) - i64::from(a) + 1;
    if span(a.x, b.x) * span(a.y, b.y) * span(a.z, b.z) > 2_000_000 {
        return Vec::new();
    }
    let mut out = Vec::new();
    for x in a.x..=b.x {
        for y in a.y..=b.y {
            for z in a.z..=b.z {
                let k = VoxelKey::new(x, y, z);
                if map.observed_occupancy(k) == Occupancy::Free {
                    out.push(map.centre_of(k));
                }
            }
        }
    }
    out
}

/// Semi-axes shrunk by the voxel centres' outward bias, `factor · voxel² / R`
/// ([`FitConfig::voxel_bias_factor`]), by at most a quarter of the shortest.
pub fn unbiased_semi_axes(semi_axes_m: &Vector3<f64>, voxel_m: f64, factor: f64) -> Vector3<f64> {
    let radius_m = (semi_axes_m.x * semi_axes_m.y * semi_axes_m.z).cbrt();
    let bias_m = factor * voxel_m * voxel_m / radius_m;
    if !(bias_m.is_finite() && bias_m > 0.0) {
        return *semi_axes_m;
    }
    let bias_m = bias_m.min(0.25 * semi_axes_m.min());
    semi_axes_m.map(|a| a - bias_m)
}

fn shape(
    kind: SolidKind,
    centre: Point3<f64>,
    axes: Vector3<f64>,
    confidence: f64,
    rms_residual_m: f64,
) -> FruitSolid {
    let product = axes.x * axes.y * axes.z;
    FruitSolid {
        kind,
        centre,
        semi_axes_m: axes,
        world_from_body: UnitQuaternion::identity(),
        exponents: [1.0, 1.0],
        taper: 0.0,
        volume_m3: 4.0 / 3.0 * std::f64::consts::PI * product,
        box_min: centre - axes,
        box_max: centre + axes,
        box_volume_m3: 8.0 * product,
        confidence,
        rms_residual_m,
    }
}

/// The box fallback: the ellipsoid inscribed in the cluster's box.
pub fn box_shape(map: &RoiMap, cluster: &RoiCluster, config: &FitConfig) -> FruitSolid {
    let centre = Point3::from((cluster.min.coords + cluster.max.coords) / 2.0);
    let axes = ((cluster.max - cluster.min) / 2.0).map(|v| v.max(0.0));
    let confidence = observed_share(map, &centre, &axes, config.surface_samples);
    shape(SolidKind::Box, centre, axes, confidence, f64::NAN)
}

/// The box (min, max corners) holding every voxel [`fit_ellipsoid`] read to fit `shape` to
/// `cluster`: the free-voxel search box around the cluster and the fitted surface's box (its
/// observed share), padded by two voxels for rounding to keys. While no voxel in it changes, the
/// fit comes out the same.
pub fn fit_read_box(
    map: &RoiMap,
    cluster: &RoiCluster,
    shape: &FruitSolid,
    config: &FitConfig,
) -> (Point3<f64>, Point3<f64>) {
    let pad = Vector3::repeat(config.free_search_margin_m.max(0.0));
    let slack = Vector3::repeat(2.0 * map.config().resolution_m);
    let min = (cluster.min - pad).inf(&shape.box_min) - slack;
    let max = (cluster.max + pad).sup(&shape.box_max) + slack;
    (min, max)
}

/// What every fit of one cluster reads: its voxel centres, the free voxels around it, and the
/// start and prior weight of the axis-aligned fit.
struct FitData {
    resolution_m: f64,
    surface: Vec<Point3<f64>>,
    /// Free voxels within the search margin of the cluster's box.
    free_around: Vec<Point3<f64>>,
    /// Those of them near the start (the only ones that can constrain the fit).
    free_near: Vec<Point3<f64>>,
    box_centre: Point3<f64>,
    box_half: Vector3<f64>,
    start_centre: Point3<f64>,
    start_axes: Vector3<f64>,
    prior_weight: f64,
}

impl FitData {
    /// `None` when the cluster is too small to fit.
    fn gather(map: &RoiMap, cluster: &RoiCluster, config: &FitConfig) -> Option<Self> {
        if cluster.voxels.len() < config.min_voxels.max(4) {
            return None;
        }
        let surface: Vec<Point3<f64>> = cluster.voxels.iter().map(|k| map.centre_of(*k)).collect();
        let margin = Vector3::repeat(config.free_search_margin_m.max(0.0));
        let free_around = free_voxels_in(map, &(cluster.min - margin), &(cluster.max + margin));
        let bounds = (cluster.min, cluster.max);
        Some(Self::of_surface(
            map.config().resolution_m,
            surface,
            bounds,
            free_around,
            config,
        ))
    }

    /// The fit's data for the voxel centres `surface` within `bounds` (min, max corners).
    fn of_surface(
        res: f64,
        surface: Vec<Point3<f64>>,
        (min, max): (Point3<f64>, Point3<f64>),
        free_around: Vec<Point3<f64>>,
        config: &FitConfig,
    ) -> Self {
        let box_centre = Point3::from((min.coords + max.coords) / 2.0);
        let box_half = ((max - min) / 2.0).map(|v| v.max(res));
        let sphere_ok = |r: f64| r.is_finite() && r >= 0.5 * res && r <= config.max_semi_axis_m;
        let (start_centre, start_axes) = match algebraic_sphere(&surface) {
            Some((c, r)) if sphere_ok(r) && (c - box_centre).norm() < 2.0 * r => {
                (c, Vector3::repeat(r))
            }
            _ => (box_centre, box_half),
        };
        let reach = start_axes.map(|a| a * 1.5 + 2.0 * res);
        let free_near = free_around
            .iter()
            .filter(|f| rho(f, &start_centre, &reach) < 1.0)
            .copied()
            .collect();
        // The prior matters where the surface leaves the shape open (a fruit seen from one
        // side) and should not bend a fruit seen all round: scale it by the directions not
        // covered.
        let coverage = angular_coverage(&surface, &start_centre);
        let prior_weight = config.roundness_weight
            * (surface.len() as f64).sqrt()
            * (2.0 * (1.0 - coverage)).clamp(0.1, 1.0);
        Self {
            resolution_m: res,
            surface,
            free_around,
            free_near,
            box_centre,
            box_half,
            start_centre,
            start_axes,
            prior_weight,
        }
    }

    /// The data without the voxels farther than the outlier band from `poor`, a solid that
    /// fitted all of them badly: what a fruit's fit loses to a leaf tip, a stalk or a clip
    /// touching it, or to the shell a pose error smears around it. `None` when too few are
    /// left ([`FitConfig::min_inlier_share`]): then the cluster is not one solid.
    fn trimmed(&self, poor: &Superellipsoid, config: &FitConfig) -> Option<Self> {
        let band_m = config.outlier_band_voxels * self.resolution_m;
        let kept: Vec<Point3<f64>> = self
            .surface
            .iter()
            .filter(|q| poor.radial_distance_m(q).abs() <= band_m)
            .copied()
            .collect();
        let enough = (config.min_inlier_share * self.surface.len() as f64).ceil() as usize;
        if kept.len() < enough.max(config.min_voxels.max(4)) || kept.len() == self.surface.len() {
            return None;
        }
        let half_voxel = Vector3::repeat(self.resolution_m / 2.0);
        let lo = kept.iter().fold(kept[0], |m, p| m.inf(p)) - half_voxel;
        let hi = kept.iter().fold(kept[0], |m, p| m.sup(p)) + half_voxel;
        let free = self.free_around.clone();
        Some(Self::of_surface(
            self.resolution_m,
            kept,
            (lo, hi),
            free,
            config,
        ))
    }

    fn axis_ok(&self, axes: &Vector3<f64>, config: &FitConfig) -> bool {
        axes.iter()
            .all(|v| v.is_finite() && *v >= 0.5 * self.resolution_m && *v <= config.max_semi_axis_m)
    }

    /// No semi-axis of a superellipsoid fitted to this cluster may be more than twice the
    /// cluster's largest half-extent: a flat patch is part of the surface of a huge solid, but
    /// no fruit (a fruit seen end-on is at most about twice as long as it is wide).
    fn size_near(&self, axes: &Vector3<f64>) -> bool {
        axes.max() <= 2.0 * self.box_half.max() + self.resolution_m
    }

    /// The fitted solid must stay near the data it was fitted to.
    fn centre_near(&self, centre: &Point3<f64>, config: &FitConfig) -> bool {
        (centre - self.box_centre)
            .iter()
            .zip(self.box_half.iter())
            .all(|(d, h)| d.abs() <= h + config.max_semi_axis_m)
    }

    /// The axis-aligned Levenberg-Marquardt solution after at most `iterations` steps: centre
    /// and semi-axes.
    fn solve_axis_aligned(
        &self,
        config: &FitConfig,
        iterations: usize,
    ) -> (Point3<f64>, Vector3<f64>) {
        let problem = Problem {
            prior_weight: self.prior_weight,
            surface: &self.surface,
            free: &self.free_near,
            resolution_m: self.resolution_m,
            config,
        };
        let (c, a) = (self.start_centre, self.start_axes);
        let start = Params::new(c.x, c.y, c.z, a.x.ln(), a.y.ln(), a.z.ln());
        unpack(&problem.solve(start, iterations))
    }
}

/// Fits the whole-fruit solid of `config.model` to `cluster` (see the module docs). Never
/// panics; degenerate input gives the box fallback.
pub fn fit_ellipsoid(map: &RoiMap, cluster: &RoiCluster, config: &FitConfig) -> FruitSolid {
    let Some(data) = FitData::gather(map, cluster, config) else {
        return box_shape(map, cluster, config);
    };
    if config.model == ShapeModel::Superellipsoid {
        if let Some(fit) = fit_solid_or_inliers(map, &data, config) {
            return fit;
        }
    }
    let (centre, axes) = data.solve_axis_aligned(config, config.max_iterations);
    let fit = finish_axis_aligned(map, cluster, &data, centre, axes, config);
    if fit.kind == SolidKind::Box && config.best_part && config.model == ShapeModel::Superellipsoid
    {
        if let Some(part) = fit_best_part(map, &data, config) {
            return part;
        }
    }
    fit
}

/// The solid fitted to the part of the cluster around its best-supported fruit-sized sphere
/// ([`consensus`]): a fruit grown together with red leaves, which the cluster's box would make
/// many times too large.
fn fit_best_part(map: &RoiMap, data: &FitData, config: &FitConfig) -> Option<FruitSolid> {
    let sphere = consensus::best_sphere(data, config)?;
    let share = FitConfig {
        min_inlier_share: consensus::MIN_SHARE,
        ..*config
    };
    fit_solid_or_inliers(map, &data.trimmed(&sphere, &share)?, config)
}

/// The superellipsoid fitted to `data`, or, when a sound solid fits it poorly, to the voxels
/// near that solid.
fn fit_solid_or_inliers(map: &RoiMap, data: &FitData, config: &FitConfig) -> Option<FruitSolid> {
    match fit_solid(map, data, config) {
        Ok(fit) => Some(fit),
        Err(Some(poor)) => {
            let inliers = data.trimmed(&poor, config)?;
            fit_solid(map, &inliers, config).ok()
        }
        Err(None) => None,
    }
}

/// The superellipsoid of steps 2-5, started from a rough axis-aligned solve.
fn fit_solid(map: &RoiMap, data: &FitData, config: &FitConfig) -> solid::SolidFit {
    let (centre, axes) =
        data.solve_axis_aligned(config, solid::START_ITERATIONS.min(config.max_iterations));
    solid::fit_superellipsoid(map, data, centre, axes, config)
}

/// Steps 4-5 of the module docs for the axis-aligned ellipsoid.
fn finish_axis_aligned(
    map: &RoiMap,
    cluster: &RoiCluster,
    data: &FitData,
    centre: Point3<f64>,
    mut axes: Vector3<f64>,
    config: &FitConfig,
) -> FruitSolid {
    let res = data.resolution_m;
    if !(centre.iter().all(|c| c.is_finite()) && data.axis_ok(&axes, config)) {
        return box_shape(map, cluster, config);
    }
    // Free-space check: shrink the axis along which free voxels sit inside the ellipsoid.
    for _ in 0..40 {
        let lo = centre - axes;
        let hi = centre + axes;
        let scale = mean_axis(&axes) / res;
        let mut push = Vector3::<f64>::zeros();
        let mut offenders = 0usize;
        for f in free_voxels_in(map, &lo, &hi) {
            let r = rho(&f, &centre, &axes);
            if (1.0 - r) * scale > config.free_margin_voxels {
                offenders += 1;
                push += (f - centre).component_div(&axes).map(|v| v * v);
            }
        }
        if offenders == 0 {
            break;
        }
        let axis = push.imax();
        axes[axis] *= 0.95;
        if axes[axis] < 0.5 * res {
            return box_shape(map, cluster, config);
        }
    }
    let scale_m = mean_axis(&axes);
    let rms_m = (data
        .surface
        .iter()
        .map(|q| ((rho(q, &centre, &axes) - 1.0) * scale_m).powi(2))
        .sum::<f64>()
        / data.surface.len() as f64)
        .sqrt();
    if !(rms_m.is_finite()
        && rms_m <= config.max_rms_voxels * res
        && data.centre_near(&centre, config))
    {
        return box_shape(map, cluster, config);
    }
    let confidence = observed_share(map, &centre, &axes, config.surface_samples);
    let axes = unbiased_semi_axes(&axes, res, config.voxel_bias_factor);
    shape(SolidKind::Ellipsoid, centre, axes, confidence, rms_m)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    use super::tests_support::*;

    fn only_cluster(map: &RoiMap) -> RoiCluster {
        let clusters = map.clusters(10);
        assert_eq!(clusters.len(), 1, "{clusters:?}");
        clusters.into_iter().next().unwrap()
    }

    fn sphere_volume(r: f64) -> f64 {
        4.0 / 3.0 * std::f64::consts::PI * r.powi(3)
    }

    /// A fruit with a red leaf tip sticking out of its side, one cluster: fitted to every voxel
    /// the solid bends towards the leaf and fails its RMS check, and the box it falls back to
    /// reports about twice the fruit's volume; fitted again to the voxels near its surface, it
    /// is a solid nearer the fruit (the leaf's base, within the band, still widens it).
    #[test]
    fn a_fruit_with_a_leaf_tip_touching_it_is_fitted_without_the_leaf() {
        let r = 0.035;
        let c = centre();
        let leaf = |o: &Point3<f64>, d: &Vector3<f64>| {
            // An 8 cm strip in the plane y = c.y, from inside the fruit out to the side.
            let t = (c.y - o.y) / d.y;
            let p = o + d * t;
            let along = p.x - c.x;
            (t > 0.0 && (0.5 * r..r + 0.08).contains(&along) && (p.z - c.z).abs() < 0.03)
                .then_some(t)
        };
        let fruit =
            |o: &Point3<f64>, d: &Vector3<f64>| hit_ellipsoid(o, d, &c, &Vector3::repeat(r));
        let mut m = map();
        for eye in [
            Vector3::new(0.0, -1.0, 0.2),
            Vector3::new(0.8, -1.0, 0.3),
            Vector3::new(-0.8, -1.0, 0.1),
        ] {
            scan_with(&mut m, c, c + eye.normalize() * 0.4, |o, d| {
                [fruit(o, d), leaf(o, d)]
                    .into_iter()
                    .flatten()
                    .min_by(f64::total_cmp)
            });
        }
        let cluster = only_cluster(&m);
        let untrimmed = FitConfig {
            min_inlier_share: 1.0,
            best_part: false,
            ..clean_scan_config()
        };
        let whole = fit_ellipsoid(&m, &cluster, &untrimmed);
        let whole_error = (whole.volume_m3 / sphere_volume(r) - 1.0).abs();
        let fit = fit_ellipsoid(&m, &cluster, &clean_scan_config());
        let ratio = fit.volume_m3 / sphere_volume(r);
        assert!(
            whole.kind == SolidKind::Box && whole_error > 0.8,
            "without trimming: {whole:?} ({whole_error:.2} off)"
        );
        assert_eq!(fit.kind, SolidKind::Ellipsoid, "{fit:?}");
        assert!(
            (ratio - 1.0).abs() < 0.6 * whole_error,
            "fitted/true {ratio:.3} against the box's {whole_error:.2} off: {fit:?}"
        );
        assert!((fit.centre - c).norm() < 0.025, "{fit:?}");
    }

    #[test]
    fn half_seen_sphere_keeps_its_volume_while_the_box_halves() {
        for dir in [
            Vector3::x(),
            -Vector3::y(),
            Vector3::new(1.0, 1.0, 0.3).normalize(),
        ] {
            let mut m = map();
            let axes = Vector3::repeat(R);
            scan(&mut m, centre() + dir * 0.4, &axes);
            let cluster = only_cluster(&m);
            let fit = fit_ellipsoid(&m, &cluster, &clean_scan_config());
            assert_eq!(fit.kind, SolidKind::Ellipsoid, "{dir:?}");
            let ratio = fit.volume_m3 / sphere_volume(R);
            assert!(
                (0.8..=1.2).contains(&ratio),
                "{dir:?}: fitted/true {ratio:.3} {fit:?}"
            );
            assert!((fit.centre - centre()).norm() < 0.012, "{dir:?}: {fit:?}");
            let size = cluster.max - cluster.min;
            let box_ratio = size.x * size.y * size.z / (8.0 * R.powi(3));
            let fitted_box_ratio = fit.box_volume_m3 / (8.0 * R.powi(3));
            if dir.iter().filter(|c| c.abs() > 0.5).count() == 1 {
                // Seen along an axis, the cluster's box covers the seen cap only: about half the
                // fruit's depth (0.9 R of 2 R here), but whole voxels on every axis (5 x 9 x 9 of
                // 8 x 8 x 8 voxels), so 0.6-0.8 of the truth's box rather than exactly half.
                assert!(
                    (0.4..=0.85).contains(&box_ratio),
                    "{dir:?}: box/true {box_ratio:.3}"
                );
                assert!(
                    (fitted_box_ratio - 1.0).abs() < (box_ratio - 1.0).abs(),
                    "{dir:?}: fitted box {fitted_box_ratio:.3} vs cluster box {box_ratio:.3}"
                );
            }
            assert!(
                (0.8..=1.2).contains(&fitted_box_ratio),
                "{dir:?}: fitted box/true {fitted_box_ratio:.3}"
            );
            // About half of the surface was observed, plus the silhouette band (module docs).
            assert!(
                (0.4..=0.85).contains(&fit.confidence),
                "{dir:?}: confidence {}",
                fit.confidence
            );
        }
    }

    #[test]
    fn ellipsoid_seen_from_all_sides_is_recovered_with_high_confidence() {
        let axes = Vector3::new(0.03, 0.038, 0.045);
        let mut m = map();
        for dir in [
            Vector3::x(),
            -Vector3::x(),
            Vector3::y(),
            -Vector3::y(),
            Vector3::z(),
            -Vector3::z(),
        ] {
            scan(&mut m, centre() + dir * 0.4, &axes);
        }
        let cluster = only_cluster(&m);
        let fit = fit_ellipsoid(&m, &cluster, &clean_scan_config());
        assert_eq!(fit.kind, SolidKind::Ellipsoid);
        for i in 0..3 {
            let rel = fit.semi_axes_m[i] / axes[i];
            assert!((0.85..=1.15).contains(&rel), "axis {i}: {fit:?}");
        }
        let truth_box = 8.0 * axes.x * axes.y * axes.z;
        let ratio = fit.box_volume_m3 / truth_box;
        assert!((0.8..=1.2).contains(&ratio), "{ratio}");
        assert!(fit.confidence > 0.9, "{}", fit.confidence);
        assert!(fit.rms_residual_m < 0.01);
    }

    #[test]
    fn free_space_limits_the_fit() {
        let axes = Vector3::repeat(R);
        let mut m = map();
        scan(&mut m, centre() + Vector3::x() * 0.4, &axes);
        let cluster = only_cluster(&m);
        let unconstrained = fit_ellipsoid(&m, &cluster, &clean_scan_config());
        // Mark the back half of the sphere (x < centre.x - 1 cm) free, as if the camera had seen
        // through it: the fitted ellipsoid must withdraw from it.
        let c = centre();
        let mut free = Vec::new();
        let k0 = m.key_of(&(c - Vector3::repeat(0.06)));
        let k1 = m.key_of(&(c + Vector3::repeat(0.06)));
        for x in k0.x..=k1.x {
            for y in k0.y..=k1.y {
                for z in k0.z..=k1.z {
                    let k = VoxelKey::new(x, y, z);
                    if m.centre_of(k).x < c.x - 0.01 {
                        free.push((
                            k,
                            glasshouse_roimap::Voxel {
                                occupancy_logodds: -1.0,
                                roi_logodds: 0.0,
                            },
                        ));
                    }
                }
            }
        }
        m.apply_voxels(&free);
        let constrained = fit_ellipsoid(&m, &cluster, &clean_scan_config());
        let deepest_free_x = free
            .iter()
            .map(|(k, _)| m.centre_of(*k).x)
            .fold(f64::NEG_INFINITY, f64::max);
        assert!(
            constrained.box_min.x > unconstrained.box_min.x + 0.01,
            "{unconstrained:?} vs {constrained:?}"
        );
        assert!(
            // One voxel of tolerance beyond the deepest free voxel centre.
            constrained.box_min.x > deepest_free_x - 0.01 - 1e-9,
            "{constrained:?}"
        );
        // No free voxel lies deep inside the result.
        let solid = Superellipsoid::from(&constrained);
        for (k, _) in &free {
            let d = solid.radial_distance_m(&m.centre_of(*k));
            assert!(d >= -0.01 - 1e-9, "{k:?} {d} m deep");
        }
    }

    #[test]
    fn degenerate_clusters_fall_back_to_the_box() {
        let mut m = map();
        // A flat 6x6 sheet of ROI voxels: no ellipsoid fits it.
        let mut sheet = Vec::new();
        for x in 0..6 {
            for y in 0..6 {
                sheet.push((
                    VoxelKey::new(x, y, 100),
                    glasshouse_roimap::Voxel {
                        occupancy_logodds: 2.0,
                        roi_logodds: 2.0,
                    },
                ));
            }
        }
        m.apply_voxels(&sheet);
        let cluster = only_cluster(&m);
        let fit = fit_ellipsoid(&m, &cluster, &clean_scan_config());
        assert_eq!(fit.kind, SolidKind::Box, "{fit:?}");
        assert!((fit.box_min - cluster.min).norm() < 1e-12);
        assert!((fit.box_max - cluster.max).norm() < 1e-12);
        // Too few voxels: box too.
        let small = RoiCluster {
            voxels: cluster.voxels[..3].to_vec(),
            ..cluster.clone()
        };
        assert_eq!(
            fit_ellipsoid(&m, &small, &clean_scan_config()).kind,
            SolidKind::Box
        );
    }

    /// Half-seen spheres of 3 and 4 cm at four voxel phases from four directions: the fitted
    /// volume stays within 20 % in nearly all cases (quantisation of a 3-voxel radius makes the
    /// rest), the median within 5 %.
    #[test]
    fn half_seen_spheres_across_voxel_phases() {
        let config = clean_scan_config();
        let mut ratios = Vec::new();
        for off in [0.0, 0.003, 0.005, 0.007] {
            let c = Point3::new(0.2 + off, -0.1 - off * 1.3, 1.0 + off * 0.7);
            for dir in [
                Vector3::x(),
                -Vector3::y(),
                Vector3::new(1.0, 1.0, 0.3).normalize(),
                Vector3::new(-0.3, 1.0, -0.5).normalize(),
            ] {
                for r in [0.03, 0.04] {
                    let mut m = map();
                    scan_at(&mut m, c, c + dir * 0.4, &Vector3::repeat(r));
                    let fit = fit_ellipsoid(&m, &only_cluster(&m), &config);
                    assert_eq!(fit.kind, SolidKind::Ellipsoid);
                    ratios.push(fit.volume_m3 / sphere_volume(r));
                }
            }
        }
        let within = ratios.iter().filter(|r| (**r - 1.0).abs() <= 0.2).count();
        assert!(within >= 30, "{within} of 32 within 20 %: {ratios:?}");
        assert!(
            ratios.iter().all(|r| (0.75..=1.3).contains(r)),
            "{ratios:?}"
        );
        let mut sorted = ratios.clone();
        sorted.sort_by(f64::total_cmp);
        let median = (sorted[15] + sorted[16]) / 2.0;
        assert!((median - 1.0).abs() < 0.05, "median {median}");
    }

    #[test]
    fn algebraic_sphere_recovers_exact_points() {
        let c = Point3::new(0.1, 0.2, 0.3);
        let pts: Vec<Point3<f64>> = fibonacci_sphere(50)
            .filter(|u| u.x > 0.0)
            .map(|u| c + u * 0.035)
            .collect();
        let (fc, r) = algebraic_sphere(&pts).unwrap();
        assert!((fc - c).norm() < 1e-9);
        assert!((r - 0.035).abs() < 1e-9);
        assert!(algebraic_sphere(&[Point3::origin(); 5]).is_none());
    }
}

#[cfg(test)]
pub(crate) mod tests_support {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use glasshouse_roimap::MapConfig;

    pub const R: f64 = 0.04;

    pub fn centre() -> Point3<f64> {
        Point3::new(0.203, -0.107, 1.005)
    }

    /// First hit of the ray `o + t·d` (unit `d`) on the ellipsoid, if any.
    pub fn hit_ellipsoid(
        o: &Point3<f64>,
        d: &Vector3<f64>,
        c: &Point3<f64>,
        axes: &Vector3<f64>,
    ) -> Option<f64> {
        let oc = (o - c).component_div(axes);
        let dd = d.component_div(axes);
        let a = dd.norm_squared();
        let b = 2.0 * oc.dot(&dd);
        let cc = oc.norm_squared() - 1.0;
        let disc = b * b - 4.0 * a * cc;
        if disc < 0.0 {
            return None;
        }
        let t = (-b - disc.sqrt()) / (2.0 * a);
        (t > 0.0).then_some(t)
    }

    /// Scans an ellipsoid (ROI) from `eye` with a fan of rays; rays that miss end on a
    /// background 0.3 m behind it (not ROI). Each scan is inserted twice (two ROI observations).
    pub fn scan(map: &mut RoiMap, eye: Point3<f64>, axes: &Vector3<f64>) {
        scan_at(map, centre(), eye, axes)
    }

    pub fn scan_at(map: &mut RoiMap, c: Point3<f64>, eye: Point3<f64>, axes: &Vector3<f64>) {
        scan_all(map, &[(c, *axes)], eye)
    }

    /// [`scan_at`] of several ellipsoids at once, each ray ending on the nearest it hits; aims
    /// at the first.
    pub fn scan_all(map: &mut RoiMap, fruits: &[(Point3<f64>, Vector3<f64>)], eye: Point3<f64>) {
        scan_with(map, fruits[0].0, eye, |o, d| {
            fruits
                .iter()
                .filter_map(|(c, axes)| hit_ellipsoid(o, d, c, axes))
                .min_by(f64::total_cmp)
        });
    }

    /// Scans whatever `hit` (first ray parameter of the ray `o + t·d`, unit `d`) describes as
    /// ROI from `eye`, aiming at `aim`: a 120 × 120 fan over ±0.25 rad; rays that miss end on a
    /// background 0.3 m behind `aim` (not ROI). Inserted twice (two ROI observations). Returns
    /// the ROI points.
    pub fn scan_with(
        map: &mut RoiMap,
        aim: Point3<f64>,
        eye: Point3<f64>,
        hit: impl Fn(&Point3<f64>, &Vector3<f64>) -> Option<f64>,
    ) -> Vec<Point3<f64>> {
        scan_labelled(map, aim, eye, hit, |_| true)
    }

    /// [`scan_with`], each hit labelled ROI only where `labelled` says so of its point (a
    /// fruit the detector sees in part); returns the ROI points.
    pub fn scan_labelled(
        map: &mut RoiMap,
        aim: Point3<f64>,
        eye: Point3<f64>,
        hit: impl Fn(&Point3<f64>, &Vector3<f64>) -> Option<f64>,
        labelled: impl Fn(&Point3<f64>) -> bool,
    ) -> Vec<Point3<f64>> {
        let forward = (aim - eye).normalize();
        let helper = if forward.z.abs() < 0.9 {
            Vector3::z()
        } else {
            Vector3::x()
        };
        let right = forward.cross(&helper).normalize();
        let up = right.cross(&forward);
        let distance = (aim - eye).norm();
        let mut points = Vec::new();
        let mut roi = Vec::new();
        let steps = 120;
        let half_angle = 0.25f64;
        for i in 0..steps {
            for j in 0..steps {
                let u = half_angle * (2.0 * (i as f64 + 0.5) / steps as f64 - 1.0);
                let v = half_angle * (2.0 * (j as f64 + 0.5) / steps as f64 - 1.0);
                let d = (forward + right * u.tan() + up * v.tan()).normalize();
                match hit(&eye, &d) {
                    Some(t) => {
                        points.push((eye + d * t).cast::<f32>());
                        roi.push(labelled(&(eye + d * t)));
                    }
                    None => {
                        points.push((eye + d * (distance + 0.3)).cast::<f32>());
                        roi.push(false);
                    }
                }
            }
        }
        for _ in 0..2 {
            map.insert_scan(&eye, &points, &roi).unwrap();
        }
        let hits = points.iter().zip(&roi).filter(|(_, r)| **r);
        hits.map(|(p, _)| p.cast::<f64>()).collect()
    }

    pub fn map() -> RoiMap {
        RoiMap::new(MapConfig::default()).unwrap()
    }

    /// The fit for the exact scans of these tests: no size prior (their fruits are whatever
    /// size the test needs) and the free margin of a noiseless camera.
    pub fn clean_scan_config() -> FitConfig {
        FitConfig {
            size_prior: SizePrior {
                typical_semi_axis_m: 0.0,
                ..SizePrior::default()
            },
            free_margin_voxels: 0.75,
            ..FitConfig::default()
        }
    }
}
