//! Round trips and hostile input for the wire codec.

use glasshouse_geom::CameraIntrinsics;
use glasshouse_proto::{
    decode, decode_as, decode_typed, encode, encode_any, samples, ImageEncoding, MessageKind,
    ProtoError, RgbdFrame, RoiCloud,
};
use rand::{Rng, SeedableRng};

#[test]
fn every_kind_round_trips() {
    for kind in MessageKind::ALL {
        let header = samples::header(7);
        let message = samples::message(kind);
        let bytes = encode_any(&header, &message);
        let (h, m) = decode_as(&bytes, kind).expect("decodes");
        assert_eq!(h, header);
        // NaN != NaN, so compare the re-encoding instead of the values.
        assert_eq!(encode_any(&h, &m), bytes, "{kind}");
        assert_eq!(decode(&bytes).expect("decodes").1.kind(), kind);
    }
}

#[test]
fn every_truncation_is_an_error_or_loses_only_padding() {
    for kind in MessageKind::ALL {
        let bytes = encode_any(&samples::header(1), &samples::message(kind));
        let mut rejected = 0;
        for len in 0..bytes.len() {
            match decode_as(&bytes[..len], kind) {
                Err(_) => rejected += 1,
                // Trailing alignment padding may go without losing content.
                Ok((h, m)) => assert_eq!(
                    encode_any(&h, &m),
                    bytes,
                    "{kind} truncated to {len} bytes decoded to something else"
                ),
            }
        }
        assert!(
            rejected + 8 >= bytes.len(),
            "{kind}: {rejected} of {}",
            bytes.len()
        );
    }
}

#[test]
fn random_corruption_never_panics() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mut rejected = 0;
    for kind in MessageKind::ALL {
        let clean = encode_any(&samples::header(1), &samples::message(kind));
        for _ in 0..400 {
            let mut bytes = clean.clone();
            for _ in 0..rng.gen_range(1..8) {
                let i = rng.gen_range(0..bytes.len());
                bytes[i] = rng.gen();
            }
            if decode_as(&bytes, kind).is_err() {
                rejected += 1;
            }
            let _ = decode(&bytes);
        }
    }
    // Flipped bytes often land in payload data, but many hit offsets or the identifier.
    assert!(
        rejected > 400,
        "only {rejected} corrupted payloads rejected"
    );
}

#[test]
fn garbage_and_wrong_kind_are_typed_errors() {
    assert!(matches!(
        decode_as(b"hello world, not a flatbuffer", MessageKind::RoiCloud),
        Err(ProtoError::WrongIdentifier) | Err(ProtoError::Invalid(_))
    ));
    assert!(decode_as(&[], MessageKind::ArmState).is_err());
    let bytes = encode_any(
        &samples::header(1),
        &samples::message(MessageKind::ArmState),
    );
    assert!(matches!(
        decode_as(&bytes, MessageKind::RankedViews),
        Err(ProtoError::UnexpectedKind { .. })
    ));
}

#[test]
fn oversized_payload_is_rejected_before_verifying() {
    let big = vec![0u8; MessageKind::ArmState.max_bytes() + 1];
    assert!(matches!(
        decode_as(&big, MessageKind::ArmState),
        Err(ProtoError::TooLarge { .. })
    ));
}

#[test]
fn inconsistent_frame_sizes_are_rejected() {
    let mut message = samples::message(MessageKind::RgbdFrame);
    if let glasshouse_proto::Message::RgbdFrame(frame) = &mut message {
        frame.depth.pop();
    }
    let bytes = encode_any(&samples::header(1), &message);
    let err = decode_as(&bytes, MessageKind::RgbdFrame).expect_err("short depth accepted");
    assert!(
        err.to_string().contains("depth: 47 samples, 48 expected"),
        "{err}"
    );
}

#[test]
fn other_protocol_versions_are_rejected() {
    let mut bytes = encode_any(
        &samples::header(1),
        &samples::message(MessageKind::ArmState),
    );
    // Find the version field by re-encoding with a patched constant is not possible from here,
    // so flip every u16 that equals the version and check at least one placement is rejected
    // as a version error.
    let mut saw_version_error = false;
    for i in 0..bytes.len() - 1 {
        if bytes[i] == glasshouse_proto::PROTOCOL_VERSION as u8 && bytes[i + 1] == 0 {
            let saved = bytes[i];
            bytes[i] = 99;
            if let Err(ProtoError::Version { found: 99, .. }) =
                decode_as(&bytes, MessageKind::ArmState)
            {
                saw_version_error = true;
            }
            bytes[i] = saved;
        }
    }
    assert!(saw_version_error);
}

#[test]
fn typed_encode_matches_the_untyped_envelope() {
    let header = samples::header(3);
    let cloud = samples::roi_cloud();
    let bytes = encode(&header, &cloud);
    assert_eq!(bytes, encode_any(&header, &cloud.clone().into()));
    let (h, back) = decode_typed::<RoiCloud>(&bytes).expect("decodes");
    assert_eq!(h, header);
    assert_eq!(back.world_from_camera, cloud.world_from_camera);
    assert_eq!(back.points_in_world.len(), cloud.points_in_world.len());
}

#[test]
fn typed_decode_rejects_another_kind() {
    let bytes = encode(&samples::header(1), &samples::arm_state());
    assert!(matches!(
        decode_typed::<RoiCloud>(&bytes),
        Err(ProtoError::UnexpectedKind {
            expected: MessageKind::RoiCloud,
            found: MessageKind::ArmState
        })
    ));
}

#[test]
fn a_cloud_with_a_non_finite_camera_pose_is_rejected() {
    let mut cloud = samples::roi_cloud();
    cloud.world_from_camera.translation.vector.x = f64::NAN;
    let bytes = encode(&samples::header(1), &cloud);
    let err = decode_typed::<RoiCloud>(&bytes).expect_err("NaN pose accepted");
    assert!(err.to_string().contains("world_from_camera"), "{err}");
}

#[test]
fn the_kind_list_names_and_limits_every_kind() {
    for kind in MessageKind::ALL {
        assert_eq!(kind.to_string(), kind.name());
        assert!(kind.max_bytes() >= 64 * 1024, "{kind}");
        assert_eq!(samples::message(kind).kind(), kind);
    }
    assert_eq!(MessageKind::ALL.len(), 12);
}

#[test]
fn a_pose_reads_back_bit_for_bit() {
    let mut cloud = glasshouse_proto::samples::roi_cloud();
    for (i, yaw) in [0.1f64, 1.3, 2.9, -2.2].into_iter().enumerate() {
        let rotation = nalgebra::UnitQuaternion::from_euler_angles(0.3 * i as f64, -0.7, yaw);
        cloud.world_from_camera =
            nalgebra::Isometry3::from_parts(nalgebra::Translation3::new(0.1, -2.5, 1.7), rotation);
        let bytes = encode(&glasshouse_proto::samples::header(1), &cloud);
        let (_, back) = decode_typed::<RoiCloud>(&bytes).expect("decodes");
        assert_eq!(back.world_from_camera, cloud.world_from_camera);
    }
}

/// A 64×48 frame with smooth depth, a few holes and flat colour, sent compressed.
fn compressed_frame() -> RgbdFrame {
    let intrinsics = CameraIntrinsics::from_horizontal_fov(64, 48, 80f64.to_radians());
    let pixels = intrinsics.pixel_count();
    RgbdFrame {
        intrinsics,
        depth: (0..pixels)
            .map(|i| {
                if i % 17 == 0 {
                    0
                } else {
                    800 + (i % 64) as u16
                }
            })
            .collect(),
        rgb: (0..3 * pixels).map(|i| [40, 160, 30][i % 3]).collect(),
        ..samples::rgbd_frame()
    }
    .encoded_as(ImageEncoding::LeftDeltaZstd)
}

#[test]
fn a_compressed_frame_round_trips_and_is_smaller() {
    let frame = compressed_frame();
    let bytes = encode(&samples::header(3), &frame);
    let raw = encode(
        &samples::header(3),
        &frame.clone().encoded_as(ImageEncoding::Raw),
    );
    assert!(
        bytes.len() * 4 < raw.len(),
        "{} vs {}",
        bytes.len(),
        raw.len()
    );
    let (_, back) = decode_typed::<RgbdFrame>(&bytes).expect("decodes");
    assert_eq!(back, frame);
    let (_, back_raw) = decode_typed::<RgbdFrame>(&raw).expect("decodes");
    assert_eq!(back_raw.depth, frame.depth);
    assert_eq!(back_raw.depth_encoding, ImageEncoding::Raw);
}

#[test]
fn corrupt_or_truncated_compressed_frames_are_typed_errors() {
    let bytes = encode(&samples::header(3), &compressed_frame());
    for len in (0..bytes.len()).step_by(7) {
        assert!(decode_typed::<RgbdFrame>(&bytes[..len]).is_err(), "{len}");
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let mut rejected = 0;
    for _ in 0..300 {
        let mut bad = bytes.clone();
        let i = rng.gen_range(0..bad.len());
        bad[i] ^= rng.gen_range(1..=255u8);
        match decode_typed::<RgbdFrame>(&bad) {
            Err(_) => rejected += 1,
            // A flipped byte outside the planes (pose, ranges, padding) may still decode.
            Ok((_, f)) => assert_eq!(f.depth.len(), 64 * 48),
        }
    }
    assert!(rejected > 100, "{rejected}");
}

#[test]
fn a_compressed_plane_of_another_size_is_a_content_error() {
    let mut frame = compressed_frame();
    // The planes hold 48 rows, the intrinsics announce 47.
    frame.intrinsics.height = 47;
    let bytes = encode(&samples::header(3), &frame);
    let err = decode_typed::<RgbdFrame>(&bytes).expect_err("wrong size accepted");
    assert!(matches!(err, ProtoError::Content { .. }), "{err}");
    assert!(err.to_string().contains("depth: zstd"), "{err}");
}

#[test]
fn a_pose_with_huge_quaternion_components_reads_as_a_unit_rotation() {
    // Found by fuzzing (fuzz/corpus/proto_*/crash-*): the norm of such a quaternion overflows
    // to infinity, and normalising by it gave a zero rotation that the decoder then returned.
    let mut cloud = samples::roi_cloud();
    let huge = nalgebra::Quaternion::new(1e300, -1e300, 0.0, 1e-300);
    cloud.world_from_camera.rotation = nalgebra::UnitQuaternion::new_unchecked(huge);
    let bytes = encode(&samples::header(1), &cloud);
    let (h, back) = decode_typed::<RoiCloud>(&bytes).expect("decodes");
    let q = back.world_from_camera.rotation.quaternion();
    assert!((q.norm() - 1.0).abs() < 1e-12, "{q:?}");
    assert!(
        (q.w - std::f64::consts::FRAC_1_SQRT_2).abs() < 1e-12,
        "{q:?}"
    );
    decode_typed::<RoiCloud>(&encode(&h, &back)).expect("the decoded pose encodes and decodes");
}
