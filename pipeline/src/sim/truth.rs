//! What a simulation realised: per frame, per target, per scene (written as truth.json).
use serde::{Deserialize, Serialize};
use sofipol_calib::Frame;

use crate::stokes::model::{Polarization, TelescopePolarization};

use super::pointing::Pointing;
use super::Scene;

/// Where the telescope pointed during one exposure (written to the header as `TEL PARANG
/// START/END`, `TEL AIRM START/END`, `TEL ALT`, `LST`, `MJD-OBS`).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FramePointing {
    /// At the exposure's start.
    pub start: Pointing,
    /// At its end (DIT x NDIT later).
    pub end: Pointing,
    /// The frame's parallactic angle eta, deg: the mean of start and end along the shorter
    /// arc (as the reduction reads it from the header).
    pub parallactic_angle_deg: f64,
}

/// Where a source landed in one frame and with what fluxes (ADU, before noise).
#[derive(Debug, Clone, Serialize)]
pub struct SourceTruth {
    /// "A", "B", or "field1"...
    pub name: String,
    /// Ordinary image position (x, y), px, true (pointing error included).
    pub o_xy: [f64; 2],
    /// Extraordinary image position.
    pub e_xy: [f64; 2],
    /// Ordinary-beam flux, ADU (transparency, throughput, polarization included; before
    /// flat field and non-linearity).
    pub flux_o: f64,
    /// Extraordinary-beam flux, ADU.
    pub flux_e: f64,
}

/// Realised parameters of one frame.
#[derive(Debug, Clone, Serialize)]
pub struct FrameTruth {
    /// File name (no directory).
    pub file: String,
    /// Rotator position angle, deg.
    pub posang_deg: f64,
    /// Analyzer angle phi = s POSANG + theta0, deg.
    pub analyzer_deg: f64,
    /// Jitter offset written to the header, px.
    pub header_offset_px: [f64; 2],
    /// True jitter offset, px.
    pub true_offset_px: [f64; 2],
    /// Transparency factor applied to the sources.
    pub transparency: f64,
    /// Sky level at the detector centre, ADU (0 without sky).
    pub sky_level_adu: f64,
    /// Seeing FWHM of this frame, px (0 without psf).
    pub fwhm_px: f64,
    /// Moffat beta of this frame (0 for other profiles).
    pub beta: f64,
    /// PSF minor/major axis ratio and major-axis angle (deg from +x towards +y), when the
    /// scene asks for `axis_ratio_range`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ellipse: Option<[f64; 2]>,
    /// Sources.
    pub sources: Vec<SourceTruth>,
    /// Cosmic-ray pixels hit.
    pub cosmic_ray_pixels: usize,
    /// Time and pointing of the exposure.
    pub pointing: FramePointing,
    /// The sky-frame (q, u) the telescope added to every source of this frame (effect
    /// `telescope_polarization`, at `pointing.parallactic_angle_deg`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telescope: Option<Polarization>,
}

/// A binary component's truth.
#[derive(Debug, Clone, Serialize)]
pub struct ComponentTruth {
    /// "A" or "B".
    pub name: String,
    /// Total flux (o + e) with unit transmission, ADU.
    pub flux: f64,
    /// Intrinsic polarization.
    pub intrinsic: Polarization,
    /// What a perfect reduction should report in the sky frame: intrinsic + ISM (uniform
    /// `interstellar_polarization` and the `foreground_field` at the star; the telescope's
    /// polarization is not the star's: it is in each frame's truth).
    pub q: f64,
    /// Sky-frame u (intrinsic + ISM).
    pub u: f64,
    /// Degree of polarization of (q, u).
    pub p: f64,
    /// Angle of (q, u), deg [0, 180).
    pub gamma_deg: f64,
}

/// One target's truth.
#[derive(Debug, Clone, Serialize)]
pub struct TargetTruth {
    /// Object name.
    pub object: String,
    /// TPL START of the sequence.
    pub tpl_start: String,
    /// Right ascension, deg (the header's `RA`).
    pub ra_deg: f64,
    /// Declination, deg (`DEC`).
    pub dec_deg: f64,
    /// Separation, arcsec.
    pub separation_arcsec: f64,
    /// PA of B from A, deg.
    pub pa_deg: f64,
    /// Components A, B.
    pub components: Vec<ComponentTruth>,
    /// Frames in exposure order.
    pub frames: Vec<FrameTruth>,
    /// The foreground field (effect `foreground_field`) at A (the binary's value) and at
    /// every star.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub foreground: Option<TargetForeground>,
    /// The field stars (the scene's, then those of `field_population`), recorded when the
    /// scene lists `foreground_field` or has a `field_population`.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub field_stars: Vec<FieldStarTruth>,
}

/// The foreground field at one binary's stars.
#[derive(Debug, Clone, Serialize)]
pub struct TargetForeground {
    /// The field's q at A: the binary's foreground.
    pub q: f64,
    /// The field's u at A.
    pub u: f64,
    /// The field at A, B and every field star (`field1`... as in [`TargetTruth::field_stars`]).
    pub stars: Vec<super::foreground::StarForeground>,
}

/// One field star's truth.
#[derive(Debug, Clone, Serialize)]
pub struct FieldStarTruth {
    /// "field1"... (the frames' source names).
    pub name: String,
    /// Separation from A, arcsec.
    pub separation_arcsec: f64,
    /// Position angle from A, deg east of north.
    pub pa_deg: f64,
    /// Total flux (o + e), ADU per NDIT-averaged frame.
    pub flux: f64,
    /// K magnitude (stars drawn by `field_population`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub k_mag: Option<f64>,
    /// Intrinsic polarization.
    pub intrinsic: Polarization,
    /// Sky-frame q: intrinsic + ISM + foreground field at the star.
    pub q: f64,
    /// Sky-frame u.
    pub u: f64,
    /// Degree of (q, u).
    pub p: f64,
    /// Angle of (q, u), deg [0, 180).
    pub gamma_deg: f64,
}

/// Truth of a whole simulation (written as truth.json).
#[derive(Debug, Clone, Serialize)]
pub struct Truth {
    /// sofipol version.
    pub software: String,
    /// The scene as parsed (defaults filled in).
    pub scene: Scene,
    /// Instrument profile name.
    pub profile: String,
    /// Effects simulated.
    pub effects: Vec<&'static str>,
    /// Effect sections present but not listed (ignored).
    pub ignored_sections: Vec<&'static str>,
    /// p_tel and psi_tel of the telescope (effect `telescope_polarization`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telescope_polarization: Option<TelescopePolarization>,
    /// The foreground field's parameters (effect `foreground_field`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub foreground_field: Option<super::foreground::ForegroundFieldTruth>,
    /// The field-star population's area and expected count per binary (`field_population`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field_population: Option<FieldPopulationTruth>,
    /// Fixed detector realisations (bad-pixel counts, flat statistics...).
    pub detector: DetectorTruth,
    /// Targets.
    pub targets: Vec<TargetTruth>,
    /// Dome-flat frames (the `dome_flats` effect), in exposure order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub dome_flats: Vec<FlatFrameTruth>,
    /// Standard stars (one component "A", separation 0), in observing order after the
    /// targets.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub standards: Vec<TargetTruth>,
}

/// The field-star population of a scene.
#[derive(Debug, Clone, Serialize)]
pub struct FieldPopulationTruth {
    /// Area the o strips see, arcmin^2.
    pub area_arcmin2: f64,
    /// Expected stars per binary between k_min_mag and k_max_mag (before the exclusion
    /// around A and B).
    pub expected_per_binary: f64,
    /// The zero-point the magnitudes were converted with (`observation.zero_point_mag`).
    pub zero_point_mag: f64,
}

/// Realised parameters of one dome-flat frame.
#[derive(Debug, Clone, Serialize)]
pub struct FlatFrameTruth {
    /// File name (no directory).
    pub file: String,
    /// Rotator position angle, deg.
    pub posang_deg: f64,
    /// Lamp on (`INS LAMP1 ST` = T).
    pub lamp_on: bool,
    /// Light per pixel in the o strips and the e strips before the pixel response, ADU.
    pub level_o_adu: f64,
    /// Same for the e strips.
    pub level_e_adu: f64,
}

/// A simulated frame in memory.
#[derive(Debug, Clone)]
pub struct SimFrame {
    /// File name (no directory).
    pub file_name: String,
    /// The frame (data in ADU, header, history).
    pub frame: Frame,
    /// Its truth.
    pub truth: FrameTruth,
}

/// The detector's fixed realisations in a scene's truth (each present when its effect is
/// simulated; keys in alphabetical order, as written before this was typed).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DetectorTruth {
    /// Bad-pixel counts by kind (effect `bad_pixels`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bad_pixels: Option<serde_json::Value>,
    /// The pixel response's statistics (effect `flat_field`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flat_field: Option<FlatFieldTruth>,
    /// The instrument's own polarization added to F (effect `instrumental_polarization`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instrumental_polarization: Option<InstrumentalPolarizationTruth>,
    /// The two beams' throughputs (effect `throughput`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub throughput: Option<ThroughputTruth>,
}

impl DetectorTruth {
    /// The detector's truth of the effects `bad_pixels` (its counts by kind) and
    /// `flat_field` (the pixel response's mean and rms); the other fields left empty.
    pub fn of_pixels(bad: Option<&super::effects::BadPixelMap>, flat: Option<&ndarray::Array2<f32>>) -> DetectorTruth {
        DetectorTruth {
            bad_pixels: bad.map(|b| serde_json::to_value(&b.summary).unwrap_or_default()),
            flat_field: flat.map(|f| {
                let n = f.len() as f64;
                let mean = f.iter().map(|&v| v as f64).sum::<f64>() / n;
                let rms = (f.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n).sqrt();
                FlatFieldTruth { mean, rms }
            }),
            ..DetectorTruth::default()
        }
    }
}

impl DetectorTruth {
    /// The offset c of F the calibration should find: (T_o - T_e)/(T_o + T_e) plus the
    /// instrumental polarization along the analyzer (none without the throughput effect).
    pub fn offset_c(&self) -> Option<f64> {
        let t = self.throughput.as_ref()?;
        let p = self
            .instrumental_polarization
            .as_ref()
            .map_or(0.0, |i| i.q_inst_added_to_f);
        Some((t.t_o - t.t_e) / (t.t_o + t.t_e) + p)
    }
}

/// The simulated pixel response's mean and rms.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FlatFieldTruth {
    /// Mean response.
    pub mean: f64,
    /// Its rms.
    pub rms: f64,
}

/// The simulated instrumental polarization.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct InstrumentalPolarizationTruth {
    /// Its angle, deg.
    pub angle_deg: f64,
    /// Its degree, fraction.
    pub p: f64,
    /// What it adds to F = (o - e)/(o + e): p cos 2 angle.
    #[serde(rename = "q_inst_added_to_F")]
    pub q_inst_added_to_f: f64,
}

/// The simulated throughputs of the two beams.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ThroughputTruth {
    /// Extraordinary beam.
    pub t_e: f64,
    /// Ordinary beam.
    pub t_o: f64,
}
