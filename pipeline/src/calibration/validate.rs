//! The checks `calibration.json` passes when it is read ([`super::Calibration::read`]): every
//! number the targets will be corrected with must be one the calibration could have written.
//!
//! | key | accepted |
//! |---|---|
//! | `filters[i].offset.c` | finite, \|c\| < 1 (F is a normalised difference) |
//! | `filters[i].offset.sigma_c` | finite, >= 0 |
//! | `filters[i].angles.parity` | +1 or -1 |
//! | `filters[i].angles.theta0_deg` | finite, \|theta0\| <= 360 (normalised to [0, 180) on reading) |
//! | `filters[i].angles.sigma_theta0_deg` | finite, in [0, 90] |
//! | `filters[i].cov_c_theta0_deg` | finite, \|cov\| <= sigma_c sigma_theta0 (\|corr\| <= 1), only with both |
use super::Calibration;
use crate::stokes::model::normalize_axial_deg;

/// Largest |theta0| accepted before normalising (sofipol writes [0, 180); far beyond a
/// turn, the normalised value would carry no digits of the original).
const MAX_ABS_THETA0_DEG: f64 = 360.0;

/// Slack of the correlation bound for the rounding of the written numbers.
const CORR_SLACK: f64 = 1e-9;

/// Check every filter's numbers; normalise theta0 into [0, 180). The error names the key path
/// (`filters[0].offset.c`), the value and what is accepted.
pub fn validate(cal: &mut Calibration) -> Result<(), String> {
    for (i, f) in cal.filters.iter_mut().enumerate() {
        let key = |k: &str| format!("filters[{i}].{k}");
        if let Some(o) = &f.offset {
            if !(o.c.is_finite() && o.c.abs() < 1.0) {
                return Err(format!("{} = {}: must be finite with |c| < 1", key("offset.c"), o.c));
            }
            if !(o.sigma_c.is_finite() && o.sigma_c >= 0.0) {
                return Err(format!(
                    "{} = {}: must be finite and >= 0",
                    key("offset.sigma_c"),
                    o.sigma_c
                ));
            }
        }
        if let Some(a) = f.angles.as_mut() {
            if a.parity != 1 && a.parity != -1 {
                return Err(format!("{} = {}: must be +1 or -1", key("angles.parity"), a.parity));
            }
            if !(a.theta0_deg.is_finite() && a.theta0_deg.abs() <= MAX_ABS_THETA0_DEG) {
                return Err(format!(
                    "{} = {}: must be finite, within +-{MAX_ABS_THETA0_DEG} deg",
                    key("angles.theta0_deg"),
                    a.theta0_deg
                ));
            }
            if !(a.sigma_theta0_deg.is_finite() && (0.0..=90.0).contains(&a.sigma_theta0_deg)) {
                return Err(format!(
                    "{} = {}: must be finite, in [0, 90]",
                    key("angles.sigma_theta0_deg"),
                    a.sigma_theta0_deg
                ));
            }
            a.theta0_deg = normalize_axial_deg(a.theta0_deg);
        }
        if let Some(cov) = f.cov_c_theta0_deg {
            let k = key("cov_c_theta0_deg");
            if !cov.is_finite() {
                return Err(format!("{k} = {cov}: must be finite"));
            }
            let (Some(o), Some(a)) = (&f.offset, &f.angles) else {
                return Err(format!("{k} = {cov}: given without both offset and angles"));
            };
            let bound = o.sigma_c * a.sigma_theta0_deg;
            if cov.abs() > bound * (1.0 + CORR_SLACK) {
                return Err(format!(
                    "{k} = {cov}: |correlation| = {:.4} exceeds 1 (sigma_c {} x sigma_theta0_deg {})",
                    cov.abs() / bound,
                    o.sigma_c,
                    a.sigma_theta0_deg
                ));
            }
        }
    }
    Ok(())
}
