//! Errors of P, gamma and Delta-gamma from the full covariance of q and u.
//!
//! Every error here is the delta method on a covariance: the gradient of the quantity,
//! `g`, and `sigma^2 = g^T Sigma g`.
//!
//! ```text
//! P      = hypot(q, u)            dP     = (q dq + u du) / P
//! gamma  = 1/2 atan2(u, q)        dgamma = (q du - u dq) / (2 P^2)      [rad]
//! sigma_P^2     = (q^2 Vq + u^2 Vu + 2 q u C) / P^2
//! sigma_gamma^2 = (u^2 Vq + q^2 Vu - 2 q u C) / (4 P^4)                  [rad^2]
//! ```
//!
//! The calibration moves a star's (q, u) by its offset gradient `d = d(q, u)/dc` times the
//! error of the offset c, and rotates it by twice the error of the zero-point theta0:
//! `J = [d, (-2u, 2q)]` on (c, theta0 in rad), so the calibration adds `J Sigma_cal J^T`.
//! The theta0 column is purely tangential: it leaves P and sigma_P alone.
//!
//! Delta-gamma = gamma_A - gamma_B (folded into [0, 90] deg, which keeps the derivative's
//! magnitude). theta0 moves both angles by the same amount and cancels; the stars' own
//! errors are independent; the offset c is common to the night and moves the two angles by
//! `gamma_A' . d_A` and `gamma_B' . d_B` per unit c, which do not cancel:
//!
//! ```text
//! sigma_dgamma^2 = gA^T S_A gA + gB^T S_B gB + (gA . d_A - gB . d_B)^2 sigma_c^2
//! ```
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

use super::inversion::UNIFORM_ANGLE_SIGMA_DEG;

/// The covariance of (q, u).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QuCovariance {
    /// Var(q).
    pub var_q: f64,
    /// Var(u).
    pub var_u: f64,
    /// Cov(q, u).
    pub cov_qu: f64,
}

impl QuCovariance {
    /// No error.
    pub const ZERO: QuCovariance = QuCovariance {
        var_q: 0.0,
        var_u: 0.0,
        cov_qu: 0.0,
    };

    /// `g^T Sigma g` for a gradient `g = (d/dq, d/du)`.
    pub fn quadratic_form(&self, g: [f64; 2]) -> f64 {
        g[0] * g[0] * self.var_q + g[1] * g[1] * self.var_u + 2.0 * g[0] * g[1] * self.cov_qu
    }

    /// The sum of two independent contributions.
    pub fn plus(&self, other: &QuCovariance) -> QuCovariance {
        QuCovariance {
            var_q: self.var_q + other.var_q,
            var_u: self.var_u + other.var_u,
            cov_qu: self.cov_qu + other.cov_qu,
        }
    }
}

/// Gradient of P with respect to (q, u): (q, u)/P. Zero at P = 0.
pub fn p_gradient(q: f64, u: f64) -> [f64; 2] {
    let p = q.hypot(u);
    if p > 0.0 {
        [q / p, u / p]
    } else {
        [0.0, 0.0]
    }
}

/// Gradient of gamma (rad) with respect to (q, u): (-u, q) / (2 P^2). Zero at P = 0.
pub fn gamma_gradient_rad(q: f64, u: f64) -> [f64; 2] {
    let p2 = q * q + u * u;
    if p2 > 0.0 {
        [-u / (2.0 * p2), q / (2.0 * p2)]
    } else {
        [0.0, 0.0]
    }
}

/// sigma_P from the full covariance. At P = 0 (no direction) the mean of the two
/// variances.
pub fn sigma_p(q: f64, u: f64, cov: &QuCovariance) -> f64 {
    if q.hypot(u) > 0.0 {
        cov.quadratic_form(p_gradient(q, u)).max(0.0).sqrt()
    } else {
        (0.5 * (cov.var_q + cov.var_u)).max(0.0).sqrt()
    }
}

/// sigma_gamma in degrees from the full covariance (the tangential error over 2P), at
/// most 90/sqrt(3) deg, the standard deviation of an angle with no information (reached
/// at low S/N, where the linear formula diverges; also the value at P = 0).
pub fn sigma_gamma_deg(q: f64, u: f64, cov: &QuCovariance) -> f64 {
    if !(q.hypot(u) > 0.0) {
        return UNIFORM_ANGLE_SIGMA_DEG;
    }
    let s = cov
        .quadratic_form(gamma_gradient_rad(q, u))
        .max(0.0)
        .sqrt()
        .to_degrees();
    s.min(UNIFORM_ANGLE_SIGMA_DEG)
}

/// The errors of a night's calibration: the offset c and the zero-point theta0.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CalibrationErrors {
    /// Var(c).
    pub var_c: f64,
    /// Var(theta0), deg^2.
    pub var_theta0_deg2: f64,
    /// Cov(c, theta0), units of c times deg.
    pub cov_c_theta0_deg: f64,
}

/// What the calibration adds to one star's (q, u) covariance: `J Sigma_cal J^T` with
/// `J = [d, (-2u, 2q)]` on (c, theta0 in rad); `offset_gradient` is `d = d(q, u)/dc`
/// (`None`: no offset subtracted, c does not enter).
pub fn calibration_covariance(
    q: f64,
    u: f64,
    offset_gradient: Option<[f64; 2]>,
    cal: &CalibrationErrors,
) -> QuCovariance {
    let d = offset_gradient.unwrap_or([0.0, 0.0]);
    let r = [-2.0 * u, 2.0 * q]; // d(q, u)/d theta0 per rad
    let rad = std::f64::consts::PI / 180.0;
    let (vc, vt, ct) = (cal.var_c, cal.var_theta0_deg2 * rad * rad, cal.cov_c_theta0_deg * rad);
    let entry = |i: usize, j: usize| d[i] * d[j] * vc + r[i] * r[j] * vt + (d[i] * r[j] + r[i] * d[j]) * ct;
    QuCovariance {
        var_q: entry(0, 0),
        var_u: entry(1, 1),
        cov_qu: entry(0, 1),
    }
}

/// One star of a binary as its Delta-gamma error needs it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StarQu {
    /// q.
    pub q: f64,
    /// u.
    pub u: f64,
    /// Covariance from this star's own measurement.
    pub stat: QuCovariance,
    /// d(q, u)/dc (zero when no offset was subtracted).
    pub offset_gradient: [f64; 2],
}

/// Delta-method 1-sigma error of Delta-gamma, deg: both stars' own covariances and the
/// common offset c (variance `var_c`); the zero-point theta0 cancels and does not enter.
pub fn sigma_delta_gamma_deg(a: &StarQu, b: &StarQu, var_c: f64) -> f64 {
    let (ga, gb) = (gamma_gradient_rad(a.q, a.u), gamma_gradient_rad(b.q, b.u));
    let dot = |g: [f64; 2], d: [f64; 2]| g[0] * d[0] + g[1] * d[1];
    let common = dot(ga, a.offset_gradient) - dot(gb, b.offset_gradient);
    (a.stat.quadratic_form(ga) + b.stat.quadratic_form(gb) + common * common * var_c)
        .max(0.0)
        .sqrt()
        .to_degrees()
}

/// The folded difference of two axial angles computed from (q, u) pairs, deg in [0, 90].
fn folded_delta_deg(qa: f64, ua: f64, qb: f64, ub: f64) -> f64 {
    let d = (0.5 * (ua.atan2(qa) - ub.atan2(qb))).to_degrees().rem_euclid(180.0);
    if d > 90.0 {
        180.0 - d
    } else {
        d
    }
}

/// Draws of the Delta-gamma interval.
pub const INTERVAL_DRAWS: usize = 8192;

/// Central 68.27 % interval [low, high] of the folded Delta-gamma, deg, over
/// [`INTERVAL_DRAWS`] Gaussian draws of (q_A, u_A, q_B, u_B) about the measured values
/// with the stars' own covariances and the common offset c. Seeded from the inputs, so
/// the same catalog gives the same interval. Near 0 or 90 deg, and at low S/N, the
/// folded distribution is skewed: the interval is then the honest summary.
pub fn delta_gamma_interval_deg(a: &StarQu, b: &StarQu, var_c: f64) -> [f64; 2] {
    let seed = [a.q, a.u, b.q, b.u, var_c]
        .iter()
        .fold(0x5eed_u64, |h, v| (h ^ v.to_bits()).wrapping_mul(0x100_0000_01b3));
    let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(seed);
    let chol = |s: &QuCovariance| {
        // Lower Cholesky factor of a 2x2 covariance (clamped at 0 for round-off).
        let l11 = s.var_q.max(0.0).sqrt();
        let l21 = if l11 > 0.0 { s.cov_qu / l11 } else { 0.0 };
        let l22 = (s.var_u - l21 * l21).max(0.0).sqrt();
        (l11, l21, l22)
    };
    let (la, lb) = (chol(&a.stat), chol(&b.stat));
    let sc = var_c.max(0.0).sqrt();
    let mut z = || -> f64 { StandardNormal.sample(&mut rng) };
    let mut draws: Vec<f64> = (0..INTERVAL_DRAWS)
        .map(|_| {
            let (z1, z2, z3, z4, zc) = (z(), z(), z(), z(), z());
            let qa = a.q + la.0 * z1 + a.offset_gradient[0] * sc * zc;
            let ua = a.u + la.1 * z1 + la.2 * z2 + a.offset_gradient[1] * sc * zc;
            let qb = b.q + lb.0 * z3 + b.offset_gradient[0] * sc * zc;
            let ub = b.u + lb.1 * z3 + lb.2 * z4 + b.offset_gradient[1] * sc * zc;
            folded_delta_deg(qa, ua, qb, ub)
        })
        .collect();
    draws.sort_by(f64::total_cmp);
    let at = |p: f64| draws[((p * INTERVAL_DRAWS as f64) as usize).min(INTERVAL_DRAWS - 1)];
    let tail = 0.5 * (1.0 - 0.682_689_492_137_085_9);
    [at(tail), at(1.0 - tail)]
}

#[cfg(test)]
mod tests;
