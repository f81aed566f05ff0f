//! The JSON catalog: what `sofipol target` / `sofipol night` write and other tools read.
//! Schema documented in docs/catalog-schema.md; keep the two in step.
use serde::{Deserialize, Serialize};

use crate::stokes::inversion::Polarization;

pub mod applied;
pub mod calibration_state;
pub mod field_stars;
pub mod flags;
pub mod frame_quality;
pub mod half_wave_plate;
pub mod photometry;
pub mod polarimetric_calibration;
pub mod provenance;
pub use applied::AppliedCalibration;
pub use calibration_state::{CalibrationState, TermSource};
pub use field_stars::FieldStar;
pub use flags::{Flag, FlagCode};
pub use frame_quality::FrameQuality;
pub use half_wave_plate::HalfWavePlateResult;
pub use provenance::Provenance;

/// Version of the catalog schema written by this build.
pub const SCHEMA_VERSION: &str = "1.0";

/// Reduction outcome of a target.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Every stage ran and both components were measured.
    Ok,
    /// Reduced with degradation (missing frames, one component lost...): see flags.
    Partial,
    /// Nothing usable: see `error`.
    Failed,
}

/// One binary component's polarimetry.
///
/// Key order in the JSON: the fixed fields (`name`, the [`Polarization`] keys, `passes_cut`,
/// `flags`), then the optional fields in alphabetical order (declared so: serde writes
/// fields in declaration order; an absent optional field writes no key), then `extra`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Component {
    /// "A" (brighter) or "B".
    pub name: String,
    /// q, u, P, gamma and their errors (keys in the JSON as if written here; read through
    /// `Deref`: `c.q`, `c.p_debiased`).
    #[serde(flatten)]
    pub pol: Polarization,
    /// P / sigma_P > 3.
    pub passes_cut: bool,
    /// Per-source flags (e.g. `truncated`, `bad_pixels`, `saturated`, `companion_overlap`, `low_snr`).
    #[serde(default)]
    pub flags: Vec<Flag>,
    /// What was calibrated, term by term (offset c, zero-point, telescope), and how; absent
    /// before the night's calibration is applied. It decides the cut.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<CalibrationState>,
    /// Covariance of q and u, measurement and calibration together (absent when q and u
    /// are not constrained).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub cov_qu: Option<f64>,
    /// Covariance of q and u from the measurement alone (the F errors of this star).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub cov_qu_stat: Option<f64>,
    /// The dithers left out of the combined F (flagged, clipped or without a value), by
    /// frame, with the reason (absent when every dither was used).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dropped_dithers: Option<Vec<DroppedDither>>,
    /// Mean o+e flux per dither, ADU (NaN when no dither was kept).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub flux_adu: Option<f64>,
    /// The instrumental offset subtracted from F or fitted (calibration).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instrumental_offset: Option<InstrumentalOffset>,
    /// Magnitude in the target's filter from the night's photometric zero-point
    /// ([`crate::calibration::photometric`]); absent when the night has no photometric
    /// standard in that filter.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub mag: Option<f64>,
    /// d(q, u)/dc: how an error of the calibration's offset c moves this star's q and u
    /// (absent when no calibration offset was subtracted). The offset is common to every
    /// target of a night, so this is what correlates the two stars of a binary.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::pair"
    )]
    pub offset_gradient: Option<[f64; 2]>,
    /// F combined over the dithers of each orientation: what the calibration re-solves
    /// q and u from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub orientations: Option<Vec<CombinedF>>,
    /// 1-sigma error of `flux_adu`: the propagated photometric error of the mean, or the
    /// standard error of the dithers' scatter when that is larger, ADU.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_flux_adu: Option<f64>,
    /// 68.27 % half-width of the Naghizadeh-Khouei & Clarke angle distribution, deg.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_gamma_nkc_deg: Option<f64>,
    /// The angle error from the measurement alone (the F errors of this star, full q-u
    /// covariance), deg.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_gamma_stat_deg: Option<f64>,
    /// The angle error from the night's calibration (offset c and zero-point theta0 with
    /// their covariance; common to every target), deg. `sigma_gamma_deg` is the two in
    /// quadrature.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_gamma_zero_point_deg: Option<f64>,
    /// 1-sigma error of `mag`: the flux's error and the zero-point's in quadrature, mag.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_mag: Option<f64>,
    /// Error of q from the measurement alone.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_q_stat: Option<f64>,
    /// Error of u from the measurement alone.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_u_stat: Option<f64>,
    /// P / sigma_P.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub snr: Option<f64>,
    /// How q and u were solved (`least_squares`, `free_offset`, `difference`, `ratio`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stokes_method: Option<String>,
    /// d(q, u)/da and d(q, u)/db: how an error of the telescope's polarization (a, b) =
    /// p_tel (cos 2psi_tel, sin 2psi_tel) moves this star's q and u (absent when the
    /// telescope's polarization was not removed). Common to every target of a night.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::square"
    )]
    pub telescope_gradient: Option<[[f64; 2]; 2]>,
    /// The telescope's polarization removed from this star, sky frame (q_tel, u_tel) at the
    /// mean parallactic angle of its frames (absent when not removed).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::pair"
    )]
    pub telescope_qu: Option<[f64; 2]>,
    /// d(q, u)/d theta0 per deg (absent when no calibration was applied: a rotation,
    /// (-2u, 2q) pi/180, is then assumed).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::pair"
    )]
    pub zero_point_gradient: Option<[f64; 2]>,
    /// Keys this build does not know (other tools, other versions): kept as read and
    /// written after the known ones. Nothing in sofipol reads or writes them.
    #[serde(flatten, default)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

impl Component {
    /// q, u, the measurement's covariance and the offset gradient, as the Delta-gamma error
    /// needs them (the totals where the measurement's part was not recorded).
    pub fn star_qu(&self) -> crate::stokes::propagation::StarQu {
        let sq = self.sigma_q_stat.unwrap_or(self.sigma_q);
        let su = self.sigma_u_stat.unwrap_or(self.sigma_u);
        let c = self.cov_qu_stat.or(self.cov_qu).unwrap_or(0.0);
        use crate::stokes::propagation::{rotation_gradient_per_deg, StarQu, CAL_C, CAL_TEL_A, CAL_TEL_B, CAL_THETA0};
        let mut jacobian = [[0.0; 2]; 4];
        jacobian[CAL_C] = self.offset_gradient.unwrap_or([0.0, 0.0]);
        jacobian[CAL_THETA0] = self
            .zero_point_gradient
            .unwrap_or_else(|| rotation_gradient_per_deg(self.q, self.u));
        if let Some([ga, gb]) = self.telescope_gradient {
            (jacobian[CAL_TEL_A], jacobian[CAL_TEL_B]) = (ga, gb);
        }
        StarQu {
            q: self.q,
            u: self.u,
            stat: crate::stokes::propagation::QuCovariance {
                var_q: sq * sq,
                var_u: su * su,
                cov_qu: c,
            },
            jacobian,
        }
    }

    /// A component with its polarization and nothing else (no flags, no optional field).
    pub fn new(name: impl Into<String>, pol: Polarization) -> Component {
        Component {
            name: name.into(),
            pol,
            passes_cut: false,
            flags: Vec::new(),
            cov_qu: None,
            cov_qu_stat: None,
            dropped_dithers: None,
            flux_adu: None,
            instrumental_offset: None,
            mag: None,
            offset_gradient: None,
            orientations: None,
            sigma_flux_adu: None,
            sigma_gamma_nkc_deg: None,
            sigma_gamma_stat_deg: None,
            sigma_gamma_zero_point_deg: None,
            sigma_mag: None,
            sigma_q_stat: None,
            sigma_u_stat: None,
            snr: None,
            stokes_method: None,
            telescope_gradient: None,
            telescope_qu: None,
            calibration: None,
            zero_point_gradient: None,
            extra: serde_json::Map::new(),
        }
    }
}

/// A dither left out of a component's combined F.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DroppedDither {
    /// The dither's frame.
    pub file: String,
    /// Why: the dither's flags (`bad_pixels`, `cosmic_ray`, `saturated`, `truncated`,
    /// `primary_not_found`, comma-separated), `clipped` (an outlier of its orientation's
    /// dithers) or `no value`.
    pub reason: String,
}

/// F = (o - e)/(o + e) of one orientation combined over its dithers (a component's
/// `orientations` entry). The keys are in alphabetical order, as before they were typed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CombinedF {
    /// Analyzer angle of the orientation (the profile's relation), deg.
    #[serde(default = "crate::nullable::nan", deserialize_with = "crate::nullable::num")]
    pub analyzer_deg: f64,
    /// Chi-square of the kept dithers about their weighted mean.
    #[serde(default = "crate::nullable::nan", deserialize_with = "crate::nullable::num")]
    pub chi2: f64,
    /// Weighted mean of F over the kept dithers.
    #[serde(default = "crate::nullable::nan", deserialize_with = "crate::nullable::num")]
    pub f: f64,
    /// Dithers kept.
    #[serde(default)]
    pub n_dithers: usize,
    /// Dithers measured.
    #[serde(default)]
    pub n_dithers_total: usize,
    /// Weighted mean over the kept dithers of (cos 2eta, sin 2eta), eta each frame's
    /// parallactic angle, with the weights of `f`: the telescope's own polarization in this
    /// orientation's F is linear in it. Absent when a frame has no parallactic angle.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::pair"
    )]
    pub parallactic_2eta: Option<[f64; 2]>,
    /// Weighted circular mean of the kept dithers' parallactic angles, deg (for reading).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub parallactic_deg: Option<f64>,
    /// Rotator angle, deg: not written by sofipol; when a catalog has it, the calibration
    /// takes it instead of inverting `analyzer_deg` with the profile.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub posang_deg: Option<f64>,
    /// Reported error of `f` (the propagated one, inflated when the scatter is significantly larger).
    #[serde(default = "crate::nullable::nan", deserialize_with = "crate::nullable::num")]
    pub sigma_f: f64,
    /// Error of `f` propagated from the photometry.
    #[serde(default = "crate::nullable::nan", deserialize_with = "crate::nullable::num")]
    pub sigma_f_propagated: f64,
    /// Error of `f` from the dither-to-dither scatter.
    #[serde(default = "crate::nullable::nan", deserialize_with = "crate::nullable::num")]
    pub sigma_f_scatter: f64,
}

/// The instrumental offset of F applied to a component (docs/calibration.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InstrumentalOffset {
    /// Offset c of F.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub c: f64,
    /// Its error.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_c: f64,
    /// `calibration` (from standards) or `fitted` (free-offset solve).
    pub source: String,
}

impl std::ops::Deref for Component {
    type Target = Polarization;
    fn deref(&self) -> &Polarization {
        &self.pol
    }
}

impl std::ops::DerefMut for Component {
    fn deref_mut(&mut self) -> &mut Polarization {
        &mut self.pol
    }
}

/// One target sequence.
///
/// Key order in the JSON: `object`, `status`, `error`, `components`, `delta_gamma_deg`
/// (with `sigma_delta_gamma_deg` and `delta_gamma_interval_deg` when present), then
/// the optional fields in alphabetical order (declared so; an absent one writes no key),
/// then `extra`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Target {
    /// Object name.
    pub object: String,
    /// Outcome.
    pub status: Status,
    /// Error message when failed (or the main degradation when partial).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Components, A first.
    #[serde(default)]
    pub components: Vec<Component>,
    /// |gamma_A - gamma_B| folded into [0, 90] when both components pass the cut.
    #[serde(default)]
    pub delta_gamma_deg: Option<f64>,
    /// 1-sigma error of `delta_gamma_deg` (delta method): both stars' measurement
    /// covariances and the part of the offset c that does not cancel; the angle zero-point
    /// theta0 cancels and is not in it.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_delta_gamma_deg: Option<f64>,
    /// Central 68.27 % interval of the folded Delta-gamma [low, high], deg, from Monte Carlo
    /// draws of the same covariance: the one to use at low S/N, where the fold makes the
    /// distribution skewed.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::pair"
    )]
    pub delta_gamma_interval_deg: Option<[f64; 2]>,
    /// Median aperture radius, px.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub aperture_radius_px: Option<f64>,
    /// Pixels masked (calibration + detected).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bad_pixels_masked: Option<usize>,
    /// Declination of the pointing, deg: mean `DEC` of the sequence's frames (absent when
    /// the frames lack it).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub dec_deg: Option<f64>,
    /// Delta-gamma after subtracting the target's `foreground` from both components,
    /// `|gamma(q_A - q_f, u_A - u_f) - gamma(q_B - q_f, u_B - u_f)|` folded into [0, 90]
    /// deg, when both components pass the cut and the target has a valid `foreground`.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub delta_gamma_fg_corrected_deg: Option<f64>,
    /// Central 68.27 % interval of `delta_gamma_fg_corrected_deg` [low, high], deg: Monte
    /// Carlo draws of both stars, the calibration and the foreground (one draw common to
    /// both stars).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::pair"
    )]
    pub delta_gamma_fg_corrected_interval_deg: Option<[f64; 2]>,
    /// Integration time of each frame of the sequence (`DET DIT`, else `EXPTIME`), s: the
    /// frames are NDIT-averaged, so `flux_adu / dit_s` is ADU per second. Absent when the
    /// frames' times differ (no magnitude is then given) or in older catalogs.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub dit_s: Option<f64>,
    /// e-o beam offset measured from the data, [dx, dy] px.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::pair"
    )]
    pub eo_offset_px: Option<[f64; 2]>,
    /// Every other point source of the target's strips, measured like the components
    /// ([`FieldStar`]; absent when field stars were not measured, `[]` when none was found).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field_stars: Option<Vec<FieldStar>>,
    /// Filter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub filter: Option<String>,
    /// Target-level flags (docs/catalog-schema.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flags: Option<Vec<Flag>>,
    /// The flat of each orientation; `Some(None)` (JSON null) when no flat was applied.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::present"
    )]
    pub flat: Option<Option<Vec<String>>>,
    /// The interstellar (foreground) polarization towards the target, e.g. measured on
    /// field stars: used by `sofipol stats` as the binary's own foreground; absent: the
    /// sample's foreground model (docs/statistics.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub foreground: Option<Foreground>,
    /// Every frame the sequence was measured from, with its seeing, sky level, airmass and
    /// transparency (absent in catalogs written before it was kept, and for failed targets).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_quality: Option<Vec<FrameQuality>>,
    /// Median seeing FWHM, px.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub fwhm_px: Option<f64>,
    /// The half-wave-plate reduction's own results (cycles, their agreement, least squares,
    /// instrument-frame values, zero point, every frame): absent for SOFI.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub half_wave_plate: Option<HalfWavePlateResult>,
    /// Every frame of the sequence.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_files: Option<Vec<String>>,
    /// Mean MJD-OBS of the sequence's frames, d (absent when the frames lack it).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub mjd_mean: Option<f64>,
    /// Rotator angles used, deg.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::list"
    )]
    pub orientations_deg: Option<Vec<f64>>,
    /// Position angle of B from A found, deg east of north.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub pa_deg: Option<f64>,
    /// How fluxes were measured: `aperture` or `psf_fit`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photometry: Option<String>,
    /// Right ascension of the pointing, deg in [0, 360): circular mean of `RA` over the
    /// sequence's frames (absent when the frames lack it).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub ra_deg: Option<f64>,
    /// Separation of B from A found, arcsec.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub separation_arcsec: Option<f64>,
    /// Sequence id, `object@TPL START`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sequence: Option<String>,
    /// 1-sigma error of `delta_gamma_fg_corrected_deg`, deg (delta method): as
    /// `sigma_delta_gamma_deg` plus the foreground's covariance, common to both stars (it
    /// moves the two angles differently and does not cancel in the difference).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_delta_gamma_fg_corrected_deg: Option<f64>,
    /// TPL START of the sequence.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tpl_start: Option<String>,
    /// Keys this build does not know (other tools, other versions): kept as read and
    /// written after the known ones. Nothing in sofipol reads or writes them.
    #[serde(flatten, default)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

/// Interstellar (foreground) polarization towards a target, in the sky frame, fractions
/// like the components' q and u (0.01 = 1 %): a mean (q, u) and its covariance, e.g. the
/// weighted mean of field stars around the target. `sofipol stats` draws each simulated
/// pair's foreground from N((q, u), covariance) (docs/statistics.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Foreground {
    /// Foreground q.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub q: f64,
    /// Foreground u.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub u: f64,
    /// 1-sigma error of q.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_q: f64,
    /// 1-sigma error of u.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_u: f64,
    /// Covariance of q and u (0 when absent).
    #[serde(default)]
    pub cov_qu: f64,
    /// How it was measured (e.g. `field stars, n = 12, within 5 arcmin`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// Number of field stars the estimate used (absent: filled by hand or another tool).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub n_used: Option<usize>,
    /// Star-to-star dispersion of the foreground among the field stars [tau_q, tau_u]
    /// (fractions), included in sigma_q, sigma_u.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::pair"
    )]
    pub tau: Option<[f64; 2]>,
    /// The estimator, in words (`pipeline/src/foreground.rs`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<String>,
    /// The field stars not used, each with why.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rejected: Vec<RejectedFieldStar>,
}

/// A field star the foreground estimate did not use.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RejectedFieldStar {
    /// The star's identifier.
    pub id: String,
    /// Why, in words (not usable, invalid, too far, outlier with its chi-square).
    pub reason: String,
}

impl Foreground {
    /// A foreground of (q, u) with its covariance and nothing else.
    pub fn new(q: f64, u: f64, sigma_q: f64, sigma_u: f64, cov_qu: f64) -> Foreground {
        Foreground {
            q,
            u,
            sigma_q,
            sigma_u,
            cov_qu,
            source: None,
            n_used: None,
            tau: None,
            method: None,
            rejected: Vec::new(),
        }
    }

    /// Check the values, naming the key and the value: finite, sigmas >= 0,
    /// |cov_qu| <= sigma_q sigma_u.
    pub fn validate(&self) -> std::result::Result<(), String> {
        for (key, v) in [("q", self.q), ("u", self.u), ("cov_qu", self.cov_qu)] {
            if !v.is_finite() {
                return Err(format!("foreground.{key} = {v}: must be finite"));
            }
        }
        for (key, v) in [("sigma_q", self.sigma_q), ("sigma_u", self.sigma_u)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("foreground.{key} = {v}: must be finite and >= 0"));
            }
        }
        if self.cov_qu * self.cov_qu > self.sigma_q * self.sigma_q * self.sigma_u * self.sigma_u * (1.0 + 1e-9) {
            return Err(format!(
                "foreground.cov_qu = {}: exceeds sigma_q sigma_u = {}: not a covariance",
                self.cov_qu,
                self.sigma_q * self.sigma_u
            ));
        }
        if let Some(t) = self.tau {
            if !t.iter().all(|v| v.is_finite() && *v >= 0.0) {
                return Err(format!(
                    "foreground.tau = [{}, {}]: must be finite and >= 0",
                    t[0], t[1]
                ));
            }
        }
        Ok(())
    }

    /// The covariance of (q, u).
    pub fn covariance(&self) -> crate::stokes::propagation::QuCovariance {
        crate::stokes::propagation::QuCovariance {
            var_q: self.sigma_q * self.sigma_q,
            var_u: self.sigma_u * self.sigma_u,
            cov_qu: self.cov_qu,
        }
    }
}

impl Target {
    /// A target with its outcome and nothing else (no component, no optional field).
    pub fn new(object: impl Into<String>, status: Status) -> Target {
        Target {
            object: object.into(),
            status,
            error: None,
            components: Vec::new(),
            delta_gamma_deg: None,
            sigma_delta_gamma_deg: None,
            delta_gamma_interval_deg: None,
            aperture_radius_px: None,
            bad_pixels_masked: None,
            dec_deg: None,
            delta_gamma_fg_corrected_deg: None,
            delta_gamma_fg_corrected_interval_deg: None,
            dit_s: None,
            eo_offset_px: None,
            field_stars: None,
            filter: None,
            flags: None,
            flat: None,
            foreground: None,
            frame_quality: None,
            fwhm_px: None,
            half_wave_plate: None,
            input_files: None,
            mjd_mean: None,
            orientations_deg: None,
            pa_deg: None,
            photometry: None,
            ra_deg: None,
            separation_arcsec: None,
            sequence: None,
            sigma_delta_gamma_fg_corrected_deg: None,
            tpl_start: None,
            extra: serde_json::Map::new(),
        }
    }

    /// Set `delta_gamma_deg`, `sigma_delta_gamma_deg` and `delta_gamma_interval_deg` from the
    /// two components (all `None` unless there are two and both pass the cut). The error is
    /// the delta method on both stars' measurement covariances and the night's calibration
    /// `cal` (covariance of c, theta0, and the telescope's a, b), common to both stars through
    /// their Jacobians: c and the telescope's term move the two angles differently, theta0
    /// cancels ([`crate::stokes::propagation`]). `None`: no calibration was applied (the
    /// offsets the components carry, if any, are used alone). A catalog written before the
    /// measurement covariances were kept apart falls back on the totals.
    ///
    /// With a valid `foreground` (f, C_f) it also sets the `*_fg_corrected_*` fields: the
    /// same on (q - q_f, u - u_f) of both stars, with C_f common to both
    /// ([`crate::stokes::propagation::sigma_delta_gamma_with_foreground_deg`]); an invalid
    /// foreground leaves them absent.
    pub fn update_delta_gamma(&mut self, cal: Option<&crate::stokes::propagation::CalibrationCovariance>) {
        use crate::stokes::propagation::{
            delta_gamma_interval_deg, delta_gamma_interval_with_foreground_deg, sigma_delta_gamma_deg,
            sigma_delta_gamma_with_foreground_deg,
        };
        (
            self.delta_gamma_deg,
            self.sigma_delta_gamma_deg,
            self.delta_gamma_interval_deg,
        ) = (None, None, None);
        (
            self.delta_gamma_fg_corrected_deg,
            self.sigma_delta_gamma_fg_corrected_deg,
            self.delta_gamma_fg_corrected_interval_deg,
        ) = (None, None, None);
        let [a, b] = self.components.as_slice() else { return };
        if !(a.passes_cut && b.passes_cut) {
            return;
        }
        self.delta_gamma_deg = Some(fold_delta_gamma(a.gamma_deg, b.gamma_deg));
        let cal = cal.copied().unwrap_or_else(|| {
            let var_c = [a, b]
                .iter()
                .filter(|c| c.offset_gradient.is_some())
                .filter_map(|c| c.instrumental_offset.as_ref())
                .map(|o| o.sigma_c * o.sigma_c)
                .fold(0.0, f64::max);
            crate::stokes::propagation::offset_covariance(var_c)
        });
        let (sa, sb) = (a.star_qu(), b.star_qu());
        let sigma = sigma_delta_gamma_deg(&sa, &sb, &cal);
        if sigma.is_finite() {
            self.sigma_delta_gamma_deg = Some(sigma);
            self.delta_gamma_interval_deg = Some(delta_gamma_interval_deg(&sa, &sb, &cal));
        }
        let Some(fg) = self.foreground.as_ref().filter(|f| f.validate().is_ok()) else {
            return;
        };
        let (ca, cb) = (sa.minus_foreground(fg.q, fg.u), sb.minus_foreground(fg.q, fg.u));
        let fg_cov = fg.covariance();
        self.delta_gamma_fg_corrected_deg = self.fg_corrected_delta_gamma();
        let sigma = sigma_delta_gamma_with_foreground_deg(&ca, &cb, &cal, &fg_cov);
        if sigma.is_finite() {
            self.sigma_delta_gamma_fg_corrected_deg = Some(sigma);
            self.delta_gamma_fg_corrected_interval_deg =
                Some(delta_gamma_interval_with_foreground_deg(&ca, &cb, &cal, &fg_cov));
        }
    }

    /// Delta-gamma of the two components after subtracting the target's foreground from
    /// both (q, u), folded into [0, 90] deg: None without two components or a valid
    /// foreground. What [`Target::update_delta_gamma`] stores and `stats` recomputes.
    pub fn fg_corrected_delta_gamma(&self) -> Option<f64> {
        let [a, b] = self.components.as_slice() else {
            return None;
        };
        let fg = self.foreground.as_ref().filter(|f| f.validate().is_ok())?;
        let (ca, cb) = (
            a.star_qu().minus_foreground(fg.q, fg.u),
            b.star_qu().minus_foreground(fg.q, fg.u),
        );
        let d = fold_delta_gamma(ca.gamma_deg(), cb.gamma_deg());
        d.is_finite().then_some(d)
    }

    /// The sequence id, or the object name when the catalog has none: what identifies a
    /// target in a night (merge, figure names, calibration).
    pub fn sequence_id(&self) -> &str {
        self.sequence.as_deref().unwrap_or(&self.object)
    }

    /// The target-level flags (none when the catalog has no `flags`).
    pub fn target_flags(&self) -> &[Flag] {
        self.flags.as_deref().unwrap_or_default()
    }
}

/// An input that could not be used.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Failure {
    /// File name.
    pub file: String,
    /// Reason.
    pub error: String,
}

/// A whole catalog.
#[derive(Debug, Clone, Serialize, Deserialize, Default)]
pub struct Catalog {
    /// Schema version.
    #[serde(default)]
    pub schema_version: String,
    /// Targets.
    pub targets: Vec<Target>,
    /// Unusable inputs.
    #[serde(default)]
    pub failures: Vec<Failure>,
    /// Provenance: software version, command line, profile, parameters...
    #[serde(default)]
    pub provenance: Provenance,
    /// Standard stars of the night, reduced as single stars (docs/catalog-schema.md).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub standards: Vec<StandardResult>,
    /// The instrumental calibration applied to the targets (`calibration.json`'s content
    /// and where it came from).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<AppliedCalibration>,
}

/// A standard star's table values, its measurement and the residuals.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StandardResult {
    /// Name in the standards table (the OBJECT when not in the table).
    pub name: String,
    /// OBJECT (or OBS TARG NAME) of the sequence.
    pub object: String,
    /// Sequence id.
    pub sequence: String,
    /// Filter.
    pub filter: String,
    /// Outcome of the reduction.
    pub status: Status,
    /// Table values (absent when the star is not in the table).
    #[serde(default)]
    pub table: Option<crate::standards::StandardStar>,
    /// Measured polarization (sky frame, calibration applied), when measured.
    #[serde(default)]
    pub measured: Option<Component>,
    /// (P - p_table) / sqrt(sigma_P,stat^2 + sigma_p_table^2), polarized standards only
    /// (sigma_P,stat: the measurement's error without the calibration's).
    #[serde(default)]
    pub residual_p_sigma: Option<f64>,
    /// gamma - gamma_table folded into [-90, 90), deg (polarized standards only).
    #[serde(default)]
    pub residual_gamma_deg: Option<f64>,
    /// The angle residual in units of the combined error (measurement and table errors).
    #[serde(default)]
    pub residual_gamma_sigma: Option<f64>,
    /// chi^2 of the measured (q, u) against 0 with their statistical covariance plus the
    /// table's sigma_p^2/2 in each, 2 dof (unpolarized standards).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub residual_qu_chi2: Option<f64>,
    /// What the calibration used it for: "offset", "angles".
    #[serde(default)]
    pub used_for: Vec<String>,
    /// Flags (`not_in_standards_table`, `no_table_values_for_filter`, ...).
    #[serde(default)]
    pub flags: Vec<Flag>,
    /// Right ascension of the pointing, deg (as [`Target::ra_deg`]).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub ra_deg: Option<f64>,
    /// Declination of the pointing, deg (as [`Target::dec_deg`]).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub dec_deg: Option<f64>,
    /// Integration time of each frame, s (as [`Target::dit_s`]).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub dit_s: Option<f64>,
    /// Mean MJD-OBS of the sequence's frames, d (as [`Target::mjd_mean`]).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub mjd_mean: Option<f64>,
    /// The sequence's frames (as [`Target::input_files`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_files: Option<Vec<String>>,
    /// Each frame's seeing, sky level, airmass and transparency (as [`Target::frame_quality`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_quality: Option<Vec<FrameQuality>>,
}

/// Fold an angle difference of two axial angles (degrees) into [0, 90].
pub fn fold_delta_gamma(gamma_a_deg: f64, gamma_b_deg: f64) -> f64 {
    let d = (gamma_a_deg - gamma_b_deg).rem_euclid(180.0);
    if d > 90.0 {
        180.0 - d
    } else {
        d
    }
}

#[cfg(test)]
mod tests;
