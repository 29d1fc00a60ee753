//! RoiCloud: ROI-labelled points of one frame, detector → planners, dashboard.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use nalgebra::{Isometry3, Point3};

use super::convert::{content, payload, point3f, pose_from_fb, pose_to_fb, string_or_empty, vec3f};
use crate::{fb, FrameId, MessageKind, Result, Wire};

/// ROI-labelled points in the world frame from one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct RoiCloud {
    pub points_in_world: Vec<Point3<f32>>,
    pub roi: Vec<bool>,
    pub sensor_origin_in_world: Point3<f64>,
    /// The camera pose of the frame the points come from, so planners need not guess it.
    pub world_from_camera: Isometry3<f64>,
    pub source_frame_seq: u64,
    /// The boot epoch of the trolley process that captured the frame.
    pub source_frame_epoch_ns: u64,
    pub invalid_pixels: u32,
    pub detector_id: String,
    /// Each point's fruit confidence, 0..=255 for 0..=1 (a learned detector's probability);
    /// empty when the labels are certain (0 or 1, e.g. the colour rule on mean colours).
    pub roi_confidence: Vec<u8>,
}

impl RoiCloud {
    /// The frame the points come from.
    pub fn source_frame(&self) -> FrameId {
        FrameId::new(self.source_frame_epoch_ns, self.source_frame_seq)
    }
}

impl Wire for RoiCloud {
    const KIND: MessageKind = MessageKind::RoiCloud;

    fn size_hint(&self) -> usize {
        self.points_in_world.len() * 13 + self.roi_confidence.len() + 1024
    }

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let points: Vec<fb::Vec3> = self.points_in_world.iter().map(vec3f).collect();
        let points = fbb.create_vector(&points);
        let flags: Vec<u8> = self.roi.iter().map(|&r| u8::from(r)).collect();
        let roi = fbb.create_vector(&flags);
        let detector = fbb.create_string(&self.detector_id);
        let confidence =
            (!self.roi_confidence.is_empty()).then(|| fbb.create_vector(&self.roi_confidence));
        let o = self.sensor_origin_in_world;
        let origin = fb::Vec3d::new(o.x, o.y, o.z);
        let pose = pose_to_fb(&self.world_from_camera);
        fb::RoiCloud::create(
            fbb,
            &fb::RoiCloudArgs {
                points: Some(points),
                roi: Some(roi),
                sensor_origin: Some(&origin),
                source_frame_seq: self.source_frame_seq,
                invalid_pixels: self.invalid_pixels,
                detector_id: Some(detector),
                world_from_camera: Some(&pose),
                source_frame_epoch_ns: self.source_frame_epoch_ns,
                roi_confidence: confidence,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let kind = Self::KIND;
        let m = payload(envelope.payload_as_roi_cloud())?;
        let points = m
            .points()
            .ok_or_else(|| content(kind, "points are missing"))?;
        let roi = m
            .roi()
            .ok_or_else(|| content(kind, "roi flags are missing"))?;
        if points.len() != roi.len() {
            return Err(content(
                kind,
                format!("{} points but {} roi flags", points.len(), roi.len()),
            ));
        }
        let roi_confidence: Vec<u8> = m.roi_confidence().map(|c| c.iter().collect()).unwrap_or_default();
        if !roi_confidence.is_empty() && roi_confidence.len() != points.len() {
            return Err(content(
                kind,
                format!("{} points but {} confidences", points.len(), roi_confidence.len()),
            ));
        }
        let origin = m
            .sensor_origin()
            .ok_or_else(|| content(kind, "sensor origin is missing"))?;
        let origin = Point3::new(origin.x(), origin.y(), origin.z());
        if origin.iter().any(|v| !v.is_finite()) {
            return Err(content(kind, "sensor origin is not finite"));
        }
        let world_from_camera = pose_from_fb(kind, "world_from_camera", m.world_from_camera())?;
        // Non-finite points are kept: the map skips and counts them.
        Ok(RoiCloud {
            points_in_world: points.iter().map(point3f).collect(),
            roi: roi.iter().map(|r| r != 0).collect(),
            sensor_origin_in_world: origin,
            world_from_camera,
            source_frame_seq: m.source_frame_seq(),
            source_frame_epoch_ns: m.source_frame_epoch_ns(),
            invalid_pixels: m.invalid_pixels(),
            detector_id: string_or_empty(m.detector_id()),
            roi_confidence,
        })
    }
}
