//! A fruit's growth between two visits, measured on one shape.
//!
//! Each visit's fitted solid is off by a fifth of its volume or so (a partial view, a solid
//! extrapolated where nothing was seen), and those errors are independent from visit to visit:
//! the difference of two fitted volumes is mostly the two errors, since a fruit gains only about
//! a third of its volume in a few days. A fruit swells about its own shape, so the growth is
//! measured instead as a scale: each visit's surface points are fitted by *one* shape, scaled
//! about its origin and shifted, and the shape's error is then the same on both visits and
//! cancels in their ratio. Both visits' solids serve as that shape in turn, and the two ratios
//! are averaged ([`volume_ratio`]).

pub use glasshouse_geom::volume_change_m3;
use glasshouse_geom::{FruitSolid, FruitSurface};
use nalgebra::{DMatrix, DVector, Point3, Vector3};

use crate::superellipsoid::Superellipsoid;

/// Surface points fewer than this give no scale.
pub const MIN_SURFACE_POINTS: usize = 12;
/// Residuals beyond this count less (Huber), metres: half a voxel of the planner's map.
const HUBER_M: f64 = 0.005;
const ITERATIONS: usize = 25;
/// Steps of a logarithm and of a shift, metres, for the numeric derivatives.
const STEP_LOG: f64 = 1e-4;
const STEP_SHIFT_M: f64 = 1e-5;
fn huber_cost(r: f64) -> f64 {
    let a = r.abs();
    if a <= HUBER_M {
        0.5 * r * r
    } else {
        HUBER_M * (a - 0.5 * HUBER_M)
    }
}

/// Robust (Huber) Levenberg-Marquardt over `residuals(params)`, numeric derivatives with
/// `steps`; `None` when a step cannot be solved for.
fn minimise(
    mut params: DVector<f64>,
    steps: &[f64],
    residuals: impl Fn(&DVector<f64>) -> Vec<f64>,
) -> Option<DVector<f64>> {
    let cost = |r: &[f64]| r.iter().map(|&v| huber_cost(v)).sum::<f64>();
    let mut at = residuals(&params);
    let mut current = cost(&at);
    let mut damping = 1e-3;
    let n = params.len();
    for _ in 0..ITERATIONS {
        let mut jacobian = DMatrix::zeros(at.len(), n);
        for k in 0..n {
            let mut delta = DVector::zeros(n);
            delta[k] = steps[k];
            let (up, down) = (
                residuals(&(&params + &delta)),
                residuals(&(&params - &delta)),
            );
            for (i, (u, d)) in up.iter().zip(&down).enumerate() {
                jacobian[(i, k)] = (u - d) / (2.0 * steps[k]);
            }
        }
        // Each row scaled by its Huber weight (not a dense n × n diagonal matrix).
        let mut weighted = jacobian.clone();
        for (mut row, r) in weighted.row_iter_mut().zip(&at) {
            row *= HUBER_M / r.abs().max(HUBER_M);
        }
        let normal = jacobian.transpose() * &weighted;
        let gradient = weighted.transpose() * DVector::from_column_slice(&at);
        let damped = &normal + DMatrix::from_diagonal(&normal.diagonal()) * damping;
        let next = &params - damped.lu().solve(&gradient)?;
        let next_at = residuals(&next);
        let next_cost = cost(&next_at);
        if next_cost < current {
            let settled = current - next_cost < 1e-10 * current.max(1e-30);
            (params, at, current, damping) = (next, next_at, next_cost, damping * 0.3);
            if settled {
                break;
            }
        } else {
            damping *= 10.0;
        }
    }
    Some(params)
}

/// `shape` with its semi-axes times `exp(log_axes)` and its origin shifted by `shift_m`.
fn moved(shape: &Superellipsoid, log_axes: Vector3<f64>, shift_m: Vector3<f64>) -> Superellipsoid {
    Superellipsoid {
        centre: shape.centre + shift_m,
        semi_axes_m: shape.semi_axes_m.component_mul(&log_axes.map(f64::exp)),
        ..*shape
    }
}

fn radial(shape: &Superellipsoid, points: &[Point3<f64>], out: &mut Vec<f64>) {
    out.extend(points.iter().map(|q| shape.radial_distance_m(q)));
}

/// The scale `s` (about the shape's origin) and shift that best bring `shape` onto `points`
/// (robust least squares of the radial distances, from `shift_m`); `None` with too few points
/// or a fit that does not settle on a finite scale.
pub fn fit_scale(
    shape: &Superellipsoid,
    points: &[Point3<f64>],
    shift_m: Vector3<f64>,
) -> Option<f64> {
    if points.len() < MIN_SURFACE_POINTS {
        return None;
    }
    let start = DVector::from_column_slice(&[0.0, shift_m.x, shift_m.y, shift_m.z]);
    let steps = [STEP_LOG, STEP_SHIFT_M, STEP_SHIFT_M, STEP_SHIFT_M];
    let fitted = minimise(start, &steps, |p| {
        let mut out = Vec::with_capacity(points.len());
        let s = moved(shape, Vector3::repeat(p[0]), Vector3::new(p[1], p[2], p[3]));
        radial(&s, points, &mut out);
        out
    })?;
    let scale = fitted[0].exp();
    (scale.is_finite() && scale > 0.0).then_some(scale)
}

/// The volume of visit `b` over that of visit `a` of one fruit, each visit's points scaled onto
/// one solid ([`fit_scale`]): `a`'s and then `b`'s, the two ratios averaged (geometrically).
/// `None` when a scale could not be fitted. (A joint fit of one shape's semi-axes to both
/// visits, with `b`'s scale over `a`'s, did no better on the tuning seeds and cost ten times as
/// much.)
pub fn volume_ratio(a: &FruitSurface, b: &FruitSurface) -> Option<f64> {
    let a_to_b = b.solid.centre - a.solid.centre;
    // The linear scale of b over a on one solid, each visit's fit started where its own
    // solid sits (`a_shift_m`: where a sits against that solid).
    let scale_on = |solid: &FruitSolid, a_shift_m: Vector3<f64>| -> Option<f64> {
        let shape = Superellipsoid::from(solid);
        let on_a = fit_scale(&shape, &a.points_m, a_shift_m)?;
        let on_b = fit_scale(&shape, &b.points_m, a_shift_m + a_to_b)?;
        Some(on_b / on_a)
    };
    let ratio = (scale_on(&a.solid, Vector3::zeros())? * scale_on(&b.solid, -a_to_b)?).powf(1.5);
    ratio.is_finite().then_some(ratio)
}

#[cfg(test)]
mod tests;
