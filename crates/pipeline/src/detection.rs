//! Detection: one RGB-D frame in, its ROI-labelled world cloud out.

use glasshouse_detect::{detect, DepthFrame, DetectError, DetectorConfig};
use glasshouse_proto::{FrameId, RgbdFrame, RoiCloud};

/// Runs the detector ([`glasshouse_detect::detect`]: 1 cm averaging, the paper's HSI rule,
/// back-projection with the frame's intrinsics and pose) on the frame `frame_id` of its trolley.
pub fn detect_frame(
    frame: &RgbdFrame,
    frame_id: FrameId,
    detector_id: &str,
    config: &DetectorConfig,
) -> Result<RoiCloud, DetectError> {
    let depth_frame = DepthFrame {
        intrinsics: frame.intrinsics,
        depth: &frame.depth,
        depth_scale_m: f64::from(frame.depth_scale_m),
        rgb: &frame.rgb,
    };
    let cloud = detect(&depth_frame, &frame.world_from_camera, config)?;
    Ok(RoiCloud {
        points_in_world: cloud.points_in_world,
        roi: cloud.roi,
        sensor_origin_in_world: cloud.sensor_origin_in_world,
        world_from_camera: frame.world_from_camera,
        source_frame_seq: frame_id.seq,
        source_frame_epoch_ns: frame_id.epoch_ns,
        invalid_pixels: cloud.invalid_pixels.min(u32::MAX as usize) as u32,
        detector_id: detector_id.to_owned(),
    })
}
