//! RgbdFrame: one RGB-D capture, edge → detectors.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use glasshouse_geom::CameraIntrinsics;
use nalgebra::Isometry3;

use super::convert::{content, intrinsics_from_fb, intrinsics_to_fb, payload, pose_from_fb, pose_to_fb};
use crate::{fb, MessageKind, Result, Wire};

/// One RGB-D capture. `depth_m = depth[i] * depth_scale_m`; 0 means no measurement.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbdFrame {
    pub intrinsics: CameraIntrinsics,
    pub world_from_camera: Isometry3<f64>,
    pub depth_scale_m: f32,
    pub min_range_m: f32,
    pub max_range_m: f32,
    pub depth: Vec<u16>,
    pub rgb: Vec<u8>,
}

impl Wire for RgbdFrame {
    const KIND: MessageKind = MessageKind::RgbdFrame;

    fn size_hint(&self) -> usize {
        self.depth.len() * 2 + self.rgb.len() + 1024
    }

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let depth = fbb.create_vector(&self.depth);
        let rgb = fbb.create_vector(&self.rgb);
        let intrinsics = intrinsics_to_fb(&self.intrinsics);
        let pose = pose_to_fb(&self.world_from_camera);
        fb::RgbdFrame::create(
            fbb,
            &fb::RgbdFrameArgs {
                intrinsics: Some(&intrinsics),
                world_from_camera: Some(&pose),
                depth_scale_m: self.depth_scale_m,
                min_range_m: self.min_range_m,
                max_range_m: self.max_range_m,
                depth: Some(depth),
                rgb: Some(rgb),
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let kind = Self::KIND;
        let m = payload(envelope.payload_as_rgbd_frame())?;
        let intrinsics = intrinsics_from_fb(kind, m.intrinsics())?;
        let world_from_camera = pose_from_fb(kind, "world_from_camera", m.world_from_camera())?;
        let pixels = intrinsics.pixel_count();
        let depth = m.depth().ok_or_else(|| content(kind, "depth is missing"))?;
        let rgb = m.rgb().ok_or_else(|| content(kind, "rgb is missing"))?;
        if depth.len() != pixels {
            return Err(content(
                kind,
                format!("depth has {} values for {pixels} pixels", depth.len()),
            ));
        }
        if rgb.len() != 3 * pixels {
            return Err(content(
                kind,
                format!("rgb has {} bytes for {pixels} pixels", rgb.len()),
            ));
        }
        let scale = m.depth_scale_m();
        if !(scale.is_finite() && scale > 0.0) {
            return Err(content(
                kind,
                format!("depth scale {scale} is not positive"),
            ));
        }
        Ok(RgbdFrame {
            intrinsics,
            world_from_camera,
            depth_scale_m: scale,
            min_range_m: m.min_range_m(),
            max_range_m: m.max_range_m(),
            depth: depth.iter().collect(),
            rgb: rgb.bytes().to_vec(),
        })
    }
}
