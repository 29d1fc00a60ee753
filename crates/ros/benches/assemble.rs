//! What the ROS 2 source adds per frame before the edge's own work: decoding a 640x480 colour
//! image, its aligned depth, the camera info and a TF message from CDR, and grouping them into an
//! RgbdFrame (`cargo bench -p glasshouse-ros`).

use criterion::{criterion_group, criterion_main, Criterion};
use glasshouse_ros::assemble::transform_of;
use glasshouse_ros::msg::*;
use glasshouse_ros::{FrameAssembler, RosTopics};
use nalgebra::Isometry3;

const W: u32 = 640;
const H: u32 = 480;

fn header(stamp_ns: u64) -> Header {
    Header {
        stamp: Time::from_ns(stamp_ns),
        frame_id: "camera_color_optical_frame".into(),
    }
}

/// One frame's four messages as CDR payloads, stamped `stamp_ns`.
fn payloads(stamp_ns: u64) -> [Vec<u8>; 4] {
    let colour = Image {
        header: header(stamp_ns),
        height: H,
        width: W,
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: W * 3,
        data: (0..W * H * 3).map(|i| (i % 251) as u8).collect(),
    };
    let depth = Image {
        encoding: "16UC1".into(),
        step: W * 2,
        data: (0..W * H)
            .flat_map(|i| (400 + (i % 2000) as u16).to_le_bytes())
            .collect(),
        ..colour.clone()
    };
    let info = CameraInfo {
        header: header(stamp_ns),
        height: H,
        width: W,
        k: [600.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0],
        ..Default::default()
    };
    let tf = TfMessage {
        transforms: vec![TransformStamped {
            header: Header {
                stamp: Time::from_ns(stamp_ns),
                frame_id: "world".into(),
            },
            child_frame_id: "camera_color_optical_frame".into(),
            transform: transform_of(&Isometry3::translation(0.1, 0.2, 1.0)),
        }],
    };
    [
        encode_cdr(&colour),
        encode_cdr(&depth),
        encode_cdr(&info),
        encode_cdr(&tf),
    ]
}

fn assemble(c: &mut Criterion) {
    let frame_payloads: Vec<[Vec<u8>; 4]> =
        (0..8).map(|i| payloads(1_000_000_000 * (i + 1))).collect();
    let mut group = c.benchmark_group("ros2_source");
    group.sample_size(30);
    group.bench_function("decode_and_assemble_640x480", |b| {
        let mut i = 0;
        let mut assembler = FrameAssembler::new(RosTopics::default());
        b.iter(|| {
            let [colour, depth, info, tf] = &frame_payloads[i % frame_payloads.len()];
            i += 1;
            assembler.push_colour(decode_cdr(colour, "Image").expect("colour"));
            assembler.push_depth(decode_cdr(depth, "Image").expect("depth"));
            assembler.push_camera_info(decode_cdr(info, "CameraInfo").expect("info"));
            let tf: TfMessage = decode_cdr(tf, "TFMessage").expect("tf");
            assembler.push_tf(&tf, false);
            let (frames, _) = assembler.poll(true);
            assert_eq!(frames.len(), 1);
            frames
        })
    });
    group.finish();
}

criterion_group!(benches, assemble);
criterion_main!(benches);
