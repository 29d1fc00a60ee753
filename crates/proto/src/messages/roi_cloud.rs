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
    /// The colour of each ROI point, in the order of the ROI points, 3 bytes (R, G, B) each: the
    /// mean of the pixels the point stands for; empty when not sent. Kept as sent: read it
    /// through [`RoiCloud::roi_colours`], which takes any other length than 3 × the ROI points
    /// as no colour.
    pub roi_rgb: Vec<u8>,
}

/// What a cloud says about its ROI points' colours ([`RoiCloud::roi_colours`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RoiColours<'a> {
    /// Not sent (an older detector, or a cloud without ROI points).
    Absent,
    /// One colour per ROI point, in the order of the ROI points.
    Rgb(&'a [[u8; 3]]),
    /// A broken sender: `bytes` colour bytes for `roi_points` ROI points. Taken as no colour.
    WrongLength { bytes: usize, roi_points: usize },
}

impl RoiCloud {
    /// The frame the points come from.
    pub fn source_frame(&self) -> FrameId {
        FrameId::new(self.source_frame_epoch_ns, self.source_frame_seq)
    }

    /// The ROI points' colours, when the cloud carries one for each.
    pub fn roi_colours(&self) -> RoiColours<'_> {
        if self.roi_rgb.is_empty() {
            return RoiColours::Absent;
        }
        let roi_points = self.roi.iter().filter(|&&r| r).count();
        let (colours, rest) = self.roi_rgb.as_chunks::<3>();
        if colours.len() != roi_points || !rest.is_empty() {
            let bytes = self.roi_rgb.len();
            return RoiColours::WrongLength { bytes, roi_points };
        }
        RoiColours::Rgb(colours)
    }
}

impl Wire for RoiCloud {
    const KIND: MessageKind = MessageKind::RoiCloud;

    fn size_hint(&self) -> usize {
        self.points_in_world.len() * 13 + self.roi_confidence.len() + self.roi_rgb.len() + 1024
    }

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let points: Vec<fb::Vec3> = self.points_in_world.iter().map(vec3f).collect();
        let points = fbb.create_vector(&points);
        let flags: Vec<u8> = self.roi.iter().map(|&r| u8::from(r)).collect();
        let roi = fbb.create_vector(&flags);
        let detector = fbb.create_string(&self.detector_id);
        let confidence =
            (!self.roi_confidence.is_empty()).then(|| fbb.create_vector(&self.roi_confidence));
        let roi_rgb = (!self.roi_rgb.is_empty()).then(|| fbb.create_vector(&self.roi_rgb));
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
                roi_rgb,
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
        let roi_confidence: Vec<u8> = m
            .roi_confidence()
            .map(|c| c.iter().collect())
            .unwrap_or_default();
        if !roi_confidence.is_empty() && roi_confidence.len() != points.len() {
            return Err(content(
                kind,
                format!(
                    "{} points but {} confidences",
                    points.len(),
                    roi_confidence.len()
                ),
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
            // Kept as sent, whatever its length: `roi_colours` judges it.
            roi_rgb: m.roi_rgb().map(|c| c.bytes().to_vec()).unwrap_or_default(),
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::{decode_typed, encode, samples, Message};

    /// A detector from before the points' colours: it wrote no `roi_rgb`.
    #[derive(Clone, Debug)]
    struct OldSender(RoiCloud);

    impl From<OldSender> for Message {
        fn from(old: OldSender) -> Self {
            Message::RoiCloud(old.0)
        }
    }

    impl Wire for OldSender {
        const KIND: MessageKind = MessageKind::RoiCloud;

        fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
            let without = RoiCloud {
                roi_rgb: Vec::new(),
                ..self.0.clone()
            };
            without.write_payload(fbb)
        }

        fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
            RoiCloud::read_payload(envelope).map(OldSender)
        }
    }

    fn round_trip(cloud: &RoiCloud) -> RoiCloud {
        decode_typed::<RoiCloud>(&encode(&samples::header(1), cloud))
            .unwrap()
            .1
    }

    #[test]
    fn the_roi_points_colours_round_trip_in_the_order_of_the_roi_points() {
        let mut cloud = samples::roi_cloud();
        cloud.roi = vec![true, false, true];
        cloud.roi_rgb = vec![200, 30, 20, 90, 10, 5];
        let read = round_trip(&cloud);
        assert_eq!(read.roi_rgb, cloud.roi_rgb);
        assert_eq!(
            read.roi_colours(),
            RoiColours::Rgb(&[[200, 30, 20], [90, 10, 5]])
        );
    }

    #[test]
    fn a_cloud_from_a_detector_without_colours_reads_with_none() {
        let sample = samples::roi_cloud();
        let old = encode(&samples::header(1), &OldSender(sample.clone()));
        let (_, read) = decode_typed::<RoiCloud>(&old).unwrap();
        assert!(read.roi_rgb.is_empty());
        assert_eq!(read.roi_colours(), RoiColours::Absent);
        // Otherwise the cloud as sent (compared as text: a point is NaN).
        let sent = RoiCloud {
            roi_rgb: Vec::new(),
            ..sample
        };
        assert_eq!(format!("{read:?}"), format!("{sent:?}"));
    }

    #[test]
    fn colours_of_the_wrong_length_decode_and_read_as_no_colour() {
        // Two bytes short, one point too many, and colours for every point rather than the ROI
        // points: each is a broken sender whose cloud still counts, without colour.
        for bytes in [1, 4, 9] {
            let cloud = RoiCloud {
                roi_rgb: vec![7; bytes],
                ..samples::roi_cloud()
            };
            let read = round_trip(&cloud);
            assert_eq!(read.roi_rgb.len(), bytes);
            assert_eq!(
                read.roi_colours(),
                RoiColours::WrongLength {
                    bytes,
                    roi_points: 1
                }
            );
        }
    }
}
