//! The half-wave-plate reduction's own results in the catalog (`sofipol night --profile
//! nirc2`, [`crate::single_pointing`]): each target's cycles, their agreement, the least
//! squares, the instrument-frame values and every frame's measurement
//! and the night's dark, sky and flat frames it was reduced with ([`HalfWavePlateResult`],
//! `Target.half_wave_plate`; absent from a SOFI catalog). The files not used are the
//! catalog's `failures`. docs/instruments.md ("The catalog") describes every key.
use serde::{Deserialize, Serialize};

/// The analyzer zero point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ZeroPoint {
    /// theta0, deg.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub deg: f64,
    /// Its 1-sigma uncertainty, deg: a systematic error of every angle on the sky, not in
    /// the angles' statistical errors.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_deg: f64,
    /// Where it comes from.
    pub source: String,
}

/// A file not used.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NotUsed {
    /// The file.
    pub file: String,
    /// Why.
    pub reason: String,
}

/// Linear polarization with its errors.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pol {
    /// Stokes q (fraction).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub q: f64,
    /// Stokes u.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub u: f64,
    /// 1-sigma error of q adopted: for a cycle or the cycles' combination the larger of the
    /// propagated and the scatter error; for a least squares the propagated error, scaled by
    /// sqrt(chi2/dof) only when chi2 lies beyond its 99th percentile.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_q: f64,
    /// 1-sigma error of u adopted.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_u: f64,
    /// The error propagated from the photometry alone, q.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_q_photometric: f64,
    /// The same, u.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_u_photometric: f64,
    /// P = sqrt(q^2 + u^2) (not debiased).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub p: f64,
    /// Its first-order error (from sigma_q, sigma_u).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_p: f64,
    /// The angle, 0.5 atan2(u, q), deg in [0, 180).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub angle_deg: f64,
    /// Its statistical error, deg (0.5 sigma_p / p).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_angle_deg: f64,
}

impl Pol {
    /// From q, u, the adopted errors and the photometric ones: P, its first-order error, the
    /// angle and its statistical error.
    pub fn new(q: f64, u: f64, sq: f64, su: f64, sq_phot: f64, su_phot: f64) -> Pol {
        let p = q.hypot(u);
        let sp = if p > 0.0 {
            ((q * sq).powi(2) + (u * su).powi(2)).sqrt() / p
        } else {
            sq.hypot(su)
        };
        Pol {
            q,
            u,
            sigma_q: sq,
            sigma_u: su,
            sigma_q_photometric: sq_phot,
            sigma_u_photometric: su_phot,
            p,
            sigma_p: sp,
            angle_deg: (0.5 * u.atan2(q).to_degrees()).rem_euclid(180.0),
            sigma_angle_deg: if p > 0.0 {
                (0.5 * sp / p).to_degrees().min(90.0)
            } else {
                90.0
            },
        }
    }
}

/// One beam's sky fit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SkyFit {
    /// Scale of the sky frame (1 for an annulus sky).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub scale: f64,
    /// Offset, ADU (the annulus median for an annulus sky).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub offset_adu: f64,
    /// Robust rms of the residuals, ADU.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_adu: f64,
    /// Pixels used.
    pub pixels: usize,
}

/// One science frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameResult {
    /// The file.
    pub file: String,
    /// Plate angle (header), deg.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub plate_deg: f64,
    /// MJD.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub mjd: f64,
    /// The analyzer's turn from the instrument to the sky (field rotation), deg.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sky_offset_deg: f64,
    /// Centre of the o image, (x, y) px 0-based.
    #[serde(deserialize_with = "crate::nullable::fixed_pair")]
    pub o_centre: [f64; 2],
    /// Centre of the e image.
    #[serde(deserialize_with = "crate::nullable::fixed_pair")]
    pub e_centre: [f64; 2],
    /// e - o, (dx, dy) px.
    #[serde(deserialize_with = "crate::nullable::fixed_pair")]
    pub eo_offset: [f64; 2],
    /// Sky of the o beam.
    pub sky_o: SkyFit,
    /// Sky of the e beam.
    pub sky_e: SkyFit,
    /// The farthest pixel above the linear limit from either centre, px (0: none).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub saturation_radius_px: f64,
    /// o flux, ADU (summed over the coadds, flat-fielded).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub o: f64,
    /// Its error.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_o: f64,
    /// e flux.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub e: f64,
    /// Its error.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_e: f64,
    /// F = (o - e)/(o + e).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub f: f64,
    /// Its error.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_f: f64,
    /// Pixels repaired as cosmic-ray hits in the o and e apertures
    /// ([`crate::single_pointing::cosmic`]); the fluxes and F above are after the repair.
    #[serde(default)]
    pub cosmic_ray_pixels: [usize; 2],
}

/// One complete plate cycle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CycleResult {
    /// Its files at plate 0, 22.5, 45, 67.5 deg.
    pub frames: Vec<String>,
    /// Double difference, instrument frame.
    pub instrument: Pol,
    /// On the sky: the double difference turned by the cycle's offset, or, when the field
    /// turns within the cycle, q, u and the constant fitted at each frame's own angle.
    pub sky: Pol,
}

/// How far the complete cycles agree.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CycleAgreement {
    /// Each consecutive pair of cycles: (q_{k+1} - q_k) / sqrt(sigma_k^2 + sigma_{k+1}^2),
    /// photometric errors, in the instrument frame, or on the sky when the field turns
    /// (pupil tracking: the star's (q, u) turns in the instrument frame).
    #[serde(deserialize_with = "crate::nullable::num_list")]
    pub q_difference_sigma: Vec<f64>,
    /// The same for u.
    #[serde(deserialize_with = "crate::nullable::num_list")]
    pub u_difference_sigma: Vec<f64>,
    /// chi^2 of the cycles' q about their mean (photometric errors), n - 1 dof.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub chi2_q: f64,
    /// The same for u.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub chi2_u: f64,
    /// Degrees of freedom.
    pub dof: usize,
}

/// The least squares over every frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LeastSquares {
    /// q, u with errors scaled by sqrt(chi2/dof) when chi2 lies beyond its 99th percentile.
    pub pol: Pol,
    /// The fitted constant c of F (beam imbalance), when fitted.
    pub c: Option<f64>,
    /// Why c was not fitted (fewer than 3 distinct angles, or angles that do not determine
    /// it), when it was not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub c_not_fitted: Option<String>,
    /// chi^2.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub chi2: f64,
    /// Degrees of freedom.
    pub dof: usize,
}

/// Which of the target's results its component carries (`component_from`).
pub const FROM_CYCLES: &str = "cycles";
/// The least squares over every frame, when no plate cycle is complete.
pub const FROM_LEAST_SQUARES: &str = "least_squares";

/// One target's half-wave-plate results (`Target.half_wave_plate`): what the component's
/// q, u, P and angle were taken from, and everything else the reduction measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HalfWavePlateResult {
    /// The result the component carries: `cycles` (the complete cycles combined, on the
    /// sky) or `least_squares` (on the sky; no complete cycle).
    pub component_from: String,
    /// The analyzer zero point the angles on the sky were turned by, with its source.
    pub zero_point: ZeroPoint,
    /// The profile's name.
    pub profile: String,
    /// `half_wave_plate` or `per_file`.
    pub modulation: String,
    /// `sky_fixed`, or `pupil_tracking` with the keywords of the angle on the sky.
    pub field_rotation: String,
    /// The night's dark frames averaged into the master dark (paths).
    pub darks: Vec<String>,
    /// The night's sky frames used (paths).
    pub skies: Vec<String>,
    /// The sky frames averaged into the flat: complete plate cycles only (paths).
    pub flat_from: Vec<String>,
    /// Bad pixels of the night (dark, flat).
    pub bad_pixels: usize,
    /// Pixels of the night's sky frames repaired as cosmic-ray hits (each sky frame against
    /// the others) before the flat and the matched skies were made of them.
    #[serde(default)]
    pub sky_cosmic_ray_pixels: usize,
    /// The cycles combined, instrument frame (theta0 = 0, no instrumental polarization
    /// removed); absent without a complete cycle.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instrument: Option<Pol>,
    /// The cycles combined on the sky (zero point and field rotation applied); absent
    /// without a complete cycle.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sky: Option<Pol>,
    /// Each complete cycle.
    pub cycles: Vec<CycleResult>,
    /// How far the cycles agree (two cycles or more).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cycle_agreement: Option<CycleAgreement>,
    /// The least squares over every usable frame, instrument frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub least_squares_instrument: Option<LeastSquares>,
    /// The same on the sky.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub least_squares_sky: Option<LeastSquares>,
    /// Frames in no complete cycle (used by the least squares only).
    pub left_out: Vec<String>,
    /// Every frame measured, in time order.
    pub frames: Vec<FrameResult>,
}
