//! Where the arm base sits in the world: a fixed pole, a ceiling gantry with a retractable pole,
//! or a rail trolley with a scissor lift, each with its extra degrees of freedom and limits.

use std::f64::consts::PI;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::collision::Obstacle;
use crate::error::{ensure_finite, invalid, ArmError, Result};

/// A closed interval `[min, max]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    pub min: f64,
    pub max: f64,
}

impl Interval {
    pub const fn new(min: f64, max: f64) -> Self {
        Self { min, max }
    }

    pub fn contains(&self, v: f64) -> bool {
        v >= self.min && v <= self.max
    }

    /// `v` clamped into the interval (NaN stays NaN).
    pub fn clamp(&self, v: f64) -> f64 {
        v.max(self.min).min(self.max)
    }

    pub fn centre(&self) -> f64 {
        0.5 * (self.min + self.max)
    }

    fn validate(&self, name: &'static str) -> Result<()> {
        ensure_finite(&[self.min, self.max], name)?;
        if self.min > self.max {
            return Err(invalid(name, "min > max"));
        }
        Ok(())
    }

    fn check(&self, axis: &'static str, value: f64) -> Result<()> {
        ensure_finite(&[value], axis)?;
        if value < self.min - 1e-9 || value > self.max + 1e-9 {
            return Err(ArmError::MountOutOfLimits {
                axis,
                value,
                min: self.min,
                max: self.max,
            });
        }
        Ok(())
    }
}

/// Radius of the poles that carry the arm (Scenario 1 and 2), metres.
pub const POLE_RADIUS_M: f64 = 0.05;

/// The arm's mount and its extra degrees of freedom (all lengths in metres, world frame).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Mount {
    /// A base that never moves, e.g. Scenario 1: upright on a static pole, 0.86 m high.
    Fixed {
        world_from_base: Isometry3<f64>,
        /// Floor height under the base (for [`Mount::structure`]); the pole stands on it.
        floor_z_m: f64,
    },
    /// Scenario 2: hanging upside down from a ceiling gantry. The pole's foot moves within
    /// `x_m` × `y_m`; the pole extends `extension_m` down from `retracted_base_z_m`.
    CeilingGantry {
        x_m: Interval,
        y_m: Interval,
        /// Base height with the pole fully retracted.
        retracted_base_z_m: f64,
        /// Maximum extension (the base then sits at `retracted_base_z_m - max_extension_m`).
        max_extension_m: f64,
        /// Ceiling height (top of the pole, for [`Mount::structure`]).
        ceiling_z_m: f64,
        /// Base rotation about the world vertical, radians.
        yaw_rad: f64,
    },
    /// Glasshouse row: a trolley on pipe rails along world x at `rail_y_m`, with a scissor lift;
    /// the base sits upright at `(position, rail_y_m, base_z_at_zero_lift_m + lift)`.
    RailLift {
        rail_y_m: f64,
        position_m: Interval,
        lift_m: Interval,
        base_z_at_zero_lift_m: f64,
        /// Base rotation about the world vertical, radians.
        yaw_rad: f64,
    },
}

/// The values of a mount's extra degrees of freedom.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum MountState {
    Fixed,
    Gantry {
        x_m: f64,
        y_m: f64,
        extension_m: f64,
    },
    Rail {
        position_m: f64,
        lift_m: f64,
    },
}

impl MountState {
    fn kind_name(&self) -> &'static str {
        match self {
            MountState::Fixed => "fixed",
            MountState::Gantry { .. } => "gantry",
            MountState::Rail { .. } => "rail",
        }
    }

    /// The degree-of-freedom values in [`Mount::axis_names`] order.
    pub fn values(&self) -> Vec<f64> {
        match *self {
            MountState::Fixed => Vec::new(),
            MountState::Gantry {
                x_m,
                y_m,
                extension_m,
            } => vec![x_m, y_m, extension_m],
            MountState::Rail { position_m, lift_m } => vec![position_m, lift_m],
        }
    }
}

impl Mount {
    /// Scenario 1: upright base on a static pole at the world origin, 0.86 m high.
    pub fn scenario_one() -> Self {
        Mount::Fixed {
            world_from_base: Isometry3::translation(0.0, 0.0, 0.86),
            floor_z_m: 0.0,
        }
    }

    /// Scenario 2: base upside down under a gantry over a 2 × 2 m square centred on the origin;
    /// base at 2.2 m retracted, extending up to 1.2 m down (to 1.0 m); ceiling at 2.6 m.
    pub fn scenario_two() -> Self {
        Mount::CeilingGantry {
            x_m: Interval::new(-1.0, 1.0),
            y_m: Interval::new(-1.0, 1.0),
            retracted_base_z_m: 2.2,
            max_extension_m: 1.2,
            ceiling_z_m: 2.6,
            yaw_rad: 0.0,
        }
    }

    /// Glasshouse row: rails centred on y = -0.7 m (as in the simulated row), trolley travel
    /// `position_m` along x, scissor lift 0–3 m, base 0.45 m above the floor at zero lift.
    pub fn row(position_m: Interval) -> Self {
        Mount::RailLift {
            rail_y_m: -0.7,
            position_m,
            lift_m: Interval::new(0.0, 3.0),
            base_z_at_zero_lift_m: 0.45,
            yaw_rad: 0.0,
        }
    }

    fn kind_name(&self) -> &'static str {
        match self {
            Mount::Fixed { .. } => "fixed",
            Mount::CeilingGantry { .. } => "gantry",
            Mount::RailLift { .. } => "rail",
        }
    }

    /// Checks the parameters are finite and the intervals non-empty.
    pub fn validate(&self) -> Result<()> {
        match self {
            Mount::Fixed {
                world_from_base,
                floor_z_m,
            } => {
                ensure_finite(world_from_base.translation.vector.as_slice(), "mount pose")?;
                ensure_finite(world_from_base.rotation.coords.as_slice(), "mount pose")?;
                ensure_finite(&[*floor_z_m], "floor height")
            }
            Mount::CeilingGantry {
                x_m,
                y_m,
                retracted_base_z_m,
                max_extension_m,
                ceiling_z_m,
                yaw_rad,
            } => {
                x_m.validate("gantry x")?;
                y_m.validate("gantry y")?;
                ensure_finite(
                    &[
                        *retracted_base_z_m,
                        *max_extension_m,
                        *ceiling_z_m,
                        *yaw_rad,
                    ],
                    "gantry parameters",
                )?;
                if *max_extension_m < 0.0 {
                    return Err(invalid("max_extension_m", "negative"));
                }
                Ok(())
            }
            Mount::RailLift {
                rail_y_m,
                position_m,
                lift_m,
                base_z_at_zero_lift_m,
                yaw_rad,
            } => {
                position_m.validate("rail position")?;
                lift_m.validate("lift")?;
                ensure_finite(
                    &[*rail_y_m, *base_z_at_zero_lift_m, *yaw_rad],
                    "rail parameters",
                )
            }
        }
    }

    /// Names of the extra degrees of freedom, in [`MountState::values`] order.
    pub fn axis_names(&self) -> &'static [&'static str] {
        match self {
            Mount::Fixed { .. } => &[],
            Mount::CeilingGantry { .. } => &["gantry_x", "gantry_y", "extension"],
            Mount::RailLift { .. } => &["rail_position", "lift"],
        }
    }

    /// Ranges of the extra degrees of freedom, in [`Mount::axis_names`] order.
    pub fn axis_ranges(&self) -> Vec<Interval> {
        match self {
            Mount::Fixed { .. } => Vec::new(),
            Mount::CeilingGantry {
                x_m,
                y_m,
                max_extension_m,
                ..
            } => vec![*x_m, *y_m, Interval::new(0.0, *max_extension_m)],
            Mount::RailLift {
                position_m, lift_m, ..
            } => vec![*position_m, *lift_m],
        }
    }

    /// A valid state: the centre of every range, the pole retracted, the lift down.
    pub fn default_state(&self) -> MountState {
        match self {
            Mount::Fixed { .. } => MountState::Fixed,
            Mount::CeilingGantry { x_m, y_m, .. } => MountState::Gantry {
                x_m: x_m.centre(),
                y_m: y_m.centre(),
                extension_m: 0.0,
            },
            Mount::RailLift {
                position_m, lift_m, ..
            } => MountState::Rail {
                position_m: position_m.centre(),
                lift_m: lift_m.min,
            },
        }
    }

    /// The state of this mount's kind with `values` in [`Mount::axis_names`] order, checked.
    pub fn state_from_values(&self, values: &[f64]) -> Result<MountState> {
        let names = self.axis_names();
        if values.len() != names.len() {
            return Err(ArmError::InvalidParameter {
                name: "mount state",
                reason: format!("{} values for the axes {names:?}", values.len()),
            });
        }
        let state = match self {
            Mount::Fixed { .. } => MountState::Fixed,
            Mount::CeilingGantry { .. } => MountState::Gantry {
                x_m: values[0],
                y_m: values[1],
                extension_m: values[2],
            },
            Mount::RailLift { .. } => MountState::Rail {
                position_m: values[0],
                lift_m: values[1],
            },
        };
        self.check_state(&state)?;
        Ok(state)
    }

    /// Error unless `state` is of this mount's kind, finite and within the ranges.
    pub fn check_state(&self, state: &MountState) -> Result<()> {
        self.validate()?;
        let mismatch = || ArmError::MountStateMismatch {
            mount: self.kind_name(),
            state: state.kind_name(),
        };
        match (self, state) {
            (Mount::Fixed { .. }, MountState::Fixed) => Ok(()),
            (
                Mount::CeilingGantry {
                    x_m,
                    y_m,
                    max_extension_m,
                    ..
                },
                MountState::Gantry {
                    x_m: x,
                    y_m: y,
                    extension_m,
                },
            ) => {
                x_m.check("gantry_x", *x)?;
                y_m.check("gantry_y", *y)?;
                Interval::new(0.0, *max_extension_m).check("extension", *extension_m)
            }
            (
                Mount::RailLift {
                    position_m, lift_m, ..
                },
                MountState::Rail {
                    position_m: s,
                    lift_m: l,
                },
            ) => {
                position_m.check("rail_position", *s)?;
                lift_m.check("lift", *l)
            }
            _ => Err(mismatch()),
        }
    }

    /// `state` moved into the ranges (values clamped); errors for a non-finite or mismatched state.
    pub fn clamp_state(&self, state: &MountState) -> Result<MountState> {
        ensure_finite(&state.values(), "mount state")?;
        let ranges = self.axis_ranges();
        let clamped = match (self, *state) {
            (Mount::Fixed { .. }, MountState::Fixed) => MountState::Fixed,
            (
                Mount::CeilingGantry { .. },
                MountState::Gantry {
                    x_m,
                    y_m,
                    extension_m,
                },
            ) => MountState::Gantry {
                x_m: ranges[0].clamp(x_m),
                y_m: ranges[1].clamp(y_m),
                extension_m: ranges[2].clamp(extension_m),
            },
            (Mount::RailLift { .. }, MountState::Rail { position_m, lift_m }) => MountState::Rail {
                position_m: ranges[0].clamp(position_m),
                lift_m: ranges[1].clamp(lift_m),
            },
            _ => {
                return Err(ArmError::MountStateMismatch {
                    mount: self.kind_name(),
                    state: state.kind_name(),
                })
            }
        };
        Ok(clamped)
    }

    /// The arm base frame in the world for a mount state (checked against the ranges).
    pub fn world_from_base(&self, state: &MountState) -> Result<Isometry3<f64>> {
        self.check_state(state)?;
        Ok(match (self, *state) {
            (
                Mount::CeilingGantry {
                    retracted_base_z_m,
                    yaw_rad,
                    ..
                },
                MountState::Gantry {
                    x_m,
                    y_m,
                    extension_m,
                },
            ) => Isometry3::from_parts(
                Translation3::new(x_m, y_m, retracted_base_z_m - extension_m),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), *yaw_rad)
                    * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI),
            ),
            (
                Mount::RailLift {
                    rail_y_m,
                    base_z_at_zero_lift_m,
                    yaw_rad,
                    ..
                },
                MountState::Rail { position_m, lift_m },
            ) => Isometry3::from_parts(
                Translation3::new(position_m, *rail_y_m, base_z_at_zero_lift_m + lift_m),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), *yaw_rad),
            ),
            (
                Mount::Fixed {
                    world_from_base, ..
                },
                _,
            ) => *world_from_base,
            // check_state rejected every other combination.
            _ => {
                return Err(ArmError::MountStateMismatch {
                    mount: self.kind_name(),
                    state: state.kind_name(),
                })
            }
        })
    }

    /// Absolute travel of every extra degree of freedom between two states.
    pub fn axis_distances(&self, from: &MountState, to: &MountState) -> Result<Vec<f64>> {
        self.check_state(from)?;
        self.check_state(to)?;
        Ok(from
            .values()
            .iter()
            .zip(to.values())
            .map(|(a, b)| (b - a).abs())
            .collect())
    }

    /// For a moving mount: the ranges of the distance from the base axis (`r`) and of the height
    /// along the base axis (`z`, base frame) that the world point `p` takes over all mount states.
    /// None for a fixed mount.
    pub(crate) fn swept_cylindrical_range(&self, p: &Point3<f64>) -> Option<(Interval, Interval)> {
        match self {
            Mount::Fixed { .. } => None,
            Mount::CeilingGantry {
                x_m,
                y_m,
                retracted_base_z_m,
                max_extension_m,
                ..
            } => {
                // Base frame z points down: z_base = base_z - p.z.
                let z = Interval::new(
                    retracted_base_z_m - max_extension_m - p.z,
                    retracted_base_z_m - p.z,
                );
                let dx_near = p.x - x_m.clamp(p.x);
                let dy_near = p.y - y_m.clamp(p.y);
                let dx_far = (p.x - x_m.min).abs().max((p.x - x_m.max).abs());
                let dy_far = (p.y - y_m.min).abs().max((p.y - y_m.max).abs());
                let r = Interval::new(dx_near.hypot(dy_near), dx_far.hypot(dy_far));
                Some((r, z))
            }
            Mount::RailLift {
                rail_y_m,
                position_m,
                lift_m,
                base_z_at_zero_lift_m,
                ..
            } => {
                let z = Interval::new(
                    p.z - base_z_at_zero_lift_m - lift_m.max,
                    p.z - base_z_at_zero_lift_m - lift_m.min,
                );
                let dy = p.y - rail_y_m;
                let dx_near = p.x - position_m.clamp(p.x);
                let dx_far = (p.x - position_m.min)
                    .abs()
                    .max((p.x - position_m.max).abs());
                Some((Interval::new(dx_near.hypot(dy), dx_far.hypot(dy)), z))
            }
        }
    }

    /// The mount's own structure as obstacles for a state, to pass to the collision checks along
    /// with the scene: floor (half-space z ≥ floor) and pole for a fixed mount; pole and ceiling for
    /// the gantry; floor and a trolley-plus-lift box (0.8 × 0.6 m) under the base for the rail.
    /// Every part ends where the base starts, so the arm's shoulder never touches it.
    pub fn structure(&self, state: &MountState) -> Result<Vec<Obstacle>> {
        let base = self.world_from_base(state)?;
        let b = Point3::from(base.translation.vector);
        Ok(match self {
            Mount::Fixed { floor_z_m, .. } => {
                let mut out = vec![Obstacle::HalfSpace {
                    point: Point3::new(0.0, 0.0, *floor_z_m),
                    outward_normal: Vector3::z(),
                }];
                if b.z - POLE_RADIUS_M > *floor_z_m {
                    out.push(Obstacle::Capsule {
                        a: Point3::new(b.x, b.y, *floor_z_m),
                        b: Point3::new(b.x, b.y, b.z - POLE_RADIUS_M),
                        radius_m: POLE_RADIUS_M,
                    });
                }
                out
            }
            Mount::CeilingGantry { ceiling_z_m, .. } => {
                let mut out = vec![Obstacle::HalfSpace {
                    point: Point3::new(0.0, 0.0, *ceiling_z_m),
                    outward_normal: -Vector3::z(),
                }];
                if b.z + POLE_RADIUS_M < *ceiling_z_m {
                    out.push(Obstacle::Capsule {
                        a: Point3::new(b.x, b.y, b.z + POLE_RADIUS_M),
                        b: Point3::new(b.x, b.y, *ceiling_z_m),
                        radius_m: POLE_RADIUS_M,
                    });
                }
                out
            }
            Mount::RailLift { yaw_rad, .. } => {
                let floor_z = 0.0;
                let bottom = 0.1_f64.min(b.z);
                let half_h = 0.5 * (b.z - bottom);
                let mut out = vec![Obstacle::HalfSpace {
                    point: Point3::new(0.0, 0.0, floor_z),
                    outward_normal: Vector3::z(),
                }];
                if half_h > 0.0 {
                    out.push(Obstacle::Box {
                        world_from_box: Isometry3::from_parts(
                            Translation3::new(b.x, b.y, bottom + half_h),
                            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), *yaw_rad),
                        ),
                        half_extents_m: Vector3::new(0.4, 0.3, half_h),
                    });
                }
                out
            }
        })
    }
}
