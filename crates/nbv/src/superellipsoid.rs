//! Rotated, tapered superellipsoids: the whole-fruit shape of [`crate::fit`].
//!
//! In its body frame (`X = R⁻¹·(q − origin)`) the shape is a superellipsoid with semi-axes
//! `a, b, c` and shape exponents `ε1` (along body z) and `ε2` (around it), tapered linearly
//! along z: a body point `X` is undone to `x = (X/t, Y/t, Z)` with `t = 1 + k·Z/c`, and `x` is
//! inside when the inside-outside function
//!
//! ```text
//! F(x) = (|x/a|^(2/ε2) + |y/b|^(2/ε2))^(ε2/ε1) + |z/c|^(2/ε1)
//! ```
//!
//! is at most 1. `ε1 = ε2 = 1, k = 0` is an ellipsoid; smaller exponents square it off (a blocky
//! capsicum), larger ones pinch it; `k > 0` widens the `+z` end and narrows the other (a capsicum
//! from shoulders to tip). Distances to the surface are measured along the ray from the origin in
//! the undone frame ([`Superellipsoid::radial_distance_m`]): the point `x·F^(−ε1/2)` lies on the
//! surface, so the distance is `|x|·(1 − F^(−ε1/2))`, exact for spheres and close to the
//! Euclidean distance near the surface of shapes that are neither too flat nor too tapered.

use nalgebra::{Point3, Rotation3, Vector3};

/// Taper factors `t` below this are where the shape has pinched to nothing: points there are
/// outside.
const MIN_TAPER_FACTOR: f64 = 0.05;

/// A tapered superellipsoid in the world frame (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Superellipsoid {
    /// Origin of the body frame: the middle of the shape along body z (not its centroid when
    /// tapered, [`Superellipsoid::centroid`]).
    pub centre: Point3<f64>,
    /// Body axes in the world frame (columns).
    pub world_from_body: Rotation3<f64>,
    /// Semi-axes along body x, y, z.
    pub semi_axes_m: Vector3<f64>,
    /// `[ε1, ε2]`: ε1 shapes the profile along body z, ε2 the cross-section around it.
    pub exponents: [f64; 2],
    /// `k`: the cross-section at `z = ±c` is `1 ± k` times as wide as at the middle.
    pub taper: f64,
}

/// Radial distance of one point and its derivatives (see [`Superellipsoid::distance_gradient`]).
#[derive(Clone, Copy, Debug)]
pub(crate) struct DistanceGradient {
    /// Signed radial distance, metres: > 0 outside.
    pub distance_m: f64,
    /// With respect to the body coordinates of the point.
    pub wrt_body: Vector3<f64>,
    /// With respect to the natural logarithms of the semi-axes.
    pub wrt_log_axes: Vector3<f64>,
    /// With respect to ε1 and ε2.
    pub wrt_exponents: [f64; 2],
    /// With respect to the taper `k`.
    pub wrt_taper: f64,
}

/// `|v|^p` as `exp(p·ln|v|)`, 0 at 0, with `ln|v|` (0 at 0, where every use of it is multiplied
/// by a power that vanishes).
fn power_and_log(v: f64, p: f64) -> (f64, f64) {
    let magnitude = v.abs();
    if magnitude < 1e-300 {
        return (0.0, 0.0);
    }
    let ln = magnitude.ln();
    ((p * ln).exp(), ln)
}

impl Superellipsoid {
    /// The sphere of radius `r` (the identity orientation).
    pub fn sphere(centre: Point3<f64>, r: f64) -> Self {
        Self {
            centre,
            world_from_body: Rotation3::identity(),
            semi_axes_m: Vector3::repeat(r),
            exponents: [1.0, 1.0],
            taper: 0.0,
        }
    }

    /// Body coordinates of a world point.
    pub fn body_of(&self, q: &Point3<f64>) -> Vector3<f64> {
        self.world_from_body
            .inverse_transform_vector(&(q - self.centre))
    }

    /// The taper factor `t` at body height `z`.
    fn taper_factor(&self, z: f64) -> f64 {
        1.0 + self.taper * z / self.semi_axes_m.z
    }

    /// Body coordinates with the taper undone; `None` where the shape has pinched to nothing.
    pub fn untapered(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        let t = self.taper_factor(x.z);
        (t >= MIN_TAPER_FACTOR).then(|| Vector3::new(x.x / t, x.y / t, x.z))
    }

    /// `F` of a point in untapered body coordinates: < 1 inside, 1 on the surface.
    pub fn inside_outside(&self, x: &Vector3<f64>) -> f64 {
        let [e1, e2] = self.exponents;
        let a = &self.semi_axes_m;
        let (a1, _) = power_and_log(x.x / a.x, 2.0 / e2);
        let (a2, _) = power_and_log(x.y / a.y, 2.0 / e2);
        let (a3, _) = power_and_log(x.z / a.z, 2.0 / e1);
        let (g, _) = power_and_log(a1 + a2, e2 / e1);
        g + a3
    }

    /// Signed distance from the surface along the ray from the origin through `q` (taper
    /// undone), metres: > 0 outside, < 0 inside.
    pub fn radial_distance_m(&self, q: &Point3<f64>) -> f64 {
        let body = self.body_of(q);
        let Some(x) = self.untapered(&body) else {
            return body.norm();
        };
        let f = self.inside_outside(&x);
        if f <= 0.0 {
            return -self.semi_axes_m.min();
        }
        x.norm() * (1.0 - f.powf(-self.exponents[0] / 2.0))
    }

    /// Whether `q` lies inside, deeper than `depth_m` below the surface (radially).
    pub fn holds(&self, q: &Point3<f64>, depth_m: f64) -> bool {
        self.radial_distance_m(q) < -depth_m
    }

    /// The surface point in the direction `u` (untapered body frame, any length) seen from the
    /// origin, tapered.
    pub fn surface_point(&self, u: &Vector3<f64>) -> Point3<f64> {
        let f = self.inside_outside(u);
        let x = if f > 0.0 {
            u * f.powf(-self.exponents[0] / 2.0)
        } else {
            Vector3::zeros()
        };
        self.centre + self.world_from_body * self.tapered(&x)
    }

    fn tapered(&self, x: &Vector3<f64>) -> Vector3<f64> {
        let t = self.taper_factor(x.z);
        Vector3::new(x.x * t, x.y * t, x.z)
    }

    /// `B(ε1/2, ε1 + 1)` and `B(3ε1/2, ε1 + 1)`: the zeroth and second moments along z of the
    /// squared cross-section scale `(1 − |z/c|^(2/ε1))^ε1`, over `c·ε1` and `c³·ε1`.
    fn profile_moments(&self) -> (f64, f64) {
        let e1 = self.exponents[0];
        (beta(e1 / 2.0, e1 + 1.0), beta(1.5 * e1, e1 + 1.0))
    }

    /// Volume: `a·b·c·ε1·ε2·B(ε2/2, ε2/2)·(B(ε1/2, ε1 + 1) + k²·B(3ε1/2, ε1 + 1))`; without
    /// taper this is the usual `2·a·b·c·ε1·ε2·B(ε1/2 + 1, ε1)·B(ε2/2, ε2/2)`.
    pub fn volume_m3(&self) -> f64 {
        let [e1, e2] = self.exponents;
        let a = &self.semi_axes_m;
        let (m0, m2) = self.profile_moments();
        let k = self.taper;
        a.x * a.y * a.z * e1 * e2 * beta(e2 / 2.0, e2 / 2.0) * (m0 + k * k * m2)
    }

    /// The centre of volume: the taper moves it `2·k·c·m2 / (m0 + k²·m2)` along body z towards
    /// the wide end.
    pub fn centroid(&self) -> Point3<f64> {
        self.centre + self.world_from_body * Vector3::z() * self.centroid_offset_m()
    }

    /// Signed distance from the origin to the centroid along body z.
    pub fn centroid_offset_m(&self) -> f64 {
        let (m0, m2) = self.profile_moments();
        let k = self.taper;
        2.0 * k * self.semi_axes_m.z * m2 / (m0 + k * k * m2)
    }

    /// The world-axis box around the surface (min, max corners), from a dense parametric sample
    /// (within ~0.3 % of the exact box).
    pub fn world_box(&self) -> (Point3<f64>, Point3<f64>) {
        const ROWS: usize = 24;
        const COLUMNS: usize = 48;
        let [e1, e2] = self.exponents;
        let signed_power = |v: f64, p: f64| v.signum() * v.abs().powf(p);
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for i in 0..=ROWS {
            let eta = -std::f64::consts::FRAC_PI_2 + std::f64::consts::PI * i as f64 / ROWS as f64;
            let (ce, se) = (signed_power(eta.cos(), e1), signed_power(eta.sin(), e1));
            for j in 0..COLUMNS {
                let omega = std::f64::consts::TAU * j as f64 / COLUMNS as f64;
                let x = Vector3::new(
                    ce * signed_power(omega.cos(), e2),
                    ce * signed_power(omega.sin(), e2),
                    se,
                )
                .component_mul(&self.semi_axes_m);
                let p = self.world_from_body * self.tapered(&x);
                (lo, hi) = (lo.inf(&p), hi.sup(&p));
            }
        }
        (self.centre + lo, self.centre + hi)
    }

    /// [`Superellipsoid::radial_distance_m`] of a point given in (tapered) body coordinates,
    /// with its derivatives; `None` at the origin, where the distance has no direction, and
    /// where the shape has pinched to nothing.
    pub(crate) fn distance_gradient(&self, body: &Vector3<f64>) -> Option<DistanceGradient> {
        let x = self.untapered(body)?;
        let plain = self.plain_gradient(&x)?;
        // x = (X/t, Y/t, Z), t = 1 + k·Z/c: the chain rule through the taper.
        let (c, k) = (self.semi_axes_m.z, self.taper);
        let t = self.taper_factor(body.z);
        let g = plain.wrt_body;
        let m = (g.x * x.x + g.y * x.y) / t;
        let mut wrt_log_axes = plain.wrt_log_axes;
        wrt_log_axes.z += k * body.z / c * m;
        Some(DistanceGradient {
            wrt_body: Vector3::new(g.x / t, g.y / t, g.z - k / c * m),
            wrt_log_axes,
            wrt_taper: -body.z / c * m,
            ..plain
        })
    }

    /// The untapered distance and its derivatives with respect to the untapered coordinates.
    fn plain_gradient(&self, x: &Vector3<f64>) -> Option<DistanceGradient> {
        let n = x.norm();
        if n < 1e-12 {
            return None;
        }
        let [e1, e2] = self.exponents;
        let a = &self.semi_axes_m;
        let (a1, l1) = power_and_log(x.x / a.x, 2.0 / e2);
        let (a2, l2) = power_and_log(x.y / a.y, 2.0 / e2);
        let (a3, l3) = power_and_log(x.z / a.z, 2.0 / e1);
        let g = a1 + a2;
        let (gp, ln_g) = power_and_log(g, e2 / e1);
        // G^(ε2/ε1 − 1), 0 where G is (A1 and A2 vanish there too).
        let gp_over_g = if g > 1e-300 { gp / g } else { 0.0 };
        let f = gp + a3;
        if !(f.is_finite() && f > 1e-300) {
            return None;
        }
        let u = (-e1 / 2.0 * f.ln()).exp();
        let over = |v: f64, p: f64| if v.abs() > 1e-300 { p / v } else { 0.0 };
        let df_dx = Vector3::new(
            2.0 / e1 * gp_over_g * over(x.x, a1),
            2.0 / e1 * gp_over_g * over(x.y, a2),
            2.0 / e1 * over(x.z, a3),
        );
        let df_dlog = Vector3::new(
            -2.0 / e1 * gp_over_g * a1,
            -2.0 / e1 * gp_over_g * a2,
            -2.0 / e1 * a3,
        );
        let df_de1 = -gp * ln_g * e2 / (e1 * e1) - a3 * l3 * 2.0 / (e1 * e1);
        let df_de2 = gp * ln_g / e1 - e2 / e1 * gp_over_g * 2.0 / (e2 * e2) * (a1 * l1 + a2 * l2);
        // d = n·(1 − u), u = F^(−ε1/2): ∂d/∂F = n·(ε1/2)·u/F.
        let dd_df = n * e1 / 2.0 * u / f;
        Some(DistanceGradient {
            distance_m: n * (1.0 - u),
            wrt_body: x / n * (1.0 - u) + df_dx * dd_df,
            wrt_log_axes: df_dlog * dd_df,
            wrt_exponents: [n * u * 0.5 * f.ln() + dd_df * df_de1, dd_df * df_de2],
            wrt_taper: 0.0,
        })
    }
}

/// `ln Γ(x)` for `x > 0` (Lanczos, g = 7, nine terms: ~1e-15 relative).
pub fn ln_gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection: Γ(x)·Γ(1 − x) = π / sin(πx); the series is accurate for x ≥ 0.5.
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let z = x - 1.0;
    let t = z + G + 0.5;
    let series = C
        .iter()
        .enumerate()
        .skip(1)
        .fold(C[0], |s, (i, c)| s + c / (z + i as f64));
    0.5 * std::f64::consts::TAU.ln() + (z + 0.5) * t.ln() - t + series.ln()
}

/// The beta function `B(p, q) = Γ(p)·Γ(q) / Γ(p + q)`.
pub fn beta(p: f64, q: f64) -> f64 {
    (ln_gamma(p) + ln_gamma(q) - ln_gamma(p + q)).exp()
}

impl Superellipsoid {
    /// This shape as a fitted [`glasshouse_geom::FruitSolid`] (its centre the centroid), with
    /// the observed share `confidence` and the fit's `rms_residual_m`.
    pub fn to_solid(&self, confidence: f64, rms_residual_m: f64) -> glasshouse_geom::FruitSolid {
        let (box_min, box_max) = self.world_box();
        let size = box_max - box_min;
        glasshouse_geom::FruitSolid {
            kind: glasshouse_geom::SolidKind::Ellipsoid,
            centre: self.centroid(),
            semi_axes_m: self.semi_axes_m,
            world_from_body: nalgebra::UnitQuaternion::from_rotation_matrix(&self.world_from_body),
            exponents: self.exponents,
            taper: self.taper,
            volume_m3: self.volume_m3(),
            box_min,
            box_max,
            box_volume_m3: size.x * size.y * size.z,
            confidence,
            rms_residual_m,
        }
    }
}

impl Superellipsoid {
    /// The centres of the voxels (`voxel_m` on a side, aligned with the origin) that hold the
    /// part of the surface facing `towards`: what a map holds of this shape seen from that side
    /// (for tests and benchmarks of what is fitted to such voxels). Sorted by voxel.
    pub fn seen_voxel_centres(&self, towards: Vector3<f64>, voxel_m: f64) -> Vec<Point3<f64>> {
        const SAMPLES: usize = 4000;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let towards = towards.normalize();
        let mut keys = std::collections::BTreeSet::new();
        for i in 0..SAMPLES {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / SAMPLES as f64;
            let (r, angle) = ((1.0 - z * z).sqrt(), golden * i as f64);
            let p = self.surface_point(&Vector3::new(r * angle.cos(), r * angle.sin(), z));
            if (p - self.centroid()).normalize().dot(&towards) > 0.1 {
                keys.insert([0, 1, 2].map(|k| (p[k] / voxel_m).floor() as i64));
            }
        }
        keys.iter()
            .map(|k| Point3::from(k.map(|v| (v as f64 + 0.5) * voxel_m)))
            .collect()
    }
}

impl From<&glasshouse_geom::FruitSolid> for Superellipsoid {
    /// The solid a fit describes (its `centre` is the centre of volume, the body origin sits
    /// off it along body z when tapered).
    fn from(fitted: &glasshouse_geom::FruitSolid) -> Self {
        let mut solid = Superellipsoid {
            centre: fitted.centre,
            world_from_body: fitted.world_from_body.to_rotation_matrix(),
            semi_axes_m: fitted.semi_axes_m,
            exponents: fitted.exponents,
            taper: fitted.taper,
        };
        if fitted.taper != 0.0 {
            solid.centre -= solid.world_from_body * Vector3::z() * solid.centroid_offset_m();
        }
        solid
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn ln_gamma_matches_known_values() {
        let pi = std::f64::consts::PI;
        let known = [
            (1.0, 0.0),
            (2.0, 0.0),
            (0.5, 0.5 * pi.ln()),
            (1.5, (pi.sqrt() / 2.0).ln()),
            (5.0, 24f64.ln()),
            (0.1, 2.252_712_651_734_205_5),
            (0.2, 1.524_063_822_430_784_3),
            (0.75, 0.203_280_951_431_295),
            (0.25, 1.288_022_524_698_077_2),
            (10.0, 362_880f64.ln()),
            (30.5, 72.953_471_184_169_4),
        ];
        for (x, want) in known {
            let got = ln_gamma(x);
            assert!(
                (got - want).abs() < 1e-12 * want.abs().max(1.0),
                "lnΓ({x}) = {got}, want {want}"
            );
        }
        assert!((beta(0.5, 0.5) - pi).abs() < 1e-12);
        assert!((beta(1.5, 1.0) - 2.0 / 3.0).abs() < 1e-12);
    }

    /// The closed-form volume and centroid against counting the cells of a 0.5 mm grid inside
    /// the shape.
    #[test]
    fn volume_and_centroid_match_a_grid_count() {
        let axes = Vector3::new(0.03, 0.025, 0.04);
        for (exponents, taper) in [
            ([1.0, 1.0], 0.0),
            ([0.5, 0.8], 0.0),
            ([1.4, 0.4], 0.0),
            ([0.3, 1.5], 0.0),
            ([1.0, 1.0], 0.5),
            ([0.6, 0.8], -0.4),
        ] {
            let s = Superellipsoid {
                exponents,
                taper,
                semi_axes_m: axes,
                ..Superellipsoid::sphere(Point3::origin(), 1.0)
            };
            let step = 0.0005;
            let reach = axes * (1.0 + taper.abs());
            let cells = |h: f64| (h / step).ceil() as i32;
            let (mut inside, mut sum_z) = (0u64, 0.0);
            for i in -cells(reach.x)..cells(reach.x) {
                for j in -cells(reach.y)..cells(reach.y) {
                    for k in -cells(reach.z)..cells(reach.z) {
                        let q = Point3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) * step;
                        if s.radial_distance_m(&q) <= 0.0 {
                            inside += 1;
                            sum_z += q.z;
                        }
                    }
                }
            }
            let counted = inside as f64 * step.powi(3);
            let rel = s.volume_m3() / counted - 1.0;
            assert!(
                rel.abs() < 0.01,
                "{exponents:?} {taper}: {} vs {counted}",
                s.volume_m3()
            );
            let centroid_z = sum_z / inside as f64;
            assert!(
                (s.centroid().z - centroid_z).abs() < 2e-4,
                "{exponents:?} {taper}"
            );
        }
        let ball = Superellipsoid::sphere(Point3::origin(), 0.03);
        let want = 4.0 / 3.0 * std::f64::consts::PI * 0.03f64.powi(3);
        assert!((ball.volume_m3() / want - 1.0).abs() < 1e-12);
    }

    fn tilted() -> Superellipsoid {
        Superellipsoid {
            centre: Point3::new(0.1, -0.2, 1.0),
            world_from_body: Rotation3::from_euler_angles(0.3, -0.4, 0.9),
            semi_axes_m: Vector3::new(0.03, 0.025, 0.045),
            exponents: [0.7, 1.2],
            taper: 0.35,
        }
    }

    #[test]
    fn surface_points_lie_on_the_surface_and_in_the_box() {
        let s = tilted();
        let (lo, hi) = s.world_box();
        let mut reached = Vector3::<f64>::zeros();
        for k in 0..400 {
            let t = k as f64 * 0.37;
            let u = Vector3::new(t.sin() * (t * 0.3).cos(), t.cos(), (t * 1.7).sin());
            let p = s.surface_point(&u);
            assert!(s.radial_distance_m(&p).abs() < 1e-12);
            let body = s.untapered(&s.body_of(&p)).unwrap();
            assert!((s.inside_outside(&body) - 1.0).abs() < 1e-9);
            assert!((p - lo).iter().all(|v| *v > -1e-4) && (hi - p).iter().all(|v| *v > -1e-4));
            reached = reached.sup(&(p - s.centre).abs());
        }
        // The box is tight: random surface points come close to each face.
        let half = (hi - lo) / 2.0;
        assert!(
            (half - reached).iter().all(|v| *v < 0.15 * half.max()),
            "{half:?} {reached:?}"
        );
        assert!(s.holds(&s.centre, 0.02) && !s.holds(&(s.centre + half * 1.01), 0.0));
    }

    /// The analytic derivatives against central differences.
    #[test]
    fn distance_gradient_matches_finite_differences() {
        let s = tilted();
        let h = 1e-7;
        for x in [
            Vector3::new(0.02, -0.01, 0.03),
            Vector3::new(-0.04, 0.002, -0.01),
            Vector3::new(0.0, 0.015, 0.05),
            Vector3::new(0.01, 0.0, 0.0),
        ] {
            let g = s.distance_gradient(&x).expect("off centre");
            let d = |s: &Superellipsoid, x: &Vector3<f64>| {
                let q = s.centre + s.world_from_body * x;
                s.radial_distance_m(&q)
            };
            assert!((g.distance_m - d(&s, &x)).abs() < 1e-12);
            for i in 0..3 {
                let mut e = Vector3::zeros();
                e[i] = h;
                let numeric = (d(&s, &(x + e)) - d(&s, &(x - e))) / (2.0 * h);
                assert!((numeric - g.wrt_body[i]).abs() < 1e-5, "x{i} at {x:?}");
                let shifted = |sign: f64| {
                    let mut t = s;
                    t.semi_axes_m[i] *= (sign * h).exp();
                    d(&t, &x)
                };
                let numeric = (shifted(1.0) - shifted(-1.0)) / (2.0 * h);
                assert!(
                    (numeric - g.wrt_log_axes[i]).abs() < 1e-5,
                    "log axis {i} at {x:?}"
                );
            }
            for k in 0..2 {
                let shifted = |sign: f64| {
                    let mut t = s;
                    t.exponents[k] += sign * h;
                    d(&t, &x)
                };
                let numeric = (shifted(1.0) - shifted(-1.0)) / (2.0 * h);
                assert!((numeric - g.wrt_exponents[k]).abs() < 1e-5, "ε{k} at {x:?}");
            }
            let shifted = |sign: f64| {
                let mut t = s;
                t.taper += sign * h;
                d(&t, &x)
            };
            let numeric = (shifted(1.0) - shifted(-1.0)) / (2.0 * h);
            assert!((numeric - g.wrt_taper).abs() < 1e-5, "taper at {x:?}");
        }
    }
}
