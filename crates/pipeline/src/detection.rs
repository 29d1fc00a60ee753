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
/// a detector whose confidences are not all 0 or 1 puts them in the cloud. Each ROI point
/// carries its colour (`roi_rgb`: the mean of the pixels it stands for), whatever the detector.
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
    let roi_rgb = roi_colours(&cloud.roi, &cloud.rgb);
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
        roi_rgb,
    })
}

/// The colours of the ROI points, in their order, 3 bytes each (`RoiCloud::roi_rgb`).
fn roi_colours(roi: &[bool], rgb: &[[u8; 3]]) -> Vec<u8> {
    let colours = rgb.iter().zip(roi).filter(|(_, &is_roi)| is_roi);
    colours.flat_map(|(c, _)| *c).collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use glasshouse_proto::{samples, RoiColours};

    use super::*;

    #[test]
    fn each_roi_point_carries_its_pixels_colour_in_the_order_of_the_roi_points() {
        // Red pixels on the left half of the image, green on the right, all 1 m away: each
        // pixel is its own 1 cm voxel, the red ones fruit.
        let mut frame = samples::rgbd_frame();
        let width = frame.intrinsics.width as usize;
        frame.depth = vec![1000; frame.depth.len()];
        frame.rgb = (0..frame.depth.len())
            .flat_map(|i| match i % width < width / 2 {
                true => [200, 30, 20],
                false => [30, 160, 40],
            })
            .collect();
        let cloud = detect_frame(&frame, FrameId::new(1, 2), "d1", &Default::default()).unwrap();
        let roi_points = cloud.roi.iter().filter(|&&r| r).count();
        assert_eq!(roi_points, frame.depth.len() / 2);
        let RoiColours::Rgb(colours) = cloud.roi_colours() else {
            panic!("no colours: {:?}", cloud.roi_colours());
        };
        assert_eq!(colours.len(), roi_points);
        assert!(colours.iter().all(|&c| c == [200, 30, 20]), "{colours:?}");
    }
}
