//! `sofipol calib NIGHT -o CALDIR`: the calibration products of a night
//! (`calibration.json`: instrumental offset c, angle zero-point, parity, their errors per
//! filter, the standards and frames used, provenance), and the shared calibration
//! options of `night` and `target` (`--calib`, `--standards`, `--stokes-method`,
//! `--no-calibration`).
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use sofipol_calib::Profile;
use sofipol_pipeline::calibration::{
    self, Calibration, CalibrationParams, CalibrationSource, CalibrationSummary, CALIBRATION_FILE,
};
use sofipol_pipeline::catalog::{Catalog, Target};
use sofipol_pipeline::night;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sequence::Sequence;
use sofipol_pipeline::standards::StandardsTable;
use sofipol_pipeline::stokes::calibration::StokesMethod;

use super::common::ProfileArgs;
use super::target::ReduceArgs;

/// Calibration options shared by `night` and `target`.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct CalibArgs {
    /// Use the calibration products of another night (a directory written by `sofipol
    /// calib`, or its calibration.json) instead of this night's standards.
    #[arg(long, value_name = "CALDIR")]
    pub calib: Option<PathBuf>,
    /// Standards table (TOML) adding to or overriding the built-in one by name and filter.
    #[arg(long, value_name = "FILE")]
    pub standards: Option<PathBuf>,
    /// How q, u are solved: auto, least_squares, free_offset, difference, ratio.
    #[arg(long, value_name = "METHOD")]
    pub stokes_method: Option<StokesMethod>,
    /// Use no calibration at all (2-orientation components are flagged `uncalibrated`).
    #[arg(long)]
    pub no_calibration: bool,
}

/// What the calibration options resolve to.
pub struct CalibSetup {
    /// Settings.
    pub params: CalibrationParams,
    /// Standards table.
    pub table: StandardsTable,
    /// A calibration read with --calib.
    pub external: Option<(PathBuf, Calibration)>,
}

impl CalibSetup {
    /// The catalog's `provenance.calibration`: settings, standards tables, `--calib` directory.
    pub fn provenance(&self) -> serde_json::Value {
        serde_json::json!({"params": self.params, "standards_table": self.table.sources,
            "calib_dir": self.external.as_ref().map(|e| e.0.display().to_string())})
    }
}

impl CalibArgs {
    /// Validate; the flags override `base` (the `[calibration]` section of --params).
    pub fn setup(&self, base: &CalibrationParams) -> anyhow::Result<CalibSetup> {
        let mut params = base.clone();
        params.no_calibration |= self.no_calibration;
        if let Some(m) = self.stokes_method {
            params.stokes_method = m;
        }
        let table = match &self.standards {
            Some(f) => StandardsTable::with_file(f).map_err(anyhow::Error::msg)?,
            None => StandardsTable::builtin(),
        };
        let external = match &self.calib {
            Some(p) => {
                anyhow::ensure!(
                    !params.no_calibration,
                    "--calib and --no-calibration exclude each other"
                );
                Some((p.clone(), Calibration::read(p).map_err(anyhow::Error::msg)?))
            }
            None => None,
        };
        Ok(CalibSetup {
            params,
            table,
            external,
        })
    }
}

/// Reduce standard sequences as single stars (in the current rayon pool).
pub fn reduce_standards(
    stds: &[Sequence],
    profile: &Profile,
    params: &TargetParams,
    night_mask: Option<&ndarray::Array2<u8>>,
    flats: Option<&sofipol_calib::flat::FlatSet>,
) -> (Vec<Target>, Catalog) {
    let plan = night::NightPlan {
        sequences: stds.to_vec(),
        ..Default::default()
    };
    let sp = calibration::standard_params(params);
    let res = night::reduce_night(&plan, profile, &sp, night_mask, flats, false, &|_| {}, &|_| {});
    let targets = res.catalog.targets.clone();
    (targets, res.catalog)
}

/// Calibrate a reduced catalog of targets: reduce the standards (unless a calibration was
/// given or none is wanted), measure, re-solve the targets. Returns the summary lines.
pub fn calibrate(
    cat: &mut Catalog,
    stds: &[Sequence],
    profile: &Profile,
    params: &TargetParams,
    night_mask: Option<&ndarray::Array2<u8>>,
    flats: Option<&sofipol_calib::flat::FlatSet>,
    setup: &CalibSetup,
) -> CalibrationSummary {
    let (std_targets, std_cat) = if stds.is_empty() {
        (vec![], Catalog::default())
    } else {
        reduce_standards(stds, profile, params, night_mask, flats)
    };
    cat.failures.extend(std_cat.failures);
    cat.failures.sort_by(|a, b| a.file.cmp(&b.file));
    let source = if setup.params.no_calibration {
        CalibrationSource::Disabled
    } else if let Some((p, c)) = &setup.external {
        CalibrationSource::File(p.clone(), Box::new(c.clone()))
    } else {
        CalibrationSource::Night
    };
    let (_, summary) = calibration::calibrate_catalog(
        cat,
        std_targets,
        &setup.table,
        profile,
        source,
        &setup.params,
        params.measure.debias,
        params.measure.cut_snr,
    );
    summary
}

/// Arguments of `sofipol calib`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Night directories (searched recursively).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Calibration directory to write (calibration.json, flats).
    #[arg(short, long, value_name = "CALDIR")]
    pub output: PathBuf,
    /// Standards table (TOML) adding to or overriding the built-in one.
    #[arg(long, value_name = "FILE")]
    pub standards: Option<PathBuf>,
    #[command(flatten)]
    pub reduce: ReduceArgs,
    #[command(flatten)]
    pub profile: ProfileArgs,
    /// Print only errors.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Flat-field products of the night, written into `caldir`; paths relative to it.
///
/// Hook for the flat-field stage (dome flats per rotator angle, else a superflat): it is
/// built on another branch (`calib::flat::build_flats` / `write_flat`); when that lands,
/// call it here and return the written file names so that `calibration.json` lists them.
/// The night's flats (dome flats per rotator angle and filter, else superflats from the
/// science frames), written into `caldir` as FITS with VARIANCE and MASK extensions (they
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

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let profile = args.profile.load()?;
    let params = args.reduce.params()?;
    let table = match &args.standards {
        Some(f) => StandardsTable::with_file(f).map_err(anyhow::Error::msg)?,
        None => StandardsTable::builtin(),
    };
    for d in &args.dirs {
        anyhow::ensure!(d.exists(), "{}: no such file or directory", d.display());
    }
    let plan = night::plan(&args.dirs, &profile, None).context("scanning the night")?;
    let (_, stds) = calibration::split_standards(plan.sequences.clone(), &profile);
    if !args.quiet {
        eprintln!(
            "sofipol calib: {} files, {} standard sequence(s)",
            plan.n_files,
            stds.len()
        );
    }
    let night_flats = night::night_flats(&plan.dome_flats, &plan.superflat_frames, &profile, &params);
    let (std_targets, _) = reduce_standards(&stds, &profile, &params, None, night_flats.set.as_ref());
    let flats = build_flat_products(&night_flats, &args.output)?;
    let mut cal = calibration::measure(&std_targets, &table, &profile).ok_or_else(|| {
        anyhow::anyhow!(
            "{}: no usable standard (DPR TYPE 'STD' sequences matched to the standards table: {} found, {})",
            args.dirs
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            stds.len(),
            std_targets
                .iter()
                .map(|t| format!(
                    "'{}'{}",
                    t.object,
                    if table.knows(&t.object) {
                        ""
                    } else {
                        " not in the table"
                    }
                ))
                .collect::<Vec<_>>()
                .join(", ")
        )
    })?;
    cal.flats = flats;
    cal.provenance = serde_json::json!({
        "software": format!("sofipol {}", env!("CARGO_PKG_VERSION")),
        "command_line": std::env::args().collect::<Vec<_>>(),
        "inputs": args.dirs,
        "standards_table": table.sources,
        "standard_sequences": std_targets.iter().map(|t| t.sequence.clone()).collect::<Vec<_>>(),
        "profile_angles": {"zero_point_deg": profile.angles.zero_point_deg, "parity": profile.angles.parity},
    });
    let path = cal
        .write(&args.output)
        .with_context(|| format!("writing {}", args.output.join(CALIBRATION_FILE).display()))?;
    if !args.quiet {
        for f in &cal.filters {
            println!(
                "{}: c = {} ; theta0 = {} ; parity {}",
                f.filter,
                f.offset
                    .map(|o| format!("{:.5} +- {:.5} from {:?}", o.c, o.sigma_c, f.offset_standards))
                    .unwrap_or_else(|| "not measured (no unpolarized standard)".into()),
                f.angles
                    .map(|a| format!(
                        "{:.2} +- {:.2} deg from {:?}",
                        a.theta0_deg, a.sigma_theta0_deg, f.angle_standards
                    ))
                    .unwrap_or_else(|| "not measured (no polarized standard)".into()),
                f.angles
                    .map(|a| format!(
                        "{:+} ({})",
                        a.parity,
                        if a.parity_measured { "measured" } else { "profile" }
                    ))
                    .unwrap_or_else(|| format!("{:+} (profile)", profile.angles.parity)),
            );
        }
        println!("-> {}", path.display());
    }
    Ok(ExitCode::SUCCESS)
}
