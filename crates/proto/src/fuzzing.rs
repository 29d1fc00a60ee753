//! The decoders as the fuzz targets (`fuzz/`) and the corpus replay test
//! (`tests/fuzz_corpus.rs`) drive them: one function per target, so both run the same code.
//!
//! Each function decodes untrusted bytes and returns the decoder's verdict; on success it also
//! checks what every reader relies on (plane sizes, a decoded message encodes and decodes again),
//! panicking when that fails, so a fuzzer reports it like a crash.

use crate::pixels::{decode_plane, PlaneShape};
use crate::*;

/// What a target's decoder said about one input.
pub type Verdict = std::result::Result<(), String>;

/// One fuzz target: its name (the `fuzz/fuzz_targets/<name>.rs` file and `fuzz/corpus/<name>/`)
/// and its decoding.
pub struct Target {
    pub name: &'static str,
    pub run: fn(&[u8]) -> Verdict,
}

/// Every target of this crate.
pub const TARGETS: &[Target] = &[
    Target {
        name: "proto_decode",
        run: decode_any,
    },
    Target {
        name: "proto_arm_state",
        run: typed::<ArmState>,
    },
    Target {
        name: "proto_detector_status",
        run: typed::<DetectorStatus>,
    },
    Target {
        name: "proto_fleet_fruits",
        run: typed::<FleetFruits>,
    },
    Target {
        name: "proto_fruit_estimates",
        run: typed::<FruitEstimates>,
    },
    Target {
        name: "proto_map_snapshot",
        run: typed::<MapSnapshot>,
    },
    Target {
        name: "proto_map_update",
        run: typed::<MapUpdate>,
    },
    Target {
        name: "proto_planner_status",
        run: typed::<PlannerStatus>,
    },
    Target {
        name: "proto_ranked_views",
        run: typed::<RankedViews>,
    },
    Target {
        name: "proto_rgbd_frame",
        run: rgbd_frame,
    },
    Target {
        name: "proto_roi_cloud",
        run: typed::<RoiCloud>,
    },
    Target {
        name: "proto_trolley_info",
        run: typed::<TrolleyInfo>,
    },
    Target {
        name: "proto_trolley_status",
        run: typed::<TrolleyStatus>,
    },
    Target {
        name: "proto_pixel_plane",
        run: pixel_plane,
    },
];

/// The target called `name`.
pub fn target(name: &str) -> Option<&'static Target> {
    TARGETS.iter().find(|t| t.name == name)
}

/// [`decode`]: a payload of any kind (the dashboard's reader).
pub fn decode_any(data: &[u8]) -> Verdict {
    let (header, message) = decode(data).map_err(|e| e.to_string())?;
    let again = encode_any(&header, &message);
    if let Err(e) = decode_as(&again, message.kind()) {
        panic!(
            "a decoded {} does not decode after encoding: {e}",
            message.kind()
        );
    }
    Ok(())
}

/// [`decode_typed`] and [`decode_as`] of one kind: both must agree.
pub fn typed<M: Wire>(data: &[u8]) -> Verdict {
    let typed = decode_typed::<M>(data);
    let untyped = decode_as(data, M::KIND);
    assert_eq!(
        typed.is_ok(),
        untyped.is_ok(),
        "decode_typed and decode_as disagree on a {}",
        M::KIND
    );
    let (header, message) = typed.map_err(|e| e.to_string())?;
    if let Err(e) = decode_typed::<M>(&encode(&header, &message)) {
        panic!("a decoded {} does not decode after encoding: {e}", M::KIND);
    }
    Ok(())
}

/// An RgbdFrame (its decoder runs each plane through [`decode_plane`]): the planes a reader
/// gets hold exactly one sample per pixel and channel.
pub fn rgbd_frame(data: &[u8]) -> Verdict {
    typed::<RgbdFrame>(data)?;
    if let Ok((_, frame)) = decode_typed::<RgbdFrame>(data) {
        let pixels = frame.intrinsics.pixel_count();
        assert_eq!(frame.depth.len(), pixels, "depth plane size");
        assert_eq!(frame.rgb.len(), 3 * pixels, "rgb plane size");
    }
    Ok(())
}

/// [`decode_plane`] on its own, past the FlatBuffers layer: byte 0 picks the sample type (bit 0:
/// u16 depth or u8 colour) and the channels (bit 1: 3 or 1), bytes 1..3 the width, bytes 3..5 the
/// height (both little-endian u16), the rest is the encoded plane. The expected size stays
/// within a frame's limit, as [`RgbdFrame`]'s decoder ensures.
pub fn pixel_plane(data: &[u8]) -> Verdict {
    let Some((head, encoded)) = data.split_first_chunk::<5>() else {
        return Err("shorter than the 5-byte plane header".into());
    };
    let channels = if head[0] & 2 == 0 { 1 } else { 3 };
    let width = usize::from(u16::from_le_bytes([head[1], head[2]]));
    let height = usize::from(u16::from_le_bytes([head[3], head[4]]));
    let samples = width * height * channels;
    if samples > MessageKind::RgbdFrame.max_bytes() / 2 {
        return Err(format!("{samples} samples exceed a frame"));
    }
    let shape = PlaneShape { width, channels };
    let decoded = if head[0] & 1 == 0 {
        decode_plane::<u16>(encoded, shape, samples).map(|p| p.len())
    } else {
        decode_plane::<u8>(encoded, shape, samples).map(|p| p.len())
    };
    let len = decoded.map_err(|e| e.to_string())?;
    assert_eq!(len, samples, "decoded plane size");
    Ok(())
}

/// The target of one kind's typed decoder.
fn kind_target(kind: MessageKind) -> &'static str {
    match kind {
        MessageKind::RgbdFrame => "proto_rgbd_frame",
        MessageKind::ArmState => "proto_arm_state",
        MessageKind::TrolleyInfo => "proto_trolley_info",
        MessageKind::RoiCloud => "proto_roi_cloud",
        MessageKind::RankedViews => "proto_ranked_views",
        MessageKind::FruitEstimates => "proto_fruit_estimates",
        MessageKind::MapUpdate => "proto_map_update",
        MessageKind::PlannerStatus => "proto_planner_status",
        MessageKind::TrolleyStatus => "proto_trolley_status",
        MessageKind::DetectorStatus => "proto_detector_status",
        MessageKind::MapSnapshot => "proto_map_snapshot",
        MessageKind::FleetFruits => "proto_fleet_fruits",
    }
}

/// The seed corpus: valid encodings of every kind (raw and compressed frames), as
/// `(target name, file name, bytes)`. `fuzz/src/bin/make_corpus.rs` writes them.
pub fn seeds() -> Vec<(&'static str, String, Vec<u8>)> {
    use crate::pixels::encode_plane;
    let mut out = Vec::new();
    for kind in MessageKind::ALL {
        let bytes = encode_any(&samples::header(1), &samples::message(kind));
        out.push((
            kind_target(kind),
            format!("sample-{}", kind.name()),
            bytes.clone(),
        ));
        out.push(("proto_decode", format!("sample-{}", kind.name()), bytes));
    }
    let compressed = samples::rgbd_frame().encoded_as(ImageEncoding::LeftDeltaZstd);
    let bytes = encode(&samples::header(2), &compressed);
    out.push((
        "proto_rgbd_frame",
        "sample-compressed".into(),
        bytes.clone(),
    ));
    out.push(("proto_decode", "sample-RgbdFrame-compressed".into(), bytes));
    // Planes with the header pixel_plane expects: depth (u16, 1 channel) and colour (u8, 3).
    let frame = samples::rgbd_frame();
    let (w, h) = (
        frame.intrinsics.width as u16,
        frame.intrinsics.height as u16,
    );
    let plane_header = |flags: u8| {
        let mut v = vec![flags];
        v.extend_from_slice(&w.to_le_bytes());
        v.extend_from_slice(&h.to_le_bytes());
        v
    };
    let depth_shape = PlaneShape {
        width: w.into(),
        channels: 1,
    };
    let rgb_shape = PlaneShape {
        width: w.into(),
        channels: 3,
    };
    if let Some(p) = encode_plane(&frame.depth, depth_shape) {
        out.push((
            "proto_pixel_plane",
            "depth".into(),
            [plane_header(0), p].concat(),
        ));
    }
    if let Some(p) = encode_plane(&frame.rgb, rgb_shape) {
        out.push((
            "proto_pixel_plane",
            "rgb".into(),
            [plane_header(3), p].concat(),
        ));
    }
    out
}
