//! UR-family kinematics: standard Denavit–Hartenberg forward kinematics and the closed-form
//! inverse kinematics (up to eight solutions), joint limits, the camera on the flange and the
//! capsules that approximate the links.

use std::f64::consts::{FRAC_PI_2, PI, TAU};

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{ensure_finite, invalid, ArmError, Result};

/// Number of arm joints.
pub const JOINT_COUNT: usize = 6;

/// Joint angles in radians, base (joint 1) first.
pub type JointVector = [f64; JOINT_COUNT];

/// Index of the camera frame for [`LinkCapsule::frame`]; frames `0..=6` are the DH frames
/// (0 = base, `i` = after joint `i`, 6 = tool flange).
pub const CAMERA_FRAME: usize = 7;

/// Twist angles α of the UR family (standard DH).
pub const UR_ALPHA: [f64; JOINT_COUNT] = [FRAC_PI_2, 0.0, 0.0, FRAC_PI_2, -FRAC_PI_2, 0.0];
/// cos α and sin α, exact.
const COS_ALPHA: [f64; JOINT_COUNT] = [0.0, 1.0, 1.0, 0.0, 0.0, 1.0];
const SIN_ALPHA: [f64; JOINT_COUNT] = [1.0, 0.0, 0.0, 1.0, -1.0, 0.0];

/// Tolerance on the arguments of `acos` before a pose counts as out of reach.
const ACOS_SLACK: f64 = 1e-9;
/// An IK solution is kept only when its FK reproduces the goal this closely (metres / rotation).
const IK_VERIFY_TOL: f64 = 1e-7;

/// The six DH lengths of a UR arm (standard DH, metres); `a1 = d2 = d3 = a4 = a5 = a6 = 0` and the
/// twists are [`UR_ALPHA`]. These fix the structure the closed-form IK relies on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct UrDh {
    pub d1: f64,
    pub a2: f64,
    pub a3: f64,
    pub d4: f64,
    pub d5: f64,
    pub d6: f64,
}

impl UrDh {
    /// Universal Robots' published UR5e parameters.
    pub const UR5E: UrDh = UrDh {
        d1: 0.1625,
        a2: -0.425,
        a3: -0.3922,
        d4: 0.1333,
        d5: 0.0997,
        d6: 0.0996,
    };

    /// Link lengths `a_i`.
    pub fn a(&self) -> [f64; JOINT_COUNT] {
        [0.0, self.a2, self.a3, 0.0, 0.0, 0.0]
    }

    /// Link offsets `d_i`.
    pub fn d(&self) -> [f64; JOINT_COUNT] {
        [self.d1, 0.0, 0.0, self.d4, self.d5, self.d6]
    }

    /// Finite, with the non-zero lengths the closed-form IK divides by.
    pub fn validate(&self) -> Result<()> {
        ensure_finite(
            &[self.d1, self.a2, self.a3, self.d4, self.d5, self.d6],
            "DH parameters",
        )?;
        for (name, v) in [
            ("a2", self.a2),
            ("a3", self.a3),
            ("d4", self.d4),
            ("d6", self.d6),
        ] {
            if v.abs() < 1e-6 {
                return Err(invalid("dh", format!("{name} must be non-zero")));
            }
        }
        Ok(())
    }

    /// An upper bound of the distance from the base origin to any point of frames 0..6.
    pub(crate) fn reach_bound(&self) -> f64 {
        self.a()
            .iter()
            .chain(self.d().iter())
            .map(|v| v.abs())
            .sum()
    }
}

impl Default for UrDh {
    fn default() -> Self {
        Self::UR5E
    }
}

/// Per-joint limits in radians, inclusive.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointLimits {
    pub lower: JointVector,
    pub upper: JointVector,
}

impl JointLimits {
    /// UR5e hardware limits: ±2π (±360°) on every joint.
    pub fn ur5e() -> Self {
        Self {
            lower: [-TAU; JOINT_COUNT],
            upper: [TAU; JOINT_COUNT],
        }
    }

    /// The common software setting: ±2π except the elbow (joint 3) at ±π.
    pub fn ur5e_elbow_pi() -> Self {
        let mut limits = Self::ur5e();
        limits.lower[2] = -PI;
        limits.upper[2] = PI;
        limits
    }

    /// Finite and `lower <= upper` for every joint.
    pub fn validate(&self) -> Result<()> {
        ensure_finite(&self.lower, "joint limits")?;
        ensure_finite(&self.upper, "joint limits")?;
        if self.lower.iter().zip(&self.upper).any(|(lo, hi)| lo > hi) {
            return Err(invalid("joint limits", "lower > upper"));
        }
        Ok(())
    }

    /// True when every joint is within its limits.
    pub fn contains(&self, q: &JointVector) -> bool {
        self.check(q).is_ok()
    }

    /// Error for a non-finite joint vector or the first joint outside its limits.
    pub fn check(&self, q: &JointVector) -> Result<()> {
        ensure_finite(q, "joint vector")?;
        for (joint, ((&value, &min), &max)) in
            q.iter().zip(&self.lower).zip(&self.upper).enumerate()
        {
            if value < min - 1e-12 || value > max + 1e-12 {
                return Err(ArmError::JointOutOfLimits {
                    joint,
                    value,
                    min,
                    max,
                });
            }
        }
        Ok(())
    }

    /// True when joint `i` can turn a full circle.
    pub fn is_full_circle(&self, joint: usize) -> bool {
        match (self.lower.get(joint), self.upper.get(joint)) {
            (Some(lo), Some(hi)) => hi - lo >= TAU - 1e-12,
            _ => false,
        }
    }

    /// `q` with each joint shifted by a multiple of 2π to the value within limits closest to
    /// `reference`; None when some joint has no such value.
    pub fn wrap_near(&self, q: &JointVector, reference: &JointVector) -> Option<JointVector> {
        let mut out = [0.0; JOINT_COUNT];
        for i in 0..JOINT_COUNT {
            out[i] = wrap_angle_near(q[i], reference[i], self.lower[i], self.upper[i])?;
        }
        Some(out)
    }
}

impl Default for JointLimits {
    fn default() -> Self {
        Self::ur5e()
    }
}

/// `theta + 2πk` within `[lo, hi]` closest to `reference`, if any.
fn wrap_angle_near(theta: f64, reference: f64, lo: f64, hi: f64) -> Option<f64> {
    let k_min = ((lo - 1e-12 - theta) / TAU).ceil();
    let k_max = ((hi + 1e-12 - theta) / TAU).floor();
    if !(k_min.is_finite() && k_max.is_finite()) || k_min > k_max {
        return None;
    }
    let k = ((reference - theta) / TAU).round().clamp(k_min, k_max);
    Some((theta + k * TAU).clamp(lo, hi))
}

/// Angle wrapped to `[-π, π)`.
pub(crate) fn wrap_pi(a: f64) -> f64 {
    a - TAU * ((a + PI) / TAU).floor()
}

/// A capsule rigidly attached to one frame of the arm: the segment `a`–`b` (in that frame's
/// coordinates) inflated by `radius_m`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LinkCapsule {
    pub name: String,
    /// `0..=6`: DH frame (0 = base, 6 = flange); [`CAMERA_FRAME`]: camera optical frame.
    pub frame: usize,
    pub a: Point3<f64>,
    pub b: Point3<f64>,
    pub radius_m: f64,
    /// False for parts that touch the mount by construction (the base housing); those are not
    /// checked against the scene.
    pub check_environment: bool,
}

/// Rigid transform as a rotation matrix and a translation: cheaper and more exact to chain than
/// quaternions for FK.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Frame {
    pub r: Matrix3<f64>,
    pub t: Vector3<f64>,
}

impl Frame {
    pub fn identity() -> Self {
        Self {
            r: Matrix3::identity(),
            t: Vector3::zeros(),
        }
    }

    pub fn mul(&self, other: &Frame) -> Frame {
        Frame {
            r: self.r * other.r,
            t: self.r * other.t + self.t,
        }
    }

    pub fn inverse(&self) -> Frame {
        let rt = self.r.transpose();
        Frame {
            r: rt,
            t: -(rt * self.t),
        }
    }

    pub fn point(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.r * p.coords + self.t)
    }

    pub fn from_isometry(iso: &Isometry3<f64>) -> Self {
        Self {
            r: *iso.rotation.to_rotation_matrix().matrix(),
            t: iso.translation.vector,
        }
    }

    pub fn to_isometry(self) -> Isometry3<f64> {
        let rotation = Rotation3::from_matrix_unchecked(self.r);
        Isometry3::from_parts(
            Translation3::from(self.t),
            UnitQuaternion::from_rotation_matrix(&rotation),
        )
    }
}

/// Transform from DH frame `i` to frame `i + 1` for joint angle `theta` (joint index `i` in 0..6):
/// `Rz(θ) Tz(d) Tx(a) Rx(α)`.
pub(crate) fn dh_frame(dh: &UrDh, i: usize, theta: f64) -> Frame {
    let (s, c) = theta.sin_cos();
    let ca = COS_ALPHA[i % JOINT_COUNT];
    let sa = SIN_ALPHA[i % JOINT_COUNT];
    let a = dh.a()[i % JOINT_COUNT];
    let d = dh.d()[i % JOINT_COUNT];
    Frame {
        r: Matrix3::new(c, -s * ca, s * sa, s, c * ca, -c * sa, 0.0, sa, ca),
        t: Vector3::new(a * c, a * s, d),
    }
}

/// A UR arm with a camera on its flange: DH lengths, joint limits, camera mount and link capsules.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ArmModel {
    pub dh: UrDh,
    pub limits: JointLimits,
    /// Camera optical frame (x right, y down, z forward) in the flange frame (DH frame 6, z out of
    /// the flange).
    pub flange_from_camera: Isometry3<f64>,
    /// Collision geometry, see [`ArmModel::ur5e_links`].
    pub links: Vec<LinkCapsule>,
}

impl Default for ArmModel {
    fn default() -> Self {
        Self::ur5e()
    }
}

impl ArmModel {
    /// UR5e with ±2π limits, the default camera mount and the default link capsules.
    pub fn ur5e() -> Self {
        Self {
            dh: UrDh::UR5E,
            limits: JointLimits::ur5e(),
            flange_from_camera: Self::default_flange_from_camera(),
            links: Self::ur5e_links(&UrDh::UR5E),
        }
    }

    /// The default camera mount: optical centre 3 cm in front of the flange on the flange axis,
    /// optical axis along the flange z, image x along flange x. With the camera on the flange
    /// axis, joint 6 only rolls the image (paper §VII).
    pub fn default_flange_from_camera() -> Isometry3<f64> {
        Isometry3::translation(0.0, 0.0, 0.03)
    }

    /// Capsules approximating a UR5e (lateral offsets from the URDF: upper arm 0.138 m along the
    /// shoulder axis, forearm 0.007 m) plus a 9 × 4 cm camera body.
    pub fn ur5e_links(dh: &UrDh) -> Vec<LinkCapsule> {
        let cap = |name: &str, frame, a: [f64; 3], b: [f64; 3], radius_m, check| LinkCapsule {
            name: name.to_string(),
            frame,
            a: Point3::from(a),
            b: Point3::from(b),
            radius_m,
            check_environment: check,
        };
        let upper_arm_offset = 0.138;
        let forearm_offset = 0.007;
        vec![
            cap("base", 0, [0.0; 3], [0.0, 0.0, dh.d1], 0.075, false),
            cap(
                "shoulder",
                1,
                [0.0, 0.0, -0.06],
                [0.0, 0.0, upper_arm_offset],
                0.075,
                true,
            ),
            cap(
                "upper_arm",
                2,
                [-dh.a2, 0.0, upper_arm_offset],
                [0.0, 0.0, upper_arm_offset],
                0.06,
                true,
            ),
            cap(
                "elbow",
                2,
                [0.0, 0.0, forearm_offset],
                [0.0, 0.0, upper_arm_offset],
                0.06,
                true,
            ),
            cap(
                "forearm",
                3,
                [-dh.a3, 0.0, forearm_offset],
                [0.0, 0.0, forearm_offset],
                0.05,
                true,
            ),
            cap(
                "wrist_1",
                3,
                [0.0, 0.0, forearm_offset],
                [0.0, 0.0, dh.d4],
                0.045,
                true,
            ),
            cap("wrist_2", 4, [0.0; 3], [0.0, 0.0, dh.d5], 0.045, true),
            cap("wrist_3", 5, [0.0; 3], [0.0, 0.0, dh.d6], 0.045, true),
            cap(
                "camera",
                CAMERA_FRAME,
                [-0.045, 0.0, -0.0125],
                [0.045, 0.0, -0.0125],
                0.02,
                true,
            ),
        ]
    }

    /// Checks parameters: DH, limits, finite camera mount, capsules.
    pub fn validate(&self) -> Result<()> {
        self.dh.validate()?;
        self.limits.validate()?;
        let f = &self.flange_from_camera;
        ensure_finite(f.translation.vector.as_slice(), "flange_from_camera")?;
        ensure_finite(f.rotation.coords.as_slice(), "flange_from_camera")?;
        for link in &self.links {
            ensure_finite(&[link.radius_m], "link capsule")?;
            ensure_finite(link.a.coords.as_slice(), "link capsule")?;
            ensure_finite(link.b.coords.as_slice(), "link capsule")?;
            if link.frame > CAMERA_FRAME || link.radius_m < 0.0 {
                return Err(invalid("links", format!("bad capsule {}", link.name)));
            }
        }
        Ok(())
    }

    /// Frames 0..=6 (base .. flange) and the camera frame, in the base frame.
    pub(crate) fn frames(&self, q: &JointVector) -> [Frame; 8] {
        let mut out = [Frame::identity(); 8];
        for i in 0..JOINT_COUNT {
            out[i + 1] = out[i].mul(&dh_frame(&self.dh, i, q[i]));
        }
        out[CAMERA_FRAME] = out[6].mul(&Frame::from_isometry(&self.flange_from_camera));
        out
    }

    /// Forward kinematics: the flange (DH frame 6) in the base frame. Joint limits are not
    /// enforced here (see [`JointLimits::check`]).
    pub fn base_from_flange(&self, q: &JointVector) -> Result<Isometry3<f64>> {
        ensure_finite(q, "joint vector")?;
        Ok(self.frames(q)[6].to_isometry())
    }

    /// Forward kinematics to the camera optical frame, in the base frame.
    pub fn base_from_camera(&self, q: &JointVector) -> Result<Isometry3<f64>> {
        ensure_finite(q, "joint vector")?;
        Ok(self.frames(q)[CAMERA_FRAME].to_isometry())
    }

    /// All DH frames 0..=6 in the base frame (index 0 is the identity).
    pub fn base_from_frames(&self, q: &JointVector) -> Result<[Isometry3<f64>; 7]> {
        ensure_finite(q, "joint vector")?;
        let f = self.frames(q);
        Ok(std::array::from_fn(|i| f[i].to_isometry()))
    }

    /// Closed-form inverse kinematics of the flange pose (base frame), ignoring joint limits:
    /// up to eight solutions with every angle in `[-π, π)`, each verified by FK. At a wrist
    /// singularity (θ5 = 0 or π) joint 6 is set to 0 and joint 4 takes up the rotation. Empty
    /// when the pose is out of reach.
    pub fn ik_flange(&self, base_from_flange: &Isometry3<f64>) -> Result<Vec<JointVector>> {
        ensure_finite(
            base_from_flange.translation.vector.as_slice(),
            "flange pose",
        )?;
        ensure_finite(base_from_flange.rotation.coords.as_slice(), "flange pose")?;
        let goal = Frame::from_isometry(base_from_flange);
        let dh = &self.dh;
        let r = &goal.r;
        let p = goal.t;
        let p05 = p - dh.d6 * r.column(2);
        let rho = p05.x.hypot(p05.y);
        let ratio = dh.d4 / rho;
        if !ratio.is_finite() || ratio.abs() > 1.0 + ACOS_SLACK {
            return Ok(Vec::new());
        }
        let psi = p05.y.atan2(p05.x);
        let phi = ratio.clamp(-1.0, 1.0).acos();
        let mut raw: Vec<JointVector> = Vec::with_capacity(8);
        for th1 in [psi + phi + FRAC_PI_2, psi - phi + FRAC_PI_2] {
            let (s1, c1) = th1.sin_cos();
            let arg5 = (p.x * s1 - p.y * c1 - dh.d4) / dh.d6;
            if arg5.abs() > 1.0 + ACOS_SLACK {
                continue;
            }
            let a5 = arg5.clamp(-1.0, 1.0).acos();
            for th5 in [a5, -a5] {
                let s5 = th5.sin();
                let th6 = if s5.abs() < 1e-10 {
                    0.0
                } else {
                    let y = (-r[(0, 1)] * s1 + r[(1, 1)] * c1) / s5;
                    let x = (r[(0, 0)] * s1 - r[(1, 0)] * c1) / s5;
                    y.atan2(x)
                };
                let t01 = dh_frame(dh, 0, th1);
                let t45 = dh_frame(dh, 4, th5);
                let t56 = dh_frame(dh, 5, th6);
                let t14 = t01
                    .inverse()
                    .mul(&goal)
                    .mul(&t56.inverse())
                    .mul(&t45.inverse());
                let (px, py) = (t14.t.x, t14.t.y);
                let c3 =
                    (px * px + py * py - dh.a2 * dh.a2 - dh.a3 * dh.a3) / (2.0 * dh.a2 * dh.a3);
                if c3.abs() > 1.0 + ACOS_SLACK {
                    continue;
                }
                let a3 = c3.clamp(-1.0, 1.0).acos();
                for th3 in [a3, -a3] {
                    let (s3, c3) = th3.sin_cos();
                    let th2 = py.atan2(px) - (dh.a3 * s3).atan2(dh.a2 + dh.a3 * c3);
                    let phi234 = t14.r[(1, 0)].atan2(t14.r[(0, 0)]);
                    let th4 = phi234 - th2 - th3;
                    raw.push([th1, th2, th3, th4, th5, th6].map(wrap_pi));
                }
            }
        }
        let mut out: Vec<JointVector> = Vec::with_capacity(raw.len());
        for q in raw {
            if !q.iter().all(|v| v.is_finite()) {
                continue;
            }
            let f = self.frames(&q)[6];
            let err = (f.t - goal.t).norm() + (f.r - goal.r).abs().max();
            if err > IK_VERIFY_TOL {
                continue;
            }
            let duplicate = out
                .iter()
                .any(|o| o.iter().zip(&q).all(|(a, b)| wrap_pi(a - b).abs() < 1e-9));
            if !duplicate {
                out.push(q);
            }
        }
        Ok(out)
    }

    /// Inverse kinematics of a camera pose in the base frame: every solution of
    /// [`ArmModel::ik_flange`] shifted by multiples of 2π to the values within limits closest to
    /// `reference` (zero when None); solutions with no such values are dropped.
    pub fn ik_camera(
        &self,
        base_from_camera: &Isometry3<f64>,
        reference: Option<&JointVector>,
    ) -> Result<Vec<JointVector>> {
        let zero = [0.0; JOINT_COUNT];
        let reference = reference.unwrap_or(&zero);
        ensure_finite(reference, "reference joint vector")?;
        let flange = base_from_camera * self.flange_from_camera.inverse();
        Ok(self
            .ik_flange(&flange)?
            .iter()
            .filter_map(|q| self.limits.wrap_near(q, reference))
            .collect())
    }
}

/// Euclidean distance in joint space (radians), without wrapping.
pub fn joint_distance(a: &JointVector, b: &JointVector) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt()
}

/// The solution closest to `current` in joint space (Euclidean, no wrapping: shift solutions
/// towards `current` first with [`JointLimits::wrap_near`], as
/// [`crate::Robot::solve_camera_pose_near`] does). None for an empty list.
pub fn best_solution(current: &JointVector, solutions: &[JointVector]) -> Option<JointVector> {
    solutions
        .iter()
        .filter(|q| q.iter().all(|v| v.is_finite()))
        .min_by(|a, b| joint_distance(current, a).total_cmp(&joint_distance(current, b)))
        .copied()
}
