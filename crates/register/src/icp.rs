//! Point-to-plane ICP of the subsampled scan against the map's surface, and the checks on its
//! result.

use glasshouse_roimap::RoiMap;
use nalgebra::{
    Isometry3, Matrix6, Point3, SymmetricEigen, Translation3, UnitQuaternion, Vector3, Vector6,
};

use crate::surface::{Plane, Probe, Surface};
use crate::{Aligned, Alignment, KeptAsSent, RegisterSettings, RejectReason, SkipReason};

/// Slack on "the residual RMS did not grow": the Huber fit and the truncated RMS weigh
/// residuals differently, so a sound alignment may raise the RMS by a hair.
const RMS_SLACK_M: f64 = 1e-4;

/// One registration: the scan's subsample, the map's surface and the settings.
pub(crate) struct Registration<'a> {
    surface: Surface<'a>,
    sample: &'a [Point3<f64>],
    sensor_origin: Point3<f64>,
    /// The sample's centroid as sent: the rotation centre (best conditioned).
    centroid: Point3<f64>,
    /// RMS distance of the sample's points from its centroid: how far a rotation reaches.
    lever_m: f64,
    settings: &'a RegisterSettings,
}

/// How the scan's points relate to the map at one pose.
#[derive(Clone, Copy)]
struct Overlap {
    near_surface: usize,
    /// Points in known free space or behind known surface.
    contradicting: usize,
}

impl Overlap {
    fn of(probes: &[Probe]) -> Self {
        let count = |f: fn(&Probe) -> bool| probes.iter().filter(|p| f(p)).count();
        Self {
            near_surface: count(|p| matches!(p, Probe::Surface(_))),
            contradicting: count(Probe::contradicts_map),
        }
    }
}

/// How well the scan fits the map at one pose.
#[derive(Clone, Copy)]
struct Fit {
    inliers: usize,
    inlier_share: f64,
    /// Points near surface and points where the map saw through.
    overlap: Overlap,
}

impl Fit {
    /// Share of the points the map has an opinion on that it contradicts.
    fn contradicting_share(&self) -> f64 {
        let opinions = self.overlap.near_surface + self.overlap.contradicting;
        self.overlap.contradicting as f64 / opinions.max(1) as f64
    }
}

/// What the iterations reached.
struct Solution {
    world_correction: Isometry3<f64>,
    iterations: usize,
    /// How far the last step moved the scan at most.
    last_step_m: f64,
    unconstrained_directions: usize,
}

impl<'a> Registration<'a> {
    pub fn new(
        map: &'a RoiMap,
        sample: &'a [Point3<f64>],
        sensor_origin: &Point3<f64>,
        settings: &'a RegisterSettings,
    ) -> Self {
        let sum = sample.iter().fold(Vector3::zeros(), |s, p| s + p.coords);
        let centroid = Point3::from(sum / sample.len().max(1) as f64);
        let spread_sq = sample
            .iter()
            .map(|p| (p - centroid).norm_squared())
            .sum::<f64>();
        let lever_m = (spread_sq / sample.len().max(1) as f64).sqrt().max(1e-3);
        Self {
            surface: Surface::new(map, sample, settings),
            sample,
            sensor_origin: *sensor_origin,
            centroid,
            lever_m,
            settings,
        }
    }

    pub fn run(mut self) -> Alignment {
        let identity = Isometry3::identity();
        let initial = self.classify_all(&identity);
        if let Some(outcome) = self.little_overlap(Overlap::of(&initial)) {
            return outcome;
        }
        // Points with no surface near at the start stay out of the iterations: the correction
        // is small, so they would not find any, and their search is the costliest.
        let active: Vec<usize> = (0..initial.len())
            .filter(|&i| matches!(initial[i], Probe::Surface(_) | Probe::Ambiguous))
            .collect();
        let solution = self.iterate(&active, &initial);
        let last = self.classify_all(&solution.world_correction);
        // The residual is watched on the points that saw surface before the alignment and do
        // not end next to an edge after it (whose plane the map cannot tell).
        let watched: Vec<usize> = (0..initial.len())
            .filter(|&i| matches!(initial[i], Probe::Surface(_)))
            .filter(|&i| !matches!(last[i], Probe::Ambiguous))
            .collect();
        let rms = (
            self.truncated_rms(&initial, &watched, &identity),
            self.truncated_rms(&last, &watched, &solution.world_correction),
        );
        let as_sent = self.fit(&identity, &initial);
        let estimate = self.fit(&solution.world_correction, &last);
        self.judge(&solution, rms, as_sent, estimate)
    }

    /// With too little surface to align to: rejected when the points the map contradicts
    /// outnumber those near its surface (unknown space says nothing), else new ground.
    fn little_overlap(&self, overlap: Overlap) -> Option<Alignment> {
        let s = self.settings;
        let Overlap {
            near_surface,
            contradicting,
        } = overlap;
        if near_surface >= s.min_inliers {
            return None;
        }
        if contradicting >= s.min_contradicting_points && contradicting > near_surface {
            return Some(Alignment::Rejected(RejectReason::ContradictsMap {
                near_surface,
                contradicting,
            }));
        }
        Some(Alignment::Skipped(SkipReason::NewGround { near_surface }))
    }

    /// Inliers at `world_correction`, and their share of the points the map has an opinion on.
    fn fit(&self, world_correction: &Isometry3<f64>, probes: &[Probe]) -> Fit {
        let inlier_m = self.settings.inlier_m;
        let is_inlier = |(p, probe): (&Point3<f64>, &Probe)| match probe {
            Probe::Surface(plane) => plane.residual_m(&(world_correction * p)).abs() <= inlier_m,
            _ => false,
        };
        let inliers = self
            .sample
            .iter()
            .zip(probes)
            .filter(|&pair| is_inlier(pair))
            .count();
        let overlap = Overlap::of(probes);
        let opinions = overlap.near_surface + overlap.contradicting;
        Fit {
            inliers,
            inlier_share: inliers as f64 / opinions.max(1) as f64,
            overlap,
        }
    }

    /// The near surface ([`Surface::near_surface`]) of the sample points `indices` moved by
    /// `world_correction`.
    fn pair_some(&mut self, indices: &[usize], world_correction: &Isometry3<f64>) -> Vec<Probe> {
        let sample = self.sample;
        let pair = |plane: Option<Plane>| plane.map_or(Probe::Unknown, Probe::Surface);
        indices
            .iter()
            .map(|&i| pair(self.surface.near_surface(&(world_correction * sample[i]))))
            .collect()
    }

    /// What the map says about every sample point moved by `world_correction`, telling also
    /// which points in unknown space lie behind known surface as seen from the (moved) sensor.
    fn classify_all(&mut self, world_correction: &Isometry3<f64>) -> Vec<Probe> {
        let sensor = world_correction * self.sensor_origin;
        let sample = self.sample;
        sample
            .iter()
            .map(|p| self.surface.classify(&(world_correction * p), &sensor))
            .collect()
    }

    /// RMS of the watched points' residuals at `world_correction`, each capped at `inlier_m`
    /// (a point that lost its surface counts the cap): comparable across poses, and not swayed
    /// by points paired with some other surface.
    fn truncated_rms(
        &self,
        probes: &[Probe],
        watched: &[usize],
        world_correction: &Isometry3<f64>,
    ) -> f64 {
        let cap = self.settings.inlier_m;
        let sum: f64 = watched
            .iter()
            .map(|&i| match &probes[i] {
                Probe::Surface(plane) => {
                    let r = plane.residual_m(&(world_correction * self.sample[i])).abs();
                    r.min(cap).powi(2)
                }
                _ => cap * cap,
            })
            .sum();
        (sum / watched.len().max(1) as f64).sqrt()
    }

    /// Gauss-Newton steps on the linearised point-to-plane cost, re-associating each time.
    fn iterate(&mut self, active: &[usize], initial: &[Probe]) -> Solution {
        let mut solution = Solution {
            world_correction: Isometry3::identity(),
            iterations: 0,
            last_step_m: 0.0,
            unconstrained_directions: 0,
        };
        let mut probes: Vec<Probe> = active.iter().map(|&i| initial[i]).collect();
        for iteration in 1..=self.settings.max_iterations {
            if iteration > 1 {
                probes = self.pair_some(active, &solution.world_correction);
            }
            let centre = solution.world_correction * self.centroid;
            let pairs = (active, probes.as_slice());
            let Some(system) = self.normal_equations(pairs, &solution.world_correction, &centre)
            else {
                break;
            };
            let (step, unconstrained) = system.solve(self.settings.degenerate_eigen_ratio);
            solution.iterations = iteration;
            solution.unconstrained_directions = unconstrained;
            let increment = about(&centre, &step);
            solution.world_correction = increment * solution.world_correction;
            solution.last_step_m = step_shift_m(&step, system.lever_m * 3.0);
            if solution.last_step_m < self.settings.converged_shift_m {
                break;
            }
        }
        solution
    }

    /// The Huber-weighted normal equations at the current pose of the sample points `indices`
    /// and their probes; None with too few pairs.
    fn normal_equations(
        &self,
        (indices, probes): (&[usize], &[Probe]),
        world_correction: &Isometry3<f64>,
        centre: &Point3<f64>,
    ) -> Option<NormalEquations> {
        let mut system = NormalEquations::default();
        for (&i, probe) in indices.iter().zip(probes) {
            let p = &self.sample[i];
            let Probe::Surface(plane) = probe else {
                continue;
            };
            let moved = world_correction * p;
            let r = plane.residual_m(&moved);
            let w = huber_weight(r, self.settings.huber_m);
            let arm = moved - centre;
            let row = Vector6::from_iterator(
                arm.cross(&plane.normal)
                    .iter()
                    .chain(plane.normal.iter())
                    .copied(),
            );
            system.h += row * row.transpose() * w;
            system.g += row * (w * r);
            system.pairs += 1;
        }
        if system.pairs < 6 {
            return None;
        }
        system.lever_m = self.lever_m;
        Some(system)
    }

    /// The checks of the crate docs on the estimate. A failed estimate still lets the scan in
    /// as sent when the map does not contradict the scan as sent (ICP wandered on weak
    /// geometry, but nothing speaks against the scan); a passed one too small to tell is not
    /// applied.
    fn judge(
        &self,
        solution: &Solution,
        (rms_before_m, rms_after_m): (f64, f64),
        as_sent: Fit,
        estimate: Fit,
    ) -> Alignment {
        let s = self.settings;
        let correction = &solution.world_correction;
        let max_point_shift_m = self
            .sample
            .iter()
            .map(|p| (correction * p - p).norm())
            .fold(0.0, f64::max);
        let below_resolution = max_point_shift_m < s.min_applied_shift_m
            || rms_before_m - rms_after_m < s.min_rms_gain_m;
        let (kept_as_sent, fit) = match self.check(solution, (rms_before_m, rms_after_m), estimate)
        {
            Ok(()) if below_resolution => (Some(KeptAsSent::BelowResolution), as_sent),
            Ok(()) => (None, estimate),
            Err(reason) if self.consistent(&as_sent) => {
                (Some(KeptAsSent::EstimateFailed(reason)), as_sent)
            }
            Err(reason) => return Alignment::Rejected(reason),
        };
        Alignment::Aligned(Aligned {
            world_correction: *correction,
            kept_as_sent,
            rotation_deg: correction.rotation.angle().to_degrees(),
            sensor_shift_m: (correction * self.sensor_origin - self.sensor_origin).norm(),
            max_point_shift_m,
            rms_before_m,
            rms_after_m,
            inliers: fit.inliers,
            inlier_share: fit.inlier_share,
            unconstrained_directions: solution.unconstrained_directions,
            iterations: solution.iterations,
        })
    }

    /// Whether the map contradicts few enough of the points at this pose.
    fn consistent(&self, fit: &Fit) -> bool {
        fit.contradicting_share() <= self.settings.max_contradicting_share
    }

    /// The first check the estimate fails, if any.
    fn check(
        &self,
        solution: &Solution,
        (rms_before_m, rms_after_m): (f64, f64),
        fit: Fit,
    ) -> Result<(), RejectReason> {
        let s = self.settings;
        let correction = &solution.world_correction;
        let unconstrained_directions = solution.unconstrained_directions;
        if unconstrained_directions > s.max_degenerate_directions {
            return Err(RejectReason::Degenerate {
                unconstrained_directions,
            });
        }
        if solution.last_step_m >= s.converged_shift_m {
            let last_step_m = solution.last_step_m;
            return Err(RejectReason::NotConverged { last_step_m });
        }
        let rotation_deg = correction.rotation.angle().to_degrees();
        let sensor_shift_m = (correction * self.sensor_origin - self.sensor_origin).norm();
        if rotation_deg > s.max_rotation_deg || sensor_shift_m > s.max_sensor_shift_m {
            return Err(RejectReason::CorrectionTooLarge {
                rotation_deg,
                sensor_shift_m,
            });
        }
        if !self.consistent(&fit) {
            return Err(RejectReason::ContradictsMap {
                near_surface: fit.overlap.near_surface,
                contradicting: fit.overlap.contradicting,
            });
        }
        if fit.inliers < s.min_inliers {
            return Err(RejectReason::TooFewInliers {
                inliers: fit.inliers,
            });
        }
        if fit.inlier_share < s.min_inlier_share {
            return Err(RejectReason::LowInlierShare {
                inlier_share: fit.inlier_share,
            });
        }
        if rms_after_m > rms_before_m + RMS_SLACK_M {
            return Err(RejectReason::RmsNotImproved {
                rms_before_m,
                rms_after_m,
            });
        }
        Ok(())
    }
}

/// `Σ w JᵀJ` and `Σ w Jᵀr` of the pairs, unknowns `(ω, t)`: a small rotation `ω` (rad) about
/// the scan's centre, then a translation `t` (m).
#[derive(Default)]
struct NormalEquations {
    h: Matrix6<f64>,
    g: Vector6<f64>,
    pairs: usize,
    /// RMS distance of the sample's points from the rotation centre: how far a rotation
    /// reaches.
    lever_m: f64,
}

impl NormalEquations {
    /// The step `(ω, t)` minimising the linearised cost, and how many directions were left out.
    /// Rotations are scaled by the lever (how far they move the points) so that both kinds of
    /// unknowns compare; a direction with an eigenvalue below `ratio` of the largest is not
    /// constrained by the geometry (a plane's in-plane moves) and gets no step.
    fn solve(&self, ratio: f64) -> (Vector6<f64>, usize) {
        let l = 1.0 / self.lever_m;
        let scale = Matrix6::from_diagonal(&Vector6::new(l, l, l, 1.0, 1.0, 1.0));
        let eigen = SymmetricEigen::new(scale * self.h * scale);
        let largest = eigen.eigenvalues.max();
        if !largest.is_finite() || largest <= 0.0 {
            return (Vector6::zeros(), 6);
        }
        let g = scale * self.g;
        let mut step = Vector6::zeros();
        let mut unconstrained = 0;
        for (i, &lambda) in eigen.eigenvalues.iter().enumerate() {
            if lambda < ratio * largest {
                unconstrained += 1;
                continue;
            }
            let v = eigen.eigenvectors.column(i);
            step -= v * (v.dot(&g) / lambda);
        }
        (scale * step, unconstrained)
    }
}

/// Huber weight of a residual: 1 within `delta`, falling as `delta / |r|` beyond.
fn huber_weight(r: f64, delta: f64) -> f64 {
    let a = r.abs();
    if a <= delta {
        1.0
    } else {
        delta / a
    }
}

/// The move `p ↦ R(ω)(p − centre) + centre + t` of a step `(ω, t)`.
fn about(centre: &Point3<f64>, step: &Vector6<f64>) -> Isometry3<f64> {
    let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(step[0], step[1], step[2]));
    let t = Vector3::new(step[3], step[4], step[5]);
    let translation = centre.coords + t - rotation * centre.coords;
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

/// A bound on how far a step moves points within `reach_m` of the rotation centre.
fn step_shift_m(step: &Vector6<f64>, reach_m: f64) -> f64 {
    let rotation = Vector3::new(step[0], step[1], step[2]).norm();
    let translation = Vector3::new(step[3], step[4], step[5]).norm();
    translation + rotation * reach_m
}
