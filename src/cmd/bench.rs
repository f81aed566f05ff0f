//! `sofipol bench ...`: the command line of the benchmarks; the benchmarks themselves are
//! the crate sofipol-bench (bench/).
use std::process::ExitCode;

/// Arguments of `sofipol bench`.
#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(clap::Subcommand, Debug)]
enum What {
    /// Simulator: one 1024x1024 frame with all effects, with none, and each effect alone.
    Sim {
        /// Frames timed per configuration (the median is reported).
        #[arg(long, default_value_t = 21)]
        repeats: usize,
    },
    /// A 49-target night (490 frames of 1024x1024, half float, half 16-bit): simulate it (not
    /// timed), then time `sofipol night` on it in a child process: wall and CPU time,
    /// per-stage breakdown, peak RSS, and right after each run the `cat` floor (time `cat`
    /// needs to read the same files, page cache warm) and the ratio wall / cat. With
    /// --python: the expert Python reduction of the same night, the ratios and the
    /// comparison of the two catalogs.
    Night(sofipol_bench::night::NightArgs),
    /// Live reduction: the bench night copied frame by frame (one every --interval s) into
    /// a folder that `sofipol watch` follows in a child process: each template's latency
    /// (last frame copied to its catalog entry) and the final catalog against `night`'s.
    Watch(sofipol_bench::watch::WatchArgs),
    /// Accuracy of the polarimetric calibration pooled over simulated nights in two hard
    /// cases (standards at nearly one parallactic angle; polarized standards only): each
    /// night drawn, simulated and reduced by `sofipol simulate` and `sofipol night` in child
    /// processes, its catalog.json scored against truth.json: Delta-gamma pulls and the
    /// coverage of their 68 % intervals, q and u pulls, theta0, c and the telescope's
    /// polarization against the truth, flags, exit codes and times (docs/accuracy.md).
    Calibration(sofipol_bench::calibration::CalibrationArgs),
    /// Cost of each reduction stage on one simulated 10-frame sequence (medians).
    Stages {
        /// Repeats per stage.
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// Reduction accuracy on simulated nights: pull widths by separation bin, and time.
    /// (`--flat` is the bench's flat mode; the reduction options of `night` but the flat's.)
    Accuracy {
        #[command(flatten)]
        accuracy: sofipol_bench::commands::AccuracyArgs,
        #[command(flatten)]
        reduce: super::setup::ReduceArgs,
    },
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    match args.what {
        What::Sim { repeats } => sofipol_bench::commands::sim(repeats),
        What::Night(a) => sofipol_bench::night::run(a)?,
        What::Watch(a) => sofipol_bench::watch::run(a)?,
        What::Calibration(a) => sofipol_bench::calibration::run(a)?,
        What::Stages { repeats } => sofipol_bench::commands::stages(repeats)?,
        What::Accuracy { accuracy, reduce } => sofipol_bench::commands::accuracy(accuracy, &reduce.params()?)?,
    }
    Ok(ExitCode::SUCCESS)
}
