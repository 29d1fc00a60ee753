//! Conversions shared by the message modules: poses, boxes, intrinsics, strings, content errors.

use flatbuffers::{FlatBufferBuilder, WIPOffset};
use glasshouse_geom::{Aabb, CameraIntrinsics};
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion};

use crate::{fb, MessageKind, ProtoError, Result};

pub(crate) fn pose_to_fb(pose: &Isometry3<f64>) -> fb::Pose {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    fb::Pose::new(
        &fb::Vec3d::new(t.x, t.y, t.z),
        &fb::Quat::new(q.i, q.j, q.k, q.w),
    )
}

pub(crate) fn intrinsics_to_fb(k: &CameraIntrinsics) -> fb::Intrinsics {
    fb::Intrinsics::new(k.width, k.height, k.fx, k.fy, k.cx, k.cy)
}

pub(crate) fn vec3f(p: &Point3<f32>) -> fb::Vec3 {
    fb::Vec3::new(p.x, p.y, p.z)
}

pub(crate) fn box_to_fb(b: &Aabb) -> fb::Box3 {
    fb::Box3::new(&vec3f(&b.min.cast()), &vec3f(&b.max.cast()))
}

pub(crate) fn strings<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    items: &[String],
) -> WIPOffset<flatbuffers::Vector<'a, flatbuffers::ForwardsUOffset<&'a str>>> {
    let offsets: Vec<_> = items.iter().map(|s| fbb.create_string(s)).collect();
    fbb.create_vector(&offsets)
}

pub(crate) fn content(kind: MessageKind, reason: impl Into<String>) -> ProtoError {
    ProtoError::Content {
        kind,
        reason: reason.into(),
    }
}

/// The payload table of a verified envelope, or [`ProtoError::NoPayload`].
pub(crate) fn payload<T>(table: Option<T>) -> Result<T> {
    table.ok_or(ProtoError::NoPayload)
}

pub(crate) fn pose_from_fb(
    kind: MessageKind,
    field: &str,
    pose: Option<&fb::Pose>,
) -> Result<Isometry3<f64>> {
    let pose = pose.ok_or_else(|| content(kind, format!("{field} is missing")))?;
    let t = pose.translation();
    let r = pose.rotation();
    let values = [t.x(), t.y(), t.z(), r.x(), r.y(), r.z(), r.w()];
    if values.iter().any(|v| !v.is_finite()) {
        return Err(content(kind, format!("{field} is not finite")));
    }
    let q = Quaternion::new(r.w(), r.x(), r.y(), r.z());
    if q.norm() < 1e-6 {
        return Err(content(
            kind,
            format!("{field} has a zero rotation quaternion"),
        ));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(t.x(), t.y(), t.z()),
        unit_rotation(q),
    ))
}

pub(crate) fn intrinsics_from_fb(
    kind: MessageKind,
    k: Option<&fb::Intrinsics>,
) -> Result<CameraIntrinsics> {
    let k = k.ok_or_else(|| content(kind, "intrinsics are missing"))?;
    let intrinsics = CameraIntrinsics {
        width: k.width(),
        height: k.height(),
        fx: k.fx(),
        fy: k.fy(),
        cx: k.cx(),
        cy: k.cy(),
    };
    if !intrinsics.is_valid() {
        return Err(content(kind, format!("invalid intrinsics {intrinsics:?}")));
    }
    Ok(intrinsics)
}

pub(crate) fn point3f(v: &fb::Vec3) -> Point3<f32> {
    Point3::new(v.x(), v.y(), v.z())
}

pub(crate) fn box_from_fb(kind: MessageKind, field: &str, b: Option<&fb::Box3>) -> Result<Aabb> {
    let b = b.ok_or_else(|| content(kind, format!("{field} is missing")))?;
    let aabb = Aabb::new(point3f(b.min()).cast(), point3f(b.max()).cast());
    let finite = aabb
        .min
        .iter()
        .chain(aabb.max.iter())
        .all(|v| v.is_finite());
    if !finite || (0..3).any(|i| aabb.min[i] > aabb.max[i]) {
        return Err(content(
            kind,
            format!("{field} is not a finite box with min <= max"),
        ));
    }
    Ok(aabb)
}

pub(crate) fn string_or_empty(s: Option<&str>) -> String {
    s.unwrap_or_default().to_owned()
}

pub(crate) fn strings_from_fb(
    v: Option<flatbuffers::Vector<'_, flatbuffers::ForwardsUOffset<&str>>>,
) -> Vec<String> {
    v.map(|v| v.iter().map(str::to_owned).collect())
        .unwrap_or_default()
}

pub(crate) fn unknown_enum(kind: MessageKind, field: &str, value: u8) -> ProtoError {
    content(kind, format!("{field} has unknown value {value}"))
}

/// The rotation of a decoded quaternion. One that is unit to within rounding is taken as it is,
/// so a pose read back is bit for bit the pose written; any other is normalised.
pub(crate) fn unit_rotation(q: Quaternion<f64>) -> UnitQuaternion<f64> {
    if (q.norm_squared() - 1.0).abs() <= 4.0 * f64::EPSILON {
        UnitQuaternion::new_unchecked(q)
    } else {
        // Scaled by its largest component first: squaring components near f64::MAX overflows
        // the norm to infinity, and dividing by it would leave a zero quaternion.
        UnitQuaternion::from_quaternion(q / q.coords.amax())
    }
}
