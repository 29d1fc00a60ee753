//! Collision primitives, distance queries and the voxel-occupancy hook.

use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// A static obstacle in the world frame (metres).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Obstacle {
    /// Segment `a`–`b` inflated by `radius_m` (poles, rails, stems).
    Capsule {
        a: Point3<f64>,
        b: Point3<f64>,
        radius_m: f64,
    },
    /// Oriented box: centre and axes from `world_from_box`, half sizes along its axes.
    Box {
        world_from_box: Isometry3<f64>,
        half_extents_m: Vector3<f64>,
    },
    /// Everything behind a plane: the solid is `(p - point) · outward_normal < 0` (floor:
    /// normal +z; ceiling: normal -z).
    HalfSpace {
        point: Point3<f64>,
        outward_normal: Vector3<f64>,
    },
}

impl Obstacle {
    /// All parameters finite, radii and half extents non-negative, normals non-zero.
    pub fn is_valid(&self) -> bool {
        let finite = |s: &[f64]| s.iter().all(|v| v.is_finite());
        match self {
            Obstacle::Capsule { a, b, radius_m } => {
                finite(a.coords.as_slice())
                    && finite(b.coords.as_slice())
                    && radius_m.is_finite()
                    && *radius_m >= 0.0
            }
            Obstacle::Box {
                world_from_box,
                half_extents_m,
            } => {
                finite(world_from_box.translation.vector.as_slice())
                    && finite(world_from_box.rotation.coords.as_slice())
                    && finite(half_extents_m.as_slice())
                    && half_extents_m.iter().all(|h| *h >= 0.0)
            }
            Obstacle::HalfSpace {
                point,
                outward_normal,
            } => {
                finite(point.coords.as_slice())
                    && finite(outward_normal.as_slice())
                    && outward_normal.norm() > 1e-12
            }
        }
    }

    /// Does the capsule (segment `a`–`b`, radius `radius`) overlap this obstacle?
    pub fn intersects_capsule(&self, a: &Point3<f64>, b: &Point3<f64>, radius: f64) -> bool {
        match self {
            Obstacle::Capsule {
                a: oa,
                b: ob,
                radius_m,
            } => {
                let d = min_along_segment(a, b, |p| point_segment_distance(p, oa, ob));
                d <= radius + radius_m
            }
            Obstacle::Box {
                world_from_box,
                half_extents_m,
            } => {
                let inv = world_from_box.inverse();
                let la = inv * a;
                let lb = inv * b;
                let d = min_along_segment(&la, &lb, |p| point_box_distance(p, half_extents_m));
                d <= radius
            }
            Obstacle::HalfSpace {
                point,
                outward_normal,
            } => {
                let n = outward_normal.normalize();
                let da = (a - point).dot(&n);
                let db = (b - point).dot(&n);
                da.min(db) < radius
            }
        }
    }
}

/// "Is this point inside an occupied voxel?" — the hook to a voxel map, so this crate does not
/// depend on one. Implemented for every `Fn(Point3<f64>) -> bool`.
pub trait OccupancyQuery {
    fn is_occupied(&self, p: Point3<f64>) -> bool;
}

impl<F: Fn(Point3<f64>) -> bool> OccupancyQuery for F {
    fn is_occupied(&self, p: Point3<f64>) -> bool {
        self(p)
    }
}

/// What the arm is checked against: static obstacles, optionally a voxel map, and a safety margin
/// added to every link radius.
#[derive(Clone, Copy)]
pub struct CollisionWorld<'a> {
    pub obstacles: &'a [Obstacle],
    /// Occupied-voxel query and the voxel edge length (metres, at least
    /// [`crate::MIN_VOXEL_RESOLUTION_M`]) used as the sampling step: every link capsule is filled
    /// with a lattice of points at most that far apart and each is queried, so a voxel that only
    /// grazes a capsule's surface can be missed; add a margin for clearance.
    pub voxels: Option<(&'a dyn OccupancyQuery, f64)>,
    pub margin_m: f64,
}

impl<'a> CollisionWorld<'a> {
    /// Obstacles only, no margin.
    pub fn obstacles(obstacles: &'a [Obstacle]) -> Self {
        Self {
            obstacles,
            voxels: None,
            margin_m: 0.0,
        }
    }

    /// Adds a voxel map sampled at `resolution_m`.
    pub fn with_voxels(mut self, occupancy: &'a dyn OccupancyQuery, resolution_m: f64) -> Self {
        self.voxels = Some((occupancy, resolution_m));
        self
    }

    /// Sets the margin added to every link radius (at most [`crate::MAX_MARGIN_M`]).
    pub fn with_margin(mut self, margin_m: f64) -> Self {
        self.margin_m = margin_m;
        self
    }
}

/// A link capsule in the world frame.
#[derive(Clone, Debug, PartialEq)]
pub struct WorldCapsule {
    /// Index into [`crate::ArmModel::links`].
    pub link: usize,
    pub a: Point3<f64>,
    pub b: Point3<f64>,
    pub radius_m: f64,
}

/// What a link touched.
#[derive(Clone, Debug, PartialEq)]
pub enum ContactWith {
    /// Index into [`CollisionWorld::obstacles`].
    Obstacle(usize),
    /// A sample point of the link that lies in an occupied voxel.
    Voxel(Point3<f64>),
}

/// A collision of one link.
#[derive(Clone, Debug, PartialEq)]
pub struct Contact {
    /// Index into [`crate::ArmModel::links`].
    pub link: usize,
    pub link_name: String,
    pub with: ContactWith,
}

/// The first collision along a joint-space path.
#[derive(Clone, Debug, PartialEq)]
pub struct PathContact {
    /// Path parameter in `[0, 1]` of the colliding sample.
    pub fraction: f64,
    pub joints: crate::JointVector,
    pub contact: Contact,
}

/// Distance from `p` to the segment `a`–`b`.
pub(crate) fn point_segment_distance(p: &Point3<f64>, a: &Point3<f64>, b: &Point3<f64>) -> f64 {
    let ab = b - a;
    let len2 = ab.norm_squared();
    let t = if len2 > 0.0 {
        ((p - a).dot(&ab) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (p - (a + ab * t)).norm()
}

/// Distance from `p` (box frame) to the box `[-h, h]` (0 inside).
fn point_box_distance(p: &Point3<f64>, h: &Vector3<f64>) -> f64 {
    let d = Vector3::new(
        (p.x.abs() - h.x).max(0.0),
        (p.y.abs() - h.y).max(0.0),
        (p.z.abs() - h.z).max(0.0),
    );
    d.norm()
}

/// Minimum of a convex function of the point along segment `a`–`b` (golden-section search; the
/// distance to a convex set is convex along a segment).
fn min_along_segment(a: &Point3<f64>, b: &Point3<f64>, f: impl Fn(&Point3<f64>) -> f64) -> f64 {
    let at = |t: f64| f(&(a + (b - a) * t));
    let inv_phi = (5f64.sqrt() - 1.0) / 2.0;
    let (mut lo, mut hi) = (0.0_f64, 1.0_f64);
    let mut x1 = hi - inv_phi * (hi - lo);
    let mut x2 = lo + inv_phi * (hi - lo);
    let mut f1 = at(x1);
    let mut f2 = at(x2);
    for _ in 0..80 {
        if f1 <= f2 {
            hi = x2;
            x2 = x1;
            f2 = f1;
            x1 = hi - inv_phi * (hi - lo);
            f1 = at(x1);
        } else {
            lo = x1;
            x1 = x2;
            f1 = f2;
            x2 = lo + inv_phi * (hi - lo);
            f2 = at(x2);
        }
    }
    at(0.0).min(at(1.0)).min(f1).min(f2)
}

/// Sample points filling the capsule: a lattice with spacing at most `step` along the axis and
/// across it, kept where within `radius` of the segment. Calls `visit` until it returns true.
pub(crate) fn capsule_samples_any(
    a: &Point3<f64>,
    b: &Point3<f64>,
    radius: f64,
    step: f64,
    mut visit: impl FnMut(Point3<f64>) -> bool,
) -> Option<Point3<f64>> {
    let axis = b - a;
    let len = axis.norm();
    let u = if len > 1e-12 {
        axis / len
    } else {
        Vector3::z()
    };
    let helper = if u.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let v = u.cross(&helper).normalize();
    let w = u.cross(&v);
    let span = len + 2.0 * radius;
    let n_axial = (span / step).ceil().max(1.0) as usize;
    let m = (radius / step).ceil() as i64;
    let cross_step = if m > 0 { radius / m as f64 } else { 0.0 };
    for i in 0..=n_axial {
        let s = -radius + span * i as f64 / n_axial as f64;
        for j in -m..=m {
            for k in -m..=m {
                let p = a + u * s + v * (j as f64 * cross_step) + w * (k as f64 * cross_step);
                if point_segment_distance(&p, a, b) <= radius + 1e-12 && visit(p) {
                    return Some(p);
                }
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capsule_box_and_half_space_distances() {
        let pole = Obstacle::Capsule {
            a: Point3::new(0.0, 0.0, 0.0),
            b: Point3::new(0.0, 0.0, 1.0),
            radius_m: 0.05,
        };
        // Horizontal capsule passing 0.1 m from the pole axis: touches with radius 0.06, not 0.04.
        let a = Point3::new(-1.0, 0.1, 0.5);
        let b = Point3::new(1.0, 0.1, 0.5);
        assert!(pole.intersects_capsule(&a, &b, 0.06));
        assert!(!pole.intersects_capsule(&a, &b, 0.04));
        let boxed = Obstacle::Box {
            world_from_box: Isometry3::translation(0.0, 0.0, 1.0),
            half_extents_m: Vector3::new(0.5, 0.5, 0.5),
        };
        assert!(boxed.intersects_capsule(
            &Point3::new(0.0, 0.0, 1.6),
            &Point3::new(0.0, 0.0, 2.0),
            0.11
        ));
        assert!(!boxed.intersects_capsule(
            &Point3::new(0.0, 0.0, 1.6),
            &Point3::new(0.0, 0.0, 2.0),
            0.09
        ));
        let floor = Obstacle::HalfSpace {
            point: Point3::origin(),
            outward_normal: Vector3::z(),
        };
        assert!(floor.intersects_capsule(
            &Point3::new(0.0, 0.0, 0.03),
            &Point3::new(1.0, 0.0, 1.0),
            0.05
        ));
        assert!(!floor.intersects_capsule(
            &Point3::new(0.0, 0.0, 0.06),
            &Point3::new(1.0, 0.0, 1.0),
            0.05
        ));
    }

    #[test]
    fn capsule_samples_fill_the_capsule() {
        let a = Point3::new(0.0, 0.0, 0.0);
        let b = Point3::new(0.3, 0.1, 0.0);
        let mut count = 0;
        let mut far = 0;
        capsule_samples_any(&a, &b, 0.05, 0.01, |p| {
            count += 1;
            if point_segment_distance(&p, &a, &b) > 0.05 + 1e-9 {
                far += 1;
            }
            false
        });
        assert_eq!(far, 0);
        // Volume / step³ is about 2.9e3 points.
        assert!(count > 1500, "{count}");
        // A point near the surface is found.
        let hit = capsule_samples_any(&a, &b, 0.05, 0.01, |p| p.z > 0.045);
        assert!(hit.is_some());
    }
}
