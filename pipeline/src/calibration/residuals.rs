//! A standard's measurement against its table values, with the measurement's statistical
//! error and the table error counted once (the calibration's own error, which comes from
//! the very standards, is left out: it would hide a disagreement).
//!
//! * Polarized standard: `(P - p_table) / sqrt(sigma_P,stat^2 + sigma_p,table^2)`, flag
//!   `p_disagrees_with_table: X sigma` beyond 3; the angle residual
//!   `(gamma - gamma_table) / sqrt(sigma_gamma,stat^2 + sigma_gamma,table^2)`.
//! * Unpolarized standard: tested in (q, u), not with the Rice-biased P:
//!   `chi^2 = (q, u) C^-1 (q, u)^T`, `C = C_stat + (sigma_p,table^2 / 2) I` (2 dof), flag
//!   `qu_disagrees_with_table: chi2 = X (2 dof)` beyond 11.83 (the 3-sigma tail, p = 0.0027).
use sofipol_calib::Profile;

use super::FilterCalibration;
use crate::catalog::{Component, Flag, FlagCode};
use crate::solve::calibrated_obs;
use crate::standards::StandardStar;
use crate::stokes::calibration::{solve, Offset, StokesMethod};
use crate::stokes::inversion::{QuFit, WK_ANGLE_FACTOR_DEG};
use crate::stokes::model::normalize_axial_deg;

/// Residual in sigma beyond which a polarized standard's P disagrees with its table.
pub const P_DISAGREES_SIGMA: f64 = 3.0;

/// chi^2 (2 dof) beyond which an unpolarized standard's (q, u) disagrees with 0 (3 sigma).
pub const QU_DISAGREES_CHI2: f64 = 11.829;

/// Residuals of one standard against the table.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TableResiduals {
    /// (P - p_table) / combined error (polarized standards).
    pub p_sigma: Option<f64>,
    /// gamma - gamma_table folded into [-90, 90), deg (polarized standards).
    pub gamma_deg: Option<f64>,
    /// The angle residual in units of the combined error (polarized standards).
    pub gamma_sigma: Option<f64>,
    /// chi^2 of (q, u) against 0 (unpolarized standards, 2 dof).
    pub qu_chi2: Option<f64>,
    /// `p_disagrees_with_table: ...`, `qu_disagrees_with_table: ...`.
    pub flags: Vec<Flag>,
}

/// q, u of a calibrated standard with their statistical covariance only: the component's
/// orientations solved again with the calibration's offset (and telescope term) taken as
/// exact and the method the component was solved with.
fn statistical_fit(m: &Component, profile: &Profile, cal: Option<&FilterCalibration>) -> Option<QuFit> {
    let obs = calibrated_obs(m, profile, cal);
    let offset = cal.and_then(|c| c.offset).map(|o| Offset { c: o.c, sigma_c: 0.0 });
    let method = m
        .stokes_method
        .as_deref()
        .and_then(|s| s.parse().ok())
        .unwrap_or(StokesMethod::Auto);
    solve(&obs, method, offset)
        .or_else(|_| solve(&obs, StokesMethod::Auto, offset))
        .ok()
        .map(|s| s.fit)
}

/// The residuals of a measured standard against its table entry.
pub fn table_residuals(
    m: &Component,
    entry: &StandardStar,
    profile: &Profile,
    cal: Option<&FilterCalibration>,
) -> TableResiduals {
    let mut r = TableResiduals::default();
    let Some(fit) = statistical_fit(m, profile, cal) else {
        return r;
    };
    let (q, u) = (fit.q, fit.u);
    if entry.polarized() {
        let p = q.hypot(u);
        if !(p > 0.0) {
            return r;
        }
        let sigma_p = ((q * q * fit.var_q + u * u * fit.var_u + 2.0 * q * u * fit.cov_qu) / (p * p)).sqrt();
        let rp = (p - entry.p) / sigma_p.hypot(entry.sigma_p);
        let gamma = normalize_axial_deg(0.5 * u.atan2(q).to_degrees());
        let d = (gamma - entry.gamma_deg + 90.0).rem_euclid(180.0) - 90.0;
        let sigma_gamma = WK_ANGLE_FACTOR_DEG * sigma_p / p;
        r.p_sigma = Some(rp);
        r.gamma_deg = Some(d);
        r.gamma_sigma = Some(d / sigma_gamma.hypot(entry.sigma_gamma_deg));
        if rp.abs() > P_DISAGREES_SIGMA {
            r.flags.push(Flag::with_detail(
                FlagCode::PDisagreesWithTable,
                format!("{:.1} sigma", rp.abs()),
            ));
        }
    } else {
        let v = entry.sigma_p.powi(2) / 2.0;
        let (a, b, c) = (fit.var_q + v, fit.var_u + v, fit.cov_qu);
        let det = a * b - c * c;
        if !(det > 0.0) {
            return r;
        }
        let chi2 = (b * q * q - 2.0 * c * q * u + a * u * u) / det;
        r.qu_chi2 = Some(chi2);
        if chi2 > QU_DISAGREES_CHI2 {
            r.flags.push(Flag::with_detail(
                FlagCode::QuDisagreesWithTable,
                format!("chi2 = {chi2:.1} (2 dof)"),
            ));
        }
    }
    r
}
