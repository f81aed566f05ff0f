//! `sofipol target`: reduce one target sequence to a JSON catalog.
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use sofipol_pipeline::catalog::Status;
use sofipol_pipeline::night::{self, NightSetup, RunOptions};
use sofipol_pipeline::photometry::Method;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::stokes::inversion::Debias;

use super::calib::CalibArgs;
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
    pub setup: SetupArgs,
    /// Print nothing but errors.
    #[arg(short, long)]
    pub quiet: bool,
}

/// What sets up a reduction, shared by `target` and `night`: the reduction settings, the
/// calibration options and the instrument profile (in this order in `--help`).
#[derive(clap::Args, Debug)]
pub struct SetupArgs {
    #[command(flatten)]
    pub reduce: ReduceArgs,
    #[command(flatten)]
    pub calib: CalibArgs,
    #[command(flatten)]
    pub profile: ProfileArgs,
}

impl SetupArgs {
    /// The validated profile, reduction parameters and calibration setup (the calibration
    /// flags override the `[calibration]` section of `--params`).
    pub fn load(&self) -> anyhow::Result<NightSetup> {
        let profile = self.profile.load()?;
        let params = self.reduce.params()?;
        let calibration = self.calib.setup(&params.calibration)?;
        Ok(NightSetup {
            profile,
            params,
            calibration,
        })
    }

    /// Files these options read (outputs must not overwrite them).
    pub fn input_files(&self) -> Vec<PathBuf> {
        let mut files = self.reduce.input_files();
        files.extend(self.profile.profile.clone());
        files
    }
}

/// Reduction settings shared by `target`, `night` and `calib`.
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
    /// Aperture method: exact, center, or subpixel:N (as `measure.method` in TOML).
    #[arg(long)]
    pub method: Option<Method>,
    /// Debiasing of P: wk (Wardle & Kronberg) or mas (Plaszczynski et al. 2014), as `measure.debias`.
    #[arg(long)]
    pub debias: Option<Debias>,
    /// Known companion separation and PA, "SEP_ARCSEC,PA_DEG" (optional hint).
    #[arg(long, value_name = "SEP,PA")]
    pub companion: Option<String>,
    /// Write sky-subtracted FITS (with VARIANCE and MASK) into this directory.
    #[arg(long, value_name = "DIR")]
    pub save_intermediate: Option<PathBuf>,
    /// Calibration flat (FITS, e.g. from `sofipol calib`) instead of building one from
    /// the night (dome flats, else a superflat from the night's sky).
    #[arg(long, value_name = "FILE", conflicts_with = "no_flat")]
    pub flat: Option<PathBuf>,
    /// Do not flat-field.
    #[arg(long)]
    pub no_flat: bool,
}

impl ReduceArgs {
    /// Files these options read (outputs must not overwrite them).
    pub fn input_files(&self) -> Vec<PathBuf> {
        self.params.iter().chain(&self.badpix).cloned().collect()
    }

    /// Validated parameters.
    pub fn params(&self) -> anyhow::Result<TargetParams> {
        let mut p: TargetParams = match &self.params {
            Some(f) => {
                let text = std::fs::read_to_string(f).with_context(|| format!("reading {}", f.display()))?;
                toml::from_str(&text).with_context(|| format!("parameters file {}", f.display()))?
            }
            None => TargetParams::default(),
        };
        if let Some(f) = &self.flat {
            p.flat = Some(f.clone());
        }
        if self.no_flat {
            p.no_flat = true;
        }
        if let Some(a) = self.aperture_fwhm {
            p.measure.aperture_fwhm = a;
        }
        if let Some(m) = self.method {
            p.measure.method = m;
        }
        if let Some(d) = self.debias {
            p.measure.debias = d;
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

/// Run: the sequence is reduced as one target of a night ([`night::run_night`]), with the
/// flats built from all the inputs and the standards among them calibrating it.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let setup = args.setup.load()?;
    for i in &args.inputs {
        anyhow::ensure!(i.exists(), "{}: no such file or directory", i.display());
    }
    let mut plan = setup.plan(&args.inputs, None);
    anyhow::ensure!(
        plan.n_files > 0,
        "no FITS files (.fits, .fit, .fits.gz, .fz) in {:?}",
        args.inputs
    );
    if let Some(obj) = &args.object {
        plan.sequences.retain(|q| &q.object == obj);
        anyhow::ensure!(
            !plan.sequences.is_empty(),
            "no polarimetric sequence of object '{obj}' in the inputs"
        );
    } else if plan.sequences.len() > 1 {
        let names: Vec<&str> = plan.sequences.iter().map(|q| q.object.as_str()).collect();
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
    let opts = RunOptions {
        inputs: args.inputs.clone(),
        ..Default::default()
    };
    let out = night::run_night(&plan, &setup, &opts);
    let cat = &out.catalog;
    if !args.quiet {
        for l in &out.summary.lines {
            eprintln!("sofipol target: {l}");
        }
    }
    sofipol_pipeline::io::write_json_atomic(&args.output, cat)
        .with_context(|| format!("writing {}", args.output.display()))?;
    if !args.quiet {
        print!("{}", super::report::summary(cat));
        println!("catalog: {}", args.output.display());
    }
    let failed = cat.targets.iter().any(|t| t.status != Status::Ok);
    Ok(if failed || !cat.failures.is_empty() {
        ExitCode::from(2)
    } else {
        ExitCode::SUCCESS
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;
    use sofipol_pipeline::stokes::calibration::{StokesMethod, STOKES_METHOD_SPELLINGS};

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        reduce: ReduceArgs,
    }

    fn cli(args: &[&str]) -> Result<TargetParams, String> {
        let a = Cli::try_parse_from(std::iter::once("t").chain(args.iter().copied())).map_err(|e| e.to_string())?;
        a.reduce.params().map_err(|e| format!("{e:#}"))
    }

    fn toml_file(body: &str) -> Result<TargetParams, String> {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("p.toml");
        std::fs::write(&f, body).unwrap();
        cli(&["--params", f.to_str().unwrap()])
    }

    #[test]
    fn method_and_debias_have_one_spelling_in_toml_and_on_the_command_line() {
        for m in [Method::Exact, Method::Center, Method::Subpixel(1), Method::Subpixel(5)] {
            for d in [Debias::WardleKronberg, Debias::Mas] {
                let (ms, ds) = (m.to_string(), d.to_string());
                let from_cli = cli(&["--method", &ms, "--debias", &ds]).unwrap();
                assert_eq!((from_cli.measure.method, from_cli.measure.debias), (m, d));
                // What the parameters serialize to (provenance) is what the flags take.
                let text = toml::to_string(&from_cli).unwrap();
                assert!(text.contains(&format!("method = \"{ms}\"")), "{text}");
                assert!(text.contains(&format!("debias = \"{ds}\"")), "{text}");
                let from_toml = toml_file(&text).unwrap();
                assert_eq!((from_toml.measure.method, from_toml.measure.debias), (m, d));
            }
        }
        // The old TOML spellings are still read.
        let old = toml_file("[measure]\nmethod = { Subpixel = 4 }\ndebias = \"wardle_kronberg\"\n").unwrap();
        assert_eq!(
            (old.measure.method, old.measure.debias),
            (Method::Subpixel(4), Debias::WardleKronberg)
        );
        assert_eq!(
            toml_file("[measure]\nmethod = \"Center\"\n").unwrap().measure.method,
            Method::Center
        );
    }

    #[derive(Parser)]
    struct SetupCli {
        #[command(flatten)]
        setup: SetupArgs,
    }

    /// The Stokes method that `--params` and the flags resolve to.
    fn stokes_method(args: &[&str]) -> Result<StokesMethod, String> {
        let a =
            SetupCli::try_parse_from(std::iter::once("t").chain(args.iter().copied())).map_err(|e| e.to_string())?;
        let setup = a.setup.load().map_err(|e| format!("{e:#}"))?;
        Ok(setup.calibration.params.stokes_method)
    }

    #[test]
    fn stokes_method_has_one_spelling_in_toml_json_and_on_the_command_line() {
        use StokesMethod::*;
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("p.toml");
        for m in [Auto, LeastSquares, FreeOffset, Difference, Ratio] {
            let s = m.to_string();
            assert_eq!(s, m.name());
            assert_eq!(stokes_method(&["--stokes-method", &s]).unwrap(), m);
            // What the settings serialize to (TOML, the catalog's JSON provenance) is what
            // the flag takes, and reads back.
            let mut p = TargetParams::default();
            p.calibration.stokes_method = m;
            let text = toml::to_string(&p).unwrap();
            assert!(text.contains(&format!("stokes_method = \"{s}\"")), "{text}");
            assert_eq!(serde_json::to_value(m).unwrap(), serde_json::json!(s));
            std::fs::write(&f, &text).unwrap();
            assert_eq!(stokes_method(&["--params", f.to_str().unwrap()]).unwrap(), m);
            // The flag overrides the file.
            let other = if m == Ratio { Difference } else { Ratio };
            let both = stokes_method(&["--params", f.to_str().unwrap(), "--stokes-method", other.name()]);
            assert_eq!(both.unwrap(), other);
        }
        let e = stokes_method(&["--stokes-method", "least-squares"]).unwrap_err();
        assert!(
            e.contains("--stokes-method") && e.contains("least-squares") && e.contains(STOKES_METHOD_SPELLINGS),
            "{e}"
        );
        std::fs::write(&f, "[calibration]\nstokes_method = \"Ratio\"\n").unwrap();
        let e = stokes_method(&["--params", f.to_str().unwrap()]).unwrap_err();
        assert!(
            e.contains("calibration.stokes_method") && e.contains("Ratio") && e.contains(STOKES_METHOD_SPELLINGS),
            "{e}"
        );
    }

    #[test]
    fn a_bad_spelling_names_the_key_the_value_and_the_allowed_values() {
        for (args, key, value, allowed) in [
            (
                &["--method", "subpixel:x"][..],
                "method",
                "subpixel:x",
                "exact, center or subpixel:N",
            ),
            (
                &["--method", "subpixel:0"][..],
                "method",
                "subpixel:0",
                "exact, center or subpixel:N",
            ),
            (
                &["--debias", "wardle"][..],
                "debias",
                "wardle",
                "wk (Wardle & Kronberg 1974) or mas",
            ),
        ] {
            let e = cli(args).unwrap_err();
            assert!(
                e.contains(&format!("--{key}")) && e.contains(value) && e.contains(allowed),
                "{e}"
            );
            let e = toml_file(&format!("[measure]\n{key} = \"{value}\"\n")).unwrap_err();
            assert!(
                e.contains(&format!("measure.{key}")) && e.contains(value) && e.contains(allowed),
                "{e}"
            );
        }
    }
}
