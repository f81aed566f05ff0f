//! The telescope's own polarization in a night's calibration, and its removal from every
//! component before the Stokes solve (part of the one solve, `solve.rs`).
//!
//! The tertiary mirror adds `(q_tel, u_tel) = R(2 eta) (a, b)` to every source, eta the
//! frame's parallactic angle. An orientation whose frames have the weighted mean
//! `(C, S) = <(cos 2eta, sin 2eta)>` (the weights of its F) therefore carries in F
//!
//! ```text
//! T(phi) = a (C cos 2phi + S sin 2phi) + b (C sin 2phi - S cos 2phi)
//! ```
//!
//! which is subtracted from F before any Stokes method (least squares, free offset,
//! difference, ratio). The calibration's (a, b) come from the standards
//! ([`crate::stokes::calibration::joint`]).
use crate::catalog::polarimetric_calibration::TelescopeCalibration;

use crate::stokes::calibration::OrientationF;
use crate::stokes::model::{Polarization, TelescopePolarization};
use crate::stokes::propagation::{self, CalibrationCovariance, QuCovariance, CAL_TEL_A, CAL_TEL_B};

impl TelescopeCalibration {
    /// From the fitted (a, b) and the calibration's covariance.
    pub fn from_fit(t: &TelescopePolarization, cov: &CalibrationCovariance) -> TelescopeCalibration {
        let [a, b] = t.ab();
        let c = QuCovariance {
            var_q: cov[CAL_TEL_A][CAL_TEL_A],
            var_u: cov[CAL_TEL_B][CAL_TEL_B],
            cov_qu: cov[CAL_TEL_A][CAL_TEL_B],
        };
        // (a, b) play the part of (q, u): the same formulas give P's and the angle's errors.
        TelescopeCalibration {
            p_tel: t.p_tel,
            sigma_p_tel: propagation::sigma_p(a, b, &c),
            psi_tel_deg: t.psi_tel_deg,
            sigma_psi_tel_deg: propagation::sigma_gamma_deg(a, b, &c),
            a,
            b,
        }
    }

    /// (a, b).
    pub fn ab(&self) -> [f64; 2] {
        [self.a, self.b]
    }
}

/// `dT/da` and `dT/db` at analyzer angle `phi_deg` for frames with mean `(C, S)`.
pub fn regressors(phi_deg: f64, parallactic_2eta: [f64; 2]) -> [f64; 2] {
    let [c, s] = parallactic_2eta;
    let t = 2.0 * phi_deg.to_radians();
    [c * t.cos() + s * t.sin(), c * t.sin() - s * t.cos()]
}

/// The telescope's term of F, `T(phi) = a r_a + b r_b`.
pub fn telescope_f(ab: [f64; 2], phi_deg: f64, parallactic_2eta: [f64; 2]) -> f64 {
    let r = regressors(phi_deg, parallactic_2eta);
    ab[0] * r[0] + ab[1] * r[1]
}

/// `F - T` for every orientation (`parallactic_2eta` aligned with `obs`). `Err` names the
/// first orientation without a parallactic angle.
pub fn remove(
    obs: &[OrientationF],
    parallactic_2eta: &[Option<[f64; 2]>],
    ab: [f64; 2],
) -> Result<Vec<OrientationF>, String> {
    obs.iter()
        .zip(parallactic_2eta)
        .map(|(o, eta)| {
            let eta = eta.ok_or_else(|| {
                format!(
                    "no parallactic angle for the orientation at analyzer angle {:.1} deg",
                    o.analyzer_deg
                )
            })?;
            Ok(OrientationF {
                f: o.f - telescope_f(ab, o.analyzer_deg, eta),
                ..*o
            })
        })
        .collect()
}

/// The sky-frame telescope polarization removed from a component: `R(2 eta) (a, b)` with
/// the orientations' (C, S) averaged with the weights of their F (for reading; the solve
/// removes it orientation by orientation).
pub fn mean_removed(obs: &[OrientationF], parallactic_2eta: &[Option<[f64; 2]>], ab: [f64; 2]) -> Option<Polarization> {
    let (mut sw, mut c, mut s) = (0.0, 0.0, 0.0);
    for (o, eta) in obs.iter().zip(parallactic_2eta) {
        let [ci, si] = (*eta)?;
        let w = o.sigma_f.powi(-2);
        sw += w;
        c += w * ci;
        s += w * si;
    }
    (sw > 0.0).then(|| {
        let (c, s) = (c / sw, s / sw);
        Polarization {
            q: ab[0] * c - ab[1] * s,
            u: ab[0] * s + ab[1] * c,
        }
    })
}

#[cfg(test)]
mod tests;
