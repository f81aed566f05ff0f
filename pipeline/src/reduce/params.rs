//! Settings of the reduction of a target: what the measurement and the calibration stages
//! read from `[measure]`, `[sky]`, `[bad_pixels]` and the top level of a settings file.
use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use sofipol_calib::badpix::BadPixelOptions;
use sofipol_calib::sky::SkyOptions;

pub use crate::error::SettingError;
use crate::photometry::{Method, PsfModel};
use crate::stokes::calibration::StokesMethod;
use crate::stokes::inversion::Debias;

/// Smallest aperture radius, px: `aperture_fwhm` x the frame's FWHM below this is raised to
/// it (a radius under a pixel would hold less than the centre pixel's area).
pub const MIN_APERTURE_RADIUS_PX: f64 = 1.0;

/// Settings of the measurement (defaults are the documented choices, docs/configuration.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MeasureParams {
    /// Aperture radius in units of the frame's FWHM (at least
    /// [`MIN_APERTURE_RADIUS_PX`]; the radius used, px, is the catalog's `aperture_radius_px`).
    pub aperture_fwhm: f64,
    /// Residual-background annulus (inner, outer) in units of the median FWHM.
    pub annulus_fwhm: (f64, f64),
    /// Aperture pixel-weighting method.
    pub method: Method,
    /// Pairs closer than this many FWHM are measured by PSF fitting instead of apertures.
    pub psf_photometry_below_fwhm: f64,
    /// Search radius for the primary around its nominal position, px.
    pub primary_search_px: f64,
    /// Nominal position of the primary's ordinary image at zero jitter offset (x, y) px;
    /// None: detector centre in x, middle of the o-target strip in y.
    pub nominal_xy_px: Option<(f64, f64)>,
    /// Largest companion separation searched, arcsec.
    pub companion_search_arcsec: f64,
    /// Companion accepted when its stacked flux S/N exceeds this.
    pub min_companion_snr: f64,
    /// ... and the two-star fit of the stack beats the one-star fit with an F statistic
    /// above this (3 and n-7 degrees of freedom; a lone star gives ~1).
    pub min_companion_f: f64,
    /// ... and lies at least this far from the primary, arcsec (the study's closest pair
    /// is 0.5").
    pub min_companion_sep_arcsec: f64,
    /// Dither values further than this many sigma from the others are rejected.
    pub clip_sigma: f64,
    /// P / sigma_P threshold of the cut.
    pub cut_snr: f64,
    /// Debiasing estimator.
    pub debias: Debias,
    /// Known separation (arcsec) and PA (deg) of the companion, when a target list gives it.
    pub companion_hint: Option<(f64, f64)>,
    /// PSF model of the stack and per-frame fits (deblending and PSF-fit fluxes). Default: a
    /// circular Moffat with beta fitted, `{ kind = "moffat" }`, since seeing-limited PSFs have
    /// Moffat wings that a Gaussian misfits; `{ kind = "moffat", beta = 3.0 }` fixes beta,
    /// `{ kind = "gaussian" }` restores the Gaussian fit.
    pub psf_model: PsfModel,
    /// With a Moffat model of free beta: measure beta on the registered stacks and hold it
    /// fixed in the per-frame fits of pairs measured by apertures (3 FWHM and wider); pairs
    /// measured by PSF-fit fluxes fit beta in every frame (`reduce::fluxes::choose_psf`).
    pub beta_from_stack: bool,
    /// Fit the o and e images of each exposure jointly: one PSF shape and one pair
    /// geometry for both beams, a flux per star and beam (`photometry::fit_psf_joint`);
    /// the o-e flux covariance of PSF-fit fluxes enters sigma_F. Off: each beam is fitted
    /// on its own.
    pub joint_beams: bool,
    /// Pairs measured by PSF-fit fluxes (closer than `psf_photometry_below_fwhm`) get an
    /// elliptical Moffat in their per-frame fits: an ellipticity (e1, e2) at any angle, two
    /// more parameters shared by both stars (and both beams). Real PSFs have axis ratios of
    /// 0.9-1 from guiding, wind shake and optics; a circular fit of an elongated pair moves
    /// flux from one star to the other along the elongation. Off: circular.
    pub psf_elliptical: bool,
    /// Detect and measure every other point source of the target's strips (the catalog's
    /// `field_stars`; docs/photometry.md, "Field stars"). Off: no `field_stars` key.
    pub field_stars: bool,
    /// Detection threshold of the field stars: S/N of the 3x3 box sum of the stacked
    /// dithers above the median of a ring about the peak, in each beam.
    pub field_star_snr: f64,
}

impl MeasureParams {
    /// The photometry aperture's radius for a frame of FWHM `fwhm_px`, px: `aperture_fwhm`
    /// x the FWHM, at least [`MIN_APERTURE_RADIUS_PX`]. The one place the FWHM becomes
    /// the aperture.
    pub fn aperture_radius_px(&self, fwhm_px: f64) -> f64 {
        (self.aperture_fwhm * fwhm_px).max(MIN_APERTURE_RADIUS_PX)
    }

    /// The residual-background annulus (inner, outer radius) for a FWHM of `fwhm_px`, px.
    pub fn annulus_px(&self, fwhm_px: f64) -> (f64, f64) {
        (self.annulus_fwhm.0 * fwhm_px, self.annulus_fwhm.1 * fwhm_px)
    }
}

impl Default for MeasureParams {
    fn default() -> Self {
        MeasureParams {
            aperture_fwhm: 1.0,
            annulus_fwhm: (4.0, 6.0),
            method: Method::Exact,
            psf_photometry_below_fwhm: 3.0,
            primary_search_px: 60.0,
            nominal_xy_px: None,
            companion_search_arcsec: 6.0,
            min_companion_snr: 5.0,
            min_companion_f: 50.0,
            min_companion_sep_arcsec: 0.3,
            clip_sigma: 4.0,
            cut_snr: 3.0,
            debias: Debias::WardleKronberg,
            companion_hint: None,
            joint_beams: true,
            psf_elliptical: true,
            psf_model: PsfModel::Moffat { beta: None },
            beta_from_stack: true,
            field_stars: true,
            field_star_snr: 7.0,
        }
    }
}

/// Settings of a target reduction.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TargetParams {
    /// Measurement settings.
    pub measure: MeasureParams,
    /// Sky subtraction (default: multiplicative scaling, cosmic-ray flagging on).
    pub sky: SkyOptions,
    /// Bad-pixel detection.
    pub bad_pixels: BadPixelOptions,
    /// A calibration bad-pixel mask (nonzero = bad), combined with the detected one.
    pub calib_mask: Option<PathBuf>,
    /// Do not detect bad pixels from the data (use only the calibration mask).
    pub no_detect_bad_pixels: bool,
    /// Write sky-subtracted FITS frames (data, UNCERT (variance), MASK) into this directory.
    pub save_intermediate: Option<PathBuf>,
    /// Sky-subtract whole frames. By default only the target strips (o-target and
    /// e-target rows, all the measurement uses) are sky-subtracted, about a third of the
    /// detector; whole frames are always done when intermediates are saved.
    pub full_frame_sky: bool,
    /// Calibration flat files (FITS, as written by `sofipol calib` or any pixel-response
    /// image), used instead of building flats from the night: each frame takes the flat of
    /// its filter at its rotator angle (`POSANG` of the flat's header), else one without an
    /// angle, else the nearest angle. In the settings file a path or a list of paths.
    /// Empty: the flats of `calibration.calib_dir` when it lists some, else built from the
    /// night.
    #[serde(deserialize_with = "one_or_many")]
    pub flat: Vec<PathBuf>,
    /// Do not flat-field (no dome flat, no superflat).
    pub no_flat: bool,
    /// How flats are built (dome flats and superflat).
    pub flat_options: sofipol_calib::flat::FlatOptions,
    /// Instrumental calibration and the Stokes method (`[calibration]`, docs/calibration.md).
    pub calibration: CalibrationParams,
}

impl Default for TargetParams {
    fn default() -> Self {
        TargetParams {
            measure: MeasureParams::default(),
            sky: SkyOptions::recommended(),
            bad_pixels: BadPixelOptions::default(),
            calib_mask: None,
            no_detect_bad_pixels: false,
            save_intermediate: None,
            full_frame_sky: false,
            flat: Vec::new(),
            no_flat: false,
            flat_options: sofipol_calib::flat::FlatOptions::default(),
            calibration: Default::default(),
        }
    }
}

/// Settings of the calibration and the Stokes solve (`[calibration]` in the settings file;
/// used by [`crate::calibration`], kept here with the rest of the settings).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct CalibrationParams {
    /// How q, u are obtained from the per-orientation F (default `auto`).
    pub stokes_method: StokesMethod,
    /// Ignore the night's standards and any calibration (q, u from the plain solve;
    /// 2-orientation targets are flagged `uncalibrated`).
    pub no_calibration: bool,
    /// A standards table (TOML) adding to or overriding the built-in one by name and filter
    /// (`--standards`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub standards: Option<std::path::PathBuf>,
    /// The calibration products of another night (a directory written by `sofipol calib`,
    /// or its calibration.json), used instead of this night's standards (`--calib`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calib_dir: Option<std::path::PathBuf>,
    /// Neither fit nor remove the telescope's own polarization (`--no-telescope-correction`;
    /// the components are flagged `telescope_polarization_uncorrected`).
    pub no_telescope_correction: bool,
    /// Let components flagged `uncalibrated` pass the P/sigma cut (`--allow-uncalibrated`):
    /// without it they never do, since their q and u carry the instrument's offset c and
    /// their angles the profile's zero-point.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub allow_uncalibrated: bool,
}

/// `Ok` when `ok`, else the error naming `key`, `value` and `allowed`.
fn check(ok: bool, key: &'static str, value: impl std::fmt::Debug, allowed: &'static str) -> Result<(), SettingError> {
    if ok {
        Ok(())
    } else {
        Err(SettingError {
            key,
            value: format!("{value:?}"),
            allowed,
        })
    }
}

/// `v` finite and in `(lo, hi]`.
fn in_open_closed(v: f64, lo: f64, hi: f64) -> bool {
    v.is_finite() && v > lo && v <= hi
}

/// `v` finite and in `[lo, hi]`.
fn in_closed(v: f64, lo: f64, hi: f64) -> bool {
    v.is_finite() && v >= lo && v <= hi
}

/// Largest subpixel sampling N of `measure.method` (N x N samples per pixel).
pub const MAX_SUBPIXEL: u32 = 32;

impl TargetParams {
    /// Check every setting once, when the settings are read (file, then command-line
    /// overrides). The one place where allowed ranges are written down: every number has a
    /// lower and an upper bound (a radius of 1e20 FWHM or 1e8 x 1e8 samples per pixel
    /// would never finish), documented in docs/configuration.md.
    pub fn validate(&self) -> Result<(), SettingError> {
        self.measure.validate()?;
        let b = &self.bad_pixels;
        check(
            in_open_closed(b.sigma, 0.0, 1000.0),
            "bad_pixels.sigma",
            b.sigma,
            "in (0, 1000]",
        )?;
        check(
            (1..=31).contains(&b.window_px),
            "bad_pixels.window_px",
            b.window_px,
            "in 1..=31",
        )?;
        check(
            in_closed(b.min_deviation_adu, 0.0, 1e6),
            "bad_pixels.min_deviation_adu",
            b.min_deviation_adu,
            "in [0, 1e6]",
        )?;
        let sk = &self.sky;
        check(
            in_open_closed(sk.clip_sigma, 0.0, 100.0),
            "sky.clip_sigma",
            sk.clip_sigma,
            "in (0, 100]",
        )?;
        check(
            in_open_closed(sk.source_sigma, 0.0, 1000.0),
            "sky.source_sigma",
            sk.source_sigma,
            "in (0, 1000]",
        )?;
        check(
            sk.source_grow_px <= 10,
            "sky.source_grow_px",
            sk.source_grow_px,
            "in 0..=10",
        )?;
        if let Some(c) = &self.sky.cosmic_rays {
            check(
                in_open_closed(c.sigma_clip, 0.0, 1000.0),
                "sky.cosmic_rays.sigma_clip",
                c.sigma_clip,
                "in (0, 1000]",
            )?;
            check(
                in_closed(c.sharpness_ratio, 0.0, 1000.0),
                "sky.cosmic_rays.sharpness_ratio",
                c.sharpness_ratio,
                "in [0, 1000]",
            )?;
            check(
                in_open_closed(c.grow_sigma, 0.0, 1000.0),
                "sky.cosmic_rays.grow_sigma",
                c.grow_sigma,
                "in (0, 1000]",
            )?;
            check(
                c.grow_iterations <= 100,
                "sky.cosmic_rays.grow_iterations",
                c.grow_iterations,
                "in 0..=100",
            )?;
        }
        validate_flat_options(&self.flat_options)
    }
}

/// The `[flat_options]` ranges: a normalized response of 1 must lie strictly between
/// `min_response` and `max_response` (else every pixel is unusable and the superflat
/// fails), and a pixel cannot need more values than the frames combined.
fn validate_flat_options(f: &sofipol_calib::flat::FlatOptions) -> Result<(), SettingError> {
    let (lo, hi) = (f64::from(f.min_response), f64::from(f.max_response));
    check(
        in_open_closed(lo, 0.0, 1.0) && lo < 1.0,
        "flat_options.min_response",
        f.min_response,
        "in (0, 1) (below max_response)",
    )?;
    check(
        in_open_closed(hi, 1.0, 100.0),
        "flat_options.max_response",
        f.max_response,
        "in (1, 100] (above min_response)",
    )?;
    check(
        in_open_closed(f64::from(f.star_sigma), 0.0, 1000.0),
        "flat_options.star_sigma",
        f.star_sigma,
        "in (0, 1000]",
    )?;
    check(
        f.star_grow_px <= 20,
        "flat_options.star_grow_px",
        f.star_grow_px,
        "in 0..=20",
    )?;
    check(
        in_open_closed(f64::from(f.clip_sigma), 0.0, 100.0),
        "flat_options.clip_sigma",
        f.clip_sigma,
        "in (0, 100]",
    )?;
    check(
        (1..=1000).contains(&f.max_frames),
        "flat_options.max_frames",
        f.max_frames,
        "in 1..=1000",
    )?;
    check(
        f.min_values >= 1 && f.min_values <= f.max_frames,
        "flat_options.min_values",
        f.min_values,
        "in 1..=max_frames",
    )
}

impl MeasureParams {
    /// Check the measurement settings (see [`TargetParams::validate`]).
    pub fn validate(&self) -> Result<(), SettingError> {
        check(
            in_open_closed(self.aperture_fwhm, 0.0, 10.0),
            "measure.aperture_fwhm",
            self.aperture_fwhm,
            "in (0, 10]",
        )?;
        let (a, b) = self.annulus_fwhm;
        check(
            in_open_closed(a, 0.0, 20.0) && in_open_closed(b, 0.0, 20.0) && a < b,
            "measure.annulus_fwhm",
            self.annulus_fwhm,
            "(inner, outer) with 0 < inner < outer <= 20",
        )?;
        if let Method::Subpixel(n) = self.method {
            check(
                (1..=MAX_SUBPIXEL).contains(&n),
                "measure.method",
                self.method,
                "exact, center, or subpixel:N with N in 1..=32",
            )?;
        }
        check(
            in_closed(self.psf_photometry_below_fwhm, 0.0, 20.0),
            "measure.psf_photometry_below_fwhm",
            self.psf_photometry_below_fwhm,
            "in [0, 20]",
        )?;
        check(
            in_open_closed(self.primary_search_px, 0.0, 1024.0),
            "measure.primary_search_px",
            self.primary_search_px,
            "in (0, 1024]",
        )?;
        if let Some((x, y)) = self.nominal_xy_px {
            check(
                in_closed(x, 0.0, 4096.0) && in_closed(y, 0.0, 4096.0),
                "measure.nominal_xy_px",
                (x, y),
                "(x, y) on the detector, each in [0, 4096]",
            )?;
        }
        check(
            in_open_closed(self.companion_search_arcsec, 0.0, 60.0),
            "measure.companion_search_arcsec",
            self.companion_search_arcsec,
            "in (0, 60]",
        )?;
        check(
            in_closed(self.min_companion_snr, 0.0, 1e6),
            "measure.min_companion_snr",
            self.min_companion_snr,
            "in [0, 1e6]",
        )?;
        check(
            in_closed(self.field_star_snr, 3.0, 1e6),
            "measure.field_star_snr",
            self.field_star_snr,
            "in [3, 1e6]",
        )?;
        check(
            in_closed(self.min_companion_f, 0.0, 1e9),
            "measure.min_companion_f",
            self.min_companion_f,
            "in [0, 1e9]",
        )?;
        check(
            in_closed(self.min_companion_sep_arcsec, 0.0, 60.0),
            "measure.min_companion_sep_arcsec",
            self.min_companion_sep_arcsec,
            "in [0, 60]",
        )?;
        check(
            in_open_closed(self.clip_sigma, 0.0, 100.0),
            "measure.clip_sigma",
            self.clip_sigma,
            "in (0, 100]",
        )?;
        check(
            in_closed(self.cut_snr, 0.0, 1000.0),
            "measure.cut_snr",
            self.cut_snr,
            "in [0, 1000]",
        )?;
        if let Some((sep, pa)) = self.companion_hint {
            check(
                in_open_closed(sep, 0.0, 60.0) && in_closed(pa, -360.0, 360.0),
                "measure.companion_hint",
                (sep, pa),
                "(separation in (0, 60] arcsec, PA in [-360, 360] deg)",
            )?;
        }
        if let PsfModel::Moffat { beta: Some(b) } = self.psf_model {
            check(
                in_open_closed(b, 1.0, 100.0),
                "measure.psf_model.beta",
                b,
                "in (1, 100]",
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_errors_name_key_value_and_range() {
        assert_eq!(TargetParams::default().validate(), Ok(()));
        let mut p = TargetParams::default();
        p.measure.annulus_fwhm = (6.0, 4.0);
        let e = p.validate().unwrap_err().to_string();
        assert!(
            e.contains("measure.annulus_fwhm") && e.contains("6.0") && e.contains("inner < outer"),
            "{e}"
        );
        let mut p = TargetParams::default();
        p.measure.aperture_fwhm = f64::NAN;
        assert_eq!(p.validate().unwrap_err().key, "measure.aperture_fwhm");
        let mut p = TargetParams::default();
        p.measure.psf_model = PsfModel::Moffat { beta: Some(1.0) };
        assert_eq!(p.validate().unwrap_err().key, "measure.psf_model.beta");
    }

    #[test]
    fn every_number_has_an_upper_bound_and_the_flat_options_a_consistent_range() {
        // Each setting just inside and just outside its range.
        type Set = fn(&mut TargetParams, f64);
        let cases: [(&str, Set, f64, f64); 10] = [
            ("measure.aperture_fwhm", |p, v| p.measure.aperture_fwhm = v, 10.0, 10.01),
            (
                "measure.primary_search_px",
                |p, v| p.measure.primary_search_px = v,
                1024.0,
                1025.0,
            ),
            (
                "measure.companion_search_arcsec",
                |p, v| p.measure.companion_search_arcsec = v,
                60.0,
                61.0,
            ),
            ("measure.clip_sigma", |p, v| p.measure.clip_sigma = v, 100.0, 101.0),
            ("measure.cut_snr", |p, v| p.measure.cut_snr = v, 1000.0, 1001.0),
            ("bad_pixels.sigma", |p, v| p.bad_pixels.sigma = v, 1000.0, 1001.0),
            ("sky.clip_sigma", |p, v| p.sky.clip_sigma = v, 100.0, 101.0),
            (
                "flat_options.min_response",
                |p, v| p.flat_options.min_response = v as f32,
                0.99,
                1.0,
            ),
            (
                "flat_options.max_response",
                |p, v| p.flat_options.max_response = v as f32,
                1.01,
                1.0,
            ),
            (
                "flat_options.clip_sigma",
                |p, v| p.flat_options.clip_sigma = v as f32,
                100.0,
                1e20,
            ),
        ];
        for (key, set, inside, outside) in cases {
            let mut p = TargetParams::default();
            set(&mut p, inside);
            assert_eq!(p.validate(), Ok(()), "{key} = {inside}");
            set(&mut p, outside);
            assert_eq!(p.validate().unwrap_err().key, key, "{key} = {outside}");
        }
        let mut p = TargetParams::default();
        p.measure.method = Method::Subpixel(MAX_SUBPIXEL);
        assert_eq!(p.validate(), Ok(()));
        p.measure.method = Method::Subpixel(100_000_000);
        assert_eq!(p.validate().unwrap_err().key, "measure.method");
        // A pixel cannot need more values than the frames combined, nor 0 frames.
        let mut p = TargetParams::default();
        p.flat_options.max_frames = 0;
        assert_eq!(p.validate().unwrap_err().key, "flat_options.max_frames");
        p.flat_options.max_frames = 4;
        assert_eq!(p.validate().unwrap_err().key, "flat_options.min_values");
        p.flat_options.min_values = 4;
        assert_eq!(p.validate(), Ok(()));
    }
}

/// A path or a list of paths (the settings file's `flat = "a.fits"` or `flat = ["a", "b"]`).
fn one_or_many<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<PathBuf>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum OneOrMany {
        One(PathBuf),
        Many(Vec<PathBuf>),
    }
    Ok(match OneOrMany::deserialize(d)? {
        OneOrMany::One(p) => vec![p],
        OneOrMany::Many(v) => v,
    })
}

#[cfg(test)]
mod tests_flat {
    use super::*;

    #[test]
    fn the_settings_flat_is_a_path_or_a_list_of_paths() {
        let one: TargetParams = toml::from_str("flat = \"cal/flat_dome_Ks_pa000.fits\"").unwrap();
        assert_eq!(one.flat, [PathBuf::from("cal/flat_dome_Ks_pa000.fits")]);
        let two: TargetParams = toml::from_str("flat = [\"a.fits\", \"b.fits\"]").unwrap();
        assert_eq!(two.flat, [PathBuf::from("a.fits"), PathBuf::from("b.fits")]);
        assert!(TargetParams::default().flat.is_empty());
        let e = toml::from_str::<TargetParams>("flat = 3").unwrap_err().to_string();
        assert!(e.contains("flat"), "{e}");
        // Written back (as `--dump-params` does) and read again: the same list.
        let back: TargetParams = toml::from_str(&toml::to_string(&two).unwrap()).unwrap();
        assert_eq!(back.flat, two.flat);
    }
}
