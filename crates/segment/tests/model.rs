//! The committed fruit model (detector-service/model/) loads, runs on seeded simulator frames
//! and finds the fruit the HSI rule cannot see: unripe yellow-green fruit in the clean world
//! and leaf-green fruit, the leaves' own colour, in the realistic one. Its operating point
//! favours recall: it also labels some leaves, which the planner's fruit evidence (flat, thin)
//! turns away, so pixel precision is bounded low and recall high. The previous model (a
//! 3x3 colour MLP that takes any image size) still loads and runs; a model that reads depth
//! too is refused with a clear error.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use glasshouse_detect::{
    detect_with, DepthFrame, DetectError, DetectorConfig, FruitDetector, HsiRule,
};
use glasshouse_segment::OnnxFruitModel;
use glasshouse_sim::{
    CameraModel, FruitColour, RgbdImage, ScenarioKind, Scene, SceneOptions, WorldSettings,
};
use nalgebra::Isometry3;

const MODEL: &[u8] = include_bytes!("../../../detector-service/model/fruit-segmenter.onnx");
/// The previous model: a 3x3 colour MLP with input `rgb` [1, 3, H, W], any size.
const COLOUR_MLP_MODEL: &[u8] = include_bytes!("data/colour-mlp-3x3.onnx");
/// A tiny model of `train.py --depth`: input `rgbd` [1, 4, H, W].
const RGBD_MODEL: &[u8] = include_bytes!("data/rgbd-tiny.onnx");

/// A seeded scenario-2 frame at the camera's 640x480 from the scene's initial view, with its
/// labels.
fn frame(world: WorldSettings, colour: FruitColour) -> (RgbdImage, Vec<u8>, Isometry3<f64>) {
    let options = SceneOptions {
        fruit_colour: colour,
        ..world.scene
    };
    let scene = Scene::generate_with(ScenarioKind::Two, 11, &options);
    let camera = CameraModel::with_resolution(640, 480);
    let pose = scene.initial_camera_pose();
    let image = scene.render_with(&camera, &pose, 11, &world.perception);
    let labels = scene.fruit_label_image(&camera, &pose);
    (image, labels, pose)
}

/// The model's probabilities for a frame.
fn probabilities(model: &OnnxFruitModel, image: &RgbdImage) -> Vec<f32> {
    let (w, h) = (image.intrinsics.width, image.intrinsics.height);
    model.probabilities(&image.rgb, w, h).unwrap()
}

/// Pixel precision and recall of `probability >= 0.5` against the labels, over pixels with
/// depth (the pixels the detector turns into points).
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
        tp + fn_ > 2000,
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
fn the_model_finds_leaf_green_fruit_in_the_realistic_world() {
    let model = OnnxFruitModel::from_bytes(MODEL).unwrap();
    let (image, labels, pose) = frame(WorldSettings::realistic(), FruitColour::LeafGreen);
    let (precision, recall) = precision_recall(&image, &labels, &probabilities(&model, &image));
    let learned = roi_points(&image, &pose, &model);
    let hsi = roi_points(&image, &pose, &HsiRule::default());
    eprintln!(
        "leaf-green: precision {precision:.3}, recall {recall:.3}, ROI points model {learned}, \
         HSI {hsi}"
    );
    assert!(
        precision >= 0.25 && recall >= 0.9,
        "precision {precision:.3}, recall {recall:.3}"
    );
    assert!(learned >= 500, "{learned} ROI points from the model");
    assert!(
        hsi * 5 <= learned,
        "HSI {hsi} against the model's {learned}"
    );
}

#[test]
fn the_model_finds_green_fruit_the_hsi_rule_misses() {
    let model = OnnxFruitModel::from_bytes(MODEL).unwrap();
    let (image, labels, pose) = frame(WorldSettings::default(), FruitColour::Green);
    let (precision, recall) = precision_recall(&image, &labels, &probabilities(&model, &image));
    let learned = roi_points(&image, &pose, &model);
    let hsi = roi_points(&image, &pose, &HsiRule::default());
    eprintln!(
        "green: precision {precision:.3}, recall {recall:.3}, ROI points model {learned}, \
         HSI {hsi}"
    );
    assert!(
        precision >= 0.45 && recall >= 0.95,
        "precision {precision:.3}, recall {recall:.3}"
    );
    assert!(learned >= 100, "{learned} ROI points from the model");
    assert!(
        hsi * 50 <= learned,
        "HSI {hsi} against the model's {learned}"
    );
}

#[test]
fn on_red_fruit_the_model_finds_what_the_hsi_rule_finds() {
    let model = OnnxFruitModel::from_bytes(MODEL).unwrap();
    let (image, labels, pose) = frame(WorldSettings::default(), FruitColour::Red);
    let (precision, recall) = precision_recall(&image, &labels, &probabilities(&model, &image));
    let learned = roi_points(&image, &pose, &model) as f64;
    let hsi = roi_points(&image, &pose, &HsiRule::default()) as f64;
    eprintln!(
        "red: precision {precision:.3}, recall {recall:.3}, ROI points model {learned}, HSI {hsi}"
    );
    assert!(
        precision >= 0.45 && recall >= 0.95,
        "precision {precision:.3}, recall {recall:.3}"
    );
    assert!(
        hsi <= learned && learned <= 3.0 * hsi,
        "model {learned} vs HSI {hsi} ROI points"
    );
}

#[test]
fn green_and_red_twins_differ_only_in_colour() {
    let (red, red_labels, _) = frame(WorldSettings::default(), FruitColour::Red);
    let (green, green_labels, _) = frame(WorldSettings::default(), FruitColour::Green);
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
    // A model that reads depth as a fourth channel is refused at load, not on the first frame.
    let err = OnnxFruitModel::from_bytes(RGBD_MODEL).err().unwrap();
    assert!(
        err.to_string()
            .contains("input \"rgbd\" has 4 channels; the detector feeds 3"),
        "{err}"
    );

    let model = OnnxFruitModel::from_bytes(MODEL).unwrap();
    assert_eq!(model.size_multiple(), 8);
    let err = model.probabilities(&[0; 10], 4, 4).unwrap_err();
    assert!(
        err.to_string().contains("10 rgb bytes for a 4x4 image"),
        "{err}"
    );
    // Sizes that are not multiples of 8 are padded and cropped back; each size gets its own
    // plan, and going back to the first still works. Padding changes nothing inside.
    for (w, h) in [(8, 6), (13, 7), (4, 4), (8, 6)] {
        let p = model.probabilities(&vec![200; 3 * w * h], w as u32, h as u32);
        let p = p.unwrap();
        assert_eq!(p.len(), w * h);
        assert!(p.iter().all(|p| (0.0..=1.0).contains(p)));
    }
    // A 19x13 image is run as the 24x16 image with zeros at the bottom and right, and cropped.
    let (w, h, cw, ch) = (24usize, 16usize, 19usize, 13usize);
    let cut: Vec<u8> = (0..3 * cw * ch).map(|i| (i * 37 % 251) as u8).collect();
    let mut zero_extended = vec![0u8; 3 * w * h];
    for (row, pixels) in cut.chunks_exact(3 * cw).enumerate() {
        zero_extended[3 * w * row..][..3 * cw].copy_from_slice(pixels);
    }
    let padded = model.probabilities(&cut, cw as u32, ch as u32).unwrap();
    let whole = model
        .probabilities(&zero_extended, w as u32, h as u32)
        .unwrap();
    let cropped: Vec<f32> = whole
        .chunks_exact(w)
        .take(ch)
        .flat_map(|row| row[..cw].to_vec())
        .collect();
    assert_eq!(padded, cropped);
}

#[test]
fn the_previous_colour_model_still_loads_and_runs() {
    let model = OnnxFruitModel::from_bytes(COLOUR_MLP_MODEL).unwrap();
    assert_eq!(model.size_multiple(), 1);
    assert_eq!(
        model.probabilities(&[200; 3 * 7 * 5], 7, 5).unwrap().len(),
        35
    );
    // It still finds the clean world's red fruit.
    let (image, labels, _) = frame(WorldSettings::default(), FruitColour::Red);
    let p = model.probabilities(&image.rgb, 640, 480).unwrap();
    let (precision, recall) = precision_recall(&image, &labels, &p);
    assert!(
        precision >= 0.9 && recall >= 0.9,
        "precision {precision:.3}, recall {recall:.3}"
    );
}
