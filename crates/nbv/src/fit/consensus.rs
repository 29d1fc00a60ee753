//! The last try before the box fallback of [`super::fit_ellipsoid`]: a fruit grown together
//! with red leaves or a clip into one cluster that no single solid fits and no waist splits.
//! Reported as the cluster's box, such a fruit's volume is 4-12 times too large.
//!
//! A sphere is fitted around each of up to [`SEEDS`] voxels spread over the cluster: first to
//! the voxels within a fruit's diameter of the seed, then, [`REFITS`] times, to the voxels within
//! the outlier band of the previous sphere's surface. Each sphere scores the voxels within the
//! band less the free voxels deeper than the free margin inside it: a sphere bent through a
//! curled leaf holds the air the camera saw through. The best sphere's voxels are then fitted as
//! a solid of their own when they are at least [`MIN_SHARE`] of the cluster. Deterministic: the
//! seeds are every k-th voxel.

use nalgebra::Point3;

use super::{algebraic_sphere, FitConfig, FitData};
use crate::superellipsoid::Superellipsoid;

/// Seed voxels tried, at most.
const SEEDS: usize = 64;
/// Refits of each seed's sphere to the voxels near its surface.
const REFITS: usize = 3;
/// Least share of the cluster the best sphere must hold: a fruit against a leaf is a third to a
/// half of its cluster.
pub(super) const MIN_SHARE: f64 = 0.2;

/// The best-supported fruit-sized sphere in `data` (module docs), `None` when none holds
/// [`MIN_SHARE`] of the voxels.
pub(super) fn best_sphere(data: &FitData, config: &FitConfig) -> Option<Superellipsoid> {
    let n = data.surface.len();
    let band_m = config.outlier_band_voxels * data.resolution_m;
    let typical_m = config
        .size_prior
        .typical_semi_axis_m
        .max(2.0 * data.resolution_m);
    let radius_ok =
        |r: f64| (0.5 * typical_m..=config.max_semi_axis_m.min(2.0 * typical_m)).contains(&r);
    let step = n.div_ceil(SEEDS).max(1);
    let mut best: Option<(f64, Superellipsoid)> = None;
    for seed in data.surface.iter().step_by(step) {
        let mut near: Vec<Point3<f64>> = data
            .surface
            .iter()
            .filter(|q| (*q - seed).norm() <= 2.0 * typical_m)
            .copied()
            .collect();
        let mut sphere = None;
        for _ in 0..=REFITS {
            let Some((centre, r)) = algebraic_sphere(&near).filter(|(_, r)| radius_ok(*r)) else {
                break;
            };
            sphere = Some((centre, r));
            near = within_band(&data.surface, &centre, r, band_m);
            if near.len() < 4 {
                break;
            }
        }
        let Some((centre, r)) = sphere else { continue };
        let score = support(data, &centre, r, band_m, config);
        if best.as_ref().is_none_or(|(s, _)| score > *s) {
            best = Some((score, Superellipsoid::sphere(centre, r)));
        }
    }
    let (score, sphere) = best?;
    (score >= MIN_SHARE * n as f64).then_some(sphere)
}

fn within_band(
    surface: &[Point3<f64>],
    centre: &Point3<f64>,
    r: f64,
    band_m: f64,
) -> Vec<Point3<f64>> {
    surface
        .iter()
        .filter(|q| ((*q - centre).norm() - r).abs() <= band_m)
        .copied()
        .collect()
}

/// Voxels within the band of the sphere's surface, less free voxels deep inside it.
fn support(data: &FitData, centre: &Point3<f64>, r: f64, band_m: f64, config: &FitConfig) -> f64 {
    let on_surface = within_band(&data.surface, centre, r, band_m).len();
    let depth_m = config.free_margin_voxels * data.resolution_m;
    let seen_through = data
        .free_around
        .iter()
        .filter(|f| r - (*f - centre).norm() > depth_m)
        .count();
    on_surface as f64 - seen_through as f64
}
