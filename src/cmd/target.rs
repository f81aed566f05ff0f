//! `sofipol target`: reduce one target sequence to a JSON catalog.
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use sofipol_pipeline::catalog::Status;
use sofipol_pipeline::night::{self, RunOptions};

use super::setup::SetupArgs;

/// Arguments of `sofipol target`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// FITS files and/or directories holding the sequence.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    /// Target name (OBJECT); needed when the inputs hold several targets [default: the
    /// inputs' one target].
    #[arg(long)]
    pub object: Option<String>,
    /// Output catalog (JSON, written atomically).
    #[arg(short, long, default_value = "catalog.json")]
    pub output: PathBuf,
    #[command(flatten)]
    pub outputs: super::common::OutputArgs,
    #[command(flatten)]
    pub setup: SetupArgs,
    /// Print only errors.
    #[arg(short, long)]
    pub quiet: bool,
    /// More detail: the night's bad-pixel mask, the stage-time summary and peak memory (on
    /// stderr).
    #[arg(short, long, action = clap::ArgAction::Count)]
    pub verbose: u8,
}

/// Run: the sequence is reduced as one target of a night ([`night::run_night`]), with the
/// flats built from all the inputs and the standards among them calibrating it.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let setup = args.setup.load()?;
    if args.setup.reduce.dump_params {
        print!("{}", super::setup::dump_params(&setup.params)?);
        return Ok(ExitCode::SUCCESS);
    }
    for i in &args.inputs {
        anyhow::ensure!(i.exists(), "{}: no such file or directory", i.display());
    }
    super::setup::check_input_frames(&setup.params)?;
    let mut plan = setup.plan_inputs(&args.inputs, None)?;
    super::common::check_scan_complete(&plan)?;
    anyhow::ensure!(
        plan.n_files > 0,
        "no FITS files (.fits, .fit, .fits.gz, .fz) in {:?}",
        args.inputs
    );
    if let Some(obj) = &args.object {
        let mut found: Vec<&str> = plan.sequences.iter().map(|q| q.object.as_str()).collect();
        found.dedup();
        if !found.contains(&obj.as_str()) {
            anyhow::bail!("{}", no_such_object(obj, &found));
        }
        plan.sequences.retain(|q| &q.object == obj);
    } else if plan.sequences.len() > 1 {
        let names: Vec<String> = plan
            .sequences
            .iter()
            .map(|q| sofipol_calib::text::printable(&q.object).into_owned())
            .collect();
        anyhow::bail!(
            "the inputs hold {} sequences ({}): choose one with --object",
            plan.sequences.len(),
            names.join(", ")
        );
    }
    anyhow::ensure!(
        !plan.sequences.is_empty(),
        "no polarimetric science frames among {} file(s)",
        plan.n_files
    );
    let mut inputs = plan.files.clone();
    inputs.extend(args.setup.input_files());
    super::common::check_output(&args.output, &inputs)?;
    if let Some(d) = &args.setup.reduce.save_intermediate {
        super::common::check_output_dir(d, "--save-intermediate")?;
    }
    // Files that are not SOFI polarimetric frames count as failures only when they were
    // named explicitly (a directory may hold anything).
    let explicit: Vec<String> = args
        .inputs
        .iter()
        .filter(|p| p.is_file())
        .map(|p| p.display().to_string())
        .collect();
    plan.not_science.retain(|f| explicit.contains(&f.file));
    // One sequence: its bad pixels are detected from its own frames.
    let outputs = super::common::outputs(&args.output, args.outputs.choice(false), &setup)?;
    let opts = RunOptions {
        inputs: args.inputs.clone(),
        outputs: Some(&outputs),
        ..Default::default()
    };
    let t0 = std::time::Instant::now();
    let out = night::run_night(&plan, &setup, &opts);
    let cat = &out.catalog;
    if !args.quiet {
        for l in &out.summary.lines {
            eprintln!("sofipol target: {}", sofipol_calib::text::printable(l));
        }
    }
    sofipol_pipeline::io::write_json_atomic(&args.output, cat)
        .with_context(|| format!("writing {}", args.output.display()))?;
    if !args.quiet {
        print!("{}", super::summary::summary(cat));
        println!("catalog: {}", args.output.display());
    }
    if args.verbose > 0 {
        super::night::print_verbose(&out, t0.elapsed().as_secs_f64());
    }
    let fits_failed = super::common::finish_outputs(outputs, true, args.quiet, "target");
    let failed = cat.targets.iter().any(|t| t.status != Status::Ok)
        || super::summary::uncalibrated_exit(cat, setup.calibration.params.allow_uncalibrated);
    Ok(if failed || !cat.failures.is_empty() || fits_failed {
        ExitCode::from(2)
    } else {
        ExitCode::SUCCESS
    })
}

/// The error of an `--object` that names no sequence: the objects found and the closest
/// one ([`closest_object`]), if any.
fn no_such_object(wanted: &str, found: &[&str]) -> String {
    use sofipol_calib::text::printable;
    let mut msg = format!(
        "no polarimetric sequence of object '{}' in the inputs",
        printable(wanted)
    );
    if let Some(c) = closest_object(wanted, found) {
        msg += &format!("; did you mean --object '{}'?", printable(c));
    }
    if found.is_empty() {
        msg += " (no science sequence found)";
    } else {
        let names: Vec<String> = found.iter().map(|n| format!("'{}'", printable(n))).collect();
        msg += &format!(
            " (--object is exact and case-sensitive; objects found: {})",
            names.join(", ")
        );
    }
    msg
}

/// The object of `found` that `wanted` most likely means: the one equal to it when case
/// and whitespace are ignored, else the nearest by Levenshtein distance (of the lower-case
/// names) when that distance is at most a third of the name's length (at least 2).
fn closest_object<'a>(wanted: &str, found: &[&'a str]) -> Option<&'a str> {
    let fold = |s: &str| {
        s.chars()
            .filter(|c| !c.is_whitespace())
            .collect::<String>()
            .to_lowercase()
    };
    let w = fold(wanted);
    if let Some(f) = found.iter().find(|f| fold(f) == w) {
        return Some(f);
    }
    let w = wanted.trim().to_lowercase();
    let limit = (w.chars().count() / 3).max(2);
    found
        .iter()
        .map(|f| (strsim::levenshtein(&w, &f.trim().to_lowercase()), *f))
        .filter(|(d, _)| *d <= limit)
        .min_by_key(|(d, _)| *d)
        .map(|(_, f)| f)
}

#[cfg(test)]
mod tests {
    use super::closest_object;

    #[test]
    fn the_closest_object_ignores_case_and_blanks_then_takes_the_edit_distance() {
        let found = ["HK Tau", "V773 Tau", "Elias 2-12"];
        assert_eq!(closest_object("hktau", &found), Some("HK Tau"));
        assert_eq!(closest_object(" hk  TAU ", &found), Some("HK Tau"));
        assert_eq!(closest_object("V733 Tau", &found), Some("V773 Tau"));
        assert_eq!(closest_object("Elias 2-21", &found), Some("Elias 2-12"));
        assert_eq!(closest_object("Nobody", &found), None);
    }
}
