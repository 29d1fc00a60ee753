//! Times the insertion of the workload's scans, in wall time and in this thread's CPU time (from
//! /proc/thread-self/schedstat, when present), a quick check on a busy machine; the benches are
//! the measurement.
use std::time::Instant;

use glasshouse_roimap::testdata::Workload;
use glasshouse_roimap::RoiMap;

fn cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // `--simd=portable|avx2|avx512` caps the walk's vector unit.
    if let Some(level) = std::env::args()
        .filter_map(|a| a.strip_prefix("--simd=").map(str::to_owned))
        .find_map(|n| glasshouse_roimap::simd::Level::from_name(&n))
    {
        glasshouse_roimap::simd::set_cap(level);
    }
    let raw = std::env::args().any(|a| a == "--raw");
    let w = Workload::standard(1);
    let scans = if raw {
        w.raw_scans()
    } else {
        w.filtered_scans()
    };
    for run in 0..2 {
        let mut m = RoiMap::new(w.map_config())?;
        let (mut wall, mut cpu) = (Vec::new(), Vec::new());
        for s in &scans {
            let (t, c) = (Instant::now(), cpu_ns());
            m.insert_scan(&s.origin, &s.points, &s.roi)?;
            wall.push(t.elapsed().as_secs_f64() * 1e3);
            if let (Some(a), Some(b)) = (c, cpu_ns()) {
                cpu.push((b - a) as f64 / 1e6);
            }
        }
        wall.sort_by(f64::total_cmp);
        cpu.sort_by(f64::total_cmp);
        println!(
            "run {run}: median wall {:.1} ms, median cpu {:.1} ms, memory {:.1} MB",
            wall[wall.len() / 2],
            cpu.get(cpu.len() / 2).copied().unwrap_or(f64::NAN),
            m.memory_bytes() as f64 / 1e6
        );
    }
    Ok(())
}
