//! Summary statistics and the one-sided Mann-Whitney U test.
//!
//! [`mann_whitney_u`] follows SciPy's `mannwhitneyu(x, y, alternative=..., method="auto")`:
//! U is the statistic of `x` (pairs `(x_i, y_j)` with `x_i > y_j`, ties counting ½); the p-value
//! is exact (the permutation distribution of U) when there are no ties and either sample has
//! fewer than 8 values, and otherwise from the normal approximation with tie correction and
//! continuity correction.

use serde::Serialize;

/// Mean and sample standard deviation (n − 1); NaN values are skipped. `None` without values;
/// the deviation of a single value is 0.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MeanStd {
    pub mean: f64,
    pub std: f64,
    /// Values that entered (non-NaN).
    pub n: usize,
}

pub fn mean_std(values: &[f64]) -> Option<MeanStd> {
    let v: Vec<f64> = values.iter().copied().filter(|x| !x.is_nan()).collect();
    if v.is_empty() {
        return None;
    }
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let std = if v.len() > 1 {
        (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    } else {
        0.0
    };
    Some(MeanStd {
        mean,
        std,
        n: v.len(),
    })
}

/// The alternative hypothesis of a one-sided test.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Alternative {
    /// `x` tends to be larger than `y`.
    Greater,
    /// `x` tends to be smaller than `y`.
    Less,
}

/// Result of [`mann_whitney_u`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MannWhitney {
    /// U statistic of `x`.
    pub u: f64,
    /// One-sided p-value.
    pub p_value: f64,
    /// True when the exact distribution was used.
    pub exact: bool,
}

/// One-sided Mann-Whitney U test of `x` against `y` (see the module docs). NaN values are
/// dropped; `None` when either sample is then empty.
pub fn mann_whitney_u(x: &[f64], y: &[f64], alternative: Alternative) -> Option<MannWhitney> {
    let x: Vec<f64> = x.iter().copied().filter(|v| !v.is_nan()).collect();
    let y: Vec<f64> = y.iter().copied().filter(|v| !v.is_nan()).collect();
    let (n1, n2) = (x.len(), y.len());
    if n1 == 0 || n2 == 0 {
        return None;
    }
    // Midranks of the pooled sample.
    let mut pooled: Vec<(f64, bool)> = x
        .iter()
        .map(|v| (*v, true))
        .chain(y.iter().map(|v| (*v, false)))
        .collect();
    pooled.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n = pooled.len();
    let mut rank_sum_x = 0.0;
    let mut tie_term = 0.0;
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j + 1 < n && pooled[j + 1].0 == pooled[i].0 {
            j += 1;
        }
        let t = (j - i + 1) as f64;
        let midrank = (i + j) as f64 / 2.0 + 1.0;
        rank_sum_x += midrank * pooled[i..=j].iter().filter(|(_, in_x)| *in_x).count() as f64;
        tie_term += t * t * t - t;
        i = j + 1;
    }
    let (f1, f2) = (n1 as f64, n2 as f64);
    let u = rank_sum_x - f1 * (f1 + 1.0) / 2.0;
    let has_ties = tie_term > 0.0;
    if !has_ties && n1.min(n2) < 8 {
        // P(U >= u) for "greater", P(U <= u) for "less"; the distribution is symmetric.
        let counts = u_distribution(n1, n2);
        let total: f64 = counts.iter().sum();
        let k = u.round() as usize;
        let tail: f64 = match alternative {
            Alternative::Greater => counts.iter().skip(k).sum(),
            Alternative::Less => counts.iter().take(k + 1).sum(),
        };
        return Some(MannWhitney {
            u,
            p_value: (tail / total).clamp(0.0, 1.0),
            exact: true,
        });
    }
    let mu = f1 * f2 / 2.0;
    let nf = n as f64;
    let var = f1 * f2 / 12.0 * ((nf + 1.0) - tie_term / (nf * (nf - 1.0)));
    let p_value = if var > 0.0 {
        let sd = var.sqrt();
        // Continuity correction towards the mean.
        let z = match alternative {
            Alternative::Greater => (u - mu - 0.5) / sd,
            Alternative::Less => (mu - u - 0.5) / sd,
        };
        normal_sf(z)
    } else {
        // Every value equal: no evidence either way.
        1.0
    };
    Some(MannWhitney {
        u,
        p_value: p_value.clamp(0.0, 1.0),
        exact: false,
    })
}

/// Number of arrangements giving each U = 0..=n1·n2 (no ties), by the recurrence
/// `f(m, n, u) = f(m − 1, n, u − n) + f(m, n − 1, u)`.
fn u_distribution(n1: usize, n2: usize) -> Vec<f64> {
    // table[m][u] for the current n; iterate n from 0 to n2.
    let max_u = n1 * n2;
    // prev[m] = distribution for (m, n-1); start with n = 0: only U = 0.
    let mut prev: Vec<Vec<f64>> = (0..=n1).map(|_| vec![1.0]).collect();
    for n in 1..=n2 {
        let mut cur: Vec<Vec<f64>> = Vec::with_capacity(n1 + 1);
        cur.push(vec![1.0]);
        for m in 1..=n1 {
            let mut d = vec![0.0; m * n + 1];
            // f(m, n - 1, u)
            for (u, c) in prev[m].iter().enumerate() {
                d[u] += c;
            }
            // f(m - 1, n, u - n)
            for (u, c) in cur[m - 1].iter().enumerate() {
                d[u + n] += c;
            }
            cur.push(d);
        }
        prev = cur;
    }
    let mut out = prev.pop().unwrap_or_else(|| vec![1.0]);
    out.resize(max_u + 1, 0.0);
    out
}

/// Upper tail of the standard normal distribution, `P(Z > z)`.
pub fn normal_sf(z: f64) -> f64 {
    0.5 * erfc(z / std::f64::consts::SQRT_2)
}

/// Complementary error function: the Numerical Recipes Chebyshev fit (`erfcc`), fractional error
/// below 1.2e-7 everywhere; enough for p-values.
pub fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let r = t * poly.exp();
    if x >= 0.0 {
        r
    } else {
        2.0 - r
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn mean_and_sample_std() {
        let m = mean_std(&[2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0]).unwrap();
        assert!((m.mean - 5.0).abs() < 1e-12);
        // Sample variance 32 / 7.
        assert!((m.std - (32.0f64 / 7.0).sqrt()).abs() < 1e-12);
        assert_eq!(m.n, 8);
        let one = mean_std(&[3.0, f64::NAN]).unwrap();
        assert_eq!((one.mean, one.std, one.n), (3.0, 0.0, 1));
        assert!(mean_std(&[]).is_none());
        assert!(mean_std(&[f64::NAN]).is_none());
    }

    #[test]
    fn normal_tail_matches_known_values() {
        assert!((normal_sf(0.0) - 0.5).abs() < 1e-7);
        assert!((normal_sf(1.959_963_985) - 0.025).abs() < 1e-7);
        assert!((normal_sf(-1.644_853_627) - 0.95).abs() < 1e-7);
        assert!((normal_sf(3.0) - 0.001_349_898).abs() < 1e-8);
    }

    #[test]
    fn u_distribution_counts_all_arrangements() {
        // n1 = n2 = 3: C(6, 3) = 20 arrangements, U from 0 to 9.
        let d = u_distribution(3, 3);
        assert_eq!(d, vec![1.0, 1.0, 2.0, 3.0, 3.0, 3.0, 3.0, 2.0, 1.0, 1.0]);
        assert_eq!(u_distribution(2, 0), vec![1.0]);
        let d = u_distribution(5, 4);
        assert_eq!(d.iter().sum::<f64>(), 126.0);
    }

    #[test]
    fn exact_test_matches_scipy() {
        // SciPy documentation example: males vs females, U1 = 17.
        let males = [19.0, 22.0, 16.0, 29.0, 24.0];
        let females = [20.0, 11.0, 17.0, 12.0];
        let r = mann_whitney_u(&males, &females, Alternative::Greater).unwrap();
        assert_eq!(r.u, 17.0);
        assert!(r.exact);
        // Two-sided exact p = 0.1111 (= 2 · 7/126).
        assert!((r.p_value - 7.0 / 126.0).abs() < 1e-12, "{r:?}");
        let r = mann_whitney_u(&males, &females, Alternative::Less).unwrap();
        assert!((r.p_value - 122.0 / 126.0).abs() < 1e-12, "{r:?}");
        // Complete separation of 3 and 3: p = 1/20.
        let r = mann_whitney_u(&[4.0, 5.0, 6.0], &[1.0, 2.0, 3.0], Alternative::Greater).unwrap();
        assert_eq!(r.u, 9.0);
        assert!((r.p_value - 0.05).abs() < 1e-12);
        let r = mann_whitney_u(&[4.0, 5.0, 6.0], &[1.0, 2.0, 3.0], Alternative::Less).unwrap();
        assert!((r.p_value - 1.0).abs() < 1e-12);
    }

    #[test]
    fn asymptotic_test_matches_scipy() {
        let females = [20.0, 11.0, 17.0, 12.0];
        // With a tie (19 twice, within males only) the asymptotic path is taken: U = 20, tie
        // term t³ − t = 6, var = 24/12 · (11 − 6/90) = 21.8667, z = 7.5 / 4.6762 = 1.60387,
        // p = 0.0543710 (checked with Python's math.erfc).
        let males = [19.0, 22.0, 16.0, 29.0, 24.0, 19.0];
        let r = mann_whitney_u(&males, &females, Alternative::Greater).unwrap();
        assert!(!r.exact);
        assert_eq!(r.u, 20.0);
        assert!((r.p_value - 0.054_371_03).abs() < 1e-7, "{r:?}");
        let r = mann_whitney_u(&males, &females, Alternative::Less).unwrap();
        assert_eq!(r.u, 20.0);
        // z = (12 - 20 - 0.5) / 4.6762 = -1.81772: p = 0.9654467.
        assert!((r.p_value - 0.965_446_7).abs() < 1e-6, "{r:?}");
        // SciPy's documentation sample with method="asymptotic" gives the two-sided p-value
        // 0.11134688653314041 (U = 17, no ties): the same normal tail, doubled.
        let (n1, n2) = (5.0f64, 4.0f64);
        let z = (17.0 - n1 * n2 / 2.0 - 0.5) / (n1 * n2 * (n1 + n2 + 1.0) / 12.0).sqrt();
        assert!((2.0 * normal_sf(z) - 0.111_346_886_533).abs() < 1e-7);
    }

    #[test]
    fn asymptotic_test_for_twenty_trials() {
        // n1 = n2 = 20 without ties (values 1..40): x holds the 20 largest values, U = 400.
        // z = (400 - 200 - 0.5) / sqrt(20·20·41/12) = 199.5 / 36.9685 = 5.3965; p ≈ 3.4e-8.
        let x: Vec<f64> = (21..=40).map(f64::from).collect();
        let y: Vec<f64> = (1..=20).map(f64::from).collect();
        let r = mann_whitney_u(&x, &y, Alternative::Greater).unwrap();
        assert!(!r.exact);
        assert_eq!(r.u, 400.0);
        assert!((r.p_value - 3.397_807_6e-8).abs() < 1e-12, "{r:?}");
        let r = mann_whitney_u(&x, &y, Alternative::Less).unwrap();
        assert!(r.p_value > 0.999_999, "{r:?}");
        // Interleaved samples (U = 190): no evidence, p = 0.611805.
        let x: Vec<f64> = (0..20).map(|i| f64::from(2 * i)).collect();
        let y: Vec<f64> = (0..20).map(|i| f64::from(2 * i + 1)).collect();
        let r = mann_whitney_u(&x, &y, Alternative::Greater).unwrap();
        assert_eq!(r.u, 190.0);
        assert!((r.p_value - 0.611_804_7).abs() < 1e-6, "{r:?}");
    }

    #[test]
    fn degenerate_samples() {
        assert!(mann_whitney_u(&[], &[1.0], Alternative::Greater).is_none());
        assert!(mann_whitney_u(&[f64::NAN], &[1.0], Alternative::Greater).is_none());
        let r = mann_whitney_u(&[1.0; 10], &[1.0; 10], Alternative::Greater).unwrap();
        assert_eq!(r.p_value, 1.0);
        assert_eq!(r.u, 50.0);
    }
}
