//! Synthetic bodies for tests: capsicums made of lobes, boxes (clips, labels) and cylinders
//! (stems), each answering the first hit of a ray.

use nalgebra::{Point3, Rotation3, Unit, Vector3};

use crate::fit::tests_support::hit_ellipsoid;

/// One lobe: an ellipsoid with its own orientation.
#[derive(Clone, Copy, Debug)]
pub struct Lobe {
    pub centre: Point3<f64>,
    pub world_from_lobe: Rotation3<f64>,
    pub semi_axes_m: Vector3<f64>,
}

impl Lobe {
    pub fn hit(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
        let o = Point3::from(
            self.world_from_lobe
                .inverse_transform_vector(&(o - self.centre)),
        );
        let d = self.world_from_lobe.inverse_transform_vector(d);
        hit_ellipsoid(&o, &d, &Point3::origin(), &self.semi_axes_m)
    }

    pub fn holds(&self, q: &Point3<f64>) -> bool {
        let x = self
            .world_from_lobe
            .inverse_transform_vector(&(q - self.centre));
        x.component_div(&self.semi_axes_m).norm_squared() <= 1.0
    }
}

/// A capsicum: `lobes` ellipsoids around an axis tilted `tilt_deg` from vertical, each 1.5 cm
/// off the axis and leaning out at the top, so that they converge to a tip at the bottom.
pub fn capsicum(
    centre: Point3<f64>,
    lobes: usize,
    tilt_deg: f64,
    lobe_m: Vector3<f64>,
) -> Vec<Lobe> {
    let tilt = Rotation3::from_axis_angle(
        &Unit::new_normalize(Vector3::new(1.0, 0.4, 0.0)),
        tilt_deg.to_radians(),
    );
    let up = tilt * Vector3::z();
    (0..lobes)
        .map(|k| {
            let angle = 0.4 + std::f64::consts::TAU * k as f64 / lobes as f64;
            let radial = tilt * Vector3::new(angle.cos(), angle.sin(), 0.0);
            let lean = Rotation3::from_axis_angle(
                &Unit::new_normalize(up.cross(&radial)),
                12f64.to_radians(),
            );
            Lobe {
                centre: centre + radial * 0.015 + up * 0.004,
                world_from_lobe: lean * tilt,
                semi_axes_m: lobe_m,
            }
        })
        .collect()
}

/// The first hit of a ray on any lobe.
pub fn first_hit(body: &[Lobe], o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
    body.iter()
        .filter_map(|l| l.hit(o, d))
        .min_by(f64::total_cmp)
}

/// A box with half-sizes `half_m` along the axes of `world_from_box`.
#[derive(Clone, Copy, Debug)]
pub struct Cuboid {
    pub centre: Point3<f64>,
    pub world_from_box: Rotation3<f64>,
    pub half_m: Vector3<f64>,
}

impl Cuboid {
    /// Slab test in the box frame.
    pub fn hit(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
        let o = self
            .world_from_box
            .inverse_transform_vector(&(o - self.centre));
        let d = self.world_from_box.inverse_transform_vector(d);
        let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
        for i in 0..3 {
            if d[i].abs() < 1e-12 {
                if o[i].abs() > self.half_m[i] {
                    return None;
                }
                continue;
            }
            let (a, b) = (
                (-self.half_m[i] - o[i]) / d[i],
                (self.half_m[i] - o[i]) / d[i],
            );
            near = near.max(a.min(b));
            far = far.min(a.max(b));
        }
        (near <= far && near > 0.0).then_some(near)
    }
}

/// A closed cylinder of `radius_m` and `length_m` along the z axis of `world_from_cylinder`.
#[derive(Clone, Copy, Debug)]
pub struct Cylinder {
    pub centre: Point3<f64>,
    pub world_from_cylinder: Rotation3<f64>,
    pub radius_m: f64,
    pub length_m: f64,
}

impl Cylinder {
    pub fn hit(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
        let o = self
            .world_from_cylinder
            .inverse_transform_vector(&(o - self.centre));
        let d = self.world_from_cylinder.inverse_transform_vector(d);
        let half = self.length_m / 2.0;
        let mut best: Option<f64> = None;
        let mut consider = |t: f64, ok: bool| {
            if ok && t > 0.0 && best.is_none_or(|b| t < b) {
                best = Some(t);
            }
        };
        let a = d.x * d.x + d.y * d.y;
        if a > 1e-12 {
            let b = 2.0 * (o.x * d.x + o.y * d.y);
            let c = o.x * o.x + o.y * o.y - self.radius_m * self.radius_m;
            let disc = b * b - 4.0 * a * c;
            if disc >= 0.0 {
                let t = (-b - disc.sqrt()) / (2.0 * a);
                consider(t, (o.z + t * d.z).abs() <= half);
            }
        }
        if d.z.abs() > 1e-12 {
            for cap in [-half, half] {
                let t = (cap - o.z) / d.z;
                let (x, y) = (o.x + t * d.x, o.y + t * d.y);
                consider(t, x * x + y * y <= self.radius_m * self.radius_m);
            }
        }
        best
    }
}

/// A rotation of `angle_deg` about `axis`.
pub fn turn(axis: Vector3<f64>, angle_deg: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Unit::new_normalize(axis), angle_deg.to_radians())
}
