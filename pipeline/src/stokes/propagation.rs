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
//! More generally the calibration is a parameter vector theta = (c, theta0 in deg, a, b), (a, b)
//! the telescope's polarization in the frame of the vertical, with covariance Sigma_cal; each
//! star carries its Jacobian `J = d(q, u)/d theta` (2 x 4) and the calibration adds
//! `J Sigma_cal J^T` ([`calibration_covariance_of`]).
//!
//! Delta-gamma = gamma_A - gamma_B (folded into [0, 90] deg, which keeps the derivative's
//! magnitude). The stars' own errors are independent; the calibration is common to both, so
//! its part is the variance of `(gA^T J_A - gB^T J_B) theta`. theta0 rotates both angles by
//! the same amount and cancels; the offset c moves the two angles by `gamma_A' . d_A` and
//! `gamma_B' . d_B` per unit c, and the telescope's term by the same vector in (q, u), which do
//! not cancel:
//!
//! ```text
//! sigma_dgamma^2 = gA^T S_A gA + gB^T S_B gB + w^T Sigma_cal w,   w = J_A^T gA - J_B^T gB
//! ```
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

/// Standard deviation of an axial angle uniform on [-90, 90) deg (no information): 90/sqrt(3).
/// The upper bound of the reported `sigma_gamma_deg`.
pub const UNIFORM_ANGLE_SIGMA_DEG: f64 = 51.961_524_227_066_32;

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

/// Index of the offset c in the calibration's parameter vector.
pub const CAL_C: usize = 0;
/// Index of the zero-point theta0 (deg).
pub const CAL_THETA0: usize = 1;
/// Index of the telescope's `a = p_tel cos 2psi_tel`.
pub const CAL_TEL_A: usize = 2;
/// Index of the telescope's `b = p_tel sin 2psi_tel`.
pub const CAL_TEL_B: usize = 3;
/// Names of the calibration parameters, in order (as written in calibration.json).
pub const CAL_PARAMETERS: [&str; 4] = ["c", "theta0_deg", "tel_a", "tel_b"];

/// Covariance of the calibration parameters (c, theta0 deg, a, b).
pub type CalibrationCovariance = [[f64; 4]; 4];

/// A star's `d(q, u)/d theta_k` for each calibration parameter (per deg for theta0).
pub type CalibrationJacobian = [[f64; 2]; 4];

/// The Jacobian of a pure rotation by theta0: `d(q, u)/d theta0 = (-2u, 2q)` per rad,
/// in per deg.
pub fn rotation_gradient_per_deg(q: f64, u: f64) -> [f64; 2] {
    let rad = std::f64::consts::PI / 180.0;
    [-2.0 * u * rad, 2.0 * q * rad]
}

/// What the calibration adds to one star's (q, u) covariance: `J Sigma_cal J^T`.
pub fn calibration_covariance_of(jac: &CalibrationJacobian, cov: &CalibrationCovariance) -> QuCovariance {
    let entry = |i: usize, j: usize| {
        let mut s = 0.0;
        for k in 0..4 {
            for l in 0..4 {
                s += jac[k][i] * cov[k][l] * jac[l][j];
            }
        }
        s
    };
    QuCovariance {
        var_q: entry(0, 0),
        var_u: entry(1, 1),
        cov_qu: entry(0, 1),
    }
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
    let mut jac = [[0.0; 2]; 4];
    jac[CAL_C] = offset_gradient.unwrap_or([0.0, 0.0]);
    jac[CAL_THETA0] = rotation_gradient_per_deg(q, u);
    calibration_covariance_of(&jac, &cal.covariance())
}

impl CalibrationErrors {
    /// As a covariance of (c, theta0 deg, a, b) (no telescope term).
    pub fn covariance(&self) -> CalibrationCovariance {
        let mut m = [[0.0; 4]; 4];
        m[CAL_C][CAL_C] = self.var_c;
        m[CAL_THETA0][CAL_THETA0] = self.var_theta0_deg2;
        m[CAL_C][CAL_THETA0] = self.cov_c_theta0_deg;
        m[CAL_THETA0][CAL_C] = self.cov_c_theta0_deg;
        m
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
    /// d(q, u)/d theta for the calibration parameters (zero columns for those that do not
    /// enter: c when no offset was subtracted, the telescope's when not removed).
    pub jacobian: CalibrationJacobian,
}

impl StarQu {
    /// A star whose calibration is the offset c alone (`offset_gradient = d(q, u)/dc`) and
    /// a zero-point that rotates it.
    pub fn with_offset_gradient(q: f64, u: f64, stat: QuCovariance, offset_gradient: [f64; 2]) -> StarQu {
        let mut jacobian = [[0.0; 2]; 4];
        jacobian[CAL_C] = offset_gradient;
        jacobian[CAL_THETA0] = rotation_gradient_per_deg(q, u);
        StarQu { q, u, stat, jacobian }
    }
}

impl StarQu {
    /// The star with a foreground (q_f, u_f) subtracted: (q - q_f, u - u_f), the same own
    /// covariance. The foreground was measured on field stars calibrated with the same
    /// zero-point, so it rotates with theta0 too: the theta0 column loses the foreground's
    /// rotation gradient (for a pure rotation it becomes the corrected star's). The other
    /// columns (c, telescope) are the star's own: the field stars' share of them is not
    /// known here, which can only overstate the error.
    pub fn minus_foreground(&self, q_f: f64, u_f: f64) -> StarQu {
        let mut jacobian = self.jacobian;
        let r = rotation_gradient_per_deg(q_f, u_f);
        jacobian[CAL_THETA0] = [jacobian[CAL_THETA0][0] - r[0], jacobian[CAL_THETA0][1] - r[1]];
        StarQu {
            q: self.q - q_f,
            u: self.u - u_f,
            stat: self.stat,
            jacobian,
        }
    }

    /// The angle 1/2 atan2(u, q), deg in [0, 180).
    pub fn gamma_deg(&self) -> f64 {
        (0.5 * self.u.atan2(self.q).to_degrees()).rem_euclid(180.0)
    }
}

/// A covariance of the offset c alone.
pub fn offset_covariance(var_c: f64) -> CalibrationCovariance {
    let mut m = [[0.0; 4]; 4];
    m[CAL_C][CAL_C] = var_c;
    m
}

/// `w = J_A^T gA - J_B^T gB`: how the calibration parameters move Delta-gamma (rad per unit).
fn common_weights(a: &StarQu, b: &StarQu) -> [f64; 4] {
    let (ga, gb) = (gamma_gradient_rad(a.q, a.u), gamma_gradient_rad(b.q, b.u));
    let dot = |g: [f64; 2], d: [f64; 2]| g[0] * d[0] + g[1] * d[1];
    std::array::from_fn(|k| dot(ga, a.jacobian[k]) - dot(gb, b.jacobian[k]))
}

/// Delta-method 1-sigma error of Delta-gamma, deg: both stars' own covariances and the
/// calibration common to both (`cal`, the covariance of (c, theta0, a, b)); theta0, a pure
/// rotation of both, cancels.
pub fn sigma_delta_gamma_deg(a: &StarQu, b: &StarQu, cal: &CalibrationCovariance) -> f64 {
    sigma_delta_gamma_with_foreground_deg(a, b, cal, &QuCovariance::ZERO)
}

/// [`sigma_delta_gamma_deg`] of two stars from which a foreground f of covariance
/// `foreground` was subtracted (`a`, `b` already corrected: [`StarQu::minus_foreground`]).
/// f is common to both: it moves Delta-gamma by `-(gA - gB) . df`, which does not cancel
/// (the two angles' gradients differ), and adds `(gA - gB)^T C_f (gA - gB)`.
pub fn sigma_delta_gamma_with_foreground_deg(
    a: &StarQu,
    b: &StarQu,
    cal: &CalibrationCovariance,
    foreground: &QuCovariance,
) -> f64 {
    let (ga, gb) = (gamma_gradient_rad(a.q, a.u), gamma_gradient_rad(b.q, b.u));
    let w = common_weights(a, b);
    let mut common = 0.0;
    for k in 0..4 {
        for l in 0..4 {
            common += w[k] * cal[k][l] * w[l];
        }
    }
    let fg = foreground.quadratic_form([ga[0] - gb[0], ga[1] - gb[1]]);
    (a.stat.quadratic_form(ga) + b.stat.quadratic_form(gb) + common + fg)
        .max(0.0)
        .sqrt()
        .to_degrees()
}

/// Lower Cholesky factor of a positive semi-definite matrix (a pivot at or below zero, from
/// a parameter that was not fitted or round-off, gives a zero column).
fn cholesky_psd(m: &CalibrationCovariance) -> [[f64; 4]; 4] {
    let mut l = [[0.0; 4]; 4];
    for j in 0..4 {
        let d = m[j][j] - (0..j).map(|k| l[j][k] * l[j][k]).sum::<f64>();
        if !(d > 1e-14 * m[j][j].abs().max(f64::MIN_POSITIVE)) {
            continue;
        }
        l[j][j] = d.sqrt();
        for i in j + 1..4 {
            l[i][j] = (m[i][j] - (0..j).map(|k| l[i][k] * l[j][k]).sum::<f64>()) / l[j][j];
        }
    }
    l
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
/// with the stars' own covariances and the calibration common to both (each draw moves
/// both stars by their Jacobians times one draw of the calibration parameters). Seeded from the inputs, so
/// the same catalog gives the same interval. Near 0 or 90 deg, and at low S/N, the
/// folded distribution is skewed: the interval is then the honest summary.
pub fn delta_gamma_interval_deg(a: &StarQu, b: &StarQu, cal: &CalibrationCovariance) -> [f64; 2] {
    delta_gamma_interval_with_foreground_deg(a, b, cal, &QuCovariance::ZERO)
}

/// [`delta_gamma_interval_deg`] of two stars from which a foreground of covariance
/// `foreground` was subtracted (`a`, `b` already corrected): each draw also draws one
/// foreground error and subtracts it from both stars. A zero `foreground` gives exactly
/// [`delta_gamma_interval_deg`]'s draws.
pub fn delta_gamma_interval_with_foreground_deg(
    a: &StarQu,
    b: &StarQu,
    cal: &CalibrationCovariance,
    foreground: &QuCovariance,
) -> [f64; 2] {
    let with_fg = *foreground != QuCovariance::ZERO;
    let fg_terms = [foreground.var_q, foreground.var_u, foreground.cov_qu];
    let seed = [a.q, a.u, b.q, b.u]
        .iter()
        .chain(cal.iter().flatten())
        .chain(fg_terms.iter().filter(|_| with_fg))
        .fold(0x5eed_u64, |h, v| (h ^ v.to_bits()).wrapping_mul(0x100_0000_01b3));
    let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(seed);
    let chol = |s: &QuCovariance| {
        // Lower Cholesky factor of a 2x2 covariance (clamped at 0 for round-off).
        let l11 = s.var_q.max(0.0).sqrt();
        let l21 = if l11 > 0.0 { s.cov_qu / l11 } else { 0.0 };
        let l22 = (s.var_u - l21 * l21).max(0.0).sqrt();
        (l11, l21, l22)
    };
    let (la, lb, lf) = (chol(&a.stat), chol(&b.stat), chol(foreground));
    let lc = cholesky_psd(cal);
    let mut z = || -> f64 { StandardNormal.sample(&mut rng) };
    let shift = |j: &CalibrationJacobian, t: &[f64; 4]| -> [f64; 2] {
        std::array::from_fn(|i| (0..4).map(|k| j[k][i] * t[k]).sum())
    };
    let mut draws: Vec<f64> = (0..INTERVAL_DRAWS)
        .map(|_| {
            let (z1, z2, z3, z4) = (z(), z(), z(), z());
            let zc: [f64; 4] = std::array::from_fn(|_| z());
            // One draw of the common calibration, theta = L z.
            let t: [f64; 4] = std::array::from_fn(|i| (0..=i).map(|k| lc[i][k] * zc[k]).sum());
            let (da, db) = (shift(&a.jacobian, &t), shift(&b.jacobian, &t));
            // One draw of the foreground's error, common to both stars.
            let (fq, fu) = if with_fg {
                let (z5, z6) = (z(), z());
                (lf.0 * z5, lf.1 * z5 + lf.2 * z6)
            } else {
                (0.0, 0.0)
            };
            let qa = a.q + la.0 * z1 + da[0] - fq;
            let ua = a.u + la.1 * z1 + la.2 * z2 + da[1] - fu;
            let qb = b.q + lb.0 * z3 + db[0] - fq;
            let ub = b.u + lb.1 * z3 + lb.2 * z4 + db[1] - fu;
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
