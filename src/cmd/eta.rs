//! Time estimate and progress bar of a long Monte Carlo (`sofipol mc --pairs 1e12`): the
//! rate of the first [`CALIBRATION_SECONDS`] of work gives the estimated time of the whole
//! run, printed on stderr when it exceeds [`LONG_RUN_SECONDS`]; a progress bar follows on a
//! terminal. `-q` silences both.
use std::io::IsTerminal;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use indicatif::{HumanDuration, ProgressBar, ProgressStyle};

/// Work measured before the estimate, seconds.
pub const CALIBRATION_SECONDS: f64 = 0.5;
/// Runs estimated longer than this get an estimate line and a progress bar, seconds.
pub const LONG_RUN_SECONDS: f64 = 5.0;

/// Progress of `total` units of work (pairs) done from several threads.
pub struct Eta {
    what: String,
    total: u64,
    quiet: bool,
    start: Instant,
    done: AtomicU64,
    /// Set once the estimate is made: the bar (hidden when the run is short or stderr is
    /// not a terminal).
    bar: OnceLock<ProgressBar>,
    estimating: Mutex<()>,
}

impl Eta {
    /// Progress of `total` pairs, named `what` on stderr.
    pub fn new(what: &str, total: u64, quiet: bool) -> Self {
        Eta {
            what: what.to_string(),
            total,
            quiet,
            start: Instant::now(),
            done: AtomicU64::new(0),
            bar: OnceLock::new(),
            estimating: Mutex::new(()),
        }
    }

    /// `n` more pairs done (called from the worker threads).
    pub fn add(&self, n: u64) {
        let done = self.done.fetch_add(n, Ordering::Relaxed) + n;
        if let Some(pb) = self.bar.get() {
            pb.set_position(done);
            return;
        }
        let elapsed = self.start.elapsed().as_secs_f64();
        if self.quiet || elapsed < CALIBRATION_SECONDS {
            return;
        }
        let Ok(_guard) = self.estimating.try_lock() else { return };
        if self.bar.get().is_some() {
            return;
        }
        let total = estimated_seconds(done, elapsed, self.total);
        let long = total > LONG_RUN_SECONDS;
        if long {
            eprintln!(
                "sofipol {}: {} pairs at {:.3e} pairs/s (measured on the first {} pairs): estimated time {} (-q to silence)",
                self.what,
                self.total,
                done as f64 / elapsed,
                done,
                HumanDuration(Duration::from_secs_f64(total))
            );
        }
        let pb = if long && std::io::stderr().is_terminal() {
            let pb = ProgressBar::new(self.total);
            pb.set_style(
                ProgressStyle::with_template("{prefix} [{bar:40}] {percent:>3}% ({elapsed}, eta {eta})")
                    .expect("valid template")
                    .progress_chars("=> "),
            );
            pb.set_prefix(format!("sofipol {}", self.what));
            pb.set_position(done);
            pb
        } else {
            ProgressBar::hidden()
        };
        let _ = self.bar.set(pb);
    }

    /// Run `f` (printing on stdout) with the bar cleared from the terminal.
    pub fn suspend<R>(&self, f: impl FnOnce() -> R) -> R {
        match self.bar.get() {
            Some(pb) => pb.suspend(f),
            None => f(),
        }
    }

    /// Remove the bar.
    pub fn finish(&self) {
        if let Some(pb) = self.bar.get() {
            pb.finish_and_clear();
        }
    }
}

/// Estimated seconds of a whole run of `total` units when `done` took `elapsed` seconds.
pub fn estimated_seconds(done: u64, elapsed: f64, total: u64) -> f64 {
    elapsed * total as f64 / done.max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estimate_scales_the_measured_rate_to_the_whole_run() {
        // 1e12 pairs at 65536 pairs in 0.5 s: 1e12 / 131072 s = 88.3 days.
        let s = estimated_seconds(65_536, 0.5, 1_000_000_000_000);
        assert!((s - 1e12 / 131_072.0).abs() < 1e-6 * s, "{s}");
        assert_eq!(estimated_seconds(10, 2.0, 10), 2.0);
    }
}
