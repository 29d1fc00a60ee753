//! Progress of the CLI's long runs: indicatif's bar on a terminal; where standard error is not
//! one (a log file, CI), the bar draws nothing, so a plain line says how far the run is every
//! [`LOG_EVERY`] instead, and once more when it ends.

use std::io::IsTerminal;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// How often a run whose output is not a terminal logs its progress.
pub(crate) const LOG_EVERY: Duration = Duration::from_secs(30);

/// A progress bar for `len` steps of `what` (a run's name, first word of every logged line).
#[derive(Debug)]
pub(crate) struct Progress {
    bar: ProgressBar,
    what: &'static str,
    /// When the last line was logged and at which position; `None` on a terminal (the bar
    /// draws itself).
    last_logged: Option<Mutex<(Instant, u64)>>,
}

impl Progress {
    pub(crate) fn new(what: &'static str, len: u64) -> Self {
        Self::with_target(what, len, std::io::stderr().is_terminal())
    }

    fn with_target(what: &'static str, len: u64, terminal: bool) -> Self {
        let bar = ProgressBar::new(len);
        let last_logged = (!terminal).then(|| {
            bar.set_draw_target(ProgressDrawTarget::hidden());
            Mutex::new((Instant::now(), 0))
        });
        Self {
            bar,
            what,
            last_logged,
        }
    }

    /// The bar's look on a terminal (indicatif's template).
    pub(crate) fn with_style(self, style: ProgressStyle) -> Self {
        self.bar.set_style(style);
        self
    }

    pub(crate) fn enable_steady_tick(&self, every: Duration) {
        if self.last_logged.is_none() {
            self.bar.enable_steady_tick(every);
        }
    }

    pub(crate) fn inc(&self, steps: u64) {
        self.bar.inc(steps);
        self.log_if_due();
    }

    pub(crate) fn set_position(&self, position: u64) {
        self.bar.set_position(position);
        self.log_if_due();
    }

    pub(crate) fn set_message(&self, message: String) {
        self.bar.set_message(message);
    }

    /// A line above the bar (on a terminal) or in the log.
    pub(crate) fn println(&self, line: String) {
        match self.last_logged {
            Some(_) => eprintln!("{line}"),
            None => self.bar.println(line),
        }
    }

    /// Clears the bar; without a terminal, logs the end unless the last line said it.
    pub(crate) fn finish_and_clear(&self) {
        if let Some(Ok(last)) = self.last_logged.as_ref().map(Mutex::lock) {
            if last.1 != self.bar.position() {
                eprintln!("{}", self.line());
            }
        }
        self.bar.finish_and_clear();
    }

    fn log_if_due(&self) {
        let Some(last) = &self.last_logged else {
            return;
        };
        let Ok(mut last) = last.lock() else {
            return;
        };
        if last.0.elapsed() >= LOG_EVERY {
            *last = (Instant::now(), self.bar.position());
            eprintln!("{}", self.line());
        }
    }

    /// `what: 40 % (120/300), message, 2m 10s elapsed, about 3m 15s left`.
    fn line(&self) -> String {
        let (position, len) = (self.bar.position(), self.bar.length().unwrap_or(0));
        let percent = 100 * position / len.max(1);
        let message = self.bar.message();
        let message = if message.is_empty() {
            String::new()
        } else {
            format!(", {message}")
        };
        let left = if position < len {
            format!(", about {} left", minutes(self.bar.eta()))
        } else {
            String::new()
        };
        format!(
            "{}: {percent} % ({position}/{len}){message}, {} elapsed{left}",
            self.what,
            minutes(self.bar.elapsed())
        )
    }
}

/// `2m 10s`, `45s`.
fn minutes(duration: Duration) -> String {
    let s = duration.as_secs();
    match s / 60 {
        0 => format!("{s}s"),
        m => format!("{m}m {:02}s", s % 60),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn a_run_without_a_terminal_logs_where_it_is() {
        let progress = Progress::with_target("eval", 300, false);
        progress.set_message("1/4 trials done".into());
        progress.inc(120);
        let line = progress.line();
        assert!(
            line.starts_with("eval: 40 % (120/300), 1/4 trials done, 0s elapsed, about "),
            "{line}"
        );
        progress.inc(180);
        assert!(!progress.line().contains("left"), "{}", progress.line());
        assert!(progress.last_logged.is_some());
        assert!(Progress::with_target("eval", 1, true).last_logged.is_none());
    }

    #[test]
    fn durations_read_as_minutes_and_seconds() {
        assert_eq!(minutes(Duration::from_secs(45)), "45s");
        assert_eq!(minutes(Duration::from_secs(130)), "2m 10s");
    }
}
