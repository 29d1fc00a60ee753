//! Levenberg-Marquardt over a rotated, tapered superellipsoid: centre, orientation, log
//! semi-axes, the two shape exponents and the taper (12 parameters), with analytic derivatives
//! of the radial distance ([`Superellipsoid`]). Residuals, in voxels:
//!
//! - every cluster voxel centre: its radial distance from the surface;
//! - every free voxel deeper inside than the free margin: a hinge on that depth (the camera saw
//!   through it, so the fruit is not there: this is what bounds a half-seen fruit's front);
//! - priors with the ellipsoid fit's coverage-scaled roundness weight: a round cross-section
//!   about body z (the stalk axis), a length along z near the cross-section's (weaker, so that
//!   elongated fruit stay elongated), exponents near 1 (the ellipsoid), no taper, and body z
//!   near vertical (weak). Where the data leave the back of a fruit open, these decide it.
//!
//! Orientation steps are rotations about the body axes, `R ← R·exp(δω)`, so the derivative at
//! each step is simple: `∂x/∂δω = [x]×` for a point's body coordinates `x`.

use nalgebra::{Rotation3, SMatrix, SVector, Vector3};

use crate::fit::SizePrior;
use crate::superellipsoid::Superellipsoid;

/// Weight of the elongation prior relative to the cross-section's roundness prior.
const ELONGATION_PRIOR: f64 = 0.3;
/// Weight of the upright prior relative to the roundness prior: a 30° tilt costs as much as a
/// 2 % difference of the cross-section's axes, a fruit lying on its side 16 times that.
const TILT_PRIOR: f64 = 0.3;

/// A step that lowers the cost by less than this share (or 0.01 squared voxels) ends the solve:
/// the shape then moves by well under a millimetre, and creeping on (the free-space hinge makes
/// the cost kinked, so the last steps are small) would cost many more iterations.
const CONVERGED: f64 = 1e-3;

/// Centre (3), orientation step (3), log semi-axes (3), exponents (2), taper (1).
const PARAMETERS: usize = 12;
type Normal = SMatrix<f64, PARAMETERS, PARAMETERS>;
type Column = SVector<f64, PARAMETERS>;

/// One fit problem: the data and weights (see the module docs).
#[derive(Clone, Copy)]
pub(super) struct Refine<'a> {
    pub surface: &'a [nalgebra::Point3<f64>],
    pub free: &'a [nalgebra::Point3<f64>],
    pub resolution_m: f64,
    /// Weight of each roundness and exponent prior residual.
    pub prior_weight: f64,
    /// The size prior: the crop's typical semi-axis and the prior's weight relative to
    /// `prior_weight` ([`crate::fit::SizePrior`]).
    pub size_prior: SizePrior,
    pub free_weight: f64,
    pub free_margin_voxels: f64,
    /// Both exponents stay inside this open interval.
    pub exponent_range: [f64; 2],
    /// The taper stays inside `(−max_taper, max_taper)`.
    pub max_taper: f64,
}

/// Logistic map of an unbounded parameter into the exponent range, and back.
fn exponent_of(t: f64, [lo, hi]: [f64; 2]) -> f64 {
    lo + (hi - lo) / (1.0 + (-t).exp())
}

fn logit_of(e: f64, [lo, hi]: [f64; 2]) -> f64 {
    let s = ((e - lo) / (hi - lo)).clamp(1e-6, 1.0 - 1e-6);
    (s / (1.0 - s)).ln()
}

impl Refine<'_> {
    /// `dε/dt` of [`exponent_of`] at exponent `e`; 0 for a fixed (empty) range.
    fn exponent_slope(&self, e: f64) -> f64 {
        let [lo, hi] = self.exponent_range;
        if hi > lo {
            (e - lo) * (hi - e) / (hi - lo)
        } else {
            0.0
        }
    }

    /// Free voxels outside the body box cannot be inside the shape (it lies within its box,
    /// widened by the taper): skipped without computing their distance.
    fn may_hold(s: &Superellipsoid, x: &Vector3<f64>) -> bool {
        let wide = 1.0 + s.taper.abs();
        let a = &s.semi_axes_m;
        x.x.abs() < a.x * wide && x.y.abs() < a.y * wide && x.z.abs() < a.z
    }

    /// `dk/dτ` of the taper `k = max_taper·tanh(τ)` at taper `k`.
    fn taper_slope(&self, k: f64) -> f64 {
        if self.max_taper > 0.0 {
            self.max_taper - k * k / self.max_taper
        } else {
            0.0
        }
    }

    /// The prior residuals with their non-zero Jacobian entries (index, value) per row.
    fn priors(&self, s: &Superellipsoid, mut row: impl FnMut(f64, &[(usize, f64)])) {
        let w = self.prior_weight;
        let l = s.semi_axes_m.map(f64::ln);
        // A round cross-section about body z (the stalk axis): what decides the depth of a fruit
        // seen from the side.
        row(w * (l.x - l.y), &[(6, w), (7, -w)]);
        // Length along z near the cross-section's, weaker: an elongated fruit seen along its
        // length shows it, and a prior as strong as the roundness one would not let it.
        let wz = w * ELONGATION_PRIOR;
        let elongation = l.z - (l.x + l.y) / 2.0;
        row(wz * elongation, &[(6, -wz / 2.0), (7, -wz / 2.0), (8, wz)]);
        for k in 0..2 {
            let e = s.exponents[k];
            row(w * (e - 1.0), &[(9 + k, w * self.exponent_slope(e))]);
        }
        row(w * s.taper, &[(11, w * self.taper_slope(s.taper))]);
        if let Some((ws, typical_ln)) = self.size_prior.weighted(w) {
            let mean = (l.x + l.y + l.z) / 3.0;
            let d = ws / 3.0;
            row(ws * (mean - typical_ln), &[(6, d), (7, d), (8, d)]);
        }
        // Fruit hang with body z within ~30° of vertical (either way up): 1 − cos² of the tilt,
        // weak, so that it only decides what a one-sided view leaves open. Turning by δω about
        // the body axes moves cos by δω·(ẑ × R⁻¹·ẑ).
        let wt = w * TILT_PRIOR;
        let up_in_body = s.world_from_body.inverse_transform_vector(&Vector3::z());
        let cos = up_in_body.z;
        let turn = Vector3::z().cross(&up_in_body) * (-2.0 * cos * wt);
        row(
            wt * (1.0 - cos * cos),
            &[(3, turn.x), (4, turn.y), (5, turn.z)],
        );
    }

    /// Cost (sum of squared residuals), and when `normal` is given, `JᵀJ` and `Jᵀr` added to it.
    fn evaluate(&self, s: &Superellipsoid, mut normal: Option<(&mut Normal, &mut Column)>) -> f64 {
        let res = self.resolution_m;
        let mut cost = 0.0;
        let slopes = s.exponents.map(|e| self.exponent_slope(e));
        let taper_slope = self.taper_slope(s.taper);
        let want_jacobian = normal.is_some();
        let mut add = |r: f64, j: Option<&Column>| {
            cost += r * r;
            if let (Some((jtj, jtr)), Some(j)) = (normal.as_mut(), j) {
                jtj.ger(1.0, j, j, 1.0);
                jtr.axpy(r, j, 1.0);
            }
        };
        let row_of = |x: &Vector3<f64>, scale: f64| -> Option<(f64, Column)> {
            let g = s.distance_gradient(x)?;
            let mut j = Column::zeros();
            if want_jacobian {
                let centre = -(s.world_from_body * g.wrt_body);
                let turn = g.wrt_body.cross(x);
                for i in 0..3 {
                    j[i] = centre[i] * scale;
                    j[3 + i] = turn[i] * scale;
                    j[6 + i] = g.wrt_log_axes[i] * scale;
                }
                for k in 0..2 {
                    j[9 + k] = g.wrt_exponents[k] * slopes[k] * scale;
                }
                j[11] = g.wrt_taper * taper_slope * scale;
            }
            Some((g.distance_m, j))
        };
        for q in self.surface {
            if let Some((d, j)) = row_of(&s.body_of(q), 1.0 / res) {
                add(d / res, Some(&j));
            }
        }
        let w = self.free_weight;
        for f in self.free {
            let x = s.body_of(f);
            if !Self::may_hold(s, &x) {
                continue;
            }
            if let Some((d, j)) = row_of(&x, -w / res) {
                let depth = -d / res - self.free_margin_voxels;
                if depth > 0.0 {
                    add(w * depth, Some(&j));
                }
            }
        }
        self.priors(s, |r, entries| {
            let mut j = Column::zeros();
            for &(i, v) in entries {
                j[i] = v;
            }
            add(r, Some(&j));
        });
        cost
    }

    /// `s` moved by the parameter step `delta` (see the module docs).
    fn stepped(&self, s: &Superellipsoid, delta: &Column) -> Superellipsoid {
        let turn = Rotation3::new(Vector3::new(delta[3], delta[4], delta[5]));
        let range = self.exponent_range;
        let exponent = |k: usize| {
            if range[1] > range[0] {
                exponent_of(logit_of(s.exponents[k], range) + delta[9 + k], range)
            } else {
                s.exponents[k]
            }
        };
        let taper = if self.max_taper > 0.0 {
            let tau = (s.taper / self.max_taper)
                .clamp(-1.0 + 1e-9, 1.0 - 1e-9)
                .atanh();
            self.max_taper * (tau + delta[11]).tanh()
        } else {
            s.taper
        };
        Superellipsoid {
            centre: s.centre + Vector3::new(delta[0], delta[1], delta[2]),
            world_from_body: s.world_from_body * turn,
            semi_axes_m: Vector3::new(
                s.semi_axes_m.x * delta[6].exp(),
                s.semi_axes_m.y * delta[7].exp(),
                s.semi_axes_m.z * delta[8].exp(),
            ),
            exponents: [exponent(0), exponent(1)],
            taper,
        }
    }

    /// The fitted shape from `start` and its cost, after at most `iterations` steps.
    pub(super) fn solve(&self, start: Superellipsoid, iterations: usize) -> (Superellipsoid, f64) {
        let mut s = start;
        let mut cost = self.evaluate(&s, None);
        let mut lambda = 1e-3;
        for _ in 0..iterations {
            let (mut jtj, mut jtr) = (Normal::zeros(), Column::zeros());
            self.evaluate(&s, Some((&mut jtj, &mut jtr)));
            // Directions the data leave flat (a sphere's orientation) still get some damping.
            let floor = 1e-9 * jtj.diagonal().max().max(1e-12);
            let mut improved = false;
            for _ in 0..10 {
                let mut damped = jtj;
                for d in 0..PARAMETERS {
                    damped[(d, d)] += lambda * (jtj[(d, d)] + floor);
                }
                let Some(step) = damped.cholesky().map(|c| c.solve(&(-jtr))) else {
                    lambda *= 10.0;
                    continue;
                };
                let candidate = self.stepped(&s, &step);
                let c = self.evaluate(&candidate, None);
                if c.is_finite() && c < cost {
                    improved = cost - c > (CONVERGED * cost).max(0.01);
                    (s, cost) = (candidate, c);
                    lambda = (lambda * 0.3).max(1e-9);
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        (s, cost)
    }
}
