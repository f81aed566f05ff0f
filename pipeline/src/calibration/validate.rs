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
//! | `filters[i].telescope.p_tel` | finite, in [0, 0.2] |
//! | `filters[i].telescope.sigma_p_tel`, `sigma_psi_tel_deg` | finite, >= 0 (the angle's at most 90) |
//! | `filters[i].telescope.psi_tel_deg` | finite; with `a`, `b` consistent: `p_tel = hypot(a, b)`, `psi_tel = atan2(b, a)/2` |
//! | `filters[i].covariance` | finite, symmetric, diagonal >= 0, every \|correlation\| <= 1 |
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
        if let Some(t) = &f.telescope {
            validate_telescope(t, &key)?;
        }
        if let Some(m) = &f.covariance {
            validate_covariance(m, &key("covariance"))?;
        }
    }
    Ok(())
}

/// The telescope's polarization: finite, plausible, its (a, b) consistent with (p, psi).
fn validate_telescope(t: &super::TelescopeCalibration, key: &dyn Fn(&str) -> String) -> Result<(), String> {
    let check = |name: &str, v: f64, ok: bool, what: &str| {
        if v.is_finite() && ok {
            Ok(())
        } else {
            Err(format!("{} = {v}: must be {what}", key(&format!("telescope.{name}"))))
        }
    };
    check("p_tel", t.p_tel, (0.0..=0.2).contains(&t.p_tel), "finite, in [0, 0.2]")?;
    check("sigma_p_tel", t.sigma_p_tel, t.sigma_p_tel >= 0.0, "finite and >= 0")?;
    check("psi_tel_deg", t.psi_tel_deg, true, "finite")?;
    check(
        "sigma_psi_tel_deg",
        t.sigma_psi_tel_deg,
        (0.0..=90.0).contains(&t.sigma_psi_tel_deg),
        "finite, in [0, 90]",
    )?;
    check("a", t.a, t.a.abs() <= 0.2, "finite, |a| <= 0.2")?;
    check("b", t.b, t.b.abs() <= 0.2, "finite, |b| <= 0.2")?;
    let want = crate::stokes::model::TelescopePolarization {
        p_tel: t.p_tel,
        psi_tel_deg: t.psi_tel_deg,
    }
    .ab();
    if (want[0] - t.a).abs() > 1e-6 || (want[1] - t.b).abs() > 1e-6 {
        return Err(format!(
            "{} = ({}, {}) disagrees with p_tel = {} and psi_tel_deg = {} (expected ({:.6}, {:.6}))",
            key("telescope.(a, b)"),
            t.a,
            t.b,
            t.p_tel,
            t.psi_tel_deg,
            want[0],
            want[1]
        ));
    }
    Ok(())
}

/// A covariance matrix: finite, symmetric, non-negative variances, correlations within +-1.
fn validate_covariance(m: &crate::stokes::propagation::CalibrationCovariance, key: &str) -> Result<(), String> {
    for i in 0..4 {
        for j in 0..4 {
            let v = m[i][j];
            if !v.is_finite() {
                return Err(format!("{key}[{i}][{j}] = {v}: must be finite"));
            }
            if i == j && v < 0.0 {
                return Err(format!("{key}[{i}][{i}] = {v}: a variance must be >= 0"));
            }
            if (v - m[j][i]).abs() > 1e-12 * v.abs().max(m[j][i].abs()).max(f64::MIN_POSITIVE) {
                return Err(format!(
                    "{key}[{i}][{j}] = {v} differs from [{j}][{i}] = {}: must be symmetric",
                    m[j][i]
                ));
            }
            let bound = (m[i][i] * m[j][j]).max(0.0).sqrt();
            if i != j && v.abs() > bound * (1.0 + CORR_SLACK) {
                return Err(format!("{key}[{i}][{j}] = {v}: |correlation| exceeds 1"));
            }
        }
    }
    Ok(())
}
