//! Motion time: per-axis trapezoidal velocity profiles, synchronised so that the slowest axis
//! decides, with the mount's axes moving in parallel with the arm.

use serde::{Deserialize, Serialize};

use crate::error::{ensure_finite, invalid, Result};
use crate::kinematics::{JointVector, JOINT_COUNT};
use crate::mount::{Mount, MountState};

/// Fixed time to capture one view once the camera has arrived, seconds; the caller adds it.
pub const CAPTURE_TIME_S: f64 = 0.5;

/// Speed and acceleration limits of one axis (rad/s and rad/s² for joints, m/s and m/s² for
/// mount axes).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisLimit {
    pub max_speed: f64,
    pub max_accel: f64,
}

impl AxisLimit {
    fn validate(&self) -> Result<()> {
        ensure_finite(&[self.max_speed, self.max_accel], "axis limit")?;
        if self.max_speed <= 0.0 || self.max_accel <= 0.0 {
            return Err(invalid("axis limit", "speed and acceleration must be > 0"));
        }
        Ok(())
    }

    /// Time to travel `distance` from rest to rest: a triangle profile
    /// `2·sqrt(d/a)` when the axis cannot reach full speed (`d ≤ v²/a`), else a trapezoid
    /// `d/v + v/a`.
    pub fn travel_time(&self, distance: f64) -> Result<f64> {
        self.validate()?;
        ensure_finite(&[distance], "travel distance")?;
        let d = distance.abs();
        let (v, a) = (self.max_speed, self.max_accel);
        Ok(if d <= v * v / a {
            2.0 * (d / a).sqrt()
        } else {
            d / v + v / a
        })
    }
}

/// Limits of the arm's joints and the mount's axes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MotionLimits {
    pub joints: [AxisLimit; JOINT_COUNT],
    /// The same limit for every mount axis (gantry x/y/extension, rail, lift).
    pub mount: AxisLimit,
}

impl Default for MotionLimits {
    /// UR5e: 180°/s on every joint (published), 4 rad/s² (a reasonable default); mount axes
    /// 0.5 m/s and 1 m/s².
    fn default() -> Self {
        Self {
            joints: [AxisLimit {
                max_speed: std::f64::consts::PI,
                max_accel: 4.0,
            }; JOINT_COUNT],
            mount: AxisLimit {
                max_speed: 0.5,
                max_accel: 1.0,
            },
        }
    }
}

impl MotionLimits {
    /// Time of a synchronised joint move: every joint follows its own rest-to-rest profile,
    /// stretched to the slowest one, so the move takes the longest single-joint time.
    pub fn joint_motion_time(&self, from: &JointVector, to: &JointVector) -> Result<f64> {
        ensure_finite(from, "joint vector")?;
        ensure_finite(to, "joint vector")?;
        let mut t: f64 = 0.0;
        for ((limit, a), b) in self.joints.iter().zip(from).zip(to) {
            t = t.max(limit.travel_time(b - a)?);
        }
        Ok(t)
    }

    /// Time of a mount move: every axis in parallel, the slowest decides.
    pub fn mount_motion_time(
        &self,
        mount: &Mount,
        from: &MountState,
        to: &MountState,
    ) -> Result<f64> {
        let mut t: f64 = 0.0;
        for d in mount.axis_distances(from, to)? {
            t = t.max(self.mount.travel_time(d)?);
        }
        Ok(t)
    }

    /// Time of a combined move, arm and mount in parallel (capture time not included, see
    /// [`CAPTURE_TIME_S`]).
    pub fn motion_time(
        &self,
        mount: &Mount,
        from: (&JointVector, &MountState),
        to: (&JointVector, &MountState),
    ) -> Result<f64> {
        let arm = self.joint_motion_time(from.0, to.0)?;
        let base = self.mount_motion_time(mount, from.1, to.1)?;
        Ok(arm.max(base))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn zero_motion_takes_no_time() {
        let limits = MotionLimits::default();
        let q = [0.3, -1.0, 2.0, 0.0, 1.0, -2.0];
        assert_eq!(limits.joint_motion_time(&q, &q).ok(), Some(0.0));
        let mount = Mount::scenario_two();
        let s = mount.default_state();
        assert_eq!(
            limits.motion_time(&mount, (&q, &s), (&q, &s)).ok(),
            Some(0.0)
        );
    }

    #[test]
    fn motion_time_is_symmetric_and_monotone() {
        let limits = MotionLimits::default();
        let a = [0.3, -1.0, 2.0, 0.0, 1.0, -2.0];
        let b = [-0.5, -0.2, 1.0, 0.7, 1.1, 2.5];
        let ab = limits.joint_motion_time(&a, &b).ok();
        let ba = limits.joint_motion_time(&b, &a).ok();
        assert!(ab.is_some() && ab == ba);
        let mut previous = -1.0;
        for i in 0..200 {
            let d = i as f64 * 0.05;
            let t = limits.joints[0].travel_time(d).unwrap_or(f64::NAN);
            assert!(t > previous, "not increasing at {d}: {t} <= {previous}");
            previous = t;
        }
    }

    #[test]
    fn triangle_and_trapezoid_profiles_match_hand_computed_values() {
        let limit = AxisLimit {
            max_speed: 2.0,
            max_accel: 4.0,
        };
        // v²/a = 1: below it a triangle, above it a trapezoid.
        // d = 0.25: 2·sqrt(0.25/4) = 0.5 s (peak speed 1 m/s at 0.25 s).
        assert!(close(limit.travel_time(0.25).unwrap_or(f64::NAN), 0.5));
        // d = 1: the boundary, both formulas give 1 s.
        assert!(close(limit.travel_time(1.0).unwrap_or(f64::NAN), 1.0));
        // d = 3: 0.5 s ramp up (0.5 m), 1 s cruise (2 m), 0.5 s ramp down (0.5 m) = 2 s.
        assert!(close(limit.travel_time(3.0).unwrap_or(f64::NAN), 2.0));
        // UR5e defaults: π rad/s, 4 rad/s²; a π rad move: π/π + π/4 = 1 + π/4.
        let ur = MotionLimits::default();
        let t = ur
            .joint_motion_time(&[0.0; 6], &[0.0, 0.0, std::f64::consts::PI, 0.0, 0.0, 0.0])
            .unwrap_or(f64::NAN);
        assert!(close(t, 1.0 + std::f64::consts::PI / 4.0));
        // Mount: 2 m on the rail at 0.5 m/s, 1 m/s²: 2/0.5 + 0.5 = 4.5 s; the lift (0.1 m,
        // triangle 2·sqrt(0.1)) is faster, and so is the arm.
        let mount = Mount::row(crate::Interval::new(0.0, 5.0));
        let from = MountState::Rail {
            position_m: 1.0,
            lift_m: 0.0,
        };
        let to = MountState::Rail {
            position_m: 3.0,
            lift_m: 0.1,
        };
        let q = [0.0; 6];
        let t = ur
            .motion_time(&mount, (&q, &from), (&q, &to))
            .unwrap_or(f64::NAN);
        assert!(close(t, 4.5));
    }

    #[test]
    fn bad_inputs_are_errors() {
        let limits = MotionLimits::default();
        let q = [0.0; 6];
        let mut bad = q;
        bad[3] = f64::NAN;
        assert!(limits.joint_motion_time(&q, &bad).is_err());
        let broken = AxisLimit {
            max_speed: 0.0,
            max_accel: 1.0,
        };
        assert!(broken.travel_time(1.0).is_err());
        let mount = Mount::scenario_one();
        let wrong = MountState::Rail {
            position_m: 0.0,
            lift_m: 0.0,
        };
        assert!(limits
            .mount_motion_time(&mount, &MountState::Fixed, &wrong)
            .is_err());
    }
}
