//! `sofipol calib NIGHT -o CALDIR`: the calibration products of a night
//! (`calibration.json`: instrumental offset c, angle zero-point, parity, their errors per
//! filter, the standards and frames used, provenance), and the shared calibration
//! options of `night` and `target` (`--calib`, `--standards`, `--stokes-method`,
//! `--no-calibration`).
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use sofipol_calib::Profile;
use sofipol_pipeline::calibration::{CalibSetup, Calibration, CALIBRATION_FILE};
use sofipol_pipeline::catalog::Provenance;
use sofipol_pipeline::night::{self, NightSetup, RunOptions};

use super::common::ProfileArgs;
use super::setup::{FlatArgs, ReduceArgs};

/// Arguments of `sofipol calib`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Night directories (searched recursively).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Calibration directory to write (calibration.json, flats; required).
    #[arg(short, long, value_name = "CALDIR")]
    pub output: PathBuf,
    /// Standards table (TOML) adding to or overriding the built-in one [default: none, the
    /// built-in table].
    #[arg(long, value_name = "FILE")]
    pub standards: Option<PathBuf>,
    #[command(flatten)]
    pub reduce: ReduceArgs,
    #[command(flatten)]
    pub flat: FlatArgs,
    #[command(flatten)]
    pub profile: ProfileArgs,
    /// Print only errors.
    #[arg(short, long)]
    pub quiet: bool,
    /// More detail: the stage-time summary and peak memory (on stderr).
    #[arg(short, long, action = clap::ArgAction::Count)]
    pub verbose: u8,
}

/// Flat-field products of the night, written into `caldir`; paths relative to it.
///
/// Hook for the flat-field stage (dome flats per rotator angle, else a superflat): it is
/// built on another branch (`calib::flat::build_flats` / `write_flat`); when that lands,
/// call it here and return the written file names so that `calibration.json` lists them.
/// The night's flats (dome flats per rotator angle and filter, else superflats from the
/// science frames), written into `caldir` as FITS with UNCERT (variance) and MASK extensions (they
/// open in DS9; `--flat FILE` takes one back). Returns the file names written.
fn build_flat_products(flats: &night::NightFlats, caldir: &Path) -> anyhow::Result<Vec<String>> {
    use sofipol_calib::flat::{flat_file_name, write_flat};
    let mut names = Vec::new();
    if let Some(set) = &flats.set {
        std::fs::create_dir_all(caldir).with_context(|| format!("creating {}", caldir.display()))?;
        for f in &set.flats {
            let name = flat_file_name(f);
            write_flat(&caldir.join(&name), f).with_context(|| format!("writing {}", caldir.join(&name).display()))?;
            names.push(name);
        }
    }
    Ok(names)
}

/// Run: the night's flats and standards, reduced as `sofipol night` does, give the
/// calibration; both are written into CALDIR.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let profile = args.profile.load_rotating("calib")?;
    let params = args.reduce.params_with(&args.flat)?;
    if args.reduce.dump_params {
        print!("{}", super::setup::dump_params(&params)?);
        return Ok(ExitCode::SUCCESS);
    }
    for d in &args.dirs {
        anyhow::ensure!(d.exists(), "{}: no such file or directory", d.display());
    }
    // The calibration is measured from this night's standards whatever the settings say.
    // The standards table is read (and refused) before CALDIR is made.
    let mut cal_params = params.calibration.clone();
    cal_params.no_calibration = false;
    cal_params.calib_dir = None;
    if let Some(f) = &args.standards {
        cal_params.standards = Some(f.clone());
    }
    let calibration = CalibSetup::new(cal_params).map_err(anyhow::Error::msg)?;
    // CALDIR is checked before the reduction: it must accept files, and calibration.json
    // must not replace an input.
    let mut inputs = args.reduce.input_files();
    inputs.extend(args.profile.profile.clone());
    inputs.extend(args.standards.clone());
    let inputs: Vec<&Path> = inputs.iter().map(PathBuf::as_path).collect();
    super::common::check_outputs_in_dir(&args.output, &[CALIBRATION_FILE], &inputs, "-o")?;
    super::setup::check_input_frames(&params)?;
    let setup = NightSetup {
        profile,
        params,
        calibration,
    };
    let mut plan = setup.plan(&args.dirs, None);
    super::common::check_scan_complete(&plan)?;
    // Only the standards: the science sequences are reduced by `sofipol night`.
    plan.sequences.clear();
    if !args.quiet {
        eprintln!(
            "sofipol calib: {} files, {} standard sequence(s)",
            plan.n_files,
            plan.standards.len()
        );
    }
    let t0 = std::time::Instant::now();
    let out = night::run_night(&plan, &setup, &RunOptions::default());
    let standards = &out.catalog.standards;
    let mut cal = out.calibration.clone().ok_or_else(|| {
        anyhow::anyhow!(
            "{}: no usable standard (DPR TYPE 'STD' sequences matched to the standards table): {}",
            args.dirs
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            standards_found(standards, &setup.calibration.table)
        )
    })?;
    // Written only once the calibration exists: a failed run writes nothing.
    cal.flats = build_flat_products(&out.flats, &args.output)?;
    cal.provenance = Provenance {
        inputs: Some(args.dirs.iter().map(|d| d.display().to_string()).collect()),
        standards_table: Some(serde_json::json!(setup.calibration.table.sources)),
        standard_sequences: Some(standards.iter().map(|s| s.sequence.clone()).collect()),
        profile_angles: Some(serde_json::json!({
            "zero_point_deg": setup.profile.angles.zero_point_deg,
            "parity": setup.profile.angles.parity
        })),
        ..Provenance::now()
    };
    let path = cal
        .write(&args.output)
        .with_context(|| format!("writing {}", args.output.join(CALIBRATION_FILE).display()))?;
    if !args.quiet {
        print_calibration(&cal, &setup.profile);
        println!("-> {}", path.display());
    }
    if args.verbose > 0 {
        super::night::print_verbose(&out, t0.elapsed().as_secs_f64());
    }
    Ok(ExitCode::SUCCESS)
}

/// The standard sequences found, in words: "none found" or "2 found: 'HD 1', 'X' (not in
/// the table)".
fn standards_found(
    standards: &[sofipol_pipeline::catalog::StandardResult],
    table: &sofipol_pipeline::standards::StandardsTable,
) -> String {
    if standards.is_empty() {
        return "none found (no frame with DPR TYPE 'STD')".into();
    }
    let names: Vec<String> = standards
        .iter()
        .map(|s| {
            format!(
                "'{}'{}",
                sofipol_calib::text::printable(&s.object),
                if table.knows(&s.object) {
                    ""
                } else {
                    " (not in the table)"
                }
            )
        })
        .collect();
    format!("{} found: {}", standards.len(), names.join(", "))
}

/// The calibration per filter, one line each, on stdout: every number with its name and
/// unit, the standards by name.
fn print_calibration(cal: &Calibration, profile: &Profile) {
    for f in &cal.filters {
        println!("{}", calibration_line(f, profile));
    }
}

/// `n standard(s): a, b` (sequence ids, printable).
fn from_standards(kind: &str, seqs: &[String]) -> String {
    let names: Vec<String> = seqs
        .iter()
        .map(|s| sofipol_calib::text::printable(s).into_owned())
        .collect();
    let plural = if seqs.len() == 1 { "" } else { "s" };
    format!("from {} {kind} standard{plural}: {}", seqs.len(), names.join(", "))
}

/// The standards c comes from: every standard of the joint fit, the polarized ones among
/// them (those the angles come from) counted apart.
fn offset_from(f: &sofipol_pipeline::calibration::FilterCalibration) -> String {
    let n = f.offset_standards.len();
    let polarized = f
        .offset_standards
        .iter()
        .filter(|s| f.angle_standards.contains(s))
        .count();
    let kind = match (n - polarized, polarized) {
        (_, 0) => "unpolarized".to_string(),
        (0, _) => "polarized".to_string(),
        (u, p) => format!("({u} unpolarized, {p} polarized)"),
    };
    let (head, tail) = if kind.starts_with('(') {
        (String::new(), format!(" {kind}"))
    } else {
        (format!(" {kind}"), String::new())
    };
    let names: Vec<String> = f
        .offset_standards
        .iter()
        .map(|s| sofipol_calib::text::printable(s).into_owned())
        .collect();
    let plural = if n == 1 { "" } else { "s" };
    format!("from {n}{head} standard{plural}{tail}: {}", names.join(", "))
}

/// One filter's calibration in words.
fn calibration_line(f: &sofipol_pipeline::calibration::FilterCalibration, profile: &Profile) -> String {
    let offset = f
        .offset
        .map(|o| {
            format!(
                "instrumental offset c = {:.5} +- {:.5} ({:.3} +- {:.3} % in F; {})",
                o.c,
                o.sigma_c,
                100.0 * o.c,
                100.0 * o.sigma_c,
                offset_from(f)
            )
        })
        .unwrap_or_else(|| "instrumental offset c not measured (no unpolarized standard)".into());
    let angles = f
        .angles
        .map(|a| {
            format!(
                "angle zero-point theta0 = {:.2} +- {:.2} deg ({})",
                a.theta0_deg,
                a.sigma_theta0_deg,
                from_standards("polarized", &f.angle_standards)
            )
        })
        .unwrap_or_else(|| "angle zero-point not measured (no polarized standard)".into());
    let parity = f
        .angles
        .map(|a| {
            format!(
                "parity {:+} ({})",
                a.parity,
                if a.parity_measured { "measured" } else { "profile" }
            )
        })
        .unwrap_or_else(|| format!("parity {:+} (profile)", profile.angles.parity));
    let telescope = f
        .telescope
        .as_ref()
        .map(|t| {
            format!(
                "telescope polarization p_tel = {:.3} +- {:.3} %, psi_tel = {:.1} +- {:.1} deg",
                100.0 * t.p_tel,
                100.0 * t.sigma_p_tel,
                t.psi_tel_deg,
                t.sigma_psi_tel_deg
            )
        })
        .unwrap_or_else(|| match &f.telescope_uncorrected {
            Some(why) => format!(
                "telescope polarization not measured ({})",
                sofipol_calib::text::printable(why)
            ),
            None => "telescope polarization not measured".into(),
        });
    format!(
        "{}: {offset}; {angles}; {parity}; {telescope}",
        sofipol_calib::text::printable(&f.filter)
    )
}
