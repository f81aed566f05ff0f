//! `sofipol night DIR -o catalog.json`: reduce a whole night in parallel.
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use anyhow::Context;
use sofipol_calib::text::printable;
use sofipol_pipeline::catalog::{Catalog, Status, Target};
use sofipol_pipeline::io;
use sofipol_pipeline::night::{self, Hooks, NightOutput, NightPlan, NightSetup, RunOptions, Shard};
use sofipol_pipeline::products::Outputs;
use sofipol_pipeline::reduce::run::StageTimes;

use super::common::{progress, OutputArgs};
use super::setup::SetupArgs;

/// Arguments of `sofipol night`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Night directories (searched recursively for .fits, .fit, .fits.gz, .fz).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Output catalog (JSON, written atomically).
    #[arg(short, long, value_name = "FILE", default_value = "catalog.json")]
    pub output: PathBuf,
    /// Worker threads (at most 4 x the cores: more are capped, with a note) [default: all
    /// cores].
    #[arg(short, long, value_name = "N")]
    pub jobs: Option<usize>,
    /// Reduce only shard K of N (1-based), a deterministic partition of the sequences; join
    /// the shard catalogs with `sofipol merge` [default: the whole night].
    #[arg(long, value_name = "K/N")]
    pub shard: Option<Shard>,
    /// Do not write the per-target PNG figures.
    #[arg(long)]
    pub no_png: bool,
    #[command(flatten)]
    pub outputs: OutputArgs,
    /// Also write the night's HTML page (`sofipol report`) to FILE, after the catalog
    /// [default: none].
    #[arg(long, value_name = "FILE")]
    pub report: Option<PathBuf>,
    #[command(flatten)]
    pub setup: SetupArgs,
    /// Print only errors.
    #[arg(short, long)]
    pub quiet: bool,
    /// More detail: the night's bad-pixel mask, the stage-time summary and peak memory.
    #[arg(short, long, action = clap::ArgAction::Count)]
    pub verbose: u8,
}

/// Run: check the options, plan the night, reduce it ([`night::run_night`]: the night-wide
/// bad-pixel mask and flats, every sequence, the standards and the calibration), write the
/// catalog.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let profile = args.setup.profile.load()?;
    if profile.modulation_kind() != sofipol_calib::profile::ModulationKind::RotateInstrument {
        return run_single_pointing(&args, &profile);
    }
    let setup = args.setup.load()?;
    if args.setup.reduce.dump_params {
        print!("{}", super::setup::dump_params(&setup.params)?);
        return Ok(ExitCode::SUCCESS);
    }
    let pool = super::common::worker_pool("night", args.jobs, args.quiet)?;
    super::setup::check_input_frames(&setup.params)?;
    for d in &args.dirs {
        anyhow::ensure!(d.exists(), "{}: no such file or directory", d.display());
    }
    let t0 = Instant::now();
    let plan = pool.install(|| plan_night(&args, &setup))?;
    if !args.quiet {
        eprintln!(
            "sofipol night: {} files, {} sequences + {} standard(s){}, {} inputs not used (found while scanning); {} threads",
            plan.n_files,
            plan.sequences.len(),
            plan.standards.len(),
            args.shard
                .map(|s| format!(" in shard {}/{}", s.k, s.n))
                .unwrap_or_default(),
            plan.failures.len() + plan.not_science.len(),
            pool.current_num_threads()
        );
    }
    let outputs = super::common::outputs(&args.output, args.outputs.choice(!args.no_png), &setup)?;
    let out = pool.install(|| reduce_with_progress(&plan, &setup, &args, &outputs));
    let cat = &out.catalog;
    if !args.quiet {
        for l in &out.summary.lines {
            eprintln!("sofipol night: {}", printable(l));
        }
    }
    sofipol_pipeline::io::write_json_atomic(&args.output, cat)
        .with_context(|| format!("writing {}", args.output.display()))?;
    let log = night::write_night_log(&args.output, cat)
        .with_context(|| format!("writing {}", night::log_path(&args.output).display()))?;
    if let Some(r) = &args.report {
        let products = (!args.no_png).then(|| night::products_dir(&args.output));
        let (pairs, seed) = (
            sofipol_pipeline::report::DEFAULT_REPORT_PAIRS,
            sofipol_pipeline::stats::mc::DEFAULT_SEED,
        );
        pool.install(|| super::report::write_page(cat.clone(), &args.output, products.as_deref(), r, pairs, seed))?;
    }
    let wall = t0.elapsed().as_secs_f64();
    if !args.quiet {
        let written = Written {
            catalog: &args.output,
            log: &log,
            figures: outputs.figures_dir(),
            regions: outputs.regions_dir(),
            report: args.report.as_deref(),
        };
        print_summary(cat, plan.failures.len() + plan.not_science.len(), wall, &written);
    }
    if args.verbose > 0 {
        print_verbose(&out, wall);
    }
    let incomplete = super::common::finish_outputs(outputs, true, args.quiet, "night");
    let bad = cat.targets.iter().any(|t| t.status != Status::Ok)
        || !cat.failures.is_empty()
        || super::summary::uncalibrated_exit(cat, setup.calibration.params.allow_uncalibrated);
    Ok(if bad || incomplete {
        ExitCode::from(2)
    } else {
        ExitCode::SUCCESS
    })
}

/// The options of `night` given that the half-wave-plate reduction does not use, each with
/// why: every field of [`Args`] is named below (no `..`), so a new option does not compile
/// until it is either used by the half-wave-plate night or refused here.
fn single_pointing_refusals(args: &Args) -> Vec<(&'static str, &'static str)> {
    use super::common::OutputArgs;
    use super::setup::{CalibArgs, FlatArgs, ReduceArgs};
    let Args {
        dirs: _,
        output: _,
        jobs: _,
        shard,
        // Nothing to leave out: the half-wave-plate night writes no figure.
        no_png: _,
        outputs: OutputArgs { regions, fits_products },
        // The night's HTML page (`sofipol report`), with its half-wave-plate section.
        report: _,
        setup:
            super::setup::SetupArgs {
                reduce:
                    ReduceArgs {
                        params,
                        param,
                        dump_params,
                        badpix,
                        aperture_fwhm,
                        method,
                        debias,
                        companion,
                        save_intermediate,
                    },
                flat: FlatArgs { flat, no_flat },
                calib:
                    CalibArgs {
                        calib,
                        standards,
                        stokes_method,
                        no_calibration,
                        no_telescope_correction,
                        allow_uncalibrated,
                    },
                // The profile and its --set overrides set the reduction.
                profile: _,
            },
        quiet: _,
        verbose,
    } = args;
    const PROFILE: &str = "the reduction is set by the profile's [single_pointing] section (change it with --set single_pointing.KEY=VALUE)";
    let refusals: [(&str, bool, &str); 20] = [
        ("--shard", shard.is_some(), "the night is one set of frames, not split into sequences"),
        ("--regions", *regions, "no DS9 region files are written for a half-wave-plate night"),
        ("--fits-products", *fits_products, "no FITS products are written for a half-wave-plate night"),
        ("--params", params.is_some(), PROFILE),
        ("--param", !param.is_empty(), PROFILE),
        ("--dump-params", *dump_params, PROFILE),
        ("--badpix", badpix.is_some(), "bad pixels come from the night's darks and flat (single_pointing.hot_pixel_adu)"),
        ("--aperture-fwhm", aperture_fwhm.is_some(), "the aperture is single_pointing.aperture_px, in pixels"),
        ("--method", method.is_some(), "the aperture's pixels are always weighted by their exact overlap"),
        ("--debias", debias.is_some(), "P is reported as measured, not debiased"),
        ("--companion", companion.is_some(), "one star per frame is measured; there is no companion search"),
        ("--save-intermediate", save_intermediate.is_some(), "no intermediate frames are written for a half-wave-plate night"),
        ("--flat", !flat.is_empty(), "the flat is made from the night's sky frames of complete plate cycles"),
        ("--no-flat", *no_flat, "the flat from the sky frames also finds the bad pixels and is always applied"),
        ("--calib", calib.is_some(), "there is no standard-star calibration: the zero point is modulation.zero_point_deg"),
        ("--standards", standards.is_some(), "there is no standard-star calibration: the zero point is modulation.zero_point_deg"),
        ("--stokes-method", stokes_method.is_some(), "q and u come from the double difference of each plate cycle and the least squares over the frames, both always given"),
        ("--no-calibration", *no_calibration, "there is no standard-star calibration to leave out (the instrument-frame result is always given)"),
        ("--no-telescope-correction", *no_telescope_correction, "the telescope's polarization is neither fitted nor removed"),
        ("--allow-uncalibrated", *allow_uncalibrated, "there is no P/sigma cut on calibration"),
    ];
    let mut out: Vec<(&str, &str)> = refusals.iter().filter(|r| r.1).map(|r| (r.0, r.2)).collect();
    if *verbose > 0 {
        out.push((
            "--verbose",
            "the half-wave-plate night prints its whole summary without it",
        ));
    }
    out
}

/// A half-wave-plate profile (`--profile nirc2`): the single-pointing reduction
/// ([`sofipol_pipeline::single_pointing`]) of every target under the inputs, its catalog
/// (sofipol's, each target's half-wave-plate results in its `half_wave_plate` section)
/// written to `-o` with the night log and set-of-frames file beside it, and its HTML page
/// to `--report`; one summary per target on stderr; exit 2 as a SOFI night's when a target
/// is not `ok` or a file was not used. The SOFI night's options that do not apply are
/// refused by name, with why ([`single_pointing_refusals`]).
fn run_single_pointing(args: &Args, profile: &sofipol_calib::Profile) -> anyhow::Result<ExitCode> {
    let refused = single_pointing_refusals(args);
    anyhow::ensure!(
        refused.is_empty(),
        "not available with profile {} (modulation.kind = {}): {}",
        profile.name,
        profile.modulation_kind().name(),
        refused
            .iter()
            .map(|(flag, why)| format!("{flag}: {why}"))
            .collect::<Vec<_>>()
            .join("; ")
    );
    for d in &args.dirs {
        anyhow::ensure!(d.exists(), "{}: no such file or directory", d.display());
    }
    let files = sofipol_pipeline::single_pointing::input_files(&args.dirs)?;
    anyhow::ensure!(
        !files.is_empty(),
        "no FITS files (.fits, .fit, .fits.gz, .fit.gz, .fz) in {}",
        args.dirs
            .iter()
            .map(|d| d.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    );
    let mut inputs: Vec<PathBuf> = files.iter().map(|f| f.path.clone()).collect();
    inputs.extend(args.setup.input_files());
    super::common::check_output(&args.output, &inputs)?;
    if let Some(r) = &args.report {
        inputs.push(args.output.clone());
        super::common::check_output(r, &inputs)?;
    }
    let pool = super::common::worker_pool("night", args.jobs, args.quiet)?;
    let t0 = Instant::now();
    let sp = pool.install(|| sofipol_pipeline::single_pointing::reduce_inputs(&files, &args.dirs, profile))?;
    let cat = sofipol_pipeline::single_pointing::output::to_catalog(&sp, &files, profile)?;
    io::write_json_atomic(&args.output, &cat).with_context(|| format!("writing {}", args.output.display()))?;
    let log = night::write_night_log(&args.output, &cat)
        .with_context(|| format!("writing {}", night::log_path(&args.output).display()))?;
    if let Some(r) = &args.report {
        let (pairs, seed) = (
            sofipol_pipeline::report::DEFAULT_REPORT_PAIRS,
            sofipol_pipeline::stats::mc::DEFAULT_SEED,
        );
        pool.install(|| super::report::write_page(cat.clone(), &args.output, None, r, pairs, seed))?;
    }
    if !args.quiet {
        for line in sofipol_pipeline::single_pointing::summary_lines(&sp) {
            eprintln!("sofipol night: {}", printable(&line));
        }
        eprintln!(
            "sofipol night: catalog {}, night log {} ({:.1} s)",
            args.output.display(),
            log.display(),
            t0.elapsed().as_secs_f64()
        );
    }
    let bad = cat.targets.iter().any(|t| t.status != Status::Ok) || !cat.failures.is_empty();
    Ok(if bad { ExitCode::from(2) } else { ExitCode::SUCCESS })
}

/// Scan the night (standards apart, this shard's sequences and failures) and check the
/// outputs against its files (never overwrite an input).
fn plan_night(args: &Args, setup: &NightSetup) -> anyhow::Result<NightPlan> {
    let plan = setup.plan_inputs(&args.dirs, args.shard)?;
    super::common::check_scan_complete(&plan)?;
    anyhow::ensure!(
        plan.n_files > 0,
        "no FITS files (.fits, .fit, .fits.gz, .fit.gz, .fz) in {}",
        args.dirs
            .iter()
            .map(|d| d.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    );
    let mut inputs = plan.files.clone();
    inputs.extend(args.setup.input_files());
    super::common::check_output(&args.output, &inputs)?;
    if let Some(r) = &args.report {
        inputs.push(args.output.clone());
        super::common::check_output(r, &inputs)?;
    }
    if let Some(d) = &args.setup.reduce.save_intermediate {
        super::common::check_output_dir(d, "--save-intermediate")?;
    }
    Ok(plan)
}

/// Run the night (in the current rayon pool) with a progress bar on a terminal, else a line
/// per target (nothing if `quiet`); each target's figure, DS9 regions and FITS products
/// written through `outputs` as asked.
fn reduce_with_progress(plan: &NightPlan, setup: &NightSetup, args: &Args, outputs: &Outputs) -> NightOutput {
    let n = plan.sequences.len();
    let quiet = args.quiet;
    let tty = std::io::stderr().is_terminal();
    let pb = progress(n as u64, "reduce", quiet || !tty);
    let done = AtomicUsize::new(0);
    let on_done = |t: &Target| {
        let k = done.fetch_add(1, Ordering::Relaxed) + 1;
        let st = match t.status {
            Status::Ok => "ok",
            Status::Partial => "partial",
            Status::Failed => "failed",
        };
        if tty && !quiet {
            pb.inc(1);
            pb.set_message(format!("{} {st}", printable(&t.object)));
        } else if !quiet {
            eprintln!(
                "[{k}/{n}] {} {st}{}",
                printable(&t.object),
                t.error
                    .as_deref()
                    .map(|e| format!(": {}", printable(e)))
                    .unwrap_or_default()
            );
        }
    };
    let opts = RunOptions {
        night_mask: true,
        shard: args.shard,
        inputs: args.dirs.clone(),
        hooks: Hooks {
            on_done: Some(&on_done),
            ..Hooks::default()
        },
        cache: None,
        outputs: Some(outputs),
    };
    let out = night::run_night(plan, setup, &opts);
    pb.finish_and_clear();
    out
}

/// Where a night's outputs went.
struct Written<'a> {
    catalog: &'a Path,
    log: &'a Path,
    figures: Option<&'a Path>,
    regions: Option<&'a Path>,
    report: Option<&'a Path>,
}

/// The night's summary on stdout: the targets, their status, the inputs not used
/// (`scan_failures` of them found while scanning), the wall time, where the outputs are.
fn print_summary(cat: &Catalog, scan_failures: usize, wall: f64, written: &Written) {
    print!("{}", super::summary::summary(cat));
    let count = |s: Status| cat.targets.iter().filter(|t| t.status == s).count();
    println!(
        "{} targets: {} ok, {} partial, {} failed; {} inputs not used ({} found while scanning, {} during the reduction); {:.2} s wall -> {}",
        cat.targets.len(),
        count(Status::Ok),
        count(Status::Partial),
        count(Status::Failed),
        cat.failures.len(),
        scan_failures,
        cat.failures.len() - scan_failures,
        wall,
        written.catalog.display()
    );
    if let Some(d) = written.figures {
        println!("figures: {}", d.display());
    }
    if let Some(d) = written.regions {
        println!("DS9 regions: {}", d.display());
    }
    println!("night log: {}", written.log.display());
    if let Some(r) = written.report {
        println!("report: {}", r.display());
    }
}

/// `-v`: the night's bad-pixel mask and flats, the stage times summed over the targets, the
/// calibration and wall times, CPU time and peak memory, on stderr.
pub fn print_verbose(out: &NightOutput, wall: f64) {
    if let Some(nm) = &out.mask {
        eprintln!(
            "night bad-pixel mask: {} pixels{} from {} frames in {:.2} s",
            nm.mask.iter().filter(|&&v| v != 0).count(),
            nm.rows
                .map(|(r0, r1)| format!(" in rows [{r0}, {r1}) (the target strips, all the reduction uses)"))
                .unwrap_or_default(),
            nm.files.len(),
            out.seconds.mask
        );
    }
    eprintln!("flats: {} in {:.2} s", out.flats.provenance.mode, out.seconds.flats);
    let times: &[StageTimes] = &out.times;
    let sum = |f: fn(&StageTimes) -> f64| times.iter().fold(0.0, |a, t| a + f(t));
    eprintln!(
        "stage time summed over targets: read {:.2} s, bad pixels {:.2} s, flat {:.2} s, sky {:.2} s, measure {:.2} s, write {:.2} s; calibration {:.2} s; figures {:.2} s; wall {wall:.2} s; cpu {:.2} s; peak RSS {:.0} MB",
        sum(|t| t.read),
        sum(|t| t.bad_pixels),
        sum(|t| t.flat),
        sum(|t| t.sky),
        sum(|t| t.measure),
        sum(|t| t.write),
        out.seconds.calibration,
        out.seconds.figures,
        io::cpu_seconds().unwrap_or(f64::NAN),
        io::peak_rss_bytes().unwrap_or(0) as f64 / 1e6
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{Args as _, FromArgMatches};

    /// Every option of `night` that the half-wave-plate reduction does not use is refused
    /// naming it: the options are taken from clap's own list of `night`'s arguments (a new
    /// one is tested without being listed here); only the ones the half-wave-plate night
    /// uses pass.
    #[test]
    fn every_sofi_only_option_is_refused_by_name() {
        let used = ["dirs", "output", "jobs", "no_png", "report", "quiet", "profile", "sets"];
        let cmd = Args::augment_args(clap::Command::new("night"));
        let mut tried = 0;
        for arg in cmd.get_arguments() {
            let id = arg.get_id().as_str();
            if used.contains(&id) {
                continue;
            }
            let long = arg.get_long().unwrap_or_else(|| panic!("{id}: no long name"));
            let flag = format!("--{long}");
            // A value clap accepts for it: its first possible value, else the first of a few
            // kinds that parses.
            let candidates: Vec<String> = if !arg.get_action().takes_values() {
                vec![]
            } else if let Some(v) = arg.get_possible_values().first() {
                vec![v.get_name().to_string()]
            } else {
                ["1/2", "1.5", "1.0,30", "a.b=1", "x.toml", "exact", "wk", "ratio"]
                    .map(String::from)
                    .to_vec()
            };
            let parsed = if candidates.is_empty() {
                cmd.clone()
                    .try_get_matches_from(["night", "d", "--profile", "nirc2", &flag])
                    .ok()
            } else {
                candidates.iter().find_map(|v| {
                    cmd.clone()
                        .try_get_matches_from(["night", "d", "--profile", "nirc2", &flag, v])
                        .ok()
                })
            };
            let m = parsed.unwrap_or_else(|| panic!("{flag}: no test value parses"));
            let args = Args::from_arg_matches(&m).unwrap();
            let refused = single_pointing_refusals(&args);
            assert_eq!(refused.len(), 1, "{flag}: {refused:?}");
            assert_eq!(refused[0].0, flag, "{flag}: {refused:?}");
            assert!(refused[0].1.len() > 20, "{flag}: no reason");
            tried += 1;
        }
        assert!(tried >= 21, "{tried} options tried");
        // The options it uses pass.
        let m = cmd
            .clone()
            .try_get_matches_from([
                "night",
                "d",
                "--profile",
                "nirc2",
                "-o",
                "c.json",
                "-j",
                "2",
                "--no-png",
                "--report",
                "r.html",
                "-q",
                "--set",
                "a.b=1",
            ])
            .unwrap();
        assert!(single_pointing_refusals(&Args::from_arg_matches(&m).unwrap()).is_empty());
    }
}
