//! The readers as the fuzz targets (`fuzz/`) and the corpus replay test
//! (`tests/fuzz_corpus.rs`) drive them: one function per target, so both run the same code.
//!
//! Each function reads untrusted bytes and returns the reader's verdict; on success it also
//! checks that what was read writes and reads back, panicking when that fails, so a fuzzer
//! reports it like a crash.

use crate::ply::{read_cloud, write_cloud};
use crate::snapshot::{crc32, frame, unpack, HEADER_BYTES, KIND_DELTA, KIND_SNAPSHOT};
use crate::testdata::Workload;
use crate::RoiMap;
use nalgebra::Point3;

/// What a target's reader said about one input.
pub type Verdict = Result<(), String>;

/// One fuzz target: its name (the `fuzz/fuzz_targets/<name>.rs` file and `fuzz/corpus/<name>/`)
/// and its reading.
pub struct Target {
    pub name: &'static str,
    pub run: fn(&[u8]) -> Verdict,
}

/// Every target of this crate.
pub const TARGETS: &[Target] = &[
    Target {
        name: "roimap_snapshot",
        run: snapshot,
    },
    Target {
        name: "roimap_snapshot_body",
        run: snapshot_body,
    },
    Target {
        name: "roimap_delta_body",
        run: delta_body,
    },
    Target {
        name: "roimap_ply",
        run: ply,
    },
];

/// The target called `name`.
pub fn target(name: &str) -> Option<&'static Target> {
    TARGETS.iter().find(|t| t.name == name)
}

/// [`RoiMap::read_snapshot`] on the file as it is, then again with its length field and CRC made
/// to match, since a mutated file almost never carries a valid checksum and the fuzzer would
/// otherwise never get past it.
pub fn snapshot(data: &[u8]) -> Verdict {
    let as_is = read_and_rewrite(data);
    if data.len() >= HEADER_BYTES + 4 {
        let mut fixed = data.to_vec();
        let body_len = (data.len() - HEADER_BYTES - 4) as u64;
        fixed[8..16].copy_from_slice(&body_len.to_le_bytes());
        let crc_at = fixed.len() - 4;
        let crc = crc32(&fixed[..crc_at]);
        fixed[crc_at..].copy_from_slice(&crc.to_le_bytes());
        read_and_rewrite(&fixed)?;
    }
    as_is
}

/// [`RoiMap::read_snapshot`] of a file whose (decompressed) body is `data`: the fuzzer works
/// on the body layout directly, past the checksum and the LZ4 block.
pub fn snapshot_body(data: &[u8]) -> Verdict {
    read_and_rewrite(&frame_body(data))
}

/// [`RoiMap::apply_delta`] of a delta whose (decompressed) body is `data`, on the seeds' small
/// scanned map (two scans): a delta that applies must leave a map that writes a snapshot that
/// reads back to the same voxels, and one that does not must leave the map as it was.
pub fn delta_body(data: &[u8]) -> Verdict {
    let Some(mut map) = seed_map() else {
        panic!("the seed map does not build");
    };
    let before = map.len();
    match map.apply_delta(&frame_kind(KIND_DELTA, data)) {
        Ok(()) => read_and_rewrite(&snapshot_of(&map)),
        Err(e) => {
            assert_eq!(map.len(), before, "a delta refused changed the map");
            Err(e.to_string())
        }
    }
}

/// A snapshot file holding `body`.
fn frame_body(body: &[u8]) -> Vec<u8> {
    frame_kind(KIND_SNAPSHOT, body)
}

/// A file of `kind` holding `body`.
fn frame_kind(kind: u16, body: &[u8]) -> Vec<u8> {
    let mut file = Vec::new();
    // Writing into a Vec cannot fail.
    let _ = frame(
        kind,
        &lz4_flex::block::compress_prepend_size(body),
        &mut file,
    );
    file
}

/// `map`'s snapshot.
fn snapshot_of(map: &RoiMap) -> Vec<u8> {
    let mut file = Vec::new();
    if let Err(e) = map.write_snapshot(&mut file) {
        panic!("a map does not write: {e}");
    }
    file
}

/// The seeds' scan points: a few short rays, a handful of blocks with free, occupied and ROI
/// voxels (small seeds, since the fuzzer mutates every byte, with every value encoding).
fn seed_points() -> (Vec<Point3<f32>>, Vec<bool>) {
    let points: Vec<Point3<f32>> = (0..12)
        .map(|i| {
            let a = f64::from(i) * 0.5;
            Point3::new(
                0.06 + 0.01 * a.cos(),
                0.05 * a.sin(),
                0.02 * f64::from(i % 3),
            )
            .cast()
        })
        .collect();
    let roi = (0..points.len()).map(|i| i % 2 == 0).collect();
    (points, roi)
}

/// The seeds' scanned map: the seed points seen from `origins`.
fn scanned_map(origins: &[Point3<f64>]) -> Option<RoiMap> {
    let (points, roi) = seed_points();
    let mut map = RoiMap::new(Workload::small(3, 32, 24, 3, 2).map_config()).ok()?;
    for origin in origins {
        map.insert_scan(origin, &points, &roi).ok()?;
    }
    Some(map)
}

const SEED_ORIGINS: [Point3<f64>; 3] = [
    Point3::new(0.0, 0.0, 0.0),
    Point3::new(0.01, 0.0, 0.0),
    Point3::new(0.0, 0.02, 0.01),
];

/// The map the delta target applies its inputs to: two scans.
fn seed_map() -> Option<RoiMap> {
    scanned_map(&SEED_ORIGINS[..2])
}

/// Reads a snapshot; a map that reads must write a snapshot that reads back to the same voxels.
fn read_and_rewrite(file: &[u8]) -> Verdict {
    let map = RoiMap::read_snapshot(file).map_err(|e| e.to_string())?;
    let mut again = Vec::new();
    if let Err(e) = map.write_snapshot(&mut again) {
        panic!("a map read from a snapshot does not write: {e}");
    }
    match RoiMap::read_snapshot(again.as_slice()) {
        Ok(back) => assert_eq!(back.len(), map.len(), "voxel count after a rewrite"),
        Err(e) => panic!("a rewritten snapshot does not read: {e}"),
    }
    Ok(())
}

/// [`read_cloud`]: a PLY point cloud.
pub fn ply(data: &[u8]) -> Verdict {
    read_cloud(data).map(|_| ()).map_err(|e| e.to_string())
}

/// The seed corpus, as `(target name, file name, bytes)`: snapshots of a small scanned map and
/// of an empty one, their bodies, and PLY clouds (binary with an origin, the map's voxel export,
/// ASCII). `fuzz/src/bin/make_corpus.rs` writes them.
pub fn seeds() -> Vec<(&'static str, String, Vec<u8>)> {
    let mut out = Vec::new();
    let (points, _) = seed_points();
    let mut maps = Vec::new();
    if let Some(map) = seed_map() {
        maps.push(("scanned", map));
    }
    if let Some(map) = scanned_map(&[]) {
        maps.push(("empty", map));
    }
    // A delta from the scanned map to one more scan, and an empty one.
    if let Some(three) = scanned_map(&SEED_ORIGINS) {
        for (name, base) in [("third-scan", 2), ("nothing", 3)] {
            let mut file = Vec::new();
            if three.write_delta(base, &mut file).is_ok() {
                if let Some(body) = file
                    .get(HEADER_BYTES..file.len().saturating_sub(4))
                    .and_then(|packed| unpack(packed).ok())
                {
                    out.push(("roimap_delta_body", format!("{name}.body"), body));
                }
            }
        }
    }
    for (name, map) in &maps {
        let mut file = Vec::new();
        if map.write_snapshot(&mut file).is_ok() {
            if let Some(body) = file
                .get(HEADER_BYTES..file.len().saturating_sub(4))
                .and_then(|packed| unpack(packed).ok())
            {
                out.push(("roimap_snapshot_body", format!("{name}.body"), body));
            }
            out.push(("roimap_snapshot", format!("{name}.ghrm"), file));
        }
    }
    let mut cloud = Vec::new();
    if write_cloud(&mut cloud, &points, Some(&Point3::new(0.1, -0.2, 0.3))).is_ok() {
        out.push(("roimap_ply", "cloud-binary.ply".into(), cloud));
    }
    if let Some((_, map)) = maps.first() {
        let mut voxels = Vec::new();
        if map.write_ply(&mut voxels).is_ok() {
            out.push(("roimap_ply", "voxels-binary.ply".into(), voxels));
        }
    }
    let ascii = "ply\nformat ascii 1.0\ncomment origin 0 0 1.5\nelement face 1\nproperty uchar a\n\
                 element vertex 3\nproperty float x\nproperty double y\nproperty int z\n\
                 property uchar red\nend_header\n7\n0.5 -1.25 2 255\n1e-3 0 -4 0\n3 4 5 6\n";
    out.push((
        "roimap_ply",
        "cloud-ascii.ply".into(),
        ascii.as_bytes().to_vec(),
    ));
    out
}
