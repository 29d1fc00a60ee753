//! Times `detect` on a synthetic 640x480 frame (a tilted plane with a red patch):
//! `cargo run --release -p glasshouse-detect --example detect_timing`.

use std::time::Instant;

use glasshouse_detect::{detect, DepthFrame, DetectorConfig};
use glasshouse_geom::{look_at, CameraIntrinsics};
use nalgebra::Point3;

fn main() {
    let k = CameraIntrinsics::from_horizontal_fov(640, 480, 80f64.to_radians());
    let mut depth = Vec::with_capacity(k.pixel_count());
    let mut rgb = Vec::with_capacity(3 * k.pixel_count());
    for v in 0..480u32 {
        for u in 0..640u32 {
            depth.push((600 + v * 3 + (u % 7)) as u16);
            let red = (200..300).contains(&u) && (100..200).contains(&v);
            rgb.extend(if red { [200, 30, 20] } else { [60, 140, 40] });
        }
    }
    let frame = DepthFrame {
        intrinsics: k,
        depth: &depth,
        depth_scale_m: 0.001,
        rgb: &rgb,
    };
    let pose = look_at(&Point3::new(0.0, -1.0, 1.0), &Point3::new(0.0, 0.0, 0.8));
    let config = DetectorConfig::default();
    let runs = 20;
    let start = Instant::now();
    let mut points = 0;
    for _ in 0..runs {
        match detect(&frame, &pose, &config) {
            Ok(cloud) => points = cloud.points_in_world.len(),
            Err(e) => {
                eprintln!("detect failed: {e}");
                return;
            }
        }
    }
    let ms = start.elapsed().as_secs_f64() * 1000.0 / runs as f64;
    println!("detect 640x480: {ms:.1} ms/frame, {points} voxel points");
}
