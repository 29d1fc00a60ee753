//! RgbdFrame: one RGB-D capture, edge → detectors.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, Vector, WIPOffset};
use glasshouse_geom::CameraIntrinsics;
use nalgebra::Isometry3;

use super::convert::{content, intrinsics_from_fb, intrinsics_to_fb, payload, pose_from_fb, pose_to_fb};
use crate::pixels::{decode_plane, encode_plane, ImageEncoding, PixelCodecError, PlaneShape, Sample};
use crate::{fb, MessageKind, Result, Wire};

/// One RGB-D capture. `depth_m = depth[i] * depth_scale_m`; 0 means no measurement.
///
/// `depth` and `rgb` always hold the plain planes; the encodings say how each plane is sent
/// (and, on a received frame, how it was sent).
#[derive(Clone, Debug, PartialEq)]
pub struct RgbdFrame {
    pub intrinsics: CameraIntrinsics,
    pub world_from_camera: Isometry3<f64>,
    pub depth_scale_m: f32,
    pub min_range_m: f32,
    pub max_range_m: f32,
    pub depth: Vec<u16>,
    pub rgb: Vec<u8>,
    pub depth_encoding: ImageEncoding,
    pub rgb_encoding: ImageEncoding,
}

/// Bytes per pixel of the plain planes (u16 depth + RGB8): bounds what a compressed frame may
/// decode to by the raw frame's size limit.
const RAW_BYTES_PER_PIXEL: usize = 5;

impl RgbdFrame {
    /// The same frame, both planes sent as `encoding`.
    pub fn encoded_as(mut self, encoding: ImageEncoding) -> Self {
        self.depth_encoding = encoding;
        self.rgb_encoding = encoding;
        self
    }

    fn depth_shape(&self) -> PlaneShape {
        PlaneShape {
            width: self.intrinsics.width as usize,
            channels: 1,
        }
    }

    fn rgb_shape(&self) -> PlaneShape {
        PlaneShape {
            width: self.intrinsics.width as usize,
            channels: 3,
        }
    }
}

/// A plane as written: its encoding and, when not raw, its encoded bytes.
fn encode_for_wire<T: Sample>(
    samples: &[T],
    shape: PlaneShape,
    encoding: ImageEncoding,
) -> (fb::ImageEncoding, Option<Vec<u8>>) {
    match encoding {
        ImageEncoding::Raw => (fb::ImageEncoding::Raw, None),
        ImageEncoding::LeftDeltaZstd => match encode_plane(samples, shape) {
            Some(bytes) => (fb::ImageEncoding::LeftDeltaZstd, Some(bytes)),
            None => (fb::ImageEncoding::Raw, None),
        },
    }
}

impl Wire for RgbdFrame {
    const KIND: MessageKind = MessageKind::RgbdFrame;

    fn size_hint(&self) -> usize {
        let raw = |e: ImageEncoding, bytes: usize| if e == ImageEncoding::Raw { bytes } else { bytes / 4 };
        raw(self.depth_encoding, self.depth.len() * 2) + raw(self.rgb_encoding, self.rgb.len()) + 1024
    }

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let (depth_encoding, depth_encoded) =
            encode_for_wire(&self.depth, self.depth_shape(), self.depth_encoding);
        let (rgb_encoding, rgb_encoded) =
            encode_for_wire(&self.rgb, self.rgb_shape(), self.rgb_encoding);
        let depth = depth_encoded.is_none().then(|| fbb.create_vector(&self.depth));
        let rgb = rgb_encoded.is_none().then(|| fbb.create_vector(&self.rgb));
        let depth_encoded = depth_encoded.map(|b| fbb.create_vector(&b));
        let rgb_encoded = rgb_encoded.map(|b| fbb.create_vector(&b));
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
                depth,
                rgb,
                depth_encoding,
                depth_encoded,
                rgb_encoding,
                rgb_encoded,
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
        if pixels > kind.max_bytes() / RAW_BYTES_PER_PIXEL {
            return Err(content(kind, format!("{pixels} pixels exceed the frame size limit")));
        }
        let width = intrinsics.width as usize;
        let (depth, depth_encoding) = read_plane(
            PlaneShape { width, channels: 1 },
            pixels,
            (m.depth_encoding(), m.depth_encoded()),
            || m.depth().map(|d| d.iter().collect()),
        )
        .map_err(|e| content(kind, format!("depth: {e}")))?;
        let (rgb, rgb_encoding) = read_plane(
            PlaneShape { width, channels: 3 },
            pixels,
            (m.rgb_encoding(), m.rgb_encoded()),
            || m.rgb().map(|d| d.bytes().to_vec()),
        )
        .map_err(|e| content(kind, format!("rgb: {e}")))?;
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
            depth,
            rgb,
            depth_encoding,
            rgb_encoding,
        })
    }
}

/// Reads one plane of `pixels` pixels: the raw vector, or the encoded bytes through
/// [`decode_plane`]; checks its length either way.
fn read_plane<T: Sample>(
    shape: PlaneShape,
    pixels: usize,
    (encoding, encoded): (fb::ImageEncoding, Option<Vector<'_, u8>>),
    raw: impl FnOnce() -> Option<Vec<T>>,
) -> Result<(Vec<T>, ImageEncoding), PixelCodecError> {
    let samples = pixels * shape.channels;
    let (plane, encoding) = match encoding {
        fb::ImageEncoding::Raw => (raw().ok_or(PixelCodecError::Missing)?, ImageEncoding::Raw),
        fb::ImageEncoding::LeftDeltaZstd => {
            let bytes = encoded.ok_or(PixelCodecError::Missing)?.bytes();
            (decode_plane(bytes, shape, samples)?, ImageEncoding::LeftDeltaZstd)
        }
        other => return Err(PixelCodecError::UnknownEncoding(other.0)),
    };
    if plane.len() != samples {
        return Err(PixelCodecError::Length {
            expected: samples,
            found: plane.len(),
        });
    }
    Ok((plane, encoding))
}
