//! The arm on its mount: world-frame kinematics, camera-pose IK, mount placement and collision
//! checks.

use nalgebra::{Isometry3, Point3, Vector3};

use crate::collision::{
    capsule_samples_any, CollisionWorld, Contact, ContactWith, PathContact, WorldCapsule,
};
use crate::error::{ensure_finite, invalid, ArmError, Result};
use crate::kinematics::{joint_distance, ArmModel, JointVector, JOINT_COUNT};
use crate::mount::{Interval, Mount, MountState};
use crate::{ArmPose, MotionLimits};

/// Largest accepted collision margin, metres (bounds the voxel sampling work).
pub const MAX_MARGIN_M: f64 = 1.0;
/// Smallest accepted voxel resolution, metres (bounds the voxel sampling work).
pub const MIN_VOXEL_RESOLUTION_M: f64 = 1e-3;

/// A UR arm with its camera, on a mount.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Robot {
    pub arm: ArmModel,
    pub mount: Mount,
}

impl Robot {
    /// Validates both parts.
    pub fn new(arm: ArmModel, mount: Mount) -> Result<Self> {
        arm.validate()?;
        mount.validate()?;
        Ok(Self { arm, mount })
    }

    /// Default UR5e on [`Mount::scenario_one`].
    pub fn scenario_one() -> Self {
        Self {
            arm: ArmModel::ur5e(),
            mount: Mount::scenario_one(),
        }
    }

    /// Default UR5e on [`Mount::scenario_two`].
    pub fn scenario_two() -> Self {
        Self {
            arm: ArmModel::ur5e(),
            mount: Mount::scenario_two(),
        }
    }

    /// Default UR5e on [`Mount::row`].
    pub fn row(rail_position_m: Interval) -> Self {
        Self {
            arm: ArmModel::ur5e(),
            mount: Mount::row(rail_position_m),
        }
    }

    /// The arm base in the world.
    pub fn world_from_base(&self, state: &MountState) -> Result<Isometry3<f64>> {
        self.mount.world_from_base(state)
    }

    /// Camera optical frame in the world (joint limits not enforced).
    pub fn world_from_camera(&self, q: &JointVector, state: &MountState) -> Result<Isometry3<f64>> {
        Ok(self.world_from_base(state)? * self.arm.base_from_camera(q)?)
    }

    /// Every joint configuration within limits that puts the camera at `world_from_camera_goal`
    /// (up to 8; each joint at its value closest to 0). Empty when out of reach; errors for a
    /// non-finite goal or a bad mount state.
    pub fn solve_camera_pose(
        &self,
        world_from_camera_goal: &Isometry3<f64>,
        state: &MountState,
    ) -> Result<Vec<JointVector>> {
        check_pose(world_from_camera_goal, "camera goal")?;
        let base = self.world_from_base(state)?;
        self.arm
            .ik_camera(&(base.inverse() * world_from_camera_goal), None)
    }

    /// Like [`Robot::solve_camera_pose`], with each joint shifted by multiples of 2π towards
    /// `current` and the solutions sorted by joint-space distance to it (closest first).
    pub fn solve_camera_pose_near(
        &self,
        world_from_camera_goal: &Isometry3<f64>,
        state: &MountState,
        current: &JointVector,
    ) -> Result<Vec<JointVector>> {
        check_pose(world_from_camera_goal, "camera goal")?;
        let base = self.world_from_base(state)?;
        let mut out = self
            .arm
            .ik_camera(&(base.inverse() * world_from_camera_goal), Some(current))?;
        out.sort_by(|a, b| joint_distance(current, a).total_cmp(&joint_distance(current, b)));
        Ok(out)
    }

    /// Where the robot would be with its camera at `world_from_camera`, as the edge places it
    /// from nowhere ([`Robot::place_mount_for`], the first solution): a guess of its pose for
    /// [`Robot::motion_time_to`] when only the camera pose is known.
    pub fn pose_guess(&self, world_from_camera: &Isometry3<f64>) -> Result<ArmPose> {
        let (mount, solutions) = self.place_mount_for(world_from_camera, None)?;
        let joints = *solutions.first().ok_or(ArmError::Unreachable)?;
        Ok(ArmPose { joints, mount })
    }

    /// How long the arm and mount take from `from` to the camera at `goal`, placed as the edge
    /// places them (the mount state it tries first, the joint solution closest to `from`), no
    /// path checked: what a view costs in time.
    pub fn motion_time_to(
        &self,
        from: &ArmPose,
        goal: &Isometry3<f64>,
        limits: &MotionLimits,
    ) -> Result<f64> {
        let (mount, solutions) = self.place_mount_for(goal, Some(&from.joints))?;
        let joints = solutions.first().ok_or(ArmError::Unreachable)?;
        limits.motion_time(&self.mount, (&from.joints, &from.mount), (joints, &mount))
    }

    /// Heuristic mount states to try for a camera goal, best guess first (clamped to the ranges,
    /// duplicates removed). Gantry: the pole foot behind the camera (against the horizontal part
    /// of its optical axis) by 0.3 m, then 0.15, 0.45 and 0 m, and the base 0.35 m above the
    /// camera, then 0.2, 0.5 and 0 m. Rail: the trolley at the camera's x, then ±0.2 and ±0.4 m,
    /// with the base 0.3 m below the camera, then 0, 0.5 and 0.15 m. Fixed: the only state.
    pub fn suggest_mount_states(
        &self,
        world_from_camera_goal: &Isometry3<f64>,
    ) -> Result<Vec<MountState>> {
        check_pose(world_from_camera_goal, "camera goal")?;
        let c = Point3::from(world_from_camera_goal.translation.vector);
        let axis = world_from_camera_goal.rotation * Vector3::z();
        let horizontal = Vector3::new(axis.x, axis.y, 0.0)
            .try_normalize(1e-9)
            .unwrap_or_else(Vector3::zeros);
        let mut raw = Vec::new();
        match &self.mount {
            Mount::Fixed { .. } => raw.push(MountState::Fixed),
            Mount::CeilingGantry {
                retracted_base_z_m, ..
            } => {
                for above in [0.35, 0.2, 0.5, 0.0] {
                    for back in [0.3, 0.15, 0.45, 0.0] {
                        raw.push(MountState::Gantry {
                            x_m: c.x - back * horizontal.x,
                            y_m: c.y - back * horizontal.y,
                            extension_m: retracted_base_z_m - (c.z + above),
                        });
                    }
                }
            }
            Mount::RailLift {
                base_z_at_zero_lift_m,
                ..
            } => {
                for below in [0.3, 0.0, 0.5, 0.15] {
                    for dx in [0.0, 0.2, -0.2, 0.4, -0.4] {
                        raw.push(MountState::Rail {
                            position_m: c.x + dx,
                            lift_m: c.z - below - base_z_at_zero_lift_m,
                        });
                    }
                }
            }
        }
        let mut out: Vec<MountState> = Vec::new();
        for s in raw {
            let s = self.mount.clamp_state(&s)?;
            let same = |o: &MountState| {
                o.values()
                    .iter()
                    .zip(s.values())
                    .all(|(a, b)| (a - b).abs() < 1e-6)
            };
            if !out.iter().any(same) {
                out.push(s);
            }
        }
        Ok(out)
    }

    /// Tries [`Robot::suggest_mount_states`] in order and returns the first state with IK
    /// solutions, sorted by distance to `current` when given. [`ArmError::Unreachable`] when none.
    pub fn place_mount_for(
        &self,
        world_from_camera_goal: &Isometry3<f64>,
        current: Option<&JointVector>,
    ) -> Result<(MountState, Vec<JointVector>)> {
        for state in self.suggest_mount_states(world_from_camera_goal)? {
            let solutions = match current {
                Some(q) => self.solve_camera_pose_near(world_from_camera_goal, &state, q)?,
                None => self.solve_camera_pose(world_from_camera_goal, &state)?,
            };
            if !solutions.is_empty() {
                return Ok((state, solutions));
            }
        }
        Err(ArmError::Unreachable)
    }

    /// The link capsules in the world frame (radii without margin).
    pub fn link_capsules(&self, q: &JointVector, state: &MountState) -> Result<Vec<WorldCapsule>> {
        ensure_finite(q, "joint vector")?;
        let base = crate::kinematics::Frame::from_isometry(&self.world_from_base(state)?);
        let frames = self.arm.frames(q);
        let mut out = Vec::with_capacity(self.arm.links.len());
        for (i, link) in self.arm.links.iter().enumerate() {
            let Some(f) = frames.get(link.frame) else {
                return Err(invalid("links", format!("bad frame of {}", link.name)));
            };
            let world = base.mul(f);
            out.push(WorldCapsule {
                link: i,
                a: world.point(&link.a),
                b: world.point(&link.b),
                radius_m: link.radius_m,
            });
        }
        Ok(out)
    }

    /// First collision of the configuration with the world (obstacles first, then voxels), or
    /// None when free. Links with `check_environment == false` are skipped. Errors for a joint
    /// vector outside the limits, a bad mount state or invalid obstacles.
    pub fn check_configuration(
        &self,
        q: &JointVector,
        state: &MountState,
        world: &CollisionWorld<'_>,
    ) -> Result<Option<Contact>> {
        validate_world(world)?;
        self.arm.limits.check(q)?;
        self.check_unchecked(q, state, world)
    }

    fn check_unchecked(
        &self,
        q: &JointVector,
        state: &MountState,
        world: &CollisionWorld<'_>,
    ) -> Result<Option<Contact>> {
        let capsules = self.link_capsules(q, state)?;
        let contact = |c: &WorldCapsule, with| Contact {
            link: c.link,
            link_name: self
                .arm
                .links
                .get(c.link)
                .map(|l| l.name.clone())
                .unwrap_or_default(),
            with,
        };
        let checked = || {
            capsules.iter().filter(|c| {
                self.arm
                    .links
                    .get(c.link)
                    .is_some_and(|l| l.check_environment)
            })
        };
        for c in checked() {
            let radius = c.radius_m + world.margin_m;
            for (i, o) in world.obstacles.iter().enumerate() {
                if o.intersects_capsule(&c.a, &c.b, radius) {
                    return Ok(Some(contact(c, ContactWith::Obstacle(i))));
                }
            }
        }
        if let Some((occupancy, resolution)) = world.voxels {
            for c in checked() {
                let radius = c.radius_m + world.margin_m;
                let hit = capsule_samples_any(&c.a, &c.b, radius, resolution, |p| {
                    occupancy.is_occupied(p)
                });
                if let Some(p) = hit {
                    return Ok(Some(contact(c, ContactWith::Voxel(p))));
                }
            }
        }
        Ok(None)
    }

    /// First collision along the straight joint-space path `from` → `to`, checked at both ends and
    /// at evenly spaced configurations no more than `max_step_rad` apart on any joint. The mount
    /// stays in `state`.
    pub fn check_path(
        &self,
        from: &JointVector,
        to: &JointVector,
        state: &MountState,
        max_step_rad: f64,
        world: &CollisionWorld<'_>,
    ) -> Result<Option<PathContact>> {
        ensure_finite(&[max_step_rad], "max_step_rad")?;
        if max_step_rad <= 0.0 {
            return Err(invalid("max_step_rad", "must be > 0"));
        }
        validate_world(world)?;
        self.arm.limits.check(from)?;
        self.arm.limits.check(to)?;
        self.mount.check_state(state)?;
        let largest = from
            .iter()
            .zip(to)
            .map(|(a, b)| (b - a).abs())
            .fold(0.0, f64::max);
        let steps = (largest / max_step_rad).ceil().max(1.0);
        if steps > 1e7 {
            return Err(invalid("max_step_rad", "too small for this path"));
        }
        let steps = steps as usize;
        for i in 0..=steps {
            let t = i as f64 / steps as f64;
            let mut q = [0.0; JOINT_COUNT];
            for j in 0..JOINT_COUNT {
                q[j] = from[j] + (to[j] - from[j]) * t;
            }
            if let Some(contact) = self.check_unchecked(&q, state, world)? {
                return Ok(Some(PathContact {
                    fraction: t,
                    joints: q,
                    contact,
                }));
            }
        }
        Ok(None)
    }
}

fn check_pose(pose: &Isometry3<f64>, what: &'static str) -> Result<()> {
    ensure_finite(pose.translation.vector.as_slice(), what)?;
    ensure_finite(pose.rotation.coords.as_slice(), what)
}

fn validate_world(world: &CollisionWorld<'_>) -> Result<()> {
    ensure_finite(&[world.margin_m], "collision margin")?;
    if !(0.0..=MAX_MARGIN_M).contains(&world.margin_m) {
        return Err(invalid(
            "margin_m",
            format!("must be in [0, {MAX_MARGIN_M}] m"),
        ));
    }
    if let Some(i) = world.obstacles.iter().position(|o| !o.is_valid()) {
        return Err(invalid("obstacles", format!("obstacle {i} is invalid")));
    }
    if let Some((_, res)) = world.voxels {
        ensure_finite(&[res], "voxel resolution")?;
        if res < MIN_VOXEL_RESOLUTION_M {
            return Err(invalid(
                "voxel resolution",
                format!("must be >= {MIN_VOXEL_RESOLUTION_M} m"),
            ));
        }
    }
    Ok(())
}
