//! Cost and size of a 640x480 simulated RgbdFrame on the wire: encoding (left delta + zstd per
//! plane, in the envelope) and decoding (verify + decode the planes), raw for comparison.
//! Prints the encoded sizes once per scenario.

use criterion::{criterion_group, criterion_main, Criterion};
use glasshouse_proto::{decode_typed, encode, samples, Header, ImageEncoding, RgbdFrame};
use glasshouse_sim::{CameraModel, ScenarioKind, Scene};

/// A frame of `kind` seen from its initial camera pose, depth in millimetres.
fn simulated_frame(kind: ScenarioKind, seed: u64) -> RgbdFrame {
    let scene = Scene::generate(kind, seed);
    let camera = CameraModel::with_resolution(640, 480);
    let pose = scene.initial_camera_pose();
    let image = scene.render(&camera, &pose, seed);
    RgbdFrame {
        intrinsics: image.intrinsics,
        world_from_camera: pose,
        depth: image.depth_as_u16(0.001),
        rgb: image.rgb,
        ..samples::rgbd_frame()
    }
}

fn frame_codec(c: &mut Criterion) {
    let header = Header::default();
    let mut group = c.benchmark_group("frame_codec");
    group.sample_size(10);
    group.measurement_time(std::time::Duration::from_secs(3));
    for (name, kind) in [("scenario2", ScenarioKind::Two), ("row", ScenarioKind::Row)] {
        let raw = simulated_frame(kind, 3);
        let packed = raw.clone().encoded_as(ImageEncoding::LeftDeltaZstd);
        let raw_bytes = encode(&header, &raw);
        let packed_bytes = encode(&header, &packed);
        eprintln!(
            "{name} 640x480: raw {} B, left delta + zstd {} B ({:.1}x)",
            raw_bytes.len(),
            packed_bytes.len(),
            raw_bytes.len() as f64 / packed_bytes.len() as f64
        );
        group.bench_function(format!("{name}/encode_compressed"), |b| {
            b.iter(|| encode(&header, &packed))
        });
        group.bench_function(format!("{name}/decode_compressed"), |b| {
            b.iter(|| decode_typed::<RgbdFrame>(&packed_bytes))
        });
        group.bench_function(format!("{name}/encode_raw"), |b| {
            b.iter(|| encode(&header, &raw))
        });
        group.bench_function(format!("{name}/decode_raw"), |b| {
            b.iter(|| decode_typed::<RgbdFrame>(&raw_bytes))
        });
    }
    group.finish();
}

criterion_group!(benches, frame_codec);
criterion_main!(benches);
