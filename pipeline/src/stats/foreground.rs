//! The interstellar foreground in the statistics: one level and angle common to the sample
//! ([`Ism`]), or one binary's own mean and covariance ([`ForegroundQu`]). Used by the
//! Monte Carlo ([`crate::stats::mc`]) and the sample read from a catalog
//! ([`crate::stats::sample`]); depends on neither.
use serde::{Deserialize, Serialize};

use crate::stats::{Error, Result};

/// Interstellar polarization common to both components.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Ism {
    /// Degree P_ism, percent.
    pub p_percent: f64,
    /// Angle gamma_ism, degrees east of north.
    pub angle_deg: f64,
}

/// The interstellar foreground of one binary in the Monte Carlo, percent: a mean (q, u)
/// and, when it was measured with errors, its covariance. Each simulated pair draws one
/// foreground from N(mean, covariance) and adds it to both components.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ForegroundQu {
    /// Mean foreground q, percent.
    pub q_percent: f64,
    /// Mean foreground u, percent.
    pub u_percent: f64,
    /// Covariance (var q, cov qu, var u), percent^2; zeros: a fixed foreground.
    pub cov_percent2: [f64; 3],
}

impl ForegroundQu {
    /// A fixed foreground of degree `ism.p_percent` at angle `ism.angle_deg`.
    pub fn fixed(ism: Ism) -> Self {
        let (s, c) = (2.0 * ism.angle_deg.to_radians()).sin_cos();
        ForegroundQu {
            q_percent: ism.p_percent * c,
            u_percent: ism.p_percent * s,
            cov_percent2: [0.0; 3],
        }
    }

    /// No foreground.
    pub const NONE: ForegroundQu = ForegroundQu {
        q_percent: 0.0,
        u_percent: 0.0,
        cov_percent2: [0.0; 3],
    };

    /// Degree of the mean foreground, percent.
    pub fn p_percent(&self) -> f64 {
        self.q_percent.hypot(self.u_percent)
    }

    /// Check the values (`what` names the binary in the error): finite, variances >= 0,
    /// the covariance positive semi-definite.
    pub fn validate(&self, what: &str) -> Result<()> {
        let [vq, c, vu] = self.cov_percent2;
        let bad = |name: &str, value: String, reason: &str| {
            Err(Error::InvalidParameter {
                name: format!("{what}: foreground {name}"),
                value,
                reason: reason.into(),
            })
        };
        if !(self.q_percent.is_finite() && self.u_percent.is_finite()) {
            return bad(
                "q, u (%)",
                format!("{}, {}", self.q_percent, self.u_percent),
                "must be finite",
            );
        }
        if !(vq >= 0.0 && vu >= 0.0 && vq.is_finite() && vu.is_finite() && c.is_finite()) {
            return bad("variances (%^2)", format!("{vq}, {vu}"), "must be finite and >= 0");
        }
        // Relative tolerance for a correlation of exactly +-1 written with rounding.
        if c * c > vq * vu * (1.0 + 1e-9) {
            return bad(
                "cov_qu (%^2)",
                c.to_string(),
                &format!("exceeds sqrt(var_q var_u) = {}: not a covariance", (vq * vu).sqrt()),
            );
        }
        Ok(())
    }

    /// Lower-triangular Cholesky factor (l_qq, l_uq, l_uu) of the covariance; None for a
    /// fixed foreground. A singular covariance (correlation +-1, or one variance 0) is
    /// factored as the limit: l_uu = 0.
    pub fn cholesky(&self) -> Option<[f64; 3]> {
        let [vq, c, vu] = self.cov_percent2;
        if vq == 0.0 && vu == 0.0 {
            return None;
        }
        let lqq = vq.sqrt();
        let luq = if lqq > 0.0 { c / lqq } else { 0.0 };
        let luu = (vu - luq * luq).max(0.0).sqrt();
        Some([lqq, luq, luu])
    }
}
