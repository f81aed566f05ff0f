//! The checks `calibration.json` passes when it is read ([`super::Calibration::read`]): every
//! number the targets will be corrected with must be one the calibration could have written.
//!
//! | key | accepted |
//! |---|---|
//! | `filters[i].filter` | once: two entries for one filter are refused |
//! | `filters[i].offset.c` | finite, \|c\| <= 0.2 (the two beams' throughputs within a factor 1.5, instrumental polarization a few per cent) |
//! | `filters[i].offset.sigma_c` | finite, >= 0; equal to the square root of the covariance's c variance when both are given |
//! | `filters[i].angles.parity` | +1 or -1 |
//! | `filters[i].angles.theta0_deg` | finite, \|theta0\| <= 360 (normalised to [0, 180) on reading) |
//! | `filters[i].angles.sigma_theta0_deg` | finite, in [0, 90] |
//! | `filters[i].cov_c_theta0_deg` | finite, \|cov\| <= sigma_c sigma_theta0 (\|corr\| <= 1), only with both |
//! | `filters[i].telescope.p_tel` | finite, in [0, 0.1] (a bare aluminium mirror at 45 deg polarizes by a few per cent at most) |
//! | `filters[i].telescope.sigma_p_tel`, `sigma_psi_tel_deg` | finite, >= 0 (the angle's at most 90) |
//! | `filters[i].telescope.psi_tel_deg` | finite; with `a`, `b` consistent: `p_tel = hypot(a, b)`, `psi_tel = atan2(b, a)/2` |
//! | `filters[i].covariance` | finite, symmetric, diagonal >= 0, every \|correlation\| <= 1; its c and theta0 entries agree with `sigma_c`, `sigma_theta0_deg` and `cov_c_theta0_deg` |
//! | `filters[i].covariance_parameters` | the names c, theta0_deg, tel_a, tel_b, each once, in any order (the matrix is read by name) |
use super::Calibration;
pub use crate::error::CalibrationValueError;
use crate::stokes::model::normalize_axial_deg;

/// What the checks return: the first value refused.
type Checked<T> = std::result::Result<T, CalibrationValueError>;

/// A value outside what is accepted.
fn refused(key: impl Into<String>, value: impl Into<String>, reason: impl Into<String>) -> CalibrationValueError {
    CalibrationValueError::Refused {
        key: key.into(),
        value: value.into(),
        reason: reason.into(),
    }
}

/// A value that contradicts another of the file.
fn contradicts(key: impl Into<String>, value: impl Into<String>, conflict: impl Into<String>) -> CalibrationValueError {
    CalibrationValueError::Contradicts {
        key: key.into(),
        value: value.into(),
        conflict: conflict.into(),
    }
}

/// Largest |theta0| accepted before normalising (sofipol writes [0, 180); far beyond a
/// turn, the normalised value would carry no digits of the original).
const MAX_ABS_THETA0_DEG: f64 = 360.0;

/// Slack of the correlation bound for the rounding of the written numbers.
const CORR_SLACK: f64 = 1e-9;

/// Largest |c| accepted: c ~ (1 - k)/(1 + k) + p_inst, so 0.2 is a beam ratio k of 0.67
/// (or 1.5) with no instrumental polarization; SOFI's is 0.018.
pub const MAX_ABS_C: f64 = 0.2;

/// Largest telescope polarization accepted: Fresnel reflection on a bare aluminium mirror
/// at 45 deg gives a few per cent in the optical and less in the infrared.
pub const MAX_P_TEL: f64 = 0.1;

/// Relative agreement asked of an error written twice (as sigma and in the covariance):
/// both are written from one number, so only the printing's rounding separates them.
const TWICE_WRITTEN: f64 = 1e-6;

/// A number for a message, short (`1e300`, never 300 digits).
fn num(x: f64) -> String {
    sofipol_calib::text::short_number(x)
}

/// Whether `a` and `b` are one number written twice (relative [`TWICE_WRITTEN`], or both
/// below 1e-300).
fn same_number(a: f64, b: f64) -> bool {
    (a - b).abs() <= TWICE_WRITTEN * a.abs().max(b.abs()) || a.abs().max(b.abs()) < 1e-300
}

/// Check every filter's numbers; normalise theta0 into [0, 180). The error names the key path
/// (`filters[0].offset.c`), the value and what is accepted.
pub fn validate(cal: &mut Calibration) -> Checked<()> {
    for (i, f) in cal.filters.iter().enumerate() {
        if let Some(j) = cal.filters[..i].iter().position(|g| g.filter == f.filter) {
            return Err(refused(
                format!("filters[{i}].filter"),
                format!("{:?}", sofipol_calib::text::short_text(&f.filter, 40)),
                format!("the filter is also filters[{j}]; one entry per filter"),
            ));
        }
    }
    for (i, f) in cal.filters.iter_mut().enumerate() {
        let key = |k: &str| format!("filters[{i}].{k}");
        if let Some(o) = &f.offset {
            if !(o.c.is_finite() && o.c.abs() <= MAX_ABS_C) {
                return Err(refused(
                    key("offset.c"),
                    num(o.c),
                    format!(
                        "must be finite with |c| <= {MAX_ABS_C} (c ~ (1 - k)/(1 + k) + p_inst: \
                         a beam ratio k beyond 0.67-1.5 is no working polarimeter)"
                    ),
                ));
            }
            if !(o.sigma_c.is_finite() && o.sigma_c >= 0.0) {
                return Err(refused(
                    key("offset.sigma_c"),
                    num(o.sigma_c),
                    "must be finite and >= 0",
                ));
            }
        }
        if let Some(a) = f.angles.as_mut() {
            if a.parity != 1 && a.parity != -1 {
                return Err(refused(key("angles.parity"), a.parity.to_string(), "must be +1 or -1"));
            }
            if !(a.theta0_deg.is_finite() && a.theta0_deg.abs() <= MAX_ABS_THETA0_DEG) {
                return Err(refused(
                    key("angles.theta0_deg"),
                    num(a.theta0_deg),
                    format!("must be finite, within +-{MAX_ABS_THETA0_DEG} deg"),
                ));
            }
            if !(a.sigma_theta0_deg.is_finite() && (0.0..=90.0).contains(&a.sigma_theta0_deg)) {
                return Err(refused(
                    key("angles.sigma_theta0_deg"),
                    num(a.sigma_theta0_deg),
                    "must be finite, in [0, 90]",
                ));
            }
            a.theta0_deg = normalize_axial_deg(a.theta0_deg);
        }
        if let Some(cov) = f.cov_c_theta0_deg {
            let k = key("cov_c_theta0_deg");
            let cov_shown = num(cov);
            if !cov.is_finite() {
                return Err(refused(k, cov_shown, "must be finite"));
            }
            let (Some(o), Some(a)) = (&f.offset, &f.angles) else {
                return Err(refused(k, cov_shown, "given without both offset and angles"));
            };
            let bound = o.sigma_c * a.sigma_theta0_deg;
            if cov.abs() > bound * (1.0 + CORR_SLACK) {
                return Err(refused(
                    k,
                    cov_shown,
                    format!(
                        "|correlation| = {:.4} exceeds 1 (sigma_c {} x sigma_theta0_deg {})",
                        cov.abs() / bound,
                        o.sigma_c,
                        a.sigma_theta0_deg
                    ),
                ));
            }
        }
        if let Some(t) = &f.telescope {
            validate_telescope(t, &key)?;
        }
        if let Some(names) = &f.covariance_parameters {
            let order = parameter_order(names, &key("covariance_parameters"))?;
            if let Some(m) = f.covariance.as_mut() {
                let read = *m;
                for a in 0..4 {
                    for b in 0..4 {
                        m[order[a]][order[b]] = read[a][b];
                    }
                }
            }
            f.covariance_parameters = Some(CAL_PARAMETERS.iter().map(|s| s.to_string()).collect());
        }
        if let Some(m) = &f.covariance {
            validate_covariance(m, &key("covariance"))?;
            covariance_agrees(f, m, &key)?;
        }
    }
    Ok(())
}

use crate::stokes::propagation::{CAL_C, CAL_PARAMETERS, CAL_THETA0};

/// Where each written row of the covariance goes: `names` must hold each of
/// [`CAL_PARAMETERS`] once.
fn parameter_order(names: &[String], key: &str) -> Checked<[usize; 4]> {
    let expected = || format!("expected the names {} in any order", CAL_PARAMETERS.join(", "));
    if names.len() != CAL_PARAMETERS.len() {
        return Err(CalibrationValueError::NameCount {
            key: key.to_string(),
            count: names.len(),
            expected: expected(),
        });
    }
    let mut order = [0; 4];
    for (i, n) in names.iter().enumerate() {
        let Some(k) = CAL_PARAMETERS.iter().position(|p| p == n) else {
            return Err(refused(
                format!("{key}[{i}]"),
                format!("{:?}", sofipol_calib::text::short_text(n, 40)),
                format!("not a calibration parameter; {}", expected()),
            ));
        };
        if names[..i].contains(n) {
            return Err(contradicts(
                format!("{key}[{i}]"),
                format!("{n:?}"),
                format!("is named twice; {}", expected()),
            ));
        }
        order[i] = k;
    }
    Ok(order)
}

/// The errors written twice agree: `sigma_c`, `sigma_theta0_deg` and `cov_c_theta0_deg`
/// with the covariance's entries (a file edited in one place and not the other).
fn covariance_agrees(
    f: &super::FilterCalibration,
    m: &crate::stokes::propagation::CalibrationCovariance,
    key: &dyn Fn(&str) -> String,
) -> Checked<()> {
    let differ = |k: &str, v: f64, cov_key: &str, w: f64| {
        Err(contradicts(
            key(k),
            sofipol_calib::text::short_number(v),
            format!(
                "contradicts {} = {} (the same error written twice must agree)",
                key(cov_key),
                sofipol_calib::text::short_number(w)
            ),
        ))
    };
    if let Some(o) = &f.offset {
        let w = m[CAL_C][CAL_C].sqrt();
        if !same_number(o.sigma_c, w) {
            return differ(
                "offset.sigma_c",
                o.sigma_c,
                "covariance[c][c] (as a standard deviation)",
                w,
            );
        }
    }
    if let Some(a) = &f.angles {
        let w = m[CAL_THETA0][CAL_THETA0].sqrt();
        if !same_number(a.sigma_theta0_deg, w) {
            return differ(
                "angles.sigma_theta0_deg",
                a.sigma_theta0_deg,
                "covariance[theta0_deg][theta0_deg] (as a standard deviation)",
                w,
            );
        }
    }
    if let Some(cov) = f.cov_c_theta0_deg {
        let w = m[CAL_C][CAL_THETA0];
        if !same_number(cov, w) {
            return differ("cov_c_theta0_deg", cov, "covariance[c][theta0_deg]", w);
        }
    }
    Ok(())
}

/// The telescope's polarization: finite, plausible, its (a, b) consistent with (p, psi).
fn validate_telescope(t: &super::TelescopeCalibration, key: &dyn Fn(&str) -> String) -> Checked<()> {
    let check = |name: &str, v: f64, ok: bool, what: &str| {
        if v.is_finite() && ok {
            Ok(())
        } else {
            Err(refused(
                key(&format!("telescope.{name}")),
                num(v),
                format!("must be {what}"),
            ))
        }
    };
    check(
        "p_tel",
        t.p_tel,
        (0.0..=MAX_P_TEL).contains(&t.p_tel),
        "finite, in [0, 0.1] (a mirror at 45 deg polarizes by a few per cent at most)",
    )?;
    check("sigma_p_tel", t.sigma_p_tel, t.sigma_p_tel >= 0.0, "finite and >= 0")?;
    check("psi_tel_deg", t.psi_tel_deg, true, "finite")?;
    check(
        "sigma_psi_tel_deg",
        t.sigma_psi_tel_deg,
        (0.0..=90.0).contains(&t.sigma_psi_tel_deg),
        "finite, in [0, 90]",
    )?;
    check("a", t.a, t.a.abs() <= MAX_P_TEL, "finite, |a| <= 0.1")?;
    check("b", t.b, t.b.abs() <= MAX_P_TEL, "finite, |b| <= 0.1")?;
    let want = crate::stokes::model::TelescopePolarization {
        p_tel: t.p_tel,
        psi_tel_deg: t.psi_tel_deg,
    }
    .ab();
    if (want[0] - t.a).abs() > 1e-6 || (want[1] - t.b).abs() > 1e-6 {
        return Err(contradicts(
            key("telescope.(a, b)"),
            format!("({}, {})", t.a, t.b),
            format!(
                "disagrees with p_tel = {} and psi_tel_deg = {} (expected ({:.6}, {:.6}))",
                t.p_tel, t.psi_tel_deg, want[0], want[1]
            ),
        ));
    }
    Ok(())
}

/// A covariance matrix: finite, symmetric, non-negative variances, correlations within +-1.
fn validate_covariance(m: &crate::stokes::propagation::CalibrationCovariance, key: &str) -> Checked<()> {
    for i in 0..4 {
        for j in 0..4 {
            let v = m[i][j];
            if !v.is_finite() {
                return Err(refused(format!("{key}[{i}][{j}]"), num(v), "must be finite"));
            }
            if i == j && v < 0.0 {
                return Err(refused(format!("{key}[{i}][{i}]"), num(v), "a variance must be >= 0"));
            }
            if (v - m[j][i]).abs() > 1e-12 * v.abs().max(m[j][i].abs()).max(f64::MIN_POSITIVE) {
                return Err(contradicts(
                    format!("{key}[{i}][{j}]"),
                    num(v),
                    format!("differs from [{j}][{i}] = {}: must be symmetric", num(m[j][i])),
                ));
            }
            let bound = (m[i][i] * m[j][j]).max(0.0).sqrt();
            if i != j && v.abs() > bound * (1.0 + CORR_SLACK) {
                return Err(refused(format!("{key}[{i}][{j}]"), num(v), "|correlation| exceeds 1"));
            }
        }
    }
    Ok(())
}
