//! The crate's error type.

use std::path::PathBuf;

/// Everything that can go wrong in this crate. Bad inputs are reported here, never by panics.
#[derive(Debug, thiserror::Error)]
pub enum ArmError {
    /// A pose, joint vector, point or parameter holds NaN or an infinity.
    #[error("{what} is not finite")]
    NonFinite { what: &'static str },
    /// No joint configuration (within the limits) reaches the requested pose.
    #[error("the pose is out of the arm's reach")]
    Unreachable,
    /// A joint value lies outside its limits.
    #[error("joint {joint} = {value} rad is outside [{min}, {max}]")]
    JointOutOfLimits {
        joint: usize,
        value: f64,
        min: f64,
        max: f64,
    },
    /// A mount degree of freedom lies outside its range.
    #[error("mount axis {axis} = {value} m is outside [{min}, {max}]")]
    MountOutOfLimits {
        axis: &'static str,
        value: f64,
        min: f64,
        max: f64,
    },
    /// The mount state is of another kind than the mount (e.g. a gantry state for a fixed mount).
    #[error("mount state {state} does not fit mount {mount}")]
    MountStateMismatch {
        mount: &'static str,
        state: &'static str,
    },
    /// A model or algorithm parameter is invalid (non-positive step, empty interval, ...).
    #[error("invalid parameter {name}: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// Reading or writing the reachability cache failed.
    #[error("reachability cache {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Result with [`ArmError`].
pub type Result<T, E = ArmError> = std::result::Result<T, E>;

pub(crate) fn ensure_finite(values: &[f64], what: &'static str) -> Result<()> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(ArmError::NonFinite { what })
    }
}

pub(crate) fn invalid(name: &'static str, reason: impl Into<String>) -> ArmError {
    ArmError::InvalidParameter {
        name,
        reason: reason.into(),
    }
}
