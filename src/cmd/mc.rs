//! `sofipol mc`: the projection / interstellar-polarization Monte Carlo of Pi(Delta gamma).
//!
//! Settings: an optional TOML file (`--config`), overridden by flags, validated into one
//! `McConfig` per ISM level. Output: a summary table on stdout; with `-o DIR`,
//! `pi_delta_gamma.json` (counts, densities, provenance) and `pi_delta_gamma.png`, both
//! written atomically. A run estimated longer than a few seconds prints its estimated time
//! and shows a progress bar on stderr ([`Eta`]; not with `-q`). `--bench` prints timing
//! figures instead.
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{bail, Context};
use serde::Deserialize;
use sofipol_pipeline::catalog::Provenance;
use sofipol_pipeline::io::write_atomic;
use sofipol_pipeline::numeric::median_in_place;
use sofipol_pipeline::stats::figures::{format_count, mc_figure};
use sofipol_pipeline::stats::mc::{
    self, simulate_with_progress, Ism, McConfig, McOutput, PIntDist, CHUNK_PAIRS, DEFAULT_BINS, DEFAULT_PAIRS,
    DEFAULT_P_INT, DEFAULT_SEED, PAPER_ISM_LEVELS_PERCENT,
};
use sofipol_pipeline::stats::AlignmentModel;

use super::eta::Eta;

/// Arguments of `sofipol mc`.
#[derive(clap::Args, Debug)]
#[command(
    after_help = "Examples:\n  sofipol mc --model random -o out/\n  sofipol mc --model spread:20 --pairs 1e6\n  sofipol mc --p-ism paper --p-int sin2i:6 -o out/ism\n  sofipol mc --p-ism 0.5,1,2 --noise 0.3 --snr-cut 3\n  sofipol mc --bench"
)]
pub struct Args {
    /// Pi(alpha): random | aligned | spread:SIGMA_DEG | uniform:ALPHA0_DEG | table:FILE [default: random]
    #[arg(long, value_name = "MODEL")]
    model: Option<String>,
    /// Number of simulated pairs (1e7 style accepted) [default: 1e7]
    #[arg(long, value_name = "N", value_parser = parse_count)]
    pairs: Option<u64>,
    /// Seed of the random streams [default: 20010101]
    #[arg(long)]
    seed: Option<u64>,
    /// Number of Delta-gamma bins on [0, 90] deg [default: 90]
    #[arg(long, value_name = "N")]
    bins: Option<usize>,
    /// Interstellar polarization degrees in percent, comma-separated, or "paper" for
    /// 0.1,0.2,0.4,0.7,1,1.5,2,3,4,5 [default: no ISM]
    #[arg(long, value_name = "PERCENT,...")]
    p_ism: Option<String>,
    /// Angle of the interstellar polarization, deg east of north [default: 0 deg]
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    ism_angle: Option<f64>,
    /// Intrinsic P distribution (percent): fixed:P | uniform:LO,HI | lognormal:MEDIAN,SIGMA_LN |
    /// sin2i:PMAX | pofi:FILE (P(i) table, CSV inclination_deg,p) | table:FILE | catalog:FILE
    /// [default: sin2i:6]
    #[arg(long, value_name = "SPEC")]
    p_int: Option<String>,
    /// Fraction (0..1) of disks polarized perpendicular to their projected long axis (angle
    /// rotated by 90 deg), drawn independently for each component [default: 0]
    #[arg(long, value_name = "F")]
    perpendicular_fraction: Option<f64>,
    /// Gaussian noise sigma of q and u of each component, percent [default: none]
    #[arg(long, value_name = "PERCENT")]
    noise: Option<f64>,
    /// Keep a pair only if both components have measured P/sigma above this (needs --noise)
    /// [default: none, no cut]
    #[arg(long, value_name = "P/SIGMA")]
    snr_cut: Option<f64>,
    /// Worker threads; results do not depend on it [default: all cores]
    #[arg(short, long, value_name = "N", alias = "threads")]
    jobs: Option<usize>,
    /// TOML file with any of: model, pairs, seed, bins, p_ism (list), ism_angle_deg, p_int,
    /// perpendicular_fraction, noise_percent, snr_cut; flags override it [default: none]
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Output directory for pi_delta_gamma.json and the figure [default: none, only the
    /// table on stdout]
    #[arg(short, long, value_name = "DIR", alias = "out")]
    output: Option<PathBuf>,
    /// Figure format: png, or svg (vector, for papers)
    #[arg(long, default_value = "png", value_parser = ["png", "svg"])]
    format: String,
    /// Print timing figures (median of --bench-runs) instead of a normal run
    #[arg(long)]
    bench: bool,
    /// Runs per benchmark configuration
    #[arg(long, value_name = "N", default_value_t = 5)]
    bench_runs: usize,
    /// Print only errors: no table, no time estimate, no progress bar (the files of -o are
    /// written)
    #[arg(short, long)]
    quiet: bool,
    /// Also print, per run, the pairs drawn and accepted and the rate (on stderr)
    #[arg(short, long)]
    verbose: bool,
}

/// The TOML model file.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct McFile {
    model: Option<String>,
    pairs: Option<u64>,
    seed: Option<u64>,
    bins: Option<usize>,
    p_ism: Option<Vec<f64>>,
    ism_angle_deg: Option<f64>,
    p_int: Option<String>,
    perpendicular_fraction: Option<f64>,
    noise_percent: Option<f64>,
    snr_cut: Option<f64>,
}

/// Parse a count written as an integer or in floating-point notation (1e7).
pub fn parse_count(s: &str) -> anyhow::Result<u64> {
    if let Ok(n) = s.parse::<u64>() {
        return Ok(n);
    }
    match s.parse::<f64>() {
        Ok(x) if x >= 1.0 && x.fract() == 0.0 && x <= 1e15 => Ok(x as u64),
        _ => bail!("'{s}' is not a positive whole number"),
    }
}

/// Parse a list of ISM levels ("paper" or "0.1,0.5,..."), percent.
pub fn parse_levels(s: &str) -> anyhow::Result<Vec<f64>> {
    if s.trim() == "paper" {
        return Ok(PAPER_ISM_LEVELS_PERCENT.to_vec());
    }
    s.split(',')
        .map(|t| {
            let v: f64 = t
                .trim()
                .parse()
                .with_context(|| format!("--p-ism: '{t}' is not a number (percent)"))?;
            if !(v >= 0.0 && v.is_finite()) {
                bail!("--p-ism: {v} % must be >= 0");
            }
            Ok(v)
        })
        .collect()
}

/// The file a `--model` or `--p-int` spec reads (`table:FILE`, `pofi:FILE`,
/// `catalog:FILE`), if any: an input that outputs must not replace.
pub fn spec_file(spec: &str) -> Option<&Path> {
    let (kind, arg) = spec.split_once(':')?;
    matches!(kind.trim(), "table" | "pofi" | "catalog").then(|| Path::new(arg.trim()))
}

/// Validated settings of one invocation.
struct Settings {
    base: McConfig,
    levels: Option<Vec<f64>>,
    ism_angle_deg: f64,
}

fn settings(args: &Args) -> anyhow::Result<Settings> {
    let file: McFile = match &args.config {
        Some(p) => {
            let text = sofipol_calib::input::read_to_string(p, sofipol_calib::input::MAX_OPTION_FILE_BYTES)
                .with_context(|| format!("reading {}", p.display()))?;
            toml::from_str(&text).with_context(|| format!("parsing {}", p.display()))?
        }
        None => McFile::default(),
    };
    let model_spec = args.model.clone().or(file.model).unwrap_or_else(|| "random".into());
    let model = AlignmentModel::parse(&model_spec)?;
    let p_int = PIntDist::parse(
        &args
            .p_int
            .clone()
            .or(file.p_int)
            .unwrap_or_else(|| DEFAULT_P_INT.into()),
    )?;
    let levels = match (&args.p_ism, file.p_ism) {
        (Some(s), _) => Some(parse_levels(s)?),
        (None, Some(v)) => Some(v),
        (None, None) => None,
    };
    let base = McConfig {
        model,
        pairs: args.pairs.or(file.pairs).unwrap_or(DEFAULT_PAIRS),
        seed: args.seed.or(file.seed).unwrap_or(DEFAULT_SEED),
        bins: args.bins.or(file.bins).unwrap_or(DEFAULT_BINS),
        p_int,
        ism: None,
        noise_percent: args.noise.or(file.noise_percent),
        snr_cut: args.snr_cut.or(file.snr_cut),
        perpendicular_fraction: [args
            .perpendicular_fraction
            .or(file.perpendicular_fraction)
            .unwrap_or(0.0); 2],
    };
    base.validate()?;
    Ok(Settings {
        base,
        levels,
        ism_angle_deg: args.ism_angle.or(file.ism_angle_deg).unwrap_or(0.0),
    })
}

/// The configurations to run: one per ISM level, or the base alone.
fn runs(s: &Settings) -> Vec<(String, McConfig)> {
    match &s.levels {
        None => vec![(s.base.model.spec(), s.base.clone())],
        Some(levels) => levels
            .iter()
            .map(|&p| {
                let mut c = s.base.clone();
                c.ism = Some(Ism {
                    p_percent: p,
                    angle_deg: s.ism_angle_deg,
                });
                (format!("P_ism = {p} %"), c)
            })
            .collect(),
    }
}

/// Summary figures of a Pi(Delta gamma) histogram: (mean, fraction < 30 deg, first/last ninth).
pub fn summary(out: &McOutput) -> (f64, f64, f64) {
    let h = &out.histogram;
    // From the pairs, not the bin centres (exact for `aligned`: 0, not half a bin).
    let mean = out.mean_delta_gamma_deg;
    let below = h.cdf(30.0);
    let last = 1.0 - h.cdf(80.0);
    let ratio = if last > 0.0 { h.cdf(10.0) / last } else { f64::INFINITY };
    (mean, below, ratio)
}

/// Run `sofipol mc`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let s = settings(&args)?;
    let pool = super::common::worker_pool("mc", args.jobs, args.quiet)?;
    if let (Some(dir), false) = (&args.output, args.bench) {
        let mut inputs: Vec<&Path> = args.config.iter().map(PathBuf::as_path).collect();
        inputs.extend(args.model.as_deref().and_then(spec_file));
        inputs.extend(args.p_int.as_deref().and_then(spec_file));
        let figure = format!("pi_delta_gamma.{}", args.format);
        super::common::check_outputs_in_dir(dir, &["pi_delta_gamma.json", &figure], &inputs, "-o")?;
    }
    if args.bench {
        return bench(&s, args.bench_runs.max(1));
    }
    let runs = runs(&s);
    let quiet = args.quiet;
    if !quiet {
        print_header(&s, &runs, pool.current_num_threads());
    }
    // One estimate and one bar for all the runs (ISM levels) of the invocation.
    let eta = Eta::new("mc", runs.iter().map(|(_, c)| c.pairs).sum(), quiet);
    let mut results = Vec::new();
    for (label, cfg) in &runs {
        let t0 = Instant::now();
        let out = pool.install(|| simulate_with_progress(cfg, &|n| eta.add(n)))?;
        let dt = t0.elapsed().as_secs_f64();
        let (mean, below, ratio) = summary(&out);
        if !quiet {
            eta.suspend(|| {
                println!(
                    "{label:<18} {:>12} {mean:>10.2} {below:>12.4} {ratio:>16.3} {dt:>9.3}",
                    out.accepted
                )
            });
        }
        if args.verbose {
            eta.suspend(|| {
                eprintln!(
                    "{label}: {} pairs drawn, {} accepted ({:.1} %), {:.3e} pairs/s on {} threads",
                    cfg.pairs,
                    out.accepted,
                    100.0 * out.accepted as f64 / cfg.pairs.max(1) as f64,
                    cfg.pairs as f64 / dt.max(1e-9),
                    pool.current_num_threads()
                )
            });
        }
        results.push((label.clone(), cfg.clone(), out));
    }
    eta.finish();
    if let Some(dir) = &args.output {
        write_outputs(dir, &s, &results, &args.format)?;
        if !quiet {
            println!(
                "wrote {} and {}",
                dir.join("pi_delta_gamma.json").display(),
                dir.join(format!("pi_delta_gamma.{}", args.format)).display()
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The settings and the table's header, on stdout.
fn print_header(s: &Settings, runs: &[(String, McConfig)], threads: usize) {
    println!(
        "sofipol mc: model {}, {} pairs, seed {}, {} threads{}{}",
        s.base.model.spec(),
        s.base.pairs,
        s.base.seed,
        threads,
        perpendicular_note(&s.base),
        if runs[0].1.simulates_polarization() {
            format!(
                ", P_int {}, noise {}, cut {}",
                s.base.p_int.spec(),
                s.base.noise_percent.map_or("none".into(), |x| format!("{x} %")),
                s.base.snr_cut.map_or("none".into(), |x| format!("P/sigma > {x}"))
            )
        } else {
            ", geometry only".into()
        }
    );
    println!(
        "{:<18} {:>12} {:>10} {:>12} {:>16} {:>9}",
        "run", "accepted", "mean [deg]", "frac < 30", "Pi(0-10)/Pi(80-90)", "time [s]"
    );
}

fn write_outputs(
    dir: &Path,
    s: &Settings,
    results: &[(String, McConfig, McOutput)],
    format: &str,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let edges = results[0].2.histogram.edges();
    let runs: Vec<serde_json::Value> = results
        .iter()
        .map(|(label, cfg, out)| {
            serde_json::json!({
                "label": label,
                "p_ism_percent": cfg.ism.map(|i| i.p_percent),
                "simulated": out.simulated,
                "accepted": out.accepted,
                "counts": out.histogram.counts,
                "density_per_deg": out.histogram.density(),
            })
        })
        .collect();
    let parameters = serde_json::json!({
            "model": s.base.model.spec(),
            "pairs": s.base.pairs,
            "seed": s.base.seed,
            "bins": s.base.bins,
            "p_int": results[0].1.simulates_polarization().then(|| s.base.p_int.spec()),
            "p_ism_percent": s.levels,
            "ism_angle_deg": s.levels.as_ref().map(|_| s.ism_angle_deg),
            "noise_percent": s.base.noise_percent,
            "snr_cut": s.base.snr_cut,
            "perpendicular_fraction": s.base.perpendicular_fraction[0],
            "rng": format!("xoshiro256++, one stream per chunk of {CHUNK_PAIRS} pairs seeded from (seed, chunk index) via splitmix64"),
            "conventions": "Delta gamma in [0, 90] deg; intrinsic polarization along the projected disk long axis (spin-axis PA + 90 deg); P in percent",
    });
    let json = serde_json::json!({
        "provenance": Provenance { parameters: Some(parameters), ..Provenance::now() },
        "bin_edges_deg": edges,
        "runs": runs,
    });
    write_atomic(
        &dir.join("pi_delta_gamma.json"),
        serde_json::to_string_pretty(&json)?.as_bytes(),
    )?;
    let plotted: Vec<(String, McOutput)> = results.iter().map(|(l, _, o)| (l.clone(), o.clone())).collect();
    let pint = if results[0].1.simulates_polarization() {
        format!(", Pᵢₙₜ {}", s.base.p_int.spec())
    } else {
        ", geometry only".to_string()
    };
    let title = format!(
        "Π(Δγ), model {}{pint}{}, {} pairs",
        s.base.model.spec(),
        perpendicular_note(&s.base),
        format_count(s.base.pairs)
    );
    mc_figure(&dir.join(format!("pi_delta_gamma.{format}")), &plotted, &title)?;
    Ok(())
}

/// ", 30 % perpendicular" when some disks are polarized perpendicular to their long axis.
fn perpendicular_note(c: &McConfig) -> String {
    let f = c.perpendicular_fraction[0];
    if f > 0.0 {
        format!(", {} % perpendicular", f * 100.0)
    } else {
        String::new()
    }
}

fn bench(s: &Settings, runs: usize) -> anyhow::Result<ExitCode> {
    let geometry = McConfig {
        ism: None,
        noise_percent: None,
        snr_cut: None,
        ..s.base.clone()
    };
    let ism = McConfig {
        ism: Some(Ism {
            p_percent: 1.0,
            angle_deg: s.ism_angle_deg,
        }),
        ..geometry.clone()
    };
    let ism_noise = McConfig {
        noise_percent: Some(0.3),
        ..ism.clone()
    };
    let ism_noise_cut = McConfig {
        snr_cut: Some(3.0),
        ..ism_noise.clone()
    };
    let configs = [
        ("geometry only", geometry),
        ("+ ISM 1 %", ism),
        ("+ ISM 1 % + noise 0.3 %", ism_noise),
        ("+ ISM + noise + cut 3", ism_noise_cut),
    ];
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    println!(
        "sofipol mc --bench: model {}, P_int {}, {} pairs, median of {runs} runs ({cores} cores available)",
        s.base.model.spec(),
        s.base.p_int.spec(),
        s.base.pairs
    );
    println!(
        "{:<26} {:>8} {:>12} {:>12} {:>14}",
        "configuration", "threads", "median [s]", "min [s]", "ns/pair/thread"
    );
    let mut threads = vec![1];
    if cores >= 2 {
        threads.push(2);
    }
    for (name, cfg) in &configs {
        for &t in &threads {
            let pool = super::common::worker_pool("mc", Some(t), true)?;
            pool.install(|| {
                mc::simulate(&McConfig {
                    pairs: cfg.pairs.min(1 << 20),
                    ..cfg.clone()
                })
            })?; // warm-up
            let mut times: Vec<f64> = (0..runs)
                .map(|_| {
                    let t0 = Instant::now();
                    pool.install(|| mc::simulate(cfg)).map(|_| t0.elapsed().as_secs_f64())
                })
                .collect::<Result<_, _>>()?;
            let min = times.iter().cloned().fold(f64::INFINITY, f64::min);
            let med = median_in_place(&mut times);
            println!(
                "{name:<26} {t:>8} {med:>12.3} {min:>12.3} {:>14.1}",
                med * 1e9 * t as f64 / cfg.pairs as f64
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
