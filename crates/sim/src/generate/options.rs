//! What a scene may have beyond the paper's: fruit of another colour or shape, red clutter.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::FruitColour;

/// Largest accepted [`SceneOptions::red_clutter`].
pub const MAX_RED_CLUTTER: f64 = 0.2;

/// Scene options, each off by default: the default options give the paper's scenes, exactly.
/// Settings files spell them `{ fruit_colour: "leaf-green", fruit_shape: "capsicum",
/// red_clutter: 0.1 }`; missing fields take the defaults.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SceneOptions {
    pub fruit_colour: FruitColour,
    pub fruit_shape: FruitShape,
    /// Share in [0, [`MAX_RED_CLUTTER`]] of leaves given a fruit-red albedo. Above 0 each plant
    /// also gets a red clip on its stem and 2-3 red petioles, and the scene two red or orange
    /// labels: red things that are not fruit.
    pub red_clutter: f64,
    /// The day of a visit, counted from the first (0): the scene as it is then, its fruit grown,
    /// set or harvested and its leaves moved (`season`). None: the scene as generated, which is
    /// not any visit's (day 0 of the visits has the fruit not yet set removed).
    pub day: Option<f64>,
}

/// Scene options out of range.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum SceneOptionsError {
    #[error("red clutter must be a share of leaves in [0, {MAX_RED_CLUTTER}], got {0}")]
    RedClutter(f64),
    #[error("a visit's day must be in [0, {MAX_DAY}], got {0}")]
    Day(f64),
}

/// Latest visit day accepted.
pub const MAX_DAY: f64 = 365.0;

impl SceneOptions {
    /// The red clutter share must be within [0, [`MAX_RED_CLUTTER`]].
    pub fn validate(&self) -> Result<(), SceneOptionsError> {
        if !(0.0..=MAX_RED_CLUTTER).contains(&self.red_clutter) {
            return Err(SceneOptionsError::RedClutter(self.red_clutter));
        }
        if let Some(day) = self.day.filter(|d| !(0.0..=MAX_DAY).contains(d)) {
            return Err(SceneOptionsError::Day(day));
        }
        Ok(())
    }

    /// The visit day generation uses: clamped into range, none for NaN.
    pub(crate) fn visit_day(&self) -> Option<f64> {
        self.day
            .filter(|d| !d.is_nan())
            .map(|d| d.clamp(0.0, MAX_DAY))
    }

    /// The red clutter share generation uses: clamped into range, 0 for NaN (generation does
    /// not fail; callers validate first).
    pub(crate) fn red_clutter_share(&self) -> f64 {
        if self.red_clutter.is_nan() {
            0.0
        } else {
            self.red_clutter.clamp(0.0, MAX_RED_CLUTTER)
        }
    }
}

/// The shape of a scene's fruit: the paper's axis-aligned ellipsoids, or capsicum-like bodies
/// (3-4 lobes around a tilted axis, a calyx and a stalk, some pressed against a leaf).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FruitShape {
    #[default]
    Ellipsoid,
    Capsicum,
}

/// A fruit shape that is not `ellipsoid` or `capsicum`.
#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
#[error("unknown fruit shape {0:?}; valid: ellipsoid, capsicum")]
pub struct ParseFruitShapeError(pub String);

impl FromStr for FruitShape {
    type Err = ParseFruitShapeError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "ellipsoid" => Ok(FruitShape::Ellipsoid),
            "capsicum" => Ok(FruitShape::Capsicum),
            _ => Err(ParseFruitShapeError(s.to_string())),
        }
    }
}

impl fmt::Display for FruitShape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            FruitShape::Ellipsoid => "ellipsoid",
            FruitShape::Capsicum => "capsicum",
        })
    }
}
