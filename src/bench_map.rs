//! `glasshouse bench-map`: times the ROI map's scan insertion on the user's own PLY clouds.

use std::fs::File;
use std::io::{BufReader, BufWriter};
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use glasshouse_roimap::{ply, MapConfig, RoiMap, ScanStats};
use nalgebra::Point3;

#[derive(clap::Args, Debug)]
pub struct BenchMapArgs {
    /// A PLY cloud (binary little-endian or ASCII, float x y z; a `comment origin X Y Z` header
    /// line gives its sensor origin). Repeat for several scans, inserted in order.
    #[arg(long = "cloud", required = true)]
    clouds: Vec<PathBuf>,
    /// Sensor origin `X,Y,Z` in metres for every cloud (overrides the PLY comments).
    #[arg(long, value_parser = parse_origin, allow_hyphen_values = true)]
    origin: Option<Point3<f64>>,
    /// Voxel edge in metres.
    #[arg(long, default_value_t = 0.01)]
    resolution: f64,
    /// Maximum sensor range in metres (0 or less: unlimited).
    #[arg(long, default_value_t = 1.5)]
    max_range: f64,
    /// How many times the whole sequence is inserted into a fresh map.
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// Threads casting rays.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    /// Write the final map's known voxels to this PLY (x y z occupancy roi).
    #[arg(long)]
    export_voxels: Option<PathBuf>,
}

fn parse_origin(s: &str) -> Result<Point3<f64>, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|c| c.trim().parse::<f64>().map_err(|e| format!("`{c}`: {e}")))
        .collect::<Result<_, _>>()?;
    match v.as_slice() {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok(Point3::new(*x, *y, *z)),
        _ => Err(format!("expected X,Y,Z (three finite numbers), got `{s}`")),
    }
}

struct Cloud {
    origin: Point3<f64>,
    points: Vec<Point3<f32>>,
    roi: Vec<bool>,
}

pub fn run(args: BenchMapArgs) -> anyhow::Result<()> {
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let config = MapConfig {
        resolution_m: args.resolution,
        max_range_m: (args.max_range > 0.0).then_some(args.max_range),
        ..MapConfig::default()
    };
    config.validate()?;
    let clouds = read_clouds(&args)?;
    let timed = time_insertion(&args, config, &clouds)?;
    if let Some(path) = &args.export_voxels {
        let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        timed.map.write_ply(BufWriter::new(file))?;
    }
    if args.json {
        print_json(&args, &clouds, &timed);
    } else {
        print_text(&args, config, &clouds, &timed);
    }
    Ok(())
}

fn read_clouds(args: &BenchMapArgs) -> anyhow::Result<Vec<Cloud>> {
    let mut clouds = Vec::with_capacity(args.clouds.len());
    for path in &args.clouds {
        let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
        let c = ply::read_cloud(BufReader::new(file))
            .with_context(|| format!("reading {}", path.display()))?;
        let origin = args.origin.or(c.origin).with_context(|| {
            format!(
                "{} has no `comment origin X Y Z` line; pass --origin X,Y,Z",
                path.display()
            )
        })?;
        let roi = vec![false; c.points.len()];
        clouds.push(Cloud {
            origin,
            points: c.points,
            roi,
        });
    }
    Ok(clouds)
}

/// Insertion times over all runs, the last scan's statistics and the last run's map.
struct Timed {
    median_ms: f64,
    min_ms: f64,
    max_ms: f64,
    last: ScanStats,
    map: RoiMap,
}

fn time_insertion(
    args: &BenchMapArgs,
    config: MapConfig,
    clouds: &[Cloud],
) -> anyhow::Result<Timed> {
    let mut times_ms = Vec::with_capacity(args.runs * clouds.len());
    let mut last = ScanStats::default();
    let mut map = RoiMap::new(config)?;
    for _ in 0..args.runs {
        map = RoiMap::new(config)?;
        for c in clouds {
            let start = Instant::now();
            last = map.insert_scan_threaded(&c.origin, &c.points, &c.roi, args.threads.max(1))?;
            times_ms.push(start.elapsed().as_secs_f64() * 1e3);
        }
    }
    times_ms.sort_by(f64::total_cmp);
    Ok(Timed {
        median_ms: times_ms[times_ms.len() / 2],
        min_ms: times_ms[0],
        max_ms: times_ms[times_ms.len() - 1],
        last,
        map,
    })
}

fn print_json(args: &BenchMapArgs, clouds: &[Cloud], t: &Timed) {
    println!(
        "{}",
        serde_json::json!({
            "median_ms": t.median_ms,
            "min_ms": t.min_ms,
            "max_ms": t.max_ms,
            "free_voxels": t.last.free_updates,
            "occupied_voxels": t.last.occupied_updates,
            "known_voxels": t.map.len(),
            "memory_bytes": t.map.memory_bytes(),
            "scans": clouds.len(),
            "runs": args.runs,
            "threads": args.threads.max(1),
            "skipped_non_finite": t.last.skipped_non_finite,
        })
    );
}

fn print_text(args: &BenchMapArgs, config: MapConfig, clouds: &[Cloud], t: &Timed) {
    let points: usize = clouds.iter().map(|c| c.points.len()).sum();
    println!(
        "{} scans ({} points), {} runs, {} thread(s), {} m voxels, max range {}",
        clouds.len(),
        points,
        args.runs,
        args.threads.max(1),
        args.resolution,
        config
            .max_range_m
            .map_or("unlimited".to_string(), |r| format!("{r} m"))
    );
    let (median_ms, min_ms, max_ms) = (t.median_ms, t.min_ms, t.max_ms);
    println!("insert per scan: median {median_ms:.2} ms, min {min_ms:.2} ms, max {max_ms:.2} ms");
    println!(
        "last scan: {} unique free voxels, {} unique occupied voxels ({} non-finite points skipped)",
        t.last.free_updates, t.last.occupied_updates, t.last.skipped_non_finite
    );
    println!(
        "map: {} known voxels, memory {:.1} MB",
        t.map.len(),
        t.map.memory_bytes() as f64 / 1e6
    );
    if let Some(path) = &args.export_voxels {
        println!("voxels written to {}", path.display());
    }
}
