//! Shared geometry for Glasshouse: camera intrinsics, boxes, poses in named frames, and the one
//! fruit estimate with its covered-volume rule ([`fruit`]), observed colour ([`colour`]).
//!
//! Conventions used by every crate:
//! - The world frame is right-handed with `z` up; lengths are metres.
//! - The camera frame is the optical frame: `x` right, `y` down, `z` forward (along the optical axis).
//! - A pose named `world_from_camera` maps a point in the camera frame to the world frame, so
//!   `world_from_camera * point_in_camera` reads right to left.

pub mod colour;
pub mod fruit;

use nalgebra::{Isometry3, Point3, Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

pub use colour::{Rgb, RgbSum};
pub use fruit::{
    box_voxel_keys, covered_volume, volume_change_m3, FruitEstimate, FruitSolid, FruitSurface,
    SolidKind,
};

/// Pinhole intrinsics of a depth/colour camera, in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraIntrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl CameraIntrinsics {
    /// Square-pixel intrinsics with the principal point at the image centre, from a horizontal
    /// field of view in radians.
    pub fn from_horizontal_fov(width: u32, height: u32, horizontal_fov_rad: f64) -> Self {
        let fx = (width as f64 / 2.0) / (horizontal_fov_rad / 2.0).tan();
        Self {
            width,
            height,
            fx,
            fy: fx,
            cx: (width as f64 - 1.0) / 2.0,
            cy: (height as f64 - 1.0) / 2.0,
        }
    }

    /// Number of pixels.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Horizontal field of view in radians.
    pub fn horizontal_fov_rad(&self) -> f64 {
        2.0 * ((self.width as f64 / 2.0) / self.fx).atan()
    }

    /// Vertical field of view in radians.
    pub fn vertical_fov_rad(&self) -> f64 {
        2.0 * ((self.height as f64 / 2.0) / self.fy).atan()
    }

    /// True when every value is finite and positive where it must be.
    pub fn is_valid(&self) -> bool {
        self.width > 0
            && self.height > 0
            && self.fx.is_finite()
            && self.fy.is_finite()
            && self.cx.is_finite()
            && self.cy.is_finite()
            && self.fx > 0.0
            && self.fy > 0.0
    }

    /// The point in the camera frame seen at pixel (u, v) at depth `depth_m` along the optical axis.
    pub fn backproject(&self, u: f64, v: f64, depth_m: f64) -> Point3<f64> {
        Point3::new(
            (u - self.cx) * depth_m / self.fx,
            (v - self.cy) * depth_m / self.fy,
            depth_m,
        )
    }

    /// Unit ray direction in the camera frame through pixel (u, v).
    pub fn ray_direction(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0).normalize()
    }
}

/// Axis-aligned box in the world frame, metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: Point3<f64>,
    pub max: Point3<f64>,
}

impl Aabb {
    pub fn new(min: Point3<f64>, max: Point3<f64>) -> Self {
        Self { min, max }
    }

    pub fn contains(&self, p: &Point3<f64>) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }

    pub fn centre(&self) -> Point3<f64> {
        nalgebra::center(&self.min, &self.max)
    }

    pub fn size(&self) -> Vector3<f64> {
        self.max - self.min
    }

    pub fn volume_m3(&self) -> f64 {
        let s = self.size();
        s.x.max(0.0) * s.y.max(0.0) * s.z.max(0.0)
    }

    /// Box grown by `margin_m` on every side.
    pub fn inflated(&self, margin_m: f64) -> Self {
        let m = Vector3::repeat(margin_m);
        Self::new(self.min - m, self.max + m)
    }

    /// Smallest box holding both.
    pub fn union(&self, other: &Aabb) -> Self {
        Self::new(self.min.inf(&other.min), self.max.sup(&other.max))
    }
}

/// Camera pose at `eye_in_world` looking at `target_in_world`, with the image `x` axis kept
/// horizontal (no roll). Falls back to a fixed right vector when looking straight up or down.
pub fn look_at(eye_in_world: &Point3<f64>, target_in_world: &Point3<f64>) -> Isometry3<f64> {
    let forward = (target_in_world - eye_in_world)
        .try_normalize(1e-12)
        .unwrap_or_else(Vector3::x);
    look_along(eye_in_world, &forward)
}

/// Camera pose at `eye_in_world` whose optical axis points along `forward_in_world`.
pub fn look_along(eye_in_world: &Point3<f64>, forward_in_world: &Vector3<f64>) -> Isometry3<f64> {
    let z = forward_in_world
        .try_normalize(1e-12)
        .unwrap_or_else(Vector3::x);
    let up = Vector3::z();
    let x = z
        .cross(&up)
        .try_normalize(1e-9)
        .unwrap_or_else(|| Vector3::y().cross(&z).normalize());
    let y = z.cross(&x);
    let rotation = Rotation3::from_basis_unchecked(&[x, y, z]);
    Isometry3::from_parts(
        eye_in_world.coords.into(),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

/// The optical axis (camera `z`) of a pose, in the world frame.
pub fn optical_axis(world_from_camera: &Isometry3<f64>) -> Vector3<f64> {
    world_from_camera.rotation * Vector3::z()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_points_optical_axis_at_target() {
        let eye = Point3::new(1.0, 2.0, 0.5);
        let target = Point3::new(0.0, 0.0, 1.0);
        let pose = look_at(&eye, &target);
        let axis = optical_axis(&pose);
        let expected = (target - eye).normalize();
        assert!((axis - expected).norm() < 1e-9);
        // Image x stays horizontal: no roll.
        let right = pose.rotation * Vector3::x();
        assert!(right.z.abs() < 1e-9);
        // Image y points downwards-ish (camera upright).
        let down = pose.rotation * Vector3::y();
        assert!(down.z < 0.0);
    }

    #[test]
    fn look_straight_down_is_finite() {
        let pose = look_at(&Point3::new(0.0, 0.0, 2.0), &Point3::origin());
        assert!((optical_axis(&pose) + Vector3::z()).norm() < 1e-9);
        assert!(pose.rotation.coords.iter().all(|c| c.is_finite()));
    }

    #[test]
    fn backproject_inverts_projection() {
        let k = CameraIntrinsics::from_horizontal_fov(640, 480, 80f64.to_radians());
        let p = k.backproject(100.0, 50.0, 2.0);
        let u = k.fx * p.x / p.z + k.cx;
        let v = k.fy * p.y / p.z + k.cy;
        assert!((u - 100.0).abs() < 1e-9 && (v - 50.0).abs() < 1e-9);
        assert!((k.horizontal_fov_rad() - 80f64.to_radians()).abs() < 1e-9);
    }
}
