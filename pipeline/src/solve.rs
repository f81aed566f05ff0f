//! The one Stokes solve of a component: q, u, P, gamma, their errors, the cut and its
//! flags from the component's per-orientation F ([`resolve_component`]). Every q, u in a
//! catalog comes from here: first provisionally, as each target is measured
//! (`reduce::entry`, no calibration: what the target's status and its FITS products'
//! "before the night calibration" cards use), then with the night's calibration
//! (`calibration::calibrate_catalog`), which the catalog keeps. A correction of q, u goes
//! here, so both see it:
//!
//! ```text
//! per-orientation F (component.orientations)
//!   -> analyzer angles: the calibration's theta0 and parity, else the profile's
//!   -> the telescope's polarization removed from F (telescope.rs) when measured
//!   -> Stokes method (stokes::calibration::solve_with_fallback), offset c subtracted
//!   -> P, gamma and errors with the calibration's covariance (its Jacobian here)
//!   -> the cut and the flags (low_snr, uncalibrated, p_above_one, ...)
//! ```
use sofipol_calib::Profile;

use crate::catalog::polarimetric_calibration::FilterCalibration;
use crate::catalog::{CalibrationState, Component, Flag, FlagCode, InstrumentalOffset, TermSource};
use crate::stokes::calibration::{solve, solve_with_fallback, OrientationF, StokesMethod};
use crate::stokes::fresnel::TelescopePrior;
use crate::stokes::inversion::{Debias, LinearPolarization};
use crate::stokes::propagation::{
    self, calibration_covariance_of, rotation_gradient_per_deg, CalibrationCovariance, CalibrationJacobian,
    QuCovariance, CAL_C, CAL_TEL_A, CAL_TEL_B, CAL_THETA0,
};

pub mod telescope;

/// Whether a component's flags refuse it the cut whatever its P/sigma: a value from
/// dithers that were all flagged (saturated, bad pixels...; it may be far off), of a
/// component whose A/B identity is not established, or of a Stokes method that fell back
/// to a solve without offset correction.
pub fn refused_by_flags(flags: &[Flag]) -> bool {
    flags.iter().any(|f| {
        f.is(FlagCode::UsedFlaggedDithers)
            || f == &Flag::new(FlagCode::AbIdentityUnverified)
            || f.is_uncalibrated_fallback()
    })
}

/// Step of the central differences in theta0, deg.
const STEP_THETA0_DEG: f64 = 0.01;

/// Step of the central differences in the telescope's (a, b).
const STEP_TEL: f64 = 1e-4;

/// The rotator angle of an analyzer angle under the profile's relation (inverse of
/// phi = s POSANG + theta0).
fn posang_of(profile: &Profile, phi: f64) -> f64 {
    profile.angles.parity as f64 * (phi - profile.angles.zero_point_deg)
}

/// One usable orientation of a component: POSANG, F, sigma_F and the weighted mean
/// (cos 2eta, sin 2eta) of its frames' parallactic angles.
#[derive(Debug, Clone, Copy)]
pub(crate) struct OrientationRow {
    pub(crate) posang_deg: f64,
    pub(crate) f: f64,
    pub(crate) sigma_f: f64,
    pub(crate) parallactic_2eta: Option<[f64; 2]>,
}

/// The usable orientations of a measured component (its `orientations` field). An
/// orientation without a finite F, sigma_F or angle (JSON null) is left out.
pub(crate) fn orientation_rows(c: &Component, profile: &Profile) -> Vec<OrientationRow> {
    let finite = |v: f64| v.is_finite().then_some(v);
    c.orientations
        .iter()
        .flatten()
        .filter_map(|o| {
            let pa = o
                .posang_deg
                .and_then(finite)
                .or_else(|| finite(o.analyzer_deg).map(|phi| posang_of(profile, phi)))?;
            Some(OrientationRow {
                posang_deg: pa,
                f: finite(o.f)?,
                sigma_f: finite(o.sigma_f)?,
                parallactic_2eta: o.parallactic_2eta.filter(|v| v.iter().all(|x| x.is_finite())),
            })
        })
        .collect()
}

/// Per-orientation (POSANG, F, sigma_F) of a measured component (its `orientations` field).
/// An orientation without a finite F, sigma_F or angle (JSON null) is left out.
pub fn orientation_values(c: &Component, profile: &Profile) -> Vec<(f64, f64, f64)> {
    orientation_rows(c, profile)
        .into_iter()
        .map(|r| (r.posang_deg, r.f, r.sigma_f))
        .collect()
}

/// A component's orientations with the calibration's analyzer angles, the telescope's
/// polarization removed from F when the calibration measured it.
pub(crate) fn calibrated_obs(c: &Component, profile: &Profile, cal: Option<&FilterCalibration>) -> Vec<OrientationF> {
    let inputs = Inputs::new(c, profile, cal);
    inputs.obs(0.0, inputs.telescope())
}

/// What the solve does to one orientation of a component: its analyzer angle, and what it
/// takes from F before the Stokes method.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrientationCorrection {
    /// Rotator angle, deg.
    pub posang_deg: f64,
    /// Analyzer angle, deg: the calibration's relation when it has one, else the profile's.
    pub analyzer_deg: f64,
    /// The calibration's offset c (0 without one).
    pub offset: f64,
    /// The telescope's term removed, `T(phi)` (0 when the calibration removes none).
    pub telescope: f64,
}

/// Per usable orientation of `c` (its `orientations` with a finite F), the analyzer angle
/// and the offset and telescope term the solve takes from F under the calibration `cal`:
/// what turns a map of the orientation's normalised differences into the catalog's
/// calibrated q, u (the FITS Stokes maps).
pub fn orientation_corrections(
    c: &Component,
    profile: &Profile,
    cal: Option<&FilterCalibration>,
) -> Vec<OrientationCorrection> {
    let inputs = Inputs::new(c, profile, cal);
    let tel = inputs.telescope();
    let offset = cal.and_then(|f| f.offset).map_or(0.0, |o| o.c);
    inputs
        .rows
        .iter()
        .zip(inputs.obs(0.0, tel))
        .map(|(r, o)| OrientationCorrection {
            posang_deg: r.posang_deg,
            analyzer_deg: o.analyzer_deg,
            offset,
            telescope: r.f - o.f,
        })
        .collect()
}

/// Analyzer angle of a rotator angle: the calibration's relation when it has one, else the
/// profile's.
fn analyzer(cal: Option<&FilterCalibration>, profile: &Profile, posang: f64) -> f64 {
    match cal.and_then(|c| c.angles.as_ref()) {
        Some(a) => a.analyzer_deg(posang),
        None => profile.angles.analyzer_angle_deg(posang),
    }
}

/// A component's orientations under a calibration, with the calibration parameters
/// perturbed (for the Jacobian): theta0 shifted by `dtheta0`, the telescope's (a, b) =
/// `tel` removed (`None`: not removed).
struct Inputs<'a> {
    rows: Vec<OrientationRow>,
    cal: Option<&'a FilterCalibration>,
    profile: &'a Profile,
}

impl<'a> Inputs<'a> {
    fn new(c: &Component, profile: &'a Profile, cal: Option<&'a FilterCalibration>) -> Inputs<'a> {
        Inputs {
            rows: orientation_rows(c, profile),
            cal,
            profile,
        }
    }

    /// The telescope's (a, b) to remove: when the calibration measured it and every
    /// orientation has its frames' parallactic angle.
    fn telescope(&self) -> Option<[f64; 2]> {
        self.cal
            .and_then(|f| f.telescope.as_ref())
            .map(|t| t.ab())
            .filter(|_| self.rows.iter().all(|r| r.parallactic_2eta.is_some()))
    }

    fn obs(&self, dtheta0: f64, tel: Option<[f64; 2]>) -> Vec<OrientationF> {
        self.rows
            .iter()
            .map(|r| {
                let phi = analyzer(self.cal, self.profile, r.posang_deg) + dtheta0;
                let t = match (tel, r.parallactic_2eta) {
                    (Some(ab), Some(eta)) => telescope::telescope_f(ab, phi, eta),
                    _ => 0.0,
                };
                OrientationF {
                    analyzer_deg: phi,
                    f: r.f - t,
                    sigma_f: r.sigma_f,
                }
            })
            .collect()
    }

    /// (q, u) by `method` (no fallback) with the inputs perturbed.
    fn qu(&self, method: StokesMethod, dtheta0: f64, tel: Option<[f64; 2]>) -> Option<[f64; 2]> {
        let offset = self.cal.and_then(|c| c.offset);
        solve(&self.obs(dtheta0, tel), method, offset)
            .ok()
            .map(|s| [s.fit.q, s.fit.u])
            .filter(|v| v.iter().all(|x| x.is_finite()))
    }

    /// d(q, u)/d theta0 (per deg) and d(q, u)/d(a, b) by central differences of the same solve.
    fn jacobian(&self, method: StokesMethod, tel: Option<[f64; 2]>) -> (Option<[f64; 2]>, Option<[[f64; 2]; 2]>) {
        let diff = |p: Option<[f64; 2]>, m: Option<[f64; 2]>, h: f64| -> Option<[f64; 2]> {
            let (p, m) = (p?, m?);
            Some([(p[0] - m[0]) / (2.0 * h), (p[1] - m[1]) / (2.0 * h)])
        };
        // theta0 enters through cos and sin: the fourth-order central difference.
        let h = STEP_THETA0_DEG;
        let theta0 = (|| {
            let (p1, m1) = (self.qu(method, h, tel)?, self.qu(method, -h, tel)?);
            let (p2, m2) = (self.qu(method, 2.0 * h, tel)?, self.qu(method, -2.0 * h, tel)?);
            Some(std::array::from_fn(|i| {
                (8.0 * (p1[i] - m1[i]) - (p2[i] - m2[i])) / (12.0 * h)
            }))
        })();
        let tel_gradient = tel.and_then(|[a, b]| {
            let h = STEP_TEL;
            let ga = diff(
                self.qu(method, 0.0, Some([a + h, b])),
                self.qu(method, 0.0, Some([a - h, b])),
                h,
            )?;
            let gb = diff(
                self.qu(method, 0.0, Some([a, b + h])),
                self.qu(method, 0.0, Some([a, b - h])),
                h,
            )?;
            Some([ga, gb])
        });
        (theta0, tel_gradient)
    }
}

/// What one solve of a component works with besides the component.
#[derive(Debug, Clone, Copy)]
pub struct SolveSettings<'a> {
    /// The instrument profile (the analyzer angles without a calibration).
    pub profile: &'a Profile,
    /// The calibration of the component's filter, if any.
    pub cal: Option<&'a FilterCalibration>,
    /// The Stokes method asked for.
    pub method: StokesMethod,
    /// How P is debiased.
    pub debias: Debias,
    /// The cut in P/sigma.
    pub cut_snr: f64,
    /// The profile's mirror prior of the telescope's term in the component's filter: when
    /// the term is not removed, its mean square is carried in the error.
    pub telescope_prior: Option<TelescopePrior>,
    /// Whether the telescope polarizes at all (the profile's `telescope.polarizes`): when
    /// not, there is no term to remove, carry or flag.
    pub telescope_polarizes: bool,
}

/// The covariance of the calibration parameters (c, theta0, a, b) a component's errors take:
/// the calibration's, and where it removes no telescope term, the prior's mean square of
/// (a, b) about zero (the term left in the values, at its expected size). The same matrix
/// gives Delta-gamma's error, in which the term is common to the two stars.
pub fn calibration_errors(cal: Option<&FilterCalibration>, prior: Option<&TelescopePrior>) -> CalibrationCovariance {
    let mut m = cal.map(FilterCalibration::covariance_matrix).unwrap_or_default();
    if let (None, Some(p)) = (cal.and_then(|f| f.telescope.as_ref()), prior) {
        let s = p.second_moment();
        for (i, ci) in [CAL_TEL_A, CAL_TEL_B].into_iter().enumerate() {
            for (j, cj) in [CAL_TEL_A, CAL_TEL_B].into_iter().enumerate() {
                m[ci][cj] = s[i][j];
            }
            m[ci][CAL_C] = 0.0;
            m[CAL_C][ci] = 0.0;
            m[ci][CAL_THETA0] = 0.0;
            m[CAL_THETA0][ci] = 0.0;
        }
    }
    m
}

/// Re-solve one component's q, u from its per-orientation F with the calibration (offset,
/// zero-point, parity, the telescope's polarization) and the chosen method; P, gamma, errors,
/// the cut, the flags and the calibration state follow. Returns whether the result is
/// uncalibrated.
pub fn resolve_component(c: &mut Component, settings: &SolveSettings) -> bool {
    let SolveSettings {
        profile,
        cal,
        method,
        debias,
        cut_snr,
        telescope_prior,
        telescope_polarizes,
    } = *settings;
    let telescope_prior = telescope_prior.filter(|_| telescope_polarizes);
    let inputs = Inputs::new(c, profile, cal);
    if inputs.rows.is_empty() {
        return false;
    }
    // The flags this solve sets afresh.
    c.flags.retain(|f| {
        !matches!(
            f.code,
            FlagCode::Uncalibrated
                | FlagCode::LowSnr
                | FlagCode::TelescopeUncorrected
                | FlagCode::TelescopeFromPrior
                | FlagCode::TelescopeUnaccounted
                | FlagCode::StokesMethodFailed
        )
    });
    // The telescope's term is removed only when measured and every orientation has its
    // frames' parallactic angle.
    let tel = inputs.telescope();
    let offset = cal.and_then(|c| c.offset);
    let obs = inputs.obs(0.0, tel);
    let sol = match solve_with_fallback(&obs, method, offset) {
        Ok((s, fell_back)) => {
            c.flags
                .extend(fell_back.map(|why| Flag::with_detail(FlagCode::StokesMethodFailed, why)));
            s
        }
        Err(e) => {
            c.flags
                .push(Flag::with_detail(FlagCode::StokesMethodFailed, e.to_string()));
            c.passes_cut = false;
            return false;
        }
    };
    let (q, u) = (sol.fit.q, sol.fit.u);
    let stat = QuCovariance {
        var_q: sol.fit.var_q,
        var_u: sol.fit.var_u,
        cov_qu: sol.fit.cov_qu,
    };
    // What the calibration adds: J Sigma_cal J^T, J = d(q, u)/d(c, theta0, a, b). c enters
    // along the offset gradient when an offset was subtracted; theta0 (a rotation, measured
    // by re-solving) when the calibration has angles; the telescope's (a, b) when removed.
    // A telescope term not removed is carried at its expected size (the prior's mean
    // square), along the component's response to it: d(q, u)/d(a, b) at (a, b) = 0.
    let angles = cal.is_some_and(|f| f.angles.is_some());
    let carried = tel.is_none() && telescope_prior.is_some();
    let every_eta = inputs.rows.iter().all(|r| r.parallactic_2eta.is_some());
    let response_at = tel.or_else(|| (carried && every_eta).then_some([0.0, 0.0]));
    let (theta0_gradient, tel_gradient) = inputs.jacobian(sol.method, response_at);
    let mut jac: CalibrationJacobian = [[0.0; 2]; 4];
    jac[CAL_C] = sol.offset_gradient.unwrap_or([0.0, 0.0]);
    jac[CAL_THETA0] = theta0_gradient.unwrap_or_else(|| rotation_gradient_per_deg(q, u));
    if let Some([ga, gb]) = tel_gradient {
        (jac[CAL_TEL_A], jac[CAL_TEL_B]) = (ga, gb);
    }
    let mut sigma_cal = calibration_errors(cal, telescope_prior.as_ref());
    if sol.offset_gradient.is_none() {
        // No calibration offset subtracted (cancelled or fitted): its error does not enter.
        sigma_cal[CAL_C] = [0.0; 4];
        for row in sigma_cal.iter_mut() {
            row[CAL_C] = 0.0;
        }
    }
    let mut zero_point = calibration_covariance_of(&jac, &sigma_cal);
    if carried && tel_gradient.is_none() {
        // No response to the term (an orientation without a parallactic angle): it is of
        // unknown direction, its mean square shared by q and u.
        let s = telescope_prior.map_or([[0.0; 2]; 2], |p| p.second_moment());
        let half = 0.5 * (s[0][0] + s[1][1]);
        zero_point.var_q += half;
        zero_point.var_u += half;
    }
    let total = stat.plus(&zero_point);
    let lp = LinearPolarization::from_qu_cov(q, u, &total, debias);
    let calibrated = sol.offset_gradient.is_some() || angles || tel.is_some() || carried;
    c.pol = lp.pol;
    c.cov_qu = Some(total.cov_qu);
    c.cov_qu_stat = Some(stat.cov_qu);
    c.sigma_q_stat = Some(stat.var_q.max(0.0).sqrt());
    c.sigma_u_stat = Some(stat.var_u.max(0.0).sqrt());
    c.sigma_gamma_stat_deg = Some(propagation::sigma_gamma_deg(q, u, &stat));
    c.sigma_gamma_zero_point_deg = calibrated.then(|| propagation::sigma_gamma_deg(q, u, &zero_point));
    c.offset_gradient = sol.offset_gradient;
    c.zero_point_gradient = angles.then_some(jac[CAL_THETA0]);
    c.telescope_gradient = response_at.and(tel_gradient);
    c.telescope_qu = tel
        .and_then(|ab| {
            let etas: Vec<Option<[f64; 2]>> = inputs.rows.iter().map(|r| r.parallactic_2eta).collect();
            telescope::mean_removed(&obs, &etas, ab)
        })
        .map(|p| [p.q, p.u]);
    if !lp.passes_cut(cut_snr) {
        c.flags.push(Flag::new(FlagCode::LowSnr));
    }
    // A value from all-flagged dithers, or of a component whose A/B identity is not
    // established, never passes the cut.
    c.passes_cut = lp.passes_cut(cut_snr) && !refused_by_flags(&c.flags);
    // A degree of polarization above 1 is no light: a calibration or a measurement gone
    // wrong, never a detection.
    c.flags.retain(|f| !f.is(FlagCode::PAboveOne));
    if lp.pol.p > 1.0 {
        c.flags.push(Flag::new(FlagCode::PAboveOne));
        c.passes_cut = false;
    }
    if sol.uncalibrated {
        c.flags.push(Flag::new(FlagCode::Uncalibrated));
    }
    let mut state = calibration_state(&sol, cal, tel.is_some(), carried);
    if !telescope_polarizes && tel.is_none() {
        state.telescope = TermSource::Absent;
    }
    if tel.is_none() && telescope_polarizes {
        c.flags.push(Flag::new(FlagCode::TelescopeUncorrected));
    }
    match state.telescope {
        TermSource::Prior => c.flags.push(Flag::new(FlagCode::TelescopeFromPrior)),
        TermSource::Missing => c.flags.push(Flag::new(FlagCode::TelescopeUnaccounted)),
        _ => {}
    }
    c.calibration = Some(state);
    c.snr = Some(lp.snr);
    c.sigma_gamma_nkc_deg = Some(lp.sigma_gamma_nkc_deg);
    c.stokes_method = Some(sol.method.name().to_string());
    c.instrumental_offset = None;
    if let Some(o) = sol.offset {
        c.instrumental_offset = Some(InstrumentalOffset {
            c: o.c,
            sigma_c: o.sigma_c,
            source: if sol.method == StokesMethod::FreeOffset {
                "fitted"
            } else {
                "calibration"
            }
            .into(),
        });
    }
    sol.uncalibrated
}

/// What a solve calibrated, term by term: the offset (subtracted, fitted, cancelled by the
/// method, or missing), the zero-point (the standards', the profile's with its error, or
/// missing) and the telescope's term (removed as measured or as fitted with the prior,
/// carried at its expected size, or missing). A calibration read from another night is
/// marked so by its caller.
fn calibration_state(
    sol: &crate::stokes::calibration::StokesSolution,
    cal: Option<&FilterCalibration>,
    telescope_removed: bool,
    telescope_carried: bool,
) -> CalibrationState {
    let offset = if sol.uncalibrated {
        TermSource::Missing
    } else if sol.offset_gradient.is_some() {
        TermSource::Measured
    } else if sol.method == StokesMethod::FreeOffset {
        TermSource::Fitted
    } else {
        TermSource::Cancelled
    };
    let zero_point = match cal {
        Some(f) if f.angles.is_some() => TermSource::Measured,
        Some(f) if f.zero_point_from_profile.is_some() => TermSource::Prior,
        _ => TermSource::Missing,
    };
    let telescope = match (telescope_removed, telescope_carried) {
        (true, _) if cal.is_some_and(|f| f.telescope_from_prior.is_some()) => TermSource::Prior,
        (true, _) => TermSource::Measured,
        (false, true) => TermSource::Carried,
        (false, false) => TermSource::Missing,
    };
    CalibrationState {
        offset,
        telescope,
        zero_point,
    }
}
