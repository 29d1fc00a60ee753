//! FruitEstimates: one trolley's fruits, owning planner → dashboard (also the simulator's truth).

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use nalgebra::{Point3, Vector3};

use super::convert::{content, payload, point3f, string_or_empty, vec3f};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Debug, PartialEq)]
pub struct Fruit {
    pub id: u32,
    pub centre_in_world: Point3<f32>,
    pub box_min: Point3<f32>,
    pub box_max: Point3<f32>,
    pub volume_m3: f32,
    pub voxel_count: u32,
    pub confidence: f32,
    /// The fitted whole-fruit estimate; `None` when the planner made no fit.
    pub fitted: Option<FittedEllipsoid>,
}

/// Axis-aligned ellipsoid estimate of one fruit, world frame, metres.
#[derive(Clone, Debug, PartialEq)]
pub struct FittedEllipsoid {
    pub centre_in_world: Point3<f32>,
    pub semi_axes_m: Vector3<f32>,
    /// `4/3·π·a·b·c`.
    pub volume_m3: f32,
    /// `8·a·b·c`, comparable with the box estimate's volume.
    pub box_volume_m3: f32,
    /// Share of the fitted surface the map has observed, 0..1.
    pub confidence: f32,
    /// False when the fit was degenerate and this is the ellipsoid inscribed in the cluster's box.
    pub is_fit: bool,
}

#[derive(Clone, Debug, PartialEq)]
pub struct FruitEstimates {
    pub fruits: Vec<Fruit>,
    pub based_on_seq: u64,
    pub planner_id: String,
}

impl Wire for FruitEstimates {
    const KIND: MessageKind = MessageKind::FruitEstimates;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let fruits: Vec<_> = self.fruits.iter().map(|f| write_fruit(fbb, f)).collect();
        let fruits = fbb.create_vector(&fruits);
        let planner = fbb.create_string(&self.planner_id);
        fb::FruitEstimates::create(
            fbb,
            &fb::FruitEstimatesArgs {
                fruits: Some(fruits),
                based_on_seq: self.based_on_seq,
                planner_id: Some(planner),
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_fruit_estimates())?;
        let fruits = m
            .fruits()
            .map(|fs| {
                fs.iter()
                    .map(|f| read_fruit(Self::KIND, f))
                    .collect::<Result<Vec<_>>>()
            })
            .transpose()?
            .unwrap_or_default();
        Ok(FruitEstimates {
            fruits,
            based_on_seq: m.based_on_seq(),
            planner_id: string_or_empty(m.planner_id()),
        })
    }
}

pub(super) fn write_fruit<'a>(fbb: &mut FlatBufferBuilder<'a>, f: &Fruit) -> WIPOffset<fb::Fruit<'a>> {
    let centre = vec3f(&f.centre_in_world);
    let bbox = fb::Box3::new(&vec3f(&f.box_min), &vec3f(&f.box_max));
    let fitted = f.fitted.as_ref().map(|e| {
        let centre = vec3f(&e.centre_in_world);
        let semi_axes = fb::Vec3::new(e.semi_axes_m.x, e.semi_axes_m.y, e.semi_axes_m.z);
        fb::FittedEllipsoid::create(
            fbb,
            &fb::FittedEllipsoidArgs {
                centre: Some(&centre),
                semi_axes: Some(&semi_axes),
                volume_m3: e.volume_m3,
                box_volume_m3: e.box_volume_m3,
                confidence: e.confidence,
                is_fit: e.is_fit,
            },
        )
    });
    fb::Fruit::create(
        fbb,
        &fb::FruitArgs {
            id: f.id,
            centre: Some(&centre),
            box_: Some(&bbox),
            volume_m3: f.volume_m3,
            voxel_count: f.voxel_count,
            confidence: f.confidence,
            fitted,
        },
    )
}

fn read_fitted(kind: MessageKind, e: fb::FittedEllipsoid<'_>) -> Result<FittedEllipsoid> {
    let centre = e
        .centre()
        .ok_or_else(|| content(kind, "fitted ellipsoid centre is missing"))?;
    let axes = e
        .semi_axes()
        .ok_or_else(|| content(kind, "fitted ellipsoid semi-axes are missing"))?;
    Ok(FittedEllipsoid {
        centre_in_world: point3f(centre),
        semi_axes_m: Vector3::new(axes.x(), axes.y(), axes.z()),
        volume_m3: e.volume_m3(),
        box_volume_m3: e.box_volume_m3(),
        confidence: e.confidence(),
        is_fit: e.is_fit(),
    })
}

/// Reads one fruit; `kind` is the message it sits in, for error reports.
pub(super) fn read_fruit(kind: MessageKind, f: fb::Fruit<'_>) -> Result<Fruit> {
    let centre = f
        .centre()
        .ok_or_else(|| content(kind, "fruit centre is missing"))?;
    let bbox = f
        .box_()
        .ok_or_else(|| content(kind, "fruit box is missing"))?;
    let fitted = f.fitted().map(|e| read_fitted(kind, e)).transpose()?;
    Ok(Fruit {
        id: f.id(),
        centre_in_world: point3f(centre),
        box_min: point3f(bbox.min()),
        box_max: point3f(bbox.max()),
        volume_m3: f.volume_m3(),
        voxel_count: f.voxel_count(),
        confidence: f.confidence(),
        fitted,
    })
}
