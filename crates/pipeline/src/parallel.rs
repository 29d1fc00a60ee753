//! Independent jobs spread over a few threads, results in job order (the planner's fits and
//! splits, a takeover's snapshot decodes).

/// `work(i)` for every `i < n`, in index order, spread over `threads` threads (the calling one
/// among them), each taking the next index: jobs such as fits differ tenfold in cost, so
/// fixed shares would leave a thread idle. One thread, or one item, runs here without spawning.
pub fn in_parallel<T: Send>(n: usize, threads: usize, work: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let threads = threads.clamp(1, n.max(1));
    if threads == 1 {
        return (0..n).map(work).collect();
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let take = || {
        let mut done = Vec::new();
        loop {
            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            if i >= n {
                return done;
            }
            done.push((i, work(i)));
        }
    };
    let mut results: Vec<(usize, T)> = std::thread::scope(|scope| {
        let helpers: Vec<_> = (1..threads).map(|_| scope.spawn(take)).collect();
        let mut all = take();
        for helper in helpers {
            // A panic in a helper's job is the job's panic, as on one thread.
            all.extend(
                helper
                    .join()
                    .unwrap_or_else(|e| std::panic::resume_unwind(e)),
            );
        }
        all
    });
    results.sort_unstable_by_key(|(i, _)| *i);
    results.into_iter().map(|(_, r)| r).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_come_in_job_order_on_any_number_of_threads() {
        // Uneven jobs, so the threads finish out of order.
        let job = |i: usize| {
            let spin: u64 = (0..(i as u64 % 5) * 20_000).sum();
            (i, spin % 2)
        };
        let one: Vec<_> = in_parallel(37, 1, job);
        for threads in [2, 3, 8, 100] {
            assert_eq!(in_parallel(37, threads, job), one, "{threads} threads");
        }
        assert_eq!(
            one.iter().map(|(i, _)| *i).collect::<Vec<_>>(),
            (0..37).collect::<Vec<_>>()
        );
        assert!(in_parallel(0, 4, job).is_empty());
    }
}
