//! `sofipol night DIR -o catalog.json`: reduce a whole night in parallel.
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::Context;
use sofipol_pipeline::catalog::Status;
use sofipol_pipeline::night::{self, Shard};

use super::common::{progress, ProfileArgs};
use super::target::ReduceArgs;

/// `--jobs` is capped at this many threads per core.
pub const MAX_JOBS_PER_CORE: usize = 4;

/// Arguments of `sofipol night`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Night directories (searched recursively for .fits, .fit, .fits.gz, .fz).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Output catalog (JSON, written atomically).
    #[arg(short, long, default_value = "catalog.json")]
    pub output: PathBuf,
    /// Worker threads (default: all cores; at most 4 x the cores: more are capped, with a note).
    #[arg(short, long)]
    pub jobs: Option<usize>,
    /// Reduce only shard K of N (1-based), a deterministic partition of the sequences; join
    /// the shard catalogs with `sofipol merge`.
    #[arg(long, value_name = "K/N")]
    pub shard: Option<Shard>,
    /// Do not write the per-target PNG figures.
    #[arg(long)]
    pub no_png: bool,
    #[command(flatten)]
    pub reduce: ReduceArgs,
    #[command(flatten)]
    pub calib: super::calib::CalibArgs,
    #[command(flatten)]
    pub profile: ProfileArgs,
    /// Print only errors.
    #[arg(short, long)]
    pub quiet: bool,
    /// More detail: the night's bad-pixel mask, the stage-time summary and peak memory.
    #[arg(short, long, action = clap::ArgAction::Count)]
    pub verbose: u8,
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let profile = args.profile.load()?;
    let params = args.reduce.params()?;
    let setup = args.calib.setup(&params.calibration)?;
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let mut jobs = args.jobs;
    if let Some(j) = jobs {
        anyhow::ensure!(j >= 1, "--jobs {j}: need at least 1");
        // Thousands of threads only thrash (and each holds a frame set in memory).
        let cap = MAX_JOBS_PER_CORE * cores;
        if j > cap {
            if !args.quiet {
                eprintln!("sofipol night: --jobs {j} capped at {cap} ({MAX_JOBS_PER_CORE} x {cores} cores)");
            }
            jobs = Some(cap);
        }
    }
    for d in &args.dirs {
        anyhow::ensure!(d.exists(), "{}: no such file or directory", d.display());
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(jobs.unwrap_or(0))
        .build()
        .context("starting worker threads")?;
    let t0 = std::time::Instant::now();
    // Standards are split off before sharding: every shard calibrates with all of them.
    let mut plan = night::plan(&args.dirs, &profile, None).context("scanning the night")?;
    anyhow::ensure!(
        plan.n_files > 0,
        "no FITS files (.fits, .fit, .fits.gz, .fit.gz, .fz) in {}",
        args.dirs
            .iter()
            .map(|d| d.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    );
    // Outputs are checked before the reduction starts, never overwrite an input.
    let mut inputs = plan.files.clone();
    inputs.extend(args.reduce.input_files());
    inputs.extend(args.profile.profile.clone());
    super::common::check_output(&args.output, &inputs)?;
    if let Some(d) = &args.reduce.save_intermediate {
        super::common::check_output_dir(d, "--save-intermediate")?;
    }
    let (science, stds) = sofipol_pipeline::calibration::split_standards(std::mem::take(&mut plan.sequences), &profile);
    plan.sequences = science;
    if let Some(sh) = args.shard {
        plan.sequences.retain(|q| sh.owns(&q.id));
        plan.failures.retain(|f| sh.owns(&f.file));
    }
    let n = plan.sequences.len();
    if !args.quiet {
        eprintln!(
            "sofipol night: {} files, {} sequences + {} standard(s){}, {} inputs not used (found while scanning); {} threads",
            plan.n_files,
            n,
            stds.len(),
            args.shard
                .map(|s| format!(" in shard {}/{}", s.k, s.n))
                .unwrap_or_default(),
            plan.failures.len(),
            pool.current_num_threads()
        );
    }
    let tty = std::io::stderr().is_terminal();
    let pb = progress(n as u64, "reduce", args.quiet || !tty);
    let done = AtomicUsize::new(0);
    let on_done = |t: &sofipol_pipeline::catalog::Target| {
        let k = done.fetch_add(1, Ordering::Relaxed) + 1;
        let st = match t.status {
            Status::Ok => "ok",
            Status::Partial => "partial",
            Status::Failed => "failed",
        };
        if tty && !args.quiet {
            pb.inc(1);
            pb.set_message(format!("{} {st}", t.object));
        } else if !args.quiet {
            eprintln!(
                "[{k}/{n}] {} {st}{}",
                t.object,
                t.error.as_deref().map(|e| format!(": {e}")).unwrap_or_default()
            );
        }
    };
    let png_dir = (!args.no_png).then(|| night::products_dir(&args.output));
    if let Some(d) = &png_dir {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let plot = |out: &sofipol_pipeline::reduce::run::TargetOutcome| {
        if let Some(d) = &png_dir {
            plot_target(d, out);
        }
    };
    // The detector's defects, detected once for the night (unless only a calibration mask
    // is wanted).
    let mut night_mask = None;
    let mut night_mask_files = Vec::new();
    if !params.no_detect_bad_pixels {
        let t = std::time::Instant::now();
        if let Some((m, files)) = pool.install(|| night::night_bad_pixel_mask(&plan, &profile, &params.bad_pixels, 15))
        {
            if args.verbose > 0 {
                eprintln!(
                    "night bad-pixel mask: {} pixels from {} frames in {:.2} s",
                    m.iter().filter(|&&v| v != 0).count(),
                    files.len(),
                    t.elapsed().as_secs_f64()
                );
            }
            night_mask = Some(m);
            night_mask_files = files;
        }
    }
    // The night's flats (dome flats, else a superflat from the night's sky), built from the
    // whole night's frame list so that every shard gets the same flats.
    let t = std::time::Instant::now();
    let flats = pool.install(|| night::night_flats(&plan.dome_flats, &plan.superflat_frames, &profile, &params));
    if args.verbose > 0 {
        eprintln!(
            "flats: {} in {:.2} s",
            flats.provenance.get("mode").and_then(|m| m.as_str()).unwrap_or("none"),
            t.elapsed().as_secs_f64()
        );
    }
    let res = pool.install(|| {
        night::reduce_night(
            &plan,
            &profile,
            &params,
            night_mask.as_ref(),
            flats.set.as_ref(),
            png_dir.is_some(),
            &on_done,
            &plot,
        )
    });
    pb.finish_and_clear();
    let mut cat = res.catalog;
    let t_cal = std::time::Instant::now();
    let cal_summary = pool.install(|| {
        super::calib::calibrate(
            &mut cat,
            &stds,
            &profile,
            &params,
            night_mask.as_ref(),
            flats.set.as_ref(),
            &setup,
        )
    });
    let cal_s = t_cal.elapsed().as_secs_f64();
    let mut prov = super::report::provenance(&profile, &params);
    prov["shard"] = serde_json::json!(args.shard.map(|s| format!("{}/{}", s.k, s.n)));
    prov["inputs"] = serde_json::json!(args.dirs);
    prov["night_bad_pixel_mask_from"] = serde_json::json!(night_mask_files);
    prov["flat"] = flats.provenance;
    let owned_flat_failures: Vec<_> = flats
        .failures
        .into_iter()
        .filter(|f| args.shard.is_none_or(|sh| sh.owns(&f.file)))
        .collect();
    cat.failures.extend(owned_flat_failures);
    cat.failures.sort_by(|a, b| a.file.cmp(&b.file));
    prov["calibration"] = serde_json::json!({"params": setup.params, "standards_table": setup.table.sources,
        "calib_dir": setup.external.as_ref().map(|e| e.0.display().to_string())});
    cat.provenance = prov;
    if !args.quiet {
        for l in &cal_summary.lines {
            eprintln!("sofipol night: {l}");
        }
    }
    sofipol_pipeline::io::write_json_atomic(&args.output, &cat)
        .with_context(|| format!("writing {}", args.output.display()))?;
    let wall = t0.elapsed().as_secs_f64();
    if !args.quiet {
        print!("{}", super::report::summary(&cat));
        let ok = cat.targets.iter().filter(|t| t.status == Status::Ok).count();
        println!(
            "{} targets: {ok} ok, {} partial, {} failed; {} inputs not used ({} found while scanning, {} during the reduction); {:.2} s wall -> {}",
            cat.targets.len(),
            cat.targets.iter().filter(|t| t.status == Status::Partial).count(),
            cat.targets.iter().filter(|t| t.status == Status::Failed).count(),
            cat.failures.len(),
            plan.failures.len(),
            cat.failures.len() - plan.failures.len(),
            wall,
            args.output.display()
        );
        if let Some(d) = &png_dir {
            println!("figures: {}", d.display());
        }
    }
    if args.verbose > 0 {
        let sum = res.times.iter().fold([0.0; 6], |a, t| {
            [
                a[0] + t.read,
                a[1] + t.bad_pixels,
                a[2] + t.sky,
                a[3] + t.measure,
                a[4] + t.write,
                a[5] + t.flat,
            ]
        });
        eprintln!(
            "stage time summed over targets: read {:.2} s, bad pixels {:.2} s, flat {:.2} s, sky {:.2} s, measure {:.2} s, write {:.2} s; calibration {cal_s:.2} s; wall {wall:.2} s; cpu {:.2} s; peak RSS {:.0} MB",
            sum[0],
            sum[1],
            sum[5],
            sum[2],
            sum[3],
            sum[4],
            night::cpu_seconds().unwrap_or(f64::NAN),
            night::peak_rss_bytes().unwrap_or(0) as f64 / 1e6
        );
    }
    let bad = cat.targets.iter().any(|t| t.status != Status::Ok) || !cat.failures.is_empty();
    Ok(if bad { ExitCode::from(2) } else { ExitCode::SUCCESS })
}

/// Write the per-target figure (never fails the night: a problem is printed).
fn plot_target(dir: &std::path::Path, out: &sofipol_pipeline::reduce::run::TargetOutcome) {
    let seq = out
        .target
        .extra
        .get("sequence")
        .and_then(|v| v.as_str())
        .unwrap_or(&out.target.object);
    let path = dir.join(format!("{}.png", night::slug(seq)));
    if let Err(e) = sofipol_pipeline::plots::target::outcome_png(&path, out) {
        eprintln!("sofipol: warning: {}: could not write the figure: {e}", path.display());
    }
}
