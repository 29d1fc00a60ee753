//! Helper of `scripts/octomap-compare`: writes the shared workload as PLY scans and checks a map
//! built from PLY scans against an OctoMap voxel dump.
//!
//! ```text
//! octomap_scans standard DIR            # filtered_00..09.ply and raw_00..09.ply
//! octomap_scans seeded DIR SEED         # a small seeded scene: scan_00..02.ply
//! octomap_scans check DUMP RES RANGE A.ply [B.ply ...]   # exit 1 on any disagreement
//! ```
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter};
use std::path::Path;
use std::process::ExitCode;

use glasshouse_roimap::testdata::{Scan, Workload};
use glasshouse_roimap::{ply, MapConfig, RoiMap, VoxelKey};

type Res<T> = Result<T, Box<dyn std::error::Error>>;

fn write_scans(dir: &Path, prefix: &str, scans: &[Scan]) -> Res<()> {
    for (i, s) in scans.iter().enumerate() {
        let f = BufWriter::new(File::create(dir.join(format!("{prefix}_{i:02}.ply")))?);
        ply::write_cloud(f, &s.points, Some(&s.origin))?;
    }
    Ok(())
}

fn check(dump: &str, res: f64, range: f64, clouds: &[String]) -> Res<bool> {
    let mut map = RoiMap::new(MapConfig {
        resolution_m: res,
        max_range_m: (range > 0.0).then_some(range),
        ..MapConfig::default()
    })?;
    for path in clouds {
        let c = ply::read_cloud(BufReader::new(File::open(path)?))?;
        let origin = c.origin.ok_or("PLY without comment origin")?;
        let roi = vec![false; c.points.len()];
        map.insert_scan(&origin, &c.points, &roi)?;
    }
    let mut theirs: BTreeMap<VoxelKey, f32> = BTreeMap::new();
    for line in BufReader::new(File::open(dump)?).lines() {
        let line = line?;
        let w: Vec<&str> = line.split_whitespace().collect();
        let [x, y, z, bits] = w.as_slice() else {
            return Err(format!("bad dump line `{line}`").into());
        };
        let k = VoxelKey::new(x.parse()?, y.parse()?, z.parse()?);
        theirs.insert(k, f32::from_bits(u32::from_str_radix(bits, 16)?));
    }
    let ours: BTreeMap<VoxelKey, f32> = map.iter().map(|(k, v)| (k, v.occupancy_logodds)).collect();
    let mut bad = 0usize;
    for (k, v) in &ours {
        match theirs.get(k) {
            Some(t) if t.to_bits() == v.to_bits() => {}
            other => {
                if bad < 10 {
                    eprintln!("voxel {k:?}: ours {v}, OctoMap {other:?}");
                }
                bad += 1;
            }
        }
    }
    for k in theirs.keys().filter(|k| !ours.contains_key(k)) {
        if bad < 10 {
            eprintln!("voxel {k:?}: only in OctoMap");
        }
        bad += 1;
    }
    println!(
        "{} scans: ours {} voxels, OctoMap {} voxels, {} disagreements",
        clouds.len(),
        ours.len(),
        theirs.len(),
        bad
    );
    Ok(bad == 0)
}

fn run() -> Res<bool> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args
        .iter()
        .map(String::as_str)
        .collect::<Vec<_>>()
        .as_slice()
    {
        ["standard", dir] => {
            let w = Workload::standard(1);
            write_scans(Path::new(dir), "filtered", &w.filtered_scans())?;
            write_scans(Path::new(dir), "raw", &w.raw_scans())?;
            Ok(true)
        }
        ["seeded", dir, seed] => {
            // 200x150 camera, 12 spheres, 3 scans; the raw cloud keeps every pixel.
            let w = Workload::small(seed.parse()?, 200, 150, 12, 3);
            write_scans(Path::new(dir), "scan", &w.raw_scans())?;
            Ok(true)
        }
        ["check", dump, res, range, clouds @ ..] if !clouds.is_empty() => {
            let clouds: Vec<String> = clouds.iter().map(|s| s.to_string()).collect();
            check(dump, res.parse()?, range.parse()?, &clouds)
        }
        _ => Err(
            "usage: octomap_scans standard DIR | seeded DIR SEED | check DUMP RES RANGE A.ply..."
                .into(),
        ),
    }
}

fn main() -> ExitCode {
    match run() {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
