//! Instrumental calibration of the Stokes solve: the offset `c`, the angle zero-point and
//! parity, and the four-orientation difference and ratio methods.
//!
//! The instrument adds to the normalised difference of every orientation a constant
//! (docs/polarimetry.md, docs/frame-format.md "Standard stars and the standards table"):
//!
//! ```text
//! F(phi) = q cos 2phi + u sin 2phi + c,   c ~ (1 - k)/(1 + k) + p_inst,   k = T_e/T_o
//! phi    = s * POSANG + theta0
//! ```
//!
//! * With a measured `c` (unpolarized standards), `F - c` goes into the least squares and the
//!   error of `c` is propagated: `(q, u)` are linear in `F`, so `c` moves them by the fit of
//!   an all-ones `F` times `c` ([`solve`]).
//! * Balanced angle sets (each analyzer angle has a partner 90 deg away) need no `c` at all:
//!   the difference method `G = (F(phi) - F(phi + 90))/2` cancels `c` to first order and the
//!   ratio method `G = tanh[(atanh F(phi) - atanh F(phi + 90))/2]` (which is
//!   `(R - 1)/(R + 1)` with `R^2 = (f_o/f_e)(phi) / (f_o/f_e)(phi + 90)`) cancels any beam
//!   ratio `k` exactly. `G = q cos 2phi + u sin 2phi` is then fitted over the pairs.
//! * Three or more distinct angles allow a free offset in the least squares.
//! * Standards: [`joint::fit_joint`] fits c and theta0 (and the parity) together over every
//!   orientation of every standard, with their covariance, and says when the standards
//!   cannot separate the two.
//! * A chosen method that cannot apply falls back to the automatic one
//!   ([`solve_with_fallback`]).
use serde::{Deserialize, Serialize};

use super::inversion::{fit_qu, QuFit};

/// How q and u are obtained from the per-orientation F.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(try_from = "String", into = "String")]
pub enum StokesMethod {
    /// Ratio method when the angles are balanced, else the least squares with the measured
    /// offset subtracted, else (3+ distinct angles) a free offset, else the plain least
    /// squares (flagged `uncalibrated`).
    #[default]
    Auto,
    /// Least squares of `F = q cos 2phi + u sin 2phi` (minus the calibration offset when
    /// there is one).
    LeastSquares,
    /// Least squares with a free offset term (3 or more distinct angles).
    FreeOffset,
    /// Difference method on pairs 90 deg apart.
    Difference,
    /// Ratio method on pairs 90 deg apart (cancels the beam ratio exactly).
    Ratio,
}

impl StokesMethod {
    /// snake_case name.
    pub fn name(self) -> &'static str {
        match self {
            StokesMethod::Auto => "auto",
            StokesMethod::LeastSquares => "least_squares",
            StokesMethod::FreeOffset => "free_offset",
            StokesMethod::Difference => "difference",
            StokesMethod::Ratio => "ratio",
        }
    }
}

/// The spellings of [`StokesMethod`], the same in TOML (`calibration.stokes_method`) and on
/// the command line (`--stokes-method`).
pub const STOKES_METHOD_SPELLINGS: &str = "auto, least_squares, free_offset, difference or ratio";

/// [`StokesMethod::name`]: the one spelling of TOML, JSON and the command line.
impl std::fmt::Display for StokesMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Parses what [`StokesMethod::name`] writes.
impl std::str::FromStr for StokesMethod {
    type Err = crate::error::SettingError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        use StokesMethod::*;
        [Auto, LeastSquares, FreeOffset, Difference, Ratio]
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| crate::error::SettingError {
                key: "calibration.stokes_method",
                value: format!("{s:?}"),
                allowed: STOKES_METHOD_SPELLINGS,
            })
    }
}

impl TryFrom<String> for StokesMethod {
    type Error = crate::error::SettingError;
    fn try_from(s: String) -> Result<Self, Self::Error> {
        s.parse()
    }
}

impl From<StokesMethod> for String {
    fn from(m: StokesMethod) -> String {
        m.name().to_string()
    }
}

/// The combined F of one orientation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OrientationF {
    /// Analyzer angle phi, deg.
    pub analyzer_deg: f64,
    /// F = (o - e)/(o + e), weighted mean over the dithers.
    pub f: f64,
    /// 1-sigma error of F.
    pub sigma_f: f64,
}

/// A measured instrumental offset of F.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Offset {
    /// c.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub c: f64,
    /// 1-sigma error of c.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_c: f64,
}

/// The result of the Stokes solve.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StokesSolution {
    /// q, u, their (co)variances and the chi^2.
    pub fit: QuFit,
    /// The method actually used.
    pub method: StokesMethod,
    /// The offset subtracted (calibration) or fitted (free offset), when any.
    pub offset: Option<Offset>,
    /// d(q, u)/dc when a calibration offset was subtracted: its error moves q and u along
    /// this vector. Not in `fit`, whose (co)variances are the measurement's alone.
    pub offset_gradient: Option<[f64; 2]>,
    /// Neither a calibration offset nor a method that cancels or fits it: q and u carry
    /// the instrumental offset.
    pub uncalibrated: bool,
}

fn key(phi: f64) -> i64 {
    (phi.rem_euclid(180.0) * 100.0).round() as i64 % 18000
}

/// Orientations merged by analyzer angle modulo 180 deg (weighted mean of F).
fn merged(obs: &[OrientationF]) -> Vec<OrientationF> {
    let mut out: Vec<(i64, f64, f64, f64)> = Vec::new(); // key, phi, sum w f, sum w
    for o in obs {
        if !(o.f.is_finite() && o.sigma_f.is_finite() && o.sigma_f > 0.0) {
            continue;
        }
        let w = o.sigma_f.powi(-2);
        let k = key(o.analyzer_deg);
        match out.iter_mut().find(|e| e.0 == k) {
            Some(e) => {
                e.2 += w * o.f;
                e.3 += w;
            }
            None => out.push((k, o.analyzer_deg, w * o.f, w)),
        }
    }
    out.sort_by_key(|e| e.0);
    out.into_iter()
        .map(|(_, phi, swf, sw)| OrientationF {
            analyzer_deg: phi,
            f: swf / sw,
            sigma_f: sw.recip().sqrt(),
        })
        .collect()
}

/// Pairs (phi, phi + 90) when every distinct angle has exactly one partner 90 deg away
/// (within 0.01 deg); `None` otherwise.
pub fn balanced_pairs(obs: &[OrientationF]) -> Option<Vec<(OrientationF, OrientationF)>> {
    let m = merged(obs);
    if m.len() < 4 || !m.len().is_multiple_of(2) {
        return None;
    }
    let mut pairs = Vec::new();
    for a in &m {
        let ka = key(a.analyzer_deg);
        if ka >= 9000 {
            continue;
        }
        let b = m.iter().find(|b| key(b.analyzer_deg) == ka + 9000)?;
        pairs.push((*a, *b));
    }
    (pairs.len() * 2 == m.len()).then_some(pairs)
}

/// Number of distinct analyzer angles modulo 180 deg.
pub fn distinct_angles(obs: &[OrientationF]) -> usize {
    merged(obs).len()
}

/// Ratio-method value of one pair and its error: `G = tanh[(atanh Fa - atanh Fb)/2]`.
pub fn ratio_pair(a: &OrientationF, b: &OrientationF) -> (f64, f64) {
    let g = (0.5 * (a.f.atanh() - b.f.atanh())).tanh();
    let da = 0.5 * (1.0 - g * g) / (1.0 - a.f * a.f);
    let db = 0.5 * (1.0 - g * g) / (1.0 - b.f * b.f);
    (g, ((da * a.sigma_f).powi(2) + (db * b.sigma_f).powi(2)).sqrt())
}

/// Difference-method value of one pair and its error: `G = (Fa - Fb)/2`.
pub fn difference_pair(a: &OrientationF, b: &OrientationF) -> (f64, f64) {
    (0.5 * (a.f - b.f), 0.5 * a.sigma_f.hypot(b.sigma_f))
}

/// Least squares of `F_i = q cos 2phi_i + u sin 2phi_i + c` with `c` free. `None` with fewer
/// than 3 distinct angles (mod 180) or a singular system. Orientations at the same angle are
/// merged first (weighted mean of F), so `chi2` has `distinct angles - 3` degrees of freedom;
/// [`fit_qu_offset_points`] fits the points one by one.
pub fn fit_qu_offset(obs: &[OrientationF]) -> Option<(QuFit, Offset)> {
    fit_qu_offset_points(&merged(obs)).map(|f| (f.fit, f.offset))
}

/// [`fit_qu_offset_points`]: q, u, c with their full 3 x 3 covariance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OffsetFit {
    /// q, u, Var(q), Var(u), Cov(q, u) and the chi^2 over every point.
    pub fit: QuFit,
    /// c and its 1-sigma error.
    pub offset: Offset,
    /// Covariance of (q, u, c), in that order.
    pub cov: [[f64; 3]; 3],
    /// Points used (finite F, finite positive error).
    pub n: usize,
}

impl OffsetFit {
    /// Degrees of freedom of `fit.chi2`: points used minus 3.
    pub fn dof(&self) -> usize {
        self.n.saturating_sub(3)
    }
}

/// Weighted least squares of `F_i = q cos 2phi_i + u sin 2phi_i + c` over every point as
/// given (no merging of equal angles: repeated angles add degrees of freedom to chi^2).
/// Points with a non-finite F or a non-finite or non-positive error are skipped. `None` with
/// fewer than 3 distinct angles (mod 180, 0.01 deg) among the usable points, or a singular
/// system.
pub fn fit_qu_offset_points(obs: &[OrientationF]) -> Option<OffsetFit> {
    let usable: Vec<&OrientationF> = obs
        .iter()
        .filter(|o| o.f.is_finite() && o.sigma_f.is_finite() && o.sigma_f > 0.0 && o.analyzer_deg.is_finite())
        .collect();
    let mut keys: Vec<i64> = usable.iter().map(|o| key(o.analyzer_deg)).collect();
    keys.sort_unstable();
    keys.dedup();
    if keys.len() < 3 {
        return None;
    }
    // Normal equations for (q, u, c).
    let mut a = [[0.0f64; 3]; 3];
    let mut y = [0.0f64; 3];
    for o in &usable {
        let w = o.sigma_f.powi(-2);
        let t = 2.0 * o.analyzer_deg.to_radians();
        let x = [t.cos(), t.sin(), 1.0];
        for i in 0..3 {
            y[i] += w * x[i] * o.f;
            for j in 0..3 {
                a[i][j] += w * x[i] * x[j];
            }
        }
    }
    let inv = invert3(&a)?;
    let p: Vec<f64> = (0..3).map(|i| (0..3).map(|j| inv[i][j] * y[j]).sum()).collect();
    let chi2 = usable
        .iter()
        .map(|o| {
            let t = 2.0 * o.analyzer_deg.to_radians();
            ((o.f - p[0] * t.cos() - p[1] * t.sin() - p[2]) / o.sigma_f).powi(2)
        })
        .sum();
    Some(OffsetFit {
        fit: QuFit {
            q: p[0],
            u: p[1],
            var_q: inv[0][0],
            var_u: inv[1][1],
            cov_qu: inv[0][1],
            chi2,
        },
        offset: Offset {
            c: p[2],
            sigma_c: inv[2][2].sqrt(),
        },
        cov: inv,
        n: usable.len(),
    })
}

fn invert3(a: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let det = a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]);
    let scale = a.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
    if !(det.abs() > 1e-10 * scale.powi(3)) {
        return None;
    }
    let mut inv = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let (r0, r1) = ([1, 0, 0][j], [2, 2, 1][j]);
            let (c0, c1) = ([1, 0, 0][i], [2, 2, 1][i]);
            let minor = a[r0][c0] * a[r1][c1] - a[r0][c1] * a[r1][c0];
            inv[i][j] = if (i + j) % 2 == 0 { minor } else { -minor } / det;
        }
    }
    Some(inv)
}

/// Least squares of `F - c`: the fit (with the measurement's (co)variances only) and
/// `d(q, u)/dc`, the gradient along which the error of `c` moves q and u. (q, u) are
/// linear in F, so a common shift of every F by dc moves them by minus the fit of an
/// all-ones F, times dc.
pub fn fit_qu_calibrated(obs: &[OrientationF], offset: Offset) -> Option<(QuFit, [f64; 2])> {
    let m = merged(obs);
    let phis: Vec<f64> = m.iter().map(|o| o.analyzer_deg).collect();
    let fs: Vec<f64> = m.iter().map(|o| o.f - offset.c).collect();
    let ss: Vec<f64> = m.iter().map(|o| o.sigma_f).collect();
    let r = fit_qu(&phis, &fs, &ss)?;
    let one = fit_qu(&phis, &vec![1.0; phis.len()], &ss)?;
    Some((r, [-one.q, -one.u]))
}

impl StokesSolution {
    /// The fit with the error of a subtracted calibration offset added to its (co)variances.
    pub fn fit_with_offset_error(&self) -> QuFit {
        let mut r = self.fit;
        if let (Some(d), Some(o)) = (self.offset_gradient, self.offset) {
            let v = o.sigma_c * o.sigma_c;
            r.var_q += d[0] * d[0] * v;
            r.var_u += d[1] * d[1] * v;
            r.cov_qu += d[0] * d[1] * v;
        }
        r
    }
}

/// Solve for q, u with the chosen method (see [`StokesMethod::Auto`] for the automatic
/// choice). `offset`: the calibration's instrumental offset, when there is one. Errors say
/// why the method cannot be used with these angles.
pub fn solve(
    obs: &[OrientationF],
    method: StokesMethod,
    offset: Option<Offset>,
) -> crate::error::Result<StokesSolution> {
    let pairs = balanced_pairs(obs);
    let n = distinct_angles(obs);
    let method = match method {
        StokesMethod::Auto => {
            if pairs.is_some() {
                StokesMethod::Ratio
            } else if offset.is_some() {
                StokesMethod::LeastSquares
            } else if n >= 3 {
                StokesMethod::FreeOffset
            } else {
                StokesMethod::LeastSquares
            }
        }
        m => m,
    };
    let err = |reason: String| crate::error::Error::StokesMethod { reason };
    let undefined = || err("orientations do not constrain q and u".to_string());
    match method {
        StokesMethod::Ratio | StokesMethod::Difference => {
            let pairs = pairs.ok_or_else(|| {
                err(format!(
                    "the {} method needs balanced orientations (pairs 90 deg apart); {n} distinct analyzer angle(s)",
                    method.name()
                ))
            })?;
            let (mut phis, mut gs, mut ss) = (Vec::new(), Vec::new(), Vec::new());
            for (a, b) in &pairs {
                let (g, s) = if method == StokesMethod::Ratio {
                    ratio_pair(a, b)
                } else {
                    difference_pair(a, b)
                };
                phis.push(a.analyzer_deg);
                gs.push(g);
                ss.push(s);
            }
            let fit = fit_qu(&phis, &gs, &ss).ok_or_else(undefined)?;
            Ok(StokesSolution {
                fit,
                method,
                offset: None,
                offset_gradient: None,
                uncalibrated: false,
            })
        }
        StokesMethod::FreeOffset => {
            let (fit, off) = fit_qu_offset(obs).ok_or_else(|| {
                err(format!(
                    "a free offset needs 3 or more distinct analyzer angles; {n} present"
                ))
            })?;
            Ok(StokesSolution {
                fit,
                method,
                offset: Some(off),
                offset_gradient: None,
                uncalibrated: false,
            })
        }
        StokesMethod::LeastSquares | StokesMethod::Auto => match offset {
            Some(off) => {
                let (fit, gradient) = fit_qu_calibrated(obs, off).ok_or_else(undefined)?;
                Ok(StokesSolution {
                    fit,
                    method: StokesMethod::LeastSquares,
                    offset: Some(off),
                    offset_gradient: Some(gradient),
                    uncalibrated: false,
                })
            }
            None => {
                let m = merged(obs);
                let phis: Vec<f64> = m.iter().map(|o| o.analyzer_deg).collect();
                let fs: Vec<f64> = m.iter().map(|o| o.f).collect();
                let ss: Vec<f64> = m.iter().map(|o| o.sigma_f).collect();
                Ok(StokesSolution {
                    fit: fit_qu(&phis, &fs, &ss).ok_or_else(undefined)?,
                    method: StokesMethod::LeastSquares,
                    offset: None,
                    offset_gradient: None,
                    uncalibrated: pairs.is_none(),
                })
            }
        },
    }
}

/// The end of that flag when the automatic fallback carries no offset correction: such a
/// component never passes the cut (`Flag::refuses_cut` of the catalog's flags).
pub const FALLBACK_UNCALIBRATED: &str = "(uncalibrated)";

/// The chosen method when it applies; otherwise the automatic choice
/// ([`StokesMethod::Auto`]) and why, the detail of the component's `stokes_method_failed`
/// flag: `<reason>; fell back to <method>` (ending in ` (uncalibrated)` when the fallback
/// corrects no offset). An error only when the automatic choice fails too (the
/// orientations do not constrain q and u).
pub fn solve_with_fallback(
    obs: &[OrientationF],
    method: StokesMethod,
    offset: Option<Offset>,
) -> crate::error::Result<(StokesSolution, Option<String>)> {
    match solve(obs, method, offset) {
        Ok(s) => Ok((s, None)),
        Err(e) if method != StokesMethod::Auto => {
            let s = solve(obs, StokesMethod::Auto, offset)?;
            let unc = if s.uncalibrated {
                format!(" {FALLBACK_UNCALIBRATED}")
            } else {
                String::new()
            };
            Ok((s, Some(format!("{e}; fell back to {}{unc}", s.method))))
        }
        Err(e) => Err(e),
    }
}

/// A standard as the calibration sees it: its per-orientation F at the rotator angles, and
/// its table polarization (sky frame; p = 0 for unpolarized standards).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StandardObservation {
    /// Name (as matched in the standards table).
    pub name: String,
    /// Rotator position angles, deg, one per orientation.
    pub posang_deg: Vec<f64>,
    /// F and its error per orientation (the analyzer angle field is ignored: angles come
    /// from `posang_deg` and the parity and zero-point being tried).
    pub f: Vec<OrientationF>,
    /// Table degree of polarization (fraction).
    pub p: f64,
    /// Its error.
    pub sigma_p: f64,
    /// Table angle, deg east of north.
    pub gamma_deg: f64,
    /// Its error, deg.
    pub sigma_gamma_deg: f64,
    /// Per orientation, the weighted mean (cos 2eta, sin 2eta) of its frames' parallactic
    /// angles (`None` or absent: unknown; the telescope's polarization is then not fitted).
    #[serde(default)]
    pub parallactic_2eta: Vec<Option<[f64; 2]>>,
}

impl StandardObservation {
    /// Whether the table calls it polarized (p > 3 sigma_p and p > 0).
    pub fn polarized(&self) -> bool {
        self.p > 0.0 && self.p > 3.0 * self.sigma_p
    }
}

/// Angle zero-point and parity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AngleCalibration {
    /// theta0, deg in [0, 180).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub theta0_deg: f64,
    /// Its 1-sigma error, deg.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_theta0_deg: f64,
    /// Image parity s (+1 or -1).
    pub parity: i32,
    /// Whether the parity was measured (2+ polarized standards with different angles)
    /// rather than taken from the profile.
    pub parity_measured: bool,
    /// Polarized standards used.
    pub n_standards: usize,
}

impl AngleCalibration {
    /// Analyzer angle of a rotator position angle.
    pub fn analyzer_deg(&self, posang_deg: f64) -> f64 {
        self.parity as f64 * posang_deg + self.theta0_deg
    }
}

pub mod joint;

#[cfg(test)]
mod tests;
