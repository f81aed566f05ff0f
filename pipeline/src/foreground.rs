//! The interstellar foreground of a binary estimated from the field stars around it, and
//! the catalog's `foreground` filled from it.
//!
//! Interstellar polarization adds one (q, u) vector to both components of a binary and
//! pulls their angles together: a fake alignment. The field stars of the same frames lie
//! behind (nearly) the same dust, so their calibrated (q, u), in the sky frame like the
//! components', measure it. This module is pure arithmetic on a list of field-star
//! measurements ([`FieldStarQu`]); it does not find or measure stars.
//!
//! # The model
//!
//! Field star j (position x_j) measures
//!
//! ```text
//! y_j = f + e(x_j) + n_j,     n_j ~ N(0, S_j)  (its own measurement covariance)
//!                             e(x) ~ N(0, T),  T = diag(tau_q^2, tau_u^2)
//! ```
//!
//! f the mean foreground of the field, e(x) its variation from place to place (the dust is
//! patchy; tau is that star-to-star dispersion: a random-effects model). The binary sees
//! f_b = f + e(x_b), one more draw of the same variation. Estimated:
//!
//! - tau_q and tau_u each from its restricted (REML) likelihood times a flat prior on
//!   0 <= tau <= [`TAU_PRIOR_MAX`] (0.5 % per q and u, the assumed largest variation of the
//!   foreground within one 5-arcmin field): the posterior means E[tau^2] and E[error of
//!   the mean] ([`tau_posterior`]). A point estimate (Paule-Mandel, REML) is often 0 when
//!   only a few field stars are more precise than tau, and the prediction is then too
//!   narrow (measured: pull rms 1.75 over the simulated fields below); the posterior mean
//!   carries the uncertainty of tau into the covariance;
//! - f by the inverse-variance weighted mean with 2 x 2 weights W_j = (S_j + T)^-1, T at
//!   E[tau^2] (a star's cov_qu enters), `f_hat = (sum W_j)^-1 sum W_j y_j`, the error of the
//!   mean `C_mean = (sum W_j)^-1`, its variances scaled to the posterior means;
//! - the random-effects prediction at the binary: f_hat, with the covariance
//!   `C = C_mean + E[T]`, the error of the mean plus the variation between the field
//!   stars' places and the binary's. It is calibrated on average over fields whose tau is
//!   within the prior's range and whose places are independent (pull rms 1.00 over 3000
//!   simulated fields with tau uniform in 0-0.5 %). It is kept in the estimate
//!   (`random_effects`) and used for the outlier clip; the prediction reported is the
//!   kriging's (next section). A field known to be uniform can assume tau = 0
//!   ([`Dispersion::None`]): then the weighted mean and its error of the mean are reported.
//!
//! # The prediction at the binary: kriging ([`kriging`])
//!
//! With weights w_j (summing to one per coordinate) and a foreground field e(x) of
//! covariance K(x, x') (stationary: K(x, x) = s^2), the error at the binary is
//! `f_hat - f_b = sum_j w_j n_j + sum_j w_j e(x_j) - e(x_b)`, of variance
//!
//! ```text
//! V = sum_j w_j^2 S_j + sum_jk w_j w_k K(x_j, x_k) - 2 sum_j w_j K(x_j, x_b) + s^2.
//! ```
//!
//! Independent places give `C_mean + T`, the random-effects covariance. A field correlated
//! over the strip (dust varies smoothly) with the binary at the strip's centre, nearer its
//! stars than they are to each other on average, makes that an upper bound: against the
//! simulator's random field (rms 0.3 %) its pulls have an rms of 1.10 at a coherence scale
//! of 20", 0.66 at 90", 0.39 at 600". So the stars' kept (q, u) are kriged (each of q and u
//! on its own; their errors correlate through each star's cov_qu): a semivariogram of a
//! nugget t (independent from place to place) plus a power law (s^2 at 5 arcmin), the
//! weights those of ordinary kriging, the REML likelihood of (t, s) on a grid, the
//! prediction and its variance the posterior mixture over (t, s). Stars near the binary
//! weigh more when the field shows structure; with none, the prediction is the
//! random-effects mean. At most [`kriging::MAX_STARS`] stars, the nearest, are used (the
//! others are listed as not used: [`Rejection::NotNearest`]). A plane across the field as
//! drift was tried: on simulated nights its two more parameters cost more than they gave
//! (end to end: pulls 0.78 and a Delta-gamma rms of 10.6 deg against 0.89 and 9.1 without).
//!
//! # The night's fields
//!
//! 5-30 stars cannot tell a nugget from a smooth field: for one field alone the posterior
//! of (t, s) is nearly its flat prior, and the mixture is as conservative as the
//! random-effects covariance (pulls 0.58 at 90"; [`estimate`]). The binaries of one night
//! lie behind dust of similar structure, so [`estimate_night`] lets the night's other
//! fields inform each field's prior: their likelihoods of (t, s, alpha) (q and u of each
//! field) give the nonparametric maximum-likelihood distribution over the grid (EM), mixed
//! with the flat prior ([`kriging::night_prior`]). The flat prior's share is chosen by how
//! well the other fields predict each other (each one's marginal likelihood under the
//! mixture of the rest; the field that most prefers the flat prior is not counted, and a
//! near tie goes to the smaller share: [`kriging::share_from_scores`]): a night whose
//! fields look alike leans on them, one whose fields differ keeps the flat prior; it is in
//! the estimate's method. A field's own data, and those of every field within [`SAME_FIELD_ARCMIN`] of it (the same binary again, or a
//! neighbour sharing its stars), are left out of its prior, and at least
//! [`MIN_OTHER_FIELDS`] others are needed. The calibration gives each filter's fields
//! alone. Measured against the simulator's field, nights of 6 fields: pull rms 1.06 at 20",
//! 0.97 at 90", 0.86 at 600"; through turbulent fields (outer scale 600", structure-function
//! exponent 0.7, 1 and 5/3): 1.11, 1.07, 0.92; end to end through `sofipol night` (rms
//! 0.4 %, 90", 16 nights of 6 binaries): 0.91, and 1.07 on 16 more (0.89 on the first 16
//! with the plain sum's best share, every predicted field counted). With the share fixed
//! at 1/(n + 1) (the flat prior weighing as one field) these were 1.02, 0.86, 0.73; 0.96, 0.90, 0.78; 0.83: too
//! wide for smooth fields, the flat prior's mass at large variations, which a field of
//! 6-24 stars cannot exclude, entering every field's error. One night's prior is common to
//! its fields: a night whose other fields happen to look smoother than this one makes its
//! errors too small. A night with fewer than 3 targets with field stars, and `sofipol
//! target`, have the flat prior.
//!
//! # Outliers
//!
//! Young stars of a star-forming region are intrinsically polarized by their own disks
//! and envelopes (1-10 % in K): their (q, u) is not the foreground. They are rejected by a
//! robust, iterated chi-square clip: start from a dispersion from the normalised residuals
//! about the per-coordinate medians (which the outliers do not inflate) and from the centre,
//! among the medians and every star's own (q, u), of highest likelihood when each star is
//! the foreground or, with probability [`OUTLIER_FRACTION`], a star polarized by
//! [`OUTLIER_SCALE`] of its own (the median alone counts stars, not their precision); a
//! star is an outlier when `chi2_j = r_j^T (S_j + T)^-1 r_j` exceeds the 2-degree-of-freedom
//! quantile of probability [`CLIP_PROBABILITY`] (13.8: a good star is lost once in 1000);
//! then refit on the kept stars and re-test every star against the fit, until the set no
//! longer changes. Each rejected star is returned with its reason ([`Rejection`]).
//!
//! A precise star among noisy ones is not clipped when it is polarized itself: the noisy
//! stars cannot contradict it enough, and the kriging leans on it with a weight near 1 (on
//! end-to-end nights: the foreground 9-17 sigma off, three binaries of 96). So the kept
//! star of largest weight, when it carries at least [`DOMINANT_WEIGHT`], is weighed as
//! possibly polarized: from its residual against the kriging's prediction at its own place
//! from the other stars, the same mixture gives the posterior probability p that it is
//! polarized ([`probability_polarized`]), and the prediction at the binary is the mixture of
//! the one with it (1 - p) and the one without it (p): mean and covariance of the two-part
//! mixture. The star, its weight and p are in the estimate ([`DominantStar`]) and its method.
//!
//! # Too few
//!
//! Fewer than [`MIN_FIELD_STARS`] (5) stars left: no estimate ([`Outcome::TooFew`]). The
//! restricted likelihood of n stars falls as tau^-(n-1) for large tau, so E[tau^2] is
//! finite without a bound only from n = 5 on (below, the covariance would be set by the
//! prior's bound alone), and a median of 4 cannot tell one young star from the foreground.
use std::fmt;

use crate::catalog::{Flag, FlagCode, Foreground, RejectedFieldStar, Target};
use crate::numeric::median_in_place;
use crate::stokes::propagation::{CalibrationCovariance, QuCovariance};

/// The fewest field stars kept (after the rejections) for an estimate (module doc: the
/// dispersion's degrees of freedom and the robust start).
pub const MIN_FIELD_STARS: usize = 5;

/// Probability that a star of the foreground, measured with its stated errors, is clipped:
/// the clip is at the chi-square (2 degrees of freedom) quantile `-2 ln p` = 13.82.
pub const CLIP_PROBABILITY: f64 = 1e-3;

/// Largest number of clip-and-refit rounds (the kept set usually settles in 2-3).
pub const MAX_CLIP_ROUNDS: usize = 20;

/// The method in words, as written in the catalog's `foreground.method`.
pub fn method_text(params: &EstimateParams) -> String {
    let tau = match params.dispersion {
        Dispersion::Estimated { tau_max } => format!(
            "outliers clipped against a random-effects mean (tau per q and u from its REML posterior, flat prior up to {} %); the foreground at the binary by Bayesian ordinary kriging of each of q and u (semivariogram nugget + power law of exponent 0.5-1.9, REML on a grid up to {} %), covariance = the posterior mixture's",
            100.0 * tau_max,
            100.0 * tau_max
        ),
        Dispersion::None => {
            "weighted mean, no dispersion assumed (tau = 0), covariance = error of the mean".to_string()
        }
    };
    format!("field stars: {tau}, chi-square clip p = {}", params.clip_probability)
}

/// One field star's calibrated polarization (sky frame, fractions like the components' q
/// and u: 0.01 = 1 %), with its measurement covariance and place.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldStarQu {
    /// Identifier (e.g. the star's number or position), quoted in the rejections.
    pub id: String,
    /// q.
    pub q: f64,
    /// u.
    pub u: f64,
    /// 1-sigma error of q.
    pub sigma_q: f64,
    /// 1-sigma error of u.
    pub sigma_u: f64,
    /// Covariance of q and u.
    pub cov_qu: f64,
    /// Right ascension, deg.
    pub ra_deg: f64,
    /// Declination, deg.
    pub dec_deg: f64,
    /// False when the measurement flagged the star unusable (saturated, blended, at the
    /// edge...): it is not used and is listed as rejected.
    pub usable: bool,
}

/// Settings of the estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EstimateParams {
    /// Stars farther than this from the binary are not used (None: all).
    pub max_separation_arcmin: Option<f64>,
    /// See [`CLIP_PROBABILITY`].
    pub clip_probability: f64,
    /// Whether the foreground's star-to-star dispersion tau is estimated.
    pub dispersion: Dispersion,
}

/// The foreground's variation from place to place.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Dispersion {
    /// Estimated from the field (module doc), tau at most `tau_max` (a fraction; the
    /// default [`TAU_PRIOR_MAX`]).
    Estimated {
        /// The largest tau the prior allows, per q and u.
        tau_max: f64,
    },
    /// Assumed zero: the field stars' own errors alone (a uniform foreground known from
    /// elsewhere). The covariance is then only the error of the mean.
    None,
}

impl Default for EstimateParams {
    fn default() -> Self {
        EstimateParams {
            max_separation_arcmin: None,
            clip_probability: CLIP_PROBABILITY,
            dispersion: Dispersion::Estimated { tau_max: TAU_PRIOR_MAX },
        }
    }
}

/// Why a field star was not used.
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    /// The measurement flagged it unusable.
    NotUsable,
    /// A non-finite q, u, position or error, or an error <= 0, or |cov_qu| >= sigma_q sigma_u.
    InvalidMeasurement,
    /// Farther from the binary than the limit.
    TooFar {
        /// Its separation, arcmin.
        separation_arcmin: f64,
        /// The limit, arcmin.
        limit_arcmin: f64,
    },
    /// Kept, but beyond the [`kriging::MAX_STARS`] nearest to the binary that the
    /// prediction uses.
    NotNearest {
        /// Its separation, arcmin.
        separation_arcmin: f64,
        /// How many nearer stars were used.
        used: usize,
    },
    /// Its (q, u) is not the foreground's (an intrinsically polarized star).
    Outlier {
        /// Its chi-square against the foreground (2 degrees of freedom).
        chi2: f64,
        /// The clip level.
        limit: f64,
    },
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Rejection::NotUsable => write!(f, "flagged unusable by its measurement"),
            Rejection::InvalidMeasurement => {
                write!(
                    f,
                    "invalid measurement (non-finite value, error <= 0 or |cov_qu| >= sigma_q sigma_u)"
                )
            }
            Rejection::TooFar {
                separation_arcmin,
                limit_arcmin,
            } => write!(
                f,
                "{separation_arcmin:.2} arcmin from the binary, beyond {limit_arcmin} arcmin"
            ),
            Rejection::NotNearest {
                separation_arcmin,
                used,
            } => write!(
                f,
                "{separation_arcmin:.2} arcmin from the binary: beyond the {used} nearest stars the prediction uses"
            ),
            Rejection::Outlier { chi2, limit } => write!(
                f,
                "outlier: chi2 = {chi2:.1} against the foreground (2 dof) above {limit:.1}: intrinsically polarized"
            ),
        }
    }
}

/// The foreground at the binary.
#[derive(Debug, Clone, PartialEq)]
pub struct ForegroundEstimate {
    /// Foreground q at the binary.
    pub q: f64,
    /// Foreground u at the binary.
    pub u: f64,
    /// Prediction covariance at the binary: error of the mean + the foreground's variation.
    pub cov: QuCovariance,
    /// The error of the field's mean alone, `(sum W_j)^-1`.
    pub cov_mean: QuCovariance,
    /// The random-effects prediction: the weighted mean and its covariance error of the
    /// mean + E[tau^2] (the binary as one more independent place of the field).
    pub random_effects: ([f64; 2], QuCovariance),
    /// The spatial model's parameters (None when the dispersion is not estimated).
    pub spatial: Option<Spatial>,
    /// Star-to-star dispersion of the foreground, q and u (tau, fractions).
    pub tau: [f64; 2],
    /// Ids of the stars used.
    pub used: Vec<String>,
    /// Ids of the stars not used, with why.
    pub rejected: Vec<(String, Rejection)>,
    /// Largest separation of a used star from the binary, arcmin.
    pub max_separation_arcmin: f64,
    /// The method in words ([`method_text`]).
    pub method: String,
    /// The star the prediction leaned on most, when it carried at least
    /// [`DOMINANT_WEIGHT`], and the chance that it is polarized itself.
    pub dominant: Option<DominantStar>,
}

/// The result of an estimate.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// An estimate from at least [`MIN_FIELD_STARS`] stars.
    Estimated(Box<ForegroundEstimate>),
    /// Fewer than [`MIN_FIELD_STARS`] stars left: no estimate.
    TooFew {
        /// Stars left after the rejections.
        n_left: usize,
        /// The minimum.
        minimum: usize,
        /// Ids of the stars not used, with why.
        rejected: Vec<(String, Rejection)>,
    },
}

/// Angular separation, arcmin (haversine).
pub fn separation_arcmin(ra1_deg: f64, dec1_deg: f64, ra2_deg: f64, dec2_deg: f64) -> f64 {
    let (d1, d2) = (dec1_deg.to_radians(), dec2_deg.to_radians());
    let dra = (ra2_deg - ra1_deg).to_radians();
    let h = (0.5 * (d2 - d1)).sin().powi(2) + d1.cos() * d2.cos() * (0.5 * dra).sin().powi(2);
    (2.0 * h.sqrt().min(1.0).asin()).to_degrees() * 60.0
}

fn valid(s: &FieldStarQu) -> bool {
    [s.q, s.u, s.ra_deg, s.dec_deg, s.cov_qu].iter().all(|v| v.is_finite())
        && s.sigma_q > 0.0
        && s.sigma_u > 0.0
        && s.sigma_q.is_finite()
        && s.sigma_u.is_finite()
        && s.cov_qu.abs() < s.sigma_q * s.sigma_u
}

/// Inverse of a symmetric 2 x 2 [var_q, cov, var_u].
fn inv2(m: [f64; 3]) -> [f64; 3] {
    let det = m[0] * m[2] - m[1] * m[1];
    [m[2] / det, -m[1] / det, m[0] / det]
}

/// One star's residual, covariance and value in the fit.
#[derive(Clone, Copy)]
struct Obs {
    y: [f64; 2],
    s: [f64; 3],
}

/// What the field says about one coordinate's dispersion tau: the posterior means of
/// tau^2 and of the variance of the weighted mean (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TauPosterior {
    /// E[tau^2 | data].
    pub tau2: f64,
    /// E[(sum_j 1/(sigma_j^2 + tau^2))^-1 | data]: the error of the field's mean.
    pub var_mean: f64,
}

/// The largest star-to-star dispersion of the foreground allowed by the prior, per q and u.
pub const TAU_PRIOR_MAX: f64 = 0.005;

/// Points of the tau grid of [`tau_posterior`] (log-spaced, plus tau = 0).
pub const TAU_GRID: usize = 400;

/// The restricted (REML) log-likelihood of tau^2 = `t` for values `y` with variances `v`:
/// `-1/2 [sum ln(v_j + t) + ln sum w_j + sum w_j (y_j - ybar_w)^2]`, w_j = 1/(v_j + t).
pub fn reml_log_likelihood(y: &[f64], v: &[f64], t: f64) -> f64 {
    let w: Vec<f64> = v.iter().map(|vi| 1.0 / (vi + t)).collect();
    let sw: f64 = w.iter().sum();
    let mean = w.iter().zip(y).map(|(w, y)| w * y).sum::<f64>() / sw;
    let q: f64 = w.iter().zip(y).map(|(w, y)| w * (y - mean) * (y - mean)).sum();
    -0.5 * (w.iter().map(|w| -w.ln()).sum::<f64>() + sw.ln() + q)
}

/// The posterior of tau for values `y` with variances `v` (at least 2): the restricted
/// likelihood times a flat prior on tau >= 0, integrated by the trapezoid rule on tau = 0
/// and [`TAU_GRID`] points log-spaced from 10^-4 to 10^2 times the scale of the data
/// (their plain standard deviation plus the largest error). The likelihood falls as
/// tau^-(n-1), so E[tau^2] is finite from n = 5 on ([`MIN_FIELD_STARS`]).
pub fn tau_posterior(y: &[f64], v: &[f64], tau_max: f64) -> TauPosterior {
    let n = y.len() as f64;
    let ybar = y.iter().sum::<f64>() / n;
    let sd = (y.iter().map(|y| (y - ybar).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
    let scale = sd + v.iter().copied().fold(0.0, f64::max).sqrt();
    let taus: Vec<f64> = std::iter::once(0.0)
        .chain((0..TAU_GRID).map(|i| scale * 10f64.powf(-4.0 + 6.0 * i as f64 / (TAU_GRID - 1) as f64)))
        .filter(|t| *t <= tau_max)
        .chain(std::iter::once(tau_max).filter(|t| t.is_finite()))
        .collect();
    let logl: Vec<f64> = taus.iter().map(|t| reml_log_likelihood(y, v, t * t)).collect();
    let top = logl.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let (mut z, mut e_t2, mut e_vm) = (0.0, 0.0, 0.0);
    for i in 1..taus.len() {
        let dt = taus[i] - taus[i - 1];
        for j in [i - 1, i] {
            let p = 0.5 * dt * (logl[j] - top).exp();
            let t2 = taus[j] * taus[j];
            let vm = 1.0 / v.iter().map(|vi| 1.0 / (vi + t2)).sum::<f64>();
            z += p;
            e_t2 += p * t2;
            e_vm += p * vm;
        }
    }
    TauPosterior {
        tau2: e_t2 / z,
        var_mean: e_vm / z,
    }
}

/// The random-effects fit of the kept stars: mean, its covariance, the posteriors of
/// tau (q, u).
struct Fit {
    mean: [f64; 2],
    cov_mean: [f64; 3],
    tau2: [f64; 2],
    post: [TauPosterior; 2],
}

fn fit(obs: &[Obs], dispersion: Dispersion) -> Fit {
    let yq: Vec<f64> = obs.iter().map(|o| o.y[0]).collect();
    let yu: Vec<f64> = obs.iter().map(|o| o.y[1]).collect();
    let vq: Vec<f64> = obs.iter().map(|o| o.s[0]).collect();
    let vu: Vec<f64> = obs.iter().map(|o| o.s[2]).collect();
    let post = match dispersion {
        Dispersion::Estimated { tau_max } => [tau_posterior(&yq, &vq, tau_max), tau_posterior(&yu, &vu, tau_max)],
        Dispersion::None => [&vq, &vu].map(|v| TauPosterior {
            tau2: 0.0,
            var_mean: 1.0 / v.iter().map(|v| 1.0 / v).sum::<f64>(),
        }),
    };
    let tau2 = [post[0].tau2, post[1].tau2];
    let (mut sw, mut swy) = ([0.0; 3], [0.0; 2]);
    for o in obs {
        let w = inv2([o.s[0] + tau2[0], o.s[1], o.s[2] + tau2[1]]);
        for k in 0..3 {
            sw[k] += w[k];
        }
        swy[0] += w[0] * o.y[0] + w[1] * o.y[1];
        swy[1] += w[1] * o.y[0] + w[2] * o.y[1];
    }
    let c = inv2(sw);
    Fit {
        mean: [c[0] * swy[0] + c[1] * swy[1], c[1] * swy[0] + c[2] * swy[1]],
        cov_mean: c,
        tau2,
        post,
    }
}

fn chi2(o: &Obs, centre: [f64; 2], tau2: [f64; 2]) -> f64 {
    let w = inv2([o.s[0] + tau2[0], o.s[1], o.s[2] + tau2[1]]);
    let (dq, du) = (o.y[0] - centre[0], o.y[1] - centre[1]);
    w[0] * dq * dq + 2.0 * w[1] * dq * du + w[2] * du * du
}

/// The variances of coordinate `k` (0 q, 1 u) of the kept stars.
fn kept_var<'a>(obs: &'a [Obs], keep: &'a [bool], k: usize) -> impl Iterator<Item = f64> + 'a {
    obs.iter().zip(keep).filter(|(_, k)| **k).map(move |(o, _)| o.s[2 * k])
}

/// Median of a chi-square with 1 degree of freedom.
const CHI2_1_MEDIAN: f64 = 0.454_936_423_119_572_8;

/// The robust start, per coordinate: the median as centre, and tau^2 such that the median
/// of the normalised squared residuals `r_j^2 / (sigma_j^2 + tau^2)` is that of a
/// chi-square with 1 degree of freedom (0 when it is below already): a robust
/// Paule-Mandel, which a minority of outliers does not inflate and which, unlike the
/// median absolute deviation, does not mistake the scatter of the noisiest stars for the
/// foreground's.
fn robust_start(obs: &[Obs]) -> ([f64; 2], [f64; 2]) {
    let mut centre = [0.0; 2];
    let mut tau2 = [0.0; 2];
    for k in 0..2 {
        let mut y: Vec<f64> = obs.iter().map(|o| o.y[k]).collect();
        let m = median_in_place(&mut y);
        let r2: Vec<f64> = obs.iter().map(|o| (o.y[k] - m).powi(2)).collect();
        let med = |t: f64| {
            let mut z: Vec<f64> = obs.iter().zip(&r2).map(|(o, r2)| r2 / (o.s[2 * k] + t)).collect();
            median_in_place(&mut z)
        };
        centre[k] = m;
        if med(0.0) <= CHI2_1_MEDIAN {
            continue;
        }
        let (mut lo, mut hi) = (0.0, r2.iter().copied().fold(0.0, f64::max) / CHI2_1_MEDIAN);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if med(mid) > CHI2_1_MEDIAN {
                lo = mid;
            } else {
                hi = mid;
            }
            if hi - lo <= 1e-12 * hi {
                break;
            }
        }
        tau2[k] = 0.5 * (lo + hi);
    }
    (centre, tau2)
}

/// Typical intrinsic polarization of a young field star per q and u (a fraction): the width
/// of the outliers' part of the start's mixture (`best_start`).
pub const OUTLIER_SCALE: f64 = 0.05;

/// Share of intrinsically polarized stars the start's mixture assumes.
pub const OUTLIER_FRACTION: f64 = 0.1;

/// ln of a 2-D normal density of the residual `r` with covariance [var_q, cov, var_u].
fn ln_normal2(r: [f64; 2], c: [f64; 3]) -> f64 {
    let det = c[0] * c[2] - c[1] * c[1];
    let w = inv2(c);
    let chi2 = w[0] * r[0] * r[0] + 2.0 * w[1] * r[0] * r[1] + w[2] * r[1] * r[1];
    -0.5 * chi2 - 0.5 * det.ln() - (2.0 * std::f64::consts::PI).ln()
}

/// The log-likelihood of the centre `c` when each star is the foreground (covariance
/// S_j + T) with probability 1 - [`OUTLIER_FRACTION`] or an intrinsically polarized star
/// (S_j + T + [`OUTLIER_SCALE`]^2 per coordinate) otherwise.
fn mixture_log_likelihood(obs: &[Obs], c: [f64; 2], tau2: [f64; 2]) -> f64 {
    let (good, bad) = ((1.0 - OUTLIER_FRACTION).ln(), OUTLIER_FRACTION.ln());
    let p2 = OUTLIER_SCALE * OUTLIER_SCALE;
    obs.iter()
        .map(|o| {
            let r = [o.y[0] - c[0], o.y[1] - c[1]];
            let cov = [o.s[0] + tau2[0], o.s[1], o.s[2] + tau2[1]];
            let a = good + ln_normal2(r, cov);
            let b = bad + ln_normal2(r, [cov[0] + p2, cov[1], cov[2] + p2]);
            let m = a.max(b);
            m + ((a - m).exp() + (b - m).exp()).ln()
        })
        .sum()
}

/// The posterior probability that a star is intrinsically polarized, from its residual
/// against the prediction at its place without it and that residual's covariance
/// (prediction + measurement): the start's mixture ([`OUTLIER_FRACTION`] of stars
/// polarized by [`OUTLIER_SCALE`] per coordinate).
pub fn probability_polarized(residual: [f64; 2], cov: [f64; 3]) -> f64 {
    let p2 = OUTLIER_SCALE * OUTLIER_SCALE;
    let a = (1.0 - OUTLIER_FRACTION).ln() + ln_normal2(residual, cov);
    let b = OUTLIER_FRACTION.ln() + ln_normal2(residual, [cov[0] + p2, cov[1], cov[2] + p2]);
    let p = 1.0 / (1.0 + (a - b).exp());
    if p.is_finite() {
        p
    } else {
        0.0
    }
}

/// The clip's starting centre: of the per-coordinate medians and every star's own (q, u),
/// the one of highest [`mixture_log_likelihood`] (dispersion `tau2`). The plain median
/// counts stars, not their precision: with one or two precise stars among many noisy
/// ones, it sits where the noisy ones scatter, and the clip then throws out the precise
/// star that shows the foreground (seen on simulated frames: the foreground at the binary
/// off by 3 sigma). The mixture weighs each star by its errors and lets the noisy stars
/// decide between two precise stars that disagree.
fn best_start(obs: &[Obs], median: [f64; 2], tau2: [f64; 2]) -> [f64; 2] {
    let mut best = (mixture_log_likelihood(obs, median, tau2), median);
    for o in obs {
        let l = mixture_log_likelihood(obs, o.y, tau2);
        if l > best.0 {
            best = (l, o.y);
        }
    }
    best.1
}

/// Estimate the foreground at the binary (`ra_deg`, `dec_deg`) from its field stars
/// (module doc: the model, the clip, the minimum), its field alone (flat priors on the
/// foreground's variation; [`estimate_night`] lets a night's fields inform each other).
pub fn estimate(ra_deg: f64, dec_deg: f64, stars: &[FieldStarQu], params: &EstimateParams) -> Outcome {
    finish(prepare(ra_deg, dec_deg, stars, params), None)
}

/// The foregrounds of a night's binaries, each (`ra_deg`, `dec_deg`, its field stars):
/// every field's kriging likelihood of the foreground's variation (t, s) enters the
/// night's distribution of it ([`kriging::night_prior`]), which is then each field's prior
/// (module doc, "The night's fields"). Give each filter's fields on their own: the
/// foreground's size differs between filters. The outcomes are in the order of `fields`.
pub fn estimate_night(fields: &[(f64, f64, &[FieldStarQu])], params: &EstimateParams) -> Vec<Outcome> {
    use rayon::prelude::*;
    let prepared: Vec<Prepared> = fields
        .par_iter()
        .map(|(ra, dec, stars)| prepare(*ra, *dec, stars, params))
        .collect();
    // Each field's q and u likelihood grids, by field.
    let grids: Vec<Vec<Vec<f64>>> = prepared
        .iter()
        .map(|p| match p {
            Prepared::Ready(r) => r
                .grids
                .as_ref()
                .map(|g| g.iter().map(|c| c.iter().map(|p| p.logl).collect()).collect())
                .unwrap_or_default(),
            Prepared::Done(_) => Vec::new(),
        })
        .collect();
    let ln_prior: Option<Vec<f64>> = prepared.iter().find_map(|p| match p {
        Prepared::Ready(r) => r.grids.as_ref().map(|g| g[0].iter().map(|p| p.ln_prior).collect()),
        Prepared::Done(_) => None,
    });
    // Each field's prior from the night's other fields: its own data are in its
    // likelihood already, and a field within SAME_FIELD_ARCMIN of it (the same binary
    // observed again, another filter's sequence of it, a neighbour sharing its stars) holds
    // nearly the same data, so it is left out too. Fewer than MIN_OTHER_FIELDS others: the
    // flat prior.
    prepared
        .into_par_iter()
        .enumerate()
        .map(|(f, p)| {
            let near = |a: usize, b: usize| {
                separation_arcmin(fields[a].0, fields[a].1, fields[b].0, fields[b].1) < SAME_FIELD_ARCMIN
            };
            let others: Vec<usize> = (0..grids.len())
                .filter(|&g| g != f && !grids[g].is_empty() && !near(f, g))
                .collect();
            let prior = match &ln_prior {
                Some(lp) if others.len() >= MIN_OTHER_FIELDS => {
                    let other_grids: Vec<&[Vec<f64>]> = others.iter().map(|&g| grids[g].as_slice()).collect();
                    Some((
                        kriging::night_prior(&other_grids, |a, b| near(others[a], others[b]), lp),
                        others.len(),
                    ))
                }
                _ => None,
            };
            finish(p, prior.as_ref())
        })
        .collect()
}

/// Fields closer than this to a field (arcmin: a SOFI field is 4.9 arcmin across) share its
/// field stars and are left out of its prior.
pub const SAME_FIELD_ARCMIN: f64 = 5.0;

/// Fewest other fields for a night's prior (fewer: the flat prior). One other field's
/// likelihood alone would make a prior nearly as sharp as a measurement of this field's
/// variation.
pub const MIN_OTHER_FIELDS: usize = 2;

/// A field's estimate up to the night's prior: the outcome itself when the field cannot
/// give one, else the kept stars' fits and kriging grids.
enum Prepared {
    Done(Box<Outcome>),
    Ready(Box<Ready>),
}

/// What [`finish`] needs of one field.
struct Ready {
    params: EstimateParams,
    cov_mean: QuCovariance,
    random_effects: ([f64; 2], QuCovariance),
    tau2: [f64; 2],
    /// The kriging grids of q and u (None when the dispersion is not estimated).
    grids: Option<[Vec<kriging::GridPoint>; 2]>,
    /// The star the prediction leans on most, when it carries at least [`DOMINANT_WEIGHT`].
    dominant: Option<Dominant>,
    /// Each used star's cov_qu, in the grids' order.
    cov_qu: Vec<f64>,
    used: Vec<String>,
    rejected: Vec<(String, Rejection)>,
    max_sep: f64,
}

fn prepare(ra_deg: f64, dec_deg: f64, stars: &[FieldStarQu], params: &EstimateParams) -> Prepared {
    let mut rejected: Vec<(usize, Rejection)> = Vec::new();
    let mut candidates: Vec<usize> = Vec::new();
    for (i, s) in stars.iter().enumerate() {
        if !s.usable {
            rejected.push((i, Rejection::NotUsable));
        } else if !valid(s) {
            rejected.push((i, Rejection::InvalidMeasurement));
        } else {
            let sep = separation_arcmin(ra_deg, dec_deg, s.ra_deg, s.dec_deg);
            match params.max_separation_arcmin {
                Some(limit) if !(sep <= limit) => rejected.push((
                    i,
                    Rejection::TooFar {
                        separation_arcmin: sep,
                        limit_arcmin: limit,
                    },
                )),
                _ => candidates.push(i),
            }
        }
    }
    let obs: Vec<Obs> = candidates
        .iter()
        .map(|&i| {
            let s = &stars[i];
            Obs {
                y: [s.q, s.u],
                s: [s.sigma_q * s.sigma_q, s.cov_qu, s.sigma_u * s.sigma_u],
            }
        })
        .collect();
    let limit = -2.0 * params.clip_probability.ln();
    let too_few = |n_left: usize, mut rejected: Vec<(usize, Rejection)>| {
        rejected.sort_by_key(|r| r.0);
        Outcome::TooFew {
            n_left,
            minimum: MIN_FIELD_STARS,
            rejected: rejected.into_iter().map(|(i, r)| (stars[i].id.clone(), r)).collect(),
        }
    };
    if obs.len() < MIN_FIELD_STARS {
        return Prepared::Done(Box::new(too_few(obs.len(), rejected)));
    }
    let (median, mut tau2) = robust_start(&obs);
    let centre = best_start(&obs, median, tau2);
    if params.dispersion == Dispersion::None {
        tau2 = [0.0; 2];
    }
    let mut keep: Vec<bool> = obs.iter().map(|o| chi2(o, centre, tau2) <= limit).collect();
    let mut result = None;
    for _ in 0..MAX_CLIP_ROUNDS {
        let kept: Vec<Obs> = obs.iter().zip(&keep).filter(|(_, k)| **k).map(|(o, _)| *o).collect();
        if kept.len() < MIN_FIELD_STARS {
            result = None;
            break;
        }
        let f = fit(&kept, params.dispersion);
        let next: Vec<bool> = obs.iter().map(|o| chi2(o, f.mean, f.tau2) <= limit).collect();
        let settled = next == keep;
        result = Some(f);
        if settled {
            break;
        }
        keep = next;
    }
    let n_kept = keep.iter().filter(|k| **k).count();
    let Some(f) = result.filter(|_| n_kept >= MIN_FIELD_STARS) else {
        for (j, &i) in candidates.iter().enumerate() {
            if !keep[j] {
                let c = chi2(&obs[j], centre, tau2);
                rejected.push((i, Rejection::Outlier { chi2: c, limit }));
            }
        }
        return Prepared::Done(Box::new(too_few(n_kept, rejected)));
    };
    // The kept stars, nearest to the binary first; the prediction uses at most
    // kriging::MAX_STARS of them.
    let mut kept_order: Vec<(f64, usize)> = candidates
        .iter()
        .enumerate()
        .filter(|(j, _)| keep[*j])
        .map(|(j, &i)| (separation_arcmin(ra_deg, dec_deg, stars[i].ra_deg, stars[i].dec_deg), j))
        .collect();
    kept_order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n_use = match params.dispersion {
        Dispersion::Estimated { .. } => kept_order.len().min(kriging::MAX_STARS),
        Dispersion::None => kept_order.len(),
    };
    let mut used = Vec::new();
    let mut max_sep: f64 = 0.0;
    for (rank, &(sep, j)) in kept_order.iter().enumerate() {
        let i = candidates[j];
        if rank < n_use {
            used.push(stars[i].id.clone());
            max_sep = max_sep.max(sep);
        } else {
            rejected.push((
                i,
                Rejection::NotNearest {
                    separation_arcmin: sep,
                    used: n_use,
                },
            ));
        }
    }
    for (j, &i) in candidates.iter().enumerate() {
        if !keep[j] {
            let c = chi2(&obs[j], f.mean, f.tau2);
            rejected.push((i, Rejection::Outlier { chi2: c, limit }));
        }
    }
    rejected.sort_by_key(|r| r.0);
    // The 2 x 2 error of the mean at E[tau^2] (the stars' cov_qu in it), each variance
    // scaled by E[var of the mean] / (var of the mean at E[tau^2]) of its coordinate: the
    // uncertainty of tau (ratio 1 when tau is not estimated).
    let ratio: [f64; 2] = std::array::from_fn(|k| {
        let at_mean = 1.0 / kept_var(&obs, &keep, k).map(|v| 1.0 / (v + f.tau2[k])).sum::<f64>();
        f.post[k].var_mean / at_mean
    });
    let cov_mean = QuCovariance {
        var_q: f.cov_mean[0] * ratio[0],
        var_u: f.cov_mean[2] * ratio[1],
        cov_qu: f.cov_mean[1] * (ratio[0] * ratio[1]).sqrt(),
    };
    let random_effects = (
        f.mean,
        QuCovariance {
            var_q: cov_mean.var_q + f.tau2[0],
            var_u: cov_mean.var_u + f.tau2[1],
            cov_qu: cov_mean.cov_qu,
        },
    );
    let (grids, dominant) = match params.dispersion {
        Dispersion::None => (None, None),
        Dispersion::Estimated { tau_max } => {
            let near: Vec<usize> = kept_order[..n_use].iter().map(|&(_, j)| j).collect();
            // The sites of coordinate k, without the one of rank `skip` in `near`.
            let sites = |k: usize, skip: Option<usize>| -> Vec<kriging::Site> {
                near.iter()
                    .enumerate()
                    .filter(|(rank, _)| Some(*rank) != skip)
                    .map(|(_, &j)| kriging::Site {
                        y: obs[j].y[k],
                        var: obs[j].s[2 * k],
                        ra_deg: stars[candidates[j]].ra_deg,
                        dec_deg: stars[candidates[j]].dec_deg,
                    })
                    .collect()
            };
            let at = |skip: Option<usize>, ra: f64, dec: f64| -> [Vec<kriging::GridPoint>; 2] {
                [0, 1].map(|k| kriging::grid_points(&sites(k, skip), ra, dec, tau_max, false))
            };
            let full = at(None, ra_deg, dec_deg);
            // The star carrying the most weight under the flat prior, when it carries at
            // least DOMINANT_WEIGHT and the others are enough for an estimate alone.
            let weights = |g: &[kriging::GridPoint]| kriging::combine(g, |_| 0.0).map(|p| p.weights);
            let dominant = match (weights(&full[0]), weights(&full[1])) {
                (Some(wq), Some(wu)) if near.len() > MIN_FIELD_STARS => (0..near.len())
                    .map(|rank| (rank, wq[rank].abs().max(wu[rank].abs())))
                    .max_by(|a, b| a.1.total_cmp(&b.1))
                    .filter(|&(_, w)| w >= DOMINANT_WEIGHT)
                    .map(|(rank, weight)| {
                        let j = near[rank];
                        let star = &stars[candidates[j]];
                        Dominant {
                            rank,
                            id: star.id.clone(),
                            weight,
                            y: obs[j].y,
                            s: obs[j].s,
                            without: at(Some(rank), ra_deg, dec_deg),
                            at_star: at(Some(rank), star.ra_deg, star.dec_deg),
                        }
                    }),
                _ => None,
            };
            (Some(full), dominant)
        }
    };
    let cov_qu = kept_order[..n_use].iter().map(|&(_, j)| obs[j].s[1]).collect();
    Prepared::Ready(Box::new(Ready {
        params: *params,
        cov_mean,
        random_effects,
        tau2: f.tau2,
        grids,
        dominant,
        cov_qu,
        used,
        rejected: rejected.into_iter().map(|(i, r)| (stars[i].id.clone(), r)).collect(),
        max_sep,
    }))
}

/// The star a prediction leans on most ([`prepare`]): the kriging again without it, at the
/// binary and at the star's own place (its leave-one-out prediction).
struct Dominant {
    /// Its rank in the used stars (nearest first).
    rank: usize,
    id: String,
    /// Its largest |weight| of q and u under the flat prior.
    weight: f64,
    /// Its q, u and covariance [var_q, cov_qu, var_u].
    y: [f64; 2],
    s: [f64; 3],
    /// The grids of q and u without it, at the binary.
    without: [Vec<kriging::GridPoint>; 2],
    /// The same at the star's place.
    at_star: [Vec<kriging::GridPoint>; 2],
}

/// A star carrying at least this weight of the prediction (q or u) is weighed as possibly
/// polarized itself ([`DominantStar`]).
pub const DOMINANT_WEIGHT: f64 = 0.5;

/// The star the prediction leaned on most, and the chance that it is intrinsically
/// polarized (module doc, "Outliers").
#[derive(Debug, Clone, PartialEq)]
pub struct DominantStar {
    /// Its id.
    pub id: String,
    /// Its largest |kriging weight| of q and u (flat prior).
    pub weight: f64,
    /// The posterior probability that it is intrinsically polarized, by which the
    /// prediction without it is mixed in.
    pub probability_polarized: f64,
}

/// The estimate of a prepared field with the night's prior (ln-weights on the kriging
/// grid; None: the flat prior).
fn finish(p: Prepared, night_prior: Option<&(kriging::NightPrior, usize)>) -> Outcome {
    let r = match p {
        Prepared::Done(o) => return *o,
        Prepared::Ready(r) => *r,
    };
    let ln_extra = |i: usize| night_prior.map_or(0.0, |(p, _)| p.ln_weights[i]);
    let predicted = r.grids.as_ref().and_then(|[gq, gu]| {
        let (pq, pu) = (kriging::combine(gq, ln_extra)?, kriging::combine(gu, ln_extra)?);
        Some((pq, pu))
    });
    // The covariance of q and u of a prediction: q and u's fields are taken as independent;
    // their errors correlate through each star's measured cov_qu (the stars `skip` left out).
    let cov_of = |pq: &kriging::Prediction, pu: &kriging::Prediction, skip: Option<usize>| {
        let cov_qu: f64 = r
            .cov_qu
            .iter()
            .enumerate()
            .filter(|(rank, _)| Some(*rank) != skip)
            .zip(pq.weights.iter().zip(&pu.weights))
            .map(|((_, c), (a, b))| a * b * c)
            .sum();
        QuCovariance {
            var_q: pq.var,
            var_u: pu.var,
            cov_qu,
        }
    };
    let mut dominant = None;
    let (mean, cov, spatial) = match predicted {
        None => (r.random_effects.0, r.random_effects.1, None),
        Some((pq, pu)) => {
            let mut mean = [pq.value, pu.value];
            let mut cov = cov_of(&pq, &pu, None);
            // The star the prediction leans on most may be a young star polarized by its
            // own disk that the clip kept (its own error small, the others' too large to
            // contradict it): the prediction is the mixture of the one with it and the one
            // without it, weighed by the posterior probability that it is polarized.
            let alternative = r.dominant.as_ref().and_then(|d| {
                let c = |g: &[kriging::GridPoint]| kriging::combine(g, ln_extra);
                let (aq, au) = (c(&d.without[0])?, c(&d.without[1])?);
                let (sq, su) = (c(&d.at_star[0])?, c(&d.at_star[1])?);
                let residual = [d.y[0] - sq.value, d.y[1] - su.value];
                let p = probability_polarized(residual, [sq.var + d.s[0], d.s[1], su.var + d.s[2]]);
                Some((d, [aq.value, au.value], cov_of(&aq, &au, Some(d.rank)), p))
            });
            if let Some((d, m, c, p)) = alternative {
                let dm = [m[0] - mean[0], m[1] - mean[1]];
                let w = 1.0 - p;
                cov = QuCovariance {
                    var_q: w * cov.var_q + p * c.var_q + w * p * dm[0] * dm[0],
                    var_u: w * cov.var_u + p * c.var_u + w * p * dm[1] * dm[1],
                    cov_qu: w * cov.cov_qu + p * c.cov_qu + w * p * dm[0] * dm[1],
                };
                mean = [mean[0] + p * dm[0], mean[1] + p * dm[1]];
                dominant = Some(DominantStar {
                    id: d.id.clone(),
                    weight: d.weight,
                    probability_polarized: p,
                });
            }
            let spatial = Spatial {
                nugget: [pq.nugget2.sqrt(), pu.nugget2.sqrt()],
                slope: [pq.slope2.sqrt(), pu.slope2.sqrt()],
                exponent: [pq.alpha, pu.alpha],
                night_prior: night_prior.map(|(_, n)| *n),
                flat_share: night_prior.map(|(p, _)| p.flat_share),
            };
            (mean, cov, Some(spatial))
        }
    };
    Outcome::Estimated(Box::new(ForegroundEstimate {
        q: mean[0],
        u: mean[1],
        cov,
        cov_mean: r.cov_mean,
        random_effects: r.random_effects,
        spatial,
        tau: [r.tau2[0].sqrt(), r.tau2[1].sqrt()],
        used: r.used,
        rejected: r.rejected,
        max_separation_arcmin: r.max_sep,
        method: match &spatial {
            Some(sp) => format!(
                "{}; prior of the foreground's variation: {}{}",
                method_text(&r.params),
                match (sp.night_prior, sp.flat_share) {
                    (Some(n), Some(share)) => format!(
                        "the night's distribution from {n} other field(s), the flat prior's share {share} (chosen by how well the other fields predict each other)"
                    ),
                    _ => "flat".to_string(),
                },
                dominant.as_ref().map_or(String::new(), |d| format!(
                    "; star {} carries weight {:.2}: polarized itself with probability {:.3}, the prediction without it mixed in by that",
                    d.id, d.weight, d.probability_polarized
                ))
            ),
            None if r.grids.is_some() => format!(
                "{}; the kriging failed (no grid point with a positive-definite covariance): the random-effects prediction, error of the mean + E[tau^2]",
                method_text(&r.params)
            ),
            None => method_text(&r.params),
        },
        dominant,
    }))
}

/// The foreground's variation over the field as the kriging saw it (posterior means,
/// fractions; [`kriging`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spatial {
    /// sqrt(E[t^2]) of q and u: the nugget, variation between neighbouring places.
    pub nugget: [f64; 2],
    /// sqrt(E[s^2]) of q and u: the power-law part's rms difference at 5 arcmin / sqrt(2).
    pub slope: [f64; 2],
    /// E\[alpha\] of q and u: the power-law part's exponent.
    pub exponent: [f64; 2],
    /// How many of the night's other fields informed the prior of t and s (None: the flat
    /// prior).
    pub night_prior: Option<usize>,
    /// The flat prior's share of the night's prior ([`kriging::night_prior`]; None: the
    /// flat prior alone).
    pub flat_share: Option<f64>,
}

impl ForegroundEstimate {
    /// As the catalog's `foreground` (fractions; the prediction covariance at the binary).
    pub fn to_catalog(&self) -> Foreground {
        Foreground {
            q: self.q,
            u: self.u,
            sigma_q: self.cov.var_q.max(0.0).sqrt(),
            sigma_u: self.cov.var_u.max(0.0).sqrt(),
            cov_qu: self.cov.cov_qu,
            source: Some(format!(
                "field stars, n = {}, within {:.1} arcmin ({} rejected)",
                self.used.len(),
                self.max_separation_arcmin,
                self.rejected.len()
            )),
            n_used: Some(self.used.len()),
            tau: Some(self.tau),
            method: Some(self.method.clone()),
            rejected: self
                .rejected
                .iter()
                .map(|(id, r)| RejectedFieldStar {
                    id: id.clone(),
                    reason: r.to_string(),
                })
                .collect(),
        }
    }
}

/// What [`set_target_foreground`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum Applied {
    /// The target's `foreground` was set and its foreground-subtracted Delta-gamma computed.
    Set(Box<ForegroundEstimate>),
    /// Too few field stars: the target's `foreground` was cleared, its flag
    /// `foreground_too_few_field_stars` set.
    TooFew {
        /// Stars left after the rejections.
        n_left: usize,
        /// Ids of the stars not used, with why.
        rejected: Vec<(String, Rejection)>,
    },
    /// The target has no sky position (`ra_deg`, `dec_deg`): no foreground (cleared), the
    /// Delta-gamma recomputed without one.
    NoPosition,
}

/// The one call for the field-star measurement: estimate the foreground of `target` from
/// its field stars, write it into `target.foreground` and recompute its Delta-gammas with
/// the night's calibration covariance `cal` (as [`Target::update_delta_gamma`]: None when
/// no calibration was applied). Too few stars: `foreground` cleared and the target flagged
/// `foreground_too_few_field_stars` (its Delta-gamma stays the uncorrected one).
pub fn set_target_foreground(
    target: &mut Target,
    stars: &[FieldStarQu],
    params: &EstimateParams,
    cal: Option<&CalibrationCovariance>,
) -> Applied {
    let (Some(ra), Some(dec)) = (
        target.ra_deg.filter(|v| v.is_finite()),
        target.dec_deg.filter(|v| v.is_finite()),
    ) else {
        // No sky position: no estimate, and the Delta-gamma of the calibrated components
        // all the same.
        target.foreground = None;
        target.update_delta_gamma(cal);
        return Applied::NoPosition;
    };
    apply_outcome(target, estimate(ra, dec, stars, params), cal)
}

/// Write an estimate's outcome into `target` ([`set_target_foreground`]: `foreground` set,
/// or cleared and flagged too few) and recompute its Delta-gammas with `cal`.
pub fn apply_outcome(target: &mut Target, outcome: Outcome, cal: Option<&CalibrationCovariance>) -> Applied {
    let applied = match outcome {
        Outcome::Estimated(e) => {
            target.foreground = Some(e.to_catalog());
            set_too_few_flag(target, None);
            Applied::Set(e)
        }
        Outcome::TooFew { n_left, rejected, .. } => {
            target.foreground = None;
            let detail = format!(
                "{n_left} usable field star(s) after {} rejection(s), need {MIN_FIELD_STARS}",
                rejected.len()
            );
            set_too_few_flag(target, Some(detail));
            Applied::TooFew { n_left, rejected }
        }
    };
    target.update_delta_gamma(cal);
    applied
}

/// Replace the target's `foreground_too_few_field_stars` flag by one with `detail` (None:
/// remove it; an emptied list becomes absent).
fn set_too_few_flag(target: &mut Target, detail: Option<String>) {
    let code = FlagCode::ForegroundTooFewFieldStars;
    let mut flags = target.flags.take().unwrap_or_default();
    flags.retain(|f| !f.is(code));
    flags.extend(detail.map(|d| Flag::with_detail(code, d)));
    target.flags = (!flags.is_empty()).then_some(flags);
}

pub mod kriging;

#[cfg(test)]
mod tests;
