//! Instrument profiles: every instrument number a stage needs, from a TOML file.
//!
//! The SOFI profile is embedded (`calib/profiles/sofi.toml`). A user file may override
//! any subset of it: it is merged key by key over the embedded one, then validated.
use serde::{Deserialize, Serialize};
use std::path::Path;

use crate::error::{Error, Result};
use crate::frame::Frame;

/// The embedded SOFI profile text.
pub const SOFI_TOML: &str = include_str!("../profiles/sofi.toml");

/// The embedded Keck/NIRC2 profile text (merged over SOFI's: it gives every key the
/// half-wave-plate reduction reads; docs/instruments.md).
pub const NIRC2_TOML: &str = include_str!("../profiles/nirc2.toml");

/// The embedded profiles `--profile NAME` selects: (name, text merged over SOFI's).
pub const EMBEDDED: [(&str, &str); 2] = [("sofi", ""), ("nirc2", NIRC2_TOML)];

mod modulation;
pub use modulation::{
    AngleTerm, Beams, Classify, FieldRotation, FieldRotationKind, KeywordRule, Modulation, ModulationKind, Role,
    SinglePointing, SkySource,
};

/// Header keyword names (without `HIERARCH`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)] // a misspelt key in --profile or --set is an error, not ignored
#[allow(missing_docs)]
pub struct Keywords {
    pub instrument: String,
    pub object: String,
    pub targ_name: String,
    pub date_obs: String,
    pub mjd_obs: String,
    pub exptime: String,
    pub dpr_catg: String,
    pub dpr_type: String,
    pub dpr_tech: String,
    pub tpl_id: String,
    pub tpl_start: String,
    pub tpl_nexp: String,
    pub tpl_expno: String,
    pub filter: String,
    /// `OPTIi ID` keywords are `{opti_prefix}{i} ID` for i = 1..=opti_max.
    pub opti_prefix: String,
    pub opti_max: u32,
    pub pixscale: String,
    pub posang: String,
    pub offset_x: String,
    pub offset_y: String,
    pub dit: String,
    pub ndit: String,
    /// Parallactic angle at the exposure's start, deg (PA of the direction to the zenith).
    pub parang: String,
    /// Parallactic angle at the exposure's end, deg.
    pub parang_end: String,
    pub airmass: String,
    pub airmass_end: String,
    /// Telescope altitude, deg.
    pub altitude: String,
    /// Right ascension of the pointing, deg (optional in a frame; catalog position).
    #[serde(default = "default_ra")]
    pub ra: String,
    /// Declination of the pointing, deg (optional in a frame; catalog position).
    #[serde(default = "default_dec")]
    pub dec: String,
}

/// `RA`: the keyword of a profile written before `ra` was a key.
fn default_ra() -> String {
    "RA".into()
}

/// `DEC`: the keyword of a profile written before `dec` was a key.
fn default_dec() -> String {
    "DEC".into()
}

impl Keywords {
    /// The parallactic angle of an exposure, deg in (-180, 180]: the mean of `parang`
    /// (start) and `parang_end` (end) taken along the shorter arc (so -179 and 179 give
    /// 180), or the start alone when the end is absent. `Ok(None)` when the start is absent;
    /// an error naming the keyword when either is present but not a finite number.
    ///
    /// A value outside [-360, 360] deg is refused (an angle is never written so), and so
    /// is an end more than [`MAX_PARANG_CHANGE_DEG`] from the start: a corrupt card, never
    /// an exposure (the angle turns that fast only within a fraction of a degree of the
    /// zenith). Either error names the keyword and its value.
    pub fn parallactic_angle_deg(&self, h: &crate::header::Header) -> Result<Option<f64>> {
        let in_range = |key: &str| -> Result<Option<f64>> {
            match h.opt_f64(key)? {
                Some(v) if v.abs() > 360.0 => Err(crate::Error::BadKeyword {
                    path: h.path.clone(),
                    keyword: key.to_string(),
                    value: crate::text::short_number(v),
                    reason: "a parallactic angle must lie within [-360, 360] deg".into(),
                }),
                v => Ok(v),
            }
        };
        let Some(start) = in_range(&self.parang)? else {
            return Ok(None);
        };
        let mean = match in_range(&self.parang_end)? {
            Some(end) if wrap_deg(end - start).abs() > MAX_PARANG_CHANGE_DEG => {
                return Err(crate::Error::BadKeyword {
                    path: h.path.clone(),
                    keyword: self.parang_end.clone(),
                    value: crate::text::short_number(end),
                    reason: format!(
                        "{:.1} deg from {} = {}: the parallactic angle cannot turn more than \
                         {MAX_PARANG_CHANGE_DEG} deg in one exposure",
                        wrap_deg(end - start).abs(),
                        self.parang,
                        crate::text::short_number(start)
                    ),
                })
            }
            Some(end) => start + 0.5 * wrap_deg(end - start),
            None => start,
        };
        Ok(Some(wrap_deg(mean)))
    }
}

/// The largest change of the parallactic angle between the start and the end of one
/// exposure that is taken as real, deg. At La Silla a star 1 deg from the zenith turns
/// by about 12 deg/min at transit; a larger jump is a corrupt header.
pub const MAX_PARANG_CHANGE_DEG: f64 = 90.0;

/// An angle in degrees mapped into (-180, 180].
fn wrap_deg(a: f64) -> f64 {
    let r = a.rem_euclid(360.0);
    if r > 180.0 {
        r - 360.0
    } else {
        r
    }
}

/// Values that identify polarimetric science frames.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)] // a misspelt key in --profile or --set is an error, not ignored
pub struct Match {
    /// Expected INSTRUME value.
    pub instrument: String,
    /// Template ID of the polarimetric imaging template.
    pub polarimetry_template: String,
    /// DPR TECH of polarimetric frames.
    pub polarimetry_tech: String,
    /// Substring identifying the Wollaston in an `INS OPTIi ID`.
    pub wollaston_contains: String,
    /// DPR TYPE values accepted as science.
    pub science_types: Vec<String>,
    /// OBJECT value that means "use OBS TARG NAME instead".
    pub object_std_alias: String,
}

/// Detector geometry: the detector, the o -> e displacement of the beam splitter and the
/// focal mask's strips. Row ranges are 0-based, half-open.
///
/// Two layouts: a focal mask (`mask = true`, the default: SOFI's six strips, each row
/// receiving one beam or none) or none (`mask = false`: a Savart-plate-like imager, both
/// beams on the whole detector, the e image of a source at `eo_offset_px` from its o image;
/// the strip keys are then ignored).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)] // a misspelt key in --profile or --set is an error, not ignored
#[allow(missing_docs)]
pub struct Geometry {
    pub nx: usize,
    pub ny: usize,
    pub pixscale_arcsec: f64,
    /// Whether a focal mask blocks all rows outside the six strips (default `true`).
    /// `false`: no mask, the whole detector sees sky through both beams.
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub mask: bool,
    pub strip_height_px: usize,
    pub o_sky2: [usize; 2],
    pub e_sky2: [usize; 2],
    pub o_target: [usize; 2],
    pub e_target: [usize; 2],
    pub o_sky1: [usize; 2],
    pub e_sky1: [usize; 2],
    /// e image position minus o image position, (dx, dy) px; a starting value only.
    pub eo_offset_px: [f64; 2],
    /// Nominal jitter step, px.
    pub jitter_step_px: f64,
}

fn is_true(b: &bool) -> bool {
    *b
}

/// The name [`Geometry::strips`] gives the one region of a detector without a focal mask.
pub const WHOLE_DETECTOR: &str = "detector";

impl Geometry {
    /// Whether a focal mask splits the detector into strips ([`Geometry::mask`]).
    pub fn has_mask(&self) -> bool {
        self.mask
    }

    /// The regions of the detector that see sky, as (name, rows [start, end)), bottom to
    /// top: the six strips of the focal mask, or without a mask one region
    /// ([`WHOLE_DETECTOR`]) of every row. Stages that level, normalize or threshold region
    /// by region take these.
    pub fn strips(&self) -> Vec<(&'static str, [usize; 2])> {
        if !self.mask {
            return vec![(WHOLE_DETECTOR, [0, self.ny])];
        }
        vec![
            ("o_sky2", self.o_sky2),
            ("e_sky2", self.e_sky2),
            ("o_target", self.o_target),
            ("e_target", self.e_target),
            ("o_sky1", self.o_sky1),
            ("e_sky1", self.e_sky1),
        ]
    }
    /// Whether row `y` sees sky: inside a strip of the mask; every row when there is no
    /// mask.
    pub fn row_in_strip(&self, y: usize) -> bool {
        self.strips().iter().any(|(_, r)| y >= r[0] && y < r[1])
    }

    /// The one image of the beam splitter that row `y` receives: `None` on rows the mask
    /// blocks, and on every row without a mask (each pixel then receives both beams: a
    /// pixel's beam is that of the source it belongs to, [`Geometry::e_image_of`]).
    pub fn beam_of_row(&self, y: usize) -> Option<Beam> {
        if !self.mask {
            return None;
        }
        let inside = |r: &[usize; 2]| y >= r[0] && y < r[1];
        if [self.o_sky2, self.o_target, self.o_sky1].iter().any(inside) {
            Some(Beam::Ordinary)
        } else if [self.e_sky2, self.e_target, self.e_sky1].iter().any(inside) {
            Some(Beam::Extraordinary)
        } else {
            None
        }
    }

    /// The rows `[start, end)` where the target's image of `beam` falls: its strip, or
    /// every row without a mask.
    pub fn target_rows(&self, beam: Beam) -> [usize; 2] {
        if !self.mask {
            return [0, self.ny];
        }
        match beam {
            Beam::Ordinary => self.o_target,
            Beam::Extraordinary => self.e_target,
        }
    }

    /// The rows `[start, end)` holding the target's two images: what a reduction that
    /// measures only the target needs to read (every row without a mask).
    pub fn measured_rows(&self) -> [usize; 2] {
        if !self.mask {
            return [0, self.ny];
        }
        [
            self.o_target[0].min(self.e_target[0]),
            self.o_target[1].max(self.e_target[1]),
        ]
    }

    /// The pointing: where the telescope puts the target's o image at zero jitter offset,
    /// (x, y) px. The detector's centre column and the middle of the o-target strip; without
    /// a mask, the point that centres the pair of images (o and e) on the detector.
    pub fn pointing_px(&self) -> (f64, f64) {
        if !self.mask {
            return (
                (self.nx as f64 - self.eo_offset_px[0]) / 2.0 - 0.5,
                (self.ny as f64 - self.eo_offset_px[1]) / 2.0 - 0.5,
            );
        }
        (
            self.nx as f64 / 2.0,
            (self.o_target[0] + self.o_target[1]) as f64 / 2.0 - 0.5,
        )
    }

    /// The first row above every strip: a frame needs at least this many rows.
    pub fn lit_rows_end(&self) -> usize {
        self.strips().iter().map(|(_, r)| r[1]).max().unwrap_or(0)
    }

    /// The nominal position of the extraordinary image of a star whose ordinary image is
    /// at `(x, y)` (a starting value: the reduction measures the offset).
    pub fn e_image_of(&self, (x, y): (f64, f64)) -> (f64, f64) {
        (x + self.eo_offset_px[0], y + self.eo_offset_px[1])
    }

    /// The checks of [`Profile::validate`] on the geometry: the reason naming key and value.
    fn check(&self) -> std::result::Result<(), String> {
        if !(1..=MAX_DETECTOR_SIDE_PX).contains(&self.nx) || !(1..=MAX_DETECTOR_SIDE_PX).contains(&self.ny) {
            return Err(format!(
                "geometry.nx = {}, ny = {}: each must be in 1..={MAX_DETECTOR_SIDE_PX}",
                self.nx, self.ny
            ));
        }
        let [dx, dy] = self.eo_offset_px;
        for (i, v, side) in [(0, dx, self.nx), (1, dy, self.ny)] {
            if v.is_finite() && v.abs() >= side as f64 {
                return Err(format!(
                    "geometry.eo_offset_px[{i}] = {v}: the e image would fall off the detector ({} px {})",
                    side,
                    if i == 0 { "wide" } else { "high" }
                ));
            }
        }
        if !self.mask {
            if dx.hypot(dy) < 2.0 {
                return Err(format!(
                    "geometry.eo_offset_px = [{dx}, {dy}]: without a mask the two images must be at least 2 px \
                     apart (they would lie on each other)"
                ));
            }
            return Ok(());
        }
        let strips = self.strips();
        for (name, r) in &strips {
            if r[0] >= r[1] || r[1] > self.ny {
                return Err(format!(
                    "geometry.{name} = [{}, {}) is not inside 0..{}",
                    r[0], r[1], self.ny
                ));
            }
        }
        for (i, (a, ra)) in strips.iter().enumerate() {
            for (b, rb) in &strips[i + 1..] {
                if ra[0] < rb[1] && rb[0] < ra[1] {
                    return Err(format!(
                        "geometry.{a} = [{}, {}) and geometry.{b} = [{}, {}) overlap",
                        ra[0], ra[1], rb[0], rb[1]
                    ));
                }
            }
        }
        Ok(())
    }
}

/// The two images of a Wollaston prism.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Beam {
    /// The ordinary image.
    Ordinary,
    /// The extraordinary image.
    Extraordinary,
}

/// Detector constants.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)] // a misspelt key in --profile or --set is an error, not ignored
pub struct Detector {
    /// Gain, electrons per ADU (per read).
    pub gain_e_per_adu: f64,
    /// Read noise per read, electrons.
    pub read_noise_e: f64,
    /// Below this level the response is linear to 0.1 %.
    pub linear_limit_adu: f64,
    /// Above this level photometry is flagged non-linear.
    pub nonlinear_warn_adu: f64,
    /// Saturation level.
    pub saturation_adu: f64,
    /// Quadratic non-linearity: measured = true * (1 - c * true).
    pub nonlin_coeff_per_adu: f64,
    /// The header keyword of the gain (e-/ADU), when the header gives it: it then wins over
    /// `gain_e_per_adu` (read by the half-wave-plate reduction).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gain_keyword: Option<String>,
    /// The header keyword of the read noise (e- per read), when the header gives it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub read_noise_keyword: Option<String>,
    /// Whether the pixel values are the SUM of the NDIT (coadd) reads (NIRC2) rather than
    /// their mean (SOFI): then the read-noise variance is NDIT x (read noise / gain)^2 and
    /// the levels above (linear limit, saturation) are per read.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub coadds_summed: bool,
}

impl Detector {
    /// The gain of a frame, e-/ADU: its header's (`gain_keyword`) or the profile's.
    pub fn gain_of(&self, h: &crate::header::Header) -> Result<f64> {
        modulation::number_or_keyword(h, self.gain_keyword.as_deref(), self.gain_e_per_adu, "a gain")
    }
    /// The read noise of a frame, e- per read: its header's (`read_noise_keyword`) or the
    /// profile's.
    pub fn read_noise_of(&self, h: &crate::header::Header) -> Result<f64> {
        modulation::number_or_keyword(h, self.read_noise_keyword.as_deref(), self.read_noise_e, "a read noise")
    }
    /// Effective gain of an NDIT-averaged frame for Poisson noise (e-/ADU).
    pub fn effective_gain(&self, ndit: u32) -> f64 {
        self.gain_e_per_adu * ndit.max(1) as f64
    }
    /// Read-noise variance of an NDIT-averaged frame, ADU^2.
    pub fn read_variance_adu2(&self, ndit: u32) -> f64 {
        let r = self.read_noise_e / self.gain_e_per_adu;
        r * r / ndit.max(1) as f64
    }
}

/// Angle conventions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)] // a misspelt key in --profile or --set is an error, not ignored
pub struct Angles {
    /// theta0, degrees.
    pub zero_point_deg: f64,
    /// Image parity s, +1 or -1.
    pub parity: i32,
    /// The 1-sigma uncertainty of `zero_point_deg`, degrees: carried as a systematic error
    /// of every angle of a filter whose standards do not measure theta0 (no polarized
    /// standard in that filter).
    #[serde(default = "default_sigma_zero_point_deg")]
    pub sigma_zero_point_deg: f64,
}

/// The profile zero-point's uncertainty when a profile does not give one, deg.
fn default_sigma_zero_point_deg() -> f64 {
    5.0
}

impl Angles {
    /// Analyzer angle phi (degrees) for a rotator position angle: phi = s * POSANG + theta0.
    pub fn analyzer_angle_deg(&self, posang_deg: f64) -> f64 {
        self.parity as f64 * posang_deg + self.zero_point_deg
    }
}

/// The mirror in front of the rotator (on SOFI the NTT's tertiary M3): the physical size
/// of the telescope's own polarization. A metal mirror at oblique incidence polarizes by
/// `(R_s - R_p)/(R_s + R_p)` (Fresnel) along a direction fixed to its plane of incidence,
/// which on the sky turns with the parallactic angle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)] // a misspelt key in --profile or --set is an error, not ignored
pub struct Telescope {
    /// Whether the telescope adds a polarization that turns with the parallactic angle (an
    /// oblique mirror in front of the rotator, as SOFI's M3). `false`: the model has no
    /// such term (nothing to fit, remove or carry).
    #[serde(default = "yes")]
    pub polarizes: bool,
    /// The coating, in words (for the record).
    pub coating: String,
    /// Angle of incidence on the mirror, deg from the normal.
    pub incidence_deg: f64,
    /// psi_tel: the angle of its polarization from the parallactic direction, deg.
    pub psi_deg: f64,
    /// 1-sigma uncertainty of `psi_deg`, deg.
    pub sigma_psi_deg: f64,
    /// 1-sigma uncertainty of p_tel relative to its Fresnel value.
    pub relative_width: f64,
    /// The coating's complex refractive index at each filter's wavelength (filter names as
    /// in the headers, compared ignoring case).
    #[serde(default)]
    pub filters: std::collections::BTreeMap<String, MirrorIndex>,
}

/// A coating's refractive index `n + i k` at one filter's wavelength.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MirrorIndex {
    /// The filter's central wavelength, micron (for the record).
    pub wavelength_um: f64,
    /// Real part.
    pub n: f64,
    /// Imaginary part (extinction coefficient).
    pub k: f64,
}

fn yes() -> bool {
    true
}

impl Telescope {
    /// No mirror described: no prior for any filter.
    pub fn undescribed() -> Telescope {
        Telescope {
            polarizes: true,
            coating: String::new(),
            incidence_deg: 45.0,
            psi_deg: 0.0,
            sigma_psi_deg: 90.0,
            relative_width: 1.0,
            filters: Default::default(),
        }
    }

    /// The coating's index in `filter` (name compared ignoring case and blanks).
    pub fn index(&self, filter: &str) -> Option<MirrorIndex> {
        let f = filter.trim();
        self.filters
            .iter()
            .find(|(name, _)| name.trim().eq_ignore_ascii_case(f))
            .map(|(_, i)| *i)
    }
}

/// A complete, validated instrument profile.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)] // a misspelt key in --profile or --set is an error, not ignored
pub struct Profile {
    /// Instrument name.
    pub name: String,
    /// Header keyword names.
    pub keywords: Keywords,
    /// Values that identify polarimetric science frames.
    #[serde(rename = "match")]
    pub matching: Match,
    /// Geometry.
    pub geometry: Geometry,
    /// Detector constants.
    pub detector: Detector,
    /// Angle conventions.
    pub angles: Angles,
    /// The mirror in front of the rotator (the telescope's own polarization).
    #[serde(default = "Telescope::undescribed")]
    pub telescope: Telescope,
    /// Photometry: the atmospheric extinction of the magnitudes' airmass term.
    #[serde(default)]
    pub photometry: Photometry,
    /// How the analyzer angle is set (absent: SOFI's turned instrument).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub modulation: Option<Modulation>,
    /// How the field turns on the detector (absent: fixed on the sky).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field_rotation: Option<FieldRotation>,
    /// File roles from keyword tests, for headers that are not ESO's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub classify: Option<Classify>,
    /// The rows of the two beams of a Wollaston without a focal mask.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub beams: Option<Beams>,
    /// How a single pointing (one star, no dithers) is measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub single_pointing: Option<SinglePointing>,
}

/// The atmosphere's extinction for the photometric zero-point (docs/calibration.md,
/// "Magnitudes"): a star's magnitude is `ZP - 2.5 log10(flux / DIT) - k X` at airmass X.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Photometry {
    /// k, mag per airmass, of every filter without its own entry in `filters`. Default 0:
    /// no La Silla value per near-infrared band could be verified here (at Paranal, the
    /// J, H and Ks extinction is below 0.1 mag per airmass: Lombardi et al. 2011, A&A 528,
    /// A43); with 0 the zero-point absorbs the mean airmass of the standards.
    #[serde(default)]
    pub extinction_mag_per_airmass: f64,
    /// k per filter (names as in the headers, compared ignoring case), mag per airmass.
    #[serde(default)]
    pub filters: std::collections::BTreeMap<String, f64>,
}

/// The largest extinction a profile may give, mag per airmass (the optical U band of a
/// good site is about 0.5; the near-infrared below 0.1).
pub const MAX_EXTINCTION_MAG_PER_AIRMASS: f64 = 2.0;

impl Photometry {
    /// k of `filter`, mag per airmass: its own entry (name compared ignoring case and
    /// blanks), else `extinction_mag_per_airmass`.
    pub fn extinction(&self, filter: &str) -> f64 {
        let f = filter.trim();
        self.filters
            .iter()
            .find(|(name, _)| name.trim().eq_ignore_ascii_case(f))
            .map_or(self.extinction_mag_per_airmass, |(_, k)| *k)
    }
}

fn merge(base: &mut toml::Value, over: toml::Value) {
    match (base, over) {
        (toml::Value::Table(b), toml::Value::Table(o)) => {
            for (k, v) in o {
                match b.get_mut(&k) {
                    Some(bv) if bv.is_table() && v.is_table() => merge(bv, v),
                    _ => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (b, o) => *b = o,
    }
}

/// Largest detector side a profile may give, px (SOFI's is 1024): beyond it, a typo would
/// size every per-frame buffer.
pub const MAX_DETECTOR_SIDE_PX: usize = 4096;

impl Profile {
    /// The embedded SOFI profile.
    pub fn sofi() -> Profile {
        Self::from_layers(&[("embedded sofi", SOFI_TOML)]).expect("embedded SOFI profile is valid")
    }

    /// An embedded profile by name (`sofi`, `nirc2`: [`EMBEDDED`]), merged over SOFI's;
    /// `None` for another name.
    pub fn embedded(name: &str) -> Option<Result<Profile>> {
        let (n, text) = EMBEDDED.iter().find(|(n, _)| n.eq_ignore_ascii_case(name.trim()))?;
        Some(Self::from_layers(&[
            ("embedded sofi", SOFI_TOML),
            (&format!("embedded {n}"), text),
        ]))
    }

    /// How the analyzer angle is set: the `[modulation]` kind, `rotate_instrument` (SOFI's)
    /// without the section.
    pub fn modulation_kind(&self) -> ModulationKind {
        self.modulation.as_ref().map(|m| m.kind).unwrap_or_default()
    }

    /// The SOFI profile with a user TOML file merged over it.
    pub fn sofi_with_override(path: &Path) -> Result<Profile> {
        let text = crate::input::read_to_string(path, crate::input::MAX_OPTION_FILE_BYTES).map_err(|e| Error::Io {
            path: path.to_path_buf(),
            source: e,
        })?;
        Self::from_layers(&[("embedded sofi", SOFI_TOML), (&path.display().to_string(), &text)])
    }

    /// Apply `section.key=value` overrides (value parsed as TOML, bare words as strings).
    pub fn with_overrides(&self, sets: &[String]) -> Result<Profile> {
        if sets.is_empty() {
            return Ok(self.clone());
        }
        let mut v = toml::Value::try_from(self).map_err(|e| Error::Profile {
            source_name: "current".into(),
            reason: e.to_string(),
        })?;
        for s in sets {
            let (path, val) = s.split_once('=').ok_or_else(|| Error::Profile {
                source_name: "--set".into(),
                reason: format!("'{s}' is not of the form section.key=value"),
            })?;
            let mut over = toml_value(val);
            for part in path.trim().split('.').rev() {
                let mut t = toml::Table::new();
                t.insert(part.to_string(), over);
                over = toml::Value::Table(t);
            }
            merge(&mut v, over);
        }
        let p: Profile = v.try_into().map_err(|e: toml::de::Error| Error::Profile {
            source_name: "--set".into(),
            reason: e.to_string(),
        })?;
        p.validate("--set")?;
        Ok(p)
    }

    fn from_layers(layers: &[(&str, &str)]) -> Result<Profile> {
        let mut acc = toml::Value::Table(toml::Table::new());
        let mut last = "";
        for (name, text) in layers {
            let v: toml::Table = text.parse().map_err(|e: toml::de::Error| Error::Profile {
                source_name: name.to_string(),
                reason: e.to_string(),
            })?;
            merge(&mut acc, toml::Value::Table(v));
            last = name;
        }
        let p: Profile = acc.try_into().map_err(|e: toml::de::Error| Error::Profile {
            source_name: last.to_string(),
            reason: e.to_string(),
        })?;
        p.validate(last)?;
        Ok(p)
    }

    /// Check internal consistency.
    pub fn validate(&self, source_name: &str) -> Result<()> {
        let err = |reason: String| {
            Err(Error::Profile {
                source_name: source_name.into(),
                reason,
            })
        };
        let g = &self.geometry;
        if let Err(reason) = g.check() {
            return err(reason);
        }
        if !(g.pixscale_arcsec > 0.0) {
            return err(format!("geometry.pixscale_arcsec = {} must be > 0", g.pixscale_arcsec));
        }
        let d = &self.detector;
        if !(d.gain_e_per_adu > 0.0) {
            return err(format!("detector.gain_e_per_adu = {} must be > 0", d.gain_e_per_adu));
        }
        if !(d.read_noise_e >= 0.0) {
            return err(format!("detector.read_noise_e = {} must be >= 0", d.read_noise_e));
        }
        if !(d.saturation_adu > d.linear_limit_adu) {
            return err(format!(
                "detector.saturation_adu = {} must exceed linear_limit_adu = {}",
                d.saturation_adu, d.linear_limit_adu
            ));
        }
        // Every number finite and in its range (NaN fails every comparison above only
        // when the test is written `!(x > 0)`; these would pass NaN or infinity).
        let finite = [
            ("geometry.pixscale_arcsec", g.pixscale_arcsec),
            ("geometry.eo_offset_px[0]", g.eo_offset_px[0]),
            ("geometry.eo_offset_px[1]", g.eo_offset_px[1]),
            ("geometry.jitter_step_px", g.jitter_step_px),
            ("detector.gain_e_per_adu", d.gain_e_per_adu),
            ("detector.read_noise_e", d.read_noise_e),
            ("detector.linear_limit_adu", d.linear_limit_adu),
            ("detector.nonlinear_warn_adu", d.nonlinear_warn_adu),
            ("detector.saturation_adu", d.saturation_adu),
            ("detector.nonlin_coeff_per_adu", d.nonlin_coeff_per_adu),
            ("angles.zero_point_deg", self.angles.zero_point_deg),
            ("angles.sigma_zero_point_deg", self.angles.sigma_zero_point_deg),
            ("telescope.incidence_deg", self.telescope.incidence_deg),
            ("telescope.psi_deg", self.telescope.psi_deg),
            ("telescope.sigma_psi_deg", self.telescope.sigma_psi_deg),
            ("telescope.relative_width", self.telescope.relative_width),
        ];
        let ph = &self.photometry;
        let extinctions = std::iter::once((
            "photometry.extinction_mag_per_airmass".to_string(),
            ph.extinction_mag_per_airmass,
        ))
        .chain(ph.filters.iter().map(|(f, k)| (format!("photometry.filters.{f}"), *k)));
        for (key, k) in extinctions {
            if !(0.0..=MAX_EXTINCTION_MAG_PER_AIRMASS).contains(&k) {
                return err(format!(
                    "{key} = {k} must be in [0, {MAX_EXTINCTION_MAG_PER_AIRMASS}] mag per airmass"
                ));
            }
        }
        for (name, v) in finite {
            if !v.is_finite() {
                return err(format!("{name} = {v} must be a finite number"));
            }
        }
        if !(d.linear_limit_adu > 0.0) {
            return err(format!(
                "detector.linear_limit_adu = {} must be > 0",
                d.linear_limit_adu
            ));
        }
        if !(0.0..=90.0).contains(&self.angles.sigma_zero_point_deg) {
            return err(format!(
                "angles.sigma_zero_point_deg = {} must be in [0, 90]",
                self.angles.sigma_zero_point_deg
            ));
        }
        let t = &self.telescope;
        if !(0.0..90.0).contains(&t.incidence_deg) {
            return err(format!(
                "telescope.incidence_deg = {} must be in [0, 90)",
                t.incidence_deg
            ));
        }
        if !(t.sigma_psi_deg > 0.0 && t.sigma_psi_deg <= 90.0) {
            return err(format!(
                "telescope.sigma_psi_deg = {} must be in (0, 90]",
                t.sigma_psi_deg
            ));
        }
        if !(t.relative_width > 0.0 && t.relative_width <= 1.0) {
            return err(format!(
                "telescope.relative_width = {} must be in (0, 1]",
                t.relative_width
            ));
        }
        let mut seen = std::collections::BTreeSet::new();
        for (name, i) in &t.filters {
            if !seen.insert(name.trim().to_ascii_lowercase()) {
                return err(format!(
                    "telescope.filters.{name}: the filter is given twice (names compared ignoring case)"
                ));
            }
            if !(i.n.is_finite() && i.n > 0.0 && i.k.is_finite() && i.k >= 0.0) {
                return err(format!(
                    "telescope.filters.{name}: n = {}, k = {} must be finite with n > 0 and k >= 0",
                    i.n, i.k
                ));
            }
            if !(i.wavelength_um.is_finite() && i.wavelength_um > 0.0) {
                return err(format!(
                    "telescope.filters.{name}.wavelength_um = {} must be > 0",
                    i.wavelength_um
                ));
            }
        }
        if !(d.nonlin_coeff_per_adu >= 0.0) {
            return err(format!(
                "detector.nonlin_coeff_per_adu = {} must be >= 0",
                d.nonlin_coeff_per_adu
            ));
        }
        if !(1..=MAX_DETECTOR_SIDE_PX).contains(&g.nx) || !(1..=MAX_DETECTOR_SIDE_PX).contains(&g.ny) {
            return err(format!(
                "geometry.nx = {}, ny = {}: each must be in 1..={MAX_DETECTOR_SIDE_PX}",
                g.nx, g.ny
            ));
        }
        if !(g.pixscale_arcsec <= 10.0) {
            return err(format!(
                "geometry.pixscale_arcsec = {} must be in (0, 10]",
                g.pixscale_arcsec
            ));
        }
        let side = MAX_DETECTOR_SIDE_PX as f64;
        for (name, v) in [
            ("geometry.eo_offset_px[0]", g.eo_offset_px[0]),
            ("geometry.eo_offset_px[1]", g.eo_offset_px[1]),
            ("geometry.jitter_step_px", g.jitter_step_px),
        ] {
            if !(v.abs() <= side) {
                return err(format!("{name} = {v} must be in [-{side}, {side}]"));
            }
        }
        if self.angles.parity != 1 && self.angles.parity != -1 {
            return err(format!("angles.parity = {} must be +1 or -1", self.angles.parity));
        }
        modulation::validate(self).or_else(err)
    }

    /// The profile seen through a crop to detector rows `[r0, r1)`: row ranges shift by
    /// -r0 and are clipped (strips outside the crop become empty); `ny = r1 - r0`.
    pub fn cropped_rows(&self, r0: usize, r1: usize) -> Profile {
        let mut p = self.clone();
        let g = &mut p.geometry;
        let n = r1.saturating_sub(r0);
        let shift = |r: &mut [usize; 2]| {
            let a = r[0].saturating_sub(r0).min(n);
            let b = r[1].saturating_sub(r0).min(n);
            *r = [a, b.max(a)];
        };
        for r in [
            &mut g.o_sky2,
            &mut g.e_sky2,
            &mut g.o_target,
            &mut g.e_target,
            &mut g.o_sky1,
            &mut g.e_sky1,
        ] {
            shift(r);
        }
        g.ny = n;
        p
    }

    /// Keyword name of `INS OPTIi ID`.
    pub fn opti_key(&self, i: u32) -> String {
        format!("{}{} ID", self.keywords.opti_prefix, i)
    }
}

/// Reads averaged in the frame: the profile's NDIT keyword, 1 when absent (an error when
/// present but not a positive integer).
pub fn frame_ndit(frame: &Frame, profile: &Profile) -> Result<u32> {
    let key = &profile.keywords.ndit;
    if !frame.header.contains(key) {
        return Ok(1);
    }
    let v = frame.header.get_i64(key)?;
    if v < 1 || v > u32::MAX as i64 {
        return Err(Error::BadKeyword {
            path: frame.header.path.clone(),
            keyword: key.clone(),
            value: v.to_string(),
            reason: "NDIT must be a positive integer".into(),
        });
    }
    Ok(v as u32)
}

/// A value given on the command line (`--set`, `--param`) as TOML reads it (`4`, `true`,
/// `"x"`, `[1, 2]`, `{ kind = "moffat" }`), else as a bare string (`median`).
pub fn toml_value(text: &str) -> toml::Value {
    match format!("x = {text}").parse::<toml::Table>() {
        Ok(mut t) => t.remove("x").unwrap_or_else(|| toml::Value::String(text.to_string())),
        Err(_) => toml::Value::String(text.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The mirror's values are checked by name: NaN, out of range, a non-boolean switch or an
    /// unknown key is refused naming the key; a filter is found ignoring case and blanks.
    #[test]
    fn hostile_telescope_values_are_refused_by_key() {
        let p = Profile::sofi();
        assert!(p.telescope.polarizes);
        assert_eq!(p.telescope.index(" ks ").map(|i| i.n), Some(2.661));
        assert!(p.telescope.index("NB2.17").is_none());
        assert_eq!(
            p.photometry.extinction("Ks"),
            0.0,
            "no unverified extinction by default"
        );
        let k = p.with_overrides(&["photometry.filters.Ks=0.07".into()]).unwrap();
        assert_eq!(
            (k.photometry.extinction(" ks "), k.photometry.extinction("J")),
            (0.07, 0.0)
        );
        for (set, key) in [
            ("telescope.relative_width=nan", "telescope.relative_width"),
            ("telescope.relative_width=0", "telescope.relative_width"),
            ("telescope.sigma_psi_deg=-1", "telescope.sigma_psi_deg"),
            ("telescope.incidence_deg=90", "telescope.incidence_deg"),
            ("telescope.psi_deg=inf", "telescope.psi_deg"),
            ("telescope.filters.Ks.n=nan", "telescope.filters.Ks"),
            ("telescope.filters.Ks.k=-2", "telescope.filters.Ks"),
            (
                "telescope.filters.Ks.wavelength_um=0",
                "telescope.filters.Ks.wavelength_um",
            ),
            ("telescope.polarizes=3", "polarizes"),
            ("telescope.mirror=1", "mirror"),
            (
                "photometry.extinction_mag_per_airmass=nan",
                "photometry.extinction_mag_per_airmass = NaN",
            ),
            (
                "photometry.extinction_mag_per_airmass=-0.1",
                "photometry.extinction_mag_per_airmass = -0.1",
            ),
            ("photometry.filters.Ks=3", "photometry.filters.Ks = 3"),
            ("photometry.k=1", "k"),
        ] {
            let e = p.with_overrides(&[set.to_string()]).expect_err(set).to_string();
            assert!(e.contains(key), "{set}: {e}");
        }
        let twice = p.with_overrides(&[
            "telescope.filters.KS.n=2.6".into(),
            "telescope.filters.KS.k=21.0".into(),
            "telescope.filters.KS.wavelength_um=2.2".into(),
        ]);
        assert!(twice.expect_err("Ks twice").to_string().contains("given twice"));
        let off = p.with_overrides(&["telescope.polarizes=false".into()]).unwrap();
        assert!(!off.telescope.polarizes);
    }

    #[test]
    fn embedded_profile_matches_frame_format_contract() {
        let p = Profile::sofi();
        assert_eq!(p.geometry.o_target, [345, 512]);
        assert_eq!(p.geometry.e_target, [512, 679]);
        assert_eq!(p.geometry.eo_offset_px, [0.0, 167.0]);
        assert_eq!(p.detector.gain_e_per_adu, 5.4);
        assert_eq!(p.keywords.posang, "ESO ADA POSANG");
        assert_eq!(p.opti_key(3), "ESO INS OPTI3 ID");
        // Strips are contiguous, 167 px each.
        let s = p.geometry.strips();
        for w in s.windows(2) {
            assert_eq!(w[0].1[1], w[1].1[0]);
        }
        for (_, r) in s {
            assert_eq!(r[1] - r[0], p.geometry.strip_height_px);
        }
    }

    #[test]
    fn parallactic_angle_is_the_mean_of_start_and_end_along_the_shorter_arc() {
        let kw = Profile::sofi().keywords;
        let h = |start: Option<f64>, end: Option<f64>| {
            let mut h = crate::header::Header::new("f.fits");
            if let Some(v) = start {
                h.set(&kw.parang, v);
            }
            if let Some(v) = end {
                h.set(&kw.parang_end, v);
            }
            h
        };
        let eta = |s, e| kw.parallactic_angle_deg(&h(s, e)).unwrap();
        assert_eq!(eta(Some(-157.1), Some(-156.9)), Some(-157.0));
        // Through +-180 (transit south of the zenith): the mean is 180, not 0.
        assert_eq!(eta(Some(-179.0), Some(179.0)), Some(180.0));
        assert_eq!(eta(Some(170.0), Some(-170.0)), Some(180.0));
        assert_eq!(eta(Some(10.0), None), Some(10.0));
        assert_eq!(eta(None, Some(10.0)), None);
        let mut bad = h(Some(1.0), None);
        bad.set(&kw.parang_end, "north");
        let err = kw.parallactic_angle_deg(&bad).unwrap_err().to_string();
        assert!(err.contains("PARANG END"), "{err}");
        // Out of range, or an end too far from the start: refused by keyword, value short.
        let e = |s, e| kw.parallactic_angle_deg(&h(s, e)).unwrap_err().to_string();
        let err = e(Some(1e300), Some(80.0));
        assert!(
            err.contains("PARANG START = 1e300") && err.contains("[-360, 360]"),
            "{err}"
        );
        let err = e(Some(80.0), Some(-400.0));
        assert!(err.contains("PARANG END = -400"), "{err}");
        let err = e(Some(10.0), Some(150.0));
        assert!(
            err.contains("PARANG END = 150") && err.contains("140.0 deg from"),
            "{err}"
        );
        // 90 deg apart along the shorter arc is still an exposure (near the zenith).
        assert_eq!(eta(Some(-135.0), Some(135.0)), Some(180.0));
        assert_eq!(eta(Some(360.0), Some(0.0)), Some(0.0));
    }

    #[test]
    fn partial_override_merges_and_validates() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("o.toml");
        std::fs::write(&f, "[detector]\ngain_e_per_adu = 6.0\n").unwrap();
        let p = Profile::sofi_with_override(&f).unwrap();
        assert_eq!(p.detector.gain_e_per_adu, 6.0);
        assert_eq!(p.detector.read_noise_e, 11.3);
        std::fs::write(&f, "[angles]\nparity = 2\n").unwrap();
        let e = Profile::sofi_with_override(&f).unwrap_err().to_string();
        assert!(e.contains("parity") && e.contains("o.toml"), "{e}");
    }

    #[test]
    fn unknown_keys_in_set_and_profile_are_rejected_by_name() {
        // Regression: a misspelt key in --set or --profile was silently ignored.
        let e = Profile::sofi()
            .with_overrides(&["detector.gian_e_per_adu=6".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("gian_e_per_adu") && e.contains("--set"), "{e}");
        let e = Profile::sofi()
            .with_overrides(&["detectr.gain_e_per_adu=6".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("detectr"), "{e}");
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("o.toml");
        std::fs::write(&f, "[detector]\nsaturation = 30000.0\n").unwrap();
        let e = Profile::sofi_with_override(&f).unwrap_err().to_string();
        assert!(e.contains("saturation") && e.contains("o.toml"), "{e}");
        // Non-finite values are named too.
        for set in [
            "detector.nonlin_coeff_per_adu=nan",
            "angles.zero_point_deg=inf",
            "geometry.jitter_step_px=nan",
        ] {
            let e = Profile::sofi().with_overrides(&[set.into()]).unwrap_err().to_string();
            assert!(e.contains(set.split('=').next().unwrap()), "{set}: {e}");
        }
        // Known keys still work.
        let p = Profile::sofi()
            .with_overrides(&["detector.gain_e_per_adu=6".into()])
            .unwrap();
        assert_eq!(p.detector.gain_e_per_adu, 6.0);
    }

    #[test]
    fn geometry_answers_from_the_strips() {
        let g = Profile::sofi().geometry;
        // Each strip's rows belong to its beam; the rows between and outside are masked.
        for (name, [a, b]) in g.strips() {
            let want = if name.starts_with("o_") {
                Beam::Ordinary
            } else {
                Beam::Extraordinary
            };
            for y in [a, (a + b) / 2, b - 1] {
                assert_eq!(g.beam_of_row(y), Some(want), "{name} row {y}");
            }
        }
        assert_eq!(g.beam_of_row(0), None);
        assert_eq!(g.beam_of_row(1013), None);
        assert_eq!(g.beam_of_row(g.ny - 1), None);
        assert_eq!(g.target_rows(Beam::Ordinary), [345, 512]);
        assert_eq!(g.target_rows(Beam::Extraordinary), [512, 679]);
        assert_eq!(g.measured_rows(), [345, 679]);
        assert_eq!(g.lit_rows_end(), 1013);
        assert_eq!(g.e_image_of((500.0, 400.0)), (500.0, 567.0));
        // The beam of every row agrees with the strip list, row by row.
        for y in 0..g.ny {
            let in_o = g
                .strips()
                .iter()
                .any(|(n, r)| n.starts_with("o_") && y >= r[0] && y < r[1]);
            let in_e = g
                .strips()
                .iter()
                .any(|(n, r)| n.starts_with("e_") && y >= r[0] && y < r[1]);
            let want = match (in_o, in_e) {
                (true, false) => Some(Beam::Ordinary),
                (false, true) => Some(Beam::Extraordinary),
                (false, false) => None,
                (true, true) => unreachable!("strips overlap at row {y}"),
            };
            assert_eq!(g.beam_of_row(y), want, "row {y}");
            assert_eq!(g.row_in_strip(y), want.is_some(), "row {y}");
        }
    }

    /// Without a focal mask every row sees sky and no row has a beam of its own; the
    /// target's rows are the whole detector; the pointing centres the pair of images; the
    /// e image of any position is at the offset vector. With the mask, nothing changes.
    #[test]
    fn geometry_without_a_mask_answers_for_the_whole_detector() {
        let p = Profile::sofi()
            .with_overrides(&[
                "geometry.mask=false".into(),
                "geometry.nx=512".into(),
                "geometry.ny=400".into(),
                "geometry.eo_offset_px=[24.0, -19.0]".into(),
            ])
            .unwrap();
        let g = &p.geometry;
        assert!(!g.has_mask());
        assert_eq!(g.strips(), vec![(WHOLE_DETECTOR, [0, 400])]);
        assert!((0..400).all(|y| g.row_in_strip(y) && g.beam_of_row(y).is_none()));
        assert!(!g.row_in_strip(400));
        assert_eq!(g.target_rows(Beam::Ordinary), [0, 400]);
        assert_eq!(g.target_rows(Beam::Extraordinary), [0, 400]);
        assert_eq!(g.measured_rows(), [0, 400]);
        assert_eq!(g.lit_rows_end(), 400);
        // The pair (o at the pointing, e at the pointing + offset) is centred on the
        // detector's centre ((nx - 1)/2, (ny - 1)/2).
        let (x, y) = g.pointing_px();
        let (xe, ye) = g.e_image_of((x, y));
        assert_eq!(((x + xe) / 2.0, (y + ye) / 2.0), (255.5, 199.5));
        // The mask's keys are not written when the mask is there (SOFI's profile text and
        // anything serialized from it unchanged), and are when it is not.
        let sofi = toml::to_string(&Profile::sofi()).unwrap();
        assert!(!sofi.contains("mask"), "{sofi}");
        assert!(toml::to_string(&p).unwrap().contains("mask = false"));
        let s = Profile::sofi();
        assert_eq!(s.geometry.pointing_px(), (512.0, 428.0));
    }

    /// Hostile geometries are refused naming the key and the value.
    #[test]
    fn hostile_geometry_is_refused_by_key_and_value() {
        for (sets, want) in [
            (
                vec!["geometry.eo_offset_px=[0.0, 1024.0]"],
                "geometry.eo_offset_px[1] = 1024",
            ),
            (
                vec!["geometry.eo_offset_px=[-2000.0, 1.0]"],
                "geometry.eo_offset_px[0] = -2000",
            ),
            (
                vec!["geometry.mask=false", "geometry.eo_offset_px=[0.5, 1.0]"],
                "geometry.eo_offset_px = [0.5, 1]",
            ),
            (
                vec![
                    "geometry.mask=false",
                    "geometry.nx=64",
                    "geometry.eo_offset_px=[80.0, 0.0]",
                ],
                "geometry.eo_offset_px[0] = 80",
            ),
            (
                vec!["geometry.o_target=[300, 520]"],
                "geometry.e_sky2 = [178, 345) and geometry.o_target = [300, 520) overlap",
            ),
            (vec!["geometry.e_sky1=[846, 1100]"], "geometry.e_sky1 = [846, 1100)"),
            (vec!["geometry.mask=1"], "mask"),
        ] {
            let sets: Vec<String> = sets.into_iter().map(String::from).collect();
            let e = Profile::sofi()
                .with_overrides(&sets)
                .expect_err(&sets.join(" "))
                .to_string();
            assert!(e.contains(want), "{sets:?}: {e}");
        }
        // Without a mask the strip keys are not read: strips beyond a small detector pass.
        let p = Profile::sofi()
            .with_overrides(&[
                "geometry.mask=false".into(),
                "geometry.ny=256".into(),
                "geometry.eo_offset_px=[10.0, 10.0]".into(),
            ])
            .unwrap();
        assert_eq!(p.geometry.lit_rows_end(), 256);
    }

    #[test]
    fn cropping_shifts_the_strips() {
        let p = Profile::sofi().cropped_rows(345, 679);
        assert_eq!(p.geometry.o_target, [0, 167]);
        assert_eq!(p.geometry.e_target, [167, 334]);
        assert_eq!(p.geometry.o_sky2[1] - p.geometry.o_sky2[0], 0);
        assert_eq!(p.geometry.e_sky1[1] - p.geometry.e_sky1[0], 0);
        assert_eq!(p.geometry.ny, 334);
        assert!(p.geometry.row_in_strip(0) && !p.geometry.row_in_strip(334));
    }

    #[test]
    fn set_overrides() {
        let p = Profile::sofi()
            .with_overrides(&["detector.gain_e_per_adu=7.5".into(), "angles.zero_point_deg=12".into()])
            .unwrap();
        assert_eq!(p.detector.gain_e_per_adu, 7.5);
        assert_eq!(p.angles.zero_point_deg, 12.0);
    }
}
