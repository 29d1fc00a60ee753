//! The superellipsoid path of [`super::fit_ellipsoid`] (step 3 of the module docs, and steps
//! 4-5 for it): starts, solves ([`super::refine`]), the canonical orientation and the checks.

use glasshouse_roimap::{Occupancy, RoiMap};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

use super::{fibonacci_sphere, refine, unbiased_semi_axes, FitConfig, FitData, FruitSolid};
use crate::evidence::principal_axes;
use crate::superellipsoid::Superellipsoid;

/// The principal-axes start: the cluster's principal axes, the one nearest world z as body z
/// (fruit hang within ~30° of vertical), the aligned fit's extent along each.
pub(super) fn principal_start(
    data: &FitData,
    centre: Point3<f64>,
    axes: Vector3<f64>,
) -> Option<Superellipsoid> {
    let pca = principal_axes(&data.surface)?;
    let columns: Vec<Vector3<f64>> = (0..3).map(|i| pca.axes.column(i).into_owned()).collect();
    let up = (0..3).max_by(|&i, &j| columns[i].z.abs().total_cmp(&columns[j].z.abs()))?;
    let z = columns[up] * columns[up].z.signum();
    let x = (0..3)
        .filter(|&i| i != up)
        .map(|i| columns[i])
        .max_by(|a, b| a.x.abs().total_cmp(&b.x.abs()))?;
    let x = x * if x.x < 0.0 { -1.0 } else { 1.0 };
    let basis = Matrix3::from_columns(&[x, z.cross(&x), z]);
    let world_from_body = Rotation3::from_matrix_unchecked(basis);
    // The extent of the axis-aligned ellipsoid along each body axis.
    let semi_axes_m = Vector3::from_fn(|k, _| basis.column(k).component_mul(&axes).norm());
    Some(Superellipsoid {
        centre,
        world_from_body,
        semi_axes_m,
        exponents: [1.0, 1.0],
        taper: 0.0,
    })
}

/// Starts of the superellipsoid turned less than this from each other are one start.
const SAME_START_RAD: f64 = 0.17;
/// Steps each start of the superellipsoid gets before the better one is carried on.
pub(super) const START_ITERATIONS: usize = 4;
/// Free-space weight of the superellipsoid's second solve, relative to the first.
const STRICT_FREE_WEIGHT: f64 = 100.0;

/// A fitted solid, or why not: `Err(Some(solid))` for a sound solid that fits its data poorly,
/// `Err(None)` for a degenerate one.
pub(super) type SolidFit = Result<FruitSolid, Option<Box<Superellipsoid>>>;

/// Step 3 of the module docs and its checks. `Err(Some(solid))` when the solid is sound but
/// fits the data poorly (the RMS check), `Err(None)` when the fit is degenerate.
pub(super) fn fit_superellipsoid(
    map: &RoiMap,
    data: &FitData,
    centre: Point3<f64>,
    axes: Vector3<f64>,
    config: &FitConfig,
) -> SolidFit {
    if !(centre.iter().all(|c| c.is_finite()) && axes.iter().all(|a| a.is_finite() && *a > 0.0)) {
        return Err(None);
    }
    let [lo, hi] = config.exponent_range;
    // 1 (the start) inside, and below 2, where the derivatives at the axis planes stay finite.
    if !(lo > 0.0 && lo <= 1.0 && (1.0..2.0).contains(&hi)) {
        return Err(None);
    }
    let problem = refine::Refine {
        surface: &data.surface,
        free: &data.free_near,
        resolution_m: data.resolution_m,
        prior_weight: data.prior_weight,
        size_prior: config.size_prior,
        free_weight: config.free_weight,
        free_margin_voxels: config.free_margin_voxels,
        exponent_range: config.exponent_range,
        max_taper: config.max_taper.clamp(0.0, 0.9),
    };
    let aligned = Superellipsoid {
        world_from_body: Rotation3::identity(),
        semi_axes_m: axes,
        ..Superellipsoid::sphere(centre, 1.0)
    };
    // Both starts get a few steps; the one ahead goes on. A principal start within a few
    // degrees of the axis-aligned one would only repeat it.
    let principal = principal_start(data, centre, axes)
        .filter(|p| canonical(*p).world_from_body.angle() > SAME_START_RAD);
    let starts = [Some(aligned), principal];
    let (ahead, _) = starts
        .into_iter()
        .flatten()
        .map(|start| problem.solve(start, START_ITERATIONS))
        .filter(|(_, cost)| cost.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .ok_or(None)?;
    // Free space the solid still holds is cleared by the solver itself, where it can move,
    // turn, taper or shorten the solid at the right end, rather than by the symmetric shrink
    // of step 4 alone.
    let strict = refine::Refine {
        free_weight: config.free_weight * STRICT_FREE_WEIGHT,
        ..problem
    };
    let (solid, _) = strict.solve(ahead, config.max_iterations);
    finish_superellipsoid(map, data, canonical(solid), config)
}

/// The same solid with the body axes turned (by the shape's symmetries: half and quarter turns
/// about body z, half turns about body x) to lie nearest the world axes, so one fruit is always
/// described the same way.
pub(super) fn canonical(s: Superellipsoid) -> Superellipsoid {
    let mut best = s;
    for quarter_turns in 0..4 {
        for flip in [false, true] {
            let about_z = Rotation3::from_axis_angle(
                &Vector3::z_axis(),
                f64::from(quarter_turns) * std::f64::consts::FRAC_PI_2,
            );
            let about_x = Rotation3::from_axis_angle(
                &Vector3::x_axis(),
                if flip { std::f64::consts::PI } else { 0.0 },
            );
            let r = s.world_from_body * about_z * about_x;
            // Turning body z over turns the taper round.
            let taper = if flip { -s.taper } else { s.taper };
            let a = &s.semi_axes_m;
            let semi_axes_m = if quarter_turns % 2 == 1 {
                Vector3::new(a.y, a.x, a.z)
            } else {
                *a
            };
            if r.matrix().trace() > best.world_from_body.matrix().trace() + 1e-12 {
                best = Superellipsoid {
                    world_from_body: r,
                    semi_axes_m,
                    taper,
                    ..s
                };
            }
        }
    }
    best
}

/// Steps 4-5 of the module docs for the superellipsoid; errors as [`fit_superellipsoid`].
pub(super) fn finish_superellipsoid(
    map: &RoiMap,
    data: &FitData,
    s: Superellipsoid,
    config: &FitConfig,
) -> SolidFit {
    let res = data.resolution_m;
    let finite =
        s.centre.iter().all(|c| c.is_finite()) && s.exponents.iter().all(|e| e.is_finite());
    if !(finite && data.axis_ok(&s.semi_axes_m, config) && data.size_near(&s.semi_axes_m)) {
        return Err(None);
    }
    let s = cleared_of_free_space(data, s, config.free_margin_voxels * res).ok_or(None)?;
    let rms_m = (data
        .surface
        .iter()
        .map(|q| s.radial_distance_m(q).powi(2))
        .sum::<f64>()
        / data.surface.len() as f64)
        .sqrt();
    let max_rms_m = config
        .max_superellipsoid_rms_voxels
        .min(config.max_rms_voxels)
        * res;
    if !(rms_m.is_finite() && data.centre_near(&s.centre, config)) {
        return Err(None);
    }
    if rms_m > max_rms_m {
        return Err(Some(Box::new(s)));
    }
    let confidence = observed_share(map, &s, config.surface_samples);
    let semi_axes_m = unbiased_semi_axes(&s.semi_axes_m, res, config.voxel_bias_factor);
    Ok(Superellipsoid { semi_axes_m, ..s }.to_solid(confidence, rms_m))
}

/// Step 4: while free voxels lie deeper than `margin_m` inside, the semi-axis along which they
/// lie shrinks by 1 % (the solver left them within a voxel of the surface). Only the free voxels
/// the fit gathered are read, so the fit reads no more than `fit_read_box`. `None` when an axis
/// shrinks to nothing.
fn cleared_of_free_space(
    data: &FitData,
    mut s: Superellipsoid,
    margin_m: f64,
) -> Option<Superellipsoid> {
    // Shrinking keeps the solid within its body box (widened by the taper), so only the free
    // voxels in that box can ever be inside.
    let wide = 1.0 + s.taper.abs();
    let reach = s.semi_axes_m.component_mul(&Vector3::new(wide, wide, 1.0));
    let candidates: Vec<Point3<f64>> = data
        .free_around
        .iter()
        .filter(|f| (0..3).all(|i| s.body_of(f)[i].abs() < reach[i]))
        .copied()
        .collect();
    for _ in 0..40 {
        let inside: Vec<Vector3<f64>> = candidates
            .iter()
            .filter(|f| s.holds(f, margin_m))
            .filter_map(|f| s.untapered(&s.body_of(f)))
            .collect();
        if inside.is_empty() {
            break;
        }
        let push = inside.iter().fold(Vector3::zeros(), |sum, x| {
            sum + x.component_div(&s.semi_axes_m).map(|v| v * v)
        });
        let axis = push.imax();
        s.semi_axes_m[axis] *= 0.99;
        if s.semi_axes_m[axis] < 0.5 * data.resolution_m {
            return None;
        }
    }
    Some(s)
}

/// Share of points spread over the surface whose voxel the map knows.
fn observed_share(map: &RoiMap, s: &Superellipsoid, samples: usize) -> f64 {
    let known = fibonacci_sphere(samples)
        .filter(|u| {
            let p = s.surface_point(&u.component_mul(&s.semi_axes_m));
            map.try_key_of(&p)
                .is_some_and(|k| map.observed_occupancy(k) != Occupancy::Unknown)
        })
        .count();
    known as f64 / samples.max(1) as f64
}
