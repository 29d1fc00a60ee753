//! The fruit model's cost per camera frame against the HSI colour rule's, measured in the same
//! run on the same frame:
//!
//! ```sh
//! cargo run --release -p glasshouse-segment --example frame_cost -- \
//!     [MODEL.onnx] [--frames N] [--width W]
//! ```
//!
//! Renders one scenario-2 frame of the realistic world (leaf-green fruit, seed 101, the scene's
//! initial view) at W × 3W/4 (640 × 480 by default), then times, N times each on one thread:
//! the per-pixel labelling alone (the model's probabilities; the HSI rule's pixel votes) and
//! the whole detection (labelling, back-projection and 1 cm averaging, `detect_with`). Prints
//! the median and mean in ms per frame and the model-to-HSI ratios.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::time::Instant;

use glasshouse_detect::{detect_with, DepthFrame, DetectorConfig, FruitDetector, HsiVotes};
use glasshouse_segment::OnnxFruitModel;
use glasshouse_sim::{CameraModel, FruitColour, ScenarioKind, Scene, SceneOptions, WorldSettings};

const DEFAULT_MODEL: &str = "detector-service/model/fruit-segmenter.onnx";

/// Median and mean of `runs` timings of `f`, in ms.
fn time_ms(runs: usize, mut f: impl FnMut()) -> (f64, f64) {
    f(); // warm-up: plans, caches
    let mut ms: Vec<f64> = (0..runs)
        .map(|_| {
            let started = Instant::now();
            f();
            started.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    ms.sort_by(f64::total_cmp);
    (ms[ms.len() / 2], ms.iter().sum::<f64>() / ms.len() as f64)
}

fn main() {
    let mut model_path = DEFAULT_MODEL.to_string();
    let (mut frames, mut width) = (20usize, 640u32);
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--frames" => {
                frames = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .expect("--frames N")
            }
            "--width" => width = args.next().and_then(|v| v.parse().ok()).expect("--width W"),
            _ => model_path = arg,
        }
    }
    let bytes = std::fs::read(&model_path).unwrap_or_else(|e| panic!("{model_path}: {e}"));
    let model = OnnxFruitModel::from_bytes(&bytes).unwrap();

    let world = WorldSettings::realistic();
    let options = SceneOptions {
        fruit_colour: FruitColour::LeafGreen,
        ..world.scene
    };
    let scene = Scene::generate_with(ScenarioKind::Two, 101, &options);
    let camera = CameraModel::with_resolution(width, width * 3 / 4);
    let pose = scene.initial_camera_pose();
    let image = scene.render_with(&camera, &pose, 101, &world.perception);
    let (w, h) = (image.intrinsics.width, image.intrinsics.height);
    let depth = image.depth_as_u16(0.001);
    let frame = DepthFrame {
        intrinsics: image.intrinsics,
        depth: &depth,
        depth_scale_m: 0.001,
        rgb: &image.rgb,
    };
    let config = DetectorConfig::default();
    let hsi = HsiVotes::default();

    let model_px = time_ms(frames, || {
        model.probabilities(&image.rgb, w, h).unwrap();
    });
    let hsi_px = time_ms(frames, || {
        hsi.pixel_probabilities(&image.rgb, w, h).unwrap();
    });
    let model_detect = time_ms(frames, || {
        detect_with(&frame, &pose, &config, &model).unwrap();
    });
    let hsi_detect = time_ms(frames, || {
        detect_with(&frame, &pose, &config, &hsi).unwrap();
    });
    println!("{model_path} on a {w}x{h} frame, {frames} runs each, median / mean ms per frame:");
    let row = |name: &str, (median, mean): (f64, f64)| {
        println!("  {name:<28} {median:8.2} / {mean:8.2}");
    };
    row("model, pixel probabilities", model_px);
    row("HSI rule, pixel votes", hsi_px);
    row("model, whole detection", model_detect);
    row("HSI rule, whole detection", hsi_detect);
    println!(
        "  model / HSI: pixels {:.1}x, whole detection {:.2}x (medians)",
        model_px.0 / hsi_px.0,
        model_detect.0 / hsi_detect.0
    );
}
