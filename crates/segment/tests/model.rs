//! The committed fruit model (detector-service/model/) loads, runs on seeded simulator frames
//! and finds the unripe green fruit the HSI rule cannot see.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use glasshouse_detect::{
    detect_with, DepthFrame, DetectError, DetectorConfig, FruitDetector, HsiRule,
};
use glasshouse_segment::OnnxFruitModel;
use glasshouse_sim::{CameraModel, FruitColour, RgbdImage, ScenarioKind, Scene};
use nalgebra::Isometry3;

const MODEL: &[u8] = include_bytes!("../../../detector-service/model/fruit-segmenter.onnx");

/// A seeded scenario-2 frame at 320x240 from the scene's initial view, with its labels.
fn frame(colour: FruitColour) -> (RgbdImage, Vec<u8>, Isometry3<f64>) {
    let scene = Scene::generate_with_fruit(ScenarioKind::Two, 11, colour);
    let camera = CameraModel::with_resolution(320, 240);
    let pose = scene.initial_camera_pose();
    let image = scene.render(&camera, &pose, 11);
    let labels = scene.fruit_label_image(&camera, &pose);
    (image, labels, pose)
}

/// Pixel precision and recall of `probability >= 0.5` against the labels, over pixels with depth.
fn precision_recall(image: &RgbdImage, labels: &[u8], probability: &[f32]) -> (f64, f64) {
    let (mut tp, mut fp, mut fn_) = (0u32, 0u32, 0u32);
    for ((&d, &l), &p) in image.depth_m.iter().zip(labels).zip(probability) {
        if !d.is_finite() {
            continue;
        }
        match (p >= 0.5, l == 1) {
            (true, true) => tp += 1,
            (true, false) => fp += 1,
            (false, true) => fn_ += 1,
            _ => {}
        }
    }
    assert!(
        tp + fn_ > 500,
        "the view must show fruit: {} fruit pixels",
        tp + fn_
    );
    (
        tp as f64 / (tp + fp).max(1) as f64,
        tp as f64 / (tp + fn_) as f64,
    )
}

/// ROI points the detector finds in the frame.
fn roi_points(image: &RgbdImage, pose: &Isometry3<f64>, detector: &dyn FruitDetector) -> usize {
    let depth = image.depth_as_u16(0.001);
    let frame = DepthFrame {
        intrinsics: image.intrinsics,
        depth: &depth,
        depth_scale_m: 0.001,
        rgb: &image.rgb,
    };
    let cloud = detect_with(&frame, pose, &DetectorConfig::default(), detector).unwrap();
    assert!(cloud
        .roi
        .iter()
        .zip(&cloud.confidence)
        .all(|(&roi, &c)| (0.0..=1.0).contains(&c) && roi == (c >= 0.5)));
    cloud.roi.iter().filter(|&&r| r).count()
}

#[test]
fn the_model_finds_green_fruit_the_hsi_rule_misses() {
    let model = OnnxFruitModel::from_bytes(MODEL).unwrap();
    let (image, labels, pose) = frame(FruitColour::Green);
    let probability = model.probabilities(&image.rgb, 320, 240).unwrap();
    let (precision, recall) = precision_recall(&image, &labels, &probability);
    assert!(
        precision >= 0.9 && recall >= 0.9,
        "precision {precision:.3}, recall {recall:.3}"
    );

    let learned = roi_points(&image, &pose, &model);
    let hsi = roi_points(&image, &pose, &HsiRule::default());
    eprintln!("green: precision {precision:.3}, recall {recall:.3}, ROI points model {learned}, HSI {hsi}");
    assert!(learned >= 100, "{learned} ROI points from the model");
    assert!(
        hsi * 50 <= learned,
        "HSI {hsi} against the model's {learned}"
    );
}

#[test]
fn on_red_fruit_the_model_agrees_with_the_hsi_rule() {
    let model = OnnxFruitModel::from_bytes(MODEL).unwrap();
    let (image, labels, pose) = frame(FruitColour::Red);
    let probability = model.probabilities(&image.rgb, 320, 240).unwrap();
    let (precision, recall) = precision_recall(&image, &labels, &probability);
    assert!(
        precision >= 0.9 && recall >= 0.9,
        "precision {precision:.3}, recall {recall:.3}"
    );
    let learned = roi_points(&image, &pose, &model) as f64;
    let hsi = roi_points(&image, &pose, &HsiRule::default()) as f64;
    eprintln!(
        "red: precision {precision:.3}, recall {recall:.3}, ROI points model {learned}, HSI {hsi}"
    );
    assert!(
        (learned / hsi - 1.0).abs() < 0.15,
        "model {learned} vs HSI {hsi} ROI points"
    );
}

#[test]
fn green_and_red_twins_differ_only_in_colour() {
    let (red, red_labels, _) = frame(FruitColour::Red);
    let (green, green_labels, _) = frame(FruitColour::Green);
    assert_eq!(red_labels, green_labels);
    let bits = |i: &RgbdImage| i.depth_m.iter().map(|d| d.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&red), bits(&green));
    assert_ne!(red.rgb, green.rgb);
}

#[test]
fn bad_models_and_inputs_are_clear_errors() {
    let err = OnnxFruitModel::from_bytes(b"not a model").err().unwrap();
    assert!(
        matches!(&err, DetectError::Model(m) if m.contains("ONNX")),
        "{err}"
    );
    // A truncated model fails to load; it does not panic.
    assert!(OnnxFruitModel::from_bytes(&MODEL[..MODEL.len() / 2]).is_err());

    let model = OnnxFruitModel::from_bytes(MODEL).unwrap();
    let err = model.probabilities(&[0; 10], 4, 4).unwrap_err();
    assert!(
        err.to_string().contains("10 rgb bytes for a 4x4 image"),
        "{err}"
    );
    // A second size gets its own plan, and going back to the first still works.
    assert_eq!(
        model.probabilities(&[200; 3 * 8 * 6], 8, 6).unwrap().len(),
        48
    );
    assert_eq!(
        model.probabilities(&[200; 3 * 4 * 4], 4, 4).unwrap().len(),
        16
    );
}
