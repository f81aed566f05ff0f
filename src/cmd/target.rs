//! `sofipol target`: reduce one target sequence to a JSON catalog.
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use sofipol_pipeline::catalog::{Catalog, Status, SCHEMA_VERSION};
use sofipol_pipeline::reduce::run::reduce_sequence;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::{scan, sequence};

use super::common::ProfileArgs;

/// Arguments of `sofipol target`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// FITS files and/or directories holding the sequence.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    /// Target name (OBJECT); needed when the inputs hold several targets.
    #[arg(long)]
    pub object: Option<String>,
    /// Output catalog (JSON, written atomically).
    #[arg(short, long, default_value = "catalog.json")]
    pub output: PathBuf,
    #[command(flatten)]
    pub reduce: ReduceArgs,
    #[command(flatten)]
    pub calib: super::calib::CalibArgs,
    #[command(flatten)]
    pub profile: ProfileArgs,
    /// Print nothing but errors.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Reduction settings shared by `target` and `night`.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ReduceArgs {
    /// Reduction parameters (TOML, sections as in docs/configuration.md); flags override.
    #[arg(long, value_name = "FILE")]
    pub params: Option<PathBuf>,
    /// Calibration bad-pixel mask (FITS, nonzero = bad).
    #[arg(long, value_name = "FILE")]
    pub badpix: Option<PathBuf>,
    /// Aperture radius in units of the FWHM.
    #[arg(long)]
    pub aperture_fwhm: Option<f64>,
    /// Aperture method: exact, center, or subpixel:N.
    #[arg(long)]
    pub method: Option<String>,
    /// Debiasing of P: wk (Wardle & Kronberg) or mas (Plaszczynski et al. 2014).
    #[arg(long)]
    pub debias: Option<String>,
    /// Known companion separation and PA, "SEP_ARCSEC,PA_DEG" (optional hint).
    #[arg(long, value_name = "SEP,PA")]
    pub companion: Option<String>,
    /// Write sky-subtracted FITS (with VARIANCE and MASK) into this directory.
    #[arg(long, value_name = "DIR")]
    pub save_intermediate: Option<PathBuf>,
}

impl ReduceArgs {
    /// Validated parameters.
    pub fn params(&self) -> anyhow::Result<TargetParams> {
        let mut p: TargetParams = match &self.params {
            Some(f) => {
                let text = std::fs::read_to_string(f).with_context(|| format!("reading {}", f.display()))?;
                toml::from_str(&text).with_context(|| format!("parameters file {}", f.display()))?
            }
            None => TargetParams::default(),
        };
        if let Some(a) = self.aperture_fwhm {
            p.measure.aperture_fwhm = a;
        }
        if let Some(m) = &self.method {
            use sofipol_pipeline::photometry::Method;
            p.measure.method = match m.as_str() {
                "exact" => Method::Exact,
                "center" => Method::Center,
                s if s.starts_with("subpixel:") => Method::Subpixel(
                    s[9..]
                        .parse()
                        .with_context(|| format!("--method {s}: N of subpixel:N must be a positive integer"))?,
                ),
                s => anyhow::bail!("--method {s}: expected exact, center or subpixel:N"),
            };
        }
        if let Some(d) = &self.debias {
            use sofipol_pipeline::stokes::inversion::Debias;
            p.measure.debias = match d.as_str() {
                "wk" => Debias::WardleKronberg,
                "mas" => Debias::Mas,
                s => anyhow::bail!("--debias {s}: expected wk or mas"),
            };
        }
        if let Some(c) = &self.companion {
            let v: Vec<f64> = c
                .split(',')
                .map(|x| x.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .with_context(|| format!("--companion {c}: expected SEP_ARCSEC,PA_DEG"))?;
            anyhow::ensure!(
                v.len() == 2 && v[0] > 0.0,
                "--companion {c}: expected SEP_ARCSEC,PA_DEG with SEP > 0"
            );
            p.measure.companion_hint = Some((v[0], v[1]));
        }
        if self.badpix.is_some() {
            p.calib_mask = self.badpix.clone();
        }
        if self.save_intermediate.is_some() {
            p.save_intermediate = self.save_intermediate.clone();
        }
        p.validate()?;
        Ok(p)
    }
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let profile = args.profile.load()?;
    let params = args.reduce.params()?;
    let setup = args.calib.setup(&params.calibration)?;
    let mut files = Vec::new();
    for i in &args.inputs {
        files.extend(scan::find_files(i).with_context(|| format!("listing {}", i.display()))?);
    }
    anyhow::ensure!(
        !files.is_empty(),
        "no FITS files (.fits, .fit, .fits.gz, .fz) in {:?}",
        args.inputs
    );
    let s = scan::classify_all(&files, &profile);
    // Standard stars in the inputs calibrate the target; they are not the target.
    let (mut seqs, stds) =
        sofipol_pipeline::calibration::split_standards(sequence::group(s.science, &profile), &profile);
    if let Some(obj) = &args.object {
        seqs.retain(|q| &q.object == obj);
        anyhow::ensure!(
            !seqs.is_empty(),
            "no polarimetric sequence of object '{obj}' in the inputs"
        );
    } else if seqs.len() > 1 {
        let names: Vec<&str> = seqs.iter().map(|q| q.object.as_str()).collect();
        anyhow::bail!(
            "the inputs hold {} sequences ({}): choose one with --object",
            seqs.len(),
            names.join(", ")
        );
    }
    anyhow::ensure!(
        !seqs.is_empty(),
        "no polarimetric science frames among {} file(s)",
        files.len()
    );
    let mut cat = Catalog {
        schema_version: SCHEMA_VERSION.into(),
        ..Default::default()
    };
    cat.failures.extend(s.unreadable);
    // Non-science files count as failures only when they were named explicitly.
    let explicit: Vec<String> = args
        .inputs
        .iter()
        .filter(|p| p.is_file())
        .map(|p| p.display().to_string())
        .collect();
    cat.failures
        .extend(s.other.into_iter().filter(|f| explicit.contains(&f.file)));
    for q in &seqs {
        let out = reduce_sequence(q, &profile, &params, None, false);
        cat.failures.extend(out.failures);
        cat.targets.push(out.target);
    }
    let cal_summary = super::calib::calibrate(&mut cat, &stds, &profile, &params, None, &setup);
    cat.provenance = super::report::provenance(&profile, &params);
    cat.provenance["calibration"] = serde_json::json!({"params": setup.params, "standards_table": setup.table.sources,
        "calib_dir": setup.external.as_ref().map(|e| e.0.display().to_string())});
    if !args.quiet {
        for l in &cal_summary.lines {
            eprintln!("sofipol target: {l}");
        }
    }
    sofipol_pipeline::io::write_json_atomic(&args.output, &cat)
        .with_context(|| format!("writing {}", args.output.display()))?;
    if !args.quiet {
        print!("{}", super::report::summary(&cat));
        println!("catalog: {}", args.output.display());
    }
    let failed = cat.targets.iter().any(|t| t.status != Status::Ok);
    Ok(if failed || !cat.failures.is_empty() {
        ExitCode::from(2)
    } else {
        ExitCode::SUCCESS
    })
}
