//! The scene file: observing setup, sources, and the list of effects to simulate.
//!
//! Only effects named in `effects` are simulated; a configuration section of an effect
//! that is not listed is ignored (and reported in the truth as ignored).
use serde::{Deserialize, Serialize};

use crate::error::Error;

/// Every effect the simulator knows, in the order they act on a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EffectKind {
    /// Point-spread function (Gaussian or Moffat, per-frame seeing). Without it, sources are
    /// unresolved points shared between the four nearest pixels (cloud-in-cell).
    Psf,
    /// Sky background: level, gradient, per-frame change.
    Sky,
    /// Focal-mask strips: light outside the six strips is blocked.
    Strips,
    /// Poisson noise of the photo-electrons (gain x NDIT).
    PhotonNoise,
    /// Read noise (per read, averaged over NDIT).
    ReadNoise,
    /// Hot and dead pixels, clusters, column segments (fixed on the detector).
    BadPixels,
    /// Pixel response (flat field): pixel-to-pixel and large-scale.
    FlatField,
    /// Unequal o and e beam throughput.
    Throughput,
    /// Instrumental polarization (instrument frame).
    InstrumentalPolarization,
    /// Interstellar polarization (sky frame, common to all sources of a target).
    InterstellarPolarization,
    /// Frame-to-frame transparency changes (multiply source fluxes).
    Transparency,
    /// True jitter offset differs from the header offset.
    PointingError,
    /// Cosmic-ray hits.
    CosmicRays,
    /// Detector non-linearity.
    Nonlinearity,
    /// Saturation (clipping at the profile's level).
    Saturation,
    /// Dome-flat frames (lamp on and off, one template per rotator angle) in the night;
    /// they see the same detector (pixel response, noise, bad pixels) as the science.
    DomeFlats,
    /// The instrument's true analyzer angle phi = s POSANG + theta0 differs from the
    /// profile's (angle zero-point and image parity, section `analyzer_angle`).
    AnalyzerAngle,
    /// Polarization of the telescope (the NTT's tertiary mirror, in front of the rotator):
    /// `p_tel` at `psi_tel_deg` from the vertical adds to every source and to the sky in
    /// the sky frame, turning with each frame's parallactic angle.
    TelescopePolarization,
    /// Interstellar polarization that varies across the sky (section `foreground_field`):
    /// a mean (q, u) plus a Gaussian random field of given rms and coherence scale,
    /// evaluated at each star's position and added to its (q, u) (binaries' A and B and
    /// every field star; not the standards).
    ForegroundField,
}

impl EffectKind {
    /// All effects.
    /// (New effects go at the end: an effect's index seeds its random streams.)
    pub const ALL: [EffectKind; 19] = [
        EffectKind::Psf,
        EffectKind::Sky,
        EffectKind::Strips,
        EffectKind::PhotonNoise,
        EffectKind::ReadNoise,
        EffectKind::BadPixels,
        EffectKind::FlatField,
        EffectKind::Throughput,
        EffectKind::InstrumentalPolarization,
        EffectKind::InterstellarPolarization,
        EffectKind::Transparency,
        EffectKind::PointingError,
        EffectKind::CosmicRays,
        EffectKind::Nonlinearity,
        EffectKind::Saturation,
        EffectKind::DomeFlats,
        EffectKind::AnalyzerAngle,
        EffectKind::TelescopePolarization,
        EffectKind::ForegroundField,
    ];
    /// snake_case name as used in scene files.
    pub fn name(self) -> &'static str {
        match self {
            EffectKind::Psf => "psf",
            EffectKind::Sky => "sky",
            EffectKind::Strips => "strips",
            EffectKind::PhotonNoise => "photon_noise",
            EffectKind::ReadNoise => "read_noise",
            EffectKind::BadPixels => "bad_pixels",
            EffectKind::FlatField => "flat_field",
            EffectKind::Throughput => "throughput",
            EffectKind::InstrumentalPolarization => "instrumental_polarization",
            EffectKind::InterstellarPolarization => "interstellar_polarization",
            EffectKind::Transparency => "transparency",
            EffectKind::PointingError => "pointing_error",
            EffectKind::CosmicRays => "cosmic_rays",
            EffectKind::Nonlinearity => "nonlinearity",
            EffectKind::Saturation => "saturation",
            EffectKind::DomeFlats => "dome_flats",
            EffectKind::AnalyzerAngle => "analyzer_angle",
            EffectKind::TelescopePolarization => "telescope_polarization",
            EffectKind::ForegroundField => "foreground_field",
        }
    }
    /// Index into per-effect tables.
    pub fn index(self) -> usize {
        Self::ALL.iter().position(|&k| k == self).unwrap_or(0)
    }
}

/// Observing setup shared by every target of the scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Observation {
    /// Rotator position angles, degrees.
    pub orientations_deg: Vec<f64>,
    /// Dither positions per orientation.
    pub dithers: usize,
    /// Jitter step along x, px (default: the profile's).
    pub jitter_step_px: Option<f64>,
    /// DIT, seconds.
    pub dit_s: f64,
    /// Reads averaged per frame.
    pub ndit: u32,
    /// Filter name written to the header.
    pub filter: String,
    /// -32 (float) or 16 (int with BZERO).
    pub bitpix: i32,
    /// Rice tile-compress the frames (.fz).
    pub compress: bool,
    /// UT date of the night, YYYY-MM-DD.
    pub date: String,
    /// UT of the first exposure, HH:MM:SS.
    pub start_ut: String,
    /// Overhead between exposures, seconds: exposure k of a sequence starts
    /// 20 s + k (DIT x NDIT + overhead_s) after the sequence's start.
    pub overhead_s: f64,
    /// Photometric zero-point of the simulated night: the magnitude of a source of 1 ADU
    /// per second in o+e (no extinction is simulated). A `[[standard]]` given by `mag` gets
    /// the flux `dit_s 10^(-0.4 (mag - zero_point_mag))` ADU per NDIT-averaged frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub zero_point_mag: Option<f64>,
}

impl Default for Observation {
    fn default() -> Self {
        Observation {
            orientations_deg: vec![0.0, 45.0],
            dithers: 5,
            jitter_step_px: None,
            dit_s: 10.0,
            ndit: 6,
            filter: "Ks".into(),
            bitpix: -32,
            compress: false,
            date: "1999-03-03".into(),
            start_ut: "01:00:00".into(),
            overhead_s: 15.0,
            zero_point_mag: None,
        }
    }
}

/// A field star near a target (appears in that target's frames).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldStar {
    /// Separation from the binary's primary, arcsec.
    pub separation_arcsec: f64,
    /// Position angle from the primary, degrees east of north.
    pub pa_deg: f64,
    /// Total flux (o + e), ADU per NDIT-averaged frame.
    pub flux: f64,
    /// Degree of polarization (fraction).
    #[serde(default)]
    pub p: f64,
    /// Polarization angle, degrees.
    #[serde(default)]
    pub gamma_deg: f64,
}

/// One binary target: one observing sequence (all orientations x dithers).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Binary {
    /// Object name written to OBJECT.
    pub name: String,
    /// Separation of B from A, arcsec.
    pub separation_arcsec: f64,
    /// Position angle of B from A, degrees east of north.
    pub pa_deg: f64,
    /// Total flux of A (o + e), ADU per NDIT-averaged frame.
    pub flux_a: f64,
    /// Total flux of B.
    pub flux_b: f64,
    /// Degree of polarization of A (fraction).
    pub p_a: f64,
    /// Angle of A, degrees.
    pub gamma_a_deg: f64,
    /// Degree of polarization of B.
    pub p_b: f64,
    /// Angle of B, degrees.
    pub gamma_b_deg: f64,
    /// x of A's ordinary image at zero offset (default: detector centre).
    #[serde(default)]
    pub x_px: Option<f64>,
    /// y of A's ordinary image at zero offset (default: middle of the o-target strip).
    #[serde(default)]
    pub y_px: Option<f64>,
    /// Field stars.
    #[serde(default)]
    pub field_star: Vec<FieldStar>,
    /// Right ascension, deg in [0, 360) (equator and equinox of the date; docs/simulator.md,
    /// "Pointing"). Absent: from `hour_angle_h`, else drawn from the name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ra_deg: Option<f64>,
    /// Declination, deg. Absent: drawn from the name in [-75, 5].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dec_deg: Option<f64>,
    /// Hour angle at the sequence's start, hours (instead of `ra_deg`: the RA is then
    /// LST(start) - H). Absent with `ra_deg`: drawn from the name in [-3, 3].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hour_angle_h: Option<f64>,
    /// UT of the sequence's start (TPL START), HH:MM:SS, within the 24 h from the
    /// observation's `start_ut` (an earlier clock time is on the next UT day). Absent: the
    /// sequence follows the previous one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_ut: Option<String>,
}

/// PSF settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PsfConfig {
    /// "gaussian" or "moffat".
    pub kind: PsfKind,
    /// Median seeing FWHM, arcsec.
    pub fwhm_arcsec: f64,
    /// Moffat beta.
    pub beta: f64,
    /// Per-frame seeing change: FWHM multiplied by exp(N(0, rms)).
    pub seeing_rms_frac: f64,
    /// Per-frame FWHM spread: FWHM also multiplied by a uniform draw in [1 - s, 1 + s]
    /// (0: off). Drawn independently of the seeing change and of beta.
    pub fwhm_spread_frac: f64,
    /// Per-frame Moffat beta, uniform in [lo, hi] (absent: `beta` for every frame). Real
    /// seeing changes beta independently of the FWHM (2.5-4 is typical).
    pub beta_range: Option<[f64; 2]>,
    /// Per-frame ellipticity (Moffat only): minor/major axis ratio uniform in [lo, hi],
    /// major axis at a uniform position angle (absent: circular). Real PSFs have axis
    /// ratios of 0.9-1 from guiding, wind shake and optics.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub axis_ratio_range: Option<[f64; 2]>,
}
impl Default for PsfConfig {
    fn default() -> Self {
        PsfConfig {
            kind: PsfKind::Moffat,
            fwhm_arcsec: 0.8,
            beta: 3.0,
            seeing_rms_frac: 0.1,
            fwhm_spread_frac: 0.0,
            beta_range: None,
            axis_ratio_range: None,
        }
    }
}

/// PSF profile family.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PsfKind {
    /// Circular Gaussian.
    Gaussian,
    /// Circular Moffat.
    Moffat,
}

/// Sky settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SkyConfig {
    /// Level at the detector centre, ADU per pixel.
    pub level_adu: f64,
    /// Gradient along x, ADU/px.
    pub gradient_x: f64,
    /// Gradient along y, ADU/px.
    pub gradient_y: f64,
    /// Per-frame change of the level: multiplied by (1 + N(0, rms)).
    pub frame_change_frac: f64,
}
impl Default for SkyConfig {
    fn default() -> Self {
        SkyConfig {
            level_adu: 1500.0,
            gradient_x: 0.05,
            gradient_y: -0.03,
            frame_change_frac: 0.03,
        }
    }
}

/// Bad-pixel settings (the map is fixed on the detector for the whole scene).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BadPixelConfig {
    /// Fraction of hot pixels.
    pub hot_fraction: f64,
    /// Fraction of dead pixels.
    pub dead_fraction: f64,
    /// Value of a hot pixel, ADU.
    pub hot_level_adu: f64,
    /// Number of dead clusters.
    pub clusters: usize,
    /// Cluster radius, px.
    pub cluster_radius_px: f64,
    /// Number of bad column segments.
    pub column_segments: usize,
    /// Length of a column segment, px.
    pub column_length_px: usize,
}
impl Default for BadPixelConfig {
    fn default() -> Self {
        BadPixelConfig {
            hot_fraction: 3e-4,
            dead_fraction: 3e-4,
            hot_level_adu: 20000.0,
            clusters: 4,
            cluster_radius_px: 2.5,
            column_segments: 3,
            column_length_px: 120,
        }
    }
}

/// Flat-field (pixel response) settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FlatFieldConfig {
    /// Pixel-to-pixel rms (fraction).
    pub pixel_rms: f64,
    /// Large-scale fall-off at the detector corners (fraction).
    pub vignetting: f64,
}
impl Default for FlatFieldConfig {
    fn default() -> Self {
        FlatFieldConfig {
            pixel_rms: 0.01,
            vignetting: 0.05,
        }
    }
}

/// Dome flats (the `dome_flats` effect): per rotator angle of the observation, one
/// template of lamp-on and lamp-off frames, before the science.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DomeFlatConfig {
    /// Lamp-on frames per rotator angle.
    pub frames_on: usize,
    /// Lamp-off frames per rotator angle.
    pub frames_off: usize,
    /// Lamp light per pixel, ADU (NDIT-averaged frame), before the focal mask and beams.
    pub lamp_adu: f64,
    /// Light present with the lamp off too (thermal emission of the dome), ADU per pixel.
    pub off_adu: f64,
    /// Degree of polarization of the lamp light (fraction): the o and e strips differ in
    /// level by 1 +- p cos 2(phi - angle).
    pub lamp_p: f64,
    /// Polarization angle of the lamp light in the instrument frame, deg.
    pub lamp_angle_deg: f64,
    /// DIT of a flat frame, s.
    pub dit_s: f64,
    /// NDIT of a flat frame.
    pub ndit: u32,
}
impl Default for DomeFlatConfig {
    fn default() -> Self {
        DomeFlatConfig {
            frames_on: 5,
            frames_off: 5,
            lamp_adu: 6000.0,
            off_adu: 400.0,
            lamp_p: 0.03,
            lamp_angle_deg: 20.0,
            dit_s: 2.0,
            ndit: 10,
        }
    }
}

/// Beam throughputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ThroughputConfig {
    /// Ordinary-beam transmission T_o.
    pub t_o: f64,
    /// Extraordinary-beam transmission T_e.
    pub t_e: f64,
}
impl Default for ThroughputConfig {
    fn default() -> Self {
        ThroughputConfig { t_o: 1.0, t_e: 0.97 }
    }
}

/// A polarization (degree and angle).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PolConfig {
    /// Degree (fraction).
    pub p: f64,
    /// Angle, degrees (instrument frame for instrumental, east of north for ISM).
    pub angle_deg: f64,
}
impl Default for PolConfig {
    fn default() -> Self {
        PolConfig {
            p: 0.01,
            angle_deg: 60.0,
        }
    }
}

/// Transparency settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TransparencyConfig {
    /// Lowest transparency factor; each frame draws uniformly in [min, 1].
    pub min: f64,
}
impl Default for TransparencyConfig {
    fn default() -> Self {
        TransparencyConfig { min: 0.9 }
    }
}

/// Pointing-error settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PointingConfig {
    /// rms of the true-minus-header offset per axis, px.
    pub rms_px: f64,
}
impl Default for PointingConfig {
    fn default() -> Self {
        PointingConfig { rms_px: 0.7 }
    }
}

/// Cosmic-ray settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CosmicConfig {
    /// Mean number of hits per frame.
    pub rate_per_frame: f64,
    /// Peak deposit range, ADU (in the NDIT-averaged frame).
    pub peak_adu: [f64; 2],
}
impl Default for CosmicConfig {
    fn default() -> Self {
        CosmicConfig {
            rate_per_frame: 40.0,
            peak_adu: [500.0, 5000.0],
        }
    }
}

/// Non-linearity settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct NonlinearityConfig {
    /// Coefficient c of measured = true (1 - c true); default: the profile's.
    pub coeff_per_adu: Option<f64>,
}

/// Saturation settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct SaturationConfig {
    /// Saturation level, ADU; default: the profile's.
    pub level_adu: Option<f64>,
}

/// A polarimetric standard star observed with the same template as the targets
/// (DPR CATG 'CALIB', DPR TYPE 'STD', OBJECT = its name): a single star, reduced as such.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StandardSource {
    /// Name written to OBJECT (match it to a standards-table entry).
    pub name: String,
    /// Total flux (o + e), ADU per NDIT-averaged frame (absent: from `mag`).
    #[serde(default = "crate::nullable::nan")]
    pub flux: f64,
    /// Magnitude: the flux from the observation's `zero_point_mag` (a photometric
    /// standard of the simulated night); with `flux` too, the two must agree.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mag: Option<f64>,
    /// Degree of polarization (fraction, sky frame; 0 for an unpolarized standard). No
    /// interstellar polarization is added: this is the star's total polarization.
    #[serde(default)]
    pub p: f64,
    /// Angle, degrees east of north.
    #[serde(default)]
    pub gamma_deg: f64,
    /// Right ascension, deg in [0, 360) (equator and equinox of the date; docs/simulator.md,
    /// "Pointing"). Absent: from `hour_angle_h`, else drawn from the name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ra_deg: Option<f64>,
    /// Declination, deg. Absent: drawn from the name in [-75, 5].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dec_deg: Option<f64>,
    /// Hour angle at the sequence's start, hours (instead of `ra_deg`: the RA is then
    /// LST(start) - H). Absent with `ra_deg`: drawn from the name in [-3, 3].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hour_angle_h: Option<f64>,
    /// UT of the sequence's start (TPL START), HH:MM:SS, within the 24 h from the
    /// observation's `start_ut` (an earlier clock time is on the next UT day). Absent: the
    /// sequence follows the previous one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_ut: Option<String>,
}

/// Polarization of the telescope (effect `telescope_polarization`): in the sky frame every
/// source and the sky gain `p_tel (cos 2(eta + psi_tel), sin 2(eta + psi_tel))`, eta the
/// frame's parallactic angle ([`crate::stokes::model::TelescopePolarization`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TelescopePolConfig {
    /// p_tel, fraction.
    pub p_tel: f64,
    /// psi_tel, deg from the vertical.
    pub psi_tel_deg: f64,
}
impl Default for TelescopePolConfig {
    fn default() -> Self {
        TelescopePolConfig {
            p_tel: 0.005,
            psi_tel_deg: 0.0,
        }
    }
}
impl TelescopePolConfig {
    /// The model it configures.
    pub fn model(&self) -> crate::stokes::model::TelescopePolarization {
        crate::stokes::model::TelescopePolarization {
            p_tel: self.p_tel,
            psi_tel_deg: self.psi_tel_deg,
        }
    }
}

/// The interstellar foreground as a field on the sky (effect `foreground_field`): at the
/// unit vector n of a star, `q(n) = q_mean + rms sqrt(2/M) sum_j cos(k_j . n + phi_j)` and
/// the same for u with its own modes, k_j drawn from a 3-D Gaussian of standard deviation
/// 1/coherence (radians) per axis, phi_j uniform: a Gaussian random field with the
/// Gaussian correlation `rms^2 exp(-d^2 / (2 coherence^2))`, d the chord between the two
/// positions (the angle, for small ones). See [`crate::sim::foreground`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ForegroundFieldConfig {
    /// Degree of the mean foreground polarization (fraction).
    pub p: f64,
    /// Angle of the mean, deg east of north.
    pub angle_deg: f64,
    /// rms of the fluctuations of q and of u, each (fraction).
    pub rms: f64,
    /// Coherence scale, arcsec: the correlation falls as exp(-d^2 / (2 coherence^2)). With
    /// `structure_exponent`, the outer scale of the power law instead.
    pub coherence_arcsec: f64,
    /// Absent: the Gaussian correlation above (a field smooth below the coherence scale).
    /// An exponent alpha in (0, 2): a turbulent field whose structure function
    /// `E[(q(x) - q(x + d))^2]` grows as d^alpha from [`INNER_SCALE_RATIO`] times
    /// `coherence_arcsec` up to `coherence_arcsec`, beyond which it levels off at 2 rms^2
    /// (the wavenumbers' magnitudes drawn from a power law, their directions isotropic).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub structure_exponent: Option<f64>,
    /// Fourier modes per Stokes parameter (more: closer to Gaussian, slower).
    pub modes: usize,
    /// Seed of the field's modes (absent: the scene's `seed`). Scenes simulated apart that
    /// look through the same foreground (the targets of one region) share it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}
impl Default for ForegroundFieldConfig {
    fn default() -> Self {
        ForegroundFieldConfig {
            p: 0.01,
            angle_deg: 60.0,
            rms: 0.003,
            coherence_arcsec: 60.0,
            structure_exponent: None,
            modes: 64,
            seed: None,
        }
    }
}

/// The inner scale of a power-law foreground field (`structure_exponent`) as a fraction of
/// its outer scale `coherence_arcsec`.
pub const INNER_SCALE_RATIO: f64 = 1e-3;

/// Field stars drawn per binary (section `field_population`): a cumulative K-band
/// luminosity function `N(<K) = density (area) 10^(slope (K - k_ref))` between `k_min_mag`
/// and `k_max_mag`, positions uniform over the sky the o strips see at the first rotator
/// angle and zero offset, a fraction intrinsically polarized. See
/// [`crate::sim::population`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FieldPopulationConfig {
    /// Stars per arcmin^2 brighter than `k_ref_mag`.
    pub density_per_arcmin2: f64,
    /// Reference magnitude of `density_per_arcmin2`.
    pub k_ref_mag: f64,
    /// d log10 N(<K) / dK, dex per magnitude.
    pub slope_dex_per_mag: f64,
    /// Brightest magnitude drawn.
    pub k_min_mag: f64,
    /// Faintest magnitude drawn.
    pub k_max_mag: f64,
    /// Fraction of the stars intrinsically polarized (young stars with disks).
    pub polarized_fraction: f64,
    /// Range of their intrinsic degree of polarization (fraction; angles uniform).
    pub p_polarized: [f64; 2],
    /// No field star within this distance of A or B, arcsec.
    pub exclude_arcsec: f64,
}
impl Default for FieldPopulationConfig {
    fn default() -> Self {
        FieldPopulationConfig {
            density_per_arcmin2: 0.5,
            k_ref_mag: 14.0,
            slope_dex_per_mag: 0.3,
            k_min_mag: 8.0,
            k_max_mag: 18.0,
            polarized_fraction: 0.1,
            p_polarized: [0.02, 0.10],
            exclude_arcsec: 3.0,
        }
    }
}

/// The instrument's true analyzer-angle relation (effect `analyzer_angle`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AnalyzerAngleConfig {
    /// Zero-point theta0, degrees.
    pub zero_point_deg: f64,
    /// Image parity s, +1 or -1.
    pub parity: i32,
}
impl Default for AnalyzerAngleConfig {
    fn default() -> Self {
        AnalyzerAngleConfig {
            zero_point_deg: 3.0,
            parity: 1,
        }
    }
}

/// A whole scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Scene name (used in file names).
    pub name: String,
    /// Master seed: the same scene and seed give bit-identical frames.
    #[serde(default)]
    pub seed: u64,
    /// Seed of the fixed detector maps (bad pixels, pixel response; absent: `seed`). Scenes
    /// observed with the same detector (targets and standards of one night simulated as
    /// separate scenes) share it while their noise stays independent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detector_seed: Option<u64>,
    /// Effects to simulate. Anything not listed is not simulated.
    #[serde(default)]
    pub effects: Vec<EffectKind>,
    /// Observing setup.
    #[serde(default)]
    pub observation: Observation,
    /// Targets.
    #[serde(default)]
    pub binary: Vec<Binary>,
    /// PSF settings (used only when `psf` is listed).
    #[serde(default)]
    pub psf: Option<PsfConfig>,
    /// Sky settings.
    #[serde(default)]
    pub sky: Option<SkyConfig>,
    /// Bad-pixel settings.
    #[serde(default)]
    pub bad_pixels: Option<BadPixelConfig>,
    /// Flat-field settings.
    #[serde(default)]
    pub flat_field: Option<FlatFieldConfig>,
    /// Throughput settings.
    #[serde(default)]
    pub throughput: Option<ThroughputConfig>,
    /// Instrumental polarization.
    #[serde(default)]
    pub instrumental_polarization: Option<PolConfig>,
    /// Interstellar polarization.
    #[serde(default)]
    pub interstellar_polarization: Option<PolConfig>,
    /// Transparency.
    #[serde(default)]
    pub transparency: Option<TransparencyConfig>,
    /// Pointing error.
    #[serde(default)]
    pub pointing_error: Option<PointingConfig>,
    /// Cosmic rays.
    #[serde(default)]
    pub cosmic_rays: Option<CosmicConfig>,
    /// Non-linearity.
    #[serde(default)]
    pub nonlinearity: Option<NonlinearityConfig>,
    /// Saturation.
    #[serde(default)]
    pub saturation: Option<SaturationConfig>,
    /// Dome flats (frames in the night; used only when `dome_flats` is listed).
    #[serde(default)]
    pub dome_flats: Option<DomeFlatConfig>,
    /// Standard stars (observed after the binaries, one sequence each). Sources, not an
    /// effect: every listed standard is simulated.
    #[serde(default)]
    pub standard: Vec<StandardSource>,
    /// True analyzer angle (used only when `analyzer_angle` is listed).
    #[serde(default)]
    pub analyzer_angle: Option<AnalyzerAngleConfig>,
    /// Telescope polarization (used only when `telescope_polarization` is listed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub telescope_polarization: Option<TelescopePolConfig>,
    /// Interstellar polarization varying across the sky (used only when
    /// `foreground_field` is listed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub foreground_field: Option<ForegroundFieldConfig>,
    /// Field stars drawn per binary from a K-band luminosity function (sources, not an
    /// effect: present, every binary gets its population; needs
    /// `observation.zero_point_mag`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field_population: Option<FieldPopulationConfig>,
    /// The instrument profile the scene is made for: an embedded profile's name (`sofi`,
    /// `nirc2`) or a TOML file (relative to the scene file) merged over SOFI's. Absent: the
    /// command's `--profile` (default SOFI's). A half-wave-plate profile
    /// (`modulation.kind = "half_wave_plate"`) needs the `half_wave_plate` section.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<String>,
    /// Overrides of the profile's values, `section.key=value` each (as `--set`, applied
    /// before the command's own `--set`). A reduction of the frames needs the same.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub profile_set: Vec<String>,
    /// A half-wave-plate observation (with a half-wave-plate profile only): stars observed
    /// at one pointing through the plate's positions, sky frames, darks
    /// ([`crate::sim::hwp`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub half_wave_plate: Option<super::hwp_scene::HwpConfig>,
}

/// The o+e flux per NDIT-averaged frame of DIT `dit_s` of a source of magnitude `mag` at
/// zero-point `zero_point_mag` (the magnitude of 1 ADU/s): `dit_s 10^(-0.4 (mag - ZP))`.
pub fn flux_of_magnitude(mag: f64, zero_point_mag: f64, dit_s: f64) -> f64 {
    dit_s * 10f64.powf(-0.4 * (mag - zero_point_mag))
}

impl Scene {
    /// Parse a scene from TOML text; `origin` names the source in errors.
    pub fn from_toml(text: &str, origin: &str) -> crate::error::Result<Scene> {
        let scene_err = |reason: String| Error::Scene {
            origin: origin.to_string(),
            reason,
        };
        let mut s: Scene = toml::from_str(text).map_err(|e| scene_err(e.to_string()))?;
        s.resolve_magnitudes().map_err(scene_err)?;
        s.validate().map_err(|e| match e {
            Error::Scene { reason, .. } => scene_err(reason),
            e => e,
        })?;
        Ok(s)
    }

    /// The flux of each standard given by its magnitude: `dit_s 10^(-0.4 (mag -
    /// zero_point_mag))` ADU per NDIT-averaged frame (the frames average NDIT reads of DIT
    /// seconds). Refused, naming the standard and key: a `mag` without the observation's
    /// `zero_point_mag`, a magnitude or zero-point that is not finite, a `flux` that
    /// disagrees with its `mag`, neither `flux` nor `mag`.
    pub fn resolve_magnitudes(&mut self) -> std::result::Result<(), String> {
        let (zp, dit) = (self.observation.zero_point_mag, self.observation.dit_s);
        if let Some(z) = zp.filter(|z| !z.is_finite()) {
            return Err(format!("observation: zero_point_mag = {z} must be finite"));
        }
        for st in &mut self.standard {
            let Some(m) = st.mag else {
                if st.flux.is_nan() {
                    return Err(format!(
                        "standard '{}': give flux (ADU per frame) or mag (with observation.zero_point_mag)",
                        st.name
                    ));
                }
                continue;
            };
            let Some(z) = zp else {
                return Err(format!(
                    "standard '{}': mag = {m} needs observation.zero_point_mag (the magnitude of 1 ADU/s)",
                    st.name
                ));
            };
            if !m.is_finite() {
                return Err(format!("standard '{}': mag = {m} must be finite", st.name));
            }
            let flux = flux_of_magnitude(m, z, dit);
            if !st.flux.is_nan() && (st.flux - flux).abs() > 1e-9 * flux {
                return Err(format!(
                    "standard '{}': flux = {} disagrees with mag = {m} (flux {flux} at zero_point_mag = {z}, dit_s = {dit}): give one",
                    st.name, st.flux
                ));
            }
            st.flux = flux;
        }
        Ok(())
    }

    /// Whether an effect is listed.
    pub fn has(&self, k: EffectKind) -> bool {
        self.effects.contains(&k)
    }

    /// Sections present in the file whose effect is not listed (they are ignored).
    pub fn ignored_sections(&self) -> Vec<&'static str> {
        let present = [
            (EffectKind::Psf, self.psf.is_some()),
            (EffectKind::Sky, self.sky.is_some()),
            (EffectKind::BadPixels, self.bad_pixels.is_some()),
            (EffectKind::FlatField, self.flat_field.is_some()),
            (EffectKind::Throughput, self.throughput.is_some()),
            (
                EffectKind::InstrumentalPolarization,
                self.instrumental_polarization.is_some(),
            ),
            (
                EffectKind::InterstellarPolarization,
                self.interstellar_polarization.is_some(),
            ),
            (EffectKind::Transparency, self.transparency.is_some()),
            (EffectKind::PointingError, self.pointing_error.is_some()),
            (EffectKind::CosmicRays, self.cosmic_rays.is_some()),
            (EffectKind::Nonlinearity, self.nonlinearity.is_some()),
            (EffectKind::Saturation, self.saturation.is_some()),
            (EffectKind::DomeFlats, self.dome_flats.is_some()),
            (EffectKind::AnalyzerAngle, self.analyzer_angle.is_some()),
            (EffectKind::TelescopePolarization, self.telescope_polarization.is_some()),
            (EffectKind::ForegroundField, self.foreground_field.is_some()),
        ];
        present
            .iter()
            .filter(|(k, p)| *p && !self.has(*k))
            .map(|(k, _)| k.name())
            .collect()
    }
}
