//! Criterion benches of the ROI map on the shared workload (`glasshouse_roimap::testdata`).
//!
//! `cargo bench -p glasshouse-roimap -- --warm-up-time 1 --measurement-time 3`
//!
//! Rows: one filtered scan and one raw scan inserted into the map of the other nine scans (1 and
//! 2 threads; `/avx2`, `/portable` = the walk capped at AVX2 or at the build's baseline vector
//! unit, beside the widest this CPU has), the unobserved-voxel gain over a 200×150-ray fan, the frontier queries (incremental)
//! next to a from-scratch recomputation, clustering, and snapshot writing. The memory of the
//! 10-scan map is printed once. The `row` group sweeps a simulated row segment by segment.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use glasshouse_geom::Aabb;
use glasshouse_roimap::testdata::{unobserved_gain, unobserved_gain_batch, Scan, Workload};
use glasshouse_roimap::{simd, Neighbourhood, Occupancy, RoiMap, VoxelKey};
use nalgebra::{Point3, Vector3};

const SEED: u64 = 1;

fn map_of(w: &Workload, scans: &[Scan]) -> RoiMap {
    let mut m = RoiMap::new(w.map_config()).expect("valid config");
    for s in scans {
        m.insert_scan(&s.origin, &s.points, &s.roi)
            .expect("valid scan");
    }
    m
}

/// The vector units below the widest this CPU has, each with its row suffix (`/avx2`,
/// `/portable`), for side-by-side rows.
fn narrower_levels() -> Vec<(simd::Level, &'static str)> {
    [
        (simd::Level::Avx2, "/avx2"),
        (simd::Level::Portable, "/portable"),
    ]
    .into_iter()
    .filter(|&(level, _)| level < simd::detected())
    .collect()
}

fn insertion(c: &mut Criterion) {
    let w = Workload::standard(SEED);
    let filtered = w.filtered_scans();
    let raw_last = w.raw_scan(&w.origins[9]);
    let nine = map_of(&w, &filtered[..9]);
    let ten = map_of(&w, &filtered);
    eprintln!(
        "workload: filtered scan {} points, raw scan {} points; 10-scan map: {} known voxels, \
         {} blocks, memory {:.1} MB",
        filtered[9].points.len(),
        raw_last.points.len(),
        ten.len(),
        ten.counts().blocks,
        ten.memory_bytes() as f64 / 1e6
    );
    let mut g = c.benchmark_group("insert");
    g.sample_size(20);
    let best = (simd::detected(), "");
    let mut runs = vec![(1usize, best)];
    runs.extend(narrower_levels().into_iter().map(|level| (1, level)));
    runs.push((2, best));
    for (threads, (level, suffix)) in runs {
        simd::set_cap(level);
        for (name, s) in [("filtered_scan", &filtered[9]), ("raw_scan", &raw_last)] {
            g.bench_function(format!("{name}/{threads}_thread{suffix}"), |b| {
                b.iter_batched_ref(
                    || nine.clone(),
                    |m| {
                        m.insert_scan_threaded(&s.origin, &s.points, &s.roi, threads)
                            .expect("valid")
                    },
                    BatchSize::LargeInput,
                )
            });
        }
    }
    simd::set_cap(simd::detected());
    g.finish();
}

fn queries(c: &mut Criterion) {
    let w = Workload::standard(SEED);
    let m = w.filtered_map().expect("valid");
    let (origin, fan) = w.gain_fan();
    let mut g = c.benchmark_group("query");
    g.sample_size(20);
    g.bench_function("gain_fan_200x150", |b| {
        b.iter(|| unobserved_gain(&m, black_box(&origin), &fan, 1.5))
    });
    g.bench_function("gain_fan_200x150/batch", |b| {
        b.iter(|| unobserved_gain_batch(&m, black_box(&origin), &fan, 1.5))
    });
    for (level, suffix) in narrower_levels() {
        simd::set_cap(level);
        g.bench_function(format!("gain_fan_200x150/batch{suffix}"), |b| {
            b.iter(|| unobserved_gain_batch(&m, black_box(&origin), &fan, 1.5))
        });
    }
    simd::set_cap(simd::detected());
    // The planner scores each candidate view with a fan this small: what a fan costs beyond
    // its rays' walk (setting up, the planes) dominates here.
    let (origin, small_fan) = w.planner_gain_fan();
    g.bench_function("gain_fan_8x6", |b| {
        b.iter(|| unobserved_gain(&m, black_box(&origin), &small_fan, 1.0))
    });
    g.bench_function("gain_fan_8x6/batch", |b| {
        b.iter(|| unobserved_gain_batch(&m, black_box(&origin), &small_fan, 1.0))
    });
    let region = Aabb::new(Point3::new(0.3, -1.0, -1.0), Point3::new(1.6, 1.0, 1.0));
    g.bench_function("frontiers/incremental_query", |b| {
        b.iter(|| {
            (
                m.exploration_frontier(black_box(&region)).len(),
                m.roi_frontier(&region).len(),
            )
        })
    });
    g.bench_function("frontiers/from_scratch", |b| {
        b.iter(|| brute_frontiers(&m, &region))
    });
    g.bench_function("clusters_min10", |b| {
        b.iter(|| m.clusters(black_box(10)).len())
    });
    let mut snap = Vec::new();
    m.write_snapshot(&mut snap).expect("write");
    eprintln!(
        "10-scan map snapshot: {} bytes, {:.3} B per known voxel",
        snap.len(),
        snap.len() as f64 / m.len() as f64
    );
    bench_snapshot(&mut g, &m, &snap);
    g.finish();

    // Frontier upkeep per scan: a scan inserted with and without (apply_voxels of the same
    // changes) is not separable, so report the share: insert time is measured above.
    let mut g = c.benchmark_group("frontier_update");
    g.sample_size(20);
    let filtered = w.filtered_scans();
    let mut nine = map_of(&w, &filtered[..9]);
    nine.take_changes();
    let mut after = nine.clone();
    let s = &filtered[9];
    after
        .insert_scan(&s.origin, &s.points, &s.roi)
        .expect("valid");
    let undrained = after.clone();
    let changes = after.take_changes();
    eprintln!("scan 10 changes {} voxels", changes.len());
    g.bench_function("apply_one_scan_of_changes", |b| {
        b.iter_batched_ref(
            || nine.clone(),
            |m| m.apply_voxels(&changes),
            BatchSize::LargeInput,
        )
    });
    g.finish();
    changes_read(c, &undrained);
}

/// The original's per-iteration recomputation: scan every known voxel.
/// One scan's changes read back: every changed voxel's values (`drain_changes`), against only
/// the solid ones a map update keeps (`drain_changed_blocks`); `changed` holds the scan's
/// changes undrained.
fn changes_read(c: &mut Criterion, changed: &RoiMap) {
    let mut g = c.benchmark_group("changes");
    g.sample_size(20);
    g.bench_function("read_every_changed_voxel", |b| {
        b.iter_batched_ref(
            || changed.clone(),
            |m| m.drain_changes(|k, v, roi| _ = std::hint::black_box((k, v, roi))),
            BatchSize::LargeInput,
        )
    });
    g.bench_function("read_changed_solid_voxels", |b| {
        b.iter_batched_ref(
            || changed.clone(),
            |m| {
                m.drain_changed_blocks(|block| {
                    let (changed, solid) = (block.changed(), block.solid());
                    let news: [u64; 8] = std::array::from_fn(|w| changed[w] & solid[w]);
                    block.for_each(&news, |k, v, roi| _ = std::hint::black_box((k, v, roi)));
                })
            },
            BatchSize::LargeInput,
        )
    });
    g.finish();
}

fn brute_frontiers(m: &RoiMap, region: &Aabb) -> (usize, usize) {
    let (mut expl, mut roi) = (0, 0);
    for (k, v) in m.iter() {
        if v.occupancy() != Occupancy::Free || !region.contains(&m.centre_of(k)) {
            continue;
        }
        let n: Vec<VoxelKey> = k.neighbours(Neighbourhood::Six).collect();
        if !n.iter().any(|&x| m.occupancy(x) == Occupancy::Unknown) {
            continue;
        }
        expl += usize::from(n.iter().any(|&x| m.occupancy(x) == Occupancy::Occupied));
        roi += usize::from(n.iter().any(|&x| m.is_roi(x)));
    }
    (expl, roi)
}

/// A scan moved by `dy_m` along the row (y).
fn shifted(s: &Scan, dy_m: f64) -> Scan {
    let dy = dy_m as f32;
    Scan {
        origin: s.origin + Vector3::new(0.0, dy_m, 0.0),
        points: s
            .points
            .iter()
            .map(|p| p + Vector3::new(0.0, dy, 0.0))
            .collect(),
        roi: s.roi.clone(),
    }
}

/// Row workload: the ten filtered scans repeated segment by segment along a row (1 m apart, 8
/// segments). Times the last scan of the first segment and of the last segment, each inserted
/// into the map of everything before it, and prints memory and snapshot bytes per known voxel; times reading and writing that
/// map's snapshot.
fn row(c: &mut Criterion) {
    const SEGMENTS: usize = 8;
    let w = Workload::standard(SEED);
    let filtered = w.filtered_scans();
    let segment =
        |i: usize| -> Vec<Scan> { filtered.iter().map(|s| shifted(s, i as f64)).collect() };
    let first = segment(0);
    let start_map = map_of(&w, &first[..9]);
    let mut end_map = RoiMap::new(w.map_config()).expect("valid config");
    let mut last = Vec::new();
    for i in 0..SEGMENTS {
        let scans = segment(i);
        let n = if i + 1 == SEGMENTS { 9 } else { 10 };
        for s in &scans[..n] {
            end_map
                .insert_scan(&s.origin, &s.points, &s.roi)
                .expect("valid");
        }
        last = scans;
    }
    let mut full = end_map.clone();
    let s = &last[9];
    full.insert_scan(&s.origin, &s.points, &s.roi)
        .expect("valid");
    let mut snap = Vec::new();
    full.write_snapshot(&mut snap).expect("write");
    eprintln!(
        "row of {SEGMENTS} segments: {} known voxels, {} blocks, memory {:.1} MB = {:.2} B per \
         known voxel, snapshot {:.2} MB = {:.3} B per known voxel",
        full.len(),
        full.counts().blocks,
        full.memory_bytes() as f64 / 1e6,
        full.memory_bytes() as f64 / full.len() as f64,
        snap.len() as f64 / 1e6,
        snap.len() as f64 / full.len() as f64
    );
    let mut g = c.benchmark_group("row");
    g.sample_size(10);
    for (name, map, scan) in [
        ("scan_start", &start_map, &first[9]),
        ("scan_end", &end_map, &last[9]),
    ] {
        g.bench_function(name, |b| {
            b.iter_batched_ref(
                || map.clone(),
                |m| {
                    m.insert_scan(&scan.origin, &scan.points, &scan.roi)
                        .expect("valid")
                },
                BatchSize::LargeInput,
            )
        });
    }
    // A trolley's map along a row, as a standby replica takes it over or an owner sends it.
    bench_snapshot(&mut g, &full, &snap);
    g.finish();
}

/// `snapshot_read` (of `snap`, `map`'s snapshot) and `snapshot_write` (of `map`) in group `g`.
fn bench_snapshot(
    g: &mut criterion::BenchmarkGroup<criterion::measurement::WallTime>,
    map: &RoiMap,
    snap: &[u8],
) {
    g.bench_function("snapshot_read", |b| {
        b.iter(|| RoiMap::read_snapshot(black_box(snap)).expect("read").len())
    });
    g.bench_function("snapshot_write", |b| {
        b.iter(|| {
            let mut out = Vec::new();
            map.write_snapshot(&mut out).expect("write");
            out.len()
        })
    });
}

criterion_group!(benches, insertion, queries, row);
criterion_main!(benches);
