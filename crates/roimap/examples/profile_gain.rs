//! Runs the gain ray fan (`query/gain_fan_200x150`'s workload) a few times, for callgrind and a
//! quick CPU-time check on a busy machine; the benches are the measurement.
use std::time::Instant;

use glasshouse_roimap::testdata::{unobserved_gain, unobserved_gain_batch, Workload};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // `--simd=portable|avx2|avx512` caps the walk's vector unit.
    if let Some(level) = std::env::args()
        .filter_map(|a| a.strip_prefix("--simd=").map(str::to_owned))
        .find_map(|n| glasshouse_roimap::simd::Level::from_name(&n))
    {
        glasshouse_roimap::simd::set_cap(level);
    }
    // Arguments: number of runs, `--batch` for the batch walk.
    let batch = std::env::args().any(|a| a == "--batch");
    let runs: usize = std::env::args()
        .filter_map(|a| a.parse().ok())
        .next()
        .unwrap_or(5);
    let w = Workload::standard(1);
    let m = w.filtered_map()?;
    let (origin, fan) = w.gain_fan();
    let mut times = Vec::new();
    let mut gain = 0.0;
    for _ in 0..runs {
        let t = Instant::now();
        gain = if batch {
            unobserved_gain_batch(&m, &origin, &fan, 1.5)
        } else {
            unobserved_gain(&m, &origin, &fan, 1.5)
        };
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    println!(
        "gain {gain:.6}, median wall {:.1} ms over {runs} runs",
        times[times.len() / 2]
    );
    Ok(())
}
