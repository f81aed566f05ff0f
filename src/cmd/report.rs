//! `sofipol report CATALOG -o night.html`: the night's self-contained HTML page
//! (`sofipol_pipeline::report`: summary, targets table, figures, calibration, statistics,
//! provenance). Also written by `sofipol night --report FILE` after the catalog.
//!
//! Exit code 0 when the page was written (also when the statistics could not be computed:
//! the page says why); 1 on an unreadable catalog or an unwritable output.
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use sofipol_calib::text::printable;
use sofipol_pipeline::catalog::Catalog;
use sofipol_pipeline::report::{self, DEFAULT_REPORT_PAIRS};
use sofipol_pipeline::stats::mc::DEFAULT_SEED;
use sofipol_pipeline::stats::setup;

use super::mc::parse_count;

/// Arguments of `sofipol report`.
#[derive(clap::Args, Debug)]
#[command(
    after_help = "Examples:\n  sofipol report night1/catalog.json -o night1/night.html\n  \
                        sofipol report sofipol-demo/catalog.json --figures sofipol-demo/figures -o demo.html"
)]
pub struct Args {
    /// The catalog JSON written by `sofipol night` / `sofipol target`
    catalog: PathBuf,
    /// The HTML page to write (atomically)
    #[arg(short, long, value_name = "FILE", default_value = "night.html")]
    output: PathBuf,
    /// Folder of the per-target figures (`<slug of the sequence id>.png`) [default: the
    /// catalog's products folder, DIR/STEM_products/, where night writes them]
    #[arg(long, value_name = "DIR")]
    figures: Option<PathBuf>,
    /// Monte-Carlo pairs per ISM level of the statistics (1e6 style accepted)
    #[arg(long, value_name = "N", default_value_t = DEFAULT_REPORT_PAIRS, value_parser = parse_count)]
    pairs: u64,
    /// Seed of the Monte Carlo
    #[arg(long, default_value_t = DEFAULT_SEED)]
    seed: u64,
    /// Worker threads; results do not depend on it [default: all cores]
    #[arg(short, long, value_name = "N")]
    jobs: Option<usize>,
    /// Print only errors
    #[arg(short, long)]
    quiet: bool,
    /// Also print what the page holds: targets, figures found, statistics, size and time
    /// (on stderr)
    #[arg(short, long)]
    verbose: bool,
}

/// Run `sofipol report`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    // `-o -`: the page on standard output (as `export` does), no file named `-`.
    let to_stdout = args.output.as_os_str() == "-";
    if !to_stdout {
        super::common::check_output(&args.output, &[&args.catalog])?;
    }
    let catalog = sofipol_pipeline::input::read_catalog(&args.catalog)?;
    let figures = args
        .figures
        .clone()
        .unwrap_or_else(|| sofipol_pipeline::night::products_dir(&args.catalog));
    anyhow::ensure!(
        args.figures.is_none() || figures.is_dir(),
        "--figures {}: not a folder",
        figures.display()
    );
    let pool = super::common::worker_pool("report", args.jobs, args.quiet)?;
    let t0 = std::time::Instant::now();
    let page = pool.install(|| {
        write_page(
            catalog,
            &args.catalog,
            Some(&figures),
            &args.output,
            args.pairs,
            args.seed,
        )
    })?;
    if args.verbose {
        eprintln!(
            "sofipol report: {} targets, {} figures found in {} ({:.0} kB), statistics: {}; page {:.0} kB in {:.2} s",
            page.targets,
            page.figures,
            figures.display(),
            page.figure_bytes as f64 / 1e3,
            page.stats,
            page.bytes as f64 / 1e3,
            t0.elapsed().as_secs_f64()
        );
    }
    if !args.quiet && !to_stdout {
        println!("sofipol report: wrote {}", args.output.display());
    }
    Ok(ExitCode::SUCCESS)
}

/// What a written page holds.
pub struct PageSummary {
    /// Targets in the table.
    pub targets: usize,
    /// Per-target figures embedded, and their bytes.
    pub figures: usize,
    /// Bytes of those figures.
    pub figure_bytes: usize,
    /// "computed" or why the statistics are missing.
    pub stats: String,
    /// Size of the page, bytes.
    pub bytes: usize,
}

/// Gather the page of `catalog` (read from `catalog_path`; per-target figures from
/// `figures`, none when `None`, each linked relative to `output`'s folder; statistics with
/// `pairs` and `seed`, in the current rayon pool) and write it to `output` atomically,
/// creating its folder, after its own figures (frame quality, statistics) into
/// `<stem>_figures/` beside it (`-`: standard output, the per-target figures linked by
/// absolute `file:` URLs, the page's own figures embedded only).
pub fn write_page(
    catalog: Catalog,
    catalog_path: &Path,
    figures: Option<&Path>,
    output: &Path,
    pairs: u64,
    seed: u64,
) -> anyhow::Result<PageSummary> {
    let opts = setup::Options {
        pairs,
        seed,
        ..Default::default()
    };
    let command_line = sofipol_pipeline::build_info::command_line_string();
    let to_stdout = output.as_os_str() == "-";
    // The folder first: the figures are linked relative to it, as it really is.
    let page_dir = output
        .parent()
        .map(|d| if d.as_os_str().is_empty() { Path::new(".") } else { d });
    if let Some(d) = page_dir.filter(|_| !to_stdout) {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let input = report::collect(
        catalog,
        catalog_path,
        figures,
        Some(output).filter(|_| !to_stdout),
        &opts,
        command_line,
    );
    let html = report::html::render(&input);
    if to_stdout {
        use std::io::Write;
        let mut out = std::io::stdout().lock();
        out.write_all(html.as_bytes())
            .and_then(|()| out.flush())
            .context("writing the page to standard output")?;
    } else {
        // The page's own figures first, into the folder beside it: the page links to them.
        report::write_figures(output, &input)?;
        report::write(output, &html)?;
    }
    Ok(PageSummary {
        targets: input.catalog.targets.len(),
        figures: input.target_figures.len(),
        figure_bytes: input.target_figures.values().map(|f| f.png.len()).sum(),
        stats: match &input.stats {
            Ok(_) => "computed".into(),
            Err(e) => printable(&e.to_string()).into_owned(),
        },
        bytes: html.len(),
    })
}
