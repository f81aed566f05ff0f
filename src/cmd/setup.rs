//! The settings of a reduction, shared by `night`, `target` and `calib`: raw flags and the
//! settings file -> one validated [`NightSetup`]. Every key of the settings file can be
//! given on the command line (`--param SECTION.KEY=VALUE`), the common ones also as flags;
//! flags override `--param`, which overrides the file; the ranges are checked once
//! ([`TargetParams::validate`]). `--dump-params` prints the settings in force.
use sofipol_calib::profile::toml_value;
use std::path::PathBuf;

use anyhow::Context;
use sofipol_pipeline::calibration::{CalibSetup, CalibrationParams};
use sofipol_pipeline::night::NightSetup;
use sofipol_pipeline::photometry::Method;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::stokes::calibration::StokesMethod;
use sofipol_pipeline::stokes::inversion::Debias;

use super::common::ProfileArgs;

/// What sets up a reduction, shared by `target` and `night`: the reduction settings, the
/// calibration options and the instrument profile (in this order in `--help`).
#[derive(clap::Args, Debug)]
pub struct SetupArgs {
    #[command(flatten)]
    pub reduce: ReduceArgs,
    #[command(flatten)]
    pub flat: FlatArgs,
    #[command(flatten)]
    pub calib: CalibArgs,
    #[command(flatten)]
    pub profile: ProfileArgs,
}

impl SetupArgs {
    /// The validated profile, reduction parameters and calibration setup (the calibration
    /// flags override the `[calibration]` section of `--params`).
    pub fn load(&self) -> anyhow::Result<NightSetup> {
        let profile = self.profile.load_rotating("target / watch")?;
        let mut params = self.reduce.params_with(&self.flat)?;
        let calibration = self.calib.setup(&params.calibration)?;
        params.calibration = calibration.params.clone();
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
        files.extend(self.calib.standards.clone());
        files.extend(self.flat.flat.iter().cloned());
        files
    }
}

/// Reduction settings shared by `target`, `night` and `calib`.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ReduceArgs {
    /// Reduction parameters (TOML, sections as in docs/configuration.md); `--param` and the
    /// flags override [default: none, the built-in settings].
    #[arg(long, value_name = "FILE")]
    pub params: Option<PathBuf>,
    /// Set one key of the reduction parameters, as in the settings file, e.g.
    /// `--param sky.estimator=median` or `--param measure.cut_snr=4` (repeatable; overrides
    /// --params, the flags below override it).
    #[arg(long = "param", value_name = "SECTION.KEY=VALUE")]
    pub param: Vec<String>,
    /// Print the reduction parameters in force (TOML, as --params reads them) and exit.
    #[arg(long)]
    pub dump_params: bool,
    /// Calibration bad-pixel mask (FITS, nonzero = bad) [default: none, bad pixels are
    /// found from the frames].
    #[arg(long, value_name = "FILE")]
    pub badpix: Option<PathBuf>,
    /// Aperture radius in units of each frame's FWHM (at least 1 px; the catalog's
    /// `aperture_radius_px` gives the radius used) [default: 1.0 FWHM].
    #[arg(long, value_name = "FWHM")]
    pub aperture_fwhm: Option<f64>,
    /// Aperture pixel weighting: exact (overlap area), center, or subpixel:N (N x N samples
    /// per pixel), as `measure.method` [default: exact].
    #[arg(long)]
    pub method: Option<Method>,
    /// Debiasing of P: wk (Wardle & Kronberg 1974) or mas (Plaszczynski et al. 2014), as
    /// `measure.debias` [default: wk].
    #[arg(long)]
    pub debias: Option<Debias>,
    /// Known companion separation (arcsec) and position angle (deg east of north),
    /// "SEP_ARCSEC,PA_DEG", a hint [default: none, the companion is searched for].
    #[arg(long, value_name = "ARCSEC,DEG")]
    pub companion: Option<String>,
    /// Write sky-subtracted FITS (with UNCERT, the variance, and MASK) into this directory [default:
    /// none, not written].
    #[arg(long, value_name = "DIR")]
    pub save_intermediate: Option<PathBuf>,
}

/// The flat-field options of `target`, `night` and `calib` (apart from [`ReduceArgs`]:
/// `bench accuracy` has its own `--flat` mode).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct FlatArgs {
    /// Calibration flat (FITS, e.g. from `sofipol calib`); repeat it for one flat per
    /// rotator angle (each frame takes the flat at its POSANG and filter) [default: built
    /// from the night: its dome flats, else the flats of --calib CALDIR, else a superflat
    /// from its sky].
    #[arg(long, value_name = "FILE", conflicts_with = "no_flat")]
    pub flat: Vec<PathBuf>,
    /// Do not flat-field.
    #[arg(long)]
    pub no_flat: bool,
}

impl ReduceArgs {
    /// Files these options read (outputs must not overwrite them).
    pub fn input_files(&self) -> Vec<PathBuf> {
        self.params.iter().chain(&self.badpix).cloned().collect()
    }

    /// The settings file (when given) with the `--param` keys set over it, read as
    /// parameters (unknown keys and wrong types are refused by name).
    fn file_and_param_keys(&self) -> anyhow::Result<TargetParams> {
        let mut table = match &self.params {
            Some(f) => {
                let text = sofipol_calib::input::read_to_string(f, sofipol_calib::input::MAX_OPTION_FILE_BYTES)
                    .with_context(|| format!("reading {}", f.display()))?;
                if self.param.is_empty() {
                    return toml::from_str(&text).with_context(|| format!("parameters file {}", f.display()));
                }
                text.parse::<toml::Table>()
                    .with_context(|| format!("parameters file {}", f.display()))?
            }
            None => toml::Table::new(),
        };
        for s in &self.param {
            anyhow::ensure!(
                !s.chars().any(char::is_control),
                "--param {}: a value holds a line break or another control character; give one \
                 SECTION.KEY=VALUE per --param",
                sofipol_calib::text::printable(s)
            );
            let (key, value) = s
                .split_once('=')
                .ok_or_else(|| anyhow::anyhow!("--param {s}: expected SECTION.KEY=VALUE, e.g. sky.estimator=median"))?;
            set_key(&mut table, key.trim(), toml_value(value.trim())).with_context(|| format!("--param {s}"))?;
        }
        let what = match &self.params {
            Some(f) => format!("parameters file {} with --param {}", f.display(), self.param.join(" ")),
            None => format!("--param {}", self.param.join(" ")),
        };
        toml::Value::Table(table)
            .try_into::<TargetParams>()
            .with_context(|| what)
    }

    /// Validated parameters (the flat as the settings file says).
    pub fn params(&self) -> anyhow::Result<TargetParams> {
        self.params_with(&FlatArgs::default())
    }

    /// Validated parameters, with the flat-field flags over the settings file.
    pub fn params_with(&self, flat: &FlatArgs) -> anyhow::Result<TargetParams> {
        let mut p = self.file_and_param_keys()?;
        if !flat.flat.is_empty() {
            p.flat = flat.flat.clone();
        }
        if flat.no_flat {
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

/// Check, before any reduction, that the calibration frames the settings name
/// (`--badpix` / `calib_mask`, `--flat` / `flat`) exist and are FITS images: a missing or
/// foreign file is an error naming the option and the file (exit 1), not a failure of
/// every target found after the work.
pub fn check_input_frames(params: &TargetParams) -> anyhow::Result<()> {
    let files = params.calib_mask.iter().map(|f| ("--badpix (calib_mask)", f));
    for (what, f) in files.chain(params.flat.iter().map(|f| ("--flat (flat)", f))) {
        sofipol_calib::fits::read_header(f).with_context(|| format!("{what} {}", f.display()))?;
    }
    Ok(())
}

/// Calibration options shared by `night` and `target`.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct CalibArgs {
    /// Use the calibration products of another night (a directory written by `sofipol
    /// calib`, or its calibration.json) [default: none, this night's standards calibrate].
    #[arg(long, value_name = "CALDIR")]
    pub calib: Option<PathBuf>,
    /// Standards table (TOML) adding to or overriding the built-in one by name and filter
    /// [default: none, the built-in table].
    #[arg(long, value_name = "FILE")]
    pub standards: Option<PathBuf>,
    /// How q, u are solved: auto, least_squares, free_offset, difference, ratio
    /// (docs/configuration.md) [default: auto].
    #[arg(long, value_name = "METHOD")]
    pub stokes_method: Option<StokesMethod>,
    /// Use no calibration at all (2-orientation components are flagged `uncalibrated`).
    #[arg(long)]
    pub no_calibration: bool,
    /// Neither fit nor remove the telescope's own polarization (components are flagged
    /// `telescope_polarization_uncorrected`).
    #[arg(long)]
    pub no_telescope_correction: bool,
    /// Let components without an instrumental calibration (flagged `uncalibrated`) pass the
    /// P/sigma cut, flagged; without it they never do and the night exits 2.
    #[arg(long)]
    pub allow_uncalibrated: bool,
}

impl CalibArgs {
    /// Validate; the flags override `base` (the `[calibration]` section of the settings).
    pub fn setup(&self, base: &CalibrationParams) -> anyhow::Result<CalibSetup> {
        let mut params = base.clone();
        params.no_calibration |= self.no_calibration;
        params.no_telescope_correction |= self.no_telescope_correction;
        params.allow_uncalibrated |= self.allow_uncalibrated;
        if let Some(m) = self.stokes_method {
            params.stokes_method = m;
        }
        if let Some(f) = &self.standards {
            params.standards = Some(f.clone());
        }
        if let Some(d) = &self.calib {
            params.calib_dir = Some(d.clone());
        }
        anyhow::ensure!(
            !(params.no_calibration && params.calib_dir.is_some()),
            "--calib and --no-calibration exclude each other (calibration.calib_dir and calibration.no_calibration)"
        );
        CalibSetup::new(params).map_err(anyhow::Error::msg)
    }
}

/// Set `a.b.c = value` in a TOML table, making the sections on the way.
fn set_key(table: &mut toml::Table, key: &str, value: toml::Value) -> anyhow::Result<()> {
    let parts: Vec<&str> = key.split('.').map(str::trim).collect();
    anyhow::ensure!(
        parts.iter().all(|p| !p.is_empty()),
        "'{key}' is not a key (SECTION.KEY)"
    );
    let (last, sections) = parts.split_last().expect("split yields one part");
    let mut t = table;
    for s in sections {
        let entry = t
            .entry(s.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        t = entry
            .as_table_mut()
            .ok_or_else(|| anyhow::anyhow!("'{s}' in '{key}' is a value, not a section"))?;
    }
    t.insert(last.to_string(), value);
    Ok(())
}

/// The reduction parameters in force as a settings file (`--dump-params`): what `--params`
/// reads back to the same settings.
pub fn dump_params(params: &TargetParams) -> anyhow::Result<String> {
    toml::to_string(params).context("writing the parameters as TOML")
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
        #[command(flatten)]
        flat: FlatArgs,
    }

    fn cli(args: &[&str]) -> Result<TargetParams, String> {
        let a = Cli::try_parse_from(std::iter::once("t").chain(args.iter().copied())).map_err(|e| e.to_string())?;
        a.reduce.params_with(&a.flat).map_err(|e| format!("{e:#}"))
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

    #[test]
    fn every_key_of_the_settings_file_is_a_param_flag_and_flags_win() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("p.toml");
        std::fs::write(
            &f,
            "[measure]\ncut_snr = 5.0\naperture_fwhm = 1.2\n[sky]\nestimator = \"median\"\n",
        )
        .unwrap();
        let fs = f.to_str().unwrap();
        // --param over the file, key by key; the other keys of the file stay.
        let p = cli(&[
            "--params",
            fs,
            "--param",
            "sky.estimator=clipped_mean",
            "--param",
            "measure.cut_snr=4",
        ])
        .unwrap();
        assert_eq!(p.measure.cut_snr, 4.0);
        assert_eq!(p.measure.aperture_fwhm, 1.2);
        assert!(toml::to_string(&p.sky)
            .unwrap()
            .contains("estimator = \"clipped_mean\""));
        // A dedicated flag over --param.
        let p = cli(&["--param", "measure.aperture_fwhm=2.0", "--aperture-fwhm", "1.5"]).unwrap();
        assert_eq!(p.measure.aperture_fwhm, 1.5);
        // Nested tables and booleans.
        let p = cli(&[
            "--param",
            "sky.cosmic_rays.enabled=false",
            "--param",
            "full_frame_sky=true",
        ])
        .unwrap();
        assert!(p.sky.cosmic().is_none() && p.full_frame_sky);
        // Wrong key, wrong type, out of range, no '=': refused by name.
        for (args, want) in [
            (&["--param", "sky.estimatr=median"][..], "estimatr"),
            (&["--param", "measure.cut_snr=high"][..], "cut_snr"),
            (&["--param", "measure.cut_snr=-1"][..], "measure.cut_snr"),
            (&["--param", "measure.cut_snr"][..], "SECTION.KEY=VALUE"),
            (&["--param", "measure.cut_snr.x=1"][..], "cut_snr"),
        ] {
            let e = cli(args).unwrap_err();
            assert!(e.contains(want), "{args:?}: {e}");
        }
    }

    #[test]
    fn dumped_parameters_read_back_to_the_same_settings() {
        let dir = tempfile::tempdir().unwrap();
        let p = cli(&[
            "--param",
            "sky.estimator=clipped_mean",
            "--param",
            "measure.psf_model={ kind = \"moffat\", beta = 3.0 }",
            "--method",
            "subpixel:5",
            "--debias",
            "mas",
            "--companion",
            "1.5,30",
            "--no-flat",
        ])
        .unwrap();
        let text = dump_params(&p).unwrap();
        let f = dir.path().join("dumped.toml");
        std::fs::write(&f, &text).unwrap();
        let back = cli(&["--params", f.to_str().unwrap()]).unwrap();
        assert_eq!(dump_params(&back).unwrap(), text);
        assert!(
            text.contains("estimator = \"clipped_mean\"") && text.contains("no_flat = true"),
            "{text}"
        );
        assert_eq!(back.measure.companion_hint, Some((1.5, 30.0)));
    }

    #[test]
    fn calibration_files_can_be_named_in_the_settings_file_or_by_flag() {
        let dir = tempfile::tempdir().unwrap();
        let table = dir.path().join("stds.toml");
        std::fs::write(&table, "").unwrap();
        let f = dir.path().join("p.toml");
        std::fs::write(
            &f,
            format!("[calibration]\nstandards = {:?}\n", table.to_str().unwrap()),
        )
        .unwrap();
        let load = |args: &[&str]| {
            SetupCli::try_parse_from(std::iter::once("t").chain(args.iter().copied()))
                .unwrap()
                .setup
                .load()
                .map_err(|e| format!("{e:#}"))
        };
        let s = load(&["--params", f.to_str().unwrap()]).unwrap();
        assert!(
            s.calibration.table.sources.iter().any(|x| x.contains("stds.toml")),
            "{:?}",
            s.calibration.table.sources
        );
        assert_eq!(s.params.calibration.standards.as_deref(), Some(table.as_path()));
        // The flag names another table: that one is read (and a missing one is refused by name).
        let e = load(&["--params", f.to_str().unwrap(), "--standards", "/no/such/table.toml"]).unwrap_err();
        assert!(e.contains("/no/such/table.toml"), "{e}");
        // --calib with --no-calibration, from the file or the flags, is refused.
        std::fs::write(&f, "[calibration]\nno_calibration = true\ncalib_dir = \"/x\"\n").unwrap();
        let e = load(&["--params", f.to_str().unwrap()]).unwrap_err();
        assert!(e.contains("exclude each other"), "{e}");
    }
}
