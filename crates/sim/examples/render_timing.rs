//! Times a 640x480 render of scenario Two from its initial pose: `cargo run --release -p
//! glasshouse-sim --example render_timing`.

use std::time::Instant;

use glasshouse_sim::{CameraModel, ScenarioKind, Scene};

fn main() {
    let generate_start = Instant::now();
    let scene = Scene::generate(ScenarioKind::Two, 7);
    let generate_secs = generate_start.elapsed().as_secs_f64();
    let camera = CameraModel::paper_default();
    let pose = scene.initial_camera_pose();
    let frames = 20;
    let start = Instant::now();
    let mut valid_pixels = 0;
    for i in 0..frames {
        let image = scene.render(&camera, &pose, i);
        valid_pixels += image.depth_m.iter().filter(|d| d.is_finite()).count();
    }
    let per_frame_ms = start.elapsed().as_secs_f64() * 1000.0 / frames as f64;
    println!(
        "scenario 2 seed 7: generate {:.1} ms, render 640x480 {per_frame_ms:.1} ms/frame, {} valid px/frame",
        generate_secs * 1000.0,
        valid_pixels / frames as usize
    );
}
