//! `sofipol`: the command-line front end. Thin: parse -> validated parameters -> call the
//! libraries -> map the outcome to an exit code: 0 everything reduced, 1 usage or fatal error, 2 reduced but some
//! input unusable or some target not fully reduced (docs/cli.md).
use std::process::ExitCode;

use clap::{Parser, Subcommand};

// A closed stdout or stderr (`sofipol night ... | head`, `2>&1 | true`) must neither panic
// nor stop the work: std's `print!` family panics on a write error (EPIPE). These
// replacements, visible in every module below, write through a locked handle and drop
// write errors, as ripgrep does on a broken pipe; the run goes on, writes its outputs
// and exits with its usual code (docs/cli.md). They also escape every control character
// but the line breaks sofipol lays out itself (`sofipol_calib::text::printable_lines`): a
// file name or header value holding ESC or CR cannot drive the terminal. Values read from
// files are escaped where they are printed (`printable`), newlines included.
macro_rules! print {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let s = format!($($t)*);
        let _ = write!(std::io::stdout().lock(), "{}", sofipol_calib::text::printable_lines(&s));
    }};
}
macro_rules! println {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let s = format!($($t)*);
        let _ = writeln!(std::io::stdout().lock(), "{}", sofipol_calib::text::printable_lines(&s));
    }};
}
macro_rules! eprintln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let s = format!($($t)*);
        let _ = writeln!(std::io::stderr().lock(), "{}", sofipol_calib::text::printable_lines(&s));
    }};
}

mod alloc;
mod cmd;

/// `sofipol --version`: the version and the git commit built from (build.rs; `-dirty` when
/// tracked files had changes, "unknown" without git), as every provenance records it.
const VERSION: &str = concat!(env!("CARGO_PKG_VERSION"), " (commit ", env!("SOFIPOL_GIT_COMMIT"), ")");

/// Dual-beam near-infrared imaging polarimetry with SOFI (ESO NTT).
#[derive(Parser, Debug)]
#[command(name = "sofipol", version = VERSION, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Simulate the embedded demo scene into ./sofipol-demo/ and reduce it.
    Demo(cmd::demo::Args),
    /// Write SOFI-like raw frames and a truth JSON from a scene TOML.
    Simulate(cmd::simulate::Args),
    /// Reduce a whole night directory in parallel into one catalog.
    Night(cmd::night::Args),
    /// Reduce a night while it is observed: follow its folder, reduce each template as it
    /// completes.
    Watch(cmd::watch::Args),
    /// Calibration products of a night (calibration.json) from its standard stars.
    Calib(cmd::calib::Args),
    /// Join shard catalogs written with `night --shard K/N`.
    Merge(cmd::merge::Args),
    /// Reduce one target sequence (files or a directory) to a JSON catalog.
    Target(cmd::target::Args),
    /// Projection / interstellar-polarization Monte Carlo of Pi(Delta gamma).
    Mc(cmd::mc::Args),
    /// Alignment statistics of a catalog: histograms, KS, Kuiper, binomial, verdict.
    Stats(cmd::stats::Args),
    /// The night's self-contained HTML page of a catalog: summary, table, figures, statistics.
    Report(cmd::report::Args),
    /// Export a catalog as a table (ECSV, FITS binary table, CSV), one row per component.
    Export(cmd::export::Args),
    /// Benchmarks that print figures (simulator, ...).
    Bench(cmd::bench::Args),
}

fn main() -> ExitCode {
    alloc::keep_freed_memory();
    sofipol_pipeline::build_info::set_commit(env!("SOFIPOL_GIT_COMMIT"));
    // Usage errors exit 1 (clap's own default of 2 means "reduced with failures" here).
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            let code = if e.use_stderr() { 1 } else { 0 };
            let _ = e.print();
            return ExitCode::from(code);
        }
    };
    let result = match cli.command {
        Command::Demo(a) => cmd::demo::run(a),
        Command::Simulate(a) => cmd::simulate::run(a),
        Command::Target(a) => cmd::target::run(a),
        Command::Night(a) => cmd::night::run(a),
        Command::Watch(a) => cmd::watch::run(a),
        Command::Merge(a) => cmd::merge::run(a),
        Command::Calib(a) => cmd::calib::run(a),
        Command::Mc(a) => cmd::mc::run(a),
        Command::Stats(a) => cmd::stats::run(a),
        Command::Report(a) => cmd::report::run(a),
        Command::Export(a) => cmd::export::run(a),
        Command::Bench(a) => cmd::bench::run(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("sofipol: error: {}", cmd::error_text(&cmd::chain_text(&e)));
            ExitCode::from(1)
        }
    }
}
