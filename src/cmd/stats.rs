//! `sofipol stats CATALOG`: are the disks of the binaries aligned?
//!
//! The sample is the binaries whose two components both pass the P/sigma cut. It prints
//! the tests (KS and Kuiper against a uniform Pi(Delta gamma), binomial test of the
//! fraction below 30 deg, two-sample KS against the random-disks + ISM Monte Carlo for
//! each P_ism) and a verdict in plain words. With `-o DIR` it also writes `stats.json`
//! and the figures `observed.png`, `ism_levels.png`, `models.png`.
//!
//! Exit code 0 whenever the catalog could be read, including samples too small to test
//! (n = 0 or 1: the verdict says so); 1 on unreadable input or invalid options.
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context};
use sofipol_calib::text::printable;
use sofipol_pipeline::catalog::Provenance;
use sofipol_pipeline::io::write_atomic;
use sofipol_pipeline::stats::alignment::DEFAULT_SIGNIFICANCE;
use sofipol_pipeline::stats::figures::{
    ism_figure, models_figure, observed_figure, paper_models, simulate_models, ModelRow,
};
use sofipol_pipeline::stats::format_p;
use sofipol_pipeline::stats::mc::{McConfig, PIntDist, DEFAULT_SEED};
use sofipol_pipeline::stats::predictions::source_name;
use sofipol_pipeline::stats::setup::{self, Noise};
use sofipol_pipeline::stats::{AlignmentModel, AlignmentReport, BinarySample};

use super::mc::{parse_count, parse_levels};

/// Arguments of `sofipol stats`.
#[derive(clap::Args, Debug)]
#[command(
    after_help = "Examples:\n  sofipol stats night1/catalog.json -o night1/stats\n  sofipol stats catalog.json --p-ism 0,0.5,1,2 --noise none --pairs 1e5"
)]
pub struct Args {
    /// The catalog JSON written by `sofipol target` / `sofipol night`
    catalog: PathBuf,
    /// Output directory for stats.json and the figures [default: none, only the report on
    /// stdout]
    #[arg(short, long, value_name = "DIR", alias = "out")]
    output: Option<PathBuf>,
    /// Interstellar polarization levels to compare with, percent, comma-separated, or "paper"
    /// (0.1,0.2,0.4,0.7,1,1.5,2,3,4,5)
    #[arg(long, value_name = "PERCENT,...", default_value = "paper")]
    p_ism: String,
    /// Angle of the interstellar polarization, deg east of north (irrelevant for isotropic
    /// disks)
    #[arg(long, value_name = "DEG", default_value_t = 0.0, allow_hyphen_values = true)]
    ism_angle: f64,
    /// Monte-Carlo pairs per ISM level (1e6 style accepted)
    #[arg(long, value_name = "N", default_value_t = sofipol_pipeline::stats::setup::DEFAULT_PAIRS, value_parser = parse_count)]
    pairs: u64,
    /// Seed of the Monte Carlo
    #[arg(long, default_value_t = DEFAULT_SEED)]
    seed: u64,
    /// Intrinsic P distribution of the Monte Carlo: "catalog" (the debiased P of the sample's
    /// components) or any `sofipol mc --p-int` spec (percent)
    #[arg(long, value_name = "SPEC", default_value = "catalog")]
    p_int: String,
    /// Fraction (0..1) of simulated disks polarized perpendicular to their projected long
    /// axis, drawn independently for each component
    #[arg(long, value_name = "F", default_value_t = 0.0)]
    perpendicular_fraction: f64,
    /// Measurement noise of the random disks + ISM Monte Carlo: "per-binary" (each binary
    /// simulated with its components' own sigma_P and cut, and tested against its own
    /// prediction), "auto" (one level for all: the median sigma_P of the catalog's
    /// components), "none", or one sigma in percent
    #[arg(long, value_name = "per-binary|auto|none|PERCENT", default_value = "per-binary")]
    noise: String,
    /// In the own-foreground prediction (made when the catalog gives some targets a
    /// `foreground`), the interstellar polarization of the binaries without one: "none" or
    /// a degree in percent (at --ism-angle)
    #[arg(long, value_name = "none|PERCENT", default_value = "none")]
    ism_fallback: String,
    /// P/sigma cut applied to simulated pairs when there is noise ("none" to disable)
    #[arg(long, value_name = "P/SIGMA", default_value = "3")]
    snr_cut: String,
    /// Recompute the sample cut as P/sigma_P > K instead of using the catalog's passes_cut
    /// [default: none, the catalog's passes_cut]
    #[arg(long, value_name = "K")]
    cut: Option<f64>,
    /// Take binaries whose components have no instrumental calibration (flagged
    /// `uncalibrated`) [default: left out, counted in a warning].
    #[arg(long)]
    allow_uncalibrated: bool,
    /// Significance level of the verdict
    #[arg(long, default_value_t = DEFAULT_SIGNIFICANCE)]
    significance: f64,
    /// Bins of the observed Delta-gamma histogram on [0, 90] deg
    #[arg(long, value_name = "N", default_value_t = 9)]
    bins: usize,
    /// Worker threads; results do not depend on it [default: all cores]
    #[arg(short, long, value_name = "N", alias = "threads")]
    jobs: Option<usize>,
    /// Figure format: png, or svg (vector, for papers)
    #[arg(long, default_value = "png", value_parser = ["png", "svg"])]
    format: String,
    /// Skip the models (a)-(d) figure (4 extra Monte-Carlo runs)
    #[arg(long)]
    no_model_figure: bool,
    /// Print only errors: no report, no warnings (the files of -o are written)
    #[arg(short, long)]
    quiet: bool,
    /// Also print the time of each step (reading, analysis, figures) and the threads (on
    /// stderr)
    #[arg(short, long)]
    verbose: bool,
}

/// Run `sofipol stats`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    if !(args.significance > 0.0 && args.significance < 1.0) {
        bail!("--significance {} must be in (0, 1)", args.significance);
    }
    if args.bins == 0 || args.bins > 90 {
        bail!("--bins {} must be in 1..=90", args.bins);
    }
    // The outputs are checked before the (long) analysis: the directory must accept files
    // and none of them may replace an input (`-o DIR` holding the catalog as stats.json).
    let ext = &args.format;
    let names = [
        "stats.json".to_string(),
        format!("observed.{ext}"),
        format!("ism_levels.{ext}"),
        format!("models.{ext}"),
    ];
    if let Some(dir) = &args.output {
        let mut inputs = vec![args.catalog.as_path()];
        inputs.extend(super::mc::spec_file(&args.p_int));
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        super::common::check_outputs_in_dir(dir, &names, &inputs, "-o")?;
    }
    let t_read = std::time::Instant::now();
    let catalog = sofipol_pipeline::input::read_catalog(&args.catalog)?;
    let sample = if args.allow_uncalibrated {
        BinarySample::from_catalog_allowing_uncalibrated(&catalog, args.cut)
    } else {
        BinarySample::from_catalog(&catalog, args.cut)
    };
    let step = |what: &str, t: std::time::Instant| {
        if args.verbose {
            eprintln!("sofipol stats: {what} in {:.2} s", t.elapsed().as_secs_f64());
        }
    };
    step("catalog read and sample built", t_read);
    for w in sample.warnings.iter().filter(|_| !args.quiet) {
        eprintln!("sofipol stats: warning: {}", printable(w));
    }
    let uncalibrated = sample
        .excluded
        .iter()
        .filter(|e| e.reason.starts_with("uncalibrated"))
        .count();
    anyhow::ensure!(
        !(sample.is_empty() && uncalibrated > 0),
        "{}: no binary to test: {uncalibrated} of {} target(s) have no instrumental calibration \
         (flagged 'uncalibrated'; their angles would fake an alignment). Reduce with standards or --calib, \
         or give --allow-uncalibrated",
        args.catalog.display(),
        catalog.targets.len()
    );

    let opts = setup::Options {
        ism_levels_percent: parse_levels(&args.p_ism)?,
        ism_angle_deg: args.ism_angle,
        pairs: args.pairs,
        seed: args.seed,
        p_int: (args.p_int != "catalog")
            .then(|| PIntDist::parse(&args.p_int))
            .transpose()?,
        perpendicular_fraction: args.perpendicular_fraction,
        noise: match args.noise.as_str() {
            "per-binary" => Noise::PerBinary,
            "auto" => Noise::Auto,
            "none" => Noise::None,
            s => Noise::Percent(
                s.parse::<f64>()
                    .with_context(|| format!("--noise '{s}': expected per-binary, auto, none or percent"))?,
            ),
        },
        snr_cut: match args.snr_cut.as_str() {
            "none" => None,
            s => Some(
                s.parse::<f64>()
                    .with_context(|| format!("--snr-cut '{s}': expected a number or none"))?,
            ),
        },
        significance: args.significance,
        ism_fallback_percent: match args.ism_fallback.as_str() {
            "none" => None,
            s => Some(
                s.parse::<f64>()
                    .with_context(|| format!("--ism-fallback '{s}': expected none or percent"))?,
            ),
        },
    };
    let params = setup::params(&sample, &opts, &args.catalog.display().to_string())?;
    let pool = super::common::worker_pool("stats", args.jobs, args.quiet)?;
    let dg = sample.delta_gamma_deg();
    let t_analysis = std::time::Instant::now();
    let report = pool.install(|| setup::analyse_sample(&sample, &params))?;
    step(
        &format!(
            "analysis ({} binaries, {} pairs a model, {} threads)",
            sample.len(),
            args.pairs,
            pool.current_num_threads()
        ),
        t_analysis,
    );
    if !args.quiet {
        print_report(&args.catalog, &sample, &report);
    }

    if let Some(dir) = &args.output {
        let t_files = std::time::Instant::now();
        write_json(dir, &args, &sample, &report)?;
        let mut written = vec!["stats.json"];
        let [_, observed, ism_levels, models] = &names;
        if !sample.is_empty() {
            let notes = setup::observed_notes(&report);
            observed_figure(&dir.join(observed), &sample, args.bins, &notes)?;
            written.push(observed);
        }
        if !report.ism.is_empty() {
            ism_figure(
                &dir.join(ism_levels),
                &report.ism,
                &dg,
                args.bins,
                &setup::mc_subtitle(&params),
            )?;
            written.push(ism_levels);
        }
        if !args.no_model_figure {
            let rows = model_rows(&report, args.pairs, args.seed, &pool)?;
            let note = report
                .errors
                .median_deg()
                .map(|m| format!("dashed: with the measured errors (median σ = {m:.1}°)"));
            models_figure(&dir.join(models), &rows, note.as_deref())?;
            written.push(models);
        }
        step("files and figures written", t_files);
        if !args.quiet {
            println!("\nwrote {} in {}", written.join(", "), dir.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Rows of the models figure: models (a)-(d) simulated with `pairs`, each with the
/// report's convolved histogram of the same model where there is one.
fn model_rows(
    report: &AlignmentReport,
    pairs: u64,
    seed: u64,
    pool: &rayon::ThreadPool,
) -> anyhow::Result<Vec<ModelRow>> {
    let base = McConfig::geometry(AlignmentModel::Random, pairs, seed);
    let mut rows = pool.install(|| simulate_models(&paper_models(), &base))?;
    for (label, _, _, convolved) in &mut rows {
        *convolved = report
            .models
            .iter()
            .find(|m| &m.label == label)
            .and_then(|m| m.with_errors.as_ref().map(|c| c.histogram.clone()));
    }
    Ok(rows)
}

fn print_report(path: &Path, sample: &BinarySample, r: &AlignmentReport) {
    println!("sofipol stats: {}", path.display());
    println!(
        "sample: {} {} with both components above the cut; {} targets excluded",
        sample.len(),
        if sample.len() == 1 { "binary" } else { "binaries" },
        sample.excluded.len()
    );
    for e in &sample.excluded {
        println!("  excluded {}: {}", printable(&e.object), printable(&e.reason));
    }
    if sample.binaries.iter().any(|b| b.sigma_source.is_some()) {
        println!("\nDelta gamma per binary [deg]:");
        println!(
            "  {:<16} {:>7} {:>7} {:>16}  error from",
            "object", "dg", "sigma", "68 % interval"
        );
        for b in &sample.binaries {
            let sigma = b.sigma_delta_gamma_deg.map_or("-".to_string(), |s| format!("{s:.1}"));
            let iv = b
                .delta_gamma_interval_deg
                .map_or("-".to_string(), |[lo, hi]| format!("[{lo:.1}, {hi:.1}]"));
            println!(
                "  {:<16} {:>7.1} {:>7} {:>16}  {}",
                printable(&b.object),
                b.delta_gamma_deg,
                sigma,
                iv,
                source_name(b.sigma_source)
            );
        }
    }
    let p_err = |c: &Option<sofipol_pipeline::stats::predictions::Convolved>| {
        c.as_ref()
            .map_or("-".to_string(), |c| format_p(c.prediction.ks.p_value))
    };
    if !r.models.is_empty() {
        println!("\nalignment models (geometry only; \"err\": convolved with the measured Delta-gamma errors):");
        println!(
            "  {:<22} {:>9} {:>9} {:>9} {:>9} {:>10} {:>10}",
            "model", "mean", "mean err", "frac<30", "f<30 err", "KS p", "KS p err"
        );
        for m in &r.models {
            let w = m.with_errors.as_ref().map(|c| &c.prediction);
            println!(
                "  {:<22} {:>9.1} {:>9} {:>9.3} {:>9} {:>10} {:>10}",
                m.label,
                m.prediction.mean_deg,
                w.map_or("-".to_string(), |p| format!("{:.1}", p.mean_deg)),
                m.prediction.fraction_below_threshold,
                w.map_or("-".to_string(), |p| format!("{:.3}", p.fraction_below_threshold)),
                format_p(m.prediction.ks.p_value),
                p_err(&m.with_errors)
            );
        }
    }
    if !r.ism.is_empty() {
        println!("\nrandom disks + ISM (Monte Carlo: {}):", r.mc_description);
        let per_binary = r.ism.iter().any(|c| c.per_binary.is_some());
        if per_binary {
            println!("  (\"KS p\": two-sample KS against the equal-weight mixture of the binaries' own predictions; \"own p\": each binary against its own prediction, the calibrated test the verdict reads)");
        }
        println!(
            "  {:>10} {:>10} {:>9} {:>10} {:>10} {:>10} {:>10}",
            "P_ism [%]", "accepted", "frac<30", "KS D", "KS p", "KS p err", "own p"
        );
        let p_own = |c: &sofipol_pipeline::stats::IsmComparison| {
            c.per_binary.as_ref().map_or("-".to_string(), |t| format_p(t.p_value))
        };
        if let Some(ks) = &r.ks_uniform {
            // Without a foreground random disks give a uniform Delta gamma whatever the noise.
            println!(
                "  {:>10} {:>10} {:>9.3} {:>10.3} {:>10} {:>10} {:>10}",
                "0 (none)",
                "-",
                r.threshold_deg / 90.0,
                ks.statistic,
                format_p(ks.p_value),
                format_p(ks.p_value),
                format_p(ks.p_value)
            );
        }
        for c in r.ism.iter().chain(&r.own_foreground) {
            let level = if c.foreground.is_some() {
                "own".to_string()
            } else {
                c.p_ism_percent.to_string()
            };
            println!(
                "  {:>10} {:>10} {:>9.3} {:>10.3} {:>10} {:>10} {:>10}",
                level,
                c.mc.accepted,
                c.mc_fraction_below_threshold,
                c.ks.statistic,
                format_p(c.ks.p_value),
                p_err(&c.with_errors),
                p_own(c)
            );
        }
        if let Some(f) = r.own_foreground.as_ref().and_then(|c| c.foreground.as_ref()) {
            println!("  own: {f}");
        }
    }
    if let Some(f) = &r.fg_corrected {
        println!(
            "\nAfter subtracting each binary's own foreground ({} of {} binaries; against uniform, the prediction of random disks without a foreground):",
            f.n, r.n
        );
        println!(
            "  before: mean Delta gamma {:.1} deg, KS p {}  (with the foreground: compare the row \"own\" above)",
            f.mean_before_deg,
            format_p(f.ks_before.p_value)
        );
        println!(
            "  after:  mean Delta gamma {:.1} deg, KS p {}, Kuiper p {}",
            f.mean_after_deg,
            format_p(f.ks_after.p_value),
            format_p(f.kuiper_after.p_value)
        );
    }
    println!("\n{}", r.verdict);
}

fn write_json(dir: &Path, args: &Args, sample: &BinarySample, r: &AlignmentReport) -> anyhow::Result<()> {
    // The per-level Monte-Carlo histograms are kept (counts on 1-deg bins).
    let parameters = serde_json::json!({
        "p_ism": args.p_ism, "ism_angle_deg": args.ism_angle, "pairs": args.pairs, "seed": args.seed,
        "p_int": args.p_int, "noise": args.noise, "snr_cut": args.snr_cut, "cut": args.cut,
        "ism_fallback": args.ism_fallback,
        "significance": args.significance, "observed_bins": args.bins,
    });
    let provenance = Provenance {
        catalog: Some(args.catalog.display().to_string()),
        parameters: Some(parameters),
        ..Provenance::now()
    };
    let json = serde_json::json!({
        "provenance": provenance,
        "sample": sample,
        "report": r,
    });
    write_atomic(&dir.join("stats.json"), serde_json::to_string_pretty(&json)?.as_bytes())?;
    Ok(())
}
