//! Detection: one RGB-D frame in, its ROI-labelled world cloud out.

use glasshouse_detect::{
    detect_with, DepthFrame, DetectError, DetectorConfig, FruitDetector, HsiVotes,
};
use glasshouse_proto::{FrameId, RgbdFrame, RoiCloud};

/// Runs the detector ([`glasshouse_detect::detect`]: 1 cm averaging, the paper's HSI rule,
/// back-projection with the frame's intrinsics and pose) on the frame `frame_id` of its trolley.
pub fn detect_frame(
    frame: &RgbdFrame,
    frame_id: FrameId,
    detector_id: &str,
    config: &DetectorConfig,
) -> Result<RoiCloud, DetectError> {
    detect_frame_with(frame, frame_id, detector_id, config, &HsiVotes(config.rule))
}

/// [`detect_frame`] with the points labelled by `detector` (the HSI rule or a learned model);
/// a detector whose confidences are not all 0 or 1 puts them in the cloud.
pub fn detect_frame_with(
    frame: &RgbdFrame,
    frame_id: FrameId,
    detector_id: &str,
    config: &DetectorConfig,
    detector: &dyn FruitDetector,
) -> Result<RoiCloud, DetectError> {
    let depth_frame = DepthFrame {
        intrinsics: frame.intrinsics,
        depth: &frame.depth,
        depth_scale_m: f64::from(frame.depth_scale_m),
        rgb: &frame.rgb,
    };
    let cloud = detect_with(&depth_frame, &frame.world_from_camera, config, detector)?;
    let certain = cloud.confidence.iter().all(|&c| c == 0.0 || c == 1.0);
    let roi_confidence = if certain {
        Vec::new()
    } else {
        cloud
            .confidence
            .iter()
            .map(|&c| (c * 255.0).round() as u8)
            .collect()
    };
    Ok(RoiCloud {
        points_in_world: cloud.points_in_world,
        roi: cloud.roi,
        sensor_origin_in_world: cloud.sensor_origin_in_world,
        world_from_camera: frame.world_from_camera,
        source_frame_seq: frame_id.seq,
        source_frame_epoch_ns: frame_id.epoch_ns,
        invalid_pixels: cloud.invalid_pixels.min(u32::MAX as usize) as u32,
        detector_id: detector_id.to_owned(),
        roi_confidence,
    })
}
